"""Action stage ``decode`` and session stage ``plates``: raw files to linear sRGB EXR, one task per camera.

Wiring only: the decoding itself is :func:`pipeline.codecs.raw.decode_raw`. Each camera's three
illuminations are decoded in one task and written as half-float EXR; the sensor's clipped pixels (any of
the three frames) go to ``clipped/<cam>.png`` for the photometric stage's validity alpha.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from pipeline.codecs.exr import write_exr
from pipeline.codecs.image import write_png
from pipeline.codecs.raw import decode_raw
from pipeline.config import Documented
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from calibration.colour import apply_colour_matrix
from stages.cameras import load_cameras, unregistered_cameras
from stages.lightcolour import colour_matrix

ILLUMINATIONS = ("full_on", "pos", "neg")


@dataclass(frozen=True)
class DecodeConfig(Documented):
    demosaic: Literal["LINEAR", "VNG", "PPG", "AHD", "DCB", "DHT", "AAHD"] = "AHD"
    """LibRaw demosaic algorithm (bench/bench_decode.py measures time against error for each)."""
    half_size: bool = False
    """Decode 2x2 Bayer blocks to one pixel: 4-8x faster, enough when the maps need at most half the
    sensor's resolution. Camera intrinsics are scaled to match."""


def scale_camera(cam: dict[str, Any], half_size: bool) -> dict[str, Any]:
    """The camera record at the decoded resolution (CONTRACTS.md: half-size K convention)."""
    if not half_size:
        return dict(cam)
    K = np.asarray(cam["K"], dtype=float).copy()
    K[0, 0] /= 2
    K[1, 1] /= 2
    K[0, 2] = (K[0, 2] - 0.5) / 2
    K[1, 2] = (K[1, 2] - 0.5) / 2
    return dict(cam) | {"K": K.tolist(), "width": cam["width"] // 2, "height": cam["height"] // 2}


def transforms_json(cameras: list[dict[str, Any]], image_dir: str = "full_on") -> dict[str, Any]:
    """The release's transforms.json: per-frame K and world_from_cam 4x4 (OpenCV axes; CONVENTIONS.md)."""
    frames = []
    for cam in cameras:
        cam_from_world = np.eye(4)
        cam_from_world[:3, :4] = np.asarray(cam["cam_from_world"], dtype=float)
        world_from_cam = np.linalg.inv(cam_from_world)
        K = cam["K"]
        frames.append({"camera_id": cam["camera_id"], "file_path": f"{image_dir}/{cam['camera_id']}.exr",
                       "w": cam["width"], "h": cam["height"], "fl_x": K[0][0], "fl_y": K[1][1],
                       "cx": K[0][2], "cy": K[1][2], "K": K, "dist": cam.get("dist", [0.0] * 5),
                       "transform_matrix": world_from_cam.tolist()})
    return {"camera_convention": "opencv", "transform_matrix": "world_from_cam", "units": "metres",
            "frame": "stage: origin at LED-sphere centre, +y up", "frames": frames}


def _file_digest(path: Path) -> str:
    """BLAKE2b-128 of a file's bytes (read in blocks; the decode reads the same bytes from the page cache)."""
    digest = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def check_no_duplicate_frames(raw_inputs: dict[str, Path], view_stats: dict[str, dict[str, Any]]) -> None:
    """Raise InputError when two frames of an action are byte-identical (one frame delivered under two names,
    e.g. copied to another camera's or illumination's file): the ratio of a pair that is one frame twice is
    0 everywhere, and a camera with another's frame gets normals of the wrong view. ``view_stats`` are the
    decode's per-camera stats with ``raw_blake2b`` (illumination -> digest)."""
    seen: dict[str, str] = {}
    for view, stats in sorted(view_stats.items()):
        for illum, digest in sorted((stats or {}).get("raw_blake2b", {}).items()):
            name = f"{illum}/{view}"
            if digest in seen:
                raise InputError(raw_inputs.get(name, name), f"the same bytes as {raw_inputs.get(seen[digest], seen[digest])}: "
                                                             "one frame delivered twice (a duplicate frame)")
            seen[digest] = name


class DecodeStage(Stage):
    name = "decode"
    version = "2"
    scope = "action"
    requires = ("cameras", "colour")
    outputs = ("full_on", "pos", "neg", "clipped", "cameras.json", "transforms.json")
    per_view = True

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        frames, errors = capture.action_frames(scope_id)
        if errors:
            more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
            raise InputError(errors[0].path, errors[0].reason + more)
        return {f"{illum}/{cam}": path for (illum, cam), path in frames.items()}

    def run_view(self, ctx: StageContext, view: str) -> dict[str, Any]:
        cameras_json = ctx.upstream["cameras"] / "cameras.json"
        cameras = load_cameras(cameras_json)
        if view not in cameras:  # the session's calibration could not register it: a missing camera
            return {"missing": unregistered_cameras(cameras_json).get(view, "camera has no calibration")}
        cam = cameras[view]
        expected = (int(cam["height"]), int(cam["width"]))
        clipped = None
        stats: dict[str, Any] = {}
        shape = None
        matrix = colour_matrix(ctx.upstream["colour"], view)
        stats["raw_blake2b"] = {}
        for illum in ILLUMINATIONS:
            path = ctx.raw_inputs[f"{illum}/{view}"]
            stats["raw_blake2b"][illum] = _file_digest(path)
            frame = decode_raw(path, demosaic=self.config.demosaic, half_size=self.config.half_size,
                               expected_size=expected)
            if shape is not None and frame.rgb.shape != shape:
                raise InputError(path, f"decoded size {frame.rgb.shape[:2]} differs from the other "
                                       f"illuminations' {shape[:2]}")
            shape = frame.rgb.shape
            if matrix is not None:
                apply_colour_matrix(frame.rgb, matrix, out=frame.rgb)
                np.maximum(frame.rgb, 0.0, out=frame.rgb)
            write_exr(ctx.out_dir / illum / f"{view}.exr", frame.rgb)
            clipped = frame.clipped if clipped is None else (clipped | frame.clipped)
            stats[f"{illum}_mean"] = float(frame.rgb.mean())
            stats[f"{illum}_clipped_fraction"] = float(frame.clipped.mean())
        write_png(ctx.out_dir / "clipped" / f"{view}.png", clipped)
        stats["height"], stats["width"] = int(shape[0]), int(shape[1])
        return stats

    def finalize(self, ctx: StageContext, view_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
        check_no_duplicate_frames(ctx.raw_inputs, view_stats)
        cameras = [scale_camera(c, self.config.half_size)
                   for c in load_cameras(ctx.upstream["cameras"] / "cameras.json").values()]
        (ctx.out_dir / "cameras.json").write_text(json.dumps({"camera_convention": "opencv",
                                                              "cameras": cameras}, indent=1))
        (ctx.out_dir / "transforms.json").write_text(json.dumps(transforms_json(cameras), indent=1))
        return {"views": view_stats}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        files = [(artifact / "transforms.json", "transforms.json", "transforms", None)]
        for illum in ILLUMINATIONS:
            files += [(p, f"{illum}/{p.name}", illum, p.stem) for p in sorted((artifact / illum).glob("*.exr"))]
        return files


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
        matrix = colour_matrix(ctx.upstream["colour"], view)
        if matrix is not None:
            apply_colour_matrix(frame.rgb, matrix, out=frame.rgb)
            np.maximum(frame.rgb, 0.0, out=frame.rgb)
        write_exr(ctx.out_dir / "plates" / f"{view}.exr", frame.rgb)
        return {"plate": True, "mean": float(frame.rgb.mean())}
