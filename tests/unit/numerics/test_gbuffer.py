"""Tests of stages.numerics.gbuffer (reprojected G-buffers) on analytic spheres seen by synthetic cameras."""
from __future__ import annotations

import numpy as np
import pytest

from stages.numerics.gbuffer import (INTERPOLATIONS, SOURCE_EDGE_WEIGHT, WEIGHTINGS, SourceView,
                                     _sample_consistent, camera_centre, depth_edges, fade_rim_normals, fuse_normals,
                                     nearest_views, reproject_gbuffer, shading_normals)
from stages.numerics.metrics import angular_error_deg
from stages.numerics.raycast import camera_rays
from synthetic.rig import look_at as rig_look_at

H = W = 64
K = np.array([[150.0, 0.0, 31.5], [0.0, 150.0, 31.5], [0.0, 0.0, 1.0]])
MAIN = (np.zeros(3), 0.5)  # centre, radius (metres)


def look_at(eye, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """OpenCV cam_from_world (3, 4) of a camera at ``eye`` looking at ``target``, world +y up."""
    return rig_look_at(np.asarray(eye, float), np.asarray(target, float))


def ring_camera(angle_deg: float, radius: float = 3.0, height: float = 0.0) -> np.ndarray:
    a = np.radians(angle_deg)
    return look_at([radius * np.sin(a), height, radius * np.cos(a)])


def main_albedo(points: np.ndarray) -> np.ndarray:
    """Smooth analytic albedo of the main sphere (so bilinear lookups are exact to first order)."""
    return (0.5 + 0.4 * points).astype(np.float32)


def render_spheres(P: np.ndarray, spheres, occluder_albedo: float = 5.0) -> dict[str, np.ndarray]:
    """Analytic ray casting of spheres: depth (camera z), world normal, albedo (main sphere: main_albedo,
    others: the constant ``occluder_albedo``), hit."""
    origins, dirs, z_per_t = camera_rays(K, P, H, W)
    best_t = np.full(len(dirs), np.inf)
    normal = np.zeros((len(dirs), 3))
    albedo = np.zeros((len(dirs), 3), np.float32)
    for idx, (centre, radius) in enumerate(spheres):
        oc = origins - centre
        b = np.einsum("ij,ij->i", oc, dirs)
        disc = b * b - (np.einsum("ij,ij->i", oc, oc) - radius * radius)
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        closer = (disc > 0) & (t > 0) & (t < best_t)
        best_t[closer] = t[closer]
        pts = origins[closer] + t[closer, None] * dirs[closer]
        normal[closer] = (pts - centre) / radius
        albedo[closer] = main_albedo(pts) if idx == 0 else occluder_albedo
    hit = np.isfinite(best_t)
    depth = np.where(hit, np.where(hit, best_t, 0.0) * z_per_t, 0.0)
    return {"depth_m": depth.reshape(H, W).astype(np.float32), "normal": normal.reshape(H, W, 3).astype(np.float32),
            "albedo": albedo.reshape(H, W, 3), "hit": hit.reshape(H, W)}


def source_from(P: np.ndarray, spheres) -> SourceView:
    r = render_spheres(P, spheres)
    return SourceView(normal=r["normal"], albedo=r["albedo"], valid=r["hit"], K=K, cam_from_world=P,
                      depth_m=r["depth_m"])


def interior(hit: np.ndarray, margin: int = 3) -> np.ndarray:
    from scipy import ndimage

    return ndimage.binary_erosion(hit, iterations=margin)


# ------------------------------------------------------------------------------------------------ cameras


def test_camera_centre_single_and_stack():
    P = ring_camera(30.0)
    c = camera_centre(P)
    assert np.allclose(c, [3.0 * np.sin(np.radians(30)), 0.0, 3.0 * np.cos(np.radians(30))])
    stack = camera_centre(np.stack([P, ring_camera(-90.0)]))
    assert stack.shape == (2, 3) and np.allclose(stack[1], [-3.0, 0.0, 0.0], atol=1e-12)


def test_nearest_views_orders_by_angle_from_subject():
    sources = [ring_camera(a) for a in (0.0, 90.0, 40.0, -20.0, 180.0)]
    target = ring_camera(25.0)
    assert nearest_views(target, sources, k=3).tolist() == [2, 0, 3]
    assert nearest_views(target, sources, k=10).tolist() == [2, 0, 3, 1, 4]
    # the camera's distance and axis tilt do not matter, only its direction from the subject centre
    far_tilted = look_at([6.0 * np.sin(np.radians(24.0)), 0.0, 6.0 * np.cos(np.radians(24.0))], target=(0.2, 0.1, 0))
    assert nearest_views(target, sources + [far_tilted], k=1).tolist() == [5]


def test_nearest_views_input_checks():
    with pytest.raises(ValueError, match="k must"):
        nearest_views(ring_camera(0.0), [ring_camera(10.0)], k=0)
    with pytest.raises(ValueError, match="no source"):
        nearest_views(ring_camera(0.0), [], k=2)
    with pytest.raises(ValueError, match="must be"):
        nearest_views(np.eye(3), [ring_camera(10.0)])


# ------------------------------------------------------------------------------------------------ reprojection


@pytest.fixture(scope="module")
def sphere_scene():
    sources = [source_from(ring_camera(a, height=h), [MAIN])
               for a, h in ((-40.0, 0.0), (-15.0, 0.8), (10.0, -0.6), (35.0, 0.3), (60.0, 0.0), (180.0, 0.0))]
    target_P = ring_camera(12.0, height=0.2)
    target = render_spheres(target_P, [MAIN])
    return sources, target_P, target


@pytest.mark.parametrize("weighting,interpolation", [(w, "cubic") for w in WEIGHTINGS] + [(WEIGHTINGS[-1], "bilinear")])
def test_reprojection_matches_analytic_sphere(sphere_scene, weighting, interpolation):
    sources, target_P, target = sphere_scene
    out = reproject_gbuffer(target["depth_m"], K, target_P, sources, k=5, depth_tolerance_m=0.05,
                            weighting=weighting, interpolation=interpolation)
    assert out["normal"].shape == (H, W, 3) and out["albedo"].shape == (H, W, 3)
    assert out["weight"].shape == (H, W) and out["valid"].shape == (H, W) and out["view_count"].shape == (H, W)
    assert out["valid"].dtype == bool
    # the camera behind the subject is never among the 5 nearest
    assert 5 not in out["sources"].tolist()
    inner = interior(target["hit"])
    assert out["valid"][inner].mean() > 0.99
    err = angular_error_deg(out["normal"], target["normal"])[inner & out["valid"]]
    assert err.mean() < 0.5 and err.max() < 3.0
    alb = np.abs(out["albedo"] - target["albedo"])[inner & out["valid"]]
    assert alb.mean() < 0.003 and alb.max() < 0.03
    n = np.linalg.norm(out["normal"][out["valid"]], axis=-1)
    assert np.allclose(n, 1.0, atol=1e-5)
    assert np.all(out["view_count"][inner] >= 2) and out["view_count"].max() <= 5
    assert np.all(out["weight"][out["valid"]] > 0)


def test_no_depth_pixels_are_invalid_and_zero(sphere_scene):
    sources, target_P, target = sphere_scene
    depth = target["depth_m"].copy()
    depth[:, : W // 2] = 0.0  # the left half has no surface
    out = reproject_gbuffer(depth, K, target_P, sources, k=4, depth_tolerance_m=0.05)
    assert not out["valid"][:, : W // 2].any()
    assert not out["valid"][~target["hit"]].any()  # background: no depth -> invalid
    for key in ("normal", "albedo", "weight", "view_count"):
        assert np.all(out[key][:, : W // 2] == 0)
    assert out["valid"][:, W // 2:][interior(target["hit"])[:, W // 2:]].mean() > 0.99
    empty = reproject_gbuffer(np.zeros((H, W), np.float32), K, target_P, sources)
    assert not empty["valid"].any() and np.all(empty["normal"] == 0)


def test_occluder_hides_source_and_gets_no_weight():
    """A small sphere in front of the main one, seen only by source 0: where it hides the main sphere
    there, source 0 must give no weight (the occluder's albedo 5.0 must not leak anywhere)."""
    P0, P1 = ring_camera(-20.0), ring_camera(25.0)
    eye0 = camera_centre(P0)
    occluder = (0.5 * eye0 / np.linalg.norm(eye0) * 1.5, 0.15)  # on source 0's line of sight, 0.75 m out
    scene = [MAIN, occluder]
    src0, src1 = source_from(P0, scene), source_from(P1, scene)
    target_P = ring_camera(5.0)
    target = render_spheres(target_P, [MAIN])  # the target depth sees only the main sphere
    hidden_in_0 = (src0.albedo[..., 0] == 5.0).sum()
    assert hidden_in_0 > 30  # the occluder covers a patch of source 0
    alone = reproject_gbuffer(target["depth_m"], K, target_P, [src0], source_indices=[0], depth_tolerance_m=0.05)
    both = reproject_gbuffer(target["depth_m"], K, target_P, [src0, src1], k=2, depth_tolerance_m=0.05)
    clear = reproject_gbuffer(target["depth_m"], K, target_P, [source_from(P0, [MAIN])], source_indices=[0],
                              depth_tolerance_m=0.05)
    inner = interior(target["hit"])
    # pixels whose point source 0 would see but for the occluder: invalid with source 0 alone, one view
    # (source 1) with both
    shadowed = inner & clear["valid"] & ~alone["valid"]
    assert shadowed.sum() > 20
    only1 = reproject_gbuffer(target["depth_m"], K, target_P, [src1], source_indices=[0], depth_tolerance_m=0.05)
    seen1 = shadowed & only1["valid"]
    assert seen1.sum() > 20
    assert np.all(both["view_count"][seen1] == 1) and both["valid"][seen1].all()
    assert not both["valid"][shadowed & ~only1["valid"]].any()  # hidden from both: no data
    for out in (alone, both):
        ok = out["valid"]
        assert out["albedo"][ok].max() < 1.0  # main albedo is 0.3..0.7: no occluder colour anywhere
        err = angular_error_deg(out["normal"], target["normal"])[ok & inner]
        assert err.mean() < 0.5
    # with both sources the occluded pixels match the analytic values (from source 1 alone)
    assert np.abs(both["albedo"] - target["albedo"])[seen1].max() < 0.03


def _plane_lookup(u: float, v: float, interpolation: str, valid: np.ndarray | None = None,
                  edge: np.ndarray | None = None, edge_weight: float = 1.0):
    """A source at constant depth 2 m (K = identity: pixel column i at u = i, row j at v = j)
    holding the map u^2 + 3 v; the point projecting to (u, v) is looked up."""
    h, w = 12, 16
    Kp = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    depth = np.full((h, w), 2.0, np.float32)
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float32)
    values = (uu ** 2 + 3 * vv)[..., None]
    valid = np.ones((h, w), bool) if valid is None else valid
    point = np.array([[u * 2.0, v * 2.0, 2.0]])
    vis, (sample,) = _sample_consistent(point, Kp, depth, valid, (values,), 0.01, interpolation, edge, edge_weight)
    return float(vis[0]), float(sample[0, 0])


def test_cubic_lookup_is_exact_on_a_quadratic_and_bilinear_is_not():
    u, v = 7.3, 4.6
    exact = u * u + 3 * v  # 53.29 + 13.8
    vis_c, cubic = _plane_lookup(u, v, "cubic")
    vis_b, bilinear = _plane_lookup(u, v, "bilinear")
    assert vis_c == pytest.approx(1.0) and vis_b == pytest.approx(1.0)  # the visibility is the bilinear one
    assert cubic == pytest.approx(exact, abs=1e-4)  # Keys (a = -0.5) reproduces quadratics
    assert bilinear == pytest.approx(0.7 * 49 + 0.3 * 64 + 3 * v, abs=1e-4)  # 53.5 + 13.8: off by u(1-u) = 0.21
    assert abs(bilinear - exact) > 0.2


def test_cubic_lookup_falls_back_to_bilinear_next_to_an_invalid_tap():
    u, v = 7.3, 4.6
    valid = np.ones((12, 16), bool)
    valid[3, 6] = False  # one of the 16 cubic taps (rows 3..6, cols 6..9), not one of the 4 bilinear ones
    _, cubic = _plane_lookup(u, v, "cubic", valid)
    _, bilinear = _plane_lookup(u, v, "bilinear", valid)
    assert cubic == pytest.approx(bilinear, abs=1e-5)
    assert INTERPOLATIONS == ("bilinear", "cubic")


def test_nan_in_source_maps_never_reaches_outputs(sphere_scene):
    sources, target_P, target = sphere_scene
    s = sources[1]
    normal = s.normal.copy()
    normal[20:40, 20:40] = np.nan
    albedo = s.albedo.copy()
    albedo[10:20, 30:50] = np.inf
    bad = SourceView(normal=normal, albedo=albedo, valid=s.valid, K=s.K, cam_from_world=s.cam_from_world,
                     depth_m=s.depth_m)
    out = reproject_gbuffer(target["depth_m"], K, target_P, [sources[0], bad, sources[2]], k=3,
                            depth_tolerance_m=0.05)
    for key in ("normal", "albedo", "weight"):
        assert np.all(np.isfinite(out[key]))
    assert out["valid"][interior(target["hit"])].mean() > 0.99


def test_reproject_input_checks(sphere_scene):
    sources, target_P, target = sphere_scene
    d = target["depth_m"]
    with pytest.raises(ValueError, match="target_depth_m"):
        reproject_gbuffer(d[..., None], K, target_P, sources)
    with pytest.raises(ValueError, match="NaN"):
        reproject_gbuffer(np.where(target["hit"], np.nan, 0.0), K, target_P, sources)
    with pytest.raises(ValueError, match="negative"):
        reproject_gbuffer(-d, K, target_P, sources)
    with pytest.raises(ValueError, match="K must"):
        reproject_gbuffer(d, K[:2], target_P, sources)
    with pytest.raises(ValueError, match="weighting"):
        reproject_gbuffer(d, K, target_P, sources, weighting="median")
    with pytest.raises(ValueError, match="interpolation"):
        reproject_gbuffer(d, K, target_P, sources, interpolation="lanczos")
    with pytest.raises(ValueError, match="no source"):
        reproject_gbuffer(d, K, target_P, [])
    with pytest.raises(ValueError, match="source_indices"):
        reproject_gbuffer(d, K, target_P, sources, source_indices=[len(sources)])
    with pytest.raises(ValueError, match="depth_tolerance_m"):
        reproject_gbuffer(d, K, target_P, sources, depth_tolerance_m=0.0)
    s = sources[0]
    wrong = SourceView(normal=s.normal[:-1], albedo=s.albedo, valid=s.valid, K=s.K,
                       cam_from_world=s.cam_from_world, depth_m=s.depth_m)
    with pytest.raises(ValueError, match=r"sources\[0\]\.normal"):
        reproject_gbuffer(d, K, target_P, [wrong], source_indices=[0])


def _subpixel_at(target, pixel, rays):
    """A subpixel input for one target ``pixel`` (row, col) whose rays are the pixel centres ``rays`` [(row,
    col), ...] of the target with their depths (a miss where there is no surface)."""
    r = np.array([pixel[0]])
    c = np.array([pixel[1]])
    v = np.array([[float(a) for a, _ in rays]])
    u = np.array([[float(b) for _, b in rays]])
    z = np.array([[target["depth_m"][a, b] for a, b in rays]], np.float64)
    return {"rows": r, "cols": c, "u": u, "v": v, "depth_m": z}


def test_subpixel_pixel_is_the_mean_of_its_rays(sphere_scene):
    sources, target_P, target = sphere_scene
    kw = dict(k=5, depth_tolerance_m=0.05)
    base = reproject_gbuffer(target["depth_m"], K, target_P, sources, **kw)
    a, b = (30, 30), (34, 36)
    assert base["valid"][a] and base["valid"][b]
    # rays at a's centre give back a's own maps exactly
    same = reproject_gbuffer(target["depth_m"], K, target_P, sources, subpixel=_subpixel_at(target, a, [a, a, a, a]), **kw)
    for key in ("normal", "albedo", "weight", "valid", "view_count"):
        np.testing.assert_allclose(same[key], base[key], rtol=1e-6, atol=1e-7)
    # rays at a's and b's centres, 3 to 1: a's albedo becomes their 3:1 mean, its normal the renormalised sum
    mixed = reproject_gbuffer(target["depth_m"], K, target_P, sources,
                              subpixel=_subpixel_at(target, a, [a, a, a, b]), **kw)
    np.testing.assert_allclose(mixed["albedo"][a], 0.75 * base["albedo"][a] + 0.25 * base["albedo"][b], atol=1e-6)
    n = 3 * base["normal"][a] + base["normal"][b]
    np.testing.assert_allclose(mixed["normal"][a], n / np.linalg.norm(n), atol=1e-6)
    np.testing.assert_allclose(mixed["weight"][a], 0.75 * base["weight"][a] + 0.25 * base["weight"][b], rtol=1e-5)
    assert mixed["view_count"][a] == max(base["view_count"][a], base["view_count"][b])
    other = np.ones((H, W), bool)
    other[a] = False
    np.testing.assert_array_equal(mixed["albedo"][other], base["albedo"][other])  # no other pixel changes
    # rays that miss (background pixel (0, 0)) do not count: one hit ray is the pixel's value
    assert not target["hit"][0, 0]
    missed = reproject_gbuffer(target["depth_m"], K, target_P, sources,
                               subpixel=_subpixel_at(target, a, [(0, 0), b, (0, 0), (0, 0)]), **kw)
    np.testing.assert_allclose(missed["albedo"][a], base["albedo"][b], atol=1e-6)
    # a background pixel whose rays partly hit becomes valid; one whose rays all miss is invalid and zero
    grown = reproject_gbuffer(target["depth_m"], K, target_P, sources,
                              subpixel=_subpixel_at(target, (0, 0), [(0, 0), b]), **kw)
    assert grown["valid"][0, 0] and np.allclose(grown["albedo"][0, 0], base["albedo"][b], atol=1e-6)
    gone = reproject_gbuffer(target["depth_m"], K, target_P, sources,
                             subpixel=_subpixel_at(target, a, [(0, 0), (0, 1)]), **kw)
    assert not gone["valid"][a] and not gone["albedo"][a].any() and gone["weight"][a] == 0


def test_subpixel_input_checks(sphere_scene):
    sources, target_P, target = sphere_scene
    d = target["depth_m"]
    good = _subpixel_at(target, (30, 30), [(30, 30), (31, 31)])
    with pytest.raises(ValueError, match="'u' is missing"):
        reproject_gbuffer(d, K, target_P, sources, subpixel={k: v for k, v in good.items() if k != "u"})
    with pytest.raises(ValueError, match=r"\(M, S\)"):
        reproject_gbuffer(d, K, target_P, sources, subpixel=good | {"u": good["u"][:, :1]})
    with pytest.raises(ValueError, match="outside"):
        reproject_gbuffer(d, K, target_P, sources, subpixel=good | {"rows": np.array([H])})
    with pytest.raises(ValueError, match="finite"):
        reproject_gbuffer(d, K, target_P, sources, subpixel=good | {"depth_m": -good["depth_m"]})


# ------------------------------------------------------------------------------------------------ held-out helpers


def test_spread_heldout_and_summary():
    from evaluation.heldout import spread_heldout, summarise

    from artifacts.camera import Camera

    cams = {f"{i:05d}": Camera(K, ring_camera(i * 30.0), 64, 64) for i in range(12)}
    assert spread_heldout(cams, 2) == ("00000", "00006")  # the opposite side of the ring
    part = {"angle_deg": np.array([1.0, 4.0, 10.0, 30.0]), "albedo_sq": np.full(6, 0.01), "ssim": 0.9, "pixels": 4}
    s = summarise([part], "_x")
    assert s["heldout_normal_mean_deg_x"] == pytest.approx(11.25)
    assert s["heldout_normal_under5_pct_x"] == pytest.approx(50.0)
    assert s["heldout_normal_under25_pct_x"] == pytest.approx(75.0)
    assert s["heldout_albedo_rmse_x"] == pytest.approx(0.1)
    assert s["heldout_albedo_psnr_db_x"] == pytest.approx(20.0)
    assert s["heldout_albedo_ssim_x"] == pytest.approx(0.9)


# ---------------------------------------------------------------------------------------------- fuse_normals


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _tilted_field(h: int = 40, w: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A smooth base field (normals turning slowly across the image) and a high-frequency detail pattern."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    base = _unit(np.stack([0.3 * np.sin(xx / 15.0), 0.2 * np.cos(yy / 12.0), np.ones_like(xx)], -1))
    detail = 0.08 * np.stack([np.where((xx.astype(int) // 2) % 2 == 0, 1.0, -1.0), np.zeros_like(xx),
                              np.zeros_like(xx)], -1)
    return base, detail


def test_fuse_normals_hand_case_constant_fields():
    # constant fields: G(d) = d and G(b) = b away from the edges, so the fused normal is b exactly there
    h, w = 30, 30
    d = np.broadcast_to(_unit(np.array([0.3, 0.0, 1.0])), (h, w, 3)).copy()
    b = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (h, w, 3)).copy()
    out = fuse_normals(d, b, np.ones((h, w), bool), sigma_px=2.0)
    assert out.shape == (h, w, 3) and out.dtype == np.float32
    assert np.allclose(out, b, atol=1e-6)  # normalised convolution: the image edge is no different


def test_fuse_normals_keeps_detail_and_replaces_the_low_frequencies():
    base, detail = _tilted_field()
    bias = np.array([0.15, -0.1, 0.0])  # a smooth bias of the detailed normals (eq. 1's lean, say)
    photometric = _unit(base + detail + bias)
    truth = _unit(base + detail)
    mask = np.ones(base.shape[:2], bool)
    fused = fuse_normals(photometric, base, mask, sigma_px=3.0)
    inner = (slice(6, -6), slice(6, -6))
    err_photometric = angular_error_deg(photometric, truth)[inner].mean()
    err_base = angular_error_deg(base, truth)[inner].mean()
    err_fused = angular_error_deg(fused, truth)[inner].mean()
    assert err_fused < 0.5 * min(err_photometric, err_base), (err_fused, err_photometric, err_base)
    assert np.allclose(np.linalg.norm(fused, axis=-1), 1.0, atol=1e-5)


def test_fuse_normals_ignores_what_lies_outside_the_mask_and_undefined_pixels():
    base, detail = _tilted_field()
    photometric = _unit(base + detail)
    mask = np.zeros(base.shape[:2], bool)
    mask[5:35, 8:40] = True
    fused = fuse_normals(photometric, base, mask, sigma_px=2.0)
    garbage = photometric.copy()
    garbage[~mask] = [0.0, -1.0, 0.0]
    base_garbage = base.copy()
    base_garbage[~mask] = np.nan
    assert np.allclose(fuse_normals(garbage, base_garbage, mask, sigma_px=2.0), fused, atol=1e-6)
    assert np.all(fused[~mask] == 0)
    # an undefined detailed normal takes the base's direction; an undefined base keeps the detail's
    hole = photometric.copy()
    hole[20, 20] = np.nan
    hole[21, 21] = 0.0
    out = fuse_normals(hole, base, mask, sigma_px=2.0)
    assert np.all(np.isfinite(out))
    assert np.allclose(out[20, 20], base[20, 20], atol=1e-6) and np.allclose(out[21, 21], base[21, 21], atol=1e-6)
    no_base = base.copy()
    no_base[10, 10] = 0.0
    assert np.allclose(fuse_normals(photometric, no_base, mask, 2.0)[10, 10], photometric[10, 10], atol=1e-6)


def test_fuse_normals_input_checks():
    n = np.zeros((4, 4, 3))
    n[..., 2] = 1
    m = np.ones((4, 4), bool)
    with pytest.raises(ValueError, match="normal_detail"):
        fuse_normals(n[..., :2], n, m, 1.0)
    with pytest.raises(ValueError, match="must match"):
        fuse_normals(n, n[:3], m, 1.0)
    with pytest.raises(ValueError, match="must match"):
        fuse_normals(n, n, m[:3], 1.0)
    for sigma in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="sigma_px"):
            fuse_normals(n, n, m, sigma)



def _square_normals():
    """A 6 x 6 square in a 10 x 10 image (distances to the outside 1 on its outer ring, 2, 3 at the 2 x 2 centre),
    normals +x and base normals +z everywhere."""
    mask = np.zeros((10, 10), bool)
    mask[2:8, 2:8] = True
    n = np.zeros((10, 10, 3))
    n[..., 0] = 1.0
    b = np.zeros((10, 10, 3))
    b[..., 2] = 1.0
    return mask, n, b


def test_fade_rim_normals_hand_case_square():
    mask, n, b = _square_normals()
    out = fade_rim_normals(n, b, mask, rim_px=2.0)
    assert out.shape == (10, 10, 3) and out.dtype == np.float32
    # w = (rim + 1 - d) / rim: 1 on the outer ring, 0.5 on the next, 0 at the centre
    assert np.allclose(out[2, 2:8], [0, 0, 1]) and np.allclose(out[2:8, 7], [0, 0, 1])
    assert np.allclose(out[3, 3:7], [np.sqrt(0.5), 0, np.sqrt(0.5)], atol=1e-6)
    assert np.allclose(out[4:6, 4:6], [1, 0, 0])
    assert np.all(out[~mask] == 0)
    # no rim: the normals unchanged on the mask
    assert np.allclose(fade_rim_normals(n, b, mask, 0.0)[mask], n[mask])


def test_fade_rim_normals_interior_weight_blends_the_base_everywhere():
    # an interior weight of 0.5 takes the base halfway inside, the rim's weight where larger
    mask, n, b = _square_normals()
    half = [np.sqrt(0.5), 0, np.sqrt(0.5)]
    out = fade_rim_normals(n, b, mask, rim_px=2.0, interior_weight=0.5)
    assert np.allclose(out[2, 2:8], [0, 0, 1])                      # outer ring: rim weight 1
    assert np.allclose(out[3, 3:7], half, atol=1e-6)                # rim weight 0.5 = interior weight
    assert np.allclose(out[4:6, 4:6], half, atol=1e-6)              # centre: rim weight 0, interior 0.5
    # weight 0.25 without a rim: unit(0.75 n + 0.25 b) = (3, 0, 1) / sqrt(10) on the whole mask
    out = fade_rim_normals(n, b, mask, rim_px=0.0, interior_weight=0.25)
    assert np.allclose(out[mask], np.array([3, 0, 1]) / np.sqrt(10), atol=1e-6)
    assert np.all(out[~mask] == 0)
    for weight in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="interior_weight"):
            fade_rim_normals(n, b, mask, 2.0, weight)


def test_fade_rim_normals_keeps_the_normals_where_the_base_is_undefined_and_checks_inputs():
    mask = np.ones((5, 5), bool)
    mask[0] = False
    n = np.broadcast_to(_unit(np.array([0.3, 0.0, 1.0])), (5, 5, 3)).copy()
    b = np.zeros((5, 5, 3))
    b[..., 1] = 1.0
    b[1, 2] = np.nan  # undefined base on the outer ring: the normal is kept
    b[1, 3] = 0.0
    out = fade_rim_normals(n, b, mask, 3.0)
    assert np.all(np.isfinite(out))
    assert np.allclose(out[1, 2], n[1, 2], atol=1e-6) and np.allclose(out[1, 3], n[1, 3], atol=1e-6)
    assert np.allclose(out[1, 1], [0, 1, 0], atol=1e-6)
    assert np.allclose(np.linalg.norm(out[mask], axis=-1), 1.0, atol=1e-6)
    with pytest.raises(ValueError, match="normals must be"):
        fade_rim_normals(n[..., :2], b, mask, 1.0)
    with pytest.raises(ValueError, match="must match"):
        fade_rim_normals(n, b[:3], mask, 1.0)
    for rim in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="rim_px"):
            fade_rim_normals(n, b, mask, rim)


def test_shading_normals_fuse_then_fade_the_rim():
    """The novel view's shading normals are the fused normals with the rim faded to the base: on a square, the
    outer ring is the base's, the centre keeps the fused detail; rim 0 is the fusion alone."""
    rng = np.random.default_rng(4)
    mask = np.zeros((16, 16), bool)
    mask[3:13, 3:13] = True
    detail = _unit(np.array([0.0, 0.0, 1.0]) + 0.2 * rng.standard_normal((16, 16, 3)))
    base = np.broadcast_to(_unit(np.array([0.2, 0.0, 1.0])), (16, 16, 3)).copy()
    out = shading_normals(detail, base, mask, 2.0, 3.0)
    fused = fuse_normals(detail, base, mask, 2.0)
    assert out.shape == (16, 16, 3) and out.dtype == np.float32 and np.all(np.isfinite(out))
    np.testing.assert_array_equal(out, fade_rim_normals(fused, base, mask, 3.0))
    np.testing.assert_allclose(out[3, 3:13], base[3, 3:13], atol=1e-6)      # outer ring: the base
    np.testing.assert_allclose(out[6:10, 6:10], fused[6:10, 6:10], atol=1e-6)  # 4 px in and more: fused
    assert not np.allclose(fused[3, 3:13], base[3, 3:13], atol=1e-3)         # (the ring did change)
    np.testing.assert_array_equal(shading_normals(detail, base, mask, 2.0, 0.0), fused)
    assert np.all(out[~mask] == 0)


def test_depth_edges_marks_both_sides_of_an_occlusion_edge_and_not_the_silhouette():
    depth = np.zeros((10, 12), np.float32)
    depth[1:9, 1:11] = 2.0  # a wall, background around it
    depth[3:7, 4:8] = 1.5  # a box 0.5 m in front of it
    edges = depth_edges(depth, radius_px=1, jump_m=0.03)
    assert edges.shape == depth.shape and edges.dtype == bool
    expected = np.zeros_like(edges)
    expected[2:8, 3:9] = True  # the box's outline grown by 1 px: the wall's ring and the box's own
    expected[4:6, 5:7] = False  # the box's inside, 2 px from the jump
    assert np.array_equal(edges, expected)
    assert not edges[depth == 0].any()  # the silhouette against the background is not an edge
    assert depth_edges(depth, radius_px=1, jump_m=0.6).sum() == 0  # a 0.5 m jump under a 0.6 m threshold
    assert depth_edges(depth, radius_px=0).sum() == 0
    assert depth_edges(depth, radius_px=2, jump_m=0.03)[4:6, 5:7].all()  # 2 px reaches the inside
    with pytest.raises(ValueError, match="radius_px"):
        depth_edges(depth, radius_px=-1)
    with pytest.raises(ValueError, match="jump_m"):
        depth_edges(depth, jump_m=0.0)
    with pytest.raises(ValueError, match="depth_m"):
        depth_edges(depth[0])


def test_an_edge_tap_lowers_the_visibility_not_the_sample():
    u, v = 7.3, 4.6  # bilinear taps (col, row) (7, 4) 0.28, (8, 4) 0.12, (7, 5) 0.42, (8, 5) 0.18
    edge = np.zeros((12, 16), bool)
    edge[5, 8] = True
    for interpolation in INTERPOLATIONS:
        plain_vis, plain = _plane_lookup(u, v, interpolation)
        vis, sample = _plane_lookup(u, v, interpolation, edge=edge, edge_weight=0.01)
        assert plain_vis == pytest.approx(1.0, abs=1e-5)
        assert vis == pytest.approx(0.28 + 0.12 + 0.42 + 0.18 * 0.01, abs=1e-5)
        assert sample == pytest.approx(plain, abs=1e-5)  # the interpolation itself is not biased
    edge[:] = True
    assert _plane_lookup(u, v, "cubic", edge=edge, edge_weight=0.01)[0] == pytest.approx(0.01, abs=1e-6)


def test_source_edges_keep_an_occluders_bleed_out_of_the_blend():
    """Source 0 sees a bright occluder in front of the main sphere and its pixels mix across the occlusion
    edge (a 3 x 3 box blur, as a camera's footprint and demosaicing do); source 1 sees the main sphere
    clear. Counting source 0's edge pixels for little keeps the occluder's colour out of the target."""
    from scipy.ndimage import uniform_filter

    P0, P1 = ring_camera(-10.0), ring_camera(20.0)
    eye0 = camera_centre(P0)
    occluder = (0.5 * eye0 / np.linalg.norm(eye0) * 1.5, 0.15)
    r0 = render_spheres(P0, [MAIN, occluder], occluder_albedo=1.0)
    mixed = uniform_filter(r0["albedo"], size=(3, 3, 1), mode="nearest")
    src0 = SourceView(normal=r0["normal"], albedo=mixed, valid=r0["hit"], K=K, cam_from_world=P0, depth_m=r0["depth_m"])
    src1 = source_from(P1, [MAIN])
    target_P = ring_camera(5.0)
    target = render_spheres(target_P, [MAIN])
    runs = {px: reproject_gbuffer(target["depth_m"], K, target_P, [src0, src1], k=2, depth_tolerance_m=0.05,
                                  source_edge_px=px) for px in (0, 1)}
    inner = interior(target["hit"]) & runs[0]["valid"] & runs[1]["valid"]
    err = {px: np.abs(out["albedo"] - target["albedo"]).max(axis=-1)[inner] for px, out in runs.items()}
    bled = err[0] > 0.02  # where the occluder's colour reached the target without the edge weight
    assert bled.sum() > 10
    assert err[1][bled].mean() < 0.25 * err[0][bled].mean()
    assert err[1].max() < err[0].max()
    assert np.array_equal(runs[0]["valid"], runs[1]["valid"])  # nothing lost: the edge taps still count a little
    assert 0 < SOURCE_EDGE_WEIGHT < 0.1
    with pytest.raises(ValueError, match="source_edge_px"):
        reproject_gbuffer(target["depth_m"], K, target_P, [src0, src1], source_edge_px=-1)
    with pytest.raises(ValueError, match="source_edge_jump_m"):
        reproject_gbuffer(target["depth_m"], K, target_P, [src0, src1], source_edge_jump_m=0.0)
