"""Where the photometric normal error comes from: the same subject rendered with one effect at a time.

Variants of the simulator (8 cameras, 1 action, default width): everything on (default), no specular,
no noise, no folds, and "ideal" (none of these and no LED errors). Each goes through the pipeline (default preset)
up to ``photometric``, whose maps are what is measured (the later stages do not change them), and is evaluated
against ground truth, over valid pixels, split by the ground-truth
visibility of the lit hemisphere. The pre-sensor error (the ratio of eq. 1 on the rendered radiance,
before mosaicing, noise and demosaicing) of the ideal variant shows what the optics alone allow.
Writes bench_normal_error_sources.json and .png.

``--quick`` (the tests' mode): 4 cameras 64 px wide, 128 LEDs, the subject unsubdivided; the numbers are not
measurements.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _quick import QUICK_HELP, quick_sim_changes  # noqa: E402

VARIANTS = {"default": {}, "no_specular": {"specular": False}, "no_noise": {"noise": False},
            "no_folds": {"fold_amplitude_m": 0.0},
            "ideal": {"specular": False, "noise": False, "fold_amplitude_m": 0.0, "led_error": 0.0}}


def pre_sensor_error(config) -> dict[str, float]:
    from stages.numerics.metrics import angular_error_deg
    from synthetic.simulate import render_views

    _, _, views = render_views(config)
    errors, visibility = [], []
    for view in views:
        pos, neg = view.radiance[..., 3:6], view.radiance[..., 6:9]
        d = (pos - neg) / np.maximum(pos + neg, 1e-9)
        errors.append(angular_error_deg(d, view.normals_world)[view.mask])
        visibility.append(view.visibility[view.mask])
    err, vis = np.concatenate(errors), np.concatenate(visibility)
    return {"unoccluded_deg": float(err[vis >= 0.9].mean()), "occluded_deg": float(err[vis < 0.9].mean()),
            "visibility_ge_0.97_deg": float(err[vis >= 0.97].mean())}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="bench/out")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--cameras", type=int, default=8)
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    if args.quick:
        args.width, args.cameras = 64, 4
    sim_changes = quick_sim_changes() if args.quick else {}
    through = "photometric"  # only its maps are measured; the neural stages after it would take minutes a variant
    out = Path(args.out)
    from pipeline.runner import ExecutionConfig
    from evaluation.release import evaluate_release
    from stages.registry import PRESETS, build_stages
    from ultrastage.run import run_pipeline
    from synthetic import SimConfig, simulate

    report = {"quick": args.quick}
    for name, overrides in VARIANTS.items():
        root = out / "normal_error_sources" / name
        shutil.rmtree(root, ignore_errors=True)
        config = dataclasses.replace(SimConfig(actions=1, n_cameras=args.cameras, width=args.width, **sim_changes),
                                     **overrides)
        simulate(root / "capture", config)
        preset = PRESETS["default"]
        run_pipeline(root / "capture", root / "release", root / "work", build_stages(preset, through=through), preset,
                     ExecutionConfig(scheduler="sync"), echo=lambda line: None)
        o = evaluate_release(root / "release", root / "capture" / "ground_truth").overall
        report[name] = {k: o[k] for k in ("normal_mean_deg", "normal_median_deg", "normal_mean_deg_unoccluded",
                                          "normal_mean_deg_occluded", "valid_fraction", "albedo_psnr_db")}
        if name == "ideal":
            report[name]["pre_sensor"] = pre_sensor_error(config)
        print(f"{name:<12} valid {o['normal_mean_deg']:6.2f} deg  unoccluded {o['normal_mean_deg_unoccluded']:6.2f}  "
              f"occluded {o['normal_mean_deg_occluded']:6.2f}  albedo {o['albedo_psnr_db']:5.2f} dB", flush=True)
    print(f"ideal, before the sensor: {json.dumps(report['ideal']['pre_sensor'])}")
    (out / "bench_normal_error_sources.json").write_text(json.dumps(report, indent=1))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    names = [n for n in report if n != "quick"]
    x = np.arange(len(names))
    ax.bar(x - 0.2, [report[n]["normal_mean_deg_unoccluded"] for n in names], 0.4, label="unoccluded")
    ax.bar(x + 0.2, [report[n]["normal_mean_deg_occluded"] for n in names], 0.4, label="occluded")
    ax.axhline(report["ideal"]["pre_sensor"]["unoccluded_deg"], color="k", ls="--", label="ideal, pre-sensor")
    ax.set_xticks(x, names)
    ax.set_ylabel("mean normal error (deg)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "bench_normal_error_sources.png", dpi=110)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
