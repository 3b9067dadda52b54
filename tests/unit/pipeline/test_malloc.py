"""pipeline.malloc: glibc's malloc settings for this process and the ones it starts; a user's own are kept."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from pipeline.malloc import MALLOC_SETTINGS

CODE = ("import json, os; from pipeline.malloc import tune_malloc; applied = tune_malloc(); "
        "print(json.dumps({'applied': applied, 'env': {k: os.environ.get(k) for k in %r}}))" % (list(MALLOC_SETTINGS),))


def _run(env: dict[str, str]) -> dict:
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, check=True, env=env).stdout
    return json.loads(out)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_settings_reach_this_process_and_its_children_and_a_users_own_are_kept():
    clean = {k: v for k, v in os.environ.items() if k not in MALLOC_SETTINGS}
    result = _run(clean)
    want = {k: value for k, (_, value) in MALLOC_SETTINGS.items()}
    assert result["applied"] == want  # mallopt took every one (glibc)
    assert result["env"] == {k: str(v) for k, v in want.items()}  # and the processes it starts inherit them
    mine = _run(clean | {"MALLOC_TRIM_THRESHOLD_": "131072"})
    assert "MALLOC_TRIM_THRESHOLD_" not in mine["applied"]
    assert mine["env"]["MALLOC_TRIM_THRESHOLD_"] == "131072"
    assert mine["env"]["MALLOC_MMAP_THRESHOLD_"] == str(want["MALLOC_MMAP_THRESHOLD_"])


def test_the_command_line_applies_them(tmp_path):
    """`ultrastage` sets them before any command runs (a command's children, dask's workers among them, inherit
    them)."""
    clean = {k: v for k, v in os.environ.items() if k not in MALLOC_SETTINGS}
    code = ("import os, sys; from ultrastage import cli; "
            "cli.cmd_verify = lambda args: print(os.environ.get('MALLOC_MMAP_THRESHOLD_')) or 0; "
            "sys.exit(cli.main(['verify', %r]))" % str(tmp_path))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=clean)
    assert out.returncode == 0, out.stderr
    expected = str(MALLOC_SETTINGS["MALLOC_MMAP_THRESHOLD_"][1]) if sys.platform.startswith("linux") else "None"
    assert out.stdout.strip() == expected
