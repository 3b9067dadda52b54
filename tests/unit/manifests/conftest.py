"""A small release on disk: one action, two cameras, every per-camera asset kind, manifests written."""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from manifests import asset_row, write_table
from pipeline.codecs.exr import write_exr
from pipeline.codecs.image import write_png

H, W = 6, 4
CAMS = ("00000", "00001")


def _normals(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(H, W, 3)).astype(np.float32)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def build_release(root: Path, action_id: str = "A0000") -> Path:
    """Write a tiny release with actions and assets manifests; returns the root."""
    rows = []
    adir = root / "actions" / action_id
    for i, cam in enumerate(CAMS):
        for ill in ("full_on", "pos", "neg"):
            p = write_exr(adir / ill / f"{cam}.exr", np.full((H, W, 3), 0.25 * (i + 1), np.float32))
            rows.append(asset_row(root, p, ill, action_id, cam))
        n = _normals(i)
        alpha = np.linspace(0, 1, H * W, dtype=np.float32).reshape(H, W)
        p = write_exr(adir / "normal_alpha" / f"{cam}.exr", np.concatenate([n, alpha[..., None]], axis=-1))
        rows.append(asset_row(root, p, "normal_alpha", action_id, cam))
        p = write_exr(adir / "albedo" / f"{cam}.exr", np.full((H, W, 3), 0.5, np.float32))
        rows.append(asset_row(root, p, "albedo", action_id, cam))
        mask = np.zeros((H, W), np.uint8)
        mask[1:4, 1:3] = 255
        p = write_png(adir / "mask" / f"{cam}.png", mask)
        rows.append(asset_row(root, p, "mask", action_id, cam))
    transforms = adir / "transforms.json"
    transforms.write_text(json.dumps({"frames": [{"camera_id": c} for c in CAMS]}))
    rows.append(asset_row(root, transforms, "transforms", action_id))
    write_table(root, "assets", rows)
    write_table(root, "actions", [dict(action_id=action_id, session_id="S000", subject="makehuman/test",
                                       status="ok", error=None, n_cameras=len(CAMS), width=W, height=H,
                                       stages_run=5, stages_cached=0, seconds=1.25)])
    return root


@pytest.fixture
def tiny() -> SimpleNamespace:
    """The constants of the tiny release (map size, cameras, the normals it holds per camera index)."""
    return SimpleNamespace(H=H, W=W, CAMS=CAMS, normals=_normals)


@pytest.fixture
def release_dir(tmp_path: Path) -> Path:
    return build_release(tmp_path / "release")
