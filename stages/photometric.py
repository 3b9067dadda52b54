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
from pipeline.codecs.image import label_picture, preview_linear, preview_normals, read_png, write_png
from pipeline.config import Documented, checked
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from stages.artifacts import ActionArtifacts
from stages.layout import ArtifactWriter
from stages.numerics.camera import Camera
from stages.numerics.denoise import joint_bilateral
from stages.exr_headers import EXR_HEADERS
from stages.numerics.photometric import (PhotometricParams, corrected_normals, facing_away_fraction,
                                         normals_with_alpha, photometric_maps)
from stages.numerics.specular_normals import SOLVERS, fit_diffuse_normals, view_directions


@dataclass(frozen=True)
class SpecularConfig(Documented):
    """The per-pixel fit of the normals with the specular reflection fitted out
    (stages/numerics/specular_normals.py): each pixel's normal fitted as Lambertian plus GGX reflection instead
    of eq. 1's ratio alone: a lower mean error against the simulator's normals over valid pixels, also on a
    subject the roughness prior was not chosen on (bench/bench_specular_normals.py measures it there)."""

    roughness: float = checked(0.6, gt=0.0, le=1.0)
    """Perceptual GGX roughness assumed for every pixel the materials' roughness does not reach (a prior: one
    pixel cannot also pin it down)."""
    f0: float = checked(0.04, ge=0.0, le=1.0)
    """Schlick Fresnel reflectance at normal incidence assumed (dielectrics: 0.02-0.05)."""
    solver: str = checked("levenberg_marquardt", one_of=SOLVERS)
    """``levenberg_marquardt`` or ``adam``. On the default capture 6 Levenberg-Marquardt steps reach the
    error against the simulator's normals that 40 Adam steps do, in about a third of the time."""
    steps: int = checked(6, ge=0)
    """Iterations of the per-pixel fit per start (Adam needs about 40)."""
    lr: float = checked(0.03, gt=0.0)
    """Adam's step size (``solver: adam`` only)."""


@dataclass(frozen=True)
class DenoiseConfig(Documented):
    """Edge-preserving denoising of the albedo and normal maps (stages/numerics/denoise.py)."""

    enabled: bool = True
    """Filter the albedo maps (and the diffuse_normals stage's ``normal_diffuse``, with its own copy of this
    config) with a joint bilateral filter guided by the albedo, over valid pixels only. Chosen against the
    simulator's truth, not the held-out protocol: on the default capture the albedo and ``normal_diffuse``
    come closer to the truth (a 1.5 px spatial width smooths the normals too much). The price: maps
    reprojected from these (held-out views, relighting) lose a little detail the blend of views had kept
    (slightly worse held-out maps and relit views against the truth), while the held-out protocol against the
    photometric maps gains most, because its references lose their pixel noise."""
    normal_alpha: bool = False
    """Also filter ``normal_alpha``, the maps the SDF is fitted to. Off: filtered, they are closer to the truth
    on the default capture, but the mesh came out worse (Chamfer and F-score at 1 mm), and the relit views
    with it."""
    spatial_sigma_px: float = checked(1.0, gt=0.0)
    """Gaussian width of the spatial weight, pixels."""
    range_sigma: float = checked(0.03, gt=0.0)
    """Gaussian width of the weight on albedo differences (albedo units): a few times the per-pixel noise,
    well under the contrast of a material edge."""
    radius: int = checked(2, ge=0)
    """Half-size of the square window, pixels."""


@dataclass(frozen=True)
class PhotometricConfig(Documented):
    params: PhotometricParams = field(default_factory=PhotometricParams)
    """Thresholds of the validity alpha and the mask (see PhotometricParams)."""
    use_clean_plate: bool = True
    """Segment the foreground against the session's clean plate when one exists (else a threshold)."""
    previews: bool = True
    """Write PNG previews (normals, albedo, mask) and a contact sheet per action."""
    light_iterations: int = 4
    """Gauss-Newton iterations when inverting the session's fitted LED ratio model."""
    denoise: DenoiseConfig = field(default_factory=DenoiseConfig)
    """Edge-preserving denoising of the albedo maps (and of ``normal_alpha`` when asked)."""


def contact_sheet(pictures: list[np.ndarray], columns: int = 8, labels: list[str] | None = None) -> np.ndarray:
    """Tile equally sized uint8 (H, W, 3) pictures into one (rows*H, columns*W, 3) picture, row-major; with
    ``labels`` (one per picture, e.g. the camera id) each tile carries its label in its top-left corner."""
    if labels is not None and len(labels) != len(pictures):
        raise ValueError(f"contact_sheet: {len(labels)} labels for {len(pictures)} pictures")
    h, w = pictures[0].shape[:2]
    rows = -(-len(pictures) // columns)
    sheet = np.zeros((rows * h, columns * w, 3), np.uint8)
    for i, pic in enumerate(pictures):
        r, c = divmod(i, columns)
        tile = pic[..., :3] if pic.ndim == 3 else np.repeat(pic[..., None], 3, axis=2)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = label_picture(tile, labels[i]) if labels else tile
    return sheet


def specular_free_normals(cam: Camera, pos: np.ndarray, neg: np.ndarray, normals_init: np.ndarray,
                          defined: np.ndarray, model: Any, spec: SpecularConfig, roughness: float | np.ndarray,
                          light_iterations: int) -> np.ndarray:
    """(H, W, 3) normals fitted as Lambertian plus GGX reflection of the given ``roughness`` (a scalar or
    (H, W)) where ``defined``; with the session's LED model, eq. 1 through that model of the frames less the
    fitted specular part, so they are on the same footing as the ratio normals."""
    if not defined.any():
        return np.zeros_like(normals_init)
    white = np.asarray(cam.record["white_reference"], np.float32)
    views = view_directions(cam.K, cam.cam_from_world, pos.shape[0], pos.shape[1])
    fit = fit_diffuse_normals(pos, neg, white, views, normals_init, defined, roughness=roughness, f0=spec.f0,
                              steps=spec.steps, lr=spec.lr, solver=spec.solver)
    if model is None:
        return fit.normals
    return corrected_normals(pos - fit.specular_pos, neg - fit.specular_neg, model, defined, light_iterations)


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
        pos, neg = (next(iter(sorted((action / i).glob(f"{view}.*"))), action / i / f"{view}.*") for i in ("pos", "neg"))
        raise InputError(pos, f"g+ and g- frames of camera {view} look swapped (with {neg.name} of 'neg'): eq. 1 "
                              f"normals face away from the camera on {100 * away:.0f}% of its {count} valid pixels")
    return away



def write_normal_sheet(previews: Path, prefix: str, sheet: str, view_stats: dict[str, dict[str, Any]]) -> None:
    """``previews/<sheet>``: the per-camera previews ``<prefix>_<camera>.png`` of the views that ran,
    side by side, each tile labelled with its camera id (nothing when none was written)."""
    paths = {v: previews / f"{prefix}_{v}.png" for v in sorted(view_stats) if "missing" not in view_stats[v]}
    shown = [v for v, p in paths.items() if p.exists()]
    if shown:
        write_png(previews / sheet,
                  contact_sheet([read_png(paths[v]) for v in shown], labels=[f"cam {v}" for v in shown]))

class PhotometricStage(Stage):
    name = "photometric"
    # 7: the normal sheet's tiles are labelled with their camera ids
    version = "7"
    scope = "action"
    requires = ("decode", "plates", "lights")
    outputs = ("normal_alpha", "albedo", "mask", "previews")
    per_view = True

    def run_view(self, ctx: StageContext, view: str) -> dict[str, Any]:
        upstream = ActionArtifacts(ctx.upstream)
        cameras = upstream.calibrated_cameras()
        if view not in cameras:
            return {"missing": "camera has no calibration"}
        cam = cameras[view]
        full_on, pos, neg = (upstream.exr(illumination, view) for illumination in ("full_on", "pos", "neg"))
        clipped = upstream.png("clipped", view) > 0
        background = upstream.plate(view) if self.config.use_clean_plate else None
        maps = photometric_maps(full_on, pos, neg, clipped, np.asarray(cam.record["white_reference"], np.float32),
                                background=background, params=self.config.params)
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
            write_png(ctx.out_dir / "previews" / f"normal_{view}.png", preview_normals(normals, maps.alpha))
            write_png(ctx.out_dir / "previews" / f"albedo_{view}.png", preview_linear(albedo, exposure=1.0))
        return {"mask_fraction": float(mask.mean()), "facing_away_fraction": facing_away,
                "valid_fraction": float(valid.sum() / max(int(mask.sum()), 1)),
                "ratio_norm_median": float(np.median(maps.ratio_norm[valid])) if valid.any() else 0.0,
                "plate": background is not None}

    def finalize(self, ctx: StageContext, view_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
        if self.config.previews:
            write_normal_sheet(ctx.out_dir / "previews", "normal", "normals_sheet.png", view_stats)
        fractions = [s["valid_fraction"] for s in view_stats.values() if "valid_fraction" in s]
        return {"views": view_stats, "valid_fraction": float(np.mean(fractions)) if fractions else 0.0}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        files = []
        for slot, ext in (("normal_alpha", "exr"), ("albedo", "exr"), ("mask", "png")):
            files += [(p, f"{slot}/{p.name}", slot, p.stem) for p in sorted((artifact / slot).glob(f"*.{ext}"))]
        files += [(p, f"previews/{p.name}", "preview", None)
                  for p in sorted((artifact / "previews").glob("*sheet*.png"))]
        return files
