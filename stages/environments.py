"""Environment maps by name: where a config's entry is found, how it is read, and its spherical-Gaussian fit.

Shared by the stages that shade under environments (``relight``, ``relightset``), the evaluation and the benches:
an entry is a file path, a file name (stem) looked up in $ULTRASTAGE_HDRI, the capture's ``environments/`` folder
and ../shared/data/hdri, or ``procedural:<kind>``. The SG fits are kept under the work folder's cache, so a map is
fitted once per work folder.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.claims import await_or_claim
from pipeline.errors import InputError

PROCEDURAL_PREFIX = "procedural:"
#: What an environment found nowhere is replaced by (a capture without ../shared still gets renders).
FALLBACK_ENVIRONMENT = "procedural:sky"
#: Where environment names are looked up, after $ULTRASTAGE_HDRI (os.pathsep-separated folders).
DEFAULT_HDRI_DIRS = (Path(__file__).resolve().parents[1].parent / "shared" / "data" / "hdri",)
_HDR_SUFFIXES = (".hdr", ".exr")


def environment_label(name: str) -> str:
    """File-name-safe label of an environment entry (``procedural:sky`` -> ``procedural_sky``)."""
    stem = name[len(PROCEDURAL_PREFIX):] if name.startswith(PROCEDURAL_PREFIX) else Path(name).stem
    label = ("procedural_" if name.startswith(PROCEDURAL_PREFIX) else "") + stem
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in label)


def find_environment(name: str, capture_root: Path | None = None) -> Path | None:
    """The file an environment entry names, or None (procedural, or found nowhere)."""
    if name.startswith(PROCEDURAL_PREFIX):
        return None
    path = Path(name).expanduser()
    if path.suffix.lower() in _HDR_SUFFIXES and path.is_file():
        return path
    dirs = [Path(d) for d in os.environ.get("ULTRASTAGE_HDRI", "").split(os.pathsep) if d]
    if capture_root is not None:
        dirs.append(Path(capture_root) / "environments")
    dirs += list(DEFAULT_HDRI_DIRS)
    for folder in dirs:
        for suffix in ("",) + _HDR_SUFFIXES:
            candidate = folder / f"{name}{suffix}"
            if candidate.is_file() and candidate.suffix.lower() in _HDR_SUFFIXES:
                return candidate
    return None


def raw_environment_inputs(names: tuple[str, ...], capture_root: Path | None) -> dict[str, Path]:
    """The environment files a config names, as raw inputs (``environment/<label>`` -> path): their digests
    enter the stage's key, so replacing a map reruns the stage. Procedural and missing names have none."""
    found = {}
    for name in names:
        path = find_environment(name, capture_root)
        if path is not None:
            found[f"environment/{environment_label(name)}"] = path
    return found


def load_environment(name: str, path: Path | None, height: int = 256) -> tuple[np.ndarray, str]:
    """(environment (H, 2H, 3) float32, how it was obtained) for a config entry and its resolved file."""
    from pipeline.codecs.hdr import read_environment
    from stages.numerics.sg import PROCEDURAL_ENVIRONMENTS, procedural_environment

    if path is not None:
        env = read_environment(path)
        if not np.all(np.isfinite(env)) or env.ndim != 3 or env.shape[1] != 2 * env.shape[0]:
            raise InputError(path, f"not a finite equirectangular (H, 2H, 3) map: shape {env.shape}")
        return np.maximum(env, 0.0).astype(np.float32), f"file {path.name}"
    kind = name[len(PROCEDURAL_PREFIX):] if name.startswith(PROCEDURAL_PREFIX) else None
    if kind is not None:
        if kind not in PROCEDURAL_ENVIRONMENTS:
            raise ValueError(f"relight.environments: unknown {name!r}; built in: "
                             f"{[PROCEDURAL_PREFIX + k for k in PROCEDURAL_ENVIRONMENTS]}")
        return procedural_environment(kind, height), "procedural"
    return procedural_environment("sky", height), f"FALLBACK: {name!r} not found, {FALLBACK_ENVIRONMENT} used"


CLAIM_STALE_S = 900.0
"""A fit's claim file older than this is taken for the claim of a process that died (a fit takes seconds)."""


def fit_sg_memo(env: np.ndarray, sg_lobes: int, fit_height: int, cache_dir: Path | None,
                wait: bool = True, iterations: int = 300) -> Any:
    """:func:`stages.numerics.sg.fit_sg_environment` of a map (``iterations`` of its optimiser), kept in
    ``cache_dir/sg_fits/`` under the hash of the map's float32 bytes, the fit's settings and the fitting code, so a
    map is fitted once per work folder (both actions and both stages of a session use the same maps). None as
    ``cache_dir``: no memo.

    A process fitting a map claims it (``<fit>.claim``, holding its pid, removed when the fit is stored): the
    two actions' relight stages start together and ask for the same maps, and a map another process is
    fitting is waited for instead of fitted twice (``wait`` False: None is returned at once, so the caller can
    fit another map meanwhile). A claim whose process is gone is taken over."""
    import hashlib

    from stages.numerics import sg
    from stages.numerics.sg import SGLobes, fit_sg_environment

    if cache_dir is None:
        return fit_sg_environment(env, sg_lobes, iterations=iterations, fit_height=fit_height)
    digest = hashlib.sha256(np.ascontiguousarray(env, np.float32).tobytes())
    digest.update(repr((env.shape, int(sg_lobes), int(fit_height), int(iterations))).encode())
    digest.update(Path(sg.__file__).read_bytes())
    path = Path(cache_dir) / "sg_fits" / f"{digest.hexdigest()[:32]}.json"
    claim = path.with_suffix(".claim")

    def stored() -> Any:
        if path.is_file():
            try:
                return SGLobes.from_dict(json.loads(path.read_text()))
            except (OSError, ValueError, KeyError):
                pass  # unreadable: fit again
        return None

    path.parent.mkdir(parents=True, exist_ok=True)
    while True:  # the fit is returned as stored, read back from its file
        lobes, claimed = await_or_claim(stored, claim, CLAIM_STALE_S, wait=wait)
        if not claimed:
            return lobes
        try:
            lobes = fit_sg_environment(env, sg_lobes, iterations=iterations, fit_height=fit_height)
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            tmp.write_text(json.dumps(lobes.numpy().to_dict()))
            os.replace(tmp, path)
        finally:
            claim.unlink(missing_ok=True)


def fit_environments(requested_names: tuple[str, ...], raw_inputs: dict[str, Path], sg_lobes: int, fit_height: int,
                     log: Any, cache_dir: Path | None = None, iterations: int = 300) -> list[dict[str, Any]]:
    """Each requested environment loaded (its file from ``raw_inputs['environment/<label>']``) and fitted with
    ``sg_lobes`` spherical Gaussians (``iterations`` of the fit's optimiser, :func:`fit_sg_memo`): records
    ``name``, ``requested``, ``label``, ``source``, ``lobes``, ``fit_seconds``, ``fit_errors``. Missing maps become
    the procedural sky, once, with a warning."""
    from stages.numerics.sg import sg_fit_errors

    environments: list[dict[str, Any]] = []
    maps: list[np.ndarray] = []
    for requested in requested_names:
        name, label = requested, environment_label(requested)
        env, how = load_environment(name, raw_inputs.get(f"environment/{label}"))
        if how.startswith("FALLBACK"):
            # Named and labelled as what it is; several missing maps give one procedural sky.
            log.warning("relight: %s", how)
            name, label = FALLBACK_ENVIRONMENT, environment_label(FALLBACK_ENVIRONMENT)
            if any(e["label"] == label for e in environments):
                continue
        elif any(e["label"] == label for e in environments):
            raise ValueError(f"relight.environments {requested_names} give the label {label!r} twice")
        environments.append({"name": name, "requested": requested, "label": label, "source": how, "lobes": None,
                             "fit_seconds": 0.0})
        maps.append(env)
    # The maps no other process is fitting first, then those it was (by then mostly stored): two stages that
    # start together share the fits instead of both fitting every map.
    for wait in (False, True):
        for record, env in zip(environments, maps):
            if record["lobes"] is None:
                t0 = time.perf_counter()
                record["lobes"] = fit_sg_memo(env, sg_lobes, fit_height, cache_dir, wait=wait,
                                              iterations=iterations)
                record["fit_seconds"] += time.perf_counter() - t0
    for record, env in zip(environments, maps):
        errors = sg_fit_errors(env, record["lobes"])
        record["fit_errors"] = {k: float(v) for k, v in errors.items() if isinstance(v, (int, float, np.floating))}
    return environments
