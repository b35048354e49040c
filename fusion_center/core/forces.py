"""Tangential (slip) force, grip-force limit and allowable load (chapter sec. 4.1, 4.2, 7).

Calibration convention (eqs 23, 27a, 36): a cell's reading in mV is ``y = m F + c`` with
slope ``m`` (mV per force unit) and intercept ``c`` (mV), so eq 30 inverts it as
``F = (y - c) / m``. Sec. 7.1 prints eq 36 as ``Y = m F - 0.0155`` and the pairs as
``(0.1661, -0.0155)``: both say c = -0.0155 mV, the sign convention used here (see
docs/chapter-notes.md for the check against the printed forces).

Units: readings are mV; every force is in the unit the calibration maps to. The pure
functions return plain floats/arrays in that unit; :class:`ForceReport` carries the unit
explicitly (``"kgf"`` or ``"N"``, converted with 1 kgf = 9.80665 N).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from taxel_net.errors import ParameterError
from .units import check_force_unit, convert_force

__all__ = [
    "tangential_force",
    "r_cell_tangential_force",
    "compose_pair",
    "total_tangential",
    "jaw_tangential",
    "gripper_tangential",
    "grip_force_limit",
    "max_load",
    "load_cell_grip_force",
    "LoadCellGrip",
    "ForceReport",
    "matrix_force_report",
    "LayoutForces",
    "CycleForces",
]


# --------------------------------------------------------------------------- validation
def _as_float_array(value, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError(name, value, "must be numeric (a number or an array of numbers)") from None
    return arr


def _raise_at_first(bad: np.ndarray, values: np.ndarray, name: str, allowed: str, axis: int = -1) -> None:
    """ParameterError ``name[cell]`` for the first True of ``bad``; the cell is its index on ``axis``."""
    if np.any(bad):
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        cell = idx[axis] if idx else 0
        raise ParameterError(f"{name}[{cell}]", float(values[idx]), allowed)


def _check_finite(values: np.ndarray, name: str, allowed: str, axis: int = -1) -> None:
    _raise_at_first(~np.isfinite(values), values, name, allowed, axis)


def _check_slopes(slope: np.ndarray, name: str = "slope") -> None:
    _raise_at_first((slope == 0) | ~np.isfinite(slope), slope, name,
                    "calibration slope m must be finite and non-zero (slope 0 = cell without "
                    "tangential calibration, eq 30 cannot invert it)")


def _check_per_cell(arr: np.ndarray, name: str, n_cells: int, what: str) -> None:
    """``arr`` must be a scalar or hold one value per cell; a mismatch names the first cell
    that has a reading but no value (or a value but no reading)."""
    if arr.ndim == 0 or (arr.ndim == 1 and arr.shape[0] == n_cells):
        return
    if arr.ndim > 1:
        raise ParameterError(name, arr.tolist(), f"must be a scalar or a 1-D array, one per {what}")
    cell = min(arr.shape[0], n_cells)
    value = float(arr[cell]) if cell < arr.shape[0] else "missing"
    side = f"{what} {cell} has no {name}" if cell == arr.shape[0] else f"{name}[{cell}] has no {what}"
    raise ParameterError(f"{name}[{cell}]", value,
                         f"{arr.shape[0]} values for {n_cells} {what}s ({side}): "
                         f"give a scalar or one value per {what}")


def _check_mu(mu) -> float:
    try:
        mu_f = float(mu)
    except (TypeError, ValueError):
        raise ParameterError("mu", mu, "friction coefficient must be a finite number > 0") from None
    if not np.isfinite(mu_f) or mu_f <= 0:
        raise ParameterError("mu", mu, "friction coefficient must be a finite number > 0")
    return mu_f


def _check_angle(inclusion_angle, count: int | None = None) -> np.ndarray:
    alpha = _as_float_array(inclusion_angle, "inclusion_angle")
    if np.any(~np.isfinite(alpha)) or np.any(alpha < 0) or np.any(alpha > np.pi):
        raise ParameterError("inclusion_angle", inclusion_angle,
                             "inclusion angle alpha must lie in [0, pi] radians")
    if alpha.ndim > 1 or (alpha.ndim == 1 and count is not None and alpha.shape[0] != count):
        raise ParameterError("inclusion_angle", inclusion_angle,
                             f"must be a scalar or one angle per composition step ({count})")
    return alpha


# --------------------------------------------------------------------------- eq 23 / 27a / 30
def tangential_force(readings, slope, intercept) -> np.ndarray:
    """Per-cell tangential force, eq 30 (inverse of the calibration line eq 23 / 27a).

    ``F_t[i] = (y[i] - incpt[i]) / slope[i]``. ``readings`` (mV) may have leading axes (e.g.
    cycles x cells); ``slope`` and ``intercept`` are per cell (last axis) or scalars. Result
    in the calibration's force unit. A zero (also -0.0) or non-finite slope, a non-finite
    reading or intercept, or mismatched lengths raise ParameterError naming the cell index.
    """
    y = _as_float_array(readings, "readings")
    m = _as_float_array(slope, "slope")
    c = _as_float_array(intercept, "intercept")
    if y.ndim == 0:
        y = y.reshape(1)
    n_cells = y.shape[-1]
    _check_per_cell(m, "slope", n_cells, "cell")
    _check_per_cell(c, "intercept", n_cells, "cell")
    _check_slopes(np.broadcast_to(m, (n_cells,)))
    _check_finite(np.broadcast_to(c, (n_cells,)), "intercept", "intercept must be finite (mV)")
    _check_finite(y, "readings", "reading must be a finite number of mV (NaN = no data)")
    return (y - c) / m


def r_cell_tangential_force(taxel_readings, slope, intercept) -> np.ndarray:
    """Tangential force per R-cell (strut) from its two taxels, eqs 36 and 30.

    Eq 36 calibrates the *strut* output ``Y_R = m F_T + c``; the two strain gauges of a strut
    are its two taxels (sec. 3.1, 6.1), so the strut output is taken as the sum of the two
    taxel readings and eq 30 is applied once per strut. ``taxel_readings`` has shape
    (..., n_struts, 2); ``slope``/``intercept`` one per strut. This is the reading of sec. 7.1
    that reproduces its printed total 6.121 kgf (docs/chapter-notes.md).
    """
    y = _as_float_array(taxel_readings, "taxel_readings")
    if y.ndim < 2 or y.shape[-1] != 2:
        raise ParameterError("taxel_readings", y.shape,
                             "must have shape (..., n_struts, 2): two taxels per R-cell")
    _check_finite(y, "taxel_readings", "reading must be a finite number of mV (index = strut)", axis=-2)
    return tangential_force(y.sum(axis=-1), slope, intercept)


# --------------------------------------------------------------------------- eqs 24, 25, 28, 29
def compose_pair(force_a, force_b, inclusion_angle=0.0) -> np.ndarray:
    """Magnitude of the vector sum of two coplanar forces, eq 25 / 28b (law of cosines).

    ``sqrt(F1^2 + F2^2 + 2 F1 F2 cos(alpha))`` on the magnitudes |F1|, |F2|, so that
    alpha = 0 (parallel cells) gives |F1| + |F2| exactly as eq 25 states.
    """
    a = np.abs(_as_float_array(force_a, "force_a"))
    b = np.abs(_as_float_array(force_b, "force_b"))
    alpha = _check_angle(inclusion_angle)
    if np.ndim(alpha) == 0 and float(alpha) == 0.0:
        return a + b  # exact: eq 25 "≡ |F1| + |F2|"
    sq = a * a + b * b + 2.0 * a * b * np.cos(alpha)
    return np.sqrt(np.maximum(sq, 0.0))


def total_tangential(forces, inclusion_angle=0.0):
    """Total tangential (slip) force on the sensor, eq 24 with eq 25 composition.

    ``TotF_t = F^(1,2) + F^3 + ... + F^m``: the running resultant is composed with the next
    cell force by eq 25, each step at ``inclusion_angle`` alpha (radians, scalar or one per
    step, i.e. m-1 values). alpha = 0 (default; the matrix sensor's cells are "co-planar
    and parallel", sec. 4.1) gives the sum of magnitudes. ``forces`` is (..., m); the last
    axis is summed. An empty set gives 0. Returns a float for 1-D input.
    """
    f = _as_float_array(forces, "forces")
    if f.ndim == 0:
        f = f.reshape(1)
    _check_finite(f, "forces", "force must be finite")
    m = f.shape[-1]
    alpha = _check_angle(inclusion_angle, max(m - 1, 0))
    if m == 0:
        out = np.zeros(f.shape[:-1])
    elif np.all(alpha == 0):
        out = np.abs(f).sum(axis=-1)
    else:
        steps = np.broadcast_to(alpha, (max(m - 1, 0),))
        out = np.abs(f[..., 0])
        for k in range(1, m):
            out = compose_pair(out, f[..., k], steps[k - 1])
    return float(out) if np.ndim(out) == 0 else out


def _pairwise_tree(values: np.ndarray, alpha) -> np.ndarray:
    """Eq 28a: compose (1,2), (3,4), ... by eq 28b, then compose the pair results."""
    level = [values[..., k] for k in range(values.shape[-1])]
    while len(level) > 1:
        nxt = [compose_pair(level[k], level[k + 1], alpha) for k in range(0, len(level) - 1, 2)]
        if len(level) % 2:
            nxt.append(np.abs(level[-1]))
        level = nxt
    return np.abs(level[0])


def jaw_tangential(fy_cells, fx_cell, inclusion_angle=0.0):
    """Total tangential force on one gripper jaw, eqs 28a, 28b and 29.

    ``TotF_t-y = F^(1,2)_t-y + F^(3,4)_t-y`` (eq 28a) with each pair composed by eq 28b at
    inclusion angle alpha (radians; default 0 = parallel cells, giving the plain sum), then
    ``TotF_t = sqrt(TotF_t-y^2 + F_t-x^2)`` (eq 29: the x and y totals are orthogonal).
    ``fy_cells`` is (..., k) with k >= 1 y-axis TBS forces (4 in the chapter); ``fx_cell``
    the x-axis TBS force (scalar or (...)).
    """
    fy = _as_float_array(fy_cells, "fy_cells")
    fx = _as_float_array(fx_cell, "fx_cell")
    if fy.ndim == 0 or fy.shape[-1] == 0:
        raise ParameterError("fy_cells", fy.tolist(), "need at least one y-axis TBS force")
    for arr, name in ((fy, "fy_cells"), (fx, "fx_cell")):
        if np.any(~np.isfinite(arr)):
            raise ParameterError(name, arr.tolist(), "forces must be finite")
    alpha = _check_angle(inclusion_angle)
    if alpha.ndim != 0:
        raise ParameterError("inclusion_angle", inclusion_angle, "must be a scalar for eq 28")
    tot_y = _pairwise_tree(fy, alpha)
    out = np.sqrt(tot_y * tot_y + fx * fx)
    return float(out) if np.ndim(out) == 0 else out


def gripper_tangential(left_fy, left_fx, right_fy, right_fx, inclusion_angle=0.0):
    """Tangential force on the object averaged over both jaws (sec. 7.2, eqs 28-29).

    Mean of :func:`jaw_tangential` of the left and the right jaw.
    """
    left = jaw_tangential(left_fy, left_fx, inclusion_angle)
    right = jaw_tangential(right_fy, right_fx, inclusion_angle)
    out = 0.5 * (np.asarray(left) + np.asarray(right))
    return float(out) if np.ndim(out) == 0 else out


# --------------------------------------------------------------------------- eqs 26a / 26b
def grip_force_limit(total_tangential, mu):
    """Upper threshold of the gripping force, eq 26a: ``F_g^cal = TotF_t / mu``.

    Eq 26a itself is missing from the chapter's text; sec. 7.1 (6.121 kgf, mu = 0.3 ->
    20.41 kgf) pins this form down. ``mu`` is the kinetic friction coefficient (> 0).
    """
    mu_f = _check_mu(mu)
    t = _as_float_array(total_tangential, "total_tangential")
    if np.any(~np.isfinite(t)) or np.any(t < 0):
        raise ParameterError("total_tangential", total_tangential,
                             "total tangential force must be finite and >= 0")
    out = t / mu_f
    return float(out) if out.ndim == 0 else out


def max_load(grip_force, mu):
    """Maximum allowable load (weight) of the two-jaw grasp, eq 26b: ``W = 2 mu F_g^cal``."""
    mu_f = _check_mu(mu)
    g = _as_float_array(grip_force, "grip_force")
    if np.any(~np.isfinite(g)) or np.any(g < 0):
        raise ParameterError("grip_force", grip_force, "grip force must be finite and >= 0")
    out = 2.0 * mu_f * g
    return float(out) if out.ndim == 0 else out


# --------------------------------------------------------------------------- eq 27b
class LoadCellGrip(NamedTuple):
    per_jaw: np.ndarray   # F_g per load cell (one per jaw), calibration unit
    mean: float | np.ndarray  # mean over the jaws (sec. 7.2: "(3.91/M) kgf")


def load_cell_grip_force(readings, grip_factor) -> LoadCellGrip:
    """Grip force from the load cells, eq 27b: ``Y_j = M F_g`` so ``F_g = Y_j / M``.

    ``readings`` (mV) is (..., n_jaws); ``grip_factor`` M (mV per force unit) per jaw or
    scalar, finite and non-zero. Returns the per-jaw forces and their mean over the jaws.
    """
    y = _as_float_array(readings, "readings")
    if y.ndim == 0:
        y = y.reshape(1)
    factor = _as_float_array(grip_factor, "grip_factor")
    n = y.shape[-1]
    if n == 0:
        raise ParameterError("readings", [], "need at least one load-cell reading")
    _check_per_cell(factor, "grip_factor", n, "load cell")
    _check_slopes(np.broadcast_to(factor, (n,)), "grip_factor")
    _check_finite(y, "readings", "reading must be a finite number of mV")
    per_jaw = y / factor
    mean = per_jaw.mean(axis=-1)
    return LoadCellGrip(per_jaw, float(mean) if mean.ndim == 0 else mean)


# --------------------------------------------------------------------------- report with unit
@dataclass(frozen=True)
class ForceReport:
    """Forces of one cycle with their unit carried explicitly (sec. 4.1, 7.1)."""

    per_cell: np.ndarray        # eq 30, per calibrated cell
    total_tangential: float     # eqs 24-25
    grip_force_limit: float     # eq 26a
    max_load: float             # eq 26b
    mu: float
    unit: str                   # "kgf" | "N"

    def to(self, unit: str) -> "ForceReport":
        """The same report in another force unit (1 kgf = 9.80665 N)."""
        check_force_unit(unit)
        return ForceReport(
            per_cell=convert_force(self.per_cell, self.unit, unit),
            total_tangential=convert_force(self.total_tangential, self.unit, unit),
            grip_force_limit=convert_force(self.grip_force_limit, self.unit, unit),
            max_load=convert_force(self.max_load, self.unit, unit),
            mu=self.mu,
            unit=unit,
        )


def matrix_force_report(readings, slope, intercept, mu, *, unit: str,
                        inclusion_angle=0.0) -> ForceReport:
    """Eqs 30, 24-25, 26a, 26b for one cycle of the matrix sensor.

    ``unit`` names the force unit the calibration (slope in mV per unit) maps to; it is
    required, so a result never has an implied unit.
    """
    check_force_unit(unit)
    per_cell = tangential_force(readings, slope, intercept)
    if per_cell.ndim != 1:
        raise ParameterError("readings", np.shape(readings), "one cycle: a 1-D array of readings")
    total = total_tangential(per_cell, inclusion_angle)
    limit = grip_force_limit(total, mu)
    return ForceReport(per_cell, total, limit, max_load(limit, mu), float(mu), unit)


# --------------------------------------------------------------------------- one layout, per cycle
SEQUENTIAL_SUM_MAX = 7  # numpy sums fewer than 8 float64 values left to right (pairwise above)


def _abs_sum(values: list[float]) -> float:
    """``float(np.abs(np.array(values)).sum())`` with the same rounding: left to right from -0.0
    for a few values (what numpy's pairwise summation does below 8 values), numpy above."""
    if len(values) > SEQUENTIAL_SUM_MAX:
        return float(np.abs(np.array(values, dtype=float)).sum())
    out = -0.0
    for v in values:
        out += abs(v)
    return out


def _mean(values: list[float]) -> float:
    """``float(np.mean(values))`` with the same rounding (see :func:`_abs_sum`)."""
    if len(values) > SEQUENTIAL_SUM_MAX:
        return float(np.mean(np.array(values, dtype=float)))
    out = -0.0
    for v in values:
        out += v
    return out / len(values)


class CycleForces(NamedTuple):
    """One cycle's forces of a :class:`LayoutForces` (calibration unit)."""

    per_cell: list[tuple[int, float]]   # (cell index, F_t eq 30) of the cells used, in index order
    per_jaw: dict[str, float] | None    # eqs 28a/28b/29 per jaw (jaw layout), else None
    total: float | None                 # TotF_t (eqs 24-25, or the mean of per_jaw); None: no tangential cell
    grip_per_cell: list[float] | None   # eq 27b per load cell, 0.0 where it is not used; None: no load cell
    grip: float | None                  # the mean of grip_per_cell (sec 7.2)


class LayoutForces:
    """Eqs 30, 24-25 or 28a/28b/29, and 27b for one fixed cell layout, cycle after cycle.

    The pure functions above check their arguments and work on numpy arrays at every call:
    on a gripper pad's few cells (4 TBS per jaw) that cost ~1.5 ms a cycle, almost all of it
    per-call overhead. This class checks the layout once (slopes, intercepts, grip factors,
    the inclusion angle; cos(alpha) taken once) and computes each cycle in float arithmetic,
    with exactly the operations and the order of those functions, so its results are the same
    floats, bit for bit (tests/test_forces_layout.py checks it against them and the closed forms):

    * eq 30: ``F = (Y - c) / m`` for each tangential cell (``slope`` != 0) that is ``used``;
    * ``jaws`` (``{jaw: (y-axis cell indexes, x-axis cell indexes)}``, every tangential cell in
      one): per jaw eq 28a/28b over its y cells (an unused cell counts 0; no y cell: one 0),
      its x cells summed as eqs 24-25 at alpha = 0, eq 29; the total is the mean over the jaws
      (sec 7.2). Else eqs 24-25 over the used tangential cells at ``inclusion_angle`` (0 when
      none is used);
    * eq 27b: ``F_g = Y / M`` for each load cell (``grip_factor`` != 0) that is used, 0.0 for
      the others, and their mean.

    A layout the checks refuse (a non-finite slope, intercept or grip factor, an angle outside
    [0, pi]), or a cycle with a non-finite reading in a used cell, is left to those functions
    (:attr:`checked` False, or per cycle), so every error is theirs, word for word.
    """

    def __init__(self, slope, intercept, grip_factor, *, jaws=None, inclusion_angle=0.0):
        self.slope = [float(v) for v in np.asarray(slope, dtype=float)]
        self.intercept = [float(v) for v in np.asarray(intercept, dtype=float)]
        self.grip_factor = [float(v) for v in np.asarray(grip_factor, dtype=float)]
        self.tangential = [i for i, m in enumerate(self.slope) if m != 0.0]
        self.load_cells = [i for i, m in enumerate(self.grip_factor) if m != 0.0]
        self.jaws = None if jaws is None else {jaw: ([int(i) for i in ys], [int(i) for i in xs])
                                               for jaw, (ys, xs) in jaws.items()}
        self.angle = inclusion_angle
        self.checked = True
        try:
            alpha = _check_angle(inclusion_angle)
            if alpha.ndim != 0:
                raise ParameterError("inclusion_angle", inclusion_angle, "must be a scalar")
        except ParameterError:
            self.checked = False
            return
        self.alpha_zero = float(alpha) == 0.0
        self.cos_alpha = float(np.cos(alpha))  # compose_pair's np.cos(alpha), once
        cells = [(self.slope[i], self.intercept[i]) for i in self.tangential]
        if any(not np.isfinite(m) or not np.isfinite(c) for m, c in cells) or \
                any(not np.isfinite(self.grip_factor[i]) for i in self.load_cells):
            self.checked = False

    def _compose(self, a: float, b: float) -> float:
        """compose_pair (eq 25 / 28b) of two floats at the layout's angle."""
        a, b = abs(a), abs(b)
        if self.alpha_zero:
            return a + b
        sq = a * a + b * b + 2.0 * a * b * self.cos_alpha
        return math.sqrt(max(sq, 0.0))

    def _jaw(self, fy: list[float], fx: float) -> float:
        """jaw_tangential: eq 28a's pairwise tree of eq 28b, then eq 29."""
        level = fy
        while len(level) > 1:
            nxt = [self._compose(level[k], level[k + 1]) for k in range(0, len(level) - 1, 2)]
            if len(level) % 2:
                nxt.append(abs(level[-1]))
            level = nxt
        tot_y = abs(level[0])
        return math.sqrt(tot_y * tot_y + fx * fx)

    def cycle(self, y, used) -> CycleForces:
        """The forces of one cycle: ``y`` the cells' Y = X - N (mV, eq 4), ``used`` which cells
        count (present and read); both indexable by cell (lists are fastest)."""
        if not self.checked:
            return self._reference(y, used)
        slope, intercept = self.slope, self.intercept
        per_cell: list[tuple[int, float]] = []
        force = {}
        for i in self.tangential:
            if used[i]:
                yi = y[i]
                if not math.isfinite(yi):
                    return self._reference(y, used)
                f = (yi - intercept[i]) / slope[i]
                per_cell.append((i, f))
                force[i] = f
        total = per_jaw = None
        if self.tangential:
            if self.jaws is not None:
                per_jaw = {}
                for jaw, (ys, xs) in self.jaws.items():
                    fy = [force.get(i, 0.0) for i in ys] if ys else [0.0]
                    fx = _abs_sum([force.get(i, 0.0) for i in xs]) if xs else 0.0
                    per_jaw[jaw] = self._jaw(fy, fx)
                total = _mean(list(per_jaw.values()))
            elif not per_cell:
                total = 0.0
            elif self.alpha_zero:
                total = _abs_sum([f for _, f in per_cell])
            else:
                total = abs(per_cell[0][1])
                for _, f in per_cell[1:]:
                    total = self._compose(total, f)
        grip_per_cell = grip = None
        if self.load_cells:
            grip_per_cell = []
            for i in self.load_cells:
                if used[i]:
                    yi = y[i]
                    if not math.isfinite(yi):
                        return self._reference(y, used)
                    grip_per_cell.append(yi / self.grip_factor[i])
                else:
                    grip_per_cell.append(0.0)
            grip = _mean(grip_per_cell)
        return CycleForces(per_cell, per_jaw, total, grip_per_cell, grip)

    def _reference(self, y, used) -> CycleForces:
        """The same cycle through the pure functions (their checks, their errors)."""
        y = np.asarray(y, dtype=float)
        used = np.asarray(used, dtype=bool)
        slope, intercept = np.array(self.slope), np.array(self.intercept)
        per_cell = np.zeros(len(self.slope))
        cells = used & (slope != 0.0)
        if cells.any():
            per_cell[cells] = tangential_force(y[cells], slope[cells], intercept[cells])
        total = per_jaw = None
        if self.tangential:
            if self.jaws is not None:
                per_jaw = {}
                for jaw, (ys, xs) in self.jaws.items():
                    fy = per_cell[ys] if ys else np.zeros(1)
                    fx = total_tangential(per_cell[xs], 0.0) if xs else 0.0
                    per_jaw[jaw] = jaw_tangential(fy, fx, self.angle)
                total = float(np.mean(list(per_jaw.values())))
            else:
                total = total_tangential(per_cell[cells], self.angle) if cells.any() else 0.0
        grip_per_cell = grip = None
        if self.load_cells:
            lc = np.array(self.load_cells)
            per_lc = np.zeros(lc.size)
            live = used[lc]
            if live.any():
                per_lc[live] = load_cell_grip_force(y[lc][live], np.array(self.grip_factor)[lc][live]).per_jaw
            grip_per_cell = [float(v) for v in per_lc]
            grip = float(per_lc.mean())
        return CycleForces([(int(i), float(per_cell[i])) for i in np.flatnonzero(cells)], per_jaw, total,
                           grip_per_cell, grip)
