"""Textures stage: the atlas face budget and the atlas' largest chart against the baked albedo texture's error,
with the stage's time.

The textures stage decimates the SDF's mesh to ``atlas_faces`` faces, unwraps it (xatlas) and bakes the albedo and
normal textures from the photometric maps. This bench runs :class:`stages.textures.TexturesStage` itself (its
``run``, configs ``dataclasses.replace(TexturesConfig(), atlas_faces=N)``) on one action of a run's work folder
(``make dataset``: its geometry, photometric and decode artifacts) for :data:`FACE_BUDGETS` plus the stage's and the
production preset's budgets, then at the stage's budget for :data:`CHART_AREAS` (``atlas_max_chart_area_m2``:
xatlas grows and flattens a few large charts for most of its time), and scores each baked albedo texture as
``ultrastage evaluate`` does (:func:`evaluation.release.texture_in_camera`): seen through its own textured mesh from
every true camera, on the pixels where the truth has the subject and the mesh is hit, PSNR against the simulator's
albedo (peak 1). Time:
the stage's CPU seconds (decimation, atlas, bake and writing; one process, numeric threads as the machine gives).

Baseline in the same process: the same run with the mesh not decimated (the budget set above its face count), so
the table says what a budget saves against keeping every face (``--no-undecimated`` leaves it out: on the default
capture's 200,000-face mesh it costs about twice the whole sweep, 122 s CPU).

``python bench/bench_textures.py --out bench/out [--run runs/default] [--action A0000] [--quick]`` writes
bench_textures.json and .md (run_all.py plots it with the other stages' trade-offs). Without a run with ground
truth it prints why and exits 0. ``--quick`` (the tests' mode): the tiny run of ``bench/_quick.py`` and two budgets
besides the stage's; not measurements.
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
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _quick import QUICK_HELP, quick_run  # noqa: E402
from _release import latest_artifact  # noqa: E402

FACE_BUDGETS = (5_000, 10_000, 20_000, 40_000, 100_000)
"""Atlas face budgets measured besides the stage's default and the production preset's."""
QUICK_FACE_BUDGETS = (1_000, 3_000)
CHART_AREAS = (0.0, 0.1, 0.05, 0.02, 0.01)
"""Largest charts (square metres) measured at the stage's face budget besides the stage's own limit."""
QUICK_CHART_AREAS = (0.02,)


def default_config():
    from stages.textures import TexturesConfig

    return TexturesConfig()


def production_config():
    from stages.registry import PRESETS

    return PRESETS["production"].textures


def chart_areas(quick: bool) -> list[float]:
    """The swept chart-area limits at the stage's face budget, the stage's own first (0: no limit)."""
    default = default_config().atlas_max_chart_area_m2
    extra = QUICK_CHART_AREAS if quick else CHART_AREAS
    return [default] + sorted({a for a in extra if a != default}, reverse=True)


def budgets(quick: bool) -> list[int]:
    """The swept budgets, the stage's default first; at the default texture size (only the budget changes)."""
    default = default_config().atlas_faces
    extra = QUICK_FACE_BUDGETS if quick else FACE_BUDGETS + (production_config().atlas_faces,)
    return [default] + sorted({b for b in extra if b != default})


class AlbedoProbe:
    """The simulator's albedo and mask per true camera of one action: scores a textured mesh's albedo texture."""

    def __init__(self, truth_dir: Path, action: str, session: str = "S000"):
        from pipeline.codecs.exr import read_exr
        from pipeline.codecs.image import read_png
        from evaluation.release import true_cameras

        self.views = []
        for cam_id, cam in sorted(true_cameras(truth_dir, session).items()):
            albedo_path = truth_dir / action / "albedo" / f"{cam_id}.exr"
            if not albedo_path.exists():
                continue
            mask = read_png(truth_dir / action / "mask" / f"{cam_id}.png")
            mask = (mask[..., 0] if mask.ndim == 3 else mask) > 127
            self.views.append((cam, mask, read_exr(albedo_path)[..., :3]))
        if not self.views:
            raise FileNotFoundError(f"{truth_dir / action}: no true albedo maps")

    def psnr_db(self, obj_path: Path, albedo_texture: np.ndarray) -> tuple[float, float]:
        """(PSNR in dB of the texture seen through the mesh against the truth, share of true-mask pixels hit)."""
        from evaluation.release import texture_in_camera

        cache: dict = {}
        sq, count, covered, total = 0.0, 0, 0, 0
        for cam, mask, truth in self.views:
            h, w = mask.shape
            seen, hit = texture_in_camera(obj_path, {"albedo": albedo_texture}, np.asarray(cam["K"]),
                                          np.asarray(cam["cam_from_world"])[:3], h, w, cache, where=mask)
            both = hit & mask
            err = np.clip(seen["albedo"][both], 0, 1).astype(np.float64) - truth[both]
            sq += float(np.sum(err ** 2))
            count += err.size
            covered += int(both.sum())
            total += int(mask.sum())
        return float(10 * np.log10(1.0 / max(sq / max(count, 1), 1e-12))), covered / max(total, 1)


def run_budget(work: Path, capture: Path, action: str, atlas_faces: int, probe: AlbedoProbe,
               max_chart_area_m2: float | None = None) -> dict:
    """The textures stage with ``atlas_faces`` (and ``max_chart_area_m2``, else the stage's), timed, its albedo
    texture scored."""
    from pipeline.codecs.exr import read_exr
    from pipeline.stage import StageContext
    from stages.textures import TexturesStage

    config = dataclasses.replace(default_config(), atlas_faces=atlas_faces)
    if max_chart_area_m2 is not None:
        config = dataclasses.replace(config, atlas_max_chart_area_m2=float(max_chart_area_m2))
    stage = TexturesStage(config)
    with tempfile.TemporaryDirectory(prefix="bench_textures_") as tmp:
        ctx = StageContext(stage="textures", scope_id=action, session_id="", action_id=action, out_dir=Path(tmp),
                           upstream={name: latest_artifact(work, name, action)
                                     for name in ("geometry", "photometric", "decode")},
                           raw_inputs={}, rig={}, capture_root=capture)
        wall, cpu = time.perf_counter(), time.process_time()
        stats = stage.run(ctx)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        score_s = time.perf_counter()
        psnr, coverage = probe.psnr_db(Path(tmp) / "mesh" / "textured.obj",
                                       read_exr(Path(tmp) / "textures" / "albedo.exr")[..., :3])
        score_s = time.perf_counter() - score_s
    return {"atlas_faces": atlas_faces, "max_chart_area_m2": config.atlas_max_chart_area_m2,
            "faces": int(stats["atlas_faces"]), "cpu_s": cpu, "wall_s": wall,
            "atlas_s": float(stats["atlas_seconds"]), "bake_s": float(stats["bake_seconds"]),
            "albedo_psnr_db": psnr, "truth_pixels_hit": coverage, "score_s": score_s}


def markdown(report: dict) -> str:
    base = report.get("baseline_undecimated")
    lines = [f"# Textures: atlas face budget and largest chart ({report['action']}, texture "
             f"{report['texture_size']}^2)", ""]
    if base:
        lines += [f"Baseline, same process: the mesh not decimated ({base['faces']} faces), {base['cpu_s']:.2f} s "
                  f"CPU, albedo {base['albedo_psnr_db']:.2f} dB.", ""]
    lines += ["| atlas_faces | largest chart m^2 | faces | CPU s | x undecimated | atlas s | bake s | albedo PSNR dB "
              "| truth pixels hit |", "|---|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        name = str(r["atlas_faces"]) + "".join(f" ({p})" for p in r["presets"])
        ratio = f"{r['cpu_s'] / base['cpu_s']:.2f}" if base else "-"
        area = r.get("max_chart_area_m2", 0.0)
        lines.append(f"| {name} | {area:g}{' (no limit)' if area == 0 else ''} | {r['faces']} | {r['cpu_s']:.2f} | "
                     f"{ratio} | {r['atlas_s']:.2f} | {r['bake_s']:.2f} | {r['albedo_psnr_db']:.2f} | "
                     f"{100 * r['truth_pixels_hit']:.1f}% |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--run", help="a make dataset run folder (default runs/default; with --quick the tiny run)")
    parser.add_argument("--action", default="A0000")
    parser.add_argument("--no-undecimated", action="store_true",
                        help="leave out the baseline run on the undecimated mesh")
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    if args.run is None:
        args.run = str(quick_run(Path(args.out)) if args.quick else ROOT / "runs" / "default")
    run = Path(args.run)
    work, capture = run / "release.work", run / "capture"
    truth = capture / "ground_truth"
    if not (work / "artifacts").is_dir() or not (truth / args.action / "albedo").is_dir():
        print(f"bench_textures: needs {run} with a work folder and ground truth (make dataset first); skipped")
        return 0
    from pipeline.codecs.mesh import read_ply

    probe = AlbedoProbe(truth, args.action)
    settings = [(faces, None, f"atlas_faces {faces}") for faces in budgets(args.quick)]
    settings += [(default_config().atlas_faces, area, f"atlas_max_chart_area_m2 {area:g}")
                 for area in chart_areas(args.quick)[1:]]
    rows = []
    for faces, area, label in settings:
        row = run_budget(work, capture, args.action, faces, probe, area)
        row["presets"] = [name for name, cfg in (("default", default_config()), ("production", production_config()))
                          if (cfg.atlas_faces, cfg.atlas_max_chart_area_m2) == (faces, row["max_chart_area_m2"])]
        rows.append(row)
        print(f"{label}: {row['faces']} faces, {row['cpu_s']:.2f} s CPU, albedo {row['albedo_psnr_db']:.2f} dB",
              flush=True)
    _, mesh_faces = read_ply(latest_artifact(work, "geometry", args.action) / "mesh" / "mesh.ply")
    report = {"action": args.action, "quick": args.quick, "texture_size": default_config().texture_size,
              "mesh_faces": int(len(mesh_faces)), "rows": rows}
    if not args.no_undecimated:
        report["baseline_undecimated"] = run_budget(work, capture, args.action, int(len(mesh_faces)) + 1, probe)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_textures.json").write_text(json.dumps(report, indent=1))
    (out / "bench_textures.md").write_text(markdown(report))
    print(markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
