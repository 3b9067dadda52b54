"""Normal-supervised neural SDF: NeuS volume rendering over a multiresolution hash encoding (pure PyTorch).

The field is Instant-NSR style: an Instant-NGP hash grid (``L`` levels of ``F`` features, dense tables
for the coarse levels that fit) feeding a small softplus MLP that outputs the signed distance in metres
(negative inside). It is trained from the light stage's photometric normal maps instead of RGB:

* **normal loss** on valid pixels: ``|n_r/|n_r| - n|_1 + (1 - cos(n_r, n))`` between the rendered normal
  ``n_r`` (NeuS weights compositing the normalised SDF gradients along the ray) and the photometric normal
  ``n``, both in the stage frame. The L1 compares directions: on ``n_r`` itself it would also push every valid
  pixel's opacity to 1, which nothing balances on the mask's outer side, and the surface creeps outwards at
  silhouettes (a sphere came out 1.6 cm too large). Grazing pixels (``|n . d| < grazing_cos_min``, or a
  normal facing away from the camera) and the worst ``outlier_fraction`` of each batch's residuals are dropped;
* **mask loss**: BCE of the accumulated opacity against the foreground mask. The opacity is the whole ray's
  (``before_window``): a ray that grazes the silhouette gathers most of it before the sampling window, and a
  window-only opacity there pulls the surface outwards;
* **eikonal** regulariser ``(|grad f| - 1)^2`` on the ray samples and on random points of the box, and a
  **hull prior** ``relu(d_hull - f)`` (the subject lies inside its visual hull) against spurious surfaces in
  space no drawn ray crosses.

The returned field is an exponential moving average of the parameters over the second half of training
(Adam's steps make the surface jitter by about a millimetre between steps).

Empty space is skipped twice. The visual hull of the masks (:mod:`stages.numerics.hull`) bounds the volume
(tight box), chooses the rays worth drawing (pixels whose ray meets the hull or lies on the mask; every
other ray has opacity 0 against a 0 mask and costs nothing), and initialises the SDF (a few hundred cheap
regression steps to the signed distance of the classic, centre-test hull). During training a cached coarse SDF grid, refreshed from
the network every ``proposal_update_every`` steps, plays the role of NeuS's coarse pass: marching it
(trilinear look-ups, no network) finds each ray's first zero crossing, and the ``samples_per_ray`` network
samples are placed in a narrow window around it. NeuS's section-wise alpha (from the SDF and its gradient at
each sample) is exact for a plane whatever the spacing, so a handful of samples per ray is enough.

Gradients of the SDF (normals, eikonal) are computed analytically without double backward through the
hash table: the encoding returns its spatial Jacobian from the same gathered corner features (the
derivative of trilinear weights), and the MLP pushes that Jacobian forward alongside its values (forward-mode,
three tangents). Everything stays first order for autograd. ``gradient="finite_difference"`` (central
differences, Neuralangelo) and ``gradient="autograd"`` (double backward) are kept for comparison
(bench/bench_geometry.py measures them).

Reproducibility: all random numbers come from generators seeded with ``config.seed`` on the CPU, so the
same seed on the CPU gives the same weights bit for bit (torch's CPU kernels used here are deterministic).
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Literal, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from pipeline.config import Documented, checked, to_dict
from stages.numerics import torch_threads
from stages.numerics import hashgrid_kernel
from stages.numerics.hull import HullGrid, check_camera, default_stage_box, subject_box, visual_hull
from stages.numerics.neural_fields import (HashEncoding, HashGridConfig, check_bounds, check_view_list, check_view_map,
                                           instant_ngp_adam, lr_factor, neus_composite, neus_opacity_before, ray_box,
                                           resolve_device)
from artifacts.camera import camera_centre, pixel_coordinates, pixel_rays

__all__ = [
    "HashGridConfig",
    "SDFConfig",
    "SDF_PRESETS",
    "SDFView",
    "SDFResult",
    "HashEncoding",
    "SDFField",
    "train_sdf",
    "render_view",
    "mask_centre",
    "subject_footprint_m",
    "resolve_device",
    "default_stage_box",
    "fit_to_signed_distance",
]

_SOFTPLUS_BETA = 100.0  # NeuS / IDR: a smooth ReLU whose curvature does not blur a metre-scale SDF

# Schedule and sampling constants of the SDF's training. They are not settings: no preset, test, bench or user
# turns them, and every preset's schedule (cpu, production, test) runs with these values.
_MLP_LR_FACTOR = 0.1
"""The MLP's learning rate is the hash table's times this (Adam moves every parameter by about its learning rate
per step: the output layer's bias is a global offset of the surface, keep it slow)."""
_EMA_DECAY = 0.99
"""Exponential moving average of the parameters over the last steps (Polyak averaging); the result is the
averaged field. Adam's per-step moves make the surface jitter by about a millimetre from one step to the next;
the average removes it."""
_EMA_START = 0.5
"""Fraction of the steps after which the average starts (all hash levels are on by then)."""
_CURVATURE_STEP_M = 0.005
"""Offset of the smoothness term's second point, metres (used only when ``weight_curvature`` > 0)."""
_HULL_INIT_LR = 1e-2
"""Adam learning rate of the hull regression (the default ``learning_rate`` of the rendering losses)."""
_PROPOSAL_BAND_M = 0.06
"""A refresh of the cached SDF grid re-evaluates only the cells whose cached |SDF| is below this (metres); the
surface must not move farther than that between two refreshes."""
_WINDOW_SHARPNESS = 8.0
"""Sampling-window half-width in units of the NeuS transition width ``1 / inv_s``: the logistic density is
about 1.3e-3 of its peak there (``4 exp(-8)``)."""
_INV_S_RAMP = 0.7
"""Fraction of the steps over which ``inv_s`` ramps to ``inv_s_end``; then kept there to the end."""


# ------------------------------------------------------------------------------------------------ config


@dataclass(frozen=True)
class SDFConfig(Documented):
    """Training of the normal-supervised SDF (see the module docstring)."""

    not_in_key = ("device", "threads", "log_every")

    encoding: HashGridConfig = HashGridConfig()
    """The hash encoding."""
    hidden_width: int = checked(64, ge=1)
    """Width of the MLP's hidden layers."""
    hidden_layers: int = checked(2, ge=0)
    """Number of hidden layers of the MLP (softplus, beta 100)."""
    iterations: int = checked(1800, ge=1)
    """Training steps with the rendering losses (after the hull pre-fit)."""
    rays_per_batch: int = checked(512, ge=1)
    """Rays drawn per step from the pixels worth drawing (on the mask or meeting the hull)."""
    samples_per_ray: int = checked(8, ge=1)
    """Network samples per ray, stratified over the window around the ray's first zero crossing."""
    learning_rate: float = checked(1e-2, gt=0.0)
    """Adam learning rate (hash table and MLP) after warm-up."""
    warmup_iterations: int = checked(50, ge=0)
    """Linear learning-rate warm-up (steps)."""
    weight_normal: float = checked(1.0, ge=0.0)
    """Weight of the normal loss ``|n_r - n|_1 + (1 - cos)`` (mean over the valid rays kept)."""
    weight_mask: float = checked(0.1, ge=0.0)
    """Weight of the mask BCE (mean over the rays drawn)."""
    weight_eikonal: float = checked(0.1, ge=0.0)
    """Weight of the eikonal term ``(|grad f| - 1)^2`` (mean over ray samples and random points)."""
    weight_curvature: float = checked(0.0, ge=0.0)
    """Weight of a smoothness term ``|n(x) - n(x + e)|^2`` between unit SDF normals at each opaque ray's surface
    sample ``x`` and at a random offset ``|e| = _CURVATURE_STEP_M`` (0 = off). It damps the photometric normals'
    noise and the surface's high frequencies; one extra gradient evaluation per ray."""
    importance_fraction: float = checked(0.0, ge=0.0, lt=1.0)
    """Share of each batch's rays drawn in proportion to the views' :attr:`SDFView.sample_weight` (the rest
    uniformly from every ray worth drawing); 0 = uniform only. Views without weights count as weight 0."""
    before_window: Literal["none", "opacity", "opacity_and_normal"] = "opacity_and_normal"
    """What counts of the NeuS mass a ray gathers on its way to its sampling window
    (:func:`stages.numerics.neural_fields.neus_opacity_before`): ``none``, the window's samples alone; ``opacity``,
    it counts in the mask loss's opacity (the whole ray's, NeuS's ``1 - Phi(min f)``); ``opacity_and_normal``, it
    also counts in the rendered normal, at the first sample's normal (the sample nearest to it). The window of a
    ray grazing the silhouette starts where the SDF is within a fraction of a mm of its minimum, so a window-only
    opacity is far too low just inside the outline (0.11 instead of 0.69 a millimetre inside a 15 cm sphere at
    ``inv_s`` 800 with an 8 mm window) and the mask loss pulls the surface outwards. On the subject panel's seven
    plain bodies (cpu preset) the mean Chamfer is 1.35 mm with ``none``, 1.28 with ``opacity`` and 1.17 with
    ``opacity_and_normal``. The first sample stands for the mass before the window only where the surface curves
    gently over the window's length: the test preset (3 cm windows at ``inv_s`` 150) takes ``opacity`` (gate
    capture Chamfer 6.82 / 6.57 / 7.07 mm), and on the ICT head (about 1.2 mm pixels, its surface already 0.5-1 mm
    inside the truth) the comparable Chamfer is 0.69 / 0.76 / 0.88 mm."""
    weight_hull: float = checked(1.0, ge=0.0)
    """Weight of the hull prior ``relu(d_hull(x) - f(x))`` at sample and random points outside the hull: the
    subject lies inside its visual hull, so the SDF there is at least the distance to the hull. It keeps
    spurious surfaces out of space that no drawn ray crosses."""
    eikonal_points: int = checked(256, ge=0)
    """Random points per step, uniform in the bounds, for the eikonal term (besides the ray samples)."""
    grazing_cos_min: float = checked(0.15, ge=0.0, lt=1.0)
    """Pixels whose photometric normal is this close to perpendicular to the view ray (``|n . d|`` below it)
    or faces away from the camera get no normal loss: their photometric normal is unreliable and a pixel
    there spans a long stretch of surface."""
    weight_free_space: float = checked(100.0, ge=0.0)
    """Weight of the free-space term ``relu(-f(x))`` (metres) at points of the rays whose views give a
    :attr:`SDFView.free_depth_m`, in the last ``free_space_span_m`` before that depth: space a camera is known to
    see through is outside the subject. It acts only where views give free depths. The term is about 0.01 where a
    surface a centimetre deep is to be carved, against a normal loss of 0.1-0.5: on the skirt's cavity, in
    bench/bench_free_space.py's rounds run once at a weight of 1 (a one-off script), the flagged pixels and the
    share of the mesh seen through stayed (1,719 -> 1,486 px, 10.5 -> 10.6% in three rounds); at 100 that share
    fell to 8.4%."""
    free_space_span_m: float = checked(0.05, gt=0.0)
    """Length of the stretch before each ray's free depth that the free-space term samples, metres."""
    outlier_fraction: float = checked(0.05, ge=0.0, lt=1.0)
    """Share of each batch's valid rays with the largest normal residual left out of the normal loss
    (specular highlights, occlusion, wrong masks)."""
    normal_supervision: bool = True
    """False: mask and eikonal losses only (the mask-only ablation)."""
    hull_resolution: int = checked(96, ge=1)
    """Voxels per axis of the visual hull over the tight bounds (and of the coarse hull over the stage box
    that finds them when no bounds are given)."""
    hull_max_misses: int = checked(1, ge=0)
    """A hull voxel may fall outside the (dilated) masks of this many views that see it."""
    hull_dilate_px: float = checked(2.0, ge=0.0)
    """Extra mask dilation of the hull test, pixels (beyond the voxel's own projected size)."""
    hull_component_views: float = checked(0.5, ge=0.0, le=1.0)
    """Hull components whose best voxel is inside the masks of fewer than this share of the views that hold the
    hull's best voxel are not the subject (:func:`stages.numerics.hull.visual_hull`'s ``component_views``): pockets
    of space next to the cameras, which the views behind the subject hold inside its silhouette. On the ICT head
    (cameras 0.54 m from it) the head is held by all 32 views and such pockets by at most 7; kept, they would make
    the SDF's box 0.86 m wide for a 0.34 m head."""
    hull_margin_m: float = checked(0.03, ge=0.0)
    """The SDF's bounds are the hull's bounding box grown by this margin."""
    hull_init_tight: bool = True
    """Pre-fit to the classic visual hull (voxel centres inside the masks, dilated by ``hull_init_dilate_px``)
    instead of the conservative one that bounds the samples: a start within a few mm of the silhouettes."""
    hull_init_dilate_px: float = checked(0.5, ge=0.0)
    """Mask dilation of the pre-fit hull, pixels (tolerance to calibration errors)."""
    hull_init_steps: int = checked(200, ge=0)
    """Regression steps of the network to the hull's signed distance before the rendering losses."""
    hull_init_points: int = 2048
    """Points per regression step (half near the hull surface, half uniform in the bounds)."""
    proposal_voxel_m: float = checked(0.015, gt=0.0)
    """Voxel size of the cached SDF grid that proposes each ray's window, metres (0 is refused)."""
    proposal_update_every: int = checked(100, ge=1)
    """Steps between refreshes of the cached SDF grid from the network."""
    window_m: float = checked(0.03, gt=0.0)
    """Half-width of the sampling window (metres along the ray) around the proposed crossing at the start;
    it shrinks with the NeuS sharpness to ``max(window_min_m, _WINDOW_SHARPNESS / inv_s)``."""
    window_min_m: float = checked(0.008, gt=0.0)
    """Smallest half-width of the sampling window, metres (covers the cached grid's crossing error)."""
    inv_s_start: float = checked(50.0, gt=0.0)
    """NeuS sharpness ``inv_s`` (1 / metres) at the first step; the logistic density of NeuS is
    ``s exp(-s f) / (1 + exp(-s f))^2`` with ``s = inv_s``."""
    inv_s_end: float = checked(800.0, gt=0.0)
    """``inv_s`` reached (geometrically) at ``_INV_S_RAMP`` of the steps, kept to the end."""
    inv_s_end_per_pixel: float = checked(0.0, ge=0.0)
    """Final NeuS transitions per pixel of the subject (:func:`sharpness_for_pixels`; 0 = off): the final ``inv_s``
    is ``max(inv_s_end, inv_s_end_per_pixel / pixel_m)``, so the transition width ``1 / inv_s`` is at most
    ``1 / inv_s_end_per_pixel`` of the median footprint ``pixel_m`` of a pixel at the subject
    (:func:`subject_pixel_m`). At ``inv_s`` 800 a surface seen at 1 mm per pixel settles inside the truth (the ICT
    head: median -0.9 mm) and a sharper one moves out. Whole runs of the ICT head (1.1 mm pixels, 8 mm windows) at
    ``inv_s_end`` 800 / 1600 / 3200 / 6400: comparable Chamfer 0.88 / 0.61 / 0.36 / 0.23 mm, relit 22.8 / 24.1 /
    26.0 / 27.6 dB. The geometry stage alone on the default body: at 5 mm pixels 1.12 / 1.48 / 1.53 mm at 800 /
    1600 / 3200, at 2.1 mm pixels (768 px wide) 0.96 / 1.00 mm at 800 / 1600; the unseen capture (4.2 mm pixels,
    whole run) 1.23 mm at 800 and 1.46 mm at 961. The cpu preset's 3.2 per pixel leaves subjects seen at 4 mm per
    pixel or coarser at 800 (every body of the panel and both captures) and gives the head about 2900."""
    coarse_to_fine: float = checked(0.5, ge=0.0, le=1.0)
    """Fraction of the steps over which the hash levels are switched on one by one (from
    ``initial_levels``), as Neuralangelo; 0 = all levels from the start."""
    initial_levels: int = checked(4, ge=1)
    """Active hash levels during the hull pre-fit and the first step."""
    gradient: Literal["analytic", "finite_difference", "autograd"] = "analytic"
    """How SDF gradients are computed: forward-mode Jacobian of the encoding and MLP (no double backward),
    central finite differences (6 extra evaluations, step ``fd_step_m``), or autograd double backward."""
    fd_step_m: float = checked(0.002, gt=0.0)
    """Step of the finite-difference gradient, metres."""
    seed: int = 0
    """Seed of every random choice (rays, jitter, initial weights)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Where to train: ``auto`` uses CUDA when available. The result's field is on the CPU."""
    threads: int = checked(0, ge=0)
    """torch CPU threads while training (restored afterwards); 0 leaves torch's setting alone."""
    log_every: int = checked(50, ge=1)
    """Steps between history entries (and progress calls)."""


SDF_PRESETS: dict[str, SDFConfig] = {
    # `make dataset` on a 2-core machine: one action (32 views, 320x480) on one thread while the other action
    # trains on the other core. The geometry stage runs this schedule as its second pass, after a shorter first
    # one (geometry.first_pass_iterations); bench/bench_sdf_schedule.py measures Chamfer against time over both
    # passes' steps, bench/bench_geometry.py the pass's curve over iterations. Pixel-exact calibrated silhouettes
    # earn the mask loss a weight of 0.5; a 2^18 table, normals down to 3 deg from grazing and 2% outliers
    # keep the finger and contour pixels the second pass's importance-drawn rays are for. An eikonal weight of
    # 0.05 lets the surface settle closer to the normals than 0.1 does (Chamfer 0.08 mm lower on average over
    # seven paired runs of two captures and three seeds, lower in six). 1500 steps keep `make dataset` under 5
    # minutes; against 1800 (both after a 150-step first pass; two seeds) they save about 12 CPU s an action and
    # cost 0.07 dB of relit views and 0.05 deg of their shading normals, Chamfer 1.058 -> 1.069 mm.
    "cpu": SDFConfig(
        encoding=HashGridConfig(levels=12, features_per_level=2, log2_table_size=18,
                                base_resolution=16, finest_resolution=512),
        hidden_width=64, hidden_layers=2, iterations=1500, rays_per_batch=512, samples_per_ray=8,
        hull_resolution=96, hull_init_steps=200, hull_init_points=2048, weight_mask=0.5, weight_eikonal=0.05,
        grazing_cos_min=0.05, outlier_fraction=0.02, inv_s_end_per_pixel=3.2,
    ),
    # Full-resolution captures on a GPU.
    "production": SDFConfig(
        encoding=HashGridConfig(levels=16, features_per_level=2, log2_table_size=19,
                                base_resolution=16, finest_resolution=2048),
        hidden_width=64, hidden_layers=2, iterations=20000, rays_per_batch=4096, samples_per_ray=16,
        hull_resolution=192, hull_init_steps=1000, hull_init_points=16384, eikonal_points=2048,
        proposal_voxel_m=0.008, proposal_update_every=200, window_min_m=0.004, inv_s_end=2000.0,
        learning_rate=1e-2, log_every=200,
    ),
    # Unit tests: seconds on one CPU thread.
    "test": SDFConfig(
        encoding=HashGridConfig(levels=6, features_per_level=2, log2_table_size=12,
                                base_resolution=4, finest_resolution=48),
        hidden_width=32, hidden_layers=1, iterations=160, rays_per_batch=256, samples_per_ray=8,
        hull_resolution=32, hull_dilate_px=1.0, hull_init_steps=60, hull_init_points=1024, eikonal_points=64,
        proposal_voxel_m=0.04, proposal_update_every=20, window_m=0.08, window_min_m=0.03,
        inv_s_start=30.0, inv_s_end=150.0, initial_levels=2, log_every=10, warmup_iterations=5,
        before_window="opacity",
    ),
}


# ------------------------------------------------------------------------------------------------ field


class SDFField(torch.nn.Module):
    """Signed distance (metres, negative inside) over an axis-aligned box: hash encoding + softplus MLP.

    Points are mapped to the unit cube around the box (``u = (x - centre) / half_extent`` in [-1, 1] along the
    longest edge), the MLP sees ``(u, encoding(u))`` and outputs the SDF in units of ``half_extent``; since the
    scale cancels, its gradient with respect to metres is the gradient with respect to ``u``.
    """

    def __init__(self, bounds: np.ndarray, encoding: HashGridConfig = HashGridConfig(), hidden_width: int = 64,
                 hidden_layers: int = 2, init_radius_m: float | None = None):
        super().__init__()
        b = check_bounds(bounds)
        self.bounds = b
        self.encoding_config = encoding
        self.hidden_width = int(hidden_width)
        self.hidden_layers = int(hidden_layers)
        centre = (b[0] + b[1]) / 2
        half = float((b[1] - b[0]).max() / 2)
        self.register_buffer("centre", torch.tensor(centre, dtype=torch.float32))
        self.register_buffer("half_extent", torch.tensor(half, dtype=torch.float32))
        self.encoding = HashEncoding(encoding)
        dims = [3 + self.encoding.out_dim] + [self.hidden_width] * self.hidden_layers + [1]
        self.layers = torch.nn.ModuleList(torch.nn.Linear(dims[i], dims[i + 1]) for i in range(len(dims) - 1))
        self._geometric_init(0.5 if init_radius_m is None else init_radius_m / half)

    def _geometric_init(self, radius: float) -> None:
        # IDR/NeuS sphere initialisation; the encoding's inputs start at zero weight (Neuralangelo) so the
        # field is a smooth sphere until the hash features learn something.
        generator = torch.Generator().manual_seed(0)
        with torch.no_grad():
            for i, layer in enumerate(self.layers):
                out_dim, in_dim = layer.weight.shape
                if i == len(self.layers) - 1:
                    layer.weight.normal_(math.sqrt(math.pi) / math.sqrt(in_dim), 1e-4, generator=generator)
                    layer.bias.fill_(-radius)
                else:
                    layer.weight.normal_(0.0, math.sqrt(2.0) / math.sqrt(out_dim), generator=generator)
                    layer.bias.zero_()
                    if i == 0:
                        layer.weight[:, 3:].zero_()

    # -- evaluation ------------------------------------------------------------------------------------

    def _to_unit(self, points: torch.Tensor) -> torch.Tensor:
        return (points - self.centre) / self.half_extent

    def _mlp(self, u: torch.Tensor, jacobian: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        enc, enc_jac = self.encoding((u + 1.0) * 0.5, jacobian)
        h = torch.cat([u, enc], dim=1)
        J = None
        if jacobian:
            N = u.shape[0]
            eye = torch.eye(3, dtype=u.dtype, device=u.device).view(3, 1, 3).expand(3, N, 3)
            J = torch.cat([eye, enc_jac * 0.5], dim=2)  # (3, N, D): tangents along u_x, u_y, u_z
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            z = F.linear(h, layer.weight, layer.bias)
            if J is not None:
                J = torch.matmul(J, layer.weight.t())
            if i == last:
                return z[:, 0], (J[..., 0].t() if J is not None else None)
            h = F.softplus(z, beta=_SOFTPLUS_BETA)
            if J is not None:
                J = J * torch.sigmoid(_SOFTPLUS_BETA * z).unsqueeze(0)
        raise AssertionError("unreachable")

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """SDF in metres at ``points`` (N, 3) metres -> (N,)."""
        sdf_unit, _ = self._mlp(self._to_unit(points), jacobian=False)
        return sdf_unit * self.half_extent

    def sdf_and_gradient(self, points: torch.Tensor, mode: str = "analytic",
                         fd_step_m: float = 0.002) -> tuple[torch.Tensor, torch.Tensor]:
        """SDF (N,) metres and its gradient (N, 3) (unitless), both differentiable w.r.t. the parameters."""
        if mode == "analytic":
            sdf_unit, grad = self._mlp(self._to_unit(points), jacobian=True)
            return sdf_unit * self.half_extent, grad
        if mode == "finite_difference":
            h = fd_step_m
            offsets = torch.eye(3, dtype=points.dtype, device=points.device) * h
            stacked = torch.cat([points, *(points + o for o in offsets), *(points - o for o in offsets)])
            values = self.forward(stacked).view(7, -1)
            grad = torch.stack([(values[1 + a] - values[4 + a]) / (2 * h) for a in range(3)], dim=1)
            return values[0], grad
        if mode == "autograd":
            self.encoding.double_backward = True
            try:
                with torch.enable_grad():
                    p = points.detach().requires_grad_(True)
                    sdf = self.forward(p)
                    (grad,) = torch.autograd.grad(sdf.sum(), p, create_graph=True)
            finally:
                self.encoding.double_backward = False
            return sdf, grad
        raise ValueError(f"mode must be 'analytic', 'finite_difference' or 'autograd', got {mode!r}")

    def set_active_levels(self, n: float) -> None:
        self.encoding.set_active_levels(n)

    # -- numpy helpers --------------------------------------------------------------------------------

    def _device(self) -> torch.device:
        return self.centre.device

    def sdf_numpy(self, points: np.ndarray, chunk: int = 65536) -> np.ndarray:
        """SDF (N,) float32 metres at ``points`` (N, 3) metres; chunked, no autograd."""
        p = np.asarray(points, np.float32).reshape(-1, 3)
        out = np.empty(len(p), np.float32)
        with torch.no_grad():
            for s in range(0, len(p), chunk):
                t = torch.from_numpy(p[s:s + chunk]).to(self._device())
                out[s:s + chunk] = self.forward(t).float().cpu().numpy()
        return np.nan_to_num(out, nan=0.0, posinf=1.0, neginf=-1.0)

    def normals_numpy(self, points: np.ndarray, chunk: int = 32768) -> np.ndarray:
        """Unit SDF gradients (N, 3) float32 at ``points`` (N, 3) metres (outward normals on the surface)."""
        p = np.asarray(points, np.float32).reshape(-1, 3)
        out = np.empty((len(p), 3), np.float32)
        with torch.no_grad():
            for s in range(0, len(p), chunk):
                t = torch.from_numpy(p[s:s + chunk]).to(self._device())
                _, g = self.sdf_and_gradient(t, "analytic")
                out[s:s + chunk] = F.normalize(g, dim=1, eps=1e-12).float().cpu().numpy()
        return np.nan_to_num(out)

    # -- serialisation --------------------------------------------------------------------------------

    def to_state(self) -> dict[str, Any]:
        """JSON-able config plus CPU tensors, for ``torch.save``; :meth:`from_state` rebuilds the field."""
        return {
            "format": "ultrastage-sdf/1",
            "config": {
                "bounds": self.bounds.tolist(),
                "encoding": to_dict(self.encoding_config),
                "hidden_width": self.hidden_width,
                "hidden_layers": self.hidden_layers,
                "level_mask": self.encoding.level_mask.cpu().tolist(),
            },
            "tensors": {k: v.detach().cpu().clone() for k, v in self.state_dict().items()},
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> "SDFField":
        """Rebuild a field saved by :meth:`to_state` (on the CPU)."""
        if not isinstance(state, dict) or state.get("format") != "ultrastage-sdf/1":
            raise ValueError("not an SDF state (expected format 'ultrastage-sdf/1')")
        cfg = state["config"]
        field_ = cls(np.asarray(cfg["bounds"]), HashGridConfig(**cfg["encoding"]), cfg["hidden_width"],
                     cfg["hidden_layers"])
        field_.load_state_dict(state["tensors"])
        mask = torch.tensor(cfg["level_mask"], dtype=torch.float32)
        field_.encoding.level_mask.copy_(mask)
        field_.encoding.active_count = max(1, int((mask > 0).sum()))
        return field_


# ------------------------------------------------------------------------------------------------ inputs


@dataclass
class SDFView:
    """One calibrated view's supervision.

    Attributes:
        normals_world: float32 (H, W, 3) photometric unit normals, stage frame (0 where undefined).
        normal_valid: bool (H, W) where the normal is trusted (alpha > 0.5 and on the mask).
        mask: bool (H, W) foreground.
        K: (3, 3) intrinsics.
        cam_from_world: (3, 4) ``[R | t]`` (OpenCV).
        sample_weight: float (H, W) >= 0, how often ``SDFConfig.importance_fraction``'s share of the rays is
            drawn at each pixel, relative to the other pixels of every view (e.g. a first fit's error there);
            None = 0. Those rays count in the normal loss, and in the mask loss where the mask is background
            (a hole a first fit spans, drawn to carve it), not where it is foreground.
        free_depth_m: float (H, W) >= 0, distance from the camera centre along each pixel's ray up to which the
            ray crosses empty space (e.g. where the views disagree on a surface there); 0 = nothing known, None =
            none anywhere. Points there are held outside by ``SDFConfig.weight_free_space``'s term.
    """

    normals_world: np.ndarray
    normal_valid: np.ndarray
    mask: np.ndarray
    K: np.ndarray
    cam_from_world: np.ndarray
    sample_weight: np.ndarray | None = None
    free_depth_m: np.ndarray | None = None


@dataclass
class SDFResult:
    """Output of :func:`train_sdf`.

    Attributes:
        field: the trained :class:`SDFField`, on the CPU, in eval mode.
        bounds: (2, 3) box to extract the surface in (the hull's box plus margin), metres.
        hull: the visual hull over ``bounds``.
        history: lists keyed by ``iteration``, ``seconds``, ``loss``, ``normal``, ``mask``, ``eikonal``, ``hull``,
            ``free`` (the free-space term), ``normal_deg`` (mean angle of the kept valid rays), ``inv_s``, ``lr``.
        stats: ``time_s``, ``device``, ``iterations``, ``steps_per_s`` (of the training loop), on a CUDA device
            ``gpu_name`` and ``gpu_peak_memory_bytes`` (torch's peak allocation over the training),
            ``importance_rays_per_iteration`` (drawn by the views'
            sample weights); ``samples_skipped_fraction``: the share of a naive
            uniform sampler's samples (every pixel's ray through the stage box, at the window's sample spacing)
            that the hull (rays worth drawing: ``candidate_ray_fraction``) and the cached SDF grid (window
            around the crossing) skipped, and ``samples_skipped_vs_neus_128`` against 128 samples on every
            pixel's ray; hull and pre-fit timings, ``time_breakdown_s``.
        start: what training started from (:class:`SDFStart`): a later :func:`train_sdf` on views with the
            same masks and cameras and a config that differs only in its schedule reuses it.
    """

    field: SDFField
    bounds: np.ndarray
    hull: HullGrid
    history: dict[str, list]
    stats: dict[str, Any]
    start: "SDFStart | None" = None


@dataclass(frozen=True)
class SDFStart:
    """A training's start: the visual hull and its signed distance, the bounds, the hull-pre-fitted field and
    the random generators' states after it, and the key of what made them (:func:`_start_key`)."""

    key: str
    hull: HullGrid
    hull_sd: np.ndarray
    sdf_bounds: np.ndarray
    stage_box: np.ndarray
    field_state: dict[str, Any]
    prefit_losses: list[float]
    generator_state: torch.Tensor
    torch_rng_state: torch.Tensor


_SCHEDULE_FIELDS = ("iterations", "warmup_iterations", "importance_fraction", "log_every")
"""SDFConfig fields that act after the start (the two passes of the geometry stage differ in these)."""


def _start_key(masks: list[np.ndarray], cams: list, config: "SDFConfig", bounds: np.ndarray | None,
               device: torch.device) -> str:
    """sha256 of what the hull, the bounds and the pre-fitted field depend on: the masks, the cameras, the
    caller's bounds, the device and every config field but the schedule's."""
    digest = hashlib.sha256()
    for mask, (K, T) in zip(masks, cams):
        digest.update(np.packbits(mask).tobytes() + repr(mask.shape).encode())
        digest.update(np.ascontiguousarray(K, np.float64).tobytes() + np.ascontiguousarray(T, np.float64).tobytes())
    digest.update(b"none" if bounds is None else np.ascontiguousarray(bounds, np.float64).tobytes())
    neutral = dataclasses.replace(config, **{name: SDFConfig.__dataclass_fields__[name].default
                                             for name in _SCHEDULE_FIELDS})
    digest.update(repr((to_dict(neutral), str(device))).encode())
    return digest.hexdigest()


def _check_views(views: Sequence[SDFView], normal_supervision: bool) -> list[tuple[np.ndarray, np.ndarray]]:
    check_view_list(views, SDFView)
    cams = []
    for i, v in enumerate(views):
        mask = np.asarray(v.mask)
        if mask.ndim != 2 or min(mask.shape) < 1:
            raise ValueError(f"views[{i}].mask must be (H, W), got shape {mask.shape}")
        H, W = mask.shape
        normal_valid = check_view_map(v.normal_valid, (H, W), f"views[{i}].normal_valid")
        check_view_map(v.normals_world, (H, W, 3), f"views[{i}].normals_world",
                       valid=normal_valid if normal_supervision else None)
        if v.sample_weight is not None:
            sw = check_view_map(v.sample_weight, (H, W), f"views[{i}].sample_weight")
            if not (np.isfinite(sw).all() and (sw >= 0).all()):
                raise ValueError(f"views[{i}].sample_weight must be finite and >= 0")
        if v.free_depth_m is not None:
            fd = check_view_map(v.free_depth_m, (H, W), f"views[{i}].free_depth_m")
            if not (np.isfinite(fd).all() and (fd >= 0).all()):
                raise ValueError(f"views[{i}].free_depth_m must be finite and >= 0")
        cams.append(check_camera(v.K, v.cam_from_world, f"views[{i}]"))
    if not any(np.asarray(v.mask).any() for v in views):
        raise ValueError("every mask is empty: nothing to reconstruct")
    return cams


def subject_pixel_m(cams: Sequence[tuple[np.ndarray, np.ndarray]], point: np.ndarray) -> float:
    """The median over the views of the footprint of one pixel at ``point`` (3,), metres: its depth in the
    camera over the focal length ``fx`` (pixels). Views with ``point`` behind them do not count.

    Raises:
        ValueError: ``point`` is behind every camera.
    """
    point = np.asarray(point, np.float64).reshape(3)
    footprints = []
    for K, T in cams:
        depth = float(np.asarray(T, np.float64)[2, :3] @ point + T[2, 3])
        if depth > 0:
            footprints.append(depth / float(K[0, 0]))
    if not footprints:
        raise ValueError(f"the point {point.tolist()} is behind every camera")
    return float(np.median(footprints))


def mask_centre(views: Sequence[SDFView]) -> np.ndarray:
    """(3,) the point nearest, in the least-squares sense, to the rays through the centroids of the views' masks
    (views with an empty mask do not count): where the subject is, before any hull.

    Raises:
        ValueError: fewer than two masks hold a pixel, or their rays are parallel.
    """
    rows, rhs = np.zeros((3, 3)), np.zeros(3)
    used = 0
    for view in views:
        ys, xs = np.nonzero(np.asarray(view.mask, bool))
        if len(xs) == 0:
            continue
        K, T = np.asarray(view.K, np.float64), np.asarray(view.cam_from_world, np.float64)
        direction, _ = pixel_rays(K, T, np.float64(xs.mean()), np.float64(ys.mean()))
        projector = np.eye(3) - np.outer(direction, direction)
        rows += projector
        rhs += projector @ camera_centre(T)
        used += 1
    if used < 2 or np.linalg.cond(rows) > 1e8:
        raise ValueError(f"the subject's centre needs two masks whose rays cross ({used} mask(s) hold a pixel)")
    return np.linalg.solve(rows, rhs)


def subject_footprint_m(views: Sequence[SDFView]) -> float:
    """The footprint of one pixel at the subject, metres: :func:`subject_pixel_m` at :func:`mask_centre` (the
    training's own figure, ``stats["subject_pixel_m"]``, is taken at the hull's centre, known only once the hull is).

    Raises:
        ValueError: as :func:`mask_centre`, or the centre is behind every camera.
    """
    cams = [(np.asarray(v.K, np.float64), np.asarray(v.cam_from_world, np.float64)) for v in views]
    return subject_pixel_m(cams, mask_centre(views))


def sharpness_for_pixels(config: SDFConfig, pixel_m: float) -> SDFConfig:
    """``config`` with the sharpness schedule a subject seen at ``pixel_m`` metres per pixel trains with: the final
    ``inv_s`` raised to ``config.inv_s_end_per_pixel / pixel_m`` where that is above ``config.inv_s_end`` (a
    schedule that starts at its end, ``inv_s_start >= inv_s_end``, keeps starting there). ``config`` itself when
    ``inv_s_end_per_pixel`` is 0 or the pixels are too coarse to raise it."""
    if not pixel_m > 0:
        raise ValueError(f"pixel_m must be positive, got {pixel_m}")
    end = config.inv_s_end_per_pixel / pixel_m
    if end <= config.inv_s_end:
        return config
    start = end if config.inv_s_start >= config.inv_s_end else config.inv_s_start
    return dataclasses.replace(config, inv_s_start=start, inv_s_end=end)


# ------------------------------------------------------------------------------------------------ rays


def _hull_footprint(hull: HullGrid, K: np.ndarray, T: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: pixels whose ray may meet an occupied hull voxel (voxel centres splatted, dilated by the
    voxel's projected radius)."""
    from scipy import ndimage

    H, W = shape
    centres = hull.centers()[hull.occupancy]
    out = np.zeros(shape, bool)
    if len(centres) == 0:
        return out
    x = centres @ T[:, :3].T + T[:, 3]
    x = x[x[:, 2] > 1e-6]
    z = x[:, 2]
    u, v = (np.rint(c).astype(np.int64) for c in pixel_coordinates(K, x))
    ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    out[v[ok], u[ok]] = True
    if len(z):
        # The projected half-diagonal of a voxel at the hull's nearest tenth (not its very nearest voxel).
        radius = int(math.ceil(K[0, 0] * 0.5 * float(np.linalg.norm(hull.voxel_size)) / float(np.quantile(z, 0.1))))
        radius = min(radius, 16) + 1
        yy, xx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
        out = ndimage.binary_dilation(out, structure=(xx * xx + yy * yy) <= radius * radius)
    return out


@dataclass
class _RayBank:
    """Every ray worth drawing, from all views, on the training device."""

    origins: torch.Tensor  # (V, 3) camera centres
    view: torch.Tensor  # (N,) int64
    dirs: torch.Tensor  # (N, 3)
    normals: torch.Tensor  # (N, 3) photometric normal
    normal_ok: torch.Tensor  # (N,) bool: valid, not grazing, facing the camera
    mask: torch.Tensor  # (N,) float 0/1
    sample_cdf: torch.Tensor | None  # (N,) float64 cumulative sample weights, normalised; None: all 0
    near: torch.Tensor  # (N,)
    far: torch.Tensor  # (N,)
    free_rays: torch.Tensor | None  # (M,) int64 indices of the rays with a free depth; None: none
    free_t: torch.Tensor | None  # (M,) their free depths, metres along the ray
    pixels_total: int
    mean_chord_all_m: float  # mean chord of all pixel rays (of all views) through the stage box


def _build_ray_bank(views, cams, hull: HullGrid, bounds: np.ndarray, stage_box: np.ndarray,
                    grazing_cos_min: float, device: torch.device, rng: np.random.Generator) -> _RayBank:
    origins, view_ids, dirs, normals, ok, masks, nears, fars = [], [], [], [], [], [], [], []
    weights, frees = [], []
    pixels_total = 0
    chord_sum = 0.0
    chord_count = 0
    for i, (v, (K, T)) in enumerate(zip(views, cams)):
        mask = np.asarray(v.mask, bool)
        H, W = mask.shape
        pixels_total += H * W
        cand = mask | _hull_footprint(hull, K, T, (H, W))
        rows, cols = np.nonzero(cand)
        d, o = pixel_rays(K, T, cols, rows)[0], camera_centre(T)
        near, far = ray_box(o[None], d, bounds)
        hit = far > near + 1e-6
        rows, cols, d, near, far = rows[hit], cols[hit], d[hit], near[hit], far[hit]
        n = np.asarray(v.normals_world, np.float32)[rows, cols]
        valid = np.asarray(v.normal_valid, bool)[rows, cols] & mask[rows, cols]
        cos = (n.astype(np.float64) * d).sum(1)
        normal_ok = valid & (cos <= -grazing_cos_min) & (np.abs(np.linalg.norm(n, axis=1) - 1) < 0.1)
        origins.append(o)
        view_ids.append(np.full(len(rows), i, np.int64))
        dirs.append(d.astype(np.float32))
        normals.append(n)
        ok.append(normal_ok)
        masks.append(mask[rows, cols].astype(np.float32))
        weights.append(np.zeros(len(rows)) if v.sample_weight is None
                       else np.asarray(v.sample_weight, np.float64)[rows, cols])
        frees.append(np.zeros(len(rows), np.float32) if v.free_depth_m is None
                     else np.asarray(v.free_depth_m, np.float32)[rows, cols])
        nears.append(near.astype(np.float32))
        fars.append(far.astype(np.float32))
        # Naive sampler reference: chords of a random subset of all pixel rays through the stage box.
        sub = rng.integers(0, H * W, size=min(2000, H * W))
        ds = pixel_rays(K, T, sub % W, sub // W)[0]
        n0, f0 = ray_box(o[None], ds, stage_box)
        chord_sum += float(np.maximum(f0 - n0, 0).sum())
        chord_count += len(sub)

    def cat(arrs, dtype=None):
        return torch.from_numpy(np.concatenate(arrs)).to(device)

    if sum(len(x) for x in view_ids) == 0:
        raise ValueError("no pixel ray meets the SDF bounds: check the cameras and bounds")
    cdf = np.cumsum(np.concatenate(weights))
    sample_cdf = torch.from_numpy(cdf / cdf[-1]).to(device) if cdf[-1] > 0 else None
    free = np.concatenate(frees)
    free_rays = np.flatnonzero(free > 0)
    return _RayBank(
        origins=torch.from_numpy(np.stack(origins).astype(np.float32)).to(device),
        view=cat(view_ids), dirs=cat(dirs), normals=cat(normals), normal_ok=cat(ok), mask=cat(masks),
        sample_cdf=sample_cdf,
        near=cat(nears), far=cat(fars), pixels_total=pixels_total,
        free_rays=torch.from_numpy(free_rays).to(device) if len(free_rays) else None,
        free_t=torch.from_numpy(free[free_rays]).to(device) if len(free_rays) else None,
        mean_chord_all_m=chord_sum / max(chord_count, 1),
    )


class ProposalGrid:
    """Cached SDF at voxel centres over the bounds; marched along rays to find each one's first crossing."""

    def __init__(self, bounds: np.ndarray, voxel_m: float, device: torch.device):
        self.bounds = np.asarray(bounds, np.float64)
        ext = self.bounds[1] - self.bounds[0]
        self.shape = tuple(int(max(2, math.ceil(e / voxel_m))) for e in ext)
        self.voxel = ext / np.asarray(self.shape)
        axes = [self.bounds[0, a] + (np.arange(self.shape[a]) + 0.5) * self.voxel[a] for a in range(3)]
        # (Dz, Dy, Dx, 3) ordering for grid_sample: the last grid axis is x.
        zz, yy, xx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        self.centres = torch.from_numpy(np.stack([xx, yy, zz], -1).reshape(-1, 3).astype(np.float32)).to(device)
        self.values = torch.zeros((1, 1) + self.shape[::-1], device=device)
        self.lo = torch.tensor(self.bounds[0], dtype=torch.float32, device=device)
        self.ext = torch.tensor(ext, dtype=torch.float32, device=device)
        self.step = float(self.voxel.min())

    def refresh(self, field_: SDFField, band_m: float | None = None, chunk: int = 65536) -> int:
        """Re-evaluate the network at the voxel centres (only where ``|cached| < band_m`` when given)."""
        flat = self.values.view(-1)
        with torch.no_grad():
            idx = torch.arange(flat.numel(), device=flat.device) if band_m is None else \
                torch.nonzero(flat.abs() < band_m).view(-1)
            for s in range(0, len(idx), chunk):
                sel = idx[s:s + chunk]
                flat[sel] = field_(self.centres[sel])
        return int(len(idx))

    def sample(self, points: torch.Tensor) -> torch.Tensor:
        """Trilinear cached SDF at points (..., 3)."""
        g = (points - self.lo) / self.ext * 2.0 - 1.0
        shape = points.shape[:-1]
        out = F.grid_sample(self.values, g.reshape(1, 1, 1, -1, 3), mode="bilinear", padding_mode="border",
                            align_corners=False)
        return out.reshape(shape)

    def first_crossing(self, origins: torch.Tensor, dirs: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                       chunk_steps: int = 64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per ray: ``(t, crossed, min_sdf)``: the first + to - crossing of the cached SDF (linear
        interpolation between steps), or where the ray comes closest to the surface when there is none."""
        R = dirs.shape[0]
        step = self.step
        n_steps = int(math.ceil(float((far - near).max()) / step)) + 1 if R else 1
        if self.values.device.type == "cpu" and hashgrid_kernel.kernel_available():
            # One ray after another, each stopping at its crossing: the chunked march below samples every ray
            # until the last one crosses.
            return hashgrid_kernel.march_first_crossing(self.values[0, 0], self.lo, self.ext, step, n_steps,
                                                        origins, dirs, near, far)
        t_hit = torch.full((R,), float("nan"), device=dirs.device)
        best_t = near.clone()
        best_s = torch.full((R,), float("inf"), device=dirs.device)
        prev_s = None
        prev_t = None
        for s0 in range(0, n_steps, chunk_steps):
            k = torch.arange(s0, min(n_steps, s0 + chunk_steps), device=dirs.device, dtype=torch.float32)
            t = near.unsqueeze(1) + (k.unsqueeze(0) + 0.5) * step  # (R, S)
            inside = t < far.unsqueeze(1)
            pts = origins.unsqueeze(1) + t.unsqueeze(-1) * dirs.unsqueeze(1)
            sdf = self.sample(pts)
            sdf = torch.where(inside, sdf, torch.full_like(sdf, float("inf")))
            if prev_s is not None:
                sdf_all = torch.cat([prev_s.unsqueeze(1), sdf], 1)
                t_all = torch.cat([prev_t.unsqueeze(1), t], 1)
            else:
                sdf_all, t_all = sdf, t
            a, b = sdf_all[:, :-1], sdf_all[:, 1:]
            cross = (a > 0) & (b <= 0) & torch.isfinite(b)
            has = cross.any(1)
            first = torch.argmax(cross.int(), dim=1)
            ta = t_all.gather(1, first[:, None])[:, 0]
            sa = a.gather(1, first[:, None])[:, 0]
            sb = b.gather(1, first[:, None])[:, 0]
            tc = ta + step * sa / (sa - sb).clamp_min(1e-12)
            new = has & torch.isnan(t_hit)
            t_hit = torch.where(new, tc, t_hit)
            smin, kmin = sdf.min(1)
            better = smin < best_s
            best_s = torch.where(better, smin, best_s)
            best_t = torch.where(better, t.gather(1, kmin[:, None])[:, 0], best_t)
            prev_s, prev_t = sdf[:, -1], t[:, -1]
            if not torch.isnan(t_hit).any():
                break
        crossed = ~torch.isnan(t_hit)
        return torch.where(crossed, t_hit, best_t), crossed, best_s


# ------------------------------------------------------------------------------------------------ training


def _draw_rays(n_bank: int, count: int, sample_cdf: torch.Tensor | None, n_important: int,
               generator: torch.Generator, device: torch.device) -> torch.Tensor:
    """Indices (count,) into a bank of ``n_bank`` rays: the first ``n_important`` drawn with the probabilities
    whose normalised cumulative sum is ``sample_cdf`` (n_bank,), the rest uniformly (all uniform when the cdf
    is None or ``n_important`` is 0)."""
    pick = torch.randint(0, n_bank, (count,), generator=generator).to(device)
    if sample_cdf is not None and n_important > 0:
        u = torch.rand(n_important, generator=generator, dtype=torch.float64).to(device)
        pick[:n_important] = torch.searchsorted(sample_cdf, u, right=True).clamp_max(n_bank - 1)
    return pick


def _inv_s(it: int, config: SDFConfig) -> float:
    ramp = max(_INV_S_RAMP * config.iterations, 1.0)
    p = min(it / ramp, 1.0)
    return config.inv_s_start * (config.inv_s_end / config.inv_s_start) ** p


def _active_levels(it: int, config: SDFConfig) -> float:
    L = config.encoding.levels
    start = min(config.initial_levels, L)
    if config.coarse_to_fine <= 0:
        return float(L)
    p = min(it / max(config.coarse_to_fine * config.iterations, 1.0), 1.0)
    return start + (L - start) * p


def _grid_sampler(grid: HullGrid, values: np.ndarray, device: torch.device) -> Callable[[torch.Tensor], torch.Tensor]:
    """Trilinear look-up (torch) of per-voxel values of ``grid`` at points (N, 3) metres."""
    table = torch.from_numpy(np.ascontiguousarray(np.transpose(values, (2, 1, 0))).astype(np.float32)).to(device)
    table = table[None, None]  # (1, 1, Rz, Ry, Rx): grid_sample's last coordinate is x
    lo = torch.tensor(grid.bounds[0], dtype=torch.float32, device=device)
    ext = torch.tensor(grid.bounds[1] - grid.bounds[0], dtype=torch.float32, device=device)

    def sample(points: torch.Tensor) -> torch.Tensor:
        g = (points - lo) / ext * 2.0 - 1.0
        return F.grid_sample(table, g.view(1, 1, 1, -1, 3), mode="bilinear", padding_mode="border",
                             align_corners=False).view(-1)

    return sample


def fit_to_signed_distance(field_: SDFField, grid: HullGrid, signed_distance: np.ndarray, steps: int,
                           points: int = 4096, lr: float = 1e-2, clip_m: float = 0.1,
                           generator: torch.Generator | None = None) -> list[float]:
    """Regress the field to a voxel signed distance (e.g. :meth:`HullGrid.signed_distance`) in place.

    Cheap steps (no SDF gradients): half the points near the zero level (voxels within two voxels of it,
    jittered), half uniform in the field's bounds. L1 within ``+-clip_m``; beyond it the prediction only has
    to be at least ``clip_m`` on the right side (the far field is not worth the capacity). The learning
    rate decays (cosine) to a tenth.

    Args:
        field_: the field to fit (its current device is used).
        grid: the grid ``signed_distance`` lives on.
        signed_distance: (Rx, Ry, Rz) metres, negative inside.
        steps, points, lr: Adam steps, points per step, learning rate.
        generator: torch CPU generator for the point draws (seeded 0 when None).

    Returns:
        The loss (metres) of every step.
    """
    sd = np.asarray(signed_distance, np.float32)
    if sd.shape != grid.occupancy.shape:
        raise ValueError(f"signed_distance must be {grid.occupancy.shape} like the grid, got {sd.shape}")
    if steps < 0 or points < 2:
        raise ValueError(f"steps must be >= 0 and points >= 2, got {steps}, {points}")
    if steps == 0:
        return []
    generator = generator if generator is not None else torch.Generator().manual_seed(0)
    device = field_._device()
    target_at = _grid_sampler(grid, sd, device)
    vs = float(grid.voxel_size.max())
    near_surface = np.argwhere(np.abs(sd) < 2.0 * vs)
    centres = torch.from_numpy((grid.bounds[0] + (near_surface + 0.5) * grid.voxel_size).astype(np.float32)).to(device)
    blo = torch.tensor(field_.bounds[0], dtype=torch.float32, device=device)
    bext = torch.tensor(field_.bounds[1] - field_.bounds[0], dtype=torch.float32, device=device)
    vs_t = torch.tensor(grid.voxel_size, dtype=torch.float32, device=device)
    optimiser = instant_ngp_adam(field_.parameters(), lr)
    k = points // 2 if len(centres) else 0
    losses = []
    for step in range(steps):
        pick = torch.randint(0, max(len(centres), 1), (k,), generator=generator).to(device)
        jitter = (torch.rand((k, 3), generator=generator).to(device) - 0.5) * vs_t
        uniform = blo + torch.rand((points - k, 3), generator=generator).to(device) * bext
        pts = torch.cat([centres[pick] + jitter, uniform]) if k else uniform
        target = target_at(pts)
        pred = field_(pts)
        far = target.abs() >= clip_m
        loss = torch.where(far, F.relu(clip_m - torch.sign(target) * pred), (pred - target).abs()).mean()
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        for group in optimiser.param_groups:
            group["lr"] = lr * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * step / steps)))
        optimiser.step()
        losses.append(float(loss.detach()))
    return losses


def train_sdf(views: Sequence[SDFView], config: SDFConfig = SDF_PRESETS["cpu"], bounds: np.ndarray | None = None,
              progress: Callable[[int, dict], None] | None = None,
              checkpoint: Callable[[int, "SDFField"], None] | None = None,
              init: "SDFField | None" = None, start: "SDFStart | None" = None) -> SDFResult:
    """Train a neural SDF of the subject from photometric normal maps and masks.

    Args:
        views: calibrated views (:class:`SDFView`), all in the stage frame.
        config: :class:`SDFConfig` (presets in ``SDF_PRESETS``).
        bounds: (2, 3) box known to hold the subject, metres. None: the visual hull over a generous box
            where the cameras look (:func:`default_stage_box`) at ``hull_resolution`` finds it.
        progress: called as ``progress(iteration, losses)`` every ``log_every`` steps.
        checkpoint: called as ``checkpoint(iteration, field)`` every ``log_every`` steps with the field as
            training would return it at that step (the parameter average once it has started; on the training
            device: copy its ``state_dict`` to keep it), e.g. to measure error over time.
        init: a trained field to continue from (a copy; its bounds are kept and the hull pre-fit is skipped).
            Pair it with a schedule that starts sharp: ``inv_s_start = inv_s_end`` and ``coarse_to_fine = 0``.
        start: an earlier result's :attr:`SDFResult.start`: used when its key is this call's (same masks,
            cameras, bounds, device and config but for the schedule), so the hull and the pre-fit are not
            computed again; the training is then the same as without it, bit for bit.

    Returns:
        :class:`SDFResult`.

    Raises:
        ValueError: bad views (shapes, cameras, all masks empty) or an empty hull (a bad config is refused when
            it is built).
    """
    cams = _check_views(views, config.normal_supervision)
    if init is not None and (to_dict(init.encoding_config) != to_dict(config.encoding)
                             or (init.hidden_width, init.hidden_layers) != (config.hidden_width, config.hidden_layers)):
        raise ValueError("init was trained with another encoding or network than config's")
    device = resolve_device(config.device)
    with torch_threads(config.threads):
        return _train(views, cams, config, bounds, progress, checkpoint, device, init, start)


def _train(views, cams, config: SDFConfig, bounds, progress, checkpoint, device, init=None,
           start: SDFStart | None = None) -> SDFResult:
    t_start = time.perf_counter()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    torch.manual_seed(config.seed)
    generator = torch.Generator().manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    masks = [np.asarray(v.mask, bool) for v in views]
    key = _start_key(masks, cams, config, bounds, device) if init is None else None
    if start is not None and key is not None and start.key == key:
        hull, hull_sd, sdf_bounds, stage_box = start.hull, start.hull_sd, start.sdf_bounds, start.stage_box
        field_ = SDFField.from_state(start.field_state).to(device)
        field_.set_active_levels(float(min(config.initial_levels, config.encoding.levels)))
        prefit_losses = list(start.prefit_losses)
        generator.set_state(start.generator_state)
        torch.set_rng_state(start.torch_rng_state)
        stats: dict[str, Any] = {"device": str(device), "hull_time_s": 0.0, "start_reused": True,
                                 "hull_occupied_fraction": hull.occupied_fraction, "hull_init_time_s": 0.0}
    else:
        Ks = [K for K, _ in cams]
        Ts = [T for _, T in cams]
        hull, sdf_bounds, stage_box = _hull_and_bounds(masks, Ks, Ts, cams, config, bounds, init)
        hull_sd = hull.signed_distance()
        prefit_hull, prefit_sd = _prefit_target(masks, Ks, Ts, hull, hull_sd, config, init)
        stats = {"device": str(device), "hull_time_s": time.perf_counter() - t_start,
                 "hull_occupied_fraction": hull.occupied_fraction}
        t0 = time.perf_counter()
        field_, prefit_losses = _initial_field(sdf_bounds, prefit_hull, prefit_sd, config, device, generator, init)
        stats["hull_init_time_s"] = time.perf_counter() - t0
        start = None if key is None else SDFStart(
            key=key, hull=hull, hull_sd=hull_sd, sdf_bounds=sdf_bounds, stage_box=stage_box,
            field_state=field_.to_state(), prefit_losses=list(prefit_losses),
            generator_state=generator.get_state(), torch_rng_state=torch.get_rng_state())
    stats["hull_init_final_l1_m"] = prefit_losses[-1] if prefit_losses else None
    stats["subject_pixel_m"] = subject_pixel_m(cams, sdf_bounds.mean(axis=0))
    config = sharpness_for_pixels(config, stats["subject_pixel_m"])
    stats["inv_s_end"] = config.inv_s_end

    bank = _build_ray_bank(views, cams, hull, sdf_bounds, stage_box, config.grazing_cos_min, device, rng)
    proposal = ProposalGrid(sdf_bounds, config.proposal_voxel_m, device)
    proposal.refresh(field_)
    hull_distance = _grid_sampler(hull, hull_sd, device)

    table = [field_.encoding.table]
    mlp = [p for n, p in field_.named_parameters() if not n.startswith("encoding.")]
    optimiser = instant_ngp_adam([{"params": table}, {"params": mlp}], config.learning_rate)
    history: dict[str, list] = {k: [] for k in ("iteration", "seconds") + _HISTORY_KEYS}
    n_important = int(round(config.importance_fraction * config.rays_per_batch)) if bank.sample_cdf is not None else 0
    box_lo = torch.tensor(sdf_bounds[0], dtype=torch.float32, device=device)
    box_ext = torch.tensor(sdf_bounds[1] - sdf_bounds[0], dtype=torch.float32, device=device)
    average = _ParameterAverage(list(field_.parameters()), config)
    meter = _LossMeter()
    counts = _SampleCounts()
    timing = {"proposal": 0.0, "forward": 0.0, "backward": 0.0, "step": 0.0, "refresh": 0.0}
    t_train = time.perf_counter()
    for it in range(config.iterations):
        inv_s, lr = _apply_schedule(it, config, field_, optimiser)
        if it > 0 and it % config.proposal_update_every == 0:
            tick = time.perf_counter()
            # Only cells near the surface: the rest keep their (large, correctly signed) values.
            proposal.refresh(field_, band_m=_PROPOSAL_BAND_M)
            timing["refresh"] += time.perf_counter() - tick
        window = max(config.window_min_m, min(config.window_m, _WINDOW_SHARPNESS / inv_s))

        tick = time.perf_counter()
        batch = _draw_batch(bank, proposal, config.rays_per_batch, n_important, generator, device)
        timing["proposal"] += time.perf_counter() - tick
        tick = time.perf_counter()
        samples = _sample_windows(field_, batch, window, box_lo, box_ext, config, generator, device)
        counts.add(config.rays_per_batch, samples.n_rays, config.samples_per_ray, window, bank.mean_chord_all_m)
        losses = _step_losses(field_, bank, batch, samples, hull_distance, it, inv_s, n_important, config,
                              generator, device)
        optimiser.zero_grad(set_to_none=True)
        timing["forward"] += time.perf_counter() - tick
        tick = time.perf_counter()
        losses.total.backward()
        timing["backward"] += time.perf_counter() - tick
        tick = time.perf_counter()
        optimiser.step()
        average.update(it)
        timing["step"] += time.perf_counter() - tick

        meter.add(losses, batch.crossed)
        if (it + 1) % config.log_every == 0 or it + 1 == config.iterations:
            entry = meter.take_means()
            entry.update(inv_s=inv_s, lr=lr)
            _report(it, entry, time.perf_counter() - t_start, history, progress, checkpoint, field_, average)

    average.finish(config.iterations - 1)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        stats["gpu_name"] = torch.cuda.get_device_name(device)
        stats["gpu_peak_memory_bytes"] = int(torch.cuda.max_memory_allocated(device))
    field_ = field_.cpu().eval()
    stats.update(_training_stats(config, bank, n_important, counts, timing, t_start, t_train))
    return SDFResult(field=field_, bounds=sdf_bounds, hull=hull, history=history, stats=stats, start=start)


def _hull_and_bounds(masks, Ks, Ts, cams, config: SDFConfig, bounds: np.ndarray | None,
                     init: SDFField | None) -> tuple[HullGrid, np.ndarray, np.ndarray]:
    """The conservative visual hull that bounds the rays and samples, the SDF's (2, 3) bounds (metres) and the
    stage box the naive sampler of the stats is measured in.

    With no ``bounds``, a coarse hull over :func:`default_stage_box` finds the subject's box first. The SDF's
    bounds are the hull's box plus ``hull_margin_m``, kept inside a caller's ``bounds``; a continued ``init``
    field keeps its own (its encoding is defined over them)."""
    if init is not None:
        bounds = np.asarray(init.bounds, np.float64)
    if bounds is None:
        stage_box = default_stage_box(cams)
        box = subject_box(masks, Ks, Ts, stage_box, min(64, config.hull_resolution), config.hull_max_misses,
                          config.hull_dilate_px, config.hull_component_views)
    else:
        box = check_bounds(bounds)
        stage_box = box
    hull = visual_hull(masks, Ks, Ts, box, config.hull_resolution, config.hull_max_misses, config.hull_dilate_px,
                       component_views=config.hull_component_views)
    sdf_bounds = hull.tight_bounds(config.hull_margin_m)
    if bounds is not None:  # never leave the box the caller vouched for
        sdf_bounds = np.stack([np.maximum(sdf_bounds[0], box[0]), np.minimum(sdf_bounds[1], box[1])])
    if init is not None:
        sdf_bounds = np.asarray(init.bounds, np.float64)
    return hull, sdf_bounds, stage_box


def _prefit_target(masks, Ks, Ts, hull: HullGrid, hull_sd: np.ndarray, config: SDFConfig,
                   init: SDFField | None) -> tuple[HullGrid, np.ndarray]:
    """The hull the new field is pre-fitted to and its signed distance (Rx, Ry, Rz) metres.

    The conservative hull bounds samples and rays; the closer, classic centre-test hull is the better starting
    surface (the mask loss alone carves slowly), unless it comes out empty."""
    if not config.hull_init_tight or init is not None:
        return hull, hull_sd
    tight = visual_hull(masks, Ks, Ts, hull.bounds, config.hull_resolution, config.hull_max_misses,
                        config.hull_init_dilate_px, conservative=False, component_views=config.hull_component_views)
    if not tight.occupancy.any():
        return hull, hull_sd
    return tight, tight.signed_distance()


def _initial_field(sdf_bounds: np.ndarray, prefit_hull: HullGrid, prefit_sd: np.ndarray, config: SDFConfig,
                   device: torch.device, generator: torch.Generator,
                   init: SDFField | None) -> tuple[SDFField, list[float]]:
    """The field training starts from, on ``device``, and the pre-fit's loss per step: a copy of ``init``
    (no pre-fit), or a new field over ``sdf_bounds`` regressed to the pre-fit hull's signed distance."""
    if init is not None:
        return SDFField.from_state(init.to_state()).to(device), []
    field_ = SDFField(sdf_bounds, config.encoding, config.hidden_width, config.hidden_layers).to(device)
    field_.set_active_levels(float(min(config.initial_levels, config.encoding.levels)))
    losses = fit_to_signed_distance(field_, prefit_hull, prefit_sd, config.hull_init_steps,
                                    config.hull_init_points, _HULL_INIT_LR, generator=generator)
    return field_, losses


def _apply_schedule(it: int, config: SDFConfig, field_: SDFField,
                    optimiser: torch.optim.Optimizer) -> tuple[float, float]:
    """Set step ``it``'s active hash levels and learning rates (the hash table's group first, the MLP's second);
    returns the step's NeuS sharpness ``inv_s`` and the table's learning rate."""
    inv_s = _inv_s(it, config)
    field_.set_active_levels(_active_levels(it, config))
    lr = config.learning_rate * lr_factor(it, config)
    optimiser.param_groups[0]["lr"] = lr
    optimiser.param_groups[1]["lr"] = lr * _MLP_LR_FACTOR
    return inv_s, lr


@dataclass
class _Batch:
    """One step's rays, drawn from the bank, with each one's first crossing in the cached SDF grid (B rays)."""

    pick: torch.Tensor  # (B,) int64 indices into the bank; the first n_important drawn by the sample weights
    origins: torch.Tensor  # (B, 3)
    dirs: torch.Tensor  # (B, 3)
    target_mask: torch.Tensor  # (B,) float 0/1
    t_cross: torch.Tensor  # (B,) distance along the ray to the proposed crossing
    crossed: torch.Tensor  # (B,) bool: the cached grid changes sign along the ray
    min_sdf: torch.Tensor  # (B,) smallest cached SDF along the ray


def _draw_batch(bank: _RayBank, proposal: ProposalGrid, count: int, n_important: int,
                generator: torch.Generator, device: torch.device) -> _Batch:
    pick = _draw_rays(int(bank.dirs.shape[0]), count, bank.sample_cdf, n_important, generator, device)
    dirs = bank.dirs[pick]
    origins = bank.origins[bank.view[pick]]
    t_cross, crossed, min_sdf = proposal.first_crossing(origins, dirs, bank.near[pick], bank.far[pick])
    return _Batch(pick=pick, origins=origins, dirs=dirs, target_mask=bank.mask[pick], t_cross=t_cross,
                  crossed=crossed, min_sdf=min_sdf)


@dataclass
class _Samples:
    """The field at the samples of the rendered rays' windows (R rays x K samples) and at random points."""

    ray: torch.Tensor  # (R,) int64 indices into the batch of the rays rendered
    points: torch.Tensor  # (R, K, 3) samples along the rendered rays
    delta: torch.Tensor  # (R,) sample spacing
    all_points: torch.Tensor  # (R * K + n_random, 3): the ray samples, then the random points
    sdf: torch.Tensor  # (R * K + n_random,) the field at all_points, metres
    grad: torch.Tensor  # (R * K + n_random, 3) its gradient

    @property
    def n_rays(self) -> int:
        return int(self.ray.numel())


def _sample_windows(field_: SDFField, batch: _Batch, window: float, box_lo: torch.Tensor, box_ext: torch.Tensor,
                    config: SDFConfig, generator: torch.Generator, device: torch.device) -> _Samples:
    """Stratified samples (``samples_per_ray``, jittered) over ``+-window`` metres around each rendered ray's
    proposed crossing, ``eikonal_points`` uniform points in the box ``box_lo + [0, box_ext]``, and the field's
    SDF and gradient at all of them."""
    K = config.samples_per_ray
    # Rays off the mask that pass far from the surface have opacity ~0 already: no samples.
    render = batch.crossed | (batch.target_mask > 0.5) | (batch.min_sdf < 2 * window)
    r_idx = torch.nonzero(render).view(-1)
    R = int(r_idx.numel())
    delta = torch.full((R,), 2 * window / K, device=device)
    jitter = torch.rand((R, K), generator=generator).to(device)
    t = (batch.t_cross[r_idx].unsqueeze(1) - window
         + (torch.arange(K, device=device).float().unsqueeze(0) + jitter) * delta.unsqueeze(1))
    pts = batch.origins[r_idx].unsqueeze(1) + t.unsqueeze(-1) * batch.dirs[r_idx].unsqueeze(1)
    rand_pts = box_lo + torch.rand((config.eikonal_points, 3), generator=generator).to(device) * box_ext
    all_pts = torch.cat([pts.reshape(-1, 3), rand_pts])
    sdf_all, grad_all = field_.sdf_and_gradient(all_pts, config.gradient, config.fd_step_m)
    return _Samples(ray=r_idx, points=pts, delta=delta, all_points=all_pts, sdf=sdf_all, grad=grad_all)


@dataclass
class _StepLosses:
    """One step's losses (scalar tensors; ``total`` is the weighted sum that is minimised)."""

    total: torch.Tensor
    normal: torch.Tensor
    mask: torch.Tensor
    eikonal: torch.Tensor
    hull: torch.Tensor
    free: torch.Tensor
    normal_deg: float  # mean angle of the kept valid rays' rendered normals, degrees; NaN when there are none


def _step_losses(field_: SDFField, bank: _RayBank, batch: _Batch, samples: _Samples,
                 hull_distance: Callable[[torch.Tensor], torch.Tensor], it: int, inv_s: float, n_important: int,
                 config: SDFConfig, generator: torch.Generator, device: torch.device) -> _StepLosses:
    """Composite the samples along the rendered rays (NeuS) and weigh the mask, eikonal, hull, normal and
    curvature losses of step ``it``."""
    R, K = samples.n_rays, config.samples_per_ray
    n_samples = R * K + config.eikonal_points
    sdf = samples.sdf[:R * K].view(R, K)
    grad = samples.grad[:R * K].view(R, K, 3)
    cos_anneal = min(1.0, it / max(0.1 * config.iterations, 1.0))
    dirs = batch.dirs[samples.ray]
    weights, _ = neus_composite(sdf, grad, dirs, samples.delta, inv_s, cos_anneal)
    opacity = weights.sum(1)
    if config.before_window != "none":
        before = neus_opacity_before(sdf, grad, dirs, samples.delta, inv_s, cos_anneal)
        if config.before_window == "opacity":
            opacity = before + (1.0 - before) * opacity
        else:  # "opacity_and_normal": the mass before the window goes to the first sample, the rest is attenuated
            weights = weights * (1.0 - before).unsqueeze(1)
            weights = torch.cat([weights[:, :1] + before.unsqueeze(1), weights[:, 1:]], 1)
            opacity = weights.sum(1)
    unit = F.normalize(grad, dim=-1, eps=1e-8)
    rendered_normal = (weights.unsqueeze(-1) * unit).sum(1)

    mask_loss = _mask_loss(opacity, batch.target_mask[samples.ray], samples.ray, config.rays_per_batch, n_important)
    eik = ((samples.grad[:n_samples].norm(dim=-1) - 1.0) ** 2).mean()
    loss = config.weight_mask * mask_loss + config.weight_eikonal * eik
    hull_loss = torch.zeros((), device=device)
    if config.weight_hull > 0:
        d_hull = hull_distance(samples.all_points[:n_samples])
        hull_loss = F.relu(d_hull - samples.sdf[:n_samples]).mean()
        loss = loss + config.weight_hull * hull_loss
    normal_loss = torch.zeros((), device=device)
    normal_deg = float("nan")
    if config.normal_supervision:
        ok = bank.normal_ok[batch.pick][samples.ray]
        if bool(ok.any()):
            target_n = bank.normals[batch.pick][samples.ray][ok]
            normal_loss, normal_deg = _normal_loss(rendered_normal[ok], target_n, config.outlier_fraction)
            loss = loss + config.weight_normal * normal_loss
    if config.weight_curvature > 0 and R > 0:
        curvature_loss = _curvature_loss(field_, samples.points, unit, weights, opacity, config, generator, device)
        if curvature_loss is not None:
            loss = loss + config.weight_curvature * curvature_loss
    free_loss = torch.zeros((), device=device)
    if config.weight_free_space > 0 and bank.free_rays is not None:
        free_loss = _free_space_loss(field_, bank, config, generator, device)
        loss = loss + config.weight_free_space * free_loss
    return _StepLosses(total=loss, normal=normal_loss, mask=mask_loss, eikonal=eik, hull=hull_loss,
                       free=free_loss, normal_deg=normal_deg)


_FREE_SPACE_RAYS = 64
"""Rays drawn per step, uniformly, among those with a free depth, for the free-space term."""
_FREE_SPACE_SAMPLES = 8
"""Points per such ray, stratified over its last ``SDFConfig.free_space_span_m`` before the free depth."""


def _free_space_loss(field_: SDFField, bank: _RayBank, config: SDFConfig, generator: torch.Generator,
                     device: torch.device) -> torch.Tensor:
    """``relu(-f)`` (metres) at ``_FREE_SPACE_SAMPLES`` stratified points over the last ``free_space_span_m`` before
    the free depth of ``_FREE_SPACE_RAYS`` rays drawn uniformly among the bank's rays with one."""
    pick = torch.randint(0, int(bank.free_rays.numel()), (_FREE_SPACE_RAYS,), generator=generator).to(device)
    ray = bank.free_rays[pick]
    t_free = bank.free_t[pick]
    S = _FREE_SPACE_SAMPLES
    u = (torch.arange(S, device=device).float().unsqueeze(0)
         + torch.rand((len(pick), S), generator=generator).to(device)) / S
    t = t_free.unsqueeze(1) - config.free_space_span_m * u
    t = torch.minimum(torch.maximum(t, bank.near[ray].unsqueeze(1)), bank.far[ray].unsqueeze(1))  # in the bounds
    pts = bank.origins[bank.view[ray]].unsqueeze(1) + t.unsqueeze(-1) * bank.dirs[ray].unsqueeze(1)
    return F.relu(-field_(pts.reshape(-1, 3))).mean()


def _mask_loss(opacity: torch.Tensor, target: torch.Tensor, ray: torch.Tensor, rays_per_batch: int,
               n_important: int) -> torch.Tensor:
    """Mask BCE of the rendered rays' opacity (R,) against their mask (R,); ``ray`` (R,) are their indices in
    the batch of ``rays_per_batch``, whose first ``n_important`` were drawn by the sample weights. The mean is
    over every uniformly drawn ray: the rays not rendered have opacity 0 against a 0 mask (loss 0)."""
    op = opacity.clamp(1e-4, 1 - 1e-4)
    bce = -(target * torch.log(op) + (1 - target) * torch.log(1 - op))
    # The importance-drawn rays chosen for their normals' error lie inside the mask: counted here they would tip
    # its balance of inside and outside rays and the surface swells (A0000: Chamfer 1.86 mm instead of 1.49 at a
    # share of 0.2). Those drawn on the mask's background are there to carve it, and count.
    if n_important:
        bce = bce[(ray >= n_important) | (target < 0.5)]
    return bce.sum() / (rays_per_batch - n_important)


def _normal_loss(pred_n: torch.Tensor, target_n: torch.Tensor, outlier_fraction: float) -> tuple[torch.Tensor, float]:
    """Normal loss ``|n_r - n|_1 + (1 - cos)`` of rendered normals (N, 3) against unit photometric ones (N, 3),
    the ``outlier_fraction`` largest residuals left out; returns it and the kept rays' mean angle, degrees."""
    cos = F.cosine_similarity(pred_n, target_n, dim=-1, eps=1e-8)
    # The L1 compares directions (the rendered normal normalised): left unnormalised it would also push the
    # opacity of every valid pixel to 1, which the mask loss balances only on the mask's inner side, and the
    # surface creeps outwards at the silhouettes.
    unit_n = pred_n / pred_n.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    residual = (unit_n - target_n).abs().sum(-1) + (1.0 - cos)
    keep = residual.numel() - int(outlier_fraction * residual.numel())
    kept, kept_idx = torch.topk(residual, max(keep, 1), largest=False, sorted=False)
    normal_deg = float(torch.rad2deg(torch.acos(cos[kept_idx].detach().clamp(-1, 1))).mean())
    return kept.mean(), normal_deg


def _curvature_loss(field_: SDFField, points: torch.Tensor, unit: torch.Tensor, weights: torch.Tensor,
                    opacity: torch.Tensor, config: SDFConfig, generator: torch.Generator,
                    device: torch.device) -> torch.Tensor | None:
    """Smoothness ``|n(x) - n(x + e)|^2`` between the unit SDF normal at each opaque ray's sample of largest
    weight (points, unit (R, K, 3); weights (R, K); opacity (R,)) and at a random offset
    ``|e| = _CURVATURE_STEP_M``; None when no ray is opaque. One point per opaque ray, on the surface: 1/K of
    the samples' cost, where the surface is."""
    R = points.shape[0]
    offsets = F.normalize(torch.randn((R, 3), generator=generator).to(device), dim=1)
    best = weights.detach().argmax(dim=1)
    on_surface = opacity.detach() > 0.5
    if not bool(on_surface.any()):
        return None
    rows = torch.nonzero(on_surface).view(-1)
    base_pts = points[rows, best[rows]]
    _, g_near = field_.sdf_and_gradient(base_pts.detach() + offsets[rows] * _CURVATURE_STEP_M,
                                        config.gradient, config.fd_step_m)
    n0 = unit[rows, best[rows]]
    n1 = F.normalize(g_near, dim=-1, eps=1e-8)
    return ((n0 - n1) ** 2).sum(-1).mean()


class _ParameterAverage:
    """Exponential moving average of the field's parameters (decay ``_EMA_DECAY``) from step
    ``_EMA_START * iterations`` on."""

    def __init__(self, params: list[torch.Tensor], config: SDFConfig):
        self.params = params
        self.first = int(_EMA_START * config.iterations)
        self.average = [p.detach().clone() for p in params]

    def update(self, it: int) -> None:
        """Take in the parameters after step ``it``: the first step copies them."""
        if it < self.first:
            return
        if it == self.first:
            torch._foreach_copy_(self.average, self.params)
        else:
            torch._foreach_lerp_(self.average, self.params, 1.0 - _EMA_DECAY)

    def differs_after(self, it: int) -> bool:
        """Whether the average after step ``it`` holds more than that step's parameters."""
        return it > self.first

    def call_with_average(self, fn: Callable[[], None]) -> None:
        """Call ``fn`` with the averaged values in the parameters, then put the live ones back."""
        with torch.no_grad():
            live = [p.detach().clone() for p in self.params]
            torch._foreach_copy_(self.params, self.average)
            fn()
            torch._foreach_copy_(self.params, live)

    def finish(self, last: int) -> None:
        """Leave the average in the parameters if it started by step ``last``."""
        if last >= self.first:
            with torch.no_grad():
                torch._foreach_copy_(self.params, self.average)


_HISTORY_KEYS = ("loss", "normal", "mask", "eikonal", "hull", "free", "normal_deg", "crossed", "inv_s", "lr")


class _LossMeter:
    """Sums of the losses since the last history entry."""

    def __init__(self):
        self.sums = {"loss": 0.0, "normal": 0.0, "mask": 0.0, "eikonal": 0.0, "hull": 0.0, "free": 0.0,
                     "normal_deg": 0.0, "crossed": 0.0}
        self.count = 0

    def add(self, losses: _StepLosses, crossed: torch.Tensor) -> None:
        self.sums["loss"] += float(losses.total.detach())
        self.sums["normal"] += float(losses.normal.detach())
        self.sums["mask"] += float(losses.mask.detach())
        self.sums["eikonal"] += float(losses.eikonal.detach())
        self.sums["hull"] += float(losses.hull.detach())
        self.sums["free"] += float(losses.free.detach())
        self.sums["crossed"] += float(crossed.float().mean())
        self.sums["normal_deg"] += 0.0 if math.isnan(losses.normal_deg) else losses.normal_deg
        self.count += 1

    def take_means(self) -> dict[str, float]:
        """The means since the last call; starts the sums again."""
        means = {k: v / self.count for k, v in self.sums.items()}
        self.sums = {k: 0.0 for k in self.sums}
        self.count = 0
        return means


def _report(it: int, entry: dict[str, float], seconds: float, history: dict[str, list],
            progress: Callable[[int, dict], None] | None, checkpoint: Callable[[int, SDFField], None] | None,
            field_: SDFField, average: _ParameterAverage) -> None:
    """After step ``it``: append ``entry`` to the history, call ``progress`` and ``checkpoint``."""
    history["iteration"].append(it + 1)
    history["seconds"].append(seconds)
    for k in _HISTORY_KEYS:
        history[k].append(float(entry[k]))
    if progress is not None:
        progress(it + 1, dict(entry))
    if checkpoint is not None:
        if average.differs_after(it):
            # Show the field training would return if it stopped here: the averaged parameters.
            average.call_with_average(lambda: checkpoint(it + 1, field_))
        else:
            checkpoint(it + 1, field_)


@dataclass
class _SampleCounts:
    """Rays and samples over the training, against a naive sampler's (for the stats)."""

    evaluated: int = 0  # samples the field was evaluated at along rays
    naive: float = 0.0  # samples a uniform sampler at the window's spacing would take over the stage box
    rays_drawn: int = 0
    rays_rendered: int = 0

    def add(self, rays_drawn: int, rays_rendered: int, samples_per_ray: int, window: float,
            mean_chord_m: float) -> None:
        self.evaluated += rays_rendered * samples_per_ray
        self.naive += rays_drawn * mean_chord_m / (2 * window / samples_per_ray)
        self.rays_drawn += rays_drawn
        self.rays_rendered += rays_rendered


def _training_stats(config: SDFConfig, bank: _RayBank, n_important: int, counts: _SampleCounts,
                    timing: dict[str, float], t_start: float, t_train: float) -> dict[str, Any]:
    """:attr:`SDFResult.stats` of the training itself (after the hull and the pre-fit)."""
    n_bank = int(bank.dirs.shape[0])
    return dict(
        time_s=time.perf_counter() - t_start,
        train_time_s=time.perf_counter() - t_train,
        iterations=config.iterations,
        steps_per_s=config.iterations / max(time.perf_counter() - t_train, 1e-9),
        rays_per_iteration=config.rays_per_batch,
        importance_rays_per_iteration=n_important,
        candidate_ray_fraction=n_bank / bank.pixels_total,
        rendered_ray_fraction=counts.rays_rendered / max(counts.rays_drawn, 1),
        samples_evaluated=int(counts.evaluated),
        naive_samples=float(counts.naive),
        samples_skipped_fraction=float(1.0 - counts.evaluated * (n_bank / bank.pixels_total) / max(counts.naive, 1.0)),
        # Against NeuS's default sampler: 64 coarse + 64 fine samples on every pixel's ray.
        samples_skipped_vs_neus_128=float(1.0 - counts.evaluated * (n_bank / bank.pixels_total)
                                          / max(128.0 * counts.rays_drawn, 1.0)),
        final_inv_s=_inv_s(config.iterations - 1, config),
        gradient=config.gradient,
        normal_supervision=config.normal_supervision,
        time_breakdown_s={k: round(v, 3) for k, v in timing.items()},
    )


# ------------------------------------------------------------------------------------------------ render


def render_view(field_: SDFField, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int,
                hull: HullGrid | None = None, max_steps: int = 96, tolerance_m: float = 2e-4,
                chunk: int = 32768) -> dict[str, np.ndarray]:
    """Sphere-trace the SDF's zero level set from a camera (previews, checks).

    Args:
        field_: the SDF.
        K, cam_from_world: the camera (OpenCV).
        height, width: image size.
        hull: when given, rays that miss its occupied voxels are not traced (they are empty), and tracing
            starts at the first occupied voxel.
        max_steps: sphere-tracing iterations.
        tolerance_m: a ray hits where ``|sdf|`` falls below this.

    Returns:
        ``depth_m`` (H, W) float32 camera z of the hit (0 where no hit), ``normals_world`` (H, W, 3) float32
        unit SDF gradient at the hit (0 where no hit), ``opacity`` (H, W) float32 1 where the ray hits.
    """
    K, T = check_camera(K, cam_from_world)
    if height < 1 or width < 1:
        raise ValueError(f"height and width must be >= 1, got {height}, {width}")
    rows, cols = np.mgrid[0:height, 0:width]
    rows, cols = rows.ravel(), cols.ravel()
    d, o = pixel_rays(K, T, cols, rows)[0], camera_centre(T)
    near, far = ray_box(o[None], d, field_.bounds)
    live = far > near
    if hull is not None:
        start = np.full(len(d), np.inf)
        idx = np.nonzero(live)[0]
        step = 0.5 * float(hull.voxel_size.min())
        for s in range(0, len(idx), chunk):
            sel = idx[s:s + chunk]
            n_steps = int(math.ceil(float((far[sel] - near[sel]).max()) / step)) + 1
            for k in range(n_steps):
                t = near[sel] + k * step
                pending = np.isinf(start[sel]) & (t < far[sel])
                if not pending.any():
                    break
                hit = pending & hull.contains(o + t[:, None] * d[sel])
                start[sel[hit]] = t[hit]
        live = np.isfinite(start)
        near = np.where(live, np.maximum(start - float(hull.voxel_size.max()), near), near)
    depth = np.zeros(len(d), np.float32)
    normals = np.zeros((len(d), 3), np.float32)
    opacity = np.zeros(len(d), np.float32)
    R = T[:, :3]
    device = field_._device()
    idx = np.nonzero(live)[0]
    with torch.no_grad():
        for s in range(0, len(idx), chunk):
            sel = idx[s:s + chunk]
            dirs = torch.from_numpy(d[sel].astype(np.float32)).to(device)
            orig = torch.from_numpy(o.astype(np.float32)).to(device)
            t = torch.from_numpy(near[sel].astype(np.float32)).to(device)
            tfar = torch.from_numpy(far[sel].astype(np.float32)).to(device)
            done = torch.zeros(len(sel), dtype=torch.bool, device=device)
            hit = torch.zeros_like(done)
            for _ in range(max_steps):
                active = torch.nonzero(~done).view(-1)
                if active.numel() == 0:
                    break
                p = orig + t[active].unsqueeze(1) * dirs[active]
                f = field_(p)
                converged = f.abs() < tolerance_m
                hit[active] |= converged
                t[active] = t[active] + torch.where(converged, torch.zeros_like(f), f * 0.9)
                done[active] |= converged | (t[active] > tfar[active]) | (f < -0.05)
            hit &= t <= tfar
            h = torch.nonzero(hit).view(-1)
            if h.numel():
                p = orig + t[h].unsqueeze(1) * dirs[h]
                _, g = field_.sdf_and_gradient(p, "analytic")
                gi = sel[h.cpu().numpy()]
                normals[gi] = F.normalize(g, dim=1).cpu().numpy()
                pw = p.cpu().numpy().astype(np.float64)
                depth[gi] = (pw @ R[2] + T[2, 3]).astype(np.float32)
                opacity[gi] = 1.0
    return {
        "depth_m": np.nan_to_num(depth).reshape(height, width),
        "normals_world": np.nan_to_num(normals).reshape(height, width, 3),
        "opacity": opacity.reshape(height, width),
    }
