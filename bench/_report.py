"""The files a bench leaves under ``--out``: its results (``<name>.json``), its table (``<name>.md``) and its figure
(``<name>.png``)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable


def write_report(out: Path | str, name: str, report: dict[str, Any], markdown: str,
                 plot: Callable[[Path], Any] | None = None, json_default: Callable[[Any], Any] | None = None) -> None:
    """``<name>.json`` (``report``, indented; ``json_default`` as :func:`json.dumps`' ``default``), ``<name>.md``
    (``markdown``) and with ``plot`` ``<name>.png`` (``plot(path)`` draws it) under ``out``, made if missing; the
    table is printed."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(report, indent=1, default=json_default))
    (out / f"{name}.md").write_text(markdown)
    if plot is not None:
        plot(out / f"{name}.png")
    print(markdown)
