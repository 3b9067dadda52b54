"""Explicit Arrow schemas of the release manifests (``RELEASE/manifests/<table>.parquet``).

Every table is declared once here as a list of :class:`Column` specs; the Arrow schemas in
:data:`SCHEMAS` are built from them, with each column's description in the Arrow field metadata
(key ``description``) and the table's description, name and schema version in the schema metadata,
so a Parquet file explains itself to any reader (pyarrow, pandas, polars, DuckDB, Spark).

Each table also has a primary key (:data:`PRIMARY_KEYS`): no two rows of a table share it, rows are
stored sorted by it (so the same content always gives the same file), and :func:`manifests.append_rows`
upserts on it by default.

Conventions used by all tables: paths are relative posix paths (``a/b/c.exr``, never absolute, never
``..``); camera ids are 5-digit strings (``"00000"``); floats are finite (no NaN, no Inf); timestamps
are UTC.
"""
from __future__ import annotations

import functools
import re
from dataclasses import dataclass

import pyarrow as pa

SCHEMA_VERSION = "2"
"""Bumped whenever a column is added, removed or changes meaning. 2: metrics holds per-action rows only,
with environment and unit columns and NULL where a column does not apply; release-wide aggregates moved to
metrics_summary."""


ILLUMINATIONS = ("full_on", "pos", "neg")
CAMERA_ID_PATTERN = re.compile(r"^[0-9]{5}$")
#: Captured cameras ('00000') or, in the assets and metrics tables, the novel views of renders/ ('N000').
VIEW_ID_PATTERN = re.compile(r"^([0-9]{5}|N[0-9]{3})$")
SHA256_PATTERN = re.compile(r"^[0-9a-f]{64}$")
METRIC_UNITS = ("deg", "dB", "%", "mm", "px", "s", "count", "1")
"""Units of the metrics tables; '1' is dimensionless."""


@dataclass(frozen=True)
class Column:
    """One column of a manifest table."""

    name: str
    """Column name, snake_case."""
    type: pa.DataType
    """Arrow type of the column."""
    description: str
    """What the column holds, with its unit; copied into the Arrow field metadata."""
    nullable: bool = False
    """Whether the column may hold null (a row may also omit a nullable column)."""
    choices: tuple[str, ...] | None = None
    """For string columns: the only allowed values (None: any string)."""
    pattern: re.Pattern | None = None
    """For string columns: a regular expression every non-null value must match in full."""
    min_value: float | None = None
    """For numeric columns: the smallest allowed value."""
    relative_path: bool = False
    """For string columns: values are relative posix paths (no leading '/', no '..', no backslash)."""
    json: bool = False
    """For string columns: values are JSON documents."""

    def field(self) -> pa.Field:
        """The Arrow field, with the description (and allowed values) in its metadata."""
        meta = {"description": self.description}
        if self.choices is not None:
            meta["allowed_values"] = "|".join(self.choices)
        return pa.field(self.name, self.type, nullable=self.nullable, metadata=meta)


@dataclass(frozen=True)
class TableSpec:
    """A manifest table: its columns, primary key and description."""

    name: str
    description: str
    columns: tuple[Column, ...]
    primary_key: tuple[str, ...]

    def schema(self) -> pa.Schema:
        """The Arrow schema with table-level metadata."""
        return pa.schema(
            [c.field() for c in self.columns],
            metadata={
                "description": self.description,
                "ultrastage.table": self.name,
                "ultrastage.schema_version": SCHEMA_VERSION,
                "ultrastage.primary_key": ",".join(self.primary_key),
            },
        )

    def column(self, name: str) -> Column:
        for c in self.columns:
            if c.name == name:
                return c
        raise KeyError(f"table {self.name!r} has no column {name!r}")


_STR = pa.string()
_I32 = pa.int32()
_I64 = pa.int64()
_F64 = pa.float64()
_TS = pa.timestamp("us", tz="UTC")


def _action_id(nullable: bool = False, extra: str = "") -> Column:
    return Column("action_id", _STR, "Action id (one pose of one subject), as in capture.json." + extra,
                  nullable=nullable)


def _camera_id(nullable: bool = False, extra: str = "", novel: bool = False) -> Column:
    if novel:
        return Column("camera_id", _STR, "Camera id, a 5-digit string such as '00000', or a novel view of "
                      "renders/ such as 'N000'." + extra, nullable=nullable, pattern=VIEW_ID_PATTERN)
    return Column("camera_id", _STR, "Camera id, a 5-digit string such as '00000'." + extra,
                  nullable=nullable, pattern=CAMERA_ID_PATTERN)


ACTIONS = TableSpec(
    name="actions",
    description="One row per action of the capture: its outcome in this release and the size of its maps.",
    primary_key=("action_id",),
    columns=(
        _action_id(),
        Column("session_id", _STR, "Capture session the action belongs to (its calibration), as in capture.json."),
        Column("subject", _STR, "Subject of the action, as in capture.json (e.g. 'makehuman/young_lightskinned_female')."),
        Column("status", _STR, "'ok' when every stage of the action succeeded, else 'failed'.",
               choices=("ok", "failed")),
        Column("error", _STR, "Null when status is 'ok'; otherwise the file at fault and the reason "
               "('<path>: <reason>').", nullable=True),
        Column("n_cameras", _I32, "Number of cameras of the action.", min_value=0),
        Column("width", _I32, "Width in pixels of the action's maps (normal_alpha, albedo, mask, images); "
               "null when the action failed before it was known.", nullable=True, min_value=0),
        Column("height", _I32, "Height in pixels of the action's maps; null when the action failed before "
               "it was known.", nullable=True, min_value=0),
        Column("stages_run", _I32, "Number of stage tasks of this action that ran in the run that wrote "
               "this row.", min_value=0),
        Column("stages_cached", _I32, "Number of stage tasks of this action resolved from the cache "
               "(same cache key, not run again).", min_value=0),
        Column("seconds", _F64, "Wall-clock seconds spent on the action's stage tasks in that run.",
               min_value=0.0),
    ),
)

FRAMES = TableSpec(
    name="frames",
    description="One row per raw input frame (action x camera x illumination) with its content digest.",
    primary_key=("action_id", "camera_id", "illumination"),
    columns=(
        _action_id(),
        _camera_id(),
        Column("illumination", _STR, "Illumination of the frame: 'full_on' (all LEDs white), "
               "'pos' (gradient g+) or 'neg' (gradient g-).", choices=ILLUMINATIONS),
        Column("raw_path", _STR, "Path of the raw file relative to the capture root (posix, e.g. "
               "'actions/A0000/pos/00003.dng'); null when the frame is missing.",
               nullable=True, relative_path=True),
        Column("raw_bytes", _I64, "Size of the raw file in bytes; null when missing.", nullable=True,
               min_value=0),
        Column("raw_sha256", _STR, "SHA-256 of the raw file, lowercase hex; null when missing.",
               nullable=True, pattern=SHA256_PATTERN),
        Column("exposure_s", _F64, "Exposure time in seconds; null when unknown.", nullable=True,
               min_value=0.0),
        Column("width", _I32, "Width in pixels of the raw frame as decoded; null when unknown.",
               nullable=True, min_value=0),
        Column("height", _I32, "Height in pixels of the raw frame as decoded; null when unknown.",
               nullable=True, min_value=0),
        Column("status", _STR, "'ok' (decoded and usable), 'failed' (present but unusable: corrupt, "
               "wrong size, black, saturated) or 'missing' (no file).",
               choices=("ok", "failed", "missing")),
        Column("error", _STR, "Null when status is 'ok'; otherwise the file at fault and the reason.",
               nullable=True),
    ),
)

ASSETS = TableSpec(
    name="assets",
    description="One row per file of the release (maps, previews, transforms, meshes, ...) with its size "
                "and SHA-256, so the release can be verified (`ultrastage verify`) and loaded lazily.",
    primary_key=("path",),
    columns=(
        _action_id(nullable=True, extra=" Null for release-level assets."),
        _camera_id(nullable=True, novel=True, extra=" Null for assets that are not per camera (transforms.json, "
                   "previews of several cameras, release-level files)."),
        Column("kind", _STR, "What the file is: 'full_on', 'pos', 'neg' (decoded linear sRGB RGB "
               "half-float EXR), 'mask' (uint8 0/255 PNG), 'normal_alpha' (RGBA EXR: world normal xyz + "
               "validity alpha), 'normal_diffuse' (the same with the specular reflection fitted out), 'albedo' (RGB EXR), "
               "'albedo_diffuse' (the same less the fitted specular reflection), 'preview' (PNG), 'transforms' (JSON), ..."),
        Column("path", _STR, "Path of the file relative to the release root (posix).", relative_path=True),
        Column("bytes", _I64, "Size of the file in bytes.", min_value=0),
        Column("sha256", _STR, "SHA-256 of the file, lowercase hex.", pattern=SHA256_PATTERN),
        Column("media_type", _STR, "Media type from the file extension, e.g. 'image/x-exr', 'image/png', "
               "'application/json'."),
    ),
)

METRICS = TableSpec(
    name="metrics",
    description="Measured numbers of the actions (accuracy against ground truth, stage statistics), one "
                "measure per row in long format: a metric name means one quantity, so AVG(value) GROUP BY "
                "metric, unit averages like with like. Release-wide aggregates are in metrics_summary, never here.",
    primary_key=("action_id", "camera_id", "metric", "region", "environment", "source"),
    columns=(
        _action_id(extra=" Every row belongs to one action (release-wide numbers: metrics_summary)."),
        _camera_id(nullable=True, novel=True, extra=" Null for metrics over a whole action (its mesh, its "
                   "textures, its held-out views)."),
        Column("metric", _STR, "Metric name, e.g. 'normal_mean_deg', 'albedo_psnr_db', 'valid_fraction'; one "
               "name is one quantity measured one way (the held-out views against the simulator's maps are "
               "'heldout_normal_mean_deg_truth', not a region of 'heldout_normal_mean_deg'); a stage's own "
               "statistics are prefixed with the stage ('photometric_valid_fraction')."),
        Column("region", _STR, "Pixels or geometry the metric is taken over: 'valid' (alpha > 0.5 inside the "
               "true mask), 'all' (the subject's mask), 'mesh' (the action's mesh against the true surface), "
               "'textures' (the UV atlas seen from the true cameras), 'heldout' (the held-out cameras' pixels, "
               "the variant in the metric's name); "
               "null when it does not apply.", nullable=True),
        Column("environment", _STR, "Label of the environment map a relit view was lit by (as in "
               "renders/environments.json); null for every other metric.", nullable=True),
        Column("value", _F64, "The value (finite), in `unit`."),
        Column("unit", _STR, "Unit of the value: 'deg', 'dB', '%', 'mm', 'px', 's', 'count' or '1' "
               "(dimensionless: fractions, SSIM, IoU, roughness, RMSE of values in [0, 1]).", choices=METRIC_UNITS),
        Column("source", _STR, "What produced the number: 'evaluate' (against ground truth) or the stage whose "
               "own statistics it is ('decode', 'photometric', 'diffuse_normals', ...)."),
        Column("run_id", _STR, "Id of the run that measured it (`ultrastage run`'s, or the evaluation's own when "
               "`ultrastage evaluate` ran alone)."),
    ),
)

METRICS_SUMMARY = TableSpec(
    name="metrics_summary",
    description="Release-wide aggregates of the metrics (what `ultrastage evaluate` prints): one row per "
                "metric of the latest evaluation, kept apart from the per-action rows of metrics.",
    primary_key=("metric", "source"),
    columns=(
        Column("metric", _STR, "Metric name; where a per-action metric of the same name exists in metrics, this "
               "is its aggregate over the release."),
        Column("value", _F64, "The value (finite), in `unit`."),
        Column("unit", _STR, "Unit of the value (as in metrics.unit).", choices=METRIC_UNITS),
        Column("aggregation", _STR, "How the value was formed: 'pooled' (over every pixel of every action), "
               "'mean_over_views', 'mean_over_actions', 'mean_over_sessions' (camera calibration) or 'count'.",
               choices=("pooled", "mean_over_views", "mean_over_actions", "mean_over_sessions", "count")),
        Column("n_actions", _I32, "Number of published actions the value covers.", min_value=0),
        Column("source", _STR, "What produced the number, e.g. 'evaluate'."),
        Column("run_id", _STR, "Id of the run that measured it."),
    ),
)

STAGE_RUNS = TableSpec(
    name="stage_runs",
    description="One row per stage task per run: ran, resolved from cache, failed or skipped; accumulated "
                "over runs.",
    primary_key=("run_id", "stage", "scope_id"),
    columns=(
        Column("run_id", _STR, "Id of the run (one `ultrastage run` invocation)."),
        Column("stage", _STR, "Stage name."),
        Column("version", _STR, "Stage version (part of the cache key), as a string."),
        Column("scope", _STR, "'action' (one task per action) or 'session' (one per capture session).",
               choices=("action", "session")),
        Column("scope_id", _STR, "The action id or session id the task covered."),
        Column("cache_key", _STR, "Hash of the stage's canonical input record (name, version, scope id, "
               "output-changing config, upstream keys, raw input digests)."),
        Column("status", _STR, "'ran', 'cached' (same key found, not run), 'failed' or 'skipped' "
               "(not needed, or upstream failed).", choices=("ran", "cached", "failed", "skipped")),
        Column("seconds", _F64, "Wall-clock seconds of the task (0 when cached or skipped).", min_value=0.0),
        Column("error", _STR, "Null unless status is 'failed': the file at fault and the reason.",
               nullable=True),
        Column("started_at", _TS, "When the task started (UTC); null when it never started.", nullable=True),
        Column("config_json", _STR, "The stage's resolved config as a JSON object.", json=True),
    ),
)


SPLITS = ("train", "validation", "test")
EXAMPLE_ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


def _release_file(name: str, what: str, nullable: bool = False) -> Column:
    return Column(name, _STR, f"Path relative to the release root of {what}.", nullable=nullable, relative_path=True)


RELIGHT_EXAMPLES = TableSpec(
    name="relight_examples",
    description="The single-image relighting set: one row per example (one view of one action's relightable "
                "asset under one rotated environment map), with its files, camera, lighting and split. "
                "See CONVENTIONS.md, section 'Relighting set'.",
    primary_key=("example_id",),
    columns=(
        Column("example_id", _STR, "Example id, '<action_id>_<view index, 2+ digits>' (also its folder "
               "relight/<example_id>/).", pattern=EXAMPLE_ID_PATTERN),
        _action_id(),
        Column("subject", _STR, "Subject of the action (capture.json); splits never share a subject."),
        Column("session_id", _STR, "Capture session of the action."),
        Column("split", _STR, "'train', 'validation' or 'test', drawn per subject from the seed and the split "
               "ratios (a subject's examples are all in one split).", choices=SPLITS),
        Column("view_index", _I32, "Index of the view among the action's examples.", min_value=0),
        Column("width", _I32, "Image width in pixels.", min_value=1),
        Column("height", _I32, "Image height in pixels.", min_value=1),
        Column("fx", _F64, "Focal length along x in pixels (OpenCV pinhole, no distortion).", min_value=0.0),
        Column("fy", _F64, "Focal length along y in pixels.", min_value=0.0),
        Column("cx", _F64, "Principal point x in pixels (pixel centres at integer coordinates).", min_value=0.0),
        Column("cy", _F64, "Principal point y in pixels.", min_value=0.0),
        Column("cam_from_world_json", _STR, "The camera pose as a JSON 3 x 4 [R | t], OpenCV axes (x right, y down, "
               "z forward), metres: x_cam = R x_world + t. World normals are R^T n_cam.", json=True),
        Column("environment_name", _STR, "Name (file stem) of the environment map, or 'procedural:<kind>'."),
        Column("environment_file", _STR, "File name of the environment map as found (no folder); "
               "'' for a procedural one."),
        Column("environment_sha256", _STR, "SHA-256 of the environment map file (of the procedural map's float32 "
               "bytes for a procedural one).", pattern=SHA256_PATTERN),
        Column("environment_rotation_deg", _F64, "Rotation of the environment about the world's +y axis, degrees, "
               "counter-clockwise seen from above: world direction = R_y(angle) x map direction."),
        Column("sh_camera_json", _STR, "Order-2 real spherical harmonics of the rotated environment's radiance in the "
               "CAMERA frame (OpenCV axes), JSON 9 x 3 (rows l,m = 00, 1-1, 10, 11, 2-2, 2-1, 20, 21, 22; columns "
               "R, G, B), the Ramamoorthi-Hanrahan basis without the cosine-lobe factors: L(w) ~ sum c_i Y_i(w).",
               json=True),
        Column("sh_world_json", _STR, "The same 9 x 3 coefficients in the world frame (+y up).", json=True),
        _release_file("image_exr", "the relit image, linear RGBA half-float EXR, radiance in the environment map's "
                      "units premultiplied by alpha"),
        _release_file("image_png", "the relit image tone-mapped to 8-bit sRGB (x png_exposure, clipped, sRGB curve)"),
        _release_file("albedo_exr", "the albedo, linear RGB half-float EXR"),
        _release_file("albedo_png", "the albedo as 8-bit sRGB PNG"),
        _release_file("normal_exr", "the camera-frame normals (OpenCV axes), float RGB EXR, 0 off the mask"),
        _release_file("normal_png", "the camera-frame normals as 8-bit PNG, (n + 1) / 2, 0 off the mask"),
        _release_file("mask_png", "the mask, 8-bit PNG 0/255 (alpha >= 0.5)"),
        Column("png_exposure", _F64, "Factor applied to the linear image before the sRGB curve of image_png.",
               min_value=0.0),
        Column("mask_pixels", _I64, "Pixels in the mask.", min_value=0),
        Column("seed", _I64, "Seed of the set's draws (views, environments, rotations, splits).", min_value=0),
        Column("example_key", _STR, "Hash of everything the example is rendered from (asset keys, camera, environment "
               "digest, rotation, render settings): equal keys, equal files."),
    ),
)

BASELINE_METRICS = TableSpec(
    name="baseline_metrics",
    description="Test metrics of a single-image baseline (AlbedoNet or NormalNet, ultrastage.baselines) on a split of "
                "the relighting set, beside its checkpoint (not a release manifest): one value per row, per example "
                "and over the whole split, for the trained network and the trivial baselines on the same examples. "
                "All metrics are taken on the examples' masked pixels.",
    primary_key=("method", "split", "example_id", "metric"),
    columns=(
        Column("network", _STR, "The network the checkpoint trains: 'albedonet' or 'normalnet'.",
               choices=("albedonet", "normalnet")),
        Column("method", _STR, "What made the prediction: the network's name (the checkpoint), 'input_image' (the "
               "linearised sRGB input photo taken as the albedo) or 'constant_normal' (every normal (0, 0, -1), "
               "facing the camera)."),
        Column("split", _STR, "Split of the relighting set the metrics are taken on.", choices=SPLITS),
        Column("example_id", _STR, "Example the row is about; '*' for the value over the whole split (albedo: "
               "the mean of the examples' values; normals: over all the split's masked pixels pooled).",
               pattern=re.compile(r"^(\*|[A-Za-z0-9][A-Za-z0-9._-]*)$")),
        Column("metric", _STR, "Metric name. Albedo (linear, [0, 1]): 'albedo_psnr_raw_db', 'albedo_ssim_raw', "
               "'albedo_rmse_raw' compare the prediction as it is; 'albedo_psnr_scaled_db', 'albedo_ssim_scaled', "
               "'albedo_rmse_scaled' first multiply each channel by its least-squares scale against the truth "
               "(the field disagrees on scale alignment). Normals (camera frame): 'normal_mean_deg', "
               "'normal_median_deg', 'normal_under_11_25_pct', 'normal_under_22_5_pct', 'normal_under_30_pct'; "
               "'pixels' is the masked pixel count."),
        Column("value", _F64, "The value (finite)."),
        Column("step", _I64, "Training step of the checkpoint evaluated (0 for the trivial baselines).", min_value=0),
    ),
)

STANDALONE_SPECS: dict[str, TableSpec] = {t.name: t for t in (BASELINE_METRICS,)}
"""Tables written as single Parquet files outside a release's manifests/ folder (never looked for by
:class:`manifests.Release`), by name."""

TABLE_SPECS: dict[str, TableSpec] = {t.name: t for t in (ACTIONS, FRAMES, ASSETS, METRICS, METRICS_SUMMARY,
                                                            STAGE_RUNS, RELIGHT_EXAMPLES)}
"""Every manifest table by name."""

SCHEMAS: dict[str, pa.Schema] = {name: spec.schema() for name, spec in TABLE_SPECS.items()}
"""Arrow schema of every manifest table by name."""

PRIMARY_KEYS: dict[str, tuple[str, ...]] = {name: spec.primary_key for name, spec in TABLE_SPECS.items()}
"""Primary-key columns of every manifest table by name."""

MEDIA_TYPES: dict[str, str] = {
    ".exr": "image/x-exr",
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".tif": "image/tiff",
    ".tiff": "image/tiff",
    ".json": "application/json",
    ".yaml": "application/yaml",
    ".yml": "application/yaml",
    ".parquet": "application/vnd.apache.parquet",
    ".ply": "application/ply",
    ".obj": "model/obj",
    ".glb": "model/gltf-binary",
    ".mtl": "model/mtl",
    ".txt": "text/plain",
    ".md": "text/markdown",
    ".csv": "text/csv",
    ".npy": "application/x-npy",
    ".npz": "application/x-npz",
}
"""Media type by lowercase file extension; anything else is 'application/octet-stream'."""


def media_type(path: str) -> str:
    """Media type of a file from its extension ('application/octet-stream' when unknown)."""
    suffix = "." + path.rsplit(".", 1)[-1].lower() if "." in path.rsplit("/", 1)[-1] else ""
    return MEDIA_TYPES.get(suffix, "application/octet-stream")


_UNIT_SUFFIXES = (("_deg", "deg"), ("_db", "dB"), ("_pct", "%"), ("_mm", "mm"), ("_px", "px"), ("_s", "s"),
                  ("seconds", "s"), ("_faces", "count"), ("_pixels", "count"), ("_views", "count"),
                  ("_registered", "count"), ("actions_ok", "count"), ("actions_failed", "count"),
                  ("width", "px"), ("height", "px"))


@functools.lru_cache(maxsize=4096)  # asked once per metric row: a release has few names and many rows
def metric_unit(metric: str) -> str:
    """The unit of a metric from its name: the name ends with it ('_deg', '_db', '_pct', '_mm', '_px', '_s' or
    'seconds'), or counts things ('_faces', '_pixels', '_views', ...); anything else is dimensionless ('1':
    fractions, SSIM, IoU, roughness). A unit suffix may be followed by a variant ('normal_mean_deg_diffuse',
    'heldout_albedo_psnr_db_truth')."""
    parts = metric.split("_")
    for end in range(len(parts), 0, -1):  # the unit suffix nearest the end wins: 'x_mm_truth' is mm
        head = "_".join(parts[:end])
        for suffix, unit in _UNIT_SUFFIXES:
            if head.endswith(suffix):
                return unit
    return "1"


def spec(name: str) -> TableSpec:
    """The spec of a manifest table or a standalone table (:data:`STANDALONE_SPECS`); ValueError naming the
    known tables for an unknown name."""
    found = TABLE_SPECS.get(name) or STANDALONE_SPECS.get(name)
    if found is None:
        raise ValueError(f"unknown manifest table {name!r}; known tables: "
                         f"{', '.join([*TABLE_SPECS, *STANDALONE_SPECS])}")
    return found
