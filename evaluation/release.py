"""Accuracy of a release against the simulator's ground truth (``ultrastage evaluate``).

Normal angular error over valid pixels (alpha > 0.5 inside the true mask), over the whole true
foreground, and split by occlusion (ground-truth visibility of the lit hemisphere >= 0.9 is
"unoccluded"); albedo PSNR/SSIM over the true foreground; mask IoU. Pooled over every pixel of every
camera with a fixed-width histogram, so memory does not grow with the release. The mesh is scored against the
simulator's mesh twice (:data:`MESH_METRICS`): plainly over both whole surfaces, and on what the capture can
show (``comparable_*``: truth that a camera sees, away from an open mesh's boundary; see
:mod:`stages.numerics.meshmetrics`), with the shares of area each figure leaves out.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.exr import read_exr
from pipeline.codecs.image import mask_from_png, read_png
from stages.numerics.metrics import angular_error_deg, downsample_to, mask_iou, ssim

UNOCCLUDED_VISIBILITY = 0.9
_BINS = np.linspace(0.0, 180.0, 3601)  # 0.05 degree bins


class _ErrorPool:
    """Mean, median and threshold shares of angular errors (degrees), pooled: the mean and the shares at or under
    5 and 25 degrees counted exactly (the ``<=`` of :func:`stages.numerics.metrics.normal_error_stats` and the
    held-out protocol), the median from a histogram of 0.05 degree bins (the centre of the bin that holds it)."""

    def __init__(self) -> None:
        self.hist = np.zeros(len(_BINS) - 1, np.int64)
        self.total = 0.0
        self.count = 0
        self.under5 = 0
        self.under25 = 0

    def add(self, errors: np.ndarray) -> None:
        """Pool ``errors`` (N,) in [0, 180]."""
        if errors.size:
            self.hist += np.histogram(errors, bins=_BINS)[0]
            self.total += float(errors.sum(dtype=np.float64))
            self.count += int(errors.size)
            self.under5 += int(np.count_nonzero(errors <= 5.0))
            self.under25 += int(np.count_nonzero(errors <= 25.0))

    def merge(self, other: "_ErrorPool") -> None:
        """Pool what ``other`` pooled (as if its errors had been added here)."""
        self.hist += other.hist
        self.total += other.total
        self.count += other.count
        self.under5 += other.under5
        self.under25 += other.under25

    def stats(self) -> dict[str, float]:
        """``mean``, ``median``, ``under5_pct``, ``under25_pct`` and ``count`` of what was pooled; {} when nothing
        was."""
        if self.count == 0:
            return {}
        cdf = np.cumsum(self.hist)
        median_bin = int(np.searchsorted(cdf, self.count / 2))
        return {"mean": self.total / self.count, "median": float((_BINS[median_bin] + _BINS[median_bin + 1]) / 2),
                "under5_pct": 100.0 * self.under5 / self.count, "under25_pct": 100.0 * self.under25 / self.count,
                "count": float(self.count)}


@dataclass
class EvaluationSummary:
    overall: dict[str, float]
    per_action: dict[str, dict[str, float]]
    rows: list[dict[str, Any]] = field(default_factory=list)


def evaluate_camera(normals: np.ndarray, alpha: np.ndarray, albedo: np.ndarray, mask: np.ndarray,
                    truth: dict[str, np.ndarray], diffuse_normals: np.ndarray | None = None,
                    diffuse_albedo: np.ndarray | None = None) -> dict[str, Any]:
    """Errors of one camera's maps against ground truth at the maps' resolution.

    Args:
        normals: (H, W, 3) estimated world normals; alpha: (H, W); albedo: (H, W, 3); mask: (H, W) bool.
        truth: "normal" (H', W', 3), "albedo" (H', W', 3), "mask" (H', W') bool, "visibility" (H', W'),
            at the same or an integer multiple of the maps' resolution.
        diffuse_normals: optional (H, W, 3) second normal map (``normal_diffuse``) scored over the same
            valid pixels (``err_valid_diffuse``).
        diffuse_albedo: optional (H, W, 3) second albedo map (``albedo_diffuse``) scored over the same pixels
            (``albedo_diffuse_sq_sum``).
    Returns:
        error arrays per region and scalar albedo/mask scores.
    """
    shape = normals.shape[:2]
    gt_normal = downsample_to(truth["normal"], shape, kind="normal")
    gt_albedo = downsample_to(truth["albedo"], shape, kind="image")
    gt_mask = downsample_to(truth["mask"], shape, kind="mask")
    gt_vis = downsample_to(truth["visibility"], shape, kind="image")
    err = angular_error_deg(normals, gt_normal)
    valid = gt_mask & (alpha > 0.5)
    unoccluded = gt_vis >= UNOCCLUDED_VISIBILITY
    fg = gt_mask
    sq = ((albedo - gt_albedo) ** 2)[fg]
    extra = {} if diffuse_normals is None else {"err_valid_diffuse": angular_error_deg(diffuse_normals, gt_normal)[valid]}
    if diffuse_albedo is not None:
        extra["albedo_diffuse_sq_sum"] = float(((diffuse_albedo - gt_albedo) ** 2)[fg].sum(dtype=np.float64))
    return extra | {"err_valid": err[valid], "err_all": err[fg], "err_valid_unoccluded": err[valid & unoccluded],
            "err_valid_occluded": err[valid & ~unoccluded], "err_all_unoccluded": err[fg & unoccluded],
            "err_all_occluded": err[fg & ~unoccluded],
            "valid_fraction": float(valid.sum() / max(int(fg.sum()), 1)),
            "albedo_sq_sum": float(sq.sum(dtype=np.float64)), "albedo_sq_count": int(sq.size),
            "albedo_ssim": float(ssim(albedo, gt_albedo, fg)) if fg.any() else float("nan"),
            "mask_iou": float(mask_iou(mask, gt_mask)), "fg_pixels": int(fg.sum())}


def _psnr_from_mse(mse: float, peak: float = 1.0) -> float:
    return float(10.0 * np.log10(peak ** 2 / max(mse, 1e-12)))


def _load_truth(truth_dir: Path, action_id: str, cam: str) -> dict[str, np.ndarray]:
    base = truth_dir / action_id
    return {"normal": read_exr(base / "normal" / f"{cam}.exr"), "albedo": read_exr(base / "albedo" / f"{cam}.exr"),
            "mask": mask_from_png(read_png(base / "mask" / f"{cam}.png")),
            "visibility": read_exr(base / "visibility" / f"{cam}.exr")}


def true_cameras(truth_dir: Path, session_id: str) -> dict[str, dict[str, Any]]:
    """camera_id -> true camera record: ``ground_truth/cameras/<session>.json`` when the capture has it
    (the simulator's true poses, which the rig spec only approximates), else the session's rig spec."""
    import json

    path = Path(truth_dir) / "cameras" / f"{session_id}.json"
    if not path.exists():
        path = Path(truth_dir).parent / "sessions" / session_id / "rig.json"
    return {c["camera_id"]: c for c in json.loads(path.read_text())["cameras"]}


def camera_errors(transforms: dict[str, Any], truth: dict[str, dict[str, Any]]) -> dict[str, float]:
    """Rotation (deg), centre (mm) and focal (%) errors of a release's cameras against true ones, in the
    stage frame as published (no re-alignment: the release claims this frame)."""
    from calibration.geometric import pose_errors

    est = {}
    focal = []
    for frame in transforms["frames"]:
        cam = frame["camera_id"]
        if cam not in truth:
            continue
        est[cam] = np.asarray(frame["cam_from_world_opencv"], float)[:3, :4]
        K_true = np.asarray(truth[cam]["K"], float)
        scale = frame["w"] / float(truth[cam]["width"])  # half-size releases: compare at the truth's size
        focal.append(abs(frame["fl_x"] / scale - K_true[0, 0]) / K_true[0, 0] * 100.0)
    errs = pose_errors(est, {c: np.asarray(t["cam_from_world"], float) for c, t in truth.items()}, align=False)
    return {"cam_rotation_err_deg": float(errs["rotation_deg_mean"]), "cam_center_err_mm": float(errs["centre_error_mm_mean"]),
            "cam_focal_err_pct": float(np.mean(focal)), "cameras_registered": float(len(est))}


def _row(action_id: str, camera_id: str | None, metric: str, region: str | None, value: float, run_id: str,
         environment: str | None = None) -> dict[str, Any]:
    """One row of the metrics manifest measured against ground truth."""
    from manifests.schemas import metric_unit

    return {"action_id": action_id, "camera_id": camera_id, "metric": metric, "region": region,
            "environment": environment, "value": float(value), "unit": metric_unit(metric), "source": "evaluate",
            "run_id": run_id}


def summary_rows(overall: dict[str, float], aggregation: dict[str, str], n_actions: int,
                 run_id: str) -> list[dict[str, Any]]:
    """The metrics_summary rows of the release-wide numbers (``aggregation``: metric -> how it was formed;
    'pooled' when absent)."""
    from manifests.schemas import metric_unit

    return [{"metric": metric, "value": float(value), "unit": metric_unit(metric),
             "aggregation": aggregation.get(metric, "pooled"), "n_actions": int(n_actions), "source": "evaluate",
             "run_id": run_id} for metric, value in sorted(overall.items())]


def evaluate_release(release: Path, truth_dir: Path, run_id: str | None = None,
                     relit_cache: Path | None = None) -> EvaluationSummary:
    """Evaluate every published action: its rows replace every 'evaluate' row of the metrics manifest, the
    release-wide numbers replace the metrics_summary table, and the release's page is written again with
    them. ``run_id``: the run the numbers belong to (default: a new id of this evaluation).
    ``relit_cache``: a folder that keeps the simulator's renders the relit views are compared with
    (:class:`RelitTruthCache`); None renders them every time.

    Runs with one BLAS thread in this process and in its workers (:func:`evaluate_workers`): the products are
    small, and idle BLAS threads spinning beside the other processes cost CPU time the measuring needs."""
    from synthetic.threads import limit_blas_threads

    with limit_blas_threads(1):
        return _evaluate_release(release, truth_dir, run_id, relit_cache)


def _evaluate_release(release: Path, truth_dir: Path, run_id: str | None, relit_cache: Path | None
                      ) -> EvaluationSummary:
    from manifests import open_release
    from pipeline.runner import new_run_id

    run_id = run_id or new_run_id()
    rel = open_release(release)
    actions = rel.actions
    ok_ids = [a for a, s in zip(actions["action_id"], actions["status"]) if s == "ok"]
    cameras = _camera_overall(rel, truth_dir, ok_ids)
    parts = _evaluate_actions(release, truth_dir, ok_ids, run_id, relit_cache)
    maps, diffuse, per_action, rows = _maps_combine(ok_ids, [p.maps for p in parts])
    overall: dict[str, float] = maps | {"actions_ok": float(len(ok_ids)),
                                        "actions_failed": float(len(actions) - len(ok_ids))} | diffuse
    aggregation = {"albedo_ssim": "mean_over_views", "mask_iou": "mean_over_views", "actions_ok": "count",
                   "actions_failed": "count"}
    aggregation |= dict.fromkeys(cameras, "mean_over_sessions")
    overall |= cameras
    means = []
    for name in ("mesh", "heldout", "materials"):
        values, action_values, part_rows = _means_over_actions(ok_ids, [getattr(p, name) for p in parts])
        means.append(values)
        for action_id, action in action_values.items():
            per_action.setdefault(action_id, {}).update(action)
        rows.extend(part_rows)
    relit, relightset, relit_per_action, relit_rows = _relit_parts(ok_ids, [p.relit for p in parts])
    for action_id, values in relit_per_action.items():
        per_action.setdefault(action_id, {}).update(values)
    rows.extend(relit_rows)
    for part in means + [relit, relightset]:
        aggregation |= dict.fromkeys(part, "mean_over_actions")
        overall |= part
    overall = {k: v for k, v in overall.items() if np.isfinite(v)}
    _write_metrics(release, rows, overall, aggregation, len(ok_ids), run_id)
    return EvaluationSummary(overall, per_action, rows)


_ActionPart = tuple[dict[str, float], dict[str, float], list[dict[str, Any]]]
"""One part of one action's evaluation (its mesh, held-out views or textures): ``(what the part's function returns
for the action alone, the action's values it records, its metrics rows)``; the first holds figures averaged over
actions that are not recorded per action (``heldout_albedo_view_dependent``)."""


@dataclass
class _ActionEvaluation:
    """Every figure of one action that :func:`evaluate_release` pools or averages over actions (plain values:
    it comes back from a worker process)."""

    maps: "_MapsAction"
    mesh: _ActionPart
    heldout: _ActionPart
    materials: _ActionPart
    relit: "_RelitAction"


def _evaluate_action(release: Path, truth_dir: Path, action_id: str, run_id: str, relit_cache: Path | None
                     ) -> _ActionEvaluation:
    """The evaluation of one action: its maps, mesh, held-out views, textures, relit views and relighting set.
    Runs in a worker process as well as in this one."""
    from manifests import open_release
    from synthetic.threads import limit_blas_threads

    rel = open_release(release)
    ids = [action_id]

    def part(measure: Callable[[dict[str, dict[str, float]], list[dict[str, Any]]], dict[str, float]]
             ) -> _ActionPart:
        per_action: dict[str, dict[str, float]] = {}
        rows: list[dict[str, Any]] = []
        means = measure(per_action, rows)
        return means, per_action.get(action_id, {}), rows

    textured: dict[str, dict] = {}  # the held-out protocol's textured mesh, for the materials
    with limit_blas_threads(1):  # as in evaluate_release, also when this runs in a worker process
        maps = _maps_action(rel, truth_dir, action_id, run_id)
        mesh = part(lambda pa, rows: _mesh_overall(rel, truth_dir, ids, pa, rows, run_id))
        heldout = part(lambda pa, rows: _heldout_overall(release, rel, truth_dir, ids, pa, rows, run_id, textured))
        materials = part(lambda pa, rows: _materials_overall(rel, truth_dir, ids, pa, rows, run_id, textured))
    relit = _relit_action(release, truth_dir, action_id, run_id, relit_cache)
    return _ActionEvaluation(maps, mesh, heldout, materials, relit)


def _evaluate_actions(release: Path, truth_dir: Path, ok_ids: list[str], run_id: str,
                      relit_cache: Path | None) -> list[_ActionEvaluation]:
    """:func:`_evaluate_action` of every action, in ``ok_ids`` order, on :func:`evaluate_workers` processes: this
    one takes every ``workers``-th action and a pool of ``workers - 1`` spawned processes the others (the
    actions take about the same time, and this process has its imports already)."""
    workers = min(evaluate_workers(), len(ok_ids))
    if workers <= 1:
        return [_evaluate_action(Path(release), Path(truth_dir), action_id, run_id, relit_cache)
                for action_id in ok_ids]
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    pool = ProcessPoolExecutor(workers - 1, mp_context=multiprocessing.get_context("spawn"))
    try:
        futures = {i: pool.submit(_evaluate_action, Path(release), Path(truth_dir), ok_ids[i], run_id, relit_cache)
                   for i in range(len(ok_ids)) if i % workers}
        results = {i: _evaluate_action(Path(release), Path(truth_dir), ok_ids[i], run_id, relit_cache)
                   for i in range(0, len(ok_ids), workers)}
        results |= {i: future.result() for i, future in futures.items()}
    finally:
        pool.shutdown(cancel_futures=True)
    return [results[i] for i in range(len(ok_ids))]


def _write_metrics(release: Path, rows: list[dict[str, Any]], overall: dict[str, float],
                   aggregation: dict[str, str], n_actions: int, run_id: str) -> None:
    """Replace the release's 'evaluate' rows of the metrics manifest and its metrics_summary table, and write
    the release's page again with them."""
    from manifests import write_table
    from manifests.page import write_release_page
    from manifests.writer import replace_rows

    replace_rows(release, "metrics", rows, drop=lambda row: row["source"] == "evaluate")
    write_table(release, "metrics_summary", summary_rows(overall, aggregation, n_actions, run_id))
    write_release_page(release)


_RelitAction = tuple[dict[str, float], list[dict[str, Any]], list[dict[str, Any]]]
"""What :func:`_relit_action` returns for one action."""


_MAP_REGIONS = ("valid", "all", "valid_unoccluded", "valid_occluded", "all_unoccluded", "all_occluded")


@dataclass
class _AlbedoSums:
    """Sums over cameras of :func:`evaluate_camera`'s albedo error and coverage."""

    sq: float = 0.0  # squared albedo error over the true foreground (all channels)
    count: int = 0  # its values
    valid_px: float = 0.0  # valid pixels (valid fraction x foreground pixels)
    fg_px: int = 0  # foreground pixels

    def merge(self, other: "_AlbedoSums") -> None:
        """Add another's sums (another action's cameras)."""
        self.sq += other.sq
        self.count += other.count
        self.valid_px += other.valid_px
        self.fg_px += other.fg_px

    def add(self, res: dict[str, Any]) -> None:
        self.sq += res["albedo_sq_sum"]
        self.count += res["albedo_sq_count"]
        self.valid_px += res["valid_fraction"] * res["fg_pixels"]
        self.fg_px += res["fg_pixels"]


def _camera_results(view: Any, truth_dir: Path, action_id: str):
    """``(camera id, evaluate_camera result)`` of each of the action's cameras that has ground truth, one at a
    time (the maps of one camera in memory)."""
    has_diffuse = "normal_diffuse" in view.kinds
    has_diffuse_albedo = "albedo_diffuse" in view.kinds
    for cam in view.cameras:
        if not (truth_dir / action_id / "normal" / f"{cam}.exr").exists():
            continue
        diffuse = view.normals(cam, diffuse=True) if has_diffuse else None
        diffuse_albedo = view.albedo(cam, diffuse=True) if has_diffuse_albedo else None
        yield cam, evaluate_camera(view.normals(cam), view.normal_alpha(cam), view.albedo(cam), view.mask(cam),
                                   _load_truth(truth_dir, action_id, cam), diffuse_normals=diffuse,
                                   diffuse_albedo=diffuse_albedo)


@dataclass
class _MapsAction:
    """One action's maps against the truth (:func:`_maps_action`), in the form :func:`_maps_combine` pools."""

    pools: dict[str, _ErrorPool]
    """Normal errors of the released maps per region of :data:`_MAP_REGIONS`."""
    diffuse_pool: _ErrorPool
    """Normal errors of the specular-fitted maps (``normal_diffuse``) over the valid pixels."""
    albedo: _AlbedoSums
    ssims: list[float]
    ious: list[float]
    diffuse_sq: float
    """Squared error of ``albedo_diffuse`` (the same pixels as the albedo's) and its value count."""
    diffuse_count: int
    values: dict[str, float]
    """The action's figures (``per_action``)."""
    rows: list[dict[str, Any]]
    """The per-camera metrics rows."""


def _maps_action(rel: Any, truth_dir: Path, action_id: str, run_id: str) -> _MapsAction:
    """Normal, albedo and mask errors of the action's published cameras' maps against the truth."""
    pools = {region: _ErrorPool() for region in _MAP_REGIONS}
    diffuse_pool, action_pool, sums = _ErrorPool(), _ErrorPool(), _AlbedoSums()
    ssims: list[float] = []
    ious: list[float] = []
    rows: list[dict[str, Any]] = []
    dsq, dcount = 0.0, 0
    for cam, res in _camera_results(rel.action(action_id), truth_dir, action_id):
        if "albedo_diffuse_sq_sum" in res:  # the albedo with the fitted specular light out, same pixels
            dsq += res["albedo_diffuse_sq_sum"]
            dcount += res["albedo_sq_count"]
        if "err_valid_diffuse" in res:  # the specular-fitted normals, over the same pixels
            diffuse_pool.add(res["err_valid_diffuse"])
        for region, pool in pools.items():
            pool.add(res[f"err_{region}"])
        action_pool.add(res["err_valid"])
        sums.add(res)
        if np.isfinite(res["albedo_ssim"]):
            ssims.append(res["albedo_ssim"])
        ious.append(res["mask_iou"])
        rows.extend(_camera_rows(action_id, cam, res, run_id))
    st = action_pool.stats()
    values = {"normal_mean_deg": st.get("mean", float("nan")), "normal_under5_pct": st.get("under5_pct", float("nan")),
              "valid_fraction": sums.valid_px / max(sums.fg_px, 1),
              "albedo_psnr_db": _psnr_from_mse(sums.sq / max(sums.count, 1))}
    if dcount:
        values["albedo_psnr_db_diffuse"] = _psnr_from_mse(dsq / dcount)
    return _MapsAction(pools, diffuse_pool, sums, ssims, ious, dsq, dcount, values, rows)


def _maps_combine(ok_ids: list[str], actions: list[_MapsAction]
                  ) -> tuple[dict[str, float], dict[str, float], dict[str, dict[str, float]], list[dict[str, Any]]]:
    """The actions' maps (in ``ok_ids`` order) pooled over every pixel of every camera (the albedo SSIM and mask
    IoU: means over views): ``(release-wide figures of the released maps, those of the specular-fitted ones
    (normal_diffuse, albedo_diffuse), per-action figures, per-camera rows)``."""
    pools = {region: _ErrorPool() for region in _MAP_REGIONS}
    diffuse_pool, total = _ErrorPool(), _AlbedoSums()
    ssims: list[float] = []
    ious: list[float] = []
    rows: list[dict[str, Any]] = []
    per_action: dict[str, dict[str, float]] = {}
    diffuse_sq, diffuse_count = 0.0, 0
    for action_id, action in zip(ok_ids, actions):
        for region, pool in pools.items():
            pool.merge(action.pools[region])
        diffuse_pool.merge(action.diffuse_pool)
        total.merge(action.albedo)
        ssims += action.ssims
        ious += action.ious
        rows += action.rows
        per_action[action_id] = dict(action.values)
        diffuse_sq += action.diffuse_sq
        diffuse_count += action.diffuse_count
    return (_maps_summary(pools, total, ssims, ious), _diffuse_summary(diffuse_pool, diffuse_sq, diffuse_count),
            per_action, rows)


def _means_over_actions(ok_ids: list[str], parts: list[_ActionPart]
                        ) -> tuple[dict[str, float], dict[str, dict[str, float]], list[dict[str, Any]]]:
    """One part of every action (in ``ok_ids`` order) put together as its function gives it over all actions:
    ``(each figure's mean over the actions that have it, per-action figures, rows action by action)``."""
    values: dict[str, list[float]] = {}
    per_action: dict[str, dict[str, float]] = {}
    rows: list[dict[str, Any]] = []
    for action_id, (means, recorded, part_rows) in zip(ok_ids, parts):
        for key, value in means.items():
            values.setdefault(key, []).append(value)
        if recorded:
            per_action[action_id] = recorded
        rows += part_rows
    return {k: float(np.mean(v)) for k, v in values.items() if v}, per_action, rows


def _camera_rows(action_id: str, cam: str, res: dict[str, Any], run_id: str) -> list[dict[str, Any]]:
    """The metrics rows of one camera's :func:`evaluate_camera` result (finite values only)."""
    cam_stats = _ErrorPool()
    cam_stats.add(res["err_valid"])
    s = cam_stats.stats()
    albedo_psnr = _psnr_from_mse(res["albedo_sq_sum"] / max(res["albedo_sq_count"], 1))
    return [_row(action_id, cam, metric, region, value, run_id)
            for metric, value, region in (("normal_mean_deg", s.get("mean"), "valid"),
                                          ("normal_under5_pct", s.get("under5_pct"), "valid"),
                                          ("valid_fraction", res["valid_fraction"], "all"),
                                          ("albedo_psnr_db", albedo_psnr, "all"),
                                          ("albedo_ssim", res["albedo_ssim"], "all"),
                                          ("mask_iou", res["mask_iou"], None))
            if value is not None and np.isfinite(value)]


def _maps_summary(pools: dict[str, _ErrorPool], total: _AlbedoSums, ssims: list[float],
                  ious: list[float]) -> dict[str, float]:
    """The release-wide numbers of the released maps (NaN where nothing was measured)."""
    valid, all_fg = pools["valid"].stats(), pools["all"].stats()
    return {
        "normal_mean_deg": valid.get("mean", float("nan")), "normal_median_deg": valid.get("median", float("nan")),
        "normal_under5_pct": valid.get("under5_pct", float("nan")),
        "normal_under25_pct": valid.get("under25_pct", float("nan")),
        "normal_mean_deg_all": all_fg.get("mean", float("nan")),
        "normal_mean_deg_unoccluded": pools["valid_unoccluded"].stats().get("mean", float("nan")),
        "normal_mean_deg_occluded": pools["valid_occluded"].stats().get("mean", float("nan")),
        "normal_mean_deg_all_unoccluded": pools["all_unoccluded"].stats().get("mean", float("nan")),
        "normal_mean_deg_all_occluded": pools["all_occluded"].stats().get("mean", float("nan")),
        "valid_fraction": total.valid_px / max(total.fg_px, 1),
        "albedo_psnr_db": _psnr_from_mse(total.sq / max(total.count, 1)) if total.count else float("nan"),
        "albedo_ssim": float(np.mean(ssims)) if ssims else float("nan"),
        "mask_iou": float(np.mean(ious)) if ious else float("nan")}


def _diffuse_summary(pool: _ErrorPool, albedo_sq: float, albedo_count: int) -> dict[str, float]:
    """The release-wide numbers of the specular-fitted maps, where the release has them."""
    out: dict[str, float] = {}
    if albedo_count:
        out["albedo_psnr_db_diffuse"] = _psnr_from_mse(albedo_sq / albedo_count)
    diffuse = pool.stats()
    out |= {f"normal_{k}{'_deg' if k in ('mean', 'median') else ''}_diffuse": diffuse[k]
            for k in ("mean", "median", "under5_pct") if k in diffuse}
    return out


def evaluate_workers() -> int:
    """Processes :func:`evaluate_release` measures the actions in, one action at a time (every figure of the
    action, :func:`_evaluate_action`), this one included: ``ULTRASTAGE_EVALUATE_WORKERS`` when set (1: all in
    this process), else 2 where this process may use two CPUs or more, else 1. Never more than the actions."""
    import os

    env = os.environ.get("ULTRASTAGE_EVALUATE_WORKERS")
    if env:
        return max(1, int(env))
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return 2 if cpus >= 2 else 1


RELIGHTSET_METRICS = ("relightset_image_psnr_db", "relightset_normal_mean_deg", "relightset_albedo_psnr_db",
                      "comparable_relightset_image_psnr_db", "composited_relightset_image_psnr_db")
RELIT_METRICS = ("relit_psnr_db", "comparable_relit_psnr_db", "composited_relit_psnr_db", "relit_normal_mean_deg")


def comparable_exclude(true: dict[str, np.ndarray]) -> np.ndarray:
    """(H, W) bool, the pixels of a truth render (:meth:`synthetic.relight.TruthRelighter.render`) left out of
    the comparable relit figures: those where any of the truth's rays meets the back of a face, the inside of an
    open mesh seen through its opening (a neck cut), which the simulator renders black and no watertight
    reconstruction can show. On a closed mesh only the odd pixel whose ray slips between two triangles onto a
    back face (on the accuracy gate's subject the two figures differ by under 0.001 dB)."""
    return np.asarray(true["backface"], np.float32) > 0.0


def _comparable_psnr(pred_rgb: np.ndarray, pred_mask: np.ndarray, true: dict[str, np.ndarray],
                     plain: dict[str, float]) -> float:
    """The relit PSNR of :func:`stages.numerics.metrics.relit_psnr` without :func:`comparable_exclude`'s pixels
    (the plain figure ``plain`` when there are none)."""
    from stages.numerics.metrics import relit_psnr

    exclude = comparable_exclude(true)
    if not exclude.any():
        return float(plain["psnr_db"])
    return float(relit_psnr(pred_rgb, pred_mask, true["radiance"], true["mask"], exclude=exclude)["psnr_db"])


def _relit_action(release: Path, truth_dir: Path, action_id: str, run_id: str, relit_cache: Path | None
                  ) -> tuple[dict[str, float], list[dict[str, Any]], list[dict[str, Any]]]:
    """:func:`_relit_overall` and :func:`_relightset_overall` of one action (they share the simulator's
    relighter, traced once per light count): ``(per-action values, relit rows, relighting-set rows)``. Takes
    and returns plain values, so it runs in a worker process as well as in this one."""
    from manifests import open_release
    from synthetic.threads import limit_blas_threads

    rel = open_release(release)
    per_action: dict[str, dict[str, float]] = {}
    relit_rows: list[dict[str, Any]] = []
    set_rows: list[dict[str, Any]] = []
    relighters: dict[tuple[str, int], Any] = {}
    with limit_blas_threads(1):  # as in evaluate_release, also when this runs in a worker process
        _relit_overall(rel, truth_dir, [action_id], per_action, relit_rows, run_id, relit_cache, relighters)
        _relightset_overall(release, rel, truth_dir, [action_id], per_action, set_rows, run_id, relit_cache,
                            relighters)
    return per_action.get(action_id, {}), relit_rows, set_rows


def _relit_parts(ok_ids: list[str], actions: list[tuple[dict[str, float], list[dict[str, Any]], list[dict[str, Any]]]]
                 ) -> tuple[dict[str, float], dict[str, float], dict[str, dict[str, float]], list[dict[str, Any]]]:
    """The per-action results of :func:`_relit_action` (in ``ok_ids`` order) put together as
    :func:`_relit_overall` and :func:`_relightset_overall` give them over all actions: ``(relit, relightset,
    per_action, rows)``, the means over actions taken in the same order and the rows in the same order (the
    relit views action by action, then the relighting set metric by metric)."""
    per_action = {action_id: values for action_id, (values, _, _) in zip(ok_ids, actions) if values}
    relit: dict[str, float] = {}
    relightset: dict[str, float] = {}
    for metric in RELIT_METRICS:
        values = [v[metric] for v in per_action.values() if metric in v]
        if values:
            relit[metric] = float(np.mean(values))
    for metric in RELIGHTSET_METRICS:
        values = [v[metric] for v in per_action.values() if metric in v]
        if values:
            relightset[metric] = float(np.mean(values))
    rows = [row for _, relit_rows, _ in actions for row in relit_rows]
    rows += [row for metric in RELIGHTSET_METRICS for _, _, set_rows in actions for row in set_rows
             if row["metric"] == metric]
    return relit, relightset, per_action, rows


MESH_METRICS = ("chamfer_mm", "chamfer_pred_to_gt_mm", "chamfer_gt_to_pred_mm", "normal_consistency",
                "fscore_1mm", "fscore_5mm", "mesh_faces",
                "comparable_chamfer_mm", "comparable_chamfer_pred_to_gt_mm", "comparable_chamfer_gt_to_pred_mm",
                "comparable_fscore_1mm", "comparable_fscore_5mm", "comparable_gt_area_fraction",
                "comparable_pred_area_fraction", "gt_unseen_area_fraction", "gt_boundary_area_fraction",
                "pred_far_from_truth_area_fraction", "pred_seen_through_area_fraction")
"""The plain Chamfer / F-score figures over the whole of both meshes, and the ``comparable_*`` ones beside them
over what the capture can show (:mod:`stages.numerics.meshmetrics`: truth seen by at least one of the session's
true cameras and over 1 cm from the truth's open boundary; prediction left out only within 5 mm of truth that is
not comparable, or within an opening's radius of the fan that closes it), with the shares of area each leaves
out, and the share of the prediction off the truth in space a camera sees through."""


def true_mesh_cameras(truth_dir: Path, session_id: str) -> list[Any]:
    """The session's true cameras as :class:`stages.numerics.meshmetrics.MeshCamera` records."""
    from stages.numerics.meshmetrics import MeshCamera

    return [MeshCamera(np.asarray(c["K"], np.float64), np.asarray(c["cam_from_world"], np.float64),
                       int(c["width"]), int(c["height"]))
            for _, c in sorted(true_cameras(truth_dir, session_id).items())]


def _mesh_overall(rel: Any, truth_dir: Path, ok_ids: list[str], per_action: dict[str, dict[str, float]],
                  rows: list[dict[str, Any]], run_id: str) -> dict[str, float]:
    """Mesh accuracy of every published action that has a mesh, against the simulator's mesh (plain and
    comparable figures, :data:`MESH_METRICS`); the per-action values go to ``per_action`` and ``rows``, the
    means over actions are returned."""
    from pipeline.codecs.mesh import read_ply
    from stages.numerics.meshmetrics import mesh_metrics

    values: dict[str, list[float]] = {k: [] for k in MESH_METRICS}
    for action_id in ok_ids:
        view = rel.action(action_id)
        truth_mesh = truth_dir / action_id / "mesh.ply"
        if "mesh" not in view.kinds or not truth_mesh.exists():
            continue
        pred_v, pred_f = read_ply(view.path("mesh"))
        gt_v, gt_f = read_ply(truth_mesh)
        metrics = mesh_metrics(pred_v, pred_f, gt_v, gt_f,
                               cameras=true_mesh_cameras(truth_dir, view.info["session_id"]))
        for key in MESH_METRICS:
            if key not in metrics:  # the comparable figures of a truth no camera sees
                continue
            value = float(metrics[key])
            if not np.isfinite(value):
                continue
            values[key].append(value)
            per_action.setdefault(action_id, {})[key] = value
            rows.append(_row(action_id, None, key, "mesh", value, run_id))
    return {k: float(np.mean(v)) for k, v in values.items() if v}


HELDOUT_METRICS = ("heldout_albedo_psnr_db", "heldout_albedo_ssim", "heldout_albedo_rmse", "heldout_normal_mean_deg",
                   "heldout_normal_under5_pct", "heldout_normal_under25_pct", "heldout_coverage")


def _heldout_overall(release: Path, rel: Any, truth_dir: Path, ok_ids: list[str],
                     per_action: dict[str, dict[str, float]], rows: list[dict[str, Any]], run_id: str,
                     textured: dict[str, dict] | None = None) -> dict[str, float]:
    """The paper's table-1 protocol on every action with a mesh: two held-out cameras' albedo and normal
    maps synthesised from the other cameras, against the held-out photometric maps and (``_truth``)
    against the simulator's maps (:mod:`evaluation.heldout`). ``textured``: receives action id -> the
    ray-casting scene and atlas of the textured mesh where the protocol loaded it (the ``scene_cache`` of
    :func:`texture_in_camera`)."""
    from evaluation.heldout import ActionGBuffers, heldout_metrics

    values: dict[str, list[float]] = {}
    for action_id in ok_ids:
        if "mesh" not in rel.action(action_id).kinds:
            continue
        truth = truth_dir if (truth_dir / action_id).is_dir() else None
        data = ActionGBuffers(release, action_id)
        metrics = heldout_metrics(release, action_id, truth_dir=truth, data=data)
        if textured is not None and "atlas" in data._shared:
            scene, atlas = data._shared["atlas"][:2]
            textured[action_id] = {"scene": scene, "atlas": atlas}
        # 1 where the white-light albedo was predicted per view (evaluation.heldout), 0 where blended as it is
        values.setdefault("heldout_albedo_view_dependent", []).append(
            float(metrics.get("heldout_albedo_model") == "view_dependent"))
        for base in HELDOUT_METRICS:
            for key in (base, f"{base}_truth"):
                value = metrics.get(key)
                if value is None or not np.isfinite(value):
                    continue
                values.setdefault(key, []).append(float(value))
                per_action.setdefault(action_id, {})[key] = float(value)
                rows.append(_row(action_id, None, key, "heldout", value, run_id))
        if "normal_diffuse" in data.view.kinds:  # the same with the specular-fitted maps
            diffuse_albedo = "albedo_diffuse" in data.view.kinds
            metrics = heldout_metrics(release, action_id, truth_dir=truth, data=data.variant(True, diffuse_albedo))
            for base in HELDOUT_METRICS:
                if not (base.startswith("heldout_normal") or (diffuse_albedo and base.startswith("heldout_albedo"))):
                    continue  # the white-light albedo: the same as above
                for key in (base, f"{base}_truth"):
                    value = metrics.get(key)
                    if value is None or not np.isfinite(value):
                        continue
                    name = key.replace(base, f"{base}_diffuse")
                    values.setdefault(name, []).append(float(value))
                    per_action.setdefault(action_id, {})[name] = float(value)
                    rows.append(_row(action_id, None, name, "heldout", value, run_id))
    return {k: float(np.mean(v)) for k, v in values.items() if v}


def texture_in_camera(obj_path: Path, textures: dict[str, np.ndarray], K: np.ndarray, cam_from_world: np.ndarray,
                      height: int, width: int, scene_cache: dict | None = None,
                      where: np.ndarray | None = None) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Textures of the atlas seen by a camera through the textured mesh: name -> (H, W[, C]) and the hit
    mask (H, W). ``where``: (H, W) bool, the only pixels the textures are looked up at (0 elsewhere); None:
    every pixel."""
    from artifacts.facade import load_atlas_mesh
    from stages.numerics.bake import sample_texture
    from stages.numerics.raycast import mesh_scene, render_uvs

    cache = scene_cache if scene_cache is not None else {}
    if "scene" not in cache:
        vertices, faces, atlas = load_atlas_mesh(obj_path)
        cache.update(scene=mesh_scene(vertices, faces), atlas=atlas)
    atlas = cache["atlas"]
    uv, hit = render_uvs(cache["scene"], atlas.faces, atlas.uvs, K, cam_from_world, height, width)
    if where is None:
        out = {name: sample_texture(tex, uv.reshape(-1, 2)).reshape((height, width) + tex.shape[2:])
               for name, tex in textures.items()}
        return out, hit
    pixels = np.asarray(where, bool)
    out = {}
    for name, tex in textures.items():
        out[name] = np.zeros((height, width) + tex.shape[2:], np.float32)
        out[name][pixels] = sample_texture(tex, uv[pixels])
    return out, hit


def _materials_overall(rel: Any, truth_dir: Path, ok_ids: list[str], per_action: dict[str, dict[str, float]],
                       rows: list[dict[str, Any]], run_id: str, textured: dict[str, dict] | None = None
                       ) -> dict[str, float]:
    """Roughness and albedo textures against the simulator's maps, seen through the textured mesh from every
    true camera (pixels where the truth has the subject and the mesh is hit): roughness mean absolute error
    and bias, and the albedo PSNR of the baked (white-light) texture, the de-occluded one and the intrinsic
    one (specular share and occlusion out). ``textured``: action id -> the textured mesh's ray-casting scene
    and atlas where already loaded (:func:`_heldout_overall`)."""
    from pipeline.codecs.exr import read_exr

    values: dict[str, list[float]] = {}
    for action_id in ok_ids:
        view = rel.action(action_id)
        if "texture_roughness" not in view.kinds or not (truth_dir / action_id / "roughness").is_dir():
            continue
        cameras = true_cameras(truth_dir, view.info["session_id"])
        textures = {"roughness": view.texture("roughness"), "albedo": view.texture("albedo")[..., :3]}
        for name in ("albedo_deoccluded", "albedo_intrinsic"):
            if f"texture_{name}" in view.kinds:
                textures[name] = view.texture(name)[..., :3]
        abs_err, signed, sq = [], [], {k: [0.0, 0] for k in textures if k.startswith("albedo")}
        cache: dict = dict((textured or {}).get(action_id, {}))  # the textured mesh the held-out protocol loaded
        for cam_id, cam in sorted(cameras.items()):
            rough_path = truth_dir / action_id / "roughness" / f"{cam_id}.exr"
            if not rough_path.exists():
                continue
            true_rough = read_exr(rough_path)
            true_rough = true_rough[..., 0] if true_rough.ndim == 3 else true_rough
            true_mask = mask_from_png(read_png(truth_dir / action_id / "mask" / f"{cam_id}.png"))
            true_albedo = read_exr(truth_dir / action_id / "albedo" / f"{cam_id}.exr")[..., :3]
            seen, hit = texture_in_camera(view.path("mesh_textured"), textures, np.asarray(cam["K"]),
                                          np.asarray(cam["cam_from_world"])[:3], true_rough.shape[0],
                                          true_rough.shape[1], cache, where=true_mask)
            both = hit & true_mask
            diff = seen["roughness"][both] - true_rough[both]
            abs_err.append(np.abs(diff))
            signed.append(diff)
            for name in sq:
                err = np.clip(seen[name][both], 0, 1) - true_albedo[both]
                sq[name][0] += float(np.sum(err ** 2))
                sq[name][1] += err.size
        if not abs_err:
            continue
        metrics = {"roughness_mae": float(np.mean(np.concatenate(abs_err))),
                   "roughness_bias": float(np.mean(np.concatenate(signed))),
                   "albedo_texture_psnr_db": _psnr_from_mse(sq["albedo"][0] / max(sq["albedo"][1], 1))}
        for name in ("albedo_deoccluded", "albedo_intrinsic"):
            if name in sq:
                metrics[f"{name}_psnr_db"] = _psnr_from_mse(sq[name][0] / max(sq[name][1], 1))
        for key, value in metrics.items():
            values.setdefault(key, []).append(value)
            per_action.setdefault(action_id, {})[key] = value
            rows.append(_row(action_id, None, key, "textures", value, run_id))
    return {k: float(np.mean(v)) for k, v in values.items() if v}


RELIT_CACHE = Path("cache") / "relit_truth"
"""Where in a work folder ``ultrastage run``'s evaluation keeps the simulator's renders (and, beside them,
:func:`truth_visibility_folder`)."""


def relit_truth_lights(cameras: list[dict]) -> int:
    """Directional lights the ground-truth relighting uses for these views: 2048 for images of 256 px and
    more (converged: 2048 vs 4096 lights differ by 45 dB PSNR at 320 x 480, 1024 vs 2048 by 34-36 dB), 512
    for the test suite's tiny captures (their pixels average away what more lights resolve)."""
    largest = max((max(int(c["width"]), int(c["height"])) for c in cameras), default=0)
    return 2048 if largest >= 256 else 512


def simulator_digest(folder: Path) -> str:
    """sha256 hex over the Python files of ``folder`` (the simulator's package): each file's name and its
    :func:`pipeline.hashing.source_digest`, so comments, docstrings and layout do not count, as for a stage's key."""
    import hashlib

    from pipeline.hashing import source_digest

    digest = hashlib.sha256()
    for path in sorted(Path(folder).glob("*.py")):
        digest.update(path.name.encode() + b"\0" + source_digest(path).encode() + b"\0")
    return digest.hexdigest()


class RelitTruthCache:
    """The simulator's renders of one action's true subject (``radiance``, ``mask``) kept on disk, so that
    evaluating a changed release does not render the same reference again (about 100 s of the default
    capture's 146 s evaluation).

    A render's key is the sha256 of a sorted record: the simulator's code (:func:`simulator_digest`), the capture's
    ``capture.json``, the action's ``truth.json`` and true mesh (file digests), the light count, the camera
    (K, pose, size) and the environment map's bytes and shape. Files are written under a temporary name and
    renamed."""

    def __init__(self, folder: Path, truth_dir: Path, action_id: str, lights: int):
        import hashlib

        import synthetic

        def digest(path: Path) -> str:
            return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else "absent"

        truth = Path(truth_dir) / action_id
        self.folder = Path(folder)
        self.record = {"format": 4, "simulator": simulator_digest(Path(synthetic.__file__).parent),
                       "lights": int(lights),
                       "capture": digest(Path(truth_dir).parent / "capture.json"),
                       "truth": digest(truth / "truth.json"), "mesh": digest(truth / "mesh.ply")}

    def key(self, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int, env: np.ndarray) -> str:
        import hashlib
        import json

        env = np.ascontiguousarray(env, np.float32)
        record = self.record | {"K": np.asarray(K, np.float64).round(9).tolist(),
                                "cam_from_world": np.asarray(cam_from_world, np.float64).round(9).tolist(),
                                "size": [int(height), int(width)], "env_shape": list(env.shape),
                                "env": hashlib.sha256(env.tobytes()).hexdigest()}
        return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()

    def load(self, key: str) -> dict[str, np.ndarray] | None:
        import zipfile

        path = self.folder / f"{key[:32]}.npz"
        if not path.exists():
            return None
        try:
            with np.load(path) as data:
                out = {"radiance": data["radiance"], "mask": data["mask"], "normals_world": data["normals_world"],
                       "backface": data["backface"]}
                if "albedo" in data.files:
                    out["albedo"] = data["albedo"]
                return out
        except (OSError, ValueError, KeyError, zipfile.BadZipFile):  # unreadable: render it again
            return None

    def save(self, key: str, render: dict[str, np.ndarray]) -> None:
        import os

        self.folder.mkdir(parents=True, exist_ok=True)
        tmp = self.folder / f".{key[:32]}.{os.getpid()}.tmp.npz"
        extra = {"albedo": np.asarray(render["albedo"], np.float32)} if "albedo" in render else {}
        np.savez_compressed(tmp, radiance=np.asarray(render["radiance"]), mask=np.asarray(render["mask"], bool),
                            normals_world=np.asarray(render["normals_world"], np.float32),
                            backface=np.asarray(render["backface"], np.float32), **extra)
        os.replace(tmp, self.folder / f"{key[:32]}.npz")


def _relit_overall(rel: Any, truth_dir: Path, ok_ids: list[str], per_action: dict[str, dict[str, float]],
                   rows: list[dict[str, Any]], run_id: str, cache_dir: Path | None = None,
                   relighters: dict[tuple[str, int], Any] | None = None) -> dict[str, float]:
    """Relit novel views against the simulator's subject rendered under the same environment from the same
    camera (:class:`synthetic.relight.TruthRelighter`, kept in ``cache_dir`` by :class:`RelitTruthCache`
    when given): PSNR after a common exposure (:func:`stages.numerics.metrics.relit_psnr`), per view and
    environment, averaged; ``comparable_relit_psnr_db``, the same over the pixels where the truth shows no inside
    of an open mesh (:func:`comparable_exclude`; on a closed mesh within a hair of the plain figure);
    ``composited_relit_psnr_db``, the same with both images as they are over black (``relit_psnr``'s
    ``composited``: a silhouette pixel counts with its coverage in both, not as 0 below its mask's threshold); and
    ``relit_normal_mean_deg``, the released shading normals
    (``renders/<view>/normal.exr``) against the true subject's, mean angle over the pixels both masks cover,
    averaged over views."""
    from stages.numerics.metrics import angular_error_deg, relit_psnr
    from stages.environments import find_environment, load_environment

    capture_root = Path(truth_dir).parent
    if not (capture_root / "capture.json").exists():
        return {}

    values: list[float] = []
    comparable_values: list[float] = []
    composited_values: list[float] = []
    normal_values: list[float] = []
    for action_id in ok_ids:
        view = rel.action(action_id)
        if "render_environments" not in view.kinds:
            continue
        envs = view.release.load(view.asset("render_environments", None))["environments"]
        cams = view.render_cameras()
        lights = relit_truth_lights(cams)
        cache = RelitTruthCache(cache_dir, truth_dir, action_id, lights) if cache_dir is not None else None
        truth = None  # built on the first render the cache does not hold
        scores, comparable, composited = [], [], []
        normal_errors: dict[str, float] = {}
        for env_record in envs:
            env, _ = load_environment(env_record["name"], find_environment(env_record["name"], capture_root))
            for cam in cams:
                relit = view.relit(cam["camera_id"], env_record["label"])
                args = (np.asarray(cam["K"]), np.asarray(cam["cam_from_world"]), cam["height"], cam["width"], env)
                key = cache.key(*args) if cache is not None else None
                true = cache.load(key) if cache is not None else None
                if true is None:
                    if truth is None:
                        truth = _relighter(relighters, capture_root, action_id, lights, cache_dir)
                    true = truth.render(*args)
                    if cache is not None:
                        cache.save(key, true)
                rgb, mask = relit[..., :3], relit[..., 3] >= 0.5
                score = relit_psnr(rgb, mask, true["radiance"], true["mask"])
                scores.append(score["psnr_db"])
                comparable.append(_comparable_psnr(rgb, mask, true, score))
                composited.append(float(relit_psnr(rgb, mask, true["radiance"], true["mask"],
                                                   composited=True)["psnr_db"]))
                if cam["camera_id"] not in normal_errors:  # the true normals do not depend on the environment
                    both = mask & np.asarray(true["mask"], bool)
                    if both.any():
                        normal = view.render_gbuffer(cam["camera_id"])["normal"]
                        error = float(angular_error_deg(normal[both], np.asarray(true["normals_world"])[both]).mean())
                        normal_errors[cam["camera_id"]] = error
                        rows.append(_row(action_id, cam["camera_id"], "relit_normal_mean_deg", "all", error,
                                         run_id))
                rows.append(_row(action_id, cam["camera_id"], "relit_psnr_db", "all", score["psnr_db"], run_id,
                                 environment=env_record["label"]))
                rows.append(_row(action_id, cam["camera_id"], "comparable_relit_psnr_db", "all", comparable[-1],
                                 run_id, environment=env_record["label"]))
                rows.append(_row(action_id, cam["camera_id"], "composited_relit_psnr_db", "all", composited[-1],
                                 run_id, environment=env_record["label"]))
        if scores:
            per_action.setdefault(action_id, {})["relit_psnr_db"] = float(np.mean(scores))
            per_action[action_id]["comparable_relit_psnr_db"] = float(np.mean(comparable))
            per_action[action_id]["composited_relit_psnr_db"] = float(np.mean(composited))
            values.append(float(np.mean(scores)))
            comparable_values.append(float(np.mean(comparable)))
            composited_values.append(float(np.mean(composited)))
        if normal_errors:
            per_action.setdefault(action_id, {})["relit_normal_mean_deg"] = float(np.mean(list(normal_errors.values())))
            normal_values.append(float(np.mean(list(normal_errors.values()))))
    out = {"relit_psnr_db": float(np.mean(values)),
           "comparable_relit_psnr_db": float(np.mean(comparable_values)),
           "composited_relit_psnr_db": float(np.mean(composited_values))} if values else {}
    if normal_values:
        out["relit_normal_mean_deg"] = float(np.mean(normal_values))
    return out


def truth_visibility_folder(relit_cache: Path) -> Path:
    """Where the ground-truth relighter keeps its traced visibility beside the renders of ``relit_cache``
    (``ultrastage run`` prefetches it there while the pipeline runs)."""
    return Path(relit_cache).parent / "truth_visibility"


def _comparable_note(overall: dict[str, float], metric: str) -> str:
    """``"; comparable X dB (...)"`` for the summary when the ``comparable_`` figure of ``metric`` differs from it
    (the truth shows the inside of an open mesh), else ``""``."""
    comparable = overall.get(f"comparable_{metric}")
    if comparable is None or abs(comparable - overall[metric]) < 5e-3:
        return ""
    return f"; comparable {comparable:.2f} dB (without the truth's open-mesh insides)"


def _composited_note(overall: dict[str, float], metric: str) -> str:
    """``"; composited X dB (...)"`` for the summary when ``metric`` has a ``composited_`` figure, else ``""``."""
    composited = overall.get(f"composited_{metric}")
    if composited is None:
        return ""
    return f"; composited {composited:.2f} dB (both images over black, no mask threshold)"


def _relighter(relighters: dict[tuple[str, int], Any] | None, capture_root: Path, action_id: str, lights: int,
               relit_cache: Path | None = None) -> Any:
    """The simulator's subject of an action for ground-truth relighting, built once per (action, lights);
    its traced visibility kept beside ``relit_cache`` when given."""
    from synthetic.relight import TruthRelighter

    folder = truth_visibility_folder(relit_cache) if relit_cache is not None else None
    if relighters is None:
        return TruthRelighter(capture_root, action_id, lights=lights, visibility_cache=folder)
    if (action_id, lights) not in relighters:
        relighters[(action_id, lights)] = TruthRelighter(capture_root, action_id, lights=lights,
                                                         visibility_cache=folder)
    return relighters[(action_id, lights)]


def _relightset_overall(release: Path, rel: Any, truth_dir: Path, ok_ids: list[str],
                        per_action: dict[str, dict[str, float]], rows: list[dict[str, Any]], run_id: str,
                        cache_dir: Path | None = None,
                        relighters: dict[tuple[str, int], Any] | None = None) -> dict[str, float]:
    """How faithful the relighting set is: each example against the simulator's subject rendered from the same
    camera under the same rotated map (:class:`synthetic.relight.TruthRelighter`): image PSNR after a common
    exposure (:func:`stages.numerics.metrics.relit_psnr`; ``comparable_*`` without the pixels where the truth
    shows the inside of an open mesh, :func:`comparable_exclude`; ``composited_*`` with both images as they are
    over black, ``relit_psnr``'s ``composited``), camera-frame normals' mean angle and albedo
    PSNR (clipped to [0, 1]) over the pixels both masks cover. Per action and over the set."""
    import json as _json
    import math

    import yaml

    from stages.numerics.metrics import angular_error_deg, relit_psnr
    from stages.numerics.sg import rotate_environment
    from stages.relightset import load_pool_map, resolve_pool

    capture_root = Path(truth_dir).parent
    examples = rel.relight_examples
    if not (capture_root / "capture.json").exists() or examples.empty:
        return {}

    config = yaml.safe_load((release / "config.yaml").read_text()) if (release / "config.yaml").exists() else {}
    entries = tuple((config.get("relightset") or {}).get("environments") or ("hdri-folders",))
    maps, _ = resolve_pool(entries, capture_root)
    environments = {m.name: m for m in maps}
    loaded: dict[str, tuple[np.ndarray, str]] = {}  # each map read and hashed once, whatever its examples
    scores: dict[str, dict[str, list[float]]] = {}
    for action_id in ok_ids:
        chosen = examples[examples["action_id"] == action_id]
        if chosen.empty:
            continue
        lights = relit_truth_lights([{"width": w, "height": h} for w, h in zip(chosen["width"], chosen["height"])])
        cache = RelitTruthCache(cache_dir, truth_dir, action_id, lights) if cache_dir is not None else None
        truth = None
        for _, example in chosen.iterrows():
            pool_map = environments.get(example["environment_name"])
            if pool_map is None:
                continue
            if pool_map.name not in loaded:
                loaded[pool_map.name] = load_pool_map(pool_map, pool_map.path)
            env, sha = loaded[pool_map.name]
            if sha != example["environment_sha256"]:
                continue  # the map changed since the set was rendered: not the same lighting
            env = rotate_environment(env, math.radians(float(example["environment_rotation_deg"])))
            pose = np.asarray(_json.loads(example["cam_from_world_json"]), np.float64)
            K = np.array([[example["fx"], 0, example["cx"]], [0, example["fy"], example["cy"]], [0, 0, 1.0]])
            args = (K, pose, int(example["height"]), int(example["width"]), env)
            key = cache.key(*args) if cache is not None else None
            true = cache.load(key) if cache is not None else None
            if true is None or "albedo" not in true:
                if truth is None:
                    truth = _relighter(relighters, capture_root, action_id, lights, cache_dir)
                true = truth.render(*args)
                if cache is not None:
                    cache.save(key, true)
            maps_ = rel.relight_example(example)
            mask = maps_["mask"]
            true_mask = np.asarray(true["mask"], bool)
            both = mask & true_mask
            action_scores = scores.setdefault(action_id, {"image": [], "normal": [], "albedo": [], "comparable": [],
                                                          "composited": []})
            if not true_mask.any() or not both.any():
                continue
            image_score = relit_psnr(maps_["image"], mask, true["radiance"], true_mask)
            action_scores["image"].append(image_score["psnr_db"])
            action_scores["comparable"].append(_comparable_psnr(maps_["image"], mask, true, image_score))
            action_scores["composited"].append(float(relit_psnr(maps_["image"], mask, true["radiance"], true_mask,
                                                                composited=True)["psnr_db"]))
            true_normals_cam = np.asarray(true["normals_world"], np.float64) @ pose[:, :3].T
            action_scores["normal"].append(float(angular_error_deg(maps_["normal"][both], true_normals_cam[both]).mean()))
            diff = np.clip(maps_["albedo"][both], 0, 1) - np.clip(np.asarray(true["albedo"])[both], 0, 1)
            action_scores["albedo"].append(_psnr_from_mse(float(np.mean(diff ** 2))))
    out: dict[str, float] = {}
    names = dict(zip(("image", "normal", "albedo", "comparable", "composited"), RELIGHTSET_METRICS))
    for kind, metric in names.items():
        values = []
        for action_id, action_scores in scores.items():
            if action_scores[kind]:
                value = float(np.mean(action_scores[kind]))
                values.append(value)
                per_action.setdefault(action_id, {})[metric] = value
                rows.append(_row(action_id, None, metric, "relightset", value, run_id))
        if values:
            out[metric] = float(np.mean(values))
    return out


def _camera_overall(rel: Any, truth_dir: Path, ok_ids: list[str]) -> dict[str, float]:
    """Camera metrics of the release, per session (every action of a session shares its cameras)."""
    import json

    per_session: dict[str, dict[str, float]] = {}
    for action_id in ok_ids:
        session_id = rel.action(action_id).info["session_id"]
        if session_id in per_session:
            continue
        view = rel.action(action_id)
        metrics = camera_errors(view.transforms(), true_cameras(truth_dir, session_id))
        calib = rel.path(f"actions/{action_id}/calibration.json")
        if calib.exists():
            summary = json.loads(calib.read_text())
            if "reprojection_error_px" in summary:  # absent when "auto" fell back to the rig spec
                metrics["reprojection_err_px"] = float(summary["reprojection_error_px"])
        per_session[session_id] = metrics
    if not per_session:
        return {}
    keys = sorted({k for m in per_session.values() for k in m})
    return {k: float(np.mean([m[k] for m in per_session.values() if k in m])) for k in keys}


def evaluate_release_cached(release: Path, truth_dir: Path, work: Path,
                            run_id: str | None = None) -> tuple[EvaluationSummary, bool]:
    """:func:`evaluate_release`, skipped when the published actions and the truth are what was last
    evaluated (the key: every action's published stage keys, and the truth folder's path)."""
    import hashlib
    import json

    published = sorted((work / "published").glob("*.json"))
    # format 2: the metrics layout of manifest schema 2 (metrics_summary); older evaluations are redone
    key = hashlib.sha256(json.dumps({"format": 2, "truth": str(Path(truth_dir).resolve()),
                                     "published": {p.stem: json.loads(p.read_text())["keys"] for p in published}},
                                    sort_keys=True).encode()).hexdigest()
    record = work / "evaluated.json"
    if record.exists():
        saved = json.loads(record.read_text())
        if saved.get("key") == key:
            return EvaluationSummary(saved["overall"], saved["per_action"]), True
    summary = evaluate_release(release, truth_dir, run_id=run_id, relit_cache=work / RELIT_CACHE)
    record.write_text(json.dumps({"key": key, "overall": summary.overall, "per_action": summary.per_action}))
    return summary, False


def print_overall(summary: EvaluationSummary) -> None:
    o = summary.overall
    print("accuracy against ground truth (all published actions):")
    print(f"  normals, valid pixels : mean {o.get('normal_mean_deg', float('nan')):.2f} deg, median "
          f"{o.get('normal_median_deg', float('nan')):.2f} deg, {o.get('normal_under5_pct', float('nan')):.1f}% < 5 deg, "
          f"{o.get('normal_under25_pct', float('nan')):.1f}% < 25 deg; valid fraction {o.get('valid_fraction', float('nan')):.3f}")
    print(f"  normals, unoccluded   : {o.get('normal_mean_deg_unoccluded', float('nan')):.2f} deg (valid), "
          f"occluded {o.get('normal_mean_deg_occluded', float('nan')):.2f} deg (valid)")
    print(f"  normals, all fg       : mean {o.get('normal_mean_deg_all', float('nan')):.2f} deg")
    if "normal_mean_deg_diffuse" in o:
        print(f"  normals, specular out : mean {o['normal_mean_deg_diffuse']:.2f} deg, median "
              f"{o.get('normal_median_deg_diffuse', float('nan')):.2f} deg, "
              f"{o.get('normal_under5_pct_diffuse', float('nan')):.1f}% < 5 deg (normal_diffuse, valid pixels)")
    print(f"  albedo                : PSNR {o.get('albedo_psnr_db', float('nan')):.2f} dB, SSIM "
          f"{o.get('albedo_ssim', float('nan')):.3f}; mask IoU {o.get('mask_iou', float('nan')):.3f}")
    if "albedo_psnr_db_diffuse" in o:
        print(f"  albedo, specular out  : PSNR {o['albedo_psnr_db_diffuse']:.2f} dB (albedo_diffuse)")
    if "cam_rotation_err_deg" in o:
        reprojection = f", reprojection {o['reprojection_err_px']:.3f} px" if "reprojection_err_px" in o else ""
        print(f"  cameras               : rotation {o['cam_rotation_err_deg']:.4f} deg, centre {o['cam_center_err_mm']:.2f} mm, "
              f"focal {o['cam_focal_err_pct']:.3f}%{reprojection}, {o['cameras_registered']:.0f} cameras")
    if "chamfer_mm" in o:
        print(f"  mesh                  : Chamfer {o['chamfer_mm']:.2f} mm (pred->gt {o.get('chamfer_pred_to_gt_mm', float('nan')):.2f}, "
              f"gt->pred {o.get('chamfer_gt_to_pred_mm', float('nan')):.2f}), normal consistency "
              f"{o.get('normal_consistency', float('nan')):.3f}, F-score {100 * o.get('fscore_1mm', float('nan')):.1f}% @1mm "
              f"{100 * o.get('fscore_5mm', float('nan')):.1f}% @5mm, {o.get('mesh_faces', 0):.0f} faces")
    if "comparable_chamfer_mm" in o:
        print(f"  mesh, comparable      : Chamfer {o['comparable_chamfer_mm']:.2f} mm (pred->gt "
              f"{o.get('comparable_chamfer_pred_to_gt_mm', float('nan')):.2f}, gt->pred "
              f"{o.get('comparable_chamfer_gt_to_pred_mm', float('nan')):.2f}), F-score "
              f"{100 * o.get('comparable_fscore_1mm', float('nan')):.1f}% @1mm "
              f"{100 * o.get('comparable_fscore_5mm', float('nan')):.1f}% @5mm on "
              f"{100 * o.get('comparable_gt_area_fraction', float('nan')):.1f}% of the truth "
              f"({100 * o.get('gt_unseen_area_fraction', float('nan')):.1f}% seen by no camera, "
              f"{100 * o.get('gt_boundary_area_fraction', float('nan')):.1f}% near its open boundary) and "
              f"{100 * o.get('comparable_pred_area_fraction', float('nan')):.1f}% of the mesh")
    if "pred_seen_through_area_fraction" in o:
        print(f"  mesh, seen through    : {100 * o['pred_seen_through_area_fraction']:.1f}% of the mesh lies over 5 mm "
              "off the truth where a camera sees through it (surface the capture contradicts)")
    if "heldout_normal_mean_deg" in o:
        model = {1.0: "view-dependent white-light albedo", 0.0: "white-light albedo blended as it is"}.get(
            o.get("heldout_albedo_view_dependent"), "white-light albedo view-dependent for some actions")
        print(f"  held-out views        : albedo {o['heldout_albedo_psnr_db']:.2f} dB, SSIM {o.get('heldout_albedo_ssim', float('nan')):.4f}, "
              f"RMSE {o.get('heldout_albedo_rmse', float('nan')):.3f}; normals {o['heldout_normal_mean_deg']:.2f} deg, "
              f"{o.get('heldout_normal_under5_pct', float('nan')):.1f}% < 5, {o.get('heldout_normal_under25_pct', float('nan')):.1f}% < 25 "
              f"(vs the held-out photometric maps; {model})")
        if "heldout_normal_mean_deg_diffuse" in o:
            print(f"  held-out, specular out: normals {o['heldout_normal_mean_deg_diffuse']:.2f} deg, "
                  f"{o.get('heldout_normal_under5_pct_diffuse', float('nan')):.1f}% < 5, "
                  f"{o.get('heldout_normal_under25_pct_diffuse', float('nan')):.1f}% < 25 (normal_diffuse maps as "
                  "sources and references)")
        if "heldout_albedo_ssim_diffuse" in o:
            print(f"  held-out, albedo_diffuse: {o.get('heldout_albedo_psnr_db_diffuse', float('nan')):.2f} dB, SSIM "
                  f"{o['heldout_albedo_ssim_diffuse']:.3f}; against the simulator's albedo "
                  f"{o.get('heldout_albedo_psnr_db_diffuse_truth', float('nan')):.2f} dB (white-light albedo "
                  f"{o.get('heldout_albedo_psnr_db_truth', float('nan')):.2f} dB)")
    if "roughness_mae" in o:
        print(f"  materials             : roughness MAE {o['roughness_mae']:.3f} (bias {o.get('roughness_bias', float('nan')):+.3f}); "
              f"albedo texture {o.get('albedo_texture_psnr_db', float('nan')):.2f} dB, de-occluded "
              f"{o.get('albedo_deoccluded_psnr_db', float('nan')):.2f} dB, intrinsic (specular and occlusion out) "
              f"{o.get('albedo_intrinsic_psnr_db', float('nan')):.2f} dB (vs the simulator's albedo)")
    if "relit_psnr_db" in o:
        print(f"  relit novel views     : PSNR {o['relit_psnr_db']:.2f} dB against the true subject under the same environments"
              + _comparable_note(o, "relit_psnr_db") + _composited_note(o, "relit_psnr_db"))
    if "relit_normal_mean_deg" in o:
        print(f"  relit shading normals : {o['relit_normal_mean_deg']:.2f} deg mean against the true subject's")
    if "relightset_image_psnr_db" in o:
        print(f"  relighting set        : image PSNR {o['relightset_image_psnr_db']:.2f} dB, normals (camera frame) "
              f"{o.get('relightset_normal_mean_deg', float('nan')):.2f} deg, albedo PSNR "
              f"{o.get('relightset_albedo_psnr_db', float('nan')):.2f} dB against the true subject"
              + _comparable_note(o, "relightset_image_psnr_db")
              + _composited_note(o, "relightset_image_psnr_db"))
    print(f"  actions               : {int(o.get('actions_ok', 0))} ok, {int(o.get('actions_failed', 0))} failed")
