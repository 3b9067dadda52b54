"""From a signed distance function to a clean, UV-mapped triangle mesh.

Pure functions, arrays in and arrays out (file I/O is in :mod:`pipeline.codecs.mesh`). Conventions
(docs/CONTRACTS.md): world frame = stage frame, metres, +y up. Meshes are ``vertices (V, 3) float32`` and
``faces (F, 3) int32`` with counter-clockwise winding seen from outside, so ``cross(b - a, c - a)`` points
out of the surface. SDFs are negative inside, positive outside.

- :func:`extract_mesh`: sparse marching cubes. A coarse grid finds the blocks where the zero level can
  be, only those are evaluated on the fine grid, and ``skimage.measure.marching_cubes`` runs on the fine
  grid with a mask of those blocks. On a smooth SDF the result is the dense marching cubes' exactly.
- :func:`largest_component`, :func:`decimate` (quadric, open3d), :func:`vertex_normals`.
- :func:`uv_atlas`: xatlas charts and packing into an :class:`artifacts.atlas.Atlas`.

UV convention (OBJ / OpenGL): ``u`` goes right and ``v`` goes *up*, both in ``[0, 1]`` over the whole
texture. A ``(T, T)`` texture array has row 0 at the top, so texel ``(row, col)`` has its centre at
``u = (col + 0.5) / T``, ``v = 1 - (row + 0.5) / T``.
"""
from __future__ import annotations

import functools
import time
from typing import Callable

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from artifacts.atlas import Atlas
from artifacts.camera import check_bounds

__all__ = [
    "extract_mesh",
    "largest_component",
    "decimate",
    "vertex_normals",
    "face_normals",
    "uv_atlas",
]


# ------------------------------------------------------------------------------------------- checks
def _check_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got shape {f.shape}")
    if f.size and not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must hold integer vertex indices, got dtype {f.dtype}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces index vertices outside [0, {len(v)}): min {f.min()}, max {f.max()}")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices hold NaN or Inf")
    return v, f.astype(np.int64, copy=False)


# ---------------------------------------------------------------------------------- marching cubes
@functools.lru_cache(maxsize=1)
def _mc_mask_offset() -> int:
    """Which corner of a cube ``marching_cubes``' mask is read at: 0 (the cube's first corner) or 1 (its
    last, index + 1 on every axis). scikit-image documents neither; 0.26 reads the last corner. A 3x3x3
    probe with a single cube crossing the level tells, so a version that changes it still works."""
    from skimage.measure import marching_cubes

    volume = np.ones((3, 3, 3), np.float32)
    volume[0, 0, 0] = -1.0  # only cube (0, 0, 0) crosses 0
    mask = np.zeros((3, 3, 3), bool)
    mask[0, 0, 0] = True
    try:
        _, faces, _, _ = marching_cubes(volume, 0.0, mask=mask)
        if len(faces):
            return 0
    except RuntimeError:  # "No surface found"
        pass
    return 1


def _corner_reduce(values: np.ndarray, op: Callable) -> np.ndarray:
    """``op`` over the 8 corners of every cell of a point grid (n0, n1, n2) -> (n0-1, n1-1, n2-1)."""
    n0, n1, n2 = values.shape
    out = None
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                corner = values[dx:n0 - 1 + dx, dy:n1 - 1 + dy, dz:n2 - 1 + dz]
                out = corner.copy() if out is None else op(out, corner)
    return out


def _evaluate(sdf_fn: Callable[[np.ndarray], np.ndarray], points: np.ndarray, chunk: int) -> np.ndarray:
    out = np.empty(len(points), np.float32)
    for start in range(0, len(points), chunk):
        block = np.ascontiguousarray(points[start:start + chunk], dtype=np.float32)
        values = np.asarray(sdf_fn(block), dtype=np.float32).reshape(-1)
        if values.shape[0] != len(block):
            raise ValueError(f"sdf_fn returned {values.shape[0]} values for {len(block)} points")
        if not np.all(np.isfinite(values)):
            raise ValueError("sdf_fn returned NaN or Inf")
        out[start:start + len(block)] = values
    return out


def extract_mesh(sdf_fn: Callable[[np.ndarray], np.ndarray], bounds: np.ndarray, resolution: int,
                 coarse_factor: int = 4, level: float = 0.0,
                 chunk: int = 262144, lipschitz: float = 1.0) -> tuple[np.ndarray, np.ndarray, dict]:
    """Triangle mesh of the ``level`` set of an SDF by marching cubes, evaluated only near the surface.

    The fine grid has cubic voxels of side ``h = max(bounds[1] - bounds[0]) / resolution``, starts at
    ``bounds[0]`` and has a multiple of ``coarse_factor`` cells on every axis (so it may reach up to
    ``coarse_factor`` voxels past ``bounds[1]``). The coarse grid is every ``coarse_factor``-th fine point.
    A coarse cell is refined when the level may cross it: its corners change sign, or some corner is
    closer to the level than the cell's diagonal times ``lipschitz`` (a true SDF cannot reach the level
    in the cell otherwise). Only the fine points of refined cells are evaluated, and marching cubes runs on the fine
    grid masked to those cells; so on an SDF whose level set does not slip between coarse corners (every
    true distance function) the mesh equals the dense marching cubes' exactly.

    Args:
        sdf_fn: ``points (N, 3) float32 -> (N,)`` signed distances in metres (negative inside).
        bounds: (2, 3) min and max corner of the box to mesh, metres.
        resolution: fine cells along the longest side of ``bounds`` (memory: one float32 per fine point).
        coarse_factor: fine cells per coarse cell along each axis (1 = dense).
        level: iso-level (metres).
        chunk: points per ``sdf_fn`` call.
        lipschitz: bound on ``|grad sdf|`` the refinement trusts; raise it (e.g. 1.5) for a learned SDF
            that is steeper than a distance, so thin parts between coarse corners are not skipped.

    Returns:
        vertices (V, 3) float32 metres, faces (F, 3) int32 (outward winding; both empty when the level is
        not crossed), stats: ``fine_evaluated_fraction`` (evaluated fine points / all fine points),
        ``sdf_evaluations`` (coarse + fine), ``coarse_cells_kept``, ``grid_shape`` (fine points per axis),
        ``voxel_m``, ``seconds``.

    Raises:
        ValueError: bad bounds / resolution / coarse_factor, or ``sdf_fn`` returning the wrong count or
            non-finite values.
    """
    from skimage.measure import marching_cubes

    t0 = time.perf_counter()
    bounds = _check_extract_args(bounds, resolution, coarse_factor, lipschitz, chunk)
    resolution, factor, chunk = int(resolution), int(coarse_factor), int(chunk)
    extent = bounds[1] - bounds[0]
    voxel = float(extent.max()) / resolution
    coarse_cells = np.maximum(np.ceil(extent / (voxel * factor) - 1e-9).astype(int), 1)  # per axis
    fine_shape = tuple(int(n) + 1 for n in coarse_cells * factor)
    origin = bounds[0]

    coarse, keep, diagonal = _coarse_pass(sdf_fn, origin, voxel, factor, coarse_cells, level, chunk, lipschitz)
    n_evals = coarse.size
    stats = {"coarse_cells_kept": int(keep.sum()), "grid_shape": list(fine_shape), "voxel_m": voxel}
    empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    if not keep.any():
        stats.update(fine_evaluated_fraction=0.0, sdf_evaluations=int(n_evals), faces=0,
                     seconds=time.perf_counter() - t0)
        return *empty, stats

    cell_fine = np.repeat(np.repeat(np.repeat(keep, factor, 0), factor, 1), factor, 2)
    volume, n_fine = _fine_volume(sdf_fn, coarse, cell_fine, fine_shape, origin, voxel, factor, diagonal, level,
                                  chunk)
    n_evals += n_fine
    mc_mask = np.zeros(fine_shape, bool)
    o = _mc_mask_offset()
    mc_mask[o:fine_shape[0] - 1 + o, o:fine_shape[1] - 1 + o, o:fine_shape[2] - 1 + o] = cell_fine
    stats.update(fine_evaluated_fraction=n_fine / float(np.prod(fine_shape)),
                 sdf_evaluations=int(n_evals))
    try:
        # skimage's winding also flips with its z-y-x -> x-y-z reordering: "descent" gives faces wound
        # counter-clockwise from outside for an SDF negative inside (test_mesh checks it on a sphere).
        verts, faces, _, _ = marching_cubes(volume, 0.0, mask=mc_mask, gradient_direction="descent")
    except (RuntimeError, ValueError):  # no crossing anywhere / level outside the range
        stats.update(faces=0, seconds=time.perf_counter() - t0)
        return *empty, stats
    vertices = (origin + voxel * verts.astype(np.float64)).astype(np.float32)
    stats.update(faces=int(len(faces)), seconds=time.perf_counter() - t0)
    return vertices, faces.astype(np.int32), stats


def _check_extract_args(bounds, resolution, coarse_factor, lipschitz, chunk) -> np.ndarray:
    """:func:`extract_mesh`'s argument checks; returns the bounds as a float64 (2, 3) array."""
    bounds = check_bounds(bounds)
    if int(resolution) < 2:
        raise ValueError(f"resolution must be >= 2, got {resolution}")
    if int(coarse_factor) < 1:
        raise ValueError(f"coarse_factor must be >= 1, got {coarse_factor}")
    if not lipschitz > 0:
        raise ValueError(f"lipschitz must be > 0, got {lipschitz}")
    if int(chunk) < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    return bounds


def _coarse_pass(sdf_fn: Callable[[np.ndarray], np.ndarray], origin: np.ndarray, voxel: float, factor: int,
                 coarse_cells: np.ndarray, level: float, chunk: int,
                 lipschitz: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The SDF less ``level`` at every ``factor``-th fine point (coarse_cells + 1 per axis), the coarse cells
    the level may cross (coarse_cells per axis, bool) and the coarse cells' diagonal (metres)."""
    coarse_axes = [origin[a] + voxel * factor * np.arange(coarse_cells[a] + 1) for a in range(3)]
    coarse_pts = np.stack(np.meshgrid(*coarse_axes, indexing="ij"), axis=-1).reshape(-1, 3)
    coarse = _evaluate(sdf_fn, coarse_pts, chunk).reshape(tuple(coarse_cells + 1)) - np.float32(level)
    diagonal = voxel * factor * np.sqrt(3.0)
    sign_change = _corner_reduce(coarse < 0, np.logical_or) & ~_corner_reduce(coarse < 0, np.logical_and)
    # Every point of a cell is within one diagonal of each corner, so a 1-Lipschitz SDF can reach the
    # level in a cell only if all its corners are within a diagonal of it (half the cells of "any corner").
    near = _corner_reduce(np.abs(coarse), np.maximum) < diagonal * float(lipschitz)
    return coarse, sign_change | near, diagonal


def _fine_volume(sdf_fn: Callable[[np.ndarray], np.ndarray], coarse: np.ndarray, cell_fine: np.ndarray,
                 fine_shape: tuple[int, int, int], origin: np.ndarray, voxel: float, factor: int, diagonal: float,
                 level: float, chunk: int) -> tuple[np.ndarray, int]:
    """The fine grid's volume (fine_shape) float32 for marching cubes: the SDF less ``level`` at every corner
    of a kept fine cell (``cell_fine``, one per fine cell), elsewhere a placeholder; and the points
    evaluated."""
    needed = np.zeros(fine_shape, bool)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                needed[dx:fine_shape[0] - 1 + dx, dy:fine_shape[1] - 1 + dy, dz:fine_shape[2] - 1 + dz] |= cell_fine

    # Unevaluated points are never read by a masked-in cube; they only have to be finite and keep the
    # level inside the volume's range (marching_cubes checks it): the coarse value's sign times the diagonal.
    nearest_coarse = np.repeat(np.repeat(np.repeat(coarse, factor, 0), factor, 1), factor, 2)
    volume = np.where(nearest_coarse[:fine_shape[0], :fine_shape[1], :fine_shape[2]] < 0,
                      np.float32(-diagonal), np.float32(diagonal)).astype(np.float32)
    del nearest_coarse
    flat_idx = np.flatnonzero(needed)
    flat_volume = volume.reshape(-1)
    for start in range(0, len(flat_idx), chunk):
        idx = flat_idx[start:start + chunk]
        ijk = np.stack(np.unravel_index(idx, fine_shape), axis=-1)
        flat_volume[idx] = _evaluate(sdf_fn, origin + voxel * ijk, chunk) - np.float32(level)
    return volume, len(flat_idx)


# ------------------------------------------------------------------------------------------ cleanup
def largest_component(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep the connected component (faces sharing vertices) with the most faces; drop the rest and any
    unreferenced vertex, reindexing faces.

    Args:
        vertices: (V, 3); faces: (F, 3) int.

    Returns:
        vertices (V', 3) of the input dtype, in their original order; faces (F', 3) int32 into them.
    """
    v, f = _check_mesh(vertices, faces)
    if len(f) == 0:
        return v[:0].copy(), np.zeros((0, 3), np.int32)
    rows = np.repeat(f[:, 0], 2)
    cols = f[:, 1:].reshape(-1)
    graph = sparse.coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(len(v), len(v)))
    _, labels = csgraph.connected_components(graph, directed=False)
    face_label = labels[f[:, 0]]
    best = np.bincount(face_label).argmax()
    kept_faces = f[face_label == best]
    used = np.unique(kept_faces)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return v[used].copy(), remap[kept_faces].astype(np.int32)


def decimate(vertices: np.ndarray, faces: np.ndarray, target_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric-error edge-collapse simplification (open3d) to about ``target_faces`` faces.

    A no-op (copies) when the mesh already has ``<= target_faces`` faces. Degenerate faces and
    unreferenced vertices left by the collapses are removed.

    Returns:
        vertices (V', 3) float32, faces (F', 3) int32.
    """
    import open3d as o3d

    v, f = _check_mesh(vertices, faces)
    if int(target_faces) < 4:
        raise ValueError(f"target_faces must be >= 4, got {target_faces}")
    if len(f) <= int(target_faces):
        return v.astype(np.float32), f.astype(np.int32)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v.astype(np.float64)),
                                     o3d.utility.Vector3iVector(f.astype(np.int32)))
    mesh = mesh.simplify_quadric_decimation(target_number_of_triangles=int(target_faces))
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    return (np.asarray(mesh.vertices, dtype=np.float32),
            np.asarray(mesh.triangles, dtype=np.int32).reshape(-1, 3))


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals (F, 3) float64 (0 for degenerate faces) and face areas (F,) float64 (m^2)."""
    v, f = _check_mesh(vertices, faces)
    v = v.astype(np.float64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    norm = np.linalg.norm(cross, axis=1)
    unit = np.divide(cross, norm[:, None], out=np.zeros_like(cross), where=norm[:, None] > 0)
    return unit, 0.5 * norm


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, (V, 3) float32 unit; 0 for vertices in no (non-degenerate) face."""
    v, f = _check_mesh(vertices, faces)
    cross = np.cross(v[f[:, 1]].astype(np.float64) - v[f[:, 0]], v[f[:, 2]].astype(np.float64) - v[f[:, 0]])
    acc = np.zeros((len(v), 3), np.float64)
    for k in range(3):  # |cross| = 2 area: summing raw cross products weights by area
        for d in range(3):
            acc[:, d] += np.bincount(f[:, k], weights=cross[:, d], minlength=len(v))
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.divide(acc, norm, out=np.zeros_like(acc), where=norm > 0).astype(np.float32)


# --------------------------------------------------------------------------------------------- atlas
def uv_atlas(vertices: np.ndarray, faces: np.ndarray, resolution: int = 1024, padding: int = 2,
             max_iterations: int = 1, brute_force: bool = False, seed_normals: bool = True,
             max_chart_area: float = 0.0) -> Atlas:
    """Cut the mesh into charts, flatten and pack them (xatlas) into a ``resolution`` square texture.

    xatlas' time grows faster than linearly in the face count (about a minute at 100k faces): atlas a
    decimated mesh (20-50k faces).

    Args:
        vertices: (V, 3) metres; faces: (F, 3) int.
        resolution: atlas side in texels the packing targets (bake at this size or a multiple).
        padding: empty texels kept around each chart (bilinear lookups and dilation need >= 2).
        max_iterations: xatlas chart-growing iterations (more = fewer, rounder charts, slower).
        brute_force: xatlas' slower, tighter packing.
        seed_normals: pass area-weighted vertex normals to xatlas (charts follow the surface better).
        max_chart_area: largest chart xatlas grows, in the vertices' units squared (0: no limit). Growing
            and flattening the few large charts is most of xatlas' time on a body.

    Returns:
        :class:`Atlas`; face order is the input's.
    """
    import xatlas

    v, f = _check_mesh(vertices, faces)
    if len(f) == 0:
        raise ValueError("uv_atlas needs at least one face")
    if int(resolution) < 8:
        raise ValueError(f"resolution must be >= 8, got {resolution}")
    if int(padding) < 0:
        raise ValueError(f"padding must be >= 0, got {padding}")
    if not float(max_chart_area) >= 0.0:
        raise ValueError(f"max_chart_area must be >= 0, got {max_chart_area}")
    t0 = time.perf_counter()
    normals = vertex_normals(v, f) if seed_normals else None

    def generate(texels_per_unit: float = 0.0):
        atlas = xatlas.Atlas()
        atlas.add_mesh(np.ascontiguousarray(v, np.float32), np.ascontiguousarray(f, np.uint32), normals)
        chart_options = xatlas.ChartOptions()
        chart_options.max_iterations = int(max_iterations)
        chart_options.max_chart_area = float(max_chart_area)
        pack_options = xatlas.PackOptions()
        pack_options.resolution = int(resolution)
        pack_options.padding = int(padding)
        pack_options.bilinear = True
        pack_options.bruteForce = bool(brute_force)
        pack_options.texels_per_unit = float(texels_per_unit)
        atlas.generate(chart_options, pack_options)
        return atlas

    atlas = generate()
    if atlas.atlas_count != 1:
        raise ValueError(f"xatlas packed {atlas.atlas_count} atlases, expected 1")
    # With only a resolution, xatlas estimates the scale and may pack into a long rectangle (seen: 2507 x
    # 789 for a 1024 target), which the unit square below would hold with two thirds left empty. Then pack
    # again at the scale that fills a resolution x resolution page, backing off while it overflows.
    def square_fill(a) -> float:  # share of the final unit square the charts (with padding) use
        return float(a.utilization) * a.width * a.height / float(max(a.width, a.height)) ** 2

    first_fill = square_fill(atlas)
    repacks = 0
    if atlas.width * atlas.height < 0.75 * max(atlas.width, atlas.height) ** 2:
        scale = 0.97 * np.sqrt(float(resolution) ** 2 / (atlas.width * atlas.height))
        for _ in range(4):
            repacks += 1
            candidate = generate(atlas.texels_per_unit * scale)
            if candidate.atlas_count == 1:
                if square_fill(candidate) > first_fill:
                    atlas = candidate
                break
            scale *= 0.9
    vmapping, indices, uvs = atlas[0]
    packed_w, packed_h = int(atlas.width), int(atlas.height)
    # xatlas' uv is (x / width, y / height) in its packed texels, y growing with the rows. With a
    # resolution and no texels_per_unit it estimates the scale, so the packed size comes out near, not
    # at, the resolution and not square: map both axes by the larger side so the atlas fits the unit
    # square without stretching the charts, then flip v to OBJ's "v up".
    side = max(packed_w, packed_h)
    uv = np.asarray(uvs, np.float64).copy()
    uv[:, 0] *= packed_w / side
    uv[:, 1] = 1.0 - uv[:, 1] * (packed_h / side)
    return Atlas(vmapping=np.asarray(vmapping, np.int64), faces=np.asarray(indices, np.int32).reshape(-1, 3),
                 uvs=np.clip(uv, 0.0, 1.0).astype(np.float32), width=side, height=side,
                 stats={"charts": int(atlas.chart_count), "utilization": float(atlas.utilization),
                        "packed_width": packed_w, "packed_height": packed_h,
                        "texels_per_metre": float(atlas.texels_per_unit), "repacks": repacks,
                        "square_fill": square_fill(atlas), "first_square_fill": first_fill,
                        "seconds": time.perf_counter() - t0})
