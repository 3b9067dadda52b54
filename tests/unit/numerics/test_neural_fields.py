"""The input checks both neural fields share (stages.numerics.neural_fields): what passes, and the message each
refusal gives, on hand-made inputs; and that the SDF and the appearance field refuse through them."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from stages.numerics.neural_fields import check_bounds, check_view_list, check_view_map


@dataclass
class _View:
    name: str = "v"


def test_check_bounds_returns_float64_and_refuses_bad_boxes():
    box = check_bounds([[0, 0, 0], [1, 2, 3]])
    assert box.dtype == np.float64 and box.shape == (2, 3) and box[1, 2] == 3.0
    for bad in ([[0, 0, 0], [1, 0, 3]], [[0, 0], [1, 1]], [[0, 0, 0], [np.inf, 1, 1]], [[1, 1, 1], [0, 2, 2]]):
        with pytest.raises(ValueError, match=r"bounds must be finite \(2, 3\) \[min, max\] with max > min"):
            check_bounds(bad)


def test_check_view_list_names_the_first_view_of_another_type():
    check_view_list([_View(), _View()], _View)
    check_view_list((_View(),), _View)
    with pytest.raises(ValueError, match="views must be a non-empty list of _View"):
        check_view_list([], _View)
    with pytest.raises(ValueError, match="views must be a non-empty list of _View"):
        check_view_list(_View(), _View)
    with pytest.raises(ValueError, match=r"views\[1\] is int, expected _View"):
        check_view_list([_View(), 3, "x"], _View)


def test_check_view_map_shapes_and_finite_on_valid_pixels():
    valid = np.array([[True, False], [True, True]])
    normals = np.zeros((2, 2, 3))
    normals[0, 1] = np.nan  # an invalid pixel may hold anything
    assert check_view_map(normals, (2, 2, 3), "views[0].normals_world", valid=valid) is not None
    with pytest.raises(ValueError, match=r"views\[0\].normals_world must be \(H, W, 3\) = \(2, 2, 3\), got \(2, 3\)"):
        check_view_map(np.zeros((2, 3)), (2, 2, 3), "views[0].normals_world")
    with pytest.raises(ValueError, match=r"views\[2\].mask must be \(H, W\) = \(2, 2\), got \(2, 2, 1\)"):
        check_view_map(np.zeros((2, 2, 1)), (2, 2), "views[2].mask")
    normals[1, 0] = np.inf  # on a valid pixel
    with pytest.raises(ValueError, match=r"views\[0\].normals_world holds NaN or Inf on valid pixels"):
        check_view_map(normals, (2, 2, 3), "views[0].normals_world", valid=valid)


def test_both_fields_refuse_through_the_shared_checks():
    from stages.numerics.appearance_field import _check_views as appearance_views
    from stages.numerics.sdf import _check_views as sdf_views

    with pytest.raises(ValueError, match="views must be a non-empty list of SDFView"):
        sdf_views([], normal_supervision=True)
    with pytest.raises(ValueError, match=r"views\[0\] is _View, expected AppearanceView"):
        appearance_views([_View()])
