"""Action stage ``photometric``: normals by eq. 1, validity alpha, albedo and mask, one task per camera.

Wiring only: the numerics are :func:`stages.numerics.photometric.photometric_maps`. The normals with the
specular reflection fitted out are the ``diffuse_normals`` stage's (:mod:`stages.diffuse_normals`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.exr import write_exr
from pipeline.codecs.image import preview_linear, preview_normals, write_png
from pipeline.config import Documented, checked
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from artifacts.facade import ActionArtifacts
from artifacts.layout import ArtifactWriter, released_files
from artifacts.camera import Camera
from stages.numerics.denoise import DenoiseConfig, joint_bilateral
from stages.exr_headers import EXR_HEADERS
from stages.numerics.photometric import (PhotometricParams, corrected_normals, facing_away_fraction,
                                         normals_with_alpha, photometric_maps)
from stages.numerics.specular_normals import view_directions
from stages.previews import write_normal_sheet


RELEASED = ("normal_alpha", "albedo", "mask", "normals_sheet")
"""The products this stage publishes, in order: the per-camera maps and the normals' contact sheet (when the
previews are on; the per-camera previews stay in the work store)."""


@dataclass(frozen=True)
class PhotometricConfig(Documented):
    params: PhotometricParams = field(default_factory=PhotometricParams)
    """Thresholds of the validity alpha and the mask (see PhotometricParams)."""
    use_clean_plate: bool = True
    """Segment the foreground against the session's clean plate when one exists (else a threshold)."""
    previews: bool = True
    """Write PNG previews (normals, albedo, mask) and a contact sheet per action."""
    light_iterations: int = checked(4, ge=0)
    """Gauss-Newton iterations when inverting the session's fitted LED ratio model (0: the normalised ratios
    as they are)."""
    denoise: DenoiseConfig = field(default_factory=DenoiseConfig)
    """Edge-preserving denoising of the albedo maps (and of ``normal_alpha`` when asked)."""


SWAPPED_FACING_AWAY = 0.5
"""A camera's g+/g- frames are taken as swapped when more than this fraction of its valid pixels get eq. 1
normals facing away from it (correct frames of the simulator: 0.7-2%; swapped: 98-99%)."""
SWAPPED_MIN_PIXELS = 50
"""Fewer valid pixels than this are too little evidence to call a pair swapped."""


def check_gradients_not_swapped(ctx: StageContext, view: str, cam: Camera, maps: Any) -> float:
    """The fraction of valid pixels whose eq. 1 normal faces away from the camera; raises InputError naming the
    camera's raw g+ and g- files when that says the two were swapped (over :data:`SWAPPED_FACING_AWAY`)."""
    h, w = maps.alpha.shape
    valid = (maps.alpha > 0.5) & maps.mask
    away, count = facing_away_fraction(maps.normals, view_directions(cam.K, cam.cam_from_world, h, w), valid)
    if count >= SWAPPED_MIN_PIXELS and away > SWAPPED_FACING_AWAY:
        action = ctx.capture_root / "actions" / str(ctx.action_id)
        if not action.is_dir():  # the public release layout: the action folder is the capture or one inside it
            action = next((p for p in (ctx.capture_root / str(ctx.action_id), ctx.capture_root)
                           if (p / "pos").is_dir()), action)
        pos, neg = (next(iter(sorted((action / i).glob(f"{view}.*"))), action / i / f"{view}.*") for i in ("pos", "neg"))
        raise InputError(pos, f"g+ and g- frames of camera {view} look swapped (with {neg.name} of 'neg'): eq. 1 "
                              f"normals face away from the camera on {100 * away:.0f}% of its {count} valid pixels")
    return away



def shipped_mask(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool mask of a capture's own mask photo at the decoded frames' size ``shape`` (a half-size decode
    takes the 2x2 blocks more than half covered); raises InputError naming the file for any other size."""
    from pipeline.codecs.srgb8 import read_mask8

    mask = read_mask8(path)
    if mask.shape == tuple(shape):
        return mask
    h, w = shape
    if (mask.shape[0] + 1) // 2 == h and (mask.shape[1] + 1) // 2 == w:
        padded = np.pad(mask, ((0, mask.shape[0] % 2), (0, mask.shape[1] % 2)), mode="edge").astype(np.float32)
        return (padded[0::2, 0::2] + padded[1::2, 0::2] + padded[0::2, 1::2] + padded[1::2, 1::2]) > 2.0
    raise InputError(path, f"mask is {mask.shape[1]} x {mask.shape[0]} pixels but the camera's images are {w} x {h}: "
                           "images of different sizes")


class PhotometricStage(Stage):
    name = "photometric"
    # 7: the normal sheet's tiles are labelled with their camera ids
    version = "7"
    scope = "action"
    requires = ("decode", "plates", "lights")
    outputs = ("normal_alpha", "albedo", "mask", "previews")
    per_view = True

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        """The masks a capture ships (the public release layout's ``mask/``; a raw capture has none)."""
        shipped = getattr(capture, "mask_paths", None)
        return {f"mask/{cam}": path for cam, path in shipped(scope_id).items()} if shipped is not None else {}

    def run_view(self, ctx: StageContext, view: str) -> dict[str, Any]:
        upstream = ActionArtifacts(ctx.upstream)
        cameras = upstream.calibrated_cameras()
        if view not in cameras:
            return {"missing": "camera has no calibration"}
        cam = cameras[view]
        full_on, pos, neg = (upstream.exr(illumination, view) for illumination in ("full_on", "pos", "neg"))
        clipped = upstream.png("clipped", view) > 0
        background = upstream.plate(view) if self.config.use_clean_plate else None
        shipped = ctx.raw_inputs.get(f"mask/{view}")
        given = shipped_mask(shipped, full_on.shape[:2]) if shipped is not None else None
        maps = photometric_maps(full_on, pos, neg, clipped, np.asarray(cam.record["white_reference"], np.float32),
                                background=background, params=self.config.params, mask=given)
        facing_away = check_gradients_not_swapped(ctx, view, cam, maps)
        model = upstream.light_model()
        defined = np.any(maps.normals != 0, axis=-1)
        if model is not None:  # the session's LEDs were calibrated: invert their ratio model
            maps.normals[...] = corrected_normals(pos, neg, model, defined, self.config.light_iterations)
        mask = maps.mask
        valid = (maps.alpha > 0.5) & mask
        albedo, normals = maps.albedo, maps.normals
        den = self.config.denoise
        if den.enabled:
            albedo, filtered = joint_bilateral(albedo, [normals] if den.normal_alpha else [], valid,
                                               den.spatial_sigma_px, den.range_sigma, den.radius)
            if den.normal_alpha:
                normals = filtered[0]
        out = ArtifactWriter(self.name, ctx.out_dir)
        write_exr(out.path("normal_alpha", view), normals_with_alpha(normals, maps.alpha),
                  header=EXR_HEADERS["normal_alpha"])
        write_exr(out.path("albedo", view), albedo, header=EXR_HEADERS["albedo"])
        write_png(out.path("mask", view), maps.mask)
        if self.config.previews:
            write_png(out.path("normal_preview", view), preview_normals(normals, maps.alpha))
            write_png(out.path("albedo_preview", view), preview_linear(albedo, exposure=1.0))
        return {"mask_fraction": float(mask.mean()), "facing_away_fraction": facing_away,
                "valid_fraction": float(valid.sum() / max(int(mask.sum()), 1)),
                "ratio_norm_median": float(np.median(maps.ratio_norm[valid])) if valid.any() else 0.0,
                "plate": background is not None}

    def finalize(self, ctx: StageContext, view_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
        if self.config.previews:
            write_normal_sheet(ArtifactWriter(self.name, ctx.out_dir), "normal_preview", "normals_sheet", view_stats)
        fractions = [s["valid_fraction"] for s in view_stats.values() if "valid_fraction" in s]
        return {"views": view_stats, "valid_fraction": float(np.mean(fractions)) if fractions else 0.0}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        return released_files(self.name, artifact, RELEASED, optional=("normals_sheet",))
