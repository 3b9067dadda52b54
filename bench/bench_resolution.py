"""The production path measured against resolution: one action of :data:`CAMERAS` cameras simulated at each of
:data:`WIDTHS` pixels wide and run cold through the whole DAG with the :data:`PRESET` preset; per stage its seconds,
CPU seconds and peak memory, every figure of ``ultrastage evaluate --json``, the simulator's seconds per camera, and
how each grows with the pixels per view.

Each step runs the project's own command line in a fresh process, started by a watcher process that reports that
child's peak resident set and CPU seconds (``resource.getrusage(RUSAGE_CHILDREN)``, as bench/bench_memory.py does):

- ``simulate``: :func:`synthetic.simulate` of the capture (with the calibration frames ``ultrastage simulate``
  writes); its progress messages give the LED visibility's seconds and the wall and CPU seconds per camera
  (render, sensor noise, DNG and ground-truth files of the three illuminations: the time from the visibility
  message to the last camera's, over the cameras);
- one ``ultrastage run --scheduler sync --no-evaluate --through STAGE`` per stage, in the pipeline's order (each
  finds the earlier stages in the store, so it runs exactly that stage): the stage's task seconds (the release's
  ``manifests/stage_runs.parquet``, summed over its tasks), the process's CPU seconds and peak RSS (the imports'
  floor, :data:`IMPORTS` measured alone, is given beside them); then one run of the whole DAG, every task cached,
  which publishes the whole release (a run publishes its own plan's products only);
- ``ultrastage evaluate --json`` (one evaluation process, ``ULTRASTAGE_EVALUATE_WORKERS=1``): every figure, and
  the evaluation's own CPU seconds and peak RSS.

Growth: per stage a log-log least-squares fit ``seconds = a * pixels ** k`` over the widths (pixels per view =
width x height), its exponent ``k`` and the extrapolation to the production sensor (6016 x 4016, **extrapolated**,
never measured here). The neural SDF (``geometry``) trains a fixed number of steps of a fixed number of rays and
samples (raised once, to ``geometry.fine_first_pass_iterations`` + ``fine_iterations``, where the subject is seen
finer than ``geometry.fine_pixel_m``: the default body wider than about 360 px), so its training does not
grow with the pixels; what grows is reading the 32 views, the visual hull
carved from their masks and the bank of rays worth drawing (built over every pixel), and the held-out and
G-buffer work of the stages after it that read full-size maps.

The **knee** of a figure is the smallest width beyond which no larger width improves it by more than its
tolerance (:data:`KNEE_TOLERANCES`: what a reader would call a change); the knee of the run is the largest over the
headline figures. "Not reached" means the largest width still improves on the one before.

The ``production`` preset is not run: it is the GPU configuration (its SDF trains :func:`production_note`'s
multiple of the default's samples), hours per action on a 2-core CPU; bench/bench_gpu.py times its field step.

Writes bench_resolution.json, .md and bench_resolution.png (figures against pixels per view, time and memory per
stage against pixels per view with the fits, the simulator's seconds per camera with its extrapolation) into
``--out``; each width's measurements are kept in ``OUT/bench_resolution/w<width>.json`` (``--reuse`` reads them back
instead of measuring that width again, when its settings are the same).

    python bench/bench_resolution.py --out bench/out [--widths 192,384,768] [--reuse] [--quick]

``--quick`` (the tests' mode): the ``test`` preset on 8 cameras (128 LEDs, the subject unsubdivided), widths 48 and
64 (32 px is too small for the colour chart), the stages through ``photometric`` in one run and the evaluation of
that partial release; the numbers are not measurements.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _report import write_report  # noqa: E402
from _quick import QUICK_HELP, quick_sim_changes  # noqa: E402

WIDTHS = (192, 384, 768)
"""Capture widths (pixels) of the full run; 1536 px does not fit the 2-core development machine's time."""
CAMERAS = 32
PRESET = "default"
SENSOR = (6016, 4016)
"""The production sensor (width, height): what the fits are extrapolated to."""
QUICK_WIDTHS, QUICK_CAMERAS, QUICK_PRESET = (48, 64), 8, "test"
QUICK_STEPS = ("photometric",)
"""The quick mode's runs: through each named stage (None: the whole DAG)."""
IMPORTS = "imports"
"""The row of the floor every step's process pays: the command line's imports and the preset's stages built."""
HEADLINE = {
    "chamfer_mm": ("Chamfer (mm)", -1),
    "fscore_1mm": ("F-score @1 mm", +1),
    "heldout_albedo_psnr_db": ("held-out albedo PSNR (dB)", +1),
    "heldout_normal_mean_deg": ("held-out normals (deg)", -1),
    "normal_mean_deg": ("normals, valid pixels (deg)", -1),
    "normal_mean_deg_diffuse": ("normals, specular out (deg)", -1),
    "relit_psnr_db": ("relit PSNR (dB)", +1),
    "relightset_image_psnr_db": ("relighting set PSNR (dB)", +1),
}
"""The figures plotted and the knee is taken over: name, label and direction (+1: higher is better)."""
KNEE_TOLERANCES = {"chamfer_mm": 0.1, "fscore_1mm": 0.01, "heldout_albedo_psnr_db": 0.25,
                   "heldout_normal_mean_deg": 0.25, "normal_mean_deg": 0.25, "normal_mean_deg_diffuse": 0.25,
                   "relit_psnr_db": 0.25, "relightset_image_psnr_db": 0.25}
"""Per headline figure, the smallest improvement counted as one (its units: mm, fraction, dB, degrees)."""
WATCHER = ("import json, resource, subprocess, sys, time; t = time.perf_counter(); "
           "rc = subprocess.call(sys.argv[2:]); u = resource.getrusage(resource.RUSAGE_CHILDREN); "
           "json.dump({'rc': rc, 'maxrss_kib': u.ru_maxrss, 'cpu_s': u.ru_utime + u.ru_stime, "
           "'wall_s': time.perf_counter() - t}, open(sys.argv[1], 'w'))")


def height_of(width: int) -> int:
    from synthetic.config import image_height

    return image_height(width)


def production_note() -> str:
    """How much more the production preset's SDF trains than the default's: network samples (rays x samples per
    ray + eikonal points) x steps, over both passes of :func:`stages.numerics.sdf_mesh.pass_configs`."""
    from stages.numerics.sdf_mesh import pass_configs
    from stages.registry import PRESETS

    def passes(name: str) -> list[tuple[int, int]]:
        return [(c.rays_per_batch * c.samples_per_ray + c.eikonal_points, c.iterations)
                for c in pass_configs(PRESETS[name].geometry) if c is not None]

    def words(steps: list[tuple[int, int]]) -> str:
        return " + ".join(f"{n:,} steps of {s:,} samples" for s, n in steps)

    production, default = passes("production"), passes(PRESET)
    ratio = sum(s * n for s, n in production) / sum(s * n for s, n in default)
    return (f"production SDF: {words(production)}, {ratio:.0f} x the {PRESET} preset's ({words(default)})")


def child_env() -> dict[str, str]:
    """The steps' environment: the project first on the path, sleeping OpenMP threads, one evaluation process."""
    path = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return os.environ | {"PYTHONPATH": path,
                         "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE"),
                         "ULTRASTAGE_EVALUATE_WORKERS": "1"}


def watched(command: list[str], scratch: Path, name: str) -> dict[str, Any]:
    """Run ``command`` under a watcher: its peak RSS (MiB), CPU and wall seconds; raises on a non-zero exit."""
    report, log = scratch / f"{name}.watch.json", scratch / f"{name}.log"
    with open(log, "w") as out:
        subprocess.run([sys.executable, "-c", WATCHER, str(report), *command], stdout=out, stderr=subprocess.STDOUT,
                       env=child_env(), cwd=ROOT, check=True)
    watch = json.loads(report.read_text())
    if watch["rc"]:
        raise RuntimeError(f"{name}: {' '.join(command)} exited {watch['rc']}; see {log}:\n"
                           + log.read_text()[-3000:])
    return {"peak_rss_mib": watch["maxrss_kib"] / 1024, "cpu_s": watch["cpu_s"], "wall_s": watch["wall_s"]}


# --- the child processes ----------------------------------------------------------------------------------------

def child_simulate(capture: Path, width: int, cameras: int, quick: bool, stamps_file: Path) -> None:
    """Simulate the capture, writing the progress messages with their seconds since the start to ``stamps_file``."""
    from synthetic import SimConfig, simulate
    from synthetic.calibration import CalibrationConfig

    shutil.rmtree(capture, ignore_errors=True)
    stamps: list[tuple[float, float, str]] = []
    start, cpu_start = time.perf_counter(), time.process_time()
    config = SimConfig(actions=1, width=width, n_cameras=cameras, **(quick_sim_changes() if quick else {}))
    # one action renders in this process (synthetic.simulate.action_workers), so its CPU time is this process's
    simulate(capture, config, calibration=CalibrationConfig(),
             progress=lambda m: stamps.append((time.perf_counter() - start, time.process_time() - cpu_start, m)))
    stamps_file.write_text(json.dumps({"total_s": time.perf_counter() - start, "stamps": stamps}))


def child_imports(preset: str) -> None:
    """The floor of a step's process: the command line's imports and the preset's stages."""
    import ultrastage.cli  # noqa: F401
    from stages.registry import PRESETS, build_stages

    build_stages(PRESETS[preset])


def camera_seconds(stamps: list[tuple[float, float, str]], cameras: int) -> dict[str, float]:
    """From the simulator's messages of one action (wall seconds, CPU seconds, message): the LED visibility's
    seconds and the wall and CPU seconds per camera (from the visibility message to the last camera's)."""
    visibility = next(s for s in stamps if "visibility of" in s[2])
    last = next(s for s in stamps if s[2].endswith(f"{cameras}/{cameras} cameras"))
    seconds = float(visibility[2].rsplit(" in ", 1)[1].removesuffix(" s"))
    return {"visibility_s": seconds, "cameras_s": last[0] - visibility[0],
            "s_per_camera": (last[0] - visibility[0]) / cameras,
            "cpu_s_per_camera": (last[1] - visibility[1]) / cameras}


def camera_cpu_seconds(simulate: dict[str, Any], cameras: int) -> float:
    """The simulator's CPU seconds per camera: measured (``cpu_s_per_camera``), or for measurements saved without
    it estimated as the process's CPU seconds times the cameras' share of its wall time, over the cameras."""
    if "cpu_s_per_camera" in simulate:
        return simulate["cpu_s_per_camera"]
    return simulate["cpu_s"] * simulate["cameras_s"] / max(simulate["total_s"], 1e-9) / cameras


# --- one width --------------------------------------------------------------------------------------------------

def stage_seconds(release: Path) -> dict[str, float]:
    """Task seconds per stage of the tasks that ran (summed over their scopes) in stage_runs.parquet."""
    import pandas as pd

    runs = pd.read_parquet(release / "manifests" / "stage_runs.parquet")
    ran = runs[runs["status"] == "ran"]
    return {str(k): float(v) for k, v in ran.groupby("stage")["seconds"].sum().items()}


def measure_width(width: int, cameras: int, preset: str, steps: list[str | None], scratch: Path,
                  quick: bool) -> dict[str, Any]:
    """Every measurement of one width (see the module docstring)."""
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir(parents=True)
    capture, release = scratch / "capture", scratch / "release"
    me = [sys.executable, str(Path(__file__).resolve())]
    result: dict[str, Any] = {"width": width, "height": height_of(width), "pixels": width * height_of(width),
                              "cameras": cameras, "preset": preset, "quick": quick}
    stamps_file = scratch / "simulate.stamps.json"
    sim = watched(me + ["--child-simulate", str(capture), str(width), str(cameras), str(int(quick)),
                        str(stamps_file)], scratch, "simulate")
    stamps = json.loads(stamps_file.read_text())
    sim |= {"total_s": stamps["total_s"], **camera_seconds(stamps["stamps"], cameras)}
    result["simulate"] = sim
    print(f"w{width}: simulated in {sim['wall_s']:.1f} s ({sim['s_per_camera']:.2f} s per camera), peak "
          f"{sim['peak_rss_mib']:.0f} MiB", flush=True)
    result["imports"] = watched(me + ["--child-imports", preset], scratch, IMPORTS)
    run = [sys.executable, "-m", "ultrastage.cli", "run", "--capture", str(capture), "--release", str(release),
           "--preset", preset, "--scheduler", "sync", "--no-evaluate"]
    result["steps"], seen = [], {}
    for step in steps:
        name = step or "all"
        measured = watched(run + (["--through", step] if step else []), scratch, f"run_{name}")
        seconds = stage_seconds(release)
        new = {s: v for s, v in seconds.items() if s not in seen}
        seen |= new
        result["steps"].append({"through": name, "stages": new, **measured})
        print(f"w{width}: {name}: {', '.join(f'{s} {v:.1f} s' for s, v in new.items()) or 'nothing ran'}; "
              f"process {measured['cpu_s']:.1f} s CPU, peak {measured['peak_rss_mib']:.0f} MiB", flush=True)
    figures = scratch / "evaluate.json"
    result["evaluate"] = watched([sys.executable, "-m", "ultrastage.cli", "evaluate", "--release", str(release),
                                  "--truth", str(capture / "ground_truth"), "--json", str(figures)], scratch,
                                 "evaluate")
    result["figures"] = {k: float(v) for k, v in json.loads(figures.read_text()).items()
                         if isinstance(v, (int, float)) and math.isfinite(v)}
    print(f"w{width}: evaluated in {result['evaluate']['wall_s']:.1f} s: "
          + ", ".join(f"{k} {result['figures'][k]:.3f}" for k in HEADLINE if k in result['figures']), flush=True)
    return result


# --- growth, knee, report ---------------------------------------------------------------------------------------

def power_fit(pixels: list[float], values: list[float]) -> dict[str, Any] | None:
    """Least squares of ``log value = log a + k log pixels``: ``{k, a, r2, residuals, rms_residual}``, the
    residuals being ``log value - (log a + k log pixels)`` per point (natural log: 0.1 is about 10 %); None with
    fewer than two positive points or a single pixel count."""
    import numpy as np

    points = [(p, v) for p, v in zip(pixels, values) if p > 0 and v > 0]
    if len(points) < 2 or len({p for p, _ in points}) < 2:
        return None
    x, y = np.log([p for p, _ in points]), np.log([v for _, v in points])
    k, log_a = np.polyfit(x, y, 1)
    residual = y - (k * x + log_a)
    spread = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(np.sum(residual ** 2)) / spread if spread > 0 else 1.0
    return {"k": float(k), "a": float(math.exp(log_a)), "r2": r2, "residuals": [float(r) for r in residual],
            "rms_residual": float(np.sqrt(np.mean(residual ** 2)))}


def knee(widths: list[int], values: list[float], direction: int, tolerance: float) -> int | None:
    """The smallest width beyond which no larger width improves ``values`` by more than ``tolerance`` (None: the
    largest width still does, over the one before)."""
    for i, width in enumerate(widths):
        if all(direction * (later - values[i]) <= tolerance for later in values[i + 1:]):
            return width if i < len(widths) - 1 else None
    return None


def growth(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Fits of every stage's task seconds, the steps' CPU seconds and peak RSS, the simulator's seconds per camera
    and the evaluation's against pixels per view, with the extrapolation to :data:`SENSOR`; the knees."""
    pixels = [r["pixels"] for r in rows]
    full = SENSOR[0] * SENSOR[1]
    stages = list(dict.fromkeys(s for r in rows for step in r["steps"] for s in step["stages"]))
    series: dict[str, list[float]] = {f"stage {s}": [sum(step["stages"].get(s, 0.0) for step in r["steps"])
                                                     for r in rows] for s in stages}
    series["all stages"] = [sum(v for step in r["steps"] for v in step["stages"].values()) for r in rows]
    floor = [r["imports"]["cpu_s"] for r in rows]
    series |= {f"cpu {step['through']}": [max(r["steps"][i]["cpu_s"] - f, 1e-3) for r, f in zip(rows, floor)]
               for i, step in enumerate(rows[0]["steps"])}
    series["cpu all steps"] = [sum(max(s["cpu_s"] - f, 1e-3) for s in r["steps"]) for r, f in zip(rows, floor)]
    series["simulate s per camera"] = [r["simulate"]["s_per_camera"] for r in rows]
    series["simulate CPU s per camera"] = [camera_cpu_seconds(r["simulate"], r["cameras"]) for r in rows]
    series["simulate (whole capture)"] = [r["simulate"]["wall_s"] for r in rows]
    series["evaluate"] = [r["evaluate"]["cpu_s"] for r in rows]
    series |= {f"peak MiB {step['through']}": [r["steps"][i]["peak_rss_mib"] for r in rows]
               for i, step in enumerate(rows[0]["steps"])}
    fits = {}
    for name, values in series.items():
        fit = power_fit(pixels, values)
        if fit is not None:
            fit["at_sensor_extrapolated"] = fit["a"] * full ** fit["k"]
        fits[name] = fit
    widths = [r["width"] for r in rows]
    knees = {}
    for name, (label, direction) in HEADLINE.items():
        values = [r["figures"].get(name) for r in rows]
        if all(v is not None for v in values):
            knees[name] = knee(widths, values, direction, KNEE_TOLERANCES[name])
    reached = list(knees.values())
    overall = None if (not reached or None in reached) else max(reached)
    return {"series": series, "fits": fits, "knees": knees, "knee_width": overall,
            "knee_reached": bool(reached) and None not in reached, "sensor_pixels": full}


def markdown(report: dict[str, Any]) -> str:
    rows, g = report["rows"], report["growth"]
    widths = [r["width"] for r in rows]
    head = " | ".join(f"{r['width']} x {r['height']}" for r in rows)
    lines = ["# Accuracy and time against resolution", "",
             f"One action, {rows[0]['cameras']} cameras, preset `{report['preset']}`, cold, in-process scheduler "
             "(`ultrastage run --scheduler sync`, one process per stage under a watcher: its peak RSS and CPU "
             "seconds). " + report["production"] + ": not run on a CPU.", "",
             "## Seconds and peak memory per stage", "",
             "Per width: the stage's task seconds (wall, stage_runs.parquet; inflated on a loaded machine) / its "
             "process's CPU seconds above the imports' floor (the floor alone, per width: "
             + ", ".join(f"{r['imports']['cpu_s']:.1f}" for r in rows) + " s CPU; "
             + ", ".join(f"{r['imports']['peak_rss_mib']:.0f}" for r in rows) + " MiB) / the process's peak RSS "
             "MiB. `k`: seconds ~ (pixels per view)^k, least squares in log-log over the widths, of the CPU seconds "
             "and of the task seconds.", "",
             "| step | k CPU | k task | " + head + " |", "|---|---|---|" + "---|" * len(rows)]

    def k_of(name: str) -> str:
        fit = g["fits"].get(name)
        return f"{fit['k']:.2f}" if fit else "-"

    for i, step in enumerate(rows[0]["steps"]):
        names = list(step["stages"])
        label = ", ".join(names) if names else f"{step['through']} (nothing ran: publishes the release)"
        k_task = k_of(f"stage {names[0]}") if len(names) == 1 else "-"
        cells = []
        for r in rows:
            s = r["steps"][i]
            cells.append(f"{sum(s['stages'].values()):.1f} / {s['cpu_s'] - r['imports']['cpu_s']:.1f} / "
                         f"{s['peak_rss_mib']:.0f}")
        lines.append(f"| {label} | {k_of('cpu ' + step['through'])} | {k_task} | " + " | ".join(cells) + " |")
    lines.append(f"| **all stages** | {k_of('cpu all steps')} | {k_of('all stages')} | " + " | ".join(
        f"{sum(v for s in r['steps'] for v in s['stages'].values()):.1f} / "
        f"{sum(s['cpu_s'] - r['imports']['cpu_s'] for s in r['steps']):.1f}"
        f" / {max(s['peak_rss_mib'] for s in r['steps']):.0f}" for r in rows) + " |")
    lines.append(f"| evaluate (wall / whole process CPU / peak) | {k_of('evaluate')} | - | " + " | ".join(
        f"{r['evaluate']['wall_s']:.1f} / {r['evaluate']['cpu_s']:.1f} / {r['evaluate']['peak_rss_mib']:.0f}"
        for r in rows) + " |")
    lines += ["", "## The simulator", "",
              "Per camera: render, sensor noise, the DNGs of three illuminations and the ground-truth files. CPU "
              "seconds per camera: the simulating process's (measurements saved before they were recorded: its "
              "CPU seconds times the cameras' share of its wall time); wall seconds are this machine's under its "
              "load.", "",
              "| width | CPU s per camera | wall s per camera | LED visibility wall s | whole capture wall s "
              "/ CPU s | peak MiB |", "|---|---|---|---|---|---|"]
    for r in rows:
        s = r["simulate"]
        lines.append(f"| {r['width']} x {r['height']} | {camera_cpu_seconds(s, r['cameras']):.2f} | "
                     f"{s['s_per_camera']:.2f} | {s['visibility_s']:.1f} | {s['wall_s']:.1f} / {s['cpu_s']:.1f} | "
                     f"{s['peak_rss_mib']:.0f} |")
    for name, what in (("simulate CPU s per camera", "CPU seconds"), ("simulate s per camera", "wall seconds")):
        fit = g["fits"].get(name)
        if fit:
            per_cam = fit["at_sensor_extrapolated"]
            lines += ["", f"{what} per camera ~ pixels^{fit['k']:.2f} (R^2 {fit['r2']:.3f}); at {SENSOR[0]} x "
                      f"{SENSOR[1]} **extrapolated, not measured**: {per_cam:.0f} s per camera, "
                      f"{per_cam * CAMERAS / 60:.0f} min for the {CAMERAS} cameras of one action (the LED visibility "
                      "and the session's calibration frames not counted)."]
    lines += ["", "## Fits (seconds ~ pixels per view ^ k) and the production sensor, extrapolated", "",
              "Residuals: log(measured) - log(fit) per width, smallest first (natural log: 0.10 is about 10 %); "
              "with two widths they are zero.", "",
              "| series | k | R^2 | residuals | at 6016 x 4016 (extrapolated) |", "|---|---|---|---|---|"]
    for name, fit in g["fits"].items():
        if fit:
            unit = "MiB" if name.startswith("peak") else "s"
            residuals = ", ".join(f"{r:+.2f}" for r in fit.get("residuals", []))
            lines.append(f"| {name} | {fit['k']:.2f} | {fit['r2']:.3f} | {residuals} | "
                         f"{fit['at_sensor_extrapolated']:.0f} {unit} |")
    lines += ["", "The SDF (`geometry`) trains a fixed number of steps of fixed rays x samples, so its training does "
              "not grow with the pixels; what grows is reading the views, the hull carved from their masks and the "
              "bank of rays worth drawing (over every pixel).", "",
              "## Every figure of `ultrastage evaluate --json`", "", "| figure | " + head + " |",
              "|---|" + "---|" * len(rows)]
    names = sorted({k for r in rows for k in r["figures"]})
    for name in names:
        bold = "**" if name in HEADLINE else ""
        lines.append(f"| {bold}{name}{bold} | " + " | ".join(
            f"{r['figures'][name]:.4g}" if name in r["figures"] else "-" for r in rows) + " |")
    lines += ["", "## The knee", "",
              "Per headline figure, the smallest width beyond which no larger one improves it by more than its "
              "tolerance (" + ", ".join(f"{k} {v:g}" for k, v in KNEE_TOLERANCES.items()) + "):", ""]
    for name, width in g["knees"].items():
        lines.append(f"- {HEADLINE[name][0]}: " + (f"{width} px" if width else f"not reached by {widths[-1]} px"))
    cost = g["series"]["cpu all steps"]
    lines += ["", "What the pixels cost (every stage's CPU seconds above the imports, per width): " + ", ".join(
        f"{w} px {c:.0f} s" + (f" ({c / cost[0]:.1f} x)" if i else "") for i, (w, c) in enumerate(zip(widths, cost)))
        + "."]
    lines += ["", ("The knee of the run: **" + (f"{g['knee_width']} px wide" if g["knee_reached"] else
                                                   f"not reached by {widths[-1]} px") + "** (the largest over the "
                   "headline figures).")]
    return "\n".join(lines) + "\n"


def plot(path: Path, report: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows, g = report["rows"], report["growth"]
    pixels = np.array([r["pixels"] for r in rows], float)
    fig, axes = plt.subplots(2, 3, figsize=(16, 9))
    groups = ((axes[0, 0], ("chamfer_mm", "heldout_normal_mean_deg", "normal_mean_deg", "normal_mean_deg_diffuse"),
               "lower is better (mm, deg)"),
              (axes[0, 1], ("heldout_albedo_psnr_db", "relit_psnr_db", "relightset_image_psnr_db"), "PSNR (dB)"),
              (axes[0, 2], ("fscore_1mm",), "F-score @1 mm"))
    for ax, names, ylabel in groups:
        for name in names:
            values = [r["figures"].get(name, np.nan) for r in rows]
            ax.plot(pixels, values, "o-", label=HEADLINE[name][0])
        ax.set_xscale("log")
        ax.set_xlabel("pixels per view")
        ax.set_ylabel(ylabel)
        if g["knee_reached"]:
            ax.axvline(g["knee_width"] * height_of(g["knee_width"]), ls=":", c="k",
                       label=f"knee {g['knee_width']} px")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    ax = axes[1, 0]
    grid = np.geomspace(pixels.min(), pixels.max(), 20)
    steps = [n for n in g["series"] if n.startswith("cpu ") and n != "cpu all steps"]
    for k, name in enumerate(steps):
        values, fit = g["series"][name], g["fits"].get(name)
        colour = plt.cm.tab20(k % 20)
        label = name.removeprefix("cpu ") + (f" k={fit['k']:.2f}" if fit else "")
        ax.plot(pixels, values, "o", color=colour, label=label)
        if fit:
            ax.plot(grid, fit["a"] * grid ** fit["k"], "-", color=colour, lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("pixels per view")
    ax.set_ylabel("CPU seconds above the imports")
    ax.set_title("CPU time per stage, seconds ~ pixels^k", fontsize=9)
    ax.legend(fontsize=6, ncol=2)
    ax.grid(alpha=0.3)
    ax = axes[1, 1]
    for k, (name, values) in enumerate((n, v) for n, v in g["series"].items() if n.startswith("peak MiB")):
        ax.plot(pixels, values, "o-", color=plt.cm.tab20(k % 20), label=name.removeprefix("peak MiB "))
    ax.set_xscale("log")
    ax.set_xlabel("pixels per view")
    ax.set_ylabel("peak RSS (MiB)")
    ax.set_title("peak memory per step", fontsize=9)
    ax.legend(fontsize=6, ncol=2)
    ax.grid(alpha=0.3)
    ax = axes[1, 2]
    values = g["series"]["simulate CPU s per camera"]
    ax.loglog(pixels, values, "o", label="measured (CPU s)")
    fit = g["fits"].get("simulate CPU s per camera")
    if fit:
        far = np.geomspace(pixels.min(), g["sensor_pixels"], 30)
        ax.loglog(far, fit["a"] * far ** fit["k"], "--", label=f"fit k={fit['k']:.2f} (extrapolated)")
        ax.loglog([g["sensor_pixels"]], [fit["at_sensor_extrapolated"]], "x", ms=10,
                  label=f"6016 x 4016: {fit['at_sensor_extrapolated']:.0f} s (extrapolated)")
    ax.set_xlabel("pixels per view")
    ax.set_ylabel("simulator CPU seconds per camera")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.suptitle(f"{rows[0]['cameras']} cameras, preset {report['preset']}" + (" (quick: not measurements)"
                                                                               if report["quick"] else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--widths", help=f"comma-separated capture widths (default {','.join(map(str, WIDTHS))})")
    parser.add_argument("--reuse", action="store_true",
                        help="read a width's measurements from OUT/bench_resolution/w<width>.json when its settings "
                             "are the same, instead of measuring it again")
    parser.add_argument("--keep", action="store_true", help="keep each width's capture and release")
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    parser.add_argument("--child-simulate", nargs=5, help=argparse.SUPPRESS)
    parser.add_argument("--child-imports", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child_simulate:
        capture, width, cameras, quick, stamps = args.child_simulate
        child_simulate(Path(capture), int(width), int(cameras), bool(int(quick)), Path(stamps))
        return 0
    if args.child_imports:
        child_imports(args.child_imports)
        return 0
    out = Path(args.out)
    store = out / "bench_resolution"
    store.mkdir(parents=True, exist_ok=True)
    widths = [int(w) for w in args.widths.split(",")] if args.widths else list(QUICK_WIDTHS if args.quick else WIDTHS)
    if len(widths) < 1 or min(widths) < 16:
        parser.error(f"--widths {args.widths}: give widths of at least 16 px")
    cameras, preset = (QUICK_CAMERAS, QUICK_PRESET) if args.quick else (CAMERAS, PRESET)
    if args.quick:
        steps: list[str | None] = list(QUICK_STEPS)
    else:
        from stages.registry import STAGE_CLASSES

        # then the whole DAG once more: every task cached, it publishes the whole release (a run publishes the
        # products of its own plan only, so the last stage's run alone would leave the others' out)
        steps = [cls.name for cls in STAGE_CLASSES] + [None]
    rows = []
    for width in sorted(widths):
        saved = store / f"w{width}.json"
        settings = {"cameras": cameras, "preset": preset, "quick": args.quick,
                    "step_names": [s or "all" for s in steps]}
        if args.reuse and saved.exists():
            row = json.loads(saved.read_text())
            if {k: row.get(k) for k in settings} == settings:
                print(f"w{width}: measurements read from {saved}", flush=True)
                rows.append(row)
                continue
        row = measure_width(width, cameras, preset, steps, store / f"w{width}", args.quick) | settings
        saved.write_text(json.dumps(row, indent=1))
        if not args.keep:
            shutil.rmtree(store / f"w{width}", ignore_errors=True)
        rows.append(row)
    report = {"quick": args.quick, "preset": preset, "cameras": cameras, "widths": [r["width"] for r in rows],
              "production": production_note(), "rows": rows}
    report["growth"] = growth(rows)
    write_report(out, "bench_resolution", report, markdown(report), lambda path: plot(path, report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
