"""Tests of synthetic.relight: environment maps as distant lights, the ground-truth subject relit."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.codecs.exr import read_exr
from pipeline.codecs.image import read_png
from stages.numerics import sg
from synthetic import SimConfig, files, simulate
from synthetic.geometry import fibonacci_sphere
from synthetic.relight import (TruthRelighter, environment_lights, equirect_directions,
                               equirect_solid_angles, prefetch_visibility)
from synthetic.simulate import render_views

LIGHTS = 128
# procedural subject (concave: self-shadowed), ideal LEDs so the simulator's full_on is a constant
# environment of radiance 1; no noise, no clean plates (the relighter reads capture.json and ground_truth);
# one ray per pixel, so every pixel is a per-ray identity (supersampled silhouette pixels also hold the stage)
CONFIG = SimConfig(actions=1, width=64, n_cameras=2, n_leds=LIGHTS, mesh="procedural", noise=False,
                   background=False, led_error=0.0, supersample=1)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return simulate(tmp_path_factory.mktemp("relight") / "capture", CONFIG)


@pytest.fixture(scope="module")
def relighter(capture) -> TruthRelighter:
    return TruthRelighter(capture, "A0000", lights=LIGHTS)


@pytest.fixture(scope="module")
def cameras(capture) -> list[dict]:
    return json.loads((capture / "ground_truth" / "cameras" / "S000.json").read_text())["cameras"]


def render(relighter: TruthRelighter, camera: dict, env: np.ndarray, **options) -> dict:
    return relighter.render(np.array(camera["K"]), np.array(camera["cam_from_world"]), camera["height"],
                            camera["width"], env, **options)


def environment_integral(env: np.ndarray) -> np.ndarray:
    """(3,) integral of an equirect map over the sphere, float64, from the pipeline's solid angles."""
    solid = sg.equirect_solid_angles(*env.shape[:2]).astype(np.float64)
    return np.einsum("hw,hwc->c", solid, env.astype(np.float64))


# --- environment -> lights --------------------------------------------------------------------------------

def test_equirect_convention_is_the_pipelines():
    for height, width in ((6, 12), (7, 5), (64, 128)):
        np.testing.assert_allclose(equirect_directions(height, width), sg.equirect_directions(height, width),
                                   atol=1e-6)
        np.testing.assert_allclose(equirect_solid_angles(height, width), sg.equirect_solid_angles(height, width),
                                   rtol=1e-6)
    # hand check, 3 x 4 map: the middle row lies on the horizon at longitudes -135, -45, 45, 135 degrees;
    # u = 0.5 (between columns 1 and 2) faces -z, u = 0.75 (between columns 2 and 3) faces +x
    h = np.sqrt(0.5)
    dirs = equirect_directions(3, 4)
    np.testing.assert_allclose(dirs[1], [[-h, 0, h], [-h, 0, -h], [h, 0, -h], [h, 0, h]], atol=1e-6)
    np.testing.assert_allclose(dirs[0, :, 1], np.cos(np.pi / 6), atol=1e-6)  # row 0 is the zenith side
    np.testing.assert_allclose(dirs[2, :, 1], -np.cos(np.pi / 6), atol=1e-6)
    assert equirect_solid_angles(5, 9).sum() == pytest.approx(4 * np.pi)


@pytest.mark.parametrize("shape", [(64, 128), (100, 170), (512, 1024)])
def test_environment_lights_conserve_energy(shape):
    env = np.random.default_rng(3).gamma(0.5, 2.0, size=(*shape, 3)).astype(np.float32)
    directions, irradiance = environment_lights(env, count=256)
    assert directions.shape == (256, 3) and irradiance.shape == (256, 3)
    assert directions.dtype == np.float32 and irradiance.dtype == np.float32
    np.testing.assert_allclose(directions, fibonacci_sphere(256), atol=1e-6)  # fixed for every map
    np.testing.assert_allclose(irradiance.astype(np.float64).sum(axis=0), environment_integral(env), rtol=1e-5)
    assert np.all(irradiance >= 0)


def test_environment_lights_place_energy_where_the_map_is_bright():
    constant = np.full((256, 512, 3), 2.0, np.float32)
    _, irradiance = environment_lights(constant, count=512)
    # every light collects about its Voronoi cell: 2 x 4 pi / 512 (texel quantisation of the cells)
    cell = irradiance[:, 1] / (2.0 * 4 * np.pi / 512)
    assert cell.mean() == pytest.approx(1.0, abs=1e-5) and cell.std() < 0.03 and cell.min() > 0.9
    spot = np.zeros((64, 128, 3), np.float32)
    spot[32, 96] = (1.0, 2.0, 3.0)  # the texel just below the horizon at u = 0.75: +x
    directions, irradiance = environment_lights(spot, count=512)
    lit = np.nonzero(irradiance[:, 0])[0]
    assert len(lit) == 1
    assert lit[0] == np.argmax(directions @ sg.equirect_directions(64, 128)[32, 96])
    np.testing.assert_allclose(irradiance[lit[0]], environment_integral(spot), rtol=1e-5)


def test_environment_lights_refuse_bad_maps():
    for env in (np.ones((8, 16)), np.ones((8, 16, 4)), np.ones((0, 16, 3)), np.ones((8, 16, 3), np.uint8)):
        with pytest.raises(ValueError, match="environment map"):
            environment_lights(env)
    bad = np.ones((8, 16, 3), np.float32)
    bad[2, 3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        environment_lights(bad)
    with pytest.raises(ValueError, match="negative"):
        environment_lights(-np.ones((8, 16, 3), np.float32))
    with pytest.raises(ValueError, match="count"):
        environment_lights(np.ones((8, 16, 3), np.float32), count=4)


# --- the relit subject ---------------------------------------------------------------------------------------

def test_truth_maps_match_the_captures_ground_truth(relighter, capture, cameras):
    assert len(relighter.subject.vertices_world) > 1000  # the rebuilt subject passed the mesh.ply check
    truth = capture / "ground_truth" / "A0000"
    env = np.ones((32, 64, 3), np.float32)
    for camera in cameras:
        out = render(relighter, camera, env)
        cid = camera["camera_id"]
        assert out["radiance"].shape == (camera["height"], camera["width"], 3)
        assert out["radiance"].dtype == np.float32 and np.all(np.isfinite(out["radiance"]))
        mask = out["mask"]
        assert mask.sum() > 500
        np.testing.assert_array_equal(mask, read_png(truth / "mask" / f"{cid}.png") > 0)
        # the ground-truth maps are half floats
        np.testing.assert_allclose(out["albedo"], read_exr(truth / "albedo" / f"{cid}.exr"), atol=1e-3)
        np.testing.assert_allclose(out["roughness"], read_exr(truth / "roughness" / f"{cid}.exr"), atol=1e-3)
        np.testing.assert_allclose(out["normals_world"], read_exr(truth / "normal" / f"{cid}.exr"), atol=2e-3)
        np.testing.assert_allclose(out["depth_m"], read_exr(truth / "depth" / f"{cid}.exr"), rtol=2e-3)
        # same light directions as the capture's LEDs: the same visibility
        np.testing.assert_allclose(out["visibility"], read_exr(truth / "visibility" / f"{cid}.exr"), atol=2e-3)
        assert np.all(out["radiance"][~mask] == 0) and np.all(out["albedo"][~mask] == 0)


def test_constant_environment_lights_a_lambertian_subject_to_albedo_times_visibility(relighter, cameras):
    colour = np.array([0.5, 1.0, 2.0], np.float32)
    out = render(relighter, cameras[0], np.broadcast_to(colour, (128, 256, 3)).copy(), specular=False)
    mask = out["mask"]
    expected = out["albedo"] * colour * out["visibility"][..., None]
    front = mask & (out["visibility"] > 0.05)
    ratio = out["radiance"][front] / np.maximum(expected[front], 1e-6)
    assert np.median(np.abs(ratio - 1)) < 0.005 and np.percentile(np.abs(ratio - 1), 95) < 0.015
    # where nothing occludes, radiance = albedo x c
    open_sky = mask & (out["visibility"] > 0.999)
    assert open_sky.sum() > 50
    np.testing.assert_allclose(out["radiance"][open_sky], (out["albedo"] * colour)[open_sky], rtol=0.01, atol=1e-4)
    # and the self-shadowed procedural subject has darker pockets
    assert (mask & (out["visibility"] < 0.7)).sum() > 20


def test_constant_environment_matches_the_simulators_full_on(relighter, cameras):
    """Ideal LEDs of unit intensity are a constant environment of radiance 1: diffuse + GGX agree."""
    _, _, views = render_views(CONFIG)
    for camera, view in zip(cameras, views):
        out = render(relighter, camera, np.ones((256, 512, 3), np.float32))
        mask = view.mask
        np.testing.assert_array_equal(out["mask"], mask)
        simulated = view.radiance[..., 0:3][mask]
        error = out["radiance"][mask] - simulated
        assert np.sqrt(np.mean(error ** 2) / np.mean(simulated ** 2)) < 0.005  # measured 0.11-0.15%
        specular_on = render(relighter, camera, np.ones((256, 512, 3), np.float32), specular=False)
        assert (out["radiance"] - specular_on["radiance"])[mask].mean() > 0.005  # the glossy lobe is there


def test_light_from_plus_x_lights_plus_x_facing_surfaces(relighter, cameras):
    env = np.zeros((64, 128, 3), np.float32)
    env[28:36, 92:100] = 50.0  # ~11 degrees around +x (u = 0.75, the horizon)
    for camera in cameras:
        out = render(relighter, camera, env)
        mask, normal_x = out["mask"], out["normals_world"][..., 0]
        facing = mask & (normal_x > 0.7) & (out["visibility"] > 0.9)
        # well below the horizon of every lit light (128 lights are ~18 degrees apart) and of the triangle
        # corners whose irradiance the pixel interpolates
        away = mask & (normal_x < -0.5)
        assert facing.sum() > 20 and away.sum() > 20
        luminance = out["radiance"].mean(axis=-1)
        assert luminance[facing].mean() > 0.05
        assert np.all(luminance[away] == 0.0)  # below their horizon: no diffuse, no specular


def test_rendering_is_deterministic_and_cached(relighter, capture, cameras):
    env = np.random.default_rng(5).gamma(0.5, 1.0, size=(32, 64, 3)).astype(np.float32)
    first = render(relighter, cameras[1], env)
    lighting = relighter.lighting(env)
    assert relighter.lighting(env.copy()) is lighting  # cached by content
    again = TruthRelighter(capture, "A0000", lights=LIGHTS)
    second = render(again, cameras[1], env)
    for key in first:
        np.testing.assert_array_equal(first[key], second[key])
    other = render(relighter, cameras[1], env[:, ::-1].copy())
    assert not np.array_equal(other["radiance"], first["radiance"])


def test_a_finer_pixel_grid_averages_the_renders_of_a_finer_camera(relighter, cameras):
    env = np.random.default_rng(8).gamma(0.5, 1.0, size=(32, 64, 3)).astype(np.float32)
    camera = cameras[0]
    default = render(relighter, camera, env)
    np.testing.assert_array_equal(render(relighter, camera, env, supersample=1)["radiance"], default["radiance"])
    grid = render(relighter, camera, env, supersample=3)
    # pixel (i, j) at 3 x 3 rays: the mean of the 3 x 3 block of pixels of a camera with 3 times finer pixels
    # (centres at i - 1/3, i, i + 1/3)
    K = np.array(camera["K"], np.float64)
    K[:2, :2] *= 3
    K[:2, 2] = (K[:2, 2] + 0.5) * 3 - 0.5
    h, w = camera["height"], camera["width"]
    fine = relighter.render(K, np.array(camera["cam_from_world"]), 3 * h, 3 * w, env)
    block_mean = fine["radiance"].reshape(h, 3, w, 3, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(grid["radiance"], block_mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(grid["mask"], fine["mask"].reshape(h, 3, w, 3).sum(axis=(1, 3)) >= 4.5)
    # silhouette pixels change with the grid, so the two renders are not the same image
    assert not np.array_equal(grid["radiance"], default["radiance"])
    for bad in (0, 1.5, -2):
        with pytest.raises(ValueError, match="supersample"):
            render(relighter, camera, env, supersample=bad)


def test_visibility_kept_on_disk_renders_the_same(relighter, capture, cameras, tmp_path):
    env = np.random.default_rng(6).gamma(0.5, 1.0, size=(32, 64, 3)).astype(np.float32)
    want = render(relighter, cameras[0], env)
    folder = tmp_path / "visibility"
    assert prefetch_visibility(capture, folder, lights=LIGHTS) == ["A0000"]
    (kept,) = folder.glob("*.npy")
    packed = np.load(kept)
    assert packed.shape == (len(relighter.subject.vertices_world), LIGHTS // 8)
    from_disk = TruthRelighter(capture, "A0000", lights=LIGHTS, visibility_cache=folder)
    got = render(from_disk, cameras[0], env)
    for key in want:
        np.testing.assert_array_equal(got[key], want[key])
    # a missing cache entry is traced and written; another light count is another entry
    other = TruthRelighter(capture, "A0000", lights=LIGHTS // 2, visibility_cache=folder)
    assert len(list(folder.glob("*.npy"))) == 2 and other.lights == LIGHTS // 2
    # a damaged entry is traced again (and rewritten), never trusted
    kept.write_bytes(b"not a numpy file")
    again = TruthRelighter(capture, "A0000", lights=LIGHTS, visibility_cache=folder)
    np.testing.assert_array_equal(render(again, cameras[0], env)["radiance"], want["radiance"])
    assert np.array_equal(np.load(kept), packed)


def test_a_visibility_another_process_is_tracing_is_waited_for_not_traced_again(relighter, capture, tmp_path,
                                                                                monkeypatch):
    """While a live process holds the trace's claim, _cached_visibility waits for its file instead of tracing;
    a claim whose process is gone is taken over, traced here and removed."""
    import os
    import threading

    from synthetic import relight, shading

    folder = tmp_path / "visibility"
    directions = relighter.directions
    want = relight._cached_visibility(folder, capture / "capture.json", "A0000", relighter.subject, directions)
    (kept,) = folder.glob("*.npy")
    packed = kept.read_bytes()
    kept.unlink()
    claim = kept.with_name(kept.name + ".claim")
    claim.write_text(str(os.getpid()))  # a live process (this one) is tracing it

    def finish_the_trace():  # what the claim's holder does: store the file, then drop the claim
        kept.write_bytes(packed)
        claim.unlink()

    traced = []
    real_trace = shading.vertex_visibility
    monkeypatch.setattr(shading, "vertex_visibility", lambda *a, **k: traced.append(1) or real_trace(*a, **k))
    timer = threading.Timer(0.5, finish_the_trace)
    timer.start()
    try:
        got = relight._cached_visibility(folder, capture / "capture.json", "A0000", relighter.subject, directions)
    finally:
        timer.join()
    np.testing.assert_array_equal(got, want)
    assert traced == []
    # the claim of a process that is gone: traced here, stored, and no claim left behind
    kept.unlink()
    claim.write_text("999999999")
    got = relight._cached_visibility(folder, capture / "capture.json", "A0000", relighter.subject, directions)
    np.testing.assert_array_equal(got, want)
    assert traced == [1] and kept.read_bytes() == packed and not claim.exists()


def test_relighter_refuses_unknown_actions_and_real_captures(capture, relighter, cameras, tmp_path):
    with pytest.raises(ValueError, match="unknown action id 'A0042'"):
        TruthRelighter(capture, "A0042", lights=LIGHTS)
    record = json.loads((capture / "capture.json").read_text())
    del record["simulator"]
    real = tmp_path / "real"
    files.write_json(real / "capture.json", record)
    with pytest.raises(ValueError, match=r"real[/\\]capture.json has no 'simulator'"):
        TruthRelighter(real, "A0000", lights=LIGHTS)
    with pytest.raises(FileNotFoundError):
        TruthRelighter(tmp_path / "nowhere", "A0000")
    with pytest.raises(ValueError, match="environment map"):
        render(relighter, cameras[0], np.ones((8, 16), np.float32))
    with pytest.raises(ValueError, match="cam_from_world"):
        relighter.render(np.array(cameras[0]["K"]), np.eye(3), 8, 8, np.ones((8, 16, 3), np.float32))


def test_relighter_refuses_a_subject_that_is_not_the_captured_one(capture, tmp_path):
    moved = tmp_path / "moved"
    moved.mkdir()
    shutil.copy(capture / "capture.json", moved / "capture.json")
    relighter_free = TruthRelighter(moved, "A0000", lights=16)  # no mesh.ply: nothing to check against
    vertices = relighter_free.subject.vertices_world + np.array([0.0, 0.01, 0.0])
    files.write_ply(moved / "ground_truth" / "A0000" / "mesh.ply", vertices, relighter_free.subject.triangles)
    with pytest.raises(ValueError, match="differs from the captured one"):
        TruthRelighter(moved, "A0000", lights=16)


def test_backface_share_marks_the_inside_of_an_open_mesh_only(relighter, cameras, tmp_path):
    """The closed procedural subject shows no back face; an open bust (a sphere cut at the neck) seen from below
    shows its black inside through the opening, and from the side none of it."""
    import trimesh

    env = np.ones((16, 32, 3), np.float32)
    for camera in cameras:
        out = render(relighter, camera, env)
        assert out["backface"].shape == out["mask"].shape and out["backface"].dtype == np.float32
        assert not out["backface"].any()

    ball = trimesh.creation.icosphere(subdivisions=3, radius=12.0)
    keep = ball.vertices[ball.faces][:, :, 1].min(axis=1) > -4.0  # the opening faces -y
    path = tmp_path / "bust.ply"
    trimesh.Trimesh(ball.vertices, ball.faces[keep], process=False).export(path)
    config = SimConfig(actions=1, width=32, n_cameras=1, n_leds=16, mesh=str(path), noise=False, background=False,
                       led_error=0.0, supersample=2)
    bust = TruthRelighter(simulate(tmp_path / "bust_capture", config), "A0000", lights=16)
    vertices = bust.subject.vertices_world
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    K = np.array([[40.0, 0.0, 15.5], [0.0, 40.0, 15.5], [0.0, 0.0, 1.0]])

    def look_from(offset: np.ndarray, rotation: np.ndarray) -> dict:
        eye = centre + offset
        return bust.render(K, np.column_stack([rotation, -rotation @ eye]), 32, 32, env)

    below = look_from(np.array([0.0, -0.6, 0.0]), np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]))  # looks up +y
    inside = below["backface"] == 1.0
    assert inside[12:20, 12:20].all()  # the middle of the view: through the opening onto the inside of the shell
    assert below["mask"][inside].all() and np.all(below["radiance"][inside] == 0)
    assert np.all((below["backface"] >= 0) & (below["backface"] <= 1))
    rim = (below["backface"] > 0) & (below["backface"] < 1)
    assert rim.any() and (below["backface"][rim] % 0.25 == 0).all()  # the cut's rim: a share of the 2 x 2 rays
    side = look_from(np.array([0.0, 0.0, -0.6]), np.eye(3))  # looks along +z at the bust's side
    assert side["mask"].sum() > 100 and not side["backface"].any()
