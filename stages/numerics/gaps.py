"""Which of a mask's filled holes are background: gaps the cameras see through, told from dark patches.

Pure numerics, arrays in and arrays out (docs/CONTRACTS.md conventions: stage frame = world frame, metres; OpenCV
cameras with ``x_cam = R @ x_world + t``; pixel ``(row i, column j)`` has its centre at ``(u, v) = (j, i)``).

Under the white light alone one view cannot tell a gap between an arm and the torso, where the backdrop shows
through, from a dark patch of clothing in shade that looks like the backdrop: both are background the silhouette
encloses. The mask step fills both (:func:`stages.numerics.photometric.foreground_mask`), and the filled gaps web
the surface the neural SDF fits. Two tests tell them apart:

- Across views (:func:`see_through_holes`): the space in a gap is empty, so every camera that looks through the
  gap sees backdrop there: the points on a gap pixel's ray fall in holes of several views, or outside their
  silhouettes. A dark patch is a surface with the body behind it: its ray runs on through the body's inside, which
  the other cameras see as foreground. It needs a second view that sees the gap.
- In one view, under the gradient illuminations (:func:`backdrop_holes`): a surface's ratio
  ``d = (g+ - g-) / (g+ + g-)`` (eq. 1's normal before normalising) has the length of its normal's response, while
  the backdrop behind the subject keeps the backdrop's own ratio, which the pixels around the silhouette show.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy import ndimage

from artifacts.camera import camera_centre, check_bounds, pixel_coordinates, pixel_rays, ray_box
from calibration.light import gradient_ratio
from pipeline.config import Documented, checked
from stages.numerics.hull import check_camera

__all__ = ["GapConfig", "GapDecision", "background_holes", "backdrop_holes", "see_through_holes"]


GradientPair = tuple[np.ndarray, np.ndarray]
"""A view's decoded gradient images ``(pos, neg)``, each (H, W, 3)."""


@dataclass(frozen=True)
class GapConfig(Documented):
    """How the filled holes of the masks are told apart (:func:`see_through_holes`, :func:`backdrop_holes`)."""

    enabled: bool = True
    """Decide the holes (across views, and by their gradient ratios when ``backdrop_ratio_max`` is above 0); off:
    every filled hole stays foreground, as the mask step left it."""
    step_m: float = checked(0.002, gt=0.0)
    """Spacing of the points tested along a hole pixel's ray (metres): finer than the narrowest gap worth
    opening."""
    min_votes: int = checked(2, ge=1)
    """A point on a hole's ray is empty space when it projects into the holes of at least this many views (the
    hole's own view counts). The limit of the test: a dark patch of width D that two views an angle t apart both
    leave as a hole has its rays empty for about D / tan(t) behind it, and opens when that reaches through the
    body (on a synthetic 0.4 m block seen by twelve cameras 30 deg apart: patches 0.11 m across stay filled,
    0.22 m ones open)."""
    max_rays: int = checked(256, ge=1)
    """Rays traced per hole at most (evenly spread over its pixels): the decision's cost on full-size frames."""
    max_blocked: float = checked(0.5, ge=0.0, le=1.0)
    """A hole is a gap when at most this fraction of its rays meet a point that is not empty space."""
    backdrop_ratio_max: float = checked(0.2, ge=0.0, le=2.0)
    """A hole is also background when its median gradient ratio lies within this distance (the 3-vector's
    Euclidean norm) of the backdrop's around it (:func:`backdrop_holes`); 0 = that test off. Over the 143 filled
    holes of fourteen simulated actions (the default capture, the unseen one, the subject panel) the 101 true gaps
    lie 0.00-0.21 from the backdrop and the 34 dark patches 0.52-0.79 (bench/bench_gaps.py scores the rule)."""


@dataclass(frozen=True, eq=False)
class GapDecision:
    """Outcome of :func:`see_through_holes`.

    Attributes:
        gaps: per view (H, W) bool: the hole pixels decided as seen-through background.
        holes: per view, one record per hole (8-connected component of the view's hole pixels):
            ``pixels``, ``rays`` (traced), ``blocked`` (the fraction of them that meet a point that is not empty
            space) and ``gap`` (bool).
    """

    gaps: list[np.ndarray]
    holes: list[list[dict]]


def _project(points: np.ndarray, K: np.ndarray, T: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """Nearest pixel (rows, cols) (N,) int64 of world points (N, 3) and whether it is in the image, in front."""
    x_cam = points @ T[:, :3].T + T[:, 3]
    z = x_cam[:, 2]
    front = z > 1e-6
    u, v = pixel_coordinates(K, x_cam, np.where(front, z, 1.0))
    col, row = np.floor(u + 0.5), np.floor(v + 0.5)
    h, w = shape
    seen = front & (col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1)
    return np.clip(row, 0, h - 1).astype(np.int64), np.clip(col, 0, w - 1).astype(np.int64), seen


def see_through_holes(
    masks: Sequence[np.ndarray],
    holes: Sequence[np.ndarray],
    Ks: Sequence[np.ndarray],
    cam_from_worlds: Sequence[np.ndarray],
    bounds: np.ndarray,
    config: GapConfig = GapConfig(),
) -> GapDecision:
    """The holes of the masks that are gaps seen through, decided across views.

    Each hole of each view (8-connected) sends rays through up to ``max_rays`` of its pixels, tested every
    ``step_m`` inside ``bounds``. A point is empty space when it projects outside the (filled) masks of two views
    or more (the visual hull's test, one bad mask allowed) or into the holes of ``min_votes`` views or more. A
    hole is a gap when at most ``max_blocked`` of its rays meet a point that is not empty.

    Args:
        masks: per view (H, W) bool foreground with the holes filled.
        holes: per view (H, W) bool: the enclosed background the mask step filled (inside ``masks``).
        Ks: per view (3, 3) intrinsics.
        cam_from_worlds: per view (3, 4) (or 4x4) ``[R | t]``.
        bounds: (2, 3) min and max corner of the subject's box, metres.
        config: thresholds, see :class:`GapConfig`.

    Returns:
        :class:`GapDecision`.

    Raises:
        ValueError: mismatched list lengths, a hole map of another shape than its mask, bad cameras or bounds.
    """
    n = len(masks)
    if not (n == len(holes) == len(Ks) == len(cam_from_worlds)) or n == 0:
        raise ValueError(f"masks, holes, Ks and cam_from_worlds must be non-empty lists of the same length, got "
                         f"{n}, {len(holes)}, {len(Ks)}, {len(cam_from_worlds)}")
    masks = [np.asarray(m) != 0 for m in masks]
    holes = [np.asarray(h) != 0 for h in holes]
    for v, (m, h) in enumerate(zip(masks, holes)):
        if m.ndim != 2 or h.shape != m.shape:
            raise ValueError(f"view {v}: holes {h.shape} must be an (H, W) map like its mask {m.shape}")
    cams = [check_camera(K, T, f"view {v}") for v, (K, T) in enumerate(zip(Ks, cam_from_worlds))]
    box = check_bounds(bounds)
    gaps = [np.zeros(m.shape, bool) for m in masks]
    records: list[list[dict]] = [[] for _ in masks]
    for v, ((K, T), h) in enumerate(zip(cams, holes)):
        labels, count = ndimage.label(h, structure=np.ones((3, 3), bool))
        if count == 0:
            continue
        rows, cols = np.nonzero(labels)
        ids = labels[rows, cols]
        order = np.argsort(ids, kind="stable")
        rows, cols, ids = rows[order], cols[order], ids[order]
        pixels = np.bincount(ids, minlength=count + 1)
        first = np.concatenate([[0], np.cumsum(pixels[1:])])
        # up to max_rays pixels of each hole, evenly spread over its pixels in raster order
        picks = np.concatenate([first[i - 1] + np.unique(np.linspace(0, pixels[i] - 1, min(pixels[i], config.max_rays))
                                                         .round().astype(np.int64)) for i in range(1, count + 1)])
        blocked = _blocked_rays(K, T, rows[picks], cols[picks], masks, holes, cams, box, config)
        traced = np.bincount(ids[picks], minlength=count + 1)
        hits = np.bincount(ids[picks], weights=blocked, minlength=count + 1)
        for i in range(1, count + 1):
            share = float(hits[i] / traced[i])
            is_gap = share <= config.max_blocked
            records[v].append({"pixels": int(pixels[i]), "rays": int(traced[i]), "blocked": round(share, 4),
                               "gap": bool(is_gap)})
            if is_gap:
                gaps[v] |= labels == i
    return GapDecision(gaps, records)


def backdrop_holes(holes: np.ndarray, mask: np.ndarray, pos: np.ndarray, neg: np.ndarray,
                   max_distance: float = 0.2, ring_px: int = 25, min_ring: int = 16) -> tuple[np.ndarray, list[dict]]:
    """The filled holes of one view whose gradient ratios are the backdrop's.

    A surface under the two gradient illuminations has the ratio :func:`gradient_ratio` of its normal (0.54-0.94
    long on the dark patches of clothing in shade the simulator's captures leave as holes: each gradient lights a
    surface's visible half of the sphere unevenly), while the backdrop a gap shows keeps the backdrop's ratio,
    which its pixels just outside the silhouette show (0.00-0.18 long in those captures: the stage's inside is
    lit nearly alike by both). So a hole whose median ratio (over its pixels, per channel) lies within ``max_distance``
    of the median over the backdrop pixels within ``ring_px`` of it is background, whatever its brightness under
    the white light. Pixels of the hole that are partly covered by the subject pull its median towards a surface's,
    so a slot a few pixels wide opens only while its backdrop pixels are most of it.

    Args:
        holes: (H, W) bool, the enclosed background the mask step filled (inside ``mask``).
        mask: (H, W) bool, the foreground with those holes filled.
        pos, neg: (H, W, 3) decoded linear gradient images (the first three channels are used).
        max_distance: largest Euclidean distance of the two median ratios (3-vectors) for a backdrop hole.
        ring_px: the backdrop compared with: pixels outside ``mask`` (and not in a hole) within this distance of
            the hole; when fewer than ``min_ring`` are, every backdrop pixel of the frame.
        min_ring: least backdrop pixels of a ring.

    Returns:
        ``(backdrop, records)``: (H, W) bool, the pixels of the holes decided as backdrop; one record per hole
        (8-connected component of ``holes``): ``pixels``, ``ratio_distance`` (None when the hole or the frame has
        no pixel with a defined ratio) and ``backdrop`` (bool).

    Raises:
        ValueError: maps of different shapes, a negative ``max_distance`` or a ``ring_px`` below 1.
    """
    holes = np.asarray(holes) != 0
    mask = np.asarray(mask) != 0
    if holes.ndim != 2 or mask.shape != holes.shape or np.shape(pos)[:2] != holes.shape:
        raise ValueError(f"holes {holes.shape}, mask {mask.shape} and pos {np.shape(pos)} must share one (H, W)")
    if not max_distance >= 0 or ring_px < 1 or min_ring < 1:
        raise ValueError(f"max_distance must be >= 0 and ring_px, min_ring >= 1, got {max_distance}, {ring_px}, "
                         f"{min_ring}")
    backdrop = np.zeros(holes.shape, bool)
    labels, count = ndimage.label(holes, structure=np.ones((3, 3), bool))
    if count == 0:
        return backdrop, []
    ratio = gradient_ratio(pos, neg)
    defined = np.all(np.isfinite(ratio), axis=-1)
    outside = ~mask & ~holes & defined
    frame_backdrop = np.median(ratio[outside], axis=0) if outside.sum() >= min_ring else None
    records = []
    h, w = holes.shape
    for i, box in enumerate(ndimage.find_objects(labels), start=1):
        r0, r1 = max(box[0].start - ring_px, 0), min(box[0].stop + ring_px, h)
        c0, c1 = max(box[1].start - ring_px, 0), min(box[1].stop + ring_px, w)
        hole = labels[r0:r1, c0:c1] == i
        pixels = int(hole.sum())
        inside = hole & defined[r0:r1, c0:c1]
        ring = (ndimage.distance_transform_edt(~hole) <= ring_px) & outside[r0:r1, c0:c1]
        reference = np.median(ratio[r0:r1, c0:c1][ring], axis=0) if ring.sum() >= min_ring else frame_backdrop
        if reference is None or not inside.any():
            records.append({"pixels": pixels, "ratio_distance": None, "backdrop": False})
            continue
        distance = float(np.linalg.norm(np.median(ratio[r0:r1, c0:c1][inside], axis=0) - reference))
        is_backdrop = distance <= max_distance
        records.append({"pixels": pixels, "ratio_distance": round(distance, 4), "backdrop": bool(is_backdrop)})
        if is_backdrop:
            backdrop[r0:r1, c0:c1] |= hole
    return backdrop, records


def background_holes(masks: Sequence[np.ndarray], holes: Sequence[np.ndarray], Ks: Sequence[np.ndarray],
                     cam_from_worlds: Sequence[np.ndarray], bounds: np.ndarray,
                     gradients: Sequence[GradientPair | Callable[[], GradientPair | None] | None],
                     config: GapConfig = GapConfig()) -> tuple[list[np.ndarray], dict[str, int]]:
    """The filled holes either test calls background: seen through across the views (:func:`see_through_holes`)
    or, where a view's gradient images are given and ``config.backdrop_ratio_max`` is above 0, whose gradient
    ratios are the backdrop's (:func:`backdrop_holes`).

    Args:
        masks, holes, Ks, cam_from_worlds, bounds: as :func:`see_through_holes`.
        gradients: per view ``(pos, neg)`` (H, W, 3) decoded gradient images, or None (that view's holes are
            decided across the views only), or a function of no argument that returns either: called only for a
            view with holes while the ratio test is on, so a caller that reads images on demand holds one view's
            at a time (a 24 MP pair is 0.6 GB of float32).
        config: both tests' thresholds.

    Returns:
        ``(gaps, counts)``: per view (H, W) bool, the hole pixels that are background; ``holes`` (all views'),
        ``seen_through`` (opened across the views) and ``by_ratio`` (opened by the ratios alone).
    """
    if len(gradients) != len(masks):
        raise ValueError(f"gradients must have one entry per view ({len(masks)}), got {len(gradients)}")
    decision = see_through_holes(masks, holes, Ks, cam_from_worlds, bounds, config)
    seen_through = sum(r["gap"] for per_view in decision.holes for r in per_view)
    gaps, by_ratio = list(decision.gaps), 0
    if config.backdrop_ratio_max > 0:
        for i, (mask, hole, pair) in enumerate(zip(masks, holes, gradients)):
            if pair is None or not np.any(hole):
                continue
            pair = pair() if callable(pair) else pair
            if pair is None:
                continue
            backdrop, records = backdrop_holes(hole, mask, pair[0], pair[1], config.backdrop_ratio_max)
            # both tests label the hole map's 8-connected components alike: their records pair up
            by_ratio += sum(mine["backdrop"] and not theirs["gap"] for mine, theirs in zip(records, decision.holes[i]))
            gaps[i] = gaps[i] | backdrop
    return gaps, {"holes": sum(len(per_view) for per_view in decision.holes), "seen_through": int(seen_through),
                  "by_ratio": int(by_ratio)}


def _blocked_rays(K: np.ndarray, T: np.ndarray, rows: np.ndarray, cols: np.ndarray, masks: list[np.ndarray],
                  holes: list[np.ndarray], cams: list[tuple[np.ndarray, np.ndarray]], box: np.ndarray,
                  config: GapConfig, chunk: int = 1 << 18) -> np.ndarray:
    """(N,) bool: the ray through pixel (rows, cols) of camera (K, T) meets a point inside ``box`` that is not empty
    space (:func:`see_through_holes`). The points go through in batches of about ``chunk`` (whole rays), so memory
    stays bounded however many holes a full-size frame has."""
    dirs, _ = pixel_rays(K, T, cols.astype(np.float64), rows.astype(np.float64))
    dirs = dirs.reshape(-1, 3)
    origin = camera_centre(T)
    t_in, t_out = ray_box(origin, dirs, box)
    steps = np.maximum(np.floor((t_out - t_in) / config.step_m).astype(np.int64) + 1, 0)
    blocked = np.zeros(rows.size, bool)
    per_batch = max(1, chunk // max(int(steps.max(initial=1)), 1))
    for first in range(0, rows.size, per_batch):
        rays = np.arange(first, min(first + per_batch, rows.size))
        counts = steps[rays]
        ray = np.repeat(rays, counts)
        offsets = np.arange(ray.size) - np.repeat(np.cumsum(counts) - counts, counts)
        points = origin + dirs[ray] * (t_in[ray] + offsets * config.step_m)[:, None]
        outside = np.zeros(ray.size, np.int16)
        votes = np.zeros(ray.size, np.int16)
        for (Kw, Tw), mask, hole in zip(cams, masks, holes):
            r, c, seen = _project(points, Kw, Tw, mask.shape)
            outside += seen & ~mask[r, c]
            votes += seen & hole[r, c]
            # a point found empty needs no more views: most of a ray's points are outside the body
            undecided = (outside < 2) & (votes < config.min_votes)
            if not undecided.all():
                points, ray, outside, votes = points[undecided], ray[undecided], outside[undecided], votes[undecided]
        blocked |= np.bincount(ray, minlength=rows.size).astype(bool)
    return blocked
