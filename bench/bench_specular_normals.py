"""Photometric normals with the specular reflection modelled out: time against error.

A small capture (1 action, 8 cameras, default width; ``--seeds`` picks the subjects: seed 0 is the
subject the roughness prior was chosen on, the others are held out) goes through the pipeline up to
``photometric`` (which fits no specular reflection: the ``diffuse_normals`` stage does); then, per camera,
from the same decoded frames:

- ``eq1``: the ratio of eq. 1 (through the session's LED model when there is one): the baseline;
- ``fit r=R``: :func:`stages.numerics.specular_normals.fit_diffuse_normals` with roughness prior R
  (F0 0.04, the stage's solver and steps), and the default prior with Adam's 40 steps (the former
  solver) and 3 / 12 Levenberg-Marquardt steps;
- ``fit oracle r``: the simulator's per-pixel roughness (what a perfect roughness would give);
- ``fit per-pixel r``: each pixel's roughness chosen from {0.3, 0.5, 0.7, 0.9} by the lowest residual.

Errors against the simulator's normals over the pixels the release calls valid, with the share of the
error on the shiny leather (roughness < 0.35) and at grazing views (n.v < 0.3). Writes
bench_specular_normals.json/.md/.png. ``--quick`` (the tests' mode): seed 0 only, 2 cameras 64 px wide, 128 LEDs,
the subject unsubdivided; the numbers are not measurements.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _quick import QUICK_HELP, quick_sim_changes  # noqa: E402
from _threads import set_numeric_threads  # noqa: E402


def prepare(root: Path, seed: int, width: int, cameras: int, **sim_changes) -> Path:
    """Simulate and run through photometric; returns the work folder."""
    from pipeline.runner import ExecutionConfig
    from stages.registry import PRESETS, build_stages
    from ultrastage.run import run_pipeline
    from synthetic import SimConfig, simulate

    shutil.rmtree(root, ignore_errors=True)
    simulate(root / "capture", SimConfig(actions=1, n_cameras=cameras, width=width, seed=seed, **sim_changes))
    preset = PRESETS["default"]
    run_pipeline(root / "capture", root / "release", root / "work", build_stages(preset, through="photometric"),
                 preset, ExecutionConfig(scheduler="sync"), echo=lambda line: None)
    return root


def variants(default_roughness: float) -> dict[str, dict]:
    out = {"eq1": {}}
    for r in (0.4, 0.5, 0.6, 0.7, 0.8):
        out[f"fit r={r}"] = {"roughness": r}
    for solver, steps in (("adam", 40), ("levenberg_marquardt", 3), ("levenberg_marquardt", 12)):
        out[f"fit r={default_roughness} {solver} {steps} steps"] = {"roughness": default_roughness, "steps": steps,
                                                                    "solver": solver}
    out["fit oracle r"] = {"roughness": "truth"}
    out["fit per-pixel r"] = {"roughness": "grid"}
    return out


def evaluate(root: Path, default_roughness: float) -> dict[str, dict[str, float]]:
    from pipeline.codecs.exr import read_exr
    from artifacts.facade import ActionArtifacts
    from stages.numerics.metrics import angular_error_deg
    from stages.numerics.photometric import corrected_normals, photometric_maps
    from stages.numerics.specular_normals import fit_diffuse_normals, view_directions
    from stages.numerics.specular_normals import SpecularConfig

    action = "A0000"
    session = {a["action_id"]: a["session_id"]
               for a in json.loads((root / "capture" / "capture.json").read_text())["actions"]}[action]
    artifacts = ActionArtifacts.from_store(root / "work" / "artifacts", action, session, ("decode", "lights"))
    if artifacts is None:
        raise FileNotFoundError(f"{root / 'work'}: no decode or lights artifact of {action}")
    model = artifacts.light_model()
    truth = root / "capture" / "ground_truth" / action
    cams = artifacts.json("cameras")["cameras"]
    found: dict[str, dict[str, list]] = {}
    for cam in cams:
        cid = cam["camera_id"]
        full, pos, neg = (artifacts.exr(k, cid) for k in ("full_on", "pos", "neg"))
        clipped = artifacts.png("clipped", cid) > 0
        white = np.asarray(cam["white_reference"], np.float32)
        maps = photometric_maps(full, pos, neg, clipped, white)
        defined = np.any(maps.normals != 0, axis=-1) & maps.mask

        def ratio_normals(p, n):
            if model is not None:
                return corrected_normals(p, n, model, defined, 4)
            d = (p - n) / np.maximum(p + n, 1e-6)
            return np.where(defined[..., None], d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9), 0)

        start = time.perf_counter()
        eq1 = ratio_normals(pos, neg)
        eq1_s = time.perf_counter() - start
        true_n = read_exr(truth / "normal" / f"{cid}.exr")[..., :3]
        true_r = read_exr(truth / "roughness" / f"{cid}.exr")
        valid = (maps.alpha > 0.5) & maps.mask & (np.linalg.norm(true_n, axis=-1) > 0.5)
        views = view_directions(cam["K"], cam["cam_from_world"], cam["height"], cam["width"])
        n_dot_v = np.abs((views * true_n).sum(-1))
        for name, spec in variants(default_roughness).items():
            start = time.perf_counter()
            if not spec:
                normals = eq1
                seconds = eq1_s
            else:
                kwargs = {"steps": spec.get("steps", SpecularConfig().steps), "f0": 0.04,
                          "solver": spec.get("solver", SpecularConfig().solver)}
                if spec["roughness"] == "grid":
                    fits = [fit_diffuse_normals(pos, neg, white, views, eq1, defined, roughness=g, **kwargs)
                            for g in (0.3, 0.5, 0.7, 0.9)]
                    best = np.argmin(np.stack([f.residual for f in fits]), 0)
                    fit = fits[0]
                    sp, sn = (np.take_along_axis(np.stack([getattr(f, a) for f in fits]), best[None, ..., None], 0)[0]
                              for a in ("specular_pos", "specular_neg"))
                else:
                    r = true_r if spec["roughness"] == "truth" else spec["roughness"]
                    fit = fit_diffuse_normals(pos, neg, white, views, eq1, defined, roughness=r, **kwargs)
                    sp, sn = fit.specular_pos, fit.specular_neg
                normals = ratio_normals(pos - sp, neg - sn) if model is not None or spec["roughness"] == "grid" \
                    else fit.normals
                seconds = time.perf_counter() - start
            err = angular_error_deg(normals, true_n)
            rec = found.setdefault(name, {"err": [], "rough": [], "nv": [], "seconds": []})
            rec["err"].append(err[valid])
            rec["rough"].append(true_r[valid])
            rec["nv"].append(n_dot_v[valid])
            rec["seconds"].append(seconds / max(int(defined.sum()), 1) * 1e4)
    report = {}
    for name, rec in found.items():
        err, rough, nv = (np.concatenate(rec[k]) for k in ("err", "rough", "nv"))
        report[name] = {"mean_deg": float(err.mean()), "median_deg": float(np.median(err)),
                        "under5_pct": float(100 * np.mean(err <= 5)),
                        "leather_deg": float(err[rough < 0.35].mean()) if np.any(rough < 0.35) else float("nan"),
                        "grazing_deg": float(err[nv < 0.3].mean()), "frontal_deg": float(err[nv >= 0.3].mean()),
                        "seconds_per_10k_px": float(np.mean(rec["seconds"]))}
    return report


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="bench/out")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--cameras", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    if args.quick:
        args.seeds, args.width, args.cameras = [0], 64, 2
    set_numeric_threads(args.threads)
    from stages.numerics.specular_normals import SpecularConfig

    default_r = SpecularConfig().roughness
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {}
    for seed in args.seeds:
        root = prepare(out / "specular_normals" / f"seed{seed}", seed, args.width, args.cameras,
                       **(quick_sim_changes() if args.quick else {}))
        report[f"seed{seed}"] = evaluate(root, default_r)
        base = report[f"seed{seed}"]["eq1"]
        for name, row in report[f"seed{seed}"].items():
            print(f"seed {seed} {name:<22} mean {row['mean_deg']:6.2f} median {row['median_deg']:5.2f} "
                  f"leather {row['leather_deg']:6.2f} grazing {row['grazing_deg']:6.2f} "
                  f"s/10k px {row['seconds_per_10k_px']:6.3f} (x{row['seconds_per_10k_px'] / max(base['seconds_per_10k_px'], 1e-9):.0f})",
                  flush=True)
    (out / "bench_specular_normals.json").write_text(json.dumps(report | {"quick": args.quick}, indent=1))
    names = list(next(iter(report.values())))
    lines = ["| variant | " + " | ".join(f"seed {s} mean / median deg" for s in args.seeds) + " | s per 10k px |",
             "|---|" + "---|" * len(args.seeds) + "---|"]
    for name in names:
        cells = [f"{report[f'seed{s}'][name]['mean_deg']:.2f} / {report[f'seed{s}'][name]['median_deg']:.2f}"
                 for s in args.seeds]
        lines.append(f"| {name} | " + " | ".join(cells)
                     + f" | {report[f'seed{args.seeds[0]}'][name]['seconds_per_10k_px']:.3f} |")
    (out / "bench_specular_normals.md").write_text("\n".join(lines) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for seed in args.seeds:
        rows = report[f"seed{seed}"]
        ax.scatter([rows[n]["seconds_per_10k_px"] for n in names], [rows[n]["mean_deg"] for n in names],
                   label=f"seed {seed}")
        for n in names:
            ax.annotate(n, (rows[n]["seconds_per_10k_px"], rows[n]["mean_deg"]), fontsize=6)
    ax.set_xscale("symlog", linthresh=0.01)
    ax.set_xlabel("seconds per 10k pixels (1 thread)")
    ax.set_ylabel("mean normal error vs truth (deg)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "bench_specular_normals.png", dpi=110)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
