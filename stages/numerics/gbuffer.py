"""G-buffers (world normal + albedo maps) for a new camera by depth-guided reprojection of captured views.

Pure numerics, arrays in and arrays out; conventions of docs/CONTRACTS.md (world = stage frame, metres;
OpenCV cameras, ``x_cam = R x_world + t``, pixel index ``i`` at continuous coordinate ``u = i``; images
``(H, W[, C])`` float32, row 0 at the top).

For each target pixel with a surface depth (rendered from the mesh or the SDF by the caller, e.g.
:func:`stages.numerics.raycast.render_mesh`) the surface point is lifted to the world, projected into the
``k`` captured views nearest to the target camera and looked up there bilinearly. A source contributes
only where the point is *visible* in it: each of the four bilinear taps is used only when the source's own
mesh depth at that tap agrees with the point's depth in the source camera (within ``depth_tolerance_m``)
and the source map is valid there; the bilinear weights are renormalised over the taps used, so the colour
or normal of an occluder in front of the point never leaks in. The sum of the used taps' bilinear weights
(in [0, 1]) is the source's soft visibility of the point.

The contributions are blended with per-source weights (``weighting``):

- ``"uniform"``: visibility only;
- ``"angle"``: visibility times ``exp(-theta^2 / (2 sigma^2))``, ``theta`` the angle at the point between
  the rays to the target and to the source camera centres (a view seeing the point from the same
  direction sees the same thing: same foreshortening, same view-dependent residue in the maps);
- ``"angle_distance"``: also times ``(f_s / d_s)^2 / (f_t / d_t)^2``, the source's sampling density of
  the surface (focal length in pixels over distance to the point) relative to the target's, so a farther
  or wider camera, which blurs the surface more, counts less;
- ``"angle_distance_grazing"``: also times ``max(n_s . v_s, 0)``, the cosine between the source's own
  (sampled) normal and its ray to the camera: photometric normals and albedo degrade toward the
  silhouette (foreshortened, mixed pixels), so grazing observations count less.

A source's pixels on either side of its own occlusion edges (within ``source_edge_px`` of a jump over
``source_edge_jump_m`` in its mesh depth, :func:`depth_edges`; not its silhouette against the background, which
its valid mask already trims) hold a mix of the occluder and the surface behind it: the camera's footprint,
optics and demosaicing blur across the jump, and the depth test, which keeps an occluder's own pixels out,
cannot tell. Their taps count :data:`SOURCE_EDGE_WEIGHT` of a tap off the edge in a source's soft visibility
(the sample itself stays the plain interpolation), so another source that sees the point clearly outweighs
that source and a point seen only there keeps it. On the default capture's held-out views (1 px, 0.05 m) the
albedo SSIM against the photometric maps is 0.9756 (0.9745 with every pixel alike) and the specular-free
normals 3.61 deg off (3.66); on the procedural subject, whose arms and belt occlude its torso in every view,
the SSIM is 0.9696 (0.9675).

A source map is read at the point's projection with Keys' cubic convolution (Catmull-Rom) where all 16
taps of the 4 x 4 neighbourhood are visible and valid, bilinearly elsewhere (``interpolation="bilinear"``
everywhere): the bilinear kernel low-passes the source texture once more. On the default capture's held-out
views cubic raises the albedo SSIM, against the photometric maps and the simulator's truth, for about twice
the lookup time (bench/bench_gbuffer.py measures both lookups). Negative lobes can overshoot: the albedo
sample is clamped at 0 (the blended normal is renormalised anyway).

A trained :class:`stages.numerics.learned_blend.LearnedBlend` (``blend``) replaces the heuristic weights by
learned ones per pixel; :func:`source_candidates` gives its input, each source's samples and terms before
blending.

Normals are blended as vectors and renormalised; albedo is blended linearly (same scale as the sources).
The default is ``"angle_distance_grazing"``: on the held-out views of the default simulated capture it
scores best against the simulator's truth (bench/bench_gbuffer.py compares the four). No output holds NaN
or Inf.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from artifacts.camera import as_pose, camera_centre, lift_points, pixel_coordinates

__all__ = ["SourceView", "WEIGHTINGS", "INTERPOLATIONS", "nearest_views", "source_candidates",
           "reproject_gbuffer", "fuse_normals", "fade_rim_normals", "shading_normals", "interpolate_camera",
           "novel_camera_pairs"]

WEIGHTINGS = ("uniform", "angle", "angle_distance", "angle_distance_grazing")
INTERPOLATIONS = ("bilinear", "cubic")
SOURCE_EDGE_PX = 1
"""Default radius of the sources' occlusion edges (:func:`depth_edges`) whose pixels count for little."""
SOURCE_EDGE_JUMP_M = 0.05
"""Default depth jump of a source's occlusion edge, metres."""
SOURCE_EDGE_WEIGHT = 0.01
"""What a tap on a source's occlusion edge counts in that source's soft visibility, relative to a tap off it."""


@dataclass(frozen=True)
class SourceView:
    """One captured view used as a source of reprojection.

    Attributes:
        normal: (H, W, 3) float32 unit world normals (0 where undefined).
        albedo: (H, W, 3) float32 linear sRGB albedo.
        valid: (H, W) bool where the maps hold data (e.g. photometric alpha > 0.5 and the subject mask).
        K: (3, 3) intrinsics. cam_from_world: (3, 4) ``[R | t]``.
        depth_m: (H, W) float32 camera z of the mesh seen by this camera (0 where no surface): the
            visibility test compares against it.
    """

    normal: np.ndarray
    albedo: np.ndarray
    valid: np.ndarray
    K: np.ndarray
    cam_from_world: np.ndarray
    depth_m: np.ndarray


def _intrinsics(K: np.ndarray, name: str = "K") -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"{name} must be (3, 3), got {K.shape}")
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"{name} must be finite with positive focal lengths, got {K.tolist()}")
    return K


def nearest_views(target_cam_from_world: np.ndarray, source_cam_from_worlds: Sequence[np.ndarray] | np.ndarray,
                  k: int = 6, subject_centre: np.ndarray | Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Indices of the ``k`` sources whose direction from the subject is closest to the target's.

    The angle compared is the one at ``subject_centre`` between the directions to the camera centres
    (not between the optical axes): two cameras that look at the subject from the same side see the same
    surface with the same foreshortening even when their axes are tilted differently, and on a light
    stage every camera looks at the stage centre (the world origin, the default), so this is the
    angle the per-pixel blend weights use, evaluated at the centre of the subject.

    Args:
        target_cam_from_world: (3, 4) target camera.
        source_cam_from_worlds: (N, 3, 4) (or a list of (3, 4)) source cameras.
        k: how many; ``min(k, N)`` are returned.
        subject_centre: (3,) world point the directions start from.

    Returns:
        (min(k, N),) int64 indices into the sources, nearest first (ties by index).
    """
    if int(k) != k or k < 1:
        raise ValueError(f"k must be a positive integer, got {k}")
    target = as_pose(target_cam_from_world, "target_cam_from_world")
    sources = [as_pose(P, f"source_cam_from_worlds[{i}]") for i, P in enumerate(source_cam_from_worlds)]
    if not sources:
        raise ValueError("nearest_views: no source cameras")
    centre = np.asarray(subject_centre, dtype=np.float64)
    if centre.shape != (3,) or not np.all(np.isfinite(centre)):
        raise ValueError(f"subject_centre must be a finite (3,) point, got {centre!r}")

    def direction(P: np.ndarray) -> np.ndarray:
        d = camera_centre(P) - centre
        n = np.linalg.norm(d)
        if n < 1e-9:
            raise ValueError("a camera centre coincides with subject_centre: no viewing direction")
        return d / n

    t = direction(target)
    angles = np.array([np.arctan2(np.linalg.norm(np.cross(t, direction(P))), float(t @ direction(P)))
                       for P in sources])
    return np.argsort(angles, kind="stable")[: min(int(k), len(sources))].astype(np.int64)


def _check_source(i: int, s: SourceView) -> tuple[np.ndarray, ...]:
    depth = np.asarray(s.depth_m, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"sources[{i}].depth_m must be (H, W), got {depth.shape}")
    h, w = depth.shape
    normal = np.asarray(s.normal, dtype=np.float32)
    albedo = np.asarray(s.albedo, dtype=np.float32)
    valid = np.asarray(s.valid).astype(bool, copy=False)
    for name, arr, shape in (("normal", normal, (h, w, 3)), ("albedo", albedo, (h, w, 3)), ("valid", valid, (h, w))):
        if arr.shape != shape:
            raise ValueError(f"sources[{i}].{name} must be {shape} like its depth_m, got {arr.shape}")
    # sanitise: undefined values never travel into the blend
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    finite = np.all(np.isfinite(normal), axis=-1) & np.all(np.isfinite(albedo), axis=-1)
    valid = valid & finite & (depth > 0)
    normal = np.nan_to_num(normal, nan=0.0, posinf=0.0, neginf=0.0)
    albedo = np.nan_to_num(albedo, nan=0.0, posinf=0.0, neginf=0.0)
    return normal, albedo, valid, depth, _intrinsics(s.K, f"sources[{i}].K"), as_pose(s.cam_from_world, f"sources[{i}].cam_from_world")


def _keys_weights(t: np.ndarray, a: float = -0.5) -> tuple[np.ndarray, ...]:
    """Keys' cubic convolution weights (a = -0.5, Catmull-Rom) of the taps at offsets -1, 0, 1, 2 from the
    sample's floor, for fractional positions ``t`` (N,) in [0, 1); they sum to 1."""
    t2, t3 = t * t, t * t * t
    return (a * (t3 - 2 * t2 + t), (a + 2) * t3 - (a + 3) * t2 + 1,
            -(a + 2) * t3 + (2 * a + 3) * t2 - a * t, -a * (t3 - t2))


def depth_edges(depth_m: np.ndarray, radius_px: int = SOURCE_EDGE_PX,
                jump_m: float = SOURCE_EDGE_JUMP_M) -> np.ndarray:
    """The surface pixels of a depth map that lie within ``radius_px`` of an occlusion edge: another surface
    pixel in their (2 r + 1)^2 neighbourhood is nearer or farther by more than ``jump_m``.

    A camera pixel on either side of an occlusion edge mixes both surfaces (its footprint, the optics, the
    demosaicing), so its photometric albedo and normal belong to neither; the silhouette against the
    background (depth 0) is not an edge here (the maps' alpha already marks it).

    Args:
        depth_m: (H, W) camera z of the surface (0 = none).
        radius_px: neighbourhood radius (0: no pixel is an edge).
        jump_m: the depth difference that makes an edge, metres (> 0).

    Returns:
        (H, W) bool.
    """
    from scipy.ndimage import maximum_filter, minimum_filter

    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got {depth.shape}")
    if int(radius_px) != radius_px or radius_px < 0:
        raise ValueError(f"radius_px must be a non-negative integer, got {radius_px}")
    if not (jump_m > 0) or not np.isfinite(jump_m):
        raise ValueError(f"jump_m must be positive, got {jump_m}")
    surface = np.isfinite(depth) & (depth > 0)
    if radius_px == 0 or not surface.any():
        return np.zeros(depth.shape, bool)
    size = 2 * int(radius_px) + 1
    nearest = minimum_filter(np.where(surface, depth, np.inf), size=size, mode="nearest")
    farthest = maximum_filter(np.where(surface, depth, 0.0), size=size, mode="nearest")
    return surface & ((depth - nearest > jump_m) | (farthest - depth > jump_m))


def _sample_consistent(point_cam: np.ndarray, K: np.ndarray, depth: np.ndarray, valid: np.ndarray,
                       maps: tuple[np.ndarray, ...], tolerance: float,
                       interpolation: str = "bilinear", edge: np.ndarray | None = None,
                       edge_weight: float = 1.0) -> tuple[np.ndarray, list[np.ndarray]]:
    """Lookup of ``maps`` at the projections of ``point_cam`` (N, 3) using only taps whose depth matches
    the point's z and where ``valid``; returns the used bilinear taps' weight sum (N,) (the soft
    visibility) and the renormalised bilinear samples (N, C) per map (0 where nothing was used).

    ``edge`` (H, W) bool (:func:`depth_edges`) marks taps whose bilinear weight counts ``edge_weight`` in the
    visibility (not in the sample): a source whose taps of a point lie on its occlusion edges weighs that much
    less in the blend, while its sample stays the unbiased interpolation.

    ``interpolation="cubic"`` replaces the bilinear sample by Keys' cubic convolution over the 4 x 4 taps
    where all 16 are visible and valid (bilinear elsewhere: at silhouettes and occlusion boundaries a
    cubic tap would reach across them); the visibility stays the bilinear one."""
    h, w = depth.shape
    z = point_cam[:, 2]
    in_front = z > 1e-6
    zs = np.where(in_front, z, 1.0)
    u, v = pixel_coordinates(K, point_cam, zs)
    u = np.where(in_front & np.isfinite(u), u, -10.0)
    v = np.where(in_front & np.isfinite(v), v, -10.0)
    u0 = np.floor(u).astype(np.int64)
    v0 = np.floor(v).astype(np.int64)
    fu = (u - u0).astype(np.float32)
    fv = (v - v0).astype(np.float32)

    def tap(du: int, dv: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Clipped indices of the tap at offset (du, dv) from the floor, and whether it sees the point."""
        uu, vv = u0 + du, v0 + dv
        uc, vc = np.clip(uu, 0, w - 1), np.clip(vv, 0, h - 1)
        tap_depth = depth[vc, uc]
        use = (in_front & (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h) & valid[vc, uc] & (tap_depth > 0)
               & (np.abs(tap_depth - z) <= tolerance))
        return uc, vc, use

    coverage = np.zeros(len(z), np.float32)
    visibility = np.zeros(len(z), np.float32)
    sums = [np.zeros((len(z), m.shape[-1]), np.float32) for m in maps]
    for du, dv, bw in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        uc, vc, use = tap(du, dv)
        bw = np.where(use, bw, 0.0).astype(np.float32)
        coverage += bw
        visibility += bw if edge is None else bw * np.where(edge[vc, uc], np.float32(edge_weight), np.float32(1.0))
        for acc, m in zip(sums, maps):
            acc += bw[:, None] * m[vc, uc]
    inv = np.divide(1.0, coverage, out=np.zeros_like(coverage), where=coverage > 1e-6)
    samples = [acc * inv[:, None] for acc in sums]
    if interpolation == "cubic":
        wu, wv = _keys_weights(fu), _keys_weights(fv)
        whole = coverage > 1e-6
        cubic = [np.zeros((len(z), m.shape[-1]), np.float32) for m in maps]
        for j, dv in enumerate((-1, 0, 1, 2)):
            for i, du in enumerate((-1, 0, 1, 2)):
                uc, vc, use = tap(du, dv)
                whole &= use
                cw = (wu[i] * wv[j]).astype(np.float32)
                for acc, m in zip(cubic, maps):
                    acc += cw[:, None] * m[vc, uc]
        samples = [np.where(whole[:, None], c, b) for c, b in zip(cubic, samples)]
    return visibility * (coverage > 1e-6), samples


def _lift(depth: np.ndarray, K: np.ndarray, P: np.ndarray):
    """World points of the pixels with a depth: rows, cols (N,), points (N, 3), unit directions to the
    camera (N, 3) and the camera's sampling density ``(f / distance)^2`` (N,)."""
    rows, cols = np.nonzero(depth > 0)
    return (rows, cols) + _lift_points(cols.astype(np.float64), rows.astype(np.float64),
                                       depth[rows, cols].astype(np.float64), K, P)


def _lift_points(u: np.ndarray, v: np.ndarray, z: np.ndarray, K: np.ndarray, P: np.ndarray):
    """World points (N, 3) at pixel coordinates ``u``, ``v`` and camera depth ``z`` (N,), their unit directions
    to the camera (N, 3) and the camera's sampling density ``(f / distance)^2`` (N,)."""
    pts = lift_points(K, P, u, v, z)
    to_target = camera_centre(P) - pts
    dist_target = np.linalg.norm(to_target, axis=-1)
    to_target /= np.maximum(dist_target, 1e-12)[:, None]
    density_target = (K[0, 0] / np.maximum(dist_target, 1e-12)) ** 2
    return pts, to_target, density_target


def _source_terms(sources: Sequence[SourceView], i: int, pts: np.ndarray, to_target: np.ndarray,
                  density_target: np.ndarray, depth_tolerance_m: float, weighting: str, angle_sigma_deg: float,
                  interpolation: str, edge_px: int = 0,
                  edge_jump_m: float = SOURCE_EDGE_JUMP_M) -> dict[str, np.ndarray]:
    """One source's look at the points (N, 3): its samples ``normal``/``albedo`` (N, 3), soft
    ``visibility``, the angle ``theta`` at the point between the rays to the target and to the source,
    ``log_density`` (log of the source's sampling density over the target's), ``cos_source`` and
    ``cos_target`` (the sampled normal against the rays to the source and to the target) and the
    heuristic blend ``weight`` of ``weighting`` (module docstring), all (N,)."""
    s_normal, s_albedo, s_valid, s_depth, s_K, s_P = _check_source(i, sources[i])
    pc = pts @ s_P[:, :3].T + s_P[:, 3]
    edge = depth_edges(s_depth, edge_px, edge_jump_m) if edge_px else None
    visibility, (nrm, alb) = _sample_consistent(pc, s_K, s_depth, s_valid, (s_normal, s_albedo),
                                                float(depth_tolerance_m), interpolation, edge, SOURCE_EDGE_WEIGHT)
    if interpolation == "cubic":  # the kernel's negative lobes may overshoot below 0 at a dark edge
        alb = np.maximum(alb, 0.0)
    to_src = camera_centre(s_P) - pts
    dist_src = np.linalg.norm(to_src, axis=-1)
    to_src /= np.maximum(dist_src, 1e-12)[:, None]
    cosang = np.clip(np.einsum("ij,ij->i", to_src, to_target), -1.0, 1.0)
    theta = np.arctan2(np.linalg.norm(np.cross(to_src, to_target), axis=-1), cosang)
    density = (s_K[0, 0] / np.maximum(dist_src, 1e-12)) ** 2 / density_target
    nrm64 = nrm.astype(np.float64)
    cos_source = np.einsum("ij,ij->i", nrm64, to_src)
    wgt = visibility.astype(np.float64)
    if weighting != "uniform":
        wgt = wgt * np.exp(-0.5 * (theta / np.radians(angle_sigma_deg)) ** 2)
        if weighting in ("angle_distance", "angle_distance_grazing"):
            wgt = wgt * density
        if weighting == "angle_distance_grazing":
            wgt = wgt * np.clip(cos_source, 0.0, 1.0)
    return {"normal": nrm, "albedo": alb, "visibility": visibility, "theta": theta,
            "log_density": np.log(np.maximum(density, 1e-12)), "cos_source": cos_source,
            "cos_target": np.einsum("ij,ij->i", nrm64, to_target), "weight": np.where(np.isfinite(wgt), wgt, 0.0)}


def _check_edges(edge_px: int, edge_jump_m: float) -> None:
    if int(edge_px) != edge_px or edge_px < 0:
        raise ValueError(f"source_edge_px must be a non-negative integer, got {edge_px}")
    if not (edge_jump_m > 0) or not np.isfinite(edge_jump_m):
        raise ValueError(f"source_edge_jump_m must be positive, got {edge_jump_m}")


def _stack_terms(terms: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Per-source terms stacked along axis 1: (N, k) and (N, k, 3) arrays."""
    return {key: np.stack([t[key] for t in terms], axis=1) for key in terms[0]}


def _prepare(target_depth_m, K, cam_from_world, sources, k, depth_tolerance_m, weighting, angle_sigma_deg,
             subject_centre, source_indices, interpolation) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Checked inputs of a reprojection: depth (H, W), K, P (3, 4) and the indices of the sources used."""
    depth = np.asarray(target_depth_m)
    if depth.ndim != 2 or depth.size == 0:
        raise ValueError(f"target_depth_m must be a non-empty (H, W) map, got {depth.shape}")
    if not np.all(np.isfinite(depth)):
        raise ValueError("target_depth_m holds NaN or Inf (use 0 for 'no surface')")
    if np.any(depth < 0):
        raise ValueError("target_depth_m holds negative depths (use 0 for 'no surface')")
    K = _intrinsics(K)
    P = as_pose(cam_from_world)
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    if not (depth_tolerance_m > 0) or not np.isfinite(depth_tolerance_m):
        raise ValueError(f"depth_tolerance_m must be positive, got {depth_tolerance_m}")
    if not (angle_sigma_deg > 0) or not np.isfinite(angle_sigma_deg):
        raise ValueError(f"angle_sigma_deg must be positive, got {angle_sigma_deg}")
    if len(sources) == 0:
        raise ValueError("reprojection: no source views")
    if source_indices is None:
        chosen = nearest_views(P, [s.cam_from_world for s in sources], k, subject_centre)
    else:
        chosen = np.asarray(source_indices, dtype=np.int64).reshape(-1)
        if chosen.size == 0 or chosen.min() < 0 or chosen.max() >= len(sources):
            raise ValueError(f"source_indices must index the {len(sources)} sources, got {chosen.tolist()}")

    return depth, K, P, chosen


def source_candidates(target_depth_m: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray,
                      sources: Sequence[SourceView], k: int = 6, depth_tolerance_m: float = 0.01,
                      weighting: str = "angle_distance_grazing", angle_sigma_deg: float = 20.0,
                      subject_centre: Sequence[float] = (0.0, 0.0, 0.0),
                      interpolation: str = "cubic", source_edge_px: int = SOURCE_EDGE_PX,
                      source_edge_jump_m: float = SOURCE_EDGE_JUMP_M) -> dict[str, np.ndarray]:
    """What each of the ``k`` nearest sources offers every target pixel with a depth, before blending (the
    input of a learned blend, :mod:`stages.numerics.learned_blend`).

    Returns ``rows``, ``cols`` (N,) of the pixels, ``sources`` (k,) and the terms of each source
    (``_source_terms``): ``normal``, ``albedo`` (N, k, 3); ``visibility``, ``theta``, ``log_density``,
    ``cos_source``, ``cos_target``, ``weight`` (N, k). Memory: about 60 bytes per pixel and source.
    """
    depth, K, P, chosen = _prepare(target_depth_m, K, cam_from_world, sources, k, depth_tolerance_m, weighting,
                                   angle_sigma_deg, subject_centre, None, interpolation)
    _check_edges(source_edge_px, source_edge_jump_m)
    rows, cols, pts, to_target, density_target = _lift(depth, K, P)
    cand = _stack_terms([_source_terms(sources, int(i), pts, to_target, density_target, depth_tolerance_m,
                                       weighting, angle_sigma_deg, interpolation, source_edge_px, source_edge_jump_m)
                         for i in chosen])
    return cand | {"rows": rows, "cols": cols, "sources": chosen}


def reproject_gbuffer(target_depth_m: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray,
                      sources: Sequence[SourceView], k: int = 6, depth_tolerance_m: float = 0.01,
                      weighting: str = "angle_distance_grazing", angle_sigma_deg: float = 20.0,
                      subject_centre: Sequence[float] = (0.0, 0.0, 0.0),
                      source_indices: Sequence[int] | None = None,
                      interpolation: str = "cubic", blend=None,
                      subpixel: dict[str, np.ndarray] | None = None, source_edge_px: int = SOURCE_EDGE_PX,
                      source_edge_jump_m: float = SOURCE_EDGE_JUMP_M) -> dict[str, np.ndarray]:
    """Normal and albedo maps of a target camera blended from the ``k`` nearest visible source views.

    Args:
        target_depth_m: (H, W) camera z of the surface seen by the target (0 = no surface there).
        K: (3, 3) target intrinsics. cam_from_world: (3, 4) target pose.
        sources: the captured views (:class:`SourceView`; any size each).
        k: number of nearest sources (by :func:`nearest_views`) looked up per pixel.
        depth_tolerance_m: a source tap is visible when its mesh depth is within this of the point's
            depth in that source.
        weighting: one of :data:`WEIGHTINGS` (see the module docstring).
        angle_sigma_deg: width of the angular weight.
        subject_centre: (3,) centre used to pick the nearest views.
        source_indices: use these sources instead of the ``k`` nearest.
        interpolation: one of :data:`INTERPOLATIONS`: how a source map is read at the point's projection,
            ``"bilinear"`` or ``"cubic"`` (Keys' cubic convolution where the 4 x 4 taps are all visible,
            bilinear elsewhere; module docstring).
        blend: a trained :class:`stages.numerics.learned_blend.LearnedBlend`: its per-pixel weights over the
            ``k`` sources replace the ``weighting``'s (which stays its prior and its input); None = the
            heuristic weights.
        subpixel: depths of sub-pixel rays at some pixels (:func:`stages.numerics.raycast.subpixel_depths`
            plus its pixels' ``rows`` and ``cols`` (M,)): those pixels get the mean of their rays' blended
            albedo and normal over the rays that hit and were seen by a source, as a camera pixel
            integrates its square, instead of their centre's. Meant for the pixels at an occlusion edge
            (:func:`stages.numerics.raycast.occlusion_edges`), where the centre sample takes one side wholly.
        source_edge_px, source_edge_jump_m: a source's pixels within ``source_edge_px`` of its own occlusion
            edges (:func:`depth_edges`, a jump over ``source_edge_jump_m``) count :data:`SOURCE_EDGE_WEIGHT` in
            that source's soft visibility, hence its blend weight (0 px: every pixel counts alike; module docstring).

    Returns:
        ``normal`` (H, W, 3) float32 unit world normals (0 where invalid), ``albedo`` (H, W, 3) float32,
        ``weight`` (H, W) float32 total blend weight (relative units: 1 = one fully visible source seen
        head-on from the target's direction and distance; at sub-sampled pixels the mean over the rays
        used), ``valid`` (H, W) bool (a surface and at least one visible source), ``view_count`` (H, W)
        int32 sources that contributed (the most of any ray at sub-sampled pixels), ``sources`` (k,) int64
        indices of the sources used.
    """
    depth, K, P, chosen = _prepare(target_depth_m, K, cam_from_world, sources, k, depth_tolerance_m, weighting,
                                   angle_sigma_deg, subject_centre, source_indices, interpolation)
    h, w = depth.shape
    _check_edges(source_edge_px, source_edge_jump_m)
    terms_kw = dict(depth_tolerance_m=depth_tolerance_m, weighting=weighting, angle_sigma_deg=angle_sigma_deg,
                    interpolation=interpolation, edge_px=int(source_edge_px), edge_jump_m=float(source_edge_jump_m))
    rows, cols, pts, to_target, density_target = _lift(depth, K, P)
    normal_px, albedo_px, weight_px, count, ok = _blend_points(sources, chosen, blend, pts, to_target,
                                                               density_target, terms_kw)
    out_normal = np.zeros((h, w, 3), np.float32)
    out_albedo = np.zeros((h, w, 3), np.float32)
    out_weight = np.zeros((h, w), np.float32)
    out_count = np.zeros((h, w), np.int32)
    out_valid = np.zeros((h, w), bool)
    out_normal[rows, cols] = np.where(ok[:, None], normal_px, 0.0)
    out_albedo[rows, cols] = np.where(ok[:, None], albedo_px, 0.0)
    out_weight[rows, cols] = np.where(ok, weight_px, 0.0)
    out_count[rows, cols] = np.where(ok, count, 0)
    out_valid[rows, cols] = ok
    if subpixel is not None:
        r, c, sub = _blend_subpixel(subpixel, (h, w), K, P, sources, chosen, blend, terms_kw)
        out_normal[r, c], out_albedo[r, c] = sub["normal"], sub["albedo"]
        out_weight[r, c], out_count[r, c], out_valid[r, c] = sub["weight"], sub["count"], sub["valid"]
    return {"normal": out_normal, "albedo": out_albedo, "weight": out_weight, "valid": out_valid,
            "view_count": out_count, "sources": chosen}


def _blend_points(sources: Sequence[SourceView], chosen: np.ndarray, blend, pts: np.ndarray, to_target: np.ndarray,
                  density_target: np.ndarray, terms_kw: dict) -> tuple[np.ndarray, ...]:
    """Blend of the chosen sources at world points (N, 3): unit normal (N, 3), albedo (N, 3), total weight
    (N,), contributing sources (N,) int32 and ok (N,) bool (some weight and a defined normal)."""
    n = len(pts)
    normal_acc = np.zeros((n, 3), np.float64)
    albedo_acc = np.zeros((n, 3), np.float64)
    weight_acc = np.zeros(n, np.float64)
    count = np.zeros(n, np.int32)
    if blend is None:  # one source at a time: no (pixels, k) arrays at full resolution
        for i in chosen:
            terms = _source_terms(sources, int(i), pts, to_target, density_target, **terms_kw)
            wgt = terms["weight"]
            normal_acc += wgt[:, None] * terms["normal"]
            albedo_acc += wgt[:, None] * terms["albedo"]
            weight_acc += wgt
            count += (wgt > 0).astype(np.int32)
    elif n:
        cand = _stack_terms([_source_terms(sources, int(i), pts, to_target, density_target, **terms_kw)
                             for i in chosen])
        # the learned weights are a softmax: scale them by the heuristic total so ``weight`` keeps its units
        wgt = blend.weights(cand) * cand["weight"].sum(axis=1, keepdims=True)
        normal_acc = np.einsum("nk,nkc->nc", wgt, cand["normal"].astype(np.float64))
        albedo_acc = np.einsum("nk,nkc->nc", wgt, cand["albedo"].astype(np.float64))
        weight_acc = wgt.sum(axis=1)
        count = (wgt > 0).sum(axis=1).astype(np.int32)

    ok = weight_acc > 1e-12
    inv = np.divide(1.0, weight_acc, out=np.zeros_like(weight_acc), where=ok)
    albedo_px = albedo_acc * inv[:, None]
    norm = np.linalg.norm(normal_acc, axis=-1)
    ok &= norm > 1e-9  # opposite normals that cancel carry no direction
    normal_px = np.divide(normal_acc, norm[:, None], out=np.zeros_like(normal_acc), where=ok[:, None])
    return normal_px, albedo_px, weight_acc, count, ok


def _blend_subpixel(subpixel: dict[str, np.ndarray], shape: tuple[int, int], K: np.ndarray, P: np.ndarray,
                    sources: Sequence[SourceView], chosen: np.ndarray, blend,
                    terms_kw: dict) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The pixels of ``subpixel`` (see :func:`reproject_gbuffer`): rows, cols (M,) and their maps, each the
    mean of the blends at the pixel's rays that hit and were blended."""
    try:
        r = np.asarray(subpixel["rows"], np.int64).reshape(-1)
        c = np.asarray(subpixel["cols"], np.int64).reshape(-1)
        z = np.asarray(subpixel["depth_m"], np.float64)
        u = np.asarray(subpixel["u"], np.float64)
        v = np.asarray(subpixel["v"], np.float64)
    except KeyError as err:
        raise ValueError(f"subpixel needs rows, cols, depth_m, u and v; {err} is missing") from None
    m = len(r)
    if c.shape != (m,) or z.ndim != 2 or z.shape[0] != m or u.shape != z.shape or v.shape != z.shape:
        raise ValueError(f"subpixel: rows {r.shape}, cols {c.shape}, depth_m/u/v {z.shape}/{u.shape}/{v.shape} "
                         "must be (M,), (M,) and (M, S)")
    if m and (r.min() < 0 or r.max() >= shape[0] or c.min() < 0 or c.max() >= shape[1]):
        raise ValueError(f"subpixel pixels fall outside the {shape[0]} x {shape[1]} target")
    if not np.all(np.isfinite(z)) or np.any(z < 0):
        raise ValueError("subpixel depth_m must be finite and >= 0 (0 = the ray missed)")
    hit = z > 0
    pts, to_target, density_target = _lift_points(u[hit], v[hit], z[hit], K, P)
    normal_h, albedo_h, weight_h, count_h, ok_h = _blend_points(sources, chosen, blend, pts, to_target,
                                                                density_target, terms_kw)
    shape_ms = z.shape
    ok = np.zeros(shape_ms, bool)
    ok[hit] = ok_h
    normal = np.zeros(shape_ms + (3,), np.float64)
    albedo = np.zeros(shape_ms + (3,), np.float64)
    weight = np.zeros(shape_ms, np.float64)
    count = np.zeros(shape_ms, np.int32)
    normal[hit], albedo[hit], weight[hit], count[hit] = normal_h, albedo_h, weight_h, count_h
    used = ok.sum(axis=1)
    valid = used > 0
    inv = np.divide(1.0, used, out=np.zeros(m, np.float64), where=valid)
    albedo_px = (albedo * ok[..., None]).sum(axis=1) * inv[:, None]
    normal_sum = (normal * ok[..., None]).sum(axis=1)
    norm = np.linalg.norm(normal_sum, axis=-1)
    valid &= norm > 1e-9
    normal_px = np.divide(normal_sum, norm[:, None], out=np.zeros_like(normal_sum), where=valid[:, None])
    weight_px = (weight * ok).sum(axis=1) * inv
    keep = valid[:, None]
    return r, c, {"normal": np.where(keep, normal_px, 0.0).astype(np.float32),
                  "albedo": np.where(keep, albedo_px, 0.0).astype(np.float32),
                  "weight": np.where(valid, weight_px, 0.0).astype(np.float32),
                  "count": np.where(valid, count.max(axis=1), 0).astype(np.int32), "valid": valid}


def fuse_normals(normal_detail: np.ndarray, normal_base: np.ndarray, mask: np.ndarray, sigma_px: float) -> np.ndarray:
    """Normals with the low frequencies of ``normal_base`` and the detail of ``normal_detail``.

    ``unit(d - G(d) + G(b))`` per pixel, ``G`` a Gaussian of ``sigma_px`` over the mask (normalised
    convolution: pixels outside the mask, or where a map is undefined, neither count nor receive). The
    reprojected photometric normals carry detail the mesh lacks but also smooth, view-dependent biases
    (eq. 1's lean, specular residue); the mesh's normals are fitted to every view and silhouette at once, so
    at low frequencies they are the better estimate.

    Args:
        normal_detail: (H, W, 3) normals whose detail is kept (e.g. the reprojected photometric ones).
        normal_base: (H, W, 3) normals whose low frequencies are kept (e.g. the mesh's smooth normals).
        mask: (H, W) bool pixels to fuse.
        sigma_px: > 0, the Gaussian's standard deviation in pixels (the frequency split).

    Returns:
        (H, W, 3) float32 unit normals inside the mask (``normal_base``'s direction where the fused vector
        vanishes or the detail is undefined, 0 where neither is defined), 0 outside. No NaN or Inf.
    """
    from scipy.ndimage import gaussian_filter

    detail = np.asarray(normal_detail, dtype=np.float64)
    base = np.asarray(normal_base, dtype=np.float64)
    mask = np.asarray(mask).astype(bool, copy=False)
    if detail.ndim != 3 or detail.shape[-1] != 3:
        raise ValueError(f"normal_detail must be (H, W, 3), got {detail.shape}")
    if base.shape != detail.shape or mask.shape != detail.shape[:2]:
        raise ValueError(f"normal_base {base.shape} and mask {mask.shape} must match normal_detail {detail.shape}")
    if not (np.isfinite(sigma_px) and sigma_px > 0):
        raise ValueError(f"sigma_px must be positive, got {sigma_px}")

    def defined(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ok = mask & np.all(np.isfinite(n), axis=-1)
        n = np.where(ok[..., None], n, 0.0)
        norm = np.linalg.norm(n, axis=-1)
        ok &= norm > 1e-6
        return np.where(ok[..., None], n / np.maximum(norm, 1e-6)[..., None], 0.0), ok

    detail, detail_ok = defined(detail)
    base, base_ok = defined(base)

    def smooth(n: np.ndarray, ok: np.ndarray) -> np.ndarray:
        weight = gaussian_filter(ok.astype(np.float64), sigma_px, mode="constant")
        blurred = np.stack([gaussian_filter(n[..., c], sigma_px, mode="constant") for c in range(3)], axis=-1)
        return blurred / np.maximum(weight, 1e-9)[..., None]

    both = detail_ok & base_ok
    fused = detail - smooth(detail, detail_ok) + smooth(base, base_ok)
    norm = np.linalg.norm(fused, axis=-1)
    use = both & (norm > 1e-6)
    fused = np.where(use[..., None], fused / np.maximum(norm, 1e-6)[..., None], base)
    out = np.where(use[..., None] | base_ok[..., None], fused, detail)
    return np.where(mask[..., None], out, 0.0).astype(np.float32)


def fade_rim_normals(normals: np.ndarray, normal_base: np.ndarray, mask: np.ndarray, rim_px: float,
                     interior_weight: float = 0.0) -> np.ndarray:
    """Normals faded to ``normal_base`` over a rim of ``rim_px`` pixels inside the silhouette of ``mask``.

    Each mask pixel at distance ``d`` from the nearest pixel outside the mask (:func:`scipy.ndimage.
    distance_transform_edt`: 1 on the mask's outer ring; the image border is not a silhouette) takes
    ``unit((1 - w) n + w b)`` with ``w = max(clip((rim_px + 1 - d) / rim_px, 0, 1), interior_weight)``: the base
    normal on the outer ring, ``normals`` blended with ``interior_weight`` of the base from ``rim_px + 1`` pixels
    in. A novel view's rim is seen at grazing angles by the nearby
    captured views too, where their photometric normals are worst (default capture, A0000: 19.7 deg off the
    truth on their outer valid ring, 7.8 deg on the next, 3.6 deg from 8 px in), so there the mesh's
    normals are the better estimate.

    Args:
        normals: (H, W, 3) unit normals (e.g. :func:`fuse_normals`'s).
        normal_base: (H, W, 3) unit normals the rim fades to (e.g. the mesh's smooth normals).
        mask: (H, W) bool, the silhouette.
        rim_px: >= 0, the rim's width in pixels (0: no rim).
        interior_weight: in [0, 1], the base's share everywhere on the mask (0: ``normals`` unchanged inside the
            rim).

    Returns:
        (H, W, 3) float32, unit inside the mask where either input is defined (``normals`` where the blend
        vanishes or the base is undefined), 0 outside. No NaN or Inf.
    """
    from scipy.ndimage import distance_transform_edt

    n = np.nan_to_num(np.asarray(normals, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    b = np.nan_to_num(np.asarray(normal_base, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    mask = np.asarray(mask).astype(bool, copy=False)
    if n.ndim != 3 or n.shape[-1] != 3:
        raise ValueError(f"normals must be (H, W, 3), got {n.shape}")
    if b.shape != n.shape or mask.shape != n.shape[:2]:
        raise ValueError(f"normal_base {b.shape} and mask {mask.shape} must match normals {n.shape}")
    if not (np.isfinite(rim_px) and rim_px >= 0):
        raise ValueError(f"rim_px must be finite and >= 0, got {rim_px}")
    if not (np.isfinite(interior_weight) and 0.0 <= interior_weight <= 1.0):
        raise ValueError(f"interior_weight must be in [0, 1], got {interior_weight}")
    if (rim_px == 0 and interior_weight == 0) or not mask.any():
        return np.where(mask[..., None], n, 0.0).astype(np.float32)
    weight = np.full(mask.shape, float(interior_weight))
    if rim_px > 0:
        weight = np.maximum(np.clip((rim_px + 1.0 - distance_transform_edt(mask)) / rim_px, 0.0, 1.0), weight)
    weight = np.where(np.linalg.norm(b, axis=-1) > 1e-6, weight, 0.0)[..., None]
    blend = (1.0 - weight) * n + weight * b
    norm = np.linalg.norm(blend, axis=-1, keepdims=True)
    out = np.divide(blend, norm, out=n.copy(), where=norm > 1e-6)
    return np.where(mask[..., None], out, 0.0).astype(np.float32)


def shading_normals(normal_detail: np.ndarray, normal_base: np.ndarray, mask: np.ndarray, sigma_px: float,
                    rim_px: float, base_weight: float = 0.0) -> np.ndarray:
    """A novel view's shading normals: :func:`fuse_normals` (``normal_detail``'s detail above ``sigma_px`` on
    ``normal_base``'s low frequencies), then :func:`fade_rim_normals` to ``normal_base`` over the silhouette's
    ``rim_px`` pixels and by ``base_weight`` inside them. Shapes and checks as those two: (H, W, 3) unit normals
    and an (H, W) bool mask in, (H, W, 3) float32 out, unit inside the mask, 0 outside."""
    return fade_rim_normals(fuse_normals(normal_detail, normal_base, mask, sigma_px), normal_base, mask, rim_px,
                            base_weight)


def interpolate_camera(K_a: np.ndarray, cam_from_world_a: np.ndarray, K_b: np.ndarray,
                       cam_from_world_b: np.ndarray, t: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """A camera between two: centre on the arc between theirs around ``(0, 0, 0)`` (radius and direction
    interpolated, so it stays on the rig's sphere rather than cutting inside it), orientation by
    quaternion slerp, intrinsics interpolated linearly.

    Args:
        K_a, K_b: (3, 3) intrinsics; cam_from_world_a, cam_from_world_b: (3, 4) poses; t: 0 = a, 1 = b.

    Returns:
        K (3, 3) float64 and cam_from_world (3, 4) float64.
    """
    from scipy.spatial.transform import Rotation, Slerp

    if not 0.0 <= float(t) <= 1.0:
        raise ValueError(f"t must be in [0, 1], got {t}")
    Pa, Pb = as_pose(cam_from_world_a, "cam_from_world_a"), as_pose(cam_from_world_b, "cam_from_world_b")
    Ka, Kb = _intrinsics(K_a, "K_a"), _intrinsics(K_b, "K_b")
    ca, cb = camera_centre(Pa), camera_centre(Pb)
    ra, rb = np.linalg.norm(ca), np.linalg.norm(cb)
    if ra < 1e-9 or rb < 1e-9:
        raise ValueError("a camera centre is at the origin: no arc to interpolate on")
    da, db = ca / ra, cb / rb
    omega = np.arccos(np.clip(da @ db, -1.0, 1.0))
    if omega < 1e-9:
        direction = da
    elif np.pi - omega < 1e-6:
        raise ValueError("the two cameras are opposite each other: the arc between them is undefined")
    else:
        direction = (np.sin((1 - t) * omega) * da + np.sin(t * omega) * db) / np.sin(omega)
    centre = direction * ((1 - t) * ra + t * rb)
    world_from_cam = Rotation.from_matrix(np.stack([Pa[:, :3].T, Pb[:, :3].T]))
    R = Slerp([0.0, 1.0], world_from_cam)([float(t)]).as_matrix()[0].T  # cam_from_world rotation
    return (1 - t) * Ka + t * Kb, np.concatenate([R, (-R @ centre)[:, None]], axis=1)


def novel_camera_pairs(cam_from_worlds: Sequence[np.ndarray], count: int,
                       subject_centre: Sequence[float] = (0.0, 0.0, 0.0)) -> list[tuple[int, int]]:
    """``count`` pairs of neighbouring cameras spread around the subject, to place novel views between.

    Cameras are ordered by azimuth (around +y) of their direction from the subject; ``count`` anchors are
    taken evenly along that order and each is paired with its nearest other camera (smallest angle at
    the subject), so a novel view between them is as far as possible from both.

    Returns:
        list of ``(a, b)`` index pairs (a != b), at most ``count``, no pair twice.
    """
    poses = [as_pose(P, f"cam_from_worlds[{i}]") for i, P in enumerate(cam_from_worlds)]
    if len(poses) < 2:
        raise ValueError("need at least two cameras to place a novel view between")
    if int(count) < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    centres = np.stack([camera_centre(P) for P in poses]) - np.asarray(subject_centre, np.float64)[None]
    dirs = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    azimuth = np.arctan2(dirs[:, 0], dirs[:, 2])
    order = np.argsort(azimuth, kind="stable")
    anchors = order[np.linspace(0, len(order), int(count), endpoint=False).astype(int)]
    pairs: list[tuple[int, int]] = []
    for a in anchors:
        cos = dirs @ dirs[a]
        cos[a] = -np.inf
        b = int(np.argmax(cos))
        pair = (int(min(a, b)), int(max(a, b)))
        if pair not in pairs:
            pairs.append(pair)
    return pairs
