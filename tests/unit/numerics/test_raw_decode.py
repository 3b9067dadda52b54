"""decode_raw: linearisation conventions, clipped masks, specific errors, real raws from ../shared."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

tifffile = pytest.importorskip("tifffile")
rawpy = pytest.importorskip("rawpy")

from pipeline.codecs.raw import DecodedFrame, decode_raw, supported_demosaic  # noqa: E402
from pipeline.errors import InputError, RawDecodeError  # noqa: E402

SHARED = Path(__file__).resolve().parents[3].parent / "shared" / "data"
RAW_DIR = SHARED / "raw"

# linear sRGB (D65) -> XYZ
XYZ_FROM_SRGB = np.array(
    [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]]
)
# A Nikon D750-like ColorMatrix (camera from XYZ, D65), rounded to the DNG's 1/10000 rationals.
CAM_FROM_XYZ = np.round(
    np.array([[0.7171, -0.1986, -0.0648], [-0.4885, 1.2465, 0.2631], [-0.0999, 0.1755, 0.7023]]) * 1e4
) / 1e4
NEUTRAL = (0.5, 1.0, 0.6)  # AsShotNeutral: camera RGB of a white surface; WB multipliers 2, 1, 1.667
BLACK, WHITE = 600, 16383


def _srat(m):
    return [x for v in np.ravel(m) for x in (int(round(v * 10000)), 10000)]


def write_test_dng(path, raw_uint16, black=BLACK, white=WHITE, cam_from_xyz=CAM_FROM_XYZ, neutral=NEUTRAL):
    """Uncompressed 16-bit RGGB CFA DNG (the recipe that LibRaw decodes exactly)."""
    extratags = [
        (33421, "H", 2, (2, 2), True),
        (33422, "B", 4, (0, 1, 1, 2), True),
        (50706, "B", 4, (1, 4, 0, 0), True),
        (50707, "B", 4, (1, 1, 0, 0), True),
        (50708, "s", 0, "UltraStage Simulated D750", True),
        (50714, "I", 1, int(black), True),
        (50717, "I", 1, int(white), True),
        (50721, "2i", 9, _srat(cam_from_xyz), True),
        (50728, "2I", 3, [x for v in neutral for x in (int(round(v * 10000)), 10000)], True),
        (50778, "H", 1, 21, True),
        (271, "s", 0, "UltraStage", True),
        (272, "s", 0, "SimD750", True),
    ]
    tifffile.imwrite(
        path, np.asarray(raw_uint16, dtype=np.uint16), photometric=32803, extratags=extratags,
        subfiletype=0, compression=None, metadata=None,
    )
    return Path(path)


def mosaic_linear_srgb(rgb, black=BLACK, white=WHITE, cam_from_xyz=CAM_FROM_XYZ, neutral=NEUTRAL):
    """Invert LibRaw's pipeline: linear sRGB (H, W, 3) -> RGGB raw DN (H, W) uint16 that decodes back to it."""
    cam_rgb = cam_from_xyz @ XYZ_FROM_SRGB
    cam_rgb = cam_rgb / cam_rgb.sum(axis=1, keepdims=True)  # LibRaw normalises rows: white -> (1, 1, 1)
    neutral = np.asarray(neutral, dtype=np.float64)
    cam = np.asarray(rgb, dtype=np.float64) @ cam_rgb.T * (neutral / neutral.max())
    h, w = cam.shape[:2]
    cfa = np.array([[0, 1], [1, 2]])
    yy, xx = np.indices((h, w))
    site = np.take_along_axis(cam, cfa[yy % 2, xx % 2][..., None], axis=2)[..., 0]
    return np.clip(np.round(site * (white - black) + black), 0, 65535).astype(np.uint16)


def _flat_raw(h, w, green_level, neutral=NEUTRAL):
    """Raw of a neutral surface whose normalised green is ``green_level``."""
    return mosaic_linear_srgb(np.full((h, w, 3), green_level), neutral=neutral)


# ------------------------------------------------------------------------------------------- conventions


@pytest.mark.parametrize("alg", ["LINEAR", "AHD"])
def test_neutral_patch_decodes_to_green_level(tmp_path, alg):
    path = write_test_dng(tmp_path / "n.dng", _flat_raw(32, 48, 0.4))
    frame = decode_raw(path, demosaic=alg)
    assert isinstance(frame, DecodedFrame)
    assert frame.rgb.dtype == np.float32 and frame.rgb.shape == (32, 48, 3)
    assert frame.clipped.dtype == bool and frame.clipped.shape == (32, 48)
    np.testing.assert_allclose(frame.rgb[4:-4, 4:-4], 0.4, atol=1e-3)
    assert not frame.clipped.any()
    assert frame.black_level == BLACK and frame.white_level == WHITE
    np.testing.assert_allclose(frame.wb_multipliers, (2.0, 1.0, 1.0 / 0.6), rtol=1e-4)
    assert frame.camera == "UltraStage SimD750"
    assert frame.raw_size == (32, 48)


def test_all_supported_algorithms_and_half_size(tmp_path):
    path = write_test_dng(tmp_path / "n.dng", _flat_raw(32, 32, 0.25))
    assert set(supported_demosaic()) >= {"LINEAR", "AHD"}
    for alg in supported_demosaic():
        np.testing.assert_allclose(decode_raw(path, demosaic=alg.lower()).rgb[4:-4, 4:-4], 0.25, atol=1e-3)
    half = decode_raw(path, half_size=True)
    assert half.rgb.shape == (16, 16, 3) and half.clipped.shape == (16, 16)
    assert half.raw_size == (32, 32) and half.half_size
    np.testing.assert_allclose(half.rgb, 0.25, atol=1e-3)


def test_colour_pipeline_is_camera_to_linear_srgb(tmp_path):
    colours = np.array([[0.3, 0.2, 0.1], [0.05, 0.4, 0.1], [0.1, 0.15, 0.6], [0.8, 0.8, 0.8]])
    img = np.repeat(np.repeat(colours[None], 32, axis=0), 16, axis=1)  # (32, 64, 3) four patches
    path = write_test_dng(tmp_path / "c.dng", mosaic_linear_srgb(img))
    rgb = decode_raw(path, demosaic="LINEAR").rgb
    for i, c in enumerate(colours):
        np.testing.assert_allclose(rgb[8:24, 16 * i + 4 : 16 * i + 12].mean(axis=(0, 1)), c, atol=2e-3)


def test_clipped_mask_dilated_and_half_size_blocks(tmp_path):
    raw = _flat_raw(32, 32, 0.3)
    raw[6, 9] = WHITE  # one saturated blue site
    path = write_test_dng(tmp_path / "s.dng", raw)
    clipped = decode_raw(path).clipped
    expect = np.zeros((32, 32), bool)
    expect[5:8, 8:11] = True
    np.testing.assert_array_equal(clipped, expect)
    half = decode_raw(path, half_size=True).clipped
    expect_h = np.zeros((16, 16), bool)
    expect_h[3, 4] = True
    np.testing.assert_array_equal(half, expect_h)


# ------------------------------------------------------------------------------------------------ errors


def _reason(excinfo) -> str:
    assert isinstance(excinfo.value, InputError)
    return excinfo.value.reason


def test_missing_and_empty(tmp_path):
    with pytest.raises(RawDecodeError) as ei:
        decode_raw(tmp_path / "nope.dng")
    assert "missing" in _reason(ei) and "nope.dng" in str(ei.value)
    (tmp_path / "empty.dng").write_bytes(b"")
    with pytest.raises(RawDecodeError) as ei:
        decode_raw(tmp_path / "empty.dng")
    assert "empty" in _reason(ei)


def test_tiny_frame_is_not_a_raw_file(tmp_path):
    # LibRaw refuses frames under 22 pixels on a side: the reason says LibRaw cannot read it.
    with pytest.raises(RawDecodeError) as ei:
        decode_raw(write_test_dng(tmp_path / "tiny.dng", _flat_raw(16, 16, 0.3)))
    assert "LibRaw can read" in _reason(ei)


def test_not_a_raw_file(tmp_path):
    (tmp_path / "junk.nef").write_bytes(b"this is not a raw file " * 200)
    with pytest.raises(RawDecodeError) as ei:
        decode_raw(tmp_path / "junk.nef")
    assert "not a raw file LibRaw can read" in _reason(ei)


def test_truncated_dng(tmp_path):
    path = write_test_dng(tmp_path / "t.dng", _flat_raw(64, 96, 0.3))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(RawDecodeError) as ei:
        decode_raw(path)
    assert "truncated" in _reason(ei)


def test_zero_filled_bottom_rows_are_truncation(tmp_path):
    raw = _flat_raw(64, 32, 0.3)
    raw[-10:] = 0  # what LibRaw leaves where compressed data ran out (black level is 600, never 0)
    with pytest.raises(RawDecodeError) as ei:
        decode_raw(write_test_dng(tmp_path / "z.dng", raw))
    assert "truncated" in _reason(ei) and "10 of 64 rows" in _reason(ei)


def test_wrong_size(tmp_path):
    path = write_test_dng(tmp_path / "n.dng", _flat_raw(32, 48, 0.3))
    assert decode_raw(path, expected_size=(32, 48)).raw_size == (32, 48)
    with pytest.raises(RawDecodeError) as ei:
        decode_raw(path, expected_size=(480, 320))
    assert "wrong frame size" in _reason(ei) and "32x48" in _reason(ei) and "480x320" in _reason(ei)


def test_black_frame(tmp_path):
    rng = np.random.default_rng(0)
    raw = (BLACK + rng.normal(0, 3, (32, 32))).astype(np.uint16)  # read noise only
    with pytest.raises(RawDecodeError) as ei:
        decode_raw(write_test_dng(tmp_path / "b.dng", raw))
    assert "black frame" in _reason(ei)
    dim = _flat_raw(32, 32, 0.01)  # dim but real signal is fine
    assert decode_raw(write_test_dng(tmp_path / "d.dng", dim)).rgb.mean() > 0.005


def test_saturated_frame(tmp_path):
    raw = np.full((32, 32), WHITE, np.uint16)
    raw[:8] = _flat_raw(8, 32, 0.3)
    with pytest.raises(RawDecodeError) as ei:
        decode_raw(write_test_dng(tmp_path / "s.dng", raw))
    assert "saturated frame" in _reason(ei) and "75.0%" in _reason(ei)


def test_unknown_demosaic_is_a_config_error(tmp_path):
    path = write_test_dng(tmp_path / "n.dng", _flat_raw(32, 32, 0.3))
    with pytest.raises(ValueError, match="unknown demosaic"):
        decode_raw(path, demosaic="MAGIC")


# ------------------------------------------------------------------------------------------ real raws

needs_shared = pytest.mark.skipif(
    not RAW_DIR.is_dir(), reason=f"shared test data not found at {RAW_DIR} (real raws live outside the repo)"
)


@pytest.mark.shared
@needs_shared
def test_real_blackmagic_dng():
    frame = decode_raw(RAW_DIR / "Blackmagic_PocketCinema4K.dng", half_size=True, expected_size=(2176, 4128))
    assert frame.raw_size == (2176, 4128) and frame.rgb.shape == (1088, 2064, 3)
    assert frame.black_level == 512 and frame.white_level == 65535
    assert "Blackmagic" in frame.camera
    assert np.isfinite(frame.rgb).all() and 0.02 < float(frame.rgb.mean()) < 0.9
    assert frame.clipped.mean() < 0.01
    full = decode_raw(RAW_DIR / "Blackmagic_PocketCinema4K.dng", demosaic="LINEAR")
    assert full.rgb.shape == (2176, 4128, 3) and full.clipped.shape == (2176, 4128)
    # half-size and full-size agree on the mean level (same linearisation)
    np.testing.assert_allclose(
        full.rgb.mean(axis=(0, 1), dtype=np.float64), frame.rgb.mean(axis=(0, 1), dtype=np.float64), rtol=0.01
    )


@pytest.mark.shared
@needs_shared
def test_real_kodak_kdc():
    frame = decode_raw(RAW_DIR / "Kodak_DC50.kdc")
    assert frame.rgb.shape == (512, 768, 3) and "Kodak" in frame.camera
    assert np.isfinite(frame.rgb).all() and frame.rgb.mean() > 0.05


@pytest.mark.shared
@needs_shared
def test_real_coolscan_nef_is_not_a_camera_frame():
    with pytest.raises(RawDecodeError) as ei:
        decode_raw(RAW_DIR / "Nikon_COOLSCAN_uncompressed.nef")
    assert "not a Bayer light-stage camera frame" in _reason(ei) and "COOLSCAN" in _reason(ei)


@pytest.mark.shared
@needs_shared
def test_real_dng_truncated(tmp_path):
    data = (RAW_DIR / "Blackmagic_PocketCinema4K.dng").read_bytes()
    cut = tmp_path / "cut.dng"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    with pytest.raises(RawDecodeError) as ei:
        decode_raw(cut)
    assert "truncated" in _reason(ei)
