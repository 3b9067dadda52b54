"""The photometric-only DAG on a dask cluster of separate processes (a ``dask scheduler`` and two ``dask
worker`` processes on 127.0.0.1, as a user starts them) gives the release a local in-process run gives
(issue 23): the same asset digests."""
from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.runner import ExecutionConfig
from stages.registry import PRESETS, build_stages
from ultrastage.run import run_pipeline
from tests.integration.conftest import dask_cluster


def _digests(release: Path) -> dict[str, str]:
    from manifests import open_release

    assets = open_release(release).assets
    return dict(zip(assets.path, assets.sha256))


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A scheduler and two single-threaded workers without resources, each its own process; yields the scheduler's
    address. The module's tests share it: none changes it."""
    with dask_cluster(tmp_path_factory.mktemp("plain_cluster"), 2) as (address, _pids):
        yield address


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


def _worker_name() -> str:
    from distributed import get_worker

    return str(get_worker().name)


def test_gpu_tasks_go_to_the_worker_started_with_the_gpu_resource(tmp_path):
    """As README says to start it: ``dask worker --resources GPU=1`` on the GPU machine, plain workers beside it. A
    task annotated like the geometry stage runs on that worker only; unannotated tasks run anywhere."""
    from pipeline.graph import DaskExecutor
    from stages.geometry import GeometryStage

    assert GeometryStage.resources == {"GPU": 1}
    (tmp_path / "gpu").mkdir()
    with dask_cluster(tmp_path / "gpu", 2, resources={0: "GPU=1"}) as (address, _pids):
        executor = DaskExecutor(address)
        try:
            gpu = [executor.submit(_worker_name, key=f"gpu-{i}", resources=GeometryStage.resources) for i in range(8)]
            anywhere = [executor.submit(_worker_name, key=f"cpu-{i}") for i in range(8)]
            assert {f.result(timeout=120) for f in gpu} == {"w1"}
            assert {f.result(timeout=120) for f in anywhere} <= {"w1", "w2"}
        finally:
            executor.close()


def test_on_a_cluster_without_the_gpu_resource_a_gpu_task_still_runs(cluster):
    """The annotation is dropped where no worker has the resource (dask would otherwise hold the task forever)."""
    from pipeline.graph import DaskExecutor
    from stages.geometry import GeometryStage

    executor = DaskExecutor(cluster)
    try:
        tasks = [executor.submit(_worker_name, key=f"gpu-{i}", resources=GeometryStage.resources) for i in range(4)]
        assert {f.result(timeout=120) for f in tasks} <= {"w1", "w2"}
    finally:
        executor.close()
