"""Materials stage helpers: surface_median, load_atlas_mesh (the textures stage's OBJ back), texel_uvs."""
from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from pipeline.codecs.mesh import write_obj
from pipeline.errors import InputError
from artifacts.facade import fitted_f0, load_atlas_mesh
from stages.numerics.material_textures import (ALBEDO_GUIDE_FLOOR, MaterialTexturesConfig, albedo_guide,
                                               diffuse_ratio_of, fit_texel_materials, fit_texel_roughness,
                                               roughness_median, surface_median, texel_uvs)
from stages.numerics.bake import sample_texture
from stages.numerics.mesh import uv_atlas, vertex_normals


# ----------------------------------------------------------------------------------- surface_median
def line(n=10):
    return np.stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)], 1)


def test_median_removes_an_outlier_on_a_line():
    values = np.ones(10, np.float32)
    values[5] = 100.0
    out = surface_median(line(), values, np.ones(10, bool), neighbours=3)
    assert out.shape == (10,) and out.dtype == np.float32
    np.testing.assert_array_equal(out, np.ones(10))
    # a linear ramp survives in the interior (median of x-1, x, x+1 is x); the ends see a one-sided window
    ramp = surface_median(line(), np.arange(10.0), np.ones(10, bool), neighbours=3)
    np.testing.assert_array_equal(ramp[1:-1], np.arange(1.0, 9.0))
    assert ramp[0] == 1.0 and ramp[-1] == 8.0


def test_median_uses_usable_points_only():
    values = np.ones(10, np.float32)
    values[[4, 5]] = 1000.0  # no observations there: neither used nor kept
    usable = np.ones(10, bool)
    usable[[4, 5]] = False
    out = surface_median(line(), values, usable, neighbours=3)
    np.testing.assert_array_equal(out, np.ones(10))  # unusable points take their usable neighbours' median
    # more neighbours than usable points: all usable points
    few = np.zeros(10, bool)
    few[[0, 9]] = True
    vals = np.arange(10.0, dtype=np.float32)
    np.testing.assert_array_equal(surface_median(line(), vals, few, neighbours=5), np.full(10, 4.5))


def test_median_identity_cases():
    rng = np.random.default_rng(0)
    pts, values = rng.normal(size=(20, 3)), rng.normal(size=20).astype(np.float32)
    same = surface_median(pts, values, np.ones(20, bool), neighbours=1)
    np.testing.assert_array_equal(same, values)
    assert same is not values  # a copy
    np.testing.assert_array_equal(surface_median(pts, values, np.zeros(20, bool), neighbours=5), values)


def test_guided_median_keeps_a_narrow_strip_of_another_material():
    """A strip one texel tall (a shiny belt, 0.25) across a patch of cloth (0.7), 20 x 5 texels 1 cm apart: the
    plain median over 15 neighbours (about 2 cm around) gives the strip the cloth's roughness; guided by the albedo
    (the strip darker by a factor e, a unit of log-albedo counting as 1 m) each texel's 15 nearest are its own
    material's (the strip holds 20), so every texel, the noisy ones too, takes its own material's roughness."""
    xs, ys = np.meshgrid(np.arange(20) * 0.01, np.arange(5) * 0.01)
    points = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    belt = np.isclose(ys.ravel(), 0.02)
    roughness = np.where(belt, 0.25, 0.7).astype(np.float32)
    roughness[[3, 45, 50]] = [0.9, 0.6, 0.1]  # noisy texels: two of the cloth, one of the strip
    albedo = np.where(belt[:, None], np.exp(-2.0), np.exp(-1.0)) * np.ones((len(points), 3))
    everyone = np.ones(len(points), bool)
    plain = surface_median(points, roughness, everyone, neighbours=15)
    assert np.all(plain[belt] == np.float32(0.7))  # the strip is lost
    guided = surface_median(points, roughness, everyone, 15, albedo_guide(albedo), guide_m=1.0)
    np.testing.assert_array_equal(guided[belt], np.float32(0.25))
    np.testing.assert_array_equal(guided[~belt], np.float32(0.7))
    # guide_m 0 (or no guide) is the plain median
    np.testing.assert_array_equal(surface_median(points, roughness, everyone, 15, albedo_guide(albedo), 0.0), plain)
    same, _ = roughness_median(points, roughness, everyone, np.ones(len(points)), 0.95, 15, albedo, 1.0)
    np.testing.assert_array_equal(same, guided)
    with pytest.raises(ValueError, match="guide_m"):
        surface_median(points, roughness, everyone, 15, albedo_guide(albedo), guide_m=-1.0)
    with pytest.raises(ValueError, match="NaN"):
        surface_median(points, roughness, everyone, 15, np.full((len(points), 3), np.nan), guide_m=1.0)


def test_roughness_median_of_one_neighbour_builds_no_guide(monkeypatch):
    """With one neighbour the median is the values themselves: the albedo guide (a k-d tree over every texel)
    is not built."""
    from stages.numerics import material_textures

    def no_guide(*args, **kwargs):
        raise AssertionError("the guide was built")

    monkeypatch.setattr(material_textures, "albedo_guide", no_guide)
    points = np.random.default_rng(0).uniform(size=(50, 3))
    roughness = np.linspace(0.1, 0.9, 50).astype(np.float32)
    albedo = np.full((50, 3), 0.3)
    same, voters = roughness_median(points, roughness, np.ones(50, bool), np.ones(50), 0.5, 1, albedo, 0.15, 32)
    np.testing.assert_array_equal(same, roughness)
    assert voters.all()


def test_albedo_guide_hand_values():
    albedo = np.array([[1.0, np.e ** -1, 0.5], [0.0, -0.1, np.nan], [np.inf, 0.02, 0.03]])
    guide = albedo_guide(albedo)
    assert guide.shape == (3, 3) and guide.dtype == np.float64 and np.all(np.isfinite(guide))
    np.testing.assert_allclose(guide[0], [0.0, -1.0, np.log(0.5)])
    np.testing.assert_allclose(guide[1], np.log(ALBEDO_GUIDE_FLOOR))  # dark, negative and NaN: the floor
    np.testing.assert_allclose(guide[2], [0.0, np.log(0.02), np.log(0.03)])  # +Inf reads as 1
    # averaged over each point's nearest (itself included): stripes 1 cm apart, alternating e^-1 and e^-3, read as
    # one material of e^-2 over 4 neighbours (two of each) in the interior; a unit strip far off keeps its own
    points = np.stack([np.r_[np.arange(8) * 0.01, 1.0], np.zeros(9), np.zeros(9)], axis=1)
    stripes = np.exp(np.r_[np.where(np.arange(8) % 2 == 0, -1.0, -3.0), 0.0])[:, None] * np.ones((9, 3))
    np.testing.assert_allclose(albedo_guide(stripes, points, 1), np.log(stripes))
    averaged = albedo_guide(stripes, points, 4)
    np.testing.assert_allclose(averaged[2:6], -2.0)
    np.testing.assert_allclose(albedo_guide(stripes, points, 2)[8], np.log(stripes[8]) / 2 + np.log(stripes[7]) / 2)
    with pytest.raises(ValueError, match="neighbours"):
        albedo_guide(stripes, points, 0)
    with pytest.raises(ValueError, match="points"):
        albedo_guide(stripes, None, 4)


# ---------------------------------------------------------------------------------- load_atlas_mesh
@pytest.fixture(scope="module")
def sphere_obj(tmp_path_factory):
    """A small sphere, its atlas and the OBJ the textures stage writes from them (split vertices)."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=0.3, resolution=6)
    v = np.asarray(mesh.vertices, np.float64) + [0.1, -0.2, 0.05]
    f = np.asarray(mesh.triangles, np.int64)
    atlas = uv_atlas(v, f, resolution=64)
    split = v[atlas.vmapping]
    path = tmp_path_factory.mktemp("atlas") / "textured.obj"
    write_obj(path, split, atlas.faces, uvs=atlas.uvs, uv_faces=atlas.faces,
              normals=vertex_normals(split, atlas.faces), material={"name": "albedo", "map_Kd": "albedo.png"})
    return v, f, atlas, path


def test_load_atlas_mesh_welds_the_seams(sphere_obj):
    v, f, atlas, path = sphere_obj
    assert len(atlas.vmapping) > len(v)  # the atlas has seams: split vertices
    vertices, faces, loaded = load_atlas_mesh(path)
    assert vertices.shape == v.shape and faces.shape == f.shape
    assert faces.min() >= 0 and faces.max() == len(vertices) - 1
    # same triangles, corner by corner (welded order may differ from the input's)
    np.testing.assert_allclose(vertices[faces], v[f], atol=1e-6)
    # the atlas round-trips: faces, UVs, and every split vertex maps to its welded position
    np.testing.assert_array_equal(loaded.faces, atlas.faces)
    np.testing.assert_allclose(loaded.uvs, atlas.uvs, atol=1e-6)
    np.testing.assert_allclose(vertices[loaded.vmapping], v[atlas.vmapping], atol=1e-6)
    np.testing.assert_array_equal(loaded.vmapping[loaded.faces], faces)
    # a seam's split copies weld back to one vertex
    assert len(np.unique(loaded.vmapping)) == len(v)


def test_load_atlas_mesh_needs_uvs(tmp_path):
    mesh = o3d.geometry.TriangleMesh.create_tetrahedron()
    path = write_obj(tmp_path / "plain.obj", np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    with pytest.raises(InputError, match="UVs"):
        load_atlas_mesh(path)


# ------------------------------------------------------------------------------------------ texel_uvs
def test_texel_uvs_hand_case_and_round_trip():
    covered = np.zeros((4, 4), bool)
    covered[0, 1] = covered[2, 3] = covered[3, 0] = True
    uv = texel_uvs(covered)
    np.testing.assert_allclose(uv, [[1.5 / 4, 1 - 0.5 / 4], [3.5 / 4, 1 - 2.5 / 4], [0.5 / 4, 1 - 3.5 / 4]])
    # the texel centres sample back exactly their own texels
    rng = np.random.default_rng(2)
    covered = rng.random((16, 16)) > 0.5
    texture = rng.random((16, 16, 3)).astype(np.float32)
    np.testing.assert_allclose(sample_texture(texture, texel_uvs(covered)), texture[covered], atol=1e-6)
    assert texel_uvs(np.zeros((8, 8), bool)).shape == (0, 2)


def test_materials_config_checks():
    from stages.materials import MaterialsConfig

    with pytest.raises(ValueError, match="specular_model"):
        MaterialsConfig(specular_model="phong")
    with pytest.raises(ValueError, match="roughness_min"):
        MaterialsConfig(roughness_min=0.5, roughness_max=0.4)
    with pytest.raises(ValueError, match="min_occlusion"):
        MaterialsConfig(min_occlusion=0.0)
    with pytest.raises(ValueError, match="median_neighbours"):
        MaterialsConfig(median_neighbours=0)


def test_fitted_f0_reads_the_artifact_record(tmp_path):
    import json

    (tmp_path / "_SUCCESS.json").write_text(json.dumps({"record": {"config": {"f0": 0.03, "texture_size": 256}}}))
    assert fitted_f0(tmp_path) == 0.03
    (tmp_path / "_SUCCESS.json").write_text(json.dumps({"record": {"config": {"texture_size": 256}}}))
    with pytest.raises(InputError, match="_SUCCESS.json: no materials f0"):
        fitted_f0(tmp_path)
    (tmp_path / "_SUCCESS.json").write_text(json.dumps({"record": {"config": {"f0": 1.5}}}))
    with pytest.raises(InputError, match="outside"):
        fitted_f0(tmp_path)
    with pytest.raises(InputError, match="no materials f0"):
        fitted_f0(tmp_path / "missing")


def test_roughness_median_leaves_shadowed_texels_out_of_the_vote():
    # a row of texels 1 cm apart: the first six are open (fitted 0.3), the last four shadowed (fitted too rough)
    points = np.stack([np.arange(10) * 0.01, np.zeros(10), np.zeros(10)], axis=1)
    roughness = np.array([0.3] * 6 + [0.7] * 4, np.float32)
    fitted = np.ones(10, bool)
    fitted[0] = False  # no views: neither votes nor counts as open
    visibility = np.array([1.0] * 6 + [0.6] * 4)
    smooth, voters = roughness_median(points, roughness, fitted, visibility, 0.95, neighbours=3)
    assert voters.tolist() == [False] + [True] * 5 + [False] * 4
    np.testing.assert_allclose(smooth, 0.3)  # every texel's 3 nearest voters are open ones
    # every texel voting (0): the shadowed end keeps its own value
    everyone, voters = roughness_median(points, roughness, fitted, visibility, 0.0, neighbours=3)
    assert voters.sum() == 9 and everyone[-1] == np.float32(0.7) and everyone[1] == np.float32(0.3)
    # no texel open enough: every fitted texel votes rather than none
    fallback, voters = roughness_median(points, roughness, fitted, visibility, 1.5, neighbours=3)
    assert voters.sum() == 9 and np.array_equal(fallback, everyone)


def test_diffuse_ratio_hand_cases():
    """diffuse / white-light albedo where solved and the albedo is above 0.02; 1 elsewhere; within [0.5, 1.5]."""
    white = np.array([[0.5, 0.4, 0.2], [0.5, 0.5, 0.5], [0.01, 0.5, 0.5], [0.5, 0.5, 0.5]])
    diffuse = np.array([[0.45, 0.4, 0.1], [0.4, 0.4, 0.4], [0.02, 0.9, 0.05], [np.nan, 0.4, 0.4]])
    solved = np.array([True, False, True, True])
    ratio = diffuse_ratio_of(diffuse, white, solved)
    assert ratio.dtype == np.float32 and ratio.shape == (4, 3)
    np.testing.assert_allclose(ratio[0], [0.9, 1.0, 0.5], rtol=1e-6)
    np.testing.assert_allclose(ratio[1], [1.0, 1.0, 1.0])  # not solved
    np.testing.assert_allclose(ratio[2], [1.0, 1.5, 0.5], rtol=1e-6)  # a dark channel, then the clip
    np.testing.assert_allclose(ratio[3], [1.0, 0.8, 0.8], rtol=1e-6)  # NaN reads as 1


def test_fit_texel_materials_takes_the_albedo_from_its_own_views():
    """The roughness comes from the usable observations alone; the diffuse ratio from a second fit on the valid
    observations of the first ``albedo_max_views`` views (0: from the roughness fit itself)."""
    from stages.numerics.materials import shade_stage_illuminations

    rng = np.random.default_rng(1)
    points, views = 6, 4
    normals = np.tile([0.0, 0.0, 1.0], (points, 1))
    view_dirs = rng.normal(size=(points, views, 3)) * [0.4, 0.4, 0.0] + [0.0, 0.0, 1.0]
    view_dirs /= np.linalg.norm(view_dirs, axis=-1, keepdims=True)
    albedo = np.full((points, 3), 0.5)
    observed = np.stack([shade_stage_illuminations(normals, view_dirs[:, v], albedo, np.full(points, 0.4),
                                                   f0=0.028, specular_model="ggx_table")
                         for v in range(views)], axis=1) * rng.uniform(0.9, 1.1, (points, views, 1, 1))
    white = np.ones((points, views, 3), np.float32)
    valid = np.ones((points, views), bool)
    usable = valid.copy()
    usable[:, 0] = False
    usable[0] = False  # a texel with no usable view
    for k in (0, 2):
        cfg = MaterialTexturesConfig(albedo_max_views=k)
        rough, rms, ratio, solved = fit_texel_materials(observed, view_dirs, valid, usable, normals, albedo, white,
                                                        cfg)
        expect = fit_texel_roughness(observed, view_dirs, usable, normals, albedo, white, cfg)
        np.testing.assert_array_equal(rough, expect[0])
        np.testing.assert_array_equal(rms, expect[1])
        if k:
            second = fit_texel_roughness(observed[:, :k], view_dirs[:, :k], valid[:, :k], normals, albedo,
                                         white[:, :k], cfg)
            np.testing.assert_array_equal(ratio, diffuse_ratio_of(second[2], albedo, second[1] >= 0))
            assert solved.all()  # the texel without usable views has valid ones
        else:
            np.testing.assert_array_equal(ratio, diffuse_ratio_of(expect[2], albedo, expect[1] >= 0))
            assert solved.tolist() == [False] + [True] * (points - 1)
            assert (ratio[0] == 1.0).all()
