"""The lights stage's action (stages.numerics.light_model): sphere samples and the validated ratio model."""
from __future__ import annotations

import numpy as np

from stages.numerics.light_model import sphere_samples, validated_light_model


def _normals(rng: np.random.Generator, n: int) -> np.ndarray:
    normals = rng.normal(size=(n, 3))
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _cameras(distortion: float, count: int = 4, seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per camera, ratios of LEDs whose gradients are bent by ``distortion`` (terms of degree 2 in the normal, which
    a degree-2 model represents and which turn the plain ratio's direction)."""
    rng = np.random.default_rng(seed)
    ratios, truths = [], []
    for _ in range(count):
        normals = _normals(rng, 500)
        bend = np.stack([normals[:, 1] * normals[:, 2], normals[:, 0] ** 2, -normals[:, 0] * normals[:, 1]], axis=1)
        ratios.append((2.0 / 3.0) * (normals + distortion * bend))
        truths.append(normals)
    return ratios, truths


def test_a_model_that_removes_a_real_bias_is_accepted_and_fitted_on_every_camera():
    fit = validated_light_model(*_cameras(0.3), degree=2, iterations=4, min_gain=0.05)
    assert fit.model is not None and fit.reason is None
    assert fit.stats["accepted"] and not fit.stats["ideal"]
    assert fit.stats["heldout_err_deg_corrected"] < 0.1 * fit.stats["heldout_err_deg_uncorrected"]
    assert fit.stats["rms_residual"] < 1e-3


def test_ideal_leds_keep_the_ideal_model():
    # the plain ratio is already exact: nothing to gain, so the fitted model is not used
    fit = validated_light_model(*_cameras(0.0), degree=2, iterations=4, min_gain=0.05)
    assert fit.model is None and fit.reason is None
    assert fit.stats["ideal"] and not fit.stats["accepted"]


def test_too_few_cameras_fall_back_with_a_reason():
    ratios, truths = _cameras(0.3, count=1)
    fit = validated_light_model(ratios, truths, degree=2, iterations=4, min_gain=0.05)
    assert fit.model is None and "fewer than 2 cameras" in fit.reason
    assert fit.stats == {"ideal": True, "accepted": False, "fallback_reason": fit.reason}


def test_sphere_samples_are_the_ratio_and_normals_on_the_sphere():
    K = np.array([[80.0, 0.0, 31.5], [0.0, 80.0, 31.5], [0.0, 0.0, 1.0]])
    cam_from_world = np.column_stack([np.eye(3), [0.0, 0.0, 3.0]])  # at (0, 0, -3) looking down +z
    pos = np.full((64, 64, 3), 0.75, np.float32)
    neg = np.full((64, 64, 3), 0.25, np.float32)
    ratios, normals = sphere_samples(pos, neg, K, cam_from_world, np.zeros(3), 0.5, erode_px=2)
    assert ratios.shape == normals.shape and ratios.shape[1] == 3 and len(ratios) > 100
    np.testing.assert_allclose(ratios, 0.5, atol=1e-6)  # (0.75 - 0.25) / (0.75 + 0.25)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    assert np.all(normals[:, 2] < 0)  # the visible half faces the camera (-z)
    # unlit pixels are left out
    dark = pos.copy()
    dark[:32] = 0.0
    few, _ = sphere_samples(dark, np.zeros_like(neg), K, cam_from_world, np.zeros(3), 0.5, erode_px=2)
    assert 0 < len(few) < len(ratios)
