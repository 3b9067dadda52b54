"""The neural SDF and the appearance field on CUDA: a few training steps on the tiny analytic problems of
test_sdf.py and test_appearance_field.py, run on ``device="cuda"``. Skipped, with the reason, where torch sees no
CUDA device (every other test forces the CPU, so these are the only ones that exercise the GPU path).

Each check is a function of the device (``check_*``), so that the same assertions can be run on the CPU by hand
(``python -c "from tests.unit.numerics.test_cuda_paths import *; check_sdf_trains('cpu')"``); the bounds are
the CPU's values with the margin given beside each."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from stages.numerics.appearance_field import (
    AppearanceField,
    render_appearance,
    sample_training_pixels,
    train_appearance_field,
)
from stages.numerics.metrics import angular_error_deg
from stages.numerics.sdf import SDF_PRESETS, SDFField, render_view, train_sdf
from tests.unit.numerics.test_appearance_field import BOUNDS as FIELD_BOUNDS
from tests.unit.numerics.test_appearance_field import CONFIG as FIELD_CONFIG
from tests.unit.numerics.test_appearance_field import HELDOUT_CAMERA, SIZE, camera, render_by_hand, sphere_sdf
from tests.unit.numerics.test_appearance_field import training_views
from tests.unit.numerics.test_sdf import BOUNDS as SDF_BOUNDS
from tests.unit.numerics.test_sdf import RADIUS, sphere_views, surface_radius

NO_CUDA = "torch sees no CUDA device (torch.cuda.is_available() is False): the GPU path is not exercised here"
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason=NO_CUDA)


def _devices_of(module: torch.nn.Module) -> set[str]:
    return {p.device.type for p in module.parameters()} | {b.device.type for b in module.buffers()}


def _finite_history(history: dict[str, list]) -> None:
    bad = [k for k, values in history.items() if not all(np.isfinite(v) for v in values)]
    assert not bad, f"non-finite values in the training history: {bad}"


# ------------------------------------------------------------------------------------------------ neural SDF

def check_sdf_trains(device: str) -> None:
    """The ``test`` SDF preset on 8 analytic 40x40 sphere views trains on ``device``: finite losses that fall, the
    field on the device while it trains (the checkpoints) and on the CPU when returned, the sphere's radius found
    and its silhouette rendered back."""
    config = dataclasses.replace(SDF_PRESETS["test"], device=device)
    seen: list[set[str]] = []
    views = sphere_views()
    result = train_sdf(views, config, bounds=SDF_BOUNDS,
                       checkpoint=lambda it, field: seen.append(_devices_of(field)))
    history = result.history
    _finite_history(history)
    assert len(history["normal"]) >= 3
    # CPU: the normal loss falls to 0.15 of its first value (bound 0.3)
    assert history["normal"][-1] < 0.3 * history["normal"][0], history["normal"]
    assert history["loss"][-1] < history["loss"][0], history["loss"]
    assert result.stats["device"].startswith(device) and result.stats["iterations"] == config.iterations
    assert seen and all(devices == {device} for devices in seen), seen
    assert _devices_of(result.field) == {"cpu"}  # returned on the CPU (SDFResult's contract)
    # CPU: radius off by 2.3 mm, spread 0.7 mm (bounds 6 and 3 mm: the GPU sums in another order)
    mean, spread = surface_radius(result.field)
    assert abs(mean - RADIUS) < 0.006 and spread < 0.003, (mean, spread)
    # the trained field's silhouette from the first camera is the sphere's (CPU: IoU 0.976; bound 0.95)
    view = views[0]
    out = render_view(result.field, view.K, view.cam_from_world, *view.mask.shape)
    assert all(np.isfinite(v).all() for v in out.values())
    hit = out["opacity"] > 0.5
    assert (hit & view.mask).sum() / (hit | view.mask).sum() > 0.95


def check_sdf_field_same_on_device(device: str) -> None:
    """One field evaluated on ``device`` gives the CPU's signed distances and analytic gradients (float32
    rounding), on the device."""
    torch.manual_seed(0)
    config = SDF_PRESETS["test"]
    field = SDFField(SDF_BOUNDS, config.encoding, config.hidden_width, config.hidden_layers).eval()
    moved = SDFField.from_state(field.to_state()).to(device).eval()
    assert _devices_of(moved) == {device}
    points = torch.from_numpy(np.random.default_rng(0).uniform(-0.4, 0.4, (2000, 3)).astype(np.float32))
    sdf_cpu, grad_cpu = field.sdf_and_gradient(points)
    sdf_dev, grad_dev = moved.sdf_and_gradient(points.to(device))
    assert sdf_dev.device.type == device and grad_dev.device.type == device
    sdf_dev, grad_dev = sdf_dev.detach().cpu().numpy(), grad_dev.detach().cpu().numpy()
    assert np.isfinite(sdf_dev).all() and np.isfinite(grad_dev).all()
    np.testing.assert_allclose(sdf_dev, sdf_cpu.detach().numpy(), atol=1e-4)
    np.testing.assert_allclose(grad_dev, grad_cpu.detach().numpy(), atol=1e-3)


@needs_cuda
def test_sdf_trains_on_cuda():
    check_sdf_trains("cuda")


@needs_cuda
def test_sdf_field_gives_the_cpu_values_on_cuda():
    check_sdf_field_same_on_device("cuda")


# ------------------------------------------------------------------------------------------------ appearance field

def check_appearance_field_trains(device: str) -> None:
    """The ``test`` appearance preset on 6 hand-rendered 40x40 views of the sphere trains on ``device``: finite
    losses that fall, the field on the device while it trains, the held-out view's albedo and normals back."""
    config = dataclasses.replace(FIELD_CONFIG, device=device)
    seen: list[set[str]] = []
    result = train_appearance_field(training_views(), sphere_sdf, config, bounds=FIELD_BOUNDS,
                                    checkpoint=lambda it, field: seen.append(_devices_of(field)))
    history = result.history
    _finite_history(history)
    # CPU: they fall to 0.033 (normals) and 0.021 (albedo) of their first values (bound 0.1)
    assert history["normal_deg"][-1] < 0.1 * history["normal_deg"][0], history["normal_deg"]
    assert history["albedo_l1"][-1] < 0.1 * history["albedo_l1"][0], history["albedo_l1"]
    assert history["loss"][-1] < history["loss"][0]
    assert result.stats["device"].startswith(device)
    assert seen and all(devices == {device} for devices in seen), seen
    assert _devices_of(result.field) == {"cpu"}  # returned on the CPU (AppearanceResult's contract)
    K, T = camera(*HELDOUT_CAMERA)
    truth = render_by_hand(K, T)
    out = render_appearance(result.field, sphere_sdf, K, T, SIZE, SIZE, config=config, bounds=FIELD_BOUNDS)
    both = out["valid"] & truth["mask"]
    assert both.sum() >= 0.93 * truth["mask"].sum()  # CPU: 0.961
    # CPU: albedo error 0.0017, normals 1.27 deg mean (bounds 0.005 and 2.5 deg)
    assert np.abs(out["albedo"] - truth["albedo"])[both].mean() < 0.005
    assert angular_error_deg(out["normals_world"], truth["normal"])[both].mean() < 2.5


def check_appearance_samples_on_device(device: str) -> None:
    """The training pixels' samples made on ``device`` are the CPU's (same surface crossings, float32 rounding)."""
    on_cpu = sample_training_pixels(training_views(), sphere_sdf, dataclasses.replace(FIELD_CONFIG, device="cpu"),
                                    bounds=FIELD_BOUNDS)
    on_device = sample_training_pixels(training_views(), sphere_sdf, dataclasses.replace(FIELD_CONFIG, device=device),
                                       bounds=FIELD_BOUNDS)
    assert len(on_device.points) == len(on_cpu.points) > 0
    for name in ("points", "weights"):
        a, b = np.asarray(getattr(on_device, name)), np.asarray(getattr(on_cpu, name))
        assert np.isfinite(a).all(), name
        np.testing.assert_allclose(a, b, atol=1e-4, err_msg=name)


def check_appearance_field_same_on_device(device: str) -> None:
    """A fresh field rendered on ``device`` gives the CPU's rendering."""
    torch.manual_seed(0)
    fresh = AppearanceField(FIELD_BOUNDS, FIELD_CONFIG.encoding, FIELD_CONFIG.hidden_width, FIELD_CONFIG.hidden_layers)
    K, T = camera(*HELDOUT_CAMERA)
    cpu = render_appearance(fresh, sphere_sdf, K, T, SIZE, SIZE, config=FIELD_CONFIG, bounds=FIELD_BOUNDS)
    dev = render_appearance(fresh, sphere_sdf, K, T, SIZE, SIZE,
                            config=dataclasses.replace(FIELD_CONFIG, device=device), bounds=FIELD_BOUNDS)
    assert (cpu["valid"] == dev["valid"]).mean() > 0.999
    both = cpu["valid"] & dev["valid"]
    for name in ("albedo", "normals_world"):
        assert np.isfinite(dev[name]).all(), name
        np.testing.assert_allclose(dev[name][both], cpu[name][both], atol=1e-3, err_msg=name)


@needs_cuda
def test_appearance_field_trains_on_cuda():
    check_appearance_field_trains("cuda")


@needs_cuda
def test_appearance_samples_on_cuda_are_the_cpus():
    check_appearance_samples_on_device("cuda")


@needs_cuda
def test_appearance_field_renders_on_cuda_as_on_the_cpu():
    check_appearance_field_same_on_device("cuda")
