"""bench/_quick.py: the shared tiny run is brought up to date once per run_all session, and again whenever a file
under it changed since."""
from __future__ import annotations

import json
import os

from tests.unit.bench.test_bench_defaults import load_bench


def _checked(tmp_path):
    quick = load_bench("_quick")
    root = tmp_path / "quick_run"
    (root / "release").mkdir(parents=True)
    (root / "release" / "run.json").write_text("{}")
    (root / "quick.json").write_text("{}")
    (root / quick.QUICK_RUN_CHECKED).write_text(json.dumps({"session": "s1", "files": quick._fingerprint(root)}))
    return quick, root


def test_the_session_that_checked_the_run_finds_it_unchanged_another_does_not(tmp_path):
    quick, root = _checked(tmp_path)
    assert quick._checked_in(root, "s1")
    assert not quick._checked_in(root, "s2")
    (root / quick.QUICK_RUN_CHECKED).unlink()
    assert not quick._checked_in(root, "s1")


def test_a_file_changed_added_or_removed_under_the_run_makes_it_run_again(tmp_path):
    quick, root = _checked(tmp_path)
    run_json = root / "release" / "run.json"
    stat = run_json.stat()
    run_json.write_text("{} ")  # another size
    assert not quick._checked_in(root, "s1")
    run_json.write_text("{}")
    os.utime(run_json, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert quick._checked_in(root, "s1")  # the same size and time again
    os.utime(run_json, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1000))
    assert not quick._checked_in(root, "s1")
    os.utime(run_json, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    (root / "release" / "new.exr").write_bytes(b"x")
    assert not quick._checked_in(root, "s1")
    (root / "release" / "new.exr").unlink()
    (root / "quick.json").unlink()
    assert not quick._checked_in(root, "s1")


def test_the_fingerprint_leaves_out_its_own_record(tmp_path):
    quick, root = _checked(tmp_path)
    before = quick._fingerprint(root)
    (root / quick.QUICK_RUN_CHECKED).write_text(json.dumps({"session": "s9", "files": "other"}))
    assert quick._fingerprint(root) == before
