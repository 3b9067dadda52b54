"""Typed, frozen configuration: dataclasses with a docstring per field, presets as code, YAML overrides.

Every stage has a ``<Name>Config`` dataclass beside it. Fields that do not change a stage's output
(worker counts, progress display) are listed in the class attribute ``not_in_key`` and left out of the
cache key, at whatever depth the class is nested. YAML overrides are merged onto a preset and reject unknown keys, naming the key and the file.
"""
from __future__ import annotations

import dataclasses
import math
import json
import types
import typing
from pathlib import Path
from typing import Any, ClassVar

import yaml

from pipeline.errors import ConfigError


def _field_types(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def to_dict(config: Any) -> dict[str, Any]:
    """A plain, JSON-able dict of a (nested) config dataclass."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            value = to_dict(value)
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out


def key_fields(config: Any) -> dict[str, Any]:
    """The fields of a (nested) stage config that change its output: ``to_dict`` less every field that its
    own dataclass lists in ``not_in_key``, at every level (``geometry.sdf.log_every`` is left out by
    ``SDFConfig.not_in_key``, not only the stage config's top-level exclusions)."""
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError(f"key_fields expects a config dataclass instance, got {type(config).__name__}")
    skip = set(getattr(config, "not_in_key", ()))
    out: dict[str, Any] = {}
    for f in dataclasses.fields(config):
        if f.name in skip:
            continue
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            value = key_fields(value)
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out


def _coerce(value: Any, annotation: Any, where: str) -> Any:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if dataclasses.is_dataclass(annotation):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping for {annotation.__name__}, got {value!r}")
        return from_dict(annotation, value, where)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{where}: {value!r} matches none of {annotation}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: {value!r} is not one of {list(args)}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        inner = args[0] if args else Any
        return tuple(_coerce(v, inner, f"{where}[{i}]") for i, v in enumerate(value))
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true/false, got {value!r}")
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):  # YAML reads .nan and .inf; no threshold or size means anything as those
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def from_dict(cls: type, data: dict[str, Any], where: str = "config") -> Any:
    """Build ``cls`` from a dict, rejecting unknown keys and mistyped values."""
    types_by_name = _field_types(cls)
    unknown = sorted(set(data) - set(types_by_name))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; {cls.__name__} has {sorted(types_by_name)}")
    kwargs = {k: _coerce(v, types_by_name[k], f"{where}.{k}") for k, v in data.items()}
    return _checked(lambda: cls(**kwargs), where)


def _checked(build: Any, where: str) -> Any:
    """``build()``, with the ValueError a config's own checks (``__post_init__``) raise turned into a
    ConfigError naming where the value came from (file and section)."""
    try:
        return build()
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def merge(config: Any, overrides: dict[str, Any], where: str = "config") -> Any:
    """A copy of ``config`` with ``overrides`` (a nested dict) applied; unknown keys are errors."""
    if not isinstance(overrides, dict):
        raise ConfigError(f"{where}: expected a mapping, got {overrides!r}")
    types_by_name = _field_types(type(config))
    unknown = sorted(set(overrides) - set(types_by_name))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; {type(config).__name__} has {sorted(types_by_name)}")
    changes = {}
    for name, value in overrides.items():
        current = getattr(config, name)
        if dataclasses.is_dataclass(current):
            changes[name] = merge(current, value, f"{where}.{name}")
        else:
            changes[name] = _coerce(value, types_by_name[name], f"{where}.{name}")
    return _checked(lambda: dataclasses.replace(config, **changes), where)


def load_overrides(path: str | Path) -> dict[str, Any]:
    """Read a YAML (or JSON) override file; an empty file is no override."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: config file not found") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections, got {type(data).__name__}")
    return data


def dump_yaml(config: Any) -> str:
    """The resolved config (a config dataclass or a plain dict) as YAML, saved beside each run."""
    data = to_dict(config) if dataclasses.is_dataclass(config) else config
    return yaml.safe_dump(json.loads(json.dumps(data)), sort_keys=True)


class Documented:
    """Mixin: ``not_in_key`` lists fields that do not change output and stay out of cache keys."""

    not_in_key: ClassVar[tuple[str, ...]] = ()
