"""Order-2 real spherical harmonics (SH) of environment maps, and the diffuse irradiance they give.

Basis (:func:`sh_basis`): the 9 real SH ``Y_lm`` of bands l = 0, 1, 2, rows ordered
``(0,0), (1,-1), (1,0), (1,1), (2,-2), (2,-1), (2,0), (2,1), (2,2)`` with the standard constants
(Ramamoorthi & Hanrahan 2001, "An efficient representation for irradiance environment maps")::

    Y00 = 0.282095
    Y1-1 = 0.488603 y    Y10 = 0.488603 z    Y11 = 0.488603 x
    Y2-2 = 1.092548 xy   Y2-1 = 1.092548 yz  Y20 = 0.315392 (3 z^2 - 1)
    Y21 = 1.092548 xz    Y22 = 0.546274 (x^2 - y^2)

Coefficients (:func:`project_environment`) are ``c_i = sum_texels L(d) Y_i(R d) dOmega`` for an
equirectangular map in the pipeline's convention (stages.numerics.sg: row 0 is the zenith +y, texel
direction ``(sin t sin p, cos t, -sin t cos p)``) and ``R = frame_from_world`` (identity: the map's own
frame; a camera's rotation: the camera frame), so ``L(w) ~ sum_i c_i Y_i(w)`` with ``w`` in that frame.
These are the coefficients of the ``relight_examples`` manifest's ``sh_camera_json`` / ``sh_world_json``.

Irradiance (:func:`sh_irradiance`): ``E(n) = sum_lm A_l c_lm Y_lm(n)`` with the clamped-cosine factors
``A0 = pi, A1 = 2 pi / 3, A2 = pi / 4``; a constant environment of radiance ``c`` gives ``E = pi c`` and a
white Lambertian surface then has radiance ``albedo / pi * E = c``. Order 2 keeps the clamped cosine's
convolution to within about 3% RMS (Ramamoorthi & Hanrahan), so shading from these coefficients is the
smooth, low-frequency part of the environment's lighting.
"""
from __future__ import annotations

import math

import numpy as np

from .sg import equirect_directions, equirect_solid_angles, resize_environment
from .sg import rotation_y as _rotation_y_rad

__all__ = ["SH_COEFFICIENTS", "SH_BAND_FACTORS", "MAX_PROJECTION_ROWS", "sh_basis", "project_environment",
           "sh_irradiance", "rotation_y"]

SH_COEFFICIENTS = 9
"""Coefficients of an order-2 (bands 0-2) real SH expansion."""
SH_BAND_FACTORS = np.array([math.pi] + [2.0 * math.pi / 3.0] * 3 + [math.pi / 4.0] * 5)
"""(9,) clamped-cosine convolution factor A_l of every coefficient (Ramamoorthi & Hanrahan)."""
MAX_PROJECTION_ROWS = 64
"""Rows an environment is area-downsampled to (at most) before projection: order-2 SH see only the
lowest frequencies, and a 64 x 128 map projects in about a millisecond; the downsampling keeps the
map's energy (solid-angle weighted), so the coefficients change by well under 1% against full size."""


def sh_basis(directions: np.ndarray) -> np.ndarray:
    """Real SH basis (N, 9) float64 of unit directions (N, 3) (module docstring for order and constants)."""
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must be (N, 3), got shape {d.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError("directions hold NaN or Inf")
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    out = np.empty((len(d), SH_COEFFICIENTS), np.float64)
    out[:, 0] = 0.282095
    out[:, 1] = 0.488603 * y
    out[:, 2] = 0.488603 * z
    out[:, 3] = 0.488603 * x
    out[:, 4] = 1.092548 * x * y
    out[:, 5] = 1.092548 * y * z
    out[:, 6] = 0.315392 * (3.0 * z * z - 1.0)
    out[:, 7] = 1.092548 * x * z
    out[:, 8] = 0.546274 * (x * x - y * y)
    return out


def _check_rotation(rotation: np.ndarray, name: str) -> np.ndarray:
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise ValueError(f"{name} must be a finite (3, 3) rotation, got shape {r.shape}")
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-4) or np.linalg.det(r) < 0:
        raise ValueError(f"{name} is not a rotation (R R^T != I or det < 0)")
    return r


def project_environment(env: np.ndarray, frame_from_world: np.ndarray | None = None) -> np.ndarray:
    """Order-2 SH coefficients (9, 3) float64 of an equirectangular map (H, W, 3) of linear radiance,
    expressed in the frame ``frame_from_world`` (3, 3) rotates world directions into (None: identity).

    Maps taller than :data:`MAX_PROJECTION_ROWS` are area-downsampled first (energy kept)."""
    env = np.asarray(env)
    if env.ndim != 3 or env.shape[2] != 3 or env.shape[0] < 1 or env.shape[1] < 1:
        raise ValueError(f"environment map must be (H, W, 3) equirectangular RGB, got shape {env.shape}")
    if not np.issubdtype(env.dtype, np.floating):
        raise ValueError(f"environment map must be float linear radiance, got dtype {env.dtype}")
    if not np.all(np.isfinite(env)):
        raise ValueError("environment map holds NaN or Inf")
    if np.any(env < 0):
        raise ValueError("environment map holds negative radiance")
    rotation = np.eye(3) if frame_from_world is None else _check_rotation(frame_from_world, "frame_from_world")
    if env.shape[0] > MAX_PROJECTION_ROWS:
        env = resize_environment(env, MAX_PROJECTION_ROWS, 2 * MAX_PROJECTION_ROWS)
    h, w = env.shape[:2]
    directions = equirect_directions(h, w).reshape(-1, 3).astype(np.float64) @ rotation.T
    # renormalise: the float32 texel directions and the rotation leave |d| a few ulp off 1
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    weights = equirect_solid_angles(h, w).reshape(-1).astype(np.float64)
    radiance = env.reshape(-1, 3).astype(np.float64)
    return sh_basis(directions).T @ (radiance * weights[:, None])


def sh_irradiance(normals: np.ndarray, coeffs: np.ndarray) -> np.ndarray:
    """Diffuse irradiance (N, 3) float64 at unit normals (N, 3) under SH radiance coefficients (9, 3) given
    in the normals' frame: ``E(n) = sum_i A_l(i) c_i Y_i(n)``, clamped at 0 (the order-2 fit of a very
    peaked environment can ring slightly negative on the side facing away from it)."""
    c = np.asarray(coeffs, dtype=np.float64)
    if c.shape != (SH_COEFFICIENTS, 3):
        raise ValueError(f"SH coefficients must be (9, 3), got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("SH coefficients hold NaN or Inf")
    basis = sh_basis(normals)
    return np.maximum(basis @ (c * SH_BAND_FACTORS[:, None]), 0.0)


def rotation_y(angle_deg: float) -> np.ndarray:
    """Right-handed rotation (3, 3) about +y by ``angle_deg`` degrees (+x turns towards -z; the
    ``relight_examples`` manifest's ``environment_rotation_deg``: world direction = R_y(angle) x map
    direction)."""
    if not math.isfinite(angle_deg):
        raise ValueError(f"rotation angle must be finite, got {angle_deg}")
    return _rotation_y_rad(math.radians(angle_deg))
