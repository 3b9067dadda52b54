"""The layers import downwards only: the engine (pipeline/) imports no other package of the project, and the
numerics (stages/numerics/) import no stage module, at module level, inside functions or under TYPE_CHECKING."""
from __future__ import annotations

import ast
from pathlib import Path

import pipeline
import stages.numerics

PROJECT_PACKAGES = ("stages", "manifests", "calibration", "synthetic", "bench", "tests")


def _imports(path: Path, package: str = "") -> list[tuple[int, str]]:
    """(line, module) of every import in the file (``ast.walk``: module level, functions, ``if TYPE_CHECKING``);
    relative imports resolved against ``package``, the dotted package the file is in (``from . import x`` gives
    ``package.x``)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.ImportFrom) and node.level > 0:
            parts = package.split(".")
            base = ".".join(parts[:len(parts) - (node.level - 1)] if node.level > 1 else parts)
            if node.module:
                found.append((node.lineno, f"{base}.{node.module}"))
            else:
                found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
    return found


def test_the_engine_imports_no_other_package_of_the_project():
    root = Path(pipeline.__file__).parent
    modules = sorted(root.rglob("*.py"))
    assert len(modules) > 10  # the scan sees the engine's modules (stage, graph, runner, ..., codecs)
    offending = [f"{path.relative_to(root.parent)}:{line} imports {name}" for path in modules
                 for line, name in _imports(path) if name.split(".")[0] in PROJECT_PACKAGES]
    assert offending == []


def _stage_imports(path: Path, package: str) -> list[tuple[int, str]]:
    """The imports of a numerics module that reach a stage module: ``stages`` or ``stages.<x>`` for any ``x``
    but ``numerics``."""
    return [(line, name) for line, name in _imports(path, package)
            if name.split(".")[0] == "stages" and name.split(".")[1:2] != ["numerics"]]


def test_no_numerics_module_imports_a_stage_module():
    root = Path(stages.numerics.__file__).parent
    modules = sorted(root.rglob("*.py"))
    assert len(modules) > 20 and root / "sdf_mesh.py" in modules  # the scan sees the numerics' modules
    offending = []
    for path in modules:
        package = ".".join(("stages", "numerics", *path.relative_to(root).parent.parts))
        offending += [f"{path.relative_to(root.parent.parent)}:{line} imports {name}"
                      for line, name in _stage_imports(path, package)]
    assert offending == []


def test_the_scan_sees_imports_inside_functions(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("import os\n\ndef f():\n    from manifests import asset_row\n    import stages.registry\n")
    assert [name for _, name in _imports(module)] == ["os", "manifests", "stages.registry"]


def test_the_numerics_scan_sees_type_checking_function_and_relative_imports_of_stages(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("from typing import TYPE_CHECKING\n"
                      "from stages.numerics.sg import fit_sg_environment\n"
                      "from .sh import sh_project\n"
                      "if TYPE_CHECKING:\n    from stages.geometry import GeometryConfig\n"
                      "def f():\n    import stages.materials\n    from stages import layout\n"
                      "    from .. import relight\n    from ..artifacts import ActionArtifacts\n")
    assert [name for _, name in _stage_imports(module, "stages.numerics")] == [
        "stages.geometry", "stages.materials", "stages", "stages.relight", "stages.artifacts"]


def _private_names(path: Path, modules: tuple[str, ...]) -> list[tuple[int, str]]:
    """(line, module.name) of every underscored name the file imports from one of ``modules``."""
    return [(node.lineno, f"{node.module}.{alias.name}")
            for node in ast.walk(ast.parse(path.read_text(), filename=str(path)))
            if isinstance(node, ast.ImportFrom) and node.module in modules
            for alias in node.names if alias.name.startswith("_")]


def test_the_neural_fields_share_their_helpers_without_private_imports():
    # what the SDF and the appearance field share lives in stages.numerics.neural_fields, imported by name
    fields = ("stages.numerics.sdf", "stages.numerics.neural_fields")
    root = Path(stages.numerics.__file__).parent.parent
    modules = sorted(root.rglob("*.py"))
    assert root / "numerics" / "appearance_field.py" in modules
    offending = [f"{path.relative_to(root.parent)}:{line} imports {name}" for path in modules
                 for line, name in _private_names(path, fields)]
    assert offending == []
