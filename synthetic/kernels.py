"""The simulator's fused C loop for GGX shading (:func:`ggx_terms`), compiled by :func:`pipeline.ckernel.load_kernel`.

:func:`synthetic.shading.ggx_weights` is a chain of about twenty elementwise float32 operations over a
(pixels, lights) array, most of the simulator's and of the relit references' shading time. The loop here does
the same IEEE float32 operations in the same order per element, so it gives the numpy chain's bits
(tests/unit/synthetic/test_simulator.py compares them bit for bit); the (N, 3) x (3, C) products and the
per-pixel terms stay numpy's. Where the loop cannot be built or loaded (no C compiler, a compile error, an unwritable
cache; :func:`pipeline.ckernel.load_kernel` says why) or ``ULTRASTAGE_SIM_KERNEL=numpy`` is set, the numpy chain
runs, with the same result.
"""
from __future__ import annotations

import ctypes
import functools
import os

import numpy as np

from pipeline.ckernel import load_kernel

_SOURCE = r"""
#include <stdint.h>
#include <math.h>

/* numpy's maximum and minimum of floats: the first operand when it wins a tie or is NaN (written without a
   branch, so the loop vectorises). */
static inline float np_max(float a, float b) { return ((a >= b) | (a != a)) ? a : b; }
static inline float np_min(float a, float b) { return ((a <= b) | (a != a)) ? a : b; }

/* synthetic.shading._ggx_weights_float32 of one (pixel, light) pair from its products nl = n.l and vl = v.l and
   the pixel's nv, lambda_v, a2, f0, operation by operation. */
static inline float ggx_one(float nl, float vl, float nvi, float lvi, float a2i, float a2_minus_1,
                            float one_minus_a2, float f0i, float one_minus_f0) {
    const float pi = (float)3.14159265358979323846;
    nl = np_max(nl, 0.0f);
    float one_plus = vl + 1.0f;
    one_plus = np_max(one_plus, 1e-6f);
    float d = nl + nvi;
    d = d * d;
    float tmp = one_plus * 2.0f;
    d = d / tmp;
    d = np_min(d, 1.0f);
    d = d * a2_minus_1;
    d = d + 1.0f;
    tmp = d * pi;
    tmp = tmp * d;
    float distribution = a2i / tmp;
    one_plus = one_plus * 0.5f;
    float f = sqrtf(one_plus);
    f = 1.0f - f;
    float fresnel = f * f;
    fresnel = fresnel * fresnel;
    fresnel = fresnel * f;
    fresnel = fresnel * one_minus_f0;
    fresnel = fresnel + f0i;
    float lambda_l = nl * nl;
    lambda_l = lambda_l * one_minus_a2;
    lambda_l = lambda_l + a2i;
    lambda_l = sqrtf(lambda_l);
    lambda_l = lambda_l * nvi;
    float denominator = nl * lvi;
    denominator = denominator + lambda_l;
    fresnel = fresnel * distribution;
    denominator = 0.5f / denominator;
    fresnel = fresnel * denominator;
    return fresnel * nl;
}

/* In place over nl (n, c): the GGX weights of n pixels against c lights (vl (n, c); nv, lambda_v, a2, f0 (n,)).
   With visibility (v, c) uint8 given, each weight is also multiplied by the light's visibility at the pixel,
   synthetic.shading.specular_radiance's sum over the pixel's triangle corners tri (n, 3) of visibility times
   bary (n, 3) (the barycentrics over 255), in its order. One clone per vector width, chosen at load. */
__attribute__((target_clones("avx512f", "avx2", "default")))
void ggx_terms(int64_t n, int64_t c, float *nl_io, const float *vl, const float *nv, const float *lambda_v,
               const float *a2, const float *f0, const uint8_t *visibility, const int64_t *tri,
               const float *bary) {
    for (int64_t i = 0; i < n; ++i) {
        const float a2i = a2[i], a2_minus_1 = a2i - 1.0f, one_minus_a2 = 1.0f - a2i;
        const float f0i = f0[i], one_minus_f0 = 1.0f - f0i, nvi = nv[i], lvi = lambda_v[i];
        float *row = nl_io + i * c;
        const float *vrow = vl + i * c;
        if (visibility == 0) {
            for (int64_t j = 0; j < c; ++j)
                row[j] = ggx_one(row[j], vrow[j], nvi, lvi, a2i, a2_minus_1, one_minus_a2, f0i, one_minus_f0);
        } else {
            const uint8_t *v0 = visibility + tri[3 * i] * c, *v1 = visibility + tri[3 * i + 1] * c;
            const uint8_t *v2 = visibility + tri[3 * i + 2] * c;
            const float b0 = bary[3 * i], b1 = bary[3 * i + 1], b2 = bary[3 * i + 2];
            for (int64_t j = 0; j < c; ++j) {
                float w = ggx_one(row[j], vrow[j], nvi, lvi, a2i, a2_minus_1, one_minus_a2, f0i, one_minus_f0);
                float seen = (float)v0[j] * b0;
                float term = (float)v1[j] * b1;
                seen = seen + term;
                term = (float)v2[j] * b2;
                seen = seen + term;
                row[j] = w * seen;
            }
        }
    }
}
"""


# Neither changes a result: errno is never read, and no floating-point exception is trapped. Without them the
# compiler may not vectorise sqrtf or the comparisons.
_FLAGS = ("-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math")


@functools.lru_cache(maxsize=1)
def _library() -> ctypes.CDLL | None:
    if os.environ.get("ULTRASTAGE_SIM_KERNEL", "").lower() == "numpy":
        return None
    f32p, i64 = ctypes.POINTER(ctypes.c_float), ctypes.c_int64
    return load_kernel("sim-ggx", _SOURCE, {"ggx_terms": ([i64, i64, f32p, f32p, f32p, f32p, f32p, f32p,
                                                            ctypes.POINTER(ctypes.c_uint8), ctypes.POINTER(i64),
                                                            f32p], None)},
                       fallback="the numpy path", extra_flags=_FLAGS)


def kernel_available() -> bool:
    """True where :func:`ggx_terms` runs the compiled loop."""
    return _library() is not None


def _ptr(array: np.ndarray):
    return array.ctypes.data_as(ctypes.POINTER(ctypes.c_float))


def ggx_terms(nl: np.ndarray, vl: np.ndarray, nv: np.ndarray, lambda_v: np.ndarray, a2: np.ndarray,
              f0: np.ndarray, visibility: np.ndarray | None = None, tri: np.ndarray | None = None,
              bary: np.ndarray | None = None) -> bool:
    """Overwrite ``nl`` (N, C) float32 C-contiguous (``normals @ lights.T``) with the GGX weights given ``vl``
    (N, C) (``view @ lights.T``) and the per-pixel nv, lambda_v, a2, f0 (N, 1) or (N,) float32; with
    ``visibility`` (V, C) uint8, ``tri`` (N, 3) vertex ids and ``bary`` (N, 3) float32 (barycentrics / 255), each
    weight times the light's visibility interpolated over the pixel's triangle. False (and ``nl`` untouched)
    where the kernel is not available."""
    lib = _library()
    if lib is None:
        return False
    n, c = nl.shape
    if not (nl.dtype == vl.dtype == np.float32 and nl.flags.c_contiguous and vl.shape == (n, c)):
        raise ValueError("ggx_terms needs float32 C-contiguous (N, C) products of the same shape")
    rows = [np.ascontiguousarray(x, np.float32).reshape(-1) for x in (nv, lambda_v, a2, f0)]
    if any(len(r) != n for r in rows):
        raise ValueError(f"ggx_terms needs {n} per-pixel values, got {[len(r) for r in rows]}")
    vl = np.ascontiguousarray(vl)
    seen = (ctypes.POINTER(ctypes.c_uint8)(), ctypes.POINTER(ctypes.c_int64)(), ctypes.POINTER(ctypes.c_float)())
    if visibility is not None:
        if not (visibility.dtype == np.uint8 and visibility.ndim == 2 and visibility.shape[1] == c
                and bary is not None and bary.dtype == np.float32 and bary.shape == (n, 3)
                and tri is not None and tri.shape == (n, 3)):
            raise ValueError("ggx_terms needs uint8 (V, C) visibility with (N, 3) ids and float32 barycentrics")
        tri = np.ascontiguousarray(tri, np.int64)
        if n and (tri.min() < 0 or tri.max() >= len(visibility)):
            raise ValueError(f"ggx_terms: vertex ids outside the visibility's {len(visibility)} rows")
        visibility, bary = np.ascontiguousarray(visibility), np.ascontiguousarray(bary)
        seen = (visibility.ctypes.data_as(ctypes.POINTER(ctypes.c_uint8)),
                tri.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)), _ptr(bary))
    lib.ggx_terms(n, c, _ptr(nl), _ptr(vl), *(_ptr(r) for r in rows), *seen)
    return True
