"""Single-image baselines over the release's relighting set (the paper's section 5): AlbedoNet and NormalNet.

- :mod:`.config`: :class:`TrainConfig` and its presets ('tiny', 'cpu', 'gpu').
- :mod:`.models`: the U-Nets (photo -> linear albedo; photo -> camera-frame unit normals).
- :mod:`.data`: :class:`RelightDataset`, a PyTorch ``Dataset`` over ``relight_examples`` (importable by users).
- :mod:`.metrics`: albedo PSNR / SSIM / RMSE raw and least-squares scaled, normal angle statistics, and the
  trivial baselines (the linearised photo as albedo, a camera-facing normal).
- :mod:`.train`: ``ultrastage train albedonet|normalnet`` (checkpoint, resume, test metrics).
- :mod:`.predict`: ``ultrastage predict`` (maps of any photos, diffuse relighting under an HDR map).
"""
from .config import NETWORKS, PRESETS, TrainConfig
from .data import RelightDataset

__all__ = ["NETWORKS", "PRESETS", "RelightDataset", "TrainConfig"]
