"""Albedo and normal metrics of the baselines (ultrastage.baselines.metrics), hand-checked."""
from __future__ import annotations

import math

import numpy as np
import pytest

from ultrastage.baselines import metrics


def _albedo(seed=0, size=24):
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.1, 0.8, size=(size, size, 3))
    mask = np.zeros((size, size), bool)
    mask[3:20, 4:21] = True
    return albedo, mask


def test_scaled_metrics_undo_a_per_channel_scale():
    truth, mask = _albedo()
    pred = truth * np.array([0.5, 1.2, 0.9])
    np.testing.assert_allclose(metrics.least_squares_scale(pred, truth, mask), [2.0, 1 / 1.2, 1 / 0.9])
    m = metrics.albedo_metrics(pred, truth, mask)
    assert m["albedo_psnr_scaled_db"] == metrics.PSNR_CAP_DB and m["albedo_rmse_scaled"] < 1e-12
    assert m["albedo_ssim_scaled"] == pytest.approx(1.0)
    assert m["albedo_psnr_raw_db"] < 30 and m["albedo_ssim_raw"] < 1
    d = (pred - truth)[mask]
    assert m["albedo_rmse_raw"] == pytest.approx(math.sqrt(np.mean(d * d)))
    assert m["albedo_psnr_raw_db"] == pytest.approx(-20 * math.log10(m["albedo_rmse_raw"]))


def test_off_mask_pixels_do_not_count():
    truth, mask = _albedo(1)
    pred = truth.copy()
    pred[~mask] = 0.0
    assert metrics.albedo_metrics(pred, truth, mask)["albedo_rmse_raw"] == 0.0


def test_normal_summary_hand_computed():
    a = np.array([5.0, 10.0, 20.0, 25.0, 40.0])
    s = metrics.normal_summary(a)
    assert s["normal_mean_deg"] == 20.0 and s["normal_median_deg"] == 20.0
    assert s["normal_under_11_25_pct"] == 40.0 and s["normal_under_22_5_pct"] == 60.0
    assert s["normal_under_30_pct"] == 80.0 and s["pixels"] == 5


def test_normal_angles_and_trivial_baselines():
    mask = np.ones((1, 2), bool)
    truth = np.array([[[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]])
    angles = metrics.normal_angles(metrics.constant_normal(1, 2), truth, mask)
    np.testing.assert_allclose(angles, [0.0, 90.0], atol=1e-4)
    srgb = np.full((2, 2, 3), 0.5)
    np.testing.assert_allclose(metrics.input_image_albedo(srgb), 0.21404, atol=1e-4)  # sRGB 0.5 -> linear


def test_bad_inputs_are_refused():
    truth, mask = _albedo()
    with pytest.raises(ValueError, match="empty mask"):
        metrics.albedo_metrics(truth, truth, np.zeros_like(mask))
    with pytest.raises(ValueError):
        metrics.albedo_metrics(truth[..., :2], truth[..., :2], mask)
    bad = truth.copy()
    bad[5, 5] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        metrics.albedo_metrics(bad, truth, mask)
    with pytest.raises(ValueError):
        metrics.normal_summary(np.array([]))
