"""What a failed run says: a skipped stage names the stage that failed (once), and the next plan says that
the task failed last time, why, and that it will retry."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.capture import open_capture
from pipeline.graph import make_plan
from pipeline.hashing import DigestCache
from pipeline.runner import ExecutionConfig
from pipeline.stage import Stage, StageContext
from pipeline.store import ArtifactStore
from ultrastage.run import run_pipeline
from tests.unit.pipeline.conftest import ToyConfig, toy_stages

SYNC = ExecutionConfig(scheduler="sync")


class PublishToy(Stage):
    """Two stages below the failing one, so a chain of "not run" would show."""

    name = "publish"
    requires = ("summary",)
    outputs = ("published.txt",)

    def run(self, ctx: StageContext) -> dict[str, Any]:
        (ctx.out_dir / "published.txt").write_text("yes")
        return {}


def _stages() -> list[Stage]:
    return toy_stages() + [PublishToy(ToyConfig())]


def _run(capture: Path, tmp: Path):
    lines: list[str] = []
    result = run_pipeline(capture, tmp / "release", tmp / "work", _stages(), {"toy": 1}, SYNC, echo=lines.append)
    return result, lines


def test_skipped_stages_name_the_failed_stage_once(toy_capture, tmp_path):
    bad = toy_capture / "actions" / "A0001" / "full_on" / "00002.dng"
    bad.write_text("BAD")
    result, _ = _run(toy_capture, tmp_path)
    tasks = {(t.stage.name, t.scope_id): t for t in result.plan.tasks}
    assert tasks[("read", "A0001")].status == "failed"
    for name in ("summary", "publish"):
        task = tasks[(name, "A0001")]
        assert task.status == "skipped" and task.failed_stage == "read"
        assert task.error == "not run: upstream read failed"
    assert result.action_errors["A0001"].startswith("read: ") and "corrupt toy frame" in result.action_errors["A0001"]


def test_plan_after_a_failure_says_why_and_that_it_will_retry(toy_capture, tmp_path):
    bad = toy_capture / "actions" / "A0001" / "full_on" / "00002.dng"
    bad.write_text("BAD")
    _run(toy_capture, tmp_path)
    work = tmp_path / "work"

    def plan_lines() -> list[str]:
        lines: list[str] = []
        make_plan(open_capture(toy_capture), _stages(), ArtifactStore(work / "artifacts"),
                  DigestCache(work / "digests.json"), echo=lines.append)
        return lines

    read_line = next(line for line in plan_lines() if line.startswith("read") and "A0001" in line)
    assert "failed last run: " in read_line and "corrupt toy frame" in read_line and read_line.endswith("; will retry")
    assert "no earlier result" not in read_line
    summary_line = next(line for line in plan_lines() if line.startswith("summary") and "A0001" in line)
    assert "upstream read failed last run" in summary_line
    # a run that succeeds clears the record: the task is cached, and no longer "failed last run"
    bad.write_text("A0001 full_on 00002")
    _run(toy_capture, tmp_path)
    assert not any("failed last run" in line for line in plan_lines())
