"""Texture baking: atlas rasterization, bilinear sampling, dilation and multi-view baking of an analytic
sphere seen by synthetic cameras (images rendered by ray casting the same mesh)."""
from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from stages.numerics.bake import (
    BakeResult,
    BakeView,
    bake_textures,
    dilate_texture,
    rasterize_atlas,
    sample_pixels,
    sample_texture,
)
from artifacts.atlas import Atlas
from stages.numerics.mesh import uv_atlas
from synthetic.rig import look_at as rig_look_at

RADIUS = 0.3
CENTRE = np.array([0.02, -0.01, 0.03])
OCCLUDER_COLOUR = 5.0


def sphere_mesh(radius=RADIUS, centre=CENTRE, resolution=24):
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    v = np.asarray(mesh.vertices) + centre
    return v.astype(np.float32), np.asarray(mesh.triangles, np.int32)


def albedo_of(points, centre=CENTRE, radius=RADIUS):
    return (0.5 + 0.5 * (points - centre) / radius).astype(np.float32)


def look_at(centre, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """OpenCV cam_from_world (3, 4) of a camera at ``centre`` looking at ``target``, world +y up."""
    return rig_look_at(np.asarray(centre, float), np.asarray(target, float))


def render_view(vertices, faces, cam_from_world, size=96, focal=150.0, spheres=((CENTRE, RADIUS),)):
    """Ray-cast the mesh; albedo = 0.5 + 0.5 (X - c) / r of the first sphere, OCCLUDER_COLOUR on others;
    normal = the sphere's radial direction."""
    k = np.array([[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]])
    rot, t = cam_from_world[:, :3], cam_from_world[:, 3]
    centre = -rot.T @ t
    cols, rows = np.meshgrid(np.arange(size, dtype=float), np.arange(size, dtype=float))
    pix = np.stack([cols, rows, np.ones_like(cols)], -1).reshape(-1, 3)
    dirs = pix @ np.linalg.inv(k).T @ rot
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(faces.astype(np.uint32)))
    rays = np.concatenate([np.broadcast_to(centre, dirs.shape), dirs], 1).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(float)
    hit = np.isfinite(t_hit)
    points = centre + np.where(hit, t_hit, 0.0)[:, None] * dirs
    dists = np.stack([np.abs(np.linalg.norm(points - c, axis=1) - r) for c, r in spheres], 1)
    which = dists.argmin(1)
    albedo = albedo_of(points)
    albedo[which > 0] = OCCLUDER_COLOUR
    normal = np.zeros_like(points)
    for i, (c, r) in enumerate(spheres):
        sel = which == i
        normal[sel] = (points[sel] - c) / np.linalg.norm(points[sel] - c, axis=1, keepdims=True)
    albedo[~hit] = 0
    normal[~hit] = 0
    images = {"albedo": albedo.reshape(size, size, 3).astype(np.float32),
              "normal": normal.reshape(size, size, 3).astype(np.float32)}
    return BakeView(images=images, valid=hit.reshape(size, size), K=k, cam_from_world=cam_from_world)


def ring_cameras(n=8, distance=2.0):
    views = []
    for i in range(n):
        a = 2 * np.pi * i / n
        elevation = 0.6 if i % 2 else -0.6  # alternate above/below so the poles are seen too
        views.append(look_at((distance * np.cos(a), elevation, distance * np.sin(a)), target=CENTRE))
    return views


@pytest.fixture(scope="module")
def sphere_atlas():
    v, f = sphere_mesh()
    return v, f, uv_atlas(v, f, resolution=256)


@pytest.fixture(scope="module")
def sphere_bake(sphere_atlas):
    v, f, atlas = sphere_atlas
    views = [render_view(v, f, cam) for cam in ring_cameras()]
    return bake_textures(v, f, atlas, views, texture_size=256)


# ------------------------------------------------------------------------------------ sample_texture
def test_sample_texture_hand_computed():
    tex = np.arange(16, dtype=np.float32).reshape(4, 4)  # value = 4 * row + col
    # texel (row 1, col 2) centre: u = 2.5 / 4, v = 1 - 1.5 / 4
    assert sample_texture(tex, np.array([2.5 / 4, 1 - 1.5 / 4])) == pytest.approx(6.0)
    # halfway between rows 1 and 2 and cols 0 and 1: mean of 4, 5, 8, 9
    assert sample_texture(tex, np.array([1.0 / 4, 1 - 2.0 / 4])) == pytest.approx(6.5)
    # outside the texture clamps to the edge texel (top-left = row 0, col 0 is u 0, v 1)
    assert sample_texture(tex, np.array([-1.0, 2.0])) == pytest.approx(0.0)
    rgb = np.stack([tex, 2 * tex, -tex], -1)
    out = sample_texture(rgb, np.zeros((5, 7, 2)))
    assert out.shape == (5, 7, 3) and out.dtype == np.float32
    assert np.allclose(out[0, 0], [12, 24, -12])  # u 0, v 0 = bottom-left texel (row 3, col 0)


def test_sample_texture_rejects_bad_shapes():
    with pytest.raises(ValueError, match="uv"):
        sample_texture(np.zeros((4, 4)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="texture"):
        sample_texture(np.zeros(4), np.zeros((3, 2)))


# ---------------------------------------------------------------------------------------- dilation
def test_dilate_texture_grows_by_iterations_and_averages():
    filled = np.zeros((9, 9), bool)
    filled[4, 4] = True
    tex = np.zeros((9, 9, 2), np.float32)
    tex[4, 4] = (2.0, -1.0)
    tex[0, 0] = 99.0  # an empty texel's value is ignored
    out, grown = dilate_texture({"t": tex}, filled, 2)
    assert grown.sum() == 25 and grown[2:7, 2:7].all()
    assert np.allclose(out["t"][grown], (2.0, -1.0))
    assert (out["t"][~grown] == 0).all()
    # two sources: a texel between them takes their mean
    filled = np.zeros((1, 3), bool)
    filled[0, [0, 2]] = True
    out, _ = dilate_texture({"t": np.array([[1.0, 0.0, 3.0]], np.float32)}, filled, 1)
    assert out["t"][0, 1] == pytest.approx(2.0)


# ------------------------------------------------------------------------------------- rasterization
def test_rasterize_single_triangle_hand_computed():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    f = np.array([[0, 1, 2]], np.int32)
    # uv = xy: a right triangle covering the lower-left half of the texture
    atlas = Atlas(vmapping=np.arange(3), faces=f, uvs=v[:, :2].copy(), width=4, height=4, stats={})
    r = rasterize_atlas(v, f, atlas, 4)
    assert r["covered"].dtype == bool and r["face"].dtype == np.int32
    # texel (row, col) centre at u = (col + .5) / 4, v = 1 - (row + .5) / 4; inside when u + v <= 1
    rows, cols = np.mgrid[0:4, 0:4]
    expected = (cols + 0.5) / 4 + 1 - (rows + 0.5) / 4 <= 1
    assert np.array_equal(r["covered"], expected)
    assert (r["face"][expected] == 0).all() and (r["face"][~expected] == -1).all()
    u, vv = (cols + 0.5) / 4, 1 - (rows + 0.5) / 4
    assert np.allclose(r["position"][expected], np.stack([u, vv, 0 * u], -1)[expected], atol=1e-6)
    assert np.allclose(r["normal"][expected], (0, 0, 1))
    assert (r["position"][~expected] == 0).all()


def test_rasterize_atlas_points_lie_on_sphere(sphere_atlas):
    v, f, atlas = sphere_atlas
    r = rasterize_atlas(v, f, atlas, 256)
    cov = r["covered"]
    assert 0.4 < cov.mean() < 0.95  # xatlas packs ~70-85%
    p = r["position"][cov]
    radius = np.linalg.norm(p - CENTRE, axis=1)
    assert radius.max() <= RADIUS + 1e-5 and radius.min() > RADIUS * 0.98  # on the chords
    radial = (p - CENTRE) / radius[:, None]
    assert np.einsum("nd,nd->n", r["normal"][cov], radial).min() > 0.99
    # each texel's barycentrics reproduce its position from its face
    fid = r["face"][cov]
    tri = v[atlas.vmapping[atlas.faces[fid]]]
    assert np.allclose(np.einsum("nk,nkd->nd", r["barycentric"][cov], tri), p, atol=1e-5)


def test_rasterize_rejects_foreign_atlas(sphere_atlas):
    v, f, atlas = sphere_atlas
    with pytest.raises(ValueError, match="atlas"):
        rasterize_atlas(v, f[:10], atlas, 64)


# -------------------------------------------------------------------------------------------- baking
def test_bake_sphere_matches_known_albedo_and_normals(sphere_atlas, sphere_bake):
    v, f, atlas = sphere_atlas
    res: BakeResult = sphere_bake
    assert set(res.textures) == {"albedo", "normal"}
    for tex in res.textures.values():
        assert tex.shape == (256, 256, 3) and tex.dtype == np.float32 and np.isfinite(tex).all()
    assert res.view_count.dtype == np.uint8 and res.confidence.dtype == np.float32
    assert res.stats["coverage"] > 0.98
    assert 2.0 < res.stats["mean_view_count"] <= 3.0
    assert res.view_count.max() == 3 and (res.view_count[~res.covered] == 0).all()
    assert 0 <= res.confidence.min() and res.confidence.max() <= 1
    assert res.confidence[res.view_count > 0].mean() > 0.5
    # sampled back at the vertices (chart corners and edges included): the known function
    points = v[atlas.vmapping]
    albedo = sample_texture(res.textures["albedo"], atlas.uvs)
    err = np.abs(albedo - albedo_of(points))
    assert np.median(err) < 0.01 and np.percentile(err, 99) < 0.05
    normal = sample_texture(res.textures["normal"], atlas.uvs)
    radial = (points - CENTRE) / np.linalg.norm(points - CENTRE, axis=1, keepdims=True)
    cos = np.einsum("nd,nd->n", normal / np.linalg.norm(normal, axis=1, keepdims=True), radial)
    assert np.degrees(np.arccos(np.clip(np.median(cos), -1, 1))) < 1.0 and cos.min() > 0.9
    # normals are renormalised to unit where seen or dilated
    n = np.linalg.norm(res.textures["normal"], axis=2)
    assert np.allclose(n[res.view_count > 0], 1.0, atol=1e-4)


def test_bake_dilation_fills_empty_texels_next_to_charts(sphere_bake):
    res = sphere_bake
    seen = res.view_count > 0
    filled = np.linalg.norm(res.textures["normal"], axis=2) > 0
    assert res.stats["dilated_texels"] > 0
    assert (filled & ~seen).sum() == res.stats["dilated_texels"]
    # every empty texel next to a seen one got a value
    from scipy import ndimage
    ring = ndimage.binary_dilation(seen, structure=np.ones((3, 3))) & ~seen
    assert filled[ring].all()


def test_bake_occluded_texels_get_nothing_from_the_hidden_view():
    v1, f1 = sphere_mesh(resolution=16)
    occ_centre, occ_radius = np.array([0.0, 0.0, 0.75]), 0.15
    v2, f2 = sphere_mesh(radius=occ_radius, centre=occ_centre, resolution=8)
    v = np.concatenate([v1, v2]).astype(np.float32)
    f = np.concatenate([f1, f2 + len(v1)]).astype(np.int32)
    atlas = uv_atlas(v, f, resolution=128)
    spheres = ((CENTRE, RADIUS), (occ_centre, occ_radius))
    # camera 0 looks straight through the occluder at the big sphere; camera 1 sees it from the side
    cams = [look_at((0.0, 0.0, 2.5), target=CENTRE), look_at((1.8, 0.0, 1.8), target=CENTRE)]
    views = [render_view(v, f, c, spheres=spheres) for c in cams]
    res = bake_textures(v, f, atlas, views, texture_size=128, max_views=2, dilate_px=0)
    r = rasterize_atlas(v, f, atlas, 128)
    on_big = r["covered"] & (r["face"] < len(f1)) & (res.view_count > 0)
    assert on_big.sum() > 500
    albedo = res.textures["albedo"][on_big]
    # no texel of the big sphere ever takes the occluder's colour, and all match the known function
    assert albedo.max() < 1.5
    assert np.percentile(np.abs(albedo - albedo_of(r["position"][on_big])), 99) < 0.05
    # the shadowed patch (behind the occluder as seen from camera 0) is baked from camera 1 only
    p = r["position"]
    ray = CENTRE - np.array([0.0, 0.0, 2.5])
    ray /= np.linalg.norm(ray)
    to_p = p - np.array([0.0, 0.0, 2.5])
    perp = np.linalg.norm(to_p - (to_p @ ray)[..., None] * ray, axis=-1)
    shadowed = on_big & (perp < 0.05) & (p[..., 2] > CENTRE[2])
    assert shadowed.sum() > 10
    assert (res.view_count[shadowed] == 1).all()


def test_bake_no_views_see_it_and_bad_inputs(sphere_atlas):
    v, f, atlas = sphere_atlas
    view = render_view(v, f, look_at((0, 0, 2.0), target=CENTRE))
    blind = BakeView(images=view.images, valid=np.zeros_like(view.valid), K=view.K,
                     cam_from_world=view.cam_from_world)
    res = bake_textures(v, f, atlas, [blind], texture_size=64)
    assert res.stats["coverage"] == 0 and (res.view_count == 0).all()
    assert all((t == 0).all() for t in res.textures.values()) and (res.confidence == 0).all()
    with pytest.raises(ValueError, match="at least one view"):
        bake_textures(v, f, atlas, [], texture_size=64)
    albedo_only = BakeView(images={"albedo": view.images["albedo"]}, valid=view.valid, K=view.K,
                           cam_from_world=view.cam_from_world)
    res = bake_textures(v, f, atlas, [albedo_only], texture_size=64)  # default normalize=("normal",)
    assert set(res.textures) == {"albedo"} and res.stats["coverage"] > 0.3
    with pytest.raises(ValueError, match="max_views"):
        bake_textures(v, f, atlas, [view], texture_size=64, max_views=0)
    with pytest.raises(ValueError, match="differ"):
        bake_textures(v, f, atlas, [view, albedo_only], texture_size=64)


def test_bake_ignores_non_finite_pixels(sphere_atlas, sphere_bake):
    v, f, atlas = sphere_atlas
    clean = [render_view(v, f, cam) for cam in ring_cameras()]

    def with_albedo(view, albedo):
        return BakeView(images={"albedo": albedo, "normal": view.images["normal"]}, valid=view.valid,
                        K=view.K, cam_from_world=view.cam_from_world)

    # NaN outside the valid mask changes nothing (zero-weight taps must not spread it)
    nan_outside = []
    for view in clean:
        albedo = view.images["albedo"].copy()
        albedo[~view.valid] = np.nan
        nan_outside.append(with_albedo(view, albedo))
    res = bake_textures(v, f, atlas, nan_outside, texture_size=256)
    assert np.array_equal(res.view_count, sphere_bake.view_count)
    assert np.allclose(res.textures["albedo"], sphere_bake.textures["albedo"], atol=1e-6)
    # Inf inside it: those pixels count as invalid, the rest still bakes the known function
    rng = np.random.default_rng(0)
    inf_inside = []
    for view in clean:
        albedo = view.images["albedo"].copy()
        albedo[(rng.random(view.valid.shape) < 0.02) & view.valid] = np.inf
        inf_inside.append(with_albedo(view, albedo))
    res = bake_textures(v, f, atlas, inf_inside, texture_size=256)
    assert all(np.isfinite(t).all() for t in res.textures.values()) and np.isfinite(res.confidence).all()
    assert res.stats["coverage"] > 0.98
    err = np.abs(sample_texture(res.textures["albedo"], atlas.uvs) - albedo_of(v[atlas.vmapping]))
    assert np.percentile(err, 99) < 0.05


def test_texture_in_camera_hand_computed_on_a_quad():
    from stages.numerics.bake import texture_in_camera
    from stages.numerics.raycast import mesh_scene

    # a 2 m square at z = 2 facing the camera at the origin, u = (x + 1) / 2, v = (1 - y) / 2 (y down)
    vertices = np.array([[-1, -1, 2], [1, -1, 2], [1, 1, 2], [-1, 1, 2]], np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    uvs = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    texture = np.tile(np.arange(4, dtype=np.float32), (4, 1))  # value = texel column
    K = np.array([[50.0, 0, 49.5], [0, 50.0, 49.5], [0, 0, 1]])
    pose = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
    values, hit = texture_in_camera(mesh_scene(vertices, faces), faces, uvs, texture, K, pose, 100, 100)
    assert values.shape == (100, 100) and hit.shape == (100, 100)
    x = (np.arange(100) - 49.5) / 50.0 * 2.0  # world x of each column's ray at z = 2
    inside = np.abs(x) < 1.0
    assert hit[50][inside].all() and not hit[50][~inside].any()
    expected = np.clip((x + 1) / 2 * 4 - 0.5, 0, 3)  # bilinear lookup of a linear texture is exact
    assert np.allclose(values[50][inside], expected[inside], atol=1e-4)
    assert np.all(values[50][~inside] == 0)
    rgb, _ = texture_in_camera(mesh_scene(vertices, faces), faces, uvs, np.stack([texture] * 3, -1), K, pose, 100, 100)
    assert rgb.shape == (100, 100, 3) and np.allclose(rgb[..., 1], values)
    with pytest.raises(ValueError, match="texture"):
        texture_in_camera(mesh_scene(vertices, faces), faces, uvs, np.zeros(4), K, pose, 100, 100)


def test_sample_pixels_interpolates_between_pixel_centres_and_clamps_outside():
    image = np.array([[0.0, 1.0], [2.0, 3.0]], np.float16)  # float16, as the silhouette step's coverage maps
    values = sample_pixels(image, np.array([0.0, 1.0, 0.5, 0.25, -3.0, 7.0]), np.array([0.0, 1.0, 0.5, 1.0, 0.0, 9.0]))
    np.testing.assert_allclose(values, [0.0, 3.0, 1.5, 2.25, 0.0, 3.0], atol=1e-6)
    assert values.dtype == np.float32
    assert sample_pixels(image, np.array([0.25]), np.array([0.0]), np.float64).dtype == np.float64
    rgb = np.stack([image, 2 * image, 3 * image], axis=-1).astype(np.float32)
    np.testing.assert_allclose(sample_pixels(rgb, np.array([0.5]), np.array([0.5])), [[1.5, 3.0, 4.5]], atol=1e-6)
