"""Stage-illumination shading in closed form and the per-point roughness fit (stages.numerics.materials),
including checks against the simulator's own GGX shading under the 512-LED sphere."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stages.numerics import materials, sg
from stages.numerics.materials import (
    NO_VIEWS_RESIDUAL,
    STAGE_COEFFICIENTS,
    fit_roughness,
    shade_stage_illuminations,
    stage_diffuse,
)

torch.set_num_threads(1)


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_views(normals, per_point, max_deg, rng):
    """(P, V, 3) unit views within max_deg of each normal."""
    out = np.zeros((len(normals), per_point, 3))
    cos_min = math.cos(math.radians(max_deg))
    for p, n in enumerate(normals):
        k = 0
        while k < per_point:
            v = unit(rng.normal(size=3))
            if v @ n > cos_min:
                out[p, k] = v
                k += 1
    return out


def simulator_shading(normals, views, albedo, roughness, f0=0.02):
    """The simulator's radiance (N, 3 illum, 3 rgb) of unoccluded points: Lambert + GGX summed over the
    512 LEDs of synthetic.rig (ideal gains), with synthetic.shading.ggx_weights."""
    from synthetic import geometry, rig, shading

    leds = rig.LedSphere(geometry.fibonacci_sphere(512), np.ones((512, 3)), 1.6)
    irradiance = leds.irradiance.astype(np.float64)
    cos = np.maximum(normals @ leds.directions.T, 0.0)
    diffuse = (np.tile(albedo / np.pi, 3) * (cos @ irradiance)).reshape(-1, 3, 3)
    weights = shading.ggx_weights(normals.astype(np.float32), views.astype(np.float32),
                                  leds.directions.astype(np.float32), (roughness ** 2).astype(np.float32),
                                  np.full(len(normals), f0, np.float32))
    return diffuse, (weights.astype(np.float64) @ irradiance).reshape(-1, 3, 3)


# ------------------------------------------------------------------------------------------ forward


def test_stage_diffuse_hand_computed():
    normals = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    albedo = np.array([[0.5, 0.4, 0.3], [0.2, 0.2, 0.2]])
    out = stage_diffuse(normals, albedo)
    assert out.shape == (2, 3, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out[:, 0], albedo, rtol=1e-6)  # full_on: radiance = albedo
    # pos_c = albedo_c (1/2 + n_c / 3), neg_c = albedo_c (1/2 - n_c / 3)
    np.testing.assert_allclose(out[0, 1], [0.5 * (0.5 + 1 / 3), 0.4 * 0.5, 0.3 * 0.5], rtol=1e-6)
    np.testing.assert_allclose(out[1, 2], [0.2 * 0.5, 0.2 * (0.5 - 0.2), 0.2 * (0.5 - 0.8 / 3)], rtol=1e-6)
    # the gradient ratio of eq. 1: (pos - neg) / (pos + neg) = (2/3) n
    ratio = (out[:, 1] - out[:, 2]) / (out[:, 1] + out[:, 2])
    np.testing.assert_allclose(ratio, (2 / 3) * normals, atol=1e-6)


@pytest.mark.parametrize("model", ["sg", "ggx_table"])
def test_shade_stage_linearity_shapes_and_gradients(model):
    rng = np.random.default_rng(0)
    normals = unit(rng.normal(size=(20, 3)))
    views = random_views(normals, 1, 70, rng)[:, 0]
    albedo = rng.uniform(0.1, 0.8, (20, 3))
    rough = rng.uniform(0.1, 1.0, 20)
    out = shade_stage_illuminations(normals, views, albedo, rough, specular_model=model)
    assert out.shape == (20, 3, 3) and out.dtype == np.float32 and np.isfinite(out).all()
    # pos + neg = full_on for any linear model of the light (the illuminations sum to full_on)
    np.testing.assert_allclose(out[:, 1] + out[:, 2], out[:, 0], rtol=1e-5, atol=1e-7)
    diffuse = shade_stage_illuminations(normals, views, albedo, rough, specular=False)
    np.testing.assert_allclose(diffuse, stage_diffuse(normals, albedo), rtol=1e-6)
    spec = out - diffuse
    assert spec[:, 0].min() >= 0 and spec[:, 0].max() > 1e-3
    # specular vanishes for a camera below the horizon
    below = shade_stage_illuminations(normals, -views, albedo, rough, specular_model=model)
    np.testing.assert_allclose(below, diffuse, atol=1e-7)
    # differentiable in roughness, finite
    r = torch.tensor(rough, dtype=torch.float32, requires_grad=True)
    shade_stage_illuminations(torch.as_tensor(normals), views, albedo, r, specular_model=model).sum().backward()
    assert torch.isfinite(r.grad).all() and r.grad.abs().max() > 0
    with pytest.raises(ValueError, match="specular_model"):
        shade_stage_illuminations(normals, views, albedo, rough, specular_model="phong")
    with pytest.raises(ValueError, match="roughness"):
        shade_stage_illuminations(normals, views, albedo, rough[:3])


def test_first_moment_table_limits():
    p, q = materials._clipped_mean(torch.tensor([1e-3, 1e-3, 5e3, 5e3]), torch.tensor([0.3, -0.5, 0.6, 1.0]))
    # a uniform lobe: the cosine-weighted mean over the hemisphere is (2/3) n
    np.testing.assert_allclose(p[:2].numpy(), [2 / 3, 2 / 3], atol=2e-3)
    np.testing.assert_allclose(q[:2].numpy(), [0, 0], atol=2e-3)
    # a sharp lobe above the horizon: its own axis (p, q) = (cos beta, sin beta)
    np.testing.assert_allclose(p[2:].numpy(), [0.6, 1.0], atol=3e-3)
    np.testing.assert_allclose(q[2:].numpy(), [0.8, 0.0], atol=3e-3)


def test_sg_closed_form_matches_quadrature_of_its_lobes():
    """The closed form integrates the SG lobes against (a + b.w) max(0, n.w); by quadrature of the same
    lobes it is within 1% (zeroth moment: the SG-cosine approximation; first: the table)."""
    rng = np.random.default_rng(3)
    normals = unit(rng.normal(size=(16, 3)))
    views = random_views(normals, 1, 70, rng)[:, 0]
    rough = rng.uniform(0.3, 0.9, 16)
    axis, sharp, weight = (x.numpy().astype(np.float64) for x in sg.ggx_sg_lobe(
        torch.tensor(normals, dtype=torch.float32), torch.tensor(views, dtype=torch.float32),
        torch.tensor(rough, dtype=torch.float32), 0.02, "smith", 3))
    h = 128
    dirs = sg.equirect_directions(h, 2 * h).reshape(-1, 3).astype(np.float64)
    solid = sg.equirect_solid_angles(h, 2 * h).reshape(-1).astype(np.float64)
    a, b = STAGE_COEFFICIENTS
    light = (a[None] + np.einsum("ick,tk->tic", b, dirs)).reshape(len(dirs), 9)
    lobe = sum(weight[:, k:k + 1] * np.exp(sharp[:, k:k + 1] * (axis @ dirs.T - 1)) for k in range(3))
    lobe *= np.maximum(normals @ dirs.T, 0.0)
    expected = ((lobe * solid) @ light).reshape(-1, 3, 3)
    got = shade_stage_illuminations(normals, views, np.zeros((16, 3)), rough)
    np.testing.assert_allclose(got, expected, rtol=0.03, atol=0.01 * expected.max())
    gradient_rel = np.linalg.norm((got[:, 1] - got[:, 2]) - (expected[:, 1] - expected[:, 2]), axis=1) \
        / np.linalg.norm(expected[:, 1] - expected[:, 2], axis=1)
    assert np.median(gradient_rel) < 0.02


def test_against_the_simulator_shading():
    """Real physics: the simulator's per-LED GGX (height-correlated Smith, Schlick) under 512 LEDs.
    Measured (300 points, views within 60 degrees): diffuse 0.08%; the GGX table 0.1% (r >= 0.45);
    SG lobes 7-10% median (pos - neg specular 13-15%)."""
    rng = np.random.default_rng(0)
    normals = unit(rng.normal(size=(60, 3)))
    views = random_views(normals, 1, 60, rng)[:, 0]
    albedo = rng.uniform(0.1, 0.8, (60, 3))
    for r in (0.45, 0.7):
        rough = np.full(60, r)
        sim_d, sim_s = simulator_shading(normals, views, albedo, rough)
        diffuse = shade_stage_illuminations(normals, views, albedo, rough, specular=False)
        np.testing.assert_allclose(diffuse, sim_d, rtol=3e-3, atol=1e-4)
        for model, tol in (("ggx_table", 0.01), ("sg", 0.2)):
            spec = shade_stage_illuminations(normals, views, albedo, rough, specular_model=model) - diffuse
            rel = np.abs(spec.sum(axis=(1, 2)) - sim_s.sum(axis=(1, 2))) / sim_s.sum(axis=(1, 2))
            assert np.median(rel) < tol, (model, r, np.median(rel))
            grad = np.linalg.norm((spec[:, 1] - spec[:, 2]) - (sim_s[:, 1] - sim_s[:, 2]), axis=1) \
                / np.linalg.norm(sim_s[:, 1] - sim_s[:, 2], axis=1)
            assert np.median(grad) < tol, (model, r, np.median(grad))


# ------------------------------------------------------------------------------------------ fitting


def _scene(points, views_per_point, seed=0, max_deg=60):
    rng = np.random.default_rng(seed)
    normals = unit(rng.normal(size=(points, 3)))
    views = random_views(normals, views_per_point, max_deg, rng)
    albedo = rng.uniform(0.1, 0.7, (points, 3))
    rough = rng.uniform(0.3, 0.9, points)
    return rng, normals, views, albedo, rough


def _render(normals, views, albedo, rough, model="ggx_table"):
    return np.stack([shade_stage_illuminations(normals, views[:, v], albedo, rough, specular_model=model)
                     for v in range(views.shape[1])], axis=1)


@pytest.mark.parametrize("model", ["sg", "ggx_table"])
def test_fit_roughness_recovers_forward_model_with_noise(model):
    rng, normals, views, albedo, rough = _scene(150, 8)
    white = np.array([[0.8, 0.9, 0.7]] * 8) * rng.uniform(0.9, 1.1, (8, 1))  # per-view white references
    observed = _render(normals, views, albedo, rough, model) * white[None, :, None, :]
    exact, residual = fit_roughness(observed, views, np.ones((150, 8), bool), normals, albedo, white,
                                    specular_model=model)
    assert exact.shape == (150,) and exact.dtype == np.float32 and residual.dtype == np.float32
    assert np.abs(exact - rough).max() < 0.01 and residual.max() < 1e-4  # noise-free: exact
    noisy = observed + 0.002 * rng.normal(size=observed.shape)  # ~0.5% of a mid-grey pixel
    fitted, residual = fit_roughness(noisy, views, np.ones((150, 8), bool), normals, albedo, white,
                                     specular_model=model)
    assert np.abs(fitted - rough).mean() < 0.03
    assert np.all((fitted >= 0.05) & (fitted <= 1.0))
    np.testing.assert_allclose(np.median(residual), 0.002 / 0.85, rtol=0.3)  # the noise in white units


def test_fit_roughness_real_physics_simulator_observations():
    """Observations rendered by the simulator's own shading (512 LEDs, per-LED GGX): roughness recovered
    with the GGX table to MAE ~0.01 for r in [0.3, 0.9] (the SG lobes: 0.10-0.15)."""
    rng, normals, views, albedo, rough = _scene(120, 8, seed=5)
    observed = np.stack([sum(simulator_shading(normals, views[:, v], albedo, rough)) for v in range(8)], axis=1)
    observed += 0.001 * rng.normal(size=observed.shape)
    fitted, _ = fit_roughness(observed, views, np.ones((120, 8), bool), normals, albedo)
    assert np.abs(fitted - rough).mean() < 0.03


def test_fit_roughness_invalid_views_fallback_and_albedo_option():
    rng, normals, views, albedo, rough = _scene(40, 6, seed=2)
    observed = _render(normals, views, albedo, rough)
    valid = np.ones((40, 6), bool)
    valid[:5] = False  # no valid view
    valid[5:10, :3] = False  # half the views
    observed[5:10, :3] = 1e3  # garbage where invalid
    observed[10, 0, 0, 0] = np.nan  # a non-finite sample counts as invalid
    fitted, residual = fit_roughness(observed, views, valid, normals, albedo)
    assert np.all(residual[:5] == NO_VIEWS_RESIDUAL) and np.all(residual[5:] >= 0)
    np.testing.assert_allclose(fitted[:5], np.median(fitted[5:]), rtol=1e-6)  # documented fallback
    assert np.abs(fitted[5:] - rough[5:]).max() < 0.01
    fixed, _ = fit_roughness(observed, views, valid, normals, albedo, fallback_roughness=0.6)
    np.testing.assert_allclose(fixed[:5], 0.6)
    # an albedo 20% too bright: biased with the albedo fixed, recovered with fit_albedo
    biased, _ = fit_roughness(observed, views, valid, normals, albedo * 1.2)
    solved, _ = fit_roughness(observed, views, valid, normals, albedo * 1.2, fit_albedo=True)
    assert np.abs(solved[5:] - rough[5:]).mean() < 0.01 < np.abs(biased[5:] - rough[5:]).mean()
    # return_albedo: the solved diffuse albedo is the true one whatever albedo was passed in; the input
    # albedo comes back where no view is valid, and everywhere when the albedo is fixed
    _, _, albedo_solved = fit_roughness(observed, views, valid, normals, albedo * 1.2, fit_albedo=True,
                                        return_albedo=True)
    assert albedo_solved.shape == (40, 3) and albedo_solved.dtype == np.float32
    np.testing.assert_allclose(albedo_solved[5:], albedo[5:], atol=2e-3)
    np.testing.assert_allclose(albedo_solved[:5], albedo[:5] * 1.2, rtol=1e-6)
    _, _, albedo_fixed = fit_roughness(observed, views, valid, normals, albedo, return_albedo=True)
    np.testing.assert_allclose(albedo_fixed, albedo, rtol=1e-6)


def test_fit_roughness_input_checks():
    _, normals, views, albedo, rough = _scene(4, 2)
    observed = _render(normals, views, albedo, rough)
    valid = np.ones((4, 2), bool)
    with pytest.raises(ValueError, match="observed"):
        fit_roughness(observed[..., :2], views, valid, normals, albedo)
    with pytest.raises(ValueError, match="valid"):
        fit_roughness(observed, views, valid[:, :1], normals, albedo)
    with pytest.raises(ValueError, match="white_scale"):
        fit_roughness(observed, views, valid, normals, albedo, white_scale=np.ones(2))
    with pytest.raises(ValueError, match="white_scale"):
        fit_roughness(observed, views, valid, normals, albedo, white_scale=0.0)
    with pytest.raises(ValueError, match="r_min"):
        fit_roughness(observed, views, valid, normals, albedo, r_min=0.5, r_max=0.4)


def _floor_and_wall():
    """A 2 m floor (z = 0) and a wall 1 m high at x = 0.1 (facing -x), as one mesh's ray-casting scene."""
    from stages.numerics.raycast import mesh_scene

    vertices = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0],
                         [0.1, -1, 0], [0.1, 1, 0], [0.1, 1, 1], [0.1, -1, 1]], np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    return mesh_scene(vertices, faces)


def test_mirror_cone_open_by_hand():
    """A point on the floor at the origin, normal +z, a wall at x = 0.1. A camera up on the +x side mirrors
    towards -x (open); one up on the -x side mirrors into the wall (shut); a camera 5 degrees above the +x
    horizon mirrors 5 degrees above the -x horizon, away from the wall: open with the axis alone, shut with a
    15-degree cone, which dips under the floor's horizon; views not valid are not traced (False)."""
    from stages.numerics.material_textures import mirror_cone_open

    scene = _floor_and_wall()
    s, c = np.sin(np.radians(5.0)), np.cos(np.radians(5.0))
    views = np.array([[[1, 0, 1], [-1, 0, 1], [c, 0, s], [1, 0, 1]]], np.float64)
    views /= np.linalg.norm(views, axis=-1, keepdims=True)
    points, normals = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    valid = np.array([[True, True, True, False]])
    axis_only = mirror_cone_open(points, normals, views, valid, scene, 0.0)
    cone = mirror_cone_open(points, normals, views, valid, scene, 15.0)
    assert axis_only.shape == (1, 4) and axis_only.dtype == bool
    assert axis_only.tolist() == [[True, False, True, False]]
    assert cone.tolist() == [[True, False, False, False]]
    with pytest.raises(ValueError, match="cone_deg"):
        mirror_cone_open(points, normals, views, valid, scene, 90.0)
    with pytest.raises(ValueError, match="view_dirs"):
        mirror_cone_open(points, normals, views[:, :2], valid, scene, 15.0)
