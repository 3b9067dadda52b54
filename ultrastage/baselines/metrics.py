"""Test metrics of the single-image baselines, on masked pixels (../shared/DESIGN.md's relighting-set protocol).

Albedo (linear, [0, 1]): PSNR (peak 1), SSIM (stages.numerics.metrics.ssim, 7x7 windows, data range 1) and
RMSE, each twice: ``raw`` compares the prediction as it is; ``scaled`` first multiplies each channel by the
least-squares scale ``s_c = sum(p t) / sum(p p)`` over the mask (the field disagrees on whether an albedo's
scale is knowable from one photo, so both are reported). Normals: angle to the truth in degrees, its mean
and median and the percentage of pixels under 11.25, 22.5 and 30 degrees.

Two trivial baselines give the floor a network must clear: :func:`input_image_albedo` (the photo linearised,
taken as the albedo) and :func:`constant_normal` (every normal (0, 0, -1), facing the camera).
"""
from __future__ import annotations

import math

import numpy as np

from pipeline.codecs.image import srgb_decode
from stages.numerics.metrics import angular_error_deg, psnr, ssim

__all__ = ["PSNR_CAP_DB", "NORMAL_THRESHOLDS_DEG", "least_squares_scale", "albedo_metrics", "normal_angles",
           "normal_summary", "input_image_albedo", "constant_normal"]

PSNR_CAP_DB = 100.0
"""PSNR of an exact prediction (infinite) is reported as this, so no table holds Inf."""
NORMAL_THRESHOLDS_DEG = (11.25, 22.5, 30.0)
"""Angles the 'under' percentages of normals are counted at."""


def _check_maps(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, ...]:
    pred = np.asarray(pred, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool)
    if pred.shape != truth.shape or pred.ndim != 3 or pred.shape[2] != 3 or mask.shape != pred.shape[:2]:
        raise ValueError(f"expected prediction and truth (H, W, 3) and mask (H, W), got {pred.shape}, "
                         f"{truth.shape}, {mask.shape}")
    if not mask.any():
        raise ValueError("empty mask: no pixel to take the metrics on")
    if not (np.all(np.isfinite(pred[mask])) and np.all(np.isfinite(truth[mask]))):
        raise ValueError("prediction or truth holds NaN or Inf on the mask")
    return pred, truth, mask


def least_squares_scale(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-channel scale (3,) minimising ``sum_mask (s_c p_c - t_c)^2`` for (H, W, 3) maps and an (H, W)
    mask; 1 for a channel whose prediction is 0 on the whole mask."""
    pred, truth, mask = _check_maps(pred, truth, mask)
    p, t = pred[mask], truth[mask]
    pp = np.einsum("nc,nc->c", p, p)
    pt = np.einsum("nc,nc->c", p, t)
    return np.where(pp > 1e-12, pt / np.maximum(pp, 1e-12), 1.0)


def albedo_metrics(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """Albedo metrics of one example (module docstring): ``albedo_{psnr,ssim,rmse}_{raw,scaled}`` (PSNR as
    ``albedo_psnr_raw_db``), pred and truth (H, W, 3) linear, mask (H, W) bool (not empty). The SSIMs are
    absent when the mask is under 3 pixels across."""
    pred, truth, mask = _check_maps(pred, truth, mask)
    out: dict[str, float] = {}
    for kind, p in (("raw", pred), ("scaled", pred * least_squares_scale(pred, truth, mask))):
        m = psnr(p, truth, mask, peak=1.0)
        out[f"albedo_psnr_{kind}_db"] = min(m, PSNR_CAP_DB)
        s = ssim(p, truth, mask, data_range=1.0)
        if math.isfinite(s):  # NaN for a mask under 3 pixels across: the SSIM is left out then
            out[f"albedo_ssim_{kind}"] = float(s)
        d = (p - truth)[mask]
        out[f"albedo_rmse_{kind}"] = float(math.sqrt(np.mean(d * d)))
    return out


def normal_angles(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Angles (M,) float64 in degrees between predicted and true normals (H, W, 3) at the M mask pixels."""
    pred, truth, mask = _check_maps(pred, truth, mask)
    return angular_error_deg(pred[mask], truth[mask]).astype(np.float64)


def normal_summary(angles_deg: np.ndarray) -> dict[str, float]:
    """``normal_mean_deg``, ``normal_median_deg``, ``normal_under_<t>_pct`` (t = 11_25, 22_5, 30) and
    ``pixels`` of angles (M,) in degrees, M > 0."""
    a = np.asarray(angles_deg, dtype=np.float64).reshape(-1)
    if a.size == 0 or not np.all(np.isfinite(a)):
        raise ValueError(f"need finite angles, got {a.size} value(s)")
    out = {"normal_mean_deg": float(a.mean()), "normal_median_deg": float(np.median(a))}
    for t in NORMAL_THRESHOLDS_DEG:
        out[f"normal_under_{str(t).replace('.', '_').removesuffix('_0')}_pct"] = 100.0 * float(np.mean(a < t))
    out["pixels"] = float(a.size)
    return out


def input_image_albedo(image_srgb: np.ndarray) -> np.ndarray:
    """The trivial albedo: the sRGB photo (H, W, 3) in [0, 1] linearised (the sRGB curve undone)."""
    return srgb_decode(np.asarray(image_srgb, dtype=np.float64)).astype(np.float32)


def constant_normal(height: int, width: int) -> np.ndarray:
    """The trivial normals (H, W, 3): (0, 0, -1) everywhere, facing the camera (OpenCV axes)."""
    out = np.zeros((height, width, 3), np.float32)
    out[..., 2] = -1.0
    return out
