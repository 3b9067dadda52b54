"""Run every bench/bench_*.py (each writes <name>.json and plots into --out) and collect a report.

Benchmarks measure time against error, and speed as ratios against a simple baseline run in the same
process; they are never timed tests.

``--quick`` (``make bench-quick``, and tests/unit/bench/test_bench_quick.py) runs every bench in its quick mode:
the same code on the smallest inputs that run it (the benches that read a release share a tiny simulated run
made once under ``--out``, see bench/_quick.py), so that the benches cannot rot; its numbers are not
measurements.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
LIBRARIES = ("numpy", "torch", "rawpy", "pycolmap", "open3d", "xatlas", "OpenEXR", "pyarrow", "dask")


def machine_lines() -> list[str]:
    """What the numbers were measured on: CPU cores, memory, GPU (torch's view) and library versions."""
    import os
    import platform
    from importlib import metadata

    lines = [f"- CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} logical cores"
             f" ({len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else os.cpu_count()} usable)"]
    try:
        pages, page_size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
        lines.append(f"- memory: {pages * page_size / 2 ** 30:.1f} GiB")
    except (ValueError, OSError, AttributeError):
        pass
    try:
        import torch

        gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none (torch sees no CUDA device)"
    except ImportError:
        gpu = "unknown (torch not importable)"
    lines.append(f"- GPU: {gpu}")
    lines.append(f"- {platform.platform()}, Python {platform.python_version()}")
    versions = []
    for name in LIBRARIES:
        try:
            versions.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            versions.append(f"{name} (absent)")
    lines.append("- " + ", ".join(versions))
    return lines


def tradeoff_section(out: Path) -> list[str]:
    """The per-stage time-against-error tables and plots (bench/_tradeoffs.py) from the benches' JSON in ``out``."""
    sys.path.insert(0, str(HERE))
    sys.path.insert(0, str(HERE.parent))
    from _tradeoffs import report_section

    return report_section(out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default=str(HERE / "out"))
    parser.add_argument("--only", help="comma-separated bench names (e.g. decode,photometric)")
    parser.add_argument("--quick", action="store_true",
                        help="every bench in its quick mode (the tests' mode): checks they run; not measurements")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scripts = sorted(HERE.glob("bench_*.py"))
    if args.only:
        wanted = {f"bench_{n}.py" for n in args.only.split(",")}
        scripts = [s for s in scripts if s.name in wanted]
    failures, times = [], {}
    report = ["# Benchmark report", ""]
    env = None
    if args.quick:
        report += ["**Quick run** (`run_all.py --quick`, `make bench-quick`): every bench on the smallest inputs that "
                   "run its code, to check that it runs. **Its numbers are not measurements**; `make bench` measures.",
                   ""]
        # numeric threads that sleep rather than spin while they wait: the tests run this beside other work
        env = os.environ | {"OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    report += ["## Machine", "", *machine_lines(), ""]
    started = time.perf_counter()
    for script in scripts:
        print(f"== {script.name}", flush=True)
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, str(script), "--out", str(out)] + (["--quick"] if args.quick else []),
                              cwd=HERE.parent, env=env)
        seconds = time.perf_counter() - start
        times[script.stem] = seconds
        print(f"== {script.name}: exit {proc.returncode}, {seconds:.1f} s", flush=True)
        if proc.returncode:
            failures.append(script.name)
        report += [f"## {script.stem}", "", f"exit {proc.returncode}, {seconds:.1f}s", ""]
        result = out / f"{script.stem}.json"
        table = out / f"{script.stem}.md"
        if table.exists():  # the bench's own tables, written for readers
            report += [table.read_text().replace("\n# ", "\n### ").removeprefix("# "), ""]
        elif result.exists():
            report += ["```json", json.dumps(json.loads(result.read_text()), indent=1)[:6000], "```", ""]
        for png in sorted(out.glob(f"{script.stem}*.png")):
            report.append(f"![{png.stem}]({png.name})")
        report.append("")
    total = time.perf_counter() - started
    first_bench = next((i for i, line in enumerate(report) if line.startswith("## bench_")), len(report))
    report[first_bench:first_bench] = tradeoff_section(out)
    report[report.index("## Machine"):report.index("## Machine")] = [
        f"{len(scripts)} benches in {total:.0f} s: " + ", ".join(f"{k.removeprefix('bench_')} {v:.0f} s"
                                                              for k, v in times.items()), ""]
    (out / "REPORT.md").write_text("\n".join(report))
    print("times: " + ", ".join(f"{k} {v:.1f} s" for k, v in times.items()))
    print(f"total {total:.1f} s; report: {out / 'REPORT.md'}")
    if failures:
        print(f"failed: {failures}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
