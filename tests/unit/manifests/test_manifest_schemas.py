"""Schemas: every column described, round trip through Parquet with metadata intact."""
from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from manifests import PRIMARY_KEYS, SCHEMAS, open_release, write_table
from manifests.schemas import TABLE_SPECS, media_type

EXPECTED_COLUMNS = {
    "actions": ["action_id", "session_id", "subject", "status", "error", "n_cameras", "width", "height",
                "stages_run", "stages_cached", "seconds"],
    "frames": ["action_id", "camera_id", "illumination", "raw_path", "raw_bytes", "raw_sha256", "exposure_s",
               "width", "height", "status", "error"],
    "assets": ["action_id", "camera_id", "kind", "path", "bytes", "sha256", "media_type"],
    "metrics": ["action_id", "camera_id", "metric", "region", "environment", "value", "unit", "source", "run_id"],
    "metrics_summary": ["metric", "value", "unit", "aggregation", "n_actions", "source", "run_id"],
    "stage_runs": ["run_id", "stage", "version", "scope", "scope_id", "cache_key", "status", "seconds",
                   "error", "started_at", "config_json"],
    "relight_examples": ["example_id", "action_id", "subject", "session_id", "split", "view_index", "width", "height",
                         "fx", "fy", "cx", "cy", "cam_from_world_json", "environment_name", "environment_file",
                         "environment_sha256", "environment_rotation_deg", "sh_camera_json", "sh_world_json",
                         "image_exr", "image_png", "albedo_exr", "albedo_png", "normal_exr", "normal_png", "mask_png",
                         "png_exposure", "mask_pixels", "seed", "example_key"],
}

SHA = "ab" * 32
T0 = datetime(2026, 1, 2, 3, 4, 5, 678901, tzinfo=timezone.utc)

SAMPLE_ROWS = {
    "actions": [dict(action_id="A0001", session_id="S000", subject="s", status="failed",
                     error="actions/A0001/pos/00003.dng: corrupt", n_cameras=32, width=None, height=None,
                     stages_run=2, stages_cached=1, seconds=3.5),
                dict(action_id="A0000", session_id="S000", subject="s", status="ok", error=None, n_cameras=32,
                     width=320, height=480, stages_run=9, stages_cached=0, seconds=12.0)],
    "frames": [dict(action_id="A0000", camera_id="00000", illumination="pos", raw_path="actions/A0000/pos/00000.dng",
                    raw_bytes=123, raw_sha256=SHA, exposure_s=0.01, width=640, height=960, status="ok", error=None),
               dict(action_id="A0000", camera_id="00001", illumination="neg", status="missing",
                    error="actions/A0000/neg/00001.*: no file")],
    "assets": [dict(action_id=None, camera_id=None, kind="datasheet", path="DATASHEET.md", bytes=10, sha256=SHA,
                    media_type="text/markdown"),
               dict(action_id="A0000", camera_id="00000", kind="mask", path="actions/A0000/mask/00000.png",
                    bytes=99, sha256=SHA, media_type="image/png")],
    "metrics": [dict(action_id="A0000", camera_id=None, metric="normal_angular_error_mean_deg", region="valid",
                     environment=None, value=4.8, unit="deg", source="evaluate", run_id="r1"),
                dict(action_id="A0000", camera_id="N000", metric="relit_psnr_db", region="all",
                     environment="procedural_sky", value=21.0, unit="dB", source="evaluate", run_id="r1")],
    "metrics_summary": [dict(metric="normal_mean_deg", value=4.8, unit="deg", aggregation="pooled", n_actions=2,
                             source="evaluate", run_id="r1"),
                        dict(metric="actions_ok", value=2, unit="count", aggregation="count", n_actions=2,
                             source="evaluate", run_id="r1")],
    "stage_runs": [dict(run_id="r1", stage="decode", version="1", scope="action", scope_id="A0000", cache_key="k1",
                        status="ran", seconds=2.0, error=None, started_at=T0, config_json='{"demosaic": "AHD"}'),
                   dict(run_id="r1", stage="calibrate", version="2", scope="session", scope_id="S000",
                        cache_key="k0", status="cached", seconds=0.0,
                        started_at=T0.astimezone(timezone(timedelta(hours=2))), config_json="{}")],
}


def test_tables_and_columns_are_as_documented():
    assert set(SCHEMAS) == set(EXPECTED_COLUMNS) | {"relight_examples"}
    for name, cols in EXPECTED_COLUMNS.items():
        assert SCHEMAS[name].names == cols
        assert set(PRIMARY_KEYS[name]) <= set(cols)


def test_every_column_has_a_description_in_field_metadata():
    for name, schema in SCHEMAS.items():
        assert schema.metadata[b"ultrastage.table"] == name.encode()
        for f in schema:
            assert f.metadata and f.metadata[b"description"].strip(), (name, f.name)
        for col in TABLE_SPECS[name].columns:
            assert col.description


def test_types_match_the_contract():
    s = SCHEMAS
    assert s["actions"].field("n_cameras").type == pa.int32()
    assert s["actions"].field("seconds").type == pa.float64()
    assert s["frames"].field("raw_bytes").type == pa.int64()
    assert s["assets"].field("bytes").type == pa.int64()
    assert s["metrics"].field("value").type == pa.float64()
    assert s["stage_runs"].field("started_at").type == pa.timestamp("us", tz="UTC")
    assert s["actions"].field("error").nullable and not s["actions"].field("action_id").nullable
    assert s["assets"].field("action_id").nullable and s["assets"].field("camera_id").nullable


@pytest.mark.parametrize("name", sorted(SAMPLE_ROWS))
def test_round_trip(tmp_path, name):
    path = write_table(tmp_path, name, SAMPLE_ROWS[name])
    assert path == tmp_path / "manifests" / f"{name}.parquet"
    table = pq.read_table(path)
    assert table.schema.equals(SCHEMAS[name], check_metadata=True)
    assert table.num_rows == len(SAMPLE_ROWS[name])
    # sorted by primary key, values preserved (omitted nullable columns read back as None)
    key = PRIMARY_KEYS[name]
    got = {tuple(r[k] for k in key): r for r in table.to_pylist()}
    for row in SAMPLE_ROWS[name]:
        stored = got[tuple(row.get(k) for k in key)]
        for col, value in row.items():
            assert stored[col] == value, (col, stored[col], value)
    df = getattr(open_release(tmp_path), name)
    assert list(df.columns) == EXPECTED_COLUMNS[name]
    assert len(df) == len(SAMPLE_ROWS[name])


def test_rows_are_stored_sorted_by_primary_key(tmp_path):
    write_table(tmp_path, "actions", SAMPLE_ROWS["actions"])
    assert pq.read_table(tmp_path / "manifests" / "actions.parquet").column("action_id").to_pylist() == [
        "A0000", "A0001"]


def test_timestamps_are_stored_in_utc(tmp_path):
    write_table(tmp_path, "stage_runs", SAMPLE_ROWS["stage_runs"])
    df = open_release(tmp_path).stage_runs
    assert str(df["started_at"].dt.tz) == "UTC"
    assert (df["started_at"] == T0).all()


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_empty_rows_give_empty_table_with_schema(tmp_path, name):
    path = write_table(tmp_path, name, [])
    table = pq.read_table(path)
    assert table.num_rows == 0
    assert table.schema.equals(SCHEMAS[name], check_metadata=True)


def test_media_types():
    assert media_type("a/b.exr") == "image/x-exr"
    assert media_type("a/b.PNG") == "image/png"
    assert media_type("transforms.json") == "application/json"
    assert media_type("a.b/noext") == "application/octet-stream"
