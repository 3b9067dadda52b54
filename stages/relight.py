"""Action stage ``relight``: novel views of the asset under HDR environments.

For each novel camera (placed between neighbouring captured cameras, :func:`novel_camera_pairs`):

1. depth from the action's mesh (Embree), the G-buffer (normal, albedo) reprojected from the ``sources``
   nearest captured views with depth tests (:func:`stages.numerics.gbuffer.reproject_gbuffer`, the paper's
   depth-guided reprojection; ``learned_blend`` optionally blends with weights learned leave one out on
   the captured views, :mod:`stages.numerics.learned_blend`), roughness and occlusion looked up in the
   materials textures through the textured mesh's UVs (pixels the mesh covers but no source sees take the
   baked textures and the mesh's smooth normals; ``normals: mesh`` uses those everywhere). The shading
   normals are by default ``fused``: the reprojected normals' detail on the mesh normals' low frequencies
   (:func:`stages.numerics.gbuffer.fuse_normals`, split at ``normal_fusion_m`` on the surface);
2. each environment (equirectangular HDR/EXR, or a built-in procedural one) fitted with ``sg_lobes``
   spherical Gaussians (:func:`stages.numerics.sg.fit_sg_environment`);
3. shading: Lambertian diffuse + GGX specular under the lobes (F0 0.02), with the mesh's self-occlusion
   (:func:`stages.numerics.shadowing.shade_sg_visible`) when ``shadows``. The sources' albedo is
   ``albedo_diffuse`` (the white-light albedo less the specular light fitted per view; with
   ``diffuse_albedo`` off or without those maps, the white-light albedo times the materials stage's diffuse
   ratio); it still holds the stage's ambient occlusion, so with shadows it is divided by the occlusion
   (else occlusion would count twice).
4. edges: a camera pixel integrates the light over its square, so at a silhouette it is part subject, part
   background. ``coverage_samples`` rays per pixel side measure the share the mesh covers
   (:func:`stages.numerics.raycast.pixel_coverage`); it is the relit images' alpha and their radiance is
   premultiplied by it. Covered pixels whose centre misses the mesh take the mean of their shaded neighbours
   (:func:`grow_edges`). The masks are alpha >= 0.5.

Outputs per action (release ``renders/``): ``cameras.json`` (the novel cameras, OpenCV, and the captured
pair each lies between), ``<view>/normal.exr``, ``albedo.exr``, ``roughness.exr``, ``mask.png`` and
``<view>/<environment>.exr`` (RGBA: linear radiance in the environment's units premultiplied by alpha, the
share of the pixel the subject covers; the G-buffer maps and ``mask.png`` cover alpha >= 0.5),
``environments.json`` (names, source files and the SG fit errors) and a preview sheet.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.exr import read_exr, write_exr
from pipeline.codecs.image import label_picture, preview_linear, preview_normals, write_png
from pipeline.config import Documented
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from stages.geometry import camera_maps, mapped_cameras
from stages.numerics import numeric_threads
from stages.numerics.learned_blend import LearnedBlendConfig

PROCEDURAL_PREFIX = "procedural:"
#: What an environment found nowhere is replaced by (a capture without ../shared still gets renders).
FALLBACK_ENVIRONMENT = "procedural:sky"
#: Where environment names are looked up, after $ULTRASTAGE_HDRI (os.pathsep-separated folders).
DEFAULT_HDRI_DIRS = (Path(__file__).resolve().parents[1].parent / "shared" / "data" / "hdri",)
_HDR_SUFFIXES = (".hdr", ".exr")
_HALF_MAX = 60000.0
TURNTABLE_FRAMES = 12
"""Views of ``previews/turntable.png`` (30 degrees apart about +y)."""
TURNTABLE_SIZE = (240, 160)
"""(height, width) in pixels of each turntable view."""


@dataclass(frozen=True)
class RelightConfig(Documented):
    environments: tuple[str, ...] = ("studio_small_03_1k", "kiara_1_dawn_1k", "forest_slope_1k")
    """Environment maps: a file path, a file name (stem) looked up in $ULTRASTAGE_HDRI, the capture's
    ``environments/`` folder and ../shared/data/hdri, or ``procedural:sky`` / ``procedural:studio``. A name
    found nowhere is replaced by the procedural sky (named and labelled so), with a warning in the log and
    its request in environments.json."""
    novel_views: int = 3
    """Novel cameras per action, each halfway between two neighbouring captured cameras."""
    sources: int = 6
    """Nearest captured views the G-buffer is reprojected from (the paper's 6)."""
    sg_lobes: int = 32
    """Spherical Gaussians per environment (bench_sg: 0.9% median irradiance error at 32)."""
    fit_height: int = 64
    """Rows of the downsampled map the SG fit works on."""
    normals: str = "fused"
    """Shading normals (also released as ``renders/<view>/normal.exr``): "fused" (the reprojected normals'
    detail on the mesh normals' low frequencies, :func:`stages.numerics.gbuffer.fuse_normals`), "reprojected"
    (the G-buffer's, blended from the photometric maps, as the paper) or "mesh" (the mesh's smooth normals).
    On the default capture's novel views (bench/bench_relight.py, both actions, 3 views, 3 environments) the
    photometric normals carry smooth biases the mesh's do not (eq. 1's lean, specular residue) and the mesh
    lacks their detail: against the simulator's normals reprojected 6.28 deg, mesh 5.58, fused 5.53 (8 mm:
    5.45, 30 mm: 5.67); relit 23.37 dB reprojected, 23.24 mesh, 23.47 fused (8 mm: 23.43, 30 mm: 23.48). The
    mesh's normals alone relight worse than they measure: the reprojected albedo's errors partly cancel the
    reprojected normals' at the scale of the detail, which the fusion keeps."""
    normal_fusion_m: float = 0.015
    """Frequency split of the "fused" normals: the Gaussian's sigma on the surface, metres (turned into pixels
    at each novel view's median depth; 3 px on the default capture)."""
    diffuse_normals: bool = True
    """Reproject the normal maps with the specular reflection fitted out (``normal_diffuse`` of the
    diffuse_normals stage, when there are any) rather than eq. 1's (relit 22.48 vs 22.24 dB, bench_relight)."""
    diffuse_albedo: bool = True
    """Reproject the sources' ``albedo_diffuse`` (the white-light albedo less the specular light fitted per view,
    when the diffuse_normals stage wrote it) and shade it as is, rather than the white-light albedo times the
    materials' diffuse ratio (one share per texel for every view). On the default capture the relit novel
    views came 23.12 -> 23.30 dB closer to the simulator's renders (A0000 and A0001, `make dataset`)."""
    shadows: bool = True
    """Occlude the environment by the mesh itself (else every direction above the horizon is lit)."""
    visibility_directions: int = 256
    """Directions per pixel for the self-occlusion (Fibonacci sphere)."""
    f0: float = 0.02
    """Fresnel reflectance at normal incidence."""
    depth_tolerance_m: float = 0.01
    """A source pixel is visible when its mesh depth agrees with the point's within this."""
    coverage_samples: int = 4
    """Rays per pixel side that measure how much of each pixel the mesh covers (alpha of the relit images,
    whose radiance is premultiplied by it; the masks are alpha >= 0.5, as the simulator's). The G-buffer is
    still sampled at pixel centres; a covered pixel whose centre misses the mesh takes the mean of its shaded
    neighbours'. 1 = hard edges (alpha = the centres' mask). On the default capture relit novel views 24.13 ->
    24.80 dB against the simulator (2 rays per side: 24.83; the simulator's camera averages 2 x 2). The grid is
    cast only at the silhouette (:func:`stages.numerics.raycast.pixel_coverage`, ``edges_only``): 0.1-0.7 s
    per 320 x 480 view instead of 0.9-2.0 s for every pixel's, 0-3 pixels' coverage different, the same masks."""
    min_alpha: float = 0.5
    """Source map pixels with a lower photometric validity alpha are not reprojected."""
    previews: bool = True
    """Write a preview sheet (views x environments, tone-mapped)."""
    learned_blend: LearnedBlendConfig = field(default_factory=LearnedBlendConfig)
    """With ``enabled: true``, blend the sources with weights learned leave one out on the action's captured
    views (the paper's blending network, :mod:`stages.numerics.learned_blend`) instead of the heuristic
    weights. Off by default: relit novel views 23.12 -> 23.04 dB against the simulator (default capture)."""

    def __post_init__(self) -> None:
        if not self.environments:
            raise ValueError("relight.environments must name at least one environment")
        if self.normals not in ("mesh", "reprojected", "fused"):
            raise ValueError(f"relight.normals must be 'fused', 'reprojected' or 'mesh', got {self.normals!r}")
        if not (np.isfinite(self.normal_fusion_m) and self.normal_fusion_m > 0):
            raise ValueError(f"relight.normal_fusion_m must be positive, got {self.normal_fusion_m!r}")
        for name in ("novel_views", "sources", "sg_lobes", "fit_height", "visibility_directions", "coverage_samples"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"relight.{name} must be >= 1")


def environment_label(name: str) -> str:
    """File-name-safe label of an environment entry (``procedural:sky`` -> ``procedural_sky``)."""
    stem = name[len(PROCEDURAL_PREFIX):] if name.startswith(PROCEDURAL_PREFIX) else Path(name).stem
    label = ("procedural_" if name.startswith(PROCEDURAL_PREFIX) else "") + stem
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in label)


def find_environment(name: str, capture_root: Path | None = None) -> Path | None:
    """The file an environment entry names, or None (procedural, or found nowhere)."""
    if name.startswith(PROCEDURAL_PREFIX):
        return None
    path = Path(name).expanduser()
    if path.suffix.lower() in _HDR_SUFFIXES and path.is_file():
        return path
    dirs = [Path(d) for d in os.environ.get("ULTRASTAGE_HDRI", "").split(os.pathsep) if d]
    if capture_root is not None:
        dirs.append(Path(capture_root) / "environments")
    dirs += list(DEFAULT_HDRI_DIRS)
    for folder in dirs:
        for suffix in ("",) + _HDR_SUFFIXES:
            candidate = folder / f"{name}{suffix}"
            if candidate.is_file() and candidate.suffix.lower() in _HDR_SUFFIXES:
                return candidate
    return None


def raw_environment_inputs(names: tuple[str, ...], capture_root: Path | None) -> dict[str, Path]:
    """The environment files a config names, as raw inputs (``environment/<label>`` -> path): their digests
    enter the stage's key, so replacing a map reruns the stage. Procedural and missing names have none."""
    found = {}
    for name in names:
        path = find_environment(name, capture_root)
        if path is not None:
            found[f"environment/{environment_label(name)}"] = path
    return found


def load_environment(name: str, path: Path | None, height: int = 256) -> tuple[np.ndarray, str]:
    """(environment (H, 2H, 3) float32, how it was obtained) for a config entry and its resolved file."""
    from pipeline.codecs.hdr import read_environment
    from stages.numerics.sg import PROCEDURAL_ENVIRONMENTS, procedural_environment

    if path is not None:
        env = read_environment(path)
        if not np.all(np.isfinite(env)) or env.ndim != 3 or env.shape[1] != 2 * env.shape[0]:
            raise InputError(path, f"not a finite equirectangular (H, 2H, 3) map: shape {env.shape}")
        return np.maximum(env, 0.0).astype(np.float32), f"file {path.name}"
    kind = name[len(PROCEDURAL_PREFIX):] if name.startswith(PROCEDURAL_PREFIX) else None
    if kind is not None:
        if kind not in PROCEDURAL_ENVIRONMENTS:
            raise ValueError(f"relight.environments: unknown {name!r}; built in: "
                             f"{[PROCEDURAL_PREFIX + k for k in PROCEDURAL_ENVIRONMENTS]}")
        return procedural_environment(kind, height), "procedural"
    return procedural_environment("sky", height), f"FALLBACK: {name!r} not found, {FALLBACK_ENVIRONMENT} used"


def novel_cameras(cameras: dict[str, dict[str, Any]], count: int) -> list[dict[str, Any]]:
    """Novel camera records halfway between ``count`` pairs of neighbouring captured cameras."""
    from stages.numerics.gbuffer import interpolate_camera, novel_camera_pairs

    ids = sorted(cameras)
    poses = [np.asarray(cameras[c]["cam_from_world"], np.float64) for c in ids]
    out = []
    for i, (a, b) in enumerate(novel_camera_pairs(poses, count)):
        ca, cb = cameras[ids[a]], cameras[ids[b]]
        K, pose = interpolate_camera(ca["K"], poses[a], cb["K"], poses[b], 0.5)
        out.append({"camera_id": f"N{i:03d}", "between": [ids[a], ids[b]], "K": K.tolist(),
                    "cam_from_world": pose.tolist(), "width": int(ca["width"]), "height": int(ca["height"])})
    return out


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


def novel_view_gbuffer(asset: ActionAsset, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int,
                       sources: int = 6, depth_tolerance_m: float = 0.01, blend: Any = None,
                       normal_fusion_m: float = 0.015) -> dict[str, np.ndarray]:
    """The G-buffer of one novel camera (step 1 of the module docstring); ``blend`` a trained
    :class:`stages.numerics.learned_blend.LearnedBlend` or None (the heuristic weights); ``normal_fusion_m``
    the frequency split of ``normal_fused`` on the surface (metres; the Gaussian's sigma, turned into pixels
    at the mask's median depth).

    Returns (H, W[, C]) maps ``mask`` (the mesh's silhouette where a source or the atlas gives an albedo),
    ``hit`` (the pixel-centre rays that meet the mesh),
    ``depth_m``, ``normal_reprojected`` (the mesh's smooth normal where no source sees the pixel),
    ``normal_mesh``, ``normal_fused`` (:func:`stages.numerics.gbuffer.fuse_normals`: the reprojected normals'
    detail on the mesh normals' low frequencies), ``albedo`` (the sources', reprojected, the baked white-light
    texture where no source sees the pixel), ``roughness``, ``occlusion``, ``diffuse_ratio`` (1 where the
    sources' albedo is already ``albedo_diffuse``); per mask pixel ``pix`` (flat indices), ``points`` (P, 3)
    and ``view_dirs`` (P, 3, towards the camera); 0 outside the mask. Also the floats ``coverage`` (share
    of the mesh's silhouette in the mask) and ``normal_fusion_px`` (the split in pixels).
    """
    from stages.numerics.bake import sample_texture
    from stages.numerics.gbuffer import fuse_normals, reproject_gbuffer
    from stages.numerics.raycast import render_attributes, render_mesh, render_uvs

    K, pose = np.asarray(K, np.float64), np.asarray(cam_from_world, np.float64)
    h, w = int(height), int(width)
    seen = render_mesh(None, None, K, pose, h, w, scene=asset.scene)
    depth = np.where(seen["hit"], seen["depth_m"], 0.0).astype(np.float32)
    gbuffer = reproject_gbuffer(depth, K, pose, asset.sources, k=sources, depth_tolerance_m=depth_tolerance_m,
                                blend=blend)
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
    centre = -pose[:, :3].T @ pose[:, 3]
    points = _pixel_points(K, pose, depth).reshape(-1, 3)[pix]
    view_dirs = centre[None] - points
    view_dirs /= np.maximum(np.linalg.norm(view_dirs, axis=1, keepdims=True), 1e-12)
    normal_reprojected = np.where(reprojected[..., None], gbuffer["normal"], mesh_normals).astype(np.float32)
    fusion_px = float(normal_fusion_m * K[0, 0] / np.median(depth[mask])) if mask.any() else 1.0
    return {"mask": mask, "hit": seen["hit"], "depth_m": depth, "pix": pix, "points": points, "view_dirs": view_dirs,
            "normal_reprojected": normal_reprojected, "normal_mesh": mesh_normals.astype(np.float32),
            "normal_fused": fuse_normals(normal_reprojected, mesh_normals, mask, max(fusion_px, 1e-3)),
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


class RelightStage(Stage):
    """Relit novel views: reprojected G-buffers shaded under SG-fitted environments."""

    name = "relight"
    # 8: edge pixels take the mean of their shaded neighbours (bake.dilate_texture), not the nearest one's;
    # 7: the coverage grid cast at the silhouette only; 6: antialiased silhouettes (alpha = pixel coverage);
    # 5: fused shading normals (normal_fusion_m); 4: G-buffers read the sources with cubic convolution
    # 9: the relit sheet's tiles are labelled (view, environment); previews/turntable.png, the textured mesh
    # from TURNTABLE_FRAMES azimuths side by side
    version = "9"
    scope = "action"
    requires = ("geometry", "textures", "materials", "decode", "photometric", "diffuse_normals")
    outputs = ("renders", "previews")

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        return raw_environment_inputs(self.config.environments, getattr(capture, "root", None))

    def run(self, ctx: StageContext) -> dict[str, Any]:
        import torch

        from pipeline.codecs.mesh import read_ply
        from stages.materials import load_atlas_mesh
        from stages.numerics.gbuffer import SourceView
        from stages.numerics.mesh import vertex_normals
        from stages.numerics.raycast import mesh_scene, pixel_coverage, render_mesh
        from stages.numerics.sg import fibonacci_sphere, fit_sg_environment, sg_fit_errors, shade_sg
        from stages.numerics.shadowing import direction_visibility, shade_sg_visible

        torch.set_num_threads(numeric_threads())
        cfg: RelightConfig = self.config
        started = time.perf_counter()
        out = ctx.out_dir
        renders = out / "renders"
        renders.mkdir(parents=True, exist_ok=True)

        # Environments -> SG lobes (once per action; cheap next to the shading).
        environments = []
        for requested in cfg.environments:
            name, label = requested, environment_label(requested)
            env, how = load_environment(name, ctx.raw_inputs.get(f"environment/{label}"))
            if how.startswith("FALLBACK"):
                # Named and labelled as what it is; several missing maps give one procedural sky.
                ctx.log.warning("relight: %s", how)
                name, label = FALLBACK_ENVIRONMENT, environment_label(FALLBACK_ENVIRONMENT)
                if any(e["label"] == label for e in environments):
                    continue
            elif any(e["label"] == label for e in environments):
                raise ValueError(f"relight.environments {cfg.environments} give the label {label!r} twice")
            t0 = time.perf_counter()
            lobes = fit_sg_environment(env, cfg.sg_lobes, fit_height=cfg.fit_height)
            errors = sg_fit_errors(env, lobes)
            environments.append({"name": name, "requested": requested, "label": label, "source": how, "lobes": lobes,
                                 "fit_seconds": time.perf_counter() - t0,
                                 "fit_errors": {k: float(v) for k, v in errors.items()
                                                if isinstance(v, (int, float, np.floating))}})

        # Captured views as reprojection sources (mesh depth rendered per source).
        vertices, faces = read_ply(ctx.upstream["geometry"] / "mesh" / "mesh.ply")
        scene = mesh_scene(vertices, faces)
        sources, cameras = [], {}
        diffuse_dir = ctx.upstream["diffuse_normals"]
        # every source's albedo_diffuse or none: the shading treats the reprojected albedo as one kind
        mapped = mapped_cameras(ctx.upstream["decode"], ctx.upstream["photometric"])
        use_diffuse_albedo = cfg.diffuse_albedo and bool(mapped) and all(
            (diffuse_dir / "albedo_diffuse" / f"{cam_id}.exr").exists() for cam_id in mapped)
        for cam_id, cam, normal_alpha, _, valid in camera_maps(ctx.upstream["decode"], ctx.upstream["photometric"],
                                                               cfg.min_alpha):
            h, w = valid.shape
            depth = render_mesh(None, None, cam["K"], cam["cam_from_world"], h, w, scene=scene)["depth_m"]
            albedo = read_exr((diffuse_dir / "albedo_diffuse" if use_diffuse_albedo else
                               ctx.upstream["photometric"] / "albedo") / f"{cam_id}.exr")[..., :3]
            normals = normal_alpha[..., :3]
            diffuse_path = diffuse_dir / "normal_diffuse" / f"{cam_id}.exr"
            if cfg.diffuse_normals and diffuse_path.exists():
                normals = read_exr(diffuse_path)[..., :3]
            sources.append(SourceView(normal=np.ascontiguousarray(normals), albedo=albedo, valid=valid,
                                      K=np.asarray(cam["K"], np.float64),
                                      cam_from_world=np.asarray(cam["cam_from_world"], np.float64), depth_m=depth))
            cameras[cam_id] = {**cam, "width": w, "height": h}
        if len(sources) < 2:
            raise InputError(ctx.upstream["photometric"] / "normal_alpha",
                             f"{len(sources)} camera(s) have maps; novel views need at least 2")

        # Materials through the textured mesh's UVs.
        materials = ctx.upstream["materials"] / "textures"
        atlas_vertices, atlas_faces, atlas = load_atlas_mesh(ctx.upstream["textures"] / "mesh" / "textured.obj")
        asset = ActionAsset(scene=scene, faces=faces, smooth_normals=vertex_normals(vertices, faces), sources=sources,
                            atlas_scene=mesh_scene(atlas_vertices, atlas_faces), atlas=atlas,
                            albedo_tex=read_exr(ctx.upstream["textures"] / "textures" / "albedo.exr")[..., :3],
                            roughness_tex=_single_channel(read_exr(materials / "roughness.exr")),
                            occlusion_tex=_single_channel(read_exr(materials / "occlusion.exr")),
                            diffuse_ratio_tex=read_exr(materials / "diffuse_ratio.exr")[..., :3],
                            sources_diffuse_albedo=use_diffuse_albedo)
        directions = fibonacci_sphere(cfg.visibility_directions) if cfg.shadows else None
        views = novel_cameras(cameras, cfg.novel_views)
        blend = None
        if cfg.learned_blend.enabled and len(sources) >= 3:
            from stages.numerics.learned_blend import fit_learned_blend

            blend = fit_learned_blend(sources, cfg.learned_blend, k=cfg.sources, depth_tolerance_m=cfg.depth_tolerance_m)
            ctx.log.info("relight: learned blend on %d views, %d pixels: loss %.4f vs heuristic %.4f (%.0f s)",
                         blend.record["views"], blend.record["pixels"], blend.record["learned_loss"],
                         blend.record["heuristic_loss"], blend.record["gather_s"] + blend.record["train_s"])

        records, sheet_rows = [], []
        for index, view in enumerate(views):
            t0 = time.perf_counter()
            h, w = view["height"], view["width"]
            gb = novel_view_gbuffer(asset, view["K"], view["cam_from_world"], h, w, sources=cfg.sources,
                                    depth_tolerance_m=cfg.depth_tolerance_m, blend=blend,
                                    normal_fusion_m=cfg.normal_fusion_m)
            mask, pix = gb["mask"], gb["pix"]
            shading_normals = gb[f"normal_{cfg.normals}"]
            normals = shading_normals.reshape(-1, 3)[pix]
            rough = np.clip(gb["roughness"].reshape(-1)[pix], 0.05, 1.0)
            visibility = None
            if cfg.shadows and len(pix):
                visibility = direction_visibility(gb["points"], normals, scene, directions)
            albedo = shading_albedo(gb["albedo"].reshape(-1, 3)[pix], gb["diffuse_ratio"].reshape(-1, 3)[pix],
                                    gb["occlusion"].reshape(-1)[pix] if visibility is not None else None)
            view_dirs = gb["view_dirs"]
            alpha, out_mask = mask.astype(np.float32), mask
            if cfg.coverage_samples > 1:
                alpha, out_mask = silhouette_alpha(mask, pixel_coverage(
                    view["K"], view["cam_from_world"], h, w, cfg.coverage_samples, scene, centre_hit=gb["hit"]))
            # the G-buffer maps on the output mask: edge pixels whose centre misses the mesh borrow their neighbours'
            maps = grow_edges({"normal": shading_normals, "albedo": _image(pix, albedo, h, w),
                               "roughness": gb["roughness"]}, mask)
            length = np.linalg.norm(maps["normal"], axis=-1, keepdims=True)
            maps["normal"] = np.divide(maps["normal"], length, out=np.zeros_like(maps["normal"]), where=length > 1e-6)
            maps = {k: np.where(out_mask.reshape(out_mask.shape + (1,) * (v.ndim - 2)), v, 0.0).astype(np.float32)
                    for k, v in maps.items()}
            folder = renders / view["camera_id"]
            for name, image in maps.items():
                write_exr(folder / f"{name}.exr", image)
            write_png(folder / "mask.png", (out_mask * 255).astype(np.uint8))
            row = [label_picture(preview_normals(maps["normal"], out_mask.astype(np.float32)),
                                 f"{view['camera_id']} normal")]
            for env in environments:
                if visibility is not None:
                    shaded = shade_sg_visible(normals, view_dirs, albedo, rough, env["lobes"], visibility,
                                              directions, f0=cfg.f0)
                else:
                    shaded = shade_sg(normals, view_dirs, albedo, rough, env["lobes"], f0=cfg.f0)
                rgb = np.clip(np.nan_to_num(shaded["rgb"], nan=0.0, posinf=0.0, neginf=0.0), 0.0, _HALF_MAX)
                # premultiplied by the pixel's coverage, as a camera integrates a silhouette pixel
                image = premultiply_edges(_image(pix, rgb, h, w), mask, alpha)
                write_exr(folder / f"{env['label']}.exr", np.concatenate([image, alpha[..., None]], axis=2))
                row.append(label_picture(preview_linear(image, exposure=_auto_exposure(image, out_mask)),
                                         f"{view['camera_id']} {env['label']}"))
            sheet_rows.append(np.concatenate(row, axis=1))
            records.append({**view, "pixels": int(len(pix)), "mask_pixels": int(out_mask.sum()),
                            "coverage": gb["coverage"], "normal_fusion_px": gb["normal_fusion_px"],
                            "seconds": time.perf_counter() - t0})
            ctx.progress(index + 1, len(views), f"view {view['camera_id']} relit under {len(environments)} "
                                                f"environment(s)")
        (renders / "cameras.json").write_text(json.dumps({"camera_convention": "opencv", "units": "metres",
                                                          "cameras": records}, indent=1))
        (renders / "environments.json").write_text(json.dumps(
            {"environments": [{k: v for k, v in e.items() if k != "lobes"} | {"lobes": e["lobes"].numpy().to_dict()}
                              for e in environments],
             "shading": {"sg_lobes": cfg.sg_lobes, "shadows": cfg.shadows, "f0": cfg.f0, "normals": cfg.normals,
                         "radiance_units": "the environment map's",
                         "alpha": (f"pixel coverage of {cfg.coverage_samples} x {cfg.coverage_samples} rays, radiance "
                                   "premultiplied" if cfg.coverage_samples > 1 else "mask (pixel centres)")},
             "blend": blend.record if blend is not None else "heuristic"}, indent=1, default=float))
        if cfg.previews and sheet_rows:
            write_png(out / "previews" / "relit.png", np.concatenate(sheet_rows, axis=0))
        if cfg.previews:
            from stages.numerics.turntable import turntable_cameras, turntable_strip

            cams = turntable_cameras(atlas_vertices, TURNTABLE_FRAMES, *TURNTABLE_SIZE)
            strip = turntable_strip(asset.atlas_scene, atlas.faces, atlas.uvs, asset.albedo_tex, cams, *TURNTABLE_SIZE)
            write_png(out / "previews" / "turntable.png", preview_linear(strip, exposure=1.0))
        return {"novel_views": len(views), "environments": [e["label"] for e in environments],
                "source_albedo": "albedo_diffuse" if use_diffuse_albedo else "albedo x diffuse_ratio",
                "fallbacks": [e["name"] for e in environments if e["source"].startswith("FALLBACK")],
                "sg_fit_seconds": float(sum(e["fit_seconds"] for e in environments)),
                "blend_seconds": float(blend.record["gather_s"] + blend.record["train_s"]) if blend is not None else 0.0,
                "seconds": time.perf_counter() - started}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        files = []
        renders = artifact / "renders"
        for p in sorted(renders.rglob("*")):
            if not p.is_file():
                continue
            rel = p.relative_to(renders).as_posix()
            if p.parent == renders or p.stem in ("normal", "albedo", "roughness", "mask"):
                kind = f"render_{p.stem}"
            else:
                kind = f"relit_{p.stem}"
            camera = p.parent.name if p.parent != renders else None
            files.append((p, f"renders/{rel}", kind, camera))
        for name in ("relit", "turntable"):
            if (artifact / "previews" / f"{name}.png").exists():
                files.append((artifact / "previews" / f"{name}.png", f"previews/{name}.png", f"preview_{name}", None))
        return files


def _image(pixels: np.ndarray, values: np.ndarray, h: int, w: int) -> np.ndarray:
    out = np.zeros((h * w, values.shape[1]), np.float32)
    out[pixels] = values
    return out.reshape(h, w, values.shape[1])


def _pixel_points(K: np.ndarray, cam_from_world: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) of a depth map (camera z)."""
    h, w = depth_m.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x_cam = np.stack([(u - K[0, 2]) / K[0, 0] * depth_m, (v - K[1, 2]) / K[1, 1] * depth_m, depth_m], axis=-1)
    R, t = cam_from_world[:, :3], cam_from_world[:, 3]
    return (x_cam - t) @ R


def _single_channel(texture: np.ndarray) -> np.ndarray:
    return texture[..., 0] if texture.ndim == 3 else texture


def _auto_exposure(image: np.ndarray, mask: np.ndarray) -> float:
    values = image[mask].mean(axis=1) if mask.any() else np.zeros(1)
    peak = float(np.percentile(values, 99)) if len(values) else 0.0
    return 0.8 / peak if peak > 0 else 1.0
