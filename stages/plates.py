"""Session stage ``plates``: the clean plates (the empty stage under full_on), decoded once per session.

The photometric stage's foreground masks difference against them. The decoding is the decode stage's
(:func:`pipeline.codecs.raw.decode_raw` with the ``decode`` config section and the ``colour`` matrices).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from calibration.colour import apply_colour_matrix
from pipeline.codecs.exr import write_exr
from pipeline.codecs.raw import decode_raw
from pipeline.stage import Stage, StageContext
from artifacts.facade import ActionArtifacts
from artifacts.layout import ArtifactWriter


class PlatesStage(Stage):
    """Clean plates (the empty stage under full_on), decoded once per session for foreground masks."""

    name = "plates"
    version = "2"
    scope = "session"
    requires = ("colour",)
    outputs = ("plates",)
    per_view = True
    config_section = "decode"

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        session = capture.sessions[scope_id]
        found = {cam: capture.background_path(scope_id, cam) for cam in session.camera_ids}
        return {f"background/{cam}": path for cam, path in found.items() if path is not None}

    def run_view(self, ctx: StageContext, view: str) -> dict[str, Any]:
        path = ctx.raw_inputs.get(f"background/{view}")
        if path is None:
            return {"plate": False}
        cam = next(c for c in ctx.rig["cameras"] if c["camera_id"] == view)
        frame = decode_raw(path, demosaic=self.config.demosaic, half_size=self.config.half_size,
                           expected_size=(int(cam["height"]), int(cam["width"])))
        matrix = ActionArtifacts(ctx.upstream).colour_matrix(view)
        if matrix is not None:
            apply_colour_matrix(frame.rgb, matrix, out=frame.rgb)
            np.maximum(frame.rgb, 0.0, out=frame.rgb)
        write_exr(ArtifactWriter(self.name, ctx.out_dir).path("plate", view), frame.rgb)
        return {"plate": True, "mean": float(frame.rgb.mean())}
