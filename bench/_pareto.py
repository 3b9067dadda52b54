"""Time against error: the Pareto front of a set of settings, and the table and plot the report shows per stage.

A point is one setting of a stage's quality knobs, measured as (seconds, error), both lower-is-better. A point is on
the front when no other point is at least as fast and at least as accurate and strictly better in one of the two.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence


@dataclass(frozen=True)
class TradeoffPoint:
    """One setting of a stage's knobs, measured."""

    label: str
    """The setting, as a reader would write it (e.g. ``AHD, half size``)."""
    seconds: float
    """Its time, in the unit of the trade-off's ``time_label`` (lower is better)."""
    error: float
    """Its error (or score, see :attr:`Tradeoff.higher_is_better`), in the unit of the trade-off's
    ``error_label``."""
    series: str = ""
    """Which sweep it belongs to when one plot holds several (one colour per series)."""
    presets: tuple[str, ...] = ()
    """The presets whose config gives this setting (``default``, ``production``, ...)."""
    baseline_seconds: float | None = None
    """A simple baseline's time measured in the same process and unit, when the bench has one."""


@dataclass(frozen=True)
class Tradeoff:
    """A stage's time against its error over its quality knobs."""

    stage: str
    """The pipeline stage (or part of it) the knobs belong to."""
    knobs: str
    """The config fields swept, as a reader would find them in a config file."""
    time_label: str
    """What the time axis measures (unit included)."""
    error_label: str
    """What the error axis measures (unit included)."""
    points: tuple[TradeoffPoint, ...]
    """The measured settings."""
    source: str
    """The bench whose rows these are."""
    notes: tuple[str, ...] = field(default_factory=tuple)
    """What a reader must know to read the numbers (preset points not in the sweep, noise, ...)."""
    higher_is_better: bool = False
    """The error axis is a score (PSNR, F-score): the front maximises it."""

    def front(self) -> list[bool]:
        """:func:`pareto_front` of the points, with the error's sense taken into account."""
        sign = -1.0 if self.higher_is_better else 1.0
        return pareto_front([p.seconds for p in self.points], [sign * p.error for p in self.points])


def pareto_front(seconds: Sequence[float], errors: Sequence[float]) -> list[bool]:
    """Which points are on the Pareto front of (seconds, errors), both minimised.

    seconds, errors: (N,) finite numbers; a point with a non-finite coordinate is never on the front and never
    dominates another. Returns N booleans. Duplicate points are all on the front when one is."""
    if len(seconds) != len(errors):
        raise ValueError(f"pareto_front: {len(seconds)} times but {len(errors)} errors")
    points = [(float(t), float(e)) for t, e in zip(seconds, errors)]
    finite = [math.isfinite(t) and math.isfinite(e) for t, e in points]
    on_front = []
    for i, (t, e) in enumerate(points):
        if not finite[i]:
            on_front.append(False)
            continue
        dominated = any(finite[j] and t2 <= t and e2 <= e and (t2 < t or e2 < e)
                        for j, (t2, e2) in enumerate(points) if j != i)
        on_front.append(not dominated)
    return on_front


def _number(x: float) -> str:
    if not math.isfinite(x):
        return "n/a"
    magnitude = abs(x)
    if magnitude == 0 or 0.01 <= magnitude < 1e5:
        return f"{x:.4g}" if magnitude < 1000 else f"{x:.0f}"
    return f"{x:.2e}"


def tradeoff_table(tradeoff: Tradeoff) -> list[str]:
    """Markdown lines: one row per point, sorted by time, with its front membership and preset marks (and the ratio
    to the bench's baseline when the points carry one), then the trade-off's notes."""
    points = list(tradeoff.points)
    front = tradeoff.front()
    with_baseline = any(p.baseline_seconds for p in points)
    head = ["setting", tradeoff.time_label, tradeoff.error_label, "Pareto", "preset"]
    if with_baseline:
        head.append("x baseline")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    order = sorted(range(len(points)), key=lambda i: (points[i].seconds, points[i].error))
    for i in order:
        p = points[i]
        label = f"{p.series}: {p.label}" if p.series else p.label
        row = [label, _number(p.seconds), _number(p.error), "yes" if front[i] else "", ", ".join(p.presets)]
        if with_baseline:
            row.append(_number(p.seconds / p.baseline_seconds) if p.baseline_seconds else "")
        lines.append("| " + " | ".join(row) + " |")
    return lines + ([""] + [f"- {note}" for note in tradeoff.notes] if tradeoff.notes else [])


def tradeoff_plot(tradeoff: Tradeoff, path: Path, log_time: bool | None = None) -> Path:
    """Write a PNG of error against time: every point, one colour per series, the Pareto front as a dashed line,
    the presets' points ringed and named. ``log_time``: a log time axis (default: when the times span over 20x)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    front = tradeoff.front()
    points = [p for p in tradeoff.points if math.isfinite(p.seconds) and math.isfinite(p.error)]
    front = [f for p, f in zip(tradeoff.points, front) if math.isfinite(p.seconds) and math.isfinite(p.error)]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    series = list(dict.fromkeys(p.series for p in points))
    for k, name in enumerate(series):
        members = [p for p in points if p.series == name]
        ax.scatter([p.seconds for p in members], [p.error for p in members], s=22, color=f"C{k}",
                   label=name or None, zorder=3)
        for p in members:
            ax.annotate(p.label, (p.seconds, p.error), fontsize=6, xytext=(3, 3), textcoords="offset points")
    front_points = sorted((p.seconds, p.error) for p, f in zip(points, front) if f)
    if front_points:
        xs, ys = zip(*front_points)
        ax.plot(xs, ys, color="0.4", lw=1, ls="--", label="Pareto front", zorder=2)
    for marker, preset in (("o", "default"), ("s", "production")):
        marked = [p for p in points if preset in p.presets]
        if marked:
            ax.scatter([p.seconds for p in marked], [p.error for p in marked], s=110, marker=marker,
                       facecolors="none", edgecolors="k" if preset == "default" else "C3", lw=1.4,
                       label=f"{preset} preset", zorder=4)
    times = [p.seconds for p in points if p.seconds > 0]
    if log_time is None:
        log_time = bool(times) and max(times) > 20 * min(times)
    if log_time:
        ax.set_xscale("log")
    ax.set_xlabel(tradeoff.time_label)
    ax.set_ylabel(tradeoff.error_label + (" (higher is better)" if tradeoff.higher_is_better else ""))
    ax.set_title(f"{tradeoff.stage}: {tradeoff.knobs}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
