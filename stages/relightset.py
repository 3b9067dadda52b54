"""Action stage ``relightset``: the single-image relighting set (the paper's section 5).

For each action, ``examples_per_action`` examples, each one view of the action's relightable asset under one
environment map of the pool turned about +y; all draws are functions of (seed, example id) alone
(:mod:`stages.numerics.relightset`), so adding actions or maps leaves the other examples' draws unchanged:

1. the camera: on a sphere around the subject (azimuth uniform, elevation uniform in ``elevation_deg``, at the
   captured cameras' median distance), looking at the subject's centre, the subject's bounding sphere filling
   a square image of ``size`` pixels (:func:`stages.numerics.relightset.orbit_camera`);
2. the environment: a map of the pool by rendezvous hashing over the maps' sha256, and a rotation uniform in
   [0, 360) degrees;
3. the render (:func:`stages.numerics.novel_view.relight_view`, the ``relight`` stage's shading): G-buffer
   reprojected from the 6 nearest captured views, shaded under the map's spherical-Gaussian fit turned by
   the rotation, antialiased silhouettes.

Files per example (published as ``RELEASE/relight/<example_id>/``): ``image.exr`` (RGBA half float, linear
radiance in the map's units premultiplied by alpha), ``image.png`` (8-bit sRGB of ``image x png_exposure``),
``albedo.exr`` / ``albedo.png`` (linear / sRGB), ``normal.exr`` / ``normal.png`` (camera-frame normals,
OpenCV axes; (n + 1) / 2), ``mask.png`` and ``example.json`` (its row of ``manifests/relight_examples.parquet``).

An example whose ``example_key`` (everything it is rendered from, the stage's code included) equals one in an earlier result of the stage
for the action is linked from there instead of rendered again: a new map in the pool re-renders only the
examples it takes over.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.codecs.exr import write_exr
from pipeline.codecs.image import write_png
from pipeline.config import Documented, broken, checked
from pipeline.errors import InputError
from pipeline.hashing import code_digests
from pipeline.stage import Stage, StageContext
from pipeline.store import link_or_copy
from artifacts.facade import ActionArtifacts
from stages.relightable import load_relightable_asset
from artifacts.layout import EXAMPLE_PRODUCTS, PRODUCTS, ArtifactWriter, released_file
from stages.exr_headers import EXR_HEADERS
from stages.numerics import numeric_threads
from stages.numerics.novel_view import ViewShading
from stages.environments import DEFAULT_HDRI_DIRS, PROCEDURAL_PREFIX, find_environment, load_environment

HDRI_FOLDERS = "hdri-folders"
"""Pool entry: every map in the folders environment names are looked up in ($ULTRASTAGE_HDRI, the capture's
``environments/``, ../shared/data/hdri); the procedural sky and studio when they hold none."""
_HDR_SUFFIXES = (".hdr", ".exr")
EXAMPLE_FILES = tuple(Path(PRODUCTS[product][1]).name for product in EXAMPLE_PRODUCTS)
"""The names of an example's files besides its example.json (``image.exr``, ``image.png``, ...)."""
RELEASED = EXAMPLE_PRODUCTS + ("relight_example",)
"""The products of an example this stage publishes at the release root, in order (their paths and kinds:
:data:`artifacts.layout.PRODUCTS`, :data:`artifacts.layout.RELEASE_KINDS`)."""
#: Bumped when the files of an example change for the same inputs (enters every example key).
RENDER_FORMAT = 1


@dataclass(frozen=True)
class RelightSetConfig(Documented):
    examples_per_action: int = checked(3, ge=1)
    """Examples (views) per action; the paper's set has 3 per model."""
    size: int = checked(256, ge=16)
    """Width and height of each example's images, pixels."""
    environments: tuple[str, ...] = checked((HDRI_FOLDERS,), nonempty=True)
    """The environment pool: folders (every .hdr / .exr in them), files, names looked up as the relight
    stage's, ``procedural:sky`` / ``procedural:studio``, or ``hdri-folders``. A map that cannot be read is
    named in the log and the stage's stats and left out; an empty pool or a name found nowhere is an error."""
    seed: int = checked(0, ge=0)
    """Seed of every draw: views, environments, rotations and splits."""
    split_ratios: tuple[float, ...] = (0.8, 0.1, 0.1)
    """Shares of subjects in train, validation and test (each subject's examples are in one split)."""
    elevation_deg: tuple[float, ...] = (-10.0, 30.0)
    """Range of the cameras' elevation above the horizontal plane through the subject's centre, degrees."""
    margin: float = checked(0.05, ge=0.0, lt=0.5)
    """Share of the image width left free on each side of the subject's bounding sphere."""
    sg_lobes: int = checked(32, ge=1)
    """Spherical Gaussians fitted to each environment map."""
    fit_height: int = checked(64, ge=4)
    """Rows of the downsampled map the SG fit works on."""
    fit_iterations: int = checked(150, ge=0)
    """Iterations of the SG fit's L-BFGS (:func:`stages.numerics.sg.fit_sg_environment`; 0: the starting lobes
    with their best amplitudes). On the default capture's five maps 150 take 1.9-2.8 CPU s a map against 3.6-5.7 s
    at 300, the irradiance error 0.008-0.010 -> 0.008-0.011 (relative L2), and the relit views and the relighting
    set move by under 0.005 dB."""
    png_level: float = checked(0.8, gt=0.0)
    """The tone-mapped PNG puts the 99th percentile of the subject's radiance at this linear level."""
    shading: ViewShading = field(default_factory=ViewShading)
    """Reprojection and shading of each view (the relight stage's)."""

    def _checks(self) -> list[str]:
        problems = []
        ratios = np.asarray(self.split_ratios, np.float64)
        if ratios.shape != (3,) or np.any(ratios < 0) or not abs(ratios.sum() - 1.0) <= 1e-6:
            problems.append(broken(self, "split_ratios", "must be 3 shares >= 0 that sum to 1"))
        if len(self.elevation_deg) != 2 or not -80.0 <= self.elevation_deg[0] <= self.elevation_deg[1] <= 80.0:
            problems.append(broken(self, "elevation_deg", "must be (low, high) with -80 <= low <= high <= 80"))
        return problems


@dataclass(frozen=True)
class PoolMap:
    """One environment map of the pool."""

    name: str
    """File stem, or 'procedural:<kind>'."""
    path: Path | None
    """The file (None for a procedural map)."""

    @property
    def label(self) -> str:
        return self.name.replace(":", "_")


def _search_folders(capture_root: Path | None) -> list[Path]:
    folders = [Path(d) for d in os.environ.get("ULTRASTAGE_HDRI", "").split(os.pathsep) if d]
    if capture_root is not None:
        folders.append(Path(capture_root) / "environments")
    return folders + list(DEFAULT_HDRI_DIRS)


def _maps_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _HDR_SUFFIXES)


def resolve_pool(entries: tuple[str, ...], capture_root: Path | None) -> tuple[list[PoolMap], list[dict[str, str]]]:
    """The environment pool a config names: (readable maps, sorted by name, duplicates of a stem once;
    ``[{"path", "reason"}]`` of the files left out because they cannot be read).

    Raises:
        InputError: a folder with no maps, a name found nowhere, or no readable map at all.
    """
    from pipeline.codecs.hdr import read_environment

    files: list[Path] = []
    procedural: list[str] = []
    for entry in entries:
        if entry.startswith(PROCEDURAL_PREFIX):
            procedural.append(entry)
        elif entry == HDRI_FOLDERS:
            found = [p for folder in _search_folders(capture_root) if folder.is_dir() for p in _maps_in(folder)]
            if found:
                files += found
            else:
                procedural += [f"{PROCEDURAL_PREFIX}sky", f"{PROCEDURAL_PREFIX}studio"]
        elif Path(entry).expanduser().is_dir():
            found = _maps_in(Path(entry).expanduser())
            if not found:
                raise InputError(Path(entry), "no .hdr or .exr environment maps in this folder")
            files += found
        else:
            path = find_environment(entry, capture_root)
            if path is None:
                raise InputError(Path(entry), "environment map not found (not a file, a folder, or a name in "
                                              f"{[str(f) for f in _search_folders(capture_root)]})")
            files.append(path)
    pool: dict[str, PoolMap] = {}
    skipped: list[dict[str, str]] = []
    for path in files:
        if path.stem in pool:
            continue
        try:
            env = read_environment(path)
            if env.ndim != 3 or env.shape[1] != 2 * env.shape[0] or not np.all(np.isfinite(env)):
                raise ValueError(f"not a finite equirectangular (H, 2H, 3) map: shape {env.shape}")
        except (InputError, ValueError, OSError) as exc:
            skipped.append({"path": path.name, "reason": str(exc).replace(str(path), path.name)})
            continue
        pool[path.stem] = PoolMap(path.stem, path)
    for name in procedural:
        pool.setdefault(name, PoolMap(name, None))
    if not pool:
        raise InputError(Path(entries[0]), "no readable environment map in the pool (left out: "
                                           f"{'; '.join(s['path'] + ': ' + s['reason'] for s in skipped)})")
    return [pool[k] for k in sorted(pool)], skipped


def load_pool_map(pool_map: PoolMap, path: Path | None) -> tuple[np.ndarray, str]:
    """(map (H, 2H, 3) float32, sha256) of a pool map (:func:`pool_map_digest`)."""
    env, _ = load_environment(pool_map.name, path)
    return env, pool_map_digest(pool_map, path, env)


def pool_map_digest(pool_map: PoolMap, path: Path | None, env: np.ndarray | None = None) -> str:
    """sha256 of a pool map: of the file's bytes, or of the float32 map for a procedural one (made here unless
    ``env`` gives it)."""
    from pipeline.hashing import file_sha256
    if path is not None:
        return file_sha256(path)
    if env is None:
        env, _ = load_environment(pool_map.name, None)
    return hashlib.sha256(np.ascontiguousarray(env, np.float32).tobytes()).hexdigest()


def _digest(record: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(record, sort_keys=True, default=float).encode()).hexdigest()


class _ActionPool:
    """The pool's maps as one action's examples use them: each read (and SG-fitted) only when an example draws it."""

    def __init__(self, maps: list[PoolMap], paths: list[Path | None], digests: list[str], cfg: RelightSetConfig,
                 cache_dir: Path | None):
        self.maps, self.paths, self.digests, self.cfg, self.cache_dir = maps, paths, digests, cfg, cache_dir
        self._envs: dict[int, np.ndarray] = {}
        self._fits: dict[int, Any] = {}

    def env(self, index: int) -> np.ndarray:
        if index not in self._envs:
            self._envs[index] = load_environment(self.maps[index].name, self.paths[index])[0]
        return self._envs[index]

    def lobes(self, index: int) -> Any:
        from stages.environments import fit_sg_memo

        if index not in self._fits:
            self._fits[index] = fit_sg_memo(self.env(index), self.cfg.sg_lobes, self.cfg.fit_height, self.cache_dir,
                                            iterations=self.cfg.fit_iterations)
        return self._fits[index]


def _example_row(ctx: StageContext, cfg: RelightSetConfig, example_id: str, index: int, subject: str, split: str,
                 draw: dict[str, Any], pool: _ActionPool, render_record: dict[str, Any]) -> dict[str, Any]:
    """An example's index row (camera, environment, its SH lighting, files, key) before it is rendered."""
    from stages.numerics.relightset import example_lighting_sh

    env_index, rotation_deg = draw["environment_index"], draw["rotation_deg"]
    K, cam_from_world = draw["K"], draw["cam_from_world"]
    key = _digest(render_record | {"example_id": example_id, "environment": pool.digests[env_index],
                                   "rotation_deg": rotation_deg, "K": K.round(9).tolist(),
                                   "cam_from_world": cam_from_world.round(9).tolist()})
    sh_world, sh_camera = example_lighting_sh(pool.env(env_index), rotation_deg, cam_from_world)
    pool_map = pool.maps[env_index]
    row = {"example_id": example_id, "action_id": ctx.action_id, "subject": subject,
           "session_id": ctx.session_id, "split": split, "view_index": index, "width": cfg.size,
           "height": cfg.size, "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
           "cy": float(K[1, 2]), "cam_from_world_json": json.dumps(cam_from_world.round(9).tolist()),
           "environment_name": pool_map.name, "environment_file": pool_map.path.name if pool_map.path else "",
           "environment_sha256": pool.digests[env_index], "environment_rotation_deg": rotation_deg,
           "sh_world_json": json.dumps(sh_world.round(6).tolist()),
           "sh_camera_json": json.dumps(sh_camera.round(6).tolist()),
           "seed": cfg.seed, "example_key": key}
    return row | {f"{name.replace('.', '_')}": f"relight/{example_id}/{name}" for name in EXAMPLE_FILES}


def _reuse_example(old: tuple[dict[str, Any], Path], folder: Path) -> dict[str, Any]:
    """Links (or copies) an earlier result's files of the same example into ``folder``; returns their row's
    ``png_exposure`` and ``mask_pixels``."""
    row, old_folder = old
    for name in EXAMPLE_FILES:
        link_or_copy(old_folder / name, folder / name)
    return {"png_exposure": row["png_exposure"], "mask_pixels": row["mask_pixels"]}


def _render_example(out: ArtifactWriter, example_id: str, asset: Any, draw: dict[str, Any], pool: _ActionPool,
                    cfg: RelightSetConfig, directions: np.ndarray | None) -> dict[str, Any]:
    """Renders one drawn example and writes its files at ``out``'s paths; returns the row's ``png_exposure`` and
    ``mask_pixels``."""
    from stages.numerics.relightset import encode_normals, render_example, tone_map

    env_index = draw["environment_index"]
    example = render_example(asset, draw["K"], draw["cam_from_world"], cfg.size, pool.lobes(env_index),
                             draw["rotation_deg"], cfg.shading, directions, cfg.png_level)
    image, mask, albedo, normals_cam = (example[k] for k in ("image", "mask", "albedo", "normals_camera"))
    path = lambda name: out.path(f"relight_example_{name}", example=example_id)  # noqa: E731
    write_exr(path("image"), np.concatenate([image, example["alpha"][..., None]], axis=2),
              header=EXR_HEADERS["relightset_image"])
    write_png(path("image_png"), tone_map(image, example["exposure"]))
    write_exr(path("albedo"), albedo, header=EXR_HEADERS["relightset_albedo"])
    write_png(path("albedo_png"), tone_map(albedo, 1.0))
    write_exr(path("normal"), normals_cam, half=False, header=EXR_HEADERS["relightset_normal"])
    write_png(path("normal_png"), encode_normals(normals_cam, mask))
    write_png(path("mask"), mask)
    return {"png_exposure": float(example["exposure"]), "mask_pixels": int(mask.sum())}


class RelightSetStage(Stage):
    """Examples of the single-image relighting set rendered from the action's relightable asset."""

    name = "relightset"
    version = "1"
    scope = "action"
    requires = ("geometry", "textures", "materials", "decode", "photometric", "diffuse_normals")
    outputs = ("relight",)

    def __init__(self, config: Any, **kwargs: Any):
        super().__init__(config, **kwargs)
        self._pools: dict[str, tuple[list[PoolMap], list[dict[str, str]]]] = {}

    def pool(self, capture_root: Path | None) -> tuple[list[PoolMap], list[dict[str, str]]]:
        key = str(capture_root)
        if key not in self._pools:
            self._pools[key] = resolve_pool(self.config.environments, capture_root)
        return self._pools[key]

    def preflight(self, capture: Any, echo: Any) -> None:
        """Resolve the environment pool once before planning: an empty or unreadable pool stops the run."""
        maps, skipped = self.pool(getattr(capture, "root", None))
        for item in skipped:
            echo(f"{self.name:<12} {'pool':<8} skipped environment {item['path']}: {item['reason']}")

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        maps, _ = self.pool(getattr(capture, "root", None))
        return {f"environment/{m.label}": m.path for m in maps if m.path is not None}

    def run(self, ctx: StageContext) -> dict[str, Any]:
        import torch

        from stages.numerics.relightset import split_of

        torch.set_num_threads(numeric_threads())
        cfg: RelightSetConfig = self.config
        started = time.perf_counter()
        maps, skipped = self.pool(ctx.capture_root)
        paths = [ctx.raw_inputs.get(f"environment/{m.label}") for m in maps]
        digests = [pool_map_digest(m, path) for m, path in zip(maps, paths)]
        pool = _ActionPool(maps, paths, digests, cfg, ctx.cache_dir)
        subject = ctx.subject or ctx.action_id
        split = split_of(cfg.seed, subject, cfg.split_ratios)
        asset, cameras = load_relightable_asset(ActionArtifacts(ctx.upstream))
        out = ArtifactWriter(self.name, ctx.out_dir)
        rows, reused, seconds = self._examples(ctx, out, asset, cameras, pool, subject, split)
        out.path("relight_examples").write_text(json.dumps(rows, indent=1, sort_keys=True))
        return {"examples": len(rows), "rendered": len(seconds), "reused": reused, "split": split,
                "pool": [m.name for m in maps], "skipped_environments": skipped,
                "seconds_per_example": float(np.mean(seconds)) if seconds else 0.0,
                "seconds": time.perf_counter() - started}

    def _examples(self, ctx: StageContext, out: ArtifactWriter, asset: Any, cameras: dict[str, Any],
                  pool: _ActionPool, subject: str, split: str) -> tuple[list[dict[str, Any]], int, list[float]]:
        """Draws each example of the action, renders it (or links its files from an earlier result with the
        same key) and writes its ``example.json``; returns the index rows, how many were linked and the
        seconds of each one rendered."""
        from stages.numerics.relightset import draw_example, subject_frame
        from stages.numerics.sg import fibonacci_sphere

        cfg: RelightSetConfig = self.config
        centre, radius, distance = subject_frame(asset.vertices, camera_centres(cameras))
        directions = fibonacci_sphere(cfg.shading.visibility_directions) if cfg.shading.shadows else None
        render_record = self._render_record(ctx)
        previous = self._previous_examples(ctx)
        out.path("relight_examples").parent.mkdir(parents=True, exist_ok=True)
        rows, reused, seconds = [], 0, []
        for index in range(cfg.examples_per_action):
            example_id = example_name(ctx.action_id, index)
            draw = draw_example(cfg.seed, example_id, pool.digests, centre, radius, distance, cfg.size,
                                cfg.elevation_deg, cfg.margin)
            row = _example_row(ctx, cfg, example_id, index, subject, split, draw, pool, render_record)
            record = out.path("relight_example", example=example_id)
            old = previous.get(row["example_key"])
            if old is not None:  # rendered before with the same inputs and code: link its files
                row |= _reuse_example(old, record.parent)
                reused += 1
            else:
                t0 = time.perf_counter()
                row |= _render_example(out, example_id, asset, draw, pool, cfg, directions)
                seconds.append(time.perf_counter() - t0)
            record.write_text(json.dumps(row, indent=1, sort_keys=True))
            rows.append(row)
            ctx.progress(index + 1, cfg.examples_per_action, f"example {example_id}")
        return rows, reused, seconds

    def _render_record(self, ctx: StageContext) -> dict[str, Any]:
        """What every example's key holds besides its own draw: the renderer's format, version, code and settings
        and the upstream keys (a renderer change re-renders, never links stale files)."""
        cfg: RelightSetConfig = self.config
        return {"format": RENDER_FORMAT, "version": self.version, "upstream": ctx.upstream_keys,
                "code": code_digests(self.code_module, self.code_packages),
                "size": cfg.size, "margin": cfg.margin, "sg_lobes": cfg.sg_lobes, "fit_height": cfg.fit_height,
                "fit_iterations": cfg.fit_iterations, "png_level": cfg.png_level, "shading": asdict(cfg.shading)}

    @staticmethod
    def _previous_examples(ctx: StageContext) -> dict[str, tuple[dict[str, Any], Path]]:
        """The examples of this action's earlier results, by example key (key -> (row, folder)); the most
        recent result wins."""
        found: dict[str, tuple[dict[str, Any], Path]] = {}
        for previous in reversed(ctx.previous):
            earlier = ActionArtifacts({"relightset": previous})
            try:
                rows = earlier.json("relight_examples")
            except (OSError, json.JSONDecodeError):
                continue
            for row in rows:
                folder = earlier.path("relight_example", example=row["example_id"]).parent
                if all((folder / name).is_file() for name in EXAMPLE_FILES):
                    found[row["example_key"]] = (row, folder)
        return found

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        """Nothing under ``actions/<id>/``: the examples are published at the release root."""
        return []

    def release_root_files(self, artifact: Path) -> list[tuple[Path, str, str]]:
        """(file, path under the release root, kind) of every example file."""
        return [released_file(self.name, artifact, product, example=row["example_id"])[:3]
                for row in self.manifest_rows(artifact).get("relight_examples", []) for product in RELEASED]

    def manifest_rows(self, artifact: Path) -> dict[str, list[dict[str, Any]]]:
        path = artifact / "relight" / "examples.json"
        return {"relight_examples": json.loads(path.read_text())} if path.is_file() else {}


def example_name(action_id: str, index: int) -> str:
    """The id (and folder name) of an action's example ``index``."""
    return f"{action_id}_{index:02d}"


def camera_centres(cameras: dict[str, Any]) -> np.ndarray:
    """World centres (C, 3) of :class:`artifacts.camera.Camera` s."""
    return np.array([c.centre for c in cameras.values()]).reshape(-1, 3)
