"""The geometry stage's action: the neural SDF trained from the normal maps, in one or two passes, and its mesh.

:func:`sdf_mesh` trains :func:`stages.numerics.sdf.train_sdf` on the views, marches the field's narrow band,
keeps the largest component and decimates it; with ``deocclude`` it trains a second time on the normals with the
first mesh's occlusion of the LED sphere divided out (:func:`deoccluded_sdf_views`). Pure: arrays and
dataclasses in, arrays out. ``cfg`` is an :class:`SDFMeshConfig` (the geometry stage's config is one, with the
stage's own fields added).
"""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.config import Documented, checked
from stages.numerics.sdf import SDF_PRESETS, SDFConfig


@dataclass(frozen=True)
class SDFMeshConfig(Documented):
    """The neural SDF, its passes and its mesh: what :func:`sdf_mesh` reads (the fields of the geometry stage's
    config that are not the stage's own, under the same names)."""

    sdf: SDFConfig = field(default_factory=lambda: SDF_PRESETS["cpu"])
    """The neural SDF: encoding, network, sampling, losses and schedule (presets in stages.numerics.sdf)."""
    mesh_resolution: int = 512
    """Marching-cubes cells along the longest side of the SDF's bounding box (narrow band only)."""
    face_budget: int = 200_000
    """Quadric decimation target of the published mesh (mesh/mesh.ply)."""
    deocclude: bool = True
    """Train the SDF a second time, on eq. 1's normals with the first mesh's occlusion of the LED sphere divided
    out (:func:`stages.numerics.shadowing.deocclude_view`). Eq. 1 measures the cosine-weighted mean of the
    *visible* light directions, which leans away from an arm or the other leg; fitted to those normals the
    surface bulges out where it is occluded (inner thighs, armpits, neck: 4-5 mm on A0000). The first pass runs
    ``first_pass_iterations`` steps (the published mesh and ``sdf/sdf.pt`` are the second pass's;
    ``training.json`` keeps both)."""
    deocclude_iterations: int = checked(0, ge=0)
    """0: the second pass trains a new field with the full schedule. N > 0: it continues the first field for N
    steps at the schedule's final sharpness with every hash level on (cheaper, and a worse mesh than a new
    field on the default capture)."""
    first_pass_iterations: int = checked(150, ge=0)
    """Steps of the first SDF pass when ``deocclude`` trains two (0: ``sdf.iterations``; the schedule's warm-up,
    sharpness ramp and coarse-to-fine are scaled to it). The first mesh only has to give the body's occlusion
    of the LED sphere and where it misses the normals; the published mesh is the second pass's
    (bench/bench_sdf_schedule.py: time against Chamfer over both passes' steps). On the default capture (two SDF
    seeds, `ultrastage run --config` on copies of one store) 150 steps against 600 save about 17 CPU s an action
    and move relit views 27.32 -> 27.34 dB, Chamfer 1.065 -> 1.058 mm, held-out normals 3.66 -> 3.69 deg and the
    intrinsic albedo texture 33.36 -> 33.28 dB (means of the two seeds)."""
    fine_pixel_m: float = checked(0.0045, ge=0.0)
    """Subjects seen finer than this, metres per pixel at the subject (:func:`stages.numerics.sdf.subject_footprint_m`:
    the median over the views), train at least ``fine_first_pass_iterations`` and ``fine_iterations`` steps
    (:func:`schedule_for_footprint`; 0 = off). The finer the pixels, the less often each pixel's ray is drawn, and
    below 4 mm the cpu preset's ``inv_s_end_per_pixel`` also raises the SDF's final sharpness, which takes more
    steps to settle. 150 + 1,500 steps against 600 + 1,800 cost (two SDF seeds where two are given): the default
    body at 384 px (4.2 mm) 0.10-0.23 dB of relit views and 0.27-0.78 dB of the relighting set, at 640 px (2.5 mm)
    0.3 dB and 0.7-0.9 dB, the ICT head (1.1 mm) 0.8 dB of relit views and 0.3 mm of Chamfer; at the default
    capture's 5.0 mm 0.05-0.07 dB of relit views, for 29 CPU s an action that `make dataset` cannot spare, so
    it and the panel's bodies (4.6-6.0 mm pixels) keep the shorter schedule."""
    fine_first_pass_iterations: int = checked(600, ge=1)
    """The first pass's least steps for a subject seen finer than ``fine_pixel_m`` (a ``first_pass_iterations`` of
    0, the whole schedule, stays 0)."""
    fine_iterations: int = checked(1800, ge=1)
    """The second pass's (``sdf.iterations``) least steps for a subject seen finer than ``fine_pixel_m``."""
    first_pass_mesh_resolution: int = checked(256, ge=0)
    """Marching-cubes cells of the first pass's mesh (0: ``mesh_resolution``)."""
    deocclude_directions: int = checked(128, ge=16)
    """Directions (Fibonacci sphere) of the visibility traced for the second pass."""
    deocclude_min_visible: float = checked(0.1, ge=0.0, lt=1.0)
    """Pixels whose cosine-weighted visible fraction is below this keep eq. 1's normal."""
    second_pass_importance: float = checked(0.2, ge=0.0, lt=1.0)
    """Share of the second pass's rays drawn where the first mesh's normal is more than
    ``second_pass_error_floor_deg`` off the de-occluded normal, in proportion to the excess (the fingers, the
    face, folds and occluding contours the first fit missed); the rest are drawn uniformly. 0 = uniform. On the
    default capture the share lowers the second pass's Chamfer together with the cpu SDF preset's table size
    and grazing/outlier settings; a share of 0.5 leaves too few rays for the rest. The mask loss counts only
    the uniform rays."""
    second_pass_error_floor_deg: float = checked(10.0, ge=0.0)
    """Normal disagreement below which a pixel gets no extra rays (the photometric normals' own noise)."""
    second_pass_carve_weight: float = checked(90.0, ge=0.0)
    """Sample weight (in the normal misses' degrees) of the pixels the first mesh covers more than
    ``_CARVE_INSET_PX`` inside its outline where the mask says background: a gap between limbs the masks open
    that the first fit webbed over (one view's background alone carves it slowly). Those rays count in the mask
    loss (:attr:`stages.numerics.sdf.SDFView.sample_weight`); together they draw at most ``_CARVE_SHARE_MAX`` of
    the importance-drawn rays. 0 = none. On the procedural subject, whose slots the masks open by their gradient
    ratios, Chamfer 1.89 -> 1.59 mm at SDF seed 0 (2.14 before the slots opened; seed 1: 1.97 -> 1.51 with both);
    the default capture moves within a seed's spread."""
    third_pass_iterations: int = checked(900, ge=0)
    """Steps of a third pass, which continues the second pass's field at the final sharpness on the normals
    de-occluded against the second mesh (the sample weights stay the first mesh's), run when that de-occlusion
    turns more than ``third_pass_turned_share`` of the valid pixels' normals by over ``_TURN_DEG`` from the first
    mesh's (:func:`turned_share`, on every view's pixels of a lattice of step ``DECISION_PIXEL_STEP``). The first
    mesh webs the gaps between limbs a short pass cannot open, and eq. 1's normals inside them, de-occluded against
    the web, stay wrong until a mesh without it de-occludes them. 0: no third pass (nor the second de-occlusion
    that decides it)."""
    third_pass_turned_share: float = checked(0.038, ge=0.0, le=1.0)
    """The share of the valid pixels whose de-occluded normal turns by over ``_TURN_DEG`` between the first and the
    second mesh above which the third pass runs. Over every view of the subject panel's stores (README, *A third SDF
    pass*) the share is 1.6-3.4% on the plain bodies and the ICT head, where the third pass moves the SDF's mesh by
    -0.14 to +0.08 mm of Chamfer (mean -0.03: a seed's spread, for 900 more steps), 4.3% on the skirt
    (5.26 -> 4.92 mm) and 13.7% on the procedural subject (1.81 -> 1.28 mm); the bound sits midway between the
    heavy body's 3.4% and the skirt's."""


DECISION_PIXEL_STEP = 2
"""The third pass's decision (:attr:`SDFMeshConfig.third_pass_turned_share`) de-occludes every view's pixels on a
lattice of this step in rows and columns (a quarter of them at 2, :func:`on_pixel_lattice`)."""
_TURN_DEG = 5.0
"""The turn of a pixel's de-occluded normal between the first and the second mesh that counts for
``third_pass_turned_share``."""
_CARVE_INSET_PX = 2
"""Pixels the first mesh covers within this distance of its outline are not carving pixels: there the mask and the
mesh differ by the outline's own sub-pixel error."""
_CARVE_SHARE_MAX = 0.2
"""The carving pixels draw at most this share of the second pass's importance-drawn rays (their weights scaled
down when they would draw more): the rest stay with the pixels whose normals the first mesh misses. The ICT head's
first mesh spans 14,000 background pixels of its masks, which uncapped drew about 40% of those rays (relit views
-0.53 dB against no carving; capped, -0.43 dB); the procedural subject's 4,862 draw 12%, the default capture's
about 470 an action 2-3%."""


def carve_pixels(mask: np.ndarray, mesh_hit: np.ndarray, inset_px: int = _CARVE_INSET_PX) -> np.ndarray:
    """(H, W) bool: background pixels of ``mask`` that the mesh's render ``mesh_hit`` (H, W) bool covers more than
    ``inset_px`` pixels inside its outline (a hole in the mask the mesh spans)."""
    from scipy import ndimage

    mask, mesh_hit = np.asarray(mask, bool), np.asarray(mesh_hit, bool)
    if mask.shape != mesh_hit.shape or mask.ndim != 2:
        raise ValueError(f"mask {mask.shape} and mesh_hit {mesh_hit.shape} must be one (H, W) shape")
    inner = ndimage.binary_erosion(mesh_hit, iterations=inset_px, border_value=0) if inset_px > 0 else mesh_hit
    return inner & ~mask


def deoccluded_sdf_views(views: list[Any], vertices: np.ndarray, faces: np.ndarray, directions: int = 256,
                         min_visible: float = 0.1, error_floor_deg: float | None = None,
                         carve_weight: float = 0.0) -> tuple[list[Any], dict[str, float]]:
    """The SDF views with their normals' occlusion by the mesh ``vertices``/``faces`` divided out (valid pixels
    only; the rest keep theirs) and the mean statistics of :func:`stages.numerics.shadowing.deocclude_view`
    over the views.

    With ``error_floor_deg`` each view also gets a ``sample_weight``: by how many degrees more than that the
    mesh's normal misses the de-occluded one (valid pixels the mesh covers; 0 elsewhere), and the statistics
    ``error_weighted_fraction`` (share of the valid pixels with a weight) and ``error_mean_deg`` (mean miss
    over the valid pixels the mesh covers). With ``carve_weight`` above 0 as well, the :func:`carve_pixels` of
    the mesh and the view's mask get that weight, scaled down over every view where their weights would make more
    than ``_CARVE_SHARE_MAX`` of all the views' weights, and ``carve_pixels`` (their count over the views) and
    ``carve_share`` (their share of the weights) are said."""
    from stages.numerics.metrics import angular_error_deg
    from stages.numerics.raycast import mesh_scene, render_mesh
    from stages.numerics.shadowing import deocclude_view

    scene = mesh_scene(vertices, faces)
    out, records, carves = [], [], []
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
            weight = np.maximum(miss - float(error_floor_deg), 0.0).astype(np.float32)
            record = record | {"error_weighted_fraction": float((weight > 0).sum() / max(valid.sum(), 1)),
                               "error_mean_deg": float(miss[covered].mean()) if covered.any() else 0.0}
            if carve_weight > 0:
                carve = carve_pixels(view.mask, render["hit"])
                weight[carve] = np.float32(carve_weight)
                record["carve_pixels"] = float(carve.sum())
                carves.append(carve)
            changes["sample_weight"] = weight
        out.append(dataclasses.replace(view, **changes))
        records.append(record)
    stats = {k: float(np.sum([r[k] for r in records]) if k == "carve_pixels" else np.mean([r[k] for r in records]))
             for k in records[0]} if records else {}
    if carves:
        stats["carve_share"] = _cap_carve_share(out, carves, _CARVE_SHARE_MAX)
    return out, stats


def on_pixel_lattice(views: list[Any], step: int) -> list[Any]:
    """The views with ``normal_valid`` kept only on the pixels whose row and column are multiples of ``step``
    (>= 1): a share of pixels read on them stands for every view's, where a subset of the views stands for its
    own (a rig's cameras come in rings, and every k-th camera can be one ring: the lowest ring of the default
    stage looks up under a skirt's hem that the others do not see)."""
    if int(step) != step or step < 1:
        raise ValueError(f"step must be a positive integer, got {step}")
    out = []
    for view in views:
        lattice = np.zeros(np.shape(view.normal_valid), bool)
        lattice[::step, ::step] = True
        out.append(dataclasses.replace(view, normal_valid=np.asarray(view.normal_valid, bool) & lattice))
    return out


def turned_share(before: list[Any], after: list[Any], turn_deg: float = _TURN_DEG) -> float:
    """The share of the views' valid pixels (``normal_valid``) whose ``normals_world`` turn by more than
    ``turn_deg`` degrees from ``before`` to ``after`` (two lists of the same views, e.g. de-occluded against two
    meshes); 0 without valid pixels."""
    from stages.numerics.metrics import angular_error_deg

    if len(before) != len(after):
        raise ValueError(f"turned_share: {len(before)} views before, {len(after)} after")
    turned = valid = 0
    for a, b in zip(before, after):
        mask = np.asarray(a.normal_valid, bool)
        angle = np.nan_to_num(angular_error_deg(a.normals_world, b.normals_world), nan=0.0)
        turned += int((mask & (angle > turn_deg)).sum())
        valid += int(mask.sum())
    return turned / valid if valid else 0.0


def _cap_carve_share(views: list[Any], carves: list[np.ndarray], share_max: float) -> float:
    """Scale the views' ``sample_weight`` on their carving pixels ``carves`` (per view (H, W) bool) down, in place,
    so that those pixels hold at most ``share_max`` of all the weights; returns the share they hold."""
    carve_total = sum(float(v.sample_weight[c].sum()) for v, c in zip(views, carves))
    other_total = sum(float(v.sample_weight.sum()) for v in views) - carve_total
    if carve_total <= 0:
        return 0.0
    allowed = share_max / (1.0 - share_max) * other_total
    if carve_total > allowed:
        for v, c in zip(views, carves):
            v.sample_weight[c] *= np.float32(allowed / carve_total)
        carve_total = allowed
    return carve_total / (carve_total + other_total) if carve_total + other_total > 0 else 0.0


def schedule_for_footprint(cfg: SDFMeshConfig, pixel_m: float) -> SDFMeshConfig:
    """``cfg`` with the step counts a subject seen at ``pixel_m`` metres per pixel trains with: below
    ``cfg.fine_pixel_m`` the first pass's steps raised to ``fine_first_pass_iterations`` (unless it runs the whole
    schedule, 0) and ``sdf.iterations`` to ``fine_iterations``; never lowered. ``cfg`` itself when the rule is
    off, the pixels are not finer or the steps are already at least those."""
    if not pixel_m > 0:
        raise ValueError(f"pixel_m must be positive, got {pixel_m}")
    if not pixel_m < cfg.fine_pixel_m:
        return cfg
    first = cfg.first_pass_iterations and max(cfg.first_pass_iterations, cfg.fine_first_pass_iterations)
    second = max(cfg.sdf.iterations, cfg.fine_iterations)
    if (first, second) == (cfg.first_pass_iterations, cfg.sdf.iterations):
        return cfg
    return dataclasses.replace(cfg, first_pass_iterations=first, sdf=dataclasses.replace(cfg.sdf, iterations=second))


def pass_configs(cfg: SDFMeshConfig) -> tuple[Any, Any]:
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


def second_pass_views(cfg: SDFMeshConfig, views: list[Any], vertices: np.ndarray,
                      faces: np.ndarray) -> tuple[list[Any], dict[str, float]]:
    """The second SDF pass's views as ``cfg`` asks for them: :func:`deoccluded_sdf_views` of the first mesh,
    with sample weights when ``cfg.second_pass_importance`` draws a share of the rays by them."""
    weighted = cfg.second_pass_importance > 0
    return deoccluded_sdf_views(views, vertices, faces, cfg.deocclude_directions, cfg.deocclude_min_visible,
                                cfg.second_pass_error_floor_deg if weighted else None,
                                cfg.second_pass_carve_weight if weighted else 0.0)


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
    """1, 2 or 3."""
    train_seconds: float
    """Wall time of the passes, meshing included."""
    second_pass_start_s: float = 0.0
    """Wall time before the second pass's training began (the first pass, its mesh and the de-occlusion); 0 with
    one pass."""
    subject_pixel_m: float | None = None
    """The subject's pixel footprint the schedule was chosen for (:func:`schedule_for_footprint`; None with the
    rule off or when the views give no footprint)."""
    third_pass: dict[str, Any] | None = None
    """The third pass's decision (``turned_share``, ``ran``, ``deocclusion_seconds``) and, when it ran, the second
    pass's stats, history and face count; None when it was not considered."""

    @property
    def iterations(self) -> tuple[int, ...]:
        """The steps each pass trained (from the passes' own statistics)."""
        first = (int(self.first_pass["stats"]["iterations"]),) if self.first_pass is not None else ()
        second = ((int(self.third_pass["second_pass"]["stats"]["iterations"]),)
                  if self.third_pass is not None and self.third_pass["ran"] else ())
        return first + second + (int(self.result.stats["iterations"]),)


def sdf_mesh(views: list[Any], cfg: SDFMeshConfig, label: str = "the action",
             progress: Callable[[int, int, str], None] | None = None,
             log: Callable[[str], None] | None = None,
             checkpoint: Callable[[int, int, Any], None] | None = None,
             on_mesh: Callable[[int, np.ndarray, np.ndarray], None] | None = None) -> SDFMesh:
    """The mesh of the neural SDF trained on ``views`` (:class:`stages.numerics.sdf.SDFView`) as ``cfg`` asks:
    :func:`pass_configs`' passes with the steps :func:`schedule_for_footprint` gives the subject's pixel footprint
    (``log`` is told when they are raised, or when the views give no footprint), the second on
    :func:`second_pass_views` of the first mesh, and a third (``third_pass_iterations``) when the normals
    de-occluded against the second mesh turn from the first's by :func:`turned_share` over
    ``third_pass_turned_share``. ``progress(step, steps, message)`` is told about once per tenth of the passes'
    steps; ``log`` gets one line about the second pass and one about the third; ``checkpoint(pass, iteration,
    field)`` (pass 1, 2 or 3) is :func:`stages.numerics.sdf.train_sdf`'s checkpoint hook of each pass (every
    ``log_every`` steps); ``on_mesh(pass, vertices, faces)`` is given each pass's mesh as it is made (what
    bench/bench_third_pass.py compares). ``label`` names the fit in errors.

    Raises:
        RuntimeError: a pass gave no usable surface.
    """
    from stages.numerics.mesh import decimate, extract_mesh, largest_component
    from stages.numerics.sdf import subject_footprint_m, train_sdf

    start = time.perf_counter()
    passes = 2 if cfg.deocclude else 1
    pixel_m = None
    if cfg.fine_pixel_m > 0:
        try:
            pixel_m = subject_footprint_m(views)
        except ValueError as error:  # the training's own checks name what is wrong with such views
            if log is not None:
                log(f"no pixel footprint for {label} ({error}): the schedule as configured")
    if pixel_m is not None:
        chosen = schedule_for_footprint(cfg, pixel_m)
        if chosen is not cfg and log is not None:
            def steps(c: SDFMeshConfig) -> str:
                return " + ".join(str(p.iterations) for p in pass_configs(c) if p is not None)

            log(f"subject seen at {1000 * pixel_m:.2f} mm per pixel (finer than {1000 * cfg.fine_pixel_m:g} mm): "
                f"SDF steps {steps(chosen)} instead of {steps(cfg)}")
        cfg = chosen
    first, second = pass_configs(cfg)
    reported = {"tenth": 0, "done": 0, "total": first.iterations + (second.iterations if second is not None else 0)}

    def on_log(iteration: int, record: dict[str, float]) -> None:
        # train_sdf calls every log_every steps; show about one line per tenth of the whole schedule
        step = reported["done"] + iteration
        tenth = 10 * step // max(reported["total"], 1)
        if tenth > reported["tenth"] and progress is not None:
            reported["tenth"] = tenth
            progress(step, reported["total"], f"SDF loss {record.get('loss', float('nan')):.4f}")

    def fit(sdf_views: list[Any], config: Any, init: Any = None, resolution: int = cfg.mesh_resolution,
            start: Any = None, index: int = 1):
        hook = None if checkpoint is None else (lambda iteration, field_: checkpoint(index, iteration, field_))
        result = train_sdf(sdf_views, config, progress=on_log, checkpoint=hook, init=init, start=start)
        reported["done"] += config.iterations
        vertices, faces, mesh_stats = extract_mesh(result.field.sdf_numpy, np.asarray(result.bounds), resolution)
        extracted = len(faces)
        vertices, faces = largest_component(vertices, faces)
        vertices, faces = decimate(vertices, faces, cfg.face_budget)
        if len(faces) == 0 or not np.all(np.isfinite(vertices)):
            raise RuntimeError(f"the SDF of {label} gave no usable surface (faces {len(faces)})")
        if on_mesh is not None:
            on_mesh(index, vertices, faces)
        return result, vertices, faces, mesh_stats | {"faces_extracted": extracted}

    result, vertices, faces, mesh_stats = fit(views, first, resolution=(
        cfg.first_pass_mesh_resolution or cfg.mesh_resolution) if second is not None else cfg.mesh_resolution)
    first_pass = third_pass = None
    deocclusion: dict[str, float] = {}
    second_start = 0.0
    if second is not None:
        tick = time.perf_counter()
        sdf_views, deocclusion = second_pass_views(cfg, views, vertices, faces)
        deocclusion["seconds"] = time.perf_counter() - tick
        weighted = (f"; {100 * deocclusion['error_weighted_fraction']:.1f}% of the pixels, where the first mesh "
                    f"misses the normals by > {cfg.second_pass_error_floor_deg:g} deg, draw "
                    f"{100 * cfg.second_pass_importance:.0f}% of the rays") if "error_weighted_fraction" in deocclusion else ""
        if "carve_pixels" in deocclusion:
            weighted += (f", with the {int(deocclusion['carve_pixels'])} background pixels of the masks it spans, to "
                         f"carve them")
        if log is not None:
            log(f"second SDF pass on de-occluded normals (mean turn "
                f"{deocclusion['occlusion_correction_mean_deg']:.2f} deg, {deocclusion['seconds']:.1f} s{weighted})")
        first_pass = {"stats": result.stats, "history": result.history, "mesh_faces": int(len(faces))}
        # the same masks and cameras: the first pass's hull and pre-fitted field are the second's start
        second_start = time.perf_counter() - start
        fitted_start = result.start
        result, vertices, faces, mesh_stats = fit(sdf_views, second,
                                                  result.field if cfg.deocclude_iterations > 0 else None,
                                                  start=fitted_start, index=2)
        if cfg.third_pass_iterations > 0:
            tick = time.perf_counter()
            # the decision reads a lattice of every view's pixels: a share of pixels needs no more, and the
            # subjects that need no third pass pay a fraction of a de-occlusion for it
            lattice = on_pixel_lattice(views, DECISION_PIXEL_STEP)
            again, _ = deoccluded_sdf_views(lattice, vertices, faces, cfg.deocclude_directions,
                                            cfg.deocclude_min_visible)
            share = turned_share(on_pixel_lattice(sdf_views, DECISION_PIXEL_STEP), again)
            third_pass = {"turned_share": share, "ran": share > cfg.third_pass_turned_share}
            if third_pass["ran"] and DECISION_PIXEL_STEP > 1:  # every pixel of every view for the pass itself
                again, _ = deoccluded_sdf_views(views, vertices, faces, cfg.deocclude_directions,
                                                cfg.deocclude_min_visible)
            third_pass["deocclusion_seconds"] = time.perf_counter() - tick
            if log is not None:
                log(f"{100 * share:.1f}% of the valid pixels' normals turn by over {_TURN_DEG:g} deg de-occluded "
                    f"against the second mesh: " + (f"a third SDF pass of {cfg.third_pass_iterations} steps"
                                                    if third_pass["ran"] else "no third pass"))
            if third_pass["ran"]:
                third_pass["second_pass"] = {"stats": result.stats, "history": result.history,
                                             "mesh_faces": int(len(faces))}
                third = dataclasses.replace(second, iterations=cfg.third_pass_iterations,
                                            inv_s_start=second.inv_s_end, coarse_to_fine=0.0,
                                            warmup_iterations=min(second.warmup_iterations, cfg.third_pass_iterations))
                reported["total"] += third.iterations
                third_views = [dataclasses.replace(a, sample_weight=b.sample_weight) for a, b in zip(again, sdf_views)]
                result, vertices, faces, mesh_stats = fit(third_views, third, result.field, start=fitted_start,
                                                          index=3)
                passes = 3
    return SDFMesh(result=result, vertices=vertices, faces=faces, mesh_stats=mesh_stats, deocclusion=deocclusion,
                   first_pass=first_pass, passes=passes, train_seconds=time.perf_counter() - start,
                   second_pass_start_s=second_start, subject_pixel_m=pixel_m, third_pass=third_pass)
