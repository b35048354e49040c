"""Exact band rates (eq 7, eq 20 band) of the preferential rule in extended-exponent
arithmetic: the rates the fast DPs leave without a certified logarithm, whatever their size.

The fast DPs carry probabilities as doubles scaled by one power of two per step: the lattice
DP tilted towards each region (:mod:`.tilted_dp`) and the {0,1} counts DPs (:mod:`.counts_dp`,
every rate >= FLOOR = 1e-300 exact, nothing below). Neither reaches every rate:

* the tilt is capped (tilted_dp.G_MAX), so where a region is reachable only through decisions
  of tiny probability (per-taxel probabilities of ~1e-25 and below) the tilted law never
  reaches it and the run trims the region away: a reachable region comes back as -inf (14
  taxels with pf = 1e-45, a false alarm needing all 14 present: P_F = 1e-630);
* the counts DPs keep their largest cell at 2^SCALE_BITS, and a cell 2^-1974 below it
  underflows to 0 without being counted as dropped: a region holding only such cells sums to
  0.0 and cannot be told from an impossible one.

Here every probability is a pair (mantissa m, int64 exponent e): value m 2^e, an exact zero m =
0 (e = _ZERO). A product multiplies the mantissa and adds the exponent; a sum scales both terms
by exact powers of two onto the larger exponent (``_pow2``) and adds; the mantissas are
renormalised to [1/2, 1) every PRUNE_EVERY steps (in between they drift by at most 2^PRUNE_EVERY).
The exponent never overflows and nothing underflows but a term below 2^-1022 of the one it is
added to. Nothing is trimmed: a cell is dropped only where no continuation of the chain can
bring it into a region asked for (exact reachability bounds on the steps still to come), so a
result is 0 exactly when the region's probability is 0 (an event the rule cannot produce, or one
needing a taxel with probability exactly 0 or 1), and otherwise positive with

    relative error <= (4 n + 6) u,     u = 2^-53,

n taxels: every value is a sum of positive products, and along any one product at most four
roundings per step (two additions of the three terms of a {0,1} state, one product, the rounding
of 1 - pi_i) and a few at the ends (the first two taxels' product, the final math.fsum). For
n = 60 that is < 3e-14 relative in P, i.e. < 3e-14 absolute in ln P.

Cost: O(n W) operations on arrays, W the reachable window (the lattice: 4 states x labels x
the x range, O(n); {0,1}: the box of counts, O(n^3)), ~50-100 ns per cell and step here; a run
that would exceed EXACT_WORK_MAX cells x steps stops (None): the rate keeps the fast DP's answer
(below FLOOR, log not computed). Used by :mod:`.preferential_rates` for the rates the fast DPs
leave below FLOOR without a log (or at 0.0), or with an error bound above 10^BOUND_OK.
"""

from __future__ import annotations

import math

import numpy as np

from .chain_dp import _first_at_least, _label_base, _Lattice, _x_range

EXACT_WORK_MAX = 30_000_000
"""Cells x steps an extended-exponent run may touch (~1-3 s on the shared 2-core machine,
~50-100 ns per cell and step): unpruned, the chain with three labels up to ~1500 taxels, one
label ~2700, the {0,1} counts box up to ~110 taxels; more where the reachability bounds prune
(a far tail)."""

PRUNE_EVERY = 8
"""Steps between the reachability prunings (a pruning costs about one step)."""

_ZERO = -(1 << 52)
"""Exponent of an exact zero (mantissa 0): below any exponent a product of doubles reaches
(>= -1075 per factor), and far from int64's limits."""
_LN2 = math.log(2.0)


# ------------------------------------------------------------------ extended-exponent arithmetic
def _zeros(shape) -> tuple[np.ndarray, np.ndarray]:
    return np.zeros(shape), np.full(shape, _ZERO, dtype=np.int64)


def _factor(x: float) -> tuple[float, int]:
    """(mantissa, exponent) of a probability x >= 0 (0 -> (0.0, 0): its products are zeros)."""
    m, e = math.frexp(x)
    return m, e


def _pow2(k: np.ndarray) -> np.ndarray:
    """2^k for an owned int64 array k <= 0, formed in place (its bits become the doubles'):
    the biased exponent k + 1023 shifted into place, 0.0 for k < -1022 -- a term that far
    below the one it is added to changes the sum by less than 2^-1022 of it. Cheaper than
    np.ldexp (a libm call per element)."""
    np.maximum(k, -1023, out=k)
    k += 1023
    np.left_shift(k, 52, out=k)
    return k.view(np.float64)


def _add_into(md, ed, m1, e1, m2, e2, tmp) -> None:
    """(md, ed) = (m1, e1) + (m2, e2), aligned on the larger exponent (one rounding); ``tmp`` an
    owned int64 array of their shape."""
    np.maximum(e1, e2, out=ed)
    np.subtract(e1, ed, out=tmp)
    np.multiply(m1, _pow2(tmp), out=md)
    np.subtract(e2, ed, out=tmp)
    scaled = _pow2(tmp)
    np.multiply(m2, scaled, out=scaled)
    md += scaled


def _acc(M: np.ndarray, E: np.ndarray, sl, m: np.ndarray, e: np.ndarray) -> None:
    """M, E [sl] += (m, e) (``sl`` basic indexing: views)."""
    mt, et = M[sl], E[sl]
    top = np.maximum(et, e)
    mt *= _pow2(et - top)
    mt += m * _pow2(e - top)
    et[...] = top


def _times(M: np.ndarray, E: np.ndarray, factor: tuple[float, int]) -> None:
    """M, E *= factor (in place; a zero factor: zeros). The mantissas leave [1/2, 1) by at most
    a factor 2 per step (a sum of two or three terms, the largest aligned to 1, times a
    mantissa in [1/2, 1)) and are renormalised every PRUNE_EVERY steps (``_normalise``)."""
    if factor[0] == 0.0:
        M[...] = 0.0
        E[...] = _ZERO
        return
    M *= factor[0]
    E += factor[1]


def _normalise(M: np.ndarray, E: np.ndarray) -> None:
    mant, exp2 = np.frexp(M)
    M[...] = mant
    E += exp2


def _log_sum(m: np.ndarray, e: np.ndarray) -> float:
    """ln of the sum of the values m 2^e (-inf for none or all zero)."""
    live = m > 0.0
    if not live.any():
        return -math.inf
    m, e = m[live], e[live]
    top = int(e.max())
    return math.log(math.fsum(np.ldexp(m, e - top).tolist())) + top * _LN2


# ------------------------------------------------------------------ lattice (chain, lattice, integer)
def _future_tables(lat: _Lattice, n: int, edges: dict) -> list:
    """For k = 0 .. n - 2 inner steps still to come after a taxel (state (a, b) at index 2 a + b),
    arrays (4, labels) of max(steps - t_high), min(steps - t_low), max(steps - t_low),
    min(steps - t_high) over every continuation (k shifts, then the last taxel's end steps; t
    the edges of the start label and the continuation's end label): a cell at x can end at or
    above the upper edge only if x + max(steps - t_high) >= 0, and so on. Exact integers."""
    labels = len(lat.start_labels)
    base = np.zeros((4, 4, labels), dtype=np.int64)  # (quantity, state, ls)
    for a in (0, 1):
        for b in (0, 1):
            steps, le = lat.end[a][b]
            for ls in range(labels):
                t_low, t_high = edges[(ls, le)]
                base[:, 2 * a + b, ls] = (steps - t_high, steps - t_low, steps - t_low, steps - t_high)
    tables = [base]
    is_max = np.array([True, False, True, False])[:, None, None]
    # state (a, b) at index 2 a + b moves to (b, c) at 2 b + c, x by shift[a, b, c]
    to = [np.array([2 * b + c for a in (0, 1) for b in (0, 1)]) for c in (0, 1)]
    moves = [np.array([int(lat.shift[a, b, c]) for a in (0, 1) for b in (0, 1)])[None, :, None] for c in (0, 1)]
    for _ in range(n - 2):
        prev = tables[-1]
        opt0, opt1 = prev[:, to[0], :] + moves[0], prev[:, to[1], :] + moves[1]
        tables.append(np.where(is_max, np.maximum(opt0, opt1), np.minimum(opt0, opt1)))
    return tables


def _reach_mask(table: np.ndarray, x: np.ndarray, regions: tuple) -> np.ndarray:
    """(4, labels, W) cells at x that some continuation brings into one of ``regions`` (0: U >=
    high, 1: low <= U < high, 2: U < low)."""
    up_hi, lo_lo, up_lo, lo_hi = (table[j][:, :, None] + x[None, None, :] for j in range(4))
    keep = np.zeros(up_hi.shape, dtype=bool)
    if 0 in regions:
        keep |= up_hi >= 0
    if 1 in regions:
        keep |= (up_lo >= 0) & (lo_hi < 0)
    if 2 in regions:
        keep |= lo_lo < 0
    return keep


def lattice_exact_logs(pi: np.ndarray, lat: _Lattice, low: float, high: float, regions=(0, 1, 2),
                       work_max: int | None = None):
    """ln P of each region in ``regions`` (0: U_G >= high, 1: low <= U_G < high, 2: U_G < low)
    for independent taxels present with probabilities ``pi`` (n = pi.size >= 2, the taxels in
    their order; U_G of eq 7 in the lattice form ``lat``, :mod:`.chain_dp`): {region: ln P},
    -inf for probability 0; None beyond ``work_max`` cells x steps (default EXACT_WORK_MAX,
    read at the call; module doc). The comparisons with the
    band edges are exact (integer thresholds on x per label pair, chain_dp._first_at_least)."""
    work_max = EXACT_WORK_MAX if work_max is None else work_max
    p, q = lat.p, lat.q
    pi = np.asarray(pi, dtype=float)
    if lat.reverse:
        pi = pi[::-1]
    n = pi.size
    labels = len(lat.start_labels)
    pairs = [(ls, le) for ls in range(labels) for le in range(len(lat.end_labels))]
    # integer thresholds on the final x per label pair, clamped to just beyond x's reach (an
    # edge of 1e300 is a Python int beyond int64; the comparisons are the same)
    xa, xb = _x_range(lat, n)
    edges = {key: (_first_at_least(lat, _label_base(lat, *key), low, p, q, (xa, xb)),
                   _first_at_least(lat, _label_base(lat, *key), high, p, q, (xa, xb))) for key in pairs}
    tables = _future_tables(lat, n, edges)
    shift = lat.shift
    smin, smax = int(shift.min()), int(shift.max())
    spread = smax - smin
    # one buffer column per x over every step's reach, `pad` zero columns beyond on both sides
    # (a step reads its sources up to `spread` columns outside their window)
    starts = [lat.start[a][b][0] for a in (0, 1) for b in (0, 1)]
    pad = spread + 1
    x_base = min(starts) + min(0, (n - 2) * smin) - pad
    size = max(starts) + max(0, (n - 2) * smax) + pad + 1 - x_base
    bufs = [_zeros((4, labels, size)), _zeros((4, labels, size))]
    M, E = bufs[0]
    probs = [(_factor(1.0 - float(x)), _factor(float(x))) for x in pi]  # (absent, present) per taxel
    for a in (0, 1):
        for b in (0, 1):
            steps, label = lat.start[a][b]
            fa, fb = probs[0][a], probs[1][b]
            m, e = math.frexp(fa[0] * fb[0])
            if m > 0.0:
                M[2 * a + b, label, steps - x_base] = m
                E[2 * a + b, label, steps - x_base] = e + fa[1] + fb[1]
    lo, hi = min(starts) - x_base, max(starts) + 1 - x_base  # the window (buffer columns)

    def prune(M, E, lo, hi, k):
        """Zero the cells of the window no continuation brings into a region asked for; the
        window shrunk to the columns left (None: nothing left). Every PRUNE_EVERY steps."""
        x = x_base + np.arange(lo, hi, dtype=np.int64)
        keep = _reach_mask(tables[k], x, regions) & (M[:, :, lo:hi] > 0.0)
        M[:, :, lo:hi][~keep] = 0.0
        E[:, :, lo:hi][~keep] = _ZERO
        cols = np.flatnonzero(keep.any(axis=(0, 1)))
        return None if cols.size == 0 else (lo + int(cols[0]), lo + int(cols[-1]) + 1)

    work = 0
    window = prune(M, E, lo, hi, n - 2)
    for i in range(2, n):
        if window is None:
            break
        lo, hi = window
        nlo, nhi = lo + smin, hi + smax
        work += 4 * labels * (nhi - nlo)
        if work > work_max:
            return None
        (M, E), (Mn, En) = bufs[i % 2], bufs[1 - i % 2]
        tmp = np.empty((labels, nhi - nlo), dtype=np.int64)
        for b in (0, 1):
            for c in (0, 1):
                # row (b, c) = P_i(c) (row (0, b) moved by shift[0, b, c] + row (1, b) moved by shift[1, b, c])
                md, ed = Mn[2 * b + c, :, nlo:nhi], En[2 * b + c, :, nlo:nhi]
                s0, s1 = int(shift[0, b, c]), int(shift[1, b, c])
                _add_into(md, ed, M[b, :, nlo - s0:nhi - s0], E[b, :, nlo - s0:nhi - s0],
                          M[2 + b, :, nlo - s1:nhi - s1], E[2 + b, :, nlo - s1:nhi - s1], tmp)
                _times(md, ed, probs[i][c])
        M[:, :, lo:hi] = 0.0  # the old window: the buffer is zero outside its window again
        E[:, :, lo:hi] = _ZERO
        window = (nlo, nhi)
        if (i - 1) % PRUNE_EVERY == 0 or i == n - 1:
            _normalise(Mn[:, :, nlo:nhi], En[:, :, nlo:nhi])
            window = prune(Mn, En, nlo, nhi, n - 1 - i)
    out = {r: -math.inf for r in regions}
    if window is None:
        return out
    M, E = bufs[n % 2] if n > 2 else bufs[0]
    lo, hi = window
    x = x_base + np.arange(lo, hi, dtype=np.int64)
    parts: dict = {r: ([], []) for r in regions}
    for a in (0, 1):
        for b in (0, 1):
            steps, le = lat.end[a][b]
            for ls in range(labels):
                t_low, t_high = edges[(ls, le)]
                xf = x + steps
                upper = xf >= t_high
                lower = xf < t_low  # as the fast DPs split the regions
                masks = {0: upper, 1: ~upper & ~lower, 2: lower}
                for r in regions:
                    sel = masks[r]
                    parts[r][0].append(M[2 * a + b, ls, lo:hi][sel])
                    parts[r][1].append(E[2 * a + b, ls, lo:hi][sel])
    for r in regions:
        out[r] = _log_sum(np.concatenate(parts[r][0]), np.concatenate(parts[r][1]))
    return out


# ------------------------------------------------------------------ {0,1}, any weights: three counts
def counts_exact_logs(pi: np.ndarray, p: float, q: float, low: float, high: float, regions=(0, 1, 2),
                      work_max: int | None = None):
    """As :func:`lattice_exact_logs` for the {0,1} tuple with any weights: the counts DP of
    :func:`.counts_dp._rates_counts` (state: last taxel absent / run of one / run of two or more;
    U_G = a + b (2^p + 2^q) + d 2^(p+q) over a 3-d box of counts per state, eq 7 on {0,1}) in
    extended-exponent arithmetic. Pruned by reachability: on {0,1} U_G only grows with the
    present set (every term of eq 7 is >= 0 and grows with its neighbours), so from a cell of
    partial value V the final value lies between V (+1 for a pending run of one: all the rest
    absent) and V plus the gain of all the rest present; a cell is dropped only where that
    interval misses every region asked for by more than a rounding margin. The comparisons of
    the final values with the edges are exact (counts_dp._classify, mpmath within rounding)."""
    from .counts_dp import _classify

    work_max = EXACT_WORK_MAX if work_max is None else work_max
    pi = np.asarray(pi, dtype=float)
    n = pi.size
    big_p, big_q, big_pq = 2.0**p, 2.0**q, 2.0 ** (p + q)
    s_val = big_p + big_q
    g = 1.0 if n == 1 else s_val + (n - 2) * big_pq
    margin = 1e-9 * (1.0 + g + abs(low if math.isfinite(low) else 0.0) + abs(high if math.isfinite(high) else 0.0))

    def gain(state: int, k: int) -> float:
        """U_G added by k more present taxels from ``state`` (0 absent, 1 run of one, 2 longer run),
        the run then ending at the last taxel."""
        if state == 0:
            return 0.0 if k == 0 else (1.0 if k == 1 else s_val + (k - 2) * big_pq)
        if state == 1:
            return 1.0 if k == 0 else s_val + (k - 1) * big_pq
        return k * big_pq

    probs = [(_factor(1.0 - float(x)), _factor(float(x))) for x in pi]
    # state boxes over (a, b, d) from `origin`, all of one shape
    states = [_zeros((1, 1, 1)) for _ in range(3)]
    states[0][0][0, 0, 0], states[0][1][0, 0, 0] = 0.5, 1  # probability 1
    origin = [0, 0, 0]
    work = 0
    for i in range(n):
        (m0, e0), (m1, e1), (m2, e2) = states
        na, nb, nd = m0.shape
        shape = (na + 1, nb + 1, nd + 1)
        work += 3 * (na + 1) * (nb + 1) * (nd + 1)
        if work > work_max:
            return None
        absent, present = probs[i]
        n0, n1, n2 = _zeros(shape), _zeros(shape), _zeros(shape)
        box = (slice(0, na), slice(0, nb), slice(0, nd))
        n0[0][box], n0[1][box] = m0, e0                          # stays absent
        _acc(*n0, box, m2, e2)                                   # a longer run ends
        _acc(*n0, (slice(1, na + 1), slice(0, nb), slice(0, nd)), m1, e1)  # a run of one ends: a + 1
        _times(*n0, absent)
        n1[0][box], n1[1][box] = m0, e0                          # a run starts
        _times(*n1, present)
        n2[0][:na, 1:, :nd], n2[1][:na, 1:, :nd] = m1, e1        # a run reaches two: b + 1
        _acc(*n2, (slice(0, na), slice(0, nb), slice(1, nd + 1)), m2, e2)  # a longer run grows: d + 1
        _times(*n2, present)
        states = [n0, n1, n2]
        if i % PRUNE_EVERY != PRUNE_EVERY - 1 and i != n - 1:
            continue
        for m, e in states:
            _normalise(m, e)
        # reachability: partial value V = a + b s + d 2^(p+q) of the closed terms
        a = origin[0] + np.arange(shape[0])[:, None, None]
        b = origin[1] + np.arange(shape[1])[None, :, None]
        d = origin[2] + np.arange(shape[2])[None, None, :]
        v = (a + b * s_val) + d * big_pq
        keep_any = np.zeros(shape, dtype=bool)
        rest = n - 1 - i
        for st, (m, e) in enumerate(states):
            lowest = v + (1.0 if st == 1 else 0.0)
            highest = v + gain(st, rest)
            keep = np.zeros(shape, dtype=bool)
            if 0 in regions:
                keep |= highest >= high - margin
            if 1 in regions:
                keep |= (highest >= low - margin) & (lowest < high + margin)
            if 2 in regions:
                keep |= lowest < low + margin
            keep &= m > 0.0
            m[~keep] = 0.0
            e[~keep] = _ZERO
            keep_any |= keep
        if not keep_any.any():
            return {r: -math.inf for r in regions}
        cuts = []
        for axis in range(3):
            idx = np.flatnonzero(keep_any.any(axis=tuple(j for j in range(3) if j != axis)))
            cuts.append((int(idx[0]), int(idx[-1]) + 1))
        sl = tuple(slice(lo_, hi_) for lo_, hi_ in cuts)
        states = [(m[sl].copy(), e[sl].copy()) for m, e in states]
        origin = [o + lo_ for o, (lo_, _) in zip(origin, cuts)]
    # the last taxel ends its run: state 1 -> a + 1
    (m0, e0), (m1, e1), (m2, e2) = states
    na, nb, nd = m0.shape
    lm, le_ = _zeros((na + 1, nb, nd))
    box = (slice(0, na), slice(0, nb), slice(0, nd))
    _acc(lm, le_, box, m0, e0)
    _acc(lm, le_, box, m2, e2)
    _acc(lm, le_, (slice(1, na + 1), slice(0, nb), slice(0, nd)), m1, e1)
    live = lm > 0.0
    a = origin[0] + np.arange(na + 1)[:, None, None]
    b = origin[1] + np.arange(nb)[None, :, None]
    d = origin[2] + np.arange(nd)[None, None, :]
    av, bv, dv = (np.broadcast_to(x, lm.shape)[live] for x in (a, b, d))
    mv, ev = lm[live], le_[live]
    values = (av + bv * s_val) + dv * big_pq
    above, below = _classify(values, lambda j: (int(av[j]), int(bv[j]), int(bv[j]), int(dv[j])), p, q, low, high)
    masks = {0: above, 1: ~above & ~below, 2: below}
    return {r: _log_sum(mv[masks[r]], ev[masks[r]]) for r in regions}
