"""Publishing into a release all or nothing: a run that cannot finish publishing (a full disk, a folder turned
read-only, an exception, a SIGKILL) leaves the release as it was before the run.

A :class:`ReleaseTransaction` lives in ``<release>/.txn-<id>/``, on the release's own file system, so that it
works with renames and hard links and needs no space of its own beyond its journal. Before each change,
``journal.jsonl`` gets a line saying what is changed; ``old/<path>`` keeps what is replaced or removed:

- a folder swapped in (``put_dir``) or out (``remove_dir``): the folder that was there is renamed into ``old/``;
- files about to be rewritten or deleted (``keep_files``: a file, or every file under a folder): each is hard-linked
  into ``old/``. The release's writers replace a file by renaming a new one over it (manifests, the page, the
  documents), so the link keeps the old bytes;
- folders created (``makedirs``), removed again on rollback when they are empty;
- the files directly in the release folder (``keep_root_listing``): one created since is deleted on rollback.

:meth:`ReleaseTransaction.rollback` undoes the journal backwards (renames and deletions only: it needs no free
space); :meth:`ReleaseTransaction.commit` renames the journal to ``committed`` and deletes the transaction folder
(and with it what was replaced). :func:`recover` is called by the next run, under the run lock: it rolls back a
transaction that a dead run left behind (or finishes deleting a committed one) and removes the staging folders
(``actions/.tmp-<id>``, ``.tmp-root-<id>``) that a dead run was filling.

The release's writers rename complete files into place, so the only things a killed run leaves in a release are
this module's: without :func:`recover` its old content would stay hidden in ``.txn-*`` while its half-swapped
new content showed; with it, the next run starts from the release as it was.
"""
from __future__ import annotations

import json
import os
import secrets
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

PREFIX = ".txn-"
JOURNAL = "journal.jsonl"
COMMITTED = "committed"


class ReleaseTransaction:
    """Changes to one release folder that are undone together (see the module's docstring)."""

    def __init__(self, release: Path, folder: Path | None = None):
        self.release = Path(release)
        self.folder = folder or self.release / f"{PREFIX}{os.getpid()}-{secrets.token_hex(3)}"
        self._journal = None

    # --- recording ------------------------------------------------------------------------------------
    def _log(self, entry: dict[str, Any]) -> None:
        if self._journal is None:
            self.folder.mkdir()
            self._journal = open(self.folder / JOURNAL, "a", encoding="utf-8")
        self._journal.write(json.dumps(entry) + "\n")
        self._journal.flush()
        os.fsync(self._journal.fileno())

    def _rel(self, path: Path) -> str:
        return Path(path).relative_to(self.release).as_posix()

    def _old(self, rel: str) -> Path:
        return self.folder / "old" / rel

    def makedirs(self, path: Path) -> None:
        """Create ``path`` and its missing parents (inside the release), each removed on rollback if empty."""
        missing = []
        p = Path(path)
        while p != self.release and not p.exists():
            missing.append(p)
            p = p.parent
        for p in reversed(missing):
            self._log({"op": "mkdir", "path": self._rel(p)})
            p.mkdir()

    def put_dir(self, tmp: Path, final: Path) -> None:
        """Rename the complete folder ``tmp`` to ``final``; what was at ``final`` is kept until commit."""
        rel = self._rel(final)
        self.makedirs(final.parent)
        had = final.exists()
        self._log({"op": "dir", "path": rel, "had": had})
        if had:
            self._old(rel).parent.mkdir(parents=True, exist_ok=True)
            os.rename(final, self._old(rel))
        os.rename(tmp, final)

    def remove_dir(self, final: Path) -> bool:
        """Take the folder ``final`` out of the release (kept until commit). False if there is none."""
        if not final.exists():
            return False
        rel = self._rel(final)
        self._log({"op": "dir", "path": rel, "had": True})
        self._old(rel).parent.mkdir(parents=True, exist_ok=True)
        os.rename(final, self._old(rel))
        return True

    def keep_root_listing(self) -> None:
        """Remember which files lie directly in the release folder: a rollback deletes any other (e.g. the
        temporary file of a writer that failed half-way)."""
        self._log({"op": "root", "path": ".",
                   "files": sorted(p.name for p in self.release.iterdir() if not p.is_dir())})

    def keep_files(self, path: Path) -> None:
        """Keep the present state of a file, or of every file under a folder, for a rollback: files changed or
        deleted afterwards get their old bytes back, files created afterwards are deleted."""
        path = Path(path)
        rel = self._rel(path)
        if path.is_dir():
            files = sorted(p.relative_to(self.release).as_posix() for p in path.rglob("*") if not p.is_dir())
            dirs = sorted(p.relative_to(self.release).as_posix() for p in path.rglob("*") if p.is_dir())
        else:
            files, dirs = ([rel] if path.exists() else []), []
        self._log({"op": "files", "path": rel, "was_dir": path.is_dir(), "files": files, "dirs": dirs})
        for f in files:
            self._old(f).parent.mkdir(parents=True, exist_ok=True)
            try:
                os.link(self.release / f, self._old(f))
            except OSError:  # a file system without hard links: a copy (this one needs space)
                shutil.copy2(self.release / f, self._old(f))

    # --- ending -----------------------------------------------------------------------------------------
    def _close(self) -> None:
        if self._journal is not None:
            self._journal.close()
            self._journal = None

    def commit(self) -> None:
        """Make the changes final: what they replaced is deleted."""
        self._close()
        if self.folder.exists():
            if (self.folder / JOURNAL).exists():
                os.rename(self.folder / JOURNAL, self.folder / COMMITTED)  # a rename: needs no space
            shutil.rmtree(self.folder)

    def rollback(self) -> None:
        """Undo every journalled change, newest first; then delete the transaction folder."""
        self._close()
        journal = self.folder / JOURNAL
        entries = [json.loads(line) for line in journal.read_text().splitlines() if line.strip()] \
            if journal.exists() else []
        for entry in reversed(entries):
            target = self.release / entry["path"]
            if entry["op"] == "mkdir":
                try:
                    target.rmdir()
                except OSError:  # not empty (something else is in it) or gone already
                    pass
            elif entry["op"] == "dir":
                old = self._old(entry["path"])
                if entry["had"] and not old.exists():
                    continue  # it was never moved away: what is there is the original
                if target.exists():
                    shutil.rmtree(target)
                if entry["had"]:
                    os.rename(old, target)
            elif entry["op"] == "files":
                self._restore_files(entry, target)
            elif entry["op"] == "root":
                for p in self.release.iterdir():
                    if not p.is_dir() and p.name not in entry["files"]:
                        p.unlink()
        shutil.rmtree(self.folder, ignore_errors=True)

    def _restore_files(self, entry: dict[str, Any], target: Path) -> None:
        had = set(entry["files"])
        now = ([p for p in target.rglob("*") if not p.is_dir()] if target.is_dir() else
               ([target] if target.exists() else []))
        for p in now:  # created since
            if p.relative_to(self.release).as_posix() not in had:
                p.unlink()
        for f in entry["files"]:
            old = self._old(f)
            if old.exists():  # never linked means never touched
                (self.release / f).parent.mkdir(parents=True, exist_ok=True)
                os.replace(old, self.release / f)
        if target.is_dir():
            keep = set(entry["dirs"])
            for d in sorted((p for p in target.rglob("*") if p.is_dir()), reverse=True):
                if d.relative_to(self.release).as_posix() not in keep and not any(d.iterdir()):
                    d.rmdir()
            if not entry["was_dir"] and not any(target.iterdir()):
                target.rmdir()


def recover(release: Path, echo: Callable[[str], None] = print) -> list[str]:
    """Roll back the transactions a dead run left in ``release`` (finish deleting committed ones) and remove the
    staging folders it was filling. Call it holding the run lock. Returns one line per thing done (also echoed)."""
    release = Path(release)
    done = []
    if not release.is_dir():
        return done
    for folder in sorted(release.glob(f"{PREFIX}*")):
        if not folder.is_dir():
            continue
        if (folder / COMMITTED).exists():
            shutil.rmtree(folder)
            done.append(f"{folder.name}: finished deleting a committed publication of an interrupted run")
        else:
            ReleaseTransaction(release, folder).rollback()
            done.append(f"{folder.name}: rolled back the unfinished publication of an interrupted run")
    stale = [p for sub in ("actions", "relight") for pattern in (".tmp-*", ".old-*")
             for p in (release / sub).glob(pattern)]  # .old-*: the swaps of runs before transactions
    stale += list(release.glob(".tmp-root-*")) + list(release.glob(".write-probe-*"))
    for path in sorted(stale):
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
        done.append(f"{path.relative_to(release)}: removed what an interrupted run was writing")
    for line in done:
        echo(f"{'release':<12} {'recover':<8} {line}")
    return done
