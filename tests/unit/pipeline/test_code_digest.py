"""Code identity in cache keys: a stage's key follows the code of its module and of the project modules it imports."""
from __future__ import annotations

import importlib
import sys
import textwrap
from pathlib import Path

import pytest

from pipeline.hashing import clear_code_cache, code_digest, code_digests
from pipeline.runner import ExecutionConfig
from ultrastage.run import run_pipeline
from tests.unit.pipeline.conftest import ToyConfig

PACKAGE = "ustest_codepkg"

FILES = {
    "__init__.py": '"""A fake project package."""\n',
    "stage_mod.py": '''
        """A stage module: imports numerics at the top, a helper inside a function, and an uncounted package."""
        from pathlib import Path

        from pipeline.stage import Stage
        from ustest_codepkg.numerics import solve
        import ustest_otherpkg.thing


        class FitStage(Stage):
            name = "fit"
            scope = "session"
            outputs = ("fit.txt",)

            def run(self, ctx):
                from .helpers import scale

                (ctx.out_dir / "fit.txt").write_text(str(scale(solve(2.0))))
                return {"value": solve(2.0)}
        ''',
    "numerics.py": '''
        """Numerics of the fake stage."""


        def solve(x):
            """Twice x."""
            return 2.0 * x  # the model
        ''',
    "helpers.py": "def scale(x):\n    return x * 10\n",
    "unused.py": "VALUE = 1\n",
}


@pytest.fixture
def code_tree(tmp_path, monkeypatch):
    """A package ``ustest_codepkg`` (and an uncounted ``ustest_otherpkg``) on sys.path, digests uncached."""
    root = tmp_path / "src"
    for name, text in FILES.items():
        path = root / PACKAGE / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text).lstrip())
    (root / "ustest_otherpkg").mkdir()
    (root / "ustest_otherpkg" / "__init__.py").write_text("")
    (root / "ustest_otherpkg" / "thing.py").write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(root))
    clear_code_cache()
    yield root / PACKAGE
    clear_code_cache()
    for module in [m for m in sys.modules if m.startswith((PACKAGE, "ustest_otherpkg"))]:
        del sys.modules[module]


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, f"{path}: {old!r} not found"
    path.write_text(text.replace(old, new))
    clear_code_cache()  # a new process would see the new file; this one caches digests


def test_digests_cover_the_module_and_its_counted_imports_transitively(code_tree):
    digests = code_digests(f"{PACKAGE}.stage_mod", [PACKAGE])
    assert set(digests) == {PACKAGE, f"{PACKAGE}.stage_mod", f"{PACKAGE}.numerics", f"{PACKAGE}.helpers"}
    with_other = code_digests(f"{PACKAGE}.stage_mod", [PACKAGE, "ustest_otherpkg"])
    assert {"ustest_otherpkg", "ustest_otherpkg.thing"} <= set(with_other)
    with pytest.raises(ValueError, match="no Python source file"):
        code_digests(f"{PACKAGE}.missing", [PACKAGE])
    with pytest.raises(ValueError, match="dotted module names"):
        importlib.import_module(f"{PACKAGE}.stage_mod").FitStage(ToyConfig(), code_packages=["stages/numerics"])


def test_a_numerics_edit_changes_the_digest_and_comments_or_docstrings_do_not(code_tree):
    module = f"{PACKAGE}.stage_mod"
    before, before_all = code_digest(module, [PACKAGE]), code_digests(module, [PACKAGE])
    # comments, docstrings and blank lines are not code
    _edit(code_tree / "numerics.py", "# the model", "# the model, per the paper")
    _edit(code_tree / "numerics.py", '"""Twice x."""', '"""Two times x."""\n\n')
    assert code_digest(module, [PACKAGE]) == before
    # nor are modules it does not import, or packages that do not count
    _edit(code_tree / "unused.py", "VALUE = 1", "VALUE = 2")
    _edit(code_tree.parent / "ustest_otherpkg" / "thing.py", "X = 1", "X = 2")
    assert code_digest(module, [PACKAGE]) == before
    # a changed constant in a numerics function is
    _edit(code_tree / "numerics.py", "2.0 * x", "3.0 * x")
    after = code_digests(module, [PACKAGE])
    assert code_digest(module, [PACKAGE]) != before
    assert [m for m in after if after[m] != before_all[m]] == [f"{PACKAGE}.numerics"]
    # and so is one in a helper imported (relatively) inside a function
    _edit(code_tree / "helpers.py", "x * 10", "x * 11")
    assert code_digests(module, [PACKAGE])[f"{PACKAGE}.helpers"] != after[f"{PACKAGE}.helpers"]


def test_a_numerics_edit_reruns_the_stage_and_says_why(code_tree, tmp_path):
    from tests.unit.pipeline.conftest import make_toy_capture

    capture = make_toy_capture(tmp_path / "capture", actions=("A0000",))
    stage_cls = importlib.import_module(f"{PACKAGE}.stage_mod").FitStage

    def run():
        lines: list[str] = []
        stage = stage_cls(ToyConfig(), code_packages=[PACKAGE])
        result = run_pipeline(capture, tmp_path / "release", tmp_path / "work", [stage], {"toy": 1},
                              ExecutionConfig(scheduler="sync"), echo=lines.append)
        task = next(t for t in result.plan.tasks if t.stage.name == "fit")
        return task, [line for line in lines if line.startswith("fit ")]

    first, _ = run()
    assert first.status == "ran" and set(first.record["code"]) >= {f"{PACKAGE}.stage_mod", f"{PACKAGE}.numerics"}
    assert run()[0].status == "cached"
    _edit(code_tree / "numerics.py", '"""Twice x."""', '"""Twice x, documented again."""')
    assert run()[0].status == "cached"
    _edit(code_tree / "numerics.py", "2.0 * x", "3.0 * x")
    rerun, lines = run()
    assert rerun.status == "ran" and rerun.key != first.key
    assert any(f"code of {PACKAGE}.numerics changed" in line for line in lines), lines
    assert rerun.record["version"] == first.record["version"]  # no hand-bumped version was needed


def test_why_names_the_changed_code_and_an_earlier_key_without_code():
    from pipeline.graph import _why

    record = {"version": "1", "code": {"pkg.a": "1", "pkg.b": "2"}, "config": {}, "upstream": {}, "inputs": {}}
    earlier = {"record": dict(record, code={"pkg.a": "1", "pkg.b": "old"})}
    assert _why(record, earlier) == "code of pkg.b changed"
    before_code_keys = {"record": {k: v for k, v in record.items() if k != "code"}}
    assert _why(record, before_code_keys) == "the earlier key had no code digest"
    assert _why(record, {"record": record}) == "result missing from store"
