"""The release page's thumbnails: written on a thread pool against one thread, in the same process.

A copy of a release (default: ``runs/default/release``, what ``make dataset`` writes; ``--release`` names another)
has its page written from scratch (``manifests.page.write_release_page``, every thumbnail made again) with one
thread (the baseline) and with the pool's default size, in turn, ``--repeats`` times each. Reports the seconds
(best and all), the CPU seconds of the process, the thumbnail count and ``x_one_thread`` (one thread's best over
the pool's), and checks that both wrote the same thumbnails (PNG bytes). Writes bench_page.json.

``python bench/bench_page.py --out bench/out [--release R] [--repeats 3] [--quick]``; ``--quick`` (the tests'
mode): the shared tiny release, once each; the numbers are not measurements.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _quick import QUICK_HELP, quick_run  # noqa: E402


def write_page_from_scratch(release: Path, threads: int | None) -> tuple[float, float, dict[str, str]]:
    """(wall s, CPU s, thumbnail -> sha256) of writing ``release``'s page with its thumbnails removed first."""
    from manifests.page import THUMBNAIL_DIR, write_release_page

    shutil.rmtree(release / THUMBNAIL_DIR, ignore_errors=True)
    wall, cpu = time.perf_counter(), time.process_time()
    write_release_page(release, threads=threads)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    thumbs = {p.relative_to(release).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
              for p in sorted((release / THUMBNAIL_DIR).rglob("*.png"))}
    return wall, cpu, thumbs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="bench/out")
    parser.add_argument("--release", help="a release folder (default: runs/default/release)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.quick:
        source, args.repeats = quick_run(out) / "release", 1
    else:
        source = Path(args.release) if args.release else ROOT / "runs" / "default" / "release"
    if not (source / "manifests").is_dir():
        raise SystemExit(f"{source}: no release there (run `make dataset` first, or name one with --release)")
    import os

    pool = max(1, min(os.cpu_count() or 1, 8))
    runs: dict[str, list[tuple[float, float]]] = {"one_thread": [], "pool": []}
    with tempfile.TemporaryDirectory(dir=out) as tmp:
        release = Path(tmp) / "release"
        shutil.copytree(source, release)
        thumbs = {}
        for _ in range(args.repeats):
            for label, threads in (("one_thread", 1), ("pool", None)):
                wall, cpu, thumbs[label] = write_page_from_scratch(release, threads)
                runs[label].append((wall, cpu))
                print(f"{label:<10} {wall:6.2f} s wall {cpu:6.2f} s CPU, {len(thumbs[label])} thumbnails", flush=True)
        if thumbs["one_thread"] != thumbs["pool"]:
            raise SystemExit("the pool wrote other thumbnails than one thread did")
    best = {k: min(w for w, _ in v) for k, v in runs.items()}
    report = {"release": str(source), "quick": args.quick, "repeats": args.repeats, "pool_threads": pool,
              "thumbnails": len(thumbs["pool"]),
              "seconds": {k: [round(w, 3) for w, _ in v] for k, v in runs.items()},
              "cpu_seconds": {k: [round(c, 3) for _, c in v] for k, v in runs.items()},
              "best_s": {k: round(v, 3) for k, v in best.items()},
              "x_one_thread": round(best["one_thread"] / best["pool"], 3) if best["pool"] > 0 else None}
    (out / "bench_page.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
