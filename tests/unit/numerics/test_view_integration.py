"""shade_gbuffer's environment integration (ViewShading.integration) on a ray-cast sphere standing on a floor."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from artifacts.camera import Camera
from stages.numerics.novel_view import ViewShading, shade_gbuffer
from stages.numerics.raycast import mesh_scene, render_mesh
from stages.numerics.sg import SGLobes


def sphere_on_floor():
    import open3d as o3d

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=0.3, resolution=24)
    vertices = np.asarray(sphere.vertices) + [0.0, 0.3, 0.0]
    faces = np.asarray(sphere.triangles)
    floor_v = np.array([[-2.0, 0.0, -2.0], [2.0, 0.0, -2.0], [2.0, 0.0, 2.0], [-2.0, 0.0, 2.0]])
    floor_f = np.array([[0, 2, 1], [0, 3, 2]]) + len(vertices)
    return np.vstack([vertices, floor_v]), np.vstack([faces, floor_f])


def gbuffer(scene, K, pose, h, w) -> dict:
    seen = render_mesh(None, None, K, pose, h, w, scene=scene)
    mask = seen["hit"]
    pix = np.flatnonzero(mask.reshape(-1))
    camera = Camera(K, pose, w, h)
    points = camera.lift_depth_map(seen["depth_m"]).reshape(-1, 3)[pix]
    view = camera.centre[None] - points
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    ones = np.where(mask, 1.0, 0.0).astype(np.float32)
    return {"mask": mask, "hit": mask, "pix": pix, "points": points, "view_dirs": view,
            "normal_fused": seen["normals_world"], "albedo": 0.5 * np.repeat(ones[..., None], 3, axis=2),
            "diffuse_ratio": np.repeat(ones[..., None], 3, axis=2), "occlusion": ones, "roughness": 0.45 * ones}


@pytest.fixture(scope="module")
def view():
    vertices, faces = sphere_on_floor()
    scene = mesh_scene(vertices, faces)
    h, w = 48, 64
    K = np.array([[60.0, 0.0, w / 2], [0.0, 60.0, h / 2], [0.0, 0.0, 1.0]])
    # looking at the sphere from 2 m, 30 degrees above the floor (OpenCV: y down in the image)
    eye = np.array([0.0, 1.0 + 0.3, 1.73])
    forward = np.array([0.0, 0.3, 0.0]) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    pose = np.concatenate([R, (-R @ eye)[:, None]], axis=1)
    lobes = SGLobes(np.array([[0.0, 1.0, 0.0], [0.6, 0.6, 0.53]], np.float32), np.array([2.0, 40.0], np.float32),
                    np.array([[1.0, 1.0, 1.0], [4.0, 3.0, 2.0]], np.float32))
    return scene, gbuffer(scene, K, pose, h, w), K, pose, lobes


def test_directions_and_closed_forms_agree_on_the_whole_and_stay_finite(view):
    """The sum over the 256 visibility directions against the lobes' closed forms, both with the floor and the
    sphere occluding, each cell lighting from its energy's mean direction (``cell_centroids``): measured 0.84% mean
    relative difference over the image (1.14% from the cells' own directions; bound 1.3%); with only the diffuse
    summed over the directions 0.30% (0.33%; bound 0.5%): the specular is where the two differ most. Both with the
    separable "physg" shadowing, which the closed forms' lobe warp follows more closely (with "smith" 1.63%)."""
    scene, gb, K, pose, lobes = view
    images = {}
    for integration in ("directions", "closed_form", "directions_diffuse"):
        out = shade_gbuffer(gb, scene, K, pose, [lobes], ViewShading(integration=integration, coverage_samples=1,
                                                                     shadowing="physg"))
        image = out["images"][0]
        assert np.all(np.isfinite(image)) and np.all(image >= 0)
        images[integration] = image[gb["mask"]]
    reference = images["closed_form"].mean()
    assert reference > 0
    assert np.abs(images["directions"] - images["closed_form"]).mean() / reference < 0.013
    assert np.abs(images["directions_diffuse"] - images["closed_form"]).mean() / reference < 0.005


def test_without_shadows_every_direction_above_the_horizon_lights(view):
    scene, gb, K, pose, lobes = view
    lit = shade_gbuffer(gb, scene, K, pose, [lobes], ViewShading(shadows=False, coverage_samples=1))["images"][0]
    shadowed = shade_gbuffer(gb, scene, K, pose, [lobes], ViewShading(coverage_samples=1))["images"][0]
    assert np.all(shadowed <= lit + 1e-6)
    # the sphere shadows the floor and the floor the sphere's underside: measured 0.942 of the light, bound 0.97
    assert shadowed.sum() < 0.97 * lit.sum()


def test_supersampled_intrinsics_put_a_pixels_samples_inside_its_square():
    from stages.numerics.novel_view import supersampled_intrinsics

    K = np.array([[100.0, 0.5, 10.0], [0.0, 90.0, 8.0], [0.0, 0.0, 1.0]])
    fine = supersampled_intrinsics(K, 2)
    np.testing.assert_allclose(fine, [[200.0, 1.0, 20.5], [0.0, 180.0, 16.5], [0.0, 0.0, 1.0]])
    # a point on pixel (3, 5)'s centre lies between fine pixels 6-7 and 10-11: on their shared corner
    ray = np.linalg.solve(K, [3.0, 5.0, 1.0])
    u, v, z = fine @ ray
    assert (u / z, v / z) == pytest.approx((6.5, 10.5))
    np.testing.assert_allclose(supersampled_intrinsics(K, 1), K)
    u, v, z = supersampled_intrinsics(K, 3) @ ray  # 3 x 3: the middle sample sits on the pixel's centre
    assert (u / z, v / z) == pytest.approx((10.0, 16.0))


def test_box_mean_by_hand_and_its_checks():
    from stages.numerics.novel_view import box_mean

    image = np.arange(4 * 6, dtype=np.float32).reshape(4, 6, 1)
    out = box_mean(image, 2)
    assert out.shape == (2, 3, 1) and out.dtype == np.float32
    assert out[0, 0, 0] == pytest.approx((0 + 1 + 6 + 7) / 4) and out[1, 2, 0] == pytest.approx((16 + 17 + 22 + 23) / 4)
    with pytest.raises(ValueError, match="2 x 2 blocks"):
        box_mean(image[:3], 2)


def test_supersampled_shading_of_the_sphere_agrees_with_the_pixel_centres_away_from_edges(view):
    """The sphere on its floor shaded on a 2 x 2 finer grid and box-filtered against one sample per pixel: within
    a few percent where a pixel and its neighbours are all inside (measured 0.70% mean relative difference, bound
    1.5%), and the supersampled alpha (2 x 2 rays per sample) equal to the 4 x 4 rays' of the pixel-centre one."""
    from stages.numerics.novel_view import box_mean, supersampled_intrinsics
    from scipy.ndimage import binary_erosion

    scene, gb, K, pose, lobes = view
    h, w = gb["mask"].shape
    fine_K = supersampled_intrinsics(K, 2)
    fine_gb = gbuffer(scene, fine_K, pose, 2 * h, 2 * w)
    coarse = shade_gbuffer(gb, scene, K, pose, [lobes], ViewShading(coverage_samples=4))
    fine = shade_gbuffer(fine_gb, scene, fine_K, pose, [lobes], ViewShading(coverage_samples=2))
    image = box_mean(fine["images"][0], 2)
    assert image.shape == (h, w, 3) and np.all(np.isfinite(image))
    inside = binary_erosion(gb["mask"], iterations=2)
    reference = coarse["images"][0][inside]
    assert np.abs(image[inside] - reference).mean() / reference.mean() < 0.015
    np.testing.assert_allclose(box_mean(fine["alpha"][..., None], 2)[..., 0], coarse["alpha"], atol=1e-6)


def test_relight_view_refuses_supersampling_with_a_learned_blend():
    from stages.numerics.novel_view import relight_view

    with pytest.raises(ValueError, match="supersample = 2 needs the heuristic blend"):
        relight_view(None, np.eye(3), np.eye(3, 4), 4, 4, [], ViewShading(supersample=2), blend=object())


def test_subject_window_by_hand():
    from stages.numerics.novel_view import crop_intrinsics, subject_window

    K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])
    pose = np.eye(3, 4)
    # projected to u in [40, 60.5], v in [30, 35]: pixels whose squares meet them, then 3 more on each side
    vertices = np.array([[-0.1, -0.1, 1.0], [0.105, -0.05, 1.0], [0.0, -0.05, 1.0]])
    # (rows 30-35 and columns 40-61: pixel 61's square [60.5, 61.5] meets u = 60.5, pixel 39's [38.5, 39.5] not 40)
    assert subject_window(vertices, K, pose, 80, 100, margin_px=0) == (30, 36, 40, 62)
    assert subject_window(vertices, K, pose, 80, 100) == (30 - 3, 36 + 3, 40 - 3, 62 + 3)
    assert subject_window(vertices, K, pose, 33, 100, margin_px=0) == (30, 33, 40, 62)  # clipped to the frame
    behind = np.vstack([vertices, [[0.0, 0.0, -1.0]]])
    assert subject_window(behind, K, pose, 80, 100) == (0, 80, 0, 100)
    assert subject_window(vertices + [5.0, 0.0, 0.0], K, pose, 80, 100) == (0, 80, 0, 100)  # off the frame
    with pytest.raises(ValueError, match="vertices must be"):
        subject_window(vertices[:, :2], K, pose, 80, 100)
    # the cut's pixel (0, 0) is the frame's (row0, col0)
    cut = crop_intrinsics(K, 26, 36)
    u, v, z = cut @ np.array([0.1, -0.05, 1.0])
    assert (u / z, v / z) == pytest.approx((60.0 - 36, 35.0 - 26))


SPHERE_VIEW = (40, 60, np.array([[70.0, 0.0, 60 / 2 - 0.3], [0.0, 70.0, 40 / 2 + 0.2], [0.0, 0.0, 1.0]]))
"""(height, width, K) of the sphere asset's views: the sphere is small in the frame."""


@pytest.fixture(scope="module")
def sphere_asset():
    """A sphere's relightable asset from 4 source views of a patterned albedo (whole frames), the sources cut to
    their subject windows by :func:`stages.relightable.windowed_source`, and a novel view and environment."""
    import dataclasses
    import open3d as o3d
    from stages.numerics.gbuffer import SourceView
    from stages.numerics.mesh import vertex_normals
    from artifacts.atlas import Atlas
    from stages.numerics.novel_view import ActionAsset, subject_window
    from stages.relightable import windowed_source
    from synthetic.rig import look_at

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=0.3, resolution=20)
    vertices = np.asarray(sphere.vertices, np.float64) + [0.0, 1.0, 0.0]
    faces = np.asarray(sphere.triangles, np.int64)
    scene = mesh_scene(vertices, faces)
    h, w, K = SPHERE_VIEW
    sources, cut_sources = [], []
    for angle in np.radians([0.0, 60.0, 120.0, 200.0]):
        eye = np.array([3.0 * np.sin(angle), 1.2, 3.0 * np.cos(angle)])
        pose = look_at(eye, np.array([0.0, 1.0, 0.0]))
        seen = render_mesh(None, None, K, pose, h, w, scene=scene)
        points = Camera(K, pose, w, h).lift_depth_map(np.where(seen["hit"], seen["depth_m"], 0.0))
        albedo = (0.4 + 0.3 * np.sin(25.0 * points)).astype(np.float32) * seen["hit"][..., None]
        normals = seen["normals_world"].astype(np.float32)
        sources.append(SourceView(normal=normals, albedo=albedo, valid=seen["hit"], K=K, cam_from_world=pose,
                                  depth_m=np.where(seen["hit"], seen["depth_m"], 0.0).astype(np.float32)))
        cut_sources.append(windowed_source(scene, K, pose, normals, albedo, seen["hit"],
                                           subject_window(vertices, K, pose, h, w)))
    uvs = np.stack([0.5 + 0.5 * np.arctan2(vertices[:, 0], vertices[:, 2]) / np.pi,
                    (vertices[:, 1] - 0.7) / 0.6], axis=1)
    texture = np.full((8, 8, 3), 0.5, np.float32)
    asset = ActionAsset(scene=scene, faces=faces, smooth_normals=vertex_normals(vertices, faces), sources=sources,
                        atlas_scene=scene, atlas=Atlas(np.arange(len(vertices)), faces, uvs, 8, 8, {}), albedo_tex=texture,
                        roughness_tex=np.full((8, 8), 0.4, np.float32), occlusion_tex=np.ones((8, 8), np.float32),
                        diffuse_ratio_tex=np.ones((8, 8, 3), np.float32), vertices=vertices)
    pose = look_at(np.array([2.6, 1.5, 2.0]), np.array([0.0, 1.0, 0.0]))
    lobes = SGLobes(np.array([[0.0, 1.0, 0.0], [0.6, 0.6, 0.53]], np.float32), np.array([2.0, 40.0], np.float32),
                    np.array([[1.0, 1.0, 1.0], [4.0, 3.0, 2.0]], np.float32))
    return asset, dataclasses.replace(asset, sources=cut_sources), pose, lobes


def _assert_same_view(cut: dict, whole: dict) -> None:
    assert whole["mask"].sum() > 100 and whole["pixels"] == cut["pixels"]
    np.testing.assert_array_equal(cut["mask"], whole["mask"])
    np.testing.assert_allclose(cut["alpha"], whole["alpha"], atol=1e-6)
    scale = float(whole["images"][0].max())
    np.testing.assert_allclose(cut["images"][0], whole["images"][0], rtol=0, atol=1e-5 * scale)
    for name, image in whole["maps"].items():
        np.testing.assert_allclose(cut["maps"][name], image, rtol=0, atol=1e-5)
    assert cut["normal_fusion_px"] == pytest.approx(whole["normal_fusion_px"])


@pytest.mark.parametrize("supersample", [1, 2])
def test_relight_view_of_the_subjects_window_is_the_whole_frames(sphere_asset, supersample):
    """A sphere seen small in its frame (its window is 14% of the pixels): the cropped render put into the frame
    equals the whole frame's render (the same mask and alpha, the images and maps within 1e-5 of their scale;
    measured identical)."""
    from stages.numerics.novel_view import relight_view, subject_window

    asset, _, pose, lobes = sphere_asset
    h, w, K = SPHERE_VIEW
    row0, row1, col0, col1 = subject_window(asset.vertices, K, pose, h, w)
    assert (row1 - row0) * (col1 - col0) < 0.2 * h * w
    shading = ViewShading(supersample=supersample, visibility_directions=64)
    _assert_same_view(relight_view(asset, K, pose, h, w, [lobes], shading),
                      relight_view(asset, K, pose, h, w, [lobes], shading, crop=False))


def test_sources_cut_to_their_windows_relight_as_the_whole_frames(sphere_asset):
    """The sphere's 4 sources cut to their windows (about a third of their frames' pixels, the mesh depth ray-cast
    there): the same cut's maps as the frames', and the novel view relit from them equal to the one from the whole
    frames (the projection into a cut source rounds differently in the last bits: measured identical here)."""
    from stages.numerics.novel_view import relight_view
    from stages.relightable import source_window

    asset, cut_asset, pose, lobes = sphere_asset
    h, w, K = SPHERE_VIEW
    camera = Camera(K, np.eye(3, 4), w, h)
    kept = 0
    for source, cut in zip(asset.sources, cut_asset.sources):
        row0, row1, col0, col1 = source_window(camera, cut)
        kept += cut.valid.size
        for name in ("normal", "albedo", "valid", "depth_m"):
            np.testing.assert_array_equal(getattr(cut, name), getattr(source, name)[row0:row1, col0:col1], err_msg=name)
        assert source.valid[row0:row1, col0:col1].sum() == source.valid.sum()  # nothing valid cut off
    assert kept < 0.5 * len(asset.sources) * h * w
    shading = ViewShading(supersample=1, visibility_directions=64)
    _assert_same_view(relight_view(cut_asset, K, pose, h, w, [lobes], shading),
                      relight_view(asset, K, pose, h, w, [lobes], shading))


def test_a_key_light_is_a_point_light_traced_from_its_own_axis(view):
    """A sun (sharpness 5,000: 0.8 degrees wide) 4 degrees off its cell's direction over a dim sky: with
    ``key_lights=1`` the image is the sky's (on the cells) plus a point light at the sun's axis whose visibility is
    traced there (:func:`stages.numerics.shadowing.direction_visibility`), to float32 rounding; on the cells
    instead (``key_lights=0``) the sphere's shadow on the floor falls from the cell's direction, and the pixels
    between the two shadow edges are wrong."""
    from stages.numerics.direction_lights import shade_directions
    from stages.numerics.sg import fibonacci_sphere, sg_integral
    from stages.numerics.shadowing import direction_visibility

    scene, gb, K, pose, _ = view
    cells = fibonacci_sphere(256)
    base = cells[np.argmax(cells @ np.array([0.5, 0.75, 0.43]))]  # a cell direction 50 degrees or so above the floor
    perp = np.cross(base, [0.0, 1.0, 0.0])
    perp /= np.linalg.norm(perp)
    sun = np.cos(np.radians(4.0)) * base + np.sin(np.radians(4.0)) * perp
    sky = SGLobes(np.array([[0.0, 1.0, 0.0]], np.float32), np.array([2.0], np.float32),
                  np.full((1, 3), 0.3, np.float32))
    sun_lobe = SGLobes(sun[None].astype(np.float32), np.array([5000.0], np.float32),
                       np.full((1, 3), 3000.0, np.float32))
    both = SGLobes(*(np.concatenate([a, b]) for a, b in zip(sky, sun_lobe)))
    shading = ViewShading(coverage_samples=1, cell_centroids=False)
    keyed = shade_gbuffer(gb, scene, K, pose, [both], dataclasses.replace(shading, key_lights=1))["images"][0]
    on_cells = shade_gbuffer(gb, scene, K, pose, [both], dataclasses.replace(shading, key_lights=0))["images"][0]
    sky_only = shade_gbuffer(gb, scene, K, pose, [sky], shading)["images"][0]
    pix = gb["pix"]
    normals = gb["normal_fused"].reshape(-1, 3)[pix]
    visible = direction_visibility(gb["points"], normals, scene, sun[None])
    point = shade_directions(normals, gb["view_dirs"], gb["albedo"].reshape(-1, 3)[pix],
                             gb["roughness"].reshape(-1)[pix],
                             np.asarray(sg_integral(sun_lobe), np.float64), visible, sun[None], f0=shading.f0,
                             shadowing=shading.shadowing)["rgb"]
    expected = sky_only.copy()
    expected.reshape(-1, 3)[pix] += point
    np.testing.assert_allclose(keyed, expected, rtol=1e-4, atol=1e-5 * float(expected.max()))
    cell_visible = direction_visibility(gb["points"], normals, scene, base[None])[:, 0]
    # on the floor, between the sphere's shadow from the sun and from its cell's direction
    edge = pix[(visible[:, 0] != cell_visible) & (normals[:, 1] > 0.99)]
    assert len(edge) >= 5
    wrong = np.abs(on_cells.reshape(-1, 3)[edge] - expected.reshape(-1, 3)[edge]).max(axis=1)
    assert np.all(wrong > 0.2 * np.abs(expected.reshape(-1, 3)[edge]).max())
