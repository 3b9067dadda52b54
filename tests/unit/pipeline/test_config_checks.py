"""Config validation in one place: rules beside the fields (``checked``), one validator (``config_problems`` /
``validate``) that reports every broken rule with the field's dotted name, its value and the rule."""
from __future__ import annotations

import ast
import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest

from pipeline.config import (Documented, InvalidConfig, broken, check, checked, config_problems, from_dict, key_fields,
                             merge, to_dict, validate)
from pipeline.errors import ConfigError

ROOT = Path(__file__).resolve().parents[3]
PROJECT_PACKAGES = ("pipeline", "artifacts", "stages", "calibration", "synthetic", "manifests", "evaluation",
                    "ultrastage")


@dataclass(frozen=True)
class Gauges(Documented):
    at_least: int = checked(0, ge=0)
    """ge."""
    above: float = checked(1.0, gt=0.0)
    """gt."""
    at_most: float = checked(1.0, le=1.0)
    """le."""
    below: float = checked(0.5, lt=1.0)
    """lt."""
    share: float = checked(0.25, ge=0.0, lt=1.0)
    """Two numeric bounds."""
    low: float = checked(0.2, ge=0.0, lt="high")
    """A bound that is another field."""
    high: float = 0.8
    """The other field."""
    flavour: str = checked("plain", one_of=("plain", "fancy"))
    """one_of."""
    labels: tuple[str, ...] = checked(("a",), nonempty=True)
    """nonempty."""
    speed: Literal["fast", "slow"] = "fast"
    """A Literal's values are its rule."""
    pair: tuple[float, ...] = (0.0, 1.0)
    """Checked by the class's _checks hook."""
    tally: int = 3
    """An int field takes whole numbers only."""
    loudness: int = field(default=0, metadata=check(ge=0))
    """The rule as explicit field metadata."""

    not_in_key = ("loudness",)

    def _checks(self) -> list[str]:
        if len(self.pair) != 2 or not self.pair[0] < self.pair[1]:
            return [broken(self, "pair", "must be (first, second) with first < second")]
        return []


@dataclass(frozen=True)
class Rack(Documented):
    gauges: Gauges = field(default_factory=Gauges)
    """A nested config."""
    slots: int = checked(4, ge=1)
    """A rule at the top level."""


def _problem(**changes) -> str:
    """The one problem ``Gauges(**changes)`` has."""
    with pytest.raises(InvalidConfig) as info:
        Gauges(**changes)
    assert len(info.value.problems) == 1, info.value.problems
    return info.value.problems[0]


@pytest.mark.parametrize("name, at_bound, past_bound, rule", [
    ("at_least", 0, -1, "must be >= 0"),
    ("above", 1e-9, 0.0, "must be > 0"),
    ("at_most", 1.0, 1.0001, "must be <= 1"),
    ("below", 0.9999, 1.0, "must be < 1"),
    ("share", 0.0, -0.5, "must be in [0, 1)"),
    ("low", 0.7999, 0.8, "must be >= 0 and < high (0.8)"),
])
def test_each_bound_accepts_its_limit_and_refuses_past_it(name, at_bound, past_bound, rule):
    assert getattr(Gauges(**{name: at_bound}), name) == at_bound
    assert _problem(**{name: past_bound}) == f"{name} = {past_bound!r}: {rule}"


def test_choices_emptiness_literals_whole_numbers_and_finite_values():
    assert Gauges(flavour="fancy").flavour == "fancy"
    assert _problem(flavour="spicy") == "flavour = 'spicy': must be one of 'plain', 'fancy'"
    assert Gauges(labels=("x", "y")).labels == ("x", "y")
    assert _problem(labels=()) == "labels = (): must not be empty"
    assert Gauges(speed="slow").speed == "slow"
    assert _problem(speed="warp") == "speed = 'warp': must be one of 'fast', 'slow'"
    assert Gauges(tally=7).tally == 7 and Gauges(tally=7.0).tally == 7.0
    assert _problem(tally=7.5) == "tally = 7.5: must be a whole number"
    assert _problem(above=float("inf")) == "above = inf: must be a finite number"
    assert _problem(above=float("nan")) == "above = nan: must be a finite number"
    assert _problem(above="1") == "above = '1': must be a number"
    assert Gauges(loudness=2).loudness == 2
    assert _problem(loudness=-2) == "loudness = -2: must be >= 0"


def test_a_rule_relating_fields_in_the_checks_hook():
    assert Gauges(pair=(-1.0, 0.0)).pair == (-1.0, 0.0)
    assert _problem(pair=(1.0, 0.0)) == "pair = (1.0, 0.0): must be (first, second) with first < second"
    # the other field of a field-name bound moved: the bound follows it
    assert Gauges(low=0.85, high=0.9).low == 0.85
    assert _problem(high=0.1) == "low = 0.2: must be >= 0 and < high (0.1)"


def test_every_broken_rule_is_reported_at_once_with_the_class_name():
    with pytest.raises(InvalidConfig) as info:
        Gauges(at_least=-1, below=2.0, flavour="spicy", pair=(3.0, 1.0))
    assert [p.split(" = ")[0] for p in info.value.problems] == ["at_least", "below", "flavour", "pair"]
    message = str(info.value)
    assert message.startswith("Gauges.at_least = -1: must be >= 0; Gauges.below = 2.0: must be < 1; ")
    assert isinstance(info.value, ConfigError) and isinstance(info.value, ValueError)
    # dataclasses.replace builds a new instance, so it is checked as well
    with pytest.raises(InvalidConfig, match=r"Gauges\.share = 1\.0: must be in \[0, 1\)"):
        dataclasses.replace(Gauges(), share=1.0)


def test_nested_configs_are_named_by_their_dotted_path():
    assert config_problems(Rack()) == []
    rack = copy.deepcopy(Rack())
    object.__setattr__(rack.gauges, "at_least", -3)  # past the nested config's own check at build
    object.__setattr__(rack, "slots", 0)
    assert config_problems(rack) == ["gauges.at_least = -3: must be >= 0", "slots = 0: must be >= 1"]
    with pytest.raises(InvalidConfig, match=r"^Rack\.gauges\.at_least = -3: must be >= 0; Rack\.slots = 0"):
        validate(rack)


def test_yaml_overrides_name_the_file_and_the_dotted_field_of_every_bad_value():
    overrides = {"gauges": {"below": 1.5, "labels": []}, "slots": 0}
    with pytest.raises(InvalidConfig) as info:
        merge(Rack(), overrides, where="o.yaml")
    assert str(info.value) == ("o.yaml.gauges.below = 1.5: must be < 1; o.yaml.gauges.labels = (): must not be empty; "
                               "o.yaml.slots = 0: must be >= 1")
    with pytest.raises(InvalidConfig) as info:
        from_dict(Rack, overrides, where="o.yaml")
    assert str(info.value) == ("o.yaml.gauges.below = 1.5: must be < 1; o.yaml.gauges.labels = (): must not be empty; "
                               "o.yaml.slots = 0: must be >= 1")
    # a type error is still reported as one: the value never reaches the rules
    with pytest.raises(ConfigError, match=r"o\.yaml\.gauges\.tally: expected an integer"):
        merge(Rack(), {"gauges": {"tally": 2.5}}, where="o.yaml")


def test_the_pipeline_config_through_yaml_and_a_preset():
    from stages.registry import PRESETS, PipelineConfig

    overrides = {"photometric": {"params": {"ratio_min": 1.5}}, "colour": {"erode_px": -1},
                 "geometry": {"sdf": {"encoding": {"levels": 40}}}}
    expected = ["photometric.params.ratio_min = 1.5: must be >= 0 and < ratio_max (1.05)",
                "colour.erode_px = -1: must be >= 0",
                "geometry.sdf.encoding.levels = 40: must be in [1, 32]"]
    for preset in ("default", "fast"):
        with pytest.raises(InvalidConfig) as info:
            merge(PRESETS[preset], overrides, where="o.yaml")
        assert info.value.owner == "o.yaml" and info.value.problems == expected
        assert str(info.value).startswith("o.yaml.photometric.params.ratio_min = 1.5: ")
    with pytest.raises(InvalidConfig) as info:
        from_dict(PipelineConfig, overrides)
    assert info.value.problems == expected
    # a cross-field rule of a stage config (relightset's split shares) through YAML
    with pytest.raises(InvalidConfig, match=r"o\.yaml\.relightset\.split_ratios = \(0\.5, 0\.5, 0\.5\): must be 3"):
        merge(PRESETS["test"], {"relightset": {"split_ratios": [0.5, 0.5, 0.5]}}, where="o.yaml")
    # every preset is valid, nested configs included
    assert {name: config_problems(config) for name, config in PRESETS.items()} == {name: [] for name in PRESETS}


def test_a_preset_written_in_code_is_checked_as_it_is_built():
    from stages.geometry import GeometryConfig
    from stages.numerics.sdf import SDF_PRESETS, HashGridConfig

    with pytest.raises(InvalidConfig, match=r"^HashGridConfig\.base_resolution = 64: must be >= 1 and "
                                            r"<= finest_resolution \(32\)$"):
        GeometryConfig(sdf=dataclasses.replace(SDF_PRESETS["test"], encoding=HashGridConfig(base_resolution=64,
                                                                                            finest_resolution=32)))
    with pytest.raises(InvalidConfig, match=r"^SDFConfig\.iterations = 0: must be >= 1$"):
        dataclasses.replace(SDF_PRESETS["cpu"], iterations=0)


def test_rules_stay_out_of_the_dict_and_the_key():
    assert to_dict(Gauges()) == {"at_least": 0, "above": 1.0, "at_most": 1.0, "below": 0.5, "share": 0.25,
                                 "low": 0.2, "high": 0.8, "flavour": "plain", "labels": ["a"], "speed": "fast",
                                 "pair": [0.0, 1.0], "tally": 3, "loudness": 0}
    assert "loudness" not in key_fields(Gauges()) and key_fields(Rack())["gauges"]["labels"] == ["a"]


# ------------------------------------------------------------------------------------------------ one place

DATA_TYPES = {
    "artifacts.camera.Camera": "a camera (K, pose, size), checked as data, not a config",
    "stages.numerics.hull.HullGrid": "a voxel grid (occupancy, bounds), checked as data",
    "calibration.light.LightModel": "a fitted model's coefficients, checked as data",
}
"""Dataclasses whose ``__post_init__`` may raise: data types, not configs."""


def _post_init_raises(path: Path, module: str) -> list[str]:
    """``module.Class`` of each class in the file whose ``__post_init__`` has a ``raise`` of its own."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ClassDef):
            for stmt in node.body:
                if (isinstance(stmt, ast.FunctionDef) and stmt.name == "__post_init__"
                        and any(isinstance(n, ast.Raise) for n in ast.walk(stmt))):
                    found.append(f"{module}.{node.name}")
    return found


def test_no_config_checks_its_values_by_hand_in_post_init():
    found = set()
    for package in PROJECT_PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
            found.update(_post_init_raises(path, module))
    assert found - set(DATA_TYPES) == set(), ("state these checks beside the fields (pipeline.config.checked) or "
                                              "in the class's _checks(), or list a data type in DATA_TYPES")
    assert set(DATA_TYPES) - found == set(), "DATA_TYPES names a class without a raising __post_init__"


def test_the_scan_sees_a_hand_written_check(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("class C:\n    def __post_init__(self):\n        if self.x < 0:\n"
                      "            raise ValueError('x')\n\nclass D:\n    def __post_init__(self):\n        pass\n")
    assert _post_init_raises(module, "m") == ["m.C"]


def _nested_configs(cls: type) -> set[type]:
    out = {cls}
    for f in dataclasses.fields(cls):
        default = (f.default if f.default is not dataclasses.MISSING
                   else f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        if dataclasses.is_dataclass(default):
            out |= _nested_configs(type(default))
    return out


def test_every_config_is_validated_when_it_is_built():
    from calibration.geometric import RigRefineConfig
    from ultrastage.baselines.config import TrainConfig
    from stages.numerics.appearance_field import AppearanceFieldConfig
    from stages.registry import PipelineConfig
    from synthetic.calibration import CalibrationConfig
    from synthetic.config import SimConfig

    configs = set().union(*(_nested_configs(cls) for cls in (PipelineConfig, SimConfig, CalibrationConfig,
                                                              TrainConfig, AppearanceFieldConfig, RigRefineConfig)))
    configs.discard(PipelineConfig)  # the sections' container: each section validates itself
    names = {cls.__name__ for cls in configs}
    assert {"PhotometricParams", "ViewShading", "HashGridConfig", "GeometricConfig", "MarkerCalibrationConfig",
            "LearnedBlendConfig", "SimConfig"} <= names
    not_checked = sorted(cls.__name__ for cls in configs
                         if not issubclass(cls, Documented) or cls.__post_init__ is not Documented.__post_init__)
    assert not_checked == []
