"""HEBTEM thresholds, eqs 16-20, against an mpmath reference built from the ORIGINAL equations.

The reference never calls fusion_center: it writes each curve exactly as printed (eqs 10-11,
12, 13, 14, with m, a, r of the chapter), integrates it in the linear U_G domain (closed-form
antiderivative at 60+ digits, cross-checked against mp.quad), and finds every sign change of

    H(lambda) = (integral_lambda^end f) / (end - lambda) - (1 - alpha)       [eqs 16, 17, 18]

on a grid of distances end - lambda (geometric near the trivial root, linear beyond), refined
with mp.findroot. Working precision grows with log10(1/xi) because the literal eq 13 cancels
about that many digits.
"""

import itertools
import math

import mpmath as mp
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from taxel_net.errors import ParameterError
from fusion_center.core.rules import g_of_n, preferential
from fusion_center.core.thresholds import (
    additive_threshold,
    max_preferential_value,
    multiplicative_threshold,
    preferential_threshold,
    solve_mean_deficit,
)

NS = [1, 2, 18, 57, 354, 355, 1000, 100_000, 1_000_000]
XIS = [1e-300, 1e-12, 0.003, 0.5, 0.999999]
LEVELS = [1e-9, 0.03, 0.473, 0.83, 1 - 1e-9]
REL = 1e-9


def _dps(xi):
    return 60 + int(-math.log10(xi)) + 20


# mean_deficit(d) on the grid of _roots, per curve (key: every input of the curve, at the working
# precision the curve fixes): the levels of GRID share a curve, and H = mean_deficit - level on the
# grid is the same subtraction whether or not the mean is remembered (the same mp numbers)
_GRID_MEANS: dict = {}


def _roots(H, span, curve_key=None, mean=None, level=None):
    """All sign changes of H(d), d = end - lambda in (0, span], refined (mp numbers).
    With ``curve_key``: H(d) is ``mean(d) - level`` and mean(d) on the grid is computed once per key."""
    span = mp.mpf(span)
    grid = {span * mp.mpf(10) ** (-mp.mpf(k) / 4) for k in range(0, 72)}
    grid |= {span * mp.mpf(i) / 96 for i in range(1, 97)}
    grid = sorted(grid)
    if curve_key is None:
        vals = [H(d) for d in grid]
    else:
        key = (curve_key, mp.mp.prec, span)
        if key not in _GRID_MEANS:
            _GRID_MEANS[key] = [mean(d) for d in grid]
        vals = [m - level for m in _GRID_MEANS[key]]
    found = []
    for (a, fa), (b, fb) in zip(zip(grid, vals), zip(grid[1:], vals[1:])):
        if fa == 0:
            found.append(a)
        elif fa * fb < 0:
            found.append(mp.findroot(H, (a, b), solver="anderson", verify=False))
    if vals[-1] == 0:
        found.append(grid[-1])
    return found


def ref_multiplicative(n, xi, beta):
    """Roots t = lambda/e^n of eq 16 with f = eqs 10-11, lambda in [-e^n, e^n]."""
    with mp.workdps(_dps(xi)):
        N, X, B = mp.mpf(n), mp.mpf(xi), mp.mpf(beta)
        E, e2n = mp.e**N, mp.e ** (2 * N)
        m = E * mp.log(1 / X) / (e2n - 1)  # eq 11a
        a = mp.e ** (-(e2n * mp.log(1 / X) / (e2n - 1)))  # eq 11b
        F = lambda x: a / m * mp.e ** (m * x)  # antiderivative of eq 10
        F_end, level = F(E), 1 - B

        def mean(w):  # w = (e^n - lambda)/e^n
            lam = E - E * w
            return (F_end - F(lam)) / (E - lam)

        def H(w):
            return mean(w) - level

        return [float(1 - w) for w in _roots(H, 2, ("multiplicative", n, xi), mean, level)]


def _pm1_parts(n, X):
    # (the constants of the curve evaluated once, at the working precision: the same numbers)
    half = mp.mpf(1) / 2
    r = (X + 1) + mp.sqrt(X * (X + 2))
    ln_r, slope = mp.log(r), (1 - half * r)
    f = lambda U: half * r ** (U / n) + slope / n * U  # eq 13
    F = lambda U: half * n * mp.e ** (ln_r * U / n) / ln_r + slope * U**2 / (2 * n)
    return f, F


def _01_parts(n, X):
    rate = mp.log(1 / X) / n
    f = lambda U: X * mp.e ** (rate * U)  # eq 12
    F = lambda U: X / rate * mp.e ** (rate * U)
    return f, F


def ref_additive(n, xi, alpha, encoding):
    """Roots lambda of eq 17 in [-n, n] (pm1, eq 13) or [0, n] (01, eq 12), ascending."""
    with mp.workdps(_dps(xi)):
        N, X, A = mp.mpf(n), mp.mpf(xi), mp.mpf(alpha)
        _, F = _pm1_parts(N, X) if encoding == "pm1" else _01_parts(N, X)
        F_end, level = F(N), 1 - A
        mean = lambda d: (F_end - F(N - d)) / d
        H = lambda d: mean(d) - level
        return sorted(float(N - d) for d in _roots(H, 2 * N if encoding == "pm1" else N,
                                                   ("additive", n, xi, encoding), mean, level))


def ref_g(n, p, q):
    """g(n) as eq 7 evaluated with every u_i = +1 (u_0 = u_{n+1} = 0)."""
    u = [0] + [1] * n + [0]
    return sum(mp.mpf(1 + u[i + 1]) ** p * mp.mpf(1 + u[i - 1]) ** q for i in range(1, n + 1))


def ref_preferential(n, xi, alpha, p, q):
    """Roots lambda_mean of eq 18 with f = eq 14 in [-g, g], ascending."""
    with mp.workdps(60):
        X, A = mp.mpf(xi), mp.mpf(alpha)
        g = ref_g(n, p, q) if n < 50 else (2**mp.mpf(p) + 2**mp.mpf(q)) + (n - 2) * 2 ** mp.mpf(p + q)
        F = lambda x: (1 - X) * x**3 / (3 * g**2) + X * x  # antiderivative of eq 14
        mean = lambda d: (F(g) - F(g - d)) / d
        H = lambda d: mean(d) - (1 - A)
        return sorted(float(g - d) for d in _roots(H, 2 * g, ("preferential", n, xi, p, q), mean, 1 - A)), float(g)


def _rel(a, b):
    return abs(a - b) / abs(b) if b != 0 else abs(a)


GRID = list(itertools.product(NS, XIS, LEVELS))


@pytest.mark.parametrize("n,xi,beta", GRID)
def test_multiplicative_matches_reference(n, xi, beta):
    ours = multiplicative_threshold(n, xi, beta)
    ref = ref_multiplicative(n, xi, beta)
    assert len(ours.scaled_thresholds) == len(ref)
    for t, t_ref, ln_t, count in zip(ours.scaled_thresholds, ref, ours.ln_thresholds, ours.present_counts):
        assert _rel(t, t_ref) <= REL, (t, t_ref)
        if t_ref > 0:
            assert ln_t is not None and abs(ln_t - (n + math.log(t_ref))) <= REL * max(1.0, abs(ln_t))
            # U_G = e^(2j - n) >= lambda and one taxel fewer is below it (checked in log space)
            ln_lam = n + math.log(t_ref)
            assert 2 * count - n >= ln_lam - 1e-9 * n
            assert count == 0 or 2 * (count - 1) - n < ln_lam + 1e-9 * n
        else:
            assert ln_t is None and count == 0


@pytest.mark.parametrize("encoding", ["pm1", "01"])
@pytest.mark.parametrize("n,xi,alpha", GRID)
def test_additive_matches_reference(n, xi, alpha, encoding):
    ours = additive_threshold(n, xi, alpha, encoding)
    ref = ref_additive(n, xi, alpha, encoding)
    assert len(ours.thresholds) == len(ref), (ours.thresholds, ref)
    for lam, lam_ref, count in zip(ours.thresholds, ref, ours.present_counts):
        assert _rel(lam, lam_ref) <= REL, (lam, lam_ref)
        value = (lambda j: 2 * j - n) if encoding == "pm1" else (lambda j: j)
        assert value(count) >= lam_ref - 1e-9 * n
        assert count == 0 or value(count - 1) < lam_ref + 1e-9 * n


PQ = [(1, 1), (0, 2), (0.5, 0), (0, 0), (2, 2)]


@pytest.mark.parametrize("n,xi,alpha", GRID)
def test_preferential_matches_reference(n, xi, alpha):
    p, q = PQ[(NS.index(n) + XIS.index(xi)) % len(PQ)]
    ours = preferential_threshold(n, xi, alpha, p, q)
    ref, g = ref_preferential(n, xi, alpha, p, q)
    assert _rel(ours.g_max, g) <= 1e-15
    assert ours.band_width == pytest.approx(alpha * g / 4, rel=1e-15)  # eq 20
    assert len(ours.mean_roots) == len(ref), (ours.mean_roots, ref)
    for lam, lam_ref in zip(ours.mean_roots, ref):
        assert _rel(lam, lam_ref) <= REL, (lam, lam_ref)
    if not ref:
        assert ours.threshold_mean is None and ours.present_count is None
        return
    assert _rel(ours.threshold_mean, ref[-1]) <= REL, (ours.threshold_mean, ref)
    assert ours.threshold_initial == pytest.approx(ours.threshold_mean - ours.band_width / 2, rel=1e-15)
    assert ours.threshold_final == pytest.approx(ours.threshold_mean + ours.band_width / 2, rel=1e-15)
    j = ours.present_count
    assert max_preferential_value(n, j, p, q) >= ours.threshold_mean
    assert all(max_preferential_value(n, i, p, q) < ours.threshold_mean for i in range(max(0, j - 12), j))


@pytest.mark.parametrize("n,xi", [(57, 0.003), (1, 1e-300), (1_000_000, 1e-12), (2, 0.999999)])
def test_reference_antiderivatives_agree_with_quadrature(n, xi):
    """The reference's closed-form integrals equal mp.quad of the printed curves (linear domain)."""
    with mp.workdps(_dps(xi)):
        n, X = mp.mpf(n), mp.mpf(xi)
        for f, F, lo in (_pm1_parts(n, X) + (-n,), _01_parts(n, X) + (mp.mpf(0),)):
            for a in (lo, n / 3, n - n / 1000):  # also near the right end, where F(n) - F(a) cancels
                assert mp.almosteq(mp.quad(f, [a, n]), F(n) - F(a), rel_eps=mp.mpf(10) ** -30)
        E = mp.e**n
        m = E * mp.log(1 / X) / (mp.e ** (2 * n) - 1)
        a = mp.e ** (-(mp.e ** (2 * n) * mp.log(1 / X) / (mp.e ** (2 * n) - 1)))
        f = lambda x: a * mp.e ** (m * x)
        for lam in (-E, E / 2, E - E / 1000):
            assert mp.almosteq(mp.quad(f, [lam, E]) / E, (a / m * (mp.e ** (m * E) - mp.e ** (m * lam))) / E,
                               rel_eps=mp.mpf(10) ** -30)


def test_chapter_examples_computed_from_the_equations():
    # sec. 6.3: n = 57, xi = 0.003. Printed: +49.753 (alpha = 0.03), -49.753 (alpha = 0.473),
    # 1.663e-20 = e^-45.543 (beta = 0.83). The equations give +50.18, -50.93 and a root
    # t = lambda/e^n = -0.0097 (docs/chapter-notes.md); the reference agrees with the code.
    plus = additive_threshold(57, 0.003, 0.03)
    minus = additive_threshold(57, 0.003, 0.473)
    assert plus.thresholds == pytest.approx(ref_additive(57, 0.003, 0.03, "pm1"), rel=1e-12)
    assert minus.thresholds == pytest.approx(ref_additive(57, 0.003, 0.473, "pm1"), rel=1e-12)
    assert 50.0 < plus.thresholds[0] < 50.3 and -51.1 < minus.thresholds[0] < -50.8
    mult = multiplicative_threshold(57, 0.003, 0.83)
    assert mult.scaled_thresholds == pytest.approx(ref_multiplicative(57, 0.003, 0.83), rel=1e-12)
    assert -0.011 < mult.scaled_thresholds[0] < -0.009
    # sec. 7.2, eq 37: 7.187e-5 l^3 - 0.517 l + 12.558 = 0 for xi = 0.003, n = 18, alpha = 0.48,
    # g = 68; printed root 27.02, band 8.16
    pref = preferential_threshold(18, 0.003, 0.48, 1, 1)
    cubic_root = mp.findroot(lambda x: mp.mpf("0.997") / (3 * 68**2) * x**3 - mp.mpf("0.517") * x
                             + 68 * (mp.mpf("0.52") - mp.mpf("0.997") / 3 - mp.mpf("0.003")), 27)
    assert pref.threshold_mean == pytest.approx(float(cubic_root), rel=1e-12)
    assert pref.threshold_mean == pytest.approx(27.036, abs=1e-3)
    assert pref.band_width == pytest.approx(8.16, rel=1e-12)
    # the chapter's own rounded coefficients put the root at 27.038, not 27.02 either
    printed = mp.findroot(lambda x: mp.mpf("7.187e-5") * x**3 - mp.mpf("0.517") * x + mp.mpf("12.558"), 27)
    assert float(printed) == pytest.approx(27.038, abs=1e-3)


@pytest.mark.parametrize("n", range(1, 11))
@pytest.mark.parametrize("p,q", [(0, 0), (1, 1), (2, 0), (0, 0.5), (1.5, 2), (2, 2)])
@pytest.mark.parametrize("encoding", ["pm1", "01"])
def test_max_preferential_value_is_the_exhaustive_maximum(n, p, q, encoding):
    absent = -1 if encoding == "pm1" else 0
    best = {}
    for u in itertools.product([absent, 1], repeat=n):
        j = u.count(1)
        best[j] = max(best.get(j, -math.inf), preferential(list(u), p, q, encoding))
    for j in range(n + 1):
        assert max_preferential_value(n, j, p, q, encoding) == pytest.approx(best[j], abs=1e-12)
    # monotone in the present count (what present_count's search relies on): strictly from 2 on;
    # 0 -> 1 may drop only for n = 2 on {-1,+1} with p, q > 0 ((-1,-1) gives 0, (1,-1) gives -2^q)
    for j in range(2, n):
        assert best[j + 1] > best[j]
    if n >= 2:
        assert best[2] >= best[1]
        if n == 2 and encoding == "pm1" and p > 0 and q > 0:
            assert best[1] < best[0] == 0
        else:
            assert best[1] >= best[0]


def _run_vector(n, left, run, encoding):
    absent = -1 if encoding == "pm1" else 0
    return [absent] * left + [1] * run + [absent] * (n - left - run)


def _best_run_by_eq7(n, run, p, q, encoding, middle):
    """max of rules.preferential (eq 7, numpy) over one-run placements: 0, 1, 2 taxels from either
    end and one placement `middle` in between (all placements with >= 2 absent taxels on both
    sides have the same value: moving the run only moves bulk absent terms)."""
    free = n - run
    lefts = {a for a in (0, 1, 2, middle, free - 2, free - 1, free) if 0 <= a <= free}
    return max(preferential(_run_vector(n, a, run, encoding), p, q, encoding) for a in lefts)


weights_with_ends = st.one_of(st.sampled_from([0.0, 1.0, 2.0, 5e-324]), st.floats(0, 2))


@settings(max_examples=150, deadline=None)
@given(st.integers(1, 10_000), st.data(), weights_with_ends, weights_with_ends, st.sampled_from(["pm1", "01"]))
def test_max_preferential_value_closed_form_against_eq7_run_vectors(n, data, p, q, encoding):
    """The closed form of max_preferential_value against eq 7 evaluated on the run vectors."""
    run = data.draw(st.integers(0, n))
    middle = data.draw(st.integers(0, n - run))
    value = _best_run_by_eq7(n, run, p, q, encoding, middle)
    tol = 1e-12 * max(1.0, g_of_n(n, p, q))
    assert max_preferential_value(n, run, p, q, encoding) == pytest.approx(value, rel=1e-12, abs=tol)
    if 2 <= run < n:  # increasing in the present count from 2 on (strictly unless 2^p or 2^q rounds to 1)
        assert _best_run_by_eq7(n, run + 1, p, q, encoding, middle) >= value


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 10_000), st.floats(1e-6, 0.74), weights_with_ends, weights_with_ends,
       st.sampled_from(["pm1", "01"]), st.data())
def test_preferential_present_count_against_eq7(n, alpha, p, q, encoding, data):
    """present_count j: some vector with j present taxels reaches lambda_mean (eq 7 on a run
    vector), no vector with j - 1 does (M increasing from 2 on; 0 and 1 checked directly)."""
    res = preferential_threshold(n, 0.003, alpha, p, q, encoding)
    assert res.g_max == g_of_n(n, p, q)
    lam, j = res.threshold_mean, res.present_count
    tol = 1e-12 * max(1.0, res.g_max)
    middle = data.draw(st.integers(0, n))
    best = lambda m: _best_run_by_eq7(n, m, p, q, encoding, min(middle, n - m))
    if j is None:
        assert best(n) < lam + tol
        return
    assert best(j) >= lam - tol
    for below in {0, 1, j - 1} & set(range(j)):
        assert best(below) < lam + tol


@pytest.mark.parametrize("p,q", [(1, 1), (0, 2), (0.5, 0), (0, 0), (2, 2)])
def test_preferential_present_count_linear_regime(p, q):
    # large n: the O(1) shortcut must agree with a scan of max_preferential_value
    n = 200
    for alpha in (0.01, 0.2, 0.5, 0.7):
        res = preferential_threshold(n, 0.003, alpha, p, q)
        scan = next(j for j in range(n + 1) if max_preferential_value(n, j, p, q) >= res.threshold_mean)
        assert res.present_count == scan


def test_solve_mean_deficit_limits():
    # D(z) = 1 - (1 - e^-z)/z: D ~ z/2 for small z, D ~ 1 - 1/z for large z
    z, _ = solve_mean_deficit(1e-12)
    assert z == pytest.approx(2e-12, rel=1e-11)
    z, _ = solve_mean_deficit(1 - 2**-40)
    assert z == pytest.approx(2.0**40, rel=1e-12)


levels = st.floats(min_value=1e-12, max_value=1 - 1e-12)
xis = st.floats(min_value=-300, max_value=-1e-6).map(lambda e: 10.0**e)
ns = st.integers(min_value=1, max_value=1_000_000)


@settings(max_examples=150, deadline=None)
@given(ns, xis, levels, levels)
def test_stricter_level_gives_higher_threshold(n, xi, l1, l2):
    """sec. 2.2.3.4: a stricter (smaller) alpha or beta is a tougher test for accepting H1."""
    assume(l1 < l2)
    m1, m2 = multiplicative_threshold(n, xi, l1), multiplicative_threshold(n, xi, l2)
    if m2.scaled_thresholds:
        assert m1.scaled_thresholds and m1.scaled_thresholds[0] >= m2.scaled_thresholds[0]
        assert m1.present_counts[0] >= m2.present_counts[0]
    for enc in ("pm1", "01"):
        a1, a2 = additive_threshold(n, xi, l1, enc), additive_threshold(n, xi, l2, enc)
        if a2.thresholds and a1.thresholds:
            assert max(a1.thresholds) >= max(a2.thresholds)
            assert max(a1.present_counts) >= max(a2.present_counts)
        if enc == "01" and a2.thresholds:
            assert a1.thresholds
    p1, p2 = preferential_threshold(n, xi, l1, 1, 1), preferential_threshold(n, xi, l2, 1, 1)
    if p2.threshold_mean is not None:
        assert p1.threshold_mean >= p2.threshold_mean
        assert p1.present_count >= p2.present_count


weights = st.floats(min_value=0, max_value=2)


@settings(max_examples=100, deadline=None)
@given(st.integers(min_value=2, max_value=10_000), weights, weights, weights, st.floats(0.01, 0.7))
def test_preferential_scales_with_g(n, p1, p2, q, alpha):
    """eq 15: g grows with p and q, and eqs 18-20 scale with g (lambda_mean/g depends on xi, alpha only)."""
    lo, hi = sorted((p1, p2))
    a, b = preferential_threshold(n, 0.003, alpha, lo, q), preferential_threshold(n, 0.003, alpha, hi, q)
    c = preferential_threshold(n, 0.003, alpha, q, hi)
    assert a.g_max <= b.g_max and a.band_width <= b.band_width
    assert b.g_max == pytest.approx(c.g_max, rel=1e-14)  # eq 15 is symmetric in p, q
    assert a.threshold_mean / a.g_max == pytest.approx(b.threshold_mean / b.g_max, rel=1e-14)
    # |lambda_mean| grows with g (lambda_mean < 0 once alpha > 2(1 - xi)/3)
    assert abs(a.threshold_mean) <= abs(b.threshold_mean) * (1 + 1e-14)


@pytest.mark.parametrize("call,field", [
    (lambda: multiplicative_threshold(0, 0.1, 0.5), "n"),
    (lambda: multiplicative_threshold(3.5, 0.1, 0.5), "n"),
    (lambda: multiplicative_threshold(5, 0.0, 0.5), "xi"),
    (lambda: multiplicative_threshold(5, 0.1, 1.0), "beta"),
    (lambda: multiplicative_threshold(5, 0.1, float("nan")), "beta"),
    (lambda: additive_threshold(5, float("nan"), 0.5), "xi"),
    (lambda: additive_threshold(5, 0.1, 0.0), "alpha"),
    (lambda: additive_threshold(5, 0.1, 0.5, "binary"), "tuple"),
    (lambda: preferential_threshold(5, 0.1, 0.5, 2.5, 1), "p"),
    (lambda: preferential_threshold(5, 0.1, 0.5, 1, -1), "q"),
    (lambda: preferential_threshold(5, 0.1, -0.5, 1, 1), "alpha"),
])
def test_bad_inputs_name_the_parameter(call, field):
    with pytest.raises(ParameterError, match=f"^{field}="):
        call()


def test_no_root_is_a_result():
    assert additive_threshold(57, 0.003, 1 - 1e-9).thresholds == ()
    assert additive_threshold(57, 0.003, 0.99, "01").thresholds == ()
    assert multiplicative_threshold(57, 0.999999, 0.5).scaled_thresholds == ()
    none = preferential_threshold(18, 0.003, 0.9, 1, 1)
    assert none.threshold_mean is None and none.g_max == 68


@pytest.mark.parametrize("n", [1, 57, 1_000_000])
@pytest.mark.parametrize("xi,alpha", [(0.999999, 0.36), (0.999999, 0.38), (0.999999, 0.4), (0.5, 0.42),
                                      (0.5, 0.425), (0.3, 0.4), (0.26, 0.45), (0.9, 0.3)])
def test_additive_pm1_two_roots_when_xi_above_quarter(n, xi, alpha):
    """For xi > 1/4 eq 13 dips below its value at -n, so eq 17 can have two roots (sec. 2.2.3.2)."""
    ours = additive_threshold(n, xi, alpha, "pm1")
    ref = ref_additive(n, xi, alpha, "pm1")
    assert len(ours.thresholds) == len(ref)
    for lam, lam_ref in zip(ours.thresholds, ref):
        assert _rel(lam, lam_ref) <= REL


@pytest.mark.parametrize("n,xi,alpha", [(18, 0.003, 0.67), (18, 0.003, 0.74), (1000, 0.5, 0.36),
                                        (5, 0.999999, 0.7e-6)])
def test_preferential_second_root_of_eq18(n, xi, alpha):
    """For 2 <= 3 alpha/(1 - xi) < 9/4 eq 18 has a second non-trivial root in [-g, -g/2]."""
    ours = preferential_threshold(n, xi, alpha, 1, 1)
    ref, _ = ref_preferential(n, xi, alpha, 1, 1)
    assert len(ref) == 2 and len(ours.mean_roots) == 2
    for lam, lam_ref in zip(ours.mean_roots, ref):
        assert _rel(lam, lam_ref) <= REL
    assert ours.threshold_mean == ours.mean_roots[-1]


def test_two_roots_do_occur():
    assert len(additive_threshold(57, 0.999999, 0.38).thresholds) == 2


@settings(max_examples=40, deadline=None)
@given(st.floats(0.2501, 0.999999), st.floats(0.2, 0.45), st.sampled_from([1, 57, 1_000_000]))
@example(0.999999, 0.36, 57)
@example(0.9554284882838996, 0.4039508811908412, 57)
def test_additive_pm1_xi_above_quarter_reference_and_iteration_count(xi, alpha, n):
    """Two roots, one, or none near the tangent case (sec. 2.2.3.2) against the mpmath reference,
    and the solver's Newton iterations end at the rounding floor instead of flipping between two
    neighbouring floats up to the iteration limit (100; e.g. xi = 0.999999, alpha = 0.36 took 112)."""
    info = {}
    ours = additive_threshold(n, xi, alpha, "pm1", info=info)
    ref = ref_additive(n, xi, alpha, "pm1")
    assert len(ours.thresholds) == len(ref), (ours.thresholds, ref)
    for lam, lam_ref in zip(ours.thresholds, ref):
        assert abs(lam - lam_ref) <= REL * max(abs(lam_ref), 1e-3 * n)
    assert info["evaluations"] <= 40


def test_d_series_and_closed_forms_against_mpmath():
    """D(z) = 1 - (1 - e^-z)/z and its first two derivatives (thresholds module doc): the written-out
    Taylor series (z <= 1/2) and the expm1 forms (z > 1/2) against mpmath, and the fused
    evaluations equal the single ones."""
    from fusion_center.core import thresholds as th

    zs = [1e-300, 1e-30, 1e-8, 0.01, 0.1, 0.25, 0.4999, 0.5, math.nextafter(0.5, 1), 0.51, 0.75, 1.3, 2.6, 30.0]
    for z in zs:
        with mp.workdps(60 + 3 * max(0, int(-math.log10(z)))):
            x = mp.mpf(z)
            em1 = mp.expm1(-x)
            ref = ((x + em1) / x, -(em1 + x * mp.e ** -x) / x**2,
                   mp.e ** -x / x + 2 * mp.e ** -x / x**2 + 2 * em1 / x**3)
            # D'' cancels a factor ~40 just above 1/2 (it only steers the search for Q's maximum)
            for ours, exact, ulps in zip((th._d(z), th._dprime(z), th._dsecond(z)), ref, (4, 4, 64)):
                assert abs(ours - exact) <= ulps * 2.0**-52 * abs(exact), (z, ours, exact)
        assert th._d_and_dprime(z) == (th._d(z), th._dprime(z))
        assert th._dprime_and_dsecond(z) == (th._dprime(z), th._dsecond(z))
