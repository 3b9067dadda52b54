"""Command line and input checks shared by the benches that measure an existing release (`make dataset`)."""
from __future__ import annotations

import argparse
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def release_parser(description: str | None, actions: str | None = None, threads: int | None = None) -> argparse.ArgumentParser:
    """A parser with ``--out``, ``--release`` and ``--capture`` (defaults: bench/out and runs/default); with
    ``actions`` also ``--actions`` (that default; "" = every action), with ``threads`` also ``--threads``."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--release", default=str(ROOT / "runs" / "default" / "release"))
    parser.add_argument("--capture", default=str(ROOT / "runs" / "default" / "capture"))
    if actions is not None:
        parser.add_argument("--actions", default=actions, help="comma-separated action ids (empty: every action)")
    if threads is not None:
        parser.add_argument("--threads", type=int, default=threads, help="torch and Embree threads")
    return parser


def check_inputs(name: str, release: Path, capture: Path, need_truth: bool) -> tuple[bool, Path | None]:
    """``(go on, ground-truth folder or None)``. Without a release, or without a simulated capture with ground
    truth when ``need_truth``, prints why the bench ``name`` is skipped and returns ``(False, None)``; a
    missing ground truth that is not needed is said once and gives ``(True, None)``."""
    if not (Path(release) / "manifests").is_dir():
        print(f"{name}: no release at {release} (run `make dataset`); skipped")
        return False, None
    truth = Path(capture) / "ground_truth"
    if (Path(capture) / "capture.json").exists() and truth.is_dir():
        return True, truth
    if need_truth:
        print(f"{name}: no simulated capture with ground truth at {capture}: nothing to measure against; skipped")
        return False, None
    print(f"{name}: no ground truth under {capture}: truth metrics skipped")
    return True, None
