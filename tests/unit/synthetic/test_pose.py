"""Tests of subject posing (synthetic.pose, SimConfig.pose_variation) and of reading mesh files."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import InputError
from synthetic import SimConfig, geometry, pose, simulate, subject
from synthetic.simulate import action_pose, subject_extent

SHARED_DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data"
MAKEHUMAN = SHARED_DATA / "meshes" / "makehuman_base.obj"
needs_shared = pytest.mark.skipif(not MAKEHUMAN.is_file(),
                                  reason=f"shared data not found ({MAKEHUMAN}); a fresh clone has no ../shared")


# --- pure numerics ---------------------------------------------------------------------------------------

def test_rotation_and_pose_draws():
    r = pose.rotation([0.3, -1.0, 0.2], 37.0)
    assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0)
    assert np.allclose(pose.rotation([1, 0, 0], 90.0) @ [0, 1, 0], [0, 0, 1])  # right-handed
    zero = pose.draw_pose(np.random.default_rng(5), 0.0)
    assert set(zero) == set(pose.POSE_RANGES_DEG) and all(v == 0.0 for v in zero.values())
    full = pose.draw_pose(np.random.default_rng(5), 1.0)
    half = pose.draw_pose(np.random.default_rng(5), 0.5)
    for name, (lo, hi) in pose.POSE_RANGES_DEG.items():
        assert lo <= full[name] <= hi and np.isclose(half[name], 0.5 * full[name])
    with pytest.raises(ValueError, match="pose variation"):
        pose.draw_pose(np.random.default_rng(5), 1.5)
    with pytest.raises(ValueError, match="pose_variation"):
        SimConfig(pose_variation=-0.1)


def test_pose_draws_are_keyed_by_seed_and_action():
    base = subject.BaseSubject("makehuman", "m", None, 0.1, np.zeros((3, 3)), np.array([[0, 1, 2]]), None,
                               landmarks={})
    config = SimConfig(actions=3, pose_variation=1.0)
    first = action_pose(config, base, 1)
    assert first == action_pose(config, base, 1)
    assert first != action_pose(config, base, 2)
    assert first != action_pose(SimConfig(actions=3, pose_variation=1.0, seed=7), base, 1)
    assert action_pose(SimConfig(actions=3), base, 1) is None                 # variation 0
    unposable = subject.BaseSubject("obj", "o", None, 1.0, np.zeros((3, 3)), np.array([[0, 1, 2]]), None)
    assert action_pose(config, unposable, 1) is None and unposable.skeleton is None


# --- the MakeHuman skeleton (needs ../shared) -------------------------------------------------------------

@pytest.fixture(scope="module")
def makehuman() -> subject.BaseSubject:
    return subject.load_base_subject(str(MAKEHUMAN), 0)


@needs_shared
def test_skeleton_from_the_makehuman_joint_groups(makehuman):
    skeleton = makehuman.skeleton
    lm = skeleton.landmarks
    assert lm["l_shoulder"][0] > 0.1 and lm["r_shoulder"][0] < -0.1                # left is +x
    assert lm["head_top"][1] > lm["neck"][1] > lm["chest"][1] > lm["pelvis"][1] > lm["l_knee"][1]
    assert np.allclose(skeleton.weights.sum(axis=1), 1.0) and skeleton.weights.min() >= 0.0
    dominant = skeleton.weights.argmax(axis=1)
    assert set(np.unique(dominant)) == set(range(len(pose.BONES)))
    # smooth: somewhere round every joint a vertex is shared by the bone and its parent
    for bone, parent in pose.PARENTS.items():
        if parent is not None:
            b, p = pose.BONES.index(bone), pose.BONES.index(parent)
            both = (skeleton.weights[:, b] > 0.3) & (skeleton.weights[:, p] > 0.3)
            assert both.any(), bone


@needs_shared
def test_zero_pose_is_the_rest_mesh_and_variation_zero_changes_nothing(makehuman):
    rest_angles = {name: 0.0 for name in pose.POSE_RANGES_DEG}
    posed = pose.pose_vertices(makehuman.vertices, makehuman.skeleton, rest_angles)
    assert np.allclose(posed, makehuman.vertices, atol=1e-12)
    config = SimConfig(actions=2)
    unposed = subject.make_action_subject(makehuman, np.random.default_rng([0, 4, 1]), 1, 0.004, 3,
                                          action_pose(config, makehuman, 1))
    today = subject.make_action_subject(makehuman, np.random.default_rng([0, 4, 1]), 1, 0.004, 3)
    assert unposed.pose_deg is None
    assert np.array_equal(unposed.vertices_world, today.vertices_world)
    assert np.array_equal(unposed.vertices_world, unposed.vertices_rest @ geometry.yaw_matrix(unposed.yaw_rad).T)
    assert subject_extent(config, makehuman) == (makehuman.radius_xz, makehuman.y_range)


@needs_shared
def test_posed_limbs_move_the_torso_stays(makehuman):
    skeleton, rest = makehuman.skeleton, makehuman.vertices
    w = skeleton.weights
    torso = w[:, pose.BONES.index("torso")] > 1 - 1e-9
    l_hand = w[:, pose.BONES.index("l_forearm")] > 0.99
    l_hand &= np.linalg.norm(rest - skeleton.landmarks["l_wrist"], axis=1) < 0.05
    r_foot = (w[:, pose.BONES.index("r_shin")] > 0.99) & (rest[:, 1] < skeleton.landmarks["r_ankle"][1])
    assert torso.sum() > 100 and l_hand.sum() > 10 and r_foot.sum() > 10
    # the conventions: swing forward takes the hand to +z, raise lifts it, knee bend takes the foot back
    moved = pose.pose_vertices(rest, skeleton, {"l_shoulder_swing": 45.0})
    assert (moved - rest)[l_hand, 2].mean() > 0.1 and np.abs(moved - rest)[torso].max() < 1e-6
    raised = pose.pose_vertices(rest, skeleton, {"l_shoulder_raise": 30.0})
    assert (raised - rest)[l_hand, 1].mean() > 0.1
    bent = pose.pose_vertices(rest, skeleton, {"r_knee_bend": 45.0})
    assert (bent - rest)[r_foot, 2].mean() < -0.1
    # drawn poses at variation 1: wrists move by many centimetres, the torso core not at all
    config = SimConfig(actions=4, pose_variation=1.0)
    for action_index in range(4):
        angles = action_pose(config, makehuman, action_index)
        posed = pose.pose_vertices(rest, skeleton, angles)
        assert np.all(np.isfinite(posed))
        assert np.linalg.norm(posed - rest, axis=1)[l_hand].mean() > 0.03, angles
        assert np.abs(posed - rest)[torso].max() < 1e-6
    # the cameras frame the reach of every pose the variation allows: it holds the drawn ones
    radius, (y_min, y_max) = subject_extent(config, makehuman)
    assert radius > makehuman.radius_xz + 0.05 and y_min <= makehuman.y_range[0] and y_max >= makehuman.y_range[1]
    for action_index in range(20):
        posed = pose.pose_vertices(rest, skeleton, action_pose(config, makehuman, action_index))
        assert np.sqrt(posed[:, 0] ** 2 + posed[:, 2] ** 2).max() <= radius + 0.01
        assert y_min - 0.01 <= posed[:, 1].min() and posed[:, 1].max() <= y_max + 0.01


@needs_shared
def test_posed_action_subject_normals_faces_and_truth_record(makehuman, tmp_path):
    angles = action_pose(SimConfig(actions=2, pose_variation=1.0), makehuman, 0)
    posed = subject.make_action_subject(makehuman, np.random.default_rng(3), 0, 0.004, 0, angles)
    unposed = subject.make_action_subject(makehuman, np.random.default_rng(3), 0, 0.004, 0)
    assert posed.pose_deg == angles and posed.triangles is makehuman.triangles
    assert np.array_equal(posed.vertices_rest, unposed.vertices_rest)   # materials follow the surface
    assert not np.allclose(posed.vertices_world, unposed.vertices_world)
    assert np.all(np.isfinite(posed.vertices_world)) and np.all(np.isfinite(posed.normals_world))
    assert np.allclose(np.linalg.norm(posed.normals_world, axis=1), 1.0, atol=1e-6)
    # a whole (tiny) capture: truth.json records the angles, mesh.ply is the posed mesh
    config = SimConfig(actions=1, width=24, n_cameras=1, n_leds=32, subdivisions=0, background=False,
                       noise=False, supersample=1, pose_variation=1.0)
    out = simulate(tmp_path / "cap", config)
    truth = json.loads((out / "ground_truth" / "A0000" / "truth.json").read_text())
    record = truth["subject"]["pose"]
    assert record["variation"] == 1.0 and set(record["angles_deg"]) == set(pose.POSE_RANGES_DEG)
    drawn = action_pose(config, makehuman, 0)
    assert all(abs(record["angles_deg"][k] - v) < 1e-3 for k, v in drawn.items())
    from synthetic.relight import _read_ply_vertices

    stored = _read_ply_vertices(out / "ground_truth" / "A0000" / "mesh.ply")
    assert stored.shape == (len(makehuman.vertices), 3) and np.all(np.isfinite(stored))
    rest_world = makehuman.vertices @ geometry.yaw_matrix(np.radians(truth["subject"]["yaw_deg"])).T
    assert np.abs(stored - rest_world).max() > 0.05                     # posed, not the rest A-pose


# --- mesh files ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("suffix", ["ply", "glb"])
def test_mesh_files_read_with_trimesh(tmp_path, suffix):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=40.0)     # centimetres -> scaled to metres
    sphere.apply_translation([5.0, 80.0, 0.0])
    path = tmp_path / f"ball.{suffix}"
    sphere.export(path)
    base = subject.load_base_subject(str(path), 0)
    assert base.kind == "mesh" and base.name == "mesh/ball" and base.corner_uvs is None and base.skeleton is None
    assert len(base.vertices) == len(sphere.vertices) and len(base.triangles) == len(sphere.faces)
    assert np.isclose(base.units_m, 0.01)
    assert np.allclose(base.vertices.max(axis=0), 0.4, atol=0.02)       # metres, centred
    assert np.allclose(base.vertices.min(axis=0), -0.4, atol=0.02)
    regions = subject.region_of(base, base.vertices)
    assert np.all(regions == subject.SKIN)                               # the procedural skin albedo


def test_unreadable_mesh_files_are_refused_naming_the_file(tmp_path, capsys):
    corrupt = tmp_path / "corrupt.glb"
    corrupt.write_bytes(b"glTF\x02\x00\x00\x00garbage that is not a binary glTF")
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"")
    points = tmp_path / "points.ply"
    points.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                      "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    for path in (corrupt, empty, points):
        with pytest.raises(InputError, match=str(path.name)):
            subject.load_base_subject(str(path), 0)
    with pytest.raises(InputError, match="missing.ply"):
        subject.resolve_mesh(str(tmp_path / "missing.ply"))
    from ultrastage.cli import main

    code = main(["simulate", "--out", str(tmp_path / "out"), "--mesh", str(corrupt), "--pose-variation", "0.5"])
    assert code == 2 and "corrupt.glb" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["corrupt.glb", "empty.ply", "points.ply"]  # nothing written
    code = main(["simulate", "--out", str(tmp_path / "out"), "--pose-variation", "2"])
    assert code == 2 and "pose_variation" in capsys.readouterr().err


@needs_shared
def test_fold_amplitude_zero_leaves_the_clothes_unfolded_and_every_other_draw_alike(makehuman, tmp_path, monkeypatch,
                                                                                    capsys):
    import synthetic
    from synthetic.simulate import action_subject
    from ultrastage.cli import main

    folded = action_subject(SimConfig(mesh=str(MAKEHUMAN)), makehuman, 0)
    flat = action_subject(SimConfig(mesh=str(MAKEHUMAN), fold_amplitude_m=0.0), makehuman, 0)
    yawed = makehuman.vertices @ geometry.yaw_matrix(flat.yaw_rad).T
    assert flat.yaw_rad == folded.yaw_rad and flat.skin_name == folded.skin_name
    assert np.allclose(flat.vertices_rest, makehuman.vertices, atol=1e-12)
    assert np.allclose(flat.vertices_world, yawed, atol=1e-12)
    moved = np.linalg.norm(folded.vertices_rest - makehuman.vertices, axis=1)
    assert 0.002 < moved.max() <= 0.005 + 1e-9    # the default 4 mm peak, drawn within x0.75-1.25
    # the command line's --fold-amplitude reaches the simulator's config, and a negative one is refused
    seen = {}
    monkeypatch.setattr(synthetic, "simulate", lambda out, config, **kw: seen.setdefault("config", config))
    monkeypatch.setattr("pipeline.store.swap_into_place", lambda tmp, out: None)
    assert main(["simulate", "--out", str(tmp_path / "out"), "--fold-amplitude", "0"]) == 0
    assert seen["config"].fold_amplitude_m == 0.0
    assert main(["simulate", "--out", str(tmp_path / "out"), "--fold-amplitude", "-0.001"]) == 2
    assert "fold_amplitude_m" in capsys.readouterr().err
