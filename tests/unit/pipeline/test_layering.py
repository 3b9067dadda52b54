"""The engine (pipeline/) imports no other package of the project, at module level or inside functions."""
from __future__ import annotations

import ast
from pathlib import Path

import pipeline

PROJECT_PACKAGES = ("stages", "manifests", "calibration", "synthetic", "bench", "tests")


def _imports(path: Path) -> list[tuple[int, str]]:
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
    return found


def test_the_engine_imports_no_other_package_of_the_project():
    root = Path(pipeline.__file__).parent
    modules = sorted(root.rglob("*.py"))
    assert len(modules) > 10  # the scan sees the engine's modules (stage, graph, runner, ..., codecs)
    offending = [f"{path.relative_to(root.parent)}:{line} imports {name}" for path in modules
                 for line, name in _imports(path) if name.split(".")[0] in PROJECT_PACKAGES]
    assert offending == []


def test_the_scan_sees_imports_inside_functions(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("import os\n\ndef f():\n    from manifests import asset_row\n    import stages.registry\n")
    assert [name for _, name in _imports(module)] == ["os", "manifests", "stages.registry"]
