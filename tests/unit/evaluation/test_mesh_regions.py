"""evaluation.mesh_regions on hand-computed cases: a sphere whose upper half is pushed out, a skirt shell's
triangle parts, and the body inside a skirt."""
from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from evaluation.mesh_regions import HEIGHT_BANDS, region_errors, truth_face_regions
from synthetic.garments import SKIRT_PARTS, skirt_shell, skirt_triangle_parts


def sphere(radius: float, resolution: int = 60) -> tuple[np.ndarray, np.ndarray]:
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles, np.int64)


def test_region_errors_split_a_half_pushed_sphere():
    """Truth: a sphere of 0.3 m. Prediction: the same mesh with every vertex above y = 0.05 m scaled by 1.02
    (6 mm out along the radius). The lower cap region (centroids below y = -0.05) is untouched: distance 0 both
    ways, offset 0; the upper cap (above 0.1 m, away from the blend) is 6 mm off both ways, the prediction
    outside (offset +6 mm); the contributions add up to the whole means."""
    gt_v, gt_f = sphere(0.3)
    pred_v = gt_v.copy()
    pred_v[gt_v[:, 1] > 0.05] *= 1.02
    centroid_y = gt_v[gt_f].mean(axis=1)[:, 1]
    region = np.where(centroid_y > 0.1, 0, np.where(centroid_y < -0.05, 1, 2))
    errors = region_errors(pred_v, gt_f, gt_v, gt_f, region, ["upper", "lower", "middle"], n_samples=40_000)
    upper, lower = errors["upper"], errors["lower"]
    # the 60-step polyhedron's flat facets lie up to 0.1 mm inside the scaled sphere's facets' planes
    assert upper["gt_to_pred_median_mm"] == pytest.approx(6.0, abs=0.15)
    assert upper["offset_median_mm"] == pytest.approx(6.0, abs=0.15)
    assert upper["pred_to_gt_median_mm"] == pytest.approx(6.0, abs=0.15)
    assert upper["gt_within_1mm"] == 0.0
    assert lower["gt_to_pred_mean_mm"] == pytest.approx(0.0, abs=0.01)
    assert lower["offset_median_mm"] == pytest.approx(0.0, abs=0.01)
    assert lower["gt_within_1mm"] == 1.0
    # the cap above y = 0.1 m of a 0.3 m sphere holds (1 - 0.1 / 0.3) / 2 = 1/3 of the area
    assert upper["gt_area_share"] == pytest.approx(1 / 3, abs=0.01)
    total = sum(r["gt_to_pred_contribution_mm"] for r in errors.values())
    assert total == pytest.approx(sum(r["gt_to_pred_mean_mm"] * r["gt_area_share"] for r in errors.values()), rel=1e-9)


def test_region_errors_refuses_a_wrong_region_array():
    gt_v, gt_f = sphere(0.3, resolution=10)
    with pytest.raises(ValueError, match="one index"):
        region_errors(gt_v, gt_f, gt_v, gt_f, np.zeros(len(gt_f) - 1, int), ["all"], n_samples=100)
    with pytest.raises(ValueError, match="one index"):
        region_errors(gt_v, gt_f, gt_v, gt_f, np.full(len(gt_f), 1), ["all"], n_samples=100)


def _shell(rings: int = 5, angles: int = 24, radius: float = 0.2, top: float = 0.1, drop: float = 0.3):
    heights = np.linspace(top, top - drop, rings)
    angle = np.arange(angles) * (2 * np.pi / angles)
    return skirt_shell(np.full((rings, angles), radius), heights, angle, np.zeros(2))


def test_skirt_triangle_parts_follow_skirt_shell():
    """Outer triangles use outer vertices only, inner ones inner vertices only; the hem and waist bands join
    both at the lowest and the highest ring."""
    vertices, triangles, is_outer = _shell()
    parts = skirt_triangle_parts(len(triangles), 24)
    assert parts.shape == (len(triangles),)
    assert is_outer[triangles[parts == 0]].all()
    assert not is_outer[triangles[parts == 1]].any()
    for part, y in ((2, vertices[:, 1].min()), (3, vertices[:, 1].max())):
        band = triangles[parts == part]
        assert np.allclose(vertices[band][..., 1], y) and is_outer[band].any(axis=1).all()
        assert (~is_outer[band]).any(axis=1).all()
    assert SKIRT_PARTS[0] == "skirt_outer"
    with pytest.raises(ValueError, match="not a skirt shell"):
        skirt_triangle_parts(len(triangles) - 2, 24)


def test_truth_face_regions_finds_the_body_inside_the_skirt():
    """A body of two spheres (a 0.1 m one inside a skirt of radius 0.2 m, a 0.05 m one below its hem) with the
    skirt appended after it as the simulator does: the inner sphere's faces are body_under_skirt, the lower
    sphere's are height bands, the skirt's four parts keep their order."""
    inner_v, inner_f = sphere(0.1, resolution=12)
    lower_v, lower_f = sphere(0.05, resolution=12)
    lower_v = lower_v + [0.0, -0.5, 0.0]
    skirt_v, skirt_f, _ = _shell(rings=5, angles=24)
    body_v = np.concatenate([inner_v, lower_v])
    body_f = np.concatenate([inner_f, lower_f + len(inner_v)])
    gt_v = np.concatenate([body_v, skirt_v])
    gt_f = np.concatenate([body_f, skirt_f + len(body_v)])
    region, names = truth_face_regions(gt_v, gt_f, garment_triangles=len(skirt_f), skirt_angles=24)
    named = np.array(names)[region]
    assert (named[:len(inner_f)] == "body_under_skirt").all()
    # the lower sphere spans 0.55 .. 0.45 m below the top of 0.65 m: the lowest 6% are feet, the rest legs
    lower_named = named[len(inner_f):len(body_f)]
    lower_fraction = (lower_v[lower_f].mean(axis=1)[:, 1] + 0.55) / 0.65
    assert (lower_named == np.where(lower_fraction < HEIGHT_BANDS[0][2], "feet", "legs")).all()
    assert list(named[len(body_f):]) == [SKIRT_PARTS[p] for p in skirt_triangle_parts(len(skirt_f), 24)]
