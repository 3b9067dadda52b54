"""Every bench runs in its quick mode (`make bench-quick`: bench/run_all.py --quick), so that none can rot: each
writes its results, marked quick, with finite numbers, and the benches whose quick output has a structure of its
own (the subject panel, the hash-grid kernel, the engine at scale) are checked on that same run's files, so no
quick mode runs twice in the suite. The benches run in run_all's two lanes (``--lanes 2``): the ones that read the
shared tiny run in one, the others beside them, each forked from run_all after the common imports. Nothing is
timed; the run takes about 6.8 CPU minutes (3 min 41 s alone on an idle 2-core machine)."""
from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
SHARED = ROOT.parent / "shared" / "data"
BENCHES = sorted(p.stem for p in (ROOT / "bench").glob("bench_*.py"))


def _printed(stdout: str, name: str) -> str:
    """What run_all printed while it ran bench ``name`` (between its ``== NAME.py ARGS`` and ``== NAME.py: exit``
    lines)."""
    return stdout.partition(f"== {name}.py ")[2].partition("\n")[2].partition(f"== {name}.py: exit")[0]


def _numbers(value, where: str):
    """(path, number) of every number in a parsed JSON value."""
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        yield where, value
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from _numbers(item, f"{where}.{key}")
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _numbers(item, f"{where}[{i}]")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("bench_quick")
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "run_all.py"), "--quick", "--lanes", "2", "--out",
                           str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=1800)
    return out, proc


@pytest.mark.slow
def test_bench_third_pass_reads_the_decision_the_stage_made(quick_run):
    """The forced third pass ran, both meshes were scored, and the bench's share on the pixel lattice, read again
    from the passes' meshes, is the stage's own decision figure."""
    out, proc = quick_run
    report = json.loads((out / "bench_third_pass.json").read_text())
    assert report["quick"] is True and 0 < report["bound"] < 1
    (row,) = report["rows"]
    assert row["third_pass_iterations"] == 20 and row["views"] >= 8
    assert row["shares"]["pixel_lattice"] == pytest.approx(row["stage_turned_share"], abs=1e-12)
    assert all(0.0 <= v <= 1.0 for v in row["shares"].values())
    assert {"two_passes", "three_passes"} == set(row["meshes"])
    assert all(math.isfinite(v) and v >= 0 for m in row["meshes"].values() for v in m.values())


@pytest.mark.slow
def test_bench_free_space_carves_by_the_cue_it_reports(quick_run):
    """The cue was read on both sets of normals at every setting, and the first carve round, on the stage's own
    SDF mesh, flagged the pixels of the cue's row at the carve's setting; both continuations were scored."""
    out, proc = quick_run
    report = json.loads((out / "bench_free_space.json").read_text())
    assert report["quick"] is True
    (row,) = report["rows"]
    settings = {(c["normals"], c["agree_deg"], c["visible_tol_m"]): c for c in row["cue"]}
    assert {n for n, _, _ in settings} == {"photometric", "specular-free"} and len(settings) == 8
    cue = settings[("specular-free", 20.0, None)]
    assert row["carve"]["carved"][0]["flagged"] == cue["flagged"]
    assert all(c["cavity"] + c["cut"] <= c["flagged"] for c in row["cue"])
    assert [r["flagged"] for r in row["carve"]["plain"]] == [0]


@pytest.mark.slow
def test_run_all_quick_exits_0_and_says_it_is_quick(quick_run):
    out, proc = quick_run
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    report = (out / "REPORT.md").read_text()
    assert "Quick run" in report.split("## Machine")[0] and "not measurements" in report
    for name in BENCHES:
        assert f"## {name}\n\nexit 0," in report, name


@pytest.mark.slow
@pytest.mark.parametrize("name", BENCHES)
def test_every_bench_writes_quick_results_with_finite_numbers(quick_run, name):
    out, proc = quick_run
    result, table = out / f"{name}.json", out / f"{name}.md"
    if not (result.exists() or table.exists()) and not SHARED.is_dir() and "skipped" in _printed(proc.stdout, name):
        pytest.skip(f"{name} needs ../shared/data (the HDR maps), absent here")
    assert result.exists() or table.exists(), f"{name} wrote neither {result.name} nor {table.name}"
    if not result.exists():
        return
    data = json.loads(result.read_text())  # Python's json reads NaN and Infinity: checked below
    assert data.get("quick") is True, f"{result.name} is not marked quick"
    bad = [where for where, x in _numbers(data, name) if not math.isfinite(x)]
    assert not bad, f"{result.name}: non-finite numbers at {bad[:10]}"


@pytest.mark.slow
def test_the_shared_run_lane_holds_the_benches_that_used_the_shared_run(quick_run):
    """run_all's lane of the shared tiny run names exactly the benches that took it: a bench missing from it would
    wait for the run while the other lane is busy (correct, but slower), a name left there after its bench stopped
    using the run keeps that lane longer than it needs. Each bench's output is printed as one block, and only the
    first user brings the run up to date."""
    out, proc = quick_run
    spec = importlib.util.spec_from_file_location("run_all_under_test", ROOT / "bench" / "run_all.py")
    run_all = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(run_all)  # its top level imports the standard library only
    users = set((out / "quick_run.users").read_text().split())
    assert users == run_all.SHARED_RUN_LANE, (sorted(users - run_all.SHARED_RUN_LANE),
                                              sorted(run_all.SHARED_RUN_LANE - users))
    for name in BENCHES:
        assert f"== {name}.py: exit 0" in proc.stdout, name
        assert "== bench_" not in _printed(proc.stdout, name), f"another bench's lines inside {name}'s block"
    # the run is brought up to date by its first user; the others find it unchanged (no bench writes into it)
    brought = [name for name in BENCHES if "quick run: tiny capture and release" in _printed(proc.stdout, name)]
    found = [name for name in BENCHES if "not run again" in _printed(proc.stdout, name)]
    assert len(brought) == 1 and sorted(brought + found) == sorted(users), (brought, found)


@pytest.mark.slow
def test_subject_panel_quick_mode_writes_the_table_and_json(quick_run):
    out, proc = quick_run
    report = json.loads((out / "bench_subjects.json").read_text())
    assert report["quick"] is True and len(report["subjects"]) == 1
    (name, subject), = report["subjects"].items()
    assert name == ("dressed" if (SHARED / "meshes" / "makehuman_base.obj").is_file() else "procedural")
    for key in ("chamfer_mm", "fscore_1mm", "heldout_albedo_psnr_db", "best_normal_mean_deg", "roughness_mae",
                "relit_psnr_db", "relightset_image_psnr_db"):
        assert math.isfinite(subject["figures"][key]), key
        assert report["worst"][key]["subject"] == name
    table = (out / "bench_subjects.md").read_text()
    assert "quick: not measurements" in table and "| Chamfer (mm) |" in table and "| relit PSNR (dB) |" in table
    assert (out / "bench_subjects.png").stat().st_size > 0


@pytest.mark.slow
def test_hashgrid_quick_mode_kernel_rows_agree_with_the_torch_path(quick_run):
    out, proc = quick_run
    result = json.loads((out / "bench_hashgrid.json").read_text())
    paths = [row["path"] for row in result["rows"]]
    assert "torch, 1 thread" in paths and "torch, 2 threads" in paths
    for row in result["rows"]:
        assert all(math.isfinite(row[k]) and row[k] > 0 for k in ("encoding_s", "field_step_s"))
    if result["kernel_available"]:
        assert "kernel, 1 thread" in paths
        assert set(result["max_relative_difference_kernel_vs_torch"]) == {"features", "jacobian", "table_gradient"}
        assert max(result["max_relative_difference_kernel_vs_torch"].values()) < 1e-5
    assert "| path |" in (out / "bench_hashgrid.md").read_text()


@pytest.mark.slow
def test_sdf_sharpness_quick_mode_recomputed_masks_reproduce_the_released_ones(quick_run):
    """The ``recomputed`` masks, the photometric stage's mask run again with the run's own parameters and no change,
    are the released masks: the same widening and, row for row, the same mesh as the ``pipeline`` rows."""
    out, proc = quick_run
    report = json.loads((out / "bench_sdf_sharpness.json").read_text())
    assert report["quick"] is True and report["seeds"] == [0] and report["mask_params"] == ""
    assert report["recomputed_widening_px"] == report["mask_widening_px"]
    by_kind = {kind: sorted(((r["inv_s_end"], r["chamfer_mm"]) for r in report["rows"] if r["masks"] == kind))
               for kind in ("pipeline", "centre", "recomputed")}
    assert len(by_kind["pipeline"]) == 2 and len(by_kind["centre"]) == 1 and len(by_kind["recomputed"]) == 1
    default = [(r["inv_s_end"], r["chamfer_mm"]) for r in report["rows"]
               if r["masks"] == "pipeline" and r["inv_s_end_set"] is None]
    assert by_kind["recomputed"] == default
    assert by_kind["centre"] != default


@pytest.mark.slow
def test_scale_quick_mode_writes_finite_positive_per_task_figures(quick_run):
    """Two tiny captures through the real engine with stub stages: the report's structure, and per-task figures
    that are finite and positive (no timings are asserted)."""
    out, proc = quick_run
    report = json.loads((out / "bench_scale.json").read_text())
    assert report["quick"] is True and report["goal_ms_per_task"] == 1.0 and report["cameras"] == 32
    results = report["results"]
    assert [(r["actions"], r["executor"]) for r in results] == [(2, "sync"), (4, "sync")]
    for r in results:
        assert set(r["runs"]) == {"cold", "cached"}
        cold, cached = r["runs"]["cold"], r["runs"]["cached"]
        # every stage of every scope ran cold and was found in the store on the rerun
        assert cold["ran"] == cold["plan_tasks"] and cached["cached"] == cached["plan_tasks"] == cold["plan_tasks"]
        assert cold["executor_tasks"] == cold["graph_tasks"] > cold["plan_tasks"] and cached["executor_tasks"] == 0
        assert set(cold["per_task"]) == {"plan_ms", "submit_ms", "execute_ms", "bookkeeping_ms",
                                         "bookkeeping_per_graph_task_ms", "bare_ms", "x_bare"}
        # the baseline ran as many tasks as the engine submitted, and its ratio is the two times' quotient
        assert r["bare_executor"]["tasks"] == cold["executor_tasks"]
        assert math.isclose(cold["per_task"]["x_bare"], cold["per_task"]["execute_ms"] / cold["per_task"]["bare_ms"])
        assert set(cached["per_task"]) == {"plan_ms", "bookkeeping_ms", "bookkeeping_per_graph_task_ms"}
        for run in (cold, cached):
            assert all(math.isfinite(v) and v > 0 for v in run["per_task"].values()), run["per_task"]
            assert all(math.isfinite(v) and v >= 0 for v in run["phases_s"].values())
        assert 0 < cold["max_in_flight"] <= cold["executor_tasks"]
        assert r["peak_rss_mib"] > 0
    table = (out / "bench_scale.md").read_text()
    assert table.startswith("# Engine overhead at release size") and "| 4 | sync | cached |" in table


@pytest.mark.slow
def test_panel_set_quick_mode_trains_both_networks_on_both_sets_against_one_test_split(quick_run):
    """The tiny run merged under two names: both training sets share the test subject, both networks trained on
    each, and the table's trivial column equals the metrics the trivial baseline got in the panel set's run."""
    out, proc = quick_run
    report = json.loads((out / "bench_panel_set.json").read_text())
    assert report["quick"] is True and report["test_subjects"] == ["qb"]
    for name, merged in report["sets"].items():
        assert merged["examples"]["test"] > 0 and merged["examples"]["train"] > 0, name
        assert [s.split("/")[0] for s in merged["subjects"]["test"]] == ["qb"], name
    trivial = {"albedonet": "input_image", "normalnet": "constant_normal"}
    for network, by_set in report["results"].items():
        assert set(by_set) == {"panel", "one_body"}
        for name, result in by_set.items():
            assert result["steps"] == 4 and set(result["overall"]) == {network, trivial[network]}, (network, name)
            assert set(result["per_subject"][network]) == {"qb"}
        # one test split: the trivial baseline scores the same whichever set the network was trained on
        assert by_set["panel"]["overall"][trivial[network]] == by_set["one_body"]["overall"][trivial[network]]
    table = (out / "bench_panel_set.md").read_text()
    assert "quick: not measurements" in table and "albedonet on one_body" in table and "worst subject" in table


@pytest.mark.slow
def test_relit_budget_quick_mode_scores_the_capture_grid_truth_against_a_finer_one(quick_run):
    """The ceiling table: the capture-grid truth against the 8 x 8 one differs (silhouette pixels move) but stays
    close, its worst image is no better than its mean, and the stage's render is scored against both truths."""
    out, proc = quick_run
    if not (out / "bench_relit_budget.json").exists():
        pytest.skip("bench_relit_budget wrote nothing here (no HDR maps)")
    report = json.loads((out / "bench_relit_budget.json").read_text())
    ceiling = report["ceiling"]
    assert ceiling["supersample"] == 8 and ceiling["n"] >= 1
    assert 15.0 < ceiling["truth_worst_db"] <= ceiling["truth_mean_db"] < 80.0, ceiling
    assert set(ceiling["rows"]) >= {"stage"}
    stage = ceiling["rows"]["stage"]
    assert stage["capture_grid_db"] == pytest.approx(report["summary"]["stage"]["psnr_db"], abs=1e-9)
    assert "The metric's ceiling" in (out / "bench_relit_budget.md").read_text()
    # every row is scored both ways: the evaluation's thresholded PSNR and its composited one
    assert all(5.0 < row["composited_psnr_db"] < 130.0 for row in report["summary"].values()), report["summary"]
    assert "composited PSNR dB" in (out / "bench_relit_budget.md").read_text()


def test_gaps_quick_mode_scores_each_rule_on_the_same_holes(quick_run):
    """Every rule scores the same hole pixels; the two single-view rules are each other's opposite; the stage's rule
    (either test) opens at least what each of its two tests opens alone."""
    out, _ = quick_run
    report = json.loads((out / "bench_gaps.json").read_text())
    summary = report["summary"]
    assert list(summary)[:4] == ["fill every hole", "open every hole", "across views or gradient ratios (stage)",
                                 "across views"]
    fill, open_ = summary["fill every hole"], summary["open every hole"]
    assert fill["gap_opened_px"] == fill["surface_opened_px"] == 0
    assert open_["gap_left_px"] == open_["surface_kept_px"] == 0
    assert fill["gap_left_px"] == open_["gap_opened_px"] and fill["surface_kept_px"] == open_["surface_opened_px"]
    for row in summary.values():
        assert row["gap_opened_px"] + row["gap_left_px"] == fill["gap_left_px"]
        assert row["surface_opened_px"] + row["surface_kept_px"] == fill["surface_kept_px"]
    stage = summary["across views or gradient ratios (stage)"]
    for alone in (summary["across views"], summary["gradient ratios 0.2"]):
        assert stage["gap_opened_px"] >= alone["gap_opened_px"]
        assert stage["surface_opened_px"] >= alone["surface_opened_px"]
    assert "Filled holes decided" in (out / "bench_gaps.md").read_text()
