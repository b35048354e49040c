"""Exact system error rates of the preferential rule (eq 7 with the band of eq 20) and of the
Chair-Varshney / Neyman-Pearson baselines (eqs 31-32) on taxels that come in kinds.

Preferential rule (eq 7). With independent taxels (P(u_i present) = pd_i under H1, pf_i under
H0) U_G depends on each taxel and its two neighbours only, so its law follows from a dynamic
programme along the chain; the state is the last two decisions and the accumulated U_G:

* {-1,+1}, p > 0, q > 0 (``method="chain"``): an absent neighbour's factor is 0^p = 0, so an
  inner taxel contributes u_i 2^(p+q) when both neighbours are present and 0 otherwise:
  U_G = 2^(p+q) m + 2^p e_1 + 2^q e_n, m in -n..n an integer, e_1 = u_1 [u_2 present],
  e_n = u_n [u_(n-1) present] in {-1, 0, 1}. The DP carries the law of m for each e_1 and
  state: O(n^2) operations, a few numpy vector operations per taxel.
* integer p, q (either tuple, ``method="integer"``): every term is an integer, U_G is an
  integer in [-g, g]; the DP carries its law in an array.
* otherwise (a zero weight on {-1,+1}, or non-integer p, q on {0,1}; ``method="exact-sparse"``):
  U_G = a + b 2^p + c 2^q + d 2^(p+q) with integers a, b, c, d; the DP carries a dictionary over
  (a, b, c, d), exact, practical up to ~60 taxels; beyond ``SPARSE_MAX_TAXELS`` the rates are
  estimated by Monte Carlo with a 95 % Wilson interval (``method="monte-carlo"``, says so).

Decision (eq 20 band): H1 iff U_G >= high, H0 iff U_G < low, undecided between. Each
comparison is exact: values within rounding of an edge are compared in mpmath. The three
probabilities under each hypothesis are sums of positive terms (no complements), so tails down
to ~1e-300 keep their relative accuracy; ``log_`` forms are natural logarithms.

Kinds (Chair-Varshney eq 31, N-P eq 32): when the taxels come in a few kinds with equal
(pd, pf) per kind, ln Lambda depends only on the present count per kind, whose law is a product
of binomials: the atoms are enumerated exactly (up to ``KIND_ATOMS_MAX`` count tuples).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from taxel_net.errors import ParameterError

__all__ = [
    "PreferentialRates",
    "preferential_error_rates",
    "SPARSE_MAX_TAXELS",
    "KindRates",
    "kinds_of",
    "llr_error_rates",
    "np_kinds_fusion",
    "KIND_ATOMS_MAX",
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
    p_undecided_h0, p_reject = P(H0 decided). log_*: natural logarithms, exact below the
    double range too (None for an impossible event); the plain values are exp of them (0.0
    below ~1e-308). method: "chain", "integer", "exact-sparse" (exact) or "monte-carlo"
    (estimate, with ``ci95`` per rate and ``samples``)."""

    log_p_detect: float | None
    log_p_undecided_h1: float | None
    log_p_miss: float | None
    log_p_false_alarm: float | None
    log_p_undecided_h0: float | None
    log_p_reject: float | None
    method: str
    samples: int | None = None
    ci95: dict | None = None

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


# ------------------------------------------------------------------ {-1,+1}, p, q > 0
# Every DP starts from total mass 2^SCALE_BITS instead of 1 (an exact power of two), so tails
# down to ~1e-570 stay normal doubles; sums are unscaled in the log domain. Columns whose every
# entry is below TRIM (scaled: ~1e-571 of probability) are dropped from the live window; the
# mass so dropped over the whole run is < 8 n^2 TRIM, far below 1e-300.
SCALE_BITS = 900
_LOG_SCALE = SCALE_BITS * math.log(2.0)
TRIM = 1e-300


def _chain_pm1(pi: np.ndarray) -> dict:
    """Scaled law of (e_1, e_n, m) for {-1,+1}, p, q > 0 (module doc): {(e1, en): array over
    m + n}, total mass 2^SCALE_BITS. One array X[a, b, e_1 + 1, m + mid] for the state
    (u_(i-1), u_i) = (a, b); a step is six vector operations on the live window."""
    n = pi.size
    size = 2 * n + 3
    mid = n + 1
    X = np.zeros((2, 2, 3, size))
    Y = np.zeros((2, 2, 3, size))
    p1, p2 = pi[0], pi[1]
    for a in (0, 1):
        for b in (0, 1):
            e1 = (1 if a else -1) if b else 0
            X[a, b, e1 + 1, mid] = 2.0**SCALE_BITS * (p1 if a else 1.0 - p1) * (p2 if b else 1.0 - p2)
    lo, hi = mid, mid + 1  # live window [lo, hi): zero outside it in X and Y
    for i in range(2, n):
        pc, qc = pi[i], 1.0 - pi[i]
        lo, hi = max(1, lo - 1), min(size - 1, hi + 1)
        w = slice(lo, hi)
        # next decision absent: no term change; the middle taxel's term is 0 unless both
        # neighbours are present
        np.add(X[0, :, :, w], X[1, :, :, w], out=Y[:, 0, :, w])
        Y[:, 0, :, w] *= qc
        # next present: previous present and middle present -> m + 1; middle absent -> m - 1
        np.add(X[0, 1, :, w], X[1, 1, :, lo - 1:hi - 1], out=Y[1, 1, :, w])
        np.add(X[0, 0, :, w], X[1, 0, :, lo + 1:hi + 1], out=Y[0, 1, :, w])
        Y[:, 1, :, w] *= pc
        X, Y = Y, X
        if i % 16 == 0 and hi - lo > 32:  # drop negligible columns at both window ends
            head = X[:, :, :, lo:lo + 16].max(axis=(0, 1, 2))
            k = int(np.argmax(head >= TRIM)) if (head >= TRIM).any() else 16
            if k:
                X[:, :, :, lo:lo + k] = 0.0
                Y[:, :, :, lo:lo + k] = 0.0
                lo += k
            tail = X[:, :, :, hi - 16:hi].max(axis=(0, 1, 2))[::-1]
            k = int(np.argmax(tail >= TRIM)) if (tail >= TRIM).any() else 16
            if k:
                X[:, :, :, hi - k:hi] = 0.0
                Y[:, :, :, hi - k:hi] = 0.0
                hi -= k
    out = {}
    for a in (0, 1):
        for b in (0, 1):
            en = (1 if b else -1) if a else 0
            for e1 in (-1, 0, 1):
                row = X[a, b, e1 + 1, 1:size - 1]  # index m + n
                out[(e1, en)] = out.get((e1, en), 0.0) + row
    return out


def _log_sum(parts) -> float:
    """ln of the unscaled total of scaled nonnegative parts (-inf for none)."""
    total = float(np.sum(np.concatenate(parts))) if parts else 0.0
    return math.log(total) - _LOG_SCALE if total > 0.0 else -math.inf


def _rates_chain_pm1(pi: np.ndarray, p: float, q: float, low: float, high: float):
    n = pi.size
    m = np.arange(-n, n + 1)
    big_p, big_q, pq = 2.0**p, 2.0**q, 2.0 ** (p + q)
    parts_h1, parts_h0, parts_u = [], [], []
    for (e1, en), probs in _chain_pm1(pi).items():
        live = np.flatnonzero(probs)
        if not live.size:
            continue
        values = (big_p * e1 + big_q * en) + pq * m[live]
        sub = probs[live]
        above, below = _classify(values, lambda i, e1=e1, en=en: (0, e1, en, int(m[live[i]])), p, q, low, high)
        parts_h1.append(sub[above])
        parts_h0.append(sub[below])
        parts_u.append(sub[~above & ~below])
    return _log_sum(parts_h1), _log_sum(parts_u), _log_sum(parts_h0)


# ------------------------------------------------------------------ integer p, q
def _factor(state: int, weight: float, encoding: str) -> float:
    """(1 + u)^w of eq 7 for a neighbour: state 0 absent, 1 present, 2 boundary."""
    if state == 2:
        return 1.0
    if state == 1:
        return 2.0**weight
    return (0.0 if weight > 0 else 1.0) if encoding == "pm1" else 1.0


def _term(a: int, b: int, c: int, p: float, q: float, encoding: str) -> float:
    """Term of the middle taxel b (0 absent / 1 present) with previous a and next c (2 = boundary)."""
    u = 1.0 if b == 1 else (-1.0 if encoding == "pm1" else 0.0)
    return u * _factor(c, p, encoding) * _factor(a, q, encoding)


def _rates_integer(pi: np.ndarray, p: float, q: float, encoding: str, low: float, high: float):
    n = pi.size
    g = 1 if n == 1 else int(round(2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)))
    size = 2 * g + 1
    off = g
    if n == 1:
        probs = {}
        for b in (0, 1):
            v = int(_term(2, b, 2, p, q, encoding))
            probs[v] = probs.get(v, 0.0) + (pi[0] if b else 1.0 - pi[0])
        values = np.array(sorted(probs), dtype=float)
        pr = np.array([probs[int(v)] for v in values]) * 2.0**SCALE_BITS
        above, below = values >= high, values < low
        return _log_sum([pr[above]]), _log_sum([pr[~above & ~below]]), _log_sum([pr[below]])
    A = {}
    for a in (0, 1):
        for b in (0, 1):
            arr = np.zeros(size)
            t1 = int(_term(2, a, b, p, q, encoding))  # taxel 1: boundary before it
            arr[off + t1] = 2.0**SCALE_BITS * (pi[0] if a else 1.0 - pi[0]) * (pi[1] if b else 1.0 - pi[1])
            A[(a, b)] = arr
    for i in range(2, n):
        pc = pi[i]
        new = {(b, c): np.zeros(size) for b in (0, 1) for c in (0, 1)}
        for a in (0, 1):
            for b in (0, 1):
                src = A[(a, b)]
                for c in (0, 1):
                    t = int(_term(a, b, c, p, q, encoding))
                    w = pc if c else 1.0 - pc
                    if t >= 0:
                        new[(b, c)][t:] += src[:size - t] * w if t else src * w
                    else:
                        new[(b, c)][:t] += src[-t:] * w
        A = new
    total = np.zeros(size)
    for (a, b), arr in A.items():
        t = int(_term(a, b, 2, p, q, encoding))  # taxel n: boundary after it
        if t >= 0:
            total[t:] += arr[:size - t] if t else arr
        else:
            total[:t] += arr[-t:]
    values = np.arange(size, dtype=float) - off
    above, below = values >= high, values < low
    return _log_sum([total[above]]), _log_sum([total[~above & ~below]]), _log_sum([total[below]])


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
    return _log_sum([probs[above]]), _log_sum([probs[~above & ~below]]), _log_sum([probs[below]])


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
    integer = float(p).is_integer() and float(q).is_integer()
    if encoding == "pm1" and p > 0 and q > 0 and n >= 2:
        method = "chain"
        run = lambda pi: _rates_chain_pm1(pi, p, q, low, high)
    elif integer:
        method = "integer"
        run = lambda pi: _rates_integer(pi, p, q, encoding, low, high)
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
    logs = [*run(pd_arr), *run(pf_arr)]
    return PreferentialRates(*[(x if x > -math.inf else None) for x in logs], method=method)


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


def linear_statistic_tail(a, b, probs, threshold: float, gamma: float = 0.0, tol: float = 1e-9) -> float | None:
    """P(S > threshold) + gamma P(S = threshold) for S = sum_i (a_i if taxel i present else b_i),
    taxel i present with probability probs_i, independent (eq 31/32 statistics; ties within
    tol relative). Exact: taxels with equal (a_i, b_i, probs_i) form kinds and every tuple of
    per-kind counts is an atom (product of binomials); None when there are more than
    KIND_ATOMS_MAX tuples."""
    from scipy.special import gammaln, xlog1py, xlogy

    a = np.asarray(a, float)
    b = np.asarray(b, float)
    probs = np.asarray(probs, float)
    groups = {}
    for key in zip(a, b, probs):
        groups[key] = groups.get(key, 0) + 1
    sizes = np.array(list(groups.values()), dtype=np.int64)
    if float(np.prod(sizes + 1.0)) > KIND_ATOMS_MAX:
        return None
    stat = np.zeros(1)
    logp = np.zeros(1)
    for (ai, bi, pi), m in groups.items():
        k = np.arange(m + 1)
        s = k * ai + (m - k) * bi
        with np.errstate(divide="ignore"):  # pi = 0 or 1: xlogy keeps 0 log 0 = 0
            lp = (gammaln(m + 1) - gammaln(k + 1) - gammaln(m - k + 1)
                  + xlogy(k, pi) + xlog1py(m - k, -pi))
        stat = (stat[:, None] + s[None, :]).ravel()
        logp = (logp[:, None] + lp[None, :]).ravel()
    scale = np.maximum(1.0, np.abs(stat))
    above = stat - threshold > tol * scale
    tie = np.abs(stat - threshold) <= tol * scale
    return float(np.exp(logp[above]).sum() + gamma * np.exp(logp[tie]).sum())
