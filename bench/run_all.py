"""Run every bench/bench_*.py (each writes <name>.json and plots into --out) and collect a report.

Benchmarks measure time against error, and speed as ratios against a simple baseline run in the same
process; they are never timed tests.
"""
from __future__ import annotations

import argparse
import json
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default=str(HERE / "out"))
    parser.add_argument("--only", help="comma-separated bench names (e.g. decode,photometric)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scripts = sorted(HERE.glob("bench_*.py"))
    if args.only:
        wanted = {f"bench_{n}.py" for n in args.only.split(",")}
        scripts = [s for s in scripts if s.name in wanted]
    failures = []
    report = ["# Benchmark report", "", "## Machine", "", *machine_lines(), ""]
    for script in scripts:
        print(f"== {script.name}", flush=True)
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, str(script), "--out", str(out)], cwd=HERE.parent)
        seconds = time.perf_counter() - start
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
    (out / "REPORT.md").write_text("\n".join(report))
    print(f"report: {out / 'REPORT.md'}")
    if failures:
        print(f"failed: {failures}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
