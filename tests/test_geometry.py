"""Convex hull and eq 35 shoelace area, including degenerate sets."""

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from taxel_net.errors import ParameterError
from fusion_center.core import geometry
from fusion_center.core.geometry import (
    SMALL_SET_MAX, active_centroid, contact_area, convex_hull, polygon_area, signed_polygon_area,
)


def _brute_force_hull(points):
    """Independent O(n^3) reference in exact rationals: (vertex set, area).

    a -> b is a counter-clockwise hull edge iff every other point lies strictly left of it
    or on the closed segment [a, b]; the area is half the sum of a x b over those edges
    (eq 35 without needing the vertex order).
    """
    pts = sorted({(Fraction(x), Fraction(y)) for x, y in points})

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    def on_segment(a, b, c):
        return min(a[0], b[0]) <= c[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= c[1] <= max(a[1], b[1])

    edges = [(a, b) for a in pts for b in pts if a != b and all(
        cross(a, b, c) > 0 or (cross(a, b, c) == 0 and on_segment(a, b, c)) for c in pts)]
    vertices = {a for a, _ in edges} if edges else set(pts)
    area = sum((a[0] * b[1] - b[0] * a[1] for a, b in edges), Fraction(0)) / 2
    return {(float(x), float(y)) for x, y in vertices}, area


def _check_against_brute_force(points, *, exact_vertices=True):
    ref_vertices, ref_area = _brute_force_hull(points)
    hull = convex_hull(points)                      # must never raise (QhullError included)
    assert len(set(map(tuple, hull.tolist()))) == len(hull)
    assert set(map(tuple, hull.tolist())) <= {(float(x), float(y)) for x, y in points}
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    extent = float(np.ptp(pts, axis=0).max()) if len(pts) else 0.0
    assert contact_area(points) == pytest.approx(float(ref_area), rel=1e-9, abs=1e-12 * extent ** 2)
    if exact_vertices:
        assert set(map(tuple, hull.tolist())) == ref_vertices
    if len(hull) >= 3:                              # counter-clockwise, checked exactly
        exact = [(Fraction(x), Fraction(y)) for x, y in hull.tolist()]
        twice_area = sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(exact, exact[1:] + exact[:1]))
        assert twice_area > 0
        if exact_vertices:
            assert twice_area / 2 == ref_area       # a simple polygon in convex order


def test_brute_force_reference_on_hand_cases():
    # the reference itself, on sets with hand-known hulls
    assert _brute_force_hull([(0, 0), (2, 0), (1, 0), (0, 2), (1, 1), (2, 2), (0, 2)]) == \
        ({(0, 0), (2, 0), (0, 2), (2, 2)}, 4)
    assert _brute_force_hull([(0, 0), (1, 1), (3, 3)]) == ({(0, 0), (3, 3)}, 0)
    assert _brute_force_hull([(5, 5)]) == ({(5, 5)}, 0)


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


def test_nearly_collinear_is_a_thin_triangle_not_a_segment():
    # Qhull refuses this set as flat; the exact fallback still finds the 3 corners
    pts = [(0, 0), (1, 1e-17), (2, 0), (1, 0)]
    hull = convex_hull(pts)
    assert set(map(tuple, hull.tolist())) == {(0.0, 0.0), (1.0, 1e-17), (2.0, 0.0)}
    assert contact_area(pts) == pytest.approx(1e-17, rel=1e-12)     # base 2, height 1e-17


def test_large_common_offset_keeps_the_area():
    # 4 x 4 square at 1e15 (exact in floats): the shoelace must not cancel it away
    base = 1e15
    square = [(base, base), (base + 4, base), (base, base + 4), (base + 4, base + 4), (base + 2, base + 2)]
    hull = convex_hull(square)
    assert len(hull) == 4 and contact_area(square) == 16.0
    tri = [(base, base), (base + 1, base), (base, base + 1)]
    assert contact_area(tri) == 0.5


def test_extent_overflow_is_a_parameter_error():
    with pytest.raises(ParameterError, match="points"):
        convex_hull([(-1e308, 0), (1e308, 0), (0, 1)])


def test_bad_points_rejected():
    with pytest.raises(ParameterError, match="points"):
        convex_hull([(0, 0, 0)])
    with pytest.raises(ParameterError, match=r"points\[1\]"):
        convex_hull([(0, 0), (np.nan, 1), (2, 2)])


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.integers(-20, 20), st.integers(-20, 20)), min_size=0, max_size=14))
def test_hull_matches_brute_force_on_small_grids(points):
    _check_against_brute_force(points)


@settings(max_examples=60, deadline=None)
@given(st.integers(-5, 5), st.integers(-5, 5), st.integers(-3, 3), st.integers(-3, 3),
       st.lists(st.integers(-30, 30), min_size=1, max_size=12), st.sampled_from([0.0, 1e15, -3e14]))
def test_collinear_sets_with_repeats_and_offsets(x0, y0, dx, dy, steps, offset):
    # all points on one line (dx = dy = 0: one repeated point), shifted by a huge offset;
    # integers below 2**53 and offsets on the float grid keep every coordinate exact
    points = [(offset + x0 + k * dx, offset + y0 + k * dy) for k in steps + steps[:3]]
    _check_against_brute_force(points)
    assert contact_area(points) == 0.0
    assert len(convex_hull(points)) == (1 if (dx, dy) == (0, 0) or len(set(steps)) == 1 else 2)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(-50, 50), st.integers(-10**6, 10**6)), min_size=3, max_size=12),
       st.floats(0.5, 2.0), st.sampled_from([1e-12, 1e-15, 1e-17]), st.sampled_from([0.0, 1e15]))
def test_nearly_collinear_sets(samples, slope, eps, offset):
    # points within ~eps of the line y = slope x: Qhull may call them flat (exact fallback)
    # or keep them; the area must match the exact brute-force hull of the very same floats.
    # Vertices are not compared: where Qhull accepts the set it may pick, between points
    # ~1e-15 x extent apart, another one than the exact hull does.
    points = [(offset + float(x), offset + slope * x + eps * (w / 10**6)) for x, w in samples]
    _check_against_brute_force(points, exact_vertices=False)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(-20, 20), st.integers(-20, 20)), min_size=1, max_size=10),
       st.sampled_from([1e15, 2.0**52]))
def test_grid_sets_at_huge_offsets(points, offset):
    _check_against_brute_force([(offset + x, offset + y) for x, y in points])


# --------------------------------------------------------------------------------------------
# The two hull paths: exact monotone chain (method="exact", the default up to SMALL_SET_MAX
# points) and Qhull (method="qhull"). Both are checked against the brute-force reference and
# against each other, forcing each path.

def _lexmin_first_ccw(hull):
    """The documented form: first vertex the lexicographically smallest, counter-clockwise."""
    rows = [tuple(r) for r in hull.tolist()]
    assert rows[0] == min(rows)
    if len(rows) >= 3:
        exact = [(Fraction(x), Fraction(y)) for x, y in rows]
        assert sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(exact, exact[1:] + exact[:1])) > 0


def _both_paths_exact(points):
    """Both paths give the brute-force hull, in the same form (identical arrays); the default
    contact_area is the brute-force area rounded once (float(Fraction) rounds correctly)."""
    ref_vertices, ref_area = _brute_force_hull(points)
    exact, qhull = convex_hull(points, "exact"), convex_hull(points, "qhull")
    assert exact.dtype == qhull.dtype == np.float64 and exact.ndim == qhull.ndim == 2
    assert set(map(tuple, exact.tolist())) == ref_vertices
    np.testing.assert_array_equal(exact, qhull)
    _lexmin_first_ccw(exact)
    if len(points) <= SMALL_SET_MAX:
        assert contact_area(points) == float(ref_area)
        np.testing.assert_array_equal(convex_hull(points), exact)


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.integers(-12, 12), st.integers(-12, 12)), min_size=1, max_size=14),
       st.sampled_from([0.0, 1e15, 2.0**52, -2.0**52]), st.sampled_from([1.0, 0.25, 3.0]))
def test_paths_agree_on_grids_with_duplicates_and_huge_offsets(points, offset, scale):
    # offsets on the float grid and integer multiples of scale keep every coordinate exact
    # (2**52 + 0.25 k would not be, so quarter steps go with offsets up to 1e15 only)
    if scale == 0.25 and abs(offset) >= 2.0**52:
        scale = 1.0
    pts = [(offset + scale * x, offset + scale * y) for x, y in points + points[:2]]
    _both_paths_exact(pts)


def test_paths_agree_on_random_float_sets():
    rng = np.random.default_rng(7)
    for trial in range(60):
        n = int(rng.integers(3, 13))
        pts = rng.random((n, 2)) * 10 ** rng.uniform(-3, 3)
        if trial % 3 == 1:
            pts = pts + 1e15 * rng.choice([-1, 1])
        pts = [(float(x), float(y)) for x, y in pts]
        _both_paths_exact(pts + pts[:1])


@pytest.mark.parametrize("pts", [
    [(0, 0), (0, 0), (0, 0)],
    [(1e15, 1e15)] * 3 + [(1e15 + 2, 1e15 + 2)] * 2,
    [(-0.0, 1.0), (0.0, 1.0), (0.0, -0.0), (1.0, 0.0)],
    [(2.0**52, 0), (2.0**52 + 1, 0), (2.0**52 + 2, 0), (2.0**52 + 1, 0)],
    [(0, 0), (1, 0), (2, 0), (2, 1), (2, 2), (1, 1), (0, 2), (0, 1)],  # points on every edge
    [(3, 1), (1, 3), (2, 2), (0, 4), (4, 0)],                          # collinear, unsorted
])
def test_paths_agree_on_degenerate_sets(pts):
    _both_paths_exact(pts)
    if len(_brute_force_hull(pts)[0]) <= 2:
        assert contact_area(pts) == 0.0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(-50, 50), st.integers(-10**6, 10**6)), min_size=3, max_size=12),
       st.floats(0.5, 2.0), st.sampled_from([1e-12, 1e-15, 1e-17]), st.sampled_from([0.0, 1e15, 2.0**52]))
def test_exact_path_on_nearly_collinear_sets(samples, slope, eps, offset):
    # the exact chain gets the very vertices and the correctly rounded area of the brute-force
    # hull of the same floats; Qhull (forced) at least the area (its vertices may differ by
    # points ~1e-15 x extent apart, see test_nearly_collinear_sets)
    points = [(offset + float(x), offset + slope * x + eps * (w / 10**6)) for x, w in samples]
    ref_vertices, ref_area = _brute_force_hull(points)
    exact = convex_hull(points, "exact")
    assert set(map(tuple, exact.tolist())) == ref_vertices
    _lexmin_first_ccw(exact)
    assert contact_area(points) == float(ref_area)
    extent = float(np.ptp(np.asarray(points), axis=0).max())
    assert polygon_area(convex_hull(points, "qhull")) == pytest.approx(float(ref_area), rel=1e-9,
                                                                       abs=1e-12 * extent ** 2)
    _lexmin_first_ccw(convex_hull(points, "qhull"))


def test_thin_triangle_at_2_pow_52_both_paths():
    # 2**52 + 1 is exact; the middle point is 1 unit (its float spacing) above the base line
    o = 2.0**52
    pts = [(o, o), (o + 4, o), (o + 2, o + 1), (o + 2, o), (o + 1, o)]
    expected = np.array([[o, o], [o + 4, o], [o + 2, o + 1]])
    np.testing.assert_array_equal(convex_hull(pts, "exact"), expected)
    np.testing.assert_array_equal(convex_hull(pts, "qhull"), expected)
    assert contact_area(pts) == 2.0                                  # base 4, height 1


def test_auto_switches_to_qhull_above_small_set_max(monkeypatch):
    calls = []
    real = geometry.ConvexHull
    monkeypatch.setattr(geometry, "ConvexHull", lambda pts: calls.append(len(pts)) or real(pts))
    rng = np.random.default_rng(3)
    small = rng.integers(0, 30, (SMALL_SET_MAX, 2)).astype(float)
    large = rng.integers(0, 30, (SMALL_SET_MAX + 1, 2)).astype(float)
    hull_small = convex_hull(small)
    contact_area(small)
    assert calls == []
    hull_large = convex_hull(large)
    area_large = contact_area(large)
    assert len(calls) == 2
    np.testing.assert_array_equal(hull_small, convex_hull(small, "qhull"))
    np.testing.assert_array_equal(hull_large, convex_hull(large, "exact"))
    assert area_large == polygon_area(hull_large)
    assert area_large == pytest.approx(float(_brute_force_hull(hull_large.tolist())[1]), rel=1e-15)


@pytest.mark.parametrize("method", ["exact", "qhull"])
def test_errors_are_the_same_on_both_paths(method):
    with pytest.raises(ParameterError, match="points") as overflow:
        convex_hull([(-1e308, 0), (1e308, 0), (0, 1)], method)
    assert "[[-1e+308, 0.0], [1e+308, 1.0]]" in str(overflow.value)
    with pytest.raises(ParameterError, match="points"):   # y extent from the first point
        convex_hull([(0, 1e308), (1, -1e308), (2, 0)], method)
    # no overflow relative to the lexicographically first point: a valid thin hull
    hull = convex_hull([(0, 0), (1, 1e308), (1, -1e308)], method)
    assert set(map(tuple, hull.tolist())) == {(0.0, 0.0), (1.0, 1e308), (1.0, -1e308)}
    # fewer than 3 distinct points: no extent check, as before
    np.testing.assert_array_equal(convex_hull([(-1e308, 0), (1e308, 0)], method), [[-1e308, 0], [1e308, 0]])
    with pytest.raises(ParameterError, match="points"):
        convex_hull([(0, 0, 0)], method)
    with pytest.raises(ParameterError, match=r"points\[2\]"):
        convex_hull([(0, 0), (1, 1), (np.inf, 1)], method)
    with pytest.raises(ParameterError, match="points"):
        convex_hull("not points", method)


def test_unknown_method_is_a_parameter_error():
    with pytest.raises(ParameterError, match="method"):
        convex_hull([(0, 0), (1, 0), (0, 1)], "quickhull")


def test_contact_area_beyond_the_float_range_is_inf():
    # true area 0.5e400 > max float: the correctly rounded value is inf (no OverflowError)
    assert contact_area([(0, 0), (1e200, 0), (0, 1e200)]) == np.inf
    # and an area below the smallest subnormal rounds to 0
    assert contact_area([(0, 0), (1e-300, 0), (0, 1e-300)]) == 0.0


def test_centroid_counts_a_shared_location_once():
    np.testing.assert_array_equal(active_centroid([(0, 0), (0, 0), (2, 0)]), [1.0, 0.0])
    assert np.all(np.isnan(active_centroid([])))


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_locations_centroid_is_active_centroid_of_the_subset_bit_for_bit(data):
    """A fixed layout's centroid of any subset (taxels sharing a location - R-cells - counted
    once) equals active_centroid of the subset's rows exactly: the same distinct rows in the
    same order, the same mean; an empty subset gives (nan, nan)."""
    n_locations = data.draw(st.integers(1, 40))
    coords = st.one_of(st.integers(-50, 50).map(float), st.floats(-1e6, 1e6, allow_nan=False))
    locations = data.draw(st.lists(st.tuples(coords, coords), min_size=n_locations, max_size=n_locations))
    # every location once or twice (an R-cell's pair), shuffled
    points = [p for p in locations for _ in range(data.draw(st.integers(1, 2)))]
    points = data.draw(st.permutations(points))
    xy = np.array(points, dtype=float) + 0.0  # no -0.0: np.unique keeps either sign of a zero
    layout = geometry.Locations(xy)
    mask = np.array(data.draw(st.lists(st.booleans(), min_size=len(xy), max_size=len(xy))))
    got = layout.centroid(mask)
    want = geometry.active_centroid(xy[mask])
    assert got.shape == (2,)
    if not mask.any():
        assert np.isnan(got).all() and np.isnan(want).all()
    else:
        assert got.tolist() == want.tolist()


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_locations_contact_area_is_contact_area_of_the_subset(data):
    """The layout's area of a subset is contact_area of the subset's rows, the same float: on
    grids (collinear rows, R-cell pairs), on random floats across magnitudes, above
    SMALL_SET_MAX (Qhull's path) and on layouts whose extent overflows (the error or inf of
    contact_area itself)."""
    kind = data.draw(st.sampled_from(["grid", "floats", "large", "huge"]))
    if kind == "grid":
        side = data.draw(st.integers(1, 9))
        pitch = data.draw(st.sampled_from([1.0, 0.1, 2.5, 1e-7, 3e5]))
        xy = np.array([(i * pitch, j * pitch) for i in range(side) for j in range(side)] * 2)  # R-cell pairs
    elif kind == "large":  # rows drawn with repeats from 150 random locations: masks around 128 rows
        rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
        pool = rng.uniform(0.0, 1e3, (150, 2))
        xy = pool[rng.integers(0, 150, data.draw(st.integers(130, 300)))]
    else:
        big = 1e300 if kind == "huge" else 1e6
        coords = st.floats(-big, big, allow_nan=False, allow_infinity=False)
        xy = np.array(data.draw(st.lists(st.tuples(coords, coords), min_size=1, max_size=60)))
    layout = geometry.Locations(xy)
    for _ in range(3):
        mask = np.array(data.draw(st.lists(st.booleans(), min_size=len(xy), max_size=len(xy))))
        try:
            want = geometry.contact_area(xy[mask])
        except ParameterError as exc:
            with pytest.raises(ParameterError) as raised:
                layout.contact_area(mask)
            assert str(raised.value) == str(exc)
            continue
        got = layout.contact_area(mask)
        assert got == want or (np.isnan(got) and np.isnan(want)), (got, want)


def test_locations_contact_area_refuses_a_subset_whose_extent_overflows_as_contact_area_does():
    """A layout whose differences from its first point are finite while a subset's from its own
    first point are not (1e308 above and below a point of x = 0): the subset is refused with
    contact_area's own error, not given an area; an empty layout's empty subset is 0.0."""
    pts = np.array([[-1.0, 0.0], [0.0, -1e308], [0.0, 1e308], [1.0, 0.0]])
    mask = np.array([False, True, True, True])
    with pytest.raises(ParameterError) as want:
        geometry.contact_area(pts[mask])
    with pytest.raises(ParameterError) as got:
        geometry.Locations(pts).contact_area(mask)
    assert str(got.value) == str(want.value)
    assert geometry.Locations(pts).contact_area(np.array([True, False, False, True])) == 0.0  # a segment
    empty = geometry.Locations(np.zeros((0, 2)))
    assert empty.contact_area(np.zeros(0, dtype=bool)) == 0.0
    assert np.isnan(empty.centroid(np.zeros(0, dtype=bool))).all()
