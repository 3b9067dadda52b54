"""bench/_pareto.py: the Pareto front of (time, error) points, and the table and plot the report shows per stage."""
from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[3] / "bench"


def _bench_module(name: str, file: str):
    """A bench module loaded from its file under a name of its own, with bench/ on the path for its sibling
    imports while it loads."""
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location(name, BENCH / file)
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module  # dataclasses look their module up by name
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCH))
    return module


@pytest.fixture(scope="module")
def pareto():
    return _bench_module("bench_pareto_under_test", "_pareto.py")


def test_front_keeps_exactly_the_undominated_points(pareto):
    seconds = [1.0, 2.0, 3.0, 2.5, 4.0, 1.0]
    errors = [5.0, 3.0, 1.0, 3.5, 1.0, 6.0]
    # (2.5, 3.5) is beaten by (2, 3); (4, 1) by (3, 1); (1, 6) by (1, 5)
    assert pareto.pareto_front(seconds, errors) == [True, True, True, False, False, False]


def test_front_ties_and_non_finite_points(pareto):
    assert pareto.pareto_front([1.0, 1.0], [2.0, 2.0]) == [True, True]
    # a NaN point neither joins the front nor knocks another point off it
    assert pareto.pareto_front([math.nan, 2.0, 0.5], [0.1, 1.0, math.inf]) == [False, True, False]
    assert pareto.pareto_front([], []) == []
    with pytest.raises(ValueError):
        pareto.pareto_front([1.0], [])


def test_table_and_plot(pareto, tmp_path):
    P = pareto.TradeoffPoint
    tradeoff = pareto.Tradeoff(
        stage="decode", knobs="demosaic", time_label="ms per MP", error_label="error (dB below 60)",
        points=(P("LINEAR", 10.0, 9.0, presets=("fast",), baseline_seconds=5.0),
                P("AHD", 40.0, 3.0, presets=("default",)), P("VNG", 50.0, 4.0)), source="bench_decode")
    lines = pareto.tradeoff_table(tradeoff)
    assert lines[0].startswith("| setting | ms per MP | error (dB below 60) | Pareto | preset | x baseline |")
    rows = {line.split(" | ")[0].strip("| "): line for line in lines[2:]}
    assert rows.keys() == {"LINEAR", "AHD", "VNG"}
    assert "| yes | default |" in rows["AHD"] and "| yes | fast | 2 |" in rows["LINEAR"]
    assert "| yes |" not in rows["VNG"]
    score = pareto.Tradeoff(stage="decode", knobs="demosaic", time_label="ms", error_label="PSNR dB",
                            points=(P("a", 1.0, 20.0), P("b", 2.0, 30.0), P("c", 3.0, 25.0)), source="x",
                            higher_is_better=True, notes=("a note",))
    assert score.front() == [True, True, False]
    assert pareto.tradeoff_table(score)[-1] == "- a note"
    path = pareto.tradeoff_plot(tradeoff, tmp_path / "decode.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_stage_tradeoffs_mark_the_presets_from_their_configs(tmp_path):
    import json

    from stages.registry import PRESETS

    tradeoffs = _bench_module("bench_tradeoffs_under_test", "_tradeoffs.py")
    rows = [{"algorithm": a, "half_size": False, "ms_per_mp": t, "psnr_db": p}
            for a, t, p in (("LINEAR", 30.0, 20.0), ("AHD", 90.0, 26.0), ("VNG", 100.0, 21.0))]
    rows.append({"algorithm": "HALF (any)", "half_size": True, "ms_per_mp": 25.0, "psnr_db": 20.5})
    (tmp_path / "bench_decode.json").write_text(json.dumps({"rows": rows}))
    [decode] = tradeoffs.decode_tradeoffs(tmp_path)
    marks = {p.label: p.presets for p in decode.points}
    assert "default" in marks[PRESETS["default"].decode.demosaic]
    assert "production" in marks["half size (no demosaic)"] and PRESETS["production"].decode.half_size
    assert marks["VNG"] == ()
    assert decode.front() == [False, True, False, True]  # half size beats LINEAR; AHD beats VNG
    section = tradeoffs.report_section(tmp_path)
    assert "### decode: decode.demosaic, decode.half_size" in section
    assert (tmp_path / "tradeoff_00_decode.png").is_file()


def test_marker_calibration_tradeoff_marks_the_default_source_and_its_baseline(tmp_path):
    import json

    tradeoffs = _bench_module("bench_tradeoffs_markers_under_test", "_tradeoffs.py")
    common = {"width": 320, "decode_s": 0.5}
    rows = [{"method": "rig_spec", "width": 320, "seconds": 0.0, "centre_mm_mean": 4.7},
            {"method": "markers", "seconds": 1.5, "centre_mm_mean": 0.16} | common,
            {"method": "markers_rig_frame", "seconds": 1.4, "centre_mm_mean": 1.36} | common,
            {"method": "markers_fixed_focal", "seconds": 1.45, "centre_mm_mean": 8.7} | common,
            {"method": "floor_nominal_gauge", "width": 320, "seconds": 0.0, "centre_mm_mean": 1.46}]
    (tmp_path / "bench_calibration_markers.json").write_text(json.dumps({"rows": rows}))
    [markers] = tradeoffs.markers_tradeoffs(tmp_path)
    marks = {p.label: p.presets for p in markers.points}
    assert set(marks) == {"markers", "markers_rig_frame", "markers_fixed_focal"}  # no time: references in the notes
    assert "default" in marks["markers"] and marks["markers_fixed_focal"] == ()
    assert all(p.baseline_seconds == 0.5 for p in markers.points)
    assert markers.front() == [True, True, False]
    assert "rig_spec 4.70 mm" in markers.notes[0] and "floor_nominal_gauge 1.46 mm" in markers.notes[0]


def test_every_bench_says_what_its_speed_baseline_is():
    """run_all's report lists each bench's same-process baseline (or that it has none): a new bench must say."""
    run_all = _bench_module("bench_run_all_under_test", "run_all.py")
    names = sorted(p.stem.removeprefix("bench_") for p in BENCH.glob("bench_*.py"))
    assert sorted(run_all.SPEED_BASELINES) == names
    section = run_all.baseline_section(names)
    lacking = [n for n in names if run_all.SPEED_BASELINES[n] is None]
    assert all(f"| {n} | **none** |" in section for n in lacking)


def test_make_bench_profile_names_real_benches_and_full_runs_them_all():
    run_all = _bench_module("bench_run_all_profile", "run_all.py")
    names = {p.stem.removeprefix("bench_") for p in BENCH.glob("bench_*.py")}
    assert set(run_all.MAKE_BENCH_ARGS) <= names
    for name in names:
        assert run_all.bench_arguments(name, quick=True, full=False) == ["--quick"]
        assert run_all.bench_arguments(name, quick=False, full=True) == []
    assert run_all.bench_arguments("scale", quick=False, full=False) == run_all.MAKE_BENCH_ARGS["scale"]
    assert run_all.bench_arguments("memory", quick=False, full=False) is None
    assert run_all.bench_arguments("decode", quick=False, full=False) == []
