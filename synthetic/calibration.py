"""Per-session calibration captures of the simulator: a colour chart and a diffuse sphere.

Opt-in: ``simulate(out, config, calibration=CalibrationConfig())`` (without it nothing changes, byte for
byte). With it, every session gets

- per-camera colour-response errors: camera k's raw is ``gain * cam_from_srgb @ R_k @ radiance`` with
  ``R_k = I + U(-colour_error, colour_error)^{3x3}`` (all its frames: actions, clean plates, calibration).
  The DNG keeps the nominal ColorMatrix (as a real camera's embedded matrix would), so a decoded frame is
  ``gain * R_k @ radiance`` and ``inv(R_k)`` is the correction the colour calibration should find;
- ``sessions/<sid>/calibration/chart/<cam>.dng``: under full_on, a flat ColorChecker card (the 24
  reference colours of ``calibration.colour.reference_chart_srgb`` as Lambertian albedos in a 6 x 4
  grid on a dark card, albedo 0.05) fills the middle of every frame, facing the camera; its irradiance
  is that of a plane facing the camera under the session's LEDs (with their errors). Layout, reference
  values and fitting target in ``sessions/<sid>/calibration/chart.json``;
- ``sessions/<sid>/calibration/sphere/{full_on,pos,neg}/<cam>.dng``: a Lambertian sphere (default radius
  0.15 m, albedo 0.8) at the point the cameras look at, per-pixel exact normals, unoccluded (distant
  LEDs), in front of the stage background. Its centre and radius go to rig.json
  ``"calibration_objects": {"sphere": {"centre": [...], "radius_m": ...}}``;
- ``sessions/<sid>/calibration/cameras/<cam>.dng``: a geometric calibration target under full_on: an
  upright Lambertian cylinder with flat caps (default radius 0.45 m, height 1.6 m) centred where the
  subject is, so it fills most of every camera's view, with a high-contrast random speckle albedo
  (0.1 / 0.8: thresholded two-octave value noise of the 3D surface point, blobs ~16-40 mm, i.e. ~4-10 px
  at 320 px wide) that SIFT finds and matches across views. Ray-traced analytically per TRUE camera
  (exact intersections, per-normal LED irradiance), in front of the stage background. It is what the
  ``cameras`` stage calibrates from (source "colmap"); parameters in rig.json
  ``"calibration_objects": {"target": ...}``;
- ``ground_truth/calibration/<sid>.json``: the ``R_k`` and their inverses, chart and sphere parameters.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from calibration.colour import REFERENCE_CHART, reference_chart_srgb
from pipeline.config import Documented, broken, checked

from . import files, sensor, shading
from .rig import Camera, LedSphere

CHART_FORMAT = "ultrastage-chart/1"
CALIBRATION_TRUTH_FORMAT = "ultrastage-calibration-truth/1"
# purposes of the random streams (synthetic.simulate uses 1..6)
_COLOUR_RESPONSE, _CALIB_NOISE, _TARGET_TEXTURE, _MARKER_LAYOUT, _MARKER_SURVEY = 7, 8, 9, 10, 11
CHART_COLUMNS, CHART_ROWS = 6, 4
CARD_ALBEDO = 0.05


@dataclass(frozen=True)
class CalibrationConfig(Documented):
    """What the simulator adds per session for colour and light calibration."""

    chart: bool = True
    """Write the colour chart frames (sessions/<sid>/calibration/chart/<cam>.dng + chart.json)."""
    sphere: bool = True
    """Write the diffuse sphere frames (sessions/<sid>/calibration/sphere/{full_on,pos,neg}/<cam>.dng)."""
    colour_error: float = checked(0.03, ge=0.0, lt=0.3)
    """Half-width of the uniform per-element error of each camera's 3x3 colour response R_k = I + E
    (0 = every camera has the nominal response)."""
    sphere_radius_m: float = checked(0.15, gt=0.0)
    """Radius of the calibration sphere, metres."""
    sphere_albedo: float = checked(0.8, gt=0.0, le=1.0)
    """Grey Lambertian albedo of the calibration sphere."""
    chart_width_fraction: float = checked(0.8, ge=0.2, le=1.0)
    """Width of the chart's patch grid as a fraction of the image width (centred)."""
    target: bool = True
    """Write the geometric calibration target frames (sessions/<sid>/calibration/cameras/<cam>.dng): a
    speckled cylinder at the stage centre for structure-from-motion calibration of the cameras."""
    target_radius_m: float = checked(0.45, gt=0.0)
    """Radius of the target cylinder, metres (the default subject's bounding cylinder is ~0.52 m)."""
    target_height_m: float = checked(1.6, gt=0.0)
    """Height of the target cylinder, metres, centred on the point the cameras look at."""
    speckle_size_m: float = checked(0.016, gt=0.0)
    """Cell size of the finer of the two value-noise octaves of the speckle (the coarser is 2.5x):
    ~4 px at 320 px wide, where a pixel covers ~4 mm of the target."""
    speckle_albedo: tuple[float, float] = (0.1, 0.8)
    """Dark and bright albedo of the speckle."""
    markers: bool = True
    """Write the marker-frame calibration frames (sessions/<sid>/calibration/markers/<cam>.dng): white balls
    of known (surveyed) positions on a rigid frame filling the capture volume (the frame's rods are thin
    and dark and not rendered). The ``cameras`` stage calibrates from them (source "markers")."""
    marker_count: int = checked(300, ge=4)
    """Number of balls on the marker frame."""
    marker_radius_m: float = checked(0.012, gt=0.0)
    """Radius of each ball, metres (~1.7-6 px at 320 px wide, from 4.6 m to 0.76 m away)."""
    marker_volume_radius_m: float = checked(1.3, gt=0.0)
    """The balls fill a ball of this radius around the point the cameras look at: they span the depth of
    every view (0.76 m to 4.6 m away), which pins each camera's distance and focal length apart, and stay
    > 0.7 m from every camera (the nearest cameras are ~2 m from that point)."""
    marker_min_separation_m: float = 0.1
    """Smallest distance between two balls' centres."""
    marker_albedo: float = checked(0.9, gt=0.0, le=1.0)
    """Grey Lambertian albedo of the balls."""
    marker_survey_error_mm: float = checked(0.1, ge=0.0)
    """Per-axis standard deviation of the error of the surveyed ball positions published in rig.json
    (the balls are rendered at the true positions, ground_truth/calibration/<sid>.json)."""
    marker_seed: int = 0
    """Which frame: the layout is a property of the physical frame (the same in every session and for
    every simulator seed), not of a session."""
    marker_supersample: int = checked(4, ge=1)
    """Sub-samples per pixel side when rendering the balls (anti-aliased edges: the blob centroids the
    calibration measures are unbiased to ~0.01 px)."""

    def _checks(self) -> list[str]:
        problems = []
        if not (len(self.speckle_albedo) == 2 and 0 <= self.speckle_albedo[0] < self.speckle_albedo[1] <= 1):
            problems.append(broken(self, "speckle_albedo", "must be (dark, bright) with 0 <= dark < bright <= 1"))
        if not self.marker_min_separation_m > 2 * self.marker_radius_m:
            problems.append(broken(self, "marker_min_separation_m",
                                   f"must be > 2 x marker_radius_m ({2 * self.marker_radius_m!r})"))
        return problems

    def to_json(self) -> dict:
        return asdict(self)


def colour_responses(seed: int, session_index: int, n_cameras: int, colour_error: float) -> np.ndarray:
    """Per-camera colour responses R_k (n_cameras, 3, 3) = I + U(-e, e), keyed by (seed, session)."""
    rng = np.random.default_rng([seed, _COLOUR_RESPONSE, session_index])
    return np.eye(3) + rng.uniform(-colour_error, colour_error, size=(n_cameras, 3, 3))


def as_seen(radiance: np.ndarray, response: np.ndarray | None) -> np.ndarray:
    """Radiance (H, W, 3) as camera response `response` (3, 3) sees it (None: unchanged), float32."""
    if response is None:
        return radiance
    return (radiance.astype(np.float32) @ response.T.astype(np.float32)).astype(np.float32)


def chart_layout(width: int, height: int, width_fraction: float = 0.8) -> tuple[np.ndarray, np.ndarray, list]:
    """The chart in an image: labels (H, W) uint8 (k = patch k-1, 25 = card, 0 = stage), the card box
    and patch boxes [x0, y0, x1, y1] (pixel indices, end exclusive) in reading order."""
    pitch = max(4, int(width * width_fraction) // CHART_COLUMNS)
    gap = max(1, pitch // 6)
    grid_w, grid_h = CHART_COLUMNS * pitch, CHART_ROWS * pitch
    x0 = (width - grid_w) // 2
    y0 = (height - grid_h) // 2
    labels = np.zeros((height, width), np.uint8)
    card = [max(0, x0 - gap), max(0, y0 - gap), min(width, x0 + grid_w + gap), min(height, y0 + grid_h + gap)]
    labels[card[1]:card[3], card[0]:card[2]] = 25
    boxes = []
    for k in range(CHART_COLUMNS * CHART_ROWS):
        r, c = divmod(k, CHART_COLUMNS)
        box = [x0 + c * pitch + gap, y0 + r * pitch + gap, x0 + (c + 1) * pitch, y0 + (r + 1) * pitch]
        labels[box[1]:box[3], box[0]:box[2]] = k + 1
        boxes.append(box)
    return labels, np.array(card), boxes


def plane_irradiance(normal: np.ndarray, leds: LedSphere) -> np.ndarray:
    """Irradiance (9,) (full_on, pos, neg x RGB) of an unoccluded plane with unit `normal` (3,)."""
    cos = np.maximum(leds.directions @ np.asarray(normal, np.float64), 0.0)
    return cos @ leds.irradiance.astype(np.float64)


def render_chart(camera: Camera, leds: LedSphere, background: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """full_on radiance (H, W, 3) float32 of the chart card facing `camera` in front of the stage."""
    _, reference = reference_chart_srgb()
    albedo = np.zeros((26, 3))
    albedo[1:25] = reference
    albedo[25] = CARD_ALBEDO
    rotation = camera.cam_from_world[:, :3]
    facing = -rotation[2]                              # world direction from the card towards the camera
    irradiance = plane_irradiance(facing, leds)[0:3]
    card = (albedo[labels] * irradiance / np.pi).astype(np.float32)
    stage = shading.render_background(camera, leds, background)[..., 0:3]
    return np.where((labels > 0)[..., None], card, stage).astype(np.float32)


def render_sphere(camera: Camera, leds: LedSphere, background: np.ndarray, centre: np.ndarray, radius: float,
                  albedo: float, chunk: int = 16384) -> tuple[np.ndarray, np.ndarray]:
    """Radiance (H, W, 9) float32 (full_on, pos, neg x RGB) of the Lambertian sphere in front of the stage
    background, and its mask (H, W)."""
    from calibration.light import sphere_normals

    normals, mask = sphere_normals(camera.K, camera.cam_from_world, camera.width, camera.height, centre, radius)
    radiance = shading.render_background(camera, leds, background).reshape(-1, 9)
    pixels = np.nonzero(mask.reshape(-1))[0]
    flat = normals.reshape(-1, 3)
    dirs, table = leds.directions.astype(np.float32), leds.irradiance
    for start in range(0, len(pixels), chunk):
        sel = pixels[start:start + chunk]
        cos = np.maximum(flat[sel] @ dirs.T, 0.0)
        radiance[sel] = cos @ table * np.float32(albedo / np.pi)
    return radiance.reshape(camera.height, camera.width, 9), mask


def sphere_centre(y_range: tuple[float, float]) -> np.ndarray:
    """Where the sphere sits: the point the cameras look at (subject's bounding-cylinder centre)."""
    return np.array([0.0, 0.5 * (y_range[0] + y_range[1]), 0.0])


class SpeckleTexture:
    """High-contrast random speckle albedo of a 3D point: two octaves of value noise (random values on a
    cubic lattice, trilinearly interpolated; cells `size` and 2.5 `size`), thresholded at 0.5 with a
    soft edge, mapped to (dark, bright). Keyed by a seed; covers the box `lo`..`hi` (metres)."""

    def __init__(self, seed: int, session_index: int, lo: np.ndarray, hi: np.ndarray, size: float,
                 albedo: tuple[float, float]):
        rng = np.random.default_rng([seed, _TARGET_TEXTURE, session_index])
        self.lo = np.asarray(lo, np.float64) - 2 * size
        self.octaves = []
        for cell, weight in ((size, 0.6), (2.5 * size, 0.4)):
            shape = tuple(int(n) for n in np.ceil((np.asarray(hi) - self.lo) / cell) + 3)
            self.octaves.append((cell, weight, rng.random(shape, dtype=np.float32)))
        self.albedo = albedo

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Albedo (N,) float32 at world points (N, 3)."""
        value = np.zeros(len(points), np.float32)
        for cell, weight, table in self.octaves:
            q = (points - self.lo) / cell
            i = np.clip(np.floor(q).astype(np.int64), 0, np.array(table.shape) - 2)
            f = np.clip(q - i, 0.0, 1.0).astype(np.float32)
            f = f * f * (3 - 2 * f)                       # smooth interpolation (no lattice creases)
            acc = np.zeros(len(points), np.float32)
            for dx in (0, 1):
                wx = f[:, 0] if dx else 1 - f[:, 0]
                for dy in (0, 1):
                    wy = f[:, 1] if dy else 1 - f[:, 1]
                    for dz in (0, 1):
                        wz = f[:, 2] if dz else 1 - f[:, 2]
                        acc += wx * wy * wz * table[i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz]
            value += weight * acc
        # value noise sums cluster round 0.5: a steep soft threshold gives ~half dark, half bright blobs
        t = np.clip((value - 0.5) / 0.06 + 0.5, 0.0, 1.0)
        t = t * t * (3 - 2 * t)
        dark, bright = self.albedo
        return (dark + (bright - dark) * t).astype(np.float32)


def cylinder_hits(origin: np.ndarray, dirs: np.ndarray, centre: np.ndarray, radius: float,
                  height: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First intersection of rays origin + s dirs (dirs (N, 3)) with the closed upright cylinder (axis
    +y through `centre`, caps at centre_y -+ height/2). Returns hit mask (N,), points (N, 3), outward
    normals (N, 3) (zero where missed)."""
    o = np.asarray(origin, np.float64) - centre
    d = dirs.astype(np.float64)
    half = 0.5 * height
    n = len(d)
    best = np.full(n, np.inf)
    normals = np.zeros((n, 3))
    # side: (ox + s dx)^2 + (oz + s dz)^2 = r^2, nearest root in front with |y| <= half
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = 2 * (o[0] * d[:, 0] + o[2] * d[:, 2])
    c = o[0] ** 2 + o[2] ** 2 - radius ** 2
    disc = b * b - 4 * a * c
    ok = (disc >= 0) & (a > 1e-12)
    # misses get a negative distance (rejected below by s > 0) so no inf * 0 makes NaN on the way
    s = np.where(ok, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * np.maximum(a, 1e-12)), -1.0)
    y = o[1] + s * d[:, 1]
    side = ok & (s > 0) & (np.abs(y) <= half)
    best[side] = s[side]
    p = o + s[:, None] * d
    normals[side] = np.column_stack([p[side, 0], np.zeros(side.sum()), p[side, 2]]) / radius
    # caps: y = +-half inside the disc
    for sign in (1.0, -1.0):
        with np.errstate(divide="ignore", invalid="ignore"):
            sc = (sign * half - o[1]) / d[:, 1]
        pc = o + np.where(np.isfinite(sc), sc, 0)[:, None] * d
        cap = np.isfinite(sc) & (sc > 0) & (pc[:, 0] ** 2 + pc[:, 2] ** 2 <= radius ** 2) & (sc < best)
        best[cap] = sc[cap]
        normals[cap] = (0.0, sign, 0.0)
    hit = np.isfinite(best)
    points = np.asarray(origin, np.float64) + np.where(hit, best, 0)[:, None] * d
    return hit, points, normals


def render_target(camera: Camera, leds: LedSphere, background: np.ndarray, centre: np.ndarray,
                  calib: CalibrationConfig, texture: SpeckleTexture) -> tuple[np.ndarray, np.ndarray]:
    """full_on radiance (H, W, 3) float32 of the speckled target cylinder in front of the stage background
    (Lambertian, unoccluded: convex; irradiance from every LED facing the surface normal), and its mask."""
    from .shading import pixel_rays

    origin, dirs, _ = pixel_rays(camera)
    hit, points, normals = cylinder_hits(origin, dirs.reshape(-1, 3), centre, calib.target_radius_m,
                                         calib.target_height_m)
    radiance = shading.render_background(camera, leds, background)[..., 0:3].reshape(-1, 3)
    # Irradiance per normal: side normals (cos phi, 0, sin phi) tabulated over 4096 azimuths (< 0.1 deg
    # apart; the irradiance is smooth in phi), plus the two cap normals.
    n_phi = 4096
    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    table_normals = np.concatenate([np.column_stack([np.cos(phi), np.zeros(n_phi), np.sin(phi)]),
                                    [[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]])
    cos = np.maximum(table_normals @ leds.directions.T.astype(np.float64), 0.0)
    irradiance = (cos @ leds.irradiance[:, 0:3].astype(np.float64)).astype(np.float32)
    pixels = np.nonzero(hit)[0]
    nrm = normals[pixels]
    index = np.rint(np.arctan2(nrm[:, 2], nrm[:, 0]) * (n_phi / (2 * np.pi))).astype(np.int64) % n_phi
    index = np.where(nrm[:, 1] > 0.5, n_phi, np.where(nrm[:, 1] < -0.5, n_phi + 1, index))
    radiance[pixels] = irradiance[index] * (texture(points[pixels]) / np.float32(np.pi))[:, None]
    return radiance.reshape(camera.height, camera.width, 3).astype(np.float32), hit.reshape(camera.height, camera.width)


def target_texture(seed: int, session_index: int, centre: np.ndarray, calib: CalibrationConfig) -> SpeckleTexture:
    """The speckle of session `session_index`'s target (keyed by seed and session)."""
    extent = np.array([calib.target_radius_m, 0.5 * calib.target_height_m, calib.target_radius_m])
    return SpeckleTexture(seed, session_index, centre - extent, centre + extent, calib.speckle_size_m,
                          calib.speckle_albedo)


def marker_layout(calib: CalibrationConfig, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ball centres of the marker frame: (true (M, 3), surveyed (M, 3)) metres, stage frame.

    True positions: uniform in the ball of radius ``marker_volume_radius_m`` round `centre`, at least
    ``marker_min_separation_m`` apart (rejection sampling keyed by ``marker_seed``: a property of the
    physical frame). Surveyed = true + N(0, ``marker_survey_error_mm``) per axis (what rig.json publishes).
    """
    rng = np.random.default_rng([calib.marker_seed, _MARKER_LAYOUT])
    radius, gap = calib.marker_volume_radius_m, calib.marker_min_separation_m
    accepted = np.zeros((0, 3))
    for _ in range(200):
        candidates = rng.uniform(-radius, radius, size=(4 * calib.marker_count, 3))
        candidates = candidates[np.einsum("ij,ij->i", candidates, candidates) <= radius * radius]
        for point in candidates:
            if len(accepted) == calib.marker_count:
                break
            if len(accepted) == 0 or np.min(np.linalg.norm(accepted - point, axis=1)) >= gap:
                accepted = np.vstack([accepted, point])
        if len(accepted) == calib.marker_count:
            break
    else:
        raise ValueError(f"CalibrationConfig: {calib.marker_count} balls {gap} m apart do not fit in a ball of "
                         f"radius {radius} m")
    true = accepted + np.asarray(centre, np.float64)
    survey = np.random.default_rng([calib.marker_seed, _MARKER_SURVEY]).normal(
        0.0, calib.marker_survey_error_mm / 1000.0, size=true.shape)
    return true, true + survey


def irradiance_quadratic(leds: LedSphere, n_normals: int = 2048) -> np.ndarray:
    """Full_on irradiance of an unoccluded surface as a quadratic form in its normal: (3, 10) coefficients
    of [1, x, y, z, xy, yz, xz, x^2, y^2, z^2] per RGB channel, least-squares fitted on `n_normals` normals
    (degree-2 spherical harmonics, which hold ~99% of a cosine-lobe irradiance)."""
    from .geometry import fibonacci_sphere

    normals = fibonacci_sphere(n_normals)
    exact = np.maximum(normals @ leds.directions.T.astype(np.float64), 0.0) @ leds.irradiance[:, 0:3].astype(np.float64)
    coefficients, *_ = np.linalg.lstsq(_quadratic_basis(normals), exact, rcond=None)
    return coefficients.T


def _quadratic_basis(n: np.ndarray) -> np.ndarray:
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    return np.column_stack([np.ones_like(x), x, y, z, x * y, y * z, x * z, x * x, y * y, z * z])


def render_markers(camera: Camera, leds: LedSphere, background: np.ndarray, positions: np.ndarray, radius: float,
                   albedo: float, supersample: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """full_on radiance (H, W, 3) float32 of the marker balls (Lambertian, centres `positions` (M, 3)) in front
    of the stage background, and each pixel's ball coverage (H, W) float32 in [0, 1].

    Ray-traced exactly on a `supersample` x `supersample` grid of sub-pixel rays (pixel centres at integer
    coordinates) in a window round each ball, nearest hit wins (z-buffer at sub-pixel resolution); shading
    from :func:`irradiance_quadratic`; no shadows between balls (they are small and far apart)."""
    H, W, S = camera.height, camera.width, int(supersample)
    K, R, t = camera.K, camera.cam_from_world[:, :3], camera.cam_from_world[:, 3]
    origin = camera.centre_world
    local = positions @ R.T + t
    z = local[:, 2]
    keep = z > radius + 0.05
    u0 = K[0, 0] * local[:, 0] / np.where(keep, z, 1.0) + K[0, 2]
    v0 = K[1, 1] * local[:, 1] / np.where(keep, z, 1.0) + K[1, 2]
    # window half-size: apparent radius (off-axis balls image as slightly elongated ellipses) + 2 px
    apparent = max(K[0, 0], K[1, 1]) * radius / np.sqrt(np.maximum(z * z - radius * radius, 1e-12))
    half = np.ceil(1.4 * apparent + 2.0).astype(np.int64)
    keep &= (u0 + half >= 0) & (u0 - half <= W - 1) & (v0 + half >= 0) & (v0 - half <= H - 1)
    sub_index, sub_depth, sub_marker = [], [], []
    for h in np.unique(half[keep]):
        ids = np.nonzero(keep & (half == h))[0]
        side = (2 * h + 1) * S
        grid = (np.arange(side) + 0.5) / S - 0.5 - h                # sub-pixel offsets from the window centre
        ui = np.rint(u0[ids])[:, None, None] + grid[None, None, :]   # (m, 1, side)
        vi = np.rint(v0[ids])[:, None, None] + grid[None, :, None]   # (m, side, 1)
        ui, vi = np.broadcast_arrays(ui, vi)
        dirs = np.stack([(ui - K[0, 2]) / K[0, 0], (vi - K[1, 2]) / K[1, 1], np.ones_like(ui)], axis=-1) @ R
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        oc = (origin - positions[ids])[:, None, None, :]
        b = np.einsum("mijk,mijk->mij", dirs, np.broadcast_to(oc, dirs.shape))
        disc = b * b - (np.einsum("mijk,mijk->mij", oc, oc) - radius * radius)
        depth = -b - np.sqrt(np.maximum(disc, 0.0))
        su = np.floor((ui + 0.5) * S).astype(np.int64)              # sub-pixel column index
        sv = np.floor((vi + 0.5) * S).astype(np.int64)
        hit = (disc > 0) & (depth > 0) & (su >= 0) & (su < W * S) & (sv >= 0) & (sv < H * S)
        sub_index.append(sv[hit] * (W * S) + su[hit])
        sub_depth.append(depth[hit])
        sub_marker.append(np.broadcast_to(ids[:, None, None], hit.shape)[hit])
    radiance = shading.render_background(camera, leds, background)[..., 0:3].reshape(-1, 3).astype(np.float64)
    coverage = np.zeros(H * W)
    if sub_index:
        index, depth, marker = (np.concatenate(a) for a in (sub_index, sub_depth, sub_marker))
        order = np.lexsort((depth, index))                          # nearest hit first per sub-pixel
        index, depth, marker = index[order], depth[order], marker[order]
        first = np.r_[True, index[1:] != index[:-1]]
        index, depth, marker = index[first], depth[first], marker[first]
        su, sv = index % (W * S), index // (W * S)
        d_cam = np.stack([((su + 0.5) / S - 0.5 - K[0, 2]) / K[0, 0], ((sv + 0.5) / S - 0.5 - K[1, 2]) / K[1, 1],
                          np.ones(len(su))], axis=-1) @ R
        d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
        normals = (origin + depth[:, None] * d_cam - positions[marker]) / radius
        shade = _quadratic_basis(normals) @ irradiance_quadratic(leds).T * (albedo / np.pi)   # (n, 3)
        pixel = (sv // S) * W + su // S
        coverage = np.bincount(pixel, minlength=H * W) / float(S * S)
        colour = np.stack([np.bincount(pixel, weights=shade[:, c], minlength=H * W) for c in range(3)], 1) / (S * S)
        radiance = radiance * (1.0 - coverage)[:, None] + colour
    return (radiance.reshape(H, W, 3).astype(np.float32), coverage.reshape(H, W).astype(np.float32))


def calibration_objects(centre: np.ndarray, calib: CalibrationConfig) -> dict:
    """The rig.json entry of the calibration objects."""
    objects = {"sphere": {"centre": [round(float(v), 6) for v in centre], "radius_m": calib.sphere_radius_m,
                          "albedo": calib.sphere_albedo, "frames": "calibration/sphere/{full_on,pos,neg}/<cam>.dng"}}
    if calib.target:
        objects["target"] = {"kind": "speckled upright cylinder with caps", "centre": [round(float(v), 6) for v in centre],
                             "radius_m": calib.target_radius_m, "height_m": calib.target_height_m,
                             "speckle_size_m": calib.speckle_size_m, "albedo": list(calib.speckle_albedo),
                             "frames": "calibration/cameras/<cam>.dng", "illumination": "full_on"}
    if calib.markers:
        _, surveyed = marker_layout(calib, centre)
        objects["markers"] = {"kind": "white Lambertian balls on a rigid frame (thin dark rods)",
                              "radius_m": calib.marker_radius_m, "albedo": calib.marker_albedo,
                              "survey_error_mm": calib.marker_survey_error_mm,
                              "frames": "calibration/markers/<cam>.dng", "illumination": "full_on",
                              "positions": np.round(surveyed, 7).tolist()}
    return objects


def write_session_calibration(out: Path, seed: int, noise: bool, full_well_e: float, read_noise_dn: float,
                              calib: CalibrationConfig, session, responses: np.ndarray, centre: np.ndarray) -> None:
    """Write one session's chart and sphere frames, chart.json and ground_truth/calibration/<sid>.json.

    `session`: a synthetic.simulate.Session; responses: (n_cameras, 3, 3); centre: sphere centre (3,).
    """
    cam_from_xyz, neutral = sensor.nikon_cam_from_xyz(), sensor.as_shot_neutral()
    folder = out / "sessions" / session.session_id / "calibration"
    names, reference = reference_chart_srgb()
    chart_cameras = {}
    texture = target_texture(seed, session.index, centre, calib) if calib.target else None
    markers_true = marker_layout(calib, centre)[0] if calib.markers else None
    for cam_index, (camera, gain) in enumerate(zip(session.cameras, session.gains)):
        background = session.backgrounds[cam_index]

        def write(radiance: np.ndarray, path: Path, stream: int) -> None:
            rng = (np.random.default_rng([seed, _CALIB_NOISE, session.index, cam_index, stream])
                   if noise else None)
            raw = sensor.raw_frame(as_seen(radiance, responses[cam_index]), gain, rng, full_well_e, read_noise_dn)
            files.write_dng(path, raw, cam_from_xyz, neutral)

        if calib.chart:
            labels, card, boxes = chart_layout(camera.width, camera.height, calib.chart_width_fraction)
            write(render_chart(camera, session.leds, background, labels), folder / "chart" / f"{camera.camera_id}.dng", 0)
            chart_cameras[camera.camera_id] = {"frame": f"calibration/chart/{camera.camera_id}.dng",
                                               "card_box": card.tolist(), "patch_boxes": boxes}
        if calib.sphere:
            radiance, _ = render_sphere(camera, session.leds, background, centre, calib.sphere_radius_m,
                                        calib.sphere_albedo)
            for illum_index, illumination in enumerate(("full_on", "pos", "neg")):
                write(radiance[..., 3 * illum_index:3 * illum_index + 3],
                      folder / "sphere" / illumination / f"{camera.camera_id}.dng", 1 + illum_index)
        if calib.target:
            radiance, _ = render_target(camera, session.leds, background, centre, calib, texture)
            write(radiance, folder / "cameras" / f"{camera.camera_id}.dng", 4)
        if calib.markers:
            radiance, _ = render_markers(camera, session.leds, background, markers_true, calib.marker_radius_m,
                                         calib.marker_albedo, calib.marker_supersample)
            write(radiance, folder / "markers" / f"{camera.camera_id}.dng", 5)
    if calib.chart:
        files.write_json(folder / "chart.json", {
            "format": CHART_FORMAT, "chart": REFERENCE_CHART, "illumination": "full_on",
            "reference_space": "linear sRGB (D65), Bradford-adapted from the chart's D50 xyY (colour-science)",
            "patch_names": list(names), "reference_linear_srgb": np.round(reference, 6).tolist(),
            "box_convention": "[x0, y0, x1, y1] pixel indices, end exclusive, reading order; shrink by ~2 px "
                              "for demosaicing blur",
            "target": "a patch's decoded linear value should be white_reference * reference_linear_srgb "
                      "(per channel; white_reference from rig.json)",
            "cameras": chart_cameras})
    truth = {"format": CALIBRATION_TRUTH_FORMAT, "session_id": session.session_id,
             "colour_error": calib.colour_error,
             "colour_model": "decoded = gain * response @ radiance (linear sRGB); correction = inv(response)",
             "cameras": {cam.camera_id: {"response": np.round(r, 8).tolist(),
                                         "correction": np.round(np.linalg.inv(r), 8).tolist()}
                         for cam, r in zip(session.cameras, responses)},
             "sphere": {"centre": centre.tolist(), "radius_m": calib.sphere_radius_m, "albedo": calib.sphere_albedo},
             "chart": {"card_albedo": CARD_ALBEDO}}
    if calib.markers:
        truth["markers"] = {"radius_m": calib.marker_radius_m, "true_positions": markers_true.tolist()}
    files.write_json(out / "ground_truth" / "calibration" / f"{session.session_id}.json", truth)
