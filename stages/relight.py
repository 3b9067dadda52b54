"""Action stage ``relight``: novel views of the asset under HDR environments.

For each novel camera (placed between neighbouring captured cameras,
:func:`stages.numerics.gbuffer.novel_camera_pairs`):

1. depth from the action's mesh (Embree), the G-buffer (normal, albedo) reprojected from the ``shading.sources``
   nearest captured views with depth tests (:func:`stages.numerics.gbuffer.reproject_gbuffer`, the paper's
   depth-guided reprojection; ``learned_blend`` optionally blends with weights learned leave one out on
   the captured views, :mod:`stages.numerics.learned_blend`), roughness and occlusion looked up in the
   materials textures through the textured mesh's UVs (pixels the mesh covers but no source sees take the
   baked textures and the mesh's smooth normals; ``shading.normals: mesh`` uses those everywhere). The shading
   normals are by default ``fused``: the reprojected normals' detail on the mesh normals' low frequencies
   (:func:`stages.numerics.gbuffer.fuse_normals`, split at ``shading.normal_fusion_m`` on the surface), faded to
   the mesh's normals over the ``shading.rim_normal_px`` pixels inside the silhouette
   (:func:`stages.numerics.gbuffer.fade_rim_normals`);
2. each environment (equirectangular HDR/EXR, or a built-in procedural one) fitted with ``sg_lobes``
   spherical Gaussians (:func:`stages.numerics.sg.fit_sg_environment`);
3. shading: Lambertian diffuse + GGX specular under the lobes (F0 ``shading.f0``, skin's 0.028; Smith shadowing,
   ``shading.shadowing``), with the mesh's self-occlusion when ``shading.shadows``: by default the lobes' energy is
   put on the ``shading.visibility_directions`` the occlusion is traced for (each cell lighting from its energy's
   mean direction, ``shading.cell_centroids``) and the BRDF summed over them, each direction occluded per pixel,
   the ``shading.key_lights`` brightest sharp lobes as point lights at their own axes with their own traced
   occlusion (:mod:`stages.numerics.direction_lights`; ``shading.integration: closed_form``: the lobes' closed
   forms scaled by their visible fractions, :func:`stages.numerics.shadowing.shade_sg_visible`). The sources'
   albedo is ``albedo_diffuse`` (the white-light albedo less the specular light fitted per view; with
   ``diffuse_albedo`` off or without those maps, the white-light albedo times the materials stage's diffuse
   ratio); it still holds the stage's ambient occlusion, so with shadows it is divided by the occlusion
   (else occlusion would count twice).
4. edges: a camera pixel integrates the light over its square, so at a silhouette it is part subject, part
   background. ``shading.coverage_samples`` rays per pixel side measure the share the mesh covers
   (:func:`stages.numerics.raycast.pixel_coverage`); it is the relit images' alpha and their radiance is
   premultiplied by it. Covered pixels whose centre misses the mesh take the mean of their shaded neighbours
   (:func:`stages.numerics.novel_view.grow_edges`). The masks are alpha >= 0.5.

Outputs per action (release ``renders/``): ``cameras.json`` (the novel cameras, OpenCV, and the captured
pair each lies between), ``<view>/normal.exr``, ``albedo.exr``, ``roughness.exr``, ``mask.png`` and
``<view>/<environment>.exr`` (RGBA: linear radiance in the environment's units premultiplied by alpha, the
share of the pixel the subject covers; the G-buffer maps and ``mask.png`` cover alpha >= 0.5),
``environments.json`` (names, source files and the SG fit errors) and a preview sheet.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.exr import write_exr
from pipeline.codecs.image import label_picture, preview_linear, preview_normals, write_png
from stages.exr_headers import EXR_HEADERS
from pipeline.config import Documented, broken, checked
from pipeline.stage import Stage, StageContext
from artifacts.facade import ActionArtifacts
from stages.relightable import load_relightable_asset
from artifacts.layout import ArtifactWriter, released_files
from stages.numerics import numeric_threads
from artifacts.camera import Camera
from stages.numerics.learned_blend import LearnedBlendConfig
from stages.environments import fit_environments, raw_environment_inputs
from stages.numerics.novel_view import ViewShading, auto_exposure, relight_view

TURNTABLE_FRAMES = 12
"""Views of ``previews/turntable.png`` (30 degrees apart about +y)."""
TURNTABLE_SIZE = (240, 160)
"""(height, width) in pixels of each turntable view."""


RELEASED_RENDERS = ("render_cameras", "render_environments", "render_normal", "render_albedo", "render_roughness",
                    "render_mask", "relit")
RELEASED_PREVIEWS = ("relit_preview", "turntable_preview")
"""The products this stage publishes: the renders (each view's maps, mask and relit images under the
environments that ``renders/environments.json`` names, and the two JSON records), then the previews (when
on)."""


@dataclass(frozen=True)
class RelightConfig(Documented):
    environments: tuple[str, ...] = checked(("studio_small_03_1k", "kiara_1_dawn_1k", "forest_slope_1k"),
                                            nonempty=True)
    """Environment maps: a file path, a file name (stem) looked up in $ULTRASTAGE_HDRI, the capture's
    ``environments/`` folder and ../shared/data/hdri, or ``procedural:sky`` / ``procedural:studio``. A name
    found nowhere is replaced by the procedural sky (named and labelled so), with a warning in the log and
    its request in environments.json."""
    novel_views: int = checked(3, ge=1)
    """Novel cameras per action, each halfway between two neighbouring captured cameras."""
    sg_lobes: int = checked(32, ge=1)
    """Spherical Gaussians per environment (bench_sg: 0.9% median irradiance error at 32)."""
    fit_height: int = checked(64, ge=1)
    """Rows of the downsampled map the SG fit works on."""
    fit_iterations: int = checked(150, ge=0)
    """Iterations of the SG fit's L-BFGS (:func:`stages.numerics.sg.fit_sg_environment`; 0: the starting lobes
    with their best amplitudes). On the default capture's five maps 150 take 1.9-2.8 CPU s a map against 3.6-5.7 s
    at 300, the irradiance error 0.008-0.010 -> 0.008-0.011 (relative L2), and the relit views and the relighting
    set move by under 0.005 dB."""
    shading: ViewShading = field(default_factory=ViewShading)
    """Reprojection and shading of each novel view: sources, depth test, shading normals, shadows, F0 and the
    antialiased edges (:class:`stages.numerics.novel_view.ViewShading`, as ``relightset.shading``)."""
    diffuse_normals: bool = True
    """Reproject the normal maps with the specular reflection fitted out (``normal_diffuse`` of the
    diffuse_normals stage, when there are any) rather than eq. 1's: the relit novel views came closer to the
    simulator's with them when this default was chosen."""
    diffuse_albedo: bool = True
    """Reproject the sources' ``albedo_diffuse`` (the white-light albedo less the specular light fitted per view,
    when the diffuse_normals stage wrote it) and shade it as is, rather than the white-light albedo times the
    materials' diffuse ratio (one share per texel for every view): closer relit novel views on the default
    capture (bench/bench_relight.py scores the white-light albedo sources beside the default)."""
    min_alpha: float = checked(0.5, ge=0.0, lt=1.0)
    """Source map pixels with a lower photometric validity alpha are not reprojected."""
    previews: bool = True
    """Write a preview sheet (views x environments, tone-mapped)."""
    learned_blend: LearnedBlendConfig = field(default_factory=LearnedBlendConfig)
    """With ``enabled: true``, blend the sources with weights learned leave one out on the action's captured
    views (the paper's blending network, :mod:`stages.numerics.learned_blend`) instead of the heuristic
    weights. Off by default: on the default capture the relit novel views came no closer to the simulator's
    with it (:class:`stages.numerics.learned_blend.LearnedBlendConfig`). It needs ``shading.supersample: 1``: the
    network weighs the sources by their density per target pixel."""

    def _checks(self) -> list[str]:
        if self.learned_blend.enabled and self.shading.supersample != 1:
            return [broken(self, "shading", "supersample must be 1 with learned_blend.enabled (the network weighs "
                                            "the sources by their density per target pixel)")]
        return []


def novel_cameras(cameras: dict[str, Camera], count: int) -> list[Camera]:
    """Novel cameras ``N000``, ``N001``, ... halfway between ``count`` pairs of neighbouring captured cameras, each
    sized as the first of its pair; their records also say which pair (``between``)."""
    from stages.numerics.gbuffer import interpolate_camera, novel_camera_pairs

    ids = sorted(cameras)
    poses = [cameras[c].cam_from_world for c in ids]
    out = []
    for i, (a, b) in enumerate(novel_camera_pairs(poses, count)):
        ca, cb = cameras[ids[a]], cameras[ids[b]]
        K, pose = interpolate_camera(ca.K, poses[a], cb.K, poses[b], 0.5)
        out.append(Camera(K, pose, ca.width, ca.height, camera_id=f"N{i:03d}",
                          record={"camera_id": f"N{i:03d}", "between": [ids[a], ids[b]]}))
    return out


class RelightStage(Stage):
    """Relit novel views: reprojected G-buffers shaded under SG-fitted environments."""

    name = "relight"
    # 8: edge pixels take the mean of their shaded neighbours (bake.dilate_texture), not the nearest one's;
    # 7: the coverage grid cast at the silhouette only; 6: antialiased silhouettes (alpha = pixel coverage);
    # 5: fused shading normals (normal_fusion_m); 4: G-buffers read the sources with cubic convolution
    # 9: the relit sheet's tiles are labelled (view, environment); previews/turntable.png, the textured mesh
    # from TURNTABLE_FRAMES azimuths side by side; 10: the fused normals fade to the mesh's on the silhouette's rim
    # (shading.rim_normal_px)
    version = "10"
    scope = "action"
    requires = ("geometry", "textures", "materials", "decode", "photometric", "diffuse_normals")
    outputs = ("renders", "previews")

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        return raw_environment_inputs(self.config.environments, getattr(capture, "root", None))

    def run(self, ctx: StageContext) -> dict[str, Any]:
        import torch

        torch.set_num_threads(numeric_threads())
        cfg: RelightConfig = self.config
        started = time.perf_counter()
        out = ArtifactWriter(self.name, ctx.out_dir)
        out.path("render_cameras").parent.mkdir(parents=True, exist_ok=True)
        environments = fit_environments(cfg.environments, ctx.raw_inputs, cfg.sg_lobes, cfg.fit_height, ctx.log,
                                        ctx.cache_dir, iterations=cfg.fit_iterations)
        asset, cameras = load_relightable_asset(ActionArtifacts(ctx.upstream), cfg.min_alpha, cfg.diffuse_normals,
                                                cfg.diffuse_albedo)
        views = novel_cameras(cameras, cfg.novel_views)
        blend = learned_blend(asset, cfg, ctx.log)
        records, sheet_rows = relight_views(asset, views, environments, cfg, blend, out, ctx.progress)
        out.path("render_cameras").write_text(json.dumps({"camera_convention": "opencv", "units": "metres",
                                                          "cameras": records}, indent=1))
        out.path("render_environments").write_text(json.dumps(_environments_record(environments, cfg, blend),
                                                              indent=1, default=float))
        if cfg.previews:
            _write_previews(out, sheet_rows, asset)
        return _run_stats(views, environments, asset, blend) | {"seconds": time.perf_counter() - started}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        """The renders (sorted by path, so each view's files lie together), then the previews (when on)."""
        environments = [e["label"] for e in ActionArtifacts({self.name: artifact}).json("render_environments")
                        ["environments"]]
        renders = released_files(self.name, artifact, RELEASED_RENDERS, fields={"environment": environments})
        return sorted(renders, key=lambda f: f[0]) + released_files(self.name, artifact, RELEASED_PREVIEWS,
                                                                    optional=RELEASED_PREVIEWS)


def learned_blend(asset: Any, cfg: RelightConfig, log: Any) -> Any:
    """The blend of the sources learned on the captured views (:func:`stages.numerics.novel_view.fit_blend`,
    logged), or None when ``cfg.learned_blend`` keeps the heuristic weights."""
    from stages.numerics.novel_view import fit_blend

    blend = fit_blend(asset, cfg.learned_blend, cfg.shading.sources, cfg.shading.depth_tolerance_m)
    if blend is not None:
        log.info("relight: learned blend on %d views, %d pixels: loss %.4f vs heuristic %.4f (%.0f s)",
                 blend.record["views"], blend.record["pixels"], blend.record["learned_loss"],
                 blend.record["heuristic_loss"], blend.record["gather_s"] + blend.record["train_s"])
    return blend


def relight_views(asset: Any, views: list[Camera], environments: list[dict[str, Any]], cfg: RelightConfig,
                  blend: Any, out: ArtifactWriter, progress: Any) -> tuple[list[dict[str, Any]], list[np.ndarray]]:
    """Relights each novel view under every environment and writes its files (:func:`_write_view`); returns the
    views' records of ``renders/cameras.json`` and the rows of the preview sheet."""
    from stages.numerics.sg import fibonacci_sphere

    directions = fibonacci_sphere(cfg.shading.visibility_directions) if cfg.shading.shadows else None
    records, sheet_rows = [], []
    for index, view in enumerate(views):
        t0 = time.perf_counter()
        rendered = relight_view(asset, view.K, view.cam_from_world, view.height, view.width,
                                [env["lobes"] for env in environments], cfg.shading, blend=blend,
                                directions=directions)
        sheet_rows.append(_write_view(out, view.camera_id, rendered, environments))
        records.append({**view.to_json(), "pixels": rendered["pixels"], "mask_pixels": int(rendered["mask"].sum()),
                        "coverage": rendered["coverage"], "normal_fusion_px": rendered["normal_fusion_px"],
                        "seconds": time.perf_counter() - t0})
        progress(index + 1, len(views), f"view {view.camera_id} relit under {len(environments)} environment(s)")
    return records, sheet_rows


def _write_view(out: ArtifactWriter, camera_id: str, rendered: dict[str, Any],
                environments: list[dict[str, Any]]) -> np.ndarray:
    """Writes one novel view's G-buffer maps, mask and relit images (RGBA, premultiplied); returns its row of
    the preview sheet (normals, then each environment tone-mapped)."""
    maps, out_mask, alpha = rendered["maps"], rendered["mask"], rendered["alpha"]
    for name, image in maps.items():
        write_exr(out.path(f"render_{name}", camera_id), image, header=EXR_HEADERS[f"render_{name}"])
    write_png(out.path("render_mask", camera_id), (out_mask * 255).astype(np.uint8))
    row = [label_picture(preview_normals(maps["normal"], out_mask.astype(np.float32)), f"{camera_id} normal")]
    for env, image in zip(environments, rendered["images"]):
        write_exr(out.path("relit", camera_id, environment=env["label"]),
                  np.concatenate([image, alpha[..., None]], axis=2), header=EXR_HEADERS["relit"])
        row.append(label_picture(preview_linear(image, exposure=auto_exposure(image, out_mask)),
                                 f"{camera_id} {env['label']}"))
    return np.concatenate(row, axis=1)


def _environments_record(environments: list[dict[str, Any]], cfg: RelightConfig, blend: Any) -> dict[str, Any]:
    """The content of ``renders/environments.json``: each environment with its lobes, the shading settings and
    the blend's record."""
    shading, samples = cfg.shading, cfg.shading.coverage_samples
    return {"environments": [{k: v for k, v in e.items() if k != "lobes"} | {"lobes": e["lobes"].numpy().to_dict()}
                             for e in environments],
            "shading": {"sg_lobes": cfg.sg_lobes, "shadows": shading.shadows, "f0": shading.f0,
                        "integration": shading.integration, "visibility_directions": shading.visibility_directions,
                        "normals": shading.normals, "radiance_units": "the environment map's",
                        "alpha": (f"pixel coverage of {samples} x {samples} rays, radiance premultiplied"
                                  if samples > 1 else "mask (pixel centres)")},
            "blend": blend.record if blend is not None else "heuristic"}


def _run_stats(views: list[Camera], environments: list[dict[str, Any]], asset: Any, blend: Any) -> dict[str, Any]:
    """The stage's statistics: views, environments (and which fell back), the sources' albedo, fit times."""
    return {"novel_views": len(views), "environments": [e["label"] for e in environments],
            "source_albedo": "albedo_diffuse" if asset.sources_diffuse_albedo else "albedo x diffuse_ratio",
            "fallbacks": [e["name"] for e in environments if e["source"].startswith("FALLBACK")],
            "sg_fit_seconds": float(sum(e["fit_seconds"] for e in environments)),
            "blend_seconds": float(blend.record["gather_s"] + blend.record["train_s"]) if blend is not None else 0.0}


def _write_previews(out: ArtifactWriter, sheet_rows: list[np.ndarray], asset: Any) -> None:
    """``previews/relit.png`` (views x environments) and ``previews/turntable.png`` (the textured mesh from
    TURNTABLE_FRAMES azimuths)."""
    from stages.numerics.turntable import turntable_cameras, turntable_strip

    if sheet_rows:
        write_png(out.path("relit_preview"), np.concatenate(sheet_rows, axis=0))
    cams = turntable_cameras(asset.vertices, TURNTABLE_FRAMES, *TURNTABLE_SIZE)
    strip = turntable_strip(asset.atlas_scene, asset.atlas.faces, asset.atlas.uvs, asset.albedo_tex, cams,
                            *TURNTABLE_SIZE)
    write_png(out.path("turntable_preview"), preview_linear(strip, exposure=1.0))
