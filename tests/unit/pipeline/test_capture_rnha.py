"""The public release layout's transforms.json reader (pipeline.capture_rnha): poses, intrinsics, scale/offset."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.capture_rnha import opencv_cam_from_world, read_transforms
from pipeline.errors import InputError

# A camera 3 m out on +z looking at the origin, +y up: its OpenGL axes are the world's.
C2W_ON_Z = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]
# By hand: OpenCV x right = world x, y down = world -y, z forward = world -z; t = -R C = (0, 0, 3).
CFW_ON_Z = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 3]]
# A camera 2 m out on +x looking at the origin, +y up: it looks along -x, its right is -z.
C2W_ON_X = [[0, 0, 1, 2], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]]
# By hand: rows x = (0, 0, -1), y = (0, -1, 0), z = (-1, 0, 0); t = -R (2, 0, 0) = (0, 0, 2).
CFW_ON_X = [[0, 0, -1, 0], [0, -1, 0, 0], [-1, 0, 0, 2]]


def _action(tmp_path: Path, frames: list[dict], **top) -> Path:
    folder = tmp_path / "act"
    for frame in frames:
        if frame.get("file_path"):
            path = folder / frame["file_path"]
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(b"jpeg")
    folder.mkdir(exist_ok=True)
    (folder / "transforms.json").write_text(json.dumps({"frames": frames, **top}))
    return folder / "transforms.json"


def _frame(cam: str, c2w, **extra) -> dict:
    return {"file_path": f"full_on/{cam}.jpg", "transform_matrix": c2w, "fl_x": 100.0, "fl_y": 101.0,
            "cx": 32.5, "cy": 48.5, "w": 64, "h": 96} | extra


def test_opengl_camera_to_world_becomes_the_hand_computed_opencv_cam_from_world():
    np.testing.assert_allclose(opencv_cam_from_world(C2W_ON_Z), CFW_ON_Z, atol=1e-12)
    np.testing.assert_allclose(opencv_cam_from_world(C2W_ON_X), CFW_ON_X, atol=1e-12)
    # the world origin is in front of the +x camera, 2 m along its optical axis, at the principal point
    point = np.asarray(CFW_ON_X)[:, :3] @ np.zeros(3) + np.asarray(CFW_ON_X)[:, 3]
    np.testing.assert_allclose(point, [0, 0, 2])


def test_the_conversion_inverts_what_a_release_writes():
    from stages.decode import opencv_cam_from_world as release_inverse
    from stages.decode import opengl_camera_to_world

    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    cam_from_world = np.hstack([R, rng.normal(size=(3, 1))])
    c2w = opengl_camera_to_world(cam_from_world)
    np.testing.assert_allclose(opencv_cam_from_world(c2w), cam_from_world, atol=1e-12)
    np.testing.assert_allclose(opencv_cam_from_world(c2w), release_inverse(c2w), atol=1e-12)


def test_a_scaled_or_mirrored_pose_is_refused():
    with pytest.raises(ValueError, match="orthonormal"):
        opencv_cam_from_world(np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="orthonormal"):
        opencv_cam_from_world(np.diag([-1.0, 1.0, 1.0, 1.0]))


def test_reader_gives_opencv_intrinsics_and_camera_ids(tmp_path):
    path = _action(tmp_path, [_frame("00000", C2W_ON_Z), _frame("00001", C2W_ON_X, k1=0.01, p2=-0.002)])
    read = read_transforms(path)
    cams = {c["camera_id"]: c for c in read.cameras}
    assert sorted(cams) == ["00000", "00001"]
    # cx, cy of instant-ngp have pixel centres at +0.5: OpenCV's are 0.5 less
    np.testing.assert_allclose(cams["00000"]["K"], [[100, 0, 32], [0, 101, 48], [0, 0, 1]])
    assert (cams["00000"]["width"], cams["00000"]["height"]) == (64, 96)
    np.testing.assert_allclose(cams["00001"]["cam_from_world"], CFW_ON_X, atol=1e-12)
    assert cams["00001"]["dist"] == [0.01, 0.0, 0.0, -0.002, 0.0]
    assert cams["00000"]["white_reference"] == [1.0, 1.0, 1.0]
    assert read.files["00001"] == path.parent / "full_on" / "00001.jpg"
    assert read.scale is None and read.ngp_box is None


def test_top_level_intrinsics_and_camera_angle_are_read(tmp_path):
    frames = [{"file_path": "full_on/00000", "transform_matrix": C2W_ON_Z}]  # no extension: .jpg is found
    path = _action(tmp_path, [], camera_angle_x=2 * math.atan(0.5 * 64 / 80.0), w=64, h=96)
    (path.parent / "full_on").mkdir()
    (path.parent / "full_on" / "00000.jpg").write_bytes(b"jpeg")
    path.write_text(json.dumps({"frames": frames, "camera_angle_x": 2 * math.atan(0.5 * 64 / 80.0), "w": 64, "h": 96}))
    cam = read_transforms(path).cameras[0]
    assert cam["camera_id"] == "00000"
    np.testing.assert_allclose(cam["K"], [[80, 0, 31.5], [0, 80, 47.5], [0, 0, 1]])  # centre when cx, cy absent


def test_scale_and_offset_describe_the_ngp_cube_and_do_not_move_the_cameras(tmp_path):
    plain = read_transforms(_action(tmp_path / "a", [_frame("00000", C2W_ON_Z), _frame("00001", C2W_ON_X)]))
    scaled = read_transforms(_action(tmp_path / "b", [_frame("00000", C2W_ON_Z), _frame("00001", C2W_ON_X)],
                                     scale=0.25, offset=[0.5, 0.25, 0.5]))
    assert [c["cam_from_world"] for c in scaled.cameras] == [c["cam_from_world"] for c in plain.cameras]
    assert scaled.scale == 0.25 and scaled.offset == [0.5, 0.25, 0.5]
    # p_ngp = 0.25 p + offset: the cube [0, 1]^3 is [-2, 2] x [-1, 3] x [-2, 2] in the world
    np.testing.assert_allclose(scaled.ngp_box, [[-2, -1, -2], [2, 3, 2]])
    scalar = read_transforms(_action(tmp_path / "c", [_frame("00000", C2W_ON_Z)], scale=0.5, offset=0.5))
    assert scalar.offset == [0.5, 0.5, 0.5]
    np.testing.assert_allclose(scalar.ngp_box, [[-1, -1, -1], [1, 1, 1]])
    default_offset = read_transforms(_action(tmp_path / "d", [_frame("00000", C2W_ON_Z)], scale=0.5))
    np.testing.assert_allclose(default_offset.ngp_box, [[-1, -1, -1], [1, 1, 1]])  # instant-ngp's 0.5


@pytest.mark.parametrize("top, frame_extra, message", [
    ({"scale": -1.0}, {}, "scale must be > 0"),
    ({"scale": "big"}, {}, "scale must be a finite number"),
    ({"offset": [0.5, 0.5]}, {}, "offset must be a number or"),
    ({}, {"fl_x": None, "fl_y": None}, "without intrinsics"),
    ({}, {"w": None}, "without intrinsics"),
    ({}, {"white_reference": [1, 0, 1]}, "white_reference must be > 0"),
    ({}, {"transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 300], [0, 0, 0, 1]]}, "read in metres"),
])
def test_bad_transforms_name_the_file_and_the_reason(tmp_path, top, frame_extra, message):
    frame = {k: v for k, v in (_frame("00000", C2W_ON_Z) | frame_extra).items() if v is not None}
    path = _action(tmp_path, [frame], **top)
    with pytest.raises(InputError, match=message) as info:
        read_transforms(path)
    assert str(path) in str(info.value)


def test_a_frame_that_names_no_file_is_an_error(tmp_path):
    path = _action(tmp_path, [_frame("00000", C2W_ON_Z)])
    (path.parent / "full_on" / "00000.jpg").unlink()
    with pytest.raises(InputError, match=r"file_path names no file .*full_on/00000.jpg") as info:
        read_transforms(path)
    assert str(path) in str(info.value)


def test_two_frames_of_one_camera_are_an_error(tmp_path):
    path = _action(tmp_path, [_frame("00000", C2W_ON_Z), _frame("00000", C2W_ON_X)])
    with pytest.raises(InputError, match="camera 00000 has two frames"):
        read_transforms(path)


def test_the_simulated_layouts_transforms_read_back_as_the_true_cameras(tmp_path):
    from synthetic.rnha import transforms_record

    cameras = [{"camera_id": "00000", "K": [[100, 0, 31.25], [0, 99, 47.75], [0, 0, 1]], "width": 64, "height": 96,
                "cam_from_world": CFW_ON_X}]
    folder = tmp_path / "sim"
    (folder / "full_on").mkdir(parents=True)
    (folder / "full_on" / "00000.jpg").write_bytes(b"jpeg")
    (folder / "transforms.json").write_text(json.dumps(transforms_record(cameras)))
    read = read_transforms(folder / "transforms.json")
    np.testing.assert_allclose(read.cameras[0]["K"], cameras[0]["K"], atol=1e-12)
    np.testing.assert_allclose(read.cameras[0]["cam_from_world"], CFW_ON_X, atol=1e-12)
    assert read.scale == pytest.approx(0.45 / 2.0) and read.offset == [0.5, 0.5, 0.5]
