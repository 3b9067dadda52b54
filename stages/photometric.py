"""Action stage ``photometric``: normals by eq. 1, validity alpha, albedo and mask, one task per camera; then, once
every camera is done, the holes the masks' cleanup filled decided across the views (:func:`open_gaps`).

Wiring only: the numerics are :func:`stages.numerics.photometric.photometric_maps` and
:func:`stages.numerics.gaps.see_through_holes`. The normals with the specular reflection fitted out are the
``diffuse_normals`` stage's (:mod:`stages.diffuse_normals`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.exr import read_exr, write_exr
from pipeline.codecs.image import mask_from_png, preview_linear, preview_normals, read_png, write_png
from pipeline.config import Documented, checked
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from artifacts.facade import ActionArtifacts
from artifacts.layout import ArtifactWriter, released_files
from artifacts.camera import Camera
from stages.numerics.denoise import DenoiseConfig, joint_bilateral
from stages.exr_headers import EXR_HEADERS
from stages.numerics.gaps import GapConfig, background_holes
from stages.numerics.hull import default_stage_box, subject_box
from stages.numerics.photometric import (PhotometricParams, corrected_normals, facing_away_fraction,
                                         foreground_mask_and_holes, normals_with_alpha, open_holes,
                                         photometric_maps)
from stages.numerics.specular_normals import view_directions
from stages.previews import contact_sheet, write_normal_sheet


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
    gaps: GapConfig = field(default_factory=GapConfig)
    """The holes the masks filled, decided across the views and by their gradient ratios: those the cameras see
    through (between an arm and the torso) go back to background in the mask and the maps; dark patches stay filled
    (:mod:`stages.numerics.gaps`)."""


SWAPPED_FACING_AWAY = 0.5
"""A camera's g+/g- frames are taken as swapped when more than this fraction of its valid pixels get eq. 1
normals facing away from it (correct frames of the simulator: 0.7-2%; swapped: 98-99%)."""
SWAPPED_MIN_PIXELS = 50
"""Fewer valid pixels than this are too little evidence to call a pair swapped."""


def valid_fraction(alpha: np.ndarray, mask: np.ndarray) -> float:
    """The share of a view's mask (H, W) whose normals are valid (``alpha`` (H, W) > 0.5): the stage's per-view
    ``valid_fraction``."""
    return float(((alpha > 0.5) & mask).sum() / max(int(mask.sum()), 1))


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


def write_gaps_sheet(out: ArtifactWriter, views: list[str], holes: list[np.ndarray], gaps: list[np.ndarray]) -> None:
    """The product ``gaps_sheet`` (work store): each view with filled holes, its albedo preview with the holes
    opened as gaps in red and those kept filled in blue, labelled with the camera and the pixel counts."""
    tiles, labels = [], []
    for v, hole, gap in zip(views, holes, gaps):
        if not hole.any() or not out.path("albedo_preview", v).exists():
            continue
        tile = read_png(out.path("albedo_preview", v))[..., :3].astype(np.float32)
        for where, colour in ((gap, (255, 40, 40)), (hole & ~gap, (60, 110, 255))):
            tile[where] = 0.3 * tile[where] + 0.7 * np.asarray(colour, np.float32)
        tiles.append(tile.astype(np.uint8))
        labels.append(f"cam {v}: {int(gap.sum())} px opened (red), {int((hole & ~gap).sum())} kept (blue)")
    if tiles:
        write_png(out.path("gaps_sheet"), contact_sheet(tiles, columns=4, labels=labels))


def open_gaps(ctx: StageContext, config: PhotometricConfig, view_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Decide the views' filled holes: a hole is background when the views see through it
    (:func:`stages.numerics.gaps.see_through_holes`) or when its gradient ratios are the backdrop's around it
    (:func:`stages.numerics.gaps.backdrop_holes`, unless ``backdrop_ratio_max`` is 0). Put those back to background
    in the stage's maps of the views that have them: mask, ``normal_alpha`` (normals and alpha 0), albedo and the
    previews. ``view_stats`` gets each view's new mask fraction and its opened pixels. Returns the decision's record
    (holes, gaps by each test, pixels, seconds), said in one log line."""
    if not config.gaps.enabled:
        return {"enabled": False}
    out = ArtifactWriter("photometric", ctx.out_dir)
    upstream = ActionArtifacts(ctx.upstream)
    cameras = upstream.calibrated_cameras()
    views = [v for v in sorted(view_stats) if v in cameras and "mask_fraction" in view_stats[v]]
    holes = {v: (mask_from_png(read_png(out.path("filled_holes", v))) if out.path("filled_holes", v).exists()
                 else None) for v in views}
    if not any(h is not None for h in holes.values()):
        return {"enabled": True, "holes": 0, "gaps": 0, "opened_pixels": 0}
    start = time.perf_counter()
    masks = {v: mask_from_png(read_png(out.path("mask", v))) for v in views}
    # the mask as the mask step filled it: a finalize run again after a lost worker decides the same
    filled = [masks[v] | (holes[v] if holes[v] is not None else False) for v in views]
    hole_maps = [holes[v] if holes[v] is not None else np.zeros_like(masks[v]) for v in views]
    Ks = [cameras[v].K for v in views]
    Ts = [cameras[v].cam_from_world for v in views]
    try:
        box = subject_box(filled, Ks, Ts, default_stage_box(list(zip(Ks, Ts))))
    except ValueError as exc:  # no hull: the masks disagree; the geometry stage says so, the holes stay filled
        ctx.log.warning(f"{ctx.scope_id}: filled holes left as they are: {exc}")
        return {"enabled": True, "skipped": str(exc)}
    # read on demand: one view's pair held at a time
    gradients = [lambda v=v: (upstream.exr("pos", v), upstream.exr("neg", v)) for v in views]
    gaps, counts = background_holes(filled, hole_maps, Ks, Ts, box, gradients, config.gaps)
    seen_through, by_ratio = counts["seen_through"], counts["by_ratio"]
    opened = 0
    for v, mask, gap in zip(views, filled, gaps):
        if not gap.any() and np.array_equal(mask, masks[v]):
            continue
        normal_alpha, albedo, mask = open_holes(read_exr(out.path("normal_alpha", v)), read_exr(out.path("albedo", v)),
                                                mask, gap, config.params)
        write_exr(out.path("normal_alpha", v), normal_alpha, header=EXR_HEADERS["normal_alpha"])
        write_exr(out.path("albedo", v), albedo, header=EXR_HEADERS["albedo"])
        write_png(out.path("mask", v), mask)
        if config.previews:
            write_png(out.path("normal_preview", v), preview_normals(normal_alpha[..., :3], normal_alpha[..., 3]))
            write_png(out.path("albedo_preview", v), preview_linear(albedo, exposure=1.0))
        view_stats[v]["mask_fraction"] = float(mask.mean())
        view_stats[v]["valid_fraction"] = valid_fraction(normal_alpha[..., 3], mask)
        view_stats[v]["gap_pixels"] = int(gap.sum())
        opened += int(gap.sum())
    if config.previews:
        write_gaps_sheet(out, views, hole_maps, gaps)
    record = {"enabled": True, "holes": counts["holes"],
              "gaps": seen_through + by_ratio, "gaps_seen_through": seen_through, "gaps_by_ratio": by_ratio,
              "opened_pixels": opened, "seconds": round(time.perf_counter() - start, 2)}
    ctx.log.info(f"{ctx.scope_id}: {record['gaps']} of {record['holes']} filled holes are background ({seen_through} "
                 f"seen through across the views, {by_ratio} more by their gradient ratios): {opened} pixels back to "
                 f"background ({record['seconds']:.1f} s)")
    return record


class PhotometricStage(Stage):
    name = "photometric"
    # 8: filled holes whose gradient ratios are the backdrop's go back to background too
    version = "8"
    scope = "action"
    requires = ("decode", "plates", "lights")
    outputs = ("normal_alpha", "albedo", "mask", "filled_holes", "previews")
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
        if shipped is not None:  # the capture's own mask: its holes are the capture's decision
            given, holes = shipped_mask(shipped, full_on.shape[:2]), None
        else:
            given, holes = foreground_mask_and_holes(full_on, background, self.config.params)
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
        if holes is not None and holes.any():
            write_png(out.path("filled_holes", view), holes)
        if self.config.previews:
            write_png(out.path("normal_preview", view), preview_normals(normals, maps.alpha))
            write_png(out.path("albedo_preview", view), preview_linear(albedo, exposure=1.0))
        return {"mask_fraction": float(mask.mean()), "facing_away_fraction": facing_away,
                "valid_fraction": valid_fraction(maps.alpha, mask),
                "ratio_norm_median": float(np.median(maps.ratio_norm[valid])) if valid.any() else 0.0,
                "plate": background is not None, "filled_hole_pixels": int(holes.sum()) if holes is not None else 0}

    def finalize(self, ctx: StageContext, view_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
        gaps = open_gaps(ctx, self.config, view_stats)
        if self.config.previews:
            write_normal_sheet(ArtifactWriter(self.name, ctx.out_dir), "normal_preview", "normals_sheet", view_stats)
        fractions = [s["valid_fraction"] for s in view_stats.values() if "valid_fraction" in s]
        return {"views": view_stats, "valid_fraction": float(np.mean(fractions)) if fractions else 0.0, "gaps": gaps}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        return released_files(self.name, artifact, RELEASED, optional=("normals_sheet",))
