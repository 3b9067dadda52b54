"""The lights stage's action: the LED gradients' ratio model from diffuse-sphere samples, validated before use.

:func:`sphere_samples` turns one camera's pos/neg frames of the calibration sphere into (ratio, true normal)
pairs; :func:`validated_light_model` fits :func:`calibration.light.fit_light_model` on half the cameras, keeps it
only if it lowers the held-out error of the plain ratio enough, and then fits it on all of them. Pure.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from calibration.light import LightModel, correct_normals, fit_light_model, gradient_ratio, sphere_normals


def sphere_samples(pos: np.ndarray, neg: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray,
                   centre: np.ndarray, radius_m: float, erode_px: int) -> tuple[np.ndarray, np.ndarray]:
    """The gradient ratios (N, 3) ``(pos - neg) / (pos + neg)`` and the sphere's true normals (N, 3) at the pixels
    of one camera that see the sphere (``centre`` (3,), ``radius_m``), its silhouette eroded ``erode_px`` pixels,
    where both frames are finite and lit. pos, neg: (H, W, 3) linear RGB; K (3, 3), cam_from_world (3, 4)/(4, 4)."""
    normals, mask = sphere_normals(np.asarray(K), np.asarray(cam_from_world), pos.shape[1], pos.shape[0],
                                   np.asarray(centre), float(radius_m))
    mask = ndimage.binary_erosion(mask, iterations=erode_px)
    ratio = gradient_ratio(pos, neg, min_total=1e-3)
    good = mask & np.all(np.isfinite(ratio), axis=-1)
    return ratio[good], normals[good]


def _mean_angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1.0, 1.0))).mean())


@dataclass(frozen=True)
class LightFit:
    """What :func:`validated_light_model` decided."""

    model: LightModel | None
    """The model fitted on every camera's samples, or None: use the ideal model."""
    stats: dict[str, Any]
    """``ideal``, ``accepted``, and ``fallback_reason`` or the held-out errors (degrees) and ``rms_residual``."""
    reason: str | None
    """Why no model could be fitted (too few cameras or samples); None when the fit was tried on held-out data."""


def validated_light_model(ratios: list[np.ndarray], truths: list[np.ndarray], degree: int, iterations: int,
                          min_gain: float) -> LightFit:
    """The ratio model of the per-camera samples (:func:`sphere_samples`, cameras in a fixed order) if it earns
    its place: fitted on the even cameras and tested on the odd ones (they see other sides of the sphere), it must
    lower the mean angular error of the plain normalised ratio by at least ``min_gain`` (a fraction) with
    ``iterations`` Gauss-Newton steps per pixel. ``degree``: of the model's spherical harmonics."""
    reason = "fewer than 2 cameras with usable sphere frames" if len(ratios) < 2 else None
    if reason is None:
        fit_d, fit_n = np.concatenate(ratios[0::2]), np.concatenate(truths[0::2])
        test_d, test_n = np.concatenate(ratios[1::2]), np.concatenate(truths[1::2])
        try:
            trial = fit_light_model(fit_d, fit_n, degree=degree)
        except ValueError as exc:  # too few sphere pixels left to fit
            reason = f"LED model not fitted: {exc}"
    if reason is not None:
        return LightFit(None, {"ideal": True, "accepted": False, "fallback_reason": reason}, reason)
    naive_err = _mean_angle(test_d / np.maximum(np.linalg.norm(test_d, axis=-1, keepdims=True), 1e-9), test_n)
    fixed_err = _mean_angle(correct_normals(test_d, trial, iterations=iterations), test_n)
    accepted = fixed_err < (1.0 - min_gain) * naive_err
    stats = {"ideal": not accepted, "heldout_err_deg_uncorrected": naive_err,
             "heldout_err_deg_corrected": fixed_err, "accepted": bool(accepted)}
    if not accepted:
        return LightFit(None, stats, None)
    model = fit_light_model(np.concatenate(ratios), np.concatenate(truths), degree=degree)
    return LightFit(model, stats | {"rms_residual": float(model.rms_residual)}, None)
