"""Exact laws of the Chair-Varshney / Neyman-Pearson statistic (eqs 31-32) on taxels that come
in kinds, and exact ROC curves from laws.

Kinds: when the taxels come in a few kinds with equal (pd, pf) per kind, ln Lambda (eq 31)
depends only on the present count per kind, whose law is a product of binomials (a
Poisson-binomial per kind where probabilities differ within a kind): the atoms are
enumerated exactly (up to ``KIND_ATOMS_MAX`` count tuples); fully heterogeneous taxels are
exact up to n = 20 (2^20 atoms), beyond that :func:`llr_error_rates` falls back on importance
sampling (:mod:`.rate_sampling`, says so in ``method``). With kinds, the N-P rule (eq 32)
becomes the most powerful randomised test over the per-kind counts (:func:`np_kinds_fusion`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from taxel_net.errors import ParameterError

from .rate_sampling import importance_sampling_tail

__all__ = [
    "KindRates", "kinds_of", "llr_error_rates", "np_kinds_fusion", "KIND_ATOMS_MAX", "linear_statistic_law",
    "linear_statistic_tail", "roc_from_laws",
]

KIND_ATOMS_MAX = 2_000_000


@dataclass(frozen=True)
class KindRates:
    """Exact rates of a fusion rule on the present count per kind (product of binomials)."""

    p_detect: float
    p_false_alarm: float
    p_undecided_h1: float = 0.0
    p_undecided_h0: float = 0.0
    method: str = "kinds"
    samples: int | None = None
    ci95: dict | None = None


def kinds_of(pd: np.ndarray, pf: np.ndarray):
    """Group taxels with equal (pd, pf): (pd_k, pf_k, size_k) arrays."""
    pairs = {}
    for a, b in zip(np.asarray(pd, float), np.asarray(pf, float)):
        pairs[(a, b)] = pairs.get((a, b), 0) + 1
    keys = list(pairs)
    return (np.array([k[0] for k in keys]), np.array([k[1] for k in keys]),
            np.array([pairs[k] for k in keys], dtype=np.int64))


def _kind_atoms(pd_k, pf_k, size_k):
    """Every tuple of present counts per kind: ln Lambda, ln P0, ln P1 (flattened)."""
    from scipy.special import gammaln

    total = int(np.prod(size_k + 1, dtype=float))
    if total > KIND_ATOMS_MAX:
        raise ParameterError("pd/pf", f"{len(size_k)} kinds, {total} count tuples",
                             f"exact kinds enumeration is limited to {KIND_ATOMS_MAX} count tuples")
    llr = np.zeros(1)
    lp0 = np.zeros(1)
    lp1 = np.zeros(1)
    for a1, a0, m in zip(pd_k, pf_k, size_k):
        k = np.arange(m + 1)
        lc = gammaln(m + 1) - gammaln(k + 1) - gammaln(m - k + 1)
        l1 = lc + k * np.log(a1) + (m - k) * np.log1p(-a1)
        l0 = lc + k * np.log(a0) + (m - k) * np.log1p(-a0)
        stat = k * (np.log(a1) - np.log(a0)) + (m - k) * (np.log1p(-a1) - np.log1p(-a0))
        llr = (llr[:, None] + stat[None, :]).ravel()
        lp0 = (lp0[:, None] + l0[None, :]).ravel()
        lp1 = (lp1[:, None] + l1[None, :]).ravel()
    return llr, lp0, lp1


def _tail_sums(llr, lp0, lp1, threshold, tol=1e-9):
    scale = np.maximum(1.0, np.abs(llr))
    above = llr - threshold > tol * scale
    tie = np.abs(llr - threshold) <= tol * scale
    e = lambda lp, mask: float(np.sum(np.exp(lp[mask]))) if mask.any() else 0.0
    return e(lp1, above), e(lp0, above), e(lp1, tie), e(lp0, tie)


def llr_error_rates(pd, pf, prior_h1: float = 0.5, *, samples: int = 200_000,
                    rng: np.random.Generator | None = None) -> KindRates:
    """P_D, P_F of the Chair-Varshney rule (eq 31, H1 iff ln P(H1|U)/P(H0|U) > 0; a tie
    within 1e-9 is "undecided"). Exact when the count tuples per kind fit in KIND_ATOMS_MAX
    (kinds, or all 2^n vectors for n <= 20); otherwise an importance-sampling estimate
    (``method="importance-sampling"``, 95 % intervals in ``ci95``)."""
    pd_k, pf_k, size_k = kinds_of(pd, pf)
    threshold = -math.log(prior_h1 / (1.0 - prior_h1))
    if float(np.prod(size_k + 1.0)) <= KIND_ATOMS_MAX:
        llr, lp0, lp1 = _kind_atoms(pd_k, pf_k, size_k)
        d, f, ud, uf = _tail_sums(llr, lp0, lp1, threshold)
        return KindRates(d, f, ud, uf, method=f"exact ({len(size_k)} kind{'s' if len(size_k) != 1 else ''})")
    pd_arr, pf_arr = np.asarray(pd, float), np.asarray(pf, float)
    a = np.log(pd_arr) - np.log(pf_arr)
    b = np.log1p(-pd_arr) - np.log1p(-pf_arr)
    rng = rng if rng is not None else np.random.default_rng(0)
    det, det_ci = importance_sampling_tail(a, b, pd_arr, threshold, samples, rng)
    fa, fa_ci = importance_sampling_tail(a, b, pf_arr, threshold, samples, rng)
    return KindRates(det, fa, method="importance-sampling", samples=samples,
                     ci95={"p_detect": det_ci, "p_false_alarm": fa_ci})



def np_kinds_fusion(pd, pf, false_alarm: float) -> dict:
    """Most powerful randomised test of size ``false_alarm`` over the present counts per kind
    (N-P lemma on the product-of-binomials law): ln Lambda of every count tuple, sorted, the
    boundary atom randomised. Returns log_threshold, gamma, achieved_false_alarm,
    detection_probability (exact)."""
    from .baselines import _merge_atoms, _randomised_boundary

    pd_k, pf_k, size_k = kinds_of(pd, pf)
    llr, lp0, lp1 = _kind_atoms(pd_k, pf_k, size_k)
    values, p0, p1 = _merge_atoms(llr, np.exp(lp0), np.exp(lp1))
    j, gamma, achieved, detection = _randomised_boundary(p0, p1, false_alarm)
    return {"log_threshold": float(values[j]), "gamma": gamma, "achieved_false_alarm": achieved,
            "detection_probability": detection, "kinds": int(len(size_k)), "method": "kinds"}


def _linear_statistic_atoms(a, b, probs):
    """(S, ln P) of every atom of S = sum_i (a_i if taxel i present else b_i), taxel i present
    with probability probs_i, independent; None beyond KIND_ATOMS_MAX atoms. Taxels with equal
    (a_i, b_i) form a kind, S depends on the present count per kind only, and each kind's count
    has the Poisson-binomial law of its taxels' probabilities (log domain, exact for unequal
    probabilities within a kind); the atoms are the tuples of per-kind counts."""
    from .poisson_binomial import log_pmf

    a = np.asarray(a, float)
    b = np.asarray(b, float)
    probs = np.asarray(probs, float)
    groups: dict = {}
    for i, key in enumerate(zip(a, b)):
        groups.setdefault(key, []).append(i)
    if float(np.prod([len(v) + 1.0 for v in groups.values()])) > KIND_ATOMS_MAX:
        return None
    stat = np.zeros(1)
    logp = np.zeros(1)
    for (ai, bi), members in groups.items():
        m = len(members)
        k = np.arange(m + 1)
        with np.errstate(divide="ignore"):
            lp = log_pmf(probs[members])
        s = k * ai + (m - k) * bi
        stat = (stat[:, None] + s[None, :]).ravel()
        logp = (logp[:, None] + lp[None, :]).ravel()
    live = np.isfinite(logp)
    return stat[live], logp[live]


def linear_statistic_law(a, b, probs, tol: float = 1e-9):
    """The law of S (:func:`_linear_statistic_atoms`) as (values ascending, ln P), atoms within
    ``tol`` (relative) of each other merged; None beyond KIND_ATOMS_MAX atoms."""
    atoms = _linear_statistic_atoms(a, b, probs)
    if atoms is None:
        return None
    stat, logp = atoms
    order = np.argsort(stat, kind="stable")
    stat, logp = stat[order], logp[order]
    gap = np.diff(stat) > tol * np.maximum(1.0, np.abs(stat[1:]))
    start = np.flatnonzero(np.r_[True, gap])
    values = stat[start]
    merged = np.array([_logsumexp(logp[s:e]) for s, e in zip(start, np.r_[start[1:], stat.size])])
    return values, merged


def _logsumexp(x) -> float:
    x = np.asarray(x, float)
    top = float(x.max())
    return top + math.log(float(np.exp(x - top).sum())) if math.isfinite(top) else -math.inf


def roc_from_laws(law_h0, laws_h1, weights, points: int = 400) -> dict:
    """Exact ROC of "H1 iff statistic >= t" from the law under H0 and the laws under the H1
    patterns (mixed with ``weights``), t over every attainable value: P_F(t) and P_D(t) as
    tails summed from the top in the log domain. Returns thresholds, pf, pd, log10_pf and
    log10_pm (P_M = 1 - P_D from the lower tails, exact also where they underflow), auc (trapezoid over all thresholds, linear axes) and at most
    about ``points`` + 2 per decade of pf of them for plotting."""
    values = np.unique(np.concatenate([law_h0[0], *[law[0] for law in laws_h1]]))[::-1]

    def log_tail(law):
        vals, logp = law
        order = np.argsort(vals)[::-1]
        vals, logp = vals[order], logp[order]
        cum = np.logaddexp.accumulate(logp)  # ln P(stat >= vals[j])
        idx = np.searchsorted(-vals, -values, side="right") - 1  # last law value >= t
        out = np.full(values.size, -np.inf)
        ok = idx >= 0
        out[ok] = cum[idx[ok]]
        return out

    def log_below(law):  # ln P(stat < t): the atoms below each t, summed from the bottom
        vals, logp = law
        order = np.argsort(vals)
        vals, logp = vals[order], logp[order]
        cum = np.logaddexp.accumulate(logp)
        idx = np.searchsorted(vals, values, side="left") - 1  # last law value < t
        out = np.full(values.size, -np.inf)
        ok = idx >= 0
        out[ok] = cum[idx[ok]]
        return out

    log_pf = log_tail(law_h0)
    pd = np.zeros(values.size)
    log_pm = np.full(values.size, -np.inf)
    for law, w in zip(laws_h1, weights):
        pd += w * np.exp(log_tail(law))
        if w > 0:
            log_pm = np.logaddexp(log_pm, math.log(w) + log_below(law))
    pf = np.exp(log_pf)
    pf_all = np.r_[0.0, pf, 1.0]
    pd_all = np.r_[0.0, pd, 1.0]
    auc = float(np.trapezoid(pd_all, pf_all))
    # thinning for the plot: the first threshold of every half decade of pf and of every
    # 1/points step of pd, and both ends
    with np.errstate(divide="ignore", invalid="ignore"):
        decade = np.where(np.isfinite(log_pf), np.floor(2.0 * log_pf / math.log(10.0)), -1e9)
    step = np.floor(pd * points)
    keep = np.union1d(np.unique(decade, return_index=True)[1], np.unique(step, return_index=True)[1])
    keep = np.union1d(keep, [0, values.size - 1]).astype(int)
    log10_pf = log_pf / math.log(10.0)
    log10_pm = log_pm / math.log(10.0)
    finite = lambda arr: [None if not math.isfinite(x) else float(x) for x in arr[keep]]
    return {"thresholds": values[keep].tolist(), "pf": pf[keep].tolist(), "pd": pd[keep].tolist(),
            "log10_pf": finite(log10_pf), "log10_pm": finite(log10_pm), "auc": auc, "method": "exact"}


def linear_statistic_tail(a, b, probs, threshold: float, gamma: float = 0.0, tol: float = 1e-9) -> float | None:
    """P(S > threshold) + gamma P(S = threshold) for S = sum_i (a_i if taxel i present else b_i),
    taxel i present with probability probs_i, independent (eq 31/32 statistics; ties within
    tol relative). Exact over the atoms of :func:`_linear_statistic_atoms` (kinds of equal
    (a_i, b_i), a Poisson-binomial count per kind); None beyond KIND_ATOMS_MAX atoms."""
    atoms = _linear_statistic_atoms(a, b, probs)
    if atoms is None:
        return None
    stat, logp = atoms
    scale = np.maximum(1.0, np.abs(stat))
    above = stat - threshold > tol * scale
    tie = np.abs(stat - threshold) <= tol * scale
    return float(np.exp(logp[above]).sum() + gamma * np.exp(logp[tie]).sum())
