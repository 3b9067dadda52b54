"""The release's manifests for a run of the engine: the catalog :func:`pipeline.runner.run_pipeline` publishes
through (:class:`pipeline.runner.ReleaseCatalog`).

The engine knows nothing of Parquet: it stages and swaps in the release's files and asks its catalog for an asset
row per file, then for the run's tables and the release page. This catalog writes the actions, frames, assets,
stage_runs and metrics tables, the tables stages add rows to (e.g. relight_examples), the relighting set's split
lists and ``index.html`` (:mod:`manifests.page`).
"""
from __future__ import annotations

import datetime
import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

from manifests import page
from manifests.schemas import SPLITS, metric_unit
from manifests.writer import (append_rows, asset_row, concat_validated, manifest_path, read_manifest, replace_rows,
                              validate_rows, write_table_keeping)
from pipeline.capture import Capture
from pipeline.graph import Plan
from pipeline.hashing import DigestCache
from pipeline.runner import RUN_RECORD, portable_message


class ManifestCatalog:
    """:class:`pipeline.runner.ReleaseCatalog` over the release's Parquet manifests."""

    def asset_row(self, release: Path, path: Path, kind: str, action_id: str | None = None,
                  camera_id: str | None = None, digest: dict[str, Any] | None = None) -> dict[str, Any]:
        """:func:`manifests.writer.asset_row`."""
        return asset_row(release, path, kind, action_id=action_id, camera_id=camera_id, digest=digest)

    def write_manifests(self, release: Path, capture: Capture, plan: Plan, digests: DigestCache, run_id: str,
                        action_status: dict[str, str], action_errors: dict[str, str],
                        asset_rows: list[dict[str, Any]], places: dict[Path, str],
                        table_rows: dict[str, list[dict[str, Any]]]) -> None:
        """:func:`write_run_manifests`."""
        write_run_manifests(release, capture, plan, digests, run_id, action_status, action_errors, asset_rows,
                            places, table_rows)

    def write_page(self, release: Path) -> None:
        """``index.html`` and its thumbnails (:func:`manifests.page.write_release_page`)."""
        page.write_release_page(release)


def _utc(epoch: float | None) -> datetime.datetime | None:
    return None if epoch is None else datetime.datetime.fromtimestamp(epoch, datetime.timezone.utc)


def write_run_manifests(release: Path, capture: Capture, plan: Plan, digests: DigestCache, run_id: str,
                     action_status: dict[str, str],
                     action_errors: dict[str, str], asset_rows: list[dict[str, Any]],
                     places: dict[Path, str],
                     table_rows: dict[str, list[dict[str, Any]]] | None = None) -> None:
    """The actions, frames, assets, stage_runs and metrics tables of this run, and the tables stages add rows to
    (``table_rows``, e.g. relight_examples). ``action_errors`` are portable already; the frames' and stages'
    errors are made so with ``places`` (:func:`portable_message`)."""
    action_rows, frame_tables, metric_tables = [], [], []
    for action_id, status in action_status.items():  # made into Arrow one action at a time: never all as dicts
        action_rows.append(_action_row(capture, plan, action_id, status, action_errors.get(action_id)))
        frame_tables.append(validate_rows("frames", _frame_rows(capture, plan, digests, action_id, status,
                                                                action_errors.get(action_id, ""), places)))
        metric_tables.append(validate_rows("metrics", _stage_metric_rows(capture, plan, action_id, run_id)))
    for name in ("CONVENTIONS.md", "DATASHEET.md", "config.yaml", RUN_RECORD):
        asset_rows.append(asset_row(release, release / name, "document"))
    # A run over some actions (--actions) leaves the other published actions' rows in place.
    keep = [a.action_id for a in capture.actions
            if a.action_id not in action_status and (release / "actions" / a.action_id).is_dir()]
    table_rows = dict(table_rows or {})
    if manifest_path(release, "relight_examples").exists():  # rewritten even when no action added rows
        table_rows.setdefault("relight_examples", [])
    for table, rows in sorted(table_rows.items()):
        write_table_keeping(release, table, rows, keep)
    asset_rows += write_split_lists(release)
    write_table_keeping(release, "actions", action_rows, keep)
    write_table_keeping(release, "frames", concat_validated("frames", frame_tables), keep)
    write_table_keeping(release, "assets", asset_rows, keep)
    append_rows(release, "stage_runs", _stage_run_rows(plan, run_id, places), ["run_id", "stage", "scope_id"])
    # This run's actions get their stage statistics anew; a failed action keeps no numbers at all (its
    # accuracy rows described files that are gone); evaluate owns the other rows of the published ones.
    replace_rows(release, "metrics", concat_validated("metrics", metric_tables),
                 drop=lambda row: row["action_id"] in action_status and (
                     row["source"] != "evaluate" or action_status[row["action_id"]] != "ok"))


def _action_row(capture: Capture, plan: Plan, action_id: str, status: str, error: str | None) -> dict[str, Any]:
    """The action's row of the actions table: its session, subject, status, camera count, decoded image size
    (the rig's when nothing was decoded) and its tasks' counts and seconds."""
    info = capture.action(action_id)
    cams = capture.sessions[info.session_id].rig["cameras"]
    tasks = plan.of_scopes(action_id)
    decode = next((t for t in tasks if t.stage.name == "decode"), None)
    views = (decode.stats.get("views", {}) if decode else {}) or {}
    first_view = next(iter(views.values()), {})
    return {"action_id": action_id, "session_id": info.session_id, "subject": info.subject, "status": status,
            "error": error, "n_cameras": len(cams),
            "width": int(first_view.get("width", cams[0]["width"])),
            "height": int(first_view.get("height", cams[0]["height"])),
            "stages_run": sum(t.status == "ran" for t in tasks), "stages_cached": sum(t.status == "cached" for t in tasks),
            "seconds": float(sum(t.seconds for t in tasks))}


def _frame_rows(capture: Capture, plan: Plan, digests: DigestCache, action_id: str, status: str, error: str,
                places: dict[Path, str]) -> list[dict[str, Any]]:
    """The action's rows of the frames table, one per camera and illumination: the raw file's path, size and
    digest, and whether the frame was missing, failed the action (its file named in ``error``), was left out by
    a stage (a camera it could not use) or is ok."""
    info = capture.action(action_id)
    cams = capture.sessions[info.session_id].rig["cameras"]
    missing_views: dict[str, str] = {}
    for task in plan.of_scopes(info.session_id, action_id):
        missing_views |= task.stats.get("missing_views", {}) or {}
    rows = []
    for illum in capture.illuminations:
        paths = capture.raw_paths(action_id, illum, [cam["camera_id"] for cam in cams])  # one folder listing
        for cam in cams:
            path = paths[cam["camera_id"]]
            row = {"action_id": action_id, "camera_id": cam["camera_id"], "illumination": illum,
                   "raw_path": None, "raw_bytes": None, "raw_sha256": None,
                   "exposure_s": cam.get("exposure_s"), "width": cam["width"], "height": cam["height"],
                   "status": "missing", "error": f"no raw file for camera {cam['camera_id']} under '{illum}'"}
            if path is not None:
                d = digests.digest(path)
                failed_here = status == "failed" and portable_message(str(path), places) in error
                left_out = missing_views.get(cam["camera_id"])
                row |= {"raw_path": path.relative_to(capture.root).as_posix(), "raw_bytes": d["bytes"],
                        "raw_sha256": d["sha256"], "status": "failed" if failed_here or left_out else "ok",
                        "error": error if failed_here else (portable_message(f"camera {cam['camera_id']}: {left_out}", places) if left_out else None)}
            rows.append(row)
    return rows


def _stage_metric_rows(capture: Capture, plan: Plan, action_id: str, run_id: str) -> list[dict[str, Any]]:
    """The action's metrics rows from its stages' statistics: a count per calibration frame a session stage left
    out (its stats' ``calibration_left_out``), and each per-camera stage's finite per-view numbers, named after
    the stage (its 'valid_fraction' is not evaluate's: one name, one quantity)."""
    rows = []
    for task in plan.of_scopes(capture.action(action_id).session_id):
        for cam in sorted(task.stats.get("calibration_left_out", {}) or {}):
            rows.append({"action_id": action_id, "camera_id": cam,
                         "metric": f"{task.stage.name}_calibration_frame_left_out", "region": None,
                         "environment": None, "value": 1.0, "unit": "count", "source": task.stage.name,
                         "run_id": run_id})
    for task in plan.of_scopes(action_id):
        if not task.stage.per_view:  # only per-camera stages report per-view stats under "views"
            continue
        for cam, stats in (task.stats.get("views", {}) or {}).items():
            for metric, value in (stats or {}).items():
                if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
                    rows.append({"action_id": action_id, "camera_id": cam, "metric": f"{task.stage.name}_{metric}",
                                 "region": None, "environment": None, "value": float(value),
                                 "unit": metric_unit(metric), "source": task.stage.name, "run_id": run_id})
    return rows


def _stage_run_rows(plan: Plan, run_id: str, places: dict[Path, str]) -> list[dict[str, Any]]:
    """One stage_runs row per task of the plan (a blocked task is 'skipped')."""
    config_json: dict[str, str] = {}  # one string per stage, not per task (its tasks share the config record)
    return [{"run_id": run_id, "stage": t.stage.name, "version": t.stage.version, "scope": t.stage.scope,
             "scope_id": t.scope_id, "cache_key": t.key, "status": t.status if t.status != "blocked" else "skipped",
             "seconds": float(t.seconds), "error": portable_message(t.error, places),
             "started_at": _utc(t.started_at),
             "config_json": config_json.get(t.stage.name) or config_json.setdefault(
                 t.stage.name, json.dumps(t.record["config"], sort_keys=True))}
            for t in plan.tasks]


def write_split_lists(release: Path) -> list[dict[str, Any]]:
    """``relight/splits/<split>.txt``: the relighting set's example ids per split, one a line (for the codes that
    read list files), rewritten from the whole relight_examples table; their asset rows."""
    table = read_manifest(release, "relight_examples")
    folder = release / "relight" / "splits"
    if table is None or table.num_rows == 0:
        shutil.rmtree(folder, ignore_errors=True)
        return []
    ids, splits = table.column("example_id").to_pylist(), table.column("split").to_pylist()
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for split in SPLITS:
        path = folder / f"{split}.txt"
        chosen = sorted(i for i, s in zip(ids, splits) if s == split)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text("".join(f"{i}\n" for i in chosen))
        os.replace(tmp, path)
        rows.append(asset_row(release, path, "relight_split"))
    return rows
