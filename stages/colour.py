"""Session stage ``colour``: per-camera colour matrices from the session's chart frames.

It fits, per camera, a 3x3 matrix from decoded linear RGB to linear sRGB against a colour chart
(:mod:`calibration.colour`); the decode and plates stages apply it to every frame of that camera. A session
without chart frames gets the identity matrix, recorded as such.

A chart frame that cannot be used (missing, truncated, corrupt, black, saturated, wrong size) costs only that
camera's matrix: the camera keeps the identity, is logged and listed with the file and the reason under
``calibration_left_out`` in the stage's stats; the engine turns that into rows of ``metrics.parquet``
(``calibration_frame_left_out``) for every action of the session.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from calibration.colour import apply_colour_matrix, chart_patch_means, delta_e_2000, fit_colour_matrix
from pipeline.codecs.raw import decode_raw
from pipeline.config import Documented, checked
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from artifacts.layout import ArtifactWriter


@dataclass(frozen=True)
class ColourConfig(Documented):
    enabled: bool = True
    """Fit per-camera colour matrices when the session has chart frames (else identity)."""
    white_preserving: bool = False
    """Constrain the fit so the chart's grey ramp maps exactly onto the reference greys."""
    erode_px: int = checked(2, ge=0)
    """Pixels trimmed from each patch box (demosaicing blur at patch edges)."""


def _left_out(ctx: StageContext, view: str, reason: str) -> dict[str, Any]:
    """Stats of a camera left out of the colour calibration (identity matrix), logged with the reason."""
    ctx.log.warning("session %s: camera %s left out of the colour calibration (identity matrix): %s",
                    ctx.scope_id, view, reason)
    return {"calibrated": False, "left_out": reason}


class ColourStage(Stage):
    name = "colour"
    version = "1"
    scope = "session"
    outputs = ("colour",)
    per_view = True

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        folder = capture.root / "sessions" / scope_id / "calibration"
        if not self.config.enabled or not (folder / "chart.json").exists():
            return {}
        found = {"chart.json": folder / "chart.json"}
        for cam in capture.sessions[scope_id].camera_ids:
            path = next(iter(sorted((folder / "chart").glob(f"{cam}.*"))), None)
            if path is not None:
                found[f"chart/{cam}"] = path
        return found

    def run_view(self, ctx: StageContext, view: str) -> dict[str, Any]:
        if "chart.json" not in ctx.raw_inputs:  # no chart in this session: every camera keeps the identity
            return {"calibrated": False}
        folder = ctx.raw_inputs["chart.json"].parent / "chart"
        frame_path = ctx.raw_inputs.get(f"chart/{view}")
        if frame_path is None:
            return _left_out(ctx, view, f"{folder}/{view}.*: no chart frame for camera {view}")
        chart = json.loads(ctx.raw_inputs["chart.json"].read_text())
        cam = next(c for c in ctx.rig["cameras"] if c["camera_id"] == view)
        if view not in chart.get("cameras", {}):
            return _left_out(ctx, view, f"{ctx.raw_inputs['chart.json']}: no patch boxes for camera {view}")
        try:
            rgb = decode_raw(frame_path, expected_size=(int(cam["height"]), int(cam["width"]))).rgb
        except InputError as exc:  # one broken chart frame costs that camera's matrix, not the session
            return _left_out(ctx, view, str(exc))
        labels = np.zeros(rgb.shape[:2], np.int32)
        for k, (x0, y0, x1, y1) in enumerate(chart["cameras"][view]["patch_boxes"]):
            labels[y0:y1, x0:x1] = k + 1
        means, _ = chart_patch_means(rgb, labels, erode=self.config.erode_px)
        white = np.asarray(cam["white_reference"], np.float64)
        target = white * np.asarray(chart["reference_linear_srgb"], np.float64)
        matrix = fit_colour_matrix(means, target, white_preserving=self.config.white_preserving)
        before = float(np.mean(delta_e_2000(means / white, target / white)))
        after = float(np.mean(delta_e_2000(apply_colour_matrix(means, matrix) / white, target / white)))
        out = ArtifactWriter(self.name, ctx.out_dir).path("colour_matrix", view)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"matrix": np.asarray(matrix).tolist(), "chart_de2000_before": before,
                                   "chart_de2000_after": after}, indent=1))
        return {"calibrated": True, "chart_de2000_before": before, "chart_de2000_after": after}

    def finalize(self, ctx: StageContext, view_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
        ArtifactWriter(self.name, ctx.out_dir).folder("colour_matrix").mkdir(exist_ok=True)
        done = [s for s in view_stats.values() if s.get("calibrated")]
        left_out = {v: s["left_out"] for v, s in sorted(view_stats.items()) if s.get("left_out")}
        summary = {"views": view_stats, "cameras_calibrated": len(done), "calibration_left_out": left_out}
        if done:
            summary["chart_de2000_before"] = float(np.mean([s["chart_de2000_before"] for s in done]))
            summary["chart_de2000_after"] = float(np.mean([s["chart_de2000_after"] for s in done]))
        return summary
