"""A tiny fake relighting set IN THE RELEASE FORMAT (files under RELEASE/relight/<example_id>/, the index
``relight_examples`` written with manifests.write_table), and a tiny trained checkpoint of each network.

Subjects are ellipsoids seen orthographically (camera-frame normals, OpenCV axes: camera-facing z < 0) with a
subject-specific patterned albedo, shaded Lambertian under order-2 SH lighting of a random environment (an
ambient colour plus one bright lobe) rotated into the camera frame, the way the relightset stage describes
its examples: ``image = albedo / pi * E(n)``, ``E`` from ``sh_camera_json``.
"""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from manifests import write_table
from pipeline.codecs.exr import write_exr
from pipeline.codecs.image import srgb_encode, write_png
from stages.numerics import sh
from stages.numerics.sg import equirect_directions

SIZE = 64
SPLIT_OF_SUBJECT = {**{f"s{i}": "train" for i in range(10)}, "s10": "validation", "s11": "test", "s12": "test",
                    "s13": "test"}

torch.set_num_threads(1)


def _environment(rng: np.random.Generator) -> np.ndarray:
    d = equirect_directions(16, 32).astype(np.float64)
    lobe = rng.normal(size=3)
    lobe /= np.linalg.norm(lobe)
    # near-white light (as white-balanced HDR maps mostly are): the albedo's colour stays learnable
    ambient = rng.uniform(0.1, 0.4) * rng.uniform(0.85, 1.15, 3)
    colour = rng.uniform(1.0, 3.0) * rng.uniform(0.85, 1.15, 3)
    return (ambient + colour * np.exp(6.0 * (d @ lobe - 1.0))[..., None]).astype(np.float32)


def _subject(index: int, rng: np.random.Generator, size: int):
    """Ellipsoid normals (H, W, 3), mask (H, W) and albedo (H, W, 3) of one view of subject ``index``."""
    cx, cy = rng.uniform(0.4, 0.6, 2) * size
    rx, ry = rng.uniform(0.22, 0.38, 2) * size
    rz = rng.uniform(0.2, 0.4) * size
    v, u = np.mgrid[0:size, 0:size].astype(np.float64) + 0.5
    x, y = (u - cx) / rx, (v - cy) / ry
    q = x * x + y * y
    mask = q < 0.97
    z = -np.sqrt(np.clip(1.0 - q, 0.0, None))
    n = np.stack([x / rx, y / ry, z / rz], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[~mask] = 0.0
    base = np.random.default_rng(100 + index).uniform(0.25, 0.8, 3)
    period = 6 + 2 * (index % 4)
    if index % 2:
        pattern = ((u // period + v // period) % 2)[..., None]  # checker
    else:
        pattern = (0.5 + 0.5 * np.sin(2 * math.pi * (u + 0.5 * v) / period))[..., None]  # stripes
    albedo = np.clip(base * (0.55 + 0.45 * pattern), 0.02, 0.95) * mask[..., None]
    return n.astype(np.float32), mask, albedo.astype(np.float32)


def make_fake_relight_set(root: Path, views: int = 2, size: int = SIZE, seed: int = 0,
                          subjects: dict[str, str] | None = None) -> Path:
    """Write the fake set into release folder ``root`` (made) and return it."""
    subjects = SPLIT_OF_SUBJECT if subjects is None else subjects
    rng = np.random.default_rng(seed)
    rows = []
    for s_index, (subject, split) in enumerate(subjects.items()):
        action_id = f"A{s_index:04d}"
        for view in range(views):
            example_id = f"{action_id}_{view:02d}"
            folder = Path("relight") / example_id
            normal, mask, albedo = _subject(s_index, rng, size)
            env = _environment(rng)
            rotation = float(rng.uniform(0, 360))
            cam_from_world = np.diag([1.0, -1.0, -1.0]) @ sh.rotation_y(float(rng.uniform(-40, 40)))
            sh_world = sh.project_environment(env, sh.rotation_y(rotation))
            sh_camera = sh.project_environment(env, cam_from_world @ sh.rotation_y(rotation))
            irradiance = sh.sh_irradiance(normal.reshape(-1, 3), sh_camera).reshape(size, size, 3)
            linear = (albedo / math.pi * irradiance * mask[..., None]).astype(np.float32)
            exposure = 0.8 / max(float(np.percentile(linear[mask], 99)), 1e-6)
            png = (srgb_encode(linear * exposure) * 255 + 0.5).astype(np.uint8)
            files = {
                "image_exr": write_exr(root / folder / "image.exr",
                                       np.concatenate([linear, mask[..., None].astype(np.float32)], axis=-1)),
                "image_png": write_png(root / folder / "image.png", png),
                "albedo_exr": write_exr(root / folder / "albedo.exr", albedo),
                "albedo_png": write_png(root / folder / "albedo.png", (srgb_encode(albedo) * 255 + 0.5).astype(np.uint8)),
                "normal_exr": write_exr(root / folder / "normal.exr", normal, half=False),
                "normal_png": write_png(root / folder / "normal.png",
                                        ((normal + 1) / 2 * 255 * mask[..., None] + 0.5).astype(np.uint8)),
                "mask_png": write_png(root / folder / "mask.png", mask),
            }
            t = np.zeros((3, 1))
            t[2] = 2.5
            rows.append({
                "example_id": example_id, "action_id": action_id, "subject": subject, "session_id": "S000",
                "split": split, "view_index": view, "width": size, "height": size,
                "fx": 500.0, "fy": 500.0, "cx": size / 2, "cy": size / 2,
                "cam_from_world_json": json.dumps(np.hstack([cam_from_world, t]).tolist()),
                "environment_name": "procedural:fake", "environment_file": "",
                "environment_sha256": hashlib.sha256(env.tobytes()).hexdigest(),
                "environment_rotation_deg": rotation,
                "sh_camera_json": json.dumps(sh_camera.tolist()), "sh_world_json": json.dumps(sh_world.tolist()),
                **{k: p.relative_to(root).as_posix() for k, p in files.items()},
                "png_exposure": exposure, "mask_pixels": int(mask.sum()), "seed": seed,
                "example_key": hashlib.sha256(f"{example_id}-{seed}".encode()).hexdigest()[:16],
            })
    write_table(root, "relight_examples", rows)
    return root


@pytest.fixture(scope="session")
def fake_set(tmp_path_factory) -> Path:
    """The fake relighting set (read-only: tests that change it make their own)."""
    return make_fake_relight_set(tmp_path_factory.mktemp("fakeset") / "release")


@pytest.fixture(scope="session")
def make_set():
    """The fake-set writer, for tests that need a set of their own (other splits, broken files)."""
    return make_fake_relight_set


@pytest.fixture(scope="session")
def trained(fake_set, tmp_path_factory) -> dict[str, Path]:
    """Output folders of ``ultrastage train <network> --preset tiny`` on the fake set, by network, trained on one
    torch thread whatever an earlier test in this process set: the summation order changes the 120 tiny steps'
    outcome (AlbedoNet's raw albedo PSNR over the input image's, measured: +0.55 dB on 1 thread, -0.63 dB on 2,
    +0.32 on 3, +0.41 on 4)."""
    from ultrastage.cli import main

    one_thread = tmp_path_factory.mktemp("train_config") / "one_thread.yaml"
    one_thread.write_text("threads: 1\n")
    out = {}
    for network in ("albedonet", "normalnet"):
        out[network] = tmp_path_factory.mktemp("trained") / network
        assert main(["train", network, "--set", str(fake_set), "--preset", "tiny", "--config", str(one_thread),
                     "--out", str(out[network])]) == 0
    return out
