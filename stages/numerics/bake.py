"""Texture baking: per-camera maps (albedo, world normals, ...) reprojected into a mesh's UV atlas.

Pure functions, arrays in and arrays out. Conventions (docs/CONTRACTS.md): world frame, metres; cameras
OpenCV (``x_cam = R x_world + t``, pixel ``i`` centred at coordinate ``i``); images ``(H, W, C)`` float32,
row 0 at the top. UVs follow :mod:`stages.numerics.mesh` (OBJ: v up; texel ``(r, c)`` of a ``T x T``
texture is centred at ``u = (c + 0.5) / T``, ``v = 1 - (r + 0.5) / T``).

:func:`bake_textures` works per texel of the atlas:

1. :func:`rasterize_atlas` gives each covered texel its 3D point and interpolated normal on the mesh.
2. Per camera, a depth map of the mesh itself (open3d ``RaycastingScene``, Embree) is rendered. A texel is
   a candidate in a view when it is in front of the camera, its normal faces the camera
   (``cos > min_cos``) and, of the four pixels its bilinear lookup reads, those that are valid and whose
   depth agrees with the texel's (within ``depth_tolerance_m`` plus the depth change a surface at that
   slant has over one pixel) carry at least half the bilinear weight. Lookups are renormalised over
   those pixels, so neither an occluder's nor an invalid pixel's value leaks in.
3. Each candidate gets a score ``cos * support * (f / z)^2``: frontal, fully supported and near (more
   pixels per square metre of surface) views rank first. The ``max_views`` best are blended with weights
   ``score - s_next`` (``s_next`` = the best unused view's score, floored at 0.1% of the score), so the
   blend changes continuously where the chosen set of views changes (no seams between view choices).
4. Names in ``normalize`` are renormalised to unit vectors; ``confidence`` is how well the texel is seen,
   ``1 - prod(1 - cos_i * support_i)`` over the views used, times the agreement between them,
   ``exp(-0.5 * sum_names (rms_name / agreement_scale)^2)`` (rms = weighted spread of the views' values).
5. Charts are dilated ``dilate_px`` texels into empty texels (mean of filled 8-neighbours, repeated), so
   bilinear lookups at chart borders do not pull black.

No output holds NaN or Inf.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from artifacts.atlas import Atlas
from stages.numerics.mesh import _check_mesh, face_normals, vertex_normals
from stages.numerics.raycast import mesh_scene, render_mesh

__all__ = ["BakeView", "BakeResult", "rasterize_atlas", "bake_textures", "gather_observations",
           "sample_texture", "texture_in_camera", "dilate_texture", "AtlasTextures", "atlas_textures"]

_MIN_TAP_SUPPORT = 0.5  # a view needs valid, depth-consistent pixels under half its bilinear weight


def _transform(points: np.ndarray, matrix: np.ndarray, offset=None) -> np.ndarray:
    """``points @ matrix.T (+ offset)`` for (N, 3) points and a small matrix, as elementwise column sums:
    a BLAS matmul with an inner size of 3 gains nothing and, with a multi-threaded BLAS on a busy
    machine, ran 4x slower overall (oversubscription)."""
    out = np.empty((len(points), matrix.shape[0]), np.float64)
    for r in range(matrix.shape[0]):
        col = points[:, 0] * matrix[r, 0] + points[:, 1] * matrix[r, 1] + points[:, 2] * matrix[r, 2]
        out[:, r] = col if offset is None else col + offset[r]
    return out
_TRI_BATCH_TEXELS = 1 << 21  # candidate texels per rasterization batch (memory bound)


@dataclass(frozen=True, eq=False)
class BakeView:
    """One camera's maps to bake.

    Attributes:
        images: name -> (H, W, C) float32 map (e.g. ``"albedo"`` linear sRGB, ``"normal"`` world normals);
            all views carry the same names with the same channel counts.
        valid: (H, W) bool, where the maps hold data (e.g. ``alpha > 0.5``).
        K: (3, 3) intrinsics (OpenCV).
        cam_from_world: (3, 4) ``[R | t]``, ``x_cam = R x_world + t``.
    """

    images: dict[str, np.ndarray]
    valid: np.ndarray
    K: np.ndarray
    cam_from_world: np.ndarray


@dataclass(frozen=True, eq=False)
class BakeResult:
    """Output of :func:`bake_textures`, all ``(T, T[, C])``.

    Attributes:
        textures: name -> (T, T, C) float32; 0 where no view saw the texel and dilation did not reach.
        view_count: (T, T) uint8, views blended per texel (0 = unseen, including dilated texels).
        confidence: (T, T) float32 in [0, 1] (0 where unseen).
        covered: (T, T) bool, texels whose centre lies on a chart.
        stats: ``coverage`` (covered texels seen by >= 1 view / covered texels), ``mean_view_count``
            (over covered texels), ``mean_view_count_seen`` (over seen ones), ``covered_texels``,
            ``dilated_texels``, ``seconds`` and the seconds of each step.
    """

    textures: dict[str, np.ndarray]
    view_count: np.ndarray
    confidence: np.ndarray
    covered: np.ndarray
    stats: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------- rasterization
def _check_atlas(vertices: np.ndarray, faces: np.ndarray, atlas: Atlas) -> None:
    if atlas.faces.ndim != 2 or atlas.faces.shape != faces.shape:
        raise ValueError(f"atlas has {atlas.faces.shape} faces, the mesh {faces.shape}: atlas of another mesh?")
    if atlas.uvs.shape != (len(atlas.vmapping), 2):
        raise ValueError(f"atlas uvs {atlas.uvs.shape} do not match vmapping ({len(atlas.vmapping)},)")
    if len(atlas.vmapping) and (atlas.vmapping.min() < 0 or atlas.vmapping.max() >= len(vertices)):
        raise ValueError("atlas.vmapping indexes vertices the mesh does not have")


def rasterize_atlas(vertices: np.ndarray, faces: np.ndarray, atlas: Atlas,
                    texture_size: int) -> dict[str, np.ndarray]:
    """Which mesh point each texel centre of a ``T x T`` texture lies on.

    Args:
        vertices: (V, 3) metres; faces: (F, 3) int, the mesh ``atlas`` was made from.
        atlas: its :class:`~artifacts.atlas.Atlas`.
        texture_size: ``T``.

    Returns:
        ``position`` (T, T, 3) float32 world point, ``normal`` (T, T, 3) float32 unit interpolated vertex
        normal, ``face`` (T, T) int32 face index (-1 empty), ``barycentric`` (T, T, 3) float32,
        ``covered`` (T, T) bool; 0 where empty. Where charts touch, the last face drawn wins.
    """
    v, f = _check_mesh(vertices, faces)
    _check_atlas(v, f, atlas)
    size = int(texture_size)
    if size < 2:
        raise ValueError(f"texture_size must be >= 2, got {texture_size}")
    uv = atlas.uvs.astype(np.float64)
    xy = np.stack([uv[:, 0] * size, (1.0 - uv[:, 1]) * size], axis=1)  # continuous texel coords
    tri = xy[atlas.faces.astype(np.int64)]  # (F, 3, 2)
    lo = np.clip(np.ceil(tri.min(axis=1) - 0.5), 0, size - 1).astype(np.int64)  # first texel centre inside
    hi = np.clip(np.floor(tri.max(axis=1) - 0.5), 0, size - 1).astype(np.int64)
    ext = hi - lo + 1
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    ok = (ext > 0).all(axis=1) & (np.abs(area2) > 1e-12)

    face_map = np.full(size * size, -1, np.int32)
    bary_map = np.zeros((size * size, 3), np.float32)
    span = np.maximum(ext.max(axis=1), 1)
    bucket = np.where(ok, np.ceil(np.log2(span)).astype(int), -1)
    eps = 1e-7
    for level in np.unique(bucket[bucket >= 0]):
        side = 1 << int(level)
        ids = np.flatnonzero(bucket == level)
        offs = np.arange(side)
        per_batch = max(1, _TRI_BATCH_TEXELS // (side * side))
        for start in range(0, len(ids), per_batch):
            t = ids[start:start + per_batch]
            cols = lo[t, 0][:, None, None] + offs[None, None, :]  # (n, 1, s)
            rows = lo[t, 1][:, None, None] + offs[None, :, None]  # (n, s, 1)
            px = cols + 0.5
            py = rows + 0.5
            ax, ay = a[t, 0][:, None, None], a[t, 1][:, None, None]
            bx, by = b[t, 0][:, None, None], b[t, 1][:, None, None]
            cx, cy = c[t, 0][:, None, None], c[t, 1][:, None, None]
            inv = 1.0 / area2[t][:, None, None]
            l0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) * inv
            l1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) * inv
            l2 = 1.0 - l0 - l1
            inside = (l0 >= -eps) & (l1 >= -eps) & (l2 >= -eps)
            inside &= (cols <= hi[t, 0][:, None, None]) & (rows <= hi[t, 1][:, None, None])
            n_idx, r_idx, c_idx = np.nonzero(inside)
            flat = rows[n_idx, r_idx, 0] * size + cols[n_idx, 0, c_idx]
            face_map[flat] = t[n_idx]
            bary_map[flat] = np.stack([l0[inside], l1[inside], l2[inside]], axis=1)

    covered = face_map >= 0
    idx = np.flatnonzero(covered)
    fid = face_map[idx].astype(np.int64)
    bary = np.clip(bary_map[idx].astype(np.float64), 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    tri_vertices = atlas.vmapping[atlas.faces[fid].astype(np.int64)]  # (n, 3) input vertex ids
    position = np.einsum("nk,nkd->nd", bary, v[tri_vertices].astype(np.float64))
    vn = vertex_normals(v, f)
    normal = np.einsum("nk,nkd->nd", bary, vn[tri_vertices].astype(np.float64))
    norm = np.linalg.norm(normal, axis=1, keepdims=True)
    fallback = face_normals(v, f)[0][fid]  # where vertex normals cancel (folds), the face's own
    normal = np.where(norm > 1e-8, normal / np.maximum(norm, 1e-12), fallback)

    out_position = np.zeros((size * size, 3), np.float32)
    out_normal = np.zeros((size * size, 3), np.float32)
    out_position[idx] = position
    out_normal[idx] = normal
    bary_out = np.zeros((size * size, 3), np.float32)
    bary_out[idx] = bary
    return {"position": out_position.reshape(size, size, 3), "normal": out_normal.reshape(size, size, 3),
            "face": face_map.reshape(size, size), "barycentric": bary_out.reshape(size, size, 3),
            "covered": covered.reshape(size, size)}


# ---------------------------------------------------------------------------------------- sampling
def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a texture at OBJ-convention UVs (v up), clamping at the edges.

    Args:
        texture: (H, W) or (H, W, C).
        uv: (..., 2) in [0, 1] (outside is clamped to the edge texels).

    Returns:
        (...,) or (..., C) float32.
    """
    tex = np.asarray(texture)
    uv = np.asarray(uv, np.float64)
    if tex.ndim not in (2, 3):
        raise ValueError(f"texture must be (H, W) or (H, W, C), got shape {tex.shape}")
    if uv.shape[-1:] != (2,):
        raise ValueError(f"uv must be (..., 2), got shape {uv.shape}")
    h, w = tex.shape[:2]
    x = np.clip(uv[..., 0] * w - 0.5, 0.0, w - 1.0)
    y = np.clip((1.0 - uv[..., 1]) * h - 0.5, 0.0, h - 1.0)
    return _bilinear(tex, x, y)


def texture_in_camera(scene, uv_faces: np.ndarray, uvs: np.ndarray, texture: np.ndarray, K: np.ndarray,
                      cam_from_world: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """A texture seen by a camera through a textured mesh: each pixel's ray hits the mesh, its UV is
    interpolated over the hit face and the texture is looked up there (:func:`sample_texture`).

    Args:
        scene: ray-casting scene of the mesh (:func:`stages.numerics.raycast.mesh_scene`).
        uv_faces: (F, 3) per-corner indices into ``uvs``, face for face with the scene's faces.
        uvs: (U, 2) OBJ-convention texture coordinates.
        texture: (Ht, Wt) or (Ht, Wt, C).
        K, cam_from_world: the camera; height, width: its image size.

    Returns:
        ``(values (H, W[, C]) float32 (0 where no hit), hit (H, W) bool)``.
    """
    from stages.numerics.raycast import render_uvs

    tex = np.asarray(texture)
    if tex.ndim not in (2, 3):
        raise ValueError(f"texture must be (H, W) or (H, W, C), got shape {tex.shape}")
    uv, hit = render_uvs(scene, uv_faces, uvs, K, cam_from_world, height, width)
    values = sample_texture(tex, uv.reshape(-1, 2)).reshape((int(height), int(width)) + tex.shape[2:])
    hit_b = hit.reshape((int(height), int(width)) + (1,) * (tex.ndim - 2))
    return np.where(hit_b, values, 0.0).astype(np.float32), hit


def sample_pixels(image: np.ndarray, x: np.ndarray, y: np.ndarray, dtype: type = np.float32) -> np.ndarray:
    """``image`` (H, W) or (H, W, C) read bilinearly at pixel coordinates ``x``, ``y`` (...,) (pixel centres at
    integers; outside the frame clamped to its edge pixels): (...,) or (..., C), interpolated in ``dtype``."""
    h, w = np.asarray(image).shape[:2]
    return _bilinear(np.asarray(image), np.clip(np.asarray(x, np.float64), 0.0, w - 1.0),
                     np.clip(np.asarray(y, np.float64), 0.0, h - 1.0), dtype)


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray, dtype: type = np.float32) -> np.ndarray:
    """Bilinear image lookup at pixel coordinates already clamped to [0, W-1] x [0, H-1], in ``dtype``."""
    h, w = image.shape[:2]
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2) if w > 1 else np.zeros(x.shape, np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2) if h > 1 else np.zeros(y.shape, np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    if image.ndim == 3:
        fx, fy = fx[..., None], fy[..., None]
    img = image.astype(dtype, copy=False)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(dtype)


# ------------------------------------------------------------------------------------------- dilation
def dilate_texture(textures: dict[str, np.ndarray], filled: np.ndarray,
                   iterations: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Grow filled regions into empty texels: each pass sets every empty texel that has filled
    8-neighbours to their mean, ``iterations`` times.

    Args:
        textures: name -> (T, T[, C]) arrays (values of empty texels are ignored).
        filled: (T, T) bool.

    Returns:
        the dilated textures (float32, 0 where still empty) and the new filled mask.
    """
    filled = np.asarray(filled, bool).copy()
    out = {}
    for name, tex in textures.items():
        t = np.asarray(tex, np.float32)
        out[name] = np.where(filled[..., None] if t.ndim == 3 else filled, t, 0.0).astype(np.float32)
    for _ in range(int(iterations)):
        pad = np.pad(filled, 1)
        count = np.zeros(filled.shape, np.float32)
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                if dy != 1 or dx != 1:
                    count += pad[dy:dy + filled.shape[0], dx:dx + filled.shape[1]]
        grow = ~filled & (count > 0)
        if not grow.any():
            break
        for name, t in out.items():
            t3 = t if t.ndim == 3 else t[..., None]
            pad_t = np.pad(t3, ((1, 1), (1, 1), (0, 0)))  # empty texels hold 0, so sums count filled only
            acc = np.zeros_like(t3)
            for dy in (0, 1, 2):
                for dx in (0, 1, 2):
                    if dy != 1 or dx != 1:
                        acc += pad_t[dy:dy + filled.shape[0], dx:dx + filled.shape[1]]
            t3[grow] = acc[grow] / count[grow][:, None]
        filled |= grow
    return out, filled


# -------------------------------------------------------------------------------------------- baking
def _check_views(views: list[BakeView]) -> dict[str, int]:
    if not views:
        raise ValueError("bake_textures needs at least one view")
    names = None
    for i, view in enumerate(views):
        if not isinstance(view, BakeView):
            raise ValueError(f"views[{i}] is a {type(view).__name__}, expected BakeView")
        valid = np.asarray(view.valid)
        if valid.ndim != 2:
            raise ValueError(f"views[{i}].valid must be (H, W), got shape {valid.shape}")
        if np.shape(view.K) != (3, 3) or np.shape(view.cam_from_world) != (3, 4):
            raise ValueError(f"views[{i}]: K must be (3, 3) and cam_from_world (3, 4), got "
                             f"{np.shape(view.K)} and {np.shape(view.cam_from_world)}")
        if not view.images:
            raise ValueError(f"views[{i}] has no images")
        channels = {}
        for name, image in view.images.items():
            if image.ndim != 3 or image.shape[:2] != valid.shape:
                raise ValueError(f"views[{i}].images[{name!r}] must be (H, W, C) with (H, W) = "
                                 f"{valid.shape}, got {image.shape}")
            channels[name] = image.shape[2]
        if names is None:
            names = channels
        elif channels != names:
            raise ValueError(f"views[{i}] images {channels} differ from views[0]'s {names}")
    return names


def _view_lookup(view: BakeView, depth_valid: np.ndarray, points: np.ndarray, normals: np.ndarray,
                 n_dot_p: np.ndarray, p_sq: np.ndarray, min_cos: float, depth_tolerance_m: float):
    """Project texel points into one view; return (candidate index, score, cos*support, taps, weights).

    ``depth_valid`` is the view's mesh depth map with ``inf`` where its maps are invalid; ``n_dot_p``
    and ``p_sq`` are the texels' ``normal . point`` and ``|point|^2``, so the culling tests cost two
    matrix-vector products per view. taps: (n, 4) flat pixel indices; weights: (n, 4) bilinear weights
    over the valid, depth-consistent taps, renormalised to sum 1.
    """
    h, w = depth_valid.shape
    cam = np.asarray(view.cam_from_world, np.float64)
    rot, trans = cam[:, :3], cam[:, 3]
    k = np.asarray(view.K, np.float64)
    centre = -rot.T @ trans
    z = _transform(points, rot[2:3], trans[2:3])[:, 0]
    dist = np.sqrt(np.maximum(p_sq - 2.0 * _transform(points, centre[None])[:, 0] + centre @ centre, 1e-24))
    cos = (_transform(normals, centre[None])[:, 0] - n_dot_p) / dist
    cand = np.flatnonzero((z > 1e-6) & (cos > min_cos))
    p, z, cos = points[cand], z[cand], cos[cand]
    pix = _transform(_transform(p, rot, trans), k)
    u = pix[:, 0] / pix[:, 2]
    v = pix[:, 1] / pix[:, 2]
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    cand, z, cos, u, v = cand[inside], z[inside], cos[inside], u[inside], v[inside]
    x0 = np.minimum(u.astype(np.int64), max(w - 2, 0))  # u >= 0: truncation is floor
    y0 = np.minimum(v.astype(np.int64), max(h - 2, 0))
    fx, fy = (u - x0).astype(np.float32), (v - y0).astype(np.float32)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    taps = np.stack([y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1], axis=1)
    weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    focal = float(np.sqrt(abs(k[0, 0] * k[1, 1])))
    tan = np.sqrt(np.maximum(1.0 - cos ** 2, 0.0)) / cos
    tolerance = (depth_tolerance_m + (z / focal) * tan).astype(np.float32)  # + a slant's depth change over a pixel
    ok = np.abs(depth_valid.reshape(-1)[taps] - z.astype(np.float32)[:, None]) <= tolerance[:, None]  # inf fails
    weights *= ok
    support = weights.sum(axis=1)
    keep = support >= _MIN_TAP_SUPPORT
    taps, weights = taps[keep], weights[keep] / support[keep, None]
    cand, z, cos, support = cand[keep], z[keep], cos[keep], support[keep].astype(np.float64)
    score = cos * support * (focal / z) ** 2
    return cand, score, cos * support, taps, weights


def _check_lookup(min_cos: float, depth_tolerance_m: float) -> None:
    if not -1.0 <= min_cos < 1.0:
        raise ValueError(f"min_cos must be in [-1, 1), got {min_cos}")
    if not depth_tolerance_m > 0:
        raise ValueError(f"depth_tolerance_m must be > 0, got {depth_tolerance_m}")


def _usable_depth_maps(views: list[BakeView], scene) -> list[np.ndarray]:
    """Each view's depth map of the mesh, ``inf`` where its maps are invalid or the mesh is missed (one
    lookup then tests both); a pixel with a non-finite value in any map counts as invalid."""
    depths = []
    for view in views:
        seen = render_mesh(None, None, view.K, view.cam_from_world, *view.valid.shape, scene=scene)
        usable = (np.asarray(view.valid, bool) & seen["hit"]
                  & np.all([np.isfinite(im).all(axis=2) for im in view.images.values()], axis=0))
        depths.append(np.where(usable, seen["depth_m"], np.float32(np.inf)))
    return depths


def _rank_views(views, depths, points, normals, n_dot_p, p_sq, min_cos, depth_tolerance_m):
    """Pass 1: every view's score per point (0 = not a candidate), (V, N) float32, and the views' order
    per point, best first (ties keep view order), (V, N)."""
    scores = np.zeros((len(views), len(points)), np.float32)
    for i, view in enumerate(views):
        cand, score, _, _, _ = _view_lookup(view, depths[i], points, normals, n_dot_p, p_sq, min_cos,
                                            depth_tolerance_m)
        scores[i, cand] = score
    return np.argsort(-scores, axis=0, kind="stable"), scores


def gather_observations(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray,
                        views: list[BakeView], max_views: int, depth_tolerance_m: float = 0.01,
                        min_cos: float = 0.2) -> dict[str, np.ndarray]:
    """Each surface point's values in the ``max_views`` views that see it best, unblended (what a per-point
    fit across views, e.g. of roughness, needs); same visibility and ranking as :func:`bake_textures`.

    Args:
        vertices: (V, 3), faces: (F, 3): the mesh the points lie on (for the per-view depth tests).
        points: (P, 3) surface points; normals: (P, 3) unit normals there.
        views: cameras with their images (:class:`BakeView`), all with the same image names.
        max_views: ``K``, views kept per point (the best by score; fewer where fewer see it).
        depth_tolerance_m, min_cos: as :func:`bake_textures`.

    Returns:
        dict with ``values``: name -> (P, K, C) float32 (0 where invalid); ``valid``: (P, K) bool;
        ``view_index``: (P, K) int32 into ``views`` (-1 where invalid); ``view_dirs``: (P, K, 3) unit
        directions from the point towards the camera (0 where invalid); ``cos``: (P, K) float32.
    """
    v, f = _check_mesh(vertices, faces)
    channels = _check_views(views)
    pts = np.asarray(points, np.float64)
    nrm = np.asarray(normals, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or nrm.shape != pts.shape:
        raise ValueError(f"points and normals must both be (P, 3), got {pts.shape} and {nrm.shape}")
    if int(max_views) < 1:
        raise ValueError(f"max_views must be >= 1, got {max_views}")
    _check_lookup(min_cos, depth_tolerance_m)
    min_cos = max(float(min_cos), 1e-3)
    k = min(int(max_views), len(views))
    n_points = len(pts)
    depths = _usable_depth_maps(views, mesh_scene(v, f))
    n_dot_p = np.einsum("nd,nd->n", nrm, pts)
    p_sq = np.einsum("nd,nd->n", pts, pts)
    order, scores = _rank_views(views, depths, pts, nrm, n_dot_p, p_sq, min_cos, depth_tolerance_m)
    slot = np.full((len(views), n_points), -1, np.int64)  # which of the K slots a (view, point) fills
    for rank in range(k):
        good = np.take_along_axis(scores, order[rank:rank + 1], axis=0)[0] > 0
        slot[order[rank, good], np.flatnonzero(good)] = rank
    del order, scores
    values = {name: np.zeros((n_points, k, c), np.float32) for name, c in channels.items()}
    valid = np.zeros((n_points, k), bool)
    view_index = np.full((n_points, k), -1, np.int32)
    view_dirs = np.zeros((n_points, k, 3), np.float32)
    cos_out = np.zeros((n_points, k), np.float32)
    for i, view in enumerate(views):
        sel = np.flatnonzero(slot[i] >= 0)
        if not len(sel):
            continue
        cand, _, _, taps, weights = _view_lookup(view, depths[i], pts[sel], nrm[sel], n_dot_p[sel], p_sq[sel],
                                                 min_cos, depth_tolerance_m)
        idx = sel[cand]
        ranks = slot[i, idx]
        for name, c in channels.items():
            image = np.asarray(view.images[name], np.float32).reshape(-1, c)
            gathered = np.nan_to_num(image[taps], nan=0.0, posinf=0.0, neginf=0.0)
            values[name][idx, ranks] = np.einsum("nk,nkc->nc", weights, gathered)
        rot, trans = np.asarray(view.cam_from_world, np.float64)[:, :3], np.asarray(view.cam_from_world)[:, 3]
        to_cam = (-rot.T @ trans)[None] - pts[idx]
        to_cam /= np.maximum(np.linalg.norm(to_cam, axis=1, keepdims=True), 1e-12)
        view_dirs[idx, ranks] = to_cam
        cos_out[idx, ranks] = np.einsum("nd,nd->n", nrm[idx], to_cam)
        valid[idx, ranks] = True
        view_index[idx, ranks] = i
    return {"values": values, "valid": valid, "view_index": view_index, "view_dirs": view_dirs, "cos": cos_out}


def bake_textures(vertices: np.ndarray, faces: np.ndarray, atlas: Atlas, views: list[BakeView],
                  texture_size: int, max_views: int = 3, depth_tolerance_m: float = 0.01,
                  min_cos: float = 0.2, normalize: tuple[str, ...] = ("normal",), dilate_px: int = 4,
                  agreement_scale: float = 0.1) -> BakeResult:
    """Bake per-camera maps into ``T x T`` textures of the atlas (see the module docstring for the method).

    Args:
        vertices: (V, 3) metres; faces: (F, 3) int; atlas: the mesh's :class:`~artifacts.atlas.Atlas`.
        views: cameras with their maps (:class:`BakeView`), all with the same image names.
        texture_size: ``T``.
        max_views: views blended per texel (the best by score).
        depth_tolerance_m: a texel is visible where the mesh's depth map agrees with its depth within
            this (plus the slant allowance).
        min_cos: least cosine between the texel's normal and the direction to the camera.
        normalize: image names renormalised to unit vectors after blending and dilation (normals);
            names the views do not carry are ignored.
        dilate_px: texels the charts grow into empty space.
        agreement_scale: spread between views (in the maps' units) at which confidence falls to
            ``exp(-0.5)`` of the seen-term.

    Returns:
        :class:`BakeResult`.
    """
    t_start = time.perf_counter()
    v, f = _check_mesh(vertices, faces)
    channels = _check_views(views)
    if int(max_views) < 1:
        raise ValueError(f"max_views must be >= 1, got {max_views}")
    _check_lookup(min_cos, depth_tolerance_m)
    if agreement_scale <= 0:
        raise ValueError("agreement_scale must be > 0")
    normalize = tuple(n for n in normalize if n in channels)  # e.g. the default "normal" in an albedo-only bake
    min_cos = max(float(min_cos), 1e-3)  # the slant allowance needs cos > 0
    timings = {}

    t0 = time.perf_counter()
    raster = rasterize_atlas(v, f, atlas, texture_size)
    size = int(texture_size)
    texel = np.flatnonzero(raster["covered"].reshape(-1))
    points = raster["position"].reshape(-1, 3)[texel].astype(np.float64)
    normals = raster["normal"].reshape(-1, 3)[texel].astype(np.float64)
    timings["rasterize_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    depths = _usable_depth_maps(views, mesh_scene(v, f))
    n_dot_p = np.einsum("nd,nd->n", normals, points)
    p_sq = np.einsum("nd,nd->n", points, points)
    timings["depth_maps_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    k = min(int(max_views), len(views))
    chosen, next_best = _choose_views(views, depths, points, normals, n_dot_p, p_sq, min_cos, depth_tolerance_m, k)
    timings["select_s"] = time.perf_counter() - t0

    # Pass 2: blend the chosen views.
    t0 = time.perf_counter()
    sums = _BlendSums.zeros(len(texel), sum(channels.values()))
    for i, view in enumerate(views):
        sel = np.flatnonzero(chosen[i])
        if len(sel):
            _add_view(sums, view, depths[i], sel, points, normals, n_dot_p, p_sq, next_best, channels, normalize,
                      min_cos, depth_tolerance_m)
    mean, seen_mask, confidence = sums.mean_and_confidence(channels, agreement_scale)
    timings["blend_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    textures, filled, grown = _texture_images(mean, seen_mask, texel, size, channels, normalize, dilate_px)
    timings["dilate_s"] = time.perf_counter() - t0

    count = sums.count
    n_texels = len(texel)
    view_count = np.zeros(size * size, np.uint8)
    view_count[texel] = np.where(seen_mask, np.minimum(count, 255), 0).astype(np.uint8)
    conf = np.zeros(size * size, np.float32)
    conf[texel] = np.clip(np.nan_to_num(confidence), 0.0, 1.0)
    n_seen = int(seen_mask.sum())
    stats = {"covered_texels": int(n_texels), "seen_texels": n_seen,
             "coverage": n_seen / n_texels if n_texels else 0.0,
             "mean_view_count": float(count[seen_mask].sum() / n_texels) if n_texels else 0.0,
             "mean_view_count_seen": float(count[seen_mask].mean()) if n_seen else 0.0,
             "dilated_texels": int(grown.sum() - filled.sum()), "views": len(views), **timings,
             "seconds": time.perf_counter() - t_start}
    return BakeResult(textures=textures, view_count=view_count.reshape(size, size),
                      confidence=conf.reshape(size, size), covered=raster["covered"], stats=stats)


def _choose_views(views: list[BakeView], depths: list, points: np.ndarray, normals: np.ndarray,
                  n_dot_p: np.ndarray, p_sq: np.ndarray, min_cos: float, depth_tolerance_m: float,
                  k: int) -> tuple[np.ndarray, np.ndarray]:
    """Pass 1: the ``k`` best-scoring views of each texel (points, normals (N, 3)) that see it, (V, N) bool,
    and the score of the best view left out, (N,) (0 when every view is chosen)."""
    order, scores = _rank_views(views, depths, points, normals, n_dot_p, p_sq, min_cos, depth_tolerance_m)
    chosen = np.zeros(scores.shape, bool)
    np.put_along_axis(chosen, order[:k], True, axis=0)
    chosen &= scores > 0
    next_best = (np.take_along_axis(scores, order[k:k + 1], axis=0)[0] if len(views) > k
                 else np.zeros(len(points), np.float32))
    return chosen, next_best


@dataclass
class _BlendSums:
    """Weighted sums over the views blended into each texel (N texels, C channels of all maps side by side)."""

    acc: np.ndarray  # (N, C) sum of weight x value
    acc2: np.ndarray  # (N, C) sum of weight x value^2
    wsum: np.ndarray  # (N,) sum of weights
    log_unseen: np.ndarray  # (N,) sum of log(1 - seen): log of the chance that no view saw the texel
    count: np.ndarray  # (N,) int32 views blended

    @classmethod
    def zeros(cls, n_texels: int, n_channels: int) -> "_BlendSums":
        return cls(acc=np.zeros((n_texels, n_channels), np.float64),
                   acc2=np.zeros((n_texels, n_channels), np.float64), wsum=np.zeros(n_texels, np.float64),
                   log_unseen=np.zeros(n_texels, np.float64), count=np.zeros(n_texels, np.int32))

    def mean_and_confidence(self, channels: dict[str, int],
                            agreement_scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The blended values (N, C), where any view was blended (N,) bool, and the confidence (N,): the chance
        that a view saw the texel times ``exp(-0.5 spread)``, the spread being the views' variance in units of
        ``agreement_scale^2`` (mean over each map's channels, summed over the maps)."""
        seen_mask = (self.count > 0) & (self.wsum > 0)
        mean = np.divide(self.acc, self.wsum[:, None], out=np.zeros_like(self.acc), where=seen_mask[:, None])
        var = np.clip(np.divide(self.acc2, self.wsum[:, None], out=np.zeros_like(self.acc2),
                                where=seen_mask[:, None]) - mean ** 2, 0.0, None)
        spread = 0.0
        start = 0
        for c in channels.values():
            spread = spread + var[:, start:start + c].mean(axis=1) / agreement_scale ** 2
            start += c
        confidence = np.where(seen_mask, (1.0 - np.exp(self.log_unseen)) * np.exp(-0.5 * spread), 0.0)
        return mean, seen_mask, confidence


def _add_view(sums: _BlendSums, view: BakeView, depth, sel: np.ndarray, points: np.ndarray, normals: np.ndarray,
              n_dot_p: np.ndarray, p_sq: np.ndarray, next_best: np.ndarray, channels: dict[str, int],
              normalize: tuple[str, ...], min_cos: float, depth_tolerance_m: float) -> None:
    """Blend ``view`` into the texels ``sel`` (indices) it was chosen for: weighted by its score's margin over
    the best view left out; texels it does not see after all, or where its maps are not finite, get nothing."""
    cand, score, seen, taps, weights = _view_lookup(view, depth, points[sel], normals[sel], n_dot_p[sel],
                                                    p_sq[sel], min_cos, depth_tolerance_m)
    idx = sel[cand]
    blend_w = np.maximum(score - next_best[idx], 1e-3 * score)
    values = []
    for name, c in channels.items():
        image = np.asarray(view.images[name], np.float32).reshape(-1, c)
        gathered = image[taps]
        gathered = np.where(np.isfinite(gathered), gathered, 0.0)  # 0-weight taps must not spread NaN
        sample = np.einsum("nk,nkc->nc", weights, gathered).astype(np.float64)
        if name in normalize:
            norm = np.linalg.norm(sample, axis=1, keepdims=True)
            sample = np.divide(sample, norm, out=np.zeros_like(sample), where=norm > 1e-8)
        values.append(sample)
    values = np.concatenate(values, axis=1)
    finite = np.all(np.isfinite(values), axis=1)  # a non-finite map value counts as invalid
    idx, blend_w, values, seen = idx[finite], blend_w[finite], values[finite], seen[finite]
    sums.acc[idx] += blend_w[:, None] * values
    sums.acc2[idx] += blend_w[:, None] * values ** 2
    sums.wsum[idx] += blend_w
    sums.log_unseen[idx] += np.log(np.clip(1.0 - seen, 1e-12, 1.0))
    sums.count[idx] += 1


def _texture_images(mean: np.ndarray, seen_mask: np.ndarray, texel: np.ndarray, size: int,
                    channels: dict[str, int], normalize: tuple[str, ...],
                    dilate_px: int) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """The blended values (N, C) of the seen texels (``texel``: their flat indices) as ``size x size`` images
    per map, dilated by ``dilate_px``, ``normalize``'s maps renormalised, nothing non-finite; the texels
    filled before dilation (size * size,) bool and after it (size, size) bool."""
    textures = {}
    start = 0
    for name, c in channels.items():
        tex = np.zeros((size * size, c), np.float32)
        tex[texel[seen_mask]] = mean[seen_mask, start:start + c]
        textures[name] = tex.reshape(size, size, c)
        start += c
    filled = np.zeros(size * size, bool)
    filled[texel[seen_mask]] = True
    textures, grown = dilate_texture(textures, filled.reshape(size, size), dilate_px)
    for name in normalize:
        tex = textures[name]
        norm = np.linalg.norm(tex, axis=2, keepdims=True)
        textures[name] = np.divide(tex, norm, out=np.zeros_like(tex), where=norm > 1e-6).astype(np.float32)
    for name in channels:  # belt and braces: nothing non-finite leaves
        textures[name] = np.nan_to_num(textures[name], nan=0.0, posinf=0.0, neginf=0.0)
    return textures, filled, grown


@dataclass(frozen=True)
class AtlasTextures:
    """The textures stage's mesh, its UV atlas and the textures baked into it."""

    vertices: np.ndarray
    """(V, 3) the decimated mesh's vertices."""
    faces: np.ndarray
    """(F, 3) its faces."""
    atlas: Atlas
    """Its UV atlas (xatlas)."""
    baked: BakeResult
    """The albedo and normal textures with their view counts, confidence and coverage."""
    atlas_seconds: float
    """Time of the decimation and the atlas."""
    bake_seconds: float
    """Time of the baking."""


def atlas_textures(vertices: np.ndarray, faces: np.ndarray, views: list[BakeView], atlas_faces: int,
                   texture_size: int, padding: int, max_views: int, depth_tolerance_m: float,
                   min_cos: float, max_chart_area_m2: float = 0.0) -> AtlasTextures:
    """The mesh (V, 3) / (F, 3) decimated to ``atlas_faces``, its UV atlas of ``texture_size`` texels with
    ``padding`` between charts and charts of at most ``max_chart_area_m2`` (0: no limit), and the views' images
    baked into it (:func:`bake_textures`: each texel blends its ``max_views`` most frontal views within
    ``depth_tolerance_m`` of the mesh and above ``min_cos``)."""
    from stages.numerics.mesh import decimate, uv_atlas

    start = time.perf_counter()
    vertices, faces = decimate(vertices, faces, atlas_faces)
    atlas = uv_atlas(vertices, faces, resolution=texture_size, padding=padding, max_chart_area=max_chart_area_m2)
    atlas_s = time.perf_counter() - start
    start = time.perf_counter()
    baked = bake_textures(vertices, faces, atlas, views, texture_size, max_views=max_views,
                          depth_tolerance_m=depth_tolerance_m, min_cos=min_cos)
    return AtlasTextures(vertices=vertices, faces=faces, atlas=atlas, baked=baked, atlas_seconds=atlas_s,
                         bake_seconds=time.perf_counter() - start)
