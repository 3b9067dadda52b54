"""Action stage ``exports``: the action's surface in the formats other tools load with their own readers.

(The 8-bit sRGB images and the nerfstudio-convention ``transforms.json`` are the decode stage's.)

- ``colmap/sparse/0/``: a COLMAP text model whose image names are the PNGs' paths relative to the action
  folder and whose points are the subject's surface (sampled on the textured mesh, coloured by its albedo
  texture), plus the same points as ``points3D.ply`` (the file gaussian-splatting trainers read first).
- ``mesh/textured.obj`` + ``textured.mtl`` + ``textured.png`` (the material's texture beside the OBJ, so
  loaders that refuse paths leaving the OBJ's folder keep it) and ``mesh/textured.glb`` (binary glTF with the
  texture embedded).

Wiring only: the formats are pure functions below; the camera conventions are the decode stage's
(:func:`stages.decode.transforms_json`); CONVENTIONS.md says how they relate.
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.config import Documented, checked
from pipeline.stage import Stage, StageContext
from artifacts.facade import ActionArtifacts
from artifacts.layout import ArtifactWriter, released_files
from stages.conventions import distortion_fields, srgb_png


@dataclass(frozen=True)
class ExportsConfig(Documented):
    colmap_points: int = checked(100_000, ge=1)
    """Points of the COLMAP model (and points3D.ply), sampled uniformly over the textured mesh's area."""
    seed: int = checked(0, ge=0)
    """Seed of the point sampling (the same mesh gives the same points); numpy seeds are >= 0."""


# ------------------------------------------------------------------------------------------- pure functions

def sample_surface(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, n: int,
                   seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` points uniformly over a mesh's area: positions (n, 3), unit face normals (n, 3) and
    interpolated UVs (n, 2).

    vertices (V, 3), faces (F, 3) into them, uvs (V, 2) per vertex (the atlas OBJ's, where vertices and
    UVs share indices). Raises ValueError for a mesh without area.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    area = np.linalg.norm(cross, axis=1)
    if not len(f) or area.sum() <= 0:
        raise ValueError("sample_surface: the mesh has no area")
    rng = np.random.default_rng(seed)
    face = rng.choice(len(f), size=int(n), p=area / area.sum())
    r1, r2 = rng.random(int(n)), rng.random(int(n))
    s = np.sqrt(r1)
    w = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)  # uniform barycentric weights
    points = np.einsum("nk,nkd->nd", w, v[f[face]])
    uv = np.einsum("nk,nkd->nd", w, np.asarray(uvs, np.float64)[f[face]])
    normals = cross[face] / np.maximum(area[face], 1e-30)[:, None]
    return points, normals, uv


def colmap_cameras_txt(cameras: list[dict[str, Any]]) -> str:
    """COLMAP cameras.txt: one OPENCV camera per captured camera (FULL_OPENCV when one has a k3), principal
    point in COLMAP's convention (OpenCV + 0.5 px)."""
    full = any(distortion_fields(c.get("dist"))["k3"] != 0.0 for c in cameras)
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]", f"# Number of cameras: {len(cameras)}"]
    for i, cam in enumerate(cameras, start=1):
        K = np.asarray(cam["K"], np.float64)
        d = distortion_fields(cam.get("dist"))
        params = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, d["k1"], d["k2"], d["p1"], d["p2"]]
        if full:
            params += [d["k3"], 0.0, 0.0, 0.0]
        lines.append(f"{i} {'FULL_OPENCV' if full else 'OPENCV'} {int(cam['width'])} {int(cam['height'])} "
                     + " ".join(f"{p:.17g}" for p in params))
    return "\n".join(lines) + "\n"


def colmap_images_txt(cameras: list[dict[str, Any]], image_dir: str = "full_on") -> str:
    """COLMAP images.txt: the pose (cam_from_world, COLMAP = OpenCV axes) of each camera, named by its PNG's
    path relative to the action folder; no 2D observations (the points come from the mesh, not from matches)."""
    from scipy.spatial.transform import Rotation

    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(cameras)}"]
    for i, cam in enumerate(cameras, start=1):
        P = np.asarray(cam["cam_from_world"], np.float64)[:3, :4]
        x, y, z, w = Rotation.from_matrix(P[:, :3]).as_quat()
        t = P[:, 3]
        lines += [f"{i} {w:.17g} {x:.17g} {y:.17g} {z:.17g} {t[0]:.17g} {t[1]:.17g} {t[2]:.17g} {i} "
                  f"{image_dir}/{cam['camera_id']}.png", ""]
    return "\n".join(lines) + "\n"


def colmap_points3d_txt(points: np.ndarray, colours: np.ndarray) -> str:
    """COLMAP points3D.txt: id, position (metres, world frame), 8-bit colour, error 0, no track."""
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {len(points)}, mean track length: 0"]
    lines += [f"{i} {p[0]:.7g} {p[1]:.7g} {p[2]:.7g} {c[0]} {c[1]} {c[2]} 0"
              for i, (p, c) in enumerate(zip(points.tolist(), colours.tolist()), start=1)]
    return "\n".join(lines) + "\n"


def points_ply(points: np.ndarray, normals: np.ndarray, colours: np.ndarray) -> bytes:
    """Binary little-endian PLY of coloured points with normals (x y z nx ny nz float, red green blue uchar):
    the layout gaussian-splatting trainers write and read as ``points3D.ply``; open3d and trimesh read it."""
    n = len(points)
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                      ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rows = np.empty(n, dtype)
    for i, name in enumerate(("x", "y", "z")):
        rows[name] = points[:, i]
        rows["n" + name] = normals[:, i]
    for i, name in enumerate(("red", "green", "blue")):
        rows[name] = colours[:, i]
    header = ("ply\nformat binary_little_endian 1.0\ncomment UltraStage subject surface points, world frame, metres\n"
              f"element vertex {n}\n" + "".join(f"property {'float' if dtype[name].kind == 'f' else 'uchar'} {name}\n"
                                                for name in dtype.names) + "end_header\n")
    return header.encode("ascii") + rows.tobytes()


def point_colours(albedo_texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 sRGB colours of the points: the linear albedo texture (OBJ-convention UVs) encoded as the
    images' PNGs are."""
    from stages.numerics.bake import sample_texture

    return srgb_png(sample_texture(albedo_texture[..., :3], uv)[None])[0]


def obj_with_texture(obj_text: str, mtl_name: str) -> str:
    """The OBJ's text with its ``mtllib`` statement pointing at ``mtl_name`` (a file beside it)."""
    lines = [f"mtllib {mtl_name}" if line.startswith("mtllib ") else line for line in obj_text.splitlines()]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------------- stage

RELEASED = ("export_mesh", "export_material", "export_texture", "export_glb", "colmap_cameras", "colmap_images",
            "colmap_points", "colmap_points_ply")
"""The products this stage publishes, in order (their paths and kinds: :data:`artifacts.layout.PRODUCTS`,
:data:`artifacts.layout.RELEASE_KINDS`)."""


class ExportsStage(Stage):
    name = "exports"
    version = "1"
    scope = "action"
    requires = ("decode", "textures")
    outputs = ("colmap", "mesh")

    def run(self, ctx: StageContext) -> dict[str, Any]:
        from pipeline.codecs.mesh import read_obj

        cfg: ExportsConfig = self.config
        out = ctx.out_dir
        upstream = ActionArtifacts(ctx.upstream)
        cameras = [c for c in upstream.camera_records().values()
                   if upstream.has("full_on_png", c["camera_id"])]

        writer = ArtifactWriter(self.name, out)
        writer.path("export_mesh").parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(upstream.existing("albedo_texture_png"), writer.path("export_texture"))
        mtl = upstream.existing("textured_material").read_text()
        writer.path("export_material").write_text("\n".join("map_Kd textured.png" if line.startswith("map_Kd ")
                                                            else line for line in mtl.splitlines()) + "\n")
        textured_obj = upstream.existing("textured_mesh")
        writer.path("export_mesh").write_text(obj_with_texture(textured_obj.read_text(), "textured.mtl"))
        _write_glb(writer.path("export_mesh"), writer.path("export_glb"))

        obj = read_obj(textured_obj)
        points, normals, uv = sample_surface(obj["vertices"], obj["faces"], obj["uvs"], cfg.colmap_points, cfg.seed)
        colours = point_colours(upstream.exr("albedo_texture"), uv)
        writer.path("colmap_cameras").parent.mkdir(parents=True, exist_ok=True)
        writer.path("colmap_cameras").write_text(colmap_cameras_txt(cameras))
        writer.path("colmap_images").write_text(colmap_images_txt(cameras))
        writer.path("colmap_points").write_text(colmap_points3d_txt(points, colours))
        writer.path("colmap_points_ply").write_bytes(points_ply(points, normals, colours))
        return {"cameras": len(cameras), "colmap_points": int(len(points))}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        return released_files(self.name, artifact, RELEASED)


def _write_glb(obj_path: Path, glb_path: Path) -> None:
    """Binary glTF of the textured OBJ (trimesh's exporter embeds the texture image)."""
    import trimesh

    loaded = trimesh.load(obj_path, process=False, maintain_order=True)
    if not isinstance(getattr(loaded.visual, "material", None), trimesh.visual.material.Material) or \
            getattr(loaded.visual.material, "image", None) is None:
        raise ValueError(f"{obj_path}: trimesh found no texture image through its MTL")
    glb_path.write_bytes(loaded.export(file_type="glb"))
