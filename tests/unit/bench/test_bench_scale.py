"""bench/bench_scale.py's quick mode runs (two tiny captures through the real engine with stub stages) and writes
the report run_all.py collects: its structure, and per-task figures that are finite and positive (no timings are
asserted)."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def test_quick_mode_writes_finite_positive_per_task_figures(tmp_path):
    env = os.environ | {"PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_scale.py"), "--quick", "--out", str(tmp_path)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads((tmp_path / "bench_scale.json").read_text())
    assert report["quick"] is True and report["goal_ms_per_task"] == 1.0 and report["cameras"] == 32
    results = report["results"]
    assert [(r["actions"], r["executor"]) for r in results] == [(2, "sync"), (4, "sync")]
    for r in results:
        assert set(r["runs"]) == {"cold", "cached"}
        cold, cached = r["runs"]["cold"], r["runs"]["cached"]
        # every stage of every scope ran cold and was found in the store on the rerun
        assert cold["ran"] == cold["plan_tasks"] and cached["cached"] == cached["plan_tasks"] == cold["plan_tasks"]
        assert cold["executor_tasks"] == cold["graph_tasks"] > cold["plan_tasks"] and cached["executor_tasks"] == 0
        assert set(cold["per_task"]) == {"plan_ms", "submit_ms", "execute_ms", "bookkeeping_ms",
                                         "bookkeeping_per_graph_task_ms", "bare_ms", "x_bare"}
        # the baseline ran as many tasks as the engine submitted, and its ratio is the two times' quotient
        assert r["bare_executor"]["tasks"] == cold["executor_tasks"]
        assert math.isclose(cold["per_task"]["x_bare"], cold["per_task"]["execute_ms"] / cold["per_task"]["bare_ms"])
        assert set(cached["per_task"]) == {"plan_ms", "bookkeeping_ms", "bookkeeping_per_graph_task_ms"}
        for run in (cold, cached):
            assert all(math.isfinite(v) and v > 0 for v in run["per_task"].values()), run["per_task"]
            assert all(math.isfinite(v) and v >= 0 for v in run["phases_s"].values())
        assert 0 < cold["max_in_flight"] <= cold["executor_tasks"]
        assert r["peak_rss_mib"] > 0
    table = (tmp_path / "bench_scale.md").read_text()
    assert table.startswith("# Engine overhead at release size") and "| 4 | sync | cached |" in table
