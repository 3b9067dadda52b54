"""The fused CPU hash-grid kernel against the encoding's torch path and a hand-computed case."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from stages.numerics import hashgrid_kernel
from stages.numerics.sdf import HashEncoding, HashGridConfig

pytestmark = pytest.mark.skipif(not hashgrid_kernel.kernel_available(), reason="no C compiler for the kernel")

# 2 dense levels and 3 hashed ones (table 2^9 per level), 2 features
CONFIG = HashGridConfig(levels=5, features_per_level=2, log2_table_size=9, base_resolution=4,
                        finest_resolution=40)


def _encoding(active: float) -> HashEncoding:
    enc = HashEncoding(CONFIG)
    with torch.no_grad():
        enc.table.copy_(torch.randn(enc.table.shape, generator=torch.Generator().manual_seed(1)))
    enc.set_active_levels(active)
    return enc


def _points(n: int = 300) -> torch.Tensor:
    x = torch.rand(n, 3, generator=torch.Generator().manual_seed(2))
    # the cube's faces and corners, and points outside it (clamped)
    x[:4] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.0, 0.5], [1.3, -0.2, 0.25]])
    return x


def _run(enc: HashEncoding, x: torch.Tensor, kernel: bool, jacobian: bool):
    enc._use_kernel = lambda x01: kernel  # type: ignore[method-assign]
    enc.table.grad = None
    features, jac = enc(x, jacobian)
    # a loss that weights every output differently, so each table entry's gradient is checked
    w = torch.linspace(-1.0, 1.0, features.numel()).view_as(features)
    loss = (features * w).sum()
    if jacobian:
        loss = loss + (jac * torch.cos(torch.arange(jac.numel(), dtype=torch.float32)).view_as(jac)).sum() * 0.01
    loss.backward()
    return features.detach(), (jac.detach() if jac is not None else None), enc.table.grad.clone()


@pytest.mark.parametrize("active", [5.0, 3.4, 1.0])
def test_kernel_equals_the_torch_path(active):
    enc, x = _encoding(active), _points()
    assert enc.n_dense == 2  # the config exercises both index kinds
    ours, ref = _run(enc, x, True, True), _run(enc, x, False, True)
    for got, want in zip(ours, ref):
        assert got.shape == want.shape
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5 * float(want.abs().max()))
    assert ref[2].abs().sum() > 0  # the gradient is not trivially zero
    if active < 5:  # levels switched off: zero features, zero Jacobian
        off = int(torch.ceil(torch.tensor(active))) * CONFIG.features_per_level
        assert torch.all(ours[0][:, off:] == 0) and torch.all(ours[1][:, :, off:] == 0)


def test_kernel_without_jacobian_equals_the_torch_path():
    enc, x = _encoding(5.0), _points()
    ours, ref = _run(enc, x, True, False), _run(enc, x, False, False)
    assert ours[1] is None and ref[1] is None
    torch.testing.assert_close(ours[0], ref[0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(ours[2], ref[2], rtol=1e-5, atol=1e-6)


def test_hand_computed_trilinear_value_and_slope():
    # one dense level of 2 cells per edge: a point at (0.25, 0.5, 0.75) lies in cell (0, 1, 1) at fractions
    # (0.5, 0, 0.5); with table value = the vertex's x index (feature 0) the feature is the x position in cells
    # (0.5) and its x derivative is res = 2 per unit cube; feature 1 = z index: 1.5, d/dz = 2.
    config = HashGridConfig(levels=1, features_per_level=2, log2_table_size=8, base_resolution=2,
                            finest_resolution=2)
    enc = HashEncoding(config)
    ix, iy, iz = torch.meshgrid(torch.arange(3), torch.arange(3), torch.arange(3), indexing="ij")
    row = (ix + iy * 3 + iz * 9).reshape(-1)
    with torch.no_grad():
        enc.table.zero_()
        enc.table[row, 0] = ix.reshape(-1).float()
        enc.table[row, 1] = iz.reshape(-1).float()
    features, jac = hashgrid_kernel.encode(enc.table.detach(), torch.tensor([[0.25, 0.5, 0.75]]), enc.res,
                                           enc.offsets, enc.n_dense, enc.hash_mask, enc.level_mask, 1, True)
    torch.testing.assert_close(features, torch.tensor([[0.5, 1.5]]))
    torch.testing.assert_close(jac[:, 0], torch.tensor([[2.0, 0.0], [0.0, 0.0], [0.0, 2.0]]))


def test_jacobian_matches_finite_differences_of_the_features():
    enc, x = _encoding(5.0), torch.rand(50, 3, generator=torch.Generator().manual_seed(3)) * 0.8 + 0.1
    table = enc.table.detach()
    args = (enc.res, enc.offsets, enc.n_dense, enc.hash_mask, enc.level_mask, 5)
    _, jac = hashgrid_kernel.encode(table, x, *args, True)
    h = 1e-4  # small against the finest cell (1/40), so the differences stay within one cell almost always
    for axis in range(3):
        step = torch.zeros(3)
        step[axis] = h
        plus, _ = hashgrid_kernel.encode(table, x + step, *args, False)
        minus, _ = hashgrid_kernel.encode(table, x - step, *args, False)
        numeric = (plus - minus) / (2 * h)
        close = (numeric - jac[axis]).abs() < 0.02 * (1 + jac[axis].abs())
        assert close.float().mean() > 0.97  # a few points straddle a cell boundary


def test_points_with_a_gradient_are_refused():
    enc = _encoding(5.0)
    x = torch.rand(4, 3, requires_grad=True)
    with pytest.raises(ValueError, match="must not require a gradient"):
        hashgrid_kernel.encode(enc.table, x, enc.res, enc.offsets, enc.n_dense, enc.hash_mask, enc.level_mask, 5,
                               False)
    assert not enc._use_kernel(x)  # the encoding takes its torch path for such points


@pytest.mark.parametrize("setting", ["forced", "unwritable cache"])
def test_the_torch_path_is_taken_when_forced_or_when_the_kernel_cannot_be_built(setting, tmp_path):
    code = "from stages.numerics import hashgrid_kernel as k; print(k.kernel_available())"
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    extra = ({"ULTRASTAGE_HASHGRID_KERNEL": "torch"} if setting == "forced"
             else {"ULTRASTAGE_KERNEL_CACHE": str(blocker / "kernels")})  # a folder under a regular file
    out = subprocess.run([sys.executable, "-c", code], env=os.environ | extra, capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"
    if setting != "forced":
        assert "the torch path is used" in out.stderr and "a_file" in out.stderr


def _proposal_grid():
    import numpy as np

    from stages.numerics.sdf import ProposalGrid

    bounds = np.array([[-0.4, -0.9, -0.5], [0.5, 0.9, 0.4]])
    grid = ProposalGrid(bounds, 0.05, torch.device("cpu"))
    c = grid.centres
    two_balls = torch.minimum((c - torch.tensor([0.0, 0.2, 0.0])).norm(dim=1) - 0.25,
                              (c - torch.tensor([0.1, -0.4, 0.0])).norm(dim=1) - 0.15)
    grid.values.view(-1)[:] = two_balls
    return grid


def _rays(n: int = 600):
    gen = torch.Generator().manual_seed(3)
    origins = torch.rand(n, 3, generator=gen) * torch.tensor([0.6, 1.2, 0.0]) + torch.tensor([-0.3, -0.6, -1.5])
    dirs = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.1 * torch.randn(n, 3, generator=gen), dim=1)
    near = torch.rand(n, generator=gen) * 0.5
    far = near + 0.5 + torch.rand(n, generator=gen) * 2.0
    near[:2] = far[:2] + 0.1  # empty intervals: no sample inside
    origins[2], dirs[2] = torch.tensor([0.0, 0.2, -1.0]), torch.tensor([0.0, 0.0, 1.0])  # straight at a ball
    return origins, dirs, near, far


def test_proposal_march_equals_the_torch_march(monkeypatch):
    grid = _proposal_grid()
    origins, dirs, near, far = _rays()
    t_kernel, crossed_kernel, min_kernel = grid.first_crossing(origins, dirs, near, far)
    monkeypatch.setattr(hashgrid_kernel, "kernel_available", lambda: False)
    t_torch, crossed_torch, min_torch = grid.first_crossing(origins, dirs, near, far)
    assert 50 < int(crossed_torch.sum()) < len(near) - 50  # both kinds of rays are exercised
    assert torch.equal(crossed_kernel, crossed_torch)
    assert torch.equal(t_kernel, t_torch)  # the same float operations, in the same order
    missed = ~crossed_torch
    assert torch.equal(min_kernel[missed], min_torch[missed])
    assert bool((min_kernel[crossed_kernel] <= 0).all())
    assert torch.equal(t_kernel[:2], near[:2]) and bool(torch.isinf(min_kernel[:2]).all())


def test_proposal_march_hand_computed_crossing():
    # a ray along +z through the first ball's centre: it enters the surface 0.25 m before the centre
    grid = _proposal_grid()
    origins, dirs = torch.tensor([[0.0, 0.2, -1.0]]), torch.tensor([[0.0, 0.0, 1.0]])
    near, far = torch.tensor([0.6]), torch.tensor([1.4])
    t, crossed, _ = grid.first_crossing(origins, dirs, near, far)
    assert bool(crossed[0])
    assert abs(float(t[0]) - 0.75) < 0.05 * 0.5  # within half a voxel of the true surface at t = 0.75


def test_proposal_march_refuses_bad_shapes():
    with pytest.raises(ValueError, match="grid must be"):
        hashgrid_kernel.march_first_crossing(torch.zeros(4, 4), torch.zeros(3), torch.ones(3), 0.1, 3,
                                             torch.zeros(1, 3), torch.zeros(1, 3), torch.zeros(1), torch.ones(1))
    with pytest.raises(ValueError, match="must agree"):
        hashgrid_kernel.march_first_crossing(torch.zeros(4, 4, 4), torch.zeros(3), torch.ones(3), 0.1, 3,
                                             torch.zeros(2, 3), torch.zeros(1, 3), torch.zeros(1), torch.ones(1))
