"""HEBTEM threshold band of the preferential rule (sec. 2.2.3.3-4, eqs 18-20 with eq 14).

With y = lambda/g (g = g(n) of eq 15) the cubic of eq 18 divided by (g - lambda) is the
quadratic y^2 + y - 2 + 3 alpha/(1 - xi) = 0, solved in closed form (exact rational tests at its
special points a = 2 and 9/4); eq 20 fixes the band width alpha g / 4; eq 19 is imposed only
with ``band="eq19"`` (docs/chapter-notes.md). The present count of the mean threshold -- the
smallest number of present taxels for which some arrangement reaches lambda_mean -- follows
from the closed-form maximum of U_G (eq 7) over vectors with a given present count
(:func:`max_preferential_value`), certified in mpmath (:mod:`.certify`) where rounding cannot
decide it. :func:`band_decision` compares a vector's U_G with the band edges exactly.

Re-exported unchanged by :mod:`.thresholds` and :mod:`fusion_center.core`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

from .certify import NEAR_DOUBLE_ROOT
from .curves import check_n, check_open_unit, check_xi
from .encoding import check_encoding, check_integer
from .mean_deficit import _EPS
from .rules import check_weight, preferential_coefficients, preferential_exact

__all__ = ["PreferentialThreshold", "preferential_threshold", "max_preferential_value", "band_decision"]


@dataclass(frozen=True)
class PreferentialThreshold:
    """Solution of eqs 18-20 (preferential rule, curve eq 14).

    g_max: g(n) of eq 15. threshold_mean: the non-trivial root of eq 18 in [-g, g] (the larger
    one if two lie there); band_width: alpha g / 4 (eq 20); threshold_initial/final:
    mean -/+ band/2 (the band is centred on the mean, "mid-point of the band", sec. 2.2.3.3;
    eq 19 is not imposed on it: see ``band`` below). present_count: smallest number of
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


# ------------------------------------------------------------------ the band decision
def _at_least(u_g: float, edge: float, g: float, exact_value) -> bool:
    """U_G >= edge for the exact U_G of eq 7: the float comparison where U_G's error bound
    decides it, else the exact value (``exact_value()``, an mpf) against the double ``edge``."""
    # U_G = a + b 2^p + c 2^q + d 2^(p+q) (rules.preferential_value) with |a| + |b| 2^p + ... <= g:
    # four roundings of terms bounded by g, and 2^p, 2^q, 2^(p+q) to an ulp each
    err = 16.0 * _EPS * (g + abs(edge))
    if abs(u_g - edge) > err:
        return u_g >= edge
    import mpmath

    from . import certify

    with mpmath.workdps(certify.DPS):
        return exact_value() >= mpmath.mpf(edge)


def band_decision(th: PreferentialThreshold, u_g: float, u) -> str:
    """The band decision of sec. 2.2.3.3 / eq 20 for one decision vector ``u`` (in
    ``th.encoding``) with U_G = ``u_g`` (eq 7, :func:`fusion_center.core.rules.preferential`):
    "H1" if U_G >= threshold_final, "H0" if U_G < threshold_initial, "undecided" inside the band
    (and when there is no band). Certified: the band edges are the doubles of ``th``; U_G's
    exact value (its integer counts and 2^p, 2^q in mpmath, :func:`rules.preferential_exact`) is
    compared with them wherever the float U_G lies within its rounding error of an edge, so the
    decision is that of the exact U_G -- the same comparison as
    :func:`fusion_center.core.exact_rates.preferential_error_rates` makes for its rates."""
    if th.threshold_initial is None or th.threshold_final is None:
        return "undecided"
    coefficients = []

    def exact_value():
        if not coefficients:
            coefficients.append(preferential_coefficients(u, th.encoding))
        return preferential_exact(coefficients[0], th.p, th.q)

    if _at_least(u_g, th.threshold_final, th.g_max, exact_value):
        return "H1"
    if not _at_least(u_g, th.threshold_initial, th.g_max, exact_value):
        return "H0"
    return "undecided"
