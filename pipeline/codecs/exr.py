"""OpenEXR read/write for float maps: half float, lossless ZIP compression, finite values only, with
optional header attributes (the colour space, what the channels hold and their units)."""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import OpenEXR

_DEFAULT_CHANNELS = {1: ("Y",), 2: ("Y", "A"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}
HALF_MAX = float(np.finfo(np.float16).max)
"""Largest finite half float (65504): half-float maps are clipped to [-HALF_MAX, HALF_MAX]."""

LINEAR_SRGB_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)
"""CIE xy of the red, green and blue primaries and the white point of linear sRGB / Rec. 709 (D65), in the
order of the EXR standard attribute ``chromaticities``."""

_RESERVED = {"channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
             "screenWindowCenter", "screenWindowWidth", "type", "tiles"}


def describe(content: str, units: str, colour: bool = False) -> dict[str, object]:
    """Header attributes that say what an EXR holds: ``content`` (what each channel is), ``units``, the
    same in the standard ``comments`` attribute (shown by ``exrheader`` and most viewers), and, for colour
    images (``colour=True``), the standard ``chromaticities`` of linear sRGB / Rec. 709 with a D65 white."""
    header: dict[str, object] = {"content": content, "units": units, "comments": f"{content} Units: {units}"}
    if colour:
        header["chromaticities"] = LINEAR_SRGB_CHROMATICITIES
    return header


def write_exr(path: str | Path, array: np.ndarray, channels: tuple[str, ...] | None = None,
              half: bool = True, header: Mapping[str, object] | None = None) -> Path:
    """Write an (H, W) or (H, W, C) float array as an EXR file.

    Args:
        path: destination; written under a temporary name and renamed, so readers never see half a file.
        array: (H, W) or (H, W, C) with C in 1..4 (or any C when ``channels`` names them).
        channels: channel names, default Y / YA / RGB / RGBA by channel count.
        half: store as half float (the release format) instead of float32.
        header: extra header attributes (e.g. from :func:`describe`): strings, or 8 floats for
            ``chromaticities``; the structural ones (channels, compression, windows, ...) are the writer's.

    Values beyond the stored type's finite range (65504 for half float, e.g. a sun in an HDR render; float32's
    for float64 input) are clipped to it, so no Inf is ever written.

    Raises:
        ValueError: non-finite values (NaN or Inf; nothing is written), a wrong shape, or a header attribute
            that would override a structural one.
    """
    path = Path(path)
    arr = np.asarray(array)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3:
        raise ValueError(f"{path}: expected (H, W) or (H, W, C), got shape {np.shape(array)}")
    n_channels = arr.shape[2]
    names = channels or _DEFAULT_CHANNELS.get(n_channels)
    if names is None or len(names) != n_channels:
        raise ValueError(f"{path}: {n_channels} channels need explicit names, got {channels}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{path}: refusing to write non-finite values (NaN or Inf)")
    dtype = np.float16 if half else np.float32
    limit = float(np.finfo(dtype).max)
    # clip in the input's precision, before the cast: a cast alone turns what is out of range into Inf
    data = {name: np.ascontiguousarray(np.clip(arr[:, :, i], -limit, limit).astype(dtype))
            for i, name in enumerate(names)}
    clash = sorted(set(header or {}) & _RESERVED)
    if clash:
        raise ValueError(f"{path}: header attributes {clash} are set by the writer")
    attributes = dict(header or {}) | {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with OpenEXR.File(attributes, data) as exr_file:
        exr_file.write(str(tmp))
    os.replace(tmp, path)
    return path


def read_exr(path: str | Path, channels: tuple[str, ...] | None = None) -> np.ndarray:
    """Read an EXR file as float32: (H, W) for one channel, else (H, W, C) in the named order.

    Default order: R, G, B, A when present, else Y (and A), else the file's channels sorted.
    """
    path = Path(path)
    with OpenEXR.File(str(path), separate_channels=True) as exr_file:
        planes = exr_file.channels()
        available = list(planes.keys())
        if channels is None:
            for candidate in (("R", "G", "B", "A"), ("R", "G", "B"), ("Y", "A"), ("Y",)):
                if set(candidate) <= set(available) and len(candidate) == len(available):
                    channels = candidate
                    break
            else:
                channels = tuple(sorted(available))
        missing = [c for c in channels if c not in planes]
        if missing:
            raise ValueError(f"{path}: channels {missing} not in file (has {available})")
        stack = [np.asarray(planes[c].pixels, dtype=np.float32) for c in channels]
    return stack[0] if len(stack) == 1 else np.stack(stack, axis=-1)


def read_exr_header(path: str | Path) -> dict[str, object]:
    """The header attributes of an EXR file (``content``, ``units``, ``chromaticities``, ... when written)."""
    with OpenEXR.File(str(path)) as exr_file:
        return dict(exr_file.header())
