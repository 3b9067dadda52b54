"""Fused CPU kernels of the SDF's training step: the multiresolution hash encoding (features, their spatial
Jacobian and the table gradient of both, in one pass over the points each) and the proposal grid's march
(:func:`march_first_crossing`: each ray sampled until its first crossing, with ``F.grid_sample``'s float
operations, so it returns the torch march's values bit for bit).

:class:`stages.numerics.sdf.HashEncoding` computes the same with torch operations; on a CPU those allocate and
walk about thirty (N, L, 8, F)-sized temporaries per step, which made the encoding more than half of an SDF
training step. This module's C source is compiled once per machine (:func:`pipeline.ckernel.load_kernel`) and
wrapped in an autograd function. Where no C compiler is found (or ``ULTRASTAGE_HASHGRID_KERNEL=torch``), for
CUDA tensors, and where torch runs on more than :data:`MAX_TORCH_THREADS` threads, the encoding keeps its torch
path; :func:`kernel_available` says whether the kernel is there. The two paths agree to float rounding
(relative differences about 1e-7, tests/unit/numerics/test_hashgrid_kernel.py), so which one ran is not part
of a stage's cache key.

The gradient flows to the table only: the encoded points are data (ray samples and random points), never
parameters, and :func:`encode` refuses points that require a gradient.
"""
from __future__ import annotations

import ctypes
import functools
import os

import torch

from pipeline.ckernel import load_kernel

_SOURCE = r"""
#include <stdint.h>
#include <math.h>

/* Corner indices (x the slowest bit, as the torch path) and per-axis cell fractions of one point at one level. */
static inline void corners(const float *x, float res, int dense, int64_t offset, uint32_t hash_mask,
                           uint32_t idx[8], float frac[3]) {
    int64_t cell[3];
    for (int a = 0; a < 3; ++a) {
        float u = x[a];
        u = u < 0.f ? 0.f : (u > 1.f ? 1.f : u);
        float p = u * res;
        float c = floorf(p);
        if (c > res - 1.f) c = res - 1.f;
        frac[a] = p - c;
        cell[a] = (int64_t)c;
    }
    if (dense) {
        int64_t stride = (int64_t)res + 1;
        for (int i = 0; i < 2; ++i)
            for (int j = 0; j < 2; ++j)
                for (int k = 0; k < 2; ++k)
                    idx[i * 4 + j * 2 + k] = (uint32_t)(offset + cell[0] + i + (cell[1] + j) * stride
                                                        + (cell[2] + k) * stride * stride);
    } else {
        for (int i = 0; i < 2; ++i)
            for (int j = 0; j < 2; ++j)
                for (int k = 0; k < 2; ++k) {
                    uint32_t h = ((uint32_t)(cell[0] + i)) ^ ((uint32_t)(cell[1] + j) * 2654435761u)
                                 ^ ((uint32_t)(cell[2] + k) * 805459861u);
                    idx[i * 4 + j * 2 + k] = (uint32_t)offset + (h & hash_mask);
                }
    }
}

/* The 8 corners' trilinear weights w and their derivatives along x, y, z (times s = res * level weight). */
static inline void weights(const float fr[3], float m, float s, float w[8], float dx[8], float dy[8], float dz[8]) {
    const float wx[2] = {1.f - fr[0], fr[0]}, wy[2] = {1.f - fr[1], fr[1]}, wz[2] = {1.f - fr[2], fr[2]};
    const float sg[2] = {-1.f, 1.f};
    for (int i = 0; i < 2; ++i)
        for (int j = 0; j < 2; ++j)
            for (int k = 0; k < 2; ++k) {
                const int c = i * 4 + j * 2 + k;
                w[c] = wx[i] * wy[j] * wz[k] * m;
                dx[c] = sg[i] * wy[j] * wz[k] * s;
                dy[c] = wx[i] * sg[j] * wz[k] * s;
                dz[c] = wx[i] * wy[j] * sg[k] * s;
            }
}

/* enc: (N, L_all*F); jac: (3, N, L_all*F) or NULL. Levels >= L are left untouched (the caller zeroes them). */
void hashgrid_forward(const float *table, int64_t F, const float *x, int64_t N, int64_t L, int64_t L_all,
                      const float *res, const int64_t *offsets, int64_t n_dense, uint32_t hash_mask,
                      const float *level_mask, float *enc, float *jac) {
    const int64_t D = L_all * F;
    for (int64_t n = 0; n < N; ++n) {
        for (int64_t l = 0; l < L; ++l) {
            uint32_t idx[8];
            float fr[3], w[8], dx[8], dy[8], dz[8];
            corners(x + 3 * n, res[l], l < n_dense, offsets[l], hash_mask, idx, fr);
            weights(fr, level_mask[l], res[l] * level_mask[l], w, dx, dy, dz);
            for (int64_t f = 0; f < F; ++f) {
                float e = 0.f, gx = 0.f, gy = 0.f, gz = 0.f;
                for (int c = 0; c < 8; ++c) {
                    const float v = table[(int64_t)idx[c] * F + f];
                    e += w[c] * v;
                    gx += dx[c] * v;
                    gy += dy[c] * v;
                    gz += dz[c] * v;
                }
                const int64_t o = n * D + l * F + f;
                enc[o] = e;
                if (jac) {
                    jac[o] = gx;
                    jac[N * D + o] = gy;
                    jac[2 * N * D + o] = gz;
                }
            }
        }
    }
}

/* grad_table (rows, F) += d loss / d table for d loss / d enc (N, L_all*F) and d loss / d jac (3, N, L_all*F)
   (either may be NULL). */
void hashgrid_backward(int64_t F, const float *x, int64_t N, int64_t L, int64_t L_all, const float *res,
                       const int64_t *offsets, int64_t n_dense, uint32_t hash_mask, const float *level_mask,
                       const float *grad_enc, const float *grad_jac, float *grad_table) {
    const int64_t D = L_all * F;
    for (int64_t n = 0; n < N; ++n) {
        for (int64_t l = 0; l < L; ++l) {
            uint32_t idx[8];
            float fr[3], w[8], dx[8], dy[8], dz[8];
            corners(x + 3 * n, res[l], l < n_dense, offsets[l], hash_mask, idx, fr);
            weights(fr, level_mask[l], res[l] * level_mask[l], w, dx, dy, dz);
            for (int64_t f = 0; f < F; ++f) {
                const int64_t o = n * D + l * F + f;
                const float ge = grad_enc ? grad_enc[o] : 0.f;
                const float gx = grad_jac ? grad_jac[o] : 0.f;
                const float gy = grad_jac ? grad_jac[N * D + o] : 0.f;
                const float gz = grad_jac ? grad_jac[2 * N * D + o] : 0.f;
                for (int c = 0; c < 8; ++c)
                    grad_table[(int64_t)idx[c] * F + f] += w[c] * ge + dx[c] * gx + dy[c] * gy + dz[c] * gz;
            }
        }
    }
}
/* The cached SDF grid (D, H, W) (W the x axis) at a point, as torch's grid_sample (trilinear, border padding,
   align_corners=False) computes it from the normalised coordinate g = (p - lo) / ext * 2 - 1. */
static inline float grid_at(const float *grid, int64_t D, int64_t H, int64_t W, const float lo[3],
                            const float ext[3], const float p[3]) {
    const int64_t size[3] = {W, H, D};
    float ix[3];
    int64_t i0[3];
    for (int a = 0; a < 3; ++a) {
        float g = (p[a] - lo[a]) / ext[a];
        g = g * 2.0f - 1.0f;
        float u = ((g + 1.0f) * (float)size[a] - 1.0f) / 2.0f;
        const float hi = (float)(size[a] - 1);
        u = u < 0.0f ? 0.0f : u;  /* clip_coordinates: std::min(hi, std::max(u, 0)) */
        u = u < hi ? u : hi;
        ix[a] = u;
        i0[a] = (int64_t)u;  /* u >= 0 here: truncation is floor */
    }
    const float x = ix[0], y = ix[1], z = ix[2];
    const int64_t x0 = i0[0], y0 = i0[1], z0 = i0[2], x1 = x0 + 1, y1 = y0 + 1, z1 = z0 + 1;
    /* corner order and weight expressions of grid_sampler_3d_cpu_impl: tnw, tne, tsw, tse, bnw, bne, bsw, bse */
    const int64_t cx[8] = {x0, x1, x0, x1, x0, x1, x0, x1};
    const int64_t cy[8] = {y0, y0, y1, y1, y0, y0, y1, y1};
    const int64_t cz[8] = {z0, z0, z0, z0, z1, z1, z1, z1};
    const float w[8] = {
        ((float)x1 - x) * ((float)y1 - y) * ((float)z1 - z),
        (x - (float)x0) * ((float)y1 - y) * ((float)z1 - z),
        ((float)x1 - x) * (y - (float)y0) * ((float)z1 - z),
        (x - (float)x0) * (y - (float)y0) * ((float)z1 - z),
        ((float)x1 - x) * ((float)y1 - y) * (z - (float)z0),
        (x - (float)x0) * ((float)y1 - y) * (z - (float)z0),
        ((float)x1 - x) * (y - (float)y0) * (z - (float)z0),
        (x - (float)x0) * (y - (float)y0) * (z - (float)z0)};
    float out = 0.0f;
    for (int c = 0; c < 8; ++c)
        if (cx[c] >= 0 && cx[c] < W && cy[c] >= 0 && cy[c] < H && cz[c] >= 0 && cz[c] < D)
            out += grid[(cz[c] * H + cy[c]) * W + cx[c]] * w[c];
    return out;
}

/* Per ray: march the cached SDF at near + (k + 0.5) * step, k < n_steps, while inside [near, far); the first
   + to - crossing (linear interpolation between the two samples) -> t_out, crossed = 1, min_s = the least
   sample up to it; without one, t_out = the first sample of least SDF (near when none is inside) and min_s
   its value (+inf when none). */
void proposal_march(const float *grid, int64_t D, int64_t H, int64_t W, const float *lo, const float *ext,
                    float step, int64_t n_steps, const float *origins, const float *dirs, const float *near,
                    const float *far, int64_t R, float *t_out, uint8_t *crossed, float *min_s) {
    for (int64_t r = 0; r < R; ++r) {
        const float *o = origins + 3 * r, *d = dirs + 3 * r;
        float best_s = INFINITY, best_t = near[r], prev_s = 0.0f, prev_t = 0.0f;
        int hit = 0;
        for (int64_t k = 0; k < n_steps; ++k) {
            const float t = near[r] + ((float)k + 0.5f) * step;
            if (!(t < far[r]))
                break;
            float p[3];
            for (int a = 0; a < 3; ++a)
                p[a] = o[a] + t * d[a];
            const float s = grid_at(grid, D, H, W, lo, ext, p);
            if (k > 0 && prev_s > 0.0f && s <= 0.0f && isfinite(s)) {
                float den = prev_s - s;
                den = den < 1e-12f ? 1e-12f : den;
                t_out[r] = prev_t + (step * prev_s) / den;
                hit = 1;
                if (s < best_s)
                    best_s = s;
                break;
            }
            if (s < best_s) {
                best_s = s;
                best_t = t;
            }
            prev_s = s;
            prev_t = t;
        }
        crossed[r] = (uint8_t)hit;
        if (!hit)
            t_out[r] = best_t;
        min_s[r] = best_s;
    }
}
"""

MAX_TORCH_THREADS = 2
"""The encoding uses the kernel (one thread) only where torch runs on at most this many threads: with more,
torch's own operations spread over the cores (the geometry stage of `make dataset` trains each action on one)."""

@functools.lru_cache(maxsize=1)
def _library() -> ctypes.CDLL | None:
    """The compiled kernel (compiled on first use, then loaded from the cache), or None where it cannot be."""
    if os.environ.get("ULTRASTAGE_HASHGRID_KERNEL", "").lower() == "torch":
        return None
    i64, f32p, i64p = ctypes.c_int64, ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_int64)
    u8p = ctypes.POINTER(ctypes.c_uint8)
    return load_kernel("hash-grid", _SOURCE, {
        "hashgrid_forward": ([f32p, i64, f32p, i64, i64, i64, f32p, i64p, i64, ctypes.c_uint32, f32p, f32p, f32p],
                             None),
        "hashgrid_backward": ([i64, f32p, i64, i64, i64, f32p, i64p, i64, ctypes.c_uint32, f32p, f32p, f32p, f32p],
                              None),
        "proposal_march": ([f32p, i64, i64, i64, f32p, f32p, ctypes.c_float, i64, f32p, f32p, f32p, f32p, i64, f32p,
                            u8p, f32p], None)}, fallback="the torch path")


def kernel_available() -> bool:
    """True where :func:`encode` runs the compiled kernel on CPU tensors."""
    return _library() is not None


def _ptr(tensor: torch.Tensor | None, kind=ctypes.c_float):
    if tensor is None:
        return ctypes.POINTER(kind)()
    return ctypes.cast(tensor.data_ptr(), ctypes.POINTER(kind))


class _Layout:
    """The encoding's constants as the kernel reads them (contiguous CPU tensors)."""

    def __init__(self, res: torch.Tensor, offsets: torch.Tensor, n_dense: int, hash_mask: int,
                 level_mask: torch.Tensor, active: int, levels: int, features: int):
        self.res = res.detach().float().contiguous()
        self.offsets = offsets.detach().long().contiguous()
        self.n_dense, self.hash_mask = int(n_dense), int(hash_mask)
        self.level_mask = level_mask.detach().float().contiguous()
        self.active, self.levels, self.features = int(active), int(levels), int(features)


class _HashGridFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, table: torch.Tensor, x01: torch.Tensor, layout: _Layout, jacobian: bool):  # type: ignore[override]
        lib = _library()
        table = table.detach().contiguous()
        x01 = x01.detach().float().contiguous()
        N, D = x01.shape[0], layout.levels * layout.features
        enc = torch.zeros(N, D, dtype=torch.float32)
        jac = torch.zeros(3, N, D, dtype=torch.float32) if jacobian else None
        lib.hashgrid_forward(_ptr(table), layout.features, _ptr(x01), N, layout.active, layout.levels,
                             _ptr(layout.res), _ptr(layout.offsets, ctypes.c_int64), layout.n_dense,
                             layout.hash_mask, _ptr(layout.level_mask), _ptr(enc), _ptr(jac))
        ctx.save_for_backward(x01)
        ctx.layout, ctx.table_shape = layout, table.shape
        return enc, jac

    @staticmethod
    def backward(ctx, grad_enc: torch.Tensor | None, grad_jac: torch.Tensor | None):  # type: ignore[override]
        (x01,) = ctx.saved_tensors
        layout: _Layout = ctx.layout
        grad_table = torch.zeros(ctx.table_shape, dtype=torch.float32)
        grad_enc = None if grad_enc is None else grad_enc.float().contiguous()
        grad_jac = None if grad_jac is None else grad_jac.float().contiguous()
        _library().hashgrid_backward(layout.features, _ptr(x01), x01.shape[0], layout.active, layout.levels,
                                     _ptr(layout.res), _ptr(layout.offsets, ctypes.c_int64), layout.n_dense,
                                     layout.hash_mask, _ptr(layout.level_mask), _ptr(grad_enc), _ptr(grad_jac),
                                     _ptr(grad_table))
        return grad_table, None, None, None


def encode(table: torch.Tensor, x01: torch.Tensor, res: torch.Tensor, offsets: torch.Tensor, n_dense: int,
           hash_mask: int, level_mask: torch.Tensor, active: int, jacobian: bool
           ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Hash-encode points with the compiled kernel.

    Args:
        table: (rows, F) float32 CPU feature table (dense levels first, then one ``hash_mask + 1`` block per
            hashed level, at ``offsets``).
        x01: (N, 3) float32 CPU points in the unit cube (clamped into it); must not require a gradient.
        res: (L,) cells per edge of each level; offsets: (L,) int64 first row of each level's table.
        n_dense: the first ``n_dense`` levels index a dense grid, the others hash.
        hash_mask: table size per hashed level minus one (a power of two minus one).
        level_mask: (L,) weight of each level (coarse-to-fine); levels from ``active`` on are all zero.
        jacobian: also return d(features)/d(x01).

    Returns:
        ``(features (N, L*F), jacobian (3, N, L*F) or None)``; differentiable with respect to ``table``.
    """
    if x01.requires_grad:
        raise ValueError("encode: the points must not require a gradient (the kernel differentiates the table only)")
    if table.device.type != "cpu" or x01.device.type != "cpu" or table.dtype != torch.float32:
        raise ValueError("encode: float32 CPU tensors only")
    if x01.ndim != 2 or x01.shape[1] != 3:
        raise ValueError(f"encode: x01 must be (N, 3), got {tuple(x01.shape)}")
    levels = int(res.shape[0])
    layout = _Layout(res, offsets, n_dense, hash_mask, level_mask, min(int(active), levels), levels,
                     int(table.shape[1]))
    enc, jac = _HashGridFunction.apply(table, x01, layout, jacobian)
    return enc, jac


def march_first_crossing(grid: torch.Tensor, lo: torch.Tensor, ext: torch.Tensor, step: float, n_steps: int,
                         origins: torch.Tensor, dirs: torch.Tensor, near: torch.Tensor, far: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The proposal grid's march (:meth:`stages.numerics.sdf.ProposalGrid.first_crossing`) with the compiled
    kernel, one ray after another with an early exit at its crossing.

    Args:
        grid: (D, H, W) float32 CPU cached SDF (W along x), sampled as ``F.grid_sample`` (trilinear, border,
            ``align_corners=False``) over the box ``lo`` (3,) + ``ext`` (3,).
        step: sample spacing along the rays; ``n_steps``: the most samples per ray.
        origins, dirs: (R, 3) float32; near, far: (R,) float32 ray interval.

    Returns:
        ``(t (R,), crossed (R,) bool, min_sdf (R,))``: the first + to - crossing (linear interpolation), else
        the first sample of least SDF; ``min_sdf`` is the least sample up to the crossing (+inf on a ray with
        no sample inside its interval).
    """
    if grid.ndim != 3 or grid.dtype != torch.float32 or grid.device.type != "cpu":
        raise ValueError(f"march_first_crossing: grid must be a (D, H, W) float32 CPU tensor, got "
                         f"{tuple(grid.shape)} {grid.dtype} {grid.device}")
    R = int(dirs.shape[0])
    if origins.shape != (R, 3) or dirs.shape != (R, 3) or near.shape != (R,) or far.shape != (R,):
        raise ValueError("march_first_crossing: origins, dirs (R, 3) and near, far (R,) must agree")
    lib = _library()
    if lib is None:
        raise RuntimeError("march_first_crossing: the compiled kernel is not available")
    grid_c = grid.detach().contiguous()
    lo_c, ext_c = lo.detach().float().contiguous(), ext.detach().float().contiguous()
    o, d = origins.detach().float().contiguous(), dirs.detach().float().contiguous()
    n, f = near.detach().float().contiguous(), far.detach().float().contiguous()
    t_out = torch.empty(R, dtype=torch.float32)
    crossed = torch.empty(R, dtype=torch.uint8)
    min_s = torch.empty(R, dtype=torch.float32)
    D, H, W = (int(v) for v in grid_c.shape)
    lib.proposal_march(_ptr(grid_c), D, H, W, _ptr(lo_c), _ptr(ext_c), float(step), int(n_steps), _ptr(o), _ptr(d),
                       _ptr(n), _ptr(f), R, _ptr(t_out), _ptr(crossed, ctypes.c_uint8), _ptr(min_s))
    return t_out, crossed.bool(), min_s
