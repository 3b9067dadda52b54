"""``ultrastage predict``: maps of any photos, diffuse SH relighting, and refused inputs."""
from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
from PIL import Image

from pipeline.codecs.exr import read_exr, write_exr
from pipeline.codecs.image import read_png
from stages.baselines import predict
from stages.baselines.train import CHECKPOINT_NAME
from stages.cli import main
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
    assert sorted(p.name for p in out.iterdir()) == ["a", "b", "c"]
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
