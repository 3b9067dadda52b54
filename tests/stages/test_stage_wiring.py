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


def test_second_pass_sample_weights_mark_where_the_mesh_misses_the_normals():
    from stages.geometry import GeometryConfig, deoccluded_sdf_views, second_pass_views
    from stages.numerics.sdf import SDFView

    # a camera 2 m above an open floor (y = 0): nothing occludes it, so the de-occlusion keeps every normal and
    # the weight is the mesh's miss beyond the floor: 0 on the floor's normal, 30 - 10 = 20 on a tilted patch
    floor_v = np.array([[-3.0, 0.0, -3.0], [3.0, 0.0, -3.0], [3.0, 0.0, 3.0], [-3.0, 0.0, 3.0]])
    floor_f = np.array([[0, 2, 1], [0, 3, 2]])
    size, f, centre = 32, 40.0, np.array([0.0, 2.0, 0.0])
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    K = np.array([[f, 0.0, (size - 1) / 2], [0.0, f, (size - 1) / 2], [0.0, 0.0, 1.0]])
    normals = np.tile(np.array([0.0, 1.0, 0.0], np.float32), (size, size, 1))
    tilt = np.radians(30.0)
    normals[10:20, 10:20] = [np.sin(tilt), np.cos(tilt), 0.0]
    valid = np.ones((size, size), bool)
    valid[:, :4] = False
    view = SDFView(normals_world=normals, normal_valid=valid, mask=np.ones((size, size), bool), K=K,
                   cam_from_world=np.concatenate([R, (-R @ centre)[:, None]], axis=1))
    plain, _ = deoccluded_sdf_views([view], floor_v, floor_f, directions=64)
    assert plain[0].sample_weight is None
    (out,), stats = deoccluded_sdf_views([view], floor_v, floor_f, directions=64, error_floor_deg=10.0)
    weight = out.sample_weight
    assert weight.shape == (size, size) and weight.dtype == np.float32 and np.isfinite(weight).all()
    np.testing.assert_allclose(out.normals_world[valid], normals[valid], atol=1e-3)  # nothing occluded
    np.testing.assert_allclose(weight[10:20, 10:20], 20.0, atol=0.5)
    outside = valid.copy()
    outside[10:20, 10:20] = False
    assert np.all(weight[outside] == 0) and np.all(weight[~valid] == 0)
    assert stats["error_weighted_fraction"] == pytest.approx(100 / valid.sum())
    assert stats["error_mean_deg"] == pytest.approx(30.0 * 100 / valid.sum(), rel=0.02)
    # the stage asks for the weights only when it draws a share of the rays by them
    (staged,), _ = second_pass_views(GeometryConfig(deocclude_directions=64), [view], floor_v, floor_f)
    np.testing.assert_array_equal(staged.sample_weight, weight)
    (uniform,), _ = second_pass_views(GeometryConfig(deocclude_directions=64, second_pass_importance=0.0), [view],
                                      floor_v, floor_f)
    assert uniform.sample_weight is None
    # the stage's settings are checked
    assert GeometryConfig().second_pass_importance > 0
    for bad, match in (({"second_pass_importance": 1.0}, "second_pass_importance"),
                       ({"second_pass_error_floor_deg": -1.0}, "second_pass_error_floor_deg")):
        with pytest.raises(ValueError, match=match):
            GeometryConfig(**bad)


def test_contact_sheet_labels_each_tile_with_its_camera():
    """The normal sheets say which camera a tile is: each tile's top-left corner carries its label (light text
    on a dark band), the rest of the tile is the picture."""
    from pipeline.codecs.image import label_picture

    pics = [np.full((40, 80, 3), 128, np.uint8) for _ in range(3)]
    sheet = contact_sheet(pics, columns=2, labels=["cam 00000", "cam 00001", "cam 00002"])
    for r, c in ((0, 0), (0, 80), (40, 0)):
        corner = sheet[r:r + 16, c:c + 60]
        assert (corner > 200).all(axis=-1).sum() > 20 and (corner == 0).all(axis=-1).sum() > 100
        assert (sheet[r + 30:r + 40, c + 60:c + 80] == 128).all()
    # the labels differ as their texts do
    assert not np.array_equal(sheet[0:16, 0:60], sheet[0:16, 80:140])
    assert np.array_equal(label_picture(pics[0], "cam 00001"), sheet[0:40, 80:160])
    with pytest.raises(ValueError, match="2 labels for 3 pictures"):
        contact_sheet(pics, labels=["a", "b"])
