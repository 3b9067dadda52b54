"""Subject panel: the whole pipeline and its evaluation on subjects that span the bodies a user brings.

Each subject is its own one-action capture at the simulator's default width (320 px, 32 cameras, 512 LEDs), run
through every stage by ``ultrastage run`` (the ``default`` preset; its evaluation at the end is
``evaluation.release.evaluate_release``, the ``ultrastage evaluate`` figures), one subject at a time:

- MakeHuman bodies at the extremes of its macro targets (``SimConfig.body``): heavy (weight 1), thin (weight 0),
  tall (height 0.7, ~1.95 m), short (height 0.3, ~1.51 m), old (age 1, 90 years); the base body posed
  (pose_variation 0.8), with hair, and in a loose skirt;
- two meshes that are not MakeHuman's: the ICT-FaceKit head (``../shared/data/meshes/ict_face_neutral.obj``) and
  the simulator's procedural subject (capsules and a torus).

It writes ``bench_subjects.json`` (every subject's simulator settings, the commit it ran on, wall and CPU seconds
of its simulation and of its run, the load average at its start and end, and its evaluation figures; per figure
the worst subject; the subjects that miss Chamfer <= 1.5 mm, relit >= 25 dB or a figure of the paper's table 1)
and ``bench_subjects.md`` (the table: one row per figure, one column per subject, the worst case), and
``bench_subjects.png`` (Chamfer and relit PSNR per subject) into ``--out``; each subject's capture, release and
work folder under ``--out/subjects/<name>/``. A subject whose capture and evaluation are already there with the
same settings is read back, not run again (``--fresh`` simulates and runs it again; ``--rerun`` keeps its
simulation and runs the pipeline again on it, reusing its work folder's stages that did not change: a code change
measured on the same captures).

``--quick``: one subject (the MakeHuman body with a random shape, hair and a skirt; the procedural subject where
../shared is absent) on a tiny capture (96 px, 8 cameras, 128 LEDs, unsubdivided mesh) through the ``test`` preset
and the ``sync`` scheduler: it checks that the panel runs; its numbers are not measurements.

    nice -n 10 python bench/bench_subjects.py --out bench/out            # the panel: 4.5-7 CPU minutes a subject
    python bench/bench_subjects.py --out bench/out --subjects thin,short  # some of its subjects
    python bench/bench_subjects.py --quick --out /tmp/quick              # the tests' mode
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from _quick import QUICK_HELP, QUICK_PRESET, quick_capture_config  # noqa: E402

DEFAULT_SHARED = ROOT.parent / "shared" / "data"
CHAMFER_TARGET_MM = 1.5
RELIT_TARGET_DB = 25.0


@dataclass(frozen=True)
class Subject:
    """One panel subject: name, what it is, and the SimConfig fields its capture changes (``mesh``: a file name
    under the shared meshes folder, ``"procedural"``, or None for the MakeHuman body)."""
    name: str
    what: str
    changes: dict = field(default_factory=dict)
    mesh: str | None = None

    def sim_changes(self, meshes: Path) -> dict:
        mesh = self.mesh if self.mesh == "procedural" else str(meshes / (self.mesh or "makehuman_base.obj"))
        return {"mesh": mesh, **self.changes}

    @property
    def makehuman(self) -> bool:
        return self.mesh is None


SUBJECTS = (
    Subject("hair", "MakeHuman body with a hair volume", {"hair": 1.0}),
    Subject("skirt", "MakeHuman body in a loose skirt", {"garment": 1.0}),
    Subject("heavy", "MakeHuman body, weight 1 (max)", {"body": "weight=1"}),
    Subject("tall", "MakeHuman body, height 0.7", {"body": "height=0.7"}),
    Subject("posed", "MakeHuman body, pose variation 0.8", {"pose_variation": 0.8}),
    Subject("ict_face", "ICT-FaceKit head (not MakeHuman)", mesh="ict_face_neutral.obj"),
    Subject("procedural", "the simulator's procedural subject (not MakeHuman)", mesh="procedural"),
    Subject("thin", "MakeHuman body, weight 0 (min)", {"body": "weight=0"}),
    Subject("short", "MakeHuman body, height 0.3", {"body": "height=0.3"}),
    Subject("old", "MakeHuman body, age 1 (90 years)", {"body": "age=1"}),
)
"""The panel, in the order it runs (the new subject kinds first)."""
QUICK_SUBJECTS = (
    Subject("dressed", "MakeHuman body, random shape, hair and a skirt",
            {"body": "random", "hair": 1.0, "garment": 1.0}),
    Subject("procedural", "the simulator's procedural subject", mesh="procedural"),
)
"""The quick mode's subjects: the first whose mesh is there runs."""

FIGURES = (  # (metric key of evaluate's overall figures, title, better: "low" | "high", group)
    ("chamfer_mm", "Chamfer (mm)", "low", "mesh"),
    ("chamfer_pred_to_gt_mm", "Chamfer pred->gt (mm)", "low", "mesh"),
    ("chamfer_gt_to_pred_mm", "Chamfer gt->pred (mm)", "low", "mesh"),
    ("fscore_1mm", "F-score @1 mm", "high", "mesh"),
    ("fscore_5mm", "F-score @5 mm", "high", "mesh"),
    ("comparable_chamfer_mm", "Chamfer, comparable surface (mm)", "low", "mesh"),
    ("comparable_chamfer_pred_to_gt_mm", "comparable pred->gt (mm)", "low", "mesh"),
    ("comparable_chamfer_gt_to_pred_mm", "comparable gt->pred (mm)", "low", "mesh"),
    ("comparable_fscore_1mm", "comparable F-score @1 mm", "high", "mesh"),
    ("gt_unseen_area_fraction", "truth area no camera sees", "low", "mesh"),
    ("pred_seen_through_area_fraction", "mesh area off the truth where a camera sees through", "low", "mesh"),
    ("normal_consistency", "normal consistency", "high", "mesh"),
    ("heldout_albedo_psnr_db", "held-out albedo PSNR (dB)", "high", "table 1"),
    ("heldout_albedo_ssim", "held-out albedo SSIM", "high", "table 1"),
    ("heldout_albedo_rmse", "held-out albedo RMSE", "low", "table 1"),
    ("heldout_normal_mean_deg_diffuse", "held-out normals, specular out (deg)", "low", "table 1"),
    ("heldout_normal_under5_pct_diffuse", "held-out normals < 5 deg, specular out (%)", "high", "table 1"),
    ("heldout_normal_under25_pct_diffuse", "held-out normals < 25 deg, specular out (%)", "high", "table 1"),
    ("heldout_normal_mean_deg", "held-out normals, photometric maps (deg)", "low", "table 1"),
    ("heldout_normal_under5_pct", "held-out normals < 5 deg, photometric maps (%)", "high", "table 1"),
    ("heldout_normal_under25_pct", "held-out normals < 25 deg, photometric maps (%)", "high", "table 1"),
    ("normal_mean_deg", "normals, photometric (deg)", "low", "normals"),
    ("normal_mean_deg_diffuse", "normals, specular out (deg)", "low", "normals"),
    ("best_normal_mean_deg", "best normals (deg)", "low", "normals"),
    ("albedo_psnr_db", "albedo PSNR (dB)", "high", "materials"),
    ("roughness_mae", "roughness MAE", "low", "materials"),
    ("relit_psnr_db", "relit PSNR (dB)", "high", "relighting"),
    ("comparable_relit_psnr_db", "comparable relit PSNR (dB)", "high", "relighting"),
    ("composited_relit_psnr_db", "composited relit PSNR (dB; both images over black)", "high", "relighting"),
    ("relightset_image_psnr_db", "relighting set image PSNR (dB)", "high", "relighting"),
    ("comparable_relightset_image_psnr_db", "comparable relighting set image PSNR (dB)", "high", "relighting"),
    ("composited_relightset_image_psnr_db", "composited relighting set image PSNR (dB)", "high", "relighting"),
    ("relightset_normal_mean_deg", "relighting set normals (deg)", "low", "relighting"),
    ("relightset_albedo_psnr_db", "relighting set albedo PSNR (dB)", "high", "relighting"),
)
"""What the table shows of each subject's evaluation; ``best_normal_mean_deg`` is the better of the photometric and
the specular-out normals; the held-out table 1 is the plain albedo and the ``normal_diffuse`` maps' normals (as
the README's default-capture figures), the photometric maps' held-out normals beside it; the ``comparable_*`` mesh
figures are over the truth a camera sees, away from an open mesh's boundary (``evaluation.release.MESH_METRICS``),
the ``comparable_*`` relit figures without the pixels where the truth shows an open mesh's inside
(``evaluation.release.comparable_exclude``), the ``composited_*`` ones with both images compared as they are over
black (``stages.numerics.metrics.relit_psnr``'s ``composited``)."""


def figures_of(overall: dict) -> dict[str, float]:
    """The FIGURES of one evaluation's overall figures (finite ones only), with the best normals added."""
    out = {key: float(overall[key]) for key, *_ in FIGURES
           if key in overall and isinstance(overall[key], (int, float)) and math.isfinite(overall[key])}
    normals = [out[k] for k in ("normal_mean_deg", "normal_mean_deg_diffuse") if k in out]
    if normals:
        out["best_normal_mean_deg"] = min(normals)
    return out


def worst_cases(per_subject: dict[str, dict[str, float]]) -> dict[str, dict]:
    """Per figure the worst subject and its value (the highest of a lower-is-better figure, else the lowest)."""
    worst = {}
    for key, _, better, _ in FIGURES:
        values = {name: f[key] for name, f in per_subject.items() if key in f}
        if values:
            name = (max if better == "low" else min)(values, key=values.get)
            worst[key] = {"subject": name, "value": values[name]}
    return worst


def misses(per_subject: dict[str, dict[str, float]]) -> dict[str, list[str]]:
    """The subjects that miss each target: Chamfer <= 1.5 mm and relit >= 25 dB (plain and comparable), and each of
    the paper's table-1 figures (evaluation.heldout.PAPER_TABLE1; the normals' both with the specular fit out,
    ``*_diffuse``, and from the photometric maps; a subject without the figure is not listed)."""
    from evaluation.heldout import PAPER_TABLE1

    better = {key: b for key, _, b, _ in FIGURES}
    out = {"chamfer_mm > 1.5": [n for n, f in per_subject.items() if f.get("chamfer_mm", 0.0) > CHAMFER_TARGET_MM],
           "comparable_chamfer_mm > 1.5": [n for n, f in per_subject.items()
                                           if f.get("comparable_chamfer_mm", 0.0) > CHAMFER_TARGET_MM],
           "relit_psnr_db < 25": [n for n, f in per_subject.items()
                                  if f.get("relit_psnr_db", math.inf) < RELIT_TARGET_DB],
           "comparable_relit_psnr_db < 25": [n for n, f in per_subject.items()
                                             if f.get("comparable_relit_psnr_db", math.inf) < RELIT_TARGET_DB]}
    for paper_key, paper in PAPER_TABLE1.items():
        for key in (paper_key, f"{paper_key}_diffuse"):  # the normals: specular out and photometric maps
            if key not in better:
                continue
            worse = [n for n, f in per_subject.items() if key in f
                     and (f[key] > paper if better[key] == "low" else f[key] < paper)]
            out[f"{key} worse than the paper's {paper}"] = worse
    return out


def markdown(report: dict) -> str:
    """The panel's table: one row per figure, one column per subject, then the worst case."""
    from evaluation.heldout import PAPER_TABLE1

    names = list(report["subjects"])
    per = {n: report["subjects"][n]["figures"] for n in names}
    lines = [f"## Subject panel{' (quick: not measurements)' if report['quick'] else ''}", "",
             f"{len(names)} subjects, one action each, {report['width']} px wide, preset `{report['preset']}`; "
             f"{report['seconds']:.0f} s in all. Targets: Chamfer <= {CHAMFER_TARGET_MM} mm, relit >= "
             f"{RELIT_TARGET_DB:.0f} dB, the paper's table 1 (column `paper`).", "",
             "| figure | " + " | ".join(names) + " | worst | paper |",
             "|---|" + "---:|" * (len(names) + 2)]
    for key, title, _, _ in FIGURES:
        if not any(key in per[n] for n in names):
            continue
        cells = [_fmt(per[n].get(key)) for n in names]
        worst = report["worst"].get(key)
        worst_cell = f"{_fmt(worst['value'])} ({worst['subject']})" if worst else ""
        paper = PAPER_TABLE1.get(key.removesuffix("_diffuse"))
        lines.append(f"| {title} | " + " | ".join(cells) + f" | {worst_cell} | {_fmt(paper)} |")
    lines.append("| seconds (simulate + run) | " + " | ".join(
        f"{report['subjects'][n]['simulate_s']:.0f} + {report['subjects'][n]['run_s']:.0f}"
        + ("*" if report["subjects"][n].get("work_reused") else "") for n in names) + " | | |")
    lines.append("| CPU seconds (simulate + run) | " + " | ".join(
        f"{report['subjects'][n]['simulate_cpu_s']:.0f} + {report['subjects'][n]['run_cpu_s']:.0f}"
        if "run_cpu_s" in report["subjects"][n] else "" for n in names) + " | | |")
    if any(report["subjects"][n].get("work_reused") for n in names):
        lines += ["", "\\* run again on its simulation and work folder (`--rerun`): only the stages that changed ran."]
    commits = sorted({report["subjects"][n].get("code", {}).get("commit", "?")[:7] for n in names})
    lines += ["", f"Code: commit {', '.join(commits)} (the commit each subject ran on)."]
    lines += ["", "Subjects:", ""]
    lines += [f"- `{n}`: {report['subjects'][n]['what']}" + (f" (failed: {report['subjects'][n]['error']})"
                                                           if report['subjects'][n].get('error') else "")
              for n in names]
    lines += ["", "Misses:", ""]
    lines += [f"- {target}: {', '.join(who) if who else 'none'}" for target, who in report["misses"].items()]
    return "\n".join(lines) + "\n"


def _fmt(value) -> str:
    if value is None:
        return ""
    return f"{value:.3f}" if abs(value) < 10 else f"{value:.2f}"


def what_to_reuse(saved: dict, settings: dict, capture_there: bool, fresh: bool, rerun: bool) -> str:
    """What of a subject's earlier run to keep: ``"record"`` (its saved figures: same settings, not ``fresh`` nor
    ``rerun``), ``"simulation"`` (``rerun`` with the same settings and its capture there: run the pipeline again on
    it) or ``"nothing"`` (simulate and run)."""
    same = bool(saved) and saved.get("settings") == json.loads(json.dumps(settings))
    if fresh or not same:
        return "nothing"
    if not rerun:
        return "record" if "figures" in saved else "nothing"
    return "simulation" if capture_there and "simulate_s" in saved else "nothing"


def run_subject(subject: Subject, folder: Path, sim_changes: dict, preset: str, quick: bool, fresh: bool,
                rerun: bool = False) -> dict:
    """Simulate, run and evaluate one subject under ``folder``; its record (settings, seconds, figures). ``rerun``:
    keep a simulation made with the same settings and run the pipeline again on it (its work folder kept)."""
    from synthetic import SimConfig, simulate
    from synthetic.calibration import CalibrationConfig

    config = SimConfig(actions=1, **sim_changes)
    settings = {"simulator": config.to_json(), "preset": preset}
    record_path = folder / "subject.json"
    saved = json.loads(record_path.read_text()) if record_path.is_file() else {}
    reuse = what_to_reuse(saved, settings, (folder / "capture" / "capture.json").is_file(), fresh, rerun)
    if reuse == "record":
        print(f"== {subject.name}: read back ({record_path})", flush=True)
        if "evaluation" in saved:  # the table's figures from the saved evaluation, as FIGURES lists them now
            saved["figures"] = figures_of(saved["evaluation"])
        return saved
    keep = reuse == "simulation"
    record: dict = {"what": subject.what, "settings": settings, "code": code_version(),
                    "load_average_at_start": os.getloadavg()[0], "work_reused": keep}
    if keep:
        print(f"== {subject.name}: running again on its simulation ({folder / 'capture'})", flush=True)
        record["simulate_s"], record["simulate_cpu_s"] = saved["simulate_s"], saved["simulate_cpu_s"]
        shutil.rmtree(folder / "release", ignore_errors=True)
    else:
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        started, cpu = time.perf_counter(), cpu_seconds()
        print(f"== {subject.name}: simulating ({subject.what})", flush=True)
        simulate(folder / "capture", config, calibration=CalibrationConfig())
        record["simulate_s"], record["simulate_cpu_s"] = time.perf_counter() - started, cpu_seconds() - cpu
    started, cpu = time.perf_counter(), cpu_seconds()
    command = [sys.executable, "-m", "ultrastage.cli", "run", "--capture", str(folder / "capture"),
               "--release", str(folder / "release"), "--preset", preset] + (["--scheduler", "sync"] if quick else [])
    env = os.environ | {"PYTHONPATH": os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p])}
    if quick:
        env["OMP_WAIT_POLICY"] = env.get("OMP_WAIT_POLICY", "PASSIVE")
    with open(folder / "run.log", "w") as log:
        proc = subprocess.run(command, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    record["run_s"], record["run_cpu_s"] = time.perf_counter() - started, cpu_seconds() - cpu
    record["load_average_at_end"] = os.getloadavg()[0]
    record["run_exit"] = proc.returncode
    evaluated = folder / "release.work" / "evaluated.json"
    overall = json.loads(evaluated.read_text())["overall"] if evaluated.is_file() else {}
    record["figures"] = figures_of(overall)
    record["evaluation"] = {k: v for k, v in overall.items()
                            if isinstance(v, (int, float)) and math.isfinite(v)}
    if proc.returncode or not overall:
        record["error"] = f"run exit {proc.returncode}, see {folder / 'run.log'}"
    record_path.write_text(json.dumps(record, indent=1, sort_keys=True))
    print(f"== {subject.name}: simulate {record['simulate_s']:.0f} s, run + evaluate {record['run_s']:.0f} s, "
          f"Chamfer {record['figures'].get('chamfer_mm', float('nan')):.2f} mm, relit "
          f"{record['figures'].get('relit_psnr_db', float('nan')):.2f} dB", flush=True)
    return record


def cpu_seconds() -> float:
    """CPU seconds (user + system) of this process and of its children that have ended."""
    import resource

    return sum(u.ru_utime + u.ru_stime for u in (resource.getrusage(resource.RUSAGE_SELF),
                                                  resource.getrusage(resource.RUSAGE_CHILDREN)))


def code_version() -> dict:
    """The repository's commit and whether its pipeline code (everything but bench/) differs from it; empty
    where git or the repository is not there."""
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                                check=True).stdout.strip()
        changed = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                                  ":(exclude)bench"], cwd=ROOT, capture_output=True, text=True,
                                 check=True).stdout.split("\n")
    except (OSError, subprocess.CalledProcessError):
        return {}
    return {"commit": commit, "pipeline_changed": [line[3:] for line in changed if line.strip()]}


def mesh_present(subject: Subject, meshes: Path) -> bool:
    """Whether the subject's mesh is there (the procedural subject always is)."""
    mesh = subject.sim_changes(meshes)["mesh"]
    return mesh == "procedural" or Path(mesh).is_file()


def plot(report: dict, path: Path) -> None:
    """Chamfer and relit PSNR per subject as two bar charts, with the targets."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(report["subjects"])
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
    for ax, key, target, title in ((axes[0], "chamfer_mm", CHAMFER_TARGET_MM, "Chamfer (mm), lower is better"),
                                   (axes[1], "relit_psnr_db", RELIT_TARGET_DB, "relit PSNR (dB), higher is better")):
        values = [report["subjects"][n]["figures"].get(key, 0.0) for n in names]
        ax.bar(range(len(names)), values, color="tab:blue")
        ax.axhline(target, color="tab:red", linestyle="--", label="target")
        ax.set_xticks(range(len(names)), names, rotation=40, ha="right")
        ax.set_title(title)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(HERE / "out"))
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    parser.add_argument("--subjects", help="comma-separated subject names (default: all of the panel)")
    parser.add_argument("--shared", default=os.environ.get("ULTRASTAGE_SHARED_DATA", str(DEFAULT_SHARED)),
                        help="the shared data folder (meshes/ inside; default ../shared/data beside the repository)")
    parser.add_argument("--fresh", action="store_true", help="simulate and run every subject again, even one already "
                                                               "evaluated")
    parser.add_argument("--rerun", action="store_true", help="run the pipeline again on every subject's simulation "
                                                               "(simulated again only where its settings changed)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meshes = Path(args.shared) / "meshes"
    panel = tuple(s for s in QUICK_SUBJECTS if mesh_present(s, meshes))[:1] if args.quick else SUBJECTS
    if args.subjects:
        wanted = args.subjects.split(",")
        panel = QUICK_SUBJECTS if args.quick else SUBJECTS
        unknown = sorted(set(wanted) - {s.name for s in panel})
        if unknown:
            parser.error(f"unknown subjects {unknown}; the panel's are {[s.name for s in panel]}")
        panel = tuple(s for s in panel if s.name in wanted)
    preset = QUICK_PRESET if args.quick else "default"
    quick_changes = {}
    if args.quick:
        from synthetic import SimConfig

        defaults = SimConfig()
        quick_changes = {k: v for k, v in quick_capture_config().to_json().items()
                         if k not in ("actions", "mesh") and getattr(defaults, k) != v}
    started = time.perf_counter()
    subjects, skipped = {}, []
    for subject in panel:
        changes = subject.sim_changes(meshes)
        if not mesh_present(subject, meshes):
            print(f"== {subject.name}: skipped, {changes['mesh']} not found", flush=True)
            skipped.append(subject.name)
            continue
        subjects[subject.name] = run_subject(subject, out / "subjects" / subject.name, quick_changes | changes,
                                             preset, args.quick, args.fresh, args.rerun)
    per = {n: r["figures"] for n, r in subjects.items()}
    width = (quick_capture_config().width if args.quick else __import__("synthetic").SimConfig().width)
    report = {"quick": args.quick, "preset": preset, "width": width, "seconds": time.perf_counter() - started,
              "subjects": subjects, "skipped": skipped, "worst": worst_cases(per), "misses": misses(per)}
    (out / "bench_subjects.json").write_text(json.dumps(report, indent=1, sort_keys=True))
    (out / "bench_subjects.md").write_text(markdown(report))
    if subjects:
        plot(report, out / "bench_subjects.png")
    print(markdown(report))
    failed = [n for n, r in subjects.items() if r.get("error")]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
