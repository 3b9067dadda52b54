"""Writer: validation errors name the column, writes are atomic, append_rows upserts."""
from __future__ import annotations

import hashlib
import math
from datetime import datetime, timezone

import numpy as np
import pyarrow.parquet as pq
import pytest

from manifests import append_rows, asset_row, file_sha256, open_release, write_table
from manifests import writer as writer_mod


def metric(value=1.0, **kw):
    row = dict(action_id="A0000", camera_id="00000", metric="normal_angular_error_mean_deg", region="valid",
               environment=None, value=value, unit="deg", source="evaluate", run_id="r1")
    row.update(kw)
    return row


def stage_run(**kw):
    row = dict(run_id="r1", stage="decode", version="1", scope="action", scope_id="A0000", cache_key="k",
               status="ran", seconds=1.0, error=None, started_at=datetime(2026, 1, 1, tzinfo=timezone.utc),
               config_json="{}")
    row.update(kw)
    return row


def manifest_files(root):
    return sorted(p.name for p in (root / "manifests").iterdir())


# -- validation -----------------------------------------------------------------------------------------

def test_unknown_column_is_named(tmp_path):
    with pytest.raises(ValueError, match="unknown column 'valeu'"):
        write_table(tmp_path, "metrics", [metric(valeu=2.0)])


def test_missing_required_column_is_named(tmp_path):
    row = metric()
    del row["source"]
    with pytest.raises(ValueError, match="missing required column 'source'"):
        write_table(tmp_path, "metrics", [row])


def test_omitted_nullable_column_becomes_null(tmp_path):
    row = metric()
    del row["camera_id"]
    write_table(tmp_path, "metrics", [row])
    assert open_release(tmp_path).table("metrics").column("camera_id").to_pylist() == [None]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, np.float32("nan"), np.float64("inf")])
def test_non_finite_floats_are_rejected(tmp_path, bad):
    with pytest.raises(ValueError, match="'value'.*NaN and Inf"):
        write_table(tmp_path, "metrics", [metric(), metric(value=bad, region="all")])
    assert not (tmp_path / "manifests" / "metrics.parquet").exists()


@pytest.mark.parametrize("column, value, message", [
    ("value", "4.2", "must be a number"),
    ("value", True, "must be a number"),
    ("camera_id", 3, "must be a str"),
    ("camera_id", "3", "is '3', which does not match"),
    ("metric", None, "is null but required"),
])
def test_bad_values_are_rejected(tmp_path, column, value, message):
    with pytest.raises(ValueError, match=f"metrics row 0: column '{column}' {message}"):
        write_table(tmp_path, "metrics", [metric(**{column: value})])


def test_numpy_scalars_are_accepted(tmp_path):
    write_table(tmp_path, "metrics", [metric(value=np.float32(0.5))])
    write_table(tmp_path, "actions", [dict(action_id="A", session_id="S", subject="x", status="ok",
                                           n_cameras=np.int64(32), width=np.int32(4), height=4, stages_run=1,
                                           stages_cached=0, seconds=0)])
    assert open_release(tmp_path).actions["n_cameras"].tolist() == [32]


def test_choices_ranges_and_status_rules(tmp_path):
    with pytest.raises(ValueError, match="'status' is 'done', expected one of"):
        write_table(tmp_path, "stage_runs", [stage_run(status="done")])
    with pytest.raises(ValueError, match="'seconds' is -1.0, below the minimum"):
        write_table(tmp_path, "stage_runs", [stage_run(seconds=-1.0)])
    with pytest.raises(ValueError, match="'error' must name the file and reason"):
        write_table(tmp_path, "stage_runs", [stage_run(status="failed")])
    with pytest.raises(ValueError, match="'error' must be null when status is 'ran'"):
        write_table(tmp_path, "stage_runs", [stage_run(error="x")])
    with pytest.raises(ValueError, match="naive datetime"):
        write_table(tmp_path, "stage_runs", [stage_run(started_at=datetime(2026, 1, 1))])
    with pytest.raises(ValueError, match="not valid JSON"):
        write_table(tmp_path, "stage_runs", [stage_run(config_json="{bad")])
    with pytest.raises(ValueError, match="out of range for int32"):
        write_table(tmp_path, "actions", [dict(action_id="A", session_id="S", subject="x", status="ok",
                                               n_cameras=2**40, stages_run=1, stages_cached=0, seconds=0.0)])


@pytest.mark.parametrize("path", ["/abs/x.exr", "../x.exr", "a/../../x.exr", "a\\b.exr", ""])
def test_asset_paths_must_be_relative_posix(tmp_path, path):
    row = dict(kind="preview", path=path, bytes=1, sha256="0" * 64, media_type="image/png")
    with pytest.raises(ValueError, match="'path'"):
        write_table(tmp_path, "assets", [row])


def test_duplicate_primary_key_is_rejected(tmp_path):
    with pytest.raises(ValueError, match="duplicate key"):
        write_table(tmp_path, "metrics", [metric(value=1.0), metric(value=2.0)])


def test_unknown_table(tmp_path):
    with pytest.raises(ValueError, match="unknown manifest table 'splits'"):
        write_table(tmp_path, "splits", [])


# -- atomic writes --------------------------------------------------------------------------------------

def test_write_leaves_no_temp_files(tmp_path):
    write_table(tmp_path, "metrics", [metric()])
    write_table(tmp_path, "metrics", [metric(value=2.0)])
    append_rows(tmp_path, "metrics", [metric(region="all")])
    assert manifest_files(tmp_path) == ["index.json", "metrics.parquet"]


def test_failed_write_keeps_old_table_and_leaves_no_temp_files(tmp_path, monkeypatch):
    write_table(tmp_path, "metrics", [metric(value=1.0)])
    before = (tmp_path / "manifests" / "metrics.parquet").read_bytes()

    def crash(table, where, **kw):
        where.write(b"PAR1 half a file")
        raise OSError("disk full")

    monkeypatch.setattr(writer_mod.pq, "write_table", crash)
    with pytest.raises(OSError, match="disk full"):
        write_table(tmp_path, "metrics", [metric(value=2.0)])
    assert manifest_files(tmp_path) == ["index.json", "metrics.parquet"]
    assert (tmp_path / "manifests" / "metrics.parquet").read_bytes() == before


def test_invalid_rows_write_nothing(tmp_path):
    write_table(tmp_path, "metrics", [metric(value=1.0)])
    with pytest.raises(ValueError):
        write_table(tmp_path, "metrics", [metric(value=math.nan)])
    assert open_release(tmp_path).metrics["value"].tolist() == [1.0]


def test_same_content_same_bytes(tmp_path):
    rows = [metric(camera_id=c, value=float(i)) for i, c in enumerate(["00002", "00000", "00001"])]
    a = (write_table(tmp_path / "a", "metrics", rows)).read_bytes()
    b = (write_table(tmp_path / "b", "metrics", list(reversed(rows)))).read_bytes()
    assert a == b


# -- upsert ---------------------------------------------------------------------------------------------

def test_append_creates_table(tmp_path):
    append_rows(tmp_path, "metrics", [metric()], ["action_id", "camera_id", "metric", "region", "source"])
    assert len(open_release(tmp_path).metrics) == 1


def test_append_replaces_matching_keys_and_keeps_others(tmp_path):
    keys = ["action_id", "camera_id", "metric", "region", "source"]
    write_table(tmp_path, "metrics", [
        metric(value=1.0),
        metric(camera_id="00001", value=2.0),
        metric(camera_id=None, region=None, metric="n_actions", value=1.0),
        metric(source="photometric", value=9.0),
    ])
    append_rows(tmp_path, "metrics", [
        metric(value=10.0, run_id="r2"),                                           # replaces
        metric(camera_id=None, region=None, metric="n_actions", value=3.0, run_id="r2"),  # null keys match
        metric(camera_id="00002", value=20.0, run_id="r2"),                        # new
    ], keys)
    df = open_release(tmp_path).metrics
    got = {(r.action_id, r.camera_id, r.metric, r.source): (r.value, r.run_id) for r in df.itertuples()}
    got = {tuple(None if isinstance(x, float) and math.isnan(x) else x for x in k): v for k, v in got.items()}
    assert got == {
        ("A0000", "00000", "normal_angular_error_mean_deg", "evaluate"): (10.0, "r2"),
        ("A0000", "00001", "normal_angular_error_mean_deg", "evaluate"): (2.0, "r1"),
        ("A0000", "00002", "normal_angular_error_mean_deg", "evaluate"): (20.0, "r2"),
        ("A0000", "00000", "normal_angular_error_mean_deg", "photometric"): (9.0, "r1"),
        ("A0000", None, "n_actions", "evaluate"): (3.0, "r2"),
    }


def test_append_accumulates_stage_runs_over_runs(tmp_path):
    keys = ["run_id", "stage", "scope_id"]
    append_rows(tmp_path, "stage_runs", [stage_run(), stage_run(stage="normals")], keys)
    append_rows(tmp_path, "stage_runs", [stage_run(run_id="r2", status="cached", seconds=0.0),
                                         stage_run(run_id="r2", stage="normals")], keys)
    append_rows(tmp_path, "stage_runs", [stage_run(run_id="r2", stage="normals", status="failed",
                                                   error="x.exr: broken")], keys)
    df = open_release(tmp_path).stage_runs
    assert len(df) == 4
    assert df.set_index(["run_id", "stage"]).loc[("r2", "normals"), "status"] == "failed"


def test_append_default_key_is_primary_key(tmp_path):
    append_rows(tmp_path, "metrics", [metric(value=1.0)])
    append_rows(tmp_path, "metrics", [metric(value=2.0)])
    assert open_release(tmp_path).metrics["value"].tolist() == [2.0]


def test_append_rejects_bad_keys_and_duplicates(tmp_path):
    with pytest.raises(ValueError, match="unknown key column 'cam'"):
        append_rows(tmp_path, "metrics", [metric()], ["cam"])
    with pytest.raises(ValueError, match="duplicate key"):
        append_rows(tmp_path, "metrics", [metric(), metric(region="all")], ["action_id", "metric"])
    # a key wider than the primary key would leave two rows with one primary key
    write_table(tmp_path, "metrics", [metric(run_id="r1")])
    with pytest.raises(ValueError, match="duplicate key"):
        append_rows(tmp_path, "metrics", [metric(run_id="r2")],
                    ["action_id", "camera_id", "metric", "region", "source", "run_id"])
    assert open_release(tmp_path).metrics["run_id"].tolist() == ["r1"]


def test_append_preserves_schema(tmp_path):
    append_rows(tmp_path, "stage_runs", [stage_run()])
    append_rows(tmp_path, "stage_runs", [stage_run(run_id="r2")])
    from manifests import SCHEMAS
    assert pq.read_table(tmp_path / "manifests" / "stage_runs.parquet").schema.equals(
        SCHEMAS["stage_runs"], check_metadata=True)


# -- asset rows -----------------------------------------------------------------------------------------

def test_file_sha256_and_asset_row(tmp_path):
    data = bytes(range(256)) * 5000
    f = tmp_path / "actions" / "A0000" / "previews" / "grid.png"
    f.parent.mkdir(parents=True)
    f.write_bytes(data)
    assert file_sha256(f, chunk=4096) == hashlib.sha256(data).hexdigest()
    row = asset_row(tmp_path, f, "preview", action_id="A0000")
    assert row == {"action_id": "A0000", "camera_id": None, "kind": "preview",
                   "path": "actions/A0000/previews/grid.png", "bytes": len(data),
                   "sha256": hashlib.sha256(data).hexdigest(), "media_type": "image/png"}
    assert asset_row(tmp_path, "actions/A0000/previews/grid.png", "preview", "A0000") == row
    write_table(tmp_path, "assets", [row])


def test_asset_row_errors(tmp_path):
    outside = tmp_path / "elsewhere.exr"
    outside.write_bytes(b"x")
    with pytest.raises(ValueError, match="not inside the release"):
        asset_row(tmp_path / "release", outside, "albedo")
    with pytest.raises(FileNotFoundError, match="kind 'mask', action A0000, camera 00003"):
        asset_row(tmp_path, "actions/A0000/mask/00003.png", "mask", "A0000", "00003")


def test_write_table_keeping_replaces_the_run_actions_rows_and_keeps_the_others(tmp_path):
    from manifests.writer import read_manifest, write_table_keeping

    write_table(tmp_path, "metrics", [metric(1.0), metric(2.0, action_id="A0001"), metric(3.0, action_id="A0002"),
                                      metric(4.0, action_id="A0003", camera_id=None)])
    # a run over A0000 only: its rows are replaced, A0001's kept, A0002's and A0003's dropped
    write_table_keeping(tmp_path, "metrics", [metric(5.0)], keep_actions=["A0001"])
    table = read_manifest(tmp_path, "metrics").to_pylist()
    assert sorted((r["action_id"], r["value"]) for r in table) == [("A0000", 5.0), ("A0001", 2.0)]
    with pytest.raises(ValueError, match="metrics"):  # a kept row may not collide with a new one
        write_table_keeping(tmp_path, "metrics", [metric(6.0, action_id="A0001")], keep_actions=["A0001"])
    write_table_keeping(tmp_path, "metrics", [metric(7.0)], keep_actions=[])  # = write_table
    assert [r["value"] for r in read_manifest(tmp_path, "metrics").to_pylist()] == [7.0]


def test_replace_rows_drops_what_the_writer_owns_and_keeps_the_rest(tmp_path):
    from manifests.writer import read_manifest, replace_rows

    write_table(tmp_path, "metrics", [metric(1.0), metric(2.0, source="photometric"),
                                      metric(3.0, action_id="A0001", metric="stale_deg")])
    replace_rows(tmp_path, "metrics", [metric(9.0)], drop=lambda row: row["source"] == "evaluate")
    got = sorted((r["action_id"], r["source"], r["value"]) for r in read_manifest(tmp_path, "metrics").to_pylist())
    assert got == [("A0000", "evaluate", 9.0), ("A0000", "photometric", 2.0)]
    with pytest.raises(ValueError, match="duplicate key"):  # a kept row may not collide with a new one
        replace_rows(tmp_path, "metrics", [metric(5.0, source="photometric")], drop=lambda row: False)


def test_every_write_records_the_tables_digests_in_the_index(tmp_path):
    from manifests.writer import read_index

    write_table(tmp_path, "metrics", [metric(1.0)])
    append_rows(tmp_path, "stage_runs", [stage_run()])
    index = read_index(tmp_path / "manifests")
    assert sorted(index) == ["metrics.parquet", "stage_runs.parquet"]
    for name, entry in index.items():
        assert entry["sha256"] == file_sha256(tmp_path / "manifests" / name)


def test_tables_validated_in_parts_equal_the_whole_and_keys_are_checked_across_parts(tmp_path):
    rows = [metric(value=float(i), action_id=f"A{i % 3:04d}", camera_id=f"{i:05d}", region=None if i % 2 else "valid")
            for i in range(9)]
    parts = [writer_mod.validate_rows("metrics", [r for r in rows if r["action_id"] == a])
             for a in ("A0002", "A0000", "A0001")]
    assert writer_mod.concat_validated("metrics", parts).equals(writer_mod.validate_rows("metrics", rows))
    twice = [parts[0], writer_mod.validate_rows("metrics", [rows[2]])]  # A0002 00002 in both parts
    with pytest.raises(ValueError, match=r"duplicate key .*'action_id': 'A0002', 'camera_id': '00002'"):
        writer_mod.concat_validated("metrics", twice)
    nulls = [writer_mod.validate_rows("metrics", [metric(region=None)])] * 2  # null matches null
    with pytest.raises(ValueError, match="duplicate key"):
        writer_mod.concat_validated("metrics", nulls)
    release = tmp_path / "release"
    writer_mod.replace_rows(release, "metrics", writer_mod.concat_validated("metrics", parts), drop=lambda r: True)
    assert open_release(release).table("metrics").equals(writer_mod.validate_rows("metrics", rows))
    with pytest.raises(ValueError, match="another schema"):
        writer_mod.write_table_keeping(release, "metrics", parts[0].drop_columns(["run_id"]), keep_actions=())
