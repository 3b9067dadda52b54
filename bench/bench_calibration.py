"""Geometric calibration on a simulated light-stage capture: pose and intrinsics error against the rig's
ground truth, per SIFT extraction resolution.

The simulator renders one action (32 cameras around a MakeHuman subject, ~3 m away) as raw DNGs; the
full_on frames are decoded (pipeline.codecs.raw) to 8-bit sRGB PNG and calibrated with
:func:`calibration.geometric.calibrate_images`: the rig's K as intrinsics prior and the rig's camera
centres as the known centres of the similarity alignment (stage frame, metres). Two prior modes:
``fixed`` (PINHOLE, the prior K kept) and ``refined`` (PINHOLE, focal lengths refined from the prior,
which measures the focal error). Errors are measured in the stage frame after that alignment
(rotation degrees, centre mm) and again after a least-squares re-alignment (``*_refit``), plus
reprojection error (px), registered cameras and wall time. The capture and the PNGs are cached under
``OUT/cache``.

    python bench/bench_calibration.py --out bench/out [--width 640] [--sizes 480,640,-1] [--centre-noise-mm 0]
    python bench/bench_calibration.py --out bench/out --quick   # the tests' mode: not measurements
    python bench/bench_calibration.py --rig-prior --widths 320,640   # calibrate_rig: nominal vs refined

``--quick`` runs the default mode on a capture 240 px wide (128 LEDs, the subject unsubdivided) at full
resolution only.

``--rig-prior`` benchmarks :func:`calibration.geometric.calibrate_rig` instead: it starts from the rig
spec's NOMINAL cameras and is measured against the TRUE cameras (ground_truth/cameras/S000.json), in the
stage frame: rotation (deg), centre (mm), focal (%) of the nominal and of the refined cameras, and time.

    python bench/bench_calibration.py --target --widths 320,640

``--target`` calibrates on the simulator's geometric calibration target (a speckled cylinder,
``sessions/S000/calibration/cameras/<cam>.dng``, synthetic.calibration) with the pipeline's conventions
(decoded and exposed to 8-bit as stages/cameras.py does): the nominal rig, ``calibrate_images`` (rig K
priors, PINHOLE, focal refined, aligned to the NOMINAL rig centres as the ``cameras`` stage does) and
``calibrate_rig`` (from the nominal cameras), each against the TRUE cameras: rotation (deg), centre (mm)
and focal (%) in the stage frame as published, and rotation / centre after an optimal similarity to the
truth (``*_sim``), registered cameras, reprojection error (px) and time.

    python bench/bench_calibration.py --markers --widths 160,320,640 [--capture DIR]

``--markers`` (what ``make bench`` runs, at width 320) calibrates from the simulator's marker frame (white balls at surveyed positions filling the
capture volume, ``sessions/S000/calibration/markers/<cam>.dng``, :mod:`calibration.markers`) as the
``cameras`` stage does (decode, grey in white units, 1 thread), against the TRUE cameras in the stage
frame: the rig spec; ``markers`` (the default: surveyed balls define the frame, focal free);
``markers_rig_frame`` (frame placement unknown: cameras moved rigidly onto the nominal centres);
``markers_fixed_focal`` (focal kept at the rig spec's); and ``floor_nominal_gauge``: the TRUE cameras
mapped onto the nominal centres by the best similarity, i.e. what any calibration aligned to the rig
spec's centres cannot beat. Reprojection errors are over the balls the calibration identified (for the
rig spec: the same observations projected with the nominal cameras). ``--capture`` uses an existing
capture (e.g. ``ultrastage simulate --out DIR``) for width 320 instead of rendering one. Each calibration's
``seconds`` include decoding its 32 marker frames (``decode_s``), timed in the same process: ``x_decode`` is the
calibration's time as a multiple of that decode, the floor of any method that reads the frames.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _quick import QUICK_HELP, quick_sim_changes  # noqa: E402
from calibration.geometric import GeometricConfig, calibrate_images, camera_centre, pose_errors  # noqa: E402


QUICK_CALIBRATION_WIDTH = 240


def capture(cache: Path, width: int, quick: bool = False) -> Path:
    """Simulated capture (one action) at ``width``, rendered once and reused; ``quick``: with
    :func:`_quick.quick_sim_changes` (cached apart)."""
    from synthetic import SimConfig, simulate

    out = cache / (f"capture_w{width}" + ("_quick" if quick else ""))
    if not (out / "sessions" / "S000" / "rig.json").is_file():
        t0 = time.perf_counter()
        simulate(out, SimConfig(actions=1, width=width, background=False, **(quick_sim_changes() if quick else {})))
        print(f"simulated {out} in {time.perf_counter() - t0:.1f} s", flush=True)
    return out


def pngs(capture_dir: Path, cache: Path, width: int, quick: bool = False) -> list[Path]:
    """full_on frames of action A0000 as 8-bit sRGB PNGs (auto exposure), cached."""
    from pipeline.codecs.image import preview_linear, write_png
    from pipeline.codecs.raw import decode_raw

    out = cache / (f"png_w{width}" + ("_quick" if quick else ""))
    paths = []
    for dng in sorted((capture_dir / "actions" / "A0000" / "full_on").glob("*.dng")):
        png = out / f"{dng.stem}.png"
        if not png.is_file():
            write_png(png, preview_linear(decode_raw(dng).rgb))
        paths.append(png)
    return paths


def rig_prior(out: Path, widths: list[int], threads: int) -> None:
    """calibrate_rig at each width: errors of the nominal and the refined cameras against the truth."""
    from calibration.geometric import RigRefineConfig, calibrate_rig

    cache = out / "cache"
    rows = []
    for width in widths:
        cap = capture(cache, width)
        nominal = json.loads((cap / "sessions" / "S000" / "rig.json").read_text())["cameras"]
        true = json.loads((cap / "ground_truth" / "cameras" / "S000.json").read_text())["cameras"]
        NK = {f"{c['camera_id']}.dng": np.asarray(c["K"], float) for c in nominal}
        NP = {f"{c['camera_id']}.dng": np.asarray(c["cam_from_world"], float) for c in nominal}
        TK = {f"{c['camera_id']}.dng": np.asarray(c["K"], float) for c in true}
        TP = {f"{c['camera_id']}.dng": np.asarray(c["cam_from_world"], float) for c in true}
        paths = sorted((cap / "actions" / "A0000" / "full_on").glob("*.dng"))
        t0 = time.perf_counter()
        res = calibrate_rig(paths, cache / f"rig_work_w{width}", NK, NP,
                            GeometricConfig(camera_model="PINHOLE", num_threads=threads), RigRefineConfig())
        seconds = time.perf_counter() - t0
        row = {"method": "rig_prior", "width": width, "registered": len(res.cameras), "cameras": len(paths),
               "seconds": seconds, "reprojection_error_px": res.reprojection_error_px, "n_points3d": res.n_points3d,
               "alignment_residual_mm": res.alignment_residual_mm, "notes": res.notes}
        for tag, P, K in (("nominal", {n: NP[n] for n in res.cameras}, NK),
                          ("refined", {n: c.cam_from_world for n, c in res.cameras.items()},
                           {n: c.K for n, c in res.cameras.items()})):
            if not P:
                continue
            e = pose_errors(P, TP, align=False)
            focal = [100.0 * abs(K[n][0, 0] / TK[n][0, 0] - 1) for n in P]
            row.update({f"{tag}_rotation_deg_mean": e["rotation_deg_mean"], f"{tag}_rotation_deg_max": e["rotation_deg_max"],
                        f"{tag}_centre_mm_mean": e["centre_error_mm_mean"], f"{tag}_centre_mm_max": e["centre_error_mm_max"],
                        f"{tag}_focal_pct_mean": float(np.mean(focal))})
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "notes"}), flush=True)
    report = {"bench": "calibration_rig_prior", "goal": "rotation < 0.05 deg and centre < 1 mm", "rows": rows}
    (out / "bench_calibration_rig.json").write_text(json.dumps(report, indent=1))
    print(f"wrote {out / 'bench_calibration_rig.json'}")


def target_capture(cache: Path, width: int) -> Path:
    """Simulated capture with the geometric calibration target (one action), rendered once and reused."""
    from synthetic import SimConfig, simulate
    from synthetic.calibration import CalibrationConfig

    out = cache / f"target_w{width}"
    if not (out / "capture.json").is_file():
        t0 = time.perf_counter()
        simulate(out, SimConfig(actions=1, width=width, background=False),
                 calibration=CalibrationConfig(chart=False, sphere=False))
        print(f"simulated {out} in {time.perf_counter() - t0:.1f} s", flush=True)
    return out


def stage_pngs(cap: Path, out: Path) -> list[Path]:
    """The target frames as the cameras stage feeds them to SIFT: decoded, white at 0.8, sRGB 8-bit."""
    from pipeline.codecs.image import srgb_encode, write_png
    from pipeline.codecs.raw import decode_raw

    rig = {c["camera_id"]: c for c in json.loads((cap / "sessions" / "S000" / "rig.json").read_text())["cameras"]}
    paths = []
    for dng in sorted((cap / "sessions" / "S000" / "calibration" / "cameras").glob("*.dng")):
        png = out / f"{dng.stem}.png"
        if not png.is_file():
            white = float(max(rig[dng.stem]["white_reference"]))
            rgb = decode_raw(dng).rgb
            write_png(png, (srgb_encode(rgb * (0.8 / white)) * 255.0 + 0.5).astype(np.uint8))
        paths.append(png)
    return paths


def target_bench(out: Path, widths: list[int], threads: int) -> None:
    """Nominal rig vs calibrate_images vs calibrate_rig on the calibration target, against the truth."""
    from calibration.geometric import RigRefineConfig, calibrate_rig

    cache = out / "cache"
    rows = []
    for width in widths:
        cap = target_capture(cache, width)
        images = stage_pngs(cap, cache / f"target_png_w{width}")
        nominal = json.loads((cap / "sessions" / "S000" / "rig.json").read_text())["cameras"]
        true = json.loads((cap / "ground_truth" / "cameras" / "S000.json").read_text())["cameras"]
        NK = {f"{c['camera_id']}.png": np.asarray(c["K"], float) for c in nominal}
        NP = {f"{c['camera_id']}.png": np.asarray(c["cam_from_world"], float) for c in nominal}
        TK = {f"{c['camera_id']}.png": np.asarray(c["K"], float) for c in true}
        TP = {f"{c['camera_id']}.png": np.asarray(c["cam_from_world"], float) for c in true}
        centres = {n: camera_centre(P) for n, P in NP.items()}
        config = GeometricConfig(camera_model="PINHOLE", refine_focal_length=True, refine_principal_point=False,
                                 refine_extra_params=False, num_threads=threads)
        runs = [("nominal", None)]
        runs.append(("calibrate_images", lambda: calibrate_images(images, cache / f"target_work_w{width}", config,
                                                                  intrinsics_prior=NK, known_centres=centres)))
        runs.append(("calibrate_rig", lambda: calibrate_rig(images, cache / f"target_rig_w{width}", NK, NP,
                                                            GeometricConfig(camera_model="PINHOLE", num_threads=threads),
                                                            RigRefineConfig())))
        for method, run in runs:
            row: dict = {"method": method, "width": width, "cameras": len(images)}
            if run is None:
                P, K = NP, NK
                row.update({"registered": len(P), "seconds": 0.0})
            else:
                t0 = time.perf_counter()
                try:
                    res = run()
                except RuntimeError as exc:
                    rows.append(row | {"error": str(exc)})
                    print(json.dumps(rows[-1]), flush=True)
                    continue
                P = {n: c.cam_from_world for n, c in res.cameras.items()}
                K = {n: c.K for n, c in res.cameras.items()}
                row.update({"registered": len(P), "seconds": time.perf_counter() - t0,
                            "reprojection_error_px": res.reprojection_error_px, "n_points3d": res.n_points3d,
                            "alignment_residual_mm": res.alignment_residual_mm, "aligned": res.aligned,
                            "notes": res.notes})
            if len(P) >= 3:
                stage, sim = pose_errors(P, TP, align=False), pose_errors(P, TP, align=True)
                focal = [100.0 * abs(K[n][0, 0] / TK[n][0, 0] - 1) for n in P]
                row.update({"rotation_deg_mean": stage["rotation_deg_mean"], "rotation_deg_max": stage["rotation_deg_max"],
                            "centre_mm_mean": stage["centre_error_mm_mean"], "centre_mm_max": stage["centre_error_mm_max"],
                            "rotation_deg_mean_sim": sim["rotation_deg_mean"], "rotation_deg_max_sim": sim["rotation_deg_max"],
                            "centre_mm_mean_sim": sim["centre_error_mm_mean"], "centre_mm_max_sim": sim["centre_error_mm_max"],
                            "focal_pct_mean": float(np.mean(focal)), "focal_pct_max": float(np.max(focal))})
            rows.append(row)
            print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items() if k != "notes"}),
                  flush=True)
    report = {"bench": "calibration_target", "goal": "rotation < 0.05 deg and centre < 1 mm at width 320, all registered",
              "rows": rows}
    (out / "bench_calibration_target.json").write_text(json.dumps(report, indent=1, default=float))
    print(f"wrote {out / 'bench_calibration_target.json'}")


def markers_capture(cache: Path, width: int) -> Path:
    """Simulated capture with only the marker-frame calibration frames (one action), rendered once."""
    from synthetic import SimConfig, simulate
    from synthetic.calibration import CalibrationConfig

    out = cache / f"markers_w{width}"
    if not (out / "capture.json").is_file():
        t0 = time.perf_counter()
        simulate(out, SimConfig(actions=1, width=width, background=False),
                 calibration=CalibrationConfig(chart=False, sphere=False, target=False))
        print(f"simulated {out} in {time.perf_counter() - t0:.1f} s", flush=True)
    return out


def markers_bench(out: Path, widths: list[int], capture_dir: Path | None = None) -> list[dict]:
    """Rig spec vs marker-frame calibration (three variants) vs the nominal-gauge floor, per width."""
    from calibration.geometric import transform_cam_from_world, umeyama
    from calibration.markers import MarkerCalibrationConfig, calibrate_markers, project_points
    from pipeline.codecs.raw import decode_raw
    from synthetic.threads import limit_blas_threads

    rows = []
    for width in widths:
        cap = capture_dir if (capture_dir is not None and width == 320) else markers_capture(out / "cache", width)
        rig = json.loads((cap / "sessions" / "S000" / "rig.json").read_text())
        nominal = {c["camera_id"]: c for c in rig["cameras"]}
        true = {c["camera_id"]: c for c in json.loads((cap / "ground_truth" / "cameras" / "S000.json").read_text())["cameras"]}
        spec = rig["calibration_objects"]["markers"]
        NK = {c: np.asarray(v["K"], float) for c, v in nominal.items()}
        NP = {c: np.asarray(v["cam_from_world"], float) for c, v in nominal.items()}
        TK = {c: np.asarray(v["K"], float) for c, v in true.items()}
        TP = {c: np.asarray(v["cam_from_world"], float) for c, v in true.items()}

        def measure(method: str, P: dict, K: dict, seconds: float, reprojection: float | None, **extra) -> None:
            stage, sim = pose_errors(P, TP, align=False), pose_errors(P, TP, align=True)
            focal = [100.0 * abs(K[n][0, 0] / TK[n][0, 0] - 1) for n in P]
            row = {"method": method, "width": width, "cameras": len(TP), "registered": len(P), "seconds": seconds,
                   "rotation_deg_mean": stage["rotation_deg_mean"], "rotation_deg_max": stage["rotation_deg_max"],
                   "centre_mm_mean": stage["centre_error_mm_mean"], "centre_mm_max": stage["centre_error_mm_max"],
                   "rotation_deg_mean_sim": sim["rotation_deg_mean"], "centre_mm_mean_sim": sim["centre_error_mm_mean"],
                   "focal_pct_mean": float(np.mean(focal)), "focal_pct_max": float(np.max(focal)),
                   "reprojection_px": reprojection} | extra
            rows.append(row)
            print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}), flush=True)

        with limit_blas_threads(1):
            t0 = time.perf_counter()
            images = {}
            for cam in sorted(nominal):
                rgb = decode_raw(cap / "sessions" / "S000" / "calibration" / "markers" / f"{cam}.dng").rgb
                images[cam] = rgb.mean(axis=-1) / float(np.mean(nominal[cam]["white_reference"]))
            decode_s = time.perf_counter() - t0
            results = {}
            for method, config in (("markers", MarkerCalibrationConfig()),
                                   ("markers_rig_frame", MarkerCalibrationConfig(frame="rig")),
                                   ("markers_fixed_focal", MarkerCalibrationConfig(refine_focal_length=False))):
                t0 = time.perf_counter()
                results[method] = (calibrate_markers(images, NK, NP, np.asarray(spec["positions"], float),
                                                     float(spec["radius_m"]), config), time.perf_counter() - t0)
        # the rig spec's reprojection error on the observations the default calibration identified
        rec = results["markers"][0].reconstruction
        markers_world = np.asarray(spec["positions"], float)
        errors = []
        for image_id in rec.reg_image_ids():
            image = rec.image(image_id)
            observed = np.array([p.xy for p in image.points2D]) - 0.5
            ids = [int(np.argmin(np.linalg.norm(markers_world - rec.point3D(p.point3D_id).xyz, axis=1)))
                   for p in image.points2D]
            errors.append(np.linalg.norm(project_points(NK[image.name], NP[image.name], markers_world[ids]) - observed,
                                         axis=1))
        measure("rig_spec", NP, NK, 0.0, float(np.mean(np.concatenate(errors))))
        for method, (res, seconds) in results.items():
            measure(method, {n: c.cam_from_world for n, c in res.cameras.items()}, {n: c.K for n, c in res.cameras.items()},
                    decode_s + seconds, res.reprojection_error_px, decode_s=decode_s,
                    x_decode=(decode_s + seconds) / decode_s, balls_seen=res.n_points3d, notes=res.notes)
        names = sorted(TP)
        s, R, t = umeyama(np.array([camera_centre(TP[n]) for n in names]), np.array([camera_centre(NP[n]) for n in names]))
        measure("floor_nominal_gauge", {n: transform_cam_from_world(TP[n], s, R, t) for n in names}, TK, 0.0, None)
    report = {"bench": "calibration_markers", "goal": "rotation < 0.05 deg and centre < 1 mm at width 320, all registered",
              "rows": rows}
    (out / "bench_calibration_markers.json").write_text(json.dumps(report, indent=1, default=float))
    print(f"wrote {out / 'bench_calibration_markers.json'}")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "out")
    ap.add_argument("--width", type=int, default=640, help="simulated image width (height is ~1.5x)")
    ap.add_argument("--sizes", default="480,640,-1", help="max_image_size values (-1: full resolution)")
    ap.add_argument("--modes", default="fixed,refined", help="prior modes: fixed, refined")
    ap.add_argument("--centre-noise-mm", type=float, default=0.0,
                    help="Gaussian noise (per axis) added to the known centres used for alignment")
    ap.add_argument("--threads", type=int, default=-1)
    ap.add_argument("--rig-prior", action="store_true", help="benchmark calibrate_rig (nominal vs refined)")
    ap.add_argument("--target", action="store_true",
                    help="calibrate on the simulated calibration target (nominal vs calibrate_images vs calibrate_rig)")
    ap.add_argument("--markers", action="store_true",
                    help="calibrate on the simulated marker frame (rig spec vs calibrate_markers variants)")
    ap.add_argument("--capture", type=Path, default=None, help="--markers: an existing capture to use at width 320")
    ap.add_argument("--widths", default="320,640", help="simulated widths for --rig-prior, --target and --markers")
    ap.add_argument("--quick", action="store_true", help=QUICK_HELP + "; the default mode only")
    args = ap.parse_args()
    out = args.out
    if args.quick:
        args.width, args.sizes = QUICK_CALIBRATION_WIDTH, "-1"
    if args.markers:
        out.mkdir(parents=True, exist_ok=True)
        markers_bench(out, [int(w) for w in args.widths.split(",")], args.capture)
        return
    if args.target:
        out.mkdir(parents=True, exist_ok=True)
        target_bench(out, [int(w) for w in args.widths.split(",")], args.threads)
        return
    if args.rig_prior:
        out.mkdir(parents=True, exist_ok=True)
        rig_prior(out, [int(w) for w in args.widths.split(",")], args.threads)
        return
    cache = out / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    cap = capture(cache, args.width, args.quick)
    images = pngs(cap, cache, args.width, args.quick)
    rig = json.loads((cap / "sessions" / "S000" / "rig.json").read_text())
    K = {f"{c['camera_id']}.png": np.asarray(c["K"], float) for c in rig["cameras"]}
    truth = {f"{c['camera_id']}.png": np.asarray(c["cam_from_world"], float) for c in rig["cameras"]}
    rng = np.random.default_rng(0)
    centres = {n: camera_centre(P) + rng.normal(0, args.centre_noise_mm / 1000.0, 3) for n, P in truth.items()}
    h, w = rig["cameras"][0]["height"], rig["cameras"][0]["width"]

    rows = []
    for mode in args.modes.split(","):
        for size in [int(s) for s in args.sizes.split(",")]:
            config = GeometricConfig(max_image_size=size, camera_model="PINHOLE", refine_focal_length=mode == "refined",
                                     num_threads=args.threads)
            t0 = time.perf_counter()
            try:
                res = calibrate_images(images, cache / "work", config, intrinsics_prior=K, known_centres=centres)
            except RuntimeError as exc:
                rows.append({"mode": mode, "max_image_size": size, "error": str(exc)})
                print(rows[-1], flush=True)
                continue
            seconds = time.perf_counter() - t0
            est = {n: c.cam_from_world for n, c in res.cameras.items()}
            row = {"mode": mode, "max_image_size": size, "image_size": [w, h],
                   "registered": len(res.cameras), "cameras": len(images), "unregistered": res.unregistered,
                   "reprojection_error_px": res.reprojection_error_px, "n_points3d": res.n_points3d,
                   "alignment_residual_mm": res.alignment_residual_mm, "seconds": seconds, "timings": res.timings,
                   "notes": res.notes}
            if len(est) >= 3 and res.aligned:
                stage = pose_errors(est, truth, align=False)
                refit = pose_errors(est, truth, align=True)
                focal = [100.0 * abs(c.K[0, 0] / K[n][0, 0] - 1) for n, c in res.cameras.items()]
                row.update({"rotation_deg_mean": stage["rotation_deg_mean"], "rotation_deg_max": stage["rotation_deg_max"],
                            "centre_mm_mean": stage["centre_error_mm_mean"], "centre_mm_max": stage["centre_error_mm_max"],
                            "rotation_deg_mean_refit": refit["rotation_deg_mean"],
                            "centre_mm_mean_refit": refit["centre_error_mm_mean"],
                            "focal_error_pct_mean": float(np.mean(focal)), "focal_error_pct_max": float(np.max(focal))})
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if k not in ("timings", "notes", "unregistered")}), flush=True)

    report = {"bench": "calibration", "width": args.width, "centre_noise_mm": args.centre_noise_mm, "quick": args.quick,
              "goal": "rotation < 0.05 deg and centre < 1 mm at the default resolution", "rows": rows,
              "default_max_image_size": GeometricConfig().max_image_size}
    (out / "bench_calibration.json").write_text(json.dumps(report, indent=1))
    plot(rows, out / "bench_calibration.png")
    print(f"wrote {out / 'bench_calibration.json'}")


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    for mode in sorted({r["mode"] for r in rows}):
        rs = [r for r in rows if r["mode"] == mode and "centre_mm_mean" in r]
        if not rs:
            continue
        x = [r["max_image_size"] if r["max_image_size"] > 0 else max(r["image_size"]) for r in rs]
        axes[0].plot(x, [r["rotation_deg_mean"] for r in rs], "o-", label=f"{mode} mean")
        axes[0].plot(x, [r["rotation_deg_max"] for r in rs], "x--", label=f"{mode} max")
        axes[1].plot(x, [r["centre_mm_mean"] for r in rs], "o-", label=f"{mode} mean")
        axes[1].plot(x, [r["centre_mm_max"] for r in rs], "x--", label=f"{mode} max")
        axes[2].plot([r["seconds"] for r in rs], [r["centre_mm_mean"] for r in rs], "o-", label=mode)
        for xi, r in zip(x, rs):
            axes[1].annotate(f"{r['registered']}/{r['cameras']}", (xi, r["centre_mm_mean"]), fontsize=7)
    axes[0].axhline(0.05, color="grey", lw=0.8)
    axes[1].axhline(1.0, color="grey", lw=0.8)
    axes[0].set(xlabel="max_image_size (px)", ylabel="rotation error (deg)", yscale="log")
    axes[1].set(xlabel="max_image_size (px)", ylabel="centre error (mm, stage frame)", yscale="log")
    axes[2].set(xlabel="calibration time (s)", ylabel="mean centre error (mm)", yscale="log")
    for ax in axes:
        if ax.lines:
            ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.suptitle("Geometric calibration on the simulated stage (rig K prior, aligned to rig centres)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
