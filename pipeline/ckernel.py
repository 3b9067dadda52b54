"""Small C kernels compiled once per machine and loaded with :mod:`ctypes`.

Numeric code whose numpy or torch form walks many temporaries (a chain of elementwise operations over a large
array) keeps that form as the reference and gets a fused C loop beside it, written to give the same float32
bits (the same IEEE operations in the same order; ``-std=c99`` keeps the compiler from contracting a multiply
and an add into one FMA). The source is compiled with the system's C compiler into ``$ULTRASTAGE_KERNEL_CACHE``
(default ``~/.cache/ultrastage/kernels``) under a name that hashes the source and flags, so processes that
compile side by side each install a whole file and an edited kernel is compiled again. Where no compiler is
found, the compile fails or the library does not load, :func:`load_kernel` returns None (saying why on stderr)
and the caller keeps its reference path.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

FLAGS = ("-O3", "-shared", "-fPIC", "-std=c99")
"""Compiler flags of every kernel: optimised, position-independent, ISO C99 (no FMA contraction)."""


def kernel_cache_dir() -> Path:
    """Where compiled kernels are kept: ``$ULTRASTAGE_KERNEL_CACHE``, else ``~/.cache/ultrastage/kernels``."""
    root = os.environ.get("ULTRASTAGE_KERNEL_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "ultrastage" / "kernels"


def load_kernel(name: str, source: str, signatures: dict[str, tuple[list[Any], Any]],
                fallback: str = "the reference path", extra_flags: tuple[str, ...] = ()) -> ctypes.CDLL | None:
    """The C ``source`` compiled (on first use) and loaded, its functions typed by ``signatures``
    (function name -> (argtypes, restype)); None where it cannot be, said on stderr as "<name> kernel: <why>;
    <fallback> is used". ``name`` labels the file and the messages; ``extra_flags`` follow :data:`FLAGS` (they must
    not change a float result: no ``-ffast-math``)."""
    compiler = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    if compiler is None:
        return None
    flags = FLAGS + tuple(extra_flags)
    digest = hashlib.sha256((source + " ".join(flags) + sys.platform).encode()).hexdigest()[:16]
    target = kernel_cache_dir() / f"{name}_{digest}.so"
    try:
        if not target.exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
                path = Path(tmp) / f"{name}.c"
                path.write_text(source)
                built = Path(tmp) / target.name
                proc = subprocess.run([compiler, *flags, "-o", str(built), str(path), "-lm"],
                                      capture_output=True, text=True)
                if proc.returncode != 0:
                    print(f"{name} kernel: {compiler} failed ({proc.stderr.strip()[:300]}); {fallback} is used",
                          file=sys.stderr)
                    return None
                os.replace(built, target)  # atomic: processes compiling side by side each install a whole file
        lib = ctypes.CDLL(str(target))
    except OSError as exc:  # an unwritable cache folder, a library that does not load: the reference path works
        print(f"{name} kernel: {target}: {exc}; {fallback} is used", file=sys.stderr)
        return None
    for function, (argtypes, restype) in signatures.items():
        getattr(lib, function).argtypes = argtypes
        getattr(lib, function).restype = restype
    return lib
