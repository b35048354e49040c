"""HEBTEM dynamic thresholds (sec. 2.2.3.4, eqs 16-20, Appendix I), solved without overflow.

The chapter's threshold equations are "area under the P(H1) curve from lambda to the right end
= (1 - alpha) (or (1 - beta)) times the rectangle" (Appendix I). Dividing by the width turns each
into "mean of P(H1) over [lambda, right end] = 1 - alpha" and every mean has a closed form in
the function

    D(z) = 1 - (1 - e^-z)/z = 1 - phi(z),   D(0+) = 0, D increasing and concave, D(inf) = 1,

evaluated by its Taylor series for small z (no cancellation) and by (z + expm1(-z))/z else.

* multiplicative, eq 16, curve eqs 10-11: with x = e^n s, L = ln(1/xi), L' = L/(1 - e^-2n) and
  w = 1 - t (t = lambda/e^n) the equation is D(L' w) = beta. Its non-trivial root is unique:
  z = D^-1(beta), w = z/L', t = 1 - w.
* additive {0,1}, eq 17 with eq 12: D(L v) = alpha, v = 1 - lambda/n in (0, 1].
* additive {-1,+1}, eq 17 with eq 13: with v = 1 - lambda/n in (0, 2], r, ln r, c of eq 13,
  Q(v) = (r/2) D(v ln r) + (c/2) v = alpha. Q(0) = 0 and Q is concave, so there are 0, 1 or
  2 roots (2 only when c < 0, i.e. xi > 1/4, where Q rises then falls inside (0, 2]).
* preferential, eq 18 with eq 14: with y = lambda/g the cubic of eq 18 divided by (g - lambda)
  is y^2 + y - 2 + 3 alpha/(1 - xi) = 0.

Roots of D(z) = b are found by Newton's method from a starting point on the safe side of a
concave/convex function (monotone, quadratic convergence, typically 2-5 steps), in plain
``math`` floats: a solve costs a few microseconds. The trivial root (lambda = right end point,
where both sides of the area equation vanish) is never returned.

Domains (documented in README and docs/chapter-notes.md):

* multiplicative: lambda in [-e^n, e^n] (t in [-1, 1]). The chapter draws the curve on
  [e^-n, e^n] but says the roots are "one positive and the other negative" and discusses
  "-lambda"; U_G itself is always > 0, so a root t <= e^-2n means "every U_G accepts" and
  present_counts reports 0 there. A root with t < -1 is "no root" (empty tuples).
* additive: lambda in [-n, n] ({-1,+1}) or [0, n] ({0,1}).
* preferential: lambda_mean in [-g, g].

Direction: a stricter (smaller) alpha or beta gives a larger lambda, i.e. a tougher test for
accepting H1 (the chapter, sec. 2.2.3.4) -- property-tested.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .curves import additive_pm1_constants, check_n, check_open_unit, check_xi
from .encoding import check_encoding, check_integer
from .rules import check_weight

__all__ = [
    "MultiplicativeThreshold",
    "AdditiveThreshold",
    "PreferentialThreshold",
    "multiplicative_threshold",
    "additive_threshold",
    "preferential_threshold",
    "max_preferential_value",
    "solve_mean_deficit",
    "DEFAULT_RTOL",
]

_EPS = 2.220446049250313e-16
DEFAULT_RTOL = 4 * _EPS
_MAX_ITER = 100

# Taylor series for z <= 1/2, written out (Horner, coefficients folded at compile time; a loop
# over a coefficient list cost ~0.6 us per call): D(z)/z = sum_{k=2}^{17} (-1)^k z^(k-2)/k!,
# D'(z) = sum_{k=2}^{17} (-1)^k (k-1) z^(k-2)/k!, D''(z) = sum_{k=3}^{18} (-1)^k (k-1)(k-2) z^(k-3)/k!.
# Alternating with decreasing terms, so the first omitted term bounds the error: at z = 1/2 it
# is < 1e-18 of the sum for each of the three (tested against mpmath).
_SERIES_LIMIT = 0.5


def _d_series(z):
    return z * (1 / 2 - z * (1 / 6 - z * (1 / 24 - z * (1 / 120 - z * (1 / 720 - z * (1 / 5040 - z * (
        1 / 40320 - z * (1 / 362880 - z * (1 / 3628800 - z * (1 / 39916800 - z * (1 / 479001600 - z * (
            1 / 6227020800 - z * (1 / 87178291200 - z * (1 / 1307674368000 - z * (1 / 20922789888000 - z * (
                1 / 355687428096000))))))))))))))))


def _dprime_series(z):
    return 1 / 2 - z * (2 / 6 - z * (3 / 24 - z * (4 / 120 - z * (5 / 720 - z * (6 / 5040 - z * (
        7 / 40320 - z * (8 / 362880 - z * (9 / 3628800 - z * (10 / 39916800 - z * (11 / 479001600 - z * (
            12 / 6227020800 - z * (13 / 87178291200 - z * (14 / 1307674368000 - z * (15 / 20922789888000 - z * (
                16 / 355687428096000)))))))))))))))


def _dsecond_series(z):
    return -(2 / 6 - z * (6 / 24 - z * (12 / 120 - z * (20 / 720 - z * (30 / 5040 - z * (42 / 40320 - z * (
        56 / 362880 - z * (72 / 3628800 - z * (90 / 39916800 - z * (110 / 479001600 - z * (
            132 / 6227020800 - z * (156 / 87178291200 - z * (182 / 1307674368000 - z * (
                210 / 20922789888000 - z * (240 / 355687428096000 - z * (272 / 6402373705728000))))))))))))))))


def _d(z: float) -> float:
    """D(z) = 1 - (1 - e^-z)/z for z >= 0, relative accuracy ~1 ulp."""
    if z <= _SERIES_LIMIT:
        return _d_series(z)
    return (z + math.expm1(-z)) / z


def _dprime(z: float) -> float:
    """D'(z) = (1 - (1 + z) e^-z)/z^2."""
    if z <= _SERIES_LIMIT:
        return _dprime_series(z)
    return -(math.expm1(-z) + z * math.exp(-z)) / (z * z)


def _dsecond(z: float) -> float:
    """D''(z) = e^-z/z + 2 e^-z/z^2 - 2 (1 - e^-z)/z^3 (< 0: D is concave)."""
    if z <= _SERIES_LIMIT:
        return _dsecond_series(z)
    e = math.exp(-z)
    return e / z + 2.0 * e / (z * z) + 2.0 * math.expm1(-z) / (z * z * z)


def _d_and_dprime(z: float) -> tuple[float, float]:
    """(D(z), D'(z)) in one call, the same values as _d and _dprime (one exp, one expm1)."""
    if z <= _SERIES_LIMIT:
        return _d_series(z), _dprime_series(z)
    em1 = math.expm1(-z)
    return (z + em1) / z, -(em1 + z * math.exp(-z)) / (z * z)


def _dprime_and_dsecond(z: float) -> tuple[float, float]:
    """(D'(z), D''(z)) in one call, the same values as _dprime and _dsecond."""
    if z <= _SERIES_LIMIT:
        return _dprime_series(z), _dsecond_series(z)
    em1 = math.expm1(-z)
    e = math.exp(-z)
    z2 = z * z
    return -(em1 + z * e) / z2, e / z + 2.0 * e / z2 + 2.0 * em1 / (z2 * z)


def solve_mean_deficit(b: float, rtol: float = DEFAULT_RTOL) -> tuple[float, int]:
    """The unique z > 0 with D(z) = b, b in (0, 1); returns (z, function evaluations).

    b <= 1/2: Newton on D(z) - b from z0 = 2b + 4b^2/3 (series inversion; D concave, so the
    iterates approach the root monotonically after one step). b > 1/2: with c = 1 - b (exact in
    floating point for b >= 1/2) Newton on the convex F(z) = c z - 1 + e^-z from z0 = 1/c,
    which lies right of the root, so the iterates decrease monotonically. Both ends stay
    accurate: b -> 0 (z ~ 2b) and b -> 1 (z ~ 1/(1 - b)).
    """
    evals = 0
    if b <= 0.5:
        z = 2.0 * b + (4.0 / 3.0) * b * b
        for _ in range(_MAX_ITER):
            d, dprime = _d_and_dprime(z)
            step = (d - b) / dprime
            evals += 1
            z -= step
            if abs(step) <= rtol * z:
                break
        return z, evals
    c = 1.0 - b
    z = 1.0 / c
    for _ in range(_MAX_ITER):
        e = math.exp(-z)
        step = (c * z - 1.0 + e) / (c - e)
        evals += 1
        z -= step
        if abs(step) <= rtol * z:
            break
    return z, evals


# ----------------------------------------------------------------------------- multiplicative


@dataclass(frozen=True)
class MultiplicativeThreshold:
    """Solution of eq 16 (multiplicative rule, {-1,+1} tuple, curve eqs 10-11).

    scaled_thresholds: t = lambda/e^n of every non-trivial root in [-1, 1] (ascending; eq 16 has
        at most one). ln_thresholds: ln lambda = n + ln t, None where t <= 0.
    present_counts: per root, the smallest number of present taxels j (0..n) whose
        U_G = e^(2j - n) >= lambda; 0 when lambda <= e^-n; None if no j qualifies.
    """

    n: int
    xi: float
    beta: float
    scaled_thresholds: tuple[float, ...]
    ln_thresholds: tuple[float | None, ...]
    present_counts: tuple[int | None, ...]


def multiplicative_threshold(n, xi, beta, *, rtol: float = DEFAULT_RTOL, info: dict | None = None) -> MultiplicativeThreshold:
    """HEBTEM threshold of the multiplicative rule, eq 16:

        int_lambda^{e^n} f(x) dx = (1 - beta)(e^n - lambda),  f = eqs 10-11.

    Solved as D(L' w) = beta with w = 1 - lambda/e^n, L' = ln(1/xi)/(1 - e^-2n) (module doc).
    Works for every n >= 1 (no e^n is formed). ``info``, if given, receives the number of
    function evaluations under "evaluations".
    """
    n = check_n(n)
    xi = check_xi(xi)
    beta = check_open_unit("beta", beta)
    l_prime = -math.log(xi) / -math.expm1(-2.0 * n)
    z, evals = solve_mean_deficit(beta, rtol)
    if info is not None:
        info["evaluations"] = evals
    w = z / l_prime
    if w > 2.0:  # t < -1: outside [-e^n, e^n]
        return MultiplicativeThreshold(n, xi, beta, (), (), ())
    t = 1.0 - w
    if t > 0.0:
        ln_t = math.log1p(-w)
        ln_lambda = n + ln_t
        present = min(n, max(0, math.ceil(n + 0.5 * ln_t)))  # 2j - n >= n + ln t
    else:
        ln_lambda = None
        present = 0
    return MultiplicativeThreshold(n, xi, beta, (t,), (ln_lambda,), (present,))


# ----------------------------------------------------------------------------------- additive


@dataclass(frozen=True)
class AdditiveThreshold:
    """Solution of eq 17 (additive rule; curve eq 13 for "pm1", eq 12 for "01").

    thresholds: every non-trivial root lambda in the domain ([-n, n] or [0, n]), ascending;
        0, 1 or 2 of them ("no root" is the empty tuple).
    present_counts: per root, the smallest number of present taxels j with U_G >= lambda
        (U_G = 2j - n for "pm1", j for "01").
    """

    n: int
    xi: float
    alpha: float
    encoding: str
    thresholds: tuple[float, ...]
    present_counts: tuple[int, ...]


def _q_pm1(v, half_r, ln_r, half_c):
    return half_r * _d(ln_r * v) + half_c * v


def _qprime_pm1(v, half_r, ln_r, half_c):
    return half_r * ln_r * _dprime(ln_r * v) + half_c


def _q_and_qprime_pm1(v, half_r, ln_r, half_c):
    """(Q(v), Q'(v)) in one call (one D/D' evaluation)."""
    d, dprime = _d_and_dprime(ln_r * v)
    return half_r * d + half_c * v, half_r * ln_r * dprime + half_c


def _newton_q(alpha, v, half_r, ln_r, half_c, rtol, evals):
    """Newton on Q(v) = alpha on one monotone side of the concave Q. From a start on the safe
    side (Q(v) <= alpha) the iterates move one way; from the other side the first tangent step
    lands on the safe side (the tangent lies above Q). After that, a step against the direction
    is rounding noise: the iterate is at the floor of the attainable accuracy and is kept
    (otherwise v can flip between two floats ~1e-15 apart until _MAX_ITER). The iteration also
    stops once the predicted next step (quadratic convergence) is below rtol v."""
    previous = 0.0
    for k in range(_MAX_ITER):
        q, qprime = _q_and_qprime_pm1(v, half_r, ln_r, half_c)
        step = (q - alpha) / qprime
        evals[0] += 1
        if k >= 2 and step * previous < 0.0:
            break
        v -= step
        if abs(step) <= rtol * v:
            break
        # quadratic convergence: the next step would be ~ |step/previous^2| step^2; stop if that
        # is below rtol (saves the one or two steps that only land in the rounding noise)
        if k >= 2 and abs(step) ** 3 <= rtol * v * previous * previous:
            break
        previous = step
    return v


def _additive_pm1_roots(alpha: float, xi: float, rtol: float, evals: list) -> list[float]:
    """Roots v in (0, 2] of Q(v) = alpha (module doc), ascending in v."""
    r, ln_r, c = additive_pm1_constants(xi)
    half_r, half_c = 0.5 * r, 0.5 * c
    slope0 = 0.25 * r * ln_r + half_c  # Q'(0) = p'(n) n / 2 > 0
    q_end = _q_pm1(2.0, half_r, ln_r, half_c)
    evals[0] += 1
    roots: list[float] = []
    if c >= 0.0 or _qprime_pm1(2.0, half_r, ln_r, half_c) >= 0.0:
        if alpha <= q_end:  # Q increasing on [0, 2]
            roots.append(min(2.0, _newton_q(alpha, alpha / slope0, half_r, ln_r, half_c, rtol, evals)))
        return roots
    # xi > 1/4 and Q has its maximum inside (0, 2): find it (Newton on Q', safeguarded). Newton
    # converges quadratically, so a step <= 1e-8 v leaves an error ~1e-16 v: stop there (smaller
    # steps are rounding noise of Q' near its zero, and bisecting them down to rtol cost ~20
    # evaluations). v_star only decides "no root" (Q(v_star) < alpha, flat there) and clamps
    # the roots of a near-tangent case.
    lo, hi = 0.0, 2.0
    v = 1.0
    newton_tol = max(rtol, 1e-8)
    for _ in range(_MAX_ITER):
        dprime, dsecond = _dprime_and_dsecond(ln_r * v)
        qp = half_r * ln_r * dprime + half_c  # Q'(v)
        qpp = half_r * ln_r * ln_r * dsecond  # Q''(v) < 0
        evals[0] += 1
        if qp == 0.0:
            break
        if qp > 0.0:
            lo = v
        else:
            hi = v
        nxt = v - qp / qpp
        if lo < nxt < hi:
            if abs(nxt - v) <= newton_tol * v:
                v = nxt
                break
        else:
            nxt = 0.5 * (lo + hi)
        if hi - lo <= rtol * hi:
            v = nxt
            break
        v = nxt
    v_star = v
    q_max = _q_pm1(v_star, half_r, ln_r, half_c)
    if alpha > q_max:
        return roots
    # starts: the roots of the parabola q_max + Q''(v_star) (v - v_star)^2 / 2 = alpha (good near
    # the tangent case, where Newton from the far starts alpha/slope0 and 2 converges only
    # linearly), kept within [alpha/slope0, 2]: alpha/slope0 <= first root (tangent at 0 above Q)
    # and Q(2) <= alpha are safe starts, and a start on the other side of a root returns to
    # the safe side in one step (_newton_q)
    half_gap = math.sqrt(2.0 * (q_max - alpha) / -qpp)
    first = _newton_q(alpha, max(alpha / slope0, v_star - half_gap), half_r, ln_r, half_c, rtol, evals)
    roots.append(min(first, v_star))
    if q_end <= alpha:
        second = _newton_q(alpha, min(2.0, v_star + half_gap), half_r, ln_r, half_c, rtol, evals)
        second = min(2.0, max(second, v_star))
        if second > roots[0] * (1.0 + 1e-12):  # a tangent (double) root is reported once
            roots.append(second)
    return roots


def additive_threshold(n, xi, alpha, encoding: str = "pm1", *, rtol: float = DEFAULT_RTOL, info: dict | None = None) -> AdditiveThreshold:
    """HEBTEM threshold of the additive rule, eq 17:

        int_lambda^n f(x) dx = (1 - alpha)(n - lambda),

    f = eq 13 on [-n, n] for ``encoding="pm1"`` or eq 12 on [0, n] for ``"01"``. Every root in
    the domain is returned (module doc); none is a result, never an error.
    """
    n = check_n(n)
    xi = check_xi(xi)
    alpha = check_open_unit("alpha", alpha)
    encoding = check_encoding(encoding)
    evals = [0]
    if encoding == "01":
        z, evals[0] = solve_mean_deficit(alpha, rtol)
        v = z / -math.log(xi)
        vs = [v] if v <= 1.0 else []
        lambdas = [n * (1.0 - v) for v in vs]
        counts = [min(n, max(0, math.ceil(n - n * v))) for v in vs]
    else:
        vs = _additive_pm1_roots(alpha, xi, rtol, evals)
        vs.reverse()  # v ascending -> lambda = n (1 - v) ascending
        lambdas = [n * (1.0 - v) for v in vs]
        counts = [min(n, max(0, math.ceil(n - 0.5 * n * v))) for v in vs]  # 2j - n >= n (1 - v)
    if info is not None:
        info["evaluations"] = evals[0]
    return AdditiveThreshold(n, xi, alpha, encoding, tuple(lambdas), tuple(counts))


# ------------------------------------------------------------------------------- preferential


@dataclass(frozen=True)
class PreferentialThreshold:
    """Solution of eqs 18-20 (preferential rule, curve eq 14).

    g_max: g(n) of eq 15. threshold_mean: the non-trivial root of eq 18 in [-g, g] (the larger
    one if two lie there); band_width: alpha g / 4 (eq 20); threshold_initial/final:
    mean -/+ band/2 (the band is centred on the mean, "mid-point of the band", sec. 2.2.3.3;
    eq 19 then holds identically and adds no condition). present_count: smallest number of
    present taxels j for which some arrangement reaches U_G >= threshold_mean (eq 7; the best
    arrangement of j present taxels is one contiguous run, see :func:`max_preferential_value`).
    threshold_mean/initial/final and present_count are None when eq 18 has no root in [-g, g]
    (alpha > 3(1 - xi)/4); band_width and g_max do not depend on the root and are always set.
    mean_roots: every non-trivial root of eq 18 in [-g, g], ascending (empty, one, or two
    when 2 <= 3 alpha/(1 - xi) < 9/4, the second one in [-g, -g/2]); threshold_mean is the
    largest.
    """

    n: int
    xi: float
    alpha: float
    p: float
    q: float
    encoding: str
    g_max: float
    threshold_mean: float | None
    band_width: float | None
    threshold_initial: float | None
    threshold_final: float | None
    present_count: int | None
    mean_roots: tuple[float, ...] = ()


def _weights(p: float, q: float) -> tuple[float, float, float, float, float]:
    """(P, Q, PQ, zp, zq) of eq 7: P = 2^p, Q = 2^q, PQ = P Q, zp = 0^p, zq = 0^q (0**0 = 1).

    P, Q are the factors (1 + u)^p, (1 + u)^q of a present neighbour, zp, zq those of an absent
    one on the {-1,+1} tuple, 1 those of the boundary u_0 = u_{n+1} = 0 (and of an absent one
    on the {0,1} tuple).
    """
    big_p, big_q = 2.0**p, 2.0**q
    return big_p, big_q, big_p * big_q, (1.0 if p == 0.0 else 0.0), (1.0 if q == 0.0 else 0.0)


def _best_run_value(n: int, present: int, weights: tuple, encoding: str) -> float:
    """M(present) = max of U_G (eq 7) over vectors with `present` present taxels, closed form, O(1).

    {0,1} tuple: absent taxels add 0 and look like the boundary to their neighbours, so every
    vector with all present taxels in one run gives U_G = g(present) (eq 15 with g(0) = 0,
    g(1) = 1), and splitting the run only loses 2^(p+q) - 2^p or the like: M(m) = g(m).

    {-1,+1} tuple: `a` absent taxels, a run of m present ones, `b` absent ones (a + b = F =
    n - m). The run gives P eL + Q eR + (m - 2) PQ (m >= 2) with eL = 1 if a = 0 else zq,
    eR = 1 if b = 0 else zp; the left absent segment S_L(0) = 0, S_L(1) = -P,
    S_L(a >= 2) = -zp - P zq - (a - 2) zp zq, the right one S_R likewise with P <-> Q,
    zp <-> zq. Grouping, U = (m - 2) PQ + L(a) + R(b) with L(0) = P, L(1) = P (zq - 1),
    L(a >= 2) = -zp - (a - 2) zp zq (R mirrored). L(0) = P >= 1 beats every other L and R(0)
    every other R, and two inner segments (a, b >= 1) never beat a run at an array end, so
    for 2 <= m <= n

        M(m) = (m - 2) PQ + E(F),  E(0) = P + Q,  E(1) = max(P - Q + Q zp, Q - P + P zq),
        E(F >= 2) = max(P - zq, Q - zp) - (F - 2) zp zq.

    m = 0: -1 (n = 1), -zp - zq - (n - 2) zp zq. m = 1 (n >= 2), by cases: p = q = 0: 2 - n
    (U_G = sum u_i); p = 0 < q: max(1 - Q, -1); q = 0 < p: max(1 - P, -1); p, q > 0: 0
    (n >= 3; the lone taxel at an end, two absent ones beside it), -min(P, Q) (n = 2).
    Checked against every vector for n <= 10 and against rules.preferential on run vectors up
    to n = 10^4 (tests/test_thresholds.py).

    Monotonicity in m (used by :func:`_smallest_present`): on 2..n, M(m + 1) - M(m) is
    PQ + zp zq > 0 (F >= 3), PQ + E(1) - E(2) in {PQ - min(P, Q), PQ, 2} > 0 (F = 2; p, q > 0
    gives P, Q > 1) and PQ + P + Q - E(1) >= PQ + min(P, Q) > 0 (F = 1): strictly increasing
    (in floating point only nondecreasing where 2^p or 2^q rounds to 1, p or q < 2^-53).
    M(1) >= M(0) and M(2) >= M(1) hold for n >= 3 (case by case above), and M(1) < M(0) = 0
    only for n = 2 with p, q > 0.
    """
    big_p, big_q, pq, zp, zq = weights
    if encoding == "01":
        if present <= 1:
            return float(present)
        return big_p + big_q + (present - 2) * pq
    if present == 0:
        return -1.0 if n == 1 else -zp - zq - (n - 2) * zp * zq
    if present == 1:
        if n == 1:
            return 1.0
        if zp and zq:
            return 2.0 - n
        if zp:
            return max(1.0 - big_q, -1.0)
        if zq:
            return max(1.0 - big_p, -1.0)
        return -min(big_p, big_q) if n == 2 else 0.0
    free = n - present
    if free == 0:
        edge = big_p + big_q
    elif free == 1:
        edge = max(big_p - big_q + big_q * zp, big_q - big_p + big_p * zq)
    else:
        edge = max(big_p - zq, big_q - zp) - (free - 2) * zp * zq
    return (present - 2) * pq + edge


def max_preferential_value(n, present, p, q, encoding: str = "pm1") -> float:
    """max of U_G (eq 7) over all decision vectors with exactly `present` present taxels.

    The maximum is reached by one contiguous run of present taxels (checked exhaustively against
    every vector for n <= 10 in tests/test_thresholds.py), touching an end of the array for
    present >= 2; its value is the closed form of :func:`_best_run_value`. O(1) in n.
    """
    n = check_n(n)
    p = check_weight("p", p)
    q = check_weight("q", q)
    encoding = check_encoding(encoding)
    present = check_integer("present", present, 0, n, allowed=f"must be an integer in 0..n (n = {n})")
    return _best_run_value(n, present, _weights(p, q), encoding)


def _smallest_present(n: int, weights: tuple, encoding: str, lam: float) -> int | None:
    """Smallest m in 0..n with M(m) >= lam (M of :func:`_best_run_value`), None if there is none.

    m = 0 and 1 are checked in order (only when lam <= 1: M(0) <= 0 and M(1) <= 1), since
    M(1) < M(0) can happen (n = 2). On 2..n M is strictly increasing and affine on 2..last
    (last = n - 2 on {-1,+1}, n on {0,1}) with slope PQ + zp zq (resp. PQ), so the answer is
    2 + ceil((lam - M(2))/slope), then stepped by at most a few places to the exact float
    comparison (rounding at an integer boundary, or m beyond `last`).
    """
    best = _best_run_value
    if lam <= 1.0:
        if best(n, 0, weights, encoding) >= lam:
            return 0
        if best(n, 1, weights, encoding) >= lam:
            return 1
    if n < 2:
        return None
    _, _, pq, zp, zq = weights
    if encoding == "01":
        slope, last = pq, n
    else:
        slope, last = pq + zp * zq, n - 2
    m = 2 + max(0, math.ceil((lam - best(n, 2, weights, encoding)) / slope))
    m = max(2, min(m, last))
    while m > 2 and best(n, m - 1, weights, encoding) >= lam:
        m -= 1
    while m <= n and best(n, m, weights, encoding) < lam:
        m += 1
    return m if m <= n else None


def preferential_threshold(n, xi, alpha, p, q, encoding: str = "pm1") -> PreferentialThreshold:
    """HEBTEM threshold band of the preferential rule, eqs 18-20 with eq 14, g = g(n) of eq 15:

        int_{lambda_mean}^{g} f(x) dx = (1 - alpha)(g - lambda_mean)           (18)
        delta lambda = alpha g / 4                                              (20)

    With y = lambda/g, eq 18 divided by (g - lambda) is y^2 + y - 2 + a = 0, a = 3 alpha/(1-xi),
    roots y = (-1 +- sqrt(9 - 4a))/2. The "+" root lies in [-1/2, 1) and exists iff
    a <= 9/4; it is formed as 1 - 2a/(3 + s) (a < 1) or 2(2 - a)/(1 + s) (a >= 1), s = sqrt(9-4a),
    without cancellation. The "-" root (-1 - s)/2 lies in [-1, -1/2] when a >= 2 (s <= 1) and
    is then returned in ``mean_roots`` too. ``encoding`` only affects present_count (U_G of
    eq 7 on that tuple).
    """
    n = check_n(n)
    xi = check_xi(xi)
    alpha = check_open_unit("alpha", alpha)
    p = check_weight("p", p)
    q = check_weight("q", q)
    encoding = check_encoding(encoding)
    weights = _weights(p, q)
    # g(n) of eq 15, the expression of rules.g_of_n (tested equal) without re-checking n, p, q
    g = 1.0 if n == 1 else (weights[0] + weights[1]) + (n - 2) * 2.0 ** (p + q)
    one_minus_xi = 1.0 - xi
    a = 3.0 * alpha / one_minus_xi
    disc = 9.0 - 4.0 * a
    band = alpha * g / 4.0  # eq 20, independent of the root
    if disc < 0.0:
        return PreferentialThreshold(n, xi, alpha, p, q, encoding, g, None, band, None, None, None)
    s = math.sqrt(disc)
    if a < 1.0:
        y = 1.0 - 2.0 * a / (3.0 + s)
    else:
        y = 2.0 * (2.0 * one_minus_xi - 3.0 * alpha) / (one_minus_xi * (1.0 + s))
    mean = y * g
    roots = (mean,)
    if s <= 1.0 and s > 0.0:  # second root (-1 - s)/2 in [-1, -1/2]; s = 0 is the double root
        roots = (0.5 * (-1.0 - s) * g, mean)
    present = _smallest_present(n, weights, encoding, mean)
    return PreferentialThreshold(
        n, xi, alpha, p, q, encoding, g, mean, band, mean - 0.5 * band, mean + 0.5 * band, present, roots
    )
