"""bench/bench_resolution.py: the power-law fit of a cost against the pixels per view (its exponent and residuals)
and the knee of a figure against the width."""
from __future__ import annotations

import math

import pytest

from tests.unit.bench.test_bench_defaults import load_bench



@pytest.fixture(scope="module")
def resolution():
    return load_bench("bench_resolution")


def test_power_fit_recovers_an_exact_power_law_with_zero_residuals(resolution):
    pixels = [55_296.0, 221_184.0, 884_736.0]
    fit = resolution.power_fit(pixels, [3.0 * p ** 0.7 for p in pixels])
    assert fit["k"] == pytest.approx(0.7) and fit["a"] == pytest.approx(3.0)
    assert fit["r2"] == pytest.approx(1.0) and fit["rms_residual"] == pytest.approx(0.0, abs=1e-9)


def test_power_fit_residuals_are_log_measured_less_log_fit(resolution):
    pixels, values = [1.0, 4.0, 16.0], [2.0, 3.9, 9.0]
    fit = resolution.power_fit(pixels, values)
    expected = [math.log(v) - math.log(fit["a"] * p ** fit["k"]) for p, v in zip(pixels, values)]
    assert fit["residuals"] == pytest.approx(expected)
    assert sum(fit["residuals"]) == pytest.approx(0.0, abs=1e-12)  # least squares with an intercept
    assert fit["rms_residual"] == pytest.approx(math.sqrt(sum(r * r for r in expected) / 3))
    assert resolution.power_fit([1.0, 1.0], [2.0, 3.0]) is None
    assert resolution.power_fit([1.0, 4.0], [2.0, 0.0]) is None


def test_knee_is_the_first_width_no_later_one_improves_on_by_more_than_the_tolerance(resolution):
    widths = [192, 384, 768]
    # lower is better: 3.0 -> 2.0 improves, 2.0 -> 1.95 is within 0.1
    assert resolution.knee(widths, [3.0, 2.0, 1.95], -1, 0.1) == 384
    assert resolution.knee(widths, [3.0, 2.0, 1.5], -1, 0.1) is None
    # higher is better, saturated from the start
    assert resolution.knee(widths, [30.0, 30.1, 29.0], +1, 0.25) == 192
