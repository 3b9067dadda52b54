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
from stages.numerics.novel_view import ActionAsset
from stages.numerics.raycast import mesh_scene, render_mesh


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
