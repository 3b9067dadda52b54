"""The baselines' networks: a plain U-Net (Ronneberger et al. 2015) with two heads.

* :class:`AlbedoNet`: sRGB photo (B, 3, H, W) in [0, 1] -> linear albedo (B, 3, H, W) in [0, 1], predicted as
  the linearised photo times a learned shading correction (untrained, it IS the input-image baseline).
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

__all__ = ["UNet", "AlbedoNet", "NormalNet", "build_network", "size_multiple", "pad_to_multiple", "predict_image",
           "srgb_to_linear"]


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

    def features(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The last level's features (B, width, H, W) and the bottleneck's (B, width 2^(depth-1), H', W')."""
        m = size_multiple(self.depth)
        if x.ndim != 4 or x.shape[2] % m or x.shape[3] % m:
            raise ValueError(f"U-Net input must be (B, C, H, W) with H, W multiples of {m}, got {tuple(x.shape)}")
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        bottleneck = x
        for block, skip in zip(self.up, reversed(skips[:-1])):
            x = F.interpolate(x, size=skip.shape[2:], mode="bilinear", align_corners=False)
            x = block(torch.cat([x, skip], dim=1))
        return x, bottleneck

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x)[0])

    def training_output(self, x: torch.Tensor) -> torch.Tensor:
        """What the training loss compares with the target (B, 3, H, W): :meth:`forward`'s output here."""
        return self(x)


class AlbedoNet(UNet):
    """Photo (B, 3, H, W) sRGB [0, 1] -> linear albedo (B, 3, H, W) in [0, 1]:
    ``clip(srgb_to_linear(photo) * exp(c + g), 0, 1)``.

    A shaded photo is albedo x shading, so the network predicts a log shading correction rather than the
    albedo itself: ``c`` (B, 3, H, W) per pixel from the U-Net's head and ``g`` (B, 3, 1, 1) per image, a
    linear layer on the mean of the bottleneck's features over the cells that hold the subject (a global
    gain: the photo's exposure normalisation hides the albedo's absolute level, and the light's colour is a
    property of the whole image). The photo is 0 off the subject, so the mean over the subject's cells alone
    does not change with the canvas around it: a training crop and a whole photo give it alike. Both layers
    start at zero, so an untrained AlbedoNet is exactly the input-image baseline and training learns what to
    take out of it.
    ``c + g`` is bounded to +-:attr:`max_log_correction` by a tanh (slope 1 at 0) so ``exp`` cannot overflow.
    """

    name = "albedonet"
    max_log_correction = 6.0
    """Bound of the log correction: the albedo lies between 1/400 and 400 (e^6) times the linearised photo."""

    def __init__(self, in_channels: int = 3, out_channels: int = 3, width: int = 32, depth: int = 4):
        super().__init__(in_channels, out_channels, width, depth)
        if in_channels != 3 or out_channels != 3:
            raise ValueError(f"AlbedoNet maps an RGB photo to RGB albedo, got {in_channels} -> {out_channels}")
        self.gain = nn.Linear(width * 2 ** (depth - 1), 3)
        for layer in (self.head, self.gain):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def log_correction(self, x: torch.Tensor) -> torch.Tensor:
        """``c + g`` (B, 3, H, W), bounded, for photos x (B, 3, H, W)."""
        last, bottleneck = self.features(x)
        subject = (x.amax(dim=1, keepdim=True) > 0).to(x.dtype)
        cells = F.max_pool2d(subject, size_multiple(self.depth))  # (B, 1, H', W'): 1 where a cell holds subject
        pooled = (bottleneck * cells).sum(dim=(2, 3)) / cells.sum(dim=(2, 3)).clamp(min=1.0)
        raw = self.head(last) + self.gain(pooled)[:, :, None, None]
        bound = self.max_log_correction
        return bound * torch.tanh(raw / bound)

    def training_output(self, x: torch.Tensor) -> torch.Tensor:
        """The albedo before clipping (B, 3, H, W), >= 0: the loss sees it so that a prediction above 1 still
        has a gradient (the clip's is 0 there); its squared error bounds the clipped one's (targets are in
        [0, 1])."""
        return srgb_to_linear(x) * torch.exp(self.log_correction(x))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.training_output(x).clamp(0.0, 1.0)


class NormalNet(UNet):
    """Photo (B, 3, H, W) sRGB [0, 1] -> unit camera-frame normals (B, 3, H, W) (OpenCV axes)."""

    name = "normalnet"

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        raw = self.head(self.features(x)[0])
        # a zero output would have no direction: normalise with an eps; its gradient stays finite
        return F.normalize(raw, dim=1, eps=1e-6)


def build_network(config: TrainConfig) -> UNet:
    """The network of ``config.network`` with the config's width and depth (fresh weights)."""
    cls = {"albedonet": AlbedoNet, "normalnet": NormalNet}[config.network]
    return cls(3, 3, width=config.width, depth=config.depth)


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """The sRGB curve undone on a tensor of values in [0, 1] (clipped first), as
    :func:`pipeline.codecs.image.srgb_decode` does on arrays: the input-image baseline's albedo."""
    x = x.clamp(0.0, 1.0)
    # the power's base stays >= 0.055 / 1.055 on both branches of the where: no NaN gradient at 0
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


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
