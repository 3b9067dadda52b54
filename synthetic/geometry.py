"""Mesh numerics: OBJ parsing, triangulation, Loop subdivision, normals, directions, procedural SDF mesh.

Everything here is arrays in, arrays out, except `read_obj` which parses a file.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np


@dataclass(frozen=True)
class ObjMesh:
    """A polygon mesh as read from an OBJ file.

    vertices: (V, 3) float64; uvs: (U, 2) float64 (possibly empty); faces: list of (vertex ids, uv ids or
    None) per polygon, zero-based; groups: group name per face.
    """
    vertices: np.ndarray
    uvs: np.ndarray
    faces: list[tuple[list[int], list[int] | None]]
    groups: list[str]


def read_obj(path: str | Path) -> ObjMesh:
    """Parse the `v`, `vt`, `f` and `g` records of a Wavefront OBJ file (1-based or negative indices)."""
    vertices: list[list[float]] = []
    uvs: list[list[float]] = []
    faces: list[tuple[list[int], list[int] | None]] = []
    groups: list[str] = []
    group = "default"
    with open(path, encoding="utf-8", errors="replace") as handle:
        for line in handle:
            if line.startswith("v "):
                vertices.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("vt "):
                uvs.append([float(x) for x in line.split()[1:3]])
            elif line.startswith("g ") or line.startswith("o "):
                group = line[2:].strip() or "default"
            elif line.startswith("f "):
                corners = line.split()[1:]
                vids, tids = [], []
                for corner in corners:
                    parts = corner.split("/")
                    vid = int(parts[0])
                    vids.append(vid - 1 if vid > 0 else len(vertices) + vid)
                    if len(parts) > 1 and parts[1]:
                        tid = int(parts[1])
                        tids.append(tid - 1 if tid > 0 else len(uvs) + tid)
                faces.append((vids, tids if len(tids) == len(vids) else None))
                groups.append(group)
    if not vertices or not faces:
        raise ValueError(f"{path}: no vertices or faces")
    return ObjMesh(np.asarray(vertices, dtype=np.float64), np.asarray(uvs, dtype=np.float64).reshape(-1, 2),
                   faces, groups)


def group_centroids(obj: ObjMesh, groups: Iterable[str]) -> dict[str, np.ndarray]:
    """Centroid (3,) of the distinct vertices of each named group that has faces (absent groups are left out)."""
    wanted = set(groups)
    members: dict[str, set[int]] = {}
    for (vids, _), group in zip(obj.faces, obj.groups):
        if group in wanted:
            members.setdefault(group, set()).update(vids)
    return {group: obj.vertices[sorted(ids)].mean(axis=0) for group, ids in members.items()}


def triangulate(obj: ObjMesh, keep_group: Callable[[str], bool]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Fan-triangulate the faces whose group passes `keep_group`, dropping unused vertices.

    Returns:
        vertices (V, 3) float64, triangles (T, 3) int64, corner_uvs (T, 3, 2) float64 or None when any
        kept face lacks UVs.
    """
    vertices, triangles, corner_uvs, _ = triangulate_with_ids(obj, keep_group)
    return vertices, triangles, corner_uvs


def triangulate_with_ids(obj: ObjMesh, keep_group: Callable[[str], bool]
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """:func:`triangulate`, and the OBJ vertex index (V,) int64 of every kept vertex."""
    tris: list[list[int]] = []
    tri_uvs: list[list[int]] = []
    has_uvs = True
    for (vids, tids), group in zip(obj.faces, obj.groups):
        if not keep_group(group):
            continue
        for k in range(1, len(vids) - 1):
            tris.append([vids[0], vids[k], vids[k + 1]])
            if tids is None:
                has_uvs = False
            else:
                tri_uvs.append([tids[0], tids[k], tids[k + 1]])
    if not tris:
        raise ValueError("no faces left after filtering groups")
    triangles = np.asarray(tris, dtype=np.int64)
    used, remapped = np.unique(triangles, return_inverse=True)
    corner_uvs = obj.uvs[np.asarray(tri_uvs, dtype=np.int64)] if has_uvs and len(obj.uvs) else None
    return obj.vertices[used], remapped.reshape(-1, 3), corner_uvs, used.astype(np.int64)


def group_vertex_ids(obj: ObjMesh, groups: Iterable[str]) -> dict[str, np.ndarray]:
    """Sorted distinct vertex indices (K,) int64 of each named group that has faces (absent groups are left out)."""
    wanted = set(groups)
    members: dict[str, set[int]] = {}
    for (vids, _), group in zip(obj.faces, obj.groups):
        if group in wanted:
            members.setdefault(group, set()).update(vids)
    return {group: np.array(sorted(ids), np.int64) for group, ids in members.items()}


def loop_subdivide(vertices: np.ndarray, triangles: np.ndarray,
                   corner_uvs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One step of Loop subdivision (smooth; boundary and non-manifold edges use the midpoint rule).

    Args:
        vertices: (V, 3) float64. triangles: (T, 3) int64. corner_uvs: (T, 3, 2) or None, subdivided
            linearly per triangle (UV seams stay seams).

    Returns:
        vertices (V + E, 3) with the E edge points after the V moved originals, triangles (4T, 3),
        corner_uvs (4T, 3, 2) or None.
    """
    n_vertices = len(vertices)
    half_edges = np.stack([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]], axis=1)
    opposite = triangles[:, [2, 0, 1]].reshape(-1)
    lo = half_edges.reshape(-1, 2).min(axis=1)
    hi = half_edges.reshape(-1, 2).max(axis=1)
    keys, edge_of_half, edge_count = np.unique(lo * n_vertices + hi, return_inverse=True, return_counts=True)
    edge_a, edge_b = keys // n_vertices, keys % n_vertices
    n_edges = len(keys)
    interior = edge_count == 2

    opposite_sum = np.stack([np.bincount(edge_of_half, weights=vertices[opposite, c], minlength=n_edges)
                             for c in range(3)], axis=1)
    midpoint = 0.5 * (vertices[edge_a] + vertices[edge_b])
    edge_points = np.where(interior[:, None],
                           0.375 * (vertices[edge_a] + vertices[edge_b]) + 0.125 * opposite_sum, midpoint)

    both = np.concatenate([edge_a, edge_b])
    other = np.concatenate([edge_b, edge_a])
    valence = np.bincount(both, minlength=n_vertices).astype(np.float64)
    neighbour_sum = np.stack([np.bincount(both, weights=vertices[other, c], minlength=n_vertices)
                              for c in range(3)], axis=1)
    boundary_both = np.concatenate([~interior, ~interior])
    boundary_valence = np.bincount(both[boundary_both], minlength=n_vertices)
    boundary_sum = np.stack([np.bincount(both[boundary_both], weights=vertices[other[boundary_both], c],
                                         minlength=n_vertices) for c in range(3)], axis=1)
    safe_valence = np.maximum(valence, 1.0)
    beta = np.where(valence > 3, 3.0 / (8.0 * safe_valence), 3.0 / 16.0)
    moved = (1.0 - valence * beta)[:, None] * vertices + beta[:, None] * neighbour_sum
    moved = np.where((boundary_valence == 2)[:, None], 0.75 * vertices + 0.125 * boundary_sum, moved)
    moved = np.where(((boundary_valence > 0) & (boundary_valence != 2))[:, None] | (valence == 0)[:, None],
                     vertices, moved)

    e = (edge_of_half.reshape(-1, 3) + n_vertices)  # edge point ids of edges 01, 12, 20
    v0, v1, v2 = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    e01, e12, e20 = e[:, 0], e[:, 1], e[:, 2]
    new_triangles = np.stack([
        np.stack([v0, e01, e20], axis=1), np.stack([v1, e12, e01], axis=1),
        np.stack([v2, e20, e12], axis=1), np.stack([e01, e12, e20], axis=1)], axis=1).reshape(-1, 3)
    new_uvs = None
    if corner_uvs is not None:
        u0, u1, u2 = corner_uvs[:, 0], corner_uvs[:, 1], corner_uvs[:, 2]
        m01, m12, m20 = 0.5 * (u0 + u1), 0.5 * (u1 + u2), 0.5 * (u2 + u0)
        new_uvs = np.stack([np.stack([u0, m01, m20], 1), np.stack([u1, m12, m01], 1),
                            np.stack([u2, m20, m12], 1), np.stack([m01, m12, m20], 1)], axis=1).reshape(-1, 3, 2)
    return np.concatenate([moved, edge_points]), new_triangles, new_uvs


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, (V, 3) float64 (a default +z where a vertex has no area)."""
    face_normals = np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]],
                            vertices[triangles[:, 2]] - vertices[triangles[:, 0]])
    normals = np.zeros_like(vertices)
    for c in range(3):
        normals[:, c] = sum(np.bincount(triangles[:, k], weights=face_normals[:, c], minlength=len(vertices))
                            for k in range(3))
    return normalize(normals, fallback=(0.0, 0.0, 1.0))


def normalize(vectors: np.ndarray, fallback: tuple[float, float, float] | None = None) -> np.ndarray:
    """Unit vectors along the last axis; zero-length rows become `fallback` (or stay zero)."""
    length = np.linalg.norm(vectors, axis=-1, keepdims=True)
    unit = vectors / np.where(length > 0, length, 1.0)
    if fallback is not None:
        unit = np.where(length > 0, unit, np.asarray(fallback, dtype=vectors.dtype))
    return unit


def fibonacci_sphere(count: int) -> np.ndarray:
    """`count` near-uniform unit directions on the sphere (Fibonacci lattice), (count, 3) float64."""
    i = np.arange(count, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * i / count
    radius = np.sqrt(np.maximum(0.0, 1.0 - y * y))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([radius * np.cos(phi), y, radius * np.sin(phi)], axis=1)


def yaw_matrix(yaw_rad: float) -> np.ndarray:
    """Rotation about +y by `yaw_rad` (right-handed), (3, 3)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


# --- procedural subject: signed distances -------------------------------------------------------------

def sdf_capsule(points: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """Signed distance (N,) from points (N, 3) to the capsule of segment a-b with the given radius."""
    ab = b - a
    t = np.clip(((points - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1) - radius


def sdf_sphere(points: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Signed distance (N,) from points (N, 3) to a sphere."""
    return np.linalg.norm(points - centre, axis=1) - radius


def sdf_torus(points: np.ndarray, centre: np.ndarray, major: float, minor: float) -> np.ndarray:
    """Signed distance (N,) to a torus around the +y axis through `centre`."""
    q = points - centre
    ring = np.sqrt(q[:, 0] ** 2 + q[:, 2] ** 2) - major
    return np.sqrt(ring ** 2 + q[:, 1] ** 2) - minor


def smooth_union(distances: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum over the first axis of (P, N) distances with blend radius k (metres)."""
    result = distances[0]
    for d in distances[1:]:
        h = np.clip(0.5 + 0.5 * (d - result) / k, 0.0, 1.0)
        result = d * (1 - h) + result * h - k * h * (1 - h)
    return result


def mesh_from_sdf(sdf: Callable[[np.ndarray], np.ndarray], lo: np.ndarray, hi: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Marching-cubes surface of sdf(points (N,3)) -> (N,) over the box [lo, hi] sampled every `step` m.

    Returns vertices (V, 3) float64 and outward-wound triangles (T, 3) int64.
    """
    from skimage.measure import marching_cubes

    axes = [np.arange(lo[i], hi[i] + step, step) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    volume = sdf(grid).reshape(len(axes[0]), len(axes[1]), len(axes[2]))
    verts, faces, _, _ = marching_cubes(volume, level=0.0, spacing=(step, step, step))
    verts = verts + lo
    faces = faces.astype(np.int64)
    # marching_cubes winds faces towards increasing values (outside): make normals point outwards
    normals = vertex_normals(verts, faces)
    probe = sdf(verts + 0.25 * step * normals) - sdf(verts)
    if np.mean(probe) < 0:
        faces = faces[:, ::-1].copy()
    return verts.astype(np.float64), faces
