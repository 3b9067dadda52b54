"""MakeHuman body shape: macro parameters -> vertex offsets of the MakeHuman base mesh.

MakeHuman's macro modifiers (makehuman/apps/humanmodifier.py, the ``macrodetails`` targets) blend morph targets
linearly. Each parameter is in [0, 1] and gives its axis' corners interpolation weights:

- gender: female ``1 - g``, male ``g``;
- age (adult corners only): young (25 years) ``1 - 2 (a - 0.5)``, old (90 years) ``2 (a - 0.5)``; MakeHuman's
  slider value, so 0.5 is 25 years and 1 is 90 (below 0.5 are the child and baby corners, not shipped);
- muscle and weight: below 0.5 min ``1 - 2 x`` and average ``2 x``; above it average ``2 - 2 x`` and
  max ``2 x - 1``;
- height: below 0.5 min ``1 - 2 h``, above it max ``2 h - 1`` (average height has no target);
- the ethnic blend: african, asian, caucasian weights summing to 1.

A corner target's weight is the product of its axes' weights: ``universal-{gender}-{age}-{muscle}-{weight}``
(gender x age x muscle x weight), ``height/{gender}-{age}-{muscle}-{weight}-{height}`` (those x height) and
``{ethnic}-{gender}-{age}`` (ethnic x gender x age); the body is the base plus the weighted sum of the
corners' offsets (:func:`blend_offsets`). At MakeHuman's default parameters (:data:`DEFAULT_PARAMS`) the
universal and height terms vanish (the average-muscle, average-weight universal targets are empty and
height 0.5 has no target), leaving the mean of the six young ethnic targets.

Target files (``*.target.gz``): gzip'd text, ``index dx dy dz`` per moved vertex in the base mesh file's units,
``#`` comments (:func:`read_target`). Everything else here is arrays in, arrays out.
"""
from __future__ import annotations

import functools
import itertools
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from pipeline.config import Documented, broken, checked
from pipeline.errors import InputError

GENDERS = ("female", "male")
AGES = ("young", "old")
LEVELS = ("min", "average", "max")
HEIGHTS = ("min", "max")
ETHNICS = ("african", "asian", "caucasian")
SHAPE_AXES = ("gender", "age", "muscle", "weight", "height")
"""The continuous shape parameters; with ETHNICS they are BodyParams' fields."""

RANDOM_RANGES = {"gender": (0.0, 1.0), "age": (0.5, 1.0), "muscle": (0.0, 1.0), "weight": (0.0, 1.0),
                 "height": (0.3, 0.7)}
"""Ranges `draw_body` draws each parameter from (uniform); the ethnic weights are a flat Dirichlet draw.
Height stays in [0.3, 0.7] (about 1.5 .. 1.95 m from the base's 1.66 m): MakeHuman's height targets at 0 and 1
make a dwarf and a giant (the head about -36 / +70 cm) that no capture frames with the other bodies."""


@dataclass(frozen=True)
class BodyParams(Documented):
    """MakeHuman macro parameters of one body, each in [0, 1] (module docstring); InvalidConfig (a ValueError)
    when out of range."""
    gender: float = checked(0.5, ge=0.0, le=1.0)
    """0 female .. 1 male."""
    age: float = checked(0.5, ge=0.5, le=1.0)
    """MakeHuman's age slider, adult part only: 0.5 = 25 years .. 1 = 90 years (the child and baby corners are
    not shipped)."""
    muscle: float = checked(0.5, ge=0.0, le=1.0)
    """0 min .. 0.5 average .. 1 max muscle."""
    weight: float = checked(0.5, ge=0.0, le=1.0)
    """0 min (MakeHuman's 50%) .. 0.5 average .. 1 max weight (150%)."""
    height: float = checked(0.5, ge=0.0, le=1.0)
    """0 min .. 0.5 average .. 1 max height."""
    african: float = checked(1.0 / 3.0, ge=0.0, le=1.0)
    """Ethnic blend weight (the three sum to 1)."""
    asian: float = checked(1.0 / 3.0, ge=0.0, le=1.0)
    """Ethnic blend weight."""
    caucasian: float = checked(1.0 / 3.0, ge=0.0, le=1.0)
    """Ethnic blend weight."""

    def _checks(self) -> list[str]:
        if abs(self.african + self.asian + self.caucasian - 1.0) > 1e-6:
            return [broken(self, "african", f"the ethnic weights ({self.african!r}, {self.asian!r}, "
                                            f"{self.caucasian!r}) must sum to 1")]
        return []

    @property
    def age_years(self) -> float:
        """The age in years MakeHuman gives the slider value (25 at 0.5 .. 90 at 1)."""
        return 25.0 + (self.age - 0.5) / 0.5 * 65.0

    def to_json(self) -> dict:
        return {k: round(float(v), 6) for k, v in asdict(self).items()} | {"age_years": round(self.age_years, 3)}


DEFAULT_PARAMS = BodyParams()
"""MakeHuman's default human: every axis at 0.5 (age 25 years), the three ethnic weights 1/3."""


def ethnic_blend(given: Mapping[str, float]) -> dict[str, float]:
    """The three ethnic weights from the ones given (MakeHuman's rule): the given ones are kept and the others
    share what is left of 1 equally; ValueError when the given ones exceed 1 (or all three are given and do
    not sum to 1)."""
    unknown = set(given) - set(ETHNICS)
    if unknown:
        raise ValueError(f"not ethnic weights: {sorted(unknown)}")
    total = float(sum(given.values()))
    rest = [e for e in ETHNICS if e not in given]
    if total > 1.0 + 1e-9 or (not rest and abs(total - 1.0) > 1e-6):
        raise ValueError(f"ethnic weights {dict(given)} must sum to 1 (or less when some are left out)")
    share = max(0.0, 1.0 - total) / len(rest) if rest else 0.0
    return {e: float(given[e]) if e in given else share for e in ETHNICS}


def parse_body_spec(spec: str) -> tuple[bool, dict[str, float]]:
    """``"random"``, ``"gender=0.2,weight=0.9"`` or ``"random,height=0.7"`` -> (random, fixed values).

    ValueError names what is wrong: an unknown name, a value that is not a number, a name given twice."""
    is_random, values = False, {}
    names = set(SHAPE_AXES) | set(ETHNICS)
    for item in (part.strip() for part in spec.split(",")):
        if not item:
            continue
        if item == "random":
            is_random = True
            continue
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in names:
            raise ValueError(f"body spec {spec!r}: {item!r} is not 'random' nor NAME=VALUE with NAME one of "
                             f"{', '.join(SHAPE_AXES + ETHNICS)}")
        if name in values:
            raise ValueError(f"body spec {spec!r}: {name} given twice")
        try:
            values[name] = float(value)
        except ValueError:
            raise ValueError(f"body spec {spec!r}: {name}={value!r} is not a number") from None
    if not is_random and not values:
        raise ValueError(f"body spec {spec!r}: empty (give 'random' or NAME=VALUE items)")
    return is_random, values


def body_from_spec(spec: str, rng: np.random.Generator | None = None) -> BodyParams:
    """The body a spec means (:func:`parse_body_spec`): its fixed values, the rest MakeHuman's defaults, or
    (``random``) drawn from `rng` (:data:`RANDOM_RANGES`, a flat Dirichlet ethnic blend) with the fixed ones
    replacing their draws. ValueError for a bad spec or values out of range."""
    is_random, values = parse_body_spec(spec)
    axes = {k: v for k, v in values.items() if k in SHAPE_AXES}
    ethnic = {k: v for k, v in values.items() if k in ETHNICS}
    if is_random:
        if rng is None:
            raise ValueError(f"body spec {spec!r} is random: a generator is needed")
        drawn = draw_body(rng)
        axes = {a: axes.get(a, getattr(drawn, a)) for a in SHAPE_AXES}
        if ethnic and len(ethnic) < len(ETHNICS):  # the drawn blend scaled into what the given ones leave
            rest = [e for e in ETHNICS if e not in ethnic]
            left = max(0.0, 1.0 - sum(ethnic.values()))
            drawn_rest = sum(getattr(drawn, e) for e in rest)
            ethnic = ethnic | {e: left * getattr(drawn, e) / drawn_rest for e in rest}
        elif not ethnic:
            ethnic = {e: getattr(drawn, e) for e in ETHNICS}
    return BodyParams(**axes, **ethnic_blend(ethnic))


def draw_body(rng: np.random.Generator) -> BodyParams:
    """A random body: each axis uniform in RANDOM_RANGES (in SHAPE_AXES order), then a flat Dirichlet ethnic
    blend, all from `rng`."""
    axes = {a: float(rng.uniform(*RANDOM_RANGES[a])) for a in SHAPE_AXES}
    blend = rng.dirichlet(np.ones(len(ETHNICS)))
    blend = blend / blend.sum()
    return BodyParams(**axes, **{e: float(w) for e, w in zip(ETHNICS, blend)}, )


# --- per-axis and corner weights (pure) ------------------------------------------------------------------

def level_weights(x: float) -> dict[str, float]:
    """min / average / max weights of a muscle or weight value in [0, 1] (two are nonzero at most)."""
    if x < 0.5:
        return {"min": 1.0 - 2.0 * x, "average": 2.0 * x, "max": 0.0}
    return {"min": 0.0, "average": 2.0 - 2.0 * x, "max": 2.0 * x - 1.0}


def axis_weights(params: BodyParams) -> dict[str, dict[str, float]]:
    """Interpolation weights of every axis' corners: axis -> corner -> weight (module docstring)."""
    old = 2.0 * (params.age - 0.5)
    return {"gender": {"female": 1.0 - params.gender, "male": params.gender},
            "age": {"young": 1.0 - old, "old": old},
            "muscle": level_weights(params.muscle),
            "weight": level_weights(params.weight),
            "height": {"min": max(0.0, 1.0 - 2.0 * params.height), "max": max(0.0, 2.0 * params.height - 1.0)},
            "ethnic": {e: getattr(params, e) for e in ETHNICS}}


def corner_weights(params: BodyParams) -> dict[str, float]:
    """Target name (path in the targets folder, no ``.target.gz``) -> weight, for every corner with a nonzero
    weight: the product of its axes' weights."""
    w = axis_weights(params)
    out: dict[str, float] = {}
    for g, a, m, wt in itertools.product(GENDERS, AGES, LEVELS, LEVELS):
        base = w["gender"][g] * w["age"][a] * w["muscle"][m] * w["weight"][wt]
        if base == 0.0:
            continue
        out[f"universal-{g}-{a}-{m}muscle-{wt}weight"] = base
        for h in HEIGHTS:
            if w["height"][h] > 0.0:
                out[f"height/{g}-{a}-{m}muscle-{wt}weight-{h}height"] = base * w["height"][h]
    for e, g, a in itertools.product(ETHNICS, GENDERS, AGES):
        weight = w["ethnic"][e] * w["gender"][g] * w["age"][a]
        if weight > 0.0:
            out[f"{e}-{g}-{a}"] = weight
    return out


def blend_offsets(weights: Mapping[str, float], targets: Mapping[str, tuple[np.ndarray, np.ndarray]],
                  n_vertices: int) -> np.ndarray:
    """Sum of weight x target offsets, (n_vertices, 3) float64.

    Args:
        weights: target name -> weight (:func:`corner_weights`); every name must be in `targets`.
        targets: name -> (vertex indices (K,) int, offsets (K, 3) float), the moved vertices of the target.
        n_vertices: vertex count of the mesh the indices refer to.
    """
    missing = sorted(set(weights) - set(targets))
    if missing:
        raise KeyError(f"targets missing: {missing[:3]}{' ...' if len(missing) > 3 else ''}")
    out = np.zeros((n_vertices, 3), np.float64)
    for name in sorted(weights):  # a fixed order: the same sum whatever the dict order
        indices, offsets = targets[name]
        if len(indices) and (indices.min() < 0 or indices.max() >= n_vertices):
            raise ValueError(f"target {name} moves vertex indices outside [0, {n_vertices})")
        np.add.at(out, indices, weights[name] * np.asarray(offsets, np.float64))  # (repeated indices add up)
    return out


# --- files ------------------------------------------------------------------------------------------------

def read_target(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A ``.target.gz`` (or plain ``.target``) file: vertex indices (K,) int64 and offsets (K, 3) float64.
    InputError names the file and the reason when it is missing or a line is not ``index dx dy dz``."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "target file does not exist")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an empty target (no moved vertex) is a valid one
            table = np.loadtxt(path, comments="#", dtype=np.float64, ndmin=2)
    except (OSError, EOFError) as exc:
        raise InputError(path, f"not a readable target file ({exc})") from exc
    except ValueError as exc:
        raise InputError(path, f"a line is not 'index dx dy dz' ({exc})") from exc
    if table.size == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.float64)
    if table.shape[1] != 4:
        raise InputError(path, f"lines have {table.shape[1]} numbers, not 4 ('index dx dy dz')")
    if not np.all(np.isfinite(table)):
        raise InputError(path, "offsets hold NaN or Inf")
    indices = table[:, 0].astype(np.int64)
    if np.any(indices != table[:, 0]) or np.any(indices < 0):
        raise InputError(path, "vertex indices are not whole numbers >= 0")
    if len(np.unique(indices)) != len(indices):
        raise InputError(path, "a vertex index appears twice")
    return indices, table[:, 1:].copy()


@functools.lru_cache(maxsize=256)
def _cached_target(path: str) -> tuple[np.ndarray, np.ndarray]:
    return read_target(path)


def makehuman_offsets(folder: str | Path, params: BodyParams, n_vertices: int) -> np.ndarray:
    """Offsets (n_vertices, 3) float64, in the base mesh file's units, of the body `params` gives, from the
    targets in `folder` (each read once per process). InputError names a target file that is missing."""
    folder = Path(folder)
    weights = corner_weights(params)
    targets = {}
    for name in weights:
        path = folder / f"{name}.target.gz"
        if not path.is_file():
            raise InputError(path, "MakeHuman target missing (the targets folder's README lists them)")
        targets[name] = _cached_target(str(path))
    return blend_offsets(weights, targets, n_vertices)


def extreme_bodies(ranges: Mapping[str, tuple[float, float]] = RANDOM_RANGES) -> list[BodyParams]:
    """Bodies at every corner of the parameter box `ranges` and the pure ethnic corners, with the axes' kinks
    (0.5 of muscle, weight, height) where inside the range: the offsets are multilinear between these grid
    points, so every vertex of any body in the box is a convex combination of its positions in these bodies
    (its bounding box and its distance from an axis are largest at one of them)."""
    def grid(axis: str) -> list[float]:
        lo, hi = ranges[axis]
        points = [lo, hi]
        if axis in ("muscle", "weight", "height") and lo < 0.5 < hi:
            points.insert(1, 0.5)
        return points

    bodies = []
    for values in itertools.product(*(grid(a) for a in SHAPE_AXES)):
        for ethnic in ETHNICS:
            bodies.append(BodyParams(**dict(zip(SHAPE_AXES, values)),
                                     **{e: float(e == ethnic) for e in ETHNICS}))
    return bodies
