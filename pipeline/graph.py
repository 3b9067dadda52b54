"""Planning and executing the stage graph.

Planning computes every task's cache key from an explicit record (stage, version, the digests of the
stage's code, scope, the config fields that change output, upstream keys, raw-input digests). A task whose
key is already committed in the store is resolved while planning and never reaches the scheduler; each
decision is logged as one line with its reason. Execution submits the remaining tasks to an executor (in-process, or
dask.distributed), one task per (stage, scope) or per (stage, action, camera) for per-view stages.

A task never raises into the scheduler: it returns a result record, and a failed upstream turns its
downstream tasks into "skipped", so one bad action never stops the others. A skipped task names the stage
that failed (``failed_stage``), once, however many stages lie between; the failure itself is that
stage's error. Failures are recorded in the store, so the next plan says "failed last run: REASON; will
retry" for a task whose key failed last time.
"""
from __future__ import annotations

import logging
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.capture import Capture
from pipeline.config import key_fields
from pipeline.errors import InputError
from pipeline.hashing import DigestCache, code_digests, record_key
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
    raw_inputs: dict[str, Path]
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
              echo: Callable[[str], None] | None = None) -> Plan:
    """Resolve every (stage, scope) task: its key, and whether it is cached, to run, or failed."""
    force = force or set()
    ordered = topo_order(stages)
    by_name = {s.name: s for s in ordered}
    wanted = list(actions) if actions is not None else [a.action_id for a in capture.actions]
    unknown = [a for a in wanted if a not in {x.action_id for x in capture.actions}]
    if unknown:
        raise InputError(capture.root / "capture.json", f"unknown action(s) {unknown}")
    stage_code: dict[str, dict[str, str]] = {}
    for stage in ordered:
        try:
            stage_code[stage.name] = code_digests(stage.code_module, stage.code_packages)
        except ValueError as exc:
            raise ValueError(f"stage {stage.name}: {exc}") from exc
    tasks: list[Task] = []
    index: dict[tuple[str, str], Task] = {}
    emit = echo or (lambda line: log.info(line))
    for stage in ordered:
        stage.preflight(capture, emit)

    def plan_one(stage: Stage, scope_id: str, session_id: str, action_id: str | None) -> Task:
        upstream = {}
        for req in stage.requires:
            req_scope = session_id if by_name[req].scope == "session" else scope_id
            upstream[req] = index[(req, req_scope)]
        error = None
        raw: dict[str, Path] = {}
        inputs: dict[str, str] = {}
        try:
            raw = stage.raw_inputs(capture, scope_id)
            for name, path in sorted(raw.items()):
                inputs[name] = digests.digest(path)["sha256"]
        except InputError as exc:
            error = str(exc)
        except FileNotFoundError as exc:
            error = f"{exc.filename}: file disappeared while planning"
        views = list(capture.sessions[session_id].camera_ids)
        record = {"stage": stage.name, "version": stage.version, "code": stage_code[stage.name], "scope": scope_id,
                  "config": key_fields(stage.config), "upstream": {n: t.key for n, t in sorted(upstream.items())},
                  "inputs": inputs}
        key = record_key(record)
        bad_up = [t for t in upstream.values() if t.status in ("failed", "blocked")]
        failed_stage = last_error = None
        if error:
            status, reason = "failed", error
        elif bad_up:
            failed_stage = bad_up[0].failed_stage or bad_up[0].stage.name  # the root, not the chain
            status, reason = "blocked", f"upstream {failed_stage} failed"
            error = f"not run: upstream {failed_stage} failed"
        elif stage.name in force:
            status, reason = "run", "forced by --only/--from"
        elif store.is_complete(stage.name, scope_id, key):
            status, reason = "cached", f"key {short(key)} already in store"
        elif (last_error := store.last_failure(stage.name, scope_id, key)) is not None:
            status, reason = "run", f"failed last run: {last_error}; will retry"
        else:
            status, reason = "run", _why(record, store.latest_record(stage.name, scope_id))
        retrying = None
        if status == "run":
            retried_up = next((t.retrying for t in upstream.values() if t.retrying), None)
            if last_error is not None and stage.name not in force:
                retrying = stage.name
            elif retried_up and reason in ("no earlier result", "result missing from store"):
                retrying = retried_up  # it never ran because that upstream stage failed
                reason = f"upstream {retried_up} failed last run; runs after its retry"
        task = Task(stage, scope_id, session_id, action_id, key, record, status, reason, upstream, raw,
                    views=views, error=error, failed_stage=failed_stage, retrying=retrying)
        emit(f"{stage.name:<12} {scope_id:<8} {status:<7} {reason}")
        index[(stage.name, scope_id)] = task
        tasks.append(task)
        return task

    sessions_needed = sorted({capture.action(a).session_id for a in wanted})
    for session_id in sessions_needed:
        for stage in ordered:
            if stage.scope == "session":
                plan_one(stage, session_id, session_id, None)
    for action_id in wanted:
        session_id = capture.action(action_id).session_id
        for stage in ordered:
            if stage.scope == "action":
                plan_one(stage, action_id, session_id, action_id)
    return Plan(tasks, store)


# --- execution -------------------------------------------------------------------------------------

def _context(task: Task, store: ArtifactStore, capture: Capture) -> StageContext:
    upstream_dirs = {n: store.final_dir(n, t.scope_id, t.key) for n, t in task.upstream.items()}
    this = store.final_dir(task.stage.name, task.scope_id, task.key)
    previous = [d for d in store.committed_dirs(task.stage.name, task.scope_id) if d != this]
    return StageContext(stage=task.stage.name, scope_id=task.scope_id, session_id=task.session_id,
                        action_id=task.action_id, out_dir=store.tmp_dir(task.stage.name, task.scope_id, task.key),
                        upstream=upstream_dirs, raw_inputs=task.raw_inputs,
                        rig=capture.sessions[task.session_id].rig, capture_root=capture.root, views=task.views,
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


def run_view_task(stage: Stage, ctx: StageContext, view: str, *upstream: dict[str, Any]) -> dict[str, Any]:
    """One camera of a per-view stage (runs on a worker)."""
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


def finish_task(stage: Stage, ctx: StageContext, store: ArtifactStore, key: str, record: dict[str, Any],
                *parts: dict[str, Any]) -> dict[str, Any]:
    """Finalize a per-view stage, or run a whole-scope stage, then commit its folder (runs on a worker)."""
    if not stage.per_view:  # its parts are upstream results: a failure there means "not run"
        skipped = _upstream_failed(parts)
        if skipped:
            store.discard(ctx.stage, ctx.scope_id, key)
            return skipped
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
        seconds = view_seconds + time.perf_counter() - start
        store.commit(ctx.stage, ctx.scope_id, key, record, stats, seconds)
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

    def as_completed(self, handles: list[Any]) -> Iterable[tuple[Any, Any]]:
        for handle in handles:
            yield handle, handle

    def close(self) -> None:
        set_local_progress(None)


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

    def submit(self, fn: Callable[..., Any], *args: Any, key: str, resources: dict | None = None) -> Any:
        # Only annotate resources the cluster has: a GPU stage on a CPU-only cluster still runs.
        usable = {k: v for k, v in (resources or {}).items() if k in self._resources} or None
        return self.client.submit(fn, *args, key=key, pure=False, resources=usable)

    def subscribe_progress(self, callback: Callable[[dict[str, Any]], None] | None) -> None:
        if callback is not None:
            self.client.subscribe_topic(PROGRESS_TOPIC, lambda event: callback(event[1]))

    def as_completed(self, handles: list[Any]) -> Iterable[tuple[Any, Any]]:
        from distributed import as_completed

        for future in as_completed(handles):
            yield future, future.result()

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def execute(plan: Plan, capture: Capture, executor: Any,
            on_done: Callable[[Task, dict[str, Any], int, int], None] | None = None,
            on_view: Callable[[Task, dict[str, Any], int, int], None] | None = None,
            on_progress: Callable[[dict[str, Any]], None] | None = None) -> None:
    """Run every task the plan marked "run"; fill in each task's status, seconds, stats and error.

    ``on_done(task, result, done, total)`` is called as each (stage, scope) completes and
    ``on_view(task, result, done, total)`` as each camera of a per-view stage does (progress display);
    ``on_progress(record)`` receives what long tasks report through ``StageContext.progress``.
    """
    if on_progress is not None and hasattr(executor, "subscribe_progress"):
        executor.subscribe_progress(on_progress)
    store = plan.store
    handles: dict[tuple[str, str], Any] = {}
    owner: dict[int, Task] = {}
    view_owner: dict[int, Task] = {}
    view_handles: list[Any] = []
    for task in plan.to_run():
        ctx = _context(task, store, capture)
        ups = [handles[(n, t.scope_id)] for n, t in task.upstream.items() if (n, t.scope_id) in handles]
        store.begin(task.stage.name, task.scope_id, task.key)
        tag = f"{task.stage.name}-{task.scope_id}-{short(task.key)}"
        res = task.stage.resources
        if task.stage.per_view:
            views = task.stage.views(ctx)
            parts = [executor.submit(run_view_task, task.stage, ctx, v, *ups, key=f"{tag}-{v}", resources=res)
                     for v in views]
            view_owner.update({id(p): task for p in parts})
            view_handles += parts
        else:
            parts = list(ups)
        handle = executor.submit(finish_task, task.stage, ctx, store, task.key, task.record, *parts,
                                 key=f"{tag}-commit")
        handles[(task.stage.name, task.scope_id)] = handle
        owner[id(handle)] = task
    total = len(handles)
    done = views_done = 0
    watched = (view_handles if on_view else []) + list(handles.values())
    for handle, result in executor.as_completed(watched):
        if id(handle) in view_owner:
            views_done += 1
            on_view(view_owner[id(handle)], result, views_done, len(view_handles))
            continue
        task = owner[id(handle)]
        done += 1
        task.seconds = float(result.get("seconds", 0.0))
        task.started_at = result.get("started_at")
        if result.get("ok"):
            task.status, task.stats = "ran", result.get("stats", {})
        else:
            task.status = "skipped" if result.get("skipped") else "failed"
            task.error = result.get("error")
            if task.status == "skipped":
                task.failed_stage = result.get("failed_stage")
            else:
                store.record_failure(task.stage.name, task.scope_id, task.key, task.error or "unknown error")
                if result.get("traceback"):
                    log.debug("%s failed:\n%s", task.name, result["traceback"])
        if on_done:
            on_done(task, result, done, total)
