"""Mesh metrics: area-uniform sampling, Chamfer, normal consistency and F-scores on analytic shapes, and the
comparable figures on open, partly unseen truths (open hemisphere, inner sphere, one-sided cameras)."""
from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from stages.numerics.meshmetrics import MeshCamera, boundary_edges, cameras_seeing, hole_caps, mesh_metrics, sample_surface


def sphere(radius, resolution=60):
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.triangles, np.int32)


def square(x0, x1, y0=0.0, y1=1.0, z=0.0):
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]], np.int32)


def test_sample_surface_is_area_uniform_with_face_normals():
    # two triangles of area 1/2 (z = 0, normal +z) and 3/2 (x = 5, normal +x)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [5, 1, 0], [5, 0, 3]], np.float64)
    f = np.array([[0, 1, 2], [3, 4, 5]], np.int32)
    pts, nrm = sample_surface(v, f, 40_000, seed=3)
    assert pts.shape == (40_000, 3) and nrm.shape == (40_000, 3)
    first = pts[:, 0] < 2
    assert first.mean() == pytest.approx(0.25, abs=0.01)
    assert np.allclose(nrm[first], (0, 0, 1)) and np.allclose(nrm[~first], (1, 0, 0))
    # inside the triangles, uniformly: the first triangle's mean point is its centroid
    assert np.allclose(pts[first].mean(axis=0), (1 / 3, 1 / 3, 0), atol=0.01)
    assert (pts[first, :2].sum(axis=1) <= 1 + 1e-9).all() and (pts[first] >= -1e-12).all()
    # deterministic per seed
    again, _ = sample_surface(v, f, 10, seed=3)
    assert np.array_equal(again, sample_surface(v, f, 10, seed=3)[0])
    with pytest.raises(ValueError, match="area"):
        sample_surface(v[:3], np.array([[0, 0, 1]]), 10)


def test_identical_meshes_are_perfect():
    v, f = sphere(0.3, resolution=20)
    m = mesh_metrics(v, f, v, f, n_samples=20_000)
    assert m["chamfer_mm"] < 1e-3 and m["normal_consistency"] == pytest.approx(1.0, abs=1e-6)
    assert m["fscore_1mm"] == 1.0 and m["fscore_5mm"] == 1.0
    assert m["precision_1mm"] == 1.0 and m["recall_1mm"] == 1.0
    assert m["mesh_faces"] == len(f) and m["method"] == "surface"


def test_sphere_2mm_larger_gives_2mm_chamfer():
    v, f = sphere(0.3)
    v2, f2 = sphere(0.302)
    m = mesh_metrics(v, f, v2, f2, n_samples=20_000)
    assert m["chamfer_mm"] == pytest.approx(2.0, abs=0.1)
    assert m["chamfer_pred_to_gt_mm"] == pytest.approx(2.0, abs=0.1)
    assert m["chamfer_gt_to_pred_mm"] == pytest.approx(2.0, abs=0.1)
    assert m["fscore_1mm"] == 0.0 and m["fscore_5mm"] == 1.0
    assert m["normal_consistency"] > 0.999
    # point-to-sample distances are biased up by the sample spacing (why "surface" is the default)
    s = mesh_metrics(v, f, v2, f2, n_samples=20_000, method="samples")
    assert s["chamfer_mm"] > m["chamfer_mm"] + 0.5


def test_half_coverage_hand_computed():
    # gt: unit square; pred: its left half, on it. precision 1; gt points with x <= 0.5 + t are recalled;
    # gt-to-pred distance is max(x - 0.5, 0): mean 0.125 m over the square.
    gv, gf = square(0.0, 1.0)
    pv, pf = square(0.0, 0.5)
    m = mesh_metrics(pv, pf, gv, gf, n_samples=100_000, thresholds_m=(0.001, 0.0005))
    assert m["chamfer_pred_to_gt_mm"] < 1e-3
    assert m["chamfer_gt_to_pred_mm"] == pytest.approx(125.0, rel=0.02)
    assert m["chamfer_mm"] == pytest.approx(62.5, rel=0.02)
    assert m["precision_1mm"] == 1.0 and m["recall_1mm"] == pytest.approx(0.501, abs=0.005)
    assert m["fscore_1mm"] == pytest.approx(2 * 0.501 / 1.501, abs=0.005)
    assert "fscore_0p5mm" in m and m["recall_0p5mm"] == pytest.approx(0.5005, abs=0.005)
    assert m["normal_consistency"] == pytest.approx(1.0)


def test_normal_consistency_of_crossed_planes_is_zero_and_sign_free():
    gv, gf = square(0.0, 1.0)
    tilted = np.array([[0.5, 0, -0.5], [0.5, 1, -0.5], [0.5, 1, 0.5], [0.5, 0, 0.5]], np.float64)
    m = mesh_metrics(tilted, gf, gv, gf, n_samples=5_000)
    assert m["normal_consistency"] == pytest.approx(0.0, abs=1e-6)  # perpendicular planes
    flipped = mesh_metrics(gv, gf[:, ::-1], gv, gf, n_samples=5_000)  # reversed winding: |cos| = 1
    assert flipped["normal_consistency"] == pytest.approx(1.0)


def test_mesh_metrics_rejects_bad_arguments():
    v, f = square(0.0, 1.0)
    with pytest.raises(ValueError, match="method"):
        mesh_metrics(v, f, v, f, n_samples=10, method="nearest")
    with pytest.raises(ValueError, match="thresholds"):
        mesh_metrics(v, f, v, f, n_samples=10, thresholds_m=(0.0,))
    with pytest.raises(ValueError, match="faces"):
        mesh_metrics(v, f + 10, v, f, n_samples=10)


# --- comparable figures: open truth, parts no camera sees --------------------------------------------------


def look_at_camera(centre, target=(0.0, 0.0, 0.0), size=200, focal=300.0):
    """A MeshCamera at ``centre`` looking at ``target`` (+y roughly up), ``size`` x ``size`` pixels."""
    c = np.asarray(centre, np.float64)
    forward = np.asarray(target, np.float64) - c
    forward /= np.linalg.norm(forward)
    up = np.array([0.0, 1.0, 0.0]) if abs(forward[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    K = np.array([[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]])
    return MeshCamera(K, np.column_stack([R, -R @ c]), size, size)


def ring_cameras(elevations_deg=(-30.0, 0.0, 30.0, 60.0), count=8, distance=1.0):
    cams = []
    for el in np.deg2rad(elevations_deg):
        for az in np.linspace(0, 2 * np.pi, count, endpoint=False):
            cams.append(look_at_camera(distance * np.array([np.cos(el) * np.sin(az), np.sin(el),
                                                            np.cos(el) * np.cos(az)])))
    return cams


def upper_hemisphere(radius, resolution=60):
    v, f = sphere(radius, resolution)
    keep = (v[f][:, :, 1] >= -1e-6).all(axis=1)
    return v, f[keep]


def test_boundary_edges_and_caps_of_open_and_closed_meshes():
    v, f = sphere(0.1, resolution=20)
    assert boundary_edges(f).shape == (0, 2)
    cap_v, cap_f = hole_caps(v, f)
    assert cap_v.shape == (0, 3) and cap_f.shape == (0, 3)
    hv, hf = upper_hemisphere(0.1, resolution=20)
    edges = boundary_edges(hf)
    assert len(edges) == 40  # the equator of a resolution-20 open3d sphere: 2 * 20 segments
    assert np.allclose(v[edges.ravel(), 1], 0.0, atol=1e-6)
    cap_v, cap_f = hole_caps(hv, hf)
    assert cap_v.shape == (1, 3) and np.allclose(cap_v[0], 0.0, atol=1e-6)  # the equator's centroid
    assert len(cap_f) == len(edges) and (cap_f[:, 0] == len(hv)).all()
    closed = np.concatenate([hf, cap_f])
    assert boundary_edges(closed).shape == (0, 2)  # capped: no opening left
    sq_v, sq_f = square(0.0, 1.0)
    assert len(boundary_edges(sq_f)) == 4


def test_boundary_edges_are_the_sorted_pairs_one_face_uses():
    """Against a direct count over the faces' sorted vertex pairs: the pairs, their order (a, then b) and dtype;
    a pair three faces use is not boundary; a negative index is refused."""
    rng = np.random.default_rng(3)
    faces = rng.integers(0, 40, (300, 3))
    faces = np.concatenate([faces, faces[:20], faces[20:25], faces[20:25]])  # pairs used twice and three times
    counts: dict[tuple[int, int], int] = {}
    for face in faces:
        for a, b in ((face[0], face[1]), (face[1], face[2]), (face[2], face[0])):
            key = (int(min(a, b)), int(max(a, b)))
            counts[key] = counts.get(key, 0) + 1
    expected = np.array(sorted(k for k, c in counts.items() if c == 1), np.int64).reshape(-1, 2)
    edges = boundary_edges(faces)
    assert edges.dtype == np.int64 and np.array_equal(edges, expected)
    with pytest.raises(ValueError, match="non-negative"):
        boundary_edges(np.array([[0, 1, -2]]))


def test_cameras_seeing_a_sphere_from_one_side():
    v, f = sphere(0.1)
    pts, nrm = sample_surface(v, f, 4000, seed=1)
    count = cameras_seeing(v, f, pts, [look_at_camera((0.0, 0.0, 1.0))])
    # a camera at z = 1 sees the cap of the sphere with z > r^2 / d = 0.01 (tangent cone), not the rest
    assert (count[pts[:, 2] > 0.015] == 1).all() and (count[pts[:, 2] < 0.005] == 0).all()
    # a point outside the image is not seen
    narrow = look_at_camera((0.0, 0.0, 1.0), size=4)
    assert cameras_seeing(v, f, np.array([[0.0, 0.099, 0.0135]]), [narrow])[0] == 0
    with pytest.raises(ValueError, match="tolerance"):
        cameras_seeing(v, f, pts, [narrow], tolerance_m=0.0)


def test_open_hemisphere_truth_against_closed_sphere_prediction():
    # the truth is open at the equator; a closed reconstruction must cap it: plain figures count the cap
    # (the lower half, up to 10 cm off), comparable ones leave it and the rim's band out
    r = 0.1
    gv, gf = upper_hemisphere(r, resolution=80)
    pv, pf = sphere(r, resolution=80)
    cams = ring_cameras()
    m = mesh_metrics(pv, pf, gv, gf, n_samples=40_000, cameras=cams)
    # measured 27.2 mm and 0.693 (the same vertices: every comparable distance is 0)
    assert m["chamfer_pred_to_gt_mm"] == pytest.approx(27.2, rel=0.05) and m["fscore_5mm"] == pytest.approx(0.69, abs=0.02)
    assert m["comparable_chamfer_mm"] < 0.01 and m["comparable_fscore_1mm"] == pytest.approx(1.0, abs=1e-3)
    # the 1 cm band above the rim is 1 cm of the hemisphere's 10 cm height: 10% of its area
    assert m["gt_boundary_area_fraction"] == pytest.approx(0.10, abs=0.015)
    assert m["gt_unseen_area_fraction"] < 0.01  # the outside is seen; the inside, behind the cap, is not sampled
    assert m["comparable_gt_area_fraction"] == pytest.approx(0.90, abs=0.015)
    # the lower half and the band's mirror on the upper half are left out of the prediction: 45% kept
    assert m["comparable_pred_area_fraction"] == pytest.approx(0.45, abs=0.02)
    assert m["pred_far_from_truth_area_fraction"] == 0.0
    # the lower half closes the opening, within its radius of the fan: not a surface the cameras contradict,
    # though the ring's lower cameras see the space it stands in
    assert m["pred_seen_through_area_fraction"] == 0.0
    # the plain figures are the ones mesh_metrics gives without cameras
    plain = mesh_metrics(pv, pf, gv, gf, n_samples=40_000)
    assert plain["chamfer_mm"] == m["chamfer_mm"] and "comparable_chamfer_mm" not in plain


def test_unseen_inner_part_of_the_truth_is_left_out():
    # truth: a sphere with a smaller one inside it (teeth in a head); no camera sees the inner one
    r, r_in = 0.1, 0.05
    ov, of = sphere(r)
    iv, i_f = sphere(r_in)
    gv = np.concatenate([ov, iv])
    gf = np.concatenate([of, i_f + len(ov)])
    m = mesh_metrics(ov, of, gv, gf, n_samples=40_000, cameras=ring_cameras())
    inner_share = r_in ** 2 / (r ** 2 + r_in ** 2)  # 20% of the area
    assert m["gt_unseen_area_fraction"] == pytest.approx(inner_share, abs=0.01)
    assert m["chamfer_gt_to_pred_mm"] == pytest.approx(1000 * (r - r_in) * inner_share, rel=0.05)
    assert m["comparable_chamfer_mm"] < 0.01 and m["comparable_fscore_1mm"] == pytest.approx(1.0, abs=1e-3)
    assert m["comparable_pred_area_fraction"] == 1.0 and m["gt_boundary_area_fraction"] == 0.0


def test_comparable_figures_keep_errors_larger_than_the_tolerance():
    r = 0.1
    gv, gf = sphere(r)
    front = [look_at_camera((0.0, 0.0, 1.0)), look_at_camera((0.3, 0.0, 0.95)), look_at_camera((-0.3, 0.0, 0.95))]
    # the back half (unseen by these cameras) pushed in by 3 mm: within the 5 mm tolerance, left out
    for push_mm, counted in ((3.0, False), (20.0, True)):
        pv = gv.astype(np.float64).copy()
        back = pv[:, 2] < -0.03
        pv[back] *= (r - push_mm / 1000) / r
        m = mesh_metrics(pv, gf, gv, gf, n_samples=40_000, cameras=front)
        assert m["gt_unseen_area_fraction"] > 0.4
        if counted:  # 20 mm is an error no rule may hide: the pushed samples still count, at their distance
            assert m["pred_far_from_truth_area_fraction"] > 0.2
            assert m["comparable_chamfer_pred_to_gt_mm"] > 5.0
            # but inside the truth, behind its seen front, no camera sees through them
            assert m["pred_seen_through_area_fraction"] == 0.0
        else:
            assert m["pred_far_from_truth_area_fraction"] == 0.0
            assert m["comparable_chamfer_pred_to_gt_mm"] < 0.3
    # a floater 5 cm from the sphere counts in both figures
    fv, ff = sphere(0.02, resolution=20)
    fv = fv + np.array([0.0, 0.0, r + 0.05])
    pv = np.concatenate([gv, fv])
    pf = np.concatenate([gf, ff + len(gv)])
    m = mesh_metrics(pv, pf, gv, gf, n_samples=40_000, cameras=ring_cameras())
    assert m["comparable_chamfer_pred_to_gt_mm"] == pytest.approx(m["chamfer_pred_to_gt_mm"], rel=0.02)
    # the floater hangs in space the ring's cameras see through: its share of the prediction's area,
    # 0.02^2 / (0.1^2 + 0.02^2) = 3.8%, all of it seen through
    assert m["pred_seen_through_area_fraction"] == pytest.approx(0.02 ** 2 / (r ** 2 + 0.02 ** 2), abs=0.004)
    assert m["comparable_pred_area_fraction"] == 1.0


def test_comparable_figures_of_a_truth_no_camera_sees_are_only_its_shares():
    v, f = sphere(0.1, resolution=20)
    away = look_at_camera((0.0, 0.0, 1.0), target=(0.0, 0.0, 2.0))
    m = mesh_metrics(v, f, v, f, n_samples=2000, cameras=[away])
    assert m["gt_unseen_area_fraction"] == 1.0 and m["comparable_gt_area_fraction"] == 0.0
    assert "comparable_chamfer_mm" not in m and "comparable_fscore_1mm" not in m
    assert all(np.isfinite(x) for x in m.values() if isinstance(x, float))
    with pytest.raises(ValueError, match="comparable_tolerance_m"):
        mesh_metrics(v, f, v, f, n_samples=10, cameras=[away], comparable_tolerance_m=0.0)
