"""The release manifests: the only code in the project that reads or writes Parquet.

- :mod:`manifests.schemas`: explicit Arrow schemas of the tables (actions, frames, assets, metrics,
  stage_runs), a description per column in the field metadata.
- :mod:`manifests.writer`: validated, atomic writes (:func:`write_table`, :func:`append_rows`) and
  asset rows (:func:`asset_row`, :func:`file_sha256`); standalone tables outside a release
  (:func:`write_standalone_table`, :func:`read_standalone_table`: a baseline's test metrics).
- :mod:`manifests.consumer`: :func:`open_release` (tables as Arrow/pandas, lazy asset loading),
  :func:`release_artifacts` (one action through the artifact facade, :mod:`artifacts.facade`) and
  :func:`verify_release` (re-hash every asset).
"""
from manifests.consumer import (ActionView, Release, ReleaseError, VerifyReport, open_release, release_artifacts,
                                verify_release)
from manifests.schemas import PRIMARY_KEYS, SCHEMAS, TABLE_SPECS
from manifests.writer import (append_rows, asset_row, file_sha256, read_manifest, read_standalone_table,
                              validate_rows, write_standalone_table, write_table)

__all__ = [
    "ActionView",
    "PRIMARY_KEYS",
    "Release",
    "ReleaseError",
    "SCHEMAS",
    "TABLE_SPECS",
    "VerifyReport",
    "append_rows",
    "asset_row",
    "file_sha256",
    "open_release",
    "read_manifest",
    "release_artifacts",
    "read_standalone_table",
    "validate_rows",
    "verify_release",
    "write_standalone_table",
    "write_table",
]
