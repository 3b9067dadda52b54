"""Reading a release: manifests as Arrow/pandas tables, assets loaded lazily, integrity checks.

    >>> import manifests
    >>> rel = manifests.open_release("runs/demo/release")
    >>> rel.actions                       # pandas DataFrame, read on first access
    >>> view = rel.action(rel.action_ids[0])
    >>> n = view.normals("00000")         # (H, W, 3) float32 world normals
    >>> a = view.normal_alpha("00000")    # (H, W) float32 validity alpha
    >>> d = view.normals("00000", diffuse=True)  # the same with the specular reflection fitted out
    >>> report = manifests.verify_release("runs/demo/release")
"""
from __future__ import annotations

import json
import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from manifests.schemas import ILLUMINATIONS, TABLE_SPECS
from manifests.writer import (INDEX_NAME, MANIFEST_DIR, file_sha256, manifest_path, read_index, read_manifest,
                              release_relpath)


class ReleaseError(FileNotFoundError):
    """A folder that is not a release (no ``manifests/`` with any manifest table in it)."""


def _asset_path_of(asset) -> str | Path:
    """The path held by an assets row (dict, pandas Series, namedtuple) or the path itself."""
    if isinstance(asset, (str, os.PathLike)):
        return asset
    if isinstance(asset, (Mapping, pd.Series)):
        return asset["path"]
    if hasattr(asset, "path"):
        return asset.path
    raise TypeError(f"expected an assets row or a path, got {type(asset).__name__}")


def load_file(path: str | Path):
    """Load a file by extension: EXR -> float32 array, PNG -> array (stored dtype), JSON -> object.

    Raises:
        ValueError: an extension there is no loader for.
        FileNotFoundError: the file does not exist.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    if suffix == ".exr":
        from pipeline.codecs.exr import read_exr

        return read_exr(path)
    if suffix == ".png":
        from pipeline.codecs.image import read_png

        return read_png(path)
    if suffix == ".json":
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    raise ValueError(f"{path}: no loader for {suffix or 'files without extension'!s} "
                     "(EXR, PNG and JSON load; use Release.path() for others)")


class Release:
    """A dataset release opened read-only. Tables are read on first access and cached.

    Use :func:`open_release` to make one.
    """

    def __init__(self, root: str | Path):
        root = Path(root)
        if not root.is_dir():
            raise ReleaseError(f"{root}: release folder not found")
        mdir = root / MANIFEST_DIR
        present = [n for n in TABLE_SPECS if (mdir / f"{n}.parquet").is_file()]
        if not present:
            raise ReleaseError(f"{root}: not a release: no manifests (expected "
                               f"{MANIFEST_DIR}/{{{','.join(TABLE_SPECS)}}}.parquet)")
        self.root = root
        self._tables: dict[str, pa.Table] = {}
        self._frames: dict[str, pd.DataFrame] = {}

    def __repr__(self) -> str:
        return f"Release({str(self.root)!r})"

    # -- tables ------------------------------------------------------------------------------------

    def has_table(self, name: str) -> bool:
        """Whether the release has the Parquet file of ``name``."""
        return manifest_path(self.root, name).is_file()

    def table(self, name: str) -> pa.Table:
        """A manifest as a pyarrow Table (an empty one with the schema when the release lacks it).

        Raises:
            ValueError: an unknown table name.
        """
        if name not in self._tables:
            table = read_manifest(self.root, name)  # validates the name
            if table is None:
                spec = TABLE_SPECS[name]
                table = spec.schema().empty_table()
            self._tables[name] = table
        return self._tables[name]

    def dataframe(self, name: str) -> pd.DataFrame:
        """A manifest as a pandas DataFrame (cached; copy it before modifying)."""
        if name not in self._frames:
            self._frames[name] = self.table(name).to_pandas()
        return self._frames[name]

    @property
    def actions(self) -> pd.DataFrame:
        """One row per action: status, error, map size, stage counts (see manifests.schemas.ACTIONS)."""
        return self.dataframe("actions")

    @property
    def frames(self) -> pd.DataFrame:
        """One row per raw frame: path, bytes, sha256, exposure, size, status."""
        return self.dataframe("frames")

    @property
    def assets(self) -> pd.DataFrame:
        """One row per release file: action, camera, kind, path, bytes, sha256, media type."""
        return self.dataframe("assets")

    @property
    def metrics(self) -> pd.DataFrame:
        """Measured numbers of the actions in long format: action, camera (view), metric, region, environment
        (None where they do not apply), value, unit, source, run. Release-wide numbers: :attr:`metrics_summary`."""
        return self.dataframe("metrics")

    @property
    def metrics_summary(self) -> pd.DataFrame:
        """Release-wide aggregates of the latest evaluation: metric, value, unit, aggregation, n_actions."""
        return self.dataframe("metrics_summary")

    @property
    def stage_runs(self) -> pd.DataFrame:
        """One row per stage task per run: status, seconds, cache key, config."""
        return self.dataframe("stage_runs")

    @property
    def action_ids(self) -> list[str]:
        """Sorted action ids: those of the actions table, else those the assets mention."""
        ids = self.table("actions").column("action_id").to_pylist()
        if not ids:
            ids = [a for a in self.table("assets").column("action_id").to_pylist() if a is not None]
        return sorted(set(ids))

    # -- assets ------------------------------------------------------------------------------------

    def path(self, asset) -> Path:
        """Path on disk of an asset (an assets row, or a path relative to the release root).

        Raises:
            ValueError: the path lies outside the release.
        """
        rel = release_relpath(self.root, _asset_path_of(asset))
        return self.root / rel

    def load(self, asset):
        """Load an asset now, by extension: EXR -> float32 (H, W[, C]), PNG -> array, JSON -> dict.

        Args:
            asset: an assets row (dict, pandas Series or itertuples row with ``path``) or a path
                relative to the release root (or absolute, inside it).
        """
        return load_file(self.path(asset))

    def action(self, action_id: str) -> ActionView:
        """The assets of one action, loaded on demand.

        Raises:
            KeyError: no action with that id in the release.
        """
        if action_id not in self.action_ids and not self._assets_mention(action_id):
            raise KeyError(f"action {action_id!r} is not in the release {self.root} "
                           f"(actions: {', '.join(self.action_ids[:10]) or 'none'})")
        return ActionView(self, action_id)

    # -- the relighting set --------------------------------------------------------------------------

    @property
    def relight_examples(self) -> pd.DataFrame:
        """The single-image relighting set: one row per example (see manifests.schemas.RELIGHT_EXAMPLES)."""
        return self.dataframe("relight_examples")

    def relight_split(self, split: str) -> pd.DataFrame:
        """The examples of one split ('train', 'validation', 'test'), sorted by example id.

        Raises:
            ValueError: an unknown split name.
        """
        from manifests.schemas import SPLITS

        if split not in SPLITS:
            raise ValueError(f"unknown split {split!r}; splits are {', '.join(SPLITS)}")
        frame = self.relight_examples
        return frame[frame["split"] == split].sort_values("example_id").reset_index(drop=True)

    def relight_example(self, example) -> dict:
        """Load one example's maps now: ``image`` (H, W, 3) linear, premultiplied by ``alpha`` (H, W),
        ``albedo`` (H, W, 3) linear, ``normal`` (H, W, 3) camera frame (OpenCV axes), ``mask`` (H, W) bool.

        Args:
            example: a row of :attr:`relight_examples` (dict or pandas Series) or an example id.
        """
        if isinstance(example, str):
            frame = self.relight_examples
            rows = frame[frame["example_id"] == example]
            if rows.empty:
                raise KeyError(f"no relighting example {example!r} in {self.root}")
            example = rows.iloc[0]
        from pipeline.codecs.image import mask_from_png

        image = self.load(example["image_exr"])
        return {"image": image[..., :3], "alpha": image[..., 3] if image.shape[-1] > 3 else None,
                "albedo": self.load(example["albedo_exr"])[..., :3],
                "normal": self.load(example["normal_exr"])[..., :3],
                "mask": mask_from_png(self.load(example["mask_png"]))}

    def _assets_mention(self, action_id: str) -> bool:
        return bool(pc.any(pc.equal(self.table("assets").column("action_id"), action_id)).as_py())


_RENDER_KINDS = ("render_", "relit_")  # assets of novel views, not of captured cameras
_PAGE_KINDS = ("page", "page_thumbnail")  # the release page's files: pictures of the assets, not assets of a view


class ActionView:
    """The assets of one action. Nothing is read until a method is called."""

    def __init__(self, release: Release, action_id: str):
        self.release = release
        self.action_id = action_id
        assets = release.table("assets")
        rows = assets.filter(pc.equal(assets.column("action_id"), action_id)).to_pylist()
        self._rows = rows
        self._index: dict[tuple[str, str | None], dict] = {(r["kind"], r["camera_id"]): r for r in rows}
        self._artifacts = None

    def __repr__(self) -> str:
        return f"ActionView({self.action_id!r}, {len(self.cameras)} cameras, {len(self._rows)} assets)"

    @property
    def assets(self) -> pd.DataFrame:
        """This action's rows of the assets table."""
        df = self.release.assets
        return df[df["action_id"] == self.action_id].reset_index(drop=True)

    @property
    def info(self) -> dict:
        """This action's row of the actions table (empty when the table lacks it)."""
        for row in self.release.table("actions").to_pylist():
            if row["action_id"] == self.action_id:
                return row
        return {}

    @property
    def cameras(self) -> list[str]:
        """Sorted ids of the captured cameras this action has per-camera assets for (novel views of
        ``renders/`` are in :attr:`render_views`)."""
        return sorted({cam for (kind, cam) in self._index
                       if cam is not None and not kind.startswith(_RENDER_KINDS) and kind not in _PAGE_KINDS})

    @property
    def render_views(self) -> list[str]:
        """Sorted ids of the novel views in ``renders/`` (``N000``...)."""
        return sorted({cam for (kind, cam) in self._index if cam is not None and kind.startswith(_RENDER_KINDS)})

    @property
    def kinds(self) -> list[str]:
        """Sorted asset kinds this action has."""
        return sorted({kind for (kind, _) in self._index})

    def asset(self, kind: str, cam: str | None = None) -> dict:
        """The assets row of (kind, camera); KeyError naming action, camera and kind when absent."""
        try:
            return self._index[(kind, cam)]
        except KeyError:
            what = f"camera {cam}" if cam is not None else "the action (no camera)"
            raise KeyError(f"action {self.action_id}, {what}: no {kind!r} asset in the release "
                           f"(kinds present: {', '.join(self.kinds) or 'none'})") from None

    def path(self, kind: str, cam: str | None = None) -> Path:
        """Path of the (kind, camera) asset."""
        return self.release.path(self.asset(kind, cam))

    @property
    def artifacts(self):
        """This action through the artifact facade (:class:`artifacts.facade.ActionArtifacts` over the release,
        :class:`artifacts.facade.ReleaseBackend`): the typed readers below read through it, and
        ``stages.relightable.load_relightable_asset(view.artifacts)`` gives the asset the renderer relights."""
        if self._artifacts is None:
            from artifacts.facade import ActionArtifacts, ReleaseBackend

            self._artifacts = ActionArtifacts(ReleaseBackend(self))
        return self._artifacts

    def normals(self, cam: str, diffuse: bool = False) -> np.ndarray:
        """(H, W, 3) float32 unit world normals (0 where undefined; see normal_alpha): eq. 1's gradient ratio,
        or with ``diffuse=True`` the normals with the specular reflection fitted out (``normal_diffuse``,
        closer to the true surface; KeyError when the release was made without them)."""
        return self.artifacts.exr("normal_diffuse" if diffuse else "normal_alpha", cam, ("R", "G", "B"))

    def normal_alpha(self, cam: str) -> np.ndarray:
        """(H, W) float32 validity alpha of the normals in [0, 1]."""
        return self.artifacts.exr("normal_alpha", cam, ("A",))

    def albedo(self, cam: str, diffuse: bool = False) -> np.ndarray:
        """(H, W, 3) float32 linear sRGB albedo from the white light (``full_on / white_reference``: it holds the
        white light's specular reflection and the stage's ambient occlusion), or with ``diffuse=True`` the same
        with the fitted specular reflection taken out (``albedo_diffuse``, closer to the diffuse albedo; KeyError
        when the release was made without it)."""
        return self.artifacts.exr("albedo_diffuse" if diffuse else "albedo", cam, ("R", "G", "B"))

    def mask(self, cam: str) -> np.ndarray:
        """(H, W) bool subject mask."""
        return self.artifacts.mask(cam)

    def image(self, illumination: str, cam: str) -> np.ndarray:
        """(H, W, 3) float32 decoded linear sRGB image under 'full_on', 'pos' or 'neg'.

        Raises:
            ValueError: an unknown illumination.
        """
        if illumination not in ILLUMINATIONS:
            raise ValueError(f"illumination {illumination!r}: expected one of {list(ILLUMINATIONS)}")
        return self.artifacts.exr(illumination, cam, ("R", "G", "B"))

    def transforms(self) -> dict:
        """The action's transforms.json: nerfstudio convention (``transform_matrix`` OpenGL camera-to-world,
        ``fl_x``..``cy`` with pixel centres at +0.5) and, per frame, the OpenCV ``K``, ``dist``,
        ``cam_from_world_opencv`` (3x4) and ``world_from_cam_opencv`` (4x4); CONVENTIONS.md."""
        return self.artifacts.json("transforms")

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The action's surface (``mesh/mesh.ply``): vertices (V, 3) float32 metres, world frame, and
        faces (F, 3) int32."""
        return self.artifacts.mesh()

    def texture(self, name: str) -> np.ndarray:
        """A baked texture of the UV atlas of ``mesh/textured.obj``: 'albedo' (T, T, 3), 'normal' (T, T, 3),
        'view_count' or 'confidence' (T, T), float32 (the materials' 'roughness', 'occlusion', 'diffuse_ratio',
        ... likewise), or 'albedo_preview', the albedo's sRGB PNG (T, T, 3) uint8; texel row 0 is v = 1 (OBJ
        convention). KeyError naming the kinds present for a texture the action lacks."""
        from artifacts.layout import RELEASE_KINDS

        if name == "albedo_preview":
            return self.artifacts.png("albedo_texture_png")
        product = f"{name}_texture"
        if product not in RELEASE_KINDS:
            self.asset(f"texture_{name}")  # KeyError naming the kinds present
            raise KeyError(f"action {self.action_id}: texture {name!r} is not a product of the artifact facade")
        data = self.artifacts.exr(product)
        single = ("view_count", "confidence", "roughness", "roughness_fit_rms", "occlusion")
        return data[..., 0] if name in single and data.ndim == 3 else data

    def render_cameras(self) -> list[dict]:
        """The novel cameras of ``renders/`` (camera_id ``N000``..., K, cam_from_world, width, height and the
        captured pair each lies between); empty when the action has no renders."""
        if "render_cameras" not in self.kinds:
            return []
        return self.artifacts.json("render_cameras")["cameras"]

    def relit(self, view: str, environment: str) -> np.ndarray:
        """A relit novel view, (H, W, 4) float32: linear radiance in the environment map's units,
        premultiplied by alpha, the share of each pixel the subject covers (alpha >= 0.5 is the mask,
        as ``render_gbuffer``'s). ``environment`` is the label in ``renders/environments.json`` (e.g.
        ``studio_small_03_1k``)."""
        return self.artifacts.exr("relit", view, environment=environment)

    def render_gbuffer(self, view: str) -> dict[str, np.ndarray]:
        """The G-buffer of a novel view: ``normal`` (H, W, 3), ``albedo`` (H, W, 3), ``roughness`` (H, W),
        ``mask`` (H, W) bool."""
        from pipeline.codecs.image import mask_from_png

        rough = self.artifacts.exr("render_roughness", view)
        return {"normal": self.artifacts.exr("render_normal", view), "albedo": self.artifacts.exr("render_albedo", view),
                "roughness": rough[..., 0] if rough.ndim == 3 else rough,
                "mask": mask_from_png(self.artifacts.png("render_mask", view))}


def open_release(path: str | Path) -> Release:
    """Open a release folder (one with ``manifests/*.parquet``).

    Raises:
        ReleaseError (a FileNotFoundError): the folder does not exist or holds no manifests.
    """
    return Release(path)


def release_artifacts(release: str | Path | Release, action_id: str):
    """One action of a release through the artifact facade (:class:`artifacts.facade.ActionArtifacts` over
    :class:`artifacts.facade.ReleaseBackend`): the folder or an opened :class:`Release`, and an action id.

    Raises:
        KeyError: no action with that id in the release.
        ReleaseError: the folder is not a release.
    """
    release = release if isinstance(release, Release) else Release(release)
    return release.action(action_id).artifacts


# ----------------------------------------------------------------------------------------------------
# verification


@dataclass
class VerifyReport:
    """Result of :func:`verify_release`: what was checked and every discrepancy found."""

    release: str
    """The release folder checked."""
    n_checked: int = 0
    """Number of assets rows checked (files found and re-hashed)."""
    missing: list[str] = field(default_factory=list)
    """Paths in the assets table with no file (or no assets table at all)."""
    mismatched: list[str] = field(default_factory=list)
    """'path: ...expected vs actual' for files whose size or SHA-256 differs from the assets table."""
    extra: list[str] = field(default_factory=list)
    """Files of the release that no manifest covers: not in the assets table, nor a manifest table in
    ``manifests/index.json``."""
    not_covered: list[str] = field(default_factory=list)
    """'path: why' for files that are not checked and are not an error: ``manifests/index.json``, the root of
    the check (it holds the digests of the tables, and the assets table the digests of every other file)."""

    @property
    def ok(self) -> bool:
        """True when nothing is missing, mismatched or extra."""
        return not (self.missing or self.mismatched or self.extra)

    def to_dict(self) -> dict:
        """Plain dict (with ``ok``) for JSON output."""
        return {"release": self.release, "ok": self.ok, "n_checked": self.n_checked,
                "missing": list(self.missing), "mismatched": list(self.mismatched), "extra": list(self.extra),
                "not_covered": list(self.not_covered)}

    def summary(self, limit: int = 20) -> str:
        """Human-readable report, listing at most ``limit`` entries per category."""
        head = (f"{self.release}: {'OK' if self.ok else 'FAILED'}: {self.n_checked} assets checked, "
                f"{len(self.missing)} missing, {len(self.mismatched)} mismatched, {len(self.extra)} extra")
        lines = [head]
        for title, items in (("missing", self.missing), ("mismatched", self.mismatched), ("extra", self.extra),
                             ("not covered", self.not_covered)):
            for item in items[:limit]:
                lines.append(f"  {title}: {item}")
            if len(items) > limit:
                lines.append(f"  ... and {len(items) - limit} more {title}")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()


def _check_asset(root: Path, rel: str, size: int, sha: str) -> tuple[str, str | None]:
    """('ok' | 'missing' | 'mismatched', detail) for one assets row."""
    try:
        full = root / release_relpath(root, rel)
    except ValueError as exc:
        return "missing", f"{rel}: {exc}"
    if not full.is_file():
        return "missing", rel
    actual_size = full.stat().st_size
    actual_sha = file_sha256(full)
    if actual_sha != sha:
        return "mismatched", (f"{rel}: sha256 expected {sha} actual {actual_sha} "
                              f"(bytes expected {size} actual {actual_size})")
    if actual_size != size:
        return "mismatched", f"{rel}: bytes expected {size} actual {actual_size} (sha256 matches)"
    return "ok", None


def verify_release(path: str | Path, workers: int | None = None) -> VerifyReport:
    """Re-hash every asset of a release against its assets table, every manifest table against
    ``manifests/index.json``, and look for files neither lists.

    Args:
        path: the release folder.
        workers: threads hashing files in parallel (default: up to 8, by CPU count).

    Returns:
        A :class:`VerifyReport`; ``report.ok`` is False when any asset or manifest table is missing or
        differs, a file of the release is listed nowhere, or the release has no assets table.

    Raises:
        ReleaseError: the folder does not exist or holds no manifests.
    """
    release = open_release(path)
    root = release.root
    report = VerifyReport(release=str(root))
    if not release.has_table("assets"):
        report.missing.append(f"{MANIFEST_DIR}/assets.parquet")
        assets = release.table("assets")
    else:
        assets = release.table("assets")
    rels = assets.column("path").to_pylist()
    sizes = assets.column("bytes").to_pylist()
    shas = assets.column("sha256").to_pylist()
    workers = workers or min(8, os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        results = list(pool.map(lambda args: _check_asset(root, *args), zip(rels, sizes, shas)))
    for (status, detail) in results:
        if status == "ok":
            report.n_checked += 1
        elif status == "missing":
            report.missing.append(detail)
        else:
            report.n_checked += 1
            report.mismatched.append(detail)
    listed = set(rels) | _check_manifest_index(root, report)
    index = f"{MANIFEST_DIR}/{INDEX_NAME}"
    for dirpath, _dirnames, filenames in os.walk(root):
        for fname in filenames:
            rel = (Path(dirpath) / fname).relative_to(root).as_posix()
            if rel == index:
                report.not_covered.append(f"{rel}: the index of the manifest tables' digests (the root of the check)")
            elif rel not in listed:
                report.extra.append(rel)
    report.extra.sort()
    report.missing = list(dict.fromkeys(report.missing))  # the assets table may be missing twice over
    return report


def _check_manifest_index(root: Path, report: VerifyReport) -> set[str]:
    """Check every table of ``manifests/index.json`` against its file (into ``report``); the paths it lists."""
    directory = root / MANIFEST_DIR
    try:
        index = read_index(directory)
    except ValueError as exc:
        report.mismatched.append(str(exc))
        return set()
    if not index:
        report.missing.append(f"{MANIFEST_DIR}/{INDEX_NAME}")
    listed = set()
    for name, entry in sorted(index.items()):
        rel = f"{MANIFEST_DIR}/{name}"
        listed.add(rel)
        status, detail = _check_asset(root, rel, int(entry["bytes"]), str(entry["sha256"]))
        if status == "missing":
            report.missing.append(detail)
        else:
            report.n_checked += 1
            if status == "mismatched":
                report.mismatched.append(detail)
    return listed
