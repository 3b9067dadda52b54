"""Ground truth for relighting: the simulator's subject rendered under an HDR environment map.

The pipeline relights each action's reconstructed asset under environment maps for novel cameras and
reports ``relit_psnr_db`` against this renderer: the exact subject the simulator captured (rebuilt from
the capture's ``simulator`` record, deterministic from its seed) shaded the way the simulator shades it,
with the LED sphere replaced by the environment.

Scheme (the simulator's, synthetic/shading.py, with other lights):

* The environment becomes ``lights`` distant directional emitters at fixed Fibonacci directions
  (:func:`environment_lights`): every texel of the map (box-downsampled to at most ``max_height`` rows)
  gives its radiance x solid angle to the nearest light direction, so the lights' total irradiance is
  exactly the integral of the map over the sphere, and a constant map ``c`` lights an unoccluded white
  Lambertian to radiance ``c`` (same radiance units as the map).
* Visibility of every light from every mesh vertex is traced ONCE per action (shadow rays, as for the
  LEDs); the directions are fixed, so every environment reuses it.
* Diffuse: per-vertex irradiance ``sum_l V(v, l) max(0, n.w_l) E_l`` interpolated over the triangle
  (Gouraud), times ``albedo / pi``. Specular: per pixel GGX (height-correlated Smith, Schlick, the
  simulator's f0 per material) against every light, with the light's visibility interpolated from the
  triangle corners (the simulator's exact levels). No interreflections; background 0.

Equirectangular convention (the pipeline's, ``stages.numerics.sg``): row 0 is the zenith +y; texel
``(i, j)`` has its centre at ``theta = pi (i + 0.5) / H`` from +y, ``phi = 2 pi (j + 0.5) / W - pi`` and
direction ``(sin theta sin phi, cos theta, -sin theta cos phi)``.

    relighter = TruthRelighter("runs/default/capture", "A0000")
    out = relighter.render(K, cam_from_world, 480, 320, read_environment("studio.hdr"))
    out["radiance"]  # (480, 320, 3) float32 linear, 0 off the subject
"""
from __future__ import annotations

import collections
import dataclasses
import functools
import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from . import geometry, shading
from .config import SimConfig
from .rig import Camera
from .simulate import action_subject, prepare_action
from .subject import load_base_subject, resolve_mesh
from .threads import limit_blas_threads

__all__ = ["DEFAULT_LIGHTS", "DEFAULT_MAX_HEIGHT", "equirect_directions", "equirect_solid_angles",
           "environment_lights", "EnvironmentLightSet", "TruthRelighter", "prefetch_visibility"]

DEFAULT_LIGHTS = 2048
"""Light directions per environment. Default capture, A0000, studio_small_03 (a small bright source), two
true cameras, PSNR on the subject with the image scaled to a 99th percentile of 1, against 4096 lights:
512 lights 26.2 / 28.6 dB, 1024 lights 37.2 / 34.0 dB, 2048 lights 45.7 / 44.9 dB. 2048 keeps the truth's
own squared error 30-100x below that of a relit image at 25-30 dB; it costs ~2x the 1024-light time
(visibility tracing)."""
DEFAULT_MAX_HEIGHT = 256
"""Rows of the box-downsampled map whose texels are assigned to the lights. At 1024 lights the energy a
light collects from a constant map varies by 1.6% (std) at 256 rows and 4.4% at 128 rows (texel
quantisation of the Voronoi cells); the assignment costs ~0.03 s."""
_CACHED_ENVIRONMENTS = 4


# --- environment -> distant lights ---------------------------------------------------------------------

def equirect_directions(height: int, width: int) -> np.ndarray:
    """Unit stage-frame directions (H, W, 3) float32 of equirect texel centres (module docstring)."""
    if height < 1 or width < 1:
        raise ValueError(f"equirect size must be positive, got {height} x {width}")
    theta = (np.arange(height, dtype=np.float64) + 0.5) * (math.pi / height)
    phi = (np.arange(width, dtype=np.float64) + 0.5) * (2.0 * math.pi / width) - math.pi
    return _directions(theta, phi).astype(np.float32)


def equirect_solid_angles(height: int, width: int) -> np.ndarray:
    """Exact solid angle (H, W) float64 of every equirect texel, ``(2 pi / W) (cos t_top - cos t_bottom)``;
    they sum to 4 pi."""
    if height < 1 or width < 1:
        raise ValueError(f"equirect size must be positive, got {height} x {width}")
    edges = np.cos(np.arange(height + 1, dtype=np.float64) * (math.pi / height))
    rows = (edges[:-1] - edges[1:]) * (2.0 * math.pi / width)
    return np.repeat(rows[:, None], width, axis=1)


def _directions(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """(len(theta), len(phi), 3) float64 directions of polar angles theta (from +y) and longitudes phi."""
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    out = np.empty((len(theta), len(phi), 3), np.float64)
    out[..., 0] = st * np.sin(phi)[None, :]
    out[..., 1] = ct
    out[..., 2] = -st * np.cos(phi)[None, :]
    return out


def _check_environment(env: np.ndarray) -> np.ndarray:
    env = np.asarray(env)
    if env.ndim != 3 or env.shape[2] != 3 or env.shape[0] < 1 or env.shape[1] < 1:
        raise ValueError(f"environment map must be (H, W, 3) equirectangular RGB, got shape {env.shape}")
    if not np.issubdtype(env.dtype, np.floating):
        raise ValueError(f"environment map must be float linear radiance, got dtype {env.dtype}")
    if not np.all(np.isfinite(env)):
        raise ValueError("environment map holds NaN or Inf")
    if np.any(env < 0):
        raise ValueError("environment map holds negative radiance")
    return env


@functools.lru_cache(maxsize=16)
def _light_of_block(height: int, width: int, max_height: int, count: int) -> tuple[np.ndarray, ...]:
    """Box downsampling of an H x W map to at most max_height x 2 max_height blocks and the nearest of
    `count` Fibonacci directions of every block: row starts (h,), column starts (w,), light index (h, w)."""
    h, w = min(height, max_height), min(width, 2 * max_height)
    # integer block edges (strictly increasing because h <= H, w <= W); blocks of a divisible map are equal
    rows = np.arange(h + 1) * height // h
    cols = np.arange(w + 1) * width // w
    theta = 0.5 * (rows[:-1] + rows[1:]) * (math.pi / height)
    phi = 0.5 * (cols[:-1] + cols[1:]) * (2.0 * math.pi / width) - math.pi
    block_dirs = _directions(theta, phi).reshape(-1, 3)
    _, nearest = cKDTree(geometry.fibonacci_sphere(count)).query(block_dirs)
    return rows[:-1], cols[:-1], nearest.reshape(h, w)


def environment_lights(env: np.ndarray, count: int = DEFAULT_LIGHTS,
                       max_height: int = DEFAULT_MAX_HEIGHT) -> tuple[np.ndarray, np.ndarray]:
    """Distant lights equivalent to an equirect environment map.

    Every texel's radiance x solid angle is summed into blocks of a box downsampling to at most
    ``max_height`` x ``2 max_height`` (exact: the energy is summed, not the radiance averaged), and every
    block's energy into the nearest of ``count`` Fibonacci directions (synthetic.geometry.fibonacci_sphere,
    the same for every map). The irradiance sums to the integral of the map over the sphere.

    Args:
        env: (H, W, 3) float linear radiance, finite and >= 0, equirect (module docstring).
        count: number of light directions (>= 16).
        max_height: rows of the downsampled map (>= 1).

    Returns:
        directions (count, 3) float32 unit (towards the light) and irradiance (count, 3) float32: the
        RGB irradiance each light gives a surface facing it (radiance x steradians).
    """
    env = _check_environment(env)
    if count < 16:
        raise ValueError(f"count must be >= 16, got {count}")
    if max_height < 1:
        raise ValueError(f"max_height must be >= 1, got {max_height}")
    height, width = env.shape[:2]
    row_starts, col_starts, nearest = _light_of_block(height, width, max_height, count)
    row_solid = equirect_solid_angles(height, 1)[:, 0]  # x W: a texel's solid angle is row_solid / W
    energy = env.astype(np.float64) * (row_solid / width)[:, None, None]
    energy = np.add.reduceat(np.add.reduceat(energy, row_starts, axis=0), col_starts, axis=1)
    irradiance = np.stack([np.bincount(nearest.ravel(), weights=energy[..., c].ravel(), minlength=count)
                           for c in range(3)], axis=1)
    return geometry.fibonacci_sphere(count).astype(np.float32), irradiance.astype(np.float32)


@dataclass(frozen=True)
class EnvironmentLightSet:
    """A set of distant lights shaped like synthetic.rig.LedSphere for synthetic.shading: directions
    (L, 3) and the (L, 9) irradiance table (full_on RGB = the environment, pos / neg slots 0)."""
    directions: np.ndarray
    irradiance: np.ndarray

    @property
    def count(self) -> int:
        return len(self.directions)


class _LightsOnly:
    """What synthetic.simulate.prepare_action reads of a session: its lights."""

    def __init__(self, leds: EnvironmentLightSet) -> None:
        self.leds = leds


# --- the visibility kept on disk -------------------------------------------------------------------------

def _visibility_key(capture_record: Path, action_id: str, lights: int) -> str:
    """sha256 of what a subject's visibility of the fixed light directions depends on: the simulator's
    source files, the capture's ``capture.json`` (its simulator record and actions), the action, the count."""
    simulator = hashlib.sha256()
    for path in sorted(Path(__file__).parent.glob("*.py")):
        simulator.update(path.name.encode() + b"\0" + path.read_bytes())
    record = {"format": 1, "simulator": simulator.hexdigest(), "action": action_id, "lights": int(lights),
              "capture": hashlib.sha256(Path(capture_record).read_bytes()).hexdigest()}
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()


VISIBILITY_CLAIM_STALE_S = 900.0
"""A visibility trace's claim older than this is taken over even if its pid runs (a trace takes seconds: the
default capture's 10-15 s an action; this bounds the wait on a pid reused after a crash, at the price of tracing
twice when a trace starved at the lowest priority takes longer)."""


def _cached_visibility(folder: Path, capture_record: Path, action_id: str, subject, directions: np.ndarray
                       ) -> np.ndarray:
    """(V, L) bool visibility of ``directions`` from the subject's vertices: read from ``folder`` when an
    earlier evaluation (or :func:`prefetch_visibility`) traced it, else traced and kept there (bit-packed,
    written under a temporary name and renamed, so a reader never sees half a file).

    The process tracing it holds a claim (:mod:`pipeline.claims`) while it does: another that needs the same
    visibility waits for it instead of tracing it twice (the evaluation after ``ultrastage run`` for the
    prefetch still tracing beside it), and takes the trace over when that process is gone."""
    import os

    from pipeline.claims import await_or_claim

    path = Path(folder) / f"{_visibility_key(capture_record, action_id, len(directions))}.npy"
    claim = path.with_name(path.name + ".claim")
    n_vertices, n_lights = len(subject.vertices_world), len(directions)

    def stored() -> np.ndarray | None:
        if path.is_file():
            try:
                packed = np.load(path)
                if packed.shape == (n_vertices, (n_lights + 7) // 8):
                    return np.unpackbits(packed, axis=1, count=n_lights).astype(bool)
            except (OSError, ValueError):
                pass  # unreadable (e.g. a disk error): traced again below and rewritten
        return None

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        visible, claimed = await_or_claim(stored, claim, VISIBILITY_CLAIM_STALE_S)
    except OSError:  # a folder that cannot be written: trace without a claim
        visible, claimed = None, False
    try:
        if visible is not None:
            return visible
        scene = shading.raycasting_scene(subject.vertices_world, subject.triangles)
        visible = shading.vertex_visibility(scene, subject.vertices_world, subject.normals_world, directions)
        try:
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            with open(tmp, "wb") as handle:
                np.save(handle, np.packbits(visible, axis=1))
            os.replace(tmp, path)
        except OSError:
            pass  # a cache that cannot be written costs the next evaluation the tracing, nothing else
        return visible
    finally:
        if claimed:
            claim.unlink(missing_ok=True)


def prefetch_visibility(capture_dir: str | Path, folder: str | Path, lights: int = DEFAULT_LIGHTS,
                        actions: list[str] | None = None) -> list[str]:
    """Trace and keep (:func:`_cached_visibility`) the ground-truth visibility of ``lights`` directions for
    each action with ground truth (``actions``: only these), so that an evaluation later finds it; returns
    the actions done. ``ultrastage run`` runs this in a low-priority process beside the pipeline: the
    tracing is the larger part of building a :class:`TruthRelighter`, and it needs only the capture."""
    capture_dir = Path(capture_dir)
    record_path = capture_dir / "capture.json"
    record = json.loads(record_path.read_text(encoding="utf-8"))
    if not isinstance(record.get("simulator"), dict):
        return []
    fields = {f.name for f in dataclasses.fields(SimConfig)}
    config = SimConfig(**({"supersample": 1} | {k: v for k, v in record["simulator"].items() if k in fields}))
    mesh_path = resolve_mesh(config.mesh)
    base = load_base_subject(str(mesh_path) if mesh_path else None, config.subdivisions if mesh_path else 0)
    trace_config = dataclasses.replace(config, specular=True, specular_led_clusters=False)
    directions = geometry.fibonacci_sphere(int(lights)).astype(np.float32)
    done = []
    for index, entry in enumerate(record.get("actions", [])):
        action_id = entry["action_id"]
        if (actions is not None and action_id not in actions) or not (capture_dir / "ground_truth" / action_id).is_dir():
            continue
        with limit_blas_threads(1):
            _cached_visibility(Path(folder), record_path, action_id, action_subject(trace_config, base, index),
                               directions)
        done.append(action_id)
    return done


# --- the relighter ---------------------------------------------------------------------------------------

def _read_ply_vertices(path: Path) -> np.ndarray:
    """Vertex positions (V, 3) float32 of a binary little-endian PLY as synthetic.files.write_ply writes."""
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if end < 0:
        raise ValueError(f"{path}: not a PLY file (no end_header)")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: expected a binary little-endian PLY")
    count, properties, in_vertex = 0, [], False
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            count, in_vertex = int(parts[2]), True
        elif parts[:1] == ["element"]:
            in_vertex = False
        elif in_vertex and parts[:1] == ["property"]:
            if parts[1] != "float":
                raise ValueError(f"{path}: vertex property {parts[-1]} is {parts[1]}, expected float")
            properties.append(parts[-1])
    records = np.frombuffer(data, dtype="<f4", count=count * len(properties), offset=end + len(b"end_header\n"))
    records = records.reshape(count, len(properties))
    return records[:, [properties.index(axis) for axis in "xyz"]]


class TruthRelighter:
    """The simulator's ground-truth subject of one captured action, rendered under environment maps.

    Construction rebuilds the subject from ``capture.json``'s ``simulator`` record, checks it against
    ``ground_truth/<action>/mesh.ply`` when present, and traces the visibility of ``lights`` fixed Fibonacci
    directions from every vertex once (Embree shadow rays: the default capture's 53514 vertices take 7-12 s
    at 1024 lights, 15-26 s at 2048 on a busy 2-core machine). Lighting per environment map is cached (up
    to 4 maps, keyed by content); a 320 x 480 render takes 0.5 / 1.2 s (1024 / 2048 lights) with a new map,
    0.25 / 0.45 s with a cached one.
    See DEFAULT_LIGHTS for the light-count convergence.

    Attributes: config (SimConfig), action_id, session_id, subject (synthetic.subject.ActionSubject),
    lights (int), max_height (int), directions (L, 3) float32.
    """

    def __init__(self, capture_dir: str | Path, action_id: str, lights: int = DEFAULT_LIGHTS,
                 max_height: int = DEFAULT_MAX_HEIGHT, visibility_cache: str | Path | None = None) -> None:
        capture_dir = Path(capture_dir)
        record_path = capture_dir / "capture.json"
        if not record_path.is_file():
            raise FileNotFoundError(f"{record_path} does not exist: not a capture folder")
        record = json.loads(record_path.read_text(encoding="utf-8"))
        if not isinstance(record.get("simulator"), dict):
            raise ValueError(f"{record_path} has no 'simulator' record: only simulated captures have a "
                             f"ground truth to relight")
        if lights < 16:
            raise ValueError(f"lights must be >= 16, got {lights}")
        if max_height < 1:
            raise ValueError(f"max_height must be >= 1, got {max_height}")
        action_ids = [entry["action_id"] for entry in record.get("actions", [])]
        if action_id not in action_ids:
            raise ValueError(f"{record_path}: unknown action id {action_id!r} (actions: {action_ids})")
        fields = {f.name for f in dataclasses.fields(SimConfig)}
        # captures written before SimConfig.supersample traced one ray per pixel
        self.config = SimConfig(**({"supersample": 1} | {k: v for k, v in record["simulator"].items() if k in fields}))
        self.action_id = action_id
        self.session_id = record["actions"][action_ids.index(action_id)]["session_id"]
        self.lights = int(lights)
        self.max_height = int(max_height)
        self.directions = geometry.fibonacci_sphere(self.lights).astype(np.float32)
        self._cache: collections.OrderedDict[str, shading.SurfaceLighting] = collections.OrderedDict()

        mesh_path = resolve_mesh(self.config.mesh)
        base = load_base_subject(str(mesh_path) if mesh_path else None,
                                 self.config.subdivisions if mesh_path else 0)
        # prepare_action traces V(vertex, light) against the session's lights: hand it the fixed
        # environment directions (zero irradiance; each map sets its own). Exact levels and specular on,
        # so its per-light visibility table is kept (uint8, 255 = visible) whatever the capture used.
        lights_only = _LightsOnly(EnvironmentLightSet(geometry.fibonacci_sphere(self.lights),
                                                      np.zeros((self.lights, 9), np.float32)))
        trace_config = dataclasses.replace(self.config, specular=True, specular_led_clusters=False)
        index = action_ids.index(action_id)
        with limit_blas_threads(1):
            subject = action_subject(trace_config, base, index)
            visible = None
            if visibility_cache is not None:
                visible = _cached_visibility(Path(visibility_cache), record_path, action_id, subject,
                                             lights_only.leds.directions)
            self.subject, self.scene, self._lighting = prepare_action(
                trace_config, base, lights_only, index, subject=subject, visible=visible)
        self._check_mesh(capture_dir / "ground_truth" / action_id / "mesh.ply")

    def _check_mesh(self, ply_path: Path) -> None:
        """The rebuilt subject must be the captured one (e.g. the shared MakeHuman mesh may be missing)."""
        if not ply_path.is_file():
            return
        stored = _read_ply_vertices(ply_path)
        rebuilt = self.subject.vertices_world
        if stored.shape != rebuilt.shape:
            raise ValueError(f"{ply_path} has {len(stored)} vertices but the rebuilt subject "
                             f"({self.subject.label}) has {len(rebuilt)}: the subject mesh the capture used "
                             f"(simulator mesh={self.config.mesh!r}) is not available here")
        error = float(np.max(np.abs(stored - rebuilt))) if len(stored) else 0.0
        if error > 1e-5:
            raise ValueError(f"{ply_path}: the rebuilt subject differs from the captured one by {error:.3g} m")

    def lighting(self, env: np.ndarray) -> shading.SurfaceLighting:
        """View-independent lighting of the subject under an environment map (H, W, 3) (cached by content):
        per-vertex irradiance (V, 9) (environment RGB in the full_on slot) and the per-light specular table."""
        env = _check_environment(env)
        digest = hashlib.blake2b(np.ascontiguousarray(env).view(np.uint8), digest_size=16)
        digest.update(repr((env.shape, env.dtype.str)).encode())
        key = digest.hexdigest()
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        _, irradiance = environment_lights(env, self.lights, self.max_height)
        table = np.zeros((self.lights, 9), np.float32)
        table[:, 0:3] = irradiance
        normals = self.subject.normals_world.astype(np.float32)
        visible = self._lighting.cluster_visibility[0]  # (V, L) uint8, 255 = visible
        per_vertex = np.zeros((len(normals), 9), np.float32)
        chunk = 8192
        with limit_blas_threads(1):
            for start in range(0, len(normals), chunk):
                stop = min(start + chunk, len(normals))
                cos = np.maximum(normals[start:stop] @ self.directions.T, 0.0)
                cos *= visible[start:stop] > 0
                per_vertex[start:stop, 0:3] = cos @ irradiance
        lighting = dataclasses.replace(self._lighting, irradiance=per_vertex,
                                       clusters=(shading.cluster_leds(self.directions, table, None),))
        self._cache[key] = lighting
        while len(self._cache) > _CACHED_ENVIRONMENTS:
            self._cache.popitem(last=False)
        return lighting

    def render(self, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int,
               env: np.ndarray, specular: bool | None = None, supersample: int | None = None
               ) -> dict[str, np.ndarray]:
        """Render the subject from a pinhole camera under an environment map.

        Args:
            K: (3, 3) OpenCV intrinsics (pixel centres at integer coordinates).
            cam_from_world: (3, 4) [R | t], x_cam = R x_world + t.
            height, width: image size in pixels.
            env: (He, We, 3) equirect linear radiance (module docstring), finite and >= 0.
            specular: add the GGX lobe; None = as the capture was rendered (SimConfig.specular).
            supersample: rays per pixel side, each pixel their mean; None = the capture's camera
                (SimConfig.supersample). A finer grid than the capture's approaches the pixel's exact area
                integral (bench/bench_relit_budget.py measures how far the capture's grid is from it).

        Returns:
            dict of float32 images (row 0 at the top): ``radiance`` (H, W, 3) linear, in the map's units,
            0 off the subject; ``mask`` (H, W) bool; ``normals_world`` (H, W, 3) (facing the camera);
            ``albedo`` (H, W, 3); ``roughness`` (H, W); ``depth_m`` (H, W) camera z; ``visibility`` (H, W)
            cosine-weighted visible fraction of the sphere of light directions. Off the mask all are 0.
            ``backface`` (H, W): the share of the pixel's rays that meet the back of a face, the inside of an
            open mesh seen through its opening (rendered black); on a closed mesh 0 but for the odd ray that slips
            between two triangles.
        """
        K = np.asarray(K, dtype=np.float64)
        cam_from_world = np.asarray(cam_from_world, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K must be a finite (3, 3) intrinsics matrix with positive focal lengths, got {K}")
        if cam_from_world.shape != (3, 4) or not np.all(np.isfinite(cam_from_world)):
            raise ValueError(f"cam_from_world must be a finite (3, 4) [R | t], got shape {cam_from_world.shape}")
        rotation = cam_from_world[:, :3]
        if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-5):
            raise ValueError("cam_from_world[:, :3] is not a rotation")
        if int(height) != height or int(width) != width or height < 1 or width < 1:
            raise ValueError(f"image size must be positive integers, got {height} x {width}")
        height, width = int(height), int(width)
        if supersample is not None and (int(supersample) != supersample or supersample < 1):
            raise ValueError(f"supersample must be a positive integer or None, got {supersample!r}")
        lighting = self.lighting(env)
        # the capture's pixels average s x s rays (SimConfig.supersample): so do these, unless told otherwise
        s = self.config.supersample if supersample is None else int(supersample)
        camera = shading.supersampled_camera(Camera("relight", width, height, K, cam_from_world, 0.0, 0.0), s)
        with limit_blas_threads(1):
            hits = shading.cast_primary_rays(self.scene, camera, self.subject.triangles)
            radiance, *maps = shading.shade_hits(
                hits, self.subject, lighting, specular=self.config.specular if specular is None else bool(specular))
        fine = shading.view_from_hits(hits, radiance[:, 0:3], *maps, camera.height, camera.width)
        view = shading.pixel_average(fine, s) if s > 1 else fine
        rgb = np.nan_to_num(view.radiance, nan=0.0, posinf=0.0, neginf=0.0)
        backface = np.zeros(camera.height * camera.width, np.float32)
        backface[hits.pixels] = hits.backface
        backface = backface.reshape(height, s, width, s).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
        return {"radiance": rgb, "mask": view.mask, "normals_world": view.normals_world, "albedo": view.albedo,
                "roughness": view.roughness, "depth_m": view.depth_m, "visibility": view.visibility,
                "backface": backface}
