"""Held-out G-buffers (the paper's table 1): depth-guided reprojection against a volume-rendered albedo/normal field.

The paper synthesises the albedo and normal maps of 2 held-out captured views from the other 30 and compares
its reprojection with an Instant-NGP field trained on the albedo/normal maps and volume rendered. For each
action of the release and the held-out cameras 00005 and 00021 this reports the 6 table-1 metrics (albedo
PSNR / SSIM / RMSE, normal mean angle, % under 5 and 25 degrees) against the held-out **photometric** maps
(the protocol) and against the simulator's **truth** (``_truth``), for

1. the **reprojection** (``evaluation.heldout.heldout_metrics``: mesh depth, K = 6 sources), with the held-out
   white-light albedo predicted per view (the default) and as the plain blend of the sources' white-light
   albedo (``albedo_model="white"``, view-independent as the field's);
2. the **volume-rendered field** (:mod:`stages.numerics.appearance_field`: hash grid + MLP with albedo and
   normal heads, NeuS weights of the action's trained SDF, the geometry stage's ``sdf.pt``; sample windows
   centred on the release mesh's depth, the same depth the reprojection uses) at a few training lengths,
   with the time of each (pixel sampling, training, rendering);
3. the **mesh's own smooth normals** (normals only; bench_gbuffer.py's baseline);

each over its own valid pixels (as the protocol: synthesised, and photometric alpha > 0.5 and mask), and the
reprojection and the field also over the pixels both synthesise. The held-out photometric maps' own score
against the truth is given beside them. Both the SDF (so the mesh) were trained on all 32 views, the
held-out ones included: the comparison is between G-buffer methods on the same geometry.

``python bench/bench_heldout_field.py --out bench/out [--release DIR --capture DIR --work DIR --lengths 100,400,1000]``;
defaults runs/default/release, runs/default/capture and <release>.work (``make dataset``); without them it
prints why and exits 0. One torch thread. Writes bench_heldout_field.json, .md and .png. ``--quick`` (the tests'
mode): the tiny run of ``bench/_quick.py`` (its action A0000, held-out cameras spread out as ``heldout_metrics``
picks them when the release lacks evaluate's), the field trained for 10 and 20 steps; the numbers are not
measurements.
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
sys.path.insert(0, str(ROOT / "bench"))

from _report import write_report  # noqa: E402

from evaluation.heldout import DEFAULT_HELDOUT as HELDOUT  # noqa: E402  (the held-out cameras evaluate uses)
KEYS = ("heldout_albedo_psnr_db", "heldout_albedo_ssim", "heldout_albedo_rmse", "heldout_normal_mean_deg",
        "heldout_normal_under5_pct", "heldout_normal_under25_pct")
HEADERS = ("PSNR dB", "SSIM", "RMSE", "mean deg", "<5 deg %", "<25 deg %")


def find_sdf(work: Path, release: Path, action: str) -> Path | None:
    """The geometry stage's artifact (holding ``sdf/sdf.pt``) in the work store ``work`` whose mesh is the
    release's (hard link or same bytes; the most recently committed first), else the last committed one."""
    from pipeline.store import ArtifactStore
    from artifacts.facade import ActionArtifacts
    from manifests import release_artifacts

    store = ArtifactStore(work / "artifacts")
    folders = [f for f in store.committed_dirs("geometry", action) if (f / "sdf" / "sdf.pt").is_file()]
    released = release_artifacts(release, action)
    if released.has("mesh"):
        release_mesh = released.existing("mesh")
        for folder in folders:
            mesh = ActionArtifacts({"geometry": folder}).path("mesh")
            if mesh.is_file() and (os.path.samefile(mesh, release_mesh)
                                   or mesh.read_bytes() == release_mesh.read_bytes()):
                return folder
    latest = store.latest_dir("geometry", action)
    return latest if latest is not None and (latest / "sdf" / "sdf.pt").is_file() else None


def _round(d: dict) -> dict:
    return {k: round(float(v), 4) for k, v in d.items() if np.isfinite(v)}


def _pick(result: dict, suffixes=("", "_truth")) -> dict:
    extra = ("heldout_coverage",)
    return _round({k + s: result[k + s] for s in suffixes for k in KEYS + extra if k + s in result})


def field_metrics(data, maps: dict, rendered: dict[str, dict]) -> dict:
    """The field's held-out scores: own pixels vs photometric and truth, and the pixels the reprojection also has."""
    from evaluation.heldout import compare_maps, summarise

    parts, parts_truth, common_field, common_reproj = [], [], [], []
    covered = masked = 0
    for cam, r in rendered.items():
        ref, truth, synth = maps[cam]["photometric"], maps[cam]["truth"], maps[cam]["synth"]
        own = r["valid"] & (ref["alpha"] > 0.5) & ref["mask"]
        parts.append(compare_maps(r["normals_world"], r["albedo"], ref["normal"], ref["albedo"], own))
        covered += int((r["valid"] & ref["mask"]).sum())
        masked += int(ref["mask"].sum())
        common = own & maps[cam]["compare"]
        common_field.append(compare_maps(r["normals_world"], r["albedo"], ref["normal"], ref["albedo"], common))
        common_reproj.append(compare_maps(synth["normal"], synth["albedo"], ref["normal"], ref["albedo"], common))
        if truth is not None:
            tmask = r["valid"] & truth["mask"]
            parts_truth.append(compare_maps(r["normals_world"], r["albedo"], truth["normal"], truth["albedo"], tmask))
    out = summarise(parts) | {"heldout_coverage": covered / max(masked, 1)}
    if parts_truth:
        out |= summarise(parts_truth, "_truth")
    return {"metrics": _pick(out), "same_pixels": {"field": _pick(summarise(common_field), ("",)),
                                                    "reprojection": _pick(summarise(common_reproj), ("",))}}


def figure(maps: dict, rendered: dict, cam: str, length: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stages.numerics.metrics import angular_error_deg

    p, s, t = maps["photometric"], maps["synth"], maps["truth"]
    r = rendered
    pm = (p["alpha"] > 0.5) & p["mask"]

    def nrm(n, m):
        return np.where(m[..., None], np.clip(n * 0.5 + 0.5, 0, 1), 1.0)

    def alb(a, m):
        return np.where(m[..., None], np.clip(a, 0, 1) ** (1 / 2.2), 1.0)

    cols = [("held-out photometric", p["normal"], p["albedo"], pm),
            ("reprojected", s["normal"], s["albedo"], s["valid"]),
            (f"field ({length} steps)", r["normals_world"], r["albedo"], r["valid"])]
    fig, axes = plt.subplots(3, 3, figsize=(9, 12))
    for j, (name, n, a, m) in enumerate(cols):
        axes[0, j].imshow(alb(a, m))
        axes[0, j].set_title(f"{name}\nalbedo", fontsize=9)
        axes[1, j].imshow(nrm(n, m))
        axes[1, j].set_title(f"{name}\nnormal", fontsize=9)
    if t is not None:
        axes[2, 0].imshow(nrm(t["normal"], t["mask"]))
        axes[2, 0].set_title("simulator's true normal", fontsize=9)
    for j, (name, n, m) in enumerate([("reprojected", s["normal"], maps["compare"]),
                                      ("field", r["normals_world"], r["valid"] & pm)], start=1):
        im = axes[2, j].imshow(np.where(m, angular_error_deg(n, p["normal"]), np.nan), vmin=0, vmax=20, cmap="magma")
        axes[2, j].set_title(f"{name} vs photometric (deg)", fontsize=9)
        fig.colorbar(im, ax=axes[2, j], fraction=0.05)
    # crop every panel to the subject (with a margin)
    rows_, cols_ = np.nonzero(p["mask"] | r["valid"])
    if len(rows_):
        H, W = p["mask"].shape
        top, bottom = max(int(rows_.min()) - 8, 0), min(int(rows_.max()) + 8, H - 1)
        left, right = max(int(cols_.min()) - 8, 0), min(int(cols_.max()) + 8, W - 1)
        for ax in axes.ravel():
            ax.set_xlim(left - 0.5, right + 0.5)
            ax.set_ylim(bottom + 0.5, top - 0.5)
    for ax in axes.ravel():
        ax.axis("off")
    fig.suptitle(f"held-out camera {cam}")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def held_out(report: dict) -> str:
    """The held-out cameras of the report's actions, for its text."""
    per_action = {a: ", ".join(e["heldout"]) for a, e in report["actions"].items()}
    if len(set(per_action.values())) == 1:
        return next(iter(per_action.values()))
    return "; ".join(f"{a}: {cams}" for a, cams in per_action.items())


def markdown(report: dict) -> str:
    paper = report["paper_table1"]
    lines = ["## Held-out G-buffers: reprojection vs a volume-rendered albedo/normal field (table 1)", "",
             f"Held-out cameras {held_out(report)} of each action, synthesised from the others. Field: "
             f"preset `{report['preset']}` ({report['field_config_summary']}), one CPU thread. Time: reprojection = "
             "the held-out metrics call (mesh depth renders of the sources included); field = pixel sampling "
             "(shared by the lengths) + training + rendering the 2 views.", ""]
    for suffix, title in (("", "against the held-out photometric maps (the paper's protocol)"),
                          ("_truth", "against the simulator's ground truth")):
        lines += [f"### Metrics {title}", "",
                  "| action | method | seconds | " + " | ".join(HEADERS) + " | coverage |",
                  "|---|---|---|" + "---|" * (len(HEADERS) + 1)]
        for action, entry in list(report["actions"].items()) + [("mean", report["mean_over_actions"])]:
            for method, row in entry["rows"].items():
                vals = [row["metrics"].get(k + suffix) for k in KEYS]
                if all(v is None for v in vals):
                    continue
                cov = row["metrics"].get("heldout_coverage" + suffix)
                cells = ["-" if v is None else f"{v:.4g}" for v in vals]
                secs = "-" if row.get("seconds") is None else f"{row['seconds']:.1f}"
                lines.append(f"| {action} | {method} | {secs} | " + " | ".join(cells)
                             + f" | {'-' if cov is None else f'{cov:.3f}'} |")
            if suffix == "_truth" and action != "mean" and entry.get("photometric_heldout_vs_truth"):
                pv = entry["photometric_heldout_vs_truth"]
                lines.append(f"| {action} | held-out photometric maps themselves | - | "
                             + " | ".join(f"{pv[k + '_truth']:.4g}" if k + "_truth" in pv else "-" for k in KEYS)
                             + " | - |")
        if suffix == "":
            lines.append("| paper (their method) | | | " + " | ".join(f"{paper[k]:.4g}" for k in KEYS) + " | |")
        lines.append("")
    lines += ["### Same pixels (both methods synthesise them; against the photometric maps)", "",
              "| action | method | " + " | ".join(HEADERS) + " |", "|---|---|" + "---|" * len(HEADERS)]
    for action, entry in report["actions"].items():
        # the field's valid pixels come from the geometry alone: the same for every length
        first = next(iter(entry["same_pixels"].values()))
        rows = [("reprojection (K=6)", first["reprojection"])]
        rows += [(f"field, {length} steps", same["field"]) for length, same in entry["same_pixels"].items()]
        for method, m in rows:
            lines.append(f"| {action} | {method} | " + " | ".join(f"{m[k]:.4g}" if k in m else "-" for k in KEYS)
                         + " |")
    lines.append("")
    return "\n".join(lines)


def main() -> int:
    from _release import check_inputs, parse_release_args, release_parser

    parser = release_parser(__doc__, actions="A0000,A0001")
    parser.add_argument("--work", help="artifact store of the release (default: <release>.work)")
    parser.add_argument("--lengths", default="100,400,1000", help="training steps of the field, comma-separated")
    parser.add_argument("--preset", default="cpu")
    args = parse_release_args(parser)
    if args.quick:
        args.lengths = "10,20"
    out = Path(args.out)
    release, capture = Path(args.release), Path(args.capture)
    work = Path(args.work) if args.work else release.with_name(release.name + ".work")
    go_on, truth_dir = check_inputs("bench_heldout_field", release, capture, need_truth=False)
    if not go_on:
        return 0
    lengths = [int(x) for x in args.lengths.split(",") if x.strip()]
    if not lengths or min(lengths) < 1:
        parser.error("--lengths must list positive integers")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)

    from bench_gbuffer import mesh_normal_baseline, photometric_vs_truth
    from manifests import open_release
    from evaluation.heldout import PAPER_TABLE1, ActionGBuffers, heldout_metrics, spread_heldout
    from stages.numerics.appearance_field import (APPEARANCE_PRESETS, AppearanceView, render_appearance,
                                                  sample_training_pixels, train_appearance_field)
    from stages.numerics.sdf import SDFField

    preset = APPEARANCE_PRESETS[args.preset]
    enc = preset.encoding
    report: dict = {"paper_table1": PAPER_TABLE1, "heldout": list(HELDOUT), "quick": args.quick, "preset": args.preset,
                    "field_config": dataclasses.asdict(preset),
                    "field_config_summary": f"hash grid {enc.levels} levels x {enc.features_per_level}, 2^"
                                            f"{enc.log2_table_size} entries, {enc.base_resolution}..."
                                            f"{enc.finest_resolution}; {preset.rays_per_batch} rays/step, "
                                            f"{preset.samples_kept} of {preset.samples_per_ray} samples kept",
                    "actions": {}}
    available = set(open_release(release).action_ids)
    figure_done = False
    out.mkdir(parents=True, exist_ok=True)
    for action in [a for a in args.actions.split(",") if a]:
        if action not in available:
            print(f"bench_heldout_field: {action} is not in the release; skipped")
            continue
        sdf_dir = find_sdf(work, release, action)
        if sdf_dir is None:
            print(f"bench_heldout_field: no geometry artifacts (sdf.pt) for {action} under {work}; skipped")
            continue
        data = ActionGBuffers(release, action)
        # evaluate's held-out cameras; a release without them (the tiny run of --quick): two spread-out
        # cameras, as heldout_metrics picks them
        heldout = HELDOUT if set(HELDOUT) <= set(data.cameras) else spread_heldout(data.cameras, 2)
        if heldout != HELDOUT:
            print(f"bench_heldout_field: {action} lacks cameras {HELDOUT}; held out instead: {heldout}")
        t0 = time.perf_counter()
        res = heldout_metrics(release, action, heldout=heldout, truth_dir=truth_dir, data=data, return_maps=True)
        reproj_s = time.perf_counter() - t0
        rows = {"reprojection (K=6)": {"seconds": reproj_s, "metrics": _pick(res)}}
        # the field's albedo does not depend on the view: the reprojection's plain white-light blend beside it
        t0 = time.perf_counter()
        white = heldout_metrics(release, action, heldout=heldout, truth_dir=truth_dir, data=data, albedo_model="white")
        rows["reprojection (K=6), white-light blend"] = {"seconds": time.perf_counter() - t0, "metrics": _pick(white)}
        mesh = mesh_normal_baseline(data, res, truth_dir)
        entry: dict = {"heldout": list(heldout),
                       "sdf": str(sdf_dir.relative_to(work) if sdf_dir.is_relative_to(work) else sdf_dir),
                       "photometric_heldout_vs_truth": photometric_vs_truth(res), "same_pixels": {}, "fields": {}}
        print(action, "reprojection", json.dumps(rows["reprojection (K=6)"]["metrics"]), flush=True)

        sdf = SDFField.from_state(torch.load(sdf_dir / "sdf" / "sdf.pt", map_location="cpu", weights_only=False))
        training = json.loads((sdf_dir / "sdf" / "training.json").read_text())
        inv_s = float(training["stats"].get("final_inv_s", preset.inv_s))
        views = []
        for cam in sorted(data.cameras):
            if cam in heldout:
                continue
            maps, c = data.photometric(cam), data.cameras[cam]
            views.append(AppearanceView(albedo=maps["albedo"], normals_world=maps["normal"],
                                        valid=(maps["alpha"] > 0.5) & maps["mask"], K=c.K,
                                        cam_from_world=c.cam_from_world, depth_m=data.render(cam)["depth_m"]))
        base = dataclasses.replace(preset, inv_s=inv_s, device="cpu", threads=1)
        samples = sample_training_pixels(views, sdf, base)
        sampling_s = samples.stats["sampling_time_s"]
        print(action, "field samples", json.dumps(_round(samples.stats)), flush=True)
        for length in lengths:
            config = dataclasses.replace(base, iterations=length, log_every=max(length // 10, 1))
            result = train_appearance_field(samples, None, config)
            t0 = time.perf_counter()
            rendered = {}
            for cam in heldout:
                c = data.cameras[cam]
                rendered[cam] = render_appearance(result.field, sdf, c.K, c.cam_from_world, c.height,
                                                  c.width, depth_m=data.render(cam)["depth_m"], config=config)
            render_s = time.perf_counter() - t0
            scores = field_metrics(data, res["maps"], rendered)
            seconds = sampling_s + result.stats["train_time_s"] + render_s
            name = f"field, {length} steps"
            rows[name] = {"seconds": seconds, "metrics": scores["metrics"]}
            entry["same_pixels"][str(length)] = scores["same_pixels"]
            entry["fields"][str(length)] = {
                "sampling_s": round(sampling_s, 2), "train_s": round(result.stats["train_time_s"], 2),
                "render_s_per_view": round(render_s / len(heldout), 3),
                "training_pixels": result.stats["training_pixels"], "parameters": result.stats["parameters"],
                "final_train_albedo_l1": round(result.history["albedo_l1"][-1], 4),
                "final_train_normal_deg": round(result.history["normal_deg"][-1], 3)}
            print(action, name, f"{seconds:.1f}s", json.dumps(scores["metrics"]), flush=True)
            if not figure_done and length == max(lengths):
                figure(res["maps"][heldout[0]], rendered[heldout[0]], heldout[0], length,
                       out / "bench_heldout_field.png")
                figure_done = True
        rows["mesh smooth normals"] = {"seconds": None, "metrics": mesh}
        entry["rows"] = rows
        entry["inv_s"] = inv_s
        report["actions"][action] = entry
    if not report["actions"]:
        print("bench_heldout_field: nothing to measure; skipped")
        return 0
    means: dict = {"rows": {}}
    first = next(iter(report["actions"].values()))
    for method in first["rows"]:
        entries = [e["rows"][method] for e in report["actions"].values() if method in e["rows"]]
        keys = set().union(*(e["metrics"] for e in entries))
        means["rows"][method] = {
            "seconds": (float(np.mean([e["seconds"] for e in entries]))
                        if all(e["seconds"] is not None for e in entries) else None),
            "metrics": {k: round(float(np.mean([e["metrics"][k] for e in entries if k in e["metrics"]])), 4)
                        for k in sorted(keys)}}
    report["mean_over_actions"] = means
    write_report(out, "bench_heldout_field", report, markdown(report), json_default=float)
    print(f"wrote {out / 'bench_heldout_field.json'}, .md and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
