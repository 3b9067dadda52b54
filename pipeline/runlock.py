"""One run at a time per release: a lock file in the run's work folder, held for the whole run.

``hold_run_lock(work)`` creates ``<work>/run.lock`` and holds an exclusive ``flock`` on it for as long as the
context lasts; the file says who holds it (pid, host, start time, command line). A second run on the same
work folder (the release's, by default ``<release>.work``) is refused at once with :class:`RunLockedError`,
which names the lock file and the run holding it, before it reads or writes anything.

The kernel drops a ``flock`` when its process dies, however it dies, so a lock file left behind by a killed
run holds no lock: the next run takes it over and says so in one line (naming the dead pid). A lock file
written on another host is not taken over (its process cannot be checked from here, and ``flock`` over a
network file system may not reach that host): the run is refused, with the host named, and the user removes
the file once no run is going. Within one process the lock is re-entrant, so a command that wraps a run
(run, then evaluate) may hold it around the whole and the run inside takes it again without refusing itself.
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from pipeline.errors import InputError

LOCK_NAME = "run.lock"

_held: dict[str, int] = {}
"""Lock files this process holds (resolved path -> nesting depth)."""


class RunLockedError(InputError):
    """Another run holds the work folder's lock; the message names the lock file and that run."""


def pid_alive(pid: int) -> bool:
    """Whether a process with this id exists on this host (signal 0: existence and permission check only)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, owned by someone else
        return True
    return True


def _read_holder(path: Path) -> dict:
    try:
        record = json.loads(path.read_text() or "{}")
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def _describe(holder: dict) -> str:
    if not holder:
        return "another run (its lock record is empty or unreadable)"
    return (f"run of pid {holder.get('pid')} on host {holder.get('host')}, started {holder.get('started_at')}"
            + (f" ({holder['command']})" if holder.get("command") else ""))


@contextlib.contextmanager
def hold_run_lock(work: str | Path, echo: Callable[[str], None] = print) -> Iterator[Path]:
    """Hold ``<work>/run.lock`` for the duration of the context; yields the lock file's path.

    Raises:
        RunLockedError: a live run holds the lock, or the lock file was written on another host.
    """
    import fcntl

    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    path = (work / LOCK_NAME).resolve()
    key = str(path)
    if key in _held:  # re-entrant within this process
        _held[key] += 1
        try:
            yield path
        finally:
            _held[key] -= 1
        return
    host = socket.gethostname()
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise
            raise RunLockedError(path, f"this release is being written by another {_describe(_read_holder(path))}; "
                                       "wait for it to finish (one run at a time per work folder)") from None
        # The holder before us may have removed the file between our open and our flock: then we hold a lock
        # on a file nobody else can see. Lock the file that is at the path now.
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        holder = _read_holder(path)
        if holder.get("pid") not in (None, os.getpid()):
            if holder.get("host") not in (None, host):
                raise RunLockedError(path, f"lock file written by a {_describe(holder)} on another host; "
                                           "remove it if no run is going there")
            state = "no longer running" if not pid_alive(int(holder["pid"])) else "alive but not holding it (pid reused)"
            echo(f"run lock {path}: taking over the stale lock of pid {holder['pid']} ({state}), "
                 f"started {holder.get('started_at')}")
        record = {"pid": os.getpid(), "host": host, "started_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                  "command": " ".join(sys.argv)[:500]}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
        os.fsync(fd)
        _held[key] = 1
        try:
            yield path
        finally:
            del _held[key]
            # unlink while still holding the flock, so no third run can lock the old file after we let go
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
    finally:
        os.close(fd)
