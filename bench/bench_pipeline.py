"""End-to-end: the default capture through the whole DAG, cold, cached, and after one config change.

Reports wall time per run and per stage, the ratio of a fully cached rerun to the cold run (goal: close
to 0, the rerun only plans), and the accuracy the cold run reached. Writes bench_pipeline.json and
bench_pipeline.png. ``--quick`` (the tests' mode): 1 action, 4 cameras 64 px wide, 128 LEDs, the subject
unsubdivided, the pipeline only through ``photometric``; the numbers are not measurements.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _quick import QUICK_HELP, quick_sim_changes  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="bench/out")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--actions", type=int, default=2)
    parser.add_argument("--scheduler", default="local")
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    if args.quick:
        args.width, args.actions = 64, 1
    sim_changes = {"n_cameras": 4, **quick_sim_changes()} if args.quick else {}
    through = "photometric" if args.quick else None
    out = Path(args.out)
    root = out / "pipeline_run"
    shutil.rmtree(root, ignore_errors=True)

    from pipeline.runner import ExecutionConfig
    from evaluation.release import evaluate_release
    from stages.numerics.photometric import PhotometricParams
    from stages.registry import PRESETS, build_stages
    from ultrastage.run import run_pipeline
    from synthetic import SimConfig, simulate

    start = time.perf_counter()
    simulate(root / "capture", SimConfig(actions=args.actions, width=args.width, **sim_changes))
    simulate_s = time.perf_counter() - start
    execution = ExecutionConfig(scheduler=args.scheduler)
    config = PRESETS["default"]
    changed = dataclasses.replace(config, photometric=dataclasses.replace(
        config.photometric, params=dataclasses.replace(PhotometricParams(), ratio_min=0.35)))
    runs = {}
    for label, cfg in (("cold", config), ("cached", config), ("photometric_changed", changed)):
        t0 = time.perf_counter()
        result = run_pipeline(root / "capture", root / "release", root / "work", build_stages(cfg, through=through),
                              cfg, execution, echo=lambda line: None)
        wall = time.perf_counter() - t0
        per_stage: dict[str, float] = {}
        for task in result.plan.tasks:
            per_stage[task.stage.name] = per_stage.get(task.stage.name, 0.0) + (task.seconds if task.status == "ran" else 0.0)
        runs[label] = {"wall_s": wall, "stage_cpu_s": per_stage,
                       "ran": sum(t.status == "ran" for t in result.plan.tasks),
                       "cached": sum(t.status == "cached" for t in result.plan.tasks)}
        print(f"{label:<20} wall {wall:7.2f}s  ran {runs[label]['ran']:>2}  cached {runs[label]['cached']:>2}  "
              f"stage cpu {json.dumps({k: round(v, 1) for k, v in per_stage.items()})}", flush=True)
    # re-run the original config so the release evaluated is the default one
    run_pipeline(root / "capture", root / "release", root / "work", build_stages(config, through=through), config,
                 execution, echo=lambda line: None)
    accuracy = evaluate_release(root / "release", root / "capture" / "ground_truth").overall
    report = {"quick": args.quick, "width": args.width, "actions": args.actions, "simulate_s": simulate_s, "runs": runs,
              "cached_over_cold": runs["cached"]["wall_s"] / runs["cold"]["wall_s"],
              "accuracy": accuracy}
    (out / "bench_pipeline.json").write_text(json.dumps(report, indent=1))
    print(f"simulate {simulate_s:.1f}s; cached/cold wall ratio {report['cached_over_cold']:.3f}")
    print(f"accuracy: normal mean {accuracy['normal_mean_deg']:.2f} deg (valid), "
          f"unoccluded {accuracy['normal_mean_deg_unoccluded']:.2f}, occluded {accuracy['normal_mean_deg_occluded']:.2f}, "
          f"valid fraction {accuracy['valid_fraction']:.3f}, albedo {accuracy['albedo_psnr_db']:.2f} dB")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 3.5))
        labels = list(runs)
        stages = sorted({s for r in runs.values() for s in r["stage_cpu_s"]})
        bottom = [0.0] * len(labels)
        for stage in stages:
            vals = [runs[label]["stage_cpu_s"].get(stage, 0.0) for label in labels]
            ax.bar(labels, vals, bottom=bottom, label=stage)
            bottom = [b + v for b, v in zip(bottom, vals)]
        ax.plot(labels, [runs[label]["wall_s"] for label in labels], "ko-", label="wall")
        ax.set_ylabel("seconds")
        ax.set_title(f"default capture ({args.actions} actions, {args.width}px): stage CPU s and wall s")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "bench_pipeline.png", dpi=110)
    except ImportError:
        pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
