"""Open subject meshes (a bust cut at the neck, a face) in every format `simulate --mesh` names stay one
connected surface with only their real opening as boundary."""
from __future__ import annotations

import numpy as np
import pytest

from stages.numerics.meshmetrics import boundary_edges
from synthetic import subject


def open_bust():
    """An icosphere of radius 12 cm cut below y = -4 cm (the neck's opening), in centimetres."""
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=3, radius=12.0)
    keep = ball.vertices[ball.faces][:, :, 1].min(axis=1) > -4.0
    return trimesh.Trimesh(ball.vertices, ball.faces[keep], process=False)


@pytest.mark.parametrize("suffix", ["obj", "ply", "stl", "off", "glb"])
def test_open_mesh_formats_load_as_one_surface_with_one_opening(tmp_path, suffix):
    bust = open_bust()
    rim = len(boundary_edges(np.asarray(bust.faces)))
    assert rim > 20
    path = tmp_path / f"bust.{suffix}"
    bust.export(path)
    base = subject.load_base_subject(str(path), 0)
    assert len(base.triangles) == len(bust.faces)
    assert len(base.vertices) == len(np.unique(np.asarray(bust.faces)))  # STL's separate corners are welded
    assert len(boundary_edges(base.triangles)) == rim                      # the neck only, no cracks
    assert np.isclose(base.units_m, 0.01) and np.ptp(base.vertices, axis=0).max() == pytest.approx(0.24, abs=0.01)
    # Loop subdivision keeps it one surface: the rim's edges are split in two, nothing else opens
    once = subject.load_base_subject(str(path), 1)
    assert len(boundary_edges(once.triangles)) == 2 * rim
