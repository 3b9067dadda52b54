"""Session stages ``colour`` and ``lights``: photometric calibration once per capture session.

``colour`` fits, per camera, a 3x3 matrix from decoded linear RGB to linear sRGB against a colour chart
(:mod:`calibration.colour`); the decode stage applies it to every frame of that camera. ``lights`` fits
a model of the LED gradients' ratio as a function of the normal from a diffuse sphere of known geometry
(:mod:`calibration.light`); the photometric stage inverts it instead of normalising the raw ratio.
A session without chart or sphere frames gets the identity matrix / the ideal model, recorded as such.

A calibration frame that cannot be used (missing, truncated, corrupt, black, saturated, wrong size) costs
only that camera's contribution: ``colour`` leaves the camera at the identity matrix, ``lights`` fits the
model without it (and falls back to the ideal model when fewer than two cameras remain or the fit fails).
Each such camera is logged and listed with the file and the reason under ``calibration_left_out`` in the
stage's stats; the engine turns that into rows of ``metrics.parquet`` (``calibration_frame_left_out``)
for every action of the session. Never the whole session fails for one bad calibration frame.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from calibration.colour import apply_colour_matrix, chart_patch_means, delta_e_2000, fit_colour_matrix
from calibration.light import LightModel, correct_normals, fit_light_model, ideal_light_model, sphere_normals
from pipeline.codecs.raw import decode_raw
from pipeline.config import Documented
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from stages.cameras import load_cameras

ILLUMINATIONS = ("full_on", "pos", "neg")


@dataclass(frozen=True)
class ColourConfig(Documented):
    enabled: bool = True
    """Fit per-camera colour matrices when the session has chart frames (else identity)."""
    white_preserving: bool = False
    """Constrain the fit so the chart's grey ramp maps exactly onto the reference greys."""
    erode_px: int = 2
    """Pixels trimmed from each patch box (demosaicing blur at patch edges)."""

    def __post_init__(self) -> None:
        if self.erode_px < 0:
            raise ValueError(f"colour.erode_px must be >= 0, got {self.erode_px!r}")


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


def colour_matrix(colour_dir: Path, camera_id: str) -> np.ndarray | None:
    """The fitted matrix of one camera from a ``colour`` artifact, or None (identity)."""
    path = Path(colour_dir) / "colour" / f"{camera_id}.json"
    return np.asarray(json.loads(path.read_text())["matrix"], np.float32) if path.exists() else None


def load_light_model(lights_dir: Path) -> LightModel | None:
    """The fitted light model of a ``lights`` artifact, or None when the session uses the ideal one."""
    path = Path(lights_dir) / "light_model.json"
    record = json.loads(path.read_text())
    return None if record.get("ideal") else LightModel.from_json(record["model"])


def _mean_angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1.0, 1.0))).mean())


def _left_out(ctx: StageContext, view: str, reason: str) -> dict[str, Any]:
    """Stats of a camera left out of the colour calibration (identity matrix), logged with the reason."""
    ctx.log.warning("session %s: camera %s left out of the colour calibration (identity matrix): %s",
                    ctx.scope_id, view, reason)
    return {"calibrated": False, "left_out": reason}


def corrected_normals(pos: np.ndarray, neg: np.ndarray, model: LightModel, mask: np.ndarray,
                      iterations: int) -> np.ndarray:
    """Normals (H, W, 3) from the gradient ratio through the fitted light model, 0 outside ``mask``."""
    total = pos + neg
    d = np.where(total > 1e-6, (pos - neg) / np.maximum(total, 1e-6), 0.0).astype(np.float32)
    normals = np.zeros_like(d)
    if mask.any():
        normals[mask] = correct_normals(d[mask], model, iterations=iterations).astype(np.float32)
    return np.nan_to_num(normals, nan=0.0, posinf=0.0, neginf=0.0)


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
        out = ctx.out_dir / "colour" / f"{view}.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"matrix": np.asarray(matrix).tolist(), "chart_de2000_before": before,
                                   "chart_de2000_after": after}, indent=1))
        return {"calibrated": True, "chart_de2000_before": before, "chart_de2000_after": after}

    def finalize(self, ctx: StageContext, view_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
        (ctx.out_dir / "colour").mkdir(exist_ok=True)
        done = [s for s in view_stats.values() if s.get("calibrated")]
        left_out = {v: s["left_out"] for v, s in sorted(view_stats.items()) if s.get("left_out")}
        summary = {"views": view_stats, "cameras_calibrated": len(done), "calibration_left_out": left_out}
        if done:
            summary["chart_de2000_before"] = float(np.mean([s["chart_de2000_before"] for s in done]))
            summary["chart_de2000_after"] = float(np.mean([s["chart_de2000_after"] for s in done]))
        return summary


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
