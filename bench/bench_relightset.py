"""Relighting set: examples per second of the stage's renderer against the simulator's own render of the same
view, and the image, normal and albedo error of each setting against the simulator's subject.

For one action of a release (default A0000; its stage inputs read from the work store of ``make dataset``,
``runs/default/release.work``), the first ``--examples`` examples are drawn exactly as the ``relightset`` stage
draws them (:func:`stages.numerics.relightset.draw_example`, the stage's config :func:`default_config`) and
rendered with the stage's renderer (:func:`stages.numerics.novel_view.relight_view`) for each variant: the
stage's default, image sizes 128 / 512 and SG lobes 16 / 64 (one change at a time). Each example is scored
like ``ultrastage evaluate`` against :class:`synthetic.relight.TruthRelighter` (image PSNR after a common
exposure, camera-frame normal angle, albedo PSNR), and timed:

- ``render_s``: the stage's render of one example (G-buffer, visibility, shading, coverage), the SG fit of its
  map excluded (it is shared by every example of a map);
- ``truth_s``: the simulator's render of the same view under the same rotated map (its per-action visibility
  tracing excluded and reported once as ``truth_setup_s``);
- ``x_truth``: truth_s / render_s in the same process (above 1: the stage renders faster than the simulator).

``python bench/bench_relightset.py --out DIR [--release DIR --capture DIR --actions A0000 --examples 3]``
writes DIR/bench_relightset.json, .md and .png (PSNR against seconds per example). ``--quick`` (the tests' mode):
the tiny run of ``bench/_quick.py``, one example, the default and one change (``QUICK_VARIANTS``), the truth
lit by 256 lights; the numbers are not measurements.
"""
from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stages.relightset import RelightSetConfig  # noqa: E402


def default_config() -> RelightSetConfig:
    """The configuration of the bench's default row: the relightset stage's own defaults."""
    return RelightSetConfig()


VARIANT_CHANGES: tuple[tuple[str, dict], ...] = (("size 128", {"size": 128}), ("size 512", {"size": 512}),
                                                 ("sg_lobes 16", {"sg_lobes": 16}), ("sg_lobes 64", {"sg_lobes": 64}))


QUICK_VARIANTS = ("size 128",)
"""The change ``--quick`` keeps (one that needs no other SG fit)."""


def variant_configs(quick: bool = False) -> list[tuple[str, RelightSetConfig]]:
    base = default_config()
    rows = [(f"default (size {base.size}, {base.sg_lobes} lobes)", base)]
    for label, change in VARIANT_CHANGES:
        if quick and label not in QUICK_VARIANTS:
            continue
        cfg = dataclasses.replace(base, **change)
        if cfg != base:
            rows.append((label, cfg))
    return rows


def main() -> int:
    from _release import check_inputs, parse_release_args, release_parser

    parser = release_parser(__doc__, actions="A0000")
    parser.add_argument("--examples", type=int, default=3)
    parser.add_argument("--work", default=None, help="work folder of the release (default: RELEASE.work)")
    args = parse_release_args(parser)
    truth_lights = 2048
    if args.quick:
        args.examples, truth_lights = 1, 256
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    release, capture = Path(args.release), Path(args.capture)
    go, truth_dir = check_inputs("bench_relightset", release, capture, need_truth=True)
    if not go:
        return 0
    work = Path(args.work) if args.work else release.with_name(release.name + ".work")

    from pipeline.capture import open_capture
    from artifacts.facade import ActionArtifacts
    from stages.relightable import load_relightable_asset
    from stages.numerics.metrics import angular_error_deg, relit_psnr
    from stages.numerics.novel_view import relight_view
    from stages.numerics.relightset import draw_example, normals_to_camera, subject_frame
    from stages.numerics.sg import fit_sg_environment, rotate_environment, rotate_sg
    from stages.relightset import RelightSetStage, camera_centres, example_name, load_pool_map
    from synthetic.relight import TruthRelighter

    cap = open_capture(capture)
    report: dict = {"variants": [], "examples": args.examples, "quick": args.quick}
    rows_md = ["| variant | image PSNR dB | normal deg | albedo PSNR dB | render s/example | truth s | x_truth |",
               "|---|---|---|---|---|---|---|"]
    for action_id in [a for a in args.actions.split(",") if a]:
        session = cap.action(action_id).session_id
        stage = RelightSetStage(default_config())
        artifacts = ActionArtifacts.from_store(work / "artifacts", action_id, session, stage.requires)
        if artifacts is None:
            print(f"bench_relightset: no committed stage results for {action_id} under {work}; skipped")
            return 0
        maps, _ = stage.pool(capture)
        loaded = [load_pool_map(m, m.path) for m in maps]
        digests = [sha for _, sha in loaded]
        asset, cameras = load_relightable_asset(artifacts)
        centre, radius, distance = subject_frame(asset.vertices, camera_centres(cameras))
        t0 = time.perf_counter()
        truth = TruthRelighter(capture, action_id, lights=truth_lights)
        report["truth_setup_s"] = time.perf_counter() - t0
        fits: dict = {}
        for label, cfg in variant_configs(args.quick):
            scores, render_s, truth_s = {"image": [], "normal": [], "albedo": []}, [], []
            for index in range(args.examples):
                example_id = example_name(action_id, index)
                draw = draw_example(cfg.seed, example_id, digests, centre, radius, distance, cfg.size,
                                    cfg.elevation_deg, cfg.margin)
                env = loaded[draw["environment_index"]][0]
                key = (draw["environment_index"], cfg.sg_lobes, cfg.fit_height)
                if key not in fits:
                    fits[key] = fit_sg_environment(env, cfg.sg_lobes, fit_height=cfg.fit_height)
                lobes = rotate_sg(fits[key], math.radians(draw["rotation_deg"]))
                t0 = time.perf_counter()
                view = relight_view(asset, draw["K"], draw["cam_from_world"], cfg.size, cfg.size, [lobes],
                                    cfg.shading)
                render_s.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                true = truth.render(draw["K"], draw["cam_from_world"], cfg.size, cfg.size,
                                    rotate_environment(env, math.radians(draw["rotation_deg"])))
                truth_s.append(time.perf_counter() - t0)
                mask, true_mask = view["mask"], np.asarray(true["mask"], bool)
                both = mask & true_mask
                scores["image"].append(relit_psnr(view["images"][0], mask, true["radiance"], true_mask)["psnr_db"])
                ours = normals_to_camera(view["maps"]["normal"], draw["cam_from_world"])
                theirs = normals_to_camera(true["normals_world"], draw["cam_from_world"])
                scores["normal"].append(float(angular_error_deg(ours[both], theirs[both]).mean()))
                diff = np.clip(view["maps"]["albedo"][both], 0, 1) - np.clip(true["albedo"][both], 0, 1)
                scores["albedo"].append(float(-10 * np.log10(max(np.mean(diff ** 2), 1e-12))))
            row = {"variant": label, "action": action_id, "size": cfg.size, "sg_lobes": cfg.sg_lobes,
                   "image_psnr_db": float(np.mean(scores["image"])), "normal_mean_deg": float(np.mean(scores["normal"])),
                   "albedo_psnr_db": float(np.mean(scores["albedo"])), "render_s": float(np.mean(render_s)),
                   "truth_s": float(np.mean(truth_s)), "examples_per_s": 1.0 / float(np.mean(render_s)),
                   "x_truth": float(np.mean(truth_s) / np.mean(render_s))}
            report["variants"].append(row)
            rows_md.append(f"| {label} | {row['image_psnr_db']:.2f} | {row['normal_mean_deg']:.2f} | "
                           f"{row['albedo_psnr_db']:.2f} | {row['render_s']:.2f} | {row['truth_s']:.2f} | "
                           f"{row['x_truth']:.2f} |")
            print(rows_md[-1], flush=True)
    (out / "bench_relightset.json").write_text(json.dumps(report, indent=1))
    (out / "bench_relightset.md").write_text("\n".join(["# bench_relightset", "", f"truth setup (visibility of "
                                                        f"{truth_lights} lights, once per action): "
                                                        f"{report.get('truth_setup_s', 0):.1f} s", ""] + rows_md) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for row in report["variants"]:
        ax.scatter(row["render_s"], row["image_psnr_db"])
        ax.annotate(row["variant"], (row["render_s"], row["image_psnr_db"]), fontsize=7)
    ax.set_xlabel("seconds per example (stage renderer)")
    ax.set_ylabel("image PSNR vs simulator (dB)")
    ax.set_title("relighting set: time against error")
    fig.tight_layout()
    fig.savefig(out / "bench_relightset.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
