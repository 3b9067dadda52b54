"""The production path on a GPU machine: one action simulated large, run with the production and default presets.

What a stage operator needs before the 2,000-action release: the wall time of every stage of one action at a
large capture size on one GPU, the SDF's steps per second and peak GPU memory, and the accuracy of each preset
there. The bench

1. simulates one action (32 cameras) at ``--width`` pixels (``--probe-width``: first a small capture, timed,
   and then the largest of ``--widths`` whose simulation is predicted, at the probe's seconds per pixel, to fit
   ``--simulate-budget-s``), timing the simulator per camera;
2. runs ``ultrastage run`` on it with each of ``--presets`` in turn (a local dask cluster sized to the machine,
   the geometry stage on the GPU when torch sees one), each under what is left of ``--budget-s``: a run cut
   short still reports the tasks its log shows finished;
3. reads each release's ``manifests/stage_runs.parquet`` (seconds per task) and the geometry stage's success
   record (the SDF's training seconds, steps per second, device and peak GPU memory), and runs
   ``ultrastage evaluate --json`` where time is left.

Writes ``bench_gpu_production.json`` and ``bench_gpu_production.md`` to ``--out``. The field step alone against one
CPU thread is ``bench/bench_gpu.py``; ``bench/bench_projection.py --gpu-speedup`` takes the measured speed-up.

    python bench/bench_gpu_production.py --out DIR --work DIR [--width 1024 | --probe-width 256]
        [--presets production,default] [--budget-s 480] [--quick]

Without a CUDA device it writes a report that says so and runs nothing (``--allow-cpu`` runs it on the CPU: hours
for the production preset's 20,000 SDF steps). ``--quick`` (the tests' mode): the benches' shared tiny capture
(bench/_quick.py) through the photometric stage with the test preset, on whatever device is there; its numbers are
not measurements.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TASK_LINE = re.compile(r"\[\s*(\d+)/(\d+)\]\s+([\d.]+)s\s+(\w+)\s+(\S+)\s+(\w+)")
"""A finished task in ``ultrastage run``'s output: ``[  7/22]   21.3s  decode       A0001    ok (6.8s cpu)``."""


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "ultrastage.cli", *args]


def _run_logged(cmd: list[str], log: Path, timeout_s: float, env: dict | None = None) -> dict:
    """Run ``cmd`` with its output (stamped with seconds since the start) in ``log``; wall seconds, exit code, and
    whether it was stopped at ``timeout_s``."""
    started = time.perf_counter()
    timed_out = False
    with open(log, "w", encoding="utf-8") as sink:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}, start_new_session=True)
        assert proc.stdout is not None
        os.set_blocking(proc.stdout.fileno(), False)
        while True:
            line = proc.stdout.readline()
            if line:
                stamped = f"{time.perf_counter() - started:8.1f}s | {line}"
                sink.write(stamped)
                sink.flush()
                print(stamped, end="", flush=True)
                continue
            if proc.poll() is not None:
                rest = proc.stdout.read() or ""
                sink.write(rest)
                print(rest, end="", flush=True)
                break
            if time.perf_counter() - started > timeout_s:
                timed_out = True
                os.killpg(proc.pid, 9)
                proc.wait()
                break
            time.sleep(0.05)
    return {"wall_s": round(time.perf_counter() - started, 2), "returncode": proc.returncode,
            "timed_out": timed_out}


def simulate(capture: Path, width: int, cameras: int) -> dict:
    """Simulate one action of ``cameras`` cameras at ``width`` px into ``capture``; wall seconds in all and per
    camera."""
    from synthetic import SimConfig
    from synthetic import simulate as run_simulator

    shutil.rmtree(capture, ignore_errors=True)
    started = time.perf_counter()
    run_simulator(capture, SimConfig(actions=1, width=width, n_cameras=cameras))
    wall = time.perf_counter() - started
    return {"width": width, "cameras": cameras, "wall_s": round(wall, 2), "s_per_camera": round(wall / cameras, 3)}


def pick_width(probe: dict, widths: list[int], budget_s: float) -> int:
    """The largest of ``widths`` whose simulation, at the probe's seconds per pixel, is predicted within
    ``budget_s`` (the probe's width when none is)."""
    per_pixel = probe["wall_s"] / probe["width"] ** 2
    fitting = [w for w in widths if per_pixel * w ** 2 <= budget_s]
    return max(fitting) if fitting else probe["width"]


def stage_seconds(release: Path) -> dict:
    """Per stage: the number of tasks that ran and their seconds (sum and largest) in the release's last run."""
    import pandas as pd

    path = release / "manifests" / "stage_runs.parquet"
    if not path.exists():
        return {}
    runs = pd.read_parquet(path)
    ran = runs[runs["status"] == "ran"]
    out = {}
    for stage, rows in ran.groupby("stage", sort=False):
        out[stage] = {"tasks": int(len(rows)), "seconds_sum": round(float(rows["seconds"].sum()), 2),
                      "seconds_max": round(float(rows["seconds"].max()), 2)}
    return out


def logged_tasks(log: Path) -> dict:
    """The tasks a run's log shows finished: per stage, their count and the seconds since the run's start at
    which the last one ended (what a run cut short still tells)."""
    out: dict[str, dict] = {}
    for line in log.read_text(encoding="utf-8", errors="replace").splitlines():
        match = TASK_LINE.search(line)
        if match:
            _, _, at_s, stage, _, status = match.groups()
            entry = out.setdefault(stage, {"finished": 0, "last_at_s": 0.0, "statuses": {}})
            entry["finished"] += 1
            entry["last_at_s"] = max(entry["last_at_s"], float(at_s))
            entry["statuses"][status] = entry["statuses"].get(status, 0) + 1
    return out


def geometry_stats(work: Path) -> dict:
    """The SDF's figures from the geometry stage's success record(s) in the work store."""
    found = {}
    for success in sorted(work.glob("**/geometry/*/*/_SUCCESS.json")):
        stats = json.loads(success.read_text()).get("stats", {})
        sdf = stats.get("sdf", {})
        found[success.parent.parent.name] = {
            "train_seconds": stats.get("train_seconds"), "passes": stats.get("passes"),
            "device": sdf.get("device"), "iterations": sdf.get("iterations"), "steps_per_s": sdf.get("steps_per_s"),
            "gpu_name": sdf.get("gpu_name"), "gpu_peak_memory_gib": (round(sdf["gpu_peak_memory_bytes"] / 2 ** 30, 2)
                                                                     if "gpu_peak_memory_bytes" in sdf else None),
            "mesh_faces": stats.get("mesh_faces")}
    return found


def run_preset(capture: Path, root: Path, preset: str, timeout_s: float, evaluate: bool, out: Path,
               through: str | None = None) -> dict:
    """One preset's run (``through``: that stage and what it needs), its per-stage seconds, its SDF figures and
    (time permitting) its accuracy."""
    release, work = root / f"release-{preset}", root / f"work-{preset}"
    shutil.rmtree(release, ignore_errors=True)
    shutil.rmtree(work, ignore_errors=True)
    started = time.perf_counter()
    run = _run_logged(_cli("run", "--capture", str(capture), "--release", str(release), "--work", str(work),
                           "--preset", preset, "--no-evaluate", *(["--through", through] if through else [])),
                      out / f"run-{preset}.log", timeout_s)
    result = {"preset": preset, "run": run, "stages": stage_seconds(release),
              "logged": logged_tasks(out / f"run-{preset}.log"), "geometry": geometry_stats(work)}
    left = timeout_s - (time.perf_counter() - started)
    if evaluate and run["returncode"] == 0 and left > 30:
        metrics = out / f"metrics-{preset}.json"
        result["evaluate"] = _run_logged(_cli("evaluate", "--release", str(release), "--truth",
                                              str(capture / "ground_truth"), "--json", str(metrics)),
                                         out / f"evaluate-{preset}.log", left,
                                         env={"ULTRASTAGE_EVALUATE_WORKERS": str(max(1, min(8, os.cpu_count() or 1)))})
        if metrics.exists():
            result["metrics"] = json.loads(metrics.read_text())
    return result


KEY_METRICS = ("cam_rotation_err_deg", "cam_center_err_mm", "normal_mean_deg", "albedo_psnr_db", "chamfer_mm",
               "fscore_1mm", "heldout_albedo_psnr_db", "heldout_albedo_ssim", "heldout_normal_mean_deg",
               "roughness_mae", "relit_psnr_db", "relightset_image_psnr_db")
"""The ``ultrastage evaluate --json`` figures the report's table shows (the JSON keeps them all)."""


def markdown(report: dict) -> str:
    machine = report["machine"]
    lines = ["# bench_gpu_production: one action at production size on one GPU", "",
             f"Machine: {machine['gpu'] or 'no CUDA device'}, {machine['cpus']} CPUs, torch {machine['torch']}.",
             f"Capture: 1 action, {report['simulate']['cameras']} cameras, {report['simulate']['width']} px wide; " +
             (f"an existing capture ({report['simulate']['existing']}), its simulation not timed here."
              if "existing" in report["simulate"] else
              f"simulated in {report['simulate']['wall_s']:.1f} s ({report['simulate']['s_per_camera']:.2f} s per "
              "camera)."), ""]
    if report.get("probe"):
        lines.insert(-1, f"Probe: {report['probe']['width']} px in {report['probe']['wall_s']:.1f} s.")
    for res in report["presets"]:
        run = res["run"]
        state = "timed out" if run["timed_out"] else f"exit {run['returncode']}"
        lines += [f"## Preset `{res['preset']}`: run wall {run['wall_s']:.1f} s ({state})", "",
                  "| stage | tasks | task seconds (sum) | largest task s | finished by (s into the run) |",
                  "|---|---|---|---|---|"]
        names = list(dict.fromkeys(list(res["stages"]) + list(res["logged"])))
        for name in names:
            s, lg = res["stages"].get(name, {}), res["logged"].get(name, {})
            lines.append(f"| {name} | {s.get('tasks', lg.get('finished', 0))} | {s.get('seconds_sum', '-')} | "
                         f"{s.get('seconds_max', '-')} | {lg.get('last_at_s', '-')} |")
        for action, g in res["geometry"].items():
            lines += ["", f"SDF ({action}): {g['iterations']} steps on {g['device']} ({g['gpu_name'] or 'CPU'}), "
                      f"{g['steps_per_s'] or 0:.1f} steps/s, training {g['train_seconds'] or 0:.1f} s over "
                      f"{g['passes']} pass(es), peak GPU memory {g['gpu_peak_memory_gib']} GiB, "
                      f"{g['mesh_faces']} mesh faces."]
        metrics = res.get("metrics")
        if metrics:
            lines += ["", "| figure | value |", "|---|---|"]
            lines += [f"| {k} | {metrics[k]:.4g} |" for k in KEY_METRICS if isinstance(metrics.get(k), (int, float))]
        lines.append("")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="folder of the report and the runs' logs")
    parser.add_argument("--work", help="folder of the capture, releases and work stores (default OUT/work)")
    parser.add_argument("--capture", help="an existing one-action capture (no simulation)")
    parser.add_argument("--width", type=int, default=1024, help="capture width when simulating")
    parser.add_argument("--probe-width", type=int, help="simulate this width first and pick from --widths")
    parser.add_argument("--widths", default="768,1024,1536,2048", help="candidate widths for --probe-width")
    parser.add_argument("--simulate-budget-s", type=float, default=120.0)
    parser.add_argument("--cameras", type=int, default=32)
    parser.add_argument("--presets", default="production,default")
    parser.add_argument("--budget-s", type=float, default=480.0, help="wall seconds for all the presets' runs")
    parser.add_argument("--no-evaluate", action="store_true")
    parser.add_argument("--simulate-only", action="store_true", help="simulate (and write the report) only")
    parser.add_argument("--allow-cpu", action="store_true", help="run even where torch sees no CUDA device")
    parser.add_argument("--quick", action="store_true", help="a tiny capture through the test preset (tests)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    root = Path(args.work) if args.work else out / "work"
    root.mkdir(parents=True, exist_ok=True)

    import torch

    report: dict = {"machine": {"gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
                                "cpus": os.cpu_count(), "torch": torch.__version__}, "quick": bool(args.quick)}
    presets = ["test"] if args.quick else [p.strip() for p in args.presets.split(",") if p.strip()]
    cameras = args.cameras
    previous = out / "bench_gpu_production.json"
    if report["machine"]["gpu"] is None and not (args.quick or args.allow_cpu):
        report["skipped"] = "torch sees no CUDA device: nothing run (--allow-cpu to run on the CPU)"
        previous.write_text(json.dumps(report, indent=1))
        (out / "bench_gpu_production.md").write_text(
            "# bench_gpu_production: one action at production size on one GPU\n\n" + report["skipped"] + ".\n")
        print(report["skipped"])
        return 0
    if args.quick and not args.capture:
        sys.path.insert(0, str(ROOT / "bench"))
        from _quick import QUICK_CAMERAS, quick_run

        args.capture, cameras = str(quick_run(out) / "capture"), QUICK_CAMERAS
    if args.capture:
        capture = Path(args.capture)
        meta = json.loads((capture / "capture.json").read_text())
        report["simulate"] = {"width": meta.get("simulator", {}).get("width"), "cameras": cameras,
                              "wall_s": 0.0, "s_per_camera": 0.0, "existing": str(capture)}
        if previous.exists():  # the timings of a --simulate-only run that made this capture
            earlier = json.loads(previous.read_text())
            if earlier.get("capture") == str(capture.resolve()):
                report.update({k: earlier[k] for k in ("simulate", "probe") if k in earlier})
    else:
        capture = root / "capture"
        width = args.width
        if args.probe_width:
            report["probe"] = simulate(root / "probe", args.probe_width, cameras, False)
            shutil.rmtree(root / "probe", ignore_errors=True)
            width = pick_width(report["probe"], [int(w) for w in args.widths.split(",")], args.simulate_budget_s)
        report["simulate"] = simulate(capture, width, cameras)
    report["capture"] = str(capture.resolve())
    print(f"capture {capture}: {report['simulate']}", flush=True)
    if args.simulate_only:
        previous.write_text(json.dumps(report, indent=1, default=str))
        return 0
    report["presets"] = []
    deadline = time.perf_counter() + args.budget_s
    for preset in presets:
        left = deadline - time.perf_counter()
        if left < 20:
            report["presets"].append({"preset": preset, "run": {"wall_s": 0.0, "returncode": None,
                                                                "timed_out": True}, "stages": {}, "logged": {},
                                      "geometry": {}, "skipped": "no time left"})
            continue
        report["presets"].append(run_preset(capture, root, preset, left, not (args.no_evaluate or args.quick), out,
                                            through="photometric" if args.quick else None))
        (out / "bench_gpu_production.json").write_text(json.dumps(report, indent=1, default=str))
    (out / "bench_gpu_production.json").write_text(json.dumps(report, indent=1, default=str))
    (out / "bench_gpu_production.md").write_text(markdown(report))
    print(markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
