"""Volume-rendered albedo/normal field (the table-1 baseline): a sphere given analytically, views of a known albedo
pattern rendered by hand, a held-out view synthesised back; shapes, determinism, serialisation, input checks."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from stages.numerics.appearance_field import (
    APPEARANCE_PRESETS,
    AppearanceField,
    AppearanceFieldConfig,
    AppearanceView,
    render_appearance,
    sample_training_pixels,
    train_appearance_field,
)
from stages.numerics.metrics import angular_error_deg
from stages.numerics.sdf import HashGridConfig, SDFField
from synthetic.rig import look_at

RADIUS = 0.3
BOUNDS = np.array([[-0.4, -0.4, -0.4], [0.4, 0.4, 0.4]])
SIZE = 40
DIST = 2.0
CONFIG = dataclasses.replace(APPEARANCE_PRESETS["test"], device="cpu")


@pytest.fixture(autouse=True)
def one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def sphere_sdf(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance of the sphere of radius RADIUS at the origin and its gradient."""
    r = np.linalg.norm(points, axis=1)
    return r - RADIUS, points / np.maximum(r, 1e-9)[:, None]


def albedo_pattern(p: np.ndarray) -> np.ndarray:
    """A smooth known albedo on the sphere: red follows x, green y, blue is constant."""
    u = p / RADIUS
    return np.stack([0.5 + 0.3 * u[:, 0], 0.45 + 0.25 * u[:, 1], np.full(len(p), 0.3)], axis=1)


def camera(azimuth_deg: float, elevation_deg: float):
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    centre = DIST * np.array([np.sin(a) * np.cos(e), np.sin(e), np.cos(a) * np.cos(e)])
    f = 0.9 * SIZE / 2 / np.tan(np.arcsin(1.3 * RADIUS / DIST))
    K = np.array([[f, 0, (SIZE - 1) / 2], [0, f, (SIZE - 1) / 2], [0, 0, 1.0]])
    return K, look_at(centre, np.zeros(3))


def render_by_hand(K: np.ndarray, T: np.ndarray) -> dict[str, np.ndarray]:
    """Ray-sphere intersection per pixel: albedo pattern, normal, depth and mask of a view."""
    R, t = T[:, :3], T[:, 3]
    o = -R.T @ t
    rows, cols = np.mgrid[0:SIZE, 0:SIZE]
    pix = np.stack([cols.ravel(), rows.ravel(), np.ones(SIZE * SIZE)], 1)
    d = np.linalg.solve(K, pix.T).T @ R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    b = d @ o
    disc = b * b - (o @ o - RADIUS ** 2)
    hit = disc > 0
    p = o + (-b - np.sqrt(np.maximum(disc, 0)))[:, None] * d
    normals = np.where(hit[:, None], p / RADIUS, 0.0)
    albedo = np.where(hit[:, None], albedo_pattern(p), 0.0)
    depth = np.where(hit, (p @ R.T + t)[:, 2], 0.0)
    shape = (SIZE, SIZE)
    return {"albedo": albedo.reshape(shape + (3,)).astype(np.float32),
            "normal": normals.reshape(shape + (3,)).astype(np.float32),
            "depth_m": depth.reshape(shape).astype(np.float32), "mask": hit.reshape(shape)}


TRAIN_CAMERAS = [(0, 20), (90, -20), (180, 20), (270, -20), (45, 60), (135, -60)]
HELDOUT_CAMERA = (40, 5)


def training_views(with_depth: bool = False) -> list[AppearanceView]:
    views = []
    for az, el in TRAIN_CAMERAS:
        K, T = camera(az, el)
        r = render_by_hand(K, T)
        views.append(AppearanceView(albedo=r["albedo"], normals_world=r["normal"], valid=r["mask"], K=K,
                                    cam_from_world=T, depth_m=r["depth_m"] if with_depth else None))
    return views


@pytest.fixture(scope="module")
def trained():
    """The test preset on 6 hand-rendered 40x40 views of the sphere (about a second on one thread)."""
    torch.set_num_threads(1)
    return train_appearance_field(training_views(), sphere_sdf, CONFIG, bounds=BOUNDS)


# ------------------------------------------------------------------------------------------------ fitting


@pytest.mark.parametrize("with_depth", [False, True])
def test_heldout_view_albedo_and_normal_come_back(trained, with_depth):
    K, T = camera(*HELDOUT_CAMERA)
    truth = render_by_hand(K, T)
    out = render_appearance(trained.field, sphere_sdf, K, T, SIZE, SIZE,
                            depth_m=truth["depth_m"] if with_depth else None, config=CONFIG, bounds=BOUNDS)
    # Coverage: the rendered silhouette is the sphere's (up to its one-pixel boundary).
    both = out["valid"] & truth["mask"]
    assert both.sum() >= 0.93 * truth["mask"].sum()
    assert (out["valid"] & ~truth["mask"]).sum() <= 0.03 * truth["mask"].sum()
    # Held-out albedo and normals close to the pattern and the sphere's normals (an untrained field is far off:
    # see test_training_reduces_the_error).
    albedo_err = np.abs(out["albedo"] - truth["albedo"])[both].mean()
    angle = angular_error_deg(out["normals_world"], truth["normal"])[both]
    assert albedo_err < 0.02, albedo_err
    assert angle.mean() < 3.0 and np.median(angle) < 2.0, (angle.mean(), np.median(angle))
    # Expected depth of the NeuS weights on the analytic surface (symmetric head-on; at the silhouette the
    # window cuts the weights off on one side).
    depth_err = np.abs(out["depth_m"] - truth["depth_m"])[both]
    assert np.median(depth_err) < 0.001 and np.quantile(depth_err, 0.9) < 0.005, depth_err


def test_training_reduces_the_error(trained):
    history = trained.history
    assert history["iteration"][-1] == CONFIG.iterations
    assert history["normal_deg"][-1] < 0.3 * history["normal_deg"][0]
    assert history["albedo_l1"][-1] < 0.3 * history["albedo_l1"][0]
    assert trained.stats["training_pixels"] > 0.9 * trained.stats["valid_pixels"]
    # Untrained: far from the pattern (the fit test's thresholds mean something).
    K, T = camera(*HELDOUT_CAMERA)
    truth = render_by_hand(K, T)
    fresh = AppearanceField(BOUNDS, CONFIG.encoding, CONFIG.hidden_width, CONFIG.hidden_layers)
    out = render_appearance(fresh, sphere_sdf, K, T, SIZE, SIZE, config=CONFIG, bounds=BOUNDS)
    both = out["valid"] & truth["mask"]
    assert angular_error_deg(out["normals_world"], truth["normal"])[both].mean() > 20.0


def test_render_shapes_dtypes_and_background(trained):
    K, T = camera(*HELDOUT_CAMERA)
    out = render_appearance(trained.field, sphere_sdf, K, T, 30, 20, config=CONFIG, bounds=BOUNDS)
    assert out["albedo"].shape == (30, 20, 3) and out["albedo"].dtype == np.float32
    assert out["normals_world"].shape == (30, 20, 3) and out["normals_world"].dtype == np.float32
    assert out["opacity"].shape == out["depth_m"].shape == (30, 20)
    assert out["valid"].dtype == bool
    for key in ("albedo", "normals_world", "opacity", "depth_m"):
        assert np.isfinite(out[key]).all()
    assert np.all(out["albedo"][~out["valid"]] == 0) and np.all(out["normals_world"][~out["valid"]] == 0)
    norms = np.linalg.norm(out["normals_world"][out["valid"]], axis=-1)
    assert np.allclose(norms, 1.0, atol=1e-4)
    assert out["albedo"].min() >= 0 and out["albedo"].max() <= CONFIG.albedo_max
    # The corner pixels' rays miss the sphere: transparent.
    assert not out["valid"][0, 0] and out["opacity"][0, 0] < 0.01


def test_sdf_field_geometry_matches_the_same_sdf_as_a_function(trained):
    # An SDFField (geometric initialisation: roughly a sphere) used directly and through a numpy function of it.
    sdf = SDFField(BOUNDS, HashGridConfig(levels=2, features_per_level=2, log2_table_size=10, base_resolution=4,
                                          finest_resolution=8), hidden_width=16, hidden_layers=1,
                   init_radius_m=RADIUS)

    def as_function(points):
        with torch.no_grad():
            f, g = sdf.sdf_and_gradient(torch.from_numpy(points), "analytic")
        return f.numpy(), g.numpy()

    K, T = camera(*HELDOUT_CAMERA)
    direct = render_appearance(trained.field, sdf, K, T, SIZE, SIZE, config=CONFIG)
    wrapped = render_appearance(trained.field, as_function, K, T, SIZE, SIZE, config=CONFIG, bounds=sdf.bounds)
    assert 0.2 * SIZE * SIZE < direct["valid"].sum() < 0.9 * SIZE * SIZE
    assert np.array_equal(direct["valid"], wrapped["valid"])
    for key in ("albedo", "normals_world", "opacity", "depth_m"):
        np.testing.assert_allclose(direct[key], wrapped[key], atol=1e-5)


# ------------------------------------------------------------------------------------------------ reproducibility


def test_same_seed_same_field_other_seed_differs():
    config = dataclasses.replace(CONFIG, iterations=15, log_every=5)
    views = training_views(with_depth=True)[:2]
    a = train_appearance_field(views, sphere_sdf, config, bounds=BOUNDS)
    b = train_appearance_field(views, sphere_sdf, config, bounds=BOUNDS)
    c = train_appearance_field(views, sphere_sdf, dataclasses.replace(config, seed=1), bounds=BOUNDS)
    sa, sb, sc = a.field.state_dict(), b.field.state_dict(), c.field.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)
    assert a.history["loss"] == b.history["loss"]


def test_precomputed_samples_train_the_same_field():
    config = dataclasses.replace(CONFIG, iterations=10, log_every=5)
    views = training_views(with_depth=True)[:2]
    samples = sample_training_pixels(views, sphere_sdf, config, bounds=BOUNDS)
    n = samples.stats["training_pixels"]
    assert samples.points.shape == (n, config.samples_kept, 3) and samples.weights.shape == (n, config.samples_kept)
    assert samples.albedo.shape == samples.normals_world.shape == (n, 3)
    np.testing.assert_allclose(samples.weights.sum(1), 1.0, atol=1e-5)
    # Kept samples lie near the sphere (within the window).
    assert np.abs(np.linalg.norm(samples.points, axis=-1) - RADIUS).max() <= config.window_m + 1e-6
    a = train_appearance_field(samples, None, config)
    b = train_appearance_field(views, sphere_sdf, config, bounds=BOUNDS)
    assert all(torch.equal(x, y) for x, y in zip(a.field.state_dict().values(), b.field.state_dict().values()))
    with pytest.raises(ValueError, match="samples were made with"):
        train_appearance_field(samples, None, dataclasses.replace(config, samples_kept=2))


def test_state_round_trip(trained):
    field_ = AppearanceField.from_state(trained.field.to_state())
    pts = torch.rand(50, 3) * 0.6 - 0.3
    with torch.no_grad():
        a0, n0 = trained.field(pts)
        a1, n1 = field_(pts)
    assert torch.equal(a0, a1) and torch.equal(n0, n1)
    with pytest.raises(ValueError, match="not an appearance-field state"):
        AppearanceField.from_state({"format": "something else"})


# ------------------------------------------------------------------------------------------------ input checks


def test_bad_inputs_raise():
    views = training_views(with_depth=True)[:1]
    v = views[0]
    tiny = dataclasses.replace(CONFIG, iterations=1)
    with pytest.raises(ValueError, match="non-empty list"):
        train_appearance_field([], sphere_sdf, tiny, bounds=BOUNDS)
    with pytest.raises(ValueError, match="albedo must be"):
        train_appearance_field([dataclasses.replace(v, albedo=v.albedo[:, :, :2])], sphere_sdf, tiny, bounds=BOUNDS)
    with pytest.raises(ValueError, match="depth_m must be"):
        train_appearance_field([dataclasses.replace(v, depth_m=v.depth_m[1:])], sphere_sdf, tiny, bounds=BOUNDS)
    bad = v.normals_world.copy()
    bad[v.valid] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        train_appearance_field([dataclasses.replace(v, normals_world=bad)], sphere_sdf, tiny, bounds=BOUNDS)
    with pytest.raises(ValueError, match="no view has a valid pixel"):
        train_appearance_field([dataclasses.replace(v, valid=np.zeros_like(v.valid))], sphere_sdf, tiny,
                               bounds=BOUNDS)
    with pytest.raises(ValueError, match="rotation"):
        train_appearance_field([dataclasses.replace(v, cam_from_world=2 * v.cam_from_world)], sphere_sdf, tiny,
                               bounds=BOUNDS)
    with pytest.raises(ValueError, match="bounds are required"):
        train_appearance_field(views, sphere_sdf, tiny)
    with pytest.raises(ValueError, match="geometry must be"):
        train_appearance_field(views, "sphere", tiny, bounds=BOUNDS)
    with pytest.raises(ValueError, match="samples_kept"):
        train_appearance_field(views, sphere_sdf, dataclasses.replace(tiny, samples_kept=9), bounds=BOUNDS)
    with pytest.raises(ValueError, match="inv_s"):
        train_appearance_field(views, sphere_sdf, dataclasses.replace(tiny, inv_s=0.0), bounds=BOUNDS)
    with pytest.raises(ValueError, match="config must be"):
        train_appearance_field(views, sphere_sdf, {"iterations": 1}, bounds=BOUNDS)  # type: ignore[arg-type]
    # A surface nowhere near the valid pixels: nothing opaque to train on.
    with pytest.raises(ValueError, match="opaque"):
        train_appearance_field(views, lambda p: (np.full(len(p), 1.0), np.tile([1.0, 0, 0], (len(p), 1))), tiny,
                               bounds=BOUNDS)
    field_ = AppearanceField(BOUNDS, CONFIG.encoding, CONFIG.hidden_width, CONFIG.hidden_layers)
    with pytest.raises(ValueError, match="height and width"):
        render_appearance(field_, sphere_sdf, v.K, v.cam_from_world, 0, 10, config=tiny, bounds=BOUNDS)
    with pytest.raises(ValueError, match="K must be"):
        render_appearance(field_, sphere_sdf, np.eye(2), v.cam_from_world, 10, 10, config=tiny, bounds=BOUNDS)
    with pytest.raises(ValueError, match="field_ must be"):
        render_appearance(object(), sphere_sdf, v.K, v.cam_from_world, 10, 10, config=tiny,  # type: ignore[arg-type]
                          bounds=BOUNDS)
    with pytest.raises(ValueError, match="bounds must be"):
        AppearanceField(np.array([[0, 0, 0], [0, 1, 1.0]]))


def test_presets_are_valid_configs():
    from pipeline.config import config_problems

    for name, preset in APPEARANCE_PRESETS.items():
        assert isinstance(preset, AppearanceFieldConfig), name
        assert config_problems(preset) == [], name
