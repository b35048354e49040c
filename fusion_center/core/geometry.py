"""Contact geometry: convex hull of the excited taxels and its planar area (sec. 4.3.2, 6.2.3.3).

The chapter's program collects the coordinates of the taxels with u_i = +1, finds the
points on their convex hull and computes the hull's planar area with the shoelace formula,
eq 35. Here the hull comes from scipy's Qhull (``scipy.spatial.ConvexHull``) for the
large sets; small sets (up to ``SMALL_SET_MAX`` points, every contact pattern of a 57-taxel
matrix) and the degenerate sets Qhull rejects (fewer than three distinct points, all points
collinear or too nearly so for its precision) go through an exact monotone chain on integer
coordinates, so no ``QhullError`` escapes and small hulls cost tens of microseconds, not
Qhull's ~0.15-0.4 ms.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import ConvexHull

try:  # scipy >= 1.11 exposes it here
    from scipy.spatial import QhullError
except ImportError:  # pragma: no cover - older scipy
    from scipy.spatial.qhull import QhullError  # type: ignore

from taxel_net.errors import ParameterError

__all__ = ["as_points", "convex_hull", "polygon_area", "signed_polygon_area", "contact_area",
           "active_centroid", "Locations"]


def as_points(points, name: str = "points") -> np.ndarray:
    """``points`` as a float (n, 2) array; empty input gives shape (0, 2)."""
    try:
        arr = np.asarray(points, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError(name, points, "must be an (n, 2) array of numbers") from None
    if arr.size == 0:
        return np.zeros((0, 2))
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ParameterError(name, arr.shape, "must have shape (n, 2): one (x, y) per point")
    if not np.isfinite(arr).all():
        i = int(np.argwhere(~np.isfinite(arr))[0][0])
        raise ParameterError(f"{name}[{i}]", arr[i].tolist(), "coordinates must be finite")
    return arr


#: Largest input (rows, duplicates included) that takes the exact monotone chain in
#: ``convex_hull(method="auto")`` and ``contact_area``; above it Qhull is faster. Crossover
#: measured with ``bench/hull.py`` on 2 shared cores: random float sets ~100 points back to
#: back and ~190 after a 10 ms idle gap (the centre's case), integer grids ~100-190 and
#: >= 256; contact patterns of 3..57 taxels: the chain is 3-12x faster hot, 2.3-4.8x cold.
SMALL_SET_MAX = 128

_METHODS = ("auto", "exact", "qhull")


def _sorted_unique_rows(pts: np.ndarray) -> list[tuple[float, float]]:
    """Distinct rows of a validated (n, 2) array in lexicographic (x, then y) order, the order
    of ``np.unique(pts, axis=0)``; -0.0 is read as 0.0."""
    return sorted(set(map(tuple, (pts + 0.0).tolist())))


def _check_extent(unique: list[tuple[float, float]]) -> None:
    """ParameterError when a coordinate minus the first (lexicographically smallest) point
    overflows a float, as ``unique - unique[0]`` would (float subtraction rounds
    monotonically, so the extreme coordinates decide)."""
    x0, y0 = unique[0]
    xs = [p[0] for p in unique]
    ys = [p[1] for p in unique]
    if not all(math.isfinite(d) for d in (max(xs) - x0, max(ys) - y0, min(ys) - y0)):
        raise ParameterError("points", [[min(xs), min(ys)], [max(xs), max(ys)]],
                             "coordinate differences must be finite (extent overflows a float)")


def _half_chain(points: list[tuple[int, int, int]]) -> list[tuple[int, int, int]]:
    """One half of Andrew's monotone chain: keeps only strict left turns (exact ints)."""
    kept: list[tuple[int, int, int]] = []
    for p in points:
        px, py, _ = p
        while len(kept) >= 2:
            ax, ay, _ = kept[-2]
            bx, by, _ = kept[-1]
            if (bx - ax) * (py - ay) > (by - ay) * (px - ax):  # cross(a, b, p) > 0: left turn
                break
            kept.pop()
        kept.append(p)
    return kept


def _exact_chain(unique: list[tuple[float, float]]) -> tuple[list[tuple[float, float]], int, int]:
    """Hull of >= 3 sorted distinct finite points by Andrew's monotone chain, exactly.

    Every finite float is ``num / 2**k`` exactly (``float.as_integer_ratio``), so with the
    common denominator ``D`` (the largest ``2**k``) each coordinate times ``D`` is an exact
    Python int; the first point is subtracted (in ints, so without rounding) and the
    orientation tests are exact integer cross products: no tolerance, no rounding. Collinear,
    nearly collinear (1e-17 off a line) and 1e15-offset sets get the true hull: strict left
    turns only, so points on an edge are not vertices and a collinear set gives its two end
    points. Returns (vertices counter-clockwise from the lexicographically smallest point,
    twice the hull's area in units of ``1/D**2`` (eq 35 in exact integers), ``D``).
    """
    scaled, den = _exact_integers(unique)
    ring, twice_area = _exact_ring(scaled)
    return [unique[p[2]] for p in ring], twice_area, den


def _exact_integers(unique: list[tuple[float, float]]) -> tuple[list[tuple[int, int, int]], int]:
    """``(x, y, k)`` of each point ``unique[k]`` as exact ints over the common denominator ``D``
    (returned), less the first point (``_exact_chain``)."""
    rx = [x.as_integer_ratio() for x, _ in unique]
    ry = [y.as_integer_ratio() for _, y in unique]
    den = max(max(d for _, d in rx), max(d for _, d in ry))  # powers of two: the lcm is the max
    x0 = rx[0][0] * (den // rx[0][1])
    y0 = ry[0][0] * (den // ry[0][1])
    return [(a * (den // b) - x0, c * (den // d) - y0, k) for k, ((a, b), (c, d)) in enumerate(zip(rx, ry))], den


def _exact_ring(scaled: list[tuple[int, int, int]]) -> tuple[list[tuple[int, int, int]], int]:
    """The hull of >= 3 lexicographically sorted distinct integer points (Andrew's monotone
    chain, counter-clockwise from the first) and twice its area (eq 35 in exact integers)."""
    lower = _half_chain(scaled)
    upper = _half_chain(scaled[::-1])
    ring = lower[:-1] + upper[:-1]
    return ring, sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(ring, ring[1:] + ring[:1]))


def _area_of(twice_area: int, den: int) -> float:
    """``twice_area / (2 D^2)`` correctly rounded (int / int); inf beyond the largest float."""
    try:
        return twice_area / (2 * den * den)  # 0 for a segment
    except OverflowError:  # true area beyond the largest float: rounds to inf
        return math.inf


def _qhull(pts: np.ndarray) -> np.ndarray:
    """Qhull on the distinct points relative to the first one; exact chain for flat sets."""
    unique = np.unique(pts + 0.0, axis=0)  # + 0.0 turns -0.0 into 0.0
    if len(unique) <= 2:
        return unique
    with np.errstate(over="ignore"):
        local = unique - unique[0]
    if np.any(~np.isfinite(local)):
        raise ParameterError("points", [unique.min(axis=0).tolist(), unique.max(axis=0).tolist()],
                             "coordinate differences must be finite (extent overflows a float)")
    try:
        vertices = unique[ConvexHull(local).vertices]  # 2-D: counter-clockwise (scipy docs)
    except QhullError:  # flat input: collinear, or nearly so beyond Qhull's precision
        return np.array(_exact_chain([tuple(row) for row in unique.tolist()])[0], dtype=float)
    if signed_polygon_area(vertices) < 0:  # defensive: guarantee the documented orientation
        vertices = vertices[::-1]
    first = int(np.lexsort((vertices[:, 1], vertices[:, 0]))[0])  # start as the chain does
    return np.roll(vertices, -first, axis=0)


def convex_hull(points, method: str = "auto") -> np.ndarray:
    """Vertices of the convex hull of ``points`` (sec. 4.3.2, for eq 35), counter-clockwise,
    as a float (k, 2) array starting at the lexicographically smallest vertex (least x,
    then least y).

    Duplicates are merged first (the chapter's own example lists (11, 41.5) twice, sec.
    6.2.3.3). Degenerate sets: 0 points -> (0, 2); one distinct point -> that point;
    collinear points (including two distinct points) -> the two end points of the segment,
    in lexicographic order. Otherwise the hull's vertices only (points on an edge are not
    vertices), counter-clockwise (positive eq 35 area).

    ``method``: ``"exact"`` is Andrew's monotone chain with exact integer cross products
    (every float is an exact dyadic rational, see ``_exact_chain``); ``"qhull"`` is scipy's
    Qhull on the points relative to one of them (a large common offset such as 1e15 costs
    no precision), with the exact chain for the flat sets Qhull refuses, so no
    ``QhullError`` escapes; ``"auto"`` (default) takes the exact chain up to
    ``SMALL_SET_MAX`` input rows and Qhull above. Both give the same vertices wherever
    Qhull's floating-point answer is right; on sets nearly collinear to ~1e-15 of their
    extent Qhull may keep a slightly different vertex, the exact chain never does.
    ParameterError for a bad shape, non-finite coordinates, a coordinate extent that
    overflows a float, or an unknown ``method``.
    """
    if method not in _METHODS:
        raise ParameterError("method", method, f"one of {', '.join(_METHODS)}")
    pts = as_points(points)
    if len(pts) == 0:
        return pts
    if method == "qhull" or (method == "auto" and len(pts) > SMALL_SET_MAX):
        return _qhull(pts)
    unique = _sorted_unique_rows(pts)
    if len(unique) <= 2:
        return np.array(unique, dtype=float)
    _check_extent(unique)
    return np.array(_exact_chain(unique)[0], dtype=float)


def signed_polygon_area(vertices) -> float:
    """Shoelace sum of eq 35: ``1/2 sum (X_i Y_{i+1} - X_{i+1} Y_i)``, indices mod N.

    Positive for counter-clockwise vertices, negative for clockwise; 0 for fewer than 3.
    The sum is translation invariant, so it runs on the vertices relative to the first one:
    a large common offset (coordinates ~1e15, extent ~1) does not cancel the area away.
    """
    v = as_points(vertices, "vertices")
    if len(v) < 3:
        return 0.0
    local = v - v[0]
    x, y = local[:, 0], local[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    return 0.5 * float(np.sum(x * y1 - x1 * y))


def polygon_area(vertices) -> float:
    """Planar area of a simple polygon, eq 35 (shoelace), as an absolute value."""
    return abs(signed_polygon_area(vertices))


def contact_area(points) -> float:
    """Area of the friction plane: eq 35 applied to the convex hull of the excited taxels.

    Up to ``SMALL_SET_MAX`` points the shoelace sum runs in the exact integers of the hull
    (``_exact_chain``) and one correctly rounded division gives the area: the float nearest
    the true area of the hull of the given floats (``polygon_area(convex_hull(points))``
    sums in floats and may differ from it in the last bits). Above, it is exactly
    ``polygon_area(convex_hull(points))``. 0.0 for fewer than 3 distinct or collinear points;
    ``inf`` when the true area exceeds the largest float (extent ~1e155 and more).
    """
    pts = as_points(points)
    if len(pts) > SMALL_SET_MAX:
        return polygon_area(convex_hull(pts))
    unique = _sorted_unique_rows(pts) if len(pts) else []
    if len(unique) <= 2:
        return 0.0
    _check_extent(unique)
    _, twice_area, den = _exact_chain(unique)
    return _area_of(twice_area, den)


def active_centroid(points) -> np.ndarray:
    """Centroid of the distinct locations in ``points``; (nan, nan) for an empty set.

    Two taxels of an R-cell share one location (sec. 6.2.3.3); counting the location once
    keeps the centroid from jumping when only one of the pair fires.
    """
    pts = as_points(points)
    if len(pts) == 0:
        return np.array([np.nan, np.nan])
    return np.unique(pts, axis=0).mean(axis=0)


class Locations:
    """The distinct locations of a fixed set of points - a scene's taxels, two of an R-cell
    sharing one - sorted once, for the centroid and the contact area of any subset of them:
    :meth:`centroid` of a mask is ``active_centroid(points[mask])`` bit for bit (the same
    sorted distinct rows, the same mean) and :meth:`contact_area` is ``contact_area(points[mask])``,
    without sorting and converting the subset again each cycle (at 4,096 taxels ``np.unique``
    of the active rows was most of the slip tracker's cost per cycle, and the conversion to
    exact integers most of a new contact pattern's area)."""

    def __init__(self, points):
        pts = as_points(points)
        self.points = pts
        self.rows, inverse = np.unique(pts, axis=0, return_inverse=True)
        self.row_of = np.asarray(inverse).reshape(-1)  # the distinct row of each point
        self._exact = None  # (the rows in _exact_chain's integers, denominator), at the first area

    def _exact_rows(self):
        """Every distinct row as exact integers over one common power-of-two denominator, less
        the first row (``_exact_chain``'s coordinates, once for the whole layout); None when
        the layout's extent (largest minus smallest coordinate) overflows a float - then a
        subset's may too, and each subset is left to contact_area - or the layout is empty.
        Below, every subset's coordinate differences are finite (no larger than the extent)."""
        if self._exact is None:
            unique = [tuple(row) for row in self.rows.tolist()]
            with np.errstate(over="ignore"):
                extent = self.rows.max(axis=0) - self.rows.min(axis=0) if unique else np.full(2, np.inf)
            if not np.isfinite(extent).all():
                # empty, or some subset's differences may overflow: contact_area decides each
                self._exact = (None, 0)
                return self._exact
            self._exact = _exact_integers(unique)
        return self._exact

    def contact_area(self, mask) -> float:
        """``contact_area(points[mask])`` (eq 35 on the hull of the subset), the same float:
        up to ``SMALL_SET_MAX`` points the hull's exact integer area over the layout's common
        denominator - the same rational as over the subset's own, so the same correctly
        rounded division - from rows sorted and converted once; above, or for a layout whose
        extent overflows, contact_area itself."""
        mask = np.asarray(mask, dtype=bool)
        scaled, den = self._exact_rows()
        if not scaled or np.count_nonzero(mask) > SMALL_SET_MAX:
            return contact_area(self.points[mask])
        seen = np.zeros(len(self.rows), dtype=bool)
        seen[self.row_of[mask]] = True
        subset = [scaled[i] for i in np.flatnonzero(seen).tolist()]  # lexicographic, as _exact_chain's
        if len(subset) <= 2:
            return 0.0
        return _area_of(_exact_ring(subset)[1], den)

    def centroid(self, mask) -> np.ndarray:
        """Centroid of the distinct locations of the points where ``mask`` (bool, one per
        point) is set; (nan, nan) for none."""
        seen = np.zeros(len(self.rows), dtype=bool)
        seen[self.row_of[np.asarray(mask, dtype=bool)]] = True
        if not seen.any():
            return np.array([np.nan, np.nan])
        return self.rows[seen].mean(axis=0)
