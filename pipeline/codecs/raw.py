"""Raw camera files (DNG, NEF, CR2, ... anything LibRaw reads) to linear sRGB float images.

One function, :func:`decode_raw`, turns a Bayer raw frame into the decoded linear values of
docs/CONTRACTS.md: black level subtracted, camera (as-shot) white balance applied, camera RGB converted
to linear sRGB with the file's colour matrix, no gamma, no auto-brightening, no flip. ``1.0`` is the clip
level of the raw channel with the smallest white-balance multiplier (green), i.e.
``(raw_green - black) / (white - black)`` for a neutral surface. Channels whose multiplier is larger
(red, blue) clip below their sensor clip level in these units, and LibRaw clips every output value at
``1.0``; the ``clipped`` mask says where the sensor itself saturated.

Every bad input is a :class:`pipeline.errors.RawDecodeError` with a specific reason: missing, empty,
truncated, unreadable, not a Bayer camera frame, wrong size, black, saturated.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import RawDecodeError

__all__ = [
    "DecodedFrame",
    "decode_raw",
    "supported_demosaic",
    "BLACK_FRAME_LEVEL",
    "SATURATED_FRAME_FRACTION",
    "CLIP_MARGIN",
]

#: A frame is black when the 99.9th percentile of ``(raw - black) / (white - black)`` is below this.
BLACK_FRAME_LEVEL = 0.002
#: A frame is saturated when more than this fraction of its CFA sites is clipped.
SATURATED_FRAME_FRACTION = 0.5
#: A CFA site is clipped when ``raw >= white - CLIP_MARGIN * (white - black)`` (at least 1 DN below white).
#: Real sensors often saturate a little below the declared white level (the Blackmagic DNG at 65472
#: of 65535), so the margin is a few tenths of a percent of the range.
CLIP_MARGIN = 0.002

_DEMOSAIC_NAMES = ("LINEAR", "VNG", "PPG", "AHD", "DCB", "DHT", "AAHD")


@dataclass(frozen=True, eq=False)
class DecodedFrame:
    """A decoded raw frame.

    Attributes:
        rgb: float32 (H, W, 3) linear sRGB decoded values (1.0 = green clip level), (H/2, W/2, 3) rounded
            up for a half-size decode.
        clipped: bool (H, W) (same H, W as ``rgb``), True where any raw site that feeds the pixel was
            saturated: dilated by one pixel for full-size decodes (demosaicing spreads a clipped site to
            its neighbours), the OR over each 2x2 block for half-size decodes.
        black_level: mean of the per-channel black levels, in raw DN.
        white_level: raw saturation level in DN, as the file declares it.
        wb_multipliers: (R, G, B) white-balance multipliers applied, normalised so the smallest is 1.
        camera: "make model" of the camera as the file names it ("unknown" when it does not).
        raw_size: (H, W) of the full-resolution visible raw frame (also for half-size decodes).
        demosaic: the demosaic algorithm name used ("HALF" for half-size decodes, which do not demosaic).
        half_size: whether this is a half-size decode.
    """

    rgb: np.ndarray
    clipped: np.ndarray
    black_level: float
    white_level: int
    wb_multipliers: tuple[float, float, float]
    camera: str
    raw_size: tuple[int, int]
    demosaic: str = "AHD"
    half_size: bool = False


def supported_demosaic() -> tuple[str, ...]:
    """Names of the demosaic algorithms this LibRaw build supports, from the set the pipeline offers."""
    import rawpy

    return tuple(n for n in _DEMOSAIC_NAMES if getattr(rawpy.DemosaicAlgorithm, n).isSupported)


def _demosaic_algorithm(name: str):
    import rawpy

    key = str(name).upper()
    if key not in _DEMOSAIC_NAMES:
        raise ValueError(f"unknown demosaic algorithm {name!r}; choose one of {', '.join(_DEMOSAIC_NAMES)}")
    alg = getattr(rawpy.DemosaicAlgorithm, key)
    if not alg.isSupported:
        raise ValueError(
            f"demosaic algorithm {key} is not supported by this LibRaw build; "
            f"supported: {', '.join(supported_demosaic())}"
        )
    return alg


# --------------------------------------------------------------------------------------------- TIFF header


def _tiff_info(path: Path) -> tuple[int | None, str | None]:
    """(end of the raw data the TIFF header declares, camera name) for TIFF-based raws, else (None, None).

    The raw data is taken as the image (IFD or SubIFD) with the most declared strip/tile bytes. Only the
    header is read. Anything tifffile cannot parse gives (None, None): LibRaw then has the last word.
    """
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError:
        return None, None
    if magic not in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return None, None
    import logging

    log = logging.getLogger("tifffile")
    was_disabled = log.disabled
    log.disabled = True  # a truncated header makes tifffile log an error per tag; the reason we raise says it
    try:
        import tifffile

        best_bytes, best_end, make, model, unique = -1, None, None, None, None
        with tifffile.TiffFile(path) as tif:
            stack = list(tif.pages)
            while stack:
                page = stack.pop()
                if page is None or not hasattr(page, "tags"):
                    continue
                tags = page.tags
                if make is None and 271 in tags:
                    make = str(tags[271].value).strip("\x00 ")
                if model is None and 272 in tags:
                    model = str(tags[272].value).strip("\x00 ")
                if unique is None and 50708 in tags:
                    unique = str(tags[50708].value).strip("\x00 ")
                offsets, counts = page.dataoffsets, page.databytecounts
                if offsets and counts and len(offsets) == len(counts):
                    total = int(sum(counts))
                    if total > best_bytes:
                        best_bytes = total
                        best_end = max(int(o) + int(c) for o, c in zip(offsets, counts))
                stack.extend(p for p in (getattr(page, "pages", None) or []) if p is not None)
        if make and model:
            camera = model if model.lower().startswith(make.lower().split()[0]) else f"{make} {model}"
        else:
            camera = unique or model or make
        return best_end, camera
    except Exception:  # noqa: BLE001 - a header tifffile cannot parse is LibRaw's call
        return None, None
    finally:
        log.disabled = was_disabled


# ------------------------------------------------------------------------------------------------ helpers


def _dilate3(mask: np.ndarray) -> np.ndarray:
    """Binary dilation by a 3x3 square with in-place slice ORs (separable, no temporaries per shift)."""
    out = mask.copy()
    out[1:, :] |= mask[:-1, :]
    out[:-1, :] |= mask[1:, :]
    rows = out.copy()
    out[:, 1:] |= rows[:, :-1]
    out[:, :-1] |= rows[:, 1:]
    return out


def _block_any(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """OR over 2x2 blocks, padded so the result has ``shape`` (= ceil(H/2), ceil(W/2))."""
    h, w = mask.shape
    ph, pw = shape[0] * 2, shape[1] * 2
    if (ph, pw) != (h, w):
        padded = np.zeros((ph, pw), dtype=bool)
        padded[: min(h, ph), : min(w, pw)] = mask[:ph, :pw]
        mask = padded
    return mask.reshape(shape[0], 2, shape[1], 2).any(axis=(1, 3))


def _resize_nearest(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    ri = np.minimum((np.arange(shape[0]) + 0.5) * mask.shape[0] / shape[0], mask.shape[0] - 1).astype(int)
    ci = np.minimum((np.arange(shape[1]) + 0.5) * mask.shape[1] / shape[1], mask.shape[1] - 1).astype(int)
    return mask[np.ix_(ri, ci)]


def _libraw_reason(exc: Exception) -> str:
    import rawpy

    detail = exc.args[0] if exc.args else str(exc)
    if isinstance(detail, bytes):
        detail = detail.decode(errors="replace")
    name = type(exc).__name__
    if isinstance(exc, rawpy.LibRawFileUnsupportedError):
        return f"not a raw file LibRaw can read ({name}: {detail})"
    if isinstance(exc, (rawpy.LibRawIOError, rawpy.LibRawDataError)):
        return f"truncated or corrupt raw data ({name}: {detail})"
    return f"LibRaw failed to decode the file ({name}: {detail})"


def _trailing_zero_rows(raw: np.ndarray) -> int:
    """Number of rows at the bottom that are exactly zero everywhere (what LibRaw leaves for lost data)."""
    n = 0
    step = 16
    h = raw.shape[0]
    # Coarse scan in blocks of rows, then refine: cheap even for large frames.
    while n < h:
        block = raw[max(0, h - n - step) : h - n]
        if not np.any(block):
            n += block.shape[0]
            continue
        nz_rows = np.flatnonzero(block.any(axis=1))
        n += block.shape[0] - 1 - int(nz_rows[-1])
        break
    return n


# ------------------------------------------------------------------------------------------------- decode


def decode_raw(
    path: str | Path,
    demosaic: str = "AHD",
    half_size: bool = False,
    expected_size: tuple[int, int] | None = None,
) -> DecodedFrame:
    """Decode a Bayer raw frame to linear sRGB.

    Args:
        path: raw file (any format LibRaw reads: .dng, .nef, .cr2, ...).
        demosaic: LibRaw demosaic algorithm name: LINEAR, VNG, PPG, AHD, DCB, DHT or AAHD (case-insensitive;
            see :func:`supported_demosaic`). Ignored for half-size decodes.
        half_size: decode each 2x2 CFA block to one pixel (no demosaicing, the two greens averaged):
            about 4x fewer pixels and roughly 10x faster.
        expected_size: (H, W) the full-resolution frame must have (e.g. from rig.json); None skips the check.

    Returns:
        DecodedFrame with ``rgb`` float32 (H, W, 3) (or (ceil(H/2), ceil(W/2), 3)) and ``clipped`` bool of
        the same H, W.

    Raises:
        RawDecodeError: missing, empty, truncated or unreadable file; not a Bayer camera frame; wrong size;
            black frame; saturated frame.
        ValueError: unknown or unsupported demosaic name (a configuration error, not a bad input).
    """
    import rawpy

    path = Path(path)
    alg = _demosaic_algorithm(demosaic)
    camera = _check_file(path) or "unknown"
    try:
        raw_file = rawpy.imread(str(path))
    except rawpy.LibRawError as exc:
        raise RawDecodeError(path, _libraw_reason(exc)) from exc
    except OSError as exc:
        raise RawDecodeError(path, f"cannot read file ({exc})") from exc

    with raw_file as rp:
        raw = _bayer_sites(path, rp, camera)
        raw_h, raw_w = int(raw.shape[0]), int(raw.shape[1])
        if expected_size is not None:
            exp = (int(expected_size[0]), int(expected_size[1]))
            if exp != (raw_h, raw_w):
                raise RawDecodeError(
                    path,
                    f"wrong frame size: {raw_h}x{raw_w} (H x W), expected {exp[0]}x{exp[1]} for this camera",
                )
        black_mean, white, sat_sites = _check_levels(path, rp, raw)
        cam_wb = _white_balance_used(rp)
        img = _postprocess(path, rp, alg, half_size)

    if img.ndim != 3 or img.shape[2] < 3:
        raise RawDecodeError(path, f"LibRaw produced an unexpected image of shape {img.shape}")
    rgb = np.empty(img.shape[:2] + (3,), dtype=np.float32)
    np.multiply(img[..., :3], np.float32(1.0 / 65535.0), out=rgb, casting="unsafe")
    return DecodedFrame(
        rgb=rgb,
        clipped=_clipped_pixels(sat_sites, rgb.shape[:2], half_size),
        black_level=black_mean,
        white_level=white,
        wb_multipliers=(float(cam_wb[0]), float(cam_wb[1]), float(cam_wb[2])),
        camera=camera,
        raw_size=(raw_h, raw_w),
        demosaic="HALF" if half_size else alg.name,
        half_size=bool(half_size),
    )


def _check_file(path: Path) -> str | None:
    """Refuse a missing, empty or (by its TIFF header) truncated file; returns the camera its TIFF header
    names, if any."""
    if not path.exists():
        raise RawDecodeError(path, "missing file: no such raw file")
    if not path.is_file():
        raise RawDecodeError(path, "not a regular file")
    size = os.path.getsize(path)
    if size == 0:
        raise RawDecodeError(path, "empty file (0 bytes)")
    declared_end, camera = _tiff_info(path)
    if declared_end is not None and declared_end > size:
        raise RawDecodeError(
            path,
            f"truncated file: {size} bytes, but its TIFF header declares raw data up to byte {declared_end} "
            f"({100.0 * size / declared_end:.0f}% present)",
        )
    return camera


def _bayer_sites(path: Path, rp, camera: str) -> np.ndarray:
    """The visible sensor sites (H, W) of an opened raw file; refuses anything but a 2x2 RGB Bayer frame."""
    import rawpy

    try:
        raw = rp.raw_image_visible
        pattern = rp.raw_pattern
        raw_type = rp.raw_type
        num_colors = rp.num_colors
    except rawpy.LibRawError as exc:
        raise RawDecodeError(path, _libraw_reason(exc)) from exc
    desc = rp.color_desc.decode(errors="replace") if isinstance(rp.color_desc, bytes) else str(rp.color_desc)
    if pattern is None or raw.ndim != 2 or raw_type != rawpy.RawType.Flat:
        chans = raw.shape[2] if raw.ndim == 3 else 1
        raise RawDecodeError(
            path,
            f"not a Bayer light-stage camera frame: LibRaw reports a {chans}-channel "
            f"{getattr(raw_type, 'name', raw_type)} image without a colour filter array pattern "
            f"({camera}; e.g. a film scanner or a linear/demosaiced DNG)",
        )
    cfa_colours = {int(v) for v in np.unique(pattern)}
    if pattern.shape != (2, 2) or num_colors != 3 or cfa_colours not in ({0, 1, 2}, {0, 1, 2, 3}):
        raise RawDecodeError(
            path,
            f"not a Bayer light-stage camera frame: CFA pattern {pattern.tolist()} with {num_colors} "
            f"colours ({desc}), only 2x2 RGB Bayer sensors are supported ({camera})",
        )
    return raw


def _check_levels(path: Path, rp, raw: np.ndarray) -> tuple[float, int, np.ndarray]:
    """Black and white levels and the saturated sites (H, W) bool of the sensor sites ``raw`` (H, W); refuses
    invalid levels, zero-filled (truncated) data, a saturated frame and a black one. Returns
    ``(mean black level, white level, saturated sites)``."""
    raw_h, raw_w = int(raw.shape[0]), int(raw.shape[1])
    blacks = np.asarray(rp.black_level_per_channel, dtype=np.float64)
    white = int(rp.white_level)
    black_max = float(blacks.max())
    span = float(white) - black_max
    if span <= 0:
        raise RawDecodeError(path, f"invalid levels: white level {white} <= black level {black_max:g}")
    clip_at = white - max(1.0, CLIP_MARGIN * span)
    sat_sites = raw >= clip_at

    tz = _trailing_zero_rows(raw)
    if 0 < tz < raw_h:
        above = raw[: raw_h - tz]
        if black_max > 0 or np.count_nonzero(above[-1]) > 0.5 * raw_w:
            raise RawDecodeError(
                path,
                f"truncated or corrupt raw data: the bottom {tz} of {raw_h} rows are all zero "
                f"(LibRaw fills missing data with zeros)",
            )

    sat_frac = float(np.count_nonzero(sat_sites)) / sat_sites.size
    if sat_frac > SATURATED_FRAME_FRACTION:
        raise RawDecodeError(
            path,
            f"saturated frame: {100 * sat_frac:.1f}% of sensor sites are clipped "
            f"(>= {clip_at:.0f} DN of white level {white}); reduce exposure",
        )
    # Subsample with odd strides so every CFA colour is represented; percentile on <= ~1M sites.
    stride = max(1, int(np.sqrt(raw.size / 1.0e6)))
    stride += 1 - stride % 2
    sub = raw[::stride, ::stride].astype(np.float32)
    colors = rp.raw_colors_visible[::stride, ::stride]
    sub -= blacks.astype(np.float32)[np.clip(colors, 0, len(blacks) - 1)]
    p999 = float(np.percentile(sub, 99.9)) / span
    if p999 < BLACK_FRAME_LEVEL:
        raise RawDecodeError(
            path,
            f"black frame: essentially no signal above the black level (99.9th percentile at "
            f"{100 * p999:.3f}% of the range, threshold {100 * BLACK_FRAME_LEVEL:.1f}%); "
            f"lights off or lens capped?",
        )
    return float(blacks.mean()), white, sat_sites


def _white_balance_used(rp) -> np.ndarray:
    """The white balance LibRaw applies (as shot, falling back to daylight, then none), scaled so that its
    smallest multiplier is 1: (3,) R, G, B."""
    cam_wb = np.asarray(rp.camera_whitebalance, dtype=np.float64)[:3]
    if not (np.all(np.isfinite(cam_wb)) and np.all(cam_wb > 0)):
        cam_wb = np.asarray(rp.daylight_whitebalance, dtype=np.float64)[:3]
    if not (np.all(np.isfinite(cam_wb)) and np.all(cam_wb > 0)):
        cam_wb = np.ones(3)
    return cam_wb / cam_wb.min()


def _postprocess(path: Path, rp, alg, half_size: bool) -> np.ndarray:
    """LibRaw's linear 16-bit sRGB image (H, W, C) of the opened file: camera white balance, no gamma, no
    brightening, highlights clipped, 1.0 at the declared white level."""
    import rawpy

    try:
        return rp.postprocess(
            demosaic_algorithm=alg,
            half_size=bool(half_size),
            use_camera_wb=True,
            use_auto_wb=False,
            output_color=rawpy.ColorSpace.sRGB,
            output_bps=16,
            gamma=(1.0, 1.0),
            no_auto_bright=True,
            bright=1.0,
            user_flip=0,
            adjust_maximum_thr=0.0,  # keep 1.0 = declared white level, never the data maximum
            highlight_mode=rawpy.HighlightMode.Clip,
            median_filter_passes=0,
        )
    except rawpy.LibRawError as exc:
        raise RawDecodeError(path, _libraw_reason(exc)) from exc


def _clipped_pixels(sat_sites: np.ndarray, out_hw: tuple[int, int], half_size: bool) -> np.ndarray:
    """Output pixels (out_hw) bool that a saturated sensor site (H, W) touches: the 2x2 block of a half-size
    pixel, the 3x3 demosaic neighbourhood of a full-size one."""
    raw_h, raw_w = sat_sites.shape
    if half_size:
        clipped = _block_any(sat_sites, out_hw) if out_hw == ((raw_h + 1) // 2, (raw_w + 1) // 2) else None
    else:
        clipped = _dilate3(sat_sites) if out_hw == (raw_h, raw_w) else None
    if clipped is None:  # pixel-aspect stretch or a rotated sensor layout: map sites by position
        clipped = _resize_nearest(_dilate3(sat_sites), out_hw)
    return clipped
