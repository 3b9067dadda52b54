"""G-buffers for held-out views (the paper's table 1): depth-guided reprojection against the photometric maps.

For both actions of a release (``evaluation.heldout.heldout_metrics``: two held-out cameras, mesh depth,
normal and albedo reprojected from the other 30 cameras) this reports

1. the held-out metrics against the held-out **photometric** maps (the paper's protocol) and against the
   simulator's **truth** (``_truth``), with the held-out photometric map's own score against the truth
   beside them (what a perfect synthesis of the photometric map would score there);
2. time per synthesised view (reprojection only, after the source depth renders, and with them);
3. metrics with the learned blend (``stages.numerics.learned_blend``, trained leave one out on the 30
   training cameras; its fit time) beside the heuristic weights; metrics against K (1, 2, 4, 6, 8), against
   the weighting (uniform, angle, angle+distance,
   angle+distance+grazing) and against the source lookup (bilinear, cubic: metrics, time per view and the
   cubic/bilinear time ratio, same process, source renders cached) and against the rays per side at the
   mesh's occlusion edges (1 = pixel centres; the sub-pixel rays' casting included in the time), and with
   the held-out white-light albedo predicted per view (``albedo_model="view_dependent"``, the default) or
   blended as the sources' are (``"white"``);
4. a baseline in the spirit of the paper's Instant-NGP comparison: the **mesh's own normals** (smooth,
   interpolated vertex normals of the release mesh) as the held-out normal map;
5. a figure (bench_gbuffer.png): photometric vs synthesised vs truth normals and albedo of one held-out
   view, with the angular error maps;
6. the same protocol on the ``normal_diffuse`` maps (specular reflection fitted out), as ``evaluate`` reports;
7. an **error budget** (with ground truth; bench_gbuffer_budget.png): the protocol with the simulator's true
   normal and albedo maps in place of the photometric ones (same cameras, mesh, depth tests and compared
   pixels: what the reprojection alone costs), and the photometric maps' own error against the truth by
   distance to the silhouette (ring 1 touches the background; every camera), which the held-out reference
   carries into the comparison view by view and the synthesis cannot predict; and how the protocol's
   numbers move when one or two more silhouette rings are left out of the compared pixels (a sensitivity,
   not the reported metric); and the geometry's share: the protocol with the simulator's depth maps in place
   of the mesh's renders (target and sources), with the albedo SSIM per band of distance to the silhouette
   for both; and with the simulator's depth for the held-out (target) views only, everywhere or only where
   the mesh is more than 16 mm off (the sources' depth tests stay on the mesh).

``python bench/bench_gbuffer.py --out bench/out [--release DIR --capture DIR] [--quick]``; defaults
runs/default/release and runs/default/capture (``make dataset``); without them it prints why and exits 0.
Writes bench_gbuffer.json, bench_gbuffer.png and bench_gbuffer_budget.png. ``--quick`` (the tests' mode): the
tiny run of ``bench/_quick.py``, two points of each sweep (the default among them) and the learned blend
trained for 20 steps; the numbers are not measurements.
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

KEYS = ("heldout_albedo_psnr_db", "heldout_albedo_ssim", "heldout_albedo_rmse", "heldout_normal_mean_deg",
        "heldout_normal_under5_pct", "heldout_normal_under25_pct", "heldout_coverage")


def _short(result: dict, suffixes=("", "_truth")) -> dict:
    return {k + s: round(float(result[k + s]), 4) for s in suffixes for k in KEYS if k + s in result}


def smooth_mesh_normals(vertices: np.ndarray, faces: np.ndarray, render: dict, K: np.ndarray,
                        cam_from_world: np.ndarray) -> np.ndarray:
    """(H, W, 3) world normals of the mesh seen by a camera, interpolated from area-weighted vertex
    normals with the barycentric coordinates of each pixel's hit point (0 where no hit)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for j in range(3):
        np.add.at(vn, f[:, j], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=-1, keepdims=True), 1e-12)
    hit = render["hit"]
    rows, cols = np.nonzero(hit)
    z = render["depth_m"][rows, cols].astype(np.float64)
    y = (rows - K[1, 2]) / K[1, 1]
    x = (cols - K[0, 2]) / K[0, 0]
    pts = (np.stack([x * z, y * z, z], -1) - cam_from_world[:, 3]) @ cam_from_world[:, :3]
    tri = f[render["face"][rows, cols]]
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    e0, e1, e2 = b - a, c - a, pts - a
    d00, d01, d11 = (e0 * e0).sum(-1), (e0 * e1).sum(-1), (e1 * e1).sum(-1)
    d20, d21 = (e2 * e0).sum(-1), (e2 * e1).sum(-1)
    den = np.where(np.abs(d00 * d11 - d01 * d01) > 1e-20, d00 * d11 - d01 * d01, 1.0)
    wb = np.clip((d11 * d20 - d01 * d21) / den, 0, 1)
    wc = np.clip((d00 * d21 - d01 * d20) / den, 0, 1)
    wa = np.clip(1 - wb - wc, 0, 1)
    n = wa[:, None] * vn[tri[:, 0]] + wb[:, None] * vn[tri[:, 1]] + wc[:, None] * vn[tri[:, 2]]
    # turn toward the camera like render_mesh's face normals
    n *= np.sign(np.einsum("ij,ij->i", n, render["normals_world"][rows, cols]))[:, None]
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    out = np.zeros(hit.shape + (3,), np.float32)
    out[rows, cols] = n
    return out


def mesh_normal_baseline(data, result: dict, truth_dir: Path | None) -> dict:
    """Held-out scores of the mesh's own normals (same pixels as the reprojection's comparison)."""
    from evaluation.heldout import compare_maps, summarise

    parts, parts_truth = [], []
    for cam, maps in result["maps"].items():
        c = data.cameras[cam]
        normals = smooth_mesh_normals(data.vertices, data.faces, data.render(cam), c.K, c.cam_from_world)
        ref = maps["photometric"]
        zero = np.zeros_like(ref["albedo"])
        parts.append(compare_maps(normals, zero, ref["normal"], ref["albedo"], maps["compare"]))
        if maps["truth"] is not None:
            tm = maps["synth"]["valid"] & maps["truth"]["mask"]
            parts_truth.append(compare_maps(normals, zero, maps["truth"]["normal"], maps["truth"]["albedo"], tm))
    out = {k: v for k, v in summarise(parts).items() if "normal" in k}
    if parts_truth:
        out |= {k: v for k, v in summarise(parts_truth, "_truth").items() if "normal" in k}
    return {k: round(float(v), 4) for k, v in out.items()}


def photometric_vs_truth(result: dict) -> dict:
    """The held-out photometric maps' own scores against the truth (over their valid pixels in the true mask)."""
    from evaluation.heldout import compare_maps, summarise

    parts = []
    for maps in result["maps"].values():
        if maps["truth"] is None:
            continue
        ref, t = maps["photometric"], maps["truth"]
        m = (ref["alpha"] > 0.5) & ref["mask"] & t["mask"]
        parts.append(compare_maps(ref["normal"], ref["albedo"], t["normal"], t["albedo"], m))
    return {k: round(float(v), 4) for k, v in summarise(parts, "_truth").items()} if parts else {}


def data_variant(data, maps=None, depth_of=None):
    """``data`` (an ActionGBuffers) with its photometric maps passed through ``maps(maps, cam) -> maps``
    and/or every camera's depth from ``depth_of(cam) -> (H, W)`` instead of the mesh's render (target and
    sources, so the depth tests use it too). It keeps its own source cache, and shares ``data``'s cached
    depth renders unless ``depth_of`` replaces them."""
    from evaluation.heldout import ActionGBuffers

    class Variant(ActionGBuffers):
        def photometric(self, cam: str) -> dict:
            out = super().photometric(cam)
            return maps(out, cam) if maps is not None else out

        def render(self, cam: str) -> dict:
            if depth_of is not None and cam not in self._render:
                self._render[cam] = {"depth_m": depth_of(cam)}
            return super().render(cam)

        def edge_subpixel(self, cam: str, samples: int, jump_m: float):
            # a given depth map has no sub-pixel rays: its edge pixels keep their centre's sample
            return None if depth_of is not None else super().edge_subpixel(cam, samples, jump_m)

    other = data.with_normals(data.diffuse_normals)
    if depth_of is not None:
        other._render = {}
    other.__class__ = Variant
    return other


def ssim_by_ring(result: dict, groups=((2, 4), (5, 6), (7, 10), (11, None))) -> dict:
    """Mean albedo SSIM (the protocol's map: 7 x 7 windows, both images zeroed outside the compared pixels)
    of the held-out views of a ``heldout_metrics(..., return_maps=True)`` result, per band of distance to
    the held-out mask's silhouette (ring 1 touches the background), pooled over the views."""
    from skimage.metrics import structural_similarity

    values: dict[str, list] = {}
    for m in result["maps"].values():
        keep = m["compare"]
        a = np.where(keep[..., None], m["synth"]["albedo"], 0.0)
        b = np.where(keep[..., None], m["photometric"]["albedo"], 0.0)
        _, smap = structural_similarity(a, b, data_range=1.0, win_size=7, full=True, channel_axis=-1)
        smap = smap.mean(axis=-1)
        ring = silhouette_ring(m["photometric"]["mask"])
        for lo, hi in groups:
            sel = keep & (ring >= lo) & (ring <= (hi if hi is not None else ring.max()))
            values.setdefault(f"{lo}-{hi}" if hi is not None else f"{lo}+", []).append(smap[sel])
    return {k: {"ssim": round(float(np.concatenate(v).mean()), 4), "pixels": int(sum(x.size for x in v))}
            for k, v in values.items() if sum(x.size for x in v)}


def silhouette_ring(mask: np.ndarray) -> np.ndarray:
    """(H, W) int32 chessboard distance of each mask pixel to the background (1 = touches it, 8-connected)."""
    from scipy import ndimage

    return ndimage.distance_transform_cdt(mask, metric="chessboard").astype(np.int32)


def error_budget(data, release: Path, action: str, truth_dir: Path, rings: int = 6) -> dict:
    """The error budget of the held-out protocol for one action (module docstring, item 7)."""
    from evaluation.heldout import heldout_metrics, load_truth
    from stages.numerics.metrics import angular_error_deg

    diffuse = data.with_normals(True)

    def truth_maps(maps: dict, cam: str) -> dict:
        t = load_truth(truth_dir, action, cam, maps["mask"].shape)
        return maps | {"normal": t["normal"], "albedo": t["albedo"]}

    def without_rings(px: int):
        def transform(maps: dict, cam: str) -> dict:
            edge = maps["mask"] & (silhouette_ring(maps["mask"]) <= px)
            return maps | {"alpha": np.where(edge, np.minimum(maps["alpha"], 0.25), maps["alpha"])}
        return transform

    # the true maps hold no specular light: their albedo is blended as it is
    out = {"truth_maps": _short(heldout_metrics(release, action, data=data_variant(diffuse, maps=truth_maps),
                                                albedo_model="white"), ("",)),
           "rings_left_out": {str(px): _short(heldout_metrics(release, action, data=data_variant(diffuse, maps=without_rings(px))), ("",))
                              for px in (2, 3)}}  # 1 is the stage's own edge: metrics_diffuse
    acc = {r: {"eq1": [], "diffuse": [], "albedo_sq": []} for r in range(1, rings + 1)}
    for cam in sorted(data.cameras):
        maps = data.photometric(cam)
        t = load_truth(truth_dir, action, cam, maps["mask"].shape)
        if t is None:
            continue
        ring = np.minimum(silhouette_ring(maps["mask"]), rings)
        defined = maps["mask"] & t["mask"] & np.any(maps["normal"] != 0, axis=-1)
        e1 = angular_error_deg(maps["normal"], t["normal"])
        ed = angular_error_deg(diffuse.photometric(cam)["normal"], t["normal"])
        sq = ((maps["albedo"] - t["albedo"]) ** 2).mean(axis=-1)
        for r in acc:
            sel = defined & (ring == r)
            acc[r]["eq1"].append(e1[sel])
            acc[r]["diffuse"].append(ed[sel])
            acc[r]["albedo_sq"].append(sq[sel])
    by_ring = {}
    for r, parts in acc.items():
        e1, ed, sq = (np.concatenate(parts[k]) for k in ("eq1", "diffuse", "albedo_sq"))
        if e1.size:
            by_ring[f"{r}+" if r == rings else str(r)] = {
                "pixels": int(e1.size), "normal_eq1_mean_deg": round(float(e1.mean()), 3),
                "normal_diffuse_mean_deg": round(float(ed.mean()), 3),
                "albedo_rmse": round(float(np.sqrt(sq.mean())), 4)}
    out["photometric_vs_truth_by_ring"] = by_ring

    # The geometry's share: the simulator's depth maps in place of the mesh's renders, eq. 1's maps as the
    # protocol (what a perfect mesh would score with these maps and this blend), SSIM by silhouette band.
    from pipeline.codecs.exr import read_exr

    def true_depth(cam: str) -> np.ndarray:
        z = read_exr(truth_dir / action / "depth" / f"{cam}.exr")
        z = z[..., 0] if z.ndim == 3 else z
        expected = data.photometric(cam)["mask"].shape
        if z.shape != expected:
            raise ValueError(f"{truth_dir / action / 'depth' / (cam + '.exr')}: {z.shape}, maps are {expected}")
        return np.where(np.isfinite(z) & (z > 0), z, 0.0).astype(np.float32)

    if all((truth_dir / action / "depth" / f"{c}.exr").exists() for c in data.cameras):
        eq1 = data.with_normals(False)
        mesh = heldout_metrics(release, action, data=eq1, return_maps=True)
        true = heldout_metrics(release, action, data=data_variant(eq1, depth_of=true_depth), return_maps=True)
        out["true_depth"] = {"mesh": _short(mesh, ("",)), "true_depth": _short(true, ("",)),
                             "ssim_by_silhouette_band": {"mesh": ssim_by_ring(mesh), "true_depth": ssim_by_ring(true)}}
        # Only the held-out (target) views' depth from the simulator, the sources' depth tests still on the
        # mesh, within the mesh's silhouette: everywhere, or only where the mesh is more than 16 mm off (the
        # occluding contours: arm over torso, fingers, collar).
        targets = set(mesh["heldout_cameras"])

        def target_depth(beyond_m: float):
            def depth(cam: str) -> np.ndarray:
                ours = eq1.render(cam)["depth_m"]
                if cam not in targets:
                    return ours
                z = true_depth(cam)
                swap = (ours > 0) & (z > 0) & (np.abs(ours - z) > beyond_m)
                return np.where(swap, z, ours).astype(np.float32)
            return depth

        for label, beyond in (("true_target_depth", 0.0), ("true_target_depth_beyond_16mm", 0.016)):
            out["true_depth"][label] = _short(heldout_metrics(release, action,
                                                              data=data_variant(eq1, depth_of=target_depth(beyond))),
                                              ("",))
    return out


def budget_figure(report: dict, path: Path) -> None:
    """Held-out metrics of the protocol variants next to the paper, and the photometric error by ring."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    actions = [a for a, e in report["actions"].items() if "error_budget" in e]
    if not actions:
        return
    rows = {"paper (table 1)": report["paper_table1"]}
    for a in actions:
        e = report["actions"][a]
        rows[f"{a} eq. 1 maps"] = e["metrics"]
        rows[f"{a} diffuse maps"] = e["metrics_diffuse"]
        rows[f"{a} true maps"] = e["error_budget"]["truth_maps"]
    fig, axes = plt.subplots(1, 4, figsize=(18, 4.5))
    for ax, key, label in ((axes[0], "heldout_albedo_psnr_db", "albedo PSNR (dB)"),
                           (axes[1], "heldout_albedo_ssim", "albedo SSIM"),
                           (axes[2], "heldout_normal_mean_deg", "normal mean error (deg)")):
        names = [n for n in rows if key in rows[n]]
        ax.barh(range(len(names)), [rows[n][key] for n in names],
                color=[next(c for tag, c in (("paper", "k"), ("eq. 1", "C1"), ("diffuse", "C2"), ("true", "C0"))
                            if tag in n) for n in names])
        ax.set_yticks(range(len(names)), names if ax is axes[0] else [""] * len(names), fontsize=7)
        ax.set_xlabel(label)
        ax.invert_yaxis()
        lo = min(rows[n][key] for n in names)
        ax.set_xlim(lo * 0.9 if key != "heldout_normal_mean_deg" else 0, None)
    for a in actions:
        by_ring = report["actions"][a]["error_budget"]["photometric_vs_truth_by_ring"]
        x = list(range(1, len(by_ring) + 1))
        axes[3].plot(x, [v["normal_eq1_mean_deg"] for v in by_ring.values()], "o-", label=f"{a} eq. 1")
        axes[3].plot(x, [v["normal_diffuse_mean_deg"] for v in by_ring.values()], "s--", label=f"{a} diffuse")
        axes[3].set_xticks(x, list(by_ring))
    axes[3].set_xlabel("silhouette ring (1 = touches the background)")
    axes[3].set_ylabel("photometric normal error vs truth (deg)")
    axes[3].legend(fontsize=7)
    fig.suptitle("held-out protocol: what the reprojection costs (true maps) and what the photometric maps bring")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def figure(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stages.numerics.metrics import angular_error_deg

    cam = result["heldout_cameras"][0]
    maps = result["maps"][cam]
    s, p, t = maps["synth"], maps["photometric"], maps["truth"]
    pm = (p["alpha"] > 0.5) & p["mask"]

    def nrm(n, m):
        return np.where(m[..., None], np.clip(n * 0.5 + 0.5, 0, 1), 1.0)

    def alb(a, m):
        return np.where(m[..., None], np.clip(a, 0, 1) ** (1 / 2.2), 1.0)

    cols = [("photometric", p["normal"], p["albedo"], pm), ("synthesised", s["normal"], s["albedo"], s["valid"])]
    if t is not None:
        cols.append(("truth", t["normal"], t["albedo"], t["mask"]))
    fig, axes = plt.subplots(2, len(cols) + 2, figsize=(3 * (len(cols) + 2), 8))
    for j, (name, n, a, m) in enumerate(cols):
        axes[0, j].imshow(nrm(n, m))
        axes[0, j].set_title(f"{name} normal")
        axes[1, j].imshow(alb(a, m))
        axes[1, j].set_title(f"{name} albedo")
    cmp = maps["compare"]
    err = np.where(cmp, angular_error_deg(s["normal"], p["normal"]), np.nan)
    im = axes[0, len(cols)].imshow(err, vmin=0, vmax=20, cmap="magma")
    axes[0, len(cols)].set_title("angle synth vs photo (deg)")
    fig.colorbar(im, ax=axes[0, len(cols)], fraction=0.05)
    aerr = np.where(cmp, np.abs(s["albedo"] - p["albedo"]).mean(-1), np.nan)
    im = axes[1, len(cols)].imshow(aerr, vmin=0, vmax=0.1, cmap="magma")
    axes[1, len(cols)].set_title("|albedo synth - photo|")
    fig.colorbar(im, ax=axes[1, len(cols)], fraction=0.05)
    if t is not None:
        tm = s["valid"] & t["mask"]
        im = axes[0, len(cols) + 1].imshow(np.where(tm, angular_error_deg(s["normal"], t["normal"]), np.nan),
                                           vmin=0, vmax=20, cmap="magma")
        axes[0, len(cols) + 1].set_title("angle synth vs truth (deg)")
        fig.colorbar(im, ax=axes[0, len(cols) + 1], fraction=0.05)
        im = axes[1, len(cols) + 1].imshow(np.where(tm, np.abs(s["albedo"] - t["albedo"]).mean(-1), np.nan),
                                           vmin=0, vmax=0.1, cmap="magma")
        axes[1, len(cols) + 1].set_title("|albedo synth - truth|")
        fig.colorbar(im, ax=axes[1, len(cols) + 1], fraction=0.05)
    for ax in axes.ravel():
        ax.axis("off")
    fig.suptitle(f"held-out camera {cam}: reprojected from {', '.join(map(str, s['source_ids']))}")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main() -> int:
    from _release import check_inputs, parse_release_args, release_parser

    args = parse_release_args(release_parser(__doc__))
    out = Path(args.out)
    release, capture = Path(args.release), Path(args.capture)
    go_on, truth_dir = check_inputs("bench_gbuffer", release, capture, need_truth=False)
    if not go_on:
        return 0
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    out.mkdir(parents=True, exist_ok=True)

    from manifests import open_release
    from evaluation.heldout import PAPER_TABLE1, ActionGBuffers, heldout_metrics
    from stages.numerics.learned_blend import LearnedBlendConfig

    quick = args.quick
    ks = (1, 6) if quick else (1, 2, 4, 6, 8)  # heldout_metrics' default k is 6
    edge_samples = (1, 3) if quick else (1, 2, 3, 4)  # evaluation.heldout.EDGE_SAMPLES is 3
    weightings = ("uniform", "angle_distance_grazing") if quick else ("uniform", "angle", "angle_distance",
                                                                      "angle_distance_grazing")
    blend = LearnedBlendConfig(enabled=True)
    if quick:
        blend = dataclasses.replace(blend, steps=20)
    report: dict = {"paper_table1": PAPER_TABLE1, "quick": quick, "actions": {}}
    first_maps = None
    for action in open_release(release).action_ids:
        t0 = time.perf_counter()
        data = ActionGBuffers(release, action)
        load_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = heldout_metrics(release, action, truth_dir=truth_dir, data=data, return_maps=True)
        first_s = time.perf_counter() - t0
        entry = {"heldout_cameras": res["heldout_cameras"], "metrics": _short(res),
                 "per_view": {c: _short(v) for c, v in res["per_view"].items()},
                 "metrics_diffuse": _short(heldout_metrics(release, action, truth_dir=truth_dir,
                                                           data=data.with_normals(True))),
                 "photometric_heldout_vs_truth": photometric_vs_truth(res),
                 "mesh_normals_baseline": mesh_normal_baseline(data, res, truth_dir),
                 "seconds": {"load_release_action": round(load_s, 3),
                             "reprojection_per_view": round(res["heldout_seconds_per_view"], 4),
                             "per_view_with_depth_renders": round(first_s / len(res["heldout_cameras"]), 4)}}
        print(action, json.dumps(entry["metrics"]), flush=True)
        if first_maps is None:
            first_maps = res
        entry["vs_k"] = {}
        for k in ks:
            r = heldout_metrics(release, action, truth_dir=truth_dir, data=data, k=k)
            entry["vs_k"][str(k)] = _short(r) | {"seconds_per_view": round(r["heldout_seconds_per_view"], 4)}
        entry["vs_interpolation"] = {}
        for interpolation in ("bilinear", "cubic"):  # the source depth renders are cached by now: lookups only
            r = heldout_metrics(release, action, truth_dir=truth_dir, data=data, interpolation=interpolation)
            entry["vs_interpolation"][interpolation] = _short(r) | {
                "seconds_per_view": round(r["heldout_seconds_per_view"], 4)}
        vi = entry["vs_interpolation"]
        vi["cubic_time_ratio"] = round(vi["cubic"]["seconds_per_view"] / max(vi["bilinear"]["seconds_per_view"], 1e-9), 2)
        print(action, "interpolation", json.dumps(vi), flush=True)
        # pixels at the mesh's occlusion edges from 1 (centres only), 2, 3 or 4 rays per side (the sub-pixel rays
        # are cast on the first call per camera: that call's time includes them, a repeat's does not)
        entry["vs_edge_samples"] = {}
        for samples in edge_samples:
            r = heldout_metrics(release, action, truth_dir=truth_dir, data=data, edge_samples=samples)
            entry["vs_edge_samples"][str(samples)] = _short(r) | {
                "seconds_per_view": round(r["heldout_seconds_per_view"], 4)}
        print(action, "edge samples", json.dumps(entry["vs_edge_samples"]), flush=True)
        # the held-out white-light albedo predicted per view (default) or the sources' blended as they are
        entry["vs_albedo_model"] = {}
        for model in ("view_dependent", "white"):
            r = heldout_metrics(release, action, truth_dir=truth_dir, data=data, albedo_model=model)
            entry["vs_albedo_model"][model] = _short(r) | {"seconds_per_view": round(r["heldout_seconds_per_view"], 4)}
        print(action, "albedo model", json.dumps(entry["vs_albedo_model"]), flush=True)
        # the learned blend (trained leave one out on the 30 training cameras) against the heuristic weights
        learned = heldout_metrics(release, action, truth_dir=truth_dir, data=data,
                                  learned_blend=blend)
        entry["vs_blend"] = {"weighted": _short(res), "learned": _short(learned),
                             "learned_fit_s": round(learned["heldout_blend_fit_s"], 2),
                             "learned_record": learned["blend"]}
        print(action, "blend", json.dumps(entry["vs_blend"], default=float), flush=True)
        entry["vs_weighting"] = {}
        for weighting in weightings:
            r = heldout_metrics(release, action, truth_dir=truth_dir, data=data, weighting=weighting)
            entry["vs_weighting"][weighting] = _short(r)
        if truth_dir is not None:
            entry["error_budget"] = error_budget(data, release, action, truth_dir)
            print(action, "error budget", json.dumps(entry["error_budget"]["truth_maps"]), flush=True)
            if "true_depth" in entry["error_budget"]:
                print(action, "depth", json.dumps({k: v.get("heldout_albedo_ssim") for k, v in
                                                   entry["error_budget"]["true_depth"].items() if isinstance(v, dict)
                                                   and "heldout_albedo_ssim" in v}), flush=True)
        report["actions"][action] = entry
    if first_maps is not None:
        figure(first_maps, out / "bench_gbuffer.png")
    budget_figure(report, out / "bench_gbuffer_budget.png")
    means = {}
    for key in next(iter(report["actions"].values()))["metrics"] if report["actions"] else []:
        vals = [e["metrics"][key] for e in report["actions"].values() if key in e["metrics"]]
        means[key] = round(float(np.mean(vals)), 4)
    report["mean_over_actions"] = means
    (out / "bench_gbuffer.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(means, indent=1))
    print(f"wrote {out / 'bench_gbuffer.json'} and {out / 'bench_gbuffer.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
