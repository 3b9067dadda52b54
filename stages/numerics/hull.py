"""Visual hull from foreground masks: a voxel occupancy grid, its signed distance, point look-ups.

Pure numerics, arrays in and arrays out (docs/CONTRACTS.md conventions: stage frame = world frame,
metres; OpenCV cameras with ``x_cam = R @ x_world + t``; pixel ``(row i, column j)`` has its centre at
``(u, v) = (j, i)``).

A voxel is kept when it projects inside the mask of every camera that sees it, allowing ``max_misses``
cameras to disagree (a mask with a hole or a clipped limb must not carve the body), and inside at least
``min_views`` masks. To stay a *superset* of the subject the default test is conservative: a voxel passes a
view when its centre lies within ``dilate_px`` plus the voxel's own projected half-diagonal of a mask pixel
(one Euclidean distance transform per view, instead of projecting eight corners). Carving is incremental:
each view only tests the voxels that survived the previous ones.

The hull bounds the volume of :mod:`stages.numerics.sdf`, chooses the rays worth drawing and initialises
the SDF (:meth:`HullGrid.signed_distance`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import ndimage

from artifacts.camera import camera_centre, check_bounds, pixel_coordinates, pixel_rays

__all__ = ["HullGrid", "visual_hull", "check_camera", "default_stage_box", "subject_box"]


def check_camera(K: np.ndarray, cam_from_world: np.ndarray, where: str = "camera") -> tuple[np.ndarray, np.ndarray]:
    """Validate one camera; returns ``(K (3,3) float64, cam_from_world (3,4) float64)``.

    Raises:
        ValueError: wrong shapes, non-finite values, a non-positive focal length or a non-rotation.
    """
    K = np.asarray(K, np.float64)
    T = np.asarray(cam_from_world, np.float64)
    if T.shape == (4, 4):
        T = T[:3]
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"{where}: K must be a finite (3, 3) matrix with positive focal lengths, got {K!r}")
    if T.shape != (3, 4) or not np.isfinite(T).all():
        raise ValueError(f"{where}: cam_from_world must be a finite (3, 4) [R | t], got shape {T.shape}")
    R = T[:, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
        raise ValueError(f"{where}: cam_from_world[:, :3] is not a rotation matrix")
    return K, T


@dataclass
class HullGrid:
    """A voxel occupancy grid over an axis-aligned box.

    Attributes:
        occupancy: bool (Rx, Ry, Rz), index order x, y, z; voxel ``(i, j, k)`` spans
            ``bounds[0] + ((i, j, k) + [0, 1]) * voxel_size``.
        bounds: float64 (2, 3) min and max corner of the grid in metres.
    """

    occupancy: np.ndarray
    bounds: np.ndarray

    def __post_init__(self) -> None:
        self.occupancy = np.asarray(self.occupancy, bool)
        if self.occupancy.ndim != 3 or min(self.occupancy.shape) < 1:
            raise ValueError(f"occupancy must be a non-empty (Rx, Ry, Rz) bool grid, got {self.occupancy.shape}")
        self.bounds = check_bounds(self.bounds)

    @property
    def resolution(self) -> tuple[int, int, int]:
        return tuple(int(r) for r in self.occupancy.shape)  # type: ignore[return-value]

    @property
    def voxel_size(self) -> np.ndarray:
        """(3,) voxel edge lengths in metres (x, y, z)."""
        return (self.bounds[1] - self.bounds[0]) / np.asarray(self.occupancy.shape, np.float64)

    @property
    def occupied_fraction(self) -> float:
        return float(self.occupancy.mean())

    def centers(self) -> np.ndarray:
        """(Rx, Ry, Rz, 3) float64 voxel centres in metres."""
        axes = [self.bounds[0, a] + (np.arange(r) + 0.5) * self.voxel_size[a] for a, r in enumerate(self.occupancy.shape)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def tight_bounds(self, margin_m: float = 0.0) -> np.ndarray:
        """(2, 3) box around the occupied voxels (their full extent), grown by ``margin_m`` on each side.

        Raises:
            ValueError: the grid holds no occupied voxel.
        """
        if not self.occupancy.any():
            raise ValueError("the hull is empty: no voxel is inside the masks of the views that see it")
        idx = np.argwhere(self.occupancy)
        lo = self.bounds[0] + idx.min(0) * self.voxel_size - margin_m
        hi = self.bounds[0] + (idx.max(0) + 1) * self.voxel_size + margin_m
        return np.stack([lo, hi])

    def signed_distance(self) -> np.ndarray:
        """(Rx, Ry, Rz) float32 signed distance to the hull's surface in metres, negative inside.

        Exact Euclidean distance between voxel centres (scipy.ndimage.distance_transform_edt with the voxel
        size as sampling), minus half a voxel so that the zero level lies between an occupied and an empty
        voxel rather than on either centre. Outside the grid box everything counts as empty.
        """
        occ = self.occupancy
        vs = self.voxel_size
        if not occ.any():
            return np.full(occ.shape, float(np.linalg.norm(self.bounds[1] - self.bounds[0])), np.float32)
        # Pad with empty voxels so that a body touching the box border still gets a boundary there.
        padded = np.pad(occ, 1, constant_values=False)
        outside = ndimage.distance_transform_edt(~padded, sampling=vs)[1:-1, 1:-1, 1:-1]
        inside = ndimage.distance_transform_edt(padded, sampling=vs)[1:-1, 1:-1, 1:-1]
        half = 0.5 * float(vs.min())
        sd = np.where(occ, -(inside - half), outside - half)
        return sd.astype(np.float32)

    def voxel_index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Voxel index of each point: ``(ijk (N, 3) int64, inside (N,) bool)``; ijk is clipped into the grid."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        finite = np.isfinite(p).all(1)
        rel = (np.where(finite[:, None], p, 0.0) - self.bounds[0]) / self.voxel_size
        ijk = np.floor(np.clip(rel, -1, np.asarray(self.occupancy.shape))).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < np.asarray(self.occupancy.shape)), axis=1) & finite
        ijk = np.clip(ijk, 0, np.asarray(self.occupancy.shape) - 1)
        return ijk, inside

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: the point lies in an occupied voxel (False outside the grid box)."""
        ijk, inside = self.voxel_index(points)
        return inside & self.occupancy[ijk[:, 0], ijk[:, 1], ijk[:, 2]]

    def sample(self, values: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Trilinear interpolation of a per-voxel field (e.g. :meth:`signed_distance`) at points.

        Args:
            values: (Rx, Ry, Rz) values at voxel centres.
            points: (N, 3) metres. Points outside the box take the value of the nearest border voxel.

        Returns:
            (N,) float32.
        """
        values = np.asarray(values)
        if values.shape != self.occupancy.shape:
            raise ValueError(f"values must be {self.occupancy.shape} like the grid, got {values.shape}")
        p = np.asarray(points, np.float64).reshape(-1, 3)
        coords = ((p - self.bounds[0]) / self.voxel_size - 0.5).T
        return ndimage.map_coordinates(values.astype(np.float32), coords, order=1, mode="nearest").astype(np.float32)

    def dilated(self, voxels: int = 1) -> "HullGrid":
        """A copy grown by ``voxels`` voxels (26-connected), e.g. to keep samples just outside the hull."""
        if voxels <= 0:
            return HullGrid(self.occupancy.copy(), self.bounds.copy())
        occ = ndimage.binary_dilation(self.occupancy, structure=np.ones((3, 3, 3), bool), iterations=int(voxels))
        return HullGrid(occ, self.bounds.copy())


def visual_hull(
    masks: Sequence[np.ndarray],
    Ks: Sequence[np.ndarray],
    cam_from_worlds: Sequence[np.ndarray],
    bounds: np.ndarray,
    resolution: int | Sequence[int],
    max_misses: int = 1,
    dilate_px: float = 2,
    min_views: int = 3,
    conservative: bool = True,
    component_views: float = 0.0,
) -> HullGrid:
    """Voxel visual hull of the masks (silhouette carving).

    Args:
        masks: per view (H, W) bool foreground (any dtype; non-zero is foreground).
        Ks: per view (3, 3) intrinsics.
        cam_from_worlds: per view (3, 4) (or 4x4) ``[R | t]``.
        bounds: (2, 3) min and max corner of the grid, metres.
        resolution: voxels per axis (int: the same count on every axis, as (R, R, R)), or (Rx, Ry, Rz).
        max_misses: a voxel survives being outside the (dilated) mask of at most this many of the views that
            see it (robust to a bad mask).
        dilate_px: extra tolerance in pixels beyond the voxel's own projected half-diagonal.
        min_views: a voxel must also project inside the masks of at least this many views (all of them when
            there are fewer), so that space at the edge of the cameras' frusta, seen by one or two views
            only, is not kept for lack of evidence.
        conservative: test the voxel's footprint (its centre within ``dilate_px`` plus its projected
            half-diagonal of the mask: a superset of the subject, for bounding samples). False: the classic
            centre-in-mask test (closer to the subject's surface, may cut thin parts; for a hull used as a
            shape estimate).
        component_views: in [0, 1]; connected components (26-connected) of the hull whose best voxel lies
            inside the masks of fewer than this share of the views that hold the hull's best voxel are dropped.
            Space close to a camera is seen by few views, and those behind the subject hold it inside their
            silhouettes: with cameras near a small subject (a head 0.5 m from the lenses) such pockets sit
            in the box's corners, apart from the subject, and would make its box as large as the stage's.
            0: every component is kept.

    Returns:
        :class:`HullGrid`.

    Raises:
        ValueError: mismatched list lengths, bad shapes, non-finite cameras or bounds, resolution < 1.
    """
    if not (len(masks) == len(Ks) == len(cam_from_worlds)) or len(masks) == 0:
        raise ValueError(f"masks, Ks and cam_from_worlds must be non-empty lists of the same length, got "
                         f"{len(masks)}, {len(Ks)}, {len(cam_from_worlds)}")
    b = check_bounds(bounds)
    res = np.broadcast_to(np.asarray(resolution, np.int64), (3,))
    if (res < 1).any() or res.max() > 1024:
        raise ValueError(f"resolution must be in 1..1024 per axis, got {resolution!r}")
    if not 0.0 <= component_views <= 1.0:
        raise ValueError(f"component_views must be in [0, 1], got {component_views}")
    if max_misses < 0 or dilate_px < 0 or min_views < 1:
        raise ValueError(f"max_misses and dilate_px must be >= 0 and min_views >= 1, got {max_misses}, {dilate_px}, "
                         f"{min_views}")
    grid = HullGrid(np.zeros(tuple(res), bool), b)
    half_diag = 0.5 * float(np.linalg.norm(grid.voxel_size))
    # Voxels still in the running: carving is incremental, so later views only test what survived.
    alive = np.arange(int(np.prod(res)))
    hits = np.zeros(len(alive), np.int16)
    misses = np.zeros(len(alive), np.int16)
    axes = [(b[0, a] + (np.arange(r) + 0.5) * grid.voxel_size[a]).astype(np.float32) for a, r in enumerate(res)]
    for v, (mask, K, T) in enumerate(zip(masks, Ks, cam_from_worlds)):
        K, T = check_camera(K, T, f"view {v}")
        mask = np.asarray(mask)
        if mask.ndim != 2 or min(mask.shape) < 1:
            raise ValueError(f"view {v}: mask must be (H, W), got shape {mask.shape}")
        mask = mask != 0
        H, W = mask.shape
        # Distance (px) from every pixel to the nearest foreground pixel; 0 on the mask.
        if mask.any():
            dist_px = ndimage.distance_transform_edt(~mask).astype(np.float32)
        else:
            dist_px = np.full(mask.shape, np.inf, np.float32)
        ix, rest = np.divmod(alive, res[1] * res[2])
        iy, iz = np.divmod(rest, res[2])
        R32 = T[:, :3].astype(np.float32)
        x_cam = (axes[0][ix, None] * R32[:, 0] + axes[1][iy, None] * R32[:, 1] + axes[2][iz, None] * R32[:, 2]
                 + T[:, 3].astype(np.float32))
        z = x_cam[:, 2]
        front = z > 1e-6
        z_front = np.where(front, z, np.float32(1.0))
        u, w = pixel_coordinates(K, x_cam, z_front)
        col = np.floor(u + 0.5)
        row = np.floor(w + 0.5)
        seen = front & (col >= 0) & (col <= W - 1) & (row >= 0) & (row <= H - 1)
        ci = np.clip(col, 0, W - 1).astype(np.int64)
        ri = np.clip(row, 0, H - 1).astype(np.int64)
        # + half a pixel diagonal: the centre was rounded to a pixel centre.
        tolerance = dilate_px + (0.5 * np.sqrt(2.0) + K[0, 0] * half_diag / z_front if conservative else 0.0)
        inside = dist_px[ri, ci] <= tolerance
        hits += seen & inside
        misses += seen & ~inside
        keep = misses <= max_misses
        alive, hits, misses = alive[keep], hits[keep], misses[keep]
    occupancy = np.zeros(int(np.prod(res)), bool)
    occupied = hits >= min(min_views, len(masks))
    occupancy[alive[occupied]] = True
    grid.occupancy = occupancy.reshape(tuple(res))
    if component_views > 0 and occupied.any():
        views_inside = np.zeros(int(np.prod(res)), np.int16)
        views_inside[alive[occupied]] = hits[occupied]
        grid.occupancy = _well_seen_components(grid.occupancy, views_inside.reshape(tuple(res)), component_views)
    return grid


def _well_seen_components(occupancy: np.ndarray, views_inside: np.ndarray, share: float) -> np.ndarray:
    """``occupancy`` without the 26-connected components whose largest ``views_inside`` (per voxel, the views
    whose masks hold it) is under ``share`` times the largest of all."""
    labels, count = ndimage.label(occupancy, structure=np.ones((3, 3, 3), bool))
    if count <= 1:
        return occupancy
    best = ndimage.maximum(views_inside, labels, index=np.arange(1, count + 1))
    keep = np.concatenate([[False], np.asarray(best) >= share * float(np.max(best))])
    return keep[labels]


def default_stage_box(cams: Sequence[tuple[np.ndarray, np.ndarray]], size_m: float = 2.5) -> np.ndarray:
    """A generous cube where the cameras look: centred on the point closest (least squares) to all optical
    axes, edge ``size_m`` but no larger than 1.6x the nearest camera's distance to that point."""
    A = np.zeros((3, 3))
    rhs = np.zeros(3)
    centres = []
    for K, T in cams:
        c = camera_centre(T)
        d = pixel_rays(K, T, K[0, 2], K[1, 2])[0]  # the optical axis
        P = np.eye(3) - np.outer(d, d)
        A += P
        rhs += P @ c
        centres.append(c)
    try:
        point = np.linalg.solve(A, rhs) if np.linalg.cond(A) < 1e8 else np.zeros(3)
    except np.linalg.LinAlgError:
        point = np.zeros(3)
    nearest = min(float(np.linalg.norm(c - point)) for c in centres)
    half = min(size_m / 2, 0.8 * nearest)
    return np.stack([point - half, point + half])


def subject_box(masks: Sequence[np.ndarray], Ks: Sequence[np.ndarray], cam_from_worlds: Sequence[np.ndarray],
                stage_box: np.ndarray, resolution: int = 64, max_misses: int = 1, dilate_px: float = 2.0,
                component_views: float = 0.5) -> np.ndarray:
    """(2, 3) box (metres) of the subject: the occupied voxels of a coarse conservative hull over ``stage_box``
    (e.g. :func:`default_stage_box`), grown by one of its voxels. 64^3 over a 2.5 m box (4 cm voxels) only has
    to find the subject, not to shape it. The other arguments are :func:`visual_hull`'s.

    Raises:
        ValueError: the coarse hull is empty (no voxel inside the masks of the views that see it).
    """
    coarse = visual_hull(masks, Ks, cam_from_worlds, stage_box, resolution, max_misses, dilate_px,
                         component_views=component_views)
    return coarse.tight_bounds(margin_m=float(coarse.voxel_size.max()))
