"""metrics.relit_psnr: PSNR of relit HDR images after a common exposure, over the union of the masks."""
from __future__ import annotations

import math

import numpy as np
import pytest

from stages.numerics.metrics import relit_psnr


def disc_mask(h=16, w=20, radius=6.0):
    rows, cols = np.mgrid[0:h, 0:w]
    return (rows - h / 2) ** 2 + (cols - w / 2) ** 2 < radius ** 2


def test_identical_images_hit_the_cap():
    rng = np.random.default_rng(0)
    mask = disc_mask()
    img = rng.uniform(0.0, 50.0, (*mask.shape, 3))
    out = relit_psnr(img, mask, img.copy(), mask)
    assert out["psnr_db"] == pytest.approx(120.0)  # the 1e-12 MSE floor
    assert out["rmse"] == 0.0 and out["pixels"] == mask.sum()
    assert set(out) == {"psnr_db", "rmse", "scale", "pixels"}


def test_constant_images_hand_computed():
    mask = disc_mask()
    true = np.full((*mask.shape, 3), 4.0)
    out = relit_psnr(np.full_like(true, 3.0), mask, true, mask)
    # p = 4 -> scale 1/4; error 0.25 everywhere: MSE 1/16 -> 10 log10(16) dB
    assert out["scale"] == pytest.approx(0.25)
    assert out["rmse"] == pytest.approx(0.25)
    assert out["psnr_db"] == pytest.approx(10 * math.log10(16.0))
    # brighter than the truth's peak clips at 1 (a display's white): no error left
    assert relit_psnr(np.full_like(true, 8.0), mask, true, mask)["psnr_db"] == pytest.approx(120.0)
    # a darker half: 0 vs 1 on half the pixels
    pred = true.copy()
    pred[: mask.shape[0] // 2] = 0.0
    frac = mask[: mask.shape[0] // 2].sum() / mask.sum()
    assert relit_psnr(pred, mask, true, mask)["psnr_db"] == pytest.approx(10 * math.log10(1 / frac))


def test_union_of_masks_counts_silhouette_errors():
    mask = disc_mask()
    true = np.full((*mask.shape, 3), 2.0)
    extra = mask.copy()
    extra[0, 0] = True  # a predicted pixel outside the truth's mask: truth is 0 there
    pred = np.full_like(true, 2.0)  # even the pixels outside the masks hold 2
    out = relit_psnr(pred, extra, true, mask)
    n = mask.sum() + 1
    assert out["pixels"] == n
    # error 1 (after scale 1/2) on one pixel's three channels among n pixels
    assert out["psnr_db"] == pytest.approx(10 * math.log10(n))
    # a truth pixel the prediction misses: the prediction is 0 there whatever its image holds
    missing = mask.copy()
    missing[8, 10] = False
    out = relit_psnr(pred, missing, true, mask)
    assert out["pixels"] == mask.sum() and out["psnr_db"] == pytest.approx(10 * math.log10(mask.sum()))


def test_exposure_invariance():
    rng = np.random.default_rng(1)
    mask = disc_mask()
    true = rng.lognormal(0.0, 1.0, (*mask.shape, 3))
    pred = true * rng.uniform(0.8, 1.2, true.shape)
    a = relit_psnr(pred, mask, true, mask)
    b = relit_psnr(10 * pred, mask, 10 * true, mask)
    assert 15 < a["psnr_db"] < 60
    assert b["psnr_db"] == pytest.approx(a["psnr_db"], abs=1e-9)
    assert b["scale"] == pytest.approx(a["scale"] / 10)
    # the peak is the truth's 99th percentile on its mask
    assert a["scale"] == pytest.approx(1 / np.percentile(true[mask], 99.0))


def test_non_finite_prediction_is_zeroed():
    mask = disc_mask()
    true = np.full((*mask.shape, 3), 1.0)
    pred = true.copy()
    pred[8, 10] = np.nan
    out = relit_psnr(pred, mask, true, mask)
    assert math.isfinite(out["psnr_db"])
    assert out["psnr_db"] == pytest.approx(10 * math.log10(mask.sum()))


def test_bad_inputs_raise():
    mask = disc_mask()
    img = np.ones((*mask.shape, 3))
    with pytest.raises(ValueError, match="truth mask is empty"):
        relit_psnr(img, mask, img, np.zeros_like(mask))
    with pytest.raises(ValueError, match="images"):
        relit_psnr(img[..., :2], mask, img[..., :2], mask)
    with pytest.raises(ValueError, match="images"):
        relit_psnr(img[1:], mask, img, mask)
    with pytest.raises(ValueError, match="masks"):
        relit_psnr(img, mask[1:], img, mask)


def test_excluded_pixels_leave_the_error_not_the_exposure():
    """Hand case: the truth is 4 on the disc, the prediction 3 except on excluded pixels where it is 0 (a cap
    over an opening the truth shows black): with them left out only the 0.25 error remains, at the same scale."""
    mask = disc_mask()
    true = np.full((*mask.shape, 3), 4.0)
    pred = np.full_like(true, 3.0)
    exclude = np.zeros_like(mask)
    exclude[8, 8:12] = True
    pred[exclude] = 0.0
    plain = relit_psnr(pred, mask, true, mask)
    out = relit_psnr(pred, mask, true, mask, exclude=exclude)
    assert out["scale"] == plain["scale"] == pytest.approx(0.25)
    assert out["pixels"] == mask.sum() - exclude.sum()
    assert out["psnr_db"] == pytest.approx(10 * math.log10(16.0))
    n = mask.sum()
    assert plain["psnr_db"] == pytest.approx(-10 * math.log10(((n - 4) * 0.0625 + 4 * 1.0) / n))
    # an all-False exclude changes nothing; excluding everything is an error
    assert relit_psnr(pred, mask, true, mask, exclude=np.zeros_like(mask)) == plain
    with pytest.raises(ValueError, match="no pixel"):
        relit_psnr(pred, mask, true, mask, exclude=np.ones_like(mask))
    with pytest.raises(ValueError, match="exclude must be"):
        relit_psnr(pred, mask, true, mask, exclude=exclude[1:])


def test_composited_counts_partly_covered_pixels_with_their_coverage():
    """A silhouette pixel both images cover a quarter of (premultiplied: a quarter of the colour) is no error
    composited; thresholded at 0.5 it is 0 in the image under its mask's threshold and the whole quarter in the
    other. Hand-computed on a 2 x 2 scene: one full pixel, one quarter-covered pixel, two empty ones."""
    true = np.zeros((2, 2, 3))
    true[0, 0] = 4.0  # full pixel; the peak (99th percentile on the truth's mask) is 4: scale 1/4
    true[0, 1] = 1.0  # a quarter of 4
    true_mask = np.array([[True, True], [False, False]])  # the truth counts the quarter pixel in (a tie rule)
    pred = true.copy()
    pred_mask = np.array([[True, False], [False, False]])  # our alpha 0.25 < 0.5: out of our mask
    plain = relit_psnr(pred, pred_mask, true, true_mask)
    # thresholded: our quarter pixel is zeroed, error 1/4 (after scale) on one of two pixels
    assert plain["pixels"] == 2 and plain["rmse"] == pytest.approx(math.sqrt(0.25 ** 2 / 2))
    composited = relit_psnr(pred, pred_mask, true, true_mask, composited=True)
    assert composited["pixels"] == 2 and composited["psnr_db"] == pytest.approx(120.0)
    assert composited["scale"] == plain["scale"] == pytest.approx(0.25)
    # a coverage we misjudge still counts: 0.5 of the colour where the truth has 0.25
    pred[0, 1] = 2.0
    assert relit_psnr(pred, pred_mask, true, true_mask, composited=True)["rmse"] == pytest.approx(
        math.sqrt(0.25 ** 2 / 2))
    # a pixel only one image shows (no mask holds it) joins the compared pixels
    pred[1, 1] = 1.0
    out = relit_psnr(pred, pred_mask, true, true_mask, composited=True)
    assert out["pixels"] == 3 and out["rmse"] == pytest.approx(math.sqrt(2 * 0.25 ** 2 / 3))
    # exclude still leaves pixels out
    exclude = np.array([[False, True], [False, True]])
    assert relit_psnr(pred, pred_mask, true, true_mask, exclude=exclude, composited=True)["pixels"] == 1
