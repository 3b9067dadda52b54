"""``ultrastage run`` wired together: the engine's run (:func:`pipeline.runner.run_pipeline`) with the release
indexed by its Parquet manifests (:class:`manifests.catalog.ManifestCatalog`)."""
from __future__ import annotations

from typing import Any

from manifests.catalog import ManifestCatalog
from pipeline.runner import RunResult
from pipeline.runner import run_pipeline as run_engine


def run_pipeline(*args: Any, **kwargs: Any) -> RunResult:
    """:func:`pipeline.runner.run_pipeline` (same arguments) publishing through the manifests' catalog."""
    return run_engine(*args, catalog=ManifestCatalog(), **kwargs)
