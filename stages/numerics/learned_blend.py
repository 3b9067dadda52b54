"""A learned blend of reprojected source views (the paper's blending network, in small).

The heuristic blend of :func:`stages.numerics.gbuffer.reproject_gbuffer` weighs each of the ``k`` nearest
sources by a fixed formula of viewing angle, sampling density, visibility and grazing. This module learns
per-pixel corrections to those weights from the captured views themselves, leave one out: every captured
view is, in turn, the target synthesised from the others and compared with its own photometric maps. No
held-out view is ever a target or a source of the training (the caller passes the views it may use).

Per pixel and source the network (a 3-layer MLP shared by all sources, ``LearnedBlendConfig``) sees

- the source's soft visibility, the angle between the rays to the target and to the source, the log ratio
  of their sampling densities, the cosines of the sampled normal with the rays to the source and to the
  target (the terms of the heuristic);
- the log of the heuristic's normalised weight;
- how far the source's albedo and normal lie from the heuristic blend (a source that disagrees with the
  others sees something else: an occluder the depth test missed, a misregistered edge, a highlight).

Its output is added to the log of the heuristic weight and a softmax over the visible sources gives the
weights, so an untrained network (output 0) is the heuristic blend. Loss: L1 on the albedo plus
``_NORMAL_WEIGHT`` times (1 - cos) on the normal, over valid target pixels.

Pure numerics (torch, CPU or CUDA); arrays in, arrays out. No output holds NaN or Inf.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import torch

from pipeline.config import Documented, checked
from stages.numerics.gbuffer import SourceView, source_candidates

__all__ = ["LearnedBlendConfig", "LearnedBlend", "BlendNet", "candidate_features", "fit_learned_blend"]

FEATURES = 8  # visibility, theta, log density, cos source, cos target, log prior weight, albedo and normal deviation
_CANDIDATE_KEYS = ("visibility", "theta", "log_density", "cos_source", "cos_target", "weight", "albedo", "normal")
_NORMAL_WEIGHT = 0.5
"""Weight of the loss's normal term ``1 - cos`` against the albedo's L1 (a fixed balance, not a setting: nothing
tunes it)."""


@dataclass(frozen=True)
class LearnedBlendConfig(Documented):
    """Leave-one-out training of the blend network on one action's captured views."""

    enabled: bool = False
    """Blend with the learned weights (else the heuristic ``angle_distance_grazing`` weights). Off by default:
    on the default capture it reproduces the held-out photometric maps slightly better (table 1's protocol)
    and the simulator's truth (albedo, eq. 1's normals, relit novel views) worse. It learns the
    view-dependent residue that neighbouring photometric maps share (eq. 1's specular tilt, highlights),
    which the truth does not hold. bench/bench_gbuffer.py reports its held-out metrics beside the heuristic
    weights' and its fit time (tens of seconds for 30 views of 320 x 480 on 2 cores)."""
    hidden_width: int = checked(32, ge=1)
    """Width of the MLP's two hidden layers."""
    steps: int = checked(400, ge=1)
    """Adam steps."""
    batch_pixels: int = checked(8192, ge=1)
    """Target pixels per step (drawn from every training view's pixels)."""
    pixels_per_view: int = checked(20000, ge=1)
    """At most this many pixels of each training view are kept (a random subset): bounds memory and the time
    of gathering at full resolution."""
    learning_rate: float = checked(3e-3, gt=0.0)
    """Adam learning rate."""
    seed: int = 0
    """Seed of the pixel subsets, the batches and the initial weights."""


def candidate_features(cand: dict[str, Any]) -> dict[str, torch.Tensor]:
    """Network inputs from :func:`stages.numerics.gbuffer.source_candidates` arrays (numpy or torch).

    Returns ``features`` (N, k, 8), ``prior`` (N, k) the heuristic weights normalised over the sources,
    ``albedo`` (N, k, 3), ``normal`` (N, k, 3) and ``visible`` (N, k) bool, float32 tensors.
    """
    t = {key: torch.as_tensor(np.asarray(cand[key]), dtype=torch.float32) for key in _CANDIDATE_KEYS}
    weight = torch.nan_to_num(t["weight"]).clamp_min(0.0)
    prior = weight / weight.sum(1, keepdim=True).clamp_min(1e-12)
    albedo, normal = torch.nan_to_num(t["albedo"]), torch.nan_to_num(t["normal"])
    blend_a = (prior.unsqueeze(-1) * albedo).sum(1, keepdim=True)
    blend_n = torch.nn.functional.normalize((prior.unsqueeze(-1) * normal).sum(1, keepdim=True), dim=-1, eps=1e-9)
    dev_a = (albedo - blend_a).abs().mean(-1)
    dev_n = 1.0 - (torch.nn.functional.normalize(normal, dim=-1, eps=1e-9) * blend_n).sum(-1)
    features = torch.stack([t["visibility"], t["theta"], t["log_density"].clamp(-5.0, 5.0), t["cos_source"],
                            t["cos_target"], torch.log(prior.clamp_min(1e-6)), 10.0 * dev_a, 10.0 * dev_n], -1)
    return {"features": torch.nan_to_num(features), "prior": prior, "albedo": albedo, "normal": normal,
            "visible": weight > 0}


class BlendNet(torch.nn.Module):
    """Per-source logit corrections (an MLP shared by the sources) on top of the heuristic's log weights."""

    def __init__(self, hidden_width: int = 32) -> None:
        super().__init__()
        self.mlp = torch.nn.Sequential(torch.nn.Linear(FEATURES, hidden_width), torch.nn.ReLU(),
                                       torch.nn.Linear(hidden_width, hidden_width), torch.nn.ReLU(),
                                       torch.nn.Linear(hidden_width, 1))
        torch.nn.init.zeros_(self.mlp[-1].weight)  # start as the heuristic blend
        torch.nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, features: torch.Tensor, prior: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
        """Weights (N, k) summing to 1 over the visible sources (0 on invisible ones; all 0 where none is).

        Args: features (N, k, 8), prior (N, k) normalised heuristic weights, visible (N, k) bool.
        """
        logit = self.mlp(features)[..., 0] + torch.log(prior.clamp_min(1e-12))
        logit = torch.where(visible, logit, torch.full_like(logit, -1e9))
        return torch.softmax(logit, dim=1) * visible.any(1, keepdim=True)


def _blend(weights: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    a = (weights.unsqueeze(-1) * albedo).sum(1)
    n = torch.nn.functional.normalize((weights.unsqueeze(-1) * normal).sum(1), dim=-1, eps=1e-9)
    return a, n


class LearnedBlend:
    """A trained :class:`BlendNet` with its config and training record; pass it as ``blend`` to
    :func:`stages.numerics.gbuffer.reproject_gbuffer`."""

    def __init__(self, net: BlendNet, config: LearnedBlendConfig, record: dict[str, Any]) -> None:
        self.net = net.cpu().eval()
        self.config = config
        self.record = record

    @torch.no_grad()
    def weights(self, cand: dict[str, Any], chunk: int = 262144) -> np.ndarray:
        """Blend weights (N, k) float64 of :func:`source_candidates`-style arrays, summing to 1 where a
        source is visible; finite."""
        n = len(np.asarray(cand["weight"]))
        out = np.zeros(np.asarray(cand["weight"]).shape, np.float64)
        for lo in range(0, n, chunk):
            part = candidate_features({key: np.asarray(cand[key])[lo:lo + chunk] for key in _CANDIDATE_KEYS})
            out[lo:lo + chunk] = self.net(part["features"], part["prior"], part["visible"]).double().numpy()
        return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)


def fit_learned_blend(views: Sequence[SourceView], config: LearnedBlendConfig = LearnedBlendConfig(), k: int = 6,
                      depth_tolerance_m: float = 0.01, interpolation: str = "cubic",
                      device: str | torch.device = "cpu",
                      progress: Callable[[int, int, str], None] | None = None) -> LearnedBlend:
    """Train the blend leave one out on ``views`` (each in turn the target of the others).

    Args:
        views: the captured views allowed in training (SourceView: maps, valid, camera, mesh depth); at
            least 3.
        config: see :class:`LearnedBlendConfig`. k, depth_tolerance_m, interpolation: as the blend that
            will use it (:func:`stages.numerics.gbuffer.reproject_gbuffer`).
        device: torch device of the training.
        progress: ``progress(done, total, message)`` per gathered view and at the end.

    Returns:
        :class:`LearnedBlend` whose ``record`` holds ``views``, ``pixels``, ``gather_s``, ``train_s``,
        ``loss_first``, ``loss_last`` (mean of the first and last 20 steps) and ``heuristic_loss`` (the
        same loss with the heuristic weights, over the training pixels).
    """
    if len(views) < 3:
        raise ValueError(f"fit_learned_blend needs at least 3 views, got {len(views)}")
    rng = np.random.default_rng(config.seed)
    torch.manual_seed(config.seed)
    start = time.perf_counter()
    parts: list[dict[str, torch.Tensor]] = []
    for i, target in enumerate(views):
        others = [v for j, v in enumerate(views) if j != i]
        cand = source_candidates(target.depth_m, target.K, target.cam_from_world, others, k=k,
                                 depth_tolerance_m=depth_tolerance_m, interpolation=interpolation)
        rows, cols = cand["rows"], cand["cols"]
        ref_albedo = np.asarray(target.albedo, np.float32)[rows, cols]
        ref_normal = np.asarray(target.normal, np.float32)[rows, cols]
        usable = (np.asarray(target.valid, bool)[rows, cols] & (cand["weight"].sum(1) > 1e-12)
                  & np.all(np.isfinite(ref_albedo), -1) & np.all(np.isfinite(ref_normal), -1)
                  & (np.linalg.norm(ref_normal, axis=-1) > 0.5))
        idx = np.nonzero(usable)[0]
        if idx.size > config.pixels_per_view:
            idx = np.sort(rng.choice(idx, config.pixels_per_view, replace=False))
        if idx.size:
            feats = candidate_features({key: cand[key][idx] for key in _CANDIDATE_KEYS})
            feats["ref_albedo"] = torch.from_numpy(ref_albedo[idx])
            feats["ref_normal"] = torch.from_numpy(ref_normal[idx])
            parts.append(feats)
        if progress is not None:
            progress(i + 1, len(views) + 1, f"blend: view {i + 1}/{len(views)} gathered")
    if not parts:
        raise ValueError("fit_learned_blend: no view has pixels that other views see")
    data = {key: torch.cat([p[key] for p in parts]).to(device) for key in parts[0]}
    gather_s = time.perf_counter() - start
    n = len(data["prior"])

    def loss_of(weights: torch.Tensor, sel: torch.Tensor | slice) -> torch.Tensor:
        a, nrm = _blend(weights, data["albedo"][sel], data["normal"][sel])
        return ((a - data["ref_albedo"][sel]).abs().mean()
                + _NORMAL_WEIGHT * (1.0 - (nrm * data["ref_normal"][sel]).sum(-1)).mean())

    net = BlendNet(config.hidden_width).to(device)
    optimiser = torch.optim.Adam(net.parameters(), lr=config.learning_rate)
    generator = torch.Generator().manual_seed(config.seed)
    losses = []
    start = time.perf_counter()
    for _ in range(config.steps):
        sel = torch.randint(0, n, (min(config.batch_pixels, n),), generator=generator).to(device)
        loss = loss_of(net(data["features"][sel], data["prior"][sel], data["visible"][sel]), sel)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        losses.append(float(loss.detach()))
    train_s = time.perf_counter() - start
    with torch.no_grad():
        prior = data["prior"] * data["visible"]
        heuristic = float(loss_of(prior / prior.sum(1, keepdim=True).clamp_min(1e-12), slice(None)))
        learned = float(loss_of(net(data["features"], data["prior"], data["visible"]), slice(None)))
    if progress is not None:
        progress(len(views) + 1, len(views) + 1, f"blend: trained ({learned:.4f} vs heuristic {heuristic:.4f})")
    window = min(20, len(losses))
    record = {"views": len(views), "pixels": int(n), "gather_s": round(gather_s, 2), "train_s": round(train_s, 2),
              "loss_first": float(np.mean(losses[:window])), "loss_last": float(np.mean(losses[-window:])),
              "heuristic_loss": heuristic, "learned_loss": learned}
    return LearnedBlend(net, config, record)
