"""Bad inputs, as a new user would make them (issue 23): what each one does to a run.

Every case runs a tiny simulated capture (2 actions, 3 cameras, 48 px) through the photometric-only DAG
with the fault put into action A0001; A0000 is the bystander that must still be published. "Fails" means:
A0001's status is 'failed' with an error naming the file and the reason (in ``actions.parquet`` and on the
frame at fault in ``frames.parquet``), A0000 is published, and nothing of A0001 is in the release (no
folder, no asset rows).

| Bad input                                   | What happens                                                        |
|---------------------------------------------|---------------------------------------------------------------------|
| empty raw file (0 bytes)                    | fails: `<file>: empty file (0 bytes)`                               |
| truncated raw file                          | fails: `<file>: truncated file: N bytes, but its TIFF header ...`   |
| corrupt raw file (header overwritten)       | fails: `<file>: not a raw file LibRaw can read` / `corrupt ...`     |
| wrong format (a PNG named .dng)             | fails: `<file>: not a raw file LibRaw can read ...`                 |
| missing camera (no file in any illumination)| fails: `<folder>/<cam>.*: camera <cam> has no raw file for '...'`   |
| duplicate frame, two files for one camera   | fails: `<file>: camera <cam> has 2 raw files ...: a duplicate frame`|
| duplicate frame, one file under two names   | fails: `<file>: the same bytes as <file>: one frame delivered twice`|
| missing illumination (no `neg/` folder)     | fails: `<folder>: illumination 'neg' is missing (no folder)`        |
| all-black frame                             | fails: `<file>: black frame: essentially no signal ...`             |
| all-saturated frame                         | fails: `<file>: saturated frame: N% of sensor sites are clipped`    |
| g+ and g- swapped (one camera)              | fails: `<pos file>: g+ and g- frames of camera <cam> look swapped`  |
| stray raw file for a camera not in the rig  | fails: `<folder>: 1 raw file(s) for cameras not in the rig: [...]`  |
| stray non-raw files (notes, sidecars, dirs) | ignored: the action is published as without them                   |
| non-finite values in an intermediate map    | degrades: those pixels get normal 0 and alpha 0; maps stay finite   |
| config: unknown key                         | refused: `<config file>.<section>: unknown key(s) [...]`            |
| config: impossible value (ratio_min > max)  | refused, each: `<config file>.<section>.<key> = <value>: <rule>`    |
| config: wrong type / NaN                    | refused: `<config file>.<key>: expected a (finite) number, got ...` |

Before issue 23's work, the duplicate frames were taken silently (the first file by name; the byte-identical
copy decoded as if it were the other view), the swapped pair was published with every normal flipped, and
the impossible, NaN and negative config values were accepted (or, for `__post_init__` checks, refused
without naming the file). Not detected: pixel data overwritten inside a well-formed file (raw formats carry
no checksum the capture writes; the photometric alpha rejects what no longer looks like a gradient pair).
"""
from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import ConfigError
from pipeline.runner import ExecutionConfig
from stages.registry import PRESETS, build_stages
from ultrastage.run import run_pipeline
from tests.integration.conftest import TINY_CAMERAS as CAMERAS

SYNC = ExecutionConfig(scheduler="sync")


@pytest.fixture(scope="module")
def clean(tiny_capture: Path) -> Path:
    return tiny_capture


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One artifact store for the cases: the session stages and A0000 run once and are cached after."""
    return tmp_path_factory.mktemp("badin-work")


def _run(capture: Path, release: Path, work: Path):
    config = PRESETS["test"]
    return run_pipeline(capture, release, work, build_stages(config, through="photometric"), config, SYNC,
                        echo=lambda line: None)


def _frame(capture: Path, illum: str, cam: str) -> Path:
    return capture / "actions" / "A0001" / illum / f"{cam}.dng"


def _rewrite_dng(path: Path, value: Callable[[np.ndarray], np.ndarray]) -> None:
    import rawpy

    from synthetic.files import write_dng
    from synthetic.sensor import as_shot_neutral, nikon_cam_from_xyz

    with rawpy.imread(str(path)) as raw:
        data = raw.raw_image_visible.copy()
    write_dng(path, value(data).astype(np.uint16), nikon_cam_from_xyz(), as_shot_neutral())


def _black(capture: Path) -> Path:
    from synthetic.sensor import BLACK_LEVEL

    path = _frame(capture, "full_on", "00001")
    _rewrite_dng(path, lambda raw: np.full_like(raw, BLACK_LEVEL))
    return path


def _saturated(capture: Path) -> Path:
    from synthetic.sensor import WHITE_LEVEL

    path = _frame(capture, "pos", "00002")
    _rewrite_dng(path, lambda raw: np.full_like(raw, WHITE_LEVEL))
    return path


def _empty(capture: Path) -> Path:
    path = _frame(capture, "pos", "00001")
    path.write_bytes(b"")
    return path


def _truncated(capture: Path) -> Path:
    path = _frame(capture, "neg", "00001")
    path.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    return path


def _corrupt(capture: Path) -> Path:
    path = _frame(capture, "full_on", "00002")
    data = bytearray(path.read_bytes())
    data[4:1024] = np.random.default_rng(0).integers(0, 256, 1020, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))
    return path


def _wrong_format(capture: Path) -> Path:
    from pipeline.codecs.image import write_png

    path = _frame(capture, "pos", "00000")
    png = write_png(capture / "tmp.png", np.zeros((48, 48, 3), np.uint8))
    shutil.move(png, path)
    return path


def _missing_camera(capture: Path) -> Path:
    for illum in ("full_on", "pos", "neg"):
        _frame(capture, illum, "00002").unlink()
    return capture / "actions" / "A0001" / "full_on" / "00002.*"


def _two_files(capture: Path) -> Path:
    path = _frame(capture, "neg", "00000")
    shutil.copy(path, path.with_suffix(".DNG"))
    return path.with_suffix(".dng")  # the second by name ('.DNG' sorts first)


def _same_bytes(capture: Path) -> Path:
    shutil.copy(_frame(capture, "pos", "00001"), _frame(capture, "pos", "00002"))  # camera 1's frame as camera 2's
    return _frame(capture, "pos", "00002")


def _missing_illumination(capture: Path) -> Path:
    shutil.rmtree(capture / "actions" / "A0001" / "neg")
    return capture / "actions" / "A0001" / "neg"


def _swapped(capture: Path) -> Path:
    pos, neg = _frame(capture, "pos", "00001"), _frame(capture, "neg", "00001")
    tmp = pos.with_name("swap.tmp")
    pos.rename(tmp)
    neg.rename(pos)
    tmp.rename(neg)
    return pos


def _stray_raw(capture: Path) -> Path:
    shutil.copy(_frame(capture, "full_on", "00001"), capture / "actions" / "A0001" / "full_on" / "00001 (1).dng")
    return capture / "actions" / "A0001" / "full_on"


FAILS = {
    "empty": (_empty, "empty file (0 bytes)"),
    "truncated": (_truncated, "truncated file"),
    "corrupt": (_corrupt, "LibRaw"),
    "wrong_format": (_wrong_format, "not a raw file LibRaw can read"),
    "missing_camera": (_missing_camera, "camera 00002 has no raw file for 'full_on'"),
    "duplicate_two_files": (_two_files, "camera 00000 has 2 raw files for 'neg'"),
    "duplicate_same_bytes": (_same_bytes, "one frame delivered twice"),
    "missing_illumination": (_missing_illumination, "illumination 'neg' is missing"),
    "black": (_black, "black frame"),
    "saturated": (_saturated, "saturated frame"),
    "swapped": (_swapped, "g+ and g- frames of camera 00001 look swapped"),
    "stray_raw_file": (_stray_raw, "raw file(s) for cameras not in the rig"),
}


@pytest.mark.parametrize("case", sorted(FAILS))
def test_bad_input_fails_its_action_only_and_names_the_file(case, clean, store, tmp_path):
    from manifests import open_release

    capture = tmp_path / "capture"
    shutil.copytree(clean, capture)
    mutate, reason = FAILS[case]
    culprit = mutate(capture)
    release = tmp_path / "release"
    result = _run(capture, release, store)
    assert result.action_status == {"A0000": "ok", "A0001": "failed"}, result.action_errors
    error = result.action_errors["A0001"]
    assert str(culprit) in error and reason in error, error
    # nothing of the failed action reaches the release; the bystander is complete
    assert not (release / "actions" / "A0001").exists()
    assert sorted(p.stem for p in (release / "actions" / "A0000" / "normal_alpha").glob("*.exr")) == list(CAMERAS)
    rel = open_release(release)
    recorded = rel.actions.set_index("action_id").loc["A0001", "error"]
    assert culprit.name in recorded and reason in recorded, recorded
    assert not (rel.assets.action_id == "A0001").any()
    frames = rel.frames[rel.frames.action_id == "A0001"].set_index("raw_path")
    at_fault = culprit.relative_to(capture).as_posix()
    if at_fault in frames.index:  # the frame at fault, when it is one, is marked failed with the reason
        assert frames.loc[at_fault, "status"] == "failed" and reason in frames.loc[at_fault, "error"]
    else:  # a missing frame or a folder-level problem: the action's error names it (above)
        assert case in ("missing_camera", "missing_illumination", "duplicate_two_files", "stray_raw_file")


def test_stray_non_raw_files_are_ignored(clean, store, tmp_path):
    capture = tmp_path / "capture"
    shutil.copytree(clean, capture)
    action = capture / "actions" / "A0001"
    (capture / "README.txt").write_text("notes from the shoot")
    (action / "pos" / ".DS_Store").write_bytes(b"\0\0\0\1Bud1")
    (action / "pos" / "00001.xmp").write_text("<x:xmpmeta/>")  # a sidecar beside its raw file
    (action / "full_on" / "Thumbs.db").write_bytes(b"\xd0\xcf\x11\xe0")
    (action / "neg" / "old").mkdir()
    (action / "neg" / "old" / "00000.dng").write_bytes(b"not looked at")
    (capture / "actions" / "A9999").mkdir()  # an action folder capture.json does not list
    result = _run(capture, tmp_path / "release", store)
    assert result.action_status == {"A0000": "ok", "A0001": "ok"}, result.action_errors
    decode = next(t for t in result.plan.tasks if t.stage.name == "decode" and t.scope_id == "A0001")
    # the strays are not inputs: exactly one raw file per camera and illumination, byte-identical to the clean ones
    assert sorted(decode.raw_inputs) == sorted(f"{i}/{c}" for i in ("full_on", "pos", "neg") for c in CAMERAS)
    assert all(p.read_bytes() == (clean / p.relative_to(capture)).read_bytes() for p in decode.raw_inputs.values())


def test_non_finite_values_in_an_intermediate_map_degrade_to_invalid_pixels(clean, tmp_path):
    import OpenEXR

    from pipeline.codecs.exr import read_exr

    work = tmp_path / "work"
    _run(clean, tmp_path / "release", work)
    # a decoded map in the store gets NaN and Inf (a bad disk, a buggy stage); write_exr would refuse them
    path = next((work / "artifacts" / "decode").glob("A0001/*/pos/00001.exr"))
    pos = read_exr(path)
    pos[10:20, 10:30] = np.nan
    pos[20:22, 10:30] = np.inf
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {c: np.ascontiguousarray(pos[..., i]) for i, c in enumerate("RGB")}) as exr:
        exr.write(str(path))
    config = PRESETS["test"]
    result = run_pipeline(clean, tmp_path / "release", work, build_stages(config, through="photometric"), config,
                          SYNC, only="photometric", echo=lambda line: None)
    assert result.action_status == {"A0000": "ok", "A0001": "ok"}
    # the rerun's maps (same key: the store's copy is replaced; the release keeps the one published first)
    artifact = next((work / "artifacts" / "photometric").glob("A0001/*/normal_alpha")).parent
    maps = read_exr(artifact / "normal_alpha" / "00001.exr")
    assert np.isfinite(maps).all()
    assert np.all(maps[10:22, 10:30, 3] == 0)  # invalid where the input was not finite
    assert (maps[22:, :, 3] > 0.5).sum() > 50  # and valid elsewhere
    assert np.isfinite(read_exr(artifact / "albedo" / "00001.exr")).all()


CONFIGS = {
    "unknown_key": ("photometric:\n  params:\n    ratio_minimum: 0.3\n", ".photometric.params: unknown key(s) ['ratio_minimum']"),
    "impossible": ("photometric:\n  params:\n    ratio_min: 1.2\n",
                   ".photometric.params.ratio_min = 1.2: must be >= 0 and < ratio_max (1.05)"),
    "negative_size": ("colour:\n  erode_px: -2\n", ".colour.erode_px = -2: must be >= 0"),
    "bad_degree": ("lights:\n  degree: 7\n", ".lights.degree = 7: must be one of 1, 2, 3"),
    "nan": ("photometric:\n  params:\n    eps: .nan\n", ".photometric.params.eps: expected a finite number"),
    "wrong_type": ("decode:\n  half_size: maybe\n", ".decode.half_size: expected true/false"),
}


@pytest.mark.parametrize("case", sorted(CONFIGS))
def test_bad_config_is_refused_naming_the_file_and_key(case, tmp_path):
    from pipeline.config import load_overrides, merge

    text, reason = CONFIGS[case]
    path = tmp_path / "override.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        merge(PRESETS["default"], load_overrides(path), where=str(path))
    assert str(info.value).startswith(str(path)) and reason in str(info.value), str(info.value)
