"""The pinhole camera of the pipeline: intrinsics, pose, image size, and the geometry every stage needs of it.

Conventions (the release's CONVENTIONS.md): OpenCV axes (x right, y down, z forward), ``x_cam = R x_world + t``
with ``cam_from_world = [R | t]``, metres, and pixel index ``i`` at continuous coordinate ``u = i`` (pixel centres at
integer coordinates). Lens distortion is not modelled here (the simulator's and the calibrations' cameras have none
that the maps need).

:class:`Camera` reads and writes the records of ``cameras.json`` (:meth:`Camera.from_json`, :meth:`Camera.to_json`;
the file format does not change) and gives the camera's centre, its rays, the projection of world points and the
lifting of pixels with a depth back to world points. Pure numpy.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Camera", "camera_centre", "as_pose", "lift_points", "pixel_rays", "pixel_coordinates", "check_bounds",
           "ray_box"]


def camera_centre(cam_from_world: np.ndarray) -> np.ndarray:
    """World position of a camera centre: ``-R^T t``.

    Args:
        cam_from_world: (3, 4) or (4, 4), or a stack (N, 3, 4).

    Returns:
        (3,) (or (N, 3)) float64.
    """
    P = np.asarray(cam_from_world, dtype=np.float64)
    if P.ndim == 2:
        P = as_pose(P)
        return -P[:, :3].T @ P[:, 3]
    if P.ndim != 3 or P.shape[-2:] not in ((3, 4), (4, 4)):
        raise ValueError(f"cam_from_world must be (3, 4), (4, 4) or (N, 3, 4), got {P.shape}")
    return -np.einsum("nji,nj->ni", P[:, :3, :3], P[:, :3, 3])


def as_pose(cam_from_world: np.ndarray, name: str = "cam_from_world") -> np.ndarray:
    """``cam_from_world`` as a (3, 4) float64 array (a (4, 4) cut to its top rows); ValueError when it is neither
    or holds non-finite values (``name`` says which argument in the message)."""
    P = np.asarray(cam_from_world, dtype=np.float64)
    if P.shape == (4, 4):
        P = P[:3]
    if P.shape != (3, 4):
        raise ValueError(f"{name} must be (3, 4) or (4, 4), got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ValueError(f"{name} holds non-finite values")
    return P


def _normalised_coordinates(K: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``x, y`` of ``K^-1 [u, v, 1] = [x, y, 1]`` (skew included), the one inverse of :func:`pixel_coordinates`."""
    y = (v - K[1, 2]) / K[1, 1]
    return (u - K[0, 2] - K[0, 1] * y) / K[0, 0], y


def pixel_coordinates(K: np.ndarray, points_cam: np.ndarray, z: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                                                   np.ndarray]:
    """Pixel coordinates ``u``, ``v`` (N,) of camera-frame points (N, 3): ``K [x / z, y / z, 1]``.

    ``z`` (N,) replaces the points' own depth as the divisor (callers pass a guarded depth, e.g. 1 behind the
    camera, to keep the division finite). The arithmetic keeps the points' float type where K's scalars allow."""
    z = points_cam[:, 2] if z is None else z
    x, y = points_cam[:, 0] / z, points_cam[:, 1] / z
    return K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]


def check_bounds(bounds: Any) -> np.ndarray:
    """``bounds`` as a float64 (2, 3) [min, max] box; ValueError unless finite with max > min on every axis."""
    b = np.asarray(bounds, np.float64)
    if b.shape != (2, 3) or not np.isfinite(b).all() or not (b[1] > b[0]).all():
        raise ValueError(f"bounds must be finite (2, 3) [min, max] with max > min, got {bounds!r}")
    return b


def ray_box(origins: np.ndarray, dirs: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slab test: (near, far) of each ray in the box; far <= near where it misses.

    origins (..., 3) or broadcastable, dirs (..., 3), bounds (2, 3) [min, max]; near and far (...,)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(dirs) < 1e-12, 1e-12, dirs)
        t0 = (bounds[0] - origins) * inv
        t1 = (bounds[1] - origins) * inv
    near = np.maximum(np.minimum(t0, t1).max(axis=-1), 0.0)
    far = np.maximum(t0, t1).min(axis=-1)
    return near, far


def pixel_rays(K: np.ndarray, cam_from_world: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray,
                                                                                                  np.ndarray]:
    """Unit world directions (..., 3) float64 of the rays through pixel coordinates ``u``, ``v`` (...,) of the
    camera K (3, 3), cam_from_world (3, 4), and the camera depth per unit of ray length (...,) (``depth_m = t *
    z_per_t``). The rays start at the camera centre (:func:`camera_centre`). Skew is included."""
    x, y = _normalised_coordinates(K, np.asarray(u, np.float64), np.asarray(v, np.float64))
    d_cam = np.stack([x, y, np.ones_like(x)], axis=-1)
    d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
    return d_cam @ cam_from_world[:, :3], d_cam[..., 2]  # rows of R^T d


def lift_points(K: np.ndarray, cam_from_world: np.ndarray, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """World points (..., 3) at pixel coordinates ``u``, ``v`` and camera depth ``z`` (all (...,)) of the camera
    K (3, 3), cam_from_world (3, 4): :meth:`Camera.lift` for callers that hold the matrices (no image size)."""
    # x_cam = z K^-1 [u, v, 1], x_world = R^T (x_cam - t)
    x_cam, y_cam = _normalised_coordinates(K, u, v)
    pts_cam = np.stack([x_cam * z, y_cam * z, z], axis=-1)
    return (pts_cam - cam_from_world[:, 3]) @ cam_from_world[:, :3]  # rows of R^T (x - t)


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: ``K`` (3, 3), ``cam_from_world`` (3, 4) (a (4, 4) is cut to its top rows), image size.

    Raises ValueError on construction when K is not (3, 3) with finite, positive focal lengths, the pose is not a
    finite (3, 4) / (4, 4) or the size is not positive."""

    K: np.ndarray
    """(3, 3) float64 intrinsics: focal lengths ``K[0, 0]``, ``K[1, 1]``, skew ``K[0, 1]``, principal point
    ``K[:2, 2]`` in pixels."""
    cam_from_world: np.ndarray
    """(3, 4) float64 ``[R | t]``: ``x_cam = R x_world + t``."""
    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    camera_id: str = ""
    """The camera's id in its rig (5 digits in a capture, e.g. ``00007``; ``N000`` for novel views)."""
    record: Mapping[str, Any] = field(default_factory=dict)
    """The ``cameras.json`` record it was read from: its other fields (``dist``, ``white_reference``, ...) are
    kept, in their order, by :meth:`to_json`."""

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be (3, 3), got {K.shape}")
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K must be finite with positive focal lengths, got {K.tolist()}")
        if int(self.width) < 1 or int(self.height) < 1:
            raise ValueError(f"image size must be positive, got {self.height} x {self.width}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "cam_from_world", as_pose(self.cam_from_world))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @classmethod
    def from_json(cls, record: Mapping[str, Any]) -> "Camera":
        """A camera from one record of ``cameras.json`` (``camera_id``, ``width``, ``height``, ``K``,
        ``cam_from_world`` and any other fields, kept in :attr:`record`)."""
        return cls(K=record["K"], cam_from_world=record["cam_from_world"], width=record["width"],
                   height=record["height"], camera_id=str(record.get("camera_id", "")), record=dict(record))

    def to_json(self) -> dict[str, Any]:
        """The ``cameras.json`` record: the fields of :attr:`record` in their order, with this camera's id, ``K``,
        ``cam_from_world`` (as nested lists) and size (after the record's fields, in that order, where the record
        lacks them)."""
        return dict(self.record) | {"camera_id": self.camera_id, "K": self.K.tolist(),
                                    "cam_from_world": self.cam_from_world.tolist(), "width": self.width,
                                    "height": self.height}

    @property
    def R(self) -> np.ndarray:
        """(3, 3) rotation from world to camera axes."""
        return self.cam_from_world[:, :3]

    @property
    def t(self) -> np.ndarray:
        """(3,) translation: the world origin in camera coordinates."""
        return self.cam_from_world[:, 3]

    @property
    def centre(self) -> np.ndarray:
        """(3,) float64 world position of the camera centre, ``-R^T t``."""
        return camera_centre(self.cam_from_world)

    def pixel_grid(self) -> np.ndarray:
        """(H * W, 2) float64 ``(u, v)`` coordinates of every pixel centre, row-major."""
        v, u = np.mgrid[0:self.height, 0:self.width]
        return np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)

    def rays(self, pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """World rays through pixels: origins (N, 3) (the centre) and unit directions (N, 3), float64.

        pixels: (N, 2) ``(u, v)``; default every pixel centre, row-major (:meth:`pixel_grid`)."""
        origins, directions, _ = self.rays_with_depth_scale(pixels)
        return origins, directions

    def rays_with_depth_scale(self, pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`rays` and, per ray, the camera depth per unit of ray length (N,) (``depth_m = t * z_per_t``)."""
        pixels = self.pixel_grid() if pixels is None else np.asarray(pixels, dtype=np.float64)
        directions, z_per_t = pixel_rays(self.K, self.cam_from_world, pixels[:, 0], pixels[:, 1])
        return np.broadcast_to(self.centre, directions.shape).copy(), directions, z_per_t

    def view_directions(self) -> np.ndarray:
        """(H, W, 3) float32 unit world directions from the surface seen at each pixel towards the camera (the
        pixel's ray reversed; lens distortion ignored)."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        return (-pixel_rays(self.K, self.cam_from_world, u, v)[0]).astype(np.float32)

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (..., 2) and camera depths (...,) of world points (..., 3), float64. Points behind the
        camera (depth <= 0) get coordinates too; callers test the depth."""
        points_world = np.asarray(points_world, dtype=np.float64)
        x_cam = points_world.reshape(-1, 3) @ self.R.T + self.t
        u, v = pixel_coordinates(self.K, x_cam)
        shape = points_world.shape[:-1]
        return np.stack([u, v], axis=-1).reshape(shape + (2,)), x_cam[:, 2].reshape(shape)

    def lift(self, uv: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """World points (..., 3) float64 at pixel coordinates ``uv`` (..., 2) and camera depth ``depth_m`` (...,)
        (camera z, not ray length): the inverse of :meth:`project`."""
        uv = np.asarray(uv, dtype=np.float64)
        return self._lift(uv[..., 0], uv[..., 1], np.asarray(depth_m, dtype=np.float64))

    def _lift(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        return lift_points(self.K, self.cam_from_world, u, v, z)

    def lift_depth_map(self, depth_m: np.ndarray) -> np.ndarray:
        """World points (H, W, 3) of every pixel of a depth map (H, W) (camera z)."""
        h, w = depth_m.shape
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        return self._lift(u, v, np.asarray(depth_m))
