"""Spherical-Gaussian environment fits: error and time against lobe count over the shared HDR maps, and the
accuracy of SG shading against brute-force quadrature.

For every map in ../shared/data/hdri (1024 x 512 equirectangular Radiance files) and every lobe count,
``fit_sg_environment`` is timed (1 thread, best of 1: fits are seconds long; ``x_sh_projection``: its ratio to the
map's order-2 SH projection, :func:`stages.numerics.sh.project_environment`, timed in the same process) and its fit
measured with ``sg_fit_errors``: relative L2 of the map (at full resolution, and area-resampled to 64 x 128), lobe energy
against map energy, and the relative error of the diffuse irradiance over 256 normals, both exactly
(quadrature of the lobes) and as ``shade_sg`` computes it (SG-cosine approximation). Suns smaller than a
texel of the 64-row fit cannot be matched by bounded-sharpness lobes, so the full-resolution map error of
sunny maps stays near 1 whatever the lobe count; the irradiance is what relighting of skin mostly sees.

The shading section renders points (normals x views x roughness) under one fitted environment with
``shade_sg`` and compares diffuse and specular with the same BRDF integrated by quadrature over the lobes'
own equirectangular map (512 x 1024). The stage section compares ``shade_stage_illuminations`` (SG lobes
and the exact GGX moment table) with the simulator's per-LED GGX under 512 LEDs, and times
``fit_roughness`` on 2000 simulator-rendered points x 8 views with the error of the recovered roughness.

``python bench/bench_sg.py --out DIR`` writes DIR/bench_sg.json, DIR/bench_sg.png (errors and time against
lobe count) and DIR/bench_sg_previews.png (tone-mapped map vs SG reconstructions). Without the shared
maps it writes a JSON saying so and exits 0. ``--quick`` (the tests' mode): one map, 8 and 32 lobes, 30 fit
iterations, 6 shading points against a 128-row quadrature, roughness fits on 200 points; the numbers are not
measurements.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
HDRI = ROOT.parent / "shared" / "data" / "hdri"


def _seconds(fn) -> float:
    started = time.perf_counter()
    fn()
    return time.perf_counter() - started


def fit_table(maps: list[Path], lobe_counts: list[int], iterations: int, fit_height: int) -> tuple[list, dict]:
    from pipeline.codecs.hdr import read_environment
    from stages.numerics import sg

    from stages.numerics.sh import project_environment

    rows, fits = [], {}
    for path in maps:
        env = read_environment(path)
        # the speed baseline, same process: the map's order-2 SH projection (9 coefficients, one weighted sum)
        sh_s = min(_seconds(lambda: project_environment(env)) for _ in range(3))
        for count in lobe_counts:
            started = time.perf_counter()
            lobes = sg.fit_sg_environment(env, count, iterations=iterations, fit_height=fit_height, seed=0)
            seconds = time.perf_counter() - started
            errors = sg.sg_fit_errors(env, lobes)
            row = {"map": path.stem, "lobes": count, "fit_s": round(seconds, 3), "sh_projection_s": round(sh_s, 4),
                   "x_sh_projection": round(seconds / max(sh_s, 1e-9), 1),
                   **{k: round(v, 5) for k, v in errors.items()}}
            rows.append(row)
            fits[(path.stem, count)] = lobes
            print(json.dumps(row), flush=True)
    return rows, fits


def summary(rows: list[dict], lobe_counts: list[int]) -> dict:
    keys = ("fit_s", "x_sh_projection", "map_rel_l2", "map_rel_l2_64", "energy_rel", "irradiance_rel_l2", "irradiance_max_rel",
            "irradiance_rel_l2_shading")
    out = {}
    for count in lobe_counts:
        sel = [r for r in rows if r["lobes"] == count]
        out[str(count)] = {f"median_{k}": round(float(np.median([r[k] for r in sel])), 5) for k in keys}
        out[str(count)]["max_irradiance_rel_l2"] = round(max(r["irradiance_rel_l2"] for r in sel), 5)
    return out


def shading_check(lobes, n_points: int = 24, seed: int = 0, max_view_deg: float = 60.0, h: int = 512) -> dict:
    """shade_sg against quadrature of the same BRDF (GGX D, Schlick F, the chosen shadowing) under the
    lobes' own map, for random normals, views within max_view_deg of the normal and r in {0.3, 0.45, 0.7}."""
    import torch

    from stages.numerics import sg

    rng = np.random.default_rng(seed)
    env = sg.render_sg_environment(lobes, h, 2 * h)
    dirs = sg.equirect_directions(h, 2 * h).reshape(-1, 3).astype(np.float64)
    radiance = env.reshape(-1, 3).astype(np.float64) * sg.equirect_solid_angles(h, 2 * h).reshape(-1, 1)
    normals = rng.normal(size=(n_points, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    views = []
    for n in normals:  # a view within 80 degrees of the normal
        while True:
            v = rng.normal(size=3)
            v /= np.linalg.norm(v)
            if v @ n > math.cos(math.radians(max_view_deg)):
                views.append(v)
                break
    views = np.array(views)
    out = {}
    for shadowing in ("physg", "smith"):
        for r in (0.3, 0.45, 0.7):
            rough = np.full(n_points, r)
            got = sg.shade_sg(normals.astype(np.float32), views.astype(np.float32), np.ones((n_points, 3), np.float32),
                              rough.astype(np.float32), lobes, f0=0.02, shadowing=shadowing)
            ref_diffuse = np.maximum(normals @ dirs.T, 0.0) @ radiance / math.pi
            ref_spec = brdf_quadrature(normals, views, rough, dirs, radiance, 0.02, shadowing)
            lum = np.array([0.2126, 0.7152, 0.0722])
            rel_s = np.abs((got["specular"] - ref_spec) @ lum) / np.maximum(ref_spec @ lum, 1e-12)
            rel_d = np.abs((got["diffuse"] - ref_diffuse) @ lum) / np.maximum(ref_diffuse @ lum, 1e-12)
            out[f"{shadowing}_r{r}"] = {
                "diffuse_median_rel": round(float(np.median(rel_d)), 4), "diffuse_max_rel": round(float(rel_d.max()), 4),
                "specular_median_rel": round(float(np.median(rel_s)), 4),
                "specular_p90_rel": round(float(np.percentile(rel_s, 90)), 4),
                "specular_total_rel": round(float(abs((got["specular"] - ref_spec).sum() / ref_spec.sum())), 4),
            }
    del torch
    return out


def brdf_quadrature(normals, views, roughness, dirs, radiance, f0, shadowing):
    """sum_w L(w) f_s(w) max(0, n.w) dW with the GGX specular BRDF (float64, per point)."""
    out = np.zeros((len(normals), 3))
    for i, (n, v, r) in enumerate(zip(normals, views, roughness)):
        alpha = r * r
        a2 = alpha * alpha
        nl = dirs @ n
        mask = nl > 0
        l, nl = dirs[mask], nl[mask]
        nv = max(float(n @ v), 1e-3)
        half = l + v
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        nh = half @ n
        d = a2 / (math.pi * (nh * nh * (a2 - 1) + 1) ** 2)
        vh = np.clip(half @ v, 0, 1)
        fres = f0 + (1 - f0) * (1 - vh) ** 5
        if shadowing == "physg":
            k = (r + 1) ** 2 / 8
            vis = 1.0 / (4 * (nl * (1 - k) + k) * (nv * (1 - k) + k))
        else:
            vis = 0.5 / (nl * math.sqrt(nv * nv * (1 - a2) + a2) + nv * np.sqrt(nl * nl * (1 - a2) + a2))
        out[i] = (d * fres * vis * nl) @ radiance[mask]
    return out


def _views_within(normals: np.ndarray, per_point: int, max_deg: float, rng) -> np.ndarray:
    out = np.zeros((len(normals), per_point, 3))
    for p, n in enumerate(normals):
        k = 0
        while k < per_point:
            v = rng.normal(size=3)
            v /= np.linalg.norm(v)
            if v @ n > math.cos(math.radians(max_deg)):
                out[p, k] = v
                k += 1
    return out


def _simulator_shading(normals, views, albedo, roughness, f0=0.02):
    """(N, 3, 3) radiance of unoccluded points as synthetic/shading.py renders them under 512 ideal LEDs."""
    from synthetic import geometry, rig, shading

    leds = rig.LedSphere(geometry.fibonacci_sphere(512), np.ones((512, 3)), 1.6)
    irradiance = leds.irradiance.astype(np.float64)
    diffuse = (np.tile(albedo / np.pi, 3) * (np.maximum(normals @ leds.directions.T, 0.0) @ irradiance))
    weights = shading.ggx_weights(normals.astype(np.float32), views.astype(np.float32),
                                  leds.directions.astype(np.float32), (roughness ** 2).astype(np.float32),
                                  np.full(len(normals), f0, np.float32))
    return diffuse.reshape(-1, 3, 3), (weights.astype(np.float64) @ irradiance).reshape(-1, 3, 3)


def stage_check(points: int = 2000, views: int = 8) -> dict:
    """Closed-form shading under full_on / pos / neg against the simulator's per-LED GGX, and roughness
    fits on simulator-rendered observations (1e-3 noise, 8 views within 70 degrees per point)."""
    from stages.numerics.materials import fit_roughness, shade_stage_illuminations

    out = {"shading": {}, "fit": {}}
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(400, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo = rng.uniform(0.1, 0.8, (400, 3))
    for max_deg in (60, 80):
        view = _views_within(normals, 1, max_deg, rng)[:, 0]
        for r in (0.25, 0.45, 0.7):
            rough = np.full(400, r)
            sim_d, sim_s = _simulator_shading(normals, view, albedo, rough)
            diffuse = shade_stage_illuminations(normals, view, albedo, rough, specular=False)
            row = {"diffuse_max_rel": round(float(np.abs(diffuse - sim_d).max() / sim_d.max()), 5)}
            for model in ("sg", "ggx_table"):
                spec = shade_stage_illuminations(normals, view, albedo, rough, specular_model=model) - diffuse
                rel = np.abs(spec.sum(axis=(1, 2)) - sim_s.sum(axis=(1, 2))) / sim_s.sum(axis=(1, 2))
                grad = np.linalg.norm((spec[:, 1] - spec[:, 2]) - (sim_s[:, 1] - sim_s[:, 2]), axis=1) \
                    / np.maximum(np.linalg.norm(sim_s[:, 1] - sim_s[:, 2], axis=1), 1e-12)
                pixel = np.abs((diffuse + spec) - (sim_d + sim_s)).max(axis=(1, 2)) / (sim_d + sim_s).max(axis=(1, 2))
                row[model] = {"specular_median_rel": round(float(np.median(rel)), 4),
                              "specular_p90_rel": round(float(np.percentile(rel, 90)), 4),
                              "pos_minus_neg_specular_median_rel": round(float(np.median(grad)), 4),
                              "pixel_p90_rel": round(float(np.percentile(pixel, 90)), 5)}
            out["shading"][f"views_within_{max_deg}deg_r{r}"] = row
    normals = rng.normal(size=(points, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    view = _views_within(normals, views, 70, rng)
    albedo = rng.uniform(0.1, 0.7, (points, 3))
    rough = rng.uniform(0.2, 0.9, points)
    observed = np.stack([sum(_simulator_shading(normals, view[:, v], albedo, rough)) for v in range(views)], axis=1)
    observed += 1e-3 * rng.normal(size=observed.shape)
    for model in ("ggx_table", "sg"):
        started = time.perf_counter()
        fitted, _ = fit_roughness(observed, view, np.ones((points, views), bool), normals, albedo, specular_model=model)
        seconds = time.perf_counter() - started
        err = fitted - rough
        out["fit"][model] = {"points": points, "views": views, "seconds": round(seconds, 3),
                             "mae": round(float(np.abs(err).mean()), 4), "bias": round(float(err.mean()), 4),
                             **{f"mae_r{lo}-{hi}": round(float(np.abs(err[(rough >= lo) & (rough < hi)]).mean()), 4)
                                for lo, hi in ((0.2, 0.4), (0.4, 0.6), (0.6, 0.9))}}
    return out


def plot(rows: list[dict], lobe_counts: list[int], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    maps = sorted({r["map"] for r in rows})
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    panels = (("map_rel_l2_64", "map rel. L2 (64x128)"), ("irradiance_rel_l2", "irradiance rel. L2 (exact)"),
              ("fit_s", "fit time (s, 1 thread)"))
    for ax, (key, title) in zip(axes, panels):
        for name in maps:
            sel = sorted((r for r in rows if r["map"] == name), key=lambda r: r["lobes"])
            ax.plot([r["lobes"] for r in sel], [r[key] for r in sel], "-o", ms=3, lw=1, alpha=0.6, label=name)
        med = [np.median([r[key] for r in rows if r["lobes"] == c]) for c in lobe_counts]
        ax.plot(lobe_counts, med, "k-", lw=3, label="median")
        if key == "irradiance_rel_l2":
            med_s = [np.median([r["irradiance_rel_l2_shading"] for r in rows if r["lobes"] == c]) for c in lobe_counts]
            ax.plot(lobe_counts, med_s, "k--", lw=2, label="median (SG-cosine approx.)")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("lobes")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=6, ncol=2)
    axes[1].legend(fontsize=6, handles=axes[1].get_lines()[-2:])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def previews(maps: list[Path], fits: dict, counts: list[int], path: Path) -> None:
    from pipeline.codecs.hdr import read_environment
    from pipeline.codecs.image import preview_linear, write_png
    from stages.numerics import sg

    h = 96
    rows = []
    for map_path in maps:
        env = sg.resize_environment(read_environment(map_path), h)
        p99 = float(np.percentile(env, 99))
        exposure = 0.9 / p99 if p99 > 0 else 1.0
        tiles = [preview_linear(env, exposure)]
        for count in counts:
            tiles.append(preview_linear(sg.render_sg_environment(fits[(map_path.stem, count)], h, supersample=2), exposure))
        gap = np.full((h, 4, 3), 255, np.uint8)
        row = np.concatenate([x for t in tiles for x in (t, gap)][:-1], axis=1)
        rows.append(row)
        rows.append(np.full((4, row.shape[1], 3), 255, np.uint8))
    write_png(path, np.concatenate(rows[:-1], axis=0))


def main() -> int:
    from _quick import QUICK_HELP
    from stages.relight import RelightConfig

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--lobes", default="8,16,32,64,128")
    parser.add_argument("--maps", help="comma-separated map stems (default: every *.hdr)")
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--fit-height", type=int, default=RelightConfig().fit_height,
                        help="rows of the map the fit works on (default: the relight stage's)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    fit_points, shading_points, quadrature_rows = 2000, 24, 512
    if args.quick:
        args.lobes, args.iterations, fit_points, shading_points, quadrature_rows = "8,32", 30, 200, 6, 128
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result_path = out / "bench_sg.json"
    maps = sorted(HDRI.glob("*.hdr")) if HDRI.is_dir() else []
    if args.maps:
        wanted = set(args.maps.split(","))
        maps = [m for m in maps if m.stem in wanted]
    if args.quick:
        maps = [next((m for m in maps if m.stem == "lebombo_1k"), maps[0])] if maps else []
    if not maps:
        result_path.write_text(json.dumps({"skipped": f"no HDR maps at {HDRI}", "quick": args.quick}, indent=1))
        print(f"skipped: no HDR maps at {HDRI}")
        return 0

    import torch

    torch.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    lobe_counts = [int(x) for x in args.lobes.split(",")]
    started = time.perf_counter()
    rows, fits = fit_table(maps, lobe_counts, args.iterations, args.fit_height)
    shading_map = next((m for m in maps if m.stem == "lebombo_1k"), maps[0])
    shading_lobes = fits[(shading_map.stem, 32 if 32 in lobe_counts else lobe_counts[-1])]
    shading = {f"views_within_{deg}deg": shading_check(shading_lobes, shading_points, max_view_deg=deg,
                                                       h=quadrature_rows) for deg in (60, 80)}
    stage = stage_check(points=fit_points)
    result = {
        "quick": args.quick,
        "stage_illuminations_vs_simulator": stage,
        "maps": [m.name for m in maps], "lobe_counts": lobe_counts, "iterations": args.iterations,
        "fit_height": args.fit_height, "threads": args.threads,
        "summary_by_lobes": summary(rows, lobe_counts),
        "shading_vs_quadrature": {"environment": f"{shading_map.stem}, {shading_lobes.count} lobes", **shading},
        "rows": rows, "total_s": round(time.perf_counter() - started, 1),
    }
    result_path.write_text(json.dumps(result, indent=1))
    plot(rows, lobe_counts, out / "bench_sg.png")
    preview_counts = [c for c in (8, 32, 128) if c in lobe_counts] or lobe_counts[:3]
    previews(maps, fits, preview_counts, out / "bench_sg_previews.png")
    print(json.dumps(result["summary_by_lobes"], indent=1))
    print(json.dumps(result["shading_vs_quadrature"], indent=1))
    print(json.dumps(stage, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
