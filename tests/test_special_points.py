"""Part A of the numerics issue: the thresholds (eqs 16-18), counts and decisions at inputs a few
ulps from the special points -- the eq-17 tangency, the domain edges (lambda = -n, lambda = 0
on {0,1}, t = -1), attainable U_G values (present counts), a = 2 and 9/4 of eq 18 -- against
independent references written here from the printed equations in mpmath (never the code's
own certify module), and the CLI's handling of values that do not survive parsing.

References:
* eq 17 on {-1,+1}: H(lambda) = mean of eq 13 over [lambda, n] - (1 - alpha) with the closed
  antiderivative of eq 13 as printed (r, c of the chapter), 90 digits; its maximum by
  mp.findroot on H', both roots by bisection on either side.
* domain edges: the mean of the curve over the whole domain in closed form (a root lies in the
  domain iff 1 - level >= that mean on a monotone branch).
* eq 18: the cubic (1 - xi)(g^3 - x^3)/(3 g^2) + (xi - 1 + alpha)(g - x) = 0 by mp.polyroots.
"""

from __future__ import annotations

import functools
import json
import math
from fractions import Fraction

import mpmath as mp
import numpy as np
import pytest

from fusion_center.cli import main
from fusion_center.core import baselines, rules
from fusion_center.core.thresholds import (
    additive_threshold,
    max_preferential_value,
    multiplicative_threshold,
    preferential_threshold,
)

DPS = 90


def ulps(x: float, k: int) -> float:
    for _ in range(abs(k)):
        x = math.nextafter(x, math.inf if k > 0 else -math.inf)
    return x


# ----------------------------------------------------------------------- references (mpmath)
def per_precision(make):
    """``make()`` evaluated once per working precision: a constant formed where it is used, at
    the precision it is used with (mp.diff raises the precision inside H), so the same number as
    forming it at every use."""
    cache = {}

    def get():
        prec = mp.mp.prec
        if prec not in cache:
            cache[prec] = make()
        return cache[prec]
    return get


def eq13_parts(n, xi):
    N, X = mp.mpf(n), mp.mpf(xi)
    r = (X + 1) + mp.sqrt(X * (X + 2))
    # F(U) = 0.5 N r^(U/N) / ln r + (1 - r/2) U^2 / (2 N), the antiderivative of eq 13; 0.5 N,
    # ln r and 1 - r/2 formed once per precision (not parsed and recomputed at every call)
    consts = per_precision(lambda: (mp.mpf("0.5") * N, mp.log(r), 1 - r / 2))

    def F(U):
        half_n, ln_r, slope = consts()
        return half_n * r ** (U / N) / ln_r + slope * U**2 / (2 * N)
    return N, F


def dps_for(xi):
    return DPS + int(max(0.0, -math.log10(xi)))  # the literal eq 13 cancels ~log10(1/xi) digits


def ref_eq17_pm1(n, xi, alpha):
    """Every root of eq 17 on {-1,+1} in [-n, n), ascending (mp numbers), exact float inputs."""
    with mp.workdps(dps_for(xi)):
        N, F = eq13_parts(n, xi)
        A = mp.mpf(alpha)
        ends = per_precision(lambda: (F(N), 1 - A))  # F(n) and the level, once per precision
        H = lambda lam: (ends()[0] - F(lam)) / (N - lam) - ends()[1]  # decreasing-then-increasing in lam
        dH = lambda lam: mp.diff(H, lam)
        lo, hi = -N, N - N / 10**6
        # H is convex-like in lambda here: its minimum (the tangency of Q) by bisection on H'
        if dH(lo) >= 0:
            lam_min = lo
        else:
            a, b = lo, hi
            if dH(b) <= 0:
                lam_min = b
            else:
                for _ in range(400):
                    m = (a + b) / 2
                    if dH(m) < 0:
                        a = m
                    else:
                        b = m
                lam_min = (a + b) / 2
        # mean over [lam, n] = 1 - alpha  <=>  H = 0; H(n-) = f(n) - (1 - alpha) = alpha > 0
        roots = []
        h_min = H(lam_min)
        if h_min > 0:
            return [], h_min
        def bisect(a, b):
            fa = H(a)
            for _ in range(600):
                m = (a + b) / 2
                fm = H(m)
                if (fm > 0) == (fa > 0):
                    a, fa = m, fm
                else:
                    b = m
            return (a + b) / 2
        if lam_min > lo and H(lo) <= 0:
            pass  # no sign change left of the minimum inside the domain
        elif lam_min > lo:
            roots.append(bisect(lo, lam_min))
        roots.append(bisect(lam_min, N - N / 10**12))
        return roots, h_min


def pm1_count(n, lam):
    return min(n, max(0, math.ceil((n + Fraction(lam)) / 2))) if isinstance(lam, float) else \
        min(n, max(0, int(mp.ceil((n + lam) / 2))))


# ------------------------------------------------------------------------------ eq 17 tangency
@pytest.mark.parametrize("alpha", [0.400480312419913, 0.4004803124199129, ulps(0.400480312419913, 1),
                                   ulps(0.400480312419913, 3), ulps(0.400480312419913, -30), 0.4004803])
def test_eq17_tangency_both_roots_no_crash(alpha):
    n, xi = 57, 0.9
    ours = additive_threshold(n, xi, alpha, "pm1")
    ref, h_min = ref_eq17_pm1(n, xi, alpha)
    assert len(ours.thresholds) == len(ref), (ours.thresholds, ref)
    for lam, lam_ref in zip(ours.thresholds, ref):
        assert abs(lam - float(lam_ref)) <= 1e-9 * n
    for lam, count in zip(ours.thresholds, ours.present_counts):
        assert count == pm1_count(n, lam)  # consistent with the lambda returned
    for count, lam_ref in zip(ours.present_counts, ref):
        assert count == pm1_count(n, lam_ref)  # and exact
    if len(ref) == 2 and abs(h_min) < 1e-8:
        assert ours.near_double_root
    if alpha == 0.4004803124199129:  # the issue: a spurious far root at +35.1 before
        assert all(abs(lam + 21.887) < 1e-3 for lam in ours.thresholds)


def test_eq17_edge_lambda_minus_n_not_invented():
    """n = 57, xi = 0.9: the second root reaches lambda = -n at alpha = Q(2); inputs around it."""
    n, xi = 57, 0.9
    with mp.workdps(DPS):
        N, F = eq13_parts(n, xi)
        alpha_edge = 1 - (F(N) - F(-N)) / (2 * N)  # mean over [-n, n] = 1 - alpha
    base = float(alpha_edge)
    for k in range(-4, 5):
        alpha = ulps(base, k)
        ours = additive_threshold(n, xi, alpha, "pm1")
        expect_edge_root = mp.mpf(alpha) >= alpha_edge  # H(-n) <= 0: the second root is inside
        assert (len(ours.thresholds) == 2) == bool(expect_edge_root), (k, ours.thresholds)
        assert all(lam >= -n for lam in ours.thresholds)
    # the case
    ours = additive_threshold(57, 0.9, 0.3574789989126017, "pm1")
    assert len(ours.thresholds) == (2 if mp.mpf(0.3574789989126017) >= alpha_edge else 1)


def test_eq17_01_edge_lambda_zero():
    """{0,1}: a root in [0, n] iff alpha <= 1 - mean of eq 12 over [0, n] = 1 - (1 - xi)/ln(1/xi)."""
    n, xi = 40, 0.01
    with mp.workdps(DPS):
        X = mp.mpf(xi)
        alpha_edge = 1 - (1 - X) / mp.log(1 / X)
    for k in range(-4, 5):
        alpha = ulps(float(alpha_edge), k)
        ours = additive_threshold(n, xi, alpha, "01")
        assert (len(ours.thresholds) == 1) == bool(mp.mpf(alpha) <= alpha_edge), k
        for lam, count in zip(ours.thresholds, ours.present_counts):
            assert lam >= 0 and count == max(0, math.ceil(Fraction(lam)))


def test_eq16_edge_t_minus_one():
    """Eq 16: a root with t >= -1 iff beta <= 1 - mean of eqs 10-11 over [-e^n, e^n]."""
    n, xi = 3, 0.2
    with mp.workdps(DPS):
        N, X = mp.mpf(n), mp.mpf(xi)
        E = mp.e**N
        m = mp.log(1 / X) / (E - 1 / E)  # eq 11a: the fit through (e^-n, xi) and (e^n, 1)
        a = mp.e ** (-m * E)  # eq 11b
        assert abs(a * mp.e ** (m / E) - X) < mp.mpf(10) ** -50  # p(e^-n) = xi
        mean_full = a / m * (mp.e ** (m * E) - mp.e ** (-m * E)) / (2 * E)
        assert abs(a * mp.e ** (m * E) - 1) < mp.mpf(10) ** -50  # p(e^n) = 1
        beta_edge = 1 - mean_full
    for k in range(-4, 5):
        beta = ulps(float(beta_edge), k)
        ours = multiplicative_threshold(n, xi, beta)
        assert (len(ours.scaled_thresholds) == 1) == bool(mp.mpf(beta) <= beta_edge), k
        assert all(t >= -1 for t in ours.scaled_thresholds)


def test_eq16_zero_crossing_counts():
    """t crosses 0 at beta = D(L'); around it the count follows the exact t (the issue: t = 0,
    count 0 where t = 2.0e-16 and 2j - n >= n + ln t need j = 39)."""
    n, xi = 57, 0.5
    with mp.workdps(DPS):
        L = mp.log(2) / (1 - mp.e ** (-2 * n))

        def exact_t(beta):
            B = mp.mpf(beta)
            z = mp.findroot(lambda z: 1 - (1 - mp.e**-z) / z - B, 1.5)
            return 1 - z / L

        for beta in [0.27865247955551825] + [ulps(0.27865247955551825, k) for k in (-3, -1, 2, 5)]:
            ours = multiplicative_threshold(n, xi, beta)
            t = exact_t(beta)
            (t_ours,), (ln_ours,), (count,) = ours.scaled_thresholds, ours.ln_thresholds, ours.present_counts
            assert abs(t_ours - float(t)) <= 1e-13
            if t > 0:
                ln_lam = n + mp.log(t)
                expect = min(n, max(0, int(mp.ceil((n + ln_lam) / 2))))
                assert ln_ours is not None and count == expect
                assert count == min(n, max(0, math.ceil((n + Fraction(ln_ours)) / 2)))
            else:
                assert ln_ours is None and count == 0
    assert multiplicative_threshold(57, 0.5, 0.27865247955551825).present_counts == (39,)


@pytest.mark.parametrize("n", [2, 10**6, 10**6 + 1])
def test_eq17_counts_at_attainable_values(n):
    """alpha placed so that lambda lies within rounding of an attainable U_G = 2j - n."""
    xi = 1e-300 if n == 2 else 0.003
    with mp.workdps(dps_for(xi)):
        N, F = eq13_parts(n, xi)
        target = mp.mpf(n % 2)  # an attainable value near the middle (0 or 1)
        alpha0 = 1 - (F(N) - F(target)) / (N - target)  # lambda = target exactly
    for k in range(-3, 4):
        alpha = ulps(float(alpha0), k)
        ours = additive_threshold(n, xi, alpha, "pm1")
        ref, _ = ref_eq17_pm1(n, xi, alpha)
        assert len(ours.thresholds) == len(ref) == 1
        lam = ours.thresholds[0]
        assert abs(lam - float(ref[0])) <= 1e-13 * n
        assert ours.present_counts[0] == pm1_count(n, ref[0]) == pm1_count(n, lam), (k, lam, ref[0])
    # the case: lambda = 2.2e-16 needs both taxels (count 2), not 1
    res = additive_threshold(2, 1e-300, 0.24999999999999997, "pm1")
    assert res.present_counts[0] == pm1_count(2, res.thresholds[0])


# ---------------------------------------------------------------------------------- eq 18
def ref_eq18(n, xi, alpha, p, q):
    """Roots of eq 18's cubic in [-g, g) (the trivial root g removed), ascending, mp."""
    with mp.workdps(DPS):
        X, A = mp.mpf(xi), mp.mpf(alpha)
        g = (2 ** mp.mpf(p) + 2 ** mp.mpf(q)) + (n - 2) * 2 ** (mp.mpf(p) + mp.mpf(q))
        # (1 - xi)(g^3 - x^3)/(3 g^2) + (xi - 1 + alpha)(g - x), coefficients of x^3..x^0
        c3 = -(1 - X) / (3 * g**2)
        c1 = -(X - 1 + A)
        c0 = (1 - X) * g / 3 + (X - 1 + A) * g
        roots = mp.polyroots([c0, c1, 0, c3], maxsteps=400, extraprec=400, asc=True)
        real = sorted(mp.re(r) for r in roots if abs(mp.im(r)) <= mp.mpf(10) ** -40 * g)
        found = [r for r in real if -g <= r and abs(r - g) > mp.mpf(10) ** -30 * g]
        return found, g


@pytest.mark.parametrize("xi", [0.7, 0.003, 0.5])
@pytest.mark.parametrize("which", ["a=2", "a=9/4"])
def test_eq18_special_a(xi, which):
    n, p, q = 57, 1.0, 1.0
    x = Fraction(xi)
    alpha0 = float(2 * (1 - x) / 3) if which == "a=2" else float(3 * (1 - x) / 4)
    for k in range(-3, 4):
        alpha = ulps(alpha0, k)
        ours = preferential_threshold(n, xi, alpha, p, q)
        ref, g = ref_eq18(n, xi, alpha, p, q)
        assert len(ours.mean_roots) == len(ref), (k, ours.mean_roots, ref)
        for lam, lam_ref in zip(ours.mean_roots, ref):
            assert abs(lam - float(lam_ref)) <= 1e-9 * float(g)
        if which == "a=9/4" and ref:
            assert ours.near_double_root


def test_eq18_double_root_reported_twice():
    ours = preferential_threshold(57, 0.7, 0.225, 1, 1)
    ref, _ = ref_eq18(57, 0.7, 0.225, 1, 1)
    assert len(ref) == 2 and len(ours.mean_roots) == 2 and ours.near_double_root
    for lam, lam_ref in zip(ours.mean_roots, ref):
        assert abs(lam - float(lam_ref)) <= 1e-9 * 224


def test_eq19_band():
    """The eq-19 band: width alpha g/4 (eq 20) and mean of eq 14 over it = 1 - alpha (eq 19),
    checked by mp.quad of the printed curve; the centred band of sec. 7.2 does not satisfy it."""
    n, xi, alpha = 18, 0.003, 0.48
    res = preferential_threshold(n, xi, alpha, 1, 1, band="eq19")
    g = 68.0
    f = lambda x: (1 - mp.mpf(xi)) / g**2 * x**2 + xi
    assert len(res.eq19_bands) == 2
    for lo, hi in res.eq19_bands:
        assert abs((hi - lo) - alpha * g / 4) < 1e-12
        assert abs(mp.quad(f, [lo, hi]) / (hi - lo) - (1 - alpha)) < 1e-12
    assert (res.threshold_initial, res.threshold_final) == res.eq19_bands[-1]
    centred = preferential_threshold(n, xi, alpha, 1, 1)
    lo, hi = centred.threshold_initial, centred.threshold_final
    assert abs(mp.quad(f, [lo, hi]) / (hi - lo) - mp.mpf("0.162")) < 1e-3  # not 1 - alpha = 0.52


@pytest.mark.parametrize("encoding", ["pm1", "01"])
def test_preferential_count_exact_for_returned_mean(encoding):
    """present_count = the smallest m such that SOME vector with m present taxels reaches the
    returned lambda_mean, with U_G of every vector (all 2^n, n <= 9) evaluated in mpmath."""
    rng = np.random.default_rng(7)
    absent = -1 if encoding == "pm1" else 0
    for n in (2, 3, 5, 9):
        vectors = np.array(np.meshgrid(*[[absent, 1]] * n)).T.reshape(-1, n)
        for _ in range(6):
            p, q = (float(v) for v in rng.uniform(0, 2, 2))
            alpha = float(rng.uniform(0.01, 0.7))
            res = preferential_threshold(n, 0.1, alpha, p, q, encoding)
            if res.threshold_mean is None:
                continue
            with mp.workdps(40):
                best = {}
                for u in vectors:
                    m = int(np.sum(u == 1))
                    val = rules.preferential_exact(rules.preferential_coefficients(u, encoding), p, q)
                    best[m] = max(best.get(m, -mp.inf), val)
                expect = next((m for m in range(n + 1) if best[m] >= mp.mpf(res.threshold_mean)), None)
            assert res.present_count == expect, (n, p, q, alpha)


def test_preferential_value_never_exceeds_g():
    rng = np.random.default_rng(3)
    for _ in range(500):
        n = int(rng.integers(1, 300))
        p, q = (float(v) for v in rng.uniform(0, 2, 2))
        assert rules.preferential([1] * n, p, q, "pm1") == rules.g_of_n(n, p, q)
        assert max_preferential_value(n, n, p, q) <= rules.g_of_n(n, p, q)


# ------------------------------------------------------------------------------------- N-P
@functools.lru_cache(maxsize=2)
def binomial_pmf_60(n, pf):
    """[C(n, k) pf^k (1 - pf)^(n - k) for k = 0..n] in mpmath at 60 digits (a tuple)."""
    with mp.workdps(60):
        PF = mp.mpf(pf)
        return tuple(mp.binomial(n, k) * PF**k * (1 - PF) ** (n - k) for k in range(n + 1))


@pytest.mark.parametrize("alpha", [0.999999999, 1 - 1e-13, 0.7, 1e-12, 0.3])
def test_np_gamma_exact_near_0_and_1(alpha):
    n, pd, pf = 1000, 0.02, 0.3
    rule = baselines.neyman_pearson_fusion(np.full(n, pd), np.full(n, pf), alpha)
    with mp.workdps(60):
        A = mp.mpf(alpha)
        p0 = binomial_pmf_60(n, pf)  # the same for every alpha: formed once
        # pd < pf: Lambda decreases with K, atoms in decreasing order are K = 0, 1, ...
        c = mp.mpf(0)
        for k in range(n + 1):
            if c + p0[k] >= A:
                break
            c += p0[k]
        gamma = (A - c) / p0[k]
    assert rule.count_threshold == k
    assert abs(rule.gamma - float(gamma)) <= 1e-9


# ------------------------------------------------------------------------------------- CLI
def _run(capsys, *argv):
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.mark.parametrize("argv, words", [
    (["threshold", "--rule", "additive", "--n", "57", "--xi", "0.9", "--alpha", "0.400480312419913"], None),
    (["fuse", "--rule", "additive", "--tuple", "01", "--u=1e-400"], ["u[0]", "1e-400"]),
    (["threshold", "--rule", "preferential", "--n", "5", "--xi", "0.1", "--alpha", "0.1", "--p=1e-400"],
     ["p=", "1e-400", "underflows", "[0, 2]"]),
    (["threshold", "--rule", "additive", "--n", "57", "--xi", "1e400", "--alpha", "0.1"], ["xi=", "overflows", "(0, 1)"]),
    (["threshold", "--rule", "additive", "--n=9007199254740993", "--xi", "0.1", "--alpha", "0.1"],
     ["n=", "9007199254740993", "2^53"]),
    (["fuse", "--rule", "preferential", "--u", "1,1,-1", "--p="], ["p=", "empty", "[0, 2]"]),
    (["fuse", "--rule", "llr", "--u", "1,1", "--pd", "0.9", "--pf", "0.1", "--prior-h1="], ["prior_h1", "empty"]),
    (["threshold", "--rule", "additive", "--n", "57", "--xi=", "--alpha", "0.1"], ["xi=", "empty"]),
    (["fuse", "--rule", "additive", "--u", "1,1.0000000000000001"], ["u[1]", "1.0000000000000001"]),
    (["threshold", "--rule", "additive", "--n", "57", "--xi", "1e-310", "--alpha", "0.1"], ["xi=", "underflows"]),
])
def test_cli_parsing(capsys, argv, words):
    rc, out, err = _run(capsys, *argv)
    if words is None:
        assert rc == 0 and "Traceback" not in err
        return
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err


def test_cli_integers_at_2_53_exact(capsys):
    rc, out, _ = _run(capsys, "threshold", "--rule", "additive", "--n=9007199254740992", "--xi", "0.1",
                      "--alpha", "0.1", "--json")
    assert rc == 0 and json.loads(out)["n"] == 2**53


def test_fuse_preferential_non_integer_pq_all_present(capsys):
    """The issue: 655 of 2,000 random (p, q) exited 2 on an all-present vector; now none, and the
    decision is right (U_G = g is above every band edge below g)."""
    rng = np.random.default_rng(11)
    for _ in range(200):
        n = int(rng.integers(2, 80))
        p, q = (repr(float(v)) for v in rng.uniform(0, 2, 2))
        rc, out, err = _run(capsys, "fuse", "--rule", "preferential", "--u", ",".join(["1"] * n), "--xi", "0.5",
                            "--alpha", "0.1", "--p", p, "--q", q, "--json")
        assert rc == 0, err
        rec = json.loads(out)
        assert rec["U_G"] == rec["g"] and rec["p_h1"] == 1.0 and rec["decision"] == "H1"


def test_fuse_preferential_decisions_exact(capsys):
    """Random vectors, non-integer p, q: the decision equals the comparison of the exact U_G
    (mpmath) with the band edges the command prints."""
    rng = np.random.default_rng(5)
    for _ in range(60):
        n = int(rng.integers(2, 30))
        u = [int(v) for v in rng.choice([-1, 1], n)]
        p, q = (float(v) for v in rng.uniform(0, 2, 2))
        rc, out, err = _run(capsys, "fuse", "--rule", "preferential", "--u=" + ",".join(map(str, u)),
                            "--xi", "0.2", "--alpha", "0.3", "--p", repr(p), "--q", repr(q), "--json")
        assert rc == 0, err
        rec = json.loads(out)
        with mp.workdps(50):
            exact = rules.preferential_exact(rules.preferential_coefficients(u, "pm1"), p, q)
            expect = "H1" if exact >= rec["threshold_final"] else (
                "H0" if exact < rec["threshold_initial"] else "undecided")
        assert rec["decision"] == expect
