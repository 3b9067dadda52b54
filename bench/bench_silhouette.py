"""Silhouette refinement: the SDF's mesh against the mesh with its contours moved to the measured outline.

The geometry stage refines the SDF's mesh (:func:`stages.numerics.silhouette.refine_silhouettes`) with each view's
pixel coverage measured on the outline of its mask (:func:`stages.numerics.photometric.edge_coverage` of the
decoded white image against the clean plate). Per action of a simulated capture and its release this bench starts
from the SDF's own mesh (``sdf/mesh.ply`` of the geometry stage's store entry, ``<release>.work``), holds out two
spread-out cameras (:func:`evaluation.heldout.spread_heldout`) and refines with the others, once per
(``outline_bias_px``, ``smoothing``) and once with the simulator's true pixel coverage (8 x 8 rays on the truth
mesh: the oracle of a perfect measurement). Per row: Chamfer, F-score at 1 mm and normal consistency
(:func:`stages.numerics.meshmetrics.mesh_metrics`), the RMS of the mesh's pixel coverage against the truth's on the
outline pixels (either coverage partial, or the two different) of ``--novel`` novel views halfway between
neighbouring cameras (as the relight stage places them) and of the held-out views, and the seconds of the step.

Per action also: how far the measured outline lies outside the one the true coverage gives, on the same profiles
of the SDF mesh's contour vertices (pixels; mean and median): what ``outline_bias_px`` corrects.

``python bench/bench_silhouette.py --out bench/out [--capture C --release R] [--actions A0000,A0001] [--biases
0,0.06,0.1] [--smoothing 8,32] [--novel 8] [--quick]``: defaults are runs/default (``make dataset``); without it
it prints why and exits 0. ``--quick`` (the tests' mode): the tiny run of ``bench/_quick.py``, one bias and one
smoothing; the numbers are not measurements.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import write_report  # noqa: E402
from _release import check_inputs, parse_release_args, release_parser, store_artifacts  # noqa: E402

COVERAGE_RAYS = 8  # per pixel side, for the truth's and the meshes' coverage


def outline_rms(truth_scene, mesh_scene_, cameras: list) -> float:
    """RMS over ``cameras`` ((K, cam_from_world, height, width)) of the mesh's pixel coverage against the truth's,
    on the pixels where either is partial or the two differ."""
    from stages.numerics.raycast import pixel_coverage

    errors = []
    for K, P, h, w in cameras:
        ct = pixel_coverage(K, P, h, w, COVERAGE_RAYS, truth_scene)
        cm = pixel_coverage(K, P, h, w, COVERAGE_RAYS, mesh_scene_)
        outline = ((ct > 0) & (ct < 1)) | ((cm > 0) & (cm < 1)) | (ct != cm)
        errors.append((ct - cm)[outline])
    return float(np.sqrt(np.mean(np.square(np.concatenate(errors))))) if errors else float("nan")


def measure_action(capture: Path, release: Path, action: str, biases: list[float], smoothing: list[int],
                   novel_count: int) -> dict:
    """Every row of one action (module docstring)."""
    from bench_geometry import read_mesh

    from evaluation.heldout import spread_heldout
    from manifests import release_artifacts
    from stages.geometry import GeometryConfig, load_sdf_views, outline_views
    from stages.numerics.gbuffer import interpolate_camera, novel_camera_pairs
    from stages.numerics.meshmetrics import mesh_metrics
    from stages.numerics.raycast import mesh_scene, pixel_coverage
    from stages.numerics.silhouette import OutlineView, outline_disagreement, refine_silhouettes

    store = store_artifacts(release, action, ("decode", "geometry"), ("plates",))
    sdf_v, sdf_f = read_mesh(store.upstream["geometry"] / "sdf" / "mesh.ply")
    truth_v, truth_f = read_mesh(capture / "ground_truth" / action / "mesh.ply")
    released = release_artifacts(release, action)
    cameras = released.cameras()
    ids, views = load_sdf_views(released, GeometryConfig().min_alpha)  # the cameras with maps, as the stage reads them
    heldout = set(spread_heldout(cameras, 2))
    keep = [i for i, c in enumerate(ids) if c not in heldout]
    measured_all = outline_views(store, ids, views)
    if measured_all is None:
        raise ValueError(f"{action}: the session has no clean plates: nothing to measure the outline with")
    measured = [measured_all[i] for i in keep]
    truth_scene = mesh_scene(truth_v, truth_f)
    oracle = [OutlineView(K=v.K, cam_from_world=v.cam_from_world,
                          coverage=pixel_coverage(v.K, v.cam_from_world, *np.asarray(v.mask).shape, COVERAGE_RAYS,
                                                  truth_scene)) for v in (views[i] for i in keep)]
    h, w = np.asarray(views[0].mask).shape
    rig = sorted(cameras)  # the novel cameras sit between the rig's neighbours, as the relight stage places them
    poses = [cameras[c].cam_from_world for c in rig]
    novel = []
    for a, b in novel_camera_pairs(poses, novel_count):
        K, P = interpolate_camera(cameras[rig[a]].K, poses[a], cameras[rig[b]].K, poses[b], 0.5)
        novel.append((K, P, cameras[rig[a]].height, cameras[rig[a]].width))
    held = [(cameras[c].K, cameras[c].cam_from_world, cameras[c].height, cameras[c].width) for c in sorted(heldout)]

    def row(name: str, vertices: np.ndarray, seconds: float, **settings) -> dict:
        metrics = mesh_metrics(vertices, sdf_f, truth_v, truth_f)
        scene = mesh_scene(vertices, sdf_f)
        return {"row": name, **settings, "seconds": seconds, "chamfer_mm": float(metrics["chamfer_mm"]),
                "fscore_1mm": float(metrics["fscore_1mm"]),
                "normal_consistency": float(metrics["normal_consistency"]),
                "novel_outline_rms": outline_rms(truth_scene, scene, novel),
                "heldout_outline_rms": outline_rms(truth_scene, scene, held),
                "mean_move_mm": float(np.linalg.norm(vertices - sdf_v, axis=1).mean() * 1e3)}

    base = GeometryConfig().silhouette
    rows = [row("SDF mesh", sdf_v, 0.0)]
    for s in smoothing:
        for bias in biases:
            cfg = dataclasses.replace(base, outline_bias_px=bias, smoothing=s)
            start = time.perf_counter()
            refined, _ = refine_silhouettes(sdf_v, sdf_f, measured, cfg)
            rows.append(row("measured", refined, time.perf_counter() - start, outline_bias_px=bias, smoothing=s))
    start = time.perf_counter()
    refined, _ = refine_silhouettes(sdf_v, sdf_f, oracle, dataclasses.replace(base, outline_bias_px=0.0))
    rows.append(row("true coverage (oracle)", refined, time.perf_counter() - start, outline_bias_px=0.0,
                    smoothing=base.smoothing))
    bias = outline_disagreement(sdf_v, sdf_f, measured, oracle, base)
    return {"action": action, "heldout": sorted(heldout), "pixels": [h, w], "novel_views": len(novel),
            "outline_bias": {"profiles": int(bias.size), "mean_px": float(bias.mean()) if bias.size else float("nan"),
                             "median_px": float(np.median(bias)) if bias.size else float("nan")}, "rows": rows}


def plot(path: Path, report: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=100)
    for action in report["actions"]:
        for s in report["smoothing"]:
            rows = [r for r in action["rows"] if r["row"] == "measured" and r["smoothing"] == s]
            for ax, key in zip(axes, ("chamfer_mm", "novel_outline_rms")):
                ax.plot([r["outline_bias_px"] for r in rows], [r[key] for r in rows], "o-",
                        label=f"{action['action']}, smoothing {s}")
        for ax, key in zip(axes, ("chamfer_mm", "novel_outline_rms")):
            first = action["rows"][0][key]
            ax.axhline(first, ls=":", color="grey")
            ax.annotate(f"{action['action']} SDF mesh", (0, first), fontsize=7, color="grey")
    axes[0].set_ylabel("Chamfer (mm)")
    axes[1].set_ylabel("novel views: coverage RMS on the outline")
    for ax in axes:
        ax.set_xlabel("outline_bias_px")
        ax.legend(fontsize=7)
    fig.suptitle("Silhouette refinement" + (" (quick run, not measurements)" if report["quick"] else ""))
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def markdown(report: dict) -> str:
    lines = ["# Silhouette refinement" + (" - quick run, not measurements" if report["quick"] else ""), ""]
    for action in report["actions"]:
        b = action["outline_bias"]
        lines += [f"## {action['action']} ({action['pixels'][1]} x {action['pixels'][0]} px; held out "
                  f"{', '.join(action['heldout'])}; {action['novel_views']} novel views)", "",
                  f"Measured outline against the true coverage's on {b['profiles']} contour profiles: "
                  f"{b['mean_px']:+.3f} px mean, {b['median_px']:+.3f} px median.", "",
                  "| row | outline_bias_px | smoothing | s | Chamfer mm | F@1mm | normal consistency | "
                  "novel outline RMS | held-out outline RMS | mean move mm |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in action["rows"]:
            lines.append(f"| {r['row']} | {r.get('outline_bias_px', '')} | {r.get('smoothing', '')} | "
                         f"{r['seconds']:.1f} | {r['chamfer_mm']:.3f} | {100 * r['fscore_1mm']:.1f}% | "
                         f"{r['normal_consistency']:.4f} | {r['novel_outline_rms']:.4f} | "
                         f"{r['heldout_outline_rms']:.4f} | {r['mean_move_mm']:.2f} |")
        lines.append("")
    return "\n".join(lines)


def main() -> int:
    parser = release_parser(__doc__, actions="A0000,A0001")
    parser.add_argument("--biases", help="outline_bias_px values, comma-separated (default 0,0.06,0.1)")
    parser.add_argument("--smoothing", help="smoothing rounds, comma-separated (default 8,32)")
    parser.add_argument("--novel", type=int, default=8, help="novel views per action (default 8)")
    args = parse_release_args(parser)
    capture, release = Path(args.capture), Path(args.release)
    go, truth = check_inputs("bench_silhouette", release, capture, need_truth=True)
    if not go:
        return 0
    try:
        biases = [float(x) for x in (args.biases or ("0.06" if args.quick else "0,0.06,0.1")).split(",") if x.strip()]
        smoothing = [int(x) for x in (args.smoothing or ("32" if args.quick else "8,32")).split(",") if x.strip()]
    except ValueError as exc:
        parser.error(str(exc))
    from manifests import open_release

    actions = [a for a in args.actions.split(",") if a.strip()] or sorted(open_release(release).action_ids())
    actions = [a for a in actions if (truth / a / "mesh.ply").exists()] if not args.quick else actions[:1]
    novel = 2 if args.quick else args.novel
    report = {"quick": args.quick, "biases": biases, "smoothing": smoothing,
              "actions": [measure_action(capture, release, a, biases, smoothing, novel) for a in actions]}
    write_report(args.out, "bench_silhouette", report, markdown(report), lambda path: plot(path, report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
