"""sg.procedural_environment: the built-in equirectangular environments (sky, studio)."""
from __future__ import annotations

import numpy as np
import pytest

from stages.numerics.sg import PROCEDURAL_ENVIRONMENTS, equirect_directions, procedural_environment

HEIGHT = 96


def brightest_direction(env: np.ndarray) -> np.ndarray:
    d = equirect_directions(*env.shape[:2])
    i, j = np.unravel_index(np.argmax(env.sum(axis=2)), env.shape[:2])
    return d[i, j].astype(np.float64)


def elevation_deg(d):
    return float(np.degrees(np.arcsin(d[1] / np.linalg.norm(d))))


@pytest.mark.parametrize("kind", PROCEDURAL_ENVIRONMENTS)
def test_shape_range_and_determinism(kind):
    env = procedural_environment(kind, HEIGHT)
    assert env.shape == (HEIGHT, 2 * HEIGHT, 3) and env.dtype == np.float32
    assert np.isfinite(env).all() and env.min() >= 0.0
    assert env.max() > 1.0  # HDR: the lights are brighter than the diffuse surround
    np.testing.assert_array_equal(env, procedural_environment(kind, HEIGHT))
    assert procedural_environment(kind).shape == (64, 128, 3)  # the default height


def test_sky_sun_is_brightest_and_high_in_the_minus_z_plus_x_quarter():
    env = procedural_environment("sky", HEIGHT)
    d = brightest_direction(env)
    assert d[0] > 0 and d[2] < 0 and d[1] > 0  # towards -z+x, above the horizon
    assert 15 < elevation_deg(d) < 40
    assert env.sum(axis=2).max() > 100 * np.median(env.sum(axis=2))  # a sun, not a bright patch of sky
    # sky above is brighter than the ground below (away from the sun)
    sky, ground = env[: HEIGHT // 4].mean(), env[-HEIGHT // 4:].mean()
    assert sky > 2 * ground
    # the sun is small: texels more than 10 degrees from it are at most sky level
    d_all = equirect_directions(HEIGHT, 2 * HEIGHT).astype(np.float64)
    far = d_all @ d < np.cos(np.radians(10))
    assert env[far].max() < 3.0


def test_sky_sun_is_30_degrees_high():
    d = brightest_direction(procedural_environment("sky", 180))  # 1 degree texels
    assert elevation_deg(d) == pytest.approx(30.0, abs=1.5)


def test_studio_key_light_direction():
    env = procedural_environment("studio", HEIGHT)
    key = np.array([-0.6, 0.6, 0.55]) / np.linalg.norm([-0.6, 0.6, 0.55])  # front-left, above
    d = brightest_direction(env)
    texel_deg = 180.0 / HEIGHT
    assert np.degrees(np.arccos(np.clip(d @ key, -1, 1))) < 1.5 * texel_deg
    assert d[0] < 0 and d[1] > 0


def test_unknown_kind_and_tiny_height_raise():
    with pytest.raises(ValueError, match="procedural environment must be one of"):
        procedural_environment("beach", 32)
    with pytest.raises(ValueError, match="height"):
        procedural_environment("sky", 2)
