"""File conventions of the release that more than one stage writes by: the nerfstudio distortion fields of a
camera and the 8-bit sRGB encoding of the linear images (CONVENTIONS.md).

The decode stage writes the PNGs and ``transforms.json`` (which names the COLMAP model's points), the exports
stage the COLMAP model and the points' colours; both take these from here rather than from each other (and where
the COLMAP model lies from :data:`artifacts.layout.COLMAP_MODEL_DIR`).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.codecs.image import srgb_encode

def srgb_png(linear_rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: the sRGB transfer curve of the linear values clipped to [0, 1], no exposure change
    (1.0, the sensor's clip level, is 255), so ``srgb_decode(png / 255)`` gives back the EXR below 1."""
    rgb = np.nan_to_num(np.asarray(linear_rgb, np.float32)[..., :3], nan=0.0, posinf=1.0, neginf=0.0)
    return (srgb_encode(rgb) * 255.0 + 0.5).astype(np.uint8)


def distortion_fields(dist: Any) -> dict[str, float]:
    """OpenCV distortion (k1, k2, p1, p2[, k3]) as nerfstudio's per-frame fields (0 where absent)."""
    d = [float(x) for x in (list(dist or []) + [0.0] * 5)[:5]]
    return {"k1": d[0], "k2": d[1], "p1": d[2], "p2": d[3], "k3": d[4]}
