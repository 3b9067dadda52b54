"""Benches measure the stages as they are: default rows equal the stage defaults, no settings or private helpers
of their own. bench/ is not a package, so its modules are imported by path."""
from __future__ import annotations

import ast
import dataclasses
import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
BENCH = ROOT / "bench"
PROJECT_PACKAGES = ("pipeline", "stages", "calibration", "synthetic", "manifests", "evaluation")


def load_bench(name: str):
    """Import bench/<name>.py as a module, with bench/ on sys.path while it loads (its helpers' imports) and the
    module in sys.modules (its dataclasses look their module up there); sys.path is restored afterwards."""
    saved = list(sys.path)
    try:
        sys.path.insert(0, str(BENCH))
        spec = importlib.util.spec_from_file_location(f"bench_under_test_{name}", BENCH / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module
        spec.loader.exec_module(module)
    finally:
        sys.path[:] = saved
    return module


@pytest.fixture(scope="module")
def bench_materials():
    return load_bench("bench_materials")


@pytest.fixture(scope="module")
def bench_relight():
    return load_bench("bench_relight")


def test_materials_default_row_is_the_stage_default(bench_materials):
    from stages.materials import MaterialsConfig

    assert bench_materials.default_config() == MaterialsConfig()
    variants = bench_materials.variant_configs()
    label, default = variants[0]
    assert default == MaterialsConfig()
    assert f"{MaterialsConfig().max_views} views" in label
    # every other row changes exactly the fields its change names, from the stage's defaults
    changes = dict(bench_materials.VARIANT_CHANGES)
    for label, cfg in variants[1:]:
        differ = {f.name for f in dataclasses.fields(cfg) if getattr(cfg, f.name) != getattr(default, f.name)}
        assert differ == set(changes[label]), label
    assert len({cfg for _, cfg in variants}) == len(variants), "a variant repeats another row"
    # the sweeps hold the stage's value, so the default row is among their points
    base = MaterialsConfig()
    assert base.median_neighbours in bench_materials.sweep(bench_materials.MEDIAN_NEIGHBOURS_SWEEP,
                                                           base.median_neighbours)


def test_relight_default_row_is_the_stage_default(bench_relight):
    from stages.relight import RelightConfig

    stage = RelightConfig()
    assert bench_relight.default_config() == stage and bench_relight.CONFIG == stage
    shading = stage.shading
    assert bench_relight.DEFAULT == {"lobes": stage.sg_lobes, "shadows": shading.shadows,
                                     "directions": shading.visibility_directions, "normals": shading.normals,
                                     "albedo": "deoccluded" if shading.shadows else "photometric",
                                     "diffuse_ratio": True, "sources": "stage",
                                     "edges": "coverage" if shading.coverage_samples > 1 else "centre"}
    assert bench_relight.VARIANTS[0] == ("default", {})
    assert stage.sg_lobes in bench_relight.LOBES_SWEEP
    assert shading.visibility_directions in bench_relight.DIRECTIONS_SWEEP
    rows = [bench_relight.DEFAULT | change for _, change in bench_relight.VARIANTS]
    assert rows.count(bench_relight.DEFAULT) == 1, "a variant repeats the default row"


def _stage_config_fields() -> set[str]:
    """Every field name of every stage config, nested configs included."""
    from stages.registry import PipelineConfig

    sections = PipelineConfig()
    names, todo = set(), [getattr(sections, f.name) for f in dataclasses.fields(sections)]
    while todo:
        config = todo.pop()
        for f in dataclasses.fields(config):
            value = getattr(config, f.name)
            if dataclasses.is_dataclass(value):
                todo.append(value)
            else:
                names.add(f.name)
    return names


BENCH_FILES = sorted(BENCH.glob("*.py"))


@pytest.mark.parametrize("path", BENCH_FILES, ids=[p.stem for p in BENCH_FILES])
def test_benches_declare_no_setting_of_a_stage_and_import_no_private_helper(path):
    fields = _stage_config_fields()
    assert {"max_views", "f0", "sources", "fit_height", "depth_tolerance_m", "texture_size"} <= fields
    tree = ast.parse(path.read_text(), filename=str(path))
    constants = [t.id for node in tree.body if isinstance(node, (ast.Assign, ast.AnnAssign))
                 for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
                 if isinstance(t, ast.Name) and t.id.isupper()]
    shadowing = [name for name in constants if name.lower() in fields]
    assert not shadowing, f"{path.name} declares its own {shadowing}: derive them from the stage's config"
    private = [f"{node.module}.{alias.name}" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
               and (node.module or "").split(".")[0] in PROJECT_PACKAGES
               for alias in node.names if alias.name.startswith("_")]
    assert not private, f"{path.name} imports private helpers {private}"


def test_sdf_schedule_default_row_is_the_stage_default():
    from stages.geometry import GeometryConfig

    bench = load_bench("bench_sdf_schedule")
    base = GeometryConfig()
    for quick in (False, True):
        rows = bench.schedules(quick)
        assert rows[0] == (base.first_pass_iterations, base.sdf.iterations)
        assert len(set(rows)) == len(rows)
        # the footprint rule off, so that a capture seen finer than fine_pixel_m runs the steps asked
        assert bench.schedule_config(*rows[0]) == dataclasses.replace(base, fine_pixel_m=0.0)
    # a schedule changes only the two step counts
    other = bench.schedule_config(1800, 1800)
    assert other.sdf == dataclasses.replace(base.sdf, iterations=1800)
    assert dataclasses.replace(other, sdf=base.sdf, first_pass_iterations=base.first_pass_iterations,
                               fine_pixel_m=base.fine_pixel_m) == base
    # the Pareto front: b is beaten by a on both axes; c is slower but better
    rows = [{"cpu_s": 10, "chamfer_mm": 1.5}, {"cpu_s": 12, "chamfer_mm": 1.6}, {"cpu_s": 20, "chamfer_mm": 1.3}]
    assert bench.pareto(rows) == [True, False, True]


def test_textures_budgets_hold_the_stage_and_production_budgets():
    from stages.textures import TexturesConfig
    from stages.registry import PRESETS

    bench = load_bench("bench_textures")
    assert bench.default_config() == TexturesConfig()
    full, quick = bench.budgets(False), bench.budgets(True)
    assert full[0] == quick[0] == TexturesConfig().atlas_faces
    assert PRESETS["production"].textures.atlas_faces in full
    assert len(set(full)) == len(full) and len(set(quick)) == len(quick)
    areas, quick_areas = bench.chart_areas(False), bench.chart_areas(True)
    assert areas[0] == quick_areas[0] == TexturesConfig().atlas_max_chart_area_m2
    assert len(set(areas)) == len(areas) > 2 and len(set(quick_areas)) == len(quick_areas) == 2
