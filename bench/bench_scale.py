"""The engine's own overhead at release size: planning, submission and bookkeeping per task.

A capture of N actions x 32 cameras x 3 illuminations (tiny raw files, one session per 50 actions) goes
through the real engine, ``pipeline.runner.run_pipeline`` with the manifests' catalog: the plan (cache-key
records and hashing, raw-file digests, store lookups), submission to the executor, the tasks' store folders
and commits (with the digests of the files each task publishes), publishing into the release, the manifests
and the release page. The stages are the real stage list (names, scopes, requirements, per-camera splits,
resources, configs and code digests) with their work replaced by a stub:
each camera piece writes one small file, each whole-scope stage one file, and every file is published
(so the release holds one file per executor task). What is timed is therefore only what the engine adds.

Each configuration runs twice on a fresh work folder: ``cold`` (every task runs) and ``cached`` (every task
is found in the store; what a rerun costs before any work). Phases, in seconds and per task:

- ``plan``: ``make_plan``, per plan task (one per stage and scope);
- ``submit``: time inside ``executor.submit`` calls, per executor task (one per camera of a per-camera
  stage plus one per stage and scope); with the in-process executor this includes running the stubs;
- ``execute``: all of ``execute`` (submission and waiting for results), per executor task;
- ``bookkeeping``: the rest of the run after execution (stats of cached tasks, publishing, manifests,
  release page), per plan task and per graph task (plan tasks plus camera pieces: what a cold run submits,
  and one published file each); ``publish``/``manifests``/``page`` are its main parts.

``max_in_flight`` is the largest number of executor tasks submitted and not yet finished at any moment:
how much of the graph the scheduler holds. Each configuration runs in its own process (``peak_rss_mib``
is that process's peak). The speed baseline, timed in the same process after the cold run: the same number of
executor tasks, each writing one stub file, through the executor alone (``bare_ms``, ``x_bare``), and on dask as one
``client.map`` (``bare_map_ms``). Writes bench_scale.json and bench_scale.md.

``python bench/bench_scale.py --out bench/out [--sizes 20,200,2000] [--executors sync,dask] [--quick]``
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
# dask's worker processes import the stages from this tree too, and the stub classes from this module (by
# reference, as they import a real stage's class: pickled by value they would cost the submission ~1 ms a task)
os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "bench")] + [
    p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])

from pipeline.capture import ILLUMINATIONS  # noqa: E402

CAMERAS = 32
ACTIONS_PER_SESSION = 50
GOAL_MS = 1.0
"""The issue's goal: under 1 ms of engine overhead per task."""


# --- the capture -----------------------------------------------------------------------------------

def make_capture(root: Path, n_actions: int, cameras: int = CAMERAS,
                 actions_per_session: int = ACTIONS_PER_SESSION) -> Path:
    """A capture folder of ``n_actions`` actions with ``cameras`` cameras, each frame a tiny raw file (the
    engine only finds, stats and hashes them; the stub stages never decode)."""
    cam_ids = [f"{i:05d}" for i in range(cameras)]
    cams = [{"camera_id": c, "width": 6016, "height": 4016, "K": [[9000, 0, 3008], [0, 9000, 2008], [0, 0, 1]],
             "cam_from_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3]], "white_reference": [0.5, 0.5, 0.5]}
            for c in cam_ids]
    sessions, actions = [], []
    for a in range(n_actions):
        session = f"S{a // actions_per_session:03d}"
        if not sessions or sessions[-1]["session_id"] != session:
            folder = root / "sessions" / session
            folder.mkdir(parents=True, exist_ok=True)
            (folder / "rig.json").write_text(json.dumps({"format": "ultrastage-rig/1", "session_id": session,
                                                         "cameras": cams}))
            sessions.append({"session_id": session, "rig": f"sessions/{session}/rig.json"})
        action = f"A{a:04d}"
        for illum in ILLUMINATIONS:
            folder = root / "actions" / action / illum
            folder.mkdir(parents=True, exist_ok=True)
            for c in cam_ids:
                (folder / f"{c}.dng").write_bytes(f"{action} {illum} {c}".encode())
        actions.append({"action_id": action, "session_id": session, "subject": f"subject{a % 97:03d}"})
    (root / "capture.json").write_text(json.dumps({
        "format": "ultrastage-capture/1", "sessions": sessions, "actions": actions,
        "illuminations": list(ILLUMINATIONS), "camera_ids": cam_ids}))
    return root


# --- stub stages -----------------------------------------------------------------------------------

class _Stub:
    """Mixed in before a real stage class: the real name, scope, requirements, per-camera split, resources,
    config, raw inputs and code digest; the work replaced by writing one small file per piece."""

    real: type

    @property
    def code_module(self) -> str:
        return self.real.__module__  # the real stage's code digest enters the key, as in a real run

    def preflight(self, capture: Any, echo: Any) -> None:
        pass

    def run_view(self, ctx: Any, view: str) -> dict[str, Any]:
        (ctx.out_dir / "views").mkdir(parents=True, exist_ok=True)
        (ctx.out_dir / "views" / f"{view}.txt").write_text(f"{ctx.stage} {ctx.scope_id} {view}")
        return {"mean": 0.5, "valid_fraction": 1.0, "width": 6016, "height": 4016}

    def finalize(self, ctx: Any, view_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
        return {"views": view_stats}

    def run(self, ctx: Any) -> dict[str, Any]:
        (ctx.out_dir / "result.txt").write_text(f"{ctx.stage} {ctx.scope_id}")
        return {"stub": 1}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        if self.scope != "action":
            return []
        if self.per_view:
            return [(p, f"{self.name}/{p.name}", self.name, p.stem) for p in sorted((artifact / "views").glob("*.txt"))]
        return [(artifact / "result.txt", f"{self.name}/result.txt", self.name, None)]

    def release_root_files(self, artifact: Path) -> list[tuple[Path, str, str]]:
        return []

    def manifest_rows(self, artifact: Path) -> dict[str, list[dict[str, Any]]]:
        return {}


def _stub_classes() -> list[type]:
    """A stub class per registry stage, made at import as attributes of this module (so that a worker process
    unpickles them by name, importing this module, as it does a real stage's class)."""
    from stages.registry import STAGE_CLASSES

    made = []
    for cls in STAGE_CLASSES:
        name = f"Stub{cls.__name__}"
        globals()[name] = stub = type(name, (_Stub, cls), {"real": cls, "__module__": __name__, "__qualname__": name})
        made.append(stub)
    return made


STUB_CLASSES = _stub_classes()


def stub_stages() -> list[Any]:
    """The registry's stages (default preset, procedural environments so no HDR file is needed) as stubs."""
    import dataclasses

    from stages.registry import CODE_PACKAGES, PRESETS

    config = PRESETS["default"]
    envs = ("procedural:sky", "procedural:studio")
    config = dataclasses.replace(config, relight=dataclasses.replace(config.relight, environments=envs),
                                 relightset=dataclasses.replace(config.relightset, environments=envs))
    return [stub(getattr(config, stub.real.config_section or stub.real.name), code_packages=CODE_PACKAGES)
            for stub in STUB_CLASSES]


# --- timing ----------------------------------------------------------------------------------------

class TimedExecutor:
    """Wraps an executor: time inside ``submit``, tasks submitted and finished, the most held at once."""

    def __init__(self, inner: Any):
        self.inner = inner
        self.name = inner.name
        self.submit_s = 0.0
        self.submitted = 0
        self.finished = 0
        self.max_in_flight = 0
        self._pending = 0
        self._pieces: dict[int, int] = {}

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def submit(self, fn: Any, *args: Any, key: str, resources: dict | None = None) -> Any:
        start = time.perf_counter()
        handle = self.inner.submit(fn, *args, key=key, resources=resources)
        self.submit_s += time.perf_counter() - start
        self.submitted += 1
        self._pending += 1
        if key.endswith("-commit"):  # a stage task's commit: it finishes after its camera pieces
            self._pieces[id(handle)] = self._pending
            self._pending = 0
        self.max_in_flight = max(self.max_in_flight, self.submitted - self.finished)
        return handle

    def _done(self, handle: Any) -> None:
        self.finished += self._pieces.pop(id(handle), 0)

    def as_completed(self, handles: Any) -> Any:
        for handle, result in self.inner.as_completed(handles):
            self._done(handle)
            yield handle, result

    def completions(self, handles: Any = ()) -> Any:
        queue = self.inner.completions(handles)
        owner = self

        class Timed:
            def add(self, handle: Any) -> None:
                queue.add(handle)

            def __iter__(self):
                for handle, result in queue:
                    owner._done(handle)
                    yield handle, result

        return Timed()


def run_once(capture: Path, work: Path, release: Path, scheduler: str, workers: int) -> dict[str, Any]:
    """One ``run_pipeline`` with each phase timed (the engine's functions wrapped in place)."""
    import manifests.catalog
    import manifests.page
    import pipeline.runner as runner

    timers: dict[str, float] = {}
    counts: dict[str, Any] = {}
    wrapped = {}

    def timed(module: Any, name: str, label: str) -> None:
        original = getattr(module, name)
        wrapped[(module, name)] = original

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                timers[label] = timers.get(label, 0.0) + time.perf_counter() - start
        setattr(module, name, wrapper)

    original_make_executor = runner.make_executor

    def make_executor(cfg: Any) -> Any:
        start = time.perf_counter()
        executor = TimedExecutor(original_make_executor(cfg))
        timers["executor_start"] = time.perf_counter() - start
        counts["executor"] = executor
        original_close = executor.inner.close

        def close() -> None:
            t0 = time.perf_counter()
            original_close()
            timers["executor_close"] = time.perf_counter() - t0
        executor.close = close
        return executor

    for module, name, label in ((runner, "make_plan", "plan"), (runner, "execute", "execute"),
                                (runner, "prepare_action", "publish"), (runner, "swap_in", "publish"),
                                (manifests.catalog, "write_run_manifests", "manifests"),
                                (runner, "_write_release_docs", "docs"), (manifests.page, "write_release_page", "page")):
        timed(module, name, label)
    runner.make_executor = make_executor
    try:
        start = time.perf_counter()
        result = runner.run_pipeline(capture, release, work, stub_stages(), {"bench": "scale"},
                                     runner.ExecutionConfig(scheduler=scheduler, workers=workers),
                                     echo=lambda line: None, catalog=manifests.catalog.ManifestCatalog())
        total = time.perf_counter() - start
    finally:
        runner.make_executor = original_make_executor
        for (module, name), original in wrapped.items():
            setattr(module, name, original)
    executor = counts.get("executor")
    plan_tasks = len(result.plan.tasks)
    ran = sum(t.status == "ran" for t in result.plan.tasks)
    cached = sum(t.status == "cached" for t in result.plan.tasks)
    if ran + cached != plan_tasks or len(result.published) != len(result.action_status):
        raise RuntimeError(f"the stub run did not complete: {ran} ran, {cached} cached of {plan_tasks}; "
                           f"{result.action_errors}")
    executor_tasks = executor.submitted if executor else 0
    graph_tasks = plan_tasks + sum(len(t.views) for t in result.plan.tasks if t.stage.per_view)
    after = total - timers.get("plan", 0.0) - timers.get("executor_start", 0.0) - timers.get("execute", 0.0) \
        - timers.get("executor_close", 0.0)
    phases = {"plan_s": timers.get("plan", 0.0), "executor_start_s": timers.get("executor_start", 0.0),
              "submit_s": executor.submit_s if executor else 0.0, "execute_s": timers.get("execute", 0.0),
              "executor_close_s": timers.get("executor_close", 0.0), "bookkeeping_s": after,
              "publish_s": timers.get("publish", 0.0), "manifests_s": timers.get("manifests", 0.0),
              "page_s": timers.get("page", 0.0), "docs_s": timers.get("docs", 0.0), "total_s": total}
    per_task = {"plan_ms": 1e3 * phases["plan_s"] / plan_tasks,
                "bookkeeping_ms": 1e3 * after / plan_tasks, "bookkeeping_per_graph_task_ms": 1e3 * after / graph_tasks}
    if executor_tasks:
        per_task |= {"submit_ms": 1e3 * phases["submit_s"] / executor_tasks,
                     "execute_ms": 1e3 * phases["execute_s"] / executor_tasks}
    return {"plan_tasks": plan_tasks, "graph_tasks": graph_tasks, "executor_tasks": executor_tasks, "ran": ran,
            "cached": cached,
            "max_in_flight": executor.max_in_flight if executor else 0, "executor": result.executor,
            "phases_s": phases, "per_task": per_task}


def write_stub_file(path: str) -> int:
    """The work of one stub task without the engine: write one small file."""
    Path(path).write_text(path)
    return 1


def bare_executor(n_tasks: int, scheduler: str, root: Path, workers: int) -> dict[str, Any]:
    """The speed baseline, timed in the same process: ``n_tasks`` stub files written through the engine's executor
    alone (no plan, store, commits or release), submitted one at a time as the engine does (``submit_s``), and on
    dask also as one ``client.map`` (``map_s``: the scheduler's floor for the same tasks)."""
    from pipeline.runner import ExecutionConfig, make_executor

    folder = root / "bare"
    folder.mkdir(parents=True, exist_ok=True)
    paths = [str(folder / f"{i}.txt") for i in range(n_tasks)]
    executor = make_executor(ExecutionConfig(scheduler=scheduler, workers=workers))
    try:
        start = time.perf_counter()
        handles = [executor.submit(write_stub_file, path, key=f"bare-{i}") for i, path in enumerate(paths)]
        done = sum(result for _, result in executor.as_completed(handles))
        result = {"tasks": n_tasks, "submit_s": time.perf_counter() - start}
        if done != n_tasks:
            raise RuntimeError(f"bare executor: {done} of {n_tasks} tasks finished")
        if scheduler != "sync":
            client = executor.client
            start = time.perf_counter()
            futures = client.map(write_stub_file, [p + ".map" for p in paths], pure=False)
            if sum(client.gather(futures)) != n_tasks:
                raise RuntimeError("bare executor: client.map did not finish every task")
            result["map_s"] = time.perf_counter() - start
    finally:
        executor.close()
    return result


def measure(n_actions: int, executor: str, root: Path, workers: int = 2) -> dict[str, Any]:
    """A fresh capture of ``n_actions`` actions, run cold then cached with ``executor`` ("sync" or "dask"),
    after a one-action warm-up run (imports, code digests: once per process, not per task)."""
    start = time.perf_counter()
    run_once(make_capture(root / "warmup" / "capture", 1), root / "warmup" / "work", root / "warmup" / "release",
             "sync", workers)
    warmup_s = time.perf_counter() - start
    start = time.perf_counter()
    capture = make_capture(root / "capture", n_actions)
    capture_s = time.perf_counter() - start
    scheduler = {"sync": "sync", "dask": "local"}[executor]
    runs = {label: run_once(capture, root / "work", root / "release", scheduler, workers)
            for label in ("cold", "cached")}
    cold = runs["cold"]
    bare = bare_executor(cold["executor_tasks"], scheduler, root, workers)
    cold["per_task"]["bare_ms"] = 1e3 * bare["submit_s"] / bare["tasks"]
    cold["per_task"]["x_bare"] = cold["per_task"]["execute_ms"] / cold["per_task"]["bare_ms"]
    if "map_s" in bare:
        cold["per_task"]["bare_map_ms"] = 1e3 * bare["map_s"] / bare["tasks"]
    return {"actions": n_actions, "cameras": CAMERAS, "executor": executor, "workers": workers if executor == "dask" else 0,
            "warmup_s": warmup_s, "make_capture_s": capture_s, "runs": runs, "bare_executor": bare,
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def _measure_in_child(n_actions: int, executor: str, workers: int, tmp: Path) -> dict[str, Any]:
    out = tmp / f"one_{n_actions}_{executor}.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--one", f"{n_actions},{executor}", "--workers",
           str(workers), "--tmp", str(tmp / f"run_{n_actions}_{executor}"), "--one-out", str(out)]
    subprocess.run(cmd, check=True, cwd=ROOT)
    return json.loads(out.read_text())


# --- report ----------------------------------------------------------------------------------------

def table(results: list[dict[str, Any]]) -> str:
    lines = ["# Engine overhead at release size", "",
             f"Stub stages on the real engine ({CAMERAS} cameras, 3 illuminations, one session per "
             f"{ACTIONS_PER_SESSION} actions; one published file per executor task). Milliseconds per task: "
             "plan and bookkeeping per plan task (stage x scope), submission and the whole execution per "
             "executor task (camera pieces + commits); bookkeeping also per graph task (plan tasks + camera "
             "pieces, one published file each). Goal: under 1 ms. `in flight`: most executor tasks "
             "submitted and not finished at once. Baseline (`bare ms`, timed in the same process): the same number "
             "of stub tasks through the executor alone, submitted one at a time as the engine does; `x bare` is the "
             "engine's execute time over it; `map ms`: the same tasks as one `client.map` on dask.", "",
             "| actions | executor | run | plan tasks | exec tasks | plan ms | submit ms | execute ms | bare ms | "
             "x bare | map ms | bookkeeping ms | bookkeeping ms / graph task | in flight | total s | peak RSS MiB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        for label, run in r["runs"].items():
            p = run["per_task"]
            fmt = lambda k: f"{p[k]:.3f}" if k in p else "-"  # noqa: E731
            lines.append(f"| {r['actions']} | {r['executor']} | {label} | {run['plan_tasks']} | {run['executor_tasks']} | "
                         f"{fmt('plan_ms')} | {fmt('submit_ms')} | {fmt('execute_ms')} | {fmt('bare_ms')} | "
                         f"{fmt('x_bare')} | {fmt('bare_map_ms')} | {fmt('bookkeeping_ms')} | "
                         f"{fmt('bookkeeping_per_graph_task_ms')} | "
                         f"{run['max_in_flight']} | {run['phases_s']['total_s']:.1f} | {r['peak_rss_mib']:.0f} |")
    lines += ["", "Bookkeeping split (seconds: publish / manifests / page):", ""]
    for r in results:
        for label, run in r["runs"].items():
            ph = run["phases_s"]
            lines.append(f"- {r['actions']} actions, {r['executor']}, {label}: {ph['publish_s']:.2f} / "
                         f"{ph['manifests_s']:.2f} / {ph['page_s']:.2f} of {ph['bookkeeping_s']:.2f}")
    return "\n".join(lines) + "\n"


def check(results: list[dict[str, Any]]) -> None:
    """Every per-task figure finite and positive (the structure the unit test relies on)."""
    for r in results:
        for run in r["runs"].values():
            for key, value in run["per_task"].items():
                if not (math.isfinite(value) and value > 0):
                    raise ValueError(f"{r['actions']} actions, {r['executor']}: {key} = {value}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--sizes", default="20,200,2000", help="numbers of actions, comma-separated")
    parser.add_argument("--executors", default="sync,dask", help="sync and/or dask (a local cluster)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes of the dask cluster")
    parser.add_argument("--quick", action="store_true", help="2 and 4 actions, in-process executor, in this process")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    parser.add_argument("--one-out", help=argparse.SUPPRESS)
    parser.add_argument("--tmp", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:  # a child: one configuration in a fresh process
        n, executor = args.one.split(",")
        result = measure(int(n), executor, Path(args.tmp), args.workers)
        Path(args.one_out).write_text(json.dumps(result))
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sizes = [2, 4] if args.quick else [int(s) for s in args.sizes.split(",")]
    executors = ["sync"] if args.quick else args.executors.split(",")
    results = []
    with tempfile.TemporaryDirectory(prefix="bench_scale_") as tmp:
        for executor in executors:
            for n in sizes:
                if args.quick:
                    result = measure(n, executor, Path(tmp) / f"run_{n}_{executor}", args.workers)
                else:
                    result = _measure_in_child(n, executor, args.workers, Path(tmp))
                shutil.rmtree(Path(tmp) / f"run_{n}_{executor}", ignore_errors=True)
                results.append(result)
                for label, run in result["runs"].items():
                    print(f"{n:>5} actions {executor:<5} {label:<6} " + "  ".join(
                        f"{k} {v:.3f}" for k, v in run["per_task"].items()) + f"  in flight {run['max_in_flight']}"
                          f"  total {run['phases_s']['total_s']:.1f}s", flush=True)
    check(results)
    report = {"goal_ms_per_task": GOAL_MS, "cameras": CAMERAS, "quick": bool(args.quick), "results": results}
    (out / "bench_scale.json").write_text(json.dumps(report, indent=1))
    (out / "bench_scale.md").write_text(table(results))
    print(f"wrote {out / 'bench_scale.json'} and {out / 'bench_scale.md'}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT / "bench"))
    import bench_scale  # this file under its own name: the stub classes pickle by reference

    raise SystemExit(bench_scale.main())
