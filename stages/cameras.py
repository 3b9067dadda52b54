"""Session stage ``cameras``: the cameras of a capture session in the stage frame, once per session.

Sources:

- "markers": calibrate every camera from the session's marker-frame frames
  (``sessions/<sid>/calibration/markers/<cam>.*``): white balls at surveyed positions (rig.json
  ``calibration_objects.markers``) filling the capture volume (:mod:`calibration.markers`: blob
  centroids, identification from the nominal cameras, pycolmap absolute pose with the focal length free).
  The surveyed positions are the stage frame, so no alignment to nominal centres is needed.
- "colmap": structure from motion with pycolmap of the session's white-light frames
  (``calibration/cameras/<cam>.*`` when present, else the full_on frames of the session's first action;
  :mod:`calibration.geometric`): the rig spec's K as priors and its nominal camera centres for a
  similarity alignment into the stage frame (metric scale).
- "rig": the rig spec's nominal cameras.
- "auto" (default): "markers" when the session has marker frames and rig.json has the balls' positions,
  else "rig". Should the marker calibration fail for the session as a whole (fewer than
  ``min_registered_fraction`` of the cameras), "auto" keeps the rig spec and says so (log, stats,
  calibration.json); "markers" fails the session.

Outputs: ``cameras.json``, ``calibration.json`` (a summary: registered and unregistered cameras, errors,
alignment) and, when pycolmap calibrated, ``colmap/``: the calibration's own COLMAP text model (its points the
marker balls or matched features, with their tracks; its images named by camera id for the marker frames, by
the PNGs of the artifact's ``images/`` for structure from motion). The release holds ``calibration.json``; the
model stays in the work store, as no file it names is released (:meth:`CamerasStage.release_files`).

The calibration reads only session-level frames (or the session's first action), so adding actions to a
session never changes its key: the calibration is computed once per session.

Downstream stages read cameras only from this stage's ``cameras.json``. A camera the calibration could
not register is absent there and listed under ``unregistered`` with the reason; actions treat it as
missing. A calibration frame that cannot be decoded (truncated, corrupt, black, wrong size) or is absent
costs only that camera: it is left out of the calibration, logged, listed with the file and reason under
``calibration_left_out`` in the stage's stats (``metrics.parquet`` rows ``calibration_frame_left_out``) and,
being unregistered, its frames of every action of the session are marked failed in ``frames.parquet``.
"""
from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from calibration.geometric import GeometricConfig
from calibration.markers import MarkerCalibrationConfig
from pipeline.config import Documented, checked
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from artifacts.layout import ArtifactWriter, released_files
from artifacts.camera import camera_centre


@dataclass(frozen=True)
class CamerasConfig(Documented):
    source: Literal["auto", "markers", "rig", "colmap"] = "auto"
    """"auto": "markers" when the session has marker frames, else "rig". "markers": calibrate from the
    surveyed marker frame. "rig": the rig spec's nominal cameras. "colmap": structure from motion with
    pycolmap from white-light frames. On the simulated stage (32 cameras, 320 px) the rig spec is off by
    0.13 deg / 4.7 mm / 0.38% focal; "markers" by 0.002 deg / 0.16 mm / 0.005% in ~3 s
    (bench/bench_calibration.py --markers)."""
    markers: MarkerCalibrationConfig = field(default_factory=MarkerCalibrationConfig)
    """Marker-frame calibration settings (sources "markers" and "auto")."""
    geometric: GeometricConfig = field(default_factory=lambda: GeometricConfig(
        camera_model="PINHOLE", refine_focal_length=True, refine_principal_point=False, refine_extra_params=False))
    """Structure-from-motion settings for source "colmap" (feature resolution, camera model, priors)."""
    demosaic: Literal["LINEAR", "VNG", "PPG", "AHD", "DCB", "DHT", "AAHD"] = "AHD"
    """LibRaw demosaic algorithm of the frames decoded for calibration (the names of ``decode.demosaic``)."""
    min_registered_fraction: float = checked(0.5, ge=0.0, le=1.0)
    """Fail the session's calibration (naming the cameras) when fewer of its cameras register: a
    similarity fitted to a handful of centres is not a calibration of the rig. A share of the rig's cameras,
    in [0, 1]; at least 3 cameras must register whatever it is."""


class _MarkerCalibrationFailed(InputError):
    """The marker calibration failed for the session as a whole; ``left_out`` names the cameras whose marker
    frames could not be decoded (camera id -> "<path>: <reason>"), which "auto" records with its fallback."""

    def __init__(self, path: Path, reason: str, left_out: dict[str, str]):
        super().__init__(path, reason)
        self.left_out = dict(left_out)


class CamerasStage(Stage):
    name = "cameras"
    version = "3"
    scope = "session"
    outputs = ("cameras.json", "colmap", "calibration.json")

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        inputs = {"rig.json": capture.sessions[scope_id].rig_path}
        source = self.config.source
        if source == "rig":
            return inputs
        session = capture.sessions[scope_id]
        calibration = capture.root / "sessions" / scope_id / "calibration"
        if source in ("auto", "markers"):
            markers = _frames(calibration / "markers", session.camera_ids)
            if markers:
                return inputs | {f"markers/{cam}": p for cam, p in markers.items()}
            if source == "markers":
                raise InputError(calibration / "markers", f"no marker-frame frames to calibrate session {scope_id}")
            return inputs
        frames = _frames(calibration / "cameras", session.camera_ids)
        if not frames:
            first = sorted(a.action_id for a in capture.actions if a.session_id == scope_id)[0]
            frames = {cam: p for cam in session.camera_ids
                      if (p := capture.raw_path(first, "full_on", cam)) is not None}
        if len(frames) < 3:
            raise InputError(calibration / "cameras", f"too few white-light frames to calibrate session {scope_id} ({len(frames)})")
        return inputs | {f"calibration/{cam}": p for cam, p in frames.items()}

    def run(self, ctx: StageContext) -> dict[str, Any]:
        rig_cams = {c["camera_id"]: c for c in ctx.rig["cameras"]}
        source = self.config.source
        if source in ("auto", "markers"):
            source = "markers" if any(n.startswith("markers/") for n in ctx.raw_inputs) else "rig"
        stats: dict[str, Any]
        if source == "markers":
            try:
                cameras, stats = self._calibrate_markers(ctx, rig_cams)
            except InputError as exc:
                if self.config.source != "auto":
                    raise
                ctx.log.warning("session %s: %s; keeping the rig spec's cameras", ctx.scope_id, exc.reason)
                left_out = getattr(exc, "left_out", {})
                ArtifactWriter(self.name, ctx.out_dir).path("calibration_summary").write_text(json.dumps(
                    {"source": "rig", "fallback_from": "markers", "reason": exc.reason}
                    | ({"left_out": left_out} if left_out else {}), indent=1))
                source = "rig"
                cameras, stats = _rig_cameras(rig_cams)
                stats["fallback_from_markers"] = exc.reason
                stats["calibration_left_out"] = left_out
        elif source == "rig":
            cameras, stats = _rig_cameras(rig_cams)
        else:
            cameras, stats = self._calibrate(ctx, rig_cams)
        stats["source"] = source
        ArtifactWriter(self.name, ctx.out_dir).path("session_cameras").write_text(json.dumps(
            {"source": source, "camera_convention": "opencv", "cameras": cameras,
             "unregistered": stats["missing_views"]}, indent=1))
        return stats

    def _calibrate_markers(self, ctx: StageContext, rig_cams: dict[str, dict]) -> tuple[list[dict], dict[str, Any]]:
        from calibration.geometric import write_colmap_text
        from calibration.markers import calibrate_markers
        from pipeline.codecs.raw import decode_raw

        where = ctx.raw_inputs["rig.json"]
        spec = ctx.rig.get("calibration_objects", {}).get("markers")
        if not spec or "positions" not in spec or "radius_m" not in spec:
            raise InputError(where, "marker frames but no calibration_objects.markers (positions, radius_m) in the rig spec")
        t0 = time.perf_counter()
        images, broken = {}, {}
        for name, raw in sorted(ctx.raw_inputs.items()):
            if name.startswith("markers/") and name.split("/", 1)[1] in rig_cams:
                cam = name.split("/", 1)[1]
                try:
                    rgb = decode_raw(raw, demosaic=self.config.demosaic,
                                     expected_size=(int(rig_cams[cam]["height"]), int(rig_cams[cam]["width"]))).rgb
                except InputError as exc:  # a broken marker frame costs that camera's pose, not the session's
                    broken[cam] = str(exc)
                    continue
                # grey in albedo units: a white surface under full_on is ~1, the balls ~0.9
                images[cam] = rgb.mean(axis=-1) / float(np.mean(rig_cams[cam]["white_reference"]))
        decode_s = time.perf_counter() - t0
        for cam, why in sorted(broken.items()):
            ctx.log.warning("session %s: camera %s left out of the marker calibration: %s", ctx.scope_id, cam, why)
        folder = ctx.capture_root / "sessions" / ctx.scope_id / "calibration" / "markers"
        left_out = broken | {c: f"{folder}/{c}.*: no marker-frame frame for camera {c}"
                             for c in rig_cams if c not in images and c not in broken}
        if len(images) < 3:
            raise _MarkerCalibrationFailed(
                where, f"marker calibration of session {ctx.scope_id}: only {len(images)} usable marker-frame "
                       f"frames" + "".join(f"; {why}" for why in list(broken.values())[:3]), left_out)
        result = calibrate_markers(images, {c: np.asarray(rig_cams[c]["K"], float) for c in images},
                                   {c: np.asarray(rig_cams[c]["cam_from_world"], float) for c in images},
                                   np.asarray(spec["positions"], float), float(spec["radius_m"]), self.config.markers)
        if len(result.cameras) < max(3, self.config.min_registered_fraction * len(rig_cams)):
            raise _MarkerCalibrationFailed(where, f"marker calibration of session {ctx.scope_id} registered only "
                                                  f"{len(result.cameras)} of {len(rig_cams)} cameras: "
                                                  + "; ".join(result.notes[:6]), left_out)
        if result.reconstruction is not None:
            write_colmap_text(result, ArtifactWriter(self.name, ctx.out_dir).path("calibration_colmap"))
        cameras = [_record(rig_cams[c], cal.K.tolist(), cal.dist.tolist(), cal.cam_from_world.tolist())
                   for c, cal in sorted(result.cameras.items())]
        missing = {c: "marker calibration failed: " + next((n.split(": ", 1)[1] for n in result.notes
                                                            if n.startswith(f"{c}: ")), "not registered")
                   for c in result.unregistered}
        missing |= {c: "marker frame unusable: " + why for c, why in broken.items()}
        missing |= {c: "no marker-frame frame to calibrate from" for c in rig_cams if c not in images and c not in broken}
        timings = dict(result.timings) | {"decode": decode_s}
        summary = result.summary() | {"source": "markers", "unregistered": missing, "timings": timings,
                                      "frame": self.config.markers.frame,
                                      "nominal_offset_mm": list(result.alignment_residual_mm or [])}
        ArtifactWriter(self.name, ctx.out_dir).path("calibration_summary").write_text(
            json.dumps(summary, indent=1, default=float))
        for cam, why in sorted(missing.items()):
            ctx.log.warning("session %s: camera %s %s", ctx.scope_id, cam, why)
        return cameras, {"n_cameras": len(cameras), "missing_views": missing, "calibration_left_out": left_out,
                         "reprojection_error_px": float(result.reprojection_error_px),
                         "nominal_offset_mm": list(result.alignment_residual_mm or []),
                         "balls_seen": result.n_points3d, "seconds": decode_s + timings["total"]}

    def _calibrate(self, ctx: StageContext, rig_cams: dict[str, dict]) -> tuple[list[dict], dict[str, Any]]:
        from calibration.geometric import calibrate_images, write_colmap_text
        from pipeline.codecs.image import srgb_encode, write_png
        from pipeline.codecs.raw import decode_raw

        image_dir = ctx.out_dir / "images"
        paths, broken = [], {}
        for name, raw in sorted(ctx.raw_inputs.items()):
            if not name.startswith("calibration/"):
                continue
            cam = name.split("/", 1)[1]
            try:
                frame = decode_raw(raw, demosaic=self.config.demosaic)
            except InputError as exc:  # a broken frame costs that camera's registration, not the session's
                broken[cam] = str(exc)
                ctx.log.warning("session %s: camera %s left out of the calibration: %s", ctx.scope_id, cam, exc)
                continue
            white = np.asarray(rig_cams[cam]["white_reference"], np.float32)
            # Expose so a white surface sits at 0.8: SIFT wants contrast, not absolute radiance.
            pic = (srgb_encode(frame.rgb * (0.8 / float(white.max()))) * 255.0 + 0.5).astype(np.uint8)
            paths.append(write_png(image_dir / f"{cam}.png", pic))
        names = [p.name for p in paths]
        priors = {f"{c}.png": np.asarray(rig_cams[c]["K"], float) for c in rig_cams if f"{c}.png" in names}
        centres = {f"{c}.png": camera_centre(rig_cams[c]["cam_from_world"]) for c in rig_cams if f"{c}.png" in names}
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
        write_colmap_text(result, ArtifactWriter(self.name, ctx.out_dir).path("calibration_colmap"))
        shutil.rmtree(ctx.out_dir / "work", ignore_errors=True)
        cameras = []
        for name, cal in sorted(result.cameras.items()):
            cam_id = Path(name).stem
            cameras.append(_record(rig_cams[cam_id], cal.K.tolist(), cal.dist.tolist(), cal.cam_from_world.tolist()))
        missing = {Path(n).stem: "not registered by the calibration" for n in result.unregistered}
        missing |= {c: "white-light frame unusable: " + why for c, why in broken.items()}
        missing |= {c: "no white-light frame to calibrate from" for c in rig_cams
                    if f"{c}.png" not in names and c not in broken}
        summary = result.summary() | {"unregistered": missing}
        ArtifactWriter(self.name, ctx.out_dir).path("calibration_summary").write_text(
            json.dumps(summary, indent=1, default=float))
        for cam, why in sorted(missing.items()):
            ctx.log.warning("session %s: camera %s %s", ctx.scope_id, cam, why)
        return cameras, {"n_cameras": len(cameras), "missing_views": missing, "calibration_left_out": broken,
                         "reprojection_error_px": float(result.reprojection_error_px),
                         "alignment_residual_mm": list(result.alignment_residual_mm or [])}


    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        # The calibration's own COLMAP model (``colmap/`` of the artifact) stays in the work store: its images
        # are the marker frames (or the structure-from-motion frames), which the release does not hold, so no
        # name in it could point at a released file. The calibrated cameras are released under their images'
        # names in the exports stage's model (colmap/sparse/0) and transforms.json; the summary is released.
        return released_files(self.name, artifact, ("calibration_summary",), optional=("calibration_summary",))


def _frames(folder: Path, camera_ids: list[str]) -> dict[str, Path]:
    """camera id -> its frame ``folder/<cam>.*`` (first by name), for the cameras that have one."""
    if not folder.is_dir():
        return {}
    return {cam: p for cam in camera_ids if (p := next(iter(sorted(folder.glob(f"{cam}.*"))), None)) is not None}


def _rig_cameras(rig_cams: dict[str, dict]) -> tuple[list[dict], dict[str, Any]]:
    cameras = [_record(c, c["K"], c.get("dist", [0.0] * 5), c["cam_from_world"]) for c in rig_cams.values()]
    return cameras, {"n_cameras": len(cameras), "missing_views": {}}


def _record(rig_cam: dict[str, Any], K: Any, dist: Any, cam_from_world: Any) -> dict[str, Any]:
    return {"camera_id": rig_cam["camera_id"], "width": rig_cam["width"], "height": rig_cam["height"], "K": K,
            "dist": list(dist), "cam_from_world": cam_from_world, "white_reference": rig_cam["white_reference"],
            "exposure_s": rig_cam.get("exposure_s")}
