"""bake.gather_observations: each point's values in its best views, unblended, on a flat square seen by a
few synthetic cameras whose images encode their own pixel coordinates and a per-view constant."""
from __future__ import annotations

import numpy as np
import pytest

from stages.numerics.bake import BakeView, gather_observations
from synthetic.rig import look_at as rig_look_at
from synthetic.rig import project

SIZE = 96
FOCAL = 80.0
K = np.array([[FOCAL, 0.0, (SIZE - 1) / 2], [0.0, FOCAL, (SIZE - 1) / 2], [0.0, 0.0, 1.0]])
HALF = 0.5  # the square spans [-HALF, HALF]^2 in the z = 0 plane, normal +z
# Camera centres: frontal-near, oblique, frontal-far (from above, so the occluder below never hides it).
CENTRES = {"front": (0.0, 0.0, 2.0), "oblique": (1.5, 0.0, 1.5), "far": (0.0, 1.5, 2.5)}
OCCLUDER = (0.1, 1.0)  # half size, z: a small square hiding the centre of the plane from "front" only


def look_at(centre) -> np.ndarray:
    return rig_look_at(np.asarray(centre, float), np.zeros(3))


def square(half: float, z: float, first: int = 0):
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int64) + first
    return v, f


def plane_mesh(occluder: bool = False):
    v, f = square(HALF, 0.0)
    if occluder:
        vo, fo = square(OCCLUDER[0], OCCLUDER[1], first=len(v))
        v, f = np.concatenate([v, vo]), np.concatenate([f, fo])
    return v, f


def make_view(index: int, P: np.ndarray, valid: np.ndarray | None = None, invalid_value: float = 0.0) -> BakeView:
    """``pix`` = (column, row) of every pixel (linear, so bilinear lookups are exact), ``const`` = index + 1
    (``invalid_value`` where ``valid`` is False)."""
    rows, cols = np.mgrid[0:SIZE, 0:SIZE].astype(np.float32)
    valid = np.ones((SIZE, SIZE), bool) if valid is None else valid
    const = np.where(valid, np.float32(index + 1), np.float32(invalid_value))[..., None]
    return BakeView(images={"pix": np.stack([cols, rows], -1), "const": const.astype(np.float32)}, valid=valid,
                    K=K, cam_from_world=P)


def grid_points(lo=-0.35, hi=0.35, n=8):
    xs = np.linspace(lo, hi, n)
    x, y = np.meshgrid(xs, xs)
    pts = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    return pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1))


def poses():
    return [look_at(c) for c in CENTRES.values()]


def hand_score(P, points):
    """cos * (f / z)^2 of fully supported points: what bake_textures ranks views by."""
    centre = -P[:, :3].T @ P[:, 3]
    to_cam = centre - points
    cos = to_cam[:, 2] / np.linalg.norm(to_cam, axis=1)
    z = points @ P[2, :3] + P[2, 3]
    return cos * (FOCAL / z) ** 2


@pytest.fixture(scope="module")
def gathered():
    v, f = plane_mesh()
    pts, nrm = grid_points()
    views = [make_view(i, P) for i, P in enumerate(poses())]
    return pts, views, gather_observations(v, f, pts, nrm, views, max_views=3)


def test_values_are_the_bilinear_samples_of_each_view(gathered):
    pts, views, out = gathered
    assert out["values"]["pix"].shape == (len(pts), 3, 2) and out["values"]["const"].shape == (len(pts), 3, 1)
    assert out["values"]["pix"].dtype == np.float32 and out["view_index"].dtype == np.int32
    assert out["valid"].all()  # every interior point is seen by all three cameras
    for slot in range(3):
        idx = out["view_index"][:, slot]
        for i, view in enumerate(views):
            sel = idx == i
            uv, _ = project(K, view.cam_from_world, pts[sel])
            # (column, row) images sampled bilinearly at the projection give back the projection
            np.testing.assert_allclose(out["values"]["pix"][sel, slot], uv, atol=2e-3)
            np.testing.assert_allclose(out["values"]["const"][sel, slot, 0], i + 1, rtol=1e-6)


def test_views_rank_frontal_and_near_first(gathered):
    pts, views, out = gathered
    scores = np.stack([hand_score(v.cam_from_world, pts) for v in views], 1)  # (P, V)
    np.testing.assert_array_equal(out["view_index"], np.argsort(-scores, axis=1, kind="stable"))
    # the near frontal camera first everywhere; the oblique (cos ~0.7, ~2.1 m) and the far frontal one
    # (cos ~0.86, ~2.9 m) swap where the plane turns away from the oblique one
    assert np.all(out["view_index"][:, 0] == 0)
    assert set(out["view_index"][:, 1]) == {1, 2}


def test_view_dirs_and_cos(gathered):
    pts, views, out = gathered
    centres = np.stack([-v.cam_from_world[:, :3].T @ v.cam_from_world[:, 3] for v in views])
    expected = centres[out["view_index"]] - pts[:, None]
    expected /= np.linalg.norm(expected, axis=2, keepdims=True)
    np.testing.assert_allclose(np.linalg.norm(out["view_dirs"], axis=2), 1.0, atol=1e-6)
    np.testing.assert_allclose(out["view_dirs"], expected, atol=1e-6)
    np.testing.assert_allclose(out["cos"], expected[..., 2], atol=1e-6)  # normal is +z


def test_occluder_hides_the_centre_from_one_view_only():
    v, f = plane_mesh(occluder=True)
    hidden, _ = grid_points(-0.08, 0.08, 3)
    seen_pts, _ = grid_points(-0.4, 0.4, 4)  # all at |x| or |y| >= 0.13, beyond the occluder's shadow
    seen_pts = seen_pts[np.abs(seen_pts[:, :2]).max(1) > 0.3]
    pts = np.concatenate([hidden, seen_pts])
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    views = [make_view(i, P) for i, P in enumerate(poses())]
    out = gather_observations(v, f, pts, nrm, views, max_views=3)
    h = len(hidden)
    # hidden points: the front camera sees the occluder there; the other two remain, best first
    np.testing.assert_array_equal(out["view_index"][:h], np.tile([1, 2, -1], (h, 1)))
    np.testing.assert_array_equal(out["valid"][:h], np.tile([True, True, False], (h, 1)))
    assert np.all(out["values"]["const"][:h, 2] == 0) and np.all(out["view_dirs"][:h, 2] == 0)
    assert np.all(out["cos"][:h, 2] == 0)
    # the others keep all three, the front one first
    assert out["valid"][h:].all() and np.all(out["view_index"][h:, 0] == 0)
    np.testing.assert_allclose(out["values"]["const"][out["valid"]][:, 0], out["view_index"][out["valid"]] + 1,
                               rtol=1e-6)


def test_fewer_views_than_max_views_and_unseen_points():
    v, f = plane_mesh()
    pts = np.array([[0.1, 0.1, 0.0], [0.2, -0.1, 0.0], [0.0, 0.0, 0.0]])
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])  # the last faces away from all
    views = [make_view(i, P) for i, P in enumerate(poses()[:2])]
    out = gather_observations(v, f, pts, nrm, views, max_views=5)
    assert out["valid"].shape == (3, 2) and out["view_index"].shape == (3, 2) and out["cos"].shape == (3, 2)
    assert out["values"]["pix"].shape == (3, 2, 2) and out["view_dirs"].shape == (3, 2, 3)
    np.testing.assert_array_equal(out["valid"], [[True, True], [True, True], [False, False]])
    np.testing.assert_array_equal(out["view_index"][2], [-1, -1])
    assert not out["values"]["pix"][2].any() and not out["view_dirs"][2].any()
    one = gather_observations(v, f, pts[:1], nrm[:1], views, max_views=1)
    assert one["valid"].shape == (1, 1) and one["view_index"][0, 0] == 0


def test_invalid_pixels_never_contribute():
    v, f = plane_mesh()
    pts, nrm = grid_points(-0.35, 0.35, 12)
    Ps = poses()
    valid = np.ones((SIZE, SIZE), bool)
    valid[:, 40:50] = False  # a stripe of the front view, holding a value that must not leak
    views = [make_view(0, Ps[0], valid=valid, invalid_value=1000.0)] + [make_view(i, P) for i, P in
                                                                          enumerate(Ps[1:], 1)]
    out = gather_observations(v, f, pts, nrm, views, max_views=3)
    from_front = out["view_index"] == 0
    np.testing.assert_allclose(out["values"]["const"][from_front, 0], 1.0, rtol=1e-6)  # valid taps only
    uv, _ = project(K, Ps[0], pts)
    deep = (uv[:, 0] > 40.5) & (uv[:, 0] < 48.5)  # all four taps in the stripe
    shallow = (uv[:, 0] < 38.5) | (uv[:, 0] > 50.5)  # no tap in it
    assert deep.any() and shallow.any()
    assert not from_front[deep].any()
    assert from_front[shallow, 0].all()
    # with the invalid stripe the front view drops out of deep points: the other two move up
    np.testing.assert_array_equal(out["view_index"][deep], np.tile([1, 2, -1], (deep.sum(), 1)))


def test_bad_inputs_raise():
    v, f = plane_mesh()
    pts, nrm = grid_points(n=2)
    views = [make_view(i, P) for i, P in enumerate(poses())]
    with pytest.raises(ValueError, match="points and normals"):
        gather_observations(v, f, pts[:, :2], nrm, views, 2)
    with pytest.raises(ValueError, match="points and normals"):
        gather_observations(v, f, pts, nrm[:2], views, 2)
    with pytest.raises(ValueError, match="max_views"):
        gather_observations(v, f, pts, nrm, views, 0)
    with pytest.raises(ValueError, match="at least one view"):
        gather_observations(v, f, pts, nrm, [], 2)
    odd = BakeView(images={"pix": views[0].images["pix"]}, valid=views[0].valid, K=K,
                   cam_from_world=views[0].cam_from_world)
    with pytest.raises(ValueError, match="differ"):
        gather_observations(v, f, pts, nrm, [views[0], odd], 2)
    with pytest.raises(ValueError, match="faces"):
        gather_observations(v, f + 10, pts, nrm, views, 2)


def test_non_positive_depth_tolerance_raises_like_bake_textures():
    v, f = plane_mesh()
    pts, nrm = grid_points(n=2)
    views = [make_view(i, P) for i, P in enumerate(poses())]
    with pytest.raises(ValueError):
        gather_observations(v, f, pts, nrm, views, 2, depth_tolerance_m=-1.0)


def test_min_cos_of_one_or_more_raises_like_bake_textures():
    v, f = plane_mesh()
    pts, nrm = grid_points(n=2)
    views = [make_view(i, P) for i, P in enumerate(poses())]
    with pytest.raises(ValueError):
        gather_observations(v, f, pts, nrm, views, 2, min_cos=1.5)
