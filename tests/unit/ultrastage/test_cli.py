"""The command line: --version, help for every argument, the stage names in --only/--from, a summary that
fits 100 columns."""
from __future__ import annotations

import argparse
import io
from types import SimpleNamespace

import pytest

from ultrastage.cli import SUMMARY_WIDTH, build_parser, summary_table
from stages.registry import STAGE_CLASSES


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args(["--version"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out.strip()
    assert out.startswith("ultrastage ") and len(out.split()) >= 2


def test_every_argument_of_every_subcommand_has_help():
    parser = build_parser()
    undocumented = []
    for name, sub in [("ultrastage", parser)] + sorted(_subparsers(parser).items()):
        for action in sub._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            if not action.help or action.help == argparse.SUPPRESS:
                undocumented.append(f"{name} {action.option_strings or action.dest}")
    assert not undocumented, undocumented
    assert "would write" in _subparsers(parser)["plan"].format_help()  # plan writes nothing


@pytest.mark.parametrize("command", ["run", "plan", "rerun"])
def test_only_and_from_list_the_stages_and_reject_others(command, capsys):
    sub = _subparsers(build_parser())[command]
    text = " ".join(sub.format_help().split())
    for cls in STAGE_CLASSES:
        assert cls.name in text
    args = ["REL"] if command == "rerun" else ["--capture", "C", "--release", "R"]
    with pytest.raises(SystemExit):
        sub.parse_args(args + ["--only", "nosuchstage"])
    assert "invalid choice" in capsys.readouterr().err
    assert sub.parse_args(args + ["--from", STAGE_CLASSES[-1].name]).from_stage == STAGE_CLASSES[-1].name


def test_the_parser_lists_the_stages_without_importing_them():
    """Every command's parser offers the stage names, yet building it imports no stage (torch, open3d): a command
    that needs none starts without them."""
    import subprocess
    import sys

    code = ("import sys; from ultrastage.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('torch', 'open3d', 'stages.registry') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
    assert [cls.name for cls in STAGE_CLASSES] == list(_subparsers(build_parser())["run"]._option_string_actions[
        "--only"].choices)


def test_summary_fits_100_columns_and_names_what_failed():
    from rich.console import Console

    def task(stage, scope, status, seconds=12.5, failed_stage=None):
        return SimpleNamespace(stage=SimpleNamespace(name=stage), scope_id=scope, status=status, seconds=seconds,
                               failed_stage=failed_stage)

    names = [cls.name for cls in STAGE_CLASSES]
    session = [task(n, "S000", "cached") for n in names[:4]]
    ok = [task(n, "A0000", "ran", 431.0) for n in names[4:]]
    bad = [task(names[4], "A0001", "failed")] + [task(n, "A0001", "skipped", 0.0, names[4]) for n in names[5:]]
    result = SimpleNamespace(run_id="20261203T080000-abcdef", published=["A0000"],
                             action_status={"A0000": "ok", "A0001": "failed"}, seconds=1234.5,
                             executor="local dask cluster, 2 worker process(es)",
                             plan=SimpleNamespace(tasks=session + ok + bad))
    metrics = {"A0000": {"normal_mean_deg": 4.77, "normal_under5_pct": 71.23, "valid_fraction": 0.93,
                         "albedo_psnr_db": 31.52, "chamfer_mm": 2.61, "roughness_mae": 0.081, "relit_psnr_db": 29.97}}
    out = io.StringIO()
    Console(file=out, width=SUMMARY_WIDTH, color_system=None).print(summary_table(result, metrics))
    lines = out.getvalue().splitlines()
    assert max(len(line) for line in lines) <= 100
    text = out.getvalue()
    assert "…" not in text  # nothing cut short to fit
    assert f"FAILED {names[4]}" in text and f"{len(names) - 4} ran" in text and "4 cached" in text
    for value in ("4.77", "71.23", "31.52", "2.61", "29.97"):
        assert value in text


def test_truth_prefetch_traces_the_visibility_beside_the_run(tmp_path):
    from evaluation.release import RELIT_CACHE, truth_visibility_folder
    from ultrastage.cli import _start_truth_prefetch, _stop
    from synthetic import SimConfig, simulate

    capture = simulate(tmp_path / "capture", SimConfig(actions=1, width=48, n_cameras=2, n_leds=64,
                                                       mesh="procedural", noise=False, background=False))
    work = tmp_path / "work"
    relit, geometry = SimpleNamespace(name="relight"), SimpleNamespace(name="geometry")
    assert _start_truth_prefetch(capture, work, [geometry]) is None  # nothing would use it
    process = _start_truth_prefetch(capture, work, [geometry, relit])
    assert process is not None
    assert process.wait(timeout=300) == 0
    import os

    assert os.getpriority(os.PRIO_PROCESS, os.getpid()) < 19  # the low priority is the child's alone
    assert len(list(truth_visibility_folder(work / RELIT_CACHE).glob("*.npy"))) == 1  # one action
    _stop(process)  # a finished process: nothing to do
    running = _start_truth_prefetch(capture, tmp_path / "other", [relit])
    import time

    niceness = None
    for _ in range(200):  # the child lowers its own priority first thing, before its imports
        niceness = os.getpriority(os.PRIO_PROCESS, running.pid)
        if niceness == 19 or running.poll() is not None:
            break
        time.sleep(0.01)
    assert niceness == 19
    _stop(running)  # stopped mid-way: nothing half-written is left, nor the claim of a trace it was in
    assert running.poll() is not None
    assert not list((tmp_path / "other").rglob("*.claim"))
    assert not list((tmp_path / "other").rglob("*.tmp"))


def test_evaluate_reads_the_truth_renders_of_the_work_folder(tmp_path, monkeypatch, capsys):
    """``evaluate`` passes <release>.work/cache/relit_truth as the cache of the simulator's renders when that work
    folder is there, the ``--work`` folder's whenever one is named (created on the first render), none for a
    release alone (e.g. downloaded): it writes nothing beside a release that has no work folder."""
    import evaluation.release
    from evaluation.release import RELIT_CACHE, EvaluationSummary
    from ultrastage.cli import main

    caches = []

    def fake_evaluate(release, truth_dir, run_id=None, relit_cache=None):
        caches.append(relit_cache)
        return EvaluationSummary({"actions_ok": 1}, {})

    monkeypatch.setattr(evaluation.release, "evaluate_release", fake_evaluate)
    monkeypatch.setattr(evaluation.release, "print_overall", lambda summary: None)
    release, truth = tmp_path / "release", tmp_path / "truth"
    release.mkdir()
    assert main(["evaluate", "--release", str(release), "--truth", str(truth)]) == 0
    (tmp_path / "release.work").mkdir()
    assert main(["evaluate", "--release", str(release), "--truth", str(truth)]) == 0
    assert main(["evaluate", "--release", str(release), "--truth", str(truth), "--work", str(tmp_path / "w")]) == 0
    assert caches == [None, tmp_path / "release.work" / RELIT_CACHE, tmp_path / "w" / RELIT_CACHE]
