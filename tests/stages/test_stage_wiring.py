"""Stage modules: the hand-checkable parts of their wiring."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from stages.conventions import srgb_png
from stages.decode import opencv_cam_from_world, scale_camera, transforms_json
from stages.previews import contact_sheet

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


def test_transforms_json_follows_nerfstudio_and_keeps_the_opencv_matrices():
    data = transforms_json([CAM])
    frame = data["frames"][0]
    assert data["camera_model"] == "OPENCV" and "transform_matrix" not in data  # the key names no string
    camera_to_world = np.asarray(frame["transform_matrix"])
    R, t = np.asarray(CAM["cam_from_world"])[:, :3], np.asarray(CAM["cam_from_world"])[:, 3]
    assert np.allclose(camera_to_world[:3, 3], -R.T @ t)  # camera centre in the world
    assert np.allclose(camera_to_world[3], [0, 0, 0, 1])
    # OpenGL axes: the camera looks along its -z; OpenCV's +z (the third row of R) is the viewing direction
    assert np.allclose(-camera_to_world[:3, 2], R[2]) and np.allclose(camera_to_world[:3, 1], -R[1])
    assert np.allclose(frame["cam_from_world_opencv"], CAM["cam_from_world"])
    assert np.allclose(np.asarray(frame["world_from_cam_opencv"]) @ np.diag([1, -1, -1, 1]), camera_to_world)
    assert np.allclose(opencv_cam_from_world(camera_to_world), CAM["cam_from_world"])
    assert frame["file_path"] == "full_on/00007.png" and frame["mask_path"] == "mask/00007.png"
    assert frame["fl_x"] == 800.0 and frame["cx"] == 160.0 and frame["cy"] == 240.0  # COLMAP/nerfstudio: +0.5
    assert frame["K"][0][2] == 159.5 and [frame[k] for k in ("k1", "k2", "p1", "p2")] == [0.0] * 4


def test_srgb_png_is_the_transfer_curve_without_exposure():
    from pipeline.codecs.image import srgb_decode

    linear = np.array([[[0.0, 0.0031308, 0.18], [0.5, 1.0, 3.0]]], np.float32)
    png = srgb_png(linear)
    assert png.dtype == np.uint8 and png[0, 1, 1] == 255 and png[0, 1, 2] == 255 and png[0, 0, 0] == 0
    assert np.allclose(srgb_decode(png[0, 0, 2] / 255.0), 0.18, atol=0.003)


def test_contact_sheet_tiles_row_major():
    pics = [np.full((2, 3, 3), i, np.uint8) for i in range(5)]
    sheet = contact_sheet(pics, columns=3)
    assert sheet.shape == (4, 9, 3)
    assert sheet[0, 3, 0] == 1 and sheet[2, 0, 0] == 3 and sheet[2, 3, 0] == 4 and sheet[2, 6, 0] == 0


def test_diffuse_normals_off_reads_and_writes_nothing(tmp_path):
    from pipeline.stage import StageContext
    from stages.diffuse_normals import DiffuseNormalsConfig, DiffuseNormalsStage
    from stages.photometric import PhotometricStage

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
    from stages.diffuse_normals import DiffuseNormalsConfig

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


def test_carve_pixels_are_the_masks_holes_the_mesh_spans_away_from_its_outline():
    from stages.numerics.sdf_mesh import carve_pixels

    hit = np.zeros((20, 20), bool)
    hit[4:16, 4:16] = True                      # the mesh's render: a 12 px square
    mask = hit.copy()
    mask[9:11, 9:11] = False                    # a hole in the mask the mesh spans
    mask[4:16, 4] = False                       # the mask's outline one column inside the mesh's
    carve = carve_pixels(mask, hit)
    expected = np.zeros_like(hit)
    expected[9:11, 9:11] = True
    np.testing.assert_array_equal(carve, expected)
    np.testing.assert_array_equal(carve_pixels(mask, hit, inset_px=0), hit & ~mask)
    assert not carve_pixels(hit, hit).any()
    with pytest.raises(ValueError, match="one"):
        carve_pixels(mask, hit[:10])


def test_second_pass_sample_weights_mark_where_the_mesh_misses_the_normals():
    from stages.geometry import GeometryConfig
    from stages.numerics.sdf_mesh import deoccluded_sdf_views, second_pass_views
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
    # a hole in the mask the floor spans gets the carving weight, and its count is said
    holed = dataclasses.replace(view, mask=view.mask.copy(), normal_valid=valid.copy())
    holed.mask[24:27, 24:27] = False
    holed.normal_valid[24:27, 24:27] = False
    (carved,), carved_stats = deoccluded_sdf_views([holed], floor_v, floor_f, directions=64, error_floor_deg=10.0,
                                                   carve_weight=90.0)
    # at weight 90 the 9 pixels would hold 810 / (810 + ~2000) of the weights: scaled down to the cap's share
    from stages.numerics.sdf_mesh import _CARVE_SHARE_MAX

    np.testing.assert_allclose(carved.sample_weight[10:20, 10:20], 20.0, atol=0.5)
    others = float(carved.sample_weight.sum() - carved.sample_weight[24:27, 24:27].sum())
    np.testing.assert_allclose(carved.sample_weight[24:27, 24:27],
                               _CARVE_SHARE_MAX / (1 - _CARVE_SHARE_MAX) * others / 9, rtol=1e-5)
    assert carved_stats["carve_pixels"] == 9.0 and carved_stats["carve_share"] == pytest.approx(_CARVE_SHARE_MAX)
    # under the cap the weight stays as given
    (light,), light_stats = deoccluded_sdf_views([holed], floor_v, floor_f, directions=64, error_floor_deg=10.0,
                                                 carve_weight=10.0)
    np.testing.assert_array_equal(light.sample_weight[24:27, 24:27], 10.0)
    assert light_stats["carve_share"] == pytest.approx(90.0 / (90.0 + others), rel=1e-4)
    (staged_holed,), _ = second_pass_views(GeometryConfig(deocclude_directions=64), [holed], floor_v, floor_f)
    np.testing.assert_array_equal(staged_holed.sample_weight, carved.sample_weight)
    (uncarved,), uncarved_stats = second_pass_views(GeometryConfig(deocclude_directions=64,
                                                                   second_pass_carve_weight=0.0),
                                                    [holed], floor_v, floor_f)
    assert np.all(uncarved.sample_weight[24:27, 24:27] == 0) and "carve_pixels" not in uncarved_stats
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


def test_released_normals_are_zero_where_the_stored_alpha_is_zero():
    from stages.numerics.photometric import normals_with_alpha

    normals = np.tile(np.array([0.0, 0.6, 0.8], np.float32), (2, 3, 1))
    alpha = np.array([[0.0, 1e-9, 0.2], [0.6, 1.0, 2e-7]], np.float32)  # 1e-9 is 0 in half float, 2e-7 is not
    out = normals_with_alpha(normals, alpha)
    assert out.shape == (2, 3, 4) and np.array_equal(out[..., 3], alpha)
    zero = alpha.astype(np.float16) == 0
    assert np.all(out[zero, :3] == 0) and zero.sum() == 2
    assert np.allclose(out[~zero, :3], [0.0, 0.6, 0.8])
    with pytest.raises(ValueError, match="normals_with_alpha"):
        normals_with_alpha(normals[..., :2], alpha)


def test_exr_headers_say_colour_space_content_and_units(tmp_path):
    from pipeline.codecs.exr import LINEAR_SRGB_CHROMATICITIES, read_exr, read_exr_header, write_exr
    from stages.exr_headers import EXR_HEADERS

    path = write_exr(tmp_path / "full_on.exr", np.full((2, 3, 3), 0.5, np.float32), header=EXR_HEADERS["full_on"])
    header = read_exr_header(path)
    assert np.allclose(header["chromaticities"], LINEAR_SRGB_CHROMATICITIES, atol=1e-6)
    assert "linear sRGB" in header["content"] and "clip level" in header["units"]
    assert header["units"] in header["comments"]
    assert np.allclose(read_exr(path), 0.5)
    normals = read_exr_header(write_exr(tmp_path / "n.exr", np.zeros((2, 3, 4), np.float32),
                                        header=EXR_HEADERS["normal_alpha"]))
    assert "chromaticities" not in normals and "alpha" in normals["content"]
    with pytest.raises(ValueError, match="set by the writer"):
        write_exr(tmp_path / "bad.exr", np.zeros((2, 2), np.float32), header={"compression": "none"})


def test_colmap_text_model_reads_in_pycolmap_and_projects_like_opencv(tmp_path):
    import pycolmap

    from stages.exports import colmap_cameras_txt, colmap_images_txt, colmap_points3d_txt, sample_surface

    vertices = np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0], [0, 0, 0.2]], float)
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    points, normals, uv = sample_surface(vertices, faces, vertices[:, :2], 50, seed=1)
    assert points.shape == (50, 3) and np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert np.all(points >= -1e-12) and np.all(points.sum(axis=1) <= 0.2 + 1e-9)  # on the tetrahedron
    (tmp_path / "cameras.txt").write_text(colmap_cameras_txt([CAM]))
    (tmp_path / "images.txt").write_text(colmap_images_txt([CAM]))
    (tmp_path / "points3D.txt").write_text(colmap_points3d_txt(points, np.full((50, 3), 200, np.uint8)))
    model = pycolmap.Reconstruction(str(tmp_path))
    assert model.num_points3D() == 50
    (image,) = model.images.values()
    assert image.name == "full_on/00007.png"
    P, K = np.asarray(CAM["cam_from_world"]), np.asarray(CAM["K"])
    x = K @ (P[:, :3] @ points[0] + P[:, 3])
    assert np.allclose(image.project_point(points[0]), x[:2] / x[2] + 0.5)  # COLMAP: pixel centres at +0.5


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


def test_schedule_for_footprint_raises_the_steps_of_finely_seen_subjects_only():
    from stages.geometry import GeometryConfig
    from stages.numerics.sdf_mesh import schedule_for_footprint

    cfg = GeometryConfig(first_pass_iterations=150, fine_pixel_m=0.004, fine_first_pass_iterations=600,
                         fine_iterations=1800)
    cfg = dataclasses.replace(cfg, sdf=dataclasses.replace(cfg.sdf, iterations=1500))
    assert schedule_for_footprint(cfg, 0.005) is cfg and schedule_for_footprint(cfg, 0.004) is cfg
    fine = schedule_for_footprint(cfg, 0.0011)
    assert (fine.first_pass_iterations, fine.sdf.iterations) == (600, 1800)
    assert dataclasses.replace(fine, first_pass_iterations=150, sdf=cfg.sdf) == cfg  # nothing else changes
    # never lowered; a first pass over the whole schedule (0) stays so
    long = dataclasses.replace(cfg, first_pass_iterations=900, sdf=dataclasses.replace(cfg.sdf, iterations=20000))
    assert schedule_for_footprint(long, 0.001) is long
    assert schedule_for_footprint(dataclasses.replace(cfg, first_pass_iterations=0), 0.001).first_pass_iterations == 0
    off = dataclasses.replace(cfg, fine_pixel_m=0.0)
    assert schedule_for_footprint(off, 1e-5) is off
    with pytest.raises(ValueError, match="pixel_m"):
        schedule_for_footprint(cfg, 0.0)
    # the presets with their own short schedules keep them
    from stages.registry import PRESETS
    assert all(PRESETS[name].geometry.fine_pixel_m == 0.0 for name in ("test", "fast", "gate"))
    assert PRESETS["default"].geometry.fine_pixel_m == 0.0045


def test_sdf_mesh_trains_the_fine_schedule_only_for_a_finely_seen_subject():
    import torch

    from stages.geometry import GeometryConfig
    from stages.numerics.sdf import SDF_PRESETS
    from stages.numerics.sdf_mesh import sdf_mesh
    from tests.unit.numerics.test_sdf import sphere_views

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        views = sphere_views(n=6, size=32)
        pixel_m = 2.0 / views[0].K[0, 0]  # the sphere's centre is 2 m along every optical axis
        sdf = dataclasses.replace(SDF_PRESETS["test"], iterations=20, hull_init_steps=10, log_every=5)
        base = GeometryConfig(sdf=sdf, first_pass_iterations=10, fine_first_pass_iterations=15, fine_iterations=25,
                              mesh_resolution=32, first_pass_mesh_resolution=32, deocclude_directions=16,
                              face_budget=2000)
        lines: list[str] = []
        coarse = sdf_mesh(views, dataclasses.replace(base, fine_pixel_m=pixel_m / 2), log=lines.append)
        assert coarse.iterations == (10, 20) and coarse.subject_pixel_m == pytest.approx(pixel_m, rel=1e-3)
        assert not any("per pixel" in line for line in lines)
        fine = sdf_mesh(views, dataclasses.replace(base, fine_pixel_m=pixel_m * 2), log=lines.append)
        assert fine.iterations == (15, 25) and fine.first_pass["stats"]["iterations"] == 15
        assert fine.result.stats["iterations"] == 25
        assert sum("SDF steps 15 + 25 instead of 10 + 20" in line for line in lines) == 1
        off = sdf_mesh(views, dataclasses.replace(base, fine_pixel_m=0.0))
        assert off.subject_pixel_m is None and off.iterations == (10, 20)
    finally:
        torch.set_num_threads(previous)


def test_pass_configs_give_each_pass_its_steps():
    from stages.geometry import GeometryConfig
    from stages.numerics.sdf_mesh import pass_configs
    from stages.numerics.sdf import SDF_PRESETS

    sdf = SDF_PRESETS["cpu"]
    first, second = pass_configs(GeometryConfig(sdf=sdf, first_pass_iterations=600))
    assert (first.iterations, second.iterations) == (600, sdf.iterations)
    assert first.importance_fraction == 0.0 and second.importance_fraction == GeometryConfig().second_pass_importance
    # 0: the first pass runs the whole schedule; a warm-up longer than a short first pass is capped to it
    first, _ = pass_configs(GeometryConfig(sdf=sdf, first_pass_iterations=0))
    assert first == sdf
    first, _ = pass_configs(GeometryConfig(sdf=sdf, first_pass_iterations=20))
    assert (first.iterations, first.warmup_iterations) == (20, 20)
    # continuation: the second pass starts at the final sharpness with every level on
    _, second = pass_configs(GeometryConfig(sdf=sdf, deocclude_iterations=300))
    assert (second.iterations, second.inv_s_start, second.coarse_to_fine) == (300, sdf.inv_s_end, 0.0)
    first, second = pass_configs(GeometryConfig(sdf=sdf, deocclude=False))
    assert first == sdf and second is None
    for bad in ({"first_pass_iterations": -1}, {"first_pass_mesh_resolution": -2}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            GeometryConfig(**bad)


def test_turned_share_counts_valid_pixels_turned_past_the_angle():
    from stages.numerics.sdf import SDFView
    from stages.numerics.sdf_mesh import turned_share

    size = 10
    up = np.tile(np.array([0.0, 1.0, 0.0], np.float32), (size, size, 1))

    def view(normals, valid):
        return SDFView(normals_world=normals, normal_valid=valid, mask=np.ones((size, size), bool), K=np.eye(3),
                       cam_from_world=np.eye(3, 4))

    def tilted(deg):
        a = np.radians(deg)
        return np.array([np.sin(a), np.cos(a), 0.0], np.float32)

    turned = up.copy()
    turned[0, :] = tilted(10.0)   # 10 pixels past 5 deg
    turned[1, :5] = tilted(3.0)   # 5 pixels under it
    turned[9, :] = tilted(40.0)   # 10 pixels past it, but not valid
    valid = np.ones((size, size), bool)
    valid[9, :] = False
    before, after = [view(up, valid)] * 2, [view(turned, valid), view(up, valid)]
    assert turned_share(before, after) == pytest.approx(10 / 180)
    assert turned_share(before, after, turn_deg=2.0) == pytest.approx(15 / 180)
    assert turned_share(before, before) == 0.0
    assert turned_share([view(up, np.zeros((size, size), bool))], [view(turned, np.zeros((size, size), bool))]) == 0.0
    with pytest.raises(ValueError, match="views"):
        turned_share(before, after[:1])


def test_on_pixel_lattice_keeps_the_valid_pixels_of_every_step_th_row_and_column():
    from stages.numerics.sdf_mesh import on_pixel_lattice

    valid = np.ones((5, 4), bool)
    valid[0, 2] = False
    views = [dataclasses.make_dataclass("V", ["normal_valid", "name"])(valid, "a")]
    (kept,) = on_pixel_lattice(views, 2)
    expected = np.zeros((5, 4), bool)
    expected[[0, 0, 2, 2, 4, 4], [0, 2, 0, 2, 0, 2]] = True
    expected[0, 2] = False  # not valid to start with
    np.testing.assert_array_equal(kept.normal_valid, expected)
    assert kept.name == "a" and views[0].normal_valid is valid and valid.sum() == 19  # the input untouched
    np.testing.assert_array_equal(on_pixel_lattice(views, 1)[0].normal_valid, valid)
    with pytest.raises(ValueError, match="step"):
        on_pixel_lattice(views, 0)


def test_a_third_pass_runs_only_when_the_second_meshs_deocclusion_turns_the_normals(monkeypatch):
    import torch

    import stages.numerics.sdf_mesh as sdf_mesh_module
    from stages.geometry import GeometryConfig
    from stages.numerics.sdf import SDF_PRESETS
    from tests.unit.numerics.test_sdf import sphere_views

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        views = sphere_views(n=6, size=32)
        sdf = dataclasses.replace(SDF_PRESETS["test"], iterations=20, hull_init_steps=10, log_every=5)
        cfg = GeometryConfig(sdf=sdf, first_pass_iterations=10, mesh_resolution=32, first_pass_mesh_resolution=32,
                             deocclude_directions=16, face_budget=2000, fine_pixel_m=0.0, third_pass_iterations=15)
        lines: list[str] = []
        # a lone sphere occludes nothing: both meshes de-occlude alike, no third pass
        plain = sdf_mesh_module.sdf_mesh(views, cfg, log=lines.append)
        assert plain.third_pass["turned_share"] < cfg.third_pass_turned_share and not plain.third_pass["ran"]
        assert plain.passes == 2 and plain.iterations == (10, 20)
        assert sum("no third pass" in line for line in lines) == 1
        read: list[tuple[list, list]] = []
        monkeypatch.setattr(sdf_mesh_module, "turned_share", lambda before, after: read.append((before, after)) or 0.5)
        import stages.numerics.sdf as sdf_module

        trained, train = [], sdf_module.train_sdf
        monkeypatch.setattr(sdf_module, "train_sdf", lambda v, *a, **k: trained.append(v) or train(v, *a, **k))
        meshes: list[tuple[int, np.ndarray, np.ndarray]] = []
        third = sdf_mesh_module.sdf_mesh(views, cfg, log=lines.append, on_mesh=lambda *m: meshes.append(m))
        # each pass's mesh was told, in order, the last one the published
        assert [m[0] for m in meshes] == [1, 2, 3]
        assert meshes[2][1] is third.vertices and meshes[2][2] is third.faces
        assert third.third_pass["ran"] and third.passes == 3 and third.iterations == (10, 20, 15)
        # the decision read every view, on the pixel lattice only
        (before, after), = read
        lattice = np.zeros((32, 32), bool)
        lattice[::2, ::2] = True
        assert len(before) == len(after) == 6
        for b, a, v in zip(before, after, views):
            np.testing.assert_array_equal(b.normal_valid, np.asarray(v.normal_valid, bool) & lattice)
            np.testing.assert_array_equal(a.normal_valid, b.normal_valid)
        # the third pass's views: every view once, in order (the decision's sample and the rest put together),
        # each with the second pass's sample weight
        assert [np.array_equal(a.cam_from_world, b.cam_from_world) for a, b in zip(trained[2], views)] == [True] * 6
        assert all(a.sample_weight is b.sample_weight for a, b in zip(trained[2], trained[1]))
        assert third.third_pass["second_pass"]["stats"]["iterations"] == 20
        assert sum("a third SDF pass of 15 steps" in line for line in lines) == 1
        assert np.all(np.isfinite(third.vertices)) and len(third.faces) > 0
        off = sdf_mesh_module.sdf_mesh(views, dataclasses.replace(cfg, third_pass_iterations=0))
        assert off.third_pass is None and off.iterations == (10, 20)
    finally:
        torch.set_num_threads(previous)
