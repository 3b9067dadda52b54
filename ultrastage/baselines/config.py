"""Training configuration of the single-image baselines: a typed frozen dataclass and its presets."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar, Literal

from pipeline.config import Documented, broken, checked
from pipeline.errors import ConfigError

NETWORKS = ("albedonet", "normalnet")
"""The baselines: AlbedoNet (photo -> linear albedo) and NormalNet (photo -> camera-frame normals)."""


@dataclass(frozen=True)
class TrainConfig(Documented):
    """How a baseline U-Net is built and trained (MSE on the masked pixels, Adam)."""

    network: Literal["albedonet", "normalnet"] = "albedonet"
    """Which baseline: 'albedonet' or 'normalnet' (the command line's positional argument sets it)."""
    width: int = checked(32, ge=1)
    """Channels of the U-Net's first level; each level down doubles them."""
    depth: int = checked(4, ge=1)
    """Levels of the U-Net (poolings = depth - 1); inputs are padded to a multiple of 2^(depth - 1)."""
    crop: int = checked(256, ge=8)
    """Side of the square random crop of each training example, pixels (images smaller than it are
    zero-padded, the padding outside the mask)."""
    batch_size: int = checked(8, ge=1)
    """Examples per step."""
    steps: int = checked(20000, ge=1)
    """Optimiser steps in all (a resumed run trains up to this count)."""
    lr: float = checked(1e-4, gt=0.0)
    """Adam learning rate (the paper: 1e-5 for 24 h on an A6000)."""
    flip: bool = True
    """Random horizontal flips (the normal's x negated)."""
    seed: int = checked(0, ge=0)
    """Seed of the initial weights and of every step's examples, crops and flips (step s draws from
    (seed, s), so a resumed run sees what an uninterrupted one would)."""
    device: str = checked("auto", one_of=("auto", "cpu", "cuda"))
    """'auto' (CUDA when torch sees it, else CPU), 'cpu' or 'cuda'."""
    checkpoint_every: int = checked(500, ge=1)
    """Steps between checkpoints (one is always written at the end)."""
    eval_every: int = checked(0, ge=0)
    """Steps between evaluations on the validation split printed during training (0: never)."""
    cache_examples: bool = True
    """Keep the decoded training examples in memory (a 1,500-example set at 512 x 512 is ~9 GB as float32:
    turn it off for big sets)."""
    threads: int = checked(0, ge=0)
    """CPU threads of torch (0: torch's default)."""

    not_in_key: ClassVar[tuple[str, ...]] = ("steps", "device", "checkpoint_every", "eval_every",
                                             "cache_examples", "threads")
    """Fields a checkpoint may be resumed with different values of (they do not change what a step does)."""

    def _checks(self) -> list[str]:
        if self.depth >= 1 and self.crop % (2 ** (self.depth - 1)):
            return [broken(self, "crop", f"must be a multiple of 2^(depth - 1) = {2 ** (self.depth - 1)}")]
        return []


PRESETS: dict[str, TrainConfig] = {
    # seconds on a CPU: the tests' config (a 64 x 64 fixture set)
    "tiny": TrainConfig(width=8, depth=3, crop=32, batch_size=4, steps=120, lr=3e-3, checkpoint_every=30),
    # a few minutes to an hour on a 2-core CPU: small crops, small net
    "cpu": TrainConfig(width=16, depth=4, crop=128, batch_size=4, steps=2000, lr=1e-3, checkpoint_every=200),
    # the paper-sized run on one GPU
    "gpu": TrainConfig(width=64, depth=5, crop=512, batch_size=8, steps=100000, lr=1e-4, checkpoint_every=2000),
}
"""Presets by name; ``ultrastage train --preset NAME`` starts from one (default 'cpu')."""


def preset(name: str, network: str) -> TrainConfig:
    """The preset ``name`` for ``network``.

    Raises:
        ConfigError: an unknown preset or network.
    """
    if name not in PRESETS:
        raise ConfigError(f"--preset {name}: unknown preset; presets are {sorted(PRESETS)}")
    return dataclasses.replace(PRESETS[name], network=network)
