"""Training configuration of the single-image baselines: a typed frozen dataclass and its presets."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar, Literal

from pipeline.errors import ConfigError

NETWORKS = ("albedonet", "normalnet")
"""The baselines: AlbedoNet (photo -> linear albedo) and NormalNet (photo -> camera-frame normals)."""


@dataclass(frozen=True)
class TrainConfig:
    """How a baseline U-Net is built and trained (MSE on the masked pixels, Adam)."""

    network: Literal["albedonet", "normalnet"] = "albedonet"
    """Which baseline: 'albedonet' or 'normalnet' (the command line's positional argument sets it)."""
    width: int = 32
    """Channels of the U-Net's first level; each level down doubles them."""
    depth: int = 4
    """Levels of the U-Net (poolings = depth - 1); inputs are padded to a multiple of 2^(depth - 1)."""
    crop: int = 256
    """Side of the square random crop of each training example, pixels (images smaller than it are
    zero-padded, the padding outside the mask)."""
    batch_size: int = 8
    """Examples per step."""
    steps: int = 20000
    """Optimiser steps in all (a resumed run trains up to this count)."""
    lr: float = 1e-4
    """Adam learning rate (the paper: 1e-5 for 24 h on an A6000)."""
    flip: bool = True
    """Random horizontal flips (the normal's x negated)."""
    seed: int = 0
    """Seed of the initial weights and of every step's examples, crops and flips (step s draws from
    (seed, s), so a resumed run sees what an uninterrupted one would)."""
    device: str = "auto"
    """'auto' (CUDA when torch sees it, else CPU), 'cpu' or 'cuda'."""
    checkpoint_every: int = 500
    """Steps between checkpoints (one is always written at the end)."""
    eval_every: int = 0
    """Steps between evaluations on the validation split printed during training (0: never)."""
    cache_examples: bool = True
    """Keep the decoded training examples in memory (a 1,500-example set at 512 x 512 is ~9 GB as float32:
    turn it off for big sets)."""
    threads: int = 0
    """CPU threads of torch (0: torch's default)."""

    not_in_key: ClassVar[tuple[str, ...]] = ("steps", "device", "checkpoint_every", "eval_every",
                                             "cache_examples", "threads")
    """Fields a checkpoint may be resumed with different values of (they do not change what a step does)."""

    def __post_init__(self) -> None:
        if self.network not in NETWORKS:
            raise ConfigError(f"network {self.network!r}: expected one of {list(NETWORKS)}")
        for name, low in (("width", 1), ("depth", 1), ("crop", 8), ("batch_size", 1), ("steps", 1),
                          ("checkpoint_every", 1), ("eval_every", 0), ("threads", 0), ("seed", 0)):
            if getattr(self, name) < low:
                raise ConfigError(f"{name} = {getattr(self, name)}: must be at least {low}")
        if not self.lr > 0:
            raise ConfigError(f"lr = {self.lr}: must be positive")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"device {self.device!r}: expected 'auto', 'cpu' or 'cuda'")
        if self.crop % (2 ** (self.depth - 1)):
            raise ConfigError(f"crop {self.crop} is not a multiple of 2^(depth - 1) = {2 ** (self.depth - 1)}")


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
