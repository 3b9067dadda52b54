"""Mesh error split by region of the truth: which parts of a reconstruction are wrong, by how much, and which way.

:func:`region_errors` samples both meshes uniformly by area and gives, per region of the truth's faces, the
truth -> prediction distances of the truth's samples there, the prediction -> truth distances of the prediction's
samples whose closest truth sample lies there, and the signed offset of the prediction along the truth (how far
it lies outside the truth: the signed distance of the truth's samples to the closed prediction, negated). The
regions of a simulated MakeHuman action come from :func:`truth_face_regions`: the skirt's parts
(:data:`synthetic.garments.SKIRT_PARTS`), the body inside the skirt, and the rest of the body in height bands.

    python -m evaluation.mesh_regions --capture CAPTURE --mesh RELEASE/actions/A0000/mesh/mesh.ply [--action A0000]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from stages.numerics.meshmetrics import MeshCamera, cameras_seeing
from stages.numerics.mesh import _check_mesh, face_normals

HEIGHT_BANDS = (("feet", 0.0, 0.06), ("legs", 0.06, 0.47), ("trunk_and_arms", 0.47, 0.84),
                ("head_and_neck", 0.84, 1.0001))
"""Body regions by a face centroid's height above the truth's lowest point, as a fraction of its height: (name,
from, to). On the MakeHuman body in the A-pose the crotch is at about 47% and the chin at about 85%."""


def _sample(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform over the area (n, 3) float64 and the face each lies on (n,)."""
    _, area = face_normals(vertices, faces)
    rng = np.random.default_rng(seed)
    face = rng.choice(len(faces), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)
    return np.einsum("nk,nkd->nd", bary, vertices.astype(np.float64)[faces[face]]), face


def _scene(vertices: np.ndarray, faces: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    return scene


def region_errors(pred_v: np.ndarray, pred_f: np.ndarray, gt_v: np.ndarray, gt_f: np.ndarray,
                  face_region: np.ndarray, names: Sequence[str], n_samples: int = 200_000, seed: int = 0,
                  cameras: Sequence[MeshCamera] | None = None) -> dict[str, dict[str, float]]:
    """Per region of the truth's faces, how far the prediction is from it (millimetres).

    Args:
        pred_v, pred_f: the prediction (V, 3) metres, (F, 3) int; closed for the signed offset to mean anything.
        gt_v, gt_f: the truth. face_region: (len(gt_f),) int index into ``names`` per truth face.
        n_samples: points sampled on each mesh. seed: of the sampling.
        cameras: when given, each region also reports the share of its area a camera sees
            (:func:`stages.numerics.meshmetrics.cameras_seeing` with the truth as occluder) and its truth ->
            prediction mean over the seen part only.

    Returns:
        name -> ``gt_area_share`` and ``pred_area_share`` (of each mesh's area), ``gt_to_pred_mean_mm``,
        ``gt_to_pred_median_mm``, ``gt_to_pred_p90_mm``, ``gt_within_1mm`` (share), ``pred_to_gt_mean_mm``,
        ``pred_to_gt_median_mm``, ``pred_within_1mm``, ``offset_median_mm`` (median over the region's truth
        samples of how far the prediction lies outside the truth; negative: inside), and each region's
        share of the plain Chamfer's two means (``gt_to_pred_contribution_mm``, ``pred_to_gt_contribution_mm``:
        they sum over the regions to the whole means); with cameras ``seen_share`` and ``gt_to_pred_seen_mean_mm``.
        Regions without truth samples are left out.

    Raises:
        ValueError: bad meshes, or ``face_region`` not one index in range per truth face.
    """
    from scipy.spatial import cKDTree
    import open3d as o3d

    pred_v, pred_f = _check_mesh(pred_v, pred_f)
    gt_v, gt_f = _check_mesh(gt_v, gt_f)
    face_region = np.asarray(face_region)
    if face_region.shape != (len(gt_f),) or (face_region < 0).any() or (face_region >= len(names)).any():
        raise ValueError(f"face_region must hold one index into the {len(names)} names per truth face "
                         f"({len(gt_f)}), got shape {face_region.shape}")
    shift = gt_v.astype(np.float64).mean(axis=0)  # Embree works in float32: coordinates near the origin
    gt_pts, gt_face = _sample(gt_v, gt_f, int(n_samples), seed)
    pred_pts, _ = _sample(pred_v, pred_f, int(n_samples), seed + 1)
    pred_scene = _scene(pred_v - shift, pred_f)
    query = o3d.core.Tensor(np.ascontiguousarray(gt_pts - shift, np.float32))
    signed = pred_scene.compute_signed_distance(query).numpy().astype(np.float64)
    d_gp = np.abs(signed)
    closest = _scene(gt_v - shift, gt_f).compute_closest_points(
        o3d.core.Tensor(np.ascontiguousarray(pred_pts - shift, np.float32)))["points"].numpy()
    d_pg = np.linalg.norm(closest.astype(np.float64) + shift - pred_pts, axis=1)
    gt_region = face_region[gt_face]
    pred_region = gt_region[cKDTree(gt_pts).query(pred_pts, k=1)[1]]
    seen = None
    if cameras is not None:
        seen = cameras_seeing(gt_v, gt_f, gt_pts, cameras) > 0
    mm, n = 1000.0, float(n_samples)
    out: dict[str, dict[str, float]] = {}
    for index, name in enumerate(names):
        g, p = gt_region == index, pred_region == index
        if not g.any():
            continue
        record = {"gt_area_share": float(g.mean()), "pred_area_share": float(p.mean()),
                  "gt_to_pred_mean_mm": mm * float(d_gp[g].mean()),
                  "gt_to_pred_median_mm": mm * float(np.median(d_gp[g])),
                  "gt_to_pred_p90_mm": mm * float(np.quantile(d_gp[g], 0.9)),
                  "gt_within_1mm": float((d_gp[g] <= 0.001).mean()),
                  "offset_median_mm": -mm * float(np.median(signed[g])),
                  "gt_to_pred_contribution_mm": mm * float(d_gp[g].sum()) / n,
                  "pred_to_gt_contribution_mm": mm * float(d_pg[p].sum()) / n}
        if p.any():
            record |= {"pred_to_gt_mean_mm": mm * float(d_pg[p].mean()),
                       "pred_to_gt_median_mm": mm * float(np.median(d_pg[p])),
                       "pred_within_1mm": float((d_pg[p] <= 0.001).mean())}
        if seen is not None:
            record["seen_share"] = float(seen[g].mean())
            if (g & seen).any():
                record["gt_to_pred_seen_mean_mm"] = mm * float(d_gp[g & seen].mean())
        out[name] = record
    return out


def truth_face_regions(gt_v: np.ndarray, gt_f: np.ndarray, garment_triangles: int = 0,
                       skirt_angles: int | None = None) -> tuple[np.ndarray, list[str]]:
    """Regions of a simulated MakeHuman action's truth faces: (len(gt_f),) int and their names.

    The body's faces go to :data:`HEIGHT_BANDS` by centroid height. With ``garment_triangles`` > 0 the last that
    many faces (and vertices 2 x rings x angles from the end) are the skirt of :func:`synthetic.garments.skirt_shell`
    (its parts, :data:`synthetic.garments.SKIRT_PARTS`), and a body face whose centroid lies within the skirt's
    height range and closer to its axis than the skirt's outer surface at the nearest ring and angle is
    ``body_under_skirt`` (approximate for a posed, skinned skirt).
    """
    from synthetic.garments import SKIRT_PARTS, skirt_triangle_parts

    gt_v = np.asarray(gt_v, np.float64)
    gt_f = np.asarray(gt_f, np.int64)
    centroid = gt_v[gt_f].mean(axis=1)
    low, high = gt_v[:, 1].min(), gt_v[:, 1].max()
    fraction = (centroid[:, 1] - low) / max(high - low, 1e-9)
    names = [name for name, _, _ in HEIGHT_BANDS]
    region = np.zeros(len(gt_f), np.int64)
    for index, (_, start, stop) in enumerate(HEIGHT_BANDS):
        region[(fraction >= start) & (fraction < stop)] = index
    if garment_triangles:
        from synthetic.subject import SKIRT_ANGLES

        angles = int(skirt_angles or SKIRT_ANGLES)
        parts = skirt_triangle_parts(garment_triangles, angles)
        rings = garment_triangles // (4 * angles)
        body_faces = len(gt_f) - garment_triangles
        names += list(SKIRT_PARTS) + ["body_under_skirt"]
        region[body_faces:] = len(HEIGHT_BANDS) + parts
        outer = gt_v[len(gt_v) - 2 * rings * angles:][:rings * angles].reshape(rings, angles, 3)
        axis = outer[0].mean(axis=0)[[0, 2]]
        radius = np.linalg.norm(outer[..., [0, 2]] - axis, axis=-1)  # (rings, angles)
        ring_y = outer[:, :, 1].mean(axis=1)
        body = centroid[:body_faces]
        offset = body[:, [0, 2]] - axis
        angle = np.arctan2(offset[:, 0], offset[:, 1]) % (2 * np.pi)
        a = np.round(angle / (2 * np.pi) * angles).astype(np.int64) % angles
        r = np.abs(body[:, 1][:, None] - ring_y[None, :]).argmin(axis=1)
        inside = ((np.linalg.norm(offset, axis=1) < radius[r, a]) & (body[:, 1] <= ring_y.max())
                  & (body[:, 1] >= ring_y.min()))
        region[:body_faces][inside] = len(names) - 1
    return region, names


def _print_table(errors: dict[str, dict[str, float]]) -> None:
    print(f"{'region':18s} {'area':>6s} {'seen':>5s} | {'gt->pred':>8s} {'median':>6s} {'p90':>6s} {'<=1mm':>5s} "
          f"{'offset':>6s} | {'pred':>5s} {'pred->gt':>8s} {'<=1mm':>5s} | {'share of the two means (mm)':s}")
    for name, r in errors.items():
        print(f"{name:18s} {100 * r['gt_area_share']:5.1f}% {100 * r.get('seen_share', float('nan')):4.0f}% | "
              f"{r['gt_to_pred_mean_mm']:8.2f} {r['gt_to_pred_median_mm']:6.2f} {r['gt_to_pred_p90_mm']:6.2f} "
              f"{r['gt_within_1mm']:5.2f} {r['offset_median_mm']:+6.2f} | {100 * r['pred_area_share']:4.1f}% "
              f"{r.get('pred_to_gt_mean_mm', float('nan')):8.2f} {r.get('pred_within_1mm', float('nan')):5.2f} | "
              f"{r['gt_to_pred_contribution_mm']:5.2f} + {r['pred_to_gt_contribution_mm']:5.2f}")
    print("(area: the truth's; seen: share of it a true camera sees; offset: median distance the prediction lies "
          "outside the truth, mm; pred: the prediction's area whose closest truth is in the region)")


def main(argv: Sequence[str] | None = None) -> int:
    from evaluation.release import true_mesh_cameras
    from pipeline.codecs.mesh import read_ply

    parser = argparse.ArgumentParser(prog="python -m evaluation.mesh_regions", description=__doc__.split("\n")[0])
    parser.add_argument("--capture", required=True, type=Path, help="simulated capture (with ground_truth/)")
    parser.add_argument("--mesh", required=True, type=Path, help="the reconstructed mesh (PLY)")
    parser.add_argument("--action", default="A0000")
    parser.add_argument("--samples", type=int, default=200_000)
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    truth_dir = args.capture / "ground_truth"
    truth = json.loads((truth_dir / args.action / "truth.json").read_text())
    gt_v, gt_f = read_ply(truth_dir / args.action / "mesh.ply")
    pred_v, pred_f = read_ply(args.mesh)
    garment = (truth.get("subject") or {}).get("garment") or {}
    region, names = truth_face_regions(gt_v, gt_f, int(garment.get("triangles", 0)))
    cameras = true_mesh_cameras(truth_dir, truth["session_id"])
    errors = region_errors(pred_v, pred_f, gt_v, gt_f, region, names, args.samples, cameras=cameras)
    _print_table(errors)
    if args.json is not None:
        args.json.write_text(json.dumps(errors, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
