"""Space the views see through: where the views disagree on the surface a mesh puts in front of them.

A pixel sees a point of the true surface, and every other view that sees that point measures the same world-space
normal there. Where a mesh closes over a cavity (a skirt's hem, closed 3-4 cm above it by a normal-supervised
SDF), a view looking into the cavity meets the mesh at a point of empty space: the other views that see that
point look at other surfaces behind it and measure other normals. :func:`normal_agreement` counts, for each
pixel a mesh covers, the other views that see the mesh's point there and agree with the pixel's normal;
:func:`disagreement_pixels` keeps the pixels no such view agrees with, in regions where most pixels are so (a
cavity is a region, a specular glint or a grazing pixel is not); :func:`free_depths` turns them into the depth up
to which the ray is taken to be empty (:attr:`stages.numerics.sdf.SDFView.free_depth_m`).

The normals must be free of the view-dependent specular part: with the photometric (eq. 1) normals, whose
specular lobe turns each view's normal toward its own mirror direction, most disagreeing regions are not cavities
(README, *The skirt's cavity*). Pure: arrays in, arrays out.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def _project(points: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray, height: int,
             width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rows and columns (N,) int of the pixels (centres at integer coordinates) ``points`` (N, 3) fall in, their
    camera depth (N,) and whether they fall in front of the camera inside the image (N,) bool."""
    cam = points @ cam_from_world[:, :3].T + cam_from_world[:, 3]
    z = cam[:, 2]
    uvw = cam @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = uvw[:, 0] / z + 0.5, uvw[:, 1] / z + 0.5
    inside = (z > 0) & np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    cols = np.clip(np.floor(np.where(inside, u, 0)), 0, width - 1).astype(np.int64)
    rows = np.clip(np.floor(np.where(inside, v, 0)), 0, height - 1).astype(np.int64)
    return rows, cols, z, inside


def normal_agreement(normals_world: Sequence[np.ndarray], normal_valid: Sequence[np.ndarray],
                     mesh_t: Sequence[np.ndarray], mesh_depth: Sequence[np.ndarray], Ks: Sequence[np.ndarray],
                     cams_from_world: Sequence[np.ndarray], agree_deg: float = 20.0,
                     visible_tol_m: float | None = None, facing_cos: float = 0.2) -> list[tuple[np.ndarray, np.ndarray]]:
    """For each view's pixels that a mesh covers, how many other views see the mesh's point there and how many of
    them agree with the pixel's normal.

    Args:
        normals_world: per view (H, W, 3) unit normals, world frame.
        normal_valid: per view (H, W) bool, where the normal is trusted.
        mesh_t: per view (H, W) distance from the camera centre to the mesh along the pixel's unit ray, metres
            (0 where the mesh misses the pixel).
        mesh_depth: per view (H, W) camera z of the mesh (0 where it misses): the visibility test.
        Ks, cams_from_world: per view (3, 3) intrinsics and (3, 4) ``[R | t]`` (OpenCV).
        agree_deg: two normals within this angle agree.
        visible_tol_m: another view sees the mesh's point when its own mesh depth at the point's pixel is within
            this of the point's camera z; None: every view the point projects into counts. A mesh closed over a
            cavity hides the cavity's points from the views that look into it obliquely (the skirt: 172 flagged
            pixels with a 0.01 m test, 1,719 without, README *The skirt's cavity*).
        facing_cos: another view counts only where the pixel's normal faces it by at least this cosine.

    Returns:
        per view ``(agree, seen)``: (H, W) int32 counts of the other views that see the point and agree, and that
        see it (0 off the pixels with a valid normal the mesh covers).
    """
    n_views = len(normals_world)
    if not (len(normal_valid) == len(mesh_t) == len(mesh_depth) == len(Ks) == len(cams_from_world) == n_views):
        raise ValueError("normal_agreement: every per-view list must have one entry per view")
    if not 0.0 < agree_deg < 180.0:
        raise ValueError(f"agree_deg must be in (0, 180), got {agree_deg}")
    cos_agree = np.cos(np.radians(agree_deg))
    from artifacts.camera import camera_centre, pixel_rays

    centres = [camera_centre(np.asarray(T, np.float64)) for T in cams_from_world]
    out = []
    for a in range(n_views):
        H, W = np.shape(normal_valid[a])
        t = np.asarray(mesh_t[a], np.float64)
        if t.shape != (H, W) or np.shape(normals_world[a]) != (H, W, 3):
            raise ValueError(f"normal_agreement: view {a}'s maps are not one (H, W) shape")
        rows, cols = np.nonzero(np.asarray(normal_valid[a], bool) & (t > 0))
        K, T = np.asarray(Ks[a], np.float64), np.asarray(cams_from_world[a], np.float64)
        dirs = pixel_rays(K, T, cols, rows)[0]
        points = centres[a] + t[rows, cols, None] * dirs
        normal = np.asarray(normals_world[a], np.float64)[rows, cols]
        agree = np.zeros(len(rows), np.int32)
        seen = np.zeros(len(rows), np.int32)
        for b in range(n_views):
            if b == a:
                continue
            Hb, Wb = np.shape(normal_valid[b])
            r, c, z, inside = _project(points, np.asarray(Ks[b], np.float64), np.asarray(cams_from_world[b],
                                                                                         np.float64), Hb, Wb)
            to_camera = centres[b] - points
            to_camera /= np.linalg.norm(to_camera, axis=1, keepdims=True)
            ok = inside & ((normal * to_camera).sum(1) > facing_cos)
            ok &= np.asarray(normal_valid[b], bool)[r, c]
            if visible_tol_m is not None:
                depth_b = np.asarray(mesh_depth[b], np.float64)[r, c]
                ok &= (depth_b > 0) & (np.abs(depth_b - z) < visible_tol_m)
            other = np.asarray(normals_world[b], np.float64)[r, c]
            seen += ok
            agree += ok & ((other * normal).sum(1) > cos_agree)
        agree_map = np.zeros((H, W), np.int32)
        seen_map = np.zeros((H, W), np.int32)
        agree_map[rows, cols] = agree
        seen_map[rows, cols] = seen
        out.append((agree_map, seen_map))
    return out


def disagreement_pixels(agree: np.ndarray, seen: np.ndarray, min_seen: int = 2, window_px: int = 9,
                        min_share: float = 0.6) -> np.ndarray:
    """(H, W) bool: pixels that at least ``min_seen`` other views see and none agrees with, where such pixels make
    more than ``min_share`` of the counted pixels (``seen`` > 0) of the ``window_px`` square around them.

    Args:
        agree, seen: (H, W) int counts of :func:`normal_agreement`.
    """
    from scipy import ndimage

    agree, seen = np.asarray(agree), np.asarray(seen)
    if agree.shape != seen.shape or agree.ndim != 2:
        raise ValueError(f"agree {agree.shape} and seen {seen.shape} must be one (H, W) shape")
    if window_px < 1 or not 0.0 <= min_share < 1.0:
        raise ValueError(f"window_px must be >= 1 and min_share in [0, 1), got {window_px}, {min_share}")
    alone = (seen >= min_seen) & (agree == 0)
    counted = ndimage.uniform_filter((seen > 0).astype(np.float64), window_px, mode="constant")
    share = ndimage.uniform_filter(alone.astype(np.float64), window_px, mode="constant") / np.maximum(counted, 1e-9)
    return alone & (share > min_share)


def free_depths(flagged: np.ndarray, mesh_t: np.ndarray, beyond_m: float) -> np.ndarray:
    """(H, W) float32 free depth (:attr:`stages.numerics.sdf.SDFView.free_depth_m`): ``beyond_m`` past the mesh's
    distance ``mesh_t`` (H, W) on the ``flagged`` pixels (H, W) bool, 0 elsewhere."""
    flagged, mesh_t = np.asarray(flagged, bool), np.asarray(mesh_t, np.float64)
    if flagged.shape != mesh_t.shape:
        raise ValueError(f"flagged {flagged.shape} and mesh_t {mesh_t.shape} must be one shape")
    if not beyond_m > 0:
        raise ValueError(f"beyond_m must be positive, got {beyond_m}")
    return np.where(flagged & (mesh_t > 0), mesh_t + beyond_m, 0.0).astype(np.float32)
