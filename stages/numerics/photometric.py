"""Photometric maps from the three light-stage illuminations: normals (seed paper eq. 1), alpha, albedo, mask.

Pure functions, arrays in and arrays out. Conventions (docs/CONTRACTS.md): images are float32 linear sRGB
``(H, W, 3)``; under the gradient ``pos`` (g+) the red, green and blue LEDs at direction ``w`` shine
``(1 + w_x)/2, (1 + w_y)/2, (1 + w_z)/2`` and ``neg`` (g-) the complement, so per channel

    d = (g+ - g-) / (g+ + g-),    n = d / |d|                (R -> x, G -> y, B -> z, stage frame)

and ``|d| = 2/3`` for an ideal unoccluded Lambertian point. Occlusion, specular reflection, noise,
saturation and dark pixels break the ratio; :func:`normal_alpha` turns those into a continuous
confidence in ``[0, 1]`` ("valid" means ``alpha > 0.5``). No output ever holds NaN or Inf, whatever the
input (zeros, negative values, NaN, Inf), and a pixel with a NaN or Inf input is never valid (alpha 0).

The per-pixel work is one fused pass over blocks of rows that fit in cache, writing into preallocated
outputs (no chain of full-size temporaries), shared by a few threads, so it runs near memory bandwidth
(bench/bench_photometric.py measures it against a plain copy of the same bytes). The thread count
defaults to the CPUs available (at most 8); set ``ULTRASTAGE_NUMERIC_THREADS`` (or ``threads=``) when
several worker processes share a machine. The mask (:func:`foreground_mask`) is separate: a per-pixel
threshold (numexpr) and morphology on the bool image (scipy.ndimage).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Sequence

import numexpr as ne
import numpy as np
from scipy import ndimage

from calibration.light import LightModel, correct_normals, gradient_ratio
from pipeline.config import Documented, checked
from stages.numerics import numeric_threads

__all__ = [
    "PhotometricParams",
    "PhotometricMaps",
    "IDEAL_RATIO_NORM",
    "gradient_normals",
    "normal_alpha",
    "albedo_from_white",
    "foreground_mask",
    "foreground_mask_and_holes",
    "open_holes",
    "edge_coverage",
    "photometric_maps",
    "facing_away_fraction",
    "normals_with_alpha",
    "corrected_normals",
]

#: ``|d|`` of an ideal, unoccluded Lambertian point under the LED gradients.
IDEAL_RATIO_NORM = 2.0 / 3.0

_BIG = np.float32(1e30)  # sums above this (Inf) count as undefined
_TINY = np.float32(1e-12)
_LUMA = (0.2126, 0.7152, 0.0722)  # Rec. 709 luminance weights (linear sRGB)


@dataclass(frozen=True)
class PhotometricParams(Documented):
    """Thresholds of the photometric maps. Every term of the alpha is 0.5 exactly at its threshold."""

    eps: float = checked(1e-6, gt=0.0)
    """Floor of the ratio's denominator (decoded linear units): ``d_c = (g+ - g-) / max(g+ + g-, eps)``, so a
    channel's ratio fades continuously to 0 as its signal vanishes (alpha is 0 there long before)."""
    min_signal: float = checked(0.03, ge=0.0)
    """Low-signal threshold relative to ``white_reference``: the darkest channel of ``full_on`` must reach
    this fraction of the white reference (an albedo-times-visibility of 3%) for alpha > 0.5."""
    min_signal_abs: float = checked(0.002, gt=0.0)
    """Absolute floor of the low-signal threshold in decoded linear units (guards against a tiny
    ``white_reference``): the threshold per channel is ``max(min_signal * white_reference, min_signal_abs)``."""
    signal_softness: float = checked(1.0, gt=0.0)
    """Width of the low-signal ramp as a multiple of the threshold: alpha's signal term goes smoothly from 0
    at ``(1 - s/2)`` times the threshold to 1 at ``(1 + s/2)`` times it."""
    ratio_min: float = checked(0.3, ge=0.0, lt="ratio_max")
    """Smallest plausible ``|d|`` (ideal 2/3): below it the point is heavily occluded or the ratio is noise."""
    ratio_max: float = 1.05
    """Largest plausible ``|d|``: above it the ratio is dominated by specular reflection or a bad exposure."""
    ratio_softness: float = checked(0.1, gt=0.0)
    """Width of the smooth ramps at ``ratio_min`` and ``ratio_max`` (in units of ``|d|``)."""
    albedo_max: float = checked(4.0, gt=0.0)
    """Albedo values are clipped to ``[0, albedo_max]`` (specular highlights can exceed 1)."""
    plate_brighter: float = checked(0.15, ge=0.0)
    """With a clean plate: a pixel is foreground where some channel exceeds the plate by this fraction of the
    plate's value (plus the noise term)."""
    plate_darker: float = checked(0.5, ge=0.0)
    """With a clean plate: ... or falls below the plate by this fraction (larger than ``plate_brighter``
    because the subject's occlusion of the LEDs darkens the background around it)."""
    plate_noise_sigmas: float = checked(4.0, ge=0.0)
    """With a clean plate: noise term of the threshold, in standard deviations of the frame-minus-plate
    difference (estimated robustly, per channel, from the plate's own pixel-to-pixel differences)."""
    plate_min_diff: float = checked(0.002, ge=0.0)
    """With a clean plate: absolute floor of the difference threshold (decoded linear units)."""
    no_plate_threshold: float = checked(0.15, gt=0.0, lt=1.0)
    """Without a plate: foreground where luminance exceeds this fraction of the image's 99.5th percentile
    luminance (the stage background is dim, 2-5% grey)."""
    majority_radius: float = checked(0.002, ge=0.0)
    """Radius of the majority (binary median) filter over a (2r+1) square that removes specks and fills
    pinholes (a speckled threshold on dark, textured or noisy regions), as a fraction of min(H, W); at least
    1 pixel, 0 = off."""
    close_radius: float = checked(0.004, ge=0.0)
    """Morphological closing radius (bridges cracks), as a fraction of min(H, W); at least 1 pixel, 0 = off."""
    refine_edges: bool = True
    """Place the mask's edge where the subject covers half of a pixel: pixels in a 2-pixel band around the
    edge are kept where ``|f - b| >= 0.5 |s - b|`` (L1 over channels), with ``s`` the mean of nearby interior
    pixels and ``b`` the plate (or the mean of nearby exterior pixels without one). Without it, a sensitive
    plate difference also takes the half-covered and demosaic-blurred rim."""
    max_hole: float = checked(0.002, ge=0.0)
    """Background holes enclosed by the foreground and smaller than this fraction of the image are filled
    (dark eyes, nostrils); larger enclosed regions (gaps between arm and body) stay background."""
    min_component: float = checked(0.0002, ge=0.0)
    """Foreground components smaller than this fraction of the image (or than 1% of the largest component)
    are dropped."""
    edge_px: int = checked(1, ge=0)
    """Foreground pixels within this many pixels (8-connected) of the background are mixed pixels: part of
    their light comes from behind the subject and demosaicing interpolates across the silhouette (on the
    default capture, eq. 1's normals there are 24-28 deg off the truth and the albedo 0.14 RMSE, against 9.7
    deg and 0.04 inside; the next ring, 19 deg and 0.09, stays valid at 1). Their alpha is capped at
    ``edge_alpha`` (invalid); they stay in the mask. 0 = off."""
    edge_alpha: float = checked(0.25, ge=0.0, le=1.0)
    """Alpha cap of the mixed pixels at the mask's edge (below 0.5: not valid)."""


@dataclass(frozen=True, eq=False)
class PhotometricMaps:
    """Outputs of :func:`photometric_maps`, all ``(H, W[, 3])``.

    Attributes:
        normals: float32 (H, W, 3) unit stage-frame normals, 0 outside the mask or where undefined.
        alpha: float32 (H, W) validity confidence in [0, 1]; valid = alpha > 0.5.
        albedo: float32 (H, W, 3) ``full_on / white_reference`` in [0, albedo_max], 0 outside the mask.
        mask: bool (H, W) foreground.
        ratio_norm: float32 (H, W) ``|d|`` (2/3 ideal), everywhere the ratio is defined, 0 elsewhere.
    """

    normals: np.ndarray
    alpha: np.ndarray
    albedo: np.ndarray
    mask: np.ndarray
    ratio_norm: np.ndarray


# --------------------------------------------------------------------------------------------- checks


def _as_rgb(name: str, x: np.ndarray, shape: tuple[int, ...] | None = None) -> np.ndarray:
    x = np.asarray(x)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"{name} must be (H, W, 3), got shape {x.shape}")
    if shape is not None and x.shape[:2] != shape:
        raise ValueError(f"{name} is {x.shape[:2]}, expected {shape} like the other images")
    if x.dtype != np.float32:
        x = x.astype(np.float32)
    return x


def _as_mask(name: str, x: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray | None:
    if x is None:
        return None
    x = np.asarray(x)
    if x.shape != shape:
        raise ValueError(f"{name} must be {shape}, got {x.shape}")
    return x if x.dtype == bool else x != 0


def _as_white(white_reference) -> np.ndarray:
    w = np.asarray(white_reference, dtype=np.float32).reshape(-1)
    if w.shape != (3,) or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(f"white_reference must be 3 positive finite values (RGB), got {white_reference!r}")
    return w


def _clip_masks(clipped, shape: tuple[int, int]) -> list[np.ndarray]:
    """None, one (H, W) mask, an (H, W, k) / (k, H, W) stack or a sequence of (H, W) masks -> list of masks."""
    if clipped is None:
        return []
    if isinstance(clipped, np.ndarray) and clipped.ndim == 2:
        masks = [clipped]
    elif isinstance(clipped, np.ndarray) and clipped.ndim == 3 and clipped.shape[:2] == shape:
        masks = [clipped[..., i] for i in range(clipped.shape[2])]
    elif isinstance(clipped, np.ndarray) and clipped.ndim == 3:
        masks = list(clipped)
    else:
        masks = list(clipped)
    return [_as_mask("clipped", m, shape) for m in masks if m is not None]


# ------------------------------------------------------------------------------------------- kernel
#
# The per-pixel work runs over blocks of rows (~64K pixels) so that every temporary lives in the core's
# cache: each full-size input is read once and each output written once, like a fused kernel. Blocks are
# shared between a few threads (numpy releases the GIL inside its loops). Broadcasts over the 3-channel
# axis are avoided (numpy runs them as a loop over length-3 rows): per-channel constants are tiled along
# the row, per-pixel factors are applied channel by channel.

_BLOCK_PIXELS = 1 << 16


_default_threads = numeric_threads


@dataclass
class _Job:
    """Arrays and constants of one call; ``None`` for the parts not asked for."""

    W: int
    pos: np.ndarray | None = None
    neg: np.ndarray | None = None
    full_on: np.ndarray | None = None
    mask: np.ndarray | None = None
    clips: tuple = ()
    normals: np.ndarray | None = None  # out
    ratio: np.ndarray | None = None  # out, or in when normals is None
    albedo: np.ndarray | None = None  # out (or None: scratch only, for alpha)
    alpha: np.ndarray | None = None  # out
    eps: np.float32 = np.float32(1e-6)
    amax: np.float32 = np.float32(4.0)
    iw_row: np.ndarray | None = None  # 1 / white_reference tiled to (W * 3,)
    k_row: np.ndarray | None = None  # white_reference / signal threshold tiled to (W * 3,)
    ramps: tuple = ()  # (a, b) pairs: term = clip(a * x + b, 0, 1); signal, ratio low, ratio high


def _block(job: _Job, r0: int, r1: int, scratch: dict) -> None:
    n, W = r1 - r0, job.W
    P, N = scratch["P"][:n], scratch["N"][:n]
    t1, t2 = scratch["t1"][:n], scratch["t2"][:n]
    m = job.mask[r0:r1] if job.mask is not None else None
    nonfinite = None  # (n, W) pixels with a NaN/Inf input (or a ratio that overflows): alpha 0 there

    # ---- normals: d = (p - q) / max(p + q, eps), r = |d|, n = d / r (0 outside the mask)
    if job.normals is not None:
        D, R = job.normals[r0:r1], job.ratio[r0:r1]
        p, q = job.pos[r0:r1], job.neg[r0:r1]
        np.subtract(p, q, out=D)
        np.add(p, q, out=P)
        np.maximum(P, job.eps, out=P)
        np.divide(D, P, out=D)
        np.multiply(D, D, out=P)
        np.matmul(P, _ONES3, out=R)
        if not np.isfinite(R.sum()):  # NaN/Inf inputs (or absurd negative ones): zero those channels
            nonfinite = ~np.isfinite(R)
            np.nan_to_num(D, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
            np.clip(D, -1.0, 1.0, out=D)
            np.multiply(D, D, out=P)
            np.matmul(P, _ONES3, out=R)
        np.sqrt(R, out=R)
        np.maximum(R, _TINY, out=t1)
        if m is not None:
            np.divide(m, t1, out=t1)
        else:
            np.divide(1.0, t1, out=t1)
        # |d| under _TINY (e.g. denormal inputs, whose squares underflow to 0) is undefined, not a tiny normal
        np.copyto(t1, 0.0, where=R < _TINY)
        for c in range(3):
            np.multiply(D[..., c], t1, out=D[..., c])
        R_in = R
    elif job.ratio is not None:
        R_in = np.nan_to_num(job.ratio[r0:r1], nan=0.0, posinf=0.0, neginf=0.0)
    else:
        R_in = None

    # ---- albedo: clip(full_on / white, 0, amax) (unmasked in A for the signal term, masked on output)
    if job.full_on is None:
        return
    A = job.albedo[r0:r1] if job.albedo is not None else N
    A2 = A.reshape(n, W * 3)
    f = job.full_on[r0:r1]
    if job.alpha is not None and not np.isfinite(f.sum()):  # one cheap reduction per block
        bad_white = ~np.isfinite(f).all(axis=-1)
        nonfinite = bad_white if nonfinite is None else (nonfinite | bad_white)
    np.multiply(f.reshape(n, W * 3), job.iw_row, out=A2)
    np.fmax(A2, 0, out=A2)  # NaN -> 0
    np.minimum(A2, job.amax, out=A2)

    # ---- alpha: product of linear ramps, times mask, zero where clipped
    if job.alpha is not None:
        AL = job.alpha[r0:r1]
        (sa, sb), (la, lb), (ha, hb) = job.ramps
        np.multiply(A2, job.k_row, out=P.reshape(n, W * 3))
        np.minimum(P[..., 0], P[..., 1], out=AL)
        np.minimum(AL, P[..., 2], out=AL)  # q = darkest channel relative to its threshold
        np.multiply(AL, sa, out=AL)
        np.add(AL, sb, out=AL)
        np.clip(AL, 0.0, 1.0, out=AL)
        for a, b in ((la, lb), (ha, hb)):
            np.multiply(R_in, a, out=t2)
            np.add(t2, b, out=t2)
            np.clip(t2, 0.0, 1.0, out=t2)
            np.multiply(AL, t2, out=AL)
        if m is not None:
            np.multiply(AL, m, out=AL)
        for c in job.clips:
            np.copyto(AL, 0.0, where=c[r0:r1])
        if nonfinite is not None:
            np.copyto(AL, 0.0, where=nonfinite)

    if job.albedo is not None and m is not None:
        for c in range(3):
            np.multiply(A[..., c], m, out=A[..., c])


_ONES3 = np.ones(3, dtype=np.float32)


def _run(job: _Job, H: int, threads: int | None) -> None:
    W = job.W
    rows = max(1, _BLOCK_PIXELS // max(W, 1))
    blocks = [(r, min(H, r + rows)) for r in range(0, H, rows)]
    threads = _default_threads() if threads is None else max(1, int(threads))
    threads = min(threads, len(blocks))

    def scratch() -> dict:
        return {
            "P": np.empty((rows, W, 3), np.float32),
            "N": np.empty((rows, W, 3), np.float32),
            "t1": np.empty((rows, W), np.float32),
            "t2": np.empty((rows, W), np.float32),
        }

    def work(i: int) -> None:
        s = scratch()
        # NaN/Inf inputs are handled explicitly; numpy's floating-point warnings (thread-local) would be noise
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            for r0, r1 in blocks[i::threads]:
                _block(job, r0, r1, s)

    if threads <= 1:
        work(0)
        return

    with ThreadPoolExecutor(max_workers=threads) as ex:
        for fut in [ex.submit(work, i) for i in range(threads)]:
            fut.result()


def _signal_rows(white: np.ndarray, params: PhotometricParams, W: int) -> tuple[np.ndarray, np.ndarray]:
    thr = np.maximum(np.float32(params.min_signal) * white, np.float32(params.min_signal_abs))
    iw = (np.float32(1.0) / white).astype(np.float32)
    k = (white / thr).astype(np.float32)  # albedo * k = full_on / threshold
    return np.tile(iw, W), np.tile(k, W)


def _ramps(params: PhotometricParams) -> tuple:
    """(a, b) with term = clip(a x + b, 0, 1): 0.5 at the threshold, 0..1 over one width."""
    f = np.float32
    isw = 1.0 / max(params.signal_softness, 1e-6)
    irw = 1.0 / max(params.ratio_softness, 1e-6)
    return (
        (f(isw), f(0.5 - isw)),  # signal: q = 1 at the threshold
        (f(irw), f(0.5 - params.ratio_min * irw)),
        (f(-irw), f(0.5 + params.ratio_max * irw)),
    )


# --------------------------------------------------------------------------------------------- normals


def gradient_normals(
    pos: np.ndarray,
    neg: np.ndarray,
    eps: float = PhotometricParams.eps,
    mask: np.ndarray | None = None,
    threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Normals from the gradient pair: ``d = (g+ - g-) / (g+ + g-)`` per channel, ``n = d / |d|``.

    Args:
        pos: (H, W, 3) decoded linear image under g+ (float32 preferred; other dtypes are converted).
        neg: (H, W, 3) decoded linear image under g-.
        eps: floor of the denominator: ``d_c = (g+ - g-) / max(g+ + g-, eps)``, so ``d_c`` fades to 0
            continuously as the channel's signal vanishes.
        mask: optional (H, W) bool; normals are 0 outside it (``ratio_norm`` is not masked).
        threads: worker threads (default: the CPUs available, at most 8; env ULTRASTAGE_NUMERIC_THREADS).

    Returns:
        normals: float32 (H, W, 3), unit length where ``|d| > 0`` (and inside ``mask``), 0 elsewhere.
        ratio_norm: float32 (H, W), ``|d|`` (2/3 for an unoccluded Lambertian point), in [0, sqrt(3)].

    For non-negative inputs each ``d_c`` is in [-1, 1]. Negative inputs (noise around the black level) can
    give ``|d_c| > 1`` on dark pixels, which :func:`normal_alpha` rejects (low signal, ``ratio_max``); a
    channel with a NaN or Inf input gets ``d_c = 0``. The result never holds NaN or Inf.
    """
    pos = _as_rgb("pos", pos)
    neg = _as_rgb("neg", neg, pos.shape[:2])
    H, W = pos.shape[:2]
    mask = _as_mask("mask", mask, (H, W))
    normals = np.empty(pos.shape, dtype=np.float32)
    ratio = np.empty((H, W), dtype=np.float32)
    _run(_Job(W=W, pos=pos, neg=neg, mask=mask, normals=normals, ratio=ratio, eps=np.float32(eps)), H, threads)
    return normals, ratio


# ----------------------------------------------------------------------------------------------- alpha


def normal_alpha(
    ratio_norm: np.ndarray,
    full_on: np.ndarray,
    white_reference,
    clipped: np.ndarray | Sequence[np.ndarray] | None = None,
    mask: np.ndarray | None = None,
    params: PhotometricParams = PhotometricParams(),
    threads: int | None = None,
) -> np.ndarray:
    """Validity confidence of the eq. 1 normals: a product of ramps, each exactly 0.5 at its threshold.

    ``alpha = signal * ratio_low * ratio_high * (not clipped) * mask`` where

    - ``signal`` = ramp of ``q = min_c albedo_c * white_reference_c / max(min_signal * white_reference_c,
      min_signal_abs)`` (i.e. ``full_on_c`` over its threshold) around ``q = 1``, width ``signal_softness``:
      dark pixels have noisy ratios;
    - ``ratio_low`` / ``ratio_high`` = ramps of ``|d|`` rising at ``ratio_min`` and falling at ``ratio_max``
      (width ``ratio_softness``): ``|d|`` far from the ideal 2/3 means occlusion, specularity or noise;
    - ``not clipped`` is 0 where any frame's decode saturated (the ratio of clipped values is wrong);
    - ``mask`` is 0 outside the foreground.

    The ramps are piecewise linear (``clip(a x + b, 0, 1)``), so alpha is continuous in the image values
    (the binary masks aside), and "valid" = ``alpha > 0.5`` means every term is well above its threshold.

    Args:
        ratio_norm: (H, W) ``|d|`` from :func:`gradient_normals` (NaN/Inf read as 0).
        full_on: (H, W, 3) decoded linear white image (NaN/negative read as 0).
        white_reference: (3,) RGB value an albedo-1 unoccluded Lambertian point gives under full_on.
        clipped: None, an (H, W) bool mask, or a sequence/stack of them (one per illumination); any True -> 0.
        mask: optional (H, W) bool foreground; alpha is 0 outside.
        params: thresholds.
        threads: worker threads (see :func:`gradient_normals`).

    Returns:
        float32 (H, W) alpha in [0, 1].
    """
    full_on = _as_rgb("full_on", full_on)
    H, W = full_on.shape[:2]
    ratio_norm = np.asarray(ratio_norm)
    if ratio_norm.shape != (H, W):
        raise ValueError(f"ratio_norm must be {(H, W)}, got {ratio_norm.shape}")
    white = _as_white(white_reference)
    iw_row, k_row = _signal_rows(white, params, W)
    alpha = np.empty((H, W), dtype=np.float32)
    job = _Job(W=W, full_on=full_on, ratio=ratio_norm.astype(np.float32, copy=False),
               mask=_as_mask("mask", mask, (H, W)), clips=tuple(_clip_masks(clipped, (H, W))), alpha=alpha,
               amax=np.float32(params.albedo_max), iw_row=iw_row, k_row=k_row, ramps=_ramps(params))
    _run(job, H, threads)
    return alpha


# ---------------------------------------------------------------------------------------------- albedo


def albedo_from_white(
    full_on: np.ndarray,
    white_reference,
    mask: np.ndarray | None = None,
    albedo_max: float = PhotometricParams.albedo_max,
    threads: int | None = None,
) -> np.ndarray:
    """Albedo from the white image: ``full_on / white_reference`` per channel.

    Args:
        full_on: (H, W, 3) decoded linear white image.
        white_reference: (3,) RGB decoded value of an ideal white unoccluded Lambertian point (> 0).
        mask: optional (H, W) bool; 0 outside it.
        albedo_max: clip ceiling (specular highlights exceed 1).
        threads: worker threads (see :func:`gradient_normals`).

    Returns:
        float32 (H, W, 3) in [0, albedo_max]; NaN and negative inputs give 0, +Inf gives ``albedo_max``.

    The white image still holds ambient occlusion (../shared/DESIGN.md, the physics): this is albedo times visibility.
    """
    full_on = _as_rgb("full_on", full_on)
    H, W = full_on.shape[:2]
    white = _as_white(white_reference)
    out = np.empty(full_on.shape, dtype=np.float32)
    job = _Job(W=W, full_on=full_on, mask=_as_mask("mask", mask, (H, W)), albedo=out,
               amax=np.float32(albedo_max), iw_row=np.tile((np.float32(1.0) / white).astype(np.float32), W))
    _run(job, H, threads)
    return out


# ------------------------------------------------------------------------------------------------ mask


def _radius(frac: float, shape: tuple[int, int]) -> int:
    if frac <= 0:
        return 0
    return max(1, int(round(frac * min(shape))))


def _or_window(x: np.ndarray, r: int, axis: int) -> np.ndarray:
    """``out[i] = OR(x[i - r .. i + r])`` along ``axis`` (False outside), by doubling: O(log r) bool ORs."""
    if r <= 0:
        return x.copy()
    x = np.moveaxis(x, axis, 0)
    L = x.shape[0]
    n = 2 * r + 1

    def shift_or(a: np.ndarray, k: int) -> np.ndarray:  # b[i] = a[i] | a[i + k]
        b = a.copy() if k >= L else np.empty_like(a)
        if k < L:
            np.logical_or(a[: L - k], a[k:], out=b[: L - k])
            b[L - k :] = a[L - k :]
        return b

    acc, w = x, 1  # acc[i] = OR x[i .. i + w - 1]
    while 2 * w <= n:
        acc = shift_or(acc, w)
        w *= 2
    if w < n:
        acc = shift_or(acc, n - w)
    out = np.empty_like(acc)
    if r < L:
        out[r:] = acc[: L - r]  # centre the window
    for i in range(min(r, L)):  # the first r rows see a truncated window x[0 .. i + r]
        out[i] = np.logical_or.reduce(x[: min(L, i + r + 1)], axis=0)
    return np.moveaxis(out, 0, axis)


def _majority(x: np.ndarray, r: int) -> np.ndarray:
    """Binary median over a (2r+1) square: True where more than half the window is (edges replicated)."""
    u8 = np.where(x, np.uint8(255), np.uint8(0))
    mean = ndimage.uniform_filter(u8, size=2 * r + 1, mode="nearest")
    return mean > 127


def _dilate(x: np.ndarray, r: int) -> np.ndarray:
    """Binary dilation by a (2r+1) square; outside the image counts as background."""
    return _or_window(_or_window(x, r, 0), r, 1) if r > 0 else x


def _erode(x: np.ndarray, r: int) -> np.ndarray:
    """Binary erosion by a (2r+1) square; outside the image counts as foreground (subjects cut by the frame
    edge are not eaten from it)."""
    return ~_dilate(~x, r) if r > 0 else x


def _bbox(x: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    rows = np.flatnonzero(x.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(x[rows[0] : rows[-1] + 1].any(axis=0))
    h, w = x.shape
    return (slice(max(0, rows[0] - margin), min(h, rows[-1] + 1 + margin)),
            slice(max(0, cols[0] - margin), min(w, cols[-1] + 1 + margin)))


def _clean_mask(fg: np.ndarray, params: PhotometricParams) -> tuple[np.ndarray, np.ndarray]:
    """Majority filter, closing, small-hole filling and small-component removal (the last three on the
    foreground's bounding box); the cleaned mask and the hole pixels it filled, both (H, W) bool."""
    shape = fg.shape
    area = fg.size
    r_major, r_close = _radius(params.majority_radius, shape), _radius(params.close_radius, shape)
    if r_major:
        fg = _majority(fg, r_major)
    box = _bbox(fg, r_close + 1)
    out = np.zeros(shape, dtype=bool)
    filled = np.zeros(shape, dtype=bool)
    if box is None:
        return out, filled
    sub = fg[box]
    if r_close:
        sub = _erode(_dilate(sub, r_close), r_close)
    # fill small enclosed holes; the box has a background margin, so a hole touching its edge is not enclosed
    if params.max_hole > 0:
        holes, n = ndimage.label(~sub)
        if n:
            sizes = np.bincount(holes.ravel())
            border = np.unique(np.concatenate([holes[0], holes[-1], holes[:, 0], holes[:, -1]]))
            fill = sizes <= params.max_hole * area
            fill[0] = False
            fill[border] = False
            if fill.any():
                filled[box] = fill[holes]
                sub = sub | filled[box]
    # drop small components
    labels, n = ndimage.label(sub)
    if n > 1 or params.min_component > 0:
        sizes = np.bincount(labels.ravel())
        sizes[0] = 0
        keep = sizes >= max(params.min_component * area, 0.01 * sizes.max(), 1)
        keep[0] = False
        if not keep[1:].all():
            sub = keep[labels]
    out[box] = sub
    return out, filled & out


_EDGE_R = 2  # half-side of the window (pixels) the edge refinement takes subject/background colours from


def _band_colours(fg: np.ndarray, f: np.ndarray, b: np.ndarray | None, band_px: int = 1) -> tuple[np.ndarray, ...]:
    """The colours that decide the coverage of the band ``dilate(fg, band_px) & ~erode(fg, band_px)``.

    Per band pixel (rows ``ys``, cols ``xs``, (N,)): its own colour ``here``, the background ``bgc`` (the plate
    ``b``, or without a plate the mean of exterior pixels ``~dilate(fg, 1)`` in the surrounding (2R+1) window)
    and the subject ``subj`` (the mean of interior pixels ``erode(fg, 1)`` in the window: the nearest ones,
    as the rim's colour differs from the body's further in), each (N, 3) float64,
    and ``known`` (N,) bool: the window holds interior (and, without a plate, exterior) pixels. Empty arrays
    when ``fg`` has no band.
    """
    inner = _erode(fg, 1) & fg
    outer = ~_dilate(fg, 1)
    band = _dilate(fg, band_px) & ~(_erode(fg, band_px) & fg)
    ys, xs = np.nonzero(band)
    h, w = fg.shape
    s_sum = np.zeros((ys.size, 3), np.float64)
    s_cnt = np.zeros(ys.size, np.float64)
    o_sum = np.zeros((ys.size, 3), np.float64) if b is None else None
    o_cnt = np.zeros(ys.size, np.float64) if b is None else None
    for dy in range(-_EDGE_R, _EDGE_R + 1):
        yy = np.clip(ys + dy, 0, h - 1)
        for dx in range(-_EDGE_R, _EDGE_R + 1):
            xx = np.clip(xs + dx, 0, w - 1)
            col = np.nan_to_num(f[yy, xx], nan=0.0, posinf=0.0, neginf=0.0)
            wi = inner[yy, xx]
            s_sum += col * wi[:, None]
            s_cnt += wi
            if b is None:
                wo = outer[yy, xx]
                o_sum += col * wo[:, None]
                o_cnt += wo
    here = np.nan_to_num(f[ys, xs].astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if b is None:
        bgc = o_sum / np.maximum(o_cnt, 1)[:, None]
        known = (s_cnt > 0) & (o_cnt > 0)
    else:
        bgc = np.nan_to_num(b[ys, xs].astype(np.float64))
        known = s_cnt > 0
    subj = s_sum / np.maximum(s_cnt, 1)[:, None]
    return ys, xs, here, bgc, subj, known


def _refine_edges(fg: np.ndarray, f: np.ndarray, b: np.ndarray | None) -> np.ndarray:
    """Keep the pixels of the band ``dilate(fg, 1) & ~erode(fg, 1)`` whose coverage is at least one half.

    Coverage of a band pixel: ``sum_c |f - b| / sum_c |s - b|`` with the colours of :func:`_band_colours` (``s``
    the subject's, ``b`` the background's). Pixels without interior (or, without a plate, exterior) neighbours,
    or with no contrast, keep their state. Only band pixels are visited.
    """
    if not fg.any():
        return fg
    ys, xs, here, bgc, subj, known = _band_colours(fg, f, b)
    if ys.size == 0:
        return fg
    num = np.abs(here - bgc).sum(axis=1)
    den = np.abs(subj - bgc).sum(axis=1)
    known &= den > 1e-6
    out = fg.copy()
    out[ys[known], xs[known]] = num[known] >= 0.5 * den[known]
    return out


def edge_coverage(mask: np.ndarray, full_on: np.ndarray, background: np.ndarray, band_px: int = 2,
                  min_contrast: float = 1e-3) -> np.ndarray:
    """The share of each pixel the subject covers, measured on the outline of its mask against a clean plate.

    1 inside the mask, 0 outside, and on the band ``dilate(mask, band_px) & ~erode(mask, band_px)`` the white
    image's colour projected on the segment from the plate's colour to the subject's (:func:`_band_colours`):
    ``c = (f - b) . (s - b) / |s - b|^2``, clipped to ``[0, 1]``. The signed projection, unlike the mask's
    ``sum |f - b| / sum |s - b|``, does not lift the noise of a background pixel above 0. Band pixels without
    interior neighbours (``erode(mask, 1)`` within 2 pixels) or with less than ``min_contrast`` between subject
    and plate keep the mask's 0 or 1. A band of 2 pixels also measures the pixels just inside the mask, which
    the mask's own threshold of one half on ``sum |f - b|`` can take in when they are mostly background.

    Args:
        mask: (H, W) bool foreground mask (:func:`foreground_mask`).
        full_on: (H, W, 3) decoded linear white image. background: (H, W, 3) the clean plate.
        band_px: half-width (pixels, >= 1) of the band measured around the mask's outline.
        min_contrast: the least ``|s - b|`` (linear units) a band pixel is measured at.

    Returns:
        (H, W) float32 in [0, 1].
    """
    mask = np.asarray(mask, bool)
    full_on = _as_rgb("full_on", full_on)
    if mask.shape != full_on.shape[:2]:
        raise ValueError(f"mask {mask.shape} and full_on {full_on.shape[:2]} differ in size")
    background = _as_rgb("background", background, mask.shape)
    if int(band_px) < 1:
        raise ValueError(f"band_px must be >= 1, got {band_px}")
    out = mask.astype(np.float32)
    if not mask.any():
        return out
    ys, xs, here, bgc, subj, known = _band_colours(mask, full_on, background, int(band_px))
    contrast = ((subj - bgc) ** 2).sum(axis=1)
    known &= np.sqrt(contrast) >= min_contrast
    share = ((here - bgc) * (subj - bgc)).sum(axis=1) / np.maximum(contrast, 1e-24)
    out[ys[known], xs[known]] = np.clip(share[known], 0.0, 1.0)
    return out


def _pair_sigma(x: np.ndarray) -> float:
    """Noise of ``frame - plate`` from the plate alone: the robust (MAD) spread of differences of pixels two
    columns apart, ``std(b[i + 2] - b[i]) = sqrt(2) sigma_b``, which equals ``std(f - b)`` when frame and plate
    have the same noise (same camera and exposure). Two apart, not adjacent: demosaicing correlates
    neighbours. Smooth structure of the plate barely moves it; its edges are outliers the median ignores.
    """
    if x.shape[1] < 3:
        return 0.0
    step = max(1, int(np.sqrt(x.size / 200_000)))
    rows = x[::step]
    d = (rows[:, 2:] - rows[:, :-2])[:, ::step]
    d = d[np.isfinite(d)]
    if d.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))))


def foreground_mask(
    full_on: np.ndarray,
    background: np.ndarray | None = None,
    params: PhotometricParams = PhotometricParams(),
) -> np.ndarray:
    """Foreground (subject) mask of the white image: :func:`foreground_mask_and_holes`'s mask."""
    return foreground_mask_and_holes(full_on, background, params)[0]


def foreground_mask_and_holes(
    full_on: np.ndarray,
    background: np.ndarray | None = None,
    params: PhotometricParams = PhotometricParams(),
) -> tuple[np.ndarray, np.ndarray]:
    """Foreground (subject) mask of the white image, and the enclosed background it filled.

    With a clean plate (``background``, the empty stage under full_on): a pixel is foreground where any
    channel ``c`` satisfies ``f_c > b_c (1 + plate_brighter) + t_c`` or ``f_c < b_c (1 - plate_darker) - t_c``
    with the noise term ``t_c = max(plate_noise_sigmas * sigma_c, plate_min_diff)``; ``sigma_c``, the noise of
    ``f_c - b_c``, is estimated from the plate alone (robust spread of pixel differences, see
    :func:`_pair_sigma`), so it does not depend on how much of the frame the subject covers.
    Without a plate: luminance above ``no_plate_threshold`` times the 99.5th percentile luminance.
    Then cleanup on the bool image: a majority filter (specks out, pinholes in), closing, filling small
    enclosed holes, dropping small components.

    Args:
        full_on: (H, W, 3) decoded linear white image.
        background: optional (H, W, 3) clean plate, same decode settings.
        params: thresholds (``plate_*``, ``no_plate_threshold``, ``majority_radius``, ``close_radius``,
            ``max_hole``, ``min_component``).

    Returns:
        ``(mask, holes)``, both bool (H, W): ``holes`` are the pixels of the enclosed holes the mask filled (inside
        ``mask``); a gap between limbs and a dark patch in shade both look like this from one view
        (:mod:`stages.numerics.gaps` tells them apart across views).
    """
    full_on = _as_rgb("full_on", full_on)
    shape = full_on.shape[:2]
    if background is not None:
        background = _as_rgb("background", background, shape)
        loc: dict = {"big": _BIG}
        terms = []
        for c in range(3):
            f, b = full_on[..., c], background[..., c]
            t = max(params.plate_noise_sigmas * _pair_sigma(b), params.plate_min_diff)
            loc.update({f"f{c}": f, f"b{c}": b, f"t{c}": np.float32(t)})
            F, B = f"where(f{c} < big, f{c}, 0)", f"where(b{c} > 0, b{c}, 0)"  # NaN-safe comparisons
            terms.append(f"({F} > {B} * hi + t{c}) | ({F} < {B} * lo - t{c})")
        loc["hi"] = np.float32(1.0 + params.plate_brighter)
        loc["lo"] = np.float32(1.0 - params.plate_darker)
        fg = ne.evaluate(" | ".join(terms), local_dict=loc)
    else:
        loc = {f"f{c}": full_on[..., c] for c in range(3)}
        loc.update({f"w{c}": np.float32(_LUMA[c]) for c in range(3)})
        loc["big"] = _BIG
        lum = ne.evaluate(
            " + ".join(f"where((f{c} > 0) & (f{c} < big), f{c}, 0) * w{c}" for c in range(3)), local_dict=loc
        )
        step = max(1, int(np.sqrt(lum.size / 250_000)))
        ref = float(np.percentile(lum[::step, ::step], 99.5))
        if ref <= 0:
            return np.zeros(shape, dtype=bool), np.zeros(shape, dtype=bool)
        fg = lum > np.float32(params.no_plate_threshold * ref)
    fg, holes = _clean_mask(np.asarray(fg, dtype=bool), params)
    if params.refine_edges:
        fg = _refine_edges(fg, full_on, background)
    return fg, holes & fg


# ---------------------------------------------------------------------------------------------- driver


def photometric_maps(
    full_on: np.ndarray,
    pos: np.ndarray,
    neg: np.ndarray,
    clipped: np.ndarray | Sequence[np.ndarray] | None,
    white_reference,
    background: np.ndarray | None = None,
    params: PhotometricParams = PhotometricParams(),
    mask: np.ndarray | None = None,
    threads: int | None = None,
) -> PhotometricMaps:
    """All photometric maps of one camera view.

    Args:
        full_on, pos, neg: (H, W, 3) decoded linear images under white light, g+ and g-.
        clipped: None, an (H, W) bool mask (e.g. the OR of the three decodes' ``clipped``), or a sequence of
            up to three (H, W) masks.
        white_reference: (3,) the camera's RGB white reference (rig.json).
        background: optional (H, W, 3) clean plate under full_on for the mask.
        params: thresholds, see :class:`PhotometricParams`.
        mask: optional precomputed (H, W) bool foreground; skips :func:`foreground_mask`.
        threads: worker threads of the per-pixel kernel (see :func:`gradient_normals`).

    Returns:
        :class:`PhotometricMaps` (normals, alpha, albedo, mask, ratio_norm).
    """
    full_on = _as_rgb("full_on", full_on)
    shape = full_on.shape[:2]
    pos = _as_rgb("pos", pos, shape)
    neg = _as_rgb("neg", neg, shape)
    white = _as_white(white_reference)
    clip_list = _clip_masks(clipped, shape)
    if mask is None:
        mask = foreground_mask(full_on, background, params)
    else:
        mask = _as_mask("mask", mask, shape)

    H, W = shape
    normals = np.empty(full_on.shape, dtype=np.float32)
    ratio = np.empty(shape, dtype=np.float32)
    albedo = np.empty(full_on.shape, dtype=np.float32)
    alpha = np.empty(shape, dtype=np.float32)
    iw_row, k_row = _signal_rows(white, params, W)
    job = _Job(W=W, pos=pos, neg=neg, full_on=full_on, mask=mask, clips=tuple(clip_list), normals=normals,
               ratio=ratio, albedo=albedo, alpha=alpha, eps=np.float32(params.eps),
               amax=np.float32(params.albedo_max), iw_row=iw_row, k_row=k_row, ramps=_ramps(params))
    _run(job, H, threads)
    if params.edge_px > 0:
        edge = mask & ~_erode(mask, int(params.edge_px))
        np.minimum(alpha, np.where(edge, np.float32(params.edge_alpha), np.float32(1.0)), out=alpha)
    return PhotometricMaps(normals=normals, alpha=alpha, albedo=albedo, mask=mask, ratio_norm=ratio)


def open_holes(normal_alpha: np.ndarray, albedo: np.ndarray, mask: np.ndarray, gaps: np.ndarray,
               params: PhotometricParams = PhotometricParams()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The maps of one view with ``gaps`` (pixels inside the mask decided as background) put back to background.

    Args:
        normal_alpha: (H, W, 4) float32 normals and alpha (:func:`normals_with_alpha`).
        albedo: (H, W, 3) float32.
        mask: (H, W) bool foreground.
        gaps: (H, W) bool, the pixels to open.
        params: ``edge_px`` and ``edge_alpha``: the gaps' new rim is a mask edge like any other, its alpha capped.

    Returns:
        ``(normal_alpha, albedo, mask)``, new arrays: zero outside the new mask.
    """
    if normal_alpha.ndim != 3 or normal_alpha.shape[2] != 4:
        raise ValueError(f"normal_alpha must be (H, W, 4), got {normal_alpha.shape}")
    shape = normal_alpha.shape[:2]
    if albedo.shape != shape + (3,):
        raise ValueError(f"albedo must be {shape + (3,)} like normal_alpha, got {albedo.shape}")
    for name, a in (("mask", mask), ("gaps", gaps)):
        if np.shape(a) != shape:
            raise ValueError(f"{name} must be {shape} like normal_alpha, got {np.shape(a)}")
    mask = np.asarray(mask, bool) & ~np.asarray(gaps, bool)
    normal_alpha = np.where(mask[..., None], normal_alpha, np.float32(0.0)).astype(np.float32)
    albedo = np.where(mask[..., None], albedo, np.float32(0.0)).astype(np.float32)
    if params.edge_px > 0:
        rim = mask & ~_erode(mask, int(params.edge_px)) & _dilate(np.asarray(gaps, bool), int(params.edge_px))
        normal_alpha[..., 3] = np.where(rim, np.minimum(normal_alpha[..., 3], np.float32(params.edge_alpha)),
                                        normal_alpha[..., 3])
    return normal_alpha, albedo, mask


def facing_away_fraction(normals: np.ndarray, views: np.ndarray, valid: np.ndarray) -> tuple[float, int]:
    """The fraction of ``valid`` pixels whose normal faces away from the camera, and how many pixels that is of.

    A camera sees only surface that faces it, so eq. 1's normals of valid pixels face it (``n . v > 0``) but
    for noise and occlusion; with g+ and g- swapped every normal flips and most face away.

    Args:
        normals: (H, W, 3) normals (0 where undefined).
        views: (H, W, 3) unit directions from each pixel's surface point towards the camera.
        valid: (H, W) bool pixels to count (e.g. alpha > 0.5 inside the mask).

    Returns:
        (fraction in [0, 1], number of valid pixels with a defined normal); (0.0, 0) when there are none.
    """
    normals, views = np.asarray(normals), np.asarray(views)
    if normals.shape != views.shape or normals.ndim != 3 or normals.shape[2] != 3:
        raise ValueError(f"normals and views must be the same (H, W, 3), got {normals.shape} and {views.shape}")
    valid = _as_mask("valid", valid, normals.shape[:2])
    cos = np.einsum("hwc,hwc->hw", np.nan_to_num(normals, nan=0.0, posinf=0.0, neginf=0.0),
                    np.nan_to_num(views, nan=0.0, posinf=0.0, neginf=0.0))
    counted = valid & np.any(normals != 0, axis=-1)
    n = int(counted.sum())
    return (float(np.count_nonzero(cos[counted] < 0)) / n if n else 0.0), n


def normals_with_alpha(normals: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """The released RGBA normal map: (H, W, 4) float32, normals (H, W, 3) in RGB and ``alpha`` (H, W) in A,
    with the normals set to 0 wherever the alpha *as stored* (half float, the release's EXR) is 0.

    A pixel whose alpha rounds to 0 in half float (below 3e-8, or exactly 0: background, clipped, no
    signal) carries no normal in the file, as CONVENTIONS.md says; normals elsewhere are kept as they are.
    """
    normals = np.asarray(normals, np.float32)
    alpha = np.asarray(alpha, np.float32)
    if normals.ndim != 3 or normals.shape[2] != 3 or alpha.shape != normals.shape[:2]:
        raise ValueError(f"normals_with_alpha: expected normals (H, W, 3) and alpha (H, W), "
                         f"got {normals.shape} and {alpha.shape}")
    none = alpha.astype(np.float16) == 0
    out = np.concatenate([normals, alpha[..., None]], axis=-1)
    out[none, :3] = 0.0
    return out


def corrected_normals(pos: np.ndarray, neg: np.ndarray, model: LightModel, mask: np.ndarray,
                      iterations: int) -> np.ndarray:
    """Normals (H, W, 3) from the gradient ratio of ``pos``/``neg`` (H, W, 3) through the fitted light model
    (:func:`calibration.light.correct_normals`, ``iterations`` Gauss-Newton steps), 0 outside ``mask`` (H, W)."""
    d = np.nan_to_num(gradient_ratio(pos, neg, min_total=1e-6), nan=0.0)
    normals = np.zeros_like(d)
    if mask.any():
        normals[mask] = correct_normals(d[mask], model, iterations=iterations).astype(np.float32)
    return np.nan_to_num(normals, nan=0.0, posinf=0.0, neginf=0.0)
