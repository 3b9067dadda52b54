"""The artifact facade: the work-store and release backends give the same typed products, and clear errors."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from manifests import asset_row, write_table
from pipeline.codecs.exr import write_exr
from pipeline.codecs.image import write_png
from artifacts.facade import ActionArtifacts
from manifests import release_artifacts
from artifacts.layout import PRODUCTS, RELEASE_KINDS, ArtifactWriter, released_files
from stages.decode import transforms_json

H, W = 6, 4
CALIBRATED = ("00000", "00001", "00002")
MAPPED = ("00000", "00001")  # 00002 is calibrated but has no photometric maps


def _camera(i: int) -> dict:
    angle = 0.3 * i
    rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    pose = np.concatenate([rotation, [[0.01 * i], [-0.02], [2.5]]], axis=1)
    return {"camera_id": f"{i:05d}", "K": [[5.0 + i, 0.0, 1.5], [0.0, 5.5, 2.5], [0.0, 0.0, 1.0]],
            "cam_from_world": pose.tolist(), "width": W, "height": H, "white_reference": [1.0, 1.0, 1.0]}


def _maps(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(i)
    normal_alpha = rng.uniform(-1, 1, (H, W, 4)).astype(np.float16).astype(np.float32)  # exact in half float
    normal_alpha[..., 3] = np.abs(normal_alpha[..., 3])
    mask = np.zeros((H, W), bool)
    mask[1:5, 1:3] = True
    albedo = rng.uniform(0, 1, (H, W, 3)).astype(np.float16).astype(np.float32)
    return normal_alpha, mask, albedo


@pytest.fixture
def sources(tmp_path: Path) -> tuple[ActionArtifacts, Path]:
    """The same action in a work store's upstream folders and in a release (``release/``, action A0000)."""
    records = [_camera(i) for i in range(len(CALIBRATED))]
    decode, photometric = tmp_path / "store" / "decode", tmp_path / "store" / "photometric"
    decode.mkdir(parents=True)
    (decode / "cameras.json").write_text(json.dumps({"camera_convention": "opencv", "cameras": records}))
    release = tmp_path / "release"
    action = release / "actions" / "A0000"
    action.mkdir(parents=True)
    (action / "transforms.json").write_text(json.dumps(transforms_json(records)))
    rows = [asset_row(release, action / "transforms.json", "transforms", "A0000")]
    for i, cam in enumerate(MAPPED):
        normal_alpha, mask, albedo = _maps(i)
        for root in (photometric, action):
            write_exr(root / "normal_alpha" / f"{cam}.exr", normal_alpha)
            write_png(root / "mask" / f"{cam}.png", mask)
            write_exr(root / "albedo" / f"{cam}.exr", albedo)
        rows += [asset_row(release, action / "normal_alpha" / f"{cam}.exr", "normal_alpha", "A0000", cam),
                 asset_row(release, action / "mask" / f"{cam}.png", "mask", "A0000", cam),
                 asset_row(release, action / "albedo" / f"{cam}.exr", "albedo", "A0000", cam)]
    write_table(release, "assets", rows)
    write_table(release, "actions", [dict(action_id="A0000", session_id="S000", subject="makehuman/test",
                                          status="ok", error=None, n_cameras=len(CALIBRATED), width=W, height=H,
                                          stages_run=2, stages_cached=0, seconds=1.0)])
    return ActionArtifacts({"decode": decode, "photometric": photometric}), release


def test_release_backend_reads_what_the_store_backend_reads(sources):
    store, release = sources
    released = release_artifacts(release, "A0000")
    assert list(store.cameras()) == list(released.cameras()) == list(MAPPED)
    assert sorted(store.calibrated_cameras()) == sorted(released.calibrated_cameras()) == list(CALIBRATED)
    for (cam_id, cam, normal_alpha, mask, valid), (cam_id_r, cam_r, normal_alpha_r, mask_r, valid_r) in zip(
            store.camera_maps(0.5), released.camera_maps(0.5), strict=True):
        assert cam_id == cam_id_r
        np.testing.assert_array_equal(cam.K, cam_r.K)
        np.testing.assert_array_equal(cam.cam_from_world, cam_r.cam_from_world)
        assert (cam.width, cam.height) == (cam_r.width, cam_r.height) == (W, H)
        expected_na, expected_mask, expected_albedo = _maps(int(cam_id))
        np.testing.assert_array_equal(normal_alpha, expected_na)
        np.testing.assert_array_equal(normal_alpha_r, expected_na)
        np.testing.assert_array_equal(mask, expected_mask)
        np.testing.assert_array_equal(mask_r, expected_mask)
        np.testing.assert_array_equal(valid, (expected_na[..., 3] > 0.5) & expected_mask)
        np.testing.assert_array_equal(valid_r, valid)
        np.testing.assert_array_equal(store.map("albedo", cam_id), expected_albedo)
        np.testing.assert_array_equal(released.map("albedo", cam_id), expected_albedo)
    assert cam.record["white_reference"] == [1.0, 1.0, 1.0]  # the store keeps the cameras.json record
    assert cam_r.record["file_path"] == f"full_on/{cam_id}.png"  # the release its transforms.json frame


def test_an_unknown_product_is_a_key_error_in_both_backends(sources):
    store, release = sources
    for artifacts in (store, release_artifacts(release, "A0000")):
        with pytest.raises(KeyError, match="unknown product 'normals'"):
            artifacts.map("normals", "00000")
        assert not artifacts.has("normals", "00000")


def test_a_product_the_source_cannot_hold(sources):
    store, release = sources
    with pytest.raises(KeyError, match="product 'mesh' comes from stage 'geometry', which is not upstream"):
        store.mesh()
    assert "plate" in PRODUCTS and "plate" not in RELEASE_KINDS
    with pytest.raises(KeyError, match="product 'plate' is not published in a release"):
        release_artifacts(release, "A0000").path("plate", "00000")


def test_a_missing_product_names_action_kind_and_file(sources):
    store, release = sources
    released = release_artifacts(release, "A0000")
    with pytest.raises(KeyError, match="action A0000, the action \\(no camera\\): no 'mesh' asset in the release"):
        released.mesh()
    with pytest.raises(FileNotFoundError, match="photometric artifact, camera 00002, albedo: file .*albedo/00002.exr "
                                                "not found"):
        store.map("albedo", "00002")
    (release / "actions" / "A0000" / "albedo" / "00001.exr").unlink()
    with pytest.raises(FileNotFoundError, match="action A0000, camera 00001, albedo: file .*00001.exr is listed in "
                                                "the assets table but missing on disk"):
        released.map("albedo", "00001")
    with pytest.raises(KeyError, match="action 'A0001' is not in the release"):
        release_artifacts(release, "A0001")


def test_a_camera_absent_from_the_maps(sources):
    store, release = sources
    released = release_artifacts(release, "A0000")
    for artifacts in (store, released):
        assert "00002" in artifacts.calibrated_cameras() and "00002" not in artifacts.cameras()
        assert not artifacts.has("normal_alpha", "00002")
    with pytest.raises(KeyError, match="action A0000, camera 00002: no 'normal_alpha' asset in the release"):
        released.exr("normal_alpha", "00002")
    with pytest.raises(FileNotFoundError, match="camera 00002, normal_alpha: file .* not found"):
        store.exr("normal_alpha", "00002")


def test_the_writer_gives_a_stage_its_own_products_only(tmp_path):
    writer = ArtifactWriter("photometric", tmp_path)
    assert writer.path("normal_alpha", "00003") == tmp_path / "normal_alpha" / "00003.exr"
    assert ArtifactWriter("relight", tmp_path).path("relit", "N000", environment="sky") == \
        tmp_path / "renders" / "N000" / "sky.exr"
    with pytest.raises(KeyError, match="product 'cameras' is written by stage 'decode', not 'photometric'"):
        writer.path("cameras")
    with pytest.raises(KeyError, match="unknown product"):
        writer.path("normals", "00000")


def test_every_released_product_is_a_product():
    assert set(RELEASE_KINDS) <= set(PRODUCTS)


def test_released_files_come_from_the_products_table(tmp_path):
    from stages.exports import RELEASED

    files = released_files("exports", tmp_path, RELEASED)
    assert [(rel, kind) for _, rel, kind, _ in files] == [
        ("mesh/textured.obj", "mesh_textured"), ("mesh/textured.mtl", "mesh_material"),
        ("mesh/textured.png", "mesh_texture"), ("mesh/textured.glb", "mesh_glb"),
        ("colmap/sparse/0/cameras.txt", "colmap_cameras_txt"), ("colmap/sparse/0/images.txt", "colmap_images_txt"),
        ("colmap/sparse/0/points3D.txt", "colmap_points3D_txt"), ("colmap/sparse/0/points3D.ply", "colmap_points3D_ply")]
    assert all(path == tmp_path / rel and camera is None for path, rel, _, camera in files)
    # an optional product is listed only when its file is there
    assert released_files("cameras", tmp_path, ("calibration_summary",), optional=("calibration_summary",)) == []
    (tmp_path / "calibration.json").write_text("{}")
    assert released_files("cameras", tmp_path, ("calibration_summary",), optional=("calibration_summary",)) == [
        (tmp_path / "calibration.json", "calibration.json", "calibration", None)]
    with pytest.raises(KeyError, match="written by stage 'exports', not 'cameras'"):
        released_files("cameras", tmp_path, ("export_mesh",))
    with pytest.raises(KeyError, match="a release does not hold it"):
        released_files("cameras", tmp_path, ("calibration_colmap",))


def test_released_files_list_a_per_camera_product_file_by_file(tmp_path):
    for camera in ("00001", "00000"):
        write_png(tmp_path / "full_on" / f"{camera}.png", np.zeros((2, 2), np.uint8))
    (tmp_path / "full_on" / "notes.txt").write_text("not a PNG: no product's path matches it")
    files = released_files("decode", tmp_path, ("full_on", "full_on_png"))
    # full_on has no EXR here: a per-camera product lists the files that are there, sorted, zero or more
    assert files == [(tmp_path / "full_on" / f"{c}.png", f"full_on/{c}.png", "full_on_png", c) for c in ("00000", "00001")]


def test_released_files_fill_the_kind_from_the_fields_and_take_only_the_values_given(tmp_path):
    for camera in ("N000", "N001"):
        for name in ("normal.exr", "sky.exr", "studio.exr"):
            (tmp_path / "renders" / camera).mkdir(parents=True, exist_ok=True)
            (tmp_path / "renders" / camera / name).write_bytes(b"")
    files = released_files("relight", tmp_path, ("render_normal", "relit"), fields={"environment": ("sky", "studio")})
    assert [(rel, kind, camera) for _, rel, kind, camera in files] == [
        ("renders/N000/normal.exr", "render_normal", "N000"), ("renders/N001/normal.exr", "render_normal", "N001"),
        ("renders/N000/sky.exr", "relit_sky", "N000"), ("renders/N000/studio.exr", "relit_studio", "N000"),
        ("renders/N001/sky.exr", "relit_sky", "N001"), ("renders/N001/studio.exr", "relit_studio", "N001")]
    # without the environments, relit's {environment} also matches the G-buffer's normal.exr
    assert ("renders/N000/normal.exr", "relit_normal") in [
        (rel, kind) for _, rel, kind, _ in released_files("relight", tmp_path, ("relit",))]


def test_each_released_product_is_published_by_one_stage_at_its_own_path():
    """The stages' published products (their RELEASED tuples) cover the kinds of RELEASE_KINDS once each; the
    textures stage's OBJ and MTL are left to the exports stage's copies (same kinds), so no mesh is published
    twice, and no two published products share a path."""
    from stages import (decode, diffuse_normals, exports, geometry, materials, photometric, relight, relightset,
                        textures)

    published = {"cameras": ("calibration_summary",), "decode": decode.RELEASED,
                 "photometric": photometric.RELEASED, "diffuse_normals": diffuse_normals.RELEASED,
                 "geometry": geometry.RELEASED, "textures": textures.RELEASED, "materials": materials.RELEASED,
                 "relight": relight.RELEASED_RENDERS + relight.RELEASED_PREVIEWS, "exports": exports.RELEASED,
                 "relightset": relightset.RELEASED}
    products = [product for stage_products in published.values() for product in stage_products]
    assert len(products) == len(set(products))
    assert all(PRODUCTS[product][0] == stage for stage, names in published.items() for product in names)
    assert set(RELEASE_KINDS) - set(products) == {"textured_mesh", "textured_material"}
    assert {RELEASE_KINDS[p] for p in ("textured_mesh", "textured_material")} == \
        {RELEASE_KINDS[p] for p in ("export_mesh", "export_material")}
    paths = [PRODUCTS[product][1] for product in products]
    assert len(paths) == len(set(paths))


def test_released_file_fills_the_fields_of_one_file(tmp_path):
    from artifacts.layout import released_file

    assert released_file("relightset", tmp_path, "relight_example_image_png", example="A0000_01") == (
        tmp_path / "relight" / "A0000_01" / "image.png", "relight/A0000_01/image.png", "relight_image_png", None)
    assert released_file("relight", tmp_path, "relit", "N000", environment="sky") == (
        tmp_path / "renders" / "N000" / "sky.exr", "renders/N000/sky.exr", "relit_sky", "N000")
    with pytest.raises(KeyError, match="a release does not hold it"):
        released_file("relightset", tmp_path, "relight_examples")


def test_normal_sheet_tiles_the_previews_written_at_the_tables_paths(tmp_path):
    from stages.previews import write_normal_sheet

    writer = ArtifactWriter("photometric", tmp_path)
    for value, camera in enumerate(("00000", "00001")):
        write_png(writer.path("normal_preview", camera), np.full((40, 50, 3), 10 * (value + 1), np.uint8))
    write_normal_sheet(writer, "normal_preview", "normals_sheet",
                       {"00000": {}, "00001": {}, "00002": {"missing": "no frames"}})
    from pipeline.codecs.image import read_png

    sheet = read_png(tmp_path / "previews" / "normals_sheet.png")
    assert sheet.shape == (40, 8 * 50, 3)  # one row of 8 columns; the missing camera has no tile
    # the tiles' bottom-right pixels (the labels are in their top-left corners)
    assert sheet[39, 49, 0] == 10 and sheet[39, 99, 0] == 20 and sheet[39, 149, 0] == 0


def test_writing_through_the_layout_keeps_the_readers_out_of_a_stage_key():
    """The cameras and colour stages write through artifacts.layout only: their keys' code records do not hold the
    facade's readers (nor the renderer load_relightable_asset imports), so editing those cannot rerun them."""
    from pipeline.hashing import code_digests
    from stages.registry import CODE_PACKAGES

    assert set(code_digests("artifacts.layout", CODE_PACKAGES)) == {"artifacts", "artifacts.layout"}
    for module in ("stages.cameras", "stages.colour"):
        modules = set(code_digests(module, CODE_PACKAGES))
        assert "artifacts.layout" in modules and "artifacts.facade" not in modules, module
    assert "artifacts.facade" in code_digests("stages.decode", CODE_PACKAGES)  # a stage that reads through it


RENDERER = {"stages.numerics.novel_view", "stages.numerics.gbuffer", "stages.numerics.learned_blend"}
"""The novel-view renderer's own modules (the SG and shadowing ones serve the specular fit and de-occlusion too)."""


@pytest.mark.parametrize("module", ["artifacts.facade", "stages.decode", "stages.photometric", "stages.geometry",
                                    "stages.lights", "stages.textures"])
def test_reading_through_the_facade_keeps_the_renderer_out_of_a_stage_key(module):
    """The relightable asset (and the renderer it imports) is in stages.relightable, which only the stages that
    render import: editing the renderer reruns relight and relightset, not decode, the SDF or the textures."""
    from pipeline.hashing import code_digests
    from stages.registry import CODE_PACKAGES

    assert not RENDERER & set(code_digests(module, CODE_PACKAGES))
    assert RENDERER <= set(code_digests("stages.relight", CODE_PACKAGES))


def test_materials_f0_from_the_store_record_and_from_the_release_config(sources, tmp_path):
    from pipeline.errors import InputError

    store, release = sources
    materials = tmp_path / "store" / "materials"
    materials.mkdir()
    (materials / "_SUCCESS.json").write_text(json.dumps({"record": {"config": {"f0": 0.03}}}))
    assert ActionArtifacts({**store.upstream, "materials": materials}).materials_f0() == 0.03
    with pytest.raises(KeyError, match="materials"):
        store.materials_f0()  # not upstream
    released = release_artifacts(release, "A0000")
    with pytest.raises(InputError, match="config.yaml: no materials.f0"):
        released.materials_f0()  # a release without its config
    (release / "config.yaml").write_text("materials:\n  f0: 0.05\n")
    assert released.materials_f0() == 0.05
    (release / "config.yaml").write_text("materials:\n  f0: 1.5\n")
    with pytest.raises(InputError, match="not a number in \\[0, 1\\]"):
        released.materials_f0()
