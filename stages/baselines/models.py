"""The baselines' networks: a plain U-Net (Ronneberger et al. 2015) with two heads.

* :class:`AlbedoNet`: sRGB photo (B, 3, H, W) in [0, 1] -> linear albedo (B, 3, H, W) in (0, 1) (sigmoid).
* :class:`NormalNet`: the same photo -> unit normals (B, 3, H, W) in the camera frame (OpenCV axes: x right,
  y down, z forward, so normals facing the camera have negative z).

H and W must be multiples of :func:`size_multiple` (``2^(depth - 1)``); :func:`pad_to_multiple` pads.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .config import TrainConfig

__all__ = ["UNet", "AlbedoNet", "NormalNet", "build_network", "size_multiple", "pad_to_multiple", "predict_image"]


def _block(c_in: int, c_out: int) -> nn.Sequential:
    # GroupNorm, not BatchNorm: the batches are small (4-8 crops) and prediction runs one photo at a time
    groups = 4 if c_out % 4 == 0 else 1
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, padding=1), nn.GroupNorm(groups, c_out), nn.ReLU(inplace=True),
        nn.Conv2d(c_out, c_out, 3, padding=1), nn.GroupNorm(groups, c_out), nn.ReLU(inplace=True))


class UNet(nn.Module):
    """U-Net: ``depth`` levels of two 3x3 conv blocks, max-pool down, bilinear up + skip concatenation, a 1x1
    convolution to ``out_channels`` raw outputs (B, out_channels, H, W)."""

    def __init__(self, in_channels: int = 3, out_channels: int = 3, width: int = 32, depth: int = 4):
        super().__init__()
        if depth < 1 or width < 1:
            raise ValueError(f"U-Net needs depth >= 1 and width >= 1, got depth {depth}, width {width}")
        self.depth = depth
        chans = [width * 2**i for i in range(depth)]
        self.down = nn.ModuleList([_block(in_channels, chans[0])] +
                                  [_block(chans[i - 1], chans[i]) for i in range(1, depth)])
        self.up = nn.ModuleList([_block(chans[i] + chans[i - 1], chans[i - 1]) for i in range(depth - 1, 0, -1)])
        self.head = nn.Conv2d(chans[0], out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        m = size_multiple(self.depth)
        if x.ndim != 4 or x.shape[2] % m or x.shape[3] % m:
            raise ValueError(f"U-Net input must be (B, C, H, W) with H, W multiples of {m}, got {tuple(x.shape)}")
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        for block, skip in zip(self.up, reversed(skips[:-1])):
            x = F.interpolate(x, size=skip.shape[2:], mode="bilinear", align_corners=False)
            x = block(torch.cat([x, skip], dim=1))
        return self.head(x)


class AlbedoNet(UNet):
    """Photo (B, 3, H, W) sRGB [0, 1] -> linear albedo (B, 3, H, W) in (0, 1)."""

    name = "albedonet"

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(super().forward(x))


class NormalNet(UNet):
    """Photo (B, 3, H, W) sRGB [0, 1] -> unit camera-frame normals (B, 3, H, W) (OpenCV axes)."""

    name = "normalnet"

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        raw = super().forward(x)
        # a zero output would have no direction: normalise with an eps; its gradient stays finite
        return F.normalize(raw, dim=1, eps=1e-6)


def build_network(config: TrainConfig) -> UNet:
    """The network of ``config.network`` with the config's width and depth (fresh weights)."""
    cls = {"albedonet": AlbedoNet, "normalnet": NormalNet}[config.network]
    return cls(3, 3, width=config.width, depth=config.depth)


def size_multiple(depth: int) -> int:
    """What H and W of a U-Net of ``depth`` levels must be a multiple of: 2^(depth - 1)."""
    return 2 ** (depth - 1)


def pad_to_multiple(x: torch.Tensor, multiple: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """Zero-pad (B, C, H, W) at the bottom and right to multiples of ``multiple``; returns the padded
    tensor and the original (H, W) to crop the prediction back to."""
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    return (F.pad(x, (0, pw, 0, ph)) if ph or pw else x), (h, w)


def predict_image(model: UNet, image: np.ndarray, device: torch.device | str = "cpu") -> np.ndarray:
    """The network's output (H, W, 3) float32 for one photo (H, W, 3) sRGB in [0, 1] of any size (zero-padded
    at the bottom and right to the U-Net's multiple, the prediction cropped back); no gradients."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"photo must be (H, W, 3), got shape {image.shape}")
    x = torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1)))[None].to(device)
    x, (h, w) = pad_to_multiple(x, size_multiple(model.depth))
    was_training = model.training
    model.eval()
    with torch.no_grad():
        out = model(x)[0, :, :h, :w]
    model.train(was_training)
    return np.ascontiguousarray(out.permute(1, 2, 0).cpu().numpy(), dtype=np.float32)
