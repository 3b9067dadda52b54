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
  0.13 / 0.14. Nearest in albedo too (``median_albedo_m``, the log white-light albedo averaged over
  ``median_albedo_neighbours`` texels as the guide), so a material narrower than the median's disc (a belt)
  keeps its own roughness instead of its surroundings': MAE 0.031 / 0.051 against 0.041 / 0.052 on the
  surface alone (the bench's guide rows).
* The fit assumes every LED above a texel's horizon lights it. Where the body hides part of a view's
  specular lobe the observation loses the lobe's far side and reads rougher; grazing views reflect towards
  the horizon, where the body hides most. So an observation is used only where the view's mirror direction
  and a cone of ``specular_cone_deg`` around it leave the mesh open
  (:func:`stages.numerics.material_textures.mirror_cone_open`): MAE 0.041 / 0.051 with the test, 0.054 / 0.055
  without (the bench's ``specular_cone_deg`` rows).
* Where the body shadows part of the stage (armpits, the belt under the hands, between the legs) the fits come
  out too rough, more so the deeper the shadow, so only texels whose ambient visibility on the mesh reaches
  ``median_min_visibility`` vote in that median (the others take their nearest voters'): a lower MAE on both
  actions than with every texel voting (the bench's ``median_min_visibility`` 0 row).
* Ambient occlusion: the stage's white light is uniform over the sphere, so the white-light albedo is the
  true albedo times the cosine-weighted visible fraction of the sphere. ``albedo_deoccluded`` divides the
  baked albedo by that fraction computed on the mesh (floored at ``min_occlusion``): a higher PSNR against
  the simulator's albedo on both actions (the bench's albedo table).
* The white-light albedo also holds the specular light (6-7% brighter than the truth on the simulator). The
  roughness fit splits each texel's light into diffuse and specular; ``diffuse_ratio`` (RGB, at the
  roughness texture's size) is the fitted diffuse albedo over the white-light one, and ``albedo_intrinsic``
  = baked albedo x diffuse_ratio / occlusion, the closest to the truth. The diffuse albedo comes from a second
  joint fit on the ``albedo_max_views`` best views with every valid observation among them: the observations
  the mirror-cone test leaves out mislead the roughness, not the albedo (intrinsic albedo 34.85 / 31.92 dB
  against 34.51 / 31.63 dB from the roughness fit's own albedo; the bench's ``albedo_max_views`` rows).
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
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from artifacts.facade import ActionArtifacts
from artifacts.layout import ArtifactWriter, released_files
from stages.numerics import numeric_threads
from stages.numerics.material_textures import MaterialTexturesConfig

ILLUMINATION_DIRS = ("full_on", "pos", "neg")


RELEASED_PREVIEWS = ("texture_albedo_intrinsic_preview", "texture_occlusion_preview", "texture_roughness_preview")
RELEASED = ("albedo_deoccluded_texture", "albedo_intrinsic_texture", "diffuse_ratio_texture", "occlusion_texture",
            "roughness_texture", "roughness_fit_rms_texture") + RELEASED_PREVIEWS
"""The products this stage publishes, in order: its textures, then their previews (when on)."""


@dataclass(frozen=True)
class MaterialsConfig(MaterialTexturesConfig):
    """The textures' fit (:class:`stages.numerics.material_textures.MaterialTexturesConfig`: sizes, views, the
    specular model, F0, roughness bounds and median, occlusion, visibility tests) and the stage's own fields."""

    min_alpha: float = 0.5
    """Map pixels with a lower photometric validity alpha are not used."""
    previews: bool = True
    """Write PNG previews of roughness, fit error, occlusion and the de-occluded albedo."""


def load_bake_views(artifacts: ActionArtifacts, min_alpha: float) -> tuple[list[Any], list[Any]]:
    """The stage's observations: per camera with maps (sorted by id), a :class:`stages.numerics.bake.BakeView`
    with ``images["obs"]`` (H, W, 9) = full_on | pos | neg and valid = alpha above ``min_alpha`` inside the
    mask, and its :class:`artifacts.camera.Camera`."""
    from stages.numerics.bake import BakeView

    views, cameras = [], []
    for cam_id, cam, _, _, valid in artifacts.camera_maps(min_alpha):
        images = [artifacts.map(illumination, cam_id) for illumination in ILLUMINATION_DIRS]
        views.append(BakeView(images={"obs": np.concatenate(images, axis=2)}, valid=valid,
                              K=cam.K, cam_from_world=cam.cam_from_world))
        cameras.append(cam)
    return views, cameras


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

        from stages.numerics.material_textures import material_textures

        torch.set_num_threads(numeric_threads())
        cfg: MaterialsConfig = self.config
        artifacts = ActionArtifacts(ctx.upstream)
        t0 = time.perf_counter()
        vertices, faces, atlas = artifacts.atlas_mesh()
        albedo_texture = artifacts.texture("albedo_texture")
        views, cameras = load_bake_views(artifacts, cfg.min_alpha)
        white = [np.asarray(cam.record["white_reference"], np.float32) for cam in cameras]
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
            write_png(out.path("texture_roughness_preview"), preview_scalar(result.roughness))
            write_png(out.path("texture_occlusion_preview"), preview_scalar(result.occlusion))
            write_png(out.path("texture_albedo_intrinsic_preview"),
                      preview_linear(result.albedo_intrinsic, exposure=1.0))
        return result.stats | {"load_s": load_s}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        return released_files(self.name, artifact, RELEASED, optional=RELEASED_PREVIEWS)
