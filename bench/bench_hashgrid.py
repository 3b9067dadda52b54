"""The hash encoding's fused CPU kernel against its torch path, in one process.

Times (CPU and wall seconds of this process, best of ``--repeats``) on the ``cpu`` SDF preset's encoding and field:

- ``encoding``: features and Jacobian of a training step's points (512 rays x 8 samples + 256 eikonal
  points), a loss on both, backward to the table;
- ``field step``: the field's SDF and analytic gradient at those points, an eikonal-style loss, backward and
  Adam (the SDF step without the rays' compositing);

each with the kernel (torch on one thread), the torch path on one thread and the torch path on two threads
(what the kernel's thread rule weighs, :data:`stages.numerics.hashgrid_kernel.MAX_TORCH_THREADS`: CPU and
wall time both), plus a
simple baseline: copying the feature table once (the memory traffic of touching every entry). The
difference between the two paths' outputs (features, Jacobian, table gradient) is the error column.
The proposal grid's march (each ray of a training step to its first crossing of the cached SDF) with the
kernel and with torch's chunked march, CPU time on one thread and whether their outputs are bit-identical.
Writes bench_hashgrid.json and bench_hashgrid.md. ``python bench/bench_hashgrid.py --out bench/out [--quick]``
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import _field_step  # noqa: E402


def _cpu_best(fn, repeats: int, inner: int) -> tuple[float, float]:
    """(CPU seconds, wall seconds) per call: the mean over ``inner`` calls of the repeat with the least CPU
    time, of ``repeats`` (after one warm-up call)."""
    fn()
    best = (float("inf"), float("inf"))
    for _ in range(repeats):
        cpu, wall = time.process_time(), time.perf_counter()
        for _ in range(inner):
            fn()
        best = min(best, ((time.process_time() - cpu) / inner, (time.perf_counter() - wall) / inner))
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="fewer repeats and points (the tests' mode)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    import torch

    from stages.numerics import hashgrid_kernel
    from stages.numerics.sdf import SDF_PRESETS

    cfg = SDF_PRESETS["cpu"]
    repeats, inner = (1, 1) if args.quick else (args.repeats, 10)
    points = 600 if args.quick else _field_step.training_points(cfg)
    field, x01, field_step = _field_step.field_step(cfg, points)
    encoding = field.encoding
    available = hashgrid_kernel.kernel_available()

    def use(kernel: bool) -> None:
        encoding._use_kernel = (lambda x: kernel)  # the choice under test, whatever the thread rule says

    def encode_step() -> None:
        encoding.table.grad = None
        features, jac = encoding(x01, True)
        (features.sum() + (jac * jac).sum()).backward()

    def outputs() -> list[torch.Tensor]:
        encoding.table.grad = None
        features, jac = encoding(x01, True)
        (features.sum() * 0.5 + (jac * jac).sum() * 1e-3).backward()
        return [features.detach(), jac.detach(), encoding.table.grad.clone()]

    table = encoding.table.detach()
    rows = []
    torch.set_num_threads(1)
    baseline = _cpu_best(lambda: table.clone(), repeats, inner)[0]
    for label, kernel, threads in (("kernel, 1 thread", True, 1), ("torch, 1 thread", False, 1),
                                   ("torch, 2 threads", False, 2)):
        if kernel and not available:
            continue
        torch.set_num_threads(threads)
        use(kernel)
        (encoding_cpu, encoding_wall), (step_cpu, step_wall) = (_cpu_best(encode_step, repeats, inner),
                                                                _cpu_best(field_step, repeats, inner))
        row = {"path": label, "threads": threads, "encoding_s": encoding_cpu, "encoding_wall_s": encoding_wall,
               "field_step_s": step_cpu, "field_step_wall_s": step_wall}
        rows.append(row)
    torch.set_num_threads(1)
    error = {}
    if available:
        use(True)
        ours = outputs()
        use(False)
        ref = outputs()
        error = {name: float((a - b).abs().max() / max(float(b.abs().max()), 1e-30))
                 for name, a, b in zip(("features", "jacobian", "table_gradient"), ours, ref)}
    reference = next((r for r in rows if r["path"] == "torch, 1 thread"), None)
    for row in rows:
        row["encoding_vs_table_copy"] = row["encoding_s"] / baseline
        if reference:
            row["encoding_speedup_vs_torch_1"] = reference["encoding_s"] / row["encoding_s"]
            row["field_step_speedup_vs_torch_1"] = reference["field_step_s"] / row["field_step_s"]
    march = _march(cfg, 64 if args.quick else cfg.rays_per_batch, repeats, inner) if available else None
    result = {"points": points, "kernel_available": available, "table_copy_s": baseline, "rows": rows,
              "max_relative_difference_kernel_vs_torch": error, "proposal_march": march, "quick": bool(args.quick)}
    (out / "bench_hashgrid.json").write_text(json.dumps(result, indent=1))
    lines = ["# bench_hashgrid: the hash encoding's CPU kernel against its torch path", "",
             f"{points} points per step (the cpu preset's rays x samples + eikonal points). CPU milliseconds of "
             "this process (all its threads; the speed-ups compare these), wall milliseconds beside them. "
             f"Baseline: copying the {tuple(table.shape)} table, {baseline * 1e3:.2f} ms CPU.", "",
             "| path | encoding fwd+bwd CPU ms (wall) | x table copy | field step CPU ms (wall) | "
             "CPU speed-up vs torch 1 thread (encoding / step) |",
             "|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['path']} | {row['encoding_s'] * 1e3:.2f} ({row['encoding_wall_s'] * 1e3:.2f}) | "
                     f"{row['encoding_vs_table_copy']:.1f} | {row['field_step_s'] * 1e3:.2f} "
                     f"({row['field_step_wall_s'] * 1e3:.2f}) | "
                     f"{row.get('encoding_speedup_vs_torch_1', float('nan')):.2f} / "
                     f"{row.get('field_step_speedup_vs_torch_1', float('nan')):.2f} |")
    if error:
        lines += ["", "Largest difference kernel vs torch, relative to the largest value: "
                  + ", ".join(f"{k} {v:.1e}" for k, v in error.items()) + "."]
    else:
        lines += ["", "No C compiler here: the kernel rows are missing."]
    if march:
        lines += ["", f"Proposal march (the SDF's cached-grid march to each ray's first crossing), {march['rays']} rays of a training "
                  f"step through a {march['grid']} grid of two spheres' SDF ({march['crossed_fraction']:.0%} of "
                  f"the rays cross): kernel {march['kernel_s'] * 1e3:.2f} ms, torch {march['torch_s'] * 1e3:.2f} ms "
                  f"CPU ({march['speedup']:.2f}x); outputs bit-identical: {march['identical']}."]
    (out / "bench_hashgrid.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def _march(cfg, n_rays: int, repeats: int, inner: int) -> dict:
    """The proposal grid's march with the kernel and with torch (one thread each) on rays from cameras 1.5 m
    away aimed at a body-sized box, the grid at the preset's voxel size holding two spheres' signed distance."""
    import numpy as np
    import torch

    from stages.numerics import hashgrid_kernel
    from stages.numerics.sdf import ProposalGrid

    bounds = np.array([[-0.4, -0.9, -0.5], [0.5, 0.9, 0.4]])
    grid = ProposalGrid(bounds, cfg.proposal_voxel_m, torch.device("cpu"))
    c = grid.centres
    grid.values.view(-1)[:] = torch.minimum((c - torch.tensor([0.0, 0.2, 0.0])).norm(dim=1) - 0.25,
                                            (c - torch.tensor([0.1, -0.4, 0.0])).norm(dim=1) - 0.15)
    gen = torch.Generator().manual_seed(2)
    origins = torch.rand(n_rays, 3, generator=gen) * torch.tensor([0.9, 1.8, 0.0]) + torch.tensor([-0.4, -0.9, -1.5])
    dirs = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.15 * torch.randn(n_rays, 3, generator=gen),
                                         dim=1)
    near = torch.full((n_rays,), 0.5)
    far = torch.full((n_rays,), 2.5)
    torch.set_num_threads(1)
    kernel_out = grid.first_crossing(origins, dirs, near, far)
    kernel_s = _cpu_best(lambda: grid.first_crossing(origins, dirs, near, far), repeats, inner)[0]
    available = hashgrid_kernel.kernel_available
    hashgrid_kernel.kernel_available = lambda: False  # the torch march, in the same process
    try:
        torch_out = grid.first_crossing(origins, dirs, near, far)
        torch_s = _cpu_best(lambda: grid.first_crossing(origins, dirs, near, far), repeats, inner)[0]
    finally:
        hashgrid_kernel.kernel_available = available
    identical = bool(torch.equal(kernel_out[0], torch_out[0]) and torch.equal(kernel_out[1], torch_out[1]))
    return {"rays": n_rays, "grid": "x".join(str(n) for n in grid.shape), "kernel_s": kernel_s, "torch_s": torch_s,
            "speedup": torch_s / kernel_s, "identical": identical,
            "crossed_fraction": float(torch_out[1].float().mean())}


if __name__ == "__main__":
    sys.exit(main())
