"""Occlusion of distant light by a mesh: ambient occlusion, per-direction visibility, SG shading with shadows.

Pure numerics (numpy in, numpy out; :func:`shade_sg_visible` also takes torch). Rays are traced with an
open3d ``RaycastingScene`` (:func:`stages.numerics.raycast.mesh_scene`); light is distant (the LED sphere
or an environment at infinity), so a ray counts as occluded when it hits the mesh at **any** distance.
Every ray starts at ``point + offset_m * normal`` (1 mm, like the simulator's shadow rays) so that a point
does not shadow itself.

* :func:`ambient_occlusion`: the cosine-weighted visible fraction of the upper hemisphere,
  ``A(p) = 1/pi int_{H(n)} V(p, w) max(0, n.w) dw`` in [0, 1] (1 = unoccluded), by Monte Carlo with
  cosine-distributed directions (Malley's method): a ``rows x cols`` grid of strata over
  ``(sin^2 theta, azimuth)``, one jittered ray per stratum, the whole pattern turned by a random azimuth
  per point (no banding across neighbouring points). This is exactly the simulator's ``visibility`` map
  (the cosine-weighted visible fraction of a uniform LED sphere) and what the white-light albedo holds:
  ``observed albedo = albedo x A``.
* :func:`direction_visibility`: ``V(p, w_d)`` for a fixed set of directions (N, D) bool, True only where
  the direction is above the normal's horizon and unoccluded.
* :func:`shade_sg_visible`: :func:`stages.numerics.sg.shade_sg` with those visibilities.
* :func:`deocclude_normals`: photometric normals with the occlusion of the LED sphere divided out (below).

**Diffuse with occlusion.** With lobes ``G_l`` the occluded irradiance is
``E = sum_l int G_l(w) V(w) max(0, n.w) dw``. Each lobe keeps its closed-form unoccluded integral
(sg._cosine_integral, the one shade_sg uses) and is scaled by the *visible fraction of that lobe's
cosine-weighted energy*, estimated over the D directions:

    E = sum_l E_l^closed * (sum_d V_d G_l(w_d) c_d) / (sum_d G_l(w_d) c_d),   c_d = max(0, n.w_d).

The ratio is exactly 1 when every direction above the horizon is visible (so the result equals shade_sg
to rounding), exactly 0 when none is, never negative, and its error is only the quadrature error of a
*fraction* (the closed form carries the magnitude); a lobe narrower than the direction spacing takes the
visibility of its nearest directions (each lobe's weights are normalised to a maximum of 1 over the
directions, so they do not underflow). Numerator and denominator are two products ``(N, D) @ (D, L)``.
Measured against a fine quadrature (2e5 directions) of ``L V cos`` with analytic occluders (a half-space
wall and a 40-degree disc) under 32-lobe fits of three HDRIs (mean |error| / mean unoccluded E, 300
normals; a one-off measurement, test_shadowing.py checks a small case): at D = 256 this ratio
gives 1.1-1.7% on the smooth maps and 1.2-2.8% on studio_small_03 (small bright softboxes); plain
quadrature ``sum_d L V c 4pi/D`` gives 0.9-4.4% on the smooth maps but 70-150% on the studio map
(sharp lobes between directions), and the closed form minus the quadrature of the occluded directions
1.8-4.1% and 2.3-3.9% (up to 51% at D = 128). Capping the lobes' sharpness (blurring the visibility)
only made the ratio worse.

**Specular with occlusion.** The unoccluded specular of shade_sg is scaled per point and colour channel
by the visible fraction of ``f_s(w) max(0, n.w) L(w)`` over the directions, where ``f_s`` is the GGX SG
mixture of sg.ggx_sg_lobe around the reflection direction and ``L`` the environment, both with their
sharpness capped at ``sharpness_cap`` (default :func:`default_sharpness_cap` = ``2 D / pi``; amplitudes
rescaled to keep each lobe's energy) so that a shiny lobe or a sun between directions still meets a few
of them. Against the same reference (SG BRDF x L x V x cos, 200 points, r = 0.3 / 0.6) the error of the
occluded specular (mean |error| / mean unoccluded specular) is 1.1-4.0% at D = 256 (2.3-9.0% at
D = 128) with that cap, vs up to 20% uncapped at D = 128 and 2-15% with a cap of ``D / (4 pi)``.

**Photometric normals with occlusion.** Under the gradient pair ``L+-(w) = (1 +- w_c) / 2`` (channel ``c``
carries axis ``c``) a Lambertian point gives eq. 1's ratio ``d_c = int V w_c max(0, n.w) dw / int V max(0,
n.w) dw``: the albedo cancels, and ``d`` is the cosine-weighted mean of the *visible* directions, the bent
normal, which equals ``2/3 n`` only where nothing occludes. Where a limb or the other leg hides part of
the sphere, eq. 1's normal leans away from the occluder (a half-space wall at the horizon: 32.5 deg).
:func:`deocclude_normals` inverts this with the mesh's visibility: it finds ``n`` whose predicted deflection
``unit(b(n, V)) - unit(b(n, 1))`` (both by the same quadrature over the D directions, so the quadrature's
own error cancels) carries it onto the measured direction, by a fixed-point iteration. On the default
capture it brings the released ``normal_diffuse`` maps closer to the simulator's normals, most where much of
the cosine-weighted sphere is hidden (bench/bench_diffuse_normals.py measures it).

The visibility fractions are constants for autograd (visibility is discrete); gradients flow through
the closed-form lobes and shade_sg as usual.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from stages.numerics import numeric_threads
from stages.numerics.metrics import angular_error_deg
from stages.numerics.sg import (SGLobes, _chunk_f0, _cosine_integral, _is_torch, _one_minus_exp_over, _t, _unit,
                                check_lobes, ggx_sg_lobe, shade_sg)

__all__ = [
    "DEFAULT_AO_RAYS",
    "SHADOW_OFFSET_M",
    "ambient_occlusion",
    "direction_visibility",
    "default_sharpness_cap",
    "shade_sg_visible",
    "deocclude_normals",
    "deocclude_view",
]

#: Rays per point of :func:`ambient_occlusion`. On A0000's reconstructed mesh (100k surface points):
#: mean |AO(64) - AO(128)| = 0.015, |AO(128) - AO(256)| = 0.0095; 1.9 s per 100k points on one thread
#: (3.7 s at 128). Against the simulator's visibility maps the AO of the *true* mesh is off by 0.014 (64
#: rays) / 0.006 (256 rays) mean abs, that of our mesh by 0.024 / 0.019 (bias +0.015: the reconstruction
#: rounds off creases): at 64 rays the noise stays below our mesh's own error at half the cost of 128.
DEFAULT_AO_RAYS = 64
#: Ray origins sit this far along the normal (metres), like the simulator's shadow rays.
SHADOW_OFFSET_M = 1e-3
_RAYS_PER_BLOCK = 1 << 19  # ~12 MB of float32 rays per Embree call


def _check_points_normals(points, normals) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got shape {p.shape}")
    if n.shape != p.shape:
        raise ValueError(f"normals must be (N, 3) like points {p.shape}, got shape {n.shape}")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(n))):
        raise ValueError("points and normals must be finite (found NaN or Inf)")
    length = np.linalg.norm(n, axis=1)
    if np.any(length < 1e-8):
        raise ValueError(f"normals must be non-zero ({int(np.sum(length < 1e-8))} have zero length)")
    return p, n / length[:, None]


def _check_scene(scene) -> None:
    if not hasattr(scene, "test_occlusions"):
        raise ValueError(f"scene must be an open3d RaycastingScene (raycast.mesh_scene), got {type(scene).__name__}")


def _check_offset(offset_m: float) -> float:
    offset = float(offset_m)
    if not (math.isfinite(offset) and offset >= 0.0):
        raise ValueError(f"offset_m must be finite and >= 0, got {offset_m!r}")
    return offset


def _occluded(scene, rays: np.ndarray, threads: int) -> np.ndarray:
    import open3d as o3d

    return scene.test_occlusions(o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32)),
                                 nthreads=threads).numpy().astype(bool)


def _tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal tangents (N, 3), (N, 3) of unit normals (Duff et al. 2017, no branch on a fixed axis)."""
    x, y, z = normals[:, 0], normals[:, 1], normals[:, 2]
    sign = np.where(z >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    t1 = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=1)
    t2 = np.stack([b, sign + y * y * a, -y], axis=1)
    return t1, t2


def _strata(rays: int) -> tuple[int, int]:
    """(rows, cols) with rows * cols = rays and rows the largest divisor <= sqrt(rays)."""
    rows = int(math.isqrt(rays))
    while rays % rows:
        rows -= 1
    return rows, rays // rows


def ambient_occlusion(points, normals, scene, rays: int = DEFAULT_AO_RAYS, offset_m: float = SHADOW_OFFSET_M,
                      seed: int = 0, chunk: int | None = None, threads: int | None = None) -> np.ndarray:
    """Cosine-weighted visible fraction of each point's upper hemisphere (module docstring).

    Args:
        points: (N, 3) surface points (metres, world frame).
        normals: (N, 3) normals (normalised here; non-zero) defining the hemisphere.
        scene: an open3d ``RaycastingScene`` of the occluding mesh (:func:`raycast.mesh_scene`).
        rays: rays per point (>= 1), stratified over a ``rows x cols`` grid (:func:`_strata`).
        offset_m: ray origins are ``point + offset_m * normal``.
        seed: seeds the jitter and per-point rotation (results do not depend on ``chunk``).
        chunk: points per Embree call (default ~5e5 rays per call).
        threads: Embree threads (default :func:`stages.numerics.numeric_threads`).

    Returns:
        (N,) float32 in [0, 1]: 1 = unoccluded, 0 = every ray hits the mesh.
    """
    p, n = _check_points_normals(points, normals)
    _check_scene(scene)
    if isinstance(rays, bool) or int(rays) != rays or rays < 1:
        raise ValueError(f"rays must be an integer >= 1, got {rays!r}")
    rays = int(rays)
    offset = _check_offset(offset_m)
    count = len(p)
    block = max(1, _RAYS_PER_BLOCK // rays) if chunk is None else int(chunk)
    if block < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk!r}")
    threads = numeric_threads() if threads is None else int(threads)
    rows, cols = _strata(rays)
    cell_row = np.repeat(np.arange(rows), cols).astype(np.float64)  # (R,) stratum of sin^2(theta)
    cell_col = np.tile(np.arange(cols), rows).astype(np.float64)  # (R,) stratum of azimuth
    rng = np.random.default_rng(seed)
    out = np.empty(count, np.float32)
    for start in range(0, count, block):
        stop = min(start + block, count)
        m = stop - start
        # one draw per point row (2R jitters + 1 rotation): the stream does not depend on the chunking
        noise = rng.random((m, 2 * rays + 1))
        u1 = (cell_row + noise[:, :rays]) / rows  # sin^2(theta): cosine-weighted (Malley)
        u2 = (cell_col + noise[:, rays:2 * rays]) / cols + noise[:, 2 * rays:]
        radius = np.sqrt(u1)
        phi = 2.0 * math.pi * u2
        lx, ly, lz = radius * np.cos(phi), radius * np.sin(phi), np.sqrt(np.maximum(1.0 - u1, 0.0))
        nc = n[start:stop]
        t1, t2 = _tangent_frames(nc)
        dirs = lx[..., None] * t1[:, None] + ly[..., None] * t2[:, None] + lz[..., None] * nc[:, None]
        origins = p[start:stop] + offset * nc
        ray_block = np.empty((m, rays, 6), np.float32)
        ray_block[..., :3] = origins[:, None, :]
        ray_block[..., 3:] = dirs
        occluded = _occluded(scene, ray_block.reshape(-1, 6), threads).reshape(m, rays)
        out[start:stop] = 1.0 - occluded.mean(axis=1)
    return out


def direction_visibility(points, normals, scene, directions, offset_m: float = SHADOW_OFFSET_M,
                         chunk: int | None = None, threads: int | None = None) -> np.ndarray:
    """Which of a fixed set of distant directions each point sees.

    Args:
        points, normals: (N, 3) as in :func:`ambient_occlusion`.
        scene: open3d ``RaycastingScene`` of the occluder.
        directions: (D, 3) directions towards the light (normalised here; non-zero), e.g.
            ``sg.fibonacci_sphere(D)``.
        offset_m: ray origin offset along the normal (metres).
        chunk: points per Embree call (default ~5e5 rays per call).
        threads: Embree threads (default :func:`stages.numerics.numeric_threads`).

    Returns:
        (N, D) bool: True where ``n.w_d > 0`` and the ray towards ``w_d`` hits nothing; only those above
        the horizon are traced.
    """
    p, n = _check_points_normals(points, normals)
    _check_scene(scene)
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or len(d) < 1:
        raise ValueError(f"directions must be (D, 3) with D >= 1, got shape {d.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError("directions must be finite (found NaN or Inf)")
    length = np.linalg.norm(d, axis=1)
    if np.any(length < 1e-8):
        raise ValueError("directions must be non-zero")
    d = d / length[:, None]
    offset = _check_offset(offset_m)
    count, n_dirs = len(p), len(d)
    block = max(1, _RAYS_PER_BLOCK // n_dirs) if chunk is None else int(chunk)
    if block < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk!r}")
    threads = numeric_threads() if threads is None else int(threads)
    visible = np.zeros((count, n_dirs), dtype=bool)
    for start in range(0, count, block):
        stop = min(start + block, count)
        nc = n[start:stop]
        above = nc @ d.T > 0.0  # (m, D)
        pi, di = np.nonzero(above)
        if len(pi) == 0:
            continue
        rays = np.empty((len(pi), 6), np.float32)
        rays[:, :3] = (p[start:stop] + offset * nc)[pi]
        rays[:, 3:] = d[di]
        seen = np.zeros_like(above)
        seen[above] = ~_occluded(scene, rays, threads)
        visible[start:stop] = seen
    return visible


def default_sharpness_cap(n_directions: int) -> float:
    """Sharpness cap of the specular visibility weights for ``n_directions`` Fibonacci directions:
    ``2 D / pi``, i.e. a lobe width ``1 / sqrt(lambda)`` of a third of the direction spacing
    ``sqrt(4 pi / D)`` (the best of 0.5-16 x ``D / (4 pi)`` in the measurements of the module docstring)."""
    return 2.0 * n_directions / math.pi


def _energy_scale(sharp: torch.Tensor, capped: torch.Tensor) -> torch.Tensor:
    """Ratio of SG integrals ``I(sharp) / I(capped)`` with ``I(l) = 2 pi (1 - e^{-2l}) / l``: a capped lobe
    times it keeps the original lobe's energy."""
    return (_one_minus_exp_over(2.0 * sharp) / _one_minus_exp_over(2.0 * capped)).clamp_min(0.0)


def _visible_fraction(numerator: torch.Tensor, denominator: torch.Tensor) -> torch.Tensor:
    """numerator / denominator in [0, 1], 1 where the denominator vanishes (no light to occlude)."""
    ok = denominator > 1e-300
    return torch.where(ok, numerator / torch.where(ok, denominator, torch.ones_like(denominator)),
                       torch.ones_like(denominator)).clamp(0.0, 1.0)


def shade_sg_visible(normals, view_dirs, albedo, roughness, lobes: SGLobes, visibility, directions,
                     f0: float = 0.02, specular: bool = True, shadowing: str = "physg", ndf_lobes: int = 3,
                     sharpness_cap: float | None = None, chunk: int = 2048) -> dict:
    """:func:`sg.shade_sg` with occlusion of the environment (module docstring).

    Args:
        normals, view_dirs, albedo, roughness, lobes, f0, specular, shadowing, ndf_lobes: as in
            :func:`sg.shade_sg` (normals (N, 3), view_dirs (N, 3) towards the camera, albedo (N, 3),
            roughness (N,)).
        visibility: (N, D) bool, True = the point sees direction d (:func:`direction_visibility`; entries
            below the normal's horizon are ignored). Compute it with the same normals as used here.
        directions: (D, 3) unit directions of ``visibility``, roughly uniform over the sphere (a Fibonacci
            set, ``sg.fibonacci_sphere``).
        sharpness_cap: largest sharpness of the BRDF and light lobes that weight the specular visibility
            (default :func:`default_sharpness_cap` of D).
        chunk: points per block (memory ~ chunk x D x 40 bytes).

    Returns:
        dict of ``diffuse``, ``specular``, ``rgb`` (N, 3) radiance; torch tensors when any input is a tensor
        (differentiable except through the visibility fractions), else float32 numpy. Equal to shade_sg
        (to float rounding) when every direction above the horizon is visible; 0 when none is.
    """
    lobes = check_lobes(lobes)
    as_numpy = not _is_torch(normals, view_dirs, albedo, roughness, *lobes)
    n = _t(normals)
    if n.ndim != 2 or n.shape[1] != 3:
        raise ValueError(f"normals must be (N, 3), got {tuple(n.shape)}")
    count = n.shape[0]
    vis = visibility.detach().cpu().numpy() if torch.is_tensor(visibility) else np.asarray(visibility)
    if vis.dtype != bool:
        raise ValueError(f"visibility must be a bool array, got dtype {vis.dtype}")
    dirs = np.asarray(directions.detach().cpu().numpy() if torch.is_tensor(directions) else directions, np.float64)
    if dirs.ndim != 2 or dirs.shape[1] != 3 or len(dirs) < 1:
        raise ValueError(f"directions must be (D, 3) with D >= 1, got shape {dirs.shape}")
    if not np.all(np.isfinite(dirs)) or np.any(np.linalg.norm(dirs, axis=1) < 1e-8):
        raise ValueError("directions must be finite and non-zero")
    if vis.shape != (count, len(dirs)):
        raise ValueError(f"visibility must be (N, D) = ({count}, {len(dirs)}), got shape {vis.shape}")
    cap = default_sharpness_cap(len(dirs)) if sharpness_cap is None else float(sharpness_cap)
    if not (math.isfinite(cap) and cap > 0):
        raise ValueError(f"sharpness_cap must be finite and > 0, got {sharpness_cap!r}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk!r}")
    # unoccluded shading (validates the remaining inputs); its specular is scaled below
    base = shade_sg(normals, view_dirs, albedo, roughness, lobes, f0=f0, specular=specular, shadowing=shadowing,
                    ndf_lobes=ndf_lobes, chunk=chunk)
    base = {k: _t(v) for k, v in base.items()}
    alb = _t(albedo)
    n_unit = _unit(n)
    axis_l, sharp_l, amp_l = _unit(_t(lobes.axis)), _t(lobes.sharpness), _t(lobes.amplitude)
    n_lobes = axis_l.shape[0]
    with torch.no_grad():
        d64 = torch.as_tensor(dirs / np.linalg.norm(dirs, axis=1, keepdims=True), dtype=torch.float64)
        vis_t = torch.as_tensor(vis)
        sharp64, axis64 = sharp_l.detach().double(), axis_l.detach().double()
        # diffuse weights (D, L): every lobe at the directions, scaled to a maximum of 1 per lobe (the
        # fraction per lobe does not depend on that scale; a sharp lobe does not underflow)
        cos_dl = d64 @ axis64.T
        env_dl = torch.exp(sharp64 * (cos_dl - cos_dl.max(dim=0, keepdim=True).values))
        # specular weights (D, 3): lobes with capped sharpness, energy kept
        sharp_cap = sharp64.clamp(max=cap)
        env_rgb = torch.exp(sharp_cap * (cos_dl - 1.0)) @ (
            amp_l.detach().double() * _energy_scale(sharp64, sharp_cap)[:, None]).clamp_min(0.0)
    view_t, rough_t = _unit(_t(view_dirs)).detach(), _t(roughness).detach()
    diffuse_parts, spec_parts = [], []
    for start in range(0, count, chunk):
        sl = slice(start, min(start + chunk, count))
        nc = n_unit[sl]
        m = nc.shape[0]
        with torch.no_grad():
            cos = (nc.detach().double() @ d64.T).clamp_min(0.0)  # (m, D)
            cos_vis = cos * vis_t[sl]
            frac_diffuse = _visible_fraction(cos_vis @ env_dl, cos @ env_dl).to(n.dtype)  # (m, L)
        lobe_e = _cosine_integral(axis_l[None].expand(m, n_lobes, 3), sharp_l[None].expand(m, n_lobes),
                                  nc[:, None, :])  # (m, L), the same closed form as shade_sg
        diffuse_parts.append(alb[sl] * ((lobe_e * frac_diffuse) @ amp_l) / math.pi)
        if specular:
            with torch.no_grad():
                b_axis, b_sharp, b_weight = ggx_sg_lobe(nc.detach(), view_t[sl], rough_t[sl], _chunk_f0(f0, sl), shadowing,
                                                        ndf_lobes)
                b_sharp, b_weight = b_sharp.double(), b_weight.double()
                b_cap = b_sharp.clamp(max=cap)
                b_weight = b_weight * _energy_scale(b_sharp, b_cap)
                cos_axis = b_axis.double() @ d64.T  # (m, D)
                brdf = sum(b_weight[:, k:k + 1] * torch.exp(b_cap[:, k:k + 1] * (cos_axis - 1.0))
                           for k in range(b_sharp.shape[1]))  # (m, D)
                frac_spec = _visible_fraction((brdf * cos_vis) @ env_rgb, (brdf * cos) @ env_rgb).to(n.dtype)
            spec_parts.append(base["specular"][sl] * frac_spec)
    diffuse = torch.cat(diffuse_parts) if diffuse_parts else n.new_zeros((0, 3))
    spec = torch.cat(spec_parts) if spec_parts else torch.zeros_like(diffuse)
    out: dict[str, Any] = {"diffuse": diffuse, "specular": spec, "rgb": diffuse + spec}
    if as_numpy:
        out = {k: val.detach().numpy().astype(np.float32) for k, val in out.items()}
    return out


def _unit_rows(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def deocclude_normals(measured, visibility, directions, surface_normals, iterations: int = 24,
                      min_visible: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Photometric (eq. 1) normals with the occlusion of a uniform light sphere divided out (module docstring).

    Args:
        measured: (N, 3) measured normal directions (any length; rows of zeros stay zero).
        visibility: (N, D) bool from :func:`direction_visibility` for ``directions`` at the points.
        directions: (D, 3) the directions traced (normalised here).
        surface_normals: (N, 3) the normals ``visibility`` was traced with. Directions below their horizon
            count as unblocked: the surface's own tangent plane is no occluder, and the candidate normal's
            cosine already drops what lies below *its* horizon.
        iterations: at most this many fixed-point steps ``n <- unit(n + a (m - p(n)))`` with the prediction
            ``p(n) = unit(n + unit(b(n, V)) - unit(b(n, 1)))``, ``b(n, V) = sum_d V_d max(0, n.w_d) w_d``, and a
            step ``a`` per point that is halved whenever it does not bring ``p(n)`` closer to ``m`` (strongly
            occluded points otherwise oscillate). Convergence is linear: a half-space wall is 4.2 deg off after
            4 steps, 0.15 after 12, 0.04 after 24; points stop once converged (the residual angle is returned).
        min_visible: points whose cosine-weighted visible fraction (around the measured normal) is below
            this keep the measured normal: almost nothing lights them, so the model has little to invert.

    Returns:
        normals (N, 3) float32 unit (zero where ``measured`` is zero), and the residual (N,) float32: the angle
        in degrees between the measured direction and the direction the returned normal predicts (0 where
        left unchanged).
    """
    m = np.asarray(measured, dtype=np.float64)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"measured must be (N, 3), got shape {m.shape}")
    count = len(m)
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or len(d) < 4:
        raise ValueError(f"directions must be (D, 3) with D >= 4, got shape {d.shape}")
    v = np.asarray(visibility)
    if v.shape != (count, len(d)):
        raise ValueError(f"visibility must be (N, D) = {(count, len(d))}, got shape {v.shape}")
    s = np.asarray(surface_normals, dtype=np.float64)
    if s.shape != (count, 3):
        raise ValueError(f"surface_normals must be (N, 3) = {(count, 3)}, got shape {s.shape}")
    if not (np.isfinite(m).all() and np.isfinite(d).all() and np.isfinite(s).all()):
        raise ValueError("measured, directions and surface_normals must be finite (found NaN or Inf)")
    if int(iterations) < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations!r}")
    if not 0.0 <= float(min_visible) < 1.0:
        raise ValueError(f"min_visible must be in [0, 1), got {min_visible!r}")
    d = _unit_rows(d)
    defined = np.linalg.norm(m, axis=-1) > 1e-9
    m = _unit_rows(m)
    open_ = v.astype(bool) | (s @ d.T <= 0.0)  # (N, D)
    d32 = d.astype(np.float32)

    def deflected(n: np.ndarray, vis: np.ndarray) -> np.ndarray:
        cos = np.maximum(n.astype(np.float32) @ d32.T, 0.0)
        return _unit_rows(n + _unit_rows((cos * vis) @ d32).astype(np.float64) - _unit_rows(cos @ d32))

    cos_m = np.maximum(m @ d.T, 0.0)
    visible_fraction = (cos_m * open_).sum(1) / np.maximum(cos_m.sum(1), 1e-12)
    work = np.flatnonzero(defined & (visible_fraction >= float(min_visible)))
    n = m.copy()
    residual = np.zeros(count)
    if len(work):
        mw, vis = m[work], open_[work].astype(np.float32)
        nw = mw.copy()
        pred = deflected(nw, vis)
        miss = np.linalg.norm(pred - mw, axis=-1)
        step = np.ones(len(mw))
        for _ in range(int(iterations)):
            # Damped per point: where a step does not bring the prediction closer, it is halved and retried
            # (strongly occluded points otherwise oscillate). Converged points (1e-6 rad) are left alone.
            live = np.flatnonzero(miss > 1e-6)
            if len(live) == 0:
                break
            trial = _unit_rows(nw[live] + step[live, None] * (mw[live] - pred[live]))
            trial_pred = deflected(trial, vis[live])
            trial_miss = np.linalg.norm(trial_pred - mw[live], axis=-1)
            better = trial_miss < miss[live]
            take = live[better]
            nw[take], pred[take], miss[take] = trial[better], trial_pred[better], trial_miss[better]
            step[live] = np.where(better, np.minimum(step[live] * 1.5, 1.0), step[live] * 0.5)
        n[work] = nw
        residual[work] = angular_error_deg(pred, mw)
    n[~defined] = 0.0
    return n.astype(np.float32), residual.astype(np.float32)


def deocclude_view(scene, K: np.ndarray, cam_from_world: np.ndarray, normals: np.ndarray, directions: int = 256,
                   min_visible: float = 0.1, seen: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, dict[str, float]]:
    """One camera's (H, W, 3) photometric ``normals`` with the occlusion by the mesh in ``scene`` divided out
    (:func:`deocclude_normals`) where the mesh covers a pixel whose normal is defined (non-zero); elsewhere
    unchanged. The visibility is traced from the mesh's surface point of each pixel along its face normal,
    over ``directions`` Fibonacci directions.

    Returns the (H, W, 3) float32 normals and statistics: ``occlusion_pixels_fraction`` (share of the defined
    pixels the mesh covers), ``occlusion_correction_mean_deg`` (mean turn of those pixels' normals),
    ``occlusion_residual_mean_deg`` (mean fixed-point residual). ``seen``: the scene's
    :func:`stages.numerics.raycast.render_mesh` from this camera at the normals' size, when the caller has it.
    """
    from stages.numerics.raycast import camera_rays, render_mesh
    from stages.numerics.sg import fibonacci_sphere

    normals = np.asarray(normals)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise ValueError(f"normals must be (H, W, 3), got shape {normals.shape}")
    h, w = normals.shape[:2]
    finite = np.isfinite(normals).all(axis=-1)
    out = np.where(finite[..., None], normals, 0.0).astype(np.float32)
    defined = np.any(out != 0, axis=-1)
    if seen is None:
        seen = render_mesh(None, None, K, cam_from_world, h, w, scene=scene)
    elif seen["depth_m"].shape != (h, w):
        raise ValueError(f"seen was rendered at {seen['depth_m'].shape}, the normals are {(h, w)}")
    todo = defined & seen["hit"]
    stats = {"occlusion_pixels_fraction": float(todo.sum() / max(int(defined.sum()), 1)),
             "occlusion_correction_mean_deg": 0.0, "occlusion_residual_mean_deg": 0.0}
    if not todo.any():
        return out, stats
    rows, cols = np.nonzero(todo)
    origins, rays, z_per_t = camera_rays(K, cam_from_world, h, w, pixels=np.stack([cols, rows], -1).astype(np.float64))
    points = origins + rays * (seen["depth_m"][rows, cols] / z_per_t)[:, None]
    surface = seen["normals_world"][rows, cols].astype(np.float64)
    dirs = fibonacci_sphere(int(directions)).astype(np.float64)
    visible = direction_visibility(points, surface, scene, dirs)
    before = _unit_rows(out[rows, cols].astype(np.float64))
    fixed, residual = deocclude_normals(before, visible, dirs, surface, min_visible=min_visible)
    out[rows, cols] = fixed
    turned = angular_error_deg(before, fixed)
    stats["occlusion_correction_mean_deg"] = float(turned.mean())
    stats["occlusion_residual_mean_deg"] = float(residual.mean())
    return out, stats
