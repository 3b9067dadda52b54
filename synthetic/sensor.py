"""The camera sensor: linear sRGB radiance -> Nikon-like camera RGB -> RGGB mosaic -> noisy 14-bit raw
(written as DNG by `synthetic.files.write_dng`).

Colour model. The camera's colour matrix is fitted once from colour-science data: the spectral
sensitivities `MSDS_CAMERA_SENSITIVITIES['Nikon 5100 (NPL)']` (the closest Nikon in the library to a
D750) integrated against the 24 `SDS_COLOURCHECKERS['ColorChecker N Ohta']` reflectances under D65 give
camera RGB; their CIE 1931 XYZ under D65 give the targets; `cam_from_xyz` is the least-squares 3x3
(camera = cam_from_xyz @ XYZ) scaled so the D65 white has a green response of 1, rounded to 1e-4 (the
DNG ColorMatrix1 stores it exactly). Simulated raw is `gain * cam_from_srgb @ rgb` with
`cam_from_srgb = cam_from_xyz @ xyz_from_srgb` (LibRaw's sRGB matrix), so LibRaw inverts it exactly:
the decoded linear value of a linear-sRGB radiance `rgb` is `gain * rgb` (1.0 = raw green clip).
AsShotNeutral is the camera response to linear-sRGB white, normalised to max 1 (green).

Noise: Gaussian approximation of shot noise (variance s / full_well_e for a normalised value s) plus
Gaussian read noise; black level 600, white level 16383, clipped, rounded to integers.
"""
from __future__ import annotations

import functools

import numpy as np

BLACK_LEVEL = 600
WHITE_LEVEL = 16383
CFA = "RGGB"
# LibRaw's xyz_rgb (sRGB primaries, D65), so that decoding with output_color=sRGB inverts our model.
XYZ_FROM_SRGB = np.array([[0.412453, 0.357580, 0.180423],
                          [0.212671, 0.715160, 0.072169],
                          [0.019334, 0.119193, 0.950227]])


@functools.lru_cache(maxsize=1)
def nikon_cam_from_xyz() -> np.ndarray:
    """XYZ -> camera RGB (3, 3) of the simulated D750 (see module docstring), rounded to 1e-4."""
    import colour

    shape = colour.SpectralShape(400, 700, 5)
    sensitivities = colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"].copy().align(shape)
    illuminant = colour.SDS_ILLUMINANTS["D65"].copy().align(shape)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    patches = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    reflectances = np.stack([sd.copy().align(shape).values for sd in patches.values()])      # (24, S)
    lit = reflectances * illuminant.values                                                   # (24, S)
    camera_rgb = lit @ sensitivities.values                                                  # (24, 3)
    xyz = lit @ cmfs.values / float(illuminant.values @ cmfs.values[:, 1])                  # (24, 3)
    solution, *_ = np.linalg.lstsq(xyz, camera_rgb, rcond=None)
    cam_from_xyz = solution.T
    white_xyz = XYZ_FROM_SRGB @ np.ones(3)
    cam_from_xyz = cam_from_xyz / (cam_from_xyz @ white_xyz)[1]
    return np.round(cam_from_xyz, 4)


def cam_from_srgb() -> np.ndarray:
    """Linear sRGB -> camera RGB (3, 3); its row sums are the as-shot neutral (green ~1)."""
    return nikon_cam_from_xyz() @ XYZ_FROM_SRGB


def as_shot_neutral() -> np.ndarray:
    """Camera response (3,) to linear-sRGB white, normalised to max 1 (the green channel)."""
    response = cam_from_srgb() @ np.ones(3)
    if int(np.argmax(response)) != 1:
        raise AssertionError("the simulated camera's largest white response must be green")
    return response / response.max()


def exposure_gain(white_radiance: np.ndarray, target_green: float) -> float:
    """Gain (normalised raw per unit radiance) putting a radiance (3,) at `target_green` in raw green."""
    return float(target_green / (cam_from_srgb() @ white_radiance)[1])


def decoded_scale() -> float:
    """Decoded linear value per (gain x linear-sRGB radiance): the green neutral, 1 after normalisation."""
    return float((cam_from_srgb() @ np.ones(3))[1] / as_shot_neutral()[1])


def mosaic_rggb(camera_rgb: np.ndarray) -> np.ndarray:
    """Bayer RGGB mosaic (H, W) of a camera-RGB image (H, W, 3): R at (even, even), B at (odd, odd)."""
    h, w, _ = camera_rgb.shape
    out = np.empty((h, w), camera_rgb.dtype)
    out[0::2, 0::2] = camera_rgb[0::2, 0::2, 0]
    out[0::2, 1::2] = camera_rgb[0::2, 1::2, 1]
    out[1::2, 0::2] = camera_rgb[1::2, 0::2, 1]
    out[1::2, 1::2] = camera_rgb[1::2, 1::2, 2]
    return out


def raw_frame(radiance_srgb: np.ndarray, gain: float, rng: np.random.Generator | None,
              full_well_e: float, read_noise_dn: float) -> np.ndarray:
    """14-bit raw DN (H, W) uint16 of a linear-sRGB radiance image (H, W, 3); rng None = no noise."""
    signal = mosaic_rggb(radiance_srgb.astype(np.float32) @ (gain * cam_from_srgb()).T.astype(np.float32))
    span = WHITE_LEVEL - BLACK_LEVEL
    if rng is not None:  # shot + read noise as one Gaussian of the summed variance
        sigma = np.sqrt(np.maximum(signal, 0.0) / full_well_e + (read_noise_dn / span) ** 2)
        signal = signal + sigma * rng.standard_normal(signal.shape, dtype=np.float32)
    dn = np.rint(BLACK_LEVEL + signal * span)
    return np.clip(dn, 0, WHITE_LEVEL).astype(np.uint16)
