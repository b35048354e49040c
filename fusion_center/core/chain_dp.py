"""The preferential rule's dynamic programme over the chain (eq 7): the lattice forms of U_G,
U_G's law for independent taxels, and the exact comparison of U_G with the band edges (eq 20).
Used by :mod:`.preferential_rates` and :mod:`.tilted_dp`. The counts DPs of {0,1} are in
:mod:`.counts_dp`, the scaling of probabilities shared by the DPs in :mod:`.dp_scaling`.

With independent taxels (P(u_i present) = pi_i) U_G depends on each taxel and its two
neighbours only (eq 7: u_i (1 + u_(i+1))^p (1 + u_(i-1))^q, one term per taxel, ``_term``), so
its law follows from a DP along the chain whose state is the last two decisions (u_(i-1), u_i).
Wherever every inner taxel's term is an integer multiple of one unit,

    U_G = unit * x + (the first taxel's term) + (the last taxel's term),   x an integer,

and the DP carries one array over x per state and start label (``_lattice``):

* {-1,+1}, p > 0, q > 0 ("chain"): an absent neighbour's factor is 0^p = 0, so an inner taxel
  contributes u_i 2^(p+q) when both neighbours are present and 0 otherwise: U_G = 2^(p+q) m +
  2^p e_1 + 2^q e_n, m in -n..n, e_1 = u_1 [u_2 present], e_n = u_n [u_(n-1) present] in {-1,
  0, 1} (three start labels); where 2^q (or 2^p) is an integer the unit 2^p (2^q) takes e_1
  into the lattice: one label, e.g. p = q = 1: U_G = 2 (2m + e_1) + 2 e_n. (Reversing the
  taxel order swaps p and q, eq 7.)
* {-1,+1} with one zero weight ("lattice"): U_G = 2^p m + u_n (or 2^q m + u_1).
* integer p, q, either tuple ("integer"): every term is an integer.

{0,1} with a non-integer weight has no such unit: an absent taxel and the boundary both give
the factor 1, so U_G = a + b (2^p + 2^q) + d 2^(p+q) over three integer counts (runs of one
present taxel, longer runs, taxels inside runs), and ``_rates_counts`` (:mod:`.counts_dp`) runs
the DP over them (polynomial, a box of counts per state).

``_lattice_law`` (used for U_G's whole law, :func:`.preferential_rates.preferential_law`)
carries probabilities scaled by powers of two (from 2^SCALE_BITS; the likelier branch is never
multiplied, its factor goes into an exact-sum logarithm) and trims the window where columns
fall below 1e-325 of probability (TRIM_TAIL), so every atom >= FLOOR = 1e-300 is exact; the
band rates use the tilted DP of :mod:`.tilted_dp` instead, trimmed by the law tilted towards
each region. Band comparisons are exact: the edges become integer thresholds on x per pair of
end labels (``_first_at_least``), decided in mpmath where rounding cannot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from .dp_scaling import _EPS, _LOG_SCALE, SCALE_BITS, TRIM_EVERY, TRIM_TAIL

# moved to their own modules, kept importable from here: the {0,1} counts DPs (counts_dp) and
# the scaling shared by the DPs (dp_scaling)
from .counts_dp import (COUNTS_WORK_MAX, TWO_COUNTS_WORK_MAX, _classify, _rates_counts,  # noqa: F401
                        _rates_two_counts, _two_count_form)
from .dp_scaling import _LOG_FLOOR, FLOOR, TRIM_BULK, _log_probability, _scaled_logs  # noqa: F401

_REEXPORTED = (COUNTS_WORK_MAX, TWO_COUNTS_WORK_MAX, _classify, _rates_counts, _rates_two_counts, _two_count_form,
               _LOG_FLOOR, FLOOR, TRIM_BULK, _log_probability, _scaled_logs)


# ------------------------------------------------------------------ lattice DP (chain, integer)
# U_G is a sum of one term per taxel (eq 7), the term of taxel i a function of u_(i-1), u_i,
# u_(i+1). Where every inner term is an integer multiple of one unit (2^(p+q) on {-1,+1} with
# p, q > 0; 2^p or 2^q when the other weight is 0; 1 for integer p, q) U_G is
#
#     U_G = unit * x + (label of taxel 1's term) + (label of taxel n's term),   x an integer,
#
# and its law follows from a DP along the chain whose state is (u_(i-1), u_i), the start label
# and x: an array over x per state and label. Every DP starts from total mass 2^SCALE_BITS (an
# exact power of two), so probabilities far below the double range stay normal numbers; logs
# are unscaled at the end. The live window of x is trimmed every TRIM_EVERY steps (module doc,
# "Accuracy").
_BASIS = ("1", "2^p", "2^q", "2^(p+q)")


def _term(prev: int, own: int, nxt: int, p: float, q: float, encoding: str) -> tuple[int, int, int, int]:
    """Integer coefficients (of 1, 2^p, 2^q, 2^(p+q)) of the eq 7 term u_i (1 + u_(i+1))^p
    (1 + u_(i-1))^q of a taxel with own decision ``own`` (1 present, 0 absent) and neighbours
    ``prev``/``nxt`` (1 present, 0 absent, 2 boundary u = 0). 0^0 = 1."""
    u = 1 if own == 1 else (-1 if encoding == "pm1" else 0)
    if u == 0:
        return (0, 0, 0, 0)

    def factor(state, weight):  # "x": 2^weight, 1, or 0
        if state == 1:
            return "x"
        if state == 2 or encoding == "01" or weight == 0.0:
            return 1
        return 0

    fp, fq = factor(nxt, p), factor(prev, q)
    if fp == 0 or fq == 0:
        return (0, 0, 0, 0)
    if fp == "x" and fq == "x":
        return (0, 0, 0, u)
    if fp == "x":
        return (0, u, 0, 0)
    if fq == "x":
        return (0, 0, u, 0)
    return (u, 0, 0, 0)


@dataclass(frozen=True)
class _Lattice:
    """U_G = unit * x + start label + end label (section comment), for the taxels in order
    (``reverse`` False) or reversed (True: U_G of the reversed vector with p and q swapped is
    the same value, eq 7). ``p``, ``q`` are the weights of that orientation, coefficients are
    of (1, 2^p, 2^q, 2^(p+q)) in it. shift[a, b, c] is the lattice step of the middle taxel's
    term; start[a][b] / end[a][b] = (steps, label index) of the first / last taxel's term
    (a, b the present bits of the first two / last two taxels)."""

    method: str
    reverse: bool
    p: float
    q: float
    unit: tuple[int, int, int, int]
    shift: np.ndarray
    start: tuple
    end: tuple
    start_labels: tuple
    end_labels: tuple

    def cost(self) -> int:
        """Work per taxel, relative: labels carried through the DP times the spread of a step."""
        return len(self.start_labels) * max(1, int(self.shift.max() - self.shift.min()))


def _lattice_form(p: float, q: float, encoding: str, unit_index: int, method: str, reverse: bool) -> _Lattice | None:
    """U_G in the lattice of basis element ``unit_index`` (0: 1, 1: 2^p, 2: 2^q, 3: 2^(p+q));
    None if an inner term is not an integer multiple of it."""
    # equal basis elements merged first: 2^0 = 1
    def merge(c):
        a, b, cq, d = c
        if p == 0.0:
            a, b, cq, d = a + b, 0, cq + d, 0
        if q == 0.0:
            a, b, cq, d = a + cq, b + d, 0, 0
        return a, b, cq, d

    # basis element j is 2^k times the unit when its exponent (0, p, q, p + q) exceeds the unit's
    # by an integer k >= 0, decided exactly on the float inputs
    exponents = [Fraction(0), Fraction(p), Fraction(q), Fraction(p) + Fraction(q)]
    mult = []
    for j in range(4):
        k = exponents[j] - exponents[unit_index]
        mult.append(2 ** int(k) if k.denominator == 1 and 0 <= k <= 8 else None)

    def fold(c):
        c = merge(c)
        steps = sum(v * m for v, m in zip(c, mult) if m is not None)
        label = tuple(0 if m is not None else v for v, m in zip(c, mult))
        return steps, label

    shift = np.zeros((2, 2, 2), dtype=np.int64)
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                steps, label = fold(_term(a, b, c, p, q, encoding))
                if any(label):
                    return None
                shift[a, b, c] = steps
    start_labels, end_labels, start, end = [], [], [[None, None], [None, None]], [[None, None], [None, None]]
    for a in (0, 1):
        for b in (0, 1):
            steps, label = fold(_term(2, a, b, p, q, encoding))  # first taxel: boundary before it
            if label not in start_labels:
                start_labels.append(label)
            start[a][b] = (steps, start_labels.index(label))
            steps, label = fold(_term(a, b, 2, p, q, encoding))  # last taxel: boundary after it
            if label not in end_labels:
                end_labels.append(label)
            end[a][b] = (steps, end_labels.index(label))
    unit = tuple(1 if j == unit_index else 0 for j in range(4))
    return _Lattice(method, reverse, p, q, unit, shift, tuple(map(tuple, start)), tuple(map(tuple, end)),
                    tuple(start_labels), tuple(end_labels))


def _lattice(p: float, q: float, encoding: str) -> _Lattice | None:
    """The cheapest lattice form of U_G for these weights (over both orientations and every
    unit that makes the inner terms integer multiples), None where U_G needs more than one
    integer coordinate ({0,1} with a non-integer weight)."""
    integer = float(p).is_integer() and float(q).is_integer()
    if encoding == "pm1" and p > 0 and q > 0:
        method = "chain"  # inner terms 0 or +-2^(p+q): units 2^(p+q), or 2^p when 2^q is an integer
    elif encoding == "pm1" and (p == 0) != (q == 0) and not integer:
        method = "lattice"  # a zero weight: inner terms 0 or +-2^p (+-2^q), an end taxel +-1
    elif integer:
        method = "integer"
    else:
        return None
    forms = []
    for reverse in (False, True):
        pp, qq = (q, p) if reverse else (p, q)
        for unit_index in range(4):
            form = _lattice_form(pp, qq, encoding, unit_index, method, reverse)
            if form is not None:
                forms.append(form)
    return min(forms, key=lambda f: (f.cost(), f.reverse, f.unit)) if forms else None


def _lattice_law(pi: np.ndarray, lat: _Lattice, lower_tail: bool = True, upper_tail: bool = True):
    """Law of (start label, end label, x) for n = pi.size >= 2 taxels in stored units:
    ({(ls, le): (x_first, array over x from x_first)}, (E, L), dropped) with stored =
    probability * 2^E / e^L, and ``dropped`` the stored mass removed by trimming (0.0 if
    none). A side with ``*_tail`` True is trimmed at TRIM_TAIL (exact down to FLOOR), otherwise
    at TRIM_BULK of the mass (the side where only the bulk's own region lies).

    One step per taxel: Y[b, c] = P(c) (X[0, b] moved by shift[0, b, c] + X[1, b] moved by
    shift[1, b, c]), four vector additions over the live window (three where the shifts of
    both b agree) and one multiplication: the branch of the more likely decision is not
    multiplied (its factor max(pc, 1 - pc) goes into L), the other by the ratio.
    Every TRIM_EVERY steps the mass is rescaled by a power of two (to ~2^SCALE_BITS) and the
    window trimmed."""
    n = pi.size
    shift = lat.shift
    smin, smax = int(shift.min()), int(shift.max())
    st = [lat.start[a][b][0] for a in (0, 1) for b in (0, 1)]
    xmin = min(st) + (n - 2) * smin
    xmax = max(st) + (n - 2) * smax
    pad = smax - smin + 2
    size = xmax - xmin + 1 + 2 * pad
    n_labels = len(lat.start_labels)
    buffers = (np.zeros((2, 2, n_labels, size)), np.zeros((2, 2, n_labels, size)))
    X = buffers[0]
    lo, hi = size, 0
    for a in (0, 1):
        for b in (0, 1):
            steps, label = lat.start[a][b]
            j = steps - xmin + pad
            X[a, b, label, j] += 2.0**SCALE_BITS * (pi[0] if a else 1.0 - pi[0]) * (pi[1] if b else 1.0 - pi[1])
            lo, hi = min(lo, j), max(hi, j + 1)
    log_two = math.log(2.0)
    exponent = SCALE_BITS  # stored = probability * 2^exponent / prod(max factors so far)
    log_max_factors = []
    log_running = 0.0  # their sum so far (for the trimming threshold; math.fsum at the end)
    dropped = 0.0
    groups = []
    for c in (0, 1):
        if shift[0, 0, c] == shift[0, 1, c] and shift[1, 0, c] == shift[1, 1, c]:
            groups.append((slice(None), c, int(shift[0, 0, c]), int(shift[1, 0, c])))
        else:
            groups.extend((b, c, int(shift[0, b, c]), int(shift[1, b, c])) for b in (0, 1))
    present_p = pi.tolist()
    parity = 0  # buffers[parity] holds the law after the last step
    for start in range(2, n, TRIM_EVERY):
        steps = min(n, start + TRIM_EVERY) - start
        # one window for the whole block (it covers every step's live range), views made once
        lo, hi = lo + smin * steps, hi + smax * steps
        views = []
        for par in (0, 1):
            source, dest = buffers[par], buffers[1 - par]
            adds = [(source[0, b, :, lo - s0:hi - s0], source[1, b, :, lo - s1:hi - s1], dest[b, c, :, lo:hi])
                    for b, c, s0, s1 in groups]
            views.append((adds, dest[:, 0, :, lo:hi], dest[:, 1, :, lo:hi]))
        for i in range(start, start + steps):
            adds, absent, present = views[parity]
            for in0, in1, out in adds:
                np.add(in0, in1, out=out)
            pc = present_p[i]
            qc = 1.0 - pc
            if pc >= qc:
                absent *= qc / pc
                log_max_factors.append(math.log(pc))
            else:
                present *= pc / qc
                log_max_factors.append(math.log1p(-pc))
            parity = 1 - parity
        X = buffers[parity]
        log_running = sum(log_max_factors[len(log_max_factors) - steps:], log_running)
        live = X[:, :, :, lo:hi]
        cols = live.sum(axis=(0, 1, 2))
        # rescale by a power of two: the largest column back to ~2^SCALE_BITS (exact)
        k = math.frexp(float(cols.max()))[1] - SCALE_BITS - 1
        if k:
            live *= math.ldexp(1.0, -k)
            cols *= math.ldexp(1.0, -k)
            dropped = math.ldexp(dropped, -k)
            exponent -= k
        if hi - lo > 8:
            # stored units of TRIM_TAIL: probability 1e-325 * 2^SCALE_BITS
            tail = TRIM_TAIL * math.exp(exponent * log_two - log_running - _LOG_SCALE)
            bulk = 1e-24 * float(cols.sum())
            keep_lo = np.flatnonzero(cols >= (tail if lower_tail else bulk))
            keep_hi = np.flatnonzero(cols >= (tail if upper_tail else bulk))
            first = int(keep_lo[0]) if keep_lo.size else hi - lo
            last = int(keep_hi[-1]) + 1 if keep_hi.size else 0
            if first < last and (first or last < hi - lo):
                dropped += float(cols[:first].sum() + cols[last:].sum())
                for arr in buffers:
                    arr[:, :, :, lo:lo + first] = 0.0
                    arr[:, :, :, lo + last:hi] = 0.0
                lo, hi = lo + first, lo + last
    X = buffers[parity]
    scale = (exponent, math.fsum(log_max_factors))
    laws: dict = {}
    emin = min(lat.end[a][b][0] for a in (0, 1) for b in (0, 1))
    emax = max(lat.end[a][b][0] for a in (0, 1) for b in (0, 1))
    width = hi - lo + emax - emin
    for a in (0, 1):
        for b in (0, 1):
            steps, le = lat.end[a][b]
            for ls in range(n_labels):
                row = X[a, b, ls, lo:hi]
                if not row.any():
                    continue
                key = (ls, le)
                if key not in laws:
                    laws[key] = np.zeros(width)
                laws[key][steps - emin:steps - emin + row.size] += row
    x_first = lo - pad + xmin + emin
    return {k: (x_first, v) for k, v in laws.items()}, scale, dropped


def _exact_value(coeffs, p: float, q: float):
    import mpmath

    a, b, c, d = coeffs
    big_p, big_q = mpmath.mpf(2) ** mpmath.mpf(p), mpmath.mpf(2) ** mpmath.mpf(q)
    return a + b * big_p + c * big_q + d * big_p * big_q


def _float_value(coeffs, p: float, q: float) -> tuple[float, float]:
    """(float value, error bound) of a + b 2^p + c 2^q + d 2^(p+q)."""
    a, b, c, d = coeffs
    terms = (float(a), b * 2.0**p, c * 2.0**q, d * 2.0 ** (p + q))
    return math.fsum(terms), 64.0 * _EPS * sum(abs(t) for t in terms)


def _at_least(coeffs, edge: float, p: float, q: float) -> bool:
    """a + b 2^p + c 2^q + d 2^(p+q) >= edge, exactly (mpmath where rounding cannot decide)."""
    value, err = _float_value(coeffs, p, q)
    if abs(value - edge) > err + 64.0 * _EPS * abs(edge):
        return value >= edge
    import mpmath

    with mpmath.workdps(60):
        return _exact_value(coeffs, p, q) >= mpmath.mpf(edge)


def _first_at_least(lat: _Lattice, base, edge: float, p: float, q: float,
                    x_range: tuple[int, int] | None = None) -> int:
    """Smallest integer x with unit * x + base >= edge (exact); with ``x_range`` = (xa, xb), x's
    reach over the decision vectors (:func:`_x_range`), the answer clamped to [xa - 1, xb + 1]
    (every reachable x compares with the edge as with the true threshold).

    The float estimate is exact to a few units only while the edge is small: for an edge of
    1e100 it is off by ~1e84 units, which the exact steps below would walk one by one. An
    estimate beyond x's reach by more than its own error is clamped without walking."""
    unit_value = _float_value(lat.unit, p, q)[0]
    base_value = _float_value(base, p, q)[0]
    if math.isinf(edge):
        return -(2**62) if edge < 0 else 2**62
    estimate = (edge - base_value) / unit_value
    if x_range is not None:
        xa, xb = x_range
        slack = 2.0 + abs(estimate) * 1e-9  # far above the float error of the estimate
        if estimate - slack > xb + 1:
            return xb + 1
        if estimate + slack < xa - 1:
            return xa - 1
    x = math.ceil(estimate)
    coeffs = lambda k: tuple(u * k + b for u, b in zip(lat.unit, base))
    while _at_least(coeffs(x - 1), edge, p, q):
        x -= 1
    while not _at_least(coeffs(x), edge, p, q):
        x += 1
    if x_range is not None:
        x = min(max(x, x_range[0] - 1), x_range[1] + 1)
    return x


def _label_base(lat: _Lattice, ls: int, le: int):
    return tuple(s + e for s, e in zip(lat.start_labels[ls], lat.end_labels[le]))


def _x_range(lat: _Lattice, n: int) -> tuple[int, int]:
    """Bounds of x over all decision vectors (start steps, n - 2 inner steps, end steps)."""
    starts = [lat.start[a][b][0] for a in (0, 1) for b in (0, 1)]
    ends = [lat.end[a][b][0] for a in (0, 1) for b in (0, 1)]
    smin, smax = int(lat.shift.min()), int(lat.shift.max())
    return min(starts) + (n - 2) * smin + min(ends), max(starts) + (n - 2) * smax + max(ends)
