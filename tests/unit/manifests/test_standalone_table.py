"""Standalone Parquet tables outside a release (manifests.write_standalone_table): the baselines' metrics."""
from __future__ import annotations

import math

import pytest

from manifests import open_release, read_standalone_table, write_standalone_table, write_table
from manifests.schemas import STANDALONE_SPECS, TABLE_SPECS


def _row(**kw):
    row = {"network": "albedonet", "method": "albedonet", "split": "test", "example_id": "*",
           "metric": "albedo_psnr_raw_db", "value": 21.5, "step": 10}
    row.update(kw)
    return row


def test_round_trip_keeps_schema_and_rows(tmp_path):
    path = write_standalone_table(tmp_path / "out" / "metrics.parquet", "baseline_metrics",
                                  [_row(), _row(example_id="A0000_00", value=20.0)])
    table = read_standalone_table(path, "baseline_metrics")
    assert table.num_rows == 2
    assert table.schema.metadata[b"ultrastage.table"] == b"baseline_metrics"
    assert sorted(table.column("example_id").to_pylist()) == ["*", "A0000_00"]
    assert not list(path.parent.glob(".*tmp"))


@pytest.mark.parametrize("bad", [dict(value=math.nan), dict(network="other"), dict(split="dev"),
                                 dict(example_id="../x"), dict(step=-1)])
def test_bad_rows_write_nothing(tmp_path, bad):
    with pytest.raises(ValueError):
        write_standalone_table(tmp_path / "m.parquet", "baseline_metrics", [_row(**bad)])
    assert not any(tmp_path.iterdir())


def test_standalone_and_release_tables_stay_apart(tmp_path):
    assert "baseline_metrics" in STANDALONE_SPECS and "baseline_metrics" not in TABLE_SPECS
    with pytest.raises(ValueError, match="not a standalone table"):
        write_standalone_table(tmp_path / "m.parquet", "actions", [])
    with pytest.raises(ValueError, match="standalone table"):
        write_table(tmp_path, "baseline_metrics", [_row()])
    # a release holding only a standalone file is still no release
    write_standalone_table(tmp_path / "manifests" / "baseline_metrics.parquet", "baseline_metrics", [_row()])
    with pytest.raises(FileNotFoundError):
        open_release(tmp_path)
