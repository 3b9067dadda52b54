"""A novel view of an action's relightable asset: its G-buffer reprojected from the captured views, and the
view shaded under spherical-Gaussian environments (the math of the ``relight`` and ``relightset`` stages;
nothing here reads or writes files).

- :class:`ActionAsset`: the mesh, the captured views as reprojection sources, the atlas and its textures.
- :func:`novel_view_gbuffer`: depth from the mesh, normal and albedo reprojected from the nearest sources
  (the paper's depth-guided reprojection), materials through the atlas.
- :class:`ViewShading` and :func:`relight_view`: one view's released maps (normal, albedo, roughness on the
  antialiased mask) and its images under any number of SG environments, premultiplied by the pixel coverage;
  :func:`shade_gbuffer` is its second half (the shading of a G-buffer, whose visibility, albedo and F0 a caller
  may replace: bench/bench_relit_budget.py swaps them for the simulator's truth).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from pipeline.config import Documented, checked
from artifacts.camera import Camera
from stages.numerics.gbuffer import SOURCE_EDGE_JUMP_M, SOURCE_EDGE_PX

HALF_MAX = 60000.0
"""Radiance is clipped here before it is written as half float (max 65504)."""


@dataclass(eq=False)
class ActionAsset:
    """What a novel view of an action is made from: the mesh (ray-casting scene, faces, smooth vertex
    normals), the captured views as reprojection sources, and the atlas (scene of the textured mesh, its UVs)
    with the white-light albedo, roughness, occlusion and diffuse-ratio textures."""

    scene: Any
    faces: np.ndarray
    smooth_normals: np.ndarray
    sources: list[Any]
    atlas_scene: Any
    atlas: Any
    albedo_tex: np.ndarray
    roughness_tex: np.ndarray
    occlusion_tex: np.ndarray
    diffuse_ratio_tex: np.ndarray
    sources_diffuse_albedo: bool = False
    """The sources' albedo is ``albedo_diffuse`` (specular light already out): no diffuse ratio where they
    give the albedo."""
    vertices: np.ndarray | None = None
    """The mesh's vertices (V, 3), world frame, metres (None when the caller did not keep them)."""


def novel_view_gbuffer(asset: ActionAsset, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int,
                       sources: int = 6, depth_tolerance_m: float = 0.01, blend: Any = None,
                       normal_fusion_m: float = 0.015, rim_normal_px: float = 4.0,
                       mesh_normal_weight: float = 0.5, source_edge_px: int = SOURCE_EDGE_PX,
                       source_edge_jump_m: float = SOURCE_EDGE_JUMP_M) -> dict[str, np.ndarray]:
    """The G-buffer of one novel camera (step 1 of the module docstring); ``blend`` a trained
    :class:`stages.numerics.learned_blend.LearnedBlend` or None (the heuristic weights); ``normal_fusion_m``
    the frequency split of ``normal_fused`` on the surface (metres; the Gaussian's sigma, turned into pixels
    at the mask's median depth); ``rim_normal_px`` the rim inside the silhouette over which ``normal_fused``
    fades to the mesh's normals (pixels, :func:`stages.numerics.gbuffer.fade_rim_normals`; 0: no fade);
    ``mesh_normal_weight`` the mesh normals' share in ``normal_fused`` inside that rim; ``source_edge_px`` and
    ``source_edge_jump_m`` the sources' occlusion edges that count little (:func:`stages.numerics.gbuffer.
    reproject_gbuffer`).

    Returns (H, W[, C]) maps ``mask`` (the mesh's silhouette where a source or the atlas gives an albedo),
    ``hit`` (the pixel-centre rays that meet the mesh),
    ``depth_m``, ``normal_reprojected`` (the mesh's smooth normal where no source sees the pixel),
    ``normal_mesh``, ``normal_fused`` (:func:`stages.numerics.gbuffer.shading_normals`: the reprojected normals'
    detail on the mesh normals' low frequencies, faded to the mesh's normals on the silhouette's rim), ``albedo`` (the sources', reprojected, the baked white-light
    texture where no source sees the pixel), ``roughness``, ``occlusion``, ``diffuse_ratio`` (1 where the
    sources' albedo is already ``albedo_diffuse``); per mask pixel ``pix`` (flat indices), ``points`` (P, 3)
    and ``view_dirs`` (P, 3, towards the camera); 0 outside the mask. Also the floats ``coverage`` (share
    of the mesh's silhouette in the mask) and ``normal_fusion_px`` (the split in pixels).
    """
    from stages.numerics.bake import sample_texture
    from stages.numerics.gbuffer import reproject_gbuffer, shading_normals
    from stages.numerics.raycast import render_attributes, render_mesh, render_uvs

    K, pose = np.asarray(K, np.float64), np.asarray(cam_from_world, np.float64)
    h, w = int(height), int(width)
    seen = render_mesh(None, None, K, pose, h, w, scene=asset.scene)
    depth = np.where(seen["hit"], seen["depth_m"], 0.0).astype(np.float32)
    gbuffer = reproject_gbuffer(depth, K, pose, asset.sources, k=sources, depth_tolerance_m=depth_tolerance_m,
                                blend=blend, source_edge_px=source_edge_px, source_edge_jump_m=source_edge_jump_m)
    reprojected = gbuffer["valid"]
    # Pixels the mesh covers but no source sees (about 1%) take the baked albedo and the mesh's normal.
    uv, on_atlas = render_uvs(asset.atlas_scene, asset.atlas.faces, asset.atlas.uvs, K, pose, h, w)
    mask = seen["hit"] & (reprojected | on_atlas)
    uv = uv.reshape(-1, 2)

    def texture(tex: np.ndarray, fill: float) -> np.ndarray:
        values = sample_texture(tex, uv).reshape((h, w) + tex.shape[2:])
        return np.where(mask.reshape((h, w) + (1,) * (tex.ndim - 2)), values, fill).astype(np.float32)

    mesh_normals, _ = render_attributes(asset.scene, asset.faces, asset.smooth_normals, K, pose, h, w)
    norm = np.linalg.norm(mesh_normals, axis=2, keepdims=True)
    mesh_normals = np.where(mask[..., None] & (norm > 1e-8), mesh_normals / np.maximum(norm, 1e-8), 0.0)
    albedo = np.where(reprojected[..., None], gbuffer["albedo"], texture(asset.albedo_tex, 0.0))
    pix = np.flatnonzero(mask.reshape(-1))
    camera = Camera(K, pose, w, h)
    centre = camera.centre
    points = camera.lift_depth_map(depth).reshape(-1, 3)[pix]
    view_dirs = centre[None] - points
    view_dirs /= np.maximum(np.linalg.norm(view_dirs, axis=1, keepdims=True), 1e-12)
    normal_reprojected = np.where(reprojected[..., None], gbuffer["normal"], mesh_normals).astype(np.float32)
    fusion_px = float(normal_fusion_m * K[0, 0] / np.median(depth[mask])) if mask.any() else 1.0
    return {"mask": mask, "hit": seen["hit"], "depth_m": depth, "pix": pix, "points": points, "view_dirs": view_dirs,
            "normal_reprojected": normal_reprojected, "normal_mesh": mesh_normals.astype(np.float32),
            "normal_fused": shading_normals(normal_reprojected, mesh_normals, mask, max(fusion_px, 1e-3),
                                            rim_normal_px, mesh_normal_weight),
            "normal_fusion_px": fusion_px,
            "albedo": np.where(mask[..., None], albedo, 0.0).astype(np.float32),
            "roughness": texture(asset.roughness_tex, 0.0), "occlusion": texture(asset.occlusion_tex, 1.0),
            "diffuse_ratio": np.where((reprojected & asset.sources_diffuse_albedo)[..., None], 1.0,
                                      texture(asset.diffuse_ratio_tex, 1.0)).astype(np.float32),
            "coverage": float(mask.sum() / max(seen["hit"].sum(), 1))}


def silhouette_alpha(shaded: np.ndarray, coverage: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Alpha of a relit view and its mask: the pixels' coverage (H, W) in [0, 1] on the ``shaded`` pixels
    (H, W) bool (whose centre sees the subject) and on their 8-neighbours (which :func:`grow_edges` fills),
    0 elsewhere; the mask is alpha >= 0.5 (as the simulator's: at least half of a pixel's rays hit)."""
    from scipy.ndimage import binary_dilation

    coverage = np.clip(np.nan_to_num(np.asarray(coverage, np.float32)), 0.0, 1.0)
    reached = binary_dilation(np.asarray(shaded, bool), np.ones((3, 3), bool))
    alpha = np.where(reached, coverage, 0.0).astype(np.float32)
    return alpha, alpha >= 0.5


def grow_edges(maps: dict[str, np.ndarray], shaded: np.ndarray) -> dict[str, np.ndarray]:
    """Maps (H, W[, C]) sampled on the ``shaded`` pixels (H, W) bool, grown by one ring of pixels: the
    silhouette pixels whose centre misses the mesh take the mean of their shaded 8-neighbours
    (:func:`stages.numerics.bake.dilate_texture`, one pass); 0 farther out."""
    from stages.numerics.bake import dilate_texture

    grown, _ = dilate_texture(maps, shaded, 1)
    return grown


def premultiply_edges(image: np.ndarray, shaded: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """A relit image (H, W, 3) shaded on ``shaded`` (H, W) bool, grown to its silhouette pixels
    (:func:`grow_edges`) and premultiplied by ``alpha`` (H, W) (:func:`silhouette_alpha`)."""
    return (grow_edges({"rgb": image}, shaded)["rgb"] * alpha[..., None]).astype(np.float32)


def shading_albedo(white_light_albedo: np.ndarray, diffuse_ratio: np.ndarray, occlusion: np.ndarray | None,
                   min_occlusion: float = 0.2) -> np.ndarray:
    """The albedo to shade with, (N, 3) in [0, 1]: the white-light albedo holds specular light (the shading
    adds it back) and, when the shading occludes, the stage's ambient occlusion (else it would count twice).

    white_light_albedo, diffuse_ratio: (N, 3); occlusion: (N,) visible fraction, or None without shadows."""
    albedo = white_light_albedo * diffuse_ratio
    if occlusion is not None:
        albedo = albedo / np.maximum(occlusion, min_occlusion)[:, None]
    return np.clip(np.nan_to_num(albedo, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)


def scatter_pixels(pixels: np.ndarray, values: np.ndarray, h: int, w: int) -> np.ndarray:
    """An (H, W, C) float32 image, 0 except at the flat pixel indices ``pixels`` (P,), which get ``values`` (P, C)."""
    out = np.zeros((h * w, values.shape[1]), np.float32)
    out[pixels] = values
    return out.reshape(h, w, values.shape[1])


def auto_exposure(image: np.ndarray, mask: np.ndarray, level: float = 0.8) -> float:
    """The factor that maps the 99th percentile of an image's (H, W, 3) mean radiance on ``mask`` (H, W) to
    ``level`` (1 for an empty or black image)."""
    values = image[mask].mean(axis=1) if mask.any() else np.zeros(1)
    peak = float(np.percentile(values, 99)) if len(values) else 0.0
    return level / peak if peak > 0 else 1.0


@dataclass(frozen=True)
class ViewShading(Documented):
    """How a novel view is reprojected and shaded: ``relight.shading`` and ``relightset.shading``."""

    sources: int = checked(6, ge=1)
    """Nearest captured views the G-buffer is reprojected from (the paper's 6)."""
    depth_tolerance_m: float = checked(0.01, gt=0.0)
    """A source pixel is visible when its mesh depth agrees with the point's within this, metres."""
    source_edge_px: int = checked(SOURCE_EDGE_PX, ge=0)
    """A captured view's pixels within this of its own occlusion edges (a depth jump over ``source_edge_jump_m``
    in its mesh depth, :func:`stages.numerics.gbuffer.depth_edges`) count 1% of a pixel off them in that view's
    blend weight: a pixel there mixes the occluder and the surface behind it. 0: every pixel counts alike."""
    source_edge_jump_m: float = checked(SOURCE_EDGE_JUMP_M, gt=0.0)
    """The depth jump, metres, of a captured view's occlusion edge for ``source_edge_px``."""
    normal_fusion_m: float = checked(0.015, gt=0.0)
    """Frequency split of the "fused" normals: the Gaussian's sigma on the surface, metres (turned into pixels
    at each novel view's median depth; 3 px on the default capture)."""
    rim_normal_px: float = checked(4.0, ge=0.0)
    """Width in pixels of the rim inside each novel view's silhouette over which the "fused" normals fade to the
    mesh's (:func:`stages.numerics.gbuffer.fade_rim_normals`: the mesh's on the outer ring, the fused ones from
    ``rim_normal_px + 1`` pixels in; 0: no fade). The captured views see that rim at grazing angles, where their
    photometric normals are worst. Default capture, all 3 views of both actions x 3 environments: relit
    25.48 dB at 0, 25.55 at 2, 25.56 at 3, 25.57 at 4 and 6; normals on the outer ring 9.4 -> 7.8 deg off
    the truth's, 1.5-2.5 px in 5.8 -> 5.2 deg. Fading by the mesh normal's cosine to the view instead (weight 1
    at 0.3-0.4, 0 at 0.7-0.8) gave 25.53-25.55 dB. It pays where the mesh's normals beat the photometric ones at
    the rim: on the accuracy gate's coarse mesh (procedural subject, 128 x 192 px, ``gate`` preset) relit 17.73 dB
    at 0, 17.67 at 2, 17.65 at 4."""
    mesh_normal_weight: float = checked(0.5, ge=0.0, le=1.0)
    """Share of the mesh's smooth normals in the "fused" normals inside the rim (``unit((1 - w) fused + w mesh)``,
    :func:`stages.numerics.gbuffer.fade_rim_normals`'s ``interior_weight``). The photometric detail the fusion
    keeps is partly noise and the two estimates' errors are partly independent: on the default capture's novel
    views (both actions, 3 views) the mesh's normals are 4.01 deg off the truth's, the fused ones 4.06, their
    even blend 3.85 (6 px and more inside the silhouette: mesh 3.37, fused 3.53, blend 3.22). Relit
    (bench_relit_budget's stage row, 3 environments) 25.76 dB at 0, 25.80 at 0.3, 25.81 at 0.5, 25.80 at 0.7; the
    relighting set's normals 4.07 -> 3.93 deg at 0.5. Like the rim fade it pays where the mesh is good: on the
    accuracy gate's coarse mesh relit 19.51 dB at 0, 19.48 at 0.5, and its normals 11.25 -> 11.69 deg."""
    normals: str = checked("fused", one_of=("fused", "reprojected", "mesh"))
    """Shading normals (:func:`novel_view_gbuffer`'s ``normal_<kind>``; the relight stage releases them as
    ``renders/<view>/normal.exr``): "fused" (the reprojected normals' detail on the mesh normals' low
    frequencies, :func:`stages.numerics.gbuffer.fuse_normals`, blended with the mesh's by ``mesh_normal_weight``
    and faded to them on the rim), "reprojected" (the G-buffer's, blended from the
    photometric maps, as the paper) or "mesh" (the mesh's smooth normals). On the default capture's novel views
    (bench/bench_relight.py, both actions, 3 views, 3 environments) the photometric normals carry smooth biases
    the mesh's do not (eq. 1's lean, specular residue) and the mesh lacks their detail: against the simulator's
    normals reprojected 6.28 deg, mesh 5.58, fused 5.53 (8 mm: 5.45, 30 mm: 5.67); relit 23.37 dB reprojected,
    23.24 mesh, 23.47 fused (8 mm: 23.43, 30 mm: 23.48). The mesh's normals alone relight worse than they
    measure: the reprojected albedo's errors partly cancel the reprojected normals' at the scale of the detail,
    which the fusion keeps."""
    shadows: bool = True
    """Occlude the environment by the mesh itself (else every direction above the horizon is lit)."""
    visibility_directions: int = checked(256, ge=1)
    """Directions per pixel for the self-occlusion (Fibonacci sphere)."""
    f0: float = checked(0.028, ge=0.0, le=1.0)
    """Fresnel reflectance at normal incidence: skin's (refractive index 1.4; relit novel views 0.08 dB closer to
    the simulator's than at 0.02, bench/bench_relit_budget.py)."""
    coverage_samples: int = checked(4, ge=1)
    """Rays per pixel side that measure how much of each pixel the mesh covers (alpha of the relit images,
    whose radiance is premultiplied by it; the masks are alpha >= 0.5, as the simulator's). The G-buffer is
    still sampled at pixel centres; a covered pixel whose centre misses the mesh takes the mean of its shaded
    neighbours'. 1 = hard edges (alpha = the centres' mask; bench/bench_relight.py scores it beside the
    default: the simulator's camera averages 2 x 2 rays, and hard edges score lower). The grid is
    cast only at the silhouette (:func:`stages.numerics.raycast.pixel_coverage`, ``edges_only``): 0.1-0.7 s
    per 320 x 480 view instead of 0.9-2.0 s for every pixel's, 0-3 pixels' coverage different, the same masks."""
    supersample: int = checked(2, ge=1)
    """Shading samples per pixel side: above 1 the images are rendered on a grid this many times finer (G-buffer,
    visibility, shading and coverage, :func:`supersampled_intrinsics`) and each pixel is the mean of its samples'
    premultiplied radiance, as a camera integrates its pixel (the simulator's averages 2 x 2 rays); the maps, mask
    and alpha stay the pixel-centre G-buffer's. 1: one sample at each pixel's centre. Needs the heuristic blend
    (``learned_blend`` is fitted on per-pixel densities). Time against error on the default capture's N000 views
    (both actions x 3 environments, against the simulator's renders): 27.03 dB at 1, 27.20 at 2, 27.21 at 3 for
    2.8, 10.7 and 24.3 CPU s per view; of the squared error the 2 removes, 56% is inside the silhouette and 44% on
    its 2 px band. Sharing each pixel's traced visibility among its samples instead of tracing theirs gave
    27.08 dB. The whole default capture at 2: relit views 26.59 -> 26.77 dB, relighting set 26.98 -> 27.29 dB, the
    two stages' task seconds 33 -> 63."""
    shadowing: str = checked("smith", one_of=("physg", "smith"))
    """The GGX shadowing-masking term of the specular (:func:`stages.numerics.sg.ggx_sg_lobe`): "smith"
    (height-correlated Smith: the simulator's, and the one the materials stage fits the roughness under) or "physg"
    (separable Schlick-GGX). Summed over the directions (the default ``integration``, with the key lights and cell
    centroids) "smith" is the closer: the budget's stage row on the default capture (both actions x 3 views x
    studio / dawn / forest maps, one sample per pixel) 26.41 / 26.95 / 26.92 dB with "physg", 26.41 / 27.30 / 27.12
    with "smith" (worst image 24.68 / 24.74 dB); the whole default capture's release relit 26.95 / 27.20 dB, its
    relighting set 27.46 / 27.80 dB. Under the SG closed forms "smith" relit the default capture's A0000 N000 0.6 dB
    further from the simulator's (25.15 vs 25.76 dB, bench/bench_relit_budget.py --shading
    integration=closed_form,shadowing=smith): a ``closed_form`` config should set "physg"."""
    key_lights: int = checked(2, ge=0)
    """Lobes of each environment shaded as distant point lights at their own axes, each with its own visibility
    traced per pixel, instead of on the visibility directions' cells (:func:`stages.numerics.direction_lights.
    split_key_lights`: the brightest of those at least ``key_light_sharpness`` sharp; with the "directions" and
    "directions_diffuse" integrations). On a cell a key light lights and shadows from the cell's direction, up to
    about 7 degrees from its own at 256 directions: a studio map's key light (sharpness 1,279, 69% of its energy)
    casts its shadows' edges that far off. It costs one traced ray per pixel and key light. 0: none. The default
    capture's novel views (bench/bench_relit_budget.py's stage row, both actions x 3 views, one sample per pixel;
    studio / dawn / forest maps): 25.99 / 26.88 / 26.89 dB on the cells' own directions, 26.40 / 26.89 / 26.90 with
    2 key lights at sharpness 300 (at 100: 26.40 / 26.90 / 26.83, the forest's two lobes of sharpness 112 and 213
    lose as point lights), 26.41 / 26.95 / 26.92 with ``cell_centroids`` as well; exact integration of the map
    over 2,048 traced lights 26.65 / 27.47 / 27.27."""
    key_light_sharpness: float = checked(300.0, gt=0.0)
    """The least SG sharpness of a key light (a lobe of sharpness ``s`` spreads about ``1 / sqrt(s)`` radians: 3.3
    degrees at 300, well within a cell of the 256 visibility directions)."""
    cell_centroids: bool = True
    """With the "directions" integrations, each visibility direction's cell lights from the mean direction of the
    energy in it (:func:`stages.numerics.direction_lights.sg_cell_lights`) instead of from the cell's direction;
    its visibility stays the cell direction's. No extra ray. The stage row above: 26.59 dB without it or key
    lights, 26.66 with it alone (studio +0.14, dawn +0.07, forest +0.02 dB)."""
    integration: str = checked("directions", one_of=("closed_form", "directions", "directions_diffuse"))
    """How the environment is integrated: "directions" (the lobes' energy put on the ``visibility_directions`` and
    Lambertian + GGX summed over them, each direction occluded per pixel, :mod:`stages.numerics.direction_lights`;
    no extra ray), "closed_form" (each SG lobe's closed-form diffuse and specular, scaled by its visible fraction
    over the visibility directions, :func:`stages.numerics.shadowing.shade_sg_visible`) or "directions_diffuse"
    (the diffuse summed over the directions, the specular by the closed forms). The closed forms' specular (the
    GGX lobe warped into SGs) is about 23% off the GGX integral; the diffuse is within 1-2%. On the default
    capture's N000 views (both actions, 3 environments, bench/bench_relit_budget.py --views 1): the stage's render
    25.96 dB closed_form, 25.99 directions_diffuse, 26.19 directions (26.16 at 512 directions, 26.31 at 1024);
    with the true geometry, albedo, material and visibility 29.39, 29.47, 30.76 (31.15, 31.79; exact
    integration of the map over 2048 lights 32.18). Time: 0.9 s of CPU to shade A0000's N000 (17,756 pixels)
    under 3 environments against 1.2 s for the closed forms, beside 2.8 s of tracing 256 directions (6.5 s for
    512)."""

    def gbuffer_options(self) -> dict[str, Any]:
        """The keyword arguments of :func:`novel_view_gbuffer` these settings give (all but ``blend``)."""
        return {"sources": self.sources, "depth_tolerance_m": self.depth_tolerance_m,
                "normal_fusion_m": self.normal_fusion_m, "rim_normal_px": self.rim_normal_px,
                "mesh_normal_weight": self.mesh_normal_weight, "source_edge_px": self.source_edge_px,
                "source_edge_jump_m": self.source_edge_jump_m}


def relight_view(asset: ActionAsset, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int,
                 environments: Sequence[Any], shading: ViewShading = ViewShading(), blend: Any = None,
                 directions: np.ndarray | None = None, crop: bool = True) -> dict[str, Any]:
    """One novel view of ``asset`` shaded under each of ``environments`` (a sequence of
    :class:`stages.numerics.sg.SGLobes`, world frame).

    Args:
        K: (3, 3) OpenCV intrinsics; cam_from_world: (3, 4) [R | t]; height, width: image size.
        blend: a trained :class:`stages.numerics.learned_blend.LearnedBlend` or None (heuristic weights).
        directions: (D, 3) visibility directions (default: ``shading.visibility_directions`` on a Fibonacci
            sphere); pass them to share one set between views.
        crop: render only :func:`subject_window` (the pixels the mesh can cover, with a margin; the view's
            neighbourhood steps see only zeros beyond it, so the result is the whole frame's) and put it into the
            frame; False renders every pixel of the frame. Needs ``asset.vertices`` (else the whole frame).

    Returns:
        ``maps``: ``normal`` (H, W, 3) world-frame shading normals, unit on the mask, ``albedo`` (H, W, 3) the
        albedo the view is shaded with (ambient occlusion divided out when shadowed), ``roughness`` (H, W);
        all grown to the silhouette pixels and 0 off ``mask``. ``mask`` (H, W) bool (alpha >= 0.5), ``alpha``
        (H, W) float32 pixel coverage, ``images`` a list of (H, W, 3) float32 linear radiance premultiplied by
        alpha, one per environment, finite and below :data:`HALF_MAX` (with ``shading.supersample`` above 1 each
        pixel the mean of its samples' premultiplied radiance); ``pixels`` (shaded pixel count, at the pixel
        centres), ``coverage`` and ``normal_fusion_px`` (of the pixel-centre G-buffer).
    """
    h, w = int(height), int(width)
    if h < 1 or w < 1:
        raise ValueError(f"image size must be positive, got {height} x {width}")
    factor = int(shading.supersample)
    if factor > 1 and blend is not None:
        raise ValueError(f"shading.supersample = {factor} needs the heuristic blend: a learned blend weighs the "
                         "sources by their density per target pixel (set supersample: 1 with learned_blend)")
    window = (0, h, 0, w)
    if crop and asset.vertices is not None:
        window = subject_window(asset.vertices, K, cam_from_world, h, w)
    if window == (0, h, 0, w):
        return _relight_frame(asset, K, cam_from_world, h, w, environments, shading, blend, directions)
    row0, row1, col0, col1 = window
    part = _relight_frame(asset, crop_intrinsics(K, row0, col0), cam_from_world, row1 - row0, col1 - col0,
                          environments, shading, blend, directions)

    def framed(image: np.ndarray) -> np.ndarray:
        out = np.zeros((h, w) + image.shape[2:], image.dtype)
        out[row0:row1, col0:col1] = image
        return out

    return {**part, "maps": {k: framed(v) for k, v in part["maps"].items()}, "mask": framed(part["mask"]),
            "alpha": framed(part["alpha"]), "images": [framed(image) for image in part["images"]]}


def _relight_frame(asset: ActionAsset, K: np.ndarray, cam_from_world: np.ndarray, h: int, w: int,
                   environments: Sequence[Any], shading: ViewShading, blend: Any,
                   directions: np.ndarray | None) -> dict[str, Any]:
    """:func:`relight_view` on every pixel of an ``h x w`` frame."""
    factor = int(shading.supersample)
    gb = novel_view_gbuffer(asset, K, cam_from_world, h, w, blend=blend, **shading.gbuffer_options())
    view = shade_gbuffer(gb, asset.scene, K, cam_from_world, environments if factor == 1 else [], shading,
                         directions=directions)
    if factor > 1 and len(environments):
        fine_K = supersampled_intrinsics(K, factor)
        fine_shading = dataclasses.replace(shading, rim_normal_px=shading.rim_normal_px * factor,
                                           coverage_samples=-(-shading.coverage_samples // factor), supersample=1)
        fine_gb = novel_view_gbuffer(asset, fine_K, cam_from_world, h * factor, w * factor,
                                     **fine_shading.gbuffer_options())
        fine = shade_gbuffer(fine_gb, asset.scene, fine_K, cam_from_world, environments, fine_shading,
                             directions=directions)
        view["images"] = [box_mean(image, factor) for image in fine["images"]]
    return view


def subject_window(vertices: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int,
                   margin_px: int = 3) -> tuple[int, int, int, int]:
    """``(row0, row1, col0, col1)``: the rows and columns of a ``height x width`` view (K (3, 3), cam_from_world
    (3, 4); pixel centres at integer coordinates) that a mesh with ``vertices`` (V, 3) can cover: its projected
    vertices' bounding box (which holds the projection of every face), each pixel whose square meets it, and
    ``margin_px`` more on every side, clipped to the frame. The whole frame when a vertex lies at or behind the
    camera's plane (its faces' projections are unbounded) or the box misses the frame."""
    vertices = np.asarray(vertices, np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {vertices.shape}")
    if margin_px < 0:
        raise ValueError(f"margin_px must be >= 0, got {margin_px}")
    h, w = int(height), int(width)
    whole = (0, h, 0, w)
    if not len(vertices):
        return whole
    uv, depth = Camera(K, cam_from_world, w, h).project(vertices)
    if not np.all(depth > 1e-9) or not np.all(np.isfinite(uv)):
        return whole
    low, high = uv.min(axis=0), uv.max(axis=0)
    # pixel j's square is [j - 1/2, j + 1/2]: it meets the box when j >= low - 1/2 and j <= high + 1/2
    col0, row0 = (int(np.ceil(c - 0.5)) - margin_px for c in low)
    col1, row1 = (int(np.floor(c + 0.5)) + 1 + margin_px for c in high)
    row0, col0, row1, col1 = max(row0, 0), max(col0, 0), min(row1, h), min(col1, w)
    if row0 >= row1 or col0 >= col1:
        return whole
    return row0, row1, col0, col1


def crop_intrinsics(K: np.ndarray, row0: int, col0: int) -> np.ndarray:
    """The (3, 3) intrinsics of the image cut from ``K``'s at row ``row0`` and column ``col0`` (its pixel (0, 0) is
    ``K``'s pixel (row0, col0))."""
    cropped = np.array(K, np.float64)
    cropped[0, 2] -= col0
    cropped[1, 2] -= row0
    return cropped


def supersampled_intrinsics(K: np.ndarray, factor: int) -> np.ndarray:
    """The (3, 3) intrinsics of the grid ``factor`` times finer than ``K``'s over the same image: fine pixel ``j``
    has its centre at ``(j + 1/2) / factor - 1/2`` of ``K``'s pixels (pixel centres at integer coordinates), so
    each pixel's square holds ``factor x factor`` fine pixels."""
    fine = np.array(K, np.float64)
    fine[:2, :] *= factor
    fine[:2, 2] += (factor - 1) / 2.0
    return fine


def box_mean(image: np.ndarray, factor: int) -> np.ndarray:
    """The mean of each ``factor x factor`` block of ``image`` (H * factor, W * factor, C): (H, W, C) float32."""
    hf, wf = image.shape[:2]
    if hf % factor or wf % factor:
        raise ValueError(f"image {hf} x {wf} is not a whole number of {factor} x {factor} blocks")
    blocks = np.asarray(image, np.float32).reshape(hf // factor, factor, wf // factor, factor, *image.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


def shade_gbuffer(gb: dict[str, Any], scene: Any, K: np.ndarray, cam_from_world: np.ndarray,
                  environments: Sequence[Any], shading: ViewShading = ViewShading(),
                  directions: np.ndarray | None = None, visibility: np.ndarray | None = None,
                  albedo: np.ndarray | None = None, f0: float | np.ndarray | None = None,
                  shadowing: str | None = None, key_visibility: Any = None) -> dict[str, Any]:
    """Steps 2-4 of :func:`relight_view` on a G-buffer: the shading, the silhouette's alpha and the maps.

    Args:
        gb: a :func:`novel_view_gbuffer` of the view (``mask``, ``hit``, ``pix``, ``points``, ``view_dirs``,
            ``normal_<shading.normals>``, ``albedo``, ``diffuse_ratio``, ``occlusion``, ``roughness``).
        scene: the ray-casting scene the visibility and the pixel coverage are traced against.
        K, cam_from_world: the view's (3, 3) intrinsics and (3, 4) pose; the size is ``gb["mask"]``'s.
        environments, shading, directions: as in :func:`relight_view` (``shading.supersample`` is
            :func:`relight_view`'s; here one sample per pixel of ``gb``); with no environments only the maps, mask and
            alpha are made and no visibility is traced.
        visibility: (P, D) bool per mask pixel of ``directions`` (default: traced against ``scene`` at the
            G-buffer's points and shading normals, :func:`stages.numerics.shadowing.direction_visibility`).
        albedo: (P, 3) albedo to shade with (default: :func:`shading_albedo` of the G-buffer's).
        f0: Fresnel reflectance at normal incidence, scalar or (P,) (default ``shading.f0``).
        shadowing: the GGX shadowing term of the SG shading ("physg" or "smith", :func:`stages.numerics.sg.ggx_sg_lobe`;
            default ``shading.shadowing``).
        key_visibility: a function of the key lights' directions (M, 3) giving their (P, M) bool visibility per mask
            pixel (``shading.key_lights``; default: traced as ``visibility`` is).

    Returns:
        What :func:`relight_view` returns.
    """
    from stages.numerics.raycast import pixel_coverage
    from stages.numerics.sg import fibonacci_sphere, shade_sg
    from stages.numerics.shadowing import direction_visibility, shade_sg_visible

    mask, pix = gb["mask"], gb["pix"]
    h, w = mask.shape
    shading_normals = gb[f"normal_{shading.normals}"]
    normals = shading_normals.reshape(-1, 3)[pix]
    rough = np.clip(gb["roughness"].reshape(-1)[pix], 0.05, 1.0)
    f0 = shading.f0 if f0 is None else f0
    shadowing = shading.shadowing if shadowing is None else shadowing
    if not np.isscalar(f0) and np.shape(f0) != (len(pix),):
        raise ValueError(f"f0 must be a scalar or ({len(pix)},), got shape {np.shape(f0)}")
    def trace(dirs: np.ndarray) -> np.ndarray:
        """(P, len(dirs)) bool: which of the distant directions each mask pixel sees."""
        if not shading.shadows:  # every direction above the horizon is lit
            return normals @ np.asarray(dirs, np.float64).T > 0.0
        if not len(pix):
            return np.zeros((0, len(dirs)), bool)
        return direction_visibility(gb["points"], normals, scene, dirs)

    if (shading.shadows or shading.integration != "closed_form") and len(environments):
        directions = fibonacci_sphere(shading.visibility_directions) if directions is None else directions
        if not shading.shadows or visibility is None:
            visibility = trace(directions)
        elif visibility.shape != (len(pix), len(directions)):
            raise ValueError(f"visibility must be ({len(pix)}, {len(directions)}), got {visibility.shape}")
    else:
        visibility = None
    if albedo is None:
        albedo = shading_albedo(gb["albedo"].reshape(-1, 3)[pix], gb["diffuse_ratio"].reshape(-1, 3)[pix],
                                gb["occlusion"].reshape(-1)[pix] if shading.shadows else None)
    elif albedo.shape != (len(pix), 3):
        raise ValueError(f"albedo must be ({len(pix)}, 3), got {albedo.shape}")
    alpha, out_mask = mask.astype(np.float32), mask
    if shading.coverage_samples > 1:
        alpha, out_mask = silhouette_alpha(mask, pixel_coverage(
            K, cam_from_world, h, w, shading.coverage_samples, scene, centre_hit=gb["hit"]))
    # the G-buffer maps on the output mask: edge pixels whose centre misses the mesh borrow their neighbours'
    maps = grow_edges({"normal": shading_normals, "albedo": scatter_pixels(pix, albedo, h, w),
                       "roughness": gb["roughness"]}, mask)
    length = np.linalg.norm(maps["normal"], axis=-1, keepdims=True)
    maps["normal"] = np.divide(maps["normal"], length, out=np.zeros_like(maps["normal"]), where=length > 1e-6)
    maps = {k: np.where(out_mask.reshape(out_mask.shape + (1,) * (v.ndim - 2)), v, 0.0).astype(np.float32)
            for k, v in maps.items()}
    key_visibility = trace if key_visibility is None else key_visibility
    images = []
    for lobes in environments:
        if shading.integration != "closed_form":
            shaded = _shade_over_directions(normals, gb["view_dirs"], albedo, rough, lobes, visibility, directions,
                                            f0, shadowing, shading, key_visibility)
        elif visibility is not None:
            shaded = shade_sg_visible(normals, gb["view_dirs"], albedo, rough, lobes, visibility, directions,
                                      f0=f0, shadowing=shadowing)
        else:
            shaded = shade_sg(normals, gb["view_dirs"], albedo, rough, lobes, f0=f0, shadowing=shadowing)
        rgb = np.clip(np.nan_to_num(shaded["rgb"], nan=0.0, posinf=0.0, neginf=0.0), 0.0, HALF_MAX)
        # premultiplied by the pixel's coverage, as a camera integrates a silhouette pixel
        images.append(premultiply_edges(scatter_pixels(pix, rgb, h, w), mask, alpha))
    return {"maps": maps, "mask": out_mask, "alpha": alpha, "images": images, "pixels": int(len(pix)),
            "coverage": gb.get("coverage", 1.0), "normal_fusion_px": gb.get("normal_fusion_px", 0.0)}


def _shade_over_directions(normals: np.ndarray, view_dirs: np.ndarray, albedo: np.ndarray, rough: np.ndarray,
                           lobes: Any, visibility: np.ndarray, directions: np.ndarray, f0: Any, shadowing: str,
                           shading: ViewShading, key_visibility: Any) -> dict[str, np.ndarray]:
    """:func:`stages.numerics.direction_lights.shade_directions` of the lobes' energy on ``directions`` and of up to
    ``shading.key_lights`` key lights at their own directions (:func:`~stages.numerics.direction_lights.
    split_key_lights`, their visibility from ``key_visibility(directions (M, 3)) -> (P, M) bool``); with
    ``shading.integration`` "directions_diffuse" only its diffuse, the specular from every lobe's closed forms
    (:func:`stages.numerics.shadowing.shade_sg_visible`). ``shading.cell_centroids``: each cell lights from its
    energy's mean direction (:func:`~stages.numerics.direction_lights.sg_cell_lights`)."""
    from stages.numerics.direction_lights import sg_cell_lights, shade_directions, split_key_lights
    from stages.numerics.shadowing import shade_sg_visible

    cells, key_dirs, key_irradiance = lobes, np.zeros((0, 3)), np.zeros((0, 3))
    if shading.key_lights > 0:
        cells, key_dirs, key_irradiance = split_key_lights(lobes, shading.key_lights, shading.key_light_sharpness)
    irradiance, cell_directions = sg_cell_lights(cells, directions)
    all_directions = cell_directions if shading.cell_centroids else np.asarray(directions, np.float64)
    all_visibility = visibility
    if len(key_dirs):
        irradiance = np.concatenate([irradiance, key_irradiance])
        all_directions = np.concatenate([all_directions, key_dirs])
        all_visibility = np.concatenate([visibility, np.asarray(key_visibility(key_dirs), bool)], axis=1)
    if shading.integration == "directions":
        return shade_directions(normals, view_dirs, albedo, rough, irradiance, all_visibility, all_directions, f0=f0,
                                shadowing=shadowing)
    diffuse = shade_directions(normals, view_dirs, albedo, rough, irradiance, all_visibility, all_directions, f0=f0,
                               specular=False)["diffuse"]
    spec = shade_sg_visible(normals, view_dirs, albedo, rough, lobes, visibility, directions, f0=f0,
                            shadowing=shadowing)["specular"]
    return {"diffuse": diffuse, "specular": spec, "rgb": diffuse + spec}


def fit_blend(asset: ActionAsset, config: Any, k: int, depth_tolerance_m: float) -> Any:
    """The learned source blend of :mod:`stages.numerics.learned_blend` fitted leave one out on the asset's
    captured views when ``config.enabled`` (a :class:`LearnedBlendConfig`) and there are at least 3 of them;
    None otherwise (the heuristic weights)."""
    if not config.enabled or len(asset.sources) < 3:
        return None
    from stages.numerics.learned_blend import fit_learned_blend

    return fit_learned_blend(asset.sources, config, k=k, depth_tolerance_m=depth_tolerance_m)
