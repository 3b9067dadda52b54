"""The relighting set's PyTorch Dataset and transforms (ultrastage.baselines.data) on the fake set."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.errors import InputError
from ultrastage.baselines.data import RelightDataset, flip_horizontal, random_crop
from ultrastage.baselines.metrics import input_image_albedo
from ultrastage.baselines.models import AlbedoNet, NormalNet, predict_image


def test_dataset_reads_the_split_masked(fake_set):
    ds = RelightDataset(fake_set, "train")
    assert len(ds) == 20 and all(i.startswith("A00") for i in ds.example_ids)
    item = ds[0]
    assert set(item) == {"image", "albedo", "normal", "mask", "example_id"}
    assert item["image"].shape == (3, 64, 64) and item["mask"].shape == (1, 64, 64)
    off = item["mask"][0] == 0
    assert torch.all(item["image"][:, off] == 0) and torch.all(item["normal"][:, off] == 0)
    on = ~off
    assert 0.2 < float(item["image"][:, on].max()) <= 1.0  # the sRGB PNG in [0, 1]
    norms = item["normal"][:, on].norm(dim=0)
    assert torch.allclose(norms, torch.ones_like(norms), atol=1e-3)
    assert float(item["normal"][2, on].mean()) < -0.5  # camera-facing: negative z (OpenCV)
    assert len(RelightDataset(fake_set, "test")) == 6


def test_crop_keeps_subject_and_flip_negates_x(fake_set):
    ds = RelightDataset(fake_set, "train", crop=32, flip=True)
    rng = np.random.default_rng(0)
    for _ in range(5):
        item = ds.example(3, rng)
        assert item["image"].shape == (3, 32, 32) and item["mask"].sum() > 0
    arrays = ds.arrays(0)
    flipped = flip_horizontal(arrays)
    np.testing.assert_array_equal(flipped["image"], arrays["image"][:, ::-1])
    np.testing.assert_array_equal(flipped["normal"][..., 0], -arrays["normal"][:, ::-1, 0])
    np.testing.assert_array_equal(flipped["normal"][..., 1:], arrays["normal"][:, ::-1, 1:])
    padded = random_crop(arrays, 80, rng)  # bigger than the image: zero-padded
    assert padded["image"].shape == (80, 80, 3) and padded["mask"].sum() == arrays["mask"].sum()


def test_networks_take_any_size_and_give_their_ranges():
    torch.manual_seed(0)
    image = np.random.default_rng(0).uniform(size=(37, 51, 3)).astype(np.float32)
    albedo = predict_image(AlbedoNet(width=4, depth=3), image)
    normal = predict_image(NormalNet(width=4, depth=3), image)
    assert albedo.shape == normal.shape == (37, 51, 3)
    assert albedo.min() >= 0 and albedo.max() <= 1
    # untrained, the AlbedoNet's shading correction is 0: it is the input-image baseline
    np.testing.assert_allclose(albedo, input_image_albedo(image), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=-1), 1.0, atol=1e-4)
    with pytest.raises(ValueError):
        AlbedoNet(width=4, depth=3)(torch.zeros(1, 3, 30, 30))


def test_missing_set_and_empty_split_are_input_errors(tmp_path, make_set):
    root = make_set(tmp_path / "release", views=1, subjects={"a": "train", "b": "validation"})
    with pytest.raises(InputError, match="test split of the relighting set is empty"):
        RelightDataset(root, "test")
    (root / "manifests" / "relight_examples.parquet").unlink()
    (root / "manifests" / "actions.parquet").write_bytes(b"")  # a release, but no relighting set
    with pytest.raises(InputError, match="no relighting set"):
        RelightDataset(root, "train")
