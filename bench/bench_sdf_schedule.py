"""Geometry stage schedule: Chamfer against the stage's CPU time over its two SDF passes' step counts.

The geometry stage trains the SDF twice (``geometry.deocclude``): a first pass whose mesh only gives the
body's occlusion of the LED sphere and where it misses the normals, and the published second pass. This
bench runs :class:`stages.geometry.GeometryStage` itself (the stage's ``run``, its configs derived from
``GeometryConfig()`` with ``dataclasses.replace``) on one action of ``runs/default`` (``make dataset``)
for several (first pass, second pass) step counts, and measures the published mesh against the simulator's
(``stages.numerics.meshmetrics.mesh_metrics``: Chamfer in mm, normal consistency, F-score at 1 mm) and the
stage's CPU seconds (one thread, as ``make dataset`` runs it). The Pareto front is marked, and the default
row is the stage default's steps. The stage's footprint rule (``geometry.fine_pixel_m``) is off, so a capture seen
finer than it (``--run`` of a 640 px capture) runs the steps asked; ``steps_run`` are the stage's own record.

Different schedules take different random paths through training: on the default capture two seeds of the
same schedule differ by about 0.05 mm, so read differences below that as noise.

``python bench/bench_sdf_schedule.py --out bench/out [--action A0000] [--workers 2] [--quick]``; ``--quick`` (the
tests' mode): the default and one short schedule on the tiny run of ``bench/_quick.py`` (unless ``--run`` is
given), each with its steps divided by ``QUICK_STEP_DIVISOR``, a coarser hull, fewer steps of the fit to it and the
meshes at 64 and 96 cells (:func:`quick_schedule_config`); the numbers are not measurements.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import write_report  # noqa: E402
from _quick import QUICK_HELP, quick_run  # noqa: E402
from _release import latest_artifact  # noqa: E402

# (first pass steps, second pass steps); the stage default is inserted first.
SCHEDULES = ((600, 1800), (150, 1800), (1800, 1800), (600, 1500), (600, 1200), (400, 1200))
QUICK_SCHEDULES = ((300, 400),)
QUICK_STEP_DIVISOR = 60


def default_config():
    from stages.geometry import GeometryConfig

    return GeometryConfig()


def schedule_config(first: int, second: int):
    """The stage default with the two passes' step counts changed and its footprint rule off (the steps run are the
    ones asked, whatever the subject's pixels)."""
    base = default_config()
    return dataclasses.replace(base, first_pass_iterations=int(first), fine_pixel_m=0.0,
                               sdf=dataclasses.replace(base.sdf, iterations=int(second)))


def quick_schedule_config(first: int, second: int):
    """``--quick``: :func:`schedule_config` with both step counts divided by ``QUICK_STEP_DIVISOR``, the visual
    hull at 48 cells and 20 steps of the fit to it, the first and published meshes at 64 and 96 cells."""
    cfg = schedule_config(max(1, first // QUICK_STEP_DIVISOR), max(1, second // QUICK_STEP_DIVISOR))
    return dataclasses.replace(cfg, first_pass_mesh_resolution=64, mesh_resolution=96,
                               sdf=dataclasses.replace(cfg.sdf, hull_resolution=48, hull_init_steps=20))


def schedules(quick: bool, chosen: list[tuple[int, int]] | None = None) -> list[tuple[int, int]]:
    """The stage's default schedule first, then ``chosen`` (default :data:`SCHEDULES`, or :data:`QUICK_SCHEDULES`
    with ``quick``) without it."""
    base = default_config()
    default = (base.first_pass_iterations or base.sdf.iterations, base.sdf.iterations)
    rest = [s for s in (chosen or (QUICK_SCHEDULES if quick else SCHEDULES)) if s != default]
    return [default] + rest


def parse_schedules(text: str) -> list[tuple[int, int]]:
    """``"600+1800,400+1200"`` -> [(600, 1800), (400, 1200)] (first pass + second pass steps)."""
    pairs = []
    for item in text.split(","):
        first, _, second = item.strip().partition("+")
        if not (first.isdigit() and second.isdigit()):
            raise ValueError(f"--schedules: {item!r} is not FIRST+SECOND steps")
        pairs.append((int(first), int(second)))
    return pairs


def run_schedule(args: tuple[str, str, str, int, int, bool]) -> dict:
    """One schedule: the geometry stage on ``action``, timed, its mesh measured against the truth."""
    import os

    os.environ.setdefault("ULTRASTAGE_NUMERIC_THREADS", "1")
    from pipeline.codecs.mesh import read_ply
    from pipeline.stage import StageContext
    from stages.geometry import GeometryStage
    from stages.numerics.meshmetrics import mesh_metrics

    work, capture, action, first, second, quick = args
    work, capture = Path(work), Path(capture)
    config = quick_schedule_config(first, second) if quick else schedule_config(first, second)
    stage = GeometryStage(config)
    with tempfile.TemporaryDirectory(prefix="bench_sdf_schedule_") as tmp:
        ctx = StageContext(stage="geometry", scope_id=action, session_id="", action_id=action, out_dir=Path(tmp),
                           upstream={"decode": latest_artifact(work, "decode", action),
                                     "photometric": latest_artifact(work, "photometric", action)},
                           raw_inputs={}, rig={}, capture_root=capture)
        wall, cpu = time.perf_counter(), time.process_time()
        stats = stage.run(ctx)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        v, f = read_ply(Path(tmp) / "mesh" / "mesh.ply")
    gv, gf = read_ply(capture / "ground_truth" / action / "mesh.ply")
    m = mesh_metrics(v, f, gv, gf)
    return {"first_pass": first, "second_pass": second, "cpu_s": cpu, "wall_s": wall,
            "steps_run": list(stats["iterations"]),
            "chamfer_mm": float(m["chamfer_mm"]), "normal_consistency": float(m["normal_consistency"]),
            "fscore_1mm": float(m["fscore_1mm"]), "train_s": float(stats["train_seconds"])}


def pareto(rows: list[dict]) -> list[bool]:
    """True for rows no other row beats in both CPU time and Chamfer."""
    return [not any(o is not r and o["cpu_s"] <= r["cpu_s"] and o["chamfer_mm"] <= r["chamfer_mm"]
                    and (o["cpu_s"] < r["cpu_s"] or o["chamfer_mm"] < r["chamfer_mm"]) for o in rows) for r in rows]


def plot(path: Path, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for r in rows:
        colour = "tab:red" if r["default"] else ("tab:blue" if r["pareto"] else "tab:gray")
        ax.scatter(r["cpu_s"], r["chamfer_mm"], color=colour, zorder=3)
        ax.annotate(f"{r['first_pass']}+{r['second_pass']}" + (" (default)" if r["default"] else ""),
                    (r["cpu_s"], r["chamfer_mm"]), textcoords="offset points", xytext=(5, 4), fontsize=8)
    front = sorted((r for r in rows if r["pareto"]), key=lambda r: r["cpu_s"])
    ax.plot([r["cpu_s"] for r in front], [r["chamfer_mm"] for r in front], "--", color="tab:blue", label="Pareto front")
    ax.set_xlabel("geometry stage CPU seconds (one thread)")
    ax.set_ylabel("Chamfer (mm)")
    ax.set_title("SDF schedule: first + second pass steps")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def markdown(report: dict) -> str:
    lines = [f"# Geometry schedule ({report['action']})", "",
             "| first + second pass steps | CPU s | vs 1800+1800 | Chamfer mm | normal consistency | F@1mm | Pareto |",
             "|---|---|---|---|---|---|---|"]
    ref = next((r for r in report["rows"] if (r["first_pass"], r["second_pass"]) == (1800, 1800)), None)
    for r in report["rows"]:
        ratio = f"{r['cpu_s'] / ref['cpu_s']:.2f}x" if ref else "-"
        name = f"{r['first_pass']}+{r['second_pass']}" + (" (default)" if r["default"] else "")
        if list(r["steps_run"]) != [r["first_pass"], r["second_pass"]]:
            name += " (--quick: ran {}+{})".format(*r["steps_run"])
        lines.append(f"| {name} | {r['cpu_s']:.0f} | {ratio} | {r['chamfer_mm']:.3f} | "
                     f"{r['normal_consistency']:.4f} | {100 * r['fscore_1mm']:.1f}% | {'yes' if r['pareto'] else ''} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--run", help="a make dataset run folder (default runs/default; with --quick the tiny run)")
    parser.add_argument("--action", default="A0000")
    parser.add_argument("--workers", type=int, default=2, help="schedules measured side by side (one thread each)")
    parser.add_argument("--schedules", help="FIRST+SECOND step pairs, comma-separated, measured besides the stage's "
                                             "default (default: SCHEDULES)")
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP + "; the default and one short schedule")
    args = parser.parse_args()
    if args.run is None:
        args.run = str(quick_run(Path(args.out)) if args.quick else ROOT / "runs" / "default")
    run = Path(args.run)
    work, capture = run / "release.work", run / "capture"
    if not (work / "artifacts").is_dir() or not (capture / "ground_truth" / args.action / "mesh.ply").exists():
        print(f"bench_sdf_schedule: needs {run} with a work folder and ground truth (make dataset first); skipped")
        return 0
    todo = schedules(args.quick, parse_schedules(args.schedules) if args.schedules else None)
    jobs = [(str(work), str(capture), args.action, first, second, args.quick) for first, second in todo]
    with ProcessPoolExecutor(max_workers=max(1, args.workers)) as pool:
        rows = list(pool.map(run_schedule, jobs))
    for row, flag in zip(rows, pareto(rows)):
        row["pareto"] = flag
    for i, row in enumerate(rows):
        row["default"] = i == 0
    report = {"action": args.action, "quick": args.quick, "rows": rows}
    write_report(args.out, "bench_sdf_schedule", report, markdown(report), lambda path: plot(path, rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
