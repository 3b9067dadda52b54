"""SDF sharpness: the geometry stage's mesh against the final NeuS sharpness, with the masks the pipeline publishes
and with oracle masks of the rays the SDF casts.

The SDF casts one ray through each pixel's centre and trains its opacity on the pixel's mask. On one action of a
simulated capture and its release (the views as the geometry stage loads them,
:func:`stages.geometry.load_sdf_views` through the artifact facade), this bench runs the stage's own function
(:func:`stages.numerics.sdf_mesh.sdf_mesh` with :class:`stages.geometry.GeometryConfig`: both passes, the published
mesh) once per (masks, ``inv_s_end``):

- masks ``pipeline``: the released masks (the photometric stage's);
- masks ``centre``: an oracle, each view's mask replaced by the pixels whose centre ray meets the truth mesh (traced
  with open3d from the view's calibrated camera) and the normals kept only there;
- masks ``recomputed``: the photometric stage's masks (:func:`stages.numerics.photometric.foreground_mask_and_holes`
  and the filled holes' decision, :func:`stages.numerics.gaps.background_holes`) made again on
  the action's decoded white images and the session's clean plates (from the run's store, ``<release>.work``) with
  the run's photometric parameters (its ``config.yaml``) and ``--mask-params`` changed
  (:class:`stages.numerics.photometric.PhotometricParams` fields, e.g. ``close_radius=0,majority_radius=0``), the
  normals kept only there;
- ``inv_s_end``: the final sharpness as given (``inv_s_end_per_pixel`` off), and a first row per mask kind with the
  stage default as it is (the rule of :func:`stages.numerics.sdf.sharpness_for_pixels`; its ``inv_s_end`` the one
  training used).

With ``--seeds`` every row is run once per SDF seed (``SDFConfig.seed``). Per row: Chamfer, F-score at 1 mm and
normal consistency (``stages.numerics.meshmetrics.mesh_metrics``), the median signed offset of the prediction
outside the truth per region of the truth (:func:`evaluation.mesh_regions.region_errors`: negative is inside), the
CPU seconds (one thread, as ``make dataset`` runs the stage) and the pixel footprint at the subject the training
measured
(:func:`stages.numerics.sdf.subject_pixel_m`). Per action: how much wider the released masks are than the centre
rays' (area difference over the centre mask's outline, pixels, mean over the views). A row's Chamfer moves by
about 0.1-0.2 mm with the SDF's seed: compare rows of one run, and several actions before reading a difference
under that as real.

``python bench/bench_sdf_sharpness.py --out bench/out [--capture C --release R] [--action A0000] [--inv-s
800,1600,3200] [--masks pipeline,centre,recomputed] [--mask-params k=v,...] [--seeds 0,1] [--workers 2]
[--quick]``: defaults are runs/default (``make dataset``);
without them it prints why and exits 0. ``--quick`` (the tests' mode): the tiny run of ``bench/_quick.py`` with the
schedule and meshes of ``bench_sdf_schedule``'s quick mode, all three mask kinds at the default sharpness and the
pipeline's masks at one value beside it; the numbers are not measurements.
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import write_report  # noqa: E402
from _release import parse_release_args, release_config, release_parser, store_artifacts  # noqa: E402

INV_S = (800.0, 1600.0, 3200.0)
QUICK_INV_S = (300.0,)
MASKS = ("pipeline", "centre", "recomputed")


def geometry_config(inv_s_end: float | None, quick: bool):
    """The stage default; with ``inv_s_end`` its SDF's final sharpness set to it (the pixel rule off). ``quick``:
    ``bench_sdf_schedule``'s quick schedule (its step counts over 60, a coarser hull, small meshes)."""
    from bench_sdf_schedule import quick_schedule_config, schedule_config
    from stages.geometry import GeometryConfig

    base = GeometryConfig()
    first, second = base.first_pass_iterations or base.sdf.iterations, base.sdf.iterations
    cfg = quick_schedule_config(first, second) if quick else schedule_config(first, second)
    if quick:  # the test preset's sharpness range: a few dozen steps cannot reach the cpu preset's
        cfg = dataclasses.replace(cfg, sdf=dataclasses.replace(cfg.sdf, inv_s_start=30.0, inv_s_end=150.0))
    if inv_s_end is not None:
        cfg = dataclasses.replace(cfg, sdf=dataclasses.replace(cfg.sdf, inv_s_end=float(inv_s_end),
                                                                inv_s_end_per_pixel=0.0))
    return cfg


def centre_ray_masks(views: list, truth_v: np.ndarray, truth_f: np.ndarray) -> list[np.ndarray]:
    """(H, W) bool per view: the pixels whose ray through the pixel centre (the SDF's ray) meets the truth mesh."""
    import open3d as o3d

    from artifacts.camera import camera_centre, pixel_rays

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.asarray(truth_v, np.float32), np.asarray(truth_f, np.uint32))
    out = []
    for view in views:
        H, W = np.asarray(view.mask).shape
        rows, cols = np.mgrid[0:H, 0:W]
        dirs = pixel_rays(view.K, view.cam_from_world, cols.astype(np.float64), rows.astype(np.float64))[0]
        origins = np.broadcast_to(camera_centre(view.cam_from_world), dirs.shape)
        rays = np.concatenate([origins, dirs], axis=-1).reshape(-1, 6).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        out.append(np.isfinite(hit).reshape(H, W))
    return out


def mask_widening_px(masks: list[np.ndarray], reference: list[np.ndarray]) -> float:
    """Mean over the views of how much wider ``masks`` are than ``reference``: area difference over the
    reference's outline length (pixels on its inner boundary), in pixels."""
    from scipy import ndimage

    values = []
    for mask, ref in zip(masks, reference):
        outline = int((ref & ~ndimage.binary_erosion(ref)).sum())
        if outline:
            values.append((int(np.asarray(mask, bool).sum()) - int(ref.sum())) / outline)
    return float(np.mean(values)) if values else float("nan")


def _load(capture: Path, release: Path, action: str, quick: bool):
    from bench_geometry import load_release_views

    from pipeline.codecs.mesh import read_ply

    views = load_release_views(release, action, geometry_config(None, quick))
    truth_v, truth_f = read_ply(capture / "ground_truth" / action / "mesh.ply")
    return views, truth_v, truth_f


def parse_mask_params(text: str) -> dict:
    """``"name=value,..."`` -> PhotometricParams changes, the values read as YAML (as ``bench_relit_budget``'s
    ``--shading``); unknown fields and values that break the rules are refused by :func:`pipeline.config.merge`."""
    import yaml

    from pipeline.config import merge
    from stages.numerics.photometric import PhotometricParams

    changes = {}
    for item in (x.strip() for x in text.split(",") if x.strip()):
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ValueError(f"--mask-params: {item!r} is not name=value")
        changes[name.strip()] = yaml.safe_load(value)
    merge(PhotometricParams(), changes, "--mask-params")
    return changes


def recomputed_masks(release: Path, action: str, views: list, mask_params: dict) -> list[np.ndarray]:
    """(H, W) bool per view: the photometric stage's masks made again from the views' decoded images and clean
    plates (the run's store beside ``release``), with the run's photometric config (its ``config.yaml``) and
    ``mask_params`` changed: each view's foreground mask with its small holes filled, then the filled holes decided
    as the stage decides them (:func:`stages.numerics.gaps.background_holes`)."""
    from pipeline.config import merge
    from stages.geometry import load_sdf_views
    from stages.numerics.gaps import background_holes
    from stages.numerics.hull import default_stage_box, subject_box
    from stages.numerics.photometric import foreground_mask_and_holes
    from stages.photometric import PhotometricConfig

    art = store_artifacts(release, action, ("decode", "photometric"), ("plates",))
    ids, store_views = load_sdf_views(art, 0.5)
    if len(ids) != len(views) or any(not np.array_equal(a.K, b.K) for a, b in zip(store_views, views)):
        raise ValueError(f"the store beside {release} does not hold the release's views of {action}")
    config = release_config(release, "photometric", PhotometricConfig)
    params = merge(config.params, mask_params, "--mask-params")
    masks, holes = zip(*(foreground_mask_and_holes(art.exr("full_on", camera=cam)[..., :3], art.plate(cam), params)
                         for cam in ids))
    if not config.gaps.enabled or not any(h.any() for h in holes):
        return list(masks)
    Ks, Ts = [v.K for v in store_views], [v.cam_from_world for v in store_views]
    try:
        box = subject_box(list(masks), Ks, Ts, default_stage_box(list(zip(Ks, Ts))))
    except ValueError:  # the stage leaves the holes filled then
        return list(masks)
    gradients = [lambda cam=cam: (art.exr("pos", camera=cam), art.exr("neg", camera=cam)) for cam in ids]
    gaps, _ = background_holes(list(masks), list(holes), Ks, Ts, box, gradients, config.gaps)
    return [m & ~g for m, g in zip(masks, gaps)]


def run_row(args: tuple) -> dict:
    """One (masks, inv_s_end, seed) row: the stage's passes on the action's views (their masks replaced by
    ``replaced`` unless it is None), the mesh measured."""
    os.environ.setdefault("ULTRASTAGE_NUMERIC_THREADS", "1")
    import torch

    from evaluation.mesh_regions import region_errors, truth_face_regions
    from stages.numerics.meshmetrics import mesh_metrics
    from stages.numerics.sdf_mesh import sdf_mesh

    torch.set_num_threads(1)
    capture, release, action, masks, replaced, inv_s_end, quick, seed = args
    capture, release = Path(capture), Path(release)
    views, truth_v, truth_f = _load(capture, release, action, quick)
    if replaced is not None:
        views = [dataclasses.replace(v, mask=m, normal_valid=np.asarray(v.normal_valid, bool) & m)
                 for v, m in zip(views, replaced)]
    cfg = geometry_config(inv_s_end, quick)
    cfg = dataclasses.replace(cfg, sdf=dataclasses.replace(cfg.sdf, seed=int(seed)))
    cpu = time.process_time()
    fitted = sdf_mesh(views, cfg)
    cpu = time.process_time() - cpu
    metrics = mesh_metrics(fitted.vertices, fitted.faces, truth_v, truth_f)
    truth = json.loads((capture / "ground_truth" / action / "truth.json").read_text())
    garment = (truth.get("subject") or {}).get("garment") or {}
    region, names = truth_face_regions(truth_v, truth_f, int(garment.get("triangles", 0)))
    regions = region_errors(fitted.vertices, fitted.faces, truth_v, truth_f, region, names,
                            20_000 if quick else 200_000)
    return {"masks": masks, "seed": int(seed), "inv_s_end_set": inv_s_end,
            "inv_s_end": float(fitted.result.stats["inv_s_end"]),
            "subject_pixel_m": float(fitted.result.stats["subject_pixel_m"]), "cpu_s": cpu,
            "chamfer_mm": float(metrics["chamfer_mm"]), "fscore_1mm": float(metrics["fscore_1mm"]),
            "normal_consistency": float(metrics["normal_consistency"]),
            "offset_median_mm": {name: float(r["offset_median_mm"]) for name, r in regions.items()}}


def plot(path: Path, report: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for masks, colour in zip(MASKS, ("tab:blue", "tab:orange", "tab:green")):
        rows = sorted((r for r in report["rows"] if r["masks"] == masks and r.get("seed", 0) == report["seeds"][0]),
                      key=lambda r: r["inv_s_end"])
        if rows:
            ax.plot([r["inv_s_end"] for r in rows], [r["chamfer_mm"] for r in rows], "o-", color=colour,
                    label=f"{masks} masks")
            for r in rows:
                if r["inv_s_end_set"] is None:
                    ax.annotate("default", (r["inv_s_end"], r["chamfer_mm"]), textcoords="offset points",
                                xytext=(4, 4), fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("final NeuS sharpness inv_s_end (1/m)")
    ax.set_ylabel("Chamfer (mm)")
    ax.set_title(f"SDF sharpness ({report['action']}, {1000 * report['subject_pixel_m']:.2f} mm per pixel)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def markdown(report: dict) -> str:
    regions = sorted({name for r in report["rows"] for name in r["offset_median_mm"]})
    lines = [f"# SDF sharpness ({report['action']})" + (" - quick run, not measurements" if report["quick"] else ""),
             "", f"Pixel footprint at the subject {1000 * report['subject_pixel_m']:.2f} mm; the released masks are "
             f"{report['mask_widening_px']:+.3f} px wider than the pixel-centre rays' (mean over the views)"
             + (f"; the recomputed masks ({report['mask_params'] or 'the run parameters'}) "
                f"{report['recomputed_widening_px']:+.3f} px" if report.get("recomputed_widening_px") is not None
                else "") + ".", "",
             "| masks | seed | inv_s_end | CPU s | Chamfer mm | F@1mm | normal consistency | "
             + " | ".join(f"offset {name} mm" for name in regions) + " |",
             "|---|---|---|---|---|---|---|" + "---|" * len(regions)]
    for r in report["rows"]:
        setting = f"{r['inv_s_end']:.0f}" + (" (default)" if r["inv_s_end_set"] is None else "")
        lines.append(f"| {r['masks']} | {r.get('seed', 0)} | {setting} | {r['cpu_s']:.0f} | {r['chamfer_mm']:.3f} | "
                     f"{100 * r['fscore_1mm']:.1f}% | {r['normal_consistency']:.4f} | "
                     + " | ".join(f"{r['offset_median_mm'].get(name, float('nan')):+.2f}" for name in regions) + " |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = release_parser(__doc__)
    parser.add_argument("--action", default="A0000")
    parser.add_argument("--inv-s", help="final sharpness values, comma-separated (default 800,1600,3200)")
    parser.add_argument("--masks", help="pipeline, centre, recomputed (comma-separated; default pipeline,centre; "
                                         "with --quick all three)")
    parser.add_argument("--mask-params", default="",
                        help="PhotometricParams changes of the recomputed masks, name=value,...")
    parser.add_argument("--seeds", default="0", help="SDF seeds, comma-separated (default 0)")
    parser.add_argument("--workers", type=int, default=2, help="rows measured side by side (one thread each)")
    args = parse_release_args(parser)
    capture, release = Path(args.capture), Path(args.release)
    if not (capture / "ground_truth" / args.action / "mesh.ply").exists() or not release.is_dir():
        print(f"bench_sdf_sharpness: needs {capture} with ground truth and {release} (make dataset first); skipped")
        return 0
    masks = [m.strip() for m in (args.masks or ("pipeline,centre,recomputed" if args.quick else "pipeline,centre"))
             .split(",") if m.strip()]
    unknown = sorted(set(masks) - set(MASKS))
    if unknown:
        parser.error(f"--masks: unknown {unknown}; choose from {list(MASKS)}")
    try:
        mask_params = parse_mask_params(args.mask_params)
        seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
    except (ValueError, TypeError) as exc:
        parser.error(str(exc))
    if not seeds:
        parser.error("--seeds: at least one seed")
    values = [float(x) for x in args.inv_s.split(",")] if args.inv_s else list(QUICK_INV_S if args.quick else INV_S)
    views, truth_v, truth_f = _load(capture, release, args.action, args.quick)
    centre = centre_ray_masks(views, truth_v, truth_f)
    widening = mask_widening_px([np.asarray(v.mask, bool) for v in views], centre)
    replacements = {"pipeline": None, "centre": centre}
    if "recomputed" in masks:
        replacements["recomputed"] = recomputed_masks(release, args.action, views, mask_params)
    recomputed = mask_widening_px(replacements["recomputed"], centre) if "recomputed" in masks else None
    # quick: the sharpness values on the pipeline's masks only; the other kinds at the default
    jobs = [(str(capture), str(release), args.action, m, replacements[m], value, args.quick, seed)
            for seed in seeds for m in masks
            for value in [None] + (values if m == "pipeline" or not args.quick else [])]
    with ProcessPoolExecutor(max_workers=max(1, args.workers)) as pool:
        rows = list(pool.map(run_row, jobs))
    # the footprint the first row's training measured (the same views for every row of a mask kind)
    report = {"action": args.action, "quick": args.quick, "subject_pixel_m": rows[0]["subject_pixel_m"],
              "mask_widening_px": widening, "mask_params": args.mask_params, "recomputed_widening_px": recomputed,
              "seeds": seeds, "rows": rows}
    write_report(args.out, "bench_sdf_sharpness", report, markdown(report), lambda path: plot(path, report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
