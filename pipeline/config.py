"""Typed, frozen configuration: dataclasses with a docstring per field, presets as code, YAML overrides.

Every stage has a ``<Name>Config`` dataclass beside it. Fields that do not change a stage's output
(worker counts, progress display) are listed in the class attribute ``not_in_key`` and left out of the
cache key, at whatever depth the class is nested. YAML overrides are merged onto a preset and reject unknown keys, naming the key and the file.

A field states its valid values beside it (``ratio_min: float = checked(0.3, ge=0.0, lt="ratio_max")``);
:func:`validate` checks a config against those rules, its annotations (a ``Literal``'s values, whole numbers for
``int``), the rules of its nested configs and its ``_checks`` hook (rules that relate several fields in ways a
bound cannot say), and reports every broken rule at once, each with the field's dotted name, its value and the
rule. :class:`Documented` configs run it when they are built, in code, in presets and from YAML.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import json
import numbers
import operator
import types
import typing
from pathlib import Path
from typing import Any, ClassVar

import yaml

from pipeline.errors import ConfigError


def _field_types(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


# ------------------------------------------------------------------------------------------------ checks

_RULE = "ultrastage.check"
"""Key of a field's :class:`Rule` in its ``dataclasses.field`` metadata."""

Bound = float | str | None
"""A number, or the name of another field of the same config whose value is the bound."""


@dataclasses.dataclass(frozen=True)
class Rule:
    """The valid values of one config field. Bounds apply to numbers (and require them finite); a bound given
    as a field name compares with that field's value."""

    ge: Bound = None
    """Smallest valid value."""
    gt: Bound = None
    """Valid values are greater than this."""
    le: Bound = None
    """Largest valid value."""
    lt: Bound = None
    """Valid values are less than this."""
    one_of: tuple[Any, ...] | None = None
    """The only valid values."""
    nonempty: bool = False
    """A sequence (or string) must hold at least one item."""

    def problem(self, config: Any, value: Any) -> str | None:
        """What is wrong with ``value`` as this field of ``config`` (None when nothing is): the rule it breaks."""
        if self.one_of is not None and value not in self.one_of:
            return "must be one of " + ", ".join(repr(v) for v in self.one_of)
        if self.nonempty and not (hasattr(value, "__len__") and len(value)):
            return "must not be empty"
        bounds = [(op, getattr(self, op)) for op in ("ge", "gt", "le", "lt") if getattr(self, op) is not None]
        if not bounds:
            return None
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return "must be a number"
        if not math.isfinite(value):
            return "must be a finite number"
        limits = [(op, bound, getattr(config, bound) if isinstance(bound, str) else bound) for op, bound in bounds]
        if all(_holds(value, op, limit) for op, _, limit in limits):
            return None
        return "must be " + _describe(limits)


def _holds(value: Any, op: str, limit: Any) -> bool:
    try:
        return bool(getattr(operator, op)(value, limit))
    except TypeError:  # a bound field that is not a number: that field's own rule reports it
        return False


_SYMBOL = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}


def _describe(limits: list[tuple[str, Bound, Any]]) -> str:
    """``in [0, 1)`` for two numeric bounds, else ``>= 0 and < ratio_max (1.05)``."""
    if len(limits) == 2 and not any(isinstance(bound, str) for _, bound, _ in limits):
        (low_op, low, _), (high_op, high, _) = sorted(limits, key=lambda item: item[0] in ("le", "lt"))
        if low_op in ("ge", "gt") and high_op in ("le", "lt"):
            return f"in {'[' if low_op == 'ge' else '('}{low:g}, {high:g}{']' if high_op == 'le' else ')'}"
    return " and ".join(f"{_SYMBOL[op]} {bound} ({limit!r})" if isinstance(bound, str) else f"{_SYMBOL[op]} {bound:g}"
                        for op, bound, limit in limits)


def check(*, ge: Bound = None, gt: Bound = None, le: Bound = None, lt: Bound = None,
          one_of: tuple[Any, ...] | None = None, nonempty: bool = False) -> dict[str, Rule]:
    """Field metadata stating a field's valid values: ``field(default_factory=..., metadata=check(nonempty=True))``.
    Bounds are numbers or the names of other fields of the config."""
    return {_RULE: Rule(ge=ge, gt=gt, le=le, lt=lt, one_of=tuple(one_of) if one_of is not None else None,
                        nonempty=nonempty)}


def checked(default: Any, **rule: Any) -> Any:
    """A dataclass field with ``default`` and the rule :func:`check` makes of ``rule``:
    ``ratio_min: float = checked(0.3, ge=0.0, lt="ratio_max")``."""
    return dataclasses.field(default=default, metadata=check(**rule))


class InvalidConfig(ConfigError):
    """Values of a config that break its rules: ``problems`` has one ``<dotted field> = <value>: <rule>`` line per
    broken rule, the names relative to ``owner`` (the config's class, or the file and section it came from)."""

    def __init__(self, owner: str, problems: list[str]):
        self.owner = owner
        self.problems = list(problems)
        super().__init__("; ".join(f"{owner}.{problem}" for problem in self.problems))


@functools.cache
def _annotations(cls: type) -> dict[str, Any]:
    try:
        return _field_types(cls)
    except (NameError, TypeError):  # a class whose annotations name what its module cannot resolve
        return {}


def _annotation_problem(annotation: Any, value: Any) -> str | None:
    """What the field's type says is wrong with ``value``: a value outside a ``Literal``, a fraction for an ``int``
    (YAML values are type-checked by :func:`from_dict`; this catches what code passes)."""
    if typing.get_origin(annotation) is typing.Literal and value not in typing.get_args(annotation):
        return "must be one of " + ", ".join(repr(v) for v in typing.get_args(annotation))
    if annotation is int and not isinstance(value, numbers.Integral):
        if not (isinstance(value, numbers.Real) and math.isfinite(value) and float(value).is_integer()):
            return "must be a whole number"
    return None


def config_problems(config: Any) -> list[str]:
    """Every broken rule of a config instance and of the configs nested in it, one
    ``<dotted field> = <value>: <rule>`` line each (empty when the config is valid). The rules: each field's
    :func:`check` metadata, its annotation (:func:`_annotation_problem`) and the class's ``_checks()``, whose
    lines name their fields the same way."""
    problems: list[str] = []
    annotations = _annotations(type(config))
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            problems += [f"{f.name}.{problem}" for problem in config_problems(value)]
            continue
        problem = _annotation_problem(annotations.get(f.name), value)
        if problem is None and _RULE in f.metadata:
            problem = f.metadata[_RULE].problem(config, value)
        if problem is not None:
            problems.append(f"{f.name} = {value!r}: {problem}")
    hook = getattr(config, "_checks", None)
    if hook is not None:
        problems += hook()
    return problems


def validate(config: Any) -> None:
    """Raise :class:`InvalidConfig` naming every broken rule of ``config`` (see :func:`config_problems`)."""
    problems = config_problems(config)
    if problems:
        raise InvalidConfig(type(config).__name__, problems)


def broken(config: Any, name: str, rule: str) -> str:
    """A problem line for a ``_checks`` hook: ``<name> = <value>: <rule>``."""
    return f"{name} = {getattr(config, name)!r}: {rule}"


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
    """Build ``cls`` from a dict, rejecting unknown keys and mistyped values (a ConfigError for the first) and
    values that break the rules (one :class:`InvalidConfig` naming all of them, ``<where>.<dotted field>``)."""
    types_by_name = _field_types(cls)
    unknown = sorted(set(data) - set(types_by_name))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; {cls.__name__} has {sorted(types_by_name)}")
    problems: list[str] = []
    kwargs = {}
    for k, v in data.items():
        try:
            kwargs[k] = _coerce(v, types_by_name[k], f"{where}.{k}")
        except InvalidConfig as exc:
            problems += [f"{k}.{problem}" for problem in exc.problems]
    if problems:
        raise InvalidConfig(where, problems + _own_problems(lambda: cls(**kwargs)))
    return _checked(lambda: cls(**kwargs), where)


def _own_problems(build: Any) -> list[str]:
    """The broken rules of the config ``build()`` makes with the invalid sections left out (as they were, or at
    their defaults), so that one report holds a section's problems and its parent's (empty when it builds, or
    when it fails for another reason)."""
    try:
        build()
    except InvalidConfig as exc:
        return exc.problems
    except (ValueError, TypeError):
        pass
    return []


def _checked(build: Any, where: str) -> Any:
    """``build()``, with the rules a config's validation finds broken (:class:`InvalidConfig`) named from
    ``where`` (file and section), and any other ValueError a constructor raises turned into a ConfigError
    naming it."""
    try:
        return build()
    except InvalidConfig as exc:
        raise InvalidConfig(where, exc.problems) from exc
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def merge(config: Any, overrides: dict[str, Any], where: str = "config") -> Any:
    """A copy of ``config`` with ``overrides`` (a nested dict) applied; unknown keys and mistyped values are
    errors, and so are the values that break the rules (one :class:`InvalidConfig` naming all of them)."""
    if not isinstance(overrides, dict):
        raise ConfigError(f"{where}: expected a mapping, got {overrides!r}")
    types_by_name = _field_types(type(config))
    unknown = sorted(set(overrides) - set(types_by_name))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; {type(config).__name__} has {sorted(types_by_name)}")
    changes = {}
    problems: list[str] = []  # broken rules of the nested sections, gathered to be reported together
    for name, value in overrides.items():
        current = getattr(config, name)
        try:
            if dataclasses.is_dataclass(current):
                changes[name] = merge(current, value, f"{where}.{name}")
            else:
                changes[name] = _coerce(value, types_by_name[name], f"{where}.{name}")
        except InvalidConfig as exc:
            problems += [f"{name}.{problem}" for problem in exc.problems]
    if problems:
        raise InvalidConfig(where, problems + _own_problems(lambda: dataclasses.replace(config, **changes)))
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
    """Mixin of the config dataclasses: ``not_in_key`` lists fields that do not change output and stay out of
    cache keys; the config is validated (:func:`validate`) when it is built. Rules that relate several fields
    in ways a field's bounds cannot say go in ``_checks``."""

    not_in_key: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        validate(self)

    def _checks(self) -> list[str]:
        """Broken rules that relate several fields, one :func:`broken` line each (none by default)."""
        return []
