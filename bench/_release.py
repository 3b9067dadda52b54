"""Command line, input checks and the run's store, shared by the benches that measure an existing release (`make
dataset`)."""
from __future__ import annotations

import argparse
from pathlib import Path

from _quick import QUICK_HELP, quick_run

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_RUN = ROOT / "runs" / "default"


def release_parser(description: str | None, actions: str | None = None, threads: int | None = None) -> argparse.ArgumentParser:
    """A parser with ``--out``, ``--release``, ``--capture`` (defaults: bench/out and runs/default) and ``--quick``
    (the release and capture of :func:`_quick.quick_run` unless given); with ``actions`` also ``--actions`` (that
    default; "" = every action), with ``threads`` also ``--threads``. Parse with :func:`parse_release_args`."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--release", help=f"default {DEFAULT_RUN / 'release'}; with --quick the tiny run's")
    parser.add_argument("--capture", help=f"default {DEFAULT_RUN / 'capture'}; with --quick the tiny run's")
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    if actions is not None:
        parser.add_argument("--actions", default=actions, help="comma-separated action ids (empty: every action)")
    if threads is not None:
        parser.add_argument("--threads", type=int, default=threads, help="torch and Embree threads")
    return parser


def parse_release_args(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> argparse.Namespace:
    """``parser.parse_args`` with ``release`` and ``capture`` filled in: runs/default's, or with ``--quick`` (and
    neither given) the tiny run's under ``--out``, made on first use."""
    args = parser.parse_args(argv)
    if args.quick and args.release is None and args.capture is None:
        run = quick_run(Path(args.out))
        args.release, args.capture = str(run / "release"), str(run / "capture")
    args.release = args.release or str(DEFAULT_RUN / "release")
    args.capture = args.capture or str(DEFAULT_RUN / "capture")
    return args


def release_config(release: Path, section: str, cls):
    """The release's config of one stage: ``section`` of its ``config.yaml`` read as ``cls`` (a stage config
    dataclass; the defaults where the section is absent or empty). Errors name the file and the section."""
    import yaml

    from pipeline.config import from_dict

    path = Path(release) / "config.yaml"
    record = (yaml.safe_load(path.read_text()) or {}).get(section) or {}
    return from_dict(cls, record, where=f"{path}: {section}")


def check_inputs(name: str, release: Path, capture: Path, need_truth: bool) -> tuple[bool, Path | None]:
    """``(go on, ground-truth folder or None)``. Without a release, or without a simulated capture with ground
    truth when ``need_truth``, prints why the bench ``name`` is skipped and returns ``(False, None)``; a
    missing ground truth that is not needed is said once and gives ``(True, None)``."""
    if not (Path(release) / "manifests").is_dir():
        print(f"{name}: no release at {release} (run `make dataset`); skipped")
        return False, None
    truth = Path(capture) / "ground_truth"
    if (Path(capture) / "capture.json").exists() and truth.is_dir():
        return True, truth
    if need_truth:
        print(f"{name}: no simulated capture with ground truth at {capture}: nothing to measure against; skipped")
        return False, None
    print(f"{name}: no ground truth under {capture}: truth metrics skipped")
    return True, None


def latest_artifact(work: Path, stage: str, scope: str) -> Path:
    """The newest committed artifact folder of ``stage`` for ``scope`` (an action or a session id) in the run's store
    ``work`` (``<release>.work``)."""
    from pipeline.store import ArtifactStore

    path = ArtifactStore(work / "artifacts").latest_dir(stage, scope)
    if path is None:
        raise FileNotFoundError(f"no committed {stage} artifact for {scope} under {work}")
    return path


def store_artifacts(release: Path, action: str, action_stages: tuple[str, ...], session_stages: tuple[str, ...] = ()):
    """An :class:`artifacts.facade.ActionArtifacts` over the newest store entries (``<release>.work``) of
    ``action_stages`` for ``action`` and of ``session_stages`` for the action's session (from the release's actions
    manifest)."""
    from artifacts.facade import ActionArtifacts
    from manifests import open_release

    work = release.with_name(release.name + ".work")
    upstream = {stage: latest_artifact(work, stage, action) for stage in action_stages}
    if session_stages:
        session = open_release(release).action(action).info.get("session_id")
        if session is None:
            raise ValueError(f"{action} is not in {release}'s actions manifest")
        upstream |= {stage: latest_artifact(work, stage, session) for stage in session_stages}
    return ActionArtifacts(upstream)
