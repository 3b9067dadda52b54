"""evaluation.release's figures on hand-computed cases: the pooled angular errors, one camera's maps against
the truth, the cameras' pose errors, the mesh figures of an offset and a scaled sphere (analytic values), PSNR,
and the relit truth's cache."""
from __future__ import annotations

import json

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import open3d as o3d
import pytest

from evaluation.release import (RelitTruthCache, _AlbedoSums, _ErrorPool, _MapsAction, _maps_combine,
                                _means_over_actions, _mesh_overall, _psnr_from_mse, _relit_parts, camera_errors,
                                evaluate_camera, relit_truth_lights, simulator_digest, summary_rows)
from pipeline.codecs.mesh import write_ply
from stages.numerics.meshmetrics import mesh_metrics
from synthetic.rig import look_at


def test_error_pool_mean_median_and_shares_hand_computed():
    """Errors 1, 2, 5, 10, 30 degrees: mean 9.6 (exact, not binned), median 5 (within its 0.05 degree bin), 60%
    at or under 5 degrees and 80% at or under 25: the same <= rule as stages.numerics.metrics.normal_error_stats
    and the held-out protocol, so an error of exactly 5 degrees counts."""
    from stages.numerics.metrics import normal_error_stats

    errors = np.array([1.0, 2.0, 5.0, 10.0, 30.0], np.float32)
    pool = _ErrorPool()
    pool.add(errors[:2])
    pool.add(np.zeros(0, np.float32))  # nothing added
    pool.add(errors[2:])
    stats = pool.stats()
    assert stats["count"] == 5 and stats["mean"] == pytest.approx(9.6)
    assert stats["median"] == pytest.approx(5.0, abs=0.05)
    assert stats["under5_pct"] == pytest.approx(60.0)
    assert stats["under25_pct"] == pytest.approx(80.0)
    plain = normal_error_stats(errors)
    assert (stats["under5_pct"], stats["under25_pct"]) == (plain["under5_pct"], plain["under25_pct"])
    assert _ErrorPool().stats() == {}
    # 180 degrees (an inverted normal) lands in the last bin, not outside the histogram
    inverted = _ErrorPool()
    inverted.add(np.array([180.0, 180.0, 0.0]))
    assert inverted.stats()["median"] == pytest.approx(180.0, abs=0.05) and inverted.stats()["mean"] == 120.0


def test_psnr_from_mse():
    assert _psnr_from_mse(0.01) == pytest.approx(20.0)
    assert _psnr_from_mse(0.04, peak=2.0) == pytest.approx(20.0)
    assert _psnr_from_mse(0.0) == pytest.approx(120.0)  # the MSE floor 1e-12 keeps it finite


def _truth_maps(h: int, w: int) -> dict[str, np.ndarray]:
    """Truth at twice (h, w): normal +z, albedo 0.5 on the subject (0 beyond it, as the simulator writes), the subject on the left half of the picture, its upper half
    fully visible (1.0) and its lower half occluded (0.5)."""
    normal = np.zeros((2 * h, 2 * w, 3), np.float32)
    normal[..., 2] = 1.0
    mask = np.zeros((2 * h, 2 * w), bool)
    mask[:, :w] = True
    visibility = np.where(np.arange(2 * h)[:, None] < h, 1.0, 0.5) * np.ones((1, 2 * w))
    return {"normal": normal, "albedo": np.where(mask[..., None], np.full(3, 0.5, np.float32), 0).astype(np.float32), "mask": mask,
            "visibility": visibility.astype(np.float32)}


def test_evaluate_camera_hand_computed_at_half_the_truths_size():
    """A 4 x 4 camera against 8 x 8 truth: the subject is the left two columns (8 px), rows 0-1 unoccluded. One
    valid pixel's normal is off by 90 degrees, one foreground pixel has alpha 0 (not valid, still in 'all'), the
    albedo is 0.6 on the subject (+0.1: 20 dB), the estimated mask has one pixel too many."""
    h = w = 4
    truth = _truth_maps(h, w)
    normals = np.zeros((h, w, 3), np.float32)
    normals[..., 2] = 1.0
    normals[0, 0] = [1.0, 0.0, 0.0]  # 90 degrees, unoccluded row
    alpha = np.zeros((h, w), np.float32)
    alpha[:, :2] = 1.0
    alpha[3, 1] = 0.0  # an occluded foreground pixel without a normal
    normals[3, 1] = 0.0
    albedo = np.zeros((h, w, 3), np.float32)
    albedo[:, :2] = 0.6
    mask = np.zeros((h, w), bool)
    mask[:, :2] = True
    mask[0, 2] = True
    res = evaluate_camera(normals, alpha, albedo, mask, truth)
    assert res["fg_pixels"] == 8 and res["valid_fraction"] == pytest.approx(7 / 8)
    np.testing.assert_allclose(np.sort(res["err_valid"]), [0] * 6 + [90], atol=1e-4)
    assert len(res["err_all"]) == 8 and np.sort(res["err_all"])[-2:].tolist() == pytest.approx([90, 90])
    assert len(res["err_valid_unoccluded"]) == 4 and res["err_valid_unoccluded"].max() == pytest.approx(90)
    assert len(res["err_valid_occluded"]) == 3 and res["err_valid_occluded"].max() == pytest.approx(0, abs=1e-4)
    assert len(res["err_all_occluded"]) == 4 and len(res["err_all_unoccluded"]) == 4
    assert res["albedo_sq_count"] == 24 and res["albedo_sq_sum"] == pytest.approx(24 * 0.01, rel=1e-5)
    assert _psnr_from_mse(res["albedo_sq_sum"] / res["albedo_sq_count"]) == pytest.approx(20.0, abs=1e-4)
    assert res["mask_iou"] == pytest.approx(8 / 9)
    assert 0.9 < res["albedo_ssim"] < 1.0
    # the second normal and albedo maps are scored over the same pixels
    exact = evaluate_camera(normals, alpha, albedo, mask, truth, diffuse_normals=truth["normal"][::2, ::2],
                            diffuse_albedo=np.full((h, w, 3), 0.5, np.float32))
    assert len(exact["err_valid_diffuse"]) == 7 and exact["err_valid_diffuse"].max() < 1e-4
    assert exact["albedo_diffuse_sq_sum"] == 0.0


def test_camera_errors_hand_computed():
    """Four true cameras; the release has three of them: one exact, one turned by 1 degree about its optical axis,
    one moved by 10 mm, at half the truth's size with one focal length 2% long: means 1/3 degree, 10/3 mm,
    2/3 %."""
    from scipy.spatial.transform import Rotation

    K = np.array([[400.0, 0, 100], [0, 400.0, 150], [0, 0, 1]])
    truth = {}
    for i, angle in enumerate((0, 90, 180, 270)):
        a = math.radians(angle)
        pose = look_at(np.array([3 * math.sin(a), 1.0, 3 * math.cos(a)]), np.array([0.0, 1.0, 0.0]))
        truth[f"{i:05d}"] = {"camera_id": f"{i:05d}", "K": K.tolist(), "width": 200, "height": 300,
                             "cam_from_world": pose.tolist()}
    frames = []
    for cam in ("00000", "00001", "00002"):
        pose = np.asarray(truth[cam]["cam_from_world"], float)
        focal = 200.0
        if cam == "00001":
            pose = np.column_stack([Rotation.from_euler("z", 1.0, degrees=True).as_matrix() @ pose[:, :3],
                                    Rotation.from_euler("z", 1.0, degrees=True).as_matrix() @ pose[:, 3]])
        if cam == "00002":
            centre = -pose[:, :3].T @ pose[:, 3] + np.array([0.0, 0.01, 0.0])
            pose = np.column_stack([pose[:, :3], -pose[:, :3] @ centre])
            focal = 204.0
        frames.append({"camera_id": cam, "cam_from_world_opencv": np.vstack([pose, [0, 0, 0, 1]]).tolist(),
                       "w": 100, "fl_x": focal})
    errors = camera_errors({"frames": frames}, truth)
    assert errors["cameras_registered"] == 3
    assert errors["cam_rotation_err_deg"] == pytest.approx(1 / 3, abs=1e-6)
    assert errors["cam_center_err_mm"] == pytest.approx(10 / 3, abs=1e-6)
    assert errors["cam_focal_err_pct"] == pytest.approx(2 / 3, abs=1e-9)


def sphere(radius: float, centre=(0.0, 0.0, 0.0), resolution: int = 60) -> tuple[np.ndarray, np.ndarray]:
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    return np.asarray(mesh.vertices) + np.asarray(centre), np.asarray(mesh.triangles, np.int64)


def test_offset_sphere_chamfer_fscore_and_normal_consistency_are_analytic():
    """A sphere of radius R against the same sphere moved by d < R. From a point at polar angle theta about the
    offset, the distance to the other sphere is |sqrt(R^2 + d^2 - 2 R d cos theta) - R|; cos theta is uniform on
    [-1, 1] over the area, so that distance r - R has density r / (2 R d) on [R - d, R + d]: its mean is d / 2
    (each direction, so the Chamfer is d / 2), the share within t <= d is t / d (precision = recall = F-score), and
    the mean cosine between the normals is 1 - d^2 / (3 R^2). R = 0.3 m, d = 50 mm: 25 mm, F(5 mm) = 0.1,
    F(25 mm) = 0.5, NC = 0.99074."""
    R, d = 0.3, 0.05
    gt_v, gt_f = sphere(R)
    pred_v, pred_f = sphere(R, centre=(d, 0.0, 0.0))
    m = mesh_metrics(pred_v, pred_f, gt_v, gt_f, n_samples=40_000, thresholds_m=(0.005, 0.025, 0.06))
    # the 60-step polyhedra lie up to 0.1 mm inside their spheres; 40k samples: +-0.003 on a share
    assert m["chamfer_mm"] == pytest.approx(1000 * d / 2, abs=0.15)
    assert m["chamfer_pred_to_gt_mm"] == pytest.approx(25.0, abs=0.15)
    assert m["chamfer_gt_to_pred_mm"] == pytest.approx(25.0, abs=0.15)
    assert m["fscore_5mm"] == pytest.approx(0.1, abs=0.01)
    assert m["fscore_25mm"] == pytest.approx(0.5, abs=0.01)
    assert m["precision_5mm"] == pytest.approx(0.1, abs=0.01) and m["recall_5mm"] == pytest.approx(0.1, abs=0.01)
    assert m["fscore_60mm"] == 1.0  # every distance is below d
    # the facets' normals differ from the spheres' by up to 1.5 degrees: about 3e-4 off the analytic 0.99074
    assert m["normal_consistency"] == pytest.approx(1 - d ** 2 / (3 * R ** 2), abs=6e-4)


def test_scaled_sphere_chamfer_is_the_radius_change():
    """A sphere 5% larger: every point is 0.05 R = 15 mm from the other surface, in both directions; no point is
    within 5 mm (F = 0), all within 20 mm (F = 1); the normals stay parallel."""
    gt_v, gt_f = sphere(0.3)
    m = mesh_metrics(gt_v * 1.05, gt_f, gt_v, gt_f, n_samples=20_000, thresholds_m=(0.005, 0.02))
    assert m["chamfer_mm"] == pytest.approx(15.0, abs=0.1)
    assert m["chamfer_pred_to_gt_mm"] == pytest.approx(15.0, abs=0.1)
    assert m["fscore_5mm"] == 0.0 and m["fscore_20mm"] == 1.0
    assert m["normal_consistency"] > 0.999


def test_mesh_overall_reads_the_release_and_truth_meshes(tmp_path):
    """_mesh_overall on a release whose one action's mesh is the true sphere moved by 20 mm: the figures of
    mesh_metrics (Chamfer d / 2 = 10 mm), per action and as metrics rows in mm; an action without a mesh is left
    out."""
    gt_v, gt_f = sphere(0.3)
    write_ply(tmp_path / "truth" / "A0000" / "mesh.ply", gt_v, gt_f)
    write_ply(tmp_path / "truth" / "A0001" / "mesh.ply", gt_v, gt_f)
    write_ply(tmp_path / "pred.ply", gt_v + np.array([0.02, 0.0, 0.0]), gt_f)
    (tmp_path / "truth" / "cameras").mkdir()
    (tmp_path / "truth" / "cameras" / "S000.json").write_text(json.dumps({"cameras": _axis_cameras()}))
    actions = {"A0000": SimpleNamespace(kinds={"mesh"}, path=lambda kind: tmp_path / "pred.ply",
                                        info={"session_id": "S000"}),
               "A0001": SimpleNamespace(kinds=set(), path=None, info={"session_id": "S000"})}
    rel = SimpleNamespace(action=actions.__getitem__)
    per_action: dict = {}
    rows: list = []
    overall = _mesh_overall(rel, tmp_path / "truth", ["A0000", "A0001"], per_action, rows, "run")
    assert overall["chamfer_mm"] == pytest.approx(10.0, abs=0.15)
    assert overall["fscore_1mm"] == pytest.approx(0.05, abs=0.01)  # t / d = 1 / 20
    assert overall["fscore_5mm"] == pytest.approx(0.25, abs=0.01)
    assert overall["mesh_faces"] == len(gt_f)
    assert set(per_action) == {"A0000"} and per_action["A0000"]["chamfer_mm"] == overall["chamfer_mm"]
    chamfer = [r for r in rows if r["metric"] == "chamfer_mm"]
    assert len(chamfer) == 1 and chamfer[0]["unit"] == "mm" and chamfer[0]["region"] == "mesh"
    assert chamfer[0]["source"] == "evaluate" and chamfer[0]["action_id"] == "A0000"
    # Six cameras on the axes see all of the closed sphere: the comparable figures keep it whole.
    assert overall["comparable_chamfer_mm"] == pytest.approx(overall["chamfer_mm"], abs=0.3)


def _axis_cameras(distance_m: float = 2.0, size: int = 64) -> list[dict]:
    """Six pinhole cameras on the axes at ``distance_m``, each looking at the origin (cameras.json records)."""
    cameras = []
    for i, axis in enumerate(np.concatenate([np.eye(3), -np.eye(3)])):
        centre = distance_m * axis
        forward = -axis
        up = np.array([0.0, 1.0, 0.0]) if abs(axis[1]) < 0.5 else np.array([0.0, 0.0, 1.0])
        right = np.cross(forward, up)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])
        K = [[size, 0.0, size / 2], [0.0, size, size / 2], [0.0, 0.0, 1.0]]
        cameras.append({"camera_id": f"{i:05d}", "K": K, "width": size, "height": size,
                        "cam_from_world": np.hstack([R, (-R @ centre)[:, None]]).tolist()})
    return cameras


def test_relit_parts_are_means_over_actions_in_order():
    """The worker results of two actions put together: each metric the mean over the actions that have it, the
    relit rows action by action, then the relighting-set rows metric by metric."""
    a = ({"relit_psnr_db": 20.0, "relightset_image_psnr_db": 18.0, "relightset_albedo_psnr_db": 25.0},
         [{"metric": "relit_psnr_db", "a": 0}], [{"metric": "relightset_albedo_psnr_db", "a": 0},
                                                   {"metric": "relightset_image_psnr_db", "a": 0}])
    b = ({"relit_psnr_db": 24.0, "relightset_image_psnr_db": 22.0}, [{"metric": "relit_psnr_db", "a": 1}],
         [{"metric": "relightset_image_psnr_db", "a": 1}])
    empty = ({}, [], [])
    relit, relightset, per_action, rows = _relit_parts(["A0", "A1", "A2"], [a, b, empty])
    assert relit == {"relit_psnr_db": 22.0}
    assert relightset == {"relightset_image_psnr_db": 20.0, "relightset_albedo_psnr_db": 25.0}
    assert set(per_action) == {"A0", "A1"}
    assert [(r["metric"], r["a"]) for r in rows] == [("relit_psnr_db", 0), ("relit_psnr_db", 1),
                                                     ("relightset_image_psnr_db", 0), ("relightset_image_psnr_db", 1),
                                                     ("relightset_albedo_psnr_db", 0)]


def test_error_pools_merged_equal_one_pool():
    """Errors pooled in two pools and merged give the figures of one pool that took them all (the actions'
    pools of the evaluation's workers put together)."""
    rng = np.random.default_rng(0)
    errors = rng.uniform(0.0, 40.0, 1001)
    whole, first, second = _ErrorPool(), _ErrorPool(), _ErrorPool()
    whole.add(errors)
    first.add(errors[:400])
    second.add(errors[400:])
    first.merge(second)
    assert first.stats() == pytest.approx(whole.stats(), rel=1e-12)
    assert first.count == 1001 and first.hist.sum() == 1001


def _maps_action(errors: list[float], ssim: float, iou: float, sq: float, count: int, action: str) -> _MapsAction:
    pools = {region: _ErrorPool() for region in ("valid", "all", "valid_unoccluded", "valid_occluded",
                                                 "all_unoccluded", "all_occluded")}
    for pool in pools.values():
        pool.add(np.array(errors))
    return _MapsAction(pools, _ErrorPool(), _AlbedoSums(sq=sq, count=count, valid_px=count / 2, fg_px=count),
                       [ssim], [iou], 0.0, 0, {"normal_mean_deg": float(np.mean(errors))},
                       [{"action_id": action}])


def test_maps_combine_pools_pixels_not_action_means():
    """Two actions' maps: the normal mean is over all pixels (1, 2, 3 and 10: 4.0, not the mean 6.0 of the two
    actions' means 2.0 and 10.0), the albedo PSNR from the summed squared error (0.05 over 5 values: 20 dB), the
    SSIM and IoU means over views, the rows action by action."""
    a = _maps_action([1.0, 2.0, 3.0], 0.9, 0.8, 0.04, 4, "A0")
    b = _maps_action([10.0], 0.7, 1.0, 0.01, 1, "A1")
    maps, diffuse, per_action, rows = _maps_combine(["A0", "A1"], [a, b])
    assert maps["normal_mean_deg"] == pytest.approx(4.0)
    assert maps["normal_under5_pct"] == pytest.approx(75.0)
    assert maps["albedo_psnr_db"] == pytest.approx(20.0)
    assert maps["albedo_ssim"] == pytest.approx(0.8) and maps["mask_iou"] == pytest.approx(0.9)
    assert maps["valid_fraction"] == pytest.approx(0.5)
    assert diffuse == {}  # no specular-fitted maps
    assert per_action == {"A0": {"normal_mean_deg": 2.0}, "A1": {"normal_mean_deg": 10.0}}
    assert [r["action_id"] for r in rows] == ["A0", "A1"]


def test_means_over_actions_only_over_actions_that_have_the_figure():
    """A figure's mean is over the actions that have it; a figure an action returns without recording it per
    action (``heldout_albedo_view_dependent``) is averaged too; rows keep the actions' order."""
    a = ({"chamfer_mm": 1.0, "view_dependent": 1.0}, {"chamfer_mm": 1.0}, [{"a": 0}])
    b = ({"chamfer_mm": 3.0, "fscore_1mm": 0.5, "view_dependent": 0.0}, {"chamfer_mm": 3.0, "fscore_1mm": 0.5},
         [{"a": 1}, {"a": 1}])
    empty = ({}, {}, [])
    means, per_action, rows = _means_over_actions(["A0", "A1", "A2"], [a, b, empty])
    assert means == {"chamfer_mm": 2.0, "view_dependent": 0.5, "fscore_1mm": 0.5}
    assert per_action == {"A0": {"chamfer_mm": 1.0}, "A1": {"chamfer_mm": 3.0, "fscore_1mm": 0.5}}
    assert [r["a"] for r in rows] == [0, 1, 1]


def test_summary_rows_name_unit_and_aggregation():
    rows = summary_rows({"chamfer_mm": 3.0, "albedo_psnr_db": 20.0}, {"chamfer_mm": "mean_over_actions"}, 2, "r1")
    assert [r["metric"] for r in rows] == ["albedo_psnr_db", "chamfer_mm"]
    assert rows[0]["aggregation"] == "pooled" and rows[1]["aggregation"] == "mean_over_actions"
    assert (rows[0]["unit"], rows[1]["unit"]) == ("dB", "mm") and rows[1]["n_actions"] == 2


def test_relit_truth_lights_by_size():
    assert relit_truth_lights([{"width": 96, "height": 144}]) == 512
    assert relit_truth_lights([{"width": 160, "height": 255}, {"width": 100, "height": 256}]) == 2048
    assert relit_truth_lights([]) == 512


def test_simulator_digest_keeps_docstrings_and_comments_out(tmp_path: Path):
    """The truth renders' key holds the simulator's code, not its text: a docstring or comment edit keeps it, a
    code edit, a new file or a renamed one changes it."""
    (tmp_path / "a.py").write_text('"""Module."""\nX = 1\n')
    (tmp_path / "notes.txt").write_text("not python")
    key = simulator_digest(tmp_path)
    (tmp_path / "a.py").write_text('"""Module, documented again."""\n# a comment\nX = 1\n')
    (tmp_path / "notes.txt").write_text("other")
    assert simulator_digest(tmp_path) == key
    (tmp_path / "a.py").write_text('"""Module."""\nX = 2\n')
    changed = simulator_digest(tmp_path)
    (tmp_path / "b.py").write_text("Y = 0\n")
    added = simulator_digest(tmp_path)
    (tmp_path / "b.py").rename(tmp_path / "c.py")
    assert len({key, changed, added, simulator_digest(tmp_path)}) == 4


def test_relit_truth_cache_round_trip_and_keys(tmp_path: Path):
    """A render saved under its key loads back; the key changes with the camera, size and environment; a missing or
    damaged file loads as None (rendered again)."""
    truth = tmp_path / "capture" / "ground_truth"
    (truth / "A0000").mkdir(parents=True)
    (truth / "A0000" / "truth.json").write_text("{}")
    cache = RelitTruthCache(tmp_path / "cache", truth, "A0000", lights=512)
    K, pose, env = np.eye(3), np.eye(4)[:3], np.ones((4, 8, 3), np.float32)
    key = cache.key(K, pose, 6, 4, env)
    assert cache.load(key) is None
    assert len({key, cache.key(2 * K, pose, 6, 4, env), cache.key(K, pose, 6, 5, env),
                cache.key(K, pose, 6, 4, 2 * env)}) == 4
    render = {"radiance": np.random.default_rng(0).random((6, 4, 3)), "mask": np.ones((6, 4), bool),
              "normals_world": np.zeros((6, 4, 3), np.float32), "albedo": np.full((6, 4, 3), 0.5, np.float32),
              "backface": np.tile(np.float32([0.0, 0.25, 0.5, 1.0]), (6, 1))}
    cache.save(key, render)
    back = cache.load(key)
    assert set(back) == set(render)
    for name in render:
        np.testing.assert_array_equal(back[name], render[name].astype(back[name].dtype))
    # an entry written without the backface map (an older cache) is rendered again
    np.savez_compressed(tmp_path / "cache" / f"{key[:32]}.npz",
                        **{k: v for k, v in render.items() if k != "backface"})
    assert cache.load(key) is None
    cache.save(key, render)
    # another light count or another truth file is another cache
    assert RelitTruthCache(tmp_path / "cache", truth, "A0000", lights=2048).key(K, pose, 6, 4, env) != key
    (truth / "A0000" / "truth.json").write_text('{"changed": 1}')
    assert RelitTruthCache(tmp_path / "cache", truth, "A0000", lights=512).key(K, pose, 6, 4, env) != key
    (tmp_path / "cache" / f"{key[:32]}.npz").write_bytes(b"not a zip")
    assert cache.load(key) is None
