"""Limit numpy's BLAS threads while the simulator runs.

The simulator's matrix products are skinny (3 or 9 columns, cache-sized chunks): BLAS threads do not pay
for them, and OpenBLAS's spinning worker threads make everything crawl when other processes share the
cores (measured on a busy 2-core machine: 47 s with 2 BLAS threads, 22 s with 1, for the default
capture). Embree's ray-casting threads are unaffected.
"""
from __future__ import annotations

import contextlib
import ctypes
from collections.abc import Iterator

_GETTERS = ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads", "openblas_get_num_threads64_",
            "openblas_get_num_threads")


def _openblas_handles() -> list[tuple[ctypes.CDLL, str]]:
    """(library, getter name) of every OpenBLAS loaded in this process (Linux; empty elsewhere)."""
    try:
        with open("/proc/self/maps", encoding="utf-8") as maps:
            paths = sorted({line.split()[-1] for line in maps if "openblas" in line.lower() and "/" in line})
    except OSError:
        return []
    handles = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for getter in _GETTERS:
            if hasattr(lib, getter) and hasattr(lib, getter.replace("get_", "set_")):
                handles.append((lib, getter))
                break
    return handles


@contextlib.contextmanager
def limit_blas_threads(limit: int = 1) -> Iterator[None]:
    """Run the body with at most `limit` BLAS threads (threadpoolctl when installed, else OpenBLAS's own
    setter through ctypes; a no-op when neither applies), restoring the previous counts after."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        threadpool_limits = None
    if threadpool_limits is not None:
        with threadpool_limits(limits=limit, user_api="blas"):
            yield
        return
    import numpy  # noqa: F401  (loads numpy's OpenBLAS so it can be found)

    saved = []
    for lib, getter in _openblas_handles():
        try:
            count = int(getattr(lib, getter)())
            getattr(lib, getter.replace("get_", "set_"))(ctypes.c_int(limit))
            saved.append((lib, getter, count))
        except (OSError, AttributeError, ValueError):
            continue
    try:
        yield
    finally:
        for lib, getter, count in saved:
            getattr(lib, getter.replace("get_", "set_"))(ctypes.c_int(count))
