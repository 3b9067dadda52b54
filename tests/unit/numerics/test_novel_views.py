"""gbuffer.interpolate_camera and novel_camera_pairs: novel cameras between captured neighbours."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.numerics.gbuffer import camera_centre, interpolate_camera, novel_camera_pairs
from synthetic.rig import look_at as rig_look_at

KA = np.array([[800.0, 0.0, 159.5], [0.0, 810.0, 239.5], [0.0, 0.0, 1.0]])
KB = np.array([[900.0, 0.0, 161.5], [0.0, 880.0, 241.5], [0.0, 0.0, 1.0]])


def look_at(eye, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    return rig_look_at(np.asarray(eye, float), np.asarray(target, float))


def ring(azimuth_deg: float, radius: float = 3.0, height: float = 0.0) -> np.ndarray:
    a = np.radians(azimuth_deg)
    return look_at([radius * np.sin(a), height, radius * np.cos(a)])


def rotation_angle_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(R1 @ R2.T).magnitude()))


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


# ------------------------------------------------------------------------------- interpolate_camera
def test_ends_give_back_the_cameras():
    Pa, Pb = look_at([2.0, 0.5, 2.0]), look_at([-0.5, 1.0, 3.0], target=(0.1, 0.2, 0.0))
    K0, P0 = interpolate_camera(KA, Pa, KB, Pb, 0.0)
    K1, P1 = interpolate_camera(KA, Pa, KB, Pb, 1.0)
    assert P0.shape == (3, 4) and K0.shape == (3, 3) and P0.dtype == np.float64
    np.testing.assert_allclose(K0, KA)
    np.testing.assert_allclose(K1, KB)
    np.testing.assert_allclose(P0, Pa, atol=1e-9)
    np.testing.assert_allclose(P1, Pb, atol=1e-9)
    # 4x4 poses are accepted too
    P4 = np.vstack([Pa, [0, 0, 0, 1]])
    np.testing.assert_allclose(interpolate_camera(KA, P4, KB, Pb, 0.0)[1], Pa, atol=1e-9)


def test_midpoint_is_on_the_arc_with_the_slerp_rotation():
    Pa = look_at([3.0, 0.4, 0.0], target=(0.0, 0.2, 0.0))
    Pb = look_at([0.0, 1.0, 2.0], target=(0.1, 0.0, 0.0))  # another radius, height and target
    K, P = interpolate_camera(KA, Pa, KB, Pb, 0.5)
    ca, cb, c = camera_centre(Pa), camera_centre(Pb), camera_centre(P)
    np.testing.assert_allclose(np.linalg.norm(c), 0.5 * (np.linalg.norm(ca) + np.linalg.norm(cb)), rtol=1e-9)
    omega = angle_deg(ca, cb)
    assert angle_deg(c, ca) == pytest.approx(omega / 2, abs=1e-6)
    assert angle_deg(c, cb) == pytest.approx(omega / 2, abs=1e-6)
    assert abs(np.linalg.det(np.stack([ca, cb, c]))) < 1e-9  # in the plane of the arc
    R, Ra, Rb = P[:, :3], Pa[:, :3], Pb[:, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    half = rotation_angle_deg(Ra, Rb) / 2
    assert half > 10
    assert rotation_angle_deg(R, Ra) == pytest.approx(half, abs=1e-6)
    assert rotation_angle_deg(R, Rb) == pytest.approx(half, abs=1e-6)
    np.testing.assert_allclose(K, 0.5 * (KA + KB))


def test_ring_midpoint_looks_at_the_centre():
    # two cameras on a horizontal ring looking at the origin: the one between them sits at the middle
    # azimuth and looks at the origin too (the slerp of two yaw rotations is the half yaw)
    _, P = interpolate_camera(KA, ring(10.0), KA, ring(70.0), 0.5)
    np.testing.assert_allclose(P, ring(40.0), atol=1e-9)
    _, P = interpolate_camera(KA, ring(10.0, radius=2.0), KA, ring(70.0, radius=4.0), 0.25)
    np.testing.assert_allclose(camera_centre(P), camera_centre(ring(25.0, radius=2.5)), atol=1e-9)


def test_interpolate_camera_rejects_bad_inputs():
    with pytest.raises(ValueError, match="opposite"):
        interpolate_camera(KA, ring(0.0), KA, ring(180.0), 0.5)
    with pytest.raises(ValueError, match="t must be"):
        interpolate_camera(KA, ring(0.0), KA, ring(30.0), 1.5)
    with pytest.raises(ValueError, match="origin"):
        interpolate_camera(KA, look_at([0.0, 0.0, 0.0], target=(0.0, 0.0, 1.0)), KA, ring(30.0), 0.5)
    with pytest.raises(ValueError, match="K_b"):
        interpolate_camera(KA, ring(0.0), KA[:2], ring(30.0), 0.5)
    with pytest.raises(ValueError, match="cam_from_world_a"):
        interpolate_camera(KA, ring(0.0)[:2], KA, ring(30.0), 0.5)


# ------------------------------------------------------------------------------- novel_camera_pairs
# irregular ring: neighbours at different gaps, two heights
AZIMUTHS = [0, 20, 55, 70, 110, 150, 165, 200, 240, 250, 290, 330]


def ring_rig():
    return [ring(a, height=0.8 if i % 2 else -0.3) for i, a in enumerate(AZIMUTHS)]


def test_pairs_are_distinct_nearest_neighbours():
    poses = ring_rig()
    dirs = np.stack([camera_centre(P) / np.linalg.norm(camera_centre(P)) for P in poses])
    angles = np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1, 1)))
    np.fill_diagonal(angles, np.inf)
    pairs = novel_camera_pairs(poses, 4)
    assert len(pairs) == 4 and len(set(pairs)) == 4
    for a, b in pairs:
        assert 0 <= a < b < len(poses)
        # one of the two is the anchor, and the other is its nearest camera
        assert angles[a, b] == pytest.approx(angles[a].min()) or angles[a, b] == pytest.approx(angles[b].min())
    # spread around the ring: the pairs start in at least three of its four quarters
    quarters = {int(min(AZIMUTHS[a], AZIMUTHS[b]) // 90) for a, b in pairs}
    assert len(quarters) >= 3


def test_pair_count_is_respected_and_never_repeats():
    poses = ring_rig()
    assert len(novel_camera_pairs(poses, 1)) == 1
    many = novel_camera_pairs(poses, 40)  # more than cameras: each anchor once, duplicates dropped
    assert len(many) == len(set(many)) <= len(poses)
    assert all(a != b for a, b in many)
    assert novel_camera_pairs(poses[:2], 3) == [(0, 1)]
    # the subject centre moves the directions: still valid pairs
    assert all(a < b for a, b in novel_camera_pairs(poses, 3, subject_centre=(0.0, 0.5, 0.0)))


def test_pairs_reject_bad_inputs():
    with pytest.raises(ValueError, match="two cameras"):
        novel_camera_pairs([ring(0.0)], 1)
    with pytest.raises(ValueError, match="count"):
        novel_camera_pairs(ring_rig(), 0)
    with pytest.raises(ValueError, match="cam_from_worlds"):
        novel_camera_pairs([ring(0.0), np.eye(3)], 1)
