"""Shared fixtures of the integration tests."""
from __future__ import annotations

from pathlib import Path

import pytest

from synthetic import SimConfig, simulate

TINY_CAMERAS = ("00000", "00001", "00002")


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2 actions, 3 cameras, 48 px, clean plates, no calibration frames: for photometric-only runs.
    Read-only: a test that changes it copies it first."""
    root = tmp_path_factory.mktemp("tiny") / "capture"
    simulate(root, SimConfig(actions=2, width=48, n_cameras=len(TINY_CAMERAS), n_leds=64))
    return root
