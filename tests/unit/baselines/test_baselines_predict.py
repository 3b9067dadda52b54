"""``ultrastage predict``: maps of any photos, their masks (beside them or in --masks, never photos themselves),
diffuse SH relighting, the contact sheet, and refused inputs."""
from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
from PIL import Image

from pipeline.codecs.exr import read_exr, write_exr
from pipeline.codecs.image import read_png
from ultrastage.baselines import predict
from ultrastage.baselines.train import CHECKPOINT_NAME
from ultrastage.cli import main
from stages.numerics import sh


@pytest.fixture()
def photos(fake_set, tmp_path):
    """Two test-split PNGs of the fake set (one cut to an odd size, given an alpha mask) and a JPEG."""
    folder = tmp_path / "photos"
    folder.mkdir()
    shutil.copy(fake_set / "relight" / "A0011_00" / "image.png", folder / "a.png")
    rgb = read_png(fake_set / "relight" / "A0012_01" / "image.png")[:61, :45]
    alpha = (read_png(fake_set / "relight" / "A0012_01" / "mask.png")[:61, :45] > 127).astype(np.uint8) * 255
    Image.fromarray(np.dstack([rgb, alpha])).save(folder / "b.png")
    Image.fromarray(rgb).save(folder / "c.jpg", quality=90)
    (folder / "notes.txt").write_text("not a photo")
    return folder


@pytest.fixture()
def environment(tmp_path):
    d = sh.equirect_directions(16, 32)
    env = (0.2 + 3.0 * np.clip(d[..., 1:2], 0, None)).repeat(3, axis=2).astype(np.float32)  # lit from above
    return write_exr(tmp_path / "envs" / "sky.exr", env, half=False)


def _ckpts(trained):
    return [str(trained[n] / CHECKPOINT_NAME) for n in ("albedonet", "normalnet")]


def test_predict_writes_maps_and_relit_images(trained, photos, environment, tmp_path):
    out = tmp_path / "out"
    a, n = _ckpts(trained)
    args = ["predict", "--checkpoint", a, "--checkpoint", n, "--images", str(photos), "--out", str(out),
            "--environment", str(environment), "--environment-rotation", "30"]
    assert main(args) == 0
    assert sorted(p.name for p in out.iterdir()) == ["a", "b", "c", "contact_sheet.png"]
    names = {"albedo.exr", "albedo.png", "normal.exr", "normal.png", "relit_sky.exr", "relit_sky.png"}
    assert {p.name for p in (out / "b").iterdir()} == names
    albedo = read_exr(out / "b" / "albedo.exr")
    normal = read_exr(out / "b" / "normal.exr")
    relit = read_exr(out / "b" / "relit_sky.exr")
    assert albedo.shape == (61, 45, 3) and relit.shape == (61, 45, 4)
    mask = relit[..., 3] > 0.5
    assert 0 < mask.sum() < mask.size and np.all(albedo[~mask] == 0)  # the alpha channel masked it
    assert np.all(np.isfinite(relit)) and relit[mask, :3].max() > 0
    np.testing.assert_allclose(np.linalg.norm(normal[mask], axis=-1), 1.0, atol=1e-3)
    # the relit image is albedo / pi * E(n) with the SH of the environment in the assumed camera frame
    coeffs = predict.environment_sh_camera(read_exr(environment), 30.0)
    expected = albedo[mask] / math.pi * sh.sh_irradiance(normal[mask].astype(np.float64), coeffs)
    np.testing.assert_allclose(relit[mask, :3], expected, rtol=2e-2, atol=2e-3)  # half-float albedo
    assert read_png(out / "c" / "albedo.png").shape == (61, 45, 3)


def test_camera_convention_up_is_minus_y():
    d = sh.equirect_directions(16, 32)
    env = (0.1 + np.clip(d[..., 1:2], 0, None)).repeat(3, axis=2).astype(np.float32)  # light from +y (up)
    e = sh.sh_irradiance(np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]]), predict.environment_sh_camera(env))
    assert np.all(e[0] > 3 * e[1])  # OpenCV y points down: the camera-frame normal facing up is -y


def test_relight_of_a_constant_environment_is_the_albedo_times_c():
    albedo = np.random.default_rng(0).uniform(0.1, 0.9, (5, 6, 3)).astype(np.float32)
    normal = np.random.default_rng(1).normal(size=(5, 6, 3)).astype(np.float32)
    mask = np.ones((5, 6), bool)
    mask[0] = False
    coeffs = predict.environment_sh_camera(np.full((32, 64, 3), 2.0, np.float32), 45.0)
    relit = predict.relight(albedo, normal, mask, coeffs)
    np.testing.assert_allclose(relit[mask], 2.0 * albedo[mask], rtol=3e-3)
    assert np.all(relit[~mask] == 0)


def _run(trained, images, out, *extra, ckpts=None):
    ckpts = _ckpts(trained) if ckpts is None else ckpts
    return main(["predict", *[x for c in ckpts for x in ("--checkpoint", c)], "--images", str(images),
                 "--out", str(out), *extra])


def test_bad_inputs_exit_2_writing_nothing(trained, photos, environment, tmp_path, capsys):
    out = tmp_path / "out"
    empty = tmp_path / "empty"
    empty.mkdir()
    corrupt = tmp_path / "broken.hdr"
    corrupt.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 8 +X 16\n\x02\x02")
    bad_photo = tmp_path / "badphotos"
    bad_photo.mkdir()
    (bad_photo / "x.png").write_bytes(b"\x89PNG broken")
    cases = [
        ((empty,), "no images"),
        ((photos, "--environment", str(empty)), "no environment maps"),
        ((photos, "--environment", str(tmp_path / "missing.hdr")), "environment map not found"),
        ((photos, "--environment", str(corrupt)), "broken.hdr"),
        ((bad_photo,), "x.png: cannot read image"),
    ]
    for (images, *extra), message in cases:
        assert _run(trained, images, out, *extra) == 2, message
        assert message in capsys.readouterr().err
        assert not out.exists(), message
    albedo_only = [str(trained["albedonet"] / CHECKPOINT_NAME)]
    assert _run(trained, photos, out, "--environment", str(environment), ckpts=albedo_only) == 2
    assert "needs an albedonet and a normalnet" in capsys.readouterr().err
    assert _run(trained, photos, out, ckpts=albedo_only * 2) == 2
    assert "a second albedonet checkpoint" in capsys.readouterr().err
    assert not out.exists()


# ------------------------------------------------------------------------------------------------ masks, sheet

def _mask_png(fake_set, example="A0012_01") -> np.ndarray:
    """(64, 64, 3) uint8 RGB mask (white = subject), as PIFu's samples store theirs."""
    return np.repeat(read_png(fake_set / "relight" / example / "mask.png")[..., None], 3, axis=2)


@pytest.fixture()
def masked_photos(fake_set, tmp_path):
    """In-the-wild layout: photos with ``NAME_mask.*`` beside them, one without, and a mask without a photo."""
    folder = tmp_path / "wild"
    folder.mkdir()
    rgb = read_png(fake_set / "relight" / "A0012_01" / "image.png")
    mask = _mask_png(fake_set)
    background = np.full_like(rgb, 200)  # a bright room behind the subject: the mask must take it out
    photo = np.where(mask > 127, rgb, background)
    Image.fromarray(photo).save(folder / "person.png")
    Image.fromarray(mask).save(folder / "person_mask.png")
    Image.fromarray(photo).save(folder / "jpeg.jpg", quality=95)
    Image.fromarray(mask).save(folder / "jpeg_mask.jpg", quality=95)
    Image.fromarray(photo).save(folder / "bare.jpg", quality=95)
    Image.fromarray(mask).save(folder / "orphan_mask.png")
    return folder, mask[..., 0] > 127


def test_masks_beside_photos_are_masks_never_photos(trained, masked_photos, tmp_path, capsys):
    folder, mask = masked_photos
    out = tmp_path / "out"
    result = predict.predict_folder(_ckpts(trained), folder, out, device="cpu")
    assert result.photos == ["bare.jpg", "jpeg.jpg", "person.png"]  # no *_mask file predicted
    assert sorted(p.name for p in out.iterdir()) == ["bare", "contact_sheet.png", "jpeg", "person"]
    assert result.masks == {"bare.jpg": "none", "jpeg.jpg": str(folder / "jpeg_mask.jpg"),
                            "person.png": str(folder / "person_mask.png")}
    for name in ("person", "jpeg"):
        albedo = read_exr(out / name / "albedo.exr")
        assert np.all(albedo[~mask] == 0) and np.all(albedo[mask].max(axis=-1) > 0), name
    bare = read_exr(out / "bare" / "albedo.exr")
    assert (bare.max(axis=-1) > 0).mean() > 0.95  # the whole frame, background included
    log = capsys.readouterr().out
    assert "note: orphan_mask.png: a mask (_mask name) with no photo orphan.* beside it; not predicted" in log
    assert ("note: bare.jpg: no mask (no bare_mask.png/.jpg beside it, no alpha channel): the whole frame is the "
            "subject") in log
    assert f"person.png: mask {folder / 'person_mask.png'}" in log
    assert [n.split(":")[0] for n in result.notes] == ["orphan_mask.png", "bare.jpg"]


def test_masks_from_a_masks_folder_by_the_photos_stems(trained, fake_set, photos, tmp_path, capsys):
    masks = tmp_path / "masks"
    masks.mkdir()
    mask = _mask_png(fake_set, "A0011_00")
    Image.fromarray(mask).save(masks / "a.png")  # same stem as photos/a.png
    Image.fromarray(mask[:61, :45]).save(masks / "c_mask.jpg", quality=95)  # NAME_mask is taken there too
    Image.fromarray(mask).save(masks / "z.png")  # no photo z
    out = tmp_path / "out"
    result = predict.predict_folder(_ckpts(trained)[:1], photos, out, device="cpu", masks=masks)
    assert result.masks == {"a.png": str(masks / "a.png"), "b.png": "alpha", "c.jpg": str(masks / "c_mask.jpg")}
    albedo = read_exr(out / "a" / "albedo.exr")
    assert np.all(albedo[mask[..., 0] <= 127] == 0) and albedo.max() > 0
    log = capsys.readouterr().out
    assert "note: b.png: no mask file; its alpha channel is the mask" in log
    assert f"note: {masks / 'z.png'}: in --masks but no photo z.* in {photos}; not used" in log


def test_bad_masks_exit_2_naming_the_file_writing_nothing(trained, fake_set, masked_photos, tmp_path, capsys):
    folder, mask = masked_photos
    out = tmp_path / "out"
    Image.fromarray(_mask_png(fake_set)[:40]).save(folder / "person_mask.png")
    assert _run(trained, folder, out) == 2
    assert "person_mask.png: mask is 64 x 40 px, its photo 64 x 64 px" in capsys.readouterr().err
    Image.fromarray(np.zeros((64, 64), np.uint8)).save(folder / "person_mask.png")
    assert _run(trained, folder, out) == 2
    assert "person_mask.png: mask is empty" in capsys.readouterr().err
    Image.fromarray((mask * 1).astype(np.uint8)).save(folder / "person_mask.png")  # a label image: 1 = subject
    np.testing.assert_array_equal(predict.read_mask(folder / "person_mask.png", (64, 64)), mask)
    Image.fromarray(_mask_png(fake_set)).save(folder / "person_mask.png")
    masks = tmp_path / "masks"
    masks.mkdir()
    Image.fromarray(_mask_png(fake_set)).save(masks / "person.png")
    assert _run(trained, folder, out, "--masks", str(masks)) == 2
    assert f"person_mask.png: a second mask of person.png (with {masks / 'person.png'})" in capsys.readouterr().err
    assert _run(trained, folder, out, "--masks", str(tmp_path / "nowhere")) == 2
    assert "nowhere: masks folder not found" in capsys.readouterr().err
    only_masks = tmp_path / "only_masks"
    only_masks.mkdir()
    Image.fromarray(_mask_png(fake_set)).save(only_masks / "x_mask.png")
    assert _run(trained, only_masks, out) == 2
    assert "no images (.png, .jpg, .jpeg) in the folder (only masks, named *_mask)" in capsys.readouterr().err
    assert not out.exists()


def test_contact_sheet_has_a_labelled_row_per_photo(trained, photos, environment, tmp_path):
    out = tmp_path / "out"
    result = predict.predict_folder(_ckpts(trained), photos, out, environment=environment, device="cpu")
    assert result.files[-1] == out / predict.CONTACT_SHEET_NAME
    sheet = read_png(out / predict.CONTACT_SHEET_NAME)
    t = predict.CONTACT_TILE
    assert sheet.shape == (3 * t, 4 * t, 3)  # photos a, b, c x (photo, albedo, normals, relit sky)
    for row, name in enumerate(("a", "b", "c")):
        for column, picture in enumerate(("albedo", "normal", "relit_sky"), start=1):
            tile = sheet[row * t:(row + 1) * t, column * t:(column + 1) * t]
            assert np.all(tile[3, 3] < 40) and tile[2:14, 2:60].max() > 200  # the label: light text, dark band
            png = read_png(out / name / f"{picture}.png")
            h, w = png.shape[:2]
            scale = t / max(h, w)
            nh, nw = round(h * scale), round(w * scale)
            top, left = (t - nh) // 2, (t - nw) // 2
            assert np.all(tile[32:, :left] == predict.CONTACT_BACKGROUND)  # grey beside a narrow picture
            if (h, w) == (64, 64):  # a: 4x nearest neighbour, pixel for pixel below the label
                np.testing.assert_array_equal(tile[32:], np.kron(png, np.ones((4, 4, 1), np.uint8))[32:])
            else:  # b and c (61 x 45): scaled to the tile's height, centred
                assert (nh, nw) == (t, 189) and left == 33
                assert np.any(tile[32:, left:left + nw] != predict.CONTACT_BACKGROUND)
    photo = read_png(photos / "a.png")  # no mask, no alpha: the photo as it is, the whole frame
    np.testing.assert_array_equal(sheet[32:t, :t], np.kron(photo, np.ones((4, 4, 1), np.uint8))[32:])
