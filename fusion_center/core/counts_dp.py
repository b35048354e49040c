"""The {0,1} counts DPs of the preferential rule (eq 7) where U_G has no lattice form ({0,1}
with a non-integer weight, :mod:`.chain_dp`): an absent taxel and the boundary both give the
factor 1, so

    U_G = a + b (2^p + 2^q) + d 2^(p+q)

over three integer counts (runs of one present taxel, longer runs, taxels inside runs).
``_rates_counts`` runs the DP over the three counts (polynomial, a box of counts per state);
where U_G needs two integer coordinates only (``_two_count_form``: a zero weight, p or q an
integer, p + q an integer) ``_rates_two_counts`` runs it over those two. Both give the band
rates (eq 20) per hypothesis, every rate >= FLOOR exact; a rate below FLOOR (or a sum of 0.0,
which may be an underflow) is named without a log and left to :mod:`.extended_dp`. The
comparisons of U_G with the band edges are exact (``_classify``: mpmath within rounding).
Used by :mod:`.preferential_rates`
(:func:`.preferential_rates.exact_counts_max_taxels` says up to how many taxels each is exact
for any probabilities).
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np

from .dp_scaling import _EPS, _LOG_SCALE, SCALE_BITS, TRIM_EVERY, TRIM_TAIL, _scaled_logs


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


# ------------------------------------------------------------------ shared by both counts DPs
def _empty_regions(n: int, p: float, q: float, low: float, high: float) -> tuple[bool, bool, bool]:
    """Regions (U >= high, low <= U < high, U < low) that no value of U_G lies in, for sure: on
    {0,1} U_G runs from 0 (all absent) to g(n) (all present, eq 15; 1 for n = 1), so U >= high
    is empty where high is beyond g(n) by more than its rounding, U < low where low <= 0, the band
    where high <= low (a zero-width band, as the report's single threshold). Their sums are 0
    for certain: impossible events, not left to :mod:`.extended_dp`."""
    g = 1.0 if n == 1 else (2.0**p + 2.0**q) + (n - 2) * 2.0 ** (p + q)
    return high > g * (1.0 + 1e-12), not low < high, low <= 0.0


def _branch_factors(pc: float) -> tuple[float, float, float]:
    """A taxel present with probability pc: (ln big, pc / big, (1 - pc) / big), big = max(pc,
    1 - pc) -- the likelier branch is not multiplied, its factor goes into an exact-sum log."""
    qc = 1.0 - pc
    big = max(pc, qc)
    return math.log(big), pc / big, qc / big


def _rescale_trim(states, origin, exponent: int, log_factors):
    """Every TRIM_EVERY taxels: the three states' boxes of counts (one shape) rescaled by a power
    of two (the largest cell of their sum back to ~2^SCALE_BITS, exact) and trimmed along each
    axis where the marginal of their sum carries less than 1e-325 of probability. Returns
    (states, origin, exponent)."""
    s0, s1, s2 = states
    total = s0 + s1 + s2
    k = math.frexp(float(total.max()))[1] - SCALE_BITS - 1
    if k:
        for arr in (s0, s1, s2):
            arr *= math.ldexp(1.0, -k)
        total *= math.ldexp(1.0, -k)
        exponent -= k
    # stored units of 1e-325 of probability
    tail = TRIM_TAIL * math.exp(exponent * math.log(2.0) - math.fsum(log_factors) - _LOG_SCALE)
    cuts = []
    for axis in range(total.ndim):
        other = tuple(j for j in range(total.ndim) if j != axis)
        marg = total.sum(axis=other)
        keep = np.flatnonzero(marg >= tail)
        cuts.append((int(keep[0]), int(keep[-1]) + 1) if keep.size else (0, marg.size))
    if any(lo_ > 0 or hi_ < size for (lo_, hi_), size in zip(cuts, total.shape)):
        sl = tuple(slice(lo_, hi_) for lo_, hi_ in cuts)
        s0, s1, s2 = s0[sl].copy(), s1[sl].copy(), s2[sl].copy()
        origin = [o + lo_ for o, (lo_, _) in zip(origin, cuts)]
    return (s0, s1, s2), origin, exponent


# ------------------------------------------------------------------ {0,1}, any weights: counts DP
def _rates_counts(pi: np.ndarray, p: float, q: float, low: float, high: float):
    """Per region (U >= high, low <= U < high, U < low): (ln P or None, below FLOOR), exact, for
    {0,1} with any p, q (eq 7): on {0,1} an absent taxel and the boundary both give the factor 1,
    so a run of L present taxels contributes 1 (L = 1) or 2^p + 2^q + (L - 2) 2^(p+q) (its first
    taxel 2^p, its last 2^q, the inner ones 2^(p+q)), and

        U_G = a + b (2^p + 2^q) + d 2^(p+q),   a = runs of length 1, b = longer runs,
                                              d = present taxels inside runs.

    The DP runs along the chain with the state "last taxel absent / run of length 1 / run of
    length >= 2" and a 3-d array over the counts (a, b, d) per state: a step adds one to a
    (a run of one ends), b (a run reaches length 2) or d (a longer run grows), three shifted
    vector additions. The counts' box is trimmed every TRIM_EVERY taxels where its slabs carry
    less than 1e-325 of probability (like the lattice DP: every rate >= FLOOR exact, those below
    not computed). Polynomial: at most (n/2)(n/3) n counts per state, in practice the box of
    the law's bulk, O(n^(3/2)) per step for a fixed per-taxel probability; beyond
    COUNTS_WORK_MAX array elements in total it gives up (None) -- preferential_error_rates then
    estimates by Monte Carlo."""
    n = pi.size
    one = 2.0**SCALE_BITS
    # arrays per state over (a, b, d) from the box origin (a0, b0, d0)
    shape = (1, 1, 1)
    s0, s1, s2 = np.full(shape, one), np.zeros(shape), np.zeros(shape)
    origin = [0, 0, 0]
    exponent = SCALE_BITS
    log_factors = []
    work = 0
    for i, pc in enumerate(pi.tolist()):
        log_big, fp, fq = _branch_factors(pc)
        log_factors.append(log_big)
        na, nb, nd = s0.shape
        n0 = np.zeros((na + 1, nb, nd))
        n0[:na] += s0
        n0[:na] += s2
        n0[1:] += s1  # a run of length one ends: a + 1
        n0 *= fq
        n1 = np.zeros((na + 1, nb, nd))
        n1[:na] = s0 * fp
        n2 = np.zeros((na + 1, nb + 1, nd + 1))
        n2[:na, 1:, :nd] += s1  # a run reaches length two: b + 1
        n2[:na, :nb, 1:] += s2  # a longer run grows: d + 1
        n2 *= fp
        # the three boxes to one shape
        shape = (na + 1, nb + 1, nd + 1)
        s0 = np.pad(n0, ((0, 0), (0, 1), (0, 1)))
        s1 = np.pad(n1, ((0, 0), (0, 1), (0, 1)))
        s2 = n2
        work += 3 * s2.size
        if work + 3 * s2.size * (n - 1 - i) > COUNTS_WORK_MAX:  # the box only grows or is trimmed
            return None
        if i % TRIM_EVERY == TRIM_EVERY - 1 or i == n - 1:
            (s0, s1, s2), origin, exponent = _rescale_trim((s0, s1, s2), origin, exponent, log_factors)
    # the last taxel ends its run: state 1 -> a + 1
    na, nb, nd = s0.shape
    law = np.zeros((na + 1, nb, nd))
    law[:na] += s0 + s2
    law[1:] += s1
    a = origin[0] + np.arange(na + 1)[:, None, None]
    b = origin[1] + np.arange(nb)[None, :, None]
    d = origin[2] + np.arange(nd)[None, None, :]
    live = law > 0.0
    av, bv, dv = (np.broadcast_to(x, law.shape)[live] for x in (a, b, d))
    weights = law[live]
    values = (av + bv * (2.0**p + 2.0**q)) + dv * 2.0 ** (p + q)
    above, below = _classify(values, lambda j: (int(av[j]), int(bv[j]), int(bv[j]), int(dv[j])), p, q, low, high)
    sums = [float(weights[above].sum()), float(weights[~above & ~below].sum()), float(weights[below].sum())]
    # a sum of 0.0 may be an underflow (dp_scaling._scaled_logs): "below FLOOR", told from an
    # impossible event by extended_dp.counts_exact_logs (preferential_rates)
    return _scaled_logs(sums, _empty_regions(n, p, q, low, high), scale=(exponent, math.fsum(log_factors)))


# ------------------------------------------------------------------ {0,1}, two counts
def _two_count_form(p: float, q: float):
    """Where U_G on {0,1} (a + b (2^p + 2^q) + d 2^(p+q), ``_rates_counts``) needs two integer
    coordinates only: U_G = y1 + c y2 with (y1, y2) moved by an integer vector per count --
    ((da, db, dd) as (y1, y2) steps, c, basis) with basis(y1, y2) the coefficients of (1, 2^p,
    2^q, 2^(p+q)) -- or None. Exact identities of eq 7's terms on {0,1}:

    * a zero weight, q = 0: 2^q = 1, U_G = (a + b) + (b + d) 2^p (p = 0: the mirror);
    * p an integer: U_G = (a + b 2^p) + (b + d 2^p) 2^q (q an integer: the mirror);
    * p + q an integer K: U_G = (a + d 2^K) + b (2^p + 2^q).

    (Both weights integers: U_G is an integer, the lattice DP's case.)"""
    if q == 0.0:
        return ((1, 0), (1, 1), (0, 1)), 2.0**p, lambda y1, y2: (y1, y2, 0, 0)
    if p == 0.0:
        return ((1, 0), (1, 1), (0, 1)), 2.0**q, lambda y1, y2: (y1, 0, y2, 0)
    if float(p).is_integer():
        k = 2 ** int(p)
        return ((1, 0), (k, 1), (0, k)), 2.0**q, lambda y1, y2: (y1, 0, y2, 0)
    if float(q).is_integer():
        k = 2 ** int(q)
        return ((1, 0), (k, 1), (0, k)), 2.0**p, lambda y1, y2: (y1, y2, 0, 0)
    if (Fraction(p) + Fraction(q)).denominator == 1:
        k = 2 ** int(Fraction(p) + Fraction(q))
        return ((1, 0), (0, 1), (k, 0)), 2.0**p + 2.0**q, lambda y1, y2: (y1, y2, y2, 0)
    return None


TWO_COUNTS_WORK_MAX = 100_000_000
"""Array elements the two-count DP may touch (~0.6-1 s here); it gives up (None) as soon as the
box it holds, growing as it has (area ~ taxels^2), would take it beyond this."""


def _rates_two_counts(pi: np.ndarray, p: float, q: float, low: float, high: float):
    """``_rates_counts`` where :func:`_two_count_form` applies: the same DP along the chain
    (state: last taxel absent / run of length 1 / run of length >= 2; a run of one ends: a + 1;
    a run reaches length two: b + 1; a longer run grows: d + 1, eq 7 on {0,1}), over a 2-d array
    of (y1, y2) per state instead of 3-d counts: O(n^2) cells per step at most, ~40x faster at
    200 taxels. Trimmed, rescaled and classified like ``_rates_counts`` (every rate >= FLOOR
    exact; comparisons with the edges exact, mpmath within rounding); None where the form does
    not apply or beyond TWO_COUNTS_WORK_MAX."""
    form = _two_count_form(p, q)
    if form is None:
        return None
    (step_a, step_b, step_d), c_value, basis = form
    g1 = max(step_a[0], step_b[0], step_d[0])
    g2 = max(step_a[1], step_b[1], step_d[1])
    n = pi.size
    s0, s1, s2 = np.full((1, 1), 2.0**SCALE_BITS), np.zeros((1, 1)), np.zeros((1, 1))
    origin = [0, 0]
    exponent = SCALE_BITS
    log_factors = []
    work = 0
    for i, pc in enumerate(pi.tolist()):
        log_big, fp, fq = _branch_factors(pc)
        log_factors.append(log_big)
        m1, m2 = s0.shape
        shape = (m1 + g1, m2 + g2)
        n0 = np.zeros(shape)  # absent: runs so far unchanged, a run of one ends (a + 1)
        n0[:m1, :m2] += s0
        n0[:m1, :m2] += s2
        n0[step_a[0]:step_a[0] + m1, step_a[1]:step_a[1] + m2] += s1
        n0 *= fq
        n1 = np.zeros(shape)  # a run starts
        n1[:m1, :m2] = s0 * fp
        n2 = np.zeros(shape)  # a run reaches two (b + 1) or grows (d + 1)
        n2[step_b[0]:step_b[0] + m1, step_b[1]:step_b[1] + m2] += s1
        n2[step_d[0]:step_d[0] + m1, step_d[1]:step_d[1] + m2] += s2
        n2 *= fp
        s0, s1, s2 = n0, n1, n2
        work += 3 * s2.size
        # the box's sides grow ~linearly (trimming aside): projected, the rest costs ~box (j/i)^2
        # per taxel j, sum ~ box (n^3 - i^3) / (3 i^2) -- giving up early, not after most of it
        rest = n - 1 - i
        grown = s2.size * (((n / (i + 1)) ** 3 - 1.0) * (i + 1) / 3.0 if i >= max(31, n // 10) else rest)
        if work + 3 * grown > TWO_COUNTS_WORK_MAX:
            return None
        if i % TRIM_EVERY == TRIM_EVERY - 1 or i == n - 1:
            (s0, s1, s2), origin, exponent = _rescale_trim((s0, s1, s2), origin, exponent, log_factors)
    # the last taxel ends its run: state 1 -> a + 1
    m1, m2 = s0.shape
    law = np.zeros((m1 + step_a[0], m2 + step_a[1]))
    law[:m1, :m2] += s0 + s2
    law[step_a[0]:step_a[0] + m1, step_a[1]:step_a[1] + m2] += s1
    y1 = origin[0] + np.arange(law.shape[0])[:, None]
    y2 = origin[1] + np.arange(law.shape[1])[None, :]
    live = law > 0.0
    v1, v2 = (np.broadcast_to(y, law.shape)[live] for y in (y1, y2))
    weights = law[live]
    values = v1 + v2 * c_value
    above, below = _classify(values, lambda j: basis(int(v1[j]), int(v2[j])), p, q, low, high)
    sums = [float(weights[above].sum()), float(weights[~above & ~below].sum()), float(weights[below].sum())]
    return _scaled_logs(sums, _empty_regions(n, p, q, low, high), scale=(exponent, math.fsum(log_factors)))


COUNTS_WORK_MAX = 400_000_000
"""Array elements the counts DP may touch in total (a few seconds); it gives up (returns None)
as soon as the box it holds, kept for the remaining taxels, would exceed this."""
