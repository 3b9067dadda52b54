"""Every bench runs in its quick mode (`make bench-quick`: bench/run_all.py --quick), so that none can rot: each
writes its results, marked quick, with finite numbers. Nothing is timed; the run takes about 3 minutes on an idle
2-core machine (the tiny simulated run the release benches share included)."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
SHARED = ROOT.parent / "shared" / "data"
BENCHES = sorted(p.stem for p in (ROOT / "bench").glob("bench_*.py"))


def _printed(stdout: str, name: str) -> str:
    """What run_all printed while it ran bench ``name``."""
    return stdout.partition(f"== {name}.py\n")[2].partition(f"== {name}.py: exit")[0]


def _numbers(value, where: str):
    """(path, number) of every number in a parsed JSON value."""
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        yield where, value
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from _numbers(item, f"{where}.{key}")
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _numbers(item, f"{where}[{i}]")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("bench_quick")
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "run_all.py"), "--quick", "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=1800)
    return out, proc


@pytest.mark.slow
def test_run_all_quick_exits_0_and_says_it_is_quick(quick_run):
    out, proc = quick_run
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    report = (out / "REPORT.md").read_text()
    assert "Quick run" in report.split("## Machine")[0] and "not measurements" in report
    for name in BENCHES:
        assert f"## {name}\n\nexit 0," in report, name


@pytest.mark.slow
@pytest.mark.parametrize("name", BENCHES)
def test_every_bench_writes_quick_results_with_finite_numbers(quick_run, name):
    out, proc = quick_run
    result, table = out / f"{name}.json", out / f"{name}.md"
    if not (result.exists() or table.exists()) and not SHARED.is_dir() and "skipped" in _printed(proc.stdout, name):
        pytest.skip(f"{name} needs ../shared/data (the HDR maps), absent here")
    assert result.exists() or table.exists(), f"{name} wrote neither {result.name} nor {table.name}"
    if not result.exists():
        return
    data = json.loads(result.read_text())  # Python's json reads NaN and Infinity: checked below
    assert data.get("quick") is True, f"{result.name} is not marked quick"
    bad = [where for where, x in _numbers(data, name) if not math.isfinite(x)]
    assert not bad, f"{result.name}: non-finite numbers at {bad[:10]}"
