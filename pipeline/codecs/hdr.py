"""Environment maps: Radiance RGBE (.hdr / .pic) and OpenEXR (.exr) as linear float32 RGB.

``read_environment(path)`` is the one entry point relighting uses; it returns the map as stored (for an
equirectangular map: row 0 is the top, +y; see ``stages.numerics.sg`` for the direction convention).

Nothing installed here reads Radiance files (imageio has no HDR backend without OpenCV or FreeImage, and
OpenCV is not a dependency), so :func:`read_radiance_hdr` is a small numpy reader of the format as
written by Radiance, Photoshop and Poly Haven: text header, resolution line, then either new-style
run-length-encoded scanlines (``2 2 hi lo`` marker, four separately RLE-coded byte planes) or flat RGBE
pixels. Old-style (``1 1 1 n``) run markers, never written by current tools, are refused.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import InputError

__all__ = ["read_environment", "read_radiance_hdr"]

_MAGICS = (b"#?RADIANCE", b"#?RGBE")


def read_environment(path: str | Path) -> np.ndarray:
    """Read an HDR environment map as float32 (H, W, 3) linear RGB.

    Args:
        path: a Radiance ``.hdr`` / ``.pic`` file or an OpenEXR ``.exr`` file (its R, G, B channels; a
            one-channel Y map is repeated into grey RGB).

    Returns:
        float32 (H, W, 3), finite and non-negative (negative EXR values, which are out of gamut, are
        clipped to 0).

    Raises:
        InputError: unknown extension, unreadable, truncated or non-finite data.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".hdr", ".pic", ".rgbe"):
        env = read_radiance_hdr(path)
    elif suffix == ".exr":
        from pipeline.codecs.exr import read_exr

        try:
            env = read_exr(path)
        except Exception as error:  # OpenEXR raises plain exceptions for corrupt files
            raise InputError(path, f"cannot read EXR environment: {error}") from error
        if env.ndim == 2:
            env = np.repeat(env[:, :, None], 3, axis=2)
        elif env.shape[2] == 4:  # RGBA: the alpha of an environment means nothing for lighting
            env = env[:, :, :3]
        elif env.shape[2] != 3:
            raise InputError(path, f"expected an RGB(A) or Y EXR, got {env.shape[2]} channels")
        if not np.all(np.isfinite(env)):
            raise InputError(path, "environment map holds NaN or Inf")
        env = np.maximum(env, 0.0).astype(np.float32)
    else:
        raise InputError(path, f"unknown environment map format {suffix!r} (expected .hdr or .exr)")
    if env.shape[0] < 1 or env.shape[1] < 1:
        raise InputError(path, "empty environment map")
    return np.ascontiguousarray(env, dtype=np.float32)


def _parse_header(data: bytes, path: Path) -> tuple[int, tuple[int, int], tuple[bool, bool, bool], float]:
    """Offset of the pixel data, (H, W), (transpose, flip_rows, flip_cols) and the EXPOSURE product."""
    if not data.startswith(_MAGICS):
        raise InputError(path, "not a Radiance HDR file (no #?RADIANCE / #?RGBE magic)")
    pos = 0
    exposure = 1.0
    while True:  # header lines up to an empty line
        end = data.find(b"\n", pos)
        if end < 0:
            raise InputError(path, "truncated Radiance header")
        line = data[pos:end].strip()
        pos = end + 1
        if not line:
            break
        if line.startswith(b"FORMAT=") and line[7:] not in (b"32-bit_rle_rgbe",):
            raise InputError(path, f"unsupported Radiance pixel format {line[7:].decode(errors='replace')!r} "
                                   "(only 32-bit_rle_rgbe)")
        if line.startswith(b"EXPOSURE="):
            try:
                exposure *= float(line[9:])
            except ValueError as error:
                raise InputError(path, f"bad EXPOSURE line {line!r}") from error
    end = data.find(b"\n", pos)
    if end < 0:
        raise InputError(path, "missing Radiance resolution line")
    resolution = data[pos:end]
    tokens = resolution.split()
    pos = end + 1
    axes = (b"-Y", b"+Y", b"-X", b"+X")
    if len(tokens) != 4 or tokens[0] not in axes or tokens[2] not in axes or tokens[0][1:] == tokens[2][1:]:
        raise InputError(path, f"bad Radiance resolution line {resolution!r}")
    try:
        n_major, n_minor = int(tokens[1]), int(tokens[3])
    except ValueError as error:
        raise InputError(path, "bad Radiance resolution line") from error
    if n_major < 1 or n_minor < 1 or n_major * n_minor > (1 << 28):
        raise InputError(path, f"implausible Radiance image size {n_major} x {n_minor}")
    # The standard "-Y H +X W" stores rows top to bottom, pixels left to right. The first axis letter is
    # the one that varies slowest (scanlines); '+Y' scanlines run bottom to top, '-X' pixels right to left.
    transpose = tokens[0][1:2] == b"X"
    y_token, x_token = (tokens[2], tokens[0]) if transpose else (tokens[0], tokens[2])
    flip_rows, flip_cols = y_token == b"+Y", x_token == b"-X"
    return pos, (n_major, n_minor), (transpose, flip_rows, flip_cols), exposure


def _decode_scanlines(buf: np.ndarray, n_lines: int, width: int, path: Path) -> np.ndarray:
    """(n_lines, width, 4) uint8 RGBE from the pixel bytes (new-style RLE or flat)."""
    out = np.empty((n_lines, width, 4), np.uint8)
    rle = 8 <= width < 32768 and len(buf) >= 4 and buf[0] == 2 and buf[1] == 2 and not (buf[2] & 0x80)
    if not rle:  # flat RGBE (also what writers emit for widths outside the RLE range)
        need = n_lines * width * 4
        if len(buf) < need:
            raise InputError(path, f"truncated Radiance pixel data ({len(buf)} of {need} bytes)")
        flat = buf[:need].reshape(n_lines, width, 4)
        if np.any(np.all(flat[:, :, :3] == 1, axis=2)):
            raise InputError(path, "old-style Radiance run-length encoding is not supported")
        out[:] = flat
        return out
    data = buf.tobytes()  # bytes indexing is much faster than numpy scalar indexing in the loop below
    pos, size = 0, len(data)
    plane = bytearray(width)
    for line in range(n_lines):
        if pos + 4 > size:
            raise InputError(path, f"truncated Radiance data at scanline {line}")
        if data[pos] != 2 or data[pos + 1] != 2 or ((data[pos + 2] << 8) | data[pos + 3]) != width:
            raise InputError(path, f"bad run-length scanline header at scanline {line}")
        pos += 4
        for channel in range(4):
            x = 0
            while x < width:
                if pos >= size:
                    raise InputError(path, f"truncated Radiance data at scanline {line}")
                count = data[pos]
                pos += 1
                if count > 128:  # a run: one byte repeated count - 128 times
                    count -= 128
                    if x + count > width or pos >= size:
                        raise InputError(path, f"bad run length at scanline {line}")
                    plane[x:x + count] = bytes((data[pos],)) * count
                    pos += 1
                else:  # a literal dump of count bytes
                    if count == 0 or x + count > width or pos + count > size:
                        raise InputError(path, f"bad dump length at scanline {line}")
                    plane[x:x + count] = data[pos:pos + count]
                    pos += count
                x += count
            out[line, :, channel] = np.frombuffer(plane, np.uint8)
    return out


def read_radiance_hdr(path: str | Path) -> np.ndarray:
    """Read a Radiance RGBE file as float32 (H, W, 3) linear RGB (row 0 at the top).

    Pixels decode as ``(m + 0.5) * 2**(e - 136)`` (Radiance's own ``colr_color``; ``e = 0`` is black), then
    are divided by the header's EXPOSURE product so values are the radiance before any exposure change.

    Raises:
        InputError: not a Radiance file, unsupported format, truncated or corrupt data.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise InputError(path, f"cannot read: {error}") from error
    offset, (n_lines, width), (transpose, flip_rows, flip_cols), exposure = _parse_header(data, path)
    rgbe = _decode_scanlines(np.frombuffer(data, np.uint8, offset=offset), n_lines, width, path)
    mantissa = rgbe[:, :, :3].astype(np.float32) + np.float32(0.5)
    exponent = rgbe[:, :, 3].astype(np.int32)
    scale = np.where(exponent > 0, np.ldexp(np.float32(1.0), exponent - 136), 0.0).astype(np.float32)
    rgb = mantissa * scale[:, :, None]
    if transpose:
        rgb = rgb.transpose(1, 0, 2)
    if flip_rows:
        rgb = rgb[::-1]
    if flip_cols:
        rgb = rgb[:, ::-1]
    if exposure > 0 and exposure != 1.0:
        rgb = rgb / np.float32(exposure)
    if not np.all(np.isfinite(rgb)):
        raise InputError(path, "decoded values are not finite")
    return np.ascontiguousarray(rgb, dtype=np.float32)
