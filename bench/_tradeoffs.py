"""Per stage, time against error over its quality knobs, read from the benches' JSON (the rows they already sweep).

Each ``*_tradeoffs(out)`` reads one bench's result under ``out`` and returns :class:`_pareto.Tradeoff` records (none
when the bench did not write one). Which point a preset gives is read from the presets' configs
(:data:`stages.registry.PRESETS`), never restated here. :func:`report_section` turns them into the report's tables
and plots.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

from _pareto import Tradeoff, TradeoffPoint, tradeoff_plot, tradeoff_table

MARKED_PRESETS = ("default", "production", "fast")
"""The presets whose points the tables name (plots ring the default and the production ones)."""


def _load(out: Path, bench: str) -> dict[str, Any] | None:
    path = Path(out) / f"{bench}.json"
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _presets_where(test: Callable[[Any], bool]) -> tuple[str, ...]:
    """The marked presets whose PipelineConfig passes ``test``."""
    from stages.registry import PRESETS

    return tuple(name for name in MARKED_PRESETS if test(PRESETS[name]))


def decode_tradeoffs(out: Path) -> list[Tradeoff]:
    data = _load(out, "bench_decode")
    if not data:
        return []
    points = []
    for r in data["rows"]:
        if r["half_size"]:
            presets = _presets_where(lambda c: c.decode.half_size)
        else:
            presets = _presets_where(lambda c, a=r["algorithm"]: not c.decode.half_size and c.decode.demosaic == a)
        points.append(TradeoffPoint(r["algorithm"] if not r["half_size"] else "half size (no demosaic)",
                                    r["ms_per_mp"], r["psnr_db"], presets=presets,
                                    baseline_seconds=r.get("baseline_ms_per_mp")))
    return [Tradeoff("decode", "decode.demosaic, decode.half_size", "ms per raw megapixel",
                     "PSNR against the known image (dB)", tuple(points), "bench_decode", higher_is_better=True,
                     notes=("Half-size decodes are scored against the 2x2 block average of the truth. The baseline "
                            "is rawpy's default call (`postprocess()`, AHD to 8-bit) on the same file.",))]


def photometric_tradeoffs(out: Path) -> list[Tradeoff]:
    result = []
    light = _load(out, "bench_light")
    if light and "correction_timing" in light:
        timing = light["correction_timing"]
        per_mp = 1e6 / timing["pixels"]
        heldout = light["levels"][-1]["sphere_heldout_deg"]["uncorrected"]
        points = [TradeoffPoint("no light model (normalize)", timing["normalize_s"] * per_mp * 1e3, heldout,
                                presets=_presets_where(lambda c: not c.lights.enabled),
                                baseline_seconds=timing["normalize_s"] * per_mp * 1e3)]
        iterations = sorted(int(k.split("_")[2]) for k in timing if k.startswith("gauss_newton_") and k.endswith("_s"))
        for it in iterations:
            points.append(TradeoffPoint(f"light model, {it} Gauss-Newton iterations",
                                        timing[f"gauss_newton_{it}_s"] * per_mp * 1e3,
                                        timing[f"gauss_newton_{it}_heldout_deg"],
                                        presets=_presets_where(lambda c, it=it: c.lights.enabled
                                                               and c.photometric.light_iterations == it),
                                        baseline_seconds=timing["normalize_s"] * per_mp * 1e3))
        result.append(Tradeoff("photometric", "lights.enabled, photometric.light_iterations",
                               "ms per megapixel of ratios", "held-out sphere normal error (deg)", tuple(points),
                               "bench_light", notes=(
                                   f"Error on the held-out cameras' sphere pixels at the highest LED error level "
                                   f"({light['levels'][-1]['led_error']}); the baseline is the plain normalize.",)))
    spec = _load(out, "bench_specular_normals")
    if spec:
        from stages.numerics.specular_normals import SpecularConfig

        fit = SpecularConfig()
        seed = next(k for k in spec if k.startswith("seed"))
        rows = spec[seed]
        eq1 = rows["eq1"]["seconds_per_10k_px"]
        points = []
        for name, r in rows.items():
            if name in ("fit oracle r", "fit per-pixel r"):
                continue  # an oracle and a variant the stage cannot be set to
            is_stage = name == f"fit r={fit.roughness}"
            points.append(TradeoffPoint(name, r["seconds_per_10k_px"], r["mean_deg"],
                                        presets=_presets_where(lambda c: c.diffuse_normals.fit == fit) if is_stage
                                        else (), baseline_seconds=eq1))
        result.append(Tradeoff("diffuse_normals (specular fit)", "diffuse_normals.fit: roughness prior, solver, steps",
                               "seconds per 10k pixels", "normal error against the truth (deg)", tuple(points),
                               "bench_specular_normals", notes=(
                                   "The baseline is eq. 1's ratio (the `eq1` row), timed in the same process. The "
                                   "preset rows are the stage's one-prior fit; the release fits each pixel with the "
                                   "materials stage's roughness (bench_diffuse_normals).",)))
    diffuse = _load(out, "bench_diffuse_normals")
    if diffuse and diffuse.get("occlusion_directions"):
        points = []
        for n, r in diffuse["occlusion_directions"].items():
            points.append(TradeoffPoint(f"{n} directions", r["deocclusion_s_per_camera"], r["mean_deg"],
                                        presets=_presets_where(lambda c, n=int(n):
                                                               c.diffuse_normals.occlusion_directions == n)))
        result.append(Tradeoff("diffuse_normals (de-occlusion)", "diffuse_normals.occlusion_directions",
                               "seconds per camera", "normal error against the truth (deg)", tuple(points),
                               "bench_diffuse_normals"))
    return result


def calibration_tradeoffs(out: Path) -> list[Tradeoff]:
    data = _load(out, "bench_calibration")
    if not data or "rows" not in data:
        return []
    default_size = data.get("default_max_image_size")
    points = []
    for r in data["rows"]:
        if "rotation_deg_mean" not in r:
            continue  # too few cameras registered to align
        full = max(r["image_size"])
        effective = full if r["max_image_size"] < 0 else min(r["max_image_size"], full)
        label = "full size" if r["max_image_size"] < 0 else f"{r['max_image_size']} px"
        presets = _presets_where(lambda c, m=r["mode"], e=effective, f=full:
                                 min(c.cameras.geometric.max_image_size, f) == e
                                 and (m == "refined") == c.cameras.geometric.refine_focal_length)
        points.append(TradeoffPoint(label, r["seconds"], r["rotation_deg_mean"], series=r["mode"], presets=presets))
    if not points:
        return []
    return [Tradeoff("cameras (structure from motion)", "cameras.geometric.max_image_size", "seconds (32 cameras)",
                     "rotation error (deg, mean)", tuple(points), "bench_calibration", notes=(
                         f"SIFT extraction resolution of `cameras: {{source: colmap}}` (stage default "
                         f"{default_size} px); the default source calibrates from the marker frames.",
                         "Centre errors per row are in bench_calibration's JSON."))]


def markers_tradeoffs(out: Path) -> list[Tradeoff]:
    """The cameras stage's default source (marker frames): its variants' time against the stage-frame centre
    error, per simulated width, the baseline being the decode of the marker frames."""
    data = _load(out, "bench_calibration_markers")
    if not data or "rows" not in data:
        return []
    from calibration.markers import MarkerCalibrationConfig

    variants = {"markers": MarkerCalibrationConfig(), "markers_rig_frame": MarkerCalibrationConfig(frame="rig"),
                "markers_fixed_focal": MarkerCalibrationConfig(refine_focal_length=False)}
    points, references = [], []
    for r in data["rows"]:
        if r["method"] in variants:
            presets = _presets_where(lambda c, v=variants[r["method"]]: c.cameras.source in ("auto", "markers")
                                     and c.cameras.markers == v)
            points.append(TradeoffPoint(r["method"], r["seconds"], r["centre_mm_mean"], series=f"{r['width']} px",
                                        presets=presets, baseline_seconds=r.get("decode_s")))
        else:
            references.append(f"{r['method']} {r['centre_mm_mean']:.2f} mm at {r['width']} px")
    if not points:
        return []
    return [Tradeoff("cameras (marker frames)", "cameras.markers (frame, refine_focal_length)",
                     "seconds (32 cameras, decode included)", "camera centre error (mm, stage frame, mean)",
                     tuple(points), "bench_calibration_markers", notes=(
                         "The baseline is the decode of the 32 marker frames, timed in the same process; without "
                         "calibration (no time): " + "; ".join(references) + " (`floor_nominal_gauge`: the best any "
                         "calibration aligned to the rig spec's centres can do).",))]


def geometry_tradeoffs(out: Path) -> list[Tradeoff]:
    result = []
    schedule = _load(out, "bench_sdf_schedule")
    if schedule and schedule.get("rows"):
        points = [TradeoffPoint(f"{r['first_pass']}+{r['second_pass']} steps", r["cpu_s"], r["chamfer_mm"],
                                presets=_presets_where(lambda c, r=r: (c.geometry.first_pass_iterations or 0)
                                                       == r["first_pass"]
                                                       and c.geometry.sdf.iterations == r["second_pass"]
                                                       and c.geometry.sdf == _default_sdf()))
                  for r in schedule["rows"]]
        result.append(Tradeoff("geometry (SDF passes)", "geometry.first_pass_iterations, geometry.sdf.iterations",
                               "stage CPU seconds (one thread)", "Chamfer (mm)", tuple(points), "bench_sdf_schedule",
                               notes=("Two seeds of one schedule differ by about 0.05 mm: smaller differences are "
                                      "noise. The production preset (GPU, 20,000 steps of 4096 rays) is not on this "
                                      "CPU sweep.",)))
    geometry = _load(out, "bench_geometry")
    if geometry:
        curve = geometry.get("curves", {}).get("normal_supervised", [])
        if curve:
            points = tuple(TradeoffPoint(f"{p['iteration']} steps", p["train_seconds"], p["chamfer_mm"],
                                         series="one pass") for p in curve)
            points += tuple(TradeoffPoint(f"{p['iteration']} steps", p["train_seconds"], p["chamfer_mm"],
                                          series="second pass, de-occluded")
                            for p in geometry["curves"].get("deoccluded_second_pass", []))
            result.append(Tradeoff("geometry (SDF training)", "geometry.sdf.iterations (checkpoints of one run)",
                                   "training seconds (one thread)", "Chamfer (mm)", points, "bench_geometry",
                                   notes=(f"SDF preset `{geometry.get('preset')}`; the second pass's clock starts "
                                          "after the first pass and the de-occlusion.",)))
        marching = geometry.get("marching", [])
        if marching:
            points = tuple(TradeoffPoint(f"{m['resolution']}^3", m["seconds"], m["chamfer_mm"],
                                         presets=_presets_where(lambda c, m=m: c.geometry.mesh_resolution
                                                                == m["resolution"]))
                           for m in marching)
            result.append(Tradeoff("geometry (marching)", "geometry.mesh_resolution", "mesh extraction seconds",
                                   "Chamfer (mm)", points, "bench_geometry",
                                   notes=("The first pass's final field meshed at each resolution; the production "
                                          "preset's resolution is marked only when swept.",)))
    return result


def _default_sdf():
    from stages.geometry import GeometryConfig

    return GeometryConfig().sdf


def textures_tradeoffs(out: Path) -> list[Tradeoff]:
    data = _load(out, "bench_textures")
    if not data:
        return []
    base = data.get("baseline_undecimated")
    points = tuple(TradeoffPoint(f"{r['atlas_faces']} faces" + (f", charts <= {r['max_chart_area_m2']:g} m^2"
                                                                if r.get("max_chart_area_m2") else ""),
                                 r["cpu_s"], r["albedo_psnr_db"],
                                 presets=_presets_where(lambda c, r=r: c.textures.atlas_faces == r["atlas_faces"]
                                                        and c.textures.atlas_max_chart_area_m2
                                                        == r.get("max_chart_area_m2", 0.0)),
                                 baseline_seconds=base["cpu_s"] if base else None)
                   for r in data["rows"])
    baseline = (f" The baseline is the stage on the undecimated mesh ({base['faces']} faces)." if base else
                " Run without its baseline (the undecimated mesh: `make bench-full`).")
    return [Tradeoff("textures", "textures.atlas_faces, atlas_max_chart_area_m2", "stage CPU seconds",
                     "albedo texture PSNR (dB)", points,
                     "bench_textures", higher_is_better=True, notes=(
                         f"At the default texture size ({data['texture_size']}^2; production bakes "
                         f"4096^2).{baseline}",))]


def relight_tradeoffs(out: Path) -> list[Tradeoff]:
    result = []
    relight = _load(out, "bench_relight")
    if relight and "summary" in relight:
        variants = relight["summary"]["variants"]
        default_lobes = relight["defaults"]["lobes"]
        baseline = variants.get("shadows off, photometric albedo (baseline)", {}).get("seconds_per_view")
        points = []
        for name, v in variants.items():
            lobes = default_lobes if name == "default" else (int(name.split()[1]) if name.startswith("sg_lobes ")
                                                             else None)
            if lobes is None:
                continue
            points.append(TradeoffPoint(f"{lobes} lobes", v["seconds_per_view"], v["psnr_db"],
                                        presets=_presets_where(lambda c, n=lobes: c.relight.sg_lobes == n),
                                        baseline_seconds=baseline))
        result.append(Tradeoff("relight", "relight.sg_lobes", "seconds per novel view (3 environments)",
                               "relit PSNR against the simulator (dB)", tuple(points), "bench_relight",
                               higher_is_better=True, notes=(
                                   "The baseline is the simplest variant (no shadows, photometric albedo) in the "
                                   "same process. The production preset also shades 6 novel views at a larger SG "
                                   "fit; only its lobe count is this row.",)))
    sg = _load(out, "bench_sg")
    if sg and sg.get("summary_by_lobes"):
        points = tuple(TradeoffPoint(f"{n} lobes", s["median_fit_s"], s["median_irradiance_rel_l2"],
                                     presets=_presets_where(lambda c, n=int(n): c.relight.sg_lobes == n),
                                     baseline_seconds=s["median_fit_s"] / s["median_x_sh_projection"]
                                     if s.get("median_x_sh_projection") else None)
                       for n, s in sg["summary_by_lobes"].items())
        result.append(Tradeoff("relight (SG fit)", "relight.sg_lobes", "fit seconds per map (median)",
                               "irradiance relative L2 (median over maps)", points, "bench_sg",
                               notes=("The baseline is the map's order-2 SH projection, timed in the same process.",)))
    return result


EXTRACTORS: tuple[Callable[[Path], list[Tradeoff]], ...] = (
    decode_tradeoffs, photometric_tradeoffs, calibration_tradeoffs, markers_tradeoffs, geometry_tradeoffs,
    textures_tradeoffs, relight_tradeoffs)
"""In pipeline order."""


def all_tradeoffs(out: Path) -> list[Tradeoff]:
    """Every stage's trade-offs found under ``out``; an extractor that fails on a bench's JSON (an older layout) is
    reported as a note rather than stopping the report."""
    found = []
    for extract in EXTRACTORS:
        try:
            found += extract(Path(out))
        except (KeyError, TypeError, ValueError, IndexError, StopIteration) as err:
            found.append(Tradeoff(extract.__name__.removesuffix("_tradeoffs"), "", "", "", (), "",
                                  notes=(f"could not read its bench's rows: {type(err).__name__}: {err}",)))
    return found


def report_section(out: Path) -> list[str]:
    """The report's "time against error" section: per trade-off a table and a plot (PNG written under ``out``)."""
    lines = ["## Time against error, per stage", "",
             "Each stage's quality knobs, swept by the bench named under each table: time against the stage's error "
             "measure, the Pareto front marked (`Pareto`: no other setting is both faster and at least as accurate) "
             "and the presets' points named (rings on the plots: the default preset black, production red). Times "
             "were taken on a shared machine: the `x baseline` column (a simple baseline timed in the same process) "
             "is the figure that transfers.", ""]
    for k, tradeoff in enumerate(all_tradeoffs(out)):
        lines += [f"### {tradeoff.stage}: {tradeoff.knobs or 'not available'}", ""]
        if not tradeoff.points:
            lines += [f"- {n}" for n in tradeoff.notes] + [""]
            continue
        lines += [f"From {tradeoff.source}.", "", *tradeoff_table(tradeoff), ""]
        name = f"tradeoff_{k:02d}_{tradeoff.source.removeprefix('bench_')}.png"
        tradeoff_plot(tradeoff, Path(out) / name)
        lines += [f"![{tradeoff.stage}]({name})", ""]
    return lines
