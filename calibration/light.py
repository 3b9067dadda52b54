"""Light calibration numerics: a smooth model of the gradient ratio's bias and its per-pixel inversion.

Pure functions, arrays in and arrays out, no I/O. Conventions: docs/CONTRACTS.md (stage frame, OpenCV
cameras, ``d = (g+ - g-) / (g+ + g-)`` per channel with R -> x, G -> y, B -> z).

Model. With ideal LEDs an unoccluded Lambertian point with normal ``n`` has ``d = (2/3) n``. Real LEDs
have per-LED, per-channel intensity errors (and real stages cover the sphere unevenly), so ``d`` is a
biased, smooth function of ``n``. We model it per channel as

    d_c(n) = a_c . phi(n),     phi = the real spherical-harmonic polynomials of degree <= `degree`

(9 functions for degree 2, 16 for degree 3; un-normalised polynomial forms, linearly independent on
the unit sphere). :func:`fit_light_model` fits ``a`` (3, K) by least squares on pixels of known normal
(a diffuse sphere: :func:`sphere_normals`), optionally with a ridge pulling towards the ideal model
(useful when the calibration normals cover only part of the sphere). :func:`ideal_light_model` is
``d = (2/3) n`` exactly.

Correction. :func:`correct_normals` solves ``model(n) ~= d`` for a unit ``n`` per pixel: Gauss-Newton
on the sphere (2 tangent-plane unknowns, 3 residuals, a little Levenberg damping), vectorised, starting
from ``normalize(d)``. Only the direction of the residual matters for a unit ``n``, so a pixel whose
``|d|`` is shrunk by occlusion keeps the direction the model explains best. For the ideal model the
start is already the solution (the residual ``(2/3) n - d`` is parallel to ``n``, so its tangent part is
0) and the correction is the identity to float precision.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "LightModel",
    "basis",
    "basis_size",
    "ideal_light_model",
    "fit_light_model",
    "correct_normals",
    "gradient_ratio",
    "sphere_normals",
    "angular_error_deg",
]

LIGHT_MODEL_FORMAT = "ultrastage-light-model/1"


def basis_size(degree: int) -> int:
    """Number K of basis functions up to `degree` ((degree + 1)^2)."""
    if degree not in (1, 2, 3):
        raise ValueError(f"degree must be 1, 2 or 3, got {degree}")
    return (degree + 1) ** 2


def basis(normals: np.ndarray, degree: int = 2, jacobian: bool = False
          ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Spherical-harmonic polynomial basis phi(n) (N, K) of normals (N, 3), and optionally its
    derivative d phi / d n (N, K, 3) (of the polynomials in x, y, z, not restricted to the sphere).

    Functions: 1 | x, y, z | xy, yz, xz, x^2 - y^2, 3z^2 - 1 |
    y(3x^2 - y^2), xyz, y(5z^2 - 1), z(5z^2 - 3), x(5z^2 - 1), z(x^2 - y^2), x(x^2 - 3y^2).
    """
    n = np.asarray(normals, dtype=np.float64)
    k = basis_size(degree)
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    one, zero = np.ones_like(x), np.zeros_like(x)
    funcs = [one, x, y, z]
    grads = [(zero, zero, zero), (one, zero, zero), (zero, one, zero), (zero, zero, one)]
    if degree >= 2:
        funcs += [x * y, y * z, x * z, x * x - y * y, 3 * z * z - 1]
        grads += [(y, x, zero), (zero, z, y), (z, zero, x), (2 * x, -2 * y, zero), (zero, zero, 6 * z)]
    if degree >= 3:
        funcs += [y * (3 * x * x - y * y), x * y * z, y * (5 * z * z - 1), z * (5 * z * z - 3),
                  x * (5 * z * z - 1), z * (x * x - y * y), x * (x * x - 3 * y * y)]
        grads += [(6 * x * y, 3 * x * x - 3 * y * y, zero), (y * z, x * z, x * y),
                  (zero, 5 * z * z - 1, 10 * y * z), (zero, zero, 15 * z * z - 3),
                  (5 * z * z - 1, zero, 10 * x * z), (2 * x * z, -2 * y * z, x * x - y * y),
                  (3 * x * x - 3 * y * y, -6 * x * y, zero)]
    phi = np.stack(funcs[:k], axis=1)
    if not jacobian:
        return phi
    dphi = np.stack([np.stack(g, axis=1) for g in grads[:k]], axis=1)
    return phi, dphi


@dataclass(frozen=True)
class LightModel:
    """The gradient-ratio model ``d = coefficients @ phi(n)`` of one session's LEDs.

    coefficients: (3, K) float64 (rows: the R/x, G/y, B/z channels; K = (degree + 1)^2).
    """
    degree: int
    """Maximum spherical-harmonic degree of the basis (1, 2 or 3)."""
    coefficients: np.ndarray = field(repr=False)
    """(3, K) coefficients of the basis functions per channel."""
    rms_residual: float = 0.0
    """RMS of ``d - model(n)`` over the fitting samples (0 for the ideal model)."""
    samples: int = 0
    """Number of samples the model was fitted on."""

    def __post_init__(self) -> None:
        coefficients = np.asarray(self.coefficients, dtype=np.float64)
        if coefficients.shape != (3, basis_size(self.degree)):
            raise ValueError(f"coefficients must be (3, {basis_size(self.degree)}), got {coefficients.shape}")
        object.__setattr__(self, "coefficients", coefficients)

    def predict(self, normals: np.ndarray) -> np.ndarray:
        """Modelled ratio d (..., 3) for unit normals (..., 3)."""
        n = np.asarray(normals, dtype=np.float64)
        return (basis(n.reshape(-1, 3), self.degree) @ self.coefficients.T).reshape(n.shape)

    def to_json(self) -> dict:
        return {"format": LIGHT_MODEL_FORMAT, "degree": self.degree,
                "basis": "real spherical-harmonic polynomials (calibration.light.basis)",
                "coefficients": self.coefficients.tolist(), "rms_residual": float(self.rms_residual),
                "samples": int(self.samples)}

    def dumps(self) -> str:
        return json.dumps(self.to_json())

    @classmethod
    def from_json(cls, record: dict | str) -> "LightModel":
        if isinstance(record, str):
            record = json.loads(record)
        if record.get("format") != LIGHT_MODEL_FORMAT:
            raise ValueError(f"not a light model record (format {record.get('format')!r})")
        return cls(int(record["degree"]), np.asarray(record["coefficients"], dtype=np.float64),
                   float(record.get("rms_residual", 0.0)), int(record.get("samples", 0)))


def ideal_light_model(degree: int = 2) -> LightModel:
    """The model of ideal LEDs: ``d = (2/3) n``."""
    coefficients = np.zeros((3, basis_size(degree)))
    coefficients[[0, 1, 2], [1, 2, 3]] = 2.0 / 3.0
    return LightModel(degree, coefficients)


def _flat3(name: str, array: np.ndarray) -> np.ndarray:
    array = np.asarray(array, dtype=np.float64)
    if array.shape[-1:] != (3,):
        raise ValueError(f"{name} must be (..., 3), got {array.shape}")
    return array.reshape(-1, 3)


def fit_light_model(d: np.ndarray, normals_true: np.ndarray, degree: int = 2, ridge: float = 0.0,
                    weights: np.ndarray | None = None) -> LightModel:
    """Least-squares fit of the ratio model on samples of known normal.

    Args:
        d: (N, 3) measured ratios ``(g+ - g-) / (g+ + g-)`` (any leading shape with a last axis of 3).
        normals_true: (N, 3) unit normals at the same samples (stage frame).
        degree: basis degree (1, 2 or 3).
        ridge: weight of ``|a - a_ideal|^2`` per sample-mean of the squared residual: the objective is
            ``mean_w |phi a_c - d_c|^2 + ridge * |a_c - a_ideal_c|^2``; 0 = plain least squares.
        weights: optional (N,) non-negative sample weights.

    Samples with a non-finite value or zero weight are ignored. Raises ValueError with fewer usable
    samples than 4 x the number of coefficients per channel.
    """
    dd, nn = _flat3("d", d), _flat3("normals_true", normals_true)
    if dd.shape != nn.shape:
        raise ValueError(f"d {dd.shape} and normals {nn.shape} differ")
    w = np.ones(len(dd)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (len(dd),):
        raise ValueError("weights must be (N,)")
    keep = np.all(np.isfinite(dd), axis=1) & np.all(np.isfinite(nn), axis=1) & np.isfinite(w) & (w > 0)
    k = basis_size(degree)
    if keep.sum() < 4 * k:
        raise ValueError(f"need at least {4 * k} usable samples for degree {degree}, got {int(keep.sum())}")
    dd, nn, w = dd[keep], nn[keep], w[keep] / w[keep].mean()
    nn = nn / np.linalg.norm(nn, axis=1, keepdims=True)
    phi = basis(nn, degree)
    ideal = ideal_light_model(degree).coefficients
    gram = (phi * w[:, None]).T @ phi / len(phi) + ridge * np.eye(k)
    rhs = (phi * w[:, None]).T @ dd / len(phi) + ridge * ideal.T
    coefficients = np.linalg.solve(gram, rhs).T
    residual = dd - phi @ coefficients.T
    rms = float(np.sqrt(np.mean(np.sum(residual ** 2, axis=1))))
    return LightModel(degree, coefficients, rms, int(len(dd)))


def gradient_ratio(pos: np.ndarray, neg: np.ndarray, min_total: float = 0.0) -> np.ndarray:
    """Per-channel gradient ratio ``d = (pos - neg) / (pos + neg)`` (H, W, 3) float32 of the two decoded gradient
    images (H, W, 3) (further channels ignored); NaN where ``pos + neg`` is not above ``min_total`` (>= 0) or
    either is not finite. The division runs in the inputs' precision (float32 at least)."""
    pos = np.asarray(pos)
    neg = np.asarray(neg)
    if pos.ndim != 3 or pos.shape[:2] != neg.shape[:2] or min(pos.shape[-1], neg.shape[-1]) < 3:
        raise ValueError(f"pos and neg must be (H, W, 3) images of one shape, got {pos.shape} and {neg.shape}")
    if not min_total >= 0:
        raise ValueError(f"min_total must be >= 0, got {min_total}")
    dtype = np.result_type(pos.dtype, neg.dtype, np.float32)
    pos = pos[..., :3].astype(dtype, copy=False)
    neg = neg[..., :3].astype(dtype, copy=False)
    total = pos + neg
    ok = np.isfinite(total) & (total > min_total)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        return np.where(ok, (pos - neg) / np.where(ok, total, 1.0), np.nan).astype(np.float32)


def _tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangent vectors (N, 3) each, orthogonal to unit normals n (N, 3) and to each other."""
    helper = np.where(np.abs(n[:, 0:1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def correct_normals(d: np.ndarray, model: LightModel, iterations: int = 4, damping: float = 1e-6,
                    mask: np.ndarray | None = None, chunk: int = 1 << 14) -> np.ndarray:
    """Unit normals n with ``model.predict(n) ~= d`` per pixel (Gauss-Newton on the sphere).

    Args:
        d: (H, W, 3) or (N, 3) measured ratios.
        model: a :class:`LightModel`.
        iterations: Gauss-Newton steps (each: 2x2 normal equations per pixel, step clamped to 0.5 rad).
        damping: Levenberg damping, relative to the trace of the 2x2 system.
        mask: optional bool of d's leading shape; normals are 0 outside it.
        chunk: pixels per vectorised block (bounds the temporaries).

    Returns:
        float32 normals of d's shape; 0 where ``|d| == 0``, d is not finite, or outside `mask`.
    """
    d = np.asarray(d)
    shape = d.shape
    flat = _flat3("d", d)
    keep = np.all(np.isfinite(flat), axis=1)
    if mask is not None:
        keep &= np.asarray(mask, dtype=bool).reshape(-1)
    norm = np.linalg.norm(np.where(keep[:, None], flat, 0.0), axis=1)
    keep &= norm > 0
    out = np.zeros(flat.shape, np.float32)
    index = np.nonzero(keep)[0]
    coefficients = model.coefficients
    for start in range(0, len(index), chunk):
        sel = index[start:start + chunk]
        target = flat[sel]
        n = target / norm[sel, None]
        for _ in range(iterations):
            phi, dphi = basis(n, model.degree, jacobian=True)
            residual = phi @ coefficients.T - target                     # (M, 3)
            t1, t2 = _tangent_basis(n)
            # directional derivatives of phi along the tangents (M, K), then of the model (M, 3)
            j1 = (dphi @ t1[:, :, None])[:, :, 0] @ coefficients.T
            j2 = (dphi @ t2[:, :, None])[:, :, 0] @ coefficients.T
            a11, a12, a22 = (j1 * j1).sum(1), (j1 * j2).sum(1), (j2 * j2).sum(1)
            g1, g2 = (j1 * residual).sum(1), (j2 * residual).sum(1)
            lam = damping * (a11 + a22) + 1e-300
            a11, a22 = a11 + lam, a22 + lam
            det = a11 * a22 - a12 * a12
            safe = np.abs(det) > 1e-300
            det = np.where(safe, det, 1.0)
            s1 = np.where(safe, -(a22 * g1 - a12 * g2) / det, 0.0)
            s2 = np.where(safe, -(a11 * g2 - a12 * g1) / det, 0.0)
            length = np.hypot(s1, s2)
            scale = np.where(length > 0.5, 0.5 / np.maximum(length, 1e-300), 1.0)
            step = (s1 * scale)[:, None] * t1 + (s2 * scale)[:, None] * t2
            n = n + step
            n /= np.linalg.norm(n, axis=1, keepdims=True)
        out[sel] = n
    return out.reshape(shape)


def sphere_normals(K: np.ndarray, cam_from_world: np.ndarray, width: int, height: int, centre: np.ndarray,
                   radius: float) -> tuple[np.ndarray, np.ndarray]:
    """World normals of a sphere seen by an OpenCV camera, by ray-sphere intersection at pixel centres.

    Args:
        K: (3, 3) intrinsics (pixel i has its centre at u = i); cam_from_world: (3, 4) ``[R | t]``.
        width, height: image size; centre: (3,) sphere centre (world, metres); radius: metres.

    Returns:
        normals_world: float32 (H, W, 3), unit on the sphere, 0 elsewhere; mask: bool (H, W), True where
        the ray through the pixel centre hits the sphere in front of the camera. Edge pixels are only
        partly covered in a real image: erode the mask by a pixel or two before fitting.
    """
    K = np.asarray(K, dtype=np.float64)
    cam_from_world = np.asarray(cam_from_world, dtype=np.float64)
    centre = np.asarray(centre, dtype=np.float64).reshape(3)
    if K.shape != (3, 3) or cam_from_world.shape != (3, 4) or radius <= 0:
        raise ValueError("need K (3, 3), cam_from_world (3, 4) and radius > 0")
    rotation, translation = cam_from_world[:, :3], cam_from_world[:, 3]
    origin = -rotation.T @ translation
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    rays = rays_cam @ rotation                                   # world directions (H, W, 3), not unit
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    oc = origin - centre
    b = rays @ oc
    c = float(oc @ oc) - radius * radius
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    mask = (disc > 0) & (t > 0)
    hits = origin + t[..., None] * rays
    normals = (hits - centre) / radius
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = np.where(mask[..., None], normals, 0.0).astype(np.float32)
    return normals, mask


def angular_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees (...,) between unit vectors a and b (..., 3)."""
    dot = np.sum(np.asarray(a, np.float64) * np.asarray(b, np.float64), axis=-1)
    return np.degrees(np.arccos(np.clip(dot, -1.0, 1.0)))
