"""Colour calibration numerics: chart reference values, camera-to-linear-sRGB matrix fit, CIE dE2000.

Pure functions, arrays in and arrays out, no I/O. Colour is linear sRGB (Rec. 709 primaries, D65), as
everywhere in the project (docs/CONTRACTS.md).

Reference chart. :func:`reference_chart_srgb` takes the X-Rite ColorChecker Classic values shipped in
colour-science (``colour.CCS_COLOURCHECKERS['ColorChecker24 - After November 2014']``, CIE xyY under the
chart's illuminant, D50), converts them to XYZ, adapts them to D65 (von Kries with the Bradford cone
space) and converts them to linear sRGB. Patch order is the chart's reading order: row 1 "dark skin" ..
"bluish green", row 4 "white 9.5" .. "black 2"; the white patch is ~0.88, the black ~0.03.

Matrix. :func:`fit_colour_matrix` returns ``M`` (3, 3) with ``reference ~= M @ measured`` per patch,
i.e. ``corrected = rgb @ M.T`` for an image (:func:`apply_colour_matrix`). Plain least squares by
default; ``white_preserving=True`` adds the equality constraint ``M @ white_measured = white_reference``
(solved exactly per row through the KKT system), so the neutral the chart defines stays exactly neutral
(and at the same level) after correction, at the price of a slightly larger residual on the colours.

dE2000. :func:`delta_e_2000` converts linear sRGB to XYZ (D65) and CIE Lab (D65 white) and calls
``colour.delta_E(..., method='CIE 2000')``. Lab is computed relative to a white of Y = 1, so pass values
on the chart's scale (white patch ~0.88), not raw exposure units.
"""
from __future__ import annotations

import functools

import numpy as np

__all__ = [
    "REFERENCE_CHART",
    "reference_chart_srgb",
    "fit_colour_matrix",
    "apply_colour_matrix",
    "linear_srgb_to_lab",
    "delta_e_2000",
    "chart_patch_means",
    "exposure_scale",
]

#: The colour-science chart used as reference (CCS_COLOURCHECKERS key).
REFERENCE_CHART = "ColorChecker24 - After November 2014"
#: Indices (0-based, reading order) of the neutral patches of the ColorChecker Classic (white .. black).
NEUTRAL_PATCHES = tuple(range(18, 24))


def _d65_xy() -> np.ndarray:
    import colour

    return np.asarray(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"], dtype=np.float64)


@functools.lru_cache(maxsize=4)
def _reference(chart: str) -> tuple[tuple[str, ...], np.ndarray]:
    import colour

    data = colour.CCS_COLOURCHECKERS[chart]
    names = tuple(data.data.keys())
    xyy = np.array(list(data.data.values()), dtype=np.float64)
    xyz = colour.xyY_to_XYZ(xyy)
    d65 = _d65_xy()
    xyz_d65 = colour.chromatic_adaptation(xyz, colour.xy_to_XYZ(data.illuminant), colour.xy_to_XYZ(d65),
                                          method="Von Kries", transform="Bradford")
    rgb = colour.XYZ_to_RGB(xyz_d65, colour.RGB_COLOURSPACES["sRGB"], illuminant=d65)
    rgb.setflags(write=False)
    return names, rgb


def reference_chart_srgb(chart: str = REFERENCE_CHART) -> tuple[tuple[str, ...], np.ndarray]:
    """Patch names (24,) and linear-sRGB (D65) reference values (24, 3) float64 of a colour-science chart.

    The array is read-only (cached); copy it to modify.
    """
    return _reference(chart)


def _as_pairs(name: str, array: np.ndarray) -> np.ndarray:
    array = np.asarray(array, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} holds NaN or Inf")
    return array


def fit_colour_matrix(measured_rgb: np.ndarray, reference_rgb: np.ndarray, white_preserving: bool = False,
                      weights: np.ndarray | None = None, white_measured: np.ndarray | None = None,
                      white_reference: np.ndarray | None = None) -> np.ndarray:
    """3x3 matrix ``M`` with ``reference ~= M @ measured`` per patch (least squares over the N patches).

    Args:
        measured_rgb: (N, 3) linear camera / decoded RGB patch means, N >= 3 (>= 4 with the constraint).
        reference_rgb: (N, 3) linear sRGB targets.
        white_preserving: constrain ``M @ white_measured = white_reference`` exactly.
        weights: optional (N,) non-negative patch weights (e.g. 0 for a clipped patch).
        white_measured, white_reference: (3,) the neutral to preserve; default: the sums of the
            measured and reference values over the neutral patches ``NEUTRAL_PATCHES`` when N == 24,
            else the patch with the largest reference luminance.

    Returns:
        float64 (3, 3); apply to an image with :func:`apply_colour_matrix`.
    """
    measured = _as_pairs("measured_rgb", measured_rgb)
    reference = _as_pairs("reference_rgb", reference_rgb)
    if measured.shape != reference.shape:
        raise ValueError(f"measured {measured.shape} and reference {reference.shape} differ")
    n = len(measured)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (n,) or np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError("weights must be (N,) finite and non-negative")
    if np.count_nonzero(w) < (4 if white_preserving else 3):
        raise ValueError("too few patches with positive weight to fit a 3x3 matrix")
    sw = np.sqrt(w)[:, None]
    a, b = measured * sw, reference * sw
    if not white_preserving:
        solution, *_ = np.linalg.lstsq(a, b, rcond=None)
        return solution.T
    if white_measured is None or white_reference is None:
        if n == 24:
            idx = list(NEUTRAL_PATCHES)
        else:
            idx = [int(np.argmax(reference @ np.array([0.2126, 0.7152, 0.0722])))]
        white_measured = measured[idx].sum(axis=0) if white_measured is None else white_measured
        white_reference = reference[idx].sum(axis=0) if white_reference is None else white_reference
    c = np.asarray(white_measured, dtype=np.float64).reshape(3)
    t = np.asarray(white_reference, dtype=np.float64).reshape(3)
    # per row r: min |a m - b_r|^2 s.t. c . m = t_r  ->  [[2 A^T A, c], [c^T, 0]] [m; mu] = [2 A^T b_r; t_r]
    kkt = np.zeros((4, 4))
    kkt[:3, :3] = 2.0 * a.T @ a
    kkt[:3, 3] = c
    kkt[3, :3] = c
    rhs = np.zeros((4, 3))
    rhs[:3] = 2.0 * a.T @ b
    rhs[3] = t
    solution = np.linalg.solve(kkt, rhs)
    return solution[:3].T


def apply_colour_matrix(rgb: np.ndarray, M: np.ndarray, out: np.ndarray | None = None,
                        block_rows: int = 64) -> np.ndarray:
    """``rgb @ M.T`` for an image (H, W, 3) (or any (..., 3)) in row blocks, without a full-size temporary.

    Args:
        rgb: (..., 3) float array (float32 images stay float32).
        M: (3, 3) matrix from :func:`fit_colour_matrix`.
        out: optional output of the same shape and dtype; ``out=rgb`` corrects in place.
        block_rows: rows of the leading axis per block.

    Returns:
        the corrected array (``out`` when given).
    """
    rgb = np.asarray(rgb)
    M = np.asarray(M, dtype=np.float64)
    if rgb.ndim < 1 or rgb.shape[-1] != 3 or M.shape != (3, 3):
        raise ValueError(f"need rgb (..., 3) and M (3, 3), got {rgb.shape} and {M.shape}")
    dtype = rgb.dtype if np.issubdtype(rgb.dtype, np.floating) else np.float32
    if out is None:
        out = np.empty(rgb.shape, dtype=dtype)
    elif out.shape != rgb.shape:
        raise ValueError(f"out {out.shape} must match rgb {rgb.shape}")
    mt = M.T.astype(dtype)
    if rgb.ndim == 1:
        out[...] = rgb @ mt
        return out
    lead = rgb.shape[0]
    for start in range(0, lead, block_rows):
        block = rgb[start:start + block_rows]
        out[start:start + block_rows] = block @ mt  # the product is a new array: safe when out is rgb
    return out


def linear_srgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """CIE Lab (D65 white, Y_white = 1) of linear sRGB values (..., 3)."""
    import colour

    d65 = _d65_xy()
    xyz = colour.RGB_to_XYZ(np.asarray(rgb, dtype=np.float64), colour.RGB_COLOURSPACES["sRGB"], illuminant=d65)
    return colour.XYZ_to_Lab(xyz, d65)


def delta_e_2000(rgb_a: np.ndarray, rgb_b: np.ndarray) -> np.ndarray:
    """CIE dE2000 (N,) between two sets of linear sRGB colours (N, 3) (via XYZ and Lab, D65)."""
    a = _as_pairs("rgb_a", rgb_a)
    b = _as_pairs("rgb_b", rgb_b)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    import colour

    return np.asarray(colour.delta_E(linear_srgb_to_lab(a), linear_srgb_to_lab(b), method="CIE 2000"),
                      dtype=np.float64)


def exposure_scale(measured_rgb: np.ndarray, reference_rgb: np.ndarray,
                   patches: tuple[int, ...] = NEUTRAL_PATCHES[1:5]) -> float:
    """Scalar ``s`` minimising ``|s * measured - reference|^2`` over `patches` (default: the four middle
    greys, which neither clip nor sit in the noise): an exposure normalisation, no colour change."""
    m = _as_pairs("measured_rgb", measured_rgb)[list(patches)].ravel()
    r = _as_pairs("reference_rgb", reference_rgb)[list(patches)].ravel()
    return float(m @ r / max(m @ m, 1e-300))


def chart_patch_means(image: np.ndarray, labels: np.ndarray, n_patches: int = 24, erode: int = 0,
                      valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mean colour per chart patch from a label image.

    Args:
        image: (H, W, C) (or (H, W)) linear values.
        labels: (H, W) integers; value k in 1..n_patches marks patch k-1, anything else is ignored.
        n_patches: number of patches.
        erode: shrink each patch by this many pixels (binary erosion) first, to drop blurred edges.
        valid: optional (H, W) bool; False pixels (clipped, NaN) are left out.

    Returns:
        means: float64 (n_patches, C), NaN for a patch without pixels.
        counts: int64 (n_patches,) pixels used per patch.
    """
    image = np.asarray(image)
    labels = np.asarray(labels)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or labels.shape != image.shape[:2]:
        raise ValueError(f"need image (H, W, C) and labels (H, W), got {image.shape} and {labels.shape}")
    lab = labels.astype(np.int64)
    lab = np.where((lab >= 1) & (lab <= n_patches), lab, 0)
    if erode > 0:
        from scipy import ndimage

        eroded = np.zeros_like(lab)
        for k in range(1, n_patches + 1):
            inside = ndimage.binary_erosion(lab == k, iterations=int(erode))
            eroded[inside] = k
        lab = eroded
    keep = np.all(np.isfinite(image), axis=-1)
    if valid is not None:
        keep &= np.asarray(valid, dtype=bool)
    lab = np.where(keep, lab, 0).ravel()
    counts = np.bincount(lab, minlength=n_patches + 1)[1:]
    flat = np.where(keep[..., None], image, 0).reshape(-1, image.shape[-1]).astype(np.float64)
    sums = np.stack([np.bincount(lab, weights=flat[:, c], minlength=n_patches + 1)[1:]
                     for c in range(flat.shape[1])], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = sums / counts[:, None]
    return np.where(counts[:, None] > 0, means, np.nan), counts.astype(np.int64)
