"""Shading by a discrete sum over the visibility directions: the environment as distant lights, each occluded per point.

The SG closed forms of :func:`stages.numerics.shadowing.shade_sg_visible` shade every lobe analytically and scale it
by a visible fraction estimated over D directions; the sum here instead puts the environment's energy on those same
D directions (the ones :func:`stages.numerics.shadowing.direction_visibility` already traces per pixel) and sums
Lambertian + GGX over them with each direction's own visibility, as the simulator renders its ground truth (it sums
2048 such lights, :func:`synthetic.relight.environment_lights`). It costs no extra ray: only the (N, D) products.

* :func:`sg_direction_irradiance`: the irradiance (D, 3) each direction carries, ``E_d = int_{cell d} L(w) dw`` over
  the direction's Voronoi cell on the sphere (nearest direction), for an environment given as SG lobes. Each lobe's
  exact energy (:func:`stages.numerics.sg.sg_integral`) is split between the cells in proportion to the lobe's
  values at ``samples`` Fibonacci points per direction (so no lobe's energy is lost, however sharp).
* :func:`split_key_lights`: the environment's sharpest bright lobes (a studio's key light, a sun) taken out of the
  cells as distant point lights at their own axes, each with its own traced visibility (a few rays per pixel). Put
  on the cells, such a lobe lights and shadows from its cell's direction, up to half a cell (about 7 degrees at 256
  directions) away from where it is: its shadows' edges and its highlights move by that much.
* :func:`shade_directions`: ``albedo / pi sum_d V_d max(0, n.w_d) E_d`` and ``sum_d V_d f_s(w_d) max(0, n.w_d) E_d``
  with the GGX BRDF ``f_s = F D G / (4 n.l n.v)`` (Schlick Fresnel, alpha = roughness^2, the shadowing term
  "smith" (height-correlated, the simulator's) or "physg" (separable Schlick-GGX, k = (r + 1)^2 / 8), as
  :func:`stages.numerics.sg.ggx_sg_lobe`).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from stages.numerics.sg import ROUGHNESS_MAX, ROUGHNESS_MIN, SGLobes, check_lobes, fibonacci_sphere, sg_integral

__all__ = ["sg_direction_irradiance", "sg_cell_lights", "split_key_lights", "shade_directions", "SHADOWING_TERMS"]

SHADOWING_TERMS = ("physg", "smith")
"""The GGX shadowing-masking terms :func:`shade_directions` knows."""


def _unit_directions(directions, name: str = "directions") -> np.ndarray:
    d = np.asarray(directions, np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or len(d) < 1:
        raise ValueError(f"{name} must be (D, 3) with D >= 1, got shape {d.shape}")
    length = np.linalg.norm(d, axis=1)
    if not np.all(np.isfinite(d)) or np.any(length < 1e-8):
        raise ValueError(f"{name} must be finite and non-zero")
    return d / length[:, None]


def sg_direction_irradiance(lobes: SGLobes, directions, samples: int = 64) -> np.ndarray:
    """The environment ``lobes`` integrated over each direction's Voronoi cell: (D, 3) float64 irradiance (radiance x
    steradians) a surface facing the direction receives from its cell; the rows sum to the lobes' integral.

    Args:
        lobes: SG lobes (numpy or torch; L lobes), world frame.
        directions: (D, 3) directions (normalised here), e.g. ``sg.fibonacci_sphere(D)``.
        samples: Fibonacci points per direction that split each lobe's energy between the cells (>= 1).
    """
    return sg_cell_lights(lobes, directions, samples)[0]


def sg_cell_lights(lobes: SGLobes, directions, samples: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Each direction's cell as one distant light: its irradiance (D, 3) float64 (:func:`sg_direction_irradiance`)
    and the unit direction (D, 3) float64 its energy comes from on average (the cell's sample points weighted by the
    lobes' energy there, RGB summed; the direction itself where the cell holds no energy). A light that fills a
    cell unevenly (a lobe near the cell's edge) then lights from where its energy is, not from the cell's centre;
    its visibility stays the cell direction's.

    Args: as :func:`sg_direction_irradiance`.
    """
    lobes = check_lobes(lobes).numpy()
    d = _unit_directions(directions)
    if int(samples) != samples or samples < 1:
        raise ValueError(f"samples must be a positive integer, got {samples!r}")
    if lobes.count == 0:  # every lobe taken out as a key light (split_key_lights)
        return np.zeros((len(d), 3)), d
    points = fibonacci_sphere(int(samples) * len(d))
    _, cell = cKDTree(d).query(points)
    axis = np.asarray(lobes.axis, np.float64)
    axis = axis / np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    sharp = np.asarray(lobes.sharpness, np.float64)
    # each lobe at the points, scaled to a maximum of 1 (a sharp lobe does not underflow; the share does not
    # depend on the scale), summed per cell
    cos = points @ axis.T  # (S, L)
    value = np.exp(sharp[None] * (cos - cos.max(axis=0, keepdims=True)))
    per_cell = np.stack([np.bincount(cell, weights=value[:, k], minlength=len(d)) for k in range(len(sharp))], axis=1)
    total = np.maximum(per_cell.sum(axis=0, keepdims=True), 1e-300)
    share = per_cell / total  # (D, L), columns sum to 1
    energy = np.asarray(sg_integral(lobes), np.float64)  # (L, 3)
    irradiance = np.nan_to_num(share @ energy, nan=0.0, posinf=0.0, neginf=0.0)
    # each point's share of the energy (RGB summed) of every lobe, summed: the cells' energy-weighted mean points
    point_energy = (value / total) @ np.maximum(energy.sum(axis=1), 0.0)  # (S,)
    centroid = np.stack([np.bincount(cell, weights=point_energy * points[:, c], minlength=len(d))
                         for c in range(3)], axis=1)
    length = np.linalg.norm(centroid, axis=1, keepdims=True)
    light_dirs = np.where(length > 0.0, centroid / np.where(length > 0.0, length, 1.0), d)
    return irradiance, light_dirs


def split_key_lights(lobes: SGLobes, count: int, min_sharpness: float) -> tuple[SGLobes, np.ndarray, np.ndarray]:
    """The environment's key lights: of the lobes at least ``min_sharpness`` sharp, the ``count`` that carry the most
    energy (their :func:`stages.numerics.sg.sg_integral` summed over RGB; lobes without energy are never taken),
    each taken out of ``lobes`` as a distant point light at its axis carrying the lobe's whole energy.

    A lobe of sharpness ``lambda`` spreads about ``1 / sqrt(lambda)`` radians about its axis (5.7 degrees at 100): far
    narrower than a cell of 256 visibility directions (about 7 degrees to its edge), so it shades and shadows as a
    point light at its axis.

    Args:
        lobes: SG lobes (numpy or torch; L lobes), world frame.
        count: most key lights (>= 0; 0 takes none).
        min_sharpness: > 0, the least sharpness of a key light.

    Returns:
        ``(rest, directions, irradiance)``: the other lobes (:class:`~stages.numerics.sg.SGLobes`, numpy, in their
        order), the key lights' unit directions (M, 3) float64 and irradiance (M, 3) float64 (radiance x
        steradians), M <= ``count``, brightest first.
    """
    lobes = check_lobes(lobes).numpy()
    if int(count) != count or count < 0:
        raise ValueError(f"count must be a non-negative integer, got {count!r}")
    if not (np.isfinite(min_sharpness) and min_sharpness > 0):
        raise ValueError(f"min_sharpness must be positive, got {min_sharpness!r}")
    energy = np.asarray(sg_integral(lobes), np.float64)  # (L, 3)
    total = energy.sum(axis=1)
    candidates = np.flatnonzero((np.asarray(lobes.sharpness) >= min_sharpness) & (total > 0))
    key = candidates[np.argsort(-total[candidates], kind="stable")][:int(count)]
    rest = np.setdiff1d(np.arange(lobes.count), key)
    axis = np.asarray(lobes.axis, np.float64)[key].reshape(-1, 3)
    axis = axis / np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    others = SGLobes(lobes.axis[rest], lobes.sharpness[rest], lobes.amplitude[rest])
    return others, axis, energy[key].reshape(-1, 3)


def _ggx(nl: np.ndarray, nv: np.ndarray, vl: np.ndarray, rough: np.ndarray, f0: np.ndarray, shadowing: str
         ) -> np.ndarray:
    """GGX BRDF x cosine ``F D G / (4 n.v) `` at (m, D) light cosines ``nl`` (>= 0), view cosines ``nv`` (m, 1) and
    view-light cosines ``vl`` (m, D); roughness, f0 (m, 1)."""
    alpha = rough * rough
    a2 = alpha * alpha
    one_plus = np.maximum(1.0 + vl, 1e-6)
    nh2 = np.minimum((nl + nv) ** 2 / (2.0 * one_plus), 1.0)
    denom = nh2 * (a2 - 1.0) + 1.0
    distribution = a2 / (math.pi * denom * denom)
    f = 1.0 - np.sqrt(0.5 * one_plus)
    f2 = f * f
    fresnel = f0 + (1.0 - f0) * (f2 * f2 * f)
    if shadowing == "smith":  # G2 / (4 nl nv), height-correlated
        vis = 0.5 / (nl * np.sqrt(nv * nv * (1.0 - a2) + a2) + nv * np.sqrt(nl * nl * (1.0 - a2) + a2))
    else:  # Schlick-GGX G1(l) G1(v) / (4 nl nv)
        k = (rough + 1.0) ** 2 / 8.0
        vis = 1.0 / (4.0 * (nl * (1.0 - k) + k) * (nv * (1.0 - k) + k))
    return fresnel * distribution * vis * nl


def shade_directions(normals, view_dirs, albedo, roughness, irradiance, visibility, directions,
                     f0: float | np.ndarray = 0.02, specular: bool = True, shadowing: str = "physg",
                     chunk: int = 4096) -> dict[str, np.ndarray]:
    """Lambertian + GGX radiance under distant lights at ``directions``, each occluded per point (module docstring).

    Args:
        normals, view_dirs (towards the camera): (N, 3) unit; albedo (N, 3) linear diffuse albedo; roughness (N,)
            perceptual, clamped to [ROUGHNESS_MIN, ROUGHNESS_MAX].
        irradiance: (D, 3) per direction (:func:`sg_direction_irradiance`), >= 0.
        visibility: (N, D) bool (:func:`stages.numerics.shadowing.direction_visibility`; directions below the
            normal's horizon count as dark whatever it says).
        directions: (D, 3) light directions (normalised here).
        f0: Fresnel reflectance at normal incidence, scalar or (N,).
        specular: add the GGX term; shadowing: its shadowing-masking term, one of :data:`SHADOWING_TERMS`.
        chunk: points per block (memory ~ chunk x D x 8 bytes x a few).

    Returns:
        ``diffuse``, ``specular``, ``rgb`` (N, 3) float32, finite and >= 0.
    """
    n = np.asarray(normals, np.float64)
    if n.ndim != 2 or n.shape[1] != 3:
        raise ValueError(f"normals must be (N, 3), got shape {n.shape}")
    count = len(n)
    v = np.asarray(view_dirs, np.float64)
    alb = np.asarray(albedo, np.float64)
    rough = np.clip(np.asarray(roughness, np.float64), ROUGHNESS_MIN, ROUGHNESS_MAX)
    if v.shape != (count, 3) or alb.shape != (count, 3) or rough.shape != (count,):
        raise ValueError(f"view_dirs {v.shape}, albedo {alb.shape} (N, 3) and roughness {rough.shape} (N,) must "
                         f"match normals ({count}, 3)")
    d = _unit_directions(directions)
    irr = np.asarray(irradiance, np.float64)
    if irr.shape != (len(d), 3) or not np.all(np.isfinite(irr)) or np.any(irr < 0):
        raise ValueError(f"irradiance must be finite, >= 0 and ({len(d)}, 3), got shape {irr.shape}")
    vis = np.asarray(visibility)
    if vis.dtype != bool or vis.shape != (count, len(d)):
        raise ValueError(f"visibility must be bool ({count}, {len(d)}), got {vis.dtype} {vis.shape}")
    if shadowing not in SHADOWING_TERMS:
        raise ValueError(f"shadowing must be one of {SHADOWING_TERMS}, got {shadowing!r}")
    f0 = np.broadcast_to(np.asarray(f0, np.float64), (count,)) if np.ndim(f0) else np.full(count, float(f0))
    if f0.shape != (count,):
        raise ValueError(f"f0 must be a scalar or ({count},), got shape {np.shape(f0)}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk!r}")
    diffuse = np.zeros((count, 3))
    spec = np.zeros((count, 3))
    for start in range(0, count, chunk):
        sl = slice(start, min(start + chunk, count))
        nl = np.maximum(n[sl] @ d.T, 0.0) * vis[sl]  # (m, D)
        diffuse[sl] = alb[sl] / math.pi * (nl @ irr)
        if specular:
            nv = np.maximum(np.sum(n[sl] * v[sl], axis=1, keepdims=True), 1e-3)
            brdf = _ggx(nl, nv, v[sl] @ d.T, rough[sl, None], f0[sl, None], shadowing)
            brdf *= (np.sum(n[sl] * v[sl], axis=1) > 0)[:, None]  # the view below the horizon sees no highlight
            spec[sl] = brdf @ irr
    out = {"diffuse": diffuse, "specular": spec, "rgb": diffuse + spec}
    return {k: np.nan_to_num(np.maximum(x, 0.0), nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
            for k, x in out.items()}
