"""Mesh accuracy metrics: Chamfer distance, normal consistency and F-score between two meshes.

Pure functions, arrays in and arrays out; metres in, millimetres in the Chamfer outputs.

Both meshes are sampled uniformly by area (:func:`sample_surface`). Distances from one mesh's samples to
the other mesh are by default **point-to-surface** (the exact closest point on the other mesh's
triangles, open3d ``RaycastingScene``): point-to-sample distances (``method="samples"``, scipy cKDTree,
the common implementation) add the other mesh's sampling spacing to every distance, about 1 mm with
200k samples on a human body, which is the size of the 1 mm F-score threshold itself.
"""
from __future__ import annotations

import numpy as np

from stages.numerics.mesh import _check_mesh, face_normals

__all__ = ["sample_surface", "mesh_metrics"]


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int,
                   seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniformly distributed over the mesh's area, with their faces' unit normals.

    Args:
        vertices: (V, 3); faces: (F, 3) int with non-zero total area.
        n: number of samples; seed: for ``numpy.random.default_rng``.

    Returns:
        points (n, 3) float64, normals (n, 3) float64 unit.
    """
    v, f = _check_mesh(vertices, faces)
    if int(n) < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    unit, area = face_normals(v, f)
    total = area.sum()
    if not total > 0:
        raise ValueError("the mesh has no area to sample")
    rng = np.random.default_rng(seed)
    face = rng.choice(len(f), size=int(n), p=area / total)
    r1, r2 = rng.random(int(n)), rng.random(int(n))
    s = np.sqrt(r1)  # uniform over the triangle: (1 - s, s (1 - r2), s r2)
    bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)
    tri = v.astype(np.float64)[f[face]]
    return np.einsum("nk,nkd->nd", bary, tri), unit[face]


def _closest_on_surface(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray):
    """Distances (n,) and unit normals (n, 3) of the closest points on the mesh's triangles."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    # Embree works in float32: callers pass coordinates relative to the mesh's centre (small values).
    closest = scene.compute_closest_points(o3d.core.Tensor(np.ascontiguousarray(points, np.float32)))
    dist = np.linalg.norm(closest["points"].numpy().astype(np.float64) - points, axis=1)
    prim = closest["primitive_ids"].numpy().astype(np.int64)
    return dist, face_normals(vertices, faces)[0][prim]


def _closest_sample(points_ref: np.ndarray, normals_ref: np.ndarray, points: np.ndarray, workers: int):
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(points_ref).query(points, k=1, workers=workers)
    return dist, normals_ref[idx]


def mesh_metrics(pred_v: np.ndarray, pred_f: np.ndarray, gt_v: np.ndarray, gt_f: np.ndarray,
                 n_samples: int = 200_000, thresholds_m: tuple[float, ...] = (0.001, 0.005),
                 seed: int = 0, method: str = "surface", workers: int = 1) -> dict:
    """Chamfer distance, normal consistency and F-scores of a predicted mesh against ground truth.

    Args:
        pred_v, pred_f: predicted mesh (V, 3) metres, (F, 3) int; gt_v, gt_f: ground-truth mesh.
        n_samples: area-uniform samples drawn on each mesh.
        thresholds_m: F-score distance thresholds (metres); keys are named in whole millimetres
            (``fscore_1mm``) or, below 1 mm or fractional, with a ``p`` (``fscore_0p5mm``).
        seed: sampling seed (pred uses ``seed``, gt ``seed + 1``).
        method: ``"surface"`` (closest point on the other mesh, exact) or ``"samples"`` (closest of the
            other mesh's samples, scipy cKDTree: biased up by the sample spacing).
        workers: cKDTree query threads for ``"samples"``.

    Returns:
        ``chamfer_mm`` (mean of the two directions' mean distances), ``chamfer_pred_to_gt_mm``
        (accuracy), ``chamfer_gt_to_pred_mm`` (completeness), ``normal_consistency`` (mean ``|cos|``
        between each sample's normal and its closest point's, averaged over both directions; 1 =
        perfect), and per threshold ``precision_*`` (pred samples within it of gt), ``recall_*`` (gt
        samples within it of pred), ``fscore_*`` (their harmonic mean, 0 when both are 0);
        ``mesh_faces`` (of pred), ``gt_faces``, ``n_samples``, ``method``.
    """
    pv, pf = _check_mesh(pred_v, pred_f)
    gv, gf = _check_mesh(gt_v, gt_f)
    if method not in ("surface", "samples"):
        raise ValueError(f"method must be 'surface' or 'samples', got {method!r}")
    if any(not t > 0 for t in thresholds_m):
        raise ValueError(f"thresholds_m must be > 0, got {thresholds_m}")
    pred_pts, pred_nrm = sample_surface(pv, pf, n_samples, seed)
    gt_pts, gt_nrm = sample_surface(gv, gf, n_samples, seed + 1)
    if method == "surface":
        shift = gv.astype(np.float64).mean(axis=0)  # keep float32 Embree coordinates small
        d_pg, n_pg = _closest_on_surface(gv - shift, gf, pred_pts - shift)
        d_gp, n_gp = _closest_on_surface(pv - shift, pf, gt_pts - shift)
    else:
        d_pg, n_pg = _closest_sample(gt_pts, gt_nrm, pred_pts, workers)
        d_gp, n_gp = _closest_sample(pred_pts, pred_nrm, gt_pts, workers)
    nc_pg = np.abs(np.einsum("nd,nd->n", pred_nrm, n_pg)).mean()
    nc_gp = np.abs(np.einsum("nd,nd->n", gt_nrm, n_gp)).mean()
    out = {
        "chamfer_mm": float(500.0 * (d_pg.mean() + d_gp.mean())),
        "chamfer_pred_to_gt_mm": float(1000.0 * d_pg.mean()),
        "chamfer_gt_to_pred_mm": float(1000.0 * d_gp.mean()),
        "normal_consistency": float(0.5 * (nc_pg + nc_gp)),
    }
    for t in thresholds_m:
        mm = 1000.0 * t
        name = f"{int(round(mm))}mm" if abs(mm - round(mm)) < 1e-9 and mm >= 1 else f"{mm:g}mm".replace(".", "p")
        precision = float((d_pg <= t).mean())
        recall = float((d_gp <= t).mean())
        out[f"precision_{name}"] = precision
        out[f"recall_{name}"] = recall
        out[f"fscore_{name}"] = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    out.update(mesh_faces=int(len(pf)), gt_faces=int(len(gf)), n_samples=int(n_samples), method=method)
    return out
