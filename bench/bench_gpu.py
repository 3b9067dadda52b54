"""The GPU section of the report: the production SDF preset's field step on the GPU against the CPU.

The geometry stage is the pipeline's GPU stage (``resources = {"GPU": 1}``; the ``production`` preset is its GPU
configuration). This bench times its field step, the part of a training step that the batch size scales: the
field's SDF and analytic gradient at a production step's points (``rays_per_batch x samples_per_ray +
eikonal_points``), an eikonal-style loss, backward and Adam, with the production preset's encoding and network.

Rows: torch on the CPU (one thread, the baseline, timed in the same process) and, where torch sees a CUDA
device, the same step on it (synchronised), with its speed-up over the CPU row. ``bench/bench_projection.py``
assumes a GPU speed-up over one CPU core; this is the measurement to put beside that assumption. Without a CUDA
device the report says so and shows the CPU row only.
Writes bench_gpu.json and bench_gpu.md. ``python bench/bench_gpu.py --out bench/out [--quick]``
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


def _best_ms(step, repeats: int, inner: int, synchronize) -> float:
    """Wall milliseconds per call: the best over ``repeats`` of the mean over ``inner`` calls, after a warm-up."""
    step()
    synchronize()
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(inner):
            step()
        synchronize()
        best = min(best, (time.perf_counter() - start) / inner)
    return best * 1e3


def field_step_ms(device: str, points: int, repeats: int, inner: int) -> float:
    """Milliseconds of one field step (:func:`_field_step.field_step`) of the production preset on ``device``
    ("cpu" or "cuda")."""
    import torch

    from stages.numerics.sdf import SDF_PRESETS

    _, _, step = _field_step.field_step(SDF_PRESETS["production"], points, device)
    synchronize = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    return _best_ms(step, repeats, inner, synchronize)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="a small batch and one repeat (the tests' mode)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    import torch

    from stages.numerics.sdf import SDF_PRESETS

    cfg = SDF_PRESETS["production"]
    points = 2048 if args.quick else _field_step.training_points(cfg)
    repeats, inner = (1, 1) if args.quick else (args.repeats, 3)
    torch.set_num_threads(1)
    rows = [{"device": "cpu", "name": "CPU, 1 thread", "field_step_ms": field_step_ms("cpu", points, repeats,
                                                                                           inner)}]
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    if gpu is not None:
        rows.append({"device": "cuda", "name": gpu,
                     "field_step_ms": field_step_ms("cuda", points, repeats, max(inner, 10))})
        rows[-1]["speedup_over_cpu_thread"] = rows[0]["field_step_ms"] / rows[-1]["field_step_ms"]
    result = {"points": points, "gpu": gpu, "rows": rows, "quick": bool(args.quick)}
    (out / "bench_gpu.json").write_text(json.dumps(result, indent=1))
    lines = ["# bench_gpu: the production SDF's field step on the GPU against one CPU thread", "",
             f"{points} points per step (the production preset's rays x samples + eikonal points), its encoding "
             f"({cfg.encoding.levels} levels, 2^{cfg.encoding.log2_table_size} entries) and network; wall "
             "milliseconds per step, best of the repeats.", "",
             "| device | field step ms | speed-up over 1 CPU thread |", "|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['name']} | {row['field_step_ms']:.2f} | "
                     f"{row.get('speedup_over_cpu_thread', 1.0):.1f} |")
    if gpu is None:
        lines += ["", "No CUDA device here (torch sees none): the GPU row is measured where one is present; "
                  "bench_projection's GPU speed-up stays an assumption until then."]
    (out / "bench_gpu.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
