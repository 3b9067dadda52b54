"""Normals with the specular reflection modelled out (stages.numerics.specular_normals)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from stages.numerics.materials import shade_stage_illuminations
from stages.numerics.metrics import angular_error_deg
from stages.numerics.specular_normals import fit_diffuse_normals, view_directions, white_light_specular

torch.set_num_threads(1)


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def scene(rng, size=(8, 10), roughness=0.5, f0=0.04, white=(0.5, 0.45, 0.4)):
    """Pixels of a glossy surface under the stage's gradients: normals within 50 deg of the view, views
    spread around +z, random albedo. Returns frames in decoded units and the truth."""
    h, w = size
    views = unit(rng.normal([0, 0, 1], 0.3, (h * w, 3)))
    normals = unit(views + rng.normal(0, 0.35, (h * w, 3)))
    normals = np.where(((normals * views).sum(-1) > 0.35)[:, None], normals, views)
    albedo = rng.uniform(0.1, 0.8, (h * w, 3))
    shaded = shade_stage_illuminations(normals, views, albedo, np.full(h * w, roughness), f0=f0,
                                       specular_model="ggx_table")  # (N, 3 illum, 3 rgb) white units
    white = np.asarray(white, np.float32)
    frames = (shaded * white).reshape(h, w, 3, 3).astype(np.float32)
    return {"full_on": frames[:, :, 0], "pos": frames[:, :, 1], "neg": frames[:, :, 2], "white": white,
            "views": views.reshape(h, w, 3).astype(np.float32), "normals": normals.reshape(h, w, 3),
            "albedo": albedo.reshape(h, w, 3)}


def eq1(pos, neg):
    d = (pos - neg) / np.maximum(pos + neg, 1e-9)
    return unit(d).astype(np.float32)


def test_view_directions_hand_computed():
    K = np.array([[100.0, 0, 4.0], [0, 100.0, 3.0], [0, 0, 1]])
    identity = np.hstack([np.eye(3), np.zeros((3, 1))])
    views = view_directions(K, identity, 7, 9)
    assert views.shape == (7, 9, 3) and views.dtype == np.float32
    np.testing.assert_allclose(views[3, 4], [0, 0, -1], atol=1e-7)  # principal point: back along -z
    np.testing.assert_allclose(views[3, 8], unit([-0.04, 0, -1]), atol=1e-6)  # 4 px right of it
    # a camera rotated 180 deg about y looks along -z in the world: its view directions point to +z
    turned = np.hstack([np.diag([-1.0, 1.0, -1.0]), np.zeros((3, 1))])
    np.testing.assert_allclose(view_directions(K, turned, 7, 9)[3, 4], [0, 0, 1], atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(views, axis=-1), 1.0, atol=1e-6)


def test_view_directions_rejects_bad_cameras():
    with pytest.raises(ValueError, match="focal"):
        view_directions(np.zeros((3, 3)), np.eye(4), 4, 4)
    with pytest.raises(ValueError, match="must be"):
        view_directions(np.eye(3), np.eye(3), 4, 4)
    with pytest.raises(ValueError, match="size"):
        view_directions(np.eye(3), np.eye(4), 0, 4)


def test_fit_recovers_normals_that_eq1_gets_wrong():
    rng = np.random.default_rng(0)
    s = scene(rng)
    pixels = np.ones(s["pos"].shape[:2], bool)
    before = angular_error_deg(eq1(s["pos"], s["neg"]), s["normals"])
    fit = fit_diffuse_normals(s["pos"], s["neg"], s["white"], s["views"], eq1(s["pos"], s["neg"]), pixels,
                              roughness=0.5, f0=0.04, steps=150)
    after = angular_error_deg(fit.normals, s["normals"])
    assert before.mean() > 2.0  # the specular reflection bends eq. 1's normals by degrees
    assert after.mean() < 0.5 and np.percentile(after, 95) < 1.5
    np.testing.assert_allclose(fit.albedo, s["albedo"], atol=0.02)
    # the returned specular parts leave the Lambertian frames: eq. 1 on them is the true normal
    lambert = eq1(s["pos"] - fit.specular_pos, s["neg"] - fit.specular_neg)
    assert angular_error_deg(lambert, s["normals"]).mean() < 0.5
    np.testing.assert_allclose(s["full_on"] - fit.specular_full, s["albedo"] * s["white"], atol=0.01)
    assert fit.residual.max() < 1e-3


def test_fit_of_a_lambertian_surface_keeps_eq1():
    rng = np.random.default_rng(1)
    s = scene(rng, f0=0.0, roughness=1.0)  # f0 = 0 still leaves Schlick's grazing term: keep views frontal
    lam = eq1(s["pos"], s["neg"])
    fit = fit_diffuse_normals(s["pos"], s["neg"], s["white"], s["views"], lam, np.ones(lam.shape[:2], bool),
                              roughness=1.0, f0=0.0)
    assert angular_error_deg(fit.normals, s["normals"]).mean() < 0.5


def test_only_the_given_pixels_are_fitted_and_bad_values_stay_finite():
    rng = np.random.default_rng(2)
    s = scene(rng, size=(5, 6))
    pos, neg = s["pos"].copy(), s["neg"].copy()
    pos[0, 0] = np.nan
    neg[0, 1] = np.inf
    pos[0, 2] = neg[0, 2] = 0.0  # black pixel
    pixels = np.ones(pos.shape[:2], bool)
    pixels[4] = False
    init = eq1(s["pos"], s["neg"])
    init[1, 1] = 0.0  # undefined start: begins at the view
    fit = fit_diffuse_normals(pos, neg, s["white"], s["views"], init, pixels, steps=20)
    for name in ("normals", "albedo", "specular_pos", "specular_neg", "specular_full", "residual"):
        arr = getattr(fit, name)
        assert np.all(np.isfinite(arr)), name
        assert not np.any(arr[4]), f"{name} written outside the pixels"
    np.testing.assert_allclose(np.linalg.norm(fit.normals[:4], axis=-1), 1.0, atol=1e-5)


def test_chunks_give_the_same_result():
    rng = np.random.default_rng(3)
    s = scene(rng, size=(4, 5))
    args = (s["pos"], s["neg"], s["white"], s["views"], eq1(s["pos"], s["neg"]), np.ones((4, 5), bool))
    whole = fit_diffuse_normals(*args, steps=30)
    chunked = fit_diffuse_normals(*args, steps=30, chunk=7)
    np.testing.assert_allclose(whole.normals, chunked.normals, atol=1e-5)


def test_levenberg_marquardt_reaches_adams_fit_in_fewer_steps():
    rng = np.random.default_rng(5)
    s = scene(rng, size=(10, 12), roughness=0.35)
    args = (s["pos"], s["neg"], s["white"], s["views"], eq1(s["pos"], s["neg"]), np.ones((10, 12), bool))
    lm = fit_diffuse_normals(*args, roughness=0.35, solver="levenberg_marquardt", steps=6)
    adam = fit_diffuse_normals(*args, roughness=0.35, solver="adam", steps=40)
    lm_err = angular_error_deg(lm.normals, s["normals"])
    adam_err = angular_error_deg(adam.normals, s["normals"])
    assert lm_err.mean() < 0.5 and lm_err.mean() <= adam_err.mean() + 0.05
    # it descends: no pixel ends worse than where eq. 1 started it, and most reach the noise-free optimum
    start = fit_diffuse_normals(*args, roughness=0.35, steps=0)
    assert np.all(lm.residual <= start.residual + 1e-7)
    assert np.mean(lm.residual < 1e-6) > 0.9
    with pytest.raises(ValueError, match="solver"):
        fit_diffuse_normals(*args, solver="newton")


def test_input_checks():
    rng = np.random.default_rng(4)
    s = scene(rng, size=(3, 3))
    ok = (s["pos"], s["neg"], s["white"], s["views"], eq1(s["pos"], s["neg"]), np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="neg"):
        fit_diffuse_normals(ok[0], ok[1][:2], *ok[2:])
    with pytest.raises(ValueError, match="pixels"):
        fit_diffuse_normals(*ok[:5], np.ones((2, 3), bool))
    with pytest.raises(ValueError, match="white_reference"):
        fit_diffuse_normals(ok[0], ok[1], [1.0, 0.0, 1.0], *ok[3:])
    with pytest.raises(ValueError, match="f0"):
        fit_diffuse_normals(*ok, f0=2.0)


def test_white_light_specular_of_a_mirror_is_schlicks_fresnel():
    # a near-mirror (the fit's smallest roughness) at n.v = 1, 0.5 and 0.2: f0 + (1 - f0)(1 - n.v)^5
    cos = np.array([1.0, 0.5, 0.2])
    views = np.stack([np.sqrt(1 - cos ** 2), np.zeros(3), cos], -1).reshape(1, 3, 3).astype(np.float32)
    normals = np.tile(np.array([0, 0, 1], np.float32), (1, 3, 1))
    spec = white_light_specular(normals, views, 0.05, f0=0.04)
    assert spec.shape == (1, 3, 3) and spec.dtype == np.float32
    np.testing.assert_allclose(spec[0, :, 0], 0.04 + 0.96 * (1 - cos) ** 5, rtol=0.02)
    assert np.all(spec[..., 0] == spec[..., 2])  # the white light is white
    # rougher lobes spread: less at grazing than the mirror, and f0 scales it
    rough = white_light_specular(normals, views, 0.6, f0=0.04)
    assert rough[0, 2, 0] < spec[0, 2, 0]
    assert np.all(white_light_specular(normals, views, 0.6, f0=0.02) < rough)


def test_white_light_specular_is_what_the_fit_took_out():
    rng = np.random.default_rng(3)
    s = scene(rng)
    pixels = np.ones(s["pos"].shape[:2], bool)
    fit = fit_diffuse_normals(s["pos"], s["neg"], s["white"], s["views"], eq1(s["pos"], s["neg"]), pixels,
                              roughness=0.5, f0=0.04)
    spec = white_light_specular(fit.normals, s["views"], 0.5, f0=0.04)
    np.testing.assert_allclose(spec * s["white"], fit.specular_full, atol=1e-5)
    # so the white-light albedo less it is the diffuse albedo
    np.testing.assert_allclose(s["full_on"] / s["white"] - spec, s["albedo"], atol=0.02)


def test_white_light_specular_undefined_normals_and_checks():
    normals = np.zeros((2, 2, 3), np.float32)
    normals[0, 0] = (0, 0, 1)
    normals[1, 1] = np.nan
    views = np.tile(np.array([0, 0, 1], np.float32), (2, 2, 1))
    spec = white_light_specular(normals, views, np.full((2, 2), 0.5, np.float32), f0=0.04, chunk=1)
    assert spec[0, 0, 0] > 0 and np.all(spec[0, 1] == 0) and np.all(spec[1] == 0) and np.all(np.isfinite(spec))
    with pytest.raises(ValueError, match="view_dirs"):
        white_light_specular(normals, views[:1], 0.5, f0=0.04)
    with pytest.raises(ValueError, match="roughness"):
        white_light_specular(normals, views, np.nan, f0=0.04)
    with pytest.raises(ValueError, match="f0"):
        white_light_specular(normals, views, 0.5, f0=1.5)
