"""Cache-key records leave out every ``not_in_key`` field, at whatever depth its config class is nested.

The classes are found by scanning the project's source for ``not_in_key`` (as a reviewer would grep), so a new
config class that declares exclusions is tested without being listed here.
"""
from __future__ import annotations

import ast
import dataclasses
import importlib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from pipeline.config import Documented, key_fields

ROOT = Path(__file__).resolve().parents[2]
PROJECT_PACKAGES = ("pipeline", "stages", "calibration", "synthetic", "manifests", "evaluation")


def _classes_with_exclusions() -> list[tuple[str, str]]:
    """(module, class name) of every class in the project's packages whose body assigns ``not_in_key``."""
    found = []
    for package in PROJECT_PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            tree = ast.parse(path.read_text(), filename=str(path))
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
            for node in ast.walk(tree):
                if isinstance(node, ast.ClassDef) and node.name != "Documented" and any(
                        isinstance(stmt, (ast.Assign, ast.AnnAssign))
                        and any(isinstance(t, ast.Name) and t.id == "not_in_key"
                                for t in (stmt.targets if isinstance(stmt, ast.Assign) else [stmt.target]))
                        for stmt in node.body):
                    found.append((module, node.name))
    return found


EXCLUDING_CLASSES = _classes_with_exclusions()


def _other_value(config: Any, name: str) -> Any:
    """A valid value of field ``name`` different from the config's, by the field's annotation."""
    annotation = typing.get_type_hints(type(config))[name]
    current = getattr(config, name)
    if typing.get_origin(annotation) is typing.Literal:
        return next(v for v in typing.get_args(annotation) if v != current)
    if annotation is bool:
        return not current
    if annotation is int:
        return current + 1
    if annotation is float:
        return current * 2.0 + 1.0
    if annotation is str:
        return current + "-changed"
    raise TypeError(f"no other value for {type(config).__name__}.{name}: {annotation}")


def _replaced(config: Any, name: str) -> Any:
    """``config`` with field ``name`` set to another value its checks accept (a string field tries a few)."""
    candidates = [_other_value(config, name)]
    if isinstance(getattr(config, name), str):
        candidates += [v for v in ("cpu", "cuda", "auto", "sync", "local") if v != getattr(config, name)]
    for value in candidates:
        try:
            return dataclasses.replace(config, **{name: value})
        except (TypeError, ValueError):
            continue
    raise AssertionError(f"no other valid value for {type(config).__name__}.{name}")


def _included_scalar_field(config: Any) -> str:
    """The first field that is in the key and whose value _other_value can change."""
    for f in dataclasses.fields(config):
        if f.name in config.not_in_key or dataclasses.is_dataclass(getattr(config, f.name)):
            continue
        try:
            dataclasses.replace(config, **{f.name: _other_value(config, f.name)})
        except (TypeError, ValueError):
            continue
        return f.name
    raise AssertionError(f"{type(config).__name__} has no changeable field in its key")


def test_the_scan_finds_the_nested_configs_with_exclusions():
    names = {name for _, name in EXCLUDING_CLASSES}
    assert {"SDFConfig", "AppearanceFieldConfig", "ExecutionConfig"} <= names


@pytest.mark.parametrize("module,name", EXCLUDING_CLASSES, ids=[n for _, n in EXCLUDING_CLASSES])
def test_excluded_nested_fields_stay_out_of_the_key(module, name):
    cls = getattr(importlib.import_module(module), name)
    assert cls.not_in_key, f"{module}.{name} declares an empty not_in_key"

    @dataclass(frozen=True)
    class Holder(Documented):
        """A stage config holding ``cls`` one level down, as GeometryConfig holds SDFConfig."""

        inner: cls = field(default_factory=cls)
        """The nested config under test."""
        gain: float = 1.0
        """A top-level field."""

    base = Holder()
    reference = key_fields(base)
    for excluded in cls.not_in_key:
        assert excluded in {f.name for f in dataclasses.fields(cls)}, f"{name}.not_in_key names no field {excluded}"
        changed = Holder(inner=_replaced(base.inner, excluded))
        assert changed != base
        assert key_fields(changed) == reference, f"{name}.{excluded} changed the key record"
        assert excluded not in key_fields(changed)["inner"]
    if set(cls.not_in_key) == {f.name for f in dataclasses.fields(cls)}:  # e.g. ExecutionConfig: never in a key
        assert reference["inner"] == {}
        return
    included = _included_scalar_field(base.inner)
    changed = Holder(inner=dataclasses.replace(base.inner, **{included: _other_value(base.inner, included)}))
    assert key_fields(changed) != reference, f"{name}.{included} did not change the key record"


def test_geometry_sdf_log_every_leaves_the_geometry_key_record_alone():
    from stages.geometry import GeometryConfig

    base = GeometryConfig()
    for excluded, value in (("log_every", base.sdf.log_every + 7), ("threads", 3), ("device", "cpu")):
        changed = dataclasses.replace(base, sdf=dataclasses.replace(base.sdf, **{excluded: value}))
        assert key_fields(changed) == key_fields(base), excluded
    more_steps = dataclasses.replace(base, sdf=dataclasses.replace(base.sdf, iterations=base.sdf.iterations + 1))
    assert key_fields(more_steps)["sdf"]["iterations"] == base.sdf.iterations + 1
    assert key_fields(more_steps) != key_fields(base)


def test_each_stage_key_holds_the_code_it_runs_and_not_the_engine():
    from pipeline.hashing import code_digests
    from stages.registry import CODE_PACKAGES, PRESETS, build_stages

    stages = {s.name: s for s in build_stages(PRESETS["test"])}
    assert all(s.code_packages == CODE_PACKAGES for s in stages.values())
    code = {name: code_digests(s.code_module, s.code_packages) for name, s in stages.items()}
    assert {"stages.geometry", "stages.numerics.sdf", "stages.numerics.mesh",
            "pipeline.codecs.mesh"} <= set(code["geometry"])
    assert {"stages.cameras", "calibration.geometric", "pipeline.codecs.raw"} <= set(code["cameras"])
    assert {"stages.materials", "stages.numerics.materials"} <= set(code["materials"])
    for name, modules in code.items():
        engine = {m for m in modules if m.startswith(("pipeline.", "manifests")) and not m.startswith("pipeline.codecs")}
        assert not engine, name
        assert "stages.registry" not in modules and not any(m.split(".")[0] == "ultrastage" for m in modules), name
