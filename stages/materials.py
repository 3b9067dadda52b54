"""Action stage ``materials``: roughness by inverse rendering under the stage's own illuminations, and an
albedo with the ambient occlusion divided out, both as textures over the action's UV atlas.

Wiring only; the numerics are :func:`stages.numerics.bake.gather_observations` (each texel's values in the
cameras that see it best, depth-tested against the mesh), :func:`stages.numerics.materials.fit_roughness`
(GGX under full_on / pos / neg in closed form, F0 fixed) and :func:`stages.numerics.shadowing.ambient_occlusion`.

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
  median (the others take their nearest voters'): MAE 0.078 / 0.080 -> 0.061 / 0.067.
* Ambient occlusion: the stage's white light is uniform over the sphere, so the white-light albedo is the
  true albedo times the cosine-weighted visible fraction of the sphere. ``albedo_deoccluded`` divides the
  baked albedo by that fraction computed on the mesh (floored at ``min_occlusion``): 28.0 -> 28.9 dB
  (A0000), 26.7 -> 27.2 dB (A0001) against the simulator's albedo.
* The white-light albedo also holds the specular light (6-7% brighter than the truth on the simulator). The
  roughness fit splits each texel's light into diffuse and specular; ``diffuse_ratio`` (RGB, at the
  roughness texture's size) is the fitted diffuse albedo over the white-light one, and ``albedo_intrinsic``
  = baked albedo x diffuse_ratio / occlusion: 31.1 dB (A0000) and 28.3 dB (A0001), the closest to the truth.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.exr import read_exr, write_exr
from stages.exr_headers import EXR_HEADERS
from pipeline.codecs.image import preview_linear, preview_scalar, write_png
from pipeline.config import Documented
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from stages.artifacts import camera_maps
from stages.numerics import numeric_threads

ILLUMINATION_DIRS = ("full_on", "pos", "neg")


@dataclass(frozen=True)
class MaterialsConfig(Documented):
    texture_size: int = 256
    """Width and height of the roughness texture (the atlas of the textures stage; roughness varies slowly)."""
    max_views: int = 16
    """Cameras used per texel (the best by angle, distance and support). On the simulator with the mesh of the
    one-pass SDF 8 and 16 were close (MAE 0.061/0.067 vs 0.068/0.068 on A0000/A0001); with the two-pass mesh
    (geometry.deocclude) 8 views fit too smooth (0.067/0.082, bias -0.025/-0.040) and 16 views give
    0.061/0.067 (bias +0.041/+0.015), for 2.5 s more per action (bench_materials)."""
    specular_model: str = "ggx_table"
    """"ggx_table" (exact GGX lobe moments under the linear gradients) or "sg" (the spherical-Gaussian lobes
    relighting uses). Measured on the simulator the table is the more accurate (see bench_materials)."""
    f0: float = 0.02
    """Fresnel reflectance at normal incidence (skin, as the paper)."""
    fit_albedo: bool = True
    """Solve the diffuse albedo with the roughness (the white-light albedo still holds specular light)."""
    roughness_min: float = 0.05
    """Lower bound of the fitted perceptual roughness."""
    roughness_max: float = 1.0
    """Upper bound of the fitted perceptual roughness."""
    median_neighbours: int = 100
    """Texels (nearest on the surface) whose median gives the published roughness; 1 = no smoothing."""
    median_min_visibility: float = 0.95
    """Only texels whose ambient visibility on the mesh (cosine-weighted visible fraction, ``occlusion_rays``
    rays) reaches this vote in that median; the others take the median of their nearest voters. The fit
    assumes every LED above a texel's horizon lights it, so texels the body itself shadows come out too rough:
    on the default capture shiny leather (0.25) was fitted 0.30 where the simulator's visibility is >= 0.95 and
    0.51-0.54 below 0.85, skin (0.45) 0.47 and 0.60-0.68. Roughness MAE (bench scratch, A0000 / A0001) 0.078 /
    0.080 with every fitted texel voting, 0.074 / 0.076 at 0.85, 0.061 / 0.067 at 0.95 (the voters: 60% of
    the texels). 0 = every fitted texel votes."""
    occlusion_rays: int = 64
    """Cosine-weighted rays per texel for the ambient occlusion."""
    occlusion_size: int = 512
    """Texture size at which the occlusion is computed (then sampled at the albedo texture's size)."""
    min_occlusion: float = 0.2
    """Floor of the visible fraction the albedo is divided by (deep creases would blow up noise)."""
    min_alpha: float = 0.5
    """Map pixels with a lower photometric validity alpha are not used."""
    depth_tolerance_m: float = 0.01
    """A texel is visible in a camera when its depth agrees with the mesh's depth there within this."""
    min_cos: float = 0.2
    """Cameras at more grazing angles to a texel than this cosine are not used."""
    previews: bool = True
    """Write PNG previews of roughness, fit error, occlusion and the de-occluded albedo."""

    def __post_init__(self) -> None:
        if self.specular_model not in ("ggx_table", "sg"):
            raise ValueError(f"materials.specular_model must be 'ggx_table' or 'sg', got {self.specular_model!r}")
        if not 0 < self.roughness_min < self.roughness_max <= 1:
            raise ValueError("materials: need 0 < roughness_min < roughness_max <= 1")
        if not 0 < self.min_occlusion <= 1:
            raise ValueError("materials.min_occlusion must be in (0, 1]")
        if not 0 <= self.median_min_visibility <= 1:
            raise ValueError("materials.median_min_visibility must be in [0, 1]")
        for name in ("texture_size", "max_views", "median_neighbours", "occlusion_rays", "occlusion_size"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"materials.{name} must be >= 1")


def fitted_f0(artifact: Path) -> float:
    """The Fresnel F0 a materials artifact's roughness texture was fitted with (its record's config): roughness
    and F0 trade off under broad light, so whoever models the specular light with that texture uses this F0."""
    path = Path(artifact) / "_SUCCESS.json"
    try:
        f0 = float(json.loads(path.read_text())["record"]["config"]["f0"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(path, f"no materials f0 in the artifact's record ({type(exc).__name__}: {exc})") from exc
    if not 0.0 <= f0 <= 1.0:
        raise InputError(path, f"materials f0 {f0} is outside [0, 1]")
    return f0


def load_atlas_mesh(obj_path: Path):
    """The textured OBJ of the textures stage as ``(vertices (V, 3) welded, faces (F, 3) into them,
    Atlas)``: the OBJ splits vertices along chart seams; welding identical positions gives back one
    surface, so normals and depth maps are continuous across seams."""
    from pipeline.codecs.mesh import read_obj
    from stages.numerics.mesh import Atlas

    obj = read_obj(obj_path)
    if obj["uvs"] is None or obj["uv_faces"] is None or not np.array_equal(obj["uv_faces"], obj["faces"]):
        raise InputError(obj_path, "the textured mesh has no per-vertex UVs (uv faces must equal faces)")
    vertices, inverse = np.unique(np.asarray(obj["vertices"], np.float64), axis=0, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1).astype(np.int64)
    faces = inverse[obj["faces"]]
    atlas = Atlas(vmapping=inverse, faces=np.asarray(obj["faces"], np.int32), uvs=np.asarray(obj["uvs"], np.float32),
                  width=1, height=1, stats={})
    return vertices, faces, atlas


def texel_uvs(covered: np.ndarray) -> np.ndarray:
    """OBJ-convention UVs (N, 2) of the covered texels' centres, in row-major order."""
    size = covered.shape[0]
    rows, cols = np.nonzero(covered)
    return np.stack([(cols + 0.5) / size, 1.0 - (rows + 0.5) / size], axis=1)


def surface_median(points: np.ndarray, values: np.ndarray, usable: np.ndarray, neighbours: int) -> np.ndarray:
    """Median of ``values`` over each point's ``neighbours`` nearest usable points in 3D, (N,) float32.

    points: (N, 3); values: (N,); usable: (N,) bool (e.g. points that had observations). With no usable
    point (or ``neighbours`` 1) the values come back unchanged."""
    from scipy.spatial import cKDTree

    values = np.asarray(values, np.float32)
    if neighbours <= 1 or not usable.any():
        return values.copy()
    k = int(min(neighbours, usable.sum()))
    _, nearest = cKDTree(points[usable]).query(points, k=k)
    nearest = nearest.reshape(len(points), k)
    return np.median(values[usable][nearest], axis=1).astype(np.float32)


def roughness_median(points: np.ndarray, roughness: np.ndarray, fitted: np.ndarray, visibility: np.ndarray,
                     min_visibility: float, neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """The published roughness: each texel's median over its ``neighbours`` nearest *voters*, the fitted
    texels (``fitted`` (N,) bool) whose ``visibility`` (N,) reaches ``min_visibility`` (every fitted texel
    when none does). points (N, 3), roughness (N,). Returns the (N,) float32 median and the (N,) bool voters."""
    voters = np.asarray(fitted, bool) & (np.asarray(visibility) >= min_visibility)
    if not voters.any():
        voters = np.asarray(fitted, bool)
    return surface_median(points, roughness, voters, neighbours), voters


def texel_samples(vertices: np.ndarray, faces: np.ndarray, atlas: Any, albedo_texture: np.ndarray,
                  views: list[Any], cfg: MaterialsConfig) -> dict[str, Any]:
    """Step 1 of the roughness: the texels of a ``cfg.texture_size`` atlas and their observations.

    vertices (V, 3), faces (F, 3) and atlas: :func:`load_atlas_mesh`; albedo_texture (T', T', 3): the baked
    white-light albedo; views: :class:`stages.numerics.bake.BakeView` with ``images["obs"]`` (H, W, 9) =
    full_on | pos | neg. Returns ``covered`` (T, T) bool, per covered texel in row-major order ``points`` and
    ``normals`` (N, 3) float64 and ``albedo`` (N, 3), and ``obs``: :func:`stages.numerics.bake.gather_observations`
    of the ``cfg.max_views`` best views (best first), with the config's depth tolerance and grazing limit."""
    from stages.numerics.bake import gather_observations, rasterize_atlas, sample_texture

    raster = rasterize_atlas(vertices, faces, atlas, int(cfg.texture_size))
    covered = raster["covered"]
    points = raster["position"][covered].astype(np.float64)
    normals = raster["normal"][covered].astype(np.float64)
    albedo = sample_texture(albedo_texture, texel_uvs(covered))
    obs = gather_observations(vertices, faces, points, normals, views, cfg.max_views,
                              depth_tolerance_m=cfg.depth_tolerance_m, min_cos=cfg.min_cos)
    return {"covered": covered, "points": points, "normals": normals, "albedo": albedo, "obs": obs}


def fit_texel_roughness(observed: np.ndarray, view_dirs: np.ndarray, valid: np.ndarray, normals: np.ndarray,
                        albedo: np.ndarray, white_scale: np.ndarray,
                        cfg: MaterialsConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2: the per-texel fit with the config's model, F0, bounds and albedo solve (arrays as
    :func:`stages.numerics.materials.fit_roughness`, whose ``(roughness, rms, diffuse albedo)`` it returns;
    texels without views have rms ``NO_VIEWS_RESIDUAL``)."""
    from stages.numerics.materials import fit_roughness

    return fit_roughness(observed, view_dirs, valid, normals, albedo, white_scale=white_scale,
                         r_min=cfg.roughness_min, r_max=cfg.roughness_max, f0=cfg.f0,
                         specular_model=cfg.specular_model, fit_albedo=cfg.fit_albedo, return_albedo=True)


def published_roughness(points: np.ndarray, roughness: np.ndarray, fitted: np.ndarray, visibility: np.ndarray,
                        cfg: MaterialsConfig) -> tuple[np.ndarray, np.ndarray]:
    """Step 3: :func:`roughness_median` with the config's voters and neighbours, within the config's bounds
    (0.5 where no texel voted). Returns the (N,) float32 roughness and the (N,) bool voters."""
    smooth, voters = roughness_median(points, roughness, fitted, visibility, cfg.median_min_visibility,
                                      cfg.median_neighbours)
    return np.clip(np.nan_to_num(smooth, nan=0.5), cfg.roughness_min, cfg.roughness_max), voters


def texel_texture(values: np.ndarray, covered: np.ndarray, fill: float | None = None) -> np.ndarray:
    """A (T, T[, C]) float32 texture holding ``values`` (N[, C]) at the ``covered`` (T, T) texels in row-major
    order, grown past the charts' borders (:func:`dilate_covered`, ``fill`` beyond)."""
    texture = np.zeros(covered.shape + np.shape(values)[1:], np.float32)
    texture[covered] = values
    return dilate_covered(texture, covered, fill=fill)


def albedo_without_occlusion(albedo_texture: np.ndarray, occlusion_texture: np.ndarray, min_occlusion: float,
                             diffuse_ratio_texture: np.ndarray | None = None) -> np.ndarray:
    """The baked albedo (T, T, 3) divided by the occlusion texture (sampled at its texels, floored at
    ``min_occlusion``), times the diffuse-ratio texture when given (``albedo_intrinsic``), in [0, 1]."""
    from stages.numerics.bake import sample_texture

    uv_full = texel_uvs(np.ones(albedo_texture.shape[:2], bool)).reshape(albedo_texture.shape[:2] + (2,))
    occlusion_full = np.maximum(sample_texture(occlusion_texture, uv_full), min_occlusion)[..., None]
    albedo = (albedo_texture if diffuse_ratio_texture is None
              else albedo_texture * sample_texture(diffuse_ratio_texture, uv_full))
    return np.clip(np.nan_to_num(albedo / occlusion_full, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)


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

        from stages.numerics.bake import BakeView, rasterize_atlas
        from stages.numerics.materials import NO_VIEWS_RESIDUAL
        from stages.numerics.raycast import mesh_scene
        from stages.numerics.shadowing import ambient_occlusion

        torch.set_num_threads(numeric_threads())
        cfg: MaterialsConfig = self.config
        decode, photometric, textures = ctx.upstream["decode"], ctx.upstream["photometric"], ctx.upstream["textures"]
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        vertices, faces, atlas = load_atlas_mesh(textures / "mesh" / "textured.obj")
        albedo_texture = read_exr(textures / "textures" / "albedo.exr")[..., :3]
        cameras = json.loads((decode / "cameras.json").read_text())["cameras"]
        white = {c["camera_id"]: np.asarray(c["white_reference"], np.float32) for c in cameras}
        views, ids = [], []
        for cam_id, cam, _, _, valid in camera_maps(decode, photometric, cfg.min_alpha):
            images = [read_exr(decode / ill / f"{cam_id}.exr")[..., :3] for ill in ILLUMINATION_DIRS]
            views.append(BakeView(images={"obs": np.concatenate(images, axis=2)}, valid=valid,
                                  K=np.asarray(cam["K"], np.float64),
                                  cam_from_world=np.asarray(cam["cam_from_world"], np.float64)))
            ids.append(cam_id)
        if not views:
            raise InputError(photometric / "normal_alpha", "no camera has photometric maps")
        timings["load_s"] = time.perf_counter() - t0

        # Roughness: observations per texel, a per-texel fit, then a median over surface neighbours.
        t0 = time.perf_counter()
        size = int(cfg.texture_size)
        texels = texel_samples(vertices, faces, atlas, albedo_texture, views, cfg)
        covered, points, normals, albedo, obs = (texels[k] for k in ("covered", "points", "normals", "albedo", "obs"))
        ctx.progress(1, 3, f"{len(points)} texels, {obs['valid'].sum(axis=1).mean():.1f} views each")
        timings["observations_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        white_per_obs = np.stack([white[c] for c in ids])[np.maximum(obs["view_index"], 0)]
        observed = obs["values"]["obs"].reshape(len(points), -1, 3, 3)
        roughness, fit_rms, diffuse_albedo = fit_texel_roughness(observed, obs["view_dirs"], obs["valid"], normals,
                                                                 albedo, white_per_obs, cfg)
        fitted = fit_rms != NO_VIEWS_RESIDUAL
        mesh = mesh_scene(vertices, faces)
        # The share of the white-light albedo that the fit explains as diffuse (the rest is specular light).
        diffuse_ratio = np.where(fitted[:, None] & (albedo > 0.02), diffuse_albedo / np.maximum(albedo, 1e-3), 1.0)
        diffuse_ratio = np.clip(np.nan_to_num(diffuse_ratio, nan=1.0), 0.5, 1.5).astype(np.float32)
        # texels the body shadows from part of the stage fit too rough: they take their unshadowed neighbours'
        texel_visibility = ambient_occlusion(points, normals, mesh, rays=cfg.occlusion_rays)
        smooth, voters = published_roughness(points, roughness, fitted, texel_visibility, cfg)
        timings["fit_s"] = time.perf_counter() - t0
        ctx.progress(2, 3, f"roughness fitted in {timings['fit_s']:.1f} s")

        roughness_tex = texel_texture(smooth, covered)
        rms_tex = np.zeros((size, size), np.float32)
        rms_tex[covered] = np.where(fitted, fit_rms, 0.0)
        ratio_tex = texel_texture(diffuse_ratio, covered, fill=1.0)

        # Ambient occlusion on the mesh, divided out of the baked albedo.
        t0 = time.perf_counter()
        occ_size = int(cfg.occlusion_size)
        occ_raster = rasterize_atlas(vertices, faces, atlas, occ_size)
        occ_covered = occ_raster["covered"]
        visible = ambient_occlusion(occ_raster["position"][occ_covered].astype(np.float64),
                                    occ_raster["normal"][occ_covered].astype(np.float64),
                                    mesh, rays=cfg.occlusion_rays)
        occlusion_tex = texel_texture(visible, occ_covered, fill=1.0)
        deoccluded = albedo_without_occlusion(albedo_texture, occlusion_tex, cfg.min_occlusion)
        intrinsic = albedo_without_occlusion(albedo_texture, occlusion_tex, cfg.min_occlusion, ratio_tex)
        timings["occlusion_s"] = time.perf_counter() - t0

        out = ctx.out_dir
        for name, texture in (("roughness", roughness_tex), ("roughness_fit_rms", rms_tex), ("occlusion", occlusion_tex),
                              ("albedo_deoccluded", deoccluded.astype(np.float32)), ("diffuse_ratio", ratio_tex),
                              ("albedo_intrinsic", intrinsic.astype(np.float32))):
            write_exr(out / "textures" / f"{name}.exr", texture, header=EXR_HEADERS[f"texture_{name}"])
        if cfg.previews:
            write_png(out / "previews" / "texture_roughness.png", preview_scalar(roughness_tex))
            write_png(out / "previews" / "texture_occlusion.png", preview_scalar(occlusion_tex))
            write_png(out / "previews" / "texture_albedo_intrinsic.png", preview_linear(intrinsic, exposure=1.0))
        used = smooth[fitted] if fitted.any() else smooth
        return {"texels": int(len(points)), "texels_fitted": int(fitted.sum()), "cameras": len(views),
                "mean_views": float(obs["valid"].sum(axis=1).mean()) if len(points) else 0.0,
                "roughness_mean": float(used.mean()) if len(used) else 0.0,
                "roughness_p10": float(np.percentile(used, 10)) if len(used) else 0.0,
                "roughness_p90": float(np.percentile(used, 90)) if len(used) else 0.0,
                "fit_rms_median": float(np.median(fit_rms[fitted])) if fitted.any() else 0.0,
                "median_voters_fraction": float(voters.sum() / max(int(fitted.sum()), 1)),
                "occlusion_mean": float(visible.mean()) if len(visible) else 1.0,
                "diffuse_ratio_median": float(np.median(diffuse_ratio[fitted])) if fitted.any() else 1.0,
                "specular_model": cfg.specular_model, **timings}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        files = [(p, f"textures/{p.name}", f"texture_{p.stem}", None)
                 for p in sorted((artifact / "textures").glob("*.exr"))]
        for p in sorted((artifact / "previews").glob("*.png")) if (artifact / "previews").exists() else []:
            files.append((p, f"previews/{p.name}", f"preview_{p.stem}", None))
        return files


def dilate_covered(texture: np.ndarray, covered: np.ndarray, fill: float | None = None, px: int = 4) -> np.ndarray:
    """Grow the covered texels of a (T, T) or (T, T, C) texture ``px`` texels (bilinear lookups at chart
    borders must not pull the empty value); texels still empty get ``fill`` (default: the covered texels'
    median)."""
    from stages.numerics.bake import dilate_texture

    channels = texture if texture.ndim == 3 else texture[..., None]
    grown, filled = dilate_texture({"t": channels}, covered, px)
    default = (np.median(channels[covered], axis=0) if fill is None and covered.any()
               else np.full(channels.shape[2], fill or 0.0))
    out = np.where(filled[..., None], grown["t"], default).astype(np.float32)
    return out if texture.ndim == 3 else out[..., 0]
