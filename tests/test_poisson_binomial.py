"""Poisson-binomial law of the present count, checked against mpmath at 50 digits."""

from __future__ import annotations

import itertools

import mpmath
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from fusion_center.core import poisson_binomial as pb
from taxel_net.errors import ParameterError

@pytest.fixture(autouse=True, scope="module")
def _references_at_50_digits():
    """The mpmath references of this module at 50 digits, restored after it (not set at import:
    that leaked into whichever module ran next in the worker)."""
    with mpmath.workdps(50):
        yield


def exact_pmf_by_enumeration(probs):
    """P(K = m) summing the probability of every one of the 2^n decision vectors."""
    n = len(probs)
    p = [mpmath.mpf(x) for x in probs]
    out = [mpmath.mpf(0)] * (n + 1)
    for bits in itertools.product((0, 1), repeat=n):
        term = mpmath.mpf(1)
        for b, pi in zip(bits, p):
            term *= pi if b else (1 - pi)
        out[sum(bits)] += term
    return out


def exact_pmf_by_polynomial(probs):
    """Coefficients of prod_i ((1 - p_i) + p_i z) at 50 digits (mpmath, scalar loops)."""
    coeffs = [mpmath.mpf(1)]
    for x in probs:
        pi = mpmath.mpf(x)
        new = [mpmath.mpf(0)] * (len(coeffs) + 1)
        for m, c in enumerate(coeffs):
            new[m] += c * (1 - pi)
            new[m + 1] += c * pi
        coeffs = new
    return coeffs


def rel_close(ours: float, exact, rel: float = 1e-12) -> bool:
    exact = mpmath.mpf(exact)
    if exact == 0:
        return ours == 0
    return abs((mpmath.mpf(ours) - exact) / exact) < rel


def test_pmf_matches_enumeration_small_n():
    probs = [0.013, 0.5, 0.77, 0.0042, 0.91, 0.3, 0.66, 0.05]
    exact = exact_pmf_by_enumeration(probs)
    ours = pb.pmf(probs)
    ours_log = pb.log_pmf(probs)
    assert ours.shape == (len(probs) + 1,)
    for m in range(len(probs) + 1):
        assert rel_close(ours[m], exact[m])
        assert abs(ours_log[m] - float(mpmath.log(exact[m]))) < 1e-12


def test_identical_probabilities_match_binomial_closed_form():
    n, p = 30, 0.137
    ours = pb.log_pmf([p] * n)
    for m in range(n + 1):
        exact = mpmath.binomial(n, m) * mpmath.mpf(p) ** m * (1 - mpmath.mpf(p)) ** (n - m)
        assert abs(ours[m] - float(mpmath.log(exact))) < 1e-11


def test_deep_tails_stay_exact_in_log_domain():
    # 60 taxels, false-alarm 1e-6 each: P(K >= 58) ~ 1e-345, below the smallest double
    n, p = 60, 1e-6
    probs = [p] * n
    exact = mpmath.fsum(
        mpmath.binomial(n, m) * mpmath.mpf(p) ** m * (1 - mpmath.mpf(p)) ** (n - m) for m in range(58, n + 1)
    )
    assert exact < mpmath.mpf("1e-330")
    assert abs(pb.log_sf(probs, 58) - float(mpmath.log(exact))) < 1e-11
    assert pb.sf(probs, 58) == 0.0  # honest underflow of the linear value, the log carries it


def test_heterogeneous_tail_against_mpmath_dp():
    rng = np.random.default_rng(7)
    probs = rng.uniform(1e-4, 8e-3, size=57)
    exact = exact_pmf_by_polynomial(probs)
    for k in (0, 1, 7, 20, 40, 57):
        tail = mpmath.fsum(exact[k:])
        head = mpmath.fsum(exact[: k + 1])
        assert abs(pb.log_sf(probs, k) - float(mpmath.log(tail))) < 1e-11 * max(1.0, abs(float(mpmath.log(tail))))
        assert abs(pb.log_cdf(probs, k) - float(mpmath.log(head))) < 1e-11 * max(1.0, abs(float(mpmath.log(head))))


def test_scipy_poisson_binom_sf_loses_the_tail_ours_does_not():
    """The reason this module exists: scipy's sf is 1 - cdf, so tails below ~1e-16 are 0."""
    if not hasattr(stats, "poisson_binom"):
        pytest.skip("scipy without stats.poisson_binom (< 1.15)")
    probs = np.full(40, 1e-3)
    exact = mpmath.fsum(exact_pmf_by_polynomial(probs)[36:])  # P(K >= 36) = P(K > 35)
    assert exact > 0 and exact < mpmath.mpf("1e-100")
    scipy_sf = stats.poisson_binom.sf(35, probs)  # scipy: P(K > 35)
    assert not rel_close(float(scipy_sf), exact, rel=0.5)  # scipy is wrong here (0.0)
    assert rel_close(pb.sf(probs, 36), exact, rel=1e-11)


def test_edges_and_counts_outside_range():
    probs = [0.2, 0.4, 0.6]
    assert pb.log_sf(probs, 0) == 0.0 and pb.log_sf(probs, -3) == 0.0
    assert pb.log_sf(probs, 4) == -np.inf
    assert pb.log_cdf(probs, -1) == -np.inf and pb.log_cdf(probs, 3) == 0.0
    assert pb.cdf(probs, 0) == pytest.approx(0.8 * 0.6 * 0.4, rel=1e-14)
    assert pb.sf(probs, 3) == pytest.approx(0.2 * 0.4 * 0.6, rel=1e-14)
    # degenerate taxels: certain and impossible
    lp = pb.log_pmf([1.0, 0.0, 1.0])
    assert lp[2] == 0.0 and np.all(np.isneginf(lp[[0, 1, 3]]))
    assert list(pb.pmf([])) == [1.0]


@pytest.mark.parametrize("bad, name", [([0.2, 1.5], "probs[1]"), ([-0.1], "probs[0]"), ([0.3, np.nan], "probs[1]")])
def test_invalid_probabilities_are_named(bad, name):
    with pytest.raises(ParameterError) as err:
        pb.pmf(bad)
    assert err.value.name == name
    assert "[0, 1]" in str(err.value)


def test_non_integer_count_rejected():
    with pytest.raises(ParameterError) as err:
        pb.log_sf([0.5, 0.5], 1.5)
    assert err.value.name == "k"


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(min_value=0.0, max_value=1.0), min_size=1, max_size=40))
def test_pmf_is_a_distribution_and_log_agrees(probs):
    linear = pb.pmf(probs)
    logs = pb.log_pmf(probs)
    assert np.all(linear >= 0)
    assert abs(linear.sum() - 1.0) < 1e-12
    # mean of the law equals the sum of the probabilities
    assert abs(np.dot(np.arange(linear.size), linear) - sum(probs)) < 1e-9
    visible = linear > 1e-250
    assert np.allclose(np.exp(logs[visible]), linear[visible], rtol=1e-10, atol=0)


def test_large_n_matches_binomial_logpmf():
    n, p = 3000, 0.021
    ours = pb.log_pmf(np.full(n, p))
    ref = stats.binom.logpmf(np.arange(n + 1), n, p)
    finite = np.isfinite(ref) & (ref > -600)
    assert np.allclose(ours[finite], ref[finite], rtol=1e-9, atol=1e-9)
