"""Light transport on the stage: self-occlusion, Lambertian + GGX shading, the dim LED-sphere background.

Scheme (chosen to be faithful yet fit the time budget; no interreflections, direct light only):

1. Visibility is computed once per action, view independently, at every vertex of the (subdivided,
   displaced) mesh against every LED: one shadow ray per (vertex, LED) pair with the LED above the
   vertex's horizon, origin offset 1 mm along the normal to avoid self-intersection acne
   (Embree `test_occlusions`). LEDs are distant directional lights.
2. Diffuse: per vertex, irradiance E_v = sum_l V(v,l) max(0, n_v.w_l) I(l) (4pi/L) for the 9 channels
   (full_on, pos, neg x RGB) as one matrix product, and the cosine-weighted visible fraction. A pixel
   interpolates E with the barycentrics of its primary-ray hit (Gouraud irradiance) and multiplies by
   albedo / pi. For an unoccluded point E is affine in n, so the interpolated E equals E at the
   interpolated normal: the gradient ratio stays exact there.
3. Specular (GGX, height-correlated Smith, Schlick Fresnel) is view dependent: per pixel and LED, with
   the LED's visibility interpolated from the pixel's triangle corners (fraction of corners that see
   it), in cache-sized chunks. Optionally (`CLUSTER_LEVELS`, SimConfig.specular_led_clusters) LEDs are
   grouped into direction clusters whose count follows the lobe width: 64 clusters for rough cloth
   (alpha >= 0.35), 256 for skin (alpha >= 0.12), every LED for shinier materials; a cluster sums its
   members' irradiance, sits at their mean direction, and its visibility at a vertex is the fraction of
   its members the vertex sees. bench/bench_simulate.py measures that at ~1.7% relative RMS radiance
   error for ~40% less render time per camera.
4. Pixels integrate over their area (`render_view(..., supersample=s)`, SimConfig.supersample): s x s
   primary rays on a regular grid inside each pixel, box-averaged (pixel_average). One ray through the
   pixel centre aliases surface detail finer than a pixel (the cloth folds) and makes silhouette pixels
   all subject or all stage, which no sensor does.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from . import geometry, kernels
from .rig import Camera, LedSphere
from .subject import ActionSubject

SHADOW_OFFSET_M = 1e-3
EXACT_LEVELS = ((0.0, None),)  # (min GGX alpha, LED cluster count; None = every LED on its own)
CLUSTER_LEVELS = ((0.35, 64), (0.12, 256), (0.0, None))
CHUNK_ELEMENTS = 1 << 17  # pixels x LED clusters per specular chunk: arrays stay cache-resident (2-3x faster)
INVALID_ID = np.iinfo(np.uint32).max
_XYZ = np.dtype((np.void, 12))  # three float32 as one item


def raycasting_scene(vertices: np.ndarray, triangles: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """An Embree scene holding one triangle mesh (vertices (V, 3), triangles (T, 3))."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)))
    return scene


def vertex_visibility(scene: o3d.t.geometry.RaycastingScene, vertices: np.ndarray, normals: np.ndarray,
                      directions: np.ndarray, offset_m: float = SHADOW_OFFSET_M, chunk: int = 8192) -> np.ndarray:
    """V(v, l): True where vertex v sees distant light direction l unoccluded, (V, L) bool.

    Only LEDs above the vertex's horizon (n.w > 0) are traced; the rest are False.
    vertices, normals: (V, 3); directions: (L, 3) unit.
    """
    n_vertices, n_dirs = len(vertices), len(directions)
    visible = np.zeros((n_vertices, n_dirs), dtype=bool)
    dirs32 = directions.astype(np.float32)
    for start in range(0, n_vertices, chunk):
        stop = min(start + chunk, n_vertices)
        normal = normals[start:stop].astype(np.float32)
        origins = vertices[start:stop].astype(np.float32) + offset_m * normal
        above = dirs32 @ normal.T > 0.0  # (L, chunk): LED-major ray order, coherent rays trace faster
        counts = np.count_nonzero(above, axis=1)
        ends = np.cumsum(counts)
        if not counts.any():
            continue
        # rays (origin, direction) in LED-major order, each 12-byte half copied as one item
        rays = np.empty((int(ends[-1]), 6), np.float32)
        starts_of_led = ends - counts
        origin_items, halves = np.ascontiguousarray(origins).view(_XYZ)[:, 0], rays.view(_XYZ)
        for led in np.nonzero(counts)[0]:
            halves[starts_of_led[led]:ends[led], 0] = origin_items[above[led]]
        halves[:, 1] = np.repeat(dirs32.view(_XYZ)[:, 0], counts)
        occluded = scene.test_occlusions(o3d.core.Tensor.from_numpy(rays)).numpy()
        seen = np.zeros_like(above)
        seen[above] = ~occluded
        visible[start:stop] = seen.T
    return visible


@dataclass(frozen=True)
class LedClusters:
    """LED direction clusters: directions (C, 3) float32, irradiance (C, 9) float32, members: cluster
    index per LED (L,), sorted LED order (L,), cluster start offsets in that order (C,), counts (C,)."""
    directions: np.ndarray
    irradiance: np.ndarray
    member_of: np.ndarray
    order: np.ndarray
    starts: np.ndarray
    counts: np.ndarray


def cluster_leds(directions: np.ndarray, irradiance: np.ndarray, count: int | None) -> LedClusters:
    """Group LEDs (directions (L, 3), irradiance (L, 9)) by nearest of `count` Fibonacci centres
    (None or >= L: one cluster per LED). Empty clusters are dropped."""
    n_leds = len(directions)
    if count is None or count >= n_leds:
        member_of = np.arange(n_leds)
    else:
        centres = geometry.fibonacci_sphere(count)
        _, member_of = np.unique(np.argmax(directions @ centres.T, axis=1), return_inverse=True)
    order = np.argsort(member_of, kind="stable")
    counts = np.bincount(member_of)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    sums = np.stack([np.bincount(member_of, weights=directions[:, c]) for c in range(3)], axis=1)
    cluster_irradiance = np.stack([np.bincount(member_of, weights=irradiance[:, c])
                                   for c in range(irradiance.shape[1])], axis=1)
    return LedClusters(geometry.normalize(sums).astype(np.float32), cluster_irradiance.astype(np.float32),
                       member_of, order, starts, counts)


@dataclass(frozen=True)
class SurfaceLighting:
    """View-independent lighting of one action's mesh.

    irradiance: (V, 9) float32 per vertex (full_on, pos, neg x RGB); visible_fraction: (V,) float32;
    levels: the (min GGX alpha, cluster count) table used; clusters: one LedClusters per level;
    cluster_visibility: per level (V, C) uint8 (255 = all members visible).
    """
    irradiance: np.ndarray
    visible_fraction: np.ndarray
    levels: tuple[tuple[float, int | None], ...]
    clusters: tuple[LedClusters, ...]
    cluster_visibility: tuple[np.ndarray, ...]


def surface_lighting(visible: np.ndarray, normals: np.ndarray, leds: LedSphere, with_specular: bool = True,
                     levels: tuple[tuple[float, int | None], ...] = EXACT_LEVELS,
                     chunk: int = 8192) -> SurfaceLighting:
    """Per-vertex irradiance and visible fraction from V (V, L) bool and vertex normals (V, 3), and the
    specular LED clusters of `levels` ((min alpha, count) rows by decreasing alpha; count None = all LEDs,
    the last row's min alpha must be 0)."""
    irradiance_table = leds.irradiance
    dirs32 = leds.directions.astype(np.float32)
    n_vertices = len(normals)
    irradiance = np.zeros((n_vertices, 9), np.float32)
    fraction = np.zeros(n_vertices, np.float32)
    for start in range(0, n_vertices, chunk):
        stop = min(start + chunk, n_vertices)
        cos = np.maximum(normals[start:stop].astype(np.float32) @ dirs32.T, 0.0)
        weighted = cos * visible[start:stop]
        irradiance[start:stop] = weighted @ irradiance_table
        total = cos.sum(axis=1)
        fraction[start:stop] = np.where(total > 0, weighted.sum(axis=1) / np.maximum(total, 1e-12), 0.0)
    clusters, cluster_vis = [], []
    if with_specular:
        by_led = None
        for _, count in levels:
            level = cluster_leds(leds.directions, irradiance_table, count)
            clusters.append(level)
            if len(level.counts) == leds.count:
                cluster_vis.append(visible.view(np.uint8) * np.uint8(255))
            else:
                if by_led is None:  # (L, V): cluster sums over contiguous rows
                    by_led = np.ascontiguousarray(visible.T).view(np.uint8)
                sums = np.add.reduceat(by_led[level.order], level.starts, axis=0, dtype=np.uint16)
                scaled = np.round(sums * (255.0 / level.counts)[:, None].astype(np.float32)).astype(np.uint8)
                cluster_vis.append(np.ascontiguousarray(scaled.T))
    return SurfaceLighting(irradiance, fraction, tuple(levels), tuple(clusters), tuple(cluster_vis))


def level_of(alpha: np.ndarray, levels: tuple[tuple[float, int | None], ...] = EXACT_LEVELS) -> np.ndarray:
    """Specular cluster level index (N,) for GGX alphas (N,): the first row whose min alpha they reach."""
    level = np.full(alpha.shape, len(levels) - 1)
    for index in reversed(range(len(levels))):
        level[alpha >= levels[index][0]] = index
    return level


def ggx_weights(normals: np.ndarray, view: np.ndarray, light_dirs: np.ndarray, alpha: np.ndarray,
                f0: np.ndarray) -> np.ndarray:
    """GGX specular radiance per unit irradiance, times the cosine: F D Vis (n.l), (N, C) float32.

    normals, view (towards the camera): (N, 3) unit; light_dirs: (C, 3) unit; alpha (GGX alpha =
    roughness**2), f0: (N,). Vis = G2 / (4 n.l n.v) with the height-correlated Smith G2; Schlick F.
    With float32 directions (the renderer's case) the (N, C) terms are computed in one fused C loop
    (:func:`synthetic.kernels.ggx_terms`), else in a few reused buffers (:func:`_ggx_weights_float32`); both do
    the formula's float32 operations in the same order, so all three give the same bits.
    """
    a2 = (alpha * alpha).astype(np.float32)[:, None]
    f0 = f0.astype(np.float32)[:, None]
    if normals.dtype == view.dtype == light_dirs.dtype == np.float32:
        if kernels.kernel_available():
            return _ggx_fused(normals, view, light_dirs, a2, f0)
        return _ggx_weights_float32(normals, view, light_dirs, a2, f0)
    return _ggx_weights_formula(normals, view, light_dirs, a2, f0)


def _ggx_weights_formula(normals: np.ndarray, view: np.ndarray, light_dirs: np.ndarray, a2: np.ndarray,
                         f0: np.ndarray) -> np.ndarray:
    """:func:`ggx_weights` written as the formula (a2, f0: (N, 1) float32)."""
    nl = np.maximum(normals @ light_dirs.T, 0.0)
    vl = view @ light_dirs.T
    nv = np.maximum(np.sum(normals * view, axis=1, keepdims=True), 1e-3)
    one_plus = np.maximum(1.0 + vl, 1e-6)
    nh2 = np.minimum((nl + nv) ** 2 / (2.0 * one_plus), 1.0)
    d = nh2 * (a2 - 1.0) + 1.0
    distribution = a2 / (np.pi * d * d)
    vh = np.sqrt(0.5 * one_plus)
    f = 1.0 - vh
    f2 = f * f
    fresnel = f0 + (1.0 - f0) * (f2 * f2 * f)
    lambda_v = np.sqrt(nv * nv * (1.0 - a2) + a2)
    lambda_l = np.sqrt(nl * nl * (1.0 - a2) + a2)
    vis = 0.5 / (nl * lambda_v + nv * lambda_l)
    return (fresnel * distribution * vis * nl).astype(np.float32)


def _ggx_weights_float32(normals: np.ndarray, view: np.ndarray, light_dirs: np.ndarray, a2: np.ndarray,
                         f0: np.ndarray) -> np.ndarray:
    """:func:`ggx_weights` of float32 inputs (a2, f0: (N, 1) float32), each (N, C) term written in place."""
    nl = normals @ light_dirs.T
    np.maximum(nl, 0.0, out=nl)
    one_plus = view @ light_dirs.T
    one_plus += 1.0
    np.maximum(one_plus, 1e-6, out=one_plus)
    nv = np.maximum(np.sum(normals * view, axis=1, keepdims=True), 1e-3)
    d = nl + nv  # nh2 = min((nl + nv)^2 / (2 (1 + v.l)), 1), then d = nh2 (a2 - 1) + 1
    np.square(d, out=d)
    tmp = one_plus * 2.0
    d /= tmp
    np.minimum(d, 1.0, out=d)
    d *= a2 - 1.0
    d += 1.0
    np.multiply(d, np.pi, out=tmp)  # distribution = a2 / (pi d d)
    tmp *= d
    distribution = np.divide(a2, tmp, out=tmp)
    one_plus *= 0.5  # f = 1 - sqrt((1 + v.l) / 2); fresnel = f0 + (1 - f0) f^5
    f = np.sqrt(one_plus, out=one_plus)
    np.subtract(1.0, f, out=f)
    fresnel = np.multiply(f, f, out=d)
    fresnel *= fresnel
    fresnel *= f
    fresnel *= 1.0 - f0
    fresnel += f0
    lambda_v = np.sqrt(nv * nv * (1.0 - a2) + a2)
    lambda_l = np.multiply(nl, nl, out=f)  # vis = 0.5 / (nl lambda_v + nv lambda_l)
    lambda_l *= 1.0 - a2
    lambda_l += a2
    np.sqrt(lambda_l, out=lambda_l)
    lambda_l *= nv
    denominator = nl * lambda_v
    denominator += lambda_l
    fresnel *= distribution
    np.divide(0.5, denominator, out=denominator)
    fresnel *= denominator
    fresnel *= nl
    return fresnel


def pixel_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera centre (3,), unit world ray directions (H, W, 3) float32 through pixel centres, and the
    camera-z component of each unit direction (H, W) (depth = t_hit * that)."""
    K, rotation = camera.K, camera.cam_from_world[:, :3]
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
    return camera.centre_world, (d_cam @ rotation).astype(np.float32), d_cam[..., 2].astype(np.float32)


def background_reflectance(directions: np.ndarray) -> np.ndarray:
    """Dim reflectance (N,) float32 of the LED sphere's inside at unit directions (N, 3) from its centre:
    ~3.5% grey, slightly darker struts every 15 degrees of latitude / longitude, faint cell shading and
    slow mottling."""
    x, y, z = directions[:, 0], directions[:, 1], directions[:, 2]
    lat = np.degrees(np.arcsin(np.clip(y, -1, 1)))
    lon = np.degrees(np.arctan2(z, x))
    strut_lat = np.abs(np.mod(lat + 7.5, 15.0) - 7.5)
    strut_lon = np.abs(np.mod(lon + 7.5, 15.0) - 7.5) * np.cos(np.radians(lat))
    strut = np.minimum(strut_lat, strut_lon) < 0.5
    mottle = 1.0 + 0.15 * np.sin(3.1 * x + 1.3) * np.sin(2.3 * y + 0.4) * np.sin(2.7 * z + 2.1)
    cell = 1.0 + 0.05 * np.cos(np.radians(lat) * 24.0) * np.cos(np.radians(lon) * 24.0)
    value = 0.035 * mottle * cell
    return np.where(strut, 0.028 * mottle, value).astype(np.float32)


def sphere_wall_reflectance(centre: np.ndarray, ray_dirs: np.ndarray, sphere_radius: float) -> np.ndarray:
    """Reflectance (N,) float32 of the LED sphere's far inside wall seen along unit rays (N, 3) from
    `centre` (inside or outside the sphere); rays missing the sphere see a darker room (0.6%)."""
    b = ray_dirs @ centre
    c = float(centre @ centre) - sphere_radius ** 2
    disc = b * b - c
    t = -b + np.sqrt(np.maximum(disc, 0.0))
    hit_dirs = geometry.normalize(centre + t[:, None] * ray_dirs)
    return np.where(disc > 0, background_reflectance(hit_dirs), 0.006).astype(np.float32)


def background_image(camera: Camera, sphere_radius: float) -> np.ndarray:
    """Reflectance (H, W) float32 of the stage background behind the subject, as a camera sees it.
    Its radiance under an illumination is this times the mean LED intensity of each channel."""
    centre, dirs, _ = pixel_rays(camera)
    flat = sphere_wall_reflectance(centre, dirs.reshape(-1, 3).astype(np.float64), sphere_radius)
    return flat.reshape(camera.height, camera.width)


@dataclass(frozen=True)
class ViewRender:
    """One camera's render: radiance (H, W, 9) float32 linear sRGB (full_on, pos, neg x RGB) and the
    ground truth maps: mask (H, W) bool, normals_world (H, W, 3), albedo (H, W, 3), roughness (H, W),
    depth_m (H, W) camera z, visibility (H, W) (0 where the mask is 0)."""
    radiance: np.ndarray
    mask: np.ndarray
    normals_world: np.ndarray
    albedo: np.ndarray
    roughness: np.ndarray
    depth_m: np.ndarray
    visibility: np.ndarray


def render_background(camera: Camera, leds: LedSphere, background: np.ndarray | None = None) -> np.ndarray:
    """Radiance (H, W, 9) of the empty stage (clean plate) seen by a camera; `background` is its
    precomputed `background_image` (H, W), or None to compute it."""
    if background is None:
        background = background_image(camera, leds.radius_m)
    return (background[..., None] * leds.mean_intensity().astype(np.float32)).astype(np.float32)


@dataclass(frozen=True)
class SurfaceHits:
    """Primary-ray hits of one camera: flat pixel indices (N,) of the H*W image, hit triangle ids (N,),
    their vertex ids (N, 3), barycentrics (N, 3) float32, unit directions towards the camera (N, 3)
    float32, backface flags (N,) (the ray entered the mesh through a hole) and camera-z depths (N,)."""
    pixels: np.ndarray
    triangle_ids: np.ndarray
    corners: np.ndarray
    barycentrics: np.ndarray
    view_dirs: np.ndarray
    backface: np.ndarray
    depth_m: np.ndarray

    def interpolate(self, per_vertex: np.ndarray) -> np.ndarray:
        """Barycentric interpolation of per-vertex values (V, C) at the hits, (N, C)."""
        b = self.barycentrics
        return sum(b[:, k:k + 1] * per_vertex[self.corners[:, k]] for k in range(3))


def cast_primary_rays(scene: o3d.t.geometry.RaycastingScene, camera: Camera, triangles: np.ndarray) -> SurfaceHits:
    """One ray through every pixel centre of `camera`; the hits on the mesh (triangles (T, 3))."""
    centre, dirs, dir_z = pixel_rays(camera)
    flat_dirs = dirs.reshape(-1, 3)
    rays = np.concatenate([np.broadcast_to(centre.astype(np.float32), flat_dirs.shape), flat_dirs], axis=1)
    result = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
    primitive = result["primitive_ids"].numpy()
    pixels = np.nonzero(primitive != INVALID_ID)[0]
    triangle_ids = primitive[pixels].astype(np.int64)
    uv = result["primitive_uvs"].numpy()[pixels]
    barycentrics = np.column_stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]]).astype(np.float32)
    view_dirs = -flat_dirs[pixels]
    backface = np.sum(result["primitive_normals"].numpy()[pixels] * view_dirs, axis=1) < 0.0
    depth = result["t_hit"].numpy()[pixels] * dir_z.reshape(-1)[pixels]
    return SurfaceHits(pixels, triangle_ids, triangles[triangle_ids], barycentrics, view_dirs, backface, depth)


def shade_hits(hits: SurfaceHits, subject: ActionSubject, lighting: SurfaceLighting,
               specular: bool = True) -> tuple[np.ndarray, ...]:
    """Radiance and surface attributes at the hits.

    Returns radiance (N, 9) float32 (full_on, pos, neg x RGB), normals_world (N, 3) (facing the camera),
    albedo (N, 3), roughness (N,), visibility (N,) (0 on backfaces: the inside of the body is dark).
    """
    normals = geometry.normalize(hits.interpolate(subject.normals_world.astype(np.float32)),
                                 fallback=(0.0, 0.0, 1.0))
    normals = np.where(hits.backface[:, None], -normals, normals).astype(np.float32)
    points_rest = hits.interpolate(subject.vertices_rest)
    uvs = None
    corner_uvs = subject.corner_uvs
    if corner_uvs is not None:
        uvs = np.einsum("nk,nkc->nc", hits.barycentrics.astype(np.float64), corner_uvs[hits.triangle_ids])
    albedo, roughness, f0, _ = subject.materials(points_rest, uvs, hits.corners[:, 0])
    irradiance = hits.interpolate(lighting.irradiance)
    visibility = np.clip(hits.interpolate(lighting.visible_fraction[:, None])[:, 0], 0.0, 1.0)
    irradiance[hits.backface] = 0.0
    visibility[hits.backface] = 0.0
    radiance = np.tile(albedo / np.pi, 3) * irradiance
    if specular and lighting.clusters:
        glossy = specular_radiance(normals, hits.view_dirs, roughness, f0, hits.corners, hits.barycentrics, lighting)
        radiance += glossy * (~hits.backface)[:, None]
    return radiance.astype(np.float32), normals, albedo, roughness, visibility.astype(np.float32)


def render_view(scene: o3d.t.geometry.RaycastingScene, subject: ActionSubject, lighting: SurfaceLighting,
                leds: LedSphere, camera: Camera, specular: bool = True,
                background: np.ndarray | None = None, supersample: int = 1) -> ViewRender:
    """Render one camera: primary rays, interpolated surface attributes, diffuse + specular shading,
    the dim stage behind. `background`: the camera's precomputed `background_image` (H, W), or None.

    `supersample` s > 1 traces s x s rays per pixel (a regular grid over the pixel's square) and box-averages
    them, as a sensor pixel integrates light over its area: silhouette pixels mix subject and stage, and
    surface detail finer than a pixel is averaged instead of aliased. The ground-truth maps are the same
    pixel averages over the rays that hit the subject (normals renormalised); the mask holds pixels where
    at least half the rays hit; the background is the pixel-centre value of `background`."""
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    if supersample > 1:
        return _render_view_supersampled(scene, subject, lighting, leds, camera, specular, background, supersample)
    hits = cast_primary_rays(scene, camera, subject.triangles)
    shaded = shade_hits(hits, subject, lighting, specular)
    return view_from_hits(hits, *shaded, camera.height, camera.width, render_background(camera, leds, background))


def view_from_hits(hits: SurfaceHits, radiance: np.ndarray, normals: np.ndarray, albedo: np.ndarray,
                   roughness: np.ndarray, visibility: np.ndarray, height: int, width: int,
                   behind: np.ndarray | None = None) -> ViewRender:
    """Per-hit shading (shade_hits' outputs, (N, C)) scattered to a ViewRender of height x width; `behind`:
    (H, W, C) radiance where no ray hit (None: 0)."""
    channels = radiance.shape[-1]
    image = np.zeros((height * width, channels), np.float32) if behind is None else \
        np.array(behind, np.float32).reshape(-1, channels)
    image[hits.pixels] = radiance
    mask = np.zeros(height * width, bool)
    mask[hits.pixels] = True

    def scatter(values: np.ndarray, c: int) -> np.ndarray:
        return hits_image(hits.pixels, values, c, height, width)

    return ViewRender(image.reshape(height, width, channels), mask.reshape(height, width), scatter(normals, 3),
                      scatter(albedo, 3), scatter(roughness, 1), scatter(hits.depth_m, 1), scatter(visibility, 1))


def supersampled_camera(camera: Camera, s: int) -> Camera:
    """The camera with an s-times finer pixel grid over the same sensor: pixel (i, j) of ``camera`` covers
    the fine pixels (s i .. s i + s - 1, s j .. s j + s - 1), whose centres are a regular grid in its square."""
    K = np.array(camera.K, np.float64)
    K[0, 0] *= s
    K[1, 1] *= s
    K[0, 1] *= s
    K[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    return dataclasses.replace(camera, width=camera.width * s, height=camera.height * s, K=K)


def _render_view_supersampled(scene: o3d.t.geometry.RaycastingScene, subject: ActionSubject,
                              lighting: SurfaceLighting, leds: LedSphere, camera: Camera, specular: bool,
                              background: np.ndarray | None, s: int) -> ViewRender:
    if background is None:
        background = background_image(camera, leds.radius_m)
    fine = render_view(scene, subject, lighting, leds, supersampled_camera(camera, s), specular,
                       np.repeat(np.repeat(background, s, axis=0), s, axis=1))
    return pixel_average(fine, s)


def pixel_average(fine: ViewRender, s: int) -> ViewRender:
    """A render on an s-times finer grid (:func:`supersampled_camera`) averaged to the camera's pixels: the
    radiance over all s x s rays, the ground-truth maps over the rays that hit the subject (normals
    renormalised), the mask where at least half of them did; every map is 0 off the mask."""
    h, w = fine.mask.shape[0] // s, fine.mask.shape[1] // s
    if (h * s, w * s) != fine.mask.shape:
        raise ValueError(f"a {fine.mask.shape} render is not {s} x {s} rays per pixel")

    def blocks(x: np.ndarray) -> np.ndarray:
        """(H s, W s, ...) -> per-pixel sums (H, W, ...)."""
        return x.reshape((h, s, w, s) + x.shape[2:]).sum(axis=(1, 3), dtype=np.float64)

    hit = fine.mask.astype(np.float64)
    count = blocks(hit)
    inv = np.divide(1.0, count, out=np.zeros_like(count), where=count > 0)
    mask = count >= 0.5 * s * s

    def over_hits(x: np.ndarray) -> np.ndarray:
        x3 = x if x.ndim == 3 else x[..., None]
        out = np.where(mask[..., None], blocks(x3 * hit[..., None]) * inv[..., None], 0.0).astype(np.float32)
        return out if x.ndim == 3 else out[..., 0]

    normals = over_hits(fine.normals_world)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 1e-6)
    return ViewRender((blocks(fine.radiance) / (s * s)).astype(np.float32), mask, normals,
                      over_hits(fine.albedo), over_hits(fine.roughness), over_hits(fine.depth_m),
                      over_hits(fine.visibility))


def hits_image(pixels: np.ndarray, values: np.ndarray, channels: int, height: int, width: int) -> np.ndarray:
    """Per-hit values (N, channels) scattered to an image at flat pixel indices (N,): (H, W, C) float32, or
    (H, W) for one channel; 0 where nothing was hit."""
    out = np.zeros((height * width, channels), np.float32)
    out[pixels] = values.reshape(len(pixels), channels)
    return out.reshape(height, width, channels) if channels > 1 else out.reshape(height, width)


def specular_radiance(normals: np.ndarray, view: np.ndarray, roughness: np.ndarray, f0: np.ndarray,
                      tri: np.ndarray, bary: np.ndarray, lighting: SurfaceLighting) -> np.ndarray:
    """GGX radiance (N, 9) at N pixels against the LED clusters of each pixel's lobe width.

    normals, view: (N, 3); roughness, f0: (N,); tri: (N, 3) vertex ids; bary: (N, 3).
    """
    alpha = roughness.astype(np.float32) ** 2
    pixel_levels = level_of(alpha, lighting.levels)
    out = np.zeros((len(normals), 9), np.float32)
    # the fused loop takes the visibility too, where the dtypes are the renderer's
    fused = (normals.dtype == view.dtype == bary.dtype == np.float32 and kernels.kernel_available()
             and all(c.directions.dtype == np.float32 for c in lighting.clusters)
             and all(v.dtype == np.uint8 for v in lighting.cluster_visibility))
    a2 = (alpha * alpha).astype(np.float32)[:, None]
    f0_column = f0.astype(np.float32)[:, None]
    for level_index, (clusters, cluster_vis) in enumerate(zip(lighting.clusters, lighting.cluster_visibility)):
        members = np.nonzero(pixel_levels == level_index)[0]
        chunk = max(64, CHUNK_ELEMENTS // len(clusters.directions))
        for start in range(0, len(members), chunk):
            sel = members[start:start + chunk]
            t, b = tri[sel], bary[sel] * np.float32(1.0 / 255.0)
            if fused:
                weights = _ggx_fused(normals[sel], view[sel], clusters.directions, a2[sel], f0_column[sel],
                                     cluster_vis, t, b)
            else:
                weights = ggx_weights(normals[sel], view[sel], clusters.directions, alpha[sel], f0[sel])
                vis = cluster_vis[t[:, 0]] * b[:, 0:1]
                vis += cluster_vis[t[:, 1]] * b[:, 1:2]
                vis += cluster_vis[t[:, 2]] * b[:, 2:3]
                weights *= vis
            out[sel] = weights @ clusters.irradiance
    return out


def _ggx_fused(normals: np.ndarray, view: np.ndarray, light_dirs: np.ndarray, a2: np.ndarray, f0: np.ndarray,
               cluster_vis: np.ndarray | None = None, tri: np.ndarray | None = None,
               bary: np.ndarray | None = None) -> np.ndarray:
    """:func:`ggx_weights` of float32 inputs (a2, f0: (N, 1) float32) by the fused loop of :mod:`synthetic.kernels`
    (which must be available), and with ``cluster_vis`` (V, C) uint8, ``tri`` (N, 3) and ``bary`` (N, 3) float32
    (barycentrics over 255) times the lights' visibility as :func:`specular_radiance` interpolates it; the bits of
    the numpy steps either way."""
    nl = normals @ light_dirs.T
    nv = np.maximum(np.sum(normals * view, axis=1, keepdims=True), 1e-3)
    lambda_v = np.sqrt(nv * nv * (1.0 - a2) + a2)
    kernels.ggx_terms(nl, view @ light_dirs.T, nv, lambda_v, a2, f0, cluster_vis, tri, bary)
    return nl
