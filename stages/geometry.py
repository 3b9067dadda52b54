"""Action stage ``geometry``: the normal-supervised neural SDF and its mesh.

Wiring only: the action is :func:`stages.numerics.sdf_mesh.sdf_mesh` over :mod:`stages.numerics.sdf` (NeuS
with a hash encoding, trained from the photometric normal maps) and :mod:`stages.numerics.mesh` (narrow-band
marching cubes, components, decimation).

The SDF is trained twice (``deocclude``): eq. 1's normals lean away from whatever hides part of the LED
sphere, so a mesh fitted to them bulges where the body occludes itself (inner thighs, armpits, neck). A short
first pass gives a mesh whose visibility of the sphere divides that lean out of the normals
(:func:`stages.numerics.shadowing.deocclude_view`) and shows where it misses them; the second training, on the
de-occluded normals, gives the published mesh. bench/bench_sdf_schedule.py measures Chamfer against the
stage's time over the two passes' step counts.

The SDF's mesh is then refined at its outline (``silhouette``, :mod:`stages.numerics.silhouette`): its outer
contours move to the sub-pixel outline each white image measures against the session's clean plate. The published
``mesh`` is the refined one; the SDF's own stays in the store beside ``sdf.pt`` (``sdf/mesh.ply``;
bench/bench_silhouette.py compares the two).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.image import preview_normals, write_png
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext
from artifacts.facade import ActionArtifacts
from artifacts.layout import ArtifactWriter, released_files
from stages.numerics import numeric_threads
from stages.numerics.sdf_mesh import SDFMeshConfig
from stages.numerics.silhouette import SilhouetteConfig


RELEASED = ("mesh", "sdf_losses_preview", "mesh_normals_preview")
"""The products this stage publishes, in order: the mesh and its previews (when on). The SDF (``sdf/``) stays in
the work store."""


@dataclass(frozen=True)
class GeometryConfig(SDFMeshConfig):
    """The SDF, its passes and its mesh (:class:`stages.numerics.sdf_mesh.SDFMeshConfig`: ``sdf``,
    ``mesh_resolution``, ``face_budget``, ``deocclude`` and the passes' fields) and the stage's own fields."""

    min_alpha: float = 0.5
    """Photometric normals with a validity alpha below this are not used as supervision."""
    min_views: int = 8
    """Fail the action when fewer cameras have maps: the hull and the SDF are not constrained enough."""
    previews: bool = True
    """Write a loss-curve plot and rendered normals of the mesh beside the photometric ones."""
    silhouette: SilhouetteConfig = field(default_factory=SilhouetteConfig)
    """The mesh's outer contours moved to the sub-pixel outline the white images measure against the clean
    plates (:mod:`stages.numerics.silhouette`)."""


def load_sdf_views(artifacts: ActionArtifacts, min_alpha: float) -> tuple[list[str], list[Any]]:
    """The calibrated cameras that have maps, as :class:`SDFView` records (sorted by camera id)."""
    from stages.numerics.sdf import SDFView

    ids, views = [], []
    for cam_id, cam, normal_alpha, mask, valid in artifacts.camera_maps(min_alpha):
        views.append(SDFView(normals_world=np.ascontiguousarray(normal_alpha[..., :3]), normal_valid=valid,
                             mask=mask, K=cam.K, cam_from_world=cam.cam_from_world))
        ids.append(cam_id)
    return ids, views


def outline_views(artifacts: ActionArtifacts, ids: list[str], views: list[Any]) -> list[Any] | None:
    """The views' measured pixel coverage on their outline (:func:`stages.numerics.photometric.edge_coverage` of the
    decoded white image against the session's clean plate, around the view's mask) as
    :class:`stages.numerics.silhouette.OutlineView` records; None when a camera has no clean plate."""
    from stages.numerics.photometric import edge_coverage
    from stages.numerics.silhouette import OutlineView

    out = []
    for cam_id, view in zip(ids, views):
        plate = artifacts.plate(cam_id)
        if plate is None:
            return None
        full_on = artifacts.exr("full_on", camera=cam_id)[..., :3]
        # float16: a step of at most 0.0005 in coverage, half the memory of 32 full frames
        out.append(OutlineView(K=view.K, cam_from_world=view.cam_from_world,
                               coverage=edge_coverage(view.mask, full_on, plate).astype(np.float16)))
    return out


def refined_mesh(artifacts: ActionArtifacts, ids: list[str], views: list[Any], vertices: np.ndarray,
                 faces: np.ndarray, cfg: SilhouetteConfig, ctx: StageContext) -> tuple[np.ndarray, dict[str, Any]]:
    """The SDF's mesh with its outer contours moved to the views' measured outline
    (:func:`stages.numerics.silhouette.refine_silhouettes`), and the step's record; the mesh as it is when
    ``cfg`` turns the step off or the session has no clean plates (said in the log)."""
    from stages.numerics.silhouette import refine_silhouettes

    if not cfg.enabled or cfg.iterations == 0:
        return vertices, {"enabled": False}
    outlines = outline_views(artifacts, ids, views)
    if outlines is None:
        ctx.log.info(f"{ctx.scope_id}: silhouette refinement skipped: the session has no clean plates")
        return vertices, {"enabled": False, "skipped": "no clean plates"}
    refined, stats = refine_silhouettes(vertices, faces, outlines, cfg)
    ctx.log.info(f"{ctx.scope_id}: silhouette refinement moved {stats['moved_vertices']} vertices, mean "
                 f"{stats['mean_move_all_mm']:.2f} mm, most {stats['max_move_mm']:.2f} mm ({stats['seconds']:.1f} s)")
    return refined, {"enabled": True} | stats


def _loss_plot(path: Path, history: dict[str, list[float]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    its = history.get("iteration", [])
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    for name, values in history.items():
        if name in ("iteration", "seconds") or len(values) != len(its) or not values:
            continue
        ax.plot(its, values, label=name)
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_title("SDF training losses")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def _normals_comparison(vertices: np.ndarray, faces: np.ndarray, views: list[Any],
                        count: int = 4) -> np.ndarray:
    """Rows of [photometric normals | mesh normals] for ``count`` cameras spread around the stage."""
    from stages.numerics.raycast import mesh_scene, render_mesh

    scene = mesh_scene(vertices, faces)
    picks = np.linspace(0, len(views) - 1, count).round().astype(int)
    rows = []
    for i in picks:
        view = views[i]
        h, w = view.mask.shape
        rendered = render_mesh(None, None, view.K, view.cam_from_world, h, w, scene=scene)
        rows.append(np.concatenate([preview_normals(view.normals_world, view.normal_valid.astype(np.float32)),
                                    preview_normals(rendered["normals_world"], rendered["hit"].astype(np.float32))],
                                   axis=1))
    return np.concatenate(rows, axis=1) if rows else np.zeros((1, 1, 3), np.uint8)


class GeometryStage(Stage):
    """Trains the SDF of one action from its normal maps and masks, then meshes it."""

    name = "geometry"
    # 4: the mesh's outer contours refined to the views' measured outline (silhouette)
    version = "4"
    scope = "action"
    requires = ("decode", "photometric", "plates")
    outputs = ("mesh", "sdf", "previews")
    resources = {"GPU": 1}

    def run(self, ctx: StageContext) -> dict[str, Any]:
        import torch

        from pipeline.codecs.mesh import write_ply
        from stages.numerics.mesh import vertex_normals
        from stages.numerics.sdf_mesh import sdf_mesh

        torch.set_num_threads(numeric_threads())
        cfg: GeometryConfig = self.config
        upstream = ActionArtifacts(ctx.upstream)
        ids, views = load_sdf_views(upstream, cfg.min_alpha)
        if len(views) < cfg.min_views:
            raise InputError(upstream.where(),
                             f"{len(views)} camera(s) have normal maps; the SDF needs at least {cfg.min_views}")
        fitted = sdf_mesh(views, cfg, label=ctx.scope_id, progress=ctx.progress, log=ctx.log.info)
        result, vertices, faces, mesh_stats = fitted.result, fitted.vertices, fitted.faces, fitted.mesh_stats
        out = ctx.out_dir
        (out / "sdf").mkdir(parents=True, exist_ok=True)
        # the SDF's own mesh stays in the work store: what the silhouette step started from (bench_silhouette)
        write_ply(out / "sdf" / "mesh.ply", vertices, faces)
        vertices, silhouette = refined_mesh(upstream, ids, views, vertices, faces, cfg.silhouette, ctx)
        torch.save(result.field.to_state(), out / "sdf" / "sdf.pt")
        (out / "sdf" / "training.json").write_text(json.dumps(
            {"bounds": np.asarray(result.bounds).tolist(), "cameras": ids, "stats": result.stats,
             "history": result.history, "deocclusion": fitted.deocclusion, "first_pass": fitted.first_pass,
             "third_pass": fitted.third_pass,
             "schedule": {"subject_pixel_m": fitted.subject_pixel_m}},
            indent=1, default=float))
        write_ply(ArtifactWriter(self.name, out).path("mesh"), vertices, faces, normals=vertex_normals(vertices, faces))
        if cfg.previews:
            writer = ArtifactWriter(self.name, out)
            _loss_plot(writer.path("sdf_losses_preview"), result.history)
            write_png(writer.path("mesh_normals_preview"), _normals_comparison(vertices, faces, views))
        return {"cameras": len(views), "train_seconds": fitted.train_seconds, "passes": fitted.passes,
                "iterations": list(fitted.iterations),
                "faces_extracted": int(mesh_stats["faces_extracted"]), "mesh_faces": int(len(faces)),
                "mesh_vertices": int(len(vertices)), "bounds": np.asarray(result.bounds).tolist(),
                "deocclusion": fitted.deocclusion, "silhouette": silhouette,
                "third_pass": None if fitted.third_pass is None else
                {k: v for k, v in fitted.third_pass.items() if k != "second_pass"},
                "sdf": {k: v for k, v in result.stats.items() if isinstance(v, (int, float, str))},
                "mesh": {k: v for k, v in mesh_stats.items() if isinstance(v, (int, float, str))}}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        return released_files(self.name, artifact, RELEASED, optional=RELEASED[1:])
