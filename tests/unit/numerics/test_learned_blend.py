"""Tests of stages.numerics.learned_blend on analytic spheres: the untrained network is the heuristic blend,
training lowers the leave-one-out loss where one source is corrupt, and the reprojection uses the weights."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from stages.numerics.gbuffer import SourceView, reproject_gbuffer, source_candidates
from stages.numerics.learned_blend import (BlendNet, LearnedBlend, LearnedBlendConfig, candidate_features,
                                           fit_learned_blend)

from tests.unit.numerics.test_gbuffer import K, MAIN, interior, render_spheres, ring_camera, source_from

RING = (-50.0, -30.0, -10.0, 10.0, 30.0, 50.0)


@pytest.fixture(scope="module")
def ring_sources():
    return [source_from(ring_camera(a, height=0.3 * np.sin(np.radians(3 * a))), [MAIN]) for a in RING]


def test_candidate_features_shapes_and_prior(ring_sources):
    target = ring_sources[2]
    cand = source_candidates(target.depth_m, target.K, target.cam_from_world, ring_sources[:2] + ring_sources[3:], k=4,
                             depth_tolerance_m=0.05)
    n = len(cand["rows"])
    assert n == int((target.depth_m > 0).sum()) and cand["albedo"].shape == (n, 4, 3)
    feats = candidate_features(cand)
    assert feats["features"].shape == (n, 4, 8) and feats["prior"].shape == (n, 4)
    assert torch.isfinite(feats["features"]).all()
    seen = feats["visible"].any(1)
    assert torch.allclose(feats["prior"][seen].sum(1), torch.ones(int(seen.sum())), atol=1e-5)


def test_untrained_network_is_the_heuristic_blend(ring_sources):
    """The last layer starts at zero: the learned blend reproduces reproject_gbuffer's heuristic maps."""
    target = ring_sources[2]
    others = ring_sources[:2] + ring_sources[3:]
    blend = LearnedBlend(BlendNet(16), LearnedBlendConfig(), {})
    a = reproject_gbuffer(target.depth_m, K, target.cam_from_world, others, k=4, depth_tolerance_m=0.05)
    b = reproject_gbuffer(target.depth_m, K, target.cam_from_world, others, k=4, depth_tolerance_m=0.05, blend=blend)
    assert np.array_equal(a["valid"], b["valid"]) and np.array_equal(a["view_count"], b["view_count"])
    np.testing.assert_allclose(b["albedo"], a["albedo"], atol=1e-5)
    np.testing.assert_allclose(b["normal"], a["normal"], atol=1e-5)
    np.testing.assert_allclose(b["weight"], a["weight"], rtol=1e-5, atol=1e-9)


def test_training_learns_to_ignore_a_corrupt_source(ring_sources):
    """One source's albedo is wrong by +0.5 everywhere: the heuristic blends it in, the trained network
    learns (from the disagreement features) to drop it, on the training views and on a new view."""
    corrupt = 1
    views = [SourceView(normal=s.normal, albedo=(s.albedo + 0.5).astype(np.float32) if i == corrupt else s.albedo,
                        valid=s.valid, K=s.K, cam_from_world=s.cam_from_world, depth_m=s.depth_m)
             for i, s in enumerate(ring_sources)]
    cfg = LearnedBlendConfig(hidden_width=16, steps=150, batch_pixels=2048, pixels_per_view=3000, seed=1)
    blend = fit_learned_blend(views, cfg, k=3, depth_tolerance_m=0.05)
    rec = blend.record
    assert rec["views"] == len(views) and rec["pixels"] > 1000
    assert rec["learned_loss"] < 0.8 * rec["heuristic_loss"]
    # a new view between the corrupt source and its neighbour
    target_P = ring_camera(-20.0, height=0.1)
    target = render_spheres(target_P, [MAIN])
    inner = interior(target["hit"])
    base = reproject_gbuffer(target["depth_m"], K, target_P, views, k=3, depth_tolerance_m=0.05)
    learned = reproject_gbuffer(target["depth_m"], K, target_P, views, k=3, depth_tolerance_m=0.05, blend=blend)
    err_base = np.abs(base["albedo"] - target["albedo"])[inner & base["valid"]].mean()
    err_learned = np.abs(learned["albedo"] - target["albedo"])[inner & learned["valid"]].mean()
    assert err_base > 0.1  # the corrupt source carries a large share of the heuristic weight here
    assert err_learned < 0.5 * err_base
    for key in ("albedo", "normal", "weight"):
        assert np.all(np.isfinite(learned[key]))


def test_fit_input_checks(ring_sources):
    with pytest.raises(ValueError, match="at least 3"):
        fit_learned_blend(ring_sources[:2])
    with pytest.raises(ValueError, match="steps"):
        LearnedBlendConfig(steps=0)
    with pytest.raises(ValueError, match="learning_rate"):
        LearnedBlendConfig(learning_rate=0.0)
