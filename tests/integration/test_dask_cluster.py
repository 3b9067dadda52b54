"""The photometric-only DAG on a dask cluster of separate processes (a ``dask scheduler`` and two ``dask
worker`` processes on 127.0.0.1, as a user starts them) gives the release a local in-process run gives
(issue 23): the same asset digests."""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.runner import ExecutionConfig, run_pipeline
from stages.registry import PRESETS, build_stages

ROOT = Path(__file__).resolve().parents[2]


def _digests(release: Path) -> dict[str, str]:
    from manifests import open_release

    assets = open_release(release).assets
    return dict(zip(assets.path, assets.sha256))


@pytest.fixture
def cluster(tmp_path):
    """A scheduler and two single-threaded workers, each its own process; yields the scheduler's address."""
    env = os.environ | {"PYTHONPATH": str(ROOT), "ULTRASTAGE_NUMERIC_THREADS": "1", "OMP_NUM_THREADS": "1"}
    info = tmp_path / "scheduler.json"
    common = dict(env=env, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                  start_new_session=True)
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                               "--port", "0", "--dashboard-address", ":0", "--scheduler-file", str(info)], **common)]
    try:
        deadline = time.monotonic() + 60
        while not info.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert info.exists(), "the dask scheduler did not start"
        for name in ("w1", "w2"):
            procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file",
                                           str(info), "--nworkers", "1", "--nthreads", "1", "--name", name,
                                           "--no-dashboard", "--host", "127.0.0.1"], **common))
        address = json.loads(info.read_text())["address"]
        from distributed import Client

        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=60)
            pids = set(client.run(os.getpid).values())
        assert len(pids) == 2 and os.getpid() not in pids  # two worker processes, not this one
        yield address
    finally:  # each was started as its own process group (a worker's nanny and its worker process): end both
        for proc in reversed(procs):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
        for proc in procs:
            proc.wait(timeout=30)


def test_a_cluster_of_processes_gives_the_local_release(tiny_capture, cluster, tmp_path):
    config = PRESETS["test"]
    stages = build_stages(config, through="photometric")
    remote = run_pipeline(tiny_capture, tmp_path / "remote" / "release", tmp_path / "remote" / "work", stages, config,
                          ExecutionConfig(scheduler=cluster), echo=lambda line: None)
    assert remote.executor == f"dask scheduler at {cluster}"
    assert remote.action_status == {"A0000": "ok", "A0001": "ok"}
    local = run_pipeline(tiny_capture, tmp_path / "local" / "release", tmp_path / "local" / "work", stages, config,
                         ExecutionConfig(scheduler="sync"), echo=lambda line: None)
    assert local.action_status == remote.action_status
    remote_digests, local_digests = _digests(tmp_path / "remote" / "release"), _digests(tmp_path / "local" / "release")
    # every file of the actions (decoded images, maps, masks, transforms): the same bytes
    actions = {p: d for p, d in local_digests.items() if p.startswith("actions/")}
    assert len(actions) > 3 * 2 * 6
    assert {p: remote_digests.get(p) for p in actions} == actions
