"""Baselines of the chapter (eqs 22, 31, 32; k-out-of-n of sec. 2.2.1; Neyman-Pearson fusion).

References are independent: mpmath at 50 digits written from the chapter's own formulas
(with P_M, not pd), brute-force enumeration of all decision vectors, scipy.stats.binom.
"""

from __future__ import annotations

import itertools
import math
import tomllib
from fractions import Fraction
from importlib import resources

import mpmath
import numpy as np
import pytest
from scipy import stats

from fusion_center.core import baselines as bl
from taxel_net.errors import ParameterError

@pytest.fixture(autouse=True, scope="module")
def _references_at_50_digits():
    """The mpmath references of this module at 50 digits, restored after it (not set at import:
    that leaked into whichever module ran next in the worker)."""
    with mpmath.workdps(50):
        yield


# ----------------------------------------------------------------- references (mpmath)
def eq31_mpmath(u_pm1, pm, pf, prior_h1=0.5):
    """Eq 31 literally: log P1/P0 + sum_S+ log((1-P_M)/P_F) + sum_S- log(P_M/(1-P_F))."""
    p1 = mpmath.mpf(prior_h1)
    total = mpmath.log(p1 / (1 - p1))
    for ui, m, f in zip(u_pm1, pm, pf):
        m, f = mpmath.mpf(m), mpmath.mpf(f)
        total += mpmath.log((1 - m) / f) if ui == 1 else mpmath.log(m / (1 - f))
    return total


def eq32_product_mpmath(u01, pm, pf):
    """Eq 32 literally: prod ((1-P_M)/P_F)^u_i (P_M/(1-P_F))^(1-u_i), u_i in {0, 1}."""
    prod = mpmath.mpf(1)
    for ui, m, f in zip(u01, pm, pf):
        m, f = mpmath.mpf(m), mpmath.mpf(f)
        prod *= ((1 - m) / f) ** ui * (m / (1 - f)) ** (1 - ui)
    return prod


def posterior_log_odds_mpmath(u01, pd, pf, prior_h1):
    """ln P(H1|U)/P(H0|U) by Bayes' rule on the joint probabilities of U."""
    p1 = mpmath.mpf(prior_h1)
    like1 = like0 = mpmath.mpf(1)
    for ui, d, f in zip(u01, pd, pf):
        d, f = mpmath.mpf(d), mpmath.mpf(f)
        like1 *= d if ui else 1 - d
        like0 *= f if ui else 1 - f
    post1 = p1 * like1 / (p1 * like1 + (1 - p1) * like0)
    return mpmath.log(post1 / (1 - post1))


# ----------------------------------------------------------------- eq 31 / eq 32
def test_chair_varshney_matches_eq31_hand_example():
    pm = [0.0015, 0.022, 0.03, 0.052]
    pf = [0.0005, 0.0023, 0.0010, 0.0002]
    pd = [1 - m for m in pm]
    u = [1, -1, 1, -1]
    ours = bl.chair_varshney_llr(u, pd, pf, "pm1")
    assert abs(ours - float(eq31_mpmath(u, pm, pf))) < 1e-12
    # by hand: ln(0.9985/0.0005) + ln(0.022/0.9977) + ln(0.97/0.001) + ln(0.052/0.9998)
    by_hand = math.log(0.9985 / 0.0005) + math.log(0.022 / 0.9977) + math.log(0.97 / 0.001) + math.log(0.052 / 0.9998)
    assert ours == pytest.approx(by_hand, rel=1e-12)
    # the same decisions in the {0, 1} tuple give the same statistic
    assert bl.chair_varshney_llr([1, 0, 1, 0], pd, pf, "01") == pytest.approx(ours, rel=1e-15)


@pytest.mark.parametrize("prior_h1", [0.5, 0.3, 0.9, 1e-4])
def test_chair_varshney_is_the_posterior_log_odds(prior_h1):
    rng = np.random.default_rng(11)
    pd = rng.uniform(0.6, 0.999, 15)
    pf = rng.uniform(0.001, 0.3, 15)
    u01 = rng.integers(0, 2, 15)
    ours = bl.chair_varshney_llr(u01, pd, pf, "01", prior_h1=prior_h1)
    ref = posterior_log_odds_mpmath(u01, pd, pf, prior_h1)
    assert abs(ours - float(ref)) < 1e-11


def test_np_log_statistic_is_ln_of_eq32_and_survives_underflow():
    # 200 taxels of the chapter's kind, none present: the plain product underflows to 0
    n = 200
    pm = np.full(n, 0.005)
    pf = np.full(n, 0.003)
    u01 = np.zeros(n, dtype=int)
    exact = eq32_product_mpmath(u01, pm, pf)
    assert exact < mpmath.mpf("1e-400")
    plain_product = np.prod(np.where(u01 == 1, (1 - pm) / pf, pm / (1 - pf)))
    assert plain_product == 0.0  # what a direct transcription of eq 32 returns
    ours = bl.np_log_statistic(u01, 1 - pm, pf, "01")
    assert abs(ours - float(mpmath.log(exact))) < 1e-12 * abs(float(mpmath.log(exact)))


def test_np_statistic_is_llr_without_prior_and_scalars_broadcast():
    u = [1, 1, -1, -1, -1]
    a = bl.np_log_statistic(u, 0.95, 0.01, "pm1")
    b = bl.np_log_statistic(u, [0.95] * 5, [0.01] * 5, "pm1")
    assert a == b
    assert a == pytest.approx(2 * math.log(95) + 3 * math.log(0.05 / 0.99), rel=1e-13)
    assert bl.chair_varshney_llr(u, 0.95, 0.01, "pm1", prior_h1=0.2) == pytest.approx(a + math.log(0.25), rel=1e-13)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(pd=[0.9, 1.0], pf=[0.1, 0.1]), "pd[1]"),
        (dict(pd=[0.9, 0.9], pf=[0.1, 0.0]), "pf[1]"),
        (dict(pd=[0.9, 0.9], pf=[0.1, np.nan]), "pf[1]"),
        (dict(pd=[0.9, 0.9], pf=[0.1, 0.1, 0.1]), "pf"),
        (dict(pd=[0.9, 0.9, 0.9], pf=[0.1, 0.1]), "pd"),
    ],
)
def test_probabilities_outside_open_interval_are_named(kwargs, name):
    with pytest.raises(ParameterError) as err:
        bl.np_log_statistic([1, -1], kwargs["pd"], kwargs["pf"], "pm1")
    assert err.value.name == name


def test_bad_prior_and_bad_decisions():
    with pytest.raises(ParameterError) as err:
        bl.chair_varshney_llr([1, -1], 0.9, 0.1, "pm1", prior_h1=1.0)
    assert err.value.name == "prior_h1"
    with pytest.raises(ParameterError) as err:
        bl.chair_varshney_llr([1, 0], 0.9, 0.1, "pm1")
    assert err.value.name == "u[1]"


# ----------------------------------------------------------------- Bayes threshold eq 22
def test_bayes_threshold_eq21b_and_eq22():
    # eq 21b / sec 2.2.3.5 example: P0/P1 = 0.7/0.3 with 0-1 costs
    assert bl.bayes_threshold(0.3, c00=0, c01=1, c10=1, c11=0) == pytest.approx(7 / 3, rel=1e-14)
    # eq 22 by hand: 0.7 (3 - 1) / (0.3 (5 - 0)) = 1.4 / 1.5
    assert bl.bayes_threshold(0.3, c00=1, c01=5, c10=3, c11=0) == pytest.approx(1.4 / 1.5, rel=1e-14)
    assert bl.bayes_log_threshold(0.3, 1, 5, 3, 0) == pytest.approx(math.log(1.4 / 1.5), rel=1e-13)
    # chapter case [b]: both differences negative -> still a positive threshold
    assert bl.bayes_threshold(0.5, c00=4, c01=1, c10=2, c11=3) == pytest.approx((4 - 2) / (3 - 1), rel=1e-14)


@pytest.mark.parametrize(
    "args, name",
    [
        ((0.5, 0, 1, 1, 1), "c01"),  # C01 = C11: zero denominator
        ((0.5, 1, 1, 1, 0), "c10"),  # C10 = C00: lambda_0 = 0
        ((0.5, 0, 0, 1, 1), "c10"),  # C10 > C00 but C01 < C11: negative
        ((0.0, 0, 1, 1, 0), "prior_h1"),
        ((1.2, 0, 1, 1, 0), "prior_h1"),
        ((0.5, 0, math.inf, 1, 0), "c01"),
    ],
)
def test_bayes_threshold_rejects_meaningless_costs(args, name):
    with pytest.raises(ParameterError) as err:
        bl.bayes_threshold(*args)
    assert err.value.name == name


# ----------------------------------------------------------------- k-out-of-n error rates
def brute_force_count_tail(k, probs):
    total = Fraction(0)
    fr = [Fraction(p).limit_denominator(10**12) for p in probs]
    for bits in itertools.product((0, 1), repeat=len(probs)):
        if sum(bits) >= k:
            term = Fraction(1)
            for b, p in zip(bits, fr):
                term *= p if b else 1 - p
            total += term
    return total


def test_k_of_n_identical_taxels_matches_binomial():
    n, pd, pf = 57, 0.995, 0.003
    for k in (1, 7, 29, 57):
        p_detect, p_false = bl.k_of_n_error_rates(k, np.full(n, pd), pf)
        assert p_detect == pytest.approx(stats.binom.sf(k - 1, n, pd), rel=1e-12)
        ref_false = mpmath.fsum(
            mpmath.binomial(n, m) * mpmath.mpf(pf) ** m * (1 - mpmath.mpf(pf)) ** (n - m) for m in range(k, n + 1)
        )
        assert rel_ok(p_false, ref_false)


def rel_ok(ours, exact, rel=1e-11):
    return abs(mpmath.mpf(ours) - exact) <= rel * abs(exact)


def test_k_of_n_heterogeneous_matches_enumeration():
    pd = [0.9985, 0.978, 0.97, 0.948, 0.9938, 0.9926, 0.9915, 0.9907]
    pf = [0.0005, 0.0023, 0.0010, 0.0002, 0.0002, 0.0004, 0.0005, 0.0013]
    for k in (1, 3, 8):
        p_detect, p_false = bl.k_of_n_error_rates(k, pd, pf)
        assert p_detect == pytest.approx(float(brute_force_count_tail(k, pd)), rel=1e-10)
        assert p_false == pytest.approx(float(brute_force_count_tail(k, pf)), rel=1e-10)


def test_count_rule_rates_in_log_domain():
    n, pd, pf = 120, 0.99, 0.002
    m = 100
    rates = bl.count_rule_error_rates(m, np.full(n, pd), np.full(n, pf))
    ref_false = mpmath.fsum(
        mpmath.binomial(n, j) * mpmath.mpf(pf) ** j * (1 - mpmath.mpf(pf)) ** (n - j) for j in range(m, n + 1)
    )
    ref_miss = mpmath.fsum(
        mpmath.binomial(n, j) * mpmath.mpf(pd) ** j * (1 - mpmath.mpf(pd)) ** (n - j) for j in range(0, m)
    )
    assert ref_false < mpmath.mpf("1e-240")
    assert abs(rates.log_p_false_alarm - float(mpmath.log(ref_false))) < 1e-11 * abs(float(mpmath.log(ref_false)))
    assert abs(rates.log_p_miss - float(mpmath.log(ref_miss))) < 1e-11 * abs(float(mpmath.log(ref_miss)))
    assert rates.p_detect == pytest.approx(float(1 - ref_miss), rel=1e-13)
    # edges: always / never H1
    always = bl.count_rule_error_rates(0, [0.9, 0.8], [0.1, 0.2])
    never = bl.count_rule_error_rates(3, [0.9, 0.8], [0.1, 0.2])
    assert always.p_detect == 1.0 and always.p_false_alarm == 1.0 and always.log_p_miss == -math.inf
    assert never.p_detect == 0.0 and never.p_false_alarm == 0.0 and never.log_p_miss == 0.0


def test_rates_near_one_are_correctly_rounded():
    # P_D = 1 - P(K <= 6) with P(K <= 6) ~ 1e-110 (57 taxels, pd = 0.995): exactly 1.0 in
    # double precision; P_F of "at least 1 present" = 1 - 0.997^57, by hand
    rates = bl.count_rule_error_rates(7, np.full(57, 0.995), 0.003)
    miss = 1 - _tail_mpmath(57, "0.995", 7)
    assert miss < mpmath.mpf("1e-100") and rates.p_detect == 1.0
    rates = bl.count_rule_error_rates(1, np.full(57, 0.995), np.full(57, 0.003))
    assert rates.p_false_alarm == pytest.approx(float(1 - mpmath.mpf("0.997") ** 57), rel=1e-15)
    rates = bl.count_rule_error_rates(56, np.full(57, 0.999), np.full(57, 0.5))
    assert rates.p_detect == pytest.approx(float(_tail_mpmath(57, "0.999", 56)), rel=1e-15)


def _tail_mpmath(n, p, m):
    p = mpmath.mpf(p)
    return mpmath.fsum(mpmath.binomial(n, j) * p**j * (1 - p) ** (n - j) for j in range(m, n + 1))


@pytest.mark.parametrize("k", [0, 4, 2.5, True])
def test_k_out_of_range(k):
    with pytest.raises(ParameterError) as err:
        bl.k_of_n_error_rates(k, [0.9, 0.9, 0.9], 0.1)
    assert err.value.name == "k"


# ----------------------------------------------------------------- Neyman-Pearson fusion
def np_reference_by_enumeration(pd, pf, alpha):
    """Textbook randomised N-P test over all 2^n vectors, exact rational arithmetic."""
    pdf = [Fraction(p).limit_denominator(10**12) for p in pd]
    pff = [Fraction(p).limit_denominator(10**12) for p in pf]
    atoms: dict[Fraction, list[Fraction]] = {}
    for bits in itertools.product((0, 1), repeat=len(pd)):
        l1 = l0 = Fraction(1)
        for b, d, f in zip(bits, pdf, pff):
            l1 *= d if b else 1 - d
            l0 *= f if b else 1 - f
        ratio = l1 / l0
        entry = atoms.setdefault(ratio, [Fraction(0), Fraction(0)])
        entry[0] += l0
        entry[1] += l1
    ratios = sorted(atoms, reverse=True)
    a = Fraction(alpha).limit_denominator(10**12)
    above0 = above1 = Fraction(0)
    for r in ratios:
        p0, p1 = atoms[r]
        if above0 + p0 >= a:
            gamma = (a - above0) / p0
            return math.log(r), float(gamma), float(above1 + gamma * p1)
        above0 += p0
        above1 += p1
    raise AssertionError("alpha not reached")


def test_np_enumeration_matches_rational_reference():
    pd = [0.9985, 0.978, 0.97, 0.948, 0.9938, 0.9926, 0.9915, 0.9907, 0.70]
    pf = [0.0005, 0.0023, 0.0010, 0.0002, 0.0002, 0.0004, 0.0005, 0.0013, 0.2]
    for alpha in (0.2, 0.01, 1e-4):
        rule = bl.neyman_pearson_fusion(pd, pf, alpha)
        ref_tau, ref_gamma, ref_power = np_reference_by_enumeration(pd, pf, alpha)
        assert rule.method == "enumerate" and rule.optimal
        assert rule.log_threshold == pytest.approx(ref_tau, rel=1e-9)
        assert rule.gamma == pytest.approx(ref_gamma, rel=1e-8, abs=1e-12)
        assert rule.detection_probability == pytest.approx(ref_power, rel=1e-9)
        assert rule.achieved_false_alarm == pytest.approx(alpha, rel=1e-9)


def test_np_identical_taxels_is_randomised_k_of_n_with_binomial_rates():
    n, pd, pf, alpha = 25, 0.8, 0.05, 0.01
    rule = bl.neyman_pearson_fusion(pd, np.full(n, pf), alpha)
    assert rule.method == "identical" and rule.optimal
    # textbook: smallest k with P0(K > k) <= alpha
    k = next(k for k in range(n + 1) if stats.binom.sf(k, n, pf) <= alpha)
    gamma = (alpha - stats.binom.sf(k, n, pf)) / stats.binom.pmf(k, n, pf)
    power = stats.binom.sf(k, n, pd) + gamma * stats.binom.pmf(k, n, pd)
    assert rule.count_threshold == k
    assert rule.gamma == pytest.approx(gamma, rel=1e-10)
    assert rule.detection_probability == pytest.approx(power, rel=1e-10)
    assert rule.achieved_false_alarm == pytest.approx(alpha, rel=1e-12)
    expected_tau = n * math.log((1 - pd) / (1 - pf)) + k * math.log(pd * (1 - pf) / (pf * (1 - pd)))
    assert rule.log_threshold == pytest.approx(expected_tau, rel=1e-12)


def test_np_beats_every_deterministic_count_rule_of_no_larger_size():
    rng = np.random.default_rng(3)
    pd = rng.uniform(0.55, 0.99, 12)
    pf = rng.uniform(0.01, 0.4, 12)
    alpha = 0.05
    rule = bl.neyman_pearson_fusion(pd, pf, alpha)
    count_rule = bl.neyman_pearson_fusion(pd, pf, alpha, method="count")
    assert not count_rule.optimal
    assert count_rule.achieved_false_alarm == pytest.approx(alpha, rel=1e-12)
    assert rule.detection_probability >= count_rule.detection_probability
    for k in range(1, 13):
        p_detect, p_false = bl.k_of_n_error_rates(k, pd, pf)
        if p_false <= alpha:
            assert rule.detection_probability >= p_detect


def test_np_equal_pd_pf_is_pure_randomisation():
    rule = bl.neyman_pearson_fusion(0.3, np.full(6, 0.3), 0.1)
    assert rule.gamma == pytest.approx(0.1, rel=1e-12)
    assert rule.detection_probability == pytest.approx(0.1, rel=1e-12)
    assert rule.decide([1, 1, 1, -1, -1, -1], "pm1") == "undecided"


def test_np_decide_semantics_and_monte_carlo_size():
    pd = [0.9, 0.85, 0.7, 0.95]
    pf = [0.1, 0.2, 0.05, 0.3]
    rule = bl.neyman_pearson_fusion(pd, pf, 0.1)
    values = {
        bits: bl.np_log_statistic(bits, pd, pf, "01") for bits in itertools.product((0, 1), repeat=4)
    }
    tol = 1e-9 * max(1, abs(rule.log_threshold))
    for bits, v in values.items():
        verdict = rule.decide(bits, "01")
        if v > rule.log_threshold + tol:
            assert verdict == "H1"
        elif v < rule.log_threshold - tol:
            assert verdict == "H0"
        else:
            assert verdict == "undecided"
    # with a generator, the empirical size under H0 is alpha (fixed seed: deterministic)
    rng = np.random.default_rng(2024)
    trials = 20000
    draws = (rng.random((trials, 4)) < np.array(pf)).astype(int)
    hits = sum(rule.decide(row, "01", rng=rng) == "H1" for row in draws)
    sigma = math.sqrt(0.1 * 0.9 / trials)
    assert abs(hits / trials - 0.1) < 5 * sigma


def test_np_count_method_for_many_heterogeneous_taxels():
    rng = np.random.default_rng(5)
    pd = rng.uniform(0.9, 0.999, 57)
    pf = rng.uniform(1e-4, 8e-3, 57)
    rule = bl.neyman_pearson_fusion(pd, pf, 1e-3)
    assert rule.method == "count" and rule.statistic == "present_count" and rule.log_threshold is None
    k = rule.count_threshold
    # exact size from the Poisson-binomial law, checked against the brute k-of-n rates
    p_detect_above, p_false_above = bl.k_of_n_error_rates(k + 1, pd, pf)
    p_detect_at_least, p_false_at_least = bl.k_of_n_error_rates(k, pd, pf)
    assert p_false_above < 1e-3 <= p_false_at_least
    gamma = (1e-3 - p_false_above) / (p_false_at_least - p_false_above)
    assert rule.gamma == pytest.approx(gamma, rel=1e-9)
    u = np.full(57, -1)
    u[:k] = 1
    assert rule.decide(u, "pm1") == "undecided"
    u[k] = 1
    assert rule.decide(u, "pm1") == "H1"


def test_np_bad_inputs():
    with pytest.raises(ParameterError) as err:
        bl.neyman_pearson_fusion([0.9, 0.8], [0.1, 0.2], 0.0)
    assert err.value.name == "false_alarm"
    with pytest.raises(ParameterError) as err:
        bl.neyman_pearson_fusion(np.full(25, 0.9), np.linspace(0.01, 0.2, 25), 0.1, method="enumerate")
    assert err.value.name == "method"


# ----------------------------------------------------------------- chapter sec. 6.2 data
def chapter_data():
    text = resources.files("fusion_center").joinpath("data/chapter_57_pf_pm.toml").read_bytes()
    return tomllib.loads(text.decode())["printed"]


def test_chapter_matrices_as_printed_have_wrong_lengths():
    data = chapter_data()
    assert len(data["y_mv"]) == 57 and len(data["noise_mv"]) == 57
    assert len(data["pf"]) == data["pf_count"] == 55  # text claims 57
    assert len(data["pm"]) == data["pm_count"] == 97  # text claims 57


def test_chapter_present_cells_not_reproduced_by_any_zeta():
    data = chapter_data()
    y_minus_n = np.array(data["y_mv"]) - np.array(data["noise_mv"])
    printed = set(data["present_cells"])
    candidates = np.unique(np.concatenate(([0.0], y_minus_n)))
    for zeta in candidates:  # every distinct present set arises at one of these cut-offs
        present = {i + 1 for i in np.flatnonzero(y_minus_n >= zeta)}
        assert present != printed
    # seven present cells do arise, for 9.5 < zeta <= 11.7, but different ones
    seven = {i + 1 for i in np.flatnonzero(y_minus_n >= 10.0)}
    assert seven == {5, 8, 18, 19, 26, 28, 32}
    # cell 20 (printed present) has Y - N = 3.8 while cell 26 (printed absent) has 16.0
    assert y_minus_n[19] == pytest.approx(3.8) and y_minus_n[25] == pytest.approx(16.0)


def test_chapter_printed_llr_and_np_values_are_mutually_inconsistent():
    # with P1 = P0, eq 31 is the logarithm of eq 32 in whatever base: check both bases
    data = chapter_data()
    ln_np = math.log(data["np_ratio"])
    log10_np = math.log10(data["np_ratio"])
    assert abs(ln_np - data["llr"]) > 100 and abs(log10_np - data["llr"]) > 5


def test_chapter_llr_from_printed_matrices_against_mpmath():
    """Reconstruction: P_F = 55 printed + median for cells 56, 57; P_M = first 57 printed."""
    data = chapter_data()
    pf = np.concatenate((data["pf"], [np.median(data["pf"])] * 2))
    pm = np.array(data["pm"][:57])
    u = -np.ones(57, dtype=int)
    u[np.array(data["present_cells"]) - 1] = 1
    ours = bl.chair_varshney_llr(u, 1 - pm, pf, "pm1")
    ref = eq31_mpmath(u, pm, pf)
    assert abs(ours - float(ref)) < 1e-11
    assert bl.np_log_statistic(u, 1 - pm, pf, "pm1") == pytest.approx(ours, rel=1e-14)
    # the printed -135.9376 is not what eq 31 gives on the printed matrices (-236.05, see
    # docs/chapter-notes.md); the two missing P_F entries belong to absent cells and move
    # the value by < 0.02 whatever they are in the printed range
    for fill in (min(data["pf"]), max(data["pf"])):
        pf_fill = np.concatenate((data["pf"], [fill] * 2))
        assert abs(bl.chair_varshney_llr(u, 1 - pm, pf_fill, "pm1") - ours) < 0.02
    assert abs(ours - data["llr"]) > 50
