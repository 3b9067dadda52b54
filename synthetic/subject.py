"""The subject: a mesh in the stage frame with per-point materials (albedo, roughness, Fresnel F0).

Four kinds:
- ``makehuman``: the MakeHuman body (``body`` group only; decimetre units scaled to metres, ~1.67 m), a
  MakeHuman skin atlas (sRGB PNG, linearised) per action, a shirt and trousers with procedural stripe /
  check / denim albedo and displaced folds, shiny shoes and belt.
- ``procedural``: a smooth union of capsules (torso, arms close to it, legs, neck), a sphere head and a
  torus round the waist, meshed by marching cubes; it has concavities and self-occlusion like a body.
- ``obj``: any other OBJ, one skin-like material with a procedural albedo by 3D position.
- ``mesh``: a PLY, glTF / GLB, STL, OFF, ... file (read with trimesh), the same material as ``obj``.

Each action varies the subject deterministically from (seed, action index): skin atlas or tone, yaw about
+y, cloth pattern and colours, fold pattern, and on the MakeHuman body only: a body shape (MakeHuman's macro
targets, synthetic.body, when SimConfig.body is set), hair and a loose skirt (synthetic.garments, per action
with SimConfig.hair / SimConfig.garment), and (`pose_variation` > 0) a pose: joint angles of a
linear-blend-skinned skeleton (synthetic.pose). The mesh is shaped first (the skeleton's joints follow the
shaped mesh, the skinning weights stay the base mesh's), then folded, given its hair, dressed, posed and
yawed. Materials are evaluated per surface point from its rest-frame (unshaped, unposed, unyawed) position,
so solid textures and cloth regions move with the body, and UV; the skirt's points carry their region.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import InputError

from . import body as body_shape
from . import garments, geometry, pose
from .body import BodyParams
from .garments import GarmentStyle, HairStyle

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_MESHES = REPO_ROOT.parent / "shared" / "data" / "meshes"
DEFAULT_MESH = SHARED_MESHES / "makehuman_base.obj"
"""The default subject; `SimConfig.mesh = None` uses it when it exists, else the procedural subject."""

MAKEHUMAN_UNITS_M = 0.1
"""MakeHuman base meshes are in decimetres."""
TARGETS_FOLDER = "makehuman_targets"
"""MakeHuman's macro targets: beside the mesh, else in SHARED_MESHES."""

# Region ids and their materials: (name, roughness, F0).
SKIN, SHIRT, TROUSERS, SHINY = 0, 1, 2, 3
MATERIALS = {
    SKIN: ("skin", 0.45, 0.028),
    SHIRT: ("cloth_shirt", 0.80, 0.04),
    TROUSERS: ("cloth_trousers", 0.70, 0.04),
    SHINY: ("leather_shiny", 0.25, 0.04),
}
"""The regions every subject can have."""
HAIR, GARMENT = 4, 5
EXTRA_MATERIALS = {
    HAIR: ("hair", 0.65, 0.046),  # keratin, n ~ 1.55; rougher than skin
    GARMENT: ("cloth_skirt", 0.85, 0.04),
}
"""Regions of the optional hair and skirt (listed in truth.json only for the actions that have them)."""
ALL_MATERIALS = MATERIALS | EXTRA_MATERIALS

FABRIC_COLOURS = np.array([  # linear sRGB diffuse albedos
    [0.03, 0.05, 0.16], [0.72, 0.71, 0.66], [0.42, 0.04, 0.05], [0.07, 0.22, 0.09], [0.22, 0.22, 0.23],
    [0.52, 0.34, 0.05], [0.30, 0.46, 0.68], [0.04, 0.04, 0.04], [0.55, 0.25, 0.35], [0.12, 0.30, 0.32]])
SKIN_TONES = np.array([[0.56, 0.36, 0.26], [0.42, 0.25, 0.16], [0.22, 0.12, 0.07], [0.62, 0.43, 0.33]])


@dataclass(frozen=True)
class BaseSubject:
    """Action-independent geometry: rest-frame mesh in metres, bounding box centred at the stage origin.

    vertices: (V, 3) float64; triangles: (T, 3) int64; corner_uvs: (T, 3, 2) or None; landmarks: skeleton
    landmark -> (3,) rest position (synthetic.pose.MAKEHUMAN_JOINTS) or None when the subject cannot be posed.
    """
    kind: str
    name: str
    source: str | None
    units_m: float
    vertices: np.ndarray
    triangles: np.ndarray
    corner_uvs: np.ndarray | None
    skins: tuple[str, ...] = ()
    landmarks: dict[str, np.ndarray] | None = field(default=None, compare=False)
    shaping: "ShapingData | None" = field(default=None, compare=False)
    """What body shaping needs (MakeHuman subjects whose targets folder exists), else None."""

    @functools.cached_property
    def skeleton(self) -> pose.Skeleton | None:
        """Joints and smooth skinning weights of the rest mesh (computed on first use), None if unposable."""
        if self.landmarks is None:
            return None
        return pose.Skeleton(pose.bone_joints(self.landmarks), self.landmarks,
                             pose.skinning_weights(self.vertices, self.triangles, self.landmarks))

    @property
    def y_range(self) -> tuple[float, float]:
        return float(self.vertices[:, 1].min()), float(self.vertices[:, 1].max())

    @property
    def radius_xz(self) -> float:
        """Largest distance of a vertex from the +y axis (yaw invariant), metres."""
        return float(np.sqrt(self.vertices[:, 0] ** 2 + self.vertices[:, 2] ** 2).max())


@dataclass(frozen=True)
class ShapingData:
    """How MakeHuman targets (indexed by OBJ vertex) reach a base subject's vertices.

    obj_vertex_count: vertices of the OBJ file; source_ids: (V0,) OBJ index of each kept vertex before
    subdivision; coarse_triangles: (T0, 3) their triangles; subdivisions: Loop steps from those to the base's
    vertices (Loop subdivision is linear in the positions, so it carries offsets the same way);
    landmark_ids: landmark -> OBJ indices of its joint group; targets_dir: the targets folder.
    """
    obj_vertex_count: int
    source_ids: np.ndarray
    coarse_triangles: np.ndarray
    subdivisions: int
    landmark_ids: dict[str, np.ndarray]
    targets_dir: str


@dataclass(frozen=True)
class ClothStyle:
    """Procedural cloth of one action."""
    shirt_pattern: str          # "stripes" | "checks" | "plain"
    shirt_colours: np.ndarray   # (2, 3) linear albedo
    shirt_period_m: float
    shirt_tilt: float           # stripe direction tilt (radians)
    trousers_pattern: str       # "denim" | "checks" | "plain"
    trousers_colours: np.ndarray
    trousers_period_m: float
    fold_freqs: np.ndarray      # (J, 3) angular spatial frequencies of the folds (rad/m)
    fold_phases: np.ndarray     # (J,)
    fold_amplitude_m: float

    def to_json(self) -> dict:
        return {"shirt": {"pattern": self.shirt_pattern, "colours": self.shirt_colours.round(4).tolist(),
                          "period_m": round(self.shirt_period_m, 4), "tilt_rad": round(self.shirt_tilt, 4)},
                "trousers": {"pattern": self.trousers_pattern,
                             "colours": self.trousers_colours.round(4).tolist(),
                             "period_m": round(self.trousers_period_m, 4)},
                "folds": {"amplitude_m": round(self.fold_amplitude_m, 5),
                          "wavelengths_m": (2 * np.pi / np.linalg.norm(self.fold_freqs, axis=1)).round(4).tolist()}}


@dataclass(frozen=True)
class ActionSubject:
    """The subject of one action: displaced rest mesh, world mesh (posed, then yawed) and material parameters.

    vertices_rest / vertices_world / normals_world: (V, 3) float64; skin_texture: (h, w, 3) float32 linear
    albedo atlas or None; pose_deg: joint angle name -> degrees (synthetic.pose.POSE_RANGES_DEG), None when
    the subject is not posed (pose_variation 0 or no skeleton).
    """
    base: BaseSubject
    label: str
    yaw_rad: float
    skin_name: str
    skin_texture: np.ndarray | None
    skin_tone: np.ndarray
    cloth: ClothStyle
    vertices_rest: np.ndarray
    vertices_world: np.ndarray
    normals_world: np.ndarray
    pose_deg: dict[str, float] | None = None
    body: BodyParams | None = None
    """The MakeHuman macro parameters the mesh was shaped with; None: the base mesh as it is."""
    hair: HairStyle | None = None
    garment: GarmentStyle | None = None
    garment_triangles: np.ndarray | None = None
    """(Tg, 3) triangles of the skirt, indexing vertices after the body's (None without a garment)."""

    @property
    def triangles(self) -> np.ndarray:
        """(T, 3): the base's triangles, then the skirt's."""
        if self.garment_triangles is None:
            return self.base.triangles
        return np.concatenate([self.base.triangles, self.garment_triangles])

    @property
    def corner_uvs(self) -> np.ndarray | None:
        """(T, 3, 2) UVs of `triangles` (the skirt's are 0: it has no atlas), or None."""
        if self.base.corner_uvs is None or self.garment_triangles is None:
            return self.base.corner_uvs
        return np.concatenate([self.base.corner_uvs, np.zeros((len(self.garment_triangles), 3, 2))])

    def materials(self, points_rest: np.ndarray, uvs: np.ndarray | None,
                  vertex_ids: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """Materials at surface points.

        Args:
            points_rest: (N, 3) rest-frame positions (metres). uvs: (N, 2) texture coordinates or None.
            vertex_ids: (N,) a vertex of each point's triangle: points on the skirt's triangles are GARMENT
                (None: the points are taken to be on the body).

        Returns:
            albedo (N, 3) float32 linear sRGB, roughness (N,) float32, f0 (N,) float32, region (N,) int8.
        """
        region = region_of(self.base, points_rest)
        if self.hair is not None:
            region[garments.hair_weight(points_rest, self.base.landmarks, self.hair) > 0.5] = HAIR
        if self.garment_triangles is not None and vertex_ids is not None:
            region[np.asarray(vertex_ids) >= len(self.base.vertices)] = GARMENT
        n = len(points_rest)
        albedo = np.zeros((n, 3), np.float32)
        skin = region == SKIN
        if self.skin_texture is not None and uvs is not None:
            albedo[skin] = sample_bilinear(self.skin_texture, uvs[skin])
        else:
            albedo[skin] = skin_albedo(points_rest[skin], self.skin_tone)
        for reg, pattern, colours, period, tilt in (
                (SHIRT, self.cloth.shirt_pattern, self.cloth.shirt_colours, self.cloth.shirt_period_m,
                 self.cloth.shirt_tilt),
                (TROUSERS, self.cloth.trousers_pattern, self.cloth.trousers_colours,
                 self.cloth.trousers_period_m, 0.0)):
            sel = region == reg
            albedo[sel] = cloth_albedo(points_rest[sel], pattern, colours, period, tilt)
        shiny = region == SHINY
        albedo[shiny] = shiny_albedo(points_rest[shiny], self.base.kind)
        if self.hair is not None:
            hair = region == HAIR
            albedo[hair] = garments.hair_albedo(points_rest[hair], self.base.landmarks, self.hair)
        if self.garment is not None:
            skirt = region == GARMENT
            albedo[skirt] = cloth_albedo(points_rest[skirt], self.garment.pattern, self.garment.colours,
                                         self.garment.period_m, 0.0)
        roughness = np.array([ALL_MATERIALS[k][1] for k in range(len(ALL_MATERIALS))], np.float32)[region]
        f0 = np.array([ALL_MATERIALS[k][2] for k in range(len(ALL_MATERIALS))], np.float32)[region]
        return np.clip(albedo, 0.0, 1.0), roughness, f0, region.astype(np.int8)


# --- loading -------------------------------------------------------------------------------------------

def resolve_mesh(mesh: str | None) -> Path | None:
    """The mesh file a config means, or None for the procedural subject (InputError if it is missing)."""
    if mesh is None:
        return DEFAULT_MESH if DEFAULT_MESH.is_file() else None
    if mesh == "procedural":
        return None
    path = Path(mesh).expanduser()
    if not path.is_file():
        raise InputError(path, "subject mesh does not exist")
    return path


@functools.lru_cache(maxsize=4)
def load_base_subject(mesh_path: str | None, subdivisions: int) -> BaseSubject:
    """Read (or build) the subject geometry, scale to metres, centre it, subdivide.

    OBJ files are parsed here (groups kept: a `body` group makes a MakeHuman subject, whose `joint-*`
    groups give the skeleton landmarks); any other format is read with trimesh as one triangle mesh.
    A file that cannot be read raises InputError naming it and the reason.
    """
    if mesh_path is None:
        vertices, triangles = procedural_body_mesh()
        return BaseSubject("procedural", "procedural/capsules-torus", None, 1.0, vertices, triangles, None)
    landmarks, shaping = None, None
    if Path(mesh_path).suffix.lower() == ".obj":
        try:
            obj = geometry.read_obj(mesh_path)
            is_makehuman = "body" in set(obj.groups)
            if is_makehuman:
                vertices, triangles, corner_uvs, source_ids = geometry.triangulate_with_ids(obj, lambda g: g == "body")
                units_m = MAKEHUMAN_UNITS_M
                found = geometry.group_centroids(obj, pose.MAKEHUMAN_JOINTS.values())
                if len(found) == len(pose.MAKEHUMAN_JOINTS):
                    landmarks = {name: found[group] for name, group in pose.MAKEHUMAN_JOINTS.items()}
                    ids = geometry.group_vertex_ids(obj, pose.MAKEHUMAN_JOINTS.values())
                    targets = Path(mesh_path).parent / TARGETS_FOLDER
                    targets = targets if targets.is_dir() else SHARED_MESHES / TARGETS_FOLDER
                    shaping = ShapingData(len(obj.vertices), source_ids, triangles, subdivisions,
                                          {name: ids[group] for name, group in pose.MAKEHUMAN_JOINTS.items()},
                                          str(targets))
            else:
                vertices, triangles, corner_uvs = geometry.triangulate(
                    obj, lambda g: not (g.startswith("helper-") or g.startswith("joint-")))
                units_m = metres_per_unit(vertices)
        except (OSError, ValueError, IndexError) as exc:
            raise InputError(mesh_path, f"not a readable OBJ mesh ({exc})") from exc
        kind = "makehuman" if is_makehuman else "obj"
    else:
        vertices, triangles = read_mesh_file(mesh_path)
        corner_uvs, is_makehuman, kind = None, False, "mesh"
        try:
            units_m = metres_per_unit(vertices)
        except ValueError as exc:
            raise InputError(mesh_path, str(exc)) from exc
    vertices = vertices * units_m
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    vertices = vertices - centre
    if landmarks is not None:
        landmarks = {name: p * units_m - centre for name, p in landmarks.items()}
    for _ in range(subdivisions):
        vertices, triangles, corner_uvs = geometry.loop_subdivide(vertices, triangles, corner_uvs)
    skins: tuple[str, ...] = ()
    if is_makehuman:
        skins = tuple(str(p) for p in sorted(Path(mesh_path).parent.glob("skins/*.png")))
        if not skins:
            skins = tuple(str(p) for p in sorted(SHARED_MESHES.glob("skins/*.png")))
    name = "makehuman" if is_makehuman else f"{kind}/{Path(mesh_path).stem}"
    return BaseSubject(kind, name, str(mesh_path), units_m, vertices, triangles,
                       corner_uvs if is_makehuman else None, skins, landmarks, shaping)


def read_mesh_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and triangles (T, 3) int64 of a mesh file trimesh reads (PLY, glTF / GLB,
    STL, OFF, ...); a scene's meshes are merged in their placed positions, vertices at the same position are
    welded (STL's separate triangle corners, seams) and triangles left degenerate by that dropped; open meshes
    (a bust cut at the neck, a face) stay open. InputError names the file and the reason when it cannot be
    read or holds no triangles."""
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds (ValueError, KeyError, struct.error, ...)
        raise InputError(path, f"not a readable mesh ({type(exc).__name__}: {exc})") from exc
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64).reshape(-1, 3)
    triangles = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64).reshape(-1, 3)
    if len(vertices) == 0 or len(triangles) == 0:
        raise InputError(path, "holds no triangles (a point cloud, an empty scene or not a mesh)")
    if not np.all(np.isfinite(vertices)):
        raise InputError(path, "vertex positions hold NaN or Inf")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise InputError(path, "faces index vertices that do not exist")
    # STL stores every triangle's corners apart, other formats split vertices at UV / normal seams: weld
    # vertices at the same position, so that the surface is connected and only real openings are boundary
    vertices, welded = np.unique(vertices, axis=0, return_inverse=True)
    triangles = welded.reshape(-1)[triangles]
    triangles = triangles[(triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2])
                          & (triangles[:, 2] != triangles[:, 0])]
    if len(triangles) == 0:
        raise InputError(path, "holds no triangles with three distinct corners")
    used, remapped = np.unique(triangles, return_inverse=True)
    return vertices[used], remapped.reshape(-1, 3)


def metres_per_unit(vertices: np.ndarray) -> float:
    """Power of ten that puts the largest bounding-box extent of a mesh in [0.2, 2) metres."""
    extent = float(np.ptp(vertices, axis=0).max())
    if extent <= 0:
        raise ValueError("degenerate mesh (zero extent)")
    return float(10.0 ** np.floor(np.log10(2.0 / extent)))


# procedural body primitives in metres (stage frame, +y up, facing +z): (kind, region, params)
PROCEDURAL_PARTS = (
    ("capsule", SHIRT, ((0.0, -0.05, 0.0), (0.0, 0.38, 0.0), 0.16)),        # torso
    ("capsule", SKIN, ((0.0, 0.45, 0.0), (0.0, 0.58, 0.0), 0.055)),          # neck
    ("sphere", SKIN, ((0.0, 0.70, 0.02), 0.115)),                             # head
    ("capsule", SKIN, ((-0.21, 0.40, 0.0), (-0.25, -0.22, 0.05), 0.05)),     # left arm, close to torso
    ("capsule", SKIN, ((0.21, 0.40, 0.0), (0.29, -0.20, -0.04), 0.05)),      # right arm
    ("capsule", TROUSERS, ((-0.09, -0.12, 0.0), (-0.12, -0.86, 0.02), 0.075)),  # left leg
    ("capsule", TROUSERS, ((0.09, -0.12, 0.0), (0.12, -0.86, -0.02), 0.075)),   # right leg
    ("torus", SHINY, ((0.0, 0.05, 0.0), 0.19, 0.035)),                        # belt ring
)


def procedural_part_distances(points: np.ndarray) -> np.ndarray:
    """Signed distances (P, N) from points (N, 3) to each procedural body part."""
    out = []
    for kind, _, params in PROCEDURAL_PARTS:
        if kind == "capsule":
            out.append(geometry.sdf_capsule(points, np.array(params[0]), np.array(params[1]), params[2]))
        elif kind == "sphere":
            out.append(geometry.sdf_sphere(points, np.array(params[0]), params[1]))
        else:
            out.append(geometry.sdf_torus(points, np.array(params[0]), params[1], params[2]))
    return np.stack(out)


def procedural_body_mesh(step: float = 0.012) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (T, 3) of the procedural subject (smooth union, ~1.75 m tall)."""
    def sdf(points: np.ndarray) -> np.ndarray:
        return geometry.smooth_union(procedural_part_distances(points), k=0.015)

    lo, hi = np.array([-0.45, -1.0, -0.35]), np.array([0.45, 0.9, 0.35])
    vertices, triangles = geometry.mesh_from_sdf(sdf, lo, hi, step)
    vertices = vertices - 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    return vertices, triangles


# --- per action ----------------------------------------------------------------------------------------

def make_action_subject(base: BaseSubject, rng: np.random.Generator, action_index: int,
                        fold_amplitude_m: float, cycle_offset: int = 0,
                        pose_deg: dict[str, float] | None = None, body: BodyParams | None = None,
                        hair: HairStyle | None = None, garment: GarmentStyle | None = None) -> ActionSubject:
    """Vary the base subject for one action: yaw, cloth colours and folds from `rng`; skin, skin tone
    and cloth pattern kinds cycle with `cycle_offset + action_index`, so consecutive actions differ.
    `body` shapes the MakeHuman mesh (its macro parameters), `hair` gives it a hair volume, `garment` a skirt;
    `pose_deg` (joint angles, synthetic.pose) poses the shaped, folded, dressed rest mesh before the yaw. Each
    is ignored (None in the result) when the base cannot take it: the body needs the MakeHuman targets
    (BaseSubject.shaping), hair, skirt and pose a skeleton."""
    cycle = cycle_offset + action_index
    yaw = float(rng.uniform(-np.pi, np.pi))
    cloth = random_cloth(rng, fold_amplitude_m, cycle)
    skin_tone = SKIN_TONES[cycle % len(SKIN_TONES)]
    skin_texture, skin_name = None, "procedural"
    if base.skins:
        skin_path = base.skins[cycle % len(base.skins)]
        skin_texture = load_skin(skin_path)
        skin_name = Path(skin_path).stem.removesuffix("_diffuse").removesuffix("_diffuse2")
    normals_rest = geometry.vertex_normals(base.vertices, base.triangles)
    weight = cloth_weight(base, base.vertices)
    displacement = cloth.fold_amplitude_m * weight * fold_pattern(base.vertices, cloth.fold_freqs,
                                                                  cloth.fold_phases)
    vertices_rest = base.vertices + displacement[:, None] * normals_rest
    body = body if base.shaping is not None else None
    hair = hair if base.landmarks is not None else None
    garment = garment if base.landmarks is not None else None
    skeleton = base.skeleton if pose_deg is not None or garment is not None else None
    if body is None and hair is None and garment is None:
        vertices_dressed, skirt = vertices_rest, None
    else:
        vertices_dressed, skeleton, skirt = dress(base, vertices_rest, displacement, normals_rest, body, hair,
                                                  garment, skeleton)
    if pose_deg is not None and skeleton is not None:
        vertices_posed = pose.pose_vertices(vertices_dressed[:len(base.vertices)], skeleton, pose_deg)
        if skirt is not None:
            transforms = pose.bone_transforms(pose_deg, skeleton)
            vertices_posed = np.concatenate([vertices_posed, pose.skin(skirt[0], skirt[2], transforms)])
    else:
        pose_deg = None
        vertices_posed = vertices_dressed if skirt is None else np.concatenate([vertices_dressed, skirt[0]])
    if skirt is not None:
        vertices_rest = np.concatenate([vertices_rest, skirt[0]])
    garment_triangles = None if skirt is None else skirt[1] + len(base.vertices)
    triangles = base.triangles if skirt is None else np.concatenate([base.triangles, garment_triangles])
    rotation = geometry.yaw_matrix(yaw)
    vertices_world = vertices_posed @ rotation.T
    normals_world = geometry.vertex_normals(vertices_world, triangles)
    label = base.name if base.kind != "makehuman" else f"makehuman/{skin_name}"
    return ActionSubject(base, label, yaw, skin_name, skin_texture, skin_tone, cloth, vertices_rest,
                         vertices_world, normals_world, pose_deg, body, hair, garment, garment_triangles)


def shape_body(base: BaseSubject, params: BodyParams) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Offsets (V, 3) metres of the base's vertices for the MakeHuman body `params` (synthetic.body, carried
    through the base's Loop subdivisions) and the shaped skeleton landmarks (centroids of the shaped joint
    groups). InputError when a target file is missing."""
    shaping = base.shaping
    if shaping is None or base.landmarks is None:
        raise ValueError(f"{base.name} cannot be shaped (not the MakeHuman body with its targets)")
    offsets_obj = body_shape.makehuman_offsets(shaping.targets_dir, params, shaping.obj_vertex_count) * base.units_m
    offsets, triangles = offsets_obj[shaping.source_ids], shaping.coarse_triangles
    for _ in range(shaping.subdivisions):
        offsets, triangles, _ = geometry.loop_subdivide(offsets, triangles)
    landmarks = {name: base.landmarks[name] + offsets_obj[ids].mean(axis=0)
                 for name, ids in shaping.landmark_ids.items()}
    return offsets, landmarks


def dress(base: BaseSubject, vertices_rest: np.ndarray, displacement: np.ndarray, normals_rest: np.ndarray,
          body: BodyParams | None, hair: HairStyle | None, garment: GarmentStyle | None,
          skeleton: pose.Skeleton | None) -> tuple[np.ndarray, pose.Skeleton | None, tuple | None]:
    """The shaped, folded body with its hair (V, 3), the skeleton of the shaped body (None when `skeleton` is
    None) and the skirt: (rest vertices (S, 3), triangles (Tg, 3) over them, skinning weights (S, B)) or None.

    vertices_rest: (V, 3) folded base vertices; displacement: (V,) their fold heights along normals_rest (V, 3).
    """
    vertices, normals = vertices_rest, normals_rest
    if body is not None:
        offsets, landmarks = shape_body(base, body)
        shaped = base.vertices + offsets
        normals = geometry.vertex_normals(shaped, base.triangles)
        vertices = shaped + displacement[:, None] * normals
        if skeleton is not None:
            skeleton = pose.Skeleton(pose.bone_joints(landmarks), landmarks, skeleton.weights)
    if hair is not None:
        lift = garments.hair_displacement(vertices, base.vertices, base.landmarks, hair)
        vertices = vertices + lift[:, None] * normals
    skirt = None
    if garment is not None:
        skirt = build_skirt(vertices, base.triangles, skeleton, garment)
    return vertices, skeleton, skirt


SKIRT_ANGLES = 160
"""Vertices round each skirt ring (about 9 mm apart at the hem)."""
SKIRT_RING_SPACING_M = 0.01
"""Vertical distance between the skirt's rings."""
WAIST_ABOVE_PELVIS = 0.033
"""Waist (belt) height above the pelvis joint, as a fraction of the body's height."""


def build_skirt(vertices: np.ndarray, triangles: np.ndarray, skeleton: pose.Skeleton,
                style: GarmentStyle) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The skirt round a rest body (vertices (V, 3), triangles (T, 3), its skeleton): rest vertices (S, 3),
    triangles (Tg, 3) over them and skinning weights (S, len(pose.BONES)) (synthetic.garments)."""
    landmarks = skeleton.landmarks
    arm_bones = [pose.BONES.index(b) for b in ("l_upper_arm", "l_forearm", "r_upper_arm", "r_forearm")]
    on_arm = skeleton.weights[:, arm_bones].sum(axis=1) > 0.3
    keep = ~on_arm[triangles].any(axis=1)
    height = float(vertices[:, 1].max() - vertices[:, 1].min())
    axis = np.array([landmarks["pelvis"][0], landmarks["pelvis"][2]])
    waist = float(landmarks["pelvis"][1]) + WAIST_ABOVE_PELVIS * height
    knee = 0.5 * float(landmarks["l_knee"][1] + landmarks["r_knee"][1])
    hem = knee + style.hem * (waist - knee)
    rings = max(3, int(np.ceil((waist - hem) / SKIRT_RING_SPACING_M)) + 1)
    heights = np.linspace(waist, hem, rings)
    angles = np.arange(SKIRT_ANGLES) * (2.0 * np.pi / SKIRT_ANGLES)
    extent = garments.body_extent_rings(vertices, triangles[keep], axis, heights, angles)
    radius = garments.skirt_radii(extent, heights, style, angles)
    skirt_vertices, skirt_triangles, _ = garments.skirt_shell(radius, heights, angles, axis)
    body_ids = np.flatnonzero(~on_arm)
    weights = garments.transfer_weights(skirt_vertices, vertices[body_ids], skeleton.weights[body_ids])
    return skirt_vertices, skirt_triangles, weights


def random_cloth(rng: np.random.Generator, fold_amplitude_m: float, cycle: int) -> ClothStyle:
    """A shirt / trousers style (pattern kinds cycle with `cycle`, colours random) and fold pattern."""
    shirt_pattern = ("stripes", "checks", "plain")[cycle % 3]
    trousers_pattern = ("denim", "checks", "plain")[(cycle + 1) % 3]
    shirt_colours = FABRIC_COLOURS[rng.choice(len(FABRIC_COLOURS), 2, replace=False)]
    trousers_colours = FABRIC_COLOURS[rng.choice(len(FABRIC_COLOURS), 2, replace=False)]
    if trousers_pattern == "denim":
        trousers_colours = np.array([[0.05, 0.09, 0.22], [0.20, 0.26, 0.40]])
    n_folds = 7
    # mostly vertical spatial frequencies -> wrinkles running round torso and limbs
    directions = geometry.normalize(np.column_stack([rng.normal(0, 0.45, n_folds), np.ones(n_folds),
                                                     rng.normal(0, 0.45, n_folds)]))
    wavelengths = rng.uniform(0.035, 0.08, n_folds)
    # periods of a few centimetres: patterns stay resolved (a pixel is ~4 mm at the default width)
    return ClothStyle(shirt_pattern, shirt_colours, float(rng.uniform(0.025, 0.05)),
                      float(rng.uniform(-0.3, 0.3)), trousers_pattern, trousers_colours,
                      float(rng.uniform(0.04, 0.08)),
                      directions * (2 * np.pi / wavelengths)[:, None], rng.uniform(0, 2 * np.pi, n_folds),
                      fold_amplitude_m * float(rng.uniform(0.75, 1.25)))


def load_skin(path: str | Path) -> np.ndarray:
    """A skin atlas PNG (sRGB-encoded) as linear float32 albedo (h, w, 3)."""
    from PIL import Image

    with Image.open(path) as img:
        encoded = np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0
    return srgb_to_linear(encoded).astype(np.float32)


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """sRGB transfer curve inverse, elementwise on [0, 1] values."""
    x = np.clip(encoded, 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


# --- regions and patterns (pure) -----------------------------------------------------------------------

def region_of(base: BaseSubject, points_rest: np.ndarray) -> np.ndarray:
    """Region id (N,) int of rest-frame points (N, 3): SKIN, SHIRT, TROUSERS or SHINY."""
    if base.kind == "procedural":
        return np.array([p[1] for p in PROCEDURAL_PARTS])[np.argmin(procedural_part_distances(points_rest), 0)]
    if base.kind != "makehuman":
        return np.zeros(len(points_rest), np.int64)
    distances = makehuman_region_distances(base, points_rest)
    region = np.full(len(points_rest), SKIN, np.int64)
    for reg in (SHIRT, TROUSERS, SHINY):
        region[distances[reg] > 0] = reg
    return region


def makehuman_region_distances(base: BaseSubject, points: np.ndarray) -> dict[int, np.ndarray]:
    """Signed distance-like margins (metres, > 0 inside) of points to the clothed regions of the body.

    Regions are bands of normalised height t = (y - y_min) / height (the body stands in an A-pose):
    shoes t < 0.045, trousers 0.045..0.555, belt 0.555..0.58, shirt 0.58..0.835 with |x| < 0.26 m
    (short sleeves; the arms leave the torso at the shoulders, hands hang at t > 0.56, |x| > 0.3 m).
    """
    y0, y1 = base.y_range
    height = y1 - y0
    t = (points[:, 1] - y0) / height
    ax = np.abs(points[:, 0])

    def band(lo: float, hi: float, x_max: float) -> np.ndarray:
        return np.minimum.reduce([(t - lo) * height, (hi - t) * height, x_max - ax])

    return {SHINY: np.maximum(band(-1.0, 0.045, 1.0), band(0.555, 0.58, 0.25)),
            TROUSERS: band(0.045, 0.555, 1.0),
            SHIRT: band(0.58, 0.835, 0.26)}


def cloth_weight(base: BaseSubject, points: np.ndarray, fade_m: float = 0.015) -> np.ndarray:
    """Fold displacement weight (N,) in [0, 1]: 1 inside shirt / trousers, fading to 0 over `fade_m`."""
    if base.kind == "procedural":
        d = procedural_part_distances(points)
        regions = np.array([p[1] for p in PROCEDURAL_PARTS])
        cloth = np.isin(regions, (SHIRT, TROUSERS))
        margin = d[~cloth].min(axis=0) - d[cloth].min(axis=0)
        return smoothstep(0.0, fade_m, margin)
    if base.kind != "makehuman":
        return np.zeros(len(points))
    distances = makehuman_region_distances(base, points)
    margin = np.maximum(distances[SHIRT], distances[TROUSERS])
    return smoothstep(0.0, fade_m, margin)


def fold_pattern(points: np.ndarray, freqs: np.ndarray, phases: np.ndarray) -> np.ndarray:
    """Ridged fold height field (N,) in about [-1, 1] from random sinusoids with a low-frequency warp."""
    warp = 1.3 * np.sin(points @ (freqs[::-1] * 0.17).T + phases[::-1])
    waves = np.sin(points @ freqs.T + phases + warp)
    f = waves.mean(axis=1) * np.sqrt(len(phases))
    ridged = 1.0 - 2.0 * np.abs(np.tanh(f))  # sharp crests, wide troughs: cloth-like
    return np.clip(ridged, -1.0, 1.0)


def smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 at edge0 to 1 at edge1."""
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def value_noise(points: np.ndarray, scale_m: float, salt: int) -> np.ndarray:
    """Smooth deterministic pseudo-noise (N,) in about [-1, 1] (sum of fixed random sinusoids)."""
    rng = np.random.default_rng(1_000_003 + salt)
    freqs = geometry.normalize(rng.normal(size=(6, 3))) * (2 * np.pi / scale_m) * rng.uniform(0.6, 1.6, (6, 1))
    return np.sin(points @ freqs.T + rng.uniform(0, 2 * np.pi, 6)).mean(axis=1) * np.sqrt(2.0)


def cloth_albedo(points: np.ndarray, pattern: str, colours: np.ndarray, period_m: float,
                 tilt: float) -> np.ndarray:
    """Solid-texture cloth albedo (N, 3) at rest points (N, 3)."""
    a, b = colours[0], colours[1]
    fibre = 1.0 + 0.06 * value_noise(points, 0.011, 1)[:, None]
    if pattern == "stripes":
        coord = (points[:, 1] * np.cos(tilt) + points[:, 0] * np.sin(tilt)) / period_m
        s = smoothstep(0.35, 0.5, np.abs(np.mod(coord, 1.0) - 0.5))[:, None]
        out = a * (1 - s) + b * s
    elif pattern == "checks":
        u = smoothstep(0.27, 0.4, np.abs(np.mod(points[:, 0] / period_m, 1.0) - 0.5))
        v = smoothstep(0.27, 0.4, np.abs(np.mod(points[:, 1] / period_m, 1.0) - 0.5))
        mix = (0.5 * (u + v))[:, None]  # gingham: 0 base, 0.5 single band, 1 crossing
        out = a * (1 - mix) + b * mix
    elif pattern == "denim":  # faded blotches and a soft diagonal wale (real twill is finer than a pixel)
        wale = 0.5 + 0.5 * np.sin((points[:, 0] + points[:, 1]) * 2 * np.pi / 0.03)
        blotch = 0.5 + 0.5 * value_noise(points, 0.09, 2)
        mix = np.clip(0.12 * wale + 0.7 * blotch, 0, 1)[:, None]
        out = a * (1 - mix) + b * mix
    else:
        out = np.broadcast_to(a, (len(points), 3))
    return (out * fibre).astype(np.float32)


def skin_albedo(points: np.ndarray, tone: np.ndarray) -> np.ndarray:
    """Procedural skin albedo (N, 3): a tone with blotchy low-frequency variation."""
    blotch = 1.0 + 0.07 * value_noise(points, 0.05, 3)[:, None] + 0.03 * value_noise(points, 0.01, 4)[:, None]
    redness = 1.0 + 0.05 * value_noise(points, 0.08, 5)[:, None] * np.array([1.0, -0.5, -0.5])
    return (tone * blotch * redness).astype(np.float32)


def shiny_albedo(points: np.ndarray, kind: str) -> np.ndarray:
    """Dark leather albedo (N, 3) for shoes / belt (procedural subject: a gold-ish ring)."""
    base = np.array([0.10, 0.06, 0.035]) if kind == "makehuman" else np.array([0.45, 0.30, 0.08])
    return (base * (1.0 + 0.08 * value_noise(points, 0.02, 6)[:, None])).astype(np.float32)


def sample_bilinear(texture: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """Bilinear lookup of texture (h, w, C) at OBJ UVs (N, 2) (v up; wraps); returns (N, C) float32."""
    h, w = texture.shape[:2]
    x = np.mod(uvs[:, 0], 1.0) * w - 0.5
    y = (1.0 - np.mod(uvs[:, 1], 1.0)) * h - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None].astype(np.float32), (y - y0)[:, None].astype(np.float32)
    x0c, x1c = np.clip(x0, 0, w - 1), np.clip(x0 + 1, 0, w - 1)
    y0c, y1c = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    top = texture[y0c, x0c] * (1 - fx) + texture[y0c, x1c] * fx
    bottom = texture[y1c, x0c] * (1 - fx) + texture[y1c, x1c] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)
