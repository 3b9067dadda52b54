"""The subject panel (bench/bench_subjects.py): its table logic on hand-made figures (its quick mode end to end is
checked on run_all's quick run in test_bench_quick.py)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.unit.bench.test_bench_defaults import load_bench

ROOT = Path(__file__).resolve().parents[3]
SHARED = Path(os.environ.get("ULTRASTAGE_SHARED_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="module")
def panel():
    """bench/bench_subjects.py imported by path (bench/ is not a package)."""
    return load_bench("bench_subjects")


def test_figures_keep_finite_values_and_add_the_best_normals(panel):
    figures = panel.figures_of({"chamfer_mm": 1.2, "relit_psnr_db": float("nan"), "normal_mean_deg": 3.0,
                                "normal_mean_deg_diffuse": 2.5, "not_a_figure": 7.0})
    assert figures == {"chamfer_mm": 1.2, "normal_mean_deg": 3.0, "normal_mean_deg_diffuse": 2.5,
                       "best_normal_mean_deg": 2.5}


def test_worst_case_and_misses_follow_each_figures_direction(panel):
    per = {"a": {"chamfer_mm": 1.0, "relit_psnr_db": 30.0, "heldout_albedo_psnr_db": 31.0,
                 "heldout_normal_mean_deg": 4.0},
           "b": {"chamfer_mm": 2.0, "relit_psnr_db": 24.0, "heldout_albedo_psnr_db": 29.0,
                 "heldout_normal_mean_deg": 5.0, "heldout_normal_mean_deg_diffuse": 4.2,
                 "comparable_chamfer_mm": 1.6},
           "d": {"chamfer_mm": 1.7, "comparable_chamfer_mm": 1.4, "relit_psnr_db": 22.0,
                 "comparable_relit_psnr_db": 25.5},
           "c": {"relit_psnr_db": 26.0}}
    worst = panel.worst_cases(per)
    assert worst["chamfer_mm"] == {"subject": "b", "value": 2.0}
    assert worst["relit_psnr_db"] == {"subject": "d", "value": 22.0}
    assert worst["comparable_relit_psnr_db"] == {"subject": "d", "value": 25.5}
    assert worst["heldout_normal_mean_deg"] == {"subject": "b", "value": 5.0}
    missed = panel.misses(per)
    assert missed["chamfer_mm > 1.5"] == ["b", "d"] and missed["relit_psnr_db < 25"] == ["b", "d"]
    assert missed["comparable_relit_psnr_db < 25"] == []
    assert missed["comparable_chamfer_mm > 1.5"] == ["b"]
    assert worst["comparable_chamfer_mm"] == {"subject": "b", "value": 1.6}
    assert missed["heldout_albedo_psnr_db worse than the paper's 30.87"] == ["b"]
    assert missed["heldout_normal_mean_deg worse than the paper's 4.3"] == ["b"]
    assert missed["heldout_normal_mean_deg_diffuse worse than the paper's 4.3"] == []


def test_the_panel_spans_the_extremes_and_two_other_meshes(panel):
    names = {s.name for s in panel.SUBJECTS}
    assert {"heavy", "thin", "tall", "short", "old", "posed", "hair", "skirt"} <= names
    assert sum(not s.makehuman for s in panel.SUBJECTS) == 2
    from synthetic import SimConfig

    for subject in panel.SUBJECTS:  # every subject's settings make a valid config
        SimConfig(actions=1, **subject.sim_changes(SHARED / "meshes"))


def test_what_to_reuse_of_an_earlier_run(panel):
    """Read back a finished subject; with --rerun keep only its simulation (same settings, capture there); simulate
    again when the settings changed, the capture is gone or --fresh asks for it."""
    settings = {"simulator": {"seed": 0, "width": 320}, "preset": "default"}
    done = {"settings": {"simulator": {"seed": 0, "width": 320}, "preset": "default"}, "figures": {}, "simulate_s": 20.0}
    reuse = panel.what_to_reuse
    assert reuse(done, settings, True, fresh=False, rerun=False) == "record"
    assert reuse(done, settings, True, fresh=False, rerun=True) == "simulation"
    assert reuse(done, settings, False, fresh=False, rerun=True) == "nothing"        # the capture is gone
    assert reuse(done, settings, True, fresh=True, rerun=True) == "nothing"
    assert reuse(done, {**settings, "preset": "fast"}, True, fresh=False, rerun=True) == "nothing"
    assert reuse({}, settings, True, fresh=False, rerun=False) == "nothing"
    assert reuse({k: v for k, v in done.items() if k != "figures"}, settings, True, fresh=False, rerun=False) == "nothing"
