"""The fusion centre's service around patch nodes (issue 14): thresholds of the centralised
tests at scale, the master's configuration of patch nodes against a stand-in SDO server."""

import numpy as np
import pytest

from fusion_center.service.centralised_tests import glrt_threshold


@pytest.mark.parametrize("n, d, alpha", [(40, 2.0, 0.01), (200, 5.0, 0.002)])
def test_the_exact_glrt_law_gives_the_monte_carlo_quantile(n, d, alpha):
    # sum_i max(0, LLR_i), LLR_i ~ N(-d_i^2/2, d_i^2): P0(U > tau) = alpha within the sampling error
    dd = np.full(n, d)
    dd[: n // 4] = 1.5 * d
    tau = glrt_threshold(dd, alpha)
    rng = np.random.default_rng(3)
    m = 200_000
    u = np.maximum(rng.standard_normal((m, n)) * dd - dd * dd / 2, 0).sum(axis=1)
    p = float(np.mean(u > tau))
    sd = np.sqrt(alpha * (1 - alpha) / m)
    assert p <= alpha + 3 * sd and p >= alpha - 6 * sd - alpha * 0.05  # conservative by at most a grid step
