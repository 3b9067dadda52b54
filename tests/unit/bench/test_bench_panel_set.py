"""bench/bench_panel_set.py's helpers: finding the panel's releases, naming an example's subject, summarising a
baseline's metric rows (the run itself is checked in test_bench_quick.py on run_all's quick run)."""
from __future__ import annotations

import pytest

from tests.unit.bench.test_bench_defaults import load_bench


@pytest.fixture(scope="module")
def bench():
    return load_bench("bench_panel_set")


def test_panel_releases_lists_subjects_with_a_relighting_set(bench, tmp_path):
    for name, has_set in (("heavy", True), ("old", True), ("broken", False)):
        manifests = tmp_path / "subjects" / name / "release" / "manifests"
        manifests.mkdir(parents=True)
        if has_set:
            (manifests / "relight_examples.parquet").write_bytes(b"")
    assert bench.panel_releases(tmp_path) == {"heavy": tmp_path / "subjects" / "heavy" / "release",
                                              "old": tmp_path / "subjects" / "old" / "release"}
    assert bench.panel_releases(tmp_path / "nothing") == {}


def test_subject_of_takes_the_longest_source_prefix(bench):
    sources = ["ict", "ict_face", "old"]
    assert bench.subject_of("ict_face_A0000_01", sources) == "ict_face"
    assert bench.subject_of("ict_A0000_01", sources) == "ict"
    assert bench.subject_of("old_A0001_00", sources) == "old"
    assert bench.subject_of("zzz_A0000_00", sources) == "zzz_A0000_00"


def test_summarise_averages_per_subject_and_keeps_the_split_wide_rows(bench):
    def row(method, example_id, metric, value):
        return {"network": "albedonet", "method": method, "split": "test", "example_id": example_id,
                "metric": metric, "value": value, "step": 0}

    rows = [row("albedonet", "old_A0000_00", "albedo_psnr_raw_db", 20.0),
            row("albedonet", "old_A0000_01", "albedo_psnr_raw_db", 24.0),
            row("albedonet", "heavy_A0000_00", "albedo_psnr_raw_db", 30.0),
            row("albedonet", "heavy_A0000_00", "albedo_ssim_raw", 0.9),
            row("input_image", "old_A0000_00", "albedo_psnr_raw_db", 15.0),
            row("albedonet", "*", "albedo_psnr_raw_db", 24.5),
            row("input_image", "*", "albedo_psnr_raw_db", 15.0)]
    summary = bench.summarise(rows, "albedonet", ["old", "heavy"])
    assert summary["overall"] == {"albedonet": {"albedo_psnr_raw_db": 24.5}, "input_image": {"albedo_psnr_raw_db": 15.0}}
    assert summary["per_subject"] == {"albedonet": {"old": 22.0, "heavy": 30.0}, "input_image": {"old": 15.0}}
