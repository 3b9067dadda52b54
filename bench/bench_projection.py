"""Projected wall time and storage of the whole release (2,000 actions of 32 cameras at 6016 x 4016 and the
1,500-example relighting set) for N CPU workers and M GPUs, from the per-stage costs a run recorded.

Measured: each stage's seconds per scope in a release's ``manifests/stage_runs.parquet`` (the latest run that ran
it; a per-camera stage's seconds are the sum over its cameras, so they are one worker's seconds), the release's
bytes per asset kind (``assets.parquet``), the work store's bytes per stage (``<work>/artifacts``, hard links
counted once), the capture's raw bytes, and, when present in ``--out``, the engine's overhead per task
(bench_scale.json) and a worker's peak memory (bench_memory.json). Those are at the default preset and resolution
(``make dataset``: 320 x 480, two actions on a 2-core machine shared by both workers: contention included).

Scaled to the production preset by stated rules (the table says which rule each stage gets):

- ``sensor``: the stage reads whole raw frames: x (6016 x 4016) / (capture pixels);
- ``maps``: per-pixel work on the production maps (half size, 3008 x 2008): x that / capture pixels;
- ``texels``: texture-space work: x the production textures' texel count / the default's (textures 4096^2 vs 1024^2,
  materials 1024^2 and occlusion 2048^2 vs 256^2 and 512^2);
- ``relight``: maps x novel views (6 vs 3) x SG lobes (64 vs 32);
- ``geometry`` (the GPU stage, ``resources = {"GPU": 1}``): x the SDF's ray samples over both passes
  (production 2 x 20,000 steps of 4096 rays x 16 samples vs 600 + 1,800 steps of 512 x 8), divided by an
  ASSUMED speed-up of one GPU over the one CPU core that measured it (``--gpu-speedup``; no GPU here);
- the relighting set: seconds per example x (512 / 256)^2 pixels x 2 SG lobes, for 1,500 examples.

Wall time for N CPU workers (one core each, as the default cluster runs them) and M GPUs:
``raw hashing + max(CPU work / N, GPU work / M) + one action's critical path + engine``, where raw hashing (the
plan's sha256 of every raw frame, :meth:`pipeline.hashing.DigestCache.digest_all`) runs in the driver's thread
pool, one thread per driver core (``--driver-cores``, ASSUMED), at the single-thread sha256 rate times the
parallel efficiency that pool measured here on the cores of this machine; the sha256 of every release file (for
the assets table) is done by the task that wrote the file (its success record), so it is CPU work on the workers,
at the single-thread rate; and the engine term is bench_scale's planning and bookkeeping per task. Disk and network
bandwidth are not counted. Writes bench_projection.json, bench_projection.md and bench_projection.png (matplotlib).

``python bench/bench_projection.py --out bench/out [--release runs/default/release] [--gpu-speedup 100]
[--driver-cores 16]``
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

ACTIONS = 2000
EXAMPLES = 1500
CAMERAS = 32
SENSOR = (6016, 4016)
ACTIONS_PER_SESSION = 50
"""Assumed: a capture session (its calibration frames and clean plates) per 50 actions."""
RAW_BYTES_PER_PIXEL = 2
"""The raw frames as the simulator writes them: uncompressed 16-bit DNG (a camera's compressed raw is smaller)."""
CPU_WORKERS = (16, 64, 256, 1024)
GPU_COUNTS = (1, 4, 8, 32)


def sdf_samples(geometry: Any) -> float:
    """Network samples of the geometry stage's SDF training: both passes' steps x (rays x samples + eikonal points)."""
    from stages.numerics.sdf_mesh import pass_configs

    return sum(c.iterations * (c.rays_per_batch * c.samples_per_ray + c.eikonal_points)
               for c in pass_configs(geometry) if c is not None)


def factors(capture_pixels: float) -> dict[str, tuple[str, float]]:
    """Stage -> (rule, factor) from the default preset to the production preset at the production sensor."""
    from stages.registry import PRESETS

    default, production = PRESETS["default"], PRESETS["production"]
    sensor = SENSOR[0] * SENSOR[1] / capture_pixels
    maps = sensor / 4 if production.decode.half_size else sensor
    tex = production.textures.texture_size ** 2 / default.textures.texture_size ** 2
    mat = (production.materials.texture_size ** 2 + production.materials.occlusion_size ** 2) / (
        default.materials.texture_size ** 2 + default.materials.occlusion_size ** 2)
    relight = maps * production.relight.novel_views / default.relight.novel_views * \
        production.relight.sg_lobes / default.relight.sg_lobes
    geometry = sdf_samples(production.geometry) / sdf_samples(default.geometry)
    return {"cameras": ("sensor", sensor), "colour": ("sensor", sensor), "lights": ("sensor", sensor),
            "plates": ("sensor", sensor), "decode": ("sensor", sensor), "photometric": ("maps", maps),
            "diffuse_normals": ("maps", maps), "geometry": ("geometry", geometry), "textures": ("texels", tex),
            "materials": ("texels", mat), "relight": ("relight", relight), "exports": ("maps", maps)}


def relightset_factor() -> float:
    from stages.registry import PRESETS

    d, p = PRESETS["default"].relightset, PRESETS["production"].relightset
    return (p.size / d.size) ** 2 * p.sg_lobes / d.sg_lobes


def measured_seconds(release: Path) -> tuple[dict[str, list[float]], dict[str, Any]]:
    """Stage -> seconds per scope (the latest run that ran each scope), and the release's actions table facts."""
    from manifests import open_release

    rel = open_release(release)
    runs = rel.stage_runs
    ran = runs[runs.status == "ran"].sort_values("run_id")
    latest = ran.groupby(["stage", "scope_id"]).tail(1)
    seconds = {stage: group.seconds.tolist() for stage, group in latest.groupby("stage")}
    actions = rel.actions
    info = {"actions": int(len(actions)), "width": int(actions.width.iloc[0]), "height": int(actions.height.iloc[0]),
            "n_cameras": int(actions.n_cameras.iloc[0]), "runs": sorted(set(latest.run_id))}
    examples = rel.relight_examples if rel.has_table("relight_examples") else None
    info["examples"] = 0 if examples is None else int(len(examples))
    return seconds, info


def release_bytes(release: Path) -> dict[str, float]:
    """Bytes of the release per action, split by what they scale with (per-camera maps, textures, the rest)."""
    from manifests import open_release

    assets = open_release(release).assets
    per_action = assets[assets.action_id.notna()]
    n = max(1, per_action.action_id.nunique())
    cams = per_action.camera_id.notna() & per_action.camera_id.str.match(r"^[0-9]{5}$").fillna(False)
    novel = per_action.camera_id.notna() & per_action.camera_id.str.startswith("N").fillna(False)
    examples = per_action.path.str.startswith("relight/")
    textures = per_action.kind.str.contains("texture") & ~cams & ~novel & ~examples
    meshes = per_action.kind.str.contains("mesh|colmap_points") & ~cams & ~novel & ~examples & ~textures
    rest = ~(cams | novel | textures | examples | meshes)
    return {"camera_maps": float(per_action[cams].bytes.sum() / n), "novel_views": float(per_action[novel].bytes.sum() / n),
            "textures": float(per_action[textures].bytes.sum() / n), "meshes": float(per_action[meshes].bytes.sum() / n),
            "examples_total": float(per_action[examples].bytes.sum()),
            "other": float(per_action[rest].bytes.sum() / n),
            "release_wide": float(assets[assets.action_id.isna()].bytes.sum())}


def store_bytes(work: Path) -> dict[str, float]:
    """Stage -> bytes per scope of the committed artifacts in ``<work>/artifacts`` (each inode once)."""
    seen: set[tuple[int, int]] = set()
    out: dict[str, float] = {}
    root = work / "artifacts"
    if not root.is_dir():
        return out
    for stage_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        scopes = [p for p in stage_dir.iterdir() if p.is_dir()]
        total = 0
        for scope in scopes:
            for dirpath, _, names in os.walk(scope):
                if "/.tmp-" in dirpath or "/.old-" in dirpath:
                    continue
                for name in names:
                    st = os.stat(os.path.join(dirpath, name))
                    if (st.st_dev, st.st_ino) not in seen:
                        seen.add((st.st_dev, st.st_ino))
                        total += st.st_size
        out[stage_dir.name] = total / max(1, len(scopes))
    return out


def sha256_rate(megabytes: int = 256) -> float:
    """Bytes per second of hashlib's sha256 in this process (what the driver's digests run at, disk aside)."""
    data = os.urandom(1 << 20) * megabytes
    start = time.perf_counter()
    hashlib.sha256(data).hexdigest()
    return len(data) / (time.perf_counter() - start)


def driver_hash_scaling(megabytes: int = 128, files: int = 32) -> dict[str, float]:
    """The driver's raw-frame hashing, measured: ``DigestCache.digest_all`` over ``files`` files of
    ``megabytes`` in all (in the page cache: sha256, not the disk), with one thread and with one per core of this
    machine. Returns the bytes per second of each and the parallel efficiency (speed-up / threads)."""
    import tempfile

    from pipeline.hashing import DigestCache

    threads = os.cpu_count() or 1
    with tempfile.TemporaryDirectory(prefix="bench_projection_") as tmp:
        paths = []
        block = os.urandom((megabytes << 20) // files)
        for i in range(files):
            paths.append(Path(tmp) / f"{i:05d}.dng")
            paths[-1].write_bytes(block[i:] + block[:i])
        rates = {}
        for n in (1, threads, 1, threads):  # twice each, the best kept: the machine may be shared
            start = time.perf_counter()
            DigestCache(Path(tmp) / f"digests-{n}-{time.perf_counter_ns()}.json").digest_all(paths, threads=n)
            rates[n] = max(rates.get(n, 0.0), (megabytes << 20) / (time.perf_counter() - start))
    return {"threads": threads, "one_thread_bytes_per_s": rates[1], "all_threads_bytes_per_s": rates[threads],
            "efficiency": min(1.0, rates[threads] / rates[1] / threads)}


def project(stage_s: dict[str, float], per_session: set[str], rules: dict[str, tuple[str, float]],
            example_s: float, gpu_speedup: float, raw_hash_s: float, publish_hash_s: float, engine_s: float,
            cameras: int) -> dict[str, Any]:
    """CPU and GPU seconds of the release and the wall time for each N, M. ``raw_hash_s``: the driver's wall
    seconds hashing raw frames; ``publish_hash_s``: the core-seconds of hashing the release files, done by the
    tasks that write them (CPU work)."""
    from stages.registry import STAGE_CLASSES

    per_view = {cls.name for cls in STAGE_CLASSES if cls.per_view}
    gpu_stages = {cls.name for cls in STAGE_CLASSES if cls.resources.get("GPU")}
    sessions = math.ceil(ACTIONS / ACTIONS_PER_SESSION)
    rows, cpu_total, gpu_total = {}, 0.0, 0.0
    for stage, seconds in stage_s.items():
        if stage == "relightset":
            continue
        rule, factor = rules[stage]
        scaled = seconds * factor
        count = sessions if stage in per_session else ACTIONS
        if stage in gpu_stages:
            scaled /= gpu_speedup
            gpu_total += scaled * count
        else:
            cpu_total += scaled * count
        rows[stage] = {"measured_s": seconds, "rule": rule, "factor": factor, "production_s": scaled,
                       "per": "session" if stage in per_session else "action", "count": count,
                       "resource": "GPU" if stage in gpu_stages else "CPU", "total_h": scaled * count / 3600}
    example = example_s * relightset_factor()
    rows["relightset"] = {"measured_s": example_s, "rule": "examples", "factor": relightset_factor(),
                          "production_s": example, "per": "example", "count": EXAMPLES, "resource": "CPU",
                          "total_h": example * EXAMPLES / 3600}
    cpu_total += example * EXAMPLES
    cpu_total += publish_hash_s

    def critical(n: int) -> float:
        width = min(n, cameras)
        chain = ["decode", "photometric", "geometry", "textures", "materials", "diffuse_normals"]
        path = sum(rows[s]["production_s"] / (width if s in per_view else 1) for s in chain if s in rows)
        tail = max([rows[s]["production_s"] for s in ("relight", "exports") if s in rows]
                   + [example * EXAMPLES / ACTIONS])
        return path + tail

    walls = {}
    for n in CPU_WORKERS:
        for m in GPU_COUNTS:
            work = max(cpu_total / n, gpu_total / m)
            walls[f"{n},{m}"] = {"workers": n, "gpus": m, "hours": (raw_hash_s + work + critical(n) + engine_s) / 3600,
                                 "bound": "GPU" if gpu_total / m > cpu_total / n else "CPU"}
    return {"stages": rows, "cpu_core_hours": cpu_total / 3600, "gpu_hours": gpu_total / 3600, "walls": walls,
            "driver_raw_hash_h": raw_hash_s / 3600, "task_publish_hash_core_h": publish_hash_s / 3600,
            "engine_h": engine_s / 3600}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--release", default=None, help="default: runs/default/release (--quick: the tiny run's)")
    parser.add_argument("--work", default=None, help="the release's work folder (default: RELEASE.work)")
    parser.add_argument("--gpu-speedup", type=float, default=100.0,
                        help="ASSUMED: one GPU trains the SDF this many times as fast as one CPU core")
    parser.add_argument("--driver-cores", type=int, default=16,
                        help="ASSUMED: cores of the machine that plans (its thread pool hashes the raw frames)")
    parser.add_argument("--quick", action="store_true",
                        help="project from bench/_quick.py's tiny run (checks the bench; not the figures)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.release is None:
        if args.quick:
            from _quick import quick_run

            args.release = str(quick_run(out) / "release")
        else:
            args.release = str(ROOT / "runs" / "default" / "release")
    release = Path(args.release)
    if not (release / "manifests" / "stage_runs.parquet").is_file():
        print(f"bench_projection: no release with stage runs at {release} (run `make dataset`); skipped")
        return 0
    work = Path(args.work) if args.work else release.with_name(release.name + ".work")
    seconds, info = measured_seconds(release)
    from stages.registry import STAGE_CLASSES

    per_session = {cls.name for cls in STAGE_CLASSES if cls.scope == "session"}
    stage_s = {s: sum(v) / len(v) for s, v in seconds.items()}
    capture_pixels = info["width"] * info["height"]
    rules = factors(capture_pixels)
    examples_measured = max(1, info["examples"])
    example_s = sum(seconds.get("relightset", [0.0])) / examples_measured

    rate = sha256_rate()
    hashing = driver_hash_scaling(16 if args.quick else 128)
    driver_rate = hashing["one_thread_bytes_per_s"] * args.driver_cores * hashing["efficiency"]
    raw_bytes = ACTIONS * CAMERAS * 3 * SENSOR[0] * SENSOR[1] * RAW_BYTES_PER_PIXEL
    rb = release_bytes(release)
    maps_factor = rules["photometric"][1]
    tex_factor = rules["textures"][1]
    # per-camera maps x map pixels, novel views x map pixels x 2 views, textures x texels, meshes x 2.5 (faces),
    # the rest (previews, thumbnails, transforms) unscaled; examples x 4 (512^2 vs 256^2 pixels)
    per_action_release = (rb["camera_maps"] * maps_factor + rb["novel_views"] * maps_factor * 2
                          + rb["textures"] * tex_factor + rb["meshes"] * 2.5 + rb["other"])
    examples_bytes = rb["examples_total"] / examples_measured * EXAMPLES * 4
    release_total = ACTIONS * per_action_release + examples_bytes + rb["release_wide"]
    sb = store_bytes(work)
    store_total = 0.0
    for stage, per_scope in sb.items():
        if stage == "relightset":
            continue
        rule, factor = rules.get(stage, ("maps", maps_factor))
        if rule in ("geometry",):
            factor = 2.5  # mesh faces 500k vs 200k and a hash table ~2.7x the cpu preset's: bytes, not samples
        if rule == "relight":
            factor = maps_factor * 2  # views at map size, twice as many; the lobes cost time, not bytes
        store_total += per_scope * factor * (math.ceil(ACTIONS / ACTIONS_PER_SESSION) if stage in per_session else ACTIONS)
    store_total += sb.get("relightset", 0.0) * info["actions"] / examples_measured * EXAMPLES * 4
    engine_s = 0.0
    scale_path = out / "bench_scale.json"
    engine_note = "not measured (run bench_scale.py)"
    if scale_path.is_file():
        scale = json.loads(scale_path.read_text())
        largest = max((r for r in scale["results"] if r["executor"] == "dask") or scale["results"],
                      key=lambda r: r["actions"])
        cold = largest["runs"]["cold"]
        per_graph = (cold["phases_s"]["plan_s"] + cold["phases_s"]["bookkeeping_s"]) / cold["graph_tasks"]
        graph_tasks = ACTIONS * (cold["graph_tasks"] / largest["actions"])
        engine_s = per_graph * graph_tasks
        engine_note = (f"{1e3 * per_graph:.3f} ms per graph task (bench_scale, {largest['actions']} actions, "
                       f"{largest['executor']}) x {graph_tasks:.0f} tasks")
    result = project(stage_s, per_session, rules, example_s, args.gpu_speedup, raw_bytes / driver_rate,
                     release_total / rate, engine_s, CAMERAS)
    memory = None
    if (out / "bench_memory.json").is_file():
        memory = json.loads((out / "bench_memory.json").read_text()).get("worker_needs")
    report = {"quick": bool(args.quick), "measured_from": {"release": str(release), **info}, "sensor": list(SENSOR),
              "actions": ACTIONS,
              "examples": EXAMPLES, "actions_per_session": ACTIONS_PER_SESSION, "gpu_speedup_assumed": args.gpu_speedup,
              "sha256_bytes_per_s": rate, "driver_hashing": {**hashing, "driver_cores_assumed": args.driver_cores,
                                                             "driver_bytes_per_s": driver_rate},
              "engine": engine_note, **result,
              "storage_tb": {"raw_capture": raw_bytes / 1e12, "release_files": release_total / 1e12,
                             "work_store": store_total / 1e12},
              "release_bytes_measured": rb, "store_bytes_measured": sb,
              "worker_memory": memory}
    (out / "bench_projection.json").write_text(json.dumps(report, indent=1))
    (out / "bench_projection.md").write_text(table(report))
    plotted = plot(report, out / "bench_projection.png")
    print(table(report))
    if not plotted:
        print("matplotlib is not installed: no plot")
    return 0


def table(r: dict[str, Any]) -> str:
    m, dh = r["measured_from"], r["driver_hashing"]
    lines = ["# Projection of the whole release", "",
             f"{r['actions']} actions x 32 cameras of {r['sensor'][0]} x {r['sensor'][1]} (production preset) and "
             f"{r['examples']} relighting examples, from the stage seconds of `{m['release']}` ({m['actions']} actions "
             f"of {m['width']} x {m['height']}, runs {', '.join(m['runs'])}; two workers sharing two cores, so "
             "contention is in the figures). Sessions: one per "
             f"{r['actions_per_session']} actions (assumed). The GPU stage's speed-up over one CPU core is ASSUMED: "
             f"{r['gpu_speedup_assumed']:g}x (no GPU measured).", "",
             "| stage | resource | per | measured s | scaling rule | factor | production s | count | total h |",
             "|---|---|---|---|---|---|---|---|---|"]
    for stage, s in r["stages"].items():
        rule = s["rule"] + (f" / {r['gpu_speedup_assumed']:g} (GPU)" if s["resource"] == "GPU" else "")
        lines.append(f"| {stage} | {s['resource']} | {s['per']} | {s['measured_s']:.2f} | {rule} | {s['factor']:.1f} | "
                     f"{s['production_s']:.0f} | {s['count']} | {s['total_h']:.0f} |")
    lines += ["", f"CPU work: **{r['cpu_core_hours']:.0f} core-hours**; GPU work: **{r['gpu_hours']:.0f} GPU-hours**. "
                  f"In the driver: sha256 of the raw frames while planning {r['driver_raw_hash_h']:.2f} h, on a thread "
                  f"pool of {dh['driver_cores_assumed']} driver cores (ASSUMED) at "
                  f"{dh['one_thread_bytes_per_s'] / 1e9:.2f} GB/s per thread x a parallel efficiency of "
                  f"{dh['efficiency']:.2f} (measured here with {dh['threads']} threads), disk not counted. The release "
                  f"files are hashed by the tasks that write them: {r['task_publish_hash_core_h']:.1f} core-hours of "
                  f"the CPU work (at {r['sha256_bytes_per_s'] / 1e9:.2f} GB/s). Engine {r['engine_h']:.2f} h "
                  f"({r['engine']}).", "",
              "Wall time, days (CPU- or GPU-bound):", "",
              "| N CPU workers | " + " | ".join(f"M = {g} GPU" for g in GPU_COUNTS) + " |",
              "|---|" + "---|" * len(GPU_COUNTS)]
    for n in CPU_WORKERS:
        cells = [f"{r['walls'][f'{n},{g}']['hours'] / 24:.1f} ({r['walls'][f'{n},{g}']['bound']})" for g in GPU_COUNTS]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    st = r["storage_tb"]
    lines += ["", f"Storage: raw capture {st['raw_capture']:.1f} TB (uncompressed 16-bit DNG), release files "
                  f"{st['release_files']:.1f} TB (per-camera maps scaled by map pixels, textures by texels), work store "
                  f"{st['work_store']:.1f} TB (the release's files are hard links into it, so the disk holds the "
                  f"store, not both)."]
    if r.get("worker_memory"):
        lines += ["", f"Worker memory (bench_memory): {r['worker_memory']}."]
    return "\n".join(lines) + "\n"


def plot(r: dict[str, Any], path: Path) -> bool:
    try:
        import matplotlib
    except ImportError:
        return False
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for g in GPU_COUNTS:
        ax.plot(CPU_WORKERS, [r["walls"][f"{n},{g}"]["hours"] / 24 for n in CPU_WORKERS], "o-", label=f"{g} GPU")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("CPU workers (cores)")
    ax.set_ylabel("wall time, days")
    ax.set_title(f"{r['actions']} actions at 6016x4016 + {r['examples']} examples "
                 f"(GPU speed-up assumed {r['gpu_speedup_assumed']:g}x)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


if __name__ == "__main__":
    raise SystemExit(main())
