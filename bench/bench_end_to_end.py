"""End to end: time per action and its split across stages, how it grows with resolution and with the number of
actions, and the share of work a rerun and a new action in a calibrated session skip.

1. **Split across stages** of a release's last run (``manifests/stage_runs.parquet``: per stage and scope, the
   latest row that ran; a per-camera stage's seconds are the sum over its cameras): seconds per action and per
   stage, the session stages (cameras, colour, lights, plates) shown once per session. Default
   ``runs/default/release`` (``make dataset``); skipped without it.
2. **Growth with resolution**: a capture of one action simulated at each of :data:`WIDTHS` (pixels wide) and run
   cold through the whole DAG with the :data:`PRESET` preset (in-process scheduler; the first run also pays the
   numeric libraries' first use, about a second): wall seconds, the sum of the tasks' seconds and the split per
   stage.
3. **Growth with the number of actions**: one capture of ``max(ACTION_COUNTS)`` actions at the smallest width, run
   cold on its first N actions for each N in :data:`ACTION_COUNTS` (fresh work folder each time).
4. **Work skipped**: on that capture, a rerun of the last cold run (every task found in the store) and a **new
   action** in the calibrated session (the run of the second-largest N gets its next action: the session's
   calibration stages are reused): of the tasks the new action needs (the session's and its own), those cached and
   ran (from the runner's task statuses), and the share of their cold task seconds not spent again.

Writes bench_end_to_end.json and .md, and bench_end_to_end.png (stacked bar of the split, seconds against width and
against actions). ``python bench/bench_end_to_end.py --out bench/out [--release runs/default/release]``;
``--quick`` (the tests' mode): the ``test`` preset through ``photometric`` on 4 cameras, widths 32/40/48 and 1-2
actions, the split from the tiny run of ``bench/_quick.py``; the numbers are not measurements.
"""
from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _report import write_report  # noqa: E402
from _quick import QUICK_HELP, quick_run, quick_sim_changes  # noqa: E402

PRESET = "fast"
"""The preset of the scaling runs (full mode): the whole DAG in its cheapest settings."""
WIDTHS = (96, 160, 240)
ACTION_COUNTS = (1, 2, 3)
CAMERAS = 8
QUICK_PRESET, QUICK_WIDTHS, QUICK_ACTION_COUNTS, QUICK_CAMERAS = "test", (32, 40, 48), (1, 2), 4
QUICK_THROUGH = "photometric"
SESSION_STAGES = ("cameras", "colour", "lights", "plates")


def stage_split(release: Path) -> dict:
    """Seconds per (action or session, stage) of the latest run of each task that ran, from stage_runs.parquet."""
    import pandas as pd

    runs = pd.read_parquet(Path(release) / "manifests" / "stage_runs.parquet")
    ran = runs[runs["status"] == "ran"].sort_values("started_at")
    latest = ran.groupby(["stage", "scope_id"], as_index=False).last()
    per_scope: dict[str, dict[str, float]] = {}
    for row in latest.itertuples():
        per_scope.setdefault(row.scope_id, {})[row.stage] = float(row.seconds)
    actions = sorted(s for s, stages in per_scope.items() if not set(stages) <= set(SESSION_STAGES))
    sessions = sorted(set(per_scope) - set(actions))
    per_action = {a: sum(per_scope[a].values()) for a in actions}
    session_s = sum(sum(per_scope[s].values()) for s in sessions)
    return {"release": str(release), "per_scope": per_scope, "actions": actions, "sessions": sessions,
            "seconds_per_action": per_action,
            "mean_seconds_per_action": sum(per_action.values()) / max(len(actions), 1),
            "session_seconds": session_s,
            "session_seconds_per_action": session_s / max(len(actions), 1)}


def run_once(capture: Path, root: Path, preset: str, through: str | None, actions: list[str] | None = None,
             fresh: bool = True) -> dict:
    """One ``run_pipeline`` of the DAG (``through``: only that stage and what it needs); wall seconds, the tasks'
    seconds per stage, ran/cached counts."""
    from ultrastage.run import run_pipeline
    from stages.registry import PRESETS, build_stages

    if fresh:
        shutil.rmtree(root, ignore_errors=True)
    config = PRESETS[preset]
    started = time.perf_counter()
    result = run_pipeline(capture, root / "release", root / "work", build_stages(config, through=through), config,
                          dataclasses.replace(config.execution, scheduler="sync"), actions=actions,
                          echo=lambda line: None, record={"preset": preset})
    wall = time.perf_counter() - started
    failed = {a: s for a, s in result.action_status.items() if s != "ok"}
    if failed:
        raise RuntimeError(f"{capture}: actions failed: {failed} {result.action_errors}")
    per_stage: dict[str, float] = {}
    seconds: dict[str, float] = {}
    for task in result.plan.tasks:
        if task.status == "ran":
            per_stage[task.stage.name] = per_stage.get(task.stage.name, 0.0) + task.seconds
            seconds[f"{task.stage.name}/{task.scope_id}"] = task.seconds
    return {"wall_s": wall, "task_s": sum(per_stage.values()), "stage_s": per_stage, "task_seconds": seconds,
            "ran": sum(t.status == "ran" for t in result.plan.tasks),
            "cached": sum(t.status == "cached" for t in result.plan.tasks),
            "tasks": [f"{t.stage.name}/{t.scope_id}" for t in result.plan.tasks]}


def simulate_capture(path: Path, actions: int, width: int, cameras: int, quick: bool) -> float:
    from synthetic import SimConfig, simulate

    shutil.rmtree(path, ignore_errors=True)
    started = time.perf_counter()
    simulate(path, SimConfig(actions=actions, width=width, n_cameras=cameras,
                             **(quick_sim_changes() if quick else {})))
    return time.perf_counter() - started


def skipped_share(run: dict, cold_task_seconds: dict[str, float]) -> dict:
    """Of the tasks ``run`` needed: how many were cached, and the share of their cold seconds not spent again."""
    needed = run["tasks"]
    reused = sum(cold_task_seconds.get(t, 0.0) for t in needed if t not in run["task_seconds"])
    total = sum(cold_task_seconds.get(t, run["task_seconds"].get(t, 0.0)) for t in needed)
    return {"ran": run["ran"], "cached": run["cached"], "tasks_cached_share": run["cached"] / max(len(needed), 1),
            "seconds_skipped_share": reused / total if total > 0 else 0.0, "wall_s": run["wall_s"]}


def scaling(out: Path, quick: bool) -> dict:
    from stages.registry import PRESETS, build_stages

    preset = QUICK_PRESET if quick else PRESET
    widths = QUICK_WIDTHS if quick else WIDTHS
    counts = QUICK_ACTION_COUNTS if quick else ACTION_COUNTS
    cameras = QUICK_CAMERAS if quick else CAMERAS
    through = QUICK_THROUGH if quick else None
    scratch = out / "end_to_end"
    result = {"preset": preset, "cameras": cameras, "through": through, "by_width": [], "by_actions": []}
    build_stages(PRESETS[preset])  # the stage modules' imports, outside the first timed run
    for width in widths:
        capture = scratch / f"capture_w{width}"
        sim_s = simulate_capture(capture, 1, width, cameras, quick)
        run = run_once(capture, scratch / f"run_w{width}", preset, through)
        result["by_width"].append({"width": width, "simulate_s": sim_s, **{k: run[k] for k in
                                                                         ("wall_s", "task_s", "stage_s")}})
        print(f"width {width}: wall {run['wall_s']:.1f} s, tasks {run['task_s']:.1f} s", flush=True)
    capture = scratch / "capture_actions"
    simulate_capture(capture, max(counts), widths[0], cameras, quick)
    ids = [f"A{i:04d}" for i in range(max(counts))]
    last = None
    for n in counts:
        last = run_once(capture, scratch / f"run_a{n}", preset, through, actions=ids[:n])
        result["by_actions"].append({"actions": n, **{k: last[k] for k in ("wall_s", "task_s", "stage_s")}})
        print(f"{n} actions: wall {last['wall_s']:.1f} s, tasks {last['task_s']:.1f} s", flush=True)
    rerun = run_once(capture, scratch / f"run_a{max(counts)}", preset, through, actions=ids, fresh=False)
    result["rerun"] = skipped_share(rerun, last["task_seconds"])
    # a new action in a calibrated session: the run of the first `before` actions gets one more
    before = counts[-2]
    added = run_once(capture, scratch / f"run_a{before}", preset, through, actions=ids[:before + 1], fresh=False)
    new_tasks = [t for t in added["tasks"]
                 if t.endswith("/" + ids[before]) or t.split("/")[0] in SESSION_STAGES]
    new_only = {**added, "tasks": new_tasks,
                "ran": sum(t in added["task_seconds"] for t in new_tasks),
                "cached": sum(t not in added["task_seconds"] for t in new_tasks)}
    result["new_action"] = skipped_share(new_only, last["task_seconds"])
    result["new_action"]["all_tasks"] = skipped_share(added, last["task_seconds"])
    for label in ("rerun", "new_action"):
        r = result[label]
        print(f"{label}: {r['cached']} tasks cached, {r['ran']} ran; {100 * r['seconds_skipped_share']:.0f}% of "
              f"the cold seconds skipped", flush=True)
    shutil.rmtree(scratch, ignore_errors=True)
    return result


def pipeline_order(names: set[str]) -> list[str]:
    """``names`` in the order of the pipeline's stage list (unknown names last, sorted)."""
    from stages.registry import STAGE_CLASSES

    order = [cls.name for cls in STAGE_CLASSES]
    return [n for n in order if n in names] + sorted(names - set(order))


def plot(path: Path, report: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    split = report.get("split")
    if split:
        bars = {a: split["per_scope"][a] for a in split["actions"]}
        bars["session (once)"] = {s: v for sid in split["sessions"] for s, v in split["per_scope"][sid].items()}
        stages = pipeline_order({s for b in bars.values() for s in b})
        bottom = [0.0] * len(bars)
        for k, stage in enumerate(stages):
            values = [b.get(stage, 0.0) for b in bars.values()]
            axes[0].bar(list(bars), values, bottom=bottom, label=stage, color=plt.cm.tab20(k % 20))
            bottom = [x + v for x, v in zip(bottom, values)]
        axes[0].set_ylabel("task seconds")
        axes[0].set_title(f"split across stages ({Path(split['release']).parent.name})", fontsize=9)
        axes[0].legend(fontsize=6, ncol=2)
    scale = report["scaling"]
    for ax, key, x_name in ((axes[1], "by_width", "width"), (axes[2], "by_actions", "actions")):
        rows = scale[key]
        xs = [r[x_name] for r in rows]
        ax.plot(xs, [r["wall_s"] for r in rows], "o-", label="wall")
        ax.plot(xs, [r["task_s"] for r in rows], "s--", label="sum of task seconds")
        ax.set_xlabel("capture width (px)" if x_name == "width" else "actions")
        ax.set_ylabel("seconds")
        ax.set_title(f"preset {scale['preset']}, {scale['cameras']} cameras, cold", fontsize=9)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def markdown(report: dict) -> str:
    lines = ["# End to end", ""]
    split = report.get("split")
    if split:
        stages = pipeline_order({s for a in split["actions"] for s in split["per_scope"][a]})
        lines += [f"Split across stages of {split['release']} (task seconds of its latest run per task; the session "
                  f"stages once per session: {split['session_seconds']:.1f} s, "
                  f"{split['session_seconds_per_action']:.1f} s per action):", "",
                  "| action | total s | " + " | ".join(stages) + " |", "|---|---|" + "---|" * len(stages)]
        for a in split["actions"]:
            lines.append(f"| {a} | {split['seconds_per_action'][a]:.1f} | "
                         + " | ".join(f"{split['per_scope'][a].get(s, 0.0):.1f}" for s in stages) + " |")
        lines.append("")
    scale = report["scaling"]
    through = f" through `{scale['through']}`" if scale.get("through") else ""
    lines += [f"Cold runs, preset `{scale['preset']}`{through}, {scale['cameras']} cameras, in-process scheduler:", "",
              "| capture | wall s | task s | x smallest |", "|---|---|---|---|"]
    base = scale["by_width"][0]["wall_s"]
    for r in scale["by_width"]:
        lines.append(f"| 1 action, {r['width']} px | {r['wall_s']:.1f} | {r['task_s']:.1f} | "
                     f"{r['wall_s'] / base:.2f} |")
    base = scale["by_actions"][0]["wall_s"]
    for r in scale["by_actions"]:
        plural = "s" if r["actions"] > 1 else ""
        lines.append(f"| {r['actions']} action{plural}, {scale['by_width'][0]['width']} px | {r['wall_s']:.1f} | "
                     f"{r['task_s']:.1f} | {r['wall_s'] / base:.2f} |")
    lines += ["", "| work skipped | tasks cached | tasks ran | share of the cold task seconds skipped | wall s |",
              "|---|---|---|---|---|"]
    for label, name in (("rerun", "rerun, nothing changed"), ("new_action", "a new action in a calibrated session")):
        r = scale[label]
        lines.append(f"| {name} | {r['cached']} | {r['ran']} | {100 * r['seconds_skipped_share']:.1f}% | "
                     f"{r['wall_s']:.1f} |")
    lines += ["", "The new action's row counts the tasks it needs (the session's and its own); its wall time is the "
              "whole run's."]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--release", help="the release whose stage split is shown (default runs/default/release; "
                                          "with --quick the tiny run's)")
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.release is None:
        args.release = str(quick_run(out) / "release" if args.quick else ROOT / "runs" / "default" / "release")
    report: dict = {"quick": args.quick}
    if (Path(args.release) / "manifests" / "stage_runs.parquet").exists():
        report["split"] = stage_split(Path(args.release))
    else:
        print(f"bench_end_to_end: no release at {args.release} (make dataset): no stage split", flush=True)
    report["scaling"] = scaling(out, args.quick)
    write_report(out, "bench_end_to_end", report, markdown(report), lambda path: plot(path, report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
