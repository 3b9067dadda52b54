"""Photometric normals with the specular reflection modelled out of the gradient ratio.

Eq. 1 of the seed paper (``d = (g+ - g-) / (g+ + g-)``, ``n = d / |d|``) is exact for a Lambertian surface.
Skin and cloth also reflect specularly, and under the gradients the specular lobe points the ratio towards
the *reflection* of the view direction, not the normal: on the default simulated capture the specular
reflection alone costs 5.8 deg of the unoccluded pixels' error before the sensor (7.5 deg with it, 1.7 deg
without; ``bench/bench_normal_error_sources.py``) and up to 28 deg on shiny leather.

This module fits, per pixel, the normal ``n`` and the diffuse albedo ``rho`` (RGB) that explain the
pixel's g+ and g- values as Lambertian plus GGX reflection under the stage's linear illuminations
(:func:`stages.numerics.materials.shade_stage_illuminations`, exact GGX moments, no occlusion), for a
*given* roughness and Fresnel F0 (a prior: one pixel's six values cannot also pin the roughness down;
see the bench for what a per-pixel choice does). For a fixed ``n`` the albedo is linear and solved in
closed form per channel, so the optimisation is over the normal only, from the Lambertian normal; where
that explains the pixel badly, also from the half-way vector between it and the view, which is where a
mirror-like pixel's normal lies; the lower residual wins.

**Solver.** Levenberg-Marquardt in the tangent plane of the current normal (two parameters per pixel, the
Jacobian of the six residuals by forward differences, a 2 x 2 solve, steps of at most 0.5 rad, the damping
per pixel), or Adam on an unnormalised 3-vector. On the default capture 6 Levenberg-Marquardt steps reach
the error against the simulator's normals that 40 Adam steps do, in about a third of the time; more steps
do not lower it.

Conventions of docs/CONTRACTS.md: stage frame, OpenCV cameras ``x_cam = R x_world + t``, images
``(H, W, 3)`` float32; radiance in white units (decoded value / ``white_reference``). Pure numerics:
arrays in, arrays out. No output holds NaN or Inf.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from pipeline.config import Documented, checked
from artifacts.camera import Camera
from stages.numerics.photometric import corrected_normals

__all__ = ["SOLVERS", "SpecularConfig", "SpecularFit", "view_directions", "fit_diffuse_normals", "white_light_specular",
           "specular_free_normals"]

SOLVERS = ("levenberg_marquardt", "adam")


@dataclass(frozen=True, eq=False)
class SpecularFit:
    """Result of :func:`fit_diffuse_normals`, all ``(H, W[, 3])`` float32, 0 outside ``pixels``.

    Attributes:
        normals: unit stage-frame normals of the fit.
        albedo: the diffuse albedo of the fit (white units, >= 0).
        specular_pos, specular_neg: the fitted specular reflection under g+ and g- in *decoded* units (so
            ``pos - specular_pos`` is the Lambertian part of the frame).
        specular_full: the fitted specular reflection under the white light, decoded units.
        residual: the fit's squared residual relative to the squared signal ``(sum g+ + g-)^2``.
    """

    normals: np.ndarray
    albedo: np.ndarray
    specular_pos: np.ndarray
    specular_neg: np.ndarray
    specular_full: np.ndarray
    residual: np.ndarray


def view_directions(K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, 3) float32 unit stage-frame directions from the surface seen at each pixel towards the camera
    (the pixel's ray reversed; lens distortion is ignored, which moves them by far less than a degree):
    :meth:`artifacts.camera.Camera.view_directions`.

    K: (3, 3) intrinsics. cam_from_world: (3, 4) or (4, 4) ``[R | t]``."""
    from artifacts.camera import Camera

    return Camera(K, cam_from_world, width, height).view_directions()


def _specular_only(n: torch.Tensor, views: torch.Tensor, roughness: torch.Tensor, f0: float) -> torch.Tensor:
    """(N, 3 illum (full_on, pos, neg), 3 rgb) GGX reflection in white units (exact moments table)."""
    from stages.numerics.materials import shade_stage_illuminations

    return shade_stage_illuminations(n, views, torch.zeros_like(n), roughness, f0=f0, specular_model="ggx_table")


def _fit_chunk(obs: torch.Tensor, views: torch.Tensor, init: torch.Tensor, roughness: torch.Tensor, f0: float,
               solver: str, steps: int, lr: float,
               retry_residual: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """obs (N, 2, 3) g+/g- in white units -> normals (N, 3), albedo (N, 3), relative residual (N,)."""
    scale = obs.sum((1, 2)).square().clamp_min(1e-12)

    def residuals_of(n: torch.Tensor, sub) -> tuple[torch.Tensor, torch.Tensor]:
        """The six residuals (N, 6) of unit normals ``n`` relative to the signal, and the albedo (N, 3)."""
        spec = _specular_only(n, sub(views), sub(roughness), f0)[:, 1:]  # (N, 2 illum, 3 rgb)
        a_pos, a_neg = 0.5 + n / 3.0, 0.5 - n / 3.0  # Lambertian g+/g- per unit albedo (unoccluded)
        o = sub(obs)
        y_pos, y_neg = o[:, 0] - spec[:, 0], o[:, 1] - spec[:, 1]
        albedo = ((y_pos * a_pos + y_neg * a_neg) / (a_pos.square() + a_neg.square())).clamp_min(0.0)
        res = torch.cat([albedo * a_pos - y_pos, albedo * a_neg - y_neg], -1) / sub(scale).sqrt()[:, None]
        return res, albedo

    def adam(start: torch.Tensor, sub):
        x = start.clone().requires_grad_(True)
        optimiser = torch.optim.Adam([x], lr=lr)
        for _ in range(steps):
            res, _ = residuals_of(torch.nn.functional.normalize(x, dim=-1), sub)
            optimiser.zero_grad()
            res.square().sum().backward()
            optimiser.step()
        with torch.no_grad():
            n = torch.nn.functional.normalize(x, dim=-1)
            res, albedo = residuals_of(n, sub)
        return n, albedo, res.square().sum(-1)

    @torch.no_grad()
    def levenberg_marquardt(start: torch.Tensor, sub, eps: float = 1e-3, max_step: float = 0.5):
        n = torch.nn.functional.normalize(start, dim=-1)
        res, albedo = residuals_of(n, sub)
        cost = torch.nan_to_num(res.square().sum(-1), nan=np.inf)
        damping = torch.full_like(cost, 1e-2)
        x_axis = n.new_tensor([1.0, 0.0, 0.0])
        y_axis = n.new_tensor([0.0, 1.0, 0.0])
        for _ in range(steps):
            t1 = torch.nn.functional.normalize(
                torch.cross(n, torch.where(n[:, :1].abs() < 0.9, x_axis, y_axis), dim=-1), dim=-1)
            t2 = torch.cross(n, t1, dim=-1)
            j1 = (residuals_of(torch.nn.functional.normalize(n + eps * t1, dim=-1), sub)[0] - res) / eps
            j2 = (residuals_of(torch.nn.functional.normalize(n + eps * t2, dim=-1), sub)[0] - res) / eps
            a11, a12, a22 = (j1 * j1).sum(-1), (j1 * j2).sum(-1), (j2 * j2).sum(-1)
            g1, g2 = (j1 * res).sum(-1), (j2 * res).sum(-1)
            d11, d22 = a11 * (1.0 + damping) + 1e-12, a22 * (1.0 + damping) + 1e-12
            det = d11 * d22 - a12 * a12
            det = torch.where(det.abs() > 1e-20, det, torch.full_like(det, 1e-20))
            s1, s2 = -(d22 * g1 - a12 * g2) / det, (a12 * g1 - d11 * g2) / det
            shrink = (max_step / torch.sqrt(s1 * s1 + s2 * s2).clamp_min(1e-12)).clamp(max=1.0)
            trial = torch.nn.functional.normalize(n + (shrink * s1)[:, None] * t1 + (shrink * s2)[:, None] * t2,
                                                  dim=-1)
            trial_res, trial_albedo = residuals_of(trial, sub)
            trial_cost = torch.nan_to_num(trial_res.square().sum(-1), nan=np.inf)
            better = trial_cost < cost
            n = torch.where(better[:, None], trial, n)
            res = torch.where(better[:, None], trial_res, res)
            albedo = torch.where(better[:, None], trial_albedo, albedo)
            cost = torch.where(better, trial_cost, cost)
            damping = torch.where(better, damping * 0.3, damping * 4.0).clamp(1e-7, 1e7)
        return n, albedo, cost

    def descend(start: torch.Tensor, rows: torch.Tensor | None):
        sub = (lambda t: t) if rows is None else (lambda t: t[rows])  # noqa: E731
        n, albedo, res = (levenberg_marquardt if solver == "levenberg_marquardt" else adam)(start, sub)
        return n, albedo, torch.nan_to_num(res, nan=np.inf)

    n, albedo, res = descend(init, None)
    # the second start only where the first explains the pixel badly (mirror-like pixels, grazing views)
    retry = torch.nonzero(res > retry_residual).flatten()
    if len(retry):
        half_way = torch.nn.functional.normalize(init[retry] + views[retry], dim=-1)
        n2, albedo2, res2 = descend(half_way, retry)
        take = res2 < res[retry]
        n[retry] = torch.where(take[:, None], n2, n[retry])
        albedo[retry] = torch.where(take[:, None], albedo2, albedo[retry])
        res[retry] = torch.minimum(res2, res[retry])
    return n, albedo, res


def fit_diffuse_normals(pos: np.ndarray, neg: np.ndarray, white_reference, view_dirs: np.ndarray,
                        normals_init: np.ndarray, pixels: np.ndarray, roughness: float | np.ndarray = 0.6,
                        f0: float = 0.04, steps: int = 6, lr: float = 0.03, retry_residual: float = 1e-5,
                        chunk: int = 262144, device: str | None = None,
                        solver: str = "levenberg_marquardt") -> SpecularFit:
    """Fit normals and diffuse albedo with the GGX reflection modelled (module docstring).

    Args:
        pos, neg: (H, W, 3) decoded linear g+ and g- frames.
        white_reference: (3,) the camera's white reference (decoded value of a white Lambertian, full_on).
        view_dirs: (H, W, 3) unit directions towards the camera (:func:`view_directions`).
        normals_init: (H, W, 3) starting normals (eq. 1's, or the light model's).
        pixels: (H, W) bool where to fit (e.g. the mask where the ratio is defined).
        roughness: perceptual GGX roughness assumed, a scalar or (H, W).
        f0: Schlick Fresnel reflectance at normal incidence assumed.
        steps: iterations per start (Levenberg-Marquardt: 6 converge; Adam needed about 40).
        lr: Adam's step size (``solver="adam"`` only).
        retry_residual: pixels whose relative residual from the first start exceeds this get the second
            (half-way) start too; 0 = every pixel.
        chunk: pixels per batch (bounds memory).
        device: torch device; None = CUDA when available, else CPU.
        solver: one of ``SOLVERS`` (module docstring).

    Returns:
        :class:`SpecularFit`.
    """
    from stages.numerics.sg import ROUGHNESS_MAX, ROUGHNESS_MIN

    pos = np.asarray(pos, np.float32)
    shape = pos.shape[:2]
    for name, arr in (("pos", pos), ("neg", neg), ("view_dirs", view_dirs), ("normals_init", normals_init)):
        if np.shape(arr) != shape + (3,) or len(shape) != 2:
            raise ValueError(f"{name} must be (H, W, 3) like pos {pos.shape}, got {np.shape(arr)}")
    pixels = np.asarray(pixels, bool)
    if pixels.shape != shape:
        raise ValueError(f"pixels must be {shape}, got {pixels.shape}")
    white = np.asarray(white_reference, np.float32).reshape(-1)
    if white.shape != (3,) or not np.all(np.isfinite(white)) or np.any(white <= 0):
        raise ValueError(f"white_reference must be 3 positive finite values, got {white_reference!r}")
    rough_map = np.broadcast_to(np.asarray(roughness, np.float32), shape)
    if not np.all(np.isfinite(rough_map)):
        raise ValueError("roughness must be finite")
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
    if not (0.0 <= f0 <= 1.0) or steps < 0 or lr <= 0 or chunk < 1:
        raise ValueError(f"need 0 <= f0 <= 1, steps >= 0, lr > 0 and chunk >= 1 (got {f0}, {steps}, {lr}, {chunk})")
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")

    normals = np.zeros(shape + (3,), np.float32)
    albedo = np.zeros(shape + (3,), np.float32)
    spec = np.zeros((3,) + shape + (3,), np.float32)
    residual = np.zeros(shape, np.float32)
    rows, cols = np.nonzero(pixels)
    obs_all = np.nan_to_num(np.stack([pos[rows, cols], np.asarray(neg, np.float32)[rows, cols]], 1) / white,
                            nan=0.0, posinf=0.0, neginf=0.0)
    views_all = np.asarray(view_dirs, np.float32)[rows, cols]
    init_all = np.asarray(normals_init, np.float32)[rows, cols]
    # an undefined start (0 or non-finite) begins at the view direction
    bad = ~np.all(np.isfinite(init_all), -1) | (np.linalg.norm(np.nan_to_num(init_all), axis=-1) < 0.5)
    init_all[bad] = views_all[bad]
    rough_all = np.clip(rough_map[rows, cols], ROUGHNESS_MIN, ROUGHNESS_MAX)
    for start in range(0, len(rows), chunk):
        sl = slice(start, start + chunk)
        to = {"device": device, "dtype": torch.float32}
        obs, views = torch.as_tensor(obs_all[sl]).to(**to), torch.as_tensor(views_all[sl]).to(**to)
        n, rho, res = _fit_chunk(obs, views, torch.as_tensor(init_all[sl]).to(**to),
                                 torch.as_tensor(rough_all[sl]).to(**to), f0, solver, steps, lr, retry_residual)
        with torch.no_grad():
            s = _specular_only(n, views, torch.as_tensor(rough_all[sl]).to(**to), f0)
        r_, c_ = rows[sl], cols[sl]
        normals[r_, c_] = n.cpu().numpy()
        albedo[r_, c_] = rho.cpu().numpy()
        spec[:, r_, c_] = np.moveaxis(s.cpu().numpy(), 1, 0) * white
        residual[r_, c_] = res.cpu().numpy()
    clean = lambda a: np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0)  # noqa: E731
    return SpecularFit(normals=clean(normals), albedo=clean(albedo), specular_full=clean(spec[0]),
                       specular_pos=clean(spec[1]), specular_neg=clean(spec[2]),
                       residual=np.nan_to_num(residual, nan=1.0, posinf=1.0, neginf=1.0))


def white_light_specular(normals: np.ndarray, view_dirs: np.ndarray, roughness: float | np.ndarray, f0: float,
                         chunk: int = 262144) -> np.ndarray:
    """GGX reflection of each pixel under the stage's white light (``full_on``), in white units: what the
    white-light albedo ``full_on / white_reference`` holds on top of the diffuse albedo (exact GGX moments as
    the fit, no occlusion). A mirror seen head-on gives ``f0``, at ``n.v = 0.5`` Schlick's
    ``f0 + (1 - f0) 0.5^5``.

    Args:
        normals: (H, W, 3) unit stage-frame normals; pixels whose normal is not a unit vector (0 = undefined,
            or non-finite) get 0.
        view_dirs: (H, W, 3) unit directions towards the camera (:func:`view_directions`).
        roughness: perceptual GGX roughness, a scalar or (H, W) (clamped to the fit's bounds).
        f0: Schlick Fresnel reflectance at normal incidence (the one the roughness was fitted with).
        chunk: pixels per batch.

    Returns:
        (H, W, 3) float32, >= 0 and finite.
    """
    from stages.numerics.sg import ROUGHNESS_MAX, ROUGHNESS_MIN

    normals = np.asarray(normals, np.float32)
    shape = normals.shape[:2]
    if normals.ndim != 3 or normals.shape[2] != 3 or np.shape(view_dirs) != normals.shape:
        raise ValueError(f"normals and view_dirs must both be (H, W, 3), got {normals.shape} and {np.shape(view_dirs)}")
    rough_map = np.broadcast_to(np.asarray(roughness, np.float32), shape)
    if not np.all(np.isfinite(rough_map)):
        raise ValueError("roughness must be finite")
    if not 0.0 <= f0 <= 1.0 or chunk < 1:
        raise ValueError(f"need 0 <= f0 <= 1 and chunk >= 1, got {f0} and {chunk}")
    finite = np.all(np.isfinite(normals), axis=-1)
    length = np.linalg.norm(np.where(finite[..., None], normals, 0.0), axis=-1)
    rows, cols = np.nonzero(finite & (np.abs(length - 1.0) < 0.1))
    out = np.zeros(shape + (3,), np.float32)
    n_all, v_all = normals[rows, cols], np.asarray(view_dirs, np.float32)[rows, cols]
    r_all = np.clip(rough_map[rows, cols], ROUGHNESS_MIN, ROUGHNESS_MAX)
    with torch.no_grad():
        for start in range(0, len(rows), chunk):
            sl = slice(start, start + chunk)
            spec = _specular_only(torch.as_tensor(n_all[sl]), torch.as_tensor(v_all[sl]),
                                  torch.as_tensor(r_all[sl]), f0)[:, 0]
            out[rows[sl], cols[sl]] = spec.numpy()
    return np.clip(np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)


@dataclass(frozen=True)
class SpecularConfig(Documented):
    """The per-pixel fit of the normals with the specular reflection fitted out
    (:func:`fit_diffuse_normals`): each pixel's normal fitted as Lambertian plus GGX reflection instead
    of eq. 1's ratio alone: a lower mean error against the simulator's normals over valid pixels, also on a
    subject the roughness prior was not chosen on (bench/bench_specular_normals.py measures it there)."""

    roughness: float = checked(0.6, gt=0.0, le=1.0)
    """Perceptual GGX roughness assumed for every pixel the materials' roughness does not reach (a prior: one
    pixel cannot also pin it down)."""
    f0: float = checked(0.04, ge=0.0, le=1.0)
    """Schlick Fresnel reflectance at normal incidence assumed (dielectrics: 0.02-0.05)."""
    solver: str = checked("levenberg_marquardt", one_of=SOLVERS)
    """``levenberg_marquardt`` or ``adam``. On the default capture 6 Levenberg-Marquardt steps reach the
    error against the simulator's normals that 40 Adam steps do, in about a third of the time."""
    steps: int = checked(6, ge=0)
    """Iterations of the per-pixel fit per start (Adam needs about 40)."""
    lr: float = checked(0.03, gt=0.0)
    """Adam's step size (``solver: adam`` only)."""


def specular_free_normals(cam: Camera, pos: np.ndarray, neg: np.ndarray, normals_init: np.ndarray,
                          defined: np.ndarray, model: Any, spec: SpecularConfig, roughness: float | np.ndarray,
                          light_iterations: int) -> np.ndarray:
    """(H, W, 3) normals fitted as Lambertian plus GGX reflection of the given ``roughness`` (a scalar or
    (H, W)) where ``defined``; with the session's LED model, eq. 1 through that model of the frames less the
    fitted specular part, so they are on the same footing as the ratio normals."""
    if not defined.any():
        return np.zeros_like(normals_init)
    white = np.asarray(cam.record["white_reference"], np.float32)
    views = view_directions(cam.K, cam.cam_from_world, pos.shape[0], pos.shape[1])
    fit = fit_diffuse_normals(pos, neg, white, views, normals_init, defined, roughness=roughness, f0=spec.f0,
                              steps=spec.steps, lr=spec.lr, solver=spec.solver)
    if model is None:
        return fit.normals
    return corrected_normals(pos - fit.specular_pos, neg - fit.specular_neg, model, defined, light_iterations)
