"""Turntable of the release page: cameras on a circle about +y that frame the mesh; shaded frames side by side."""
from __future__ import annotations

import numpy as np
import pytest

from stages.numerics.turntable import turntable_cameras, turntable_strip


def _box(size=(0.4, 1.6, 0.3), centre=(0.1, 0.9, -0.2)):
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64) / 2
    vertices = corners * size + centre
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                      [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int64)
    return vertices, faces


def test_cameras_circle_the_mesh_about_up_and_frame_all_of_it():
    vertices, _ = _box()
    cams = turntable_cameras(vertices, 8, 240, 160)
    centre = (vertices.min(0) + vertices.max(0)) / 2
    eyes = []
    for K, P in cams:
        R, t = P[:, :3], P[:, 3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-9)
        x = (vertices @ R.T + t)
        assert (x[:, 2] > 0).all()
        uv = x @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        assert (uv >= 0).all() and (uv[:, 0] < 160).all() and (uv[:, 1] < 240).all()
        c = K @ (R @ centre + t)
        assert np.allclose(c[:2] / c[2], [79.5, 119.5], atol=1e-6)  # looks at the centre
        assert (R[1] @ [0, 1, 0]) < 0  # image y (down) points against world +y (up)
        eyes.append(-R.T @ t)
    eyes = np.array(eyes)
    assert np.allclose(eyes[:, 1], eyes[0, 1])  # one height: a turn about +y
    assert np.allclose(np.linalg.norm((eyes - centre)[:, [0, 2]], axis=1), np.linalg.norm((eyes - centre)[0, [0, 2]]))
    with pytest.raises(ValueError, match="vertices"):
        turntable_cameras(np.zeros((0, 3)), 8, 10, 10)


def test_strip_shows_the_textured_mesh_on_a_background():
    from stages.numerics.raycast import mesh_scene

    vertices, faces = _box()
    uvs = np.full((len(vertices), 2), 0.5)
    albedo = np.zeros((4, 4, 3), np.float32)
    albedo[..., 0] = 0.8  # red
    cams = turntable_cameras(vertices, 3, 60, 40)
    strip = turntable_strip(mesh_scene(vertices, faces), faces, uvs, albedo, cams, 60, 40)
    assert strip.shape == (60, 120, 3) and strip.dtype == np.float32
    for i in range(3):
        frame = strip[:, 40 * i:40 * (i + 1)]
        subject = frame[..., 1] < 0.5  # the background is white, the box red
        assert 0.05 < subject.mean() < 0.9
        assert (frame[subject, 0] > 0.19).all() and (frame[subject, 0] <= 0.8 + 1e-6).all()
        assert (frame[~subject] == 1.0).all()
