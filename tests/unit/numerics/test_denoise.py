"""joint_bilateral: smoke, shapes, hand-computed cases, edges kept, invalid pixels untouched."""
from __future__ import annotations

import numpy as np
import pytest

from stages.numerics.denoise import joint_bilateral


def _unit(v: np.ndarray) -> np.ndarray:
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


def test_shapes_types_and_a_constant_map_is_unchanged():
    albedo = np.full((6, 7, 3), 0.3, np.float32)
    normal = np.broadcast_to(np.float32([0, 0, 1]), (6, 7, 3)).copy()
    out_albedo, (out_normal,) = joint_bilateral(albedo, [normal], np.ones((6, 7), bool))
    assert out_albedo.shape == (6, 7, 3) and out_albedo.dtype == np.float32
    assert out_normal.shape == (6, 7, 3) and out_normal.dtype == np.float32
    np.testing.assert_allclose(out_albedo, albedo, rtol=1e-6)
    np.testing.assert_allclose(out_normal, normal, atol=1e-6)


def test_hand_computed_three_pixels():
    """One row, radius 1, a huge range width: the middle pixel is the spatially weighted mean of the three."""
    albedo = np.float32([[[0.1] * 3, [0.2] * 3, [0.6] * 3]])
    normal = _unit(np.float32([[[1, 0, 1], [0, 0, 1], [0, 1, 1]]]))
    out_albedo, (out_normal,) = joint_bilateral(albedo, [normal], np.ones((1, 3), bool), spatial_sigma_px=1.0,
                                                range_sigma=1e6, radius=1)
    side = np.exp(-0.5)
    expected = (0.2 + side * (0.1 + 0.6)) / (1 + 2 * side)
    np.testing.assert_allclose(out_albedo[0, 1], expected, rtol=1e-5)
    blended = normal[0, 1] + side * (normal[0, 0] + normal[0, 2])
    np.testing.assert_allclose(out_normal[0, 1], blended / np.linalg.norm(blended), rtol=1e-5)
    # with a narrow range width the 0.6 neighbour carries no weight
    out_albedo, _ = joint_bilateral(albedo, [normal], np.ones((1, 3), bool), 1.0, 0.03, 1)
    w_left = side * np.exp(-(0.1 ** 2) / (2 * 0.03 ** 2))
    np.testing.assert_allclose(out_albedo[0, 1], (0.2 + w_left * 0.1) / (1 + w_left), rtol=1e-4)


def test_noise_goes_down_and_an_albedo_edge_stays():
    rng = np.random.default_rng(0)
    truth = np.where(np.arange(40)[None, :, None] < 20, 0.2, 0.6).astype(np.float32) * np.ones((40, 40, 3), np.float32)
    noisy = truth + rng.normal(0, 0.008, truth.shape).astype(np.float32)
    tilt = rng.normal(0, 0.03, (40, 40, 3)).astype(np.float32)
    normal = _unit(np.float32([0, 0, 1]) + tilt)
    out_albedo, (out_normal,) = joint_bilateral(noisy, [normal], np.ones((40, 40), bool))
    assert np.sqrt(np.mean((out_albedo - truth) ** 2)) < 0.5 * np.sqrt(np.mean((noisy - truth) ** 2))
    # the edge: the columns next to it keep their side's level (no mixing across 0.2 | 0.6)
    assert np.all(np.abs(out_albedo[:, 19] - 0.2) < 0.02) and np.all(np.abs(out_albedo[:, 20] - 0.6) < 0.02)
    angle_in = np.degrees(np.arccos(np.clip(normal[..., 2], -1, 1))).mean()
    angle_out = np.degrees(np.arccos(np.clip(out_normal[..., 2], -1, 1))).mean()
    assert angle_out < 0.5 * angle_in
    np.testing.assert_allclose(np.linalg.norm(out_normal, axis=-1), 1.0, atol=1e-5)


def test_invalid_pixels_neither_change_nor_contribute():
    albedo = np.full((5, 5, 3), 0.3, np.float32)
    albedo[2, 3] = 0.31
    normal = np.broadcast_to(np.float32([0, 0, 1]), (5, 5, 3)).copy()
    normal[2, 3] = _unit(np.float32([1, 0, 1]))
    valid = np.ones((5, 5), bool)
    valid[2, 3] = False
    out_albedo, (out_normal,) = joint_bilateral(albedo, [normal], valid, range_sigma=1.0)
    np.testing.assert_array_equal(out_albedo[2, 3], albedo[2, 3])
    np.testing.assert_array_equal(out_normal[2, 3], normal[2, 3])
    np.testing.assert_allclose(out_albedo[valid], 0.3, rtol=1e-6)  # the invalid 0.31 never leaked in
    np.testing.assert_allclose(out_normal[valid], normal[valid], atol=1e-6)


def test_non_finite_inputs_and_bad_arguments():
    albedo = np.full((4, 4, 3), 0.3, np.float32)
    albedo[1, 1, 0] = np.nan
    normal = np.broadcast_to(np.float32([0, 0, 1]), (4, 4, 3)).copy()
    normal[2, 2] = np.inf
    out_albedo, (out_normal,) = joint_bilateral(albedo, [normal], np.ones((4, 4), bool))
    assert np.all(np.isfinite(out_albedo)) and np.all(np.isfinite(out_normal))
    np.testing.assert_allclose(out_albedo[0, 0], 0.3, rtol=1e-6)
    with pytest.raises(ValueError, match="albedo"):
        joint_bilateral(albedo[..., :2], [normal], np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="normals"):
        joint_bilateral(albedo, [normal[:3]], np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="valid"):
        joint_bilateral(albedo, [normal], np.ones((4, 3), bool))
    for kwargs in ({"spatial_sigma_px": 0.0}, {"range_sigma": -1.0}, {"radius": -1}, {"radius": 1.5}):
        with pytest.raises(ValueError):
            joint_bilateral(albedo, [normal], np.ones((4, 4), bool), **kwargs)
    # radius 0 copies; a pixel with a non-finite normal gets 0 albedo too (nothing undefined travels)
    same, (same_normal,) = joint_bilateral(np.full((3, 3, 3), 0.2, np.float32), [normal[:3, :3]],
                                           np.ones((3, 3), bool), radius=0)
    np.testing.assert_allclose(same[:2], 0.2, rtol=1e-6)
    assert np.all(same[2, 2] == 0) and np.all(same_normal[2, 2] == 0)
