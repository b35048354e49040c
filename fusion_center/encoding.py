"""Local decisions and the two decision encodings (chapter sec. 2.1, eqs 1-4).

The chapter uses two tuples for the local decision u_i and mixes them in its own examples:

* ``"pm1"``: u_i in {-1, +1} (-1: H0 "signal absent", +1: H1 "signal present");
* ``"01"``:  u_i in {0, 1}.

Every function that consumes decisions takes the encoding explicitly; nothing is inferred
from the values (a vector of all ones is valid in both).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from .errors import ParameterError

Encoding = Literal["pm1", "01"]
ENCODINGS: tuple[str, ...] = ("pm1", "01")

PRESENT = 1
ABSENT = {"pm1": -1, "01": 0}


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
    x = np.asarray(observation, dtype=float)
    n = np.asarray(noise, dtype=float)
    z = np.asarray(zeta, dtype=float)
    if np.any(~np.isfinite(z)) or np.any(z < 0):
        bad = z[~np.isfinite(z) | (z < 0)].flat[0]
        raise ParameterError("zeta", float(bad), "cut-off must be finite and >= 0 mV")
    present = (x - n) >= z  # NaN compares False -> absent
    return np.where(present, np.int8(PRESENT), np.int8(ABSENT[encoding])).astype(np.int8)


def validate_decisions(u, encoding: Encoding = "pm1", name: str = "u") -> np.ndarray:
    """Return ``u`` as an int8 array after checking every entry belongs to ``encoding``.

    Raises ParameterError naming the first offending index and value.
    """
    check_encoding(encoding)
    arr = np.asarray(u)
    if arr.ndim != 1:
        raise ParameterError(name, arr.shape, "must be a 1-D sequence of decisions")
    if arr.size == 0:
        raise ParameterError(name, [], "needs at least one decision (n >= 1)")
    allowed = (-1, 1) if encoding == "pm1" else (0, 1)
    as_float = arr.astype(float)
    ok = np.isin(as_float, allowed)
    if not ok.all():
        i = int(np.flatnonzero(~ok)[0])
        raise ParameterError(f"{name}[{i}]", arr[i].item(), f"must be one of {allowed} for tuple '{encoding}'")
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
