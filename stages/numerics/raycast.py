"""Rays of a pinhole camera and ray casting of a triangle mesh (open3d / Embree).

Pure numerics: arrays in, arrays out. Cameras follow docs/CONTRACTS.md (OpenCV, ``x_cam = R x_world + t``,
pixel index ``i`` at continuous coordinate ``u = i``).
"""
from __future__ import annotations

import numpy as np


def _check_camera(K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    K = np.asarray(K, dtype=np.float64)
    P = np.asarray(cam_from_world, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    if P.shape[-2:] != (3, 4) and P.shape != (4, 4):
        raise ValueError(f"cam_from_world must be (3, 4) or (4, 4), got {P.shape}")
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height}x{width}")
    return K, P[:3, :4]


def camera_rays(K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int,
                pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World-space rays through pixel centres (:meth:`artifacts.camera.Camera.rays_with_depth_scale`).

    Args:
        K: (3, 3) intrinsics. cam_from_world: (3, 4) ``[R | t]``.
        pixels: optional (N, 2) float pixel coordinates (u, v); default every pixel, row-major.

    Returns:
        origins (N, 3) float64 (the camera centre), directions (N, 3) float64 unit, and
        z_per_t (N,) float64: camera depth per unit of ray length (depth_m = t * z_per_t).
    """
    from artifacts.camera import Camera

    _check_camera(K, cam_from_world, height, width)
    return Camera(K, cam_from_world, width, height).rays_with_depth_scale(pixels)


def mesh_scene(vertices: np.ndarray, faces: np.ndarray):
    """An open3d ``RaycastingScene`` of a triangle mesh, to render it from many cameras.

    Args:
        vertices: (V, 3) world positions (metres). faces: (F, 3) vertex indices.
    """
    import open3d as o3d

    vertices = np.asarray(vertices, dtype=np.float32)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"expected vertices (V, 3) and faces (F, 3), got {vertices.shape} and {faces.shape}")
    if len(faces) == 0:
        raise ValueError("render_mesh: the mesh has no faces")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
    return scene


def render_mesh(vertices: np.ndarray | None, faces: np.ndarray | None, K: np.ndarray, cam_from_world: np.ndarray,
                height: int, width: int, scene=None) -> dict[str, np.ndarray]:
    """Depth, geometric normal and face id of a mesh seen by a pinhole camera.

    Args:
        vertices: (V, 3) world positions (metres). faces: (F, 3) vertex indices. Both may be None when
            ``scene`` (from :func:`mesh_scene`) is given.
        K, cam_from_world: the camera. height, width: image size in pixels.

    Returns:
        ``depth_m`` (H, W) float32 camera z (0 where no hit), ``normals_world`` (H, W, 3) float32 unit face
        normals turned toward the camera (0 where no hit), ``face`` (H, W) int64 (-1 where no hit),
        ``hit`` (H, W) bool.
    """
    import open3d as o3d

    if scene is None:
        scene = mesh_scene(vertices, faces)
    origins, directions, z_per_t = camera_rays(K, cam_from_world, height, width)
    rays = np.concatenate([origins, directions], axis=-1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = ans["t_hit"].numpy()
    face = ans["primitive_ids"].numpy().astype(np.int64)
    hit = np.isfinite(t_hit)
    face[~hit] = -1
    normals = ans["primitive_normals"].numpy().astype(np.float32)
    facing = np.sum(normals * directions.astype(np.float32), axis=-1) > 0
    normals[facing] *= -1.0
    normals[~hit] = 0.0
    depth = np.where(hit, np.where(hit, t_hit, 0.0) * z_per_t, 0.0).astype(np.float32)
    return {"depth_m": depth.reshape(height, width), "normals_world": normals.reshape(height, width, 3),
            "face": face.reshape(height, width), "hit": hit.reshape(height, width)}


def pixel_coverage(K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int, samples: int,
                   scene, edges_only: bool = True, chunk_pixels: int = 1 << 16,
                   centre_hit: np.ndarray | None = None) -> np.ndarray:
    """Share of each pixel's square that a mesh covers, seen by a pinhole camera.

    A camera pixel integrates the light over its square (the simulator's camera averages a grid of rays per
    pixel): at a silhouette a pixel is partly subject, partly background. This casts a regular ``samples x
    samples`` grid of rays through a pixel's square (pixel ``i`` spans ``[i - 1/2, i + 1/2]``; the rays sit
    at the centres of the grid's cells) and counts the hits.

    With ``edges_only`` the grid is cast only where the pixel-centre rays of a 3 x 3 neighbourhood disagree
    (some hit, some miss); elsewhere the coverage is the centre ray's 0 or 1. Cost: one ray per pixel plus
    ``samples^2`` per edge pixel (a few percent of them) instead of ``samples^2`` per pixel; it misses
    only features that lie wholly between pixel centres (a hole or a sliver narrower than a pixel).

    Args:
        K, cam_from_world: the camera (:func:`camera_rays`). height, width: image size in pixels.
        samples: rays per pixel side, >= 1 (1: the pixel centre's ray only, coverage 0 or 1).
        scene: :func:`mesh_scene` of the mesh.
        edges_only: cast the grid only at the silhouette (above); False: at every pixel.
        chunk_pixels: pixels whose grids are cast at once (bounds the memory).
        centre_hit: (H, W) bool, the pixel-centre rays' hits when the caller has rendered them already
            (:func:`render_mesh`'s ``hit``); None casts them.

    Returns:
        (H, W) float32 in [0, 1], multiples of ``1 / samples^2``.
    """
    K, P = _check_camera(K, cam_from_world, height, width)
    if int(samples) != samples or samples < 1:
        raise ValueError(f"samples must be an integer >= 1, got {samples!r}")
    if int(chunk_pixels) < 1:
        raise ValueError(f"chunk_pixels must be >= 1, got {chunk_pixels!r}")
    s = int(samples)
    if centre_hit is None:
        centre = render_mesh(None, None, K, P, height, width, scene=scene)["hit"]
    else:
        centre = np.asarray(centre_hit).astype(bool, copy=False)
        if centre.shape != (height, width):
            raise ValueError(f"centre_hit must be ({height}, {width}), got {centre.shape}")
    coverage = centre.astype(np.float32)
    if s == 1:
        return coverage
    if edges_only:
        from scipy.ndimage import binary_dilation

        around = np.ones((3, 3), bool)
        cast = binary_dilation(centre, around) & binary_dilation(~centre, around)
    else:
        cast = np.ones_like(centre)
    rows, cols = np.nonzero(cast)
    for sl, depth, _, _ in _subpixel_chunks(K, P, height, width, rows, cols, s, scene, int(chunk_pixels)):
        coverage[rows[sl], cols[sl]] = (depth > 0).mean(axis=1, dtype=np.float64)
    return coverage


def subpixel_depths(K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int, rows: np.ndarray,
                    cols: np.ndarray, samples: int, scene, chunk_pixels: int = 1 << 16) -> dict[str, np.ndarray]:
    """Camera depth of a mesh along a regular ``samples x samples`` grid of rays through each given pixel's
    square (pixel ``i`` spans ``[i - 1/2, i + 1/2]``; the rays sit at the centres of the grid's cells).

    Args:
        K, cam_from_world: the camera (:func:`camera_rays`). height, width: image size in pixels.
        rows, cols: (M,) int indices of the pixels.
        samples: rays per pixel side, >= 1 (1: the pixel centre).
        scene: :func:`mesh_scene` of the mesh.
        chunk_pixels: pixels whose grids are cast at once (bounds the memory).

    Returns:
        ``depth_m`` (M, S) float32 camera z of each ray's hit (0 = miss), ``u``, ``v`` (M, S) float64 the
        rays' pixel coordinates, with ``S = samples^2`` (grid row-major: the first ``samples`` rays share the
        smallest ``v``).
    """
    K, P = _check_camera(K, cam_from_world, height, width)
    if int(samples) != samples or samples < 1:
        raise ValueError(f"samples must be an integer >= 1, got {samples!r}")
    if int(chunk_pixels) < 1:
        raise ValueError(f"chunk_pixels must be >= 1, got {chunk_pixels!r}")
    rows = np.asarray(rows, np.int64).reshape(-1)
    cols = np.asarray(cols, np.int64).reshape(-1)
    if rows.shape != cols.shape:
        raise ValueError(f"rows and cols differ in length: {rows.shape} vs {cols.shape}")
    s = int(samples)
    out = {"depth_m": np.zeros((len(rows), s * s), np.float32), "u": np.zeros((len(rows), s * s)),
           "v": np.zeros((len(rows), s * s))}
    for sl, depth, u, v in _subpixel_chunks(K, P, height, width, rows, cols, s, scene, int(chunk_pixels)):
        out["depth_m"][sl], out["u"][sl], out["v"][sl] = depth, u, v
    return out


def _subpixel_chunks(K: np.ndarray, P: np.ndarray, height: int, width: int, rows: np.ndarray, cols: np.ndarray,
                     s: int, scene, chunk_pixels: int):
    """The rays of :func:`subpixel_depths`, cast ``chunk_pixels`` pixels at a time: yields the chunk's slice of
    the pixels, and its depth_m (m, s*s) float32, u and v (m, s*s) float64."""
    import open3d as o3d

    offsets = (np.arange(s) + 0.5) / s - 0.5
    du, dv = np.meshgrid(offsets, offsets)  # (s, s): row j of the grid is at v offset offsets[j]
    for start in range(0, len(rows), chunk_pixels):
        sl = slice(start, start + chunk_pixels)
        u = cols[sl, None] + du.reshape(1, -1)
        v = rows[sl, None] + dv.reshape(1, -1)
        origins, directions, z_per_t = camera_rays(K, P, height, width, pixels=np.stack([u.ravel(), v.ravel()], -1))
        rays = np.concatenate([origins, directions], axis=-1).astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(t_hit)
        depth = np.where(hit, np.where(hit, t_hit, 0.0) * z_per_t, 0.0).reshape(u.shape).astype(np.float32)
        yield sl, depth, u, v


def occlusion_edges(depth_m: np.ndarray, jump_m: float) -> np.ndarray:
    """Pixels at an occlusion edge inside a silhouette: the pixel-centre depths of the 3 x 3 neighbourhood are
    all on a surface and more than ``jump_m`` apart (an arm in front of the torso; also a surface so oblique
    that its depth changes by ``jump_m`` over two pixels). Pixels whose neighbourhood reaches the background
    are not: a silhouette is the coverage's business (:func:`pixel_coverage`).

    Args:
        depth_m: (H, W) camera z, 0 = no surface. jump_m: > 0, metres.

    Returns:
        (H, W) bool.
    """
    from scipy.ndimage import maximum_filter, minimum_filter

    depth = np.asarray(depth_m, np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got {depth.shape}")
    if not (np.isfinite(jump_m) and jump_m > 0):
        raise ValueError(f"jump_m must be positive, got {jump_m!r}")
    surface = depth > 0
    inside = minimum_filter(surface.astype(np.uint8), size=3, mode="nearest") > 0
    span = maximum_filter(depth, size=3, mode="nearest") + maximum_filter(-depth, size=3, mode="nearest")
    return inside & (span > jump_m)


def render_attributes(scene, faces: np.ndarray, attributes: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray,
                      height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex attributes of a mesh seen by a pinhole camera, interpolated with the hits' barycentrics.

    Args:
        scene: :func:`mesh_scene` of the mesh (face ``i`` of the scene is row ``i`` of ``faces``).
        faces: (F, 3) int indices into ``attributes`` per face corner (e.g. a UV atlas' faces, whose
            corners index split vertices, while the scene was built from the welded ones).
        attributes: (A, C) per-vertex values (UVs, smooth normals, ...).
        K, cam_from_world, height, width: the camera.

    Returns:
        values (H, W, C) float64 (0 where the mesh is missed) and hit (H, W) bool.
    """
    import open3d as o3d

    faces = np.asarray(faces, np.int64)
    attributes = np.asarray(attributes, np.float64)
    if faces.ndim != 2 or faces.shape[1] != 3 or attributes.ndim != 2:
        raise ValueError(f"expected faces (F, 3) and attributes (A, C), got {faces.shape} and {attributes.shape}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(attributes)):
        raise ValueError(f"faces index {faces.max() + 1} attributes, only {len(attributes)} given")
    origins, directions, _ = camera_rays(K, cam_from_world, height, width)
    rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    hit = np.isfinite(ans["t_hit"].numpy())
    face = np.where(hit, ans["primitive_ids"].numpy().astype(np.int64), 0)
    if hit.any() and face[hit].max() >= len(faces):
        raise ValueError(f"the scene has more faces than the {len(faces)} given: another mesh?")
    bary = ans["primitive_uvs"].numpy().astype(np.float64)  # hit = (1 - u - v) p0 + u p1 + v p2
    corners = attributes[faces[face]]  # (N, 3, C)
    values = (corners[:, 0] * (1.0 - bary[:, :1] - bary[:, 1:2]) + corners[:, 1] * bary[:, :1]
              + corners[:, 2] * bary[:, 1:2])
    values = np.where(hit[:, None], values, 0.0)
    return values.reshape(height, width, attributes.shape[1]), hit.reshape(height, width)


def render_uvs(scene, uv_faces: np.ndarray, uvs: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray,
               height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Texture coordinates (H, W, 2) of a textured mesh seen by a camera, and the hit mask (H, W):
    :func:`render_attributes` of the per-corner UVs."""
    uvs = np.asarray(uvs, np.float64)
    if uvs.ndim != 2 or uvs.shape[1] != 2:
        raise ValueError(f"uvs must be (U, 2), got {uvs.shape}")
    return render_attributes(scene, uv_faces, uvs, K, cam_from_world, height, width)
