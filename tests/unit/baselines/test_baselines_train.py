"""``ultrastage train``: a tiny config beats the trivial baselines; checkpoints resume and are checked."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch
import yaml

from manifests import read_standalone_table
from ultrastage.baselines.config import preset
from ultrastage.baselines.train import CHECKPOINT_NAME, METRICS_NAME, read_checkpoint, train
from ultrastage.cli import main


def _overall(out_dir):
    table = read_standalone_table(out_dir / METRICS_NAME, "baseline_metrics").to_pylist()
    return {(r["method"], r["metric"]): r["value"] for r in table if r["example_id"] == "*"}, table


def test_tiny_albedonet_beats_the_input_image(trained):
    out = trained["albedonet"]
    for name in (CHECKPOINT_NAME, "config.yaml", "loss.png", METRICS_NAME):
        assert (out / name).is_file(), name
    assert yaml.safe_load((out / "config.yaml").read_text())["network"] == "albedonet"
    m, rows = _overall(out)
    assert {r["example_id"] for r in rows} >= {"*", "A0011_00", "A0013_01"}  # per example and over the split
    assert {r["split"] for r in rows} == {"test"}
    # every albedo metric, raw and scale-aligned, beats the linearised photo taken as the albedo
    for metric in ("albedo_psnr_raw_db", "albedo_psnr_scaled_db", "albedo_ssim_raw", "albedo_ssim_scaled"):
        assert m[("albedonet", metric)] > m[("input_image", metric)], metric
    for metric in ("albedo_rmse_raw", "albedo_rmse_scaled"):
        assert m[("albedonet", metric)] < m[("input_image", metric)], metric
    # the margin where the network's work shows most: the shading taken out, up to the unknowable scale
    assert m[("albedonet", "albedo_psnr_scaled_db")] > m[("input_image", "albedo_psnr_scaled_db")] + 1.0
    # no loss-went-down check: an untrained AlbedoNet already is the baseline, and losses of 4 random crops
    # vary more from batch to batch than they fall; the test metrics above are what says it learnt
    losses = read_checkpoint(out / CHECKPOINT_NAME, "albedonet")["losses"]
    assert len(losses) == 120 and all(math.isfinite(x) for x in losses)


def test_tiny_normalnet_beats_the_camera_facing_normal(trained):
    m, _ = _overall(trained["normalnet"])
    assert m[("normalnet", "normal_mean_deg")] < m[("constant_normal", "normal_mean_deg")] - 10.0
    assert m[("normalnet", "normal_median_deg")] < m[("constant_normal", "normal_median_deg")]
    for metric in ("normal_under_11_25_pct", "normal_under_22_5_pct", "normal_under_30_pct"):
        assert m[("normalnet", metric)] > m[("constant_normal", metric)], metric


def test_resume_continues_as_one_run(fake_set, tmp_path):
    config = dataclasses.replace(preset("tiny", "normalnet"), width=4, steps=4, checkpoint_every=2)
    whole = train(fake_set, config, tmp_path / "whole", evaluate_test=False, log=lambda *_: None)
    half = train(fake_set, dataclasses.replace(config, steps=2), tmp_path / "split", evaluate_test=False,
                 log=lambda *_: None)
    assert half.step == 2
    resumed = train(fake_set, config, tmp_path / "split", evaluate_test=False, log=lambda *_: None)
    assert (whole.step, resumed.step, resumed.steps_run) == (4, 4, 2)
    a = read_checkpoint(whole.checkpoint)
    b = read_checkpoint(resumed.checkpoint)
    assert a["losses"] == pytest.approx(b["losses"], rel=1e-5)
    for key, value in a["model"].items():
        torch.testing.assert_close(value, b["model"][key], rtol=1e-5, atol=1e-6)
    again = train(fake_set, config, tmp_path / "split", evaluate_test=False, log=lambda *_: None)
    assert again.steps_run == 0  # already trained to config.steps
    changed = dataclasses.replace(config, lr=1e-2)
    with pytest.raises(ValueError, match="another config.*lr"):
        train(fake_set, changed, tmp_path / "split", evaluate_test=False)


def test_checkpoint_of_the_other_network_or_version_is_refused(trained, tmp_path, fake_set, capsys):
    # the albedonet's checkpoint in a normalnet's folder
    out = tmp_path / "wrong"
    out.mkdir()
    (out / CHECKPOINT_NAME).write_bytes((trained["albedonet"] / CHECKPOINT_NAME).read_bytes())
    assert main(["train", "normalnet", "--set", str(fake_set), "--preset", "tiny", "--out", str(out)]) == 2
    assert "checkpoint of albedonet, not of normalnet" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == [CHECKPOINT_NAME]  # nothing else written
    ckpt = torch.load(out / CHECKPOINT_NAME, weights_only=True)
    ckpt["format_version"] = 99
    torch.save(ckpt, out / CHECKPOINT_NAME)
    assert main(["train", "albedonet", "--set", str(fake_set), "--preset", "tiny", "--out", str(out)]) == 2
    assert "format version 99" in capsys.readouterr().err
    (out / CHECKPOINT_NAME).write_bytes(b"not a checkpoint")
    assert main(["train", "albedonet", "--set", str(fake_set), "--evaluate-only", "--out", str(out)]) == 2
    assert CHECKPOINT_NAME in capsys.readouterr().err


@pytest.mark.parametrize("subjects,message", [
    ({"a": "validation", "b": "test"}, "train split of the relighting set is empty"),
    ({"a": "train", "b": "validation"}, "test split of the relighting set is empty"),
])
def test_empty_splits_exit_2_writing_nothing(tmp_path, make_set, subjects, message, capsys):
    root = make_set(tmp_path / "release", views=1, subjects=subjects)
    out = tmp_path / "out"
    assert main(["train", "albedonet", "--set", str(root), "--preset", "tiny", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and "relight_examples.parquet" in err
    assert not out.exists()


def test_release_without_relighting_set_exits_2(tmp_path, make_set, capsys):
    assert main(["train", "albedonet", "--set", str(tmp_path / "nowhere"), "--preset", "tiny"]) == 2
    assert "nowhere" in capsys.readouterr().err
    root = make_set(tmp_path / "release", views=1, subjects={})  # the index with no rows
    assert main(["train", "albedonet", "--set", str(root), "--preset", "tiny"]) == 2
    assert "no examples" in capsys.readouterr().err
    assert not (tmp_path / "release.baselines").exists()


def test_bad_config_exits_2(tmp_path, fake_set, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("{steps: 3, colour: red}\n")
    assert main(["train", "albedonet", "--set", str(fake_set), "--config", str(cfg), "--out", str(tmp_path / "o")]) == 2
    assert "colour" in capsys.readouterr().err
    assert main(["train", "albedonet", "--set", str(fake_set), "--preset", "huge"]) == 2
