"""Run every bench/bench_*.py (each writes <name>.json and plots into --out) and collect a report.

Benchmarks measure time against error, and speed as ratios against a simple baseline run in the same
process; they are never timed tests.

``--quick`` (``make bench-quick``, and tests/unit/bench/test_bench_quick.py) runs every bench in its quick mode:
the same code on the smallest inputs that run it (the benches that read a release share a tiny simulated run
made once under ``--out``, see bench/_quick.py), so that the benches cannot rot; its numbers are not
measurements. A quick run forks every bench from itself after importing the common libraries once
(:data:`PRELOAD`); ``--quick --lanes 2`` (the tests) runs them in two lanes side by side (:data:`SHARED_RUN_LANE`).
Without ``--quick`` (``make bench``) the slowest benches run smaller (:data:`MAKE_BENCH_ARGS`); ``--full``
(``make bench-full``) runs every bench with its own defaults. Each bench's wall and CPU seconds go into the report and
``bench_times.json``.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
MAKE_BENCH_ARGS: dict[str, list[str] | None] = {
    "calibration": ["--markers", "--widths", "320"],
    "diffuse_normals": ["--stride", "8"],
    "executor": ["--steps", "75"],
    "free_space": ["--actions", "A0000"],
    "geometry": ["--checkpoints", "4", "--no-ablation"],
    "gpu_production": None,
    "heldout_field": ["--lengths", "100,400"],
    "memory": None,
    "panel_set": None,
    "pipeline": None,
    "relight": ["--actions", "A0000"],
    "relit_budget": ["--actions", "A0000"],
    "relightset": ["--examples", "2"],
    "relight_window": ["--scales", "1,2"],
    "resolution": None,
    "scale": ["--sizes", "20,100"],
    "sdf_schedule": ["--schedules", "400+1200,1800+1800"],
    "sdf_sharpness": ["--inv-s", "1600"],
    "sg": ["--lobes", "8,32,64"],
    "specular_normals": ["--seeds", "0"],
    "subjects": None,
    "textures": ["--no-undecimated"],
    "third_pass": ["--actions", "A0000"],
}
"""What ``make bench`` runs smaller than the bench's own defaults (``--full``, ``make bench-full``, runs every bench
with its own defaults): per bench (name without ``bench_``) its arguments, or None for a bench left to the full run.
Chosen so that ``make bench`` fits in 45 minutes on an idle 2-core machine (it took 23 min 54 s there; README). Left to
the full run: the production-size memory measurements (memory), the default capture end to end at 2 actions
through dask (pipeline: bench_end_to_end measures the same things on small captures), one action of 32 cameras
through the whole DAG and its evaluation at 192, 384 and 768 px (resolution), the subject panel and the baselines
trained on its relighting set (subjects, panel_set) and the production path on a GPU (gpu_production: it runs nothing
where torch sees no CUDA device)."""
SPEED_BASELINES: dict[str, str | None] = {
    "calibration": "decoding the 32 marker frames it reads (`x_decode`; `--markers`, the cameras stage's default source)",
    "decode": "rawpy's default call (`imread().postprocess()`) on the same file, and a memory copy of the bytes a "
              "decode reads and writes (`x_rawpy_default`, `x_memcpy`)",
    "diffuse_normals": "the fit with one roughness prior (`time_vs_one_prior`)",
    "end_to_end": "the smallest capture for the growth with width and actions (`x smallest`), the cold run for a "
                  "rerun and a new action (share of its task seconds skipped)",
    "executor": "the same SDF steps in the bench's own process (`worker / in_process`)",
    "gaps": "the single-view rules on the same holes, every hole filled and every hole opened (accuracy; the "
            "decision's seconds per action)",
    "gbuffer": "bilinear source lookup for the cubic one (`cubic_time_ratio`)",
    "gpu": "the same production field step on one CPU thread (`speedup_over_cpu_thread`)",
    "gpu_production": "the default preset's run of the same capture on the same machine, beside the production "
                      "preset's (bench_gpu gives the speed-up over one CPU thread)",
    "geometry": "autograd's double backward for the analytic SDF gradients; the naive uniform samples for the "
                "empty-space skipping (`samples_skipped_fraction`)",
    "hashgrid": "a copy of the feature table, and the torch path for the fused kernel",
    "heldout_field": "the depth-guided reprojection's time beside the volume-rendered field's",
    "light": "the plain `normalize(d)` for the light model's correction",
    "materials": "gathering the texels' observations the fits read (`x_gather`)",
    "memory": "the imports alone (memory, not speed)",
    "normal_error_sources": "no speed figure (accuracy per simulated effect)",
    "page": "the same thumbnails written on one thread (`x_one_thread`)",
    "photometric": "a memory copy of the same bytes, and a naive numpy chain (`ratio_to_memcpy`, "
                   "`speedup_over_naive`)",
    "pipeline": "the cold run for the cached rerun (`cached_over_cold`)",
    "projection": "no speed figure of its own (a projection from a run's stage seconds)",
    "relight": "the simplest variant (no shadows, photometric albedo; `x_baseline`)",
    "relightset": "the simulator's render of the same view (`x_truth`)",
    "relight_window": "the same view rendered over the whole frame (`x_whole`, memory and CPU seconds)",
    "relit_budget": "no speed figure (accuracy per component swapped for the truth; seconds per piece of a view)",
    "resolution": "the smallest width (each stage's exponent k: seconds ~ pixels^k over it), and the imports alone "
                  "for each stage's process (`CPU s above the imports`)",
    "scale": "the same number of stub tasks through the executor alone (`x_bare`), and as one `client.map` on dask",
    "sdf_schedule": "the 1800+1800 schedule (`vs 1800+1800`)",
    "sdf_sharpness": "no speed figure (accuracy per sharpness and mask kind; CPU seconds per row)",
    "silhouette": "the SDF's mesh as it is, no refinement (its row; the step's seconds per row)",
    "sg": "the map's order-2 SH projection (`x_sh_projection`)",
    "simulate": "exact per-LED GGX for the specular LED clusters; 4 x 4 rays per pixel for the pixel integration; "
                "the numpy steps for the fused GGX loop (`x_numpy`)",
    "specular_normals": "eq. 1's ratio (the `eq1` row)",
    "subjects": "no speed figure (the pipeline's accuracy per subject: `make panel`)",
    "panel_set": "the trivial baselines on the same test examples (accuracy, not speed: `make panel`)",
    "textures": "the stage on the undecimated mesh (`x undecimated`; `make bench-full` only)",
    "free_space": "no speed figure (the free-space cue's pixels against the truth, and the SDF carved by it; CPU "
                  "seconds per row)",
    "third_pass": "no speed figure (the third SDF pass's decision share and what the pass does to the mesh; CPU "
                  "seconds per row)",
}
"""Per bench (name without ``bench_``): the simple baseline its speed figures are a ratio to, timed in the same
process, or None where it has none yet (the report lists those)."""
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


READS_OTHER_BENCHES = frozenset({"bench_projection", "bench_panel_set"})
"""Benches that read other benches' results from ``--out``: run after every other bench."""


def bench_arguments(name: str, quick: bool, full: bool) -> list[str] | None:
    """The arguments run_all gives bench ``name`` beyond ``--out`` (None: not run in this mode)."""
    if quick:
        return ["--quick"]
    if full or name not in MAKE_BENCH_ARGS:
        return []
    return MAKE_BENCH_ARGS[name]


SHARED_RUN_LANE = frozenset({
    "bench_diffuse_normals", "bench_end_to_end", "bench_free_space", "bench_gaps", "bench_gbuffer", "bench_geometry",
    "bench_gpu_production", "bench_heldout_field", "bench_materials", "bench_page", "bench_panel_set", "bench_projection",
    "bench_relight", "bench_relight_window", "bench_relightset", "bench_relit_budget", "bench_sdf_schedule", "bench_sdf_sharpness",
    "bench_silhouette", "bench_textures", "bench_third_pass"})
"""The benches whose quick mode reads the shared tiny run (bench/_quick.py's ``quick_run``): with ``--lanes 2`` they
run one after another in one lane and every other bench in the other. ``quick_run`` holds a lock for the life of
the process that uses it, so a bench missing here still takes the run in turn, only later; the quick run's
``quick_run.users`` lists the benches that did use it (tests/unit/bench/test_bench_quick.py compares the two)."""


PRELOAD = ("numpy", "scipy.ndimage", "torch", "matplotlib.pyplot", "pyarrow.parquet", "stages.registry",
           "evaluation.release", "synthetic")
"""What ``run_all.py --quick`` imports once before it forks every bench from itself: about 4 CPU seconds a bench
process would spend on these imports (the benches' own subprocesses still import for themselves)."""


def preload(env: dict[str, str]) -> None:
    """Import :data:`PRELOAD` into this process, with ``env`` set first (the OpenMP wait policy is read when the
    OpenMP runtime loads, with torch) and matplotlib on its file backend."""
    os.environ.update(env)
    os.environ.setdefault("MPLBACKEND", "Agg")
    if str(HERE.parent) not in sys.path:
        sys.path.insert(0, str(HERE.parent))
    import importlib

    for name in PRELOAD:
        importlib.import_module(name)


def _forked_bench(script: Path, extra: list[str], out: Path, log: Path | None) -> None:
    """In a child forked from run_all: run ``script`` as ``__main__`` with its command line, output to ``log``
    (else inherited), and end the process with the bench's exit status. Never returns."""
    code = 1
    try:
        if log is not None:
            fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            os.dup2(fd, 1)
            os.dup2(fd, 2)
            os.close(fd)
        os.chdir(HERE.parent)
        sys.argv = [str(script), "--out", str(out), *extra]
        sys.path.insert(0, str(script.parent))  # as when the script is run: its siblings import by name
        import runpy

        try:
            runpy.run_path(str(script), run_name="__main__")
            code = 0
        except SystemExit as exc:
            if exc.code is None or isinstance(exc.code, int):
                code = exc.code or 0
            else:
                print(exc.code, file=sys.stderr)
    except BaseException:  # noqa: BLE001 - whatever the bench raised is its failure, reported like Python's own
        import traceback

        traceback.print_exc()
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def start_bench(script: Path, extra: list[str], out: Path, env: dict | None, log: Path | None,
                fork: bool) -> tuple[int, subprocess.Popen | None]:
    """Start one bench in a process of its own: ``python SCRIPT --out OUT EXTRA``, or with ``fork`` a child of this
    process that runs it (:func:`_forked_bench`; :func:`preload` first). Its output goes to this process's, or
    with ``log`` to that file. Returns (pid, the Popen object or None)."""
    if fork:
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _forked_bench(script, extra, out, log)
        return pid, None
    with open(log, "w") if log else contextlib.nullcontext() as sink:
        proc = subprocess.Popen([sys.executable, str(script), "--out", str(out)] + extra, cwd=HERE.parent, env=env,
                                stdout=sink, stderr=subprocess.STDOUT if log else None)
    return proc.pid, proc


def run_benches(plan: list[tuple[Path, list[str]]], out: Path, env: dict | None, lanes: int,
                fork: bool = False) -> dict[str, tuple[int, float, float]]:
    """Run ``plan``'s benches, each in its own process (:func:`start_bench`); per bench name (exit status, wall s,
    CPU s of it and its waited-for children). With one lane in order, their output streamed. With two,
    :data:`SHARED_RUN_LANE`'s benches in one lane and the others in the other, side by side, each bench's output
    printed whole when it ends. The benches that read other benches' results run after the lanes."""
    results: dict[str, tuple[int, float, float]] = {}
    logs = out / "logs" if lanes > 1 else None
    if logs is not None:
        logs.mkdir(parents=True, exist_ok=True)

    def run_lanes(queues: list[list[tuple[Path, list[str]]]]) -> None:
        running: dict[int, tuple[int, Path, list[str], float, subprocess.Popen | None]] = {}

        def launch(lane: int) -> None:
            if not queues[lane]:
                return
            script, extra = queues[lane].pop(0)
            if logs is None:
                print(f"== {script.name} {' '.join(extra)}".rstrip(), flush=True)
            log = logs / f"{script.stem}.log" if logs is not None else None
            pid, proc = start_bench(script, extra, out, env, log, fork)
            running[pid] = (lane, script, extra, time.perf_counter(), proc)

        for lane in range(len(queues)):
            launch(lane)
        while running:
            pid, status, usage = os.wait4(-1, 0)  # that child's own resource use, whatever else runs beside it
            if pid not in running:
                continue
            lane, script, extra, started, proc = running.pop(pid)
            code = os.waitstatus_to_exitcode(status)
            if proc is not None:
                proc.returncode = code
            seconds, cpu = time.perf_counter() - started, usage.ru_utime + usage.ru_stime
            results[script.stem] = code, seconds, cpu
            ended = f"== {script.name}: exit {code}, {seconds:.1f} s ({cpu:.1f} s CPU)"
            if logs is not None:  # one print call: the other lane's lines do not fall inside this block
                text = (logs / f"{script.stem}.log").read_text(errors="replace")
                print(f"== {script.name} {' '.join(extra)}".rstrip() + "\n" + text
                      + ("\n" if text and not text.endswith("\n") else "") + ended, flush=True)
            else:
                print(ended, flush=True)
            launch(lane)

    last = [(s, e) for s, e in plan if s.stem in READS_OTHER_BENCHES]
    first = [(s, e) for s, e in plan if s.stem not in READS_OTHER_BENCHES]
    if lanes == 1:
        run_lanes([first + last])
    else:
        run_lanes([[(s, e) for s, e in first if s.stem in SHARED_RUN_LANE],
                   [(s, e) for s, e in first if s.stem not in SHARED_RUN_LANE]])
        run_lanes([last])
    return results


def baseline_section(names: list[str]) -> list[str]:
    """The report's list of each bench's speed baseline, and of the benches that have none."""
    lines = ["## Speed figures and their baselines", "",
             "Each speed figure is given beside a simple baseline timed in the same process, as a ratio, so that it "
             "holds on a loaded machine.", "", "| bench | baseline |", "|---|---|"]
    lacking = []
    for name in names:
        baseline = SPEED_BASELINES.get(name)
        lines.append(f"| {name} | {baseline or '**none**'} |")
        if baseline is None:
            lacking.append(name)
    if lacking:
        lines += ["", "Without a baseline yet: " + ", ".join(lacking) + " (their times are absolute seconds on the "
                  "machine above)."]
    return lines + [""]


def tradeoff_section(out: Path) -> list[str]:
    """The per-stage time-against-error tables and plots (bench/_tradeoffs.py) from the benches' JSON in ``out``."""
    sys.path.insert(0, str(HERE))
    sys.path.insert(0, str(HERE.parent))
    from _tradeoffs import report_section

    return report_section(out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default=str(HERE / "out"))
    parser.add_argument("--only", help="comma-separated bench names (e.g. decode,photometric)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true",
                      help="every bench in its quick mode (the tests' mode): checks they run; not measurements")
    mode.add_argument("--full", action="store_true",
                      help="every bench with its own (largest) defaults; without: MAKE_BENCH_ARGS's smaller runs")
    parser.add_argument("--lanes", type=int, choices=(1, 2), default=1,
                        help="with --quick: 2 runs the benches that read the shared tiny run in one lane and the "
                             "others beside them (the tests' mode; a measuring run keeps one bench at a time)")
    args = parser.parse_args()
    if args.lanes != 1 and not args.quick:
        parser.error("--lanes 2 is for --quick only: benches that measure time run one at a time")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    # the benches that read others' results (the projection reads bench_resolution.json, bench_gpu.json) run last
    scripts = sorted(HERE.glob("bench_*.py"), key=lambda s: (s.stem in READS_OTHER_BENCHES, s.name))
    if args.only:
        wanted = {f"bench_{n}.py" for n in args.only.split(",")}
        scripts = [s for s in scripts if s.name in wanted]
    failures, times, cpu_times = [], {}, {}
    report = ["# Benchmark report", ""]
    env = None
    if args.quick:
        report += ["**Quick run** (`run_all.py --quick`, `make bench-quick`): every bench on the smallest inputs that "
                   "run its code, to check that it runs. **Its numbers are not measurements**; `make bench` measures.",
                   ""]
        # numeric threads that sleep rather than spin while they wait: the tests run this beside other work
        from _quick import QUICK_RUN_SESSION_ENV

        env = os.environ | {"OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE"),
                            # the shared tiny run is brought up to date once per invocation, by its first user
                            QUICK_RUN_SESSION_ENV: f"{os.getpid()}-{time.time_ns()}"}
        # the benches are forked from this process with the common imports done once (before torch is imported
        # for the machine's lines below, so that its OpenMP runtime reads the wait policy)
        preload(env)
    elif not args.full:
        report += ["`make bench` (`run_all.py`): the slowest benches run smaller than their own defaults "
                   "(`MAKE_BENCH_ARGS`); `make bench-full` (`--full`) runs them all at full size.", ""]
    report += ["## Machine", "", *machine_lines(), ""]
    started = time.perf_counter()
    plan = []
    for script in scripts:
        extra = bench_arguments(script.stem.removeprefix("bench_"), args.quick, args.full)
        if extra is None:
            print(f"== {script.name}: left to the full run (make bench-full)", flush=True)
        plan.append((script, extra))
    results = run_benches([(s, e) for s, e in plan if e is not None], out, env, args.lanes, fork=args.quick)
    for script, extra in plan:
        if extra is None:
            report += [f"## {script.stem}", "", "not run: left to `make bench-full` (see MAKE_BENCH_ARGS)", ""]
            continue
        returncode, seconds, cpu = results[script.stem]
        times[script.stem], cpu_times[script.stem] = seconds, cpu
        if returncode:
            failures.append(script.name)
        report += [f"## {script.stem}", "", f"exit {returncode}, {seconds:.1f}s wall, {cpu:.1f}s CPU"
                   + (f" (`{' '.join(extra)}`)" if extra and not args.quick else ""), ""]
        result = out / f"{script.stem}.json"
        table = out / f"{script.stem}.md"
        if table.exists():  # the bench's own tables, written for readers
            report += [table.read_text().replace("\n# ", "\n### ").removeprefix("# "), ""]
        elif result.exists():
            report += ["```json", json.dumps(json.loads(result.read_text()), indent=1)[:6000], "```", ""]
        for png in sorted(out.glob(f"{script.stem}*.png")):
            report.append(f"![{png.stem}]({png.name})")
        report.append("")
    total = time.perf_counter() - started
    first_bench = next((i for i, line in enumerate(report) if line.startswith("## bench_")), len(report))
    report[first_bench:first_bench] = tradeoff_section(out) + baseline_section(
        [s.stem.removeprefix("bench_") for s in scripts])
    report[report.index("## Machine"):report.index("## Machine")] = [
        f"{len(times)} benches in {total:.0f} s wall, {sum(cpu_times.values()):.0f} s CPU (wall / CPU per bench): "
        + ", ".join(f"{k.removeprefix('bench_')} {v:.0f} / {cpu_times[k]:.0f} s" for k, v in times.items()), ""]
    (out / "REPORT.md").write_text("\n".join(report))
    (out / "bench_times.json").write_text(json.dumps(
        {"mode": "quick" if args.quick else "full" if args.full else "make bench", "total_wall_s": total,
         "benches": {k: {"wall_s": v, "cpu_s": cpu_times[k]} for k, v in times.items()}}, indent=1))
    print("times: " + ", ".join(f"{k} {v:.1f} s" for k, v in times.items()))
    print(f"total {total:.1f} s; report: {out / 'REPORT.md'}")
    if failures:
        print(f"failed: {failures}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
