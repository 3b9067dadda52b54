"""PNG read/write and preview rendering (8-bit sRGB pictures of linear maps)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image


def write_png(path: str | Path, array: np.ndarray) -> Path:
    """Write a uint8/uint16 (H, W) or (H, W, 3|4) array, or a bool mask (as 0/255), atomically."""
    path = Path(path)
    arr = np.asarray(array)
    if arr.dtype == bool:
        arr = arr.astype(np.uint8) * 255
    if arr.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{path}: write_png takes uint8, uint16 or bool, got {arr.dtype}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    Image.fromarray(arr).save(tmp, format="PNG", compress_level=3)
    os.replace(tmp, path)
    return path


def read_png(path: str | Path) -> np.ndarray:
    """Read a PNG as its stored dtype, (H, W) or (H, W, C)."""
    with Image.open(path) as img:
        return np.asarray(img)


def mask_from_png(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool subject mask of a mask PNG's pixels ((H, W) or (H, W, C), first channel): above half the
    dtype's range (127 of 8 bits)."""
    mask = mask[..., 0] if mask.ndim == 3 else mask
    return mask > (np.iinfo(mask.dtype).max // 2 if np.issubdtype(mask.dtype, np.integer) else 0.5)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] to the sRGB transfer curve, float in [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] to linear [0, 1]."""
    x = np.clip(encoded, 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))


def preview_linear(rgb: np.ndarray, exposure: float | None = None) -> np.ndarray:
    """uint8 sRGB picture of a linear image; exposure defaults to putting the 99th percentile at 0.9."""
    rgb = np.nan_to_num(np.asarray(rgb, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    if exposure is None:
        p99 = float(np.percentile(rgb, 99)) if rgb.size else 1.0
        exposure = 0.9 / p99 if p99 > 0 else 1.0
    return (srgb_encode(rgb * exposure) * 255.0 + 0.5).astype(np.uint8)


def preview_normals(normals: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """uint8 RGB picture of unit normals ((n + 1) / 2), black where alpha <= 0.5."""
    pic = (np.clip((np.asarray(normals, dtype=np.float32) + 1.0) * 0.5, 0, 1) * 255.0 + 0.5).astype(np.uint8)
    if alpha is not None:
        pic[np.asarray(alpha) <= 0.5] = 0
    return pic


def preview_scalar(values: np.ndarray, vmin: float = 0.0, vmax: float = 1.0) -> np.ndarray:
    """uint8 grey picture of a scalar map mapped from [vmin, vmax]."""
    v = np.nan_to_num(np.asarray(values, dtype=np.float32))
    return (np.clip((v - vmin) / max(vmax - vmin, 1e-12), 0, 1) * 255.0 + 0.5).astype(np.uint8)


def label_picture(picture: np.ndarray, text: str) -> np.ndarray:
    """A copy of a uint8 (H, W, 3) picture with ``text`` written in its top-left corner, light on a dark band,
    in Pillow's default font: 11 px high, smaller (down to 9 px) where the text is wider than the picture, and
    broken at spaces onto more lines where even that is too wide."""
    from PIL import ImageDraw, ImageFont

    pic = np.asarray(picture)
    if pic.dtype != np.uint8 or pic.ndim != 3 or pic.shape[2] < 3:
        raise ValueError(f"label_picture takes a uint8 (H, W, 3) picture, got {pic.dtype} {pic.shape}")
    image = Image.fromarray(np.ascontiguousarray(pic[..., :3]))
    draw = ImageDraw.Draw(image)
    room = image.width - 6
    for size in (11, 10, 9):
        font = ImageFont.load_default(size=size)
        if draw.textlength(text, font=font) <= room:
            break
    else:
        lines = [""]
        for word in text.split(" "):
            joined = f"{lines[-1]} {word}".strip()
            if lines[-1] and draw.textlength(joined, font=font) > room:
                lines.append(word)
            else:
                lines[-1] = joined
        text = "\n".join(lines)
    left, top, right, bottom = draw.multiline_textbbox((3, 2), text, font=font, spacing=1)
    draw.rectangle((0, 0, min(right + 3, image.width - 1), min(bottom + 2, image.height - 1)), fill=(0, 0, 0))
    draw.multiline_text((3, 2), text, fill=(255, 255, 255), font=font, spacing=1)
    out = np.asarray(image).copy()
    return np.concatenate([out, pic[..., 3:]], axis=2) if pic.shape[2] > 3 else out
