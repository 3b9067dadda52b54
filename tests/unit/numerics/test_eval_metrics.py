"""Evaluation metrics on hand-computed cases."""
from __future__ import annotations

import math

import numpy as np
import pytest

from stages.numerics.metrics import (
    angular_error_deg,
    downsample_to,
    mask_iou,
    normal_error_stats,
    psnr,
    ssim,
)


def test_angular_error_hand_cases():
    est = np.array([[[0, 0, 1], [0, 0, 2], [1, 0, 0], [0, 0, -1], [1, 1, 0], [0, 0, 0]]], np.float32)
    gt = np.array([[[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1], [1, 0, 0], [0, 0, 1]]], np.float32)
    err = angular_error_deg(est, gt)
    assert err.shape == (1, 6) and err.dtype == np.float32
    np.testing.assert_allclose(err[0], [0, 0, 90, 180, 45, 90], atol=1e-4)


def test_angular_error_small_angles_are_accurate():
    t = np.radians(0.01)
    est = np.array([[[np.sin(t), 0, np.cos(t)]]], np.float32)
    gt = np.array([[[0, 0, 1]]], np.float32)
    assert angular_error_deg(est, gt)[0, 0] == pytest.approx(0.01, rel=1e-3)


def test_angular_error_finite_for_garbage():
    est = np.array([[[np.nan, 0, 1], [np.inf, 0, 0], [0, 0, 0]]], np.float32)
    gt = np.zeros((1, 3, 3), np.float32)
    err = angular_error_deg(est, gt)
    assert np.isfinite(err).all()
    with pytest.raises(ValueError):
        angular_error_deg(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)))


def test_normal_error_stats():
    err = np.array([[1.0, 4.0, 10.0], [30.0, 100.0, np.nan]])
    mask = np.array([[True, True, True], [True, False, True]])
    s = normal_error_stats(err, mask)
    assert s["count"] == 4
    assert s["mean"] == pytest.approx(45 / 4)
    assert s["median"] == pytest.approx(7.0)
    assert s["under5_pct"] == pytest.approx(50.0)
    assert s["under25_pct"] == pytest.approx(75.0)
    assert normal_error_stats(err)["count"] == 5
    empty = normal_error_stats(err, np.zeros_like(mask))
    assert empty["count"] == 0 and math.isnan(empty["mean"])


def test_psnr_hand_computed():
    gt = np.zeros((4, 4, 3))
    est = gt.copy()
    est[0, 0, 0] = 0.1  # MSE over the masked 2x2x3 = 12 values: 0.01 / 12
    mask = np.zeros((4, 4), bool)
    mask[:2, :2] = True
    assert psnr(est, gt, mask) == pytest.approx(10 * np.log10(12 / 0.01))
    assert psnr(est, gt) == pytest.approx(10 * np.log10(48 / 0.01))
    assert psnr(est, gt, mask, peak=2.0) == pytest.approx(10 * np.log10(4 * 12 / 0.01))
    assert psnr(gt, gt) == math.inf
    assert math.isnan(psnr(est, gt, np.zeros((4, 4), bool)))


def test_ssim_identity_and_degradation():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 1, (40, 50, 3))
    mask = np.zeros((40, 50), bool)
    mask[10:30, 12:40] = True
    assert ssim(gt, gt, mask) == pytest.approx(1.0)
    noisy = np.clip(gt + rng.normal(0, 0.1, gt.shape), 0, 1)
    s_noisy = ssim(noisy, gt, mask)
    assert 0 < s_noisy < 0.95
    assert ssim(np.clip(gt + rng.normal(0, 0.3, gt.shape), 0, 1), gt, mask) < s_noisy
    # errors outside the mask's window neighbourhood do not count
    off = gt.copy()
    off[:2] = 0
    assert ssim(off, gt, mask) == pytest.approx(1.0)
    assert ssim(gt[..., 0], gt[..., 0]) == pytest.approx(1.0)  # single channel, whole image
    assert math.isnan(ssim(gt, gt, np.zeros((40, 50), bool)))


def test_mask_iou():
    a = np.zeros((4, 4), bool)
    b = np.zeros((4, 4), bool)
    assert mask_iou(a, b) == 1.0
    a[:2, :2] = True  # 4 px
    b[1:3, 1:3] = True  # 4 px, overlap 1
    assert mask_iou(a, b) == pytest.approx(1 / 7)
    assert mask_iou(a, a.astype(np.uint8) * 255) == 1.0


def test_downsample_image_and_mask():
    x = np.arange(16, dtype=np.float32).reshape(4, 4)
    np.testing.assert_allclose(downsample_to(x, (2, 2)), [[2.5, 4.5], [10.5, 12.5]])
    m = np.array([[1, 1, 0, 0], [0, 0, 0, 0], [1, 1, 1, 0], [1, 0, 0, 0]], bool)
    np.testing.assert_array_equal(downsample_to(m, (2, 2), kind="mask"), [[True, False], [True, False]])
    rgb = np.stack([x, 2 * x, 3 * x], -1)
    assert downsample_to(rgb, (2, 2)).shape == (2, 2, 3)
    assert downsample_to(x, (4, 4)) is not None and downsample_to(x, (4, 4)).shape == (4, 4)
    # odd size at half size: ceil(5 / 2) = 3, last row/column replicated
    odd = np.arange(25, dtype=np.float32).reshape(5, 5)
    half = downsample_to(odd, (3, 3))
    assert half.shape == (3, 3) and half[2, 2] == pytest.approx(24.0)
    with pytest.raises(ValueError, match="integer factor"):
        downsample_to(x, (3, 3))


def test_downsample_normals_renormalised():
    n = np.zeros((2, 2, 3), np.float32)
    n[0, 0] = [1, 0, 0]
    n[0, 1] = [0, 1, 0]  # two orthogonal normals and two undefined (0) ones
    out = downsample_to(n, (1, 1), kind="normal")
    np.testing.assert_allclose(out[0, 0], [np.sqrt(0.5), np.sqrt(0.5), 0], atol=1e-6)
    assert not downsample_to(np.zeros((2, 2, 3)), (1, 1), kind="normal").any()
