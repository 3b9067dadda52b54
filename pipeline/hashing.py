"""Content hashing: canonical records for cache keys, file digests computed once at ingest, and digests of the
code a stage runs.

A stage's code digest covers its module and every module of the counted packages that it imports,
transitively, found by an AST scan of its ``import`` and ``from ... import`` statements (those inside
functions included), as DVC hashes a stage's code dependencies. Each module is hashed from its syntax tree
less docstrings: comments, blank lines, formatting and docstrings do not change a key; any change to what the
code does (a statement, a constant, a default) does. The tree is written out by Python's own ``ast.dump``, so
a new Python version may change every key once. The scan imports nothing, so the engine can hash the code of
packages it must not import; imports made by name at run time (``importlib.import_module``) are not seen.
"""
from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
import json
import os
import sys
import threading
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
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


def _sha256_or_none(path: str) -> str | None:
    try:
        return file_sha256(path)
    except OSError:
        return None


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
        self._real_dirs: dict[str, str] = {}

    def _resolved(self, path: str | Path) -> str:
        """``Path(path).resolve()`` as a string, with the folders' real paths remembered: a capture's frames
        share a few folders, so each file costs one ``lstat`` instead of one per path component. (A folder
        link changed while this cache lives is not seen; a cache lives for one run.)"""
        text = os.fspath(path)
        if not os.path.isabs(text):
            text = os.path.join(os.getcwd(), text)
        folder, name = os.path.split(text)
        if name in ("", ".", ".."):
            return os.path.realpath(text)
        real = self._real_dirs.get(folder)
        if real is None:
            real = self._real_dirs[folder] = os.path.realpath(folder)
        full = os.path.join(real, name)
        return os.path.realpath(full) if os.path.islink(full) else full

    def digest(self, path: str | Path) -> dict[str, Any]:
        """``{"sha256", "bytes"}`` for a file; raises FileNotFoundError when it is missing."""
        key = self._resolved(path)
        stat = os.stat(key)
        with self._lock:
            entry = self._entries.get(key)
            if entry and entry["bytes"] == stat.st_size and entry["mtime_ns"] == stat.st_mtime_ns:
                self.reused += 1
                return {"sha256": entry["sha256"], "bytes": entry["bytes"]}
        sha = file_sha256(key)
        with self._lock:
            self._entries[key] = {"sha256": sha, "bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns}
            self._dirty = True
            self.hashed += 1
        return {"sha256": sha, "bytes": stat.st_size}

    def digest_all(self, paths: Iterable[str | Path], threads: int = 0) -> int:
        """Hash, ``threads`` files at a time, every file of ``paths`` whose digest is not known for its current
        size and mtime; :meth:`digest` then finds them known. Returns how many files it hashed.

        sha256 and file reads release the GIL, so threads hash in parallel (up to the cores and the disk): a
        capture's new frames cost their bytes / (cores x sha256 rate) instead of / (one core's rate). A path
        that does not exist is left to :meth:`digest`, which names it. ``threads``: 0 = one per CPU core.
        """
        todo: dict[str, os.stat_result] = {}
        for path in paths:
            key = self._resolved(path)
            if key in todo:
                continue
            try:
                stat = os.stat(key)
            except OSError:
                continue
            entry = self._entries.get(key)
            if not (entry and entry["bytes"] == stat.st_size and entry["mtime_ns"] == stat.st_mtime_ns):
                todo[key] = stat
        if not todo:
            return 0
        workers = max(1, min(threads or os.cpu_count() or 1, len(todo)))
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="digest") as pool:
            shas = list(pool.map(_sha256_or_none, todo))
        hashed = 0
        with self._lock:
            for (key, stat), sha in zip(todo.items(), shas):
                if sha is not None:  # unreadable now: digest() raises for it where the plan names the task
                    self._entries[key] = {"sha256": sha, "bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns}
                    hashed += 1
            self._dirty = self._dirty or hashed > 0
            self.hashed += hashed
        return hashed

    def save(self) -> None:
        if not self._dirty:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(self._entries, sort_keys=True))
        os.replace(tmp, self.path)
        self._dirty = False


# --- code digests -----------------------------------------------------------------------------------

def _counts(module: str, packages: Iterable[str]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in packages)


def module_file(module: str) -> tuple[Path, bool] | None:
    """(source file, is a package) of a module, found without importing it; None when there is none.

    A module already imported is taken from ``sys.modules`` (the code this process runs); otherwise its
    top-level package is looked up on ``sys.path`` and the dotted path followed through its folders.
    """
    loaded = sys.modules.get(module)
    source = getattr(loaded, "__file__", None) if loaded is not None else None
    if source and source.endswith(".py"):
        return Path(source), Path(source).name == "__init__.py"
    top, *rest = module.split(".")
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        return None
    if spec is None:
        return None
    if not rest:
        if spec.submodule_search_locations:
            for folder in spec.submodule_search_locations:
                if (Path(folder) / "__init__.py").is_file():
                    return Path(folder) / "__init__.py", True
            return None
        return (Path(spec.origin), False) if spec.origin and spec.origin.endswith(".py") else None
    for folder in spec.submodule_search_locations or ():
        base = Path(folder).joinpath(*rest)
        if (base / "__init__.py").is_file():
            return base / "__init__.py", True
        if base.with_suffix(".py").is_file():
            return base.with_suffix(".py"), False
    return None


def _imported_modules(tree: ast.AST, module: str, is_package: bool) -> set[str]:
    """Every module name an import statement anywhere in ``tree`` may load, with the parent packages that
    importing it runs; ``from a import b`` yields ``a.b`` as well (b may be a submodule)."""
    package = module if is_package else module.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".") if package else []
                if node.level - 1 > len(parts):
                    continue  # beyond the top-level package: an ImportError at run time, nothing to hash
                base = ".".join(parts[:len(parts) - (node.level - 1)])
                base = f"{base}.{node.module}" if node.module and base else (node.module or base)
            else:
                base = node.module or ""
            if not base:
                continue
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names if alias.name != "*")
    with_parents = set()
    for name in names:
        parts = name.split(".")
        with_parents.update(".".join(parts[:i]) for i in range(1, len(parts) + 1))
    return with_parents


def _without_docstrings(tree: ast.AST) -> ast.AST:
    """``tree`` with every bare string statement (module, class, function and attribute docstrings) removed."""
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list):
            node.body = [stmt for stmt in body if not (isinstance(stmt, ast.Expr)
                                                        and isinstance(stmt.value, ast.Constant)
                                                        and isinstance(stmt.value.value, str))]
    return tree


def _parse(path: Path) -> ast.Module:
    try:
        return ast.parse(path.read_bytes(), filename=str(path))
    except SyntaxError as exc:
        reason = f"cannot hash its code, Python cannot parse it ({exc.msg}, line {exc.lineno})"
        raise ValueError(f"{path}: {reason}") from exc


def _tree_digest(tree: ast.AST) -> str:
    return hashlib.sha256(ast.dump(_without_docstrings(tree)).encode()).hexdigest()


def source_digest(path: Path) -> str:
    """sha256 hex of a Python file's syntax tree less docstrings (comments and layout do not count)."""
    return _tree_digest(_parse(path))


@functools.lru_cache(maxsize=None)
def _module_code(module: str) -> tuple[str, frozenset[str]] | None:
    """(source digest, modules its imports may load) of one module, parsed once per process."""
    found = module_file(module)
    if found is None:
        return None
    path, is_package = found
    tree = _parse(path)
    imported = _imported_modules(tree, module, is_package)
    return _tree_digest(tree), frozenset(imported)


@functools.lru_cache(maxsize=None)
def _code_digests(module: str, packages: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    if _module_code(module) is None:
        raise ValueError(f"module {module}: no Python source file found to hash its code")
    parts = module.split(".")
    # importing the module runs its parent packages' __init__ first
    todo = [module] + [p for p in (".".join(parts[:i]) for i in range(1, len(parts))) if _counts(p, packages)]
    digests: dict[str, str] = {}
    while todo:
        name = todo.pop()
        code = _module_code(name)
        if name in digests or code is None:  # None: an attribute (from a import b) or an absent optional import
            continue
        digests[name] = code[0]
        todo += sorted(m for m in code[1] if m not in digests and _counts(m, packages))
    return tuple(sorted(digests.items()))


def clear_code_cache() -> None:
    """Forget every code digest of this process (for tests that edit source files)."""
    _module_code.cache_clear()
    _code_digests.cache_clear()


def code_digests(module: str, packages: Iterable[str]) -> dict[str, str]:
    """Module name -> :func:`source_digest` for ``module`` and every module under ``packages`` (dotted
    prefixes, e.g. ``{"stages", "pipeline.codecs"}``) that it imports, transitively.

    Cached per process: the code a process runs does not change while it runs, whatever happens to the files
    (:func:`clear_code_cache` starts over).
    """
    if not module:
        raise ValueError("code_digests needs a module name")
    return dict(_code_digests(module, tuple(sorted(set(packages)))))


def code_digest(module: str, packages: Iterable[str]) -> str:
    """One sha256 hex over :func:`code_digests` in sorted module order."""
    return record_key({"code": code_digests(module, packages)})
