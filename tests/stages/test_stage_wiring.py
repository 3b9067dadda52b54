"""Stage modules: the hand-checkable parts of their wiring."""
from __future__ import annotations

import numpy as np
import pytest

from stages.decode import scale_camera, transforms_json
from stages.photometric import contact_sheet

CAM = {"camera_id": "00007", "width": 320, "height": 480, "K": [[800.0, 0, 159.5], [0, 800.0, 239.5], [0, 0, 1]],
       "cam_from_world": [[0, 0, -1, 0.1], [0, -1, 0, 0.2], [-1, 0, 0, 3.0]]}


def test_half_size_camera_follows_the_pixel_centre_convention():
    half = scale_camera(CAM, half_size=True)
    assert (half["width"], half["height"]) == (160, 240)
    K = np.asarray(half["K"])
    assert K[0, 0] == 400.0 and K[1, 1] == 400.0
    # full-res pixel centres 0 and 1 (u = 0.5 between them) become half-res pixel 0: cx' = (cx - 0.5) / 2
    assert K[0, 2] == 79.5 and K[1, 2] == 119.5
    assert scale_camera(CAM, half_size=False) == CAM


def test_transforms_json_holds_world_from_cam():
    frame = transforms_json([CAM])["frames"][0]
    world_from_cam = np.asarray(frame["transform_matrix"])
    centre = world_from_cam[:3, 3]
    R, t = np.asarray(CAM["cam_from_world"])[:, :3], np.asarray(CAM["cam_from_world"])[:, 3]
    assert np.allclose(centre, -R.T @ t)  # camera centre in the world
    assert np.allclose(world_from_cam[3], [0, 0, 0, 1])
    assert frame["file_path"] == "full_on/00007.exr" and frame["fl_x"] == 800.0


def test_contact_sheet_tiles_row_major():
    pics = [np.full((2, 3, 3), i, np.uint8) for i in range(5)]
    sheet = contact_sheet(pics, columns=3)
    assert sheet.shape == (4, 9, 3)
    assert sheet[0, 3, 0] == 1 and sheet[2, 0, 0] == 3 and sheet[2, 3, 0] == 4 and sheet[2, 6, 0] == 0


def test_diffuse_normals_off_reads_and_writes_nothing(tmp_path):
    from pipeline.stage import StageContext
    from stages.photometric import DiffuseNormalsConfig, DiffuseNormalsStage, PhotometricStage

    # upstream folders that do not exist: a disabled stage must not look at them
    absent = {name: tmp_path / "absent" / name for name in DiffuseNormalsStage.requires}
    ctx = StageContext(stage="diffuse_normals", scope_id="A0000", session_id="S000", action_id="A0000",
                       out_dir=tmp_path / "out", upstream=absent, raw_inputs={}, rig={}, capture_root=tmp_path)
    stage = DiffuseNormalsStage(DiffuseNormalsConfig(enabled=False))
    assert stage.run_view(ctx, "00000") == {"disabled": True}
    assert not (tmp_path / "out").exists()
    # the photometric stage leaves the specular fit to this stage
    assert "normal_diffuse" not in PhotometricStage.outputs and "normal_diffuse" in DiffuseNormalsStage.outputs


def test_occlusion_configs_check_their_fields():
    from stages.geometry import GeometryConfig
    from stages.photometric import DiffuseNormalsConfig

    assert GeometryConfig().deocclude and DiffuseNormalsConfig().occlusion  # on by default
    for bad, match in (({"deocclude_iterations": -1}, "deocclude_iterations"),
                       ({"deocclude_directions": 8}, "deocclude_directions"),
                       ({"deocclude_min_visible": 1.0}, "deocclude_min_visible")):
        with pytest.raises(ValueError, match=match):
            GeometryConfig(**bad)
    for bad, match in (({"occlusion_directions": 4}, "occlusion_directions"),
                       ({"occlusion_min_visible": -0.1}, "occlusion_min_visible")):
        with pytest.raises(ValueError, match=match):
            DiffuseNormalsConfig(**bad)
