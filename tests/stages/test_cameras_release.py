"""What the cameras stage releases: the calibration summary, not the calibration's own COLMAP model (its images
are the calibration frames, which the release does not hold)."""
from __future__ import annotations

import json

from stages.cameras import CamerasConfig, CamerasStage


def test_the_calibration_model_stays_in_the_work_store(tmp_path):
    artifact = tmp_path / "artifact"
    (artifact / "colmap").mkdir(parents=True)
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        (artifact / "colmap" / name).write_text("# a COLMAP text model\n")
    (artifact / "cameras.json").write_text(json.dumps({"cameras": []}))
    (artifact / "calibration.json").write_text(json.dumps({"registered": []}))
    stage = CamerasStage(CamerasConfig())
    assert stage.release_files(artifact) == [(artifact / "calibration.json", "calibration.json", "calibration", None)]
    (artifact / "calibration.json").unlink()  # the rig spec's cameras: nothing calibrated, nothing released
    assert stage.release_files(artifact) == []
