"""verify_release: re-hashes every asset; catches modified, deleted and unlisted files."""
from __future__ import annotations

import json

import pytest

from manifests import ReleaseError, VerifyReport, verify_release


def test_intact_release_verifies(release_dir):
    report = verify_release(release_dir)
    assert isinstance(report, VerifyReport)
    assert report.ok, report.summary()
    assert report.n_checked == 13
    assert (report.missing, report.mismatched, report.extra) == ([], [], [])
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
    assert report.n_checked == 13 and not report.missing and not report.extra
    assert "FAILED" in report.summary() and "mismatched: actions/A0000/albedo/00000.exr" in report.summary()


def test_deleted_file_is_missing(release_dir):
    (release_dir / "actions" / "A0000" / "mask" / "00001.png").unlink()
    report = verify_release(release_dir)
    assert not report.ok
    assert report.missing == ["actions/A0000/mask/00001.png"]
    assert report.n_checked == 12


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
