"""Independent references for the exact system rates (tests/test_exact_rates.py,
tests/test_exact_roc.py): every decision vector enumerated with U_G summed in mpmath (eq 10),
the preferential-rule chain DP in mpmath, a log-domain DP in numpy without scaling or trimming,
the coefficient law of {0,1} chains and the Chair-Varshney LLR by enumeration. None of them calls
the code under test; their precision is the caller's (the tests take it with ``mp.workdps``)."""

from __future__ import annotations

import bisect
import functools
import itertools
import math

import mpmath as mp
import numpy as np
from mpmath.libmp import fzero, mpf_add, mpf_ge, mpf_lt, mpf_mul

def all_vectors(pd, pf, p, q, encoding):
    """Every decision vector's U_G (eq 10, summed term by term in mpmath) and its probability
    under H1 (``pd``) and H0 (``pf``): ``[(U_G, P(u | H1), P(u | H0)), ...]``, 2^n of them.

    The vectors come in itertools.product order; the sum of the first k terms and the product of
    the first k factors are kept from the previous vector as long as the bits they depend on are
    unchanged (term i depends on u_(i-1), u_i, u_(i+1)), and each term u_i fp fq is formed once
    per neighbourhood: the same mp operations in the same order as summing and multiplying every
    vector from scratch, so the same numbers, without the O(n) work per vector."""
    n = len(pd)
    absent = -1 if encoding == "pm1" else 0
    P, Q = mp.mpf(2) ** mp.mpf(p), mp.mpf(2) ** mp.mpf(q)
    one, zero = mp.mpf(1), mp.mpf(0)
    # (1 + neighbour)^p / ^q by 1 + neighbour (neighbour -1/0/1; 0 also the boundary)
    fac_p = {2: P, 1: one, 0: one if p == 0 else zero}
    fac_q = {2: Q, 1: one, 0: one if q == 0 else zero}
    term = {(prv, mid, nxt): mid * fac_p[1 + nxt] * fac_q[1 + prv]
            for prv in (-1, 0, 1) for mid in (absent, 1) for nxt in (-1, 0, 1)}
    factors = [[(1 - mp.mpf(pi), mp.mpf(pi)) for pi in probs] for probs in (pd, pf)]
    padded = [0] * (n + 2)
    sums = [zero] * (n + 1)  # sums[k]: the first k terms
    prods = [[one] * (n + 1) for _ in factors]  # prods[h][k]: the first k factors
    vectors = []
    last = None
    for bits in itertools.product((0, 1), repeat=n):
        first = 0 if last is None else next(i for i in range(n) if bits[i] != last[i])
        last = bits
        for i in range(first, n):
            padded[i + 1] = 1 if bits[i] else absent
        for k in range(max(first - 1, 0), n):  # term k (taxel k + 1) reads bits k - 1 .. k + 1
            sums[k + 1] = sums[k] + term[padded[k], padded[k + 1], padded[k + 2]]
        for h, fs in enumerate(factors):
            pr = prods[h]
            for k in range(first, n):
                pr[k + 1] = pr[k] * fs[k][bits[k]]
        vectors.append((sums[n], prods[0][n], prods[1][n]))
    return vectors

def brute_preferential(pd, pf, p, q, encoding, low, high, vectors=None):
    """P(H1 decided), P(undecided), P(H0 decided) under H1 and H0 by summing over every vector
    (``vectors``: :func:`all_vectors` of the same arguments, to classify them for more bands)."""
    out = {"h1": [mp.mpf(0)] * 3, "h0": [mp.mpf(0)] * 3}  # [H1 decided, undecided, H0 decided]
    lo, hi = mp.mpf(low), mp.mpf(high)  # (exact conversions of the float edges, once)
    for val, w1, w0 in vectors if vectors is not None else all_vectors(pd, pf, p, q, encoding):
        k = 0 if val >= hi else (2 if val < lo else 1)
        out["h1"][k] += w1
        out["h0"][k] += w0
    return out

def mp_chain_dp(pi, p, q, encoding, low, high):
    """An independent DP in mpmath (40 digits): state (u_(i-1), u_i) -> {U_G so far (mp number):
    probability}.

    The inner loop runs mpmath's own mpf_add / mpf_mul on the numbers' raw (sign, man, exp, bc)
    tuples, at the precision and rounding an mpf operation would use: what ``v + t``, ``pr * w``
    compute, without building an mpf object per step (a raw tuple is the mpf's canonical form,
    so equal values are equal keys). The eight terms and the factors pi_i, 1 - pi_i are formed
    once. The same mp numbers as the plain mpf loop, ~3x faster."""
    n = len(pi)
    absent = -1 if encoding == "pm1" else 0
    with mp.workdps(40):
        prec, rnd = mp.mp._prec_rounding
        P, Q = mp.mpf(2) ** p, mp.mpf(2) ** q
        one, zero = mp.mpf(1), mp.mpf(0)
        fac = lambda v, w, big: big if v == 1 else (one if (v == 0 or absent == 0 or w == 0) else zero)
        # v: neighbour value (0 = boundary)
        term = {(prev, mid, nxt): (mid * fac(nxt, p, P) * fac(prev, q, Q))._mpf_
                for prev in (absent, 0, 1) for mid in (absent, 1) for nxt in (absent, 0, 1)}
        probs = [{1: x._mpf_, absent: (1 - x)._mpf_} for x in map(mp.mpf, pi)]
        states = {}
        for a in (absent, 1):
            for b in (absent, 1):
                states[(a, b)] = {term[0, a, b]: mpf_mul(probs[0][a], probs[1][b], prec, rnd)}
        for i in range(2, n):
            new = {}
            for (a, b), dist in states.items():
                for c in (absent, 1):
                    w = probs[i][c]
                    t = term[a, b, c]
                    tgt = new.setdefault((b, c), {})
                    get = tgt.get
                    for v, pr in dist.items():
                        vt = mpf_add(v, t, prec, rnd)
                        tgt[vt] = mpf_add(get(vt, fzero), mpf_mul(pr, w, prec, rnd), prec, rnd)
            states = new
        res = [fzero] * 3
        lo, hi = mp.mpf(low)._mpf_, mp.mpf(high)._mpf_  # (exact conversions of the float edges)
        for (a, b), dist in states.items():
            t = term[a, b, 0]
            for v, pr in dist.items():
                val = mpf_add(v, t, prec, rnd)
                k = 0 if mpf_ge(val, hi) else (2 if mpf_lt(val, lo) else 1)
                res[k] = mpf_add(res[k], pr, prec, rnd)
        return [mp.mp.make_mpf(x) for x in res]

def brute_llr(pd, pf, prior):
    n = len(pd)
    t = -math.log(prior / (1 - prior))
    d = f = 0.0
    for bits in itertools.product((0, 1), repeat=n):
        s = sum(math.log(a / b) if x else math.log((1 - a) / (1 - b)) for x, a, b in zip(bits, pd, pf))
        w1 = math.prod(a if x else 1 - a for x, a in zip(bits, pd))
        w0 = math.prod(b if x else 1 - b for x, b in zip(bits, pf))
        if s - t > 1e-9 * max(1, abs(s)):
            d += w1
            f += w0
    return d, f

def log_chain_states(pi):
    """An independent DP for {-1,+1}, p, q > 0 in the log domain (np.logaddexp), without scaling
    or trimming: ``(L, mid)``, L[u_(n-1), u_n, e_1 + 1, m + mid] = ln P of that end state and
    m = -n..n, where U_G = 2^(p+q) m + 2^p e_1 + 2^q e_n (e_n = u_n-term of the last run end).

    It does not depend on p, q: computed once per ``pi`` (a test that checks two weight pairs on
    the same probabilities reuses it); the arrays are read-only."""
    pi = np.asarray(pi, dtype=float)
    return _log_chain_states(pi.tobytes())

@functools.lru_cache(maxsize=4)
def _log_chain_states(pi_bytes):
    pi = np.frombuffer(pi_bytes, dtype=float)
    n = len(pi)
    size = 2 * n + 3
    mid = n + 1
    ninf = -np.inf
    L = np.full((2, 2, 3, size), ninf)
    lp, lq = np.log(pi), np.log1p(-np.asarray(pi))
    for a in (0, 1):
        for b in (0, 1):
            e1 = (1 if a else -1) if b else 0
            L[a, b, e1 + 1, mid] = (lp[0] if a else lq[0]) + (lp[1] if b else lq[1])
    for i in range(2, n):
        new = np.full_like(L, ninf)
        for a in (0, 1):
            for b in (0, 1):
                for c in (0, 1):
                    s = (1 if b else -1) if (a and c) else 0
                    moved = np.full(size, ninf)[None, :].repeat(3, 0)
                    if s == 0:
                        moved = L[a, b]
                    elif s == 1:
                        moved[:, 1:] = L[a, b, :, :-1]
                    else:
                        moved[:, :-1] = L[a, b, :, 1:]
                    new[b, c] = np.logaddexp(new[b, c], moved + (lp[i] if c else lq[i]))
        L = new
    L.flags.writeable = False
    return L, mid

def log_chain_reference(pi, p, q, low, high):
    """:func:`log_chain_states` classified: U_G compared with the edges in mpmath. Returns
    ln P(H1), ln P(undecided), ln P(H0)."""
    L, mid = log_chain_states(pi)
    out = [[], [], []]
    P, Q = mp.mpf(2) ** mp.mpf(p), mp.mpf(2) ** mp.mpf(q)
    # (P Q, P e_1, Q e_n and the edges formed once, not per value: U_G = (P Q (j - mid) + P e_1)
    # + Q e_n is the same mp number; the edges' conversions are exact. Along a row U_G(j) is
    # non-decreasing in j -- P Q > 0 and each rounding to nearest is monotone -- so the j with
    # U_G >= high form a suffix and those with U_G < low a prefix of the row's finite entries:
    # both boundaries found by bisection, U_G evaluated at O(log n) of them instead of all, and
    # each value lands in the region (and each list in the order) the value-by-value test gave.)
    PQ, lo, hi = P * Q, mp.mpf(low), mp.mpf(high)
    for a in (0, 1):
        for b in (0, 1):
            en = (1 if b else -1) if a else 0
            Qen = Q * en
            for e1 in (-1, 0, 1):
                row, Pe1 = L[a, b, e1 + 1], P * e1
                js = np.flatnonzero(np.isfinite(row))
                u = lambda j: PQ * (j - mid) + Pe1 + Qen  # noqa: E731 (Pe1, Qen of this row)
                first_high = bisect.bisect_left(js, True, key=lambda j: u(j) >= hi)
                first_mid = min(bisect.bisect_left(js, True, key=lambda j: not u(j) < lo), first_high)
                out[2].extend(row[js[:first_mid]])
                out[1].extend(row[js[first_mid:first_high]])
                out[0].extend(row[js[first_high:]])
    from scipy.special import logsumexp
    return [float(logsumexp(v)) if v else None for v in out]

def assert_logs_match_reference(ours, pd, pf, p, q, low, high) -> dict:
    """Every rate's natural log in ``ours`` (both hypotheses) against :func:`log_chain_reference`
    to 1e-11 (relative, on the log); returns {rate name: reference ln P}."""
    refs = {}
    for probs, names in ((pd, ("p_detect", "p_undecided_h1", "p_miss")),
                         (pf, ("p_false_alarm", "p_undecided_h0", "p_reject"))):
        for name, r in zip(names, log_chain_reference(probs, p, q, low, high)):
            got = getattr(ours, "log_" + name)
            assert got is not None and abs(got - r) <= 1e-11 * max(1.0, abs(r)), (p, q, name, got, r)
            refs[name] = r
    return refs

def coeff_chain_law(pi):
    """{0,1} reference: a DP over (u_(i-1), u_i) -> {integer coefficients (a, b, c, d) of U_G =
    a + b 2^p + c 2^q + d 2^(p+q) so far: probability} (eq 7 term by term: a present taxel
    contributes 2^p if its successor is present, times 2^q if its predecessor is). Returns the
    final {coefficients: probability}. It does not depend on p, q: computed once per ``pi``."""
    return _coeff_chain_law(tuple(float(x) for x in pi))

_SHIFT = 16  # bits per coefficient in a packed key (each coefficient counts taxels: < 2^16)

@functools.lru_cache(maxsize=4)
def _coeff_chain_law(pi):
    # (the coefficients kept packed in one int, a + b 2^16 + c 2^32 + d 2^48: a key's addition is
    # one int addition, no carry as each coefficient stays below 2^16; the probabilities in
    # Python floats, not numpy scalars: the same IEEE double operations in the same order, so the
    # same law, ~5x faster)
    n = len(pi)
    assert n < 1 << _SHIFT

    def term(prev, mid, nxt):
        if not mid:
            return 0
        return 1 << _SHIFT * ((nxt == 1) + 2 * (prev == 1))

    states = {(a, b): {term(0, a, b): (pi[0] if a else 1 - pi[0]) * (pi[1] if b else 1 - pi[1])}
              for a in (0, 1) for b in (0, 1)}
    for i in range(2, n):
        new = {}
        for (a, b), dist in states.items():
            for c in (0, 1):
                w = pi[i] if c else 1 - pi[i]
                tgt = new.setdefault((b, c), {})
                get = tgt.get
                t = term(a, b, c)
                for k, v in dist.items():
                    key = k + t
                    tgt[key] = get(key, 0.0) + v * w
        states = new
    final = {}
    for (a, b), dist in states.items():
        for k, v in dist.items():
            key = k + term(a, b, 0)
            final[key] = final.get(key, 0.0) + v
    mask = (1 << _SHIFT) - 1
    return {(k & mask, k >> _SHIFT & mask, k >> 2 * _SHIFT & mask, k >> 3 * _SHIFT): v for k, v in final.items()}

def classify_law(final, p, q, low, high):
    """[P(U >= high), P(low <= U < high), P(U < low)]; values within 1e-9 of an edge in mpmath."""
    res = [0.0, 0.0, 0.0]
    P, Q = mp.mpf(2) ** mp.mpf(p), mp.mpf(2) ** mp.mpf(q)
    fp, fq, fpq = 2.0**p, 2.0**q, 2.0 ** (p + q)  # (the same doubles as forming them per value)
    for (a, b, c, d), v in final.items():
        val = a + b * fp + c * fq + d * fpq
        if min(abs(val - low), abs(val - high)) <= 1e-9 * max(1.0, abs(val)):
            val = a + b * P + c * Q + d * P * Q
        res[0 if val >= high else (2 if val < low else 1)] += v
    return res

def brute_numpy(pi, p, q, encoding, low, high):
    """All 2^n vectors in numpy (n <= 16): eq 7 term by term, each vector's probability as a
    product; values within 1e-9 of an edge re-evaluated in mpmath. [P(>= high), P(mid), P(< low)]."""
    bits, above, below = _vector_regions(len(pi), p, q, encoding, low, high, mp.mp.prec)
    prob = np.prod(np.where(bits, pi, 1.0 - np.asarray(pi)), axis=1)
    return [math.fsum(prob[above]), math.fsum(prob[~above & ~below]), math.fsum(prob[below])]

@functools.lru_cache(maxsize=2)
def _vector_values(n, p, q, encoding, prec):
    """(bits, U_G in doubles, {vector index: U_G in mpmath}) of all 2^n vectors: the same for
    every band and both hypotheses, so formed once (read-only arrays); the mpmath values are
    filled in where a band needs them (near an edge) and kept for the next band (``prec``: the
    working precision they are formed at, part of the key)."""
    bits = ((np.arange(2**n)[:, None] >> np.arange(n)) & 1).astype(bool)
    absent = -1.0 if encoding == "pm1" else 0.0
    u = np.where(bits, 1.0, absent)
    padded = np.pad(u, ((0, 0), (1, 1)))
    fac = lambda v, w: np.where(v == 1.0, 2.0**w, np.where((v == 0.0) | (absent == 0.0) | (w == 0.0), 1.0, 0.0))
    terms_p = fac(padded[:, 2:], p)  # (1 + u_(i+1))^p
    terms_q = fac(padded[:, :-2], q)
    ug = (u * terms_p * terms_q).sum(axis=1)
    for arr in (bits, ug):
        arr.flags.writeable = False
    return bits, ug, {}

@functools.lru_cache(maxsize=8)
def _vector_regions(n, p, q, encoding, low, high, prec):
    """(bits, U_G >= high, U_G < low) of all 2^n vectors: the same for H1's and H0's
    probabilities, so classified once per band (read-only arrays)."""
    bits, ug, exact = _vector_values(n, p, q, encoding, prec)
    absent = -1.0 if encoding == "pm1" else 0.0
    near = np.flatnonzero(np.minimum(np.abs(ug - low), np.abs(ug - high)) <= 1e-9 * np.maximum(1.0, np.abs(ug)))
    above, below = ug >= high, ug < low
    P, Q = mp.mpf(2) ** mp.mpf(p), mp.mpf(2) ** mp.mpf(q)
    lo, hi = mp.mpf(low), mp.mpf(high)  # (exact conversions of the float edges, once)
    fac_p = {1: P, 0: 1, -1: 1 if (absent == 0 or p == 0) else 0}  # (1 + u)^p by u (0: the boundary)
    fac_q = {1: Q, 0: 1, -1: 1 if (absent == 0 or q == 0) else 0}
    # u_i (1 + u_(i+1))^p (1 + u_(i-1))^q by (u_(i-1), u_i, u_(i+1)): formed once, the same numbers
    terms = {(prv, mid, nxt): mid * fac_p[nxt] * fac_q[prv] for prv in (-1, 0, 1) for mid in (-1, 0, 1)
             for nxt in (-1, 0, 1)}
    for j in near:
        val = exact.get(j)
        if val is None:
            val = mp.mpf(0)
            row = [0] + [1 if b else int(absent) for b in bits[j]] + [0]
            for i in range(1, n + 1):
                val += terms[row[i - 1], row[i], row[i + 1]]
            exact[j] = val
        above[j], below[j] = val >= hi, val < lo
    for arr in (above, below):
        arr.flags.writeable = False
    return bits, above, below
