"""Exact system rates (part B): the preferential-rule DP (eq 7, eq 20 band) against brute force
over all 2^n decision vectors (n <= 12, both tuples, integer and non-integer p, q, unequal
per-taxel pd_i/pf_i), U_G and every vector's probability in mpmath; Chair-Varshney (eq 31) and
N-P (eq 32) rates on kinds against brute force and against the identical-taxel N-P rule."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import mpmath as mp
import numpy as np
import pytest

from fusion_center.core import baselines
from fusion_center.core.exact_rates import llr_error_rates, np_kinds_fusion, preferential_error_rates

sys.path.insert(0, str(Path(__file__).resolve().parent))
from exact_rate_references import (all_vectors, assert_logs_match_reference, brute_llr,  # noqa: E402
                                   brute_numpy, brute_preferential, classify_law, coeff_chain_law,
                                   log_chain_reference, mp_chain_dp)


@pytest.fixture(autouse=True, scope="module")
def _references_at_40_digits():
    """The mpmath references of this module at 40 digits, restored after it (not set at import:
    that leaked into whichever module ran next in the worker)."""
    with mp.workdps(40):
        yield


CASES = [("pm1", 1.0, 1.0), ("pm1", 1.3, 0.18), ("pm1", 0.0, 1.5), ("01", 1.0, 1.0), ("01", 0.5, 2.0),
         ("01", 1.7, 0.3), ("pm1", 2.0, 0.0), ("01", 0.0, 0.0)]


@pytest.mark.parametrize("encoding, p, q", CASES)
@pytest.mark.parametrize("n", [1, 2, 3, 8])
def test_preferential_dp_vs_all_vectors(encoding, p, q, n):
    rng = np.random.default_rng(n * 31 + int(10 * p) + int(100 * q))
    pd = rng.uniform(0.5, 0.99, n)
    pf = rng.uniform(0.001, 0.3, n)
    g = 1.0 if n == 1 else 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
    vectors = all_vectors(pd, pf, p, q, encoding)
    for low, high in ((0.2 * g, 0.45 * g), (-0.1 * g, 0.1 * g), (0.6 * g, 0.6 * g + 1e-9)):
        ours = preferential_error_rates(pd, pf, p, q, encoding, low, high)
        ref = brute_preferential(pd, pf, p, q, encoding, low, high, vectors)
        got = {"h1": (ours.p_detect, ours.p_undecided_h1, ours.p_miss),
               "h0": (ours.p_false_alarm, ours.p_undecided_h0, ours.p_reject)}
        for hyp in ("h1", "h0"):
            for a, b in zip(got[hyp], ref[hyp]):
                assert abs(a - float(b)) <= 1e-12 * float(b) + 1e-300, (ours.method, hyp, a, b)


@pytest.mark.parametrize("encoding, p, q", [("pm1", 1.3, 0.18), ("01", 0.5, 2.0), ("pm1", 0.0, 1.5)])
def test_preferential_dp_vs_all_vectors_n12(encoding, p, q):
    test_preferential_dp_vs_all_vectors(encoding, p, q, 12)


@pytest.mark.parametrize("encoding, p, q", [("pm1", 1.0, 1.0), ("pm1", 1.5, 0.5), ("01", 1.0, 2.0)])
def test_preferential_dp_vs_mpmath_dp_n72(encoding, p, q):
    rng = np.random.default_rng(2)
    n = 72  # beyond the 60 taxels where a non-lattice case would switch method; the mpmath DP is O(n^3)
    pi = rng.uniform(0.001, 0.2, n)
    g = 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
    low, high = 0.05 * g, 0.2 * g
    ours = preferential_error_rates(pi, pi, p, q, encoding, low, high)
    ref = mp_chain_dp(list(pi), p, q, encoding, low, high)
    for a, b in zip((ours.p_false_alarm, ours.p_undecided_h0, ours.p_reject), ref):
        assert abs(a - float(b)) <= 1e-11 * float(b) + 1e-300, (ours.method, a, b)


def test_preferential_dp_edge_ties_exact():
    """Integer p, q: U_G lands exactly on the band edges; H1 iff U_G >= high, H0 iff U_G < low."""
    pd, pf = [0.7] * 9, [0.2] * 9
    for encoding in ("pm1", "01"):
        vectors = all_vectors(pd, pf, 1, 1, encoding)
        for low, high in ((4.0, 12.0), (0.0, 0.0), (-3.0, 8.0)):
            ours = preferential_error_rates(pd, pf, 1, 1, encoding, low, high)
            ref = brute_preferential(pd, pf, 1, 1, encoding, low, high, vectors)
            assert abs(ours.p_detect - float(ref["h1"][0])) <= 1e-13
            assert abs(ours.p_reject - float(ref["h0"][2])) <= 1e-13


def test_preferential_dp_tiny_tail_log_form():
    """Under H0 with pf = 1e-3, H1 needs (almost) every taxel present: P ~ 1e-3^n, down to
    1e-297 for n = 99 (chain DP), checked against the closed form of the few qualifying vectors."""
    n = 99
    g = 2 + 2 + (n - 2) * 4.0
    ours = preferential_error_rates(0.9, 1e-3, 1, 1, "pm1", g - 1, g - 0.5, n=n)  # only all-present reaches g
    assert ours.method == "chain"
    assert math.isclose(ours.p_false_alarm, 1e-297, rel_tol=1e-12)
    assert math.isclose(ours.logs()["log_p_false_alarm"], 99 * math.log(1e-3), rel_tol=1e-14)


def test_llr_kinds_vs_all_vectors():
    pd = [0.9] * 5 + [0.7] * 4 + [0.95] * 3
    pf = [0.1] * 5 + [0.2] * 4 + [0.01] * 3
    for prior in (0.5, 0.2, 0.9):
        ours = llr_error_rates(pd, pf, prior)
        d, f = brute_llr(pd, pf, prior)
        assert math.isclose(ours.p_detect, d, rel_tol=1e-12) and math.isclose(ours.p_false_alarm, f, rel_tol=1e-12)


def test_np_kinds_matches_identical_rule_and_beats_count_rule():
    """One kind: the kinds N-P rule equals the identical-taxel rule. Two kinds: its power is at
    least that of the count-only rule of the same size (it is the most powerful test)."""
    pd, pf = np.full(40, 0.8), np.full(40, 0.1)
    a = np_kinds_fusion(pd, pf, 0.01)
    b = baselines.neyman_pearson_fusion(pd, pf, 0.01)
    assert math.isclose(a["detection_probability"], b.detection_probability, rel_tol=1e-12)
    assert math.isclose(a["gamma"], b.gamma, rel_tol=1e-9)
    pd2 = np.r_[np.full(20, 0.9), np.full(37, 0.6)]
    pf2 = np.r_[np.full(20, 0.05), np.full(37, 0.3)]
    k = np_kinds_fusion(pd2, pf2, 0.01)
    c = baselines.neyman_pearson_fusion(pd2, pf2, 0.01, method="count")
    assert math.isclose(k["achieved_false_alarm"], 0.01, rel_tol=1e-9)
    assert k["detection_probability"] >= c.detection_probability


def _fuse(capsys, *argv):
    import json

    from fusion_center.cli import main

    rc = main(["fuse", *argv, "--json"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    return json.loads(out)


def test_fuse_preferential_rates_cli_vs_all_vectors(capsys):
    """fuse --rule preferential --pd/--pf: the four rates and their logs against brute force,
    on the sec. 7.2 gripper ({0,1}, p = q = 1) and on non-integer p, q ({-1,+1})."""
    u01 = "1,1,1,0,1,0,1,1,1,0,1,1,1,1,1,1,0,0"
    rec = _fuse(capsys, "--rule", "preferential", "--u", u01, "--tuple", "01", "--xi", "0.003", "--alpha", "0.48",
                "--pd", "0.95", "--pf", "0.05")
    # all 2^18 vectors in numpy: p = q = 1 on {0,1} gives integer U_G (exact in floats)
    bits = ((np.arange(2**18)[:, None] >> np.arange(18)) & 1).astype(float)
    padded = np.pad(bits, ((0, 0), (1, 1)))
    ug = (bits * (1 + padded[:, 2:]) * (1 + padded[:, :-2])).sum(axis=1)
    k = bits.sum(axis=1)
    for pi, names in ((0.95, ("p_detect", "p_undecided_h1")), (0.05, ("p_false_alarm", "p_undecided_h0"))):
        w = np.exp(k * math.log(pi) + (18 - k) * math.log1p(-pi))
        h1 = w[ug >= rec["threshold_final"]].sum()
        und = w[(ug < rec["threshold_final"]) & (ug >= rec["threshold_initial"])].sum()
        assert math.isclose(rec[names[0]], h1, rel_tol=1e-12)
        assert math.isclose(rec[names[1]], und, rel_tol=1e-12)
        assert math.isclose(rec["log_" + names[0]], math.log(h1), rel_tol=1e-12, abs_tol=1e-12)
    pd = [0.9, 0.8, 0.95, 0.7, 0.85, 0.9, 0.99, 0.6, 0.75, 0.9]
    pf = [0.1, 0.05, 0.2, 0.01, 0.1, 0.3, 0.02, 0.05, 0.1, 0.15]
    rec = _fuse(capsys, "--rule", "preferential", "--u", "1,1,-1,1,1,1,-1,1,1,1", "--xi", "0.2", "--alpha", "0.3",
                "--p", "1.37", "--q", "0.41", "--pd", ",".join(map(str, pd)), "--pf", ",".join(map(str, pf)))
    ref = brute_preferential(pd, pf, 1.37, 0.41, "pm1", rec["threshold_initial"], rec["threshold_final"])
    assert rec["rates_method"] == "chain"
    assert math.isclose(rec["p_detect"], float(ref["h1"][0]), rel_tol=1e-12)
    assert math.isclose(rec["p_false_alarm"], float(ref["h0"][0]), rel_tol=1e-12)


def test_fuse_llr_and_np_rates_cli(capsys):
    pd = [0.9] * 6 + [0.7] * 5
    pf = [0.1] * 6 + [0.2] * 5
    rec = _fuse(capsys, "--rule", "llr", "--u", "1,1,1,-1,-1,1,1,-1,1,-1,1", "--pd", ",".join(map(str, pd)),
                "--pf", ",".join(map(str, pf)))
    d, f = brute_llr(pd, pf, 0.5)
    assert math.isclose(rec["p_detect"], d, rel_tol=1e-12) and math.isclose(rec["p_false_alarm"], f, rel_tol=1e-12)
    rec = _fuse(capsys, "--rule", "np", "--u", "1,1,1,-1,-1,1,1,-1,1,-1,1", "--pd", ",".join(map(str, pd)),
                "--pf", ",".join(map(str, pf)), "--false-alarm", "0.05")
    assert math.isclose(rec["p_false_alarm"], 0.05, rel_tol=1e-12) and rec["optimal"] is True


def test_monte_carlo_results_carry_exact_values_for_every_rule():
    """evaluation.simulate: the preferential, llr and np rules now have exact P_D, P_F (DP over
    the chain, product of binomials); where the Monte Carlo saw events, the exact value lies in
    a 99.9 % Wilson interval around it."""
    from fusion_center import evaluation
    from fusion_center.core.montecarlo import wilson_interval
    from taxel_net.scene import load_scene

    for path in ("scenes/point_force.toml", "scenes/gripper18.toml"):
        scene = load_scene(path)
        mc = evaluation.simulate(scene, 20000, np.random.default_rng(4))
        for name in ("preferential", "llr", "np"):
            if name not in mc.rules:
                continue
            res = mc.rules[name]
            assert res.pf.exact is not None and res.pd.exact is not None, (path, name)
            for rate in (res.pf, res.pd):
                lo, hi = wilson_interval(rate.successes, rate.trials, 0.999)
                assert lo - 1e-12 <= rate.exact <= hi + 1e-12, (path, name, rate)


def test_importance_sampling_tail_covers_exact():
    """The importance-sampling estimate (used beyond the exact reach) against the exact kinds
    value, for tails down to 1e-12: the exact value lies in its 99.9 % interval (seeded)."""
    from fusion_center.core.exact_rates import importance_sampling_tail, linear_statistic_tail

    rng = np.random.default_rng(1)
    pd = np.r_[np.full(20, 0.9), np.full(20, 0.8)]
    pf = np.r_[np.full(20, 0.05), np.full(20, 0.2)]
    a, b = np.log(pd) - np.log(pf), np.log1p(-pd) - np.log1p(-pf)
    for probs in (pf, pd):
        for t in (0.0, 10.0, -5.0):
            exact = linear_statistic_tail(a, b, probs, t)
            est, (lo, hi) = importance_sampling_tail(a, b, probs, t, 40_000, rng)
            half = (hi - lo) / 2 * 3.29 / 1.96
            assert abs(est - exact) <= half + 1e-15, (t, exact, est, lo, hi)


# ------------------------------------------------------------------ lattice DP: every lattice form, deep tails
@pytest.mark.parametrize("encoding, p, q", [("pm1", 1.5, 0.0), ("pm1", 0.5, 1.5), ("pm1", 1.0, 2.0), ("pm1", 2.0, 2.0),
                                            ("pm1", 0.0, 0.0), ("01", 2.0, 0.0), ("01", 1.0, 2.0)])
@pytest.mark.parametrize("n", [2, 3, 9])
def test_lattice_forms_vs_all_vectors(encoding, p, q, n):
    """Folded units (2^q an integer), reversed chains (p and q swapped) and one zero weight."""
    test_preferential_dp_vs_all_vectors(encoding, p, q, n)


@pytest.mark.parametrize("encoding, p, q", [("pm1", 0.0, 1.5), ("pm1", 1.7, 0.0)])
def test_one_zero_weight_is_exact_beyond_the_sparse_limit(encoding, p, q):
    """{-1,+1} with one zero weight: U_G = 2^p m + u_n (or mirrored), exact for any n (was a
    Monte Carlo estimate beyond 60 taxels); against the mpmath DP at n = 90."""
    rng = np.random.default_rng(5)
    n = 90
    pi = rng.uniform(0.05, 0.6, n)
    g = 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
    low, high = -0.2 * g, 0.25 * g
    ours = preferential_error_rates(pi, pi, p, q, encoding, low, high)
    assert ours.method == "lattice"
    ref = mp_chain_dp(list(pi), p, q, encoding, low, high)
    for a, b in zip((ours.p_false_alarm, ours.p_undecided_h0, ours.p_reject), ref):
        assert abs(a - float(b)) <= 1e-11 * float(b) + 1e-300, (a, b)


def test_deep_tails_vs_a_log_domain_reference():
    """n = 400, the chapter's band (xi = 0.003, alpha = 0.48): under H1 undecided ~1e-3 and a
    miss ~1e-8, under H0 undecided ~1e-272 and a false alarm ~1e-371; every rate agrees with an
    untrimmed log-domain DP to 1e-11 (relative, on the log), the ones below 1e-300 included
    (exact logs from the tilted DP, named in below_floor, with a proven error bound)."""
    from fusion_center.core.thresholds import preferential_threshold

    rng = np.random.default_rng(11)
    n = 400
    pd = rng.uniform(0.8, 0.99, n)
    pf = rng.uniform(0.001, 0.02, n)
    for p, q in ((1.3, 0.2), (1.0, 1.0)):
        band = preferential_threshold(n, 0.003, 0.48, p, q)
        low, high = band.threshold_initial, band.threshold_final
        ours = preferential_error_rates(pd, pf, p, q, "pm1", low, high)
        assert ours.method == "chain"
        for name, r in assert_logs_match_reference(ours, pd, pf, p, q, low, high).items():
            assert (name in ours.below_floor) == (r < math.log(1e-300)), name
            if r < math.log(1e-300):
                assert ours.error_bounds[name] < -13
        assert ours.below_floor  # this band puts the H0 rates of H1-or-undecided far below 1e-300
        shallow = preferential_error_rates(pd, pf, p, q, "pm1", low, high, deep=False)
        assert all(getattr(shallow, "log_" + k) is None for k in shallow.below_floor)


def test_floor_and_impossible_events():
    """A zero-width band holds no value: impossible (None, not below the floor); a far tail
    below 1e-300 is named in below_floor and its log is exact (1e-600: all 200 present)."""
    n = 200
    ours = preferential_error_rates(0.9, 1e-3, 1, 1, "pm1", 10.5, 10.5, n=n)
    assert ours.log_p_undecided_h1 is None and ours.log_p_undecided_h0 is None
    assert "p_undecided_h1" not in ours.below_floor and "p_undecided_h0" not in ours.below_floor
    g = 4.0 * n - 4.0
    far = preferential_error_rates(0.5, 1e-3, 1, 1, "pm1", g - 1, g - 0.5, n=n)  # H1 needs all 200 present
    assert "p_false_alarm" in far.below_floor and far.p_false_alarm == 0.0  # 1e-600 underflows ...
    assert math.isclose(far.log_p_false_alarm, n * math.log(1e-3), rel_tol=1e-13)  # ... its log is exact
    assert math.isclose(far.log_p_detect, n * math.log(0.5), rel_tol=1e-13)  # 2^-200, exact


@pytest.mark.parametrize("encoding, p, q", [("pm1", 1.0, 1.0), ("pm1", 1.5, 0.5), ("pm1", 0.0, 1.5), ("01", 1.0, 2.0)])
def test_rates_below_1e300_vs_mpmath(encoding, p, q):
    """Rates of 1e-330 .. 1e-500 (heterogeneous pf ~ 1e-8, the band near the top of U_G's
    range, n = 60): their logs against the mpmath chain DP (40 digits), to 1e-12 relative;
    the plain values underflow to 0."""
    rng = np.random.default_rng(7)
    n = 60
    pi = 10.0 ** rng.uniform(-9.0, -7.0, n)
    top = 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)  # g(n), eq 15
    low, high = 0.6 * top, 0.9 * top
    ours = preferential_error_rates(pi, pi, p, q, encoding, low, high)
    ref = mp_chain_dp(list(pi), p, q, encoding, low, high)
    for name, r in zip(("p_false_alarm", "p_undecided_h0", "p_reject"), ref):
        got = getattr(ours, "log_" + name)
        if r == 0:
            assert got is None
            continue
        lr = float(mp.log(r))
        assert got is not None and abs(got - lr) <= 1e-12 * max(1.0, abs(lr)), (name, got, lr)
        if lr < math.log(1e-300):
            assert name in ours.below_floor and getattr(ours, name) <= 1e-300
    assert any(float(mp.log(r)) < -330 * math.log(10.0) for r in ref[:2] if r > 0)


@pytest.mark.parametrize("p, q", [(0.5, 2.0), (1.7, 0.3), (0.0, 1.5)])
def test_01_non_integer_weights_exact_beyond_60_taxels(p, q):
    """{0,1} with a non-integer weight: the counts DP (runs of length 1 / longer runs / inner
    taxels) is exact beyond the old 60-taxel limit (was Monte Carlo); against a DP over the
    integer coefficients of 1, 2^p, 2^q, 2^(p+q) at n = 72, unequal pi."""
    assert_counts_dp_matches_coefficient_law(np.random.default_rng(9).uniform(0.05, 0.7, 72), p, q)


def assert_counts_dp_matches_coefficient_law(pi, p, q):
    """The {0,1} counts DP ("exact-counts") against the DP over the integer coefficients of 1,
    2^p, 2^q, 2^(p+q) (``coeff_chain_law``), for two bands, each rate to 1e-11 relative."""
    n = len(pi)
    g = 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
    law = coeff_chain_law(list(pi))
    for low, high in ((0.1 * g, 0.25 * g), (0.3 * g, 0.5 * g)):
        ours = preferential_error_rates(pi, pi, p, q, "01", low, high)
        assert ours.method == "exact-counts"
        ref = classify_law(law, p, q, low, high)
        for a, b in zip((ours.p_false_alarm, ours.p_undecided_h0, ours.p_reject), ref):
            assert abs(a - b) <= 1e-11 * b + 1e-300, (a, b)


def test_monte_carlo_band_rates_match_the_rule():
    """The vectorised Monte Carlo fallback: the same U_G as rules.preferential_value per sample
    (seeded draws replayed one by one)."""
    from fusion_center.core.rate_sampling import monte_carlo_band_rates
    from fusion_center.core.rules import preferential_coefficients, preferential_value

    pi = np.random.default_rng(1).uniform(0.2, 0.8, 15)
    for encoding, p, q in (("01", 0.5, 2.0), ("pm1", 1.3, 0.0)):
        low, high = 3.0, 9.0
        got = monte_carlo_band_rates(pi, p, q, encoding, low, high, 500, np.random.default_rng(4))
        rng = np.random.default_rng(4)
        draws = rng.random((500, 15)) < pi
        counts = np.zeros(3)
        for row in draws:
            u = np.where(row, 1, -1 if encoding == "pm1" else 0)
            v = preferential_value(preferential_coefficients(u, encoding), p, q)
            counts[0 if v >= high else (2 if v < low else 1)] += 1
        assert np.array_equal(got, counts / 500)


@pytest.mark.parametrize("encoding, p, q", [("pm1", 1.3, 0.18), ("01", 0.5, 2.0), ("01", 1.7, 0.3), ("pm1", 0.0, 1.5),
                                            ("01", 1.0, 1.0)])
def test_all_2_16_vectors(encoding, p, q):
    """n = 16, unequal pd_i / pf_i, three bands (one edge on an attainable value of U_G): every
    rate against all 2^16 decision vectors."""
    rng = np.random.default_rng(16)
    n = 16
    pd = rng.uniform(0.5, 0.99, n)
    pf = rng.uniform(0.01, 0.4, n)
    g = 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
    for low, high in ((0.2 * g, 0.45 * g), (-0.1 * g, 0.1 * g), (2.0**p + 2.0**q, 0.7 * g)):
        ours = preferential_error_rates(pd, pf, p, q, encoding, low, high)
        for probs, names in ((pd, ("p_detect", "p_undecided_h1", "p_miss")),
                             (pf, ("p_false_alarm", "p_undecided_h0", "p_reject"))):
            for name, ref in zip(names, brute_numpy(probs, p, q, encoding, low, high)):
                assert abs(getattr(ours, name) - ref) <= 1e-12 * ref + 1e-300, (ours.method, name, low, high)


@pytest.mark.parametrize("seed", range(16))
def test_random_chain_cases_vs_log_domain_reference(seed):
    """Random {-1,+1} chains (p, q > 0 non-integer or integer, n 20..160, per-taxel pd/pf from
    near 0 to near 1, bands anywhere in U_G's range, deep or not): all six logs against the
    untrimmed log-domain DP to 1e-11 (relative on the log); the rates below 1e-300 too (deep),
    or None and named (shallow); every proven error bound below 1e-13."""
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(20, 161))
    p, q = (float(rng.choice([1.0, 2.0])), float(rng.choice([1.0, 0.5]))) if seed % 3 == 0 else \
        (float(rng.uniform(0.1, 2.0)), float(rng.uniform(0.1, 2.0)))
    pd = rng.uniform(*sorted(rng.uniform(0.3, 0.999, 2)), n)
    pf = 10.0 ** rng.uniform(-4.0, -0.5, n)
    g = 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
    low, high = sorted(rng.uniform(-0.3 * g, 0.95 * g, 2))
    deep = seed % 2 == 0
    ours = preferential_error_rates(pd, pf, p, q, "pm1", low, high, deep=deep)
    for probs, names in ((pd, ("p_detect", "p_undecided_h1", "p_miss")),
                         (pf, ("p_false_alarm", "p_undecided_h0", "p_reject"))):
        ref = log_chain_reference(probs, p, q, low, high)
        for name, r in zip(names, ref):
            got = getattr(ours, "log_" + name)
            if r is None:
                assert got is None and name not in ours.below_floor, name
            elif r < math.log(1e-300) and not deep:
                assert got is None and name in ours.below_floor, (name, r)
            else:
                assert got is not None and abs(got - r) <= 1e-11 * max(1.0, abs(r)), (seed, name, got, r)
                assert ours.error_bounds[name] < -13, (name, ours.error_bounds[name])


@pytest.mark.parametrize("seed", range(8))
def test_extreme_probabilities_vs_log_domain_reference(seed):
    """Per-taxel probabilities of exactly 0 or 1, 1e-12 or 10^-12..10^-1 (strong tilts, masses
    that shrink by 1e-12 per taxel): every log against the untrimmed log-domain DP, deep."""
    rng = np.random.default_rng(200 + seed)
    n = int(rng.integers(30, 110))
    p, q = float(rng.uniform(0.05, 2.0)), float(rng.uniform(0.05, 2.0))
    pi = rng.uniform(0, 1, n)
    if seed % 2:
        pi = 10.0 ** rng.uniform(-12, -1, n)
    pi[rng.integers(0, n, 5)] = rng.choice([0.0, 1.0, 1e-12, 1 - 1e-12], 5)
    g = 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
    low, high = sorted(rng.uniform(-1.1 * g, 1.1 * g, 2))
    ours = preferential_error_rates(pi, pi, p, q, "pm1", low, high)
    with np.errstate(divide="ignore"):
        ref = log_chain_reference(pi, p, q, low, high)
    for name, r in zip(("p_false_alarm", "p_undecided_h0", "p_reject"), ref):
        got = getattr(ours, "log_" + name)
        if r is None or r == -math.inf:
            assert got is None, (name, got)
        else:
            assert got is not None and abs(got - r) <= 1e-11 * max(1.0, abs(r)), (seed, name, got, r)


# ------------------------------------------------------------------ bridge trimming (tilted_dp)
def test_bridge_trimmed_rates_vs_log_domain_reference():
    """n = 1200 (bridge trimming: from tilted_dp.BRIDGE_MIN_TAXELS taxels on), the chapter's band:
    every rate of both hypotheses, the ones far below 1e-300 included (H0: ~1e-900 and
    ~1e-1250), against the untrimmed log-domain DP to 1e-11 (relative, on the log), each with
    its proven error bound below 1e-13."""
    from fusion_center.core import tilted_dp
    from fusion_center.core.thresholds import preferential_threshold

    rng = np.random.default_rng(12)
    n = 1200
    assert n >= tilted_dp.BRIDGE_MIN_TAXELS
    pd = rng.uniform(0.8, 0.99, n)
    pf = rng.uniform(0.001, 0.01, n)
    for p, q in ((1.3, 0.2), (1.0, 1.0)):
        band = preferential_threshold(n, 0.003, 0.48, p, q)
        low, high = band.threshold_initial, band.threshold_final
        ours = preferential_error_rates(pd, pf, p, q, "pm1", low, high)
        for name in assert_logs_match_reference(ours, pd, pf, p, q, low, high):
            assert ours.error_bounds[name] < -13, (name, ours.error_bounds[name])
        assert ours.log_p_false_alarm < -800 * math.log(10.0)


@pytest.mark.parametrize("seed", range(8))
def test_bridge_trimming_forced_at_small_n_vs_log_domain_reference(seed, monkeypatch):
    """Bridge trimming forced from 2 taxels on (random {-1,+1} chains as in
    test_random_chain_cases_vs_log_domain_reference, deep): all six logs against the untrimmed
    log-domain DP, every error bound below 1e-13."""
    from fusion_center.core import tilted_dp

    monkeypatch.setattr(tilted_dp, "BRIDGE_MIN_TAXELS", 2)
    rng = np.random.default_rng(300 + seed)
    n = int(rng.integers(40, 261))
    p, q = float(rng.uniform(0.1, 2.0)), float(rng.uniform(0.1, 2.0))
    pd = rng.uniform(*sorted(rng.uniform(0.3, 0.999, 2)), n)
    pf = 10.0 ** rng.uniform(-6.0, -0.5, n)
    if seed % 2:
        pf[rng.integers(0, n, 4)] = rng.choice([0.0, 1.0, 1e-12], 4)
    g = 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
    low, high = sorted(rng.uniform(-0.3 * g, 0.95 * g, 2))
    ours = preferential_error_rates(pd, pf, p, q, "pm1", low, high)
    for probs, names in ((pd, ("p_detect", "p_undecided_h1", "p_miss")),
                         (pf, ("p_false_alarm", "p_undecided_h0", "p_reject"))):
        with np.errstate(divide="ignore"):
            ref = log_chain_reference(probs, p, q, low, high)
        for name, r in zip(names, ref):
            got = getattr(ours, "log_" + name)
            if r is None or r == -math.inf:
                assert got is None, (seed, name, got)
            else:
                assert got is not None and abs(got - r) <= 1e-11 * max(1.0, abs(r)), (seed, name, got, r)
                assert ours.error_bounds[name] < -13, (name, ours.error_bounds[name])


@pytest.mark.parametrize("encoding, p, q", [("pm1", 1.3, 0.2), ("01", 1.0, 1.0), ("pm1", 0.0, 1.5)])
def test_suffix_bounds_vs_log_domain_backward_recursion(encoding, p, q):
    """tilted_dp._suffix_logs: at every block end, ln max over states of E[e^(theta S) | state]
    (S the remaining steps, the last taxel's end steps included) against a backward recursion in
    the log domain (np.logaddexp, taxel by taxel): an upper bound, within 1e-9 of it; and
    Lambda(theta) against log_partition."""
    from fusion_center.core import tilted_dp
    from fusion_center.core.chain_dp import _lattice

    rng = np.random.default_rng(5)
    n = 150
    pi = rng.uniform(0.0, 1.0, n)
    pi[:3] = (1e-13, 0.999, 0.3)
    pi[rng.integers(0, n, 6)] = rng.choice([0.0, 1.0, 1e-14], 6)
    lat = _lattice(p, q, encoding)
    thetas = np.array([-3.0, -0.4, 0.0, 0.7, 4.0])
    bounds, log_hmax, lam = tilted_dp._suffix_logs(pi, lat, thetas, block=16)
    assert np.allclose(lam, tilted_dp.log_partition(pi, lat, thetas), rtol=1e-12, atol=1e-10)
    with np.errstate(divide="ignore"):
        lp = np.stack([np.log1p(-pi), np.log(pi)])
    for k, th in enumerate(thetas):
        h = np.array([th * lat.end[a][b][0] for a in (0, 1) for b in (0, 1)], float)  # state index 2 a + b
        want = {n: float(h.max())}
        for j in range(n - 1, 1, -1):  # taxel j added from state (u_(j-2), u_(j-1))
            new = np.empty(4)
            for a in (0, 1):
                for b in (0, 1):
                    new[2 * a + b] = np.logaddexp(lp[0, j] + th * lat.shift[a, b, 0] + h[2 * b],
                                                  lp[1, j] + th * lat.shift[a, b, 1] + h[2 * b + 1])
            h = new
            want[j] = float(h.max())
        for b_idx, e in enumerate(bounds):
            assert log_hmax[k, b_idx] >= want[e] - 1e-9 * max(1.0, abs(want[e])), (th, e)
            assert log_hmax[k, b_idx] <= want[e] + 1e-9 * max(1.0, abs(want[e])), (th, e)


@pytest.mark.parametrize("seed", range(4))
def test_bridge_error_bounds_hold_when_trimmed_hard(seed, monkeypatch):
    """The bridge's error bounds are bounds: trimmed hard on purpose (BRIDGE_REL = 1e-4, every
    bound accepted), each far rate's true relative error (against the untrimmed log-domain DP)
    stays below the bound the run reports for it, and the trimming did cost accuracy."""
    from fusion_center.core import tilted_dp
    from fusion_center.core.chain_dp import _lattice
    from fusion_center.core.thresholds import preferential_threshold

    monkeypatch.setattr(tilted_dp, "BRIDGE_MIN_TAXELS", 2)
    monkeypatch.setattr(tilted_dp, "BRIDGE_REL", 1e-4)
    monkeypatch.setattr(tilted_dp, "BOUND_OK", 0.0)
    rng = np.random.default_rng(400 + seed)
    n = int(rng.integers(150, 301))
    p, q = ((1.0, 1.0), (1.3, 0.2), (0.7, 1.6), (2.0, 0.5))[seed]
    band = preferential_threshold(n, 0.003, 0.48, p, q)
    low, high = band.threshold_initial, band.threshold_final
    loosest = -math.inf
    for probs in (rng.uniform(0.8, 0.99, n), rng.uniform(0.001, 0.02, n)):
        regions = tilted_dp.lattice_band_logs(probs, _lattice(p, q, "pm1"), low, high)
        ref = log_chain_reference(probs, p, q, low, high)
        for (log, _, bound), r in zip(regions, ref):
            if bound is None or log is None:
                continue
            err = abs(math.expm1(log - r))
            # plus rounding: ~1e-16 relative on a log of size |r| (both logs), ~1e-13 overall
            assert err <= 10.0**bound * (1 + 1e-6) + 1e-15 * max(1.0, abs(r)) + 1e-13, (seed, log, r, err, bound)
            loosest = max(loosest, err)
    assert loosest > 1e-6  # the hard trimming did change the results


# ------------------------------------------------------------------ {0,1}: the two-count DP
TWO_COUNT_CASES = [(1.0, 0.3), (0.4, 2.0), (0.25, 0.75), (1.5, 0.5), (1.3, 0.0), (0.0, 0.6), (2.0, 1.7)]


@pytest.mark.parametrize("p, q", TWO_COUNT_CASES)
def test_two_count_dp_vs_all_2_16_vectors(p, q):
    """{0,1} where U_G needs two integer coordinates (p or q an integer, p + q an integer, a zero
    weight): every rate against all 2^16 decision vectors, three bands (one edge on an
    attainable value), unequal pd_i / pf_i."""
    from fusion_center.core.chain_dp import _two_count_form

    assert _two_count_form(p, q) is not None
    rng = np.random.default_rng(17)
    n = 16
    pd = rng.uniform(0.5, 0.99, n)
    pf = rng.uniform(0.01, 0.4, n)
    g = 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
    for low, high in ((0.2 * g, 0.45 * g), (-0.1 * g, 0.1 * g), (2.0**p + 2.0**q, 0.7 * g)):
        ours = preferential_error_rates(pd, pf, p, q, "01", low, high)
        assert ours.method == "exact-counts"
        for probs, names in ((pd, ("p_detect", "p_undecided_h1", "p_miss")),
                             (pf, ("p_false_alarm", "p_undecided_h0", "p_reject"))):
            for name, ref in zip(names, brute_numpy(probs, p, q, "01", low, high)):
                assert abs(getattr(ours, name) - ref) <= 1e-12 * ref + 1e-300, (name, low, high)


def test_two_count_form_only_where_exact():
    """The two-count form is decided on the float inputs exactly: 0.3 + 0.7 is not 1 in
    doubles (2^0.3 2^0.7 != 2), so that pair takes the three-count DP; both integers are the
    lattice DP's."""
    from fusion_center.core.chain_dp import _two_count_form

    assert _two_count_form(0.3, 0.7) is None
    assert _two_count_form(0.25, 0.75) is not None
    assert _two_count_form(1.3, 0.2) is None


@pytest.mark.parametrize("p, q", [(1.0, 0.3), (0.25, 0.75)])
def test_two_count_dp_exact_at_300_taxels(p, q):
    """Beyond the three-count DP's 200 taxels the two-count DP is exact (was Monte Carlo): at
    n = 90 against the DP over the integer coefficients of 1, 2^p, 2^q, 2^(p+q) (the test
    reference, too slow at 300), at n = 300 the method is exact and each hypothesis' three
    rates sum to 1."""
    rng = np.random.default_rng(21)
    assert_counts_dp_matches_coefficient_law(rng.uniform(0.05, 0.7, 90), p, q)
    n = 300
    pd, pf = rng.uniform(0.3, 0.9, n), rng.uniform(0.05, 0.4, n)
    g = 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
    ours = preferential_error_rates(pd, pf, p, q, "01", 0.2 * g, 0.3 * g)
    assert ours.method == "exact-counts"
    assert math.isclose(ours.p_detect + ours.p_undecided_h1 + ours.p_miss, 1.0, rel_tol=1e-13)
    assert math.isclose(ours.p_false_alarm + ours.p_undecided_h0 + ours.p_reject, 1.0, rel_tol=1e-13)
