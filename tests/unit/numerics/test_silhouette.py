"""The measured outline coverage (photometric.edge_coverage) and the silhouette refinement of a mesh."""
import numpy as np
import pytest

from stages.numerics.photometric import edge_coverage
from stages.numerics.raycast import mesh_scene, pixel_coverage
from stages.numerics.silhouette import OutlineView, SilhouetteConfig, outline_offsets, refine_silhouettes
from synthetic.rig import look_at

SUBJECT = np.array([0.5, 0.3, 0.2], np.float32)
PLATE = np.array([0.05, 0.06, 0.08], np.float32)
SIZE, FOCAL, DISTANCE = 96, 240.0, 1.5  # one pixel is 6.25 mm at the sphere
EXACT = SilhouetteConfig(outline_bias_px=0.0)  # the coverage here is exact: no rim to correct for


def _composite(coverage: np.ndarray) -> np.ndarray:
    """The white image a camera records of a flat-coloured subject covering ``coverage`` of each pixel."""
    return (coverage[..., None] * SUBJECT + (1.0 - coverage[..., None]) * PLATE).astype(np.float32)


def _sphere(radius: float, resolution: int = 80) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def _ring(count: int = 8) -> list[tuple[np.ndarray, np.ndarray]]:
    K = np.array([[FOCAL, 0.0, (SIZE - 1) / 2], [0.0, FOCAL, (SIZE - 1) / 2], [0.0, 0.0, 1.0]])
    out = []
    for k in range(count):
        a = 2 * np.pi * k / count
        centre = DISTANCE * np.array([np.cos(a), 0.3 * np.sin(3 * a), np.sin(a)])
        out.append((K, look_at(centre, np.zeros(3))))
    return out


def _outline_views(radius: float) -> list[OutlineView]:
    """The ring's views of a sphere of ``radius``: exact coverage (16 x 16 rays) measured through a white image."""
    scene = mesh_scene(*_sphere(radius, 200))
    views = []
    for K, P in _ring():
        truth = pixel_coverage(K, P, SIZE, SIZE, 16, scene)
        plate = np.broadcast_to(PLATE, (SIZE, SIZE, 3))
        views.append(OutlineView(K=K, cam_from_world=P, coverage=edge_coverage(truth >= 0.5, _composite(truth), plate)))
    return views


# ------------------------------------------------------------------------------------------- edge_coverage


def test_edge_coverage_recovers_a_straight_edge():
    # a subject filling the left of the frame up to x = 20.3 px: the pixel at column 20 is 80% covered
    cols = np.arange(40, dtype=np.float64)
    share = np.clip(20.3 + 0.5 - cols, 0.0, 1.0)
    truth = np.broadcast_to(share, (30, 40)).astype(np.float32)
    plate = np.broadcast_to(PLATE, (30, 40, 3))
    out = edge_coverage(truth >= 0.5, _composite(truth), plate)
    assert out.shape == (30, 40) and out.dtype == np.float32
    np.testing.assert_allclose(out[:, 20], 0.8, atol=1e-5)
    np.testing.assert_allclose(out, truth, atol=1e-5)


def test_edge_coverage_measures_pixels_the_mask_took_in_wrongly():
    truth = np.zeros((20, 20), np.float32)
    truth[:, :10] = 1.0
    truth[:, 10] = 0.3
    mask = np.zeros((20, 20), bool)
    mask[:, :11] = True  # the mostly-background column 10 taken in, and column 9 the band's second pixel in
    out = edge_coverage(mask, _composite(truth), np.broadcast_to(PLATE, (20, 20, 3)))
    np.testing.assert_allclose(out[:, 10], 0.3, atol=1e-5)
    np.testing.assert_allclose(out[:, 8:10], 1.0, atol=1e-5)
    np.testing.assert_allclose(out[:, 11:13], 0.0, atol=1e-5)
    assert np.all(out[:, :8] == 1.0) and np.all(out[:, 13:] == 0.0)


def test_edge_coverage_noise_is_clipped_and_no_contrast_keeps_the_mask():
    rng = np.random.default_rng(0)
    truth = np.zeros((20, 20), np.float32)
    truth[5:15, 5:15] = 1.0
    image = _composite(truth) + rng.normal(0.0, 0.05, (20, 20, 3)).astype(np.float32)
    image[0, 0] = np.nan
    out = edge_coverage(truth > 0.5, image, np.broadcast_to(PLATE, (20, 20, 3)))
    assert np.all(np.isfinite(out)) and out.min() >= 0.0 and out.max() <= 1.0
    flat = edge_coverage(truth > 0.5, np.broadcast_to(PLATE, (20, 20, 3)), np.broadcast_to(PLATE, (20, 20, 3)))
    np.testing.assert_array_equal(flat, truth)  # subject and plate alike: nothing to measure


def test_edge_coverage_checks_its_inputs():
    image = np.zeros((10, 10, 3), np.float32)
    with pytest.raises(ValueError, match="differ in size"):
        edge_coverage(np.zeros((10, 11), bool), image, image)
    with pytest.raises(ValueError, match="band_px"):
        edge_coverage(np.zeros((10, 10), bool), image, image, band_px=0)
    np.testing.assert_array_equal(edge_coverage(np.zeros((10, 10), bool), image, image), 0.0)


# ------------------------------------------------------------------------------------------ outline_offsets


def test_outline_offsets_measure_how_far_the_contour_lies_inside():
    from artifacts.camera import camera_centre
    from stages.numerics.mesh import vertex_normals
    from stages.numerics.silhouette import _contour_vertices, _edges_with_faces

    views = _outline_views(0.2)
    pixel_mm = 1e3 * (DISTANCE ** 2 - 0.2 ** 2) / DISTANCE / FOCAL  # the contour's depth over the focal length
    biased = SilhouetteConfig(outline_bias_px=0.16)  # the outline read 0.16 px too far out: a 1 mm move in
    for radius, cfg, expected_mm in ((0.2, EXACT, 0.0), (0.1985, EXACT, 1.5), (0.2015, EXACT, -1.5),
                                     (0.2, biased, -0.16 * pixel_mm)):
        v, f = _sphere(radius)
        edges, fa, fb = _edges_with_faces(f)
        scene, normals = mesh_scene(v, f), vertex_normals(v, f).astype(np.float64)
        moves = []
        for view in views:
            contour = _contour_vertices(v, f, edges, fa, fb, camera_centre(view.cam_from_world))
            move, used = outline_offsets(scene, v, normals, contour, view.K, view.cam_from_world, view.coverage,
                                         cfg)
            assert move.shape == used.shape == contour.shape and np.all(move[~used] == 0.0)
            assert used.mean() > 0.5
            moves.append(move[used])
        assert np.mean(np.concatenate(moves)) * 1e3 == pytest.approx(expected_mm, abs=0.1)


# ----------------------------------------------------------------------------------------- refine_silhouettes


def test_refine_silhouettes_moves_a_small_sphere_out_to_the_measured_outline():
    views = _outline_views(0.2)
    v, f = _sphere(0.1985)  # 1.5 mm, a quarter pixel, inside
    refined, stats = refine_silhouettes(v, f, views, EXACT)
    assert refined.shape == v.shape and refined.dtype == np.float32 and np.all(np.isfinite(refined))
    before = np.abs(np.linalg.norm(v, axis=1) - 0.2).mean()
    after = np.abs(np.linalg.norm(refined, axis=1) - 0.2).mean()
    assert after < 0.5 * before, (before, after)
    assert len(stats["samples_used"]) == 3 and min(stats["samples_used"]) > 0
    assert stats["faces_kept_back"] == 0 and 0 < stats["max_move_mm"] < 3.0


def test_refine_silhouettes_leaves_a_right_mesh_and_zero_iterations_alone():
    views = _outline_views(0.2)
    v, f = _sphere(0.2)
    refined, stats = refine_silhouettes(v, f, views, EXACT)
    assert np.abs(np.linalg.norm(refined, axis=1) - 0.2).max() < 0.5e-3
    same, stats0 = refine_silhouettes(v, f, views, SilhouetteConfig(iterations=0))
    np.testing.assert_array_equal(same, v.astype(np.float32))
    assert stats0["moved_vertices"] == 0


def test_refine_silhouettes_checks_its_inputs():
    v, f = _sphere(0.2, 10)
    view = OutlineView(K=np.eye(3), cam_from_world=np.eye(4)[:3], coverage=np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="coverage"):
        refine_silhouettes(v, f, [view])
    with pytest.raises(ValueError, match="NaN"):
        refine_silhouettes(np.full_like(v, np.nan), f, [])
    with pytest.raises(ValueError, match="expected vertices"):
        refine_silhouettes(v[:, :2], f, [])
    with pytest.raises(Exception, match="step"):
        SilhouetteConfig(step=0.0)


def test_outline_disagreement_is_the_offset_between_two_coverages_in_pixels():
    from stages.numerics.silhouette import outline_disagreement

    v, f = _sphere(0.2)
    views = _outline_views(0.2)
    same = outline_disagreement(v, f, views, views)
    assert same.size > 100 and np.all(same == 0.0)
    wider = outline_disagreement(v, f, _outline_views(0.2015), views)  # a 1.5 mm larger subject
    pixel_mm = 1e3 * (DISTANCE ** 2 - 0.2 ** 2) / DISTANCE / FOCAL
    assert np.median(wider) == pytest.approx(1.5 / pixel_mm, abs=0.03)
    with pytest.raises(ValueError, match="reference"):
        outline_disagreement(v, f, views, views[:1])


def test_the_geometry_stage_measures_every_camera_or_none():
    """stages.geometry.outline_views: the coverage of each camera's white image against its plate around its mask,
    or None when a camera has no clean plate (the step is then skipped)."""
    from types import SimpleNamespace

    from stages.geometry import outline_views

    truth = np.zeros((12, 12), np.float32)
    truth[3:9, 3:9] = 1.0
    truth[3:9, 9] = 0.4
    plate = np.broadcast_to(PLATE, (12, 12, 3)).astype(np.float32)

    class Store:
        def __init__(self, plates):
            self.plates = plates

        def plate(self, camera):
            return plate if camera in self.plates else None

        def exr(self, kind, camera):
            assert kind == "full_on"
            return np.concatenate([_composite(truth), np.ones((12, 12, 1), np.float32)], axis=-1)  # RGBA as read

    views = [SimpleNamespace(K=np.eye(3), cam_from_world=np.eye(4)[:3], mask=truth > 0.5) for _ in range(2)]
    out = outline_views(Store({"a", "b"}), ["a", "b"], views)
    assert [type(o).__name__ for o in out] == ["OutlineView", "OutlineView"]
    assert out[1].coverage.dtype == np.float16
    np.testing.assert_allclose(out[1].coverage, truth, atol=1e-3)
    assert outline_views(Store({"a"}), ["a", "b"], views) is None


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_refine_silhouettes_leaves_the_mesh_where_a_frame_measures_nothing(value):
    """A black (or saturated, all-subject) coverage holds no outline: every profile is skipped, nothing moves."""
    v, f = _sphere(0.2, 40)
    blank = [OutlineView(K=view.K, cam_from_world=view.cam_from_world, coverage=np.full((SIZE, SIZE), value))
             for view in _outline_views(0.2)[:3]]
    refined, stats = refine_silhouettes(v, f, blank, EXACT)
    np.testing.assert_array_equal(refined, v.astype(np.float32))
    assert stats["samples_used"] == [0, 0, 0] and stats["moved_vertices"] == 0
