"""The geometry stage's action: the neural SDF trained from the normal maps, in one or two passes, and its mesh.

:func:`sdf_mesh` trains :func:`stages.numerics.sdf.train_sdf` on the views, marches the field's narrow band,
keeps the largest component and decimates it; with ``deocclude`` it trains a second time on the normals with the
first mesh's occlusion of the LED sphere divided out (:func:`deoccluded_sdf_views`). Pure: arrays and
dataclasses in, arrays out. ``cfg`` is a :class:`stages.geometry.GeometryConfig`.
"""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from stages.geometry import GeometryConfig


def deoccluded_sdf_views(views: list[Any], vertices: np.ndarray, faces: np.ndarray, directions: int = 256,
                         min_visible: float = 0.1,
                         error_floor_deg: float | None = None) -> tuple[list[Any], dict[str, float]]:
    """The SDF views with their normals' occlusion by the mesh ``vertices``/``faces`` divided out (valid pixels
    only; the rest keep theirs) and the mean statistics of :func:`stages.numerics.shadowing.deocclude_view`
    over the views.

    With ``error_floor_deg`` each view also gets a ``sample_weight``: by how many degrees more than that the
    mesh's normal misses the de-occluded one (valid pixels the mesh covers; 0 elsewhere), and the statistics
    ``error_weighted_fraction`` (share of the valid pixels with a weight) and ``error_mean_deg`` (mean miss
    over the valid pixels the mesh covers)."""
    from stages.numerics.metrics import angular_error_deg
    from stages.numerics.raycast import mesh_scene, render_mesh
    from stages.numerics.shadowing import deocclude_view

    scene = mesh_scene(vertices, faces)
    out, records = [], []
    for view in views:
        valid = np.asarray(view.normal_valid, bool)
        normals = np.where(valid[..., None], view.normals_world, 0.0).astype(np.float32)
        render = None
        if error_floor_deg is not None:
            render = render_mesh(None, None, view.K, view.cam_from_world, *valid.shape, scene=scene)
        fixed, record = deocclude_view(scene, view.K, view.cam_from_world, normals, directions, min_visible, render)
        fixed = np.where(valid[..., None], fixed, view.normals_world).astype(np.float32)
        changes: dict[str, Any] = {"normals_world": fixed}
        if render is not None:
            covered = valid & (render["depth_m"] > 0)
            miss = np.where(covered, angular_error_deg(render["normals_world"], fixed), 0.0)
            miss = np.nan_to_num(miss, nan=0.0, posinf=0.0, neginf=0.0)
            changes["sample_weight"] = np.maximum(miss - float(error_floor_deg), 0.0).astype(np.float32)
            record = record | {"error_weighted_fraction": float((changes["sample_weight"] > 0).sum() / max(valid.sum(), 1)),
                               "error_mean_deg": float(miss[covered].mean()) if covered.any() else 0.0}
        out.append(dataclasses.replace(view, **changes))
        records.append(record)
    stats = {k: float(np.mean([r[k] for r in records])) for k in records[0]} if records else {}
    return out, stats


def pass_configs(cfg: GeometryConfig) -> tuple[Any, Any]:
    """The SDF configs of the stage's passes: ``(first, second)``, ``second`` None without ``deocclude``.

    The first pass runs ``first_pass_iterations`` steps of ``cfg.sdf`` (its warm-up capped to them; the sharpness
    ramp and coarse-to-fine are fractions of the steps); the second runs ``cfg.sdf`` with the importance share
    of its rays, or continues the first field for ``deocclude_iterations`` steps at the final sharpness."""
    if not cfg.deocclude:
        return cfg.sdf, None
    first = cfg.sdf
    if cfg.first_pass_iterations > 0:
        first = dataclasses.replace(cfg.sdf, iterations=cfg.first_pass_iterations,
                                    warmup_iterations=min(cfg.sdf.warmup_iterations, cfg.first_pass_iterations))
    second = cfg.sdf
    if cfg.deocclude_iterations > 0:
        second = dataclasses.replace(cfg.sdf, iterations=cfg.deocclude_iterations, inv_s_start=cfg.sdf.inv_s_end,
                                     coarse_to_fine=0.0,
                                     warmup_iterations=min(cfg.sdf.warmup_iterations, cfg.deocclude_iterations))
    return first, dataclasses.replace(second, importance_fraction=cfg.second_pass_importance)


def second_pass_views(cfg: GeometryConfig, views: list[Any], vertices: np.ndarray,
                      faces: np.ndarray) -> tuple[list[Any], dict[str, float]]:
    """The second SDF pass's views as ``cfg`` asks for them: :func:`deoccluded_sdf_views` of the first mesh,
    with sample weights when ``cfg.second_pass_importance`` draws a share of the rays by them."""
    return deoccluded_sdf_views(views, vertices, faces, cfg.deocclude_directions, cfg.deocclude_min_visible,
                                cfg.second_pass_error_floor_deg if cfg.second_pass_importance > 0 else None)


@dataclass(frozen=True)
class SDFMesh:
    """The published pass's field and mesh, and what the passes measured."""

    result: Any
    """:class:`stages.numerics.sdf.SDFResult` of the last pass (field, bounds, stats, history)."""
    vertices: np.ndarray
    """(V, 3) float64 metres, world frame: the largest component, decimated to the face budget."""
    faces: np.ndarray
    """(F, 3) int."""
    mesh_stats: dict[str, Any]
    """The marching's statistics and ``faces_extracted`` before the component and decimation."""
    deocclusion: dict[str, float]
    """Statistics of the second pass's de-occluded normals (empty with one pass)."""
    first_pass: dict[str, Any] | None
    """The first pass's stats, history and face count when there were two."""
    passes: int
    """1 or 2."""
    train_seconds: float
    """Wall time of the passes, meshing included."""


def sdf_mesh(views: list[Any], cfg: GeometryConfig, label: str = "the action",
             progress: Callable[[int, int, str], None] | None = None,
             log: Callable[[str], None] | None = None) -> SDFMesh:
    """The mesh of the neural SDF trained on ``views`` (:class:`stages.numerics.sdf.SDFView`) as ``cfg`` asks:
    :func:`pass_configs`' passes, the second on :func:`second_pass_views` of the first mesh. ``progress(step,
    steps, message)`` is told about once per tenth of both passes' steps; ``log`` gets one line about the second
    pass. ``label`` names the fit in errors.

    Raises:
        RuntimeError: a pass gave no usable surface.
    """
    from stages.numerics.mesh import decimate, extract_mesh, largest_component
    from stages.numerics.sdf import train_sdf

    start = time.perf_counter()
    passes = 2 if cfg.deocclude else 1
    first, second = pass_configs(cfg)
    total = first.iterations + (second.iterations if second is not None else 0)
    reported = {"tenth": 0, "done": 0}

    def on_log(iteration: int, record: dict[str, float]) -> None:
        # train_sdf calls every log_every steps; show about one line per tenth of the whole schedule
        step = reported["done"] + iteration
        tenth = 10 * step // max(total, 1)
        if tenth > reported["tenth"] and progress is not None:
            reported["tenth"] = tenth
            progress(step, total, f"SDF loss {record.get('loss', float('nan')):.4f}")

    def fit(sdf_views: list[Any], config: Any, init: Any = None, resolution: int = cfg.mesh_resolution,
            start: Any = None):
        result = train_sdf(sdf_views, config, progress=on_log, init=init, start=start)
        reported["done"] += config.iterations
        vertices, faces, mesh_stats = extract_mesh(result.field.sdf_numpy, np.asarray(result.bounds), resolution)
        extracted = len(faces)
        vertices, faces = largest_component(vertices, faces)
        vertices, faces = decimate(vertices, faces, cfg.face_budget)
        if len(faces) == 0 or not np.all(np.isfinite(vertices)):
            raise RuntimeError(f"the SDF of {label} gave no usable surface (faces {len(faces)})")
        return result, vertices, faces, mesh_stats | {"faces_extracted": extracted}

    result, vertices, faces, mesh_stats = fit(views, first, resolution=(
        cfg.first_pass_mesh_resolution or cfg.mesh_resolution) if second is not None else cfg.mesh_resolution)
    first_pass = None
    deocclusion: dict[str, float] = {}
    if second is not None:
        tick = time.perf_counter()
        sdf_views, deocclusion = second_pass_views(cfg, views, vertices, faces)
        deocclusion["seconds"] = time.perf_counter() - tick
        weighted = (f"; {100 * deocclusion['error_weighted_fraction']:.1f}% of the pixels, where the first mesh "
                    f"misses the normals by > {cfg.second_pass_error_floor_deg:g} deg, draw "
                    f"{100 * cfg.second_pass_importance:.0f}% of the rays") if "error_weighted_fraction" in deocclusion else ""
        if log is not None:
            log(f"second SDF pass on de-occluded normals (mean turn "
                f"{deocclusion['occlusion_correction_mean_deg']:.2f} deg, {deocclusion['seconds']:.1f} s{weighted})")
        first_pass = {"stats": result.stats, "history": result.history, "mesh_faces": int(len(faces))}
        # the same masks and cameras: the first pass's hull and pre-fitted field are the second's start
        result, vertices, faces, mesh_stats = fit(sdf_views, second,
                                                  result.field if cfg.deocclude_iterations > 0 else None,
                                                  start=result.start)
    return SDFMesh(result=result, vertices=vertices, faces=faces, mesh_stats=mesh_stats, deocclusion=deocclusion,
                   first_pass=first_pass, passes=passes, train_seconds=time.perf_counter() - start)
