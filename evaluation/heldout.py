"""Held-out view protocol of the paper's table 1: synthesise the G-buffers of captured views from the others.

For each held-out camera of an action: the release mesh is rendered from it (depth), its albedo and
normal maps are reprojected from the other cameras (:func:`stages.numerics.gbuffer.reproject_gbuffer`;
held-out cameras are never sources) and compared with

- the held-out **photometric** maps (the paper's protocol) over pixels valid in both: the held-out
  photometric alpha > 0.5, its mask, and a synthesised value;
- with ``truth_dir``, the simulator's **ground truth** (suffix ``_truth``) over the true mask where a
  value was synthesised.

**Albedo scale.** The synthesised albedo is made of the release's photometric albedos (``full_on /
white_reference``), so it is on exactly the scale of the held-out photometric albedo it is compared with:
no gain is fitted. That photometric albedo still holds the ambient occlusion of the lit hemisphere (the
paper says so); the simulator's albedo does not, so the ``_truth`` albedo scores include that bias (the
bench reports the held-out photometric map's own score against the truth beside it).

**View-dependent albedo** (``albedo_model="view_dependent"``, the default). The white-light albedo a camera
measures is the diffuse albedo plus the specular reflection of the white light, which depends on the view
(larger at grazing views; stages.diffuse_normals.DiffuseNormalsConfig.albedo), and near a held-out view's
silhouette that view sees the surface at grazing angles that the nearest sources, weighted to the ones that
see it head-on, do not. So the held-out white-light albedo is predicted (:func:`predict_white_albedo`) as the
blend of the other cameras' ``albedo_diffuse`` (their white-light albedo less their own specular light) plus
the GGX reflection of the white light for the held-out camera's view directions, with the blended
``normal_diffuse``, the materials' roughness texture seen through the textured mesh and the materials' F0
(:func:`stages.numerics.specular_normals.white_light_specular`, the model that fitted them). The roughness
texture, like the mesh, is fitted from every camera of the action, the held-out ones included.
``albedo_model="white"`` blends the sources' white-light albedo as they are; releases without
``albedo_diffuse``, ``normal_diffuse``, the roughness texture or the textured mesh fall back to it.
bench/bench_gbuffer.py reports both models. Against the simulator's albedo (``_truth``) the prediction
scores lower than the plain blend (it adds the specular light the truth lacks); the ``albedo_diffuse``
protocol is the one to compare with the truth (:mod:`evaluation.release`'s
``heldout_albedo_*_diffuse_truth``).

**Occlusion edges.** A camera pixel integrates the light over its square: where an arm passes in front of
the torso the held-out photometric pixel mixes both sides, while a G-buffer sampled at the pixel centre
takes one side wholly. The pixels at an occlusion edge of the mesh (their 3 x 3 neighbourhood on the
surface and more than ``edge_jump_m`` deep; :func:`stages.numerics.raycast.occlusion_edges`, which also
takes in surfaces seen obliquely enough) are synthesised from ``edge_samples`` x ``edge_samples`` sub-pixel
rays, averaged over those that hit (:func:`stages.numerics.gbuffer.reproject_gbuffer`'s ``subpixel``);
bench/bench_gbuffer.py reports the metrics against the rays per side. Silhouette pixels and the interior are
left at their centre: sub-sampled, silhouette rays graze the surface where the photometric maps are worst,
and the interior's texture is low-passed once more.

**Blend.** With an enabled ``learned_blend`` the sources are blended by a network trained leave one out
on the action's other cameras (:mod:`stages.numerics.learned_blend`; the held-out cameras are neither targets nor
sources of that training), else by the heuristic weights of ``reproject_gbuffer``.

Reads the release only through :mod:`manifests` (``open_release(path).action(id)``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from artifacts.facade import transforms_cameras
from artifacts.camera import Camera
from stages.numerics.gbuffer import SourceView, reproject_gbuffer
from stages.numerics.metrics import angular_error_deg, downsample_to, ssim

DEFAULT_HELDOUT = ("00005", "00021")
ALBEDO_MODELS = ("view_dependent", "white")
EDGE_SAMPLES = 3
EDGE_JUMP_M = 0.01
PAPER_TABLE1 = {"heldout_albedo_psnr_db": 30.87, "heldout_albedo_ssim": 0.972, "heldout_albedo_rmse": 0.029,
                "heldout_normal_mean_deg": 4.30, "heldout_normal_under5_pct": 80.8,
                "heldout_normal_under25_pct": 96.3}


def spread_heldout(cameras: dict[str, Camera], n: int = 2) -> tuple[str, ...]:
    """``n`` cameras spread around the subject: greedy farthest-point choice on the directions of the
    camera centres from the stage centre, starting from the first camera id."""
    ids = sorted(cameras)
    dirs = np.stack([cameras[c].centre for c in ids])
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    chosen = [0]
    while len(chosen) < min(n, len(ids)):
        closeness = np.max(dirs @ dirs[chosen].T, axis=1)
        closeness[chosen] = np.inf
        chosen.append(int(np.argmin(closeness)))
    return tuple(ids[i] for i in chosen)


class ActionGBuffers:
    """The cameras, maps and mesh of one released action, with the mesh depth of each camera cached."""

    def __init__(self, release_dir: str | Path, action_id: str, diffuse_normals: bool = False):
        from manifests import open_release

        self.view = open_release(release_dir).action(action_id)
        self.diffuse_normals = diffuse_normals  # the specular-fitted normal maps as sources and references
        self.diffuse_albedo = False  # the white-light albedo less the fitted specular light (albedo_diffuse)
        self.action_id = action_id
        self.cameras = transforms_cameras(self.view.transforms())
        self.vertices, self.faces = self.view.mesh()
        self._scene = None  # one ray-casting scene of the mesh for every camera, built on first use
        self._render: dict[str, dict[str, np.ndarray]] = {}
        self._subpixel: dict[tuple, dict[str, np.ndarray]] = {}
        self._sources: dict[str, SourceView] = {}
        # shared by every variant (with_normals / with_albedo): the textured mesh, roughness and F0 of the
        # specular prediction
        self._shared: dict[str, Any] = {}
        self._variants: dict[tuple[bool, bool], ActionGBuffers] = {}  # this object's, see variant()

    def with_normals(self, diffuse: bool) -> ActionGBuffers:
        """The same action with the other normal maps as sources and references (``normal_diffuse`` or eq.
        1's), sharing this one's mesh, ray-casting scene and cached depth renders."""
        other = object.__new__(type(self))
        other.__dict__.update(self.__dict__)
        other.diffuse_normals = diffuse
        other._sources = {}
        other._variants = {}
        return other

    def with_albedo(self, diffuse: bool) -> ActionGBuffers:
        """The same action with the other albedo maps as sources and references (``albedo_diffuse`` or the
        white-light ``albedo``), sharing the mesh, scene and cached depth renders."""
        other = self.with_normals(self.diffuse_normals)
        other.diffuse_albedo = diffuse
        return other

    def render(self, cam: str) -> dict[str, np.ndarray]:
        """The mesh seen by camera ``cam`` (render_mesh output, cached)."""
        from stages.numerics.raycast import mesh_scene, render_mesh

        if cam not in self._render:
            if self._scene is None:
                self._scene = mesh_scene(self.vertices, self.faces)
            c = self.cameras[cam]
            self._render[cam] = render_mesh(None, None, c.K, c.cam_from_world, c.height, c.width,
                                            scene=self._scene)
        return self._render[cam]

    def edge_subpixel(self, cam: str, samples: int, jump_m: float) -> dict[str, np.ndarray] | None:
        """Sub-pixel ray depths (``samples`` x ``samples`` per pixel) at camera ``cam``'s pixels at an occlusion
        edge of the mesh (:func:`stages.numerics.raycast.occlusion_edges`), with their ``rows`` and ``cols``: the
        ``subpixel`` input of :func:`reproject_gbuffer`. None for ``samples`` <= 1."""
        from stages.numerics.raycast import mesh_scene, occlusion_edges, subpixel_depths

        if samples <= 1:
            return None
        key = (cam, int(samples), float(jump_m))
        if key not in self._subpixel:
            depth = self.render(cam)["depth_m"]
            if self._scene is None:
                self._scene = mesh_scene(self.vertices, self.faces)
            rows, cols = np.nonzero(occlusion_edges(depth, jump_m))
            c = self.cameras[cam]
            sub = subpixel_depths(c.K, c.cam_from_world, c.height, c.width, rows, cols, int(samples),
                                  self._scene)
            self._subpixel[key] = sub | {"rows": rows, "cols": cols}
        return self._subpixel[key]

    def variant(self, diffuse_normals: bool, diffuse_albedo: bool) -> ActionGBuffers:
        """:meth:`with_normals` / :meth:`with_albedo` kept for reuse (their source maps are read once)."""
        key = (bool(diffuse_normals), bool(diffuse_albedo))
        if (self.diffuse_normals, self.diffuse_albedo) == key:
            return self
        if key not in self._variants:
            self._variants[key] = self.with_normals(key[0]).with_albedo(key[1])
        return self._variants[key]

    def predicts_specular(self) -> bool:
        """Whether the release holds what :func:`predict_white_albedo` needs: ``albedo_diffuse`` and
        ``normal_diffuse`` maps, the roughness texture and the textured mesh."""
        return {"albedo_diffuse", "normal_diffuse", "texture_roughness", "mesh_textured"} <= set(self.view.kinds)

    def materials_f0(self) -> float:
        """The Fresnel F0 the release's roughness was fitted with (the facade's, from the release's config)."""
        if "f0" not in self._shared:
            self._shared["f0"] = self.view.artifacts.materials_f0()
        return self._shared["f0"]

    def roughness(self, cam: str) -> np.ndarray:
        """(H, W) float32 roughness of the materials' texture seen by camera ``cam`` through the textured mesh;
        the texture's median where that mesh misses a pixel."""
        from artifacts.facade import load_atlas_mesh
        from stages.numerics.raycast import mesh_scene
        from stages.diffuse_normals import materials_roughness

        if "atlas" not in self._shared:
            vertices, faces, atlas = load_atlas_mesh(self.view.path("mesh_textured"))
            texture = self.view.texture("roughness")
            fitted = texture[np.isfinite(texture) & (texture > 0)]
            self._shared["atlas"] = (mesh_scene(vertices, faces), atlas, texture,
                                     float(np.median(fitted)) if fitted.size else 0.5)
        scene, atlas, texture, fallback = self._shared["atlas"]
        c = self.cameras[cam]
        return materials_roughness(scene, atlas, texture, c, c.height, c.width, fallback)[0]

    def photometric(self, cam: str) -> dict[str, np.ndarray]:
        """Photometric maps of ``cam``: normal (H, W, 3), albedo (H, W, 3), alpha (H, W), mask (H, W) bool."""
        return {"normal": self.view.normals(cam, diffuse=self.diffuse_normals),
                "albedo": self.view.albedo(cam, diffuse=self.diffuse_albedo),
                "alpha": self.view.normal_alpha(cam), "mask": self.view.mask(cam)}

    def source(self, cam: str) -> SourceView:
        """Camera ``cam`` as a reprojection source (valid = alpha > 0.5 and mask), depth rendered lazily
        only for the sources actually looked up."""
        if cam not in self._sources:
            maps = self.photometric(cam)
            c = self.cameras[cam]
            self._sources[cam] = _LazySource(self, cam, maps, c)
        return self._sources[cam]


class _LazySource(SourceView):
    """A SourceView whose depth map is rendered from the mesh on first access."""

    def __init__(self, owner: ActionGBuffers, cam: str, maps: dict[str, np.ndarray], c: Camera):
        object.__setattr__(self, "_owner", owner)
        object.__setattr__(self, "_cam", cam)
        object.__setattr__(self, "normal", maps["normal"])
        object.__setattr__(self, "albedo", maps["albedo"])
        object.__setattr__(self, "valid", (maps["alpha"] > 0.5) & maps["mask"])
        object.__setattr__(self, "K", c.K)
        object.__setattr__(self, "cam_from_world", c.cam_from_world)

    def __getattr__(self, name: str):
        if name == "depth_m":
            return self._owner.render(self._cam)["depth_m"]
        raise AttributeError(name)


def compare_maps(normal: np.ndarray, albedo: np.ndarray, ref_normal: np.ndarray, ref_albedo: np.ndarray,
                 mask: np.ndarray) -> dict[str, Any]:
    """Errors of synthesised maps against reference ones over ``mask`` (H, W) bool: the pixel errors (for
    pooling over views) and the view's SSIM (mean of the SSIM map over the mask, both images zeroed
    outside it)."""
    err = angular_error_deg(normal, ref_normal)[mask].astype(np.float64)
    sq = ((albedo.astype(np.float64) - ref_albedo) ** 2)[mask].ravel()
    # SSIM windows at the mask's edge see neighbours outside it: both images hold 0 there, so what lies
    # beyond the compared pixels (background, unsynthesised pixels) neither helps nor hurts
    keep = mask[..., None]
    value = ssim(np.where(keep, albedo, 0.0), np.where(keep, ref_albedo, 0.0), mask) if mask.any() else float("nan")
    return {"angle_deg": err, "albedo_sq": sq, "ssim": float(value), "pixels": int(mask.sum())}


def summarise(parts: list[dict[str, Any]], suffix: str = "") -> dict[str, float]:
    """Pooled metrics over views: PSNR/RMSE from the pooled squared albedo error (all channels), SSIM the
    mean over views, normal statistics over the pooled pixels."""
    err = np.concatenate([p["angle_deg"] for p in parts]) if parts else np.zeros(0)
    sq = np.concatenate([p["albedo_sq"] for p in parts]) if parts else np.zeros(0)
    ssims = [p["ssim"] for p in parts if np.isfinite(p["ssim"])]
    out: dict[str, float] = {}
    if sq.size:
        mse = float(sq.mean())
        out[f"heldout_albedo_psnr_db{suffix}"] = float(10.0 * np.log10(1.0 / max(mse, 1e-12)))
        out[f"heldout_albedo_rmse{suffix}"] = float(np.sqrt(mse))
    if ssims:
        out[f"heldout_albedo_ssim{suffix}"] = float(np.mean(ssims))
    if err.size:
        out[f"heldout_normal_mean_deg{suffix}"] = float(err.mean())
        out[f"heldout_normal_median_deg{suffix}"] = float(np.median(err))
        out[f"heldout_normal_under5_pct{suffix}"] = float(100.0 * np.mean(err <= 5.0))
        out[f"heldout_normal_under25_pct{suffix}"] = float(100.0 * np.mean(err <= 25.0))
    out[f"heldout_pixels{suffix}"] = float(err.size)
    return out


def load_truth(truth_dir: Path, action_id: str, cam: str, shape: tuple[int, int]) -> dict[str, np.ndarray] | None:
    """The simulator's normal, albedo and mask of camera ``cam`` resampled to ``shape`` (H, W), or None when the
    ground truth has no normal map for it."""
    from pipeline.codecs.exr import read_exr
    from pipeline.codecs.image import mask_from_png, read_png

    base = Path(truth_dir) / action_id
    if not (base / "normal" / f"{cam}.exr").exists():
        return None
    mask = mask_from_png(read_png(base / "mask" / f"{cam}.png"))
    return {"normal": downsample_to(read_exr(base / "normal" / f"{cam}.exr")[..., :3], shape, kind="normal"),
            "albedo": downsample_to(read_exr(base / "albedo" / f"{cam}.exr")[..., :3], shape, kind="image"),
            "mask": downsample_to(mask, shape, kind="mask")}


def synthesise_heldout(data: ActionGBuffers, cam: str, heldout: Sequence[str], k: int = 6,
                       edge_samples: int = EDGE_SAMPLES, edge_jump_m: float = EDGE_JUMP_M,
                       **reproject_kwargs) -> dict[str, np.ndarray]:
    """Reproject camera ``cam``'s G-buffer from every camera not in ``heldout``, pixels at an occlusion edge of
    the mesh from ``edge_samples`` x ``edge_samples`` sub-pixel rays (1 = pixel centres only; module docstring);
    adds ``depth_m`` and ``seconds`` (reprojection time, source depth renders and sub-pixel rays included on
    first use) to the result."""
    source_ids = [c for c in sorted(data.cameras) if c not in set(heldout) and c != cam]
    sources = [data.source(c) for c in source_ids]
    c = data.cameras[cam]
    depth = data.render(cam)["depth_m"]
    start = time.perf_counter()
    subpixel = data.edge_subpixel(cam, edge_samples, edge_jump_m)
    out = reproject_gbuffer(depth, c.K, c.cam_from_world, sources, k=k, subpixel=subpixel,
                            **reproject_kwargs)
    out["seconds"] = np.float64(time.perf_counter() - start)
    out["depth_m"] = depth
    out["source_ids"] = np.asarray([source_ids[i] for i in out["sources"]])
    return out


def predict_white_albedo(data: ActionGBuffers, cam: str, heldout: Sequence[str], k: int = 6,
                         **synth_kwargs) -> dict[str, np.ndarray]:
    """The white-light albedo camera ``cam`` would measure, predicted from the other cameras (module
    docstring, *View-dependent albedo*): the blend of their ``albedo_diffuse`` plus the GGX reflection of the
    white light (:func:`stages.numerics.specular_normals.white_light_specular`) for ``cam``'s view directions,
    the blended ``normal_diffuse``, the materials' roughness and F0.

    Returns ``albedo`` (H, W, 3), ``specular`` (H, W, 3), ``valid`` (H, W) and ``seconds``; needs
    ``data.predicts_specular()``."""
    from stages.numerics.specular_normals import view_directions, white_light_specular

    diffuse = synthesise_heldout(data.variant(True, True), cam, heldout, k=k, **synth_kwargs)
    start = time.perf_counter()
    c = data.cameras[cam]
    views = view_directions(c.K, c.cam_from_world, c.height, c.width)
    specular = white_light_specular(diffuse["normal"], views, data.roughness(cam), data.materials_f0())
    valid = diffuse["valid"]
    keep = valid[..., None]
    return {"albedo": np.where(keep, diffuse["albedo"] + specular, 0.0).astype(np.float32),
            "specular": np.where(keep, specular, 0.0).astype(np.float32), "valid": valid,
            "seconds": np.float64(diffuse["seconds"] + time.perf_counter() - start)}


def heldout_metrics(release_dir: str | Path, action_id: str, heldout: Sequence[str] | None = DEFAULT_HELDOUT,
                    truth_dir: str | Path | None = None, k: int = 6, data: ActionGBuffers | None = None,
                    return_maps: bool = False, diffuse_normals: bool = False,
                    learned_blend: Any = None, albedo_model: str = "view_dependent",
                    **reproject_kwargs) -> dict[str, Any]:
    """Held-out G-buffer metrics of one action (see the module docstring).

    Args:
        release_dir: the release folder. action_id: the action.
        heldout: camera ids held out (never used as sources); None, or ids the release lacks, picks two
            spread-out cameras (:func:`spread_heldout`).
        truth_dir: ``capture/ground_truth`` for the ``_truth`` metrics (optional).
        k: sources per held-out view.
        data: an already opened :class:`ActionGBuffers` (reuses its cached depth renders).
        diffuse_normals: use the normal maps with the specular reflection fitted out (``normal_diffuse``) as
            sources and references instead of eq. 1's (ignored when ``data`` is given).
        return_maps: also return the synthesised and reference maps per view under ``"maps"``.
        learned_blend: a :class:`stages.numerics.learned_blend.LearnedBlendConfig`: train the blend on the
            cameras not held out and blend with it (None, ``enabled=False`` or fewer than 3 such cameras:
            the heuristic weights).
        albedo_model: how the white-light albedo of a held-out view is synthesised (module docstring):
            ``"view_dependent"`` (:func:`predict_white_albedo`; the ``"white"`` blend when the release lacks
            its inputs) or ``"white"`` (the blend of the other cameras' white-light albedo). Ignored when
            ``data`` compares ``albedo_diffuse`` maps (no specular light to predict).
        reproject_kwargs: passed to :func:`reproject_gbuffer` (weighting, depth_tolerance_m, ...).

    Returns:
        ``heldout_albedo_model`` (the albedo synthesis used: "view_dependent", "white" or "diffuse"),
        ``heldout_albedo_psnr_db``, ``heldout_albedo_ssim``, ``heldout_albedo_rmse``,
        ``heldout_normal_mean_deg``, ``heldout_normal_median_deg``, ``heldout_normal_under5_pct``,
        ``heldout_normal_under25_pct``, ``heldout_pixels``, ``heldout_coverage`` (share of the held-out
        masks' pixels synthesised), the same with ``_truth`` when ``truth_dir`` is given,
        ``heldout_seconds_per_view``, ``heldout_cameras`` and ``per_view`` (the metrics of each view);
        with a learned blend also ``heldout_blend_fit_s`` and ``blend`` (its training record).
        Every float is finite (metrics without pixels are left out).
    """
    data = data if data is not None else ActionGBuffers(release_dir, action_id, diffuse_normals)
    if heldout is None or not set(heldout) <= set(data.cameras) or len(set(heldout)) >= len(data.cameras):
        heldout = spread_heldout(data.cameras, 2)
    heldout = tuple(heldout)
    albedo_model = _albedo_model_used(data, albedo_model)
    blend_record = None
    fitted = _fit_blend(data, heldout, learned_blend, k, reproject_kwargs) if learned_blend is not None else None
    if fitted is not None:
        blend, blend_record = fitted
        reproject_kwargs = reproject_kwargs | {"blend": blend}
    views = [_heldout_view(data, action_id, cam, heldout, k, albedo_model, truth_dir, reproject_kwargs,
                           return_maps) for cam in heldout]
    result = _pooled_metrics(views)
    if blend_record is not None:
        result["heldout_blend_fit_s"] = float(blend_record["fit_s"])
    result["heldout_cameras"] = list(heldout)
    result["heldout_albedo_model"] = albedo_model
    result["per_view"] = {view.cam: view.metrics for view in views}
    if blend_record is not None:
        result["blend"] = blend_record
    if return_maps:
        result["maps"] = {view.cam: view.maps for view in views}
    return result


def _albedo_model_used(data: ActionGBuffers, albedo_model: str) -> str:
    """The albedo synthesis :func:`heldout_metrics` uses for ``data`` when asked for ``albedo_model``:
    "diffuse" for ``albedo_diffuse`` maps, "white" where the release lacks the view-dependent prediction's
    inputs."""
    if albedo_model not in ALBEDO_MODELS:
        raise ValueError(f"albedo_model must be one of {ALBEDO_MODELS}, got {albedo_model!r}")
    if data.diffuse_albedo:
        return "diffuse"
    if albedo_model == "view_dependent" and not data.predicts_specular():
        return "white"
    return albedo_model


def _fit_blend(data: ActionGBuffers, heldout: tuple[str, ...], config: Any, k: int,
               reproject_kwargs: dict[str, Any]) -> tuple[Any, dict[str, Any]] | None:
    """The learned blend (``config``: a ``LearnedBlendConfig``) trained on the cameras not held out, and its
    training record with ``fit_s``; None when it is disabled or fewer than 3 cameras are not held out."""
    training_ids = [c for c in sorted(data.cameras) if c not in set(heldout)]
    if not config.enabled or len(training_ids) < 3:
        return None
    from stages.numerics.learned_blend import fit_learned_blend

    start = time.perf_counter()
    training = [data.source(c) for c in training_ids]
    blend = fit_learned_blend(training, config, k=k,
                              depth_tolerance_m=reproject_kwargs.get("depth_tolerance_m", 0.01),
                              interpolation=reproject_kwargs.get("interpolation", "cubic"))
    return blend, blend.record | {"fit_s": time.perf_counter() - start}


@dataclass
class _HeldoutView:
    """One held-out view's comparison."""

    cam: str
    part: dict[str, Any]  # compare_maps against the held-out photometric maps
    part_truth: dict[str, Any] | None  # compare_maps against the simulator's maps (None: no truth)
    covered: int  # pixels of the held-out mask synthesised
    masked: int  # pixels of the held-out mask
    seconds: float  # synthesis time
    metrics: dict[str, float]  # the view's own metrics (finite ones)
    maps: dict[str, Any] | None  # "synth", "photometric", "truth" (or None), "compare" (pixels compared)


def _synthesise_view(data: ActionGBuffers, cam: str, heldout: tuple[str, ...], k: int, albedo_model: str,
                     reproject_kwargs: dict[str, Any]) -> dict[str, np.ndarray]:
    """:func:`synthesise_heldout` of ``cam``, its albedo replaced by :func:`predict_white_albedo`'s for the
    "view_dependent" model (valid where both are, both times counted)."""
    synth = synthesise_heldout(data, cam, heldout, k=k, **reproject_kwargs)
    if albedo_model != "view_dependent":
        return synth
    white = predict_white_albedo(data, cam, heldout, k=k, **reproject_kwargs)
    return synth | {"albedo": white["albedo"], "specular": white["specular"],
                    "valid": synth["valid"] & white["valid"], "seconds": synth["seconds"] + white["seconds"]}


def _heldout_view(data: ActionGBuffers, action_id: str, cam: str, heldout: tuple[str, ...], k: int,
                  albedo_model: str, truth_dir: str | Path | None, reproject_kwargs: dict[str, Any],
                  keep_maps: bool) -> _HeldoutView:
    """Synthesise held-out camera ``cam``'s maps and compare them with its photometric maps (where valid in
    both and on its mask) and, with ``truth_dir``, with the simulator's (on the true mask); ``keep_maps``:
    keep the maps in the result."""
    synth = _synthesise_view(data, cam, heldout, k, albedo_model, reproject_kwargs)
    ref = data.photometric(cam)
    compare = synth["valid"] & (ref["alpha"] > 0.5) & ref["mask"]
    part = compare_maps(synth["normal"], synth["albedo"], ref["normal"], ref["albedo"], compare)
    covered, masked = int((synth["valid"] & ref["mask"]).sum()), int(ref["mask"].sum())
    metrics = summarise([part]) | {"heldout_coverage": covered / max(masked, 1), "seconds": float(synth["seconds"])}
    truth = part_truth = None
    if truth_dir is not None:
        truth = load_truth(Path(truth_dir), action_id, cam, synth["depth_m"].shape)
        if truth is not None:
            tmask = synth["valid"] & truth["mask"]
            part_truth = compare_maps(synth["normal"], synth["albedo"], truth["normal"], truth["albedo"], tmask)
            metrics |= summarise([part_truth], "_truth")
            metrics["heldout_coverage_truth"] = int(tmask.sum()) / max(int(truth["mask"].sum()), 1)
    return _HeldoutView(cam=cam, part=part, part_truth=part_truth, covered=covered, masked=masked,
                        seconds=float(synth["seconds"]),
                        metrics={k_: v for k_, v in metrics.items() if np.isfinite(v)},
                        maps={"synth": synth, "photometric": ref, "truth": truth, "compare": compare}
                        if keep_maps else None)


def _pooled_metrics(views: list[_HeldoutView]) -> dict[str, Any]:
    """The metrics pooled over the held-out views (finite ones), coverage and seconds per view."""
    result: dict[str, Any] = summarise([view.part for view in views])
    result["heldout_coverage"] = sum(view.covered for view in views) / max(sum(view.masked for view in views), 1)
    parts_truth = [view.part_truth for view in views if view.part_truth is not None]
    if parts_truth:
        result |= summarise(parts_truth, "_truth")
    result["heldout_seconds_per_view"] = float(np.mean([view.seconds for view in views]))
    return {k_: v for k_, v in result.items() if np.isfinite(v)}
