"""Light calibration: ratio model, per-pixel inversion, sphere normals; the simulator's calibration
frames end to end; DiLiGenT's real sphere (skips without ../shared)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.light import (LightModel, angular_error_deg, basis, correct_normals, fit_light_model,
                               ideal_light_model, sphere_normals)

SHARED = Path(__file__).resolve().parents[3].parent / "shared" / "data"
DILIGENT = SHARED / "photometric" / "diligent_ball"
needs_diligent = pytest.mark.skipif(not (DILIGENT / "Normal_gt.mat").is_file(),
                                    reason=f"shared data not found ({DILIGENT}); a fresh clone has no ../shared")


def random_normals(n: int, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_basis_jacobian_matches_finite_differences():
    n = random_normals(50)
    for degree in (1, 2, 3):
        phi, dphi = basis(n, degree, jacobian=True)
        assert phi.shape == (50, (degree + 1) ** 2) and dphi.shape == (50, (degree + 1) ** 2, 3)
        for j in range(3):
            step = np.zeros(3)
            step[j] = 1e-6
            numeric = (basis(n + step, degree) - basis(n - step, degree)) / 2e-6
            np.testing.assert_allclose(dphi[:, :, j], numeric, atol=1e-6)
        # linearly independent on the sphere (full column rank)
        assert np.linalg.matrix_rank(basis(random_normals(500, 1), degree)) == (degree + 1) ** 2


def test_ideal_leds_model_is_two_thirds_n_and_correction_is_identity():
    n = random_normals(2000)
    ideal = ideal_light_model(2)
    np.testing.assert_allclose(ideal.predict(n), 2.0 / 3.0 * n, atol=1e-15)
    fitted = fit_light_model(2.0 / 3.0 * n, n, degree=2)
    np.testing.assert_allclose(fitted.coefficients, ideal.coefficients, atol=1e-12)
    assert fitted.rms_residual < 1e-12
    # identity also for a shrunk |d| (occlusion) and an image-shaped input
    d = (2.0 / 3.0 * n * np.random.default_rng(2).uniform(0.3, 1.0, (2000, 1))).reshape(40, 50, 3)
    corrected = correct_normals(d, fitted)
    assert corrected.shape == (40, 50, 3) and corrected.dtype == np.float32
    np.testing.assert_allclose(corrected.reshape(-1, 3), n, atol=1e-6)
    for degree in (1, 3):
        np.testing.assert_allclose(correct_normals(2.0 / 3.0 * n, ideal_light_model(degree)), n, atol=1e-6)


def test_biased_ratio_is_inverted():
    """A smooth, strongly biased ratio model (LEDs brighter above, dimmer blue) is fitted and inverted."""
    rng = np.random.default_rng(3)
    n = random_normals(5000, 4)
    n = n[n[:, 2] > -0.2]                     # a camera sees a bit more than a hemisphere
    truth = ideal_light_model(2)
    coefficients = truth.coefficients + 0.05 * rng.normal(size=truth.coefficients.shape)
    model = LightModel(2, coefficients)
    d = model.predict(n)
    before = angular_error_deg(d / np.linalg.norm(d, axis=1, keepdims=True), n)
    fitted = fit_light_model(d + 0.002 * rng.normal(size=d.shape), n, degree=2)
    after = angular_error_deg(correct_normals(d, fitted), n)
    assert before.mean() > 2.0 and after.mean() < 0.2, (before.mean(), after.mean())
    # JSON round trip
    again = LightModel.from_json(json.loads(fitted.dumps()))
    np.testing.assert_array_equal(again.coefficients, fitted.coefficients)
    assert again.degree == 2 and again.samples == fitted.samples
    # undefined input stays 0 and finite
    bad = np.array([[0.0, 0.0, 0.0], [np.nan, 0.1, 0.2], [0.1, 0.2, 0.5]])
    out = correct_normals(bad, fitted, mask=np.array([True, True, False]))
    assert np.all(out == 0) and np.all(np.isfinite(out))
    with pytest.raises(ValueError):
        fit_light_model(d[:10], n[:10], degree=2)


def test_sphere_normals_by_ray_intersection():
    K = np.array([[200.0, 0, 49.5], [0, 200.0, 39.5], [0, 0, 1]])
    # camera at z = +2 looking down -z (OpenCV: x right, y down, z forward)
    rotation = np.diag([1.0, -1.0, -1.0])
    centre_cam = np.array([0.0, 0.0, 2.0])
    cam_from_world = np.column_stack([rotation, -rotation @ centre_cam])
    normals, mask = sphere_normals(K, cam_from_world, 100, 80, np.zeros(3), 0.2)
    assert normals.shape == (80, 100, 3) and mask.shape == (80, 100)
    # radius 0.2 at distance 2 subtends ~ 200 * 0.2 / sqrt(4 - 0.04) ~ 20.1 px radius
    assert abs(mask.sum() - np.pi * 20.1 ** 2) < 60
    np.testing.assert_allclose(np.linalg.norm(normals[mask], axis=-1), 1.0, atol=1e-6)
    assert np.all(normals[~mask] == 0)
    centre_pixel = normals[39, 49]  # near the principal point: faces the camera (+z world)
    assert centre_pixel[2] > 0.999
    assert normals[39, 60][0] > 0.3 and normals[30, 49][1] > 0.3  # right -> +x, up (row above) -> +y
    # the normal points towards the camera on every pixel
    hit_to_camera = centre_cam - 0.2 * normals[mask]
    assert np.all(np.sum(normals[mask] * hit_to_camera, axis=1) > 0)


# --- the simulator's calibration frames --------------------------------------------------------------------

@pytest.fixture(scope="module")
def calibration_capture(tmp_path_factory):
    from synthetic import SimConfig, simulate
    from synthetic.calibration import CalibrationConfig

    config = SimConfig(actions=1, width=128, n_cameras=8, n_leds=256, mesh="procedural", noise=False,
                       specular=False, background=False, led_error=0.1)
    return simulate(tmp_path_factory.mktemp("calib") / "cap", config, calibration=CalibrationConfig())


def _decoded_ratio(capture: Path, folder: str, camera: dict, correction: np.ndarray) -> tuple[np.ndarray, ...]:
    from calibration.colour import apply_colour_matrix
    from pipeline.codecs.raw import decode_raw

    frames = {}
    for illumination in ("pos", "neg"):
        rgb = decode_raw(capture / folder / illumination / f"{camera['camera_id']}.dng").rgb
        frames[illumination] = apply_colour_matrix(rgb, correction, out=rgb)
    total = frames["pos"] + frames["neg"]
    return (frames["pos"] - frames["neg"]) / np.maximum(total, 1e-6)


def test_simulator_sphere_calibration_reduces_the_normal_error(calibration_capture):
    """Fit on the sphere in the even cameras, test on the sphere in the odd ones and on the subject's
    unoccluded pixels in all cameras; colour matrices from the chart frames."""
    from scipy import ndimage

    from calibration.colour import chart_patch_means, fit_colour_matrix, reference_chart_srgb
    from pipeline.codecs.exr import read_exr
    from pipeline.codecs.raw import decode_raw

    capture = calibration_capture
    session = capture / "sessions" / "S000"
    rig = json.loads((session / "rig.json").read_text())
    chart = json.loads((session / "calibration" / "chart.json").read_text())
    sphere = rig["calibration_objects"]["sphere"]
    # The rig spec holds nominal cameras (mounting tolerances); this test is about the LEDs, so the
    # sphere's normals come from the true cameras.
    true_cameras = json.loads((capture / "ground_truth" / "cameras" / "S000.json").read_text())["cameras"]
    _, reference = reference_chart_srgb()
    d_parts, n_parts, corrections = [], [], {}
    for index, camera in enumerate(true_cameras):
        cid = camera["camera_id"]
        image = decode_raw(session / chart["cameras"][cid]["frame"]).rgb
        labels = np.zeros(image.shape[:2], np.int64)
        for k, (x0, y0, x1, y1) in enumerate(chart["cameras"][cid]["patch_boxes"]):
            labels[y0:y1, x0:x1] = k + 1
        means, _ = chart_patch_means(image, labels, erode=2)
        corrections[cid] = fit_colour_matrix(means, np.asarray(camera["white_reference"]) * reference)
        d = _decoded_ratio(session, "calibration/sphere", camera, corrections[cid])
        normals, mask = sphere_normals(np.asarray(camera["K"]), np.asarray(camera["cam_from_world"]),
                                       camera["width"], camera["height"], sphere["centre"], sphere["radius_m"])
        mask = ndimage.binary_erosion(mask, iterations=2)
        d_parts.append(d[mask])
        n_parts.append(normals[mask])
    # cameras 0, 2, 4, 6 (rings 0 and 2, both sides of the stage) fit, cameras 1, 3, 5, 7 test
    model = fit_light_model(np.concatenate(d_parts[0::2]), np.concatenate(n_parts[0::2]), degree=2)
    d_test, n_test = np.concatenate(d_parts[1::2]), np.concatenate(n_parts[1::2])
    sphere_before = angular_error_deg(d_test / np.linalg.norm(d_test, axis=1, keepdims=True), n_test).mean()
    sphere_after = angular_error_deg(correct_normals(d_test, model), n_test).mean()

    errors_before, errors_after = [], []
    truth = capture / "ground_truth" / "A0000"
    for camera in rig["cameras"]:
        cid = camera["camera_id"]
        d = _decoded_ratio(capture / "actions" / "A0000", "", camera, corrections[cid])
        normals = read_exr(truth / "normal" / f"{cid}.exr")
        solid = ndimage.binary_erosion(read_exr(truth / "visibility" / f"{cid}.exr") > 0.98, iterations=2)
        errors_before.append(angular_error_deg(d[solid] / np.linalg.norm(d[solid], axis=1, keepdims=True),
                                               normals[solid]))
        errors_after.append(angular_error_deg(correct_normals(d[solid], model), normals[solid]))
    subject_before, subject_after = np.concatenate(errors_before).mean(), np.concatenate(errors_after).mean()
    print(f"\nsimulator (led_error 0.1, no noise): sphere in held-out cameras {sphere_before:.3f} -> "
          f"{sphere_after:.3f} deg; subject unoccluded pixels {subject_before:.3f} -> {subject_after:.3f} deg")
    assert sphere_after < 0.8 * sphere_before
    assert subject_after < subject_before


def test_simulator_chart_colour_correction_matches_truth(calibration_capture):
    from calibration.colour import chart_patch_means, delta_e_2000, fit_colour_matrix, reference_chart_srgb
    from pipeline.codecs.raw import decode_raw

    session = calibration_capture / "sessions" / "S000"
    rig = json.loads((session / "rig.json").read_text())
    chart = json.loads((session / "calibration" / "chart.json").read_text())
    truth = json.loads((calibration_capture / "ground_truth" / "calibration" / "S000.json").read_text())
    _, reference = reference_chart_srgb()
    assert chart["reference_linear_srgb"] == np.round(reference, 6).tolist()
    for camera in rig["cameras"][:4]:
        cid = camera["camera_id"]
        white = np.asarray(camera["white_reference"])
        image = decode_raw(session / chart["cameras"][cid]["frame"]).rgb
        labels = np.zeros(image.shape[:2], np.int64)
        for k, (x0, y0, x1, y1) in enumerate(chart["cameras"][cid]["patch_boxes"]):
            labels[y0:y1, x0:x1] = k + 1
        means, counts = chart_patch_means(image, labels, erode=2)
        assert np.all(counts > 10)
        M = fit_colour_matrix(means, white * reference)
        true = np.asarray(truth["cameras"][cid]["correction"])
        assert np.abs(true - np.eye(3)).max() > 0.01          # there is something to correct
        np.testing.assert_allclose(M, true, atol=0.02)
        before = delta_e_2000(means / white, reference).mean()
        after = delta_e_2000(means @ M.T / white, reference).mean()
        assert after < 0.5 * before and after < 1.0, (before, after)


# --- DiLiGenT ------------------------------------------------------------------------------------------

@needs_diligent
def test_diligent_ball_gradient_ratio_with_light_calibration():
    """Gradient illuminations synthesised from DiLiGenT's 96 real images (light transport is linear):
    the ratio method is strongly biased (lights only in a cone towards the camera); the light model fitted
    on the left half of the ball corrects the right half. Baseline: least-squares photometric stereo."""
    import open3d as o3d
    import scipy.io
    from PIL import Image

    mask = np.asarray(Image.open(DILIGENT / "mask.png"))
    mask = (mask[..., 0] if mask.ndim == 3 else mask) > 0
    rows, cols = np.nonzero(mask)
    y0, y1, x0, x1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    inside = mask[y0:y1, x0:x1]
    names = (DILIGENT / "filenames.txt").read_text().split()
    directions = np.loadtxt(DILIGENT / "light_directions.txt")
    intensities = np.loadtxt(DILIGENT / "light_intensities.txt")
    assert len(names) == len(directions) == len(intensities) == 96
    # open3d reads 16-bit RGB PNGs as uint16 (Pillow would truncate them to 8 bits)
    unit = np.stack([np.asarray(o3d.io.read_image(str(DILIGENT / name)))[y0:y1, x0:x1][inside]
                     for name in names]).astype(np.float64) / intensities[:, None, :]   # (96, P, 3)
    normals_gt = scipy.io.loadmat(DILIGENT / "Normal_gt.mat")["Normal_gt"][y0:y1, x0:x1][inside]

    pos = np.einsum("jpc,jc->pc", unit, (1 + directions) / 2)
    neg = np.einsum("jpc,jc->pc", unit, (1 - directions) / 2)
    white = unit.sum(axis=0)
    np.testing.assert_allclose(pos + neg, white, rtol=1e-9)
    d = (pos - neg) / (pos + neg)
    ratio_normals = d / np.linalg.norm(d, axis=1, keepdims=True)

    # least-squares photometric stereo (grey): I_j = rho * w_j . n
    solution, *_ = np.linalg.lstsq(directions, unit.mean(axis=2), rcond=None)
    ls_normals = (solution / np.linalg.norm(solution, axis=0)).T
    ls_error = angular_error_deg(ls_normals, normals_gt).mean()

    _, cols_in = np.nonzero(inside)
    train = cols_in < cols_in.mean()          # left half of the ball (image x), test on the right half
    test = ~train
    model = fit_light_model(d[train], normals_gt[train], degree=2)
    uncorrected = angular_error_deg(ratio_normals[test], normals_gt[test]).mean()
    corrected = angular_error_deg(correct_normals(d[test], model), normals_gt[test]).mean()
    checker = ((rows - y0) // 16 + (cols - x0) // 16) % 2 == 0   # interleaved 16 px blocks
    model_checker = fit_light_model(d[checker], normals_gt[checker], degree=2)
    checker_corrected = angular_error_deg(correct_normals(d[~checker], model_checker), normals_gt[~checker]).mean()
    print(f"\nDiLiGenT ball ({inside.sum()} px): ratio method {uncorrected:.2f} deg on the right half, "
          f"light-calibrated (fit on the left half) {corrected:.2f} deg, (fit on interleaved blocks) "
          f"{checker_corrected:.2f} deg; least-squares photometric stereo {ls_error:.2f} deg (all pixels)")
    assert 3.5 < ls_error < 5.0
    assert uncorrected > 20.0
    assert corrected < 0.3 * uncorrected and corrected < 10.0
    assert checker_corrected < ls_error


def test_gradient_ratio_hand_computed_and_undefined_pixels():
    from calibration.light import gradient_ratio

    pos = np.array([[[3.0, 1.0, 0.0], [np.inf, 2.0, 1.0]]], np.float32)
    neg = np.array([[[1.0, 1.0, 0.0], [1.0, -2.0, 3.0]]], np.float32)
    d = gradient_ratio(pos, neg)
    assert d.shape == (1, 2, 3) and d.dtype == np.float32
    np.testing.assert_allclose(d[0, 0, :2], [0.5, 0.0])
    assert np.isnan(d[0, 0, 2]) and np.isnan(d[0, 1, 0]) and np.isnan(d[0, 1, 1])  # 0 / 0, inf, pos + neg = 0
    assert d[0, 1, 2] == pytest.approx(-0.5)
    with pytest.raises(ValueError, match="one shape"):
        gradient_ratio(pos, neg[:, :1])
    with pytest.raises(ValueError, match="min_total"):
        gradient_ratio(pos, neg, min_total=-1.0)


def test_gradient_ratio_floor_alpha_and_precision():
    """``min_total`` leaves dim pixels undefined; a fourth channel is ignored; float64 frames are divided in
    float64 (the float32 result is their quotient rounded once)."""
    from calibration.light import gradient_ratio

    pos = np.array([[[3e-4, 0.6, 0.2, 9.0]]])
    neg = np.array([[[1e-4, 0.2, 0.1, 9.0]]])
    d = gradient_ratio(pos, neg, min_total=1e-3)
    assert d.shape == (1, 1, 3) and np.isnan(d[0, 0, 0])
    np.testing.assert_array_equal(d[0, 0, 1:], np.float32([(0.6 - 0.2) / (0.6 + 0.2), (0.2 - 0.1) / (0.2 + 0.1)]))
    assert gradient_ratio(pos, neg)[0, 0, 0] == np.float32(0.5)
