"""Selecting the actions `ultrastage rerun` redoes, from a release's manifests."""
from __future__ import annotations

import math

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from manifests.select import action_metric, parse_condition, select_actions
from pipeline.errors import InputError


def _release(tmp_path):
    folder = tmp_path / "manifests"
    folder.mkdir()
    pq.write_table(pa.Table.from_pylist([
        {"action_id": "A0000", "session_id": "S000", "subject": "mh/alice", "status": "ok", "error": None},
        {"action_id": "A0001", "session_id": "S000", "subject": "mh/bob", "status": "failed",
         "error": "x.dng: truncated file"},
        {"action_id": "A0002", "session_id": "S001", "subject": "other/carol", "status": "ok", "error": None},
    ]), folder / "actions.parquet")
    rows = [{"action_id": "A0000", "camera_id": None, "metric": "psnr", "value": 28.0},
            {"action_id": "A0002", "camera_id": None, "metric": "psnr", "value": 33.0},
            # per-camera only: the action's value is their mean; NaN rows are left out
            {"action_id": "A0000", "camera_id": "00000", "metric": "err", "value": 2.0},
            {"action_id": "A0000", "camera_id": "00001", "metric": "err", "value": 4.0},
            {"action_id": "A0000", "camera_id": "00002", "metric": "err", "value": math.nan},
            {"action_id": "A0002", "camera_id": "00000", "metric": "err", "value": 1.0}]
    pq.write_table(pa.Table.from_pylist(rows), folder / "metrics.parquet")
    return tmp_path


def test_parse_condition():
    c = parse_condition("heldout_albedo_psnr_db < 30")
    assert (c.metric, c.op, c.value) == ("heldout_albedo_psnr_db", "<", 30.0)
    assert parse_condition("x>=1e-3").value == 1e-3
    assert c.holds(29.9) and not c.holds(30.0) and not c.holds(math.nan)
    for bad in ("x << 1", "x < ", "< 3", "x < abc", ""):
        with pytest.raises(ValueError, match="METRIC OP NUMBER"):
            parse_condition(bad)


def test_action_metric_prefers_the_action_row_else_the_camera_mean():
    table = [{"action_id": "A", "camera_id": None, "metric": "m", "value": 5.0},
             {"action_id": "A", "camera_id": "0", "metric": "m", "value": 1.0},
             {"action_id": "B", "camera_id": "0", "metric": "m", "value": 1.0},
             {"action_id": "B", "camera_id": "1", "metric": "m", "value": 2.0},
             {"action_id": "C", "camera_id": "0", "metric": "other", "value": 9.0}]
    assert action_metric(table, "m") == {"A": 5.0, "B": 1.5}


def test_select_failed_where_subject_session(tmp_path):
    release = _release(tmp_path)
    failed = select_actions(release, failed=True)
    assert failed.actions == ["A0001"] and "truncated file" in failed.reasons["A0001"]
    low = select_actions(release, where=parse_condition("psnr < 30"))
    assert low.actions == ["A0000"] and low.reasons["A0000"] == "psnr = 28 < 30"
    assert select_actions(release, where=parse_condition("err >= 3")).actions == ["A0000"]  # mean of 2 and 4
    # either criterion selects; filters restrict
    assert select_actions(release, failed=True, where=parse_condition("psnr < 30")).actions == ["A0000", "A0001"]
    assert select_actions(release, failed=True, where=parse_condition("psnr < 30"), subject="mh/bob").actions == ["A0001"]
    assert select_actions(release, subject="mh/").actions == ["A0000", "A0001"]
    assert select_actions(release, session="S001").actions == ["A0002"]
    assert select_actions(release, where=parse_condition("psnr > 40")).actions == []
    with pytest.raises(InputError, match="no values of metric 'nosuch'"):
        select_actions(release, where=parse_condition("nosuch < 1"))
    with pytest.raises(InputError, match="actions.parquet"):
        select_actions(tmp_path / "elsewhere", failed=True)
