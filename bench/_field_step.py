"""The SDF field step that bench_hashgrid and bench_gpu time: one place, so both measure the same thing."""
from __future__ import annotations

from typing import Any, Callable


def training_points(cfg: Any) -> int:
    """Points one training step of ``cfg`` (an SDFConfig) evaluates the field at: every ray's samples and the
    eikonal points."""
    return cfg.rays_per_batch * cfg.samples_per_ray + cfg.eikonal_points


def field_step(cfg: Any, points: int, device: str = "cpu") -> tuple[Any, Any, Callable[[], None]]:
    """A field of ``cfg``'s encoding and network (table drawn from N(0, 0.01), seed 0) on ``device``, ``points``
    random points (seed 1) and the step: the field's SDF and analytic gradient at the points, an eikonal-style
    loss, backward and Adam (the SDF training step without the rays' compositing).

    Returns ``(field, x01 (N, 3) the points in the unit cube on the CPU, step)``."""
    import numpy as np
    import torch

    from stages.numerics.sdf import SDFField

    field = SDFField(np.array([[-0.5, -0.9, -0.5], [0.5, 0.9, 0.5]]), cfg.encoding, cfg.hidden_width,
                     cfg.hidden_layers)
    with torch.no_grad():
        field.encoding.table.normal_(0.0, 1e-2, generator=torch.Generator().manual_seed(0))
    field = field.to(device)
    x01 = torch.rand(points, 3, generator=torch.Generator().manual_seed(1))
    x_m = ((x01 - 0.5) * torch.tensor([1.0, 1.8, 1.0])).to(device)
    optimiser = torch.optim.Adam(field.parameters(), lr=1e-3)

    def step() -> None:
        sdf, grad = field.sdf_and_gradient(x_m, "analytic")
        loss = sdf.abs().mean() + 0.1 * ((grad.norm(dim=-1) - 1.0) ** 2).mean()
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()

    return field, x01, step
