"""Benches import the numerics' constants, never copy them: a copy (``ROUGHNESS_MIN = 0.05``, or the value
written out where the numerics clip with it) keeps measuring the old value once the numerics change theirs.

The numerics' constants are the public UPPER_CASE names assigned at module level in stages/numerics/*.py. A
bench breaks the rule when it

1. assigns one of those names itself (anywhere: module level, a class, a function), or
2. writes one of their *distinctive* values as a literal: in a module-level UPPER_CASE assignment, or as a bound
   of a ``clip`` / ``clamp`` call. Distinctive values are the float literals of the numerics other than 0 and
   +-1 (``ROUGHNESS_MIN`` 0.05, ``HALF_MAX`` 60000.0, ``SHADOW_OFFSET_M`` 0.001, ...): integer constants are
   counts (64 rays, 8 features, 9 coefficients) that a bench's own counts equal by chance, and 0 and 1 bound
   every clip of a unit quantity.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
BENCH_FILES = sorted((ROOT / "bench").glob("*.py"))
CLIP_CALLS = {"clip", "clamp", "clip_", "clamp_"}
PUBLIC_CONSTANT = re.compile(r"[A-Z][A-Z0-9_]*")
TRIVIAL = {0.0, 1.0, -1.0}


def _number(node: ast.AST) -> float | None:
    """The value of a numeric literal (``-x`` included), else None (booleans are not numbers here)."""
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        value = _number(node.operand)
        return None if value is None else (-value if isinstance(node.op, ast.USub) else value)
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
        return float(node.value)
    return None


def _assignments(tree: ast.AST, module_level: bool) -> list[tuple[int, str, ast.AST | None]]:
    """(line, name, value) of the assignments to a plain name: the module's own statements, or every one."""
    nodes = tree.body if module_level else list(ast.walk(tree))
    found = []
    for node in nodes:
        if isinstance(node, ast.Assign):
            found += [(node.lineno, t.id, node.value) for t in node.targets if isinstance(t, ast.Name)]
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            found.append((node.lineno, node.target.id, node.value))
    return found


def numerics_constants(root: Path = ROOT) -> dict[str, tuple[str, float | None]]:
    """name -> (module file, value when it is a float literal) of every public UPPER_CASE module-level constant
    of stages/numerics/*.py."""
    out = {}
    for path in sorted((root / "stages" / "numerics").glob("*.py")):
        for _, name, value in _assignments(ast.parse(path.read_text(), filename=str(path)), module_level=True):
            if PUBLIC_CONSTANT.fullmatch(name):
                is_float = (value is not None and _number(value) is not None
                            and isinstance(getattr(value, "operand", value).value, float))
                out[name] = (path.name, _number(value) if is_float else None)
    return out


def copied_constants(source: str, constants: dict[str, tuple[str, float | None]]) -> list[str]:
    """Where a bench's ``source`` copies one of the numerics' ``constants`` (the module docstring's two rules),
    one line each."""
    values: dict[float, list[str]] = {}
    for name, (_, value) in constants.items():
        if value is not None and value not in TRIVIAL:
            values.setdefault(value, []).append(name)
    tree = ast.parse(source)
    found = [f"line {line}: assigns {name}, a constant of stages/numerics/{constants[name][0]}: import it"
             for line, name, _ in _assignments(tree, module_level=False) if name in constants]
    for line, name, value in _assignments(tree, module_level=True):
        number = None if value is None else _number(value)
        if PUBLIC_CONSTANT.fullmatch(name) and number in values and name not in constants:
            found.append(f"line {line}: {name} = {number:g} is the value of {', '.join(values[number])}: import it")
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
        if func not in CLIP_CALLS:
            continue
        for argument in [*node.args, *(k.value for k in node.keywords)]:
            number = _number(argument)
            if number in values:
                found.append(f"line {node.lineno}: {func} bound {number:g} is the value of "
                             f"{', '.join(values[number])}: import it")
    return found


def test_the_constants_seen_include_the_ones_benches_clip_with():
    constants = numerics_constants()
    assert constants["ROUGHNESS_MIN"] == ("sg.py", 0.05)
    assert constants["HALF_MAX"] == ("novel_view.py", 60000.0)
    assert constants["DEFAULT_AO_RAYS"] == ("shadowing.py", None)  # an integer count: its name only


@pytest.mark.parametrize("path", BENCH_FILES, ids=[p.stem for p in BENCH_FILES])
def test_benches_copy_no_constant_of_the_numerics(path):
    assert copied_constants(path.read_text(), numerics_constants()) == []


def test_the_rule_catches_copies_by_name_and_by_value():
    # the first two are bench_relight's own lines from before it imported ROUGHNESS_MIN and HALF_MAX
    source = """
import numpy as np
ROUGH_FLOOR = 0.05
HALF = 6e4
QUICK_CAMERAS = 8
def f(gb, pix, values):
    HALF_MAX = 60000.0
    r = np.clip(gb["roughness"].reshape(-1)[pix], 0.05, 1.0)
    out = np.clip(np.nan_to_num(values), 0, 6e4)
    unit = np.clip(values, 0.0, 1.0), values.clamp(min=-1.0, max=1)
    return r, out, unit
"""
    found = copied_constants(source, numerics_constants())
    assert found == ["line 7: assigns HALF_MAX, a constant of stages/numerics/novel_view.py: import it",
                     "line 3: ROUGH_FLOOR = 0.05 is the value of SOURCE_EDGE_JUMP_M, ROUGHNESS_MIN: import it",
                     "line 4: HALF = 60000 is the value of HALF_MAX: import it",
                     "line 8: clip bound 0.05 is the value of SOURCE_EDGE_JUMP_M, ROUGHNESS_MIN: import it",
                     "line 9: clip bound 60000 is the value of HALF_MAX: import it"]
