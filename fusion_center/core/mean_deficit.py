"""The mean-deficit function D of the HEBTEM threshold equations (Appendix I) and its inverse.

The chapter's threshold equations (eqs 16-18) say "area under the P(H1) curve from lambda to
the right end = (1 - alpha) (or (1 - beta)) times the rectangle" (Appendix I). Divided by the
width, each becomes "mean of P(H1) over [lambda, right end] = 1 - alpha", and for the
exponential curves (eqs 10-13) that mean has a closed form in

    D(z) = 1 - (1 - e^-z)/z = 1 - phi(z),   D(0+) = 0, D increasing and concave, D(inf) = 1,

evaluated by its Taylor series for z <= 1/2 (no cancellation) and by (z + expm1(-z))/z else.
:func:`solve_mean_deficit` inverts it (D(z) = b) by monotone Newton iterations in plain
``math`` floats (a few microseconds); :mod:`.thresholds` builds eqs 16-17 on it.
"""

from __future__ import annotations

import math

__all__ = ["solve_mean_deficit", "DEFAULT_RTOL"]

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
