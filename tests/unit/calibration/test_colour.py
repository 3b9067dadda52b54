"""Colour calibration: chart reference, matrix fit, dE2000; a real ColorChecker photo (skips without ../shared)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration.colour import (NEUTRAL_PATCHES, apply_colour_matrix, chart_patch_means, delta_e_2000,
                                exposure_scale, fit_colour_matrix, reference_chart_srgb)

SHARED = Path(__file__).resolve().parents[3].parent / "shared" / "data"
CHART_DIR = SHARED / "colorchecker"
needs_chart = pytest.mark.skipif(not (CHART_DIR / "colorchecker_patch_labels.png").is_file(),
                                 reason=f"shared data not found ({CHART_DIR}); a fresh clone has no ../shared")


def test_reference_chart_is_the_colorchecker_in_linear_srgb():
    names, ref = reference_chart_srgb()
    assert len(names) == 24 and ref.shape == (24, 3)
    assert names[0] == "dark skin" and names[18].startswith("white") and names[23].startswith("black")
    # neutrals are neutral after adaptation to D65, white ~0.88, black ~0.03
    greys = ref[list(NEUTRAL_PATCHES)]
    assert np.all(np.ptp(greys[1:], axis=1) / greys[1:].mean(axis=1) < 0.05)
    assert 0.85 < greys[0, 1] < 0.9 and 0.02 < greys[-1, 1] < 0.04
    assert np.all(np.diff(greys[:, 1]) < 0)
    red, green, blue = ref[14], ref[13], ref[12]
    assert red.argmax() == 0 and green.argmax() == 1 and blue.argmax() == 2


def test_delta_e_2000_zero_for_equal_and_known_scale():
    _, ref = reference_chart_srgb()
    np.testing.assert_allclose(delta_e_2000(ref, ref), 0.0, atol=1e-9)
    de = delta_e_2000(ref, ref * 1.2)
    assert np.all(de > 0.5) and np.all(de < 15)


def test_fit_recovers_a_known_matrix_and_white_preserving_constraint():
    rng = np.random.default_rng(0)
    _, ref = reference_chart_srgb()
    true = np.eye(3) + 0.1 * rng.normal(size=(3, 3))
    measured = ref @ np.linalg.inv(true).T
    M = fit_colour_matrix(measured, ref)
    np.testing.assert_allclose(M, true, atol=1e-10)
    np.testing.assert_allclose(delta_e_2000(measured @ M.T, ref), 0.0, atol=1e-6)
    # noisy: the constrained fit maps the measured neutral exactly onto the reference neutral
    noisy = measured * (1 + 0.02 * rng.normal(size=measured.shape))
    Mw = fit_colour_matrix(noisy, ref, white_preserving=True)
    idx = list(NEUTRAL_PATCHES)
    np.testing.assert_allclose(Mw @ noisy[idx].sum(axis=0), ref[idx].sum(axis=0), rtol=1e-10)
    free = fit_colour_matrix(noisy, ref)
    assert np.sum((noisy @ free.T - ref) ** 2) <= np.sum((noisy @ Mw.T - ref) ** 2) + 1e-12
    # weights: a zero-weight outlier does not matter
    spoiled = measured.copy()
    spoiled[5] *= 3
    w = np.ones(24)
    w[5] = 0
    np.testing.assert_allclose(fit_colour_matrix(spoiled, ref, weights=w), true, atol=1e-10)
    with pytest.raises(ValueError):
        fit_colour_matrix(measured[:2], ref[:2])


def test_apply_colour_matrix_in_place_and_blocks():
    rng = np.random.default_rng(1)
    image = rng.random((130, 7, 3)).astype(np.float32)
    M = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    expected = image.astype(np.float64) @ M.T
    out = apply_colour_matrix(image, M)
    assert out.dtype == np.float32 and out.shape == image.shape
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-6)
    same = apply_colour_matrix(image, M, out=image, block_rows=16)
    assert same is image
    np.testing.assert_allclose(image, expected, rtol=1e-5, atol=1e-6)


def test_chart_patch_means_from_a_label_image():
    labels = np.zeros((40, 60), np.uint8)
    image = np.zeros((40, 60, 3), np.float32)
    for k in range(1, 25):
        r, c = divmod(k - 1, 6)
        labels[r * 10 + 1:r * 10 + 9, c * 10 + 1:c * 10 + 9] = k
        image[r * 10 + 1:r * 10 + 9, c * 10 + 1:c * 10 + 9] = [k, 2 * k, 3 * k]
    image[0, 0] = 99  # background is ignored
    means, counts = chart_patch_means(image, labels)
    np.testing.assert_allclose(means[:, 0], np.arange(1, 25))
    assert np.all(counts == 64)
    means, counts = chart_patch_means(image, labels, erode=2)
    assert np.all(counts == 16)
    valid = np.ones((40, 60), bool)
    valid[labels == 3] = False
    means, counts = chart_patch_means(image, labels, valid=valid)
    assert counts[2] == 0 and np.isnan(means[2]).all() and np.isfinite(means[3]).all()


# --- real chart ------------------------------------------------------------------------------------------

def _held_out_errors(measured: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """Mean dE2000 of (leave-one-out, two-fold even/odd) fits, each patch predicted by a matrix that did
    not see it."""
    loo = []
    for i in range(len(measured)):
        train = np.setdiff1d(np.arange(len(measured)), [i])
        M = fit_colour_matrix(measured[train], reference[train])
        loo.append(delta_e_2000(measured[i:i + 1] @ M.T, reference[i:i + 1])[0])
    folds = []
    for train in (np.arange(0, 24, 2), np.arange(1, 24, 2)):
        test = np.setdiff1d(np.arange(24), train)
        M = fit_colour_matrix(measured[train], reference[train])
        folds.append(delta_e_2000(measured[test] @ M.T, reference[test]))
    return float(np.mean(loo)), float(np.mean(np.concatenate(folds)))


@needs_chart
def test_real_colorchecker_photo():
    """A real ColorChecker photo: dE2000 before and after the fitted matrix, in and out of sample.

    Label mapping: the label image's values 1..24 number the patches in reading order of the image
    (left to right, top to bottom). Both the label image and the photos show the chart in its standard
    orientation (logo top left, "dark skin" top left, "black" bottom right): the 180-degree rotation of
    the physical capture has already been undone in these files, so label k is reference patch k-1. The
    rotated mapping (label k -> patch 24-k) is checked to fit far worse.

    Linearity: the TIFF is 8-bit and gamma encoded, not linear: its green channel equals
    0.91 * mosaic^0.44 (mosaic = the linear 8-bit raw mosaic, GBRG) to 0.7% over the patches, i.e. a pure
    power law with gamma ~2.27; we decode it with gamma 2.2 (which the grey ramp follows to ~6%). The raw
    mosaic is linear (black/white green ratio 0.034 vs 0.036 in the reference), so it gives a second,
    cleaner measurement: per-patch means of its R, G, B sites, clipped sites (>= 254) left out.
    """
    import tifffile
    from PIL import Image

    labels = np.asarray(Image.open(CHART_DIR / "colorchecker_patch_labels.png"))
    _, ref = reference_chart_srgb()
    results = {}

    # 1. the white-balanced camera-RGB TIFF, linearised
    tif = tifffile.imread(CHART_DIR / "colorchecker_wb_camera_rgb.tif")
    assert tif.dtype == np.uint8
    linear = (tif.astype(np.float64) / 255.0) ** 2.2
    measured, counts = chart_patch_means(linear, labels, erode=3)
    assert np.all(counts > 500)

    # 2. the linear raw mosaic (GBRG: G at (0,0) and (1,1), B at (0,1), R at (1,0))
    mosaic = tifffile.imread(CHART_DIR / "colorchecker_raw_mosaic.tif").astype(np.float64) / 255.0
    sites = {0: [(1, 0)], 1: [(0, 0), (1, 1)], 2: [(0, 1)]}
    raw = np.zeros((24, 3))
    for channel, offsets in sites.items():
        values = np.concatenate([mosaic[dy::2, dx::2].ravel() for dy, dx in offsets])
        site_labels = np.concatenate([labels[dy::2, dx::2].ravel() for dy, dx in offsets])
        m, _ = chart_patch_means(values[:, None, None], site_labels[:, None], valid=(values < 254 / 255)[:, None])
        raw[:, channel] = m[:, 0]
    # camera RGB taken as sRGB: white balance and exposure from the middle greys
    greys = list(NEUTRAL_PATCHES[1:5])
    raw_wb = raw * (ref[greys].sum(axis=0) / raw[greys].sum(axis=0))

    for name, values in (("tif", measured), ("mosaic", raw_wb)):
        before = delta_e_2000(values * exposure_scale(values, ref), ref).mean()
        M = fit_colour_matrix(values, ref)
        after = delta_e_2000(values @ M.T, ref).mean()
        Mw = fit_colour_matrix(values, ref, white_preserving=True)
        after_white = delta_e_2000(values @ Mw.T, ref).mean()
        loo, twofold = _held_out_errors(values, ref)
        rotated = delta_e_2000(values @ fit_colour_matrix(values, ref[::-1]).T, ref[::-1]).mean()
        results[name] = (before, after, after_white, loo, twofold, rotated)
        print(f"\n{name}: mean dE2000 before {before:.2f}, after 3x3 fit {after:.2f} "
              f"(white-preserving {after_white:.2f}); held out: leave-one-out {loo:.2f}, even/odd {twofold:.2f}; "
              f"rotated label mapping {rotated:.2f}")
        assert after < before and loo < before
        assert rotated > 2 * after
        assert after < 7.0
