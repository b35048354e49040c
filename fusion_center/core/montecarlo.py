"""Vectorised Monte Carlo of detection error: every fusion rule and the centralised raw test.

What is simulated (docs/scene-format.md, the same model as ``node_sim.physics``):
X_i = S_i(c) + N_i + sigma_i eps_i, eps_i ~ N(0, 1) i.i.d. per taxel and trial. The node's
test sees Y_i = X_i - N_i (eq 4) = S_i(c) + sigma_i eps_i, so the simulation draws Y directly
(N_i cancels exactly; in floating point only at a measure-zero boundary).

* H0 trials: S = 0 (no contact, eq 1 H0).
* H1 trials: a cycle c drawn uniformly from the scene's ``present`` cycles (its ground truth);
  S(c) is ``node_sim.physics.signal_mv(scene, c)`` (footprint, calibration, slip motion).

Local decisions u_i = +1 iff Y_i >= zeta_i (eqs 2-3). Then, per trial, in decision mode:

* count rules - additive (eq 6, HEBTEM threshold eq 17), multiplicative (eq 5, threshold
  eq 16), k-of-n (sec. 2.2.1): each is "H1 iff present count K >= m" for its own m (U_G is
  monotone in K); ``fusion_center.core.thresholds`` gives m as ``present_counts``.
* preferential (eq 7) against lambda_Th-mean (eqs 14, 18): :func:`preferential_batch`.
* llr, Chair-Varshney (eq 31) against ln lambda_0 (eq 22): :func:`chair_varshney_batch`.
* np, Neyman-Pearson fusion of the decisions (eq 32) at the scene's ``np_false_alarm``,
  randomised at the boundary (``fusion_center.core.baselines.neyman_pearson_fusion``).
* the centralised raw-data tests ``centralised_known`` and ``centralised_glrt``
  (``fusion_center.core.centralised``) at the same false-alarm rate, and ``centralised_bayes``:
  the known-footprint likelihood ratio against the Bayes threshold ln lambda_0 (eq 22) - the
  smallest Bayes risk any detector can reach on the scene (with 0-1 costs and P1 = 1/2:
  the smallest total error).

LLR and N-P use the scene's *declared* per-taxel pf/pm (what the fusion centre is told, as in
the chapter's P_fi.txt / P_mi.txt); the simulation measures what the decisions *actually* do.
The exact per-taxel rates of the Gaussian model are pf_i = Q(zeta_i / sigma_i) and
pd_i(c) = Q((zeta_i - S_i(c)) / sigma_i) (:func:`taxel_rates`, via scipy.special.ndtr), and
for count rules the exact system rates follow from the Poisson-binomial law of K
(``fusion_center.core.poisson_binomial``) - reported beside the Monte Carlo estimates.

Estimates carry Wilson score intervals. Total error vs ground truth is
pi1 (1 - P_D) + pi0 P_F with pi1 the scene's share of present cycles; its interval combines the
two Wilson bounds (conservative).

Pure: no I/O; randomness only from the ``rng`` passed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.special import ndtr, ndtri

from . import baselines, centralised, poisson_binomial
from .encoding import check_encoding
from taxel_net.errors import ParameterError

COUNT_RULES = ("additive", "multiplicative", "k-of-n")
DECISION_RULES = ("additive", "multiplicative", "preferential", "k-of-n", "llr", "np")
CENTRAL_TESTS = ("centralised_known", "centralised_glrt", "centralised_bayes")


# --------------------------------------------------------------------------- intervals
def wilson_interval(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion successes/trials."""
    if trials <= 0:
        raise ParameterError("trials", trials, "must be >= 1")
    if not 0 <= successes <= trials:
        raise ParameterError("successes", successes, f"must lie in 0..trials={trials}")
    z = float(ndtri(0.5 + confidence / 2.0))
    p = successes / trials
    denom = 1.0 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denom
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denom
    lo = 0.0 if successes == 0 else max(0.0, centre - half)  # exact ends: no rounding residue
    hi = 1.0 if successes == trials else min(1.0, centre + half)
    return lo, hi


@dataclass(frozen=True)
class Rate:
    """A Monte Carlo proportion with its 95 % Wilson interval (and the exact value if known)."""

    estimate: float
    lower: float
    upper: float
    successes: int
    trials: int
    exact: float | None = None

    @classmethod
    def of(cls, successes: int, trials: int, exact: float | None = None) -> "Rate":
        lo, hi = wilson_interval(int(successes), int(trials))
        return cls(successes / trials, lo, hi, int(successes), int(trials), exact)

    def to_dict(self) -> dict:
        return {"estimate": self.estimate, "ci95": [self.lower, self.upper], "successes": self.successes,
                "trials": self.trials, "exact": self.exact}


# --------------------------------------------------------------------------- exact taxel rates
def taxel_rates(signal_mv, zeta_mv, sigma_mv) -> np.ndarray:
    """P(u_i = +1) = P(S_i + sigma_i eps >= zeta_i) = Q((zeta_i - S_i)/sigma_i) = ndtr((S_i - zeta_i)/sigma_i).

    S = 0 gives pf_i = Q(zeta_i/sigma_i). sigma_i = 0 (noiseless): 1 if S_i >= zeta_i else 0.
    Broadcasts (patterns (C, n) against per-taxel zeta, sigma).
    """
    s = np.asarray(signal_mv, dtype=float)
    z = np.asarray(zeta_mv, dtype=float)
    sd = np.asarray(sigma_mv, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        noisy = ndtr((s - z) / np.where(sd > 0, sd, 1.0))
    return np.where(sd > 0, noisy, (s >= z).astype(float))


# --------------------------------------------------------------------------- vectorised rules
def _as_present(present) -> np.ndarray:
    arr = np.asarray(present)
    if arr.dtype != bool:
        raise ParameterError("present", arr.dtype, "must be a boolean array (u_i = +1)")
    return arr


def decisions_to_present(u, encoding: str) -> np.ndarray:
    """Batch (T, n) of decisions in ``encoding`` -> boolean "present" (u_i = +1) array."""
    check_encoding(encoding)
    arr = np.asarray(u)
    allowed = (-1, 1) if encoding == "pm1" else (0, 1)
    if not np.isin(arr, allowed).all():
        raise ParameterError("u", "batch", f"entries must be in {allowed} for tuple '{encoding}'")
    return arr == 1


def additive_batch(present, encoding: str) -> np.ndarray:
    """Eq 6 over a batch: U_G = sum u_i = 2K - n (pm1) or K (01), K = present count."""
    check_encoding(encoding)
    p = _as_present(present)
    k = np.count_nonzero(p, axis=-1)
    return 2 * k - p.shape[-1] if encoding == "pm1" else k


def multiplicative_ln_batch(present, encoding: str) -> np.ndarray:
    """Eq 5 over a batch, as ln U_G = sum u_i (same value as the additive U_G)."""
    return additive_batch(present, encoding).astype(float)


def preferential_batch(present, p: float, q: float, encoding: str) -> np.ndarray:
    """Eq 7 over a batch: U_G = sum_i u_i (1 + u_{i+1})^p (1 + u_{i-1})^q, u_0 = u_{n+1} = 0.

    Applied literally to the values of ``encoding`` (as ``fusion_center.core.rules.preferential``).
    Each factor takes one of three values - 2^w for a present neighbour, (1 + absent)^w for an
    absent one (0^w, with 0^0 = 1, for pm1; 1 for 01) and 1 at the ends - so the batch is a few
    table look-ups, no power per element.
    """
    check_encoding(encoding)
    pres = _as_present(present)
    absent = -1.0 if encoding == "pm1" else 0.0
    u = np.where(pres, 1.0, absent)
    nxt_present, prv_present = pres[..., 1:], pres[..., :-1]
    f_present_p, f_absent_p = 2.0**p, (1.0 + absent) ** p
    f_present_q, f_absent_q = 2.0**q, (1.0 + absent) ** q
    fp = np.ones(pres.shape)
    fq = np.ones(pres.shape)
    fp[..., :-1] = np.where(nxt_present, f_present_p, f_absent_p)  # (1 + u_{i+1})^p, last: u_{n+1} = 0
    fq[..., 1:] = np.where(prv_present, f_present_q, f_absent_q)   # (1 + u_{i-1})^q, first: u_0 = 0
    return np.sum(u * fp * fq, axis=-1)


def _log_terms(pd, pf):
    pd = np.asarray(pd, dtype=float)
    pf = np.asarray(pf, dtype=float)
    present = np.log(pd) - np.log(pf)
    absent = np.log1p(-pd) - np.log1p(-pf)
    return present, absent


def np_log_statistic_batch(present, pd, pf) -> np.ndarray:
    """Eq 32 over a batch: ln Lambda = sum_{S+} ln(pd_i/pf_i) + sum_{S-} ln((1-pd_i)/(1-pf_i)).

    Written as sum_i absent_i + present . (a - b): one matrix-vector product per batch.
    """
    pres = _as_present(present)
    a, b = _log_terms(pd, pf)
    return pres.astype(np.float64) @ (a - b) + float(np.sum(b))


def chair_varshney_batch(present, pd, pf, prior_h1: float) -> np.ndarray:
    """Eq 31 over a batch: ln(P1/P0) + ln Lambda (eq 32). Decide H1 iff > ln lambda_0 (eq 22)."""
    return math.log(prior_h1) - math.log1p(-prior_h1) + np_log_statistic_batch(present, pd, pf)


def np_decide_batch(rule: baselines.NPFusionRule, present, rng: np.random.Generator) -> np.ndarray:
    """Randomised N-P decisions (True = H1) of a batch, as ``NPFusionRule.decide`` with a coin."""
    pres = _as_present(present)
    if rule.statistic == "llr":
        value = np_log_statistic_batch(pres, rule.pd, rule.pf)
        tol = baselines.LLR_TIE_TOLERANCE * max(1.0, abs(rule.log_threshold))
        diff = value - rule.log_threshold
        above, at = diff > tol, np.abs(diff) <= tol
    else:
        diff = np.count_nonzero(pres, axis=-1) - rule.count_threshold
        if not rule.count_increasing:
            diff = -diff
        above, at = diff > 0, diff == 0
    coin = rng.random(pres.shape[0]) < rule.gamma
    return above | (at & coin)


# --------------------------------------------------------------------------- configuration
@dataclass
class RuleSetup:
    """Decision parameters of every rule (``fusion_center.evaluation.setup_rules`` builds them from a scene)."""

    encoding: str
    n: int
    min_present_count: dict[str, int] = field(default_factory=dict)  # count rules: H1 iff K >= m
    preferential: tuple[float, float, float] | None = None  # (p, q, lambda_Th-mean)
    llr: tuple[np.ndarray, np.ndarray, float, float] | None = None  # (pd, pf, prior_h1, ln lambda_0)
    np_rule: baselines.NPFusionRule | None = None
    central: dict[str, centralised.CentralisedParams] = field(default_factory=dict)
    thresholds: dict[str, float] = field(default_factory=dict)  # the rule's own threshold value
    skipped: dict[str, str] = field(default_factory=dict)


# --------------------------------------------------------------------------- simulation
@dataclass
class RuleResult:
    pd: Rate | None
    pf: Rate
    total_error: dict
    threshold: float | None = None
    min_present_count: int | None = None

    def to_dict(self) -> dict:
        return {"pd": None if self.pd is None else self.pd.to_dict(), "pf": self.pf.to_dict(),
                "total_error": self.total_error, "threshold": self.threshold,
                "min_present_count": self.min_present_count}


@dataclass
class MonteCarloResult:
    n_trials: int
    prior_h1: float                       # share of present cycles in the scene (ground truth)
    rules: dict[str, RuleResult]
    skipped: dict[str, str]
    statistics_h0: dict[str, np.ndarray]  # kept per-trial statistics (ROC, achieved P_F)
    statistics_h1: dict[str, np.ndarray]
    taxel_pf: np.ndarray                  # exact Gaussian-model per-taxel rates
    taxel_pd_patterns: np.ndarray         # (C, n)
    pattern_weights: np.ndarray           # (C,)
    taxel_decisions: int                  # n * trials simulated (local decisions)
    setup: RuleSetup = field(repr=False, default=None)

    def to_dict(self) -> dict:
        return {"n_trials_per_hypothesis": self.n_trials, "prior_h1": self.prior_h1,
                "rules": {k: v.to_dict() for k, v in self.rules.items()}, "skipped": dict(self.skipped),
                "taxel_decisions": self.taxel_decisions}


def exact_count_rates(m: int, taxel_pf: np.ndarray, pd_patterns: np.ndarray, weights: np.ndarray):
    """Exact P_F = P(K >= m | H0) and P_D = sum_c w_c P(K >= m | S(c)) (Poisson-binomial tails)."""
    pf = float(np.exp(poisson_binomial.log_sf(taxel_pf, m)))
    if pd_patterns.shape[0] == 0:
        return None, pf
    pd = float(sum(w * np.exp(poisson_binomial.log_sf(row, m)) for row, w in zip(pd_patterns, weights)))
    return pd, pf


def _statistics(setup: RuleSetup, y: np.ndarray, present: np.ndarray) -> dict[str, np.ndarray]:
    out = {"present_count": np.count_nonzero(present, axis=1)}
    if setup.preferential is not None:
        p, q, _ = setup.preferential
        out["preferential"] = preferential_batch(present, p, q, setup.encoding)
    if setup.llr is not None:
        pd, pf, prior, _ = setup.llr
        out["llr"] = chair_varshney_batch(present, pd, pf, prior)
    if setup.np_rule is not None and setup.np_rule.statistic == "llr":
        out["np"] = np_log_statistic_batch(present, setup.np_rule.pd, setup.np_rule.pf)
    for name, params in setup.central.items():
        if name == "centralised_bayes" and "centralised_known" in out:
            out[name] = out["centralised_known"]  # same statistic, other threshold
        else:
            out[name] = centralised.statistic_from_offsets(y, params)
    return out


def _decide(setup: RuleSetup, stats, present, rng) -> dict[str, np.ndarray]:
    k = stats["present_count"]
    out = {rule: k >= m for rule, m in setup.min_present_count.items()}
    if setup.preferential is not None:
        out["preferential"] = stats["preferential"] >= setup.preferential[2]  # U_G >= lambda_Th-mean
    if setup.llr is not None:
        out["llr"] = stats["llr"] > setup.llr[3]  # eq 31: H1 iff > ln lambda_0 (0 for 0-1 costs, P1 = 1/2)
    if setup.np_rule is not None:
        out["np"] = np_decide_batch(setup.np_rule, present, rng)
    for name, params in setup.central.items():
        out[name] = stats[name] > params.threshold
    return out


def simulate_model(setup: RuleSetup, zeta_mv, sigma_mv, patterns_mv, weights, prior_h1: float,
                   n_trials: int, rng: np.random.Generator, *, chunk: int = 32768, keep: int = 200_000,
                   progress=None, dtype=np.float32) -> MonteCarloResult:
    """Monte Carlo of every rule in ``setup`` on the Gaussian model of the module docstring.

    ``zeta_mv``, ``sigma_mv``: per-taxel thresholds zeta_i (eqs 2-3) and noise std sigma_i;
    ``patterns_mv`` (C, n): the H1 signal vectors S(c) with probabilities ``weights`` (C,);
    ``prior_h1``: pi1 of the total error. ``n_trials`` trials under H0 and as many under H1
    (when C > 0). ``keep``: per-trial statistics kept (first trials) for ROC curves and the
    achieved-P_F analysis. ``progress(done, total)`` is called after every chunk.
    ``fusion_center.evaluation.simulate`` derives all of these from a scene.
    """
    if not isinstance(n_trials, (int, np.integer)) or n_trials < 1:
        raise ParameterError("n_trials", n_trials, "must be an integer >= 1")
    zeta = np.asarray(zeta_mv, dtype=float)
    sigma = np.asarray(sigma_mv, dtype=float)
    n = zeta.size
    patterns = np.asarray(patterns_mv, dtype=float).reshape(-1, n)
    weights = np.asarray(weights, dtype=float)
    pi1 = float(prior_h1)
    taxel_pf = taxel_rates(0.0, zeta, sigma)
    pd_patterns = taxel_rates(patterns, zeta, sigma) if patterns.shape[0] else np.zeros((0, n))

    zeta_t = zeta.astype(dtype)
    sigma_t = sigma.astype(dtype)
    patterns_t = patterns.astype(dtype)
    hypotheses = [0] + ([1] if patterns.shape[0] else [])
    total = n_trials * len(hypotheses)
    done = 0
    successes = {h: {} for h in hypotheses}
    kept = {h: {} for h in hypotheses}
    for h in hypotheses:
        left = int(n_trials)
        while left > 0:
            m = min(chunk, left)
            y = rng.standard_normal((m, n), dtype=dtype)
            y *= sigma_t
            if h == 1:
                if patterns.shape[0] == 1:
                    y += patterns_t[0]
                else:
                    y += patterns_t[rng.choice(patterns.shape[0], size=m, p=weights)]
            present = y >= zeta_t  # eqs 2-4
            stats = _statistics(setup, y, present)
            decided = _decide(setup, stats, present, rng)
            for name, d in decided.items():
                successes[h][name] = successes[h].get(name, 0) + int(np.count_nonzero(d))
            have = sum(len(v) for v in kept[h].get("present_count", []))
            if have < keep:
                take = min(m, keep - have)
                for name, v in stats.items():
                    kept[h].setdefault(name, []).append(np.asarray(v[:take], dtype=float))
            left -= m
            done += m
            if progress is not None:
                progress(done, total)

    results: dict[str, RuleResult] = {}
    names = list(successes[0].keys())
    for name in names:
        exact_pd = exact_pf = None
        m_count = setup.min_present_count.get(name)
        if m_count is not None:
            exact_pd, exact_pf = exact_count_rates(m_count, taxel_pf, pd_patterns, weights)
        elif name == "np" and setup.np_rule is not None and setup.np_rule.statistic == "present_count":
            exact_pd, exact_pf = _exact_randomised_count(setup.np_rule, taxel_pf, pd_patterns, weights)
        elif name in ("preferential", "llr", "np"):
            exact_pd, exact_pf = _exact_other(name, setup, taxel_pf, pd_patterns, weights)
        pf = Rate.of(successes[0][name], n_trials, exact_pf)
        pd = Rate.of(successes[1][name], n_trials, exact_pd) if 1 in successes else None
        results[name] = RuleResult(pd, pf, _total_error(pd, pf, pi1), setup.thresholds.get(name), m_count)
    stats_h0 = {k: np.concatenate(v) for k, v in kept[0].items()}
    stats_h1 = {k: np.concatenate(v) for k, v in kept.get(1, {}).items()}
    return MonteCarloResult(int(n_trials), pi1, results, dict(setup.skipped), stats_h0, stats_h1,
                            taxel_pf, pd_patterns, weights, int(total * n), setup)


def _exact_other(name, setup, taxel_pf, pd_patterns, weights):
    """Exact (P_D, P_F) of the preferential rule (DP over the chain, U_G >= lambda_Th-mean), the
    Chair-Varshney rule (eq 31 > ln lambda_0) and the N-P rule on ln Lambda (eq 32, randomised
    boundary), under H0 and under every H1 pattern (weighted): fusion_center.core.exact_rates.
    (None, None) where the exact law is out of reach (too many count tuples)."""
    from . import exact_rates

    def mixture(fn):
        pf = fn(taxel_pf)
        if pf is None:
            return None, None
        if pd_patterns.shape[0] == 0:
            return None, pf
        pds = [fn(row) for row in pd_patterns]
        if any(v is None for v in pds):
            return None, pf
        return float(sum(w * v for w, v in zip(weights, pds))), pf

    if name == "preferential":
        p, q, tm = setup.preferential
        n = taxel_pf.size
        if exact_rates._lattice(p, q, setup.encoding) is None and n > exact_rates.exact_counts_max_taxels(p, q):
            return None, None  # {0,1} with a non-integer weight beyond the exact counts DPs

        def fn(probs):
            return exact_rates.preferential_error_rates(probs, probs, p, q, setup.encoding, tm, tm).p_detect
        return mixture(fn)
    if name == "llr":
        pd, pf, prior, ln_l0 = setup.llr
        a = np.log(pd) - np.log(pf)
        b = np.log1p(-pd) - np.log1p(-pf)
        shift = math.log(prior) - math.log1p(-prior)
        return mixture(lambda probs: exact_rates.linear_statistic_tail(a, b, probs, ln_l0 - shift, tol=0.0))
    rule = setup.np_rule
    if rule is None or rule.statistic != "llr":
        return None, None
    a = np.log(rule.pd) - np.log(rule.pf)
    b = np.log1p(-rule.pd) - np.log1p(-rule.pf)
    return mixture(lambda probs: exact_rates.linear_statistic_tail(
        a, b, probs, rule.log_threshold, rule.gamma, tol=baselines.LLR_TIE_TOLERANCE))


def _exact_randomised_count(rule, taxel_pf, pd_patterns, weights):
    m = rule.count_threshold
    pmf0 = poisson_binomial.pmf(taxel_pf)
    pf = float(pmf0[m + 1:].sum() + rule.gamma * pmf0[m])
    if pd_patterns.shape[0] == 0:
        return None, pf
    pd = 0.0
    for row, w in zip(pd_patterns, weights):
        pmf1 = poisson_binomial.pmf(row)
        pd += w * float(pmf1[m + 1:].sum() + rule.gamma * pmf1[m])
    return pd, pf


def _total_error(pd: Rate | None, pf: Rate, pi1: float) -> dict:
    """pi1 P_M + pi0 P_F with bounds from the two Wilson intervals (and exact when both known)."""
    pi0 = 1.0 - pi1
    if pd is None:
        return {"estimate": pi0 * pf.estimate, "ci95": [pi0 * pf.lower, pi0 * pf.upper],
                "exact": None if pf.exact is None else pi0 * pf.exact}
    est = pi1 * (1 - pd.estimate) + pi0 * pf.estimate
    lo = pi1 * (1 - pd.upper) + pi0 * pf.lower
    hi = pi1 * (1 - pd.lower) + pi0 * pf.upper
    exact = None
    if pd.exact is not None and pf.exact is not None:
        exact = pi1 * (1 - pd.exact) + pi0 * pf.exact
    return {"estimate": est, "ci95": [lo, hi], "exact": exact}


# --------------------------------------------------------------------------- ROC / achieved P_F
def empirical_roc(stat_h0: np.ndarray, stat_h1: np.ndarray, points: int = 200) -> dict:
    """(P_F, P_D) of "H1 iff statistic >= t" for t over the pooled sample's quantiles."""
    pooled = np.concatenate([stat_h0, stat_h1])
    ts = np.unique(np.quantile(pooled, np.linspace(0, 1, points)))
    s0 = np.sort(stat_h0)
    s1 = np.sort(stat_h1)
    pf = 1.0 - np.searchsorted(s0, ts, side="left") / s0.size
    pd = 1.0 - np.searchsorted(s1, ts, side="left") / s1.size
    pf = np.concatenate([[1.0], pf, [0.0]])
    pd = np.concatenate([[1.0], pd, [0.0]])
    return {"thresholds": ts.tolist(), "pf": pf.tolist(), "pd": pd.tolist(), "auc": mann_whitney_auc(s0, s1)}


def mann_whitney_auc(stat_h0, stat_h1) -> float:
    """Area under the empirical ROC of "H1 iff statistic >= t" over every threshold:
    P(S1 > S0) + P(S1 = S0)/2 over all pairs of the two samples (the Mann-Whitney statistic),
    from the ranks of the pooled sample -- exact for the samples, unlike a trapezoid over a
    grid of thresholds. A NaN statistic gives NaN."""
    s0 = np.asarray(stat_h0, float)
    s1 = np.asarray(stat_h1, float)
    ranks = mean_ranks(np.concatenate([s0, s1]))  # ties get their mean rank
    r1 = float(ranks[s0.size:].sum())
    return (r1 - s1.size * (s1.size + 1) / 2.0) / (s0.size * s1.size)


def mean_ranks(x) -> np.ndarray:
    """Ranks 1..n of the values ``x``, tied values sharing their mean rank (half-integers, exact
    in float); all NaN if any value is NaN. ``scipy.stats.rankdata(x)`` - the same numbers -
    without importing scipy.stats (~0.7 s of CPU, a quarter of ``fusion-center report``'s
    start-up, for one function)."""
    x = np.asarray(x, float)
    if np.isnan(x).any():
        return np.full(x.shape, np.nan)
    order = np.argsort(x, kind="stable")
    y = x[order]
    first = np.flatnonzero(np.r_[True, y[1:] != y[:-1]])     # first index of each run of ties
    counts = np.diff(np.r_[first, y.size])
    ranks = np.empty(y.size)
    ranks[order] = np.repeat(first + 1 + (counts - 1) / 2.0, counts)
    return ranks


def exact_count_roc(taxel_pf, pd_patterns, weights) -> dict:
    """Exact ROC of every count rule "K >= m", m = 0..n+1 (Poisson-binomial): pf, pd, and
    log10_pf = log10 P(K >= m | H0), log10_pm = log10 P(K < m | H1) summed in the log domain
    (exact where pf or 1 - pd underflow; None for an impossible event)."""
    n = taxel_pf.size
    ms = np.arange(n + 2)
    lp0 = np.append(poisson_binomial.log_pmf(taxel_pf), -np.inf)
    log_pf = np.logaddexp.accumulate(lp0[::-1])[::-1]  # ln P(K >= m)
    pf = np.exp(log_pf)
    pd = np.zeros(n + 2)
    log_pm = np.full(n + 2, -np.inf)
    for row, w in zip(pd_patterns, weights):
        lp1 = np.append(poisson_binomial.log_pmf(row), -np.inf)
        pd += w * np.exp(np.logaddexp.accumulate(lp1[::-1])[::-1])
        below = np.r_[-np.inf, np.logaddexp.accumulate(lp1[:-1])]  # ln P(K < m) = ln P(K <= m - 1)
        if w > 0:
            log_pm = np.logaddexp(log_pm, math.log(w) + below)
    log10 = lambda x: [None if not math.isfinite(v) else float(v / math.log(10.0)) for v in x]
    return {"min_present_count": ms.tolist(), "pf": pf.tolist(), "pd": pd.tolist(),
            "log10_pf": log10(log_pf), "log10_pm": log10(log_pm), "method": "exact"}


def area_under_roc(pf, pd) -> float:
    pf = np.asarray(pf)
    pd = np.asarray(pd)
    order = np.argsort(pf, kind="stable")
    return float(np.trapezoid(pd[order], pf[order]))
