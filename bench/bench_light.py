"""Light (and colour) calibration on the simulator: normal error with and without the light model, and
the time of the per-pixel correction.

For each LED error level, a small capture is simulated with calibration frames
(``simulate(..., calibration=CalibrationConfig())``: per-camera colour-response errors, a chart and a
diffuse sphere per session). Then, as the stage wiring would:

1. per camera, the chart frame is decoded, patch means measured and a colour matrix fitted
   (decoded -> white_reference * reference); every frame below is decoded and multiplied by it;
2. the light model (degree 2) is fitted on the sphere pixels (true normals by ray-sphere intersection,
   mask eroded by 2 px) of the even cameras;
3. errors (mean angle to the truth, degrees) of ``normalize(d)`` and of ``correct_normals(d, model)`` on
   the sphere in the odd cameras and on the subject (all masked pixels, and unoccluded ones:
   visibility > 0.95), plus the chart dE2000 before/after the colour matrix;
4. the correction is timed on 1 MP of ratios for 2, 4 (default) and 6 Gauss-Newton iterations (best of 3) against
   the plain ``normalize(d)``, with the error each reaches on the held-out sphere pixels.

``python bench/bench_light.py --out bench/out [--quick]`` writes bench_light.json and bench_light.png. ``--quick``
(the tests' mode): 4 cameras 96 px wide, 128 LEDs, the subject unsubdivided, the correction timed once on 16k
ratios; the numbers are not measurements.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _quick import QUICK_HELP, quick_sim_changes  # noqa: E402

from calibration.colour import (apply_colour_matrix, chart_patch_means, delta_e_2000,  # noqa: E402
                                fit_colour_matrix, reference_chart_srgb)
from calibration.light import angular_error_deg, correct_normals, fit_light_model, sphere_normals  # noqa: E402


def normalize(d: np.ndarray) -> np.ndarray:
    return d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)


def ratio(folder: Path, cid: str, M: np.ndarray) -> np.ndarray:
    from pipeline.codecs.raw import decode_raw

    frames = []
    for illumination in ("pos", "neg"):
        rgb = decode_raw(folder / illumination / f"{cid}.dng").rgb
        frames.append(apply_colour_matrix(rgb, M, out=rgb))
    return (frames[0] - frames[1]) / np.maximum(frames[0] + frames[1], 1e-6)


def run_level(led_error: float, width: int, cameras: int, work: Path, **sim_changes) -> dict:
    from scipy import ndimage

    from pipeline.codecs.exr import read_exr
    from pipeline.codecs.raw import decode_raw
    from synthetic import SimConfig, simulate
    from synthetic.calibration import CalibrationConfig

    config = SimConfig(actions=1, width=width, n_cameras=cameras, led_error=led_error, background=False,
                       **sim_changes)
    started = time.perf_counter()
    capture = simulate(work / f"cap_{led_error}", config, calibration=CalibrationConfig())
    sim_s = time.perf_counter() - started
    session = capture / "sessions" / "S000"
    rig = json.loads((session / "rig.json").read_text())
    chart = json.loads((session / "calibration" / "chart.json").read_text())
    sphere = rig["calibration_objects"]["sphere"]
    _, reference = reference_chart_srgb()

    de_before, de_after, d_parts, n_parts, matrices = [], [], [], [], {}
    for camera in rig["cameras"]:
        cid, white = camera["camera_id"], np.asarray(camera["white_reference"])
        image = decode_raw(session / chart["cameras"][cid]["frame"]).rgb
        labels = np.zeros(image.shape[:2], np.int64)
        for k, (x0, y0, x1, y1) in enumerate(chart["cameras"][cid]["patch_boxes"]):
            labels[y0:y1, x0:x1] = k + 1
        means, _ = chart_patch_means(image, labels, erode=2)
        M = fit_colour_matrix(means, white * reference)
        matrices[cid] = M
        de_before.append(delta_e_2000(means / white, reference).mean())
        de_after.append(delta_e_2000(means @ M.T / white, reference).mean())
        d = ratio(session / "calibration" / "sphere", cid, M)
        normals, mask = sphere_normals(np.asarray(camera["K"]), np.asarray(camera["cam_from_world"]),
                                       camera["width"], camera["height"], sphere["centre"], sphere["radius_m"])
        mask = ndimage.binary_erosion(mask, iterations=2)
        d_parts.append(d[mask])
        n_parts.append(normals[mask])
    model = fit_light_model(np.concatenate(d_parts[0::2]), np.concatenate(n_parts[0::2]), degree=2)
    d_test, n_test = np.concatenate(d_parts[1::2]), np.concatenate(n_parts[1::2])

    subject = {"all": ([], []), "unoccluded": ([], [])}
    truth = capture / "ground_truth" / "A0000"
    for camera in rig["cameras"]:
        cid = camera["camera_id"]
        d = ratio(capture / "actions" / "A0000", cid, matrices[cid])
        normals = read_exr(truth / "normal" / f"{cid}.exr")
        mask = ndimage.binary_erosion(read_exr(truth / "visibility" / f"{cid}.exr") > 0, iterations=2)
        solid = mask & (read_exr(truth / "visibility" / f"{cid}.exr") > 0.95)
        corrected = correct_normals(d, model, mask=mask)
        for name, sel in (("all", mask), ("unoccluded", solid)):
            subject[name][0].append(angular_error_deg(normalize(d[sel]), normals[sel]))
            subject[name][1].append(angular_error_deg(corrected[sel], normals[sel]))

    return {
        "led_error": led_error, "simulate_s": round(sim_s, 2),
        "chart_de2000": {"before": float(np.mean(de_before)), "after": float(np.mean(de_after))},
        "light_model": model.to_json(),
        "sphere_heldout_deg": {"pixels": int(len(d_test)),
                               "uncorrected": float(angular_error_deg(normalize(d_test), n_test).mean()),
                               "corrected": float(angular_error_deg(correct_normals(d_test, model), n_test).mean())},
        "subject_deg": {name: {"pixels": int(sum(len(e) for e in before)),
                               "uncorrected": float(np.concatenate(before).mean()),
                               "corrected": float(np.concatenate(after).mean())}
                        for name, (before, after) in subject.items()},
        "_model": model, "_test": (d_test, n_test),
    }


def best_of(fn, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        times.append(time.perf_counter() - started)
    return min(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--cameras", type=int, default=16)
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    if args.quick:
        args.width, args.cameras = 96, 4
    pixels, repeats = (1 << 14, 1) if args.quick else (1 << 20, 3)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    levels = []
    with tempfile.TemporaryDirectory() as tmp:
        for led_error in (0.03, 0.1):
            levels.append(run_level(led_error, args.width, args.cameras, Path(tmp),
                                    **(quick_sim_changes() if args.quick else {})))
            print(json.dumps({k: v for k, v in levels[-1].items() if not k.startswith("_") and k != "light_model"}),
                  flush=True)

    model = levels[-1]["_model"]
    d_test, n_test = levels[-1]["_test"]
    rng = np.random.default_rng(0)
    d_big = d_test[rng.integers(0, len(d_test), pixels)]
    timing = {"pixels": len(d_big), "normalize_s": best_of(lambda: normalize(d_big), repeats)}
    iterations = (2, 4, 6)
    for it in iterations:
        timing[f"gauss_newton_{it}_s"] = best_of(lambda: correct_normals(d_big, model, iterations=it), repeats)
        timing[f"gauss_newton_{it}_heldout_deg"] = float(
            angular_error_deg(correct_normals(d_test, model, iterations=it), n_test).mean())
    print(json.dumps(timing), flush=True)

    result = {"bench": "light", "width": args.width, "cameras": args.cameras, "quick": args.quick,
              "levels": [{k: v for k, v in level.items() if not k.startswith("_")} for level in levels],
              "correction_timing": timing}
    (out / "bench_light.json").write_text(json.dumps(result, indent=1))

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    labels, before, after = [], [], []
    for level in levels:
        for name, record in (("sphere (held-out cams)", level["sphere_heldout_deg"]),
                             ("subject, unoccluded", level["subject_deg"]["unoccluded"]),
                             ("subject, all", level["subject_deg"]["all"])):
            labels.append(f"{name}\nled_error {level['led_error']}")
            before.append(record["uncorrected"])
            after.append(record["corrected"])
    x = np.arange(len(labels))
    axes[0].bar(x - 0.2, before, 0.4, label="normalize(d)")
    axes[0].bar(x + 0.2, after, 0.4, label="light-calibrated")
    axes[0].set_xticks(x, labels, rotation=60, ha="right", fontsize=7)
    axes[0].set_ylabel("mean angular error (deg)")
    axes[0].legend()
    axes[0].set_title("normal error vs ground truth")
    secs = [timing["normalize_s"]] + [timing[f"gauss_newton_{it}_s"] for it in iterations]
    errs = [levels[-1]["sphere_heldout_deg"]["uncorrected"]] + [timing[f"gauss_newton_{it}_heldout_deg"]
                                                                 for it in iterations]
    axes[1].plot(np.array(secs) / (timing["pixels"] / 1e6), errs, "o-")
    for s, e, name in zip(secs, errs, ["normalize"] + [f"GN {it}" for it in iterations]):
        axes[1].annotate(name, (s / (timing["pixels"] / 1e6), e))
    axes[1].set_xlabel("seconds per megapixel (1 thread)")
    axes[1].set_ylabel("held-out sphere error (deg), led_error 0.1")
    axes[1].set_title("time vs error of the correction")
    fig.tight_layout()
    fig.savefig(out / "bench_light.png", dpi=110)
    print(f"wrote {out / 'bench_light.json'} and bench_light.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
