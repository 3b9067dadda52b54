"""Which settings of the pipeline config are turned somewhere: the walk over the config and the search.

A setting counts as turned when something other than its own definition sets it: a preset (``PRESETS`` in
stages/registry.py, ``SDF_PRESETS`` in stages/numerics/sdf.py), a test, a bench, or the user documentation
(README.md, docs/), which is where a user learns that a setting exists. The search is by field name, so a
name shared by several configs (``seed``, ``previews``) counts as turned for all of them: the test can miss an
unturned field of that kind, never call a turned one unturned.

A field nobody turns belongs in ``USER_KNOBS`` below with the reason a user would turn it, or becomes a
constant in the code that reads it. Running this file as a script writes that list with each field's owner,
default and a verdict (``python tests/unit/pipeline/test_config_knobs.py OUT.txt``).
"""
from __future__ import annotations

import dataclasses
import re
import sys
import typing
from pathlib import Path
from typing import Any, NamedTuple

from stages.registry import PipelineConfig

REPO = Path(__file__).resolve().parents[3]

USER_KNOBS: dict[str, str] = {}
"""``Owner.field`` -> why a user turns it, for the fields that no preset, test, bench or document sets yet."""


class Knob(NamedTuple):
    owner: str
    """The dataclass that declares the field."""
    name: str
    path: str
    """Where it sits in the pipeline config, e.g. ``geometry.sdf.encoding.levels``."""
    default: Any


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def pipeline_knobs(cls: type = PipelineConfig, prefix: str = "") -> list[Knob]:
    """Every leaf field under ``cls``, nested configs walked (a section that is a config is no knob itself)."""
    hints = typing.get_type_hints(cls)
    out: list[Knob] = []
    for f in dataclasses.fields(cls):
        nested = [t for t in (hints[f.name], *typing.get_args(hints[f.name])) if dataclasses.is_dataclass(t)]
        if nested:
            out += pipeline_knobs(nested[0], f"{prefix}{f.name}.")
        else:
            out.append(Knob(cls.__name__, f.name, prefix + f.name, _default(f)))
    return out


def _preset_source(path: Path, start: str) -> str:
    """The text of a preset table: from the line starting with ``start`` to the closing brace at column 0."""
    text = path.read_text()
    begin = text.index(start)
    return text[begin:text.index("\n}\n", begin)]


def _corpus() -> tuple[str, str]:
    """(Python text, Markdown text) that can turn a setting: presets, tests less this file, benches, docs."""
    this = Path(__file__).resolve()
    py = [_preset_source(REPO / "stages/registry.py", "PRESETS: dict"),
          _preset_source(REPO / "stages/numerics/sdf.py", "SDF_PRESETS: dict")]
    for folder in ("tests", "bench"):
        py += [p.read_text() for p in sorted((REPO / folder).rglob("*.py")) if p.resolve() != this]
    md = [(REPO / "README.md").read_text()] + [p.read_text() for p in sorted((REPO / "docs").rglob("*.md"))]
    return "\n".join(py), "\n".join(md)


def turned_names(names: set[str]) -> set[str]:
    """The names among ``names`` that the corpus sets: as a keyword argument (``name=``), a dict key
    (``"name":``), a YAML key (``name: ...`` at the start of a line) or, in the docs, a dotted path
    (``section.name``) or a quoted name (`` `name` ``)."""
    py, md = _corpus()
    found = set()
    for name in names:
        n = re.escape(name)
        if (re.search(rf"[(,]\s*{n}\s*=(?!=)", py) or re.search(rf"[\"']{n}[\"']\s*:", py)
                or re.search(rf"(?m)(^|\\n)\s*{n}:\s*\S", py) or re.search(rf"[{{,]\s*{n}:\s", py)
                or re.search(rf"(?m)\w\.{n}\b|`{n}`|^\s*{n}:|[{{,]\s*{n}:\s", md)):
            found.add(name)
    return found


def unturned_knobs() -> list[Knob]:
    knobs = pipeline_knobs()
    turned = turned_names({k.name for k in knobs})
    return [k for k in knobs if k.name not in turned]


def test_the_walk_reaches_nested_configs():
    paths = {k.path for k in pipeline_knobs()}
    assert {"geometry.sdf.encoding.levels", "photometric.denoise.radius", "diffuse_normals.fit.steps",
            "relightset.shading.visibility_directions", "execution.scheduler"} <= paths
    assert "geometry.sdf" not in paths


def test_the_search_sees_presets_tests_and_docs():
    # hull_init_points only in SDF_PRESETS, ratio_min in the README's override example, a name nobody uses.
    assert turned_names({"hull_init_points", "ratio_min", "no_such_knob_anywhere"}) == {"hull_init_points",
                                                                                      "ratio_min"}


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("/dev/stdout")
    rows = [f"{k.owner}.{k.name}\t{k.path}\tdefault={k.default!r}\t"
            + (f"keep: {USER_KNOBS[k.owner + '.' + k.name]}" if f"{k.owner}.{k.name}" in USER_KNOBS else "?")
            for k in unturned_knobs()]
    out.write_text("\n".join(rows) + "\n")
    print(f"{len(rows)} unturned of {len(pipeline_knobs())} settings", file=sys.stderr)
