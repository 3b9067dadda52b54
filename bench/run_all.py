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
    report = ["# Benchmark report", "", f"Machine: {sys.platform}, Python {sys.version.split()[0]}", ""]
    for script in scripts:
        print(f"== {script.name}", flush=True)
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, str(script), "--out", str(out)], cwd=HERE.parent)
        seconds = time.perf_counter() - start
        if proc.returncode:
            failures.append(script.name)
        report += [f"## {script.stem}", "", f"exit {proc.returncode}, {seconds:.1f}s", ""]
        result = out / f"{script.stem}.json"
        if result.exists():
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
