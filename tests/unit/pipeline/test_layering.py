"""The packages import downwards only, along the arrows of :data:`ALLOWED`, and their graph has no circle.

Every import of every module of the project's packages counts: at module level, inside functions and under
``if TYPE_CHECKING`` (a type-only import still ties two packages together for a reader). ``bench/`` and
``tests/`` may import anything. Inside ``stages``, a stage module imports no other stage module (it reads what
another stage made through the artifact facade: importing it would put that stage's code in this stage's cache
key), and the two neural fields share their helpers through ``stages.numerics.neural_fields`` by public names.
"""
from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]

ALLOWED: dict[str, set[str]] = {
    "pipeline": set(),
    "calibration": {"pipeline"},
    "artifacts": {"pipeline", "calibration"},
    "synthetic": {"pipeline", "calibration"},
    "manifests": {"pipeline", "artifacts"},
    "stages.numerics": {"pipeline", "artifacts", "calibration"},
    "stages": {"pipeline", "artifacts", "calibration", "stages.numerics"},
    "evaluation": {"pipeline", "artifacts", "calibration", "synthetic", "manifests", "stages.numerics", "stages"},
    "ultrastage": {"pipeline", "artifacts", "calibration", "synthetic", "manifests", "stages.numerics", "stages",
                   "evaluation"},
}
"""Package -> the packages its modules may import (besides its own). ``pipeline`` is the engine and knows nothing of
3D; ``calibration`` is numerics with no I/O; ``artifacts`` is the facade (where products lie, their readers, the
Camera and Atlas types) below both ``stages`` and ``manifests``; ``stages.numerics`` are pure functions below
the stage modules; ``evaluation`` measures a release against the simulator's truth; ``ultrastage`` (the command
line, the run wiring, the baselines) is the one package that may import every other."""

FREE = ("bench", "tests")
"""Folders whose code may import any package (they are not packages of the distribution)."""


def package_of(module: str) -> str | None:
    """The package of :data:`ALLOWED` a dotted module name belongs to (the longest that prefixes it), or None for
    a module outside the project (``numpy``, ``os``)."""
    found = [p for p in ALLOWED if module == p or module.startswith(p + ".")]
    return max(found, key=len) if found else None


def imports(path: Path, module: str) -> list[tuple[int, str]]:
    """(line, dotted module) of every import in the file: ``ast.walk`` sees module level, function bodies and ``if
    TYPE_CHECKING`` blocks alike; relative imports are resolved against ``module``, the file's own dotted name
    (``from . import x`` in ``a/b/c.py`` gives ``a.b.x``; in ``a/b/__init__.py`` it gives ``a.b.x``)."""
    is_package = path.name == "__init__.py"
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                base = node.module or ""
            else:
                parts = module.split(".") if is_package else module.split(".")[:-1]
                parts = parts[:len(parts) - (node.level - 1)]
                base = ".".join(parts + ([node.module] if node.module else []))
            found.append((node.lineno, base))
            found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names if alias.name != "*"]
    return found


def project_modules(root: Path) -> list[tuple[Path, str]]:
    """(file, dotted module name) of every Python file of the packages of :data:`ALLOWED` under ``root``."""
    tops = sorted({p.split(".")[0] for p in ALLOWED})
    modules = []
    for top in tops:
        for path in sorted((root / top).rglob("*.py")):
            modules.append((path, ".".join(path.relative_to(root).with_suffix("").parts).removesuffix(".__init__")))
    return modules


def package_arrows(root: Path = ROOT) -> dict[tuple[str, str], list[str]]:
    """(importing package, imported package) -> the ``file:line`` of each import that draws the arrow, over the
    project's packages under ``root``."""
    arrows: dict[tuple[str, str], list[str]] = {}
    for path, module in project_modules(root):
        source = package_of(module)
        for line, name in imports(path, module):
            target = package_of(name)
            if target is not None and target != source:
                arrows.setdefault((source, target), []).append(f"{path.relative_to(root)}:{line} imports {name}")
    return arrows


def circle(edges: dict[str, set[str]]) -> list[str]:
    """One circle of the directed graph ``edges`` (node -> the nodes it points at) as its nodes in order, the first
    repeated at the end; [] when there is none (depth-first search, three colours)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        path.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        path.pop()
        state[node] = 2
        return []

    for node in sorted(edges):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return []


# ------------------------------------------------------------------------------------------- the arrows

def test_every_top_level_package_has_a_place_in_the_layers():
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")}
    assert {"pipeline", "artifacts", "stages", "manifests", "ultrastage"} <= packages  # the scan sees the tree
    assert packages - {p.split(".")[0] for p in ALLOWED} - set(FREE) == set()


def test_every_import_between_packages_follows_an_allowed_arrow():
    arrows = package_arrows()
    assert ("stages", "artifacts") in arrows and ("ultrastage", "evaluation") in arrows  # the scan sees imports
    offending = [where for (source, target), found in sorted(arrows.items()) if target not in ALLOWED[source]
                 for where in found]
    assert offending == []


def test_the_allowed_arrows_and_the_imports_have_no_circle():
    assert circle(ALLOWED) == []
    actual: dict[str, set[str]] = {}
    for source, target in package_arrows():
        actual.setdefault(source, set()).add(target)
    assert circle(actual) == []


def test_no_stage_module_imports_another_stage_module():
    from stages.registry import STAGE_CLASSES

    stage_modules = {cls.__module__ for cls in STAGE_CLASSES}
    assert len(stage_modules) >= 10 and "stages.photometric" in stage_modules
    offending = {}
    for module in sorted(stage_modules):
        path = Path(importlib.import_module(module).__file__)
        others = sorted({name for _, name in imports(path, module)} & stage_modules - {module})
        if others:
            offending[module] = others
    assert offending == {}


def _private_names(path: Path, modules: tuple[str, ...]) -> list[tuple[int, str]]:
    """(line, module.name) of every underscored name the file imports from one of ``modules``."""
    return [(node.lineno, f"{node.module}.{alias.name}")
            for node in ast.walk(ast.parse(path.read_text(), filename=str(path)))
            if isinstance(node, ast.ImportFrom) and node.module in modules
            for alias in node.names if alias.name.startswith("_")]


def test_the_neural_fields_share_their_helpers_without_private_imports():
    # what the SDF and the appearance field share lives in stages.numerics.neural_fields, imported by name
    fields = ("stages.numerics.sdf", "stages.numerics.neural_fields")
    root = ROOT / "stages"
    modules = sorted(root.rglob("*.py"))
    assert root / "numerics" / "appearance_field.py" in modules
    offending = [f"{path.relative_to(ROOT)}:{line} imports {name}" for path in modules
                 for line, name in _private_names(path, fields)]
    assert offending == []


# ------------------------------------------------------------------------------------ the scan itself

def test_the_scan_sees_type_checking_function_and_relative_imports(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("import os\n"
                      "from typing import TYPE_CHECKING\n"
                      "from .sh import sh_project\n"
                      "if TYPE_CHECKING:\n    from stages.geometry import GeometryConfig\n"
                      "def f():\n    import stages.materials\n    from stages import layout\n"
                      "    from .. import relight\n    from ..registry import PRESETS\n")
    names = [name for _, name in imports(module, "stages.numerics.m")]
    assert names == ["os", "typing", "typing.TYPE_CHECKING", "stages.numerics.sh", "stages.numerics.sh.sh_project",
                     "stages.geometry", "stages.geometry.GeometryConfig", "stages.materials", "stages",
                     "stages.layout", "stages", "stages.relight", "stages.registry", "stages.registry.PRESETS"]
    assert [package_of(n) for n in ("stages.numerics.sh", "stages.geometry", "manifests", "numpy")] == [
        "stages.numerics", "stages", "manifests", None]


def test_relative_imports_of_a_package_init_resolve_inside_it(tmp_path):
    init = tmp_path / "__init__.py"
    init.write_text("from .config import TrainConfig\nfrom . import data\n")
    assert [name for _, name in imports(init, "ultrastage.baselines")] == [
        "ultrastage.baselines.config", "ultrastage.baselines.config.TrainConfig", "ultrastage.baselines",
        "ultrastage.baselines.data"]


@pytest.mark.parametrize("edges, expected", [
    ({"a": {"b"}, "b": {"c"}, "c": set()}, []),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, ["a", "b", "c", "a"]),
    ({"a": {"a"}}, ["a", "a"]),
    ({"a": {"b", "c"}, "b": {"d"}, "c": {"d"}, "d": set()}, []),
])
def test_the_circle_search_finds_a_circle_and_only_a_circle(edges, expected):
    assert circle(edges) == expected


def test_a_forbidden_arrow_is_reported_with_its_file_and_line(tmp_path):
    pkg = tmp_path / "manifests"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "bad.py").write_text("def f():\n    from stages.registry import PRESETS\n")
    arrows = package_arrows(tmp_path)
    assert arrows == {("manifests", "stages"): ["manifests/bad.py:2 imports stages.registry",
                                                "manifests/bad.py:2 imports stages.registry.PRESETS"]}
    assert "stages" not in ALLOWED["manifests"]
