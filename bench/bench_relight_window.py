"""Relit novel views rendered in the subject's window: peak memory and CPU seconds of one view against its size.

:func:`stages.numerics.novel_view.relight_view` renders only the rows and columns the mesh can cover
(:func:`stages.numerics.novel_view.subject_window`: its projected vertices' box and 3 pixels) and puts them into the
frame; ``crop=False`` renders every pixel of the frame, the baseline here. For one action of a release (default
A0000) and its first novel camera (``renders/cameras.json``), the camera is scaled to 1, 2 and 4 times its size
(``--scales``; intrinsics and image together; the asset's sources stay the release's) and the view is rendered
with the stage's shading (:class:`stages.relight.RelightConfig`'s ``shading``: ``supersample`` 2, so the shading
runs on a grid 4 x the pixels; ``--supersample`` sets another factor) under as many SG environments as the stage
renders, each of the stage's lobe count (seeded random lobes: the cost does not depend on their values). Each render runs in a fresh process under a watcher that reads
its peak resident set (``getrusage(RUSAGE_CHILDREN).ru_maxrss``); the child reports its own peak after loading the
asset, so ``above the asset`` is what the view itself adds. Both renders' first image and alpha are compared: the
window is exact when they agree. The sources' share of their frames and their bytes are reported beside.

``python bench/bench_relight_window.py --out DIR [--release DIR --capture DIR --actions A0000 --scales 1,2,4
--threads 2 --supersample N]`` writes DIR/bench_relight_window.json and .md. ``--quick`` (the tests' mode): the tiny
run of ``bench/_quick.py`` at scale 1 only; the numbers are not measurements.
"""
from __future__ import annotations

import dataclasses
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_memory import WATCHER  # noqa: E402  (the watcher that reports one child's peak resident set)

MODES = ("window", "whole")


def child(release: Path, action: str, scale: int, mode: str, threads: int, out_npz: Path, info: Path,
          supersample: int | None = None) -> None:
    """Render the scaled view in this process; write its first image and alpha to ``out_npz`` and the figures to
    ``info``."""
    from _threads import set_numeric_threads

    set_numeric_threads(threads)
    from manifests import release_artifacts
    from stages.numerics.novel_view import relight_view, subject_window
    from stages.numerics.sg import SGLobes, fibonacci_sphere
    from stages.relight import RelightConfig
    from stages.relightable import load_relightable_asset

    config = RelightConfig()
    if supersample is not None:
        config = dataclasses.replace(config, shading=dataclasses.replace(config.shading, supersample=supersample))
    artifacts = release_artifacts(release, action)
    asset, cameras = load_relightable_asset(artifacts, config.min_alpha, config.diffuse_normals, config.diffuse_albedo)
    cam = artifacts.backend.view.render_cameras()[0]
    K = np.array(cam["K"], np.float64)
    K[:2] *= scale
    # pixel centres at integer coordinates: the coarse grid's pixel j is the scaled grid's scale j + (scale - 1) / 2
    K[:2, 2] += (scale - 1) / 2.0
    h, w = int(cam["height"]) * scale, int(cam["width"]) * scale
    pose = np.array(cam["cam_from_world"], np.float64)
    rng = np.random.default_rng(0)
    environments = []
    for _ in config.environments:
        axes = rng.normal(size=(config.sg_lobes, 3))
        environments.append(SGLobes((axes / np.linalg.norm(axes, axis=1, keepdims=True)).astype(np.float32),
                                    rng.uniform(2.0, 60.0, config.sg_lobes).astype(np.float32),
                                    rng.uniform(0.0, 2.0, (config.sg_lobes, 3)).astype(np.float32)))
    loaded_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    cpu0, wall0 = time.process_time(), time.perf_counter()
    view = relight_view(asset, K, pose, h, w, environments, config.shading,
                        directions=fibonacci_sphere(config.shading.visibility_directions), crop=mode == "window")
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    row0, row1, col0, col1 = subject_window(asset.vertices, K, pose, h, w)
    np.savez(out_npz, image=view["images"][0], alpha=view["alpha"])
    frames = sum(c.width * c.height for c in cameras.values())
    source_bytes = sum(getattr(src, name).nbytes for src in asset.sources
                       for name in ("normal", "albedo", "valid", "depth_m"))
    info.write_text(json.dumps({"size": [w, h], "pixels": view["pixels"],
                                "window_share": (row1 - row0) * (col1 - col0) / (h * w),
                                "sources": len(asset.sources), "source_mib": source_bytes / 2 ** 20,
                                "source_share": sum(src.valid.size for src in asset.sources) / frames,
                                "source_frame_bytes": source_bytes / sum(src.valid.size for src in asset.sources),
                                "environments": len(environments), "loaded_mib": loaded_kib / 1024,
                                "cpu_s": cpu, "wall_s": wall}))


def measure(args, action: str, scale: int, mode: str, folder: Path) -> dict:
    """One render in a watched child: its figures, peak RSS (MiB) and the file of its image."""
    stem = folder / f"{action}_x{scale}_{mode}"
    rss, info, npz = stem.with_suffix(".rss.json"), stem.with_suffix(".json"), stem.with_suffix(".npz")
    subprocess.run([sys.executable, "-c", WATCHER, str(rss), sys.executable, str(Path(__file__).resolve()), "--child",
                    "--release", str(args.release), "--actions", action, "--scale", str(scale), "--mode", mode,
                    "--threads", str(args.threads), "--npz", str(npz), "--info", str(info),
                    *(["--supersample", str(args.supersample)] if args.supersample else [])], check=True, cwd=ROOT)
    watched = json.loads(rss.read_text())
    if watched["rc"]:
        raise RuntimeError(f"bench_relight_window: {action} x{scale} {mode}: exit {watched['rc']}")
    row = json.loads(info.read_text())
    row["peak_rss_mib"] = watched["maxrss_kib"] / 1024
    row["above_asset_mib"] = max(row["peak_rss_mib"] - row["loaded_mib"], 0.0)
    row["npz"] = str(npz)
    return row


def compare(window: dict, whole: dict) -> dict:
    """The two renders' largest differences: image (relative to the whole frame's brightest value) and alpha."""
    a, b = np.load(window["npz"]), np.load(whole["npz"])
    scale = max(float(np.abs(b["image"]).max()), 1e-12)
    return {"image_max_rel": float(np.abs(a["image"] - b["image"]).max() / scale),
            "alpha_max_abs": float(np.abs(a["alpha"] - b["alpha"]).max())}


def markdown(report: dict) -> str:
    scales = ", ".join(f"{row['scale']} x" for row in report["rows"])
    lines = ["# Relit views in the subject's window", "",
             f"One novel view ({report['action']}, first camera of `renders/cameras.json`) scaled {scales} and "
             f"rendered by `relight_view` with the stage's shading (supersample {report['supersample']}, "
             f"{report['visibility_directions']} visibility directions) under {report['environments']} SG "
             "environments, once in the subject's window and once over the whole frame, each in a fresh process "
             f"({report['threads']} threads). `above the asset`: the peak RSS less the child's peak after loading the "
             "asset (the view's own memory).", "",
             "| scale | view | subject pixels | window share | MiB above the asset: window / whole | "
             "peak RSS MiB: window / whole | CPU s: window / whole | x_whole (memory, CPU) | largest difference "
             "(image rel., alpha) |", "|---|---|---|---|---|---|---|---|---|"]
    for row in report["rows"]:
        win, whole = row["window"], row["whole"]
        mem = whole["above_asset_mib"] / max(win["above_asset_mib"], 1e-9)
        lines.append(f"| {row['scale']} | {win['size'][0]} x {win['size'][1]} | {win['pixels']} | "
                     f"{win['window_share']:.2f} | {win['above_asset_mib']:.0f} / {whole['above_asset_mib']:.0f} | "
                     f"{win['peak_rss_mib']:.0f} / {whole['peak_rss_mib']:.0f} | {win['cpu_s']:.1f} / "
                     f"{whole['cpu_s']:.1f} | {mem:.2f}, {whole['cpu_s'] / max(win['cpu_s'], 1e-9):.2f} | "
                     f"{row['difference']['image_max_rel']:.1e}, {row['difference']['alpha_max_abs']:.1e} |")
    first = report["rows"][0]["window"]
    lines += ["", f"The asset's {first['sources']} sources (each cut to the part of its frame the mesh can cover, "
                  f"`stages.relightable.windowed_source`) hold {first['source_share']:.0%} of their frames' pixels at "
                  f"{first['source_frame_bytes']:.0f} bytes each: {first['source_mib']:.0f} MiB."]
    return "\n".join(lines) + "\n"


def main() -> int:
    from _release import check_inputs, parse_release_args, release_parser

    parser = release_parser(__doc__, actions="A0000", threads=2)
    parser.add_argument("--scales", default="1,2,4", help="comma-separated integer scales of the view")
    parser.add_argument("--supersample", type=int, default=None,
                        help="the shading's supersample factor (default: the relight stage's)")
    parser.add_argument("--child", action="store_true", help=argparse_hidden())
    parser.add_argument("--scale", type=int, default=1, help=argparse_hidden())
    parser.add_argument("--mode", choices=MODES, default="window", help=argparse_hidden())
    parser.add_argument("--npz", help=argparse_hidden())
    parser.add_argument("--info", help=argparse_hidden())
    if "--child" in sys.argv:
        args = parser.parse_args()
        child(Path(args.release), args.actions, args.scale, args.mode, args.threads, Path(args.npz), Path(args.info),
              args.supersample)
        return 0
    args = parse_release_args(parser)
    release, out = Path(args.release), Path(args.out)
    if not check_inputs("bench_relight_window", release, Path(args.capture), need_truth=False)[0]:
        return 0
    from manifests import open_release
    from stages.relight import RelightConfig

    action = args.actions.split(",")[0]
    if action not in open_release(release).action_ids or not open_release(release).action(action).render_cameras():
        print(f"bench_relight_window: {release} has no renders/ for {action}; skipped")
        return 0
    scales = [1] if args.quick else [int(s) for s in args.scales.split(",")]
    if any(s < 1 for s in scales):
        parser.error(f"--scales must be positive integers, got {args.scales}")
    if args.supersample is not None and args.supersample < 1:
        parser.error(f"--supersample must be >= 1, got {args.supersample}")
    folder = out / "bench_relight_window"
    folder.mkdir(parents=True, exist_ok=True)
    config = RelightConfig()
    report = {"action": action, "threads": args.threads, "quick": args.quick,
              "supersample": args.supersample or config.shading.supersample,
              "visibility_directions": config.shading.visibility_directions,
              "environments": len(config.environments), "rows": []}
    started = time.perf_counter()
    for scale in scales:
        runs = {}
        for mode in MODES:
            runs[mode] = measure(args, action, scale, mode, folder)
            print(f"x{scale} {mode}: {runs[mode]['size'][0]} x {runs[mode]['size'][1]}, peak "
                  f"{runs[mode]['peak_rss_mib']:.0f} MiB ({runs[mode]['above_asset_mib']:.0f} above the asset), "
                  f"{runs[mode]['cpu_s']:.1f} CPU s", flush=True)
        difference = compare(runs["window"], runs["whole"])
        for run in runs.values():
            Path(run.pop("npz")).unlink()
        report["rows"].append({"scale": scale, **runs, "difference": difference})
    report["total_s"] = round(time.perf_counter() - started, 1)
    (out / "bench_relight_window.json").write_text(json.dumps(report, indent=1))
    (out / "bench_relight_window.md").write_text(markdown(report))
    print(markdown(report))
    return 0


def argparse_hidden() -> str:
    import argparse

    return argparse.SUPPRESS


if __name__ == "__main__":
    sys.exit(main())
