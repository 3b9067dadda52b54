"""The artifact store (Meshroom style): one folder per (stage, scope, cache key), complete or absent.

Layout: ``<root>/<stage>/<scope_id>/<key16>/`` with ``_SUCCESS.json`` inside. Work goes to
``<root>/<stage>/<scope_id>/.tmp-<key16>`` and is renamed into place when complete, so a crash leaves
only a temporary folder that the next run removes. ``latest.json`` beside the keyed folders records the
last committed record, so a plan can say *why* a stage reruns; ``failed.json`` there records the last
failure of a key (its error), so a plan can say that a task failed last time and why, until it commits.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any, Iterable

SUCCESS = "_SUCCESS.json"
FAILURE = "failed.json"
_POINTERS = ("latest", "failed")
"""The pointer files of a (stage, scope) folder (``<name>.json``), each written as :func:`_pointer_tmp` then renamed."""


def _pointer_tmp(folder: Path, name: str) -> Path:
    """This process's temporary file for the pointer ``name`` (of :data:`_POINTERS`) in ``folder``."""
    return folder / f".{name}.{os.getpid()}.tmp"


def short(key: str) -> str:
    return key[:16]


def swap_into_place(tmp: Path, final: Path) -> None:
    """Rename a complete folder ``tmp`` to ``final``, replacing (then deleting) any folder there."""
    if final.exists():
        old = final.with_name(f".old-{final.name}-{os.getpid()}")
        os.rename(final, old)
        os.rename(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(tmp, final)


def link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link ``src`` to ``dst`` (its folders made), or copy it where links are not possible."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


class ArtifactStore:
    def __init__(self, root: str | Path):
        self.root = Path(root)

    def final_dir(self, stage: str, scope_id: str, key: str) -> Path:
        return self.root / stage / scope_id / short(key)

    def tmp_dir(self, stage: str, scope_id: str, key: str) -> Path:
        return self.root / stage / scope_id / f".tmp-{short(key)}"

    def is_complete(self, stage: str, scope_id: str, key: str) -> bool:
        return (self.final_dir(stage, scope_id, key) / SUCCESS).is_file()

    def success_record(self, stage: str, scope_id: str, key: str) -> dict[str, Any]:
        return json.loads((self.final_dir(stage, scope_id, key) / SUCCESS).read_text())

    def latest_record(self, stage: str, scope_id: str) -> dict[str, Any] | None:
        path = self.root / stage / scope_id / "latest.json"
        try:
            return json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            return None

    def latest_dir(self, stage: str, scope_id: str) -> Path | None:
        """The folder of the last committed result of a (stage, scope), if it is still complete."""
        record = self.latest_record(stage, scope_id)
        if record is None or not self.is_complete(stage, scope_id, record.get("key", "")):
            return None
        return self.final_dir(stage, scope_id, record["key"])

    def committed_dirs(self, stage: str, scope_id: str) -> list[Path]:
        """Every complete result of a (stage, scope), under any key, the most recently committed first."""
        folder = self.root / stage / scope_id
        if not folder.is_dir():
            return []
        found = [d for d in folder.iterdir() if d.is_dir() and not d.name.startswith(".") and (d / SUCCESS).is_file()]
        return sorted(found, key=lambda d: (d / SUCCESS).stat().st_mtime_ns, reverse=True)

    def begin(self, stage: str, scope_id: str, key: str) -> Path:
        """A fresh, empty temporary folder for this key (a leftover from a crashed run is removed)."""
        tmp = self.tmp_dir(stage, scope_id, key)
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        return tmp

    def commit(self, stage: str, scope_id: str, key: str, record: dict[str, Any],
               stats: dict[str, Any], seconds: float, attempt: str | None = None,
               started_at: float | None = None, files: dict[str, dict[str, Any]] | None = None) -> Path:
        """Write the success record into the temporary folder and rename it into place.

        ``files``: path in the folder -> ``{"bytes", "sha256", "mtime_ns"}`` of the files the stage publishes
        (:func:`pipeline.graph.published_digests`), kept in the record for :meth:`file_digest`.

        ``attempt`` names the execution that commits (:func:`committed_by`). Hidden ``*.tmp`` files left in the
        folder by a writer that died before renaming them (the codecs write ``.<name>.<pid>.tmp``, then rename:
        a worker killed mid-write leaves one behind) are removed first: a committed folder holds outputs only.
        """
        tmp = self.tmp_dir(stage, scope_id, key)
        final = self.final_dir(stage, scope_id, key)
        for leftover in [p for p in tmp.rglob(".*.tmp") if p.is_file()]:
            leftover.unlink()
        success = {"stage": stage, "scope_id": scope_id, "key": key, "record": record, "stats": stats,
                   "seconds": seconds, "committed_at": time.time(), "attempt": attempt,
                   "started_at": started_at, "files": files or {}}
        (tmp / SUCCESS).write_text(json.dumps(success, indent=1, sort_keys=True))
        swap_into_place(tmp, final)  # a forced rerun of the same key replaces the old copy
        self.note_committed(stage, scope_id, key, record)
        return final

    @staticmethod
    def file_digest(success: dict[str, Any], artifact: Path, path: Path) -> dict[str, Any] | None:
        """``{"bytes", "sha256"}`` of ``path`` (a file in the committed folder ``artifact``) from its success
        record ``success``, when the record has it and the file's size and mtime are still the ones hashed;
        else None (the caller hashes the file)."""
        try:
            entry = success.get("files", {}).get(Path(path).relative_to(artifact).as_posix())
        except ValueError:
            return None
        if entry is None:
            return None
        try:
            stat = os.stat(path)
        except OSError:
            return None
        if stat.st_size != entry["bytes"] or stat.st_mtime_ns != entry["mtime_ns"]:
            return None
        return {"bytes": entry["bytes"], "sha256": entry["sha256"]}

    def note_committed(self, stage: str, scope_id: str, key: str, record: dict[str, Any]) -> None:
        """``latest.json`` names this key, and its last failure is forgotten (idempotent: the tail of a commit)."""
        folder = self.root / stage / scope_id
        latest_tmp = _pointer_tmp(folder, "latest")
        latest_tmp.write_text(json.dumps({"key": key, "record": record}, sort_keys=True))
        os.replace(latest_tmp, folder / "latest.json")
        (folder / FAILURE).unlink(missing_ok=True)

    def sweep_pointer_temps(self, scopes: Iterable[tuple[str, str]]) -> list[Path]:
        """Remove the temporary files of the pointers (:func:`_pointer_tmp`: ``.latest.<pid>.tmp``,
        ``.failed.<pid>.tmp``) in the (stage, scope) folders and return them: a writer killed between writing one
        and renaming it (:meth:`note_committed`, :meth:`record_failure`) leaves it behind, and no later writer
        renames another process's. Call it only when nothing writes to those folders (the run that holds the work
        folder's lock, after its tasks): a live writer renames its own a moment after writing it."""
        removed = []
        for stage, scope_id in sorted(set(scopes)):
            folder = self.root / stage / scope_id
            for name in _POINTERS:
                for path in sorted(folder.glob(f".{name}.*.tmp")):
                    try:
                        path.unlink()
                    except FileNotFoundError:
                        continue
                    removed.append(path)
        return removed

    def committed_by(self, stage: str, scope_id: str, key: str, attempt: str) -> dict[str, Any] | None:
        """The success record of this key if the execution ``attempt`` committed it, else None.

        dask recomputes a finished task whose result was held only by a worker that died; a task that finds its
        folder committed by its own execution returns that record instead of running (and committing) again.
        """
        try:
            success = self.success_record(stage, scope_id, key)
        except (OSError, json.JSONDecodeError):
            return None
        return success if success.get("attempt") == attempt else None

    def record_failure(self, stage: str, scope_id: str, key: str, error: str) -> None:
        """Remember that this key's last run failed, and why (replaced by the next failure, removed by a commit)."""
        folder = self.root / stage / scope_id
        tmp = _pointer_tmp(folder, "failed")
        try:
            folder.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps({"key": key, "error": error, "failed_at": time.time()}, sort_keys=True))
            os.replace(tmp, folder / FAILURE)
        except OSError as exc:  # e.g. the work folder is full (often the very failure): the memo only helps a message
            tmp.unlink(missing_ok=True)
            logging.getLogger("ultrastage.store").warning("%s: could not record the failure of %s %s: %s", folder,
                                                          stage, scope_id, exc)

    def last_failure(self, stage: str, scope_id: str, key: str) -> str | None:
        """The error of this key's last run when that run failed (and nothing committed since), else None."""
        try:
            record = json.loads((self.root / stage / scope_id / FAILURE).read_text())
        except (OSError, json.JSONDecodeError):
            return None
        return record.get("error") if record.get("key") == key else None

    def discard(self, stage: str, scope_id: str, key: str) -> None:
        shutil.rmtree(self.tmp_dir(stage, scope_id, key), ignore_errors=True)
