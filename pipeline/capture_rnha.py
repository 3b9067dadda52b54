"""The seed paper's public release layout (RNHA) opened as a capture, so every stage from decode on runs on it.

Layout of one action (one capture of the public release, one folder per zip)::

    <action>/full_on/<cam>.jpg   <action>/pos/<cam>.jpg   <action>/neg/<cam>.jpg   8-bit sRGB photos
    <action>/mask/<cam>.jpg      subject mask (optional; 255 = subject)
    <action>/normal_alpha/<cam>.jpg   the release's own normal estimate (not read: the pipeline makes its own)
    <action>/transforms.json     cameras, instant-ngp convention

``open_capture`` (pipeline.capture) opens such a folder, or a folder of them, when it has no ``capture.json``.
The reader turns each action's ``transforms.json`` into the rig records the stages read (``K``,
``cam_from_world`` OpenCV, ``width``, ``height``, ``dist``, ``white_reference``):

- ``transform_matrix``: 4x4 camera-to-world with OpenGL camera axes (x right, y up, z back), as instant-ngp
  and nerfstudio read it; ``cam_from_world = inverse(transform_matrix @ diag(1, -1, -1, 1))[:3]`` (the inverse
  of what ``stages.decode.opengl_camera_to_world`` writes into a release). Its world is taken as the stage
  frame in metres (the public release's cameras, normals and lights share the stage's world frame); camera
  centres further than ``MAX_CAMERA_DISTANCE_M`` or nearer than ``MIN_CAMERA_DISTANCE_M`` to the origin are
  refused as another unit.
- intrinsics per frame, else at the top level (instant-ngp reads both): ``fl_x``, ``fl_y`` (or
  ``camera_angle_x``/``camera_angle_y`` in radians), ``cx``, ``cy`` (pixel centres at +0.5, as instant-ngp
  and COLMAP: OpenCV ``K[0][2] = cx - 0.5``; absent: the image centre, instant-ngp's default), ``w``, ``h``,
  and ``k1``, ``k2``, ``p1``, ``p2``, ``k3`` (0 when absent). A frame without a focal length or size is an
  error naming the file.
- instant-ngp's ``scale`` and ``offset`` place this world in instant-ngp's unit cube (``p_ngp = scale * p +
  offset``); they do not move the cameras. The reader checks them and records the cube's box in the world
  (``ngp_box``) for the run's record.
- the camera id of a frame is its ``file_path``'s stem (``full_on/00003.jpg`` -> ``00003``); a frame whose
  ``file_path`` names no file is an error.

What the layout lacks is replaced by documented defaults (:data:`DEFAULTS`, said in the run's output and the
release's run.json and DATASHEET.md): no colour chart (identity colour matrix), no diffuse sphere (the ideal
LED model d = 2/3 n), no clean plates (the mask is the release's ``mask/``, else the no-plate threshold), a
white reference of 1.0 (255 is an albedo-1 unoccluded Lambertian surface under full_on; a transforms.json
``white_reference`` [r, g, b], top level or per frame, overrides it), sessions formed by actions with the
same cameras.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.capture import ILLUMINATIONS, RIG_FORMAT, ActionInfo, Capture, SessionInfo
from pipeline.codecs.srgb8 import EIGHT_BIT_EXTENSIONS
from pipeline.errors import InputError

LAYOUT = "rnha"
TRANSFORMS = "transforms.json"
MASK_FOLDER = "mask"
LAYOUT_FOLDERS = ("full_on", "pos", "neg", MASK_FOLDER, "normal_alpha")
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Camera axes: OpenCV (x right, y down, z forward) to OpenGL (x right, y up, z back); its own inverse."""
MIN_CAMERA_DISTANCE_M = 0.2
MAX_CAMERA_DISTANCE_M = 20.0
"""Median camera distance from the world origin (metres) a light stage's cameras can have; outside it the
transforms.json is in another unit or frame and is refused."""
DEFAULT_WHITE_REFERENCE = (1.0, 1.0, 1.0)
"""Linear value of an albedo-1, unoccluded Lambertian surface under full_on, per channel: the 8-bit code 255."""

DEFAULTS = {
    "images": "8-bit sRGB photos decoded to linear with the sRGB curve (255 = 1.0); pixels at 255 in any "
              "channel are treated as clipped",
    "colour": "identity colour matrix (the layout has no colour-chart frames)",
    "lights": "ideal LED gradients, d = 2/3 n (the layout has no diffuse-sphere frames)",
    "plates": "no clean plates: the foreground mask is the layout's mask/ where present, else the no-plate "
              "luminance threshold",
    "white_reference": "1.0 per channel (code 255 = an albedo-1 unoccluded Lambertian under full_on) unless "
                       "transforms.json gives white_reference: albedo is known up to one scale per camera",
    "cameras": "transforms.json as given (OpenGL camera-to-world, taken as the stage frame in metres; instant-ngp "
               "scale/offset recorded, not applied); no calibration frames",
    "normal_alpha": "the layout's normal_alpha/ is not read: normals are computed from pos/ and neg/",
    "sessions": "actions with identical cameras form one session",
    "subjects": "the layout names no subject: each action is its own subject (relighting-set splits by subject "
                "may then put one person in two splits)",
}
"""What stands in for what the public layout lacks: said by ``ultrastage run`` and in the release."""


def opencv_cam_from_world(transform_matrix: Any) -> np.ndarray:
    """(3, 4) OpenCV cam_from_world of a (4, 4) (or (3, 4)) OpenGL camera-to-world ``transform_matrix``:
    ``inverse(transform_matrix @ diag(1, -1, -1, 1))[:3]``.

    Raises:
        ValueError: not a finite (3|4, 4) matrix with an orthonormal, right-handed rotation (to 1e-4).
    """
    T = np.asarray(transform_matrix, np.float64)
    if T.shape not in ((3, 4), (4, 4)) or not np.all(np.isfinite(T)):
        raise ValueError(f"transform_matrix must be a finite 4 x 4 (or 3 x 4) matrix, got shape {T.shape}")
    P = np.eye(4)
    P[:3] = T[:3]
    R = P[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise ValueError("transform_matrix's rotation is not orthonormal and right-handed (a scaled or mirrored "
                         "pose; instant-ngp's scale and offset belong in the top-level keys)")
    return np.linalg.inv(P @ OPENGL_FROM_OPENCV)[:3]


@dataclass(frozen=True)
class RnhaTransforms:
    """One action's transforms.json, read: the rig records by camera id and instant-ngp's cube."""

    path: Path
    cameras: list[dict[str, Any]]
    """Rig camera records (camera_id, width, height, K, dist, cam_from_world OpenCV 3x4, white_reference)."""
    files: dict[str, Path]
    """camera id -> the file its frame's ``file_path`` names."""
    scale: float | None
    offset: list[float] | None
    ngp_box: list[list[float]] | None
    """[[min x, y, z], [max x, y, z]]: instant-ngp's unit cube in this world (``(0 - offset) / scale`` to
    ``(1 - offset) / scale``); None without ``scale``."""


def _number(value: Any, where: Path, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise InputError(where, f"{what} must be a finite number, got {value!r}")
    return float(value)


def _frame_value(frame: dict[str, Any], top: dict[str, Any], key: str) -> Any:
    return frame[key] if key in frame else top.get(key)


def _intrinsics(frame: dict[str, Any], top: dict[str, Any], where: Path, label: str) -> tuple[np.ndarray, int, int, list[float]]:
    """K (OpenCV), width, height and dist of one frame (per-frame keys, else the top level's)."""
    w, h = _frame_value(frame, top, "w"), _frame_value(frame, top, "h")
    if w is None or h is None:
        raise InputError(where, f"{label}: no image size (w, h): a transforms.json without intrinsics")
    width, height = int(_number(w, where, f"{label} w")), int(_number(h, where, f"{label} h"))
    if width < 2 or height < 2 or width != _number(w, where, "w") or height != _number(h, where, "h"):
        raise InputError(where, f"{label}: w, h must be whole numbers of pixels >= 2, got {w!r}, {h!r}")
    fx, fy = _frame_value(frame, top, "fl_x"), _frame_value(frame, top, "fl_y")
    angle_x, angle_y = _frame_value(frame, top, "camera_angle_x"), _frame_value(frame, top, "camera_angle_y")
    if fx is None and angle_x is not None:
        fx = 0.5 * width / math.tan(0.5 * _number(angle_x, where, f"{label} camera_angle_x"))
    if fy is None and angle_y is not None:
        fy = 0.5 * height / math.tan(0.5 * _number(angle_y, where, f"{label} camera_angle_y"))
    if fx is None and fy is None:
        raise InputError(where, f"{label}: no focal length (fl_x, fl_y or camera_angle_x): a transforms.json "
                                "without intrinsics")
    fx = _number(fx if fx is not None else fy, where, f"{label} fl_x")
    fy = _number(fy if fy is not None else fx, where, f"{label} fl_y")
    if fx <= 0 or fy <= 0:
        raise InputError(where, f"{label}: focal lengths must be > 0, got {fx}, {fy}")
    cx, cy = _frame_value(frame, top, "cx"), _frame_value(frame, top, "cy")
    cx = _number(cx, where, f"{label} cx") if cx is not None else width / 2.0
    cy = _number(cy, where, f"{label} cy") if cy is not None else height / 2.0
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    dist = [_number(_frame_value(frame, top, k) or 0.0, where, f"{label} {k}") for k in ("k1", "k2", "p1", "p2", "k3")]
    return K, width, height, dist


def _white_reference(frame: dict[str, Any], top: dict[str, Any], where: Path, label: str) -> list[float]:
    value = _frame_value(frame, top, "white_reference")
    if value is None:
        return list(DEFAULT_WHITE_REFERENCE)
    if not isinstance(value, list) or len(value) != 3:
        raise InputError(where, f"{label}: white_reference must be [r, g, b], got {value!r}")
    ref = [_number(v, where, f"{label} white_reference") for v in value]
    if min(ref) <= 0:
        raise InputError(where, f"{label}: white_reference must be > 0, got {ref}")
    return ref


def _frame_file(action_dir: Path, file_path: str) -> Path | None:
    """The file a frame's ``file_path`` names (relative to the action folder); without an extension, the
    first of :data:`EIGHT_BIT_EXTENSIONS` that exists (as instant-ngp tries .png and .exr)."""
    path = action_dir / file_path
    if path.is_file():
        return path
    if not path.suffix:
        for ext in EIGHT_BIT_EXTENSIONS:
            if path.with_suffix(ext).is_file():
                return path.with_suffix(ext)
    return None


def read_transforms(path: str | Path) -> RnhaTransforms:
    """Read one action's instant-ngp ``transforms.json`` into rig camera records (see the module docstring).

    Raises:
        InputError: naming the file: missing or not JSON, no frames, a frame without ``file_path`` or
            ``transform_matrix``, a ``file_path`` that names no file, two frames of one camera, missing
            intrinsics, a bad pose, scale or offset, or cameras not in metres around the stage.
    """
    path = Path(path)
    try:
        top = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "transforms.json is missing (the public layout's cameras)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, f"transforms.json is not valid JSON ({exc})") from None
    if not isinstance(top, dict) or not isinstance(top.get("frames"), list) or not top["frames"]:
        raise InputError(path, "transforms.json has no frames")
    cameras, files = [], {}
    for i, frame in enumerate(top["frames"]):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str) or not frame["file_path"]:
            raise InputError(path, f"frame #{i} has no file_path")
        label = f"frame #{i} ({frame['file_path']})"
        found = _frame_file(path.parent, frame["file_path"])
        if found is None:
            raise InputError(path, f"{label}: file_path names no file ({path.parent / frame['file_path']} does not "
                                   "exist)")
        cam_id = Path(frame["file_path"]).stem if Path(frame["file_path"]).suffix.lower() in EIGHT_BIT_EXTENSIONS \
            else Path(frame["file_path"]).name
        if cam_id in files:
            raise InputError(path, f"{label}: camera {cam_id} has two frames")
        if "transform_matrix" not in frame:
            raise InputError(path, f"{label}: no transform_matrix")
        try:
            cam_from_world = opencv_cam_from_world(frame["transform_matrix"])
        except (ValueError, TypeError) as exc:
            raise InputError(path, f"{label}: {exc}") from None
        K, width, height, dist = _intrinsics(frame, top, path, label)
        files[cam_id] = found
        cameras.append({"camera_id": cam_id, "width": width, "height": height, "K": K.tolist(), "dist": dist,
                        "cam_from_world": cam_from_world.tolist(),
                        "white_reference": _white_reference(frame, top, path, label), "exposure_s": None})
    centres = [-np.asarray(c["cam_from_world"])[:, :3].T @ np.asarray(c["cam_from_world"])[:, 3] for c in cameras]
    distance = float(np.median([np.linalg.norm(c) for c in centres]))
    if not MIN_CAMERA_DISTANCE_M <= distance <= MAX_CAMERA_DISTANCE_M:
        raise InputError(path, f"the cameras lie {distance:.4g} units from the world origin (median): the layout is "
                               f"read in metres around the stage ({MIN_CAMERA_DISTANCE_M}-{MAX_CAMERA_DISTANCE_M} m)")
    scale = offset = box = None
    if "scale" in top:
        scale = _number(top["scale"], path, "scale")
        if scale <= 0:
            raise InputError(path, f"scale must be > 0, got {scale}")
    if "offset" in top:
        raw = top["offset"]
        values = raw if isinstance(raw, list) else [raw] * 3
        if len(values) != 3:
            raise InputError(path, f"offset must be a number or [x, y, z], got {raw!r}")
        offset = [_number(v, path, "offset") for v in values]
    if scale is not None:
        o = np.asarray(offset if offset is not None else [0.5, 0.5, 0.5])  # instant-ngp's default offset
        box = [((0.0 - o) / scale).tolist(), ((1.0 - o) / scale).tolist()]
    return RnhaTransforms(path, cameras, files, scale, offset, box)


def is_rnha_action(folder: Path) -> bool:
    """Whether ``folder`` is one action of the public layout: it has a transforms.json or an illumination
    folder (``full_on``, ``pos``, ``neg``), and no capture.json."""
    if (folder / "capture.json").exists():
        return False
    return (folder / TRANSFORMS).is_file() or any((folder / i).is_dir() for i in ILLUMINATIONS)


def is_rnha_layout(root: str | Path) -> bool:
    """Whether ``root`` (no capture.json) is one public-layout action or a folder of them."""
    root = Path(root)
    if not root.is_dir() or (root / "capture.json").exists():
        return False
    return is_rnha_action(root) or any(is_rnha_action(p) for p in _subfolders(root))


def _subfolders(root: Path) -> list[Path]:
    try:
        with os.scandir(root) as entries:
            return sorted(Path(e.path) for e in entries if e.is_dir() and not e.name.startswith("."))
    except (FileNotFoundError, NotADirectoryError, PermissionError):
        return []


def _eight_bit_names(folder: Path) -> list[str]:
    try:
        with os.scandir(folder) as entries:
            return sorted(e.name for e in entries if Path(e.name).suffix.lower() in EIGHT_BIT_EXTENSIONS)
    except (FileNotFoundError, NotADirectoryError, PermissionError):
        return []


@dataclass
class RnhaCapture(Capture):
    """A capture opened from the public layout: the :class:`pipeline.capture.Capture` interface over action
    folders of 8-bit photos (frames are found by camera id with any of :data:`EIGHT_BIT_EXTENSIONS`)."""

    action_dirs: dict[str, Path] = field(default_factory=dict)
    transforms: dict[str, RnhaTransforms] = field(default_factory=dict)

    @property
    def ground_truth(self) -> Path | None:
        return None

    def action_dir(self, action_id: str) -> Path:
        self.action(action_id)
        return self.action_dirs[action_id]

    def _files(self, folder: Path, camera_id: str, names: list[str] | None = None) -> list[Path]:
        names = _eight_bit_names(folder) if names is None else names
        return [folder / n for n in names if Path(n).stem == camera_id]

    def raw_path(self, action_id: str, illumination: str, camera_id: str) -> Path | None:
        found = self._files(self.action_dir(action_id) / illumination, camera_id)
        return found[0] if found else None

    def raw_paths(self, action_id: str, illumination: str, camera_ids: list[str]) -> dict[str, Path | None]:
        folder = self.action_dir(action_id) / illumination
        names = _eight_bit_names(folder)
        return {cam: next(iter(self._files(folder, cam, names)), None) for cam in camera_ids}

    def background_path(self, session_id: str, camera_id: str) -> Path | None:
        return None

    def mask_paths(self, action_id: str) -> dict[str, Path]:
        """camera id -> the layout's mask photo of that camera (``mask/<cam>.jpg``), for the cameras that have
        one; empty when the action has no ``mask/`` folder."""
        session = self.sessions[self.action(action_id).session_id]
        folder = self.action_dir(action_id) / MASK_FOLDER
        names = _eight_bit_names(folder)
        return {cam: found[0] for cam in session.camera_ids if (found := self._files(folder, cam, names))}

    def action_frames(self, action_id: str) -> tuple[dict[tuple[str, str], Path], list[InputError]]:
        """All frames of an action keyed by (illumination, camera), and one error per missing illumination
        folder, camera without a photo in an illumination, camera with two photos (a duplicate frame) or photo of
        a camera transforms.json does not list (the :meth:`pipeline.capture.Capture.action_frames` rules)."""
        session = self.sessions[self.action(action_id).session_id]
        action_dir = self.action_dir(action_id)
        frames: dict[tuple[str, str], Path] = {}
        errors: list[InputError] = []
        expected = set(session.camera_ids)
        for illum in self.illuminations:
            folder = action_dir / illum
            if not folder.is_dir():
                errors.append(InputError(folder, f"illumination '{illum}' is missing (no folder)"))
                continue
            names = _eight_bit_names(folder)
            for cam in session.camera_ids:
                found = self._files(folder, cam, names)
                if not found:
                    errors.append(InputError(folder / f"{cam}.jpg", f"camera {cam} has no image for '{illum}'"))
                elif len(found) > 1:
                    errors.append(InputError(found[1], f"camera {cam} has {len(found)} images for '{illum}' "
                                                       f"({[p.name for p in found]}): a duplicate frame"))
                else:
                    frames[(illum, cam)] = found[0]
            extra = sorted(n for n in names if Path(n).stem not in expected)
            if extra:
                errors.append(InputError(folder, f"{len(extra)} image(s) for cameras not in transforms.json: "
                                                 f"{extra[:5]} (expected {len(expected)} cameras)"))
        return frames, errors


def open_rnha_capture(root: str | Path) -> RnhaCapture:
    """Open one public-layout action folder, or a folder of them (each subfolder with a transforms.json or an
    illumination folder is an action; others, e.g. ``ground_truth``, are ignored). Action ids are the folder
    names; actions with identical cameras share a session (``S000``, ``S001``, ... in action order).

    Raises:
        InputError: naming the file: an action's transforms.json is missing or bad (:func:`read_transforms`),
            or the folder holds no action.
    """
    root = Path(root)
    action_dirs = [root] if is_rnha_action(root) else [p for p in _subfolders(root) if is_rnha_action(p)]
    if not action_dirs:
        raise InputError(root, "no action of the public layout (transforms.json with full_on/, pos/, neg/) here")
    sessions: dict[str, SessionInfo] = {}
    by_cameras: dict[str, str] = {}
    actions, dirs, transforms = [], {}, {}
    for folder in action_dirs:
        read = read_transforms(folder / TRANSFORMS)
        action_id = folder.name
        signature = json.dumps(sorted(read.cameras, key=lambda c: c["camera_id"]), sort_keys=True)
        session_id = by_cameras.get(signature)
        if session_id is None:
            session_id = f"S{len(sessions):03d}"
            by_cameras[signature] = session_id
            rig = {"format": RIG_FORMAT, "session_id": session_id, "layout": LAYOUT,
                   "stage_frame": "transforms.json's world, taken as the stage frame in metres",
                   "camera_convention": "opencv", "cameras": sorted(read.cameras, key=lambda c: c["camera_id"])}
            sessions[session_id] = SessionInfo(session_id, read.path, rig)
        actions.append(ActionInfo(action_id, session_id, f"rnha/{action_id}"))
        dirs[action_id] = folder
        transforms[action_id] = read
    meta = {"format": "rnha-public-layout", "layout": LAYOUT,
            "origin": "the seed paper's public release layout (RNHA): 8-bit sRGB JPEG photos and transforms.json",
            "sessions": [{"session_id": s.session_id, "transforms": os.path.relpath(s.rig_path, root)}
                         for s in sessions.values()],
            "actions": [{"action_id": a.action_id, "session_id": a.session_id, "subject": a.subject,
                         "ngp_scale": transforms[a.action_id].scale, "ngp_offset": transforms[a.action_id].offset}
                        for a in actions],
            "illuminations": list(ILLUMINATIONS), "defaults": dict(DEFAULTS)}
    return RnhaCapture(root=root, meta=meta, sessions=sessions, actions=actions, illuminations=ILLUMINATIONS,
                       action_dirs=dirs, transforms=transforms)
