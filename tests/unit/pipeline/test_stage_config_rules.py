"""The value rules of the stage configs that had none (textures, cameras, decode, exports, photometric, relight
and the shading it shares with relightset): each accepts its bound and refuses the value past it, with the
field's name, its value and the rule, when built in code and from a YAML override."""
from __future__ import annotations

import pytest

from pipeline.config import InvalidConfig, merge
from pipeline.errors import ConfigError
from stages.cameras import CamerasConfig
from stages.decode import DecodeConfig
from stages.exports import ExportsConfig
from stages.numerics.novel_view import ViewShading
from stages.photometric import PhotometricConfig
from stages.relight import RelightConfig
from stages.textures import TexturesConfig

RULES = [
    (TexturesConfig, "atlas_faces", 4, 3, "must be >= 4"),
    (TexturesConfig, "texture_size", 8, 7, "must be >= 8"),
    (TexturesConfig, "atlas_padding", 0, -1, "must be >= 0"),
    (TexturesConfig, "max_views", 1, 0, "must be >= 1"),
    (TexturesConfig, "depth_tolerance_m", 1e-9, 0.0, "must be > 0"),
    (TexturesConfig, "min_cos", -1.0, -1.0001, "must be in [-1, 1)"),
    (TexturesConfig, "min_cos", 0.9999, 1.0, "must be in [-1, 1)"),
    (TexturesConfig, "min_alpha", 0.0, -0.1, "must be in [0, 1)"),
    (TexturesConfig, "min_alpha", 0.9999, 1.0, "must be in [0, 1)"),
    (CamerasConfig, "min_registered_fraction", 0.0, -0.1, "must be in [0, 1]"),
    (CamerasConfig, "min_registered_fraction", 1.0, 1.01, "must be in [0, 1]"),
    (ExportsConfig, "colmap_points", 1, 0, "must be >= 1"),
    (ExportsConfig, "seed", 0, -1, "must be >= 0"),
    (PhotometricConfig, "light_iterations", 0, -1, "must be >= 0"),
    (RelightConfig, "min_alpha", 0.0, -0.5, "must be in [0, 1)"),
    (RelightConfig, "min_alpha", 0.9999, 1.0, "must be in [0, 1)"),
    (ViewShading, "depth_tolerance_m", 1e-9, 0.0, "must be > 0"),
    (ViewShading, "normal_fusion_m", 1e-9, 0.0, "must be > 0"),
    (ViewShading, "f0", 0.0, -0.01, "must be in [0, 1]"),
    (ViewShading, "f0", 1.0, 1.01, "must be in [0, 1]"),
]


@pytest.mark.parametrize("cls, name, at_bound, past_bound, rule", RULES,
                         ids=[f"{c.__name__}.{n}={p}" for c, n, _, p, _ in RULES])
def test_each_rule_accepts_its_bound_and_refuses_past_it(cls, name, at_bound, past_bound, rule):
    assert getattr(cls(**{name: at_bound}), name) == at_bound
    with pytest.raises(InvalidConfig) as info:
        cls(**{name: past_bound})
    assert info.value.problems == [f"{name} = {past_bound!r}: {rule}"]
    assert str(info.value) == f"{cls.__name__}.{name} = {past_bound!r}: {rule}"


def test_choices_of_the_demosaic_fields():
    """Both demosaic fields take LibRaw's algorithm names and nothing else (the annotation is the rule)."""
    for cls in (DecodeConfig, CamerasConfig):
        assert cls(demosaic="LINEAR").demosaic == "LINEAR"
        with pytest.raises(InvalidConfig, match=rf"^{cls.__name__}\.demosaic = 'fast': must be one of 'LINEAR', "):
            cls(demosaic="fast")


def test_yaml_overrides_of_a_stage_name_the_file_and_every_broken_rule():
    from stages.registry import PRESETS

    overrides = {"textures": {"atlas_faces": 3, "texture_size": 4}, "exports": {"colmap_points": 0},
                 "cameras": {"min_registered_fraction": 2.0}, "photometric": {"light_iterations": -1},
                 "relight": {"shading": {"f0": 1.5}}}
    with pytest.raises(InvalidConfig) as info:
        merge(PRESETS["test"], overrides, where="o.yaml")
    assert info.value.problems == ["textures.atlas_faces = 3: must be >= 4",  # in the order of the overrides
                                   "textures.texture_size = 4: must be >= 8",
                                   "exports.colmap_points = 0: must be >= 1",
                                   "cameras.min_registered_fraction = 2.0: must be in [0, 1]",
                                   "photometric.light_iterations = -1: must be >= 0",
                                   "relight.shading.f0 = 1.5: must be in [0, 1]"]
    with pytest.raises(ConfigError, match=r"o\.yaml\.cameras\.demosaic: 'fast' is not one of"):
        merge(PRESETS["test"], {"cameras": {"demosaic": "fast"}}, where="o.yaml")
