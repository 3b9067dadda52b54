"""Materials stage: the roughness texture and the de-occluded albedo against the simulator, with their times.

For each action of a release (default A0000 and A0001) this runs the materials stage's steps on the release's
own files, calling the functions the stage calls (``stages.materials`` ``texel_samples``, ``fit_texel_materials``,
``published_roughness``, ``texel_texture``, ``albedo_without_occlusion``, and
``stages.numerics.shadowing.ambient_occlusion``) with configs derived from the stage's defaults
(:func:`default_config`, one field changed per variant: :func:`variant_configs`), and scores every
variant like ``ultrastage evaluate`` does (``evaluation.release._materials_overall``): the textures are seen
through the textured mesh from every **true** camera (pixels where the truth has the subject and the mesh
is hit) and compared with the simulator's roughness and albedo maps.

1. **Roughness** (the stage's texture size): mean absolute error and bias against the truth for ``specular_model``
   sg, ``fit_albedo`` off, ``max_views`` 8 (the 8 best views are the first 8 of those gathered: same ranking),
   ``median_min_visibility`` 0/0.85 (which texels vote in the surface median: those whose ambient visibility on
   the mesh reaches it), ``min_cos`` 0.2/0.4/0.6 (the most grazing view a fit takes; the observations are
   gathered once at the lowest limit and each fit keeps the views within its own), ``specular_cone_deg`` 0 (no
   mirror-cone test)/8/25 and the test off at ``min_cos`` 0.4 (each cone traced once, as the stage traces it),
   ``albedo_max_views`` 0/4/16, ``median_neighbours`` 1/25/100/200 and the albedo guide of the median
   (``median_albedo_m`` / ``median_albedo_neighbours``: :data:`ALBEDO_GUIDE_SWEEP`), one change at a time from
   the stage's defaults (a change equal to the default is left out), with the fit time (``fit_roughness``, both
   fits with ``albedo_max_views``, ``--threads`` torch threads; ``x_gather``: as a ratio to gathering the
   observations it fits, in the same process) and the smoothing time. Per variant also the PSNR against the truth
   of the intrinsic albedo texture its diffuse ratio gives (the baked albedo times the ratio, the released
   occlusion texture divided out, as the stage).
   Per variant, the fitted mean at each true roughness (the simulator's materials).
   Baselines: a constant roughness equal to the median of the per-texel fits (what a fit that finds no
   variation gives) and, as oracles, the truth's own mean and median over the compared pixels (the median
   is the constant with the least absolute error).
   The default row must match the released texture's score (``released`` row) when the release was made
   with the stage's defaults.
2. **Albedo**: PSNR against the truth of the baked white-light albedo texture and of the de-occluded one
   (ambient occlusion on the mesh at the stage's ``occlusion_size`` with ``occlusion_rays`` 16/64/128, divided
   out with a floor ``min_occlusion`` 0.1/0.2/0.4, the stage's defaults included), with the occlusion time and
   each texture's median ratio to the truth
   (its gain); and the baked albedo divided by the simulator's per-pixel visibility map. That is no upper
   bound: in creases the blurred texture and the true pixel disagree and the division blows the error up.

``python bench/bench_materials.py --out DIR [--release DIR --capture DIR --actions A0000,A0001 --threads 2]``
writes DIR/bench_materials.json, DIR/bench_materials.md (tables) and DIR/bench_materials.png (roughness MAE
against fit seconds; albedo PSNR against occlusion seconds). Defaults: runs/default/release and
runs/default/capture; without them (or without ground truth) it prints why and exits 0. ``--quick`` (the tests'
mode): the tiny run of ``bench/_quick.py``, the roughness texture at 64 and the occlusion at 128 texels a side
(every other setting the stage's); the numbers are not measurements.
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _report import write_report  # noqa: E402

from stages.materials import MaterialsConfig  # noqa: E402

# One change at a time from the stage's defaults; the sweeps' values besides the defaults (which every sweep
# includes). The bench declares no setting of its own: everything else is the stage's config.
VARIANT_CHANGES = [("specular_model sg", {"specular_model": "sg"}),
                   ("fit_albedo off", {"fit_albedo": False}),
                   ("max_views 8", {"max_views": 8}),
                   ("max_views 16", {"max_views": 16}),
                   ("median_min_visibility 0 (every fitted texel votes)", {"median_min_visibility": 0.0}),
                   ("median_min_visibility 0.85", {"median_min_visibility": 0.85}),
                   ("min_cos 0.2", {"min_cos": 0.2}),
                   ("min_cos 0.4", {"min_cos": 0.4}),
                   ("min_cos 0.6", {"min_cos": 0.6}),
                   ("specular_cone_deg 0 (no mirror-cone test)", {"specular_cone_deg": 0.0}),
                   ("specular_cone_deg 8", {"specular_cone_deg": 8.0}),
                   ("specular_cone_deg 25", {"specular_cone_deg": 25.0}),
                   ("no mirror-cone test, min_cos 0.4", {"specular_cone_deg": 0.0, "min_cos": 0.4}),
                   ("albedo_max_views 0 (the albedo of the roughness fit)", {"albedo_max_views": 0}),
                   ("albedo_max_views 4", {"albedo_max_views": 4}),
                   ("albedo_max_views 16", {"albedo_max_views": 16})]
MEDIAN_NEIGHBOURS_SWEEP = (1, 25, 100, 200)
ALBEDO_GUIDE_SWEEP = ((0.0, 1), (0.15, 1), (0.05, 32), (0.15, 16), (0.3, 32))
"""(median_albedo_m, median_albedo_neighbours) of the albedo-guided median's sweep on the default fit (0: nearest on
the surface alone); the stage's default is added."""
OCCLUSION_RAYS_SWEEP = (16, 64, 128)
MIN_OCCLUSION_SWEEP = (0.1, 0.2, 0.4)


def default_config() -> MaterialsConfig:
    """The configuration of the bench's default row: the materials stage's own defaults."""
    return MaterialsConfig()


def variant_configs(base: MaterialsConfig | None = None) -> list[tuple[str, MaterialsConfig]]:
    """(label, config) of every roughness variant: ``base`` (default :func:`default_config`) first, then each
    of ``VARIANT_CHANGES`` applied to it alone, leaving out those that equal ``base``."""
    base = default_config() if base is None else base
    rows = [(f"default ({base.specular_model}, fit_albedo {base.fit_albedo}, {base.max_views} views, "
             f"voters >= {base.median_min_visibility:g} visible)", base)]
    for label, change in VARIANT_CHANGES:
        config = dataclasses.replace(base, **change)
        if config != base:
            rows.append((label, config))
    return rows


def sweep(values: tuple, default) -> list:
    """A sweep's values with the stage's default among them, sorted."""
    return sorted(set(values) | {default})


def white_references(release: Path, capture: Path, action: str, session: str) -> dict[str, np.ndarray]:
    """camera_id -> white_reference (3,): the decode stage's calibrated cameras in the release's work store
    (what the materials stage used, through the artifact facade), else the capture's rig.json."""
    from artifacts.facade import ActionArtifacts

    work = release.parent / f"{release.name}.work" / "artifacts"
    decoded = ActionArtifacts.from_store(work, action, session, ("decode",)) if work.is_dir() else None
    if decoded is not None and decoded.has("cameras"):
        records = decoded.camera_records().values()
    else:
        records = json.loads((capture / "sessions" / session / "rig.json").read_text())["cameras"]
    return {c["camera_id"]: np.asarray(c["white_reference"], np.float32) for c in records}


def load_action(release: Path, capture: Path, action: str, cfg: MaterialsConfig) -> dict:
    """The release's inputs of the materials stage for one action, read through the artifact facade as the stage
    reads them (:func:`stages.materials.load_bake_views`): the welded textured mesh and its atlas, the baked
    albedo texture and one BakeView per camera (full_on | pos | neg stacked, valid = alpha above
    ``cfg.min_alpha`` inside the mask), with the cameras' white references (:func:`white_references`)."""
    from manifests import release_artifacts
    from stages.materials import load_bake_views

    artifacts = release_artifacts(release, action)
    view = artifacts.backend.view
    session = view.info.get("session_id") or "S000"
    white = white_references(release, capture, action, session)
    vertices, faces, atlas = artifacts.atlas_mesh()
    views, cameras = load_bake_views(artifacts, cfg.min_alpha)
    textures = {"albedo": artifacts.texture("albedo_texture"), "roughness": artifacts.texture("roughness_texture", 1)}
    for name in ("albedo_deoccluded", "albedo_intrinsic"):
        if artifacts.has(f"{name}_texture"):
            textures[name] = artifacts.texture(f"{name}_texture")
    if artifacts.has("occlusion_texture"):
        textures["occlusion"] = artifacts.texture("occlusion_texture", 1)
    return {"view": view, "vertices": vertices, "faces": faces, "atlas": atlas, "views": views,
            "white": np.stack([white[cam.camera_id] for cam in cameras]), "released": textures,
            "obj": artifacts.existing("textured_mesh"), "session": session}


class TruthProbe:
    """Every true camera's view of the textured mesh (UVs of the pixels where the truth has the subject
    and the mesh is hit) with the truth there: scores any texture of the atlas like evaluate does."""

    def __init__(self, data: dict, truth_dir: Path, action: str):
        from pipeline.codecs.exr import read_exr
        from pipeline.codecs.image import read_png
        from evaluation.release import true_cameras
        from stages.numerics.raycast import mesh_scene, render_uvs

        scene = mesh_scene(data["vertices"], data["faces"])
        atlas = data["atlas"]
        uvs, rough, albedo, visibility = [], [], [], []
        for cam_id, cam in sorted(true_cameras(truth_dir, data["session"]).items()):
            base = truth_dir / action
            if not (base / "roughness" / f"{cam_id}.exr").exists():
                continue
            true_rough = read_exr(base / "roughness" / f"{cam_id}.exr")
            true_rough = true_rough[..., 0] if true_rough.ndim == 3 else true_rough
            mask = read_png(base / "mask" / f"{cam_id}.png")
            mask = (mask[..., 0] if mask.ndim == 3 else mask) > 127
            h, w = true_rough.shape
            uv, hit = render_uvs(scene, atlas.faces, atlas.uvs, np.asarray(cam["K"]),
                                 np.asarray(cam["cam_from_world"])[:3], h, w)
            both = hit & mask
            vis = read_exr(base / "visibility" / f"{cam_id}.exr")
            vis = vis[..., 0] if vis.ndim == 3 else vis
            uvs.append(uv[both])
            rough.append(true_rough[both])
            albedo.append(read_exr(base / "albedo" / f"{cam_id}.exr")[..., :3][both])
            visibility.append(vis[both])
        if not uvs:
            raise FileNotFoundError(f"{truth_dir / action}: no true roughness maps")
        self.uv = np.concatenate(uvs)
        self.roughness = np.concatenate(rough).astype(np.float64)
        self.albedo = np.concatenate(albedo).astype(np.float64)
        self.visibility = np.concatenate(visibility).astype(np.float64)
        self.cameras = len(uvs)

    def roughness_errors(self, texture: np.ndarray | float) -> dict[str, float]:
        from stages.numerics.bake import sample_texture

        seen = (np.full(len(self.uv), float(texture)) if np.isscalar(texture)
                else sample_texture(texture, self.uv).astype(np.float64))
        diff = seen - self.roughness
        return {"mae": float(np.mean(np.abs(diff))), "bias": float(np.mean(diff))}

    def by_level(self, texture: np.ndarray) -> list[dict[str, float]]:
        """Per true roughness level (rounded to 0.01, those on more than 1% of the pixels): its share of the
        pixels, the texture's mean there and its MAE there."""
        from stages.numerics.bake import sample_texture

        seen = sample_texture(texture, self.uv).astype(np.float64)
        levels = np.round(self.roughness, 2)
        return [{"true_roughness": float(v), "share": round(float(np.mean(levels == v)), 4),
                 "pred_mean": round(float(seen[levels == v].mean()), 4),
                 "mae": round(float(np.abs(seen[levels == v] - self.roughness[levels == v]).mean()), 4)}
                for v in np.unique(levels) if np.mean(levels == v) > 0.01]

    def albedo_gain(self, texture: np.ndarray) -> float:
        """Median ratio of the texture's albedo (channel mean) to the truth's, where the truth is > 0.05."""
        from stages.numerics.bake import sample_texture

        seen = sample_texture(texture, self.uv).astype(np.float64).mean(axis=1)
        truth = self.albedo.mean(axis=1)
        keep = truth > 0.05
        return float(np.median(seen[keep] / truth[keep])) if keep.any() else 1.0

    def albedo_psnr(self, texture: np.ndarray, divide_by_truth_visibility: float | None = None) -> float:
        from stages.numerics.bake import sample_texture

        seen = sample_texture(texture, self.uv).astype(np.float64)
        if divide_by_truth_visibility is not None:
            seen = seen / np.maximum(self.visibility, divide_by_truth_visibility)[:, None]
        mse = float(np.mean((np.clip(seen, 0, 1) - self.albedo) ** 2))
        return float(10 * np.log10(1.0 / max(mse, 1e-12)))


def roughness_section(data: dict, probe: TruthProbe, base: MaterialsConfig, progress) -> dict:
    """Per-texel fits for every variant (:func:`variant_configs`), smoothed and scored; times of the gather,
    fits and medians. Observations are gathered once, for the most views and the most grazing limit any variant
    uses."""
    from stages.numerics.material_textures import (albedo_without_occlusion, fit_texel_materials, mirror_cone_open,
                                                   published_roughness, texel_samples, texel_texture)
    from stages.numerics.materials import NO_VIEWS_RESIDUAL
    from stages.numerics.raycast import mesh_scene
    from stages.numerics.shadowing import ambient_occlusion

    variants = variant_configs(base)
    max_k = max(cfg.max_views for _, cfg in variants)
    # gathered once at the most grazing limit any variant has; each fit keeps the views within its own
    lowest_cos = min(cfg.min_cos for _, cfg in variants)
    t0 = time.perf_counter()
    texels = texel_samples(data["vertices"], data["faces"], data["atlas"], data["released"]["albedo"], data["views"],
                           dataclasses.replace(base, max_views=max_k, min_cos=lowest_cos))
    covered, points, normals, albedo, obs = (texels[k] for k in ("covered", "points", "normals", "albedo", "obs"))
    gather_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    visibility = ambient_occlusion(points, normals, mesh_scene(data["vertices"], data["faces"]),
                                   rays=base.occlusion_rays)
    visibility_s = time.perf_counter() - t0
    out = {"texels": int(len(points)), "gathered_views": max_k, "gather_s": round(gather_s, 2),
           "texel_visibility_s": round(visibility_s, 2),
           "mean_valid_views": round(float(obs["valid"].sum(axis=1).mean()), 2), "variants": [], "neighbours": [],
           "albedo_guide": []}

    scene = mesh_scene(data["vertices"], data["faces"])
    mirror_open: dict[float, np.ndarray] = {}  # cone half-angle -> (P, K) the stage's mirror-cone test

    def fit(cfg: MaterialsConfig, rows: slice = slice(None)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The stage's fit of the texels ``rows`` on the first ``cfg.max_views`` gathered views (best first) whose
        cosine to the texel reaches ``cfg.min_cos`` and whose mirror cone is open (``cfg.specular_cone_deg``):
        roughness, residual and the diffuse ratio (:func:`fit_texel_materials`, as the stage: its second fit on the
        first ``cfg.albedo_max_views`` of those views within ``cfg.min_cos``)."""
        k = cfg.max_views
        observed = obs["values"]["obs"][rows, :k]
        observed = observed.reshape(len(observed), -1, 3, 3)  # fewer than k when fewer cameras see the mesh
        white = data["white"][np.maximum(obs["view_index"][rows, :k], 0)]
        within = obs["valid"][rows, :k] & (obs["cos"][rows, :k] >= max(cfg.min_cos, 1e-3))
        valid = within
        if cfg.specular_cone_deg > 0:
            if cfg.specular_cone_deg not in mirror_open:
                mirror_open[cfg.specular_cone_deg] = mirror_cone_open(points, normals, obs["view_dirs"], obs["valid"],
                                                                      scene, cfg.specular_cone_deg)
            valid = within & mirror_open[cfg.specular_cone_deg][rows, :k]
        rough, rms, ratio, _ = fit_texel_materials(observed, obs["view_dirs"][rows, :k], within, valid,
                                                   normals[rows], albedo[rows], white, cfg)
        return rough, rms, ratio

    def intrinsic_psnr(ratio: np.ndarray) -> float | None:
        """PSNR of the intrinsic albedo texture the stage would write with this diffuse ratio (the released
        occlusion texture divided out), or None without one."""
        if "occlusion" not in data["released"]:
            return None
        intrinsic = albedo_without_occlusion(data["released"]["albedo"], data["released"]["occlusion"],
                                             base.min_occlusion, texel_texture(ratio, covered, fill=1.0))
        return round(probe.albedo_psnr(intrinsic), 3)

    # Warm up: the first fit of a process builds the specular moment tables (about a second); not timed.
    for _, cfg in variants:
        fit(cfg, slice(0, 64))
    default_fit = None
    for label, cfg in variants:
        t0 = time.perf_counter()
        rough, rms, ratio = fit(cfg)
        fit_s = time.perf_counter() - t0
        fitted = rms != NO_VIEWS_RESIDUAL
        t0 = time.perf_counter()
        smooth, _ = published_roughness(points, rough, fitted, visibility, cfg, albedo)
        median_s = time.perf_counter() - t0
        score = probe.roughness_errors(texel_texture(smooth, covered))
        raw = probe.roughness_errors(texel_texture(rough, covered))
        settings = {name: getattr(cfg, name) for name in ("specular_model", "fit_albedo", "max_views",
                                                          "median_neighbours", "median_min_visibility", "min_cos",
                                                          "specular_cone_deg", "albedo_max_views")}
        out["variants"].append({"variant": label, **settings, "fit_s": round(fit_s, 2),
                                "x_gather": round(fit_s / max(gather_s, 1e-9), 2),
                                "median_s": round(median_s, 2),
                                "mae": round(score["mae"], 4), "bias": round(score["bias"], 4),
                                "mae_unsmoothed": round(raw["mae"], 4),
                                "intrinsic_albedo_psnr_db": intrinsic_psnr(ratio),
                                "fit_rms_median": round(float(np.median(rms[fitted])), 5) if fitted.any() else 0.0,
                                "by_true_level": probe.by_level(texel_texture(smooth, covered))})
        progress(f"  {label}: MAE {score['mae']:.4f} bias {score['bias']:+.4f} fit {fit_s:.1f} s")
        if cfg == base:
            default_fit = (rough, fitted)
    rough, fitted = default_fit
    for neighbours in sweep(MEDIAN_NEIGHBOURS_SWEEP, base.median_neighbours):
        t0 = time.perf_counter()
        smooth, _ = published_roughness(points, rough, fitted, visibility,
                                        dataclasses.replace(base, median_neighbours=neighbours), albedo)
        median_s = time.perf_counter() - t0
        score = probe.roughness_errors(texel_texture(smooth, covered))
        out["neighbours"].append({"median_neighbours": neighbours, "median_s": round(median_s, 2),
                                  "mae": round(score["mae"], 4), "bias": round(score["bias"], 4)})
    for guide_m, guide_neighbours in sorted(set(ALBEDO_GUIDE_SWEEP) | {(base.median_albedo_m,
                                                                        base.median_albedo_neighbours)}):
        cfg = dataclasses.replace(base, median_albedo_m=guide_m, median_albedo_neighbours=guide_neighbours)
        t0 = time.perf_counter()
        smooth, _ = published_roughness(points, rough, fitted, visibility, cfg, albedo)
        median_s = time.perf_counter() - t0
        texture = texel_texture(smooth, covered)
        score = probe.roughness_errors(texture)
        out["albedo_guide"].append({"median_albedo_m": guide_m, "median_albedo_neighbours": guide_neighbours,
                                    "median_s": round(median_s, 2), "mae": round(score["mae"], 4),
                                    "bias": round(score["bias"], 4), "by_true_level": probe.by_level(texture)})
    median_fit = float(np.median(rough[fitted])) if fitted.any() else 0.5
    truth_mean = float(np.mean(probe.roughness))
    truth_median = float(np.median(probe.roughness))
    out["baselines"] = {name: {"value": round(value, 4)} | _round(probe.roughness_errors(value))
                        for name, value in (("constant_median_of_fits", median_fit),
                                            ("constant_truth_mean_oracle", truth_mean),
                                            ("constant_truth_median_oracle", truth_median))}
    out["baselines"]["released_texture"] = _round(probe.roughness_errors(data["released"]["roughness"]))
    out["default_by_true_level"] = probe.by_level(
        texel_texture(published_roughness(points, rough, fitted, visibility, base, albedo)[0], covered))
    return out


def albedo_section(data: dict, probe: TruthProbe, base: MaterialsConfig, threads: int, progress) -> dict:
    """Baked vs de-occluded albedo (the stage's occlusion at several ray counts and floors) vs the truth."""
    from stages.numerics.material_textures import albedo_without_occlusion, texel_texture
    from stages.numerics.bake import rasterize_atlas
    from stages.numerics.raycast import mesh_scene
    from stages.numerics.shadowing import ambient_occlusion

    floors = sweep(MIN_OCCLUSION_SWEEP, base.min_occlusion)
    baked = data["released"]["albedo"]
    out = {"baked_psnr_db": round(probe.albedo_psnr(baked), 3), "baked_gain": round(probe.albedo_gain(baked), 4),
           "occlusion_size": base.occlusion_size, "default_min_occlusion": base.min_occlusion, "occlusion": [],
           "baked_over_truth_visibility_psnr_db": {str(f): round(probe.albedo_psnr(baked, f), 3) for f in floors}}
    if "albedo_deoccluded" in data["released"]:
        out["released_deoccluded_psnr_db"] = round(probe.albedo_psnr(data["released"]["albedo_deoccluded"]), 3)
        out["released_deoccluded_gain"] = round(probe.albedo_gain(data["released"]["albedo_deoccluded"]), 4)
    if "albedo_intrinsic" in data["released"]:
        out["released_intrinsic_psnr_db"] = round(probe.albedo_psnr(data["released"]["albedo_intrinsic"]), 3)
        out["released_intrinsic_gain"] = round(probe.albedo_gain(data["released"]["albedo_intrinsic"]), 4)
    t0 = time.perf_counter()
    raster = rasterize_atlas(data["vertices"], data["faces"], data["atlas"], int(base.occlusion_size))
    covered = raster["covered"]
    points = raster["position"][covered].astype(np.float64)
    normals = raster["normal"][covered].astype(np.float64)
    scene = mesh_scene(data["vertices"], data["faces"])
    out["raster_s"] = round(time.perf_counter() - t0, 2)
    for rays in sweep(OCCLUSION_RAYS_SWEEP, base.occlusion_rays):
        t0 = time.perf_counter()
        visible = ambient_occlusion(points, normals, scene, rays=rays, threads=threads)
        occ_s = time.perf_counter() - t0
        occlusion = texel_texture(visible, covered, fill=1.0)
        row = {"occlusion_rays": rays, "occlusion_s": round(occ_s, 2), "mean_visible": round(float(visible.mean()), 4)}
        for floor in floors:
            deoccluded = albedo_without_occlusion(baked, occlusion, floor)
            row[f"psnr_db_min_occlusion_{floor}"] = round(probe.albedo_psnr(deoccluded), 3)
            if floor == base.min_occlusion:
                row["gain_default_min_occlusion"] = round(probe.albedo_gain(deoccluded), 4)
        out["occlusion"].append(row)
        progress(f"  occlusion {rays} rays: {occ_s:.1f} s, PSNR at floor {base.min_occlusion:g} "
                 f"{row[f'psnr_db_min_occlusion_{base.min_occlusion}']:.2f} dB")
    return out


def _round(d: dict, digits: int = 4) -> dict:
    return {k: round(float(v), digits) for k, v in d.items()}


def markdown(report: dict) -> str:
    lines = ["# bench_materials", "", f"torch threads {report['threads']}; texture {report['texture_size']}; "
             "roughness MAE / bias against the simulator over every true camera's view of the textured mesh; "
             "every other setting the materials stage's default (``defaults``).", ""]
    for action, entry in report["actions"].items():
        r = entry["roughness"]
        lines += [f"## {action} ({r['texels']} texels, {r['mean_valid_views']} valid views each of "
                  f"{r['gathered_views']}, gather {r['gather_s']} s, {entry['true_cameras']} true cameras)", "",
                  "| roughness variant | MAE | bias | MAE per texel (no median) | intrinsic albedo dB | fit s | "
                  "x gather | median s |",
                  "|---|---|---|---|---|---|---|---|"]
        for v in r["variants"]:
            psnr = v.get("intrinsic_albedo_psnr_db")
            lines.append(f"| {v['variant']} | {v['mae']:.4f} | {v['bias']:+.4f} | {v['mae_unsmoothed']:.4f} | "
                         f"{'-' if psnr is None else f'{psnr:.2f}'} | "
                         f"{v['fit_s']:.1f} | {v['x_gather']:.1f} | {v['median_s']:.2f} |")
        for n in r["neighbours"]:
            lines.append(f"| default, median_neighbours {n['median_neighbours']} | {n['mae']:.4f} | {n['bias']:+.4f} "
                         f"| | | | | {n['median_s']:.2f} |")
        for g in r.get("albedo_guide", []):
            lines.append(f"| default, median_albedo_m {g['median_albedo_m']:g}, median_albedo_neighbours "
                         f"{g['median_albedo_neighbours']} | {g['mae']:.4f} | {g['bias']:+.4f} | | | | | "
                         f"{g['median_s']:.2f} |")
        for name, b in r["baselines"].items():
            value = f" = {b['value']:.3f}" if "value" in b else ""
            lines.append(f"| baseline: {name}{value} | {b['mae']:.4f} | {b['bias']:+.4f} | | 0 | | |")
        lines += ["", "| true roughness | share of pixels | fitted mean | MAE |", "|---|---|---|---|"]
        lines += [f"| {x['true_roughness']:.2f} | {x['share']:.3f} | {x['pred_mean']:.3f} | {x['mae']:.3f} |"
                  for x in r["default_by_true_level"]]
        true_levels = [x["true_roughness"] for x in r["default_by_true_level"]]
        lines += ["", "The fitted mean per true roughness, per variant:", "",
                  "| roughness variant | " + " | ".join(f"{v:.2f}" for v in true_levels) + " |",
                  "|---|" + "---|" * len(true_levels)]
        guided = [(f"default, median_albedo_m {g['median_albedo_m']:g}, median_albedo_neighbours "
                   f"{g['median_albedo_neighbours']}", g) for g in r.get("albedo_guide", [])]
        for label, v in [(v["variant"], v) for v in r["variants"]] + guided:
            means = {x["true_roughness"]: x["pred_mean"] for x in v.get("by_true_level", [])}
            lines.append(f"| {label} | " + " | ".join(f"{means[t]:.3f}" if t in means else "-"
                                                      for t in true_levels) + " |")
        a = entry["albedo"]
        floors = [float(f) for f in a["baked_over_truth_visibility_psnr_db"]]
        lines += ["", f"Albedo PSNR vs truth: baked (white-light) texture **{a['baked_psnr_db']:.2f} dB** (median "
                  f"ratio to the truth {a['baked_gain']:.3f})"
                  + (f", released de-occluded {a['released_deoccluded_psnr_db']:.2f} dB (ratio "
                     f"{a['released_deoccluded_gain']:.3f})" if "released_deoccluded_psnr_db" in a else "")
                  + (f", released intrinsic {a['released_intrinsic_psnr_db']:.2f} dB (ratio "
                     f"{a['released_intrinsic_gain']:.3f})" if "released_intrinsic_psnr_db" in a else "")
                  + "; baked / the simulator's per-pixel visibility, floors "
                  + ", ".join(f"{k}: {v:.2f}" for k, v in a["baked_over_truth_visibility_psnr_db"].items())
                  + " dB.", "",
                  "| occlusion rays | AO s | mean visible | "
                  + " | ".join(f"PSNR floor {f}" for f in floors) + " |",
                  "|---" * (3 + len(floors)) + "|"]
        for o in a["occlusion"]:
            lines.append(f"| {o['occlusion_rays']} | {o['occlusion_s']:.1f} | {o['mean_visible']:.3f} | "
                         + " | ".join(f"{o[f'psnr_db_min_occlusion_{f}']:.2f}" for f in floors) + " |")
        lines.append("")
    return "\n".join(lines)


def figure(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), dpi=100)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (action, entry) in enumerate(report["actions"].items()):
        c = colours[i % len(colours)]
        r = entry["roughness"]
        for v in r["variants"]:
            axes[0].scatter(v["fit_s"], v["mae"], color=c)
            axes[0].annotate(v["variant"].split(" (")[0], (v["fit_s"], v["mae"]), fontsize=7)
        base = r["variants"][0]["fit_s"]
        axes[0].plot([base] * len(r["neighbours"]), [n["mae"] for n in r["neighbours"]], "+", color=c)
        axes[0].axhline(r["baselines"]["constant_median_of_fits"]["mae"], color=c, ls="--", lw=1,
                        label=f"{action}: constant = median of fits")
        axes[0].axhline(r["baselines"]["constant_truth_median_oracle"]["mae"], color=c, ls=":", lw=1,
                        label=f"{action}: constant = truth median (oracle)")
        a = entry["albedo"]
        floors = [float(f) for f in a["baked_over_truth_visibility_psnr_db"]]
        for floor, marker in zip(floors, "os^v<>"):
            axes[1].plot([o["occlusion_s"] for o in a["occlusion"]],
                         [o[f"psnr_db_min_occlusion_{floor}"] for o in a["occlusion"]], marker=marker, color=c,
                         label=f"{action} de-occluded, floor {floor}")
        axes[1].axhline(a["baked_psnr_db"], color=c, ls="--", lw=1, label=f"{action} baked")
    axes[0].set_xlabel("fit seconds (fit_roughness)")
    axes[0].set_ylabel("roughness MAE vs truth")
    axes[0].set_title("roughness: variants (dots), median_neighbours sweep (+)")
    axes[0].legend(fontsize=7)
    axes[1].set_xlabel("ambient occlusion seconds (16 / 64 / 128 rays)")
    axes[1].set_ylabel("albedo PSNR vs truth (dB)")
    axes[1].set_title("albedo: baked vs de-occluded")
    axes[1].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> int:
    from _release import check_inputs, parse_release_args, release_parser

    args = parse_release_args(release_parser(__doc__, actions="", threads=2))
    release, capture, out = Path(args.release), Path(args.capture), Path(args.out)
    go_on, truth_dir = check_inputs("bench_materials", release, capture, need_truth=True)
    if not go_on:
        return 0
    from _threads import set_numeric_threads

    set_numeric_threads(args.threads)
    from manifests import open_release

    rel = open_release(release)
    actions = [a for a in (args.actions.split(",") if args.actions else rel.action_ids)
               if "texture_roughness" in rel.action(a).kinds and (truth_dir / a / "roughness").is_dir()]
    if not actions:
        print(f"bench_materials: no action of {release} has a roughness texture and ground truth; skipped")
        return 0
    out.mkdir(parents=True, exist_ok=True)
    base = default_config()
    if args.quick:  # a lower resolution: the texels are the inputs of the fits and of the occlusion
        base = dataclasses.replace(base, texture_size=64, occlusion_size=128)
    report = {"threads": args.threads, "quick": args.quick, "texture_size": base.texture_size,
              "defaults": dataclasses.asdict(base), "actions": {}}
    started = time.perf_counter()
    for action in actions:
        t0 = time.perf_counter()
        data = load_action(release, capture, action, base)
        probe = TruthProbe(data, truth_dir, action)
        print(f"{action}: loaded in {time.perf_counter() - t0:.1f} s ({probe.cameras} true cameras)", flush=True)
        entry = {"true_cameras": probe.cameras, "load_s": round(time.perf_counter() - t0, 2)}
        entry["roughness"] = roughness_section(data, probe, base, lambda m: print(m, flush=True))
        entry["albedo"] = albedo_section(data, probe, base, args.threads, lambda m: print(m, flush=True))
        report["actions"][action] = entry
    report["total_s"] = round(time.perf_counter() - started, 1)
    write_report(out, "bench_materials", report, markdown(report), lambda path: figure(report, path))
    print(f"total {report['total_s']} s; wrote {out / 'bench_materials.json'}, .md and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
