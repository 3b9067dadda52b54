"""Occlusion by a mesh: ambient occlusion, direction visibility, SG shading with shadows
(stages.numerics.shadowing)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stages.numerics import sg
from stages.numerics.raycast import mesh_scene, render_mesh
from stages.numerics.shadowing import (ambient_occlusion, deocclude_normals, deocclude_view, default_sharpness_cap,
                                       direction_visibility, shade_sg_visible)

torch.set_num_threads(1)
THREADS = 1


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def sphere(radius=1.0, resolution=20):
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def box(lo, hi):
    """Closed axis-aligned box (12 triangles)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))]
    return corners, np.array(faces)


def disc(radius, height, segments=256):
    """Horizontal disc (fan) of ``radius`` centred on the +y axis at ``height``."""
    angle = np.arange(segments) * (2 * math.pi / segments)
    rim = np.stack([radius * np.cos(angle), np.full(segments, height), radius * np.sin(angle)], axis=1)
    vertices = np.concatenate([[[0.0, height, 0.0]], rim])
    faces = np.stack([np.zeros(segments, int), 1 + np.arange(segments), 1 + (np.arange(segments) + 1) % segments], 1)
    return vertices, faces


def wall(x=0.1, size=1e3):
    """The plane x = ``x`` as one huge quad (nearly an infinite wall)."""
    vertices = np.array([[x, -1.0, -size], [x, size, -size], [x, size, size], [x, -1.0, size]])
    return vertices, np.array([[0, 1, 2], [0, 2, 3]])


def origin_up(n):
    return np.zeros((n, 3)), np.tile([0.0, 1.0, 0.0], (n, 1))


# ------------------------------------------------------------------------------------ ambient occlusion


def test_ao_convex_sphere_is_unoccluded():
    vertices, faces = sphere(1.0, 20)
    scene = mesh_scene(vertices, faces)
    tri = vertices[faces]
    face_normals = unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    face_normals *= np.sign((face_normals * tri.mean(1)).sum(1))[:, None]  # outward
    # vertices with radial normals (a supporting plane of the inscribed polyhedron) and face centroids
    points = np.concatenate([vertices, tri.mean(1)])
    normals = np.concatenate([unit(vertices), face_normals])
    ao = ambient_occlusion(points, normals, scene, rays=32, threads=THREADS)
    assert ao.shape == (len(points),) and ao.dtype == np.float32
    np.testing.assert_array_equal(ao, 1.0)
    # the same points facing inwards see the inside of the closed sphere: fully occluded
    np.testing.assert_array_equal(ambient_occlusion(points, -normals, scene, rays=32, threads=THREADS), 0.0)


def test_ao_closed_box_floor_is_zero():
    scene = mesh_scene(*box([-1, 0, -1], [1, 1, 1]))
    points, normals = origin_up(10)
    np.testing.assert_array_equal(ambient_occlusion(points, normals, scene, rays=16, threads=THREADS), 0.0)


@pytest.mark.parametrize("radius,height,rays", [(1.0, 1.0, 64), (0.5, 1.0, 36), (0.5, 1.0, 37), (2.0, 1.0, 16)])
def test_ao_under_a_disc_matches_the_solid_angle(radius, height, rays):
    """A disc of radius a at height h above a point hides the cone theta < atan(a / h): its cosine-weighted
    share is sin^2(theta_max) = a^2 / (a^2 + h^2), so AO = h^2 / (a^2 + h^2)."""
    scene = mesh_scene(*disc(radius, height))
    points, normals = origin_up(400)
    ao = ambient_occlusion(points, normals, scene, rays=rays, seed=3, threads=THREADS)
    expected = height ** 2 / (radius ** 2 + height ** 2)
    assert abs(float(ao.mean()) - expected) < 0.01
    # per point: stratified over sin^2(theta) the spread is well below plain Monte Carlo's
    # sqrt(p (1 - p) / R) (measured 0.05x at 64 rays, 0.4x at 36); 37 rays (prime) only stratify the azimuth
    plain = math.sqrt(expected * (1 - expected) / rays)
    assert float(ao.std()) < (1.3 if rays == 37 else 0.6) * plain


def test_ao_beside_an_infinite_wall_is_one_half():
    scene = mesh_scene(*wall(0.05))
    points, normals = origin_up(500)
    ao = ambient_occlusion(points, normals, scene, rays=64, threads=THREADS)
    assert abs(float(ao.mean()) - 0.5) < 0.01
    assert np.all((ao > 0.3) & (ao < 0.7))


def test_ao_deterministic_and_chunk_independent():
    scene = mesh_scene(*disc(1.0, 1.0))
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-0.5, 0.5, 50), np.zeros(50), rng.uniform(-0.5, 0.5, 50)]
    normals = unit(np.c_[rng.normal(0, 0.3, 50), np.ones(50), rng.normal(0, 0.3, 50)])
    a = ambient_occlusion(points, normals, scene, rays=16, seed=1, threads=THREADS)
    b = ambient_occlusion(points, normals, scene, rays=16, seed=1, chunk=7, threads=THREADS)
    c = ambient_occlusion(points, normals, scene, rays=16, seed=2, threads=THREADS)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.all((a >= 0) & (a <= 1))


# --------------------------------------------------------------------------------- direction visibility


def test_direction_visibility_under_a_disc():
    scene = mesh_scene(*disc(0.5, 1.0))  # hides the cone of atan(0.5) = 26.6 degrees around +y
    c, s = math.cos(math.radians(10)), math.sin(math.radians(10))
    directions = np.array([[0, 1, 0], [s, c, 0], [1, 1, 0], [1, 0, 0], [0, -1, 0], [0, -1, 1], [2, 0.1, 0]])
    points = np.zeros((2, 3))
    normals = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    vis = direction_visibility(points, normals, scene, directions, threads=THREADS)
    assert vis.shape == (2, 7) and vis.dtype == bool
    np.testing.assert_array_equal(vis[0], [False, False, True, False, False, False, True])
    # facing down: only the lower hemisphere counts, and nothing is there
    np.testing.assert_array_equal(vis[1], [False, False, False, False, True, True, False])


def test_direction_visibility_agrees_with_ao():
    scene = mesh_scene(*disc(1.0, 1.0))
    directions = sg.fibonacci_sphere(2048)
    points, normals = origin_up(3)
    vis = direction_visibility(points, normals, scene, directions, chunk=2, threads=THREADS)
    cos = np.maximum(directions @ normals[0], 0)
    fraction = (vis * cos).sum(1) / cos.sum()
    np.testing.assert_allclose(fraction, 0.5, atol=0.01)


# ------------------------------------------------------------------------------------------ shading


def _lobes():
    axis = unit([[0.3, 1.0, 0.2], [-1.0, 0.2, 0.5], [0.2, -0.3, -1.0], [0.0, 0.0, 1.0]])
    return sg.SGLobes(axis.astype(np.float32), np.array([3.0, 20.0, 1.0, 300.0], np.float32),
                      np.array([[2.0, 1.5, 1.0], [5.0, 5.0, 6.0], [0.3, 0.4, 0.5], [20.0, 18.0, 15.0]], np.float32))


def _gbuffer(n, seed=0):
    rng = np.random.default_rng(seed)
    normals = unit(rng.normal(size=(n, 3)))
    views = unit(normals + 0.7 * unit(rng.normal(size=(n, 3))))
    views = np.where((views * normals).sum(1, keepdims=True) > 0.05, views, normals)
    albedo = rng.uniform(0.2, 0.8, (n, 3))
    roughness = rng.uniform(0.2, 0.8, n)
    return [x.astype(np.float32) for x in (normals, views, albedo, roughness)]


def test_shade_visible_equals_shade_sg_when_unoccluded():
    normals, views, albedo, roughness = _gbuffer(300)
    lobes = _lobes()
    directions = sg.fibonacci_sphere(128)
    ref = sg.shade_sg(normals, views, albedo, roughness, lobes)
    for vis in (np.ones((300, 128), bool), (normals @ directions.T) > 0):
        out = shade_sg_visible(normals, views, albedo, roughness, lobes, vis, directions, chunk=100)
        assert set(out) == {"diffuse", "specular", "rgb"} and out["rgb"].shape == (300, 3)
        np.testing.assert_allclose(out["diffuse"], ref["diffuse"], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(out["specular"], ref["specular"], rtol=1e-5, atol=1e-7)
    # visibility traced against a small triangle far away: nothing is hidden
    far = mesh_scene(np.array([[50.0, 50, 50], [50.1, 50, 50], [50, 50.1, 50]]), np.array([[0, 1, 2]]))
    vis = direction_visibility(np.zeros((300, 3)), normals, far, directions, threads=THREADS)
    out = shade_sg_visible(normals, views, albedo, roughness, lobes, vis, directions)
    assert float(np.abs(out["diffuse"] / ref["diffuse"] - 1).max()) < 0.01


def test_shade_visible_fully_enclosed_is_black():
    normals, views, albedo, roughness = _gbuffer(20)
    directions = sg.fibonacci_sphere(64)
    scene = mesh_scene(*box([-1, -1, -1], [1, 1, 1]))
    vis = direction_visibility(np.zeros((20, 3)), normals, scene, directions, threads=THREADS)
    assert not vis.any()
    out = shade_sg_visible(normals, views, albedo, roughness, _lobes(), vis, directions)
    np.testing.assert_array_equal(out["rgb"], 0.0)


def test_shade_visible_diffuse_matches_fine_quadrature_beside_a_wall():
    """Diffuse irradiance with the half space x > 0 hidden, against a fine quadrature of L V cos."""
    lobes = _lobes()
    normals = sg.fibonacci_sphere(60, rotation=sg.rotation_y(0.3)).astype(np.float32)
    fine = sg.fibonacci_sphere(40000)
    radiance = sg.evaluate_sg(lobes, fine).astype(np.float64)
    weight = np.maximum(normals.astype(np.float64) @ fine.T, 0) * (fine[:, 0] < 0) * (4 * math.pi / len(fine))
    reference = weight @ radiance
    directions = sg.fibonacci_sphere(256)
    vis = (directions[:, 0] < 0)[None] & (normals @ directions.T > 0)
    albedo = np.full((60, 3), math.pi, np.float32)  # diffuse radiance = E
    out = shade_sg_visible(normals, normals, albedo, np.full(60, 0.5, np.float32), lobes, vis, directions,
                           specular=False)
    unoccluded = sg.sg_irradiance(lobes, normals).mean()
    # the ratio estimator: a few % of the mean unoccluded irradiance (measured 1.1%)
    assert float(np.abs(out["diffuse"] - reference).mean() / unoccluded) < 0.03
    np.testing.assert_array_equal(out["specular"], 0.0)


def test_shade_visible_specular_follows_the_reflection():
    normal = np.array([[0.0, 1.0, 0.0]], np.float32)
    view = np.array([[math.sin(math.radians(40)), math.cos(math.radians(40)), 0.0]], np.float32)
    reflect = np.array([[-view[0, 0], view[0, 1], 0.0]])
    lobes = sg.SGLobes(reflect.astype(np.float32), np.array([30.0], np.float32), np.ones((1, 3), np.float32))
    directions = sg.fibonacci_sphere(512)
    albedo, rough = np.zeros((1, 3), np.float32), np.full(1, 0.25, np.float32)
    above = directions[:, 1] > 0
    free = shade_sg_visible(normal, view, albedo, rough, lobes, above[None], directions)["specular"]
    blocked = shade_sg_visible(normal, view, albedo, rough, lobes, (above & (directions[:, 0] > 0))[None],
                               directions)["specular"]  # the reflection side (x < 0) hidden
    open_ = shade_sg_visible(normal, view, albedo, rough, lobes, (above & (directions[:, 0] < 0))[None],
                             directions)["specular"]  # the other side hidden
    assert float(free.min()) > 0
    assert float((blocked / free).max()) < 0.05
    assert float((open_ / free).min()) > 0.9


def test_shade_visible_torch_gradients():
    normals, views, albedo, roughness = _gbuffer(30)
    directions = sg.fibonacci_sphere(64)
    vis = (normals @ directions.T > 0) & (directions[:, 0] < 0.3)[None]
    alb = torch.tensor(albedo, requires_grad=True)
    rough = torch.tensor(roughness, requires_grad=True)
    out = shade_sg_visible(torch.tensor(normals), torch.tensor(views), alb, rough, _lobes(), vis, directions)
    assert torch.is_tensor(out["rgb"])
    out["rgb"].sum().backward()
    assert torch.isfinite(alb.grad).all() and alb.grad.abs().sum() > 0
    assert torch.isfinite(rough.grad).all() and rough.grad.abs().sum() > 0


def test_default_sharpness_cap():
    assert default_sharpness_cap(256) == pytest.approx(512 / math.pi)


# --------------------------------------------------------------------------------------- bad inputs


def test_bad_inputs_raise():
    scene = mesh_scene(*disc(1.0, 1.0, 16))
    points, normals = origin_up(4)
    dirs = sg.fibonacci_sphere(8)
    with pytest.raises(ValueError, match="points must be"):
        ambient_occlusion(points[:, :2], normals, scene)
    with pytest.raises(ValueError, match="normals must be"):
        ambient_occlusion(points, normals[:3], scene)
    with pytest.raises(ValueError, match="non-zero"):
        ambient_occlusion(points, np.zeros((4, 3)), scene)
    with pytest.raises(ValueError, match="finite"):
        ambient_occlusion(np.full((4, 3), np.nan), normals, scene)
    with pytest.raises(ValueError, match="rays"):
        ambient_occlusion(points, normals, scene, rays=0)
    with pytest.raises(ValueError, match="offset_m"):
        ambient_occlusion(points, normals, scene, offset_m=-1e-3)
    with pytest.raises(ValueError, match="RaycastingScene"):
        ambient_occlusion(points, normals, "mesh.ply")
    with pytest.raises(ValueError, match="directions"):
        direction_visibility(points, normals, scene, dirs[:, :2])
    with pytest.raises(ValueError, match="directions"):
        direction_visibility(points, normals, scene, np.zeros((2, 3)))
    g_normals, views, albedo, rough = _gbuffer(4)
    vis = np.ones((4, 8), bool)
    with pytest.raises(ValueError, match="bool"):
        shade_sg_visible(g_normals, views, albedo, rough, _lobes(), vis.astype(np.float32), dirs)
    with pytest.raises(ValueError, match=r"visibility must be \(N, D\)"):
        shade_sg_visible(g_normals, views, albedo, rough, _lobes(), vis[:, :5], dirs)
    with pytest.raises(ValueError, match="directions"):
        shade_sg_visible(g_normals, views, albedo, rough, _lobes(), vis, dirs[:, :2])
    with pytest.raises(ValueError, match="sharpness_cap"):
        shade_sg_visible(g_normals, views, albedo, rough, _lobes(), vis, dirs, sharpness_cap=0.0)
    with pytest.raises(ValueError, match="albedo"):
        shade_sg_visible(g_normals, views, albedo[:3], rough, _lobes(), vis, dirs)


# ------------------------------------------------------------------------------------ deocclude_normals


def _bent(normal, visible, directions):
    """Eq. 1's direction for a Lambertian point: the cosine-weighted mean of the visible directions."""
    cos = np.maximum(directions @ normal, 0.0) * visible
    return unit(cos @ directions)


def test_deocclude_leaves_unoccluded_normals_alone():
    dirs = sg.fibonacci_sphere(256).astype(np.float64)
    normals = unit(np.random.default_rng(0).normal(size=(50, 3)))
    visible = normals @ dirs.T > 0  # every direction above the horizon
    fixed, residual = deocclude_normals(normals, visible, dirs, normals)
    assert fixed.shape == (50, 3) and fixed.dtype == np.float32 and residual.shape == (50,)
    np.testing.assert_allclose(fixed, normals, atol=1e-6)
    assert residual.max() < 1e-3


def test_deocclude_half_space_wall_by_hand():
    # A wall blocking every direction with x > 0 above a surface facing +z: eq. 1 measures the bent normal
    # (-4 / (3 pi), 0, 2 / 3) / |.|, atan(2 / pi) = 32.48 deg from the true normal towards -x.
    dirs = sg.fibonacci_sphere(2048).astype(np.float64)
    tilt = math.atan(2.0 / math.pi)
    measured = np.array([[-math.sin(tilt), 0.0, math.cos(tilt)]])
    np.testing.assert_allclose(_bent(np.array([0.0, 0.0, 1.0]), (dirs[:, 0] <= 0), dirs), measured[0], atol=2e-3)
    visible = ((dirs[:, 0] <= 0) & (dirs[:, 2] > 0))[None]
    fixed, residual = deocclude_normals(measured, visible, dirs, np.array([[0.0, 0.0, 1.0]]))
    error = math.degrees(math.acos(min(1.0, float(fixed[0, 2]))))
    assert error < 0.3, error
    assert residual[0] < 0.05
    # a few steps are not enough: the iteration count is what converges it
    early, _ = deocclude_normals(measured, visible, dirs, np.array([[0.0, 0.0, 1.0]]), iterations=2)
    assert math.degrees(math.acos(min(1.0, float(early[0, 2])))) > 5.0


def test_deocclude_inverts_its_forward_model_under_random_occluders():
    rng = np.random.default_rng(1)
    dirs = sg.fibonacci_sphere(512).astype(np.float64)
    truth = unit(rng.normal(size=(40, 3)))
    # each point loses a random cap of the sphere (cone of 40-70 deg around a random axis); the damped
    # iteration converges for every one of them
    axes = unit(rng.normal(size=(40, 3)))
    half = np.radians(rng.uniform(40, 70, size=(40, 1)))
    visible = (truth @ dirs.T > 0) & (axes @ dirs.T < np.cos(half))
    measured = np.stack([_bent(n, v, dirs) for n, v in zip(truth, visible)])
    lean = np.degrees(np.arccos(np.clip((measured * truth).sum(-1), -1, 1)))
    fixed, residual = deocclude_normals(measured, visible, dirs, truth, min_visible=0.0)
    error = np.degrees(np.arccos(np.clip((fixed * truth).sum(-1), -1, 1)))
    assert lean.mean() > 5.0  # the occluders matter
    assert error.max() < 1.0 and residual.max() < 1.0, (error.max(), residual.max())


def test_deocclude_keeps_dark_and_undefined_pixels():
    dirs = sg.fibonacci_sphere(256).astype(np.float64)
    measured = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.3, 0.0, 1.0]])
    visible = np.zeros((3, 256), bool)  # nothing lit at all
    visible[2] = dirs[:, 2] > 0
    fixed, residual = deocclude_normals(measured, visible, dirs, np.tile([0.0, 0.0, 1.0], (3, 1)))
    np.testing.assert_allclose(fixed[0], [0, 0, 1], atol=1e-6)  # too dark: kept
    np.testing.assert_array_equal(fixed[1], [0, 0, 0])  # undefined: stays zero
    assert np.isfinite(fixed).all() and np.isfinite(residual).all()
    np.testing.assert_allclose(np.linalg.norm(fixed[[0, 2]], axis=1), 1.0, atol=1e-6)


def test_deocclude_bad_inputs_raise():
    dirs = sg.fibonacci_sphere(64)
    n = np.array([[0.0, 0.0, 1.0]])
    ok = np.ones((1, 64), bool)
    with pytest.raises(ValueError, match="measured"):
        deocclude_normals(np.zeros((1, 2)), ok, dirs, n)
    with pytest.raises(ValueError, match="visibility"):
        deocclude_normals(n, np.ones((1, 63), bool), dirs, n)
    with pytest.raises(ValueError, match="surface_normals"):
        deocclude_normals(n, ok, dirs, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="finite"):
        deocclude_normals(np.array([[np.nan, 0.0, 1.0]]), ok, dirs, n)
    with pytest.raises(ValueError, match="iterations"):
        deocclude_normals(n, ok, dirs, n, iterations=0)
    with pytest.raises(ValueError, match="min_visible"):
        deocclude_normals(n, ok, dirs, n, min_visible=1.0)


def test_deocclude_view_of_a_floor_beside_a_tall_wall():
    # A camera 2 m above a floor (y = 0, x < 0.1) that ends at a wall (x = 0.1, 1 km tall): every floor point
    # loses the half of the sphere towards +x, so eq. 1 measures the floor's normal tilted 32.48 deg to -x.
    wv, wf = wall(0.1)
    floor_v = np.array([[-3.0, 0.0, -3.0], [0.1, 0.0, -3.0], [0.1, 0.0, 3.0], [-3.0, 0.0, 3.0]])
    scene = mesh_scene(np.concatenate([wv, floor_v]), np.concatenate([wf, np.array([[4, 6, 5], [4, 7, 6]])]))
    size, f, centre = 48, 60.0, np.array([-0.5, 2.0, 0.0])
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # looking down -y, image rows along +z
    K = np.array([[f, 0.0, (size - 1) / 2], [0.0, f, (size - 1) / 2], [0.0, 0.0, 1.0]])
    cam_from_world = np.concatenate([R, (-R @ centre)[:, None]], axis=1)
    tilt = math.atan(2.0 / math.pi)
    measured = np.tile(np.array([-math.sin(tilt), math.cos(tilt), 0.0], np.float32), (size, size, 1))
    measured[:4] = 0.0  # undefined rows stay undefined
    measured[4:8, :4] = np.nan  # NaN is treated as undefined
    fixed, stats = deocclude_view(scene, K, cam_from_world, measured, directions=512)
    assert fixed.shape == measured.shape and fixed.dtype == np.float32 and np.isfinite(fixed).all()
    assert np.all(fixed[:4] == 0) and np.all(fixed[4:8, :4] == 0)
    # floor pixels (x < 0: columns left of the wall's image) come back to the floor's normal
    x_world = centre[0] + (np.arange(size) - (size - 1) / 2) / f * 2.0
    floor = np.zeros((size, size), bool)
    floor[8:, :] = (x_world < 0.0)[None, :]
    error = np.degrees(np.arccos(np.clip(fixed[floor] @ np.array([0.0, 1.0, 0.0]), -1, 1)))
    assert error.max() < 1.5, error.max()
    assert stats["occlusion_pixels_fraction"] > 0.99 and 20.0 < stats["occlusion_correction_mean_deg"] < 40.0
    assert stats["occlusion_residual_mean_deg"] < 0.1
    # a render the caller already has gives the same maps; one of another size is refused
    seen = render_mesh(None, None, K, cam_from_world, size, size, scene=scene)
    again, _ = deocclude_view(scene, K, cam_from_world, measured, directions=512, seen=seen)
    np.testing.assert_array_equal(again, fixed)
    with pytest.raises(ValueError, match="seen was rendered at"):
        deocclude_view(scene, K, cam_from_world, measured[:-1], directions=512, seen=seen)
    with pytest.raises(ValueError, match="normals"):
        deocclude_view(scene, K, cam_from_world, measured[..., :2])
