"""The materials stage's action: texel observations -> roughness, ambient occlusion and albedo textures.

:func:`material_textures` runs the three steps over the action's UV atlas (:func:`texel_samples`,
:func:`fit_texel_materials`, :func:`published_roughness`), the ambient occlusion on the mesh and the albedos
divided by it; the stage module (stages/materials.py) says why each step is there and what it measured. Pure:
arrays and dataclasses in, arrays out. ``cfg`` is a :class:`MaterialTexturesConfig` (the materials stage's config
is one, with the stage's own fields added).
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.config import Documented, checked


@dataclass(frozen=True)
class MaterialTexturesConfig(Documented):
    """The roughness fit, its median, the ambient occlusion and the visibility tests: what
    :func:`material_textures` reads (the fields of the materials stage's config that are not the stage's own,
    under the same names)."""

    texture_size: int = checked(256, ge=1)
    """Width and height of the roughness texture (the atlas of the textures stage; roughness varies slowly)."""
    max_views: int = checked(16, ge=1)
    """Cameras used per texel (the best by angle, distance and support, within ``min_cos``). On the default
    capture (``python bench/bench_materials.py``, A0000 / A0001) 8 views give MAE 0.054 / 0.055 (bias -0.006 /
    -0.009), 16 views 0.051 / 0.056 (bias +0.016 / -0.003) for about 1.5 s more fit per action."""
    specular_model: str = checked("ggx_table", one_of=("ggx_table", "sg"))
    """"ggx_table" (exact GGX lobe moments under the linear gradients) or "sg" (the spherical-Gaussian lobes
    relighting uses). Measured on the simulator the table is the more accurate (see bench_materials)."""
    f0: float = checked(0.028, ge=0.0, le=1.0)
    """Fresnel reflectance at normal incidence the roughness is fitted with, and that ``albedo_diffuse`` takes the
    specular light out with: skin's (refractive index 1.4), the F0 the relit views are shaded with
    (:class:`stages.numerics.novel_view.ViewShading`), so the fitted roughness is read under the Fresnel it was
    fitted for. At 0.02 (the paper's) and 0.028 (with ``min_cos`` 0.2), on the default capture / the unseen one
    (``simulate --seed 3 --width 384``): relit views 27.20 and 27.31 / 28.49 and 28.70 dB, relighting set 27.80 and
    27.94 / 28.67 and 28.84 dB, the intrinsic albedo texture 32.46 and 33.09 / 32.90 and 33.59 dB; at 0.028 the
    roughness comes out rougher, MAE 0.060 and 0.064 / 0.053 and 0.058 (bias +0.029 and +0.038 / +0.029 and +0.037),
    and ``albedo_diffuse`` darker, 25.60 and 25.42 / 25.58 and 25.41 dB against the simulator's albedo. At 0.04
    (cloth's) the default capture's relit views score 27.15 dB and the roughness MAE 0.074."""
    fit_albedo: bool = True
    """Solve the diffuse albedo with the roughness (the white-light albedo still holds specular light)."""
    albedo_max_views: int = checked(8, ge=0)
    """With ``fit_albedo``, take the diffuse albedo (the ``diffuse_ratio`` and ``albedo_intrinsic`` textures) from a
    second joint fit on the best this many of the gathered views, every valid observation among them (no
    mirror-cone test); the roughness stays the first fit's. 0: the albedo of the roughness fit. The observations
    the mirror-cone test leaves out mislead the roughness, not the albedo, and the albedo is better from the more
    frontal views: on the default capture (``python bench/bench_materials.py``, A0000 / A0001) the intrinsic
    albedo texture scores 34.51 / 31.63 dB from the roughness fit, 34.85 / 31.92 dB from 8 views and 34.72 / 31.76
    dB from 16, and 4 views 34.82 / 32.04 dB. The second fit on 8 views costs 1-3 s per action."""
    roughness_min: float = checked(0.05, gt=0.0, lt="roughness_max")
    """Lower bound of the fitted perceptual roughness."""
    roughness_max: float = checked(1.0, le=1.0)
    """Upper bound of the fitted perceptual roughness."""
    median_neighbours: int = checked(100, ge=1)
    """Texels (nearest on the surface) whose median gives the published roughness; 1 = no smoothing."""
    median_albedo_m: float = checked(0.15, ge=0.0)
    """The median's neighbours are nearest in albedo too (:func:`albedo_guide`, the log of each channel of the
    baked white-light albedo): a unit of log-albedo difference counts as this many metres on the surface (0:
    nearest on the surface alone). A material narrower than the median's neighbourhood keeps its own roughness:
    on the default capture the shiny belt (0.25) reads 0.30 / 0.34 (A0000 / A0001) with it and 0.37 / 0.38 without,
    the median of the cloth around it (``python bench/bench_materials.py``, its guide rows; the README's *The
    albedo-guided roughness median*)."""
    median_albedo_neighbours: int = checked(32, ge=1)
    """The guide's log-albedo is each texel's mean over its this many nearest texels on the surface: a pattern
    finer than that (a plaid's stripes) stays one material, whose stripes the per-texel fit would otherwise
    split by their albedo (1: each texel's own albedo)."""
    median_min_visibility: float = checked(0.95, ge=0.0, le=1.0)
    """Only texels whose ambient visibility on the mesh (cosine-weighted visible fraction, ``occlusion_rays``
    rays) reaches this vote in that median; the others take the median of their nearest voters. The fit
    assumes every LED above a texel's horizon lights it, so texels the body itself shadows come out too rough:
    on the default capture shiny leather (0.25) was fitted 0.30 where the simulator's visibility is >= 0.95 and
    0.51-0.54 below 0.85, skin (0.45) 0.47 and 0.60-0.68. Roughness MAE (bench_materials, A0000 / A0001) 0.073
    / 0.076 with every fitted texel voting, 0.061 / 0.064 at 0.85, 0.051 / 0.056 at 0.95 (the voters: about 60%
    of the texels). 0 = every fitted texel votes."""
    occlusion_rays: int = checked(64, ge=1)
    """Cosine-weighted rays per texel for the ambient occlusion."""
    occlusion_size: int = checked(512, ge=1)
    """Texture size at which the occlusion is computed (then sampled at the albedo texture's size)."""
    min_occlusion: float = checked(0.2, gt=0.0, le=1.0)
    """Floor of the visible fraction the albedo is divided by (deep creases would blow up noise)."""
    depth_tolerance_m: float = 0.01
    """A texel is visible in a camera when its depth agrees with the mesh's depth there within this."""
    min_cos: float = checked(0.3, ge=-1.0, lt=1.0)
    """Cameras at more grazing angles to a texel than this cosine are not used (``python bench/bench_materials.py``
    sweeps it with the mirror-cone test below)."""
    specular_cone_deg: float = checked(15.0, ge=0.0, lt=90.0)
    """An observation is used only where the mesh leaves the view's mirror direction open: the view direction
    reflected about the texel's normal and 8 directions this many degrees around it meet nothing
    (:func:`mirror_cone_open`; 0: no test). The fit assumes every LED above the texel's horizon lights it;
    where the body hides part of the specular lobe the observation loses the lobe's far side and reads rougher.
    Grazing views reflect towards the horizon, where the body hides most: without the test the fit read grazing
    views rougher than frontal ones on every material. On the default capture (``python
    bench/bench_materials.py``, A0000 / A0001) the test leaves out about a fifth of the observations; roughness
    MAE 0.0505 / 0.0561 without it at ``min_cos`` 0.4, 0.0411 / 0.0510 with it at 0.3, 0.0406 / 0.0518 at 0.2,
    0.0464 / 0.0548 at 0.4; cones of 8 and 25 degrees 0.0437 / 0.0521 and 0.0468 / 0.0535. About 1 s of
    tracing per action."""


def texel_uvs(covered: np.ndarray) -> np.ndarray:
    """OBJ-convention UVs (N, 2) of the covered texels' centres, in row-major order."""
    size = covered.shape[0]
    rows, cols = np.nonzero(covered)
    return np.stack([(cols + 0.5) / size, 1.0 - (rows + 0.5) / size], axis=1)


def _median_is_identity(neighbours: int, usable: np.ndarray) -> bool:
    """Whether :func:`surface_median` returns its values unchanged: one neighbour, or no usable point."""
    return neighbours <= 1 or not np.asarray(usable, bool).any()


def surface_median(points: np.ndarray, values: np.ndarray, usable: np.ndarray, neighbours: int,
                   guide: np.ndarray | None = None, guide_m: float = 0.0) -> np.ndarray:
    """Median of ``values`` over each point's ``neighbours`` nearest usable points, (N,) float32.

    points: (N, 3) metres; values: (N,); usable: (N,) bool (e.g. points that had observations). "Nearest" is in
    3D, or with ``guide`` (N, F) and ``guide_m`` > 0 in the joint space of the points and ``guide_m`` times the
    guide's features (a unit of feature difference counts as ``guide_m`` metres). With no usable point (or
    ``neighbours`` 1) the values come back unchanged."""
    from scipy.spatial import cKDTree

    values = np.asarray(values, np.float32)
    if _median_is_identity(neighbours, usable):
        return values.copy()
    if not (np.isfinite(guide_m) and guide_m >= 0):
        raise ValueError(f"guide_m must be finite and >= 0, got {guide_m}")
    coords = np.asarray(points, np.float64)
    if guide is not None and guide_m > 0:
        guide = np.asarray(guide, np.float64).reshape(len(coords), -1)
        if not np.all(np.isfinite(guide)):
            raise ValueError("guide holds NaN or Inf")
        coords = np.hstack([coords, guide_m * guide])
    k = int(min(neighbours, usable.sum()))
    _, nearest = cKDTree(coords[usable]).query(coords, k=k)
    nearest = nearest.reshape(len(points), k)
    return np.median(values[usable][nearest], axis=1).astype(np.float32)


def roughness_median(points: np.ndarray, roughness: np.ndarray, fitted: np.ndarray, visibility: np.ndarray,
                     min_visibility: float, neighbours: int, albedo: np.ndarray | None = None,
                     albedo_guide_m: float = 0.0, albedo_neighbours: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The published roughness: each texel's median over its ``neighbours`` nearest *voters*, the fitted
    texels (``fitted`` (N,) bool) whose ``visibility`` (N,) reaches ``min_visibility`` (every fitted texel
    when none does); nearest on the surface and, with ``albedo`` (N, 3) and ``albedo_guide_m`` > 0, in albedo
    (:func:`albedo_guide` over ``albedo_neighbours``, a unit of it counting ``albedo_guide_m`` metres). points
    (N, 3), roughness (N,). Returns the (N,) float32 median and the (N,) bool voters."""
    voters = np.asarray(fitted, bool) & (np.asarray(visibility) >= min_visibility)
    if not voters.any():
        voters = np.asarray(fitted, bool)
    # the guide's k-d tree over every texel is wasted where the median returns the values as they are
    guided = albedo is not None and albedo_guide_m > 0 and not _median_is_identity(neighbours, voters)
    guide = albedo_guide(albedo, points, albedo_neighbours) if guided else None
    return surface_median(points, roughness, voters, neighbours, guide, albedo_guide_m), voters


ALBEDO_GUIDE_FLOOR = 0.02
"""Albedo below which :func:`albedo_guide` no longer tells values apart (its log is taken of the albedo clipped
here): a texel's noise and dark creases there are not another material."""


def albedo_guide(albedo: np.ndarray, points: np.ndarray | None = None, neighbours: int = 1) -> np.ndarray:
    """The features (N, 3) float64 the roughness median compares albedos by: the natural log of each channel,
    clipped below at :data:`ALBEDO_GUIDE_FLOOR` (a ratio between two albedos, not their difference, tells
    materials apart: a dark belt against dark cloth as a pale shirt against pale skin), averaged over each
    point's ``neighbours`` nearest ``points`` (N, 3) in 3D (itself included; 1: no average), so a pattern finer
    than that neighbourhood reads as one material. albedo (N, 3), a non-finite value taken as the floor."""
    albedo = np.nan_to_num(np.asarray(albedo, np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    guide = np.log(np.clip(albedo, ALBEDO_GUIDE_FLOOR, None))
    if int(neighbours) != neighbours or neighbours < 1:
        raise ValueError(f"neighbours must be a positive integer, got {neighbours}")
    if neighbours > 1 and len(guide) > 1:
        from scipy.spatial import cKDTree

        if points is None or np.shape(points) != (len(guide), 3):
            raise ValueError(f"points must be ({len(guide)}, 3) to average the guide over neighbours")
        _, nearest = cKDTree(np.asarray(points, np.float64)).query(points, k=int(min(neighbours, len(guide))))
        guide = guide[nearest].mean(axis=1)
    return guide


def mirror_cone_open(points, normals, view_dirs, valid, scene, cone_deg: float, rays: int = 8,
                     offset_m: float | None = None, threads: int | None = None) -> np.ndarray:
    """Whether the mesh leaves each view's mirror direction open at each point: the view direction reflected
    about the normal, and ``rays`` directions ``cone_deg`` degrees around it (evenly spaced), all meet nothing.

    Args:
        points, normals: (P, 3) surface points (metres) and their normals (normalised here; non-zero).
        view_dirs: (P, V, 3) unit directions from each point towards each view's camera.
        valid: (P, V) bool: only these are traced (the others come back False).
        scene: open3d ``RaycastingScene`` of the occluder (:func:`stages.numerics.raycast.mesh_scene`).
        cone_deg: the cone's half-angle, degrees, in [0, 90); 0 traces the mirror direction alone.
        rays: directions on the cone besides its axis (ignored when ``cone_deg`` is 0).
        offset_m: ray origins are ``point + offset_m * normal`` (default
            :data:`stages.numerics.shadowing.SHADOW_OFFSET_M`).
        threads: Embree threads (default :func:`stages.numerics.numeric_threads`).

    Returns:
        (P, V) bool. A cone direction below the point's horizon meets the surface itself: such a view is not
        open.
    """
    from stages.numerics import numeric_threads
    from stages.numerics.shadowing import (SHADOW_OFFSET_M, _check_offset, _check_points_normals, _check_scene,
                                           _occluded, _tangent_frames, _unit_rows)

    offset_m = SHADOW_OFFSET_M if offset_m is None else offset_m
    p, n = _check_points_normals(points, normals)
    _check_scene(scene)
    v = np.asarray(view_dirs, dtype=np.float64)
    ok = np.asarray(valid, bool)
    if v.ndim != 3 or v.shape[0] != len(p) or v.shape[2] != 3 or ok.shape != v.shape[:2]:
        raise ValueError(f"view_dirs must be (P, V, 3) and valid (P, V) with P = {len(p)}, got {v.shape} and "
                         f"{ok.shape}")
    if not (0.0 <= float(cone_deg) < 90.0) or int(rays) < 0:
        raise ValueError(f"cone_deg must be in [0, 90) and rays >= 0, got {cone_deg!r} and {rays!r}")
    offset = _check_offset(offset_m)
    threads = numeric_threads() if threads is None else int(threads)
    pi, vi = np.nonzero(ok)
    open_ = np.zeros(ok.shape, bool)
    if len(pi) == 0:
        return open_
    nn = n[pi]
    vv = _unit_rows(np.nan_to_num(v[pi, vi]))
    axis = _unit_rows(2.0 * np.einsum("ij,ij->i", vv, nn)[:, None] * nn - vv)
    t1, t2 = _tangent_frames(axis)
    angle = np.radians(float(cone_deg))
    count = int(rays) if cone_deg > 0 else 0
    directions = [axis] + [np.cos(angle) * axis + np.sin(angle) * (np.cos(phi) * t1 + np.sin(phi) * t2)
                           for phi in 2.0 * np.pi * np.arange(count) / max(count, 1)]
    origins = p[pi] + offset * nn
    seen = np.ones(len(pi), bool)
    for d in directions:
        seen &= ~_occluded(scene, np.concatenate([origins, d], axis=1), threads)
    open_[pi, vi] = seen
    return open_


def texel_samples(vertices: np.ndarray, faces: np.ndarray, atlas: Any, albedo_texture: np.ndarray,
                  views: list[Any], cfg: MaterialTexturesConfig) -> dict[str, Any]:
    """Step 1 of the roughness: the texels of a ``cfg.texture_size`` atlas and their observations.

    vertices (V, 3), faces (F, 3) and atlas: :func:`artifacts.facade.load_atlas_mesh`; albedo_texture (T', T', 3):
    the baked white-light albedo; views: :class:`stages.numerics.bake.BakeView` with ``images["obs"]`` (H, W, 9) =
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
                        cfg: MaterialTexturesConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2: the per-texel fit with the config's model, F0, bounds and albedo solve (arrays as
    :func:`stages.numerics.materials.fit_roughness`, whose ``(roughness, rms, diffuse albedo)`` it returns;
    texels without views have rms ``NO_VIEWS_RESIDUAL``)."""
    from stages.numerics.materials import fit_roughness

    return fit_roughness(observed, view_dirs, valid, normals, albedo, white_scale=white_scale,
                         r_min=cfg.roughness_min, r_max=cfg.roughness_max, f0=cfg.f0,
                         specular_model=cfg.specular_model, fit_albedo=cfg.fit_albedo, return_albedo=True)


def fit_texel_materials(observed: np.ndarray, view_dirs: np.ndarray, valid: np.ndarray, usable: np.ndarray,
                        normals: np.ndarray, albedo: np.ndarray, white_scale: np.ndarray,
                        cfg: MaterialTexturesConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 2 with its albedo: :func:`fit_texel_roughness` on the ``usable`` (P, V) observations (valid, mirror
    cone open), and the diffuse ratio (:func:`diffuse_ratio_of`) of the albedo fitted with it or, with
    ``cfg.albedo_max_views`` and ``cfg.fit_albedo``, of a second joint fit on the ``valid`` (P, V) observations
    of the first ``cfg.albedo_max_views`` views. observed (P, V, 3, 3), view_dirs (P, V, 3), normals and albedo
    (P, 3), white_scale (P, V, 3) as :func:`stages.numerics.materials.fit_roughness`. Returns the roughness (P,),
    its fit's rms (P,; ``NO_VIEWS_RESIDUAL`` where no view was usable), the diffuse ratio (P, 3) float32 and
    whether the albedo was solved (P,) bool."""
    from stages.numerics.materials import NO_VIEWS_RESIDUAL

    roughness, fit_rms, diffuse_albedo = fit_texel_roughness(observed, view_dirs, usable, normals, albedo,
                                                             white_scale, cfg)
    albedo_rms = fit_rms
    if cfg.albedo_max_views > 0 and cfg.fit_albedo:
        k = min(int(cfg.albedo_max_views), observed.shape[1])
        _, albedo_rms, diffuse_albedo = fit_texel_roughness(observed[:, :k], view_dirs[:, :k], valid[:, :k],
                                                            normals, albedo, white_scale[:, :k], cfg)
    solved = albedo_rms != NO_VIEWS_RESIDUAL
    return roughness, fit_rms, diffuse_ratio_of(diffuse_albedo, albedo, solved), solved


def published_roughness(points: np.ndarray, roughness: np.ndarray, fitted: np.ndarray, visibility: np.ndarray,
                        cfg: MaterialTexturesConfig,
                        albedo: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Step 3: :func:`roughness_median` with the config's voters, neighbours and albedo guide (``albedo`` (N, 3):
    the texels' white-light albedo; None: nearest on the surface alone), within the config's bounds (0.5 where no
    texel voted). Returns the (N,) float32 roughness and the (N,) bool voters."""
    smooth, voters = roughness_median(points, roughness, fitted, visibility, cfg.median_min_visibility,
                                      cfg.median_neighbours, albedo, cfg.median_albedo_m,
                                      cfg.median_albedo_neighbours)
    return np.clip(np.nan_to_num(smooth, nan=0.5), cfg.roughness_min, cfg.roughness_max), voters


def diffuse_ratio_of(diffuse_albedo: np.ndarray, albedo: np.ndarray, solved: np.ndarray) -> np.ndarray:
    """The share (N, 3) float32 of the white-light albedo (N, 3) that a fit explains as diffuse (the rest is
    specular light): ``diffuse_albedo / albedo`` where ``solved`` (N,) and the albedo exceeds 0.02, else 1, in
    [0.5, 1.5]."""
    ratio = np.where(solved[:, None] & (albedo > 0.02), diffuse_albedo / np.maximum(albedo, 1e-3), 1.0)
    return np.clip(np.nan_to_num(ratio, nan=1.0), 0.5, 1.5).astype(np.float32)


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


@dataclass(frozen=True)
class MaterialTextures:
    """The materials stage's textures (float32) and the statistics of their fit."""

    roughness: np.ndarray
    """(T, T) perceptual roughness, the surface median of the per-texel fits."""
    roughness_fit_rms: np.ndarray
    """(T, T) residual of each texel's fit (0 where no view saw it)."""
    occlusion: np.ndarray
    """(T_occ, T_occ) cosine-weighted visible fraction of the LED sphere on the mesh."""
    albedo_deoccluded: np.ndarray
    """(T', T', 3) the baked albedo divided by the occlusion."""
    diffuse_ratio: np.ndarray
    """(T, T, 3) the fitted diffuse albedo over the white-light one."""
    albedo_intrinsic: np.ndarray
    """(T', T', 3) the baked albedo times the diffuse ratio, divided by the occlusion."""
    stats: dict[str, Any]
    """Texel counts, roughness percentiles, fit residual, occlusion and diffuse-ratio summaries, step times."""


def material_textures(vertices: np.ndarray, faces: np.ndarray, atlas: Any, albedo_texture: np.ndarray,
                      views: list[Any], white_per_view: np.ndarray, cfg: MaterialTexturesConfig,
                      progress: Callable[[int, int, str], None] | None = None) -> MaterialTextures:
    """Roughness by inverse rendering under full_on / pos / neg, ambient occlusion and the albedos without it.

    vertices (V, 3), faces (F, 3), atlas: the welded textured mesh (:func:`artifacts.facade.load_atlas_mesh`);
    albedo_texture (T', T', 3): the baked white-light albedo; views: :class:`stages.numerics.bake.BakeView` with
    ``images["obs"]`` (H, W, 9) = full_on | pos | neg; white_per_view (C, 3): each view's white reference.
    ``progress(step, steps, message)`` is told after the observations and after the fit."""
    from stages.numerics.bake import rasterize_atlas
    from stages.numerics.materials import NO_VIEWS_RESIDUAL
    from stages.numerics.raycast import mesh_scene
    from stages.numerics.shadowing import ambient_occlusion

    timings: dict[str, float] = {}
    # Roughness: observations per texel, a per-texel fit, then a median over surface neighbours.
    t0 = time.perf_counter()
    size = int(cfg.texture_size)
    texels = texel_samples(vertices, faces, atlas, albedo_texture, views, cfg)
    covered, points, normals, albedo, obs = (texels[k] for k in ("covered", "points", "normals", "albedo", "obs"))
    if progress is not None:
        progress(1, 3, f"{len(points)} texels, {obs['valid'].sum(axis=1).mean():.1f} views each")
    timings["observations_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    white_per_obs = np.asarray(white_per_view)[np.maximum(obs["view_index"], 0)]
    observed = obs["values"]["obs"].reshape(len(points), -1, 3, 3)
    mesh = mesh_scene(vertices, faces)
    usable = obs["valid"]
    if cfg.specular_cone_deg > 0:
        usable = usable & mirror_cone_open(points, normals, obs["view_dirs"], usable, mesh, cfg.specular_cone_deg)
    roughness, fit_rms, diffuse_ratio, albedo_solved = fit_texel_materials(
        observed, obs["view_dirs"], obs["valid"], usable, normals, albedo, white_per_obs, cfg)
    fitted = fit_rms != NO_VIEWS_RESIDUAL
    # texels the body shadows from part of the stage fit too rough: they take their unshadowed neighbours'
    texel_visibility = ambient_occlusion(points, normals, mesh, rays=cfg.occlusion_rays)
    smooth, voters = published_roughness(points, roughness, fitted, texel_visibility, cfg, albedo)
    timings["fit_s"] = time.perf_counter() - t0
    if progress is not None:
        progress(2, 3, f"roughness fitted in {timings['fit_s']:.1f} s")

    roughness_tex = texel_texture(smooth, covered)
    rms_tex = np.zeros((size, size), np.float32)
    rms_tex[covered] = np.where(fitted, fit_rms, 0.0)
    ratio_tex = texel_texture(diffuse_ratio, covered, fill=1.0)

    # Ambient occlusion on the mesh, divided out of the baked albedo.
    t0 = time.perf_counter()
    occ_raster = rasterize_atlas(vertices, faces, atlas, int(cfg.occlusion_size))
    occ_covered = occ_raster["covered"]
    visible = ambient_occlusion(occ_raster["position"][occ_covered].astype(np.float64),
                                occ_raster["normal"][occ_covered].astype(np.float64),
                                mesh, rays=cfg.occlusion_rays)
    occlusion_tex = texel_texture(visible, occ_covered, fill=1.0)
    deoccluded = albedo_without_occlusion(albedo_texture, occlusion_tex, cfg.min_occlusion)
    intrinsic = albedo_without_occlusion(albedo_texture, occlusion_tex, cfg.min_occlusion, ratio_tex)
    timings["occlusion_s"] = time.perf_counter() - t0

    used = smooth[fitted] if fitted.any() else smooth
    stats = {"texels": int(len(points)), "texels_fitted": int(fitted.sum()), "cameras": len(views),
             "mean_views": float(obs["valid"].sum(axis=1).mean()) if len(points) else 0.0,
             "mean_views_mirror_open": float(usable.sum(axis=1).mean()) if len(points) else 0.0,
             "roughness_mean": float(used.mean()) if len(used) else 0.0,
             "roughness_p10": float(np.percentile(used, 10)) if len(used) else 0.0,
             "roughness_p90": float(np.percentile(used, 90)) if len(used) else 0.0,
             "fit_rms_median": float(np.median(fit_rms[fitted])) if fitted.any() else 0.0,
             "median_voters_fraction": float(voters.sum() / max(int(fitted.sum()), 1)),
             "occlusion_mean": float(visible.mean()) if len(visible) else 1.0,
             "diffuse_ratio_median": float(np.median(diffuse_ratio[albedo_solved])) if albedo_solved.any() else 1.0,
             "specular_model": cfg.specular_model, **timings}
    return MaterialTextures(roughness=roughness_tex, roughness_fit_rms=rms_tex, occlusion=occlusion_tex,
                            albedo_deoccluded=deoccluded.astype(np.float32), diffuse_ratio=ratio_tex,
                            albedo_intrinsic=intrinsic.astype(np.float32), stats=stats)
