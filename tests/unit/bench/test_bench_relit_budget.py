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
    assert rows[f"+ {budget.COMPONENTS[-1]}"] == set(budget.COMPONENTS)
    cumulative = [rows[f"+ {c}"] for c in budget.COMPONENTS]
    assert all(a < b for a, b in zip(cumulative, cumulative[1:]))
