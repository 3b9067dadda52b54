"""verify_release: re-hashes every asset; catches modified, deleted and unlisted files."""
from __future__ import annotations

import json

import pytest

from manifests import ReleaseError, VerifyReport, verify_release


def test_intact_release_verifies(release_dir):
    report = verify_release(release_dir)
    assert isinstance(report, VerifyReport)
    assert report.ok, report.summary()
    assert report.n_checked == 15
    assert (report.missing, report.mismatched, report.extra) == ([], [], [])
    # the two manifest tables are checked against manifests/index.json, which verify names as the root
    assert [n.split(":")[0] for n in report.not_covered] == ["manifests/index.json"]
    assert "OK" in str(report)
    assert json.loads(json.dumps(report.to_dict()))["ok"] is True


def test_modified_file_is_mismatched(release_dir):
    f = release_dir / "actions" / "A0000" / "albedo" / "00000.exr"
    data = bytearray(f.read_bytes())
    data[-1] ^= 0xFF  # same size, different content
    f.write_bytes(bytes(data))
    report = verify_release(release_dir, workers=2)
    assert not report.ok
    assert len(report.mismatched) == 1
    entry = report.mismatched[0]
    assert entry.startswith("actions/A0000/albedo/00000.exr: sha256 expected ")
    assert " actual " in entry
    assert report.n_checked == 15 and not report.missing and not report.extra
    assert "FAILED" in report.summary() and "mismatched: actions/A0000/albedo/00000.exr" in report.summary()


def test_deleted_file_is_missing(release_dir):
    (release_dir / "actions" / "A0000" / "mask" / "00001.png").unlink()
    report = verify_release(release_dir)
    assert not report.ok
    assert report.missing == ["actions/A0000/mask/00001.png"]
    assert report.n_checked == 14


def test_extra_file_is_reported(release_dir):
    extra = release_dir / "actions" / "A0000" / "previews" / "stray.png"
    extra.parent.mkdir()
    extra.write_bytes(b"not listed")
    (release_dir / "actions" / "A0000" / "normal_alpha" / ".00000.exr.123.tmp").write_bytes(b"half")
    report = verify_release(release_dir)
    assert not report.ok
    assert report.extra == ["actions/A0000/normal_alpha/.00000.exr.123.tmp", "actions/A0000/previews/stray.png"]
    assert not report.missing and not report.mismatched


def test_release_without_assets_table_fails(release_dir):
    (release_dir / "manifests" / "assets.parquet").unlink()
    report = verify_release(release_dir)
    assert not report.ok
    assert report.missing == ["manifests/assets.parquet"]


def test_not_a_release(tmp_path):
    with pytest.raises(ReleaseError):
        verify_release(tmp_path)


def test_changed_manifest_and_unlisted_top_level_file_are_named(release_dir):
    table = release_dir / "manifests" / "actions.parquet"
    data = bytearray(table.read_bytes())
    data[len(data) // 2] ^= 0xFF
    table.write_bytes(bytes(data))
    (release_dir / "run.json").write_text("{}")
    report = verify_release(release_dir)
    assert not report.ok
    assert [m.split(":")[0] for m in report.mismatched] == ["manifests/actions.parquet"]
    assert report.extra == ["run.json"]
    assert "extra: run.json" in report.summary()
