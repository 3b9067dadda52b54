"""Claim files: one process produces a cached result while the others that need it wait for it.

A claim is a file created exclusively beside the result (``<result>.claim``), holding the pid of the process that
produces the result; it is removed once the result is stored. A claim whose process is gone (or that is older than
the caller's limit) is stale and may be taken over. The sg fits' memo (:func:`stages.environments.fit_sg_memo`) and
the ground-truth visibility (:func:`synthetic.relight.prefetch_visibility`) share work between processes this way.
"""
from __future__ import annotations

import os
import time
from pathlib import Path


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
