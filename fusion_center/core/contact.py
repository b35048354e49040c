"""Contact-type metrics: t_c, fp_c, Table 1 classes, RSI and fig. 15's zones (sec. 5).

Table 1 (sec. 5.2) maps the taxel-count ratio t_c (eq 34a) or the friction-plane area
ratio fp_c (eq 34b) to a contact type. Its printed ranges overlap
(point force 0.01-0.02, small object 0.01-0.1, larger object 0.1-1); the precedence used
here, with all limits parameters:

* ratio < 0.01                 -> ``no_contact``   (below every row of Table 1)
* 0.01 <= ratio <= 0.02        -> ``point_force``  (frictionless point contact; the
  narrower row wins inside the overlap)
* 0.02 < ratio < 0.1           -> ``small_object`` (point contact with friction)
* 0.1 <= ratio <= 1            -> ``larger_object`` (soft-finger contact; 0.1 is shared by
  rows 2 and 3 and goes to the larger object)
"""

from __future__ import annotations

from enum import Enum

import numpy as np

from taxel_net.errors import ParameterError

__all__ = [
    "ContactType", "CONTACT_MECHANICS", "classify", "classify_ratio", "taxel_count_ratio",
    "friction_plane_ratio", "relative_softness_index", "ContactZone", "contact_zone",
    "POINT_FORCE_MIN", "POINT_FORCE_MAX", "LARGER_OBJECT_MIN",
]

POINT_FORCE_MIN = 0.01      # Table 1, lower limit of every contact row
POINT_FORCE_MAX = 0.02      # Table 1, row 1 upper limit
LARGER_OBJECT_MIN = 0.1     # Table 1, row 3 lower limit (= row 2 upper limit)


class ContactType(str, Enum):
    """Equivalent object nomenclature of Table 1 (plus "no contact" below its range)."""

    NO_CONTACT = "no_contact"
    POINT_FORCE = "point_force"
    SMALL_OBJECT = "small_object"
    LARGER_OBJECT = "larger_object"


_CLASS_LIST = (ContactType.NO_CONTACT, ContactType.POINT_FORCE, ContactType.SMALL_OBJECT,
               ContactType.LARGER_OBJECT)  # by precedence row 0..3
_CLASSES = np.array(_CLASS_LIST, dtype=object)


def _row(r, point_force_min, point_force_max, larger_object_min):
    """Precedence row 0..3 of a ratio (module docstring): the number of Table 1 boundaries it
    has reached. The one definition of the boundaries, for a float or a float array alike
    (0 <= point_force_min <= point_force_max < larger_object_min <= 1 assumed)."""
    return 1 * (r >= point_force_min) + 1 * (r > point_force_max) + 1 * (r >= larger_object_min)


def _check_limits(point_force_min, point_force_max, larger_object_min) -> None:
    if not (0 <= point_force_min <= point_force_max < larger_object_min <= 1):
        raise ParameterError(
            "limits", (point_force_min, point_force_max, larger_object_min),
            "need 0 <= point_force_min <= point_force_max < larger_object_min <= 1")

#: Table 1's "Contact Type" column for each class.
CONTACT_MECHANICS: dict[ContactType, str] = {
    ContactType.NO_CONTACT: "none",
    ContactType.POINT_FORCE: "point contact (without friction)",
    ContactType.SMALL_OBJECT: "point contact (with friction)",
    ContactType.LARGER_OBJECT: "soft finger contact",
}


def _number(value, name: str, array: bool = False):
    """``value`` as a float (or float array); non-numeric input is a ParameterError."""
    try:
        return np.asarray(value, dtype=float) if array else float(value)
    except (TypeError, ValueError):
        raise ParameterError(name, value, "must be a number") from None


def classify(ratio, *, point_force_min: float = POINT_FORCE_MIN,
             point_force_max: float = POINT_FORCE_MAX,
             larger_object_min: float = LARGER_OBJECT_MIN):
    """Contact type of a t_c or fp_c ratio by Table 1 (precedence in the module docstring).

    ``ratio`` must lie in [0, 1] (NaN refused). A scalar gives a :class:`ContactType`; an
    array gives an object array of them with the same shape.
    """
    _check_limits(point_force_min, point_force_max, larger_object_min)
    r = _number(ratio, "ratio", array=True)
    bad = ~np.isfinite(r) | (r < 0) | (r > 1)
    if np.any(bad):
        value = float(r[bad][0]) if r.ndim else float(r)
        raise ParameterError("ratio", value, "t_c / fp_c must be a number in [0, 1]")
    rows = _row(r, point_force_min, point_force_max, larger_object_min)
    return _CLASSES[rows] if r.ndim else _CLASSES[int(rows)]


def classify_ratio(ratio: float, *, point_force_min: float = POINT_FORCE_MIN,
                   point_force_max: float = POINT_FORCE_MAX,
                   larger_object_min: float = LARGER_OBJECT_MIN) -> ContactType:
    """:func:`classify` for one ratio (t_c of eq 34a or fp_c of eq 34b) without numpy: the
    same Table 1 boundaries (``_row``) and checks, for the live pipeline's per-cycle record."""
    _check_limits(point_force_min, point_force_max, larger_object_min)
    r = _number(ratio, "ratio")
    if not 0.0 <= r <= 1.0:  # NaN fails too
        raise ParameterError("ratio", r, "t_c / fp_c must be a number in [0, 1]")
    return _CLASS_LIST[_row(r, point_force_min, point_force_max, larger_object_min)]


def taxel_count_ratio(n_affected, n_total) -> float:
    """Taxel_Count, eq 34a: ``t_c = N_affected / N_total`` (0 <= N_affected <= N_total, N_total >= 1)."""
    for value, name in ((n_affected, "n_affected"), (n_total, "n_total")):
        try:
            whole = not isinstance(value, bool) and float(value).is_integer()
        except (TypeError, ValueError, OverflowError):
            whole = False
        if not whole:
            raise ParameterError(name, value, "must be a whole number of taxels")
    if n_total < 1:
        raise ParameterError("n_total", n_total, "must be >= 1")
    if not 0 <= n_affected <= n_total:
        raise ParameterError("n_affected", n_affected, f"must lie in [0, n_total={n_total}]")
    return float(n_affected) / float(n_total)


def friction_plane_ratio(area, total_area) -> float:
    """Friction_Plane_Area_Count, eq 34b: ``fp_c = Δ_friction_plane / Δ_total``.

    ``total_area`` > 0 is the sensor's planar area; 0 <= ``area`` <= ``total_area``.
    """
    a, t = _number(area, "area"), _number(total_area, "total_area")
    if not np.isfinite(t) or t <= 0:
        raise ParameterError("total_area", total_area, "must be a finite area > 0")
    if not np.isfinite(a) or a < 0 or a > t * (1 + 1e-12):
        raise ParameterError("area", area, f"must lie in [0, total_area={t}]")
    return min(a / t, 1.0)


def relative_softness_index(hardness_jaw, hardness_object):
    """Relative softness index, eq 33: ``RSI = (1/H_O)/(1/H_J) - 1 = H_J/H_O - 1``.

    Hardness values on one uniform (Rockwell) scale, finite and > 0. RSI > 0: object softer
    than the jaw; RSI = 0: equal hardness (fig. 15's locked contact); -1 < RSI < 0: jaw softer.
    """
    hj = _number(hardness_jaw, "hardness_jaw", array=True)
    ho = _number(hardness_object, "hardness_object", array=True)
    for arr, name, raw in ((hj, "hardness_jaw", hardness_jaw), (ho, "hardness_object", hardness_object)):
        if np.any(~np.isfinite(arr)) or np.any(arr <= 0):
            raise ParameterError(name, raw, "hardness must be finite and > 0 (one uniform scale)")
    out = hj / ho - 1.0
    return float(out) if out.ndim == 0 else out


class ContactZone(str, Enum):
    """Contact zones of fig. 15 along the RSI axis."""

    LOCKED = "locked_contact"
    POINT_WITHOUT_FRICTION = "point_contact_without_friction"
    POINT_WITH_FRICTION = "point_contact_with_friction"
    SOFT_FINGER = "soft_finger_contact"


def contact_zone(rsi, *, frictionless_below: float = 0.25, soft_finger_from: float = 3.0,
                 locked_tolerance: float = 1e-9) -> ContactZone:
    """Contact zone of fig. 15 for a relative softness index (eq 33).

    Fig. 15 is missing from the text; sec. 5.1 fixes only its shape: locked contact at
    RSI = 0, point contact without friction for very low RSI, soft finger for high RSI and
    point contact with friction in a "fairly large range" in between. Boundaries (parameters):
    ``|RSI| <= locked_tolerance`` -> locked; ``RSI < frictionless_below`` -> point without
    friction; ``RSI < soft_finger_from`` -> point with friction; else soft finger.
    RSI < 0 (jaw softer than object, "impractical" per the chapter's footnote 1) falls in the
    low-RSI zone. RSI <= -1 is impossible for positive hardness and is refused.
    """
    if not (0 <= locked_tolerance < frictionless_below < soft_finger_from) or not np.isfinite(soft_finger_from):
        raise ParameterError("zone limits", (locked_tolerance, frictionless_below, soft_finger_from),
                             "need 0 <= locked_tolerance < frictionless_below < soft_finger_from < inf")
    try:
        r = float(rsi)
    except (TypeError, ValueError):
        raise ParameterError("rsi", rsi, "must be a finite number > -1") from None
    if not np.isfinite(r) or r <= -1:
        raise ParameterError("rsi", rsi, "RSI = H_J/H_O - 1 must be finite and > -1")
    if abs(r) <= locked_tolerance:
        return ContactZone.LOCKED
    if r < frictionless_below:
        return ContactZone.POINT_WITHOUT_FRICTION
    if r < soft_finger_from:
        return ContactZone.POINT_WITH_FRICTION
    return ContactZone.SOFT_FINGER
