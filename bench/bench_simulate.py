"""Simulator: wall time of the default capture, and what its shortcuts cost in accuracy.

1. `simulate()` with the default SimConfig (2 actions, 32 cameras, 320 x 480, 512 LEDs) into a temporary
   folder: total wall time and the time of each phase (from the progress messages).
2. Specular LED clusters (SimConfig.specular_led_clusters) against exact per-LED GGX (the default):
   one action, 8 cameras, rendered both ways; time per camera and the error of the clustered radiance
   (PSNR in decoded units, peak 1.0; relative RMS).
3. The gradient-ratio normals n = normalize((pos - neg) / (pos + neg)) against the ground-truth normals
   on pre-sensor radiance (no noise, no demosaicing): ideal Lambertian LEDs, + LED errors, + specular,
   split by ground-truth visibility; and on the rawpy-decoded DNGs of part 1 (noise and demosaicing).
4. Pixel integration (SimConfig.supersample): time per camera and error of the radiance and the true
   normals with 1 ray per pixel and with the default s x s, against 4 x 4 rays per pixel (the pixel
   integral, nearly converged), one action, 8 cameras.
5. The GGX shading's fused C loop (:mod:`synthetic.kernels`) against the numpy steps it replaces, in the same
   process: the exact per-LED renders of part 2's cameras both ways, seconds per camera, their ratio
   (``x_numpy``) and whether the radiance is the same to the bit.

    python bench/bench_simulate.py --out bench/out [--quick]

``--quick`` (the tests' mode): every part on a capture of 1 action, 8 cameras 64 px wide, 128 LEDs and the
subject unsubdivided, cameras 0 and 4; the numbers are not measurements.
"""
from __future__ import annotations

import argparse
import dataclasses
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
from synthetic import SimConfig, simulate  # noqa: E402
from synthetic import geometry, shading  # noqa: E402
from synthetic.simulate import make_session, prepare_action  # noqa: E402
from synthetic.subject import load_base_subject, resolve_mesh  # noqa: E402
from synthetic.threads import limit_blas_threads  # noqa: E402

VIS_BINS = ((0.0, 0.5), (0.5, 0.9), (0.9, 0.99), (0.99, 1.01))


def angular_error_deg(radiance: np.ndarray, normals: np.ndarray) -> np.ndarray:
    pos, neg = radiance[..., 3:6], radiance[..., 6:9]
    d = geometry.normalize((pos - neg) / np.maximum(pos + neg, 1e-12))
    return np.degrees(np.arccos(np.clip(np.sum(d * normals, axis=-1), -1.0, 1.0)))


def time_default_capture(work: Path, config: SimConfig) -> dict:
    stamps: list[tuple[float, str]] = []
    start = time.perf_counter()
    simulate(work / "capture", config, progress=lambda m: stamps.append((time.perf_counter() - start, m)))
    total = time.perf_counter() - start
    phases, previous = [], 0.0
    for t, message in stamps:
        phases.append({"until_s": round(t, 2), "took_s": round(t - previous, 2), "message": message})
        previous = t
    return {"config": config.to_json(), "total_s": round(total, 2), "phases": phases}


def specular_clusters_vs_exact(config: SimConfig, cameras: list[int]) -> dict:
    mesh_path = resolve_mesh(config.mesh)
    base = load_base_subject(str(mesh_path) if mesh_path else None, config.subdivisions if mesh_path else 0)
    session = make_session(config, base, 0)
    subject, scene, _ = prepare_action(config, base, session, 0)
    visible = shading.vertex_visibility(scene, subject.vertices_world, subject.normals_world,
                                        session.leds.directions)
    result = {"subject": subject.label, "cameras": len(cameras)}
    renders = {}
    for name, levels in (("clusters", shading.CLUSTER_LEVELS), ("exact", shading.EXACT_LEVELS)):
        lighting = shading.surface_lighting(visible, subject.normals_world, session.leds, levels=levels)
        start = time.perf_counter()
        renders[name] = [shading.render_view(scene, subject, lighting, session.leds, session.cameras[c])
                         for c in cameras]
        result[f"{name}_s_per_camera"] = round((time.perf_counter() - start) / len(cameras), 4)
    squared, reference = [], []
    for c, approx, exact in zip(cameras, renders["clusters"], renders["exact"]):
        gain = session.gains[c]
        squared.append(((approx.radiance - exact.radiance)[exact.mask] * gain) ** 2)
        reference.append((exact.radiance[exact.mask] * gain) ** 2)
    mse = float(np.mean(np.concatenate(squared)))
    result["psnr_db"] = round(10 * np.log10(1.0 / max(mse, 1e-20)), 2)
    result["relative_rms"] = round(float(np.sqrt(mse / np.mean(np.concatenate(reference)))), 5)
    return result


def fused_ggx_vs_numpy(config: SimConfig, cameras: list[int]) -> dict:
    """Part 5: the exact per-LED renders of ``cameras`` with the fused GGX loop and with the numpy steps."""
    from synthetic import kernels

    if not kernels.kernel_available():
        return {"skipped": "no C compiler: only the numpy steps run here"}
    mesh_path = resolve_mesh(config.mesh)
    base = load_base_subject(str(mesh_path) if mesh_path else None, config.subdivisions if mesh_path else 0)
    session = make_session(config, base, 0)
    subject, scene, lighting = prepare_action(dataclasses.replace(config, specular_led_clusters=False), base,
                                              session, 0)
    renders, seconds = {}, {}
    available = kernels.kernel_available
    for name in ("fused", "numpy"):
        kernels.kernel_available = available if name == "fused" else (lambda: False)
        try:
            start = time.perf_counter()
            renders[name] = [shading.render_view(scene, subject, lighting, session.leds, session.cameras[c])
                             for c in cameras]
            seconds[name] = (time.perf_counter() - start) / len(cameras)
        finally:
            kernels.kernel_available = available
    same = all(np.array_equal(a.radiance.view(np.uint32), b.radiance.view(np.uint32))
               for a, b in zip(renders["fused"], renders["numpy"]))
    return {"cameras": len(cameras), "fused_s_per_camera": round(seconds["fused"], 4),
            "numpy_s_per_camera": round(seconds["numpy"], 4),
            "x_numpy": round(seconds["numpy"] / max(seconds["fused"], 1e-9), 2), "same_bits": bool(same)}


def pixel_integration(config: SimConfig, cameras: list[int], reference: int = 4) -> dict:
    """Radiance PSNR (decoded units, peak 1) and normal error of s rays per pixel side against ``reference``."""
    mesh_path = resolve_mesh(config.mesh)
    base = load_base_subject(str(mesh_path) if mesh_path else None, config.subdivisions if mesh_path else 0)
    session = make_session(config, base, 0)
    subject, scene, lighting = prepare_action(config, base, session, 0)
    renders, result = {}, {"cameras": len(cameras), "reference_rays_per_side": reference}
    for s in sorted({1, config.supersample, reference}):
        start = time.perf_counter()
        renders[s] = [shading.render_view(scene, subject, lighting, session.leds, session.cameras[c],
                                          background=session.backgrounds[c], supersample=s) for c in cameras]
        result[f"s{s}_s_per_camera"] = round((time.perf_counter() - start) / len(cameras), 4)
    for s in sorted({1, config.supersample}):
        squared, angles = [], []
        for c, view, ref in zip(cameras, renders[s], renders[reference]):
            squared.append(((view.radiance - ref.radiance) * session.gains[c]).ravel() ** 2)
            both = view.mask & ref.mask
            cos = np.clip(np.sum(view.normals_world[both] * ref.normals_world[both], axis=-1), -1.0, 1.0)
            angles.append(np.degrees(np.arccos(cos)))
        mse = float(np.mean(np.concatenate(squared)))
        result[f"s{s}_radiance_psnr_db"] = round(10 * np.log10(1.0 / max(mse, 1e-20)), 2)
        result[f"s{s}_normal_mean_deg"] = round(float(np.concatenate(angles).mean()), 3)
    return result


def ratio_normal_errors(base_config: SimConfig, cameras: list[int]) -> dict:
    variants = {"lambert_ideal_leds": dict(led_error=0.0, specular=False),
                "lambert_led_error": dict(specular=False),
                "lambert_plus_ggx (default)": dict()}
    out = {}
    for name, overrides in variants.items():
        config = dataclasses.replace(base_config, **overrides)
        mesh_path = resolve_mesh(config.mesh)
        base = load_base_subject(str(mesh_path) if mesh_path else None, config.subdivisions if mesh_path else 0)
        session = make_session(config, base, 0)
        subject, scene, lighting = prepare_action(config, base, session, 0)
        errors, vis = [], []
        for c in cameras:
            view = shading.render_view(scene, subject, lighting, session.leds, session.cameras[c],
                                       specular=config.specular)
            errors.append(angular_error_deg(view.radiance, view.normals_world)[view.mask])
            vis.append(view.visibility[view.mask])
        out[name] = summarise(np.concatenate(errors), np.concatenate(vis))
    return out


def summarise(errors: np.ndarray, visibility: np.ndarray) -> dict:
    record = {"all": {"mean_deg": round(float(errors.mean()), 3), "median_deg": round(float(np.median(errors)), 3),
                      "pixels": int(len(errors))}}
    for lo, hi in VIS_BINS:
        sel = (visibility >= lo) & (visibility < hi)
        if sel.any():
            record[f"visibility {lo:.2f}-{min(hi, 1.0):.2f}"] = {"mean_deg": round(float(errors[sel].mean()), 3),
                                                              "pixels": int(sel.sum())}
    return record


def decoded_capture_errors(capture: Path, cameras: list[int]) -> dict:
    import rawpy

    from pipeline.codecs.exr import read_exr
    from pipeline.codecs.image import read_png

    errors, vis = [], []
    for c in cameras:
        cam = f"{c:05d}"
        planes = []
        for illumination in ("full_on", "pos", "neg"):
            with rawpy.imread(str(capture / "actions" / "A0000" / illumination / f"{cam}.dng")) as raw:
                planes.append(raw.postprocess(use_camera_wb=True, output_color=rawpy.ColorSpace.sRGB,
                                              gamma=(1, 1), no_auto_bright=True, output_bps=16,
                                              user_flip=0).astype(np.float32) / 65535.0)
        truth = capture / "ground_truth" / "A0000"
        mask = read_png(truth / "mask" / f"{cam}.png") > 0
        normals = read_exr(truth / "normal" / f"{cam}.exr")
        errors.append(angular_error_deg(np.concatenate(planes, axis=-1), normals)[mask])
        vis.append(read_exr(truth / "visibility" / f"{cam}.exr")[mask])
    return summarise(np.concatenate(errors), np.concatenate(vis))


def plot(result: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    variants = dict(result["ratio_normals_presensor"])
    variants["decoded DNG (noise, AHD)"] = result["ratio_normals_decoded"]
    labels = [k for k in next(iter(variants.values())) if k.startswith("visibility")]
    width = 0.8 / len(variants)
    for i, (name, rec) in enumerate(variants.items()):
        axes[0].bar(np.arange(len(labels)) + i * width, [rec.get(k, {}).get("mean_deg", np.nan) for k in labels],
                    width, label=name)
    axes[0].set_xticks(np.arange(len(labels)) + 0.4 - width / 2, labels, rotation=15, fontsize=8)
    axes[0].set_ylabel("mean ratio-normal error (deg)")
    axes[0].legend(fontsize=7)
    axes[0].set_title("gradient-ratio normals vs ground truth")
    spec = result["specular_clusters_vs_exact"]
    axes[1].bar(["clusters", "exact"], [spec["clusters_s_per_camera"], spec["exact_s_per_camera"]])
    axes[1].set_ylabel("render time per camera (s)")
    axes[1].set_title(f"specular LED clusters: PSNR {spec['psnr_db']} dB vs exact")
    fig.tight_layout()
    fig.savefig(out / "bench_simulate.png", dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    config = SimConfig()
    if args.quick:
        config = dataclasses.replace(config, actions=1, n_cameras=8, width=64, **quick_sim_changes())
    cameras = list(range(0, config.n_cameras, 4))
    with tempfile.TemporaryDirectory() as tmp:
        result = {"quick": args.quick, "default_capture": time_default_capture(Path(tmp), config)}
        print(f"default simulate(): {result['default_capture']['total_s']} s", flush=True)
        result["ratio_normals_decoded"] = decoded_capture_errors(Path(tmp) / "capture", cameras)
    with limit_blas_threads(1):  # as simulate() runs
        result["specular_clusters_vs_exact"] = specular_clusters_vs_exact(config, cameras)
        print(f"specular clusters vs exact: {result['specular_clusters_vs_exact']}", flush=True)
        result["ratio_normals_presensor"] = ratio_normal_errors(config, cameras)
        result["pixel_integration"] = pixel_integration(config, cameras)
        print(f"pixel integration: {result['pixel_integration']}", flush=True)
        result["fused_ggx_vs_numpy"] = fused_ggx_vs_numpy(config, cameras)
        print(f"fused GGX loop vs numpy steps: {result['fused_ggx_vs_numpy']}", flush=True)
    (out / "bench_simulate.json").write_text(json.dumps(result, indent=1) + "\n")
    plot(result, out)
    print(json.dumps({k: v for k, v in result.items() if k not in ("default_capture", "quick")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
