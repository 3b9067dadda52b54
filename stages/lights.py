"""Session stage ``lights``: the LED gradients' ratio model from the session's diffuse-sphere frames.

It fits a model of the ratio as a function of the normal from a diffuse sphere of known geometry
(:mod:`calibration.light`); the photometric stage inverts it instead of normalising the raw ratio. A session
without sphere frames gets the ideal model (d = 2/3 n), recorded as such.

A sphere frame that cannot be used (missing, truncated, corrupt, black, saturated, wrong size) costs only that
camera's samples: the model is fitted without it (the ideal model when fewer than two cameras remain or the fit
fails), and the camera is logged and listed with the file and the reason under ``calibration_left_out`` in the
stage's stats (rows ``calibration_frame_left_out`` of ``metrics.parquet``). Never the whole session fails for
one bad calibration frame.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from calibration.colour import apply_colour_matrix
from calibration.light import ideal_light_model
from pipeline.codecs.raw import decode_raw
from pipeline.config import Documented, checked
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from artifacts.facade import ActionArtifacts, read_cameras
from artifacts.layout import ArtifactWriter
from stages.numerics.light_model import sphere_samples, validated_light_model

ILLUMINATIONS = ("full_on", "pos", "neg")


@dataclass(frozen=True)
class LightsConfig(Documented):
    enabled: bool = True
    """Fit the LED ratio model when the session has sphere frames (else the ideal d = 2/3 n)."""
    degree: int = checked(2, one_of=(1, 2, 3))
    """Spherical-harmonic degree of the ratio model (1 = affine, 2, 3)."""
    iterations: int = checked(4, ge=0)
    """Gauss-Newton iterations when inverting the model per pixel."""
    erode_px: int = checked(2, ge=0)
    """Pixels trimmed from the sphere's silhouette (demosaicing blur, grazing angles)."""
    min_gain: float = checked(0.05, ge=0.0, lt=1.0)
    """Use the fitted model only if it lowers the held-out sphere error by at least this fraction."""


class LightsStage(Stage):
    name = "lights"
    version = "1"
    scope = "session"
    requires = ("cameras", "colour")
    outputs = ("light_model.json",)

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        folder = capture.root / "sessions" / scope_id / "calibration" / "sphere"
        sphere = capture.sessions[scope_id].rig.get("calibration_objects", {}).get("sphere")
        if not self.config.enabled or sphere is None or not folder.is_dir():
            return {}
        found = {}
        for illum in ILLUMINATIONS:
            for cam in capture.sessions[scope_id].camera_ids:
                path = next(iter(sorted((folder / illum).glob(f"{cam}.*"))), None)
                if path is not None:
                    found[f"{illum}/{cam}"] = path
        return found

    def run(self, ctx: StageContext) -> dict[str, Any]:
        out = ArtifactWriter(self.name, ctx.out_dir).path("light_model")
        if not ctx.raw_inputs:
            out.write_text(json.dumps({"ideal": True, "model": ideal_light_model(self.config.degree).to_json()}))
            return {"ideal": True}
        ratios, truths, left_out = self._sphere_samples(ctx)
        for cam_id, why in sorted(left_out.items()):
            ctx.log.warning("session %s: camera %s left out of the LED calibration: %s", ctx.scope_id, cam_id, why)
        fit = validated_light_model(ratios, truths, self.config.degree, self.config.iterations, self.config.min_gain)
        stats: dict[str, Any] = {"sphere_pixels": int(sum(len(r) for r in ratios)), "cameras_used": len(ratios),
                                 "calibration_left_out": left_out} | fit.stats
        if fit.reason is not None:
            ctx.log.warning("session %s: %s; using the ideal LED model", ctx.scope_id, fit.reason)
        elif fit.model is None:
            ctx.log.warning("session %s: LED model rejected (held-out sphere %.3f -> %.3f deg)", ctx.scope_id,
                            stats["heldout_err_deg_uncorrected"], stats["heldout_err_deg_corrected"])
        model = fit.model if fit.model is not None else ideal_light_model(self.config.degree)
        out.write_text(json.dumps({"ideal": fit.model is None, "model": model.to_json(), "fit": stats}, indent=1))
        return stats

    def _sphere_samples(self, ctx: StageContext) -> tuple[list[np.ndarray], list[np.ndarray], dict[str, str]]:
        """Per camera with usable sphere frames (sorted by id), its ratios and true normals
        (:func:`stages.numerics.light_model.sphere_samples`); and camera -> why it was left out (a frame missing
        or unreadable: one broken frame costs that camera's samples, not the session's calibration)."""
        sphere = ctx.rig["calibration_objects"]["sphere"]
        upstream = ActionArtifacts(ctx.upstream)
        cameras = read_cameras(upstream.existing("session_cameras"))
        folder = ctx.capture_root / "sessions" / ctx.scope_id / "calibration" / "sphere"
        ratios, truths, left_out = [], [], {}
        for cam_id, cam in sorted(cameras.items()):
            absent = [i for i in ("pos", "neg") if f"{i}/{cam_id}" not in ctx.raw_inputs]
            if absent:
                left_out[cam_id] = f"{folder / absent[0]}/{cam_id}.*: no sphere frame for camera {cam_id}"
                continue
            try:
                pos, neg = (decode_raw(ctx.raw_inputs[f"{i}/{cam_id}"],
                                       expected_size=(cam.height, cam.width)).rgb
                            for i in ("pos", "neg"))
            except InputError as exc:
                left_out[cam_id] = str(exc)
                continue
            matrix = upstream.colour_matrix(cam_id)
            if matrix is not None:
                apply_colour_matrix(pos, matrix, out=pos)
                apply_colour_matrix(neg, matrix, out=neg)
            d, n = sphere_samples(pos, neg, cam.K, cam.cam_from_world, sphere["centre"], sphere["radius_m"],
                                  self.config.erode_px)
            ratios.append(d)
            truths.append(n)
        return ratios, truths, left_out
