"""The engine end to end on toy stages: caching, reruns, forcing, failure isolation, atomic release."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.graph import downstream_of, topo_order
from pipeline.runner import ExecutionConfig
from ultrastage.run import run_pipeline
from tests.unit.pipeline.conftest import toy_stages

SYNC = ExecutionConfig(scheduler="sync")


def _run(capture: Path, tmp: Path, stages=None, **kw):
    lines: list[str] = []
    result = run_pipeline(capture, tmp / "release", tmp / "work", stages or toy_stages(), {"toy": 1},
                          kw.pop("execution", SYNC), echo=lines.append, **kw)
    return result, lines


def _statuses(result):
    return {(t.stage.name, t.scope_id): t.status for t in result.plan.tasks}


def test_first_run_runs_everything_and_second_run_nothing(toy_capture, tmp_path):
    first, _ = _run(toy_capture, tmp_path)
    assert set(_statuses(first).values()) == {"ran"}
    assert first.action_status == {"A0000": "ok", "A0001": "ok"}
    release = tmp_path / "release"
    assert (release / "actions" / "A0000" / "frames" / "00002.txt").read_text() == "A0000 full_on 00002 x1.0"
    second, lines = _run(toy_capture, tmp_path)
    assert set(_statuses(second).values()) == {"cached"}
    assert second.executor.startswith("none")
    # one line per skip decision, with its reason
    assert sum("cached" in line for line in lines) == len(second.plan.tasks) + 2  # + 2 release lines


def test_config_change_reruns_exactly_that_stage_and_downstream(toy_capture, tmp_path):
    _run(toy_capture, tmp_path)
    result, lines = _run(toy_capture, tmp_path, stages=toy_stages(gain=2.0))
    st = _statuses(result)
    assert st[("calib", "S000")] == "cached"
    assert st[("read", "A0000")] == "ran" and st[("summary", "A0000")] == "ran"
    assert any("config.gain 1.0 -> 2.0" in line for line in lines)
    # a field outside the key changes nothing
    result, _ = _run(toy_capture, tmp_path, stages=toy_stages(gain=2.0, workers=8))
    assert set(_statuses(result).values()) == {"cached"}


def test_changed_raw_input_reruns_only_its_action(toy_capture, tmp_path):
    _run(toy_capture, tmp_path)
    (toy_capture / "actions" / "A0001" / "pos" / "00001.dng").write_text("new bytes")
    result, _ = _run(toy_capture, tmp_path)
    st = _statuses(result)
    assert st[("read", "A0000")] == "cached" and st[("read", "A0001")] == "ran"


def test_only_and_from_force_stages(toy_capture, tmp_path):
    _run(toy_capture, tmp_path)
    only, _ = _run(toy_capture, tmp_path, only="read")
    st = _statuses(only)
    assert st[("read", "A0000")] == "ran" and st[("summary", "A0000")] == "cached"
    from_, _ = _run(toy_capture, tmp_path, from_stage="read")
    st = _statuses(from_)
    assert st[("read", "A0000")] == "ran" and st[("summary", "A0000")] == "ran" and st[("calib", "S000")] == "cached"
    with pytest.raises(ValueError, match="no such stage"):
        _run(toy_capture, tmp_path, only="nope")


def test_bad_frame_fails_its_action_only_and_leaves_nothing_in_release(toy_capture, tmp_path):
    _run(toy_capture, tmp_path)
    bad = toy_capture / "actions" / "A0001" / "full_on" / "00002.dng"
    bad.write_text("BAD")
    result, _ = _run(toy_capture, tmp_path)
    assert result.action_status == {"A0000": "ok", "A0001": "failed"}
    assert str(bad) in result.action_errors["A0001"] and "corrupt toy frame" in result.action_errors["A0001"]
    st = _statuses(result)
    assert st[("read", "A0001")] == "failed" and st[("summary", "A0001")] == "skipped"
    release = tmp_path / "release"
    assert not (release / "actions" / "A0001").exists()
    assert (release / "actions" / "A0000").is_dir()
    assert not list((release / "actions").glob(".tmp-*"))
    assert not list((tmp_path / "work" / "artifacts" / "read" / "A0001").glob(".tmp-*"))
    from manifests import open_release

    rel = open_release(release)
    row = rel.actions.set_index("action_id").loc["A0001"]
    assert row["status"] == "failed" and "corrupt toy frame" in row["error"]
    frames = rel.frames
    failed = frames[(frames.action_id == "A0001") & (frames.status == "failed")]
    assert list(failed.camera_id) == ["00002"]


def test_missing_camera_fails_at_plan_time_naming_it(toy_capture, tmp_path):
    (toy_capture / "actions" / "A0000" / "neg" / "00001.dng").unlink()
    result, lines = _run(toy_capture, tmp_path)
    assert result.action_status["A0000"] == "failed" and result.action_status["A0001"] == "ok"
    assert "camera 00001 has no raw file for 'neg'" in result.action_errors["A0000"]
    frames = __import__("manifests").open_release(tmp_path / "release").frames
    assert "missing" in set(frames[frames.action_id == "A0000"].status)


def test_release_manifests_and_verify(toy_capture, tmp_path):
    _run(toy_capture, tmp_path)
    from manifests import open_release, verify_release

    rel = open_release(tmp_path / "release")
    assert set(rel.stage_runs.status) == {"ran"} and rel.stage_runs.started_at.notna().all()
    assert len(rel.assets[rel.assets.kind == "frame"]) == 6
    assert verify_release(tmp_path / "release").ok
    path = tmp_path / "release" / "actions" / "A0000" / "summary.txt"
    path.write_text("tampered")
    assert not verify_release(tmp_path / "release").ok


def test_graph_helpers():
    stages = toy_stages()
    assert [s.name for s in topo_order(list(reversed(stages)))] == ["calib", "read", "summary"]
    assert downstream_of(stages, "read") == {"read", "summary"}


def test_long_tasks_report_progress_in_process(toy_capture, tmp_path):
    records: list[dict] = []
    _run(toy_capture, tmp_path, stage_progress=records.append)
    assert records == [{"stage": "calib", "scope_id": "S000", "done": 1, "total": 1, "message": "calibrated"}]


def test_dask_local_cluster_gives_the_same_release(toy_capture, tmp_path):
    records: list[dict] = []
    result, _ = _run(toy_capture, tmp_path, execution=ExecutionConfig(scheduler="local", workers=2),
                     stage_progress=records.append)
    # the record travels from the worker process as a dask event, before the task's result
    assert [(r["stage"], r["message"]) for r in records] == [("calib", "calibrated")]
    assert result.executor.startswith("local dask cluster")
    assert result.action_status == {"A0000": "ok", "A0001": "ok"}
    text = (tmp_path / "release" / "actions" / "A0001" / "frames" / "00000.txt").read_text()
    assert text == "A0000 full_on 00000 x1.0".replace("A0000", "A0001")
    record = json.loads((tmp_path / "work" / "published" / "A0001.json").read_text())
    assert {r["kind"] for r in record["assets"]} == {"frame", "summary"}


def test_existing_scheduler_by_address(toy_capture, tmp_path):
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        result, _ = _run(toy_capture, tmp_path, execution=ExecutionConfig(scheduler=cluster.scheduler_address))
    assert result.executor == f"dask scheduler at {cluster.scheduler_address}"
    assert result.action_status == {"A0000": "ok", "A0001": "ok"}


def test_relative_paths_work_like_make_dataset(toy_capture, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = run_pipeline(Path("capture"), Path("runs/release"), Path("runs/release.work"), toy_stages(),
                          {"toy": 1}, SYNC, echo=lambda line: None)
    assert result.action_status == {"A0000": "ok", "A0001": "ok"}
    from manifests import open_release, verify_release

    assert verify_release(tmp_path / "runs" / "release").ok
    assert set(open_release(tmp_path / "runs" / "release").assets.path.str.startswith("actions/").dropna()) >= {True}


def test_new_action_in_a_session_reuses_the_session_stages(tmp_path):
    from tests.unit.pipeline.conftest import make_toy_capture

    capture = make_toy_capture(tmp_path / "capture", actions=("A0000",))
    _run(capture, tmp_path)
    grown = make_toy_capture(tmp_path / "capture2", actions=("A0000", "A0001"))
    (grown / "sessions" / "S000" / "rig.json").write_bytes((capture / "sessions" / "S000" / "rig.json").read_bytes())
    result, lines = _run(grown, tmp_path)
    st = _statuses(result)
    assert st[("calib", "S000")] == "cached"  # calibrated once per session, not per action
    assert st[("read", "A0001")] == "ran" and st[("read", "A0000")] == "cached"


def test_local_cluster_workers_keep_glibc_malloc_trim(monkeypatch):
    import os

    from pipeline.graph import DaskExecutor

    # dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 in its workers, which made numeric work 2.6x slower
    # (bench/bench_executor.py); the executor's workers keep this process's setting (here: none)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    for var in ("ULTRASTAGE_NUMERIC_THREADS", "OMP_NUM_THREADS"):  # the executor sets them for its workers
        monkeypatch.setenv(var, "1")
    executor = DaskExecutor(workers=1)
    try:
        seen = executor.client.submit(os.environ.get, "MALLOC_TRIM_THRESHOLD_", "unset", pure=False).result()
    finally:
        executor.close()
    assert seen == "unset"
