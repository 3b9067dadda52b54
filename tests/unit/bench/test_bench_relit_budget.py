"""The relit error budget's own numerics (bench/bench_relit_budget.py): the exact shading its ``lighting`` rows use,
the tone gain of its ``tone`` rows and the simulator's F0 of its ``material`` rows. Its --quick run is in
test_bench_quick.py."""
from __future__ import annotations

import math

import numpy as np
import pytest

from tests.unit.bench.test_bench_defaults import load_bench


@pytest.fixture(scope="module")
def budget():
    return load_bench("bench_relit_budget")


def test_exact_shade_of_a_constant_sky_is_the_albedo_times_the_radiance(budget):
    # a constant environment c as 4096 equal lights: an unoccluded Lambertian point has radiance albedo * c
    from stages.numerics.sg import fibonacci_sphere

    dirs = fibonacci_sphere(4096).astype(np.float32)
    c = np.array([1.0, 2.0, 0.5], np.float32)
    irradiance = np.tile(c * (4 * math.pi / len(dirs)), (len(dirs), 1)).astype(np.float32)
    normals = fibonacci_sphere(20).astype(np.float32)
    albedo = np.full((20, 3), 0.5, np.float32)
    visible = np.ones((20, len(dirs)), bool)
    rgb = budget.exact_shade(normals, normals, albedo, np.ones(20, np.float32), 0.0, dirs, irradiance, visible)
    # f0 = 0 leaves Schlick's (1 - v.h)^5 of specular, next to nothing with the view along the normal
    assert np.allclose(rgb, 0.5 * c, rtol=1e-3), rgb[:3]  # measured: within 1.1e-4
    half = visible & (normals @ dirs.T > 0) & (dirs[:, 1] > 0)[None]  # the lower half of the sky hidden
    dark = budget.exact_shade(normals, normals, albedo, np.ones(20, np.float32), 0.0, dirs, irradiance,
                              np.zeros_like(visible))
    assert np.all(dark == 0)
    partly = budget.exact_shade(normals, normals, albedo, np.ones(20, np.float32), 0.0, dirs, irradiance, half)
    assert np.all(partly <= rgb + 1e-6) and np.any(partly < 0.9 * rgb)


def test_exact_shade_checks_shapes(budget):
    dirs = np.eye(3, dtype=np.float32)
    with pytest.raises(ValueError, match="visibility"):
        budget.exact_shade(np.eye(3, dtype=np.float32), np.eye(3, dtype=np.float32), np.ones((3, 3), np.float32),
                           np.ones(3, np.float32), 0.04, dirs, np.ones((3, 3), np.float32), np.ones((3, 2), bool))


def test_tone_gain_recovers_a_per_channel_gain(budget):
    rng = np.random.default_rng(0)
    true = rng.uniform(0.1, 1.0, (8, 8, 3))
    mask = np.ones((8, 8), bool)
    gain = budget.tone_gain(true / np.array([2.0, 1.0, 0.5]), mask, true, mask)
    assert np.allclose(gain, [2.0, 1.0, 0.5], rtol=1e-9)


def test_simulator_f0_is_skin_at_skin_roughness_and_cloth_elsewhere(budget):
    from synthetic.subject import MATERIALS

    skin = [f0 for name, rough, f0 in MATERIALS.values() if name == "skin"][0]
    f0 = budget.simulator_f0(np.array([0.45, 0.8, 0.7, 0.25, 0.46]))
    assert f0[0] == pytest.approx(skin) and f0[4] == pytest.approx(skin)
    assert np.allclose(f0[1:4], 0.04)


def test_budget_rows_swap_one_component_then_accumulate(budget):
    rows = budget.budget_rows()
    assert rows["only albedo"] == {"albedo"}
    assert rows["geometry: shading normals only"] == {"normals"}
    assert rows[f"+ {budget.COMPONENTS[-1]}"] == set(budget.COMPONENTS)
    cumulative = [rows[f"+ {c}"] for c in budget.COMPONENTS]
    assert all(a < b for a, b in zip(cumulative, cumulative[1:]))


def test_pixel_classes_split_the_union_of_two_masks_by_the_band(budget):
    # two 10-column squares, one shifted a column right: columns 2-11 and 3-12 of rows 2-11
    pred = np.zeros((14, 16), bool)
    true = np.zeros((14, 16), bool)
    pred[2:12, 2:12] = True
    true[2:12, 3:13] = True
    classes = budget.pixel_classes(pred, true, band_px=2)
    assert classes["pred_only"].sum() == 10 and classes["pred_only"][2:12, 2].all()
    assert classes["true_only"].sum() == 10 and classes["true_only"][2:12, 12].all()
    # interior: at least 3 px from both outlines (rows 4-9, columns 5-9)
    assert classes["interior"].sum() == 6 * 5 and classes["interior"][4:10, 5:10].all()
    assert classes["band"].sum() == (pred & true).sum() - 30
    total = sum(c.astype(int) for c in classes.values())
    assert np.array_equal(total, (pred | true).astype(int))  # a partition of the union
    with pytest.raises(ValueError, match="masks"):
        budget.pixel_classes(pred, true[:3])


def test_outline_offset_of_a_straight_edge_moved_a_quarter_pixel_out(budget):
    # a vertical edge through column 5 at half coverage, and the same edge 0.25 px farther right
    true = np.zeros((8, 10))
    true[:, :5] = 1.0
    true[:, 5] = 0.5
    pred = true.copy()
    pred[:, 5] = 0.75
    out = budget.outline_offset_px(pred, true)
    assert out["outline_px"] == pytest.approx(8.0)  # one pixel of outline per row
    assert out["offset_px"] == pytest.approx(0.25)
    assert out["edge_rms"] == pytest.approx(0.25)
    assert budget.outline_offset_px(true, true)["offset_px"] == 0.0
    assert budget.outline_offset_px(np.zeros((4, 4)), np.zeros((4, 4)))["offset_px"] == 0.0  # no outline


def test_unpremultiplied_divides_by_alpha_and_fills_the_rest_from_the_nearest_pixel(budget):
    alpha = np.array([[1.0, 0.5, 0.0]])
    image = np.array([[[0.2, 0.4, 0.6], [0.1, 0.1, 0.1], [0.0, 0.0, 0.0]]])
    colour = budget.unpremultiplied(image, alpha)
    assert colour.shape == (1, 3, 3)
    assert np.allclose(colour[0, 0], [0.2, 0.4, 0.6]) and np.allclose(colour[0, 1], [0.2, 0.2, 0.2])
    assert np.allclose(colour[0, 2], colour[0, 1])
    assert np.all(budget.unpremultiplied(image, np.zeros((1, 3))) == 0)


def test_silhouette_split_swaps_the_bands_colour_for_a_finer_truths(budget):
    """A disc rendered with a rim darker than its inside: swapping the band's colour for the truth's own recovers
    the most, for the colour of a finer truth that matches ours only what differs from it, and ``colour_fine_truth``
    is absent without one."""
    h = w = 24
    yy, xx = np.mgrid[:h, :w]
    radius = np.hypot(yy - 11.5, xx - 11.5)
    alpha = np.clip(8.5 - radius, 0.0, 1.0)               # the coverage of a disc of radius 8 px
    true_colour = np.where((radius > 6.5)[..., None], [0.2, 0.2, 0.2], [0.8, 0.6, 0.4])
    ours = np.full((h, w, 3), [0.8, 0.6, 0.4])            # right inside, too bright on the rim
    true = {"radiance": (true_colour * alpha[..., None]).astype(np.float32), "mask": alpha >= 0.5}
    image = ours * alpha[..., None]
    split = budget.silhouette_split(image, alpha, alpha >= 0.5, true, alpha, alpha)
    assert "colour_fine_truth" not in split["swaps"]
    assert split["swaps"]["colour"] > split["psnr_db"] + 10  # the rim's colour is all the error
    same = budget.silhouette_split(image, alpha, alpha >= 0.5, true, alpha, alpha, fine_colour=ours)
    assert same["swaps"]["colour_fine_truth"] == pytest.approx(same["psnr_db"])
    exact = budget.silhouette_split(image, alpha, alpha >= 0.5, true, alpha, alpha, fine_colour=true_colour)
    assert exact["swaps"]["colour_fine_truth"] == pytest.approx(exact["swaps"]["colour"])
