"""The held-out view protocol (evaluation.heldout, the paper's table 1) on hand-computed cases: the pooled metrics,
the choice of held-out cameras, and the whole protocol on a flat square seen by seven cameras whose source maps
are off by a known angle and albedo."""
from __future__ import annotations

import math

import numpy as np
import pytest

from evaluation.heldout import ActionGBuffers, compare_maps, heldout_metrics, spread_heldout, summarise
from pipeline.codecs.exr import write_exr
from pipeline.codecs.image import write_png
from artifacts.camera import Camera
from stages.numerics.raycast import render_mesh
from synthetic.rig import look_at

SIZE = 48
K = np.array([[60.0, 0.0, 23.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
# a 1 m square in the plane z = 0, its normal +z
SQUARE_V = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]], np.float64)
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
HELDOUT = ("00000", "00003")
TILT = math.radians(10.0)
SOURCE_NORMAL = np.array([0.0, -math.sin(TILT), math.cos(TILT)], np.float32)  # +z turned 10 deg about x


def ring_cameras() -> dict[str, Camera]:
    """One camera 2 m above the square's centre and six on a 25 degree cone around it, all looking at it."""
    centres = [np.array([0.0, 0.0, 2.0])]
    for i in range(6):
        a = math.radians(60.0 * i + 15.0)
        tilt = math.radians(25.0)
        centres.append(2.0 * np.array([math.sin(tilt) * math.cos(a), math.sin(tilt) * math.sin(a), math.cos(tilt)]))
    return {f"{i:05d}": Camera(K=K, cam_from_world=look_at(c, np.zeros(3)), width=SIZE, height=SIZE,
                               camera_id=f"{i:05d}") for i, c in enumerate(centres)}


class SquareAction(ActionGBuffers):
    """An action without a release: the square's mesh and cameras, and photometric maps made from its renders.
    The held-out cameras' maps are exact (normal +z, albedo 0.5); the sources' normals are turned by 10 degrees
    and their albedo is 0.6."""

    def __init__(self):  # the attributes ActionGBuffers' methods use, without opening a release
        self.view = None
        self.diffuse_normals = False
        self.diffuse_albedo = False
        self.action_id = "A0000"
        self.cameras = ring_cameras()
        self.vertices, self.faces = SQUARE_V, SQUARE_F
        self._scene = None
        self._render, self._subpixel, self._sources, self._shared, self._variants = {}, {}, {}, {}, {}

    def predicts_specular(self) -> bool:
        return False

    def photometric(self, cam: str) -> dict[str, np.ndarray]:
        hit = self.render(cam)["hit"]
        exact = cam in HELDOUT
        normal = np.where(hit[..., None], np.array([0, 0, 1], np.float32) if exact else SOURCE_NORMAL, 0.0)
        albedo = np.where(hit[..., None], np.full(3, 0.5 if exact else 0.6, np.float32), 0.0)
        return {"normal": normal.astype(np.float32), "albedo": albedo.astype(np.float32),
                "alpha": hit.astype(np.float32), "mask": hit.copy()}


def write_truth(root, data: SquareAction) -> None:
    """The simulator's maps of the held-out cameras (normal +z on the square, albedo 0.5) at twice the maps'
    resolution, as ground_truth/<action>/{normal,albedo,mask}/<cam>.* holds them."""
    for cam in HELDOUT:
        c = data.cameras[cam]
        big = render_mesh(SQUARE_V, SQUARE_F, K * np.array([[2], [2], [1]]) + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]),
                          c.cam_from_world, 2 * SIZE, 2 * SIZE)["hit"]
        base = root / "A0000"
        write_exr(base / "normal" / f"{cam}.exr", np.where(big[..., None], np.float32([0, 0, 1]), 0).astype(np.float32))
        # the albedo 0.5 beyond the square too: the mask's edge pixels, half on it, keep 0.5 at the maps' size
        write_exr(base / "albedo" / f"{cam}.exr", np.full((2 * SIZE, 2 * SIZE, 3), 0.5, np.float32))
        write_png(base / "mask" / f"{cam}.png", (big * 255).astype(np.uint8))


def test_heldout_protocol_on_a_square_gives_the_known_errors(tmp_path):
    """Every held-out pixel is blended from sources whose normals are all turned by 10 degrees and whose albedo is
    0.6 against 0.5: normal error 10 deg everywhere (none under 5, all under 25), albedo RMSE 0.1, PSNR
    10 log10(1 / 0.01) = 20 dB; the same against the simulator's maps; the held-out cameras are never sources."""
    data = SquareAction()
    write_truth(tmp_path, data)
    result = heldout_metrics(None, "A0000", heldout=HELDOUT, truth_dir=tmp_path, data=data, albedo_model="white")
    assert result["heldout_cameras"] == list(HELDOUT) and result["heldout_albedo_model"] == "white"
    for suffix in ("", "_truth"):
        assert result[f"heldout_normal_mean_deg{suffix}"] == pytest.approx(10.0, abs=0.01)
        assert result[f"heldout_normal_median_deg{suffix}"] == pytest.approx(10.0, abs=0.01)
        assert result[f"heldout_normal_under5_pct{suffix}"] == 0.0
        assert result[f"heldout_normal_under25_pct{suffix}"] == 100.0
        assert result[f"heldout_albedo_rmse{suffix}"] == pytest.approx(0.1, abs=1e-5)
        assert result[f"heldout_albedo_psnr_db{suffix}"] == pytest.approx(20.0, abs=1e-3)
        # constant maps: SSIM is its luminance term (2 * 0.6 * 0.5 + C1) / (0.6^2 + 0.5^2 + C1), C1 = 1e-4, inside;
        # the windows at the compared pixels' edge see the zeros both maps hold beyond them
        assert 0.95 < result[f"heldout_albedo_ssim{suffix}"] < 1.0
    # the square fills the held-out views' middles; every pixel of their masks is synthesised
    assert result["heldout_coverage"] == pytest.approx(1.0, abs=0.01)
    assert result["heldout_pixels"] > 0.2 * 2 * SIZE * SIZE
    for cam in HELDOUT:
        view = result["per_view"][cam]
        assert view["heldout_normal_mean_deg"] == pytest.approx(10.0, abs=0.01)
        assert view["heldout_coverage_truth"] > 0.95
    maps = heldout_metrics(None, "A0000", heldout=HELDOUT, data=data, albedo_model="white", return_maps=True)["maps"]
    for cam in HELDOUT:
        assert not set(maps[cam]["synth"]["source_ids"]) & set(HELDOUT)
        assert set(maps[cam]["synth"]["source_ids"]) <= set(data.cameras) - set(HELDOUT)


def test_heldout_protocol_with_exact_sources_is_perfect():
    """Sources equal to the held-out maps: zero normal error, the albedo PSNR at its 120 dB ceiling (MSE floor
    1e-12), SSIM 1."""

    class Exact(SquareAction):
        def photometric(self, cam):
            maps = super().photometric(cam)
            hit = maps["mask"]
            return maps | {"normal": np.where(hit[..., None], np.float32([0, 0, 1]), 0).astype(np.float32),
                           "albedo": np.where(hit[..., None], np.full(3, 0.5, np.float32), 0).astype(np.float32)}

    result = heldout_metrics(None, "A0000", heldout=HELDOUT, data=Exact(), albedo_model="white")
    assert result["heldout_normal_mean_deg"] < 1e-3 and result["heldout_normal_under5_pct"] == 100.0
    assert result["heldout_albedo_rmse"] < 1e-6 and result["heldout_albedo_psnr_db"] > 110.0
    assert result["heldout_albedo_ssim"] == pytest.approx(1.0, abs=1e-9)


def test_unknown_or_all_heldout_cameras_fall_back_to_two_spread_ones():
    data = SquareAction()
    for heldout in (("99999",), tuple(data.cameras), None):
        result = heldout_metrics(None, "A0000", heldout=heldout, data=data, albedo_model="white")
        assert tuple(result["heldout_cameras"]) == spread_heldout(data.cameras, 2)
    with pytest.raises(ValueError, match="albedo_model"):
        heldout_metrics(None, "A0000", heldout=HELDOUT, data=data, albedo_model="brightest")


def test_spread_heldout_picks_opposite_cameras():
    """Greedy farthest-point choice on the centres' directions: from the first id, the one facing it, then the
    two between them."""
    cams = {}
    for i, angle in enumerate((0, 45, 90, 180, 270)):
        a = math.radians(angle)
        centre = np.array([3 * math.sin(a), 0.0, 3 * math.cos(a)])
        cams[f"{i:05d}"] = Camera(K=K, cam_from_world=look_at(centre, np.zeros(3)), width=8, height=8)
    assert spread_heldout(cams, 1) == ("00000",)
    assert spread_heldout(cams, 2) == ("00000", "00003")  # 0 and 180 degrees
    assert set(spread_heldout(cams, 4)) == {"00000", "00003", "00002", "00004"}  # then 90 and 270
    assert len(spread_heldout(cams, 9)) == 5


def test_compare_maps_and_summarise_hand_computed():
    """Two views: errors pooled over their pixels (mean, median, shares under 5 and 25 degrees, all at <=), the
    albedo PSNR and RMSE from the pooled squared error, SSIM the mean over views."""
    normal = np.zeros((4, 4, 3), np.float32)
    normal[..., 2] = 1.0
    ref = normal.copy()
    ref[0, 0] = [0, 1, 0]  # 90 degrees
    ref[0, 1] = [math.sin(math.radians(5)), 0, math.cos(math.radians(5))]  # exactly 5 degrees
    albedo = np.full((4, 4, 3), 0.5, np.float32)
    ref_albedo = albedo.copy()
    ref_albedo[0, 0] = 0.7  # three channels off by 0.2 on one of the 16 compared pixels
    whole = np.ones((4, 4), bool)
    one = compare_maps(normal, albedo, ref, ref_albedo, whole)
    assert one["pixels"] == 16 and one["angle_deg"].shape == (16,) and one["albedo_sq"].shape == (48,)
    np.testing.assert_allclose(np.sort(one["angle_deg"])[-2:], [5.0, 90.0], atol=1e-3)
    exact = compare_maps(normal, albedo, normal, albedo, whole)
    assert exact["ssim"] == pytest.approx(1.0)
    out = summarise([one, exact])
    mse = 3 * 0.04 / 96
    assert out["heldout_albedo_psnr_db"] == pytest.approx(10 * math.log10(1 / mse), abs=1e-4)
    assert out["heldout_albedo_rmse"] == pytest.approx(math.sqrt(mse), rel=1e-5)
    assert out["heldout_normal_mean_deg"] == pytest.approx(95.0 / 32, abs=1e-3)
    assert out["heldout_normal_median_deg"] == 0.0
    assert out["heldout_normal_under5_pct"] == pytest.approx(100.0 * 31 / 32)  # the 5 degree pixel counts
    assert out["heldout_normal_under25_pct"] == pytest.approx(100.0 * 31 / 32)
    assert out["heldout_pixels"] == 32
    assert out["heldout_albedo_ssim"] == pytest.approx((one["ssim"] + 1.0) / 2)
    assert set(summarise([one], "_truth")) == {k + "_truth" for k in out}
    assert summarise([]) == {"heldout_pixels": 0.0}


def test_compare_maps_ssim_of_constant_maps_is_the_luminance_term():
    """Two constant albedo maps 0.6 and 0.5 over the whole image: no variance, so SSIM is
    (2 mu_x mu_y + C1) / (mu_x^2 + mu_y^2 + C1) with C1 = (0.01 * data range)^2."""
    normal = np.zeros((12, 12, 3), np.float32)
    normal[..., 2] = 1
    part = compare_maps(normal, np.full((12, 12, 3), 0.6, np.float32), normal, np.full((12, 12, 3), 0.5, np.float32),
                        np.ones((12, 12), bool))
    c1 = 1e-4
    assert part["ssim"] == pytest.approx((2 * 0.6 * 0.5 + c1) / (0.36 + 0.25 + c1), abs=1e-6)
    assert compare_maps(normal, normal, normal, normal, np.zeros((12, 12), bool))["pixels"] == 0
