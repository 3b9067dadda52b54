"""Relight stage helpers: environment lookup (files, names, procedural, fallback, bad files), labels,
novel cameras, and the stage's config checks."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.codecs.exr import write_exr
from pipeline.config import merge
from pipeline.errors import ConfigError, InputError
from stages.environments import environment_label, find_environment, load_environment, raw_environment_inputs
from artifacts.camera import Camera
from stages.numerics.novel_view import ViewShading
from stages.relight import RelightConfig, novel_cameras
from synthetic.rig import look_at


def test_labels_are_file_name_safe():
    assert environment_label("procedural:sky") == "procedural_sky"
    assert environment_label("/data/hdri/studio_small_03_1k.hdr") == "studio_small_03_1k"
    assert environment_label("my env (2).exr") == "my_env__2_"


def test_find_by_path_by_name_in_hdri_dirs_and_capture(tmp_path, monkeypatch):
    env = np.full((8, 16, 3), 0.5, np.float32)
    hdri = tmp_path / "hdri"
    write_exr(hdri / "room.exr", env)
    write_exr(tmp_path / "capture" / "environments" / "yard.exr", env)
    monkeypatch.setenv("ULTRASTAGE_HDRI", str(hdri))
    assert find_environment(str(hdri / "room.exr")) == hdri / "room.exr"
    assert find_environment("room") == hdri / "room.exr"
    assert find_environment("yard", tmp_path / "capture") == tmp_path / "capture" / "environments" / "yard.exr"
    assert find_environment("yard") is None  # not without the capture
    assert find_environment("procedural:sky") is None


def test_load_procedural_file_and_fallback(tmp_path):
    sky, how = load_environment("procedural:sky", None)
    assert how == "procedural" and sky.shape[1] == 2 * sky.shape[0] and np.isfinite(sky).all()
    studio, _ = load_environment("procedural:studio", None)
    assert not np.array_equal(sky, studio)
    fallback, how = load_environment("no_such_map", None)
    assert how.startswith("FALLBACK") and "no_such_map" in how
    np.testing.assert_array_equal(fallback, sky)
    with pytest.raises(ValueError, match="procedural:sky"):
        load_environment("procedural:volcano", None)
    path = tmp_path / "grey.exr"
    write_exr(path, np.full((8, 16, 3), 0.25, np.float32))
    env, how = load_environment("grey", path)
    assert how == "file grey.exr" and env.shape == (8, 16, 3) and np.allclose(env, 0.25, atol=1e-3)


def test_bad_environment_files_name_the_file(tmp_path):
    truncated = tmp_path / "broken.hdr"
    truncated.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 8 +X 16\n\x02\x02")
    with pytest.raises(InputError, match="broken.hdr"):
        load_environment("broken", truncated)
    square = tmp_path / "square.exr"
    write_exr(square, np.ones((8, 8, 3), np.float32))
    with pytest.raises(InputError, match="square.exr"):
        load_environment("square", square)  # not equirectangular (H, 2H)


def test_environment_files_are_raw_inputs_so_their_digest_enters_the_key(tmp_path, monkeypatch):
    hdri = tmp_path / "hdri"
    write_exr(hdri / "room.exr", np.ones((8, 16, 3), np.float32))
    monkeypatch.setenv("ULTRASTAGE_HDRI", str(hdri))
    found = raw_environment_inputs(("room", "procedural:sky", "missing"), None)
    assert found == {"environment/room": hdri / "room.exr"}


def _ring(n=8, radius=3.0):
    cams = {}
    for i in range(n):
        angle = 2 * np.pi * i / n
        centre = np.array([radius * np.sin(angle), 0.2 * (i % 2), radius * np.cos(angle)])
        cams[f"{i:05d}"] = Camera([[500.0, 0, 160], [0, 500.0, 240], [0, 0, 1]], look_at(centre, np.zeros(3)), 320, 480,
                                  camera_id=f"{i:05d}")
    return cams


def test_novel_cameras_lie_between_neighbours():
    cams = _ring()
    views = novel_cameras(cams, 3)
    assert [v.camera_id for v in views] == ["N000", "N001", "N002"]
    for v in views:
        a, b = v.record["between"]
        centre = v.centre
        ca, cb = (cams[c].centre for c in (a, b))
        # on the arc around the stage centre: mean radius, the same angle to both, and not at either
        radius = np.linalg.norm(centre)
        assert abs(radius - 0.5 * (np.linalg.norm(ca) + np.linalg.norm(cb))) < 1e-9

        def angle(p, q):
            return np.arccos(np.clip(p @ q / (np.linalg.norm(p) * np.linalg.norm(q)), -1, 1))

        assert abs(angle(centre, ca) - angle(centre, cb)) < 1e-9 and angle(centre, ca) > 0.1
        assert (v.width, v.height) == (320, 480)
        assert list(v.to_json())[:2] == ["camera_id", "between"]


def test_config_checks():
    with pytest.raises(ValueError, match="environments"):
        RelightConfig(environments=())
    with pytest.raises(ValueError, match=r"RelightConfig\.shading\.normals = 'bent'"):
        merge(RelightConfig(), {"shading": {"normals": "bent"}}, where="RelightConfig")
    assert RelightConfig(shading=ViewShading(normals="reprojected")).shading.normals == "reprojected"
    for width in (0.0, -0.01, float("nan")):
        with pytest.raises(ValueError, match="normal_fusion_m"):
            ViewShading(normal_fusion_m=width)
    with pytest.raises(ValueError, match="sg_lobes"):
        RelightConfig(sg_lobes=0)
    with pytest.raises(ValueError, match="coverage_samples"):
        ViewShading(coverage_samples=0)
    with pytest.raises(ValueError, match="supersample"):
        ViewShading(supersample=0)
    with pytest.raises(ValueError, match="supersample must be 1 with learned_blend"):
        merge(RelightConfig(), {"learned_blend": {"enabled": True}}, where="RelightConfig")
    blended = merge(RelightConfig(), {"learned_blend": {"enabled": True}, "shading": {"supersample": 1}},
                    where="RelightConfig")
    assert blended.learned_blend.enabled and blended.shading.supersample == 1


def test_shading_knobs_have_one_spelling_in_both_stages():
    """relight and relightset take their reprojection and shading from one nested ViewShading each."""
    from stages.relightset import RelightSetConfig

    assert RelightConfig().shading == ViewShading() == RelightSetConfig().shading
    shading_fields = {f.name for f in dataclasses.fields(ViewShading)}
    assert not shading_fields & {f.name for f in dataclasses.fields(RelightConfig)}
    assert not shading_fields & {f.name for f in dataclasses.fields(RelightSetConfig)}
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['normals'\]"):
        merge(RelightConfig(), {"normals": "mesh"})
    assert merge(RelightConfig(), {"shading": {"normals": "mesh"}}).shading.normals == "mesh"


def test_silhouette_alpha_and_premultiplied_edges_by_hand():
    from stages.numerics.novel_view import premultiply_edges, silhouette_alpha

    shaded = np.zeros((1, 6), bool)
    shaded[0, 1:3] = True  # two pixels whose centres see the subject
    coverage = np.array([[0.75, 1.0, 0.25, 0.5, 0.0, 0.5]], np.float32)
    alpha, mask = silhouette_alpha(shaded, coverage)
    # column 3 (half covered, centre off the subject) borrows column 2; column 5 is 3 px from any shaded
    # pixel: a sliver with no neighbour to lend it a value, alpha 0; column 2's centre hits but covers a quarter
    np.testing.assert_array_equal(alpha, [[0.75, 1.0, 0.25, 0.5, 0.0, 0.0]])
    np.testing.assert_array_equal(mask, [[True, True, False, True, False, False]])
    image = np.zeros((1, 6, 3), np.float32)
    image[0, 1], image[0, 2] = (2, 2, 2), (4, 4, 4)
    out = premultiply_edges(image, shaded, alpha)
    np.testing.assert_allclose(out[0, :, 0], [1.5, 2.0, 1.0, 2.0, 0.0, 0.0])
    # a pixel next to two shaded ones takes their mean
    shaded = np.array([[True, False], [False, True]])
    image = np.zeros((2, 2, 3), np.float32)
    image[0, 0], image[1, 1] = 2.0, 4.0
    out = premultiply_edges(image, shaded, np.full((2, 2), 0.5, np.float32))
    np.testing.assert_allclose(out[..., 1], [[1.0, 1.5], [1.5, 2.0]])


def _claims(tmp_path):
    return sorted((tmp_path / "sg_fits").glob("*.claim"))


def test_sg_fit_memo_waits_for_the_process_fitting_the_map(tmp_path, monkeypatch):
    """A map another live process has claimed is not fitted again: without ``wait`` the call returns None at
    once, with it the call returns that process's stored fit when it lands (here a thread stands for the other
    process); a claim whose process is gone is taken over; no claim file is left behind."""
    import os
    import threading

    from stages import environments
    from stages.environments import fit_environments, fit_sg_memo
    from stages.numerics import sg

    env, _ = load_environment("procedural:sky", None)  # as fit_environments loads it
    fits = []
    order: list[str] = []
    real_fit = sg.fit_sg_environment

    def counting_fit(*args, **kwargs):
        fits.append(1)
        order.append("fit")
        return real_fit(*args, **kwargs)

    monkeypatch.setattr(sg, "fit_sg_environment", counting_fit)
    reference = fit_sg_memo(env, 4, 16, None)
    assert len(fits) == 1
    # another live process (this one's pid) holds the claim: nothing is fitted
    stored = tmp_path / "other"
    first = fit_sg_memo(env, 4, 16, stored)  # find the memo's file names, then take the fit away
    memo = next((stored / "sg_fits").glob("*.json"))
    cache = tmp_path / "cache"
    (cache / "sg_fits").mkdir(parents=True)
    claim = cache / "sg_fits" / (memo.stem + ".claim")
    claim.write_text(str(os.getpid()))
    fits.clear()
    assert fit_sg_memo(env, 4, 16, cache, wait=False) is None and not fits

    def other_process_finishes():
        (cache / "sg_fits" / memo.name).write_text(memo.read_text())
        claim.unlink()

    timer = threading.Timer(0.3, other_process_finishes)
    timer.start()
    waited = fit_sg_memo(env, 4, 16, cache)
    timer.join()
    assert not fits and np.array_equal(waited.numpy().axis, first.numpy().axis)
    # a claim left by a process that is gone is taken over and fitted here
    (cache / "sg_fits" / memo.name).unlink()
    claim.write_text("999999999")
    taken = fit_sg_memo(env, 4, 16, cache)
    assert len(fits) == 1 and np.allclose(taken.numpy().axis, reference.numpy().axis) and not _claims(cache)
    assert environments.CLAIM_STALE_S > 60  # a fit takes seconds; a live claim is never broken by its age alone

    # fit_environments fits the unclaimed map first and the claimed one after it lands
    fits.clear()
    fresh = tmp_path / "fresh"
    (fresh / "sg_fits").mkdir(parents=True)
    claim = fresh / "sg_fits" / (memo.stem + ".claim")
    claim.write_text(str(os.getpid()))
    order.clear()

    def landed():
        order.append("other")
        (fresh / "sg_fits" / memo.name).write_text(memo.read_text())
        claim.unlink()

    timer = threading.Timer(2.0, landed)  # well after fit_environments has loaded both maps (about 0.05 s)
    timer.start()

    class Log:
        def warning(self, *args):
            pass

    records = fit_environments(("procedural:sky", "procedural:studio"), {}, 4, 16, Log(), fresh)
    timer.join()
    assert [r["label"] for r in records] == ["procedural_sky", "procedural_studio"]
    # only the studio map fitted here, at once, and the sky map taken from the other process when it landed
    assert len(fits) == 1 and order == ["fit", "other"]
    assert all(r["lobes"] is not None and "fit_errors" in r for r in records) and not _claims(fresh)


def test_gbuffer_options_are_every_setting_of_the_novel_views_gbuffer():
    """``ViewShading.gbuffer_options`` feeds each call of ``novel_view_gbuffer`` (the stage's views at both
    sample grids, the benches): a parameter it leaves out would silently keep its default there."""
    import inspect

    from stages.numerics.novel_view import novel_view_gbuffer

    params = set(inspect.signature(novel_view_gbuffer).parameters) - {"asset", "K", "cam_from_world", "height",
                                                                       "width", "blend"}
    shading = ViewShading(source_edge_px=0, source_edge_jump_m=0.2, rim_normal_px=2.0)
    options = shading.gbuffer_options()
    assert set(options) == params
    assert (options["source_edge_px"], options["source_edge_jump_m"], options["rim_normal_px"]) == (0, 0.2, 2.0)
    with pytest.raises(ValueError, match="source_edge_px"):
        ViewShading(source_edge_px=-1)
    with pytest.raises(ValueError, match="source_edge_jump_m"):
        ViewShading(source_edge_jump_m=0.0)
