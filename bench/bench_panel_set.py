"""The relighting set drawn from the subject panel, and the single-image baselines trained on it against one body.

Two training sets are measured on the same test examples (the panel subjects named by ``--test``), each made by
``ultrastage merge-sets`` (:func:`ultrastage.merge_sets.merge_relight_sets`, ``--subject-from release``, so every
panel subject is its own subject and all of its examples are in one split):

- ``panel``: the examples of every other panel subject (``bench_subjects``' releases, ``--panel
  DIR/subjects/<name>/release``);
- ``one_body``: the examples of the one-body release (``--one-body``, e.g. ``make dataset``'s: one MakeHuman body
  in two skins).

AlbedoNet and NormalNet are trained on each with the ``--preset`` (``cpu``) and measured on the test split
(:func:`ultrastage.baselines.train.train`) against the trivial baselines (the linearised photo as the albedo, a
camera-facing normal): split-wide metrics (masked pixels), and per test subject the albedo PSNR and the normals'
mean angle, with the worst subject. Torch runs on ``--threads`` threads (1: on a machine shared with other work,
spinning OpenMP threads made a step up to ten times slower).

    python bench/bench_panel_set.py --out bench/out      # after `make panel` and `make dataset` (--panel, --one-body)
    python bench/bench_panel_set.py --quick --out /tmp/quick     # the tests' mode: not measurements

writes OUT/bench_panel_set.json and .md; the merged sets under OUT/panel_set/sets/ and the checkpoints under
OUT/panel_set/train/<set>/<network>/. ``--quick``: the tiny run of ``bench/_quick.py`` merged under two names (one
for training, one for testing) and the ``tiny`` preset for a few steps.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from _quick import QUICK_HELP, quick_run  # noqa: E402

DEFAULT_TEST = ("heavy", "old", "ict_face")
"""Held-out panel subjects: two MakeHuman extremes and a mesh that is not MakeHuman's."""
NETWORKS = ("albedonet", "normalnet")
HEADLINE = {"albedonet": [("albedo_psnr_raw_db", "PSNR raw dB", 2), ("albedo_psnr_scaled_db", "PSNR scaled dB", 2),
                          ("albedo_ssim_raw", "SSIM raw", 4), ("albedo_ssim_scaled", "SSIM scaled", 4),
                          ("albedo_rmse_raw", "RMSE raw", 4)],
            "normalnet": [("normal_mean_deg", "mean deg", 2), ("normal_median_deg", "median deg", 2),
                          ("normal_under_11_25_pct", "< 11.25 deg %", 1), ("normal_under_30_pct", "< 30 deg %", 1)]}
"""Per network, the split-wide metrics of the table: (metric, label, decimals)."""
PER_SUBJECT = {"albedonet": ("albedo_psnr_raw_db", "albedo PSNR raw dB", max),
               "normalnet": ("normal_mean_deg", "normals mean deg", min)}
"""Per network, the per-subject figure and which way is better (for the worst subject)."""


def panel_releases(panel: Path) -> dict[str, Path]:
    """``{subject: release}`` of every panel subject under ``panel/subjects/`` with a relighting set."""
    found = {}
    for release in sorted((Path(panel) / "subjects").glob("*/release")):
        if (release / "manifests" / "relight_examples.parquet").is_file():
            found[release.parent.name] = release
    return found


def build_sets(panel: dict[str, Path], one_body: Path, test: tuple[str, ...], out: Path) -> dict[str, Path]:
    """The ``panel`` and ``one_body`` training sets with the same test subjects, merged under ``out``."""
    from ultrastage.merge_sets import SetSource, merge_relight_sets

    missing = [t for t in test if t not in panel]
    if missing:
        raise SystemExit(f"bench_panel_set: test subject(s) {', '.join(missing)} not in the panel "
                         f"({', '.join(panel) or 'none found'})")
    sets = {"panel": out / "panel", "one_body": out / "one_body"}
    merge_relight_sets([SetSource(n, p) for n, p in panel.items()], sets["panel"], subject_from="release",
                       test=test, replace=True)
    merge_relight_sets([SetSource("onebody", one_body)] + [SetSource(n, panel[n]) for n in test],
                       sets["one_body"], subject_from="release", test=test, replace=True)
    return sets


def subject_of(example_id: str, sources: list[str]) -> str:
    """The source (panel subject) an example id of a merged set comes from (the longest matching prefix)."""
    matches = [s for s in sources if example_id.startswith(s + "_")]
    return max(matches, key=len) if matches else example_id


def summarise(rows: list[dict], network: str, sources: list[str]) -> dict:
    """Split-wide metrics per method, and the per-subject figure of :data:`PER_SUBJECT` per method."""
    overall: dict[str, dict[str, float]] = {}
    per_subject: dict[str, dict[str, list[float]]] = {}
    metric = PER_SUBJECT[network][0]
    for row in rows:
        if row["example_id"] == "*":
            overall.setdefault(row["method"], {})[row["metric"]] = float(row["value"])
        elif row["metric"] == metric:
            subject = subject_of(row["example_id"], sources)
            per_subject.setdefault(row["method"], {}).setdefault(subject, []).append(float(row["value"]))
    return {"overall": overall,
            "per_subject": {m: {s: sum(v) / len(v) for s, v in subjects.items()} for m, subjects in per_subject.items()}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(HERE / "out"))
    parser.add_argument("--panel", help="bench_subjects' --out folder (its subjects/<name>/release; default --out)")
    parser.add_argument("--one-body", default=str(ROOT / "runs" / "default" / "release"),
                        help="a release of one body (default make dataset's runs/default/release)")
    parser.add_argument("--test", default=",".join(DEFAULT_TEST), help="comma-separated held-out panel subjects")
    parser.add_argument("--preset", default="cpu", help="training preset (ultrastage.baselines.config.PRESETS)")
    parser.add_argument("--steps", type=int, default=0, help="training steps (0: the preset's)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--seed", type=int, default=0, help="training seed (initial weights, crops, flips)")
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    work = out / "panel_set"

    from ultrastage.baselines.config import preset
    from ultrastage.baselines.train import train

    if args.quick:
        release = quick_run(out) / "release"
        panel, one_body, test = {"qa": release, "qb": release}, release, ("qb",)
        args.preset, args.steps = "tiny", 4
    else:
        panel, one_body = panel_releases(Path(args.panel or out)), Path(args.one_body)
        if not panel or not (one_body / "manifests" / "relight_examples.parquet").is_file():
            print(f"bench_panel_set: needs the panel's releases ({Path(args.panel or out) / 'subjects'}, "
                  f"`make panel`) and a one-body release with a relighting set ({one_body}, `make dataset`); skipped")
            return 0
        test = tuple(t for t in args.test.split(",") if t)
    sets = build_sets(panel, one_body, test, work / "sets")
    sources = sorted(set(panel) | {"onebody"})

    report: dict = {"quick": args.quick, "preset": args.preset, "threads": args.threads, "seed": args.seed,
                    "test_subjects": list(test),
                    "sets": {}, "results": {}}
    for set_name, folder in sets.items():
        record = json.loads((folder / "merge.json").read_text())
        report["sets"][set_name] = {"examples": record["examples"], "subjects": record["subjects"]}
    for network in NETWORKS:
        for set_name, folder in sets.items():
            config = preset(args.preset, network)
            config = dataclasses.replace(config, threads=args.threads, device="cpu", seed=args.seed,
                                         **({"steps": args.steps} if args.steps else {}))
            shutil.rmtree(work / "train" / set_name / network, ignore_errors=True)  # the sets change: never resume
            started, cpu = time.perf_counter(), time.process_time()
            result = train(folder, config, work / "train" / set_name / network, log=lambda *_: None)
            summary = summarise(result.metrics, network, sources)
            summary.update(steps=result.step, seconds=round(time.perf_counter() - started, 1),
                           cpu_seconds=round(time.process_time() - cpu, 1))
            report["results"].setdefault(network, {})[set_name] = summary
            print(f"bench_panel_set: {network} on {set_name}: {result.step} steps, {summary['seconds']} s")
    (out / "bench_panel_set.json").write_text(json.dumps(report, indent=1) + "\n")
    (out / "bench_panel_set.md").write_text(markdown(report))
    print(markdown(report))
    return 0


def markdown(report: dict) -> str:
    """The report's tables: per network, the trivial baseline and the network trained on each set."""
    from ultrastage.baselines.train import TRIVIAL_METHOD

    sets = report["sets"]
    lines = [f"## The baselines on the panel's relighting set{' (quick: not measurements)' if report['quick'] else ''}",
             "",
             f"Test split: the panel subjects {', '.join(report['test_subjects'])} "
             f"({sets['panel']['examples']['test']} examples). Training sets: "
             + "; ".join(f"`{n}` {s['examples']['train']} examples of {len(s['subjects']['train'])} subject(s)"
                         for n, s in sets.items())
             + f". Preset `{report['preset']}`, training seed {report.get('seed', 0)}, {report['threads']} thread(s).", ""]
    for network, by_set in report["results"].items():
        trivial = TRIVIAL_METHOD[network]
        columns = [(f"{trivial} (trivial)", by_set["panel"]["overall"][trivial],
                    by_set["panel"]["per_subject"].get(trivial, {}))]
        columns += [(f"{network} on {name}", s["overall"][network], s["per_subject"].get(network, {}))
                    for name, s in by_set.items()]
        lines += [f"### {network}", "", "| figure | " + " | ".join(c[0] for c in columns) + " |",
                  "|---|" + "---:|" * len(columns)]
        for metric, label, digits in HEADLINE[network]:
            lines.append(f"| {label} | " + " | ".join(f"{c[1].get(metric, float('nan')):.{digits}f}" for c in columns)
                         + " |")
        metric, label, better = PER_SUBJECT[network]
        subjects = sorted({s for c in columns for s in c[2]})
        for subject in subjects:
            lines.append(f"| {label}, {subject} | " + " | ".join(
                f"{c[2][subject]:.2f}" if subject in c[2] else "-" for c in columns) + " |")
        worst = min if better is max else max
        lines.append(f"| worst subject ({label}) | " + " | ".join(
            (lambda s: f"{s[1]:.2f} ({s[0]})")(worst(c[2].items(), key=lambda kv: kv[1])) if c[2] else "-"
            for c in columns) + " |")
        lines.append("| training seconds (CPU) | - | " + " | ".join(
            f"{s['seconds']:.0f} ({s['cpu_seconds']:.0f})" for s in by_set.values()) + " |")
        lines.append("")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    sys.exit(main())
