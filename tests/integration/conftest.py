"""Shared fixtures of the integration tests."""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from synthetic import SimConfig, simulate
from synthetic.calibration import CalibrationConfig

TINY_CAMERAS = ("00000", "00001", "00002")

GATE_SIM = SimConfig(actions=1, width=128, n_cameras=32, n_leds=256, mesh="procedural")
"""The accuracy gate's capture: one action of the whole 32-camera rig at 128 x 192 px, the procedural subject
(the same with or without ../shared/data)."""
GATE_CALIBRATION = CalibrationConfig(target=False)
"""Its session frames: colour chart, diffuse sphere and the marker frame (27 of the 32 cameras identify enough of
its 12 mm balls at 128 px to be calibrated; the session is still calibrated from them); no structure-from-motion
target."""


@pytest.fixture(scope="session")
def gate_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """:data:`GATE_SIM` with :data:`GATE_CALIBRATION`, simulated once per test session. Read-only."""
    root = tmp_path_factory.mktemp("gate") / "capture"
    simulate(root, GATE_SIM, calibration=GATE_CALIBRATION)
    return root


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2 actions, 3 cameras, 48 px, clean plates, no calibration frames: for photometric-only runs.
    Read-only: a test that changes it copies it first."""
    root = tmp_path_factory.mktemp("tiny") / "capture"
    simulate(root, SimConfig(actions=2, width=48, n_cameras=len(TINY_CAMERAS), n_leds=64))
    return root


ROOT = Path(__file__).resolve().parents[2]


@contextlib.contextmanager
def dask_cluster(folder: Path, n_workers: int, env: dict[str, str] | None = None,
                 resources: dict[int, str] | None = None) -> Iterator[tuple[str, dict[str, int]]]:
    """A ``dask scheduler`` and ``n_workers`` single-threaded ``dask worker`` processes on 127.0.0.1, as a user
    starts them, each its own process group; ``env`` is added to their environment (e.g. dask config variables);
    ``resources``: worker index (0-based, named ``w<index + 1>``) -> its ``--resources`` (e.g. ``"GPU=1"``).
    Yields the scheduler's address and each worker's address -> the pid of its worker process."""
    env = os.environ | {"PYTHONPATH": str(ROOT), "ULTRASTAGE_NUMERIC_THREADS": "1", "OMP_NUM_THREADS": "1"} | (env or {})
    info = folder / "scheduler.json"
    common = dict(env=env, cwd=folder, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                               "--port", "0", "--dashboard-address", ":0", "--scheduler-file", str(info)], **common)]
    try:
        deadline = time.monotonic() + 60
        while not info.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert info.exists(), "the dask scheduler did not start"
        for i in range(n_workers):
            extra = ["--resources", resources[i]] if resources and i in resources else []
            procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file",
                                           str(info), "--nworkers", "1", "--nthreads", "1", "--name", f"w{i + 1}",
                                           "--no-dashboard", "--host", "127.0.0.1", *extra], **common))
        address = json.loads(info.read_text())["address"]
        from distributed import Client

        with Client(address, timeout=60) as client:
            client.wait_for_workers(n_workers, timeout=60)
            pids = client.run(os.getpid)
        assert len(set(pids.values())) == n_workers and os.getpid() not in pids.values()  # separate processes
        yield address, pids
    finally:  # each was started as its own process group (a worker's nanny and its worker process): end both
        for proc in reversed(procs):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
        for proc in procs:
            proc.wait(timeout=30)
