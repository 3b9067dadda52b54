"""``ultrastage``: the command line (thin: parse, call an action, print)."""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

from pipeline.errors import ConfigError, InputError, WriteError


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


SUMMARY_WIDTH = 100
"""Columns the run summary is laid out for (a terminal's default is 80-120)."""

SUMMARY_METRICS = (("normal_mean_deg", "normal°"), ("normal_under5_pct", "<5°%"), ("valid_fraction", "valid"),
                   ("albedo_psnr_db", "alb dB"), ("chamfer_mm", "cham mm"), ("roughness_mae", "rough"),
                   ("relit_psnr_db", "relit dB"))
"""(metric key of the evaluation's per-action summary, column title) shown per row when there is truth."""


def _scope_outcome(tasks: list[Any]) -> tuple[str, float]:
    """One cell for a scope's tasks: "3 ran, 9 cached", or the stage that failed ("FAILED decode"; the
    error is printed below the table), and the seconds its tasks took."""
    seconds = float(sum(t.seconds for t in tasks))
    failed = [t for t in tasks if t.status == "failed"]
    skipped = [t for t in tasks if t.status in ("skipped", "blocked")]
    if failed:
        return f"[red]FAILED {failed[0].stage.name}[/red]", seconds
    if skipped:
        return f"[yellow]skipped: {skipped[0].failed_stage or '?'} failed[/yellow]", seconds
    ran = sum(t.status == "ran" for t in tasks)
    cached = sum(t.status == "cached" for t in tasks)
    return ", ".join(part for part in (f"{ran} ran" if ran else "", f"{cached} cached" if cached else "") if part), seconds


def summary_table(result: Any, metrics: dict[str, dict[str, float]] | None) -> Any:
    """The run summary as a rich Table: one row per session and action (what ran, what failed, the time,
    and the accuracy against truth when there is one), laid out for SUMMARY_WIDTH columns."""
    from rich import box
    from rich.table import Table

    table = Table(title=f"run {result.run_id}: {len(result.published)} published, "
                        f"{sum(s == 'failed' for s in result.action_status.values())} failed, "
                        f"{result.seconds:.0f}s ({result.executor})", box=box.SIMPLE_HEAD, pad_edge=False)
    table.add_column("scope")
    table.add_column("stages")
    table.add_column("time", justify="right")
    if metrics:
        for _, title in SUMMARY_METRICS:
            table.add_column(title, justify="right")
    scopes: dict[str, list[Any]] = {}  # in plan order, grouped in one pass (a release has thousands of scopes)
    for t in result.plan.tasks:
        scopes.setdefault(t.scope_id, []).append(t)
    for scope, scope_tasks in scopes.items():
        outcome, seconds = _scope_outcome(scope_tasks)
        cells = [scope, outcome, f"{seconds:.0f}s"]
        if metrics:
            m = metrics.get(scope, {})
            cells += [f"{m[k]:.2f}" if k in m else "" for k, _ in SUMMARY_METRICS]
        table.add_row(*cells)
    return table


def _summary(result: Any, metrics: dict[str, dict[str, float]] | None) -> None:
    from rich.console import Console

    console = Console(width=min(SUMMARY_WIDTH, Console().width) if sys.stdout.isatty() else SUMMARY_WIDTH)
    console.print(summary_table(result, metrics))
    for action, error in result.action_errors.items():
        console.print(f"[red]action {action} failed[/red]: {error}", markup=True, highlight=False)


def cmd_simulate(args: argparse.Namespace) -> int:
    import dataclasses
    import shutil

    from pipeline.store import swap_into_place
    from synthetic import SimConfig, simulate
    from synthetic.calibration import CalibrationConfig

    overrides = {k: v for k, v in {"mesh": args.mesh, "actions": args.actions, "width": args.width,
                                   "seed": args.seed, "pose_variation": args.pose_variation, "body": args.body,
                                   "hair": args.hair, "garment": args.garment,
                                   "fold_amplitude_m": args.fold_amplitude}.items()
                 if v is not None}
    try:
        config = dataclasses.replace(SimConfig(), **overrides)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    out = Path(args.out)
    if getattr(args, "layout", "raw") == "rnha":  # the raw capture with its truth, and the public layout beside it
        return _simulate_rnha(args, out)
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


def _simulate_rnha(args: argparse.Namespace, out: Path) -> int:
    """``simulate --layout rnha``: the raw capture (and its ground truth) in ``OUT/raw``, the same frames in the
    public release's layout in ``OUT/rnha`` (:func:`synthetic.rnha.write_rnha_layout`), and ``OUT/layout.json``
    saying which is which; the 8-bit photos are made again whenever the raw capture is."""
    from synthetic.rnha import JPEG_QUALITY, write_rnha_layout

    raw = out / "raw"
    record_path = out / "layout.json"
    before = (raw / "capture.json").read_bytes() if (raw / "capture.json").exists() else None
    code = cmd_simulate(argparse.Namespace(**(vars(args) | {"layout": "raw", "out": str(raw)})))
    if code:
        return code
    record = {"layout": "rnha", "rnha": "rnha", "raw": "raw", "ground_truth": "raw/ground_truth",
              "jpeg_quality": JPEG_QUALITY, "chroma_subsampling": "4:2:0",
              "exposure": "each camera white-balanced and exposed so its white reference is 255",
              "run": f"ultrastage run --capture {out / 'rnha'} --release RELEASE",
              "evaluate": f"ultrastage evaluate --release RELEASE --truth {raw / 'ground_truth'}"}
    same = (before == (raw / "capture.json").read_bytes() and (out / "rnha").is_dir() and record_path.exists()
            and json.loads(record_path.read_text()) == record)
    if same and not args.force:
        print(f"public layout {out / 'rnha'} is up to date: skipped (--force to redo)")
        return 0
    start = time.perf_counter()
    write_rnha_layout(raw, out / "rnha", JPEG_QUALITY, progress=lambda msg: print(f"  {msg}", flush=True))
    record_path.write_text(json.dumps(record, indent=1) + "\n")
    print(f"public layout (8-bit sRGB JPEG, quality {JPEG_QUALITY}) written to {out / 'rnha'} in "
          f"{time.perf_counter() - start:.1f}s; its ground truth: {raw / 'ground_truth'}")
    return 0


def _capture_layout_record(capture: str) -> dict[str, Any]:
    """For a capture in the public release's layout: print what stands in for what it lacks and return it for
    the release's run.json (``{"capture_layout": ...}``); ``{}`` for a raw capture."""
    from pipeline.capture_rnha import DEFAULTS, is_rnha_layout, open_rnha_capture

    if not is_rnha_layout(capture):
        return {}
    opened = open_rnha_capture(capture)
    print(f"capture {capture}: the public release layout (RNHA: 8-bit sRGB photos, transforms.json), "
          f"{len(opened.actions)} action(s), {len(opened.sessions)} session(s); in place of what it lacks:")
    for key, text in DEFAULTS.items():
        print(f"  {key:<16} {text}")
    ngp = {a["action_id"]: {"scale": a["ngp_scale"], "offset": a["ngp_offset"]} for a in opened.meta["actions"]}
    return {"capture_layout": {"layout": "rnha", "defaults": dict(DEFAULTS), "ngp_scale_offset": ngp}}


def _work_dir(args: argparse.Namespace, release: Path) -> Path:
    return Path(args.work) if args.work else release.with_name(release.name + ".work")


def _start_truth_prefetch(capture: Path, work: Path, stages: list[Any]) -> Any:
    """A lowest-priority process tracing the ground truth's visibility for the relit evaluation
    (:func:`synthetic.relight.prefetch_visibility`) while the pipeline runs: it takes the cores' idle moments,
    and the evaluation after the run finds what it finished. None when nothing would use it (no ground truth,
    no relit stage)."""
    import subprocess

    from pipeline.capture import open_capture

    if not (capture / "ground_truth").is_dir() or not {"relight", "relightset"} & {s.name for s in stages}:
        return None
    try:
        opened = open_capture(capture)
    except InputError:
        return None  # the run itself names what is wrong with the capture
    if not isinstance(opened.meta.get("simulator"), dict) or not opened.sessions:
        return None
    from evaluation.release import RELIT_CACHE, relit_truth_lights, truth_visibility_folder

    lights = relit_truth_lights(next(iter(opened.sessions.values())).rig["cameras"])
    folder = truth_visibility_folder(work / RELIT_CACHE)
    # os.nice in the child itself: a preexec_fn is not safe once the parent runs threads. SIGTERM exits through
    # the finally blocks, so the claim of a trace it is stopped in is removed.
    script = ("import os, signal, sys; os.nice(19); signal.signal(signal.SIGTERM, lambda *_: sys.exit(143)); "
              "from synthetic.relight import prefetch_visibility; "
              "prefetch_visibility(sys.argv[1], sys.argv[2], int(sys.argv[3]))")
    return subprocess.Popen([sys.executable, "-c", script, str(capture), str(folder), str(lights)],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env=os.environ | {"OMP_NUM_THREADS": "1"})


def _stop(process: Any) -> None:
    """End a helper process (what it finished is on disk, written whole)."""
    if process is not None and process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=30)
        except Exception:  # noqa: BLE001 - it must not outlive the command
            process.kill()


def cmd_run(args: argparse.Namespace, plan_only: bool = False) -> int:
    from ultrastage.run import run_pipeline
    from stages.registry import build_stages

    config = _resolve_config(args.preset, args.config, args.scheduler)
    release = Path(args.release)
    work = _work_dir(args, release)
    stages = build_stages(config, through=args.through)
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
    layout = _capture_layout_record(args.capture)
    on_done, on_view, on_progress = _progress_printer()
    truth = Path(args.capture) / "ground_truth"
    prefetch = None if args.no_evaluate else _start_truth_prefetch(Path(args.capture), work, stages)
    try:
        result = run_pipeline(Path(args.capture), release, work, stages, config, config.execution,
                              only=args.only, from_stage=args.from_stage, actions=actions,
                              progress=on_done, view_progress=on_view, stage_progress=on_progress,
                              record={"preset": args.preset, **({"through": args.through} if args.through else {}),
                                      **layout})
        metrics = None
        if not args.no_evaluate and truth.is_dir() and result.published:
            from evaluation.release import evaluate_release_cached

            # The prefetch goes on beside the evaluation: a trace it has not finished is waited for (it holds a
            # claim, and a waiting process leaves it the core), not traced again from the start.
            summary, cached = evaluate_release_cached(release, truth, work, run_id=result.run_id)
            print(f"{'evaluate':<12} {'release':<8} "
                  f"{'cached  release unchanged since its last evaluation' if cached else 'ran'}")
            metrics = summary.per_action
            result.metrics = metrics
    finally:
        _stop(prefetch)
    _summary(result, metrics)
    if metrics:
        from evaluation.release import print_overall

        print_overall(summary)
    return 0 if all(s == "ok" for s in result.action_status.values()) else 3


def cmd_rerun(args: argparse.Namespace) -> int:
    from pipeline.runner import RUN_RECORD, read_run_record

    release = Path(args.release)
    if not (release / RUN_RECORD).exists():
        raise InputError(release / RUN_RECORD, "no run record: this folder was not written by `ultrastage run`")
    info = read_run_record(release)
    ns = argparse.Namespace(capture=info["capture"], release=str(release), work=info["work"],
                            preset=info.get("preset", "default"), config=args.config or None,
                            scheduler=args.scheduler, only=args.only, from_stage=args.from_stage,
                            actions=args.actions, no_evaluate=args.no_evaluate, through=info.get("through"))
    if args.config is None and (release / "config.yaml").exists():
        ns.config = str(release / "config.yaml")
    if args.failed or args.where or args.subject or args.session:
        from manifests.select import parse_condition, select_actions

        try:
            where = parse_condition(args.where) if args.where else None
        except ValueError as exc:
            raise InputError(release / "manifests" / "metrics.parquet", str(exc)) from None
        selection = select_actions(release, failed=args.failed, where=where, subject=args.subject,
                                   session=args.session)
        if args.actions:
            wanted = set(args.actions.split(","))
            selection.actions = [a for a in selection.actions if a in wanted]
        for action_id in selection.actions:
            print(f"{'select':<12} {action_id:<8} {selection.reasons[action_id]}")
        if not selection.actions:
            print("rerun: no action matches; nothing to redo")
            return 0
        ns.actions = ",".join(selection.actions)
    return cmd_run(ns, plan_only=args.dry_run)


def cmd_evaluate(args: argparse.Namespace) -> int:
    from evaluation.release import RELIT_CACHE, evaluate_release, print_overall

    release = Path(args.release)
    work = _work_dir(args, release)
    # the simulator's renders the relit views are compared with: those the run kept are read, not rendered again
    # (a release without its work folder beside it, e.g. downloaded, gets none unless --work names one)
    relit_cache = work / RELIT_CACHE if args.work or work.is_dir() else None
    summary = evaluate_release(release, Path(args.truth), relit_cache=relit_cache)
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
    for label, items in (("missing", report.missing), ("changed", report.mismatched), ("extra", report.extra),
                         ("not covered", report.not_covered)):
        for item in items[:50]:
            print(f"  {label}: {item}")
    print("OK" if report.ok else "FAILED")
    return 0 if report.ok else 1


def cmd_train(args: argparse.Namespace) -> int:
    from pipeline.config import load_overrides, merge
    from ultrastage.baselines.config import preset
    from ultrastage.baselines.train import CHECKPOINT_NAME, METRICS_NAME, default_out_dir, evaluate, select_device, train

    config = preset(args.preset, args.network)
    if args.config:
        config = merge(config, load_overrides(args.config), where=str(args.config))
        if config.network != args.network:
            raise ConfigError(f"{args.config}: network {config.network!r} contradicts the command's {args.network!r}")
    out = Path(args.out) if args.out else default_out_dir(Path(args.set), args.network)
    if args.evaluate_only:
        evaluate(Path(args.set), out / CHECKPOINT_NAME, out / METRICS_NAME, device=select_device(config.device))
        print(f"wrote {out / METRICS_NAME}")
        return 0
    result = train(Path(args.set), config, out)
    print(f"{args.network}: {result.step} steps ({result.steps_run} now, {result.seconds:.1f}s); "
          f"wrote {result.checkpoint}, {out / 'config.yaml'}, {out / 'loss.png'}, {out / METRICS_NAME}")
    return 0


def cmd_merge_sets(args: argparse.Namespace) -> int:
    from ultrastage.merge_sets import merge_relight_sets, parse_sources

    def names(text: str | None) -> tuple[str, ...]:
        return tuple(t.strip() for t in text.split(",") if t.strip()) if text else ()

    result = merge_relight_sets(parse_sources(args.sources), Path(args.out), subject_from=args.subject_from,
                                test=names(args.test), validation=names(args.validation), seed=args.seed,
                                replace=args.replace)
    print(f"wrote {result.out} ({sum(result.examples.values())} examples)")
    return 0


def cmd_predict(args: argparse.Namespace) -> int:
    from ultrastage.baselines.predict import predict_folder

    result = predict_folder([Path(c) for c in args.checkpoint], Path(args.images), Path(args.out),
                            Path(args.environment) if args.environment else None, args.environment_rotation,
                            device=args.device, masks=Path(args.masks) if args.masks else None)
    print(f"{len(result.photos)} photo(s), {len(result.files)} file(s) written to {args.out} "
          f"(contact sheet {Path(args.out) / 'contact_sheet.png'})")
    return 0


def _stage_names() -> list[str]:
    from stages.stage_names import STAGE_NAMES

    return list(STAGE_NAMES)


def _add_stage_choice(p: argparse.ArgumentParser, stage_names: list[str]) -> None:
    listed = ", ".join(stage_names)
    group = p.add_mutually_exclusive_group()
    group.add_argument("--only", metavar="STAGE", choices=stage_names,
                       help=f"force this stage to rerun (its dependents rerun only if their keys change); one of {listed}")
    group.add_argument("--from", dest="from_stage", metavar="STAGE", choices=stage_names,
                       help=f"force this stage and everything downstream of it; one of {listed}")


def _add_run_args(p: argparse.ArgumentParser, stage_names: list[str], release_help: str) -> None:
    p.add_argument("--capture", required=True, help="capture folder (capture.json inside), or a folder in the public "
                                                    "release's layout (full_on/ pos/ neg/ mask/ *.jpg and "
                                                    "transforms.json), or a folder of those")
    p.add_argument("--release", required=True, help=release_help)
    p.add_argument("--work", help="artifact store and run logs (default: <release>.work beside the release)")
    p.add_argument("--preset", default="default", help="config preset: default, production (GPU, full-resolution captures), fast (quick looks), test (tiny captures)")
    p.add_argument("--config", help="YAML overrides, e.g. {decode: {demosaic: DCB}}; unknown keys are errors")
    p.add_argument("--scheduler", help="'local' (a dask cluster on this machine, the default), 'sync' (in this process) "
                                       "or the address of a running dask scheduler, e.g. tcp://10.0.0.5:8786")
    _add_stage_choice(p, stage_names)
    p.add_argument("--through", metavar="STAGE", choices=stage_names,
                   help="run only this stage and the stages it needs (e.g. photometric: no neural stages); "
                        f"`rerun` keeps it; one of {', '.join(stage_names)}")
    p.add_argument("--actions", help="comma-separated action ids (default: all)")
    p.add_argument("--no-evaluate", action="store_true", help="skip the accuracy summary against ground truth")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ultrastage")
    except PackageNotFoundError:  # a source tree that was never installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ultrastage", description="UltraStage light-stage dataset pipeline")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}",
                        help="print the installed version and exit")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging (tracebacks of failures)")
    stage_names = _stage_names()
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="render a synthetic raw capture with ground truth")
    p.add_argument("--out", required=True, help="capture folder to write")
    p.add_argument("--mesh", help="subject mesh (OBJ, PLY, glTF/GLB, STL, OFF; 'procedural' for the built-in "
                   "subject); default: the MakeHuman body in ../shared, else procedural")
    p.add_argument("--pose-variation", type=float, metavar="X",
                   help="0..1: how far each action's pose departs from the rest A-pose (default 0; "
                        "MakeHuman subject only)")
    p.add_argument("--body", metavar="SPEC",
                   help="MakeHuman body shape (MakeHuman subject only): 'random' (drawn per action), "
                        "'gender=0.2,weight=0.9,...' (fixed; names gender, age, muscle, weight, height, african, "
                        "asian, caucasian, each 0..1, age >= 0.5 = 25 years), or 'random,height=0.7'; "
                        "default: the base mesh as it is")
    p.add_argument("--hair", type=float, metavar="FRACTION",
                   help="0..1: fraction of the actions (drawn per action) with a hair volume (default 0; "
                        "MakeHuman subject only)")
    p.add_argument("--garment", type=float, metavar="FRACTION",
                   help="0..1: fraction of the actions (drawn per action) wearing a loose skirt (default 0; "
                        "MakeHuman subject only)")
    p.add_argument("--fold-amplitude", type=float, metavar="M",
                   help="peak displacement of the clothes' folds along the normal, metres (default 0.004, drawn "
                        "x0.75-1.25 per action; 0: no folds)")
    p.add_argument("--actions", type=int, help="number of actions")
    p.add_argument("--width", type=int, help="image width in pixels (height follows the D750's 2:3 portrait)")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument("--force", action="store_true", help="render again even if the capture is up to date")
    p.add_argument("--layout", choices=("raw", "rnha"), default="raw",
                   help="raw: the stage's raw capture (default); rnha: also the public release's layout of the same "
                        "frames (8-bit sRGB JPEG, quality 95, transforms.json) in OUT/rnha, the raw capture and its "
                        "ground truth in OUT/raw")
    p.set_defaults(fn=cmd_simulate)

    p = sub.add_parser("run", help="run the DAG on a capture and write the release")
    _add_run_args(p, stage_names, "release folder to write (created if absent; published actions are replaced)")
    p.set_defaults(fn=cmd_run)

    p = sub.add_parser("plan", help="show what `run` would do (cached / run and why) without running it")
    _add_run_args(p, stage_names, "release folder the run would write (only its work folder is read)")
    p.set_defaults(fn=lambda a: cmd_run(a, plan_only=True))

    p = sub.add_parser("rerun", help="run again with the capture, work folder and config a release records")
    p.add_argument("release", help="a release folder written by `ultrastage run` (its run.json names the capture)")
    p.add_argument("--config", help="YAML overrides (default: the release's config.yaml)")
    p.add_argument("--scheduler", help="'local', 'sync' or a dask scheduler address (default: the config's)")
    _add_stage_choice(p, stage_names)
    p.add_argument("--actions", help="comma-separated action ids (default: all)")
    p.add_argument("--failed", action="store_true", help="the actions that failed in the last run (manifests/actions.parquet)")
    p.add_argument("--where", metavar="'METRIC OP NUMBER'",
                   help="actions whose metric (manifests/metrics.parquet: the action's value, else the mean over its "
                        "cameras) meets the condition, e.g. \"heldout_albedo_psnr_db < 30\"; OP: < <= > >= == !=")
    p.add_argument("--subject", help="only this subject's actions (exact, or a prefix ending in '/')")
    p.add_argument("--session", help="only this session's actions")
    p.add_argument("--dry-run", action="store_true", help="print what would be redone and why; run nothing")
    p.add_argument("--no-evaluate", action="store_true", help="skip the accuracy summary against ground truth")
    p.set_defaults(fn=cmd_rerun)

    p = sub.add_parser("evaluate", help="accuracy of a release against ground truth")
    p.add_argument("--release", required=True, help="release folder to evaluate (manifests/ inside)")
    p.add_argument("--truth", required=True, help="the simulator's ground truth: CAPTURE/ground_truth")
    p.add_argument("--json", help="also write one flat JSON object of metric name to number")
    p.add_argument("--work", help="the run's work folder (default: <release>.work beside the release, when there): "
                                  "the simulator's renders the relit views are compared with are read from its "
                                  "cache and the missing ones kept there")
    p.set_defaults(fn=cmd_evaluate)

    p = sub.add_parser("calibrate", help="calibrate the cameras of any folder of photos (pycolmap)")
    p.add_argument("--images", required=True, help="folder of photos (PNG/JPEG/TIFF or raw)")
    p.add_argument("--out", required=True, help="folder for transforms.json and the COLMAP text model")
    p.add_argument("--intrinsics", help="JSON with known K (shared or per image); see calibration.geometric")
    p.set_defaults(fn=cmd_calibrate)

    p = sub.add_parser("verify", help="re-check every asset of a release against its sha256")
    p.add_argument("release", help="release folder to check (manifests/assets.parquet inside)")
    p.set_defaults(fn=cmd_verify)

    p = sub.add_parser("train", help="train the AlbedoNet or NormalNet baseline on a release's relighting set")
    p.add_argument("network", choices=("albedonet", "normalnet"),
                   help="which baseline to train: albedonet (image -> linear albedo) or normalnet "
                        "(image -> camera-frame normals)")
    p.add_argument("--set", required=True, help="release folder with the relighting set (relight_examples)")
    p.add_argument("--preset", default="cpu", help="config preset: tiny (tests), cpu (default), gpu")
    p.add_argument("--config", help="YAML overrides of TrainConfig, e.g. {steps: 500, lr: 0.001}")
    p.add_argument("--out", help="folder of the checkpoint, config, loss curve and test metrics "
                                 "(default: <release>.baselines/<network>/ beside the release); resumes from it")
    p.add_argument("--evaluate-only", action="store_true", help="only measure the test split with OUT's checkpoint")
    p.set_defaults(fn=cmd_train)

    p = sub.add_parser("merge-sets", help="one relighting set from the relighting sets of several releases, "
                                          "split by subject")
    p.add_argument("out", help="folder of the merged set (a release layout holding only the relighting set)")
    p.add_argument("sources", nargs="+", metavar="[NAME=]RELEASE",
                   help="releases to merge; NAME prefixes their example ids (default: the folder's name, or the "
                        "name of the folder above one called 'release')")
    p.add_argument("--subject-from", choices=("subject", "release"), default="subject",
                   help="'subject': the sources' subject names as they are (one subject in two releases stays one); "
                        "'release': each source's subjects are its own (NAME/subject)")
    p.add_argument("--test", help="comma-separated subjects (or source names: all their subjects) for the test split")
    p.add_argument("--validation", help="comma-separated subjects (or source names) for the validation split")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the splits drawn per subject when neither --test nor --validation is given")
    p.add_argument("--replace", action="store_true", help="replace OUT (once the new set is complete)")
    p.set_defaults(fn=cmd_merge_sets)

    p = sub.add_parser("predict", help="albedo and normal maps of photos (and relit images under an HDR map)")
    p.add_argument("--checkpoint", action="append", required=True,
                   help="a checkpoint of `ultrastage train` (give one per network; both for relighting)")
    p.add_argument("--images", required=True,
                   help="folder of PNG/JPEG photos; NAME_mask.png/.jpg beside NAME.* is its mask (never a photo), "
                        "else its alpha, else the whole frame")
    p.add_argument("--masks", help="folder of mask files named as the photos (NAME.png/.jpg or NAME_mask.*); "
                                   "white = subject, the photo's size")
    p.add_argument("--out", required=True, help="folder to write OUT/<photo>/{albedo,normal,relit_<env>}.{exr,png} "
                                                "and OUT/contact_sheet.png")
    p.add_argument("--environment", help="HDR environment map (.hdr/.exr) or a folder of them: relight under each")
    p.add_argument("--environment-rotation", type=float, default=0.0,
                   help="degrees about +y (world = R_y(deg) map); the camera looks along the map's -z")
    p.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda")
    p.set_defaults(fn=cmd_predict)
    return parser


def main(argv: list[str] | None = None) -> int:
    from pipeline.malloc import tune_malloc

    args = build_parser().parse_args(argv)
    tune_malloc()
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.fn(args) or 0)
    except (InputError, ConfigError, ValueError) as exc:
        if args.verbose:  # a developer wants the traceback, a user the one-line reason
            raise
        print(f"ultrastage {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except (WriteError, OSError) as exc:  # a folder that cannot take the output: full, read-only, not a folder
        if args.verbose:
            raise
        print(f"ultrastage {args.command}: error: {exc}", file=sys.stderr)
        return 4


if __name__ == "__main__":
    sys.exit(main())
