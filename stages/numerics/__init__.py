"""Pure numeric functions of the stages (arrays in, arrays out; no file I/O)."""
from __future__ import annotations

import contextlib
from collections.abc import Iterator


def numeric_threads() -> int:
    """Threads a numeric kernel of this process may use: ``ULTRASTAGE_NUMERIC_THREADS`` when set (the
    executor splits the cores between its worker processes), else the CPUs available, at most 8."""
    import os

    env = os.environ.get("ULTRASTAGE_NUMERIC_THREADS")
    if env:
        return max(1, int(env))
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        n = os.cpu_count() or 1
    return max(1, min(n, 8))


@contextlib.contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Run the block with ``threads`` torch CPU threads and restore the previous count afterwards;
    0 leaves torch's setting alone (the configs' ``threads: 0`` default)."""
    import torch

    previous = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    try:
        yield
    finally:
        if threads:
            torch.set_num_threads(previous)
