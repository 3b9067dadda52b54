"""pipeline.ckernel: a C kernel compiled once into the cache and loaded, or None with the reason on stderr."""
from __future__ import annotations

import ctypes
import shutil

import pytest

from pipeline.ckernel import load_kernel

_ADD = "int add(int a, int b) { return a + b; }\n"
_SIGNATURES = {"add": ([ctypes.c_int, ctypes.c_int], ctypes.c_int)}

needs_compiler = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                                    reason="no C compiler here")


@needs_compiler
def test_a_kernel_is_compiled_once_typed_and_loaded(tmp_path, monkeypatch):
    monkeypatch.setenv("ULTRASTAGE_KERNEL_CACHE", str(tmp_path / "kernels"))
    lib = load_kernel("adder", _ADD, _SIGNATURES)
    assert lib is not None and lib.add(2, 40) == 42
    built = list((tmp_path / "kernels").glob("adder_*.so"))
    assert len(built) == 1
    stamp = built[0].stat().st_mtime_ns
    assert load_kernel("adder", _ADD, _SIGNATURES).add(1, 1) == 2
    assert built[0].stat().st_mtime_ns == stamp  # loaded from the cache, not compiled again
    load_kernel("adder", _ADD, _SIGNATURES, extra_flags=("-fno-math-errno",))
    assert len(list((tmp_path / "kernels").glob("adder_*.so"))) == 2  # other flags: another library


@needs_compiler
def test_a_source_that_does_not_compile_gives_none_and_says_why(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("ULTRASTAGE_KERNEL_CACHE", str(tmp_path / "kernels"))
    assert load_kernel("broken", "int add(int a, { return a; }\n", _SIGNATURES, fallback="the slow path") is None
    err = capsys.readouterr().err
    assert "broken kernel:" in err and "failed" in err and "the slow path is used" in err
    assert not list((tmp_path / "kernels").glob("broken_*.so"))


@needs_compiler
def test_an_unwritable_cache_gives_none_and_names_the_path(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    monkeypatch.setenv("ULTRASTAGE_KERNEL_CACHE", str(blocker / "kernels"))  # a folder under a regular file
    assert load_kernel("adder", _ADD, _SIGNATURES) is None
    err = capsys.readouterr().err
    assert "adder kernel:" in err and "a_file" in err and "the reference path is used" in err
