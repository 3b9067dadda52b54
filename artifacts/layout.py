"""Where each product of the stages lies: in its stage's artifact folder and in a release.

:data:`PRODUCTS` gives the stage and the path inside its artifact folder of every product another stage or the
consumer API reads, or that a stage publishes; :data:`RELEASE_KINDS` the kind of the release's assets manifest
that holds it; :class:`ArtifactWriter` gives a stage the paths of the products it writes, and
:func:`released_files` (and :func:`released_file`, one file) the files a stage publishes, derived from the two
tables (every stage lists the files it publishes through them, per camera where a product is one file a camera). The readers are in :mod:`artifacts.facade`. This module imports nothing of the project, so
a stage that only writes its products through it keeps its cache key's code digest to its own modules.
"""
from __future__ import annotations

import re
from collections.abc import Collection, Mapping
from pathlib import Path

COLMAP_MODEL_DIR = "colmap/sparse/0"
"""Where the exports stage's COLMAP model lies in the action folder (the sparse/0 layout COLMAP, nerfstudio
and gaussian-splatting readers look for); transforms.json names its points3D.ply."""

# The exports stage's COLMAP text model: product -> file name in COLMAP_MODEL_DIR.
_COLMAP_FILES = {"colmap_cameras": "cameras.txt", "colmap_images": "images.txt", "colmap_points": "points3D.txt",
                 "colmap_points_ply": "points3D.ply"}

# The textures of the atlas: the textures stage bakes the first four, the materials stage fits the rest.
_TEXTURES = {"albedo": "textures", "normal": "textures", "view_count": "textures", "confidence": "textures",
             "roughness": "materials", "roughness_fit_rms": "materials", "occlusion": "materials",
             "albedo_deoccluded": "materials", "diffuse_ratio": "materials", "albedo_intrinsic": "materials"}

# The files of a relighting-set example (``relight/<example>/``): product -> file name; ``relight_example_<x>``
# is released under the kind ``relight_<x>``.
_EXAMPLE_FILES = {"image": "image.exr", "image_png": "image.png", "albedo": "albedo.exr", "albedo_png": "albedo.png",
                  "normal": "normal.exr", "normal_png": "normal.png", "mask": "mask.png"}
EXAMPLE_PRODUCTS = tuple(f"relight_example_{name}" for name in _EXAMPLE_FILES)
"""The products of the files of a relighting-set example besides its ``example.json``, in the order the
relightset stage publishes them."""

# The PNG previews of the atlas's textures (``previews/texture_<name>.png``) and the stage that draws each.
_TEXTURE_PREVIEWS = {"normal": "textures", "confidence": "textures", "roughness": "materials",
                     "occlusion": "materials", "albedo_intrinsic": "materials"}

#: Where each product lives inside its stage's artifact folder: (stage, relative path); ``{camera}`` is a
#: camera id, other fields (``{environment}``) are named by the reader or the writer. The previews (PNGs for
#: people, under ``previews/``) are products too, so that a stage writes them at these paths.
PRODUCTS: dict[str, tuple[str, str]] = {
    "session_cameras": ("cameras", "cameras.json"),
    "calibration_summary": ("cameras", "calibration.json"),
    "calibration_colmap": ("cameras", "colmap"),  # a folder: the calibration's own COLMAP text model
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
    "filled_holes": ("photometric", "filled_holes/{camera}.png"),  # work store only: the holes the mask filled
    "normal_preview": ("photometric", "previews/normal_{camera}.png"),
    "albedo_preview": ("photometric", "previews/albedo_{camera}.png"),
    "normals_sheet": ("photometric", "previews/normals_sheet.png"),
    "gaps_sheet": ("photometric", "previews/gaps_sheet.png"),  # work store only: the filled holes' decision
    "normal_diffuse": ("diffuse_normals", "normal_diffuse/{camera}.exr"),
    "albedo_diffuse": ("diffuse_normals", "albedo_diffuse/{camera}.exr"),
    "normal_diffuse_preview": ("diffuse_normals", "previews/normal_diffuse_{camera}.png"),
    "normals_diffuse_sheet": ("diffuse_normals", "previews/normals_diffuse_sheet.png"),
    "mesh": ("geometry", "mesh/mesh.ply"),
    "sdf_losses_preview": ("geometry", "previews/sdf_losses.png"),
    "mesh_normals_preview": ("geometry", "previews/mesh_normals.png"),
    "textured_mesh": ("textures", "mesh/textured.obj"),
    "textured_material": ("textures", "mesh/textured.mtl"),
    "albedo_texture_png": ("textures", "textures/albedo.png"),
    **{f"{name}_texture": (stage, f"textures/{name}.exr") for name, stage in _TEXTURES.items()},
    **{f"texture_{name}_preview": (stage, f"previews/texture_{name}.png") for name, stage in _TEXTURE_PREVIEWS.items()},
    "render_cameras": ("relight", "renders/cameras.json"),
    "render_environments": ("relight", "renders/environments.json"),
    **{f"render_{name}": ("relight", f"renders/{{camera}}/{name}.{'png' if name == 'mask' else 'exr'}")
       for name in ("normal", "albedo", "roughness", "mask")},
    "relit": ("relight", "renders/{camera}/{environment}.exr"),
    "relit_preview": ("relight", "previews/relit.png"),
    "turntable_preview": ("relight", "previews/turntable.png"),
    "export_mesh": ("exports", "mesh/textured.obj"),
    "export_material": ("exports", "mesh/textured.mtl"),
    "export_texture": ("exports", "mesh/textured.png"),
    "export_glb": ("exports", "mesh/textured.glb"),
    **{product: ("exports", f"{COLMAP_MODEL_DIR}/{name}") for product, name in _COLMAP_FILES.items()},
    "relight_examples": ("relightset", "relight/examples.json"),
    "relight_example": ("relightset", "relight/{example}/example.json"),
    **{f"relight_example_{name}": ("relightset", f"relight/{{example}}/{file}") for name, file in _EXAMPLE_FILES.items()},
}

#: The release's asset kind of each product a release holds (the kinds the stages' ``release_files`` give;
#: ``cameras`` is read from ``transforms``, the release's copy of the calibrated cameras; ``textured_mesh`` and
#: ``textured_material`` are read from the exports stage's copies, ``export_mesh`` and ``export_material``, which
#: the release holds under the same kinds, so the textures stage does not publish its own: a stage publishes the
#: products it names to :func:`released_files`, not every product of its own that has a kind here). The
#: per-camera previews are not released, only their contact sheets (both sheets under the kind ``preview``).
#: The relighting set's examples (``relight_example*``) lie at the release's root, not in an action's folder.
RELEASE_KINDS: dict[str, str] = {
    **{p: p for p in ("transforms", "full_on", "pos", "neg", "full_on_png", "pos_png", "neg_png", "normal_alpha",
                      "albedo", "mask", "normal_diffuse", "albedo_diffuse", "mesh", "render_cameras",
                      "render_environments", "render_normal", "render_albedo", "render_roughness", "render_mask")},
    "textured_mesh": "mesh_textured",
    "textured_material": "mesh_material",
    "albedo_texture_png": "texture_albedo_preview",
    **{f"{name}_texture": f"texture_{name}" for name in _TEXTURES},
    "relit": "relit_{environment}",
    "normals_sheet": "preview",
    "normals_diffuse_sheet": "preview",
    "sdf_losses_preview": "preview_sdf_losses",
    "mesh_normals_preview": "preview_mesh_normals",
    **{f"texture_{name}_preview": f"preview_texture_{name}" for name in _TEXTURE_PREVIEWS},
    "relit_preview": "preview_relit",
    "turntable_preview": "preview_turntable",
    "calibration_summary": "calibration",
    "export_mesh": "mesh_textured",
    "export_material": "mesh_material",
    "export_texture": "mesh_texture",
    "export_glb": "mesh_glb",
    **{product: "colmap_" + name.replace(".", "_") for product, name in _COLMAP_FILES.items()},
    "relight_example": "relight_example",
    **{f"relight_example_{name}": f"relight_{name}" for name in _EXAMPLE_FILES},
}


def check_product(product: str) -> None:
    """KeyError naming the known products when ``product`` is not one of :data:`PRODUCTS`."""
    if product not in PRODUCTS:
        raise KeyError(f"unknown product {product!r}; products are {sorted(PRODUCTS)}")


def released_files(stage: str, artifact: Path, products: tuple[str, ...], optional: tuple[str, ...] = (),
                   fields: Mapping[str, Collection[str]] | None = None) -> list[tuple[Path, str, str, str | None]]:
    """``(file, path in the action's release folder, kind, camera)`` of the files a stage publishes: each of
    ``products`` at its :data:`PRODUCTS` path in the artifact folder ``artifact`` and at the same path in the
    release, under its :data:`RELEASE_KINDS` kind, product by product in the order given.

    A product whose path has no field is one file with no camera: left out when it is in ``optional`` and its
    file is not there; a required one is listed whether or not it is (the publisher names a missing file). A
    product whose path has fields (``{camera}``, ``{environment}``) is every file of the artifact that its path
    matches, sorted by path, zero or more: ``{camera}`` is the row's camera, every field fills the kind
    (``relit_{environment}``); a field named in ``fields`` matches only the values given there (a path whose
    field would match another product's file, as ``renders/{camera}/{environment}.exr`` matches
    ``renders/<camera>/normal.exr``, needs them). KeyError for a product that is another stage's or not
    released."""
    files = []
    for product in products:
        rel = _released_path(stage, product)
        if "{" not in rel:
            if product in optional and not (Path(artifact) / rel).is_file():
                continue
            files.append(released_file(stage, artifact, product))
            continue
        for path, values in _matching_files(Path(artifact), rel, fields or {}):
            files.append((path, rel.format(**values), RELEASE_KINDS[product].format(**values), values.get("camera")))
    return files


def _released_path(stage: str, product: str) -> str:
    """A released product's :data:`PRODUCTS` path (its fields unfilled); KeyError for a product that is another
    stage's or not released."""
    check_product(product)
    owner, rel = PRODUCTS[product]
    if owner != stage:
        raise KeyError(f"product {product!r} is written by stage {owner!r}, not {stage!r}")
    if product not in RELEASE_KINDS:
        raise KeyError(f"product {product!r} has no kind in RELEASE_KINDS: a release does not hold it")
    return rel


def released_file(stage: str, artifact: Path, product: str, camera: str | None = None,
                  **fields: str) -> tuple[Path, str, str, str | None]:
    """``(file, path in the release, kind, camera)`` of one file of a stage's product, its fields filled (the
    ``example`` of ``relight/{example}/image.exr``): at its :data:`PRODUCTS` path in the artifact folder and the
    same path in the release, under its :data:`RELEASE_KINDS` kind; listed whether or not the file is there (the
    publisher names a missing file). KeyError for a product that is another stage's or not released."""
    rel = _released_path(stage, product)
    rel = rel.format(camera=camera, **fields)
    return Path(artifact) / rel, rel, RELEASE_KINDS[product].format(camera=camera, **fields), camera


def _matching_files(artifact: Path, rel: str, fields: Mapping[str, Collection[str]]) -> list[tuple[Path, dict[str, str]]]:
    """``(file, {field: value})`` of the files under ``artifact`` that the product path ``rel`` (with ``{field}``
    parts, each one path component or part of one) matches, sorted by path; a field in ``fields`` only takes
    the values given there."""
    parts = re.split(r"\{(\w+)\}", rel)  # literal, field, literal, field, ..., literal
    pattern = "".join(re.escape(part) if i % 2 == 0 else f"(?P<{part}>[^/]+)" for i, part in enumerate(parts))
    glob = "".join(part if i % 2 == 0 else "*" for i, part in enumerate(parts))
    found = []
    for path in sorted(artifact.glob(glob)):
        match = re.fullmatch(pattern, path.relative_to(artifact).as_posix())
        if match is None or not path.is_file():
            continue
        values = match.groupdict()
        if all(values[name] in allowed for name, allowed in fields.items() if name in values):
            found.append((path, values))
    return found


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
