"""Shading under the light stage's gradient illuminations in closed form, and a per-point roughness fit.

The illuminations are functions of the light direction ``w`` on the sphere (stage frame, docs/CONTRACTS.md
"LED gradients"), per RGB channel ``c``:

    full_on_c(w) = 1,    pos_c(w) = (1 + w_c) / 2,    neg_c(w) = (1 - w_c) / 2,

all of the form ``L(w) = a + b.w`` (:data:`STAGE_COEFFICIENTS`). Radiance is in the stage's white units:
an unoccluded white Lambertian under ``full_on`` has radiance 1 (the simulator's convention, so decoded
values are radiance times ``white_reference``).

* Diffuse, exactly: ``E(n) = int (a + b.w) max(0, n.w) dw = pi a + (2 pi / 3) b.n``, radiance
  ``albedo / pi * E``.
* Specular: the GGX BRDF as a mixture of warped SG lobes (``stages.numerics.sg.ggx_sg_lobe``, the same lobes
  ``shade_sg`` uses) times ``a + b.w`` and the clamped cosine. Each lobe gives ``C (a + b.m)``: ``C`` the
  lobe's integral against the clamped cosine (the hemispherical SG-cosine integral of ``shade_sg``) and
  ``m`` the lobe's cosine-weighted mean direction over the upper hemisphere. Over the whole sphere and
  without the cosine, ``m = mu (coth(lambda) - 1/lambda)`` (the SG's first moment, closed form); the clamp
  pulls ``m`` towards ``n``, by up to 40% of the pos - neg signal for rough lobes, so ``m`` is read from a
  table built once by quadrature (:func:`_first_moment_table`, 48 x 33, bilinear, differentiable).

:func:`fit_roughness` fits per-point perceptual roughness (bounded) to observed pixel values under the three
illuminations from several views with normals, albedo (and F0 = 0.02) fixed: a grid search over r, then
damped Gauss-Newton steps, vectorised over points. As the lights are linear, the specular term may also
come from a table of the exact GGX lobe's zeroth and first moments (``specular_model="ggx_table"``, the
fit's default): it matches the simulator's per-LED GGX to 0.1-0.3% where the SG lobes are 7-15% off. Everything is torch (float32) inside; numpy in, numpy out.
"""
from __future__ import annotations

import functools

import numpy as np
import torch

from stages.numerics.sg import ROUGHNESS_MAX, ROUGHNESS_MIN, _cosine_integral, _unit, ggx_sg_lobe

__all__ = [
    "ILLUMINATIONS",
    "STAGE_COEFFICIENTS",
    "NO_VIEWS_RESIDUAL",
    "stage_diffuse",
    "SPECULAR_MODELS",
    "shade_stage_illuminations",
    "fit_roughness",
]

ILLUMINATIONS = ("full_on", "pos", "neg")

#: (a (3 illum, 3 rgb), b (3 illum, 3 rgb, 3 xyz)): illumination i, channel c is ``a[i, c] + b[i, c] . w``.
STAGE_COEFFICIENTS = (
    np.array([[1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [0.5, 0.5, 0.5]], np.float32),
    np.stack([np.zeros((3, 3)), 0.5 * np.eye(3), -0.5 * np.eye(3)]).astype(np.float32),
)

#: ``residual`` of :func:`fit_roughness` for points without a valid view (their roughness is the fallback).
NO_VIEWS_RESIDUAL = -1.0


_TABLE_LAMBDA = (1e-3, 1e4)  # sharpness range of the first-moment table (clamped outside)


@functools.lru_cache(maxsize=1)
def _first_moment_table(n_lambda: int = 48, n_cos: int = 33, n_theta: int = 48, n_phi: int = 96) -> torch.Tensor:
    """(2, n_lambda, n_cos) float32: the mean direction of an SG lobe weighted by the clamped cosine,
    ``m = int_H G(w) (n.w) w dw / int_H G(w) (n.w) dw = p n + q t`` (t: unit tangent towards the axis), as
    (p, q) over log-spaced sharpness and ``cos_beta = mu.n``. Midpoint quadrature in a frame around the
    axis, out to 8 lobe widths (~0.1% accurate); built once per process (~0.3 s).

    There is no closed form once the cosine is clamped; the lobe's own first moment
    ``mu (coth(lambda) - 1/lambda)`` ignores both the cosine's pull towards n and the horizon, which for
    rough lobes gets the pos - neg specular wrong by 40%."""
    lams = np.geomspace(*_TABLE_LAMBDA, n_lambda)
    cos_beta = np.linspace(-1.0, 1.0, n_cos)
    sin_beta = np.sqrt(np.maximum(0.0, 1.0 - cos_beta ** 2))
    table = np.zeros((2, n_lambda, n_cos))
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    for i, lam in enumerate(lams):
        theta_max = min(np.pi, 8.0 / np.sqrt(lam))
        theta = (np.arange(n_theta) + 0.5) * (theta_max / n_theta)
        ct, st = np.cos(theta)[:, None], np.sin(theta)[:, None]
        weight = np.exp(lam * (ct - 1.0)) * st  # lobe x area element (the constant steps cancel in ratios)
        # w = ct mu + st (cos phi e1 + sin phi e2), mu = (sb, 0, cb), e1 = (cb, 0, -sb); n = z, t = x
        cp = np.cos(phi)[None, :]
        for j, (cb, sb) in enumerate(zip(cos_beta, sin_beta)):
            wz = ct * cb - st * cp * sb
            wx = ct * sb + st * cp * cb
            w = weight * np.maximum(wz, 0.0)
            total = w.sum()
            if total > 0:
                table[0, i, j] = (w * wz).sum() / total
                table[1, i, j] = (w * wx).sum() / total
    return torch.as_tensor(table, dtype=torch.float32)


def _bilinear(table: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of ``table`` (C, X, Y) at fractional indices x, y (...) -> (C, ...), differentiable
    in x and y (indices clamped to the table)."""
    n_x, n_y = table.shape[-2:]
    x = x.clamp(0, n_x - 1)
    y = y.clamp(0, n_y - 1)
    x0 = x.detach().floor().clamp(max=n_x - 2).long()
    y0 = y.detach().floor().clamp(max=n_y - 2).long()
    fx, fy = x - x0, y - y0
    flat = table.reshape(table.shape[0], -1)

    def at(xi, yi):
        return flat[:, xi * n_y + yi]

    return (at(x0, y0) * (1 - fx) * (1 - fy) + at(x0 + 1, y0) * fx * (1 - fy)
            + at(x0, y0 + 1) * (1 - fx) * fy + at(x0 + 1, y0 + 1) * fx * fy)


def _clipped_mean(sharpness: torch.Tensor, cos_beta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(p, q) of :func:`_first_moment_table` by bilinear interpolation (differentiable in both)."""
    table = _first_moment_table()
    n_lambda, n_cos = table.shape[1:]
    lo, hi = np.log(_TABLE_LAMBDA[0]), np.log(_TABLE_LAMBDA[1])
    x = (torch.log(sharpness.clamp(*_TABLE_LAMBDA)) - lo) / (hi - lo) * (n_lambda - 1)
    y = (cos_beta.clamp(-1.0, 1.0) + 1.0) * 0.5 * (n_cos - 1)
    value = _bilinear(table, x, y)
    return value[0], value[1]


_GGX_NV = (0.02, 1.0)  # n.v range of the GGX moment table (n.v below 0.02 reads the 0.02 row)


@functools.lru_cache(maxsize=2)
def _ggx_moment_table(shadowing: str, n_nv: int = 33, n_r: int = 39, n_xi: int = 96, n_phi: int = 96) -> torch.Tensor:
    """(2, 3, n_nv, n_r) float32: moments of the exact GGX specular lobe (Schlick Fresnel, the given
    shadowing) times the clamped cosine, over n.v in [0.02, 1] and roughness in [ROUGHNESS_MIN, 1]:
    for the Fresnel parts ``F = F0 (1 - s) + s``, ``s = (1 - v.h)^5`` (index 0: the F0 part without F0,
    1: the s part), the moments ``rho0 = int f (n.l) dl`` and ``rho1 = int f (n.l) l dl = p n + q t``
    (t: unit tangent of v) as (rho0, p, q). Stratified GGX importance sampling of the half vector
    (96 x 96, ~0.1%); built once per process per shadowing model (~0.5 s)."""
    nvs = np.linspace(*_GGX_NV, n_nv)
    rs = np.linspace(ROUGHNESS_MIN, ROUGHNESS_MAX, n_r)
    table = np.zeros((2, 3, n_nv, n_r))
    xi = (np.arange(n_xi) + 0.5) / n_xi
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    xi_g, phi_g = np.meshgrid(xi, phi, indexing="ij")
    for j, r in enumerate(rs):
        a2 = r ** 4
        tan2 = a2 * xi_g / (1.0 - xi_g)  # GGX sampling: pdf(h) = D(h) (n.h)
        ch = 1.0 / np.sqrt(1.0 + tan2)
        sh = np.sqrt(1.0 - ch * ch)
        hx, hy, hz = sh * np.cos(phi_g), sh * np.sin(phi_g), ch
        for i, nv in enumerate(nvs):
            vx = np.sqrt(1.0 - nv * nv)  # v = (vx, 0, nv), n = z, t = x
            vh = hx * vx + hz * nv
            lx, lz = 2.0 * vh * hx - vx, 2.0 * vh * hz - nv
            ok = (lz > 0) & (vh > 0)
            nl = np.maximum(lz, 1e-9)
            if shadowing == "smith":
                vis = 0.5 / (nl * np.sqrt(nv * nv * (1 - a2) + a2) + nv * np.sqrt(nl * nl * (1 - a2) + a2))
            else:
                k = (r + 1.0) ** 2 / 8.0
                vis = 1.0 / (4.0 * (nl * (1.0 - k) + k) * (nv * (1.0 - k) + k))
            base = np.where(ok, vis * nl * 4.0 * vh / ch, 0.0)  # f (n.l) / pdf(l) without F and D
            s5 = (1.0 - np.clip(vh, 0.0, 1.0)) ** 5
            for part, fresnel in enumerate((1.0 - s5, s5)):
                w = base * fresnel
                table[part, :, i, j] = (w.mean(), (w * lz).mean(), (w * lx).mean())
    return torch.as_tensor(table, dtype=torch.float32)


def _stage_specular_table(n: torch.Tensor, v: torch.Tensor, r: torch.Tensor, f0, shadowing: str) -> torch.Tensor:
    """Specular radiance (N, 3, 3) under the stage illuminations from the exact GGX moments (table)."""
    table = _ggx_moment_table(shadowing).to(n.device)
    n_nv, n_r = table.shape[-2:]
    nv_raw = (n * v).sum(-1)
    x = (nv_raw - _GGX_NV[0]) / (_GGX_NV[1] - _GGX_NV[0]) * (n_nv - 1)
    y = (r.clamp(ROUGHNESS_MIN, ROUGHNESS_MAX) - ROUGHNESS_MIN) / (ROUGHNESS_MAX - ROUGHNESS_MIN) * (n_r - 1)
    parts = _bilinear(table.reshape(6, n_nv, n_r), x, y).reshape(2, 3, -1)  # (2, 3, N)
    moments = f0 * parts[0] + parts[1]  # (3, N): rho0, p, q
    moments = moments * (nv_raw > 0).to(moments.dtype)
    tangent = _unit(v - nv_raw[:, None] * n)
    a, b = (torch.as_tensor(x, device=n.device) for x in STAGE_COEFFICIENTS)
    b_n = torch.einsum("ick,nk->nic", b, n)
    b_t = torch.einsum("ick,nk->nic", b, tangent)
    return (moments[0][:, None, None] * a[None] + moments[1][:, None, None] * b_n
            + moments[2][:, None, None] * b_t)


def _as_tensor(name: str, x, shape: tuple[int, ...]) -> torch.Tensor:
    t = x.to(torch.float32) if torch.is_tensor(x) else torch.as_tensor(np.asarray(x, dtype=np.float32))
    if tuple(t.shape) != shape:
        raise ValueError(f"{name} must be {shape}, got {tuple(t.shape)}")
    return t


def stage_diffuse(normals, albedo):
    """Lambertian radiance (N, 3 illum, 3 rgb) under full_on, pos, neg: ``albedo_c (a_ic + (2/3) b_ic . n)``
    (exact for an unoccluded point). normals (N, 3) unit, albedo (N, 3). Torch in, torch out; else numpy."""
    as_numpy = not (torch.is_tensor(normals) or torch.is_tensor(albedo))
    n = _unit(_as_tensor("normals", normals, (len(normals), 3)))
    alb = _as_tensor("albedo", albedo, (n.shape[0], 3))
    a, b = (torch.as_tensor(x, device=n.device) for x in STAGE_COEFFICIENTS)
    out = alb[:, None, :] * (a[None] + (2.0 / 3.0) * torch.einsum("ick,nk->nic", b, n))
    return out.numpy() if as_numpy else out


def _stage_specular(n: torch.Tensor, v: torch.Tensor, r: torch.Tensor, f0, shadowing: str, ndf_lobes: int) -> torch.Tensor:
    """Specular radiance (N, 3 illum, 3 rgb) under the three illuminations (module docstring)."""
    a, b = (torch.as_tensor(x) for x in STAGE_COEFFICIENTS)
    axis, sharp, weight = ggx_sg_lobe(n, v, r, f0, shadowing, ndf_lobes)  # (N, 3), (N, K), (N, K)
    out = n.new_zeros((n.shape[0], 3, 3))
    cos_beta = (axis * n).sum(-1)
    tangent = _unit(axis - cos_beta[:, None] * n)  # towards the axis (0 when the axis is the normal: q = 0)
    b_n = torch.einsum("ick,nk->nic", b, n)  # b_ic . n: (N, 3, 3)
    b_t = torch.einsum("ick,nk->nic", b, tangent)
    for k in range(sharp.shape[1]):
        lam = sharp[:, k]
        zeroth = weight[:, k] * _cosine_integral(axis, lam, n)  # (N,): int of the lobe x clamped cosine
        p, q = _clipped_mean(lam, cos_beta)
        out = out + zeroth[:, None, None] * (a[None] + p[:, None, None] * b_n + q[:, None, None] * b_t)
    return out


SPECULAR_MODELS = ("sg", "ggx_table")


def shade_stage_illuminations(normals, view_dirs, albedo, roughness, f0: float = 0.02, specular: bool = True,
                              shadowing: str = "smith", ndf_lobes: int = 3, specular_model: str = "sg"):
    """Radiance of points under the stage's full_on, pos and neg illuminations, (N, 3 illum, 3 rgb).

    Args:
        normals: (N, 3) unit stage-frame normals.
        view_dirs: (N, 3) unit directions from the point towards the camera.
        albedo: (N, 3) linear diffuse albedo.
        roughness: (N,) perceptual GGX roughness (alpha = r**2), clamped to [ROUGHNESS_MIN, 1].
        f0: Schlick Fresnel reflectance at normal incidence.
        specular: add the GGX term (else diffuse only).
        shadowing: "smith" (height-correlated, as the simulator) or "physg" (see ``sg.ggx_sg_lobe``).
        ndf_lobes: SGs approximating the GGX NDF (1, 2 or 3).
        specular_model: "sg" (the SG lobes of ``shade_sg``, module docstring) or "ggx_table" (the exact GGX
            lobe's moments, tabulated once: linear lights only need the lobe's zeroth and first moments).

    Returns:
        (N, 3, 3): [point, illumination (full_on, pos, neg), rgb], in white units (an albedo-1 Lambertian
        point under full_on is 1). Torch (differentiable) when any input is a tensor, else float32 numpy.
        No occlusion: every LED direction above the horizon is assumed visible.
    """
    as_numpy = not any(torch.is_tensor(x) for x in (normals, view_dirs, albedo, roughness))
    count = len(normals)
    n = _unit(_as_tensor("normals", normals, (count, 3)))
    v = _unit(_as_tensor("view_dirs", view_dirs, (count, 3)))
    alb = _as_tensor("albedo", albedo, (count, 3))
    r = _as_tensor("roughness", roughness, (count,))
    if specular_model not in SPECULAR_MODELS:
        raise ValueError(f"specular_model must be one of {SPECULAR_MODELS}, got {specular_model!r}")
    out = stage_diffuse(n, alb)
    if specular:
        out = out + _specular(n, v, r, f0, shadowing, ndf_lobes, specular_model)
    return out.detach().numpy() if as_numpy else out


def _specular(n, v, r, f0, shadowing, ndf_lobes, specular_model):
    if shadowing not in ("smith", "physg"):
        raise ValueError(f"shadowing must be 'smith' or 'physg', got {shadowing!r}")
    if specular_model == "ggx_table":
        return _stage_specular_table(n, v, r, f0, shadowing)
    return _stage_specular(n, v, r, f0, shadowing, ndf_lobes)


def _broadcast_white(white_scale, shape: tuple[int, int]) -> torch.Tensor:
    """white_scale as (P, V, 3): a scalar, (3,), (V, 3) or (P, V, 3); positive and finite."""
    w = np.asarray(white_scale, dtype=np.float32)
    p, v = shape
    if w.ndim == 0 or w.shape == (3,) or w.shape == (v, 3) or w.shape == (p, v, 3):
        w = np.broadcast_to(w if w.ndim else w.reshape(1), (p, v, 3))
    else:
        raise ValueError(f"white_scale must be a scalar, (3,), (V, 3) or (P, V, 3), got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ValueError("white_scale must be positive and finite")
    return torch.from_numpy(np.array(w, dtype=np.float32))  # a copy: broadcast views are read-only


def fit_roughness(observed, view_dirs, valid, normals, albedo, white_scale=1.0, r_min: float = 0.05,
                  r_max: float = 1.0, f0: float = 0.02, grid: int = 20, gauss_newton_steps: int = 4,
                  shadowing: str = "smith", ndf_lobes: int = 3, specular_model: str = "ggx_table",
                  fit_albedo: bool = False,
                  fallback_roughness: float | None = None, chunk: int = 8192, return_albedo: bool = False
                  ) -> tuple[np.ndarray, ...]:
    """Per-point GGX roughness from observations under full_on, pos and neg from several views.

    The model is ``white_scale * shade_stage_illuminations(n, v, albedo, r, f0)`` per (point, view); the fit
    minimises the squared error over valid views, illuminations and channels in white units
    (``observed / white_scale``). A grid search over ``grid`` roughness values in [r_min, r_max] picks the
    best per point, then ``gauss_newton_steps`` damped Gauss-Newton steps (central-difference Jacobians, a
    step kept only where it lowers the point's error) refine it; vectorised over points.

    Args:
        observed: (P, V, 3, 3) [point, view, illumination (full_on, pos, neg), rgb], decoded linear values.
        view_dirs: (P, V, 3) unit directions from the point towards each view's camera.
        valid: (P, V) bool: the view sees the point, unoccluded and unsaturated (others are ignored).
        normals: (P, 3) unit normals; albedo: (P, 3) diffuse albedo (fixed unless ``fit_albedo``).
        white_scale: decoded value of radiance 1 (a white Lambertian under full_on): scalar, (3,), (V, 3)
            per view (the cameras' ``white_reference``) or (P, V, 3).
        r_min, r_max: roughness bounds (0 < r_min < r_max <= 1).
        f0: Fresnel reflectance at normal incidence (0.02: skin, as the paper).
        grid, gauss_newton_steps: search grid size (>= 2) and refinement steps (>= 0).
        shadowing, ndf_lobes, specular_model: the specular model (see :func:`shade_stage_illuminations`).
            The default is the exact GGX moments ("ggx_table"): the illuminations are linear, so nothing
            needs the SG lobes here, and on observations rendered by the simulator's per-LED GGX they
            recover roughness to MAE ~0.01 (r in [0.3, 0.9]) where the SG lobes (7-15% specular error)
            are off by 0.1-0.15 around skin's r = 0.45 (bias -0.09 for views within 60 degrees of the
            normal, +0.14 within 70). Use "sg" to fit the same lobes ``shade_sg`` relights with.
        fit_albedo: also solve the diffuse albedo per point (closed form for each r) instead of fixing it;
            use when the albedo still holds specular light or occlusion.
        fallback_roughness: roughness given to points with no valid view; default the median of the fitted
            points (0.5 when none is fitted).
        chunk: points per block.
        return_albedo: also return the diffuse albedo (P, 3) the fit used: the solved one with
            ``fit_albedo`` (the white-light albedo with the specular light taken out), else ``albedo``.

    Returns:
        roughness (P,) float32 in [r_min, r_max]; residual (P,) float32, the RMS error of the fit over the
        point's valid views, illuminations and channels in white units, or :data:`NO_VIEWS_RESIDUAL` (-1)
        for points with no valid view (flagged: their roughness is the fallback); with ``return_albedo``
        also the albedo (P, 3) float32 (the input albedo where no view is valid).
    """
    obs = np.asarray(observed, dtype=np.float32)
    if obs.ndim != 4 or obs.shape[2:] != (3, 3):
        raise ValueError(f"observed must be (P, V, 3, 3), got {obs.shape}")
    p_count, v_count = obs.shape[:2]
    views = _as_tensor("view_dirs", view_dirs, (p_count, v_count, 3))
    mask = np.asarray(valid)
    if mask.shape != (p_count, v_count):
        raise ValueError(f"valid must be ({p_count}, {v_count}), got {mask.shape}")
    n_all = _unit(_as_tensor("normals", normals, (p_count, 3)))
    alb_all = _as_tensor("albedo", albedo, (p_count, 3))
    if not 0 < r_min < r_max <= ROUGHNESS_MAX or r_min < ROUGHNESS_MIN:
        raise ValueError(f"need {ROUGHNESS_MIN} <= r_min < r_max <= {ROUGHNESS_MAX}, got {r_min}, {r_max}")
    if specular_model not in SPECULAR_MODELS:
        raise ValueError(f"specular_model must be one of {SPECULAR_MODELS}, got {specular_model!r}")
    if grid < 2 or gauss_newton_steps < 0:
        raise ValueError("grid must be >= 2 and gauss_newton_steps >= 0")
    white = _broadcast_white(white_scale, (p_count, v_count))
    mask = mask.astype(bool) & np.all(np.isfinite(obs), axis=(2, 3))
    target_all = torch.as_tensor(np.nan_to_num(obs, nan=0.0, posinf=0.0, neginf=0.0)) / white[:, :, None, :]
    valid_all = torch.as_tensor(mask)
    has_views = mask.any(axis=1)

    roughness = np.zeros(p_count, np.float32)
    residual = np.full(p_count, NO_VIEWS_RESIDUAL, np.float32)
    albedo_out = alb_all.numpy().astype(np.float32).copy()
    grid_values = torch.linspace(r_min, r_max, grid)
    fitted_index = np.nonzero(has_views)[0]
    with torch.no_grad():
        for start in range(0, len(fitted_index), chunk):
            idx = torch.as_tensor(fitted_index[start:start + chunk])
            r_fit, rms, alb_fit = _fit_block(target_all[idx], views[idx], valid_all[idx], n_all[idx], alb_all[idx],
                                             grid_values, r_min, r_max, f0, gauss_newton_steps, shadowing, ndf_lobes,
                                             specular_model, fit_albedo)
            roughness[idx.numpy()] = r_fit
            residual[idx.numpy()] = rms
            albedo_out[idx.numpy()] = alb_fit
    if fallback_roughness is None:
        fallback_roughness = float(np.median(roughness[has_views])) if has_views.any() else 0.5
    roughness[~has_views] = np.clip(fallback_roughness, r_min, r_max)
    if return_albedo:
        return roughness, residual, albedo_out
    return roughness, residual


def _fit_block(target, views, valid, normals, albedo, grid_values, r_min, r_max, f0, steps, shadowing, ndf_lobes,
               specular_model, fit_albedo):
    """Grid search + Gauss-Newton for one block of points (all with at least one valid view)."""
    m, v_count = valid.shape
    weight = valid.to(torch.float32)[:, :, None, None]  # (m, V, 1, 1)
    n_rep = normals[:, None, :].expand(m, v_count, 3).reshape(-1, 3)
    v_flat = views.reshape(-1, 3)
    diffuse_unit = stage_diffuse(n_rep, torch.ones_like(n_rep)).reshape(m, v_count, 3, 3)  # per unit albedo
    count = weight.sum(dim=(1, 2, 3)) * 9.0  # residual entries per point

    def residuals(r: torch.Tensor, with_albedo: bool = False):
        """(m, V, 3, 3) weighted residuals for roughness r (m,) (and the albedo (m, 3) they used)."""
        spec = _specular(n_rep, v_flat, r[:, None].expand(m, v_count).reshape(-1), f0, shadowing, ndf_lobes,
                         specular_model).reshape(m, v_count, 3, 3)
        if fit_albedo:  # least-squares albedo per point and channel for this r (diffuse is linear in it)
            rest = (target - spec) * weight
            num = (rest * diffuse_unit).sum(dim=(1, 2))
            den = (diffuse_unit * diffuse_unit * weight).sum(dim=(1, 2)).clamp_min(1e-12)
            alb = (num / den).clamp_min(0.0)
        else:
            alb = albedo
        res = (target - spec - diffuse_unit * alb[:, None, None, :]) * weight
        return (res, alb) if with_albedo else res

    def loss(r: torch.Tensor) -> torch.Tensor:
        return (residuals(r) ** 2).sum(dim=(1, 2, 3))

    losses = torch.stack([loss(torch.full((m,), float(g))) for g in grid_values])  # (grid, m)
    best = losses.argmin(dim=0)
    r = grid_values[best].clone()
    current = losses.gather(0, best[None])[0]
    spacing = float(grid_values[1] - grid_values[0])
    h = 1e-3
    damping = torch.full((m,), 1e-6)
    for _ in range(steps):
        res = residuals(r)
        r_hi, r_lo = (r + h).clamp(r_min, r_max), (r - h).clamp(r_min, r_max)
        jac = (residuals(r_hi) - residuals(r_lo)) / (r_hi - r_lo)[:, None, None, None]
        g = (jac * res).sum(dim=(1, 2, 3))
        hess = (jac * jac).sum(dim=(1, 2, 3))
        step = (-g / (hess + damping + 1e-12)).clamp(-spacing, spacing)
        candidate = (r + step).clamp(r_min, r_max)
        new_loss = loss(candidate)
        better = new_loss < current
        r = torch.where(better, candidate, r)
        current = torch.where(better, new_loss, current)
        damping = torch.where(better, damping * 0.1, damping * 10.0 + hess)
    rms = torch.sqrt(current / count.clamp_min(1.0))
    _, alb = residuals(r, with_albedo=True)
    return r.numpy().astype(np.float32), rms.numpy().astype(np.float32), alb.numpy().astype(np.float32)

