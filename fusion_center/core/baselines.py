"""Baselines the chapter compares HEBTEM with (sec. 2.2.1, 2.2.3.5, 4.3.3, 6.2).

* :func:`chair_varshney_llr` -- the Chair-Varshney log-likelihood-ratio fusion statistic,
  eq 31; decide H1 iff it is > 0.
* :func:`np_log_statistic` -- ln of the likelihood ratio P(U|H1)/P(U|H0) of eq 32. The
  chapter prints the ratio itself (26.19898e-143 for its 57 taxels); the plain product
  underflows to 0 once it drops below ~1e-308 (about 130-150 taxels of the chapter's kind),
  so everything here stays in the log domain.
* :func:`neyman_pearson_fusion` -- the optimal (randomised) Neyman-Pearson fusion of
  independent binary local decisions at a prescribed system false-alarm rate.
* :func:`bayes_threshold` / :func:`bayes_log_threshold` -- the Bayes threshold lambda_0 of
  eq 22 (eq 21b when costs are 0-1).
* :func:`k_of_n_error_rates` / :func:`count_rule_error_rates` -- exact system detection and
  false-alarm probabilities of the k-out-of-n rule of sec. 2.2.1 ("H1 iff at least k taxels
  report present"), from the Poisson-binomial law of the present count.

Notation: pd_i = 1 - pm_i is taxel i's detection probability (the chapter gives P_M^i),
pf_i its false-alarm probability. Both must lie in the open interval (0, 1): at 0 or 1 a
log-likelihood term is infinite. Decisions u are given with their tuple ``encoding``
("pm1": {-1,+1}, "01": {0,1}); "present" is u_i = +1 in both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import poisson_binomial
from .curves import check_open_unit
from .encoding import PRESENT, Encoding, check_integer, check_real, validate_decisions
from taxel_net.errors import ParameterError

# heterogeneous taxels: exact enumeration of all 2^n decision vectors up to this n
NP_ENUMERATION_MAX_TAXELS = 20
# two log-likelihood values closer than this (relative, min absolute 1e-9) are one atom:
# the same ratio summed in a different order differs only by rounding
LLR_TIE_TOLERANCE = 1e-9


def compare_log_ratio(value: float, log_threshold: float) -> int:
    """+1, -1 or 0 (a tie) for ln Lambda against a log threshold (eqs 31-32).

    Values within LLR_TIE_TOLERANCE (relative, min absolute 1e-9) are a tie: a likelihood ratio
    of exactly 1, e.g. (0.9/0.1) (0.1/0.9), sums its logarithms to about 1e-16, not to 0.
    """
    diff = value - log_threshold
    if abs(diff) <= LLR_TIE_TOLERANCE * max(1.0, abs(log_threshold)):
        return 0
    return 1 if diff > 0 else -1


def _open_probabilities(values, name: str, n: int | None = None) -> np.ndarray:
    """1-D float array of probabilities strictly inside (0, 1); a scalar broadcasts to n."""
    arr = poisson_binomial.validate_probabilities(values, name, open_interval=True)
    if arr.size == 0:
        raise ParameterError(name, [], "needs one probability per taxel (n >= 1)")
    if n is not None and arr.size != n:
        if arr.size == 1:
            return np.full(n, arr[0])
        raise ParameterError(name, f"{arr.size} values", f"must give 1 or n={n} probabilities")
    return arr


def _taxel_probabilities(pd, pf, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """pd and pf as arrays of one common length (a scalar broadcasts to the other's length)."""
    if n is None:
        sizes = [np.asarray(x).size for x in (pd, pf) if np.asarray(x).ndim > 0]
        n = max(sizes) if sizes else None
    pd_arr = _open_probabilities(pd, "pd", n)
    pf_arr = _open_probabilities(pf, "pf", pd_arr.size)
    return pd_arr, pf_arr


def _prior(prior_h1) -> float:
    return check_open_unit("prior_h1", prior_h1)


def _log_ratio_terms(pd: np.ndarray, pf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-taxel log-likelihood contributions: (present: ln(pd/pf), absent: ln((1-pd)/(1-pf)))."""
    present = np.log(pd) - np.log(pf)
    absent = np.log1p(-pd) - np.log1p(-pf)
    return present, absent


def _decisions_and_probs(u, pd, pf, encoding):
    decisions = validate_decisions(u, encoding)
    pd_arr, pf_arr = _taxel_probabilities(pd, pf, decisions.size)
    return decisions == PRESENT, pd_arr, pf_arr


def np_log_statistic(u, pd, pf, encoding: Encoding = "pm1") -> float:
    """ln Lambda(U) = ln P(U|H1) / P(U|H0), the Neyman-Pearson statistic of eq 32.

    ln Lambda = sum_{S+} ln(pd_i / pf_i) + sum_{S-} ln((1 - pd_i) / (1 - pf_i)),
    S+ = {i: u_i = +1}, S- the rest; the 1 - p terms use log1p. ``pd``/``pf`` are per-taxel
    arrays or scalars (identical taxels). exp() of the result is the chapter's printed ratio.
    """
    present, pd_arr, pf_arr = _decisions_and_probs(u, pd, pf, encoding)
    a, b = _log_ratio_terms(pd_arr, pf_arr)
    return float(np.sum(np.where(present, a, b)))


def chair_varshney_llr(u, pd, pf, encoding: Encoding = "pm1", prior_h1: float = 0.5) -> float:
    """Chair-Varshney fusion statistic, eq 31: ln P(H1|U) / P(H0|U).

    = ln(P1/P0) + sum_{S+} ln(pd_i/pf_i) + sum_{S-} ln((1-pd_i)/(1-pf_i)), with
    P1 = ``prior_h1``, P0 = 1 - P1. Eq 31 text: decide H1 iff the value is > 0 (the optimal
    Bayes rule for 0-1 costs); a value of exactly 0 is the chapter's "undefined zone".
    """
    p1 = _prior(prior_h1)
    return float(np.log(p1) - np.log1p(-p1)) + np_log_statistic(u, pd, pf, encoding)


def bayes_log_threshold(prior_h1: float, c00: float, c01: float, c10: float, c11: float) -> float:
    """ln lambda_0 of eq 22 (see :func:`bayes_threshold` for the validation)."""
    p1 = _prior(prior_h1)
    costs = {"c00": c00, "c01": c01, "c10": c10, "c11": c11}
    c00, c01, c10, c11 = (
        check_real(name, value, -math.inf, math.inf, allowed="cost must be a finite number")
        for name, value in costs.items()
    )
    false_alarm_penalty = c10 - c00  # C10 - C00
    miss_penalty = c01 - c11  # C01 - C11
    if miss_penalty == 0.0:
        raise ParameterError(
            "c01", c01, f"must differ from c11={c11!r}: C01 - C11 = 0 is a zero denominator in eq 22"
        )
    if false_alarm_penalty == 0.0:
        raise ParameterError(
            "c10", c10, f"must differ from c00={c00!r}: C10 - C00 = 0 gives lambda_0 = 0 (every U accepts H1)"
        )
    if (false_alarm_penalty > 0) != (miss_penalty > 0):
        raise ParameterError(
            "c10",
            c10,
            f"C10 - C00 = {false_alarm_penalty:g} and C01 - C11 = {miss_penalty:g} must have the same sign "
            "(chapter sec. 6.2: C10 > C00 and C01 > C11, or C10 < C00 and C01 < C11)",
        )
    return float(
        np.log1p(-p1) - np.log(p1) + np.log(abs(false_alarm_penalty)) - np.log(abs(miss_penalty))
    )


def bayes_threshold(prior_h1: float, c00: float, c01: float, c10: float, c11: float) -> float:
    """Bayes threshold lambda_0 = P0 (C10 - C00) / (P1 (C01 - C11)), eq 22.

    C_ij is the cost of accepting H_i when H_j is true; P1 = ``prior_h1``, P0 = 1 - P1.
    With 0-1 costs it is eq 21b, P0/P1. The likelihood-ratio test is Lambda(U) > lambda_0
    -> H1 when C10 > C00 and C01 > C11 (the usual case). When C10 < C00 and C01 < C11 (the
    chapter's case [b]) lambda_0 is still positive but the Bayes rule turns into
    Lambda(U) < lambda_0 -> H1. Rejected (ParameterError): priors outside (0, 1), non-finite
    costs, C01 = C11 (zero denominator), C10 = C00 (lambda_0 = 0) and differences of
    opposite sign (lambda_0 < 0: no likelihood-ratio threshold exists).
    """
    return float(np.exp(bayes_log_threshold(prior_h1, c00, c01, c10, c11)))


# --------------------------------------------------------------------------- count rules
@dataclass(frozen=True)
class CountRuleRates:
    """System error rates of "H1 iff present_count >= min_present_count" (sec. 2.2.1)."""

    min_present_count: int
    p_detect: float
    p_false_alarm: float
    log_p_detect: float
    log_p_false_alarm: float
    log_p_miss: float


def _probability_from_logs(log_tail: float, log_head: float) -> float:
    """P = e^log_tail, or 1 - e^log_head when P > 1/2 (then the head is the small, exact side:
    1 - 1e-110 rounds to 1.0, where exp(logsumexp(tail)) gives 1 - 4e-16)."""
    return float(np.exp(log_tail)) if log_tail < -np.log(2.0) else float(-np.expm1(log_head))


def count_rule_error_rates(min_present_count: int, pd, pf) -> CountRuleRates:
    """Exact P_D, P_F (and logs, and ln P_M) of the rule "H1 iff K >= min_present_count".

    K = number of taxels reporting present; under H0 it is Poisson-binomial(pf), under H1
    Poisson-binomial(pd) (independent taxels, sec. 2.1). P_D = P(K >= m | H1),
    P_F = P(K >= m | H0), P_M = P(K <= m - 1 | H1), all evaluated in the log domain so a
    1e-200 false-alarm rate is exact. ``min_present_count`` may be 0 (always H1) to n + 1
    (never H1). The additive rule of eq 6 with threshold lambda is this rule with
    m = ceil((lambda + n) / 2) for the pm1 tuple (U_G = 2K - n), m = ceil(lambda) for 01.
    """
    pd_arr, pf_arr = _taxel_probabilities(pd, pf)
    n = pd_arr.size
    m = check_integer("min_present_count", min_present_count, 0, n + 1)
    log_pd_tail = poisson_binomial.log_sf(pd_arr, m)
    log_pf_tail = poisson_binomial.log_sf(pf_arr, m)
    log_miss = poisson_binomial.log_cdf(pd_arr, m - 1)
    log_pf_head = poisson_binomial.log_cdf(pf_arr, m - 1)
    return CountRuleRates(
        min_present_count=m,
        p_detect=_probability_from_logs(log_pd_tail, log_miss),
        p_false_alarm=_probability_from_logs(log_pf_tail, log_pf_head),
        log_p_detect=log_pd_tail,
        log_p_false_alarm=log_pf_tail,
        log_p_miss=log_miss,
    )


def k_of_n_error_rates(k: int, pd, pf) -> tuple[float, float]:
    """(P_D, P_F) of the k-out-of-n rule of sec. 2.2.1: U_G = +1 iff sum u_i >= 2k - n.

    With {-1,+1} decisions sum u_i = 2K - n, so the rule is "at least k of the n taxels
    report present"; k must be in [1, n]. ``pd``/``pf``: per-taxel arrays or scalars
    (identical taxels; then the other argument fixes n). Exact Poisson-binomial tails.
    """
    pd_arr, pf_arr = _taxel_probabilities(pd, pf)
    k = check_integer("k", k, 1, pd_arr.size)
    rates = count_rule_error_rates(k, pd_arr, pf_arr)
    return rates.p_detect, rates.p_false_alarm


# --------------------------------------------------------------------------- Neyman-Pearson
@dataclass(frozen=True)
class NPFusionRule:
    """A randomised Neyman-Pearson fusion rule over independent binary taxel decisions.

    ``statistic`` is "llr" (the rule thresholds ln Lambda(U) of eq 32) or "present_count"
    (it thresholds the count K; then ``count_threshold`` holds the boundary count).
    Decide H1 when the statistic is above the threshold, H0 below it, and at the threshold
    H1 with probability ``gamma``. ``achieved_false_alarm`` = P0(above) + gamma P0(at),
    which equals the requested rate up to rounding; ``detection_probability`` likewise
    under H1. ``optimal`` is True when the rule is the most powerful test of its size over
    all functions of U (exact enumeration, or identical taxels, where Lambda is monotone
    in K); False for the count-based rule for many heterogeneous taxels.
    """

    method: str
    statistic: str
    log_threshold: float | None
    count_threshold: int | None
    gamma: float
    achieved_false_alarm: float
    detection_probability: float
    requested_false_alarm: float
    optimal: bool
    pd: np.ndarray = field(repr=False)
    pf: np.ndarray = field(repr=False)
    count_increasing: bool = True

    def statistic_value(self, u, encoding: Encoding = "pm1") -> float:
        """The value of this rule's statistic for decisions ``u`` (ln Lambda or K)."""
        if self.statistic == "llr":
            return np_log_statistic(u, self.pd, self.pf, encoding)
        decisions = validate_decisions(u, encoding)
        if decisions.size != self.pd.size:
            raise ParameterError("u", f"{decisions.size} decisions", f"must have n={self.pd.size} decisions")
        return float(np.count_nonzero(decisions == PRESENT))

    def decide(self, u, encoding: Encoding = "pm1", rng: np.random.Generator | None = None) -> str:
        """Return "H1", "H0" or "undecided".

        Above the threshold -> "H1", below -> "H0". Exactly at the boundary (within the
        tie tolerance for the llr statistic) the N-P test is randomised: with ``rng`` (a
        numpy Generator) it returns "H1" with probability ``gamma``; without ``rng`` it
        returns "undecided" -- unless gamma is 0 ("H0") or 1 ("H1"), when no coin is needed.
        """
        return self.decide_value(self.statistic_value(u, encoding), rng)

    def decide_value(self, value: float, rng: np.random.Generator | None = None) -> str:
        """:meth:`decide` for a statistic value already computed (ln Lambda or K)."""
        if self.statistic == "llr":
            position = compare_log_ratio(value, self.log_threshold)
        else:
            diff = value - self.count_threshold
            if not self.count_increasing:
                diff = -diff
            position = (diff > 0) - (diff < 0)
        if position > 0:
            return "H1"
        if position < 0:
            return "H0"
        if self.gamma <= 0.0:
            return "H0"
        if self.gamma >= 1.0:
            return "H1"
        if rng is None:
            return "undecided"
        return "H1" if rng.random() < self.gamma else "H0"


def _merge_atoms(values: np.ndarray, p0: np.ndarray, p1: np.ndarray):
    """Sort atoms by decreasing statistic and merge values equal within the tie tolerance."""
    order = np.argsort(-values, kind="stable")
    values, p0, p1 = values[order], p0[order], p1[order]
    scale = np.maximum(1.0, np.abs(values))
    new_group = np.empty(values.size, dtype=bool)
    new_group[0] = True
    new_group[1:] = (values[:-1] - values[1:]) > LLR_TIE_TOLERANCE * scale[1:]
    starts = np.flatnonzero(new_group)
    return values[starts], np.add.reduceat(p0, starts), np.add.reduceat(p1, starts)


def _randomised_boundary(p0: np.ndarray, p1: np.ndarray, alpha: float):
    """Index j of the boundary atom and gamma, atoms in decreasing statistic order:
    P0(atoms before j) + gamma p0[j] = alpha (N-P lemma, randomised boundary).

    alpha <= 1/2: prefix sums. alpha > 1/2: complements, 1 - alpha (exact in floats for
    alpha >= 1/2) against the H0 mass *after* j, summed from the small end, so gamma keeps its
    digits for a false-alarm rate near 1 (1 - gamma = (1 - alpha - tail)/p0[j]); the prefix
    form would subtract two numbers near 1 (1.4e-4 off in gamma at alpha = 1 - 1e-9).
    """
    size = p0.size
    if alpha <= 0.5:
        cum_before = np.concatenate(([0.0], np.cumsum(p0)[:-1]))
        cum_after = cum_before + p0
        j = min(int(np.searchsorted(cum_after, alpha, side="left")), size - 1)  # first reaching alpha
        gamma = (alpha - cum_before[j]) / p0[j] if p0[j] > 0 else 0.0
        gamma = float(min(1.0, max(0.0, gamma)))
        achieved = float(cum_before[j] + gamma * p0[j])
    else:
        beta0 = 1.0 - alpha  # exact (Sterbenz)
        tail_after = np.concatenate((np.cumsum(p0[::-1])[::-1][1:], [0.0]))  # P0(atoms after j)
        # first j whose atoms up to j reach alpha: tail_after[j] <= 1 - alpha (tail decreasing)
        j = min(int(np.searchsorted(-tail_after, -beta0, side="left")), size - 1)
        rest = (beta0 - tail_after[j]) / p0[j] if p0[j] > 0 else 1.0  # = 1 - gamma
        rest = float(min(1.0, max(0.0, rest)))
        gamma = 1.0 - rest
        achieved = float(1.0 - (tail_after[j] + rest * p0[j]))
    detection = float(np.sum(p1[:j]) + gamma * p1[j])
    return j, gamma, achieved, detection


def _enumerate_llr_atoms(pd: np.ndarray, pf: np.ndarray):
    """ln Lambda and its probability under H0 and H1 for all 2^n decision vectors."""
    a, b = _log_ratio_terms(pd, pf)
    values = np.zeros(1)
    log_p0 = np.zeros(1)
    log_p1 = np.zeros(1)
    for i in range(pd.size):
        values = np.concatenate((values + b[i], values + a[i]))
        log_p0 = np.concatenate((log_p0 + np.log1p(-pf[i]), log_p0 + np.log(pf[i])))
        log_p1 = np.concatenate((log_p1 + np.log1p(-pd[i]), log_p1 + np.log(pd[i])))
    return values, np.exp(log_p0), np.exp(log_p1)


def neyman_pearson_fusion(pd, pf, false_alarm: float, method: str = "auto") -> NPFusionRule:
    """Most powerful fusion rule of size ``false_alarm`` for independent binary decisions.

    By the Neyman-Pearson lemma the optimal rule thresholds Lambda(U) (eq 32), randomising
    on the boundary so that the system false-alarm rate equals ``false_alarm`` exactly:
    choose tau, gamma with P0(ln Lambda > tau) + gamma P0(ln Lambda = tau) = alpha.

    ``method``:
    * "identical" -- all pd_i equal and all pf_i equal: ln Lambda = n ln((1-pd)/(1-pf))
      + K ln(pd (1-pf) / (pf (1-pd))) is monotone in the present count K, so the optimal
      rule is a k-out-of-n rule with a randomised boundary count; K is binomial (exact,
      any n). ``count_threshold`` and ``log_threshold`` are both given.
    * "enumerate" -- heterogeneous taxels, n <= 20: the law of ln Lambda under H0 and H1
      over all 2^n decision vectors (equal values merged within LLR_TIE_TOLERANCE).
      Exact and optimal; O(2^n) time and memory.
    * "count" -- any n: the best rule among those that look only at K ("at least k
      present", boundary count randomised), P_F and P_D exact from the Poisson-binomial
      law. For heterogeneous taxels it is NOT the optimal N-P rule (the optimal one weighs
      each taxel by ln(pd/pf) - ln((1-pd)/(1-pf))); ``optimal`` is False and
      ``log_threshold`` None. Its power is a lower bound on the optimum's.
    * "kinds" -- heterogeneous taxels that come in a few kinds with equal (pd, pf) per kind:
      ln Lambda depends only on the present count per kind, whose law is a product of
      binomials; every count tuple is an atom (up to exact_rates.KIND_ATOMS_MAX of them).
      Exact and optimal (the most powerful randomised test), any n. "auto" picks it for
      n > 20 when the count tuples fit, "count" otherwise.
    * "auto" -- "identical" if the taxels are identical, else "enumerate" for n <= 20,
      else "count".
    """
    pd_arr, pf_arr = _taxel_probabilities(pd, pf)
    alpha = check_open_unit("false_alarm", false_alarm)
    n = pd_arr.size
    identical = bool(np.all(pd_arr == pd_arr[0]) and np.all(pf_arr == pf_arr[0]))
    if method == "auto":
        method = "identical" if identical else ("enumerate" if n <= NP_ENUMERATION_MAX_TAXELS else "count")
        if method == "count":
            from .exact_rates import KIND_ATOMS_MAX, kinds_of

            sizes = kinds_of(pd_arr, pf_arr)[2]
            if float(np.prod(sizes + 1.0)) <= KIND_ATOMS_MAX:
                method = "kinds"
    if method == "identical" and not identical:
        raise ParameterError("method", method, "needs equal pd and equal pf for every taxel")
    if method == "enumerate" and n > NP_ENUMERATION_MAX_TAXELS:
        raise ParameterError("method", method, f"enumerates 2^n vectors: n={n} exceeds {NP_ENUMERATION_MAX_TAXELS}")
    if method not in ("identical", "enumerate", "count", "kinds"):
        raise ParameterError("method", method, "must be 'auto', 'identical', 'enumerate', 'count' or 'kinds'")

    common = dict(requested_false_alarm=alpha, pd=pd_arr, pf=pf_arr)
    if method in ("enumerate", "kinds"):
        if method == "kinds":
            from .exact_rates import _kind_atoms, kinds_of

            llr, lp0, lp1 = _kind_atoms(*kinds_of(pd_arr, pf_arr))
            atoms = (llr, np.exp(lp0), np.exp(lp1))
        else:
            atoms = _enumerate_llr_atoms(pd_arr, pf_arr)
        values, p0, p1 = _merge_atoms(*atoms)
        j, gamma, achieved, detection = _randomised_boundary(p0, p1, alpha)
        return NPFusionRule(
            method=method, statistic="llr", log_threshold=float(values[j]), count_threshold=None,
            gamma=gamma, achieved_false_alarm=achieved, detection_probability=detection,
            optimal=True, **common,
        )

    counts = np.arange(n + 1)
    p0 = poisson_binomial.pmf(pf_arr)
    p1 = poisson_binomial.pmf(pd_arr)
    if method == "identical":
        a, b = _log_ratio_terms(pd_arr[:1], pf_arr[:1])
        llr_of_count = n * b[0] + counts * (a[0] - b[0])
        values, p0m, p1m = _merge_atoms(llr_of_count, p0, p1)
        j, gamma, achieved, detection = _randomised_boundary(p0m, p1m, alpha)
        increasing = bool(a[0] >= b[0])
        if values.size == 1:  # pd == pf: Lambda = 1 for every U, pure randomisation
            boundary_count = 0 if increasing else n
        else:
            boundary_count = int(np.argmin(np.abs(llr_of_count - values[j])))
        return NPFusionRule(
            method=method, statistic="llr", log_threshold=float(values[j]), count_threshold=boundary_count,
            gamma=gamma, achieved_false_alarm=achieved, detection_probability=detection,
            optimal=True, count_increasing=increasing, **common,
        )

    # count-based: decide H1 on large counts
    descending = counts[::-1]
    j, gamma, achieved, detection = _randomised_boundary(p0[::-1], p1[::-1], alpha)
    return NPFusionRule(
        method=method, statistic="present_count", log_threshold=None, count_threshold=int(descending[j]),
        gamma=gamma, achieved_false_alarm=achieved, detection_probability=detection,
        optimal=identical, **common,
    )
