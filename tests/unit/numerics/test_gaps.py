"""Filled holes decided across views: a frame the cameras see through against dark patches on a solid block."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from stages.numerics.gaps import GapConfig, see_through_holes
from tests.unit.numerics.test_hull import look_at

SIZE = 64
BOUNDS = np.array([[-0.45, -0.45, -0.45], [0.45, 0.45, 0.45]])
# A square frame in the x-y plane (its opening 0.3 m wide, 0.15 m deep along z) as four bars (min, max corners).
FRAME = [np.array(b, float) for b in (
    [[-0.3, 0.15, -0.075], [0.3, 0.3, 0.075]], [[-0.3, -0.3, -0.075], [0.3, -0.15, 0.075]],
    [[-0.3, -0.15, -0.075], [-0.15, 0.15, 0.075]], [[0.15, -0.15, -0.075], [0.3, 0.15, 0.075]])]
BLOCK = [np.array([[-0.2, -0.2, -0.2], [0.2, 0.2, 0.2]])]


def ring_cameras(n=12, dist=2.0):
    """n cameras on a ring around the y axis, slightly above the middle, 64 px, the scene filling half the frame."""
    f = 0.5 * SIZE / 2 / np.tan(np.arcsin(0.45 / dist))
    K = np.array([[f, 0, (SIZE - 1) / 2], [0, f, (SIZE - 1) / 2], [0, 0, 1.0]])
    return [(K, look_at(dist * np.array([np.cos(a), 0.1, np.sin(a)])))
            for a in 2 * np.pi * (np.arange(n) + 0.5) / n]


def box_mask(K, T, boxes):
    """(SIZE, SIZE) bool: the pixels whose ray hits one of the axis-aligned boxes (slab test)."""
    R, t = T[:, :3], T[:, 3]
    origin = -R.T @ t
    rows, cols = np.mgrid[0:SIZE, 0:SIZE]
    pix = np.stack([cols.ravel(), rows.ravel(), np.ones(SIZE * SIZE)], 1)
    d = np.linalg.solve(K, pix.T).T @ R
    d = np.where(np.abs(d) < 1e-12, 1e-12, d)
    hit = np.zeros(SIZE * SIZE, bool)
    for lo, hi in boxes:
        t0, t1 = (lo - origin) / d, (hi - origin) / d
        hit |= np.minimum(t0, t1).max(1) <= np.maximum(t0, t1).min(1)
    return hit.reshape(SIZE, SIZE)


def filled(mask):
    """The mask with its enclosed holes filled, and those holes."""
    full = ndimage.binary_fill_holes(mask)
    return full, full & ~mask


def decide(boxes, holes_of=None, config=GapConfig()):
    cams = ring_cameras()
    masks, holes = [], []
    for v, (K, T) in enumerate(cams):
        full, hole = filled(box_mask(K, T, boxes))
        if holes_of is not None:
            hole = holes_of(v, K, T, full)
        masks.append(full)
        holes.append(hole)
    decision = see_through_holes(masks, holes, [K for K, _ in cams], [T for _, T in cams], BOUNDS, config)
    return decision, masks, holes


def test_a_frame_the_cameras_see_through_has_its_holes_opened():
    decision, masks, holes = decide(FRAME)
    seen_through = [v for v, h in enumerate(holes) if h.sum() >= 20]
    assert len(seen_through) >= 4  # the views facing the opening from either side
    for v in seen_through:
        assert all(r["gap"] for r in decision.holes[v]), decision.holes[v]
        assert decision.gaps[v].sum() == holes[v].sum()
    for gap, mask in zip(decision.gaps, masks):
        assert gap.shape == mask.shape and gap.dtype == bool and not (gap & ~mask).any()


def test_dark_patches_on_a_solid_block_stay_filled():
    front = np.array([0.0, 0.0, 0.2])  # the centre of the block's face towards +z

    def patch(v, K, T, full):  # a dark patch around the face's centre, in the views that see that face
        x = T[:, :3] @ front + T[:, 3]
        if (T[:, :3] @ np.array([0.0, 0.0, 1.0]))[2] > -0.2:  # the face turns away from this camera
            return np.zeros_like(full)
        u, w = (K @ (x / x[2]))[:2]
        rows, cols = np.mgrid[0:SIZE, 0:SIZE]
        return ((cols - u) ** 2 + (rows - w) ** 2 <= 4) & full  # 11 cm across, a quarter of the face

    decision, masks, holes = decide(BLOCK, patch)
    patched = [v for v, h in enumerate(holes) if h.any()]
    assert len(patched) >= 3  # the patch is in several views, so the space just behind it gets the votes
    for v in patched:
        assert decision.holes[v] and not any(r["gap"] for r in decision.holes[v]), decision.holes[v]
        assert all(r["blocked"] > 0.9 for r in decision.holes[v])
    assert not any(g.any() for g in decision.gaps)


def test_votes_of_more_views_than_see_the_opening_open_nothing():
    decision, _, holes = decide(FRAME, config=GapConfig(min_votes=13))
    assert not any(g.any() for g in decision.gaps)
    assert sum(len(r) for r in decision.holes) > 0 and all(rec["blocked"] > 0.5 for r in decision.holes for rec in r)


def test_no_holes_and_bad_inputs():
    cams = ring_cameras(4)
    masks = [box_mask(K, T, BLOCK) for K, T in cams]
    Ks, Ts = [K for K, _ in cams], [T for _, T in cams]
    none = see_through_holes(masks, [np.zeros_like(m) for m in masks], Ks, Ts, BOUNDS)
    assert not any(g.any() for g in none.gaps) and none.holes == [[]] * 4
    with pytest.raises(ValueError, match="same length"):
        see_through_holes(masks, masks[:2], Ks, Ts, BOUNDS)
    with pytest.raises(ValueError, match="view 1"):
        see_through_holes(masks, [m if v != 1 else m[:10] for v, m in enumerate(masks)], Ks, Ts, BOUNDS)
    with pytest.raises(ValueError, match="rotation"):
        see_through_holes(masks, masks, Ks, [np.hstack([2 * np.eye(3), np.zeros((3, 1))])] * 4, BOUNDS)


def test_ray_batches_of_any_size_give_the_same_answer():
    from stages.numerics.gaps import _blocked_rays
    from stages.numerics.hull import check_camera

    cams = [check_camera(K, T) for K, T in ring_cameras()]
    masks, holes = zip(*(filled(box_mask(K, T, FRAME)) for K, T in cams))
    v = max(range(len(holes)), key=lambda i: holes[i].sum())
    rows, cols = np.nonzero(masks[v])  # rays through the frame's bars and its opening
    args = (cams[v][0], cams[v][1], rows, cols, list(masks), list(holes), cams, BOUNDS, GapConfig())
    whole = _blocked_rays(*args)
    assert whole.any() and not whole.all()  # the bars block, the opening does not
    np.testing.assert_array_equal(_blocked_rays(*args, chunk=1), whole)
    np.testing.assert_array_equal(_blocked_rays(*args, chunk=1000), whole)


# ---------------------------------------------------------------------------------- the gradient-ratio test

BACKDROP_RATIO = np.array([0.03, -0.02, 0.01], np.float32)
"""The backdrop's ratio d in the synthetic frames below: the stage's inside is lit nearly alike by both gradients."""
SURFACE_RATIO = np.array([0.6, 0.0, 0.0], np.float32)
"""A surface's ratio d in those frames: it faces +x."""


def block_slit(size=SIZE):
    """(size, size) bool: a small rectangle on the block's face in every ring camera's view (BLOCK)."""
    slit = np.zeros((size, size), bool)
    slit[30:34, 28:36] = True
    return slit


def gradient_images(shown_surface):
    """Decoded gradient images (pos, neg) (H, W, 3) of a view: SURFACE_RATIO where ``shown_surface`` (H, W) bool,
    BACKDROP_RATIO elsewhere, at one brightness (under the white light a dark patch and the backdrop look alike)."""
    ratio = np.where(np.asarray(shown_surface, bool)[..., None], SURFACE_RATIO, BACKDROP_RATIO)
    return (0.05 * (1 + ratio)).astype(np.float32), (0.05 * (1 - ratio)).astype(np.float32)


def gradient_frames(seed=0, size=96, noise=0.02):
    """A synthetic view under the two gradients: a disk-shaped subject (mask) on a dim backdrop, two holes inside
    it. Returns (pos, neg, mask with holes filled, holes, slot, patch): the slot shows the backdrop, the patch is
    a dark surface facing +x (ratio (0.6, 0, 0)), as dark as the backdrop under the white light."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:size, 0:size]
    subject = (rows - size / 2) ** 2 + (cols - size / 2) ** 2 < (0.4 * size) ** 2
    slot = subject & (np.abs(cols - 0.35 * size) < 2) & (np.abs(rows - size / 2) < 12)
    patch = subject & (np.abs(cols - 0.65 * size) < 4) & (np.abs(rows - size / 2) < 4)
    level = np.full((size, size), 0.035, np.float32)            # backdrop and dark patch: alike under white light
    level[subject & ~slot & ~patch] = 0.4
    ratio = np.broadcast_to(BACKDROP_RATIO, (size, size, 3)).copy()
    ratio[subject & ~slot] = SURFACE_RATIO                      # every surface faces +x here
    total = (2 * level)[..., None] * (1 + noise * rng.standard_normal((size, size, 3)))
    pos, neg = (total * (1 + ratio) / 2).astype(np.float32), (total * (1 - ratio) / 2).astype(np.float32)
    return pos, neg, subject, slot | patch, slot, patch


def test_a_hole_showing_the_backdrop_opens_a_dark_surface_stays():
    from stages.numerics.gaps import backdrop_holes

    pos, neg, mask, holes, slot, patch = gradient_frames()
    backdrop, records = backdrop_holes(holes, mask, pos, neg)
    np.testing.assert_array_equal(backdrop, slot)
    assert [r["backdrop"] for r in records] == [True, False]           # label order: the slot's column first
    assert records[0]["ratio_distance"] < 0.05 and records[1]["ratio_distance"] == pytest.approx(0.58, abs=0.05)
    assert [r["pixels"] for r in records] == [int(slot.sum()), int(patch.sum())]
    # a hole's brightness under the white light plays no part: the patch matches the backdrop there
    assert np.isclose(pos[patch].sum(-1).mean() + neg[patch].sum(-1).mean(),
                      pos[~mask].sum(-1).mean() + neg[~mask].sum(-1).mean(), rtol=0.05)
    off, _ = backdrop_holes(holes, mask, pos, neg, max_distance=0.0)
    assert not off.any()


def test_a_slot_mostly_covered_by_the_subject_stays_filled():
    """A slot's pixels partly covered by the subject read as the surface's ratio: while most of its pixels show the
    backdrop it opens, once most read as surface its median is a surface's and it stays filled."""
    from stages.numerics.gaps import backdrop_holes

    pos, neg, mask, _, slot, _ = gradient_frames()
    rows, cols = np.nonzero(slot)
    for share, opens in ((1 / 3, True), (2 / 3, False)):
        covered = np.zeros_like(slot)
        k = int(share * len(rows))
        covered[rows[:k], cols[:k]] = True
        total = pos + neg
        mixed_pos = np.where(covered[..., None], total * (1 + 0.6) / 2, pos)       # ratio (0.6, 0, 0) there
        mixed_neg = np.where(covered[..., None], total * (1 - 0.6) / 2, neg)
        mixed_pos[..., 1:], mixed_neg[..., 1:] = pos[..., 1:], neg[..., 1:]
        backdrop, records = backdrop_holes(slot, mask, mixed_pos, mixed_neg)
        assert backdrop.any() == opens, (share, records)


def test_a_hole_far_from_the_outline_is_compared_with_the_whole_backdrop():
    from stages.numerics.gaps import backdrop_holes

    pos, neg, mask, holes, slot, _ = gradient_frames()
    near, _ = backdrop_holes(slot, mask, pos, neg, ring_px=25)
    far, records = backdrop_holes(slot, mask, pos, neg, ring_px=2)      # no backdrop pixel within 2 px
    np.testing.assert_array_equal(near, far)
    assert far.any() and records[0]["ratio_distance"] < 0.05
    # a frame without backdrop pixels has nothing to compare with: the hole stays filled
    none, records = backdrop_holes(slot, np.ones_like(mask), pos, neg, ring_px=2)
    assert not none.any() and records == [{"pixels": int(slot.sum()), "ratio_distance": None, "backdrop": False}]


def test_backdrop_holes_no_holes_and_bad_inputs():
    from stages.numerics.gaps import backdrop_holes

    pos, neg, mask, holes, _, _ = gradient_frames()
    backdrop, records = backdrop_holes(np.zeros_like(holes), mask, pos, neg)
    assert not backdrop.any() and records == []
    with pytest.raises(ValueError, match="share one"):
        backdrop_holes(holes[:10], mask, pos, neg)
    with pytest.raises(ValueError, match="max_distance"):
        backdrop_holes(holes, mask, pos, neg, max_distance=-0.1)
    with pytest.raises(ValueError, match="ring_px"):
        backdrop_holes(holes, mask, pos, neg, ring_px=0)


def test_background_holes_opens_what_either_test_opens():
    """The frame's openings (seen through across the views) and one view's slit only its gradient ratios call
    backdrop: both open, and the counts say which test opened what; a view without gradient images is decided
    across the views only."""
    from stages.numerics.gaps import background_holes

    cams = ring_cameras()
    Ks, Ts = [K for K, _ in cams], [T for _, T in cams]
    masks, holes = map(list, zip(*(filled(box_mask(K, T, BLOCK)) for K, T in cams)))
    slit = block_slit()
    holes[3] = holes[3] | (slit & masks[3])
    gradients = [None] * len(cams)
    gradients[3] = gradient_images(masks[3] & ~slit)
    gaps, counts = background_holes(masks, holes, Ks, Ts, BOUNDS, gradients)
    np.testing.assert_array_equal(gaps[3], slit & masks[3])
    assert counts == {"holes": 1, "seen_through": 0, "by_ratio": 1}
    gaps, counts = background_holes(masks, holes, Ks, Ts, BOUNDS, [None] * len(cams))
    assert not any(g.any() for g in gaps) and counts == {"holes": 1, "seen_through": 0, "by_ratio": 0}
    # read on demand: only the view with holes is asked for its images, and they decide alike
    asked = []

    def loader(i):
        def load():
            asked.append(i)
            return gradients[i]
        return load

    lazy_gaps, lazy_counts = background_holes(masks, holes, Ks, Ts, BOUNDS, [loader(i) for i in range(len(cams))])
    assert asked == [3] and lazy_counts == {"holes": 1, "seen_through": 0, "by_ratio": 1}
    np.testing.assert_array_equal(lazy_gaps[3], slit & masks[3])
    with pytest.raises(ValueError, match="one entry per view"):
        background_holes(masks, holes, Ks, Ts, BOUNDS, [None])
