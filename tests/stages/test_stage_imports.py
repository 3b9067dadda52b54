"""A stage reads what another stage made through the artifact facade, never by importing that stage's module:
importing it would put the other stage's code in this stage's cache key and tie the two modules together."""
from __future__ import annotations

import ast
import importlib
from pathlib import Path

from stages.registry import STAGE_CLASSES


def _imported_modules(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module)
            found |= {f"{node.module}.{alias.name}" for alias in node.names}  # `from stages import decode`
    return found


def test_no_stage_module_imports_another_stage_module():
    stage_modules = {cls.__module__ for cls in STAGE_CLASSES}
    assert len(stage_modules) >= 10 and "stages.photometric" in stage_modules
    offending = {}
    for module in sorted(stage_modules):
        path = Path(importlib.import_module(module).__file__)
        others = sorted((_imported_modules(path) & stage_modules) - {module})
        if others:
            offending[module] = others
    assert offending == {}


def test_the_scan_sees_a_stage_imported_inside_a_function(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from stages.photometric import SpecularConfig\n    from stages import decode\n")
    assert {"stages.photometric", "stages.decode"} <= _imported_modules(module)
