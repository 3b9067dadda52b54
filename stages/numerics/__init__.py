"""Pure numeric functions of the stages (arrays in, arrays out; no file I/O)."""


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
