"""Convex hull and eq 35 shoelace area, including degenerate sets."""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from fusion_center.errors import ParameterError
from fusion_center.geometry import (
    active_centroid, contact_area, convex_hull, polygon_area, signed_polygon_area,
)


def _monotone_chain(points):
    """Independent reference hull (Andrew's monotone chain), CCW, no collinear vertices."""
    pts = sorted(set(map(tuple, points)))
    if len(pts) <= 2:
        return pts

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


def test_unit_square_with_interior_edge_and_duplicate_points():
    pts = [(0, 0), (1, 0), (1, 1), (0, 1), (0.5, 0.5), (0.5, 0), (1, 1)]
    hull = convex_hull(pts)
    assert hull.shape == (4, 2)
    assert set(map(tuple, hull)) == {(0, 0), (1, 0), (1, 1), (0, 1)}
    assert signed_polygon_area(hull) == pytest.approx(1.0)  # positive = counter-clockwise
    assert contact_area(pts) == pytest.approx(1.0)


def test_shoelace_orientation_and_absolute_area():
    tri = [(0, 0), (4, 0), (0, 3)]
    assert signed_polygon_area(tri) == 6.0
    assert signed_polygon_area(tri[::-1]) == -6.0
    assert polygon_area(tri[::-1]) == 6.0


@pytest.mark.parametrize("pts, expected", [
    ([], np.zeros((0, 2))),
    ([(2.0, 3.0)], [[2.0, 3.0]]),
    ([(2.0, 3.0)] * 4, [[2.0, 3.0]]),
    ([(0, 0), (3, 4)], [[0, 0], [3, 4]]),
    ([(0, 0), (1, 1), (3, 3), (2, 2), (1, 1)], [[0, 0], [3, 3]]),
    ([(5, 1), (5, 7), (5, 3)], [[5, 1], [5, 7]]),
])
def test_degenerate_sets_do_not_raise(pts, expected):
    hull = convex_hull(pts)
    np.testing.assert_array_equal(hull, np.asarray(expected, dtype=float).reshape(-1, 2))
    assert contact_area(pts) == 0.0


def test_nearly_collinear_is_handled():
    pts = [(0, 0), (1, 1e-17), (2, 0)]
    hull = convex_hull(pts)
    assert len(hull) in (2, 3)
    assert contact_area(pts) == pytest.approx(0.0, abs=1e-15)


def test_bad_points_rejected():
    with pytest.raises(ParameterError, match="points"):
        convex_hull([(0, 0, 0)])
    with pytest.raises(ParameterError, match=r"points\[1\]"):
        convex_hull([(0, 0), (np.nan, 1), (2, 2)])


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.integers(-20, 20), st.integers(-20, 20)), min_size=0, max_size=25))
def test_hull_matches_independent_monotone_chain(points):
    ref = _monotone_chain(points)
    hull = convex_hull(points)
    assert sorted(map(tuple, hull.tolist())) == sorted((float(x), float(y)) for x, y in ref)
    ref_area = polygon_area(ref) if len(ref) >= 3 else 0.0
    assert contact_area(points) == pytest.approx(ref_area, abs=1e-9)
    if len(hull) >= 3:
        assert signed_polygon_area(hull) > 0


def test_centroid_counts_a_shared_location_once():
    np.testing.assert_array_equal(active_centroid([(0, 0), (0, 0), (2, 0)]), [1.0, 0.0])
    assert np.all(np.isnan(active_centroid([])))
