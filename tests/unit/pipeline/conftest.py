"""A toy capture and toy stages to exercise the engine without decoding anything."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from pipeline.config import Documented
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext

CAMS = ["00000", "00001", "00002"]


def make_toy_capture(root: Path, actions: tuple[str, ...] = ("A0000", "A0001")) -> Path:
    cams = [{"camera_id": c, "width": 4, "height": 6, "K": [[5, 0, 2], [0, 5, 3], [0, 0, 1]],
             "cam_from_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2]], "white_reference": [0.5, 0.5, 0.5]}
            for c in CAMS]
    (root / "sessions" / "S000").mkdir(parents=True)
    (root / "sessions" / "S000" / "rig.json").write_text(json.dumps(
        {"format": "ultrastage-rig/1", "session_id": "S000", "cameras": cams}))
    for a in actions:
        for illum in ("full_on", "pos", "neg"):
            d = root / "actions" / a / illum
            d.mkdir(parents=True)
            for c in CAMS:
                (d / f"{c}.dng").write_text(f"{a} {illum} {c}")
    (root / "capture.json").write_text(json.dumps({
        "format": "ultrastage-capture/1", "sessions": [{"session_id": "S000", "rig": "sessions/S000/rig.json"}],
        "actions": [{"action_id": a, "session_id": "S000", "subject": "toy"} for a in actions],
        "illuminations": ["full_on", "pos", "neg"], "camera_ids": CAMS}))
    return root


@dataclass(frozen=True)
class ToyConfig(Documented):
    gain: float = 1.0
    """Multiplies the 'signal'."""
    workers: int = 1
    """Not in the key."""
    not_in_key = ("workers",)


class SessionToy(Stage):
    name = "calib"
    scope = "session"
    outputs = ("calib.txt",)

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        return {"rig": capture.sessions[scope_id].rig_path}

    def run(self, ctx: StageContext) -> dict[str, Any]:
        (ctx.out_dir / "calib.txt").write_text("calibrated")
        ctx.progress(1, 1, "calibrated")
        return {"ok": 1}


class ReadToy(Stage):
    """Per-view: 'decodes' a raw file (its text) and fails on files containing BAD."""

    name = "read"
    requires = ("calib",)
    outputs = ("frames",)
    per_view = True

    def raw_inputs(self, capture: Any, scope_id: str) -> dict[str, Path]:
        frames, errors = capture.action_frames(scope_id)
        if errors:
            raise InputError(errors[0].path, errors[0].reason)
        return {f"{i}/{c}": p for (i, c), p in frames.items()}

    def run_view(self, ctx: StageContext, view: str) -> dict[str, Any]:
        text = ctx.raw_inputs[f"full_on/{view}"].read_text()
        if "BAD" in text:
            raise InputError(ctx.raw_inputs[f"full_on/{view}"], "corrupt toy frame")
        (ctx.out_dir / "frames").mkdir(exist_ok=True)
        (ctx.out_dir / "frames" / f"{view}.txt").write_text(f"{text} x{self.config.gain}")
        return {"chars": len(text)}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        return [(p, f"frames/{p.name}", "frame", p.stem) for p in sorted((artifact / "frames").glob("*.txt"))]


class SumToy(Stage):
    name = "summary"
    requires = ("read",)
    outputs = ("summary.txt",)

    def run(self, ctx: StageContext) -> dict[str, Any]:
        files = sorted((ctx.upstream["read"] / "frames").glob("*.txt"))
        (ctx.out_dir / "summary.txt").write_text(str(len(files)))
        return {"n": len(files)}

    def release_files(self, artifact: Path) -> list[tuple[Path, str, str, str | None]]:
        return [(artifact / "summary.txt", "summary.txt", "summary", None)]


def toy_stages(gain: float = 1.0, workers: int = 1) -> list[Stage]:
    cfg = ToyConfig(gain=gain, workers=workers)
    return [SessionToy(ToyConfig()), ReadToy(cfg), SumToy(ToyConfig())]


@pytest.fixture
def toy_capture(tmp_path: Path) -> Path:
    return make_toy_capture(tmp_path / "capture")
