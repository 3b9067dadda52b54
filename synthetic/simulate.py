"""`simulate()`: render a complete light-stage capture (raw DNGs, rig, clean plates, ground truth).

Layout and conventions: docs/CONTRACTS.md. Randomness is keyed by (seed, purpose, indices) so every
file is reproducible on its own: the same config gives byte-identical raw files.
"""
from __future__ import annotations

import dataclasses

import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import open3d as o3d

from . import calibration as calib_frames
from . import body as body_shape
from . import files, garments, pose, sensor, shading
from .calibration import CalibrationConfig
from .config import SimConfig
from .rig import ILLUMINATIONS, NOMINAL_EXPOSURE_S, Camera, LedSphere, make_cameras, make_leds, perturb_pose
from .subject import (EXTRA_MATERIALS, FABRIC_COLOURS, GARMENT, HAIR, MATERIALS, ActionSubject, BaseSubject,
                      load_base_subject, make_action_subject, resolve_mesh, shape_body)
from .threads import limit_blas_threads

CAPTURE_FORMAT = "ultrastage-capture/1"
RIG_FORMAT = "ultrastage-rig/1"
TRUTH_FORMAT = "ultrastage-truth/1"
CAPTURE_ENTRIES = ("capture.json", "sessions", "actions", "ground_truth", "previews")

# purposes of the random streams: default_rng([seed, PURPOSE, ...])
_RIG, _SESSION_RIG, _LEDS, _SUBJECT, _NOISE, _PLATE_NOISE, _RIG_SPEC, _POSE, _BODY, _HAIR, _GARMENT = range(1, 12)


@dataclass(frozen=True)
class Session:
    """One capture session: cameras, LEDs, per-camera exposure gain (normalised raw per unit radiance)
    and white reference (decoded linear RGB of an albedo-1 unoccluded Lambertian under full_on), and
    the background reflectance image (H, W) each camera sees behind the subject."""
    session_id: str
    index: int
    cameras: list[Camera]
    leds: LedSphere
    gains: list[float]
    white_references: list[np.ndarray]
    backgrounds: list[np.ndarray]
    spec_cameras: list[Camera]
    """The rig spec's nominal cameras: the true ones off by the mounting tolerances of SimConfig."""

    def cameras_json(self, cameras: list[Camera]) -> list[dict]:
        return [cam.to_json(ref) for cam, ref in zip(cameras, self.white_references)]

    def truth_cameras_json(self) -> dict:
        """The true cameras (ground_truth/cameras/<sid>.json): what calibration should recover."""
        return {"format": "ultrastage-truth-cameras/1", "session_id": self.session_id,
                "camera_convention": "opencv", "cameras": self.cameras_json(self.cameras)}

    def rig_json(self) -> dict:
        return {"format": RIG_FORMAT, "session_id": self.session_id,
                "stage_frame": "origin at LED-sphere centre, +y up, metres",
                "camera_convention": "opencv",
                "raw": {"black_level": sensor.BLACK_LEVEL, "white_level": sensor.WHITE_LEVEL, "cfa": sensor.CFA},
                "cameras": self.cameras_json(self.spec_cameras),
                "leds": {"count": self.leds.count, "radius_m": self.leds.radius_m,
                         "directions": np.round(self.leds.directions, 6).tolist()}}


def make_session(config: SimConfig, base: BaseSubject, index: int) -> Session:
    """Rig, LEDs and exposures of session `index` (session 0 has the nominal rig)."""
    session_rng = np.random.default_rng([config.seed, _SESSION_RIG, index]) if index > 0 else None
    radius_xz, y_range = subject_extent(config, base)
    cameras = make_cameras(config.n_cameras, config.width, config.height, radius_xz, y_range,
                           np.random.default_rng([config.seed, _RIG]), session_rng)
    leds = make_leds(config.n_leds, config.led_error, config.led_radius_m,
                     np.random.default_rng([config.seed, _LEDS, index]))
    white_radiance = leds.white_radiance()
    gains, references = [], []
    for camera in cameras:
        target = config.exposure_target * camera.exposure_s / NOMINAL_EXPOSURE_S
        gain = sensor.exposure_gain(white_radiance, target)
        gains.append(gain)
        references.append(gain * sensor.decoded_scale() * white_radiance)
    backgrounds = [shading.background_image(camera, leds.radius_m) for camera in cameras]
    return Session(f"S{index:03d}", index, cameras, leds, gains, references, backgrounds,
                   spec_cameras(cameras, config, np.random.default_rng([config.seed, _RIG_SPEC, index])))


def action_pose(config: SimConfig, base: BaseSubject, action_index: int) -> dict[str, float] | None:
    """Joint angles (degrees) of an action, drawn from (seed, action index); None when the action is not
    posed (pose_variation 0, or a subject without a skeleton)."""
    if config.pose_variation <= 0.0 or base.landmarks is None:
        return None
    return pose.draw_pose(np.random.default_rng([config.seed, _POSE, action_index]), config.pose_variation)


def action_body(config: SimConfig, base: BaseSubject, action_index: int) -> body_shape.BodyParams | None:
    """The body shape of an action (SimConfig.body, random parts drawn from (seed, action index)); None when
    the config sets none or the subject cannot be shaped."""
    if config.body is None or base.shaping is None:
        return None
    return body_shape.body_from_spec(config.body, np.random.default_rng([config.seed, _BODY, action_index]))


def action_hair(config: SimConfig, base: BaseSubject, action_index: int) -> garments.HairStyle | None:
    """The hair of an action: with probability SimConfig.hair, a style drawn from (seed, action index)."""
    if config.hair <= 0.0 or base.landmarks is None:
        return None
    rng = np.random.default_rng([config.seed, _HAIR, action_index])
    return garments.draw_hair(rng) if rng.uniform() < config.hair else None


def action_garment(config: SimConfig, base: BaseSubject, action_index: int) -> garments.GarmentStyle | None:
    """The skirt of an action: with probability SimConfig.garment, a style drawn from (seed, action index)."""
    if config.garment <= 0.0 or base.landmarks is None:
        return None
    rng = np.random.default_rng([config.seed, _GARMENT, action_index])
    return garments.draw_garment(rng, FABRIC_COLOURS) if rng.uniform() < config.garment else None


def subject_extent(config: SimConfig, base: BaseSubject) -> tuple[float, tuple[float, float]]:
    """Bounding cylinder (radius about +y, (y_min, y_max)) the cameras frame: the rest mesh's, widened to
    the reach of every pose pose_variation allows (synthetic.pose.reach_extent), so raised or spread limbs
    stay in view and the rig does not depend on the number of actions or their draws. With body shapes
    (SimConfig.body) it is the extent of every body the spec can give (a fixed body's own; for random ones
    the union over the corners of the parameter box, synthetic.body.extreme_bodies), widened by the pose
    reach (a fixed body's own; for random ones the base's reach beyond its rest extent, scaled by the tallest
    body's height); hair (SimConfig.hair) adds its largest thickness above the head."""
    if config.body is not None and base.shaping is not None:
        radius, (y_min, y_max) = _shaped_extent(config, base)
    elif config.pose_variation <= 0.0 or base.landmarks is None:
        radius, (y_min, y_max) = base.radius_xz, base.y_range
    else:
        radius, y_min, y_max = pose.reach_extent(base.vertices, base.skeleton, config.pose_variation)
    if config.hair > 0.0 and base.landmarks is not None:
        y_max += garments.HAIR_MAX_THICKNESS_M
    return radius, (y_min, y_max)


def _shaped_extent(config: SimConfig, base: BaseSubject) -> tuple[float, tuple[float, float]]:
    """subject_extent of a config with a body spec (base.shaping is set)."""
    is_random, fixed = body_shape.parse_body_spec(config.body)
    posed = config.pose_variation > 0.0 and base.landmarks is not None
    if not is_random:
        params = body_shape.body_from_spec(config.body)
        offsets, landmarks = shape_body(base, params)
        vertices = base.vertices + offsets
        if posed:
            skeleton = pose.Skeleton(pose.bone_joints(landmarks), landmarks, base.skeleton.weights)
            radius, y_min, y_max = pose.reach_extent(vertices, skeleton, config.pose_variation)
            return radius, (y_min, y_max)
        return float(np.sqrt(vertices[:, 0] ** 2 + vertices[:, 2] ** 2).max()), \
            (float(vertices[:, 1].min()), float(vertices[:, 1].max()))
    shaping = base.shaping
    ranges = {a: (fixed[a], fixed[a]) if a in fixed else body_shape.RANDOM_RANGES[a] for a in body_shape.SHAPE_AXES}
    radius, y_min, y_max, tallest = 0.0, np.inf, -np.inf, 0.0
    base_coarse = None
    for params in body_shape.extreme_bodies(ranges):
        offsets = body_shape.makehuman_offsets(shaping.targets_dir, params, shaping.obj_vertex_count)
        if base_coarse is None:  # the coarse vertices in the base's frame: Loop subdivision keeps them in their hull
            base_coarse = _coarse_vertices(base)
        coarse = base_coarse + offsets[shaping.source_ids] * base.units_m
        radius = max(radius, float(np.sqrt(coarse[:, 0] ** 2 + coarse[:, 2] ** 2).max()))
        y_min, y_max = min(y_min, float(coarse[:, 1].min())), max(y_max, float(coarse[:, 1].max()))
        tallest = max(tallest, float(np.ptp(coarse[:, 1])))
    if posed:
        reach_radius, reach_min, reach_max = pose.reach_extent(base.vertices, base.skeleton, config.pose_variation)
        scale = tallest / float(np.ptp(base.vertices[:, 1]))
        radius += scale * max(0.0, reach_radius - base.radius_xz)
        y_min -= scale * max(0.0, base.y_range[0] - reach_min)
        y_max += scale * max(0.0, reach_max - base.y_range[1])
    return radius, (y_min, y_max)


def _coarse_vertices(base: BaseSubject) -> np.ndarray:
    """The base's vertices before subdivision (V0, 3), in its (centred, metre) frame."""
    from .geometry import read_obj

    kept = read_obj(base.source).vertices[base.shaping.source_ids] * base.units_m
    return kept - 0.5 * (kept.min(axis=0) + kept.max(axis=0))


def spec_cameras(cameras: list[Camera], config: SimConfig, rng: np.random.Generator) -> list[Camera]:
    """The rig spec's nominal cameras: each true camera moved by the mounting tolerances of ``config``."""
    nominal = []
    for cam in cameras:
        pose = cam.cam_from_world
        if config.spec_shift_mm > 0 or config.spec_angle_deg > 0:
            pose = perturb_pose(pose, rng, angle_deg=config.spec_angle_deg, shift_m=config.spec_shift_mm / 1000.0)
        K = cam.K.copy()
        scale = 1.0 + rng.normal(0.0, config.spec_focal_pct / 100.0)
        K[0, 0] *= scale
        K[1, 1] *= scale
        nominal.append(dataclasses.replace(cam, K=K, cam_from_world=pose, focal_mm=cam.focal_mm * scale))
    return nominal


def simulate(out_dir: Path, config: SimConfig, progress: Callable[[str], None] | None = None,
             calibration: CalibrationConfig | None = None) -> Path:
    """Render a synthetic capture into `out_dir` (created if needed) and return its path.

    Writes capture.json, sessions/<sid>/rig.json (+ background/<cam>.dng clean plates),
    actions/<aid>/{full_on,pos,neg}/<cam>.dng, ground_truth/<aid>/... and previews/<aid>.png.
    capture.json is written last, so a folder without it is an interrupted capture. A previous simulated
    capture in `out_dir` is replaced; a folder holding anything else is refused (FileExistsError).
    `progress(message)` is called per session, per camera of every action and at the end.
    `calibration`: also write the per-session calibration frames (colour chart, diffuse sphere, speckled target,
    surveyed marker balls, as :class:`synthetic.calibration.CalibrationConfig` turns each on) and give every camera
    its own colour-response error: what ``ultrastage simulate`` writes. None (default): no calibration frames, so
    the cameras stage falls back to the rig's nominal cameras (on the default capture 0.13 degrees and 4.7 mm
    off, against 0.002 degrees and 0.16 mm from the markers; every figure from the mesh on is worse for it).
    """
    with limit_blas_threads(1):
        return _simulate(Path(out_dir), config, progress, calibration)


def _simulate(out_dir: Path, config: SimConfig, progress: Callable[[str], None] | None,
              calibration: CalibrationConfig | None = None) -> Path:
    say = progress or (lambda message: None)
    started = time.perf_counter()
    out = Path(out_dir)
    # read the subject first: a bad mesh file is refused before anything is written
    mesh_path = resolve_mesh(config.mesh)
    base = load_base_subject(str(mesh_path) if mesh_path else None, config.subdivisions if mesh_path else 0)
    clear_previous_capture(out)
    say(f"subject {base.name}: {len(base.vertices)} vertices, {len(base.triangles)} triangles")
    sessions, responses, frames = _write_sessions(out, config, base, calibration, say)
    blocks = np.array_split(np.arange(config.actions), config.sessions)
    jobs = [(session_pos, int(action_index)) for session_pos, block in enumerate(blocks) for action_index in block]
    workers = action_workers(len(jobs))
    if workers > 1:
        labels = _render_forked_actions(out, config, base, sessions, responses, jobs, workers, calibration, frames,
                                        say)
    else:
        _write_session_frames(out, config, calibration, frames, say)
        labels = [render_action(out, config, base, sessions[s], a, f"A{a:04d}", say, responses[s]) for s, a in jobs]
    actions = [{"action_id": f"A{a:04d}", "session_id": sessions[s].session_id, "subject": label}
               for (s, a), label in zip(jobs, labels)]
    capture = {"format": CAPTURE_FORMAT,
               "sessions": [{"session_id": s.session_id, "rig": f"sessions/{s.session_id}/rig.json"}
                            for s in sessions],
               "actions": actions,
               "illuminations": list(ILLUMINATIONS),
               "camera_ids": [cam.camera_id for cam in sessions[0].cameras],
               "simulator": config.to_json()}
    if calibration is not None:
        capture["simulator_calibration"] = calibration.to_json()
    files.write_json(out / "capture.json", capture)
    say(f"capture written to {out} in {time.perf_counter() - started:.1f} s")
    return out


def _write_sessions(out: Path, config: SimConfig, base: BaseSubject, calibration: CalibrationConfig | None,
                    say: Callable[[str], None]) -> tuple[list[Session], list[Any], list[tuple[Session, Any, Any]]]:
    """Each session's rig and true cameras written; returns the sessions, their cameras' colour responses (None
    without calibration) and ``(session, response, sphere centre)`` of the sessions that have calibration frames
    or clean plates to write."""
    sessions, responses, frames = [], [], []
    for index in range(config.sessions):
        session = make_session(config, base, index)
        rig, response, centre = session.rig_json(), None, None
        if calibration is not None:
            response = calib_frames.colour_responses(config.seed, index, len(session.cameras),
                                                     calibration.colour_error)
            centre = calib_frames.sphere_centre(base.y_range)
            rig["calibration_objects"] = calib_frames.calibration_objects(centre, calibration)
        files.write_json(out / "sessions" / session.session_id / "rig.json", rig)
        files.write_json(out / "ground_truth" / "cameras" / f"{session.session_id}.json", session.truth_cameras_json())
        sessions.append(session)
        responses.append(response)
        say(f"session {session.session_id}: rig with {len(session.cameras)} cameras, {session.leds.count} LEDs")
        if calibration is not None or config.background:
            frames.append((session, response, centre))
    return sessions, responses, frames


def _write_session_frames(out: Path, config: SimConfig, calibration: CalibrationConfig | None,
                          frames: list[tuple[Session, Any, Any]], say: Callable[[str], None]) -> None:
    """Every session's calibration frames and clean plates (the actions do not read them)."""
    for session, response, centre in frames:
        begun = time.perf_counter()
        if calibration is not None:
            calib_frames.write_session_calibration(out, config.seed, config.noise, config.full_well_e,
                                                   config.read_noise_dn, calibration, session, response, centre)
        if config.background:
            write_clean_plates(out, config, session, response)
        written = [name for name, on in (("calibration frames", calibration is not None),
                                         ("clean plates", config.background)) if on]
        say(f"session {session.session_id}: {' and '.join(written)} in {time.perf_counter() - begun:.1f} s")


def _render_forked_actions(out: Path, config: SimConfig, base: BaseSubject, sessions: list[Session],
                           responses: list[Any], jobs: list[tuple[int, int]], workers: int,
                           calibration: CalibrationConfig | None, frames: list[tuple[Session, Any, Any]],
                           say: Callable[[str], None]) -> list[str]:
    """The actions rendered by ``workers`` forked processes while a thread of this one writes the sessions'
    frames; returns each job's subject label.

    Forked children see the subject, sessions and responses without pickling them; each action's random numbers
    come from its own seeded generators, so the files do not depend on which process wrote them. Progress
    messages of both come back through a queue and reach ``say`` in this process's main thread, whole."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, wait

    global _FORKED
    context = multiprocessing.get_context("fork")
    messages = context.SimpleQueue()
    _FORKED = (out, config, base, sessions, responses, messages.put)
    try:
        with ProcessPoolExecutor(workers, mp_context=context) as pool:
            futures = [pool.submit(_render_forked, job) for job in jobs]  # forks every worker
            with ThreadPoolExecutor(1) as side:
                written = side.submit(_write_session_frames, out, config, calibration, frames, messages.put)
                pending = set(futures) | {written}
                while pending:
                    _, pending = wait(pending, timeout=0.2)
                    while not messages.empty():
                        say(messages.get())
            while not messages.empty():
                say(messages.get())
            written.result()
            return [f.result() for f in futures]
    finally:
        _FORKED = None


_FORKED: tuple | None = None  # what the forked action renderers share (set only while a pool runs)


def action_workers(n_actions: int) -> int:
    """Processes that render actions side by side: ``ULTRASTAGE_SIMULATE_WORKERS`` when set, else the CPUs this
    process may use (at most 8), never more than the actions; 1 where ``fork`` is unavailable."""
    import multiprocessing
    import os

    if "fork" not in multiprocessing.get_all_start_methods():
        return 1
    env = os.environ.get("ULTRASTAGE_SIMULATE_WORKERS")
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    wanted = int(env) if env else min(cpus, 8)
    return max(1, min(wanted, n_actions))


def _render_forked(job: tuple[int, int]) -> str:
    out, config, base, sessions, responses, say = _FORKED
    session_pos, action_index = job
    with limit_blas_threads(1):
        return render_action(out, config, base, sessions[session_pos], action_index, f"A{action_index:04d}", say,
                             responses[session_pos])


def clear_previous_capture(out: Path) -> None:
    """Make `out` an empty folder for a new capture. A folder holding only what the simulator writes
    (a previous or interrupted capture) is emptied of it; any other non-empty folder is refused."""
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"{out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    entries = list(out.iterdir())
    leftovers = [p for p in entries if p.name.startswith(".") and p.name.endswith(".tmp") and p.is_file()]
    foreign = sorted(p.name for p in entries if p.name not in CAPTURE_ENTRIES and p not in leftovers)
    if foreign:
        raise FileExistsError(f"{out} is not empty and not a simulated capture (it holds {foreign[:5]}); "
                              f"choose a new folder")
    if (out / "capture.json").exists():
        meta = json.loads((out / "capture.json").read_text())
        if "simulator" not in meta:
            raise FileExistsError(f"{out} holds a real capture (capture.json without 'simulator'); refusing to "
                                  f"overwrite it")
        (out / "capture.json").unlink()
    for entry in entries:
        if entry.is_dir():
            shutil.rmtree(entry)
        elif entry in leftovers:
            entry.unlink()


def write_clean_plates(out: Path, config: SimConfig, session: Session, responses: np.ndarray | None = None) -> None:
    """Clean plates: the empty stage under full_on, one DNG per camera (`responses`: per-camera colour
    responses (n, 3, 3) of synthetic.calibration, None = nominal)."""
    cam_from_xyz, neutral = sensor.nikon_cam_from_xyz(), sensor.as_shot_neutral()
    for cam_index, (camera, gain) in enumerate(zip(session.cameras, session.gains)):
        radiance = shading.render_background(camera, session.leds, session.backgrounds[cam_index])[..., 0:3]
        radiance = calib_frames.as_seen(radiance, None if responses is None else responses[cam_index])
        rng = np.random.default_rng([config.seed, _PLATE_NOISE, session.index, cam_index]) if config.noise else None
        raw = sensor.raw_frame(radiance, gain, rng, config.full_well_e, config.read_noise_dn)
        files.write_dng(out / "sessions" / session.session_id / "background" / f"{camera.camera_id}.dng",
                         raw, cam_from_xyz, neutral)


def action_subject(config: SimConfig, base: BaseSubject, action_index: int) -> ActionSubject:
    """The posed, folded subject of one action (deterministic from the config's seed)."""
    cycle_offset = int(np.random.default_rng([config.seed, _SUBJECT]).integers(1 << 16))
    return make_action_subject(base, np.random.default_rng([config.seed, _SUBJECT, action_index]),
                               action_index, config.fold_amplitude_m, cycle_offset,
                               action_pose(config, base, action_index), action_body(config, base, action_index),
                               action_hair(config, base, action_index), action_garment(config, base, action_index))


def prepare_action(config: SimConfig, base: BaseSubject, session: Session, action_index: int,
                   subject: ActionSubject | None = None, visible: np.ndarray | None = None
                   ) -> tuple[ActionSubject, o3d.t.geometry.RaycastingScene, shading.SurfaceLighting]:
    """The action's subject, its ray-casting scene and its view-independent lighting. ``subject`` and
    ``visible`` ((V, L) bool, :func:`shading.vertex_visibility` of the session's lights) when the caller has
    them already (the ground-truth relighter keeps its visibility on disk)."""
    subject = subject if subject is not None else action_subject(config, base, action_index)
    scene = shading.raycasting_scene(subject.vertices_world, subject.triangles)
    if visible is None:
        visible = shading.vertex_visibility(scene, subject.vertices_world, subject.normals_world,
                                            session.leds.directions)
    levels = shading.CLUSTER_LEVELS if config.specular_led_clusters else shading.EXACT_LEVELS
    lighting = shading.surface_lighting(visible, subject.normals_world, session.leds,
                                        with_specular=config.specular, levels=levels)
    return subject, scene, lighting


def render_views(config: SimConfig, action_index: int = 0, session_index: int = 0
                 ) -> tuple[Session, ActionSubject, list[shading.ViewRender]]:
    """Render one action for every camera in memory, writing nothing (tests, benchmarks, notebooks).

    The radiance of each view is the pre-sensor linear-sRGB image; `gain * radiance` is the decoded
    linear image without noise or demosaicing.
    """
    with limit_blas_threads(1):
        return _render_views(config, action_index, session_index)


def _render_views(config: SimConfig, action_index: int, session_index: int
                  ) -> tuple[Session, ActionSubject, list[shading.ViewRender]]:
    mesh_path = resolve_mesh(config.mesh)
    base = load_base_subject(str(mesh_path) if mesh_path else None, config.subdivisions if mesh_path else 0)
    session = make_session(config, base, session_index)
    subject, scene, lighting = prepare_action(config, base, session, action_index)
    views = [shading.render_view(scene, subject, lighting, session.leds, camera, specular=config.specular,
                                 background=background, supersample=config.supersample)
             for camera, background in zip(session.cameras, session.backgrounds)]
    return session, subject, views


def render_action(out: Path, config: SimConfig, base: BaseSubject, session: Session, action_index: int,
                  action_id: str, say: Callable[[str], None], responses: np.ndarray | None = None) -> str:
    """Render and write one action (all cameras and illuminations, ground truth, preview); `responses`:
    per-camera colour responses (n, 3, 3) of synthetic.calibration, None = nominal."""
    started = time.perf_counter()
    subject, scene, lighting = prepare_action(config, base, session, action_index)
    leds = session.leds
    say(f"{action_id}: subject {subject.label}, visibility of {len(subject.vertices_world)} vertices x "
        f"{leds.count} LEDs in {time.perf_counter() - started:.1f} s")

    cam_from_xyz, neutral = sensor.nikon_cam_from_xyz(), sensor.as_shot_neutral()
    truth_dir = out / "ground_truth" / action_id
    thumbnails = []
    for cam_index, (camera, gain) in enumerate(zip(session.cameras, session.gains)):
        view = shading.render_view(scene, subject, lighting, leds, camera, specular=config.specular,
                                   background=session.backgrounds[cam_index], supersample=config.supersample)
        for illum_index, illumination in enumerate(ILLUMINATIONS):
            rng = (np.random.default_rng([config.seed, _NOISE, action_index, cam_index, illum_index])
                   if config.noise else None)
            radiance = view.radiance[..., 3 * illum_index:3 * illum_index + 3]
            radiance = calib_frames.as_seen(radiance, None if responses is None else responses[cam_index])
            raw = sensor.raw_frame(radiance, gain, rng, config.full_well_e, config.read_noise_dn)
            files.write_dng(out / "actions" / action_id / illumination / f"{camera.camera_id}.dng",
                             raw, cam_from_xyz, neutral)
        files.write_ground_truth(truth_dir, camera.camera_id, view.normals_world, view.albedo, view.roughness,
                                 view.depth_m, view.visibility, view.mask)
        thumbnails.append(files.thumbnail(view.radiance[..., 0:3] * (gain * sensor.decoded_scale())))
        if (cam_index + 1) % 8 == 0 or cam_index + 1 == len(session.cameras):
            say(f"{action_id}: {cam_index + 1}/{len(session.cameras)} cameras")

    files.write_ply(truth_dir / "mesh.ply", subject.vertices_world, subject.triangles, subject.normals_world)
    files.write_json(truth_dir / "truth.json", truth_record(config, subject, session, action_id))
    files.write_png(out / "previews" / f"{action_id}.png", files.contact_sheet(thumbnails))
    say(f"{action_id}: done in {time.perf_counter() - started:.1f} s")
    return subject.label


def optional_subject_record(config: SimConfig, subject: ActionSubject) -> dict:
    """truth.json's subject entries for the options that change the subject's shape: ``body`` (the MakeHuman
    parameters and the rest height), ``hair`` and ``garment`` (their styles, None for an action without), each
    present only when its option is set (so a capture without them has the truth.json it had before them)."""
    record: dict = {}
    if config.body is not None:
        record["body"] = None if subject.body is None else subject.body.to_json() | {
            "spec": config.body, "targets": "MakeHuman macrodetails (universal, height, ethnic), linear blend",
            "height_m": None if subject.pose_deg is not None else
            round(float(np.ptp(subject.vertices_world[:len(subject.base.vertices), 1])), 4)}
    if config.hair > 0.0:
        record["hair"] = None if subject.hair is None else subject.hair.to_json() | {"region": "hair"}
    if config.garment > 0.0:
        record["garment"] = None if subject.garment is None else subject.garment.to_json() | {
            "region": "cloth_skirt", "triangles": len(subject.garment_triangles)}
    return record


def action_materials(subject: ActionSubject) -> list[tuple[str, float, float]]:
    """(name, roughness, F0) of the regions an action's subject has: every subject's (MATERIALS), then hair and
    skirt when it has them."""
    rows = list(MATERIALS.values())
    if subject.hair is not None:
        rows.append(EXTRA_MATERIALS[HAIR])
    if subject.garment is not None:
        rows.append(EXTRA_MATERIALS[GARMENT])
    return rows


def truth_record(config: SimConfig, subject: ActionSubject, session: Session, action_id: str) -> dict:
    """truth.json: subject, materials, LEDs and the rendering scheme of one action."""
    base = subject.base
    return {
        "format": TRUTH_FORMAT, "action_id": action_id, "session_id": session.session_id,
        "subject": {"label": subject.label, "kind": base.kind, "source": base.source,
                    "metres_per_unit": base.units_m, "yaw_deg": round(float(np.degrees(subject.yaw_rad)), 4),
                    "skin": subject.skin_name,
                    "skin_tone": subject.skin_tone.tolist() if subject.skin_texture is None else None,
                    "vertices": len(subject.vertices_world), "triangles": len(subject.triangles),
                    "cloth": subject.cloth.to_json() if base.kind in ("makehuman", "procedural") else None,
                    "pose": (None if subject.pose_deg is None else
                             {"variation": config.pose_variation, "skinning": "linear blend, 10 bones",
                              "angles_deg": {k: round(v, 3) for k, v in subject.pose_deg.items()}})}
        | optional_subject_record(config, subject),
        "materials": {name: {"roughness": rough, "f0": f0, "ggx_alpha": round(rough ** 2, 4),
                             "model": "lambert + GGX (Smith height-correlated, Schlick)" if config.specular
                             else "lambert"} for name, rough, f0 in action_materials(subject)},
        "leds": {"count": session.leds.count, "led_error": config.led_error,
                 "solid_angle_sr": session.leds.solid_angle,
                 "gains": np.round(session.leds.gains, 6).tolist(),
                 "white_radiance": session.leds.white_radiance().tolist()},
        "rendering": {"lights": "distant directional LEDs, irradiance I * 4pi/L each",
                      "visibility": "per vertex x LED shadow rays (1 mm normal offset), barycentric interpolation",
                      "diffuse": "per-vertex irradiance interpolated (Gouraud), times albedo/pi",
                      "specular": ("off" if not config.specular else
                                   f"per pixel GGX against LED clusters {shading.CLUSTER_LEVELS}"
                                   if config.specular_led_clusters else "per pixel and LED GGX"),
                      "interreflections": "none"},
    }
