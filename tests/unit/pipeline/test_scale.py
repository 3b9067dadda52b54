"""What keeps the engine linear at release size (issue 23, bench/bench_scale.py): lookups by index instead of
scans, and the same answers as before."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from pipeline.capture import open_capture
from pipeline.hashing import DigestCache
from tests.unit.pipeline.conftest import make_toy_capture

ACTIONS = tuple(f"A{i:04d}" for i in range(6))


def test_capture_lookups_and_listing_agree_with_the_folder(tmp_path):
    capture = open_capture(make_toy_capture(tmp_path / "capture", actions=ACTIONS))
    assert [capture.action(a).action_id for a in ACTIONS] == list(ACTIONS)
    with pytest.raises(KeyError, match="no action A9999"):
        capture.action("A9999")
    folder = tmp_path / "capture" / "actions" / "A0001" / "pos"
    (folder / "00001.DNG").write_text("second file of a camera")
    (folder / "notes.txt").write_text("not a raw file")
    (folder / "00002.dng").unlink()
    cams = ["00000", "00001", "00002"]
    assert capture.raw_paths("A0001", "pos", cams) == {c: capture.raw_path("A0001", "pos", c) for c in cams}
    assert capture.raw_paths("A0001", "pos", cams)["00002"] is None
    frames, errors = capture.action_frames("A0001")
    assert sorted(e.reason.split(":")[0] for e in errors) == ["camera 00001 has 2 raw files for 'pos' (['00001.DNG', "
                                                              "'00001.dng'])", "camera 00002 has no raw file for 'pos'"]
    assert ("pos", "00000") in frames and ("pos", "00001") not in frames
    capture.actions.append(capture.actions[0].__class__("A0100", "S000", "toy"))  # a grown list is seen
    assert capture.action("A0100").action_id == "A0100"


def test_digest_keys_are_resolved_paths(tmp_path, monkeypatch):
    real = tmp_path / "real"
    real.mkdir()
    (real / "a.dng").write_bytes(b"frame")
    (real / "target.dng").write_bytes(b"other")
    os.symlink(real, tmp_path / "linked")
    os.symlink(real / "target.dng", real / "b.dng")
    monkeypatch.chdir(tmp_path)
    cache = DigestCache(tmp_path / "digests.json")
    for path in (tmp_path / "linked" / "a.dng", Path("linked/a.dng"), Path("real/../linked/a.dng"),
                 real / "b.dng", tmp_path / "linked" / "b.dng"):
        assert cache._resolved(path) == str(Path(path).resolve())
        assert cache.digest(path)["bytes"] == Path(path).stat().st_size
    assert cache.hashed == 2 and set(cache._entries) == {str(real / "a.dng"), str(real / "target.dng")}
    with pytest.raises(FileNotFoundError):
        cache.digest(real / "missing.dng")




def test_tasks_of_scopes_come_in_plan_order(tmp_path):
    from pipeline.graph import make_plan
    from pipeline.store import ArtifactStore
    from tests.unit.pipeline.conftest import toy_stages

    capture = open_capture(make_toy_capture(tmp_path / "capture", actions=ACTIONS))
    plan = make_plan(capture, toy_stages(), ArtifactStore(tmp_path / "work" / "artifacts"),
                     DigestCache(tmp_path / "work" / "digests.json"), echo=lambda line: None)
    for scopes in (("A0003",), ("S000", "A0003"), ("A0003", "S000"), ("A0001", "A0000"), ("nope",)):
        assert plan.of_scopes(*scopes) == [t for t in plan.tasks if t.scope_id in scopes]
    assert plan.for_scope("A0002") == [t for t in plan.tasks if t.scope_id == "A0002"]


def test_validated_rows_are_the_same_whichever_path_checks_them():
    import datetime

    import numpy as np

    from manifests.writer import _checked_columns, _fast_columns, validate_rows
    from manifests.schemas import spec

    rows = [{"action_id": f"A{i:04d}", "camera_id": f"{i % 3:05d}", "metric": "decode_mean", "region": None,
             "environment": None, "value": v, "unit": "1", "source": "decode", "run_id": "r1"}
            for i, v in enumerate([0.5, 1, 2.25, 3])]
    ts = spec("metrics")
    assert _fast_columns("metrics", ts, rows) == _checked_columns("metrics", ts, rows)
    assert validate_rows("metrics", rows).column("value").to_pylist() == [0.5, 1.0, 2.25, 3.0]
    # numpy scalars take the row-by-row path, which converts them: the same table
    mixed = [dict(r, value=np.float32(r["value"])) for r in rows]
    assert validate_rows("metrics", mixed).equals(validate_rows("metrics", rows))
    # and errors are named as before: the first bad row in row order
    bad = [dict(rows[0], value=float("nan")), dict(rows[1], camera_id="7")]
    with pytest.raises(ValueError, match=r"metrics row 0: column 'value' is nan"):
        validate_rows("metrics", bad)
    stage_row = {"run_id": "r1", "stage": "decode", "version": "1", "scope": "action", "scope_id": "A0000",
                 "cache_key": "0" * 64, "status": "ran", "seconds": 1.0, "error": "not allowed",
                 "started_at": datetime.datetime.now(datetime.timezone.utc), "config_json": "{}"}
    with pytest.raises(ValueError, match="row 0: column 'error' must be null when status is 'ran'"):
        validate_rows("stage_runs", [stage_row])
