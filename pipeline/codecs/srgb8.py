"""8-bit sRGB photos (JPEG, PNG) decoded to the linear values the decode stage writes for raw frames.

The public release of the seed paper (RNHA) ships its frames as 8-bit sRGB JPEGs; :func:`decode_srgb8` turns
one into a :class:`pipeline.codecs.raw.DecodedFrame` as a raw decode would: ``rgb`` linear sRGB with 1.0 at
the 8-bit code 255 (the sRGB transfer curve undone, no exposure change) and ``clipped`` where any channel
sits at 255 (the value the photo was clipped to; the ratio of such a pixel is not a measurement).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.codecs.raw import DecodedFrame
from pipeline.errors import InputError

EIGHT_BIT_EXTENSIONS = (".jpg", ".jpeg", ".png")
"""File extensions (any case) decoded by :func:`decode_srgb8` instead of LibRaw."""

_LINEAR_OF_CODE = None


def linear_of_code() -> np.ndarray:
    """(256,) float32: the linear value of each 8-bit sRGB code (the IEC 61966-2-1 curve undone)."""
    global _LINEAR_OF_CODE
    if _LINEAR_OF_CODE is None:
        x = np.arange(256, dtype=np.float64) / 255.0
        _LINEAR_OF_CODE = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)
    return _LINEAR_OF_CODE


def is_eight_bit(path: str | Path) -> bool:
    """Whether ``path`` names an 8-bit photo (by its extension) rather than a raw frame."""
    return Path(path).suffix.lower() in EIGHT_BIT_EXTENSIONS


def read_srgb8(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an 8-bit photo (grey is repeated, alpha dropped).

    Raises:
        InputError: the file is missing, empty, not an image PIL reads, or not 8 bits per channel.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise InputError(path, "file is missing") from None
    if size == 0:
        raise InputError(path, "empty file (0 bytes)")
    try:
        with Image.open(path) as img:
            img.load()
            if img.mode not in ("L", "RGB", "RGBA", "LA", "P"):
                raise InputError(path, f"image mode {img.mode!r}: expected 8-bit RGB or grey")
            pixels = np.asarray(img.convert("RGB"))
    except UnidentifiedImageError:
        raise InputError(path, "not an image file (PIL cannot identify it)") from None
    except OSError as exc:  # truncated or corrupt data
        raise InputError(path, f"cannot decode the image ({exc})") from None
    return pixels


def decode_srgb8(path: str | Path, demosaic: str = "AHD", half_size: bool = False,
                 expected_size: tuple[int, int] | None = None) -> DecodedFrame:
    """Decode an 8-bit sRGB photo to linear values (the :func:`pipeline.codecs.raw.decode_raw` contract).

    Args:
        path: a JPEG or PNG (8 bits per channel, sRGB).
        demosaic: ignored (the photo is demosaiced already); kept so both decoders take the same arguments.
        half_size: average each 2x2 block of linear values to one pixel ((ceil(H/2), ceil(W/2)), edge pixels
            repeated for odd sizes); ``clipped`` is the OR over the block.
        expected_size: (H, W) the photo must have (from transforms.json); None skips the check.

    Returns:
        DecodedFrame: ``rgb`` float32 (H, W, 3) linear in [0, 1] (1.0 = code 255), ``clipped`` bool (H, W)
        where any channel is 255, ``camera`` "8-bit sRGB photo", ``demosaic`` "NONE" (or "HALF").

    Raises:
        InputError: unreadable file (see :func:`read_srgb8`), a wrong size, or an all-black photo.
    """
    path = Path(path)
    codes = read_srgb8(path)
    h, w = codes.shape[:2]
    if expected_size is not None and (h, w) != tuple(int(v) for v in expected_size):
        raise InputError(path, f"image is {w} x {h} pixels but its camera is {int(expected_size[1])} x "
                               f"{int(expected_size[0])} (transforms.json w, h): images of different sizes")
    if not codes.any():
        raise InputError(path, "black frame: every pixel is 0")
    rgb = linear_of_code()[codes]
    clipped = (codes == 255).any(axis=-1)
    if half_size:
        rgb, clipped = _half(rgb), _half_any(clipped)
    return DecodedFrame(rgb=np.ascontiguousarray(rgb, np.float32), clipped=clipped, black_level=0.0, white_level=255,
                        wb_multipliers=(1.0, 1.0, 1.0), camera="8-bit sRGB photo", raw_size=(h, w),
                        demosaic="HALF" if half_size else "NONE", half_size=half_size)


def _pad_even(x: np.ndarray) -> np.ndarray:
    h, w = x.shape[:2]
    pad = [(0, h % 2), (0, w % 2)] + [(0, 0)] * (x.ndim - 2)
    return np.pad(x, pad, mode="edge") if (h % 2 or w % 2) else x


def _half(rgb: np.ndarray) -> np.ndarray:
    x = _pad_even(rgb)
    return 0.25 * (x[0::2, 0::2] + x[1::2, 0::2] + x[0::2, 1::2] + x[1::2, 1::2])


def _half_any(mask: np.ndarray) -> np.ndarray:
    x = _pad_even(mask)
    return x[0::2, 0::2] | x[1::2, 0::2] | x[0::2, 1::2] | x[1::2, 1::2]


def read_mask8(path: str | Path, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W) bool subject mask of an 8-bit mask photo (JPEG or PNG, first channel above 127: a JPEG's
    ringing around the edge does not cross half way).

    Raises:
        InputError: unreadable file, or not of ``expected_size`` (H, W).
    """
    codes = read_srgb8(path)
    h, w = codes.shape[:2]
    if expected_size is not None and (h, w) != tuple(int(v) for v in expected_size):
        raise InputError(path, f"mask is {w} x {h} pixels but its camera is {int(expected_size[1])} x "
                               f"{int(expected_size[0])} (transforms.json w, h): images of different sizes")
    return codes[..., 0] > 127
