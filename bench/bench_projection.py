"""Projected wall time and storage of the whole release (2,000 actions of 32 cameras at 6016 x 4016 and the
1,500-example relighting set) for N CPU workers and M GPUs, from the per-stage costs a run recorded.

Measured: each stage's seconds per scope, from bench_resolution's report (``--resolution``, by default
``OUT/bench_resolution.json`` where present: the CPU seconds of the stage's own process above the imports' floor at
its largest width, one action of 32 cameras, and each stage's exponent k of CPU seconds against pixels per view over
its widths; CPU seconds, so a loaded machine does not inflate them), or else from a release's
``manifests/stage_runs.parquet`` (the latest run that ran it; a per-camera stage's seconds are the sum over its
cameras, so they are one worker's seconds, wall seconds with the machine's contention in them); the release's
bytes per asset kind (``assets.parquet``), the work store's bytes per stage (``<work>/artifacts``, hard links
counted once), the capture's raw bytes, and, when present in ``--out``, the engine's overhead per task
(bench_scale.json), a worker's peak memory (bench_memory.json) and the GPU's speed-up (bench_gpu.json). Those are at
the default preset.

Scaled to the production preset by stated rules (the table says which rule each stage gets):

- ``sensor``: the stage reads whole raw frames: x (6016 x 4016) / (capture pixels);
- ``maps``: per-pixel work on the production maps (half size, 3008 x 2008): x that / capture pixels;
- ``texels``: texture-space work: x the production textures' texel count / the default's (textures 4096^2 vs 1024^2,
  materials 1024^2 and occlusion 2048^2 vs 256^2 and 512^2);
- ``relight``: maps x novel views (6 vs 3) x SG lobes (64 vs 32) x shading samples per pixel (``supersample``
  squared: 1 vs 2 x 2; a view at 2 took 3.9 x the CPU of 1 on the default subject at 640 px, README);
- ``geometry`` (the GPU stage, ``resources = {"GPU": 1}``): x the SDF's ray samples over both passes
  (production 2 x 20,000 steps of 4096 rays x 16 samples vs 600 + 1,800 steps of 512 x 8), divided by the
  speed-up of one GPU over one CPU core: ``--gpu-speedup``, else bench_gpu's measured field-step speed-up where it
  saw a GPU, else an ASSUMED :data:`ASSUMED_GPU_SPEEDUP`;
- the relighting set: seconds per example x (512 / 256)^2 pixels x 2 SG lobes x the shading samples per pixel
  (2 x 2 in both presets), for 1,500 examples.

With bench_resolution's exponents the CPU work is projected a second time with each per-pixel stage's pixel
factor raised to its measured k: for a cost that is a fixed part plus a per-pixel part, the whole factor is an upper
bound and the measured power law a lower one. The report marks every figure measured, projected or assumed.

Wall time for N CPU workers (one core each, as the default cluster runs them) and M GPUs:
``raw hashing + max(CPU work / N, GPU work / M) + one action's critical path + engine``, where raw hashing (the
plan's sha256 of every raw frame, :meth:`pipeline.hashing.DigestCache.digest_all`) runs in the driver's thread
pool, one thread per driver core (``--driver-cores``, ASSUMED), at the single-thread sha256 rate times the
parallel efficiency that pool measured here on the cores of this machine; the sha256 of every release file (for
the assets table) is done by the task that wrote the file (its success record), so it is CPU work on the workers,
at the single-thread rate; and the engine term is bench_scale's planning and bookkeeping per task. Disk and network
bandwidth are not counted. Writes bench_projection.json, bench_projection.md and bench_projection.png (matplotlib).

``python bench/bench_projection.py --out bench/out [--release runs/default/release] [--resolution
bench/out/bench_resolution.json] [--gpu-speedup 100] [--driver-cores 16]``
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
ASSUMED_GPU_SPEEDUP = 100.0
"""One GPU's SDF training against one CPU core, assumed where no GPU has been measured (bench_gpu.py measures it)."""
GPU_COUNTS = (1, 4, 8, 32)


def sdf_samples(geometry: Any) -> float:
    """Network samples of the geometry stage's SDF training: both passes' steps x (rays x samples + eikonal points)."""
    from stages.numerics.sdf_mesh import pass_configs

    return sum(c.iterations * (c.rays_per_batch * c.samples_per_ray + c.eikonal_points)
               for c in pass_configs(geometry) if c is not None)


def factors(capture_pixels: float) -> dict[str, tuple[str, float, float]]:
    """Stage -> (rule, factor, pixel factor) from the default preset at ``capture_pixels`` per view to the
    production preset at the production sensor; the pixel factor is the part of the factor that is the growth of
    the pixels a stage works on (1 for the texel and SDF rules), the part a measured exponent replaces."""
    from stages.registry import PRESETS

    default, production = PRESETS["default"], PRESETS["production"]
    sensor = SENSOR[0] * SENSOR[1] / capture_pixels
    maps = sensor / 4 if production.decode.half_size else sensor
    tex = production.textures.texture_size ** 2 / default.textures.texture_size ** 2
    mat = (production.materials.texture_size ** 2 + production.materials.occlusion_size ** 2) / (
        default.materials.texture_size ** 2 + default.materials.occlusion_size ** 2)
    relight = maps * production.relight.novel_views / default.relight.novel_views * \
        production.relight.sg_lobes / default.relight.sg_lobes * shading_samples(production.relight, default.relight)
    geometry = sdf_samples(production.geometry) / sdf_samples(default.geometry)
    return {"cameras": ("sensor", sensor, sensor), "colour": ("sensor", sensor, sensor),
            "lights": ("sensor", sensor, sensor), "plates": ("sensor", sensor, sensor),
            "decode": ("sensor", sensor, sensor), "photometric": ("maps", maps, maps),
            "diffuse_normals": ("maps", maps, maps), "geometry": ("geometry", geometry, 1.0),
            "textures": ("texels", tex, 1.0), "materials": ("texels", mat, 1.0),
            "relight": ("relight", relight, maps), "exports": ("maps", maps, maps)}


def resolution_seconds(report: dict[str, Any]) -> tuple[dict[str, float], dict[str, float], dict[str, Any]]:
    """The CPU figures of bench_resolution's report (its ``bench_resolution.json``): per stage the CPU seconds
    above the imports' floor of the stage's own process at the largest width measured (one action, so a session
    stage's seconds are one session's), per stage the exponent ``k`` of its CPU seconds against the pixels per view
    over the widths (absent where fewer than two widths were measured), and the facts (width, height, widths,
    preset, cameras, quick).

    A step that ran more than one stage shares its CPU seconds among them in proportion to their task seconds; a
    step that ran none (the final publish) is left out.

    Raises:
        ValueError: the report has no rows.
    """
    rows = report.get("rows") or []
    if not rows:
        raise ValueError("bench_resolution report: no widths measured")
    largest = max(rows, key=lambda r: r["pixels"])
    floor = largest["imports"]["cpu_s"]
    fits = (report.get("growth") or {}).get("fits") or {}
    seconds: dict[str, float] = {}
    exponents: dict[str, float] = {}
    for step in largest["steps"]:
        stages = step["stages"]
        if not stages:
            continue
        cpu = max(step["cpu_s"] - floor, 0.0)
        task_total = sum(stages.values())
        for stage, task_s in stages.items():
            seconds[stage] = cpu * (task_s / task_total if task_total > 0 else 1.0 / len(stages))
            fit = fits.get(f"cpu {step['through']}")
            if fit is not None and len(rows) >= 2:
                exponents[stage] = float(fit["k"])
    info = {"width": int(largest["width"]), "height": int(largest["height"]),
            "widths": sorted(int(r["width"]) for r in rows), "preset": report.get("preset"),
            "cameras": int(largest["cameras"]), "quick": bool(report.get("quick"))}
    return seconds, exponents, info


def shading_samples(production: Any, default: Any) -> float:
    """The ratio of shading samples per pixel (``shading.supersample`` squared) of two relight or relighting-set
    configs."""
    return (production.shading.supersample / default.shading.supersample) ** 2


def relightset_factor() -> float:
    from stages.registry import PRESETS

    d, p = PRESETS["default"].relightset, PRESETS["production"].relightset
    return (p.size / d.size) ** 2 * p.sg_lobes / d.sg_lobes * shading_samples(p, d)


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


def gpu_speedup(out: Path, given: float | None) -> dict[str, Any]:
    """The GPU stage's speed-up over one CPU core and where it comes from: ``given`` (the command line, "given"),
    else bench_gpu's measured field-step speed-up in ``out/bench_gpu.json`` where that bench saw a GPU
    ("measured"), else :data:`ASSUMED_GPU_SPEEDUP` ("assumed"). ``cpu_field_step_ms``: bench_gpu's one-thread
    CPU field step of the production SDF where it ran (measured either way)."""
    bench = None
    if (out / "bench_gpu.json").is_file():
        bench = json.loads((out / "bench_gpu.json").read_text())
    rows = (bench or {}).get("rows", [])
    cpu = next((r["field_step_ms"] for r in rows if r.get("device") == "cpu"), None)
    measured = next((r for r in rows if r.get("device") == "cuda" and "speedup_over_cpu_thread" in r), None)
    if given is not None:
        return {"speedup": given, "source": "given", "cpu_field_step_ms": cpu}
    if measured is not None and not (bench or {}).get("quick"):
        return {"speedup": float(measured["speedup_over_cpu_thread"]), "source": "measured",
                "device": measured.get("name"), "cpu_field_step_ms": cpu}
    return {"speedup": ASSUMED_GPU_SPEEDUP, "source": "assumed", "cpu_field_step_ms": cpu}


def project(stage_s: dict[str, float], per_session: set[str], rules: dict[str, tuple[str, float, float]],
            example_s: float, gpu_speedup: float, raw_hash_s: float, publish_hash_s: float, engine_s: float,
            cameras: int, exponents: dict[str, float] | None = None) -> dict[str, Any]:
    """CPU and GPU seconds of the release and the wall time for each N, M. ``raw_hash_s``: the driver's wall
    seconds hashing raw frames; ``publish_hash_s``: the core-seconds of hashing the release files, done by the
    tasks that write them (CPU work).

    ``exponents`` (stage -> k, bench_resolution's measured growth of the stage's CPU seconds with the pixels per
    view): a second projection of the CPU work with each stage's pixel factor raised to its ``k`` instead of
    taken whole (``cpu_core_hours_measured_k``, and ``production_s_measured_k`` per stage). For a stage whose cost
    is a fixed part plus a per-pixel part, the whole pixel factor is an upper bound and the power law with ``k``
    measured at smaller sizes a lower bound (its log-log slope rises towards 1 as the pixels grow)."""
    from stages.registry import STAGE_CLASSES

    per_view = {cls.name for cls in STAGE_CLASSES if cls.per_view}
    gpu_stages = {cls.name for cls in STAGE_CLASSES if cls.resources.get("GPU")}
    sessions = math.ceil(ACTIONS / ACTIONS_PER_SESSION)
    rows, cpu_total, gpu_total, cpu_total_k = {}, 0.0, 0.0, 0.0
    for stage, seconds in stage_s.items():
        if stage == "relightset":
            continue
        rule, factor, pixel_factor = rules[stage]
        scaled = seconds * factor
        count = sessions if stage in per_session else ACTIONS
        row = {"measured_s": seconds, "rule": rule, "factor": factor, "production_s": scaled,
               "per": "session" if stage in per_session else "action", "count": count,
               "resource": "GPU" if stage in gpu_stages else "CPU"}
        if stage in gpu_stages:
            scaled /= gpu_speedup
            row["production_s"] = scaled
            gpu_total += scaled * count
        else:
            cpu_total += scaled * count
            if exponents is not None:
                k = exponents.get(stage)
                scaled_k = scaled if k is None or pixel_factor == 1.0 else \
                    seconds * factor / pixel_factor * pixel_factor ** k
                row |= {"k_measured": k, "production_s_measured_k": scaled_k}
                cpu_total_k += scaled_k * count
        rows[stage] = row | {"total_h": scaled * count / 3600}
    example = example_s * relightset_factor()
    rows["relightset"] = {"measured_s": example_s, "rule": "examples", "factor": relightset_factor(),
                          "production_s": example, "per": "example", "count": EXAMPLES, "resource": "CPU",
                          "total_h": example * EXAMPLES / 3600}
    cpu_total += example * EXAMPLES + publish_hash_s
    cpu_total_k += example * EXAMPLES + publish_hash_s

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
            "cpu_core_hours_measured_k": cpu_total_k / 3600 if exponents is not None else None,
            "driver_raw_hash_h": raw_hash_s / 3600, "task_publish_hash_core_h": publish_hash_s / 3600,
            "engine_h": engine_s / 3600}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--release", default=None, help="default: runs/default/release (--quick: the tiny run's)")
    parser.add_argument("--work", default=None, help="the release's work folder (default: RELEASE.work)")
    parser.add_argument("--gpu-speedup", type=float, default=None,
                        help="one GPU trains the SDF this many times as fast as one CPU core (default: bench_gpu's "
                             "measured field-step speed-up from OUT/bench_gpu.json where it measured a GPU, else "
                             f"{ASSUMED_GPU_SPEEDUP:g}, ASSUMED)")
    parser.add_argument("--driver-cores", type=int, default=16,
                        help="ASSUMED: cores of the machine that plans (its thread pool hashes the raw frames)")
    parser.add_argument("--resolution", default=None,
                        help="bench_resolution.json whose CPU figures give the stage seconds (its largest width) and "
                             "the measured exponents (default: OUT/bench_resolution.json when present and not a "
                             "quick run's, not with --quick; 'none': the release's stage_runs task seconds)")
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
    from stages.registry import PRESETS, STAGE_CLASSES

    per_session = {cls.name for cls in STAGE_CLASSES if cls.scope == "session"}
    examples_measured = max(1, info["examples"])
    resolution_path = args.resolution
    if resolution_path is None and not args.quick and (out / "bench_resolution.json").is_file() and \
            not json.loads((out / "bench_resolution.json").read_text()).get("quick"):
        resolution_path = str(out / "bench_resolution.json")
    exponents, source = None, None
    if resolution_path not in (None, "none"):
        try:
            resolution = json.loads(Path(resolution_path).read_text())
            stage_s, exponents, source = resolution_seconds(resolution)
        except (OSError, ValueError, KeyError, TypeError) as error:
            parser.error(f"--resolution {resolution_path}: not a bench_resolution report ({error})")
        source |= {"kind": "bench_resolution", "path": resolution_path}
        example_s = stage_s.get("relightset", 0.0) / PRESETS[source["preset"]].relightset.examples_per_action
        rules = factors(source["width"] * source["height"])
    else:
        stage_s = {s: sum(v) / len(v) for s, v in seconds.items()}
        example_s = sum(seconds.get("relightset", [0.0])) / examples_measured
        rules = factors(info["width"] * info["height"])
        source = {"kind": "stage_runs", "path": str(release), "width": info["width"], "height": info["height"]}
    byte_rules = factors(info["width"] * info["height"])

    rate = sha256_rate()
    hashing = driver_hash_scaling(16 if args.quick else 128)
    driver_rate = hashing["one_thread_bytes_per_s"] * args.driver_cores * hashing["efficiency"]
    raw_bytes = ACTIONS * CAMERAS * 3 * SENSOR[0] * SENSOR[1] * RAW_BYTES_PER_PIXEL
    rb = release_bytes(release)
    maps_factor = byte_rules["photometric"][1]
    tex_factor = byte_rules["textures"][1]
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
        rule, factor, _ = byte_rules.get(stage, ("maps", maps_factor, maps_factor))
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
        largest = max([r for r in scale["results"] if r["executor"] == "dask"] or scale["results"],
                      key=lambda r: r["actions"])
        cold = largest["runs"]["cold"]
        per_graph = (cold["phases_s"]["plan_s"] + cold["phases_s"]["bookkeeping_s"]) / cold["graph_tasks"]
        graph_tasks = ACTIONS * (cold["graph_tasks"] / largest["actions"])
        engine_s = per_graph * graph_tasks
        engine_note = (f"{1e3 * per_graph:.3f} ms per graph task (bench_scale, {largest['actions']} actions, "
                       f"{largest['executor']}) x {graph_tasks:.0f} tasks")
    gpu = gpu_speedup(out, args.gpu_speedup)
    result = project(stage_s, per_session, rules, example_s, gpu["speedup"], raw_bytes / driver_rate,
                     release_total / rate, engine_s, CAMERAS, exponents)
    memory = None
    if (out / "bench_memory.json").is_file():
        memory = json.loads((out / "bench_memory.json").read_text()).get("worker_needs")
    report = {"quick": bool(args.quick), "measured_from": {"release": str(release), **info},
              "seconds_from": source, "sensor": list(SENSOR),
              "actions": ACTIONS,
              "examples": EXAMPLES, "actions_per_session": ACTIONS_PER_SESSION, "gpu_speedup": gpu,
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
    m, dh, src, gpu = r["measured_from"], r["driver_hashing"], r["seconds_from"], r["gpu_speedup"]
    if src["kind"] == "bench_resolution":
        seconds_from = (f"the CPU seconds of each stage's own process above the imports' floor at {src['width']} x "
                        f"{src['height']} (`{src['path']}`: one action of {src['cameras']} cameras, preset "
                        f"`{src['preset']}`, widths {', '.join(map(str, src['widths']))} px; CPU seconds, so a loaded "
                        "machine does not inflate them)")
    else:
        seconds_from = (f"the task seconds of `{m['release']}`'s stage_runs ({m['actions']} actions of {m['width']} x "
                        f"{m['height']}, runs {', '.join(m['runs'])}; wall seconds of workers sharing the cores, so "
                        "contention is in them)")
    gpu_words = {"measured": f"MEASURED by bench_gpu on {gpu.get('device')} (the field step only, not a whole "
                             "training step)",
                 "given": "GIVEN on the command line", "assumed": "ASSUMED (no GPU measured)"}[gpu["source"]]
    cpu_step = (f"; bench_gpu measured the production SDF's field step at {gpu['cpu_field_step_ms']:.0f} ms on one "
                "CPU thread" if gpu.get("cpu_field_step_ms") else "")
    lines = ["# Projection of the whole release", "",
             f"{r['actions']} actions x 32 cameras of {r['sensor'][0]} x {r['sensor'][1]} (production preset) and "
             f"{r['examples']} relighting examples. Every figure below is PROJECTED except where it says measured.",
             "", "## What is measured and what is projected", "",
             f"- MEASURED: per stage, {seconds_from} (the `measured s` column)"
             + ("; and each stage's exponent `k`, CPU seconds ~ (pixels per view)^k, least squares over those widths"
                if src["kind"] == "bench_resolution" else "") + ".",
             f"- MEASURED: the sha256 rate of this machine and its thread pool's parallel efficiency; the release's and "
             f"the work store's bytes per asset kind (`{m['release']}`, {m['width']} x {m['height']}).",
             "- PROJECTED: every production figure: the stage seconds scaled to the production preset and sensor by "
             "the rules in the table (the whole pixel factor for the per-pixel stages), totals, wall times and "
             "storage. Nothing has run at 6016 x 4016.",
             f"- GPU speed-up of the SDF over one CPU core: {gpu['speedup']:g}x, {gpu_words}{cpu_step}.",
             f"- ASSUMED: a capture session per {r['actions_per_session']} actions; {dh['driver_cores_assumed']} "
             "driver cores hashing the raw frames; disk and network bandwidth not counted.", "",
             "| stage | resource | per | measured s | scaling rule | factor | production s (projected) "
             + ("| k measured | production s with k (projected) " if r.get("cpu_core_hours_measured_k") else "")
             + "| count | total h |", "|---|---|---|---|---|---|---|" + ("---|---|" if r.get(
                 "cpu_core_hours_measured_k") else "") + "---|---|"]
    for stage, s in r["stages"].items():
        rule = s["rule"] + (f" / {gpu['speedup']:g} (GPU)" if s["resource"] == "GPU" else "")
        with_k = ""
        if r.get("cpu_core_hours_measured_k"):
            k = s.get("k_measured")
            with_k = (f"| {k:.2f} " if k is not None else "| - ") + (
                f"| {s['production_s_measured_k']:.0f} " if "production_s_measured_k" in s else "| - ")
        lines.append(f"| {stage} | {s['resource']} | {s['per']} | {s['measured_s']:.2f} | {rule} | {s['factor']:.1f} | "
                     f"{s['production_s']:.0f} {with_k}| {s['count']} | {s['total_h']:.0f} |")
    lines += ["", f"CPU work (projected): **{r['cpu_core_hours']:.0f} core-hours**"
              + (f" with the whole pixel factor, **{r['cpu_core_hours_measured_k']:.0f}** with the measured exponents "
                 "(for a stage whose cost is a fixed part plus a per-pixel part, the first is an upper bound and the "
                 "second a lower one: the log-log slope rises towards 1 as the pixels grow)"
                 if r.get("cpu_core_hours_measured_k") else "")
              + f"; GPU work (projected, speed-up {gpu['source']}): **{r['gpu_hours']:.0f} GPU-hours**. "
              f"In the driver: sha256 of the raw frames while planning {r['driver_raw_hash_h']:.2f} h, on a thread "
              f"pool of {dh['driver_cores_assumed']} driver cores (ASSUMED) at "
              f"{dh['one_thread_bytes_per_s'] / 1e9:.2f} GB/s per thread x a parallel efficiency of "
              f"{dh['efficiency']:.2f} (measured here with {dh['threads']} threads), disk not counted. The release "
              f"files are hashed by the tasks that write them: {r['task_publish_hash_core_h']:.1f} core-hours of "
              f"the CPU work (at {r['sha256_bytes_per_s'] / 1e9:.2f} GB/s, measured). Engine {r['engine_h']:.2f} h "
              f"({r['engine']}).", "",
              "Wall time, days (projected, with the whole pixel factor; CPU- or GPU-bound):", "",
              "| N CPU workers | " + " | ".join(f"M = {g} GPU" for g in GPU_COUNTS) + " |",
              "|---|" + "---|" * len(GPU_COUNTS)]
    for n in CPU_WORKERS:
        cells = [f"{r['walls'][f'{n},{g}']['hours'] / 24:.1f} ({r['walls'][f'{n},{g}']['bound']})" for g in GPU_COUNTS]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    st = r["storage_tb"]
    lines += ["", f"Storage (projected): raw capture {st['raw_capture']:.1f} TB (uncompressed 16-bit DNG), release "
                  f"files {st['release_files']:.1f} TB (per-camera maps scaled by map pixels, textures by texels), "
                  f"work store {st['work_store']:.1f} TB (the release's files are hard links into it, so the disk "
                  "holds the store, not both)."]
    if r.get("worker_memory"):
        lines += ["", f"Worker memory (bench_memory, measured): {r['worker_memory']}."]
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
                 f"(projected; GPU speed-up {r['gpu_speedup']['source']} {r['gpu_speedup']['speedup']:g}x)",
                 fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


if __name__ == "__main__":
    raise SystemExit(main())
