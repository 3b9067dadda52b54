"""The stage list, the pipeline config (one section per stage) and its presets, as code."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from pipeline.runner import ExecutionConfig
from pipeline.stage import Stage
from stages.cameras import CamerasConfig, CamerasStage
from stages.decode import DecodeConfig, DecodeStage, PlatesStage
from stages.lightcolour import ColourConfig, ColourStage, LightsConfig, LightsStage
from stages.photometric import PhotometricConfig, PhotometricStage

STAGE_CLASSES: tuple[type[Stage], ...] = (CamerasStage, ColourStage, LightsStage, PlatesStage, DecodeStage,
                                          PhotometricStage)


@dataclass(frozen=True)
class PipelineConfig:
    cameras: CamerasConfig = field(default_factory=CamerasConfig)
    """Where the cameras come from (the rig spec until calibration lands)."""
    colour: ColourConfig = field(default_factory=ColourConfig)
    """Per-camera colour matrices from the session's chart frames."""
    lights: LightsConfig = field(default_factory=LightsConfig)
    """The LED ratio model from the session's diffuse-sphere frames."""
    decode: DecodeConfig = field(default_factory=DecodeConfig)
    """Raw decoding (also used for the session's clean plates)."""
    photometric: PhotometricConfig = field(default_factory=PhotometricConfig)
    """Normals, alpha, albedo and masks."""
    execution: ExecutionConfig = field(default_factory=ExecutionConfig)
    """Where and how tasks run; never part of a cache key."""


PRESETS: dict[str, PipelineConfig] = {
    # The embedded default capture is small (320 px wide), so full-size decoding is cheap.
    "default": PipelineConfig(),
    # Full-resolution 24 MP captures: maps at half the sensor resolution are what the SDF uses.
    "production": PipelineConfig(decode=DecodeConfig(demosaic="AHD", half_size=True)),
    # Quick looks and tests: cheapest demosaic, in-process execution.
    "fast": PipelineConfig(decode=DecodeConfig(demosaic="LINEAR"),
                           execution=ExecutionConfig(scheduler="sync")),
}


def build_stages(config: PipelineConfig) -> list[Stage]:
    """One instance per stage class, each given its config section."""
    stages = []
    for cls in STAGE_CLASSES:
        section = cls.config_section or cls.name
        stages.append(cls(getattr(config, section)))
    return stages


def config_sections(config: PipelineConfig) -> list[str]:
    return [f.name for f in dataclasses.fields(config)]
