"""The capture folder as the pipeline sees it: sessions, rigs, actions and their raw files.

Layout in docs/CONTRACTS.md. Reading a capture never decodes anything; it finds files and reports what
is missing, so a planning step can fail one action with a clear message and go on with the others.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.errors import InputError

CAPTURE_FORMAT = "ultrastage-capture/1"
RIG_FORMAT = "ultrastage-rig/1"
ILLUMINATIONS = ("full_on", "pos", "neg")
# Raw extensions LibRaw reads that a stage camera may write; anything else beside them is ignored.
RAW_EXTENSIONS = (".dng", ".nef", ".nrw", ".cr2", ".cr3", ".arw", ".raf", ".orf", ".rw2", ".pef", ".kdc", ".srw")


@dataclass(frozen=True)
class ActionInfo:
    action_id: str
    session_id: str
    subject: str


@dataclass
class SessionInfo:
    session_id: str
    rig_path: Path
    rig: dict[str, Any]

    @property
    def camera_ids(self) -> list[str]:
        return [c["camera_id"] for c in self.rig["cameras"]]

    def camera(self, camera_id: str) -> dict[str, Any]:
        for cam in self.rig["cameras"]:
            if cam["camera_id"] == camera_id:
                return cam
        raise KeyError(f"{self.rig_path}: no camera {camera_id}")


@dataclass
class Capture:
    """An opened capture folder."""

    root: Path
    meta: dict[str, Any]
    sessions: dict[str, SessionInfo]
    actions: list[ActionInfo]
    illuminations: tuple[str, ...] = ILLUMINATIONS
    problems: list[str] = field(default_factory=list)

    @property
    def ground_truth(self) -> Path | None:
        gt = self.root / "ground_truth"
        return gt if gt.is_dir() else None

    def action(self, action_id: str) -> ActionInfo:
        """The action's entry, looked up by id in a dict (a release-size capture is asked once per task)."""
        index = self.__dict__.get("_action_index")
        if index is None or index[0] is not self.actions or len(index[1]) != len(self.actions):
            index = (self.actions, {info.action_id: info for info in reversed(self.actions)})  # the first wins
            self.__dict__["_action_index"] = index
        info = index[1].get(action_id)
        if info is None:
            raise KeyError(f"{self.root}: no action {action_id}")
        return info

    def raw_path(self, action_id: str, illumination: str, camera_id: str) -> Path | None:
        """The raw file of one frame (any extension LibRaw reads), or None when it is missing."""
        return _find_raw(self.root / "actions" / action_id / illumination, camera_id)

    def raw_paths(self, action_id: str, illumination: str, camera_ids: list[str]) -> dict[str, Path | None]:
        """:meth:`raw_path` of several cameras of one illumination, from one listing of its folder."""
        folder = self.root / "actions" / action_id / illumination
        names = _raw_names(folder)
        found = {}
        for cam in camera_ids:
            matches = _raw_files(folder, cam, names)
            found[cam] = matches[0] if matches else None
        return found

    def background_path(self, session_id: str, camera_id: str) -> Path | None:
        return _find_raw(self.root / "sessions" / session_id / "background", camera_id)

    def action_frames(self, action_id: str) -> tuple[dict[tuple[str, str], Path], list[InputError]]:
        """All raw frames of an action keyed by (illumination, camera), and one error per missing frame,
        per camera with more than one raw file for an illumination (a duplicate frame) or per unexpected extra
        raw file (a wrong count). Files that are not raw (sidecars, notes, thumbnails) are ignored."""
        info = self.action(action_id)
        session = self.sessions[info.session_id]
        frames: dict[tuple[str, str], Path] = {}
        errors: list[InputError] = []
        action_dir = self.root / "actions" / action_id
        if not action_dir.is_dir():
            return frames, [InputError(action_dir, "action folder is missing")]
        for illum in self.illuminations:
            folder = action_dir / illum
            if not folder.is_dir():
                errors.append(InputError(folder, f"illumination '{illum}' is missing (no folder)"))
                continue
            expected = set(session.camera_ids)
            names = _raw_names(folder)  # one listing of the folder for all its cameras
            for cam in session.camera_ids:
                found = _raw_files(folder, cam, names)
                if not found:
                    errors.append(InputError(folder / f"{cam}.*", f"camera {cam} has no raw file for '{illum}'"))
                elif len(found) > 1:  # e.g. 00002.dng beside 00002.DNG: which one is the frame is anyone's guess
                    errors.append(InputError(found[1], f"camera {cam} has {len(found)} raw files for '{illum}' "
                                                       f"({[p.name for p in found]}): a duplicate frame"))
                else:
                    frames[(illum, cam)] = found[0]
            extra = sorted(n for n in names if Path(n).stem not in expected)
            if extra:
                errors.append(InputError(folder, f"{len(extra)} raw file(s) for cameras not in the rig: {extra[:5]}"
                                                 f" (expected {len(expected)} cameras)"))
        return frames, errors


def _raw_names(folder: Path) -> list[str]:
    """The names in a folder with a raw extension (any case), sorted; empty when it is not a folder."""
    try:
        with os.scandir(folder) as entries:
            return sorted(e.name for e in entries if Path(e.name).suffix.lower() in RAW_EXTENSIONS)
    except (FileNotFoundError, NotADirectoryError, PermissionError):
        return []


def _raw_files(folder: Path, camera_id: str, names: list[str] | None = None) -> list[Path]:
    """The raw files of one camera in a folder (``<camera_id>.<raw extension>``), sorted by name; ``names``:
    the folder's :func:`_raw_names` when the caller listed it already (one listing for every camera)."""
    if names is None:
        names = _raw_names(folder)
    prefix = f"{camera_id}."
    return [folder / n for n in names if n.startswith(prefix)]


def _find_raw(folder: Path, camera_id: str) -> Path | None:
    matches = _raw_files(folder, camera_id)
    return matches[0] if matches else None


def _read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise InputError(path, f"{what} is missing") from exc
    except json.JSONDecodeError as exc:
        raise InputError(path, f"{what} is not valid JSON ({exc})") from exc


def _check_rig(rig: dict[str, Any], path: Path) -> None:
    if rig.get("format") != RIG_FORMAT:
        raise InputError(path, f"unknown rig format {rig.get('format')!r}, expected {RIG_FORMAT!r}")
    cameras = rig.get("cameras")
    if not cameras:
        raise InputError(path, "rig has no cameras")
    required = ("camera_id", "width", "height", "K", "cam_from_world", "white_reference")
    for i, cam in enumerate(cameras):
        missing = [k for k in required if k not in cam]
        if missing:
            raise InputError(path, f"camera #{i} lacks {missing}")
    ids = [c["camera_id"] for c in cameras]
    if len(set(ids)) != len(ids):
        raise InputError(path, "duplicate camera ids in rig")


def open_capture(root: str | Path) -> Capture:
    """Open a capture folder; raises InputError naming the file for a missing or malformed index. A folder
    without ``capture.json`` in the public release's layout (one action folder of ``full_on/``, ``pos/``,
    ``neg/`` photos and a ``transforms.json``, or a folder of them) opens as :class:`pipeline.capture_rnha.RnhaCapture`."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "capture folder does not exist")
    if not (root / "capture.json").exists():
        from pipeline.capture_rnha import is_rnha_layout, open_rnha_capture

        if is_rnha_layout(root):  # the seed paper's public release layout: 8-bit photos and transforms.json
            return open_rnha_capture(root)
    meta = _read_json(root / "capture.json", "capture index")
    if meta.get("format") != CAPTURE_FORMAT:
        raise InputError(root / "capture.json", f"unknown capture format {meta.get('format')!r}")
    sessions: dict[str, SessionInfo] = {}
    for entry in meta.get("sessions", []):
        rig_path = root / entry["rig"]
        rig = _read_json(rig_path, "rig spec")
        _check_rig(rig, rig_path)
        sessions[entry["session_id"]] = SessionInfo(entry["session_id"], rig_path, rig)
    actions = []
    for entry in meta.get("actions", []):
        if entry["session_id"] not in sessions:
            raise InputError(root / "capture.json", f"action {entry['action_id']} names unknown session "
                                                    f"{entry['session_id']}")
        actions.append(ActionInfo(entry["action_id"], entry["session_id"], entry.get("subject", "")))
    if not actions:
        raise InputError(root / "capture.json", "capture lists no actions")
    ids = [a.action_id for a in actions]
    if len(set(ids)) != len(ids):
        raise InputError(root / "capture.json", "duplicate action ids")
    illums = tuple(meta.get("illuminations", ILLUMINATIONS))
    if set(illums) != set(ILLUMINATIONS):
        raise InputError(root / "capture.json", f"illuminations {list(illums)} are not {list(ILLUMINATIONS)}")
    return Capture(root=root, meta=meta, sessions=sessions, actions=actions, illuminations=ILLUMINATIONS)
