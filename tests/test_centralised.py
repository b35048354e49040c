"""Centralised raw-data test: statistics against scipy / brute force / mpmath, thresholds
against their closed forms (tests of fusion_center.core.centralised)."""

from __future__ import annotations

import itertools

import mpmath as mp
import numpy as np
import pytest
from scipy.stats import norm

from fusion_center import evaluation, stages
from fusion_center.core import centralised
from fusion_center.core.encoding import local_decision
from taxel_net.errors import ParameterError
from taxel_net.scene import load_scene


def test_per_taxel_decisions_same_as_the_nodes():
    rng = np.random.default_rng(3)
    x = rng.normal(1.0, 1.0, (50, 7))
    noise = rng.uniform(0, 0.5, 7)
    zeta = rng.uniform(0, 1.5, 7)
    got = centralised.per_taxel_decisions(x, noise, zeta, "01")
    assert np.array_equal(got, ((x - noise) >= zeta).astype(np.int8))
    assert np.array_equal(centralised.per_taxel_decisions(x, noise, zeta, "pm1"), local_decision(x, noise, zeta, "pm1"))


def test_taxel_llr_is_gaussian_log_ratio():
    y = np.linspace(-3, 6, 11)
    s, sd = 2.5, 0.7
    want = norm.logpdf(y, s, sd) - norm.logpdf(y, 0, sd)
    assert np.allclose(centralised.taxel_llr(y, sd, s), want, rtol=1e-12, atol=1e-12)


@mp.workdps(50)
def test_known_statistic_single_and_mixture():
    rng = np.random.default_rng(4)
    noise = np.array([0.1, 0.2, 0.0, 0.3])
    sigma = np.array([0.5, 1.0, 0.8, 1.2])
    pats = np.array([[2.0, 0.0, 1.0, 0.0], [0.0, 3.0, 0.0, 1.5]])
    x = rng.normal(0.5, 1.0, 4)
    y = x - noise
    one = centralised.make_params(noise, sigma, pats[:1], method="known")
    want1 = np.sum(norm.logpdf(y, pats[0], sigma) - norm.logpdf(y, 0, sigma))
    assert centralised.centralised_llr(x, one) == pytest.approx(want1, rel=1e-12)
    both = centralised.make_params(noise, sigma, pats, method="known")
    terms = [mp.fsum(mp.log(mp.npdf(yi, si, sdi)) - mp.log(mp.npdf(yi, 0, sdi)) for yi, si, sdi in zip(y, p, sigma))
             for p in pats]
    want2 = mp.log((mp.exp(terms[0]) + mp.exp(terms[1])) / 2)
    assert centralised.centralised_llr(x, both) == pytest.approx(float(want2), rel=1e-12)


def test_glrt_is_max_over_all_footprints():
    rng = np.random.default_rng(5)
    n = 6
    sigma = rng.uniform(0.5, 1.5, n)
    s = rng.uniform(1.0, 4.0, n)
    params = centralised.make_params(np.zeros(n), sigma, s[None, :], s, method="glrt")
    for _ in range(20):
        x = rng.normal(1.0, 1.5, n)
        best = max(
            sum(norm.logpdf(x[i], s[i], sigma[i]) - norm.logpdf(x[i], 0, sigma[i]) for i in subset)
            for r in range(n + 1) for subset in itertools.combinations(range(n), r)
        )
        assert centralised.centralised_llr(x, params) == pytest.approx(best, abs=1e-10)


def test_known_threshold_closed_form_holds_its_false_alarm():
    sigma = np.array([1.0, 0.5, 2.0])
    s = np.array([1.0, 0.5, 1.0])
    params = centralised.make_params(np.zeros(3), sigma, s[None, :], method="known")
    tau = centralised.centralised_threshold(params, 0.05)
    rng = np.random.default_rng(6)
    stat = centralised.sample_h0_statistic(params, 400_000, rng, "known")
    pf = np.mean(stat > tau)
    assert abs(pf - 0.05) < 5 * np.sqrt(0.05 * 0.95 / 400_000)


def test_glrt_threshold_single_taxel_closed_form():
    # n = 1: P0(max(0, L) > t) = P0(L > t) = Q((t + d^2/2)/d) for t > 0, d = S/sigma
    sigma, s, alpha = 1.0, 2.0, 0.01
    d = s / sigma
    t_exact = d * norm.isf(alpha) - d * d / 2
    params = centralised.make_params([0.0], [sigma], [[s]], method="glrt")
    t_mc = centralised.centralised_threshold(params, alpha, rng=np.random.default_rng(7), n_samples=400_000)
    # quantile standard error: sqrt(a(1-a)/N) / density at the quantile (density of L: N(-d^2/2, d^2))
    dens = norm.pdf(t_exact, -d * d / 2, d)
    assert abs(t_mc - t_exact) < 5 * np.sqrt(alpha * (1 - alpha) / 400_000) / dens


def test_bad_inputs():
    with pytest.raises(ParameterError, match="sigma_mv"):
        centralised.make_params([0.0, 0.0], [1.0, 0.0], [[1.0, 1.0]])
    params = centralised.make_params([0.0], [1.0], [[1.0]])
    with pytest.raises(ParameterError, match="false_alarm"):
        centralised.centralised_threshold(params, 1.5)
    with pytest.raises(ParameterError, match="readings_mv"):
        centralised.centralised_llr([1.0, 2.0], params)


def test_params_from_scene_and_support():
    scene = load_scene("scenes/matrix57.toml")
    assert stages.centralised_support(scene) is None
    params = evaluation.params_from_scene(scene, "known")
    assert params.signal_patterns_mv.shape == (1, 57)
    assert np.count_nonzero(params.signal_patterns_mv) == 6  # the 6 contacted taxels
    chapter = load_scene("scenes/matrix57_chapter.toml")  # sigma = 0: no raw LLR
    assert "noise_sigma_mv = 0" in stages.centralised_support(chapter)
