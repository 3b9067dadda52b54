"""File writers of the simulator (all atomic: temporary name in the same folder, then os.replace)."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from pipeline.codecs.exr import write_exr
from pipeline.codecs.image import preview_linear, write_png

from .sensor import BLACK_LEVEL, WHITE_LEVEL


def _tmp(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def write_json(path: str | Path, record: dict) -> Path:
    """Write a JSON document (indented, keys in insertion order) atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp(path)
    tmp.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, path)
    return path


def write_ply(path: str | Path, vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray | None = None) -> Path:
    """Binary little-endian PLY of a triangle mesh: vertices (V, 3), triangles (T, 3), normals (V, 3)."""
    path = Path(path)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    vertex_records = np.zeros(len(vertices), dtype=fields)
    for i, axis in enumerate("xyz"):
        vertex_records[axis] = vertices[:, i]
        if normals is not None:
            vertex_records["n" + axis] = normals[:, i]
    face_records = np.zeros(len(triangles), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face_records["n"] = 3
    face_records["v"] = triangles
    header = ["ply", "format binary_little_endian 1.0", "comment UltraStage simulator, world frame, metres",
              f"element vertex {len(vertices)}"]
    header += [f"property float {name}" for name, _ in fields]
    header += [f"element face {len(triangles)}", "property list uchar int vertex_indices", "end_header"]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp(path)
    with open(tmp, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        handle.write(vertex_records.tobytes())
        handle.write(face_records.tobytes())
    os.replace(tmp, path)
    return path


def write_ground_truth(folder: Path, camera_id: str, normals_world: np.ndarray, albedo: np.ndarray,
                       roughness: np.ndarray, depth_m: np.ndarray, visibility: np.ndarray, mask: np.ndarray) -> None:
    """One camera's ground-truth maps under `folder` (ground_truth/<action_id>/), CONTRACTS layout."""
    write_exr(folder / "normal" / f"{camera_id}.exr", normals_world)
    write_exr(folder / "albedo" / f"{camera_id}.exr", albedo)
    write_exr(folder / "roughness" / f"{camera_id}.exr", roughness)
    write_exr(folder / "depth" / f"{camera_id}.exr", depth_m)
    write_exr(folder / "visibility" / f"{camera_id}.exr", visibility)
    write_png(folder / "mask" / f"{camera_id}.png", mask.astype(bool))


def thumbnail(decoded_linear: np.ndarray, max_width: int = 160) -> np.ndarray:
    """uint8 sRGB thumbnail (h, w, 3) of a decoded-linear image (H, W, 3) (box-downsampled)."""
    factor = max(1, int(np.ceil(decoded_linear.shape[1] / max_width)))
    h = decoded_linear.shape[0] // factor * factor
    w = decoded_linear.shape[1] // factor * factor
    small = decoded_linear[:h, :w].reshape(h // factor, factor, w // factor, factor, 3).mean(axis=(1, 3))
    return preview_linear(small, exposure=1.5)


def contact_sheet(thumbnails: list[np.ndarray], columns: int = 8, gap: int = 2) -> np.ndarray:
    """Grid (uint8 RGB) of equally sized thumbnails, `columns` wide, separated by `gap` black pixels."""
    columns = min(columns, len(thumbnails))
    rows = -(-len(thumbnails) // columns)
    th, tw = thumbnails[0].shape[:2]
    sheet = np.zeros((rows * (th + gap) - gap, columns * (tw + gap) - gap, 3), np.uint8)
    for index, thumb in enumerate(thumbnails):
        r, c = divmod(index, columns)
        sheet[r * (th + gap):r * (th + gap) + th, c * (tw + gap):c * (tw + gap) + tw] = thumb
    return sheet


def _rationals(values: np.ndarray, denominator: int = 1_000_000) -> list[int]:
    return [x for v in np.ravel(values) for x in (int(round(float(v) * denominator)), denominator)]


def write_dng(path: str | Path, raw: np.ndarray, cam_from_xyz: np.ndarray, neutral: np.ndarray) -> Path:
    """Write an uncompressed 16-bit RGGB CFA DNG that LibRaw reads; atomic (temporary name + rename).

    raw: (H, W) uint16 DN; cam_from_xyz: (3, 3) ColorMatrix1 (D65); neutral: (3,) AsShotNeutral.
    """
    import tifffile

    path = Path(path)
    extratags = [
        (33421, "H", 2, (2, 2), True),                  # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), True),            # CFAPattern RGGB
        (50706, "B", 4, (1, 4, 0, 0), True),            # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),            # DNGBackwardVersion
        (50708, "s", 0, "UltraStage Simulated D750", True),
        (50714, "I", 1, BLACK_LEVEL, True),
        (50717, "I", 1, WHITE_LEVEL, True),
        (50721, "2i", 9, _rationals(cam_from_xyz), True),   # ColorMatrix1, XYZ -> camera
        (50728, "2I", 3, _rationals(neutral), True),        # AsShotNeutral
        (50778, "H", 1, 21, True),                      # CalibrationIlluminant1 = D65
        (271, "s", 0, "UltraStage", True),
        (272, "s", 0, "SimD750", True),
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp(path)
    tifffile.imwrite(tmp, np.ascontiguousarray(raw, dtype=np.uint16), photometric=32803, extratags=extratags,
                     subfiletype=0, compression=None, metadata=None)
    os.replace(tmp, path)
    return path
