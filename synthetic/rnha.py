"""A simulated capture in the seed paper's public release layout (RNHA), made from a simulated raw capture.

:func:`write_rnha_layout` turns each action of a raw capture (``synthetic.simulate``) into one folder of the
public layout (``pipeline.capture_rnha``)::

    <out>/<action_id>/full_on/<cam>.jpg  pos/<cam>.jpg  neg/<cam>.jpg  mask/<cam>.jpg  normal_alpha/<cam>.jpg
    <out>/<action_id>/transforms.json

as a release author would make it from the same frames: each raw frame decoded by LibRaw (AHD, sRGB output,
:func:`pipeline.codecs.raw.decode_raw`, as the raw path's decode stage does before its colour matrix),
white-balanced and exposed so that the camera's white reference (an albedo-1 unoccluded Lambertian under
full_on) is 1.0 (the reader's default white reference), the sRGB curve, 8 bits, JPEG quality
:data:`JPEG_QUALITY` with PIL's default 4:2:0 chroma subsampling (the public release's quality is not stated;
95 is what the issue asks when unknown). The masks are the simulator's true masks (a release ships its own
segmentation); ``normal_alpha/`` holds eq. 1 normals of the decoded frames as ``(n + 1) / 2`` times the mask
(JPEG has no alpha channel; the pipeline does not read it). ``transforms.json`` holds the simulator's true
cameras (a release holds its calibrated ones) in the instant-ngp convention with its keys: per frame
``file_path``, ``transform_matrix`` (OpenGL camera-to-world), ``fl_x``, ``fl_y``, ``cx``, ``cy`` (pixel centres
at +0.5), ``w``, ``h``; at the top ``scale`` and ``offset`` (instant-ngp's unit cube around the cameras) and
``aabb_scale``. The raw capture (with its ``ground_truth/``) stays beside it, so the release made from the
8-bit photos is measured against the same truth as the raw path's.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Callable

import numpy as np
from PIL import Image

from pipeline.codecs.image import srgb_encode
from pipeline.codecs.raw import decode_raw

JPEG_QUALITY = 95
"""JPEG quality of the simulated public layout (the public release does not state its own)."""
ILLUMINATIONS = ("full_on", "pos", "neg")
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def eight_bit(linear: np.ndarray, white_reference: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 sRGB codes of a decoded linear frame (H, W, 3) exposed so ``white_reference`` (3,) is 255.

    Raises:
        ValueError: a frame that is not (H, W, 3) or a white reference that is not three positive numbers.
    """
    linear = np.asarray(linear, np.float32)
    white = np.asarray(white_reference, np.float32)
    if linear.ndim != 3 or linear.shape[2] != 3:
        raise ValueError(f"frame must be (H, W, 3), got {linear.shape}")
    if white.shape != (3,) or not np.all(white > 0):
        raise ValueError(f"white_reference must be three positive numbers, got {white_reference!r}")
    return np.rint(srgb_encode(linear / white) * 255.0).astype(np.uint8)


def eq1_normal_picture(pos: np.ndarray, neg: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 ``(n + 1) / 2`` of eq. 1's normals n = normalize((pos - neg) / (pos + neg)) inside ``mask``
    (0 outside it and where the ratio is 0)."""
    d = (pos - neg) / np.maximum(pos + neg, 1e-6)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    n = np.where(norm > 0, d / np.maximum(norm, 1e-12), 0.0)
    picture = np.rint((n + 1.0) * 0.5 * 255.0) * (mask[..., None] & (norm > 0))
    return np.clip(picture, 0, 255).astype(np.uint8)


def transforms_record(cameras: list[dict[str, Any]], image_dir: str = "full_on", ext: str = ".jpg") -> dict[str, Any]:
    """The instant-ngp transforms.json of OpenCV camera records (K, cam_from_world, width, height): per frame
    ``file_path``, ``transform_matrix`` (OpenGL camera-to-world), ``fl_x``, ``fl_y``, ``cx``, ``cy`` (``K`` + 0.5),
    ``w``, ``h``; ``scale`` puts the camera centres within 0.45 of the cube's centre, ``offset`` [0.5, 0.5, 0.5]."""
    frames, centres = [], []
    for cam in cameras:
        P = np.eye(4)
        P[:3] = np.asarray(cam["cam_from_world"], np.float64)[:3]
        world_from_cam = np.linalg.inv(P)
        centres.append(world_from_cam[:3, 3])
        K = np.asarray(cam["K"], np.float64)
        frames.append({"file_path": f"{image_dir}/{cam['camera_id']}{ext}",
                       "transform_matrix": (world_from_cam @ OPENGL_FROM_OPENCV).tolist(),
                       "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]) + 0.5,
                       "cy": float(K[1, 2]) + 0.5, "w": int(cam["width"]), "h": int(cam["height"])})
    reach = float(np.max(np.abs(np.asarray(centres)))) if centres else 1.0
    return {"aabb_scale": 1, "scale": round(0.45 / reach, 6), "offset": [0.5, 0.5, 0.5], "frames": frames}


def _save_jpeg(path: Path, codes: np.ndarray, quality: int) -> None:
    """Save 8-bit codes as a JPEG of ``quality``, or losslessly as PNG when ``path`` ends in .png."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".png":
        Image.fromarray(codes).save(path, format="PNG")
    else:
        Image.fromarray(codes).save(path, format="JPEG", quality=quality)


def write_rnha_layout(raw_capture: str | Path, out: str | Path, quality: int = JPEG_QUALITY,
                      progress: Callable[[str], None] | None = None, lossless: bool = False) -> Path:
    """Write the public layout of every action of a simulated raw capture into ``out`` (see the module docstring).

    Args:
        raw_capture: a capture written by :func:`synthetic.simulate` (with ``ground_truth/``).
        out: the folder of action folders to write (replaced whole: written beside it, then renamed).
        quality: JPEG quality, 1..100.
        lossless: write the same 8-bit codes as PNG instead of JPEG (a control that separates what JPEG's
            compression costs from what 8 bits cost; the public release is JPEG).

    Returns:
        ``out``.

    Raises:
        ValueError: ``quality`` outside 1..100, or a capture without the simulator's true cameras.
    """
    import shutil

    if not 1 <= int(quality) <= 100:
        raise ValueError(f"JPEG quality must be in 1..100, got {quality}")
    raw_capture, out = Path(raw_capture), Path(out)
    meta = json.loads((raw_capture / "capture.json").read_text())
    truth = raw_capture / "ground_truth"
    tmp = out.with_name(f".{out.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    ext = ".png" if lossless else ".jpg"
    for entry in meta["actions"]:
        action_id, session_id = entry["action_id"], entry["session_id"]
        cameras_path = truth / "cameras" / f"{session_id}.json"
        if not cameras_path.exists():
            raise ValueError(f"{cameras_path}: no true cameras (not a capture of the simulator)")
        cameras = json.loads(cameras_path.read_text())["cameras"]
        folder = tmp / action_id
        for cam in cameras:
            cid = cam["camera_id"]
            white = np.asarray(cam["white_reference"], np.float32)
            linear = {}
            for illum in ILLUMINATIONS:
                raw = next(iter(sorted((raw_capture / "actions" / action_id / illum).glob(f"{cid}.*"))))
                linear[illum] = decode_raw(raw, demosaic="AHD").rgb
                _save_jpeg(folder / illum / f"{cid}{ext}", eight_bit(linear[illum], white), quality)
            with Image.open(truth / action_id / "mask" / f"{cid}.png") as img:
                mask = np.asarray(img)
            mask = (mask[..., 0] if mask.ndim == 3 else mask) > 127
            _save_jpeg(folder / "mask" / f"{cid}{ext}", (mask * np.uint8(255)).astype(np.uint8), quality)
            _save_jpeg(folder / "normal_alpha" / f"{cid}{ext}", eq1_normal_picture(linear["pos"], linear["neg"], mask),
                       quality)
        (folder / "transforms.json").write_text(json.dumps(transforms_record(cameras, ext=ext), indent=1))
        if progress is not None:
            progress(f"{action_id}: {len(cameras)} cameras in the public layout ("
                     + ("lossless PNG" if lossless else f"JPEG quality {quality}") + ")")
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists():
        old = out.with_name(f".{out.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(out, old)
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out)
    return out
