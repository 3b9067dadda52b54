"""A PyTorch ``Dataset`` over the single-image relighting set's Parquet index (``relight_examples``).

    from ultrastage.baselines.data import RelightDataset
    train = RelightDataset("runs/default/release", "train", crop=256, flip=True, seed=0)
    item = train[0]   # image (3, 256, 256) sRGB [0, 1] masked, albedo (3, ...) linear, normal (3, ...), mask (1, ...)
    loader = torch.utils.data.DataLoader(train, batch_size=8, shuffle=True)

The input is the 8-bit sRGB PNG of each example (``image_png``, tone-mapped as in-the-wild photos are) in
[0, 1], multiplied by the mask (0 off the subject). Targets are the linear albedo (``albedo_exr``, clipped to
[0, 1]) and the camera-frame normals (``normal_exr``, OpenCV axes: x right, y down, z forward; camera-facing
normals have negative z; 0 off the mask). Transforms: a random square crop around a random pixel of the
subject (zero-padded when the image is smaller) and a horizontal flip, which mirrors the image and negates
the normal's x.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch

from manifests.consumer import Release, ReleaseError, open_release
from manifests.writer import manifest_path
from pipeline.errors import InputError

__all__ = ["RelightDataset", "open_relight_set", "load_example", "random_crop", "flip_horizontal",
           "to_tensors"]


def open_relight_set(release: str | Path | Release, splits: tuple[str, ...] = ()) -> Release:
    """The release, checked to hold a non-empty relighting set with examples in each of ``splits``.

    Raises:
        InputError: not a release, no ``relight_examples`` manifest, no examples, or an empty split (naming
            the manifest file).
    """
    if not isinstance(release, Release):
        try:
            release = open_release(release)
        except ReleaseError as error:
            raise InputError(release, f"not a release: {error}") from None
    index = manifest_path(release.root, "relight_examples")
    if not release.has_table("relight_examples"):
        raise InputError(index, "no relighting set in this release (the relightset stage writes it)")
    examples = release.relight_examples
    if examples.empty:
        raise InputError(index, "the relighting set has no examples (no published actions?)")
    for split in splits:
        if not (examples["split"] == split).any():
            raise InputError(index, f"the {split} split of the relighting set is empty "
                                    f"(splits present: {sorted(set(examples['split']))})")
    return release


def load_example(release: Release, row: pd.Series | dict) -> dict[str, np.ndarray]:
    """One example's arrays: ``image`` (H, W, 3) float32 sRGB in [0, 1] (the PNG, masked), ``albedo``
    (H, W, 3) float32 linear in [0, 1], ``normal`` (H, W, 3) float32 camera frame, ``mask`` (H, W) bool.

    Raises:
        InputError: a missing or unreadable file, or maps of different sizes (naming the file).
    """
    from pipeline.codecs.exr import read_exr
    from pipeline.codecs.image import mask_from_png, read_png

    def read(column: str, reader):
        path = release.root / row[column]
        if not path.is_file():
            raise InputError(path, f"file of example {row['example_id']} ({column}) not found")
        try:
            return np.asarray(reader(path))
        except Exception as error:  # codecs raise plain library errors for corrupt files
            raise InputError(path, f"cannot read {column}: {error}") from error

    image = read("image_png", read_png)
    mask = read("mask_png", read_png)
    albedo = read("albedo_exr", read_exr)
    normal = read("normal_exr", read_exr)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    mask = mask_from_png(mask)
    h, w = mask.shape
    for column, arr in (("image_png", image), ("albedo_exr", albedo), ("normal_exr", normal)):
        if arr.shape[:2] != (h, w) or arr.ndim != 3 or arr.shape[2] < 3:
            raise InputError(release.root / row[column], f"shape {arr.shape} does not match the mask's {h} x {w} "
                             "(expected (H, W, 3+))")
    scale = 65535.0 if image.dtype == np.uint16 else 255.0
    image = image[..., :3].astype(np.float32) / scale * mask[..., None]
    albedo = np.clip(np.nan_to_num(albedo[..., :3], nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0) * mask[..., None]
    normal = np.nan_to_num(normal[..., :3], nan=0.0, posinf=0.0, neginf=0.0) * mask[..., None]
    return {"image": image.astype(np.float32), "albedo": albedo.astype(np.float32),
            "normal": normal.astype(np.float32), "mask": mask}


def random_crop(arrays: dict[str, np.ndarray], crop: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A ``crop`` x ``crop`` window of every (H, W, ...) array, containing a pixel of ``arrays['mask']`` drawn
    at random (anywhere when the mask is empty); images smaller than the crop are zero-padded first."""
    mask = arrays["mask"]
    h, w = mask.shape
    ph, pw = max(crop - h, 0), max(crop - w, 0)
    if ph or pw:
        arrays = {k: np.pad(v, [(0, ph), (0, pw)] + [(0, 0)] * (v.ndim - 2)) for k, v in arrays.items()}
        mask = arrays["mask"]
        h, w = mask.shape
    ys, xs = np.nonzero(mask)
    if len(ys):
        k = int(rng.integers(len(ys)))
        cy, cx = int(ys[k]), int(xs[k])
    else:
        cy, cx = int(rng.integers(h)), int(rng.integers(w))
    # offsets that keep the drawn pixel inside the window and the window inside the image
    y0 = int(rng.integers(max(0, cy - crop + 1), min(cy, h - crop) + 1))
    x0 = int(rng.integers(max(0, cx - crop + 1), min(cx, w - crop) + 1))
    return {k: v[y0:y0 + crop, x0:x0 + crop] for k, v in arrays.items()}


def flip_horizontal(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Mirror every (H, W, ...) array left-right; the normals' x is negated (x points right)."""
    out = {k: v[:, ::-1] for k, v in arrays.items()}
    if "normal" in out:
        out["normal"] = out["normal"] * np.array([-1.0, 1.0, 1.0], np.float32)
    return out


def to_tensors(arrays: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """(H, W, C) / (H, W) arrays -> contiguous float32 (C, H, W) / (1, H, W) tensors."""
    out = {}
    for k, v in arrays.items():
        v = np.ascontiguousarray(v, dtype=np.float32)
        out[k] = torch.from_numpy(v[None] if v.ndim == 2 else v.transpose(2, 0, 1).copy())
    return out


class RelightDataset(torch.utils.data.Dataset):
    """The examples of one split of a release's relighting set.

    Items are dicts of tensors ``image``, ``albedo``, ``normal`` (3, h, w), ``mask`` (1, h, w) (module
    docstring) and ``example_id`` (str); ``h = w = crop`` when cropping, else the example's size.
    """

    def __init__(self, release: str | Path | Release, split: str, crop: int | None = None, flip: bool = False,
                 seed: int | None = None, cache: bool = False):
        """
        Args:
            release: a release folder (or an opened :class:`manifests.Release`) with a relighting set.
            split: 'train', 'validation' or 'test'.
            crop: side of the random square crop (None: whole images).
            flip: random horizontal flips.
            seed: seed of the crops and flips of ``dataset[i]`` (None: fresh entropy).
            cache: keep decoded examples in memory.

        Raises:
            InputError: see :func:`open_relight_set` (the split must not be empty).
        """
        self.release = open_relight_set(release, (split,))
        self.split = split
        self.rows = self.release.relight_split(split)
        self.crop = crop
        self.flip = flip
        self.cache = cache
        self._cached: dict[int, dict[str, np.ndarray]] = {}
        self._rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def example_ids(self) -> list[str]:
        """Example ids in index order."""
        return list(self.rows["example_id"])

    def arrays(self, index: int) -> dict[str, np.ndarray]:
        """The untransformed arrays of example ``index`` (:func:`load_example`)."""
        if index in self._cached:
            return self._cached[index]
        arrays = load_example(self.release, self.rows.iloc[index])
        if self.cache:
            self._cached[index] = arrays
        return arrays

    def example(self, index: int, rng: np.random.Generator | None = None) -> dict:
        """Example ``index`` transformed with draws from ``rng`` (the dataset's own generator when None)."""
        rng = self._rng if rng is None else rng
        arrays = self.arrays(index)
        if self.crop is not None:
            arrays = random_crop(arrays, self.crop, rng)
        if self.flip and rng.random() < 0.5:
            arrays = flip_horizontal(arrays)
        item = to_tensors(arrays)
        item["example_id"] = str(self.rows.iloc[index]["example_id"])
        return item

    def __getitem__(self, index: int) -> dict:
        return self.example(index)
