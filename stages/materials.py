"""Action stage ``materials``: roughness by inverse rendering under the stage's own illuminations, and an
albedo with the ambient occlusion divided out, both as textures over the action's UV atlas.

Wiring only; the action is :func:`stages.numerics.material_textures.material_textures` over
:func:`stages.numerics.bake.gather_observations` (each texel's values in the cameras that see it best,
depth-tested against the mesh), :func:`stages.numerics.materials.fit_roughness` (GGX under full_on / pos / neg
in closed form, F0 fixed) and :func:`stages.numerics.shadowing.ambient_occlusion`.

Method (measured on the simulator's default capture, ``python bench/bench_materials.py``; MAE of the
roughness seen from the 32 true cameras, A0000 / A0001, with the other steps at their defaults):

* Each texel of a ``texture_size`` atlas gets the decoded full_on / pos / neg values of its ``max_views`` best
  cameras (validity from the photometric alpha, so saturated and grazing pixels are out), the mesh normal and
  the view directions. The albedo is solved with the roughness (``fit_albedo``): the white-light albedo
  still holds the specular light, and fixing it pushes every fit towards rough (MAE 0.36 / 0.36 without).
* The specular term under the linear gradients is the exact GGX lobe's tabulated moments
  (``specular_model="ggx_table"``); the spherical-Gaussian lobes of PhySG (``"sg"``) are 7-10% off in
  specular energy and fit roughness biased rough (MAE 0.13 / 0.13 vs 0.06 / 0.07).
* Per-texel fits are noisy (a few views, noise on a small lobe); roughness varies slowly over a surface, so
  the texture is the median over each texel's ``median_neighbours`` nearest texels *on the surface* (3D, so
  atlas charts do not matter): MAE 0.12 / 0.15 without it. A constant roughness (the fits' median) scores
  0.13 / 0.14.
* The fit assumes every LED above a texel's horizon lights it. Where the body shadows part of the stage
  (armpits, the belt under the hands, between the legs) the fits come out too rough, more so the deeper the
  shadow, so only texels whose ambient visibility on the mesh reaches ``median_min_visibility`` vote in that
  median (the others take their nearest voters'): a lower MAE on both actions than with every texel voting
  (the bench's ``median_min_visibility`` 0 row).
* Ambient occlusion: the stage's white light is uniform over the sphere, so the white-light albedo is the
  true albedo times the cosine-weighted visible fraction of the sphere. ``albedo_deoccluded`` divides the
  baked albedo by that fraction computed on the mesh (floored at ``min_occlusion``): a higher PSNR against
  the simulator's albedo on both actions (the bench's albedo table).
* The white-light albedo also holds the specular light (6-7% brighter than the truth on the simulator). The
  roughness fit splits each texel's light into diffuse and specular; ``diffuse_ratio`` (RGB, at the
  roughness texture's size) is the fitted diffuse albedo over the white-light one, and ``albedo_intrinsic``
  = baked albedo x diffuse_ratio / occlusion: 31.1 dB (A0000) and 28.3 dB (A0001), the closest to the truth.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.exr import write_exr
from stages.exr_headers import EXR_HEADERS
from pipeline.codecs.image import preview_linear, preview_scalar, write_png
from pipeline.config import Documented, checked
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from stages.artifacts import ActionArtifacts
from stages.layout import ArtifactWriter
from stages.numerics import numeric_threads

ILLUMINATION_DIRS = ("full_on", "pos", "neg")


@dataclass(frozen=True)
class MaterialsConfig(Documented):
    texture_size: int = checked(256, ge=1)
    """Width and height of the roughness texture (the atlas of the textures stage; roughness varies slowly)."""
    max_views: int = checked(16, ge=1)
    """Cameras used per texel (the best by angle, distance and support). On the simulator with the mesh of the
    one-pass SDF 8 and 16 were close (MAE 0.061/0.067 vs 0.068/0.068 on A0000/A0001); with the two-pass mesh
    (geometry.deocclude) 8 views fit too smooth (0.067/0.082, bias -0.025/-0.040) and 16 views give
    0.061/0.067 (bias +0.041/+0.015), for 2.5 s more per action (bench_materials)."""
    specular_model: str = checked("ggx_table", one_of=("ggx_table", "sg"))
    """"ggx_table" (exact GGX lobe moments under the linear gradients) or "sg" (the spherical-Gaussian lobes
    relighting uses). Measured on the simulator the table is the more accurate (see bench_materials)."""
    f0: float = 0.02
    """Fresnel reflectance at normal incidence (skin, as the paper)."""
    fit_albedo: bool = True
    """Solve the diffuse albedo with the roughness (the white-light albedo still holds specular light)."""
    roughness_min: float = checked(0.05, gt=0.0, lt="roughness_max")
    """Lower bound of the fitted perceptual roughness."""
    roughness_max: float = checked(1.0, le=1.0)
    """Upper bound of the fitted perceptual roughness."""
    median_neighbours: int = checked(100, ge=1)
    """Texels (nearest on the surface) whose median gives the published roughness; 1 = no smoothing."""
    median_min_visibility: float = checked(0.95, ge=0.0, le=1.0)
    """Only texels whose ambient visibility on the mesh (cosine-weighted visible fraction, ``occlusion_rays``
    rays) reaches this vote in that median; the others take the median of their nearest voters. The fit
    assumes every LED above a texel's horizon lights it, so texels the body itself shadows come out too rough:
    on the default capture shiny leather (0.25) was fitted 0.30 where the simulator's visibility is >= 0.95 and
    0.51-0.54 below 0.85, skin (0.45) 0.47 and 0.60-0.68. Roughness MAE (bench scratch, A0000 / A0001) 0.078 /
    0.080 with every fitted texel voting, 0.074 / 0.076 at 0.85, 0.061 / 0.067 at 0.95 (the voters: 60% of
    the texels). 0 = every fitted texel votes."""
    occlusion_rays: int = checked(64, ge=1)
    """Cosine-weighted rays per texel for the ambient occlusion."""
    occlusion_size: int = checked(512, ge=1)
    """Texture size at which the occlusion is computed (then sampled at the albedo texture's size)."""
    min_occlusion: float = checked(0.2, gt=0.0, le=1.0)
    """Floor of the visible fraction the albedo is divided by (deep creases would blow up noise)."""
    min_alpha: float = 0.5
    """Map pixels with a lower photometric validity alpha are not used."""
    depth_tolerance_m: float = 0.01
    """A texel is visible in a camera when its depth agrees with the mesh's depth there within this."""
    min_cos: float = 0.2
    """Cameras at more grazing angles to a texel than this cosine are not used."""
    previews: bool = True
    """Write PNG previews of roughness, fit error, occlusion and the de-occluded albedo."""


class MaterialsStage(Stage):
    """Roughness texture (inverse rendering under full_on/pos/neg), occlusion, and albedos without occlusion
    and without specular light."""

    name = "materials"
    version = "4"
    scope = "action"
    requires = ("textures", "decode", "photometric")
    outputs = ("textures", "previews")

    def run(self, ctx: StageContext) -> dict[str, Any]:
        import torch

        from stages.numerics.bake import BakeView
        from stages.numerics.material_textures import material_textures

        torch.set_num_threads(numeric_threads())
        cfg: MaterialsConfig = self.config
        artifacts = ActionArtifacts(ctx.upstream)
        t0 = time.perf_counter()
        vertices, faces, atlas = artifacts.atlas_mesh()
        albedo_texture = artifacts.texture("albedo_texture")
        views, white = [], []
        for cam_id, cam, _, _, valid in artifacts.camera_maps(cfg.min_alpha):
            images = [artifacts.map(illumination, cam_id) for illumination in ILLUMINATION_DIRS]
            views.append(BakeView(images={"obs": np.concatenate(images, axis=2)}, valid=valid,
                                  K=cam.K, cam_from_world=cam.cam_from_world))
            white.append(np.asarray(cam.record["white_reference"], np.float32))
        if not views:
            raise InputError(artifacts.where(), "no camera has photometric maps")
        load_s = time.perf_counter() - t0
        result = material_textures(vertices, faces, atlas, albedo_texture, views, np.stack(white), cfg,
                                   progress=ctx.progress)
        out = ArtifactWriter(self.name, ctx.out_dir)
        for name in ("roughness", "roughness_fit_rms", "occlusion", "albedo_deoccluded", "diffuse_ratio",
                     "albedo_intrinsic"):
            write_exr(out.path(f"{name}_texture"), getattr(result, name),
                      header=EXR_HEADERS[f"texture_{name}"])
        if cfg.previews:
            previews = ctx.out_dir / "previews"
            write_png(previews / "texture_roughness.png", preview_scalar(result.roughness))
            write_png(previews / "texture_occlusion.png", preview_scalar(result.occlusion))
            write_png(previews / "texture_albedo_intrinsic.png", preview_linear(result.albedo_intrinsic, exposure=1.0))
        return result.stats | {"load_s": load_s}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        files = [(p, f"textures/{p.name}", f"texture_{p.stem}", None)
                 for p in sorted((artifact / "textures").glob("*.exr"))]
        for p in sorted((artifact / "previews").glob("*.png")) if (artifact / "previews").exists() else []:
            files.append((p, f"previews/{p.name}", f"preview_{p.stem}", None))
        return files
