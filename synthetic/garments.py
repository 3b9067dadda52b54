"""Hair and a loose skirt for the MakeHuman subject: their styles (drawn per action), geometry and albedo.

- Hair is a volume on the scalp: the head's vertices are pushed out along their normals by the style's
  thickness times a hair weight (:func:`hair_weight`), 1 on the scalp and falling to 0 over about a centimetre
  at the hairline (high on the forehead, lower at the sides and down to the nape at the back). The weight is a
  function of the rest-frame (unshaped, unposed) position, so the hair region of a surface point is found from
  the same position the other regions are (synthetic.subject.region_of).
- The skirt is a closed thin shell (outer and inner surfaces ``SKIRT_THICKNESS_M`` apart, joined at the hem and
  at the waist) hanging from the belt to the style's hem above the knees: its radius about the pelvis' vertical
  axis is, per angle and height, the body's outer extent there (ray cast from outside, arms left out) plus a
  clearance that grows downwards with the flare, so it leaves the legs' surface and never cuts into it in the
  rest pose. Its top ring sits 3 mm inside the waist. It is skinned with the skinning weights of the nearest
  body vertices, so it follows the hips and thighs when posed (cloth dynamics are not simulated: a strongly
  swung leg can push through it).

Everything here is arrays in, arrays out.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometry

HAIR_COLOURS = np.array([  # linear albedos: black, dark brown, brown, auburn, dark blond, grey
    [0.016, 0.013, 0.011], [0.035, 0.022, 0.014], [0.07, 0.043, 0.025], [0.11, 0.045, 0.022],
    [0.20, 0.13, 0.065], [0.17, 0.165, 0.16]])
HAIR_MAX_THICKNESS_M = 0.03
"""Largest hair thickness a style draws (the cameras' framing leaves this much above the head)."""
SKIRT_THICKNESS_M = 0.004
"""Distance between the skirt's outer and inner surfaces."""
SKIRT_CLEARANCE_M = 0.012
"""Least gap between the skirt's outer surface and the body below its waist ring."""


@dataclass(frozen=True)
class HairStyle:
    """Hair of one action: colour (3,) linear albedo, thickness at the crown (m), hairline heights (the cosine
    of the angle from the head's up axis below which there is no hair, at the front and the back), strand
    streak period (m) and contrast."""
    colour: np.ndarray
    thickness_m: float
    front_line: float
    back_line: float
    streak_period_m: float
    streak_contrast: float

    def to_json(self) -> dict:
        return {"colour": np.round(self.colour, 4).tolist(), "thickness_m": round(self.thickness_m, 4),
                "front_hairline": round(self.front_line, 3), "back_hairline": round(self.back_line, 3),
                "streak_period_m": round(self.streak_period_m, 4),
                "streak_contrast": round(self.streak_contrast, 3)}


def draw_hair(rng: np.random.Generator) -> HairStyle:
    """A random hair style: colour one of HAIR_COLOURS (x 0.85..1.15), 1..3 cm thick, a hairline from a high
    forehead to a low one, from the nape to mid-neck at the back."""
    colour = HAIR_COLOURS[int(rng.integers(len(HAIR_COLOURS)))] * float(rng.uniform(0.85, 1.15))
    return HairStyle(colour, float(rng.uniform(0.01, HAIR_MAX_THICKNESS_M)), float(rng.uniform(0.3, 0.55)),
                     float(rng.uniform(-0.6, -0.3)), float(rng.uniform(0.002, 0.004)), float(rng.uniform(0.3, 0.6)))


def head_frame(landmarks: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Head centre (3,) (45% of the way from the neck joint to the top of the head, 5 cm forward) and the
    head's unit up axis (3,), from rest-frame skeleton landmarks."""
    neck, top = np.asarray(landmarks["neck"], np.float64), np.asarray(landmarks["head_top"], np.float64)
    up = geometry.normalize(top - neck)
    return neck + 0.45 * (top - neck) + np.array([0.0, 0.0, 0.05]), up


def hair_weight(points: np.ndarray, landmarks: dict[str, np.ndarray], style: HairStyle) -> np.ndarray:
    """Hair weight (N,) in [0, 1] of rest-frame points (N, 3): 1 on the scalp, 0 off the head and below the
    hairline, a smooth step of width ~0.12 in the cosine between (about 1.2 cm on the head)."""
    centre, up = head_frame(landmarks)
    offset = np.asarray(points, np.float64) - centre
    distance = np.linalg.norm(offset, axis=1)
    direction = offset / np.maximum(distance, 1e-9)[:, None]
    cos_up = direction @ up
    frontness = smoothstep(-0.3, 0.5, direction[:, 2])
    line = style.front_line * frontness + style.back_line * (1.0 - frontness)
    on_head = 1.0 - smoothstep(0.15, 0.18, distance)
    return smoothstep(line - 0.06, line + 0.06, cos_up) * on_head


def hair_displacement(vertices: np.ndarray, weight_points: np.ndarray, landmarks: dict[str, np.ndarray],
                      style: HairStyle) -> np.ndarray:
    """Outward displacement (V,) metres of the hair volume at vertices (V, 3), whose hair weight is taken at
    `weight_points` (V, 3) (their rest-frame positions): thickness x weight x a slow +-15% lumpiness."""
    lumps = 1.0 + 0.15 * np.sin(vertices @ np.array([23.0, 31.0, -17.0]) + 1.3) * np.sin(
        vertices @ np.array([-19.0, 13.0, 29.0]) + 0.4)
    return style.thickness_m * hair_weight(weight_points, landmarks, style) * lumps


def hair_albedo(points: np.ndarray, landmarks: dict[str, np.ndarray], style: HairStyle) -> np.ndarray:
    """Hair albedo (N, 3) float32 at rest points (N, 3): the colour with fine streaks running down from the
    crown (along the head's meridians) and a slow darkening towards the ends."""
    centre, up = head_frame(landmarks)
    offset = np.asarray(points, np.float64) - centre
    side = geometry.normalize(np.cross(up, [0.0, 0.0, 1.0]))
    forward = np.cross(side, up)
    azimuth = np.arctan2(offset @ side, offset @ forward)
    cos_up = geometry.normalize(offset, fallback=(0.0, 1.0, 0.0)) @ up
    arc = azimuth * 0.1  # metres round the head at a 10 cm radius
    wave = 2.0 * np.pi / style.streak_period_m
    streak = (np.sin(arc * wave + 2.0 * np.sin(cos_up * 9.0)) * 0.6
              + np.sin(arc * wave * 2.7 + 1.7 + 3.0 * cos_up) * 0.4)
    shade = (1.0 + style.streak_contrast * 0.5 * streak) * (0.8 + 0.2 * np.clip(cos_up, 0.0, 1.0))
    return (style.colour[None, :] * shade[:, None]).astype(np.float32)


@dataclass(frozen=True)
class GarmentStyle:
    """A skirt of one action: hem height (fraction of the way from the knees up to the waist), flare angle,
    pleats (count, depth m, phase), and its cloth (pattern as synthetic.subject.cloth_albedo, colours (2, 3)
    linear albedo, period m)."""
    hem: float
    flare_deg: float
    pleats: int
    pleat_depth_m: float
    pleat_phase: float
    pattern: str
    colours: np.ndarray
    period_m: float

    def to_json(self) -> dict:
        return {"kind": "skirt", "hem_above_knee": round(self.hem, 3), "flare_deg": round(self.flare_deg, 2),
                "pleats": self.pleats, "pleat_depth_m": round(self.pleat_depth_m, 4),
                "pattern": self.pattern, "colours": np.round(self.colours, 4).tolist(),
                "period_m": round(self.period_m, 4), "thickness_m": SKIRT_THICKNESS_M}


def draw_garment(rng: np.random.Generator, fabric_colours: np.ndarray) -> GarmentStyle:
    """A random skirt: hem 10..45% of the way from the knees to the waist, flare 8..22 degrees, 0 or 8..20
    pleats up to 1.5 cm deep, plain / stripes / checks in two of `fabric_colours` ((K, 3) linear)."""
    pleats = int(rng.choice([0, int(rng.integers(8, 21))]))
    colours = fabric_colours[rng.choice(len(fabric_colours), 2, replace=False)]
    return GarmentStyle(float(rng.uniform(0.1, 0.45)), float(rng.uniform(8.0, 22.0)), pleats,
                        float(rng.uniform(0.004, 0.015)) if pleats else 0.0, float(rng.uniform(0, 2 * np.pi)),
                        ("plain", "stripes", "checks")[int(rng.integers(3))], colours,
                        float(rng.uniform(0.03, 0.07)))


def body_extent_rings(vertices: np.ndarray, triangles: np.ndarray, axis_xz: np.ndarray, heights: np.ndarray,
                      angles: np.ndarray, reach_m: float = 1.0) -> np.ndarray:
    """Outer extent (R, A) metres of a mesh about a vertical axis: per height (R,) and angle (A,) (about +y,
    0 = +z), the distance from the axis of the first surface a ray from `reach_m` outside meets going
    towards the axis (0 where it meets none). vertices (V, 3), triangles (T, 3), axis_xz (2,)."""
    from .shading import raycasting_scene

    scene = raycasting_scene(vertices, triangles)
    radial = np.stack([np.sin(angles), np.zeros_like(angles), np.cos(angles)], axis=1)  # (A, 3)
    axis = np.array([axis_xz[0], 0.0, axis_xz[1]])
    origins = axis[None, None, :] + reach_m * radial[None, :, :] + np.asarray(heights)[:, None, None] * [0, 1, 0]
    directions = np.broadcast_to(-radial[None], origins.shape)
    import open3d as o3d

    rays = np.concatenate([origins, directions], axis=-1).reshape(-1, 6).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(len(heights), len(angles))
    return np.where(np.isfinite(t_hit), np.maximum(reach_m - t_hit, 0.0), 0.0)


def skirt_radii(extent: np.ndarray, heights: np.ndarray, style: GarmentStyle, angles: np.ndarray) -> np.ndarray:
    """Outer radius (R, A) of the skirt's rings from the body's outer extent (R, A) at ring heights (R,)
    (from the waist down) and angles (A,): the top ring 3 mm inside the waist; below it the largest extent of
    the rings above plus the clearance and the flare, smoothed round the ring, never closer than the clearance,
    with pleats deepening towards the hem."""
    drop = heights[0] - heights  # (R,) metres below the waist
    running = np.maximum.accumulate(extent, axis=0)
    radius = running + SKIRT_CLEARANCE_M + drop[:, None] * np.tan(np.radians(style.flare_deg))
    n = len(angles)
    kernel = np.exp(-0.5 * (np.arange(-6, 7) / 2.5) ** 2)
    kernel /= kernel.sum()
    padded = np.concatenate([radius[:, -6:], radius, radius[:, :6]], axis=1)
    smooth = np.stack([np.convolve(row, kernel, mode="valid") for row in padded])[:, :n]
    radius = np.maximum(smooth, running + SKIRT_CLEARANCE_M)
    if style.pleats:
        depth = style.pleat_depth_m * (drop / max(drop[-1], 1e-6))[:, None]
        radius = radius + depth * 0.5 * (1.0 + np.cos(style.pleats * angles + style.pleat_phase))[None, :]
    radius[0] = np.maximum(extent[0] - 0.003, 0.02)
    return radius


def skirt_shell(radius: np.ndarray, heights: np.ndarray, angles: np.ndarray,
                axis_xz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed thin shell from outer ring radii (R, A) at heights (R,) and angles (A,) about the axis (2,):
    vertices (2 R A, 3) (outer rings, then inner rings SKIRT_THICKNESS_M inside), outward-wound triangles, and
    whether each vertex is on the outer surface (2 R A,) bool."""
    n_rings, n_angles = radius.shape
    inner = np.maximum(radius - SKIRT_THICKNESS_M, 0.5 * radius)

    def ring_points(r: np.ndarray) -> np.ndarray:
        return np.stack([axis_xz[0] + r * np.sin(angles)[None, :], np.broadcast_to(heights[:, None], r.shape),
                         axis_xz[1] + r * np.cos(angles)[None, :]], axis=-1).reshape(-1, 3)

    vertices = np.concatenate([ring_points(radius), ring_points(inner)])
    k, j = np.meshgrid(np.arange(n_rings - 1), np.arange(n_angles), indexing="ij")
    k, j = k.ravel(), j.ravel()
    jn = (j + 1) % n_angles

    def vid(ring: np.ndarray, col: np.ndarray, surface: int) -> np.ndarray:
        return surface * n_rings * n_angles + ring * n_angles + col

    a, b, c, d = vid(k, j, 0), vid(k + 1, j, 0), vid(k, jn, 0), vid(k + 1, jn, 0)
    outer = np.concatenate([np.stack([a, b, c], 1), np.stack([c, b, d], 1)])
    a, b, c, d = vid(k, j, 1), vid(k + 1, j, 1), vid(k, jn, 1), vid(k + 1, jn, 1)
    inner_tris = np.concatenate([np.stack([a, c, b], 1), np.stack([c, d, b], 1)])
    j = np.arange(n_angles)
    jn = (j + 1) % n_angles
    last = np.full(n_angles, n_rings - 1)
    o, i, on, inn = vid(last, j, 0), vid(last, j, 1), vid(last, jn, 0), vid(last, jn, 1)
    hem = np.concatenate([np.stack([o, i, on], 1), np.stack([on, i, inn], 1)])
    first = np.zeros(n_angles, np.int64)
    o, i, on, inn = vid(first, j, 0), vid(first, j, 1), vid(first, jn, 0), vid(first, jn, 1)
    top = np.concatenate([np.stack([o, on, i], 1), np.stack([on, inn, i], 1)])
    triangles = np.concatenate([outer, inner_tris, hem, top]).astype(np.int64)
    is_outer = np.arange(len(vertices)) < n_rings * n_angles
    return vertices, triangles, is_outer


SKIRT_PARTS = ("skirt_outer", "skirt_inner", "skirt_hem", "skirt_waist")
"""Names of :func:`skirt_triangle_parts`' labels, in label order."""


def skirt_triangle_parts(n_triangles: int, n_angles: int) -> np.ndarray:
    """Which part of the skirt (an index into SKIRT_PARTS) each of :func:`skirt_shell`'s triangles is on, from the
    shell's triangle count and its vertices per ring: (n_triangles,) int64 in the order skirt_shell writes them
    (outer surface, inner surface, hem band, waist band).

    Raises:
        ValueError: ``n_triangles`` is not 4 x rings x ``n_angles`` for some rings >= 2.
    """
    rings, remainder = divmod(int(n_triangles), 4 * int(n_angles))
    if remainder or rings < 2:
        raise ValueError(f"{n_triangles} triangles are not a skirt shell of {n_angles} vertices per ring "
                         f"(4 x rings x {n_angles}, rings >= 2)")
    side = 2 * (rings - 1) * n_angles
    return np.repeat(np.arange(4, dtype=np.int64), [side, side, 2 * n_angles, 2 * n_angles])


def transfer_weights(points: np.ndarray, body_vertices: np.ndarray, body_weights: np.ndarray,
                     k: int = 8) -> np.ndarray:
    """Skinning weights (N, B) of points (N, 3): the inverse-distance mean of the weights (V, B) of their k
    nearest body vertices (V, 3); rows sum to 1."""
    from scipy.spatial import cKDTree

    distance, index = cKDTree(body_vertices).query(points, k=k)
    inverse = 1.0 / np.maximum(distance, 1e-4)
    weights = np.einsum("nk,nkb->nb", inverse, body_weights[index])
    return weights / weights.sum(axis=1, keepdims=True)


def smoothstep(edge0: float | np.ndarray, edge1: float | np.ndarray, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 at edge0 to 1 at edge1 (elementwise; edges may be arrays)."""
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)
