"""The benches' ``--quick`` mode: their own code on the smallest inputs that still run it, so that the tests can
run every bench (``make bench-quick``, tests/unit/bench/test_bench_quick.py). Its numbers are not measurements.

The benches that read a release (``make dataset``) read instead a tiny simulated capture and its release, made
once per ``--out`` folder by :func:`quick_run` and shared by every bench run into that folder.
"""
from __future__ import annotations

import json
import shutil
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


def quick_sim_changes() -> dict:
    """SimConfig fields every quick capture changes: 128 LEDs and the subject mesh unsubdivided (13k vertices):
    the LEDs' visibility per vertex is most of a small capture's simulation time."""
    return {"n_leds": QUICK_LEDS, "subdivisions": 0}


def quick_capture_config():
    """The SimConfig of the shared tiny capture: 1 action, 8 cameras, 96 px wide, :func:`quick_sim_changes`;
    everything else the simulator's defaults."""
    from synthetic import SimConfig

    return SimConfig(actions=QUICK_ACTIONS, width=QUICK_WIDTH, n_cameras=QUICK_CAMERAS, **quick_sim_changes())


def quick_run(out: Path, say=print) -> Path:
    """``OUT/quick_run``: the tiny capture (:func:`quick_capture_config`) and its release by the ``test`` preset
    (``release/``, work folder ``release.work/`` as ``ultrastage run`` lays them out), made on first use and
    reused while its record (``quick.json``, written last) matches."""
    from stages.registry import PRESETS

    root = Path(out) / QUICK_RUN
    sim = quick_capture_config()
    record = {"simulate": sim.to_json(), "preset": QUICK_PRESET}
    marker = root / "quick.json"
    if marker.is_file():
        try:
            if json.loads(marker.read_text()) == json.loads(json.dumps(record)):
                return root
        except ValueError:
            pass
    from pipeline.runner import ExecutionConfig, run_pipeline
    from stages.registry import build_stages
    from synthetic import simulate

    shutil.rmtree(root, ignore_errors=True)
    started = time.perf_counter()
    simulate(root / "capture", sim)
    config = PRESETS[QUICK_PRESET]
    result = run_pipeline(root / "capture", root / "release", root / "release.work", build_stages(config), config,
                          ExecutionConfig(scheduler="sync"), echo=lambda line: None,
                          record={"preset": QUICK_PRESET})
    failed = {a: s for a, s in result.action_status.items() if s != "ok"}
    if failed:
        raise RuntimeError(f"quick run under {root}: actions failed: {failed} {result.action_errors}")
    marker.write_text(json.dumps(record, indent=1))
    say(f"quick run: tiny capture and release under {root} in {time.perf_counter() - started:.1f} s")
    return root
