"""The benches' ``--quick`` mode: their own code on the smallest inputs that still run it, so that the tests can
run every bench (``make bench-quick``, tests/unit/bench/test_bench_quick.py). Its numbers are not measurements.

The benches that read a release (``make dataset``) read instead a tiny simulated capture and its release, made
once per ``--out`` folder by :func:`quick_run` and shared by every bench run into that folder.

``run_all.py --quick`` runs the benches with ``OMP_WAIT_POLICY=PASSIVE``: several benches import torch before they
set their threads, and on a machine shared with other work spinning OpenMP threads made some quick runs several
times slower (a bench run by hand with ``--quick`` may want the same).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

QUICK_HELP = ("quick mode: the same code on the smallest inputs that run it (the tests' mode); the numbers are "
              "not measurements")
QUICK_RUN = "quick_run"
"""Folder under ``--out`` of the shared tiny run: ``capture/``, ``release/`` and ``release.work/``."""
QUICK_ACTIONS = 1
QUICK_CAMERAS = 8  # the geometry stage's default min_views; 2 held-out cameras + 6 sources for the G-buffers
QUICK_WIDTH = 96
QUICK_LEDS = 128
QUICK_PRESET = "test"  # the preset of the tests' tiny captures: every stage runs, in seconds
QUICK_RUN_LOCK = "quick_run.lock"
"""File under ``--out`` that a process using the shared tiny run holds locked until it exits."""
QUICK_RUN_USERS = "quick_run.users"
"""File under ``--out``: one line per process that used the shared tiny run, its script's name."""
QUICK_RUN_SESSION_ENV = "ULTRASTAGE_QUICK_RUN_SESSION"
"""Environment variable ``run_all.py --quick`` sets to a token of its own invocation: within it the shared run is
brought up to date once, by its first user, and found unchanged by the others."""
QUICK_RUN_CHECKED = "checked.json"
"""File in the shared run's folder: the session token that last brought it up to date, and the fingerprint of its
files then."""
_held_lock = None


def quick_sim_changes() -> dict:
    """SimConfig fields every quick capture changes: 128 LEDs and the subject mesh unsubdivided (13k vertices):
    the LEDs' visibility per vertex is most of a small capture's simulation time."""
    return {"n_leds": QUICK_LEDS, "subdivisions": 0}


def quick_capture_config():
    """The SimConfig of the shared tiny capture: 1 action, 8 cameras, 96 px wide, :func:`quick_sim_changes`;
    everything else the simulator's defaults."""
    from synthetic import SimConfig

    return SimConfig(actions=QUICK_ACTIONS, width=QUICK_WIDTH, n_cameras=QUICK_CAMERAS, **quick_sim_changes())


def quick_run(out: Path) -> Path:
    """``OUT/quick_run``: the tiny capture (:func:`quick_capture_config`, simulated on first use and kept while its
    config is the same: ``quick.json``) and its release by the ``test`` preset (``release/``, work folder
    ``release.work/`` as ``ultrastage run`` lays them out). The pipeline runs every time: its cache makes that a
    plan when nothing changed, and the stages the code changed run again. Within one ``run_all.py --quick`` (its
    token in :data:`QUICK_RUN_SESSION_ENV`) it runs for the first user only, and again only if a file under the
    run changed since (:data:`QUICK_RUN_CHECKED`): the check costs a fresh interpreter's imports, about 6 CPU
    seconds, for each of the benches that read the run.

    It runs in a child process whose OpenMP threads sleep while they wait (``OMP_WAIT_POLICY=PASSIVE``, unless
    set): on a 2-core machine shared with other work, spinning threads made this run 100-120 s instead of 13-16 s.

    The calling process holds ``OUT/quick_run.lock`` from here until it exits, so that benches run side by side
    (``run_all.py --quick --lanes 2``) take the shared run one at a time: a second pipeline run on the same folder
    would be refused by its run lock, and a rerun may rewrite files another bench reads. It adds its script's name
    to ``OUT/quick_run.users``."""
    global _held_lock
    root = Path(out) / QUICK_RUN
    if _held_lock is None:
        import fcntl

        root.parent.mkdir(parents=True, exist_ok=True)
        _held_lock = open(root.parent / QUICK_RUN_LOCK, "a")
        fcntl.flock(_held_lock, fcntl.LOCK_EX)  # released by the OS when this process ends
        with open(root.parent / QUICK_RUN_USERS, "a") as users:
            users.write(Path(sys.argv[0]).stem + "\n")
    session = os.environ.get(QUICK_RUN_SESSION_ENV)
    if session and _checked_in(root, session):
        print(f"quick run: {root} brought up to date earlier in this run_all session and unchanged since; "
              "not run again", flush=True)
        return root
    env = os.environ | {"OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    subprocess.run([sys.executable, str(Path(__file__).resolve()), str(root)], check=True, env=env)
    if session:
        (root / QUICK_RUN_CHECKED).write_text(json.dumps({"session": session, "files": _fingerprint(root)}))
    return root


def _fingerprint(root: Path) -> str:
    """A digest of every file under ``root`` but :data:`QUICK_RUN_CHECKED`: its path, size and modification time."""
    import hashlib

    digest = hashlib.sha256()
    for folder, _, files in sorted(os.walk(root)):
        for name in sorted(files):
            path = Path(folder) / name
            if path == root / QUICK_RUN_CHECKED:
                continue
            stat = path.stat()
            digest.update(f"{path.relative_to(root)}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return digest.hexdigest()


def _checked_in(root: Path, session: str) -> bool:
    """Whether the run's :data:`QUICK_RUN_CHECKED` says this session brought it up to date and no file under ``root``
    changed since: the code cannot have changed within one run_all invocation, so the pipeline would only plan."""
    try:
        record = json.loads((root / QUICK_RUN_CHECKED).read_text())
    except (OSError, ValueError):
        return False
    return record.get("session") == session and record.get("files") == _fingerprint(root)


def _make_quick_run(root: Path) -> None:
    from pipeline.runner import ExecutionConfig
    from stages.registry import PRESETS, build_stages
    from ultrastage.run import run_pipeline

    sim = quick_capture_config()
    record = json.loads(json.dumps({"simulate": sim.to_json()}))
    marker = root / "quick.json"
    started = time.perf_counter()
    try:
        same = json.loads(marker.read_text()) == record and (root / "capture" / "capture.json").is_file()
    except (OSError, ValueError):
        same = False
    if not same:
        from synthetic import simulate

        shutil.rmtree(root, ignore_errors=True)
        simulate(root / "capture", sim)
        marker.write_text(json.dumps(record, indent=1))
    config = PRESETS[QUICK_PRESET]
    result = run_pipeline(root / "capture", root / "release", root / "release.work", build_stages(config), config,
                          ExecutionConfig(scheduler="sync"), echo=lambda line: None,
                          record={"preset": QUICK_PRESET})
    failed = {a: s for a, s in result.action_status.items() if s != "ok"}
    if failed:
        raise RuntimeError(f"quick run under {root}: actions failed: {failed} {result.action_errors}")
    ran = sum(t.status == "ran" for t in result.plan.tasks)
    print(f"quick run: tiny capture and release under {root} ({ran} stage tasks ran) in "
          f"{time.perf_counter() - started:.1f} s", flush=True)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    _make_quick_run(Path(sys.argv[1]))
