"""The relighting set's draws and conversions (stages.numerics.relightset)."""
from __future__ import annotations

import numpy as np
import pytest

from stages.numerics.relightset import (choose_environment, encode_normals, look_at, normals_to_camera, orbit_camera,
                                        split_of, tone_map, unit_draw)


def test_unit_draw_is_deterministic_uniform_and_keyed():
    draws = [unit_draw(0, "rotation", f"A{i:04d}_00") for i in range(2000)]
    assert draws == [unit_draw(0, "rotation", f"A{i:04d}_00") for i in range(2000)]
    assert all(0.0 <= d < 1.0 for d in draws)
    assert abs(np.mean(draws) - 0.5) < 0.03 and abs(np.var(draws) - 1 / 12) < 0.01
    assert unit_draw(1, "rotation", "A0000_00") != unit_draw(0, "rotation", "A0000_00")
    assert unit_draw(0, "azimuth", "A0000_00") != unit_draw(0, "rotation", "A0000_00")


def test_choose_environment_keeps_choices_when_a_map_is_added():
    pool = [f"{i:064x}" for i in range(5)]
    ids = [f"A{i:04d}_{k:02d}" for i in range(300) for k in range(3)]
    before = {e: pool[choose_environment(7, e, pool)] for e in ids}
    bigger = pool + [f"{99:064x}"]
    after = {e: bigger[choose_environment(7, e, bigger)] for e in ids}
    moved = [e for e in ids if before[e] != after[e]]
    # only examples the new map takes over change, about 1/6 of them
    assert all(after[e] == bigger[-1] for e in moved)
    assert 0.10 < len(moved) / len(ids) < 0.24
    # the order of the pool does not matter; every map gets used
    shuffled = pool[::-1]
    assert all(shuffled[choose_environment(7, e, shuffled)] == before[e] for e in ids)
    assert set(before.values()) == set(pool)
    with pytest.raises(ValueError):
        choose_environment(0, "x", [])


def test_split_of_is_per_subject_and_follows_ratios():
    subjects = [f"subject{i}" for i in range(3000)]
    splits = [split_of(0, s, (0.8, 0.1, 0.1)) for s in subjects]
    shares = {name: splits.count(name) / len(splits) for name in ("train", "validation", "test")}
    assert abs(shares["train"] - 0.8) < 0.03 and abs(shares["test"] - 0.1) < 0.03
    assert split_of(0, "subject1", (0.8, 0.1, 0.1)) == split_of(0, "subject1", (0.8, 0.1, 0.1))
    assert {split_of(0, s, (0.0, 0.0, 1.0)) for s in subjects[:50]} == {"test"}
    assert {split_of(0, s, (1.0, 0.0, 0.0)) for s in subjects[:50]} == {"train"}
    for bad in ((0.5, 0.5), (0.5, 0.6, -0.1), (0.3, 0.3, 0.3)):
        with pytest.raises(ValueError):
            split_of(0, "s", bad)


def test_look_at_by_hand():
    # a camera on +z looking at the origin: right is +x (OpenCV x), down is -y, forward is -z
    pose = look_at(np.array([0.0, 0.0, 2.0]), np.zeros(3))
    np.testing.assert_allclose(pose[:, :3], [[1, 0, 0], [0, -1, 0], [0, 0, -1]], atol=1e-12)
    np.testing.assert_allclose(pose[:, :3] @ np.zeros(3) + pose[:, 3], [0, 0, 2], atol=1e-12)
    with pytest.raises(ValueError):
        look_at(np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError):
        look_at(np.array([0.0, 2.0, 0.0]), np.zeros(3))


def test_orbit_camera_frames_the_bounding_sphere():
    centre, radius, size, margin = np.array([0.1, 0.9, -0.2]), 0.5, 200, 0.05
    K, pose = orbit_camera(centre, radius, 3.0, azimuth_deg=90.0, elevation_deg=20.0, size=size, margin=margin)
    rotation, t = pose[:, :3], pose[:, 3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    position = -rotation.T @ t
    np.testing.assert_allclose(np.linalg.norm(position - centre), 3.0, rtol=1e-12)
    assert position[0] - centre[0] > 2.0  # azimuth 90 deg: on +x
    assert np.degrees(np.arcsin((position[1] - centre[1]) / 3.0)) == pytest.approx(20.0)
    x = K @ (rotation @ centre + t)
    np.testing.assert_allclose(x[:2] / x[2], [(size - 1) / 2] * 2, atol=1e-9)  # centre in the middle
    # the sphere's silhouette (a tangent cone) spans the image less the margins
    half_width_px = K[0, 0] * np.tan(np.arcsin(radius / 3.0))
    assert half_width_px == pytest.approx(size / 2 * (1 - 2 * margin))
    with pytest.raises(ValueError):
        orbit_camera(centre, 1.0, 0.5, 0.0, 0.0, size)


def test_normals_to_camera_and_encodings():
    pose = look_at(np.array([0.0, 0.0, 2.0]), np.zeros(3))
    normals_world = np.zeros((2, 2, 3), np.float32)
    normals_world[0, 0] = [0, 0, 1]  # facing the camera
    normals_world[0, 1] = [0, 1, 0]  # up
    cam = normals_to_camera(normals_world, pose)
    np.testing.assert_allclose(cam[0, 0], [0, 0, -1], atol=1e-6)  # OpenCV: towards the camera is -z
    np.testing.assert_allclose(cam[0, 1], [0, -1, 0], atol=1e-6)  # up is -y
    np.testing.assert_array_equal(cam[1, 1], 0)
    mask = np.array([[True, True], [False, False]])
    picture = encode_normals(cam, mask)
    np.testing.assert_array_equal(picture[0, 0], [128, 128, 0])
    np.testing.assert_array_equal(picture[1], 0)
    image = np.full((1, 2, 3), 0.5, np.float32)
    image[0, 1] = 100.0
    mapped = tone_map(image, 1.0)
    assert mapped.dtype == np.uint8 and mapped[0, 1, 0] == 255 and mapped[0, 0, 0] == 188  # sRGB(0.5)
    with pytest.raises(ValueError):
        tone_map(image, 0.0)
