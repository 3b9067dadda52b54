"""Session stage ``cameras``: the rig's cameras in the stage frame, once per capture session.

Until geometric calibration lands this reads the rig spec's nominal cameras; downstream stages read
cameras only from this stage's ``cameras.json``, so calibration can replace it without touching them.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.config import Documented
from pipeline.stage import Stage, StageContext


@dataclass(frozen=True)
class CamerasConfig(Documented):
    source: str = "rig"
    """Where cameras come from: "rig" (the rig spec's nominal cameras)."""


class CamerasStage(Stage):
    name = "cameras"
    version = "1"
    scope = "session"
    outputs = ("cameras.json",)

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        return {"rig.json": capture.sessions[scope_id].rig_path}

    def run(self, ctx: StageContext) -> dict[str, Any]:
        cameras = []
        for cam in ctx.rig["cameras"]:
            cameras.append({k: cam[k] for k in ("camera_id", "width", "height", "K", "cam_from_world",
                                                "white_reference")} |
                           {"dist": cam.get("dist", [0.0] * 5), "exposure_s": cam.get("exposure_s")})
        (ctx.out_dir / "cameras.json").write_text(json.dumps(
            {"source": self.config.source, "camera_convention": "opencv", "cameras": cameras}, indent=1))
        return {"n_cameras": len(cameras)}


def load_cameras(path: Path) -> dict[str, dict[str, Any]]:
    """camera_id -> camera record from a ``cameras.json``."""
    return {c["camera_id"]: c for c in json.loads(Path(path).read_text())["cameras"]}
