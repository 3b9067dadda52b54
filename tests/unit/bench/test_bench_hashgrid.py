"""bench_hashgrid runs in its quick mode and its kernel rows agree with the torch path (no timing asserted)."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def test_bench_hashgrid_quick(tmp_path):
    subprocess.run([sys.executable, str(ROOT / "bench" / "bench_hashgrid.py"), "--out", str(tmp_path), "--quick"],
                   check=True, capture_output=True, text=True, cwd=ROOT)
    result = json.loads((tmp_path / "bench_hashgrid.json").read_text())
    paths = [row["path"] for row in result["rows"]]
    assert "torch, 1 thread" in paths and "torch, 2 threads" in paths
    for row in result["rows"]:
        assert all(math.isfinite(row[k]) and row[k] > 0 for k in ("encoding_s", "field_step_s"))
    if result["kernel_available"]:
        assert "kernel, 1 thread" in paths
        assert set(result["max_relative_difference_kernel_vs_torch"]) == {"features", "jacobian", "table_gradient"}
        assert max(result["max_relative_difference_kernel_vs_torch"].values()) < 1e-5
    assert "| path |" in (tmp_path / "bench_hashgrid.md").read_text()
