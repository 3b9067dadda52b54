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
from scipy import ndimage

from calibration.colour import apply_colour_matrix
from calibration.light import correct_normals, fit_light_model, ideal_light_model, sphere_normals
from pipeline.codecs.raw import decode_raw
from pipeline.config import Documented
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from stages.artifacts import colour_matrix
from stages.cameras import load_cameras

ILLUMINATIONS = ("full_on", "pos", "neg")


@dataclass(frozen=True)
class LightsConfig(Documented):
    enabled: bool = True
    """Fit the LED ratio model when the session has sphere frames (else the ideal d = 2/3 n)."""
    degree: int = 2
    """Spherical-harmonic degree of the ratio model (1 = affine, 2, 3)."""
    iterations: int = 4
    """Gauss-Newton iterations when inverting the model per pixel."""
    erode_px: int = 2
    """Pixels trimmed from the sphere's silhouette (demosaicing blur, grazing angles)."""
    min_gain: float = 0.05
    """Use the fitted model only if it lowers the held-out sphere error by at least this fraction."""

    def __post_init__(self) -> None:
        if self.degree not in (1, 2, 3) or self.iterations < 0 or self.erode_px < 0 or not 0.0 <= self.min_gain < 1.0:
            raise ValueError(f"lights: need degree 1, 2 or 3, iterations >= 0, erode_px >= 0 and 0 <= min_gain < 1; "
                             f"got {self.degree!r}, {self.iterations!r}, {self.erode_px!r}, {self.min_gain!r}")


def _mean_angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1.0, 1.0))).mean())


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
        out = ctx.out_dir / "light_model.json"
        if not ctx.raw_inputs:
            out.write_text(json.dumps({"ideal": True, "model": ideal_light_model(self.config.degree).to_json()}))
            return {"ideal": True}
        sphere = ctx.rig["calibration_objects"]["sphere"]
        cameras = load_cameras(ctx.upstream["cameras"] / "cameras.json")
        folder = ctx.capture_root / "sessions" / ctx.scope_id / "calibration" / "sphere"
        ratios, truths, left_out = [], [], {}
        for cam_id, cam in sorted(cameras.items()):
            absent = [i for i in ("pos", "neg") if f"{i}/{cam_id}" not in ctx.raw_inputs]
            if absent:
                left_out[cam_id] = f"{folder / absent[0]}/{cam_id}.*: no sphere frame for camera {cam_id}"
                continue
            try:
                # one broken sphere frame costs that camera's samples, not the session's calibration
                pos, neg = (decode_raw(ctx.raw_inputs[f"{i}/{cam_id}"],
                                       expected_size=(int(cam["height"]), int(cam["width"]))).rgb
                            for i in ("pos", "neg"))
            except InputError as exc:
                left_out[cam_id] = str(exc)
                continue
            matrix = colour_matrix(ctx.upstream["colour"], cam_id)
            if matrix is not None:
                apply_colour_matrix(pos, matrix, out=pos)
                apply_colour_matrix(neg, matrix, out=neg)
            normals, mask = sphere_normals(np.asarray(cam["K"]), np.asarray(cam["cam_from_world"]), pos.shape[1],
                                           pos.shape[0], np.asarray(sphere["centre"]), float(sphere["radius_m"]))
            mask = ndimage.binary_erosion(mask, iterations=self.config.erode_px)
            total = pos + neg
            good = mask & np.all(total > 1e-3, axis=-1) & np.all(np.isfinite(total), axis=-1)
            ratios.append(((pos - neg) / np.maximum(total, 1e-6))[good])
            truths.append(normals[good])
        for cam_id, why in sorted(left_out.items()):
            ctx.log.warning("session %s: camera %s left out of the LED calibration: %s", ctx.scope_id, cam_id, why)
        stats: dict[str, Any] = {"sphere_pixels": int(sum(len(r) for r in ratios)), "cameras_used": len(ratios),
                                 "calibration_left_out": left_out}
        # Validate before trusting: fit on the even cameras, test on the odd ones (they see other sides
        # of the sphere). A model that does not beat the plain ratio there is not used.
        reason = "fewer than 2 cameras with usable sphere frames" if len(ratios) < 2 else None
        if reason is None:
            fit_d, fit_n = np.concatenate(ratios[0::2]), np.concatenate(truths[0::2])
            test_d, test_n = np.concatenate(ratios[1::2]), np.concatenate(truths[1::2])
            try:
                trial = fit_light_model(fit_d, fit_n, degree=self.config.degree)
            except ValueError as exc:  # too few sphere pixels left to fit
                reason = f"LED model not fitted: {exc}"
        if reason is not None:
            ctx.log.warning("session %s: %s; using the ideal LED model", ctx.scope_id, reason)
            stats |= {"ideal": True, "accepted": False, "fallback_reason": reason}
            out.write_text(json.dumps({"ideal": True, "model": ideal_light_model(self.config.degree).to_json(),
                                       "fit": stats}, indent=1))
            return stats
        naive_err = _mean_angle(test_d / np.maximum(np.linalg.norm(test_d, axis=-1, keepdims=True), 1e-9), test_n)
        fixed_err = _mean_angle(correct_normals(test_d, trial, iterations=self.config.iterations), test_n)
        accepted = fixed_err < (1.0 - self.config.min_gain) * naive_err
        stats |= {"ideal": not accepted, "heldout_err_deg_uncorrected": naive_err,
                  "heldout_err_deg_corrected": fixed_err, "accepted": bool(accepted)}
        if not accepted:
            ctx.log.warning("session %s: LED model rejected (held-out sphere %.3f -> %.3f deg)", ctx.scope_id,
                            naive_err, fixed_err)
            out.write_text(json.dumps({"ideal": True, "model": ideal_light_model(self.config.degree).to_json(),
                                       "fit": stats}, indent=1))
            return stats
        model = fit_light_model(np.concatenate(ratios), np.concatenate(truths), degree=self.config.degree)
        stats["rms_residual"] = float(model.rms_residual)
        out.write_text(json.dumps({"ideal": False, "model": model.to_json(), "fit": stats}, indent=1))
        return stats
