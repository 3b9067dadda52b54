"""raycast.render_attributes / render_uvs: per-vertex attributes interpolated at the rays' hits."""
from __future__ import annotations

import numpy as np
import pytest

from stages.numerics.raycast import camera_rays, mesh_scene, render_attributes, render_uvs
from synthetic.rig import look_at as rig_look_at

H, W = 40, 48
K = np.array([[60.0, 0.0, (W - 1) / 2], [0.0, 60.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
# a tilted triangle (not parallel to the image plane, so depth varies across it)
TRIANGLE = np.array([[-0.5, -0.4, 0.0], [0.5, -0.3, -0.2], [0.0, 0.5, 0.3]])
FACES = np.array([[0, 1, 2]])


def camera() -> np.ndarray:
    return rig_look_at(np.array([0.2, 0.1, 2.0]), np.zeros(3))


def hand_hits(P):
    """Analytic ray / plane intersections and barycentrics of every pixel's ray with TRIANGLE."""
    origins, dirs, _ = camera_rays(K, P, H, W)
    a, b, c = TRIANGLE
    n = np.cross(b - a, c - a)
    t = ((a - origins) @ n) / (dirs @ n)
    points = origins + t[:, None] * dirs
    # barycentrics = signed sub-triangle areas over the triangle's
    l1 = np.cross(points - a, c - a) @ n / (n @ n)  # weight of b
    l2 = np.cross(b - a, points - a) @ n / (n @ n)  # weight of c
    l0 = 1 - l1 - l2
    return points, np.stack([l0, l1, l2], 1)


def test_attributes_equal_the_hit_points():
    P = camera()
    values, hit = render_attributes(mesh_scene(TRIANGLE, FACES), FACES, TRIANGLE, K, P, H, W)
    assert values.shape == (H, W, 3) and values.dtype == np.float64 and hit.shape == (H, W)
    points, bary = hand_hits(P)
    inside = (bary > 1e-3).all(1)  # clearly inside (pixels on the edges may go either way)
    outside = (bary < -1e-3).any(1)
    assert inside.sum() > 100 and outside.sum() > 100
    flat_hit, flat_values = hit.reshape(-1), values.reshape(-1, 3)
    assert flat_hit[inside].all() and not flat_hit[outside].any()
    np.testing.assert_allclose(flat_values[inside], points[inside], atol=1e-5)  # float32 barycentrics
    assert not flat_values[~flat_hit].any()


def test_split_corners_and_uvs_are_the_barycentrics():
    # the scene is the welded triangle; the attribute rows of its corners are 3, 4, 5 (an atlas' split ones)
    P = camera()
    scene = mesh_scene(TRIANGLE, FACES)
    uvs = np.array([[9, 9], [9, 9], [9, 9], [0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    uv, hit = render_uvs(scene, np.array([[3, 4, 5]]), uvs, K, P, H, W)
    assert uv.shape == (H, W, 2)
    _, bary = hand_hits(P)
    inside = (bary > 1e-3).all(1)
    np.testing.assert_allclose(uv.reshape(-1, 2)[inside], bary[inside][:, 1:], atol=1e-5)
    assert np.all(uv.reshape(-1, 2)[hit.reshape(-1)] <= 1.0 + 1e-6)  # never the unused rows' 9s
    assert not uv[~hit].any()


def test_bad_inputs_raise():
    P = camera()
    scene = mesh_scene(TRIANGLE, FACES)
    with pytest.raises(ValueError, match="faces index 4 attributes, only 3"):
        render_attributes(scene, np.array([[0, 1, 3]]), TRIANGLE, K, P, H, W)
    with pytest.raises(ValueError, match="faces index"):
        render_attributes(scene, np.array([[0, -1, 2]]), TRIANGLE, K, P, H, W)
    with pytest.raises(ValueError, match="attributes"):
        render_attributes(scene, FACES, TRIANGLE.ravel(), K, P, H, W)
    # a scene built from more faces than given (another mesh): its second face, in front, is hit
    with pytest.raises(ValueError, match="more faces"):
        render_attributes(mesh_scene(np.concatenate([TRIANGLE, TRIANGLE + [0, 0, 0.5]]),
                                     np.array([[0, 1, 2], [3, 4, 5]])), FACES, TRIANGLE, K, P, H, W)
    with pytest.raises(ValueError, match="uvs"):
        render_uvs(scene, FACES, TRIANGLE, K, P, H, W)
    with pytest.raises(ValueError, match="K"):
        render_attributes(scene, FACES, TRIANGLE, K[:2], P, H, W)
