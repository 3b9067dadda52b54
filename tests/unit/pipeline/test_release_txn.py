"""pipeline.release_txn: a publication is undone whole, by rollback or, after a SIGKILL, by the next run's recover."""
from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.release_txn import ReleaseTransaction, recover

ROOT = Path(__file__).resolve().parents[3]


def _state(folder: Path) -> dict[str, str]:
    """Every file and folder under ``folder`` (hidden ones too): sha256 of a file's bytes, 'dir' for a folder."""
    return {p.relative_to(folder).as_posix(): "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*"))}


def _release(root: Path) -> Path:
    release = root / "release"
    for rel, text in {"actions/A0000/full_on/00000.exr": "A old", "actions/A0002/mask/00000.png": "C",
                      "manifests/assets.parquet": "assets old", "manifests/index.json": "{}",
                      "index.html": "page old", "page/A0000/full_on_00000.png": "thumb old",
                      "relight/A0000_00/image.exr": "example old"}.items():
        (release / rel).parent.mkdir(parents=True, exist_ok=True)
        (release / rel).write_text(text)
    return release


def _replace(path: Path, text: str) -> None:
    """As the release's writers do: a new file renamed over the old one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _stage(release: Path, name: str, files: dict[str, str]) -> Path:
    tmp = release / "actions" / f".tmp-{name}"
    for rel, text in files.items():
        (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp / rel).write_text(text)
    return tmp


def _publish(release: Path, txn: ReleaseTransaction) -> None:
    """Every kind of change a run makes: an action replaced, one added, one removed, a root folder replaced,
    manifests and page rewritten (one file new, one deleted), a half-written temporary file at the root."""
    txn.keep_root_listing()
    for name in ("manifests", "page", "index.html", "relight/splits"):
        txn.keep_files(release / name)
    txn.put_dir(_stage(release, "A0000", {"full_on/00000.exr": "A new"}), release / "actions" / "A0000")
    txn.put_dir(_stage(release, "A0001", {"full_on/00000.exr": "B new"}), release / "actions" / "A0001")
    txn.remove_dir(release / "actions" / "A0002")
    staging = release / ".tmp-root-A0000" / "relight" / "A0000_00"
    staging.mkdir(parents=True)
    (staging / "image.exr").write_text("example new")
    txn.put_dir(staging, release / "relight" / "A0000_00")
    staging.parent.rmdir()
    staging.parent.parent.rmdir()  # the staging folder, emptied by the swap (as runner.swap_in removes it)
    _replace(release / "manifests" / "assets.parquet", "assets new")
    _replace(release / "manifests" / "actions.parquet", "actions new")
    _replace(release / "index.html", "page new")
    (release / "page" / "A0000" / "full_on_00000.png").unlink()
    _replace(release / "page" / "A0001" / "full_on_00000.png", "thumb new")
    _replace(release / "relight" / "splits" / "train.txt", "A0000_00\n")
    (release / ".DATASHEET.md.123.tmp").write_text("half")


def test_rollback_restores_the_release_byte_for_byte(tmp_path):
    release = _release(tmp_path)
    before = _state(release)
    txn = ReleaseTransaction(release)
    _publish(release, txn)
    assert _state(release) != before
    txn.rollback()
    assert _state(release) == before


def test_commit_keeps_the_new_release_and_deletes_what_it_replaced(tmp_path):
    release = _release(tmp_path)
    txn = ReleaseTransaction(release)
    _publish(release, txn)
    txn.commit()
    state = _state(release)
    assert not [p for p in state if p.startswith(".txn-")]
    assert (release / "actions" / "A0000" / "full_on" / "00000.exr").read_text() == "A new"
    assert not (release / "actions" / "A0002").exists() and (release / "index.html").read_text() == "page new"


def test_a_failure_between_the_two_renames_of_a_swap_is_rolled_back(tmp_path, monkeypatch):
    release = _release(tmp_path)
    before = _state(release)
    txn = ReleaseTransaction(release)
    tmp = _stage(release, "A0000", {"full_on/00000.exr": "A new"})
    real_rename = os.rename

    def rename(src, dst):
        if Path(src) == tmp:
            raise OSError(28, "No space left on device")
        real_rename(src, dst)

    monkeypatch.setattr(os, "rename", rename)
    with pytest.raises(OSError):
        txn.put_dir(tmp, release / "actions" / "A0000")
    monkeypatch.undo()
    assert not (release / "actions" / "A0000").exists()  # moved aside, the new one not yet in
    txn.rollback()
    import shutil

    shutil.rmtree(tmp)
    assert _state(release) == before


@pytest.mark.parametrize("committed", [False, True], ids=["killed-mid-publication", "killed-after-commit-began"])
def test_recover_after_a_sigkill(tmp_path, committed):
    """A process SIGKILLs itself in the middle of a publication (or after the journal was marked committed,
    before the transaction folder was deleted); the next run's recover rolls it back (or finishes it)."""
    release = _release(tmp_path)
    before = _state(release)
    script = (
        "import os, signal, sys; from pathlib import Path\n"
        "from tests.unit.pipeline.test_release_txn import _publish\n"
        "from pipeline.release_txn import ReleaseTransaction, JOURNAL, COMMITTED\n"
        "release = Path(sys.argv[1]); txn = ReleaseTransaction(release); _publish(release, txn)\n"
        "if sys.argv[2] == '1': txn._close(); os.rename(txn.folder / JOURNAL, txn.folder / COMMITTED)\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n")
    done = subprocess.run([sys.executable, "-c", script, str(release), str(int(committed))], cwd=ROOT,
                          env=os.environ | {"PYTHONPATH": str(ROOT)})
    assert done.returncode == -signal.SIGKILL
    assert [p.name for p in release.glob(".txn-*")]  # left behind
    lines = recover(release, echo=lambda line: None)
    after = _state(release)
    assert not [p for p in after if p.startswith((".txn-", ".tmp-root-")) or "/.tmp-" in p]
    if committed:
        assert any("finished deleting a committed publication" in line for line in lines)
        assert (release / "index.html").read_text() == "page new" and not (release / "actions" / "A0002").exists()
    else:
        assert any("rolled back the unfinished publication" in line for line in lines)
        assert after == before
