"""The third SDF pass: its decision's share over every view against the samples it could be read on, and what the
pass does to the mesh, per subject.

For each action (of a release, or with ``--panel`` the A0000 of every subject of ``bench_subjects``' panel), the
geometry stage's own function (:func:`stages.numerics.sdf_mesh.sdf_mesh`, on the views as the stage loads them,
:func:`stages.geometry.load_sdf_views`, with the release's geometry config) runs with the third pass forced
(``third_pass_turned_share`` 0; a config without a third pass gets the stage default's steps) and gives its meshes
(``on_mesh``). Every view is then de-occluded against the first and the second mesh
(:func:`stages.numerics.sdf_mesh.deoccluded_sdf_views`) and the share of the valid pixels whose normal turns by over
5 degrees between the two (:func:`stages.numerics.sdf_mesh.turned_share`, the decision's figure) is read over every
pixel of every view, on every fourth view, and on the pixel lattice the stage reads
(:func:`stages.numerics.sdf_mesh.on_pixel_lattice`). The second and third meshes (the SDF's own, before the
silhouette refinement) are scored against the truth (:func:`stages.numerics.meshmetrics.mesh_metrics`: Chamfer,
comparable Chamfer, F-score at 1 mm). One row per action, sorted by the share over every view, beside the stage's
bound (:attr:`stages.numerics.sdf_mesh.SDFMeshConfig.third_pass_turned_share`): the decision is worth its time
where the third mesh beats the second by more than an SDF seed's spread (0.1-0.2 mm of Chamfer).

``python bench/bench_third_pass.py --out bench/out [--capture C --release R] [--actions A0000] [--panel DIR]
[--threads 1] [--quick]`` writes OUT/bench_third_pass.json and .md; defaults runs/default (``make dataset``), every
action. ``--panel DIR``: the subjects under ``DIR/subjects/`` (``bench_subjects.py --out DIR``), each folder's
``capture/`` and ``release/``. About 4 minutes an action of the default capture on one thread. ``--quick`` (the
tests' mode): the tiny run of ``bench/_quick.py`` with a third pass of 20 steps; the numbers are not measurements.
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import write_report  # noqa: E402
from _release import parse_release_args, release_config, release_parser, store_artifacts  # noqa: E402

QUICK_THIRD_PASS_ITERATIONS = 20
"""Steps of the forced third pass in ``--quick`` mode (the test preset's schedule has none)."""
FORMER_STRIDE = 4
"""The decision's former sample: every this-many-th view."""
MESH_FIGURES = ("chamfer_mm", "comparable_chamfer_mm", "fscore_1mm")


def geometry_config(release: Path, quick: bool):
    """The release's geometry config (its ``config.yaml``) with the third pass forced: bound 0, and where the
    config has no third pass the stage default's steps (``--quick``: :data:`QUICK_THIRD_PASS_ITERATIONS`)."""
    from stages.geometry import GeometryConfig

    cfg = release_config(release, "geometry", GeometryConfig)
    steps = (QUICK_THIRD_PASS_ITERATIONS if quick else cfg.third_pass_iterations or
             GeometryConfig().third_pass_iterations)
    return dataclasses.replace(cfg, third_pass_turned_share=0.0, third_pass_iterations=steps)


def decision_shares(views: list, first: tuple, second: tuple, cfg) -> dict[str, float]:
    """The share of valid pixels whose normal turns by over the decision's angle between the views de-occluded
    against the ``first`` and the ``second`` mesh ((vertices, faces) each): over every view, every
    :data:`FORMER_STRIDE`-th view, and on the stage's pixel lattice."""
    from stages.numerics.sdf_mesh import (DECISION_PIXEL_STEP, deoccluded_sdf_views, on_pixel_lattice,
                                          turned_share)

    before, _ = deoccluded_sdf_views(views, *first, cfg.deocclude_directions, cfg.deocclude_min_visible)
    after, _ = deoccluded_sdf_views(views, *second, cfg.deocclude_directions, cfg.deocclude_min_visible)
    return {"every_view": turned_share(before, after),
            "every_fourth_view": turned_share(before[::FORMER_STRIDE], after[::FORMER_STRIDE]),
            "pixel_lattice": turned_share(on_pixel_lattice(before, DECISION_PIXEL_STEP),
                                          on_pixel_lattice(after, DECISION_PIXEL_STEP))}


def measure(name: str, capture: Path, release: Path, action: str, quick: bool) -> dict:
    """One action's row: the decision's shares, both meshes' figures and the seconds."""
    from evaluation.release import true_mesh_cameras
    from pipeline.codecs.mesh import read_ply
    from stages.geometry import load_sdf_views
    from stages.numerics.meshmetrics import mesh_metrics
    from stages.numerics.sdf_mesh import sdf_mesh

    cfg = geometry_config(release, quick)
    art = store_artifacts(release, action, ("decode", "photometric"), ("plates",))
    ids, views = load_sdf_views(art, cfg.min_alpha)
    meshes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    tick = time.process_time()
    fitted = sdf_mesh(views, cfg, label=f"{name} {action}", on_mesh=lambda i, v, f: meshes.__setitem__(i, (v, f)))
    passes_s = time.process_time() - tick
    if sorted(meshes) != [1, 2, 3]:
        raise RuntimeError(f"{name} {action}: the passes gave meshes {sorted(meshes)}, not 1, 2 and 3")
    tick = time.process_time()
    shares = decision_shares(views, meshes[1], meshes[2], cfg)
    shares_s = time.process_time() - tick
    truth = capture / "ground_truth" / action
    session = json.loads((truth / "truth.json").read_text())["session_id"]
    cameras = true_mesh_cameras(capture / "ground_truth", session)
    gv, gf = read_ply(truth / "mesh.ply")
    scores = {}
    for index, label in ((2, "two_passes"), (3, "three_passes")):
        m = mesh_metrics(*meshes[index], gv, gf, cameras=cameras)
        scores[label] = {k: float(m[k]) for k in MESH_FIGURES if k in m}
    return {"subject": name, "action": action, "views": len(ids), "shares": shares, "meshes": scores,
            "third_pass_iterations": cfg.third_pass_iterations, "passes_cpu_s": round(passes_s, 1),
            "shares_cpu_s": round(shares_s, 1), "stage_turned_share": fitted.third_pass["turned_share"]}


def markdown(report: dict) -> str:
    bound = report["bound"]
    lines = ["# The third SDF pass: its decision and what it does", "",
             f"Share of valid pixels whose de-occluded normal turns by over 5 deg between the first and the second "
             f"mesh (the stage's bound: {100 * bound:.1f}% on the pixel lattice); the SDF's own meshes (before the "
             f"silhouette refinement) after two and three passes, against the truth."
             + (" Quick mode: not measurements." if report["quick"] else ""), "",
             "| subject | action | every view | every 4th view | pixel lattice | decides | Chamfer (comparable) mm, "
             "2 -> 3 passes | F-score @ 1 mm | CPU s (passes, shares) |",
             "|---|---|---:|---:|---:|---|---|---|---:|"]
    for r in sorted(report["rows"], key=lambda r: r["shares"]["every_view"]):
        s, two, three = r["shares"], r["meshes"]["two_passes"], r["meshes"]["three_passes"]

        def mm(m: dict) -> str:
            return f"{m['chamfer_mm']:.2f} ({m.get('comparable_chamfer_mm', float('nan')):.2f})"

        lines.append(f"| {r['subject']} | {r['action']} | {100 * s['every_view']:.1f}% | "
                     f"{100 * s['every_fourth_view']:.1f}% | {100 * s['pixel_lattice']:.1f}% | "
                     f"{'three' if s['pixel_lattice'] > bound else 'two'} | {mm(two)} -> {mm(three)} | "
                     f"{two['fscore_1mm']:.3f} -> {three['fscore_1mm']:.3f} | "
                     f"{r['passes_cpu_s']:.0f}, {r['shares_cpu_s']:.0f} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = release_parser(__doc__, actions="", threads=1)
    parser.add_argument("--panel", help="bench_subjects' --out folder: the A0000 of each subject under subjects/")
    args = parse_release_args(parser)
    os.environ.setdefault("ULTRASTAGE_NUMERIC_THREADS", str(args.threads))
    import torch

    from stages.numerics.sdf_mesh import SDFMeshConfig

    torch.set_num_threads(max(1, args.threads))
    if args.panel:
        subjects = Path(args.panel) / "subjects"
        folders = [p for p in sorted(subjects.iterdir()) if (p / "release" / "config.yaml").exists()
                   and (p / "capture" / "ground_truth" / "A0000" / "mesh.ply").exists()] if subjects.is_dir() else []
        if not folders:
            print(f"bench_third_pass: no subject with a release and ground truth under {subjects}; skipped")
            return 0
        jobs = [(p.name, p / "capture", p / "release", "A0000") for p in folders]
    else:
        capture, release = Path(args.capture), Path(args.release)
        if not (release / "config.yaml").exists() or not (capture / "ground_truth").is_dir():
            print(f"bench_third_pass: needs {release} and {capture} with ground truth (make dataset first); skipped")
            return 0
        actions = [a for a in args.actions.split(",") if a] or sorted(
            p.name for p in (capture / "ground_truth").iterdir() if (p / "mesh.ply").exists())
        jobs = [(release.parent.name, capture, release, a) for a in actions]
    rows = []
    for name, capture, release, action in jobs:
        rows.append(measure(name, capture, release, action, args.quick))
        r = rows[-1]
        print(f"{name} {action}: share {100 * r['shares']['every_view']:.2f}% (lattice "
              f"{100 * r['shares']['pixel_lattice']:.2f}%), Chamfer {r['meshes']['two_passes']['chamfer_mm']:.3f} -> "
              f"{r['meshes']['three_passes']['chamfer_mm']:.3f} mm", flush=True)
    report = {"quick": args.quick, "bound": SDFMeshConfig().third_pass_turned_share, "rows": rows}
    write_report(args.out, "bench_third_pass", report, markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
