"""``RELEASE/index.html``: a static page that shows a release in any browser, offline (no server, nothing
fetched from the internet: the CSS and the few lines of script are inline, every picture is a file of the
release).

It reads the release's manifests and files and writes:

- ``index.html``: the summary (counts, failed actions and why, accuracy from ``metrics_summary`` and
  ``metrics``), a card per published action (labelled thumbnails of every camera's maps linking to the
  files, relit novel views per environment, the mesh as a turntable, the plots, every file), and the
  relighting set when ``relight_examples`` exists;
- ``page/<action_id>/<kind>_<camera>.png``: the thumbnails of the EXR maps (browsers do not show EXR).

Both are registered in the assets table (kinds ``page`` and ``page_thumbnail``), so ``ultrastage verify``
covers them. Thumbnails are made again only when their source is newer.
"""
from __future__ import annotations

import html
import json
import os
import shutil
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

PAGE = "index.html"
THUMBNAIL_DIR = "page"
THUMBNAIL_WIDTH = 128
"""Width in pixels of a thumbnail (the height keeps the map's aspect)."""

#: Per-camera maps shown on an action's card, in this order: (asset kind, row title).
CAMERA_MAPS = (("full_on", "image, white light (full_on)"), ("pos", "image, gradient g+ (pos)"),
               ("neg", "image, gradient g- (neg)"), ("normal_alpha", "normals, eq. 1 (normal_alpha)"),
               ("normal_diffuse", "normals, specular fitted out (normal_diffuse)"),
               ("albedo", "albedo, white light (albedo)"), ("albedo_diffuse", "albedo, specular out (albedo_diffuse)"),
               ("mask", "mask"))
#: G-buffer maps of a novel view shown before its relit images: (asset kind, label).
RENDER_MAPS = (("render_normal", "normal"), ("render_albedo", "albedo"))
#: Summary metrics shown first in the accuracy table, in this order (the rest follow by name).
HEADLINE_METRICS = ("normal_mean_deg", "normal_median_deg", "normal_mean_deg_diffuse", "valid_fraction",
                    "albedo_psnr_db", "albedo_psnr_db_diffuse", "albedo_ssim", "mask_iou", "chamfer_mm",
                    "normal_consistency", "heldout_albedo_psnr_db", "heldout_normal_mean_deg", "roughness_mae",
                    "relit_psnr_db", "relit_normal_mean_deg", "cam_rotation_err_deg", "cam_center_err_mm")


# ----------------------------------------------------------------------------------------------------
# thumbnails (pure picture functions, then the files)


def thumbnail_picture(kind: str, data: np.ndarray, width: int = THUMBNAIL_WIDTH) -> np.ndarray:
    """uint8 (h, width, 3) sRGB picture of a map for the page.

    Args:
        kind: the asset kind: images ('full_on', 'pos', 'neg', 'relit_*': exposed so the 99th percentile is
            near white), normals ('normal_alpha', 'normal_diffuse', 'render_normal': (n + 1) / 2, black where
            alpha <= 0.5), albedo ('albedo*', 'render_albedo': as it is) or a mask.
        data: the map as loaded, float (H, W[, C]) or uint8.
    """
    from pipeline.codecs.image import preview_linear, preview_normals

    data = np.asarray(data)
    if kind in ("normal_alpha", "normal_diffuse", "render_normal"):
        alpha = data[..., 3] if data.shape[-1] > 3 else np.any(data[..., :3] != 0, axis=-1).astype(np.float32)
        pic = preview_normals(data[..., :3], alpha)
    elif data.dtype == np.uint8:
        pic = data if data.ndim == 3 else np.repeat(data[..., None], 3, axis=2)
        pic = pic[..., :3]
    elif kind.startswith("albedo") or kind == "render_albedo":
        return preview_linear(_resize_linear(data[..., :3], width), exposure=1.0)
    else:  # linear radiance of an unknown scale, exposed by the whole map's 99th percentile
        rgb = data[..., :3] if data.ndim == 3 else np.repeat(data[..., None], 3, axis=2)
        rgb = np.nan_to_num(np.asarray(rgb, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        p99 = float(np.percentile(rgb, 99)) if rgb.size else 1.0
        return preview_linear(_resize_linear(rgb, width), exposure=0.9 / p99 if p99 > 0 else 1.0)
    return _resize(pic, width)


def _resize_linear(rgb: np.ndarray, width: int) -> np.ndarray:
    """A float (H, W, 3) linear map box-filtered to ``width`` (as :func:`_resize`): averaged in linear light, then
    encoded once at the thumbnail's size (a tenth of the pixels to encode)."""
    from PIL import Image

    rgb = np.nan_to_num(np.asarray(rgb, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    h, w = rgb.shape[:2]
    if w <= width:
        return rgb
    size = (width, max(1, round(h * width / w)))
    return np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(rgb[..., c])).resize(
        size, Image.Resampling.BOX)) for c in range(rgb.shape[2])], axis=-1)


def _resize(picture: np.ndarray, width: int) -> np.ndarray:
    from PIL import Image

    h, w = picture.shape[:2]
    if w <= width:
        return np.ascontiguousarray(picture)
    height = max(1, round(h * width / w))
    return np.asarray(Image.fromarray(np.ascontiguousarray(picture)).resize((width, height), Image.Resampling.BOX))


def _fresh(target: Path, source: Path) -> bool:
    """Whether ``target`` exists and is no older than ``source`` (published files keep the mtime they were
    written with, so a changed map is newer than its thumbnail)."""
    return target.is_file() and target.stat().st_mtime >= source.stat().st_mtime


def _write_thumbnail(root: Path, rel_source: str, kind: str, out_rel: str) -> None:
    from manifests.consumer import load_file
    from pipeline.codecs.image import write_png

    source, target = root / rel_source, root / out_rel
    if _fresh(target, source):
        return
    write_png(target, thumbnail_picture(kind, load_file(source)))


# ----------------------------------------------------------------------------------------------------
# what the page shows (plain data gathered from the manifests)


def _esc(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _href(rel: str) -> str:
    """A release-relative posix path as a URL path (each segment percent-encoded)."""
    from urllib.parse import quote

    return "/".join(quote(part) for part in rel.split("/"))


def _format_value(value: float, unit: str) -> str:
    if unit == "count":
        return f"{value:.0f}"
    magnitude = abs(value)
    digits = 4 if magnitude < 1 else (3 if magnitude < 10 else 2)
    return f"{value:.{digits}f}"


def _size(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} B"


def accuracy_rows(summary: list[dict], metrics: list[dict], action_ids: list[str]) -> list[dict]:
    """The accuracy table: one row per evaluated metric with its release value (metrics_summary) and, per
    action, the mean of its rows in metrics (source 'evaluate'; a per-camera metric is averaged over cameras,
    a per-environment one over environments).

    Returns:
        dicts ``{metric, unit, aggregation, release (float | None), per_action {action_id: float}}``, the
        headline metrics first, then by name.
    """
    by_metric: dict[str, dict] = {}
    for row in summary:
        by_metric[row["metric"]] = {"metric": row["metric"], "unit": row["unit"], "aggregation": row["aggregation"],
                                    "release": row["value"], "per_action": {}}
    sums: dict[tuple[str, str], list[float]] = {}
    for row in metrics:
        if row["source"] != "evaluate":
            continue
        sums.setdefault((row["metric"], row["action_id"]), []).append(row["value"])
        by_metric.setdefault(row["metric"], {"metric": row["metric"], "unit": row["unit"], "aggregation": "",
                                             "release": None, "per_action": {}})
    for (metric, action_id), values in sums.items():
        if action_id in action_ids:
            by_metric[metric]["per_action"][action_id] = float(np.mean(values))
    order = {m: i for i, m in enumerate(HEADLINE_METRICS)}
    return sorted(by_metric.values(), key=lambda r: (order.get(r["metric"], len(order)), r["metric"]))


# ----------------------------------------------------------------------------------------------------
# HTML


_CSS = """
:root { --fg: #1d232b; --muted: #5b6675; --line: #d9dee5; --card: #ffffff; --bg: #f3f5f8; --accent: #2a5db0;
        --bad: #b3261e; --ok: #1e7b34; }
* { box-sizing: border-box; }
body { margin: 0; font: 14px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif;
       color: var(--fg); background: var(--bg); }
header { background: #1d2733; color: #fff; padding: 18px 28px; }
header h1 { margin: 0 0 4px; font-size: 22px; font-weight: 600; }
header p { margin: 0; color: #c7d0db; }
main { padding: 18px 28px 40px; max-width: 1400px; }
section, article { background: var(--card); border: 1px solid var(--line); border-radius: 8px; padding: 14px 18px;
                   margin: 0 0 18px; }
h2 { font-size: 18px; margin: 0 0 10px; } h3 { font-size: 15px; margin: 16px 0 6px; }
a { color: var(--accent); text-decoration: none; } a:hover { text-decoration: underline; }
.counts { display: flex; flex-wrap: wrap; gap: 10px; margin: 0; padding: 0; list-style: none; }
.counts li { border: 1px solid var(--line); border-radius: 6px; padding: 6px 12px; background: #fafbfc; }
.counts b { display: block; font-size: 18px; }
table { border-collapse: collapse; font-size: 13px; }
th, td { border-bottom: 1px solid var(--line); padding: 3px 10px; text-align: left; vertical-align: top; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
.muted { color: var(--muted); } .bad { color: var(--bad); } .ok { color: var(--ok); }
.strip { display: flex; gap: 6px; overflow-x: auto; padding-bottom: 6px; }
figure { margin: 0; flex: none; text-align: center; width: 112px; }
figure img { display: block; width: 112px; height: auto; background: #000; border-radius: 3px; }
.plots figure, .meshrow figure { width: auto; }
figcaption { font-size: 11px; line-height: 1.25; color: var(--muted); overflow-wrap: anywhere; padding-top: 2px; }
.rowtitle { margin-top: 8px; font-weight: 600; font-size: 12px; color: var(--muted); }
.plots { display: flex; flex-wrap: wrap; gap: 12px; }
.plots img { max-width: 420px; max-height: 320px; border: 1px solid var(--line); }
.turntable { width: 200px; height: 300px; background-repeat: no-repeat; border: 1px solid var(--line);
             border-radius: 4px; background-color: #fff; }
.meshrow { display: flex; gap: 18px; align-items: flex-start; flex-wrap: wrap; }
details table { margin-top: 6px; }
details summary { cursor: pointer; color: var(--accent); }
.files { columns: 3 260px; font-size: 12px; margin: 6px 0 0; padding-left: 18px; }
code { background: #eef1f5; padding: 1px 4px; border-radius: 3px; }
"""

# Errors of the page's own script are shown on the page (and read back by the browser test).
_SCRIPT = """
window.addEventListener('error', function (e) {
  var box = document.getElementById('page-errors');
  box.hidden = false; box.textContent += (e.message || 'error') + '\\n';
});
document.querySelectorAll('[data-turntable]').forEach(function (box) {
  var frames = parseInt(box.dataset.frames, 10), view = box.querySelector('.turntable');
  var slider = box.querySelector('input'), frame = 0, timer = null;
  function show(i) { frame = (i + frames) % frames; slider.value = frame;
    view.style.backgroundPosition = (frames > 1 ? 100 * frame / (frames - 1) : 0) + '% 0'; }
  function play() { timer = setInterval(function () { show(frame + 1); }, 250); }
  slider.addEventListener('input', function () { clearInterval(timer); timer = null; show(parseInt(slider.value, 10)); });
  view.addEventListener('click', function () { if (timer) { clearInterval(timer); timer = null; } else { play(); } });
  show(0); play();
});
"""


def _figure(href: str, src: str, caption: str, wide: bool = False) -> str:
    cls = ' class="wide"' if wide else ""
    return (f'<figure{cls}><a href="{_href(href)}"><img loading="lazy" src="{_href(src)}" alt="{_esc(caption)}">'
            f'</a><figcaption>{_esc(caption)}</figcaption></figure>')


def _table(head: Iterable[str], rows: Iterable[Iterable[str]]) -> str:
    out = ["<table><thead><tr>", *(f"<th>{h}</th>" for h in head), "</tr></thead><tbody>"]
    for row in rows:
        out.append("<tr>" + "".join(row) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _accuracy_html(rows: list[dict], action_ids: list[str]) -> str:
    if not rows:
        return ('<p class="muted">Not evaluated: no accuracy against ground truth in manifests/metrics.parquet '
                '(run <code>ultrastage evaluate</code> with the capture\'s ground truth).</p>')
    headline = [r for r in rows if r["metric"] in HEADLINE_METRICS]
    rest = [r for r in rows if r["metric"] not in HEADLINE_METRICS]
    if not headline:
        headline, rest = rows, []
    out = _metric_table(headline, action_ids)
    if rest:
        out += f"<details><summary>The other {len(rest)} metrics</summary>{_metric_table(rest, action_ids)}</details>"
    return out


def _metric_table(rows: list[dict], action_ids: list[str]) -> str:
    body = []
    for r in rows:
        cells = [f"<td><code>{_esc(r['metric'])}</code></td>", f"<td>{_esc(r['unit'])}</td>",
                 f"<td class=\"num\">{_format_value(r['release'], r['unit']) if r['release'] is not None else ''}</td>"]
        cells += [f"<td class=\"num\">{_format_value(r['per_action'][a], r['unit']) if a in r['per_action'] else ''}</td>"
                  for a in action_ids]
        cells.append(f"<td class=\"muted\">{_esc(r['aggregation'].replace('_', ' '))}</td>")
        body.append(cells)
    return _table(["metric", "unit", "release", *(_esc(a) for a in action_ids), "release value is"], body)


class _Action:
    """The assets of one action, by (kind, camera), as the page needs them."""

    def __init__(self, action: dict, assets: list[dict]):
        self.info = action
        self.id = action["action_id"]
        self.assets = sorted(assets, key=lambda r: r["path"])
        self.by_kind: dict[tuple[str, str | None], dict] = {(r["kind"], r["camera_id"]): r for r in assets}

    def cameras(self, kind: str) -> list[str]:
        return sorted(c for (k, c) in self.by_kind if k == kind and c is not None)


def _thumb_rel(action_id: str, kind: str, camera: str | None) -> str:
    return f"{THUMBNAIL_DIR}/{action_id}/{kind}_{camera or 'action'}.png"


def _action_card(root: Path, action: _Action, make_thumb: Callable[[str, str, str], str]) -> str:
    a = action.info
    parts = [f'<article id="action-{_esc(action.id)}"><h2>Action {_esc(action.id)} '
             f'<span class="ok">published</span></h2>',
             f'<p class="muted">subject {_esc(a["subject"])} · session {_esc(a["session_id"])} · '
             f'{a["n_cameras"]} cameras · maps {a["width"]} × {a["height"]} px · {a["stages_run"]} stage task(s) ran, '
             f'{a["stages_cached"]} cached</p>']
    links = [(kind, label) for kind, label in (("transforms", "transforms.json"), ("mesh", "mesh (PLY)"),
                                                ("mesh_textured", "textured mesh (OBJ)"), ("calibration", "calibration"))
             if (kind, None) in action.by_kind]
    if links:
        parts.append("<p>" + " · ".join(f'<a href="{_href(action.by_kind[(k, None)]["path"])}">{_esc(label)}</a>'
                                         for k, label in links) + "</p>")

    turntable = action.by_kind.get(("preview_turntable", None))
    if turntable is not None or ("mesh", None) in action.by_kind:
        parts.append("<h3>Mesh</h3><div class=\"meshrow\">")
        if turntable is not None:
            from PIL import Image

            with Image.open(root / turntable["path"]) as im:
                w, h = im.size
            frames = max(1, round(w / (h * 2 / 3)))
            parts.append(f'<div data-turntable data-frames="{frames}"><div class="turntable" role="img" '
                         f'aria-label="turntable of the textured mesh" style="background-image:url(\'{_href(turntable["path"])}\');'
                         f'background-size:{frames * 100}% 100%"></div><input type="range" min="0" max="{frames - 1}" '
                         f'value="0" aria-label="turntable angle" style="width:200px"><div class="muted" '
                         f'style="font-size:11px">textured mesh, {frames} views; click to pause</div></div>')
        shown = [(k, t) for k, t in (("preview_mesh_normals", "mesh normals against the photometric normals"),
                                     ("texture_albedo_preview", "albedo texture")) if (k, None) in action.by_kind]
        for kind, title in shown:
            path = action.by_kind[(kind, None)]["path"]
            parts.append(f'<figure><a href="{_href(path)}"><img src="{_href(path)}" alt="{_esc(title)}" '
                         f'style="width:auto;max-height:150px"></a><figcaption>{_esc(title)}</figcaption></figure>')
        parts.append("</div>")

    parts.append("<h3>Cameras</h3>")
    for kind, title in CAMERA_MAPS:
        cams = action.cameras(kind)
        if not cams:
            continue
        figs = []
        for cam in cams:
            asset = action.by_kind[(kind, cam)]
            figs.append(_figure(asset["path"], make_thumb(asset["path"], kind, _thumb_rel(action.id, kind, cam)),
                                f"cam {cam} · {kind}"))
        parts.append(f'<div class="rowtitle">{_esc(title)}</div><div class="strip">{"".join(figs)}</div>')

    views = sorted({c for (k, c) in action.by_kind if k.startswith("relit_") and c is not None})
    if views:
        parts.append("<h3>Relit novel views</h3>")
        environments = sorted({k[len("relit_"):] for (k, c) in action.by_kind if k.startswith("relit_") and c})
        for view in views:
            figs = []
            for kind, label in RENDER_MAPS:
                asset = action.by_kind.get((kind, view))
                if asset is not None:
                    figs.append(_figure(asset["path"], make_thumb(asset["path"], kind, _thumb_rel(action.id, kind, view)),
                                        f"view {view} · {label}"))
            for env in environments:
                asset = action.by_kind.get((f"relit_{env}", view))
                if asset is not None:
                    kind = f"relit_{env}"
                    figs.append(_figure(asset["path"], make_thumb(asset["path"], kind, _thumb_rel(action.id, kind, view)),
                                        f"view {view} · {env}"))
            parts.append(f'<div class="strip">{"".join(figs)}</div>')

    plots = [r for r in action.assets if r["media_type"] == "image/png" and r["path"].split("/")[2:3] == ["previews"]
             and r["kind"] != "preview_turntable"]
    if plots:
        parts.append("<h3>Plots and previews</h3><div class=\"plots\">")
        for r in plots:
            name = r["path"].rsplit("/", 1)[-1]
            parts.append(f'<figure><a href="{_href(r["path"])}"><img loading="lazy" src="{_href(r["path"])}" '
                         f'alt="{_esc(name)}" style="width:auto"></a><figcaption>{_esc(name)}</figcaption></figure>')
        parts.append("</div>")

    files = "".join(f'<li><a href="{_href(r["path"])}">{_esc(r["path"].split("/", 2)[-1])}</a> '
                    f'<span class="muted">{_esc(r["kind"])}, {_size(r["bytes"])}</span></li>'
                    for r in action.assets if not r["path"].startswith(THUMBNAIL_DIR + "/"))
    parts.append(f"<details><summary>All {sum(not r['path'].startswith(THUMBNAIL_DIR + '/') for r in action.assets)} "
                 f"files of the action</summary><ul class=\"files\">{files}</ul></details></article>")
    return "".join(parts)


def _relight_section(examples: list[dict], limit: int = 24) -> str:
    if not examples:
        return ""
    by_split: dict[str, int] = {}
    for e in examples:
        by_split[e["split"]] = by_split.get(e["split"], 0) + 1
    shown = sorted(examples, key=lambda e: (e["split"], e["example_id"]))[:limit]
    figs = []
    for e in shown:
        label = f"{e['example_id']} · {e['split']} · {e['environment_name']}"
        tiles = "".join(_figure(e[col], e[col], f"{what}") for col, what in
                        (("image_png", "image"), ("albedo_png", "albedo"), ("normal_png", "normal (camera)")))
        figs.append(f'<div><div class="strip">{tiles}</div><div class="muted" style="font-size:12px">{_esc(label)}</div></div>')
    counts = ", ".join(f"{n} {s}" for s, n in sorted(by_split.items()))
    return (f'<section id="relighting-set"><h2>Relighting set</h2><p>{len(examples)} examples ({_esc(counts)}); '
            f'index <a href="manifests/relight_examples.parquet">manifests/relight_examples.parquet</a>. '
            f'{"The first " + str(limit) + " by split and id:" if len(examples) > limit else ""}</p>'
            f'<div class="plots">{"".join(figs)}</div></section>')


def page_html(root: Path, actions: list[dict], assets: list[dict], summary: list[dict], metrics: list[dict],
              examples: list[dict], run: dict, make_thumb: Callable[[str, str, str], str]) -> str:
    """The page's HTML from the release's manifest rows (``make_thumb(source_rel, kind, out_rel)`` returns the
    release-relative path of a thumbnail it made)."""
    from manifests.schemas import SCHEMA_VERSION

    ok = [a for a in actions if a["status"] == "ok"]
    failed = [a for a in actions if a["status"] != "ok"]
    ok_ids = [a["action_id"] for a in ok]
    total = sum(r["bytes"] for r in assets)
    counts = [("actions published", len(ok)), ("actions failed", len(failed)),
              ("camera views", sum(a["n_cameras"] for a in ok)),
              ("files", len(assets)), ("size", _size(total))]
    if examples:
        counts.append(("relighting examples", len(examples)))
    docs = "".join(f' · <a style="color:#9cc2ff" href="{name}">{name}</a>'
                   for name in ("CONVENTIONS.md", "DATASHEET.md", "config.yaml") if (root / name).is_file())
    head = (f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><meta name=\"viewport\" "
            f"content=\"width=device-width, initial-scale=1\"><title>UltraStage release {_esc(root.name)}</title>"
            f"<style>{_CSS}</style></head><body><header><h1>UltraStage release <code style=\"background:none;"
            f"color:#fff\">{_esc(root.name)}</code></h1><p>run {_esc(run.get('run_id', 'unknown'))} · preset "
            f"{_esc(run.get('preset', 'unknown'))} · manifest schema {SCHEMA_VERSION}{docs}</p></header><main>"
            f"<pre id=\"page-errors\" class=\"bad\" hidden></pre>")
    parts = [head, "<section id=\"summary\"><h2>Summary</h2><ul class=\"counts\">",
             *(f"<li><b>{_esc(v)}</b>{_esc(k)}</li>" for k, v in counts), "</ul>"]
    if failed:
        parts.append("<h3 class=\"bad\">Failed actions</h3>")
        parts.append(_table(["action", "subject", "why"], [
            [f"<td>{_esc(a['action_id'])}</td>", f"<td>{_esc(a['subject'])}</td>",
             f"<td class=\"bad\">{_esc(a['error'] or 'failed')}</td>"] for a in failed]))
    if ok:
        parts.append("<p>Published: " + ", ".join(f'<a href="#action-{_esc(i)}">{_esc(i)}</a>' for i in ok_ids) + "</p>")
    parts.append("<p class=\"muted\">Check every file against its SHA-256 with <code>ultrastage verify RELEASE</code>; "
                 "load the manifests with <code>manifests.open_release(RELEASE)</code>, pandas or duckdb "
                 "(their digests: <a href=\"manifests/index.json\">manifests/index.json</a>).</p></section>")
    parts.append("<section id=\"accuracy\"><h2>Accuracy against ground truth</h2><p class=\"muted\">The release "
                 "column is <code>manifests/metrics_summary.parquet</code>; an action's column is the mean of its rows "
                 "in <code>manifests/metrics.parquet</code> (over its cameras, novel views or environments).</p>")
    parts.append(_accuracy_html(accuracy_rows(summary, metrics, ok_ids), ok_ids))
    parts.append("</section>")
    by_action: dict[str, list[dict]] = {}
    for r in assets:
        if r["action_id"] is not None:
            by_action.setdefault(r["action_id"], []).append(r)
    for a in ok:
        parts.append(_action_card(root, _Action(a, by_action.get(a["action_id"], [])), make_thumb))
    parts.append(_relight_section(examples))
    parts.append(f"</main><script>{_SCRIPT}</script></body></html>\n")
    return "".join(parts)


# ----------------------------------------------------------------------------------------------------
# the action: read the release, write the page and its thumbnails, register them


def write_release_page(release: str | Path, threads: int | None = None) -> Path:
    """Write ``RELEASE/index.html`` and the thumbnails it shows, and list them in the assets table (rows of
    kind 'page' and 'page_thumbnail' replace the previous page's). ``threads``: the thumbnails' thread pool (default
    one per core, at most 8; bench/bench_page.py times it against 1).

    Returns:
        The path of index.html.

    Raises:
        ReleaseError: the folder holds no manifests.
        ValueError: ``threads`` is not an integer >= 1.
    """
    from manifests.consumer import open_release
    from manifests.writer import asset_row, replace_rows

    if threads is not None and (isinstance(threads, bool) or int(threads) != threads or threads < 1):
        raise ValueError(f"threads must be an integer >= 1, got {threads!r}")
    root = Path(release)
    import pyarrow as pa
    import pyarrow.compute as pc

    rel = open_release(root)
    actions = rel.table("actions").to_pylist()
    page_kinds = ("page", "page_thumbnail")
    # Rows become Python dicts only for what the page shows: at release size the assets and metrics tables hold
    # hundreds of thousands of rows (the digests and the stages' per-camera statistics are not shown).
    assets_table = rel.table("assets")
    assets_table = assets_table.filter(pc.invert(pc.is_in(assets_table["kind"], pa.array(page_kinds))))
    assets = assets_table.select([c for c in assets_table.column_names if c != "sha256"]).to_pylist()
    summary = rel.table("metrics_summary").to_pylist()
    metrics_table = rel.table("metrics")
    metrics = metrics_table.filter(pc.equal(metrics_table["source"], "evaluate")).to_pylist()  # accuracy_rows' rows
    examples = rel.table("relight_examples").to_pylist() if rel.has_table("relight_examples") else []
    run_path = root / "run.json"
    run = json.loads(run_path.read_text()) if run_path.is_file() else {}

    made: list[tuple[str, str | None, str | None]] = []
    # The thumbnails are written by a pool of threads while the page's text is put together: reading the EXR,
    # resizing and the PNG encoding release the GIL for most of their time.
    pool = ThreadPoolExecutor(int(threads) if threads is not None else max(1, min(os.cpu_count() or 1, 8)))
    pending: dict[str, Any] = {}  # one job per thumbnail file, however often the page shows it

    def make_thumb(source_rel: str, kind: str, out_rel: str) -> str:
        if out_rel not in pending:
            pending[out_rel] = pool.submit(_write_thumbnail, root, source_rel, kind, out_rel)
        action_id, camera = out_rel.split("/")[1], out_rel.rsplit("/", 1)[-1][:-4].rsplit("_", 1)[-1]
        made.append((out_rel, action_id, None if camera == "action" else camera))
        return out_rel

    try:
        text = page_html(root, actions, assets, summary, metrics, examples, run, make_thumb)
        for future in pending.values():
            future.result()  # the first thumbnail that failed raises here
    finally:
        pool.shutdown(cancel_futures=True)
    _remove_stale_thumbnails(root, {p for p, _, _ in made})
    tmp = root / f".{PAGE}.{os.getpid()}.tmp"
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, root / PAGE)
    except BaseException:  # e.g. a full disk: leave no half-written page behind
        tmp.unlink(missing_ok=True)
        raise
    rows = [asset_row(root, PAGE, "page")]
    rows += [asset_row(root, path, "page_thumbnail", action_id=a, camera_id=c) for path, a, c in made]
    replace_rows(root, "assets", rows, drop=lambda r: r["kind"] in page_kinds)
    return root / PAGE


def _remove_stale_thumbnails(root: Path, keep: set[str]) -> None:
    """Delete thumbnails the page no longer shows (e.g. of an action that failed since), and empty folders."""
    folder = root / THUMBNAIL_DIR
    if not folder.is_dir():
        return
    for path in sorted(folder.rglob("*"), reverse=True):
        rel = path.relative_to(root).as_posix()
        if path.is_file() and rel not in keep:
            path.unlink()
        elif path.is_dir() and not any(path.iterdir()):
            shutil.rmtree(path)
