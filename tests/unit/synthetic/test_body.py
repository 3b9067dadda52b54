"""Tests of the MakeHuman body shape blend (synthetic.body) and of shaped subjects."""
from __future__ import annotations

import gzip
import os
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import InputError
from synthetic import body, geometry

SHARED_DATA = Path(os.environ.get("ULTRASTAGE_SHARED_DATA",
                                  Path(__file__).resolve().parents[3].parent / "shared" / "data"))
MAKEHUMAN = SHARED_DATA / "meshes" / "makehuman_base.obj"
TARGETS = SHARED_DATA / "meshes" / "makehuman_targets"
needs_shared = pytest.mark.skipif(not TARGETS.is_dir(),
                                  reason=f"shared data not found ({TARGETS}); a fresh clone has no ../shared")


# --- weights (pure) ----------------------------------------------------------------------------------------

def test_default_params_weigh_the_average_universal_corners_and_the_young_ethnic_ones():
    weights = body.corner_weights(body.DEFAULT_PARAMS)
    expected = {"universal-female-young-averagemuscle-averageweight": 0.5,
                "universal-male-young-averagemuscle-averageweight": 0.5}
    expected |= {f"{e}-{g}-young": 1.0 / 6.0 for e in body.ETHNICS for g in body.GENDERS}
    assert weights.keys() == expected.keys()  # height 0.5 has no target
    for name, value in expected.items():
        assert weights[name] == pytest.approx(value, abs=1e-12)


def test_per_axis_weights_are_makehumans_piecewise_linear_ones():
    w = body.axis_weights(body.BodyParams(gender=0.3, age=0.75, muscle=0.75, weight=0.2, height=0.25))
    assert w["gender"] == pytest.approx({"female": 0.7, "male": 0.3})
    assert w["age"] == pytest.approx({"young": 0.5, "old": 0.5})
    assert w["muscle"] == pytest.approx({"min": 0.0, "average": 0.5, "max": 0.5})
    assert w["weight"] == pytest.approx({"min": 0.6, "average": 0.4, "max": 0.0})
    assert w["height"] == pytest.approx({"min": 0.5, "max": 0.0})


@pytest.mark.parametrize("seed", range(5))
def test_corner_weights_sum_to_one_per_family(seed):
    params = body.draw_body(np.random.default_rng(seed))
    weights = body.corner_weights(params)
    universal = sum(v for k, v in weights.items() if k.startswith("universal-"))
    height = sum(v for k, v in weights.items() if k.startswith("height/"))
    ethnic = sum(v for k, v in weights.items() if k.split("-")[0] in body.ETHNICS)
    assert universal == pytest.approx(1.0, abs=1e-12)
    assert ethnic == pytest.approx(1.0, abs=1e-12)
    assert height == pytest.approx(abs(2.0 * params.height - 1.0), abs=1e-12)
    assert all(v > 0 for v in weights.values())


def fake_targets(offsets: dict[str, tuple[int, tuple[float, float, float]]]) -> dict:
    """Every target name corner_weights can give, empty unless listed (name -> (vertex, offset))."""
    names = set()
    for seed in range(50):
        names |= set(body.corner_weights(body.draw_body(np.random.default_rng(seed))))
    names |= set(body.corner_weights(body.DEFAULT_PARAMS))
    out = {n: (np.zeros(0, np.int64), np.zeros((0, 3))) for n in names}
    for name, (vertex, d) in offsets.items():
        out[name] = (np.array([vertex]), np.array([d], float))
    return out


def test_blend_of_two_gender_corners_is_hand_computed():
    targets = fake_targets({"universal-female-young-averagemuscle-averageweight": (0, (1.0, 0.0, 0.0)),
                            "universal-male-young-averagemuscle-averageweight": (0, (0.0, 2.0, 0.0)),
                            "asian-male-young": (1, (0.0, 0.0, 3.0))})
    params = body.BodyParams(gender=0.3)
    out = body.blend_offsets(body.corner_weights(params), targets, 3)
    # vertex 0: 0.7 x female + 0.3 x male; vertex 1: asian 1/3 x male 0.3 x young 1
    np.testing.assert_allclose(out, [[0.7, 0.6, 0.0], [0.0, 0.0, 0.3], [0.0, 0.0, 0.0]], atol=1e-12)


def test_height_corner_weighs_by_every_axis():
    name = "height/male-old-maxmuscle-averageweight-maxheight"
    targets = fake_targets({name: (0, (0.0, 1.0, 0.0))})
    params = body.BodyParams(gender=0.8, age=0.9, muscle=0.6, weight=0.5, height=0.75)
    out = body.blend_offsets(body.corner_weights(params), targets, 1)
    assert out[0, 1] == pytest.approx(0.8 * 0.8 * 0.2 * 1.0 * 0.5, abs=1e-12)


def test_blend_offsets_refuses_missing_targets_and_outside_vertices():
    with pytest.raises(KeyError, match="targets missing"):
        body.blend_offsets({"nope": 1.0}, {}, 3)
    with pytest.raises(ValueError, match="outside"):
        body.blend_offsets({"a": 1.0}, {"a": (np.array([5]), np.ones((1, 3)))}, 3)


# --- specs ---------------------------------------------------------------------------------------------------

def test_spec_fixed_values_keep_makehuman_defaults_for_the_rest():
    params = body.body_from_spec("gender=0.2,weight=0.9")
    assert (params.gender, params.weight, params.muscle, params.age, params.height) == (0.2, 0.9, 0.5, 0.5, 0.5)
    assert (params.african, params.asian, params.caucasian) == pytest.approx((1 / 3, 1 / 3, 1 / 3))


def test_spec_ethnic_values_share_the_rest_equally():
    params = body.body_from_spec("african=0.5")
    assert (params.african, params.asian, params.caucasian) == pytest.approx((0.5, 0.25, 0.25))
    params = body.body_from_spec("caucasian=1")
    assert (params.african, params.asian, params.caucasian) == (0.0, 0.0, 1.0)


def test_random_spec_is_deterministic_and_keeps_fixed_values():
    a = body.body_from_spec("random,height=0.7", np.random.default_rng([0, 9, 3]))
    b = body.body_from_spec("random,height=0.7", np.random.default_rng([0, 9, 3]))
    c = body.body_from_spec("random,height=0.7", np.random.default_rng([0, 9, 4]))
    assert a == b and a != c and a.height == 0.7
    assert a.african + a.asian + a.caucasian == pytest.approx(1.0)
    for axis, (lo, hi) in body.RANDOM_RANGES.items():
        if axis != "height":
            assert lo <= getattr(a, axis) <= hi


@pytest.mark.parametrize("spec, message", [
    ("", "empty"), ("tall=1", "not 'random' nor NAME=VALUE"), ("gender=x", "not a number"),
    ("gender=0.1,gender=0.2", "given twice"), ("weight=1.5", r"in \[0, 1\]"), ("age=0.2", r"age = 0.2: must be in \[0.5, 1\]"),
    ("african=0.7,asian=0.6", "sum to 1")])
def test_bad_specs_say_what_is_wrong(spec, message):
    with pytest.raises(ValueError, match=message):
        body.body_from_spec(spec, np.random.default_rng(0))


def test_sim_config_refuses_a_bad_body_spec():
    from pipeline.config import InvalidConfig
    from synthetic import SimConfig

    with pytest.raises(InvalidConfig, match="body"):
        SimConfig(body="weight=2")
    assert "body" not in SimConfig().to_json() and SimConfig(body="random").to_json()["body"] == "random"


# --- files ---------------------------------------------------------------------------------------------------

def test_read_target_parses_comments_and_refuses_bad_lines(tmp_path):
    good = tmp_path / "good.target.gz"
    with gzip.open(good, "wt") as f:
        f.write("# a comment\n3 0.5 -1 2\n7 0 0 1e-3\n")
    indices, offsets = body.read_target(good)
    np.testing.assert_array_equal(indices, [3, 7])
    np.testing.assert_allclose(offsets, [[0.5, -1, 2], [0, 0, 1e-3]])
    empty = tmp_path / "empty.target.gz"
    with gzip.open(empty, "wt") as f:
        f.write("# nothing moves\n")
    assert body.read_target(empty)[1].shape == (0, 3)
    for name, text, message in (("short", "3 0.5 1\n", "not 4"), ("twice", "3 0 0 0\n3 1 1 1\n", "twice"),
                                ("word", "3 a 0 0\n", "not 'index dx dy dz'")):
        bad = tmp_path / f"{name}.target.gz"
        with gzip.open(bad, "wt") as f:
            f.write(text)
        with pytest.raises(InputError, match=message):
            body.read_target(bad)
    with pytest.raises(InputError, match="does not exist"):
        body.read_target(tmp_path / "missing.target.gz")


def test_loop_subdivision_carries_offsets_linearly():
    """shape_body subdivides the offsets on their own: Loop subdivision is linear in the positions."""
    rng = np.random.default_rng(1)
    vertices = geometry.fibonacci_sphere(40)
    from scipy.spatial import ConvexHull

    triangles = ConvexHull(vertices).simplices.astype(np.int64)
    offsets = rng.normal(0, 0.01, vertices.shape)
    moved, _, _ = geometry.loop_subdivide(vertices + offsets, triangles)
    base, tris, _ = geometry.loop_subdivide(vertices, triangles)
    carried, _, _ = geometry.loop_subdivide(offsets, triangles)
    np.testing.assert_allclose(moved, base + carried, atol=1e-12)


# --- the MakeHuman data (needs ../shared) --------------------------------------------------------------------

@needs_shared
def test_default_params_give_the_mean_of_the_young_ethnic_targets():
    n = sum(1 for line in open(MAKEHUMAN) if line.startswith("v "))
    out = body.makehuman_offsets(TARGETS, body.DEFAULT_PARAMS, n)
    expected = np.zeros((n, 3))
    for e in body.ETHNICS:
        for g in body.GENDERS:
            indices, offsets = body.read_target(TARGETS / f"{e}-{g}-young.target.gz")
            expected[indices] += offsets / 6.0
    np.testing.assert_allclose(out, expected, atol=1e-12)
    for g in body.GENDERS:  # the average universal corners are empty in MakeHuman's data
        assert len(body.read_target(TARGETS / f"universal-{g}-young-averagemuscle-averageweight.target.gz")[0]) == 0


@needs_shared
def test_shaped_subjects_follow_their_parameters():
    from synthetic.subject import load_base_subject, shape_body

    base = load_base_subject(str(MAKEHUMAN), 0)
    height = {}
    waist = {}
    for label, spec in (("thin", "weight=0"), ("heavy", "weight=1"), ("short", "height=0.3"),
                        ("tall", "height=0.7"), ("average", "gender=0.5")):
        offsets, landmarks = shape_body(base, body.body_from_spec(spec))
        v = base.vertices + offsets
        assert np.isfinite(v).all()
        height[label] = float(np.ptp(v[:, 1]))
        band = np.abs(v[:, 1] - landmarks["pelvis"][1] - 0.1) < 0.02  # the belly, away from the hands
        waist[label] = float(np.abs(v[band & (np.abs(v[:, 0]) < 0.25), 2] - landmarks["pelvis"][2]).max())
    # measured: belly depth thin 0.112, average 0.126, heavy 0.136 m; height short 1.513, average 1.659,
    # tall 1.948 m (the bounds leave ~40% of each difference as margin)
    assert waist["thin"] < waist["average"] - 0.008 and waist["heavy"] > waist["average"] + 0.006
    assert height["short"] < height["average"] - 0.09 and height["tall"] > height["average"] + 0.17
    assert height["thin"] == pytest.approx(height["average"], abs=0.01)
