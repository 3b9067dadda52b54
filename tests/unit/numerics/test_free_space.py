"""Free space from the views' disagreement: the agreement counts on a hand-built scene, the region filter and the
free depths."""
from __future__ import annotations

import numpy as np
import pytest

from artifacts.camera import camera_centre, pixel_rays
from stages.numerics.free_space import disagreement_pixels, free_depths, normal_agreement

SIZE = 41
K = np.array([[60.0, 0.0, 20.0], [0.0, 60.0, 20.0], [0.0, 0.0, 1.0]])


def looking_down(x):
    """A camera at (x, 0, 1) looking down -z at the plane z = 0 (OpenCV: image y along world -y)."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    return np.concatenate([R, (-R @ np.array([x, 0.0, 1.0]))[:, None]], 1)


def true_normal(x):
    """The scene's normals vary along x: (sin 8x, 0, cos 8x), on the plane z = 0."""
    return np.stack([np.sin(8 * x), np.zeros_like(x), np.cos(8 * x)], -1)


def maps(cameras, mesh_z):
    """Per camera: the true surface's normals (the plane z = 0), all valid, and a mesh at the plane z = mesh_z:
    its distance along each ray and its camera depth."""
    normals, valid, mesh_t, mesh_depth = [], [], [], []
    rows, cols = np.mgrid[0:SIZE, 0:SIZE]
    for T in cameras:
        d, z_per_t = pixel_rays(K, T, cols.ravel(), rows.ravel())
        o = camera_centre(T)
        x_true = o[0] + (-o[2] / d[:, 2]) * d[:, 0]
        normals.append(true_normal(x_true).reshape(SIZE, SIZE, 3))
        valid.append(np.ones((SIZE, SIZE), bool))
        t = (mesh_z - o[2]) / d[:, 2]
        mesh_t.append(t.reshape(SIZE, SIZE))
        mesh_depth.append((t * z_per_t).reshape(SIZE, SIZE))
    return normals, valid, mesh_t, mesh_depth


def test_the_views_agree_on_the_true_surface_and_not_in_front_of_it():
    cameras = [looking_down(x) for x in (-0.2, 0.0, 0.2)]
    centre = SIZE // 2
    on_truth = normal_agreement(*maps(cameras, 0.0), [K] * 3, cameras)
    # the middle camera's centre pixel sees (0, 0, 0): both other cameras see it (0.16 m off their axes, inside
    # their images, facing them) and measure the same normal there
    agree, seen = on_truth[1]
    assert seen[centre, centre] == 2 and agree[centre, centre] == 2
    # a mesh 0.1 m in front of the surface: the others see its point at (0, 0, 0.1) on other parts of the plane,
    # about 0.02 m off in x, whose normals are 8-10 deg away: more than 5 deg, less than 20
    off = normal_agreement(*maps(cameras, 0.1), [K] * 3, cameras, agree_deg=5.0)
    agree, seen = off[1]
    assert seen[centre, centre] == 2 and agree[centre, centre] == 0
    loose = normal_agreement(*maps(cameras, 0.1), [K] * 3, cameras, agree_deg=20.0)
    assert loose[1][0][centre, centre] == 2
    # over the middle view, the mesh on the truth is agreed with wherever it is seen; the wrong one is not
    assert (on_truth[1][0] == on_truth[1][1]).all()
    assert (off[1][0][off[1][1] > 0] == 0).mean() > 0.9


def test_a_view_that_does_not_see_the_point_does_not_count():
    cameras = [looking_down(x) for x in (-0.2, 0.0, 0.2)]
    normals, valid, mesh_t, mesh_depth = maps(cameras, 0.0)
    mesh_depth[2] = mesh_depth[2] - 0.05  # the third camera's mesh lies 5 cm in front of the point: occluded
    valid[0][:] = False  # the first camera trusts none of its normals
    agree, seen = normal_agreement(normals, valid, mesh_t, mesh_depth, [K] * 3, cameras, visible_tol_m=0.01)[1]
    assert seen.max() == 0 and agree.max() == 0
    # without the visibility test the third camera counts again
    agree, seen = normal_agreement(normals, valid, mesh_t, mesh_depth, [K] * 3, cameras)[1]
    assert seen[SIZE // 2, SIZE // 2] == 1 and agree[SIZE // 2, SIZE // 2] == 1
    # nor one the pixel's normal faces away from: a normal leaning along +x faces the camera at x = 0.2 only
    # (cosines 0.29 and -0.10 at the middle camera's centre pixel; facing_cos 0.2)
    normals, valid, mesh_t, mesh_depth = maps(cameras, 0.0)
    lean = np.array([1.0, 0.0, 0.1]) / np.linalg.norm([1.0, 0.0, 0.1])
    normals = [np.broadcast_to(lean, n.shape).copy() for n in normals]
    agree, seen = normal_agreement(normals, valid, mesh_t, mesh_depth, [K] * 3, cameras)[1]
    assert seen[SIZE // 2, SIZE // 2] == 1 and agree[SIZE // 2, SIZE // 2] == 1


def test_disagreement_keeps_regions_not_scattered_pixels():
    agree = np.ones((30, 30), np.int32)
    seen = np.full((30, 30), 3, np.int32)
    agree[5:20, 5:20] = 0  # a region no view agrees with
    agree[25, 25] = 0  # one pixel alone
    flagged = disagreement_pixels(agree, seen, window_px=5, min_share=0.6)
    assert flagged[8:17, 8:17].all()  # the region's inside
    assert not flagged[25, 25]
    assert flagged.sum() <= 15 * 15
    # a pixel seen by fewer than min_seen views is not flagged however its neighbours go
    seen[10, 10] = 1
    assert not disagreement_pixels(agree, seen, min_seen=2, window_px=5)[10, 10]
    # the share counts only pixels with a view: a region at the edge of what is seen is kept
    seen[:, 15:] = 0
    assert disagreement_pixels(agree, seen, window_px=5)[8:17, 12:15].all()
    with pytest.raises(ValueError):
        disagreement_pixels(agree, seen[:, :3])


def test_free_depths_lie_past_the_mesh_on_flagged_pixels_only():
    flagged = np.array([[True, False], [True, True]])
    mesh_t = np.array([[1.0, 2.0], [0.0, 1.5]])
    np.testing.assert_allclose(free_depths(flagged, mesh_t, 0.02), [[1.02, 0.0], [0.0, 1.52]], rtol=1e-6)
    with pytest.raises(ValueError):
        free_depths(flagged, mesh_t, 0.0)
