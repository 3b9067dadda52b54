"""Session stage ``cameras``: the cameras of a capture session in the stage frame, once per session.

Two sources: the rig spec's nominal cameras ("rig"), or a geometric calibration ("colmap") of the
session's white-light frames with pycolmap (:mod:`calibration.geometric`): the rig spec's K as priors
and its nominal camera centres for a similarity alignment into the stage frame (metric scale). The
calibration reads the session's calibration frames (``sessions/<sid>/calibration/cameras/<cam>.*``)
when it has them, else the full_on frames of the session's first action, so adding actions to a session
never changes its key: the calibration is computed once per session.

Downstream stages read cameras only from this stage's ``cameras.json``. A camera the calibration could
not register is absent there and listed under ``unregistered`` with the reason; actions treat it as
missing.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from calibration.geometric import GeometricConfig
from pipeline.config import Documented
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext


@dataclass(frozen=True)
class CamerasConfig(Documented):
    source: Literal["rig", "colmap"] = "rig"
    """"rig": the rig spec's nominal cameras. "colmap": calibrate with pycolmap from white-light frames."""
    geometric: GeometricConfig = field(default_factory=lambda: GeometricConfig(
        camera_model="PINHOLE", refine_focal_length=True, refine_principal_point=False, refine_extra_params=False))
    """Structure-from-motion settings for source "colmap" (feature resolution, camera model, priors)."""
    demosaic: str = "AHD"
    """Demosaic of the frames decoded for calibration."""
    min_registered_fraction: float = 0.5
    """Fail the session's calibration (naming the cameras) when fewer of its cameras register: a
    similarity fitted to a handful of centres is not a calibration of the rig."""


def _centre(cam_from_world: Any) -> np.ndarray:
    P = np.asarray(cam_from_world, dtype=float)
    return -P[:, :3].T @ P[:, 3]


class CamerasStage(Stage):
    name = "cameras"
    version = "2"
    scope = "session"
    outputs = ("cameras.json", "colmap", "calibration.json")

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        inputs = {"rig.json": capture.sessions[scope_id].rig_path}
        if self.config.source == "rig":
            return inputs
        session = capture.sessions[scope_id]
        calib_dir = capture.root / "sessions" / scope_id / "calibration" / "cameras"
        frames = {}
        if calib_dir.is_dir():
            frames = {cam: p for cam in session.camera_ids
                      if (p := next(iter(sorted(calib_dir.glob(f"{cam}.*"))), None)) is not None}
        if not frames:
            first = sorted(a.action_id for a in capture.actions if a.session_id == scope_id)[0]
            frames = {cam: p for cam in session.camera_ids
                      if (p := capture.raw_path(first, "full_on", cam)) is not None}
        if len(frames) < 3:
            raise InputError(calib_dir, f"too few white-light frames to calibrate session {scope_id} ({len(frames)})")
        return inputs | {f"calibration/{cam}": p for cam, p in frames.items()}

    def run(self, ctx: StageContext) -> dict[str, Any]:
        rig_cams = {c["camera_id"]: c for c in ctx.rig["cameras"]}
        if self.config.source == "rig":
            cameras = [_record(c, c["K"], c.get("dist", [0.0] * 5), c["cam_from_world"]) for c in rig_cams.values()]
            stats: dict[str, Any] = {"n_cameras": len(cameras), "missing_views": {}}
        else:
            cameras, stats = self._calibrate(ctx, rig_cams)
        (ctx.out_dir / "cameras.json").write_text(json.dumps(
            {"source": self.config.source, "camera_convention": "opencv", "cameras": cameras,
             "unregistered": stats["missing_views"]}, indent=1))
        return stats

    def _calibrate(self, ctx: StageContext, rig_cams: dict[str, dict]) -> tuple[list[dict], dict[str, Any]]:
        from calibration.geometric import calibrate_images, write_colmap_text
        from pipeline.codecs.image import srgb_encode, write_png
        from pipeline.codecs.raw import decode_raw

        image_dir = ctx.out_dir / "images"
        paths = []
        for name, raw in sorted(ctx.raw_inputs.items()):
            if not name.startswith("calibration/"):
                continue
            cam = name.split("/", 1)[1]
            frame = decode_raw(raw, demosaic=self.config.demosaic)
            white = np.asarray(rig_cams[cam]["white_reference"], np.float32)
            # Expose so a white surface sits at 0.8: SIFT wants contrast, not absolute radiance.
            pic = (srgb_encode(frame.rgb * (0.8 / float(white.max()))) * 255.0 + 0.5).astype(np.uint8)
            paths.append(write_png(image_dir / f"{cam}.png", pic))
        names = [p.name for p in paths]
        priors = {f"{c}.png": np.asarray(rig_cams[c]["K"], float) for c in rig_cams if f"{c}.png" in names}
        centres = {f"{c}.png": _centre(rig_cams[c]["cam_from_world"]) for c in rig_cams if f"{c}.png" in names}
        where = ctx.raw_inputs["rig.json"]  # errors name the session's rig spec, not a scratch folder
        try:
            result = calibrate_images(paths, ctx.out_dir / "work", self.config.geometric, intrinsics_prior=priors,
                                      known_centres=centres)
        except RuntimeError as exc:
            raise InputError(where, f"geometric calibration of session {ctx.scope_id} failed: {exc}") from exc
        if len(result.cameras) < max(3, self.config.min_registered_fraction * len(rig_cams)):
            raise InputError(where, f"calibration of session {ctx.scope_id} registered only {len(result.cameras)} of {len(rig_cams)} "
                                          f"cameras (unregistered: {', '.join(sorted(Path(n).stem for n in result.unregistered))})")
        if not result.aligned:
            raise InputError(where, "calibration could not be aligned to the rig's nominal camera centres: "
                                          + "; ".join(result.notes[-3:]))
        write_colmap_text(result, ctx.out_dir / "colmap")
        shutil.rmtree(ctx.out_dir / "work", ignore_errors=True)
        cameras = []
        for name, cal in sorted(result.cameras.items()):
            cam_id = Path(name).stem
            cameras.append(_record(rig_cams[cam_id], cal.K.tolist(), cal.dist.tolist(), cal.cam_from_world.tolist()))
        missing = {Path(n).stem: "not registered by the calibration" for n in result.unregistered}
        missing |= {c: "no white-light frame to calibrate from" for c in rig_cams if f"{c}.png" not in names}
        summary = result.summary() | {"unregistered": missing}
        (ctx.out_dir / "calibration.json").write_text(json.dumps(summary, indent=1, default=float))
        for cam, why in sorted(missing.items()):
            ctx.log.warning("session %s: camera %s %s", ctx.scope_id, cam, why)
        return cameras, {"n_cameras": len(cameras), "missing_views": missing,
                         "reprojection_error_px": float(result.reprojection_error_px),
                         "alignment_residual_mm": list(result.alignment_residual_mm or [])}


    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        files = [(p, f"colmap/{p.name}", "colmap", None) for p in sorted((artifact / "colmap").glob("*.txt"))]
        if (artifact / "calibration.json").exists():
            files.append((artifact / "calibration.json", "calibration.json", "calibration", None))
        return files


def _record(rig_cam: dict[str, Any], K: Any, dist: Any, cam_from_world: Any) -> dict[str, Any]:
    return {"camera_id": rig_cam["camera_id"], "width": rig_cam["width"], "height": rig_cam["height"], "K": K,
            "dist": list(dist), "cam_from_world": cam_from_world, "white_reference": rig_cam["white_reference"],
            "exposure_s": rig_cam.get("exposure_s")}


def load_cameras(path: Path) -> dict[str, dict[str, Any]]:
    """camera_id -> camera record from a ``cameras.json`` (calibrated cameras only)."""
    return {c["camera_id"]: c for c in json.loads(Path(path).read_text())["cameras"]}


def unregistered_cameras(path: Path) -> dict[str, str]:
    """camera_id -> reason for the cameras of the session that have no calibration."""
    return dict(json.loads(Path(path).read_text()).get("unregistered", {}))
