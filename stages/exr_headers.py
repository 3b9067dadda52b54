"""What each float map of the release holds, as EXR header attributes (``content``, ``units``, the
standard ``comments``, and ``chromaticities`` for colour images): one table, so the files and
CONVENTIONS.md say the same thing. Writers pass ``header=EXR_HEADERS[kind]`` to ``write_exr``."""
from __future__ import annotations

from pipeline.codecs.exr import describe

_RADIANCE = "relative linear radiance: 1.0 is the sensor's clip level of the green channel"
_REFLECTANCE = "reflectance, linear, 0..1"
_UNITLESS = "unitless"


def _world_normals(what: str) -> dict[str, object]:
    return describe(f"RGB: {what} (x, y, z; stage frame, metres, +y up); A: validity alpha in [0, 1], "
                    "valid = alpha > 0.5; normal 0 where alpha is 0.",
                    "RGB unit-vector components, A unitless")


EXR_HEADERS: dict[str, dict[str, object]] = {
    "full_on": describe("RGB: decoded camera image under white light (all LEDs), linear sRGB.", _RADIANCE, True),
    "pos": describe("RGB: decoded camera image under the colour gradient g+, linear sRGB.", _RADIANCE, True),
    "neg": describe("RGB: decoded camera image under the colour gradient g-, linear sRGB.", _RADIANCE, True),
    "normal_alpha": _world_normals("world-space unit normal from the gradient ratio (eq. 1)"),
    "normal_diffuse": _world_normals("world-space unit normal with the specular reflection fitted out and the "
                                     "mesh's occlusion divided out"),
    "albedo": describe("RGB: diffuse albedo from the white image (holds ambient occlusion), linear sRGB.",
                       _REFLECTANCE, True),
    "albedo_diffuse": describe("RGB: diffuse albedo less the fitted white-light specular reflection, linear sRGB.",
                               _REFLECTANCE, True),
    "texture_albedo": describe("RGB: baked albedo texture of the UV atlas (row 0 is v = 1), linear sRGB.",
                               _REFLECTANCE, True),
    "texture_normal": describe("RGB: world-space unit normal per texel (stage frame, +y up); 0 where no camera "
                               "saw the texel.", "unit-vector components"),
    "texture_view_count": describe("Y: number of cameras blended per texel.", "count"),
    "texture_confidence": describe("Y: bake confidence per texel, 0 = not seen, 1 = best.", _UNITLESS),
    "texture_roughness": describe("Y: perceptual GGX roughness r per texel (GGX alpha = r^2), 0.05..1.", _UNITLESS),
    "texture_roughness_fit_rms": describe("Y: RMS error of the roughness fit per texel (0 = not seen).",
                                          "white units: 1.0 is the camera's white reference"),
    "texture_occlusion": describe("Y: cosine-weighted fraction of the sphere the texel sees past the mesh "
                                  "(1 = unoccluded).", _UNITLESS),
    "texture_albedo_deoccluded": describe("RGB: albedo texture divided by the occlusion (floored at 0.2), "
                                          "linear sRGB.", _REFLECTANCE, True),
    "texture_diffuse_ratio": describe("RGB: share of the white-light albedo explained as diffuse, per channel.",
                                      "ratio, 0..1"),
    "texture_albedo_intrinsic": describe("RGB: albedo x diffuse ratio / occlusion, linear sRGB.", _REFLECTANCE, True),
    "render_normal": describe("RGB: shading normal of the novel view, world space (stage frame, +y up); 0 outside "
                              "the mask.", "unit-vector components"),
    "render_albedo": describe("RGB: shading albedo of the novel view, linear sRGB; 0 outside the mask.",
                              _REFLECTANCE, True),
    "render_roughness": describe("Y: perceptual GGX roughness of the novel view; 0 outside the mask.", _UNITLESS),
    "relit": describe("RGB: the novel view relit under the environment, linear sRGB, premultiplied by alpha; "
                      "A: the share of the pixel the subject covers.",
                      "RGB linear radiance in the environment map's own units, A unitless", True),
    "relightset_image": describe("RGB: the relighting-set example's image under its turned environment, linear sRGB, "
                                 "premultiplied by alpha; A: the share of the pixel the subject covers.",
                                 "RGB linear radiance in the environment map's own units, A unitless", True),
    "relightset_albedo": describe("RGB: the example's diffuse albedo (specular light and ambient occlusion out), "
                                  "linear sRGB; 0 outside the mask.", _REFLECTANCE, True),
    "relightset_normal": describe("RGB: unit normal in the example's CAMERA frame, OpenCV axes (x right, y down, "
                                  "z forward; facing the camera: z < 0); 0 outside the mask.",
                                  "unit-vector components"),
}
"""Header attributes per asset kind of the release's EXR files."""
