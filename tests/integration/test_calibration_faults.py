"""Broken and missing calibration frames cost only their camera's contribution, never the session (issue 23).

One tiny simulated session (6 cameras, 160 px, chart + diffuse sphere + marker frames) gets, at once:
a truncated and a deleted frame of each calibration (chart -> ``colour``, sphere -> ``lights``, marker
frames -> ``cameras``), on different cameras so each effect can be told apart. The action must still be
published, each left-out camera logged and listed with its file and reason in the stage's stats, and
recorded in ``metrics.parquet`` (metric ``<stage>_calibration_frame_left_out``, source = the stage).
"""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import pytest

from pipeline.runner import ExecutionConfig
from stages.registry import PRESETS, build_stages
from ultrastage.run import run_pipeline
from synthetic import SimConfig, simulate
from synthetic.calibration import CalibrationConfig

SYNC = ExecutionConfig(scheduler="sync")
N_CAMERAS = 6


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


@pytest.fixture(scope="module")
def faulty_run(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("calfaults")
    capture = root / "capture"
    # 160 px is the smallest width at which the marker balls calibrate (the test of the markers source)
    simulate(capture, SimConfig(actions=1, width=160, n_cameras=N_CAMERAS, n_leds=64, background=False),
             calibration=CalibrationConfig(target=False))
    cal = capture / "sessions" / "S000" / "calibration"
    _truncate(cal / "chart" / "00001.dng")
    (cal / "chart" / "00002.dng").unlink()
    _truncate(cal / "sphere" / "pos" / "00003.dng")
    (cal / "sphere" / "neg" / "00000.dng").unlink()
    _truncate(cal / "markers" / "00005.dng")
    (cal / "markers" / "00004.dng").unlink()
    logs: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = logs.append  # type: ignore[method-assign]
    logging.getLogger("ultrastage").addHandler(handler)
    try:
        config = PRESETS["test"]
        result = run_pipeline(capture, root / "release", root / "work", build_stages(config, through="photometric"),
                              config, SYNC, echo=lambda line: None)
    finally:
        logging.getLogger("ultrastage").removeHandler(handler)
    return capture, root / "release", result, [r.getMessage() for r in logs]


def _stats(result, stage: str) -> dict:
    return next(t for t in result.plan.tasks if t.stage.name == stage).stats


def _left_out_metrics(release: Path, source: str) -> set[str]:
    from manifests import open_release

    metrics = open_release(release).metrics
    rows = metrics[(metrics.metric == f"{source}_calibration_frame_left_out") & (metrics.source == source)]
    assert set(rows.action_id) <= {"A0000"} and (rows.value == 1.0).all()
    return set(rows.camera_id)


def test_the_session_survives_and_its_action_is_published(faulty_run):
    _, release, result, _ = faulty_run
    assert result.action_status == {"A0000": "ok"}, result.action_errors
    assert all(t.status == "ran" for t in result.plan.tasks)
    # the two cameras without a marker pose are missing from the action; the other four are published
    published = sorted(p.stem for p in (release / "actions" / "A0000" / "normal_alpha").glob("*.exr"))
    assert published == [f"{i:05d}" for i in range(N_CAMERAS) if i not in (4, 5)]


def test_a_broken_chart_frame_costs_that_cameras_colour_matrix(faulty_run):
    capture, release, result, logs = faulty_run
    colour = _stats(result, "colour")
    assert colour["cameras_calibrated"] == N_CAMERAS - 2
    left_out = colour["calibration_left_out"]
    assert set(left_out) == {"00001", "00002"}
    assert str(capture / "sessions/S000/calibration/chart/00001.dng") in left_out["00001"]
    assert "truncated" in left_out["00001"]
    assert "no chart frame" in left_out["00002"]
    assert any("00001 left out of the colour calibration" in m and "truncated" in m for m in logs)
    assert _left_out_metrics(release, "colour") == {"00001", "00002"}


def test_a_broken_sphere_frame_costs_that_cameras_led_samples(faulty_run):
    capture, release, result, logs = faulty_run
    lights = _stats(result, "lights")
    left_out = lights["calibration_left_out"]
    assert set(left_out) == {"00000", "00003"}
    assert str(capture / "sessions/S000/calibration/sphere/pos/00003.dng") in left_out["00003"]
    assert "truncated" in left_out["00003"]
    assert "no sphere frame" in left_out["00000"] and "sphere/neg" in left_out["00000"]
    # fitted from the cameras that remain (8, less the 2 unregistered, less the 2 left out)
    assert lights["cameras_used"] == N_CAMERAS - 4 and lights["sphere_pixels"] > 500
    assert "fallback_reason" not in lights
    assert any("00003 left out of the LED calibration" in m for m in logs)
    assert _left_out_metrics(release, "lights") == {"00000", "00003"}


def test_a_broken_marker_frame_costs_that_cameras_pose(faulty_run):
    capture, release, result, logs = faulty_run
    cameras = _stats(result, "cameras")
    assert cameras["source"] == "markers" and cameras["n_cameras"] == N_CAMERAS - 2
    left_out = cameras["calibration_left_out"]
    assert set(left_out) == {"00004", "00005"}
    assert str(capture / "sessions/S000/calibration/markers/00005.dng") in left_out["00005"]
    assert "truncated" in left_out["00005"] and "no marker-frame frame" in left_out["00004"]
    assert set(cameras["missing_views"]) == {"00004", "00005"}
    assert any("00005 left out of the marker calibration" in m for m in logs)
    assert _left_out_metrics(release, "cameras") == {"00004", "00005"}
    # unregistered cameras' frames are failed frames of the action, with the reason
    from manifests import open_release

    frames = open_release(release).frames
    bad = frames[frames.status != "ok"]
    assert set(bad.camera_id) == {"00004", "00005"} and set(bad.status) == {"failed"}
    assert bad[bad.camera_id == "00005"].error.str.contains("truncated").all()
    transforms = json.loads((release / "actions" / "A0000" / "transforms.json").read_text())
    assert {f["camera_id"] for f in transforms["frames"]} == {f"{i:05d}" for i in range(N_CAMERAS)} - {"00004", "00005"}


def test_lights_falls_back_to_the_ideal_model_when_too_few_cameras_remain(faulty_run, tmp_path):
    capture, _, _, _ = faulty_run
    copy = tmp_path / "capture"
    shutil.copytree(capture, copy)
    sphere = copy / "sessions" / "S000" / "calibration" / "sphere"
    for path in sorted((sphere / "pos").glob("*.dng")):  # only camera 00001 keeps its g+ sphere frame
        if path.stem != "00001":
            path.unlink()
    config = PRESETS["test"]
    result = run_pipeline(copy, tmp_path / "release", tmp_path / "work", build_stages(config, through="lights"),
                          config, SYNC, echo=lambda line: None)
    lights = _stats(result, "lights")
    assert result.action_status == {"A0000": "ok"}
    assert lights["ideal"] and lights["fallback_reason"] == "fewer than 2 cameras with usable sphere frames"
    assert lights["cameras_used"] == 1 and set(lights["calibration_left_out"]) == {"00000", "00002", "00003"}
