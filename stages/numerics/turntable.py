"""A turntable of a textured mesh: views on a circle about the world's +y axis, shaded for a preview.

The release page shows the action's mesh as these frames (one PNG strip) instead of a 3D viewer, so it works
offline in any browser.
"""
from __future__ import annotations

import numpy as np


def turntable_cameras(vertices: np.ndarray, frames: int, height: int, width: int,
                      elevation_deg: float = 10.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Cameras looking at the mesh's bounding-box centre from ``frames`` azimuths about +y (world up), at a
    distance where the whole box fits the picture.

    Args:
        vertices: (V, 3) world positions, metres. frames: number of views (>= 1). height, width: picture size.
        elevation_deg: how far above the centre the cameras look down from.

    Returns:
        ``frames`` pairs ``(K (3, 3), cam_from_world (3, 4))``, OpenCV axes, the first seen from +z.
    """
    vertices = np.asarray(vertices, np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise ValueError(f"vertices must be (V, 3) with V > 0, got {vertices.shape}")
    if frames < 1 or height < 1 or width < 1:
        raise ValueError(f"frames, height and width must be positive, got {frames}, {height}, {width}")
    lo, hi = vertices.min(0), vertices.max(0)
    centre = (lo + hi) / 2
    # the mesh turns within a vertical cylinder about the centre: fit its height and its width from any side,
    # from its near side (the camera is the cylinder's radius closer to it than to the axis)
    radius = max(float(np.linalg.norm(vertices[:, [0, 2]] - centre[[0, 2]], axis=1).max()), 1e-6)
    half_height = max(float(hi[1] - lo[1]) / 2, 1e-6)
    focal = 1.2 * min(height, width)  # about 45 degrees across the narrow side
    distance = radius + 1.1 * max(half_height * focal / (height / 2), radius * focal / (width / 2))
    K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]], np.float64)
    elevation = np.radians(elevation_deg)
    cameras = []
    for azimuth in np.linspace(0.0, 2 * np.pi, frames, endpoint=False):
        eye = centre + distance * np.array([np.sin(azimuth) * np.cos(elevation), np.sin(elevation),
                                            np.cos(azimuth) * np.cos(elevation)])
        forward = (centre - eye) / np.linalg.norm(centre - eye)
        right = np.cross(forward, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])  # rows: camera x (right), y (down), z (forward) in world axes
        cameras.append((K.copy(), np.concatenate([R, (-R @ eye)[:, None]], axis=1)))
    return cameras


def turntable_strip(scene, faces: np.ndarray, uvs: np.ndarray, albedo: np.ndarray,
                    cameras: list[tuple[np.ndarray, np.ndarray]], height: int, width: int,
                    background: float = 1.0) -> np.ndarray:
    """The mesh seen by each camera, its albedo texture shaded by a head light (a quarter ambient), the frames
    side by side.

    Args:
        scene: :func:`stages.numerics.raycast.mesh_scene` of the mesh. faces: (F, 3) corner indices into ``uvs``
            (the atlas' faces, row ``i`` is face ``i`` of the scene). uvs: (U, 2) OBJ-convention UVs.
        albedo: (T, T, 3) linear albedo texture. cameras: from :func:`turntable_cameras`.
        background: linear grey of the pixels that miss the mesh.

    Returns:
        (height, width * len(cameras), 3) float32 linear RGB.
    """
    from stages.numerics.bake import sample_texture
    from stages.numerics.raycast import render_mesh, render_uvs

    pictures = []
    for K, cam_from_world in cameras:
        uv, hit = render_uvs(scene, faces, uvs, K, cam_from_world, height, width)
        geometry = render_mesh(None, None, K, cam_from_world, height, width, scene=scene)
        colour = sample_texture(albedo, uv.reshape(-1, 2)).reshape(height, width, -1)[..., :3]
        # the light comes from the camera: n . (towards the camera), the normals already face it
        towards = -np.asarray(cam_from_world)[2, :3]
        lit = np.clip(geometry["normals_world"] @ towards, 0.0, 1.0)[..., None]
        shaded = colour * (0.25 + 0.75 * lit)
        pictures.append(np.where(hit[..., None], shaded, background).astype(np.float32))
    return np.concatenate(pictures, axis=1)
