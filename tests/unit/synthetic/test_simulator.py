"""Tests of the light-stage simulator: physics of the gradient ratio, occlusion, sensor/DNG path, files."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from synthetic import SimConfig, simulate
from synthetic import files, geometry, sensor, subject
from synthetic.simulate import render_views

SHARED_DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data"
MAKEHUMAN = SHARED_DATA / "meshes" / "makehuman_base.obj"
needs_shared = pytest.mark.skipif(not MAKEHUMAN.is_file(),
                                  reason=f"shared data not found ({MAKEHUMAN}); a fresh clone has no ../shared")

TINY = dict(width=64, n_cameras=4, n_leds=128)


def rawpy_decode(path: Path, half_size: bool = False) -> np.ndarray:
    """Decoded linear values (1.0 = raw green clip) of a raw file, float32 (H, W, 3)."""
    import rawpy

    with rawpy.imread(str(path)) as raw:
        rgb = raw.postprocess(use_camera_wb=True, output_color=rawpy.ColorSpace.sRGB, gamma=(1, 1),
                              no_auto_bright=True, output_bps=16, user_flip=0, half_size=half_size)
    return rgb.astype(np.float32) / 65535.0


@pytest.fixture(scope="module")
def sphere_obj(tmp_path_factory) -> Path:
    """A convex subject: a UV-less sphere of radius 0.4 m as an OBJ (metres)."""
    icosahedron_t = (1 + 5 ** 0.5) / 2
    vertices = np.array([[-1, icosahedron_t, 0], [1, icosahedron_t, 0], [-1, -icosahedron_t, 0],
                         [1, -icosahedron_t, 0], [0, -1, icosahedron_t], [0, 1, icosahedron_t],
                         [0, -1, -icosahedron_t], [0, 1, -icosahedron_t], [icosahedron_t, 0, -1],
                         [icosahedron_t, 0, 1], [-icosahedron_t, 0, -1], [-icosahedron_t, 0, 1]], float)
    faces = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                      [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                      [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    for _ in range(5):
        vertices, faces, _ = geometry.loop_subdivide(vertices, faces)
        vertices = geometry.normalize(vertices)
    vertices *= 0.4
    path = tmp_path_factory.mktemp("mesh") / "sphere.obj"
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def ratio_normals(radiance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d = (pos - neg) / (pos + neg) per channel (H, W, 3) and its unit direction."""
    pos, neg = radiance[..., 3:6], radiance[..., 6:9]
    d = (pos - neg) / np.maximum(pos + neg, 1e-12)
    return d, geometry.normalize(d)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


# --- numerics -----------------------------------------------------------------------------------------

def test_config_defaults_and_portrait_height():
    config = SimConfig()
    assert (config.actions, config.width, config.height, config.n_leds, config.n_cameras) == (2, 320, 480, 512, 32)
    assert SimConfig(width=64).height == 96
    assert SimConfig(width=63).height == 94
    with pytest.raises(ValueError):
        SimConfig(width=8)
    with pytest.raises(Exception):
        config.width = 10  # frozen


def test_loop_subdivision_of_a_closed_mesh():
    vertices = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    triangles = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    new_vertices, new_triangles, _ = geometry.loop_subdivide(vertices, triangles)
    assert new_vertices.shape == (4 + 6, 3) and new_triangles.shape == (16, 3)
    # closed and consistently wound: every directed edge appears exactly once, its reverse once
    edges = np.concatenate([new_triangles[:, [0, 1]], new_triangles[:, [1, 2]], new_triangles[:, [2, 0]]])
    assert len({tuple(e) for e in edges}) == len(edges)
    assert {tuple(e[::-1]) for e in edges} == {tuple(e) for e in edges}
    # Loop smoothing shrinks the tetrahedron towards its centre
    assert np.linalg.norm(new_vertices[:4], axis=1).max() < np.sqrt(3)


def test_ratio_normals_on_a_convex_sphere(sphere_obj):
    """Unoccluded Lambertian, ideal LEDs: (pos-neg)/(pos+neg) = 2/3 n and pos + neg = full_on."""
    # one ray per pixel: the identities hold per ray, and averaged silhouette pixels also see the stage
    config = SimConfig(mesh=str(sphere_obj), led_error=0.0, noise=False, specular=False, supersample=1, **TINY)
    _, _, views = render_views(config)
    errors, lengths, sum_errors = [], [], []
    for view in views:
        inside = view.mask & (view.visibility > 0.999)
        d, d_unit = ratio_normals(view.radiance)
        errors.append(angle_deg(d_unit, view.normals_world)[inside])
        lengths.append(np.linalg.norm(d, axis=-1)[inside])
        full_on, both = view.radiance[..., 0:3], view.radiance[..., 3:6] + view.radiance[..., 6:9]
        sum_errors.append((np.abs(both - full_on) / np.maximum(full_on, 1e-9))[inside])
    errors, lengths = np.concatenate(errors), np.concatenate(lengths)
    assert len(errors) > 1000
    print(f"\nconvex sphere ratio-normal error: mean {errors.mean():.3f} deg, p99 {np.percentile(errors, 99):.3f}"
          f" deg, max {errors.max():.3f} deg; |d| {lengths.min():.4f}..{lengths.max():.4f}")
    assert errors.mean() < 0.3 and np.percentile(errors, 99) < 0.8
    assert np.all(np.abs(lengths - 2 / 3) < 0.02)
    assert np.concatenate(sum_errors).max() < 1e-4


def test_occlusion_biases_normals_on_the_concave_procedural_subject():
    config = SimConfig(mesh="procedural", led_error=0.0, noise=False, specular=False, **TINY)
    _, subj, views = render_views(config)
    assert subj.base.kind == "procedural"
    occluded_err, open_err = [], []
    for view in views:
        _, d_unit = ratio_normals(view.radiance)
        err = angle_deg(d_unit, view.normals_world)
        occluded_err.append(err[view.mask & (view.visibility < 0.9)])
        open_err.append(err[view.mask & (view.visibility >= 0.9)])
    occluded_err, open_err = np.concatenate(occluded_err), np.concatenate(open_err)
    assert len(occluded_err) > 100 and len(open_err) > 1000
    assert occluded_err.mean() > 2.0 * open_err.mean()
    assert occluded_err.mean() > 5.0


def test_specular_adds_view_dependent_light(sphere_obj):
    base = dict(mesh=str(sphere_obj), led_error=0.0, noise=False, supersample=1, **TINY)  # off-mask = stage only
    _, _, lambert = render_views(SimConfig(specular=False, **base))
    _, _, glossy = render_views(SimConfig(specular=True, **base))
    extra = glossy[0].radiance - lambert[0].radiance
    assert np.all(extra[glossy[0].mask] >= -1e-6)
    assert extra[glossy[0].mask].mean() > 0.005
    np.testing.assert_allclose(glossy[0].radiance[~glossy[0].mask], lambert[0].radiance[~glossy[0].mask])


def test_supersampled_camera_grid():
    """Fine pixel (s i + k) of an s-times finer camera has its centre at k + 1/2 of s steps across coarse pixel i."""
    from synthetic.rig import Camera
    from synthetic.shading import supersampled_camera

    K = np.array([[100.0, 0.0, 31.5], [0.0, 100.0, 47.5], [0.0, 0.0, 1.0]])
    camera = Camera("c", 64, 96, K, np.hstack([np.eye(3), np.zeros((3, 1))]), 50.0, 0.01)
    fine = supersampled_camera(camera, 3)
    assert (fine.width, fine.height) == (192, 288)
    point = np.array([0.1, -0.2, 2.0])
    coarse_uv = (K @ point)[:2] / point[2]  # (36.5, 37.5)
    fine_uv = (fine.K @ point)[:2] / point[2]
    np.testing.assert_allclose(fine_uv, (coarse_uv + 0.5) * 3 - 0.5)
    # coarse pixel 36's square [35.5, 36.5) holds fine pixels 108..110, centres at 35.5 + (k + 0.5) / 3
    np.testing.assert_allclose((np.arange(108, 111) + 0.5) / 3 - 0.5, 35.5 + (np.arange(3) + 0.5) / 3)
    with pytest.raises(ValueError, match="supersample"):
        SimConfig(supersample=0)


def test_pixel_average_by_hand():
    """2 x 2 rays per pixel: radiance over all rays, truth maps over the rays that hit, mask from half of them."""
    from synthetic.shading import ViewRender, pixel_average

    mask = np.array([[1, 1, 1, 0], [1, 0, 0, 0]], bool)  # pixel 0: 3 of 4 rays hit, pixel 1: 1 of 4
    radiance = np.zeros((2, 4, 9), np.float32)
    radiance[mask] = 4.0
    radiance[~mask] = 0.5  # the stage behind
    albedo = np.where(mask[..., None], np.array([[[0.2], [0.4], [0.6], [0.0]], [[0.8], [0.0], [0.0], [0.0]]]), 0.0)
    albedo = np.repeat(albedo, 3, axis=-1).astype(np.float32)
    normals = np.zeros((2, 4, 3), np.float32)
    normals[mask] = [0.0, 0.0, 1.0]
    normals[0, 1] = [1.0, 0.0, 0.0]
    scalar = np.where(mask, 2.0, 0.0).astype(np.float32)
    out = pixel_average(ViewRender(radiance, mask, normals, albedo, scalar, scalar, scalar), 2)
    np.testing.assert_array_equal(out.mask, [[True, False]])
    np.testing.assert_allclose(out.radiance[0, 0], (3 * 4.0 + 0.5) / 4)
    np.testing.assert_allclose(out.radiance[0, 1], (4.0 + 3 * 0.5) / 4)
    np.testing.assert_allclose(out.albedo[0, 0], (0.2 + 0.4 + 0.8) / 3, rtol=1e-6)
    np.testing.assert_allclose(out.normals_world[0, 0], np.array([1.0, 0.0, 2.0]) / np.sqrt(5.0), rtol=1e-6)
    assert np.all(out.albedo[0, 1] == 0) and np.all(out.normals_world[0, 1] == 0) and out.depth_m[0, 1] == 0
    np.testing.assert_allclose(out.depth_m[0, 0], 2.0)
    with pytest.raises(ValueError, match="rays per pixel"):
        pixel_average(ViewRender(radiance[:, :3], mask[:, :3], normals[:, :3], albedo[:, :3], scalar[:, :3],
                                 scalar[:, :3], scalar[:, :3]), 2)


def test_supersampled_render_integrates_the_pixels(sphere_obj):
    """Against one ray per pixel: the same subject (mask, normals), and silhouette pixels that mix it with the
    stage behind (what one ray per pixel cannot give)."""
    base = dict(mesh=str(sphere_obj), led_error=0.0, noise=False, specular=False, **TINY)
    _, _, single = render_views(SimConfig(supersample=1, **base))
    _, _, multi = render_views(SimConfig(supersample=3, **base))
    a, b = single[0], multi[0]
    assert (a.mask & b.mask).sum() / (a.mask | b.mask).sum() > 0.9
    both = a.mask & b.mask
    assert angle_deg(a.normals_world[both], b.normals_world[both]).mean() < 3.0
    for arr in (b.radiance, b.normals_world, b.albedo, b.depth_m, b.roughness, b.visibility):
        assert np.all(np.isfinite(arr))
    full_a, full_b = a.radiance[..., 0:3].mean(-1), b.radiance[..., 0:3].mean(-1)
    stage = np.median(full_a[~a.mask])
    sphere = np.median(full_a[a.mask])
    # pixels between the stage's and the subject's brightness occur only along the silhouette when averaging
    between = (full_b > stage + 0.2 * (sphere - stage)) & (full_b < sphere - 0.2 * (sphere - stage))
    between_single = (full_a > stage + 0.2 * (sphere - stage)) & (full_a < sphere - 0.2 * (sphere - stage))
    assert between.sum() > between_single.sum() + 10 and (between & ~b.mask).sum() > 0


def test_specular_led_clusters_approximate_the_exact_lobe(sphere_obj):
    base = dict(mesh=str(sphere_obj), led_error=0.0, noise=False, **TINY)
    _, _, exact = render_views(SimConfig(**base))
    _, _, clustered = render_views(SimConfig(specular_led_clusters=True, **base))
    mask = exact[0].mask
    difference = clustered[0].radiance[mask] - exact[0].radiance[mask]
    assert np.sqrt(np.mean(difference ** 2) / np.mean(exact[0].radiance[mask] ** 2)) < 0.05


def test_dng_decodes_to_the_simulated_linear_values(tmp_path):
    """A flat patch of known linear-sRGB radiance decodes (rawpy, camera WB, sRGB) to gain x radiance."""
    for colour in ([0.4, 0.4, 0.4], [0.30, 0.45, 0.12]):
        radiance = np.broadcast_to(np.array(colour, np.float32), (32, 48, 3))
        gain = 1.0
        raw = sensor.raw_frame(radiance, gain, None, 40000.0, 0.0)
        path = files.write_dng(tmp_path / "patch.dng", raw, sensor.nikon_cam_from_xyz(), sensor.as_shot_neutral())
        decoded = rawpy_decode(path)
        assert decoded.shape == (32, 48, 3)
        np.testing.assert_allclose(decoded[8:-8, 8:-8].mean(axis=(0, 1)), colour, rtol=0.006, atol=2e-4)


# --- end to end ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def procedural_capture(tmp_path_factory) -> tuple[Path, list[str]]:
    """A tiny two-session capture of the procedural subject, made as in a clone without ../shared."""
    messages: list[str] = []
    tmp = tmp_path_factory.mktemp("procedural")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(subject, "DEFAULT_MESH", tmp / "missing" / "makehuman_base.obj")
        out = simulate(tmp / "cap", SimConfig(actions=2, sessions=2, **TINY), progress=messages.append)
    return out, messages


def test_procedural_capture_files_when_no_mesh_exists(procedural_capture):
    out, messages = procedural_capture
    assert messages and any("A0001" in m for m in messages)

    capture = json.loads((out / "capture.json").read_text())
    assert capture["format"] == "ultrastage-capture/1"
    assert capture["illuminations"] == ["full_on", "pos", "neg"]
    assert capture["camera_ids"] == ["00000", "00001", "00002", "00003"]
    assert [a["action_id"] for a in capture["actions"]] == ["A0000", "A0001"]
    assert [a["session_id"] for a in capture["actions"]] == ["S000", "S001"]
    assert capture["actions"][0]["subject"].startswith("procedural")
    assert capture["simulator"]["width"] == 64

    from pipeline.codecs.exr import read_exr
    from pipeline.codecs.image import read_png

    for session in capture["sessions"]:
        rig = json.loads((out / session["rig"]).read_text())
        assert rig["format"] == "ultrastage-rig/1" and rig["camera_convention"] == "opencv"
        assert rig["raw"] == {"black_level": 600, "white_level": 16383, "cfa": "RGGB"}
        assert rig["leds"]["count"] == 128 and len(rig["leds"]["directions"]) == 128
        for cam in rig["cameras"]:
            assert (cam["width"], cam["height"]) == (64, 96)
            assert np.asarray(cam["K"]).shape == (3, 3) and np.asarray(cam["cam_from_world"]).shape == (3, 4)
            rotation = np.asarray(cam["cam_from_world"])[:, :3]
            np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)
            assert 24 <= cam["focal_mm"] <= 120 and cam["sensor_mm"] == [24.0, 35.9]
            assert 0.4 < cam["white_reference"][1] < 0.6
            plate = out / "sessions" / session["session_id"] / "background" / f"{cam['camera_id']}.dng"
            assert plate.is_file()
    plate_rgb = rawpy_decode(out / "sessions" / "S000" / "background" / "00000.dng", half_size=True)
    assert 0.005 < np.median(plate_rgb[..., 1]) < 0.05

    for action in ("A0000", "A0001"):
        for illumination in ("full_on", "pos", "neg"):
            for cam in capture["camera_ids"]:
                assert (out / "actions" / action / illumination / f"{cam}.dng").is_file()
        truth_dir = out / "ground_truth" / action
        for cam in capture["camera_ids"]:
            mask = read_png(truth_dir / "mask" / f"{cam}.png")
            assert mask.shape == (96, 64) and mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
            assert (mask > 0).mean() > 0.05
            for name, shape in (("normal", (96, 64, 3)), ("albedo", (96, 64, 3)), ("roughness", (96, 64)),
                                ("depth", (96, 64)), ("visibility", (96, 64))):
                values = read_exr(truth_dir / name / f"{cam}.exr")
                assert values.shape == shape and np.all(np.isfinite(values)), name
                assert np.all(values[mask == 0] == 0), name
            normals = read_exr(truth_dir / "normal" / f"{cam}.exr")
            np.testing.assert_allclose(np.linalg.norm(normals[mask > 0], axis=-1), 1.0, atol=2e-3)
            assert read_exr(truth_dir / "depth" / f"{cam}.exr")[mask > 0].min() > 0.5
        truth = json.loads((truth_dir / "truth.json").read_text())
        assert truth["subject"]["kind"] == "procedural"
        assert len(truth["leds"]["gains"]) == 128
        assert {"skin", "cloth_shirt", "leather_shiny"} <= set(truth["materials"])
        import open3d as o3d
        mesh = o3d.io.read_triangle_mesh(str(truth_dir / "mesh.ply"))
        assert len(mesh.triangles) > 1000
        assert (out / "previews" / f"{action}.png").is_file()
    frame = rawpy_decode(out / "actions" / "A0000" / "full_on" / "00000.dng")
    assert frame.shape == (96, 64, 3)


def test_pipeline_reads_the_capture(procedural_capture):
    """The pipeline's own capture reader and raw decoder accept what the simulator writes."""
    capture_module = pytest.importorskip("pipeline.capture")
    raw_module = pytest.importorskip("pipeline.codecs.raw")
    out, _ = procedural_capture
    capture = capture_module.open_capture(out)
    frames, errors = capture.action_frames("A0001")
    assert not errors and len(frames) == 3 * 4
    decoded = raw_module.decode_raw(frames[("full_on", "00002")], expected_size=(96, 64))
    assert decoded.rgb.shape == (96, 64, 3) and np.all(np.isfinite(decoded.rgb))
    assert capture.background_path("S001", "00003") is not None


def test_white_reference_reproduces_albedo(tmp_path, sphere_obj):
    """full_on / white_reference = albedo for unoccluded Lambertian points, on rawpy-decoded frames."""
    config = SimConfig(mesh=str(sphere_obj), actions=1, width=128, n_cameras=2, n_leds=128, noise=False,
                       specular=False, background=False)
    out = simulate(tmp_path / "cap", config)
    rig = json.loads((out / "sessions" / "S000" / "rig.json").read_text())
    from pipeline.codecs.exr import read_exr

    for cam in rig["cameras"]:
        decoded = rawpy_decode(out / "actions" / "A0000" / "full_on" / f"{cam['camera_id']}.dng", half_size=True)
        albedo = read_exr(out / "ground_truth" / "A0000" / "albedo" / f"{cam['camera_id']}.exr")
        visibility = read_exr(out / "ground_truth" / "A0000" / "visibility" / f"{cam['camera_id']}.exr")
        h, w = decoded.shape[:2]
        albedo_half = albedo[:2 * h, :2 * w].reshape(h, 2, w, 2, 3).mean(axis=(1, 3))
        solid = (visibility[:2 * h, :2 * w].reshape(h, 2, w, 2).min(axis=(1, 3)) > 0.999)
        ratio = decoded[solid] / np.asarray(cam["white_reference"]) / albedo_half[solid]
        assert solid.sum() > 100
        print(f"\ncamera {cam['camera_id']}: median decoded / (white_reference * albedo) = {np.median(ratio, axis=0)}")
        np.testing.assert_allclose(np.median(ratio, axis=0), 1.0, atol=0.01)


def test_same_seed_gives_identical_raw_files(tmp_path):
    config = SimConfig(mesh="procedural", actions=1, **TINY)
    first = simulate(tmp_path / "a", config)
    second = simulate(tmp_path / "b", config)
    raws = sorted(p.relative_to(first) for p in first.rglob("*.dng"))
    assert len(raws) == 4 * 3 + 4
    for rel in raws:
        assert (first / rel).read_bytes() == (second / rel).read_bytes(), rel
    other = simulate(tmp_path / "c", SimConfig(mesh="procedural", actions=1, seed=1, **TINY))
    assert (other / raws[0]).read_bytes() != (first / raws[0]).read_bytes()


def test_output_folder_rules(tmp_path):
    config = SimConfig(mesh="procedural", actions=1, width=32, n_cameras=1, n_leds=32, background=False)
    out = simulate(tmp_path / "cap", config)
    (out / "actions" / "A0000" / "full_on" / "00099.dng").write_bytes(b"stale")
    simulate(out, config)  # a previous simulated capture is replaced, stale files included
    assert not (out / "actions" / "A0000" / "full_on" / "00099.dng").exists()
    assert (out / "capture.json").is_file()
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError):
        simulate(tmp_path / "other", config)
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


# --- the MakeHuman subject (needs ../shared) ------------------------------------------------------------

@needs_shared
def test_makehuman_subject_geometry_and_materials():
    base = subject.load_base_subject(str(MAKEHUMAN), 1)
    height = base.y_range[1] - base.y_range[0]
    assert base.kind == "makehuman" and 1.5 < height < 1.9
    assert base.corner_uvs is not None and base.corner_uvs.shape == (len(base.triangles), 3, 2)
    assert len(base.skins) >= 1
    regions = subject.region_of(base, base.vertices)
    assert set(np.unique(regions)) == {subject.SKIN, subject.SHIRT, subject.TROUSERS, subject.SHINY}
    a = subject.make_action_subject(base, np.random.default_rng(1), 0, 0.004)
    b = subject.make_action_subject(base, np.random.default_rng(2), 1, 0.004)
    assert a.skin_name != b.skin_name and a.yaw_rad != b.yaw_rad
    assert a.cloth.shirt_pattern != b.cloth.shirt_pattern
    displacement = np.linalg.norm(a.vertices_rest - base.vertices, axis=1)
    clothed = np.isin(regions, (subject.SHIRT, subject.TROUSERS))
    assert displacement[clothed].max() > 0.002 and displacement[regions == subject.SKIN].max() < 0.004
    albedo, roughness, f0, _ = a.materials(base.vertices[:5000], None)
    assert albedo.shape == (5000, 3) and np.all((albedo >= 0) & (albedo <= 1))


@needs_shared
def test_makehuman_capture(tmp_path):
    out = simulate(tmp_path / "cap", SimConfig(actions=2, **TINY))
    capture = json.loads((out / "capture.json").read_text())
    assert capture["actions"][0]["subject"].startswith("makehuman/")
    truths = [json.loads((out / "ground_truth" / a / "truth.json").read_text()) for a in ("A0000", "A0001")]
    assert truths[0]["subject"]["yaw_deg"] != truths[1]["subject"]["yaw_deg"]
    assert truths[0]["subject"]["skin"] != truths[1]["subject"]["skin"]
    from pipeline.codecs.exr import read_exr

    roughness = np.concatenate([read_exr(out / "ground_truth" / "A0000" / "roughness" / f"{c:05d}.exr").ravel()
                                for c in range(4)])
    present = np.unique(roughness[roughness > 0]).astype(np.float64)
    for expected in (0.25, 0.45, 0.7, 0.8):  # shiny leather, skin, trousers, shirt
        assert np.isclose(present, expected, atol=2e-3).any(), (expected, present)


def test_actions_rendered_side_by_side_write_the_same_files(tmp_path, monkeypatch):
    """Actions render in forked processes when there are several, the sessions' calibration frames and clean
    plates written beside them: byte-identical files, progress kept."""
    import hashlib

    from synthetic.calibration import CalibrationConfig
    from synthetic.simulate import action_workers

    def digests(root: Path) -> dict[str, str]:
        return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(root.rglob("*")) if p.is_file()}

    config = SimConfig(mesh="procedural", actions=3, sessions=2, **TINY)
    runs = {}
    for workers in ("1", "2"):
        monkeypatch.setenv("ULTRASTAGE_SIMULATE_WORKERS", workers)
        assert action_workers(3) == int(workers)
        messages: list[str] = []
        runs[workers] = digests(simulate(tmp_path / f"cap{workers}", config, progress=messages.append,
                                         calibration=CalibrationConfig()))
        assert any(m.startswith("A0002: done") for m in messages), messages
        for session in ("S000", "S001"):
            assert any(m.startswith(f"session {session}: calibration frames and clean plates in") for m in messages)
    assert runs["1"] == runs["2"] and len(runs["1"]) > 10
    assert any("/calibration/" in name for name in runs["1"]) and any("/background/" in name for name in runs["1"])
    monkeypatch.setenv("ULTRASTAGE_SIMULATE_WORKERS", "8")
    assert action_workers(3) == 3 and action_workers(1) == 1


def test_ggx_weights_in_place_are_the_formula_bit_for_bit():
    """The float32 path of ggx_weights (reused buffers) gives the formula's bits, grazing and back-facing
    views included, so captures and relit references do not change with it."""
    from synthetic import geometry
    from synthetic.shading import _ggx_weights_float32, _ggx_weights_formula, ggx_weights

    rng = np.random.default_rng(7)
    for count in (64, 2048):
        normals = geometry.normalize(rng.normal(size=(300, 3))).astype(np.float32)
        views = geometry.normalize(rng.normal(size=(300, 3)) + 1.5 * normals).astype(np.float32)
        lights = geometry.fibonacci_sphere(count).astype(np.float32)
        views[:4] = -normals[:4]
        normals[4:8], views[4:8] = lights[:4], -lights[:4]
        a2 = (rng.uniform(0.05, 0.9, (300, 1)) ** 4).astype(np.float32)
        f0 = rng.uniform(0.02, 0.05, (300, 1)).astype(np.float32)
        fast = _ggx_weights_float32(normals, views, lights, a2, f0)
        formula = _ggx_weights_formula(normals, views, lights, a2, f0)
        assert fast.dtype == formula.dtype == np.float32
        assert np.array_equal(fast.view(np.uint32), formula.view(np.uint32))
        alpha = np.sqrt(a2[:, 0])
        squared = (alpha * alpha)[:, None]
        assert np.array_equal(ggx_weights(normals, views, lights, alpha, f0[:, 0]).view(np.uint32),
                              _ggx_weights_formula(normals, views, lights, squared, f0).view(np.uint32))
        wide = normals.astype(np.float64)  # other dtypes take the formula
        assert np.array_equal(ggx_weights(wide, views, lights, alpha, f0[:, 0]),
                              _ggx_weights_formula(wide, views, lights, squared, f0))


def test_the_fused_ggx_loop_gives_the_numpy_bits_with_and_without_visibility(monkeypatch):
    """synthetic.kernels' loop (ggx_weights' float32 path, and specular_radiance's weights times the corners'
    visibility) against the numpy steps it replaces, bit for bit: the capture does not depend on whether a C
    compiler was there."""
    from synthetic import geometry, kernels, shading
    from synthetic.shading import _ggx_weights_formula, ggx_weights, specular_radiance

    if not kernels.kernel_available():
        pytest.skip("no C compiler here: the numpy path is the only one")
    rng = np.random.default_rng(11)
    n, vertices = 500, 40
    normals = geometry.normalize(rng.normal(size=(n, 3))).astype(np.float32)
    views = geometry.normalize(rng.normal(size=(n, 3)) + 1.5 * normals).astype(np.float32)
    views[:4] = -normals[:4]  # back-facing views: n.v clamped
    lights = geometry.fibonacci_sphere(300).astype(np.float32)
    normals[4:8], views[4:8] = lights[:4], -lights[:4]  # 1 + v.l = 0 for one light each
    alpha = rng.uniform(0.05, 0.9, n).astype(np.float32) ** 2
    f0 = rng.uniform(0.02, 0.05, n).astype(np.float32)
    squared = (alpha * alpha).astype(np.float32)[:, None]
    assert np.array_equal(ggx_weights(normals, views, lights, alpha, f0).view(np.uint32),
                          _ggx_weights_formula(normals, views, lights, squared, f0[:, None]).view(np.uint32))

    table = rng.uniform(0.0, 2.0, (len(lights), 9)).astype(np.float32)
    visible = rng.integers(0, 256, (vertices, len(lights)), dtype=np.uint8)
    lighting = shading.SurfaceLighting(np.zeros((vertices, 9), np.float32), np.zeros(vertices, np.float32),
                                       shading.EXACT_LEVELS, (shading.cluster_leds(lights, table, None),), (visible,))
    tri = rng.integers(0, vertices, (n, 3))
    bary = rng.dirichlet(np.ones(3), n).astype(np.float32) * np.float32(255)
    roughness = np.sqrt(alpha)
    fused = specular_radiance(normals, views, roughness, f0, tri, bary, lighting)
    monkeypatch.setattr(kernels, "kernel_available", lambda: False)
    reference = specular_radiance(normals, views, roughness, f0, tri, bary, lighting)
    assert np.any(reference != 0)
    assert np.array_equal(fused.view(np.uint32), reference.view(np.uint32))


def test_the_numpy_path_is_taken_when_asked_for():
    """``ULTRASTAGE_SIM_KERNEL=numpy`` leaves the fused loop out (a library that cannot be built is
    pipeline.ckernel's case, tested there)."""
    out = subprocess.run([sys.executable, "-c", "from synthetic import kernels; print(kernels.kernel_available())"],
                         env=os.environ | {"ULTRASTAGE_SIM_KERNEL": "numpy"}, capture_output=True, text=True,
                         check=True, cwd=Path(__file__).resolve().parents[3])
    assert out.stdout.strip() == "False"


def test_vertex_visibility_traces_every_vertex_led_pair_above_the_horizon():
    """vertex_visibility (rays built LED by LED, in chunks) against one shadow ray per (vertex, LED) pair."""
    import open3d as o3d

    from synthetic import geometry
    from synthetic.shading import SHADOW_OFFSET_M, raycasting_scene, vertex_visibility
    from synthetic.subject import load_base_subject

    base = load_base_subject(None, 0)
    vertices = base.vertices.astype(np.float32)
    normals = geometry.normalize(np.random.default_rng(3).normal(size=vertices.shape)).astype(np.float32)
    directions = geometry.fibonacci_sphere(48)
    scene = raycasting_scene(vertices, base.triangles)
    visible = vertex_visibility(scene, vertices, normals, directions, chunk=1000)
    above = normals @ directions.astype(np.float32).T > 0.0
    v, l = np.nonzero(above)
    rays = np.concatenate([vertices[v] + SHADOW_OFFSET_M * normals[v], directions.astype(np.float32)[l]], axis=1)
    expected = np.zeros_like(above)
    expected[v, l] = ~scene.test_occlusions(o3d.core.Tensor(np.ascontiguousarray(rays, np.float32))).numpy()
    assert visible.shape == above.shape and np.array_equal(visible, expected)
    assert 0 < expected.sum() < above.sum()  # some rays blocked, some not
