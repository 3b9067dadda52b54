"""Typed readers of the stages' artifacts: one place that knows where each product lives.

A stage's upstream artifacts are folders of the work store (``ctx.upstream[name]``); :class:`ActionArtifacts`
wraps them and reads each product by what it is (cameras, normal maps, mesh, atlas, textures) instead of by
path, so the stages that consume a product do not repeat its layout; :func:`colour_matrix` and
:func:`load_light_model` read the session stages' products, :func:`load_atlas_mesh` and :func:`fitted_f0` the
textures and materials stages'. :func:`load_relightable_asset` builds
the :class:`stages.numerics.novel_view.ActionAsset` that the ``relight`` and ``relightset`` stages render from.
"""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.exr import read_exr
from pipeline.codecs.image import read_png
from pipeline.errors import InputError
from stages.cameras import load_cameras
from stages.numerics.camera import Camera

#: Where each product lives inside its stage's artifact folder: (stage, relative path).
PRODUCTS: dict[str, tuple[str, str]] = {
    "cameras": ("decode", "cameras.json"),
    "full_on": ("decode", "full_on/{camera}.exr"),
    "pos": ("decode", "pos/{camera}.exr"),
    "neg": ("decode", "neg/{camera}.exr"),
    "normal_alpha": ("photometric", "normal_alpha/{camera}.exr"),
    "albedo": ("photometric", "albedo/{camera}.exr"),
    "mask": ("photometric", "mask/{camera}.png"),
    "normal_diffuse": ("diffuse_normals", "normal_diffuse/{camera}.exr"),
    "albedo_diffuse": ("diffuse_normals", "albedo_diffuse/{camera}.exr"),
    "mesh": ("geometry", "mesh/mesh.ply"),
    "textured_mesh": ("textures", "mesh/textured.obj"),
    "albedo_texture": ("textures", "textures/albedo.exr"),
    "roughness_texture": ("materials", "textures/roughness.exr"),
    "occlusion_texture": ("materials", "textures/occlusion.exr"),
    "diffuse_ratio_texture": ("materials", "textures/diffuse_ratio.exr"),
}


def colour_matrix(colour_dir: Path, camera_id: str) -> np.ndarray | None:
    """The fitted matrix (3, 3) float32 of one camera from a ``colour`` artifact, or None (identity)."""
    path = Path(colour_dir) / "colour" / f"{camera_id}.json"
    return np.asarray(json.loads(path.read_text())["matrix"], np.float32) if path.exists() else None


def load_light_model(lights_dir: Path) -> Any:
    """The fitted :class:`calibration.light.LightModel` of a ``lights`` artifact, or None when the session uses
    the ideal one."""
    from calibration.light import LightModel

    record = json.loads((Path(lights_dir) / "light_model.json").read_text())
    return None if record.get("ideal") else LightModel.from_json(record["model"])


def read_cameras(cameras_json: Path) -> dict[str, Camera]:
    """camera_id -> :class:`Camera` of the calibrated cameras of a ``cameras.json`` (their records, with
    ``white_reference`` and the rest, in ``Camera.record``)."""
    return {cam_id: Camera.from_json(record) for cam_id, record in load_cameras(cameras_json).items()}


def mapped_cameras(decode_dir: Path, photometric_dir: Path) -> dict[str, Camera]:
    """camera_id -> camera of the calibrated cameras that have a photometric normal map, sorted by id (a
    missing camera, with no calibration or failed frames, has none)."""
    cameras = read_cameras(Path(decode_dir) / "cameras.json")
    return {c: cameras[c] for c in sorted(cameras) if (Path(photometric_dir) / "normal_alpha" / f"{c}.exr").exists()}


def camera_maps(decode_dir: Path, photometric_dir: Path, min_alpha: float):
    """Yield ``(camera_id, Camera, normal_alpha (H, W, 4), mask (H, W) bool, valid (H, W) bool)`` for the
    :func:`mapped_cameras`, sorted by id; ``valid`` = alpha above ``min_alpha`` inside the mask."""
    photometric_dir = Path(photometric_dir)
    for cam_id, cam in mapped_cameras(decode_dir, photometric_dir).items():
        normal_alpha = read_exr(photometric_dir / "normal_alpha" / f"{cam_id}.exr")
        mask = read_png(photometric_dir / "mask" / f"{cam_id}.png")
        mask = (mask[..., 0] if mask.ndim == 3 else mask) > 127
        yield cam_id, cam, normal_alpha, mask, (normal_alpha[..., 3] > min_alpha) & mask


def fitted_f0(artifact: Path) -> float:
    """The Fresnel F0 a materials artifact's roughness texture was fitted with (its record's config): roughness
    and F0 trade off under broad light, so whoever models the specular light with that texture uses this F0."""
    path = Path(artifact) / "_SUCCESS.json"
    try:
        f0 = float(json.loads(path.read_text())["record"]["config"]["f0"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(path, f"no materials f0 in the artifact's record ({type(exc).__name__}: {exc})") from exc
    if not 0.0 <= f0 <= 1.0:
        raise InputError(path, f"materials f0 {f0} is outside [0, 1]")
    return f0


def load_atlas_mesh(obj_path: Path):
    """The textured OBJ of the textures stage as ``(vertices (V, 3) welded, faces (F, 3) into them,
    Atlas)``: the OBJ splits vertices along chart seams; welding identical positions gives back one
    surface, so normals and depth maps are continuous across seams."""
    from pipeline.codecs.mesh import read_obj
    from stages.numerics.mesh import Atlas

    obj = read_obj(obj_path)
    if obj["uvs"] is None or obj["uv_faces"] is None or not np.array_equal(obj["uv_faces"], obj["faces"]):
        raise InputError(obj_path, "the textured mesh has no per-vertex UVs (uv faces must equal faces)")
    vertices, inverse = np.unique(np.asarray(obj["vertices"], np.float64), axis=0, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1).astype(np.int64)
    faces = inverse[obj["faces"]]
    atlas = Atlas(vmapping=inverse, faces=np.asarray(obj["faces"], np.int32), uvs=np.asarray(obj["uvs"], np.float32),
                  width=1, height=1, stats={})
    return vertices, faces, atlas


class ActionArtifacts:
    """The upstream artifacts of one action's stage task (the work store's folders by stage name)."""

    def __init__(self, upstream: Mapping[str, Path]):
        self.upstream = {name: Path(path) for name, path in upstream.items()}

    @classmethod
    def from_store(cls, store_root: Path, action_id: str, session_id: str,
                   stages: tuple[str, ...]) -> "ActionArtifacts | None":
        """The last committed results of ``stages`` for an action in a work store (``<work>/artifacts``), as a
        stage task would see them (session-scoped stages by ``session_id``); None when one is missing."""
        from pipeline.store import ArtifactStore

        store = ArtifactStore(store_root)
        upstream = {}
        for stage in stages:
            folder = store.latest_dir(stage, action_id) or store.latest_dir(stage, session_id)
            if folder is None:
                return None
            upstream[stage] = folder
        return cls(upstream)

    def path(self, product: str, camera: str | None = None) -> Path:
        """Where a product is (it may not exist); KeyError for an unknown product or a stage not upstream."""
        if product not in PRODUCTS:
            raise KeyError(f"unknown product {product!r}; products are {sorted(PRODUCTS)}")
        stage, rel = PRODUCTS[product]
        if stage not in self.upstream:
            raise KeyError(f"product {product!r} comes from stage {stage!r}, which is not upstream "
                           f"(upstream: {sorted(self.upstream)})")
        return self.upstream[stage] / rel.format(camera=camera)

    def has(self, product: str, camera: str | None = None) -> bool:
        try:
            return self.path(product, camera).exists()
        except KeyError:
            return False

    def cameras(self) -> dict[str, Camera]:
        """camera_id -> :class:`Camera` of the calibrated cameras that have a photometric normal map, sorted by
        id."""
        return mapped_cameras(self.upstream["decode"], self.upstream["photometric"])

    def camera_maps(self, min_alpha: float) -> Iterator[tuple[str, Camera, np.ndarray, np.ndarray, np.ndarray]]:
        """``(camera_id, camera, normal_alpha (H, W, 4), mask (H, W), valid (H, W))`` per mapped camera."""
        return camera_maps(self.upstream["decode"], self.upstream["photometric"], min_alpha)

    def map(self, product: str, camera: str, channels: int = 3) -> np.ndarray:
        """A per-camera float map (H, W, channels) read from its EXR."""
        return read_exr(self.path(product, camera))[..., :channels]

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The action's mesh: vertices (V, 3) float64 metres, world frame; faces (F, 3)."""
        from pipeline.codecs.mesh import read_ply

        return read_ply(self.path("mesh"))

    def atlas_mesh(self) -> tuple[np.ndarray, np.ndarray, Any]:
        """The textured mesh welded (vertices, faces, :class:`stages.numerics.mesh.Atlas`)."""
        return load_atlas_mesh(self.path("textured_mesh"))

    def texture(self, product: str, channels: int = 3) -> np.ndarray:
        """A texture of the atlas: (T, T, 3) for ``channels`` 3, (T, T) for 1."""
        texture = read_exr(self.path(product))
        if channels == 1:
            return texture[..., 0] if texture.ndim == 3 else texture
        return texture[..., :channels]


def load_relightable_asset(artifacts: ActionArtifacts, min_alpha: float = 0.5, diffuse_normals: bool = True,
                           diffuse_albedo: bool = True) -> tuple[Any, dict[str, Camera]]:
    """The action's relightable asset and its mapped cameras (sized as their maps).

    The captured views become reprojection sources with their mesh depth; their normals are
    ``normal_diffuse`` when ``diffuse_normals`` and present (else eq. 1's), their albedo ``albedo_diffuse``
    when ``diffuse_albedo`` and every camera has one (the shading treats the reprojected albedo as one kind),
    else the white-light albedo (times the materials' diffuse ratio at shading time).

    Raises:
        InputError: fewer than 2 cameras have maps.
    """
    from stages.numerics.gbuffer import SourceView
    from stages.numerics.mesh import vertex_normals
    from stages.numerics.novel_view import ActionAsset
    from stages.numerics.raycast import mesh_scene, render_mesh

    vertices, faces = artifacts.mesh()
    scene = mesh_scene(vertices, faces)
    mapped = artifacts.cameras()
    use_diffuse_albedo = diffuse_albedo and bool(mapped) and all(artifacts.has("albedo_diffuse", c) for c in mapped)
    sources, cameras = [], {}
    for cam_id, cam, normal_alpha, _, valid in artifacts.camera_maps(min_alpha):
        h, w = valid.shape
        depth = render_mesh(None, None, cam.K, cam.cam_from_world, h, w, scene=scene)["depth_m"]
        albedo = artifacts.map("albedo_diffuse" if use_diffuse_albedo else "albedo", cam_id)
        normals = normal_alpha[..., :3]
        if diffuse_normals and artifacts.has("normal_diffuse", cam_id):
            normals = artifacts.map("normal_diffuse", cam_id)
        sources.append(SourceView(normal=np.ascontiguousarray(normals), albedo=albedo, valid=valid,
                                  K=cam.K, cam_from_world=cam.cam_from_world, depth_m=depth))
        cameras[cam_id] = dataclasses.replace(cam, width=w, height=h)
    if len(sources) < 2:
        raise InputError(artifacts.path("normal_alpha", "00000").parent,
                         f"{len(sources)} camera(s) have maps; novel views need at least 2")
    atlas_vertices, atlas_faces, atlas = artifacts.atlas_mesh()
    asset = ActionAsset(scene=scene, faces=faces, smooth_normals=vertex_normals(vertices, faces), sources=sources,
                        atlas_scene=mesh_scene(atlas_vertices, atlas_faces), atlas=atlas,
                        albedo_tex=artifacts.texture("albedo_texture"),
                        roughness_tex=artifacts.texture("roughness_texture", 1),
                        occlusion_tex=artifacts.texture("occlusion_texture", 1),
                        diffuse_ratio_tex=artifacts.texture("diffuse_ratio_texture"),
                        sources_diffuse_albedo=use_diffuse_albedo, vertices=np.asarray(vertices, np.float64))
    return asset, cameras
