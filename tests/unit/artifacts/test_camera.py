"""The pinhole camera type (artifacts.camera): shapes, a hand-computed case, round trips, JSON."""
from __future__ import annotations

import json

import numpy as np
import pytest

from artifacts.camera import Camera, camera_centre, pixel_coordinates, pixel_rays

K = np.array([[100.0, 0.0, 32.0], [0.0, 110.0, 24.0], [0.0, 0.0, 1.0]])


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _posed_camera() -> Camera:
    R = _rotation(np.array([0.3, 1.0, -0.2]), 0.7)
    t = np.array([0.1, -0.2, 2.5])
    return Camera(K, np.column_stack([R, t]), 64, 48, camera_id="00003")


def test_a_camera_at_a_known_pose_projects_a_known_point():
    # camera at world (0, 0, -2) looking down +z (identity rotation): x_cam = x_world + (0, 0, 2)
    camera = Camera(K, np.column_stack([np.eye(3), [0.0, 0.0, 2.0]]), 64, 48)
    np.testing.assert_allclose(camera.centre, [0.0, 0.0, -2.0])
    uv, depth = camera.project(np.array([[0.2, -0.1, 0.5]]))
    # z = 2.5: u = 100 * 0.2 / 2.5 + 32 = 40, v = 110 * -0.1 / 2.5 + 24 = 19.6
    np.testing.assert_allclose(uv, [[40.0, 19.6]])
    np.testing.assert_allclose(depth, [2.5])
    # the principal point's ray is the optical axis
    origins, directions = camera.rays(np.array([[32.0, 24.0]]))
    np.testing.assert_allclose(origins, [[0.0, 0.0, -2.0]])
    np.testing.assert_allclose(directions, [[0.0, 0.0, 1.0]])


def test_centre_is_minus_rotation_transpose_times_translation():
    camera = _posed_camera()
    np.testing.assert_allclose(camera.centre, -camera.R.T @ camera.t, atol=1e-15)
    # the centre is where x_cam = 0, and a stack of poses gives one centre each
    np.testing.assert_allclose(camera.R @ camera.centre + camera.t, 0.0, atol=1e-12)
    stack = np.stack([camera.cam_from_world, np.column_stack([np.eye(3), [1.0, 2.0, 3.0]])])
    np.testing.assert_allclose(camera_centre(stack), [camera.centre, [-1.0, -2.0, -3.0]], atol=1e-12)


def test_project_of_lift_gives_back_the_pixels_and_depths():
    camera = _posed_camera()
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [63, 47], size=(200, 2))
    depth = rng.uniform(0.5, 4.0, size=200)
    points = camera.lift(uv, depth)
    assert points.shape == (200, 3) and points.dtype == np.float64
    uv_back, depth_back = camera.project(points)
    np.testing.assert_allclose(uv_back, uv, atol=1e-9)
    np.testing.assert_allclose(depth_back, depth, atol=1e-12)
    # with a skew too
    skewed = Camera(K + np.array([[0.0, 3.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), camera.cam_from_world, 64, 48)
    np.testing.assert_allclose(skewed.project(skewed.lift(uv, depth))[0], uv, atol=1e-9)


def test_rays_start_at_the_centre_and_pass_through_their_pixels():
    camera = _posed_camera()
    origins, directions = camera.rays()
    assert origins.shape == directions.shape == (64 * 48, 3)
    np.testing.assert_allclose(origins, np.broadcast_to(camera.centre, origins.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-12)
    uv, depth = camera.project(origins + 1.7 * directions)
    np.testing.assert_allclose(uv, camera.pixel_grid(), atol=1e-9)
    assert np.all(depth > 0)
    # depth per unit of ray length: a point t along the ray lies at camera depth t * z_per_t
    _, _, z_per_t = camera.rays_with_depth_scale()
    np.testing.assert_allclose(depth, 1.7 * z_per_t, atol=1e-12)


def test_rays_of_a_skewed_camera_pass_through_their_pixels():
    # the skew is part of K^-1: every consumer of rays (SDF training, ray casting, view directions) sees it
    posed = _posed_camera()
    skewed = Camera(K + np.array([[0.0, 4.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), posed.cam_from_world, 64, 48)
    origins, directions = skewed.rays()
    uv, _ = skewed.project(origins + 2.3 * directions)
    np.testing.assert_allclose(uv, skewed.pixel_grid(), atol=1e-9)
    np.testing.assert_allclose(skewed.view_directions().reshape(-1, 3), -directions, atol=1e-6)


def test_pixel_rays_hand_computed_case():
    # identity pose: the ray through (u, v) = (132, 24) is along K^-1 [u, v, 1] = [1, 0, 1] / sqrt(2)
    directions, z_per_t = pixel_rays(K, np.column_stack([np.eye(3), np.zeros(3)]), np.array([132.0]), np.array([24.0]))
    np.testing.assert_allclose(directions, [[2 ** -0.5, 0.0, 2 ** -0.5]], atol=1e-15)
    np.testing.assert_allclose(z_per_t, [2 ** -0.5], atol=1e-15)
    # scalars give one ray (the optical axis here)
    axis, _ = pixel_rays(K, np.column_stack([np.eye(3), np.zeros(3)]), K[0, 2], K[1, 2])
    np.testing.assert_array_equal(axis, [0.0, 0.0, 1.0])


def test_pixel_coordinates_divide_by_the_given_depth():
    points_cam = np.array([[0.5, -0.25, 2.0], [0.1, 0.2, -1.0]])
    u, v = pixel_coordinates(K, points_cam)
    np.testing.assert_allclose(u, [100 * 0.25 + 32, 100 * -0.1 + 32])
    np.testing.assert_allclose(v, [110 * -0.125 + 24, 110 * -0.2 + 24])
    # a guarded depth (1 behind the camera) replaces the divisor, float32 points stay float32 before K
    u_guarded, _ = pixel_coordinates(K, points_cam.astype(np.float32), np.array([2.0, 1.0], np.float32))
    np.testing.assert_allclose(u_guarded, [57.0, 42.0], rtol=1e-6)


def test_view_directions_are_the_rays_reversed_per_pixel():
    camera = _posed_camera()
    views = camera.view_directions()
    assert views.shape == (48, 64, 3) and views.dtype == np.float32
    _, directions = camera.rays()
    np.testing.assert_allclose(views.reshape(-1, 3), -directions, atol=1e-6)


def test_lift_depth_map_lifts_every_pixel():
    camera = _posed_camera()
    depth = np.full((48, 64), 2.0, np.float32)
    points = camera.lift_depth_map(depth)
    assert points.shape == (48, 64, 3)
    np.testing.assert_allclose(points.reshape(-1, 3), camera.lift(camera.pixel_grid(), np.full(48 * 64, 2.0)),
                               atol=1e-12)


def test_json_round_trip_keeps_the_record_and_its_order():
    record = {"camera_id": "00007", "width": 64, "height": 48, "K": K.tolist(), "dist": [0.0] * 5,
              "cam_from_world": _posed_camera().cam_from_world.tolist(), "focal_mm": 35.0,
              "white_reference": [0.9, 1.0, 1.1]}
    camera = Camera.from_json(record)
    assert camera.camera_id == "00007" and (camera.width, camera.height) == (64, 48)
    assert camera.K.shape == (3, 3) and camera.cam_from_world.shape == (3, 4)
    assert json.dumps(camera.to_json()) == json.dumps(record)
    # a (4, 4) pose is cut to its top rows
    square = Camera(K, np.vstack([camera.cam_from_world, [0.0, 0.0, 0.0, 1.0]]), 64, 48)
    np.testing.assert_array_equal(square.cam_from_world, camera.cam_from_world)
    assert list(Camera(K, camera.cam_from_world, 64, 48).to_json()) == ["camera_id", "K", "cam_from_world", "width",
                                                                        "height"]


@pytest.mark.parametrize("kwargs, match", [
    ({"K": np.eye(2)}, "K must be"),
    ({"K": np.zeros((3, 3))}, "focal"),
    ({"cam_from_world": np.eye(3)}, "cam_from_world must be"),
    ({"cam_from_world": np.full((3, 4), np.nan)}, "non-finite"),
    ({"width": 0}, "size"),
])
def test_bad_cameras_are_refused(kwargs, match):
    args = {"K": K, "cam_from_world": np.column_stack([np.eye(3), np.zeros(3)]), "width": 4, "height": 4} | kwargs
    with pytest.raises(ValueError, match=match):
        Camera(**args)
