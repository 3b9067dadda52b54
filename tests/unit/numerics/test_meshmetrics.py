"""Mesh metrics: area-uniform sampling, Chamfer, normal consistency and F-scores on analytic shapes."""
from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from stages.numerics.meshmetrics import mesh_metrics, sample_surface


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
