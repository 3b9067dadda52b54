"""Faults of the machines a run is on (issue 23): a dask worker killed mid-run, the driver killed mid-run, a full
disk and an unwritable release folder. Each is done for real (SIGKILL, a tmpfs that fills up, a read-only bind
mount) on a small simulated capture through the photometric-only DAG, and the release is compared, digest by
digest, with the one an uninterrupted run writes.

- A worker killed (SIGKILL to its process) while it runs a task and holds results of committed stages: dask
  reschedules the lost tasks and the same run completes. Before the fix in ``pipeline.graph.finish_task`` the
  recomputed commit of an already committed stage ran again into a folder that was gone, and every action
  failed; now a task committed by its own execution returns that commit. With the scheduler allowed no
  failures (``allowed-failures: 0``) the task is lost instead (``KilledWorker``): the run records the actions
  it belongs to as failed, and a rerun completes them.
- The driver (``ultrastage run``) killed once some stages committed: the rerun takes over the dead run's lock,
  takes every committed stage from the store (reported cached), runs only the rest, and rebuilds the manifests
  from the success records. The share of tasks it redoes is printed.
- A full disk (a tmpfs, as root; skipped otherwise) under the release: the run ends with exit 4 and an error
  naming the release folder, ENOSPC and the step of the publication, and the release is byte for byte what it
  was (nothing of a new one; a published one still verifies), whichever step the disk runs full in; with the
  space back the same run publishes the uninterrupted release. Under the work folder: the actions fail, named
  with the file and the reason, and the rerun retries them. A release folder on a read-only bind mount, or under
  a regular file: refused before any work (exit 4), naming the path.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.runner import ExecutionConfig
from stages.registry import PRESETS, build_stages
from ultrastage.run import run_pipeline
from synthetic import SimConfig, simulate
from tests.integration.conftest import ROOT, dask_cluster

THROUGH = "photometric"
RUN_SPECIFIC = ("run.json", "index.html")
"""Release files that name the run (its id and time): they differ between any two runs."""


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """6 actions of 3 cameras at 48 px: enough tasks that a run can be caught half done."""
    root = tmp_path_factory.mktemp("faults") / "capture"
    simulate(root, SimConfig(actions=6, width=48, n_cameras=3, n_leds=64))
    return root


def _cli_command(capture: Path, release: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "ultrastage.cli", "run", "--capture", str(capture), "--release", str(release),
            "--preset", "test", "--through", THROUGH, "--no-evaluate", *extra]


def _env() -> dict[str, str]:
    return os.environ | {"PYTHONPATH": str(ROOT)}


@pytest.fixture(scope="module")
def reference(capture: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The release of an uninterrupted ``ultrastage run`` on a local dask cluster (the default deployment)."""
    release = tmp_path_factory.mktemp("reference") / "release"
    done = subprocess.run(_cli_command(capture, release, "--scheduler", "local"), env=_env(), cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return release


def _digests(release: Path, leave_out: tuple[str, ...] = RUN_SPECIFIC) -> dict[str, str]:
    from manifests import open_release

    assets = open_release(release).assets
    return {p: d for p, d in zip(assets.path, assets.sha256) if p not in leave_out}


def _committed(work: Path) -> set[tuple[str, str]]:
    """(stage, scope) of every folder committed in the work folder's store."""
    return {(p.parts[-4], p.parts[-3]) for p in (work / "artifacts").glob("*/*/*/_SUCCESS.json")}


def _leftovers(folder: Path) -> list[str]:
    """Temporary files and folders (``.tmp-*``, ``.old-*``, ``.*.tmp``, ``.txn-*``) anywhere under ``folder``."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob(".*")
                  if p.name.startswith((".tmp-", ".old-", ".txn-")) or p.name.endswith(".tmp"))


# --- a worker killed ------------------------------------------------------------------------------------

_KILL_ATTEMPTS = 3
"""Runs of the lost-task scenario before the test gives up on the kill landing on a running task."""


def _kill_a_busy_worker_holding_committed_results(address: str, work: str, out: str, timeout: float = 120.0) -> None:
    """SIGKILL the process of a worker that is running a task while it holds the result of an action's decode
    stage, committed in the store (so dask has to reschedule what it runs and recompute what it held, which the
    photometric tasks still need); write what was killed to ``out`` (JSON). Runs in its own process, as an
    operator would, with its own dask client (two clients in the driver's process trip over each other's event
    loops)."""
    from distributed import Client

    with Client(address, timeout=60) as client:
        pids = client.run(os.getpid)
        Path(out).with_suffix(".ready").touch()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            committed = _committed(Path(work))
            who_has = client.who_has() if committed else {}
            for worker, keys in client.processing().items() if committed else ():
                held = [k for k, where in who_has.items() if worker in where and k.startswith("decode-")
                        and k.endswith("-commit") and tuple(k.split("-")[:2]) in committed]
                if not keys or not held:
                    continue
                running = client.run(lambda dask_worker: [ts.key for ts in dask_worker.state.executing],
                                     workers=[worker]).get(worker, [])
                if running:
                    os.kill(pids[worker], signal.SIGKILL)
                    Path(out).write_text(json.dumps({"pid": pids[worker], "running": running, "held": held,
                                                     "committed": len(committed)}))
                    return
            time.sleep(0.005)
    Path(out).write_text(json.dumps({"error": "no moment found with a worker running a task and holding "
                                              "committed results"}))


@pytest.mark.parametrize("allowed_failures", [None, 0], ids=["rescheduled", "lost-then-rerun"])
def test_a_killed_worker(capture, reference, tmp_path, allowed_failures):
    start = time.perf_counter()
    env = {} if allowed_failures is None else {"DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": str(allowed_failures)}
    config = PRESETS["test"]
    stages = build_stages(config, through=THROUGH)
    # The killer signals a worker it saw running a task; a task that ends between that look and the signal is
    # not lost (its result already left the worker). With allowed_failures 0 that leaves nothing to fail and the
    # scenario did not happen, so it is tried again on a fresh cluster and folders, at most _KILL_ATTEMPTS times.
    for attempt in range(_KILL_ATTEMPTS):
        folder = tmp_path / f"attempt{attempt}"
        folder.mkdir()
        release, work = folder / "release", folder / "work"
        with dask_cluster(folder, 3, env=env) as (address, _pids):
            out = folder / "killed.json"
            killer = subprocess.Popen([sys.executable, "-c", "import sys; from tests.integration.test_faults import "
                                       "_kill_a_busy_worker_holding_committed_results as k; k(*sys.argv[1:])",
                                       address, str(work), str(out)], env=_env(), cwd=ROOT)
            try:
                deadline = time.monotonic() + 60
                while not out.with_suffix(".ready").exists():
                    assert killer.poll() is None and time.monotonic() < deadline, "the killer did not start"
                    time.sleep(0.05)
                result = run_pipeline(capture, release, work, stages, config, ExecutionConfig(scheduler=address),
                                      echo=lambda line: None, view_progress=lambda *a: None)
            finally:
                with contextlib.suppress(ProcessLookupError):
                    killer.kill()
                killer.wait()
            assert out.exists(), "the run ended before a worker could be killed in it"
            killed = json.loads(out.read_text())
            assert "pid" in killed, killed
            n_tasks = len(result.plan.tasks)
            assert killed["committed"] < n_tasks  # killed mid-run
            print(f"\nkilled worker pid {killed['pid']} running {killed['running']} holding {killed['held']}; "
                  f"{killed['committed']}/{n_tasks} tasks committed then")
            if allowed_failures is None:  # dask reschedules: this very run completes
                assert result.action_status == {a: "ok" for a in result.action_status}, result.action_errors
                break
            # the task is lost: its actions fail, named; a rerun completes them
            failed = {a: e for a, e in result.action_errors.items() if result.action_status[a] == "failed"}
            if not failed and result.action_status == {a: "ok" for a in result.action_status}:
                print(f"attempt {attempt + 1}: {killed['running']} ended before the signal; nothing was lost")
                continue
            assert failed and all("KilledWorker" in e for e in failed.values()), result.action_errors
            print(f"first run: {len(failed)} action(s) failed: {next(iter(failed.values()))[:160]}")
            rerun = run_pipeline(capture, release, work, stages, config, ExecutionConfig(scheduler=address),
                                 echo=lambda line: None)
            assert rerun.action_status == {a: "ok" for a in rerun.action_status}, rerun.action_errors
            assert any(t.status == "cached" for t in rerun.plan.tasks) and any(t.status == "ran" for t in rerun.plan.tasks)
            break
    else:
        pytest.fail(f"in {_KILL_ATTEMPTS} runs no killed worker lost a running task (each ended before the signal)")

    from manifests import verify_release

    assert verify_release(release).ok, verify_release(release).summary()
    # config.yaml names the scheduler (the cluster's address here, "local" in the reference): not a stage output
    assert _digests(release, RUN_SPECIFIC + ("config.yaml",)) == _digests(reference, RUN_SPECIFIC + ("config.yaml",))
    assert _leftovers(work / "artifacts") == [] and _leftovers(release) == []
    print(f"test_a_killed_worker[{allowed_failures}]: {time.perf_counter() - start:.1f}s")


# --- the driver killed -----------------------------------------------------------------------------------


def _stage_runs(release: Path, run_id: str) -> dict[tuple[str, str], str]:
    from manifests import open_release

    table = open_release(release).table("stage_runs").to_pylist()
    return {(r["stage"], r["scope_id"]): r["status"] for r in table if r["run_id"] == run_id}


def _metrics(release: Path) -> set[tuple]:
    from manifests import open_release

    rows = open_release(release).table("metrics").to_pylist()
    return {(r["action_id"], r["camera_id"], r["metric"], round(r["value"], 9)) for r in rows}


def test_a_killed_driver_is_rerun_from_its_success_records(capture, reference, tmp_path):
    start = time.perf_counter()
    release = tmp_path / "release"
    work = tmp_path / "release.work"
    log = (tmp_path / "killed.log").open("w")
    proc = subprocess.Popen(_cli_command(capture, release, "--scheduler", "local"), env=_env(), cwd=ROOT,
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 180
        while not list((work / "artifacts" / THROUGH).glob("*/*/_SUCCESS.json")):
            assert proc.poll() is None, "the run ended before any action's photometric stage committed"
            assert time.monotonic() < deadline, "no photometric stage committed in 180 s"
            time.sleep(0.01)
        os.kill(proc.pid, signal.SIGKILL)  # the driver only: its local cluster's workers follow it
        assert proc.wait(timeout=30) == -signal.SIGKILL
        deadline = time.monotonic() + 30
        while subprocess.run(["pgrep", "-s", str(proc.pid)], capture_output=True).returncode == 0:
            assert time.monotonic() < deadline, "the killed driver's worker processes are still running"
            time.sleep(0.2)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        log.close()
    done_before = _committed(work)
    lock = json.loads((work / "run.lock").read_text())
    assert lock["pid"] == proc.pid  # the dead run's lock file is still there
    assert not (release / "manifests").exists()  # killed before it published anything

    rerun = subprocess.run(_cli_command(capture, release, "--scheduler", "local"), env=_env(), cwd=ROOT,
                           capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stdout[-3000:] + rerun.stderr[-3000:]
    assert f"taking over the stale lock of pid {proc.pid} (no longer running)" in rerun.stdout
    run_id = json.loads((release / "run.json").read_text())["run_id"]
    statuses = _stage_runs(release, run_id)
    cached = {k for k, s in statuses.items() if s == "cached"}
    ran = {k for k, s in statuses.items() if s == "ran"}
    assert cached == done_before  # everything the killed run committed, and nothing else, is taken as it is
    assert ran == set(statuses) - done_before and ran
    for stage, scope in sorted(cached):
        assert any(line.split()[:3] == [stage, scope, "cached"] for line in rerun.stdout.splitlines()), (stage, scope)
    share = len(ran) / len(statuses)
    print(f"\nrerun after a driver kill: {len(ran)} task(s) ran, {len(cached)} cached of {len(statuses)}: "
          f"{100 * share:.0f}% redone")

    from manifests import open_release, verify_release

    assert verify_release(release).ok, verify_release(release).summary()
    assert _digests(release) == _digests(reference)
    assert _metrics(release) == _metrics(reference)  # the cached stages' statistics, from their success records
    actions = open_release(release).actions
    assert set(actions.status) == {"ok"} and int(actions.stages_cached.sum()) == len(
        [k for k in cached if k[1].startswith("A")])
    assert _leftovers(work / "artifacts") == [] and _leftovers(release) == []
    print(f"test_a_killed_driver: {time.perf_counter() - start:.1f}s")


# --- a full disk, an unwritable release folder ----------------------------------------------------------

OVERRIDE = "{photometric: {params: {ratio_min: 0.35}}}\n"
"""A config change that reruns photometric: every action is published anew."""


@contextlib.contextmanager
def _mounted(folder: Path, *mount_args: str):
    """``mount *mount_args folder``, unmounted again at the end; skips the test when this user cannot mount."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs or a read-only bind mount needs root")
    folder.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["mount", *mount_args, str(folder)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount here ({' '.join(mount_args)}): {done.stderr.strip()}")
    try:
        yield folder
    finally:
        if subprocess.run(["umount", str(folder)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def _cli(capsys, capture: Path, release: Path, work: Path, *extra: str) -> tuple[int, str, str]:
    from ultrastage.cli import main as cli

    capsys.readouterr()
    code = cli(["run", "--capture", str(capture), "--release", str(release), "--work", str(work), "--preset", "test",
                "--through", THROUGH, "--no-evaluate", "--scheduler", "sync", *extra])
    out = capsys.readouterr()
    return code, out.out, out.err


def _files(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (hidden ones too) -> sha256 of its bytes."""
    import hashlib

    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _free_bytes(folder: Path) -> int:
    st = os.statvfs(folder)
    return st.f_bavail * st.f_frsize


def _leave_free(disk: Path, free: int) -> Path:
    """Fill the file system of ``disk`` with a file ``disk/filler`` so that about ``free`` bytes are left."""
    filler = disk / "filler"
    with open(filler, "wb") as fh:
        fh.write(b"\0" * max(0, _free_bytes(disk) - free))
    return filler


def _pages(folder: Path) -> int:
    """Bytes the files under ``folder`` take on a tmpfs (whole 4 KiB pages)."""
    return sum(-(-p.stat().st_size // 4096) * 4096 for p in folder.rglob("*") if p.is_file())


@pytest.fixture(scope="module")
def reference_changed(tiny_capture: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The release an uninterrupted run with OVERRIDE writes (sync, in this process)."""
    from ultrastage.cli import main as cli

    out = tmp_path_factory.mktemp("reference_changed")
    (out / "o.yaml").write_text(OVERRIDE)
    code = cli(["run", "--capture", str(tiny_capture), "--release", str(out / "release"), "--work", str(out / "work"),
                "--preset", "test", "--through", THROUGH, "--no-evaluate", "--scheduler", "sync",
                "--config", str(out / "o.yaml")])
    assert code == 0
    return out / "release"


STEPS = ("staging the action files beside the release", "swapping the actions in", "writing the documents",
         "writing the manifests", "writing the release page")
"""The steps of a publication (``pipeline.runner``'s error names the one that failed); all but the swap (renames,
after the transaction's journal is written) write files' bytes."""


def _publication_error(err: str, release: Path) -> str:
    """The step a run that ran out of space in ``release`` names; fails unless the error names the release folder
    and ENOSPC."""
    found = re.search(rf"{re.escape(str(release))}: No space left on device \(ENOSPC\) while publishing the "
                      rf"release \((.*?)\); it is left as it was before this run", err)
    assert found, err
    return found.group(1)


def test_a_full_disk_under_a_new_release(tiny_capture, reference_changed, tmp_path, capsys):
    """The first run into a release on a tmpfs too small for it (mounted at the release's parent, a filler file
    leaving half the space the action files need): exit 4, an error naming the release folder and ENOSPC, and
    nothing at all in the release folder; with the filler gone the same run publishes the uninterrupted release."""
    start = time.perf_counter()
    (tmp_path / "o.yaml").write_text(OVERRIDE)
    changed = ("--config", str(tmp_path / "o.yaml"))
    with _mounted(tmp_path / "disk", "-t", "tmpfs", "-o", "size=2m", "tmpfs") as disk:
        release = disk / "release"
        filler = _leave_free(disk, _pages(reference_changed / "actions") // 2)
        code, out, err = _cli(capsys, tiny_capture, release, tmp_path / "work", *changed)
        assert code == 4, out[-2000:] + err
        assert _publication_error(err, release) == STEPS[0]
        assert list(release.rglob("*")) == []  # no file, no folder
        failure = err.strip()
        filler.unlink()
        code, out, err = _cli(capsys, tiny_capture, release, tmp_path / "work", *changed)
        assert code == 0, err
        assert "executing" not in out  # the stages' results were committed before the disk ran full: cached
        from manifests import verify_release

        assert verify_release(release).ok and _digests(release) == _digests(reference_changed)
        assert _leftovers(release) == []
    with capsys.disabled():
        print(f"\n[new release] {failure}; {time.perf_counter() - start:.1f}s")


def test_a_full_disk_under_a_published_release(tiny_capture, reference_changed, tmp_path, capsys):
    """A published release on a tmpfs (mounted at its parent), and a run that republishes every action (a changed
    photometric config) with less and less space taken away by a filler file, so that the disk runs full at every
    step of the publication in turn: staging the action files, the documents, the manifests, the page. Each time:
    exit 4, an error naming the release folder, ENOSPC and the step, and the release is byte for byte the one
    before (every file, hidden ones too; it verifies against its manifests). The first run with room enough
    publishes the uninterrupted run's release."""
    from manifests import verify_release

    start = time.perf_counter()
    work = tmp_path / "work"
    (tmp_path / "o.yaml").write_text(OVERRIDE)
    changed = ("--config", str(tmp_path / "o.yaml"))
    with _mounted(tmp_path / "disk", "-t", "tmpfs", "-o", "size=4m", "tmpfs") as disk:
        release = disk / "release"
        code, out, err = _cli(capsys, tiny_capture, release, work)
        assert code == 0, err
        before = _files(release)
        need = _pages(reference_changed / "actions")  # the new action folders, staged in full
        steps = []
        for free in [need // 2] + [need + k * 12 * 1024 for k in range(40)]:
            filler = _leave_free(disk, free)
            code, out, err = _cli(capsys, tiny_capture, release, work, *changed)
            filler.unlink()
            if code == 0:
                break
            assert code == 4, out[-2000:] + err
            steps.append(_publication_error(err, release))
            assert _files(release) == before, steps[-1]  # as it was, byte for byte
            assert verify_release(release).ok, verify_release(release).summary()
        assert code == 0, "no run succeeded with 480 KiB more than the action files"
        assert set(STEPS) - {STEPS[1]} <= set(steps) <= set(STEPS), steps  # it ran full at every step
        assert verify_release(release).ok, verify_release(release).summary()
        assert _digests(release) == _digests(reference_changed)
        assert _leftovers(release) == []
    with capsys.disabled():
        print(f"\n[published release] ran full {len(steps)} times: " +
              ", ".join(f"{s} x{steps.count(s)}" for s in STEPS) + f"; {time.perf_counter() - start:.1f}s")


def test_a_full_disk_under_the_work_folder(tiny_capture, reference_changed, tmp_path, capsys):
    """The work folder (the artifact store) on a tmpfs with 64 KiB free: the stages that write there fail, each
    action is recorded failed with the file in the work folder and 'No space left on device' (exit 3), nothing of
    it is in the release and the store holds no half-written result; with the space back, the rerun retries them
    and publishes the uninterrupted release."""
    from manifests import open_release, verify_release

    start = time.perf_counter()
    (tmp_path / "o.yaml").write_text(OVERRIDE)
    changed = ("--config", str(tmp_path / "o.yaml"))
    release = tmp_path / "release"
    with _mounted(tmp_path / "disk", "-t", "tmpfs", "-o", "size=2m", "tmpfs") as disk:
        work = disk / "work"
        filler = _leave_free(disk, 64 * 1024)
        code, out, err = _cli(capsys, tiny_capture, release, work, *changed)
        assert code == 3, out[-3000:] + err
        actions = open_release(release).actions
        assert set(actions.status) == {"failed"}
        for error in actions.error:
            assert "No space left on device" in error and "<work>/artifacts/" in error, error
        assert verify_release(release).ok
        assert not (release / "actions").exists() or not any((release / "actions").iterdir())
        assert _leftovers(work / "artifacts") == []  # the failed tasks' folders were discarded
        assert not [p for p in (work / "artifacts").glob("*/*/*") if p.is_dir() and not (p / "_SUCCESS.json").exists()]
        failure = actions.error.iloc[0]
        filler.unlink()
        code, out, err = _cli(capsys, tiny_capture, release, work, *changed)
        assert code == 0, out[-3000:] + err
        assert "will retry" in out
        assert verify_release(release).ok and _digests(release) == _digests(reference_changed)
    with capsys.disabled():
        print(f"\n[work folder] first run: {failure}; {time.perf_counter() - start:.1f}s")


@pytest.mark.parametrize("how", ["read-only", "parent-is-a-file"])
def test_an_unwritable_release_folder(tiny_capture, tmp_path, capsys, how):
    """A published release on a file system turned read-only (a read-only bind mount), or a release path under a
    regular file: the run stops before any work with exit 4 and an error naming the path and the reason."""
    start = time.perf_counter()
    work = tmp_path / "work"
    (tmp_path / "o.yaml").write_text(OVERRIDE)
    changed = ("--config", str(tmp_path / "o.yaml"))
    if how == "parent-is-a-file":
        (tmp_path / "afile").write_text("not a folder")
        release = tmp_path / "afile" / "release"
        code, out, err = _cli(capsys, tiny_capture, release, work, *changed)
        assert code == 4, out[-2000:] + err
        assert f"{release}: cannot create the release folder: {tmp_path / 'afile'} is a file, not a folder" in err
        assert not (work / "artifacts").exists()  # refused before any work
    else:
        source = tmp_path / "source"
        code, out, err = _cli(capsys, tiny_capture, source / "release", work)
        assert code == 0, err
        before, store = _files(source / "release"), _files(work / "artifacts")
        with _mounted(tmp_path / "ro", "--bind", str(source)) as ro:
            if subprocess.run(["mount", "-o", "remount,ro,bind", str(ro)], capture_output=True).returncode != 0:
                pytest.skip("cannot remount the bind mount read-only here")
            release = ro / "release"
            code, out, err = _cli(capsys, tiny_capture, release, work, *changed)
            assert code == 4, out[-2000:] + err
            assert f"{release}: Read-only file system (EROFS) while checking that the release folder can be written" in err
            assert _files(release) == before and _files(work / "artifacts") == store  # nothing done
            assert "executing" not in out
    with capsys.disabled():
        print(f"\n[{how}] {err.strip()}\ntest_an_unwritable_release_folder[{how}]: {time.perf_counter() - start:.1f}s")
