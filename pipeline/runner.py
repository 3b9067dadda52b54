"""One pipeline run: plan, execute, publish complete actions into the release, have them indexed.

This module is the engine's "action" layer (OpenSfM style): it knows the stage contract, the store and
the release layout, but nothing about what the stages compute, nor how the release is indexed: a
:class:`ReleaseCatalog` (the project's: ``manifests.catalog.ManifestCatalog``) makes the asset rows, the
tables and the page.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import secrets
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from pipeline.capture import Capture, open_capture
from pipeline.config import Documented, checked, dump_yaml
from pipeline.graph import DaskExecutor, Plan, SyncExecutor, Task, downstream_of, execute, make_plan
from pipeline.hashing import DigestCache
from pipeline.errors import WriteError
from pipeline.release_txn import ReleaseTransaction, recover
from pipeline.runlock import hold_run_lock
from pipeline.stage import Stage
from pipeline.store import ArtifactStore, link_or_copy

log = logging.getLogger("ultrastage.run")
CONVENTIONS = Path(__file__).with_name("conventions.md")


@dataclass(frozen=True)
class ExecutionConfig(Documented):
    scheduler: str = checked("local", nonempty=True)
    """"local" (a dask.distributed cluster on this machine), "sync" (in this process), or the address
    of an existing dask scheduler (e.g. tcp://10.0.0.5:8786)."""
    workers: int = checked(0, ge=0)
    """Worker processes of the local cluster; 0 = one per CPU core (at most 8)."""
    memory_limit: str = "auto"
    """Memory limit per local worker (dask syntax, e.g. "4GiB")."""
    scopes_in_flight: int = checked(0, ge=0)
    """At most this many actions (or sessions) submitted to the executor and not finished; the next goes in as
    one finishes, so the scheduler holds a few actions' tasks, not the release's. 0 = twice the executor's
    worker threads, at least 4."""

    hash_threads: int = checked(0, ge=0)
    """Threads that hash the raw frames not hashed before (their digests enter the cache keys) while planning;
    0 = one per CPU core of the machine that runs the plan."""

    not_in_key = ("scheduler", "workers", "memory_limit", "scopes_in_flight", "hash_threads")


@dataclass
class RunResult:
    run_id: str
    plan: Plan
    action_status: dict[str, str]
    action_errors: dict[str, str]
    published: list[str]
    seconds: float
    executor: str
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)


def new_run_id() -> str:
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime()) + "-" + secrets.token_hex(3)


def make_executor(cfg: ExecutionConfig) -> Any:
    if cfg.scheduler == "sync":
        return SyncExecutor()
    if cfg.scheduler == "local":
        return DaskExecutor(workers=cfg.workers, memory_limit=cfg.memory_limit)
    return DaskExecutor(address=cfg.scheduler)


def _root_units(entries: list[tuple[Path, str, str]]) -> list[str]:
    """The folders (first two path parts, e.g. ``relight/A0000_00``) that release-root files are published in."""
    return sorted({"/".join(rel.split("/")[:2]) for _, rel, _ in entries})


@dataclass
class PreparedAction:
    """One action's release files staged beside the release by :func:`prepare_action`, ready to be swapped in."""

    action_id: str
    rows: list[dict[str, Any]]
    """Asset rows (path, bytes, sha256), hashed once, in the staging folder."""
    tables: dict[str, list[dict[str, Any]]]
    """Rows its stages add to other manifest tables (``manifest_rows``)."""
    record: dict[str, Any]
    """What ``<work>/published/<id>.json`` says once the release holds it."""
    cached: bool
    """The same stage keys are published already: nothing to swap in."""
    tmp: Path | None = None
    staging: Path | None = None
    old_units: list[str] = field(default_factory=list)


class ReleaseCatalog(Protocol):
    """What indexes a release (the project's is ``manifests.catalog.ManifestCatalog``, Parquet): the engine stages
    and swaps in the files and hands the catalog what to record; it never reads or writes the index itself."""

    def asset_row(self, release: Path, path: Path, kind: str, action_id: str | None = None,
                  camera_id: str | None = None, digest: dict[str, Any] | None = None) -> dict[str, Any]:
        """The index row of one release file (its ``path`` relative to ``release`` under ``"path"``); ``digest``:
        its ``{"bytes", "sha256"}`` when known (None: the catalog hashes the file)."""

    def write_manifests(self, release: Path, capture: Capture, plan: Plan, digests: DigestCache, run_id: str,
                        action_status: dict[str, str], action_errors: dict[str, str],
                        asset_rows: list[dict[str, Any]], places: dict[Path, str],
                        table_rows: dict[str, list[dict[str, Any]]]) -> None:
        """Index this run: its actions (``action_status``, ``action_errors``), their raw frames (``digests``), the
        files published (``asset_rows``), the plan's tasks, and the rows stages add to other tables."""

    def write_page(self, release: Path) -> None:
        """The release's page, from the index just written."""


def prepare_action(release: Path, work: Path, store: ArtifactStore, action_id: str, tasks: list[Task],
                   catalog: ReleaseCatalog) -> PreparedAction:
    """Stage an action's release files: hard-linked (or copied, across file systems) from the store into
    ``release/actions/.tmp-<id>``, and the files its stages publish at the release root (``release_root_files``,
    e.g. ``relight/<example>/``) into ``release/.tmp-root-<id>``, and hash them. Nothing the release shows changes
    yet (:func:`swap_in` does that). An action whose stage keys are published already is not
    staged again (``cached``).

    Raises:
        OSError: the staging could not be written (full disk, read-only folder); what was staged is removed.
    """
    keys = {t.stage.name: t.key for t in tasks}
    record_path = work / "published" / f"{action_id}.json"
    final = release / "actions" / action_id
    old_record = json.loads(record_path.read_text()) if record_path.exists() else {}
    if old_record and final.is_dir() and old_record.get("keys") == keys and \
            all((release / unit).is_dir() for unit in old_record.get("root_units", [])):
        return PreparedAction(action_id, old_record["assets"], old_record.get("tables", {}), old_record, cached=True)
    tmp = release / "actions" / f".tmp-{action_id}"
    staging = release / f".tmp-root-{action_id}"
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(staging, ignore_errors=True)
        tmp.mkdir(parents=True)
        entries, root_entries, tables = [], [], {}
        for task in tasks:
            artifact = store.final_dir(task.stage.name, task.scope_id, task.key)
            success = store.success_record(task.stage.name, task.scope_id, task.key)
            for src, rel, kind, camera in (task.stage.release_files(artifact) if hasattr(task.stage, "release_files")
                                           else []):
                link_or_copy(src, tmp / rel)
                entries.append((rel, kind, camera, store.file_digest(success, artifact, src)))
            if hasattr(task.stage, "release_root_files"):
                root_entries += [(src, rel, kind, store.file_digest(success, artifact, src))
                                 for src, rel, kind in task.stage.release_root_files(artifact)]
            if hasattr(task.stage, "manifest_rows"):
                for table, rows in task.stage.manifest_rows(artifact).items():
                    tables.setdefault(table, []).extend(rows)
        # the digests come from the success records (hashed by the tasks that wrote the files); a file without
        # one (a result committed before the records held digests) is hashed here
        rows = [catalog.asset_row(release, tmp / rel, kind, action_id=action_id, camera_id=camera, digest=digest)
                for rel, kind, camera, digest in entries]
        prefix = f"actions/.tmp-{action_id}/"
        for row in rows:  # rows were made in the temporary folder; record their final paths
            row["path"] = row["path"].replace(prefix, f"actions/{action_id}/", 1)
        for src, rel, kind, digest in root_entries:
            link_or_copy(src, staging / rel)
            row = catalog.asset_row(release, staging / rel, kind, action_id=action_id, digest=digest)
            row["path"] = rel
            rows.append(row)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(staging, ignore_errors=True)
        raise
    record = {"keys": keys, "assets": rows, "root_units": _root_units([e[:3] for e in root_entries]),
              "tables": tables}
    return PreparedAction(action_id, rows, tables, record, cached=False, tmp=tmp, staging=staging,
                          old_units=list(old_record.get("root_units", [])))


def swap_in(prepared: PreparedAction, release: Path, txn: ReleaseTransaction) -> None:
    """Swap a staged action into the release: its folder and each of its root folders whole (renames, under
    ``txn``); root folders it no longer has are taken out."""
    if prepared.cached:
        return
    txn.put_dir(prepared.tmp, release / "actions" / prepared.action_id)
    units = prepared.record["root_units"]
    for unit in units:
        txn.put_dir(prepared.staging / unit, release / unit)
    for unit in sorted(set(prepared.old_units) - set(units)):  # folders the action no longer has
        txn.remove_dir(release / unit)
    shutil.rmtree(prepared.staging, ignore_errors=True)


def unpublish_action(release: Path, work: Path, action_id: str, txn: ReleaseTransaction) -> bool:
    """Take a failed action out of the release (nothing of a failed action may appear there), under ``txn``;
    its ``<work>/published`` record is deleted by the caller once ``txn`` commits."""
    record_path = work / "published" / f"{action_id}.json"
    removed = False
    if record_path.exists():
        try:
            units = json.loads(record_path.read_text()).get("root_units", [])
        except (OSError, json.JSONDecodeError):
            units = []
        for unit in units:
            removed |= txn.remove_dir(release / unit)
    return txn.remove_dir(release / "actions" / action_id) or removed


def check_writable(folder: Path, role: str) -> None:
    """Create ``folder`` (and its parents) if needed and write a file in it, before any work is done.

    Raises:
        WriteError: naming the folder and the reason: a file where a folder should be, a read-only file
            system, no permission, no space.
    """
    folder = Path(folder)
    blocking = next((p for p in [folder, *folder.parents] if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise WriteError(folder, f"cannot create {role}: {blocking} is a file, not a folder")
    probe = folder / f".write-probe-{os.getpid()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise WriteError.from_os_error(folder, exc, f"checking that {role} can be written") from exc


def _write_atomically(path: Path, content: str | bytes) -> None:
    """Write a file by renaming a complete new one over it (a rollback keeps the old one by a hard link)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(content if isinstance(content, bytes) else content.encode())
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if exc.filename is None:  # a failed write() names no file: name the one it was for
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


RELEASE_FILES_REWRITTEN = ("CONVENTIONS.md", "DATASHEET.md", "config.yaml", "run.json", "index.html", "manifests",
                           "page", "relight/splits")
"""What a run rewrites in the release besides the action folders: kept for a rollback by every publication."""


def run_pipeline(capture_dir: Path, release: Path, work: Path, stages: Sequence[Stage], config: Any,
                 execution: ExecutionConfig, only: str | None = None, from_stage: str | None = None,
                 actions: Sequence[str] | None = None, echo: Callable[[str], None] = print,
                 progress: Callable[[Task, dict, int, int], None] | None = None,
                 view_progress: Callable[[Task, dict, int, int], None] | None = None,
                 stage_progress: Callable[[dict], None] | None = None,
                 record: dict[str, Any] | None = None, *, catalog: ReleaseCatalog) -> RunResult:
    """Run the DAG over a capture and publish the release, indexed by ``catalog``. ``config`` is saved beside
    the run.

    The run holds ``<work>/run.lock`` throughout (:mod:`pipeline.runlock`): a second run on the same work
    folder is refused with :class:`pipeline.runlock.RunLockedError` before it reads or writes anything. The
    release gets ``run.json`` (:func:`write_run_record`, with ``record``'s fields, e.g. the preset name), its
    index and its page (:class:`ReleaseCatalog`).
    """
    check_writable(Path(work), "the work folder")
    with hold_run_lock(work, echo=echo):
        start = time.perf_counter()
        capture_dir, release, work = Path(capture_dir).resolve(), Path(release).resolve(), Path(work).resolve()
        capture = open_capture(capture_dir)
        check_writable(release, "the release folder")
        recover(release, echo)  # a publication a killed run left unfinished is rolled back
        store = ArtifactStore(work / "artifacts")
        digests = DigestCache(work / "digests.json")
        run_id = new_run_id()
        echo(f"run {run_id}: capture {capture_dir} -> release {release}")
        plan, executor_name = _plan_and_execute(capture, stages, store, digests, execution, only, from_stage, actions,
                                                echo, progress, view_progress, stage_progress)
        wanted = list(actions) if actions is not None else [a.action_id for a in capture.actions]
        publication = _publish(release, work, capture, plan, digests, wanted, config, run_id, record or {}, catalog,
                               echo)
        (work / "runs" / run_id).mkdir(parents=True, exist_ok=True)
        (work / "runs" / run_id / "config.yaml").write_text(dump_yaml(config))
        return RunResult(run_id, plan, publication.action_status, publication.action_errors, publication.published,
                         time.perf_counter() - start, executor_name)


def _plan_and_execute(capture: Capture, stages: Sequence[Stage], store: ArtifactStore, digests: DigestCache,
                      execution: ExecutionConfig, only: str | None, from_stage: str | None,
                      actions: Sequence[str] | None, echo: Callable[[str], None],
                      progress: Callable[[Task, dict, int, int], None] | None,
                      view_progress: Callable[[Task, dict, int, int], None] | None,
                      stage_progress: Callable[[dict], None] | None) -> tuple[Plan, str]:
    """Plan every task (``--only`` forces one stage, ``--from`` it and everything downstream), run those not
    cached, and give every task its stats (a cached one's from its success record); the plan and the executor's
    name."""
    names = {s.name for s in stages}
    for flag, name in (("--only", only), ("--from", from_stage)):
        if name and name not in names:
            raise ValueError(f"{flag} {name}: no such stage; stages are {sorted(names)}")
    force = {only} if only else (downstream_of(stages, from_stage) if from_stage else set())
    plan = make_plan(capture, stages, store, digests, actions=actions, force=force, echo=echo,
                     hash_threads=execution.hash_threads)
    digests.save()
    executor_name = "none (everything cached)"
    if plan.to_run():
        executor = make_executor(execution)
        executor_name = executor.name
        echo(f"executing {len(plan.to_run())} stage task(s) on {executor_name}")
        try:
            execute(plan, capture, executor, on_done=progress, on_view=view_progress, on_progress=stage_progress,
                    window=execution.scopes_in_flight)
        finally:
            executor.close()
    # every task of the run has ended and the run lock keeps other runs out: a pointer file left half-written is
    # a killed worker's (of this run or an earlier one)
    swept = store.sweep_pointer_temps((task.stage.name, task.scope_id) for task in plan.tasks)
    if swept:
        echo(f"removed {len(swept)} half-written pointer file(s) a killed worker left: "
             + ", ".join(str(p.relative_to(store.root)) for p in swept))
    for task in plan.tasks:  # cached results carry the stats they were committed with
        if task.status == "cached":
            task.stats = store.success_record(task.stage.name, task.scope_id, task.key).get("stats", {})
    return plan, executor_name


@dataclass
class _Publication:
    """What publishing a run decided per action, and what it staged."""

    action_status: dict[str, str] = field(default_factory=dict)
    action_errors: dict[str, str] = field(default_factory=dict)
    published: list[str] = field(default_factory=list)
    prepared: list[PreparedAction] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    """Failed actions: taken out of the release if it holds them."""
    asset_rows: list[dict[str, Any]] = field(default_factory=list)
    table_rows: dict[str, list[dict[str, Any]]] = field(default_factory=dict)


def _stage_actions(release: Path, work: Path, capture: Capture, plan: Plan, wanted: list[str],
                   catalog: ReleaseCatalog, publication: _Publication) -> None:
    """Sort ``wanted`` into published and failed actions, staging each complete one (:func:`prepare_action`)."""
    for action_id in wanted:
        session_id = capture.action(action_id).session_id
        tasks = plan.of_scopes(session_id, action_id)
        bad = [t for t in tasks if t.status not in ("ran", "cached")]
        if bad:
            first = next((t for t in bad if t.status == "failed"), bad[0])
            publication.action_status[action_id] = "failed"
            publication.action_errors[action_id] = f"{first.stage.name}: {first.error}"
            publication.removed.append(action_id)
            continue
        publication.action_status[action_id] = "ok"
        prepared = prepare_action(release, work, plan.store, action_id, tasks, catalog)
        publication.prepared.append(prepared)
        publication.asset_rows += prepared.rows
        for table, rows in prepared.tables.items():
            publication.table_rows.setdefault(table, []).extend(rows)
        publication.published.append(action_id)


def _publish(release: Path, work: Path, capture: Capture, plan: Plan, digests: DigestCache, wanted: list[str],
             config: Any, run_id: str, record: dict[str, Any], catalog: ReleaseCatalog,
             echo: Callable[[str], None]) -> _Publication:
    """Publish the run as one transaction: the action folders are staged beside the release first (where the
    bytes are written), then swapped in, then the documents, index and page are rewritten; any failure rolls all
    of it back, so the release is either this run's or the one before it. ``<work>/published`` follows once the
    release holds this run's actions.

    Raises:
        WriteError: the release could not be written (naming the step); it is left as it was.
    """
    txn = ReleaseTransaction(release)
    had_actions_folder = (release / "actions").is_dir()
    publication = _Publication()
    step = "staging the action files beside the release"
    try:
        _stage_actions(release, work, capture, plan, wanted, catalog, publication)
        step = "swapping the actions in"
        txn.keep_root_listing()
        for name in RELEASE_FILES_REWRITTEN:
            txn.keep_files(release / name)
        for prep in publication.prepared:
            swap_in(prep, release, txn)
        unpublished = [a for a in publication.removed if unpublish_action(release, work, a, txn)]
        step = "writing the documents"
        _write_release_docs(release, config, capture)
        write_run_record(release, run_id, capture.root, work, record)
        step = "writing the manifests"
        places = {capture.root: "<capture>", work: "<work>", release: "<release>"}
        catalog.write_manifests(release, capture, plan, digests, run_id, publication.action_status,
                                {a: portable_message(e, places) for a, e in publication.action_errors.items()},
                                publication.asset_rows, places, publication.table_rows)
        step = "writing the release page"
        catalog.write_page(release)
    except BaseException as exc:
        for prep in publication.prepared:
            for folder in (prep.tmp, prep.staging):
                if folder is not None:
                    shutil.rmtree(folder, ignore_errors=True)
        txn.rollback()
        if not had_actions_folder:
            with contextlib.suppress(OSError):
                (release / "actions").rmdir()  # made for the staging folders, empty again
        if isinstance(exc, OSError):
            raise WriteError.from_os_error(release, exc, f"publishing the release ({step}); it is left as it was "
                                                         "before this run") from exc
        raise
    txn.commit()
    for prep in publication.prepared:
        echo(f"{'release':<12} {prep.action_id:<8} " + ("cached  same stage keys already published" if prep.cached
                                                          else f"written {len(prep.rows)} files"))
    for action_id in unpublished:
        echo(f"{'release':<12} {action_id:<8} removed (action failed)")
    for action_id in publication.removed:
        (work / "published" / f"{action_id}.json").unlink(missing_ok=True)
    for prep in publication.prepared:
        if not prep.cached:
            record_path = work / "published" / f"{prep.action_id}.json"
            record_path.parent.mkdir(parents=True, exist_ok=True)
            _write_atomically(record_path, json.dumps(prep.record))
    return publication


RUN_RECORD = "run.json"


def write_run_record(release: Path, run_id: str, capture: Path, work: Path, extra: dict[str, Any]) -> Path:
    """``RELEASE/run.json``: the run id and the capture and work folders as paths relative to the release (no
    absolute path of this machine goes into a release), plus ``extra`` (e.g. ``{"preset": "default"}``)."""
    path = release / RUN_RECORD
    _write_atomically(path, json.dumps({"run_id": run_id, "capture": os.path.relpath(capture, release),
                                        "work": os.path.relpath(work, release), **extra}, indent=1) + "\n")
    return path


def read_run_record(release: Path) -> dict[str, Any]:
    """``RELEASE/run.json`` with ``capture`` and ``work`` as absolute paths (resolved against the release;
    records of older runs hold absolute paths already).

    Raises:
        FileNotFoundError: no run.json (naming it). ValueError: it is not a JSON object with those keys.
    """
    path = Path(release) / RUN_RECORD
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no run record: this folder was not written by `ultrastage run`")
    try:
        info = json.loads(path.read_text())
        for key in ("capture", "work"):
            info[key] = os.path.normpath(Path(release).resolve() / info[key])
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a run record ({exc!r})") from None
    return info


def portable_message(text: str | None, places: dict[Path, str]) -> str | None:
    """``text`` with the absolute folders of this machine named by their role instead (``{capture_dir:
    "<capture>"}``): messages that go into a release name files relative to the capture, work or release
    folder. The longest folder is replaced first, so a folder inside another keeps its own name."""
    if text is None:
        return None
    for folder, name in sorted(places.items(), key=lambda kv: -len(str(kv[0]))):
        for spelling in {str(folder), os.path.realpath(folder)}:
            text = text.replace(spelling.rstrip("/") + "/", name + "/").replace(spelling, name)
    return text


def _materials_f0(config: Any) -> str:
    """The F0 the release's roughness was fitted with, as the datasheet states it (``?`` for a config without a
    materials stage)."""
    f0 = getattr(getattr(config, "materials", None), "f0", None)
    return f"{f0:g}" if isinstance(f0, (int, float)) else "?"


def _write_release_docs(release: Path, config: Any, capture: Capture) -> None:
    _write_atomically(release / "CONVENTIONS.md", CONVENTIONS.read_bytes())
    _write_atomically(release / "config.yaml", dump_yaml(config))
    sim = capture.meta.get("simulator")
    lines = ["# Datasheet", "",
             f"- Capture: `{capture.root.name}` ({len(capture.actions)} actions, "
             f"{len(capture.sessions)} session(s), {len(next(iter(capture.sessions.values())).camera_ids)} cameras).",
             f"- Origin: {capture.meta.get('origin') or ('synthetic, rendered by the UltraStage simulator' if sim else 'light-stage capture')}.",
             "- Contents: decoded linear images (full_on, pos, neg), world-space normals with validity alpha, "
             "albedo from the white image (albedo and normal_diffuse denoised edge-preservingly; albedo_diffuse "
             "with the fitted specular light taken out), foreground masks, "
             "cameras (transforms.json); per action, when the "
             "neural stages ran, a mesh, a UV atlas with albedo/normal/roughness/occlusion textures and relit "
             "novel views (renders/).",
             "- Known biases: photometric normals are biased where the lit hemisphere is occluded (armpits, "
             "between limbs) and by specular reflection (normal_alpha, eq. 1, is left as measured; "
             "normal_diffuse has the specular reflection fitted out, with the roughness of the materials stage "
             "and an assumed F0, and the mesh's occlusion of the LED sphere divided out, and is closer to the "
             "surface, but it leaves small per-material biases that would inflate the mesh by millimetres, so the "
             "mesh is fitted to normal_alpha, the second of its two SDF passes with the first mesh's occlusion "
             "divided out; where the mesh is wrong, so is that correction); the mesh fuses fingers that lie on "
             "the body into a mitten (on the default capture their gaps are 1-3 pixels wide and the SDF does not "
             "carve them; held-out and relit views show skin there); the mesh closes the opening of a loose "
             "garment (a skirt's hem) with a cap, as nothing in the images carves the space inside it (on the "
             "simulator's skirt a tenth of the mesh's area, about 3 cm from any true surface); the mesh keeps "
             "only the smooth part of "
             "detail a few pixels across, such as cloth folds (on the default capture's 3-5 mm folds seen at 5 mm "
             "a pixel its trunk lies a median 0.4-0.5 mm outside the truth, 0.15 mm without the folds, which are "
             "a quarter of its Chamfer); the white-light albedo still contains ambient occlusion "
             "(textures/albedo_deoccluded.exr divides the mesh's occlusion out, partly: the mesh smooths "
             "creases); albedo holds the white light's specular reflection (6-10% head-on, more at grazing "
             "views on the simulator; albedo_diffuse takes the fitted one out); roughness assumes Fresnel F0 = "
             f"{_materials_f0(config)} everywhere (skin's; cloth's is nearer 0.04); relit views have no "
             "interreflections; see metrics.parquet.",
             "- Manifests: manifests/*.parquet; load with `manifests.open_release(path)`.", ""]
    defaults = capture.meta.get("defaults")  # what the capture's layout lacks and what stands in for it
    if isinstance(defaults, dict) and defaults:
        lines[-1:-1] = ["- Estimated or assumed, not measured (the capture's layout lacks it): "
                        + "; ".join(f"{key}: {text}" for key, text in defaults.items()) + "."]
    _write_atomically(release / "DATASHEET.md", "\n".join(lines))
