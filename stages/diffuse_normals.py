"""Action stage ``diffuse_normals``: the normals with the specular reflection fitted out, each pixel with the
materials stage's roughness, and the mesh's occlusion of the LED sphere divided out; one task per camera.

Wiring only: the numerics are :func:`stages.numerics.specular_normals.fit_diffuse_normals` and
:func:`stages.numerics.shadowing.deocclude_view`.
"""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.exr import read_exr, write_exr
from pipeline.codecs.image import preview_normals, write_png
from pipeline.config import Documented, checked
from pipeline.stage import Stage, StageContext
from stages.exr_headers import EXR_HEADERS
from artifacts.facade import ActionArtifacts
from artifacts.layout import ArtifactWriter, released_files
from artifacts.camera import Camera
from stages.numerics.photometric import normals_with_alpha
from stages.numerics.shadowing import deocclude_view
from stages.numerics.denoise import DenoiseConfig, joint_bilateral
from stages.numerics.specular_normals import SpecularConfig, specular_free_normals, view_directions, white_light_specular
from stages.previews import write_normal_sheet


RELEASED = ("normal_diffuse", "albedo_diffuse", "normals_diffuse_sheet")
"""The products this stage publishes, in order: the per-camera maps and the normals' contact sheet (when the
previews are on; the per-camera previews stay in the work store)."""


@dataclass(frozen=True)
class DiffuseNormalsConfig(Documented):
    """The released ``normal_diffuse`` maps: the specular fit, each pixel with its roughness from the materials
    stage; and ``albedo_diffuse``, the white-light albedo less the specular light that fit predicts. The
    photometric stage does not fit them: the mesh and the roughness texture need only eq. 1's ``normal_alpha``,
    so a first pass with one roughness prior for every pixel would be thrown away (it cost 1.5 s per camera on
    the default capture)."""

    enabled: bool = True
    """Write ``normal_diffuse`` (and so release them). The ratio normals stay the release's ``normal_alpha``: the
    SDF is fitted to those (with the specular-fitted ones its mesh came out about a millimetre larger, a worse
    Chamfer: the fit leaves a few hundredths of n.v of bias per material, which moves a 10 cm limb's surface
    by millimetres)."""
    use_materials_roughness: bool = True
    """Fit each pixel with the materials stage's roughness texture seen through the textured mesh: on the
    default capture the maps come closer to the simulator's normals than with one roughness prior, shiny
    materials most, most of the way to a fit with the simulator's own roughness, for the same fit time
    (bench/bench_diffuse_normals.py measures the three). Off: every pixel is fitted with ``fit.roughness``."""
    fit: SpecularConfig = field(default_factory=SpecularConfig)
    """The per-pixel fit; its ``roughness`` is used where the textured mesh does not cover a pixel (every
    pixel with ``use_materials_roughness`` off)."""
    denoise: DenoiseConfig = field(default_factory=DenoiseConfig)
    """The same edge-preserving filter as the photometric stage's maps get, guided by the released albedo
    (``normal_alpha`` is not read here)."""
    light_iterations: int = 4
    """Gauss-Newton iterations when inverting the session's LED ratio model (as ``photometric``'s)."""
    albedo: bool = True
    """Also write ``albedo_diffuse``: the released white-light albedo less the GGX reflection of the white light
    that the fitted normals, each pixel's roughness and the materials stage's F0 predict (its roughness was
    fitted with that F0). On the default capture the white-light albedo lies above the simulator's albedo,
    about three times more at grazing views than head-on, and ``albedo_diffuse`` much closer to it at every
    n.v, for a few hundredths of a second per camera (bench/bench_diffuse_normals.py: the median difference
    per band of n.v and the PSNR of both). It still holds the stage's ambient occlusion, as the white-light
    albedo."""
    occlusion: bool = True
    """Divide the occlusion of the LED sphere out of the fitted normals: the mesh's visibility of each pixel's
    surface point over ``occlusion_directions`` directions, inverted by
    :func:`stages.numerics.shadowing.deocclude_normals` (eq. 1's ratio measures the cosine-weighted mean of the
    *visible* directions, which leans away from an arm or the other leg). On the default capture the maps
    come closer to the simulator's normals, most where much of the cosine-weighted sphere is hidden
    (bench/bench_diffuse_normals.py measures the error with and without). About 1 s per camera."""
    occlusion_directions: int = checked(128, ge=16)
    """Directions (Fibonacci sphere) of the visibility. On the default capture 256 cost 4-5 CPU s more an action;
    128 with ``textures.atlas_max_chart_area_m2`` 0.05 (measured together) cost the relit views' shading normals
    0.01 deg and the relit views 0.02 dB (bench/bench_diffuse_normals.py sweeps it)."""
    occlusion_min_visible: float = checked(0.1, ge=0.0, lt=1.0)
    """Pixels whose cosine-weighted visible fraction is below this keep the fitted normal."""
    previews: bool = True
    """Write a PNG preview per camera and a contact sheet."""


@functools.lru_cache(maxsize=2)
def _roughness_atlas(textured_obj: str, roughness_exr: str) -> tuple[Any, Any, np.ndarray]:
    """The textured mesh's ray-casting scene, its atlas and the roughness texture (once per process, by the
    files' paths)."""
    from artifacts.facade import load_atlas_mesh
    from stages.numerics.raycast import mesh_scene

    vertices, faces, atlas = load_atlas_mesh(Path(textured_obj))
    texture = read_exr(Path(roughness_exr))
    return mesh_scene(vertices, faces), atlas, (texture[..., 0] if texture.ndim == 3 else texture)


def materials_roughness(scene: Any, atlas: Any, texture: np.ndarray, cam: Camera, height: int, width: int,
                        fallback: float) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 roughness of each pixel from the materials' texture seen through the textured mesh
    (``fallback`` where the mesh does not cover the pixel or the texture holds no value), and the (H, W)
    bool pixels that got it from the texture."""
    from stages.numerics.bake import texture_in_camera

    seen, on_mesh = texture_in_camera(scene, atlas.faces, atlas.uvs, texture, cam.K, cam.cam_from_world,
                                      height, width)
    on_mesh = on_mesh & np.isfinite(seen) & (seen > 0)
    return np.where(on_mesh, seen, fallback).astype(np.float32), on_mesh


def refit_diffuse_normals(cam: Camera, pos: np.ndarray, neg: np.ndarray, normal_alpha: np.ndarray,
                          mask: np.ndarray, albedo: np.ndarray, model: Any, cfg: DiffuseNormalsConfig,
                          roughness: float | np.ndarray) -> np.ndarray:
    """The diffuse_normals stage's maps of one camera for a given roughness: the specular fit from eq. 1's
    normals (``normal_alpha`` (H, W, 4)) where they are defined, then the edge-preserving filter over the
    valid pixels (alpha > 0.5 inside ``mask``) guided by ``albedo``. (H, W, 3) float32, finite."""
    normals_init = normal_alpha[..., :3]  # eq. 1 (through the LED model when there is one), unfiltered
    defined = np.any(normals_init != 0, axis=-1)
    normals = specular_free_normals(cam, pos, neg, normals_init, defined, model, cfg.fit, roughness,
                                    cfg.light_iterations)
    if cfg.denoise.enabled:
        valid = (normal_alpha[..., 3] > 0.5) & mask
        _, (normals,) = joint_bilateral(albedo, [normals], valid, cfg.denoise.spatial_sigma_px,
                                        cfg.denoise.range_sigma, cfg.denoise.radius)
    return np.where(np.isfinite(normals), normals, 0.0).astype(np.float32)


def diffuse_albedo(albedo: np.ndarray, normals: np.ndarray, cam: Camera, roughness: float | np.ndarray,
                   f0: float) -> np.ndarray:
    """(H, W, 3) float32 white-light ``albedo`` (H, W, 3) less the white light's GGX reflection predicted from
    ``normals`` (H, W, 3), the camera's view directions, ``roughness`` (scalar or (H, W)) and ``f0``, clipped to
    [0, 1] (so where a normal is undefined (0), the white-light albedo clipped)."""
    h, w = albedo.shape[:2]
    views = view_directions(cam.K, cam.cam_from_world, h, w)
    specular = white_light_specular(normals, views, roughness, f0)
    return np.clip(np.nan_to_num(albedo - specular, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class ViewInputs:
    """What the stage reads of one camera: its calibrated camera (its record in ``cam.record``), the decoded gradient images ``pos`` and
    ``neg`` (H, W, 3), eq. 1's ``normal_alpha`` (H, W, 4), the mask (H, W) bool and the white-light albedo
    (H, W, 3)."""

    cam: Camera
    pos: np.ndarray
    neg: np.ndarray
    normal_alpha: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray


def read_view_inputs(artifacts: ActionArtifacts, view: str) -> ViewInputs | None:
    """One camera's :class:`ViewInputs` from the decode and photometric artifacts; None when the camera has no
    calibration or no photometric maps."""
    cameras = artifacts.calibrated_cameras()
    if view not in cameras or not artifacts.has("normal_alpha", view):
        return None
    return ViewInputs(cam=cameras[view], pos=artifacts.exr("pos", view), neg=artifacts.exr("neg", view),
                      normal_alpha=artifacts.exr("normal_alpha", view), mask=artifacts.mask(view),
                      albedo=artifacts.map("albedo", view))


@dataclass(frozen=True)
class DiffuseView:
    """One camera's products: ``normals`` (H, W, 3), ``albedo_diffuse`` (H, W, 3) or None, and the stats."""

    normals: np.ndarray
    albedo_diffuse: np.ndarray | None
    stats: dict[str, float]


def diffuse_view(inputs: ViewInputs, light_model: Any, cfg: DiffuseNormalsConfig, scene: Any, atlas: Any,
                 texture: np.ndarray | None, f0: float) -> DiffuseView:
    """The stage's action on one camera: each pixel's roughness (the materials' ``texture`` seen through the
    textured mesh's ``scene`` and ``atlas`` with ``cfg.use_materials_roughness``, else ``cfg.fit.roughness``),
    the specular refit (:func:`refit_diffuse_normals`), the LED sphere's occlusion by the mesh divided out
    (``cfg.occlusion``) and, with ``cfg.albedo``, the albedo less the fitted specular light for ``f0``."""
    alpha = inputs.normal_alpha[..., 3]
    if cfg.use_materials_roughness:
        roughness, on_mesh = materials_roughness(scene, atlas, texture, inputs.cam, *alpha.shape, cfg.fit.roughness)
    else:
        roughness = np.full(alpha.shape, cfg.fit.roughness, np.float32)
        on_mesh = np.zeros(alpha.shape, bool)
    normals = refit_diffuse_normals(inputs.cam, inputs.pos, inputs.neg, inputs.normal_alpha, inputs.mask,
                                    inputs.albedo, light_model, cfg, roughness)
    stats: dict[str, float] = {}
    if cfg.occlusion:
        normals, stats = deocclude_view(scene, inputs.cam.K, inputs.cam.cam_from_world, normals,
                                        cfg.occlusion_directions, cfg.occlusion_min_visible)
    fitted = np.any(inputs.normal_alpha[..., :3] != 0, axis=-1) & (alpha > 0.5) & inputs.mask
    albedo_out = None
    if cfg.albedo:
        albedo_out = diffuse_albedo(inputs.albedo, normals, inputs.cam, roughness, f0)
        taken = (inputs.albedo - albedo_out).mean(axis=-1)[fitted]
        stats = {"albedo_f0": f0, "specular_taken_mean": float(taken.mean()) if taken.size else 0.0} | stats
    stats = {"roughness_mean": float(roughness[fitted].mean()) if fitted.any() else 0.0,
             "on_mesh_fraction": float(on_mesh[fitted].mean()) if fitted.any() else 0.0} | stats
    return DiffuseView(normals=normals, albedo_diffuse=albedo_out, stats=stats)


class DiffuseNormalsStage(Stage):
    """``normal_diffuse`` fitted with per-pixel roughness, and ``albedo_diffuse``, one task per camera (see the
    config)."""

    name = "diffuse_normals"
    # 5: the normal sheet's tiles are labelled with their camera ids
    version = "5"
    scope = "action"
    requires = ("decode", "lights", "photometric", "textures", "materials")
    outputs = ("normal_diffuse", "albedo_diffuse", "previews")
    per_view = True

    def run_view(self, ctx: StageContext, view: str) -> dict[str, Any]:
        cfg: DiffuseNormalsConfig = self.config
        if not cfg.enabled:
            return {"disabled": True}
        upstream = ActionArtifacts(ctx.upstream)
        inputs = read_view_inputs(upstream, view)
        if inputs is None:
            return {"missing": "no photometric normal_alpha for this camera"}
        start = time.perf_counter()
        scene = atlas = texture = None
        if cfg.use_materials_roughness or cfg.occlusion:
            scene, atlas, texture = _roughness_atlas(str(upstream.existing("textured_mesh")),
                                                     str(upstream.existing("roughness_texture")))
        f0 = cfg.fit.f0
        if cfg.albedo and cfg.use_materials_roughness:
            f0 = upstream.materials_f0()
        result = diffuse_view(inputs, upstream.light_model(), cfg, scene, atlas, texture, f0)
        alpha = inputs.normal_alpha[..., 3]
        out = ArtifactWriter(self.name, ctx.out_dir)
        write_exr(out.path("normal_diffuse", view), normals_with_alpha(result.normals, alpha),
                  header=EXR_HEADERS["normal_diffuse"])
        self._preview(ctx, view, result.normals, alpha)
        if result.albedo_diffuse is not None:
            write_exr(out.path("albedo_diffuse", view), result.albedo_diffuse,
                      header=EXR_HEADERS["albedo_diffuse"])
        return {"fitted": True, "seconds": time.perf_counter() - start, **result.stats}

    def _preview(self, ctx: StageContext, view: str, normals: np.ndarray, alpha: np.ndarray) -> None:
        if self.config.previews:
            write_png(ArtifactWriter(self.name, ctx.out_dir).path("normal_diffuse_preview", view),
                      preview_normals(normals, alpha))

    def finalize(self, ctx: StageContext, view_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
        if self.config.previews:
            write_normal_sheet(ArtifactWriter(self.name, ctx.out_dir), "normal_diffuse_preview",
                               "normals_diffuse_sheet", view_stats)
        fitted = [s for s in view_stats.values() if s.get("fitted")]
        return {"views": view_stats, "fitted_views": len(fitted),
                "seconds": float(sum(s["seconds"] for s in fitted))}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        return released_files(self.name, artifact, RELEASED, optional=("normals_diffuse_sheet",))
