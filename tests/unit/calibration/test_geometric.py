"""Geometric calibration: alignment and pose-error maths, exports, and SfM on real photos (skips without
../shared/data)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.geometric import (
    CalibrationResult,
    CameraCalibration,
    GeometricConfig,
    calibrate_images,
    camera_centre,
    pose_errors,
    read_intrinsics_file,
    read_transforms_json,
    transform_cam_from_world,
    umeyama,
    umeyama_ransac,
    write_colmap_text,
    write_opencv_intrinsics_json,
    write_transforms_json,
)

SHARED = Path(__file__).resolve().parents[3].parent / "shared" / "data"
TEMPLE = SHARED / "multiview" / "templeSparseRing"


def rot(axis, deg):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


def look_at(centre, target=(0.0, 1.0, 0.0), up=(0.0, 1.0, 0.0)):
    """(3, 4) OpenCV cam_from_world of a camera at ``centre`` looking at ``target`` (y down in image)."""
    centre = np.asarray(centre, float)
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return np.hstack([R, (-R @ centre)[:, None]])


def ring(n=12, radius=3.0):
    out = {}
    for i in range(n):
        a = 2 * np.pi * i / n
        out[f"{i:05d}"] = look_at([radius * np.cos(a), 1.0 + 0.5 * (i % 3), radius * np.sin(a)])
    return out


def test_umeyama_recovers_known_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    s, R, t = 2.5, rot([1, 2, 3], 40), np.array([0.3, -1.0, 2.0])
    dst = s * src @ R.T + t
    s2, R2, t2 = umeyama(src, dst)
    assert s2 == pytest.approx(s, rel=1e-10)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-10)


def test_umeyama_ransac_ignores_outliers():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    s, R, t = 0.7, rot([0, 1, 0], -75), np.array([1.0, 2.0, 3.0])
    dst = s * src @ R.T + t
    dst[[3, 11]] += [0.5, -0.4, 0.3]
    s2, R2, t2, inl = umeyama_ransac(src, dst, max_error=0.01)
    assert not inl[3] and not inl[11] and inl.sum() == 18
    assert s2 == pytest.approx(s, rel=1e-9)
    np.testing.assert_allclose(R2, R, atol=1e-9)


def test_pose_errors_zero_after_similarity_and_one_degree_perturbation():
    truth = ring()
    s, R, t = 0.37, rot([0.2, 1, -0.4], 123), np.array([5.0, -2.0, 0.5])
    # estimated poses live in another frame: x_est = s R x_true + t
    est = {n: transform_cam_from_world(P, s, R, t) for n, P in truth.items()}
    res = pose_errors(est, truth)
    assert res["rotation_deg_max"] < 1e-8 and res["centre_error_mm_max"] < 1e-6
    assert res["similarity"]["scale"] == pytest.approx(1 / s)
    with pytest.raises(ValueError):
        pose_errors({}, truth)
    # rotate one camera by 1 degree about its own centre: 1 degree error there, centres untouched
    name = "00004"
    P = est[name]
    R1 = rot([1, 1, 0], 1.0) @ P[:, :3]
    est[name] = np.hstack([R1, (-R1 @ camera_centre(P))[:, None]])
    res = pose_errors(est, truth)
    assert res["rotation_deg"][name] == pytest.approx(1.0, abs=1e-9)
    assert max(v for n, v in res["rotation_deg"].items() if n != name) < 1e-8
    assert res["centre_error_mm_max"] < 1e-6


def test_pose_errors_without_alignment_reports_metric_offsets():
    truth = ring()
    est = {n: P.copy() for n, P in truth.items()}
    c = camera_centre(truth["00000"]) + [0.002, 0.0, 0.0]  # move one camera 2 mm
    R = truth["00000"][:, :3]
    est["00000"] = np.hstack([R, (-R @ c)[:, None]])
    res = pose_errors(est, truth, align=False)
    assert res["centre_error_mm"]["00000"] == pytest.approx(2.0, abs=1e-9)
    assert res["similarity"] is None and res["missing"] == []


def _result(n=4):
    cams = {}
    for i, (name, P) in enumerate(ring(n).items()):
        K = np.array([[800.0 + i, 0, 319.5], [0, 801.0, 239.5], [0, 0, 1]])
        cams[f"{name}.png"] = CameraCalibration(K=K, dist=np.array([0.01 * i, 0, 0, 0, 0]), cam_from_world=P,
                                                width=640, height=480)
    return CalibrationResult(cameras=cams, unregistered=["bad.png"], reprojection_error_px=0.4,
                             alignment_residual_mm=(0.5, 1.0), n_points3d=0, aligned=True)


def test_transforms_json_roundtrip(tmp_path):
    result = _result()
    path = write_transforms_json(result, tmp_path / "transforms.json", "images")
    data = json.loads(path.read_text())
    assert data["camera_convention"] == "opencv" and data["transform_matrix"] == "world_from_cam"
    assert data["unregistered"] == ["bad.png"] and data["frames"][0]["file_path"] == "images/00000.png"
    back = read_transforms_json(path)
    assert sorted(back) == sorted(result.cameras)
    for name, cam in result.cameras.items():
        np.testing.assert_allclose(back[name].cam_from_world, cam.cam_from_world, atol=1e-12)
        np.testing.assert_allclose(back[name].K, cam.K)
        np.testing.assert_allclose(back[name].dist, cam.dist)
        # transform_matrix maps the camera origin to its centre
        frame = next(f for f in data["frames"] if f["file_path"].endswith(name))
        np.testing.assert_allclose(np.asarray(frame["transform_matrix"])[:3, 3], camera_centre(cam.cam_from_world))


def test_colmap_text_and_intrinsics_files(tmp_path):
    result = _result()
    out = write_colmap_text(result, tmp_path / "colmap")
    cams = [ln for ln in (out / "cameras.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(cams) == 4 and cams[0].split()[1] == "OPENCV"
    assert float(cams[0].split()[6]) == pytest.approx(320.0)  # COLMAP principal point = OpenCV + 0.5
    names = [f"{n}" for n in result.cameras]
    path = write_opencv_intrinsics_json(result, tmp_path / "intr.json")
    K, dist = read_intrinsics_file(path, names)
    for n in names:
        np.testing.assert_allclose(K[n], result.cameras[n].K)
        np.testing.assert_allclose(dist[n], result.cameras[n].dist)
    shared = tmp_path / "shared.json"
    shared.write_text(json.dumps({"K": [[500, 0, 10], [0, 500, 20], [0, 0, 1]]}))
    K, dist = read_intrinsics_file(shared, names)
    assert sorted(K) == sorted(names) and dist == {}
    shared.write_text(json.dumps({"nope.png": {"K": [[500, 0, 10], [0, 500, 20], [0, 0, 1]]}}))
    with pytest.raises(ValueError, match="unknown images"):
        read_intrinsics_file(shared, names)


def test_config_rejects_bad_values():
    with pytest.raises(ValueError):
        GeometricConfig(camera_model="FISHEYE")
    with pytest.raises(ValueError):
        GeometricConfig(matcher="vocab")


def test_no_model_from_featureless_images_raises(tmp_path):
    from PIL import Image

    paths = []
    for i in range(3):
        p = tmp_path / f"black{i}.png"
        Image.fromarray(np.zeros((120, 160, 3), np.uint8)).save(p)
        paths.append(p)
    with pytest.raises(RuntimeError, match="could not build any model"):
        calibrate_images(paths, tmp_path / "work", GeometricConfig(num_threads=2))


def _temple_truth():
    K, P = {}, {}
    for line in (TEMPLE / "templeSR_par.txt").read_text().splitlines()[1:]:
        v = line.split()
        if len(v) != 22:
            continue
        a = np.array(v[1:], float)
        K[v[0]] = a[:9].reshape(3, 3)
        P[v[0]] = np.hstack([a[9:18].reshape(3, 3), a[18:21, None]])
    return K, P


# One thread: COLMAP's matching and mapping are seeded, but with 2 threads their order follows the thread
# scheduling, and one clean-clone CI run (under load) registered only 9 of the 16 views.
TEMPLE_CONFIG = GeometricConfig(max_image_size=-1, camera_model="PINHOLE", refine_focal_length=False, num_threads=1)


@pytest.mark.shared
@pytest.mark.skipif(not TEMPLE.is_dir(), reason="needs ../shared/data/multiview/templeSparseRing")
def test_unregistrable_images_are_reported_by_name(tmp_path):
    from PIL import Image

    K, _ = _temple_truth()
    paths = sorted(TEMPLE.glob("templeSR*.png"))
    Image.fromarray(np.zeros((480, 640, 3), np.uint8)).save(tmp_path / "black.png")
    noise = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    Image.fromarray(noise).save(tmp_path / "noise.png")
    paths += [tmp_path / "black.png", tmp_path / "noise.png"]
    prior = {**K, "black.png": K[paths[0].name], "noise.png": K[paths[0].name]}
    result = calibrate_images(paths, tmp_path / "work", TEMPLE_CONFIG, intrinsics_prior=prior)
    assert "black.png" in result.unregistered and "noise.png" in result.unregistered
    assert len(result.cameras) >= 14
    assert set(result.cameras) | set(result.unregistered) == {p.name for p in paths}


@pytest.mark.shared
@pytest.mark.skipif(not TEMPLE.is_dir(), reason="needs ../shared/data/multiview/templeSparseRing")
def test_temple_sparse_ring_accuracy(tmp_path):
    """All 16 views registered; camera centres within 1 mm on average of the ground truth (known K used as
    a fixed prior; the ground-truth centres serve as the known centres of the alignment)."""
    K, truth = _temple_truth()
    paths = sorted(TEMPLE.glob("templeSR*.png"))
    centres = {n: camera_centre(P) for n, P in truth.items()}
    result = calibrate_images(paths, tmp_path / "work", TEMPLE_CONFIG, intrinsics_prior=K, known_centres=centres)
    assert result.unregistered == [] and len(result.cameras) == 16
    assert result.aligned and result.alignment_residual_mm[0] < 1.0
    est = {n: c.cam_from_world for n, c in result.cameras.items()}
    aligned = pose_errors(est, truth, align=False)  # already in the truth frame
    assert aligned["centre_error_mm_mean"] < 1.0, aligned["centre_error_mm"]
    assert aligned["rotation_deg_mean"] < 0.2
    assert result.reprojection_error_px < 0.5
    refit = pose_errors(est, truth, align=True)
    assert refit["centre_error_mm_mean"] == pytest.approx(aligned["centre_error_mm_mean"], abs=0.05)
    out = write_colmap_text(result, tmp_path / "colmap")
    assert (out / "points3D.txt").stat().st_size > 1000


def test_calibrate_rig_on_simulated_stage_stays_finite_and_near_nominal(tmp_path):
    """calibrate_rig (nominal-pose refinement) on a small simulated stage: finite output, cameras within
    the rig tolerances of the nominal ones. NOTE: it does not yet beat the nominal rig on this data (see
    calibrate_rig's docstring), so closeness to the truth is not asserted."""
    from calibration.geometric import RigRefineConfig, calibrate_rig
    from synthetic import SimConfig, simulate

    cap = tmp_path / "cap"
    simulate(cap, SimConfig(actions=1, width=256, n_cameras=12, background=False))
    rig = json.loads((cap / "sessions" / "S000" / "rig.json").read_text())
    K = {f"{c['camera_id']}.dng": np.asarray(c["K"], float) for c in rig["cameras"]}
    P = {f"{c['camera_id']}.dng": np.asarray(c["cam_from_world"], float) for c in rig["cameras"]}
    paths = sorted((cap / "actions" / "A0000" / "full_on").glob("*.dng"))
    res = calibrate_rig(paths, tmp_path / "work", K, P, GeometricConfig(camera_model="PINHOLE", num_threads=2),
                        RigRefineConfig(rematch_rounds=0, ba_rounds=2, min_observations=15))
    assert sorted(res.cameras) + res.unregistered == sorted(res.cameras) + [n for n in sorted(K) if n not in res.cameras]
    assert np.isfinite(res.reprojection_error_px)
    assert res.n_points3d > 50
    for name, cam in res.cameras.items():
        assert np.all(np.isfinite(cam.K)) and np.all(np.isfinite(cam.cam_from_world))
        assert np.linalg.norm(cam.centre_world - camera_centre(P[name])) < 0.02
        assert abs(cam.K[0, 0] / K[name][0, 0] - 1) < 0.03
