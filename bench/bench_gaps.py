"""The masks' filled holes decided across views, against the simulator's true masks: what each rule opens.

A run's photometric store keeps each view's mask and the holes its cleanup filled (``filled_holes``). Per action,
every rule below decides those holes again, and each hole's pixels are scored against the true mask:

- ``fill every hole``: the masks as the single-view cleanup leaves them (the baseline, no decision);
- ``open every hole``: the opposite single-view rule;
- ``across views``: :func:`stages.numerics.gaps.see_through_holes` with the stage's :class:`GapConfig`, beside a
  sweep of its ``max_blocked`` and ``min_votes``;
- ``gradient ratios``: :func:`stages.numerics.gaps.backdrop_holes` alone (one view at a time), at the stage's
  ``backdrop_ratio_max`` and beside it;
- ``across views or gradient ratios (stage)``: either test opens a hole (what ``make dataset`` ships).

Scored in pixels: the true gaps opened and left filled, the subject's surface opened (a dark patch taken for a gap:
the error that carves tunnels into the mesh) and kept, and the masks' IoU with the truth on the views with holes;
the seconds of each decision. ``python bench/bench_gaps.py --release runs/R/release --capture runs/R/capture``
(default runs/default); ``--quick``: the tiny run of the tests, whose holes may be none; its numbers are not
measurements.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import write_report  # noqa: E402
from _release import check_inputs, parse_release_args, release_parser, store_artifacts  # noqa: E402

SWEEP = (("max_blocked", 0.25), ("max_blocked", 0.75), ("min_votes", 3))
"""The stage's config with one field of the test across views changed, one row each."""
RATIO_SWEEP = (0.1, 0.3)
"""Other ``backdrop_ratio_max`` of the gradient-ratio test alone, one row each."""
STAGE = "across views or gradient ratios (stage)"
"""The row of the stage's own rule."""


def action_views(release: Path, truth: Path, action: str) -> dict:
    """The action's calibrated views with filled holes: ids, filled masks, holes, true masks, cameras and the decoded
    gradient images of the views with holes (None for the others)."""
    from pipeline.codecs.image import mask_from_png, read_png

    art = store_artifacts(release, action, ("decode", "photometric"))
    views: dict = {"ids": [], "filled": [], "holes": [], "truth": [], "K": [], "T": [], "pos": [], "neg": []}
    for cam_id, cam in sorted(art.cameras().items()):
        mask = art.mask(cam_id)
        path = art.path("filled_holes", cam_id)
        holes = mask_from_png(read_png(path)) if path.exists() else np.zeros_like(mask)
        views["ids"].append(cam_id)
        views["filled"].append(mask | holes)
        views["holes"].append(holes)
        views["truth"].append(mask_from_png(read_png(truth / action / "mask" / f"{cam_id}.png")))
        views["K"].append(cam.K)
        views["T"].append(cam.cam_from_world)
        views["pos"].append(art.exr("pos", cam_id) if holes.any() else None)
        views["neg"].append(art.exr("neg", cam_id) if holes.any() else None)
    return views


def score(views: dict, opened: list[np.ndarray]) -> dict:
    """Pixels of the holes by truth and decision, and the mean mask IoU over the views with holes."""
    counts = {"gap_opened_px": 0, "gap_left_px": 0, "surface_opened_px": 0, "surface_kept_px": 0}
    ious = []
    for filled, holes, truth, open_ in zip(views["filled"], views["holes"], views["truth"], opened):
        if not holes.any():
            continue
        gap = holes & ~truth
        surface = holes & truth
        counts["gap_opened_px"] += int((gap & open_).sum())
        counts["gap_left_px"] += int((gap & ~open_).sum())
        counts["surface_opened_px"] += int((surface & open_).sum())
        counts["surface_kept_px"] += int((surface & ~open_).sum())
        mask = filled & ~open_
        ious.append(float((mask & truth).sum() / max(int((mask | truth).sum()), 1)))
    return counts | {"mask_iou": float(np.mean(ious)) if ious else None, "views_with_holes": len(ious)}


def rules() -> list[tuple[str, object]]:
    """(row name, rule): a single-view rule's name (``fill``, ``open``), or ``(tests, GapConfig)`` with tests a
    subset of ``across`` and ``ratio``."""
    from stages.numerics.gaps import GapConfig

    base = GapConfig()
    return ([("fill every hole", "fill"), ("open every hole", "open"), (STAGE, ({"across", "ratio"}, base)),
             ("across views", ({"across"}, base))]
            + [(f"across views, {field} {value}", ({"across"}, dataclasses.replace(base, **{field: value})))
               for field, value in SWEEP]
            + [(f"gradient ratios {base.backdrop_ratio_max:g}", ({"ratio"}, base))]
            + [(f"gradient ratios {value:g}", ({"ratio"}, dataclasses.replace(base, backdrop_ratio_max=value)))
               for value in RATIO_SWEEP])


def measure_action(release: Path, truth: Path, action: str) -> dict:
    from stages.numerics.gaps import background_holes, backdrop_holes, see_through_holes
    from stages.numerics.hull import default_stage_box, subject_box

    views = action_views(release, truth, action)
    rows = {}
    box = None
    for name, rule in rules():
        start = time.perf_counter()
        if rule == "fill":
            opened = [np.zeros_like(h) for h in views["holes"]]
        elif rule == "open":
            opened = [h.copy() for h in views["holes"]]
        elif not any(h.any() for h in views["holes"]):
            opened = [np.zeros_like(h) for h in views["holes"]]
        else:
            tests, config = rule
            if "across" in tests and box is None:
                box = subject_box(views["filled"], views["K"], views["T"],
                                  default_stage_box(list(zip(views["K"], views["T"]))))
            if tests == {"across", "ratio"}:
                gradients = [(p, n) if p is not None else None for p, n in zip(views["pos"], views["neg"])]
                opened = background_holes(views["filled"], views["holes"], views["K"], views["T"], box, gradients,
                                          config)[0]
            elif tests == {"across"}:
                opened = see_through_holes(views["filled"], views["holes"], views["K"], views["T"], box, config).gaps
            else:
                opened = [backdrop_holes(h, m, p, n, config.backdrop_ratio_max)[0] if h.any() else np.zeros_like(h)
                          for h, m, p, n in zip(views["holes"], views["filled"], views["pos"], views["neg"])]
        rows[name] = score(views, opened) | {"seconds": time.perf_counter() - start}
    return rows


def summarise(per_action: dict[str, dict]) -> dict:
    """Per rule: the pixel counts summed over the actions, the mean IoU, the worst action (most surface opened, then
    the least share of its gaps opened) and the mean seconds."""
    out = {}
    for name, _ in rules():
        rows = [a[name] for a in per_action.values()]
        total = {k: sum(r[k] for r in rows) for k in ("gap_opened_px", "gap_left_px", "surface_opened_px",
                                                      "surface_kept_px")}
        gaps = total["gap_opened_px"] + total["gap_left_px"]
        share = [r["gap_opened_px"] / (r["gap_opened_px"] + r["gap_left_px"]) for r in rows
                 if r["gap_opened_px"] + r["gap_left_px"]]
        ious = [r["mask_iou"] for r in rows if r["mask_iou"] is not None]
        worst = max(per_action, key=lambda a: (per_action[a][name]["surface_opened_px"],
                                               -per_action[a][name]["gap_opened_px"]))
        out[name] = total | {
            "gap_opened_share": total["gap_opened_px"] / gaps if gaps else None,
            "worst_action_gap_opened_share": min(share) if share else None,
            "worst_action_surface_opened_px": max(r["surface_opened_px"] for r in rows),
            "worst_action": worst,
            "mask_iou": float(np.mean(ious)) if ious else None,
            "seconds_per_action": float(np.mean([r["seconds"] for r in rows])) if rows else 0.0}
    return out


def _f(value, digits: int) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def markdown(report: dict) -> str:
    lines = [f"# Filled holes decided ({report['release']}{'; quick: not measurements' if report['quick'] else ''})", "",
             "Pixels of the holes the masks' cleanup filled, by the true mask: a true gap opened is right, a surface "
             "opened (a dark patch taken for a gap) is the error that carves the mesh.", "",
             "| rule | gaps opened (px) | gaps left (px) | share of gaps opened (worst action) | surface opened (px, "
             "worst action) | surface kept (px) | mask IoU, views with holes | s / action |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, r in report["summary"].items():
        lines.append(f"| {name} | {r['gap_opened_px']} | {r['gap_left_px']} | {_f(r['gap_opened_share'], 3)} "
                     f"({_f(r['worst_action_gap_opened_share'], 3)}) | {r['surface_opened_px']} "
                     f"({r['worst_action_surface_opened_px']}) | {r['surface_kept_px']} | {_f(r['mask_iou'], 4)} | "
                     f"{r['seconds_per_action']:.2f} |")
    lines += ["", "Per action (the stage's rule): " + "; ".join(
        f"{a}: {r[STAGE]['gap_opened_px']} gap px opened, {r[STAGE]['gap_left_px']} "
        f"left, {r[STAGE]['surface_opened_px']} surface px opened"
        for a, r in report["actions"].items()), ""]
    return "\n".join(lines)


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, r in report["summary"].items():
        ax.scatter(r["surface_opened_px"], r["gap_left_px"], s=40)
        ax.annotate(f"{name} ({r['seconds_per_action']:.1f} s)", (r["surface_opened_px"], r["gap_left_px"]),
                    fontsize=7, xytext=(4, 4), textcoords="offset points")
    ax.set_xlabel("surface pixels opened (dark patches taken for gaps)")
    ax.set_ylabel("true gap pixels left filled")
    ax.set_title("filled holes: each rule's two errors (lower left is right)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = release_parser(__doc__, actions="")
    args = parse_release_args(parser, argv)
    release, capture = Path(args.release), Path(args.capture)
    go, truth = check_inputs("bench_gaps", release, capture, need_truth=True)
    if not go:
        return 0
    from manifests import open_release

    actions = [a for a in args.actions.split(",") if a] or sorted(open_release(release).action_ids)
    per_action = {}
    for action in actions:
        per_action[action] = measure_action(release, truth, action)
        stage = per_action[action][STAGE]
        print(f"{action}: {stage['gap_opened_px']} gap px opened, {stage['surface_opened_px']} surface px opened "
              f"({stage['seconds']:.1f} s)", flush=True)
    report = {"release": str(release), "capture": str(capture), "quick": bool(args.quick), "actions": per_action,
              "summary": summarise(per_action)}
    write_report(args.out, "bench_gaps", report, markdown(report), lambda p: plot(report, p))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
