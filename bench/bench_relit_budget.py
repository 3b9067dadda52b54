"""Relit novel views: an error budget by oracle swaps (what each component of the relight stage costs in dB).

For each action of a release (default: every action with renders), each novel camera of its ``renders/cameras.json``
and each environment of its ``renders/environments.json`` (the stage's own SG lobes), the relight stage's view is
rendered again with the stage's own functions (:func:`stages.relightable.load_relightable_asset`,
:func:`stages.numerics.novel_view.novel_view_gbuffer` and :func:`stages.numerics.novel_view.shade_gbuffer`, the two
halves of ``relight_view``) and scored like ``ultrastage evaluate`` (``evaluation.release._relit_overall``:
:func:`stages.numerics.metrics.relit_psnr` against :class:`synthetic.relight.TruthRelighter`'s render of the true
subject, with the evaluation's light count); then again with one component at a time replaced by the simulator's
truth (read from the capture's ``ground_truth/`` folder, as evaluation/release.py reads it), and cumulatively in the
order of :data:`COMPONENTS`:

* ``geometry``: the true mesh (``ground_truth/<action>/mesh.ply``) for the novel view's depth, silhouette, smooth
  normals and coverage, and the captured views' true depth and normal maps (``ground_truth/<action>/depth``,
  ``normal``) as the reprojection's sources;
* ``albedo``: the captured views' true albedo maps as the sources' albedo (shaded as is: no ambient occlusion to
  divide out, no diffuse ratio);
* ``material``: the true roughness (the truth render's map), the simulator's F0 per material (skin 0.028, else 0.04,
  told apart by their roughness, :func:`simulator_f0`) and its specular shadowing term (height-correlated Smith, ``shadowing="smith"``);
* ``visibility``: the self-occlusion traced against the true mesh instead of ours (from the same surface points,
  each moved to the nearest point of the mesh traced against);
* ``lighting``: the SG lobes and the stage's shading of them (ViewShading.integration: the sum over the visibility
  directions, or the closed forms) replaced by exact integration of the environment map:
  the truth's own distant lights (:func:`synthetic.relight.environment_lights`, its light count), each occluded per
  pixel (traced against the mesh of the visibility row), with the simulator's GGX (:func:`synthetic.shading.ggx_weights`);
  an extra row integrates the SG lobes' own map exactly (the fit's share apart from the closed forms');
* ``reprojection``: the true G-buffer in the novel view itself (the truth render's normals, albedo and depth) instead
  of the true sources reprojected;
* ``tone``: a per-channel gain (exposure and white balance) fitted by least squares to the truth.

Each row: PSNR (dB) and SSIM (the images at the PSNR's common exposure, clipped to [0, 1], on the union of the
masks), and the dB it recovers over the stage's render (one at a time) or over the row before (cumulative); means
over actions, views and environments. The ``released`` row scores the release's own images (equal to ``stage``
when the release was made with the defaults this bench uses).

A second table splits the stage's render at the silhouette (:func:`silhouette_split`): the squared error's shares in
the interior, in a band of :data:`SILHOUETTE_BAND_PX` pixels of either outline and in one mask only, and the PSNR with
that band's alpha swapped for the true mesh's coverage (``outline``), its colour for the truth's (``colour``), both,
and both on the truth camera's own ray grid (``both_camera_grid``: the simulator's ``supersample`` x ``supersample``
rays per pixel instead of the stage's ``coverage_samples`` grid); beside it our mesh's outline against the true
mesh's (:func:`outline_offset_px`: mean offset outwards and RMS coverage difference at 8 x 8 rays per pixel).

A third table is the metric's own ceiling: the truth is rendered as the capture's camera renders (the simulator's
``supersample`` x ``supersample`` rays per pixel, 2 x 2 on the default capture), a coarse estimate of each pixel's
area integral wherever the image changes within a pixel (on the default capture 1% of the pixels hold 65-89% of its
error, about two thirds of them within 2 px of the silhouette). The same truth at ``--ceiling-supersample`` rays per side
(default 8) stands for the exact integral: the capture-grid truth's PSNR against it is the most any render can be
sure to score (mean and worst image), beside the stage's render and the all-truth row (``+ reprojection``: every
input true) scored against both.

``python bench/bench_relit_budget.py --out DIR [--release DIR --capture DIR --actions A0000,A0001 --threads 2]``
writes DIR/bench_relit_budget.json, .md (the table) and .png (a bar plot of the dB recovered). ``--shading
field=value,...`` renders every row with a variant of the stage's ViewShading (e.g. ``integration=closed_form``: the SG
lobes' closed forms instead of the sum over the visibility directions; ``visibility_directions=512``), ``--rows`` and
``--views`` measure a subset, ``--tag`` names the files. Defaults
runs/default/release and runs/default/capture; without them or the ground truth it prints why and exits 0.
``--quick`` (the tests' mode): the tiny run of ``bench/_quick.py``, its first view and first environment; the
numbers are not measurements.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stages.numerics.novel_view import HALF_MAX  # noqa: E402
from stages.numerics.sg import ROUGHNESS_MAX, ROUGHNESS_MIN  # noqa: E402

COMPONENTS = ("geometry", "albedo", "material", "visibility", "lighting", "reprojection", "tone")
"""The components swapped for the simulator's truth, in the order of the cumulative rows."""
EXTRA_ROWS = {"lighting: SG lobes integrated exactly": frozenset({"lighting_sg"}),
              "geometry: shading normals only": frozenset({"normals"})}
"""Rows beyond one component at a time: label -> swaps (``lighting_sg``: the lobes' own map integrated exactly;
``normals``: the stage's G-buffer with only its shading normals replaced by the truth render's, on the pixels both
silhouettes hold; its depth, outline, visibility and maps kept: the share of ``geometry`` the normals are)."""


SHADING_OVERRIDES: dict[str, Any] = {}
"""``--shading`` (``field=value,...``): changes to the stage's :class:`stages.numerics.novel_view.ViewShading` that
every row renders with (a variant measured on the budget's rows; empty: the release's own shading)."""


def stage_shading(release: Path | None = None) -> Any:
    """The relight stage's :class:`stages.numerics.novel_view.ViewShading` and its config: the release's
    (``config.yaml``'s ``relight``) when it has one, else the defaults; with :data:`SHADING_OVERRIDES` applied."""
    from pipeline.config import merge

    import yaml

    from pipeline.config import from_dict
    from stages.relight import RelightConfig

    path = Path(release) / "config.yaml" if release is not None else None
    record = (yaml.safe_load(path.read_text()) or {}).get("relight") if path is not None and path.exists() else None
    cfg = from_dict(RelightConfig, record, where=f"{path}: relight") if record else RelightConfig()
    return merge(cfg.shading, SHADING_OVERRIDES, "--shading"), cfg


def simulator_f0(roughness: np.ndarray) -> np.ndarray:
    """The simulator's F0 (P,) float32 for roughness values (P,) of its materials (synthetic.subject.MATERIALS:
    each material's F0 at the material whose roughness is nearest)."""
    from synthetic.subject import MATERIALS

    table = np.array([(rough, f0) for _, rough, f0 in MATERIALS.values()], np.float64)
    nearest = np.abs(np.asarray(roughness, np.float64)[:, None] - table[None, :, 0]).argmin(axis=1)
    return table[nearest, 1].astype(np.float32)


def exact_shade(normals: np.ndarray, view_dirs: np.ndarray, albedo: np.ndarray, roughness: np.ndarray,
                f0: float | np.ndarray, light_dirs: np.ndarray, light_irradiance: np.ndarray,
                visibility: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Lambertian + GGX radiance (P, 3) float32 under distant lights, each occluded per point: diffuse
    ``albedo / pi sum_l V max(0, n.l) E_l``, specular ``sum_l V F D Vis (n.l) E_l`` with the simulator's GGX
    (:func:`synthetic.shading.ggx_weights`, alpha = roughness**2).

    normals, view_dirs (towards the camera): (P, 3) unit; albedo (P, 3); roughness (P,); f0 scalar or (P,);
    light_dirs (L, 3) unit; light_irradiance (L, 3); visibility (P, L) bool."""
    from synthetic.shading import ggx_weights

    n = np.asarray(normals, np.float32)
    p = len(n)
    if view_dirs.shape != (p, 3) or albedo.shape != (p, 3) or roughness.shape != (p,):
        raise ValueError(f"view_dirs, albedo (P, 3) and roughness (P,) must match normals {n.shape}")
    if visibility.shape != (p, len(light_dirs)) or light_irradiance.shape != (len(light_dirs), 3):
        raise ValueError(f"visibility {visibility.shape} / irradiance {light_irradiance.shape} do not match "
                         f"{p} points and {len(light_dirs)} lights")
    f0 = np.broadcast_to(np.asarray(f0, np.float32), (p,))
    dirs = np.asarray(light_dirs, np.float32)
    irr = np.asarray(light_irradiance, np.float32)
    alpha = np.clip(np.asarray(roughness, np.float32), ROUGHNESS_MIN, ROUGHNESS_MAX) ** 2
    out = np.zeros((p, 3), np.float32)
    for start in range(0, p, chunk):
        sl = slice(start, min(start + chunk, p))
        vis = visibility[sl].astype(np.float32)
        cos = np.maximum(n[sl] @ dirs.T, 0.0) * vis
        diffuse = albedo[sl] / np.pi * (cos @ irr)
        spec = (ggx_weights(n[sl], np.asarray(view_dirs[sl], np.float32), dirs, alpha[sl], f0[sl]) * vis) @ irr
        out[sl] = diffuse + spec
    return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)


def tone_gain(pred: np.ndarray, pred_mask: np.ndarray, true: np.ndarray, true_mask: np.ndarray) -> np.ndarray:
    """The per-channel gain (3,) that brings ``pred`` (H, W, 3) closest to ``true`` in least squares over the union
    of the masks (H, W) (exposure and white balance); 1 where a channel of ``pred`` is black."""
    union = np.asarray(pred_mask, bool) | np.asarray(true_mask, bool)
    x = np.where(pred_mask[..., None], pred, 0.0)[union].astype(np.float64)
    y = np.where(true_mask[..., None], true, 0.0)[union].astype(np.float64)
    den = (x * x).sum(axis=0)
    return np.where(den > 0, (x * y).sum(axis=0) / np.maximum(den, 1e-30), 1.0)


def score(pred: np.ndarray, pred_mask: np.ndarray, true: dict) -> dict[str, float]:
    """PSNR (:func:`stages.numerics.metrics.relit_psnr`, the evaluation's) and SSIM of the images at its common
    exposure, clipped to [0, 1], over the union of the masks; ``composited_psnr_db``, the evaluation's composited
    figure (both images as they are over black, no mask threshold)."""
    from stages.numerics.metrics import relit_psnr, ssim

    result = relit_psnr(pred, pred_mask, true["radiance"], true["mask"])
    composited = relit_psnr(pred, pred_mask, true["radiance"], true["mask"], composited=True)
    union = pred_mask | true["mask"]
    a = np.clip(np.where(pred_mask[..., None], pred, 0.0) * result["scale"], 0, 1)
    b = np.clip(np.where(true["mask"][..., None], true["radiance"], 0.0) * result["scale"], 0, 1)
    return {"psnr_db": result["psnr_db"], "ssim": ssim(a, b, union), "composited_psnr_db": composited["psnr_db"]}


def project_onto(scene: Any, points: np.ndarray) -> np.ndarray:
    """The nearest points (P, 3) of a ray-casting scene's surface to ``points`` (P, 3)."""
    import open3d as o3d

    if len(points) == 0:
        return np.asarray(points, np.float64)
    ans = scene.compute_closest_points(o3d.core.Tensor(np.asarray(points, np.float32)))
    return ans["points"].numpy().astype(np.float64)


class ActionBudget:
    """One action's stage asset, its truth and the G-buffers, visibilities and images of every swap, cached."""

    def __init__(self, release: Path, capture: Path, action: str, threads: int, quick: bool,
                 truth_visibility: Path | None = None, ceiling_supersample: int = 0):
        from evaluation.release import relit_truth_lights
        from manifests import open_release, release_artifacts
        from pipeline.codecs.exr import read_exr
        from pipeline.codecs.mesh import read_ply
        from stages.numerics.gbuffer import SourceView
        from stages.numerics.raycast import mesh_scene
        from stages.relightable import load_relightable_asset
        from synthetic.relight import TruthRelighter, environment_lights

        self.shading, cfg = stage_shading(release)
        self.threads = threads
        t0 = time.perf_counter()
        rel = open_release(release)
        self.view = rel.action(action)
        # whole frames: the true geometry's points can project outside the part of a frame the stage's mesh covers
        self.asset, self.cameras = load_relightable_asset(release_artifacts(rel, action), cfg.min_alpha,
                                                          cfg.diffuse_normals, cfg.diffuse_albedo, cut_sources=False)
        self.cams = self.view.render_cameras()
        self.environments = self.view.release.load(self.view.asset("render_environments", None))["environments"]
        truth_dir = Path(capture) / "ground_truth" / action
        lights = relit_truth_lights(self.cams)
        self.truth = TruthRelighter(capture, action, lights=lights, visibility_cache=truth_visibility)
        self.capture_root = Path(capture)
        true_vertices, true_faces = read_ply(truth_dir / "mesh.ply")
        self.true_scene = mesh_scene(true_vertices, true_faces)
        self.light_dirs = self.truth.directions
        self.environment_lights = environment_lights
        # the captured views' truth: depth and normals (geometry), albedo; in the order of the asset's sources
        geo_sources, albedo_sources = [], []
        for cam_id, src in zip(self.cameras, self.asset.sources):
            normal = read_exr(truth_dir / "normal" / f"{cam_id}.exr")[..., :3]
            albedo = read_exr(truth_dir / "albedo" / f"{cam_id}.exr")[..., :3]
            depth = read_exr(truth_dir / "depth" / f"{cam_id}.exr")
            depth = depth[..., 0] if depth.ndim == 3 else depth
            seen = depth > 0
            geo_sources.append(SourceView(normal=np.ascontiguousarray(normal, np.float32), albedo=src.albedo,
                                          valid=seen, K=src.K, cam_from_world=src.cam_from_world,
                                          depth_m=depth.astype(np.float32)))
            albedo_sources.append(dataclasses.replace(src, albedo=np.ascontiguousarray(albedo, np.float32)))
        true_asset = dataclasses.replace(self.asset, scene=self.true_scene, faces=true_faces,
                                         smooth_normals=self.truth.subject.normals_world.astype(np.float64),
                                         sources=geo_sources)
        self.assets = {(False, False): self.asset,
                       (True, False): true_asset,
                       (False, True): dataclasses.replace(self.asset, sources=albedo_sources,
                                                          sources_diffuse_albedo=True),
                       (True, True): dataclasses.replace(true_asset, sources=[
                           dataclasses.replace(g, albedo=a.albedo) for g, a in zip(geo_sources, albedo_sources)],
                           sources_diffuse_albedo=True)}
        self.load_s = time.perf_counter() - t0
        self.quick = quick
        self.ceiling_supersample = int(ceiling_supersample)

    def lobes(self, env_record: dict) -> Any:
        from stages.numerics.sg import SGLobes

        return SGLobes.from_dict(env_record["lobes"])


def _gbuffer_from_truth(gb: dict, true: dict, K: np.ndarray, pose: np.ndarray, kind: str) -> dict:
    """A G-buffer (:func:`stages.numerics.novel_view.novel_view_gbuffer`'s keys) whose silhouette, normals and albedo
    are the truth render's, on the points of ``gb`` (the true mesh's G-buffer); roughness, occlusion and diffuse
    ratio kept from ``gb`` (the nearest of its pixels off its mask)."""
    from artifacts.camera import Camera

    mask = np.asarray(true["mask"], bool)
    h, w = mask.shape
    pix = np.flatnonzero(mask.reshape(-1))
    camera = Camera(K, pose, w, h)
    # the true mesh's depth at the pixel centres (``gb``'s, cast against it) where it has one: the truth's is the
    # mean over the pixel's rays, inside a convex surface
    depth = np.where(gb["hit"], gb["depth_m"], np.asarray(true["depth_m"], np.float32))
    points = camera.lift_depth_map(depth).reshape(-1, 3)[pix]
    view_dirs = camera.centre[None] - points
    view_dirs /= np.maximum(np.linalg.norm(view_dirs, axis=1, keepdims=True), 1e-12)
    normals = np.asarray(true["normals_world"], np.float32)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 1e-6)
    out = dict(gb)
    out.update({"mask": mask, "hit": mask | gb["hit"], "pix": pix, "points": points, "view_dirs": view_dirs,
                f"normal_{kind}": normals, "albedo": np.asarray(true["albedo"], np.float32)})
    for name in ("roughness", "occlusion", "diffuse_ratio"):  # the true mesh's texture lookups, nearest outside
        out[name] = np.where(mask.reshape(mask.shape + (1,) * (gb[name].ndim - 2)),
                             fill_nearest(gb[name], gb["mask"]), 0.0).astype(np.float32)
    return out


def fill_nearest(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``image`` (H, W[, C]) with every pixel off ``valid`` (H, W) given its nearest valid pixel's value."""
    from scipy.ndimage import distance_transform_edt

    if not valid.any() or valid.all():
        return image
    _, (rows, cols) = distance_transform_edt(~valid, return_indices=True)
    return image[rows, cols]


SILHOUETTE_BAND_PX = 2
"""Width of the silhouette band of :func:`silhouette_split`: pixels within this of either mask's outline."""


def pixel_classes(pred_mask: np.ndarray, true_mask: np.ndarray, band_px: float = SILHOUETTE_BAND_PX
                  ) -> dict[str, np.ndarray]:
    """The union of two masks (H, W) split into (H, W) bool classes: ``interior`` (in both, farther than ``band_px``
    from either outline), ``band`` (in both, within ``band_px`` of either outline: distance from a pixel to the
    nearest pixel on the other side of a mask's edge, 1 for the pixels touching it), ``pred_only`` and
    ``true_only`` (in one mask only)."""
    from scipy.ndimage import distance_transform_edt

    pm, tm = np.asarray(pred_mask, bool), np.asarray(true_mask, bool)
    if pm.shape != tm.shape or pm.ndim != 2:
        raise ValueError(f"masks must both be (H, W), got {pm.shape} and {tm.shape}")

    def to_edge(m: np.ndarray) -> np.ndarray:
        if m.all() or not m.any():
            return np.full(m.shape, np.inf)
        return np.where(m, distance_transform_edt(m), distance_transform_edt(~m))

    near = (to_edge(pm) <= band_px) | (to_edge(tm) <= band_px)
    both = pm & tm
    return {"interior": both & ~near, "band": both & near, "pred_only": pm & ~tm, "true_only": tm & ~pm}


def outline_offset_px(pred_coverage: np.ndarray, true_coverage: np.ndarray) -> dict[str, float]:
    """How far one silhouette lies outside another, from their pixel coverages (H, W) in [0, 1]: ``offset_px`` the
    covered area's difference over the true outline's length (the sum of the true coverage's gradient magnitude,
    ``np.gradient``: one per pixel of a straight edge), positive outwards; ``edge_rms`` the RMS coverage difference
    over the pixels either outline crosses (0 < coverage < 1); ``outline_px`` the length."""
    pred = np.asarray(pred_coverage, np.float64)
    true = np.asarray(true_coverage, np.float64)
    if pred.shape != true.shape or pred.ndim != 2:
        raise ValueError(f"coverages must both be (H, W), got {pred.shape} and {true.shape}")
    gy, gx = np.gradient(true)
    length = float(np.hypot(gx, gy).sum())
    edge = ((pred > 0) & (pred < 1)) | ((true > 0) & (true < 1))
    return {"offset_px": float((pred.sum() - true.sum()) / length) if length > 0 else 0.0,
            "edge_rms": float(np.sqrt(np.mean((pred - true)[edge] ** 2))) if edge.any() else 0.0,
            "outline_px": length}


def unpremultiplied(image: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """The colour (H, W, 3) of an image premultiplied by ``alpha`` (H, W): image / alpha where alpha > 0, the nearest
    such pixel's colour elsewhere (0 for an empty alpha)."""
    alpha = np.asarray(alpha, np.float64)
    if not (alpha > 0).any():
        return np.zeros(np.shape(image), np.float64)
    colour = np.where(alpha[..., None] > 0, np.asarray(image, np.float64) / np.maximum(alpha, 1e-6)[..., None], 0.0)
    return fill_nearest(colour, alpha > 0)


def silhouette_split(image: np.ndarray, alpha: np.ndarray, mask: np.ndarray, true: dict, true_alpha: np.ndarray,
                     true_alpha_camera: np.ndarray, fine_colour: np.ndarray | None = None) -> dict[str, Any]:
    """What a relit view's silhouette band costs (:func:`pixel_classes`, band of :data:`SILHOUETTE_BAND_PX`): the
    shares of the squared error (the PSNR's, :func:`score`'s exposure) per class, and the PSNR with the band's (its
    pixels and the one-mask ones) alpha and colour swapped for the truth's: ``outline`` (the true mesh's coverage
    ``true_alpha`` (H, W), on the stage's ray grid, our colour), ``colour`` (the truth's colour, the truth's
    radiance over its coverage, our alpha), ``both`` and ``both_camera_grid`` (the truth's colour at the coverage of
    the truth camera's own rays, ``true_alpha_camera``); with ``fine_colour`` (H, W, 3), the colour of a finer
    truth (the ceiling's render over its coverage), also ``colour_fine_truth``: that colour, our alpha, what exact
    shading of the band could recover, the rest of ``colour`` being the capture grid's own sampling of the rim.
    Masks are alpha >= 0.5 as the stage's."""
    from stages.numerics.metrics import relit_psnr

    radiance, true_mask = np.asarray(true["radiance"], np.float64), np.asarray(true["mask"], bool)
    classes = pixel_classes(mask, true_mask)
    result = relit_psnr(image, mask, radiance, true_mask)
    scale = result["scale"]
    pred = np.clip(np.where(mask[..., None], image, 0.0) * scale, 0, 1)
    ref = np.clip(np.where(true_mask[..., None], radiance, 0.0) * scale, 0, 1)
    sq = ((pred - ref) ** 2).sum(axis=2)
    total = max(float(sq.sum()), 1e-30)
    band = classes["band"] | classes["pred_only"] | classes["true_only"]
    colour, true_colour = unpremultiplied(image, alpha), unpremultiplied(radiance, true_alpha_camera)

    def swapped(c: np.ndarray, a: np.ndarray) -> float:
        c = np.where(band[..., None], c, colour)
        a = np.where(band, a, alpha)
        return relit_psnr(c * a[..., None], a >= 0.5, radiance, true_mask)["psnr_db"]

    swaps = {"outline": swapped(colour, true_alpha), "colour": swapped(true_colour, alpha),
             "both": swapped(true_colour, true_alpha), "both_camera_grid": swapped(true_colour, true_alpha_camera)}
    if fine_colour is not None:
        swaps["colour_fine_truth"] = swapped(np.asarray(fine_colour, np.float64), alpha)
    return {"psnr_db": result["psnr_db"], "shares": {k: float(sq[v].sum() / total) for k, v in classes.items()},
            "pixels": {k: int(v.sum()) for k, v in classes.items()}, "swaps": swaps}


def budget_view(ab: ActionBudget, cam: dict, env_records: list[dict], rows: dict[str, frozenset],
                progress) -> dict:
    """Every row's PSNR and SSIM for one novel camera under every environment, with the time of each piece."""
    from stages.numerics.novel_view import (novel_view_gbuffer, premultiply_edges, scatter_pixels, shade_gbuffer,
                                            silhouette_alpha)
    from stages.numerics.raycast import pixel_coverage
    from stages.numerics.sg import fibonacci_sphere, render_sg_environment
    from stages.numerics.shadowing import direction_visibility
    from stages.environments import find_environment, load_environment

    shading = ab.shading
    K, pose = np.asarray(cam["K"], np.float64), np.asarray(cam["cam_from_world"], np.float64)
    h, w = int(cam["height"]), int(cam["width"])
    directions = fibonacci_sphere(shading.visibility_directions)
    times: dict[str, float] = {}
    gbuffers: dict[tuple, dict] = {}
    visibilities: dict[tuple, np.ndarray] = {}
    alphas: dict[tuple, tuple] = {}

    def timed(name: str, fn, *args, **kwargs):
        t0 = time.perf_counter()
        value = fn(*args, **kwargs)
        times[name] = times.get(name, 0.0) + time.perf_counter() - t0
        return value

    env_maps = {}
    for record in env_records:
        env_maps[record["label"]] = load_environment(record["name"], find_environment(record["name"],
                                                                                      ab.capture_root))[0]
    truths = {label: timed("truth_render", ab.truth.render, K, pose, h, w, env) for label, env in env_maps.items()}
    true0 = next(iter(truths.values()))

    coverages: dict[int, np.ndarray] = {}

    def true_coverage(samples: int) -> np.ndarray:
        """The true mesh's pixel coverage on ``samples`` x ``samples`` rays, traced once per count (the ceiling's
        colour and the outline share the 8 x 8 one)."""
        if samples not in coverages:
            coverages[samples] = timed("silhouette", pixel_coverage, K, pose, h, w, samples, ab.true_scene)
        return coverages[samples]

    def gbuffer(swaps: frozenset) -> dict:
        key = ("geometry" in swaps or "reprojection" in swaps, "albedo" in swaps or "reprojection" in swaps,
               "reprojection" in swaps)
        if key not in gbuffers:
            if key[2]:
                gb = _gbuffer_from_truth(gbuffer(frozenset({"geometry", "albedo"})), true0, K, pose, shading.normals)
            else:
                gb = timed("gbuffer", novel_view_gbuffer, ab.assets[key[:2]], K, pose, h, w,
                           **shading.gbuffer_options())
            gbuffers[key] = gb
        return gbuffers[key]

    def geometry_key(swaps: frozenset) -> str:
        return "truth" if "reprojection" in swaps else "true_mesh" if "geometry" in swaps else "ours"

    def visibility(swaps: frozenset, dirs: np.ndarray, tag: str) -> np.ndarray:
        gb = gbuffer(swaps)
        true_occluder = "visibility" in swaps
        key = (geometry_key(swaps), true_occluder, tag)
        if key not in visibilities:
            scene = ab.true_scene if true_occluder else ab.asset.scene
            points = gb["points"]
            if true_occluder != (geometry_key(swaps) != "ours"):  # the points lie on the other mesh
                points = project_onto(scene, points)
            normals = gb[f"normal_{shading.normals}"].reshape(-1, 3)[gb["pix"]]
            visibilities[key] = timed(f"visibility_{tag}", direction_visibility, points, normals, scene, dirs,
                                      threads=ab.threads)
        return visibilities[key]

    def silhouette(swaps: frozenset) -> tuple[np.ndarray, np.ndarray]:
        gb = gbuffer(swaps)
        key = geometry_key(swaps)
        if key not in alphas:
            scene = ab.asset.scene if key == "ours" else ab.true_scene
            alphas[key] = timed("coverage", lambda: silhouette_alpha(gb["mask"], pixel_coverage(
                K, pose, h, w, shading.coverage_samples, scene, centre_hit=gb["hit"])))
        return alphas[key]

    images: dict[frozenset, dict[str, tuple[np.ndarray, np.ndarray]]] = {}

    def render(swaps: frozenset) -> dict[str, dict[str, float]]:
        """Every environment's scores with ``swaps``; the images are kept by their swaps but the tone's."""
        base = swaps - {"tone"}
        if base not in images:
            images[base] = shade(base)
        out = {}
        for label, (image, mask) in images[base].items():
            true = truths[label]
            if "tone" in swaps:
                image = (image * tone_gain(image, mask, true["radiance"], true["mask"])).astype(np.float32)
            out[label] = score(image, mask, true)
        return out

    def shade(swaps: frozenset) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        gb = gbuffer(swaps)
        pix = gb["pix"]
        normals = gb[f"normal_{shading.normals}"].reshape(-1, 3)[pix]
        if "normals" in swaps:
            true_normals = np.asarray(true0["normals_world"], np.float64).reshape(-1, 3)[pix]
            length = np.linalg.norm(true_normals, axis=1, keepdims=True)
            inside = np.asarray(true0["mask"], bool).reshape(-1)[pix] & (length[:, 0] > 1e-6)
            normals = np.where(inside[:, None], true_normals / np.maximum(length, 1e-12), normals).astype(np.float32)
            gb = dict(gb, **{f"normal_{shading.normals}": scatter_pixels(pix, normals, h, w)})
        albedo = None
        if "albedo" in swaps or "reprojection" in swaps:  # the true diffuse albedo: shaded as is
            albedo = np.clip(gb["albedo"].reshape(-1, 3)[pix], 0.0, 1.0)
        rough = np.clip(gb["roughness"].reshape(-1)[pix], ROUGHNESS_MIN, ROUGHNESS_MAX)
        f0, shadowing = shading.f0, shading.shadowing
        if "material" in swaps:
            true_rough = np.asarray(true0["roughness"], np.float32).reshape(-1)[pix]
            inside = np.asarray(true0["mask"], bool).reshape(-1)[pix]
            rough = np.clip(np.where(inside, true_rough, rough), ROUGHNESS_MIN, ROUGHNESS_MAX)
            f0, shadowing = simulator_f0(rough), "smith"
        gb = dict(gb, roughness=scatter_pixels(pix, rough[:, None], h, w)[..., 0])
        out = {}
        exact = "lighting" in swaps or "lighting_sg" in swaps
        if exact:
            vis = visibility(swaps, ab.light_dirs, "lights")
            if albedo is None:
                from stages.numerics.novel_view import shading_albedo

                albedo = shading_albedo(gb["albedo"].reshape(-1, 3)[pix], gb["diffuse_ratio"].reshape(-1, 3)[pix],
                                        gb["occlusion"].reshape(-1)[pix])
            alpha, out_mask = silhouette(swaps)
        else:
            vis = visibility(swaps, directions, "stage")
        for record in env_records:
            label = record["label"]
            t0 = time.perf_counter()
            if exact:
                env = env_maps[label] if "lighting" in swaps else render_sg_environment(
                    ab.lobes(record), *env_maps[label].shape[:2])
                _, irradiance = ab.environment_lights(env, ab.truth.lights, ab.truth.max_height)
                rgb = exact_shade(normals, gb["view_dirs"], albedo, rough, f0, ab.light_dirs, irradiance, vis)
                image = premultiply_edges(scatter_pixels(pix, np.clip(rgb, 0, HALF_MAX), h, w), gb["mask"], alpha)
                mask = out_mask
            else:
                # the key lights' visibility traced as the directions' is (the same points and occluder)
                view = shade_gbuffer(gb, ab.true_scene if geometry_key(swaps) != "ours" else ab.asset.scene, K, pose,
                                     [ab.lobes(record)], shading, directions=directions, visibility=vis,
                                     albedo=albedo, f0=f0, shadowing=shadowing,
                                     key_visibility=lambda dirs, tag=f"key_{label}": visibility(swaps, dirs, tag))
                image, mask = view["images"][0], view["mask"]
            times["shade"] = times.get("shade", 0.0) + time.perf_counter() - t0
            out[label] = (image, mask)
        return out

    results = {"stage": render(frozenset())}
    for label, swaps in rows.items():
        results[label] = render(swaps)
    released = {}
    for record in env_records:
        try:
            image = ab.view.relit(cam["camera_id"], record["label"])
            released[record["label"]] = score(image[..., :3], image[..., 3] >= 0.5, truths[record["label"]])
        except (KeyError, FileNotFoundError):
            pass
    results["released"] = released
    ceiling, fine_colours = {}, {}
    if ab.ceiling_supersample:
        ceiling_rows = {"stage": frozenset()} | ({"+ reprojection": rows["+ reprojection"]}
                                                  if "+ reprojection" in rows else {})
        fine_coverage = true_coverage(ab.ceiling_supersample)
        for label, env in env_maps.items():
            fine = timed("ceiling_render", ab.truth.render, K, pose, h, w, env, supersample=ab.ceiling_supersample)
            fine_colours[label] = unpremultiplied(fine["radiance"], fine_coverage)
            ceiling[label] = {"truth": score(truths[label]["radiance"], truths[label]["mask"], fine)}
            for row, swaps in ceiling_rows.items():
                image, mask = images[swaps][label]
                ceiling[label][row] = score(image, mask, fine)
    # the stage's render against the true mesh's outline (silhouette_split)
    gb, (alpha, mask) = gbuffer(frozenset()), silhouette(frozenset())
    true_alpha = true_coverage(shading.coverage_samples)
    camera_grid = timed("silhouette", pixel_coverage, K, pose, h, w, ab.truth.config.supersample, ab.true_scene,
                        edges_only=False)
    split = {label: silhouette_split(image, alpha, mask, truths[label], true_alpha, camera_grid,
                                     fine_colours.get(label))
             for label, (image, _) in images[frozenset()].items()}
    ours = timed("silhouette", pixel_coverage, K, pose, h, w, 8, ab.asset.scene)
    outline = outline_offset_px(ours, true_coverage(8))
    outline["mm_per_px"] = float(np.median(gb["depth_m"][gb["mask"]]) / K[0, 0] * 1e3) if gb["mask"].any() else 0.0
    progress(f"  {cam['camera_id']}: " + "; ".join(
        f"{label} " + ", ".join(f"{v['psnr_db']:.2f}" for v in envs.values()) for label, envs in results.items())
        + " dB; " + ", ".join(f"{k} {v:.1f} s" for k, v in times.items()))
    return {"camera_id": cam["camera_id"], "pixels": int(len(gbuffer(frozenset())["pix"])),
            "rows": results, "silhouette": {"environments": split, "outline": outline}, "ceiling": ceiling,
            "seconds": times}


def budget_rows() -> dict[str, frozenset]:
    """label -> swaps: each component alone, the extra rows, then the cumulative ones (``+ component``)."""
    rows = {f"only {c}": frozenset({c}) for c in COMPONENTS}
    rows.update(EXTRA_ROWS)
    done: set[str] = set()
    for c in COMPONENTS:
        done.add(c)
        rows[f"+ {c}"] = frozenset(done)
    return rows


def summarise(report: dict) -> dict:
    """Mean PSNR and SSIM per row over actions, views and environments, and the dB each recovers (one at a time:
    over the stage's render; cumulative: over the row before)."""
    per_row: dict[str, dict[str, list[float]]] = {}
    for action in report["actions"].values():
        for view in action["views"]:
            for label, envs in view["rows"].items():
                for metrics in envs.values():
                    for k, v in metrics.items():
                        per_row.setdefault(label, {}).setdefault(k, []).append(float(v))
    means = {label: {k: float(np.mean(v)) for k, v in m.items()} | {"n": len(m["psnr_db"])}
             for label, m in per_row.items()}
    stage = means["stage"]["psnr_db"]
    previous = stage
    for label in means:
        if label.startswith("+ "):
            means[label]["recovered_db"] = means[label]["psnr_db"] - previous
            previous = means[label]["psnr_db"]
        elif label not in ("stage", "released"):
            means[label]["recovered_db"] = means[label]["psnr_db"] - stage
    return means


def summarise_silhouette(report: dict) -> dict:
    """Means over actions, views and environments of :func:`silhouette_split` (shares, PSNRs and the dB each swap
    recovers over the stage's render) and over views of :func:`outline_offset_px` (with the offset in mm)."""
    splits = [e for a in report["actions"].values() for v in a["views"] for e in v["silhouette"]["environments"].values()]
    outlines = [v["silhouette"]["outline"] for a in report["actions"].values() for v in a["views"]]
    stage = float(np.mean([e["psnr_db"] for e in splits]))
    swaps = {k: float(np.mean([e["swaps"][k] for e in splits])) for k in splits[0]["swaps"]}
    return {"psnr_db": stage, "n": len(splits),
            "shares": {k: float(np.mean([e["shares"][k] for e in splits])) for k in splits[0]["shares"]},
            "pixel_shares": {k: float(np.mean([e["pixels"][k] / max(sum(e["pixels"].values()), 1) for e in splits]))
                             for k in splits[0]["pixels"]},
            "swaps": swaps, "recovered_db": {k: v - stage for k, v in swaps.items()},
            "offset_px": float(np.mean([o["offset_px"] for o in outlines])),
            "offset_mm": float(np.mean([o["offset_px"] * o["mm_per_px"] for o in outlines])),
            "edge_rms": float(np.mean([o["edge_rms"] for o in outlines]))}


def summarise_ceiling(report: dict) -> dict:
    """Over actions, views and environments: the capture-grid truth's PSNR against the fine truth (mean, worst
    image and where), and each ceiling row's mean PSNR against the fine truth and against the capture-grid truth
    (empty without ``--ceiling-supersample``)."""
    per_image = [(action_id, view["camera_id"], env, scores) for action_id, action in report["actions"].items()
                 for view in action["views"] for env, scores in view.get("ceiling", {}).items()]
    if not per_image:
        return {}
    truth = [scores["truth"]["psnr_db"] for *_, scores in per_image]
    worst = int(np.argmin(truth))
    rows = [k for k in per_image[0][3] if k != "truth"]
    against_capture = {label: float(np.mean([view["rows"][label][env]["psnr_db"]
                                             for action in report["actions"].values() for view in action["views"]
                                             for env in view.get("ceiling", {})])) for label in rows}
    return {"n": len(per_image), "supersample": report["ceiling_supersample"], "truth_mean_db": float(np.mean(truth)),
            "truth_worst_db": truth[worst], "truth_worst_image": "/".join(per_image[worst][:3]),
            "rows": {label: {"fine_db": float(np.mean([s[label]["psnr_db"] for *_, s in per_image])),
                             "capture_grid_db": against_capture[label]} for label in rows}}


def markdown(report: dict) -> str:
    s = report["summary"]
    changed = report.get("shading_overrides") or {}
    lines = ["# Relit novel views: error budget by oracle swaps", "",
             *([f"Shading changed from the release's: {changed}", ""] if changed else []),
             f"Actions {', '.join(report['actions'])}, {report['views']} views x {report['environments']} "
             f"environments ({s['stage']['n']} images per row); the stage's render, then each component replaced "
             "by the simulator's truth (one at a time: dB over the stage's; cumulative `+`: dB over the row before)."
             + (f" The rows render one shading sample per pixel; the release's images (`released`) "
                f"{report['shading']['supersample']} x {report['shading']['supersample']}."
                if report["shading"].get("supersample", 1) != 1 else "")
             + (" **Quick run: not measurements.**" if report["quick"] else ""), "",
             "| row | PSNR dB | SSIM | dB recovered | composited PSNR dB |", "|---|---:|---:|---:|---:|"]
    for label, m in s.items():
        rec = f"{m['recovered_db']:+.2f}" if "recovered_db" in m else ""
        composited = f"{m['composited_psnr_db']:.2f}" if "composited_psnr_db" in m else ""
        lines.append(f"| {label} | {m['psnr_db']:.2f} | {m['ssim']:.4f} | {rec} | {composited} |")
    sil = report["silhouette"]
    lines += ["", f"## The silhouette band ({SILHOUETTE_BAND_PX} px of either outline, and the pixels in one mask "
              f"only; {sil['n']} images)", "",
              "| class | pixels | squared error |", "|---|---:|---:|"]
    lines += [f"| {k} | {sil['pixel_shares'][k]:.1%} | {sil['shares'][k]:.1%} |" for k in sil["shares"]]
    lines += ["", "| the band's ... swapped for the truth's | PSNR dB | dB recovered |", "|---|---:|---:|",
              f"| nothing (the stage's render) | {sil['psnr_db']:.2f} | |"]
    lines += [f"| {k} | {sil['swaps'][k]:.2f} | {sil['recovered_db'][k]:+.2f} |" for k in sil["swaps"]]
    if "colour_fine_truth" in sil["swaps"]:
        lines += ["", "`colour_fine_truth`: the band's colour from the ceiling's finer truth (below), what exact "
                  "shading of the band could recover; the rest of `colour` is the capture-grid truth's own sampling "
                  "of the rim, which no render can match."]
    lines += ["", f"Our mesh's outline against the true mesh's (8 x 8 rays per pixel): {sil['offset_px']:+.3f} px "
              f"({sil['offset_mm']:+.2f} mm) outside on average, RMS coverage difference {sil['edge_rms']:.3f} on the "
              "pixels either outline crosses."]
    c = report.get("ceiling") or {}
    if c:
        lines += ["", f"## The metric's ceiling: the truth at the capture's grid against {c['supersample']} x "
                  f"{c['supersample']} rays per pixel ({c['n']} images)", "",
                  f"The capture-grid truth scores {c['truth_mean_db']:.2f} dB on average against the finer one, "
                  f"{c['truth_worst_db']:.2f} dB on its worst image ({c['truth_worst_image']}): a render of the exact "
                  "pixel integrals would score about that against the truth the evaluation uses.", "",
                  "| row | PSNR dB against the capture-grid truth | against the fine truth |", "|---|---:|---:|"]
        lines += [f"| {label} | {m['capture_grid_db']:.2f} | {m['fine_db']:.2f} |" for label, m in c["rows"].items()]
    t = report["seconds_per_view"]
    lines += ["", "Seconds per view (mean): " + ", ".join(f"{k} {v:.1f}" for k, v in t.items()), ""]
    return "\n".join(lines)


def figure(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = report["summary"]
    labels = [k for k in s if "recovered_db" in s[k]]
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(labels) + 1.5))
    values = [s[k]["recovered_db"] for k in labels]
    colours = ["tab:orange" if k.startswith("+ ") else "tab:blue" for k in labels]
    ax.barh(range(len(labels)), values, color=colours)
    ax.set_yticks(range(len(labels)), labels)
    ax.invert_yaxis()
    ax.axvline(0, color="k", lw=0.5)
    ax.set_xlabel(f"dB recovered (stage {s['stage']['psnr_db']:.2f} dB; blue: alone, orange: cumulative)")
    ax.set_title("Relit novel views: error budget by oracle swaps" + (" (quick)" if report["quick"] else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    from _release import check_inputs, parse_release_args, release_parser
    from _report import write_report

    parser = release_parser(__doc__, actions="", threads=2)
    parser.add_argument("--shading", default="", help="ViewShading changes every row renders with, "
                        "field=value[,field=value] (e.g. shadowing=smith,f0=0.03): a variant on the budget's rows")
    parser.add_argument("--rows", default="", help="only these rows besides the stage's (labels, comma-separated; "
                        "default every row)")
    parser.add_argument("--views", type=int, default=0, help="the first N novel views of each action (0: all)")
    parser.add_argument("--tag", default="", help="suffix of the output files' names (bench_relit_budget<tag>.*)")
    parser.add_argument("--ceiling-supersample", type=int, default=8,
                        help="rays per pixel side of the fine truth the ceiling table scores against (0: no table)")
    args = parse_release_args(parser)
    if args.ceiling_supersample < 0:
        parser.error(f"--ceiling-supersample must be >= 0, got {args.ceiling_supersample}")
    import yaml

    SHADING_OVERRIDES.update({k.strip(): yaml.safe_load(v) for k, v in
                              (item.split("=", 1) for item in args.shading.split(",") if item.strip())})
    release, capture, out = Path(args.release), Path(args.capture), Path(args.out)
    if not check_inputs("bench_relit_budget", release, capture, need_truth=True)[0]:
        return 0
    from _threads import set_numeric_threads

    set_numeric_threads(args.threads)
    from manifests import open_release

    shading, cfg = stage_shading(release)
    if cfg.learned_blend.enabled:
        print("bench_relit_budget: the stage's default blend is learned; this bench renders the heuristic weights")
        return 1
    if shading.supersample != 1:
        print(f"bench_relit_budget: the release's images have {shading.supersample} x {shading.supersample} shading "
              "samples per pixel (its `released` row); the budget's rows render one at each pixel's centre")
    rel = open_release(release)
    actions = [a for a in (args.actions.split(",") if args.actions else rel.action_ids)
               if rel.action(a).render_cameras()]
    if not actions:
        print(f"bench_relit_budget: no action of {release} has renders/; skipped")
        return 0
    started = time.perf_counter()
    rows = budget_rows()
    if args.rows:
        wanted = [r.strip() for r in args.rows.split(",") if r.strip()]
        unknown = sorted(set(wanted) - set(rows))
        if unknown:
            parser.error(f"--rows: unknown {unknown}; rows are {list(rows)}")
        rows = {k: v for k, v in rows.items() if k in wanted}
    report: dict[str, Any] = {"quick": args.quick, "threads": args.threads, "release": str(release),
                              "shading_overrides": dict(SHADING_OVERRIDES),
                              "shading": dataclasses.asdict(shading), "components": list(COMPONENTS),
                              "rows": {k: sorted(v) for k, v in rows.items()}, "actions": {},
                              "ceiling_supersample": args.ceiling_supersample}
    for action in actions:
        ab = ActionBudget(release, capture, action, args.threads, args.quick, out / "truth_visibility",
                          args.ceiling_supersample)
        cams = ab.cams[:1] if args.quick else ab.cams[:args.views] if args.views else ab.cams
        envs = ab.environments[:1] if args.quick else ab.environments
        print(f"{action}: asset and truth loaded in {ab.load_s:.1f} s", flush=True)
        views = [budget_view(ab, cam, envs, rows, lambda m: print(m, flush=True)) for cam in cams]
        report["actions"][action] = {"load_s": ab.load_s, "views": views}
        report["views"], report["environments"] = len(cams), len(envs)
    report["summary"] = summarise(report)
    report["silhouette"] = summarise_silhouette(report)
    report["ceiling"] = summarise_ceiling(report)
    seconds: dict[str, list[float]] = {}
    for action in report["actions"].values():
        for view in action["views"]:
            for k, v in view["seconds"].items():
                seconds.setdefault(k, []).append(v)
    report["seconds_per_view"] = {k: float(np.mean(v)) for k, v in seconds.items()}
    report["total_s"] = time.perf_counter() - started
    name = f"bench_relit_budget{args.tag}"
    write_report(out, name, report, markdown(report), lambda path: figure(report, path), json_default=_json_default)
    print(f"total {report['total_s']:.0f} s; wrote {out / name}.json, .md and .png")
    return 0


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value)}")


if __name__ == "__main__":
    sys.exit(main())
