"""Visual hull numerics: carving a sphere from analytic masks, signed distance, look-ups, input checks."""
from __future__ import annotations

import numpy as np
import pytest

from stages.numerics.hull import HullGrid, _well_seen_components, check_camera, visual_hull

RADIUS = 0.3
BOUNDS = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])


def look_at(centre, target=np.zeros(3)):
    """OpenCV cam_from_world (3, 4) at ``centre`` looking at ``target``, image y pointing down (-y world)."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, -1.0, 0.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return np.concatenate([R, (-R @ centre)[:, None]], axis=1)


def sphere_cameras(n=8, dist=2.0, size=64):
    f = 0.9 * size / 2 / np.tan(np.arcsin(RADIUS * 1.5 / dist))
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        el = 0.5 * np.sin(2 * a + 0.3)
        c = dist * np.array([np.cos(a) * np.cos(el), np.sin(el), np.sin(a) * np.cos(el)])
        cams.append((K, look_at(c)))
    return cams


def sphere_mask(K, T, size=64, radius=RADIUS, centre=np.zeros(3)):
    """Analytic silhouette: pixels whose ray passes within ``radius`` of ``centre`` (the origin)."""
    R, t = T[:, :3], T[:, 3]
    o = -R.T @ t - centre
    rows, cols = np.mgrid[0:size, 0:size]
    pix = np.stack([cols.ravel(), rows.ravel(), np.ones(size * size)], 1)
    d = np.linalg.solve(K, pix.T).T @ R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    closest = o - (d @ o)[:, None] * d
    return (np.linalg.norm(closest, axis=1) < radius).reshape(size, size)


@pytest.fixture(scope="module")
def sphere_hull():
    cams = sphere_cameras()
    masks = [sphere_mask(K, T) for K, T in cams]
    grid = visual_hull(masks, [K for K, _ in cams], [T for _, T in cams], BOUNDS, 40, max_misses=0, dilate_px=0)
    return grid, cams, masks


def test_sphere_hull_contains_sphere_and_is_close(sphere_hull):
    grid, _, _ = sphere_hull
    assert grid.occupancy.shape == (40, 40, 40) and grid.occupancy.dtype == bool
    rng = np.random.default_rng(0)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert grid.contains(d * RADIUS * rng.uniform(0, 1, (3000, 1))).all()  # a superset of the solid ball
    assert grid.contains(d * RADIUS).all()
    # Eight views carve close to the sphere: nothing beyond 1.35 r (the hull of a few cones), and the
    # hull's surface (voxels next to empty ones) averages within ~2 voxels of the sphere.
    centres = grid.centers()[grid.occupancy]
    assert np.linalg.norm(centres, axis=1).max() < 1.35 * RADIUS
    sd = grid.signed_distance()
    boundary = grid.centers()[grid.occupancy & (sd > -float(grid.voxel_size.max()))]
    mean_excess = np.linalg.norm(boundary, axis=1).mean() - RADIUS
    assert 0 < mean_excess < 2.0 * float(grid.voxel_size.max())


def test_centre_test_hull_is_inside_the_conservative_one(sphere_hull):
    grid, cams, masks = sphere_hull
    plain = visual_hull(masks, [K for K, _ in cams], [T for _, T in cams], BOUNDS, 40, max_misses=0, dilate_px=0,
                        conservative=False)
    assert plain.occupancy.sum() < grid.occupancy.sum()
    assert (grid.occupancy | ~plain.occupancy).all()
    # The classic centre test carves to within about one voxel of the sphere (mean radius of its surface).
    sd = plain.signed_distance()
    boundary = plain.centers()[plain.occupancy & (sd > -float(plain.voxel_size.max()))]
    assert abs(np.linalg.norm(boundary, axis=1).mean() - RADIUS) < float(plain.voxel_size.max())


def test_tight_bounds_and_voxel_size(sphere_hull):
    grid, _, _ = sphere_hull
    np.testing.assert_allclose(grid.voxel_size, [0.025, 0.025, 0.025])
    tb = grid.tight_bounds(0.0)
    assert (tb[0] <= -RADIUS).all() and (tb[1] >= RADIUS).all()
    assert (tb[0] > -1.35 * RADIUS).all() and (tb[1] < 1.35 * RADIUS).all()
    np.testing.assert_allclose(grid.tight_bounds(0.05), tb + [[-0.05] * 3, [0.05] * 3])


def test_signed_distance_hand_computed():
    occ = np.zeros((9, 9, 9), bool)
    occ[3:6, 3:6, 3:6] = True  # a 3-voxel cube of 1 m voxels
    grid = HullGrid(occ, np.array([[0.0, 0.0, 0.0], [9.0, 9.0, 9.0]]))
    sd = grid.signed_distance()
    assert sd.dtype == np.float32 and sd.shape == (9, 9, 9)
    assert sd[4, 4, 4] == pytest.approx(-1.5)  # centre: 2 voxel centres to the nearest empty one, minus 1/2
    assert sd[3, 4, 4] == pytest.approx(-0.5)
    assert sd[2, 4, 4] == pytest.approx(0.5)
    assert sd[0, 4, 4] == pytest.approx(2.5)
    assert sd[2, 2, 4] == pytest.approx(np.sqrt(2) - 0.5)  # diagonal to the cube's edge voxel


def test_sample_is_exact_for_linear_fields_and_contains_outside_box(sphere_hull):
    grid, _, _ = sphere_hull
    field = grid.centers() @ np.array([1.0, -2.0, 0.5])
    pts = np.random.default_rng(1).uniform(-0.45, 0.45, (200, 3))
    np.testing.assert_allclose(grid.sample(field, pts), pts @ np.array([1.0, -2.0, 0.5]), atol=1e-5)
    assert not grid.contains(np.array([[0.0, 0.0, 0.9], [np.nan, 0.0, 0.0]])).any()
    with pytest.raises(ValueError, match="values must be"):
        grid.sample(field[:-1], pts)


def test_max_misses_survives_one_empty_mask(sphere_hull):
    _, cams, masks = sphere_hull
    bad = [m.copy() for m in masks]
    bad[3][:] = False  # one view's mask is lost
    Ks, Ts = [K for K, _ in cams], [T for _, T in cams]
    assert not visual_hull(bad, Ks, Ts, BOUNDS, 16, max_misses=0, dilate_px=0).occupancy.any()
    robust = visual_hull(bad, Ks, Ts, BOUNDS, 16, max_misses=1, dilate_px=0)
    assert robust.contains(np.zeros((1, 3))).all()


def test_dilation_grows_the_hull(sphere_hull):
    _, cams, masks = sphere_hull
    Ks, Ts = [K for K, _ in cams], [T for _, T in cams]
    tight = visual_hull(masks, Ks, Ts, BOUNDS, 24, max_misses=0, dilate_px=0)
    loose = visual_hull(masks, Ks, Ts, BOUNDS, 24, max_misses=0, dilate_px=4)
    assert loose.occupancy.sum() > tight.occupancy.sum()
    assert (loose.occupancy | ~tight.occupancy).all()  # monotone: dilation only adds voxels
    assert tight.dilated(1).occupancy.sum() > tight.occupancy.sum()


def test_input_checks(sphere_hull):
    _, cams, masks = sphere_hull
    Ks, Ts = [K for K, _ in cams], [T for _, T in cams]
    with pytest.raises(ValueError, match="same length"):
        visual_hull(masks[:-1], Ks, Ts, BOUNDS, 8)
    with pytest.raises(ValueError, match="bounds"):
        visual_hull(masks, Ks, Ts, BOUNDS[::-1], 8)
    with pytest.raises(ValueError, match="resolution"):
        visual_hull(masks, Ks, Ts, BOUNDS, 0)
    with pytest.raises(ValueError, match="rotation"):
        visual_hull(masks, Ks, [T * 2 for T in Ts], BOUNDS, 8)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        visual_hull([m[..., None] for m in masks], Ks, Ts, BOUNDS, 8)
    with pytest.raises(ValueError, match="focal"):
        check_camera(np.zeros((3, 3)), Ts[0])
    with pytest.raises(ValueError, match="empty"):
        HullGrid(np.zeros((4, 4, 4), bool), BOUNDS).tight_bounds()


def test_component_views_drops_a_pocket_only_a_few_views_hold():
    """A 4 cm ball in a corner of the box, in the frame of 3 of the 8 views (and in their masks): the plain hull
    keeps it apart from the sphere and its box reaches the corner; with component_views 0.5 it is dropped (held
    by 3 views against the sphere's 8) and the box is the sphere's."""
    cams = sphere_cameras()
    pocket = np.array([0.45, -0.42, 0.4])
    masks = [sphere_mask(K, T) | sphere_mask(K, T, radius=0.04, centre=pocket) for K, T in cams]
    Ks, Ts = [K for K, _ in cams], [T for _, T in cams]
    plain = visual_hull(masks, Ks, Ts, BOUNDS, 40, max_misses=0, dilate_px=0)
    assert plain.contains(pocket[None])[0]
    assert plain.tight_bounds()[1, 0] > 0.45 and plain.tight_bounds()[0, 1] < -0.45
    kept = visual_hull(masks, Ks, Ts, BOUNDS, 40, max_misses=0, dilate_px=0, component_views=0.5)
    assert not kept.contains(pocket[None])[0]
    np.testing.assert_allclose(kept.tight_bounds(), [[-0.325] * 3, [0.325] * 3], atol=0.026)
    sphere_only = visual_hull([sphere_mask(K, T) for K, T in cams], Ks, Ts, BOUNDS, 40, max_misses=0, dilate_px=0)
    assert not (plain.occupancy & sphere_only.occupancy & ~kept.occupancy).any()  # every sphere voxel stays
    assert 0 < (plain.occupancy & ~kept.occupancy).sum() < 0.01 * kept.occupancy.sum()  # the pocket goes


def test_component_views_keeps_a_single_component_and_checks_its_range(sphere_hull):
    grid, cams, masks = sphere_hull
    Ks, Ts = [K for K, _ in cams], [T for _, T in cams]
    same = visual_hull(masks, Ks, Ts, BOUNDS, 40, max_misses=0, dilate_px=0, component_views=1.0)
    np.testing.assert_array_equal(same.occupancy, grid.occupancy)
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="component_views"):
            visual_hull(masks, Ks, Ts, BOUNDS, 8, component_views=bad)


def test_well_seen_components_hand_case():
    """Two blobs (26-connected: the diagonal pair is one): the best voxels held by 8 and 3 views."""
    occ = np.zeros((6, 6, 6), bool)
    occ[0, 0, 0] = occ[1, 1, 1] = True          # one component through the corner
    occ[4:6, 4:6, 4:6] = True                   # another
    views = np.zeros((6, 6, 6), np.int16)
    views[0, 0, 0], views[1, 1, 1] = 2, 8
    views[4:6, 4:6, 4:6] = 3
    kept = _well_seen_components(occ, views, 0.5)   # 3 < 0.5 x 8
    assert kept[0, 0, 0] and kept[1, 1, 1] and not kept[4:6, 4:6, 4:6].any()
    np.testing.assert_array_equal(_well_seen_components(occ, views, 0.375), occ)  # 3 >= 0.375 x 8
    single = np.zeros_like(occ)
    single[2, 2, 2] = True
    np.testing.assert_array_equal(_well_seen_components(single, views, 1.0), single)


def test_subject_box_holds_the_sphere_within_a_coarse_voxel():
    from stages.numerics.hull import default_stage_box, subject_box

    cams = sphere_cameras()
    masks = [sphere_mask(K, T) for K, T in cams]
    Ks, Ts = [K for K, _ in cams], [T for _, T in cams]
    stage = default_stage_box(cams)
    np.testing.assert_allclose(stage.mean(0), 0.0, atol=1e-9)  # every optical axis meets at the origin
    box = subject_box(masks, Ks, Ts, stage)
    assert (box[0] <= -RADIUS).all() and (box[1] >= RADIUS).all()  # a superset of the sphere
    assert (box[0] >= stage[0]).all() and (box[1] <= stage[1]).all()
    # found, not shaped: 8 cameras and 4 cm voxels leave it loose, but well inside the 2.5 m stage box
    assert np.prod(box[1] - box[0]) < 0.25 * np.prod(stage[1] - stage[0])
    with pytest.raises(ValueError, match="empty"):
        subject_box([np.zeros_like(m) for m in masks], Ks, Ts, stage)
