"""Action stage ``decode``: raw files to linear sRGB EXR, one task per camera.

Wiring only: the decoding itself is :func:`pipeline.codecs.raw.decode_raw` (8-bit sRGB photos of the public
release's layout: :func:`pipeline.codecs.srgb8.decode_srgb8`, the sRGB curve undone). Each camera's three
illuminations are decoded in one task and written as half-float EXR (its header says the colour space and
units) and as an 8-bit sRGB PNG beside it (for viewers and for tools that read 8-bit images: nerfstudio,
splatting trainers); the sensor's clipped pixels (any of the three frames) go to ``clipped/<cam>.png`` for
the photometric stage's validity alpha. ``transforms.json`` holds the cameras in the nerfstudio / instant-ngp
convention with the OpenCV matrices beside (:func:`transforms_json`).
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
from pipeline.codecs.srgb8 import decode_srgb8, is_eight_bit
from pipeline.config import Documented
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from calibration.colour import apply_colour_matrix
from artifacts.facade import ActionArtifacts
from artifacts.layout import COLMAP_MODEL_DIR, ArtifactWriter, released_files
from stages.conventions import distortion_fields, srgb_png
from stages.exr_headers import EXR_HEADERS

ILLUMINATIONS = ("full_on", "pos", "neg")
RELEASED = ("transforms",) + tuple(p for illum in ILLUMINATIONS for p in (illum, f"{illum}_png"))
"""The products this stage publishes, in order: transforms.json, then each illumination's EXRs and its PNGs, a
file a camera (their paths and kinds: :data:`artifacts.layout.PRODUCTS`, :data:`artifacts.layout.RELEASE_KINDS`)."""
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Camera axes: OpenCV (x right, y down, z forward) to OpenGL (x right, y up, z back); its own inverse."""


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


def opengl_camera_to_world(cam_from_world: np.ndarray) -> np.ndarray:
    """(4, 4) camera-to-world with OpenGL camera axes (nerfstudio's and instant-ngp's ``transform_matrix``)
    from an OpenCV (3, 4) or (4, 4) cam_from_world: the OpenCV world_from_cam with its y and z columns negated."""
    P = np.eye(4)
    P[:3, :4] = np.asarray(cam_from_world, np.float64)[:3, :4]
    return np.linalg.inv(P) @ OPENGL_FROM_OPENCV


def opencv_cam_from_world(transform_matrix: np.ndarray) -> np.ndarray:
    """(3, 4) OpenCV cam_from_world from an OpenGL camera-to-world ``transform_matrix`` (the inverse of
    :func:`opengl_camera_to_world`)."""
    return np.linalg.inv(np.asarray(transform_matrix, np.float64) @ OPENGL_FROM_OPENCV)[:3, :4]


def transforms_json(cameras: list[dict[str, Any]], image_dir: str = "full_on") -> dict[str, Any]:
    """The release's transforms.json for the cameras (OpenCV records: K, dist, cam_from_world, width, height).

    ``transform_matrix``, ``fl_x``, ``fl_y``, ``cx``, ``cy`` and the distortion fields follow nerfstudio /
    instant-ngp (OpenGL camera-to-world; pixel centres at +0.5, as COLMAP: ``cx`` = OpenCV ``K[0][2]`` + 0.5).
    ``K``, ``dist``, ``cam_from_world_opencv`` and ``world_from_cam_opencv`` are the OpenCV ones.
    """
    frames = []
    for cam in cameras:
        cid = cam["camera_id"]
        K = np.asarray(cam["K"], np.float64)
        cam_from_world = np.eye(4)
        cam_from_world[:3, :4] = np.asarray(cam["cam_from_world"], np.float64)[:3, :4]
        frames.append({
            "camera_id": cid, "file_path": f"{image_dir}/{cid}.png", "mask_path": f"mask/{cid}.png",
            "exr_path": f"{image_dir}/{cid}.exr", "w": int(cam["width"]), "h": int(cam["height"]),
            "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]) + 0.5, "cy": float(K[1, 2]) + 0.5,
            **distortion_fields(cam.get("dist")),
            "transform_matrix": opengl_camera_to_world(cam_from_world).tolist(),
            "K": K.tolist(), "dist": list(distortion_fields(cam.get("dist")).values()),  # OpenCV order
            "cam_from_world_opencv": cam_from_world[:3].tolist(),
            "world_from_cam_opencv": np.linalg.inv(cam_from_world).tolist()})
    return {"camera_model": "OPENCV",
            "matrix_conventions": "transform_matrix: camera-to-world, OpenGL camera axes (x right, y up, z back), "
                                  "as nerfstudio and instant-ngp read it; cam_from_world_opencv (3x4) and "
                                  "world_from_cam_opencv (4x4): OpenCV camera axes (x right, y down, z forward); "
                                  "transform_matrix = world_from_cam_opencv @ diag(1, -1, -1, 1) (CONVENTIONS.md)",
            "intrinsics_conventions": "fl_x, fl_y, cx, cy, k1, k2, p1, p2, k3: nerfstudio/COLMAP (pixel centres at "
                                      "+0.5: cx = K[0][2] + 0.5); K and dist: OpenCV (pixel centres at integers)",
            "units": "metres", "world": "stage frame: origin at the LED-sphere centre, +y up",
            "ply_file_path": f"{COLMAP_MODEL_DIR}/points3D.ply", "frames": frames}


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
    version = "3"
    scope = "action"
    requires = ("cameras", "colour")
    outputs = ("full_on", "pos", "neg", "clipped", "cameras.json", "transforms.json")
    """full_on/, pos/, neg/ hold <cam>.exr (linear) and <cam>.png (8-bit sRGB)."""
    per_view = True

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        frames, errors = capture.action_frames(scope_id)
        if errors:
            more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
            raise InputError(errors[0].path, errors[0].reason + more)
        return {f"{illum}/{cam}": path for (illum, cam), path in frames.items()}

    def run_view(self, ctx: StageContext, view: str) -> dict[str, Any]:
        upstream = ActionArtifacts(ctx.upstream)
        out = ArtifactWriter(self.name, ctx.out_dir)
        cameras = upstream.camera_records("session_cameras")
        if view not in cameras:  # the session's calibration could not register it: a missing camera
            return {"missing": upstream.unregistered_cameras().get(view, "camera has no calibration")}
        cam = cameras[view]
        expected = (int(cam["height"]), int(cam["width"]))
        clipped = None
        stats: dict[str, Any] = {}
        shape = None
        matrix = upstream.colour_matrix(view)
        stats["raw_blake2b"] = {}
        for illum in ILLUMINATIONS:
            path = ctx.raw_inputs[f"{illum}/{view}"]
            stats["raw_blake2b"][illum] = _file_digest(path)
            decode = decode_srgb8 if is_eight_bit(path) else decode_raw  # the public layout's 8-bit photos
            frame = decode(path, demosaic=self.config.demosaic, half_size=self.config.half_size,
                           expected_size=expected)
            if shape is not None and frame.rgb.shape != shape:
                raise InputError(path, f"decoded size {frame.rgb.shape[:2]} differs from the other "
                                       f"illuminations' {shape[:2]}")
            shape = frame.rgb.shape
            if matrix is not None:
                apply_colour_matrix(frame.rgb, matrix, out=frame.rgb)
                np.maximum(frame.rgb, 0.0, out=frame.rgb)
            write_exr(out.path(illum, view), frame.rgb, header=EXR_HEADERS[illum])
            write_png(out.path(f"{illum}_png", view), srgb_png(frame.rgb))
            clipped = frame.clipped if clipped is None else (clipped | frame.clipped)
            stats[f"{illum}_mean"] = float(frame.rgb.mean())
            stats[f"{illum}_clipped_fraction"] = float(frame.clipped.mean())
        write_png(out.path("clipped", view), clipped)
        stats["height"], stats["width"] = int(shape[0]), int(shape[1])
        return stats

    def finalize(self, ctx: StageContext, view_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
        check_no_duplicate_frames(ctx.raw_inputs, view_stats)
        out = ArtifactWriter(self.name, ctx.out_dir)
        cameras = [scale_camera(c, self.config.half_size)
                   for c in ActionArtifacts(ctx.upstream).camera_records("session_cameras").values()]
        out.path("cameras").write_text(json.dumps({"camera_convention": "opencv", "cameras": cameras}, indent=1))
        out.path("transforms").write_text(json.dumps(transforms_json(cameras), indent=1))
        return {"views": view_stats}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        return released_files(self.name, artifact, RELEASED)
