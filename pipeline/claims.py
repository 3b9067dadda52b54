"""Claim files: one process produces a cached result while the others that need it wait for it.

A claim is a file created exclusively beside the result (``<result>.claim``), holding the pid of the process that
produces the result; it is removed once the result is stored. A claim whose process is gone (or that is older than
the caller's limit) is stale and may be taken over. The sg fits' memo (:func:`stages.environments.fit_sg_memo`) and
the ground-truth visibility (:func:`synthetic.relight.prefetch_visibility`) share work between processes this way.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


def try_claim(claim: Path) -> bool:
    """Create ``claim`` holding this process's pid; False when it exists already (another process holds it).
    OSError (e.g. an unwritable folder) is the caller's."""
    try:
        fd = os.open(claim, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return False
    try:
        os.write(fd, str(os.getpid()).encode())
    finally:
        os.close(fd)
    return True


def claim_is_stale(claim: Path, stale_after_s: float) -> bool:
    """Whether a claim file's process is gone (its pid is not running here) or the claim is older than
    ``stale_after_s`` seconds. False while the file is being written or was just removed: look again."""
    try:
        pid = int(claim.read_text().strip() or "0")
        age = time.time() - claim.stat().st_mtime
    except (OSError, ValueError):
        return False
    if age > stale_after_s:
        return True
    if pid <= 0:
        return False  # created, pid not written yet
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # e.g. PermissionError: a live process of another user
        return False
    return False


def await_or_claim(stored: Callable[[], T | None], claim: Path, stale_after_s: float, wait: bool = True,
                   poll_s: float = 0.1) -> tuple[T | None, bool]:
    """Wait until ``stored()`` gives the result or this process holds ``claim``: ``(result, False)`` once it is
    stored (by another process, or between the look and the claim), ``(None, True)`` when this process must
    produce it (store it, then remove ``claim``), ``(None, False)`` when another live process holds the claim and
    ``wait`` is False. A stale claim (:func:`claim_is_stale`) is removed and claimed again. OSError from creating
    the claim (e.g. an unwritable folder) is the caller's."""
    while (result := stored()) is None:
        if try_claim(claim):
            result = stored()
            if result is not None:
                claim.unlink(missing_ok=True)
            return result, result is None
        if claim_is_stale(claim, stale_after_s):
            claim.unlink(missing_ok=True)
        elif not wait:
            return None, False
        else:
            time.sleep(poll_s)
    return result, False
