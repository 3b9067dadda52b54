"""What keeps the engine linear at release size (issue 23, bench/bench_scale.py): scopes submitted a window at a
time with finished handles let go, lookups by index instead of scans, and the same answers as before."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from pipeline.capture import open_capture
from pipeline.graph import SyncExecutor, execute, make_plan
from pipeline.hashing import DigestCache
from pipeline.store import ArtifactStore
from tests.unit.pipeline.conftest import SessionToy, make_toy_capture, toy_stages

ACTIONS = tuple(f"A{i:04d}" for i in range(6))


class CountingSync(SyncExecutor):
    """The in-process executor, counting the scopes whose tasks were submitted and not yet seen complete."""

    def __init__(self) -> None:
        self.open: dict[str, int] = {}
        self.most_scopes = 0
        self._scope_of: dict[int, str] = {}

    def submit(self, fn: Any, *args: Any, key: str, resources: dict | None = None) -> Any:
        result = super().submit(fn, *args, key=key, resources=resources)
        scope = key.split("-")[1]
        if key.endswith("-commit"):
            self._scope_of[id(result)] = scope
            self.open[scope] = self.open.get(scope, 0) + 1
            self.most_scopes = max(self.most_scopes, len(self.open))
        return result

    def completions(self, handles: Any = ()) -> Any:
        inner = super().completions(handles)
        owner = self

        class Seen:
            def add(self, handle: Any) -> None:
                inner.add(handle)

            def __iter__(self):
                for handle, result in inner:
                    scope = owner._scope_of.pop(id(handle), None)
                    if scope is not None:
                        owner.open[scope] -= 1
                        if not owner.open[scope]:
                            del owner.open[scope]
                    yield handle, result

        return Seen()


def _plan(tmp_path: Path, stages=None):
    capture = open_capture(make_toy_capture(tmp_path / "capture", actions=ACTIONS))
    store = ArtifactStore(tmp_path / "work" / "artifacts")
    plan = make_plan(capture, stages or toy_stages(), store, DigestCache(tmp_path / "work" / "digests.json"),
                     echo=lambda line: None)
    return capture, plan


@pytest.mark.parametrize("window", [1, 2])
def test_execute_holds_at_most_a_window_of_scopes(tmp_path, window):
    capture, plan = _plan(tmp_path)
    executor = CountingSync()
    done: list[str] = []
    execute(plan, capture, executor, on_done=lambda task, result, n, total: done.append(task.name), window=window)
    assert executor.most_scopes == window
    assert {t.status for t in plan.tasks} == {"ran"} and len(done) == len(plan.tasks)
    # session first, then the actions in plan order
    assert done[0] == "calib S000" and [n for n in done if n.startswith("summary")] == [f"summary {a}" for a in ACTIONS]


def test_an_executor_without_completions_gets_everything_at_once(tmp_path):
    class OnlyAsCompleted:
        name = "as_completed only"

        def __init__(self) -> None:
            self.scopes: set[str] = set()
            self.scopes_at_first_result: int | None = None

        def submit(self, fn: Any, *args: Any, key: str, resources: dict | None = None) -> Any:
            self.scopes.add(key.split("-")[1])
            return fn(*args)

        def as_completed(self, handles: list[Any]):
            for handle in handles:
                if self.scopes_at_first_result is None:
                    self.scopes_at_first_result = len(self.scopes)
                yield handle, handle

    capture, plan = _plan(tmp_path)
    executor = OnlyAsCompleted()
    execute(plan, capture, executor, window=1)
    assert executor.scopes_at_first_result == 1 + len(ACTIONS)
    assert {t.status for t in plan.tasks} == {"ran"}


class FailingCalib(SessionToy):
    def run(self, ctx):  # noqa: ANN001
        raise RuntimeError("no calibration today")


def test_a_failure_reaches_scopes_submitted_after_it_finished(tmp_path):
    """With a window of one scope the session has finished (and its handle been let go) before any action is
    submitted: the actions still learn that it failed, and are skipped naming it."""
    stages = toy_stages()
    stages[0] = FailingCalib(stages[0].config)
    capture, plan = _plan(tmp_path, stages)
    execute(plan, capture, SyncExecutor(), window=1)
    calib = next(t for t in plan.tasks if t.stage.name == "calib")
    assert calib.status == "failed" and "no calibration today" in calib.error
    others = [t for t in plan.tasks if t is not calib]
    assert {t.status for t in others} == {"skipped"} and {t.failed_stage for t in others} == {"calib"}


def test_dask_scheduler_holds_a_window_not_the_graph(tmp_path):
    from distributed import LocalCluster

    from pipeline.graph import DaskExecutor

    capture, plan = _plan(tmp_path)
    seen: list[int] = []
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        executor = DaskExecutor(address=cluster.scheduler_address)
        try:
            def count(task, result, n, total):  # noqa: ANN001
                seen.append(executor.client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)))
            execute(plan, capture, executor, on_done=count, window=1)
        finally:
            executor.close()
    graph = len(plan.tasks) + sum(len(t.views) for t in plan.tasks if t.stage.per_view)  # 1 + 6 x (3 + 1 + 1)
    assert {t.status for t in plan.tasks} == {"ran"}
    per_action = 3 + 1 + 1
    assert max(seen) <= 3 * per_action + 1 < graph  # an action, and some the scheduler has not forgotten yet


def test_capture_lookups_and_listing_agree_with_the_folder(tmp_path):
    capture = open_capture(make_toy_capture(tmp_path / "capture", actions=ACTIONS))
    assert [capture.action(a).action_id for a in ACTIONS] == list(ACTIONS)
    with pytest.raises(KeyError, match="no action A9999"):
        capture.action("A9999")
    folder = tmp_path / "capture" / "actions" / "A0001" / "pos"
    (folder / "00001.DNG").write_text("second file of a camera")
    (folder / "notes.txt").write_text("not a raw file")
    (folder / "00002.dng").unlink()
    cams = ["00000", "00001", "00002"]
    assert capture.raw_paths("A0001", "pos", cams) == {c: capture.raw_path("A0001", "pos", c) for c in cams}
    assert capture.raw_paths("A0001", "pos", cams)["00002"] is None
    frames, errors = capture.action_frames("A0001")
    assert sorted(e.reason.split(":")[0] for e in errors) == ["camera 00001 has 2 raw files for 'pos' (['00001.DNG', "
                                                              "'00001.dng'])", "camera 00002 has no raw file for 'pos'"]
    assert ("pos", "00000") in frames and ("pos", "00001") not in frames
    capture.actions.append(capture.actions[0].__class__("A0100", "S000", "toy"))  # a grown list is seen
    assert capture.action("A0100").action_id == "A0100"


def test_digest_keys_are_resolved_paths(tmp_path, monkeypatch):
    real = tmp_path / "real"
    real.mkdir()
    (real / "a.dng").write_bytes(b"frame")
    (real / "target.dng").write_bytes(b"other")
    os.symlink(real, tmp_path / "linked")
    os.symlink(real / "target.dng", real / "b.dng")
    monkeypatch.chdir(tmp_path)
    cache = DigestCache(tmp_path / "digests.json")
    for path in (tmp_path / "linked" / "a.dng", Path("linked/a.dng"), Path("real/../linked/a.dng"),
                 real / "b.dng", tmp_path / "linked" / "b.dng"):
        assert cache._resolved(path) == str(Path(path).resolve())
        assert cache.digest(path)["bytes"] == Path(path).stat().st_size
    assert cache.hashed == 2 and set(cache._entries) == {str(real / "a.dng"), str(real / "target.dng")}
    with pytest.raises(FileNotFoundError):
        cache.digest(real / "missing.dng")


def test_validated_rows_are_the_same_whichever_path_checks_them():
    import datetime

    import numpy as np

    from manifests.writer import _checked_columns, _fast_columns, validate_rows
    from manifests.schemas import spec

    rows = [{"action_id": f"A{i:04d}", "camera_id": f"{i % 3:05d}", "metric": "decode_mean", "region": None,
             "environment": None, "value": v, "unit": "1", "source": "decode", "run_id": "r1"}
            for i, v in enumerate([0.5, 1, 2.25, 3])]
    ts = spec("metrics")
    assert _fast_columns("metrics", ts, rows) == _checked_columns("metrics", ts, rows)
    assert validate_rows("metrics", rows).column("value").to_pylist() == [0.5, 1.0, 2.25, 3.0]
    # numpy scalars take the row-by-row path, which converts them: the same table
    mixed = [dict(r, value=np.float32(r["value"])) for r in rows]
    assert validate_rows("metrics", mixed).equals(validate_rows("metrics", rows))
    # and errors are named as before: the first bad row in row order
    bad = [dict(rows[0], value=float("nan")), dict(rows[1], camera_id="7")]
    with pytest.raises(ValueError, match=r"metrics row 0: column 'value' is nan"):
        validate_rows("metrics", bad)
    stage_row = {"run_id": "r1", "stage": "decode", "version": "1", "scope": "action", "scope_id": "A0000",
                 "cache_key": "0" * 64, "status": "ran", "seconds": 1.0, "error": "not allowed",
                 "started_at": datetime.datetime.now(datetime.timezone.utc), "config_json": "{}"}
    with pytest.raises(ValueError, match="row 0: column 'error' must be null when status is 'ran'"):
        validate_rows("stage_runs", [stage_row])


def test_tasks_of_scopes_come_in_plan_order(tmp_path):
    capture, plan = _plan(tmp_path)
    for scopes in (("A0003",), ("S000", "A0003"), ("A0003", "S000"), ("A0001", "A0000"), ("nope",)):
        assert plan.of_scopes(*scopes) == [t for t in plan.tasks if t.scope_id in scopes]
    assert plan.for_scope("A0002") == [t for t in plan.tasks if t.scope_id == "A0002"]
