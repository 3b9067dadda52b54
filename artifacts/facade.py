"""The artifact facade: the stages' products read by what they are, from the work store or from a release.

Where each product lies is :mod:`artifacts.layout`'s (:data:`~artifacts.layout.PRODUCTS` in its stage's artifact
folder, :data:`~artifacts.layout.RELEASE_KINDS` in the release's assets manifest). Two small backends resolve a
product (and a camera) to a file: :class:`StoreBackend` over a stage task's upstream folders of the work store,
:class:`ReleaseBackend` over one action of a release. :class:`ActionArtifacts` reads each product by what it is
(cameras, normal maps, masks, mesh, atlas, textures, light model, colour matrices) through either, so the
stages and the consumer API (:class:`manifests.consumer.ActionView`) read the same way (a stage writes its own
products at :class:`artifacts.layout.ArtifactWriter`'s paths). The asset the ``relight`` and ``relightset``
stages render from is built by :func:`stages.relightable.load_relightable_asset` from either source (in a module
of its own: the renderer it imports stays out of the cache keys of the stages that only read products here).
"""
from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from artifacts.camera import Camera
from artifacts.layout import PRODUCTS, RELEASE_KINDS, check_product
from pipeline.codecs.exr import read_exr
from pipeline.codecs.image import mask_from_png, read_png
from pipeline.errors import InputError


class StoreBackend:
    """Products of one stage task's upstream artifacts in the work store (folders by stage name)."""

    def __init__(self, upstream: Mapping[str, Path]):
        self.upstream = {name: Path(path) for name, path in upstream.items()}

    def path(self, product: str, camera: str | None = None, **fields: str) -> Path:
        """Where a product is (it may not exist); KeyError for an unknown product or a stage not upstream."""
        check_product(product)
        stage, rel = PRODUCTS[product]
        if stage not in self.upstream:
            raise KeyError(f"product {product!r} comes from stage {stage!r}, which is not upstream "
                           f"(upstream: {sorted(self.upstream)})")
        return self.upstream[stage] / rel.format(camera=camera, **fields)

    def missing(self, product: str, camera: str | None, path: Path, **fields: str) -> FileNotFoundError:
        """The error for a product whose file is not there (naming the stage, camera, product and file)."""
        what = f"camera {camera}" if camera is not None else "no camera"
        return FileNotFoundError(f"{PRODUCTS[product][0]} artifact, {what}, {product}: file {path} not found")

    def where(self) -> Path:
        """The folder an error about the action's maps names: the photometric normal maps'."""
        if "photometric" in self.upstream:
            return self.upstream["photometric"] / "normal_alpha"
        return next(iter(self.upstream.values()), Path("."))

    def calibrated_cameras(self, artifacts: "ActionArtifacts") -> dict[str, Camera]:
        """camera_id -> :class:`Camera` of every calibrated camera (``cameras.json``; the record in ``record``)."""
        return read_cameras(artifacts.existing("cameras"))

    def materials_f0(self) -> float:
        """The F0 in the materials artifact's record (:func:`fitted_f0`); KeyError when materials is not
        upstream."""
        if "materials" not in self.upstream:
            raise KeyError(f"stage 'materials' is not upstream (upstream: {sorted(self.upstream)})")
        return fitted_f0(self.upstream["materials"])


class ReleaseBackend:
    """Products of one action of a release, found through its assets manifest.

    ``view`` is the action's :class:`manifests.consumer.ActionView` (its ``asset`` and ``path`` give the row
    and file of a kind and camera, with the consumer's errors)."""

    def __init__(self, view: Any):
        self.view = view

    def path(self, product: str, camera: str | None = None, **fields: str) -> Path:
        """Where a product is; KeyError for an unknown product, one a release does not hold, or a (kind,
        camera) absent from the assets manifest (naming the action, camera and kind)."""
        check_product(product)
        if product not in RELEASE_KINDS:
            raise KeyError(f"product {product!r} is not published in a release; released products are "
                           f"{sorted(RELEASE_KINDS) + ['cameras']}")
        return self.view.path(RELEASE_KINDS[product].format(**fields), camera)

    def missing(self, product: str, camera: str | None, path: Path, **fields: str) -> FileNotFoundError:
        """The error for a product listed in the assets manifest whose file is not there (naming the action,
        camera, kind and file, as :class:`manifests.consumer.ActionView` does)."""
        what = f"camera {camera}" if camera is not None else "no camera"
        kind = RELEASE_KINDS[product].format(**fields)
        return FileNotFoundError(f"action {self.view.action_id}, {what}, {kind}: file {path} is listed in the "
                                 "assets table but missing on disk")

    def where(self) -> Path:
        """The folder an error about the action's maps names: the action's folder of the release."""
        return self.view.release.root / "actions" / self.view.action_id

    def calibrated_cameras(self, artifacts: "ActionArtifacts") -> dict[str, Camera]:
        """camera_id -> :class:`Camera` of the frames of the action's ``transforms.json`` (OpenCV ``K``,
        ``cam_from_world_opencv``, ``w``, ``h``; the frame in ``record``)."""
        return transforms_cameras(artifacts.json("transforms"))

    def materials_f0(self) -> float:
        """``materials.f0`` of the release's ``config.yaml`` (the resolved config of the run that wrote it).

        Raises:
            InputError: no config.yaml, no ``materials.f0`` in it, or not a number in [0, 1]."""
        import yaml

        path = Path(self.view.release.root) / "config.yaml"
        try:
            f0 = (yaml.safe_load(path.read_text()) or {})["materials"]["f0"]
        except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
            raise InputError(path, f"no materials.f0 in the release's config ({type(exc).__name__}: {exc})") from exc
        if isinstance(f0, bool) or not isinstance(f0, (int, float)) or not 0.0 <= f0 <= 1.0:
            raise InputError(path, f"materials.f0 {f0!r} is not a number in [0, 1]")
        return float(f0)


def transforms_cameras(transforms: Mapping[str, Any]) -> dict[str, Camera]:
    """camera_id -> :class:`Camera` of the frames of a release's ``transforms.json`` (OpenCV ``K``,
    ``cam_from_world_opencv``, ``w``, ``h``; the frame in ``record``)."""
    return {f["camera_id"]: Camera(K=f["K"], cam_from_world=f["cam_from_world_opencv"], width=f["w"], height=f["h"],
                                   camera_id=str(f["camera_id"]), record=dict(f))
            for f in transforms["frames"]}


def read_cameras(cameras_json: Path) -> dict[str, Camera]:
    """camera_id -> :class:`Camera` of the calibrated cameras of a ``cameras.json`` (their records, with
    ``white_reference`` and the rest, in ``Camera.record``)."""
    records = json.loads(Path(cameras_json).read_text())["cameras"]
    return {r["camera_id"]: Camera.from_json(r) for r in records}


def load_light_model(lights_dir: Path) -> Any:
    """The fitted :class:`calibration.light.LightModel` of a ``lights`` artifact, or None when the session uses
    the ideal one."""
    return ActionArtifacts({"lights": lights_dir}).light_model()


def fitted_f0(artifact: Path) -> float:
    """The Fresnel F0 a materials artifact's roughness texture was fitted with (its record's config): roughness
    and F0 trade off under broad light, so whoever models the specular light with that texture uses this F0."""
    path = Path(artifact) / "_SUCCESS.json"
    try:
        f0 = float(json.loads(path.read_text())["record"]["config"]["f0"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(path, f"no materials f0 in the artifact's record ({type(exc).__name__}: {exc})") from exc
    if not 0.0 <= f0 <= 1.0:
        raise InputError(path, f"materials f0 {f0} is outside [0, 1]")
    return f0


def load_atlas_mesh(obj_path: Path):
    """The textured OBJ of the textures stage as ``(vertices (V, 3) welded, faces (F, 3) into them,
    Atlas)``: the OBJ splits vertices along chart seams; welding identical positions gives back one
    surface, so normals and depth maps are continuous across seams."""
    from pipeline.codecs.mesh import read_obj
    from artifacts.atlas import Atlas

    obj = read_obj(obj_path)
    if obj["uvs"] is None or obj["uv_faces"] is None or not np.array_equal(obj["uv_faces"], obj["faces"]):
        raise InputError(obj_path, "the textured mesh has no per-vertex UVs (uv faces must equal faces)")
    vertices, inverse = np.unique(np.asarray(obj["vertices"], np.float64), axis=0, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1).astype(np.int64)
    faces = inverse[obj["faces"]]
    atlas = Atlas(vmapping=inverse, faces=np.asarray(obj["faces"], np.int32), uvs=np.asarray(obj["uvs"], np.float32),
                  width=1, height=1, stats={})
    return vertices, faces, atlas


class ActionArtifacts:
    """The products of one action, read by what they are, from the work store or from a release.

    ``source``: a stage task's upstream folders by stage name (the work store, :class:`StoreBackend`) or a
    backend (:class:`StoreBackend`, :class:`ReleaseBackend`). One action of a release opens as
    :func:`manifests.release_artifacts` (``release_artifacts(release, action_id)``, the folder or an opened
    release), the action's :attr:`manifests.consumer.ActionView.artifacts`: the manifests read through this
    facade, never the other way. Readers raise KeyError for an unknown product, or one the source cannot hold,
    and FileNotFoundError naming the product, camera and file when its file is not there.
    """

    def __init__(self, source: Mapping[str, Path] | StoreBackend | ReleaseBackend):
        self.backend = source if isinstance(source, (StoreBackend, ReleaseBackend)) else StoreBackend(source)

    @classmethod
    def from_store(cls, store_root: Path, action_id: str, session_id: str,
                   stages: tuple[str, ...]) -> "ActionArtifacts | None":
        """The last committed results of ``stages`` for an action in a work store (``<work>/artifacts``), as a
        stage task would see them (session-scoped stages by ``session_id``); None when one is missing."""
        from pipeline.store import ArtifactStore

        store = ArtifactStore(store_root)
        upstream = {}
        for stage in stages:
            folder = store.latest_dir(stage, action_id) or store.latest_dir(stage, session_id)
            if folder is None:
                return None
            upstream[stage] = folder
        return cls(upstream)

    @property
    def upstream(self) -> dict[str, Path]:
        """The upstream folders by stage name of a work-store source (AttributeError for a release)."""
        if not isinstance(self.backend, StoreBackend):
            raise AttributeError("a release source has no upstream folders")
        return self.backend.upstream

    def path(self, product: str, camera: str | None = None, **fields: str) -> Path:
        """Where a product is (it may not exist); KeyError for an unknown product or one the source cannot
        hold."""
        return self.backend.path(product, camera, **fields)

    def has(self, product: str, camera: str | None = None, **fields: str) -> bool:
        """Whether the source holds the product's file."""
        try:
            return self.path(product, camera, **fields).is_file()
        except KeyError:
            return False

    def existing(self, product: str, camera: str | None = None, **fields: str) -> Path:
        """The product's file; KeyError as :meth:`path`, FileNotFoundError naming product, camera and file
        when it is not there."""
        path = self.path(product, camera, **fields)
        if not path.is_file():
            raise self.backend.missing(product, camera, path, **fields)
        return path

    def where(self) -> Path:
        """The folder an error about the action's maps names: the photometric normal maps' in the work store,
        the action's in a release."""
        return self.backend.where()

    # -- files by format ----------------------------------------------------------------------------

    def exr(self, product: str, camera: str | None = None, channels: tuple[str, ...] | None = None,
            **fields: str) -> np.ndarray:
        """A product's EXR as float32: (H, W) for one channel, else (H, W, C), in ``channels``' order (default
        R, G, B, A when present; :func:`pipeline.codecs.exr.read_exr`)."""
        return read_exr(self.existing(product, camera, **fields), channels=channels)

    def png(self, product: str, camera: str | None = None, **fields: str) -> np.ndarray:
        """A product's PNG as its stored dtype, (H, W) or (H, W, C)."""
        return read_png(self.existing(product, camera, **fields))

    def json(self, product: str, camera: str | None = None) -> Any:
        """A product's JSON document."""
        return json.loads(self.existing(product, camera).read_text(encoding="utf-8"))

    # -- typed readers ------------------------------------------------------------------------------

    def calibrated_cameras(self) -> dict[str, Camera]:
        """camera_id -> :class:`Camera` of every calibrated camera of the action, at the decoded maps' size."""
        return self.backend.calibrated_cameras(self)

    def camera_records(self, product: str = "cameras") -> dict[str, dict[str, Any]]:
        """camera_id -> record (``K``, ``cam_from_world``, ``width``, ``height``, ``white_reference``, ...) of the
        calibrated cameras of a ``cameras.json`` product: ``cameras`` (the decoded maps') or
        ``session_cameras`` (the session calibration's, at the sensor's size)."""
        return {record["camera_id"]: record for record in self.json(product)["cameras"]}

    def unregistered_cameras(self) -> dict[str, str]:
        """camera_id -> why, for the cameras of the session its calibration could not register."""
        return dict(self.json("session_cameras").get("unregistered", {}))

    def cameras(self) -> dict[str, Camera]:
        """camera_id -> :class:`Camera` of the calibrated cameras that have a photometric normal map, sorted by
        id (a missing camera, with no calibration or failed frames, has none)."""
        cameras = self.calibrated_cameras()
        return {c: cameras[c] for c in sorted(cameras) if self.has("normal_alpha", c)}

    def mask(self, camera: str) -> np.ndarray:
        """(H, W) bool subject mask of a camera."""
        return mask_from_png(self.png("mask", camera))

    def camera_maps(self, min_alpha: float) -> Iterator[tuple[str, Camera, np.ndarray, np.ndarray, np.ndarray]]:
        """Yield ``(camera_id, camera, normal_alpha (H, W, 4), mask (H, W) bool, valid (H, W) bool)`` per
        camera of :meth:`cameras`; ``valid`` = alpha above ``min_alpha`` inside the mask."""
        for cam_id, cam in self.cameras().items():
            normal_alpha = self.exr("normal_alpha", cam_id)
            mask = self.mask(cam_id)
            yield cam_id, cam, normal_alpha, mask, (normal_alpha[..., 3] > min_alpha) & mask

    def map(self, product: str, camera: str, channels: int = 3) -> np.ndarray:
        """A per-camera float map (H, W, channels) read from its EXR."""
        return self.exr(product, camera)[..., :channels]

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The action's mesh: vertices (V, 3) metres, world frame; faces (F, 3)
        (:func:`pipeline.codecs.mesh.read_ply`)."""
        from pipeline.codecs.mesh import read_ply

        return read_ply(self.existing("mesh"))

    def atlas_mesh(self) -> tuple[np.ndarray, np.ndarray, Any]:
        """The textured mesh welded (vertices, faces, :class:`artifacts.atlas.Atlas`)."""
        return load_atlas_mesh(self.existing("textured_mesh"))

    def texture(self, product: str, channels: int = 3) -> np.ndarray:
        """A texture of the atlas: (T, T, 3) for ``channels`` 3, (T, T) for 1."""
        texture = self.exr(product)
        if channels == 1:
            return texture[..., 0] if texture.ndim == 3 else texture
        return texture[..., :channels]

    def colour_matrix(self, camera: str) -> np.ndarray | None:
        """The session's fitted colour matrix (3, 3) float32 of a camera, or None (identity) when it has none."""
        path = self.path("colour_matrix", camera)
        return np.asarray(json.loads(path.read_text())["matrix"], np.float32) if path.exists() else None

    def plate(self, camera: str) -> np.ndarray | None:
        """The session's clean plate (H, W, 3) of a camera, or None when it has none."""
        return read_exr(self.path("plate", camera)) if self.has("plate", camera) else None

    def materials_f0(self) -> float:
        """The Fresnel F0 the materials stage fitted the roughness texture with: roughness and F0 trade off under
        broad light, so whoever models the specular light with that texture uses this F0."""
        return self.backend.materials_f0()

    def light_model(self) -> Any:
        """The session's fitted :class:`calibration.light.LightModel`, or None when it uses the ideal one."""
        from calibration.light import LightModel

        record = self.json("light_model")
        return None if record.get("ideal") else LightModel.from_json(record["model"])
