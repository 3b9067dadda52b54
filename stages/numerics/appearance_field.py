"""Volume-rendered albedo/normal field: the Instant-NGP baseline of the held-out G-buffer protocol (table 1).

The paper compares its depth-guided G-buffer reprojection with an Instant-NGP field trained on the albedo and
normal maps of the captured views and volume rendered from the held-out ones. This module is that baseline,
built from the pieces it shares with the SDF (:mod:`stages.numerics.neural_fields`: hash encoding, NeuS
compositing, ray helpers, Adam and learning-rate schedule) and the SDF's cached grid
(:class:`stages.numerics.sdf.ProposalGrid`):

* **Geometry is given, appearance is learnt** (design (a)): the samples of each ray and their volume-rendering
  weights come from the action's trained SDF (NeuS weights at its final sharpness ``inv_s``), and the field
  only learns what to composite there: an Instant-NGP hash grid (``L`` levels of ``F`` features) feeding a
  small ReLU MLP with two heads, albedo (linear sRGB, sigmoid times ``albedo_max``) and a normal (world frame,
  3 unnormalised outputs). So the comparison with the reprojection is "the same geometry, another way of
  producing the G-buffers", and training costs minutes on two CPU cores. A full density + appearance field
  (design (b), NeRF-style) would also have to learn the geometry from 30 maps and masks, which the SDF stage
  already does better (it is trained for it, with normal supervision), so its errors would mix a worse
  geometry into the comparison, at several times the cost.
* **Rendering.** For a pixel, ``samples_per_ray`` samples are placed uniformly in ``+-window_m`` around the
  ray's surface crossing (a depth map given by the caller, e.g. the release mesh's, or else the first zero
  crossing of the SDF cached on a voxel grid, as the SDF training does); the SDF and its gradient there give
  the NeuS weights ``w_k``; the ``samples_kept`` largest are kept (at ``inv_s = 800`` the logistic density is
  about 5 mm wide: the 4 largest of 8 samples over +-6 mm hold about 80% of the weight on the default capture,
  and keeping 2 or 4 gave the same held-out scores there). The pixel's albedo is ``sum w_k a(x_k) / sum w_k``
  and its normal ``normalise(sum w_k n(x_k))``, over the kept samples; its opacity is the sum of all the
  weights and the pixel is valid where it exceeds ``min_opacity``. Since the geometry is frozen, the samples
  and weights of every training pixel are computed once before training.
* **Loss** on the valid pixels of the training views (photometric alpha > 0.5 and mask, as the reprojection
  uses them): ``weight_albedo * |a_r - a|_1`` (or squared) ``+ weight_normal * (1 - cos(n_r, n))``. Pixels
  whose photometric normal is within ``grazing_cos_min`` of perpendicular to the view ray (or faces away) are
  left out: the maps are unreliable there and other views see the same surface head-on.

Conventions (docs/CONTRACTS.md): world = stage frame, metres; OpenCV cameras ``x_cam = R x_world + t``, pixel
index ``i`` at continuous coordinate ``u = i``; images ``(H, W[, C])`` float32, row 0 at the top. Numpy in and
numpy out at the public functions; the field is a torch module. Training runs on CUDA when torch sees it
(``device="auto"``); on the CPU the same seed gives the same weights bit for bit.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Literal, Sequence, Union

import numpy as np
import torch
import torch.nn.functional as F

from pipeline.config import Documented, checked, to_dict
from stages.numerics import torch_threads
from stages.numerics.hull import check_camera
from artifacts.camera import camera_centre, pixel_rays
from stages.numerics.neural_fields import (
    HashEncoding,
    HashGridConfig,
    check_bounds,
    check_view_list,
    check_view_map,
    instant_ngp_adam,
    lr_factor,
    neus_composite,
    ray_box,
    resolve_device,
)
from stages.numerics.sdf import ProposalGrid, SDFField

__all__ = [
    "AppearanceFieldConfig",
    "APPEARANCE_PRESETS",
    "AppearanceView",
    "AppearanceResult",
    "AppearanceSamples",
    "AppearanceField",
    "SDFCallable",
    "sample_training_pixels",
    "train_appearance_field",
    "render_appearance",
]

#: A signed distance given as a function: points (N, 3) float32 metres -> (sdf (N,) metres, gradient (N, 3)).
SDFCallable = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


# ------------------------------------------------------------------------------------------------ config


@dataclass(frozen=True)
class AppearanceFieldConfig(Documented):
    """Training and rendering of the albedo/normal field (see the module docstring)."""

    not_in_key = ("device", "threads", "log_every")

    encoding: HashGridConfig = HashGridConfig(levels=12, features_per_level=2, log2_table_size=17,
                                              base_resolution=16, finest_resolution=512)
    """The hash encoding over the cube around the SDF's bounds. Its finest cell should be about the pixels'
    footprint on the surface: finer grids memorise each view's noise (on the default capture, 5 mm pixels and a
    1.76 m cube, finest 1024 reached 3.6 deg on the training pixels but 10.9 deg on the held-out views after 1500
    steps; finest 512: 8.9 deg)."""
    hidden_width: int = checked(64, ge=1)
    """Width of the MLP's hidden layers (ReLU, as Instant-NGP's colour network)."""
    hidden_layers: int = checked(2, ge=0)
    """Number of hidden layers of the MLP."""
    albedo_max: float = checked(1.0, gt=0.0)
    """The albedo head is ``albedo_max * sigmoid(.)``: diffuse albedo lies in [0, 1]; highlights above it in the
    photometric maps are view-dependent residue a view-independent field should not chase."""
    iterations: int = checked(2000, ge=1)
    """Training steps."""
    rays_per_batch: int = checked(4096, ge=1)
    """Training pixels drawn per step (uniformly over the valid pixels of all training views)."""
    samples_per_ray: int = checked(8, ge=1)
    """SDF samples per ray in the window around the surface crossing (NeuS weights)."""
    samples_kept: int = checked(4, ge=1, le="samples_per_ray")
    """The samples of largest weight kept per ray for the field (its cost is per sample)."""
    window_m: float = checked(0.006, gt=0.0)
    """Half-width of the sampling window around the crossing, metres along the ray (NeuS's density at the
    SDF's sharpness ``inv_s`` spans about ``+-4 / inv_s`` metres of depth head-on)."""
    inv_s: float = checked(800.0, gt=0.0)
    """NeuS sharpness (1 / metres) of the weights: the value the SDF was trained to (its ``final_inv_s``)."""
    min_opacity: float = checked(0.5, ge=0.0, le=1.0)
    """A pixel is rendered (valid) where the NeuS opacity of its window exceeds this; training pixels below it
    are dropped (the SDF puts no surface there)."""
    proposal_voxel_m: float = checked(0.008, gt=0.0)
    """Without depth maps, the crossing is the first zero of the SDF cached on voxels of this size (metres)."""
    grazing_cos_min: float = checked(0.15, ge=0.0, lt=1.0)
    """Training pixels whose photometric normal has ``|n . d|`` below this, or faces away from the camera, get no
    loss (0 keeps every valid pixel)."""
    albedo_loss: Literal["l1", "l2"] = "l1"
    """Albedo loss per pixel: mean absolute (robust to the highlights of the photometric albedo) or squared error."""
    weight_albedo: float = checked(1.0, ge=0.0)
    """Weight of the albedo loss."""
    weight_normal: float = checked(1.0, ge=0.0)
    """Weight of the normal loss ``1 - cos(n_r, n)``."""
    learning_rate: float = checked(1e-2, gt=0.0)
    """Adam learning rate of the hash table after warm-up (Instant-NGP's)."""
    mlp_lr_factor: float = checked(1.0, gt=0.0)
    """The MLP's learning rate is ``learning_rate`` times this."""
    warmup_iterations: int = checked(20, ge=0)
    """Linear learning-rate warm-up (steps)."""
    final_lr_fraction: float = checked(0.05, ge=0.0, le=1.0)
    """The learning rate decays (cosine) to this fraction of ``learning_rate`` at the last step."""
    seed: int = 0
    """Seed of every random choice (initial MLP weights, pixels drawn)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Where to train and render: ``auto`` uses CUDA when available. The result's field is on the CPU."""
    threads: int = checked(0, ge=0)
    """torch CPU threads while training or rendering (restored afterwards); 0 leaves torch's setting alone."""
    log_every: int = checked(100, ge=1)
    """Steps between history entries (and progress / checkpoint calls)."""


APPEARANCE_PRESETS: dict[str, AppearanceFieldConfig] = {
    # One action of the default capture (30 training views, 320x480, ~480k valid pixels) on one CPU thread:
    # see bench/bench_heldout_field.py for time against error.
    "cpu": AppearanceFieldConfig(),
    # Full-resolution captures on a GPU: a finer, larger grid, longer training.
    "production": AppearanceFieldConfig(
        encoding=HashGridConfig(levels=16, features_per_level=2, log2_table_size=21, base_resolution=16,
                                finest_resolution=4096),
        iterations=20000, rays_per_batch=16384, samples_per_ray=16, samples_kept=6, window_m=0.004,
        inv_s=2000.0, log_every=500),
    # Unit tests: seconds on one CPU thread.
    "test": AppearanceFieldConfig(
        encoding=HashGridConfig(levels=6, features_per_level=2, log2_table_size=12, base_resolution=4,
                                finest_resolution=48),
        hidden_width=32, hidden_layers=1, iterations=200, rays_per_batch=512, samples_per_ray=8, samples_kept=4,
        window_m=0.02, inv_s=300.0, proposal_voxel_m=0.03, grazing_cos_min=0.0, learning_rate=2e-2,
        warmup_iterations=5, log_every=50),
}


def _check_config(config: AppearanceFieldConfig) -> None:
    """Refuse what is not an AppearanceFieldConfig (one is validated when it is built)."""
    if not isinstance(config, AppearanceFieldConfig):
        raise ValueError(f"config must be an AppearanceFieldConfig, got {type(config).__name__}")


# ------------------------------------------------------------------------------------------------ field


class AppearanceField(torch.nn.Module):
    """Albedo and normal at points: hash encoding of the point in the cube around ``bounds`` + ReLU MLP.

    Points map to the unit cube around the box like :class:`~stages.numerics.sdf.SDFField` does (centred, the
    longest edge spans it). Outputs: albedo (N, 3) in ``[0, albedo_max]`` and an unnormalised normal (N, 3).
    """

    def __init__(self, bounds: np.ndarray, encoding: HashGridConfig = APPEARANCE_PRESETS["cpu"].encoding,
                 hidden_width: int = 64, hidden_layers: int = 2, albedo_max: float = 1.0, seed: int = 0):
        super().__init__()
        b = check_bounds(bounds)
        self.bounds = b
        self.encoding_config = encoding
        self.hidden_width, self.hidden_layers = int(hidden_width), int(hidden_layers)
        self.albedo_max = float(albedo_max)
        self.register_buffer("centre", torch.tensor((b[0] + b[1]) / 2, dtype=torch.float32))
        self.register_buffer("half_extent", torch.tensor(float((b[1] - b[0]).max() / 2), dtype=torch.float32))
        self.encoding = HashEncoding(encoding)
        dims = [self.encoding.out_dim] + [self.hidden_width] * self.hidden_layers + [6]
        self.layers = torch.nn.ModuleList(torch.nn.Linear(dims[i], dims[i + 1]) for i in range(len(dims) - 1))
        # Seeded initialisation (torch's default uniform bound), independent of the global RNG.
        generator = torch.Generator().manual_seed(int(seed))
        with torch.no_grad():
            for layer in self.layers:
                bound = 1.0 / math.sqrt(layer.weight.shape[1])
                layer.weight.uniform_(-bound, bound, generator=generator)
                layer.bias.uniform_(-bound, bound, generator=generator)

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(albedo (N, 3), normal (N, 3) unnormalised)`` at ``points`` (N, 3) metres."""
        u01 = ((points - self.centre) / self.half_extent + 1.0) * 0.5
        h, _ = self.encoding(u01)
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            h = layer(h)
            if i < last:
                h = F.relu(h)
        return self.albedo_max * torch.sigmoid(h[:, :3]), h[:, 3:]

    def _device(self) -> torch.device:
        return self.centre.device

    def to_state(self) -> dict[str, Any]:
        """JSON-able config plus CPU tensors, for ``torch.save``; :meth:`from_state` rebuilds the field."""
        return {"format": "ultrastage-appearance/1",
                "config": {"bounds": self.bounds.tolist(), "encoding": to_dict(self.encoding_config),
                           "hidden_width": self.hidden_width, "hidden_layers": self.hidden_layers,
                           "albedo_max": self.albedo_max},
                "tensors": {k: v.detach().cpu().clone() for k, v in self.state_dict().items()}}

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> "AppearanceField":
        """Rebuild a field saved by :meth:`to_state` (on the CPU)."""
        if not isinstance(state, dict) or state.get("format") != "ultrastage-appearance/1":
            raise ValueError("not an appearance-field state (expected format 'ultrastage-appearance/1')")
        cfg = state["config"]
        field_ = cls(np.asarray(cfg["bounds"]), HashGridConfig(**cfg["encoding"]), cfg["hidden_width"],
                     cfg["hidden_layers"], cfg["albedo_max"])
        field_.load_state_dict(state["tensors"])
        return field_


# ------------------------------------------------------------------------------------------------ geometry


class _Surface:
    """The SDF the weights come from (an :class:`SDFField` or an :data:`SDFCallable`), evaluated in chunks."""

    def __init__(self, geometry: Union[SDFField, SDFCallable], bounds: np.ndarray | None, chunk: int = 65536):
        if isinstance(geometry, SDFField):
            self.field: SDFField | None = geometry
            self.function: SDFCallable | None = None
            b = geometry.bounds if bounds is None else bounds
        elif callable(geometry):
            if bounds is None:
                raise ValueError("bounds are required when the geometry is a function")
            self.field, self.function, b = None, geometry, bounds
        else:
            raise ValueError(f"geometry must be an SDFField or a function points -> (sdf, gradient), got "
                             f"{type(geometry).__name__}")
        self.bounds = check_bounds(b)
        self.chunk = chunk
        self._proposals: dict[tuple[float, str], ProposalGrid] = {}

    def _eval(self, points: torch.Tensor, gradient: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        values, grads = [], []
        with torch.no_grad():
            for s in range(0, points.shape[0], self.chunk):
                p = points[s:s + self.chunk]
                if self.field is not None:
                    q = p.to(self.field._device())
                    if gradient:
                        f, g = self.field.sdf_and_gradient(q, "analytic")
                    else:
                        f, g = self.field(q), None
                else:
                    f_np, g_np = self.function(p.detach().cpu().numpy().astype(np.float32))
                    f_np = np.asarray(f_np, np.float32).reshape(-1)
                    g_np = np.asarray(g_np, np.float32).reshape(-1, 3)
                    if f_np.shape[0] != p.shape[0] or g_np.shape[0] != p.shape[0]:
                        raise ValueError(f"the SDF function returned {f_np.shape} and {g_np.shape} for "
                                         f"{p.shape[0]} points; expected (N,) and (N, 3)")
                    f, g = torch.from_numpy(f_np), torch.from_numpy(g_np)
                values.append(f.to(points.device).float())
                if gradient:
                    grads.append(g.to(points.device).float())
        sdf = torch.nan_to_num(torch.cat(values), nan=1.0, posinf=1.0, neginf=-1.0)
        return sdf, (torch.nan_to_num(torch.cat(grads)) if gradient else None)

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        """SDF at points (what :class:`ProposalGrid` refreshes from)."""
        return self._eval(points, gradient=False)[0]

    def sdf_and_gradient(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        sdf, grad = self._eval(points, gradient=True)
        assert grad is not None
        return sdf, grad

    def proposal(self, voxel_m: float, device: torch.device) -> ProposalGrid:
        key = (float(voxel_m), str(device))
        if key not in self._proposals:
            grid = ProposalGrid(self.bounds, voxel_m, device)
            grid.refresh(self)
            self._proposals[key] = grid
        return self._proposals[key]


@dataclass
class _RaySamples:
    points: torch.Tensor  # (R, M, 3) kept samples
    weights: torch.Tensor  # (R, M) their NeuS weights, normalised to sum 1 (0 on rays without a crossing)
    opacity: torch.Tensor  # (R,) sum of all the window's weights
    kept_fraction: torch.Tensor  # (R,) share of the window's weight in the kept samples
    depth_m: torch.Tensor  # (R,) camera z of the weighted mean sample


def _ray_samples(surface: _Surface, K: np.ndarray, T: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                 depth_m: np.ndarray | None, config: AppearanceFieldConfig, device: torch.device,
                 chunk_rays: int = 8192) -> _RaySamples:
    """Kept NeuS samples of the pixels (rows, cols) of one camera (see the module docstring)."""
    dirs_np, origin = pixel_rays(K, T, cols, rows)[0], camera_centre(T)
    R_rot = T[:, :3]
    n = len(rows)
    t_c = np.full(n, np.nan)
    if depth_m is not None:
        z = depth_m[rows, cols].astype(np.float64)
        cos_axis = dirs_np @ R_rot[2]  # camera z per unit length along the ray
        ok = (z > 0) & np.isfinite(z) & (cos_axis > 1e-6)
        t_c[ok] = z[ok] / cos_axis[ok]
    else:
        near, far = ray_box(origin[None], dirs_np, surface.bounds)
        meets = np.nonzero(far > near + 1e-9)[0]
        if len(meets):
            grid = surface.proposal(config.proposal_voxel_m, device)
            for s in range(0, len(meets), chunk_rays):
                sel = meets[s:s + chunk_rays]
                d = torch.from_numpy(dirs_np[sel].astype(np.float32)).to(device)
                o = torch.from_numpy(origin.astype(np.float32)).to(device).expand(len(sel), 3)
                tc, crossed, _ = grid.first_crossing(o, d, torch.from_numpy(near[sel].astype(np.float32)).to(device),
                                                     torch.from_numpy(far[sel].astype(np.float32)).to(device))
                tc = tc.cpu().numpy().astype(np.float64)
                crossed = crossed.cpu().numpy()
                t_c[sel[crossed]] = tc[crossed]
    Kn, M = config.samples_per_ray, config.samples_kept
    points = torch.zeros((n, M, 3), dtype=torch.float32, device=device)
    weights = torch.zeros((n, M), dtype=torch.float32, device=device)
    opacity = torch.zeros(n, dtype=torch.float32, device=device)
    kept_fraction = torch.zeros(n, dtype=torch.float32, device=device)
    depth = torch.zeros(n, dtype=torch.float32, device=device)
    live = np.nonzero(np.isfinite(t_c))[0]
    w = config.window_m
    spacing = 2.0 * w / Kn
    offsets = torch.tensor(-w + (np.arange(Kn) + 0.5) * spacing, dtype=torch.float32, device=device)
    o_t = torch.from_numpy(origin.astype(np.float32)).to(device)
    z_axis = torch.from_numpy(R_rot[2].astype(np.float32)).to(device)
    for s in range(0, len(live), chunk_rays):
        sel = live[s:s + chunk_rays]
        idx = torch.from_numpy(sel).to(device)
        d = torch.from_numpy(dirs_np[sel].astype(np.float32)).to(device)
        t = torch.from_numpy(t_c[sel].astype(np.float32)).to(device).unsqueeze(1) + offsets.unsqueeze(0)  # (r, Kn)
        pts = o_t + t.unsqueeze(-1) * d.unsqueeze(1)
        sdf, grad = surface.sdf_and_gradient(pts.reshape(-1, 3))
        wts, _ = neus_composite(sdf.view(-1, Kn), grad.view(-1, Kn, 3), d,
                                torch.full((len(sel),), spacing, device=device), config.inv_s, 1.0)
        total = wts.sum(1)
        top_w, top_i = torch.topk(wts, M, dim=1)
        kept = top_w.sum(1, keepdim=True)
        norm_w = torch.where(kept > 1e-12, top_w / kept.clamp_min(1e-12), torch.zeros_like(top_w))
        points[idx] = pts.gather(1, top_i.unsqueeze(-1).expand(-1, -1, 3))
        weights[idx] = norm_w
        opacity[idx] = total
        kept_fraction[idx] = kept[:, 0] / total.clamp_min(1e-12)
        t_mean = (t.gather(1, top_i) * norm_w).sum(1)
        depth[idx] = t_mean * (d @ z_axis)
    return _RaySamples(points=points, weights=weights, opacity=opacity, kept_fraction=kept_fraction, depth_m=depth)


def _composite(field_: AppearanceField, points: torch.Tensor,
               weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Albedo (R, 3) and unnormalised normal (R, 3) of rays from their kept samples (R, M, 3) and weights (R, M)."""
    R, M = weights.shape
    albedo, normal = field_(points.reshape(-1, 3))
    w = weights.unsqueeze(-1)
    return (w * albedo.view(R, M, 3)).sum(1), (w * normal.view(R, M, 3)).sum(1)


# ------------------------------------------------------------------------------------------------ inputs


@dataclass
class AppearanceView:
    """One training view.

    Attributes:
        albedo: float32 (H, W, 3) linear sRGB albedo (photometric ``full_on / white_reference``).
        normals_world: float32 (H, W, 3) unit normals, stage frame (0 where undefined).
        valid: bool (H, W) where the maps are trusted (photometric alpha > 0.5 and on the mask).
        K: (3, 3) intrinsics. cam_from_world: (3, 4) ``[R | t]`` (OpenCV).
        depth_m: optional float32 (H, W) camera z of the surface (e.g. the mesh rendered from the camera;
            0 where none): the centre of each pixel's sample window. None: the SDF's first zero crossing.
    """

    albedo: np.ndarray
    normals_world: np.ndarray
    valid: np.ndarray
    K: np.ndarray
    cam_from_world: np.ndarray
    depth_m: np.ndarray | None = None


@dataclass
class AppearanceResult:
    """Output of :func:`train_appearance_field`.

    Attributes:
        field: the trained :class:`AppearanceField`, on the CPU, in eval mode.
        history: lists keyed by ``iteration``, ``seconds`` (training time, sampling not included), ``loss``,
            ``albedo_l1``, ``normal_deg`` (mean angle over the pixels drawn), ``lr``.
        stats: ``device``, ``time_s`` (sampling + training), ``sampling_time_s`` (samples and weights of the
            training pixels), ``train_time_s``, ``training_pixels`` (valid, not grazing, opaque),
            ``valid_pixels``, ``dropped_grazing``, ``dropped_transparent``, ``iterations``, ``parameters``.
    """

    field: AppearanceField
    history: dict[str, list]
    stats: dict[str, Any]


def _check_depth(depth_m: np.ndarray | None, shape: tuple[int, int], where: str) -> np.ndarray | None:
    if depth_m is None:
        return None
    d = np.asarray(depth_m, np.float32)
    if d.shape != shape:
        raise ValueError(f"{where}: depth_m must be (H, W) = {shape}, got {d.shape}")
    return np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0)


def _check_views(views: Sequence[AppearanceView]) -> list[tuple[np.ndarray, np.ndarray]]:
    check_view_list(views, AppearanceView)
    cams = []
    for i, v in enumerate(views):
        valid = np.asarray(v.valid)
        if valid.ndim != 2 or min(valid.shape) < 1:
            raise ValueError(f"views[{i}].valid must be (H, W), got shape {valid.shape}")
        H, W = valid.shape
        for name in ("albedo", "normals_world"):
            check_view_map(getattr(v, name), (H, W, 3), f"views[{i}].{name}", valid=valid)
        _check_depth(v.depth_m, (H, W), f"views[{i}]")
        cams.append(check_camera(v.K, v.cam_from_world, f"views[{i}]"))
    if not any(np.asarray(v.valid).any() for v in views):
        raise ValueError("no view has a valid pixel: nothing to train on")
    return cams


# ------------------------------------------------------------------------------------------------ training


@dataclass
class AppearanceSamples:
    """The training pixels with their kept samples, weights and targets (what training draws from).

    The geometry is frozen, so these are computed once (:func:`sample_training_pixels`) and can be reused by
    several trainings with the same sampling fields (e.g. of different lengths).

    Attributes:
        points: float32 (N, M, 3) kept sample positions of the N training pixels, metres.
        weights: float32 (N, M) their NeuS weights normalised to sum 1 per pixel.
        albedo: float32 (N, 3) target albedo. normals_world: float32 (N, 3) target unit normals.
        bounds: (2, 3) the field's box.
        stats: ``sampling_time_s``, ``valid_pixels``, ``training_pixels``, ``dropped_grazing``,
            ``dropped_transparent``, ``kept_weight_fraction`` (mean share of a pixel's weight in its kept samples).
        sampling: the config fields the samples depend on (checked against the training config).
    """

    points: np.ndarray
    weights: np.ndarray
    albedo: np.ndarray
    normals_world: np.ndarray
    bounds: np.ndarray
    stats: dict[str, Any]
    sampling: dict[str, Any]


_SAMPLING_FIELDS = ("samples_per_ray", "samples_kept", "window_m", "inv_s", "min_opacity", "proposal_voxel_m",
                    "grazing_cos_min")


def sample_training_pixels(views: Sequence[AppearanceView], geometry: Union[SDFField, SDFCallable],
                           config: AppearanceFieldConfig = APPEARANCE_PRESETS["cpu"],
                           bounds: np.ndarray | None = None) -> AppearanceSamples:
    """Samples, NeuS weights and targets of every training pixel (valid, not grazing, opaque).

    Args:
        views, geometry, config, bounds: as in :func:`train_appearance_field` (only the sampling fields of the
            config, ``device`` and ``threads`` matter here).

    Returns:
        :class:`AppearanceSamples`.

    Raises:
        ValueError: bad views, geometry, bounds or config, or no valid pixel with an opaque surface.
    """
    _check_config(config)
    cams = _check_views(views)
    surface = _Surface(geometry, bounds)
    device = resolve_device(config.device)
    with torch_threads(config.threads):
        return _sample_views(views, cams, surface, config, device)


def _sample_views(views, cams, surface: _Surface, config: AppearanceFieldConfig,
                  device: torch.device) -> AppearanceSamples:
    t_start = time.perf_counter()
    pts_all, w_all, alb_all, nrm_all = [], [], [], []
    valid_total = dropped_grazing = dropped_transparent = 0
    kept_sum = 0.0
    for v, (K, T) in zip(views, cams):
        valid = np.asarray(v.valid, bool)
        rows, cols = np.nonzero(valid)
        valid_total += len(rows)
        normals = np.asarray(v.normals_world, np.float32)[rows, cols]
        if config.grazing_cos_min > 0:
            d = pixel_rays(K, T, cols, rows)[0]
            cos = (normals.astype(np.float64) * d).sum(1)
            keep = cos <= -config.grazing_cos_min
            dropped_grazing += int((~keep).sum())
            rows, cols, normals = rows[keep], cols[keep], normals[keep]
        if len(rows) == 0:
            continue
        samples = _ray_samples(surface, K, T, rows, cols, _check_depth(v.depth_m, valid.shape, "view"), config,
                               device)
        opaque = (samples.opacity > config.min_opacity).cpu().numpy()
        dropped_transparent += int((~opaque).sum())
        sel = torch.from_numpy(np.nonzero(opaque)[0]).to(device)
        kept_sum += float(samples.kept_fraction[sel].sum())
        pts_all.append(samples.points[sel].cpu().numpy())
        w_all.append(samples.weights[sel].cpu().numpy())
        alb_all.append(np.asarray(v.albedo, np.float32)[rows[opaque], cols[opaque]])
        nrm_all.append(normals[opaque])
    n_pix = sum(len(p) for p in pts_all)
    if n_pix == 0:
        raise ValueError("no valid training pixel has an opaque surface (check the geometry, cameras and inv_s)")
    normals = np.concatenate(nrm_all)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-8)
    stats = {"sampling_time_s": time.perf_counter() - t_start, "valid_pixels": valid_total,
             "training_pixels": n_pix, "dropped_grazing": dropped_grazing, "dropped_transparent": dropped_transparent,
             "kept_weight_fraction": kept_sum / n_pix}
    return AppearanceSamples(points=np.concatenate(pts_all), weights=np.concatenate(w_all),
                             albedo=np.concatenate(alb_all), normals_world=normals.astype(np.float32),
                             bounds=surface.bounds.copy(), stats=stats,
                             sampling={k: getattr(config, k) for k in _SAMPLING_FIELDS})


def train_appearance_field(views: Sequence[AppearanceView] | AppearanceSamples,
                           geometry: Union[SDFField, SDFCallable, None],
                           config: AppearanceFieldConfig = APPEARANCE_PRESETS["cpu"], bounds: np.ndarray | None = None,
                           progress: Callable[[int, dict], None] | None = None,
                           checkpoint: Callable[[int, AppearanceField], None] | None = None) -> AppearanceResult:
    """Train the albedo/normal field on the valid pixels of ``views``, volume rendered with ``geometry``'s weights.

    Args:
        views: calibrated training views (:class:`AppearanceView`), stage frame; or the
            :class:`AppearanceSamples` of :func:`sample_training_pixels` (then ``geometry`` and ``bounds`` are
            not used, and the config's sampling fields must be those the samples were made with).
        geometry: the subject's SDF: an :class:`~stages.numerics.sdf.SDFField` (e.g. the geometry stage's
            ``sdf.pt`` through ``SDFField.from_state``) or a function ``points (N, 3) float32 -> (sdf (N,)
            metres, gradient (N, 3))``.
        config: :class:`AppearanceFieldConfig` (presets in ``APPEARANCE_PRESETS``); ``inv_s`` should be the
            SDF's final sharpness.
        bounds: (2, 3) box of the field (and of the SDF's crossings); defaults to the SDFField's bounds,
            required with a function.
        progress: called as ``progress(iteration, losses)`` every ``log_every`` steps.
        checkpoint: called as ``checkpoint(iteration, field)`` every ``log_every`` steps (on the training
            device, in eval mode; do not modify it), e.g. to measure error against training time.

    Returns:
        :class:`AppearanceResult`.

    Raises:
        ValueError: bad views (shapes, cameras, non-finite maps, no valid pixel), bad geometry or bounds, a bad
            config, samples made with other sampling fields, or no valid pixel with an opaque surface.
    """
    _check_config(config)
    if isinstance(views, AppearanceSamples):
        samples = views
        wanted = {k: getattr(config, k) for k in _SAMPLING_FIELDS}
        if samples.sampling != wanted:
            raise ValueError(f"the samples were made with {samples.sampling}, the config asks for {wanted}")
        n = len(samples.points)
        m = config.samples_kept
        if (n == 0 or samples.points.shape != (n, m, 3) or samples.weights.shape != (n, m)
                or samples.albedo.shape != (n, 3) or samples.normals_world.shape != (n, 3)):
            raise ValueError("AppearanceSamples arrays are inconsistent (points (N, M, 3), weights (N, M), albedo "
                             "and normals_world (N, 3), N > 0)")
    else:
        samples = sample_training_pixels(views, geometry, config, bounds)
    device = resolve_device(config.device)
    with torch_threads(config.threads):
        return _train(samples, config, progress, checkpoint, device)


def _train(samples: AppearanceSamples, config: AppearanceFieldConfig, progress, checkpoint,
           device: torch.device) -> AppearanceResult:
    t_start = time.perf_counter()
    generator = torch.Generator().manual_seed(config.seed)
    bank_pts = torch.from_numpy(np.ascontiguousarray(samples.points, np.float32)).to(device)
    bank_w = torch.from_numpy(np.ascontiguousarray(samples.weights, np.float32)).to(device)
    bank_alb = torch.from_numpy(np.ascontiguousarray(samples.albedo, np.float32)).to(device)
    bank_nrm = torch.from_numpy(np.ascontiguousarray(samples.normals_world, np.float32)).to(device)
    n_pix = int(bank_pts.shape[0])

    # The field and the optimiser (Instant-NGP's Adam; sdf.py's warm-up + cosine schedule).
    field_ = AppearanceField(samples.bounds, config.encoding, config.hidden_width, config.hidden_layers,
                             config.albedo_max, seed=config.seed).to(device)
    mlp = [p for name, p in field_.named_parameters() if not name.startswith("encoding.")]
    optimiser = instant_ngp_adam([{"params": [field_.encoding.table]}, {"params": mlp}], config.learning_rate)
    keys = ("loss", "albedo_l1", "normal_deg", "lr")
    history: dict[str, list] = {k: [] for k in ("iteration", "seconds") + keys}
    sums = {"loss": 0.0, "albedo_l1": 0.0, "normal_deg": 0.0}
    count = 0
    outside = 0.0  # seconds spent in the callbacks, not training
    for it in range(config.iterations):
        lr = config.learning_rate * lr_factor(it, config)
        optimiser.param_groups[0]["lr"] = lr
        optimiser.param_groups[1]["lr"] = lr * config.mlp_lr_factor
        pick = torch.randint(0, n_pix, (config.rays_per_batch,), generator=generator).to(device)
        albedo, normal = _composite(field_, bank_pts[pick], bank_w[pick])
        diff = albedo - bank_alb[pick]
        albedo_loss = diff.abs().mean() if config.albedo_loss == "l1" else (diff * diff).mean()
        cos = F.cosine_similarity(normal, bank_nrm[pick], dim=-1, eps=1e-8)
        loss = config.weight_albedo * albedo_loss + config.weight_normal * (1.0 - cos).mean()
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        sums["loss"] += float(loss.detach())
        sums["albedo_l1"] += float(diff.detach().abs().mean())
        sums["normal_deg"] += float(torch.rad2deg(torch.acos(cos.detach().clamp(-1, 1))).mean())
        count += 1
        if (it + 1) % config.log_every == 0 or it + 1 == config.iterations:
            history["iteration"].append(it + 1)
            history["seconds"].append(time.perf_counter() - t_start - outside)
            for k in sums:
                history[k].append(sums[k] / count)
            history["lr"].append(lr)
            tick = time.perf_counter()
            if progress is not None:
                progress(it + 1, {k: history[k][-1] for k in keys})
            if checkpoint is not None:
                field_.eval()
                checkpoint(it + 1, field_)
                field_.train()
            outside += time.perf_counter() - tick
            sums = {k: 0.0 for k in sums}
            count = 0
    field_ = field_.cpu().eval()
    train_s = time.perf_counter() - t_start - outside
    stats = dict(samples.stats)
    stats.update(device=str(device), train_time_s=train_s, time_s=train_s + samples.stats["sampling_time_s"],
                 iterations=config.iterations, parameters=int(sum(p.numel() for p in field_.parameters())))
    return AppearanceResult(field=field_, history=history, stats=stats)


# ------------------------------------------------------------------------------------------------ render


def render_appearance(field_: AppearanceField, geometry: Union[SDFField, SDFCallable], K: np.ndarray,
                      cam_from_world: np.ndarray, height: int, width: int, depth_m: np.ndarray | None = None,
                      config: AppearanceFieldConfig = APPEARANCE_PRESETS["cpu"], bounds: np.ndarray | None = None,
                      chunk: int = 16384) -> dict[str, np.ndarray]:
    """Volume-render the field's albedo and normal maps from a camera.

    Args:
        field_: the trained field.
        geometry: the SDF it was trained with (see :func:`train_appearance_field`).
        K, cam_from_world: the camera (OpenCV). height, width: image size.
        depth_m: optional (H, W) camera z of the surface (0 where none) centring each pixel's window; None:
            the SDF's first zero crossing (cached voxel grid).
        config: the sampling fields (``samples_per_ray``, ``samples_kept``, ``window_m``, ``inv_s``,
            ``min_opacity``, ``proposal_voxel_m``), ``device`` and ``threads``; use the training config.
        bounds: as in :func:`train_appearance_field`.

    Returns:
        ``albedo`` (H, W, 3) float32, ``normals_world`` (H, W, 3) float32 unit, ``opacity`` (H, W) float32,
        ``valid`` (H, W) bool (opacity > ``min_opacity``), ``depth_m`` (H, W) float32 (weighted camera z); maps
        are 0 where not valid. No NaN or Inf.

    Raises:
        ValueError: a bad camera, size, depth map, geometry or config.
    """
    _check_config(config)
    if not isinstance(field_, AppearanceField):
        raise ValueError(f"field_ must be an AppearanceField, got {type(field_).__name__}")
    K, T = check_camera(K, cam_from_world)
    if int(height) < 1 or int(width) < 1:
        raise ValueError(f"height and width must be >= 1, got {height}, {width}")
    H, W = int(height), int(width)
    depth = _check_depth(depth_m, (H, W), "render_appearance")
    surface = _Surface(geometry, bounds)
    device = resolve_device(config.device)
    with torch_threads(config.threads):
        rows, cols = np.mgrid[0:H, 0:W]
        rows, cols = rows.ravel(), cols.ravel()
        if depth is not None:  # only pixels with a surface
            keep = depth[rows, cols] > 0
            rows, cols = rows[keep], cols[keep]
        samples = _ray_samples(surface, K, T, rows, cols, depth, config, device)
        valid = samples.opacity > config.min_opacity
        albedo = torch.zeros((len(rows), 3), device=device)
        normal = torch.zeros((len(rows), 3), device=device)
        model = field_.to(device)
        idx = torch.nonzero(valid).view(-1)
        with torch.no_grad():
            for s in range(0, int(idx.numel()), chunk):
                sel = idx[s:s + chunk]
                a, n = _composite(model, samples.points[sel], samples.weights[sel])
                albedo[sel] = a
                normal[sel] = F.normalize(n, dim=-1, eps=1e-8)
        field_.cpu()
    valid_np = valid.cpu().numpy()
    out = {"albedo": np.zeros((H, W, 3), np.float32), "normals_world": np.zeros((H, W, 3), np.float32),
           "opacity": np.zeros((H, W), np.float32), "valid": np.zeros((H, W), bool),
           "depth_m": np.zeros((H, W), np.float32)}
    out["albedo"][rows, cols] = np.where(valid_np[:, None], albedo.cpu().numpy(), 0.0)
    out["normals_world"][rows, cols] = np.where(valid_np[:, None], normal.cpu().numpy(), 0.0)
    out["opacity"][rows, cols] = samples.opacity.cpu().numpy()
    out["valid"][rows, cols] = valid_np
    out["depth_m"][rows, cols] = np.where(valid_np, samples.depth_m.cpu().numpy(), 0.0)
    for k in ("albedo", "normals_world", "opacity", "depth_m"):
        out[k] = np.nan_to_num(out[k], nan=0.0, posinf=0.0, neginf=0.0)
    return out
