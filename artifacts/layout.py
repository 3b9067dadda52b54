"""Where each product of the stages lies: in its stage's artifact folder and in a release.

:data:`PRODUCTS` gives the stage and the path inside its artifact folder of every product another stage or the
consumer API reads; :data:`RELEASE_KINDS` the kind of the release's assets manifest that holds it;
:class:`ArtifactWriter` gives a stage the paths of the products it writes. The readers are in
:mod:`artifacts.facade`. This module imports nothing of the project, so a stage that only writes its products
through it keeps its cache key's code digest to its own modules.
"""
from __future__ import annotations

from pathlib import Path

# The textures of the atlas: the textures stage bakes the first four, the materials stage fits the rest.
_TEXTURES = {"albedo": "textures", "normal": "textures", "view_count": "textures", "confidence": "textures",
             "roughness": "materials", "roughness_fit_rms": "materials", "occlusion": "materials",
             "albedo_deoccluded": "materials", "diffuse_ratio": "materials", "albedo_intrinsic": "materials"}

#: Where each product lives inside its stage's artifact folder: (stage, relative path); ``{camera}`` is a
#: camera id, other fields (``{environment}``) are named by the reader.
PRODUCTS: dict[str, tuple[str, str]] = {
    "session_cameras": ("cameras", "cameras.json"),
    "colour_matrix": ("colour", "colour/{camera}.json"),
    "plate": ("plates", "plates/{camera}.exr"),
    "light_model": ("lights", "light_model.json"),
    "cameras": ("decode", "cameras.json"),
    "transforms": ("decode", "transforms.json"),
    "full_on": ("decode", "full_on/{camera}.exr"),
    "pos": ("decode", "pos/{camera}.exr"),
    "neg": ("decode", "neg/{camera}.exr"),
    "full_on_png": ("decode", "full_on/{camera}.png"),
    "pos_png": ("decode", "pos/{camera}.png"),
    "neg_png": ("decode", "neg/{camera}.png"),
    "clipped": ("decode", "clipped/{camera}.png"),
    "normal_alpha": ("photometric", "normal_alpha/{camera}.exr"),
    "albedo": ("photometric", "albedo/{camera}.exr"),
    "mask": ("photometric", "mask/{camera}.png"),
    "normal_diffuse": ("diffuse_normals", "normal_diffuse/{camera}.exr"),
    "albedo_diffuse": ("diffuse_normals", "albedo_diffuse/{camera}.exr"),
    "mesh": ("geometry", "mesh/mesh.ply"),
    "textured_mesh": ("textures", "mesh/textured.obj"),
    "textured_material": ("textures", "mesh/textured.mtl"),
    "albedo_texture_png": ("textures", "textures/albedo.png"),
    **{f"{name}_texture": (stage, f"textures/{name}.exr") for name, stage in _TEXTURES.items()},
    "render_cameras": ("relight", "renders/cameras.json"),
    "render_environments": ("relight", "renders/environments.json"),
    **{f"render_{name}": ("relight", f"renders/{{camera}}/{name}.{'png' if name == 'mask' else 'exr'}")
       for name in ("normal", "albedo", "roughness", "mask")},
    "relit": ("relight", "renders/{camera}/{environment}.exr"),
    "relight_examples": ("relightset", "relight/examples.json"),
    "relight_example": ("relightset", "relight/{example}/example.json"),
}

#: The release's asset kind of each product a release holds (the kinds the stages' ``release_files`` give;
#: ``cameras`` is read from ``transforms``, the release's copy of the calibrated cameras).
RELEASE_KINDS: dict[str, str] = {
    **{p: p for p in ("transforms", "full_on", "pos", "neg", "full_on_png", "pos_png", "neg_png", "normal_alpha",
                      "albedo", "mask", "normal_diffuse", "albedo_diffuse", "mesh", "render_cameras",
                      "render_environments", "render_normal", "render_albedo", "render_roughness", "render_mask")},
    "textured_mesh": "mesh_textured",
    "textured_material": "mesh_material",
    "albedo_texture_png": "texture_albedo_preview",
    **{f"{name}_texture": f"texture_{name}" for name in _TEXTURES},
    "relit": "relit_{environment}",
}


def check_product(product: str) -> None:
    """KeyError naming the known products when ``product`` is not one of :data:`PRODUCTS`."""
    if product not in PRODUCTS:
        raise KeyError(f"unknown product {product!r}; products are {sorted(PRODUCTS)}")


class ArtifactWriter:
    """Where a stage task writes its products: their :data:`PRODUCTS` paths under its output folder."""

    def __init__(self, stage: str, out_dir: Path):
        self.stage = stage
        self.out_dir = Path(out_dir)

    def path(self, product: str, camera: str | None = None, **fields: str) -> Path:
        """The output path of one of this stage's products; KeyError for an unknown product or another stage's."""
        check_product(product)
        stage, rel = PRODUCTS[product]
        if stage != self.stage:
            raise KeyError(f"product {product!r} is written by stage {stage!r}, not {self.stage!r}")
        return self.out_dir / rel.format(camera=camera, **fields)

    def folder(self, product: str) -> Path:
        """The folder of one of this stage's per-camera products (``colour/``, ``normal_alpha/``, ...)."""
        return self.path(product, "_").parent
