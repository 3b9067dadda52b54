"""Mesh numerics (sparse marching cubes, components, decimation, normals, UV atlas) and the mesh codecs."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from skimage.measure import marching_cubes

from pipeline.codecs.mesh import read_obj, read_ply, write_obj, write_ply
from pipeline.errors import InputError
from stages.numerics.bake import rasterize_atlas
from stages.numerics.mesh import (
    Atlas,
    decimate,
    extract_mesh,
    face_normals,
    largest_component,
    uv_atlas,
    vertex_normals,
)

CENTRE = np.array([0.013, -0.021, 0.007])
RADIUS = 0.3
BOUNDS = np.array([[-0.4, -0.4, -0.4], [0.4, 0.4, 0.4]])


def sphere_sdf(points, centre=CENTRE, radius=RADIUS):
    return np.linalg.norm(points - centre, axis=1) - radius


def torus_sdf(points, major=0.25, minor=0.08):
    q = np.stack([np.hypot(points[:, 0], points[:, 2]) - major, points[:, 1]], axis=1)
    return np.linalg.norm(q, axis=1) - minor


def dense_marching_cubes(sdf, bounds, resolution):
    """Reference: marching cubes on the fully evaluated grid extract_mesh uses (coarse_factor 1)."""
    voxel = float((bounds[1] - bounds[0]).max()) / resolution
    cells = np.ceil((bounds[1] - bounds[0]) / voxel - 1e-9).astype(int)
    axes = [bounds[0][a] + voxel * np.arange(cells[a] + 1) for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    volume = sdf(grid.reshape(-1, 3).astype(np.float32)).reshape(grid.shape[:3]).astype(np.float32)
    v, f, _, _ = marching_cubes(volume, 0.0, gradient_direction="descent")
    return (bounds[0] + voxel * v).astype(np.float32), f


# -------------------------------------------------------------------------------------- extract_mesh
@pytest.mark.parametrize("sdf, factor", [(sphere_sdf, 4), (sphere_sdf, 8), (torus_sdf, 4)])
def test_extract_mesh_equals_dense_marching_cubes(sdf, factor):
    v, f, stats = extract_mesh(sdf, BOUNDS, 64, coarse_factor=factor)
    v_ref, f_ref = dense_marching_cubes(sdf, BOUNDS, 64)
    assert v.dtype == np.float32 and f.dtype == np.int32
    assert np.array_equal(f, f_ref)
    assert np.allclose(v, v_ref, atol=1e-6)
    dense_points = 65 ** 3
    assert stats["sdf_evaluations"] < 0.5 * dense_points
    assert 0 < stats["fine_evaluated_fraction"] < 0.5
    assert stats["grid_shape"] == [65, 65, 65] and stats["faces"] == len(f)


def test_extract_mesh_sphere_geometry_and_winding():
    v, f, stats = extract_mesh(sphere_sdf, BOUNDS, 96)
    voxel = stats["voxel_m"]
    radius = np.linalg.norm(v - CENTRE, axis=1)
    # vertices interpolate the exact SDF along grid edges: on the sphere to a small fraction of a voxel
    assert np.abs(radius - RADIUS).max() < 0.02 * voxel
    normals, area = face_normals(v, f)
    outward = np.einsum("nd,nd->n", normals, v[f].mean(axis=1) - CENTRE)
    assert (outward[area > 0] > 0).all()  # counter-clockwise seen from outside
    # refinement keeps a thin shell: finer grids evaluate a smaller fraction
    _, _, coarse_stats = extract_mesh(sphere_sdf, BOUNDS, 48)
    assert stats["fine_evaluated_fraction"] < coarse_stats["fine_evaluated_fraction"] < 0.35


def test_extract_mesh_level_chunks_and_non_cubic_bounds():
    calls = []

    def sdf(points):
        calls.append(len(points))
        return sphere_sdf(points)

    bounds = np.array([[-0.5, -0.35, -0.4], [0.5, 0.4, 0.4]])
    v, f, stats = extract_mesh(sdf, bounds, 50, level=0.02, chunk=5000)
    assert max(calls) <= 5000 and sum(calls) == stats["sdf_evaluations"]
    assert np.abs(np.linalg.norm(v - CENTRE, axis=1) - (RADIUS + 0.02)).max() < 0.001
    assert stats["voxel_m"] == pytest.approx(0.02)
    assert all(n % 4 == 1 for n in stats["grid_shape"])  # coarse blocks tile the fine grid
    assert (v.min(axis=0) >= bounds[0]).all()


def test_extract_mesh_no_surface_and_bad_inputs():
    v, f, stats = extract_mesh(lambda p: np.ones(len(p)), BOUNDS, 16)
    assert v.shape == (0, 3) and f.shape == (0, 3) and stats["fine_evaluated_fraction"] == 0.0
    with pytest.raises(ValueError, match="bounds"):
        extract_mesh(sphere_sdf, BOUNDS[::-1], 16)
    with pytest.raises(ValueError, match="NaN"):
        extract_mesh(lambda p: np.full(len(p), np.nan), BOUNDS, 16)
    with pytest.raises(ValueError, match="values for"):
        extract_mesh(lambda p: np.zeros(3), BOUNDS, 16)


# ----------------------------------------------------------------------------------------- cleanup
def test_largest_component_drops_floaters_and_reindexes():
    big_v, big_f, _ = extract_mesh(sphere_sdf, BOUNDS, 24)
    small_v = np.array([[1, 1, 1], [1.1, 1, 1], [1, 1.1, 1]], np.float32)
    v = np.concatenate([small_v, big_v])  # the floater first, so indices must shift
    f = np.concatenate([np.array([[0, 1, 2]]), big_f + 3]).astype(np.int32)
    v_out, f_out = largest_component(v, f)
    assert len(v_out) == len(big_v) and np.array_equal(v_out, big_v)
    assert np.array_equal(f_out, big_f) and f_out.dtype == np.int32
    # unreferenced vertices go too
    v2, f2 = largest_component(np.concatenate([v, [[5, 5, 5]]]).astype(np.float32), f)
    assert len(v2) == len(big_v)


def test_decimate_reaches_target_and_keeps_shape():
    v, f, _ = extract_mesh(sphere_sdf, BOUNDS, 48)
    vd, fd = decimate(v, f, 2000)
    assert fd.dtype == np.int32 and vd.dtype == np.float32
    assert 1800 <= len(fd) <= 2000
    assert np.abs(np.linalg.norm(vd - CENTRE, axis=1) - RADIUS).max() < 0.005
    same_v, same_f = decimate(vd, fd, 5000)  # fewer faces than the target: unchanged
    assert np.array_equal(same_f, fd) and np.array_equal(same_v, vd)


def test_vertex_normals_hand_computed():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [9, 9, 9]], np.float32)
    f = np.array([[0, 1, 2], [0, 1, 3]], np.int32)  # z-up triangle (area 1/2) and y-down one (area 1/2)
    n = vertex_normals(v, f)
    assert n.dtype == np.float32 and n.shape == (5, 3)
    assert np.allclose(n[2], (0, 0, 1)) and np.allclose(n[3], (0, -1, 0))
    assert np.allclose(n[0], np.array([0, -1, 1]) / np.sqrt(2), atol=1e-6)  # equal areas: the bisector
    assert np.allclose(n[4], 0)  # in no face


# -------------------------------------------------------------------------------------------- atlas
def test_uv_atlas_charts_cover_the_mesh_without_overlap():
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=20)
    v = np.asarray(mesh.vertices, np.float32)
    f = np.asarray(mesh.triangles, np.int32)
    atlas = uv_atlas(v, f, resolution=256, padding=2)
    assert isinstance(atlas, Atlas) and atlas.faces.shape == f.shape and atlas.uvs.dtype == np.float32
    assert atlas.uvs.min() >= 0 and atlas.uvs.max() <= 1
    assert np.array_equal(v[atlas.vmapping][atlas.faces], v[f])  # same faces, same order
    assert 0.8 * 256 < atlas.width < 1.5 * 256 and atlas.width == atlas.height
    # no overlap: rasterized texels = total UV area x T^2 (overlapping charts would count once)
    uv = atlas.uvs[atlas.faces].astype(np.float64)
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    size = 512
    covered = rasterize_atlas(v, f, atlas, size)["covered"].sum()
    assert covered == pytest.approx(area.sum() * size * size, rel=0.03)
    # charts are isometric-ish: UV area per 3D area is nearly constant over faces
    ratio = area / face_normals(v, f)[1]
    assert np.percentile(ratio, 95) / np.percentile(ratio, 5) < 2.0


def test_uv_atlas_max_chart_area_bounds_every_chart():
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=20)
    v = np.asarray(mesh.vertices, np.float32)
    f = np.asarray(mesh.triangles, np.int32)
    sphere_m2 = 4 * np.pi * RADIUS ** 2
    free = uv_atlas(v, f, resolution=256, padding=2)
    limit = sphere_m2 / 10
    bounded = uv_atlas(v, f, resolution=256, padding=2, max_chart_area=limit)
    assert np.array_equal(v[bounded.vmapping][bounded.faces], v[f])  # the same faces in the same order
    assert bounded.stats["charts"] >= 10 > free.stats["charts"]
    # each chart (faces joined through shared UV vertices) holds at most the limit of surface
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = len(bounded.vmapping)
    edges = np.concatenate([bounded.faces[:, [0, 1]], bounded.faces[:, [1, 2]]])
    graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    face_area = face_normals(v, f)[1]
    chart_area = np.bincount(label[bounded.faces[:, 0]], weights=face_area)
    assert chart_area.max() <= limit * 1.0001
    with pytest.raises(ValueError, match="max_chart_area"):
        uv_atlas(v, f, resolution=256, max_chart_area=-1.0)


# ------------------------------------------------------------------------------------------- codecs
def test_ply_round_trip_and_open3d_reads_it(tmp_path):
    v, f, _ = extract_mesh(sphere_sdf, BOUNDS, 16)
    n = vertex_normals(v, f)
    path = write_ply(tmp_path / "m.ply", v, f, normals=n)
    v2, f2, n2 = read_ply(path, with_normals=True)
    assert np.array_equal(v2, v) and np.array_equal(f2, f) and np.array_equal(n2, n)
    assert f2.dtype == np.int32
    mesh = o3d.io.read_triangle_mesh(str(path))
    assert np.allclose(np.asarray(mesh.vertices), v) and np.array_equal(np.asarray(mesh.triangles), f)
    write_ply(tmp_path / "plain.ply", v, f)
    assert read_ply(tmp_path / "plain.ply", with_normals=True)[2] is None


def test_ply_ascii_polygons_and_bad_files(tmp_path):
    text = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
            "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
            "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    (tmp_path / "quad.ply").write_text(text)
    v, f = read_ply(tmp_path / "quad.ply")
    assert v.shape == (4, 3) and np.array_equal(f, [[0, 1, 2], [0, 2, 3]])
    (tmp_path / "bad.ply").write_bytes(b"not a ply")
    with pytest.raises(InputError, match="bad.ply"):
        read_ply(tmp_path / "bad.ply")
    good = write_ply(tmp_path / "t.ply", v, f).read_bytes()
    (tmp_path / "trunc.ply").write_bytes(good[:-7])
    with pytest.raises(InputError, match="truncated"):
        read_ply(tmp_path / "trunc.ply")
    with pytest.raises(ValueError, match="non-finite"):
        write_ply(tmp_path / "nan.ply", np.full((3, 3), np.nan), [[0, 1, 2]])


def test_obj_round_trip_with_uvs_normals_and_material(tmp_path):
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=6)
    v = np.asarray(mesh.vertices, np.float32)
    f = np.asarray(mesh.triangles, np.int32)
    atlas = uv_atlas(v, f, resolution=64)
    av = v[atlas.vmapping]
    n = vertex_normals(av, atlas.faces)
    material = {"name": "skin", "map_Kd": "albedo.png", "norm": "normal.exr", "Ks": (0.0, 0.0, 0.0)}
    path = write_obj(tmp_path / "asset.obj", av, atlas.faces, uvs=atlas.uvs, normals=n, material=material)
    back = read_obj(path)
    assert np.allclose(back["vertices"], av, atol=1e-6) and np.array_equal(back["faces"], atlas.faces)
    assert np.allclose(back["uvs"], atlas.uvs, atol=1e-6) and np.array_equal(back["uv_faces"], atlas.faces)
    assert np.allclose(back["normals"], n, atol=1e-5)
    assert back["mtllib"] == "asset.mtl"
    assert back["material"] == {"name": "skin", "map_Kd": "albedo.png", "norm": "normal.exr",
                                "Ks": "0 0 0", "Kd": "1 1 1"}
    # open3d reads the same triangles and per-corner UVs
    o3 = o3d.io.read_triangle_mesh(str(path))
    assert len(o3.triangles) == len(f)
    corner_uv = np.asarray(o3.triangle_uvs).reshape(-1, 3, 2)
    tri_pos = np.asarray(o3.vertices)[np.asarray(o3.triangles)]
    assert np.allclose(tri_pos, av[atlas.faces], atol=1e-6)
    # open3d flips v on load (image rows down); either way the corners carry our UVs
    assert np.allclose(corner_uv[..., 0], atlas.uvs[atlas.faces][..., 0], atol=1e-6)
    assert np.allclose(np.minimum(np.abs(corner_uv[..., 1] - atlas.uvs[atlas.faces][..., 1]),
                                  np.abs(1 - corner_uv[..., 1] - atlas.uvs[atlas.faces][..., 1])), 0, atol=1e-6)
    # separate uv indexing (uv_faces) and plain geometry
    write_obj(tmp_path / "plain.obj", v, f)
    plain = read_obj(tmp_path / "plain.obj")
    assert plain["uvs"] is None and plain["material"] is None and np.array_equal(plain["faces"], f)
    with pytest.raises(ValueError, match="uv_faces"):
        write_obj(tmp_path / "x.obj", v, f, uvs=np.zeros((len(v) + 1, 2)))


def test_uv_atlas_repacks_a_long_atlas_into_the_square():
    """A long thin mesh makes xatlas pack into a long rectangle at its own scale (here 562 x 128 texels
    for a 256 request: 18% of the unit square used); uv_atlas packs again at the scale that fills the
    requested square and keeps the packing that uses more of it (on a body: 2507 x 789 -> 1024 x 1024,
    12.5% -> 42% of a 1024 texture)."""
    import open3d as o3d

    from stages.numerics.mesh import uv_atlas

    cylinder = o3d.geometry.TriangleMesh.create_cylinder(radius=0.05, height=2.0, resolution=24, split=40)
    vertices, faces = np.asarray(cylinder.vertices), np.asarray(cylinder.triangles)
    atlas = uv_atlas(vertices, faces, resolution=256, padding=2)
    stats = atlas.stats
    assert stats["repacks"] >= 1
    assert stats["square_fill"] > 1.2 * stats["first_square_fill"], stats
    assert (stats["packed_width"], stats["packed_height"]) == (256, 256)
    assert atlas.uvs.min() >= 0.0 and atlas.uvs.max() <= 1.0


def _obj_readers(path):
    """(the column reader's result, the line reader's) of one OBJ file."""
    from pipeline.codecs import mesh as codec

    fast = codec.read_obj(path)
    text = Path(path).read_text()
    assert codec._read_obj_columns(text) is not None  # the file takes the column path
    lines = dict(zip(("v", "vt", "vn", "fv", "ft", "fn", "mtllib"), codec._read_obj_lines(Path(path), text)))
    return fast, lines


@pytest.mark.parametrize("with_uvs,with_normals", [(True, True), (True, False), (False, True), (False, False)])
def test_read_obj_columns_equal_the_line_reader(tmp_path, with_uvs, with_normals):
    from pipeline.codecs.mesh import read_obj, write_obj

    rng = np.random.default_rng(4)
    vertices = rng.normal(size=(50, 3)).astype(np.float32)
    faces = rng.integers(0, 50, size=(80, 3))
    uvs = rng.random((50, 2)).astype(np.float32) if with_uvs else None
    normals = rng.normal(size=(50, 3)).astype(np.float32) if with_normals else None
    path = write_obj(tmp_path / "m.obj", vertices, faces, uvs=uvs, normals=normals, material={"name": "skin"})
    fast, lines = _obj_readers(path)
    np.testing.assert_array_equal(fast["vertices"], np.asarray(lines["v"], np.float32))
    np.testing.assert_array_equal(fast["faces"], faces.astype(np.int32))
    np.testing.assert_allclose(fast["vertices"], vertices, rtol=1e-6, atol=1e-7)  # 7 digits in the file
    assert (fast["uvs"] is None) == (not with_uvs) and (fast["normals"] is None) == (not with_normals)
    if with_uvs:
        np.testing.assert_array_equal(fast["uvs"], np.asarray(lines["vt"], np.float32))
        np.testing.assert_array_equal(fast["uv_faces"], faces.astype(np.int32))
    if with_normals:
        np.testing.assert_array_equal(fast["normals"], np.asarray(lines["vn"], np.float32))
        np.testing.assert_array_equal(fast["normal_faces"], np.asarray(lines["fn"]) - 1)
    assert fast["material"]["name"] == "skin"
    # quads, a 4-number vertex and tabs leave the column path: the line reader reads them the same
    quads = tmp_path / "quad.obj"
    quads.write_text("v 0 0 0\nv 1 0 0 1\nv\t1 1 0\nv 0 1 0\nf 1 2 3 4\n")
    from pipeline.codecs import mesh as codec

    assert codec._read_obj_columns(quads.read_text()) is None
    quad = read_obj(quads)
    np.testing.assert_array_equal(quad["faces"], [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(quad["vertices"][1], [1, 0, 0])
    broken = tmp_path / "broken.obj"
    broken.write_text("v 0 0 0\nv 1 0 0\nv 0 1 x\nf 1 2 3\n")
    with pytest.raises(InputError, match="line 3"):
        read_obj(broken)
