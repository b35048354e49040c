"""Local decisions and the two decision encodings (chapter sec. 2.1, eqs 1-4).

The chapter uses two tuples for the local decision u_i and mixes them in its own examples:

* ``"pm1"``: u_i in {-1, +1} (-1: H0 "signal absent", +1: H1 "signal present");
* ``"01"``:  u_i in {0, 1}.

Every function that consumes decisions takes the encoding explicitly; nothing is inferred
from the values (a vector of all ones is valid in both).
"""

from __future__ import annotations

from typing import Literal

import math
import numbers

import numpy as np

from taxel_net.errors import ParameterError

Encoding = Literal["pm1", "01"]
ENCODINGS: tuple[str, ...] = ("pm1", "01")

PRESENT = 1
ABSENT = {"pm1": -1, "01": 0}


# ------------------------------------------------ input checks shared by the numerical core
def _scalar_float(value) -> float:
    """float(value) for a real scalar; TypeError/ValueError for bools, arrays, complex, text."""
    if isinstance(value, (bool, np.bool_)) or (isinstance(value, np.ndarray) and value.ndim > 0):
        raise TypeError(value)
    return float(value)


def check_real(name: str, value, low: float, high: float, *, open_interval: bool = False,
               allowed: str | None = None) -> float:
    """``value`` as a finite float in [low, high] (or (low, high) with ``open_interval``).

    Bools, NaN, +-inf, arrays and non-numbers raise ParameterError(name, value, allowed).
    """
    if allowed is None:
        interval = f"({low:g}, {high:g})" if open_interval else f"[{low:g}, {high:g}]"
        allowed = f"must be a real number in {interval}"
    try:
        v = _scalar_float(value)
    except (TypeError, ValueError):
        raise ParameterError(name, value, allowed) from None
    inside = (low < v < high) if open_interval else (low <= v <= high)
    if not (math.isfinite(v) and inside):
        raise ParameterError(name, value, allowed)
    return v


def check_integer(name: str, value, low: int | None = None, high: int | None = None, *,
                  allowed: str | None = None) -> int:
    """``value`` as an int in [low, high] (None: unbounded). Integral floats (3.0) and numpy
    integers are accepted; bools, fractions, NaN, inf and non-numbers raise ParameterError."""
    if allowed is None:
        if low is not None and high is not None:
            allowed = f"must be an integer in [{low}, {high}]"
        elif low is not None:
            allowed = f"must be an integer >= {low}"
        else:
            allowed = "must be an integer"
    if isinstance(value, (bool, np.bool_)):
        raise ParameterError(name, value, allowed)
    if isinstance(value, numbers.Integral):
        v = int(value)
    else:
        try:
            f = _scalar_float(value)
        except (TypeError, ValueError):
            raise ParameterError(name, value, allowed) from None
        if not (math.isfinite(f) and f.is_integer()):
            raise ParameterError(name, value, allowed)
        v = int(f)
    if (low is not None and v < low) or (high is not None and v > high):
        raise ParameterError(name, value, allowed)
    return v


def as_float_array(name: str, values) -> np.ndarray:
    """``values`` as a float64 array; text, None, complex or ragged input raise ParameterError."""
    try:
        raw = np.asarray(values)
        if raw.dtype.kind == "c" or raw.dtype.kind not in "biuf" and raw.dtype != object:
            raise TypeError(raw.dtype)
        return raw.astype(float)
    except (TypeError, ValueError):
        scalar = isinstance(values, (str, bytes, numbers.Number)) or values is None
        shown = values if scalar else "a non-numeric or ragged sequence"
        raise ParameterError(name, shown, "must be real numbers") from None


def check_encoding(encoding: str) -> str:
    if encoding not in ENCODINGS:
        raise ParameterError("tuple", encoding, "must be 'pm1' ({-1,+1}) or '01' ({0,1})")
    return encoding


def local_decision(observation, noise, zeta, encoding: Encoding = "pm1") -> np.ndarray:
    """Local detector of every taxel, eqs 1-4.

    Y_i = X_i - N_i (eq 4); u_i = +1 when Y_i >= zeta_i (eqs 2-3), else the absent value of
    ``encoding`` (-1 for ``pm1``, 0 for ``01``). ``observation`` X_i, ``noise`` N_i and
    ``zeta`` may be scalars or arrays that broadcast (zeta per taxel or per kind).
    A NaN observation is never "present": it decides absent (a node must flag it as a fault).
    Returns int8 decisions.
    """
    check_encoding(encoding)
    x = as_float_array("observation", observation)
    n = as_float_array("noise", noise)
    z = as_float_array("zeta", zeta)
    if np.any(~np.isfinite(z)) or np.any(z < 0):
        bad = z[~np.isfinite(z) | (z < 0)].flat[0]
        raise ParameterError("zeta", float(bad), "cut-off must be finite and >= 0 mV")
    present = (x - n) >= z  # NaN compares False -> absent
    return np.where(present, np.int8(PRESENT), np.int8(ABSENT[encoding])).astype(np.int8)


class LocalDetectors:
    """The local detectors of a fixed set of taxels (eqs 1-4), their ``noise`` N_i and cut-offs
    ``zeta`` checked once (as :func:`local_decision` checks them), for the centre's raw mode: each
    cycle's readings X_i -> the decision vector the nodes would have sent.

    :meth:`wire` equals ``local_decision(x[ok], noise[ok], zeta[ok], "pm1")`` on the readings
    that are not NaN (``ok``) and 0 on the others, bit for bit (the same subtraction and
    comparison per element), in a handful of array operations: ``local_decision``'s checks and
    fancy indexing of the received subset took 0.04-0.2 ms of every raw cycle, on the grip
    command's path."""

    def __init__(self, noise, zeta):
        self.noise = as_float_array("noise", noise).reshape(-1)
        z = as_float_array("zeta", zeta).reshape(-1)
        if np.any(~np.isfinite(z)) or np.any(z < 0):
            bad = z[~np.isfinite(z) | (z < 0)].flat[0]
            raise ParameterError("zeta", float(bad), "cut-off must be finite and >= 0 mV")
        if z.shape != self.noise.shape:
            raise ParameterError("zeta", z.shape, f"needs one cut-off per taxel ({self.noise.shape[0]})")
        self.zeta = z
        self.n = z.shape[0]

    def wire(self, readings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(u, available)`` of one cycle's readings X_i (float64, one per taxel, NaN = none):
        ``u`` int8, +1 where ``X_i - N_i >= zeta_i`` (eqs 2-4), -1 where not, 0 where X_i is NaN;
        ``available`` the readings that are not NaN."""
        if readings.shape != (self.n,):
            raise ParameterError("readings", readings.shape, f"must be {self.n} readings")
        available = ~np.isnan(readings)
        y = readings - self.noise                      # eq 4
        present = y >= self.zeta                       # NaN compares False
        u = present.view(np.int8) * np.int8(2)         # +2 / 0 ...
        u -= available.view(np.int8)                   # ... -> +1 / -1, and 0 where NaN
        return u, available


def validate_decisions(u, encoding: Encoding = "pm1", name: str = "u") -> np.ndarray:
    """Return ``u`` as an int8 array after checking every entry belongs to ``encoding``.

    Raises ParameterError naming the first offending index and value.
    """
    check_encoding(encoding)
    allowed = (-1, 1) if encoding == "pm1" else (0, 1)
    as_float = as_float_array(name, u)
    if as_float.ndim != 1:
        raise ParameterError(name, as_float.shape, "must be a 1-D sequence of decisions")
    if as_float.size == 0:
        raise ParameterError(name, [], "needs at least one decision (n >= 1)")
    ok = np.isin(as_float, allowed)
    if not ok.all():
        i = int(np.flatnonzero(~ok)[0])
        bad = as_float[i].item()
        raise ParameterError(f"{name}[{i}]", int(bad) if bad.is_integer() else bad,
                             f"must be one of {allowed} for tuple '{encoding}'")
    return as_float.astype(np.int8)


def to_pm1(u, encoding: Encoding) -> np.ndarray:
    """Convert decisions in ``encoding`` to the {-1,+1} tuple."""
    arr = validate_decisions(u, encoding)
    return arr if encoding == "pm1" else (2 * arr - 1).astype(np.int8)


def to_01(u, encoding: Encoding) -> np.ndarray:
    """Convert decisions in ``encoding`` to the {0,1} tuple."""
    arr = validate_decisions(u, encoding)
    return arr if encoding == "01" else ((arr + 1) // 2).astype(np.int8)


def present_count(u, encoding: Encoding) -> int:
    """Number of taxels deciding "present" (u_i = +1); n - k in the chapter's notation."""
    return int(np.count_nonzero(validate_decisions(u, encoding) == PRESENT))
