"""Raw-data mode: the centralised reference ("what you lose by deciding locally").

The chapter's introduction (sec. 1) contrasts two architectures: every sensor streams its raw
observation X_i to a central detector, or every sensor decides locally (eqs 1-4) and only the
decisions u_i reach the fusion centre, "although this method suffers from loss of
information". In raw-data mode (TPDO2, the process value X_i as REAL32 mV) the fusion centre
holds the raw readings and can do two things with them:

1. :func:`per_taxel_decisions` - apply the nodes' own test centrally: Y_i = X_i - N_i (eq 4),
   u_i = +1 iff Y_i >= zeta_i (eqs 2-3). Given the same X_i, N_i and zeta_i this yields
   *exactly the same* decisions as the nodes (it is the same function,
   :func:`fusion_center.core.encoding.local_decision`), so every decision-mode rule fed from raw
   data gives the same verdict as in decision mode; raw mode only costs bus time.
2. The optimal centralised test on the raw data, under the scene's Gaussian model
   (docs/scene-format.md): X_i = S_i + N_i + sigma_i eps_i, eps_i ~ N(0, 1) i.i.d., where
   S_i is the contact signal of a contacted taxel and 0 otherwise (H0: S = 0, eq 1 H0;
   H1: eq 1 H1 restricted to the footprint). With y_i = x_i - N_i the per-taxel log-likelihood
   ratio of "contacted with signal S_i" against "not contacted" is

       LLR_i(y_i) = ln N(y_i; S_i, sigma_i^2) / N(y_i; 0, sigma_i^2)
                  = (S_i y_i - S_i^2 / 2) / sigma_i^2.

   * ``method="known"`` (the clairvoyant reference): H1 is the scene's own contact model - the
     footprint signal vectors S^(c) of its present cycles, equally likely (one vector for a
     static object; several for a slipping one). The statistic is the exact log-likelihood
     ratio ln( mean_c prod_i N(y_i; S_i^(c), sigma_i^2) / prod_i N(y_i; 0, sigma_i^2) )
     = logmeanexp_c sum_i LLR_i^(c). By the Neyman-Pearson lemma no detector, central or
     not, has a higher P_D at the same P_F for this scene: an upper bound.
   * ``method="glrt"`` (implementable without knowing where the object is): the generalised
     likelihood ratio over *all* footprints, each taxel either contacted with its nominal
     signal S_i or not: max over subsets A of sum_{i in A} LLR_i = sum_i max(0, LLR_i). We use
     this rather than a mixture with a contact prior because it needs no prior on the
     footprint size (the chapter's Table 1 spans t_c from 0.01 to 1).

   Thresholds: for a requested false-alarm rate alpha, :func:`centralised_threshold` uses the
   closed form when the statistic is Gaussian under H0 (``known`` with one footprint:
   L ~ N(-d^2/2, d^2), d^2 = sum S_i^2 / sigma_i^2, so tau = -d^2/2 + d Q^-1(alpha)) and the
   (1 - alpha) quantile of a Monte Carlo sample under H0 otherwise. The Bayes alternative is
   ``known`` with tau = ln lambda_0 (eq 22).

Pure functions, numpy-vectorised: every statistic accepts a single reading vector (n,) and
returns a float, or a batch (..., n) and returns an array. sigma_i must be > 0 (a noiseless
taxel has an infinite LLR).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import logsumexp, ndtri

from .encoding import Encoding, local_decision
from taxel_net.errors import ParameterError

METHODS = ("known", "glrt")


def per_taxel_decisions(readings_mv, noise_mv, zeta_mv, encoding: Encoding = "pm1") -> np.ndarray:
    """The nodes' local test (eqs 1-4) applied centrally to raw readings X_i.

    Identical to the decisions the nodes would send in decision mode for the same X_i, N_i
    and zeta_i (it is :func:`fusion_center.core.encoding.local_decision`). Broadcasts over a batch.
    """
    return local_decision(readings_mv, noise_mv, zeta_mv, encoding)


def _positive(values, name: str) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(values, dtype=float))
    bad = ~np.isfinite(arr) | (arr <= 0)
    if bad.any():
        i = int(np.flatnonzero(bad.ravel())[0])
        raise ParameterError(f"{name}[{i}]", float(arr.ravel()[i]), "must be a finite noise std > 0 mV for the raw-data LLR")
    return arr


def _finite(values, name: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    bad = ~np.isfinite(arr)
    if bad.any():
        i = int(np.flatnonzero(bad.ravel())[0])
        raise ParameterError(f"{name}[{i}]", float(arr.ravel()[i]), "must be finite")
    return arr


@dataclass(frozen=True)
class CentralisedParams:
    """Everything the centralised raw-data test needs (all arrays per taxel, fusion order).

    ``noise_mv`` N_i (eq 4, subtracted from X_i), ``sigma_mv`` the noise std sigma_i,
    ``signal_patterns_mv`` (C, n) the H1 signal vectors of the ``known`` test, ``taxel_signal_mv``
    (n,) the nominal signal S_i of a contacted taxel for the ``glrt`` test, ``method`` the
    default statistic and ``threshold`` its decision threshold (decide H1 iff statistic > it).
    """

    noise_mv: np.ndarray
    sigma_mv: np.ndarray
    signal_patterns_mv: np.ndarray
    taxel_signal_mv: np.ndarray
    method: str = "glrt"
    threshold: float = 0.0
    info: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.sigma_mv.size)


def make_params(noise_mv, sigma_mv, signal_patterns_mv, taxel_signal_mv=None, method: str = "glrt",
                threshold: float = 0.0) -> CentralisedParams:
    """Validated :class:`CentralisedParams`; ``taxel_signal_mv`` defaults to the per-taxel
    largest |S| over the patterns (with its sign)."""
    sigma = _positive(sigma_mv, "sigma_mv")
    n = sigma.size
    noise = np.broadcast_to(_finite(noise_mv, "noise_mv"), (n,)).astype(float)
    patterns = np.atleast_2d(_finite(signal_patterns_mv, "signal_patterns_mv")).astype(float)
    if patterns.shape[1] != n:
        raise ParameterError("signal_patterns_mv", patterns.shape, f"must have n={n} columns")
    if taxel_signal_mv is None:
        idx = np.argmax(np.abs(patterns), axis=0)
        taxel_signal = patterns[idx, np.arange(n)]
    else:
        taxel_signal = np.broadcast_to(_finite(taxel_signal_mv, "taxel_signal_mv"), (n,)).astype(float)
    if method not in METHODS:
        raise ParameterError("method", method, f"must be one of {METHODS}")
    return CentralisedParams(noise, sigma, patterns, taxel_signal, method, float(threshold))


def taxel_llr(offsets_mv, sigma_mv, signal_mv) -> np.ndarray:
    """LLR_i(y_i) = (S_i y_i - S_i^2/2) / sigma_i^2 for offsets y_i = X_i - N_i (eq 4)."""
    y = np.asarray(offsets_mv, dtype=float)
    s = np.asarray(signal_mv, dtype=float)
    return (s * y - 0.5 * s * s) / np.asarray(sigma_mv, dtype=float) ** 2


def statistic_from_offsets(offsets_mv, params: CentralisedParams, method: str | None = None):
    """The centralised statistic for offsets y = X - N, shape (n,) -> float, (..., n) -> (...)."""
    method = params.method if method is None else method
    y = np.asarray(offsets_mv, dtype=float)
    if y.shape[-1] != params.n:
        raise ParameterError("readings_mv", y.shape, f"must have n={params.n} readings per cycle")
    inv_var = 1.0 / params.sigma_mv**2
    if method == "glrt":
        s = params.taxel_signal_mv
        out = np.maximum(0.0, (y * s - 0.5 * s * s) * inv_var).sum(axis=-1)
    elif method == "known":
        weights = (params.signal_patterns_mv * inv_var).T  # (n, C)
        offsets = -0.5 * np.sum(params.signal_patterns_mv**2 * inv_var, axis=1)  # (C,)
        per_pattern = y @ weights + offsets  # (..., C)
        c = params.signal_patterns_mv.shape[0]
        out = per_pattern[..., 0] if c == 1 else logsumexp(per_pattern, axis=-1) - np.log(c)
    else:
        raise ParameterError("method", method, f"must be one of {METHODS}")
    return float(out) if np.ndim(out) == 0 else out


def centralised_llr(readings_mv, params: CentralisedParams, method: str | None = None):
    """Centralised raw-data statistic of one cycle (readings X_i, mV, fusion order) -> float.

    ``params``: a :class:`CentralisedParams` (``fusion_center.evaluation.params_from_scene``
    builds it from a scene). A batch (..., n) of readings gives an array. Decide H1 iff the
    value > params.threshold.
    """
    if not isinstance(params, CentralisedParams):
        raise ParameterError("params", type(params).__name__, "must be a CentralisedParams (see make_params)")
    x = _finite(readings_mv, "readings_mv")
    return statistic_from_offsets(x - params.noise_mv, params, method)


def centralised_decision(readings_mv, params: CentralisedParams, method: str | None = None):
    """True (H1) iff :func:`centralised_llr` > ``params.threshold``."""
    return np.asarray(centralised_llr(readings_mv, params, method)) > params.threshold


def known_footprint_gaussian_threshold(params: CentralisedParams, false_alarm: float) -> float:
    """Closed-form tau for ``known`` with one footprint: under H0 L ~ N(-d^2/2, d^2),
    d^2 = sum_i S_i^2/sigma_i^2, so P0(L > tau) = alpha gives tau = -d^2/2 + d Q^-1(alpha)."""
    alpha = _alpha(false_alarm)
    if params.signal_patterns_mv.shape[0] != 1:
        raise ParameterError("signal_patterns_mv", params.signal_patterns_mv.shape[0], "closed form needs exactly one footprint")
    d = float(np.sqrt(np.sum(params.signal_patterns_mv[0] ** 2 / params.sigma_mv**2)))
    if d == 0.0:
        raise ParameterError("signal_patterns_mv", 0.0, "the footprint carries no signal (d = 0): no test exists")
    return -0.5 * d * d + d * float(ndtri(1.0 - alpha))


def _alpha(false_alarm) -> float:
    a = float(false_alarm)
    if not np.isfinite(a) or not 0.0 < a < 1.0:
        raise ParameterError("false_alarm", false_alarm, "must be a probability in the open interval (0, 1)")
    return a


def sample_h0_statistic(params: CentralisedParams, n_samples: int, rng: np.random.Generator,
                        method: str | None = None, chunk: int = 65536) -> np.ndarray:
    """The statistic of ``n_samples`` H0 cycles (y_i = sigma_i eps_i), chunked."""
    out = np.empty(int(n_samples))
    done = 0
    while done < n_samples:
        m = min(chunk, n_samples - done)
        y = rng.standard_normal((m, params.n)) * params.sigma_mv
        out[done:done + m] = statistic_from_offsets(y, params, method)
        done += m
    return out


def centralised_threshold(params: CentralisedParams, false_alarm: float, method: str | None = None,
                          rng: np.random.Generator | None = None, n_samples: int = 200_000) -> float:
    """Threshold tau with P(statistic > tau | H0) = ``false_alarm``.

    Closed form for ``known`` with a single footprint (Gaussian under H0); otherwise the
    empirical (1 - alpha) quantile of ``n_samples`` H0 draws (``rng`` default: seed 0, so the
    threshold is reproducible). Monte Carlo needs n_samples * alpha >> 1: refused below 20.
    """
    method = params.method if method is None else method
    alpha = _alpha(false_alarm)
    if method == "known" and params.signal_patterns_mv.shape[0] == 1:
        return known_footprint_gaussian_threshold(params, alpha)
    if n_samples * alpha < 20:
        raise ParameterError("n_samples", n_samples, f"must be >= {int(np.ceil(20 / alpha))} for false_alarm={alpha:g}")
    rng = np.random.default_rng(0) if rng is None else rng
    sample = sample_h0_statistic(params, n_samples, rng, method)
    return float(np.quantile(sample, 1.0 - alpha, method="higher"))
