"""Geometric calibration of a fixed camera rig from a frame of surveyed marker balls (known 3D target).

Why: structure from motion on a target at the stage centre (:mod:`calibration.geometric`) cannot separate
a camera's distance from its focal length well enough: with 28-50 mm lenses and a target +-0.45 m deep
seen from ~3 m, a 1 mm move along the optical axis changes the images by < 0.01 px once the focal length
compensates. And aligning any reconstruction to the rig spec's nominal camera centres (mounting tolerance
3 mm per axis) leaves the stage frame itself uncertain by ~1.4 mm even for a perfect reconstruction. A
rigid frame of white balls at surveyed positions (as motion-capture systems calibrate) fixes both: the
balls fill the capture volume, so every camera sees points from ~0.8 m to ~4.6 m away (perspective pins
distance and focal length apart), and their surveyed positions ARE the stage frame (the frame is
registered to the stage), so no alignment to nominal centres is needed.

Per camera (cameras are independent: the 3D points are known):

1. predict the image of every ball with the nominal camera (exact ellipse centre of a sphere's
   silhouette, :func:`sphere_image_centres`) and detect bright blobs (:func:`detect_blobs`:
   intensity-weighted centroids over a morphological background);
2. vote for the common image zoom and shift between predictions and blobs (the nominal orientation error
   moves all balls alike, a focal length error scales them about the principal point), then identify balls (:func:`identify_markers`): mutual nearest blob within a search
   radius, only balls whose images are clear of every other ball's image;
3. fit pose and focal length to the 2D-3D correspondences with pycolmap (LO-RANSAC absolute pose, then
   non-linear refinement with the focal length free; the pixel aspect ratio and principal point stay at
   the rig spec's), the observed centroids corrected from ellipse centre to point projection; repeat
   2-3 with the refined camera and a tight search radius.

Conventions (docs/CONTRACTS.md): OpenCV K with pixel centres at integer coordinates; ``cam_from_world``
(3, 4) ``[R | t]``. Everything here is arrays in, arrays out; decoding frames is the caller's job.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.geometric import (CalibrationResult, CameraCalibration, K_to_colmap, camera_centre,
                                   colmap_params_from_K, rotation_angle_deg, transform_cam_from_world, umeyama)
from pipeline.config import Documented, checked


@dataclass(frozen=True)
class MarkerCalibrationConfig(Documented):
    """Options of :func:`calibrate_markers`."""

    threshold: float = checked(0.2, gt=0.0)
    """Blob detection threshold above the local background, in units of the image (the stage passes
    images scaled so a white surface is ~1: balls are ~0.9, the stage background ~0.03)."""
    background_window_px: int = 21
    """Side of the grey opening that estimates the background under the balls (> the largest ball image)."""
    shift_search_px: float = checked(20.0, gt=0.0)
    """Largest common image shift between nominal predictions and blobs that the first pass looks for
    (nominal orientation error 0.2 deg sigma: ~20 px is 0.5 deg at 320 px with the longest lens)."""
    zoom_search: float = 0.05
    """Largest image zoom about the principal point (nominal focal length or distance error) the first
    pass looks for, in steps of 1%."""
    first_search_px: float = checked(4.0, gt=0.0)
    """Search radius of the first identification, after the common zoom and shift are removed (what is
    left of the nominal camera's errors: roll, parallax, the zoom's 0.5% step)."""
    search_px: float = checked(1.5, gt=0.0)
    """Search radius of the later identifications, from the refined camera."""
    clearance_px: float = 3.0
    """A ball is used only when every other ball's predicted image is further than the two apparent
    radii plus this (no merged blobs, no neighbour inside its centroid window)."""
    first_clearance_px: float = 8.0
    """The same clearance in the first identification (predictions are still a few pixels off)."""
    border_px: float = 2.0
    """Balls whose image comes closer than this to the image border are not used."""
    passes: int = checked(3, ge=1)
    """Identify + fit rounds (the first from the nominal camera)."""
    min_markers: int = checked(12, ge=6)
    """Fewest identified balls for a camera to be calibrated; fewer: the camera is unregistered."""
    ransac_max_error_px: float = 3.0
    """Inlier threshold of the first, RANSAC pose estimate (the nominal focal length may be 1.5% off)."""
    max_residual_px: float = checked(0.6, gt=0.0)
    """Correspondences with a larger reprojection error after a refinement are dropped in the next round."""
    refine_focal_length: bool = True
    """Fit the focal length (pixel aspect kept at the rig spec's); False keeps the nominal focal length."""
    frame: str = checked("target", one_of=("target", "rig"))
    """Gauge: "target": the surveyed ball positions define the stage frame (the frame is registered to the
    stage); "rig": move the calibrated cameras by the rigid transform that best maps their centres onto
    the nominal ones (when the frame's placement in the stage is not known; scale stays the frame's)."""
    max_change_m: float = 0.05
    """A calibrated centre further than this from the nominal one, or ..."""
    max_change_deg: float = 2.0
    """... an orientation further than this, marks a failed calibration: the camera is unregistered."""


def sphere_image_centres(K: np.ndarray, cam_from_world: np.ndarray, centres_world: np.ndarray, radius: float
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image of spheres: centres of their silhouette ellipses (N, 2) pixels, camera depths (N,) of the
    sphere centres and apparent radii (N,) pixels (along the shorter ellipse axis).

    The tangent cone of a sphere at unit direction ``a`` (camera frame) with half-angle ``alpha``
    (``sin alpha = radius / distance``) cuts the plane z = 1 in an ellipse centred at
    ``a_xy a_z / (a_z^2 - sin^2 alpha)``: further out than the projection of the sphere centre,
    ``a_xy / a_z``, by a fraction ~ ``sin^2 alpha`` of it. A uniformly bright ball's centroid is that
    ellipse centre. Spheres behind or around the camera get NaN centres and radius 0.
    """
    K = np.asarray(K, float)
    P = np.asarray(cam_from_world, float)
    X = np.asarray(centres_world, float) @ P[:, :3].T + P[:, 3]
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"centres_world must be (N, 3), got {np.shape(centres_world)}")
    distance = np.linalg.norm(X, axis=1)
    sin2 = (radius / np.maximum(distance, 1e-12)) ** 2
    a = X / np.maximum(distance, 1e-12)[:, None]
    den = a[:, 2] ** 2 - sin2
    ok = (X[:, 2] > radius) & (den > 1e-9)
    w = a[:, :2] * (a[:, 2] / np.where(ok, den, 1.0))[:, None]
    uv = np.where(ok[:, None], w * np.array([K[0, 0], K[1, 1]]) + K[:2, 2], np.nan)
    apparent = np.where(ok, min(K[0, 0], K[1, 1]) * np.sqrt(sin2 / np.maximum(1.0 - sin2, 1e-12)), 0.0)
    return uv, X[:, 2], apparent


def project_points(K: np.ndarray, cam_from_world: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """Pinhole projection (N, 2) pixels of world points (N, 3)."""
    P = np.asarray(cam_from_world, float)
    X = np.asarray(points_world, float) @ P[:, :3].T + P[:, 3]
    z = np.where(np.abs(X[:, 2]) > 1e-12, X[:, 2], 1e-12)
    return X[:, :2] / z[:, None] * np.array([K[0, 0], K[1, 1]]) + np.asarray(K)[:2, 2]


def detect_blobs(image: np.ndarray, threshold: float, background_window_px: int = 21, min_pixels: int = 2
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bright blobs of a grey image (H, W): intensity-weighted centroids (M, 2) as (u, v) pixels (pixel
    centres at integer coordinates), pixel counts (M,) above the threshold and peak heights (M,) above
    the background.

    Background: grey opening with a ``background_window_px`` square (removes anything smaller). Blobs:
    8-connected components of ``image - background > threshold`` with at least ``min_pixels`` pixels.
    Centroids weigh ``max(image - background, 0)`` over each component grown by 2 pixels, so the blob's
    soft (anti-aliased, demosaiced) edge counts symmetrically.
    """
    from scipy import ndimage

    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 2:
        raise ValueError(f"detect_blobs: image must be (H, W), got {image.shape}")
    if threshold <= 0:
        raise ValueError("detect_blobs: threshold must be > 0")
    signal = image - ndimage.grey_opening(image, size=(background_window_px, background_window_px))
    above = signal > threshold
    labels, count = ndimage.label(above, structure=np.ones((3, 3), bool))
    if count == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0)
    pixels = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    grown = ndimage.grey_dilation(labels, size=(5, 5))       # component + 2 px (touching blobs: larger label)
    weight = np.maximum(signal, 0.0).ravel()
    index = grown.ravel()
    v, u = np.divmod(np.arange(image.size), image.shape[1])
    total = np.bincount(index, weights=weight, minlength=count + 1)[1:]
    cu = np.bincount(index, weights=weight * u, minlength=count + 1)[1:]
    cv = np.bincount(index, weights=weight * v, minlength=count + 1)[1:]
    peak = ndimage.maximum(signal, labels, np.arange(1, count + 1))
    keep = (pixels >= min_pixels) & (total > 0)
    centroids = np.stack([cu[keep] / total[keep], cv[keep] / total[keep]], axis=1)
    return centroids, pixels[keep], np.asarray(peak)[keep]


def common_shift(predicted: np.ndarray, blobs: np.ndarray, max_shift_px: float, bin_px: float = 1.0
                 ) -> tuple[np.ndarray, float]:
    """The image shift (2,) that brings most predicted points (N, 2) onto a blob (M, 2), and its vote
    (smoothed count): a vote over every prediction-to-blob difference shorter than ``max_shift_px``
    (histogram with ``bin_px`` bins, 3x3 box-smoothed), refined by the median of the differences within
    ``2 bin_px`` of the winner."""
    from scipy import ndimage

    if len(predicted) == 0 or len(blobs) == 0:
        return np.zeros(2), 0.0
    diff = blobs[None, :, :] - predicted[:, None, :]
    diff = diff[np.einsum("ijk,ijk->ij", diff, diff) < max_shift_px ** 2]
    if len(diff) == 0:
        return np.zeros(2), 0.0
    n = int(np.ceil(max_shift_px / bin_px))
    edges = np.arange(-n, n + 1) * bin_px
    hist, _, _ = np.histogram2d(diff[:, 0], diff[:, 1], bins=(edges, edges))
    hist = ndimage.uniform_filter(hist, size=3, mode="constant")
    i, j = np.unravel_index(np.argmax(hist), hist.shape)
    guess = np.array([edges[i] + 0.5 * bin_px, edges[j] + 0.5 * bin_px])
    near = diff[np.linalg.norm(diff - guess, axis=1) < 2 * bin_px]
    return (np.median(near, axis=0) if len(near) else guess), float(hist[i, j])


def common_zoom_and_shift(predicted: np.ndarray, blobs: np.ndarray, centre: np.ndarray, max_shift_px: float,
                          max_zoom: float, zoom_step: float = 0.01) -> tuple[float, np.ndarray]:
    """(zoom, shift (2,)) with ``centre + zoom (predicted - centre) + shift`` closest to the blobs: the
    :func:`common_shift` vote repeated over zooms ``1 +- k zoom_step`` up to ``max_zoom`` (a nominal focal
    length or distance error scales the image about the principal point), the best-voted kept."""
    best = (-1.0, 1.0, np.zeros(2))
    count = int(np.floor(max_zoom / zoom_step + 1e-9))
    for zoom in 1.0 + zoom_step * np.arange(-count, count + 1):
        shift, votes = common_shift(centre + zoom * (predicted - centre), blobs, max_shift_px)
        if votes > best[0] + 1e-9 or (abs(votes - best[0]) <= 1e-9 and abs(zoom - 1) < abs(best[1] - 1)):
            best = (votes, float(zoom), shift)
    return best[1], best[2]


def identify_markers(predicted: np.ndarray, apparent_px: np.ndarray, usable: np.ndarray, blobs: np.ndarray,
                     search_px: float, clearance_px: float) -> np.ndarray:
    """Blob index (N,) of each ball, -1 where none: mutual nearest neighbours between predicted ball images
    (N, 2) and blob centroids (M, 2) within ``search_px``, for balls marked ``usable`` (N,) whose predicted
    image is clear of every other ball's (centre distance > both apparent radii (N,) + ``clearance_px``)."""
    from scipy.spatial import cKDTree

    n = len(predicted)
    out = np.full(n, -1, np.int64)
    finite = np.all(np.isfinite(predicted), axis=1)
    if len(blobs) == 0 or not finite.any():
        return out
    ids = np.nonzero(finite)[0]
    pts = predicted[ids]
    tree = cKDTree(pts)
    reach = 2.0 * float(apparent_px[ids].max()) + clearance_px
    clear = np.ones(len(ids), bool)
    for a, b in tree.query_pairs(reach, output_type="ndarray"):
        if np.linalg.norm(pts[a] - pts[b]) <= apparent_px[ids[a]] + apparent_px[ids[b]] + clearance_px:
            clear[a] = clear[b] = False
    candidates = ids[clear & usable[ids]]
    if len(candidates) == 0:
        return out
    blob_tree = cKDTree(blobs)
    dist, nearest = blob_tree.query(predicted[candidates], distance_upper_bound=search_px)
    hit = np.isfinite(dist)
    # mutual: the blob's nearest prediction (among all finite balls) is this ball
    back_dist, back = tree.query(blobs[nearest[hit]])
    mutual = ids[back] == candidates[hit]
    out[candidates[hit][mutual]] = nearest[hit][mutual]
    return out


RANSAC_SEED = 0
"""The seed COLMAP's random generator is set to before each camera's RANSAC (:func:`_fit_camera`), so a camera's
calibration is a function of its own image alone, not of the fits that ran before it in the process."""


def _fit_camera(uv: np.ndarray, xyz: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray | None,
                size: tuple[int, int], config: MarkerCalibrationConfig, ransac: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Pose and focal length from 2D (N, 2) - 3D (N, 3) correspondences with pycolmap. The camera is
    SIMPLE_PINHOLE on rows rescaled by fx / fy (square pixels), principal point fixed. Returns (K (3, 3),
    cam_from_world (3, 4), inlier mask (N,)) or None."""
    import pycolmap

    K = np.asarray(K, float)
    aspect = K[1, 1] / K[0, 0]
    width, height = size
    Kc = K_to_colmap(K)
    square = np.column_stack([uv[:, 0], K[1, 2] + (uv[:, 1] - K[1, 2]) / aspect]) + 0.5   # COLMAP: +0.5 px
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=int(width), height=int(height),
                             params=[Kc[0, 0], Kc[0, 2], Kc[1, 2]])
    refine = pycolmap.AbsolutePoseRefinementOptions()
    refine.refine_focal_length = config.refine_focal_length
    refine.gradient_tolerance = 1e-12
    refine.max_num_iterations = 200
    refine.loss_function_scale = 1.0
    if ransac or cam_from_world is None:
        estimate = pycolmap.AbsolutePoseEstimationOptions()
        estimate.ransac.max_error = config.ransac_max_error_px
        estimate.ransac.min_inlier_ratio = 0.25
        # COLMAP's RANSAC draws from a generator that lives as long as the process: unseeded, a camera's pose would
        # depend on how many fits ran before it in this process (1e-12 apart, which the SDF's training grows)
        pycolmap.set_random_seed(RANSAC_SEED)
        found = pycolmap.estimate_and_refine_absolute_pose(square, xyz, camera, estimate, refine)
        if found is None:
            return None
        pose, inliers = found["cam_from_world"], np.asarray(found["inlier_mask"], bool).ravel()
        # RANSAC classified inliers with the nominal focal length: refine once more on all that now fit
        P = np.asarray(pose.matrix(), float)
    else:
        P = np.asarray(cam_from_world, float)
        inliers = np.ones(len(uv), bool)
    for _ in range(2):
        result = pycolmap.refine_absolute_pose(pycolmap.Rigid3d(pycolmap.Rotation3d(P[:, :3]), P[:, 3].copy()),
                                               square, xyz, inliers, camera, refine)
        if result is None:
            return None
        P = np.asarray(result["cam_from_world"].matrix(), float)
        f = float(camera.params[0])
        K_new = np.array([[f, 0.0, K[0, 2]], [0.0, f * aspect, K[1, 2]], [0.0, 0.0, 1.0]])
        residual = np.linalg.norm(project_points(K_new, P, xyz) - uv, axis=1)
        new = residual < config.max_residual_px * (4.0 if ransac else 1.0)
        if new.sum() < config.min_markers or np.array_equal(new, inliers):
            break
        inliers = new
    return K_new, P, inliers


def calibrate_camera_markers(image: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray,
                             markers_world: np.ndarray, radius_m: float,
                             config: MarkerCalibrationConfig = MarkerCalibrationConfig()) -> dict[str, Any]:
    """Calibrate one camera from its image of the marker frame.

    image: (H, W) grey, white ~1. K (3, 3), cam_from_world (3, 4): the nominal camera. markers_world (M, 3):
    surveyed ball centres (stage frame, metres); radius_m: ball radius. Returns a dict: ``K``,
    ``cam_from_world`` (None when it failed), ``observations`` (n, 2) ellipse-corrected centroids,
    ``marker_ids`` (n,), ``residuals_px`` (n,), ``reason`` (why it failed, else ""), ``n_blobs``.
    """
    image = np.asarray(image)
    markers_world = np.asarray(markers_world, float)
    if markers_world.ndim != 2 or markers_world.shape[1] != 3:
        raise ValueError(f"markers_world must be (M, 3), got {markers_world.shape}")
    H, W = image.shape[:2]
    blobs, _, _ = detect_blobs(image, config.threshold, config.background_window_px)
    K_cur, P_cur = np.asarray(K, float), np.asarray(cam_from_world, float)[:3, :4]
    out: dict[str, Any] = {"K": K_cur, "cam_from_world": None, "observations": np.zeros((0, 2)),
                           "marker_ids": np.zeros(0, np.int64), "residuals_px": np.zeros(0), "reason": "",
                           "n_blobs": len(blobs)}
    if len(blobs) < config.min_markers:
        out["reason"] = f"only {len(blobs)} bright blobs in the marker frame"
        return out
    for round_ in range(config.passes):
        centre_uv, depth, apparent = sphere_image_centres(K_cur, P_cur, markers_world, radius_m)
        margin = apparent + config.border_px
        usable = np.all(np.isfinite(centre_uv), axis=1) & (depth > 0)
        usable &= (centre_uv[:, 0] >= margin) & (centre_uv[:, 0] <= W - 1 - margin)
        usable &= (centre_uv[:, 1] >= margin) & (centre_uv[:, 1] <= H - 1 - margin)
        if round_ == 0:
            zoom, shift = common_zoom_and_shift(centre_uv[usable], blobs, K_cur[:2, 2], config.shift_search_px,
                                                config.zoom_search)
            match = identify_markers(K_cur[:2, 2] + zoom * (centre_uv - K_cur[:2, 2]) + shift, apparent, usable,
                                     blobs, config.first_search_px, config.first_clearance_px)
        else:
            match = identify_markers(centre_uv, apparent, usable, blobs, config.search_px, config.clearance_px)
        ids = np.nonzero(match >= 0)[0]
        if len(ids) < config.min_markers:
            out["reason"] = f"only {len(ids)} balls identified (pass {round_ + 1})"
            return out
        # centroid = ellipse centre; the pinhole model wants the projection of the ball centre
        shift_to_point = project_points(K_cur, P_cur, markers_world[ids]) - centre_uv[ids]
        uv = blobs[match[ids]] + shift_to_point
        fitted = _fit_camera(uv, markers_world[ids], K_cur, P_cur, (W, H), config, ransac=round_ == 0)
        if fitted is None:
            out["reason"] = f"pose estimation failed (pass {round_ + 1}, {len(ids)} balls)"
            return out
        K_cur, P_cur, inliers = fitted
        if inliers.sum() < config.min_markers:
            out["reason"] = f"only {int(inliers.sum())} consistent balls (pass {round_ + 1})"
            return out
    # final observations with the final camera's ellipse correction
    centre_uv, _, _ = sphere_image_centres(K_cur, P_cur, markers_world[ids], radius_m)
    uv = blobs[match[ids]] + project_points(K_cur, P_cur, markers_world[ids]) - centre_uv
    residual = np.linalg.norm(project_points(K_cur, P_cur, markers_world[ids]) - uv, axis=1)
    keep = inliers
    out.update(K=K_cur, cam_from_world=P_cur, observations=uv[keep], marker_ids=ids[keep], residuals_px=residual[keep])
    return out


def centre_std_mm(K: np.ndarray, cam_from_world: np.ndarray, points_world: np.ndarray, sigma_px: float,
                  refine_focal_length: bool = True) -> float:
    """Predicted standard deviation (mm, 3D rms) of a camera centre fitted to ``points_world`` (N, 3)
    observed with ``sigma_px`` noise per image coordinate (Cramer-Rao bound, pose + focal length)."""
    from scipy.spatial.transform import Rotation

    P = np.asarray(cam_from_world, float)
    R0, C = P[:, :3], camera_centre(P)

    def proj(p: np.ndarray) -> np.ndarray:
        R = Rotation.from_rotvec(p[:3]).as_matrix() @ R0
        Kp = np.array(K, float)
        Kp[0, 0] *= 1 + p[6]
        Kp[1, 1] *= 1 + p[6]
        return project_points(Kp, np.column_stack([R, -R @ p[3:6]]), points_world).ravel()

    p0 = np.r_[np.zeros(3), C, 0.0]
    n = 7 if refine_focal_length else 6
    J = np.empty((2 * len(points_world), n))
    for i in range(n):
        step = np.zeros(7)
        step[i] = 1e-6
        J[:, i] = (proj(p0 + step) - proj(p0 - step)) / 2e-6
    cov = sigma_px ** 2 * np.linalg.pinv(J.T @ J)
    return float(np.sqrt(np.trace(cov[3:6, 3:6])) * 1000.0)


def calibrate_markers(images: dict[str, np.ndarray], nominal_K: dict[str, np.ndarray],
                      nominal_cam_from_world: dict[str, np.ndarray], markers_world: np.ndarray, radius_m: float,
                      config: MarkerCalibrationConfig = MarkerCalibrationConfig()) -> CalibrationResult:
    """Calibrate every camera of a fixed rig from its image of the surveyed marker frame.

    images: name -> (H, W) grey image (white ~1) of the marker frame; nominal_K / nominal_cam_from_world:
    name -> the rig spec's (3, 3) K and (3, 4) pose, for every image; markers_world (M, 3) surveyed ball
    centres in the stage frame (metres), radius_m their radius.

    Returns a :class:`calibration.geometric.CalibrationResult` in the stage frame (``aligned`` True):
    ``cameras`` (PINHOLE K, zero distortion), ``unregistered`` (too few balls identified, failed fit, or a
    result beyond ``max_change_m`` / ``max_change_deg`` of the nominal camera; reasons in ``notes``),
    ``reprojection_error_px`` (mean over all used observations), ``alignment_residual_mm`` (mean, max
    distance between calibrated and nominal centres: the mounting offsets found), ``n_points3d`` (balls
    seen by at least one camera) and ``reconstruction`` (a pycolmap.Reconstruction: cameras, the balls as
    3D points with their observations). Raises ValueError on missing nominal cameras.
    """
    t_start = time.perf_counter()
    markers_world = np.asarray(markers_world, float)
    missing = [n for n in images if n not in nominal_K or n not in nominal_cam_from_world]
    if missing:
        raise ValueError(f"calibrate_markers: no nominal camera for {missing[:5]}")
    if markers_world.ndim != 2 or markers_world.shape[1] != 3 or len(markers_world) < config.min_markers:
        raise ValueError(f"markers_world must be (M >= {config.min_markers}, 3), got {markers_world.shape}")
    per_camera: dict[str, dict[str, Any]] = {}
    notes: list[str] = []
    for name in sorted(images):
        fit = calibrate_camera_markers(images[name], nominal_K[name], nominal_cam_from_world[name], markers_world,
                                       radius_m, config)
        if fit["cam_from_world"] is not None:
            N = np.asarray(nominal_cam_from_world[name], float)[:3, :4]
            shift = float(np.linalg.norm(camera_centre(fit["cam_from_world"]) - camera_centre(N)))
            angle = rotation_angle_deg(fit["cam_from_world"][:, :3] @ N[:, :3].T)
            if shift > config.max_change_m or angle > config.max_change_deg:
                fit["reason"] = f"calibrated camera {1000 * shift:.0f} mm / {angle:.2f} deg from the nominal one"
                fit["cam_from_world"] = None
        if fit["cam_from_world"] is None:
            notes.append(f"{name}: {fit['reason']}")
        per_camera[name] = fit
    good = {n: f for n, f in per_camera.items() if f["cam_from_world"] is not None}
    timings = {"cameras": time.perf_counter() - t_start}
    if config.frame == "rig" and len(good) >= 3:
        src = np.array([camera_centre(f["cam_from_world"]) for f in good.values()])
        dst = np.array([camera_centre(nominal_cam_from_world[n]) for n in good])
        _, R, t = umeyama(src, dst, with_scale=False)
        for f in good.values():
            f["cam_from_world"] = transform_cam_from_world(f["cam_from_world"], 1.0, R, t)
        notes.append("cameras moved rigidly onto the nominal centres (frame 'rig')")
    cameras: dict[str, CameraCalibration] = {}
    offsets = []
    for name, f in good.items():
        H, W = np.asarray(images[name]).shape[:2]
        cameras[name] = CameraCalibration(K=f["K"], dist=np.zeros(5), cam_from_world=f["cam_from_world"], width=W,
                                          height=H)
        offsets.append(np.linalg.norm(camera_centre(f["cam_from_world"])
                                      - camera_centre(nominal_cam_from_world[name])) * 1000.0)
    residuals = np.concatenate([f["residuals_px"] for f in good.values()]) if good else np.zeros(0)
    seen = np.unique(np.concatenate([f["marker_ids"] for f in good.values()])) if good else np.zeros(0, np.int64)
    rec = _reconstruction(good, cameras, markers_world) if good else None
    timings["total"] = time.perf_counter() - t_start
    if good:
        counts = [len(f["marker_ids"]) for f in good.values()]
        # what limits the result: the centre precision each camera's observations allow (Cramer-Rao, at
        # that camera's residual rms per image coordinate)
        stds = [centre_std_mm(f["K"], f["cam_from_world"], markers_world[f["marker_ids"]],
                              float(np.sqrt(np.sum(f["residuals_px"] ** 2) / max(2 * len(f["residuals_px"]) - 7, 1))),
                              config.refine_focal_length) for f in good.values()]
        notes.append(f"balls used per camera: {min(counts)}-{max(counts)} (median {int(np.median(counts))}); "
                     f"reprojection rms {float(np.sqrt(np.mean(residuals ** 2))):.3f} px; predicted centre std "
                     f"{float(np.median(stds)):.2f} mm median, {float(np.max(stds)):.2f} mm worst")
    return CalibrationResult(
        cameras=dict(sorted(cameras.items())), unregistered=sorted(n for n in images if n not in cameras),
        reprojection_error_px=float(residuals.mean()) if len(residuals) else 0.0,
        alignment_residual_mm=(float(np.mean(offsets)), float(np.max(offsets))) if offsets else None,
        n_points3d=int(len(seen)), timings=timings, aligned=bool(cameras), alignment_outliers=[], notes=notes,
        reconstruction=rec)


def _reconstruction(fits: dict[str, dict[str, Any]], cameras: dict[str, CameraCalibration],
                    markers_world: np.ndarray) -> Any:
    """pycolmap.Reconstruction of the calibrated cameras with the balls as 3D points (COLMAP convention)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    tracks: dict[int, list[tuple[int, int]]] = {}
    for image_id, (name, fit) in enumerate(sorted(fits.items()), start=1):
        cal = cameras[name]
        camera = pycolmap.Camera(model="PINHOLE", width=cal.width, height=cal.height,
                                 params=colmap_params_from_K("PINHOLE", cal.K), camera_id=image_id)
        rec.add_camera_with_trivial_rig(camera)
        image = pycolmap.Image(name=name, keypoints=np.asarray(fit["observations"], float) + 0.5,
                               camera_id=image_id, image_id=image_id)
        P = cal.cam_from_world
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(P[:, :3]), P[:, 3].copy()))
        for k, marker in enumerate(fit["marker_ids"]):
            tracks.setdefault(int(marker), []).append((image_id, k))
    for marker, elements in sorted(tracks.items()):
        track = pycolmap.Track()
        for image_id, k in elements:
            track.add_element(image_id, k)
        rec.add_point3D(markers_world[marker], track)
    rec.update_point_3d_errors()
    return rec
