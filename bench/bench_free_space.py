"""Space the views see through: the free-space cue against the truth, and what carving by it does to the SDF.

For each action (of a release, or with ``--panel DIR`` the A0000 of every subject of ``bench_subjects``' panel), the
geometry stage's SDF mesh (``sdf/mesh.ply``, before the silhouette refinement) is put in front of every view
(:mod:`stages.numerics.free_space`): the pixels whose mesh point no other view agrees with on the normal, in
regions of such pixels (:func:`~stages.numerics.free_space.disagreement_pixels`), are the cue that the mesh closes
over space the view sees through (a skirt's cavity). It is read with two sets of normals: the photometric (eq. 1)
maps the geometry stage trains on, and the ``diffuse_normals`` stage's maps with the specular part taken out
(computed after the mesh, from its roughness); at 12 and 20 degrees of agreement, with and without the visibility
test. Against the truth (the true mesh rendered in every view), a flagged pixel is a **cavity** pixel where the
truth lies more than 10 mm beyond our mesh along its ray and a **cut** pixel where it lies within 5 mm (carving
there would cut the true surface).

``--carve-rounds N`` (default 0) also continues the stage's SDF (``sdf/sdf.pt``) for N rounds of ``--carve-steps``
steps at its final sharpness, on the normals de-occluded against its mesh, each round with free depths
(:attr:`stages.numerics.sdf.SDFView.free_depth_m`) ``--beyond`` past the round's mesh on the pixels flagged on the
specular-free normals (20 degrees, no visibility test), and the same rounds without them (each continuation
restarts the optimiser, which costs the mesh by itself: compare the two columns, not the rounds with the stage's
mesh). Every round's mesh is scored against the truth (Chamfer, comparable Chamfer, F-score at 1 mm, the share of
the mesh off the truth where a camera sees through).

``python bench/bench_free_space.py --out bench/out [--capture C --release R] [--actions A0000] [--panel DIR
[--subjects skirt]] [--carve-rounds 2] [--quick]`` writes OUT/bench_free_space.json and .md; on one thread the cue
(both sets of normals at the four settings) takes about 22 CPU s an action of 32 views at 320 x 480, a round of
300 steps 22-31 s. ``--quick`` (the tests' mode): the tiny run of
``bench/_quick.py``, one round of 10 steps; the numbers are not measurements.
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

from _release import (latest_artifact, parse_release_args, release_config, release_parser,  # noqa: E402
                      store_artifacts)
from _report import write_report  # noqa: E402

SETTINGS = ((12.0, None), (20.0, None), (12.0, 0.01), (20.0, 0.01))
"""(agreement angle in degrees, visibility tolerance in metres or None) the cue is read at."""
CARVE_SETTING = (20.0, None)
"""The setting whose flagged pixels (on the specular-free normals) the carve rounds use."""
CAVITY_MM = 10
"""A flagged pixel whose truth lies more than this (millimetres) beyond our mesh along its ray is a cavity pixel."""
CUT_MM = 5
"""A flagged pixel whose truth lies within this (millimetres) of our mesh is a cut pixel."""
MESH_FIGURES = ("chamfer_mm", "comparable_chamfer_mm", "fscore_1mm", "pred_seen_through_area_fraction")


def diffuse_normals(art, ids: list[str], views: list) -> tuple[list, list]:
    """The diffuse_normals stage's maps of the views (``art``: the action's artifacts with that stage's), world
    normals and where they are valid: finite, unit, alpha above 0.5 and valid in the photometric maps."""
    normals, valid = [], []
    for cam_id, view in zip(ids, views):
        m = art.exr("normal_diffuse", cam_id)
        n = np.nan_to_num(np.asarray(m[..., :3], np.float32))
        ok = (np.abs(np.linalg.norm(n, axis=-1) - 1.0) < 0.1) & np.asarray(view.normal_valid, bool)
        if m.shape[-1] > 3:
            ok &= m[..., 3] > 0.5
        normals.append(np.where(ok[..., None], n, 0.0).astype(np.float32))
        valid.append(ok)
    return normals, valid


def mesh_in_views(views: list, vertices: np.ndarray, faces: np.ndarray) -> tuple[list, list]:
    """Per view: the mesh's distance along each pixel's ray (0 where it misses) and its camera depth."""
    from stages.numerics.raycast import camera_rays, mesh_scene, render_mesh

    scene = mesh_scene(vertices, faces)
    mesh_t, mesh_depth = [], []
    for v in views:
        H, W = np.shape(v.normal_valid)
        render = render_mesh(None, None, v.K, v.cam_from_world, H, W, scene=scene)
        z_per_t = camera_rays(v.K, v.cam_from_world, H, W)[2].reshape(H, W)
        mesh_t.append(np.where(render["hit"], render["depth_m"] / z_per_t, 0.0))
        mesh_depth.append(render["depth_m"])
    return mesh_t, mesh_depth


def flagged_pixels(normals: list, valid: list, views: list, mesh_t: list, mesh_depth: list, agree_deg: float,
                   visible_tol_m: float | None) -> list[np.ndarray]:
    """Per view (H, W) bool: the free-space cue's pixels."""
    from stages.numerics.free_space import disagreement_pixels, normal_agreement

    counts = normal_agreement(normals, valid, mesh_t, mesh_depth, [v.K for v in views],
                              [v.cam_from_world for v in views], agree_deg=agree_deg, visible_tol_m=visible_tol_m)
    return [disagreement_pixels(agree, seen) for agree, seen in counts]


def cue_rows(sets: dict, views: list, mesh_t: list, mesh_depth: list, truth_offset: list | None) -> list[dict]:
    """One row per set of normals and setting: flagged pixels, their share, cavity and cut pixels."""
    rows = []
    for name, (normals, valid) in sets.items():
        total = int(sum(int(np.sum(v)) for v in valid))
        for agree_deg, tol in SETTINGS:
            flagged = flagged_pixels(normals, valid, views, mesh_t, mesh_depth, agree_deg, tol)
            count = int(sum(int(f.sum()) for f in flagged))
            row = {"normals": name, "agree_deg": agree_deg, "visible_tol_m": tol, "flagged": count,
                   "flagged_share": count / max(total, 1)}
            if truth_offset is not None:
                off = np.concatenate([o[f] for o, f in zip(truth_offset, flagged)]) if count else np.zeros(0)
                row["cavity"] = int((off > CAVITY_MM / 1000).sum())
                row["cut"] = int((np.abs(off) < CUT_MM / 1000).sum())
            rows.append(row)
    return rows


def carve_rounds(cfg, views: list, normals: list, valid: list, field_state: dict, vertices: np.ndarray,
                 faces: np.ndarray, rounds: int, steps: int, beyond_m: float, score) -> dict[str, list]:
    """The SDF continued ``rounds`` times with free depths (``carved``) and without (``plain``): each round's mesh
    figures (``score(vertices, faces)``), flagged pixels and seconds."""
    from stages.numerics.free_space import free_depths
    from stages.numerics.mesh import decimate, extract_mesh, largest_component
    from stages.numerics.sdf import SDFField, train_sdf
    from stages.numerics.sdf_mesh import pass_configs, second_pass_views

    second = pass_configs(cfg)[1] or cfg.sdf
    config = dataclasses.replace(second, iterations=steps, inv_s_start=second.inv_s_end, coarse_to_fine=0.0,
                                 warmup_iterations=min(second.warmup_iterations, steps))
    base_views, _ = second_pass_views(cfg, views, vertices, faces)
    out = {}
    for mode in ("plain", "carved"):
        field_ = SDFField.from_state(field_state)
        mesh = (vertices, faces)
        rows = []
        for r in range(1, rounds + 1):
            tick = time.process_time()
            sdf_views, count = base_views, 0
            if mode == "carved":
                mesh_t, mesh_depth = mesh_in_views(views, *mesh)
                flagged = flagged_pixels(normals, valid, views, mesh_t, mesh_depth, *CARVE_SETTING)
                count = int(sum(int(f.sum()) for f in flagged))
                sdf_views = [dataclasses.replace(v, free_depth_m=free_depths(f, t, beyond_m))
                             for v, f, t in zip(base_views, flagged, mesh_t)]
            result = train_sdf(sdf_views, config, init=field_)
            field_ = result.field
            v, f, _ = extract_mesh(field_.sdf_numpy, np.asarray(result.bounds), cfg.mesh_resolution)
            v, f = largest_component(v, f)
            mesh = decimate(v, f, cfg.face_budget)
            rows.append({"round": r, "flagged": count, "cpu_s": round(time.process_time() - tick, 1),
                         **score(*mesh)})
            print(f"  {mode} round {r}: {count} flagged, {rows[-1]}", flush=True)
        out[mode] = rows
    return out


def measure(name: str, capture: Path, release: Path, action: str, rounds: int, steps: int, beyond_m: float) -> dict:
    """One action's row: the cue's rows per set of normals and setting, and the carve rounds."""
    import torch

    from evaluation.release import true_mesh_cameras
    from pipeline.codecs.mesh import read_ply
    from stages.geometry import GeometryConfig, load_sdf_views
    from stages.numerics.meshmetrics import mesh_metrics

    cfg = release_config(release, "geometry", GeometryConfig)
    work = release.with_name(release.name + ".work")
    art = store_artifacts(release, action, ("decode", "photometric", "diffuse_normals"))
    ids, views = load_sdf_views(art, cfg.min_alpha)
    geometry = latest_artifact(work, "geometry", action)
    vertices, faces = read_ply(geometry / "sdf" / "mesh.ply")
    tick = time.process_time()
    mesh_t, mesh_depth = mesh_in_views(views, vertices, faces)
    truth = capture / "ground_truth" / action
    gv, gf = read_ply(truth / "mesh.ply")
    true_t, _ = mesh_in_views(views, gv, gf)
    offset = [np.where((t > 0) & (g > 0), g - t, np.inf) for t, g in zip(mesh_t, true_t)]
    diffuse = diffuse_normals(art, ids, views)
    sets = {"photometric": ([v.normals_world for v in views], [np.asarray(v.normal_valid, bool) for v in views]),
            "specular-free": diffuse}
    cue = cue_rows(sets, views, mesh_t, mesh_depth, offset)
    cue_s = time.process_time() - tick
    session = json.loads((truth / "truth.json").read_text())["session_id"]
    cameras = true_mesh_cameras(capture / "ground_truth", session)

    def score(v: np.ndarray, f: np.ndarray) -> dict:
        m = mesh_metrics(v, f, gv, gf, cameras=cameras)
        return {k: float(m[k]) for k in MESH_FIGURES if k in m}

    row = {"subject": name, "action": action, "views": len(ids), "cue": cue, "cue_cpu_s": round(cue_s, 1),
           "sdf_mesh": score(vertices, faces)}
    if rounds > 0:
        state = torch.load(geometry / "sdf" / "sdf.pt", weights_only=False)
        row["carve"] = carve_rounds(cfg, views, *diffuse, state, vertices, faces, rounds, steps, beyond_m, score)
        row["carve_steps"], row["carve_beyond_m"] = steps, beyond_m
    return row


def markdown(report: dict) -> str:
    lines = ["# Space the views see through: the free-space cue and carving by it", "",
             "Flagged pixels (no other view agrees with the SDF mesh's point on the normal, in regions of such "
             "pixels) per set of normals and setting; cavity: the truth over 10 mm beyond our mesh on the pixel's "
             "ray, cut: within 5 mm." + (" Quick mode: not measurements." if report["quick"] else ""), "",
             "| subject | action | normals | agree | visibility test | flagged (share) | cavity | cut |",
             "|---|---|---|---:|---|---:|---:|---:|"]
    for r in report["rows"]:
        for c in r["cue"]:
            tol = "none" if c["visible_tol_m"] is None else f"{1000 * c['visible_tol_m']:g} mm"
            lines.append(f"| {r['subject']} | {r['action']} | {c['normals']} | {c['agree_deg']:g} deg | {tol} | "
                         f"{c['flagged']} ({100 * c['flagged_share']:.3f}%) | {c.get('cavity', '')} | "
                         f"{c.get('cut', '')} |")
    carved = [r for r in report["rows"] if "carve" in r]
    if carved:
        lines += ["", "The SDF continued in rounds, without and with free depths (Chamfer and comparable Chamfer mm, "
                  "F-score at 1 mm, mesh seen through %):", "",
                  "| subject | round | flagged | plain | carved |", "|---|---:|---:|---|---|"]

        def fig(m: dict) -> str:
            return (f"{m['chamfer_mm']:.2f} ({m.get('comparable_chamfer_mm', float('nan')):.2f}), "
                    f"{m['fscore_1mm']:.3f}, {100 * m.get('pred_seen_through_area_fraction', float('nan')):.1f}%")

        for r in carved:
            lines.append(f"| {r['subject']} | 0 (the stage's SDF mesh) | | {fig(r['sdf_mesh'])} | |")
            for plain, carve in zip(r["carve"]["plain"], r["carve"]["carved"]):
                lines.append(f"| {r['subject']} | {plain['round']} | {carve['flagged']} | {fig(plain)} | "
                             f"{fig(carve)} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = release_parser(__doc__, actions="", threads=1)
    parser.add_argument("--panel", help="bench_subjects' --out folder: the A0000 of each subject under subjects/")
    parser.add_argument("--subjects", default="", help="with --panel: comma-separated subject names (empty: all)")
    parser.add_argument("--carve-rounds", type=int, default=0, help="carve rounds (0: the cue only)")
    parser.add_argument("--carve-steps", type=int, default=300, help="SDF steps per carve round")
    parser.add_argument("--beyond", type=float, default=0.03, help="free depth past the mesh, metres")
    args = parse_release_args(parser)
    os.environ.setdefault("ULTRASTAGE_NUMERIC_THREADS", str(args.threads))
    import torch

    torch.set_num_threads(max(1, args.threads))
    rounds, steps = (1, 10) if args.quick else (args.carve_rounds, args.carve_steps)
    wanted = {s for s in args.subjects.split(",") if s}

    def ready(capture: Path, release: Path, action: str) -> bool:
        work = release.with_name(release.name + ".work")
        return ((release / "config.yaml").exists() and (capture / "ground_truth" / action / "mesh.ply").exists()
                and (work / "artifacts" / "diffuse_normals").is_dir())

    if args.panel:
        subjects = Path(args.panel) / "subjects"
        jobs = [(p.name, p / "capture", p / "release", "A0000") for p in sorted(subjects.iterdir())
                if (not wanted or p.name in wanted)] if subjects.is_dir() else []
    else:
        capture, release = Path(args.capture), Path(args.release)
        truth = capture / "ground_truth"
        actions = [a for a in args.actions.split(",") if a] or (sorted(
            p.name for p in truth.iterdir() if (p / "mesh.ply").exists()) if truth.is_dir() else [])
        jobs = [(release.parent.name, capture, release, a) for a in actions]
    jobs = [j for j in jobs if ready(*j[1:])]
    if not jobs:
        print("bench_free_space: no action with a release, its diffuse normals and ground truth (make dataset "
              "first); skipped")
        return 0
    rows = []
    for name, capture, release, action in jobs:
        print(f"{name} {action}:", flush=True)
        rows.append(measure(name, capture, release, action, rounds, steps, args.beyond))
        for c in rows[-1]["cue"]:
            print(f"  {c['normals']} {c['agree_deg']:g} deg, visibility {c['visible_tol_m']}: {c['flagged']} flagged, "
                  f"cavity {c.get('cavity')}, cut {c.get('cut')}", flush=True)
    report = {"quick": args.quick, "rows": rows}
    write_report(args.out, "bench_free_space", report, markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
