"""The simulator's geometric calibration target (synthetic.calibration, a speckled cylinder) and
structure-from-motion calibration on it, as the ``cameras`` stage runs it (rig K priors, PINHOLE,
aligned to the nominal rig centres), against the true cameras."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.geometric import GeometricConfig, calibrate_images, camera_centre, pose_errors
from synthetic import SimConfig, simulate
from synthetic.calibration import CalibrationConfig, cylinder_hits

N_CAMERAS = 24


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("target") / "capture"
    # 128 LEDs: the action, which these tests do not read, renders in half the time; the LED count changes the
    # target frames only through the white reference they are scaled by
    simulate(out, SimConfig(actions=1, width=256, n_cameras=N_CAMERAS, background=False, n_leds=128),
             calibration=CalibrationConfig(chart=False, sphere=False, markers=False))
    return out


def stage_png(dng: Path, white: float, out: Path) -> Path:
    """As stages/cameras.py feeds SIFT: decoded, white at 0.8, sRGB 8-bit."""
    from pipeline.codecs.image import srgb_encode, write_png
    from pipeline.codecs.raw import decode_raw

    rgb = decode_raw(dng).rgb
    return write_png(out / f"{dng.stem}.png", (srgb_encode(rgb * (0.8 / white)) * 255.0 + 0.5).astype(np.uint8))


def test_cylinder_hits_side_and_caps():
    centre = np.array([0.0, 0.0, 0.0])
    dirs = np.array([[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
    hit, points, normals = cylinder_hits(np.array([0.0, 0.0, 3.0]), dirs, centre, 0.5, 1.0)
    assert hit.tolist() == [True, False, False]
    np.testing.assert_allclose(points[0], [0.0, 0.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(normals[0], [0.0, 0.0, 1.0], atol=1e-12)
    hit, points, normals = cylinder_hits(np.array([0.1, 3.0, 0.0]), dirs[1:2], centre, 0.5, 1.0)
    assert hit[0]
    np.testing.assert_allclose(points[0], [0.1, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(normals[0], [0.0, 1.0, 0.0])


def test_target_frames_decode_with_speckle_contrast(capture):
    from pipeline.codecs.raw import decode_raw

    rig = json.loads((capture / "sessions" / "S000" / "rig.json").read_text())
    assert rig["calibration_objects"]["target"]["frames"] == "calibration/cameras/<cam>.dng"
    frames = sorted((capture / "sessions" / "S000" / "calibration" / "cameras").glob("*.dng"))
    assert [f.stem for f in frames] == [c["camera_id"] for c in rig["cameras"]]
    for frame, cam in zip(frames[:3], rig["cameras"]):
        rgb = decode_raw(frame).rgb
        assert rgb.shape == (cam["height"], cam["width"], 3) and np.isfinite(rgb).all()
        grey = rgb.mean(-1) / np.mean(cam["white_reference"])       # albedo units on the target
        middle = grey[grey.shape[0] // 3:2 * grey.shape[0] // 3, grey.shape[1] // 3:2 * grey.shape[1] // 3]
        lo, hi = np.percentile(middle, [10, 90])
        assert lo < 0.2 and hi > 0.6, (lo, hi)                     # dark (0.1) and bright (0.8) speckles
        assert 0.2 < np.mean(middle > 0.45) < 0.8                   # both cover a good part of the view


def test_calibrate_images_on_target_registers_all(capture, tmp_path):
    rig = json.loads((capture / "sessions" / "S000" / "rig.json").read_text())["cameras"]
    true = json.loads((capture / "ground_truth" / "cameras" / "S000.json").read_text())["cameras"]
    folder = capture / "sessions" / "S000" / "calibration" / "cameras"
    images = [stage_png(folder / f"{c['camera_id']}.dng", max(c["white_reference"]), tmp_path) for c in rig]
    K = {f"{c['camera_id']}.png": np.asarray(c["K"], float) for c in rig}
    centres = {f"{c['camera_id']}.png": camera_centre(np.asarray(c["cam_from_world"], float)) for c in rig}
    truth = {f"{c['camera_id']}.png": np.asarray(c["cam_from_world"], float) for c in true}
    config = GeometricConfig(camera_model="PINHOLE", refine_focal_length=True, refine_principal_point=False,
                             refine_extra_params=False, num_threads=1)  # one thread: reproducible (see test_geometric)
    res = calibrate_images(images, tmp_path / "work", config, intrinsics_prior=K, known_centres=centres)
    assert len(res.cameras) == N_CAMERAS and res.aligned
    assert res.reprojection_error_px < 0.6
    est = {n: c.cam_from_world for n, c in res.cameras.items()}
    errors = pose_errors(est, truth, align=True)
    assert errors["rotation_deg_mean"] < ROTATION_BOUND_DEG, errors["rotation_deg_mean"]
    assert errors["centre_error_mm_mean"] < CENTRE_BOUND_MM, errors["centre_error_mm_mean"]


# Measured (24 cameras, 256 px, the cameras stage's settings: focal refined from the rig prior): 0.48 deg and
# 36 mm mean after the optimal similarity, reprojection 0.26 px -- WORSE than the nominal rig (~0.13 deg,
# ~4.5 mm): SfM on this target registers every camera but does not yet reach calibration accuracy (with
# the focal kept at the prior: 0.20 deg, 9 mm). These bounds only guard against regressions.
ROTATION_BOUND_DEG = 1.0
CENTRE_BOUND_MM = 70.0
