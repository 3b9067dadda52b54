"""ultrastage.merge_sets: one relighting set from several releases' sets, split by subject."""
from __future__ import annotations

import json
from pathlib import Path

import duckdb
import pytest

from manifests.consumer import open_release, verify_release
from pipeline.errors import ConfigError, InputError
from stages.numerics.relightset import split_of
from tests.unit.baselines.conftest import make_fake_relight_set
from ultrastage.baselines.data import RelightDataset
from ultrastage.cli import main
from ultrastage.merge_sets import FILE_COLUMNS, merge_relight_sets, parse_sources


def _source(root: Path, subjects: dict[str, str], seed: int) -> Path:
    return make_fake_relight_set(root / "release", views=2, size=16, seed=seed, subjects=subjects)


@pytest.fixture(scope="module")
def two_sources(tmp_path_factory) -> list:
    """Two releases: 'alpha' with subjects s0, s1 and 'beta' with s1 (the same name), s2."""
    base = tmp_path_factory.mktemp("sources")
    alpha = _source(base / "alpha", {"s0": "train", "s1": "train"}, seed=1)
    beta = _source(base / "beta", {"s1": "test", "s2": "train"}, seed=2)
    return parse_sources([str(alpha), f"beta={beta}"])


def test_parse_sources_names_a_release_folder_after_the_folder_above(tmp_path):
    sources = parse_sources([str(tmp_path / "hair" / "release"), str(tmp_path / "set7"), f"x.y-z={tmp_path}"])
    assert [s.name for s in sources] == ["hair", "set7", "x.y-z"]
    assert sources[2].release == tmp_path


@pytest.mark.parametrize("specs, reason", [
    ([], "no source"),
    (["a=/x", "a=/y"], "two sources named a"),
    (["a b=/x"], "must be letters"),
    (["_a=/x"], "must be letters"),
])
def test_parse_sources_refuses(specs, reason):
    with pytest.raises(ConfigError, match=reason):
        parse_sources(specs)


def test_merge_keeps_a_subject_of_two_releases_in_one_split(two_sources, tmp_path):
    out = tmp_path / "set"
    result = merge_relight_sets(two_sources, out, test=("s1",), log=lambda *_: None)
    table = open_release(out).relight_examples
    assert len(table) == 8 and table["example_id"].is_unique
    assert sorted(table["example_id"])[:2] == ["alpha_A0000_00", "alpha_A0000_01"]
    assert set(table["action_id"]) == {"alpha_A0000", "alpha_A0001", "beta_A0000", "beta_A0001"}
    by_subject = table.groupby("subject")["split"].agg(set).to_dict()
    assert by_subject == {"s0": {"train"}, "s1": {"test"}, "s2": {"train"}}
    assert result.examples == {"train": 4, "validation": 0, "test": 4}
    assert result.subjects["test"] == ["s1"]
    # the list files of the older codes and the record
    assert (out / "relight" / "splits" / "test.txt").read_text().split() == sorted(
        table.loc[table["split"] == "test", "example_id"])
    record = json.loads((out / "merge.json").read_text())
    assert record["subject_from"] == "subject" and record["splits_from"] == "named"
    assert [s["name"] for s in record["sources"]] == ["alpha", "beta"]


def test_merged_files_are_the_sources_files_and_example_json_is_the_row(two_sources, tmp_path):
    out = tmp_path / "set"
    merge_relight_sets(two_sources, out, test=("s1",), log=lambda *_: None)
    table = open_release(out).relight_examples
    row = table[table["example_id"] == "beta_A0001_01"].iloc[0]
    source = open_release(two_sources[1].release).relight_examples
    original = source[source["example_id"] == "A0001_01"].iloc[0]
    for column in FILE_COLUMNS:
        assert row[column].startswith("relight/beta_A0001_01/")
        assert (out / row[column]).read_bytes() == (two_sources[1].release / original[column]).read_bytes()
    example = json.loads((out / "relight" / "beta_A0001_01" / "example.json").read_text())
    assert example["example_id"] == "beta_A0001_01" and example["split"] == row["split"]
    assert example["png_exposure"] == pytest.approx(original["png_exposure"])
    report = verify_release(out)
    assert report.ok, (report.missing, report.mismatched, report.extra)
    # + 3 split lists, merge.json, and the 2 manifest tables against index.json
    assert report.n_checked == 8 * (len(FILE_COLUMNS) + 1) + 3 + 1 + 2


def test_merged_set_loads_with_duckdb_and_the_dataset(two_sources, tmp_path):
    out = tmp_path / "set"
    merge_relight_sets(two_sources, out, subject_from="release", test=("beta",), log=lambda *_: None)
    counts = duckdb.sql(f"SELECT split, count(*) AS n, count(DISTINCT subject) AS s FROM "
                        f"'{out}/manifests/relight_examples.parquet' GROUP BY split ORDER BY split").fetchall()
    assert counts == [("test", 4, 2), ("train", 4, 2)]
    test = RelightDataset(out, "test")
    item = test[0]
    assert item["image"].shape == (3, 16, 16) and bool(item["mask"].any())


def test_subject_from_release_tells_the_sources_subjects_apart(two_sources, tmp_path):
    result = merge_relight_sets(two_sources, tmp_path / "set", subject_from="release",
                                test=("alpha/s1",), validation=("beta",), log=lambda *_: None)
    assert result.subjects == {"train": ["alpha/s0"], "validation": ["beta/s1", "beta/s2"], "test": ["alpha/s1"]}
    assert result.examples == {"train": 2, "validation": 4, "test": 2}


def test_drawn_splits_are_the_relightset_stages_draws(two_sources, tmp_path):
    result = merge_relight_sets(two_sources, tmp_path / "set", subject_from="release", seed=5,
                                split_ratios=(0.5, 0.0, 0.5), log=lambda *_: None)
    expected: dict[str, list[str]] = {"train": [], "validation": [], "test": []}
    for subject in ["alpha/s0", "alpha/s1", "beta/s1", "beta/s2"]:
        expected[split_of(5, subject, (0.5, 0.0, 0.5))].append(subject)
    assert result.subjects == expected
    assert json.loads((tmp_path / "set" / "merge.json").read_text())["splits_from"] == "drawn"


@pytest.mark.parametrize("kwargs, reason", [
    ({"test": ("s9",)}, "no such subject or source"),
    ({"test": ("s1",), "validation": ("s1",)}, "both test and validation"),
    ({"test": ("s0", "s1", "s2")}, "no subject is left for the train split"),
    ({"subject_from": "person"}, "must be 'subject' or 'release'"),
])
def test_bad_splits_are_refused_before_anything_is_written(two_sources, tmp_path, kwargs, reason):
    with pytest.raises(ConfigError, match=reason):
        merge_relight_sets(two_sources, tmp_path / "set", log=lambda *_: None, **kwargs)
    assert list(tmp_path.iterdir()) == []


def test_an_existing_folder_is_replaced_only_when_asked(two_sources, tmp_path):
    out = tmp_path / "set"
    merge_relight_sets(two_sources, out, test=("s1",), log=lambda *_: None)
    with pytest.raises(ConfigError, match="exists"):
        merge_relight_sets(two_sources, out, test=("s2",), log=lambda *_: None)
    merge_relight_sets(two_sources, out, test=("s2",), replace=True, log=lambda *_: None)
    assert set(open_release(out).relight_split("test")["subject"]) == {"s2"}
    assert [p.name for p in tmp_path.iterdir()] == ["set"]


def test_a_missing_source_file_names_it_and_leaves_nothing(tmp_path):
    source = _source(tmp_path / "a", {"s0": "train"}, seed=3)
    (source / "relight" / "A0000_01" / "albedo.exr").unlink()
    with pytest.raises(InputError, match=r"A0000_01/albedo\.exr.*not found"):
        merge_relight_sets(parse_sources([str(source)]), tmp_path / "set", log=lambda *_: None)
    assert not (tmp_path / "set").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["a"]


def test_a_changed_source_file_is_caught_against_its_assets_table(two_sources, tmp_path):
    merged = tmp_path / "merged"
    merge_relight_sets(two_sources, merged, test=("s1",), log=lambda *_: None)  # a source with an assets table
    image = merged / "relight" / "alpha_A0000_00" / "image.png"
    data = bytearray(image.read_bytes())
    image.unlink()  # a hard link to the source's file: change a copy
    data[-20] ^= 0xFF
    image.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"alpha_A0000_00/image\.png.*sha256"):
        merge_relight_sets(parse_sources([f"m={merged}"]), tmp_path / "again", log=lambda *_: None)
    assert not (tmp_path / "again").exists()


def test_a_source_without_a_relighting_set_is_named(tmp_path):
    with pytest.raises(InputError, match="not a release"):
        merge_relight_sets(parse_sources([str(tmp_path / "nothing")]), tmp_path / "set", log=lambda *_: None)


def test_cli_merges_and_reports_errors(two_sources, tmp_path, capsys):
    args = ["merge-sets", str(tmp_path / "set")] + [f"{s.name}={s.release}" for s in two_sources]
    assert main(args + ["--subject-from", "release", "--test", "alpha"]) == 0
    assert "wrote" in capsys.readouterr().out
    table = open_release(tmp_path / "set").relight_examples
    assert set(table.loc[table["split"] == "test", "subject"]) == {"alpha/s0", "alpha/s1"}
    assert main(args + ["--test", "alpha"]) == 2
    assert "exists" in capsys.readouterr().err
    assert main(args + ["--replace", "--test", "nobody"]) == 2
    assert "no such subject or source" in capsys.readouterr().err
    kept = open_release(tmp_path / "set").relight_examples  # the failed replace left the set as it was
    assert set(kept.loc[kept["split"] == "test", "subject"]) == {"alpha/s0", "alpha/s1"}
