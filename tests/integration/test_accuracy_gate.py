"""The accuracy gate: the whole DAG on one action of the full 32-camera rig, evaluated against the simulator's truth,
every stage's figure held to a bound set from its measured value, so a change that makes any stage clearly worse
fails here.

The capture is ``conftest.GATE_SIM`` (128 x 192 px, the procedural subject, colour chart, diffuse sphere and marker
frame), run with the ``gate`` preset (stages/registry.py) and scored by :func:`evaluation.release.evaluate_release`,
the numbers of ``ultrastage evaluate --json``. The run is deterministic on one machine (two runs, one with 2 numeric
threads and one with 1 on a fresh simulation, gave the same figures to the last bit, and so do two runs in one
process), but the SDF's training grows the smallest difference in arithmetic: before the marker calibration seeded
COLMAP's RANSAC for each camera (calibration.markers.RANSAC_SEED), a second run in the same process had cameras
1e-12 apart and a Chamfer 0.15 mm apart. Another machine's arithmetic does the same, and so does another SDF seed:
seed 0 gave a held-out coverage of 0.9768 on one machine and 0.9702 on another, and on the second, seeds 0-7 (1-3
one after another in one process, 0 and 4-7 in another) spread it over 0.962-0.972, the roughness MAE over
0.126-0.152, the relit views over 20.6-22.0 dB and the relighting set over 22.2-25.7 dB. The same eight seeds on
the code with the seeded RANSAC (cameras 1e-12 apart, so every seed takes another path) gave another eight: held-out
albedo 27.50-31.12 dB (seed 6, whose Chamfer, 4.91 mm, is the worst of the sixteen), roughness MAE 0.125-0.165.
So each bound sits beside the worst of those sixteen runs (``python
tests/integration/gate_spread.py --out DIR`` prints the spread of eight and the bounds it gives) and its margin:
errors 1.25 x the worst run's, PSNR 1 dB under it, a share that is 1 at best (SSIM, normal consistency, mask IoU,
coverage, valid fraction) 1.25 x as far from 1, an F-score 1.25 x smaller, the registered cameras as many as
measured. The margins are for what sixteen runs did not show. They still catch a plain regression: turning every
photometric normal by 12 degrees (``gate_spread.py --rotate-normals-deg 12``, seeds 0 and 1) fails the photometric
normals and the held-out normals against the truth on both seeds (15.1-15.4 deg against 10.43), the F-score at 1 mm
and the composited relighting set on one (its Chamfer, 6.10 mm on seed 0, passes 6.13). The bounds are bounds on
regressions, not targets: a change that improves a figure passes, and when it improves it a lot the bounds are set
again from the script's seeds.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pytest

from pipeline.runner import ExecutionConfig
from stages.registry import PRESETS, STAGE_CLASSES, build_stages
from ultrastage.run import run_pipeline

pytestmark = pytest.mark.slow


@dataclass(frozen=True)
class Bound:
    """One figure of the evaluation and how far it may get worse."""

    stage: str
    """The stage whose output the figure measures (what a failure names)."""
    metric: str
    """Its key in the evaluation's ``overall`` (``ultrastage evaluate --json``)."""
    worst: float
    """The worst value that passes."""
    measured: float
    """The worst value of the SDF seeds' runs when the bound was set (gate preset, this capture; gate_spread.py)."""
    margin: str
    """How ``worst`` was derived from ``measured`` (the margin)."""
    higher_is_better: bool = False
    """True for PSNR, SSIM, shares and counts (the figure must stay >= ``worst``), else it must stay <= ``worst``."""

    def passes(self, value: float) -> bool:
        return value >= self.worst if self.higher_is_better else value <= self.worst


def _error(stage: str, metric: str, measured: float, worst: float) -> Bound:
    """An error (degrees, millimetres, percent, pixels, roughness): ``worst`` = 1.25 x ``measured``."""
    return Bound(stage, metric, worst, measured, "1.25 x the worst seed's error")


def _psnr(stage: str, metric: str, measured: float, worst: float) -> Bound:
    """A PSNR: ``worst`` = ``measured`` - 1 dB."""
    return Bound(stage, metric, worst, measured, "1 dB under the worst seed's PSNR", higher_is_better=True)


def _share(stage: str, metric: str, measured: float, worst: float) -> Bound:
    """A score that is 1 at best (SSIM, IoU, normal consistency, coverage, valid fraction): ``worst`` =
    1 - 1.25 x (1 - ``measured``)."""
    return Bound(stage, metric, worst, measured, "1.25 x the worst seed's shortfall from 1", higher_is_better=True)


def _fscore(stage: str, metric: str, measured: float, worst: float) -> Bound:
    """An F-score: ``worst`` = ``measured`` / 1.25."""
    return Bound(stage, metric, worst, measured, "the worst seed's F-score / 1.25", higher_is_better=True)


BOUNDS: tuple[Bound, ...] = (
    # cameras: the marker-frame calibration against the simulator's true poses
    _error("cameras", "cam_rotation_err_deg", 0.01401, 0.01752),
    _error("cameras", "cam_center_err_mm", 1.046, 1.307),
    _error("cameras", "cam_focal_err_pct", 0.04205, 0.05256),
    _error("cameras", "reprojection_err_px", 0.09751, 0.1219),
    # 27 of the 32 cameras identify enough marker balls at 128 px to be calibrated (conftest.GATE_CALIBRATION)
    Bound("cameras", "cameras_registered", 27.0, 27.0, "the cameras measured", higher_is_better=True),
    # photometric: eq. 1's normals, the white-light albedo and the masks, every camera's pixels pooled
    _error("photometric", "normal_mean_deg", 10.67, 13.33),
    _error("photometric", "normal_mean_deg_all", 12.48, 15.6),
    _share("photometric", "valid_fraction", 0.8758, 0.8448),
    _psnr("photometric", "albedo_psnr_db", 22.62, 21.62),
    _share("photometric", "albedo_ssim", 0.7837, 0.7297),
    _share("photometric", "mask_iou", 0.9831, 0.9789),
    # diffuse_normals: the normals and albedo with the specular reflection fitted out
    _error("diffuse_normals", "normal_mean_deg_diffuse", 7.451, 9.314),
    _psnr("diffuse_normals", "albedo_psnr_db_diffuse", 22, 21),
    # geometry: the neural SDF's mesh against the true mesh
    _error("geometry", "chamfer_mm", 4.906, 6.132),
    _fscore("geometry", "fscore_5mm", 0.6949, 0.5559),
    _fscore("geometry", "fscore_1mm", 0.205, 0.164),
    _share("geometry", "normal_consistency", 0.9241, 0.9051),
    # held-out views (the paper's table 1): two cameras' maps synthesised from the other 25 through the mesh
    _psnr("heldout", "heldout_albedo_psnr_db", 27.5, 26.5),
    _share("heldout", "heldout_albedo_ssim", 0.9244, 0.9055),
    _error("heldout", "heldout_normal_mean_deg", 6.17, 7.713),
    _psnr("heldout", "heldout_albedo_psnr_db_truth", 25.54, 24.54),
    _error("heldout", "heldout_normal_mean_deg_truth", 8.346, 10.43),
    _share("heldout", "heldout_coverage", 0.9614, 0.9518),
    # textures and materials: the baked albedo, the fitted roughness, the de-occluded albedo, seen from every camera
    _psnr("textures", "albedo_texture_psnr_db", 24.03, 23.03),
    _error("materials", "roughness_mae", 0.1648, 0.206),
    _psnr("materials", "albedo_deoccluded_psnr_db", 25.3, 24.3),
    # relight: the relit novel view against the true subject under the same environment, and its shading normals
    _psnr("relight", "relit_psnr_db", 20.53, 19.53),
    _psnr("relight", "composited_relit_psnr_db", 21.29, 20.29),
    _error("relight", "relit_normal_mean_deg", 11.02, 13.78),
    # relightset: the single-image relighting set's examples against the true subject
    _psnr("relightset", "relightset_image_psnr_db", 22.18, 21.18),
    _psnr("relightset", "composited_relightset_image_psnr_db", 23.23, 22.23),
    _error("relightset", "relightset_normal_mean_deg", 12.05, 15.06),
    _psnr("relightset", "relightset_albedo_psnr_db", 26.48, 25.48),
)

SYNC = ExecutionConfig(scheduler="sync")


@pytest.fixture(scope="module")
def gate_run(gate_capture: Path, tmp_path_factory: pytest.TempPathFactory):
    """The gate preset's run over the gate capture and its evaluation: ``(RunResult, overall figures)``; the
    figures are also written to ``figures.json`` in the run's folder (to set the bounds again from)."""
    from evaluation.release import evaluate_release

    out = tmp_path_factory.mktemp("gate_run")
    config = PRESETS["gate"]
    result = run_pipeline(gate_capture, out / "release", out / "work", build_stages(config), config, SYNC,
                          echo=lambda line: None)
    overall = evaluate_release(out / "release", gate_capture / "ground_truth").overall
    (out / "figures.json").write_text(json.dumps(overall, indent=1, sort_keys=True))
    return result, overall


def test_bounds_are_set_from_their_measurements_with_the_stated_margins():
    """Each bound is looser than the value it was set from, by the margin it states (to rounding), and every
    stage the evaluation measures has one."""
    for bound in BOUNDS:
        assert bound.passes(bound.measured), bound
        if bound.margin == "1.25 x the worst seed's error":
            expected = 1.25 * bound.measured
        elif bound.margin == "1 dB under the worst seed's PSNR":
            expected = bound.measured - 1.0
        elif bound.margin == "1.25 x the worst seed's shortfall from 1":
            expected = 1 - 1.25 * (1 - bound.measured)
        elif bound.margin == "the worst seed's F-score / 1.25":
            expected = bound.measured / 1.25
        else:
            expected = bound.measured
        assert bound.worst == pytest.approx(expected, rel=0.01, abs=0.002), bound
    assert len({b.metric for b in BOUNDS}) == len(BOUNDS)
    evaluated = {"cameras", "photometric", "diffuse_normals", "geometry", "textures", "materials", "relight",
                 "relightset"}
    assert evaluated <= {b.stage for b in BOUNDS} and evaluated <= {cls.name for cls in STAGE_CLASSES}


def test_the_spread_script_sets_each_bound_from_the_worst_run_with_its_margin():
    """gate_spread.py's proposal on three made-up runs: the worst run's value through the bound's own margin."""
    from tests.integration.gate_spread import MARGINS, spread_rows

    assert {bound.margin for bound in BOUNDS} <= set(MARGINS)
    chamfer = _error("geometry", "chamfer_mm", 4.0, 5.0)
    relit = _psnr("relight", "relit_psnr_db", 21.0, 20.0)
    coverage = _share("heldout", "heldout_coverage", 0.96, 0.95)
    runs = {0: {"chamfer_mm": 4.0, "relit_psnr_db": 22.0, "heldout_coverage": 0.97},
            1: {"chamfer_mm": 6.0, "relit_psnr_db": 19.0, "heldout_coverage": 0.94},
            2: {"chamfer_mm": 5.0, "relit_psnr_db": 21.0, "heldout_coverage": 0.96}}
    rows = {row["bound"].metric: row for row in spread_rows(runs, (chamfer, relit, coverage))}
    assert (rows["chamfer_mm"]["worst"], rows["chamfer_mm"]["median"], rows["chamfer_mm"]["fails"]) == (6.0, 5.0, 1)
    assert rows["chamfer_mm"]["proposed"] == pytest.approx(7.5)
    assert (rows["relit_psnr_db"]["worst"], rows["relit_psnr_db"]["fails"]) == (19.0, 1)
    assert rows["relit_psnr_db"]["proposed"] == pytest.approx(18.0)
    assert rows["heldout_coverage"]["proposed"] == pytest.approx(1 - 1.25 * 0.06)


def test_every_stage_ran_for_the_gate(gate_run):
    result, _ = gate_run
    assert result.action_status == {"A0000": "ok"}
    ran = {task.stage.name for task in result.plan.tasks if task.status == "ran"}
    assert ran == {cls.name for cls in STAGE_CLASSES}


@pytest.mark.parametrize("bound", BOUNDS, ids=lambda b: f"{b.stage}:{b.metric}")
def test_figure_within_its_bound(gate_run, bound: Bound):
    _, overall = gate_run
    assert bound.metric in overall, f"{bound.stage}: the evaluation gave no {bound.metric} (figures: {sorted(overall)})"
    value = overall[bound.metric]
    sense = ">=" if bound.higher_is_better else "<="
    assert bound.passes(value), (f"{bound.stage} got worse: {bound.metric} = {value:.4g}, the gate wants {sense} "
                                 f"{bound.worst:g} (measured {bound.measured:g}; margin: {bound.margin})")


def test_comparable_relit_figures_match_the_plain_ones_on_a_closed_subject(gate_run):
    """The gate's procedural subject is closed: the truth shows no inside of an open mesh, so the comparable relit
    figures leave out only the odd pixel whose ray slips between two triangles onto a back face (measured:
    under 0.001 dB apart) and stay within 0.01 dB of the plain ones."""
    _, overall = gate_run
    assert overall["comparable_relit_psnr_db"] == pytest.approx(overall["relit_psnr_db"], abs=0.01)
    assert overall["comparable_relightset_image_psnr_db"] == pytest.approx(overall["relightset_image_psnr_db"],
                                                                           abs=0.01)
