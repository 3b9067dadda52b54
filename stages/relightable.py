"""The relightable asset of one action, from the work store or a release: what ``relight`` and ``relightset``
render from.

A module of its own, imported only by those stages (and by users who re-render a release): it imports the
renderer (G-buffer sources, novel views, ray casting), and a stage's cache key holds the code of every module it
imports, so the stages that only read products through :mod:`artifacts.facade` do not rerun when the renderer
changes.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from pipeline.errors import InputError
from artifacts.facade import ActionArtifacts
from artifacts.camera import Camera
from stages.numerics.gbuffer import SourceView
from stages.numerics.mesh import vertex_normals
from stages.numerics.novel_view import ActionAsset, crop_intrinsics, subject_window
from stages.numerics.raycast import mesh_scene, render_mesh


def load_relightable_asset(artifacts: ActionArtifacts, min_alpha: float = 0.5, diffuse_normals: bool = True,
                           diffuse_albedo: bool = True, cut_sources: bool = True) -> tuple[Any, dict[str, Camera]]:
    """The action's relightable asset and its mapped cameras (sized as their maps).

    The captured views become reprojection sources with their mesh depth, each cut to the part of its frame the
    mesh can cover when ``cut_sources`` (:func:`windowed_source`; :func:`source_window` says which part): a
    point reprojected onto this mesh projects inside that part and reads there what it would read in the whole
    frame, and the sources hold about a third of the frames' pixels (keep the whole frames to reproject another
    surface, e.g. a true mesh's). Their normals are
    ``normal_diffuse`` when ``diffuse_normals`` and present (else eq. 1's), their albedo ``albedo_diffuse``
    when ``diffuse_albedo`` and every camera has one (the shading treats the reprojected albedo as one kind),
    else the white-light albedo (times the materials' diffuse ratio at shading time).

    Raises:
        InputError: fewer than 2 cameras have maps.
    """
    vertices, faces = artifacts.mesh()
    scene = mesh_scene(vertices, faces)
    mapped = artifacts.cameras()
    use_diffuse_albedo = diffuse_albedo and bool(mapped) and all(artifacts.has("albedo_diffuse", c) for c in mapped)
    sources, cameras = [], {}
    for cam_id, cam, normal_alpha, _, valid in artifacts.camera_maps(min_alpha):
        h, w = valid.shape
        albedo = artifacts.map("albedo_diffuse" if use_diffuse_albedo else "albedo", cam_id)
        normals = normal_alpha[..., :3]
        if diffuse_normals and artifacts.has("normal_diffuse", cam_id):
            normals = artifacts.map("normal_diffuse", cam_id)
        window = subject_window(vertices, cam.K, cam.cam_from_world, h, w) if cut_sources else (0, h, 0, w)
        sources.append(windowed_source(scene, cam.K, cam.cam_from_world, normals, albedo, valid, window))
        cameras[cam_id] = dataclasses.replace(cam, width=w, height=h)
    if len(sources) < 2:
        raise InputError(artifacts.where(), f"{len(sources)} camera(s) have maps; novel views need at least 2")
    atlas_vertices, atlas_faces, atlas = artifacts.atlas_mesh()
    asset = ActionAsset(scene=scene, faces=faces, smooth_normals=vertex_normals(vertices, faces), sources=sources,
                        atlas_scene=mesh_scene(atlas_vertices, atlas_faces), atlas=atlas,
                        albedo_tex=artifacts.texture("albedo_texture"),
                        roughness_tex=artifacts.texture("roughness_texture", 1),
                        occlusion_tex=artifacts.texture("occlusion_texture", 1),
                        diffuse_ratio_tex=artifacts.texture("diffuse_ratio_texture"),
                        sources_diffuse_albedo=use_diffuse_albedo, vertices=np.asarray(vertices, np.float64))
    return asset, cameras


def windowed_source(scene: Any, K: np.ndarray, cam_from_world: np.ndarray, normals: np.ndarray, albedo: np.ndarray,
                    valid: np.ndarray, window: tuple[int, int, int, int]) -> SourceView:
    """A captured view as a reprojection source over ``window`` ``(row0, row1, col0, col1)`` of its frame (the part
    its mesh can cover: :func:`stages.numerics.novel_view.subject_window`; or the whole frame), its mesh depth
    ray-cast against ``scene`` there.

    K, cam_from_world: the view's (3, 3) intrinsics and (3, 4) pose; normals, albedo (H, W, 3) and valid (H, W): its
    maps over the whole frame (copied: the frames are not kept alive by the cut)."""
    row0, row1, col0, col1 = window
    cut_K = crop_intrinsics(K, row0, col0)
    depth = render_mesh(None, None, cut_K, cam_from_world, row1 - row0, col1 - col0, scene=scene)["depth_m"]

    def cut(image: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(image[row0:row1, col0:col1])

    return SourceView(normal=cut(normals), albedo=cut(albedo), valid=cut(valid), K=cut_K,
                      cam_from_world=np.asarray(cam_from_world), depth_m=depth)


def source_window(camera: Camera, source: SourceView) -> tuple[int, int, int, int]:
    """``(row0, row1, col0, col1)``: the part of ``camera``'s frame that ``source`` (one of
    :func:`load_relightable_asset`'s, made from that camera's maps) holds."""
    row0 = int(round(float(camera.K[1, 2] - source.K[1, 2])))
    col0 = int(round(float(camera.K[0, 2] - source.K[0, 2])))
    rows, cols = source.valid.shape
    return row0, row0 + rows, col0, col0 + cols
