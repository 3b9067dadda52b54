"""Thread setup shared by the benches that time torch numerics on a possibly shared machine."""
from __future__ import annotations

import os


def set_numeric_threads(threads: int) -> None:
    """Use ``threads`` OpenMP/torch threads, with sleeping rather than spinning OpenMP workers: on a machine
    shared with other busy processes, spinning torch threads made a 2-thread roughness fit 7-20x slower than
    1 thread (30-80 s vs 4.3 s); passive: 3.6 s. Must run before torch is first imported."""
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import torch

    torch.set_num_threads(threads)
