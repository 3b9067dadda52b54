"""Every setting of the pipeline config is turned somewhere, or is a knob a user plausibly turns.

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

USER_KNOBS: dict[str, str] = {
    # Marker calibration (calibration/markers.py): search radii and tolerances that depend on a real rig's
    # lenses, its target and how far its mounting is from the rig spec; the simulator needs none turned.
    **{f"MarkerCalibrationConfig.{name}": "tolerance of the marker target's detection to a real rig's optics"
       for name in ("background_window_px", "shift_search_px", "zoom_search", "first_search_px", "search_px",
                    "clearance_px", "first_clearance_px", "border_px", "min_markers",
                    "ransac_max_error_px", "max_residual_px")},
    "MarkerCalibrationConfig.max_change_m": "how far a recalibrated camera may move before the run refuses it",
    "MarkerCalibrationConfig.max_change_deg": "how far a recalibrated camera may turn before the run refuses it",
    # Structure from motion (calibration/geometric.py): COLMAP's own options, passed through under COLMAP's
    # names, for users who tune COLMAP to their photos.
    **{f"GeometricConfig.{name}": "a COLMAP option, passed through for users who tune COLMAP"
       for name in ("max_num_features", "peak_threshold", "first_octave", "domain_size_pooling",
                    "estimate_affine_shape", "shared_camera", "exhaustive_max_images", "sequential_overlap",
                    "guided_matching", "min_num_matches", "retry_unregistered", "relaxed_min_num_inliers",
                    "ba_function_tolerance", "final_ba_iterations", "final_ba_rounds", "final_ba_loss",
                    "final_filter_max_error_px", "final_retriangulate", "alignment_max_error")},
    "GeometricConfig.verbose": "COLMAP's log output, for a user debugging a failed reconstruction",
    # The validity alpha and the mask: thresholds a user sets to a real capture's noise, background and plate
    # (the README's override example turns ratio_min, their sibling).
    **{f"PhotometricParams.{name}": "validity or mask threshold set to a real capture's noise and background"
       for name in ("signal_softness", "ratio_max", "ratio_softness", "plate_brighter", "plate_darker",
                    "plate_noise_sigmas", "plate_min_diff", "no_plate_threshold", "min_component")},
    "GapConfig.step_m": "the narrowest gap between limbs the masks open: finer for a slim subject, coarser for "
                        "speed on full-resolution captures",
    "GapConfig.max_rays": "the decision's cost against its sampling of a hole, on full-resolution captures",
    "PhotometricConfig.use_clean_plate": "turns a step off: segment by threshold where a session's plate is bad",
    "DiffuseNormalsConfig.use_materials_roughness": "turns an input off: the roughness prior instead of the "
                                                    "materials' roughness (an ablation a user compares)",
    # The SDF's loss weights and hull tolerances: what a user tunes to a subject or a rig (weight_mask and
    # weight_eikonal, their siblings, are turned by the cpu preset).
    "SDFConfig.weight_normal": "loss weight, tuned per subject as weight_mask is",
    "SDFConfig.weight_curvature": "turns the smoothness term on (0 = off) for noisy normals",
    "SDFConfig.weight_hull": "loss weight, tuned per subject as weight_mask is",
    "SDFConfig.hull_max_misses": "tolerance of the hull to a camera with a bad mask on a real rig",
    "SDFConfig.hull_margin_m": "room around the subject: larger for loose clothing or hair the hull cuts",
    "SDFConfig.hull_init_tight": "turns a step off: the conservative hull as the start (an ablation)",
    "SDFConfig.hull_init_dilate_px": "tolerance of the pre-fit hull to calibration errors on a real rig",
    "SDFConfig.gradient": "speed/memory trade-off of the SDF gradients, device-dependent",
    **{f"{owner}.min_alpha": "which pixels count as the subject: coverage against accuracy at the silhouette"
       for owner in ("GeometryConfig", "TexturesConfig", "MaterialsConfig", "RelightConfig")},
    "TexturesConfig.atlas_padding": "texel padding of the atlas charts, for users whose renderer mipmaps",
    "RelightSetConfig.png_level": "exposure of the set's 8-bit PNGs, a user's output choice",
    "ExecutionConfig.memory_limit": "the machine's memory per worker, a user's resource choice",
}
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


def test_every_knob_is_turned_or_a_documented_user_knob():
    unturned = sorted({f"{k.owner}.{k.name}" for k in unturned_knobs()} - set(USER_KNOBS))
    assert not unturned, (f"settings no preset, test, bench or document turns: {unturned}; make each a constant "
                          f"where it is read, or add it to USER_KNOBS in {Path(__file__).name} with the reason "
                          "a user turns it")


def test_user_knobs_name_unturned_fields_with_a_reason():
    # An entry that no longer names an unturned field (renamed, removed, or now set by a preset or test) goes.
    unturned = {f"{k.owner}.{k.name}" for k in unturned_knobs()}
    assert not set(USER_KNOBS) - unturned, f"USER_KNOBS names no unturned field: {sorted(set(USER_KNOBS) - unturned)}"
    assert all(reason.strip() for reason in USER_KNOBS.values())


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("/dev/stdout")
    rows = [f"{k.owner}.{k.name}\t{k.path}\tdefault={k.default!r}\t"
            + (f"keep: {USER_KNOBS[k.owner + '.' + k.name]}" if f"{k.owner}.{k.name}" in USER_KNOBS else "?")
            for k in unturned_knobs()]
    out.write_text("\n".join(rows) + "\n")
    print(f"{len(rows)} unturned of {len(pipeline_knobs())} settings", file=sys.stderr)
