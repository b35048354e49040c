"""HEBTEM dynamic thresholds (sec. 2.2.3.4, eqs 16-20, Appendix I), solved without overflow.

The chapter's threshold equations are "area under the P(H1) curve from lambda to the right end
= (1 - alpha) (or (1 - beta)) times the rectangle" (Appendix I). Dividing by the width turns each
into "mean of P(H1) over [lambda, right end] = 1 - alpha", and for eqs 16-17 every mean has a
closed form in the mean-deficit function D(z) = 1 - (1 - e^-z)/z of :mod:`.mean_deficit`
(D(0+) = 0, increasing and concave, D(inf) = 1; inverted by :func:`solve_mean_deficit`).

This module solves eqs 16-17 and certifies their roots and present counts:

* multiplicative, eq 16, curve eqs 10-11: with x = e^n s, L = ln(1/xi), L' = L/(1 - e^-2n) and
  w = 1 - t (t = lambda/e^n) the equation is D(L' w) = beta. Its non-trivial root is unique:
  z = D^-1(beta), w = z/L', t = 1 - w.
* additive {0,1}, eq 17 with eq 12: D(L v) = alpha, v = 1 - lambda/n in (0, 1].
* additive {-1,+1}, eq 17 with eq 13: with v = 1 - lambda/n in (0, 2], r, ln r, c of eq 13,
  Q(v) = (r/2) D(v ln r) + (c/2) v = alpha. Q(0) = 0 and Q is concave, so there are 0, 1 or
  2 roots (2 only when c < 0, i.e. xi > 1/4, where Q rises then falls inside (0, 2]).

The preferential band (eqs 18-20 with eq 14: y^2 + y - 2 + 3 alpha/(1 - xi) = 0, y = lambda/g)
is solved in :mod:`.preferential_band`; :func:`preferential_threshold`,
:class:`PreferentialThreshold` and :func:`max_preferential_value` are re-exported here, as are
:func:`solve_mean_deficit` and ``DEFAULT_RTOL``, so every name of this module stays where it was.

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

from .certify import NEAR_DOUBLE_ROOT
from .curves import additive_pm1_constants, check_n, check_open_unit, check_xi
from .encoding import check_encoding
# D and its inverse (Appendix I) live in .mean_deficit; the names are re-exported here unchanged
from .mean_deficit import (  # noqa: F401
    _EPS,
    _MAX_ITER,
    DEFAULT_RTOL,
    _d,
    _d_and_dprime,
    _dprime,
    _dprime_and_dsecond,
    _dsecond,
    solve_mean_deficit,
)
# the preferential band (eqs 18-20) lives in .preferential_band; re-exported here unchanged
from .preferential_band import PreferentialThreshold, max_preferential_value, preferential_threshold

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


# ------------------------------------------------------------------ certification helpers
# Every float root below carries an error bound. Where the bound cannot decide a discrete
# question -- the number of roots near a tangency, a root at a domain edge, the side of an
# attainable U_G value (the present count) -- the problem is solved again for the exact float
# inputs in mpmath (fusion_center.core.certify) and the root is rounded to the double on the
# side that keeps every comparison with an attainable value exact.
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
