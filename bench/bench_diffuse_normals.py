"""The released ``normal_diffuse`` maps: the specular fit with one roughness prior against the fit with the
materials stage's roughness (what the ``diffuse_normals`` stage releases) and with the simulator's own
roughness (an oracle), in the same process, on the same cameras; every variant with the mesh's occlusion of
the LED sphere divided out as the stage does (``diffuse_normals.occlusion``), and the released one also
without it.

Needs `make dataset` (the release and its work folder: decoded frames, photometric maps, the textured mesh,
the roughness texture and the session's LED model) and the simulator's ground truth. For every action and
every ``--stride``-th camera it reports per variant:

1. the error of the maps against the simulator's normals over the valid pixels (alpha > 0.5, mask): mean,
   median, % under 5 deg, and the mean on shiny (true roughness < 0.3) and other pixels;
2. seconds per camera of the fit and its edge-preserving filter (and of seeing the roughness texture through
   the mesh), and the ratio to the one-prior baseline;
3. that the ``materials`` variant reproduces the released maps (max abs difference);
4. the released ``albedo_diffuse`` against the white-light ``albedo``: the median difference to the
   simulator's albedo per band of n.v (true normal, view direction) and the PSNR over the valid pixels, and the
   seconds per camera of taking the specular light out (:func:`stages.diffuse_normals.diffuse_albedo`, which
   must reproduce the released map);
5. the released fit's de-occlusion over :data:`DIRECTION_SWEEP` and the stage's occlusion directions: error
   against the simulator's normals and seconds per camera (the stage's knob, time against error).

Writes bench_diffuse_normals.json and bench_diffuse_normals.png (error and time per variant). ``--quick`` (the
tests' mode): the tiny run of ``bench/_quick.py`` (its release and work folder); the numbers are not measurements.
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _scalar(image: np.ndarray) -> np.ndarray:
    return image[..., 0] if image.ndim == 3 else image


DIRECTION_SWEEP = (64, 128, 256)
"""Occlusion directions measured besides the stage's ``occlusion_directions`` (time against normal error)."""


def measure_action(work: Path, truth: Path, action: str, session: str, stride: int) -> dict:
    """The variants of one action (module docstring)."""
    from pipeline.codecs.exr import read_exr
    from pipeline.codecs.image import read_png
    from artifacts.facade import ActionArtifacts
    from stages.numerics.metrics import angular_error_deg
    from stages.numerics.raycast import mesh_scene
    from stages.numerics.specular_normals import view_directions
    from stages.diffuse_normals import DiffuseNormalsConfig, diffuse_albedo, materials_roughness, refit_diffuse_normals

    from stages.numerics.shadowing import deocclude_view

    cfg = DiffuseNormalsConfig()
    # the diffuse_normals stage's upstream artifacts and its own, as the stage's task sees them
    artifacts = ActionArtifacts.from_store(work / "artifacts", action, session,
                                           ("decode", "photometric", "lights", "textures", "materials",
                                            "diffuse_normals"))
    if artifacts is None:
        raise FileNotFoundError(f"{work}: a stage's artifacts of {action} are missing")
    model = artifacts.light_model()
    vertices, faces, atlas = artifacts.atlas_mesh()
    scene = mesh_scene(vertices, faces)
    texture = artifacts.texture("roughness_texture", 1)
    cameras = artifacts.calibrated_cameras()
    variants = ("one prior", "materials, occlusion not divided out", "materials", "simulator (oracle)")
    errors = {v: [] for v in variants}
    shiny = []
    seconds = {v: 0.0 for v in variants}
    lookup_s, reproduced, count, deocclusion_s = 0.0, 0.0, 0, 0.0
    f0 = artifacts.materials_f0()
    albedo_rows: list[tuple[np.ndarray, ...]] = []
    albedo_s, albedo_reproduced = 0.0, 0.0
    sweep: dict[int, dict] = {}  # occlusion directions -> errors and seconds of the de-occlusion
    for cam_id in sorted(cameras)[::stride]:
        if not artifacts.has("normal_alpha", cam_id):
            continue
        cam = cameras[cam_id]
        normal_alpha = artifacts.exr("normal_alpha", cam_id)
        alpha = normal_alpha[..., 3]
        h, w = alpha.shape
        pos, neg = artifacts.exr("pos", cam_id), artifacts.exr("neg", cam_id)
        mask = artifacts.mask(cam_id)
        albedo = artifacts.map("albedo", cam_id)
        valid = (alpha > 0.5) & mask
        t0 = time.perf_counter()
        from_materials, _ = materials_roughness(scene, atlas, texture, cam, h, w, cfg.fit.roughness)
        lookup_s += time.perf_counter() - t0
        true_rough = _scalar(read_exr(truth / action / "roughness" / f"{cam_id}.exr"))
        true_normals = read_exr(truth / action / "normal" / f"{cam_id}.exr")[..., :3]
        true_mask = _scalar(read_png(truth / action / "mask" / f"{cam_id}.png")) > 127
        roughness = {"one prior": cfg.fit.roughness,
                     "materials": from_materials,
                     "simulator (oracle)": np.where(true_mask & (true_rough > 0), true_rough, cfg.fit.roughness).astype(np.float32)}
        scored = valid & true_mask
        fits: dict[str, tuple[np.ndarray, float]] = {}  # one fit per roughness source, with its seconds
        for variant in variants:
            source = "materials" if variant.startswith("materials") else variant
            if source not in fits:
                t0 = time.perf_counter()
                fitted = refit_diffuse_normals(cam, pos, neg, normal_alpha, mask, albedo, model, cfg,
                                               roughness[source])
                fits[source] = (fitted, time.perf_counter() - t0)
            normals, fit_s = fits[source]
            seconds[variant] += fit_s
            if cfg.occlusion and variant != "materials, occlusion not divided out":
                t1 = time.perf_counter()
                normals, _ = deocclude_view(scene, cam.K, cam.cam_from_world, normals, cfg.occlusion_directions,
                                            cfg.occlusion_min_visible)
                if variant == "materials":
                    deocclusion_s += time.perf_counter() - t1
            errors[variant].append(angular_error_deg(normals, true_normals)[scored])
            if variant == "materials" and artifacts.has("normal_diffuse", cam_id):
                released = artifacts.map("normal_diffuse", cam_id)
                reproduced = max(reproduced, float(np.abs(released - normals)[scored].max()))
            if variant == "materials" and artifacts.has("albedo_diffuse", cam_id):
                t0 = time.perf_counter()
                diffuse = diffuse_albedo(albedo, normals, cam, roughness[variant], f0)
                albedo_s += time.perf_counter() - t0
                released_albedo = artifacts.map("albedo_diffuse", cam_id)
                albedo_reproduced = max(albedo_reproduced, float(np.abs(released_albedo - diffuse)[scored].max()))
                true_albedo = read_exr(truth / action / "albedo" / f"{cam_id}.exr")[..., :3]
                n_dot_v = (true_normals * view_directions(cam.K, cam.cam_from_world, h, w)).sum(-1)
                albedo_rows.append((n_dot_v[scored], (albedo - true_albedo)[scored],
                                    (released_albedo - true_albedo)[scored]))
        if cfg.occlusion:  # the released fit's occlusion traced over fewer directions than the stage's
            fitted = fits["materials"][0]
            for n_dirs in sorted(set(DIRECTION_SWEEP) | {cfg.occlusion_directions}):
                t1 = time.perf_counter()
                swept, _ = deocclude_view(scene, cam.K, cam.cam_from_world, fitted, n_dirs,
                                          cfg.occlusion_min_visible)
                row = sweep.setdefault(n_dirs, {"errors": [], "seconds": 0.0})
                row["seconds"] += time.perf_counter() - t1
                row["errors"].append(angular_error_deg(swept, true_normals)[scored])
        shiny.append(true_rough[scored] < 0.3)
        count += 1
    shiny_all = np.concatenate(shiny)
    out = {"cameras": count, "roughness_lookup_s_per_camera": round(lookup_s / max(count, 1), 3),
           "deocclusion_s_per_camera": round(deocclusion_s / max(count, 1), 3),
           "materials_vs_released_max_abs": reproduced, "variants": {}}
    if albedo_rows:
        n_dot_v = np.concatenate([r[0] for r in albedo_rows])
        white, diffuse = (np.concatenate([r[i] for r in albedo_rows]) for i in (1, 2))
        bands = {}
        for lo, hi in ((0.7, 1.01), (0.5, 0.7), (0.3, 0.5), (0.15, 0.3), (0.0, 0.15)):
            sel = (n_dot_v >= lo) & (n_dot_v < hi)
            if sel.any():
                bands[f"{lo}-{min(hi, 1.0)}"] = {"pixels": int(sel.sum()),
                                                 "white_minus_truth": round(float(np.median(white[sel].mean(-1))), 4),
                                                 "diffuse_minus_truth": round(float(np.median(diffuse[sel].mean(-1))), 4)}
        psnr = lambda e: round(float(10 * np.log10(1.0 / max(float(np.mean(e.astype(np.float64) ** 2)), 1e-12))), 2)  # noqa: E731
        out["albedo"] = {"f0": f0, "by_n_dot_v": bands, "psnr_white_db": psnr(white), "psnr_diffuse_db": psnr(diffuse),
                         "seconds_per_camera": round(albedo_s / len(albedo_rows), 3),
                         "released_max_abs_difference": albedo_reproduced}
    out["occlusion_directions"] = {
        str(n_dirs): {"mean_deg": round(float(np.concatenate(r["errors"]).mean()), 3),
                      "under5_pct": round(float(100 * np.mean(np.concatenate(r["errors"]) <= 5)), 2),
                      "deocclusion_s_per_camera": round(r["seconds"] / max(count, 1), 3),
                      "stage_default": n_dirs == cfg.occlusion_directions}
        for n_dirs, r in sorted(sweep.items())}
    base_s = seconds["one prior"]
    for variant in variants:
        e = np.concatenate(errors[variant])
        out["variants"][variant] = {
            "mean_deg": round(float(e.mean()), 3), "median_deg": round(float(np.median(e)), 3),
            "under5_pct": round(float(100 * np.mean(e <= 5)), 2),
            "shiny_mean_deg": round(float(e[shiny_all].mean()), 3) if shiny_all.any() else None,
            "other_mean_deg": round(float(e[~shiny_all].mean()), 3),
            "fit_s_per_camera": round(seconds[variant] / max(count, 1), 3),
            "time_vs_one_prior": round(seconds[variant] / max(base_s, 1e-9), 2)}
    return out


def figure(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    actions = list(report["actions"])
    variants = list(next(iter(report["actions"].values()))["variants"])
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.6))
    width = 0.8 / len(variants)
    for i, variant in enumerate(variants):
        x = np.arange(len(actions)) + i * width
        axes[0].bar(x, [report["actions"][a]["variants"][variant]["mean_deg"] for a in actions], width, label=variant)
        axes[1].bar(x, [report["actions"][a]["variants"][variant]["shiny_mean_deg"] or 0 for a in actions], width,
                    label=variant)
    for ax, title in zip(axes, ("all valid pixels", "shiny pixels (true roughness < 0.3)")):
        ax.set_xticks(np.arange(len(actions)) + width * (len(variants) - 1) / 2, actions)
        ax.set_ylabel("mean angular error vs truth (deg)")
        ax.set_title(title)
    axes[0].legend(fontsize=8, loc="lower left")
    for action, result in report["actions"].items():
        bands = result.get("albedo", {}).get("by_n_dot_v", {})
        for key, style in (("white_minus_truth", "--"), ("diffuse_minus_truth", "-")):
            axes[2].plot(list(bands), [b[key] for b in bands.values()], style, marker="o",
                         label=f"{action} {'albedo' if key.startswith('white') else 'albedo_diffuse'}")
    axes[2].axhline(0.0, color="grey", lw=0.8)
    axes[2].set_xlabel("n.v band (true normal, view)")
    axes[2].set_ylabel("median albedo - simulator's albedo")
    axes[2].set_title("released per-view albedo maps")
    axes[2].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    from _release import check_inputs, parse_release_args, release_parser

    parser = release_parser(__doc__, threads=2)
    parser.add_argument("--stride", type=int, default=4, help="every stride-th camera (default 4: 8 of 32)")
    args = parse_release_args(parser)
    release, capture, out = Path(args.release), Path(args.capture), Path(args.out)
    go_on, truth = check_inputs("bench_diffuse_normals", release, capture, need_truth=True)
    if not go_on:
        return 0
    from pipeline.runner import read_run_record

    from artifacts.facade import ActionArtifacts

    work = Path(read_run_record(release)["work"])  # run.json holds it relative to the release
    capture_json = json.loads((capture / "capture.json").read_text())
    session_of = {a["action_id"]: a["session_id"] for a in capture_json["actions"]
                  if ActionArtifacts.from_store(work / "artifacts", a["action_id"], a["session_id"],
                                                ("diffuse_normals",)) is not None}
    if not session_of:
        print(f"bench_diffuse_normals: no diffuse_normals artifacts under {work} (rerun `make dataset`); skipped")
        return 0
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    import torch

    torch.set_num_threads(args.threads)
    report = {"stride": args.stride, "threads": args.threads, "quick": args.quick, "actions": {}}
    for action in sorted(session_of):
        report["actions"][action] = measure_action(work, truth, action, session_of[action], args.stride)
        print(action, json.dumps(report["actions"][action]), flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_diffuse_normals.json").write_text(json.dumps(report, indent=1))
    if report["actions"]:
        figure(report, out / "bench_diffuse_normals.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
