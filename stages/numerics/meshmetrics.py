"""Mesh accuracy metrics: Chamfer distance, normal consistency and F-score between two meshes.

Pure functions, arrays in and arrays out; metres in, millimetres in the Chamfer outputs.

Both meshes are sampled uniformly by area (:func:`sample_surface`). Distances from one mesh's samples to
the other mesh are by default **point-to-surface** (the exact closest point on the other mesh's
triangles, open3d ``RaycastingScene``): point-to-sample distances (``method="samples"``, scipy cKDTree,
the common implementation) add the other mesh's sampling spacing to every distance, about 1 mm with
200k samples on a human body, which is the size of the 1 mm F-score threshold itself.

**Comparable figures.** Where the truth holds surface the capture cannot show, the plain figures measure the
capture, not the reconstruction: a truth mesh that is open (a bust cut at the neck, a face) leaves an opening
that a closed SDF surface must cap, and parts no camera sees (the inside of a mouth, teeth, the backs of the
eyeballs, soles of feet) cannot be reconstructed by any method that works from the cameras. Given the
cameras, :func:`mesh_metrics` also reports ``comparable_*`` figures, beside the plain ones, on what is
comparable (:func:`comparable_truth`):

- a truth sample counts when at least one camera sees it (in the frame, its line of sight not blocked by the
  truth *closed* with a fan over each opening, :func:`hole_caps`, so the inside of an open mesh seen through
  its opening does not count as seen) and it lies farther than ``boundary_margin_m`` from the truth's open
  boundary (where the SDF must turn to close the surface);
- a prediction sample is left out only when its closest point on the closed truth is not comparable (an
  unseen part or the boundary band: then only within ``comparable_tolerance_m`` of it; a cap: then within
  the opening's radius, the largest distance of its rim from its centroid, as a closing surface may bulge
  out of the flat fan by up to that). A prediction surface farther than that from every truth surface and
  cap (a floater, a bulge) is always counted, with its distance to the truth: the rule leaves out only
  surface that sits where the truth is unknown to the cameras or where a closed surface must close an
  opening, never an error larger than the tolerance (or, at an opening, than the opening's radius).

The areas left out are reported (``comparable_gt_area_fraction``, ``comparable_pred_area_fraction``, the truth's
``gt_unseen_area_fraction`` and ``gt_boundary_area_fraction``), so a figure is never read without its share. Beside
them ``pred_seen_through_area_fraction`` says how much of the prediction lies off the truth in space the cameras
see through (a floater, a surface closing a cavity that some camera looks into): an error the capture itself
contradicts, hence the reconstruction's, not the metric's.
"""
from __future__ import annotations

import numpy as np

from typing import NamedTuple, Sequence

from stages.numerics.mesh import _check_mesh, face_normals


class MeshCamera(NamedTuple):
    """A pinhole camera for the comparable figures (docs/CONTRACTS.md: OpenCV, ``x_cam = R x_world + t``)."""

    K: np.ndarray
    """(3, 3) intrinsics, pixels."""
    cam_from_world: np.ndarray
    """(3, 4) ``[R | t]`` (or (4, 4))."""
    width: int
    """Image width, pixels."""
    height: int
    """Image height, pixels."""

__all__ = ["sample_surface", "mesh_metrics", "boundary_edges", "hole_caps", "cameras_seeing",
           "comparable_truth", "MeshCamera"]


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


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) int64 vertex pairs of the edges that exactly one face uses (the open boundary; an edge of three or
    more faces is non-manifold, not boundary). ``faces``: (F, 3) int."""
    f = np.asarray(faces, np.int64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got shape {f.shape}")
    if len(f) == 0:
        return np.zeros((0, 2), np.int64)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    if edges.min() < 0:
        raise ValueError("faces must hold non-negative vertex indices")
    # one int64 key per edge, ordered as the (a, b) pairs are: a 1-D unique, many times faster than rows'
    stride = int(edges.max()) + 1
    keys, counts = np.unique(edges[:, 0] * stride + edges[:, 1], return_counts=True)
    once = keys[counts == 1]
    return np.stack([once // stride, once % stride], axis=1)


def hole_caps(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fans that close each opening of a mesh: per connected set of boundary edges (:func:`boundary_edges`), one
    new vertex at its vertices' centroid and a triangle (centroid, a, b) per boundary edge (a, b).

    Args:
        vertices: (V, 3); faces: (F, 3) int.

    Returns:
        cap_vertices (C, 3) float64 (C openings; (0, 3) for a closed mesh), cap_faces (K, 3) int64 indexing the
        stacked ``[vertices; cap_vertices]``.
    """
    from scipy import sparse
    from scipy.sparse import csgraph

    v, _ = _check_mesh(vertices, faces)
    edges = boundary_edges(faces)
    if len(edges) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    graph = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(v), len(v)))
    _, label = csgraph.connected_components(graph, directed=False)
    loop_of_edge = label[edges[:, 0]]
    loops, loop_index = np.unique(loop_of_edge, return_inverse=True)
    on_boundary = np.unique(edges)
    which = np.searchsorted(loops, label[on_boundary])
    counts = np.bincount(which, minlength=len(loops)).astype(np.float64)
    centroids = np.stack([np.bincount(which, weights=v[on_boundary, c].astype(np.float64), minlength=len(loops))
                          for c in range(3)], axis=1) / counts[:, None]
    cap_faces = np.column_stack([len(v) + loop_index, edges[:, 0], edges[:, 1]]).astype(np.int64)
    return centroids, cap_faces


def _welded(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with vertices at the same position merged and faces left degenerate by that dropped, so that a
    triangle soup (STL) or seams do not count as open boundary: (V', 3) float64, (F', 3) int64."""
    v, f = _check_mesh(vertices, faces)
    unique, inverse = np.unique(np.asarray(v, np.float64), axis=0, return_inverse=True)
    g = inverse.reshape(-1)[f]
    return unique, g[(g[:, 0] != g[:, 1]) & (g[:, 1] != g[:, 2]) & (g[:, 2] != g[:, 0])]


def _scene(vertices: np.ndarray, faces: np.ndarray, shift: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices - shift, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    return scene


def cameras_seeing(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, cameras: Sequence[MeshCamera],
                   tolerance_m: float = 0.0005) -> np.ndarray:
    """How many cameras see each point on (or near) a mesh: the point projects inside the camera's image, in
    front of it, and the camera's line of sight to it meets the mesh no nearer than ``tolerance_m`` before it.

    Args:
        vertices: (V, 3) metres; faces: (F, 3) int: the occluding mesh (the points' own surface included).
        points: (N, 3) metres. cameras: :class:`MeshCamera` records. tolerance_m: > 0.

    Returns:
        (N,) int64 counts in [0, len(cameras)].
    """
    import open3d as o3d

    v, f = _check_mesh(vertices, faces)
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all():
        raise ValueError(f"points must be finite (N, 3), got shape {p.shape}")
    if not tolerance_m > 0:
        raise ValueError(f"tolerance_m must be > 0, got {tolerance_m}")
    shift = v.astype(np.float64).mean(axis=0)  # float32 Embree coordinates near the origin
    scene = _scene(v, f, shift)
    count = np.zeros(len(p), np.int64)
    for i, cam in enumerate(cameras):
        K = np.asarray(cam.K, np.float64)
        T = np.asarray(cam.cam_from_world, np.float64)[:3]
        if K.shape != (3, 3) or T.shape != (3, 4) or not (np.isfinite(K).all() and np.isfinite(T).all()):
            raise ValueError(f"cameras[{i}]: K must be finite (3, 3) and cam_from_world (3, 4)")
        x_cam = p @ T[:, :3].T + T[:, 3]
        z = x_cam[:, 2]
        zs = np.where(z > 1e-9, z, 1.0)
        u = K[0, 0] * x_cam[:, 0] / zs + K[0, 1] * x_cam[:, 1] / zs + K[0, 2]
        w = K[1, 1] * x_cam[:, 1] / zs + K[1, 2]
        in_frame = (z > 1e-9) & (u >= -0.5) & (u <= cam.width - 0.5) & (w >= -0.5) & (w <= cam.height - 0.5)
        centre = -T[:, :3].T @ T[:, 3]
        to_point = p - centre
        length = np.linalg.norm(to_point, axis=1)
        rays = np.concatenate([np.broadcast_to(centre - shift, p.shape), to_point / np.maximum(length, 1e-12)[:, None]],
                              axis=1)
        hit = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays, np.float32)))["t_hit"].numpy()
        count += in_frame & (hit.astype(np.float64) >= length - tolerance_m)
    return count


def _distance_to_edges(vertices: np.ndarray, edges: np.ndarray, points: np.ndarray, spacing_m: float) -> np.ndarray:
    """(N,) distance from points (N, 3) to the polyline edges (E, 2) of vertices, within ``spacing_m / 2`` (the
    edges are sampled every ``spacing_m`` at most); inf without edges."""
    from scipy.spatial import cKDTree

    if len(edges) == 0:
        return np.full(len(points), np.inf)
    a, b = vertices[edges[:, 0]].astype(np.float64), vertices[edges[:, 1]].astype(np.float64)
    steps = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / spacing_m).astype(np.int64), 1)
    edge = np.repeat(np.arange(len(edges)), steps + 1)
    t = np.concatenate([np.linspace(0.0, 1.0, k + 1) for k in steps])
    samples = a[edge] + t[:, None] * (b[edge] - a[edge])
    return cKDTree(samples).query(points, k=1)[0]


def comparable_truth(gt_v: np.ndarray, gt_f: np.ndarray, points: np.ndarray, cameras: Sequence[MeshCamera],
                     boundary_margin_m: float = 0.01, visibility_tolerance_m: float = 0.0005) -> dict[str, np.ndarray]:
    """Which points of a truth surface are comparable with a reconstruction from ``cameras``.

    A point is comparable when at least one camera sees it (:func:`cameras_seeing`, occluded by the truth
    closed with :func:`hole_caps`, so the inside of an open mesh seen through its opening is not seen) and it
    lies farther than ``boundary_margin_m`` from the truth's open boundary (:func:`boundary_edges`). Vertices
    at the same position are welded first, so a triangle soup's or a seam's edges are not boundary.

    Args:
        gt_v: (V, 3) metres; gt_f: (F, 3) int. points: (N, 3) metres on the truth. cameras: as
            :func:`cameras_seeing`. boundary_margin_m: >= 0 (0: the boundary excludes nothing).

    Returns:
        ``comparable``, ``seen`` and ``near_boundary``: (N,) bool each.
    """
    if not boundary_margin_m >= 0:
        raise ValueError(f"boundary_margin_m must be >= 0, got {boundary_margin_m}")
    v, f = _welded(gt_v, gt_f)
    cap_v, cap_f = hole_caps(v, f)
    closed_v = np.concatenate([v.astype(np.float64), cap_v])
    seen = cameras_seeing(closed_v, np.concatenate([f, cap_f]), points, cameras, visibility_tolerance_m) > 0
    near = np.zeros(len(points), bool)
    if boundary_margin_m > 0:
        edges = boundary_edges(f)
        near = _distance_to_edges(v, edges, np.asarray(points, np.float64), boundary_margin_m / 20) <= boundary_margin_m
    return {"comparable": seen & ~near, "seen": seen, "near_boundary": near}


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
                 seed: int = 0, method: str = "surface", workers: int = 1,
                 cameras: Sequence[MeshCamera] | None = None, boundary_margin_m: float = 0.01,
                 comparable_tolerance_m: float = 0.005, visibility_tolerance_m: float = 0.0005) -> dict:
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
        cameras: the capture's cameras (:class:`MeshCamera`); given, the ``comparable_*`` figures are added
            (module docstring; :func:`comparable_truth`). None: the plain figures only.
        boundary_margin_m: truth within this of its open boundary is not comparable (>= 0).
        comparable_tolerance_m: a prediction sample whose closest point on the closed truth is not comparable
            is left out only within this distance of it (> 0; on a cap: the opening's radius, if larger);
            farther, it always counts.
        visibility_tolerance_m: slack of the line-of-sight test (:func:`cameras_seeing`).

    Returns:
        ``chamfer_mm`` (mean of the two directions' mean distances), ``chamfer_pred_to_gt_mm``
        (accuracy), ``chamfer_gt_to_pred_mm`` (completeness), ``normal_consistency`` (mean ``|cos|``
        between each sample's normal and its closest point's, averaged over both directions; 1 =
        perfect), and per threshold ``precision_*`` (pred samples within it of gt), ``recall_*`` (gt
        samples within it of pred), ``fscore_*`` (their harmonic mean, 0 when both are 0);
        ``mesh_faces`` (of pred), ``gt_faces``, ``n_samples``, ``method``. With ``cameras`` also
        ``comparable_chamfer_mm``, ``comparable_chamfer_pred_to_gt_mm``, ``comparable_chamfer_gt_to_pred_mm``,
        ``comparable_precision_*``, ``comparable_recall_*``, ``comparable_fscore_*`` (the same figures on the
        comparable samples: mean distances and shares over the kept samples of each side, the plain
        distances), ``comparable_gt_area_fraction`` and ``comparable_pred_area_fraction`` (the shares of each
        surface kept), ``gt_unseen_area_fraction`` (truth no camera sees), ``gt_boundary_area_fraction``
        (truth within ``boundary_margin_m`` of its open boundary) and ``pred_far_from_truth_area_fraction``
        (prediction counted although its closest truth is not comparable, for lying farther than
        ``comparable_tolerance_m`` from it) and ``pred_seen_through_area_fraction`` (prediction farther than
        ``comparable_tolerance_m`` from the truth in space a camera sees through: its line of sight to the point
        meets the closed truth beyond it, so the capture shows that surface is not there; a surface closing an
        opening, within the opening's radius, does not count).
        Where one side has no comparable sample (no camera sees the truth), the comparable distances and
        scores are left out and only the area shares are given.

    Raises:
        ValueError: bad meshes or arguments.
    """
    pv, pf = _check_mesh(pred_v, pred_f)
    gv, gf = _check_mesh(gt_v, gt_f)
    if method not in ("surface", "samples"):
        raise ValueError(f"method must be 'surface' or 'samples', got {method!r}")
    if any(not t > 0 for t in thresholds_m):
        raise ValueError(f"thresholds_m must be > 0, got {thresholds_m}")
    if cameras is not None and not (boundary_margin_m >= 0 and comparable_tolerance_m > 0
                                    and visibility_tolerance_m > 0):
        raise ValueError(f"boundary_margin_m must be >= 0 and comparable_tolerance_m, visibility_tolerance_m > 0, "
                         f"got {boundary_margin_m}, {comparable_tolerance_m}, {visibility_tolerance_m}")
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
    out.update(_threshold_scores(d_pg, d_gp, thresholds_m))
    if cameras is not None:
        keep_gt, keep_pred, shares = _comparable_samples(gv, gf, gt_pts, pred_pts, cameras, boundary_margin_m,
                                                         comparable_tolerance_m, visibility_tolerance_m, d_pg)
        if keep_gt.any() and keep_pred.any():
            out.update({
                "comparable_chamfer_mm": float(500.0 * (d_pg[keep_pred].mean() + d_gp[keep_gt].mean())),
                "comparable_chamfer_pred_to_gt_mm": float(1000.0 * d_pg[keep_pred].mean()),
                "comparable_chamfer_gt_to_pred_mm": float(1000.0 * d_gp[keep_gt].mean()),
            })
            out.update({f"comparable_{k}": v for k, v in
                        _threshold_scores(d_pg[keep_pred], d_gp[keep_gt], thresholds_m).items()})
        out.update(shares)
    out.update(mesh_faces=int(len(pf)), gt_faces=int(len(gf)), n_samples=int(n_samples), method=method)
    return out


def _threshold_scores(d_pg: np.ndarray, d_gp: np.ndarray, thresholds_m: tuple[float, ...]) -> dict[str, float]:
    """``precision_*``, ``recall_*`` and ``fscore_*`` per threshold of the two directions' distances."""
    out = {}
    for t in thresholds_m:
        mm = 1000.0 * t
        name = f"{int(round(mm))}mm" if abs(mm - round(mm)) < 1e-9 and mm >= 1 else f"{mm:g}mm".replace(".", "p")
        precision = float((d_pg <= t).mean())
        recall = float((d_gp <= t).mean())
        out[f"precision_{name}"] = precision
        out[f"recall_{name}"] = recall
        out[f"fscore_{name}"] = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return out


def _comparable_samples(gv: np.ndarray, gf: np.ndarray, gt_pts: np.ndarray, pred_pts: np.ndarray,
                        cameras: Sequence[MeshCamera], boundary_margin_m: float, tolerance_m: float,
                        visibility_tolerance_m: float, pred_to_truth_m: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """The comparable truth samples (n,) bool, the kept prediction samples (m,) bool (module docstring) and the
    area shares of :func:`mesh_metrics`; ``pred_to_truth_m`` (m,) each prediction sample's distance to the truth."""
    import open3d as o3d

    truth = comparable_truth(gv, gf, gt_pts, cameras, boundary_margin_m, visibility_tolerance_m)
    gv, gf = _welded(gv, gf)
    cap_v, cap_f = hole_caps(gv, gf)
    closed_v = np.concatenate([gv.astype(np.float64), cap_v])
    shift = gv.astype(np.float64).mean(axis=0)
    closest = _scene(closed_v, np.concatenate([gf, cap_f]), shift).compute_closest_points(
        o3d.core.Tensor(np.ascontiguousarray(pred_pts - shift, np.float32)))
    nearest = closest["points"].numpy().astype(np.float64) + shift
    on_cap = closest["primitive_ids"].numpy().astype(np.int64) >= len(gf)
    distance = np.linalg.norm(nearest - pred_pts, axis=1)
    nearest_comparable = ~on_cap
    if nearest_comparable.any():
        at = comparable_truth(gv, gf, nearest[nearest_comparable], cameras, boundary_margin_m, visibility_tolerance_m)
        nearest_comparable[nearest_comparable] = at["comparable"]
    # an opening's closure may stand out of its flat fan by up to the opening's radius
    allowed = np.full(len(pred_pts), tolerance_m)
    if on_cap.any():
        loop = cap_f[:, 0] - len(gv)
        rim = np.linalg.norm(gv[cap_f[:, 1]].astype(np.float64) - cap_v[loop], axis=1)
        radius = np.zeros(len(cap_v))
        np.maximum.at(radius, loop, rim)
        face = closest["primitive_ids"].numpy().astype(np.int64)[on_cap] - len(gf)
        allowed[on_cap] = np.maximum(radius[loop[face]], tolerance_m)
    far = ~nearest_comparable & (distance > allowed)
    keep_pred = nearest_comparable | far
    # prediction off the truth where a camera's line of sight passes it and meets the truth beyond: surface the
    # capture contradicts (a surface closing an opening of the truth, within the opening's radius of its fan, is
    # not: there the cameras see into an open mesh)
    off = (np.asarray(pred_to_truth_m) > tolerance_m) & ~(on_cap & (distance <= allowed))
    seen_through = np.zeros(len(pred_pts), bool)
    if off.any():
        seen_through[off] = cameras_seeing(closed_v, np.concatenate([gf, cap_f]), pred_pts[off], cameras,
                                           visibility_tolerance_m) > 0
    return truth["comparable"], keep_pred, {
        "pred_seen_through_area_fraction": float(seen_through.mean()),
        "comparable_gt_area_fraction": float(truth["comparable"].mean()),
        "comparable_pred_area_fraction": float(keep_pred.mean()),
        "gt_unseen_area_fraction": float((~truth["seen"]).mean()),
        "gt_boundary_area_fraction": float(truth["near_boundary"].mean()),
        "pred_far_from_truth_area_fraction": float(far.mean()),
    }
