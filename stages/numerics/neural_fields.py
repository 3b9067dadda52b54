"""What the neural fields share: the multiresolution hash encoding and the training helpers.

The normal-supervised SDF (:mod:`stages.numerics.sdf`) and the volume-rendered albedo/normal field
(:mod:`stages.numerics.appearance_field`) are both an Instant-NGP hash grid (:class:`HashGridConfig`,
:class:`HashEncoding`) feeding a small MLP, rendered along rays through a box (:func:`ray_box`) with NeuS
weights (:func:`neus_composite`) and trained with Instant-NGP's Adam (:func:`instant_ngp_adam`) under a warm-up
and cosine learning-rate schedule (:func:`lr_factor`) on the device :func:`resolve_device` picks. Both check
their inputs with the same functions: :func:`check_bounds`, :func:`check_view_list`, :func:`check_view_map`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

# re-exported: the SDF and the appearance field take them from here
from artifacts.camera import check_bounds, ray_box  # noqa: F401
from pipeline.config import Documented, checked
from stages.numerics import hashgrid_kernel

__all__ = [
    "HashGridConfig",
    "HashEncoding",
    "resolve_device",
    "ray_box",
    "neus_composite",
    "neus_opacity_before",
    "instant_ngp_adam",
    "lr_factor",
]

_PRIMES = (1, 2654435761, 805459861)  # Instant-NGP's spatial hash

_FINAL_LR_FRACTION = 0.1
"""The learning rate decays (cosine) to this fraction of ``learning_rate`` at the last step."""


@dataclass(frozen=True)
class HashGridConfig(Documented):
    """Multiresolution hash encoding (Instant-NGP) over the cube around a field's bounds."""

    levels: int = checked(12, ge=1, le=32)
    """Number of resolution levels ``L``, geometrically spaced from ``base_resolution`` to ``finest_resolution``."""
    features_per_level: int = checked(2, ge=1, le=8)
    """Features per level ``F`` (the MLP's input is ``3 + L * F``: the position plus the features)."""
    log2_table_size: int = checked(16, ge=8, le=24)
    """log2 of the entries per level ``T``; coarse levels with ``(res + 1)^3 <= T`` use a dense table instead."""
    base_resolution: int = checked(16, ge=1, le="finest_resolution")
    """Grid cells along the cube's edge at the coarsest level."""
    finest_resolution: int = 512
    """Grid cells along the cube's edge at the finest level (the cube is the bounds' longest edge, so
    ``edge / finest_resolution`` is the finest cell in metres)."""


def resolve_device(device: str) -> torch.device:
    """``auto`` -> CUDA when available else CPU; ``cuda`` without CUDA raises ValueError."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("device='cuda' but torch sees no CUDA device; use 'auto' or 'cpu'")
    if device not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda', got {device!r}")
    return torch.device(device)


# ------------------------------------------------------------------------------------------------ encoding


class _Gather(torch.autograd.Function):
    """``table[index]`` whose backward scatters into a flat view of the table (about twice as fast on the
    CPU as index_select's row-wise index_add for 2-feature rows). First order only."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.save_for_backward(index)
        ctx.table_shape = table.shape
        return table.index_select(0, index)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        (index,) = ctx.saved_tensors
        rows, width = ctx.table_shape
        flat_index = (index.long().unsqueeze(1) * width + torch.arange(width, device=index.device)).view(-1)
        out = torch.zeros(rows * width, dtype=grad.dtype, device=grad.device)
        out.scatter_add_(0, flat_index, grad.contiguous().view(-1))
        return out.view(rows, width), None


class HashEncoding(torch.nn.Module):
    """Multiresolution hash encoding of points in the unit cube, with its spatial Jacobian on request.

    Level ``l`` has ``res_l = floor(base * b^l)`` cells per edge (``b`` spaces the levels geometrically up to
    ``finest_resolution``) and ``(res_l + 1)^3`` corner vertices; a level whose vertices fit in ``T`` entries
    indexes a dense table, finer ones hash the vertex (Instant-NGP primes) into ``T`` entries. Features are
    trilinearly interpolated from the 8 corners.
    """

    def __init__(self, config: HashGridConfig):
        super().__init__()
        self.config = config
        L, T = config.levels, 2 ** config.log2_table_size
        growth = (config.finest_resolution / config.base_resolution) ** (1.0 / max(L - 1, 1))
        res = [int(math.floor(config.base_resolution * growth ** level + 1e-6)) for level in range(L)]
        dense = [(r + 1) ** 3 <= T for r in res]  # the coarse levels: res grows with the level
        n_dense = int(sum(dense))
        dense_sizes = [(r + 1) ** 3 for r in res[:n_dense]]
        # Dense tables packed first; hashed tables start at a multiple of T, so that a hashed level's offset
        # has no bits in common with the hash (< T) and can be folded in before the XORs.
        dense_offsets = np.concatenate([[0], np.cumsum(dense_sizes)]).astype(np.int64)
        hash_start = int(math.ceil(dense_offsets[-1] / T) * T) if n_dense < L else int(dense_offsets[-1])
        offsets = list(dense_offsets[:n_dense]) + [hash_start + k * T for k in range(L - n_dense)]
        total = hash_start + (L - n_dense) * T
        self.resolutions = tuple(res)
        self.n_dense = n_dense
        self.hash_mask = T - 1
        self.register_buffer("res", torch.tensor(res, dtype=torch.float32), persistent=False)
        self.register_buffer("res_long", torch.tensor(res, dtype=torch.int64), persistent=False)
        self.register_buffer("offsets", torch.tensor(offsets, dtype=torch.int64), persistent=False)
        self.register_buffer("level_mask", torch.ones(L), persistent=False)
        self.active_count = L
        self.double_backward = False  # set while SDFField computes gradients with autograd (create_graph)
        # Instant-NGP: small uniform init, so that the MLP starts from the position input alone.
        generator = torch.Generator().manual_seed(0)
        table = (torch.rand(total, config.features_per_level, generator=generator) * 2 - 1) * 1e-4
        self.table = torch.nn.Parameter(table)

    @property
    def out_dim(self) -> int:
        return self.config.levels * self.config.features_per_level

    def set_active_levels(self, n: float) -> None:
        """Coarse-to-fine: levels below ``n`` are on, the next one fades in by the fraction of ``n``."""
        L = self.config.levels
        levels = torch.arange(L, dtype=torch.float32, device=self.level_mask.device)
        mask = torch.clamp(n - levels, 0.0, 1.0)
        self.level_mask.copy_(mask)
        self.active_count = max(1, int((mask > 0).sum()))

    def _use_kernel(self, x01: torch.Tensor) -> bool:
        """The fused CPU kernel (:mod:`stages.numerics.hashgrid_kernel`) computes this call: float32 CPU
        tensors, points without a gradient, no double backward, torch on at most
        :data:`hashgrid_kernel.MAX_TORCH_THREADS` threads (the kernel runs on one), and a compiled kernel."""
        return (x01.device.type == "cpu" and self.table.dtype == torch.float32 and not x01.requires_grad
                and not self.double_backward and torch.get_num_threads() <= hashgrid_kernel.MAX_TORCH_THREADS
                and hashgrid_kernel.kernel_available())

    def forward(self, x01: torch.Tensor, jacobian: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Encode points (with the fused CPU kernel where :meth:`_use_kernel`, else torch operations).

        Args:
            x01: (N, 3) points in the unit cube (clamped into it).
            jacobian: also return d(features)/d(x01).

        Returns:
            ``(features (N, L*F), jacobian (3, N, L*F) or None)``.
        """
        if self._use_kernel(x01):
            return hashgrid_kernel.encode(self.table, x01, self.res, self.offsets, self.n_dense, self.hash_mask,
                                          self.level_mask, self.active_count, jacobian)
        L_all, Fd = self.config.levels, self.config.features_per_level
        L = self.active_count  # switched-off fine levels are not computed at all (coarse-to-fine is cheap)
        N = x01.shape[0]
        x01 = x01.clamp(0.0, 1.0)
        res = self.res[:L]
        pos = x01.unsqueeze(1) * res.view(1, L, 1)  # (N, L, 3)
        cell_f = torch.minimum(torch.floor(pos), (res - 1).view(1, L, 1))
        frac = pos - cell_f  # (N, L, 3), in [0, 1]
        cell = cell_f.long()
        # Index and weight of the 8 corners, factorised per axis: (N, L, 2) per axis (int64 products, masked
        # to int32), combined by broadcasting to (N, L, 2, 2, 2): two int32 ops on the big tensors instead of
        # hashing (N, L, 8, 3) corner coordinates.
        lo_hi = torch.stack([cell, cell + 1], dim=-1)  # (N, L, 3, 2)
        parts = []
        nd = min(self.n_dense, L)
        if nd:
            c = lo_hi[:, :nd]
            stride = (self.res_long[:nd] + 1).view(1, nd, 1)
            cx = (c[:, :, 0] + self.offsets[:nd].view(1, nd, 1)).int()
            cy = (c[:, :, 1] * stride).int()
            cz = (c[:, :, 2] * (stride * stride)).int()
            parts.append(cx.unsqueeze(-1).unsqueeze(-1) + cy.unsqueeze(-2).unsqueeze(-1)
                         + cz.unsqueeze(-2).unsqueeze(-2))
        if nd < L:
            c = lo_hi[:, nd:]
            hx = (((c[:, :, 0] * _PRIMES[0]) & self.hash_mask) + self.offsets[nd:L].view(1, L - nd, 1)).int()
            hy = ((c[:, :, 1] * _PRIMES[1]) & self.hash_mask).int()
            hz = ((c[:, :, 2] * _PRIMES[2]) & self.hash_mask).int()
            parts.append(hx.unsqueeze(-1).unsqueeze(-1) ^ hy.unsqueeze(-2).unsqueeze(-1) ^ hz.unsqueeze(-2).unsqueeze(-2))
        # (N, L, 2x, 2y, 2z) -> (N, L, 8) with x the slowest bit, matching the weights below.
        index = parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)
        if self.table.requires_grad and torch.is_grad_enabled() and not self.double_backward:
            feats = _Gather.apply(self.table, index.reshape(-1))
        else:
            feats = self.table.index_select(0, index.reshape(-1))
        # Trilinear interpolation as three lerps (x, then y, then z) on (N, L, 2, 2, 2, F) corner features:
        # fewer and smaller temporaries than weighting all 8 corners (and than tiny batched matmuls).
        f = feats.view(N, L, 2, 2, 2, Fd)
        fx = frac[:, :, 0].view(N, L, 1, 1, 1)
        fy = frac[:, :, 1].view(N, L, 1, 1)
        fz = frac[:, :, 2].view(N, L, 1)
        f_x = torch.lerp(f[:, :, 0], f[:, :, 1], fx)  # (N, L, 2y, 2z, F)
        f_xy = torch.lerp(f_x[:, :, 0], f_x[:, :, 1], fy)  # (N, L, 2z, F)
        mask = self.level_mask[:L].view(1, L, 1)
        enc = torch.lerp(f_xy[:, :, 0], f_xy[:, :, 1], fz) * mask  # (N, L, F)
        enc = enc.reshape(N, L * Fd)
        if L < L_all:
            enc = F.pad(enc, (0, (L_all - L) * Fd))
        if not jacobian:
            return enc, None
        # Derivatives of the trilinear interpolant: the difference along one axis, lerped along the others;
        # d pos / d x01 = res.
        dfx = f[:, :, 1] - f[:, :, 0]  # (N, L, 2y, 2z, F)
        dfx_y = torch.lerp(dfx[:, :, 0], dfx[:, :, 1], fy)  # (N, L, 2z, F)
        dx = torch.lerp(dfx_y[:, :, 0], dfx_y[:, :, 1], fz)
        dfy = f_x[:, :, 1] - f_x[:, :, 0]  # (N, L, 2z, F)
        dy = torch.lerp(dfy[:, :, 0], dfy[:, :, 1], fz)
        dz = f_xy[:, :, 1] - f_xy[:, :, 0]
        scale = (res.view(1, L, 1) * mask)
        jac = torch.stack([dx * scale, dy * scale, dz * scale])  # (3, N, L, F)
        jac = jac.reshape(3, N, L * Fd)
        if L < L_all:
            jac = F.pad(jac, (0, (L_all - L) * Fd))
        return enc, jac


# ------------------------------------------------------------------------------------------------ input checks


def check_view_list(views: Any, view_type: type) -> None:
    """ValueError unless ``views`` is a non-empty list or tuple of ``view_type``, naming the first that is not."""
    if not isinstance(views, (list, tuple)) or len(views) == 0:
        raise ValueError(f"views must be a non-empty list of {view_type.__name__}")
    for i, v in enumerate(views):
        if not isinstance(v, view_type):
            raise ValueError(f"views[{i}] is {type(v).__name__}, expected {view_type.__name__}")


def check_view_map(values: Any, shape: tuple[int, ...], where: str, valid: np.ndarray | None = None) -> np.ndarray:
    """A view's per-pixel map as an array of ``shape`` ((H, W) or (H, W, C)); with ``valid`` (H, W) it must also
    be finite on the valid pixels. ``where`` names the map in the ValueError (e.g. ``views[3].normals_world``)."""
    a = np.asarray(values)
    if a.shape != tuple(shape):
        named = "(H, W)" if len(shape) == 2 else f"(H, W, {shape[2]})"
        raise ValueError(f"{where} must be {named} = {tuple(shape)}, got {a.shape}")
    if valid is not None and not np.isfinite(a[np.asarray(valid, bool)]).all():
        raise ValueError(f"{where} holds NaN or Inf on valid pixels")
    return a


# ------------------------------------------------------------------------------------------------ rendering and training


def neus_composite(sdf: torch.Tensor, grad: torch.Tensor, dirs: torch.Tensor, delta: torch.Tensor,
                   inv_s: float, cos_anneal: float) -> tuple[torch.Tensor, torch.Tensor]:
    """NeuS weights of K samples per ray. sdf (R, K), grad (R, K, 3), dirs (R, 3), delta (R,) spacing.

    Each sample stands for a section of length ``delta``; the SDF at its ends is extrapolated with the
    gradient along the ray (NeuS's estimate, exact for a plane), the section's alpha is
    ``(Phi(f_prev) - Phi(f_next)) / Phi(f_prev)`` with ``Phi`` the logistic CDF of sharpness ``inv_s``.
    Returns ``(weights (R, K), alpha (R, K))``.
    """
    prev_cdf, next_cdf = _section_cdfs(sdf, grad, dirs, delta, inv_s, cos_anneal)
    alpha = ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clamp(0.0, 1.0)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-7], 1), 1)[:, :-1]
    return alpha * trans, alpha


def neus_opacity_before(sdf: torch.Tensor, grad: torch.Tensor, dirs: torch.Tensor, delta: torch.Tensor,
                        inv_s: float, cos_anneal: float) -> torch.Tensor:
    """The NeuS opacity (R,) a ray gathers before a window of samples (the arguments of :func:`neus_composite`),
    when it comes from far outside the surface (``Phi = 1``) without crossing it first: ``1 - Phi(f_start)``,
    ``f_start`` the SDF at the start of the first sample's section.

    The whole ray's opacity is then ``before + (1 - before) * weights.sum(1)``: NeuS's ``1 - Phi(min f)`` on a ray
    whose SDF falls and rises once, wherever the window starts. The window alone misses it where the window starts
    near the surface: on a ray grazing the silhouette the SDF stays within a few mm of its minimum for centimetres.
    """
    prev_cdf, _ = _section_cdfs(sdf[:, :1], grad[:, :1], dirs, delta, inv_s, cos_anneal)
    return (1.0 - prev_cdf[:, 0]).clamp(0.0, 1.0)


def _section_cdfs(sdf: torch.Tensor, grad: torch.Tensor, dirs: torch.Tensor, delta: torch.Tensor, inv_s: float,
                  cos_anneal: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``Phi`` at the start and the end of each sample's section (R, K) each."""
    true_cos = (grad * dirs.unsqueeze(1)).sum(-1)
    # NeuS's cosine annealing: early on the density also lives where the ray leaves the surface.
    iter_cos = -(F.relu(-true_cos * 0.5 + 0.5) * (1.0 - cos_anneal) + F.relu(-true_cos) * cos_anneal)
    half = (delta * 0.5).unsqueeze(1)
    return torch.sigmoid((sdf - iter_cos * half) * inv_s), torch.sigmoid((sdf + iter_cos * half) * inv_s)


def instant_ngp_adam(params: Any, lr: float) -> torch.optim.Adam:
    """Adam with Instant-NGP's settings (betas 0.9, 0.99; eps 1e-15) over ``params`` (tensors or parameter
    groups), fused where torch has it: the fused kernel is several times faster on a 1M-entry table."""
    try:
        return torch.optim.Adam(params, lr=lr, betas=(0.9, 0.99), eps=1e-15, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(params, lr=lr, betas=(0.9, 0.99), eps=1e-15)


def lr_factor(it: int, config: Any) -> float:
    """The learning rate's factor at step ``it`` of ``config`` (any config with ``iterations`` and
    ``warmup_iterations``): a linear warm-up, then a cosine decay to :data:`_FINAL_LR_FRACTION` at the last step."""
    if it < config.warmup_iterations:
        return (it + 1) / config.warmup_iterations
    span = max(config.iterations - config.warmup_iterations, 1)
    p = min((it - config.warmup_iterations) / span, 1.0)
    f = _FINAL_LR_FRACTION
    return f + (1 - f) * 0.5 * (1 + math.cos(math.pi * p))
