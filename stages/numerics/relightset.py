"""The draws and conversions of the single-image relighting set (pure functions; no files).

Every random choice of the set is a function of the seed and a name, never of a running random stream, so
that adding an action, an example or an environment map leaves every other example's draws unchanged:

- :func:`unit_draw`: a uniform number in [0, 1) from sha256 of (seed, purpose, key).
- :func:`choose_environment`: rendezvous hashing over the pool's digests: each example takes the map with
  the highest draw, so a map added to a pool of N takes over about 1 / (N + 1) of the examples and the rest
  keep theirs.
- :func:`split_of`: a subject's split from one draw and the split ratios.
- :func:`orbit_camera`: a pinhole camera on a sphere around the subject looking at its centre, the subject's
  bounding sphere filling the square image less a margin.

:func:`render_example` renders one drawn example (image, alpha, mask, albedo, camera-frame normals, PNG exposure)
and :func:`example_lighting_sh` gives its lighting as order-2 spherical harmonics.
"""
from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

SPLIT_NAMES = ("train", "validation", "test")


def unit_draw(seed: int, purpose: str, key: str) -> float:
    """A number uniform in [0, 1) determined by (seed, purpose, key) alone (sha256, 53 bits)."""
    digest = hashlib.sha256(f"{int(seed)}\0{purpose}\0{key}".encode()).digest()
    return (int.from_bytes(digest[:8], "big") >> 11) / float(1 << 53)


def choose_environment(seed: int, example_id: str, pool_digests: Sequence[str]) -> int:
    """Index into the pool of the map example ``example_id`` is lit by (rendezvous hashing over the maps'
    sha256 digests, so the choice does not depend on the pool's order or on the other maps)."""
    if len(pool_digests) == 0:
        raise ValueError("the environment pool is empty")
    scores = [unit_draw(seed, f"environment:{digest}", example_id) for digest in pool_digests]
    return int(np.argmax(scores))


def split_of(seed: int, subject: str, ratios: Sequence[float]) -> str:
    """'train', 'validation' or 'test' for a subject: one draw against the cumulative ``ratios`` (3,),
    non-negative and summing to 1 (checked)."""
    ratios = np.asarray(ratios, np.float64)
    if ratios.shape != (3,) or np.any(~np.isfinite(ratios)) or np.any(ratios < 0) or abs(ratios.sum() - 1) > 1e-6:
        raise ValueError(f"split ratios must be 3 non-negative numbers summing to 1, got {ratios.tolist()}")
    u = unit_draw(seed, "split", subject)
    edges = np.cumsum(ratios)
    for name, edge in zip(SPLIT_NAMES, edges):
        if u < edge:
            return name
    return SPLIT_NAMES[int(np.flatnonzero(ratios > 0)[-1])]


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 1.0, 0.0])) -> np.ndarray:
    """cam_from_world (3, 4) of an OpenCV camera (x right, y down, z forward) at ``position`` (3,) looking at
    ``target`` (3,), with the world's ``up`` (3,) pointing up in the image."""
    position, target, up = (np.asarray(v, np.float64) for v in (position, target, up))
    forward = target - position
    if np.linalg.norm(forward) < 1e-12:
        raise ValueError("look_at: position and target coincide")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: the view direction is parallel to up")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    return np.concatenate([rotation, (-rotation @ position)[:, None]], axis=1)


def orbit_camera(centre: np.ndarray, radius_m: float, distance_m: float, azimuth_deg: float, elevation_deg: float,
                 size: int, margin: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), cam_from_world (3, 4)) of a square ``size`` x ``size`` camera at ``distance_m`` from
    ``centre`` (3,), at ``azimuth_deg`` about +y (0 = on +z, 90 = on +x) and ``elevation_deg`` above the
    horizontal plane, looking at the centre; the focal length makes the subject's bounding sphere of
    ``radius_m`` fill the image's width less ``margin`` on each side. Pixel centres at integer coordinates."""
    if not (radius_m > 0 and distance_m > radius_m):
        raise ValueError(f"need 0 < radius_m < distance_m, got {radius_m} and {distance_m}")
    if size < 2 or not (0 <= margin < 0.5):
        raise ValueError(f"need size >= 2 and margin in [0, 0.5), got {size} and {margin}")
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    direction = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    position = np.asarray(centre, np.float64) + distance_m * direction
    half_angle = math.asin(radius_m / distance_m)
    focal = (size / 2.0) * (1.0 - 2.0 * margin) / math.tan(half_angle)
    c = (size - 1) / 2.0
    K = np.array([[focal, 0.0, c], [0.0, focal, c], [0.0, 0.0, 1.0]])
    return K, look_at(position, centre)


def normals_to_camera(normals_world: np.ndarray, cam_from_world: np.ndarray) -> np.ndarray:
    """Normals (H, W, 3) rotated into the camera frame (OpenCV axes); zero vectors stay zero."""
    rotation = np.asarray(cam_from_world, np.float64)[:, :3]
    return (np.asarray(normals_world, np.float64) @ rotation.T).astype(np.float32)


def tone_map(image: np.ndarray, exposure: float) -> np.ndarray:
    """uint8 sRGB picture (H, W, 3) of a linear image: ``image * exposure`` clipped to [0, 1], sRGB curve."""
    from pipeline.codecs.image import srgb_encode

    if not (np.isfinite(exposure) and exposure > 0):
        raise ValueError(f"exposure must be positive and finite, got {exposure}")
    scaled = np.nan_to_num(np.asarray(image, np.float32) * float(exposure), nan=0.0, posinf=0.0, neginf=0.0)
    return (srgb_encode(scaled) * 255.0 + 0.5).astype(np.uint8)


def encode_normals(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """uint8 picture (H, W, 3) of unit normals as (n + 1) / 2, 0 off ``mask`` (H, W)."""
    picture = (np.clip((np.asarray(normals, np.float32) + 1.0) * 0.5, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    picture[~np.asarray(mask, bool)] = 0
    return picture


def subject_frame(vertices: np.ndarray, camera_centres: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(centre (3,), bounding radius, camera distance) of a subject: the centre of the vertices' (V, 3) box, the
    largest distance of a vertex from it, and the median distance of the captured cameras' centres (C, 3)
    from it (at least 1.5 radii)."""
    vertices = np.asarray(vertices, np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0 or not np.all(np.isfinite(vertices)):
        raise ValueError(f"vertices must be a finite non-empty (V, 3) array, got shape {vertices.shape}")
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    radius = float(np.linalg.norm(vertices - centre, axis=1).max())
    distances = np.linalg.norm(np.asarray(camera_centres, np.float64).reshape(-1, 3) - centre, axis=1)
    distance = max(float(np.median(distances)) if len(distances) else 0.0, 1.5 * radius)
    return centre, radius, distance


def draw_example(seed: int, example_id: str, pool_digests: Sequence[str], centre: np.ndarray, radius_m: float,
                 distance_m: float, size: int, elevation_deg: Sequence[float], margin: float) -> dict:
    """The draws of one example: ``environment_index`` (into ``pool_digests``), ``rotation_deg`` in [0, 360),
    ``azimuth_deg``, ``elevation_deg`` (uniform in the range), and its camera ``K`` (3, 3) and
    ``cam_from_world`` (3, 4) (:func:`orbit_camera`)."""
    low, high = elevation_deg
    azimuth = 360.0 * unit_draw(seed, "azimuth", example_id)
    elevation = low + (high - low) * unit_draw(seed, "elevation", example_id)
    K, cam_from_world = orbit_camera(centre, radius_m, distance_m, azimuth, elevation, size, margin)
    return {"environment_index": choose_environment(seed, example_id, pool_digests),
            "rotation_deg": 360.0 * unit_draw(seed, "rotation", example_id), "azimuth_deg": azimuth,
            "elevation_deg": elevation, "K": K, "cam_from_world": cam_from_world}


def example_lighting_sh(env: np.ndarray, rotation_deg: float, cam_from_world: np.ndarray) -> tuple[np.ndarray,
                                                                                                    np.ndarray]:
    """An example's lighting as order-2 spherical harmonics (9, 3): in the world frame and in the camera's, of the
    environment ``env`` (H, 2H, 3) turned ``rotation_deg`` about +y. cam_from_world: (3, 4) or (4, 4)."""
    from stages.numerics.sg import rotation_y
    from stages.numerics.sh import project_environment

    world_from_map = rotation_y(math.radians(rotation_deg))
    return (project_environment(env, world_from_map),
            project_environment(env, np.asarray(cam_from_world)[:3, :3] @ world_from_map))


def render_example(asset: Any, K: np.ndarray, cam_from_world: np.ndarray, size: int, lobes: Any, rotation_deg: float,
                   shading: Any, directions: np.ndarray | None, png_level: float) -> dict[str, Any]:
    """One example of the set: the asset (:class:`stages.numerics.novel_view.ActionAsset`) seen by the square
    ``size`` camera (K (3, 3), cam_from_world (3, 4) or (4, 4)) under the SG ``lobes`` turned ``rotation_deg``
    about +y (:func:`stages.numerics.novel_view.relight_view` with ``shading``).

    Returns ``image`` (S, S, 3) linear radiance premultiplied by ``alpha`` (S, S), ``mask`` (S, S) bool,
    ``albedo`` (S, S, 3) in [0, 1], ``normals_camera`` (S, S, 3) (OpenCV camera frame) and ``exposure``, the
    PNG's exposure that puts the masked pixels' ``png_level`` quantile at the top of the range."""
    from stages.numerics.novel_view import auto_exposure, relight_view
    from stages.numerics.sg import rotate_sg

    view = relight_view(asset, K, cam_from_world, size, size, [rotate_sg(lobes, math.radians(rotation_deg))],
                        shading, directions=directions)
    image, mask = view["images"][0], view["mask"]
    return {"image": image, "alpha": view["alpha"], "mask": mask, "albedo": np.clip(view["maps"]["albedo"], 0.0, 1.0),
            "normals_camera": normals_to_camera(view["maps"]["normal"], cam_from_world),
            "exposure": auto_exposure(image, mask, png_level)}
