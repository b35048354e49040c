"""Certified refinement of the HEBTEM thresholds (eqs 16-18) in extended precision (mpmath).

The float solvers of :mod:`fusion_center.core.thresholds` carry an explicit error bound. Where
that bound cannot decide something discrete -- how many roots eq 17 has near a tangency, whether
a root lies inside the domain at an edge (lambda = -n, lambda = 0, t = -1), on which side of an
attainable U_G value a root lies (the present count, a decision U_G >= lambda) -- the question
is answered here by solving the same equations for the *exact* float inputs in mpmath, at 60
significant digits and more (up to 480) while the answer is still within the working
precision's error. Only the rare undecided cases come here (a few ms each).

Every routine works on the exact binary value of each float input (mpf(x) is exact), so the
answer is the exact answer for the given inputs; :func:`to_float` then rounds a root to a
double on the side that keeps every comparison with an attainable value exact.
"""

from __future__ import annotations

import math

__all__ = [
    "DPS",
    "NEAR_DOUBLE_ROOT",
    "mp_d",
    "mp_dprime",
    "additive_pm1_roots",
    "additive_01_root",
    "multiplicative_root",
    "to_float",
]

DPS = 60  # first working precision (decimal digits); doubled while undecided, up to 480
MAX_DPS = 480

NEAR_DOUBLE_ROOT = 1e-8
"""|alpha_tangent - alpha| below which two roots of eq 17 / eq 18 are a near-double pair: both
are reported (from the extended-precision solution) and flagged ``near_double_root``."""


def _mp():
    import mpmath  # imported on first use: the float paths never load it

    return mpmath


def mp_d(z):
    """D(z) = 1 - (1 - e^-z)/z in the current mpmath precision (series for z < 1/2: no
    cancellation however small z is, e.g. z ~ 1e-150 for xi = 1e-300)."""
    mp = _mp().mp
    if z < 0.5:
        total, term, k = mp.mpf(0), z / 2, 2  # sum_{k>=2} (-1)^k z^(k-1)/k!
        while True:
            total += term
            k += 1
            term = -term * z / k
            if abs(term) < abs(total) * mp.eps / 16:
                return total
    return (z + _mp().expm1(-z)) / z


def mp_dprime(z):
    """D'(z) = (1 - (1 + z) e^-z)/z^2 (series sum_{k>=2} (-1)^k (k-1) z^(k-2)/k! for z < 1/2)."""
    mpm = _mp()
    if z < 0.5:
        total, k, fact, power = mpm.mp.mpf(0), 2, mpm.mp.mpf(2), mpm.mp.mpf(1)
        while True:
            term = (k - 1) * power / fact * (1 if k % 2 == 0 else -1)
            total += term
            if abs(term) < abs(total) * mpm.mp.eps / 16 and k > 3:
                return total
            k += 1
            fact *= k
            power *= z
    return (1 - (1 + z) * mpm.exp(-z)) / (z * z)


def _bracket_root(f, lo, hi, f_lo, f_hi):
    """Root of f in [lo, hi] (f(lo), f(hi) of opposite signs or zero): Illinois (regula falsi
    halving the stale end's value) with a bisection whenever three steps did not halve the
    bracket; stops when the bracket is below the working precision."""
    mp = _mp().mp
    if f_lo == 0:
        return lo
    if f_hi == 0:
        return hi
    side = 0
    width_before = hi - lo
    for step in range(1, 40 * mp.dps):
        width = hi - lo
        if width <= 4 * mp.eps * max(abs(lo), abs(hi)):
            break
        if step % 3 == 0:
            if width > width_before / 2:
                x = (lo + hi) / 2
            else:
                x = None
            width_before = width
        else:
            x = None
        if x is None:
            x = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
            if not (lo < x < hi):
                x = (lo + hi) / 2
        fx = f(x)
        if fx == 0:
            return x
        if (fx < 0) == (f_lo < 0):
            lo, f_lo = x, fx
            if side == -1:
                f_hi /= 2
            side = -1
        else:
            hi, f_hi = x, fx
            if side == 1:
                f_lo /= 2
            side = 1
    return (lo + hi) / 2


def additive_pm1_roots(xi: float, alpha: float, near_double: float):
    """Roots v in [0, 2] of eq 17 on {-1,+1}, Q(v) = (r/2) D(v ln r) + (c/2) v = alpha
    (v = 1 - lambda/n, thresholds module doc), for the exact float inputs.

    Returns (roots, flag): roots ascending in v as mpf at the final precision (a double root
    is listed twice), flag True when Q(v*) - alpha < ``near_double`` at the maximum v* (the
    roots are then a near-double pair, each sensitive as sqrt of an input perturbation).
    """
    mpm = _mp()
    dps = DPS
    while True:
        with mpm.workdps(dps):
            result = _additive_pm1_roots_at(mpm, xi, alpha, near_double)
            if result is not None:
                roots, flag = result
                return [+v for v in roots], flag
        if dps >= MAX_DPS:
            with mpm.workdps(dps):
                return _additive_pm1_roots_at(mpm, xi, alpha, near_double, force=True)
        dps *= 2


def _additive_pm1_roots_at(mpm, xi, alpha, near_double, force=False):
    mp = mpm.mp
    x, a = mp.mpf(xi), mp.mpf(alpha)
    s = mp.sqrt(x * (x + 2))
    r = x + 1 + s
    ln_r = mpm.log1p(x + s)
    c = (1 - 4 * x) / (2 * (1 - x + s))  # 1 - r/2 without cancellation
    tiny = mp.mpf(10) ** (-(mp.dps - 12))

    def q(v):
        return r / 2 * mp_d(ln_r * v) + c / 2 * v

    def qp(v):
        return r / 2 * ln_r * mp_dprime(ln_r * v) + c / 2

    two = mp.mpf(2)
    if c >= 0 or qp(two) >= 0:
        v_star = two
    else:
        v_star = _bracket_root(qp, mp.mpf(0), two, qp(mp.mpf(0)), qp(two))
    gap = q(v_star) - a
    if abs(gap) <= tiny * (1 + a):
        if not force:
            return None  # undecided at this precision
        gap = mp.mpf(0)
    flag = v_star < two and gap < near_double
    if gap < 0:
        return [], flag
    if gap == 0:
        return [v_star, v_star], True
    roots = [_bracket_root(lambda v: q(v) - a, mp.mpf(0), v_star, -a, gap)]
    if v_star < two:
        end = q(two) - a
        if abs(end) <= tiny * (1 + a) and not force:
            return None
        if end <= 0:
            roots.append(_bracket_root(lambda v: q(v) - a, v_star, two, gap, end))
    return roots, flag


def _solve_d(mpm, b):
    """z > 0 with D(z) = b (D increasing), in the current precision."""
    mp = mpm.mp
    hi = mp.mpf(4) * b + 1 / (1 - b) + 1  # D(hi) > b: D(z) >= 1 - 1/z and D(z) >= z/2 - z^2/6
    return _bracket_root(lambda z: mp_d(z) - b, mp.mpf(0), hi, -b, mp_d(hi) - b)


def additive_01_root(xi: float, alpha: float):
    """v = z / ln(1/xi) of eq 17 on {0,1} (D(z) = alpha), exact inputs; v <= 1 is in the domain."""
    mpm = _mp()
    with mpm.workdps(DPS):
        z = _solve_d(mpm, mpm.mp.mpf(alpha))
        return +(z / -mpm.log(mpm.mp.mpf(xi)))


def multiplicative_root(n: int, xi: float, beta: float):
    """t = 1 - z/L' of eq 16 (D(z) = beta, L' = ln(1/xi)/(1 - e^-2n)), exact inputs, as mpf
    with DPS digits (its absolute error is ~1e-60, far below any t that matters)."""
    mpm = _mp()
    with mpm.workdps(DPS):
        mp = mpm.mp
        z = _solve_d(mpm, mp.mpf(beta))
        l_prime = -mpm.log(mp.mpf(xi)) / -mpm.expm1(-2 * mp.mpf(n))
        return +(1 - z / l_prime)


def to_float(exact, attainable_floor=None) -> float:
    """The double nearest ``exact`` (an mpf), moved by one ulp where rounding would put it onto
    or across the nearest attainable value A (an integer, the grid of U_G values): afterwards
    ``A >= result`` iff ``A >= exact``. ``attainable_floor(x)`` returns the attainable values
    next to x (a pair lo <= x <= hi, integers); None means no grid.
    """
    f = float(exact)
    if attainable_floor is None or not math.isfinite(f):
        return f
    for grid in attainable_floor(f):
        if exact > grid and f <= grid:
            f = math.nextafter(float(grid), math.inf)
        elif exact <= grid and f > grid:
            f = float(grid)
    return f
