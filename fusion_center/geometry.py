"""Contact geometry: convex hull of the excited taxels and its planar area (sec. 4.3.2, 6.2.3.3).

The chapter's program collects the coordinates of the taxels with u_i = +1, finds the
points on their convex hull and computes the hull's planar area with the shoelace formula,
eq 35. Here the hull comes from scipy's Qhull (``scipy.spatial.ConvexHull``) for the
general case; the degenerate sets Qhull rejects (fewer than three distinct points, all
points collinear) are handled explicitly, so no ``QhullError`` escapes.
"""

from __future__ import annotations

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


def _collinear(pts: np.ndarray) -> bool:
    centred = pts - pts.mean(axis=0)
    scale = max(float(np.abs(centred).max()), 1.0)
    sv = np.linalg.svd(centred / scale, compute_uv=False)
    return bool(sv[-1] <= 1e-12 * max(sv[0], 1e-300) * len(pts))


def _segment_ends(pts: np.ndarray) -> np.ndarray:
    """The two extreme points of a collinear set (ordered lexicographically)."""
    centred = pts - pts.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    proj = centred @ vt[0]
    ends = pts[[int(np.argmin(proj)), int(np.argmax(proj))]]
    order = np.lexsort((ends[:, 1], ends[:, 0]))
    return ends[order]


def convex_hull(points) -> np.ndarray:
    """Vertices of the convex hull of ``points``, counter-clockwise, as a (k, 2) array.

    Duplicates are merged first (the chapter's own example lists (11, 41.5) twice, sec.
    6.2.3.3). Degenerate sets: 0 points -> (0, 2); one distinct point -> that point;
    collinear points (including two distinct points) -> the two end points of the segment.
    Otherwise the hull's vertices only (points on an edge are not vertices), starting at
    the vertex Qhull reports first, counter-clockwise (positive shoelace area).
    """
    pts = as_points(points)
    if len(pts) == 0:
        return pts
    unique = np.unique(pts, axis=0)
    if len(unique) == 1:
        return unique
    if len(unique) == 2 or _collinear(unique):
        return _segment_ends(unique)
    try:
        hull = ConvexHull(unique)
    except QhullError:  # nearly collinear beyond our tolerance: Qhull's precision check
        return _segment_ends(unique)
    vertices = unique[hull.vertices]  # 2-D: counter-clockwise order (scipy docs)
    if signed_polygon_area(vertices) < 0:  # defensive: guarantee the documented orientation
        vertices = vertices[::-1]
    return vertices


def signed_polygon_area(vertices) -> float:
    """Shoelace sum of eq 35: ``1/2 sum (X_i Y_{i+1} - X_{i+1} Y_i)``, indices mod N.

    Positive for counter-clockwise vertices, negative for clockwise; 0 for fewer than 3.
    """
    v = as_points(vertices, "vertices")
    if len(v) < 3:
        return 0.0
    x, y = v[:, 0], v[:, 1]
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
