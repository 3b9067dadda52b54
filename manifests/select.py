"""Which actions of a release to run again, chosen from its manifests (``ultrastage rerun``).

Pure selection over the Parquet tables a run writes: ``manifests/actions.parquet`` (status, subject, session)
and ``manifests/metrics.parquet`` (one value per action, or per camera, of each metric). Nothing here runs
work; the command line passes the chosen actions to the runner.
"""
from __future__ import annotations

import math
import operator
import re
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.errors import InputError

_OPERATORS = {"<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge, "==": operator.eq,
              "!=": operator.ne}
_CONDITION = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(<=|>=|==|!=|<|>)\s*([-+0-9.eE]+|nan|inf)\s*$")


@dataclass(frozen=True)
class Condition:
    """``metric op value``, e.g. ``heldout_albedo_psnr_db < 30``."""

    metric: str
    op: str
    value: float

    def holds(self, x: float) -> bool:
        return math.isfinite(x) and _OPERATORS[self.op](x, self.value)


def parse_condition(text: str) -> Condition:
    """``"NAME OP NUMBER"`` with OP one of ``< <= > >= == !=`` -> :class:`Condition` (ValueError otherwise)."""
    match = _CONDITION.match(text or "")
    if not match:
        raise ValueError(f"--where {text!r}: expected 'METRIC OP NUMBER' with OP one of {' '.join(_OPERATORS)}, "
                         "e.g. 'heldout_albedo_psnr_db < 30'")
    return Condition(match.group(1), match.group(2), float(match.group(3)))


@dataclass
class Selection:
    """The chosen action ids (sorted) and, per action, why it was chosen."""

    actions: list[str] = field(default_factory=list)
    reasons: dict[str, str] = field(default_factory=dict)


def _read(path: Path) -> list[dict]:
    import pyarrow.parquet as pq

    if not path.is_file():
        raise InputError(path, "missing: the release has no such manifest (was it written by `ultrastage run`?)")
    return pq.read_table(path).to_pylist()


def action_metric(rows: list[dict], metric: str) -> dict[str, float]:
    """action_id -> the action's value of ``metric``: its action-level row (no camera) when it has one, else
    the mean over its cameras' rows; non-finite values are left out."""
    whole: dict[str, float] = {}
    cams: dict[str, list[float]] = {}
    for r in rows:
        if r.get("metric") != metric or r.get("value") is None or not math.isfinite(float(r["value"])):
            continue
        if r.get("camera_id") is None:
            whole[r["action_id"]] = float(r["value"])
        else:
            cams.setdefault(r["action_id"], []).append(float(r["value"]))
    return {a: whole.get(a, sum(v) / len(v) if (v := cams.get(a)) else math.nan)
            for a in sorted(set(whole) | set(cams))}


def select_actions(release: Path, failed: bool = False, where: Condition | None = None,
                   subject: str | None = None, session: str | None = None) -> Selection:
    """Actions of ``release`` to redo: those that failed in the last run (``failed``), and/or whose metric
    meets ``where``, restricted to a ``subject`` (exact name or a prefix ending in ``/``) and a ``session``.
    With no criterion at all every action of the release is selected."""
    release = Path(release)
    actions = _read(release / "manifests" / "actions.parquet")
    chosen = [a for a in actions
              if (session is None or a.get("session_id") == session)
              and (subject is None or a.get("subject") == subject
                   or (subject.endswith("/") and str(a.get("subject", "")).startswith(subject)))]
    out = Selection()
    values: dict[str, float] = {}
    if where is not None:
        values = action_metric(_read(release / "manifests" / "metrics.parquet"), where.metric)
        if not values:
            raise InputError(release / "manifests" / "metrics.parquet",
                             f"no values of metric {where.metric!r} (see the metric column for the names)")
    for a in chosen:
        aid = a["action_id"]
        why = []
        if failed and a.get("status") != "ok":
            why.append(f"failed last run: {a.get('error') or a.get('status')}")
        if where is not None and where.holds(values.get(aid, math.nan)):
            why.append(f"{where.metric} = {values[aid]:.4g} {where.op} {where.value:g}")
        if not failed and where is None:
            why.append("selected" + (f" (session {session})" if session else "") + (f" (subject {subject})" if subject else ""))
        if why:
            out.actions.append(aid)
            out.reasons[aid] = "; ".join(why)
    out.actions.sort()
    return out
