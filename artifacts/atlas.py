"""The UV atlas of a textured mesh: which input vertex each atlas vertex copies, the faces into them and their UVs.

:func:`stages.numerics.mesh.uv_atlas` makes one; :func:`artifacts.facade.load_atlas_mesh` reads one back from the
textures stage's OBJ. UV convention (OBJ / OpenGL): ``u`` right, ``v`` up, both in ``[0, 1]``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Atlas:
    """A UV atlas of a mesh: the mesh's vertices split along chart seams, each with one UV.

    Attributes:
        vmapping: (V',) int64, the input vertex each atlas vertex copies (``vertices[vmapping]``).
        faces: (F, 3) int32 into the atlas vertices; face ``i`` is input face ``i`` (same order).
        uvs: (V', 2) float32 in [0, 1], OBJ convention: u right, v *up* (texel row ``r`` of a ``T x T``
            texture has ``v = 1 - (r + 0.5) / T``).
        width, height: the square the charts were packed in, in texels (``padding`` is in these); xatlas
            lands near, not at, the requested resolution, so baking at ``texture_size`` scales the
            padding by ``texture_size / width``.
        stats: xatlas ``charts``, ``utilization``, ``packed_width``/``packed_height``,
            ``texels_per_metre`` (packed texels), ``seconds``.
    """

    vmapping: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    width: int
    height: int
    stats: dict
