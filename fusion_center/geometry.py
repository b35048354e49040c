"""Contact geometry: convex hull of the excited taxels and its planar area (sec. 4.3.2, 6.2.3.3).

The chapter's program collects the coordinates of the taxels with u_i = +1, finds the
points on their convex hull and computes the hull's planar area with the shoelace formula,
eq 35. Here the hull comes from scipy's Qhull (``scipy.spatial.ConvexHull``) for the
general case; the degenerate sets Qhull rejects (fewer than three distinct points, all
points collinear or too nearly so for its precision) are handled explicitly (exact
monotone chain), so no ``QhullError`` escapes.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
from scipy.spatial import ConvexHull

try:  # scipy >= 1.11 exposes it here
    from scipy.spatial import QhullError
except ImportError:  # pragma: no cover - older scipy
    from scipy.spatial.qhull import QhullError  # type: ignore

from .errors import ParameterError

__all__ = ["as_points", "convex_hull", "polygon_area", "signed_polygon_area", "contact_area",
           "active_centroid"]


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
    if np.any(~np.isfinite(arr)):
        i = int(np.argwhere(~np.isfinite(arr))[0][0])
        raise ParameterError(f"{name}[{i}]", arr[i].tolist(), "coordinates must be finite")
    return arr


def _exact_hull(unique: np.ndarray) -> np.ndarray:
    """Hull vertices of lexicographically sorted distinct points, exact (Andrew's monotone chain).

    The orientation test runs on :class:`fractions.Fraction` copies of the floats (every
    float is an exact rational), so collinear, nearly collinear and offset sets get the
    true answer: a collinear set gives its two end points, a thin triangle its three
    corners. Used where Qhull refuses the input as flat.
    """
    exact = [(Fraction(x), Fraction(y)) for x, y in unique.tolist()]

    def left_turn(o, a, b) -> bool:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]) > 0

    def chain(order) -> list[int]:
        kept: list[int] = []
        for k in order:
            while len(kept) >= 2 and not left_turn(exact[kept[-2]], exact[kept[-1]], exact[k]):
                kept.pop()
            kept.append(k)
        return kept

    n = len(exact)
    lower, upper = chain(range(n)), chain(range(n - 1, -1, -1))
    return unique[lower[:-1] + upper[:-1]]


def convex_hull(points) -> np.ndarray:
    """Vertices of the convex hull of ``points``, counter-clockwise, as a (k, 2) array.

    Duplicates are merged first (the chapter's own example lists (11, 41.5) twice, sec.
    6.2.3.3). Degenerate sets: 0 points -> (0, 2); one distinct point -> that point;
    collinear points (including two distinct points) -> the two end points of the segment,
    in lexicographic order. Otherwise the hull's vertices only (points on an edge are not
    vertices), counter-clockwise (positive eq 35 area). Qhull sees the points relative to
    one of them, so a large common offset (e.g. 1e15) costs no precision; the flat sets
    Qhull refuses (``QhullError``) go to an exact monotone chain instead.
    """
    pts = as_points(points)
    if len(pts) == 0:
        return pts
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
        return _exact_hull(unique)
    if signed_polygon_area(vertices) < 0:  # defensive: guarantee the documented orientation
        vertices = vertices[::-1]
    return vertices


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
    """Area of the friction plane: eq 35 applied to the convex hull of the excited taxels."""
    return polygon_area(convex_hull(points))


def active_centroid(points) -> np.ndarray:
    """Centroid of the distinct locations in ``points``; (nan, nan) for an empty set.

    Two taxels of an R-cell share one location (sec. 6.2.3.3); counting the location once
    keeps the centroid from jumping when only one of the pair fires.
    """
    pts = as_points(points)
    if len(pts) == 0:
        return np.array([np.nan, np.nan])
    return np.unique(pts, axis=0).mean(axis=0)
