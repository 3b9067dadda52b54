"""Silhouette refinement: move a mesh's occluding contours to the sub-pixel outline the captured views measure.

The SDF is fitted to the masks as 0/1 per pixel, and its outline in a view lies about a quarter pixel either way
from the subject's (the mesh's local shape at the scale of its Chamfer). The white image measures more than
the mask says: on the outline each pixel's colour is a mix of the subject's and the clean plate's, and the mix
is the share of the pixel the subject covers (:func:`stages.numerics.photometric.edge_coverage`).

Per view, the mesh's *outer* contour vertices (on an edge between a face turned to the camera and one turned
away, with the mesh on the inside of the profile and nothing on the outside) are moved along their normal. The
outline is located along the image direction in which that move pushes the vertex's projection (the
``profile``), from ``-PROFILE_PX`` to ``+PROFILE_PX`` pixels:

- measured: ``e = integral of c(t) dt - PROFILE_PX`` over the coverage ``c`` read bilinearly along the profile
  and divided by its level just inside (for a straight edge blurred by any symmetric footprint, the integral of
  the blurred step equals the step's, so ``e`` is the outline's offset along the profile);
- the mesh's: the same integral of the mesh's own hits along the profile (rays at the same points).

Their difference in pixels, less ``outline_bias_px`` (a rim seen edge-on reads brighter than the body a pixel
further in, so the measured outline lies a little outside the subject's), over the profile's pixels per metre of
move is the vertex's move for that view.
Profiles that do not look like one clean outline are skipped: the mesh has surface on the outside (another
limb) or none on the inside, the measured level inside is under ``MIN_INSIDE`` or outside over ``MAX_OUTSIDE``,
the coverage rises again going out by more than ``MAX_RISE``, or the two outlines differ by more than
``max_offset_px`` (a mask that holds what the mesh lacks, or the reverse: not this step's to mend). Each vertex
takes the mean of its views' moves; the moves are spread over the surface by ``smoothing`` rounds of
normalised averaging with the neighbours (contours of nearby views lie next to each other; a lone vertex must
not move alone) and applied at ``step`` of their size, ``iterations`` times, the contours found again each time.
A move that turns a face over is taken back.

Pure numerics: arrays in, arrays out; no output holds NaN or Inf.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from pipeline.config import Documented, checked

__all__ = ["SilhouetteConfig", "OutlineView", "refine_silhouettes", "outline_offsets", "outline_disagreement"]

PROFILE_PX = 3.0
"""Half-length (pixels) of the profile the outline is located on: room for the quarter pixel the mesh is off and
for the two pixels of the mask's band (:func:`stages.numerics.photometric.edge_coverage`) on either side."""
PROFILE_CELLS = 24
"""Samples of the profile (a quarter pixel apart)."""
MIN_INSIDE = 0.7
"""The least measured coverage on the profile's innermost pixel a profile is used with."""
MAX_OUTSIDE = 0.15
"""The most measured coverage on the profile's outermost pixel."""
MAX_RISE = 0.15
"""The most the normalised coverage may rise from one sample to the next going outwards."""


@dataclass(frozen=True)
class SilhouetteConfig(Documented):
    """How the mesh's contours are moved to the views' measured outline (module docstring)."""

    enabled: bool = True
    """Refine the published mesh's outer contours to the outline the white images measure against the clean
    plates (actions without plates keep the SDF's mesh)."""
    iterations: int = checked(3, ge=0)
    """Rounds of contours found, outlines compared and moves applied."""
    step: float = checked(0.5, gt=0.0, le=1.0)
    """Share of each round's smoothed move that is applied (the measured outline is noisy: a quarter pixel RMS
    per contour vertex on the default capture, about as much as the SDF's own error)."""
    smoothing: int = checked(32, ge=0)
    """Rounds of normalised averaging with the neighbouring vertices that spread the moves over the surface
    (fewer leave bumps that turn the mesh's normals: on the default capture 8 rounds lower its normal
    consistency by up to 0.004, 32 leave it as it was)."""
    max_offset_px: float = checked(0.75, gt=0.0)
    """Profiles whose measured and mesh outlines differ by more (pixels) are skipped."""
    outline_bias_px: float = checked(0.06)
    """How far (pixels) the measured outline lies outside the subject's, subtracted from every measurement. A rim
    seen edge-on reads brighter than the body a pixel further in (grazing specular light), so its pixels read
    as more covered than they are. 0.06: the median over the default capture's contour profiles of the measured
    outline against the one the simulator's true pixel coverage gives on the same profiles (0.066 and 0.059 px
    on its two actions; 0.08-0.09 on the unseen capture, 0.06 on the procedural subject; see the README)."""


@dataclass(frozen=True)
class OutlineView:
    """One captured view as the refinement reads it."""

    K: np.ndarray
    """(3, 3) intrinsics."""
    cam_from_world: np.ndarray
    """(3, 4) ``[R | t]``."""
    coverage: np.ndarray
    """(H, W) measured share of each pixel the subject covers, in [0, 1], any float type
    (:func:`stages.numerics.photometric.edge_coverage`)."""


def _edges_with_faces(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The edges shared by two faces: (E, 2) vertex pairs and the two faces of each (E,), (E,)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    fid = np.tile(np.arange(len(faces)), 3)
    key = np.sort(e, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, fid = key[order], fid[order]
    twin = np.nonzero(np.all(key[1:] == key[:-1], axis=1))[0]
    return key[twin], fid[twin], fid[twin + 1]


def _image_motion(points: np.ndarray, normals: np.ndarray, K: np.ndarray,
                  P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) and camera depth (N,) of world points (N, 3), and the motion of their projection
    (N, 2), pixels per metre, as each moves along its normal (N, 3) (a finite difference of 0.1 mm)."""
    from artifacts.camera import pixel_coordinates

    def project(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cam = x @ P[:, :3].T + P[:, 3]
        z = cam[:, 2]
        return np.stack(pixel_coordinates(K, cam, np.where(np.abs(z) > 1e-12, z, 1e-12)), axis=-1), z

    eps = 1e-4
    uv, z = project(points)
    uv_moved, _ = project(points + eps * normals)
    return uv, z, (uv_moved - uv) / eps


def outline_offsets(scene: Any, vertices: np.ndarray, normals: np.ndarray, contour: np.ndarray, K: np.ndarray,
                    cam_from_world: np.ndarray, coverage: np.ndarray,
                    cfg: SilhouetteConfig = SilhouetteConfig()) -> tuple[np.ndarray, np.ndarray]:
    """The move (metres along the normal) that puts each contour vertex on the measured outline, in one view.

    Args:
        scene: the mesh's open3d ``RaycastingScene`` (:func:`stages.numerics.raycast.mesh_scene`).
        vertices: (V, 3) world positions. normals: (V, 3) unit vertex normals.
        contour: (M,) indices of the view's contour vertices.
        K: (3, 3) intrinsics. cam_from_world: (3, 4).
        coverage: (H, W) measured pixel coverage in [0, 1] (:func:`stages.numerics.photometric.edge_coverage`).
        cfg: the profile's settings.

    Returns:
        move_m (M,) float64 and used (M,) bool (the profile passed every check; move_m is 0 elsewhere).
    """
    import open3d as o3d

    from stages.numerics.bake import sample_pixels
    from stages.numerics.raycast import camera_rays

    K = np.asarray(K, np.float64)
    P = np.asarray(cam_from_world, np.float64)[:3, :4]
    m = len(contour)
    if m == 0:
        return np.zeros(0), np.zeros(0, bool)
    pts = np.asarray(vertices, np.float64)[contour]
    nrm = np.asarray(normals, np.float64)[contour]
    uv, z, duv = _image_motion(pts, nrm, K, P)
    speed = np.linalg.norm(duv, axis=1)  # pixels per metre of move
    direction = duv / np.maximum(speed, 1e-12)[:, None]
    # the midpoints of equal cells over [-PROFILE_PX, PROFILE_PX]: no sample falls on the contour vertex itself,
    # where the mesh's own outline is, so a step there counts exactly half of the samples
    dt = 2.0 * PROFILE_PX / PROFILE_CELLS
    t = -PROFILE_PX + dt * (np.arange(PROFILE_CELLS) + 0.5)
    u = uv[:, :1] + t[None] * direction[:, :1]
    v = uv[:, 1:] + t[None] * direction[:, 1:]
    coverage = np.asarray(coverage)
    origins, dirs, _ = camera_rays(K, P, *coverage.shape, pixels=np.stack([u.ravel(), v.ravel()], axis=-1))
    rays = np.ascontiguousarray(np.concatenate([origins, dirs], axis=-1), dtype=np.float32)
    hits = np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()).reshape(m, -1)
    measured = sample_pixels(coverage, u, v, np.float64)
    inside_px, outside_px = t <= -PROFILE_PX + 1.0, t >= PROFILE_PX - 1.0
    level_inside = measured[:, inside_px].mean(axis=1)
    # the rim can read brighter than the body further in: the outline's own level is the brightest just inside
    level = np.maximum(measured[:, (t >= -PROFILE_PX + 0.5) & (t <= -0.5)].max(axis=1), level_inside)
    normalised = measured / np.maximum(level, 1e-6)[:, None]
    e_measured = np.clip(normalised, 0.0, 1.0).sum(axis=1) * dt
    e_mesh = hits.sum(axis=1) * dt
    residual_px = e_measured - cfg.outline_bias_px - e_mesh
    used = ((z > 0) & (speed > 0.5 * np.median(speed)) & hits[:, t < -1.0].all(axis=1) & ~hits[:, t > 1.0].any(axis=1)
            & (level_inside >= MIN_INSIDE) & (measured[:, outside_px].mean(axis=1) <= MAX_OUTSIDE)
            & (np.diff(normalised, axis=1) <= MAX_RISE).all(axis=1)
            & (np.abs(residual_px) <= cfg.max_offset_px) & np.isfinite(residual_px))
    move = np.where(used, residual_px / np.maximum(speed, 1e-12), 0.0)
    return move, used


def _face_frames(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each face's (unnormalised) normal, the cross product of its edges (F, 3), and its centroid (F, 3): what
    :func:`_contour_vertices` tests every view against."""
    v0 = vertices[faces[:, 0]]
    return np.cross(vertices[faces[:, 1]] - v0, vertices[faces[:, 2]] - v0), vertices[faces].mean(axis=1)


def _contour_vertices(vertices: np.ndarray, faces: np.ndarray, edges: np.ndarray, face_a: np.ndarray,
                      face_b: np.ndarray, centre: np.ndarray,
                      frames: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Vertices on an edge between a face turned to the camera centre (3,) and one turned away. ``frames``: the
    mesh's :func:`_face_frames`, when the caller tests several views of the same vertices."""
    cross, centroid = _face_frames(vertices, faces) if frames is None else frames
    front = np.einsum("ij,ij->i", cross, centre - centroid) > 0
    return np.unique(edges[front[face_a] != front[face_b]])


def refine_silhouettes(vertices: np.ndarray, faces: np.ndarray, views: Sequence[OutlineView],
                       cfg: SilhouetteConfig = SilhouetteConfig()) -> tuple[np.ndarray, dict[str, Any]]:
    """The mesh's vertices with its outer contours moved to the outline the views measure (module docstring).

    Args:
        vertices: (V, 3) world positions (metres). faces: (F, 3) vertex indices.
        views: the captured views (:class:`OutlineView`).
        cfg: the refinement's settings; ``iterations`` 0 returns the vertices as they are.

    Returns:
        (V, 3) float32 vertices and stats: ``samples_used`` and ``samples_skipped`` per round (profiles over all
        views), ``mean_move_mm`` per round (the mean of the vertices' measured moves before smoothing),
        ``moved_vertices``, ``max_move_mm`` and ``mean_move_all_mm`` (final against input), ``faces_kept_back``
        (vertices whose move was taken back because it turned a face over) and ``seconds``.
    """
    from scipy import sparse

    from artifacts.camera import camera_centre
    from stages.numerics.mesh import vertex_normals
    from stages.numerics.raycast import mesh_scene

    start = time.perf_counter()
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"expected vertices (V, 3) and faces (F, 3), got {v.shape} and {f.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices hold NaN or Inf")
    for i, view in enumerate(views):
        cov = np.asarray(view.coverage)
        if cov.ndim != 2 or not np.all(np.isfinite(cov)):
            raise ValueError(f"view {i}: coverage must be a finite (H, W) map, got shape {cov.shape}")
    stats: dict[str, Any] = {"samples_used": [], "samples_skipped": [], "mean_move_mm": [], "faces_kept_back": 0}
    if cfg.iterations == 0 or len(f) == 0 or not views:
        return v.astype(np.float32), stats | {"moved_vertices": 0, "max_move_mm": 0.0, "mean_move_all_mm": 0.0,
                                              "seconds": time.perf_counter() - start}
    n = len(v)
    edges, face_a, face_b = _edges_with_faces(f)
    adjacency = sparse.coo_matrix((np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]],
                                                               np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n)).tocsr()
    degree = np.maximum(np.asarray(adjacency.sum(axis=1)).ravel(), 1.0)
    centres = [camera_centre(np.asarray(view.cam_from_world, np.float64)[:3, :4]) for view in views]
    current = v.copy()
    for _ in range(cfg.iterations):
        normals = vertex_normals(current, f).astype(np.float64)
        scene = mesh_scene(current, f)
        total, count = np.zeros(n), np.zeros(n)
        used_all = skipped = 0
        frames = _face_frames(current, f)
        for view, centre in zip(views, centres):
            contour = _contour_vertices(current, f, edges, face_a, face_b, centre, frames)
            move, used = outline_offsets(scene, current, normals, contour, view.K, view.cam_from_world,
                                         view.coverage, cfg)
            np.add.at(total, contour[used], move[used])
            np.add.at(count, contour[used], 1.0)
            used_all += int(used.sum())
            skipped += int((~used).sum())
        measured = np.divide(total, count, out=np.zeros(n), where=count > 0)
        # normalised averaging: moves spread to the neighbours by weight, where the measured ones are
        weighted, weight = measured * (count > 0), (count > 0).astype(np.float64)
        for _ in range(cfg.smoothing):
            weighted = 0.5 * weighted + 0.5 * (adjacency @ weighted) / degree
            weight = 0.5 * weight + 0.5 * (adjacency @ weight) / degree
        spread = np.divide(weighted, weight, out=np.zeros(n), where=weight > 1e-3)
        spread *= np.clip(weight / 0.05, 0.0, 1.0)  # fade out where the measured moves thin out
        moved = current + cfg.step * spread[:, None] * normals
        kept_back = _faces_turned_over(current, moved, f)
        moved[kept_back] = current[kept_back]
        stats["faces_kept_back"] += int(kept_back.sum())
        current = moved
        stats["samples_used"].append(used_all)
        stats["samples_skipped"].append(skipped)
        stats["mean_move_mm"].append(float(np.abs(measured[count > 0]).mean() * 1e3) if (count > 0).any() else 0.0)
    shift = np.linalg.norm(current - v, axis=1)
    stats |= {"moved_vertices": int((shift > 0).sum()), "max_move_mm": float(shift.max() * 1e3),
              "mean_move_all_mm": float(shift.mean() * 1e3), "seconds": time.perf_counter() - start}
    return current.astype(np.float32), stats


def outline_disagreement(vertices: np.ndarray, faces: np.ndarray, views: Sequence[OutlineView],
                         reference: Sequence[OutlineView], cfg: SilhouetteConfig = SilhouetteConfig()) -> np.ndarray:
    """How far (pixels) the outline ``views`` measure lies outside the one ``reference`` gives (the same cameras,
    another coverage: e.g. the simulator's true one), on the same contour profiles of the mesh: one value per
    profile that passes the checks with both coverages (``outline_bias_px`` not applied). What
    ``outline_bias_px`` corrects is their median."""
    from artifacts.camera import camera_centre
    from stages.numerics.mesh import vertex_normals
    from stages.numerics.raycast import mesh_scene

    if len(views) != len(reference):
        raise ValueError(f"{len(views)} views against {len(reference)} reference views")
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    unbiased = dataclasses.replace(cfg, outline_bias_px=0.0)
    edges, face_a, face_b = _edges_with_faces(f)
    normals = vertex_normals(v, f).astype(np.float64)
    scene = mesh_scene(v, f)
    out = []
    frames = _face_frames(v, f)
    for view, ref in zip(views, reference):
        contour = _contour_vertices(v, f, edges, face_a, face_b, camera_centre(np.asarray(view.cam_from_world)[:3]),
                                    frames)
        move, used = outline_offsets(scene, v, normals, contour, view.K, view.cam_from_world, view.coverage, unbiased)
        move_ref, used_ref = outline_offsets(scene, v, normals, contour, ref.K, ref.cam_from_world, ref.coverage,
                                             unbiased)
        P = np.asarray(view.cam_from_world, np.float64)[:3, :4]
        speed = np.linalg.norm(_image_motion(v[contour], normals[contour], np.asarray(view.K, np.float64), P)[2],
                               axis=1)  # pixels per metre of move
        both = used & used_ref
        out.append((move - move_ref)[both] * speed[both])
    return np.concatenate(out) if out else np.zeros(0)


def _faces_turned_over(before: np.ndarray, after: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) bool: the vertices of the faces whose normal turned by more than 90 degrees from ``before`` to
    ``after``."""
    def cross(x: np.ndarray) -> np.ndarray:
        return np.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]])

    flipped = np.einsum("ij,ij->i", cross(before), cross(after)) < 0
    out = np.zeros(len(before), bool)
    out[faces[flipped].ravel()] = True
    return out
