from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from pipeline.config import Documented, from_dict, key_fields, load_overrides, merge, to_dict
from pipeline.errors import ConfigError


@dataclass(frozen=True)
class Inner(Documented):
    threshold: float = 0.5
    """A threshold."""
    name: str = "a"
    """A name."""


@dataclass(frozen=True)
class Outer(Documented):
    inner: Inner = field(default_factory=Inner)
    """Nested section."""
    count: int = 3
    """A count."""
    workers: int = 2
    """Not part of the key."""
    not_in_key = ("workers",)


def test_merge_applies_nested_overrides():
    cfg = merge(Outer(), {"inner": {"threshold": 1}, "count": 5})
    assert cfg.inner.threshold == 1.0 and isinstance(cfg.inner.threshold, float)
    assert cfg.count == 5 and cfg.inner.name == "a"


def test_unknown_key_is_rejected_with_its_path():
    with pytest.raises(ConfigError, match=r"cfg\.inner: unknown key\(s\) \['treshold'\]"):
        merge(Outer(), {"inner": {"treshold": 1}}, where="cfg")


def test_wrong_type_is_rejected():
    with pytest.raises(ConfigError, match="expected an integer"):
        merge(Outer(), {"count": "five"})
    with pytest.raises(ConfigError, match="expected true/false|expected an integer"):
        merge(Outer(), {"count": True})


def test_key_fields_exclude_not_in_key():
    assert "workers" not in key_fields(Outer())
    assert key_fields(Outer())["inner"] == {"threshold": 0.5, "name": "a"}


@dataclass(frozen=True)
class Leaf(Documented):
    steps: int = 10
    """In the key."""
    log_every: int = 5
    """Progress display only."""
    not_in_key = ("log_every",)


@dataclass(frozen=True)
class Middle(Documented):
    leaf: Leaf = field(default_factory=Leaf)
    """Two levels below the stage config."""


@dataclass(frozen=True)
class Top(Documented):
    middle: Middle = field(default_factory=Middle)
    """One level below."""


def test_key_fields_apply_not_in_key_at_every_depth():
    assert key_fields(Top()) == {"middle": {"leaf": {"steps": 10}}}
    quiet = Top(Middle(Leaf(log_every=500)))
    assert key_fields(quiet) == key_fields(Top())
    assert key_fields(Top(Middle(Leaf(steps=11)))) != key_fields(Top())
    with pytest.raises(TypeError, match="config dataclass instance"):
        key_fields({"steps": 10})


def test_round_trip_through_dict():
    cfg = Outer(inner=Inner(0.25, "b"), count=7)
    assert from_dict(Outer, to_dict(cfg)) == cfg


def test_yaml_file_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("- a list\n")
    with pytest.raises(ConfigError, match="bad.yaml"):
        load_overrides(bad)
    assert load_overrides(_write(tmp_path / "empty.yaml", "")) == {}
    with pytest.raises(ConfigError, match="not found"):
        load_overrides(tmp_path / "missing.yaml")


def _write(path, text):
    path.write_text(text)
    return path
