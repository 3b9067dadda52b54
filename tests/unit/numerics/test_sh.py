"""Order-2 spherical harmonics of environment maps (stages.numerics.sh)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from stages.numerics import sh
from stages.numerics.sg import equirect_directions


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def map_of(fn, height=32):
    """An equirect map (H, 2H, 3) whose texel radiance is fn(direction (H, 2H, 3)) -> (H, 2H, 3)."""
    return fn(equirect_directions(height, 2 * height).astype(np.float64)).astype(np.float32)


def test_basis_constants_and_order():
    x, y, z = unit([0.3, -0.5, 0.8])
    row = sh.sh_basis(np.array([[x, y, z]]))[0]
    expected = [0.282095, 0.488603 * y, 0.488603 * z, 0.488603 * x, 1.092548 * x * y, 1.092548 * y * z,
                0.315392 * (3 * z * z - 1), 1.092548 * x * z, 0.546274 * (x * x - y * y)]
    np.testing.assert_allclose(row, expected, rtol=1e-12)


def test_basis_is_orthonormal_over_the_sphere():
    h = 64
    dirs = equirect_directions(h, 2 * h).reshape(-1, 3).astype(np.float64)
    weights = sh.equirect_solid_angles(h, 2 * h).reshape(-1).astype(np.float64)
    basis = sh.sh_basis(unit(dirs))
    gram = basis.T @ (basis * weights[:, None])
    np.testing.assert_allclose(gram, np.eye(9), atol=2e-3)


def test_constant_map_projects_to_c00_only():
    c = np.array([0.5, 1.0, 2.0])
    coeffs = sh.project_environment(map_of(lambda d: np.broadcast_to(c, d.shape).copy()))
    # c00 = c * Y00 * 4 pi = c * sqrt(4 pi) (Y00 = 1 / sqrt(4 pi))
    np.testing.assert_allclose(coeffs[0], c * math.sqrt(4 * math.pi), rtol=1e-5)
    # the higher bands vanish up to the texel grid's quadrature error of z^2 and y^2 (~1e-3 of c00)
    assert np.all(np.abs(coeffs[1:]) < 1e-3 * coeffs[0])


def test_constant_map_irradiance_is_pi_c():
    c = np.array([0.5, 1.0, 2.0])
    coeffs = sh.project_environment(map_of(lambda d: np.broadcast_to(c, d.shape).copy()))
    normals = unit(np.random.default_rng(0).normal(size=(50, 3)))
    np.testing.assert_allclose(sh.sh_irradiance(normals, coeffs), np.tile(math.pi * c, (50, 1)), rtol=2e-3)


def test_linear_map_matches_hand_computed_irradiance():
    # L(w) = 1 + 0.5 w_y lies in bands 0-1, where order 2 is exact:
    # c1-1 = 0.5 * 0.488603 * int y^2 dw = 0.5 * 0.488603 * 4 pi / 3;  E(n) = pi + 0.5 * (2 pi / 3) n_y
    coeffs = sh.project_environment(map_of(lambda d: np.repeat(1.0 + 0.5 * d[..., 1:2], 3, axis=2), 64))
    np.testing.assert_allclose(coeffs[1], 0.5 * 0.488603 * 4 * math.pi / 3, rtol=1e-3)
    normals = unit(np.random.default_rng(1).normal(size=(40, 3)))
    expected = math.pi + 0.5 * (2 * math.pi / 3) * normals[:, 1]
    np.testing.assert_allclose(sh.sh_irradiance(normals, coeffs)[:, 0], expected, rtol=3e-3)


def test_light_from_above_lights_up_facing_normals_more():
    env = np.zeros((32, 64, 3), np.float32)
    env[:4] = 10.0  # the rows nearest the zenith (+y)
    coeffs = sh.project_environment(env)
    e = sh.sh_irradiance(np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]]), coeffs)
    assert np.all(e[0] > 5 * e[2]) and np.all(e[2] > e[1])
    assert np.all(e >= 0)


def test_rotating_the_frame_equals_rotating_the_normals():
    rng = np.random.default_rng(2)
    lobe = unit([0.4, 0.3, -0.8])
    env = map_of(lambda d: np.exp(4.0 * (d @ lobe - 1.0))[..., None] * rng.uniform(0.5, 2.0, 3) + 0.1, 48)
    rotation = sh.rotation_y(37.0) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], np.float64)
    world = sh.project_environment(env)
    framed = sh.project_environment(env, rotation)
    normals = unit(rng.normal(size=(30, 3)))
    np.testing.assert_allclose(sh.sh_irradiance(normals @ rotation.T, framed),
                               sh.sh_irradiance(normals, world), rtol=1e-5)  # float32 texel directions
    assert not np.allclose(framed, world, atol=1e-3)  # the frame did change the coefficients


def test_rotation_y_turns_x_towards_minus_z():
    np.testing.assert_allclose(sh.rotation_y(90.0) @ [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(sh.rotation_y(0.0), np.eye(3))


def test_big_map_is_downsampled_keeping_energy():
    rng = np.random.default_rng(3)
    env = rng.uniform(0.0, 3.0, size=(256, 512, 3)).astype(np.float32)
    small = sh.project_environment(env)
    assert small.shape == (9, 3) and np.all(np.isfinite(small))
    weights = sh.equirect_solid_angles(256, 512)[..., None].astype(np.float64)
    np.testing.assert_allclose(small[0], 0.282095 * (env * weights).sum(axis=(0, 1)), rtol=1e-4)


@pytest.mark.parametrize("bad", [np.zeros((4, 8)), np.full((4, 8, 3), np.nan, np.float32),
                                 np.full((4, 8, 3), -1.0, np.float32), np.zeros((4, 8, 3), np.int32)])
def test_bad_maps_are_refused(bad):
    with pytest.raises(ValueError):
        sh.project_environment(bad)


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError):
        sh.sh_basis(np.zeros((3, 2)))
    with pytest.raises(ValueError):
        sh.sh_irradiance(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError):
        sh.project_environment(np.ones((4, 8, 3), np.float32), np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError):
        sh.rotation_y(float("nan"))
