"""Session calibration stages on a small simulated capture with chart and sphere frames."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.runner import ExecutionConfig
from stages.cameras import CamerasConfig
from stages.registry import PRESETS, build_stages
from ultrastage.run import run_pipeline
from synthetic import SimConfig, simulate
from synthetic.calibration import CalibrationConfig

SYNC = ExecutionConfig(scheduler="sync")


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("cal") / "capture"
    simulate(root, SimConfig(actions=1, width=96, n_cameras=6, n_leds=128), calibration=CalibrationConfig())
    return root


def _run(capture: Path, out: Path, config=PRESETS["default"], through: str = "photometric"):
    # the calibration stages and what consumes them; the neural stages are tested elsewhere
    return run_pipeline(capture, out / "release", out / "work", build_stages(config, through=through), config, SYNC,
                        echo=lambda line: None)


def _stats(result, stage: str) -> dict:
    return next(t for t in result.plan.tasks if t.stage.name == stage).stats


def test_colour_and_light_calibration_run_once_per_session(capture, tmp_path):
    result = _run(capture, tmp_path)
    assert result.action_status == {"A0000": "ok"}
    colour = _stats(result, "colour")
    assert colour["cameras_calibrated"] == 6
    assert colour["chart_de2000_after"] < 0.6 * colour["chart_de2000_before"]
    lights = _stats(result, "lights")
    assert lights["sphere_pixels"] > 500
    # the model is used exactly when it beats the plain ratio on the held-out cameras
    assert lights["accepted"] == (lights["heldout_err_deg_corrected"] < 0.95 * lights["heldout_err_deg_uncorrected"])
    assert lights["ideal"] == (not lights["accepted"])
    # the decoded frames carry the fitted matrix: a second run with colour disabled decodes differently
    off = dataclasses.replace(PRESETS["default"], colour=dataclasses.replace(PRESETS["default"].colour, enabled=False))
    again = _run(capture, tmp_path, off)
    status = {(t.stage.name, t.scope_id): t.status for t in again.plan.tasks}
    assert status[("colour", "S000")] == "ran" and status[("decode", "A0000")] == "ran"
    assert status[("cameras", "S000")] == "cached"
    # the default cameras source is "auto": this capture has marker frames, but 96 px images of 12 mm balls
    # (~0.5 px) cannot be calibrated, so the session keeps the rig spec and says why
    cameras = _stats(result, "cameras")
    assert cameras["source"] == "rig" and "registered only" in cameras["fallback_from_markers"]
    assert json.loads((tmp_path / "release" / "actions" / "A0000" / "calibration.json").read_text())["source"] == "rig"


def test_thin_geometric_calibration_fails_the_session_clearly(capture, tmp_path):
    config = dataclasses.replace(PRESETS["default"], cameras=CamerasConfig(source="colmap"))
    result = _run(capture, tmp_path, config)
    cameras = next(t for t in result.plan.tasks if t.stage.name == "cameras")
    if cameras.status == "ran":  # 6 views of a 96 px human can register; then the cameras are metric
        transforms = json.loads((tmp_path / "release" / "actions" / "A0000" / "transforms.json").read_text())
        assert len(transforms["frames"]) >= 3
        assert np.isfinite(np.asarray(transforms["frames"][0]["transform_matrix"])).all()
    else:
        assert result.action_status == {"A0000": "failed"}
        error = result.action_errors["A0000"]
        assert "rig.json" in error and "calibration of session S000" in error
        assert not (tmp_path / "release" / "actions" / "A0000").exists()


def test_marker_calibration_is_the_default_and_beats_the_rig_spec(tmp_path):
    from evaluation.release import camera_errors, true_cameras

    root = tmp_path / "capture"
    simulate(root, SimConfig(actions=1, width=160, n_cameras=8, n_leds=128, background=False),
             calibration=CalibrationConfig(chart=False, sphere=False, target=False))
    result = _run(root, tmp_path, through="decode")
    assert result.action_status == {"A0000": "ok"}
    stats = _stats(result, "cameras")
    assert stats["source"] == "markers" and stats["missing_views"] == {} and stats["reprojection_error_px"] < 0.2
    action = tmp_path / "release" / "actions" / "A0000"
    # the calibration's own model (the balls, with their tracks) stays in the work store: its images are the
    # marker frames, which the release does not hold
    import pycolmap

    (model,) = (tmp_path / "work" / "artifacts" / "cameras" / "S000").glob("*/colmap")
    balls = pycolmap.Reconstruction(str(model))
    assert balls.num_images() == 8 and balls.num_points3D() > 20 and balls.compute_mean_track_length() > 2
    assert (action / "calibration.json").is_file()
    assert not list((tmp_path / "release").rglob("images.txt"))  # through decode: no COLMAP model is released
    truth = true_cameras(root / "ground_truth", "S000")
    calibrated = camera_errors(json.loads((action / "transforms.json").read_text()), truth)
    rig = json.loads((root / "sessions" / "S000" / "rig.json").read_text())
    spec = camera_errors({"frames": [{"camera_id": c["camera_id"], "w": c["width"], "fl_x": c["K"][0][0],
                                      "cam_from_world_opencv": c["cam_from_world"]}
                                     for c in rig["cameras"]]}, truth)
    assert calibrated["cameras_registered"] == 8
    for key in ("cam_rotation_err_deg", "cam_center_err_mm", "cam_focal_err_pct"):
        assert calibrated[key] < 0.5 * spec[key], (key, calibrated[key], spec[key])
    assert calibrated["cam_rotation_err_deg"] < 0.05 and calibrated["cam_center_err_mm"] < 2.0
