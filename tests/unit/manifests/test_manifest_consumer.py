"""Consumer: open_release, cached tables, lazy asset loading through the codecs, action views."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pytest

import manifests
from manifests import ReleaseError, open_release, write_table
from manifests import consumer as consumer_mod


def test_open_release_exported_and_tables(release_dir, tiny):
    rel = manifests.open_release(release_dir)
    assert isinstance(rel.actions, pd.DataFrame)
    assert rel.actions["action_id"].tolist() == ["A0000"]
    assert rel.action_ids == ["A0000"]
    assert isinstance(rel.table("assets"), pa.Table)
    assert len(rel.assets) == 6 * len(tiny.CAMS) + 1
    # tables the release lacks are empty, with their columns
    assert rel.metrics.empty and "value" in rel.metrics.columns
    assert rel.table("stage_runs").schema.equals(manifests.SCHEMAS["stage_runs"])


def test_tables_are_read_lazily_and_cached(release_dir, monkeypatch):
    calls = []
    real = consumer_mod.read_manifest

    def counting(root, name):
        calls.append(name)
        return real(root, name)

    monkeypatch.setattr(consumer_mod, "read_manifest", counting)
    rel = open_release(release_dir)
    assert calls == []
    rel.actions
    rel.actions
    rel.table("actions")
    assert calls == ["actions"]
    assert rel.actions is rel.actions


def test_load_is_lazy_and_by_extension(release_dir, tiny, monkeypatch):
    rel = open_release(release_dir)
    loaded = []
    real = consumer_mod.load_file
    monkeypatch.setattr(consumer_mod, "load_file", lambda p: loaded.append(p) or real(p))
    view = rel.action("A0000")
    assert loaded == []  # nothing read until asked
    rows = rel.assets.set_index(["kind", "camera_id"])
    exr = rel.load(rows.loc[("albedo", "00001")])               # a pandas row
    assert exr.dtype == np.float32 and exr.shape == (tiny.H, tiny.W, 3)
    np.testing.assert_allclose(exr, 0.5)
    png = rel.load("actions/A0000/mask/00000.png")              # a relative path
    assert png.dtype == np.uint8 and png.shape == (tiny.H, tiny.W) and set(np.unique(png)) == {0, 255}
    row = next(r for r in rel.table("assets").to_pylist() if r["kind"] == "transforms")
    assert rel.load(row)["frames"][0]["camera_id"] == "00000"    # a dict row
    assert len(loaded) == 3
    assert view.cameras == list(tiny.CAMS)


def test_load_rejects_unknown_extension_and_outside_paths(release_dir):
    rel = open_release(release_dir)
    (release_dir / "actions" / "A0000" / "notes.txt").write_text("hi")
    with pytest.raises(ValueError, match="no loader for .txt"):
        rel.load("actions/A0000/notes.txt")
    with pytest.raises(ValueError, match="not inside the release"):
        rel.load("../elsewhere.exr")


def test_action_view_maps(release_dir, tiny):
    view = open_release(release_dir).action("A0000")
    n = view.normals("00001")
    assert n.shape == (tiny.H, tiny.W, 3) and n.dtype == np.float32
    np.testing.assert_allclose(n, tiny.normals(1), atol=2e-3)  # half float on disk
    a = view.normal_alpha("00001")
    assert a.shape == (tiny.H, tiny.W)
    np.testing.assert_allclose(a, np.linspace(0, 1, tiny.H * tiny.W).reshape(tiny.H, tiny.W), atol=1e-3)
    m = view.mask("00000")
    assert m.dtype == bool and m.sum() == 6 and m[1, 1] and not m[0, 0]
    assert view.albedo("00000").shape == (tiny.H, tiny.W, 3)
    for ill, level in (("full_on", 0.25), ("pos", 0.25), ("neg", 0.25)):
        np.testing.assert_allclose(view.image(ill, "00000"), level)
    np.testing.assert_allclose(view.image("pos", "00001"), 0.5)
    assert view.transforms()["frames"][1]["camera_id"] == "00001"
    assert view.info["status"] == "ok"
    assert set(view.kinds) == {"full_on", "pos", "neg", "normal_alpha", "albedo", "mask", "transforms"}


def test_missing_assets_name_action_camera_kind(release_dir):
    rel = open_release(release_dir)
    view = rel.action("A0000")
    with pytest.raises(KeyError, match="action A0000, camera 00007: no 'normal_alpha' asset"):
        view.normals("00007")
    with pytest.raises(ValueError, match="illumination 'white'"):
        view.image("white", "00000")
    (release_dir / "actions" / "A0000" / "albedo" / "00001.exr").unlink()
    with pytest.raises(FileNotFoundError, match="action A0000, camera 00001, albedo: .*missing on disk"):
        view.albedo("00001")
    with pytest.raises(KeyError, match="action 'A9999' is not in the release"):
        rel.action("A9999")


def test_open_folder_without_manifests_is_a_clear_error(tmp_path):
    with pytest.raises(ReleaseError, match="not a release: no manifests"):
        open_release(tmp_path)
    with pytest.raises(FileNotFoundError, match="release folder not found"):
        open_release(tmp_path / "nope")
    (tmp_path / "manifests").mkdir()
    (tmp_path / "manifests" / "other.parquet").write_bytes(b"")
    with pytest.raises(ReleaseError):
        open_release(tmp_path)


def test_unknown_table_name(release_dir):
    with pytest.raises(ValueError, match="unknown manifest table"):
        open_release(release_dir).table("nope")


def test_old_file_missing_a_nullable_column_still_reads(tmp_path):
    import pyarrow.parquet as pq

    write_table(tmp_path, "metrics", [dict(action_id="A", camera_id=None, metric="m", region=None, value=1.0,
                                           unit="1", source="evaluate", run_id="r")])
    path = tmp_path / "manifests" / "metrics.parquet"
    pq.write_table(pq.read_table(path).drop_columns(["camera_id"]), path)
    table = open_release(tmp_path).table("metrics")
    assert table.schema.names == manifests.SCHEMAS["metrics"].names
    assert table.column("camera_id").to_pylist() == [None]


def test_metrics_of_schema_1_are_read_in_the_current_layout(tmp_path):
    """A release written before schema 2: summary rows (null action) are dropped, '' regions become null, a
    relit view's environment leaves the region column, held-out variants get their own names, units appear."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    (tmp_path / "manifests").mkdir()
    old = [("A0000", "00000", "valid_fraction", "", 0.8), ("A0000", "N000", "relit_psnr_db", "procedural_sky", 20.0),
           ("A0000", None, "heldout_normal_mean_deg", "heldout_truth", 9.0),
           ("A0000", None, "heldout_normal_mean_deg", "heldout", 7.0), (None, None, "normal_mean_deg", "", 5.0)]
    pq.write_table(pa.table({"action_id": [r[0] for r in old], "camera_id": [r[1] for r in old],
                             "metric": [r[2] for r in old], "region": [r[3] for r in old],
                             "value": [r[4] for r in old], "source": ["evaluate"] * len(old),
                             "run_id": ["evaluate"] * len(old)}), tmp_path / "manifests" / "metrics.parquet")
    got = {(r["metric"], r["region"], r["environment"], r["unit"]): r["value"]
           for r in open_release(tmp_path).table("metrics").to_pylist()}
    assert got == {("valid_fraction", None, None, "1"): 0.8, ("relit_psnr_db", "all", "procedural_sky", "dB"): 20.0,
                   ("heldout_normal_mean_deg_truth", "heldout", None, "deg"): 9.0,
                   ("heldout_normal_mean_deg", "heldout", None, "deg"): 7.0}
