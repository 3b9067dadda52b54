"""Peak memory of a worker's tasks at production size: one camera at full sensor resolution (6016 x 4016)
through decode and the photometric maps, and the geometry stage's SDF at the production preset's sizes.

Each measurement runs the project's own code in a fresh process, started by a watcher process that reports the
peak resident set of that one child (``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss``):

- ``baseline``: the imports only (numpy, torch, the stages), the floor of every worker process;
- ``decode_production`` / ``decode_full``: :meth:`stages.decode.DecodeStage.run_view` and ``finalize`` on one
  camera's three raw frames (full_on, pos, neg; 16-bit RGGB DNGs of 6016 x 4016 written with the simulator's
  ``synthetic.files.write_dng``, a lit ellipsoid before a dark background), with the production preset's decode
  (AHD, half size: 3008 x 2008 maps) and with full-size maps (AHD, 6016 x 4016);
- ``photometric_production`` / ``photometric_full``: :meth:`stages.photometric.PhotometricStage.run_view` on the
  decode's output (eq. 1 normals from the gradient pair, alpha, albedo, mask, the joint-bilateral denoise,
  the EXR and PNG files);
- ``sdf_production_<k>``: :func:`stages.numerics.sdf.train_sdf` with ``SDF_PRESETS["production"]``'s sizes
  (hash grid of 16 levels x 2^19 entries, 4096 rays x 16 samples a step, 2048 eikonal points, hull of 192^3,
  proposal grid of 8 mm) for a few steps on the CPU, from 32 views of an ellipsoid at 1/k of the production map
  size (3008 x 2008) per axis, k = 4, 2 and 1 (k = 1 is the geometry stage's input at production size; what
  grows with the views' pixels, the views themselves and the bank of rays worth drawing, is also extrapolated
  linearly in pixels from k = 4 and 2, a check of the k = 1 row).

Writes bench_memory.json and bench_memory.md. ``python bench/bench_memory.py --out bench/out [--quick]``
(``--quick``: a 1/8-size camera and one SDF run on 1/16-size views with smaller batches, seconds; for checking the
bench, not for the figures).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.capture import ILLUMINATIONS  # noqa: E402

SENSOR = (6016, 4016)
"""Production sensor (width, height)."""
CAMERA = "00000"
RADII = np.array([0.30, 0.90, 0.25])
"""Semi-axes of the synthetic subject (metres): a body-sized ellipsoid."""
LIMIT_GIB = 24.0
QUICK_SDF_K = 16
"""The quick mode's SDF views are 1/16 of the production maps per axis; a run at that size also trains with an
eighth of the production batches and a coarser hull and proposal grid (it checks the code, its figures are not
the production's)."""
WATCHER = ("import json, resource, subprocess, sys; rc = subprocess.call(sys.argv[2:]); "
           "json.dump({'rc': rc, 'maxrss_kib': resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}, "
           "open(sys.argv[1], 'w'))")


# --- a synthetic subject -----------------------------------------------------------------------------

def look_at(eye: np.ndarray, target: np.ndarray = np.zeros(3), up: np.ndarray = np.array([0.0, -1.0, 0.0])):
    """(R, t) of an OpenCV camera at ``eye`` looking at ``target`` (+y down in the image)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(-up, z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def render_ellipsoid(K: np.ndarray, R: np.ndarray, t: np.ndarray, height: int, width: int,
                     rows_per_chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """(mask (H, W) bool, world normals (H, W, 3) float32, 0 off the subject) of the ellipsoid RADII at the
    origin, seen by a pinhole camera; computed in bands of rows (full-size frames stay a few hundred MB)."""
    mask = np.zeros((height, width), bool)
    normals = np.zeros((height, width, 3), np.float32)
    centre = -R.T @ t
    Kinv = np.linalg.inv(K)
    cols = np.arange(width) + 0.5
    for r0 in range(0, height, rows_per_chunk):
        rows = np.arange(r0, min(height, r0 + rows_per_chunk)) + 0.5
        uu, vv = np.meshgrid(cols, rows)
        pix = np.stack([uu, vv, np.ones_like(uu)], -1) @ Kinv.T
        d = pix @ R  # world directions (R^T applied to each row vector)
        o = centre / RADII
        ds = d / RADII
        a = (ds * ds).sum(-1)
        b = 2 * (ds @ o)
        c = o @ o - 1
        disc = b * b - 4 * a * c
        hit = disc > 0
        s = np.where(hit, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0)
        p = centre + s[..., None] * d
        n = p / RADII ** 2
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        mask[r0:r0 + len(rows)] = hit
        normals[r0:r0 + len(rows)] = np.where(hit[..., None], n, 0).astype(np.float32)
    return mask, normals


def camera_record(width: int, height: int) -> dict[str, Any]:
    """Camera 00000 of the rig: 3 m in front of the subject, the subject filling about 60% of the frame's height."""
    f = 0.6 * height * 3.0 / (2 * RADII[1])
    R, t = look_at(np.array([0.0, 0.0, -3.0]))
    return {"camera_id": CAMERA, "width": width, "height": height,
            "K": [[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]],
            "cam_from_world": np.hstack([R, t[:, None]]).tolist(), "white_reference": [0.8, 0.9, 0.7],
            "exposure_s": 0.01}


def write_camera_frames(folder: Path, width: int, height: int) -> dict[str, Path]:
    """The three raw frames of one camera (16-bit DNG, the simulator's sensor model, no noise) and the
    calibration folders a decode and photometric task read (cameras.json; no colour matrix, ideal lights,
    no clean plate)."""
    from synthetic import files, sensor

    cam = camera_record(width, height)
    mask, n = render_ellipsoid(np.asarray(cam["K"]), np.asarray(cam["cam_from_world"])[:, :3],
                               np.asarray(cam["cam_from_world"])[:, 3], height, width)
    white = np.asarray(cam["white_reference"], np.float32)
    yy = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None, None]
    albedo = (0.35 + 0.25 * np.sin(40 * yy)) * np.array([0.9, 0.7, 0.6], np.float32)  # skin-ish, varying
    background = np.float32(0.02)
    gain = sensor.exposure_gain(white, 0.8)
    cam_from_xyz, neutral = sensor.nikon_cam_from_xyz(), sensor.as_shot_neutral()
    paths = {}
    for illum in ILLUMINATIONS:
        if illum == "full_on":
            radiance = albedo * white
        else:
            sign = 1.0 if illum == "pos" else -1.0
            radiance = albedo * white * (1.0 + sign * n) / 2.0
        radiance = np.where(mask[..., None], radiance, background).astype(np.float32)
        raw = sensor.raw_frame(radiance, gain, None, 40000.0, 2.5)
        del radiance
        paths[illum] = files.write_dng(folder / "capture" / "actions" / "A0000" / illum / f"{CAMERA}.dng", raw,
                                       cam_from_xyz, neutral)
        del raw
    (folder / "cameras").mkdir(parents=True, exist_ok=True)
    (folder / "cameras" / "cameras.json").write_text(json.dumps({"camera_convention": "opencv", "cameras": [cam]}))
    (folder / "colour").mkdir(exist_ok=True)
    (folder / "plates").mkdir(exist_ok=True)
    (folder / "lights").mkdir(exist_ok=True)
    (folder / "lights" / "light_model.json").write_text(json.dumps({"ideal": True}))
    (folder / "rig.json").write_text(json.dumps({"format": "ultrastage-rig/1", "cameras": [cam]}))
    return paths


# --- the measured children ---------------------------------------------------------------------------

def _context(folder: Path, stage: str, out: Path, upstream: dict[str, Path], raw: dict[str, Path]):
    from pipeline.stage import StageContext

    rig = json.loads((folder / "rig.json").read_text())
    out.mkdir(parents=True, exist_ok=True)
    return StageContext(stage=stage, scope_id="A0000", session_id="S000", action_id="A0000", out_dir=out,
                        upstream=upstream, raw_inputs=raw, rig=rig, capture_root=folder / "capture",
                        views=[CAMERA], subject="synthetic", cache_dir=folder / "cache")


def child_decode(folder: Path, variant: str) -> dict[str, Any]:
    from stages.decode import DecodeConfig, DecodeStage
    from stages.registry import PRESETS

    config = PRESETS["production"].decode if variant == "production" else DecodeConfig(demosaic="AHD", half_size=False)
    raw = {f"{i}/{CAMERA}": folder / "capture" / "actions" / "A0000" / i / f"{CAMERA}.dng" for i in ILLUMINATIONS}
    ctx = _context(folder, "decode", folder / f"decode_{variant}",
                   {"cameras": folder / "cameras", "colour": folder / "colour"}, raw)
    stage = DecodeStage(config)
    stats = stage.run_view(ctx, CAMERA)
    stage.finalize(ctx, {CAMERA: stats})
    return {"config": {"demosaic": config.demosaic, "half_size": config.half_size},
            "map_size": [stats["width"], stats["height"]]}


def child_photometric(folder: Path, variant: str) -> dict[str, Any]:
    from stages.photometric import PhotometricStage
    from stages.registry import PRESETS

    ctx = _context(folder, "photometric", folder / f"photometric_{variant}",
                   {"decode": folder / f"decode_{variant}", "plates": folder / "plates", "lights": folder / "lights"}, {})
    stats = PhotometricStage(PRESETS["production"].photometric).run_view(ctx, CAMERA)
    if "missing" in stats:
        raise RuntimeError(f"photometric: {stats}")
    return {"valid_fraction": stats["valid_fraction"], "mask_fraction": stats["mask_fraction"]}


def sdf_views(width: int, height: int, count: int = 32) -> list[Any]:
    """``count`` views on a ring 3 m around the ellipsoid (its height in about 60% of each frame)."""
    from stages.numerics.sdf import SDFView

    cam = camera_record(width, height)
    K = np.asarray(cam["K"], np.float64)
    views = []
    for i in range(count):
        angle = 2 * np.pi * i / count
        R, t = look_at(np.array([3.0 * np.sin(angle), -0.3 * np.cos(3 * angle), -3.0 * np.cos(angle)]))
        mask, normals = render_ellipsoid(K, R, t, height, width)
        views.append(SDFView(normals_world=normals, normal_valid=mask.copy(), mask=mask, K=K,
                             cam_from_world=np.hstack([R, t[:, None]])))
    return views


def child_sdf(folder: Path, variant: str) -> dict[str, Any]:
    import dataclasses

    import torch

    from stages.numerics.sdf import SDF_PRESETS, train_sdf

    k = int(variant)
    width, height = SENSOR[0] // 2 // k, SENSOR[1] // 2 // k
    torch.set_num_threads(2)
    views = sdf_views(width, height)
    steps = 4
    config = dataclasses.replace(SDF_PRESETS["production"], iterations=steps, hull_init_steps=2, warmup_iterations=1,
                                 proposal_update_every=2, log_every=1, device="cpu", threads=2)
    if k == QUICK_SDF_K:  # the quick mode's check of the code: production's hash table, an eighth of its batches
        config = dataclasses.replace(config, rays_per_batch=512, eikonal_points=256, hull_init_points=2048,
                                     hull_resolution=64, proposal_voxel_m=0.032)
    start = time.perf_counter()
    result = train_sdf(views, config)
    encoding = config.encoding
    return {"views": len(views), "view_size": [width, height], "steps": steps, "seconds": time.perf_counter() - start,
            "hash_levels": encoding.levels, "log2_table_size": encoding.log2_table_size,
            "rays_per_batch": config.rays_per_batch, "samples_per_ray": config.samples_per_ray,
            "parameters": int(sum(p.numel() for p in result.field.parameters())),
            "candidate_rays": result.stats.get("candidate_rays"),
            "candidate_ray_fraction": result.stats.get("candidate_ray_fraction")}


def child_baseline(folder: Path, variant: str) -> dict[str, Any]:
    import torch  # noqa: F401

    import stages.decode  # noqa: F401
    import stages.numerics.sdf  # noqa: F401
    import stages.photometric  # noqa: F401

    return {}


CHILDREN = {"baseline": child_baseline, "decode": child_decode, "photometric": child_photometric, "sdf": child_sdf}


def measure(name: str, variant: str, folder: Path) -> dict[str, Any]:
    """Run one child under a watcher; its peak RSS (MiB), wall seconds and what it returned."""
    info, rss = folder / f"{name}_{variant}.json", folder / f"{name}_{variant}.rss.json"
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", WATCHER, str(rss), sys.executable, str(Path(__file__).resolve()),
                    "--child", name, "--variant", variant, "--folder", str(folder), "--info", str(info)],
                   check=True, cwd=ROOT)
    wall = time.perf_counter() - start
    watched = json.loads(rss.read_text())
    if watched["rc"]:
        raise RuntimeError(f"{name} {variant}: exit {watched['rc']}")
    return {"peak_rss_mib": watched["maxrss_kib"] / 1024, "wall_s": wall, **json.loads(info.read_text())}


# --- report ------------------------------------------------------------------------------------------

def extrapolate(points: dict[int, float]) -> float:
    """Peak at k = 1 from peaks at k (views of 1/k size per axis), linear in pixels (1/k^2)."""
    ks = sorted(points)
    x = np.array([1.0 / k ** 2 for k in ks])
    y = np.array([points[k] for k in ks])
    slope, intercept = np.polyfit(x, y, 1)
    return float(intercept + slope)


def table(report: dict[str, Any]) -> str:
    runs = report["runs"]
    base = runs["baseline"]["peak_rss_mib"]
    w, h = report["sensor"]
    lines = ["# Peak memory of a worker's tasks", "",
             f"Peak resident set of one process per row (`getrusage(RUSAGE_CHILDREN).ru_maxrss` of a fresh child); "
             f"`above imports`: less the baseline row (the interpreter, numpy, torch and the stages: "
             f"{base:.0f} MiB). One camera of {w} x {h}; the SDF at the production preset's sizes for "
             f"{report['sdf_steps']} steps on the CPU. Limit of this machine: {LIMIT_GIB:.0f} GiB.", "",
             "| task | what | peak RSS MiB | above imports MiB | wall s |", "|---|---|---|---|---|"]
    what = {"baseline": "imports only",
            "decode_production": "decode, production preset (AHD, half size), 3 raw frames -> maps",
            "decode_full": "decode, full-size maps (AHD), 3 raw frames -> maps",
            "photometric_production": "photometric maps of the half-size decode",
            "photometric_full": "photometric maps of the full-size decode"}
    for key, run in runs.items():
        label = what.get(key)
        if label is None and key.startswith("sdf_"):
            size = run["view_size"]
            label = f"SDF, production sizes, {run['views']} views of {size[0]} x {size[1]}"
        lines.append(f"| {key} | {label} | {run['peak_rss_mib']:.0f} | {run['peak_rss_mib'] - base:.0f} | "
                     f"{run['wall_s']:.1f} |")
    if "sdf_full_extrapolated_mib" in report:
        lines += ["", f"SDF with 32 views at the production map size ({w // 2} x {h // 2}), extrapolated linearly in "
                      f"the views' pixels from k = 4 and 2 (a check of the measured row): **{report['sdf_full_extrapolated_mib'] / 1024:.1f} GiB**."]
    lines += ["", f"What a worker needs: {report['worker_needs']}"]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--quick", action="store_true",
                        help="1/8-size frames, one SDF run on 1/16-size views (checks the bench only)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--variant", help=argparse.SUPPRESS)
    parser.add_argument("--folder", help=argparse.SUPPRESS)
    parser.add_argument("--info", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        result = CHILDREN[args.child](Path(args.folder), args.variant)
        Path(args.info).write_text(json.dumps(result))
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scale = 8 if args.quick else 1
    width, height = SENSOR[0] // scale, SENSOR[1] // scale
    sdf_ks = [QUICK_SDF_K] if args.quick else [4, 2, 1]
    runs: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        folder = Path(tmp)
        start = time.perf_counter()
        write_camera_frames(folder, width, height)
        print(f"frames of {width} x {height} written in {time.perf_counter() - start:.1f} s", flush=True)
        plan = [("baseline", "none"), ("decode", "production"), ("decode", "full"), ("photometric", "production"),
                ("photometric", "full")] + [("sdf", str(k)) for k in sdf_ks]
        for name, variant in plan:
            key = name if name == "baseline" else f"{name}_{variant}"
            runs[key] = measure(name, variant, folder)
            print(f"{key:<24} peak {runs[key]['peak_rss_mib']:8.0f} MiB  {runs[key]['wall_s']:6.1f} s", flush=True)
    report: dict[str, Any] = {"sensor": [width, height], "quick": bool(args.quick), "runs": runs,
                              "sdf_steps": runs[f"sdf_{sdf_ks[0]}"]["steps"]}
    sdf_points = {k: runs[f"sdf_{k}"]["peak_rss_mib"] for k in sdf_ks if k != 1}
    if not args.quick:
        report["sdf_full_extrapolated_mib"] = extrapolate(sdf_points)
    sdf_need = runs["sdf_1"]["peak_rss_mib"] if "sdf_1" in runs else report.get("sdf_full_extrapolated_mib",
                                                                                max(sdf_points.values()))
    camera = max(runs[k]["peak_rss_mib"] for k in ("decode_production", "photometric_production"))
    camera_full = max(runs[k]["peak_rss_mib"] for k in ("decode_full", "photometric_full"))
    report["worker_needs"] = (f"a CPU worker {camera / 1024:.1f} GiB per camera task at the production preset "
                              f"({camera_full / 1024:.1f} GiB with full-size maps), the geometry (GPU) task "
                              f"{sdf_need / 1024:.1f} GiB of host memory")
    report["peaks_gib"] = {k: v["peak_rss_mib"] / 1024 for k, v in runs.items()}
    report["all_under_limit"] = bool(max(report["peaks_gib"].values()) < LIMIT_GIB and sdf_need / 1024 < LIMIT_GIB)
    (out / "bench_memory.json").write_text(json.dumps(report, indent=1))
    (out / "bench_memory.md").write_text(table(report))
    print(report["worker_needs"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
