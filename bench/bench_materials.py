"""Materials stage: the roughness texture and the de-occluded albedo against the simulator, with their times.

For each action of a release (default A0000 and A0001) this rebuilds the materials stage's steps outside the
stage, from the release's own files, with the numerics the stage calls (``stages.numerics.bake``
``rasterize_atlas`` / ``gather_observations``, ``stages.numerics.materials.fit_roughness``,
``stages.materials.roughness_median``, ``stages.numerics.shadowing.ambient_occlusion``), and scores every
variant like ``ultrastage evaluate`` does (``stages.evaluate._materials_overall``): the textures are seen
through the textured mesh from every **true** camera (pixels where the truth has the subject and the mesh
is hit) and compared with the simulator's roughness and albedo maps.

1. **Roughness** (texture 256): mean absolute error and bias against the truth for ``specular_model``
   ggx_table vs sg, ``fit_albedo`` on/off, ``max_views`` 8/16 (the 8 best views are the first 8 of the 16
   gathered: same ranking), ``median_min_visibility`` 0/0.85/0.95 (which texels vote in the surface median: those
   whose ambient visibility on the mesh reaches it) and ``median_neighbours`` 1/25/100/200, one change at a
   time from the stage's defaults, with the fit time (``fit_roughness``, ``--threads`` torch threads) and the
   smoothing time.
   Baselines: a constant roughness equal to the median of the per-texel fits (what a fit that finds no
   variation gives) and, as oracles, the truth's own mean and median over the compared pixels (the median
   is the constant with the least absolute error).
   The default row must match the released texture's score (``released`` row) when the release was made
   with the stage's defaults.
2. **Albedo**: PSNR against the truth of the baked white-light albedo texture and of the de-occluded one
   (ambient occlusion on the mesh with ``occlusion_rays`` 16/64/128, divided out with a floor
   ``min_occlusion`` 0.1/0.2/0.4), with the occlusion time and each texture's median ratio to the truth
   (its gain); and the baked albedo divided by the simulator's per-pixel visibility map. That is no upper
   bound: in creases the blurred texture and the true pixel disagree and the division blows the error up.

``python bench/bench_materials.py --out DIR [--release DIR --capture DIR --actions A0000,A0001 --threads 2]``
writes DIR/bench_materials.json, DIR/bench_materials.md (tables) and DIR/bench_materials.png (roughness MAE
against fit seconds; albedo PSNR against occlusion seconds). Defaults: runs/default/release and
runs/default/capture; without them (or without ground truth) it prints why and exits 0.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

ILLUMINATIONS = ("full_on", "pos", "neg")
DEFAULTS = {"specular_model": "ggx_table", "fit_albedo": True, "max_views": 8, "median_neighbours": 100,
            "median_min_visibility": 0.95}
VARIANTS = [("default (ggx_table, fit_albedo, 8 views, voters >= 0.95 visible)", {}),
            ("specular_model sg", {"specular_model": "sg"}),
            ("fit_albedo off", {"fit_albedo": False}),
            ("max_views 16", {"max_views": 16}),
            ("median_min_visibility 0 (every fitted texel votes)", {"median_min_visibility": 0.0}),
            ("median_min_visibility 0.85", {"median_min_visibility": 0.85})]
NEIGHBOURS = (1, 25, 100, 200)
OCCLUSION_RAYS = (16, 64, 128)
MIN_OCCLUSION = (0.1, 0.2, 0.4)
TEXTURE_SIZE = 256
OCCLUSION_SIZE = 512
MIN_ALPHA = 0.5


def white_references(release: Path, capture: Path, action: str, session: str) -> dict[str, np.ndarray]:
    """camera_id -> white_reference (3,): the decode stage's cameras.json in the release's work folder (what
    the materials stage used), else the capture's rig.json."""
    latest = release.parent / f"{release.name}.work" / "artifacts" / "decode" / action / "latest.json"
    path = None
    if latest.exists():
        key = json.loads(latest.read_text()).get("key", "")
        candidate = latest.parent / key[:16] / "cameras.json"
        path = candidate if candidate.exists() else None
    if path is None:
        path = capture / "sessions" / session / "rig.json"
    return {c["camera_id"]: np.asarray(c["white_reference"], np.float32)
            for c in json.loads(path.read_text())["cameras"]}


def load_action(release: Path, capture: Path, action: str) -> dict:
    """The release's inputs of the materials stage for one action: the welded textured mesh and its atlas,
    the baked albedo texture and one BakeView per camera (full_on | pos | neg stacked, valid = alpha > 0.5
    inside the mask), with the cameras' white references."""
    from manifests import open_release
    from stages.heldout import release_cameras
    from stages.materials import load_atlas_mesh
    from stages.numerics.bake import BakeView

    view = open_release(release).action(action)
    cameras = release_cameras(view.transforms())
    white = white_references(release, capture, action, view.info.get("session_id") or "S000")
    vertices, faces, atlas = load_atlas_mesh(view.path("mesh_textured"))
    views, whites = [], []
    for cam_id in sorted(cameras):
        images = np.concatenate([view.image(ill, cam_id) for ill in ILLUMINATIONS], axis=2)
        valid = (view.normal_alpha(cam_id) > MIN_ALPHA) & view.mask(cam_id)
        views.append(BakeView(images={"obs": images}, valid=valid, K=cameras[cam_id]["K"],
                              cam_from_world=cameras[cam_id]["cam_from_world"]))
        whites.append(white[cam_id])
    textures = {"albedo": view.texture("albedo")[..., :3], "roughness": view.texture("roughness")}
    for name in ("albedo_deoccluded", "albedo_intrinsic"):
        if f"texture_{name}" in view.kinds:
            textures[name] = view.texture(name)[..., :3]
    return {"view": view, "vertices": vertices, "faces": faces, "atlas": atlas, "views": views,
            "white": np.stack(whites), "released": textures, "obj": view.path("mesh_textured"),
            "session": view.info.get("session_id") or "S000"}


class TruthProbe:
    """Every true camera's view of the textured mesh (UVs of the pixels where the truth has the subject
    and the mesh is hit) with the truth there: scores any texture of the atlas like evaluate does."""

    def __init__(self, data: dict, truth_dir: Path, action: str):
        from pipeline.codecs.exr import read_exr
        from pipeline.codecs.image import read_png
        from stages.evaluate import true_cameras
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


def roughness_section(data: dict, probe: TruthProbe, progress) -> dict:
    """Per-texel fits for every variant, smoothed and scored; times of the gather, fits and medians."""
    from stages.materials import _dilate, roughness_median, texel_uvs
    from stages.numerics.raycast import mesh_scene
    from stages.numerics.shadowing import ambient_occlusion
    from stages.numerics.bake import gather_observations, rasterize_atlas, sample_texture
    from stages.numerics.materials import NO_VIEWS_RESIDUAL, fit_roughness

    t0 = time.perf_counter()
    raster = rasterize_atlas(data["vertices"], data["faces"], data["atlas"], TEXTURE_SIZE)
    covered = raster["covered"]
    points = raster["position"][covered].astype(np.float64)
    normals = raster["normal"][covered].astype(np.float64)
    albedo = sample_texture(data["released"]["albedo"], texel_uvs(covered))
    max_k = max(DEFAULTS["max_views"], *(v.get("max_views", 0) for _, v in VARIANTS))
    obs = gather_observations(data["vertices"], data["faces"], points, normals, data["views"], max_k)
    gather_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    visibility = ambient_occlusion(points, normals, mesh_scene(data["vertices"], data["faces"]), rays=64)
    visibility_s = time.perf_counter() - t0
    out = {"texels": int(len(points)), "gather_s_16_views": round(gather_s, 2),
           "texel_visibility_s": round(visibility_s, 2),
           "mean_valid_views": round(float(obs["valid"].sum(axis=1).mean()), 2), "variants": [], "neighbours": []}

    def texture_of(values: np.ndarray) -> np.ndarray:
        tex = np.zeros((TEXTURE_SIZE, TEXTURE_SIZE), np.float32)
        tex[covered] = values
        return _dilate(tex, covered)

    # Warm up: the first fit of a process builds the specular moment tables (about a second); not timed.
    for model in sorted({(DEFAULTS | change)["specular_model"] for _, change in VARIANTS}):
        fit_roughness(obs["values"]["obs"][:64].reshape(-1, max_k, 3, 3), obs["view_dirs"][:64], obs["valid"][:64],
                      normals[:64], albedo[:64], white_scale=data["white"][np.maximum(obs["view_index"][:64], 0)],
                      specular_model=model)
    default_fit = None
    for label, change in VARIANTS:
        cfg = DEFAULTS | change
        k = cfg["max_views"]
        observed = obs["values"]["obs"][:, :k].reshape(len(points), k, 3, 3)
        white = data["white"][np.maximum(obs["view_index"][:, :k], 0)]
        t0 = time.perf_counter()
        rough, rms = fit_roughness(observed, obs["view_dirs"][:, :k], obs["valid"][:, :k], normals, albedo,
                                   white_scale=white, specular_model=cfg["specular_model"],
                                   fit_albedo=cfg["fit_albedo"])
        fit_s = time.perf_counter() - t0
        fitted = rms != NO_VIEWS_RESIDUAL
        t0 = time.perf_counter()
        smooth, _ = roughness_median(points, rough, fitted, visibility, cfg["median_min_visibility"],
                                     cfg["median_neighbours"])
        median_s = time.perf_counter() - t0
        smooth = np.clip(np.nan_to_num(smooth, nan=0.5), 0.05, 1.0)
        score = probe.roughness_errors(texture_of(smooth))
        raw = probe.roughness_errors(texture_of(rough))
        out["variants"].append({"variant": label, **cfg, "fit_s": round(fit_s, 2), "median_s": round(median_s, 2),
                                "mae": round(score["mae"], 4), "bias": round(score["bias"], 4),
                                "mae_unsmoothed": round(raw["mae"], 4),
                                "fit_rms_median": round(float(np.median(rms[fitted])), 5) if fitted.any() else 0.0})
        progress(f"  {label}: MAE {score['mae']:.4f} bias {score['bias']:+.4f} fit {fit_s:.1f} s")
        if not change:
            default_fit = (rough, fitted)
    rough, fitted = default_fit
    for neighbours in NEIGHBOURS:
        t0 = time.perf_counter()
        smooth, _ = roughness_median(points, rough, fitted, visibility, DEFAULTS["median_min_visibility"], neighbours)
        smooth = np.clip(np.nan_to_num(smooth, nan=0.5), 0.05, 1.0)
        median_s = time.perf_counter() - t0
        score = probe.roughness_errors(texture_of(smooth))
        out["neighbours"].append({"median_neighbours": neighbours, "median_s": round(median_s, 2),
                                  "mae": round(score["mae"], 4), "bias": round(score["bias"], 4)})
    median_fit = float(np.median(rough[fitted])) if fitted.any() else 0.5
    truth_mean = float(np.mean(probe.roughness))
    truth_median = float(np.median(probe.roughness))
    out["baselines"] = {name: {"value": round(value, 4)} | _round(probe.roughness_errors(value))
                        for name, value in (("constant_median_of_fits", median_fit),
                                            ("constant_truth_mean_oracle", truth_mean),
                                            ("constant_truth_median_oracle", truth_median))}
    out["baselines"]["released_texture"] = _round(probe.roughness_errors(data["released"]["roughness"]))
    levels = np.round(probe.roughness, 2)
    smooth_default = texture_of(np.clip(np.nan_to_num(roughness_median(
        points, rough, fitted, visibility, DEFAULTS["median_min_visibility"], DEFAULTS["median_neighbours"])[0],
        nan=0.5), 0.05, 1))
    seen = sample_texture(smooth_default, probe.uv)
    out["default_by_true_level"] = [
        {"true_roughness": float(v), "share": round(float(np.mean(levels == v)), 4),
         "pred_mean": round(float(seen[levels == v].mean()), 4),
         "mae": round(float(np.abs(seen[levels == v] - probe.roughness[levels == v]).mean()), 4)}
        for v in np.unique(levels) if np.mean(levels == v) > 0.01]
    return out


def albedo_section(data: dict, probe: TruthProbe, threads: int, progress) -> dict:
    """Baked vs de-occluded albedo (the stage's occlusion at several ray counts and floors) vs the truth."""
    from stages.materials import _dilate
    from stages.numerics.bake import rasterize_atlas, sample_texture
    from stages.numerics.raycast import mesh_scene
    from stages.numerics.shadowing import ambient_occlusion

    baked = data["released"]["albedo"]
    out = {"baked_psnr_db": round(probe.albedo_psnr(baked), 3), "baked_gain": round(probe.albedo_gain(baked), 4),
           "occlusion": [],
           "baked_over_truth_visibility_psnr_db": {str(f): round(probe.albedo_psnr(baked, f), 3)
                                                   for f in MIN_OCCLUSION}}
    if "albedo_deoccluded" in data["released"]:
        out["released_deoccluded_psnr_db"] = round(probe.albedo_psnr(data["released"]["albedo_deoccluded"]), 3)
        out["released_deoccluded_gain"] = round(probe.albedo_gain(data["released"]["albedo_deoccluded"]), 4)
    if "albedo_intrinsic" in data["released"]:
        out["released_intrinsic_psnr_db"] = round(probe.albedo_psnr(data["released"]["albedo_intrinsic"]), 3)
        out["released_intrinsic_gain"] = round(probe.albedo_gain(data["released"]["albedo_intrinsic"]), 4)
    t0 = time.perf_counter()
    raster = rasterize_atlas(data["vertices"], data["faces"], data["atlas"], OCCLUSION_SIZE)
    covered = raster["covered"]
    points = raster["position"][covered].astype(np.float64)
    normals = raster["normal"][covered].astype(np.float64)
    scene = mesh_scene(data["vertices"], data["faces"])
    out["raster_s"] = round(time.perf_counter() - t0, 2)
    h, w = baked.shape[:2]
    rows, cols = np.mgrid[0:h, 0:w]
    uv_full = np.stack([(cols + 0.5) / w, 1.0 - (rows + 0.5) / h], axis=-1)
    for rays in OCCLUSION_RAYS:
        t0 = time.perf_counter()
        visible = ambient_occlusion(points, normals, scene, rays=rays, threads=threads)
        occ_s = time.perf_counter() - t0
        occlusion = np.ones((OCCLUSION_SIZE, OCCLUSION_SIZE), np.float32)
        occlusion[covered] = visible
        occlusion_full = sample_texture(_dilate(occlusion, covered, fill=1.0), uv_full)
        row = {"occlusion_rays": rays, "occlusion_s": round(occ_s, 2), "mean_visible": round(float(visible.mean()), 4)}
        for floor in MIN_OCCLUSION:
            deoccluded = np.clip(np.nan_to_num(baked / np.maximum(occlusion_full, floor)[..., None]), 0.0, 1.0)
            row[f"psnr_db_min_occlusion_{floor}"] = round(probe.albedo_psnr(deoccluded), 3)
            if floor == 0.2:
                row["gain_min_occlusion_0.2"] = round(probe.albedo_gain(deoccluded), 4)
        out["occlusion"].append(row)
        progress(f"  occlusion {rays} rays: {occ_s:.1f} s, PSNR at floor 0.2 {row['psnr_db_min_occlusion_0.2']:.2f} dB")
    return out


def _round(d: dict, digits: int = 4) -> dict:
    return {k: round(float(v), digits) for k, v in d.items()}


def markdown(report: dict) -> str:
    lines = ["# bench_materials", "", f"torch threads {report['threads']}; texture {TEXTURE_SIZE}; roughness "
             "MAE / bias against the simulator over every true camera's view of the textured mesh.", ""]
    for action, entry in report["actions"].items():
        r = entry["roughness"]
        lines += [f"## {action} ({r['texels']} texels, {r['mean_valid_views']} valid views each of 16, gather "
                  f"{r['gather_s_16_views']} s, {entry['true_cameras']} true cameras)", "",
                  "| roughness variant | MAE | bias | MAE per texel (no median) | fit s | median s |",
                  "|---|---|---|---|---|---|"]
        for v in r["variants"]:
            lines.append(f"| {v['variant']} | {v['mae']:.4f} | {v['bias']:+.4f} | {v['mae_unsmoothed']:.4f} | "
                         f"{v['fit_s']:.1f} | {v['median_s']:.2f} |")
        for n in r["neighbours"]:
            lines.append(f"| default, median_neighbours {n['median_neighbours']} | {n['mae']:.4f} | {n['bias']:+.4f} "
                         f"| | | {n['median_s']:.2f} |")
        for name, b in r["baselines"].items():
            value = f" = {b['value']:.3f}" if "value" in b else ""
            lines.append(f"| baseline: {name}{value} | {b['mae']:.4f} | {b['bias']:+.4f} | | 0 | |")
        lines += ["", "| true roughness | share of pixels | fitted mean | MAE |", "|---|---|---|---|"]
        lines += [f"| {x['true_roughness']:.2f} | {x['share']:.3f} | {x['pred_mean']:.3f} | {x['mae']:.3f} |"
                  for x in r["default_by_true_level"]]
        a = entry["albedo"]
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
                  + " | ".join(f"PSNR floor {f}" for f in MIN_OCCLUSION) + " |",
                  "|---" * (3 + len(MIN_OCCLUSION)) + "|"]
        for o in a["occlusion"]:
            lines.append(f"| {o['occlusion_rays']} | {o['occlusion_s']:.1f} | {o['mean_visible']:.3f} | "
                         + " | ".join(f"{o[f'psnr_db_min_occlusion_{f}']:.2f}" for f in MIN_OCCLUSION) + " |")
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
        for floor, marker in zip(MIN_OCCLUSION, "os^"):
            axes[1].plot([o["occlusion_s"] for o in a["occlusion"]],
                         [o[f"psnr_db_min_occlusion_{floor}"] for o in a["occlusion"]], marker=marker, color=c,
                         label=f"{action} de-occluded, floor {floor}")
        axes[1].axhline(a["baked_psnr_db"], color=c, ls="--", lw=1, label=f"{action} baked")
    axes[0].set_xlabel("fit seconds (fit_roughness)")
    axes[0].set_ylabel("roughness MAE vs truth")
    axes[0].set_title("roughness: variants (dots), median_neighbours 1/25/100/200 (+)")
    axes[0].legend(fontsize=7)
    axes[1].set_xlabel("ambient occlusion seconds (16 / 64 / 128 rays)")
    axes[1].set_ylabel("albedo PSNR vs truth (dB)")
    axes[1].set_title("albedo: baked vs de-occluded")
    axes[1].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> int:
    from _release import check_inputs, release_parser

    args = release_parser(__doc__, actions="", threads=2).parse_args()
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
    report = {"threads": args.threads, "texture_size": TEXTURE_SIZE, "defaults": DEFAULTS, "actions": {}}
    started = time.perf_counter()
    for action in actions:
        t0 = time.perf_counter()
        data = load_action(release, capture, action)
        probe = TruthProbe(data, truth_dir, action)
        print(f"{action}: loaded in {time.perf_counter() - t0:.1f} s ({probe.cameras} true cameras)", flush=True)
        entry = {"true_cameras": probe.cameras, "load_s": round(time.perf_counter() - t0, 2)}
        entry["roughness"] = roughness_section(data, probe, lambda m: print(m, flush=True))
        entry["albedo"] = albedo_section(data, probe, args.threads, lambda m: print(m, flush=True))
        report["actions"][action] = entry
    report["total_s"] = round(time.perf_counter() - started, 1)
    (out / "bench_materials.json").write_text(json.dumps(report, indent=1))
    (out / "bench_materials.md").write_text(markdown(report))
    figure(report, out / "bench_materials.png")
    print(markdown(report))
    print(f"total {report['total_s']} s; wrote {out / 'bench_materials.json'}, .md and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
