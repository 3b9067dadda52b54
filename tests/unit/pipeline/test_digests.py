"""Digests off the driver's serial path: raw frames hashed by a thread pool while planning, release files hashed
by the tasks that wrote them (their success records), with the same digests as a serial hash of the bytes."""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest

import manifests.writer
from pipeline.hashing import DigestCache
from pipeline.runner import ExecutionConfig
from pipeline.store import SUCCESS
from ultrastage.run import run_pipeline
from tests.unit.pipeline.conftest import toy_stages

SYNC = ExecutionConfig(scheduler="sync")


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_digest_all_hashes_in_threads_what_digest_would_and_only_once(tmp_path):
    files = []
    for i in range(12):
        files.append(tmp_path / f"{i:05d}.dng")
        files[-1].write_bytes(os.urandom(3000 + 5000 * i))  # above hashlib's size for releasing the GIL
    cache = DigestCache(tmp_path / "digests.json")
    assert cache.digest_all(files + [files[0], tmp_path / "missing.dng"], threads=4) == 12
    serial = DigestCache(tmp_path / "serial.json")
    for f in files:
        assert cache.digest(f) == serial.digest(f) == {"sha256": _sha(f), "bytes": f.stat().st_size}
    assert (cache.hashed, cache.reused) == (12, 12)
    cache.save()
    again = DigestCache(tmp_path / "digests.json")  # a rerun: unchanged frames cost a stat, not a read
    assert again.digest_all(files, threads=4) == 0
    files[3].write_bytes(b"replaced")
    os.utime(files[3], ns=(1, 1))
    assert again.digest_all(files, threads=4) == 1
    assert again.digest(files[3])["sha256"] == hashlib.sha256(b"replaced").hexdigest()
    with pytest.raises(FileNotFoundError):
        again.digest(tmp_path / "missing.dng")


def test_the_plan_hashes_every_raw_input_before_planning(toy_capture, tmp_path, monkeypatch):
    calls = []
    original = DigestCache.digest_all

    def spy(self, paths, threads=0):
        paths = list(paths)
        calls.append((len(paths), threads))
        return original(self, paths, threads)

    monkeypatch.setattr(DigestCache, "digest_all", spy)
    result = run_pipeline(toy_capture, tmp_path / "release", tmp_path / "work", toy_stages(), {"toy": 1},
                          ExecutionConfig(scheduler="sync", hash_threads=3), echo=lambda line: None)
    # one batch: the rig of the session stage and 2 actions x 3 illuminations x 3 cameras
    assert calls == [(1 + 2 * 9, 3)]
    frames = result.plan.of_scopes("A0000")[0]
    assert frames.record["inputs"]["pos/00001"] == _sha(toy_capture / "actions" / "A0000" / "pos" / "00001.dng")


def test_release_digests_come_from_the_success_records_and_equal_the_files(toy_capture, tmp_path, monkeypatch):
    release, work = tmp_path / "release", tmp_path / "work"
    hashed_by_publishing = []
    original = manifests.writer.file_sha256

    def counting(path, *args, **kwargs):
        hashed_by_publishing.append(Path(path).name)
        return original(path, *args, **kwargs)

    monkeypatch.setattr(manifests.writer, "file_sha256", counting)
    run_pipeline(toy_capture, release, work, toy_stages(), {"toy": 1}, SYNC, echo=lambda line: None)
    # only the release-wide documents and manifests are hashed while publishing: no action file
    assert hashed_by_publishing and not [n for n in hashed_by_publishing if n.endswith(".txt")]
    success = json.loads(next((work / "artifacts" / "read" / "A0000").glob(f"*/{SUCCESS}")).read_text())
    assert sorted(success["files"]) == ["frames/00000.txt", "frames/00001.txt", "frames/00002.txt"]
    table = manifests.writer.read_manifest(release, "assets").to_pylist()
    action_rows = [r for r in table if r["action_id"] is not None]
    assert len(action_rows) == 2 * 4  # 3 frames and a summary per action
    for row in table:
        assert row["sha256"] == _sha(release / row["path"]) and row["bytes"] == (release / row["path"]).stat().st_size


def test_a_result_without_recorded_digests_is_hashed_when_published(toy_capture, tmp_path):
    """A store committed before the records held digests (or a file changed since): the same rows, hashed."""
    first = tmp_path / "first"
    run_pipeline(toy_capture, first / "release", first / "work", toy_stages(), {"toy": 1}, SYNC, echo=lambda line: None)
    expected = {r["path"]: r["sha256"] for r in manifests.writer.read_manifest(first / "release", "assets").to_pylist()
                if r["action_id"] is not None}
    for success_path in (first / "work" / "artifacts").rglob(SUCCESS):
        success = json.loads(success_path.read_text())
        success.pop("files", None)
        success_path.write_text(json.dumps(success))
    second = tmp_path / "second"
    run_pipeline(toy_capture, second / "release", first / "work", toy_stages(), {"toy": 1}, SYNC,
                 echo=lambda line: None)
    got = {r["path"]: r["sha256"] for r in manifests.writer.read_manifest(second / "release", "assets").to_pylist()
           if r["action_id"] is not None}
    assert got == expected and len(got) == 8
