"""Content hashing: canonical records for cache keys and file digests computed once at ingest."""
from __future__ import annotations

import hashlib
import json
import os
import threading
from pathlib import Path
from typing import Any


def canonical_json(record: Any) -> str:
    """Sorted, compact JSON: the same record always gives the same bytes."""
    return json.dumps(record, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def record_key(record: dict[str, Any]) -> str:
    """sha256 hex of the canonical record (DVC style: the key is a hash of an explicit sorted record)."""
    return hashlib.sha256(canonical_json(record).encode()).hexdigest()


def file_sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """sha256 hex of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(chunk):
            digest.update(block)
    return digest.hexdigest()


class DigestCache:
    """Raw-file digests computed once: re-hashed only when a file's size or mtime changes.

    Stored as one JSON file in the work folder, keyed by absolute path; this is how a second run over a
    capture of terabytes costs a ``stat`` per file instead of a full read.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._lock = threading.Lock()
        self._entries: dict[str, dict[str, Any]] = {}
        self._dirty = False
        if self.path.exists():
            try:
                self._entries = json.loads(self.path.read_text())
            except (OSError, json.JSONDecodeError):
                self._entries = {}
        self.hashed = 0
        self.reused = 0

    def digest(self, path: str | Path) -> dict[str, Any]:
        """``{"sha256", "bytes"}`` for a file; raises FileNotFoundError when it is missing."""
        path = Path(path).resolve()
        stat = path.stat()
        key = str(path)
        with self._lock:
            entry = self._entries.get(key)
            if entry and entry["bytes"] == stat.st_size and entry["mtime_ns"] == stat.st_mtime_ns:
                self.reused += 1
                return {"sha256": entry["sha256"], "bytes": entry["bytes"]}
        sha = file_sha256(path)
        with self._lock:
            self._entries[key] = {"sha256": sha, "bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns}
            self._dirty = True
            self.hashed += 1
        return {"sha256": sha, "bytes": stat.st_size}

    def save(self) -> None:
        if not self._dirty:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(self._entries, sort_keys=True))
        os.replace(tmp, self.path)
        self._dirty = False
