"""Relight stage: relit novel views against the simulator's subject under the same environments, with times.

For each action of a release (default A0000 and A0001), each novel camera of its ``renders/cameras.json``
and each of the stage's environments (``RelightConfig.environments``, from ../shared/data/hdri), the relight
stage's per-view steps run on the release's files, read through the artifact facade into the asset the stage
renders (:func:`stages.relightable.load_relightable_asset`), through the functions the stage calls
(``stages.numerics.novel_view`` ``novel_view_gbuffer``, ``silhouette_alpha``, ``premultiply_edges``, ``shading_albedo``;
``fit_sg_environment``, ``direction_visibility``, ``shade_sg`` / ``shade_sg_visible``) with the stage's
config (:func:`default_config`: sources, depth tolerance, fusion width, coverage samples, F0, SG fit height,
lobes, visibility directions; the heuristic source weights), and every variant's image is scored like
``ultrastage evaluate``
(``evaluation.release._relit_overall``): ``relit_psnr`` against ``synthetic.relight.TruthRelighter``'s
rendering of the true subject (common exposure from the truth's 99th percentile, union of the masks).

1. **Variants**, one change at a time from the stage's defaults (:func:`default_row`: its lobes, shadows with
   its visibility directions, its normals, the sources' ``albedo_diffuse`` when the release has it, de-occluded,
   silhouettes antialiased by the pixels' coverage): hard edges (``coverage_samples`` 1: alpha = the pixel
   centres' mask), ``sg_lobes`` 8/16/32/64 (with the SG fit time per environment), ``visibility_directions``
   64/128/256 (each sweep with the stage's default in it),
   shadows off (with the de-occluded and with the photometric albedo: the stage with ``shadows: false``
   shades the photometric albedo unshadowed), shadows with the photometric albedo (occlusion counted twice),
   ``normals`` reprojected, mesh, fused at 8 and 30 mm besides the stage's ``normal_fusion_m``, the
   white-light albedo as the sources (times the diffuse-ratio texture, as before ``albedo_diffuse``, and
   without it). The shading normals' mean angle to the simulator's is reported per kind. Time per view: the G-buffer
   (mesh depth, reprojection, atlas lookups; the sources' depth is rendered when the asset is loaded), the
   visibility and the shading under the 3 environments; ``x_baseline`` is that time over the simplest
   variant's (no shadows, photometric albedo) in the same process. The ``released`` row scores the
   release's own relit images (equal to the default row when the release used the defaults with
   ``shading.supersample`` 1: the rows shade one sample at each pixel's centre).
2. **Decomposition** on the pixels both the truth and our mask cover, at the true surface points with the
   true mesh's visibility (the stage's visibility directions), its lobe count and F0 (the simulator's skin has
   0.028, cloth 0.04):
   the true G-buffers (normal, albedo, roughness) shaded with SG = the shading model's floor (also without
   shadows); then our normal (also the reprojected one), our (de-occluded, and not de-occluded) albedo or our
   roughness swapped in one at a time, all three together, and our default render itself (our geometry,
   silhouette and visibility too).

``python bench/bench_relight.py --out DIR [--release DIR --capture DIR --actions A0000,A0001 --threads 2]``
writes DIR/bench_relight.json, DIR/bench_relight.md (tables) and DIR/bench_relight.png (PSNR against
seconds per view; PSNR and SG fit seconds against lobe count). Defaults runs/default/release and
runs/default/capture; without them, the ground truth or the maps it prints why and exits 0. ``--quick`` (the
tests' mode): the tiny run of ``bench/_quick.py``, the stage's first environment only, two points of each sweep
(:func:`sweeps`), the truth lit by 256 lights; the numbers are not measurements.
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _report import write_report  # noqa: E402

from stages.numerics.novel_view import HALF_MAX, scatter_pixels  # noqa: E402
from stages.numerics.sg import ROUGHNESS_MAX, ROUGHNESS_MIN  # noqa: E402
from stages.relight import RelightConfig  # noqa: E402


def default_config() -> RelightConfig:
    """The configuration of the bench's default row: the relight stage's own defaults."""
    return RelightConfig()


def default_row(cfg: RelightConfig) -> dict:
    """The shading choices of the stage with config ``cfg``, in the terms of the bench's variants."""
    shading = cfg.shading
    return {"lobes": cfg.sg_lobes, "shadows": shading.shadows, "directions": shading.visibility_directions,
            "normals": shading.normals,
            # the stage divides the ambient occlusion out of the albedo when it shades with shadows
            "albedo": "deoccluded" if shading.shadows else "photometric",
            "diffuse_ratio": True, "sources": "stage",
            "edges": "coverage" if shading.coverage_samples > 1 else "centre"}


def sweep(values: tuple, default) -> tuple:
    """A sweep's values with the stage's default among them, sorted."""
    return tuple(sorted(set(values) | {default}))


CONFIG = default_config()
DEFAULT = default_row(CONFIG)
LOBES_SWEEP = sweep((8, 16, 32, 64), CONFIG.sg_lobes)
DIRECTIONS_SWEEP = sweep((64, 128, 256), CONFIG.shading.visibility_directions)
FUSION_WIDTHS_M = (0.008, 0.03)  # frequency splits of the fused normals besides the stage's (normal_fusion_m)
BASELINE = "shadows off, photometric albedo (baseline)"
VARIANTS = ([("default", {})]
            + ([("hard edges (coverage_samples 1)", {"edges": "centre"})] if DEFAULT["edges"] == "coverage" else [])
            + [(f"sg_lobes {n}", {"lobes": n}) for n in LOBES_SWEEP if n != DEFAULT["lobes"]]
            + [(f"visibility_directions {n}", {"directions": n}) for n in DIRECTIONS_SWEEP
               if n != DEFAULT["directions"]]
            + [("shadows off, de-occluded albedo", {"shadows": False, "albedo": "deoccluded"}),
               (BASELINE, {"shadows": False, "albedo": "photometric"}),
               ("shadows on, photometric albedo", {"shadows": True, "albedo": "photometric"})]
            + [(f"normals {kind}", {"normals": kind}) for kind in ("reprojected", "mesh", "fused")
               if kind != DEFAULT["normals"]]
            + [(f"normals fused {width * 1000:g} mm", {"normals": f"fused_{width:g}"}) for width in FUSION_WIDTHS_M]
            + [("white-light sources x diffuse ratio", {"sources": "white"}),
               ("white-light sources, no diffuse ratio", {"sources": "white", "diffuse_ratio": False})])


class Sweeps(NamedTuple):
    """What one run of the bench covers: the lobe counts fitted, the visibility directions traced and the variants."""
    lobes: tuple
    directions: tuple
    variants: list


def sweeps(quick: bool = False) -> Sweeps:
    """Every sweep point and variant; ``quick``: the smallest point and the stage's default of each sweep, and the
    variants within them."""
    if not quick:
        return Sweeps(LOBES_SWEEP, DIRECTIONS_SWEEP, VARIANTS)
    lobes = sweep((min(LOBES_SWEEP),), CONFIG.sg_lobes)
    directions = sweep((min(DIRECTIONS_SWEEP),), CONFIG.shading.visibility_directions)
    return Sweeps(lobes, directions, [(label, change) for label, change in VARIANTS
                                      if (DEFAULT | change)["lobes"] in lobes
                                      and (DEFAULT | change)["directions"] in directions])


DECOMPOSITION = ("truth G-buffers (SG floor)", "truth G-buffers, no shadows", "truth + our normal",
                 "truth + our reprojected normal", "truth + our albedo", "truth + our albedo, not de-occluded",
                 "truth + our roughness",
                 "our normal+albedo+roughness",
                 "our default render")


def fit_environments(names: list[str], capture: Path, progress, lobes_sweep: tuple = LOBES_SWEEP
                     ) -> tuple[dict, list]:
    """(name -> {"env", lobes -> SGLobes}, rows of fit time and errors per environment and lobe count)."""
    from stages.numerics.sg import fit_sg_environment, sg_fit_errors
    from stages.environments import find_environment, load_environment

    fits, rows = {}, []
    for name in names:
        path = find_environment(name, capture)
        if path is None:
            progress(f"environment {name} not found; skipped")
            continue
        env, _ = load_environment(name, path)
        fits[name] = {"env": env}
        for count in lobes_sweep:
            t0 = time.perf_counter()
            lobes = fit_sg_environment(env, count, fit_height=CONFIG.fit_height)
            fit_s = time.perf_counter() - t0
            errors = sg_fit_errors(env, lobes)
            fits[name][count] = lobes
            rows.append({"environment": name, "lobes": count, "fit_s": round(fit_s, 2),
                         **{k: round(float(errors[k]), 4)
                            for k in ("irradiance_rel_l2", "map_rel_l2_64", "energy_rel")}})
            progress(f"  {name}: {count} lobes fitted in {fit_s:.1f} s, irradiance error "
                     f"{errors['irradiance_rel_l2']:.4f}")
    return fits, rows


class ActionScene:
    """What the relight stage renders one action from, read from the release through the artifact facade
    (:func:`manifests.release_artifacts`) by the stage's own loader
    (:func:`stages.relightable.load_relightable_asset` with the stage's ``min_alpha``, ``diffuse_normals`` and
    ``diffuse_albedo``): the mesh, the captured views as reprojection sources with their mesh depth, the atlas
    and its textures."""

    def __init__(self, release: Path, action: str):
        from manifests import release_artifacts
        from stages.relightable import load_relightable_asset

        self.artifacts = release_artifacts(release, action)
        self.view = self.artifacts.backend.view
        self.asset, _ = load_relightable_asset(self.artifacts, CONFIG.min_alpha, CONFIG.diffuse_normals,
                                               CONFIG.diffuse_albedo)
        self.scene = self.asset.scene
        self.diffuse_albedo = self.asset.sources_diffuse_albedo
        # the white-light albedo as the sources (x the diffuse-ratio texture): the stage with diffuse_albedo off
        self.asset_white = self.asset
        if self.diffuse_albedo:
            white, _ = load_relightable_asset(self.artifacts, CONFIG.min_alpha, CONFIG.diffuse_normals,
                                              diffuse_albedo=False)
            self.asset_white = dataclasses.replace(self.asset, sources=white.sources, sources_diffuse_albedo=False)

    def gbuffer(self, cam: dict) -> dict:
        """The stage's G-buffer of a novel camera (stages.numerics.novel_view.novel_view_gbuffer), with every normal
        choice and both source albedos, per mask pixel, and the full maps for the decomposition;
        ``stage_seconds`` times the stage's G-buffer alone (not the variants' extra work)."""
        from stages.numerics.gbuffer import shading_normals
        from stages.numerics.raycast import pixel_coverage
        from stages.numerics.novel_view import novel_view_gbuffer, silhouette_alpha

        h, w = int(cam["height"]), int(cam["width"])
        t0 = time.perf_counter()
        gb = novel_view_gbuffer(self.asset, cam["K"], cam["cam_from_world"], h, w, **CONFIG.shading.gbuffer_options())
        alpha, edge_mask = silhouette_alpha(gb["mask"], pixel_coverage(
            cam["K"], cam["cam_from_world"], h, w, CONFIG.shading.coverage_samples, self.asset.scene,
            centre_hit=gb["hit"]))
        stage_seconds = time.perf_counter() - t0
        white = gb if self.asset_white is self.asset else novel_view_gbuffer(
            self.asset_white, cam["K"], cam["cam_from_world"], h, w, **CONFIG.shading.gbuffer_options())
        pix = gb["pix"]
        full = {k: gb[f"normal_{k}"] for k in ("reprojected", "mesh", "fused")}
        for width in FUSION_WIDTHS_M:  # as the stage's fused normals, rim fade included: only the split differs
            full[f"fused_{width:g}"] = shading_normals(
                gb["normal_reprojected"], gb["normal_mesh"], gb["mask"],
                gb["normal_fusion_px"] * width / CONFIG.shading.normal_fusion_m, CONFIG.shading.rim_normal_px,
                CONFIG.shading.mesh_normal_weight)
        return {"mask": gb["mask"], "alpha": alpha, "edge_mask": edge_mask, "pix": pix, "points": gb["points"],
                "view_dirs": gb["view_dirs"], "shape": (h, w),
                "stage_seconds": stage_seconds,
                "normals": {k: n.reshape(-1, 3)[pix].astype(np.float64) for k, n in full.items()},
                "normals_full": full,
                "albedo": {"stage": gb["albedo"].reshape(-1, 3)[pix], "white": white["albedo"].reshape(-1, 3)[pix]},
                "diffuse_ratio": {"stage": gb["diffuse_ratio"].reshape(-1, 3)[pix],
                                  "white": white["diffuse_ratio"].reshape(-1, 3)[pix]},
                "occlusion": gb["occlusion"].reshape(-1)[pix],
                "roughness": np.clip(gb["roughness"].reshape(-1)[pix], ROUGHNESS_MIN, ROUGHNESS_MAX),
                "albedo_full": gb["albedo"], "diffuse_ratio_full": gb["diffuse_ratio"],
                "roughness_full": gb["roughness"], "occlusion_full": gb["occlusion"]}


def _image(pix: np.ndarray, values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) float32 image of the shaded pixels ``pix`` (P,): ``values`` (P, 3) made finite and clipped to
    [0, HALF_MAX] as :func:`stages.numerics.novel_view.relight_view` does, 0 elsewhere."""
    rgb = np.clip(np.nan_to_num(np.asarray(values, np.float32), nan=0.0, posinf=0.0, neginf=0.0), 0.0, HALF_MAX)
    return scatter_pixels(pix, rgb, shape[0], shape[1])


def shade(normals, view_dirs, albedo, roughness, lobes, visibility=None, directions=None) -> np.ndarray:
    from stages.numerics.sg import shade_sg
    from stages.numerics.shadowing import shade_sg_visible

    if visibility is None:
        return shade_sg(normals, view_dirs, albedo, roughness, lobes, f0=CONFIG.shading.f0)["rgb"]
    return shade_sg_visible(normals, view_dirs, albedo, roughness, lobes, visibility, directions,
                            f0=CONFIG.shading.f0)["rgb"]


def bench_view(scene: ActionScene, truth, true_scene, cam: dict, fits: dict, threads: int, progress,
               plan: Sweeps | None = None) -> dict:
    """Every variant and the decomposition for one novel camera under every environment."""
    from stages.numerics.metrics import angular_error_deg, relit_psnr
    from stages.numerics.raycast import camera_rays
    from stages.numerics.sg import fibonacci_sphere
    from stages.numerics.shadowing import direction_visibility
    from stages.numerics.novel_view import premultiply_edges, shading_albedo

    plan = plan or sweeps()
    gb = scene.gbuffer(cam)
    gbuffer_s = gb["stage_seconds"]
    directions = {d: fibonacci_sphere(d) for d in plan.directions}
    visibility, vis_s = {}, {}
    for normals_kind in gb["normals"]:
        for d in (plan.directions if normals_kind == DEFAULT["normals"] else (DEFAULT["directions"],)):
            t0 = time.perf_counter()
            visibility[(normals_kind, d)] = direction_visibility(gb["points"], gb["normals"][normals_kind],
                                                                 scene.scene, directions[d], threads=threads)
            vis_s[(normals_kind, d)] = time.perf_counter() - t0
    K, pose = np.asarray(cam["K"], np.float64), np.asarray(cam["cam_from_world"], np.float64)
    h, w = gb["shape"]
    albedos = {(kind, ratio, src): shading_albedo(gb["albedo"][src], gb["diffuse_ratio"][src] if ratio else 1.0,
                                                  gb["occlusion"] if kind == "deoccluded" else None)
               for kind in ("deoccluded", "photometric") for ratio in (True, False) for src in ("stage", "white")}

    rows = {label: {"psnr_db": {}, "shade_s": {}} for label, _ in plan.variants}
    rows["released"] = {"psnr_db": {}}
    decomposition = {label: {} for label in DECOMPOSITION}
    default_images = {}
    true_geometry = None
    for env_name, fit in fits.items():
        t0 = time.perf_counter()
        true = truth.render(K, pose, h, w, fit["env"])
        truth_s = time.perf_counter() - t0
        for label, change in plan.variants:
            cfg = DEFAULT | change
            vis = visibility[(cfg["normals"], cfg["directions"])] if cfg["shadows"] else None
            t0 = time.perf_counter()
            albedo = albedos[(cfg["albedo"], cfg["diffuse_ratio"], cfg["sources"])]
            rgb = shade(gb["normals"][cfg["normals"]], gb["view_dirs"], albedo,
                        gb["roughness"],
                        fit[cfg["lobes"]], vis, directions[cfg["directions"]] if vis is not None else None)
            rows[label]["shade_s"][env_name] = time.perf_counter() - t0
            image = _image(gb["pix"], rgb, (h, w))
            if cfg["edges"] == "coverage":  # the stage's antialiased silhouette (coverage_samples)
                image, mask = premultiply_edges(image, gb["mask"], gb["alpha"]), gb["edge_mask"]
            else:
                mask = gb["mask"]
            rows[label]["psnr_db"][env_name] = relit_psnr(image, mask, true["radiance"], true["mask"])["psnr_db"]
            if not change:
                default_images[env_name] = image
        try:
            released = scene.view.relit(cam["camera_id"], env_name)
            rows["released"]["psnr_db"][env_name] = relit_psnr(released[..., :3], released[..., 3] >= 0.5,
                                                               true["radiance"], true["mask"])["psnr_db"]
        except (KeyError, FileNotFoundError):
            pass

        # Decomposition: the true surface points and visibility, G-buffers swapped one at a time.
        both = true["mask"] & gb["mask"]
        bp = np.flatnonzero(both.reshape(-1))
        if true_geometry is None:
            centre = -pose[:, :3].T @ pose[:, 3]
            origins, rays, z_per_t = camera_rays(K, pose, h, w)  # the truth's depth is camera z, not ray length
            points = (origins + rays * (true["depth_m"].reshape(-1).astype(np.float64) / z_per_t)[:, None])[bp]
            view_dirs = centre[None] - points
            view_dirs /= np.maximum(np.linalg.norm(view_dirs, axis=1, keepdims=True), 1e-12)
            true_normals = true["normals_world"].reshape(-1, 3)[bp].astype(np.float64)
            true_vis = direction_visibility(points, true_normals, true_scene, directions[DEFAULT["directions"]],
                                            threads=threads)
            ours = {"normal": gb["normals_full"][DEFAULT["normals"]].reshape(-1, 3)[bp].astype(np.float64),
                    "reprojected normal": gb["normals_full"]["reprojected"].reshape(-1, 3)[bp].astype(np.float64),
                    "albedo": shading_albedo(gb["albedo_full"].reshape(-1, 3)[bp],
                                             gb["diffuse_ratio_full"].reshape(-1, 3)[bp],
                                             gb["occlusion_full"].reshape(-1)[bp]),
                    "albedo_occluded": shading_albedo(gb["albedo_full"].reshape(-1, 3)[bp],
                                                      gb["diffuse_ratio_full"].reshape(-1, 3)[bp], None),
                    "roughness": np.clip(gb["roughness_full"].reshape(-1)[bp], ROUGHNESS_MIN, ROUGHNESS_MAX)}
            true_geometry = (points, view_dirs, true_normals, true_vis, ours)
            normal_error = {kind: float(np.mean(angular_error_deg(n.reshape(-1, 3)[bp], true_normals)))
                            for kind, n in gb["normals_full"].items()}
        points, view_dirs, true_normals, true_vis, ours = true_geometry
        t_buf = {"normal": true_normals, "albedo": true["albedo"].reshape(-1, 3)[bp],
                 "roughness": np.clip(true["roughness"].reshape(-1)[bp], ROUGHNESS_MIN, ROUGHNESS_MAX)}
        target = true["radiance"] * both[..., None]
        lobes = fit[DEFAULT["lobes"]]

        def score(buffers: dict, shadows: bool = True) -> float:
            rgb = shade(buffers["normal"], view_dirs, buffers["albedo"], buffers["roughness"], lobes,
                        true_vis if shadows else None, directions[DEFAULT["directions"]] if shadows else None)
            return relit_psnr(_image(bp, rgb, (h, w)), both, target, both)["psnr_db"]

        decomposition["truth G-buffers (SG floor)"][env_name] = score(t_buf)
        decomposition["truth G-buffers, no shadows"][env_name] = score(t_buf, shadows=False)
        for name in ("normal", "albedo", "roughness"):
            decomposition[f"truth + our {name}"][env_name] = score(t_buf | {name: ours[name]})
        decomposition["truth + our reprojected normal"][env_name] = score(t_buf | {"normal": ours["reprojected normal"]})
        decomposition["truth + our albedo, not de-occluded"][env_name] = score(t_buf | {"albedo": ours["albedo_occluded"]})
        decomposition["our normal+albedo+roughness"][env_name] = score({k: ours[k] for k in t_buf})
        decomposition["our default render"][env_name] = relit_psnr(default_images[env_name] * both[..., None], both,
                                                                   target, both)["psnr_db"]
        rows["released"].setdefault("truth_render_s", {})[env_name] = truth_s
    variants = {}
    for label, change in plan.variants:
        cfg = DEFAULT | change
        vis_time = vis_s[(cfg["normals"], cfg["directions"])] if cfg["shadows"] else 0.0
        seconds = gbuffer_s + vis_time + sum(rows[label]["shade_s"].values())
        variants[label] = {"psnr_db": rows[label]["psnr_db"], "seconds_per_view": seconds,
                           "visibility_s": vis_time, "shade_s": rows[label]["shade_s"]}
    variants["released"] = {"psnr_db": rows["released"]["psnr_db"]}
    progress(f"  {cam['camera_id']}: {len(gb['pix'])} pixels, G-buffer {gbuffer_s:.1f} s, default "
             + ", ".join(f"{e[:12]} {v:.2f}" for e, v in rows["default"]["psnr_db"].items()) + " dB; floor "
             + ", ".join(f"{v:.2f}" for v in decomposition["truth G-buffers (SG floor)"].values()))
    return {"camera_id": cam["camera_id"], "pixels": int(len(gb["pix"])), "gbuffer_s": gbuffer_s,
            "normal_error_deg": normal_error,
            "visibility_s": {f"{k[0]}_{k[1]}": v for k, v in vis_s.items()}, "variants": variants,
            "decomposition": decomposition}


def summarise(report: dict, plan: Sweeps | None = None) -> dict:
    """Means over actions, views and environments (and per environment) of every variant and decomposition
    row; seconds per view averaged over views."""
    plan = plan or sweeps()
    views = [v for a in report["actions"].values() for v in a["views"]]
    envs = list(report["environments"])
    out = {"variants": {}, "decomposition": {}}
    base_s = np.mean([v["variants"][BASELINE]["seconds_per_view"] for v in views])
    for label in [lab for lab, _ in plan.variants] + ["released"]:
        per_env = {e: float(np.mean([v["variants"][label]["psnr_db"][e] for v in views
                                     if e in v["variants"][label]["psnr_db"]])) for e in envs
                   if any(e in v["variants"][label]["psnr_db"] for v in views)}
        if not per_env:
            continue
        row = {"psnr_db": round(float(np.mean(list(per_env.values()))), 3),
               "per_environment": {e: round(x, 3) for e, x in per_env.items()},
               "per_action": {a: round(float(np.mean([x for v in e["views"]
                                                       for x in v["variants"][label]["psnr_db"].values()])), 3)
                              for a, e in report["actions"].items()}}
        if label != "released":
            seconds = float(np.mean([v["variants"][label]["seconds_per_view"] for v in views]))
            row |= {"seconds_per_view": round(seconds, 2), "x_baseline": round(seconds / base_s, 2),
                    "shade_s_per_environment": round(float(np.mean([s for v in views for s in
                                                                     v["variants"][label]["shade_s"].values()])), 3)}
        out["variants"][label] = row
    for label in DECOMPOSITION:
        per_env = {e: float(np.mean([v["decomposition"][label][e] for v in views])) for e in envs}
        out["decomposition"][label] = {"psnr_db": round(float(np.mean(list(per_env.values()))), 3),
                                       "per_environment": {e: round(x, 3) for e, x in per_env.items()}}
    out["normal_error_deg"] = {kind: round(float(np.mean([v["normal_error_deg"][kind] for v in views])), 3)
                               for kind in views[0]["normal_error_deg"]}
    lobes_psnr = {}
    for count in plan.lobes:
        label = "default" if count == DEFAULT["lobes"] else f"sg_lobes {count}"
        lobes_psnr[str(count)] = out["variants"][label]["per_environment"]
    out["psnr_by_lobes"] = lobes_psnr
    return out


def markdown(report: dict) -> str:
    s = report["summary"]
    envs = list(report["environments"])
    short = [e.split("_1k")[0] for e in envs]
    lines = ["# bench_relight", "",
             f"{len(report['actions'])} action(s) x {report['views_per_action']} novel views x {len(envs)} "
             f"environments; threads {report['threads']}. relit PSNR (dB) against the simulator (evaluate's "
             "relit_psnr); seconds per view = G-buffer + visibility + shading under all environments (SG fits "
             "excluded).", "",
             "| variant | PSNR | " + " | ".join(short) + " | s / view | x baseline | shade s / env |",
             "|---" * (5 + len(envs)) + "|"]
    for label, row in s["variants"].items():
        cells = " | ".join(f"{row['per_environment'].get(e, float('nan')):.2f}" for e in envs)
        extra = (f"{row['seconds_per_view']:.2f} | {row['x_baseline']:.2f} | {row['shade_s_per_environment']:.2f}"
                 if "seconds_per_view" in row else " | | ")
        lines.append(f"| {label} | {row['psnr_db']:.2f} | {cells} | {extra} |")
    shading = {a: e.get("released_shading") for a, e in report["actions"].items()}
    lines += ["", f"`released` scores the release's own images, made with: {json.dumps(shading)}."]
    lines += ["", "Per action: " + "; ".join(f"{a} default {s['variants']['default']['per_action'][a]:.2f} dB"
                                           for a in report["actions"]), "",
              f"Decomposition (pixels in both masks, true surface points and true-mesh visibility, "
              f"{report['defaults']['lobes']} lobes, F0 {report['f0']:g}):",
              "", "| G-buffers | PSNR | " + " | ".join(short) + " |", "|---" * (2 + len(envs)) + "|"]
    for label, row in s["decomposition"].items():
        lines.append(f"| {label} | {row['psnr_db']:.2f} | "
                     + " | ".join(f"{row['per_environment'][e]:.2f}" for e in envs) + " |")
    lines += ["", "Shading normals against the simulator's (mean angle, degrees, pixels in both masks): "
              + ", ".join(f"{kind} {err:.2f}" for kind, err in s["normal_error_deg"].items()) + "."]
    lines += ["", f"SG fits (fit_height {report['fit_height']}, torch threads as above):", "",
              "| environment | lobes | fit s | irradiance rel L2 | map rel L2 (64 rows) | relit PSNR |",
              "|---" * 6 + "|"]
    for r in report["sg_fits"]:
        psnr = s["psnr_by_lobes"][str(r["lobes"])].get(r["environment"], float("nan"))
        lines.append(f"| {r['environment']} | {r['lobes']} | {r['fit_s']:.1f} | {r['irradiance_rel_l2']:.4f} | "
                     f"{r['map_rel_l2_64']:.3f} | {psnr:.2f} |")
    lines.append("")
    return "\n".join(lines)


def figure(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = report["summary"]
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), dpi=100)
    for label, row in s["variants"].items():
        if "seconds_per_view" not in row:
            continue
        axes[0].scatter(row["seconds_per_view"], row["psnr_db"])
        axes[0].annotate(label, (row["seconds_per_view"], row["psnr_db"]), fontsize=7)
    floor = s["decomposition"]["truth G-buffers (SG floor)"]["psnr_db"]
    axes[0].set_xlabel(f"seconds per view (G-buffer + visibility + {len(report['environments'])} environments)")
    axes[0].set_ylabel("relit PSNR vs truth (dB), mean")
    axes[0].set_title(f"relight variants (truth G-buffers + SG shading: {floor:.2f} dB)")
    ax2 = axes[1].twinx()
    for env in report["environments"]:
        rows = [r for r in report["sg_fits"] if r["environment"] == env]
        axes[1].plot([r["lobes"] for r in rows], [s["psnr_by_lobes"][str(r["lobes"])].get(env, np.nan) for r in rows],
                     "o-", label=f"{env} PSNR")
        ax2.plot([r["lobes"] for r in rows], [r["fit_s"] for r in rows], "x--", label=f"{env} fit s")
    axes[1].set_xscale("log", base=2)
    axes[1].set_xlabel("SG lobes")
    axes[1].set_ylabel("relit PSNR (dB)")
    ax2.set_ylabel("SG fit seconds")
    axes[1].legend(fontsize=6, loc="lower left")
    ax2.legend(fontsize=6, loc="lower right")
    axes[1].set_title("lobe count: PSNR (o) and fit time (x)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> int:
    from _release import check_inputs, parse_release_args, release_parser

    args = parse_release_args(release_parser(__doc__, actions="", threads=2))
    release, capture, out = Path(args.release), Path(args.capture), Path(args.out)
    if not check_inputs("bench_relight", release, capture, need_truth=True)[0]:
        return 0
    from _threads import set_numeric_threads

    set_numeric_threads(args.threads)
    from manifests import open_release
    from pipeline.codecs.mesh import read_ply
    from stages.numerics.raycast import mesh_scene
    from synthetic.relight import TruthRelighter

    rel = open_release(release)
    actions = [a for a in (args.actions.split(",") if args.actions else rel.action_ids)
               if rel.action(a).render_cameras() and "texture_occlusion" in rel.action(a).kinds]
    if not actions:
        print(f"bench_relight: no action of {release} has renders/ and an occlusion texture; skipped")
        return 0

    def progress(message: str) -> None:
        print(message, flush=True)

    if CONFIG.learned_blend.enabled:
        print("bench_relight: the stage's default blend is learned (relight.learned_blend); this bench reproduces "
              "the heuristic source weights only")
        return 1
    started = time.perf_counter()
    plan = sweeps(args.quick)
    environments = list(CONFIG.environments)[:1] if args.quick else list(CONFIG.environments)
    fits, fit_rows = fit_environments(environments, capture, progress, plan.lobes)
    if not fits:
        print("bench_relight: none of the environments was found (../shared/data/hdri); skipped")
        return 0
    out.mkdir(parents=True, exist_ok=True)
    report = {"threads": args.threads, "quick": args.quick, "defaults": DEFAULT, "f0": CONFIG.shading.f0,
              "fit_height": CONFIG.fit_height,
              "stage_config": dataclasses.asdict(CONFIG), "environments": list(fits),
              "sg_fits": fit_rows, "actions": {}}
    for action in actions:
        t0 = time.perf_counter()
        scene = ActionScene(release, action)
        load_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        truth = TruthRelighter(capture, action, **({"lights": 256} if args.quick else {}))
        true_scene = mesh_scene(*read_ply(capture / "ground_truth" / action / "mesh.ply"))
        truth_s = time.perf_counter() - t0
        progress(f"{action}: release loaded in {load_s:.1f} s, truth relighter built in {truth_s:.1f} s")
        cams = scene.view.render_cameras()
        report["views_per_action"] = len(cams)
        try:
            shading = scene.view.release.load(scene.view.asset("render_environments", None)).get("shading")
        except (KeyError, FileNotFoundError):
            shading = None
        views = [bench_view(scene, truth, true_scene, cam, fits, args.threads, progress, plan) for cam in cams]
        report["actions"][action] = {"load_s": round(load_s, 2), "truth_relighter_s": round(truth_s, 2),
                                     "released_shading": shading, "views": views}
    report["summary"] = summarise(report, plan)
    report["total_s"] = round(time.perf_counter() - started, 1)
    write_report(out, "bench_relight", report, markdown(report), lambda path: figure(report, path),
                 json_default=_json_default)
    print(f"total {report['total_s']} s; wrote {out / 'bench_relight.json'}, .md and .png")
    return 0


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value)}")


if __name__ == "__main__":
    sys.exit(main())
