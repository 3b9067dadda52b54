"""Writing the release manifests: validated rows in, atomically replaced Parquet files out.

Every write validates the rows against the table's schema (:mod:`manifests.schemas`) before anything
touches the disk, writes a temporary file in ``RELEASE/manifests/`` and renames it into place, so a
reader never sees half a table and a crash leaves the previous table intact. Rows are stored sorted by
the table's primary key, so the same content always gives the same file.

Writers in one release are serialised with an advisory lock on the ``manifests/`` folder (POSIX
``flock``), so :func:`append_rows` from two processes of one machine does not lose rows. Prefer writing
manifests from the driver process anyway.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import uuid
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path, PurePosixPath

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from manifests.schemas import Column, TableSpec, media_type, spec
from pipeline.hashing import file_sha256  # one implementation; re-exported by manifests

MANIFEST_DIR = "manifests"
"""Folder of the manifests inside a release."""
INDEX_NAME = "index.json"
"""``RELEASE/manifests/index.json``: bytes and SHA-256 of every manifest table, rewritten with each table (the
assets table cannot list itself; ``ultrastage verify`` checks the tables against this index)."""

_INT_RANGES = {pa.int32(): (-(2**31), 2**31 - 1), pa.int64(): (-(2**63), 2**63 - 1)}

# Status values after which `error` must be null, and those for which it must be given.
_STATUS_RULES: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "actions": (("ok",), ("failed",)),
    "frames": (("ok",), ("failed",)),
    "stage_runs": (("ran", "cached"), ("failed",)),
}


def manifest_path(release_dir: str | Path, name: str) -> Path:
    """Path of a table's Parquet file: ``RELEASE/manifests/<name>.parquet`` (release tables only)."""
    from manifests.schemas import TABLE_SPECS

    if name not in TABLE_SPECS:
        spec(name)  # the message naming the known tables for an unknown name
        raise ValueError(f"{name!r} is a standalone table, not a release manifest (write_standalone_table)")
    return Path(release_dir) / MANIFEST_DIR / f"{name}.parquet"


# ----------------------------------------------------------------------------------------------------
# validation


def _fail(table: str, index: int, column: str, reason: str) -> ValueError:
    return ValueError(f"{table} row {index}: column {column!r} {reason}")


def _check_value(table: str, index: int, col: Column, value):
    """The value converted for Arrow, or ValueError naming the table, row and column."""
    if value is None:
        if not col.nullable:
            raise _fail(table, index, col.name, "is null but required")
        return None
    t = col.type
    if pa.types.is_string(t):
        if not isinstance(value, str):
            raise _fail(table, index, col.name, f"must be a str, got {type(value).__name__} {value!r}")
        if col.choices is not None and value not in col.choices:
            raise _fail(table, index, col.name, f"is {value!r}, expected one of {list(col.choices)}")
        if col.pattern is not None and not col.pattern.fullmatch(value):
            raise _fail(table, index, col.name, f"is {value!r}, which does not match {col.pattern.pattern}")
        if col.relative_path:
            parts = PurePosixPath(value).parts
            if not value or value.startswith("/") or "\\" in value or ".." in parts or ":" in value.split("/")[0]:
                raise _fail(table, index, col.name, f"is {value!r}, expected a relative posix path")
        if col.json:
            try:
                json.loads(value)
            except ValueError as exc:
                raise _fail(table, index, col.name, f"is not valid JSON ({exc})") from None
        return value
    if pa.types.is_integer(t):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise _fail(table, index, col.name, f"must be an int, got {type(value).__name__} {value!r}")
        value = int(value)
        lo, hi = _INT_RANGES[t]
        if not lo <= value <= hi:
            raise _fail(table, index, col.name, f"is {value}, out of range for {t}")
    elif pa.types.is_floating(t):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise _fail(table, index, col.name, f"must be a number, got {type(value).__name__} {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise _fail(table, index, col.name, f"is {value} (NaN and Inf are not allowed)")
    elif pa.types.is_timestamp(t):
        if not isinstance(value, datetime):
            raise _fail(table, index, col.name, f"must be a datetime, got {type(value).__name__} {value!r}")
        if value.tzinfo is None or value.utcoffset() is None:
            raise _fail(table, index, col.name, f"is a naive datetime ({value}); give it a timezone (UTC)")
        return value.astimezone(timezone.utc)
    else:  # pragma: no cover - every schema type is handled above
        raise TypeError(f"unhandled Arrow type {t} of column {col.name}")
    if col.min_value is not None and value < col.min_value:
        raise _fail(table, index, col.name, f"is {value}, below the minimum {col.min_value}")
    return value


def _check_status(table: str, index: int, row: dict) -> None:
    rules = _STATUS_RULES.get(table)
    if rules is None:
        return
    no_error, needs_error = rules
    status, error = row.get("status"), row.get("error")
    if status in no_error and error is not None:
        raise _fail(table, index, "error", f"must be null when status is {status!r}, got {error!r}")
    if status in needs_error and not error:
        raise _fail(table, index, "error", f"must name the file and reason when status is {status!r}")


def _duplicates(table: str, keys: Sequence[str], columns: Mapping[str, Sequence]) -> None:
    counts = Counter(zip(*(columns[k] for k in keys)))
    dup = [k for k, n in counts.items() if n > 1]
    if dup:
        shown = ", ".join(str(dict(zip(keys, k))) for k in dup[:3])
        more = f" (and {len(dup) - 3} more)" if len(dup) > 3 else ""
        raise ValueError(f"{table}: duplicate key {tuple(keys)}: {shown}{more}")


def _table_duplicates(table_name: str, keys: Sequence[str], table: pa.Table) -> None:
    """:func:`_duplicates` over an Arrow table, counted by Arrow (null matches null): a release-size table's key
    columns are never turned into Python objects."""
    if table.num_rows < 2:
        return
    keys = list(keys)
    counts = table.select(keys).group_by(keys).aggregate([([], "count_all")])
    dup = counts.filter(pc.greater(counts["count_all"], 1))
    if dup.num_rows:
        shown = ", ".join(str(row) for row in dup.select(keys).slice(0, 3).to_pylist())
        more = f" (and {dup.num_rows - 3} more)" if dup.num_rows > 3 else ""
        raise ValueError(f"{table_name}: duplicate key {tuple(keys)}: {shown}{more}")


def concat_validated(name: str, tables: Sequence[pa.Table]) -> pa.Table:
    """One table of the tables :func:`validate_rows` made from parts of a table's rows (e.g. one action's at a
    time, so that a release-size table's rows are never all Python dicts at once), sorted by the primary key.

    Raises:
        ValueError: two rows of different parts share the primary key.
    """
    ts = spec(name)
    if not tables:
        return validate_rows(name, [])
    if len(tables) == 1:
        return tables[0]
    table = pa.concat_tables(tables)
    _table_duplicates(name, ts.primary_key, table)
    return _sorted(table, ts)


def _as_table(name: str, rows: Iterable[Mapping] | pa.Table) -> pa.Table:
    """``rows`` validated into a table (:func:`validate_rows`), or a table already validated with this table's
    schema (:func:`concat_validated`)."""
    if isinstance(rows, pa.Table):
        if not rows.schema.equals(spec(name).schema()):
            raise ValueError(f"{name}: a table with another schema than the manifest's")
        return rows
    return validate_rows(name, rows)


def _sorted(table: pa.Table, ts: TableSpec) -> pa.Table:
    if table.num_rows < 2:
        return table
    return table.sort_by([(k, "ascending") for k in ts.primary_key])


def validate_rows(name: str, rows: Iterable[Mapping]) -> pa.Table:
    """Validate rows (dicts keyed by column name) against a table's schema and build the Arrow table.

    Nullable columns may be omitted from a row (they become null). The result is sorted by the
    table's primary key.

    Raises:
        ValueError: unknown table; a row that is not a dict; an unknown column or a missing required
            one (named); a value of the wrong type, out of its allowed values, pattern or range; NaN or
            Inf in a float column; a naive timestamp; an inconsistent status/error pair; two rows with
            the same primary key.
    """
    ts = spec(name)
    rows = rows if isinstance(rows, list) else list(rows)
    try:
        columns = _fast_columns(name, ts, rows)
    except (_Slow, ValueError):  # the row-by-row check below converts the rest, or names the first error
        columns = _checked_columns(name, ts, rows)
    _duplicates(name, ts.primary_key, columns)
    schema = ts.schema()
    arrays = [pa.array(columns[c.name], type=c.type) for c in ts.columns]
    return _sorted(pa.Table.from_arrays(arrays, schema=schema), ts)


class _Slow(Exception):
    """A row or value that the column-wise check leaves to the row-by-row one."""


def _fast_columns(name: str, ts: TableSpec, rows: list) -> dict[str, list]:
    """The columns of ``rows`` when every row is a dict of known columns with the required ones and every value
    is of the column's plain Python type (str, int, float, None where nullable) and valid; raises
    :class:`_Slow` (or ValueError) otherwise, and :func:`_checked_columns` then says what is wrong. One pass per
    column without per-value calls: a release-size table has hundreds of thousands of rows."""
    known_set = {c.name for c in ts.columns}
    required = {c.name for c in ts.columns if not c.nullable}
    for row in rows:
        if not isinstance(row, Mapping) or not known_set.issuperset(row) or not required.issubset(row.keys()):
            raise _Slow
    columns: dict[str, list] = {}
    for col in ts.columns:
        values = [row.get(col.name) for row in rows]
        t, nullable = col.type, col.nullable
        if col.relative_path or col.json or pa.types.is_timestamp(t):
            values = [_check_value(name, i, col, v) for i, v in enumerate(values)]
        elif pa.types.is_string(t):
            choices, pattern = col.choices, col.pattern
            for v in values:
                if type(v) is not str:
                    if v is None and nullable:
                        continue
                    raise _Slow
                if (choices is not None and v not in choices) or (pattern is not None and not pattern.fullmatch(v)):
                    raise _Slow
        elif pa.types.is_integer(t):
            lo, hi = _INT_RANGES[t]
            if col.min_value is not None:
                lo = max(lo, math.ceil(col.min_value))
            for v in values:
                if type(v) is not int or not lo <= v <= hi:
                    if v is None and nullable:
                        continue
                    raise _Slow
        elif pa.types.is_floating(t):
            low = -math.inf if col.min_value is None else col.min_value
            isfinite = math.isfinite
            out = []
            for v in values:
                if type(v) is not float:
                    if v is None and nullable:
                        out.append(None)
                        continue
                    if type(v) is not int:
                        raise _Slow
                    v = float(v)
                if not isfinite(v) or v < low:
                    raise _Slow
                out.append(v)
            values = out
        else:
            raise _Slow
        columns[col.name] = values
    if name in _STATUS_RULES:
        for index, row in enumerate(rows):
            _check_status(name, index, row)
    return columns


def _checked_columns(name: str, ts: TableSpec, rows: list) -> dict[str, list]:
    """The columns of ``rows``, each value checked and converted in row order: the first error is named."""
    known = [c.name for c in ts.columns]
    known_set = set(known)
    columns: dict[str, list] = {c: [] for c in known}
    for index, row in enumerate(rows):
        if not isinstance(row, Mapping):
            raise ValueError(f"{name} row {index}: expected a dict of column -> value, got {type(row).__name__}")
        unknown = [k for k in row if k not in known_set]
        if unknown:
            raise ValueError(f"{name} row {index}: unknown column {unknown[0]!r} "
                             f"(table {name} has columns {known})")
        for col in ts.columns:
            if col.name not in row and not col.nullable:
                raise ValueError(f"{name} row {index}: missing required column {col.name!r}")
            columns[col.name].append(_check_value(name, index, col, row.get(col.name)))
        _check_status(name, index, row)
    return columns


# ----------------------------------------------------------------------------------------------------
# reading (shared with the consumer)


def conform(table: pa.Table, name: str, source: str | Path = "") -> pa.Table:
    """Cast a table read from disk to the current schema of ``name``.

    Columns the file lacks become null when nullable; columns the schema does not know are kept after
    the known ones (forward compatibility).

    Raises:
        ValueError: a required column is missing or cannot be cast (naming the file and column).
    """
    ts = spec(name)
    where = f"{source}: " if source else f"{name}: "
    arrays, fields = [], []
    for col in ts.columns:
        if col.name in table.column_names:
            try:
                arrays.append(table.column(col.name).cast(col.type))
            except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
                raise ValueError(f"{where}column {col.name!r} cannot be read as {col.type}: {exc}") from None
        elif col.nullable:
            arrays.append(pa.nulls(table.num_rows, col.type))
        else:
            raise ValueError(f"{where}required column {col.name!r} is missing")
        fields.append(col.field())
    for extra in table.schema:
        if extra.name not in {c.name for c in ts.columns}:
            arrays.append(table.column(extra.name))
            fields.append(extra)
    schema = pa.schema(fields, metadata=ts.schema().metadata)
    return pa.Table.from_arrays(arrays, schema=schema)


def upgrade_metrics_v1(table: pa.Table) -> pa.Table:
    """A metrics table of schema version 1 in the current layout: release-wide rows (null action) dropped
    (they belong in metrics_summary, which the next evaluation writes), '' regions null, a relit view's
    environment moved from ``region`` to ``environment``, held-out variants named as their own metrics
    (``heldout_normal_mean_deg`` of region 'heldout_truth' -> ``heldout_normal_mean_deg_truth``, region
    'heldout') and the unit derived from the metric name."""
    from manifests.schemas import metric_unit

    heldout = {"heldout": "", "heldout_truth": "_truth", "heldout_diffuse": "_diffuse",
               "heldout_truth_diffuse": "_diffuse_truth"}
    rows = []
    for row in table.to_pylist():
        if row.get("action_id") is None:
            continue
        metric, region, environment = row["metric"], row.get("region") or None, None
        if metric == "relit_psnr_db" and region is not None:
            region, environment = "all", region
        elif region in heldout:
            metric, region = metric + heldout[region], "heldout"
        rows.append({"action_id": row["action_id"], "camera_id": row.get("camera_id"), "metric": metric,
                     "region": region, "environment": environment, "value": row["value"],
                     "unit": metric_unit(metric), "source": row["source"], "run_id": row["run_id"]})
    return validate_rows("metrics", rows)


def read_manifest(release_dir: str | Path, name: str) -> pa.Table | None:
    """The table ``RELEASE/manifests/<name>.parquet`` in the current schema, or None when absent (a metrics
    table of schema version 1 is upgraded on reading: :func:`upgrade_metrics_v1`)."""
    path = manifest_path(release_dir, name)
    if not path.is_file():
        return None
    table = pq.read_table(path)
    if name == "metrics" and "unit" not in table.column_names:
        return upgrade_metrics_v1(table)
    return conform(table, name, path)


# ----------------------------------------------------------------------------------------------------
# writing


@contextlib.contextmanager
def _locked(directory: Path) -> Iterator[None]:
    """Advisory exclusive lock on a folder (POSIX flock on the folder itself; no lock file left behind)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    fd = os.open(directory, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def _write_atomic(directory: Path, name: str, table: pa.Table) -> Path:
    dest = directory / f"{name}.parquet"
    tmp = directory / f".{name}.parquet.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
    try:
        with open(tmp, "wb") as fh:
            pq.write_table(table, fh, compression="zstd")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, dest)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _update_index(directory)
    with contextlib.suppress(OSError):  # make the rename durable where the platform allows it
        dfd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    return dest


def read_index(directory: Path) -> dict[str, dict]:
    """The ``tables`` of ``manifests/index.json`` (file name -> {bytes, sha256}); empty when absent.

    Raises:
        ValueError: the index is not valid JSON (naming the file).
    """
    path = Path(directory) / INDEX_NAME
    if not path.is_file():
        return {}
    try:
        return dict(json.loads(path.read_text())["tables"])
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a manifest index ({exc})") from None


def _update_index(directory: Path) -> None:
    """Rewrite ``index.json`` with the digest of every ``*.parquet`` of the folder (called under the lock)."""
    tables = {p.name: {"bytes": p.stat().st_size, "sha256": file_sha256(p)}
              for p in sorted(directory.glob("*.parquet"))}
    from manifests.schemas import SCHEMA_VERSION

    text = json.dumps({"schema_version": SCHEMA_VERSION, "tables": tables}, indent=1, sort_keys=True) + "\n"
    tmp = directory / f".{INDEX_NAME}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
    tmp.write_text(text)
    os.replace(tmp, directory / INDEX_NAME)


def replace_rows(release_dir: str | Path, name: str, rows: Iterable[Mapping] | pa.Table,
                 drop: Callable[[dict], bool]) -> Path:
    """Write a table as its existing rows for which ``drop(row)`` is false plus ``rows``, atomically, under the
    release's manifest lock: a writer replaces the rows it owns (e.g. every 'evaluate' row) without leaving
    stale ones behind or touching the others'. ``rows``: dicts, or a table :func:`concat_validated` made.

    Raises:
        ValueError: invalid rows (:func:`validate_rows`) or a kept row sharing the primary key with a new one.
    """
    ts = spec(name)
    new = _as_table(name, rows if isinstance(rows, pa.Table) else list(rows))
    directory = Path(release_dir) / MANIFEST_DIR
    directory.mkdir(parents=True, exist_ok=True)
    with _locked(directory):
        old = read_manifest(release_dir, name)
        table = new
        if old is not None and old.num_rows:
            # row dicts a batch at a time: the whole metrics table as dicts is ~1 KiB a row at release size
            keep = [not drop(r) for batch in old.to_batches(max_chunksize=1 << 14) for r in batch.to_pylist()]
            kept = old.filter(pa.array(keep, type=pa.bool_()))
            if kept.num_rows:
                kept = kept.select([c.name for c in ts.columns]).cast(new.schema)
                table = _sorted(pa.concat_tables([kept, new]), ts)
                _table_duplicates(name, ts.primary_key, table)
        return _write_atomic(directory, name, table)


def write_table(release_dir: str | Path, name: str, rows: Iterable[Mapping]) -> Path:
    """Validate ``rows`` and write them as ``RELEASE/manifests/<name>.parquet``, replacing the table.

    The file is written under a temporary name in the same folder and renamed into place (atomic).
    No rows give an empty table with the full schema.

    Returns:
        The path of the Parquet file.

    Raises:
        ValueError: see :func:`validate_rows`; nothing is written then.
    """
    return write_table_keeping(release_dir, name, rows, keep_actions=())


def write_table_keeping(release_dir: str | Path, name: str, rows: Iterable[Mapping] | pa.Table,
                        keep_actions: Iterable[str]) -> Path:
    """:func:`write_table`, but the existing rows of the actions in ``keep_actions`` stay: a run over some
    actions of a release replaces their rows (and the rows of no action) and leaves the other actions'.
    ``rows``: dicts, or a table :func:`concat_validated` made.

    Raises:
        ValueError: see :func:`validate_rows`, or a kept row sharing the primary key with a new one.
    """
    manifest_path(release_dir, name)  # a release table (not a standalone one)
    ts = spec(name)
    table = _as_table(name, rows)
    keep = set(keep_actions)
    directory = Path(release_dir) / MANIFEST_DIR
    directory.mkdir(parents=True, exist_ok=True)
    with _locked(directory):
        old = read_manifest(release_dir, name) if keep else None
        if old is not None and old.num_rows:
            kept = old.filter(pa.array([a in keep for a in old.column("action_id").to_pylist()], type=pa.bool_()))
            if kept.num_rows:
                kept = kept.select([c.name for c in ts.columns]).cast(table.schema)
                table = _sorted(pa.concat_tables([kept, table]), ts)
                _table_duplicates(name, ts.primary_key, table)
        return _write_atomic(directory, name, table)


def write_standalone_table(path: str | Path, name: str, rows: Iterable[Mapping]) -> Path:
    """Validate ``rows`` against a standalone table's schema (:data:`manifests.schemas.STANDALONE_SPECS`, e.g.
    ``baseline_metrics``) and write them as the single Parquet file ``path`` (outside any release), replacing
    it atomically (temporary file in the same folder, then rename).

    Raises:
        ValueError: a name that is not a standalone table, or see :func:`validate_rows`; nothing is written then.
    """
    from manifests.schemas import STANDALONE_SPECS

    if name not in STANDALONE_SPECS:
        raise ValueError(f"{name!r} is not a standalone table; standalone tables: {', '.join(STANDALONE_SPECS)}")
    path = Path(path)
    table = validate_rows(name, rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    stem = path.name[: -len(".parquet")] if path.name.endswith(".parquet") else path.name
    written = _write_atomic(path.parent, stem, table)
    if written != path:  # _write_atomic names the file <stem>.parquet
        os.replace(written, path)
    return path


def read_standalone_table(path: str | Path, name: str) -> pa.Table:
    """A standalone table's Parquet file read in the current schema of ``name``.

    Raises:
        FileNotFoundError: no such file. ValueError: a required column missing or of the wrong type.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    return conform(pq.read_table(path), name, path)


def append_rows(release_dir: str | Path, name: str, rows: Iterable[Mapping],
                key_columns: Sequence[str] | None = None) -> Path:
    """Upsert ``rows`` into a table: existing rows whose ``key_columns`` equal a new row's are replaced.

    Reads the existing table (if any), drops the rows matched by the new ones, adds the new rows and
    writes the result atomically, under the release's manifest lock. Null key values match null.

    Args:
        key_columns: columns that identify a row; default the table's primary key
            (:data:`manifests.schemas.PRIMARY_KEYS`), e.g. ``(action_id, camera_id, metric, region,
            source)`` for metrics and ``(run_id, stage, scope_id)`` for stage_runs.

    Raises:
        ValueError: an unknown key column, invalid rows (:func:`validate_rows`), new rows sharing a key,
            or a result in which two rows share the primary key.
    """
    ts = spec(name)
    keys = tuple(key_columns) if key_columns is not None else ts.primary_key
    if not keys:
        raise ValueError(f"{name}: key_columns must name at least one column")
    known = {c.name for c in ts.columns}
    for k in keys:
        if k not in known:
            raise ValueError(f"{name}: unknown key column {k!r}")
    rows = list(rows)
    new = validate_rows(name, rows)
    new_keys_list = list(zip(*(new.column(k).to_pylist() for k in keys)))
    _duplicates(name, keys, {k: new.column(k).to_pylist() for k in keys})
    directory = Path(release_dir) / MANIFEST_DIR
    directory.mkdir(parents=True, exist_ok=True)
    with _locked(directory):
        old = read_manifest(release_dir, name)
        if old is None or old.num_rows == 0:
            combined = new
        else:
            new_keys = set(new_keys_list)
            old_keys = zip(*(old.column(k).to_pylist() for k in keys))
            kept = old.filter(pa.array([k not in new_keys for k in old_keys], type=pa.bool_()))
            kept = kept.select([c.name for c in ts.columns]).cast(new.schema)
            combined = pa.concat_tables([kept, new])
            _duplicates(name, ts.primary_key, {k: combined.column(k).to_pylist() for k in ts.primary_key})
        return _write_atomic(directory, name, _sorted(combined, ts))


# ----------------------------------------------------------------------------------------------------
# asset rows


def release_relpath(release_dir: str | Path, path: str | Path) -> str:
    """``path`` (absolute, or relative to the release root) as a posix path relative to the release root.

    Raises:
        ValueError: the path lies outside the release.
    """
    root = Path(os.path.abspath(release_dir))
    p = Path(path)
    full = Path(os.path.abspath(p if p.is_absolute() else root / p))
    try:
        rel = full.relative_to(root)
    except ValueError:
        try:  # the same places spelled through symlinks (e.g. /tmp vs /private/tmp)
            rel = Path(os.path.realpath(full)).relative_to(os.path.realpath(root))
        except ValueError:
            raise ValueError(f"{path}: not inside the release {release_dir}") from None
    if rel == Path("."):
        raise ValueError(f"{path}: is the release root, not a file in it")
    return rel.as_posix()


def asset_row(release_dir: str | Path, path: str | Path, kind: str,
              action_id: str | None = None, camera_id: str | None = None, digest: dict | None = None) -> dict:
    """The ``assets`` row of a file of the release: relative path, bytes, sha256 and media type.

    Args:
        release_dir: the release root.
        path: the file, absolute or relative to the release root.
        kind: what the file is ('normal_alpha', 'mask', 'preview', 'transforms', ...).
        digest: ``{"bytes", "sha256"}`` of the file when the task that wrote it hashed it already; None: the
            file is read and hashed here.

    Raises:
        ValueError: the path lies outside the release.
        FileNotFoundError: the file does not exist.
    """
    rel = release_relpath(release_dir, path)
    full = Path(release_dir) / rel
    if not full.is_file():
        raise FileNotFoundError(f"{full}: asset file not found (kind {kind!r}, action {action_id}, "
                                f"camera {camera_id})")
    return {
        "action_id": action_id,
        "camera_id": camera_id,
        "kind": kind,
        "path": rel,
        "bytes": int(digest["bytes"]) if digest else full.stat().st_size,
        "sha256": digest["sha256"] if digest else file_sha256(full),
        "media_type": media_type(rel),
    }
