"""Photometric numerics: eq. 1 normals, alpha, albedo, mask, and the combined maps."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from stages.numerics.photometric import (
    IDEAL_RATIO_NORM,
    PhotometricMaps,
    PhotometricParams,
    albedo_from_white,
    foreground_mask,
    foreground_mask_and_holes,
    gradient_normals,
    normal_alpha,
    open_holes,
    photometric_maps,
)

WHITE = np.array([0.8, 0.9, 0.7], np.float32)


def physics(normals, albedo, white=WHITE):
    """Ideal unoccluded Lambertian images: pos_c = a (1 + 2/3 n_c)/2 E_c, neg_c = a (1 - 2/3 n_c)/2 E_c."""
    n = np.asarray(normals, np.float64)
    a = np.asarray(albedo, np.float64)
    pos = a * (1 + (2 / 3) * n) / 2 * white
    neg = a * (1 - (2 / 3) * n) / 2 * white
    return (pos + neg).astype(np.float32), pos.astype(np.float32), neg.astype(np.float32)


def random_normals(h, w, seed=0):
    n = np.random.default_rng(seed).normal(size=(h, w, 3))
    return (n / np.linalg.norm(n, axis=2, keepdims=True)).astype(np.float32)


def assert_finite(*arrays):
    for a in arrays:
        assert np.isfinite(a).all()


# --------------------------------------------------------------------------------------------- normals


def test_single_pixel_hand_computed():
    pos = np.array([[[0.6, 0.5, 0.4]]], np.float32)
    neg = np.array([[[0.2, 0.5, 0.6]]], np.float32)
    normals, ratio = gradient_normals(pos, neg)
    d = np.array([0.4 / 0.8, 0.0, -0.2 / 1.0])  # (g+ - g-) / (g+ + g-)
    assert normals.shape == (1, 1, 3) and ratio.shape == (1, 1)
    assert normals.dtype == np.float32 and ratio.dtype == np.float32
    np.testing.assert_allclose(ratio[0, 0], np.sqrt(0.29), rtol=1e-6)
    np.testing.assert_allclose(normals[0, 0], d / np.sqrt(0.29), rtol=1e-6)


def test_physics_identity_recovers_normals_exactly():
    n = random_normals(37, 53)
    albedo = np.random.default_rng(1).uniform(0.1, 0.9, (37, 53, 3))
    _, pos, neg = physics(n, albedo)
    est, ratio = gradient_normals(pos, neg)
    np.testing.assert_allclose(est, n, atol=2e-6)
    np.testing.assert_allclose(ratio, IDEAL_RATIO_NORM, atol=2e-6)
    # each channel of d is (2/3) n_axis
    d = est * ratio[..., None]
    np.testing.assert_allclose(d, (2 / 3) * n, atol=2e-6)


def test_axis_normals():
    n = np.array([[[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1]]], np.float32)
    _, pos, neg = physics(n, np.full((1, 4, 1), 0.5))
    est, ratio = gradient_normals(pos, neg)
    np.testing.assert_allclose(est, n, atol=1e-6)
    np.testing.assert_allclose(ratio, 2 / 3, atol=1e-6)


@pytest.mark.parametrize("threads", [1, 2])
def test_large_image_blocks_and_threads_agree(threads):
    # taller than one block of rows, with a ragged last block
    n = random_normals(300, 301, seed=3)
    _, pos, neg = physics(n, 0.5)
    est, ratio = gradient_normals(pos, neg, threads=threads)
    np.testing.assert_allclose(est, n, atol=2e-6)


def test_zero_black_negative_nan_inf_inputs_stay_finite():
    pos = np.zeros((4, 6, 3), np.float32)
    neg = np.zeros((4, 6, 3), np.float32)
    normals, ratio = gradient_normals(pos, neg)
    assert not normals.any() and not ratio.any()
    pos[0, 0] = [np.nan, 0.2, 0.1]
    neg[0, 0] = [0.1, np.inf, 0.1]
    pos[0, 1] = [-0.01, -0.02, 0.0]
    neg[0, 1] = [0.01, 0.0, -0.0]
    pos[0, 2] = [1e-9, 0, 0]
    pos[1, 0] = [np.inf, np.inf, np.inf]
    neg[1, 0] = [np.inf, 1.0, -np.inf]
    pos[1, 1] = [3e38, 3e38, 3e38]
    neg[1, 1] = [-3e38, 0, 0]
    normals, ratio = gradient_normals(pos, neg)
    assert_finite(normals, ratio)
    norms = np.linalg.norm(normals, axis=2)
    assert np.all((np.abs(norms - 1) < 1e-5) | (norms == 0))
    # a vanishing signal fades continuously: d = (p - n) / max(p + n, eps)
    assert ratio[0, 2] == pytest.approx(1e-9 / 1e-6, rel=1e-4)


def test_mask_zeroes_normals():
    n = random_normals(5, 5)
    _, pos, neg = physics(n, 0.5)
    mask = np.zeros((5, 5), bool)
    mask[1:3, 2:4] = True
    est, ratio = gradient_normals(pos, neg, mask=mask)
    np.testing.assert_allclose(est[mask], n[mask], atol=2e-6)
    assert not est[~mask].any()
    np.testing.assert_allclose(ratio, 2 / 3, atol=2e-6)  # ratio is not masked


def test_shape_checks():
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        gradient_normals(np.zeros((4, 4)), np.zeros((4, 4)))
    with pytest.raises(ValueError, match="neg"):
        gradient_normals(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))
    with pytest.raises(ValueError, match="white_reference"):
        albedo_from_white(np.zeros((4, 4, 3)), [1.0, 0.0, 1.0])


# ----------------------------------------------------------------------------------------------- alpha


def _alpha_for(albedo, ratio, params=PhotometricParams(), **kw):
    full = np.broadcast_to(np.asarray(albedo, np.float32) * WHITE, (1, 1, 3)).copy()
    return float(normal_alpha(np.full((1, 1), ratio, np.float32), full, WHITE, params=params, **kw)[0, 0])


def test_alpha_ideal_point_is_one():
    assert _alpha_for(0.5, 2 / 3) == pytest.approx(1.0)


def test_alpha_terms_are_half_at_thresholds():
    p = PhotometricParams()
    assert _alpha_for(p.min_signal, 2 / 3) == pytest.approx(0.5, abs=1e-5)
    assert _alpha_for(0.5, p.ratio_min) == pytest.approx(0.5, abs=1e-5)
    assert _alpha_for(0.5, p.ratio_max) == pytest.approx(0.5, abs=1e-5)
    assert _alpha_for(0.5 * p.min_signal, 2 / 3) == pytest.approx(0.0)
    assert _alpha_for(0.5, 0.1) == 0.0
    assert _alpha_for(0.5, 1.4) == 0.0
    # the darkest channel decides the signal term
    assert _alpha_for([0.5, 0.5, 0.01], 2 / 3) < 0.5


def test_alpha_absolute_signal_floor():
    p = PhotometricParams(min_signal=0.0, min_signal_abs=0.05)
    full = np.full((1, 1, 3), 0.05, np.float32)
    a = normal_alpha(np.full((1, 1), 2 / 3, np.float32), full, WHITE, params=p)
    assert a[0, 0] == pytest.approx(0.5, abs=1e-5)


def test_alpha_is_continuous_and_monotone_in_signal():
    levels = np.linspace(0.0, 0.1, 201)
    alphas = np.array([_alpha_for(a, 2 / 3) for a in levels])
    assert np.all(np.diff(alphas) >= -1e-7)
    assert np.max(np.abs(np.diff(alphas))) < 0.05  # no jump
    assert alphas[0] == 0.0 and alphas[-1] == pytest.approx(1.0)


def test_alpha_clipped_and_mask():
    full = np.full((2, 2, 3), 0.5, np.float32) * WHITE
    ratio = np.full((2, 2), 2 / 3, np.float32)
    clip_pos = np.array([[True, False], [False, False]])
    clip_neg = np.array([[False, True], [False, False]])
    mask = np.array([[True, True], [True, False]])
    a = normal_alpha(ratio, full, WHITE, clipped=[clip_pos, clip_neg, np.zeros((2, 2), bool)],
                     mask=mask)
    np.testing.assert_allclose(a, [[0, 0], [1, 0]])
    stacked = normal_alpha(ratio, full, WHITE, clipped=np.stack([clip_pos, clip_neg], -1))
    np.testing.assert_allclose(stacked, [[0, 0], [1, 1]])
    assert a.dtype == np.float32


def test_alpha_nan_inputs():
    full = np.array([[[np.nan, 0.5, 0.5], [np.inf, np.inf, np.inf]]], np.float32)
    a = normal_alpha(np.array([[np.nan, np.inf]], np.float32), full, WHITE)
    assert_finite(a)
    assert np.all((a >= 0) & (a <= 1))


# ---------------------------------------------------------------------------------------------- albedo


def test_albedo_from_white():
    full = np.array([[[0.4, 0.45, 0.35], [8.0, 0.0, -0.1]], [[np.nan, 0.9, 0.7], [0.4, 0.45, 0.35]]], np.float32)
    mask = np.array([[True, True], [True, False]])
    alb = albedo_from_white(full, WHITE, mask=mask, albedo_max=2.0)
    assert alb.dtype == np.float32 and alb.shape == (2, 2, 3)
    np.testing.assert_allclose(alb[0, 0], 0.5, rtol=1e-6)
    np.testing.assert_allclose(alb[0, 1], [2.0, 0.0, 0.0])  # clipped high, zero and negative -> 0
    np.testing.assert_allclose(alb[1, 0], [0.0, 1.0, 1.0], rtol=1e-6)  # NaN -> 0
    np.testing.assert_allclose(alb[1, 1], 0.0)  # outside the mask


# ------------------------------------------------------------------------------------------------ mask


def _scene(h=240, w=180, seed=0):
    """Dim structured background (2-5% grey), an elliptical subject with a dark 'hair' cap, a hand-loop gap."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    bg_level = 0.035 + 0.012 * np.sin(xx / 7.0) * np.cos(yy / 11.0) + 0.004 * (yy / h)
    plate = np.repeat(bg_level[..., None], 3, axis=2) * np.array([1.0, 0.95, 1.05])
    body = ((yy - 130) / 90.0) ** 2 + ((xx - 90) / 50.0) ** 2 < 1
    gap = ((yy - 130) / 14.0) ** 2 + ((xx - 90) / 12.0) ** 2 < 1  # a real hole (background seen through)
    hair = body & (yy < 70)
    eye = ((yy - 100) / 2.0) ** 2 + ((xx - 80) / 2.0) ** 2 < 1  # a tiny dark spot inside the subject
    subject = body & ~gap
    tex = 0.35 + 0.15 * np.sin(xx / 3.0 + yy / 5.0)
    img = plate.copy()
    img[subject] = (tex[subject, None] * np.array([0.9, 0.7, 0.6]))
    img[hair & ~gap] = 0.08  # dark hair: 60-130% above the plate
    img[eye] = plate[eye]  # looks exactly like background
    noise = 0.002
    img = img + rng.normal(0, noise, img.shape)
    plate_obs = plate + rng.normal(0, noise, plate.shape)
    img[5, 5] = 0.9  # a hot pixel in the background: a speck the opening removes
    return img.astype(np.float32), plate_obs.astype(np.float32), subject, hair & subject


def _iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


def test_mask_with_clean_plate():
    img, plate, subject, _ = _scene()
    mask = foreground_mask(img, plate)
    assert mask.dtype == bool and mask.shape == img.shape[:2]
    assert _iou(mask, subject) > 0.97
    assert not mask[5, 5]  # speck removed
    assert mask[100, 80]  # small dark hole inside the subject filled
    assert not mask[130, 90]  # the large enclosed gap stays background


def test_mask_and_holes_names_the_filled_hole_and_nothing_else():
    img, plate, subject, _ = _scene()
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    patch = (yy - 175) ** 2 + (xx - 100) ** 2 <= 16  # 49 px that look like the backdrop, under max_hole's 86
    img[patch] = plate[patch]
    mask, holes = foreground_mask_and_holes(img, plate)
    np.testing.assert_array_equal(mask, foreground_mask(img, plate))
    assert holes.dtype == bool and holes.shape == mask.shape and not (holes & ~mask).any()
    assert mask[175, 100] and holes[175, 100]  # filled, and named as filled
    assert not holes[130, 90]  # the large gap was not filled, so it is no filled hole
    assert not holes[100, 80]  # the 2 px eye is gone in the majority filter, before any hole is filled
    lab, n = ndimage.label(holes)
    assert n == 1 and 30 <= holes.sum() <= 49  # the patch (its rim may close), no other pixel
    assert not foreground_mask_and_holes(img, plate, PhotometricParams(max_hole=0.0))[1].any()
    empty_mask, empty_holes = foreground_mask_and_holes(np.zeros((40, 30, 3), np.float32))
    assert not empty_mask.any() and not empty_holes.any() and empty_holes.shape == (40, 30)


def test_open_holes_clears_the_gap_and_caps_its_new_rim():
    h, w = 12, 12
    normal_alpha = np.zeros((h, w, 4), np.float32)
    normal_alpha[..., 2] = 1.0
    normal_alpha[..., 3] = 0.9
    albedo = np.full((h, w, 3), 0.5, np.float32)
    mask = np.ones((h, w), bool)
    gaps = np.zeros((h, w), bool)
    gaps[5:7, 5:7] = True
    na, alb, m = open_holes(normal_alpha, albedo, mask, gaps, PhotometricParams(edge_px=1, edge_alpha=0.25))
    assert not m[5:7, 5:7].any() and m.sum() == h * w - 4
    assert (na[5:7, 5:7] == 0).all() and (alb[5:7, 5:7] == 0).all()
    ring = np.zeros((h, w), bool)
    ring[4:8, 4:8] = True
    ring[5:7, 5:7] = False  # the 12 pixels around the opened 2 x 2 (8-connected)
    np.testing.assert_array_equal(na[..., 3] == np.float32(0.25), ring)
    assert (na[~ring & m, 3] == np.float32(0.9)).all() and (alb[m] == 0.5).all()
    assert (normal_alpha[5:7, 5:7, 3] == 0.9).all()  # the inputs are not changed
    with pytest.raises(ValueError, match="gaps"):
        open_holes(normal_alpha, albedo, mask, gaps[:5])
    with pytest.raises(ValueError, match="albedo"):
        open_holes(normal_alpha, albedo[..., 0], mask, gaps)


def test_mask_without_plate_thresholds_luminance():
    img, _, subject, hair = _scene()
    mask = foreground_mask(img)
    assert _iou(mask, subject) > 0.97
    assert not mask[5, 5]
    # hair darker than no_plate_threshold x the bright level is lost without a plate (documented)
    img[hair] = 0.045
    assert _iou(foreground_mask(img), subject & ~hair) > 0.95


def test_mask_empty_and_black():
    assert not foreground_mask(np.zeros((40, 30, 3), np.float32)).any()
    plate = np.full((40, 30, 3), 0.03, np.float32)
    assert not foreground_mask(plate.copy(), plate).any()


def test_mask_subject_touching_frame_edge_is_kept():
    img = np.full((60, 60, 3), 0.03, np.float32)
    img[30:, 20:40] = 0.5  # legs cut by the bottom of the frame
    mask = foreground_mask(img)
    assert mask[45:, 20:40].all()  # not eaten from the frame edge (only the free corners round off)
    assert mask[31:, 21:39].all() and not mask[:29].any() and not mask[:, :19].any()


# ---------------------------------------------------------------------------------------------- driver


def test_photometric_maps_smoke_and_semantics():
    img, plate, subject, _ = _scene()
    h, w = img.shape[:2]
    n = random_normals(h, w, seed=5)
    albedo = np.where(subject[..., None], 0.5, 0.0)
    full, pos, neg = physics(n, albedo)
    full = np.where(subject[..., None], full, img)
    pos = np.where(subject[..., None], pos, img / 2)
    neg = np.where(subject[..., None], neg, img / 2)
    clipped = np.zeros((h, w), bool)
    clipped[120:124, 60:64] = True
    maps = photometric_maps(full, pos, neg, clipped, WHITE, background=plate)
    assert isinstance(maps, PhotometricMaps)
    assert maps.normals.shape == (h, w, 3) and maps.normals.dtype == np.float32
    assert maps.alpha.shape == (h, w) and maps.alpha.dtype == np.float32
    assert maps.albedo.shape == (h, w, 3) and maps.albedo.dtype == np.float32
    assert maps.mask.shape == (h, w) and maps.mask.dtype == bool
    assert maps.ratio_norm.shape == (h, w)
    assert_finite(maps.normals, maps.alpha, maps.albedo, maps.ratio_norm)
    inside = maps.mask & subject & ~clipped
    np.testing.assert_allclose(maps.normals[inside], n[inside], atol=1e-5)
    np.testing.assert_allclose(maps.albedo[inside], 0.5, atol=1e-5)
    # pixels touching the background (8-connected) are mixed pixels: in the mask, alpha capped (invalid)
    from scipy import ndimage

    edge = maps.mask & ~ndimage.binary_erosion(maps.mask, np.ones((3, 3), bool), border_value=1)
    assert 0 < edge.sum() < 0.1 * maps.mask.sum()
    assert (maps.alpha[inside & ~edge] > 0.99).all()
    assert (maps.alpha[edge] <= 0.25).all()
    no_edge = photometric_maps(full, pos, neg, clipped, WHITE, background=plate,
                               params=PhotometricParams(edge_px=0))
    assert (no_edge.alpha[inside] > 0.99).all()
    np.testing.assert_array_equal(no_edge.alpha[~edge], maps.alpha[~edge])
    with pytest.raises(ValueError, match="edge_px"):
        PhotometricParams(edge_px=-1)
    assert (maps.alpha[clipped] == 0).all()
    assert not maps.normals[~maps.mask].any() and not maps.albedo[~maps.mask].any()
    assert (maps.alpha[~maps.mask] == 0).all()
    # precomputed mask, float64 inputs, threads=1 give the same maps
    again = photometric_maps(full.astype(np.float64), pos, neg, [clipped], WHITE, mask=maps.mask, threads=1)
    np.testing.assert_array_equal(again.alpha, maps.alpha)
    np.testing.assert_array_equal(again.normals, maps.normals)


@pytest.mark.parametrize("level", [0.0, 1.0])
def test_photometric_maps_black_and_saturated_frames(level):
    img = np.full((32, 32, 3), level, np.float32)
    clipped = np.full((32, 32), level >= 1.0)
    maps = photometric_maps(img, img, img, clipped, WHITE, mask=np.ones((32, 32), bool))
    assert_finite(maps.normals, maps.alpha, maps.albedo, maps.ratio_norm)
    assert (maps.alpha == 0).all()
    assert not maps.normals.any()  # pos == neg: d = 0, normal undefined -> 0
    maps = photometric_maps(img, img, img, None, WHITE)  # mask from the image itself
    assert_finite(maps.normals, maps.alpha, maps.albedo, maps.ratio_norm)


def test_mask_large_speckled_subject_with_and_without_plate():
    # the subject covers ~70% of the frame and its albedo varies per pixel (some pixels as dark as the
    # background): the plate's noise estimate must not depend on coverage, and specks/pinholes are voted away
    rng = np.random.default_rng(2)
    h, w = 120, 100
    yy, xx = np.mgrid[0:h, 0:w]
    subject = ((yy - 60) / 58.0) ** 2 + ((xx - 50) / 46.0) ** 2 < 1
    plate = (0.03 + 0.01 * np.sin(xx / 5.0))[..., None] * np.ones(3)
    img = plate + rng.normal(0, 0.002, (h, w, 3))
    albedo = rng.uniform(0.05, 0.8, (h, w, 1))
    img = np.where(subject[..., None], albedo * WHITE, img).astype(np.float32)
    plate_obs = (plate + rng.normal(0, 0.002, plate.shape)).astype(np.float32)
    assert subject.mean() > 0.65
    assert _iou(foreground_mask(img, plate_obs), subject) > 0.97
    assert _iou(foreground_mask(img), subject) > 0.95


def test_mask_edge_at_half_coverage():
    # anti-aliased disc, slightly blurred (demosaic-like): the plate difference alone takes the whole rim;
    # edge refinement keeps pixels at least half covered
    from scipy.ndimage import gaussian_filter

    h, w, ss = 80, 80, 8
    yy, xx = (np.mgrid[0 : h * ss, 0 : w * ss] + 0.5) / ss
    cover = (((yy - 40.3) ** 2 + (xx - 39.6) ** 2) < 25.0**2).reshape(h, ss, w, ss).mean(axis=(1, 3))
    rng = np.random.default_rng(4)
    plate = np.full((h, w, 3), 0.03) * np.array([1.0, 0.9, 1.1])
    subject = np.array([0.45, 0.3, 0.25])
    img = cover[..., None] * subject + (1 - cover[..., None]) * plate
    img = np.stack([gaussian_filter(img[..., c], 0.6) for c in range(3)], -1)
    img = (img + rng.normal(0, 0.001, img.shape)).astype(np.float32)
    plate_obs = (plate + rng.normal(0, 0.001, plate.shape)).astype(np.float32)
    truth = cover >= 0.5
    refined = foreground_mask(img, plate_obs)
    rough = foreground_mask(img, plate_obs, PhotometricParams(refine_edges=False))
    assert _iou(refined, truth) > 0.98
    assert _iou(refined, truth) > _iou(rough, truth) + 0.02
    assert _iou(foreground_mask(img), truth) > 0.98  # without a plate: exterior neighbours as background
