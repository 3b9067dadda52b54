"""Pinhole rays and mesh ray casting (stages.numerics.raycast)."""
from __future__ import annotations

import numpy as np
import pytest

from stages.numerics.raycast import camera_rays, render_mesh


def _sphere(radius: float = 0.5, n: int = 40):
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=n)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def _camera(distance: float = 2.0):
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    # camera on +z looking at the origin: x_cam = R x + t with R flipping y and z
    R = np.diag([1.0, -1.0, -1.0])
    t = -R @ np.array([0.0, 0.0, distance])
    return K, np.concatenate([R, t[:, None]], axis=1)


def test_rays_through_principal_point_and_corner():
    K, P = _camera()
    origins, dirs, z_per_t = camera_rays(K, P, 48, 64, pixels=np.array([[31.5, 23.5], [131.5, 23.5]]))
    np.testing.assert_allclose(origins, [[0, 0, 2.0]] * 2)
    np.testing.assert_allclose(dirs[0], [0, 0, -1], atol=1e-12)  # straight at the origin
    # 100 px right of the principal point at f = 100: 45 degrees, toward +x (image right = world +x here)
    np.testing.assert_allclose(dirs[1], [np.sqrt(0.5), 0, -np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(z_per_t, [1.0, np.sqrt(0.5)], atol=1e-12)
    assert camera_rays(K, P, 48, 64)[1].shape == (48 * 64, 3)


def test_render_sphere_depth_and_normals():
    vertices, faces = _sphere(0.5, 60)
    K, P = _camera(2.0)
    out = render_mesh(vertices, faces, K, P, 48, 64)
    assert out["depth_m"].shape == (48, 64) and out["normals_world"].shape == (48, 64, 3)
    # the centre pixel sees the sphere's nearest point, 1.5 m away, with normal toward the camera
    centre_depth = out["depth_m"][23:25, 31:33].mean()
    assert centre_depth == pytest.approx(1.5, abs=2e-3)
    np.testing.assert_allclose(out["normals_world"][24, 32], [0, 0, 1], atol=0.05)
    # silhouette: radius on the image = f * r / sqrt(d^2 - r^2)
    radius_px = 100 * 0.5 / np.sqrt(2.0**2 - 0.5**2)
    assert out["hit"].sum() == pytest.approx(np.pi * radius_px**2, rel=0.05)
    assert np.all(out["depth_m"][~out["hit"]] == 0) and np.all(out["face"][~out["hit"]] == -1)
    assert np.all(np.isfinite(out["depth_m"]))
    # every hit normal faces the camera
    _, dirs, _ = camera_rays(K, P, 48, 64)
    facing = np.sum(out["normals_world"].reshape(-1, 3) * dirs, axis=-1)
    assert np.all(facing[out["hit"].ravel()] < 0)


def test_render_mesh_rejects_bad_input():
    K, P = _camera()
    with pytest.raises(ValueError, match="no faces"):
        render_mesh(np.zeros((3, 3)), np.zeros((0, 3), int), K, P, 4, 4)
    with pytest.raises(ValueError, match="K must be"):
        camera_rays(np.eye(2), P, 4, 4)


def _half_plane(edge_x: float):
    """A large quad at z = 1 covering x >= edge_x, and a camera at the origin looking down +z (f = 10 px,
    principal point (5, 4)): pixel column i looks at x = (i - 5) / 10 on the plane."""
    from stages.numerics.raycast import mesh_scene

    v = np.array([[edge_x, -10, 1], [10, -10, 1], [10, 10, 1], [edge_x, 10, 1]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    K = np.array([[10.0, 0, 5.0], [0, 10.0, 4.0], [0, 0, 1]])
    return mesh_scene(v, f), K, np.hstack([np.eye(3), np.zeros((3, 1))])


@pytest.mark.parametrize("samples", [2, 4])
def test_pixel_coverage_of_a_half_covered_column(samples):
    from stages.numerics.raycast import pixel_coverage

    # the edge through column 5's centre: it is half covered, columns left of it empty, right of it full
    scene, K, P = _half_plane(0.0)
    cov = pixel_coverage(K, P, 8, 10, samples, scene)
    assert cov.shape == (8, 10) and cov.dtype == np.float32
    np.testing.assert_allclose(cov, np.broadcast_to([0, 0, 0, 0, 0, 0.5, 1, 1, 1, 1], (8, 10)))
    # the edge a quarter pixel right of column 5's centre: a quarter of it is covered (4 x 4 rays at
    # offsets -3/8, -1/8, 1/8, 3/8 px: one column of them lies beyond +1/4)
    scene, K, P = _half_plane(0.025)
    assert pixel_coverage(K, P, 8, 10, 4, scene)[0, 5] == pytest.approx(0.25)


def test_pixel_coverage_bands_and_one_sample():
    from stages.numerics.raycast import mesh_scene, pixel_coverage

    v, f = _sphere(n=200)  # fine enough that the inscribed polygon's silhouette is the disc's within 0.1%
    K, P = _camera(3.0)  # the whole disc inside the 64 x 48 image
    scene = mesh_scene(v, f)
    whole = pixel_coverage(K, P, 48, 64, 3, scene, edges_only=False)
    # a convex subject has no feature between pixel centres: the edge pixels' grids alone give the same,
    # in chunks of any size
    np.testing.assert_array_equal(pixel_coverage(K, P, 48, 64, 3, scene), whole)
    np.testing.assert_array_equal(pixel_coverage(K, P, 48, 64, 3, scene, chunk_pixels=7), whole)
    edge = (whole > 0) & (whole < 1)
    assert edge.sum() > 20 and np.all(np.isin(np.round(whole * 9), np.arange(10)))
    hit = render_mesh(None, None, K, P, 48, 64, scene=scene)["hit"]
    np.testing.assert_array_equal(pixel_coverage(K, P, 48, 64, 1, scene), hit.astype(np.float32))
    # the caller's own centre render gives the same
    np.testing.assert_array_equal(pixel_coverage(K, P, 48, 64, 3, scene, centre_hit=hit), whole)
    with pytest.raises(ValueError, match="centre_hit"):
        pixel_coverage(K, P, 48, 64, 3, scene, centre_hit=hit[1:])
    # the disc's area: pi r^2 with r the sphere's apparent radius (f r / sqrt(d^2 - r^2) px), within 1%
    # (a 3 x 3 grid per pixel: the edge pixels' coverage errors, up to 1/18, average out along the rim)
    radius_px = 100.0 * 0.5 / np.sqrt(3.0 ** 2 - 0.5 ** 2)
    assert whole.sum() == pytest.approx(np.pi * radius_px ** 2, rel=0.01)
    for bad in (0, 1.5):
        with pytest.raises(ValueError, match="samples"):
            pixel_coverage(K, P, 48, 64, bad, scene)


def test_pixel_coverage_edges_only_misses_a_sliver_between_pixel_centres():
    from stages.numerics.raycast import mesh_scene, pixel_coverage

    # a strip at x in [0.01, 0.04] on z = 1: inside column 5's square (x in [-0.05, 0.05]) but off every
    # pixel centre (x = 0, 0.1): the full grid sees it (rays at x = 0.0125 and 0.0375), the edge test does not
    v = np.array([[0.01, -10, 1], [0.04, -10, 1], [0.04, 10, 1], [0.01, 10, 1]], float)
    scene = mesh_scene(v, np.array([[0, 1, 2], [0, 2, 3]]))
    K = np.array([[10.0, 0, 5.0], [0, 10.0, 4.0], [0, 0, 1]])
    P = np.hstack([np.eye(3), np.zeros((3, 1))])
    full = pixel_coverage(K, P, 8, 10, 4, scene, edges_only=False)
    np.testing.assert_allclose(full, np.broadcast_to([0, 0, 0, 0, 0, 0.5, 0, 0, 0, 0], (8, 10)))
    assert not pixel_coverage(K, P, 8, 10, 4, scene).any()


def test_subpixel_depths_grid_on_a_half_plane():
    from stages.numerics.raycast import pixel_coverage, subpixel_depths

    # plane z = 1 for x >= 0.025: column 5 (x in [-0.05, 0.05]) is hit by the rays right of x = 0.025 only
    scene, K, P = _half_plane(0.025)
    rows, cols = np.array([0, 3, 7]), np.array([5, 6, 1])
    out = subpixel_depths(K, P, 8, 10, rows, cols, 4, scene)
    assert out["depth_m"].shape == (3, 16) and out["depth_m"].dtype == np.float32
    offsets = np.array([-3, -1, 1, 3]) / 8
    # row-major grid: the first 4 rays share the smallest v offset and run through the u offsets
    np.testing.assert_allclose(out["u"][0, :4], 5 + offsets)
    np.testing.assert_allclose(out["v"][0, ::4], 0 + offsets)
    np.testing.assert_allclose(out["v"][1, :4], 3 - 3 / 8)
    # column 5: the rays at u offset +3/8 (x = 0.0375) hit the plane at z = 1; the others miss
    expected = np.tile([0.0, 0.0, 0.0, 1.0], 4)
    np.testing.assert_allclose(out["depth_m"][0], expected, atol=1e-6)
    np.testing.assert_allclose(out["depth_m"][1], 1.0, atol=1e-6)  # column 6: wholly on the plane
    assert not out["depth_m"][2].any()  # column 1: wholly off it
    # chunking changes nothing, and pixel_coverage is the share of hits
    np.testing.assert_array_equal(subpixel_depths(K, P, 8, 10, rows, cols, 4, scene, chunk_pixels=2)["depth_m"],
                                  out["depth_m"])
    assert pixel_coverage(K, P, 8, 10, 4, scene)[0, 5] == pytest.approx(0.25)
    empty = subpixel_depths(K, P, 8, 10, np.zeros(0, int), np.zeros(0, int), 3, scene)
    assert empty["depth_m"].shape == (0, 9)
    with pytest.raises(ValueError, match="samples"):
        subpixel_depths(K, P, 8, 10, rows, cols, 0, scene)
    with pytest.raises(ValueError, match="differ in length"):
        subpixel_depths(K, P, 8, 10, rows, cols[:2], 2, scene)


def test_occlusion_edges_hand_case():
    from stages.numerics.raycast import occlusion_edges

    depth = np.zeros((5, 9), np.float32)
    depth[:, 1:5] = 2.0   # a surface at 2 m ...
    depth[:, 5:8] = 2.03  # ... next to one 3 cm behind it; columns 0 and 8 hold no surface
    edges = occlusion_edges(depth, 0.01)
    assert edges.dtype == bool and edges.shape == depth.shape
    # the jump between columns 4 and 5: both sides' pixels; columns 1 and 7 touch the background: not edges
    np.testing.assert_array_equal(edges[2], [0, 0, 0, 0, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(edges, np.broadcast_to(edges[2], edges.shape))
    assert not occlusion_edges(depth, 0.05).any()  # a jump smaller than the threshold is no edge
    assert not occlusion_edges(np.zeros((4, 4)), 0.01).any()  # no surface anywhere
    assert not occlusion_edges(np.ones((4, 4)), 0.01).any()  # one flat surface
    # a plane tilted so that its depth grows 6 mm per pixel: spans 12 mm over a 3 x 3 neighbourhood (6 mm at
    # the image's first and last columns, whose neighbourhood is padded with their own values)
    ramp = 2.0 + 0.006 * np.arange(8)[None, :].repeat(4, 0)
    np.testing.assert_array_equal(occlusion_edges(ramp, 0.01)[0], [0, 1, 1, 1, 1, 1, 1, 0])
    assert not occlusion_edges(ramp, 0.015).any()
    with pytest.raises(ValueError, match="jump_m"):
        occlusion_edges(depth, 0.0)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        occlusion_edges(depth[..., None], 0.01)
