"""The accuracy gate: the whole DAG on one action of the full 32-camera rig, evaluated against the simulator's truth,
every stage's figure held to a bound set from its measured value, so a change that makes any stage clearly worse
fails here.

The capture is ``conftest.GATE_SIM`` (128 x 192 px, the procedural subject, colour chart, diffuse sphere and marker
frame), run with the ``gate`` preset (stages/registry.py) and scored by :func:`evaluation.release.evaluate_release`,
the numbers of ``ultrastage evaluate --json``. Each bound sits beside the value measured when it was set and its
margin: errors 1.25 x the measured one, PSNR 1 dB under it, a share that is 1 at best (SSIM, normal consistency,
mask IoU, coverage, valid fraction) 1.25 x as far from 1, an F-score 1.25 x smaller, the registered cameras as many
as measured. The run is deterministic: two runs, one with 2 numeric threads and one with 1 on a fresh simulation,
gave the same 67 figures to the last bit, so the margins are for other machines' arithmetic, not for noise. They
are tight enough that turning every photometric normal by 12 degrees fails the photometric, geometry, held-out
and relighting-set bounds (with 1.5 x margins it failed only two held-out ones). The bounds are bounds on
regressions, not targets: a change that improves a figure passes, and when it improves it a lot the bound is
tightened by hand to the new measurement.
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
    """The value measured when the bound was set (gate preset, this capture)."""
    margin: str
    """How ``worst`` was derived from ``measured``."""
    higher_is_better: bool = False
    """True for PSNR, SSIM, shares and counts (the figure must stay >= ``worst``), else it must stay <= ``worst``."""

    def passes(self, value: float) -> bool:
        return value >= self.worst if self.higher_is_better else value <= self.worst


def _error(stage: str, metric: str, measured: float, worst: float) -> Bound:
    """An error (degrees, millimetres, percent, pixels, roughness): ``worst`` = 1.25 x ``measured``."""
    return Bound(stage, metric, worst, measured, "1.25 x the measured error")


def _psnr(stage: str, metric: str, measured: float, worst: float) -> Bound:
    """A PSNR: ``worst`` = ``measured`` - 1 dB."""
    return Bound(stage, metric, worst, measured, "1 dB under the measured PSNR", higher_is_better=True)


def _share(stage: str, metric: str, measured: float, worst: float) -> Bound:
    """A score that is 1 at best (SSIM, IoU, normal consistency, coverage, valid fraction): ``worst`` =
    1 - 1.25 x (1 - ``measured``)."""
    return Bound(stage, metric, worst, measured, "1.25 x the measured shortfall from 1", higher_is_better=True)


def _fscore(stage: str, metric: str, measured: float, worst: float) -> Bound:
    """An F-score: ``worst`` = ``measured`` / 1.25."""
    return Bound(stage, metric, worst, measured, "the measured F-score / 1.25", higher_is_better=True)


BOUNDS: tuple[Bound, ...] = (
    # cameras: the marker-frame calibration against the simulator's true poses
    _error("cameras", "cam_rotation_err_deg", 0.0140, 0.0175),
    _error("cameras", "cam_center_err_mm", 1.046, 1.31),
    _error("cameras", "cam_focal_err_pct", 0.0421, 0.0526),
    _error("cameras", "reprojection_err_px", 0.0975, 0.122),
    # 27 of the 32 cameras identify enough marker balls at 128 px to be calibrated (conftest.GATE_CALIBRATION)
    Bound("cameras", "cameras_registered", 27.0, 27.0, "the cameras measured", higher_is_better=True),
    # photometric: eq. 1's normals, the white-light albedo and the masks, every camera's pixels pooled
    _error("photometric", "normal_mean_deg", 10.68, 13.3),
    _error("photometric", "normal_mean_deg_all", 12.48, 15.6),
    _share("photometric", "valid_fraction", 0.876, 0.8450),
    _psnr("photometric", "albedo_psnr_db", 22.62, 21.62),
    _share("photometric", "albedo_ssim", 0.784, 0.7300),
    _share("photometric", "mask_iou", 0.983, 0.9788),
    # diffuse_normals: the normals and albedo with the specular reflection fitted out
    _error("diffuse_normals", "normal_mean_deg_diffuse", 7.361, 9.201),
    _psnr("diffuse_normals", "albedo_psnr_db_diffuse", 22.06, 21.06),
    # geometry: the neural SDF's mesh against the true mesh
    _error("geometry", "chamfer_mm", 4.618, 5.773),
    _fscore("geometry", "fscore_5mm", 0.7131, 0.5705),
    _fscore("geometry", "fscore_1mm", 0.2124, 0.1699),
    _share("geometry", "normal_consistency", 0.9269, 0.9086),
    # held-out views (the paper's table 1): two cameras' maps synthesised from the other 25 through the mesh
    _psnr("heldout", "heldout_albedo_psnr_db", 29.92, 28.92),
    _share("heldout", "heldout_albedo_ssim", 0.9421, 0.9276),
    _error("heldout", "heldout_normal_mean_deg", 6.081, 7.601),
    _psnr("heldout", "heldout_albedo_psnr_db_truth", 26.07, 25.07),
    _error("heldout", "heldout_normal_mean_deg_truth", 8.068, 10.09),
    _share("heldout", "heldout_coverage", 0.9768, 0.971),
    # textures and materials: the baked albedo, the fitted roughness, the de-occluded albedo, seen from every camera
    _psnr("textures", "albedo_texture_psnr_db", 24.17, 23.17),
    _error("materials", "roughness_mae", 0.1162, 0.1453),
    _psnr("materials", "albedo_deoccluded_psnr_db", 25.62, 24.62),
    # relight: the relit novel view against the true subject under the same environment, and its shading normals
    _psnr("relight", "relit_psnr_db", 21.39, 20.39),
    _error("relight", "relit_normal_mean_deg", 10.83, 13.54),
    # relightset: the single-image relighting set's examples against the true subject
    _psnr("relightset", "relightset_image_psnr_db", 25.08, 24.08),
    _error("relightset", "relightset_normal_mean_deg", 11.97, 14.96),
    _psnr("relightset", "relightset_albedo_psnr_db", 27.33, 26.33),
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
        if bound.margin == "1.25 x the measured error":
            expected = 1.25 * bound.measured
        elif bound.margin == "1 dB under the measured PSNR":
            expected = bound.measured - 1.0
        elif bound.margin == "1.25 x the measured shortfall from 1":
            expected = 1 - 1.25 * (1 - bound.measured)
        elif bound.margin == "the measured F-score / 1.25":
            expected = bound.measured / 1.25
        else:
            expected = bound.measured
        assert bound.worst == pytest.approx(expected, rel=0.01, abs=0.002), bound
    assert len({b.metric for b in BOUNDS}) == len(BOUNDS)
    evaluated = {"cameras", "photometric", "diffuse_normals", "geometry", "textures", "materials", "relight",
                 "relightset"}
    assert evaluated <= {b.stage for b in BOUNDS} and evaluated <= {cls.name for cls in STAGE_CLASSES}


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
