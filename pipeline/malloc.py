"""glibc malloc settings for the pipeline's processes: large temporaries reused from the heap, not mapped anew.

glibc serves an allocation above its mmap threshold (at most 32 MiB, however it adapts) with a fresh ``mmap`` and
gives it back with ``munmap`` when freed, so every page of it faults in again the next time. The SDF's training
steps, the simulator's ray chunks and the evaluation's renders allocate and free arrays of tens of MiB thousands of
times: a cold ``make dataset`` took 9.3 million minor page faults and 35.6 s of system time. With the threshold at
256 MiB, the heap's top kept up to 512 MiB before it is trimmed and grown 64 MiB at a time, the same run took 1.27
million faults and 16.9 s (``ultrastage run`` on the default capture, the same figures to the last digit).
Arrays above 256 MiB (the production preset's full-resolution images) are still mapped and unmapped.
"""
from __future__ import annotations

import os
import sys

MALLOC_SETTINGS: dict[str, tuple[int, int]] = {
    "MALLOC_MMAP_THRESHOLD_": (-3, 256 << 20),
    "MALLOC_TRIM_THRESHOLD_": (-1, 512 << 20),
    "MALLOC_TOP_PAD_": (-2, 64 << 20),
}
"""Environment variable glibc reads at a process's start -> (its ``mallopt`` parameter, the value set)."""


def tune_malloc() -> dict[str, int]:
    """Apply :data:`MALLOC_SETTINGS` to this process (``mallopt``) and to the processes it starts (the
    environment: dask's workers, the evaluation's, the truth prefetch). A variable already in the environment is
    the user's choice: left as it is, and glibc applied it to this process at its start. Returns what was set here
    ({} off glibc, e.g. macOS or musl, where nothing is changed)."""
    if not sys.platform.startswith("linux"):
        return {}
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return {}
    applied = {}
    for variable, (parameter, value) in MALLOC_SETTINGS.items():
        if variable in os.environ:
            continue
        if mallopt(ctypes.c_int(parameter), ctypes.c_int(value)) == 1:
            os.environ[variable] = str(value)
            applied[variable] = value
    return applied
