"""Geometry: the normal-supervised neural SDF (stages.numerics.sdf) against the truth, time against error.

On one action of a simulated capture and its release (the photometric normal maps, masks and cameras the
pipeline published, read through the artifact facade as the geometry stage reads them:
:func:`stages.geometry.load_sdf_views`), on one CPU thread as ``make dataset`` runs it:

1. **time vs Chamfer over iterations**: one training run of the preset (the stage's one-pass schedule), the field
   snapshotted at checkpoints (``log_every``); each snapshot is meshed and measured afterwards (training time
   only on the x axis);
2. the geometry stage's **two passes** (``geometry.deocclude``), run by the stage's own function
   (:func:`stages.numerics.sdf_mesh.sdf_mesh` with :class:`stages.geometry.GeometryConfig` over the same SDF
   preset, its passes from :func:`~stages.numerics.sdf_mesh.pass_configs`): a first pass of
   ``first_pass_iterations`` steps meshed as the stage meshes it, eq. 1's normals with that mesh's occlusion of
   the LED sphere divided out, and the second training on them that draws the stage's share of its rays where
   the first mesh missed the normals (``geometry.second_pass_importance``), snapshotted like 1. (its clock starts
   where the first pass, its mesh and the de-occlusion ended); the stage's published mesh (largest component,
   decimated) is scored too. The same curve for the **mask-only ablation** (``normal_supervision=False``) and
   the **visual hull alone** (classic centre test at 256^3, no dilation, one miss allowed);
3. **marching resolution**: mesh extraction time and Chamfer of the final field per grid resolution;
4. **empty-space skipping**: share of the naive uniform samples (same spacing, every pixel's ray through the
   stage box) the hull and the cached SDF grid let the training skip;
5. **SDF gradients**: time of a forward + backward pass of the eikonal and normal terms on 4096 points with
   the analytic (forward-mode Jacobian), finite-difference and autograd (double backward) gradients.

Meshes: ``stages.numerics.mesh.extract_mesh``; metrics: ``stages.numerics.meshmetrics.mesh_metrics``
(point-to-surface Chamfer, mean of both directions, in mm; normal consistency; F-scores), with a
skimage + cKDTree fallback when those modules are absent. The ground-truth mesh may hold parts no camera
sees (mouth, soles on the floor): look at both directions.

``python bench/bench_geometry.py --out bench/out [--capture DIR --release DIR --action A0000]`` writes
bench_geometry.json, bench_geometry.png and bench_geometry.md; defaults are runs/default/capture and
runs/default/release (``make dataset``); without them it prints why and exits 0. ``--quick`` (the tests' mode):
the tiny run of ``bench/_quick.py`` unless ``--capture``/``--release`` are given, 30 steps per training and per
pass (after 20 of the fit to a hull of 48 cells), 2 checkpoints, meshes at 64 and 96 cells (the stage's first and
published meshes at 96, the visual hull alone at 64), 10k surface samples, gradients timed once on 512 points;
the numbers are not measurements.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import write_report  # noqa: E402
from _quick import QUICK_HELP  # noqa: E402
from _release import parse_release_args  # noqa: E402


# ------------------------------------------------------------------------------------------------ inputs


def load_release_views(release: Path, action: str, geometry):
    """The SDF views of one released action as the geometry stage with config ``geometry`` loads them
    (:func:`stages.geometry.load_sdf_views` through the artifact facade: the photometric normal maps, masks and
    cameras of ``transforms.json``)."""
    from manifests import release_artifacts
    from stages.geometry import load_sdf_views

    return load_sdf_views(release_artifacts(release, action), geometry.min_alpha)[1]


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        from pipeline.codecs.mesh import read_ply

        v, f = read_ply(path)
    except ImportError:
        import open3d as o3d

        m = o3d.io.read_triangle_mesh(str(path))
        v, f = np.asarray(m.vertices), np.asarray(m.triangles)
    return np.asarray(v, np.float64), np.asarray(f, np.int64)


# ------------------------------------------------------------------------------------------------ meshing


def mesh_of(sdf_fn, bounds: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(vertices, faces, seconds) of the zero level set."""
    start = time.perf_counter()
    try:
        from stages.numerics.mesh import extract_mesh

        v, f, _ = extract_mesh(sdf_fn, bounds, resolution)
    except ImportError:
        from skimage.measure import marching_cubes

        ext = bounds[1] - bounds[0]
        h = float(ext.max()) / resolution
        n = np.ceil(ext / h).astype(int) + 1
        axes = [bounds[0, a] + np.arange(n[a]) * h for a in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
        values = np.asarray(sdf_fn(grid), np.float32).reshape(tuple(n))
        if not (values.min() < 0 < values.max()):
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64), time.perf_counter() - start
        v, f, _, _ = marching_cubes(values, 0.0, spacing=(h, h, h))
        v = v + bounds[0]
    return np.asarray(v, np.float64), np.asarray(f, np.int64), time.perf_counter() - start


def metrics_of(v, f, gt_v, gt_f, n_samples: int) -> dict:
    if len(f) == 0:
        return {"chamfer_mm": None, "chamfer_pred_to_gt_mm": None, "chamfer_gt_to_pred_mm": None,
                "normal_consistency": None, "fscore_1mm": None, "fscore_5mm": None}
    try:
        from stages.numerics.meshmetrics import mesh_metrics

        m = mesh_metrics(v, f, gt_v, gt_f, n_samples=n_samples)
    except ImportError:
        m = _fallback_metrics(v, f, gt_v, gt_f, n_samples)
    keys = ("chamfer_mm", "chamfer_pred_to_gt_mm", "chamfer_gt_to_pred_mm", "normal_consistency",
            "fscore_1mm", "fscore_5mm")
    return {k: float(m[k]) for k in keys}


def _fallback_metrics(v, f, gt_v, gt_f, n) -> dict:
    from scipy.spatial import cKDTree

    def sample(vv, ff, seed):
        rng = np.random.default_rng(seed)
        a, b = vv[ff[:, 1]] - vv[ff[:, 0]], vv[ff[:, 2]] - vv[ff[:, 0]]
        cross = np.cross(a, b)
        area = np.linalg.norm(cross, axis=1)
        idx = rng.choice(len(ff), n, p=area / area.sum())
        r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
        p = (vv[ff[idx, 0]] * (1 - r1)[:, None] + vv[ff[idx, 1]] * (r1 * (1 - r2))[:, None]
             + vv[ff[idx, 2]] * (r1 * r2)[:, None])
        return p, cross[idx] / np.maximum(area[idx], 1e-20)[:, None]

    pp, pn = sample(v, f, 0)
    gp, gn = sample(gt_v, gt_f, 1)
    d_pg, i_pg = cKDTree(gp).query(pp)
    d_gp, i_gp = cKDTree(pp).query(gp)
    out = {"chamfer_mm": 500 * (d_pg.mean() + d_gp.mean()), "chamfer_pred_to_gt_mm": 1000 * d_pg.mean(),
           "chamfer_gt_to_pred_mm": 1000 * d_gp.mean(),
           "normal_consistency": 0.5 * (np.abs((pn * gn[i_pg]).sum(1)).mean() + np.abs((gn * pn[i_gp]).sum(1)).mean())}
    for t, name in ((0.001, "1mm"), (0.005, "5mm")):
        p, r = (d_pg <= t).mean(), (d_gp <= t).mean()
        out[f"fscore_{name}"] = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return out


# ------------------------------------------------------------------------------------------------ runs


def train_with_checkpoints(views, config, checkpoints: int):
    """Train once; snapshot the field at ``checkpoints`` evenly spaced steps (``train_sdf``'s checkpoint hook)."""
    from stages.numerics.sdf import SDFField, train_sdf

    config = dataclasses.replace(config, log_every=max(1, config.iterations // checkpoints))
    snapshots = []

    def keep(iteration: int, field) -> None:
        snapshots.append((iteration, field.to_state()))

    result = train_sdf(views, config, checkpoint=keep)
    # Snapshot copies take a few ms each; the history's seconds are the training clock.
    seconds = dict(zip(result.history["iteration"], result.history["seconds"]))
    fields = [(it, seconds.get(it, float("nan")), SDFField.from_state(state).eval()) for it, state in snapshots]
    return result, fields


def stage_passes_with_checkpoints(views, geometry, checkpoints: int):
    """The geometry stage's two passes (:func:`stages.numerics.sdf_mesh.sdf_mesh` with ``geometry``), the second
    pass's field snapshotted at ``checkpoints`` evenly spaced steps; the snapshots' seconds are the training
    clock from the stage's start (first pass, its mesh and the de-occlusion before the second pass's own)."""
    from stages.numerics.sdf import SDFField
    from stages.numerics.sdf_mesh import sdf_mesh

    sdf = dataclasses.replace(geometry.sdf, log_every=max(1, geometry.sdf.iterations // checkpoints))
    snapshots = []

    def keep(index: int, iteration: int, field) -> None:
        if index == 2:
            snapshots.append((iteration, field.to_state()))

    fitted = sdf_mesh(views, dataclasses.replace(geometry, sdf=sdf), checkpoint=keep)
    history = fitted.result.history
    seconds = dict(zip(history["iteration"], history["seconds"]))
    fields = [(it, fitted.second_pass_start_s + seconds.get(it, float("nan")), SDFField.from_state(state).eval())
              for it, state in snapshots]
    return fitted, fields


def curve(fields, bounds, gt_v, gt_f, resolution: int, n_samples: int) -> list[dict]:
    rows = []
    for iteration, seconds, field in fields:
        v, f, _ = mesh_of(field.sdf_numpy, bounds, resolution)
        rows.append({"iteration": int(iteration), "train_seconds": float(seconds),
                     **metrics_of(v, f, gt_v, gt_f, n_samples)})
    return rows


def gradient_timing(config, bounds, points: int = 4096, repeats: int = 3) -> dict:
    """ms of forward + backward of eikonal + normal terms per gradient mode (best of ``repeats``)."""
    import torch

    from stages.numerics.sdf import SDFField

    field = SDFField(bounds, config.encoding, config.hidden_width, config.hidden_layers)
    generator = torch.Generator().manual_seed(0)
    lo = torch.tensor(bounds[0], dtype=torch.float32)
    ext = torch.tensor(bounds[1] - bounds[0], dtype=torch.float32)
    x = lo + torch.rand((points, 3), generator=generator) * ext
    target = torch.nn.functional.normalize(torch.randn((points, 3), generator=generator), dim=1)
    out = {}
    for mode in ("analytic", "finite_difference", "autograd"):
        best = float("inf")
        for _ in range(repeats + 1):  # the first is a warm-up
            start = time.perf_counter()
            sdf, grad = field.sdf_and_gradient(x, mode, config.fd_step_m)
            loss = (grad.norm(dim=1) - 1).square().mean() + (1 - torch.cosine_similarity(grad, target)).mean()
            field.zero_grad(set_to_none=True)
            loss.backward()
            best = min(best, time.perf_counter() - start)
        out[mode] = 1000.0 * best
    return out


# ------------------------------------------------------------------------------------------------ report


def plot(path: Path, report: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), dpi=100)
    ax = axes[0]
    for key, label, style in (("normal_supervised", "normal-supervised SDF", "o-"),
                              ("deoccluded_second_pass", "second pass, de-occluded normals", "^-"),
                              ("mask_only", "mask-only ablation", "s--")):
        rows = [r for r in report["curves"].get(key, []) if r["chamfer_mm"] is not None]
        if rows:
            ax.plot([r["train_seconds"] for r in rows], [r["chamfer_mm"] for r in rows], style, label=label)
    hull = report.get("hull_alone", {}).get("chamfer_mm")
    if hull is not None:
        ax.axhline(hull, color="grey", ls=":", label=f"visual hull alone ({hull:.1f} mm)")
    ax.set_xlabel("training time (s, 1 thread)")
    ax.set_ylabel("Chamfer (mm, mean of both directions)")
    ax.set_yscale("log")
    ax.set_title("time vs Chamfer over iterations")
    ax.legend(fontsize=8)
    ax = axes[1]
    rows = report["marching"]
    ax.plot([r["resolution"] for r in rows], [r["chamfer_mm"] for r in rows], "o-", color="C0")
    ax.set_xlabel("marching-cubes cells along the longest side")
    ax.set_ylabel("Chamfer (mm)", color="C0")
    twin = ax.twinx()
    twin.plot([r["resolution"] for r in rows], [r["seconds"] for r in rows], "s--", color="C1")
    twin.set_ylabel("extraction time (s)", color="C1")
    ax.set_title("marching resolution")
    ax = axes[2]
    modes = report["gradient_ms"]
    ax.bar(list(modes), list(modes.values()), color=["C0", "C1", "C2"])
    ax.set_ylabel(f"ms per forward + backward ({report['gradient_points']} points)")
    ax.set_title("SDF gradients")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def fmt(x, digits=2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def markdown(report: dict) -> str:
    s = report["skipping"]
    lines = [
        "## Geometry: normal-supervised neural SDF",
        "",
        f"Action {report['action']} ({report['views']} views, {report['image_size']}), preset "
        f"`{report['preset']}`, one CPU thread. Chamfer: point-to-surface, mean of both directions (mm).",
        "",
        "| method | train s | Chamfer | pred->gt | gt->pred | normal consistency | F@1mm | F@5mm |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, row in report["final"].items():
        lines.append(f"| {name} | {fmt(row.get('time_s'), 1)} | {fmt(row['chamfer_mm'])} | "
                     f"{fmt(row['chamfer_pred_to_gt_mm'])} | {fmt(row['chamfer_gt_to_pred_mm'])} | "
                     f"{fmt(row['normal_consistency'], 4)} | {fmt(row['fscore_1mm'], 3)} | {fmt(row['fscore_5mm'], 3)} |")
    lines += ["", "Over iterations (normal-supervised):", "", "| iteration | train s | Chamfer | normal consistency |",
              "|---|---|---|---|"]
    for r in report["curves"]["normal_supervised"]:
        lines.append(f"| {r['iteration']} | {r['train_seconds']:.1f} | {fmt(r['chamfer_mm'])} | "
                     f"{fmt(r['normal_consistency'], 4)} |")
    if "deoccluded_second_pass" in report["curves"]:
        lines += ["", "Second pass on de-occluded normals (clock continues from the first pass):", "",
                  "| iteration | train s | Chamfer | normal consistency |", "|---|---|---|---|"]
        for r in report["curves"]["deoccluded_second_pass"]:
            lines.append(f"| {r['iteration']} | {r['train_seconds']:.1f} | {fmt(r['chamfer_mm'])} | "
                         f"{fmt(r['normal_consistency'], 4)} |")
    lines += ["", "Marching resolution (first pass's final field):", "", "| cells | seconds | Chamfer |",
              "|---|---|---|"]
    for r in report["marching"]:
        lines.append(f"| {r['resolution']} | {r['seconds']:.2f} | {fmt(r['chamfer_mm'])} |")
    lines += ["", f"Empty space: {100 * s['samples_skipped_fraction']:.2f}% of the naive uniform samples skipped "
              f"(rays worth drawing: {100 * s['candidate_ray_fraction']:.1f}% of the pixels; hull occupies "
              f"{100 * s['hull_occupied_fraction']:.1f}% of its box).", "",
              f"SDF gradients, ms per forward + backward on {report['gradient_points']} points: " + ", ".join(
                  f"{k} {v:.1f}" for k, v in report["gradient_ms"].items()), ""]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--capture", help="default runs/default/capture; with --quick the tiny run's")
    parser.add_argument("--release", help="default runs/default/release; with --quick the tiny run's")
    parser.add_argument("--action", default="A0000")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--iterations", type=int, help="override the preset's iterations (quick checks)")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="override an SDFConfig field of the preset, e.g. --set weight_mask=0.1 (repeatable)")
    parser.add_argument("--checkpoints", type=int, default=8)
    parser.add_argument("--eval-resolution", type=int, default=256)
    parser.add_argument("--samples", type=int, default=100_000, help="surface samples per mesh for the metrics")
    parser.add_argument("--no-ablation", action="store_true", help="skip the mask-only run")
    parser.add_argument("--no-deocclude", action="store_true", help="skip the second pass on de-occluded normals")
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parse_release_args(parser)
    marching = (128, 192, 256, 384, 512)
    hull_resolution, stage_mesh_resolution, gradient_points, gradient_repeats = 256, None, 4096, 3
    if args.quick:
        args.iterations, args.checkpoints, args.eval_resolution, args.samples = 30, 2, 64, 10_000
        marching, hull_resolution, stage_mesh_resolution, gradient_points, gradient_repeats = (64, 96), 64, 96, 512, 1

    out = Path(args.out)
    capture, release = Path(args.capture), Path(args.release)
    gt_mesh = capture / "ground_truth" / args.action / "mesh.ply"
    from manifests import ReleaseError, release_artifacts

    try:
        release_artifacts(release, args.action).existing("transforms")
        missing = [] if gt_mesh.exists() else [str(gt_mesh)]
    except (ReleaseError, KeyError, FileNotFoundError) as exc:
        missing = [f"{args.action} of a release at {release} ({exc})"] + ([] if gt_mesh.exists() else [str(gt_mesh)])
    if missing:
        print(f"bench_geometry: skipped, missing {', '.join(missing)} (run `make dataset`, or pass --capture "
              f"and --release of a simulated capture and its release)")
        return 0

    import torch

    from stages.geometry import GeometryConfig
    from stages.numerics.hull import visual_hull
    from stages.numerics.sdf import SDF_PRESETS
    from stages.numerics.sdf_mesh import pass_configs

    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    sdf = dataclasses.replace(SDF_PRESETS[args.preset], device="cpu")
    if args.iterations:
        sdf = dataclasses.replace(sdf, iterations=args.iterations)
    if args.quick:
        sdf = dataclasses.replace(sdf, hull_resolution=48, hull_init_steps=20)
    for item in args.set:
        name, _, value = item.partition("=")
        if name not in {f.name for f in dataclasses.fields(sdf)} or not value:
            parser.error(f"--set {item}: expected FIELD=VALUE with an SDFConfig field")
        current = getattr(sdf, name)
        parsed = value.lower() in ("1", "true", "yes") if isinstance(current, bool) else type(current)(value)
        sdf = dataclasses.replace(sdf, **{name: parsed})
    # the geometry stage's config with that SDF; its one-pass schedule is the curve over iterations
    geometry = GeometryConfig(sdf=sdf)
    if stage_mesh_resolution:
        geometry = dataclasses.replace(geometry, first_pass_iterations=sdf.iterations,
                                       first_pass_mesh_resolution=stage_mesh_resolution,
                                       mesh_resolution=stage_mesh_resolution)
    config, _ = pass_configs(dataclasses.replace(geometry, deocclude=False))
    views = load_release_views(release, args.action, geometry)
    gt_v, gt_f = read_mesh(gt_mesh)
    print(f"bench_geometry: {len(views)} views of {args.action}, preset {args.preset}", flush=True)

    report: dict = {"action": args.action, "views": len(views), "preset": args.preset, "quick": args.quick,
                    "image_size": "x".join(str(s) for s in views[0].mask.shape[::-1]),
                    "config": dataclasses.asdict(config), "curves": {}, "final": {}}

    result, fields = train_with_checkpoints(views, config, args.checkpoints)
    bounds = np.asarray(result.bounds)
    print(f"  normal-supervised: {result.stats['time_s']:.1f} s", flush=True)
    report["curves"]["normal_supervised"] = curve(fields, bounds, gt_v, gt_f, args.eval_resolution, args.samples)
    final = dict(report["curves"]["normal_supervised"][-1])  # the last checkpoint is the returned field
    final["time_s"] = float(result.stats["time_s"])
    report["final"]["normal-supervised SDF"] = final
    report["stats"] = {k: v for k, v in result.stats.items() if isinstance(v, (int, float, str, dict))}
    report["skipping"] = {k: result.stats[k] for k in ("samples_skipped_fraction", "candidate_ray_fraction",
                                                        "hull_occupied_fraction", "samples_evaluated", "naive_samples")}

    if not args.no_deocclude:
        fitted, fields_2 = stage_passes_with_checkpoints(views, geometry, args.checkpoints)
        first_s = float(fitted.first_pass["stats"]["time_s"])
        between = fitted.second_pass_start_s - first_s
        deocclusion = fitted.deocclusion
        print(f"  the stage's two passes: {first_s:.1f} + {between:.1f} + {fitted.result.stats['time_s']:.1f} s "
              f"(mean turn {deocclusion['occlusion_correction_mean_deg']:.2f} deg)", flush=True)
        report["curves"]["deoccluded_second_pass"] = curve(fields_2, np.asarray(fitted.result.bounds), gt_v, gt_f,
                                                           args.eval_resolution, args.samples)
        final = dict(report["curves"]["deoccluded_second_pass"][-1])
        final["time_s"] = fitted.second_pass_start_s + float(fitted.result.stats["time_s"])
        report["final"]["two passes, the second on de-occluded normals (stage default)"] = final
        report["final"][f"the stage's published mesh ({geometry.mesh_resolution} cells, decimated)"] = {
            "time_s": fitted.train_seconds, **metrics_of(fitted.vertices, fitted.faces, gt_v, gt_f, args.samples)}
        report["deocclusion"] = deocclusion | {"first_pass_s": first_s, "mesh_and_visibility_s": between,
                                               "first_pass_iterations": pass_configs(geometry)[0].iterations}

    report["marching"] = []
    for resolution in marching:
        v, f, seconds = mesh_of(result.field.sdf_numpy, bounds, resolution)
        report["marching"].append({"resolution": resolution, "seconds": seconds, "faces": int(len(f)),
                                   **metrics_of(v, f, gt_v, gt_f, args.samples)})
        print(f"  marching {resolution}: {seconds:.2f} s", flush=True)

    if not args.no_ablation:
        ablation = dataclasses.replace(config, normal_supervision=False)
        result_mask, fields_mask = train_with_checkpoints(views, ablation, args.checkpoints)
        print(f"  mask-only: {result_mask.stats['time_s']:.1f} s", flush=True)
        report["curves"]["mask_only"] = curve(fields_mask, np.asarray(result_mask.bounds), gt_v, gt_f,
                                              args.eval_resolution, args.samples)
        final = dict(report["curves"]["mask_only"][-1])
        final["time_s"] = float(result_mask.stats["time_s"])
        report["final"]["mask-only ablation"] = final

    start = time.perf_counter()
    hull = visual_hull([v.mask for v in views], [v.K for v in views], [v.cam_from_world for v in views], bounds,
                       hull_resolution, max_misses=1, dilate_px=0, conservative=False)
    sd = hull.signed_distance()
    hull_s = time.perf_counter() - start
    v, f, _ = mesh_of(lambda p: hull.sample(sd, p), hull.bounds, hull_resolution)
    report["hull_alone"] = {"time_s": hull_s, **metrics_of(v, f, gt_v, gt_f, args.samples)}
    report["final"][f"visual hull alone ({hull_resolution}^3)"] = report["hull_alone"]

    report["gradient_ms"] = gradient_timing(config, bounds, gradient_points, gradient_repeats)
    report["gradient_points"] = gradient_points

    write_report(out, "bench_geometry", report, markdown(report), lambda path: plot(path, report), json_default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
