"""``ultrastage``: the command line (thin: parse, call an action, print)."""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

from pipeline.errors import ConfigError, InputError


def _resolve_config(preset: str, config_file: str | None, scheduler: str | None) -> Any:
    from pipeline.config import load_overrides, merge
    from pipeline.runner import ExecutionConfig
    from stages.registry import PRESETS

    if preset not in PRESETS:
        raise ConfigError(f"--preset {preset}: unknown preset; presets are {sorted(PRESETS)}")
    config = PRESETS[preset]
    if config_file:
        config = merge(config, load_overrides(config_file), where=str(config_file))
    if scheduler:
        import dataclasses

        config = dataclasses.replace(config, execution=dataclasses.replace(config.execution, scheduler=scheduler))
    assert isinstance(config.execution, ExecutionConfig)
    return config


def _progress_printer() -> tuple[Any, Any, Any]:
    """Callbacks for stage completions (one line each), camera completions (a live status line on a
    terminal; in a log, one line per tenth of the cameras) and what long tasks report (one line each)."""
    start = time.perf_counter()
    tty = sys.stdout.isatty()
    state = {"tenth": -1}

    def on_progress(record: dict) -> None:
        if tty:
            print("\r" + " " * 100 + "\r", end="")
        total = max(int(record.get("total", 0)), 1)
        print(f"  {record.get('stage', '?'):<12} {record.get('scope_id', '?'):<8} {record.get('done', 0)}/{total} "
              f"({100 * int(record.get('done', 0)) / total:.0f}%) {record.get('message', '')}, "
              f"{time.perf_counter() - start:.0f}s", flush=True)

    def on_view(task: Any, result: dict, done: int, total: int) -> None:
        line = f"  cameras {done}/{total} ({100 * done / total:.0f}%), {time.perf_counter() - start:.0f}s"
        if tty:
            print(f"\r{line}  last: {task.stage.name} {task.scope_id}/{result.get('view')}   ", end="", flush=True)
        elif (tenth := 10 * done // total) > state["tenth"]:
            state["tenth"] = tenth
            print(line, flush=True)

    def on_done(task: Any, result: dict, done: int, total: int) -> None:
        if tty:
            print("\r" + " " * 100 + "\r", end="")
        status = "ok" if result.get("ok") else ("skipped" if result.get("skipped") else "FAILED")
        extra = "" if result.get("ok") else f": {result.get('error')}"
        print(f"  [{done:>3}/{total}] {time.perf_counter() - start:6.1f}s  {task.stage.name:<12} "
              f"{task.scope_id:<8} {status} ({result.get('seconds', 0.0):.1f}s cpu){extra}", flush=True)

    return on_done, on_view, on_progress


def _summary(result: Any, metrics: dict[str, dict[str, float]] | None) -> None:
    from rich.console import Console
    from rich.table import Table

    stage_names = list(dict.fromkeys(t.stage.name for t in result.plan.tasks))
    table = Table(title=f"run {result.run_id}: {len(result.published)} action(s) published, "
                        f"{sum(s == 'failed' for s in result.action_status.values())} failed, "
                        f"{result.seconds:.1f}s wall ({result.executor})")
    table.add_column("action")
    for name in stage_names:
        table.add_column(name, justify="right")
    metric_cols = [("normal_mean_deg", "normal err °"), ("normal_under5_pct", "<5° %"),
                   ("valid_fraction", "valid"), ("albedo_psnr_db", "albedo dB"), ("chamfer_mm", "chamfer mm"),
                   ("roughness_mae", "rough MAE"), ("relit_psnr_db", "relit dB")]
    if metrics:
        for _, title in metric_cols:
            table.add_column(title, justify="right")
    scopes = list(dict.fromkeys(t.scope_id for t in result.plan.tasks))
    for scope in scopes:
        cells = []
        for name in stage_names:
            task = next((t for t in result.plan.tasks if t.scope_id == scope and t.stage.name == name), None)
            if task is None:
                cells.append("")
            elif task.status == "ran":
                cells.append(f"ran {task.seconds:.1f}s" if task.seconds < 100 else f"ran {task.seconds:.0f}s")
            elif task.status == "cached":
                cells.append("cached")
            else:
                cells.append(f"[red]{task.status}[/red]")
        if metrics:
            m = metrics.get(scope, {})
            cells += [f"{m[k]:.2f}" if k in m else "" for k, _ in metric_cols]
        table.add_row(scope, *cells)
    console = Console(width=max(190, Console().width))
    console.print(table)
    for action, error in result.action_errors.items():
        console.print(f"[red]action {action} failed[/red]: {error}", markup=True, highlight=False)


def cmd_simulate(args: argparse.Namespace) -> int:
    import dataclasses
    import shutil

    from pipeline.store import swap_into_place
    from synthetic import SimConfig, simulate
    from synthetic.calibration import CalibrationConfig

    overrides = {k: v for k, v in {"mesh": args.mesh, "actions": args.actions, "width": args.width,
                                   "seed": args.seed, "pose_variation": args.pose_variation}.items()
                 if v is not None}
    try:
        config = dataclasses.replace(SimConfig(), **overrides)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    out = Path(args.out)
    index = out / "capture.json"
    calibration = CalibrationConfig()  # chart and diffuse-sphere frames for the session stages
    wanted = json.loads(json.dumps({"simulator": config.to_json(), "simulator_calibration": calibration.to_json()}))
    if index.exists() and not args.force:
        try:
            meta = json.loads(index.read_text())
        except json.JSONDecodeError:
            meta = {}
        if {k: meta.get(k) for k in wanted} == wanted:
            print(f"capture {out} is up to date with these simulator settings: skipped (--force to redo)")
            return 0
    # Render beside the target and swap it in, so an interrupted run never leaves half a capture.
    tmp = out.with_name(f".{out.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    start = time.perf_counter()
    simulate(tmp, config, progress=lambda msg: print(f"  {msg}", flush=True), calibration=calibration)
    out.parent.mkdir(parents=True, exist_ok=True)
    swap_into_place(tmp, out)
    print(f"simulated capture written to {out} in {time.perf_counter() - start:.1f}s")
    return 0


def _work_dir(args: argparse.Namespace, release: Path) -> Path:
    return Path(args.work) if args.work else release.with_name(release.name + ".work")


def cmd_run(args: argparse.Namespace, plan_only: bool = False) -> int:
    from pipeline.runner import run_pipeline
    from stages.registry import build_stages

    config = _resolve_config(args.preset, args.config, args.scheduler)
    release = Path(args.release)
    work = _work_dir(args, release)
    stages = build_stages(config)
    actions = args.actions.split(",") if args.actions else None
    if plan_only:
        from pipeline.capture import open_capture
        from pipeline.graph import downstream_of, make_plan
        from pipeline.hashing import DigestCache
        from pipeline.store import ArtifactStore

        capture = open_capture(args.capture)
        force = {args.only} if args.only else (downstream_of(stages, args.from_stage) if args.from_stage else set())
        plan = make_plan(capture, stages, ArtifactStore(work / "artifacts"), DigestCache(work / "digests.json"),
                         actions=actions, force=force, echo=print)
        counts = {s: sum(t.status == s for t in plan.tasks) for s in ("run", "cached", "failed", "blocked")}
        print("plan: " + ", ".join(f"{v} {k}" for k, v in counts.items()))
        return 0
    on_done, on_view, on_progress = _progress_printer()
    result = run_pipeline(Path(args.capture), release, work, stages, config, config.execution,
                          only=args.only, from_stage=args.from_stage, actions=actions,
                          progress=on_done, view_progress=on_view, stage_progress=on_progress)
    (release / "run.json").write_text(json.dumps({"run_id": result.run_id, "capture": str(Path(args.capture).resolve()),
                                                  "work": str(work.resolve()), "preset": args.preset}, indent=1))
    metrics = None
    truth = Path(args.capture) / "ground_truth"
    if not args.no_evaluate and truth.is_dir() and result.published:
        from stages.evaluate import evaluate_release_cached

        summary, cached = evaluate_release_cached(release, truth, work, run_id=result.run_id)
        print(f"{'evaluate':<12} {'release':<8} {'cached  release unchanged since its last evaluation' if cached else 'ran'}")
        metrics = summary.per_action
        result.metrics = metrics
    _summary(result, metrics)
    if metrics:
        from stages.evaluate import print_overall

        print_overall(summary)
    return 0 if all(s == "ok" for s in result.action_status.values()) else 3


def cmd_rerun(args: argparse.Namespace) -> int:
    release = Path(args.release)
    info_path = release / "run.json"
    if not info_path.exists():
        raise InputError(info_path, "no run record: this folder was not written by `ultrastage run`")
    info = json.loads(info_path.read_text())
    ns = argparse.Namespace(capture=info["capture"], release=str(release), work=info["work"],
                            preset=info.get("preset", "default"), config=args.config or None,
                            scheduler=args.scheduler, only=args.only, from_stage=args.from_stage,
                            actions=args.actions, no_evaluate=args.no_evaluate)
    if args.config is None and (release / "config.yaml").exists():
        ns.config = str(release / "config.yaml")
    return cmd_run(ns)


def cmd_evaluate(args: argparse.Namespace) -> int:
    from stages.evaluate import evaluate_release, print_overall

    summary = evaluate_release(Path(args.release), Path(args.truth))
    print_overall(summary)
    if args.json:
        Path(args.json).write_text(json.dumps(summary.overall, indent=1, sort_keys=True))
        print(f"wrote {args.json}")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from calibration.geometric import calibrate_folder

    result = calibrate_folder(Path(args.images), Path(args.out), Path(args.intrinsics) if args.intrinsics else None)
    print(f"registered {len(result.cameras)} image(s), {len(result.unregistered)} not registered"
          f"{': ' + ', '.join(result.unregistered) if result.unregistered else ''}; "
          f"mean reprojection error {result.reprojection_error_px:.3f} px")
    print(f"wrote {Path(args.out) / 'transforms.json'} and {Path(args.out) / 'colmap'}")
    return 0 if not result.unregistered else 3


def cmd_verify(args: argparse.Namespace) -> int:
    from manifests import verify_release

    report = verify_release(Path(args.release))
    print(f"checked {report.n_checked} asset(s): {len(report.missing)} missing, "
          f"{len(report.mismatched)} changed, {len(report.extra)} not in the manifest")
    for label, items in (("missing", report.missing), ("changed", report.mismatched), ("extra", report.extra)):
        for item in items[:50]:
            print(f"  {label}: {item}")
    print("OK" if report.ok else "FAILED")
    return 0 if report.ok else 1


def _add_run_args(p: argparse.ArgumentParser, capture_required: bool = True) -> None:
    p.add_argument("--capture", required=capture_required, help="capture folder (capture.json inside)")
    p.add_argument("--release", required=True, help="release folder to write")
    p.add_argument("--work", help="artifact store and run logs (default: <release>.work beside the release)")
    p.add_argument("--preset", default="default", help="config preset: default, production (GPU, full-resolution captures), fast (quick looks), test (tiny captures)")
    p.add_argument("--config", help="YAML overrides, e.g. {decode: {demosaic: DCB}}; unknown keys are errors")
    p.add_argument("--scheduler", help="'local', 'sync' or a dask scheduler address")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--only", help="force this stage to rerun (its dependents rerun only if their keys change)")
    group.add_argument("--from", dest="from_stage", help="force this stage and everything downstream")
    p.add_argument("--actions", help="comma-separated action ids (default: all)")
    p.add_argument("--no-evaluate", action="store_true", help="skip the accuracy summary against ground truth")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ultrastage", description="UltraStage light-stage dataset pipeline")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging (tracebacks of failures)")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="render a synthetic raw capture with ground truth")
    p.add_argument("--out", required=True, help="capture folder to write")
    p.add_argument("--mesh", help="subject mesh (OBJ, PLY, glTF/GLB, STL, OFF; 'procedural' for the built-in "
                   "subject); default: the MakeHuman body in ../shared, else procedural")
    p.add_argument("--pose-variation", type=float, metavar="X",
                   help="0..1: how far each action's pose departs from the rest A-pose (default 0; "
                        "MakeHuman subject only)")
    p.add_argument("--actions", type=int, help="number of actions")
    p.add_argument("--width", type=int, help="image width in pixels (height follows the D750's 2:3 portrait)")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument("--force", action="store_true", help="render again even if the capture is up to date")
    p.set_defaults(fn=cmd_simulate)

    p = sub.add_parser("run", help="run the DAG on a capture and write the release")
    _add_run_args(p)
    p.set_defaults(fn=cmd_run)

    p = sub.add_parser("plan", help="show what `run` would do (cached / run and why) without running it")
    _add_run_args(p)
    p.set_defaults(fn=lambda a: cmd_run(a, plan_only=True))

    p = sub.add_parser("rerun", help="run again with the capture, work folder and config a release records")
    p.add_argument("release")
    p.add_argument("--config", help="YAML overrides (default: the release's config.yaml)")
    p.add_argument("--scheduler")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--only")
    group.add_argument("--from", dest="from_stage")
    p.add_argument("--actions")
    p.add_argument("--no-evaluate", action="store_true")
    p.set_defaults(fn=cmd_rerun)

    p = sub.add_parser("evaluate", help="accuracy of a release against ground truth")
    p.add_argument("--release", required=True)
    p.add_argument("--truth", required=True, help="CAPTURE/ground_truth")
    p.add_argument("--json", help="also write one flat JSON object of metric name to number")
    p.set_defaults(fn=cmd_evaluate)

    p = sub.add_parser("calibrate", help="calibrate the cameras of any folder of photos (pycolmap)")
    p.add_argument("--images", required=True, help="folder of photos (PNG/JPEG/TIFF or raw)")
    p.add_argument("--out", required=True, help="folder for transforms.json and the COLMAP text model")
    p.add_argument("--intrinsics", help="JSON with known K (shared or per image); see calibration.geometric")
    p.set_defaults(fn=cmd_calibrate)

    p = sub.add_parser("verify", help="re-check every asset of a release against its sha256")
    p.add_argument("release")
    p.set_defaults(fn=cmd_verify)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.fn(args) or 0)
    except (InputError, ConfigError, ValueError) as exc:
        if args.verbose:  # a developer wants the traceback, a user the one-line reason
            raise
        print(f"ultrastage {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
