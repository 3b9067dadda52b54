"""bench/bench_projection.py: the stage seconds and exponents it takes from a bench_resolution report, the second
projection with the measured exponents, and where its GPU speed-up comes from (measured, given or assumed)."""
from __future__ import annotations

import json
import math

import pytest

from tests.unit.bench.test_bench_defaults import load_bench



@pytest.fixture(scope="module")
def projection():
    return load_bench("bench_projection")


def _row(width: int, floor: float, steps: list[tuple[str, dict[str, float], float]]) -> dict:
    return {"width": width, "height": width * 3 // 2, "pixels": width * (width * 3 // 2), "cameras": 32,
            "imports": {"cpu_s": floor},
            "steps": [{"through": through, "stages": stages, "cpu_s": cpu} for through, stages, cpu in steps]}


def _report() -> dict:
    small = _row(192, 2.0, [("decode", {"decode": 4.0}, 6.0), ("geometry", {"geometry": 100.0}, 152.0),
                            ("all", {}, 3.0)])
    large = _row(384, 2.5, [("decode", {"decode": 9.0}, 12.5), ("geometry", {"geometry": 120.0}, 162.5),
                            ("all", {}, 3.5)])
    return {"preset": "default", "quick": False, "rows": [small, large],
            "growth": {"fits": {"cpu decode": {"k": 0.9, "a": 1.0, "r2": 1.0},
                                "cpu geometry": {"k": 0.05, "a": 1.0, "r2": 1.0}}}}


def test_resolution_seconds_are_the_largest_widths_cpu_above_the_floor(projection):
    seconds, exponents, info = projection.resolution_seconds(_report())
    assert seconds == {"decode": 10.0, "geometry": 160.0}  # 12.5 - 2.5, 162.5 - 2.5; the publish step left out
    assert exponents == {"decode": 0.9, "geometry": 0.05}
    assert info["width"] == 384 and info["widths"] == [192, 384] and info["preset"] == "default"


def test_a_step_of_two_stages_shares_its_cpu_by_task_seconds(projection):
    report = _report()
    report["rows"][1]["steps"][0] = {"through": "decode", "stages": {"decode": 3.0, "plates": 1.0}, "cpu_s": 10.5}
    seconds, _, _ = projection.resolution_seconds(report)
    assert seconds["decode"] == pytest.approx(6.0) and seconds["plates"] == pytest.approx(2.0)


def test_one_width_gives_no_exponents_and_no_rows_is_an_error(projection):
    report = _report()
    report["rows"] = report["rows"][:1]
    assert projection.resolution_seconds(report)[1] == {}
    with pytest.raises(ValueError, match="no widths"):
        projection.resolution_seconds({"rows": []})


def test_measured_exponent_raises_only_the_pixel_part_of_the_factor(projection):
    # relight's factor is maps x views x lobes x shading samples; only the maps part (the pixels) takes the exponent.
    # Today's presets make the rest 2 x 2 x 1/4 = 1: the rule is given a part of 3 beside the pixels' here.
    rules = projection.factors(384 * 576)
    rule, factor, pixels = rules["relight"]
    assert rule == "relight" and factor == pytest.approx(pixels) and pixels > 1.0
    factor = 3.0 * pixels
    rules["relight"] = (rule, factor, pixels)
    result = projection.project({"relight": 10.0, "geometry": 100.0}, set(), rules, 1.0, 100.0, 0.0, 0.0, 0.0, 32,
                                {"relight": 0.5, "geometry": 0.05})
    row = result["stages"]["relight"]
    assert row["production_s"] == pytest.approx(10.0 * factor)
    assert row["production_s_measured_k"] == pytest.approx(10.0 * factor / pixels * math.sqrt(pixels))
    # the GPU stage keeps its sample rule, with or without exponents
    assert "production_s_measured_k" not in result["stages"]["geometry"]
    assert result["cpu_core_hours_measured_k"] < result["cpu_core_hours"]
    without = projection.project({"relight": 10.0}, set(), rules, 1.0, 100.0, 0.0, 0.0, 0.0, 32)
    assert without["cpu_core_hours_measured_k"] is None


def test_gpu_speedup_is_measured_given_or_assumed(projection, tmp_path):
    assert projection.gpu_speedup(tmp_path, None) == {"speedup": projection.ASSUMED_GPU_SPEEDUP,
                                                      "source": "assumed", "cpu_field_step_ms": None}
    cpu_only = {"quick": False, "rows": [{"device": "cpu", "field_step_ms": 250.0}]}
    (tmp_path / "bench_gpu.json").write_text(json.dumps(cpu_only))
    assumed = projection.gpu_speedup(tmp_path, None)
    assert assumed["source"] == "assumed" and assumed["cpu_field_step_ms"] == 250.0
    with_gpu = {"quick": False, "rows": cpu_only["rows"] + [{"device": "cuda", "name": "H200", "field_step_ms": 2.5,
                                                             "speedup_over_cpu_thread": 83.0}]}
    (tmp_path / "bench_gpu.json").write_text(json.dumps(with_gpu))
    measured = projection.gpu_speedup(tmp_path, None)
    assert measured["source"] == "measured" and measured["speedup"] == pytest.approx(83.0)
    assert projection.gpu_speedup(tmp_path, 40.0)["source"] == "given"


def test_relight_factors_count_the_shading_samples(projection, monkeypatch):
    """The production preset shades its relit views once a pixel and the default 2 x 2 times: the relight factor
    holds (1/2)^2, and shading the production views at 2 x 2 too multiplies it by 4; the relighting set's likewise."""
    import dataclasses

    from stages.numerics.novel_view import ViewShading
    from stages.registry import PRESETS

    production = PRESETS["production"]
    assert production.relight.shading.supersample == 1 and PRESETS["default"].relight.shading.supersample == 2
    once, set_once = projection.factors(1e6)["relight"][1], projection.relightset_factor()
    monkeypatch.setitem(PRESETS, "production", dataclasses.replace(
        production, relight=dataclasses.replace(production.relight, shading=ViewShading(supersample=2)),
        relightset=dataclasses.replace(production.relightset, shading=ViewShading(supersample=1))))
    assert projection.factors(1e6)["relight"][1] == pytest.approx(4 * once)
    assert projection.relightset_factor() == pytest.approx(set_once / 4)
