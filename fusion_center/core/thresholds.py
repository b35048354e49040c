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
from fractions import Fraction

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


# ------------------------------------------------------------------ certification helpers
# Every float root below carries an error bound. Where the bound cannot decide a discrete
# question -- the number of roots near a tangency, a root at a domain edge, the side of an
# attainable U_G value (the present count) -- the problem is solved again for the exact float
# inputs in mpmath (fusion_center.core.certify) and the root is rounded to the double on the
# side that keeps every comparison with an attainable value exact.

NEAR_DOUBLE_ROOT = 1e-8
"""|alpha_tangent - alpha| below which two roots of eq 17 / eq 18 are a near-double pair: both
are reported (from the extended-precision solution) and flagged ``near_double_root``."""


def _grid_pm1(n: int):
    """Attainable U_G = 2j - n (additive and ln of multiplicative, {-1,+1}): the two grid
    values around x (integers of n's parity)."""
    def around(x: float):
        k = math.floor(x)
        if (k - n) % 2:
            k -= 1
        return (k, k + 2)
    return around


def _grid_int(x: float):
    k = math.floor(x)
    return (k, k + 1)


def _near_grid(x: float, err: float, around) -> bool:
    lo, hi = around(x)
    return x - lo <= err or hi - x <= err


def _ceil_exact(x) -> int:
    """ceil of a float or Fraction, exactly (no float rounding of n + lambda for n up to 2^53)."""
    return math.ceil(Fraction(x))


# ----------------------------------------------------------------------------- multiplicative


@dataclass(frozen=True)
class MultiplicativeThreshold:
    """Solution of eq 16 (multiplicative rule, {-1,+1} tuple, curve eqs 10-11).

    scaled_thresholds: t = lambda/e^n of every non-trivial root in [-1, 1] (ascending; eq 16 has
        at most one). ln_thresholds: ln lambda = n + ln t, None where t <= 0.
    present_counts: per root, the smallest number of present taxels j (0..n) whose
        U_G = e^(2j - n) >= lambda, exact (certified, consistent with ln_thresholds); 0 when
        lambda <= e^-n.
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
    Works for every n >= 1 (no e^n is formed). Certified: where the float error bound of t
    cannot decide t <= 0, t >= -1 (the edge lambda = -e^n) or the side of an attainable
    ln U_G = 2j - n, t is recomputed in mpmath (:mod:`.certify`). ``info``, if given, receives
    the number of function evaluations under "evaluations" and "certified": True when the
    extended-precision path was taken.
    """
    n = check_n(n)
    xi = check_xi(xi)
    beta = check_open_unit("beta", beta)
    l_prime = -math.log(xi) / -math.expm1(-2.0 * n)
    z, evals = solve_mean_deficit(beta, rtol)
    if info is not None:
        info["evaluations"] = evals
        info["certified"] = False
    w = z / l_prime
    err_t = 16.0 * _EPS * w + _EPS  # z, L' and w to a few ulps each, 1 - w one more
    grid = _grid_pm1(n)
    t = 1.0 - w
    exact = abs(w - 2.0) <= err_t or abs(t) <= err_t
    if not exact and t > 0.0:
        ln_lambda = n + math.log1p(-w)
        err_ln = err_t / t + 4.0 * _EPS * abs(ln_lambda)
        exact = -n < ln_lambda + err_ln and ln_lambda - err_ln < n and _near_grid(ln_lambda, err_ln, grid)
    if exact:
        from . import certify

        if info is not None:
            info["certified"] = True
        t_exact = certify.multiplicative_root(n, xi, beta)
        if t_exact < -1:
            return MultiplicativeThreshold(n, xi, beta, (), (), ())
        t = float(t_exact)
        if t_exact > 0:
            import mpmath

            with mpmath.workdps(certify.DPS):
                ln_exact = n + mpmath.log(t_exact)
            ln_lambda = certify.to_float(ln_exact, grid)
        else:
            ln_lambda = None
    elif w > 2.0:  # t < -1: outside [-e^n, e^n]
        return MultiplicativeThreshold(n, xi, beta, (), (), ())
    elif t <= 0.0:
        ln_lambda = None
    if ln_lambda is None:
        present = 0
    elif exact:
        present = min(n, max(0, _ceil_exact((n + Fraction(ln_lambda)) / 2)))  # 2j - n >= ln lambda
    else:  # ln lambda is farther than its error bound from every 2j - n: the float ceil is exact
        present = min(n, max(0, math.ceil(0.5 * (n + ln_lambda))))
    return MultiplicativeThreshold(n, xi, beta, (t,), (ln_lambda,), (present,))


# ----------------------------------------------------------------------------------- additive


@dataclass(frozen=True)
class AdditiveThreshold:
    """Solution of eq 17 (additive rule; curve eq 13 for "pm1", eq 12 for "01").

    thresholds: every non-trivial root lambda in the domain ([-n, n] or [0, n]), ascending;
        0, 1 or 2 of them ("no root" is the empty tuple).
    present_counts: per root, the smallest number of present taxels j with U_G >= lambda
        (U_G = 2j - n for "pm1", j for "01"), exact for the lambda returned.
    near_double_root: True when alpha is within NEAR_DOUBLE_ROOT of the tangent value (the
        maximum of Q, module doc): the two roots are then a near-double pair, both reported
        (computed in extended precision), or none if alpha lies above the maximum.
    """

    n: int
    xi: float
    alpha: float
    encoding: str
    thresholds: tuple[float, ...]
    present_counts: tuple[int, ...]
    near_double_root: bool = False


def _q_pm1(v, half_r, ln_r, half_c):
    return half_r * _d(ln_r * v) + half_c * v


def _qprime_pm1(v, half_r, ln_r, half_c):
    return half_r * ln_r * _dprime(ln_r * v) + half_c


def _q_and_qprime_pm1(v, half_r, ln_r, half_c):
    """(Q(v), Q'(v)) in one call (one D/D' evaluation)."""
    d, dprime = _d_and_dprime(ln_r * v)
    return half_r * d + half_c * v, half_r * ln_r * dprime + half_c


def _q_error(v, half_r, half_c, alpha):
    """Bound on the float error of Q(v) - alpha (each term to a few ulps, generous factor)."""
    return 64.0 * _EPS * (half_r + abs(half_c) * v + alpha)


def _bracketed_newton(alpha, v, lo, hi, increasing, half_r, ln_r, half_c, rtol, evals):
    """Root of Q(v) = alpha in [lo, hi], Q monotone there (increasing or not): Newton steps
    kept inside the shrinking bracket, a bisection when a step leaves it or Q' = 0 (so the
    tangent point of a near-double root cannot divide by zero). Stops when the step is below
    rtol v, the bracket below 4 ulps, or Q(v) - alpha is within its own rounding error (one
    last Newton step is taken then)."""
    for _ in range(_MAX_ITER):
        q, qprime = _q_and_qprime_pm1(v, half_r, ln_r, half_c)
        evals[0] += 1
        f = q - alpha
        if f == 0.0:
            return v
        if (f < 0.0) == increasing:
            lo = v
        else:
            hi = v
        nxt = v - f / qprime if qprime != 0.0 else math.nan
        inside = lo <= nxt <= hi
        if not inside:
            nxt = 0.5 * (lo + hi)
        if abs(nxt - v) <= rtol * abs(nxt) or hi - lo <= 4.0 * _EPS * hi:
            return nxt
        if inside and abs(f) <= _q_error(v, half_r, half_c, alpha):
            return nxt
        v = nxt
    return v


def _additive_pm1_roots(alpha: float, xi: float, rtol: float, evals: list):
    """Roots v in (0, 2] of Q(v) = alpha (module doc), ascending in v, in floats; None when the
    error bound cannot decide the number of roots (near tangency, a root at v = 2)."""
    r, ln_r, c = additive_pm1_constants(xi)
    half_r, half_c = 0.5 * r, 0.5 * c
    slope0 = 0.25 * r * ln_r + half_c  # Q'(0) = p'(n) n / 2 > 0
    evals[0] += 1
    if c >= 0.0 or _qprime_pm1(2.0, half_r, ln_r, half_c) >= 0.0:
        v_star = 2.0  # Q increasing on [0, 2]
    else:
        # xi > 1/4 and Q has its maximum inside (0, 2): Newton on Q', safeguarded by bisection;
        # a step <= 1e-8 v leaves an error ~1e-16 v in v_star and ~1e-32 in Q(v_star)
        lo, hi = 0.0, 2.0
        v = 1.0
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
                if abs(nxt - v) <= 1e-8 * v:
                    v = nxt
                    break
            else:
                nxt = 0.5 * (lo + hi)
            if hi - lo <= rtol * hi:
                v = nxt
                break
            v = nxt
        v_star = v
    gap = _q_pm1(v_star, half_r, ln_r, half_c) - alpha
    evals[0] += 1
    if abs(gap) <= _q_error(v_star, half_r, half_c, alpha) or (v_star < 2.0 and abs(gap) <= NEAR_DOUBLE_ROOT):
        return None
    if gap < 0.0:
        return []
    start = min(alpha / slope0, v_star)  # left of the first root (the tangent at 0 lies above Q)
    roots = [_bracketed_newton(alpha, start, 0.0, v_star, True, half_r, ln_r, half_c, rtol, evals)]
    if v_star < 2.0:
        end = _q_pm1(2.0, half_r, ln_r, half_c) - alpha
        evals[0] += 1
        if abs(end) <= _q_error(2.0, half_r, half_c, alpha):
            return None
        if end < 0.0:
            roots.append(_bracketed_newton(alpha, 2.0, v_star, 2.0, False, half_r, ln_r, half_c, rtol, evals))
    return roots


def _additive_v_error(v, alpha, xi) -> float:
    """Bound on the error of a float root v of Q(v) = alpha: E/|Q'(v)| + a few ulps of v."""
    r, ln_r, c = additive_pm1_constants(xi)
    half_r, half_c = 0.5 * r, 0.5 * c
    slope = abs(_qprime_pm1(v, half_r, ln_r, half_c))
    e = _q_error(v, half_r, half_c, alpha)
    return (8.0 * e / slope if slope > 0.0 else math.inf) + 8.0 * _EPS * max(v, 1.0)


def additive_threshold(n, xi, alpha, encoding: str = "pm1", *, rtol: float = DEFAULT_RTOL, info: dict | None = None) -> AdditiveThreshold:
    """HEBTEM threshold of the additive rule, eq 17:

        int_lambda^n f(x) dx = (1 - alpha)(n - lambda),

    f = eq 13 on [-n, n] for ``encoding="pm1"`` or eq 12 on [0, n] for ``"01"``. Every root in
    the domain is returned (module doc); none is a result, never an error. Certified: the number
    of roots, a root at a domain edge and the present counts are exact (mpmath where the float
    error bound cannot decide, :mod:`.certify`); near a tangency both roots are reported and
    ``near_double_root`` is set.
    """
    n = check_n(n)
    xi = check_xi(xi)
    alpha = check_open_unit("alpha", alpha)
    encoding = check_encoding(encoding)
    evals = [0]
    near_double = False
    grid = _grid_int if encoding == "01" else _grid_pm1(n)
    if encoding == "01":
        z, evals[0] = solve_mean_deficit(alpha, rtol)
        v = z / -math.log(xi)
        err_v = 16.0 * _EPS * v
        vs = None if abs(v - 1.0) <= err_v else ([v] if v <= 1.0 else [])
        errs = [err_v]
    else:
        vs = _additive_pm1_roots(alpha, xi, rtol, evals)
        if vs is not None:
            vs.reverse()  # v descending -> lambda = n (1 - v) ascending
            errs = [_additive_v_error(v, alpha, xi) for v in vs]
    lambdas = None
    if vs is not None:
        lambdas = [n * (1.0 - v) for v in vs]
        for lam, err_v in zip(lambdas, errs):
            err = n * err_v + 4.0 * _EPS * abs(lam)
            if _near_grid(lam, err, grid) and -n < lam + err:
                lambdas = None  # the side of an attainable U_G is undecided: certify
                break
    certified = lambdas is None
    if certified:
        from . import certify

        import mpmath

        if encoding == "01":
            v_exact = certify.additive_01_root(xi, alpha)
            exact_vs = [v_exact] if v_exact <= 1 else []
        else:
            exact_vs, near_double = certify.additive_pm1_roots(xi, alpha, NEAR_DOUBLE_ROOT)
            exact_vs = exact_vs[::-1]
        with mpmath.workdps(certify.DPS + 20):
            lambdas = [certify.to_float(n * (1 - v), grid) for v in exact_vs]
    # 2j - n >= lambda (pm1) or j >= lambda (01); off the certified path lambda is farther than
    # its error bound (which exceeds the rounding of n + lambda) from every attainable value,
    # so the float ceil is exact there
    if certified:
        ceil = _ceil_exact
        half = lambda lam: (n + Fraction(lam)) / 2
    else:
        ceil = math.ceil
        half = lambda lam: 0.5 * (n + lam)
    if encoding == "01":
        counts = [min(n, max(0, ceil(lam))) for lam in lambdas]
    else:
        counts = [min(n, max(0, ceil(half(lam)))) for lam in lambdas]
    if info is not None:
        info["evaluations"] = evals[0]
        info["certified"] = certified
    return AdditiveThreshold(n, xi, alpha, encoding, tuple(lambdas), tuple(counts), near_double)


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
    largest. near_double_root: alpha within NEAR_DOUBLE_ROOT of the tangent value 3(1 - xi)/4
    (both roots of the near-double pair are listed in mean_roots).

    band: "centred" (default, the band centred on threshold_mean as above) or "eq19": the band of
    width alpha g / 4 (eq 20) on which the mean of f is 1 - alpha (eq 19). Eq 19 and eq 20 fix
    the band without eq 18; with f of eq 14 there are 0, 1 or 2 such bands in [-g, g],
    listed in eq19_bands (initial, final), ascending; threshold_initial/final are then the
    upper one (None if there is none). The centred band satisfies eq 19 only by coincidence
    (docs/chapter-notes.md).
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
    near_double_root: bool = False
    band: str = "centred"
    eq19_bands: tuple[tuple[float, float], ...] = ()


def _weights(p: float, q: float) -> tuple[float, float, float, float, float]:
    """(P, Q, PQ, zp, zq) of eq 7: P = 2^p, Q = 2^q, PQ = P Q, zp = 0^p, zq = 0^q (0**0 = 1).

    P, Q are the factors (1 + u)^p, (1 + u)^q of a present neighbour, zp, zq those of an absent
    one on the {-1,+1} tuple, 1 those of the boundary u_0 = u_{n+1} = 0 (and of an absent one
    on the {0,1} tuple).
    """
    big_p, big_q = 2.0**p, 2.0**q
    # PQ as 2^(p+q), the same float as in g(n) (rules.g_of_n), so U_G of the all-present vector
    # equals g in floating point too
    return big_p, big_q, 2.0 ** (p + q), (1.0 if p == 0.0 else 0.0), (1.0 if q == 0.0 else 0.0)


def _mp_weights(p: float, q: float):
    """The weights of :func:`_weights` in the current mpmath precision (exact inputs)."""
    import mpmath

    two = mpmath.mpf(2)
    return (two ** mpmath.mpf(p), two ** mpmath.mpf(q), two ** (mpmath.mpf(p) + mpmath.mpf(q)),
            mpmath.mpf(1 if p == 0.0 else 0), mpmath.mpf(1 if q == 0.0 else 0))


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


def _float_above(x) -> float:
    f = float(x)
    return math.nextafter(f, math.inf) if f <= x else f


def _float_at_or_below(x) -> float:
    f = float(x)
    return math.nextafter(f, -math.inf) if f > x else f


def _certified_present(n, p, q, weights, encoding, mean, exact_mean):
    """(present_count, mean): the smallest m with M(m) >= lambda_mean, exact. Where a float
    M(m) lies within its error bound of the float mean, M(m) and the mean are evaluated in
    mpmath (``exact_mean()``), and the returned mean is moved by an ulp if rounding put it on
    the wrong side of M(m) (so the count and the returned mean agree)."""
    m = _smallest_present(n, weights, encoding, mean)
    g = weights[0] + weights[1] + n * weights[2]
    err = 32.0 * _EPS * (abs(mean) + g)
    centre = m if m is not None else n
    # the comparisons that decided m: M(m) >= mean, M(m - 1) < mean (and M(0), M(1) near the start)
    decisive = (0, 1, centre - 1, centre) if centre <= 3 else (centre - 1, centre)
    if all(abs(_best_run_value(n, k, weights, encoding) - mean) > err for k in decisive if 0 <= k <= n):
        return m, mean
    window = sorted({0, 1, n} | {k for k in range(centre - 2, centre + 3) if 0 <= k <= n})
    import mpmath

    from . import certify

    with mpmath.workdps(certify.DPS):
        lam = exact_mean()
        w = _mp_weights(p, q)
        exact_m = {k: _best_run_value(n, k, w, encoding) for k in window}
        for value in exact_m.values():
            if abs(value - mean) <= err:
                if lam > value and mean <= value:
                    mean = _float_above(value)
                elif lam <= value and mean > value:
                    mean = _float_at_or_below(value)
        # smallest k: 0 and 1 in order (M(1) < M(0) can happen), then M increasing on 2..n
        # (the float answer m is within one place of the exact one: the window covers it)
        if exact_m[0] >= lam:
            found = 0
        elif exact_m[1] >= lam:
            found = 1
        else:
            found = next((k for k in window if k >= 2 and exact_m[k] >= lam), None)
    return found, mean


def _exact_mean_root(n, xi, alpha, p, q, minus=False):
    """lambda_mean of eq 18 in mpmath, the + root (or the - root) for the exact inputs."""
    import mpmath

    a = 3 * mpmath.mpf(alpha) / (1 - mpmath.mpf(xi))
    s = mpmath.sqrt(9 - 4 * a)
    y = (-1 - s) / 2 if minus else 2 * (2 - a) / (1 + s)
    big_p, big_q, pq, _, _ = _mp_weights(p, q)
    g = mpmath.mpf(1) if n == 1 else (big_p + big_q) + (n - 2) * pq
    return y * g


def _eq19_bands(xi: float, alpha: float, g: float) -> tuple[tuple[float, float], ...]:
    """Bands [y_i, y_i + w] g of width w g, w = alpha/4 (eq 20), with mean of f (eq 14) = 1 - alpha
    (eq 19): (1 - xi)(y_i^2 + w y_i + w^2/3) + xi = 1 - alpha, i.e.
    y_i^2 + w y_i + w^2/3 - C = 0, C = 1 - alpha/(1 - xi); y_i = (-w +- sqrt(4C - w^2/3))/2,
    kept where the band lies inside [-1, 1]. The discriminant and C - w^2/3 are formed exactly
    (fractions): no cancellation at the tangent band."""
    a_, x_ = Fraction(alpha), Fraction(xi)
    w = a_ / 4
    c = 1 - a_ / (1 - x_)
    disc = 4 * c - w * w / 3
    if disc < 0:
        return ()
    s = math.sqrt(float(disc))
    wf = float(w)
    upper = 2.0 * float(c - w * w / 3) / (s + wf)  # (-w + s)/2 without cancellation
    lower = -0.5 * (wf + s)
    bands = []
    for y in sorted({lower, upper}):
        if -1.0 <= y and y + wf <= 1.0:
            bands.append((y * g, (y + wf) * g))
    return tuple(bands)


def preferential_threshold(n, xi, alpha, p, q, encoding: str = "pm1", band: str = "centred") -> PreferentialThreshold:
    """HEBTEM threshold band of the preferential rule, eqs 18-20 with eq 14, g = g(n) of eq 15:

        int_{lambda_mean}^{g} f(x) dx = (1 - alpha)(g - lambda_mean)           (18)
        int_{lambda_i}^{lambda_f} f(x) dx = (1 - alpha)(lambda_f - lambda_i)     (19)
        delta lambda = lambda_f - lambda_i = alpha g / 4                         (20)

    With y = lambda/g, eq 18 divided by (g - lambda) is y^2 + y - 2 + a = 0, a = 3 alpha/(1-xi),
    roots y = (-1 +- sqrt(9 - 4a))/2. The "+" root lies in [-1/2, 1) and exists iff a <= 9/4;
    it is formed as 1 - 2a/(3 + s) (a < 1) or 2(2 - a)/(1 + s) (a >= 1), s = sqrt(9 - 4a). The
    "-" root (-1 - s)/2 lies in [-1, -1/2] when a >= 2 and is then returned in ``mean_roots``
    too. 9 - 4a, 2 - a and the tests a <= 9/4, a >= 2 are exact (fractions of the float
    inputs), so no root is invented or lost at a = 2 or 9/4 and both roots of a near-double
    pair are returned (``near_double_root``). ``encoding`` only affects present_count (U_G of
    eq 7 on that tuple), which is certified (:func:`_certified_present`). ``band``: "centred"
    (default) or "eq19" (:class:`PreferentialThreshold`).
    """
    n = check_n(n)
    xi = check_xi(xi)
    alpha = check_open_unit("alpha", alpha)
    p = check_weight("p", p)
    q = check_weight("q", q)
    encoding = check_encoding(encoding)
    if band not in ("centred", "eq19"):
        from taxel_net.errors import ParameterError

        raise ParameterError("band", band, "must be 'centred' or 'eq19'")
    weights = _weights(p, q)
    # g(n) of eq 15, the expression of rules.g_of_n (tested equal) without re-checking n, p, q
    g = 1.0 if n == 1 else (weights[0] + weights[1]) + (n - 2) * weights[2]
    a_float = 3.0 * alpha / (1.0 - xi)
    width = alpha * g / 4.0  # eq 20, independent of the root
    bands = _eq19_bands(xi, alpha, g) if band == "eq19" else ()
    if abs(a_float - 2.0) > 1e-5 and abs(a_float - 2.25) > 1e-5:
        # away from a = 2 and 9/4: floats decide and keep ~1e-10 relative accuracy in 2 - a, 9 - 4a
        a_exact = a_float
        disc = 9.0 - 4.0 * a_float
        near_double = False
    else:  # exact rational arithmetic on the float inputs
        a_exact = 3 * Fraction(alpha) / (1 - Fraction(xi))
        disc = 9 - 4 * a_exact
        near_double = abs(Fraction(3, 4) * (1 - Fraction(xi)) - Fraction(alpha)) <= NEAR_DOUBLE_ROOT
    if disc < 0:
        return PreferentialThreshold(n, xi, alpha, p, q, encoding, g, None, width, None, None, None, (),
                                     near_double, band, bands)
    s = math.sqrt(float(disc))
    if a_exact < 1:
        y = 1.0 - 2.0 * float(a_exact) / (3.0 + s)
    elif isinstance(a_exact, Fraction):
        y = 2.0 * float(2 - a_exact) / (1.0 + s)
    else:  # 2(1 - xi) - 3 alpha over (1 - xi): the printed form's cancellation is bounded by 1e-5
        y = 2.0 * (2.0 * (1.0 - xi) - 3.0 * alpha) / ((1.0 - xi) * (1.0 + s))
    mean = y * g
    mean, present = _certified_mean(n, xi, alpha, p, q, weights, encoding, mean)
    roots = (mean,)
    if a_exact >= 2:  # second root (-1 - s)/2 in [-1, -1/2] (a double root at a = 9/4 is listed twice)
        roots = (0.5 * (-1.0 - s) * g, mean)
    if band == "eq19":
        initial, final = bands[-1] if bands else (None, None)
    else:
        initial, final = mean - 0.5 * width, mean + 0.5 * width
    return PreferentialThreshold(
        n, xi, alpha, p, q, encoding, g, mean, width, initial, final, present, roots, near_double, band, bands
    )


def _certified_mean(n, xi, alpha, p, q, weights, encoding, mean):
    present, mean = _certified_present(n, p, q, weights, encoding, mean,
                                       lambda: _exact_mean_root(n, xi, alpha, p, q))
    return mean, present
