"""Evaluation metrics against ground truth: normal angular error, PSNR, SSIM, mask IoU, resampling.

Pure functions on numpy arrays. Maps follow docs/CONTRACTS.md: ``(H, W)`` or ``(H, W, C)``, normals are
unit vectors with 0 where undefined. Masks select the pixels a score is taken over.
"""
from __future__ import annotations

import math
from typing import Literal

import numpy as np

__all__ = [
    "angular_error_deg",
    "normal_error_stats",
    "psnr",
    "ssim",
    "mask_iou",
    "downsample_to",
]


def _unit(v: np.ndarray) -> np.ndarray:
    """float32 copy of ``v`` (..., 3) scaled to unit length; zero (or non-finite) vectors become 0."""
    v = np.nan_to_num(np.asarray(v, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    # the length in float64: that of a float32 vector near float32's maximum overflows float32
    n = np.sqrt(np.einsum("...i,...i->...", v, v, dtype=np.float64))
    inv = np.divide(1.0, n, out=np.zeros_like(n), where=n > 1e-12).astype(np.float32)
    return v * inv[..., None]


def angular_error_deg(normals_est: np.ndarray, normals_gt: np.ndarray) -> np.ndarray:
    """Angle between estimated and true normals, in degrees.

    Args:
        normals_est: (H, W, 3) (or (..., 3)) normals; need not be unit length.
        normals_gt: same shape.

    Returns:
        float32 (H, W) in [0, 180]. Both inputs are normalised first (safely). Where either vector is zero
        (undefined) the error is 90 degrees; select pixels with a mask. Computed as
        ``2 atan2(|a - b|, |a + b|)``, which stays accurate for small angles where ``arccos`` of the
        (clipped) dot product loses precision in float32.
    """
    a = np.asarray(normals_est)
    b = np.asarray(normals_gt)
    if a.shape != b.shape or a.shape[-1] != 3:
        raise ValueError(f"normals must have the same (..., 3) shape, got {a.shape} and {b.shape}")
    ua, ub = _unit(a), _unit(b)
    diff = ua - ub
    summ = ua + ub
    dn = np.sqrt(np.einsum("...i,...i->...", diff, diff))
    sn = np.sqrt(np.einsum("...i,...i->...", summ, summ))
    err = np.degrees(2.0 * np.arctan2(dn, sn)).astype(np.float32)
    # a zero vector: |a - b| = |a + b| = |b| -> 90 degrees already, and both zero -> atan2(0, 0) = 0: make it 90
    zero = (np.abs(ua).sum(axis=-1) == 0) | (np.abs(ub).sum(axis=-1) == 0)
    err[zero] = 90.0
    return err


def normal_error_stats(err_deg: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Summary of angular errors over a mask.

    Args:
        err_deg: (H, W) errors from :func:`angular_error_deg`.
        mask: (H, W) bool; None = every pixel. Non-finite errors are ignored.

    Returns:
        ``{"mean", "median", "under5_pct", "under25_pct", "count"}``: mean and median in degrees, the
        percentage of pixels with error <= 5 and <= 25 degrees, and the pixel count (mean and median are
        NaN and the percentages 0 when the count is 0).
    """
    err = np.asarray(err_deg)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != err.shape:
            raise ValueError(f"mask {mask.shape} does not match errors {err.shape}")
        vals = err[mask]
    else:
        vals = err.ravel()
    vals = vals[np.isfinite(vals)].astype(np.float64)
    n = int(vals.size)
    if n == 0:
        return {"mean": math.nan, "median": math.nan, "under5_pct": 0.0, "under25_pct": 0.0, "count": 0}
    return {
        "mean": float(vals.mean()),
        "median": float(np.median(vals)),
        "under5_pct": 100.0 * float(np.count_nonzero(vals <= 5.0)) / n,
        "under25_pct": 100.0 * float(np.count_nonzero(vals <= 25.0)) / n,
        "count": n,
    }


def _select(x: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    if mask is None:
        return x.reshape(-1)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != x.shape[: mask.ndim]:
        raise ValueError(f"mask {mask.shape} does not match image {x.shape}")
    return x[mask].reshape(-1)


def psnr(est: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None, peak: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over the masked pixels (all channels): ``10 log10(peak^2 / MSE)``.

    Args:
        est, gt: (H, W) or (H, W, C) images of the same shape.
        mask: (H, W) bool; None = every pixel.
        peak: the signal peak (1.0 for decoded linear values and albedo).

    Returns:
        dB; ``inf`` for identical images, NaN for an empty mask.
    """
    est = np.asarray(est, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if est.shape != gt.shape:
        raise ValueError(f"images differ in shape: {est.shape} vs {gt.shape}")
    d = _select(est - gt, mask)
    if d.size == 0:
        return math.nan
    mse = float(np.mean(d * d))
    if mse == 0.0:
        return math.inf
    return float(10.0 * np.log10(peak * peak / mse))


def ssim(
    est: np.ndarray,
    gt: np.ndarray,
    mask: np.ndarray | None = None,
    data_range: float = 1.0,
    win_size: int = 7,
) -> float:
    """Mean structural similarity over the masked pixels (skimage's SSIM map, uniform 7x7 windows).

    The SSIM map is computed on the mask's bounding box (grown by the window radius, so windows at the
    mask's edge see their true neighbourhood) and averaged over the mask's pixels (and channels).

    Args:
        est, gt: (H, W) or (H, W, C) images of the same shape.
        mask: (H, W) bool; None = every pixel.
        data_range: value range of the images (1.0 for albedo and decoded linear values).
        win_size: odd window side; shrunk to fit small images.

    Returns:
        mean SSIM in [-1, 1]; NaN for an empty mask or an image smaller than 3 pixels on a side.
    """
    from skimage.metrics import structural_similarity

    est = np.asarray(est, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if est.shape != gt.shape:
        raise ValueError(f"images differ in shape: {est.shape} vs {gt.shape}")
    h, w = est.shape[:2]
    if mask is None:
        mask = np.ones((h, w), dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (h, w):
        raise ValueError(f"mask {mask.shape} does not match image {est.shape}")
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return math.nan
    cols = np.flatnonzero(mask.any(axis=0))
    r = win_size // 2
    ys = slice(max(0, rows[0] - r), min(h, rows[-1] + 1 + r))
    xs = slice(max(0, cols[0] - r), min(w, cols[-1] + 1 + r))
    a, b, m = est[ys, xs], gt[ys, xs], mask[ys, xs]
    side = min(a.shape[:2])
    win = min(win_size, side if side % 2 else side - 1)
    if win < 3:
        return math.nan
    a = np.nan_to_num(a)
    b = np.nan_to_num(b)
    kw = {"channel_axis": -1} if a.ndim == 3 else {}
    _, smap = structural_similarity(a, b, data_range=data_range, win_size=win, full=True, **kw)
    if smap.ndim == 3:
        smap = smap.mean(axis=-1)
    return float(smap[m].mean())


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two (H, W) masks (nonzero = in); 1.0 when both are empty."""
    a = np.asarray(a).astype(bool, copy=False)
    b = np.asarray(b).astype(bool, copy=False)
    if a.shape != b.shape:
        raise ValueError(f"masks differ in shape: {a.shape} vs {b.shape}")
    union = int(np.count_nonzero(a | b))
    if union == 0:
        return 1.0
    return float(np.count_nonzero(a & b)) / union


def downsample_to(
    x: np.ndarray,
    shape: tuple[int, int],
    kind: Literal["image", "normal", "mask"] = "image",
) -> np.ndarray:
    """Bring a full-resolution map to a smaller (H', W') by an integer factor (e.g. half-size decodes).

    The factor ``f`` is ``H / H'`` rounded, the same on both axes; sizes that do not divide (odd sizes
    decoded at half size: ``H' = ceil(H / 2)``) are padded by replicating the last row/column.

    Args:
        x: (H, W) or (H, W, C) map.
        shape: target (H', W').
        kind: "image" block average (float32); "normal" block average then renormalised (zero stays zero);
            "mask" majority vote: True where at least half the block is (a tie counts as foreground).

    Returns:
        (H', W'[, C]) float32 (bool for masks). ``x`` itself (converted) when it already has ``shape``.

    Raises:
        ValueError: if the sizes are not related by an integer factor.
    """
    x = np.asarray(x)
    H, W = x.shape[:2]
    h, w = int(shape[0]), int(shape[1])
    if kind not in ("image", "normal", "mask"):
        raise ValueError(f"kind must be 'image', 'normal' or 'mask', got {kind!r}")
    if (H, W) == (h, w):
        return x.astype(bool) if kind == "mask" else x.astype(np.float32, copy=False)
    if h <= 0 or w <= 0:
        raise ValueError(f"bad target shape {shape}")
    f = int(round(H / h))
    if f < 1 or -(-H // f) != h or -(-W // f) != w:
        raise ValueError(f"cannot downsample {(H, W)} to {(h, w)} by an integer factor")
    src = x.astype(np.float32) if kind != "mask" else (x != 0).astype(np.float32)
    if (h * f, w * f) != (H, W):
        pad = [(0, h * f - H), (0, w * f - W)] + [(0, 0)] * (src.ndim - 2)
        src = np.pad(src, pad, mode="edge")
    blocks = src.reshape((h, f, w, f) + src.shape[2:])
    out = blocks.mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
    if kind == "mask":
        return out >= 0.5
    if kind == "normal":
        if out.ndim != 3 or out.shape[-1] != 3:
            raise ValueError(f"normal maps must be (H, W, 3), got {x.shape}")
        out = _unit(out)
    return out


def relit_psnr(pred_rgb: np.ndarray, pred_mask: np.ndarray, true_rgb: np.ndarray, true_mask: np.ndarray,
               percentile: float = 99.0, exclude: np.ndarray | None = None,
               composited: bool = False) -> dict[str, float]:
    """PSNR of a relit HDR image against the ground-truth rendering, after a common exposure.

    HDR radiance has no fixed peak, so both images are scaled by ``1 / p`` with ``p`` the ``percentile``
    of the truth's radiance (all channels) on its subject, then clipped to [0, 1] (what a display shows);
    the error is taken over the union of both masks (a silhouette error counts; outside its mask an image
    is 0), less the ``exclude`` pixels. The exposure does not depend on ``exclude``: a figure with pixels left
    out is on the same scale as the one without.

    ``composited``: both images as they are, premultiplied by their own pixel coverage (what either shows over
    black), nothing zeroed outside a mask; the error over every pixel where either mask holds or either image
    is non-zero, less ``exclude``. A silhouette pixel a quarter covered then counts as the quarter of its
    colour it is, in both images, instead of as 0 or as the whole pixel on the side of its mask's threshold.

    Args:
        pred_rgb, true_rgb: (H, W, 3) linear radiance; pred_mask, true_mask: (H, W) bool.
        exclude: optional (H, W) bool, pixels left out of the error (e.g. where the truth shows what no
            reconstruction can: the inside of an open mesh).

    Returns:
        ``psnr_db``, ``rmse`` (in the scaled units), ``scale`` (the 1/p applied), ``pixels`` (union less
        ``exclude``). ValueError when no pixel is left.
    """
    pred = np.asarray(pred_rgb, np.float64)
    true = np.asarray(true_rgb, np.float64)
    pm, tm = np.asarray(pred_mask, bool), np.asarray(true_mask, bool)
    if pred.shape != true.shape or pred.ndim != 3 or pred.shape[2] != 3:
        raise ValueError(f"images must both be (H, W, 3), got {pred.shape} and {true.shape}")
    if pm.shape != pred.shape[:2] or tm.shape != pred.shape[:2]:
        raise ValueError(f"masks must be {pred.shape[:2]}, got {pm.shape} and {tm.shape}")
    if exclude is not None and np.shape(exclude) != pred.shape[:2]:
        raise ValueError(f"exclude must be {pred.shape[:2]}, got {np.shape(exclude)}")
    if not tm.any():
        raise ValueError("the truth mask is empty: nothing to compare")
    pred = np.nan_to_num(pred, nan=0.0, posinf=0.0, neginf=0.0)
    true = np.nan_to_num(true, nan=0.0, posinf=0.0, neginf=0.0)
    union = pm | tm
    if composited:
        union |= np.any(pred != 0, axis=-1) | np.any(true != 0, axis=-1)
    else:
        pred = np.where(pm[..., None], pred, 0.0)
        true = np.where(tm[..., None], true, 0.0)
    peak = float(np.percentile(true[tm], percentile))
    scale = 1.0 / peak if peak > 0 else 1.0
    if exclude is not None:
        union &= ~np.asarray(exclude, bool)
        if not union.any():
            raise ValueError("exclude leaves no pixel of either mask to compare")
    diff = np.clip(pred[union] * scale, 0, 1) - np.clip(true[union] * scale, 0, 1)
    mse = float(np.mean(diff ** 2))
    return {"psnr_db": float(10 * np.log10(1.0 / max(mse, 1e-12))), "rmse": float(np.sqrt(mse)),
            "scale": scale, "pixels": float(union.sum())}
