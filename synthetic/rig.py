"""The rig: 32 portrait Nikon D750 cameras on four rings, and the LED sphere with its illuminations.

Cameras (modelled on UltraStage): four rings of 8 at elevations -18, 2, 22 and 48 degrees round the
subject, azimuths staggered between rings, zoom focal lengths 35, 50, 40 and 28 mm. Each camera looks at
the subject's centre from the distance at which the subject's bounding cylinder (yaw invariant, so every
action fits) fills the frame up to a 6% margin. Intrinsics follow from focal length and the 24 x 35.9 mm
portrait sensor scaled to the image size; principal points are offset by up to 1% of the width; no
distortion. Later sessions perturb every pose slightly (re-mounted cameras).

LEDs: `n_leds` Fibonacci directions, treated as distant directional lights. Each LED has per-channel
intensity errors (1 + led_error * N(0, 1)) fixed per session. LED l contributes irradiance
``I(l) * 4 pi / n_leds`` to a surface facing it, so an unoccluded white Lambertian under ideal full_on
has radiance 1 (exactly in the continuous limit; the mean over normals is exactly the mean LED intensity).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometry

SENSOR_MM = (24.0, 35.9)          # portrait: width x height
SENSOR_PIXELS = (4016, 6016)
RING_ELEVATIONS_DEG = (-18.0, 2.0, 22.0, 48.0)
RING_FOCALS_MM = (35.0, 50.0, 40.0, 28.0)
FRAME_MARGIN = 0.06
NOMINAL_EXPOSURE_S = 0.01
ILLUMINATIONS = ("full_on", "pos", "neg")


@dataclass(frozen=True)
class Camera:
    """One camera: OpenCV intrinsics K (3, 3), cam_from_world (3, 4), image size, lens and exposure."""
    camera_id: str
    width: int
    height: int
    K: np.ndarray
    cam_from_world: np.ndarray
    focal_mm: float
    exposure_s: float

    @property
    def centre_world(self) -> np.ndarray:
        rotation, translation = self.cam_from_world[:, :3], self.cam_from_world[:, 3]
        return -rotation.T @ translation

    def to_json(self, white_reference: np.ndarray) -> dict:
        return {"camera_id": self.camera_id, "width": self.width, "height": self.height,
                "K": self.K.tolist(), "dist": [0.0] * 5, "cam_from_world": self.cam_from_world.tolist(),
                "focal_mm": round(self.focal_mm, 4), "sensor_mm": list(SENSOR_MM),
                "exposure_s": round(self.exposure_s, 8),
                "white_reference": [float(v) for v in white_reference]}


def look_at(centre: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 1.0, 0.0])) -> np.ndarray:
    """cam_from_world (3, 4) of an OpenCV camera at `centre` looking at `target` with world `up` up."""
    forward = geometry.normalize(target - centre)
    right = geometry.normalize(np.cross(forward, up))
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    return np.column_stack([rotation, -rotation @ centre])


def intrinsics(focal_mm: float, width: int, height: int, principal_offset_px: tuple[float, float]) -> np.ndarray:
    """K (3, 3) of the portrait sensor scaled to width x height (pixel centres at integer coordinates)."""
    fx = focal_mm * width / SENSOR_MM[0]
    fy = focal_mm * height / SENSOR_MM[1]
    cx = (width - 1) / 2.0 + principal_offset_px[0]
    cy = (height - 1) / 2.0 + principal_offset_px[1]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def project(K: np.ndarray, cam_from_world: np.ndarray, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) and camera depths (N,) of world points (N, 3)."""
    cam = points_world @ cam_from_world[:, :3].T + cam_from_world[:, 3]
    uv = cam[:, :2] / cam[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    return uv, cam[:, 2]


def bounding_cylinder_points(radius: float, y_range: tuple[float, float], n: int = 48) -> np.ndarray:
    """Points (3n, 3) on the rims and middle circle of a vertical cylinder about the y axis."""
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rims = [np.column_stack([radius * np.cos(angles), np.full(n, y), radius * np.sin(angles)])
            for y in (y_range[0], 0.5 * sum(y_range), y_range[1])]
    return np.concatenate(rims)


def fit_distance(direction: np.ndarray, target: np.ndarray, K: np.ndarray, width: int, height: int,
                 bound_points: np.ndarray, margin: float = FRAME_MARGIN) -> float:
    """Smallest camera distance along `direction` from `target` at which all bound points project
    inside the frame shrunk by `margin` on each side (bisection)."""
    lo_u, hi_u = margin * width, (1 - margin) * width - 1
    lo_v, hi_v = margin * height, (1 - margin) * height - 1

    def fits(distance: float) -> bool:
        cam_from_world = look_at(target + distance * direction, target)
        uv, depth = project(K, cam_from_world, bound_points)
        return bool(np.all(depth > 0.05) and np.all((uv[:, 0] >= lo_u) & (uv[:, 0] <= hi_u)
                                                    & (uv[:, 1] >= lo_v) & (uv[:, 1] <= hi_v)))

    near, far = 0.1, 50.0
    if not fits(far):
        raise ValueError("subject does not fit in the frame even from 50 m")
    for _ in range(40):
        mid = 0.5 * (near + far)
        near, far = (near, mid) if fits(mid) else (mid, far)
    return far


def make_cameras(n_cameras: int, width: int, height: int, radius_xz: float, y_range: tuple[float, float],
                 rng: np.random.Generator, session_rng: np.random.Generator | None = None) -> list[Camera]:
    """The camera rig (see module docstring). `rng` draws the nominal rig, `session_rng` (None for the
    first session) a small per-session perturbation: ~0.5 deg of orientation and ~5 mm of position."""
    target = np.array([0.0, 0.5 * (y_range[0] + y_range[1]), 0.0])
    bound = bounding_cylinder_points(radius_xz, y_range)
    n_rings = len(RING_ELEVATIONS_DEG)
    cameras = []
    for index in range(n_cameras):
        ring = index % n_rings
        slot = index // n_rings
        per_ring = (n_cameras - ring + n_rings - 1) // n_rings
        azimuth = np.deg2rad(360.0 * slot / per_ring + 90.0 * ring / n_rings + rng.uniform(-3, 3))
        elevation = np.deg2rad(RING_ELEVATIONS_DEG[ring] + rng.uniform(-2, 2))
        focal = RING_FOCALS_MM[ring] * float(rng.uniform(0.97, 1.03))
        offset = (float(rng.uniform(-0.01, 0.01) * width), float(rng.uniform(-0.01, 0.01) * width))
        K = intrinsics(focal, width, height, offset)
        direction = np.array([np.sin(azimuth) * np.cos(elevation), np.sin(elevation),
                              np.cos(azimuth) * np.cos(elevation)])
        distance = fit_distance(direction, target, K, width, height, bound)
        cam_from_world = look_at(target + distance * direction, target)
        exposure = NOMINAL_EXPOSURE_S * float(rng.uniform(0.92, 1.08))
        if session_rng is not None:
            cam_from_world = perturb_pose(cam_from_world, session_rng)
        cameras.append(Camera(f"{index:05d}", width, height, K, cam_from_world, focal, exposure))
    return cameras


def perturb_pose(cam_from_world: np.ndarray, rng: np.random.Generator, angle_deg: float = 0.5,
                 shift_m: float = 0.005) -> np.ndarray:
    """cam_from_world (3, 4) rotated by a small random rotation and its centre shifted."""
    axis = geometry.normalize(rng.normal(size=3))
    angle = np.deg2rad(rng.normal(0, angle_deg))
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    delta = np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew
    rotation = delta @ cam_from_world[:, :3]
    centre = -cam_from_world[:, :3].T @ cam_from_world[:, 3] + rng.normal(0, shift_m, 3)
    return np.column_stack([rotation, -rotation @ centre])


@dataclass(frozen=True)
class LedSphere:
    """LED directions (L, 3), per-LED per-channel gains (L, 3) and the derived illumination table.

    `irradiance` (L, 9): per-LED irradiance contribution for full_on RGB, pos RGB, neg RGB (in that
    order), i.e. nominal emitter intensity x gain x solid angle 4 pi / L, linear sRGB.
    """
    directions: np.ndarray
    gains: np.ndarray
    radius_m: float

    @property
    def count(self) -> int:
        return len(self.directions)

    @property
    def solid_angle(self) -> float:
        return 4.0 * np.pi / self.count

    @property
    def intensities(self) -> np.ndarray:
        """(L, 9) emitter intensities: full_on (1,1,1), pos (1+w)/2, neg (1-w)/2, times the gains."""
        return led_intensities(self.directions, self.gains)

    @property
    def irradiance(self) -> np.ndarray:
        return (self.intensities * self.solid_angle).astype(np.float32)

    def white_radiance(self) -> np.ndarray:
        """(3,) radiance of an albedo-1 unoccluded Lambertian under full_on, averaged over normals:
        (1/pi) sum_l mean_n max(0, n.w_l) I_l 4pi/L = mean_l I_l (mean_n max(0, n.w) = 1/4)."""
        return self.intensities[:, 0:3].mean(axis=0)

    def mean_intensity(self) -> np.ndarray:
        """(9,) mean emitter intensity per illumination channel (drives the dim background)."""
        return self.intensities.mean(axis=0)


def led_intensities(directions: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """(L, 9) emitter intensities of full_on, pos, neg (RGB each) for directions (L, 3), gains (L, 3)."""
    full_on = np.ones_like(directions)
    pos = 0.5 * (1.0 + directions)
    neg = 0.5 * (1.0 - directions)
    return np.concatenate([full_on * gains, pos * gains, neg * gains], axis=1)


def make_leds(n_leds: int, led_error: float, radius_m: float, rng: np.random.Generator) -> LedSphere:
    """Fibonacci LED sphere with per-LED, per-channel gains 1 + led_error * N(0, 1) (clipped >= 0.05)."""
    directions = geometry.fibonacci_sphere(n_leds)
    gains = np.clip(1.0 + led_error * rng.normal(size=(n_leds, 3)), 0.05, None)
    return LedSphere(directions, gains, radius_m)
