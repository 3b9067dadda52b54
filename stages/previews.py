"""Contact sheets of the per-camera previews the stages write (``previews/<prefix>_<camera>.png``, at the
paths :data:`artifacts.layout.PRODUCTS` names)."""
from __future__ import annotations

from typing import Any

import numpy as np

from artifacts.layout import ArtifactWriter
from pipeline.codecs.image import label_picture, read_png, write_png


def contact_sheet(pictures: list[np.ndarray], columns: int = 8, labels: list[str] | None = None) -> np.ndarray:
    """Tile equally sized uint8 (H, W, 3) pictures into one (rows*H, columns*W, 3) picture, row-major; with
    ``labels`` (one per picture, e.g. the camera id) each tile carries its label in its top-left corner."""
    if labels is not None and len(labels) != len(pictures):
        raise ValueError(f"contact_sheet: {len(labels)} labels for {len(pictures)} pictures")
    h, w = pictures[0].shape[:2]
    rows = -(-len(pictures) // columns)
    sheet = np.zeros((rows * h, columns * w, 3), np.uint8)
    for i, pic in enumerate(pictures):
        r, c = divmod(i, columns)
        tile = pic[..., :3] if pic.ndim == 3 else np.repeat(pic[..., None], 3, axis=2)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = label_picture(tile, labels[i]) if labels else tile
    return sheet


def write_normal_sheet(out: ArtifactWriter, tile: str, sheet: str, view_stats: dict[str, dict[str, Any]]) -> None:
    """The product ``sheet``: the per-camera previews (product ``tile``) of the views that ran, side by side,
    each tile labelled with its camera id (nothing when none was written); both at ``out``'s paths."""
    paths = {v: out.path(tile, v) for v in sorted(view_stats) if "missing" not in view_stats[v]}
    shown = [v for v, p in paths.items() if p.exists()]
    if shown:
        write_png(out.path(sheet),
                  contact_sheet([read_png(paths[v]) for v in shown], labels=[f"cam {v}" for v in shown]))
