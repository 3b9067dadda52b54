"""The stage contract (../shared/DESIGN.md, "The stage contract"): what a stage declares and what it sees when it runs.

A stage declares ``name``, ``version``, ``scope`` ("action" or "session"), ``requires`` (upstream stage
names), ``outputs`` (named slots, each a folder in its artifact) and ``resources``. A per-view stage
(``per_view = True``) is run as one task per camera plus a ``finalize`` task, so full-resolution frames
never leave the process that decodes them; every other stage runs as one task.

Its cache key holds, besides its config, upstream keys and inputs, a digest of its code: its module and the
modules of ``code_packages`` it imports (:func:`pipeline.hashing.code_digests`), so editing a numerics
function reruns the stages that call it whether or not anyone bumps ``version``.

A stage sees only its :class:`StageContext`: its config, its upstream artifact folders, its raw input
files and the rig. It writes into ``ctx.out_dir`` (a temporary folder the engine renames into place).
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar

PROGRESS_TOPIC = "ultrastage-progress"
"""dask event topic that carries progress records of long stage tasks to the process that runs the DAG."""

_local_progress: Callable[[dict[str, Any]], None] | None = None


def set_local_progress(callback: Callable[[dict[str, Any]], None] | None) -> None:
    """Where progress records of tasks run in this process go (the in-process executor sets it)."""
    global _local_progress
    _local_progress = callback


def report_progress(record: dict[str, Any]) -> None:
    """Send a progress record to whoever runs the DAG: a dask event from a worker, else the local callback."""
    try:
        from distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):
        worker = None
    if worker is not None:
        worker.log_event(PROGRESS_TOPIC, record)
    elif _local_progress is not None:
        _local_progress(record)


@dataclass
class StageContext:
    """Everything one stage task may look at."""

    stage: str
    scope_id: str
    session_id: str
    action_id: str | None
    out_dir: Path
    """Temporary output folder; renamed into the artifact store when the stage completes."""
    upstream: dict[str, Path]
    """Upstream stage name -> its committed artifact folder."""
    raw_inputs: dict[str, Path]
    """Raw input files by a stage-defined name (e.g. "full_on/00003")."""
    rig: dict[str, Any]
    capture_root: Path
    views: list[str] = field(default_factory=list)
    subject: str | None = None
    """The action's subject (capture.json); None for session-scoped tasks."""
    upstream_keys: dict[str, str] = field(default_factory=dict)
    """Upstream stage name -> its cache key."""
    previous: Path | None = None
    cache_dir: Path | None = None
    """A folder of content-addressed memos shared by every task of the work folder (a result stored under the
    hash of everything it depends on, e.g. an environment map's SG fit); None: no memos."""
    """This stage's last committed result for the same scope under another key, if any: a stage may reuse
    the parts of it whose own inputs did not change (it must check that itself)."""

    @property
    def log(self) -> logging.Logger:
        return logging.getLogger(f"ultrastage.{self.stage}")

    def progress(self, done: int, total: int, message: str = "") -> None:
        """Report progress of a long task (e.g. training iterations); shown by ``ultrastage run``."""
        report_progress({"stage": self.stage, "scope_id": self.scope_id, "done": int(done), "total": int(total),
                         "message": message})


class Stage:
    """Base class; subclasses set the class attributes and implement ``run`` or ``run_view``/``finalize``."""

    name: ClassVar[str]
    version: ClassVar[str] = "1"
    scope: ClassVar[str] = "action"
    requires: ClassVar[tuple[str, ...]] = ()
    outputs: ClassVar[tuple[str, ...]] = ()
    resources: ClassVar[dict[str, float]] = {}
    per_view: ClassVar[bool] = False
    config_section: ClassVar[str | None] = None
    """The section of the pipeline config this stage reads (defaults to its name)."""

    def __init__(self, config: Any, code_packages: Sequence[str] | None = None):
        packages = tuple(code_packages) if code_packages is not None else (type(self).__module__.split(".")[0],)
        bad = [p for p in packages if not isinstance(p, str) or not all(part.isidentifier() for part in p.split("."))]
        if bad:
            raise ValueError(f"stage {type(self).__name__}: code_packages must be dotted module names, got {bad}")
        self.config = config
        self.code_packages: tuple[str, ...] = packages
        """Dotted module prefixes whose code can change this stage's output: the code of the stage's module and
        of every module under these prefixes that it imports, transitively, enters its cache key
        (:func:`pipeline.hashing.code_digests`). Default: the top-level package of the stage's module."""

    @property
    def code_module(self) -> str:
        """The module that defines this stage (where the scan for its code starts)."""
        return type(self).__module__

    # --- planning ---------------------------------------------------------------------------------
    def preflight(self, capture: Any, echo: Callable[[str], None]) -> None:
        """Checks of the stage's own inputs before any task is planned; an InputError stops the run."""

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        """The raw files this stage reads for a scope, by name; their digests enter the cache key."""
        return {}

    def views(self, ctx: StageContext) -> list[str]:
        """Camera ids to run ``run_view`` on (per-view stages)."""
        return list(ctx.views)

    # --- execution --------------------------------------------------------------------------------
    def run(self, ctx: StageContext) -> dict[str, Any]:
        """Whole-scope stages: do the work, return a JSON-able stats record."""
        raise NotImplementedError

    def run_view(self, ctx: StageContext, view: str) -> dict[str, Any]:
        """Per-view stages: the work for one camera; returns a JSON-able stats record."""
        raise NotImplementedError

    def finalize(self, ctx: StageContext, view_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
        """Per-view stages: after every view ran; returns the stage's stats record."""
        return {"views": view_stats}

    def output_paths(self, artifact_dir: Path) -> dict[str, Path]:
        """A path per output slot."""
        return {slot: artifact_dir / slot for slot in self.outputs}
