"""One run at a time per release: the work folder's run.lock, tried with real processes (issue 23)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.runlock import LOCK_NAME, RunLockedError, hold_run_lock

ROOT = Path(__file__).resolve().parents[3]
ENV = os.environ | {"PYTHONPATH": str(ROOT)}
HOLDER = """
import sys, time
from pipeline.runlock import hold_run_lock
with hold_run_lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(120)
"""


def _holder(work: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(work)], env=ENV, cwd=ROOT, stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_run_is_refused_and_a_dead_runs_lock_is_taken_over(tmp_path):
    release = tmp_path / "release"
    work = tmp_path / "release.work"  # the CLI's default work folder for this release
    first = _holder(work)
    try:
        second = subprocess.run([sys.executable, "-m", "ultrastage.cli", "run", "--capture", str(tmp_path / "capture"),
                                 "--release", str(release), "--preset", "test", "--no-evaluate"],
                                env=ENV, cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert second.returncode == 2, second.stderr
        assert str(work / LOCK_NAME) in second.stderr and f"pid {first.pid}" in second.stderr
        assert "being written by another run" in second.stderr
        assert not release.exists()  # refused before it wrote anything
    finally:
        first.send_signal(signal.SIGKILL)  # dies without cleaning up: its lock file stays behind
        first.wait()
    assert json.loads((work / LOCK_NAME).read_text())["pid"] == first.pid
    third = subprocess.run([sys.executable, "-c", "import sys\nfrom pipeline.runlock import hold_run_lock\n"
                            "with hold_run_lock(sys.argv[1]): print('ran', flush=True)", str(work)],
                           env=ENV, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert third.returncode == 0, third.stderr
    assert f"taking over the stale lock of pid {first.pid} (no longer running)" in third.stdout
    assert third.stdout.strip().endswith("ran")
    assert not (work / LOCK_NAME).exists()  # released at the end of the run


def test_the_lock_is_reentrant_in_one_process_and_released_after(tmp_path):
    with hold_run_lock(tmp_path) as path:
        record = json.loads(path.read_text())
        assert record["pid"] == os.getpid()
        with hold_run_lock(tmp_path):  # e.g. the CLI holding it around run + evaluate
            assert path.exists()
        assert path.exists()
    assert not path.exists()
    with hold_run_lock(tmp_path):  # and can be taken again
        pass


def test_a_lock_written_on_another_host_is_not_taken_over(tmp_path):
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": 12345, "host": "render-node-7", "started_at": "x"}))
    with pytest.raises(RunLockedError, match="render-node-7.*another host"):
        with hold_run_lock(tmp_path):
            pass
    assert (tmp_path / LOCK_NAME).exists()
