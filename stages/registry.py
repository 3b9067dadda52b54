"""The stage list, the pipeline config (one section per stage) and its presets, as code."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from pipeline.runner import ExecutionConfig
from pipeline.stage import Stage
from stages.cameras import CamerasConfig, CamerasStage
from stages.colour import ColourConfig, ColourStage
from stages.decode import DecodeConfig, DecodeStage
from stages.exports import ExportsConfig, ExportsStage
from stages.geometry import GeometryConfig, GeometryStage
from stages.lights import LightsConfig, LightsStage
from stages.materials import MaterialsConfig, MaterialsStage
from stages.numerics.sdf import SDF_PRESETS
from stages.diffuse_normals import DiffuseNormalsConfig, DiffuseNormalsStage
from stages.photometric import PhotometricConfig, PhotometricStage
from stages.plates import PlatesStage
from stages.numerics.novel_view import ViewShading
from stages.numerics.specular_normals import SpecularConfig
from stages.relight import RelightConfig, RelightStage
from stages.relightset import RelightSetConfig, RelightSetStage
from stages.stage_names import STAGE_NAMES
from stages.textures import TexturesConfig, TexturesStage

STAGE_CLASSES: tuple[type[Stage], ...] = (CamerasStage, ColourStage, LightsStage, PlatesStage, DecodeStage,
                                          PhotometricStage, GeometryStage, TexturesStage,
                                          MaterialsStage, DiffuseNormalsStage, RelightStage, RelightSetStage,
                                          ExportsStage)
if tuple(cls.name for cls in STAGE_CLASSES) != STAGE_NAMES:
    raise RuntimeError(f"stages.stage_names.STAGE_NAMES {STAGE_NAMES} does not list the registry's stages "
                       f"{tuple(cls.name for cls in STAGE_CLASSES)}: update it with the registry")

CODE_PACKAGES: tuple[str, ...] = ("stages", "artifacts", "calibration", "synthetic", "pipeline.codecs")
"""The project's packages whose code can change a stage's output: a stage's cache key holds the digests of its
module and of the modules under these that it imports. The engine (pipeline.stage, graph, store, config, runner),
the command line and manifests/ are left out: they decide what runs and where, not what a stage computes."""


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
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    """The normal-supervised neural SDF and its mesh."""
    textures: TexturesConfig = field(default_factory=TexturesConfig)
    """UV atlas and baked albedo/normal textures."""
    materials: MaterialsConfig = field(default_factory=MaterialsConfig)
    """Roughness texture by inverse rendering, occlusion and the occlusion-free albedo."""
    diffuse_normals: DiffuseNormalsConfig = field(default_factory=DiffuseNormalsConfig)
    """The released normal_diffuse and albedo_diffuse maps: the specular fit again with the materials' roughness
    per pixel, and the white-light albedo less the specular light it predicts."""
    relight: RelightConfig = field(default_factory=RelightConfig)
    """Novel views under HDR environments (renders/)."""
    relightset: RelightSetConfig = field(default_factory=RelightSetConfig)
    """The single-image relighting set (relight/ at the release root, manifests/relight_examples.parquet)."""
    exports: ExportsConfig = field(default_factory=ExportsConfig)
    """The action in other tools' formats: 8-bit sRGB images, nerfstudio transforms.json, a COLMAP model of
    the subject's surface points, the textured OBJ with its texture beside it and a GLB."""
    execution: ExecutionConfig = field(default_factory=ExecutionConfig)
    """Where and how tasks run; never part of a cache key."""


PRESETS: dict[str, PipelineConfig] = {
    # The embedded default capture is small (320 px wide), so full-size decoding is cheap.
    "default": PipelineConfig(),
    # Full-resolution 24 MP captures on a GPU: maps at half the sensor resolution are what the SDF uses. The relit
    # views shade one sample a pixel: supersampling's gain falls as the pixels shrink (on the default capture +0.17 dB
    # at 320 px wide, +0.12 at 640) and it costs 4 x the stage's CPU, about 35 CPU minutes an action at 3008 x 2008
    # (README); the relighting set's 512 px examples keep 2, as the default capture's views. The atlas keeps its
    # charts whole, the de-occlusion of the maps traces 256 directions and the SG fits run 300 iterations: the
    # cheaper settings the default preset takes for make dataset's minutes were measured at the default capture's
    # size only.
    "production": PipelineConfig(decode=DecodeConfig(demosaic="AHD", half_size=True),
                                 geometry=GeometryConfig(sdf=SDF_PRESETS["production"], mesh_resolution=1024,
                                                         face_budget=500_000, first_pass_iterations=0,
                                                         first_pass_mesh_resolution=0, deocclude_directions=256),
                                 textures=TexturesConfig(atlas_faces=100_000, texture_size=4096, max_views=4,
                                                         atlas_max_chart_area_m2=0.0),
                                 diffuse_normals=DiffuseNormalsConfig(occlusion_directions=256),
                                 materials=MaterialsConfig(texture_size=1024, occlusion_size=2048),
                                 relight=RelightConfig(novel_views=6, sg_lobes=64, fit_height=128, fit_iterations=300,
                                                       shading=ViewShading(supersample=1)),
                                 relightset=RelightSetConfig(size=512, sg_lobes=64, fit_height=128,
                                                             fit_iterations=300)),
    # Quick looks: cheapest demosaic, in-process execution, a short SDF schedule (no third pass: on the gate's
    # procedural capture 60 more steps took Chamfer 4.61 -> 3.57 mm but the relighting set 25.13 -> 24.47 dB).
    "fast": PipelineConfig(decode=DecodeConfig(demosaic="LINEAR"),
                           geometry=GeometryConfig(sdf=SDF_PRESETS["test"], mesh_resolution=256, face_budget=50_000,
                                                   deocclude_iterations=60, first_pass_iterations=0,
                                                   first_pass_mesh_resolution=0, fine_pixel_m=0.0,
                                                   third_pass_iterations=0),
                           textures=TexturesConfig(atlas_faces=10_000, texture_size=512),
                           materials=MaterialsConfig(max_views=8, occlusion_rays=32),
                           relight=RelightConfig(novel_views=2, sg_lobes=16,
                                                 shading=ViewShading(visibility_directions=128)),
                           relightset=RelightSetConfig(examples_per_action=2, size=128, sg_lobes=16,
                                                       shading=ViewShading(visibility_directions=128)),
                           execution=ExecutionConfig(scheduler="sync")),
    # The test suite's tiny captures (a few cameras, ~100 px): every stage runs, in seconds (no third SDF pass, as
    # "fast").
    "test": PipelineConfig(geometry=GeometryConfig(sdf=SDF_PRESETS["test"], min_views=4, mesh_resolution=96,
                                                   face_budget=20_000, previews=True, deocclude_iterations=60,
                                                   first_pass_iterations=0, first_pass_mesh_resolution=0,
                                                   fine_pixel_m=0.0, third_pass_iterations=0),
                           textures=TexturesConfig(atlas_faces=3_000, texture_size=256),
                           exports=ExportsConfig(colmap_points=5_000),
                           materials=MaterialsConfig(texture_size=64, max_views=4, median_neighbours=16,
                                                     occlusion_rays=16, occlusion_size=64),
                           relight=RelightConfig(environments=("procedural:sky", "procedural:studio"), novel_views=1,
                                                 sg_lobes=8, fit_height=16,
                                                 shading=ViewShading(visibility_directions=64)),
                           relightset=RelightSetConfig(examples_per_action=2, size=48, sg_lobes=8, fit_height=16,
                                                       environments=("procedural:sky", "procedural:studio"),
                                                       split_ratios=(0.5, 0.0, 0.5),
                                                       shading=ViewShading(visibility_directions=64,
                                                                           coverage_samples=2)),
                           execution=ExecutionConfig(scheduler="sync")),
}
# The test suite's accuracy gate (tests/integration/test_accuracy_gate.py: one action, 32 cameras, 128 px): the test
# preset with the two costliest parts of its run made cheaper, the per-pixel specular fit of diffuse_normals (3
# Levenberg-Marquardt steps, 64 occlusion directions) and the relit views (one environment), no previews.
PRESETS["gate"] = dataclasses.replace(
    PRESETS["test"],
    diffuse_normals=DiffuseNormalsConfig(fit=SpecularConfig(steps=3), occlusion_directions=64, previews=False),
    relight=dataclasses.replace(PRESETS["test"].relight, environments=("procedural:sky",), previews=False))


def build_stages(config: PipelineConfig, through: str | None = None) -> list[Stage]:
    """One instance per stage class, each given its config section; with ``through``, only that stage
    and what it needs upstream (e.g. ``through="photometric"`` leaves out the neural stages)."""
    classes = STAGE_CLASSES
    if through is not None:
        by_name = {cls.name: cls for cls in STAGE_CLASSES}
        if through not in by_name:
            raise ValueError(f"through={through!r}: no such stage; stages are {sorted(by_name)}")
        needed, todo = set(), [through]
        while todo:
            name = todo.pop()
            if name not in needed:
                needed.add(name)
                todo += list(by_name[name].requires)
        classes = tuple(cls for cls in STAGE_CLASSES if cls.name in needed)
    stages = []
    for cls in classes:
        section = cls.config_section or cls.name
        stages.append(cls(getattr(config, section), code_packages=CODE_PACKAGES))
    return stages


def config_sections(config: PipelineConfig) -> list[str]:
    return [f.name for f in dataclasses.fields(config)]
