"""Monte Carlo: the vectorised rule evaluators against the per-cycle functions of
fusion_center.core.rules / baselines on random inputs, exact taxel rates against mpmath, the Wilson
interval by hand, and simulated rates against the exact Poisson-binomial values."""

from __future__ import annotations

import dataclasses
import math

import mpmath as mp
import numpy as np
import pytest

from fusion_center import evaluation
from fusion_center.core import baselines, montecarlo, rules
from fusion_center.core.encoding import ABSENT
from taxel_net.scene import load_scene


def _random_u(rng, t, n, enc):
    present = rng.random((t, n)) < rng.uniform(0.1, 0.9)
    return present, np.where(present, 1, ABSENT[enc]).astype(np.int8)


@pytest.mark.parametrize("enc", ["pm1", "01"])
@pytest.mark.parametrize("p,q", [(1.0, 1.0), (0.0, 1.0), (2.0, 0.5), (0.0, 0.0), (1.3, 2.0)])
def test_preferential_batch_matches_rule(enc, p, q):
    rng = np.random.default_rng(11)
    for n in (1, 2, 3, 18):
        present, u = _random_u(rng, 40, n, enc)
        got = montecarlo.preferential_batch(present, p, q, enc)
        want = [rules.preferential(row, p, q, enc) for row in u]
        assert np.allclose(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("enc", ["pm1", "01"])
def test_count_batches_match_rules(enc):
    rng = np.random.default_rng(12)
    present, u = _random_u(rng, 60, 57, enc)
    assert np.array_equal(montecarlo.additive_batch(present, enc), [rules.additive(r, enc) for r in u])
    assert np.array_equal(montecarlo.multiplicative_ln_batch(present, enc),
                          [rules.multiplicative(r, enc).ln_U_G for r in u])


def test_llr_and_np_batches_match_baselines():
    rng = np.random.default_rng(13)
    n = 30
    pd = rng.uniform(0.5, 0.999, n)
    pf = rng.uniform(1e-4, 0.2, n)
    present, u = _random_u(rng, 50, n, "pm1")
    got = montecarlo.chair_varshney_batch(present, pd, pf, 0.3)
    want = [baselines.chair_varshney_llr(r, pd, pf, "pm1", 0.3) for r in u]
    assert np.allclose(got, want, rtol=1e-10)
    got = montecarlo.np_log_statistic_batch(present, pd, pf)
    want = [baselines.np_log_statistic(r, pd, pf, "pm1") for r in u]
    assert np.allclose(got, want, rtol=1e-10)


@pytest.mark.parametrize("n", [8, 40])
def test_np_decide_batch_matches_rule_off_the_boundary(n):
    rng = np.random.default_rng(14)
    pd = rng.uniform(0.6, 0.99, n)
    pf = rng.uniform(0.01, 0.2, n)
    rule = baselines.neyman_pearson_fusion(pd, pf, 0.05)
    present, u = _random_u(rng, 200, n, "pm1")
    got = montecarlo.np_decide_batch(rule, present, np.random.default_rng(0))
    for row, g in zip(u, got):
        d = rule.decide(row, "pm1")
        if d != "undecided":
            assert g == (d == "H1")


@mp.workdps(50)
def test_taxel_rates_against_mpmath():
    s = np.array([0.0, 2.0, 5.6, 10.0])
    zeta, sigma = 3.0, 0.7
    got = montecarlo.taxel_rates(s, zeta, sigma)
    for gi, si in zip(got, s):
        want = mp.erfc((mp.mpf(zeta) - mp.mpf(si)) / (mp.mpf(sigma) * mp.sqrt(2))) / 2
        assert gi == pytest.approx(float(want), rel=1e-13)
    assert montecarlo.taxel_rates([2.0, 4.0], 3.0, 0.0).tolist() == [0.0, 1.0]


def test_wilson_interval_by_hand():
    z = 1.959963984540054
    lo, hi = montecarlo.wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(z * z / (10 + z * z))
    # 5 of 10: centre 0.5, half-width z sqrt(0.25/10 + z^2/400) / (1 + z^2/10)
    lo, hi = montecarlo.wilson_interval(5, 10)
    half = z * math.sqrt(0.025 + z * z / 400) / (1 + z * z / 10)
    assert (lo, hi) == (pytest.approx(0.5 - half), pytest.approx(0.5 + half))


def _noisy_small_scene():
    """matrix57 with 4x the noise: per-taxel rates of a few percent, so MC resolves them."""
    base = load_scene("scenes/small_object.toml")
    taxels = tuple(dataclasses.replace(t, noise_sigma_mv=t.noise_sigma_mv * 2.5) for t in base.taxels)
    return dataclasses.replace(base, taxels=taxels)


def test_simulated_count_rules_match_exact_poisson_binomial():
    scene = _noisy_small_scene()
    n_trials = 40_000
    res = evaluation.simulate(scene, n_trials, np.random.default_rng(15), rules=["k-of-n"], central=False)
    r = res.rules["k-of-n"]
    for rate in (r.pf, r.pd):
        sd = math.sqrt(rate.exact * (1 - rate.exact) / n_trials)
        assert abs(rate.estimate - rate.exact) < 5 * sd + 1e-12
    # the exact values are the Poisson-binomial tails of the Gaussian-model rates
    # (static object: one footprint) - cross-check with baselines.count_rule_error_rates
    assert res.taxel_pd_patterns.shape[0] == 1
    ref = baselines.count_rule_error_rates(scene.fusion.k, res.taxel_pd_patterns[0], res.taxel_pf)
    assert r.pf.exact == pytest.approx(ref.p_false_alarm, rel=1e-12)
    assert r.pd.exact == pytest.approx(ref.p_detect, rel=1e-12)
    assert 0 < r.pf.exact < 1 and 0 < r.pd.exact < 1
    assert res.prior_h1 == pytest.approx(100 / 200)


def test_simulated_centralised_false_alarm_and_total_error():
    scene = _noisy_small_scene()
    n_trials = 40_000
    res = evaluation.simulate(scene, n_trials, np.random.default_rng(16), rules=["k-of-n", "centralised_known"])
    a = scene.fusion.np_false_alarm
    pf = res.rules["centralised_known"].pf
    assert abs(pf.estimate - a) < 5 * math.sqrt(a * (1 - a) / n_trials)
    te = res.rules["k-of-n"].total_error
    pd, pf = res.rules["k-of-n"].pd, res.rules["k-of-n"].pf
    assert te["estimate"] == pytest.approx(0.5 * (1 - pd.estimate) + 0.5 * pf.estimate)
    assert te["ci95"][0] <= te["estimate"] <= te["ci95"][1]


def test_exact_count_roc_endpoints_and_monotone():
    pf = np.array([0.1, 0.2, 0.05])
    pdp = np.array([[0.9, 0.8, 0.7]])
    roc = montecarlo.exact_count_roc(pf, pdp, np.array([1.0]))
    assert roc["pf"][0] == pytest.approx(1.0) and roc["pf"][-1] == 0.0
    # K >= 3 under H0: product of the pf_i
    assert roc["pf"][3] == pytest.approx(0.1 * 0.2 * 0.05)
    assert roc["pd"][3] == pytest.approx(0.9 * 0.8 * 0.7)
    assert np.all(np.diff(roc["pd"]) <= 1e-15)
