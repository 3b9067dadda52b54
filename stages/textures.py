"""Action stage ``textures``: a UV atlas of the decimated mesh and albedo/normal textures baked into it.

Wiring only: the numerics are :mod:`stages.numerics.mesh` (decimation, xatlas) and :mod:`stages.numerics.bake`
(texel reprojection into the cameras that see it).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.exr import write_exr
from pipeline.codecs.image import preview_linear, preview_normals, preview_scalar, write_png
from pipeline.config import Documented, checked
from pipeline.stage import Stage, StageContext
from artifacts.facade import ActionArtifacts
from artifacts.layout import ArtifactWriter, released_files
from stages.exr_headers import EXR_HEADERS


RELEASED_PREVIEWS = ("texture_confidence_preview", "texture_normal_preview")
RELEASED = ("albedo_texture", "albedo_texture_png", "confidence_texture", "normal_texture",
            "view_count_texture") + RELEASED_PREVIEWS
"""The products this stage publishes, in order: the textures (and the albedo's PNG), then their previews (when
on). Not the textured OBJ and its MTL (``textured_mesh``, ``textured_material``): the exports stage publishes
its copies under the same kinds, with the texture beside the OBJ (this artifact's MTL points at
``../textures/albedo.png``, a path some loaders refuse) and a GLB."""


@dataclass(frozen=True)
class TexturesConfig(Documented):
    atlas_faces: int = checked(40_000, ge=4)
    """Faces of the textured mesh (xatlas time grows faster than linearly with faces); at least 4, the
    decimation's floor (:func:`stages.numerics.mesh.decimate`)."""
    texture_size: int = checked(1024, ge=8)
    """Width and height of the texture atlas in texels; at least 8, the atlas packer's floor
    (:func:`stages.numerics.mesh.uv_atlas`)."""
    atlas_padding: int = checked(2, ge=0)
    """Texels between charts in the atlas."""
    atlas_max_chart_area_m2: float = checked(0.05, ge=0.0)
    """Largest chart of the atlas in square metres (0: no limit; xatlas' ``max_chart_area``). Growing and flattening
    a body's few large charts is most of xatlas' time: on the default capture 0.05 takes the stage from 14.2 to
    10.7 CPU s an action, and with ``diffuse_normals.occlusion_directions`` 128 as well (measured together) the
    relit views lose 0.02 dB (bench/bench_textures.py sweeps it)."""
    max_views: int = checked(3, ge=1)
    """A texel blends at most this many of the cameras that see it (the most frontal)."""
    depth_tolerance_m: float = checked(0.01, gt=0.0)
    """A texel is visible in a camera when its depth is within this of the mesh's depth there."""
    min_cos: float = checked(0.2, ge=-1.0, lt=1.0)
    """Cameras seeing a texel at more grazing angles than this cosine are not used (a cosine: in [-1, 1))."""
    min_alpha: float = checked(0.5, ge=0.0, lt=1.0)
    """Map pixels with a lower validity alpha are not baked."""
    previews: bool = True
    """Write PNG previews of the textures."""


class TexturesStage(Stage):
    """UV atlas of the decimated mesh and albedo/normal textures baked from the photometric maps."""

    name = "textures"
    version = "3"
    scope = "action"
    requires = ("geometry", "photometric", "decode")
    outputs = ("mesh", "textures", "previews")

    def run(self, ctx: StageContext) -> dict[str, Any]:
        from stages.numerics.bake import BakeView, atlas_textures

        cfg: TexturesConfig = self.config
        artifacts = ActionArtifacts(ctx.upstream)
        vertices, faces = artifacts.mesh()
        views = [BakeView(images={"albedo": artifacts.map("albedo", cam_id),
                                  "normal": np.ascontiguousarray(normal_alpha[..., :3])},
                          valid=valid, K=cam.K, cam_from_world=cam.cam_from_world)
                 for cam_id, cam, normal_alpha, _, valid in artifacts.camera_maps(cfg.min_alpha)]
        result = atlas_textures(vertices, faces, views, cfg.atlas_faces, cfg.texture_size, cfg.atlas_padding,
                                cfg.max_views, cfg.depth_tolerance_m, cfg.min_cos, cfg.atlas_max_chart_area_m2)
        _write_textures(ctx.out_dir, result, cfg.previews)
        return {"atlas_faces": int(len(result.faces)), "atlas_seconds": result.atlas_seconds,
                "bake_seconds": result.bake_seconds, "cameras": len(views),
                "bake": {k: v for k, v in result.baked.stats.items() if isinstance(v, (int, float, str))}}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        return released_files(self.name, artifact, RELEASED, optional=RELEASED_PREVIEWS)


def _write_textures(out: Path, result: Any, previews: bool) -> None:
    """The textures (EXR, and the albedo as PNG for the OBJ's material), the textured OBJ and the previews of a
    :class:`stages.numerics.bake.AtlasTextures`."""
    from pipeline.codecs.mesh import write_obj
    from stages.numerics.mesh import vertex_normals

    baked, atlas = result.baked, result.atlas
    writer = ArtifactWriter(TexturesStage.name, out)
    write_exr(writer.path("albedo_texture"), baked.textures["albedo"], header=EXR_HEADERS["texture_albedo"])
    write_exr(writer.path("normal_texture"), baked.textures["normal"], header=EXR_HEADERS["texture_normal"])
    write_exr(writer.path("view_count_texture"), baked.view_count.astype(np.float32),
              header=EXR_HEADERS["texture_view_count"])
    write_exr(writer.path("confidence_texture"), baked.confidence.astype(np.float32),
              header=EXR_HEADERS["texture_confidence"])
    # The OBJ's material shows the albedo in any viewer; the linear EXR is the data.
    write_png(writer.path("albedo_texture_png"), preview_linear(baked.textures["albedo"], exposure=1.0))
    atlas_vertices = np.asarray(result.vertices)[atlas.vmapping]
    write_obj(writer.path("textured_mesh"), atlas_vertices, atlas.faces, uvs=atlas.uvs, uv_faces=atlas.faces,
              normals=vertex_normals(atlas_vertices, atlas.faces),
              material={"name": "albedo", "map_Kd": "../textures/albedo.png"})
    if previews:
        covered = baked.covered.astype(np.float32)
        write_png(writer.path("texture_normal_preview"), preview_normals(baked.textures["normal"], covered))
        write_png(writer.path("texture_confidence_preview"), preview_scalar(baked.confidence))
