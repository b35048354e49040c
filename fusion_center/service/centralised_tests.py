"""Raw mode (issue 6): the centralised raw-data tests of a cycle's readings.

In raw mode the nodes send X_i (TPDO2, REAL32 mV) instead of u_i; the centre decides per taxel
with the nodes' own test (eqs 1-4, ``encoding.local_decision``, in the pipeline) and fuses
those decisions with every rule as in decision mode, and it also runs the centralised raw-data
tests of :mod:`fusion_center.core.centralised` (``rules.centralised_glrt``,
``rules.centralised_known``: statistic, threshold at the scene's ``np_false_alarm``, decision)
- the "what you lose by deciding locally" reference. Their parameters are built once
(``params_from_scene``); a cycle with readings missing uses the same test on the received
taxels (threshold recomputed once per missing-set, cached).

Large scenes (more than :data:`MONTE_CARLO_TAXELS` taxels, e.g. the 4,096-taxel skins): the
Monte Carlo threshold of ``evaluation.params_from_scene`` (200,000 H0 cycles of n readings,
and for ``known`` a product with every footprint) takes minutes; the centre computes it instead
as ``glrt``: the exact H0 law of sum_i max(0, LLR_i) (independent terms, each a Gaussian
LLR_i ~ N(-d_i^2/2, d_i^2), d_i = |S_i| / sigma_i, rectified at 0: a point mass at 0 and a
truncated Gaussian) by convolution on a grid of step :data:`GLRT_GRID_MV` (FFT), tau the first
grid point with P0(U > tau) <= alpha plus one step; ``known``: the union bound of
:meth:`CentralisedTests.params_for` (P_F <= alpha), as for a cycle with readings missing.
"""

from __future__ import annotations

import math

import numpy as np

from .. import evaluation
from ..core import centralised
from taxel_net.errors import ParameterError
from taxel_net.scene import Scene
from .decision_fusion import verdict
from .records import jsonable


MONTE_CARLO_TAXELS = 1024  # above: thresholds without Monte Carlo (module docstring)
GLRT_GRID = 0.002          # grid step of the exact glrt law (LLR units)


def glrt_threshold(d: np.ndarray, alpha: float, step: float = GLRT_GRID) -> float:
    """tau with P0(sum_i max(0, LLR_i) > tau) <= alpha, LLR_i ~ N(-d_i^2/2, d_i^2) independent
    (module docstring): the law on a grid by FFT convolution, one factor per distinct d_i."""
    from scipy.special import ndtr, ndtri

    d = np.asarray(d, dtype=float)
    d = d[d > 0]
    if d.size == 0:
        raise ParameterError("readings_mv", "taxels", "no taxel carries signal: no test")
    values, counts = np.unique(np.round(d, 9), return_counts=True)
    n = d.size
    # support: one term beyond x has P <= 1e-18 / n; the others add their mean and a wide margin
    far = float(np.max(-values * ndtri(1e-18 / n) - values**2 / 2))
    mean = float(np.sum(counts * (values * np.exp(-values**2 / 8) / np.sqrt(2 * np.pi))))
    top = max(far, 0.0) * 4 + 50.0 * mean + 10.0
    size = 1 << int(np.ceil(np.log2(top / step + 2)))
    edges = (np.arange(size + 1) - 0.5) * step  # bin k = ((k - 1/2) h, (k + 1/2) h]
    spectrum = np.ones(size // 2 + 1, dtype=complex)
    for value, count in zip(values, counts):
        cdf = ndtr((np.maximum(edges, 0.0) + value * value / 2) / value)  # P(LLR <= x), x >= 0
        pmf = np.diff(cdf)
        pmf[0] = cdf[1]  # the point mass at 0 (LLR <= 0) and (0, h/2]
        spectrum *= np.fft.rfft(pmf) ** int(count)
    law = np.clip(np.fft.irfft(spectrum, size), 0.0, None)
    tail = np.cumsum(law[::-1])[::-1]  # P(U >= k h)
    k = int(np.argmax(tail <= alpha))  # first k with P(U >= k h) <= alpha
    return float(k * step + step)


class CentralisedTests:
    """The centralised raw-data tests ``names`` (``centralised_glrt``, ``centralised_known``)
    of one scene: parameters and thresholds once per scene, per missing-set when readings
    are missing."""

    def __init__(self, scene: Scene, names):
        self.scene = scene
        self.params: dict[str, centralised.CentralisedParams] = {}
        for name in names:
            method = name.removeprefix("centralised_")
            if scene.n > MONTE_CARLO_TAXELS:
                self.params[name] = self._large_scene_params(scene, method)
            else:
                self.params[name] = evaluation.params_from_scene(scene, method)
        self._subsets: dict[tuple[str, bytes], object] = {}
        self._known_weights = None
        if any(p.method == "known" for p in self.params.values()):
            # imported here, once per scene, never on the cycle path: the first cycle with a
            # reading missing otherwise paid scipy.optimize's import (~0.15 s: a late SYNC)
            import scipy.optimize  # noqa: F401
            import scipy.special  # noqa: F401

    def _large_scene_params(self, scene: Scene, method: str):
        """The test's parameters without Monte Carlo (module docstring: exact glrt law, union
        bound for known)."""
        patterns = evaluation.scene_patterns(scene)[0]
        nominal = np.array([evaluation.nominal_signal_mv(t, scene.object) for t in scene.taxels])
        if patterns.shape[0] == 0:
            patterns = nominal[None, :]
        part = centralised.make_params([t.noise_mv for t in scene.taxels], [t.noise_sigma_mv for t in scene.taxels],
                                       patterns, nominal, method)
        alpha = float(scene.fusion.np_false_alarm)
        info = {"false_alarm": alpha}
        if method == "glrt":
            tau = glrt_threshold(np.abs(part.taxel_signal_mv) / part.sigma_mv, alpha)
            return centralised.CentralisedParams(part.noise_mv, part.sigma_mv, part.signal_patterns_mv,
                                                 part.taxel_signal_mv, method, tau, info)
        full = centralised.CentralisedParams(part.noise_mv, part.sigma_mv, part.signal_patterns_mv,
                                             part.taxel_signal_mv, method, 0.0, info)
        return self._subset_params(full, np.ones(scene.n, dtype=bool))

    def _known_full(self, params, readings: np.ndarray) -> float:
        """``centralised_llr`` of ``known`` over every taxel, its footprint weights computed once
        (the same operations in the same order: the same value; per cycle they cost as much as
        the product itself at 4,096 taxels x 96 footprints)."""
        cached = self._known_weights
        if cached is None or cached[0] is not params:
            inv_var = 1.0 / params.sigma_mv**2
            weights = np.ascontiguousarray((params.signal_patterns_mv * inv_var).T)
            offsets = -0.5 * np.sum(params.signal_patterns_mv**2 * inv_var, axis=1)
            cached = self._known_weights = (params, weights, offsets)
        x = centralised._finite(readings, "readings_mv")
        per_pattern = (x - params.noise_mv) @ cached[1] + cached[2]
        c = per_pattern.shape[-1]
        if c == 1:
            return float(per_pattern[0])
        from scipy.special import logsumexp

        return float(logsumexp(per_pattern) - np.log(c))

    def results(self, readings: np.ndarray, available: np.ndarray) -> dict[str, dict]:
        """Test name -> JSON-able result of the cycle (an error is reported, not raised)."""
        rule_results: dict[str, dict] = {}
        for name in self.params:
            try:
                result = self.test(name, readings, available)
            except ParameterError as exc:
                result = {"U_G": None, "threshold": None, "decision": "undecided", "p_h1": None,
                          "error": str(exc)}
            rule_results[name] = {k: jsonable(v) for k, v in result.items()}
        return rule_results

    def params_for(self, name: str, available: np.ndarray):
        """The test's parameters over the taxels with a reading.

        Full set: the scene's parameters (threshold at P_F = ``np_false_alarm``). With readings
        missing (a silent or missing node), no Monte Carlo in the worker - it would stall the
        live cycle - but a threshold that still guarantees P_F <= alpha, cached per missing-set:

        * ``glrt``: the received taxels' sum of max(0, LLR_i) is <= the full sum, so the full
          threshold keeps P_F <= alpha (a missing taxel adds no evidence);
        * ``known``: per footprint c the received LLR is Gaussian under H0,
          L_c ~ N(-d_c^2/2, d_c^2) (d_c^2 = sum over received S_i^2/sigma_i^2), and
          logmeanexp_c L_c <= max_c L_c, so tau with sum_c Q((tau + d_c^2/2)/d_c) = alpha
          (exact for one footprint, a union bound otherwise) gives P_F <= alpha.
        """
        params = self.params[name]
        if available.all():
            return params
        key = (name, available.tobytes())
        sub = self._subsets.get(key)
        if sub is None:
            if len(self._subsets) > 256:
                self._subsets.clear()
            try:
                sub = self._subset_params(params, available)
            except ParameterError as exc:
                sub = exc
            self._subsets[key] = sub
        if isinstance(sub, ParameterError):
            raise sub
        return sub

    @staticmethod
    def _subset_params(params, available: np.ndarray):
        from scipy.optimize import brentq
        from scipy.special import log_ndtr, ndtri

        part = centralised.make_params(params.noise_mv[available], params.sigma_mv[available],
                                       params.signal_patterns_mv[:, available], params.taxel_signal_mv[available],
                                       params.method)
        alpha = params.info["false_alarm"]
        if params.method == "glrt":
            tau = params.threshold
        else:
            d = np.sqrt(np.sum(part.signal_patterns_mv**2 / part.sigma_mv**2, axis=1))
            d = d[d > 0]
            if d.size == 0:
                raise ParameterError("readings_mv", "received taxels", "no received taxel carries signal: no test")
            if d.size == 1:  # exact: L ~ N(-d^2/2, d^2) under H0
                tau = -0.5 * float(d[0]) ** 2 + float(d[0]) * float(ndtri(1.0 - alpha))
            else:
                def excess(t):  # ln(sum_c Q((t + d_c^2/2)/d_c)) - ln(alpha)
                    z = -(t + 0.5 * d * d) / d
                    return float(np.logaddexp.reduce(log_ndtr(z))) - np.log(alpha)

                lo, hi = -0.5 * float(d.max()) ** 2 - 50.0 * float(d.max()), 50.0 * float(d.max()) + 50.0
                tau = brentq(excess, lo, hi, xtol=1e-12)
        return centralised.CentralisedParams(part.noise_mv, part.sigma_mv, part.signal_patterns_mv,
                                             part.taxel_signal_mv, part.method, float(tau),
                                             dict(params.info))

    def test(self, name: str, readings: np.ndarray, available: np.ndarray) -> dict:
        """Centralised raw-data test of one cycle (decide H1 iff statistic > threshold)."""
        params = self.params_for(name, available)
        if params.method == "known" and available.all():
            value = self._known_full(params, readings)
        else:
            value = centralised.centralised_llr(readings[available], params)
        result = {"U_G": value, "threshold": params.threshold, "decision": verdict(value > params.threshold),
                  "false_alarm": params.info["false_alarm"], "n": int(params.n)}
        if params.method == "known":
            # exact log-likelihood ratio of the scene's own H1: posterior with the prior (eq 22)
            p1 = self.scene.fusion.prior_h1
            z = value + math.log(p1 / (1.0 - p1))
            result["p_h1"] = 1.0 / (1.0 + math.exp(-z)) if z > -700 else 0.0
        else:
            result["p_h1"] = None
        return result
