"""The dask executor's cost for numeric work: one workload in this process and in local-cluster workers.

The workload is the SDF's training step without cameras: a hash-grid SDF field (the ``cpu`` preset's
encoding and MLP) fitted to a sphere's distance on random points, with the analytic gradient, an eikonal
term, backward and Adam; one torch thread, as each worker of the default 2-core cluster gets. Timed (best
of ``--repeats``) in three places:

- ``in_process``: here (the baseline);
- ``worker``: a worker of :class:`pipeline.graph.DaskExecutor` (what ``make dataset`` uses);
- ``worker_dask_default``: a worker of a plain ``LocalCluster``, whose nanny sets dask's default
  ``MALLOC_TRIM_THRESHOLD_=65536``: freed memory goes back to the OS at once and every step faults its
  tensors' pages in again.

Reports seconds and the ratio of each worker to the in-process run (goal: close to 1). Writes
bench_executor.json. ``python bench/bench_executor.py --out bench/out [--steps 150 --points 4096] [--quick]``;
``--quick`` (the tests' mode): 5 steps on 512 points, once in each place; the numbers are not measurements.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _quick import QUICK_HELP  # noqa: E402


def sdf_steps(steps: int, points: int, seed: int = 0) -> float:
    """Seconds for ``steps`` training steps of the cpu preset's SDF field on ``points`` random points."""
    import numpy as np
    import torch

    from stages.numerics.sdf import SDF_PRESETS, SDFField

    torch.set_num_threads(1)
    torch.manual_seed(seed)
    cfg = SDF_PRESETS["cpu"]
    field = SDFField(np.array([[-0.5, -0.9, -0.5], [0.5, 0.9, 0.5]]), cfg.encoding, cfg.hidden_width,
                     cfg.hidden_layers)
    optimiser = torch.optim.Adam(field.parameters(), lr=1e-3)
    generator = torch.Generator().manual_seed(seed)
    start = time.perf_counter()
    for _ in range(steps):
        x = (torch.rand((points, 3), generator=generator) - 0.5) * torch.tensor([1.0, 1.8, 1.0])
        sdf, grad = field.sdf_and_gradient(x, "analytic")
        target = x.norm(dim=-1) - 0.3
        loss = (sdf.reshape(-1) - target).abs().mean() + 0.1 * ((grad.norm(dim=-1) - 1.0) ** 2).mean()
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
    return time.perf_counter() - start


def _best(fn, repeats: int) -> float:
    return min(fn() for _ in range(repeats))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="bench/out")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--points", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    if args.quick:
        args.steps, args.points, args.repeats = 5, 512, 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    from distributed import Client, LocalCluster

    from pipeline.graph import DaskExecutor

    seconds = {"in_process": _best(lambda: sdf_steps(args.steps, args.points), args.repeats)}
    executor = DaskExecutor(workers=1)
    try:
        seconds["worker"] = _best(lambda: executor.client.submit(sdf_steps, args.steps, args.points,
                                                                 pure=False).result(), args.repeats)
    finally:
        executor.client.close()
        executor.cluster.close()
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        seconds["worker_dask_default"] = _best(lambda: client.submit(sdf_steps, args.steps, args.points,
                                                                     pure=False).result(), args.repeats)
    report = {"steps": args.steps, "points": args.points, "repeats": args.repeats, "quick": args.quick,
              "seconds": {k: round(v, 3) for k, v in seconds.items()},
              "ratio_to_in_process": {k: round(v / seconds["in_process"], 3) for k, v in seconds.items()}}
    (out / "bench_executor.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
