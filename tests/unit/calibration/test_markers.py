"""Marker-frame calibration (calibration.markers) and the simulator's marker frame (synthetic.calibration):
sphere images, blob centroids, identification, and calibration of rendered cameras against the truth."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibration.geometric import camera_centre, pose_errors
from calibration.markers import (MarkerCalibrationConfig, calibrate_markers, centre_std_mm, common_shift,
                                 common_zoom_and_shift,
                                 detect_blobs, identify_markers, project_points, sphere_image_centres)
from synthetic.calibration import CalibrationConfig, marker_layout, render_markers
from synthetic.rig import look_at, make_cameras, make_leds, perturb_pose
from synthetic.shading import background_image

K = np.array([[500.0, 0.0, 159.5], [0.0, 501.4, 239.5], [0.0, 0.0, 1.0]])


def test_sphere_image_centre_on_axis_and_off_axis():
    P = np.hstack([np.eye(3), np.zeros((3, 1))])
    uv, depth, radius = sphere_image_centres(K, P, np.array([[0.0, 0.0, 2.0]]), 0.1)
    np.testing.assert_allclose(uv[0], K[:2, 2])
    assert depth[0] == 2.0
    assert radius[0] == pytest.approx(500.0 * 0.1 / np.sqrt(4.0 - 0.01))   # tan of the cone's half-angle
    # off axis: the silhouette's centre is the midpoint of its extreme points along the radial line,
    # found here by bisection on rays that graze the sphere
    centre = np.array([0.5, 0.0, 1.0])
    r = 0.2
    uv, _, _ = sphere_image_centres(K, P, centre[None], r)

    def hits(u: float) -> bool:
        d = np.array([(u - K[0, 2]) / K[0, 0], 0.0, 1.0])
        d /= np.linalg.norm(d)
        return np.linalg.norm(centre - (centre @ d) * d) <= r

    inside = K[0, 0] * 0.5 + K[0, 2]
    edges = []
    for outside in (inside - 400.0, inside + 400.0):
        a, b = inside, outside
        for _ in range(60):
            m = 0.5 * (a + b)
            a, b = (m, b) if hits(m) else (a, m)
        edges.append(a)
    assert uv[0, 0] == pytest.approx(0.5 * sum(edges), abs=1e-6)
    assert uv[0, 0] > inside + 5.0                                         # pushed outwards, not the projection


def test_sphere_behind_camera_has_no_image():
    P = np.hstack([np.eye(3), np.zeros((3, 1))])
    uv, _, radius = sphere_image_centres(K, P, np.array([[0.0, 0.0, -2.0], [0.0, 0.0, 0.05]]), 0.1)
    assert np.isnan(uv).all() and (radius == 0).all()


def _disc_image(centres: np.ndarray, radius: float, shape=(60, 80), supersample: int = 8,
                background: np.ndarray | None = None) -> np.ndarray:
    v, u = np.mgrid[0:shape[0] * supersample, 0:shape[1] * supersample]
    u = (u + 0.5) / supersample - 0.5
    v = (v + 0.5) / supersample - 0.5
    fine = np.zeros(u.shape)
    for cu, cv in centres:
        fine[(u - cu) ** 2 + (v - cv) ** 2 <= radius ** 2] = 0.9
    image = fine.reshape(shape[0], supersample, shape[1], supersample).mean(axis=(1, 3))
    return image + (0.03 if background is None else background)


def test_detect_blobs_finds_subpixel_centroids_on_a_sloped_background():
    truth = np.array([[12.3, 15.7], [40.55, 20.25], [65.9, 44.1]])
    slope = 0.03 + 0.002 * np.arange(80)[None, :] + 0.001 * np.arange(60)[:, None]
    image = _disc_image(truth, 2.2, background=slope)
    centroids, pixels, peaks = detect_blobs(image, threshold=0.2)
    assert len(centroids) == 3
    order = np.argsort(centroids[:, 0])
    np.testing.assert_allclose(centroids[order], truth, atol=0.02)
    assert (pixels > 10).all() and (peaks > 0.8).all()
    assert len(detect_blobs(np.full((20, 20), 0.5), 0.2)[0]) == 0
    with pytest.raises(ValueError):
        detect_blobs(np.zeros((4, 4, 3)), 0.2)


def test_common_shift_and_identification():
    rng = np.random.default_rng(0)
    predicted = rng.uniform(0, 300, size=(40, 2))
    blobs = np.vstack([predicted + [6.3, -4.1] + rng.normal(0, 0.1, (40, 2)), rng.uniform(0, 300, (5, 2))])
    shift, votes = common_shift(predicted, blobs, max_shift_px=20.0)
    np.testing.assert_allclose(shift, [6.3, -4.1], atol=0.1)
    assert votes > 3.0                     # 40 agreeing differences, 3x3-smoothed; the 5 clutter blobs: < 1
    # a 3% zoom about the principal point on top of the shift (a nominal focal length 3% off)
    centre = np.array([150.0, 150.0])
    zoomed = centre + 1.03 * (predicted - centre) + [6.3, -4.1]
    zoom, shift2 = common_zoom_and_shift(predicted, zoomed, centre, 20.0, 0.05)
    assert zoom == pytest.approx(1.03)
    np.testing.assert_allclose(shift2, [6.3, -4.1], atol=0.3)
    radius = np.full(40, 2.0)
    match = identify_markers(predicted + shift, radius, np.ones(40, bool), blobs, 1.0, 3.0)
    clear = np.array([all(np.linalg.norm(predicted[i] - predicted[j]) > 7.0 for j in range(40) if j != i)
                      for i in range(40)])
    assert (match[clear] == np.arange(40)[clear]).all()
    assert (match[~clear] == -1).all()
    # two balls whose images overlap are never used; an unusable ball is never matched
    pair = np.array([[50.0, 50.0], [53.0, 50.0], [100.0, 100.0]])
    match = identify_markers(pair, np.full(3, 2.0), np.array([True, True, False]), pair, 1.0, 3.0)
    assert match.tolist() == [-1, -1, -1]


def test_marker_layout_is_a_property_of_the_frame():
    calib = CalibrationConfig(marker_count=120)
    centre = np.array([0.0, 0.1, 0.0])
    true, surveyed = marker_layout(calib, centre)
    assert true.shape == (120, 3)
    assert np.linalg.norm(true - centre, axis=1).max() <= calib.marker_volume_radius_m + 1e-12
    gaps = np.linalg.norm(true[:, None] - true[None], axis=-1) + np.eye(120) * 10
    assert gaps.min() >= calib.marker_min_separation_m
    assert 0.03e-3 < np.std(surveyed - true) < 0.2e-3                        # 0.1 mm survey error
    np.testing.assert_array_equal(marker_layout(calib, centre)[0], true)
    other = marker_layout(dataclasses.replace(calib, marker_seed=1), centre)[0]
    assert not np.allclose(other, true)


def _rig(n_cameras: int, width: int, seed: int = 3):
    """True cameras (the simulator's rig round a 1.7 m subject), nominal ones off by the rig tolerances."""
    height = int(2 * round(width * 6016 / 4016 / 2))
    cameras = make_cameras(n_cameras, width, height, 0.52, (-0.83, 0.83), np.random.default_rng(seed))
    rng = np.random.default_rng(seed + 100)
    nominal = {}
    for cam in cameras:
        Kn = cam.K.copy()
        Kn[:2, :2] *= 1.0 + rng.normal(0.0, 0.005)
        nominal[cam.camera_id] = (Kn, perturb_pose(cam.cam_from_world, rng, angle_deg=0.2, shift_m=0.003))
    return cameras, nominal


def test_render_markers_covers_the_ball_area():
    camera = _rig(1, 320)[0][0]
    leds = make_leds(128, 0.0, 1.6, np.random.default_rng(0))
    target = np.array([0.0, 0.0, 0.0])
    ball = target + 0.3 * (camera.centre_world - target) / np.linalg.norm(camera.centre_world - target)
    radiance, coverage = render_markers(camera, leds, background_image(camera, 1.6), ball[None], 0.02, 0.9, 4)
    uv, _, apparent = sphere_image_centres(camera.K, camera.cam_from_world, ball[None], 0.02)
    assert coverage.sum() == pytest.approx(np.pi * apparent[0] ** 2, rel=0.03)
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    np.testing.assert_allclose([(coverage * u).sum() / coverage.sum(), (coverage * v).sum() / coverage.sum()],
                               uv[0], atol=0.05)                              # 4x4 sub-samples: ~0.015 px rms
    assert np.isfinite(radiance).all() and radiance.max() > 0.5                # the ball is bright (albedo 0.9)


@pytest.fixture(scope="module")
def rendered():
    """8 true cameras, their nominal cameras and grey images (white ~1, with noise) of the marker frame."""
    cameras, nominal = _rig(8, 320)
    calib = CalibrationConfig()
    true, surveyed = marker_layout(calib, np.zeros(3))
    leds = make_leds(128, 0.0, 1.6, np.random.default_rng(0))
    rng = np.random.default_rng(5)
    white = float(leds.white_radiance().mean())
    images = {}
    for cam in cameras:
        radiance, _ = render_markers(cam, leds, background_image(cam, 1.6), true, calib.marker_radius_m,
                                     calib.marker_albedo, 4)
        grey = radiance.mean(axis=-1) / white
        images[cam.camera_id] = (grey + rng.normal(0.0, 0.005, grey.shape)).astype(np.float32)
    return cameras, nominal, images, surveyed, calib.marker_radius_m


def test_calibrate_markers_beats_the_goal_on_rendered_frames(rendered):
    cameras, nominal, images, surveyed, radius = rendered
    result = calibrate_markers(images, {c: k for c, (k, _) in nominal.items()},
                               {c: p for c, (_, p) in nominal.items()}, surveyed, radius)
    truth = {c.camera_id: c.cam_from_world for c in cameras}
    assert sorted(result.cameras) == sorted(truth) and result.unregistered == []
    errors = pose_errors({n: c.cam_from_world for n, c in result.cameras.items()}, truth, align=False)
    nominal_errors = pose_errors({c: p for c, (_, p) in nominal.items()}, truth, align=False)
    assert nominal_errors["centre_error_mm_mean"] > 3.0                        # what calibration must beat
    assert errors["rotation_deg_max"] < 0.02 and errors["centre_error_mm_max"] < 1.0, errors
    focal = [abs(result.cameras[c.camera_id].K[0, 0] / c.K[0, 0] - 1) for c in cameras]
    assert max(focal) < 5e-4                                                   # nominal: 0.5% sigma
    for c in cameras:                                                           # pixel aspect and principal point kept
        Kc = result.cameras[c.camera_id].K
        assert Kc[1, 1] / Kc[0, 0] == pytest.approx(nominal[c.camera_id][0][1, 1] / nominal[c.camera_id][0][0, 0])
        np.testing.assert_allclose(Kc[:2, 2], nominal[c.camera_id][0][:2, 2])
    assert result.reprojection_error_px < 0.1 and result.aligned
    assert result.reconstruction.num_points3D() == result.n_points3d > 100
    # the observations behind the reconstruction are the corrected centroids the cameras were fitted to
    assert result.reconstruction.compute_mean_reprojection_error() == pytest.approx(result.reprojection_error_px, rel=0.05)


def test_calibration_does_not_depend_on_what_ran_before_it(rendered):
    """COLMAP's RANSAC generator lives as long as the process: the same frames calibrated again in this
    process, after other fits, and with the cameras in another order give the same cameras to the bit."""
    cameras, nominal, images, surveyed, radius = rendered

    def calibrate(names):
        result = calibrate_markers({c: images[c] for c in names}, {c: nominal[c][0] for c in names},
                                   {c: nominal[c][1] for c in names}, surveyed, radius)
        return {n: (c.K, c.cam_from_world) for n, c in result.cameras.items()}

    names = sorted(images)
    first = calibrate(names)
    calibrate(names[:3])  # other fits in between move the generator along
    for again in (calibrate(names), calibrate(names[::-1])):
        assert sorted(again) == sorted(first)
        for name, (K, pose) in first.items():
            np.testing.assert_array_equal(again[name][0], K)
            np.testing.assert_array_equal(again[name][1], pose)


def test_calibrate_markers_names_the_camera_it_cannot_calibrate(rendered):
    cameras, nominal, images, surveyed, radius = rendered
    images = dict(images)
    dark = cameras[0].camera_id
    images[dark] = np.zeros_like(images[dark])
    result = calibrate_markers(images, {c: k for c, (k, _) in nominal.items()},
                               {c: p for c, (_, p) in nominal.items()}, surveyed, radius)
    assert result.unregistered == [dark]
    assert any(n.startswith(f"{dark}: only 0 bright blobs") for n in result.notes)
    with pytest.raises(ValueError, match="no nominal camera"):
        calibrate_markers(images, {}, {}, surveyed, radius)


def test_rig_frame_moves_the_cameras_onto_the_nominal_centres(rendered):
    cameras, nominal, images, surveyed, radius = rendered
    names = sorted(images)[:5]
    result = calibrate_markers({n: images[n] for n in names}, {c: k for c, (k, _) in nominal.items()},
                               {c: p for c, (_, p) in nominal.items()}, surveyed, radius,
                               MarkerCalibrationConfig(frame="rig"))
    src = np.array([camera_centre(result.cameras[n].cam_from_world) for n in names])
    dst = np.array([camera_centre(nominal[n][1]) for n in names])
    np.testing.assert_allclose(src.mean(0), dst.mean(0), atol=1e-9)         # rigid fit: centroids agree


def test_centre_std_grows_with_noise_and_fixed_focal_is_tighter():
    P = look_at(np.array([0.0, 0.0, 3.0]), np.zeros(3))
    pts = np.random.default_rng(0).uniform(-1.0, 1.0, size=(150, 3))
    free = centre_std_mm(K, P, pts, 0.1)
    assert centre_std_mm(K, P, pts, 0.2) == pytest.approx(2 * free, rel=1e-6)
    assert centre_std_mm(K, P, pts, 0.1, refine_focal_length=False) < free
    # a shallow target (+-5 cm at 3 m) cannot tell distance from focal length
    flat = pts * np.array([1.0, 1.0, 0.05])
    assert centre_std_mm(K, P, flat, 0.1) > 5 * free
    np.testing.assert_allclose(project_points(K, P, np.zeros((1, 3))), K[None, :2, 2])
