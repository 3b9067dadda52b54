"""Planning and executing the stage graph.

Planning computes every task's cache key from an explicit record (stage, version, the digests of the
stage's code, scope, the config fields that change output, upstream keys, raw-input digests). A task whose
key is already committed in the store is resolved while planning and never reaches the scheduler; each
decision is logged as one line with its reason. Execution submits the remaining tasks to an executor (in-process, or
dask.distributed), one task per (stage, scope) or per (stage, action, camera) for per-view stages, a few
scopes at a time (a window: the scheduler holds a few actions' tasks, not the release's).

A task never raises into the scheduler: it returns a result record, and a failed upstream turns its
downstream tasks into "skipped", so one bad action never stops the others. A skipped task names the stage
that failed (``failed_stage``), once, however many stages lie between; the failure itself is that
stage's error. Failures are recorded in the store, so the next plan says "failed last run: REASON; will
retry" for a task whose key failed last time.
"""
from __future__ import annotations

import collections
import logging
import os
import secrets
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.capture import Capture
from pipeline.config import key_fields
from pipeline.errors import InputError
from pipeline.hashing import DigestCache, code_digests, file_sha256, record_key
from pipeline.stage import PROGRESS_TOPIC, Stage, StageContext, set_local_progress
from pipeline.store import ArtifactStore, short

log = logging.getLogger("ultrastage.plan")


@dataclass
class Task:
    """One (stage, scope) of the plan."""

    stage: Stage
    scope_id: str
    session_id: str
    action_id: str | None
    key: str
    record: dict[str, Any]
    status: str
    """"cached", "run", or "failed" (bad input found while planning) / "blocked" (upstream failed)."""
    reason: str
    upstream: dict[str, "Task"]
    raw_paths: dict[str, str]
    """The raw input files by name, as strings: a release-size plan holds some 200,000 of them, and a Path object
    costs about three times its string (314 against 95 bytes for a frame's path; :attr:`raw_inputs` makes the
    Paths)."""
    views: list[str] = field(default_factory=list)
    error: str | None = None
    seconds: float = 0.0
    stats: dict[str, Any] = field(default_factory=dict)
    started_at: float | None = None
    """Epoch seconds when its first piece of work started (None: cached, failed at plan, skipped)."""
    failed_stage: str | None = None
    """For a blocked or skipped task: the upstream stage whose failure stopped it (None otherwise)."""
    retrying: str | None = None
    """For a task planned to run: the stage (itself or upstream) whose last run failed and is retried."""

    @property
    def name(self) -> str:
        return f"{self.stage.name} {self.scope_id}"

    @property
    def raw_inputs(self) -> dict[str, Path]:
        """The raw input files by name (what ``Stage.raw_inputs`` gave)."""
        return {name: Path(path) for name, path in self.raw_paths.items()}


@dataclass
class Plan:
    tasks: list[Task]
    store: ArtifactStore

    def for_scope(self, scope_id: str) -> list[Task]:
        return self.of_scopes(scope_id)

    def of_scopes(self, *scope_ids: str) -> list[Task]:
        """The tasks of these scopes (e.g. an action and its session), in plan order, from an index by scope
        built once: a release-size run asks once per action, and a scan of every task each time is quadratic."""
        index = self.__dict__.get("_by_scope")
        if index is None or index[0] != len(self.tasks):
            groups: dict[str, list[tuple[int, Task]]] = {}
            for position, task in enumerate(self.tasks):
                groups.setdefault(task.scope_id, []).append((position, task))
            index = self.__dict__["_by_scope"] = (len(self.tasks), groups)
        found = [pt for scope in dict.fromkeys(scope_ids) for pt in index[1].get(scope, [])]
        if len(scope_ids) > 1:
            found.sort(key=lambda pt: pt[0])
        return [task for _, task in found]

    def to_run(self) -> list[Task]:
        return [t for t in self.tasks if t.status == "run"]


def topo_order(stages: Sequence[Stage]) -> list[Stage]:
    """Stages ordered so that every stage comes after what it requires; unknown requirements are errors."""
    by_name = {s.name: s for s in stages}
    ordered: list[Stage] = []
    state: dict[str, int] = {}

    def visit(name: str, chain: tuple[str, ...]) -> None:
        if name not in by_name:
            raise ValueError(f"stage {chain[-1]} requires unknown stage {name}")
        if state.get(name) == 2:
            return
        if state.get(name) == 1:
            raise ValueError(f"stage cycle: {' -> '.join(chain + (name,))}")
        state[name] = 1
        for req in by_name[name].requires:
            visit(req, chain + (name,))
        state[name] = 2
        ordered.append(by_name[name])

    for s in stages:
        visit(s.name, ())
    return ordered


def downstream_of(stages: Sequence[Stage], name: str) -> set[str]:
    """``name`` and every stage that depends on it, directly or not."""
    out = {name}
    changed = True
    while changed:
        changed = False
        for s in stages:
            if s.name not in out and any(r in out for r in s.requires):
                out.add(s.name)
                changed = True
    return out


def _changed_leaves(old: Any, new: Any, prefix: str = "") -> list[tuple[str, Any, Any]]:
    """(dotted path, old value, new value) for every leaf that differs between two nested dicts."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new)):
            out += _changed_leaves(old.get(k), new.get(k), f"{prefix}.{k}" if prefix else str(k))
        return out
    return [] if old == new else [(prefix, old, new)]


def _why(record: dict[str, Any], previous: dict[str, Any] | None) -> str:
    """Human reason for a rerun: which part of the record changed since the last committed run."""
    if previous is None:
        return "no earlier result"
    old = previous.get("record", {})
    changes = []
    if old.get("version") != record.get("version"):
        changes.append(f"version {old.get('version')} -> {record.get('version')}")
    if "code" not in old:
        changes.append("the earlier key had no code digest")
    else:
        code_old, code_new = old["code"], record["code"]
        changed_code = [m for m in sorted(set(code_old) | set(code_new)) if code_old.get(m) != code_new.get(m)]
        if changed_code:
            more = f" and {len(changed_code) - 3} more module(s)" if len(changed_code) > 3 else ""
            changes.append(f"code of {', '.join(changed_code[:3])}{more} changed")
    changes += [f"config.{path} {a!r} -> {b!r}" for path, a, b in _changed_leaves(old.get("config", {}), record["config"])]
    for k in sorted(set(old.get("upstream", {})) | set(record["upstream"])):
        if old.get("upstream", {}).get(k) != record["upstream"].get(k):
            changes.append(f"upstream {k} changed")
    inputs_old, inputs_new = old.get("inputs", {}), record["inputs"]
    changed_inputs = [k for k in sorted(set(inputs_old) | set(inputs_new)) if inputs_old.get(k) != inputs_new.get(k)]
    if changed_inputs:
        changes.append(f"{len(changed_inputs)} raw input(s) changed (e.g. {changed_inputs[0]})")
    if not changes:
        return "result missing from store"
    return "; ".join(changes[:4])


def make_plan(capture: Capture, stages: Sequence[Stage], store: ArtifactStore, digests: DigestCache,
              actions: Iterable[str] | None = None, force: set[str] | None = None,
              echo: Callable[[str], None] | None = None, hash_threads: int = 0) -> Plan:
    """Resolve every (stage, scope) task: its key, and whether it is cached, to run, or failed.

    The raw inputs of every task are listed first and the ones whose digest is not known yet hashed together,
    ``hash_threads`` files at a time (:meth:`DigestCache.digest_all`; 0 = one per CPU core), before any key is
    computed."""
    ordered = topo_order(stages)
    wanted = list(actions) if actions is not None else [a.action_id for a in capture.actions]
    unknown = [a for a in wanted if a not in {x.action_id for x in capture.actions}]
    if unknown:
        raise InputError(capture.root / "capture.json", f"unknown action(s) {unknown}")
    emit = echo or (lambda line: log.info(line))
    for stage in ordered:
        stage.preflight(capture, emit)
    scopes = _scopes(capture, ordered, wanted)
    raw_of = _raw_inputs(capture, scopes)
    digests.digest_all((path for raw in raw_of.values() if isinstance(raw, dict) for path in raw.values()),
                       threads=hash_threads)
    planner = _Planner(capture, ordered, store, digests, force or set(), raw_of)
    tasks = []
    for stage, scope_id, session_id, action_id in scopes:
        task = planner.plan(stage, scope_id, session_id, action_id)
        emit(f"{stage.name:<12} {scope_id:<8} {task.status:<7} {task.reason}")
        tasks.append(task)
    return Plan(tasks, store)


def _scopes(capture: Capture, ordered: Sequence[Stage], wanted: Sequence[str]) -> list[tuple[Stage, str, str, str | None]]:
    """``(stage, scope_id, session_id, action_id)`` of every task, in plan order: the session stages of every
    session the wanted actions belong to, then each action's stages."""
    sessions_needed = sorted({capture.action(a).session_id for a in wanted})
    scopes = [(stage, session_id, session_id, None) for session_id in sessions_needed
              for stage in ordered if stage.scope == "session"]
    return scopes + [(stage, action_id, capture.action(action_id).session_id, action_id) for action_id in wanted
                     for stage in ordered if stage.scope == "action"]


def _raw_inputs(capture: Capture, scopes: Sequence[tuple[Stage, str, str, str | None]]
                ) -> dict[tuple[str, str], dict[str, str] | str]:
    """(stage, scope_id) -> the task's raw inputs as strings (the Paths made by ``raw_inputs`` are let go scope by
    scope), or why they cannot be had."""
    raw_of: dict[tuple[str, str], dict[str, str] | str] = {}
    for stage, scope_id, _, _ in scopes:
        try:
            raw_of[(stage.name, scope_id)] = {name: os.fspath(path)
                                              for name, path in stage.raw_inputs(capture, scope_id).items()}
        except InputError as exc:
            raw_of[(stage.name, scope_id)] = str(exc)
        except FileNotFoundError as exc:
            raw_of[(stage.name, scope_id)] = f"{exc.filename}: file disappeared while planning"
    return raw_of


class _Planner:
    """Plans one task at a time, in an order where each task's upstream tasks come first."""

    def __init__(self, capture: Capture, ordered: Sequence[Stage], store: ArtifactStore, digests: DigestCache,
                 force: set[str], raw_of: dict[tuple[str, str], dict[str, str] | str]):
        self.capture, self.store, self.digests, self.force, self.raw_of = capture, store, digests, force, raw_of
        self.by_name = {s.name: s for s in ordered}
        self.stage_config = {stage.name: key_fields(stage.config) for stage in ordered}  # one record per stage
        self.stage_code: dict[str, dict[str, str]] = {}
        for stage in ordered:
            try:
                self.stage_code[stage.name] = code_digests(stage.code_module, stage.code_packages)
            except ValueError as exc:
                raise ValueError(f"stage {stage.name}: {exc}") from exc
        self.index: dict[tuple[str, str], Task] = {}
        self.session_views: dict[str, list[str]] = {}

    def plan(self, stage: Stage, scope_id: str, session_id: str, action_id: str | None) -> Task:
        upstream = {req: self.index[(req, session_id if self.by_name[req].scope == "session" else scope_id)]
                    for req in stage.requires}
        raw, inputs, error = self._inputs(stage, scope_id)
        views = self.session_views.setdefault(session_id, list(self.capture.sessions[session_id].camera_ids))
        record = {"stage": stage.name, "version": stage.version, "code": self.stage_code[stage.name],
                  "scope": scope_id, "config": self.stage_config[stage.name],
                  "upstream": {n: t.key for n, t in sorted(upstream.items())}, "inputs": inputs}
        key = record_key(record)
        status, reason, error, failed_stage, retrying = self._decide(stage, scope_id, key, record, upstream, error)
        task = Task(stage, scope_id, session_id, action_id, key, record, status, reason, upstream, raw,
                    views=views, error=error, failed_stage=failed_stage, retrying=retrying)
        self.index[(stage.name, scope_id)] = task
        return task

    def _inputs(self, stage: Stage, scope_id: str) -> tuple[dict[str, str], dict[str, str], str | None]:
        """The task's raw input paths, their digests by name, and why they cannot be had (or None)."""
        raw = self.raw_of.pop((stage.name, scope_id))
        if isinstance(raw, str):
            return {}, {}, raw
        inputs: dict[str, str] = {}
        try:
            for name, path in sorted(raw.items()):
                inputs[name] = self.digests.digest(path)["sha256"]
        except FileNotFoundError as exc:
            return raw, inputs, f"{exc.filename}: file disappeared while planning"
        return raw, inputs, None

    def _decide(self, stage: Stage, scope_id: str, key: str, record: dict[str, Any], upstream: dict[str, Task],
                error: str | None) -> tuple[str, str, str | None, str | None, str | None]:
        """``(status, reason, error, failed_stage, retrying)`` of a task: failed (its inputs), blocked (an upstream
        task failed), run (forced, failed last time, or changed: the reason says what) or cached."""
        bad_up = [t for t in upstream.values() if t.status in ("failed", "blocked")]
        failed_stage = last_error = None
        if error:
            return "failed", error, error, None, None
        if bad_up:
            failed_stage = bad_up[0].failed_stage or bad_up[0].stage.name  # the root, not the chain
            return "blocked", f"upstream {failed_stage} failed", f"not run: upstream {failed_stage} failed", \
                failed_stage, None
        if stage.name in self.force:
            status, reason = "run", "forced by --only/--from"
        elif self.store.is_complete(stage.name, scope_id, key):
            return "cached", f"key {short(key)} already in store", None, None, None
        elif (last_error := self.store.last_failure(stage.name, scope_id, key)) is not None:
            status, reason = "run", f"failed last run: {last_error}; will retry"
        else:
            status, reason = "run", _why(record, self.store.latest_record(stage.name, scope_id))
        retrying = None
        retried_up = next((t.retrying for t in upstream.values() if t.retrying), None)
        if last_error is not None and stage.name not in self.force:
            retrying = stage.name
        elif retried_up and reason in ("no earlier result", "result missing from store"):
            retrying = retried_up  # it never ran because that upstream stage failed
            reason = f"upstream {retried_up} failed last run; runs after its retry"
        return status, reason, None, None, retrying


# --- execution -------------------------------------------------------------------------------------

def _context(task: Task, store: ArtifactStore, capture: Capture) -> StageContext:
    upstream_dirs = {n: store.final_dir(n, t.scope_id, t.key) for n, t in task.upstream.items()}
    this = store.final_dir(task.stage.name, task.scope_id, task.key)
    previous = [d for d in store.committed_dirs(task.stage.name, task.scope_id) if d != this]
    return StageContext(stage=task.stage.name, scope_id=task.scope_id, session_id=task.session_id,
                        action_id=task.action_id, out_dir=store.tmp_dir(task.stage.name, task.scope_id, task.key),
                        upstream=upstream_dirs, raw_inputs=task.raw_inputs,
                        rig=capture.sessions[task.session_id].rig, capture_root=capture.root, views=list(task.views),
                        subject=capture.action(task.action_id).subject if task.action_id else None,
                        upstream_keys={n: t.key for n, t in sorted(task.upstream.items())},
                        previous=previous, cache_dir=store.root.parent / "cache")


def _failure(exc: BaseException) -> str:
    if isinstance(exc, InputError):
        return str(exc)
    tb = traceback.extract_tb(exc.__traceback__)
    where = f" at {Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else ""
    return f"{type(exc).__name__}: {exc}{where}"


def _upstream_failed(results: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """The "skipped" record of a task one of whose upstream results failed: it names the stage that
    failed first (a skipped upstream passes its own ``failed_stage`` on), not a chain of "not run"s."""
    for res in results:
        if not res.get("ok"):
            failed_stage = res.get("failed_stage") or res.get("stage", "?")
            return {"ok": False, "skipped": True, "failed_stage": failed_stage,
                    "error": f"not run: upstream {failed_stage} failed", "seconds": 0.0}
    return None


def run_view_task(stage: Stage, ctx: StageContext, store: ArtifactStore, key: str, attempt: str, view: str,
                  *upstream: dict[str, Any]) -> dict[str, Any]:
    """One camera of a per-view stage (runs on a worker)."""
    if store.committed_by(ctx.stage, ctx.scope_id, key, attempt) is not None:
        # recomputed after its worker died, but the stage is committed already: nothing to write
        return {"ok": True, "view": view, "stats": {}, "seconds": 0.0, "recomputed": True}
    skipped = _upstream_failed(upstream)
    if skipped:
        return skipped
    start, started_at = time.perf_counter(), time.time()
    try:
        stats = stage.run_view(ctx, view)
        return {"ok": True, "view": view, "stats": stats, "seconds": time.perf_counter() - start,
                "started_at": started_at}
    except Exception as exc:  # noqa: BLE001 - every failure becomes a record naming the file and reason
        return {"ok": False, "stage": stage.name, "view": view, "error": _failure(exc),
                "seconds": time.perf_counter() - start, "started_at": started_at, "traceback": traceback.format_exc()}


def published_digests(stage: Stage, folder: Path) -> dict[str, dict[str, Any]]:
    """Path in ``folder`` -> ``{"bytes", "sha256", "mtime_ns"}`` of each file the stage publishes from it
    (``release_files``, ``release_root_files``): hashed by the task that wrote them, on its worker, so that
    publishing reads the digests from the success record instead of re-reading every file in the driver."""
    listed = [src for src, *_ in (stage.release_files(folder) if hasattr(stage, "release_files") else [])]
    listed += [src for src, *_ in (stage.release_root_files(folder) if hasattr(stage, "release_root_files") else [])]
    files: dict[str, dict[str, Any]] = {}
    for src in listed:
        src = Path(src)
        rel = src.relative_to(folder).as_posix()
        if rel in files or not src.is_file():
            continue  # a file the stage did not write is reported when it is published
        stat = src.stat()
        files[rel] = {"bytes": stat.st_size, "sha256": file_sha256(src), "mtime_ns": stat.st_mtime_ns}
    return files


def finish_task(stage: Stage, ctx: StageContext, store: ArtifactStore, key: str, record: dict[str, Any],
                attempt: str, *parts: dict[str, Any]) -> dict[str, Any]:
    """Finalize a per-view stage, or run a whole-scope stage, then commit its folder (runs on a worker).

    ``attempt`` names this execution of the plan. dask runs a task again when the worker that ran it died:
    before it finished (the task starts over: a whole-scope stage in a fresh folder, a camera rewrites its
    files) or after (its result was lost with the worker's memory). In the second case the folder is committed
    already, by this execution, and the task returns that commit's record instead of redoing it (a second
    finalize would write into a folder that is gone, or commit only the recomputed cameras' files).
    """
    done = store.committed_by(ctx.stage, ctx.scope_id, key, attempt)
    if done is not None:
        store.note_committed(ctx.stage, ctx.scope_id, key, record)  # in case the worker died inside commit
        return {"ok": True, "stats": done.get("stats", {}), "seconds": float(done.get("seconds", 0.0)),
                "started_at": done.get("started_at"), "recomputed": True}
    if not stage.per_view:  # its parts are upstream results: a failure there means "not run"
        skipped = _upstream_failed(parts)
        if skipped:
            store.discard(ctx.stage, ctx.scope_id, key)
            return skipped
        store.begin(ctx.stage, ctx.scope_id, key)  # a fresh folder: an attempt on a lost worker may have left files
    start = time.perf_counter()
    view_seconds = sum(p.get("seconds", 0.0) for p in parts if "view" in p)
    started_at = min([p["started_at"] for p in parts if "view" in p and "started_at" in p] + [time.time()])
    try:
        failed = [p for p in parts if not p.get("ok")]
        if failed:
            store.discard(ctx.stage, ctx.scope_id, key)
            first = failed[0]
            return {"ok": False, "stage": stage.name, "skipped": bool(first.get("skipped")),
                    "failed_stage": first.get("failed_stage"), "error": first.get("error"),
                    "traceback": first.get("traceback"), "seconds": view_seconds,
                    "started_at": None if first.get("skipped") else started_at}
        if stage.per_view:
            stats = stage.finalize(ctx, {p["view"]: p["stats"] for p in parts})
        else:
            stats = stage.run(ctx)
        files = published_digests(stage, ctx.out_dir)
        seconds = view_seconds + time.perf_counter() - start
        store.commit(ctx.stage, ctx.scope_id, key, record, stats, seconds, attempt=attempt, started_at=started_at,
                     files=files)
        return {"ok": True, "stats": stats, "seconds": seconds, "started_at": started_at}
    except Exception as exc:  # noqa: BLE001
        store.discard(ctx.stage, ctx.scope_id, key)
        return {"ok": False, "stage": stage.name, "error": _failure(exc), "traceback": traceback.format_exc(),
                "seconds": view_seconds + time.perf_counter() - start, "started_at": started_at}


class SyncExecutor:
    """Runs tasks in this process, in submission order (for tests, debugging and tiny runs)."""

    name = "sync"

    def submit(self, fn: Callable[..., Any], *args: Any, key: str, resources: dict | None = None) -> Any:
        return fn(*args)

    def subscribe_progress(self, callback: Callable[[dict[str, Any]], None] | None) -> None:
        set_local_progress(callback)

    slots = 1
    """Tasks it runs at once."""

    def as_completed(self, handles: list[Any]) -> Iterable[tuple[Any, Any]]:
        for handle in handles:
            yield handle, handle

    def completions(self, handles: Iterable[Any] = ()) -> "_InOrder":
        """(handle, result) of each handle as it completes, including handles ``add``-ed while iterating."""
        return _InOrder(handles)

    def close(self) -> None:
        set_local_progress(None)


class _InOrder:
    """The in-process executor's completions: its handles are its results, yielded in the order added."""

    def __init__(self, handles: Iterable[Any]):
        self._queue = collections.deque(handles)

    def add(self, handle: Any) -> None:
        self._queue.append(handle)

    def __iter__(self) -> Iterable[tuple[Any, Any]]:
        while self._queue:
            handle = self._queue.popleft()
            yield handle, handle


class DaskExecutor:
    """dask.distributed: a local cluster sized to the machine, or an existing scheduler by address."""

    def __init__(self, address: str | None = None, workers: int = 0, threads_per_worker: int = 1,
                 memory_limit: str = "auto"):
        import os

        import dask
        from distributed import Client, LocalCluster

        # The scheduler of a local cluster lives in this process; its INFO chatter is not progress.
        for name in ("distributed", "distributed.scheduler", "distributed.nanny", "distributed.core",
                     "distributed.worker", "distributed.http.proxy"):
            logging.getLogger(name).setLevel(logging.ERROR)
        if address:
            self.client = Client(address)
            self.cluster = None
            self.name = f"dask scheduler at {address}"
        else:
            n_workers = workers or max(1, min(os.cpu_count() or 1, 8))
            # Worker processes inherit this: numeric kernels split the cores instead of each taking all.
            per_worker = str(max(1, (os.cpu_count() or 1) // n_workers))
            for var in ("ULTRASTAGE_NUMERIC_THREADS", "OMP_NUM_THREADS"):
                os.environ.setdefault(var, per_worker)
            # dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 in its workers so that freed memory goes back to the
            # OS at once; every training step then faults its tensors' pages in again, and the SDF ran 2.1x
            # slower in a worker than in a plain process (bench/bench_executor.py). Workers
            # keep glibc's own threshold instead (or the one this process's environment sets).
            with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
                self.cluster = LocalCluster(n_workers=n_workers, threads_per_worker=threads_per_worker,
                                            processes=True, memory_limit=memory_limit, dashboard_address=None,
                                            silence_logs=logging.ERROR)
            self.client = Client(self.cluster)
            self.name = f"local dask cluster, {n_workers} worker process(es)"
        info = self.client.scheduler_info()
        self._resources = set()
        for worker in info.get("workers", {}).values():
            self._resources |= set(worker.get("resources", {}))
        self.slots = max(1, sum(int(w.get("nthreads", 1)) for w in info.get("workers", {}).values()))
        """Tasks the cluster runs at once (its workers' threads when it started)."""

    def submit(self, fn: Callable[..., Any], *args: Any, key: str, resources: dict | None = None) -> Any:
        # Only annotate resources the cluster has: a GPU stage on a CPU-only cluster still runs.
        usable = {k: v for k, v in (resources or {}).items() if k in self._resources} or None
        return self.client.submit(fn, *args, key=key, pure=False, resources=usable)

    def subscribe_progress(self, callback: Callable[[dict[str, Any]], None] | None) -> None:
        if callback is not None:
            self.client.subscribe_topic(PROGRESS_TOPIC, lambda event: callback(event[1]))

    def as_completed(self, handles: list[Any]) -> Iterable[tuple[Any, Any]]:
        """(future, result) as each finishes. A task that raised in dask itself (our tasks never raise) gives a
        failure record instead: ``KilledWorker`` when workers died running it more often than the scheduler's
        ``allowed-failures``, or the error of an upstream task that did; the run goes on and records it."""
        from distributed import as_completed

        for future in as_completed(handles):
            yield future, _dask_result(future)

    def completions(self, handles: Iterable[Any] = ()) -> "_DaskCompletions":
        """(future, result) of each future as it completes, including futures ``add``-ed while iterating."""
        return _DaskCompletions(handles)

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


class _DaskCompletions:
    def __init__(self, futures: Iterable[Any]):
        from distributed import as_completed

        self._futures = as_completed(list(futures))

    def add(self, future: Any) -> None:
        self._futures.add(future)

    def __iter__(self) -> Iterable[tuple[Any, Any]]:
        for future in self._futures:
            yield future, _dask_result(future)


def _dask_result(future: Any) -> dict[str, Any]:
    """A finished future's result; a task that raised in dask itself (our tasks never raise) gives a failure
    record instead: ``KilledWorker`` when workers died running it more often than the scheduler's
    ``allowed-failures``, or the error of an upstream task that did; the run goes on and records it."""
    try:
        return future.result()
    except Exception as exc:  # noqa: BLE001
        return {"ok": False, "error": f"{type(exc).__name__}: {exc}", "executor_error": True}


def default_window(executor: Any) -> int:
    """Scopes in flight when the configuration does not say: twice the tasks the executor runs at once, at
    least 4 (each action in flight has a runnable task most of the time, and per-camera stages have 32)."""
    return max(4, 2 * int(getattr(executor, "slots", 1) or 1))


def _outcome(result: dict[str, Any]) -> dict[str, Any]:
    """What a downstream task needs of a finished upstream result (:func:`_upstream_failed`): passed instead of
    the finished task's handle, so the executor can let go of it."""
    return {k: result[k] for k in ("ok", "stage", "skipped", "failed_stage", "error") if k in result}


def execute(plan: Plan, capture: Capture, executor: Any,
            on_done: Callable[[Task, dict[str, Any], int, int], None] | None = None,
            on_view: Callable[[Task, dict[str, Any], int, int], None] | None = None,
            on_progress: Callable[[dict[str, Any]], None] | None = None, window: int = 0) -> None:
    """Run every task the plan marked "run"; fill in each task's status, seconds, stats and error.

    ``on_done(task, result, done, total)`` is called as each (stage, scope) completes and
    ``on_view(task, result, done, total)`` as each camera of a per-view stage does (progress display);
    ``on_progress(record)`` receives what long tasks report through ``StageContext.progress``.

    Tasks are submitted a scope (a session, an action) at a time, in plan order, with at most ``window``
    scopes submitted and not finished (0: :func:`default_window`); the next scope goes in as one finishes. A
    finished task's handle is let go: downstream tasks submitted later get its outcome instead, so the
    executor holds the tasks of a few scopes, never the whole release's graph. An executor without
    ``completions`` gets every task at once.
    """
    if on_progress is not None and hasattr(executor, "subscribe_progress"):
        executor.subscribe_progress(on_progress)
    run = _Execution(plan, capture, executor, on_view is not None)
    dynamic = hasattr(executor, "completions")
    limit = (window if window > 0 else default_window(executor)) if dynamic else max(1, len(run.pending))
    run.fill(limit)
    done = views_done = 0
    for handle, result in run.completed():
        if id(handle) in run.view_owner:
            _, task = run.view_owner.pop(id(handle))
            views_done += 1
            on_view(task, result, views_done, run.total_views)
            continue
        task = run.finished(handle, result)
        done += 1
        if on_done:
            on_done(task, result, done, run.total)
        run.scope_left[task.scope_id] -= 1
        if run.scope_left[task.scope_id] == 0:  # a scope finished: the next one goes in
            run.in_flight -= 1
            run.fill(limit)
    run.classify_lost()


class _Execution:
    """The state of one :func:`execute`: the scopes still to submit, the handles in flight and the outcomes of
    the finished tasks (what downstream tasks submitted later get instead of a handle)."""

    def __init__(self, plan: Plan, capture: Capture, executor: Any, watch_views: bool):
        self.plan, self.capture, self.executor, self.store = plan, capture, executor, plan.store
        self.attempt = secrets.token_hex(8)  # this execution; a task recomputed after its worker died checks it
        todo = plan.to_run()
        self.total = len(todo)
        scopes: dict[str, list[Task]] = {}
        for task in todo:
            scopes.setdefault(task.scope_id, []).append(task)
        self.pending = collections.deque(scopes.values())
        # A task's context (and its view list) is made when its scope is submitted, not for the whole plan here:
        # the driver holds a window of contexts, and lists a task's earlier results only when it runs.
        self.views: dict[int, list[str]] = {}
        for task in todo:
            if task.stage.per_view and type(task.stage).views is not Stage.views:  # a stage that picks its views
                self.views[id(task)] = task.stage.views(_context(task, self.store, capture))
        self.total_views = sum(len(self.views[id(t)]) if id(t) in self.views else len(t.views)
                               for t in todo if t.stage.per_view)
        self.watch_views = watch_views
        self.handles: dict[tuple[str, str], Any] = {}  # submitted, not finished
        self.outcomes: dict[tuple[str, str], dict[str, Any]] = {}  # finished
        self.owner: dict[int, tuple[Any, Task]] = {}  # the handle is held with its task, so its id stays its own
        self.view_owner: dict[int, tuple[Any, Task]] = {}
        self.scope_left: dict[str, int] = {}
        self.in_flight = 0
        self.lost: list[Task] = []
        self._watched: list[Any] = []
        self._completions = executor.completions() if hasattr(executor, "completions") else None

    def fill(self, limit: int) -> None:
        """Submit pending scopes until ``limit`` are in flight."""
        while self.pending and self.in_flight < limit:
            self._submit_scope(self.pending.popleft())
            self.in_flight += 1

    def completed(self) -> Iterable[tuple[Any, dict[str, Any]]]:
        """(handle, result) of each watched handle as it finishes, including those submitted meanwhile."""
        if self._completions is not None:
            return self._completions
        return self.executor.as_completed(self._watched)

    def _watch(self, handle: Any) -> None:
        if self._completions is not None:
            self._completions.add(handle)
        else:
            self._watched.append(handle)

    def _submit_scope(self, tasks: list[Task]) -> None:
        self.scope_left[tasks[0].scope_id] = len(tasks)
        for task in tasks:
            ctx = _context(task, self.store, self.capture)
            ups = []
            for n, t in task.upstream.items():
                if (n, t.scope_id) in self.handles:
                    ups.append(self.handles[(n, t.scope_id)])
                elif (n, t.scope_id) in self.outcomes:
                    ups.append(self.outcomes[(n, t.scope_id)])
            self.store.begin(task.stage.name, task.scope_id, task.key)
            tag = f"{task.stage.name}-{task.scope_id}-{short(task.key)}"
            res = task.stage.resources
            if task.stage.per_view:
                views = self.views.pop(id(task)) if id(task) in self.views else task.stage.views(ctx)
                parts = [self.executor.submit(run_view_task, task.stage, ctx, self.store, task.key, self.attempt, v,
                                              *ups, key=f"{tag}-{v}", resources=res)
                         for v in views]
                if self.watch_views:
                    for p in parts:
                        self.view_owner[id(p)] = (p, task)
                        self._watch(p)
            else:
                parts = list(ups)
            handle = self.executor.submit(finish_task, task.stage, ctx, self.store, task.key, task.record,
                                          self.attempt, *parts, key=f"{tag}-commit")
            self.handles[(task.stage.name, task.scope_id)] = handle
            self.owner[id(handle)] = (handle, task)
            self._watch(handle)

    def finished(self, handle: Any, result: dict[str, Any]) -> Task:
        """Record a (stage, scope) task's result in its task and the store; its outcome replaces its handle."""
        _, task = self.owner.pop(id(handle))
        task.seconds = float(result.get("seconds", 0.0))
        task.started_at = result.get("started_at")
        if result.get("ok"):
            task.status, task.stats = "ran", result.get("stats", {})
        else:
            task.status = "skipped" if result.get("skipped") else "failed"
            task.error = result.get("error")
            if result.get("executor_error"):
                self.lost.append(task)  # classified by classify_lost, once every upstream task's outcome is known
            elif task.status == "skipped":
                task.failed_stage = result.get("failed_stage")
            else:
                self.store.record_failure(task.stage.name, task.scope_id, task.key, task.error or "unknown error")
                if result.get("traceback"):
                    log.debug("%s failed:\n%s", task.name, result["traceback"])
        self.handles.pop((task.stage.name, task.scope_id), None)
        self.outcomes[(task.stage.name, task.scope_id)] = _outcome(result)
        return task

    def classify_lost(self) -> None:
        """dask passes a task's error on to the tasks that depend on it: those were not run, the first one
        failed."""
        for task in sorted(self.lost, key=self.plan.tasks.index):  # plan order: upstream before downstream
            bad = next((t for t in task.upstream.values() if t.status in ("failed", "skipped")), None)
            if bad is not None:
                task.status, task.failed_stage = "skipped", bad.failed_stage or bad.stage.name
                task.error = f"not run: upstream {task.failed_stage} failed"
            else:
                self.store.record_failure(task.stage.name, task.scope_id, task.key, task.error or "unknown error")
