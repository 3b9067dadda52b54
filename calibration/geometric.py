"""Geometric camera calibration: structure from motion with pycolmap, similarity alignment, pose errors.

Conventions (docs/CONTRACTS.md): OpenCV cameras (x right, y down, z forward), ``cam_from_world`` is a
3x4 ``[R | t]`` with ``x_cam = R @ x_world + t``, ``K`` is 3x3 with the centre of pixel ``i`` at
continuous coordinate ``u = i``. COLMAP puts the centre of pixel ``i`` at ``i + 0.5``; every K that
enters or leaves COLMAP is shifted by half a pixel here (:func:`K_from_colmap`, :func:`K_to_colmap`).

Images are named by their file name (``image_paths[i].name``); names must be unique.

Main entry points:

- :func:`calibrate_images`: SIFT features, exhaustive (or sequential) matching, incremental mapping with
  intrinsics priors, retries for unregistered images, optional alignment to known camera centres.
- :func:`calibrate_folder`: the same on a folder of photos, writing transforms.json, a COLMAP text model
  and an OpenCV intrinsics JSON.
- :func:`pose_errors`, :func:`umeyama`, :func:`umeyama_ransac`: evaluation against ground truth.
- :func:`calibrate_rig` (:class:`RigRefineConfig`): refine a fixed rig's nominal cameras (pose-guided
  matching, triangulation at the nominal poses, bundle adjustment with pose priors, gauge from the nominal
  centres) instead of incremental mapping. Experimental: see its docstring for the measured status.

On a fixed light stage with a rig spec, :mod:`calibration.markers` (a surveyed frame of balls filling the
capture volume) is what reaches sub-millimetre cameras; structure from motion here cannot, for two
measured reasons (simulated stage, 320 px): (1) a target at the stage centre (+-0.45 m deep, ~3 m away,
28-50 mm lenses) leaves each camera's distance and focal length nearly interchangeable: with ~1000
features at 0.2 px the Cramer-Rao bound on a camera centre is ~2.3 mm even with PERFECT 3D points;
(2) aligning a reconstruction to the nominal camera centres (3 mm per axis off) puts even the TRUE
cameras 1.46 mm (mean) from where they are (``bench/bench_calibration.py --markers``,
``floor_nominal_gauge``).
"""
from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.config import Documented, broken, checked

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".ppm", ".pgm")
RAW_SUFFIXES = (".dng", ".nef", ".cr2", ".cr3", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw", ".raw")
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclass(frozen=True)
class GeometricConfig(Documented):
    """Options of :func:`calibrate_images`."""

    max_image_size: int = 1600
    """Longest image side (pixels) at which SIFT features are extracted; larger images are downscaled
    for extraction (keypoints are reported in full-resolution pixels). -1: full resolution."""
    max_num_features: int = checked(8192, ge=64)
    """Maximum SIFT features per image."""
    peak_threshold: float = 0.0066666
    """SIFT difference-of-Gaussian peak threshold (COLMAP default 0.02/3); lower finds more features on
    weakly textured images."""
    first_octave: int = -1
    """SIFT first octave: -1 upsamples the image once (finer features on small images), 0 does not."""
    domain_size_pooling: bool = False
    """DSP-SIFT descriptors (pooled over scales): more and better matches on wide baselines, slower."""
    estimate_affine_shape: bool = False
    """Affine-adapted SIFT keypoints (more robust to oblique views, slower)."""
    camera_model: str = checked("SIMPLE_RADIAL", one_of=CAMERA_MODELS)
    """COLMAP camera model: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV. Exported as OpenCV
    K and a 5-vector dist (k1 k2 p1 p2 k3)."""
    shared_camera: bool = False
    """One camera (intrinsics) for all images instead of one per image."""
    refine_focal_length: bool = True
    """Refine focal lengths in bundle adjustment. With an intrinsics prior, False keeps the prior."""
    refine_principal_point: bool = False
    """Refine principal points in bundle adjustment (poorly constrained; off by default)."""
    refine_extra_params: bool = True
    """Refine distortion parameters in bundle adjustment."""
    matcher: str = checked("auto", one_of=("auto", "exhaustive", "sequential"))
    """"exhaustive", "sequential" (loop closure on, for an ordered ring) or "auto": exhaustive up to
    ``exhaustive_max_images`` images, sequential above."""
    exhaustive_max_images: int = 64
    """Image count up to which "auto" matching is exhaustive."""
    sequential_overlap: int = 10
    """Neighbours matched on each side by sequential matching."""
    guided_matching: bool = False
    """Second, epipolar-guided matching pass per pair (more inliers, slower)."""
    min_num_matches: int = checked(15, ge=4)
    """Minimum verified matches for an image pair to be used by the mapper."""
    retry_unregistered: bool = True
    """When images stay unregistered, continue the largest model with relaxed registration thresholds."""
    relaxed_min_num_inliers: int = 12
    """Absolute-pose inlier minimum used by the relaxed retry (COLMAP default 30)."""
    ba_function_tolerance: float = 1e-8
    """Relative cost decrease at which the final global bundle adjustment stops."""
    final_ba_iterations: int = 200
    """Iterations of each final global bundle adjustment round run after all registrations (0: none)."""
    final_ba_rounds: int = 2
    """Rounds of (retriangulate when ``final_retriangulate``, bundle adjust, drop observations with
    reprojection error above ``final_filter_max_error_px``) after mapping."""
    final_ba_loss: str = "cauchy"
    """Robust loss of the final bundle adjustment: "cauchy" (scale 1 px) or "trivial" (least squares)."""
    final_filter_max_error_px: float = 2.0
    """Observations with a larger reprojection error are dropped between final BA rounds."""
    final_retriangulate: bool = False
    """Re-triangulate all matches with the registered poses before the final bundle adjustment."""
    alignment_max_error: float = checked(0.05, gt=0.0)
    """RANSAC inlier threshold (units of ``known_centres``, metres on the stage) of the similarity
    alignment of reconstructed to known camera centres."""
    num_threads: int = -1
    """Threads for extraction, matching and mapping (-1: all cores). Only 1 gives the same cameras on every run:
    ``calibrate_rig`` run three times in one process on a simulated 12-camera stage at 256 px gave the same
    poses to the bit with 1 thread, and pose entries up to 4e-3 apart with 2 (seeded either way)."""
    seed: int = 0
    """Random seed of COLMAP's RANSAC and mapper (results can still vary with thread scheduling)."""
    verbose: bool = False
    """Let COLMAP log to stderr."""

    def _checks(self) -> list[str]:
        if self.max_image_size != -1 and not self.max_image_size >= 64:
            return [broken(self, "max_image_size", "must be -1 or >= 64")]
        return []


@dataclass
class CameraCalibration:
    """One registered image: OpenCV intrinsics and pose."""

    K: np.ndarray
    """(3, 3) OpenCV intrinsics (pixel centres at integer coordinates)."""
    dist: np.ndarray
    """(5,) OpenCV distortion k1 k2 p1 p2 k3."""
    cam_from_world: np.ndarray
    """(3, 4) [R | t], in the aligned frame when known centres were given."""
    width: int
    height: int

    @property
    def centre_world(self) -> np.ndarray:
        """(3,) camera centre ``-R^T t``."""
        return camera_centre(self.cam_from_world)


@dataclass
class CalibrationResult:
    """What :func:`calibrate_images` found."""

    cameras: dict[str, CameraCalibration]
    """Registered images by name."""
    unregistered: list[str]
    """Names of the images not in the kept model (no features, no matches or failed registration)."""
    reprojection_error_px: float
    """Mean reprojection error over all observations of the kept model, pixels."""
    alignment_residual_mm: tuple[float, float] | None
    """(mean, max) distance between aligned and known camera centres over the RANSAC inliers, in
    thousandths of the known centres' unit (mm for metres); None without known centres or when the
    alignment failed."""
    n_points3d: int
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per step: extract, match, map, retry, ba, align."""
    aligned: bool = False
    """True when the poses are in the frame of ``known_centres``."""
    alignment_outliers: list[str] = field(default_factory=list)
    """Images whose centre was a RANSAC outlier of the alignment."""
    notes: list[str] = field(default_factory=list)
    """Human-readable remarks (retries, models found, alignment problems)."""
    reconstruction: Any = field(default=None, repr=False, compare=False)
    """The pycolmap.Reconstruction (in the aligned frame), or None."""

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary without per-camera arrays."""
        return {"registered": sorted(self.cameras), "unregistered": list(self.unregistered),
                "reprojection_error_px": self.reprojection_error_px,
                "alignment_residual_mm": list(self.alignment_residual_mm) if self.alignment_residual_mm else None,
                "aligned": self.aligned, "alignment_outliers": list(self.alignment_outliers),
                "n_points3d": self.n_points3d, "timings": dict(self.timings), "notes": list(self.notes)}


# ----------------------------------------------------------------------------------------------------------
# Small geometry helpers


def camera_centre(cam_from_world: np.ndarray) -> np.ndarray:
    """(3, 4) [R | t] -> (3,) centre ``-R^T t``."""
    P = np.asarray(cam_from_world, dtype=float)
    return -P[:3, :3].T @ P[:3, 3]


def world_from_cam_4x4(cam_from_world: np.ndarray) -> np.ndarray:
    """(3, 4) cam_from_world -> (4, 4) world_from_cam."""
    P = np.asarray(cam_from_world, dtype=float)
    out = np.eye(4)
    out[:3, :3] = P[:3, :3].T
    out[:3, 3] = camera_centre(P)
    return out


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle (degrees) of a (3, 3) rotation matrix."""
    c = (np.trace(R) - 1.0) / 2.0
    # arccos is ill-conditioned near 0; use atan2 of the sine (norm of the skew part) and cosine
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return float(np.degrees(np.arctan2(s, c)))


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s * R @ src + t`` (Umeyama 1991).

    src, dst: (N, 3), N >= 3 (not collinear). Returns (s, R (3, 3), t (3,)).
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError(f"umeyama needs two (N>=3, 3) arrays, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def umeyama_ransac(src: np.ndarray, dst: np.ndarray, max_error: float, with_scale: bool = True,
                   iterations: int = 500, seed: int = 0) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Robust similarity ``dst ~ s R src + t``: RANSAC over 3-point samples, refit on the inliers.

    src, dst: (N, 3). max_error: inlier distance in dst units. Returns (s, R, t, inliers (N,) bool).
    With fewer than 4 points this is plain :func:`umeyama` (all points inliers).
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    n = len(src)
    if n < 4:
        s, R, t = umeyama(src, dst, with_scale)
        return s, R, t, np.ones(n, bool)
    rng = np.random.default_rng(seed)
    best = np.zeros(n, bool)
    best_err = np.inf
    for _ in range(iterations):
        idx = rng.choice(n, 3, replace=False)
        try:
            s, R, t = umeyama(src[idx], dst[idx], with_scale)
        except np.linalg.LinAlgError:
            continue
        if not np.isfinite(s) or s <= 0:
            continue
        err = np.linalg.norm(s * src @ R.T + t - dst, axis=1)
        inl = err < max_error
        score = np.minimum(err, max_error).sum()
        if inl.sum() > best.sum() or (inl.sum() == best.sum() and score < best_err):
            best, best_err = inl, score
    if best.sum() < 3:
        best = np.ones(n, bool)
    for _ in range(3):  # refit on inliers, re-classify
        s, R, t = umeyama(src[best], dst[best], with_scale)
        err = np.linalg.norm(s * src @ R.T + t - dst, axis=1)
        new = err < max_error
        if new.sum() < 3 or np.array_equal(new, best):
            break
        best = new
    return s, R, t, best


def transform_cam_from_world(cam_from_world: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Express a (3, 4) cam_from_world in the new world ``x_new = s R x_old + t``. Returns (3, 4)."""
    P = np.asarray(cam_from_world, dtype=float)
    R_new = P[:3, :3] @ R.T
    c_new = s * R @ camera_centre(P) + t
    return np.hstack([R_new, (-R_new @ c_new)[:, None]])


def pose_errors(estimated: dict[str, np.ndarray], truth: dict[str, np.ndarray], align: bool = True,
                robust_max_error: float | None = None) -> dict[str, Any]:
    """Per-camera rotation and centre errors of estimated against true poses.

    estimated, truth: name -> (3, 4) cam_from_world. Only names in both are compared (at least 3 when
    ``align``). With ``align`` the estimated centres are first mapped onto the true ones by a least-squares
    similarity (Umeyama; with ``robust_max_error`` a RANSAC one whose inliers are refit), which also
    rotates the estimated orientations. Returns::

        {"names": [...], "rotation_deg": {name: float}, "centre_error": {name: float} (input units),
         "centre_error_mm": {name: float} (input units * 1000, i.e. mm for metres),
         "rotation_deg_mean", "rotation_deg_max", "centre_error_mm_mean", "centre_error_mm_max",
         "centre_error_mm_median", "similarity": {"scale", "R", "t"} or None, "missing": [names in truth only]}
    """
    names = sorted(set(estimated) & set(truth))
    missing = sorted(set(truth) - set(estimated))
    if not names:
        raise ValueError("pose_errors: no camera names in common")
    est = {n: np.asarray(estimated[n], dtype=float)[:3, :4] for n in names}
    tru = {n: np.asarray(truth[n], dtype=float)[:3, :4] for n in names}
    sim = None
    if align:
        if len(names) < 3:
            raise ValueError("pose_errors: alignment needs at least 3 common cameras")
        src = np.array([camera_centre(est[n]) for n in names])
        dst = np.array([camera_centre(tru[n]) for n in names])
        if robust_max_error is None:
            s, R, t = umeyama(src, dst)
        else:
            s, R, t, _ = umeyama_ransac(src, dst, robust_max_error)
        est = {n: transform_cam_from_world(est[n], s, R, t) for n in names}
        sim = {"scale": s, "R": R.tolist(), "t": t.tolist()}
    rot = {n: rotation_angle_deg(est[n][:, :3] @ tru[n][:, :3].T) for n in names}
    cen = {n: float(np.linalg.norm(camera_centre(est[n]) - camera_centre(tru[n]))) for n in names}
    r, c = np.array(list(rot.values())), np.array(list(cen.values())) * 1000.0
    return {"names": names, "rotation_deg": rot, "centre_error": cen,
            "centre_error_mm": {n: v * 1000.0 for n, v in cen.items()},
            "rotation_deg_mean": float(r.mean()), "rotation_deg_max": float(r.max()),
            "centre_error_mm_mean": float(c.mean()), "centre_error_mm_max": float(c.max()),
            "centre_error_mm_median": float(np.median(c)), "similarity": sim, "missing": missing}


# ----------------------------------------------------------------------------------------------------------
# COLMAP <-> OpenCV cameras


def K_to_colmap(K: np.ndarray) -> np.ndarray:
    """OpenCV (3, 3) K -> COLMAP convention (principal point + 0.5 px)."""
    K = np.array(K, dtype=float)
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    return K


def K_from_colmap(K: np.ndarray) -> np.ndarray:
    """COLMAP (3, 3) K -> OpenCV convention (principal point - 0.5 px)."""
    K = np.array(K, dtype=float)
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    return K


def colmap_params_from_K(model: str, K: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """COLMAP parameter vector of ``model`` from an OpenCV K (3, 3) and optional dist (5,)."""
    Kc = K_to_colmap(K)
    fx, fy, cx, cy = Kc[0, 0], Kc[1, 1], Kc[0, 2], Kc[1, 2]
    f = 0.5 * (fx + fy)
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).ravel()
    if model == "SIMPLE_PINHOLE":
        return np.array([f, cx, cy])
    if model == "PINHOLE":
        return np.array([fx, fy, cx, cy])
    if model == "SIMPLE_RADIAL":
        return np.array([f, cx, cy, d[0]])
    if model == "RADIAL":
        return np.array([f, cx, cy, d[0], d[1]])
    if model == "OPENCV":
        return np.array([fx, fy, cx, cy, d[0], d[1], d[2], d[3]])
    raise ValueError(f"unsupported camera model {model}")


def opencv_from_colmap_camera(camera: Any) -> tuple[np.ndarray, np.ndarray]:
    """pycolmap.Camera -> (K (3, 3) OpenCV convention, dist (5,) k1 k2 p1 p2 k3)."""
    model = camera.model.name if hasattr(camera.model, "name") else str(camera.model)
    p = np.asarray(camera.params, dtype=float)
    dist = np.zeros(5)
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]; cx, cy = p[1], p[2]  # noqa: E702
    elif model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]; cx, cy = p[1], p[2]; dist[0] = p[3]  # noqa: E702
    elif model == "RADIAL":
        fx = fy = p[0]; cx, cy = p[1], p[2]; dist[0:2] = p[3:5]  # noqa: E702
    elif model in ("OPENCV", "FULL_OPENCV"):
        fx, fy, cx, cy = p[:4]
        dist[:4] = p[4:8]
        if model == "FULL_OPENCV":
            dist[4] = p[8]
    else:
        raise ValueError(f"camera model {model} has no OpenCV equivalent here")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return K_from_colmap(K), dist


# ----------------------------------------------------------------------------------------------------------
# Calibration


def _stage_images(image_paths: list[Path], image_dir: Path) -> dict[str, str]:
    """Link (or, for raw files, decode) the images into ``image_dir``. Returns name -> COLMAP image name."""
    image_dir.mkdir(parents=True, exist_ok=True)
    names: dict[str, str] = {}
    for path in image_paths:
        path = Path(path)
        if path.name in names:
            raise ValueError(f"duplicate image name {path.name!r}: image names must be unique")
        suffix = path.suffix.lower()
        if suffix in RAW_SUFFIXES:
            colmap_name = path.stem + ".png"
            target = image_dir / colmap_name
            if not target.exists():
                from pipeline.codecs.image import preview_linear, write_png
                from pipeline.codecs.raw import decode_raw

                write_png(target, preview_linear(decode_raw(path).rgb))
        elif suffix in IMAGE_SUFFIXES:
            colmap_name = path.name
            target = image_dir / colmap_name
            if target.is_symlink() or target.exists():
                target.unlink()
            try:
                os.symlink(path.resolve(), target)
            except OSError:
                shutil.copyfile(path, target)
        else:
            raise ValueError(f"{path}: unsupported image type {path.suffix!r}")
        if colmap_name in names.values():
            raise ValueError(f"{path}: two images map to {colmap_name!r}")
        names[path.name] = colmap_name
    return names


def _extraction_options(config: GeometricConfig, scale_features: float = 1.0) -> Any:
    import pycolmap

    opts = pycolmap.FeatureExtractionOptions()
    opts.max_image_size = config.max_image_size
    opts.num_threads = config.num_threads
    opts.use_gpu = False
    opts.sift.max_num_features = int(config.max_num_features * scale_features)
    opts.sift.peak_threshold = config.peak_threshold
    opts.sift.first_octave = config.first_octave
    opts.sift.domain_size_pooling = config.domain_size_pooling
    opts.sift.estimate_affine_shape = config.estimate_affine_shape
    return opts


def _set_priors(database_path: Path, colmap_names: dict[str, str], config: GeometricConfig,
                intrinsics_prior: dict[str, np.ndarray] | None, dist_prior: dict[str, np.ndarray] | None) -> None:
    """Write the prior K (and dist) of each image into its database camera; mark the focal as a prior."""
    import pycolmap

    if not intrinsics_prior:
        return
    db = pycolmap.Database.open(str(database_path))
    try:
        by_colmap = {v: k for k, v in colmap_names.items()}
        images = db.read_all_images()
        per_camera: dict[int, list[str]] = {}
        for image in images:
            name = by_colmap.get(image.name)
            if name is not None and name in intrinsics_prior:
                per_camera.setdefault(image.camera_id, []).append(name)
        for camera_id, names in per_camera.items():
            camera = db.read_camera(camera_id)
            K = np.mean([np.asarray(intrinsics_prior[n], dtype=float) for n in names], axis=0)
            d = None
            if dist_prior:
                ds = [np.asarray(dist_prior[n], dtype=float) for n in names if n in dist_prior]
                d = np.mean(ds, axis=0) if ds else None
            camera.params = colmap_params_from_K(config.camera_model, K, d)
            camera.has_prior_focal_length = True
            db.update_camera(camera)
    finally:
        db.close()


def _mapping_options(config: GeometricConfig, has_prior: bool, relaxed: bool = False) -> Any:
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = config.num_threads
    opts.random_seed = config.seed
    opts.min_num_matches = config.min_num_matches
    opts.multiple_models = True
    opts.extract_colors = False
    refine_focal = config.refine_focal_length or not has_prior
    opts.ba_refine_focal_length = refine_focal
    opts.ba_refine_principal_point = config.refine_principal_point
    opts.ba_refine_extra_params = config.refine_extra_params
    opts.mapper.abs_pose_refine_focal_length = refine_focal
    opts.mapper.abs_pose_refine_extra_params = config.refine_extra_params
    opts.mapper.random_seed = config.seed
    opts.triangulation.random_seed = config.seed
    opts.init_num_trials = 200
    if relaxed:
        opts.min_num_matches = max(6, config.min_num_matches // 2)
        opts.mapper.abs_pose_min_num_inliers = config.relaxed_min_num_inliers
        opts.mapper.abs_pose_min_inlier_ratio = 0.1
        opts.mapper.abs_pose_max_error = 16.0
        opts.mapper.max_reg_trials = 10
        opts.mapper.init_min_num_inliers = 50
        opts.mapper.init_min_tri_angle = 8.0
        opts.init_num_trials = 400
    return opts


def _global_ba(reconstruction: Any, config: GeometricConfig, has_prior: bool) -> None:
    import pycolmap

    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = config.refine_focal_length or not has_prior
    opts.refine_principal_point = config.refine_principal_point
    opts.refine_extra_params = config.refine_extra_params
    opts.print_summary = False
    opts.ceres.loss_function_type = (pycolmap.LossFunctionType.CAUCHY if config.final_ba_loss == "cauchy"
                                     else pycolmap.LossFunctionType.TRIVIAL)
    opts.ceres.loss_function_scale = 1.0
    opts.ceres.solver_options.max_num_iterations = config.final_ba_iterations
    opts.ceres.solver_options.function_tolerance = config.ba_function_tolerance
    opts.ceres.solver_options.gradient_tolerance = 1e-10
    opts.ceres.solver_options.parameter_tolerance = 1e-10
    opts.ceres.solver_options.num_threads = config.num_threads
    pycolmap.bundle_adjustment(reconstruction, opts)


def _largest(models: dict[int, Any]) -> Any | None:
    if not models:
        return None
    return max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))


def calibrate_images(image_paths: list[Path], work_dir: Path, config: GeometricConfig = GeometricConfig(),
                     intrinsics_prior: dict[str, np.ndarray] | None = None,
                     known_centres: dict[str, np.ndarray] | None = None,
                     dist_prior: dict[str, np.ndarray] | None = None) -> CalibrationResult:
    """Calibrate the cameras of a set of overlapping photos (structure from motion).

    image_paths: PNG/JPEG/TIFF files (or raw files, decoded to 8-bit sRGB PNG first), names unique.
    work_dir: scratch folder (COLMAP database, linked images, models); reused runs start afresh.
    intrinsics_prior: image name -> (3, 3) OpenCV K, e.g. from the rig spec. Cameras start from it and
        keep it when ``config.refine_focal_length`` is False (principal point is only refined when
        ``config.refine_principal_point``). With ``config.shared_camera`` the priors are averaged.
    known_centres: image name -> (3,) nominal camera centre in the target frame. With 3 or more of them
        registered, the reconstruction is mapped onto them by a RANSAC similarity (metric scale, target
        frame) and ``alignment_residual_mm`` says how well they agree.
    dist_prior: image name -> (5,) OpenCV distortion to start from (optional).

    Images COLMAP cannot register (no features, too few matches) are listed in ``unregistered``; the
    call only raises when no model at all could be built.
    """
    import pycolmap

    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    notes: list[str] = []
    image_paths = [Path(p) for p in image_paths]
    if len(image_paths) < 2:
        raise ValueError("calibrate_images needs at least 2 images")
    for p in image_paths:
        if not p.is_file():
            raise FileNotFoundError(p)
    work_dir = Path(work_dir)
    _clear_work_dir(work_dir, ("images", "sparse", "database.db"))
    image_dir, database_path = work_dir / "images", work_dir / "database.db"
    _start_colmap(config)
    colmap_names = _stage_images(image_paths, image_dir)
    by_colmap = {v: k for k, v in colmap_names.items()}
    has_prior = bool(intrinsics_prior)
    timings["stage_images"] = time.perf_counter() - t_start

    t0 = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    mode = pycolmap.CameraMode.SINGLE if config.shared_camera else pycolmap.CameraMode.PER_IMAGE
    pycolmap.extract_features(str(database_path), str(image_dir), image_names=sorted(colmap_names.values()),
                              camera_mode=mode, reader_options=reader,
                              extraction_options=_extraction_options(config), device=pycolmap.Device.cpu)
    _set_priors(database_path, colmap_names, config, intrinsics_prior, dist_prior)
    timings["extract"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    _match_database(database_path, config, len(image_paths))
    timings["match"] = time.perf_counter() - t0

    rec = _incremental_model(work_dir, config, has_prior, len(image_paths), timings, notes)
    if config.retry_unregistered and len(_registered_names(rec, by_colmap)) < len(image_paths):
        t0 = time.perf_counter()
        rec = _retry_unregistered(rec, work_dir, config, has_prior, by_colmap, notes)
        timings["retry"] = timings.get("retry", 0.0) + time.perf_counter() - t0
    if config.final_ba_iterations > 0 and config.final_ba_rounds > 0:
        t0 = time.perf_counter()
        rec = _final_bundle_adjustment(rec, work_dir, config, has_prior)
        timings["ba"] = time.perf_counter() - t0

    aligned, residual, outliers = False, None, []
    if known_centres:
        t0 = time.perf_counter()
        aligned, residual, outliers = _align_to_known_centres(rec, by_colmap, known_centres, config, notes)
        timings["align"] = time.perf_counter() - t0

    cameras: dict[str, CameraCalibration] = {}
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        camera = rec.camera(image.camera_id)
        K, dist = opencv_from_colmap_camera(camera)
        cameras[by_colmap[image.name]] = CameraCalibration(
            K=K, dist=dist, cam_from_world=np.asarray(image.cam_from_world().matrix(), dtype=float),
            width=int(camera.width), height=int(camera.height))
    unregistered = [p.name for p in image_paths if p.name not in cameras]
    timings["total"] = time.perf_counter() - t_start
    return CalibrationResult(cameras=dict(sorted(cameras.items())), unregistered=unregistered,
                             reprojection_error_px=float(rec.compute_mean_reprojection_error()),
                             alignment_residual_mm=residual, n_points3d=int(rec.num_points3D()), timings=timings,
                             aligned=aligned, alignment_outliers=outliers, notes=notes, reconstruction=rec)


def _clear_work_dir(work_dir: Path, entries: tuple[str, ...]) -> None:
    """Remove ``entries`` (files, folders or links) of a previous run from ``work_dir`` and create it."""
    for sub in entries:
        target = work_dir / sub
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists() or target.is_symlink():
            target.unlink()
    work_dir.mkdir(parents=True, exist_ok=True)


def _start_colmap(config: GeometricConfig) -> None:
    """Seed COLMAP's random numbers and quiet its log unless ``config.verbose``."""
    import pycolmap

    pycolmap.set_random_seed(config.seed)
    if not config.verbose:
        pycolmap.logging.minloglevel = 2  # warnings and errors only


def _registered_names(rec: Any, by_colmap: dict[str, str]) -> set[str]:
    """The image names (as given) of the images registered in ``rec``."""
    return {by_colmap[rec.image(i).name] for i in rec.reg_image_ids()}


def _incremental_model(work_dir: Path, config: GeometricConfig, has_prior: bool, n_images: int,
                       timings: dict[str, float], notes: list[str]) -> Any:
    """COLMAP's incremental mapping of the matched database into ``work_dir/sparse``: the largest model, from
    a second, relaxed mapping when the first builds none. Raises RuntimeError when neither does."""
    import pycolmap

    image_dir, database_path, sparse_dir = work_dir / "images", work_dir / "database.db", work_dir / "sparse"
    t0 = time.perf_counter()
    sparse_dir.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(str(database_path), str(image_dir), str(sparse_dir),
                                          options=_mapping_options(config, has_prior))
    rec = _largest(models)
    timings["map"] = time.perf_counter() - t0
    if len(models) > 1:
        notes.append(f"mapper built {len(models)} models of sizes "
                     f"{sorted((m.num_reg_images() for m in models.values()), reverse=True)}; kept the largest")
    if rec is None:
        # One more try with relaxed initialisation before giving up.
        t0 = time.perf_counter()
        models = pycolmap.incremental_mapping(str(database_path), str(image_dir), str(sparse_dir),
                                              options=_mapping_options(config, has_prior, relaxed=True))
        rec = _largest(models)
        timings["retry"] = time.perf_counter() - t0
        if rec is None:
            raise RuntimeError(f"calibrate_images: COLMAP could not build any model from {n_images} "
                               "images (too few features or matches)")
        notes.append("first mapping failed; relaxed mapping built a model")
    return rec


def _retry_unregistered(rec: Any, work_dir: Path, config: GeometricConfig, has_prior: bool,
                        by_colmap: dict[str, str], notes: list[str]) -> Any:
    """Continue mapping from ``rec`` with relaxed options to register more images: the continued model when
    it registers more, else ``rec``."""
    import pycolmap

    before = len(_registered_names(rec, by_colmap))
    model_dir = work_dir / "sparse_best"
    if model_dir.exists():
        shutil.rmtree(model_dir)
    model_dir.mkdir()
    rec.write(str(model_dir))
    retry_dir = work_dir / "sparse_retry"
    if retry_dir.exists():
        shutil.rmtree(retry_dir)
    retry_dir.mkdir()
    opts = _mapping_options(config, has_prior, relaxed=True)
    opts.multiple_models = False
    try:
        retried = pycolmap.incremental_mapping(str(work_dir / "database.db"), str(work_dir / "images"),
                                               str(retry_dir), options=opts, input_path=str(model_dir))
        cand = _largest(retried)
        if cand is not None and len(_registered_names(cand, by_colmap)) > before:
            rec = cand
    except Exception as exc:  # noqa: BLE001 - a failed retry keeps the first model
        notes.append(f"relaxed retry failed: {exc}")
    notes.append(f"relaxed registration retry: {before} -> {len(_registered_names(rec, by_colmap))} images")
    return rec


def _final_bundle_adjustment(rec: Any, work_dir: Path, config: GeometricConfig, has_prior: bool) -> Any:
    """Optionally re-triangulate, then ``config.final_ba_rounds`` global bundle adjustments, filtering the
    points between rounds; returns the model."""
    import pycolmap

    if config.final_retriangulate:
        tri_dir = work_dir / "sparse_tri"
        tri_dir.mkdir(exist_ok=True)
        opts = _mapping_options(config, has_prior)
        rec = pycolmap.triangulate_points(rec, str(work_dir / "database.db"), str(work_dir / "images"),
                                          str(tri_dir), clear_points=False, options=opts, refine_intrinsics=False)
    for round_ in range(config.final_ba_rounds):
        _global_ba(rec, config, has_prior)
        if round_ + 1 < config.final_ba_rounds:
            pycolmap.ObservationManager(rec).filter_all_points3D(config.final_filter_max_error_px, 1.5)
    return rec


def _align_to_known_centres(rec: Any, by_colmap: dict[str, str], known_centres: dict[str, np.ndarray],
                            config: GeometricConfig,
                            notes: list[str]) -> tuple[bool, tuple[float, float] | None, list[str]]:
    """Map ``rec`` in place onto the known centres of its registered images by a RANSAC similarity:
    ``(aligned, (mean, max) residual mm of the inliers, outlier names)``; not aligned with fewer than 3
    such images or inliers."""
    import pycolmap

    reg = {by_colmap[rec.image(i).name]: i for i in rec.reg_image_ids()}
    common = sorted(set(reg) & set(known_centres))
    if len(common) < 3:
        notes.append(f"alignment skipped: only {len(common)} registered images have known centres")
        return False, None, []
    src = np.array([np.asarray(rec.image(reg[n]).projection_center(), dtype=float) for n in common])
    dst = np.array([np.asarray(known_centres[n], dtype=float).ravel() for n in common])
    # RANSAC threshold is in target units; scale-free source is handled by sampling minimal sets.
    s, R, t, inl = umeyama_ransac(src, dst, config.alignment_max_error, seed=config.seed)
    if inl.sum() < 3:
        notes.append("alignment failed: fewer than 3 inliers")
        return False, None, []
    rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(R), t))
    err = np.linalg.norm(s * src @ R.T + t - dst, axis=1) * 1000.0
    residual = (float(err[inl].mean()), float(err[inl].max()))
    outliers = [n for n, ok in zip(common, inl) if not ok]
    if outliers:
        notes.append(f"alignment outliers (centre off by > {config.alignment_max_error}): {outliers}")
    return True, residual, outliers


# ----------------------------------------------------------------------------------------------------------
# Exports and imports


def transforms_dict(result: CalibrationResult, image_dir_rel: str = "images") -> dict[str, Any]:
    """transforms.json content: per-frame K, dist and ``transform_matrix`` = world_from_cam 4x4 (OpenCV axes).

    Same schema as the release's transforms.json (stages.decode.transforms_json) with ``file_path`` the
    image's own name under ``image_dir_rel``; ``units``/``frame`` say whether the poses were aligned.
    """
    frames = []
    for name, cam in result.cameras.items():
        K = np.asarray(cam.K, dtype=float)
        frames.append({"camera_id": Path(name).stem, "file_path": f"{image_dir_rel}/{name}" if image_dir_rel else name,
                       "w": int(cam.width), "h": int(cam.height), "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
                       "cx": float(K[0, 2]), "cy": float(K[1, 2]), "K": K.tolist(),
                       "dist": np.asarray(cam.dist, dtype=float).tolist(),
                       "transform_matrix": world_from_cam_4x4(cam.cam_from_world).tolist()})
    aligned = result.aligned
    return {"camera_convention": "opencv", "transform_matrix": "world_from_cam",
            "units": "metres" if aligned else "arbitrary (reconstruction scale, not aligned)",
            "frame": "stage: origin at LED-sphere centre, +y up" if aligned else "reconstruction (not aligned)",
            "unregistered": list(result.unregistered), "reprojection_error_px": result.reprojection_error_px,
            "alignment_residual_mm": list(result.alignment_residual_mm) if result.alignment_residual_mm else None,
            "frames": frames}


def write_transforms_json(result: CalibrationResult, path: Path, image_dir_rel: str = "images") -> Path:
    """Write :func:`transforms_dict` to ``path`` (atomically). Returns the path."""
    return _write_json(Path(path), transforms_dict(result, image_dir_rel))


def read_transforms_json(path: Path) -> dict[str, CameraCalibration]:
    """Read a transforms.json (this module's or the release's) back: file name -> CameraCalibration."""
    data = json.loads(Path(path).read_text())
    out = {}
    for frame in data["frames"]:
        world_from_cam = np.asarray(frame["transform_matrix"], dtype=float)
        cam_from_world = np.linalg.inv(world_from_cam)[:3, :4]
        out[Path(frame["file_path"]).name] = CameraCalibration(
            K=np.asarray(frame["K"], dtype=float), dist=np.asarray(frame.get("dist", [0.0] * 5), dtype=float),
            cam_from_world=cam_from_world, width=int(frame["w"]), height=int(frame["h"]))
    return out


def write_opencv_intrinsics_json(result: CalibrationResult, path: Path) -> Path:
    """OpenCV intrinsics per image: ``{name: {"K": 3x3, "dist": [k1,k2,p1,p2,k3], "width", "height"}}``.

    The same format :func:`read_intrinsics_file` accepts, so a calibration can seed the next one.
    """
    data = {name: {"K": np.asarray(c.K).tolist(), "dist": np.asarray(c.dist).tolist(), "width": c.width,
                   "height": c.height} for name, c in result.cameras.items()}
    return _write_json(Path(path), data)


def read_intrinsics_file(path: Path, image_names: list[str]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Read an intrinsics prior file; returns (name -> K (3, 3), name -> dist (5,)).

    Accepted JSON forms (K in OpenCV convention, pixel centres at integer coordinates):
    ``{"K": [[fx,0,cx],[0,fy,cy],[0,0,1]], "dist": [...]}`` (one K for every image), or
    ``{"img1.png": {"K": [[...]], "dist": [...]}, ...}`` (per image; images not listed get no prior, and a
    ``"*"`` entry, if present, is the default). ``dist`` is optional everywhere.
    """
    data = json.loads(Path(path).read_text())
    K_out: dict[str, np.ndarray] = {}
    d_out: dict[str, np.ndarray] = {}

    def parse(entry: Any, where: str) -> tuple[np.ndarray, np.ndarray | None]:
        if not isinstance(entry, dict) or "K" not in entry:
            raise ValueError(f"{path}: {where} needs a 'K' 3x3 matrix")
        K = np.asarray(entry["K"], dtype=float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"{path}: {where}: K must be a finite 3x3 matrix with positive focal lengths")
        d = entry.get("dist")
        if d is not None:
            d = np.zeros(5) if len(d) == 0 else np.pad(np.asarray(d, dtype=float), (0, max(0, 5 - len(d))))[:5]
        return K, d

    if "K" in data:
        shared = parse(data, "top level")
        per = {n: shared for n in image_names}
    else:
        default = parse(data["*"], "'*'") if "*" in data else None
        per = {}
        for n in image_names:
            if n in data:
                per[n] = parse(data[n], repr(n))
            elif default is not None:
                per[n] = default
        unknown = sorted(set(data) - set(image_names) - {"*"})
        if unknown:
            raise ValueError(f"{path}: intrinsics for unknown images {unknown[:5]}")
    for n, (K, d) in per.items():
        K_out[n] = K
        if d is not None:
            d_out[n] = d
    return K_out, d_out


def write_colmap_text(result_or_reconstruction: Any, out_dir: Path) -> Path:
    """Write a COLMAP text model (cameras.txt, images.txt, points3D.txt) into ``out_dir``.

    Takes a :class:`CalibrationResult` (its reconstruction, in the aligned frame, with points) or a
    pycolmap.Reconstruction. A result without a reconstruction is written from its cameras alone
    (OPENCV cameras, no points). Note COLMAP's principal point is the OpenCV one + 0.5 px.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rec = result_or_reconstruction
    if isinstance(rec, CalibrationResult):
        if rec.reconstruction is None:
            return _write_colmap_text_from_cameras(rec, out_dir)
        rec = rec.reconstruction
    rec.write_text(str(out_dir))
    return out_dir


def _write_colmap_text_from_cameras(result: CalibrationResult, out_dir: Path) -> Path:
    from scipy.spatial.transform import Rotation

    cams, ims = ["# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"], [
        "# Image list: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME / POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, (name, c) in enumerate(result.cameras.items(), start=1):
        params = colmap_params_from_K("OPENCV", c.K, c.dist)
        cams.append(f"{i} OPENCV {c.width} {c.height} " + " ".join(f"{p:.17g}" for p in params))
        x, y, z, w = Rotation.from_matrix(np.asarray(c.cam_from_world)[:, :3]).as_quat()
        t = np.asarray(c.cam_from_world)[:, 3]
        ims.append(f"{i} {w:.17g} {x:.17g} {y:.17g} {z:.17g} {t[0]:.17g} {t[1]:.17g} {t[2]:.17g} {i} {name}")
        ims.append("")
    (out_dir / "cameras.txt").write_text("\n".join(cams) + "\n")
    (out_dir / "images.txt").write_text("\n".join(ims) + "\n")
    (out_dir / "points3D.txt").write_text("# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n")
    return out_dir


def _write_json(path: Path, data: Any) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)
    return path


def calibrate_folder(images_dir: Path, out_dir: Path, intrinsics_file: Path | None = None,
                     config: GeometricConfig | None = None,
                     known_centres: dict[str, np.ndarray] | None = None) -> CalibrationResult:
    """Calibrate every photo in ``images_dir`` and write the results into ``out_dir``.

    Images: files in ``images_dir`` (not recursive) with a suffix in IMAGE_SUFFIXES or RAW_SUFFIXES
    (raw files are decoded to 8-bit sRGB PNG first), sorted by name; names are the file names.

    ``intrinsics_file`` (optional) is JSON with K in OpenCV convention (pixel centres at integer
    coordinates), either one shared camera::

        {"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "dist": [k1, k2, p1, p2, k3]}

    or per image (``"*"`` is an optional default for images not listed)::

        {"img0001.png": {"K": [[...], [...], [...]], "dist": [...]}, "*": {"K": ...}}

    ``dist`` is optional. With a file the focal lengths are kept fixed (``refine_focal_length=False``) and a
    PINHOLE camera is used unless ``config`` says otherwise; without one COLMAP estimates SIMPLE_RADIAL
    intrinsics. The file written as ``intrinsics_opencv.json`` has the per-image form and can be passed back.

    Writes into ``out_dir``: ``transforms.json`` (:func:`write_transforms_json`, file paths relative to
    out_dir pointing at the input images), ``colmap/{cameras,images,points3D}.txt``,
    ``intrinsics_opencv.json``, ``calibration.json`` (summary: registered/unregistered, errors, timings)
    and the scratch folder ``work/`` (COLMAP database). Raises ValueError when the folder holds fewer than
    2 images and RuntimeError when no model could be built.
    """
    images_dir, out_dir = Path(images_dir), Path(out_dir)
    suffixes = IMAGE_SUFFIXES + RAW_SUFFIXES
    paths = sorted(p for p in images_dir.iterdir() if p.is_file() and p.suffix.lower() in suffixes)
    if len(paths) < 2:
        raise ValueError(f"{images_dir}: fewer than 2 images ({', '.join(suffixes)})")
    prior = dist = None
    if intrinsics_file is not None:
        prior, dist = read_intrinsics_file(Path(intrinsics_file), [p.name for p in paths])
    if config is None:
        config = GeometricConfig(camera_model="PINHOLE" if prior else "SIMPLE_RADIAL",
                                 refine_focal_length=not prior)
    out_dir.mkdir(parents=True, exist_ok=True)
    result = calibrate_images(paths, out_dir / "work", config, intrinsics_prior=prior, known_centres=known_centres,
                              dist_prior=dist or None)
    rel = os.path.relpath(images_dir.resolve(), out_dir.resolve())
    write_transforms_json(result, out_dir / "transforms.json", rel)
    write_colmap_text(result, out_dir / "colmap")
    write_opencv_intrinsics_json(result, out_dir / "intrinsics_opencv.json")
    _write_json(out_dir / "calibration.json", {"config": {k: getattr(config, k) for k in config.__dataclass_fields__},
                                               "intrinsics_file": str(intrinsics_file) if intrinsics_file else None,
                                               **result.summary()})
    return result


# ----------------------------------------------------------------------------------------------------------
# Fixed rig: refine the nominal cameras (no incremental mapping)


@dataclass(frozen=True)
class RigRefineConfig(Documented):
    """Options of :func:`calibrate_rig` beyond the shared :class:`GeometricConfig` (features, matching,
    threads, seed, BA iterations and tolerance, ``alignment_max_error``)."""

    ba_rounds: int = checked(4, ge=1)
    """Rounds of (bundle adjust poses [and focal], drop observations with reprojection error above
    ``filter_max_error_px``, re-triangulate with the refined poses)."""
    refine_focal_length: bool = True
    """Refine each camera's focal lengths (fx, fy) in the bundle adjustment; the principal point stays at
    the nominal one unless ``GeometricConfig.refine_principal_point``."""
    loss: str = checked("cauchy", one_of=("cauchy", "huber", "trivial"))
    """Robust loss of the bundle adjustment: "cauchy" or "huber" (scale ``loss_scale_px``) or "trivial"."""
    loss_scale_px: float = 1.0
    filter_max_error_px: float = checked(2.0, gt=0.0)
    """Observations with a larger reprojection error are dropped between rounds."""
    min_observations: int = checked(30, ge=1)
    """Images observing fewer triangulated points than this keep their nominal pose (held constant in
    the bundle adjustment) and are listed in ``unregistered``."""
    max_change_m: float = 0.05
    """A refined camera centre further than this from the nominal one (after the gauge alignment), or ..."""
    max_change_deg: float = 2.0
    """... a refined orientation further than this from the nominal one, is treated as a failed refinement:
    the camera is listed in ``unregistered`` and ``alignment_outliers`` and left out of the result."""
    min_triangulation_angle_deg: float = 1.5
    """Minimum triangulation angle of new points (COLMAP default 1.5)."""
    pose_prior: bool = True
    """Bundle adjust with Gaussian priors pulling each camera towards its nominal pose and focal length
    (sigmas ``prior_centre_mm``, ``prior_angle_deg``, ``prior_focal_pct``; scipy least squares, Huber loss
    on the reprojection errors). Without it COLMAP's bundle adjustment runs unconstrained (the gauge is
    fixed by two cameras), which drifts along the focal/distance ambiguity of long lenses on sparse
    points."""
    prior_centre_mm: float = 3.0
    """Per-axis sigma of a camera centre around the nominal one (the rig's mounting tolerance)."""
    prior_angle_deg: float = 0.2
    """Per-axis sigma (rotation vector) of a camera orientation around the nominal one."""
    prior_focal_pct: float = 0.5
    """Sigma of the focal length around the nominal one, percent."""
    matching: str = checked("guided", one_of=("guided", "colmap"))
    """"guided": match SIFT descriptors only along the epipolar band the nominal (later: refined) poses
    predict and only where the two rays meet inside ``scene_radius_m`` of the stage origin (many more
    correct matches on weakly textured, repetitive scenes); "colmap": COLMAP's exhaustive matching with
    two-view geometric verification (:class:`GeometricConfig` matching options)."""
    epipolar_tolerance_deg: float = 0.6
    """Guided matching: half-width of the epipolar band as an angle (pixels = focal * angle + 1.5 px);
    covers the mounting tolerance of both cameras."""
    refined_tolerance_deg: float = 0.12
    """Guided matching is repeated with the refined poses and this narrower band (``rematch_rounds``)."""
    rematch_rounds: int = 1
    """Guided matching: times matches are recomputed from the refined poses, each followed by a full
    triangulate + bundle adjustment cycle."""
    ratio: float = 0.85
    """Guided matching: Lowe ratio among the candidates inside the band (mutual best matches only)."""
    max_descriptor_distance: float = 0.7
    """Guided matching: largest accepted distance between L2-normalised descriptors."""
    max_view_angle_deg: float = 100.0
    """Guided matching: only pairs whose optical axes differ by less than this are matched."""
    scene_radius_m: float = 1.8
    """Guided matching: matched rays must meet within this distance of the stage origin (the LED sphere
    and what is inside it)."""


def _rigid3d(cam_from_world: np.ndarray) -> Any:
    import pycolmap

    P = np.asarray(cam_from_world, dtype=float)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(P[:3, :3]), P[:3, 3].copy())


def _match_database(database_path: Path, config: GeometricConfig, n_images: int) -> None:
    """Exhaustive (or sequential) matching with two-view geometric verification, as calibrate_images."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = config.num_threads
    matching.use_gpu = False
    matching.guided_matching = config.guided_matching
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = config.seed
    matcher = config.matcher
    if matcher == "auto":
        matcher = "exhaustive" if n_images <= config.exhaustive_max_images else "sequential"
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(str(database_path), matching_options=matching,
                                  verification_options=verification, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = config.sequential_overlap
        pairing.loop_detection = False
        pycolmap.match_sequential(str(database_path), matching_options=matching, pairing_options=pairing,
                                  verification_options=verification, device=pycolmap.Device.cpu)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _guided_match_pair(ka: np.ndarray, da: np.ndarray, Ka: np.ndarray, Pa: np.ndarray, kb: np.ndarray,
                       db_: np.ndarray, Kb: np.ndarray, Pb: np.ndarray, tol_px: float, rig: "RigRefineConfig"
                       ) -> np.ndarray:
    """Mutual-best descriptor matches (M, 2) of keypoints ka/kb (pixels, any convention shared with the Ks)
    restricted to the epipolar band of half-width ``tol_px`` and to rays meeting inside the scene ball."""
    if len(ka) == 0 or len(kb) == 0:
        return np.zeros((0, 2), np.uint32)
    R = Pb[:, :3] @ Pa[:, :3].T
    t = Pb[:, 3] - R @ Pa[:, 3]
    F = np.linalg.inv(Kb).T @ _skew(t) @ R @ np.linalg.inv(Ka)
    xa = np.c_[ka, np.ones(len(ka))]
    xb = np.c_[kb, np.ones(len(kb))]
    la = xa @ F.T  # epipolar lines in b
    lb = xb @ F  # epipolar lines in a
    num = np.abs(la @ xb.T)  # (Na, Nb) = |xb^T F xa|
    dist_b = num / np.linalg.norm(la[:, :2], axis=1, keepdims=True).clip(1e-12)
    dist_a = num / np.linalg.norm(lb[:, :2], axis=1)[None, :].clip(1e-12)
    valid = (dist_b < tol_px) & (dist_a < tol_px)
    ia, ib = np.nonzero(valid)
    if len(ia) == 0:
        return np.zeros((0, 2), np.uint32)
    # rays meet (midpoint) in front of both cameras and inside the scene ball
    ca, cb = camera_centre(Pa), camera_centre(Pb)
    ra = (Pa[:, :3].T @ np.linalg.solve(Ka, xa.T)).T
    rb = (Pb[:, :3].T @ np.linalg.solve(Kb, xb.T)).T
    ra /= np.linalg.norm(ra, axis=1, keepdims=True)
    rb /= np.linalg.norm(rb, axis=1, keepdims=True)
    u, v, w0 = ra[ia], rb[ib], ca - cb
    b = (u * v).sum(1)
    d, e = u @ w0, v @ w0
    den = np.maximum(1.0 - b * b, 1e-12)
    sa, sb = (b * e - d) / den, (e - b * d) / den
    mid = 0.5 * (ca + sa[:, None] * u + cb + sb[:, None] * v)
    ok = (sa > 0) & (sb > 0) & (np.linalg.norm(mid, axis=1) < rig.scene_radius_m)
    valid[:] = False
    valid[ia[ok], ib[ok]] = True
    if not valid.any():
        return np.zeros((0, 2), np.uint32)
    D = np.sqrt(np.maximum(2.0 - 2.0 * da @ db_.T, 0.0))
    D = np.where(valid, D, np.inf)
    order = np.argsort(D, axis=1)[:, :2]
    best = D[np.arange(len(D)), order[:, 0]]
    second = D[np.arange(len(D)), order[:, 1]] if D.shape[1] > 1 else np.full(len(D), np.inf)
    best_a_for_b = np.argmin(D, axis=0)
    i = np.arange(len(D))
    j = order[:, 0]
    keep = np.isfinite(best) & (best < rig.max_descriptor_distance) & (best < rig.ratio * second) \
        & (best_a_for_b[j] == i)
    return np.stack([i[keep], j[keep]], axis=1).astype(np.uint32)


def _guided_matching(database_path: Path, rec: Any, rig: "RigRefineConfig", tolerance_deg: float) -> int:
    """Replace the database's matches by pose-guided matches computed with the poses and intrinsics of
    ``rec`` (same image ids); returns the number of matches written."""
    import pycolmap

    db = pycolmap.Database.open(str(database_path))
    try:
        db.clear_matches()
        db.clear_two_view_geometries()
        data = {}
        for image_id in sorted(rec.reg_image_ids()):
            image = rec.image(image_id)
            kp = np.asarray(db.read_keypoints(image_id), dtype=float)
            kp = kp[:, :2] if kp.size else np.zeros((0, 2))
            desc = np.asarray(db.read_descriptors(image_id).data if hasattr(db.read_descriptors(image_id), "data")
                              else db.read_descriptors(image_id), dtype=np.float32)
            desc /= np.linalg.norm(desc, axis=1, keepdims=True).clip(1e-9) if len(desc) else 1.0
            K = np.asarray(rec.camera(image.camera_id).calibration_matrix(), dtype=float)
            P = np.asarray(image.cam_from_world().matrix(), dtype=float)
            data[int(image_id)] = (kp, desc, K, P)
        ids = sorted(data)
        total = 0
        cos_max = np.cos(np.radians(rig.max_view_angle_deg))
        for n, a in enumerate(ids):
            for b in ids[n + 1:]:
                ka, da, Ka, Pa = data[a]
                kb, db_, Kb, Pb = data[b]
                if Pa[2, :3] @ Pb[2, :3] < cos_max:
                    continue
                tol = 1.5 + np.radians(tolerance_deg) * 0.5 * (Ka[0, 0] + Kb[0, 0])
                m = _guided_match_pair(ka, da, Ka, Pa, kb, db_, Kb, Pb, tol, rig)
                if len(m) == 0:
                    continue
                db.write_matches(a, b, m)
                tvg = pycolmap.TwoViewGeometry()
                tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
                tvg.inlier_matches = m
                db.write_two_view_geometry(a, b, tvg)
                total += len(m)
    finally:
        db.close()
    return total


def _prior_ba(rec: Any, nominal: dict[int, tuple[np.ndarray, np.ndarray]], rig: "RigRefineConfig",
              constant_image_ids: set[int], max_iterations: int) -> None:
    """Bundle adjustment with pose and focal priors (MAP), in place on ``rec``.

    nominal: image id -> (COLMAP-convention K (3, 3), cam_from_world (3, 4)) of the nominal camera.
    Unknowns per free image: rotation vector (about the nominal orientation), centre, focal scale; all
    3D points. Residuals: reprojection (px, Huber 1.5 px), priors (in sigmas). Principal points stay.
    """
    from scipy.optimize import least_squares

    image_ids = sorted(int(i) for i in rec.reg_image_ids() if int(i) not in constant_image_ids)
    if not image_ids:
        return
    point_ids = sorted(int(p) for p in rec.point3D_ids())
    if not point_ids:
        return
    obs = _prior_ba_observations(rec, image_ids, point_ids)
    K0 = np.array([nominal[i][0] for i in image_ids])
    R0 = np.array([nominal[i][1][:, :3] for i in image_ids])
    C0 = np.array([camera_centre(nominal[i][1]) for i in image_ids])
    x_cam = _prior_ba_start(rec, image_ids, K0, R0)
    x_pt = np.array([np.asarray(rec.point3D(p).xyz, dtype=float) for p in point_ids])
    sigmas = (np.radians(rig.prior_angle_deg), rig.prior_centre_mm / 1000.0, rig.prior_focal_pct / 100.0)
    residuals = _prior_ba_residuals(obs, K0, R0, C0, len(point_ids), sigmas)
    jac_sparsity = _prior_ba_sparsity(obs, len(image_ids), len(point_ids))
    x0 = np.concatenate([x_cam.ravel(), x_pt.ravel()])
    sol = least_squares(residuals, x0, jac_sparsity=jac_sparsity, method="trf", loss="huber", f_scale=1.5,
                        x_scale="jac", max_nfev=max(10, max_iterations), xtol=1e-10, ftol=1e-10)
    if np.all(np.isfinite(sol.x)):
        _write_prior_ba(rec, sol.x, image_ids, point_ids, K0, R0)


@dataclass
class _PriorBAObservations:
    """The observations of :func:`_prior_ba`'s points (N of them)."""

    cam: np.ndarray  # (N,) index of the observing free image in the free images, -1 for a constant image
    point: np.ndarray  # (N,) index of the point
    xy: np.ndarray  # (N, 2) observed pixel
    fixed_P: np.ndarray | None  # (N, 3, 4) K [R | t] of the constant observing image (zeros for free ones);
    # None when every observation is by a free image

    @property
    def free(self) -> np.ndarray:
        return self.cam >= 0


def _prior_ba_observations(rec: Any, image_ids: list[int], point_ids: list[int]) -> _PriorBAObservations:
    """Every observation of the points ``point_ids`` in ``rec``, with the free images ``image_ids``."""
    cam_index = {i: k for k, i in enumerate(image_ids)}
    p_index = {p: k for k, p in enumerate(point_ids)}
    obs_cam, obs_pt, obs_xy, obs_fixed = [], [], [], []
    fixed_P = {}
    for pid in point_ids:
        point = rec.point3D(pid)
        for el in point.track.elements:
            image = rec.image(el.image_id)
            obs_pt.append(p_index[pid])
            obs_xy.append(np.asarray(image.points2D[el.point2D_idx].xy, dtype=float))
            if int(el.image_id) in cam_index:
                obs_cam.append(cam_index[int(el.image_id)])
                obs_fixed.append(-1)
            else:
                obs_cam.append(-1)
                obs_fixed.append(int(el.image_id))
                if int(el.image_id) not in fixed_P:
                    cam = rec.camera(image.camera_id)
                    fixed_P[int(el.image_id)] = (np.asarray(cam.calibration_matrix(), dtype=float),
                                                 np.asarray(image.cam_from_world().matrix(), dtype=float))
    obs_cam, obs_fixed = np.array(obs_cam), np.array(obs_fixed)
    # fixed-camera projections are precomputed matrices
    fixed_list = np.array([fixed_P[i][0] @ fixed_P[i][1] if i >= 0 else np.zeros((3, 4)) for i in obs_fixed]) \
        if (obs_cam < 0).any() else None
    return _PriorBAObservations(cam=obs_cam, point=np.array(obs_pt), xy=np.array(obs_xy), fixed_P=fixed_list)


def _prior_ba_start(rec: Any, image_ids: list[int], K0: np.ndarray, R0: np.ndarray) -> np.ndarray:
    """(n, 7) unknowns of the free images at their current estimate: rotation vector about the nominal
    orientation ``R0`` (n, 3, 3), centre, focal scale less 1 against the nominal ``K0`` (n, 3, 3)."""
    from scipy.spatial.transform import Rotation

    x_cam = np.zeros((len(image_ids), 7))
    for k, i in enumerate(image_ids):
        image = rec.image(i)
        P = np.asarray(image.cam_from_world().matrix(), dtype=float)
        x_cam[k, :3] = Rotation.from_matrix(P[:, :3] @ R0[k].T).as_rotvec()
        x_cam[k, 3:6] = camera_centre(P)
        f = np.asarray(rec.camera(image.camera_id).calibration_matrix(), dtype=float)[0, 0]
        x_cam[k, 6] = f / K0[k][0, 0] - 1.0
    return x_cam


def _prior_ba_residuals(obs: _PriorBAObservations, K0: np.ndarray, R0: np.ndarray, C0: np.ndarray, n_pt: int,
                        sigmas: tuple[float, float, float]) -> Callable[[np.ndarray], np.ndarray]:
    """The residual function of :func:`_prior_ba`: unknowns (7 n + 3 n_pt,) -> reprojection errors (2 N,)
    pixels, then the priors (7 n,) in sigmas (``sigmas``: rotation rad, centre m, focal scale)."""
    from scipy.spatial.transform import Rotation

    n_cam, n_obs = len(K0), len(obs.point)
    s_a, s_c, s_f = sigmas
    free = obs.free
    obs_cam, obs_pt, obs_xy, fixed_list = obs.cam, obs.point, obs.xy, obs.fixed_P

    def residuals(x: np.ndarray) -> np.ndarray:
        cams = x[:n_cam * 7].reshape(n_cam, 7)
        pts = x[n_cam * 7:].reshape(n_pt, 3)
        R = Rotation.from_rotvec(cams[:, :3]).as_matrix() @ R0
        out = np.empty((n_obs, 2))
        if free.any():
            c = obs_cam[free]
            X = np.einsum("nij,nj->ni", R[c], pts[obs_pt[free]] - cams[c, 3:6])
            scale = 1.0 + cams[c, 6]
            Kc = K0[c]
            z = np.where(np.abs(X[:, 2]) > 1e-9, X[:, 2], 1e-9)
            u = Kc[:, 0, 0] * scale * X[:, 0] / z + Kc[:, 0, 2]
            v = Kc[:, 1, 1] * scale * X[:, 1] / z + Kc[:, 1, 2]
            out[free] = np.stack([u, v], 1) - obs_xy[free]
        if fixed_list is not None:
            nf = ~free
            Xh = np.einsum("nij,nj->ni", fixed_list[nf], np.c_[pts[obs_pt[nf]], np.ones(nf.sum())])
            z = np.where(np.abs(Xh[:, 2]) > 1e-9, Xh[:, 2], 1e-9)
            out[nf] = Xh[:, :2] / z[:, None] - obs_xy[nf]
        prior = np.concatenate([(cams[:, :3] / s_a).ravel(), ((cams[:, 3:6] - C0) / s_c).ravel(),
                                (cams[:, 6] / s_f).ravel()])
        return np.concatenate([out.ravel(), prior])

    return residuals


def _prior_ba_sparsity(obs: _PriorBAObservations, n_cam: int, n_pt: int) -> Any:
    """The Jacobian's sparsity pattern (CSR, int8) of :func:`_prior_ba_residuals`."""
    from scipy.sparse import lil_matrix

    n_obs = len(obs.point)
    free = obs.free
    J = lil_matrix((2 * n_obs + 7 * n_cam, 7 * n_cam + 3 * n_pt), dtype=np.int8)
    rows = np.arange(n_obs)
    for d in range(2):
        r = 2 * rows + d
        for q in range(7):
            J[r[free], 7 * obs.cam[free] + q] = 1
        for q in range(3):
            J[r, 7 * n_cam + 3 * obs.point + q] = 1
    base = 2 * n_obs
    for k in range(n_cam):
        for q in range(3):
            J[base + 3 * k + q, 7 * k + q] = 1
            J[base + 3 * n_cam + 3 * k + q, 7 * k + 3 + q] = 1
        J[base + 6 * n_cam + k, 7 * k + 6] = 1
    return J.tocsr()


def _write_prior_ba(rec: Any, x: np.ndarray, image_ids: list[int], point_ids: list[int], K0: np.ndarray,
                    R0: np.ndarray) -> None:
    """Put :func:`_prior_ba`'s solution ``x`` into ``rec``: the free images' poses and focal lengths, the
    points, and the points' errors."""
    from scipy.spatial.transform import Rotation

    n_cam, n_pt = len(image_ids), len(point_ids)
    cams = x[:n_cam * 7].reshape(n_cam, 7)
    pts = x[n_cam * 7:].reshape(n_pt, 3)
    R = Rotation.from_rotvec(cams[:, :3]).as_matrix() @ R0
    for k, i in enumerate(image_ids):
        image = rec.image(i)
        P = np.hstack([R[k], (-R[k] @ cams[k, 3:6])[:, None]])
        rec.frame(image.frame_id).rig_from_world = _rigid3d(P)
        camera = rec.camera(image.camera_id)
        Kn = K0[k]
        camera.params = np.array([Kn[0, 0] * (1 + cams[k, 6]), Kn[1, 1] * (1 + cams[k, 6]), Kn[0, 2], Kn[1, 2]])
    for k, pid in enumerate(point_ids):
        rec.point3D(pid).xyz = pts[k]
    rec.update_point_3d_errors()


def _observations_per_image(rec: Any) -> dict[int, int]:
    return {int(i): int(rec.image(i).num_points3D) for i in rec.reg_image_ids()}


def _rig_ba(rec: Any, config: GeometricConfig, rig: RigRefineConfig, constant_image_ids: set[int]) -> None:
    """Bundle adjustment of poses (and focal lengths) with a robust loss; images in ``constant_image_ids``
    keep their pose; the gauge (7 dof) is fixed by COLMAP (two cameras) and set afterwards by alignment."""
    import pycolmap

    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = rig.refine_focal_length
    opts.refine_principal_point = config.refine_principal_point
    opts.refine_extra_params = False
    opts.print_summary = False
    opts.ceres.loss_function_type = {"cauchy": pycolmap.LossFunctionType.CAUCHY,
                                     "huber": pycolmap.LossFunctionType.HUBER,
                                     "trivial": pycolmap.LossFunctionType.TRIVIAL}[rig.loss]
    opts.ceres.loss_function_scale = rig.loss_scale_px
    opts.ceres.solver_options.max_num_iterations = max(config.final_ba_iterations, 1)
    opts.ceres.solver_options.function_tolerance = config.ba_function_tolerance
    opts.ceres.solver_options.gradient_tolerance = 1e-10
    opts.ceres.solver_options.parameter_tolerance = 1e-10
    opts.ceres.solver_options.num_threads = config.num_threads
    ba_config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        ba_config.add_image(image_id)
    for image_id in constant_image_ids:
        if rec.exists_image(image_id):
            ba_config.set_constant_rig_from_world_pose(rec.image(image_id).frame_id)
    if len(constant_image_ids) < 2:
        ba_config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_bundle_adjuster(opts, ba_config, rec).solve()


def calibrate_rig(image_paths: list[Path], work_dir: Path, nominal_K: dict[str, np.ndarray],
                  nominal_cam_from_world: dict[str, np.ndarray], config: GeometricConfig | None = None,
                  rig_config: RigRefineConfig | None = None) -> CalibrationResult:
    """Refine the nominal cameras of a fixed rig (light stage) from one set of simultaneous photos.

    Unlike :func:`calibrate_images` nothing is reconstructed from scratch: every image starts at its
    nominal (rig spec) camera, which only needs to be within mounting tolerances of the truth.

    1. SIFT features (``config``: ``max_num_features``, ``peak_threshold``, ``first_octave``,
       ``max_image_size`` ...), exhaustive matching with two-view geometric verification.
    2. A COLMAP model with one PINHOLE camera per image (nominal K) at its nominal pose; points are
       triangulated from the verified matches with the poses held fixed (``pycolmap.triangulate_points``).
    3. ``rig_config.ba_rounds`` rounds of robust bundle adjustment of poses (and focal lengths), dropping
       observations above ``rig_config.filter_max_error_px`` and re-triangulating between rounds. Images
       with fewer than ``rig_config.min_observations`` observations keep their nominal pose.
    4. Gauge: the refined centres are mapped onto the nominal centres by a similarity (RANSAC Umeyama,
       inlier threshold ``config.alignment_max_error`` metres), so scale and frame are the rig's (stage
       frame, metres); ``alignment_residual_mm`` is the mean/max distance between refined and nominal
       centres, i.e. roughly the mounting error the calibration found.

    image_paths: one image per camera (PNG/JPEG or raw; raws are decoded to 8-bit sRGB PNG), names unique.
    nominal_K, nominal_cam_from_world: image name (``path.name``) -> OpenCV (3, 3) K and (3, 4)
        cam_from_world in the stage frame, for every image.
    Status (simulated stage, 32 cameras): the refined cameras are NOT closer to the truth than the nominal
    ones (``bench/bench_calibration.py --rig-prior`` measures both against the true cameras). Started from
    the TRUE cameras the points triangulate with more than a pixel of reprojection error and the adjustment
    moves away from the truth, so the observations carry a systematic error (repetitive LED-sphere grid
    matches, or a pixel convention mismatch between renderer and decode) that is not resolved. Use the
    nominal rig unless a capture shows otherwise.

    Returns a :class:`CalibrationResult` with ``aligned`` True; ``cameras`` holds the refined cameras
    (dist zero), ``unregistered`` the images that kept no refined pose (too few observations or a
    refinement beyond ``max_change_m``/``max_change_deg``). Raises ValueError on missing nominal cameras.
    """
    import pycolmap

    config = config or GeometricConfig(camera_model="PINHOLE")
    rig = rig_config or RigRefineConfig()
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    notes: list[str] = []
    image_paths = [Path(p) for p in image_paths]
    if len(image_paths) < 3:
        raise ValueError("calibrate_rig needs at least 3 images")
    missing = [p.name for p in image_paths if p.name not in nominal_K or p.name not in nominal_cam_from_world]
    if missing:
        raise ValueError(f"calibrate_rig: no nominal camera for {missing[:5]}")
    for p in image_paths:
        if not p.is_file():
            raise FileNotFoundError(p)
    work_dir = Path(work_dir)
    _clear_work_dir(work_dir, ("images", "database.db", "rig_nominal", "rig_tri"))
    image_dir, database_path = work_dir / "images", work_dir / "database.db"
    _start_colmap(config)
    colmap_names = _stage_images(image_paths, image_dir)
    by_colmap = {v: k for k, v in colmap_names.items()}
    timings["stage_images"] = time.perf_counter() - t_start

    t0 = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    pycolmap.extract_features(str(database_path), str(image_dir), image_names=sorted(colmap_names.values()),
                              camera_mode=pycolmap.CameraMode.PER_IMAGE, reader_options=reader,
                              extraction_options=_extraction_options(config), device=pycolmap.Device.cpu)
    timings["extract"] = time.perf_counter() - t0
    if rig.matching == "colmap":
        t0 = time.perf_counter()
        _match_database(database_path, config, len(image_paths))
        timings["match"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    rec = _nominal_model(database_path, by_colmap, nominal_K, nominal_cam_from_world)
    nominal_by_id = {int(i): (K_to_colmap(nominal_K[by_colmap[rec.image(i).name]]),
                              np.asarray(nominal_cam_from_world[by_colmap[rec.image(i).name]], dtype=float)[:3, :4])
                     for i in rec.reg_image_ids()}
    (work_dir / "rig_nominal").mkdir()
    (work_dir / "rig_tri").mkdir()
    rec.write(str(work_dir / "rig_nominal"))
    opts = _mapping_options(config, has_prior=True)
    opts.triangulation.min_angle = rig.min_triangulation_angle_deg
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    timings["model"] = time.perf_counter() - t0

    rec = _refine_rig(rec, work_dir, opts, config, rig, nominal_by_id, timings, notes)
    obs = _observations_per_image(rec)
    constant = {i for i, n in obs.items() if n < rig.min_observations}

    # Gauge: refined centres onto the nominal ones.
    t0 = time.perf_counter()
    names = {int(i): by_colmap[rec.image(i).name] for i in rec.reg_image_ids()}
    free = sorted(i for i in names if i not in constant)
    aligned, residual = _align_to_nominal_centres(rec, free, names, nominal_cam_from_world, config, rig, notes)
    timings["align"] = time.perf_counter() - t0

    cameras: dict[str, CameraCalibration] = {}
    outliers: list[str] = []
    if aligned:
        cameras, outliers = _refined_cameras(rec, free, names, nominal_cam_from_world, rig)
    if outliers:
        notes.append(f"refinement moved {outliers} beyond {rig.max_change_m} m / {rig.max_change_deg} deg "
                     "of the nominal camera; dropped")
    few = sorted(names[i] for i in constant)
    if few:
        notes.append(f"too few observations (< {rig.min_observations}) to refine {few}")
    unregistered = [p.name for p in image_paths if p.name not in cameras]
    reproj = float(rec.compute_mean_reprojection_error()) if rec.num_points3D() else float("nan")
    timings["total"] = time.perf_counter() - t_start
    return CalibrationResult(cameras=dict(sorted(cameras.items())), unregistered=unregistered,
                             reprojection_error_px=reproj if np.isfinite(reproj) else 0.0,
                             alignment_residual_mm=residual, n_points3d=int(rec.num_points3D()), timings=timings,
                             aligned=aligned, alignment_outliers=outliers, notes=notes, reconstruction=rec)


def _nominal_model(database_path: Path, by_colmap: dict[str, str], nominal_K: dict[str, np.ndarray],
                   nominal_cam_from_world: dict[str, np.ndarray]) -> Any:
    """A COLMAP model of the database's images, each with its own PINHOLE camera at its nominal K and pose
    (ids as in the database), holding their keypoints and no points."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    db = pycolmap.Database.open(str(database_path))
    try:
        db_images = db.read_all_images()
        db_cameras = {c.camera_id: c for c in db.read_all_cameras()}
        for image in sorted(db_images, key=lambda im: im.image_id):
            name = by_colmap[image.name]
            cam = db_cameras[image.camera_id]
            K = np.asarray(nominal_K[name], dtype=float)
            camera = pycolmap.Camera(model="PINHOLE", width=int(cam.width), height=int(cam.height),
                                     params=colmap_params_from_K("PINHOLE", K), camera_id=int(image.camera_id))
            camera.has_prior_focal_length = True
            rec.add_camera_with_trivial_rig(camera)
            keypoints = np.asarray(db.read_keypoints(image.image_id), dtype=float)
            keypoints = keypoints[:, :2] if keypoints.size else np.zeros((0, 2))
            new = pycolmap.Image(name=image.name, keypoints=keypoints, camera_id=int(image.camera_id),
                                 image_id=int(image.image_id))
            rec.add_image_with_trivial_frame(new, _rigid3d(nominal_cam_from_world[name]))
    finally:
        db.close()
    return rec


def _refine_rig(rec: Any, work_dir: Path, opts: Any, config: GeometricConfig, rig: RigRefineConfig,
                nominal_by_id: dict[int, tuple[np.ndarray, np.ndarray]], timings: dict[str, float],
                notes: list[str]) -> Any:
    """Match (guided: ``1 + rig.rematch_rounds`` times, each from the latest poses), triangulate with the
    poses held, and run ``rig.ba_rounds`` robust bundle adjustments (images with fewer than
    ``rig.min_observations`` observations held), filtering and re-triangulating between them; returns the
    refined model (its frame still the nominal one, up to the adjustment's gauge)."""
    import pycolmap

    database_path, image_dir, tri_dir = work_dir / "database.db", work_dir / "images", work_dir / "rig_tri"
    cycles = 1 + (rig.rematch_rounds if rig.matching == "guided" else 0)
    for cycle in range(cycles):
        if rig.matching == "guided":
            t0 = time.perf_counter()
            tol = rig.epipolar_tolerance_deg if cycle == 0 else rig.refined_tolerance_deg
            n_matches = _guided_matching(database_path, rec, rig, tol)
            timings["match"] = timings.get("match", 0.0) + time.perf_counter() - t0
            notes.append(f"guided matching ({tol} deg band, {'nominal' if cycle == 0 else 'refined'} poses): "
                         f"{n_matches} matches")
        t0 = time.perf_counter()
        rec = pycolmap.triangulate_points(rec, str(database_path), str(image_dir), str(tri_dir),
                                          clear_points=True, options=opts, refine_intrinsics=False)
        timings["triangulate"] = timings.get("triangulate", 0.0) + time.perf_counter() - t0
        if cycle == 0:
            notes.append(f"triangulated {rec.num_points3D()} points at the nominal poses "
                         f"(reprojection error {rec.compute_mean_reprojection_error():.2f} px)")
        # Robust BA rounds.
        t0 = time.perf_counter()
        for round_ in range(rig.ba_rounds):
            obs = _observations_per_image(rec)
            constant = {i for i, n in obs.items() if n < rig.min_observations}
            if rig.pose_prior:
                _prior_ba(rec, nominal_by_id, rig, constant, config.final_ba_iterations)
            else:
                _rig_ba(rec, config, rig, constant)
            pycolmap.ObservationManager(rec).filter_all_points3D(rig.filter_max_error_px, 1.0)
            if round_ + 1 < rig.ba_rounds:
                rec = pycolmap.triangulate_points(rec, str(database_path), str(image_dir), str(tri_dir),
                                                  clear_points=True, options=opts, refine_intrinsics=False)
        timings["ba"] = timings.get("ba", 0.0) + time.perf_counter() - t0
    return rec


def _align_to_nominal_centres(rec: Any, free: list[int], names: dict[int, str],
                              nominal_cam_from_world: dict[str, np.ndarray], config: GeometricConfig,
                              rig: RigRefineConfig, notes: list[str]) -> tuple[bool, tuple[float, float] | None]:
    """Map ``rec`` in place onto the nominal centres of its refined images ``free`` (ids; ``names``: id ->
    image name) by a RANSAC similarity: ``(aligned, (mean, max) residual mm of the inliers)``."""
    import pycolmap

    if len(free) < 3:
        notes.append(f"only {len(free)} images had >= {rig.min_observations} observations; nominal cameras returned")
        return False, None
    src = np.array([np.asarray(rec.image(i).projection_center(), dtype=float) for i in free])
    dst = np.array([camera_centre(nominal_cam_from_world[names[i]]) for i in free])
    s, R, t, inl = umeyama_ransac(src, dst, config.alignment_max_error, seed=config.seed)
    if not (inl.sum() >= 3 and np.isfinite(s) and s > 0):
        notes.append("alignment to the nominal centres failed; nominal cameras returned")
        return False, None
    rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(R), t))
    err = np.linalg.norm(s * src @ R.T + t - dst, axis=1) * 1000.0
    return True, (float(err[inl].mean()), float(err[inl].max()))


def _refined_cameras(rec: Any, free: list[int], names: dict[int, str],
                     nominal_cam_from_world: dict[str, np.ndarray],
                     rig: RigRefineConfig) -> tuple[dict[str, CameraCalibration], list[str]]:
    """The aligned model's cameras of the images ``free`` (ids; ``names``: id -> image name), and the sorted
    names of those dropped: non-finite, or moved beyond ``rig.max_change_m`` / ``rig.max_change_deg`` from
    the nominal camera."""
    cameras: dict[str, CameraCalibration] = {}
    failed: list[str] = []
    for image_id in free:
        image = rec.image(image_id)
        name = names[image_id]
        K, dist = opencv_from_colmap_camera(rec.camera(image.camera_id))
        P = np.asarray(image.cam_from_world().matrix(), dtype=float)
        N = np.asarray(nominal_cam_from_world[name], dtype=float)
        shift = float(np.linalg.norm(camera_centre(P) - camera_centre(N)))
        angle = rotation_angle_deg(P[:, :3] @ N[:, :3].T)
        if not (np.all(np.isfinite(P)) and np.all(np.isfinite(K))) or shift > rig.max_change_m \
                or angle > rig.max_change_deg:
            failed.append(name)
            continue
        cam = rec.camera(image.camera_id)
        cameras[name] = CameraCalibration(K=K, dist=dist, cam_from_world=P, width=int(cam.width),
                                          height=int(cam.height))
    return cameras, sorted(failed)
