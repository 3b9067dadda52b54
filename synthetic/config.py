"""Configuration of the light-stage simulator."""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from pipeline.config import Documented, broken, checked


@dataclass(frozen=True)
class SimConfig(Documented):
    """What `synthetic.simulate` renders: subject, rig, lighting, sensor and output options."""

    actions: int = checked(2, ge=1)
    """Number of actions (poses) to render; each gets its own skin, yaw, cloth pattern and folds (and
    joint angles when pose_variation > 0)."""
    width: int = checked(320, ge=16)
    """Image width in pixels. Height is `width * 6016 / 4016` rounded to an even number: the D750s are
    mounted in portrait, so the 24 x 35.9 mm sensor is 24 mm wide and 35.9 mm tall."""
    seed: int = 0
    """Seed of every random choice (rig jitter, LED errors, subject variations, sensor noise)."""
    mesh: str | None = None
    """Subject OBJ path. None: `../shared/data/meshes/makehuman_base.obj` beside the repository when it
    exists, else the procedural subject. "procedural" forces the procedural subject. An OBJ with a
    MakeHuman `body` group gets skins, clothes and folds; any other OBJ, or a PLY / glTF / GLB / STL / OFF
    file (read with trimesh), gets a procedural albedo."""
    pose_variation: float = checked(0.0, ge=0.0, le=1.0)
    """How far each action's pose departs from the rest A-pose, in [0, 1]: every joint angle (neck turn /
    bend / tilt, shoulders, elbows, hips, knees; synthetic.pose.POSE_RANGES_DEG) is this times a uniform
    draw in its range, keyed by (seed, action index). 0 renders the rest pose exactly (the same files as
    without posing). Only subjects with a skeleton are posed: the MakeHuman body (its joint groups); the
    procedural subject and other meshes stay in their rest pose."""
    body: str | None = None
    """MakeHuman body shape (synthetic.body: MakeHuman's macro targets), MakeHuman subject only. None: the
    base mesh as it is. ``"random"``: every action draws gender, age (25..90 years), muscle, weight, height
    and an ethnic blend (african / asian / caucasian) from (seed, action index). ``"gender=0.2,weight=0.9"``:
    those values for every action, the others at MakeHuman's defaults (0.5, an even ethnic blend);
    ``"random,height=0.7"``: drawn, but for the values given. Each is in [0, 1] (age >= 0.5, MakeHuman's
    slider: 0.5 = 25 years, 1 = 90). The shape goes on before the pose; the ground truth follows it."""
    hair: float = checked(0.0, ge=0.0, le=1.0)
    """Fraction of the actions (each drawn from (seed, action index)) whose subject has a hair volume
    (synthetic.garments: its own region and material, darker and rougher than skin; MakeHuman subject only).
    0: none (the capture is the same as without the option)."""
    garment: float = checked(0.0, ge=0.0, le=1.0)
    """Fraction of the actions (each drawn from (seed, action index)) whose subject wears a loose skirt over
    the trousers (synthetic.garments: a thin closed shell off the legs' surface, its own region and
    material; MakeHuman subject only). 0: none."""
    n_leds: int = checked(512, ge=16)
    """Number of LEDs on the sphere (Fibonacci directions)."""
    led_error: float = checked(0.03, ge=0.0)
    """Relative standard deviation of the per-LED, per-channel intensity errors (fixed per session)."""
    noise: bool = True
    """Add shot and read noise to the raw frames."""
    sessions: int = checked(1, ge=1, le="actions")
    """Number of capture sessions; actions are split into contiguous blocks, one per session. Each
    session has its own slightly perturbed rig, LED errors and clean plates."""
    background: bool = True
    """Write clean plates (`sessions/<sid>/background/<cam>.dng`, full_on, no subject)."""
    n_cameras: int = checked(32, ge=1, le=99999)
    """Number of cameras. The stage has 32; tests use fewer. Cameras are spread over four rings."""
    specular: bool = True
    """Render the GGX specular lobe. False gives a purely Lambertian subject (physics tests)."""
    specular_led_clusters: bool = False
    """Evaluate the specular lobe against LED direction clusters sized to the lobe width instead of every
    LED (~40% faster per camera, ~1.7% RMS radiance error; see synthetic.shading)."""
    fold_amplitude_m: float = checked(0.004, ge=0.0)
    """Peak displacement of the cloth folds along the normal, metres (0 disables folds)."""
    subdivisions: int = checked(1, ge=0, le=3)
    """Loop subdivision steps applied to a mesh subject before the folds are displaced."""
    led_radius_m: float = 1.6
    """Radius of the LED sphere, metres (lights are treated as distant: the sphere is much larger
    than the subject)."""
    full_well_e: float = checked(40000.0, gt=0.0)
    """Electrons at the raw clip level; shot-noise variance of a normalised raw value s is s / full_well_e."""
    read_noise_dn: float = checked(2.5, ge=0.0)
    """Standard deviation of the Gaussian read noise in 14-bit digital numbers."""
    spec_shift_mm: float = checked(3.0, ge=0.0)
    """Standard deviation of the difference between each camera's true centre and the rig spec's
    nominal one, per axis, millimetres (mounting tolerance; 0 = the rig spec is exact)."""
    spec_angle_deg: float = checked(0.2, ge=0.0)
    """Standard deviation of the angle between each camera's true and nominal orientation, degrees."""
    spec_focal_pct: float = checked(0.5, ge=0.0)
    """Standard deviation of the nominal focal length's error, percent."""
    supersample: int = checked(2, ge=1, le=8)
    """Rays per pixel side: each pixel averages s x s rays over its square, as a sensor pixel integrates the
    light over its area (1 = one ray through the pixel centre, which aliases detail finer than a pixel
    and gives silhouette pixels that are all subject or all stage). The ground-truth maps are the same
    pixel averages (synthetic.shading.render_view)."""
    exposure_target: float = checked(0.5, gt=0.0, lt=0.9)
    """Normalised green raw value of an albedo-1 unoccluded Lambertian under full_on (per-camera
    exposures jitter by +-8% around it)."""

    @property
    def height(self) -> int:
        """Image height in pixels (portrait D750 aspect, rounded to even)."""
        return image_height(self.width)

    def _checks(self) -> list[str]:
        if self.body is None:
            return []
        from .body import body_from_spec

        try:
            body_from_spec(self.body, np.random.default_rng(0))
        except ValueError as exc:
            return [broken(self, "body", str(exc))]
        return []

    def to_json(self) -> dict[str, Any]:
        """The config as a JSON-ready dict (for capture.json). The subject options added with body shapes
        (``OPTIONAL_FIELDS``) are left out while they are at their defaults, so a capture without them has
        the capture.json it had before them."""
        record = asdict(self)
        for name, default in OPTIONAL_FIELDS.items():
            if record[name] == default:
                del record[name]
        return record


OPTIONAL_FIELDS = {"body": None, "hair": 0.0, "garment": 0.0}
"""Fields SimConfig.to_json leaves out at these (default) values."""


def image_height(width: int) -> int:
    """Height of a portrait D750 frame (6016 x 4016 sensor pixels) of the given width, rounded to even."""
    return int(2 * round(width * 6016 / 4016 / 2))
