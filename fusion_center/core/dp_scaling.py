"""Scaled probabilities shared by the DPs over the chain (eq 7): the lattice DP of
:mod:`.chain_dp` and the {0,1} counts DPs of :mod:`.counts_dp` (and the tilted DP of
:mod:`.tilted_dp`).

Every DP starts from total mass 2^SCALE_BITS (an exact power of two), so probabilities far
below the double range stay normal numbers; a stored value is probability * 2^E / e^L (E the
running power of two, L the sum of the per-taxel factors kept out of the arithmetic), and the
logs are unscaled at the end (``_log_probability``, ``_scaled_logs``). Rates at or above FLOOR
= 1e-300 are exact: columns are trimmed at TRIM_TAIL (1e-325 of probability) every TRIM_EVERY
taxels.
"""

from __future__ import annotations

import math

_EPS = 2.220446049250313e-16

SCALE_BITS = 900
_LOG_SCALE = SCALE_BITS * math.log(2.0)
FLOOR = 1e-300
"""The fast DPs' rates at or above FLOOR are exact; a rate below it is named in ``below_floor``
(its plain value may underflow) and its log comes from the tilted DP or :mod:`.extended_dp`."""
_LOG_FLOOR = math.log(FLOOR)
# a tail side is trimmed at 1e-325 of probability (scaled), far below FLOOR: the mass so
# dropped over the whole run is < n W 1e-325 (W the window) -- below 1e-300 * 1e-13 for any
# n W up to 1e12; the side of the bulk only, where no small region lies, at 1e-24 of the mass
TRIM_TAIL = math.exp(-325.0 * math.log(10.0) + _LOG_SCALE)
TRIM_BULK = 1e-24 * 2.0**SCALE_BITS
TRIM_EVERY = 8


def _log_probability(stored: float, scale=(SCALE_BITS, 0.0)) -> float:
    """ln of the probability behind a stored value (stored = probability * 2^E / e^L, scale =
    (E, L)), formed without cancellation: ln(mantissa) + (exponent - E) ln 2 + L."""
    if stored <= 0.0:
        return -math.inf
    mantissa, exp2 = math.frexp(stored)
    return math.log(mantissa) + (exp2 - scale[0]) * math.log(2.0) + scale[1]


def _scaled_logs(sums, empty=(False, False, False), scale=(SCALE_BITS, 0.0)):
    """Per region, from stored sums (``_log_probability``): (ln P or None, below FLOOR).
    Exact at or above FLOOR; a region ``empty`` (no value of U_G lies in it) is an impossible
    event (None, False); else (None, True): 0 <= P < FLOOR. A sum of 0.0 is not taken for an
    impossible event: besides the trimming, a scaled cell more than 2^(SCALE_BITS + 1074)
    below the largest underflows to 0 uncounted (14 taxels at pf = 1e-45 all present, 1e-630,
    did); :mod:`.extended_dp` tells the two apart."""
    out = []
    for s, none in zip(sums, empty):
        log = _log_probability(s, scale)
        if log >= _LOG_FLOOR:
            out.append((log, False))
        else:
            out.append((None, not none))
    return out
