"""bench/bench_sdf_sharpness.py's own helpers: the ``--mask-params`` parser (its quick run, with all three mask
kinds, is checked in test_bench_quick.py)."""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[3] / "bench"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCH))
    try:
        yield importlib.import_module("bench_sdf_sharpness")
    finally:
        sys.path.remove(str(BENCH))


def test_mask_params_parse_yaml_values(bench):
    assert bench.parse_mask_params("") == {}
    assert bench.parse_mask_params("close_radius=0, majority_radius=0.001,refine_edges=false") == {
        "close_radius": 0, "majority_radius": 0.001, "refine_edges": False}


def test_mask_params_refuse_unknown_fields_and_bad_values(bench):
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['closing'\]"):
        bench.parse_mask_params("closing=0")
    with pytest.raises(ValueError, match="not name=value"):
        bench.parse_mask_params("close_radius")
    with pytest.raises(ValueError):
        bench.parse_mask_params("close_radius=-1")  # PhotometricParams checks it (ge=0)
