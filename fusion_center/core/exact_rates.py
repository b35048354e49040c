"""Exact system error rates of the preferential rule (eq 7 with the band of eq 20) and of the
Chair-Varshney / Neyman-Pearson baselines (eqs 31-32) on taxels that come in kinds.

Preferential rule (eq 7). With independent taxels (P(u_i present) = pd_i under H1, pf_i under
H0) U_G depends on each taxel and its two neighbours only, so its law follows from a dynamic
programme along the chain; the state is the last two decisions (u_(i-1), u_i) and a lattice
coordinate x. Wherever every inner taxel's term is an integer multiple of one unit,

    U_G = unit * x + (the first taxel's term) + (the last taxel's term),   x an integer:

* {-1,+1}, p > 0, q > 0 (``method="chain"``): an absent neighbour's factor is 0^p = 0, so an
  inner taxel contributes u_i 2^(p+q) when both neighbours are present and 0 otherwise:
  U_G = 2^(p+q) m + 2^p e_1 + 2^q e_n, m in -n..n, e_1 = u_1 [u_2 present], e_n = u_n
  [u_(n-1) present] in {-1, 0, 1}; the DP carries m per state and per e_1 (three "labels").
  Where 2^q (or 2^p) is an integer the unit 2^p (2^q) takes e_1 into the lattice: one label,
  e.g. p = q = 1: U_G = 2 (2m + e_1) + 2 e_n. (Reversing the taxel order swaps p and q, eq 7.)
* {-1,+1} with one zero weight (``method="lattice"``): U_G = 2^p m + u_n (or 2^q m + u_1).
* integer p, q (either tuple, ``method="integer"``): every term is an integer.
* otherwise ({0,1} with a non-integer weight: U_G = a + b (2^p + 2^q) + d 2^(p+q) needs three
  integer coordinates; ``method="exact-sparse"``): a dictionary over the integer coefficients
  (a, b, c, d) of 1, 2^p, 2^q, 2^(p+q), exact, practical up to ~60 taxels; beyond
  ``SPARSE_MAX_TAXELS`` the rates are estimated by Monte Carlo with a 95 % Wilson interval
  (``method="monte-carlo"``, says so).

The lattice DP is a handful of numpy vector operations per taxel over the live window of x
(``_lattice_law``): O(n W) with W the width of the law that matters, O(sqrt n) around the
bulk plus the distance from the bulk to the band edges -- n = 10^4 in 0.3-0.7 s
(``bench/preferential_dp.py``; before the window trimming of issue 13: O(n^2), 1.4-1.5 s).

Accuracy. Probabilities are carried scaled by powers of two (from 2^900; the branch of the
likelier decision is never multiplied, its factor goes into an exact-sum logarithm), so they
stay normal doubles far below 1e-300. The window is trimmed every TRIM_EVERY taxels: on a
side of the bulk where a band region may be small, columns below 1e-325 of probability
(their total over the run stays below 1e-300 * 1e-12 for any n W up to 10^12); on a side where
only the bulk's own region lies (x above the mean when U_G >= high holds the mean, say), below
1e-24 of the mass -- that region is large, and mass that far beyond the bulk reaches the other
side's regions even less often than the bulk does (the DP is shift-invariant in x). Every rate
at or above FLOOR = 1e-300 is exact to ~1e-13 relative (tested against brute force over all
2^n vectors, an mpmath DP and an untrimmed log-domain DP); a rate below FLOOR is not computed:
its log is None and its name is in ``below_floor`` (an impossible event has None and is not).

Decision (eq 20 band): H1 iff U_G >= high, H0 iff U_G < low, undecided between. Each
comparison is exact: the band edges become an integer threshold on x per pair of end labels,
decided in mpmath where rounding cannot; the three probabilities under each hypothesis are
sums of positive terms (no complements); ``log_`` forms are natural logarithms.

Kinds (Chair-Varshney eq 31, N-P eq 32): when the taxels come in a few kinds with equal
(pd, pf) per kind, ln Lambda depends only on the present count per kind, whose law is a product
of binomials: the atoms are enumerated exactly (up to ``KIND_ATOMS_MAX`` count tuples).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from taxel_net.errors import ParameterError

__all__ = [
    "PreferentialRates",
    "preferential_error_rates",
    "preferential_law",
    "FLOOR",
    "SPARSE_MAX_TAXELS",
    "KindRates",
    "kinds_of",
    "llr_error_rates",
    "np_kinds_fusion",
    "KIND_ATOMS_MAX",
    "linear_statistic_law",
    "roc_from_laws",
]

SPARSE_MAX_TAXELS = 60
KIND_ATOMS_MAX = 2_000_000
_EPS = 2.220446049250313e-16


def _log(x: float) -> float | None:
    return math.log(x) if x > 0.0 else None


_NAMES = ("p_detect", "p_undecided_h1", "p_miss", "p_false_alarm", "p_undecided_h0", "p_reject")


@dataclass(frozen=True)
class PreferentialRates:
    """System rates of the preferential band decision. Under H1: p_detect = P(H1 decided),
    p_undecided_h1, p_miss = P(H0 decided); under H0: p_false_alarm = P(H1 decided),
    p_undecided_h0, p_reject = P(H0 decided). log_*: natural logarithms, exact down to FLOOR
    (1e-300, below the double range of the plain values too); None for an impossible event, or
    for a rate below FLOOR -- those are named in ``below_floor`` (0 <= rate < 1e-300). The plain
    values are exp of the logs (0.0 below ~1e-308). method: "chain", "lattice", "integer",
    "exact-sparse" (exact) or "monte-carlo" (estimate, with ``ci95`` per rate and ``samples``)."""

    log_p_detect: float | None
    log_p_undecided_h1: float | None
    log_p_miss: float | None
    log_p_false_alarm: float | None
    log_p_undecided_h0: float | None
    log_p_reject: float | None
    method: str
    samples: int | None = None
    ci95: dict | None = None
    below_floor: tuple = ()

    def __getattr__(self, name):
        if name in _NAMES:
            log = object.__getattribute__(self, "log_" + name)
            return 0.0 if log is None else math.exp(log)
        raise AttributeError(name)

    def logs(self) -> dict:
        return {f"log_{k}": getattr(self, "log_" + k) for k in _NAMES}

    def as_dict(self) -> dict:
        out = {k: getattr(self, k) for k in _NAMES}
        out.update(self.logs())
        return out


# ------------------------------------------------------------------ value classification
def _classify(values: np.ndarray, coeffs, p: float, q: float, low: float, high: float) -> tuple[np.ndarray, np.ndarray]:
    """(>= high, < low) for float values, exact: entries within rounding of an edge are
    re-evaluated in mpmath from their integer coefficients (callable coeffs(index) ->
    (a, b, c, d): value = a + b 2^p + c 2^q + d 2^(p+q))."""
    scale = np.abs(values) + abs(high) + abs(low) + 1.0
    err = 64.0 * _EPS * scale
    above = values >= high
    below = values < low
    doubtful = np.flatnonzero((np.abs(values - high) <= err) | (np.abs(values - low) <= err))
    if doubtful.size:
        import mpmath

        with mpmath.workdps(60):
            big_p, big_q = mpmath.mpf(2) ** mpmath.mpf(p), mpmath.mpf(2) ** mpmath.mpf(q)
            for i in doubtful:
                a, b, c, d = coeffs(int(i))
                exact = a + b * big_p + c * big_q + d * big_p * big_q
                above[i] = exact >= mpmath.mpf(high)
                below[i] = exact < mpmath.mpf(low)
    return above, below


def _check_probs(name: str, values, n: int) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,) or not np.all(np.isfinite(arr)) or np.any(arr < 0.0) or np.any(arr > 1.0):
        raise ParameterError(name, values if arr.ndim == 0 else "a list", f"must be one or n={n} probabilities in [0, 1]")
    return arr


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
SCALE_BITS = 900
_LOG_SCALE = SCALE_BITS * math.log(2.0)
FLOOR = 1e-300
"""Rates below FLOOR are not reported (``below_floor``); rates at or above it are exact."""
_LOG_FLOOR = math.log(FLOOR)
# a tail side is trimmed at 1e-325 of probability (scaled), far below FLOOR: the mass so
# dropped over the whole run is < n W 1e-325 (W the window) -- below 1e-300 * 1e-13 for any
# n W up to 1e12; the side of the bulk only, where no small region lies, at 1e-24 of the mass
TRIM_TAIL = math.exp(-325.0 * math.log(10.0) + _LOG_SCALE)
TRIM_BULK = 1e-24 * 2.0**SCALE_BITS
TRIM_EVERY = 8
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


def _mean_steps(pi: np.ndarray, lat: _Lattice) -> float:
    """E[x] of the lattice form (exact up to rounding): every term's expected lattice steps."""
    w1, w0 = pi, 1.0 - pi
    total = 0.0
    for a in (0, 1):
        for b in (0, 1):
            pa, pb = (w1 if a else w0), (w1 if b else w0)
            total += float(pa[0] * pb[1]) * lat.start[a][b][0] + float(pa[-2] * pb[-1]) * lat.end[a][b][0]
            for c in (0, 1):
                s = int(lat.shift[a, b, c])
                if s:
                    pc_ = w1 if c else w0
                    total += s * float(np.sum(pa[:-2] * pb[1:-1] * pc_[2:]))
    return total


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


def _first_at_least(lat: _Lattice, base, edge: float, p: float, q: float) -> int:
    """Smallest integer x with unit * x + base >= edge (exact)."""
    unit_value = _float_value(lat.unit, p, q)[0]
    base_value = _float_value(base, p, q)[0]
    if math.isinf(edge):
        return -(2**62) if edge < 0 else 2**62
    x = math.ceil((edge - base_value) / unit_value)
    coeffs = lambda k: tuple(u * k + b for u, b in zip(lat.unit, base))
    while _at_least(coeffs(x - 1), edge, p, q):
        x -= 1
    while not _at_least(coeffs(x), edge, p, q):
        x += 1
    return x


def _label_base(lat: _Lattice, ls: int, le: int):
    return tuple(s + e for s, e in zip(lat.start_labels[ls], lat.end_labels[le]))


def _rates_lattice(pi: np.ndarray, lat: _Lattice, low: float, high: float):
    """Per region (U >= high, low <= U < high, U < low): (ln P or None, below FLOOR), for one
    hypothesis (taxels present with probabilities ``pi``)."""
    p, q = lat.p, lat.q
    if lat.reverse:
        pi = pi[::-1]
    pairs = [(ls, le) for ls in range(len(lat.start_labels)) for le in range(len(lat.end_labels))]
    edges = {key: (_first_at_least(lat, _label_base(lat, *key), low, p, q),
                   _first_at_least(lat, _label_base(lat, *key), high, p, q)) for key in pairs}
    mean = _mean_steps(pi, lat)
    # a side of the bulk holds a region that may be small unless the bulk's own region covers it
    # (B = x < t_low lies below the mean unless it holds it, A = x >= t_high above it likewise)
    lower_tail = any(t_low <= mean for t_low, _ in edges.values())
    upper_tail = any(t_high > mean for _, t_high in edges.values())
    laws, scale, dropped = _lattice_law(pi, lat, lower_tail=lower_tail, upper_tail=upper_tail)
    sums = [0.0, 0.0, 0.0]  # H1 decided, undecided, H0 decided
    for key, (x_first, arr) in laws.items():
        t_low, t_high = edges[key]
        i_low = min(max(t_low - x_first, 0), arr.size)
        i_high = min(max(t_high - x_first, 0), arr.size)
        sums[0] += float(arr[i_high:].sum())
        sums[2] += float(arr[:i_low].sum())
        if i_high > i_low:
            sums[1] += float(arr[i_low:i_high].sum())
    # a region without a point of the x range for every label pair is impossible, trimmed or not
    xmin, xmax = _x_range(lat, pi.size)
    empty = (all(t_high > xmax for _, t_high in edges.values()),
             all(max(t_low, xmin) >= min(t_high, xmax + 1) for t_low, t_high in edges.values()),
             all(t_low <= xmin for t_low, _ in edges.values()))
    return _scaled_logs(sums, dropped, empty, scale)


def _x_range(lat: _Lattice, n: int) -> tuple[int, int]:
    """Bounds of x over all decision vectors (start steps, n - 2 inner steps, end steps)."""
    starts = [lat.start[a][b][0] for a in (0, 1) for b in (0, 1)]
    ends = [lat.end[a][b][0] for a in (0, 1) for b in (0, 1)]
    smin, smax = int(lat.shift.min()), int(lat.shift.max())
    return min(starts) + (n - 2) * smin + min(ends), max(starts) + (n - 2) * smax + max(ends)


def _log_probability(stored: float, scale=(SCALE_BITS, 0.0)) -> float:
    """ln of the probability behind a stored value (stored = probability * 2^E / e^L, scale =
    (E, L)), formed without cancellation: ln(mantissa) + (exponent - E) ln 2 + L."""
    if stored <= 0.0:
        return -math.inf
    mantissa, exp2 = math.frexp(stored)
    return math.log(mantissa) + (exp2 - scale[0]) * math.log(2.0) + scale[1]


def _scaled_logs(sums, dropped: float, empty=(False, False, False), scale=(SCALE_BITS, 0.0)):
    """Per region, from stored sums (``_log_probability``): (ln P or None, below FLOOR).
    Exact at or above FLOOR; an empty region, or 0 with nothing trimmed, is an impossible event
    (None, False); else (None, True): 0 <= P < FLOOR."""
    out = []
    for s, none in zip(sums, empty):
        log = _log_probability(s, scale)
        if log >= _LOG_FLOOR:
            out.append((log, False))
        else:
            out.append((None, not none and (s > 0.0 or dropped > 0.0)))
    return out


def preferential_law(pi, p, q, encoding: str):
    """The law of U_G (eq 7) for independent taxels present with probabilities ``pi``: (values,
    ln probabilities), values ascending (floats; equal values merged), every atom of
    probability >= FLOOR (the rest, < 1e-300 each and < 1e-290 together, left out). Lattice
    cases only (module doc); None for {0,1} with a non-integer weight."""
    from .encoding import check_encoding
    from .rules import check_weight

    p = check_weight("p", p)
    q = check_weight("q", q)
    encoding = check_encoding(encoding)
    pi = _check_probs("pi", pi, np.asarray(pi).size)
    n = pi.size
    if n == 1:
        u0 = 0.0 if encoding == "01" else -1.0
        atoms = {u0: 1.0 - pi[0], 1.0: pi[0]}
        vals = np.array(sorted(v for v, w in atoms.items() if w >= FLOOR))
        return vals, np.log([atoms[v] for v in vals])
    lat = _lattice(p, q, encoding)
    if lat is None:
        return None
    p, q = lat.p, lat.q
    laws, scale, _ = _lattice_law(pi[::-1] if lat.reverse else pi, lat)
    unit = _float_value(lat.unit, p, q)[0]
    vals, weights = [], []
    for (ls, le), (x_first, arr) in laws.items():
        base = _float_value(_label_base(lat, ls, le), p, q)[0]
        live = np.flatnonzero(arr)
        vals.append(base + unit * (x_first + live))
        weights.append(arr[live])
    vals = np.concatenate(vals)
    weights = np.concatenate(weights)
    order = np.argsort(vals, kind="stable")
    vals, weights = vals[order], weights[order]
    uniq, start = np.unique(vals, return_index=True)
    merged = np.add.reduceat(weights, start)
    logs = np.array([_log_probability(w, scale) for w in merged])
    keep = logs >= _LOG_FLOOR
    return uniq[keep], logs[keep]

# ------------------------------------------------------------------ generic (exact, sparse)
def _rates_sparse(pi: np.ndarray, p: float, q: float, encoding: str, low: float, high: float):
    n = pi.size
    # term coefficients (a, b, c, d) of the middle taxel: factor classes -> coefficient slot
    def coeff(a, b, c):
        u = 1 if b == 1 else (-1 if encoding == "pm1" else 0)
        if u == 0:
            return (0, 0, 0, 0)
        # next factor: c (succeeding, weight p), previous factor: a (weight q)
        def cls(state, weight):
            if state == 1:
                return "x"
            if state == 2 or encoding == "01":
                return 1
            return 1 if weight == 0.0 else 0
        fp, fq = cls(c, p), cls(a, q)
        if fp == 0 or fq == 0:
            return (0, 0, 0, 0)
        if fp == "x" and fq == "x":
            return (0, 0, 0, u)
        if fp == "x":
            return (0, u, 0, 0)
        if fq == "x":
            return (0, 0, u, 0)
        return (u, 0, 0, 0)

    def add(x, y):
        return (x[0] + y[0], x[1] + y[1], x[2] + y[2], x[3] + y[3])

    if n == 1:
        states = {(2, b): {coeff(2, b, 2): (pi[0] if b else 1.0 - pi[0])} for b in (0, 1)}
        final = {}
        for d in states.values():
            for k, v in d.items():
                final[k] = final.get(k, 0.0) + v
    else:
        states = {}
        for a in (0, 1):
            for b in (0, 1):
                states[(a, b)] = {coeff(2, a, b): (pi[0] if a else 1.0 - pi[0]) * (pi[1] if b else 1.0 - pi[1])}
        for i in range(2, n):
            pc = pi[i]
            new = {(b, c): {} for b in (0, 1) for c in (0, 1)}
            for (a, b), dist in states.items():
                for c in (0, 1):
                    t = coeff(a, b, c)
                    w = pc if c else 1.0 - pc
                    target = new[(b, c)]
                    for k, v in dist.items():
                        key = add(k, t)
                        target[key] = target.get(key, 0.0) + v * w
            states = new
        final = {}
        for (a, b), dist in states.items():
            t = coeff(a, b, 2)
            for k, v in dist.items():
                key = add(k, t)
                final[key] = final.get(key, 0.0) + v
    keys = list(final)
    big_p, big_q, pq = 2.0**p, 2.0**q, 2.0 ** (p + q)
    values = np.array([((b * big_p + c * big_q) + d * pq) + a for a, b, c, d in keys])
    probs = np.array([final[k] for k in keys]) * 2.0**SCALE_BITS
    above, below = _classify(values, lambda i: keys[i], p, q, low, high)
    return _scaled_logs([float(probs[above].sum()), float(probs[~above & ~below].sum()), float(probs[below].sum())], 0.0)


def _rates_monte_carlo(pi: np.ndarray, p: float, q: float, encoding: str, low: float, high: float,
                       samples: int, rng: np.random.Generator):
    from .rules import preferential_coefficients, preferential_value

    counts = np.zeros(3)
    absent = -1 if encoding == "pm1" else 0
    for _ in range(samples):
        u = np.where(rng.random(pi.size) < pi, 1, absent)
        v = preferential_value(preferential_coefficients(u, encoding), p, q)
        counts[0 if v >= high else (2 if v < low else 1)] += 1
    return counts / samples


def _wilson(k: float, n: int) -> tuple[float, float]:
    z = 1.959963984540054
    phat = k / n
    denom = 1 + z * z / n
    centre = (phat + z * z / (2 * n)) / denom
    half = z * math.sqrt(phat * (1 - phat) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def preferential_error_rates(pd, pf, p, q, encoding: str, low: float, high: float, n: int | None = None,
                             *, samples: int = 100_000, rng: np.random.Generator | None = None) -> PreferentialRates:
    """Exact system rates of "H1 iff U_G >= high, H0 iff U_G < low" (eq 7, eq 20 band) for
    independent taxels with P(present) = pd_i under H1 and pf_i under H0 (module doc).

    ``pd``, ``pf``: one value or n values in [0, 1]; ``n`` required when both are scalars.
    """
    from .encoding import check_encoding
    from .rules import check_weight

    p = check_weight("p", p)
    q = check_weight("q", q)
    encoding = check_encoding(encoding)
    if n is None:
        n = np.asarray(pd).size if np.asarray(pd).ndim else np.asarray(pf).size
    pd_arr = _check_probs("pd", pd, n)
    pf_arr = _check_probs("pf", pf, n)
    lat = _lattice(p, q, encoding) if n >= 2 else None
    if n == 1:  # U_G = u_1 (boundary on both sides): an integer
        method = "integer"
        run = lambda pi: _rates_single(pi[0], encoding, low, high)
    elif lat is not None:
        method = lat.method
        run = lambda pi: _rates_lattice(pi, lat, low, high)
    elif n <= SPARSE_MAX_TAXELS:
        method = "exact-sparse"
        run = lambda pi: _rates_sparse(pi, p, q, encoding, low, high)
    else:
        rng = rng if rng is not None else np.random.default_rng(0)
        r1 = _rates_monte_carlo(pd_arr, p, q, encoding, low, high, samples, rng)
        r0 = _rates_monte_carlo(pf_arr, p, q, encoding, low, high, samples, rng)
        ci = {"p_detect": _wilson(r1[0] * samples, samples), "p_undecided_h1": _wilson(r1[1] * samples, samples),
              "p_miss": _wilson(r1[2] * samples, samples), "p_false_alarm": _wilson(r0[0] * samples, samples),
              "p_undecided_h0": _wilson(r0[1] * samples, samples), "p_reject": _wilson(r0[2] * samples, samples)}
        logs = [(math.log(x) if x > 0 else None) for x in (*r1, *r0)]
        return PreferentialRates(*logs, method="monte-carlo", samples=samples, ci95=ci)
    results = [*run(pd_arr), *run(pf_arr)]
    below = tuple(name for name, (_, low_) in zip(_NAMES, results) if low_)
    return PreferentialRates(*[log for log, _ in results], method=method, below_floor=below)


def _rates_single(pi: float, encoding: str, low: float, high: float):
    """One taxel: U_G = u_1 in {-1, 1} or {0, 1} (eq 7 with u_0 = u_2 = 0)."""
    sums = [0.0, 0.0, 0.0]
    for value, w in ((1.0, pi), (-1.0 if encoding == "pm1" else 0.0, 1.0 - pi)):
        sums[0 if value >= high else (2 if value < low else 1)] += w * 2.0**SCALE_BITS
    return _scaled_logs(sums, 0.0)


# ------------------------------------------------------------------ kinds: LLR and N-P
@dataclass(frozen=True)
class KindRates:
    """Exact rates of a fusion rule on the present count per kind (product of binomials)."""

    p_detect: float
    p_false_alarm: float
    p_undecided_h1: float = 0.0
    p_undecided_h0: float = 0.0
    method: str = "kinds"
    samples: int | None = None
    ci95: dict | None = None


def kinds_of(pd: np.ndarray, pf: np.ndarray):
    """Group taxels with equal (pd, pf): (pd_k, pf_k, size_k) arrays."""
    pairs = {}
    for a, b in zip(np.asarray(pd, float), np.asarray(pf, float)):
        pairs[(a, b)] = pairs.get((a, b), 0) + 1
    keys = list(pairs)
    return (np.array([k[0] for k in keys]), np.array([k[1] for k in keys]),
            np.array([pairs[k] for k in keys], dtype=np.int64))


def _kind_atoms(pd_k, pf_k, size_k):
    """Every tuple of present counts per kind: ln Lambda, ln P0, ln P1 (flattened)."""
    from scipy.special import gammaln

    total = int(np.prod(size_k + 1, dtype=float))
    if total > KIND_ATOMS_MAX:
        raise ParameterError("pd/pf", f"{len(size_k)} kinds, {total} count tuples",
                             f"exact kinds enumeration is limited to {KIND_ATOMS_MAX} count tuples")
    llr = np.zeros(1)
    lp0 = np.zeros(1)
    lp1 = np.zeros(1)
    for a1, a0, m in zip(pd_k, pf_k, size_k):
        k = np.arange(m + 1)
        lc = gammaln(m + 1) - gammaln(k + 1) - gammaln(m - k + 1)
        l1 = lc + k * np.log(a1) + (m - k) * np.log1p(-a1)
        l0 = lc + k * np.log(a0) + (m - k) * np.log1p(-a0)
        stat = k * (np.log(a1) - np.log(a0)) + (m - k) * (np.log1p(-a1) - np.log1p(-a0))
        llr = (llr[:, None] + stat[None, :]).ravel()
        lp0 = (lp0[:, None] + l0[None, :]).ravel()
        lp1 = (lp1[:, None] + l1[None, :]).ravel()
    return llr, lp0, lp1


def _tail_sums(llr, lp0, lp1, threshold, tol=1e-9):
    scale = np.maximum(1.0, np.abs(llr))
    above = llr - threshold > tol * scale
    tie = np.abs(llr - threshold) <= tol * scale
    e = lambda lp, mask: float(np.sum(np.exp(lp[mask]))) if mask.any() else 0.0
    return e(lp1, above), e(lp0, above), e(lp1, tie), e(lp0, tie)


def llr_error_rates(pd, pf, prior_h1: float = 0.5, *, samples: int = 200_000,
                    rng: np.random.Generator | None = None) -> KindRates:
    """P_D, P_F of the Chair-Varshney rule (eq 31, H1 iff ln P(H1|U)/P(H0|U) > 0; a tie
    within 1e-9 is "undecided"). Exact when the count tuples per kind fit in KIND_ATOMS_MAX
    (kinds, or all 2^n vectors for n <= 20); otherwise an importance-sampling estimate
    (``method="importance-sampling"``, 95 % intervals in ``ci95``)."""
    pd_k, pf_k, size_k = kinds_of(pd, pf)
    threshold = -math.log(prior_h1 / (1.0 - prior_h1))
    if float(np.prod(size_k + 1.0)) <= KIND_ATOMS_MAX:
        llr, lp0, lp1 = _kind_atoms(pd_k, pf_k, size_k)
        d, f, ud, uf = _tail_sums(llr, lp0, lp1, threshold)
        return KindRates(d, f, ud, uf, method=f"exact ({len(size_k)} kind{'s' if len(size_k) != 1 else ''})")
    pd_arr, pf_arr = np.asarray(pd, float), np.asarray(pf, float)
    a = np.log(pd_arr) - np.log(pf_arr)
    b = np.log1p(-pd_arr) - np.log1p(-pf_arr)
    rng = rng if rng is not None else np.random.default_rng(0)
    det, det_ci = importance_sampling_tail(a, b, pd_arr, threshold, samples, rng)
    fa, fa_ci = importance_sampling_tail(a, b, pf_arr, threshold, samples, rng)
    return KindRates(det, fa, method="importance-sampling", samples=samples,
                     ci95={"p_detect": det_ci, "p_false_alarm": fa_ci})


def importance_sampling_tail(a, b, probs, threshold: float, samples: int, rng: np.random.Generator):
    """P(S > threshold), S = sum_i (a_i if present else b_i), taxel i present with probability
    probs_i, by importance sampling with exponential tilting: taxel i is drawn present with
    q_i = p_i e^(theta a_i) / (p_i e^(theta a_i) + (1 - p_i) e^(theta b_i)), theta chosen so that
    the tilted mean of S is the threshold (theta = 0 when the event is not rare), each sample
    weighted by exp(-theta S + sum_i ln M_i(theta)). Returns (estimate, 95 % normal interval)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    p = np.asarray(probs, float)

    def tilted(theta):
        la = np.log(p) + theta * a
        lb = np.log1p(-p) + theta * b
        lm = np.logaddexp(la, lb)  # ln M_i(theta)
        q = np.exp(la - lm)
        return q, lm

    def mean(theta):
        q, _ = tilted(theta)
        return float(np.sum(q * a + (1 - q) * b))

    # the rarer side is estimated: the upper tail if the mean lies below the threshold (tilt up,
    # theta > 0), else the lower tail P(S <= threshold) (tilt down) and its complement returned
    upper = mean(0.0) < threshold
    sign = 1.0 if upper else -1.0
    lo, hi = 0.0, 1.0
    while (mean(sign * hi) < threshold) == upper and hi < 1e6:
        hi *= 2.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if (mean(sign * mid) < threshold) == upper:
            lo = mid
        else:
            hi = mid
    theta = sign * hi
    q, lm = tilted(theta)
    total_lm = float(np.sum(lm))
    values = []
    for start in range(0, samples, 10_000):
        m = min(10_000, samples - start)
        present = rng.random((m, p.size)) < q
        stat = np.where(present, a, b).sum(axis=1)
        hit = stat - threshold > 1e-9 * np.maximum(1.0, np.abs(stat))
        if not upper:
            hit = ~hit
        values.append(np.where(hit, np.exp(-theta * stat + total_lm), 0.0))
    w = np.concatenate(values)
    est = float(w.mean())
    half = 1.959963984540054 * float(w.std(ddof=1)) / math.sqrt(w.size)
    if upper:
        return est, (max(0.0, est - half), est + half)
    return 1.0 - est, (max(0.0, 1.0 - est - half), min(1.0, 1.0 - est + half))


def np_kinds_fusion(pd, pf, false_alarm: float) -> dict:
    """Most powerful randomised test of size ``false_alarm`` over the present counts per kind
    (N-P lemma on the product-of-binomials law): ln Lambda of every count tuple, sorted, the
    boundary atom randomised. Returns log_threshold, gamma, achieved_false_alarm,
    detection_probability (exact)."""
    from .baselines import _merge_atoms, _randomised_boundary

    pd_k, pf_k, size_k = kinds_of(pd, pf)
    llr, lp0, lp1 = _kind_atoms(pd_k, pf_k, size_k)
    values, p0, p1 = _merge_atoms(llr, np.exp(lp0), np.exp(lp1))
    j, gamma, achieved, detection = _randomised_boundary(p0, p1, false_alarm)
    return {"log_threshold": float(values[j]), "gamma": gamma, "achieved_false_alarm": achieved,
            "detection_probability": detection, "kinds": int(len(size_k)), "method": "kinds"}


def _linear_statistic_atoms(a, b, probs):
    """(S, ln P) of every atom of S = sum_i (a_i if taxel i present else b_i), taxel i present
    with probability probs_i, independent; None beyond KIND_ATOMS_MAX atoms. Taxels with equal
    (a_i, b_i) form a kind, S depends on the present count per kind only, and each kind's count
    has the Poisson-binomial law of its taxels' probabilities (log domain, exact for unequal
    probabilities within a kind); the atoms are the tuples of per-kind counts."""
    from .poisson_binomial import log_pmf

    a = np.asarray(a, float)
    b = np.asarray(b, float)
    probs = np.asarray(probs, float)
    groups: dict = {}
    for i, key in enumerate(zip(a, b)):
        groups.setdefault(key, []).append(i)
    if float(np.prod([len(v) + 1.0 for v in groups.values()])) > KIND_ATOMS_MAX:
        return None
    stat = np.zeros(1)
    logp = np.zeros(1)
    for (ai, bi), members in groups.items():
        m = len(members)
        k = np.arange(m + 1)
        with np.errstate(divide="ignore"):
            lp = log_pmf(probs[members])
        s = k * ai + (m - k) * bi
        stat = (stat[:, None] + s[None, :]).ravel()
        logp = (logp[:, None] + lp[None, :]).ravel()
    live = np.isfinite(logp)
    return stat[live], logp[live]


def linear_statistic_law(a, b, probs, tol: float = 1e-9):
    """The law of S (:func:`_linear_statistic_atoms`) as (values ascending, ln P), atoms within
    ``tol`` (relative) of each other merged; None beyond KIND_ATOMS_MAX atoms."""
    atoms = _linear_statistic_atoms(a, b, probs)
    if atoms is None:
        return None
    stat, logp = atoms
    order = np.argsort(stat, kind="stable")
    stat, logp = stat[order], logp[order]
    gap = np.diff(stat) > tol * np.maximum(1.0, np.abs(stat[1:]))
    start = np.flatnonzero(np.r_[True, gap])
    values = stat[start]
    merged = np.array([_logsumexp(logp[s:e]) for s, e in zip(start, np.r_[start[1:], stat.size])])
    return values, merged


def _logsumexp(x) -> float:
    x = np.asarray(x, float)
    top = float(x.max())
    return top + math.log(float(np.exp(x - top).sum())) if math.isfinite(top) else -math.inf


def roc_from_laws(law_h0, laws_h1, weights, points: int = 400) -> dict:
    """Exact ROC of "H1 iff statistic >= t" from the law under H0 and the laws under the H1
    patterns (mixed with ``weights``), t over every attainable value: P_F(t) and P_D(t) as
    tails summed from the top in the log domain. Returns thresholds, pf, pd, log10_pf and
    log10_pm (P_M = 1 - P_D from the lower tails, exact also where they underflow), auc (trapezoid over all thresholds, linear axes) and at most
    about ``points`` + 2 per decade of pf of them for plotting."""
    values = np.unique(np.concatenate([law_h0[0], *[law[0] for law in laws_h1]]))[::-1]

    def log_tail(law):
        vals, logp = law
        order = np.argsort(vals)[::-1]
        vals, logp = vals[order], logp[order]
        cum = np.logaddexp.accumulate(logp)  # ln P(stat >= vals[j])
        idx = np.searchsorted(-vals, -values, side="right") - 1  # last law value >= t
        out = np.full(values.size, -np.inf)
        ok = idx >= 0
        out[ok] = cum[idx[ok]]
        return out

    def log_below(law):  # ln P(stat < t): the atoms below each t, summed from the bottom
        vals, logp = law
        order = np.argsort(vals)
        vals, logp = vals[order], logp[order]
        cum = np.logaddexp.accumulate(logp)
        idx = np.searchsorted(vals, values, side="left") - 1  # last law value < t
        out = np.full(values.size, -np.inf)
        ok = idx >= 0
        out[ok] = cum[idx[ok]]
        return out

    log_pf = log_tail(law_h0)
    pd = np.zeros(values.size)
    log_pm = np.full(values.size, -np.inf)
    for law, w in zip(laws_h1, weights):
        pd += w * np.exp(log_tail(law))
        if w > 0:
            log_pm = np.logaddexp(log_pm, math.log(w) + log_below(law))
    pf = np.exp(log_pf)
    pf_all = np.r_[0.0, pf, 1.0]
    pd_all = np.r_[0.0, pd, 1.0]
    auc = float(np.trapezoid(pd_all, pf_all))
    # thinning for the plot: the first threshold of every half decade of pf and of every
    # 1/points step of pd, and both ends
    with np.errstate(divide="ignore", invalid="ignore"):
        decade = np.where(np.isfinite(log_pf), np.floor(2.0 * log_pf / math.log(10.0)), -1e9)
    step = np.floor(pd * points)
    keep = np.union1d(np.unique(decade, return_index=True)[1], np.unique(step, return_index=True)[1])
    keep = np.union1d(keep, [0, values.size - 1]).astype(int)
    log10_pf = log_pf / math.log(10.0)
    log10_pm = log_pm / math.log(10.0)
    finite = lambda arr: [None if not math.isfinite(x) else float(x) for x in arr[keep]]
    return {"thresholds": values[keep].tolist(), "pf": pf[keep].tolist(), "pd": pd[keep].tolist(),
            "log10_pf": finite(log10_pf), "log10_pm": finite(log10_pm), "auc": auc, "method": "exact"}


def linear_statistic_tail(a, b, probs, threshold: float, gamma: float = 0.0, tol: float = 1e-9) -> float | None:
    """P(S > threshold) + gamma P(S = threshold) for S = sum_i (a_i if taxel i present else b_i),
    taxel i present with probability probs_i, independent (eq 31/32 statistics; ties within
    tol relative). Exact over the atoms of :func:`_linear_statistic_atoms` (kinds of equal
    (a_i, b_i), a Poisson-binomial count per kind); None beyond KIND_ATOMS_MAX atoms."""
    atoms = _linear_statistic_atoms(a, b, probs)
    if atoms is None:
        return None
    stat, logp = atoms
    scale = np.maximum(1.0, np.abs(stat))
    above = stat - threshold > tol * scale
    tie = np.abs(stat - threshold) <= tol * scale
    return float(np.exp(logp[above]).sum() + gamma * np.exp(logp[tie]).sum())
