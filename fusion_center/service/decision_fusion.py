"""Decision fusion of one cycle (sec. 2.2): the rules of ``[fusion] rules`` over the decisions
*received* in the cycle, with the caches that keep it off the live path.

Every rule of ``[fusion] rules`` the scene supports (:func:`fusion_center.stages.plan_stages`)
runs over the decisions received in the cycle, in fusion order, with n adjusted to the number
received (a missing or silent node is left out; for the preferential rule eq 7 the remaining
taxels become neighbours). HEBTEM thresholds depend only on (n, xi, alpha/beta, p, q) and are
cached per n, so a degraded cycle costs one solve once.

Live fast path (same values as the library functions, tested equal in
``tests/test_pipeline_fastpath.py``): the decisions of a cycle come from the assembler, which
accepts only u_i = +-1 on the wire, so they are checked once per cycle
(:meth:`DecisionFusion.cycle_decisions`) and the rules are evaluated without re-validating them
in every rule:

* additive (eq 6), multiplicative (eq 5) and k-of-n (sec. 2.2.1) depend on the decisions only
  through the received count n and the present count j: sum u_i = 2j - n ({-1,+1} tuple) or
  j ({0,1} tuple). Their whole result (U_G, threshold, decision, p_h1 of eqs 10-13) is computed
  from (n, j) by ``_count_rule`` and cached per (rule, n, j); the full-set entries
  (n = scene n, every j) are computed when the pipeline starts (:meth:`DecisionFusion.warm_up`),
  so cycle 0 costs no solve;
* Chair-Varshney (eq 31) and Neyman-Pearson (eq 32): the per-taxel log-likelihood terms
  ln(pd/pf) and ln((1-pd)/(1-pf)) are computed once per received set (the same numpy
  expressions as :mod:`fusion_center.core.baselines`, so the sums are bit-identical) and summed over
  the cycle's present/absent taxels;
* the preferential rule (eq 7) calls :func:`fusion_center.core.rules.preferential` (it needs the
  order of the decisions) and decides with
  :func:`fusion_center.core.preferential_band.band_decision`: the band edges are compared with
  the exact U_G (its integer counts, mpmath) wherever the float U_G lies within its rounding
  error of an edge, as the count rules' certified counts do.

The pipeline (:mod:`fusion_center.service.pipeline`) calls this once per new decision vector
only: it caches the rule results per vector.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from ..core import baselines, curves, poisson_binomial, rules, thresholds
from ..core.preferential_band import band_decision
from taxel_net.errors import ParameterError
from taxel_net.scene import Scene
from .records import jsonable

DECISIONS = ("H1", "H0", "undecided")
COUNT_RULES = frozenset(("additive", "multiplicative", "k-of-n"))


# --------------------------------------------------------------------------- cached thresholds
@lru_cache(maxsize=512)
def additive_threshold_cached(n: int, xi: float, alpha: float, encoding: str):
    return thresholds.additive_threshold(n, xi, alpha, encoding)


@lru_cache(maxsize=512)
def multiplicative_threshold_cached(n: int, xi: float, beta: float):
    return thresholds.multiplicative_threshold(n, xi, beta)


@lru_cache(maxsize=512)
def preferential_threshold_cached(n: int, xi: float, alpha: float, p: float, q: float, encoding: str):
    return thresholds.preferential_threshold(n, xi, alpha, p, q, encoding)


def verdict(condition: bool) -> str:
    return "H1" if condition else "H0"


def json_result(result: dict) -> dict:
    """A rule's result with JSON-able values (lists element-wise)."""
    return {k: (jsonable(v) if not isinstance(v, list) else [jsonable(x) for x in v]) for k, v in result.items()}


def rule_error(exc: ParameterError) -> dict:
    return {"U_G": None, "threshold": None, "decision": "undecided", "p_h1": None, "error": str(exc)}


def log_ratio_terms(pd: np.ndarray, pf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-taxel log-likelihood terms of eqs 31-32: (present: ln(pd/pf), absent:
    ln((1-pd)/(1-pf))), the same numpy expressions as :mod:`fusion_center.core.baselines`, so sums
    over them equal ``baselines.np_log_statistic`` bit for bit."""
    return np.log(pd) - np.log(pf), np.log1p(-pd) - np.log1p(-pf)


def _memo(cache: dict, key, limit: int, compute):
    """Bounded memo of the per-cycle caches: ``compute()`` once per key (the cache is emptied
    past ``limit`` entries); a ParameterError is cached as the result and raised again."""
    entry = cache.get(key)
    if entry is None:
        if len(cache) > limit:
            cache.clear()
        try:
            entry = compute()
        except ParameterError as exc:
            entry = exc
        cache[key] = entry
    if isinstance(entry, ParameterError):
        raise entry
    return entry


ALIKE_BINOMIAL_MIN = 256  # alike taxels, more received: the N-P rule from binomial laws (np_alike)


def _binomial_pmf(n: int, p: float) -> np.ndarray:
    """P(K = k), k = 0..n, K ~ Binomial(n, p), 0 < p < 1: exp of the log-pmf (lgamma)."""
    from scipy.special import gammaln

    k = np.arange(n + 1, dtype=float)
    log_choose = gammaln(n + 1.0) - gammaln(k + 1.0) - gammaln(n - k + 1.0)
    return np.exp(log_choose + k * math.log(p) + (n - k) * math.log1p(-p))


def np_alike(pd: np.ndarray, pf: np.ndarray, false_alarm: float) -> baselines.NPFusionRule:
    """``baselines.neyman_pearson_fusion`` of identical taxels (its ``"identical"`` method) with
    the count's law from scipy's binomial pmf, O(n), instead of the O(n^2) Poisson-binomial
    recursion (125 ms at 4,096 taxels: a skin's degraded cycle with a new received count would
    wait for it). Same atoms, same boundary; the laws agree to rounding."""
    n = pd.size
    counts = np.arange(n + 1)
    p0 = _binomial_pmf(n, float(pf[0]))
    p1 = _binomial_pmf(n, float(pd[0]))
    a, b = baselines._log_ratio_terms(pd[:1], pf[:1])
    llr_of_count = n * b[0] + counts * (a[0] - b[0])
    values, p0m, p1m = baselines._merge_atoms(llr_of_count, p0, p1)
    j, gamma, achieved, detection = baselines._randomised_boundary(p0m, p1m, false_alarm)
    increasing = bool(a[0] >= b[0])
    if values.size == 1:
        boundary_count = 0 if increasing else n
    else:
        boundary_count = int(np.argmin(np.abs(llr_of_count - values[j])))
    return baselines.NPFusionRule(
        method="identical", statistic="llr", log_threshold=float(values[j]), count_threshold=boundary_count,
        gamma=gamma, achieved_false_alarm=achieved, detection_probability=detection,
        optimal=True, count_increasing=increasing, requested_false_alarm=float(false_alarm), pd=pd, pf=pf)


class DecisionFusion:
    """The fusion rules ``rule_names`` of one scene over a cycle's received decisions, with
    their caches (module docstring). :meth:`warm_up` once before the first cycle."""

    def __init__(self, scene: Scene, rule_names: tuple[str, ...]):
        self.scene = scene
        fusion = scene.fusion
        self.encoding = fusion.tuple
        self.rules = rule_names
        self.n = scene.n
        taxels = scene.taxels
        has_pf = all(t.pf is not None and t.pm is not None for t in taxels)
        self.pf = np.array([t.pf for t in taxels], dtype=float) if has_pf else None
        self.pd = np.array([1.0 - t.pm for t in taxels], dtype=float) if has_pf else None
        # every taxel alike (one pd, one pf): the N-P rule and the LLR terms of a received set
        # depend on its size alone (cached per size: a skin's degraded cycles share a few)
        self._alike = bool(has_pf and np.all(self.pd == self.pd[0]) and np.all(self.pf == self.pf[0]))
        if "llr" in self.rules and self.pf is not None:
            c00, c01, c10, c11 = fusion.costs
            p1 = fusion.prior_h1
            # eq 31 carries ln(P1/P0); the Bayes rule (eq 22) then compares it with
            # ln((C10 - C00)/(C01 - C11)); the comparison flips when both differences are < 0
            self.llr_threshold = baselines.bayes_log_threshold(p1, c00, c01, c10, c11) + math.log(p1 / (1 - p1))
            self.llr_flip = (c10 - c00) < 0
        self._np_rules: dict[bytes, object] = {}
        self._count_results: dict[tuple[str, int, int], dict] = {}
        self._llr_subsets: dict[bytes, object] = {}
        if "llr" in self.rules and self.pf is not None:
            p1 = fusion.prior_h1  # checked in (0, 1) by bayes_log_threshold above
            self._llr_prior = float(np.log(p1) - np.log1p(-p1))  # eq 31's ln(P1/P0), as baselines

    def warm_up(self) -> None:
        """Compute what the first cycles would otherwise compute on the live path: the count
        rules' results for the full set (n = scene n, every present count, thresholds solved
        once), the N-P rule and the log-likelihood terms of the full set."""
        everyone = np.ones(self.n, dtype=bool)
        for name in self.rules:
            if name in COUNT_RULES:
                for present in range(self.n + 1):
                    self._count_result(name, self.n, present)
            elif name == "llr" and self.pf is not None:
                self._llr_terms(everyone)
            elif name == "np" and self.pf is not None:
                self._np_entry(everyone)
            elif name == "preferential":
                f = self.scene.fusion
                try:
                    preferential_threshold_cached(self.n, f.xi, f.alpha, f.p, f.q, self.encoding)
                except ParameterError:
                    pass  # reported by every cycle's result

    def cycle_decisions(self, wire: np.ndarray, available: np.ndarray):
        """(received mask, present mask, n received, present count) of a cycle's {-1,0,+1}
        decisions - the one check of the decisions per cycle: every received u_i must be +-1
        (the assembler accepts nothing else from the wire; local_decision gives +-1)."""
        present_mask = wire == 1
        present = int(np.count_nonzero(present_mask))
        n_received = int(np.count_nonzero(available))
        if n_received != present + int(np.count_nonzero(wire == -1)):
            i = int(np.flatnonzero(available & (wire != 1) & (wire != -1))[0])
            raise ParameterError(f"u[{i}]", int(wire[i]), "a received decision must be -1 or +1")
        return available, present_mask, n_received, present

    def results(self, wire: np.ndarray, received: np.ndarray, n_received: int, present: int) -> dict[str, dict]:
        """Fusion rule -> JSON-able result over the received decisions (checked by
        :meth:`cycle_decisions`; ``n_received`` > 0)."""
        rule_results: dict[str, dict] = {}
        u_pm1 = wire[received]
        present_sub = u_pm1 == 1
        u = u_pm1 if self.encoding == "pm1" else present_sub.astype(np.int8)
        for name in self.rules:
            try:
                result = self._rule(name, n_received, present, received, present_sub, u)
            except ParameterError as exc:
                result = rule_error(exc)
            rule_results[name] = result if name in COUNT_RULES else json_result(result)
        return rule_results

    # ------------------------------------------------------------------ rules
    def _np_entry(self, received: np.ndarray):
        """(N-P rule of the received taxels, its log-likelihood terms), cached per received set
        (a ParameterError is cached and raised again)."""
        def compute():
            if self._alike and np.count_nonzero(received) > ALIKE_BINOMIAL_MIN:
                rule = np_alike(self.pd[received], self.pf[received], self.scene.fusion.np_false_alarm)
            else:
                rule = baselines.neyman_pearson_fusion(self.pd[received], self.pf[received],
                                                       self.scene.fusion.np_false_alarm)
            return (rule, *log_ratio_terms(rule.pd, rule.pf))

        key = int(np.count_nonzero(received)) if self._alike else received.tobytes()
        return _memo(self._np_rules, key, 256, compute)

    def _llr_terms(self, received: np.ndarray):
        """Log-likelihood terms of eq 31 over the received taxels, cached per received set
        (pd, pf checked once in (0, 1) as :func:`baselines.chair_varshney_llr` does)."""
        def compute():
            pd = poisson_binomial.validate_probabilities(self.pd[received], "pd", open_interval=True)
            pf = poisson_binomial.validate_probabilities(self.pf[received], "pf", open_interval=True)
            return log_ratio_terms(pd, pf)

        key = int(np.count_nonzero(received)) if self._alike else received.tobytes()
        return _memo(self._llr_subsets, key, 256, compute)

    def _count_result(self, name: str, n: int, present: int) -> dict:
        """JSON-able result of a count rule for (n received, present), cached (module docstring)."""
        def compute():
            try:
                return json_result(self._count_rule(name, n, present))
            except ParameterError as exc:
                return json_result(rule_error(exc))

        return _memo(self._count_results, (name, n, present), 4096, compute)

    def _count_rule(self, name: str, n: int, present: int) -> dict:
        """Additive (eq 6), multiplicative (eq 5) or k-of-n (sec. 2.2.1) from the counts alone.

        With j = ``present`` of the n received decisions deciding "present" (k = n - j absent),
        sum u_i = n - 2k = 2j - n on the {-1,+1} tuple and n - k = j on the {0,1} tuple: eq 6's
        U_G, eq 5's ln U_G, and the k-of-n rule's sum.
        """
        f = self.scene.fusion
        enc = self.encoding
        total = 2 * present - n if enc == "pm1" else present  # sum of u_i in the scene's tuple
        if name == "additive":
            value = total
            th = additive_threshold_cached(n, f.xi, f.alpha, enc)
            if not th.thresholds:
                lam, decision = None, "undecided"
            else:
                lam = th.thresholds[0] if f.additive_root == "lower" else th.thresholds[-1]
                decision = verdict(value >= lam)
            p = (curves.p_additive_pm1(value, n, f.xi) if enc == "pm1"
                 else curves.p_additive_01(value, n, f.xi))
            return {"U_G": value, "threshold": lam, "decision": decision, "p_h1": p}
        if name == "multiplicative":
            ln_u_g = float(total)
            try:
                u_g = math.exp(ln_u_g)
            except OverflowError:
                u_g = math.inf
            th = multiplicative_threshold_cached(n, f.xi, f.beta)
            if not th.present_counts or th.present_counts[0] is None:
                lam = ln_lam = None
                decision = "undecided"
            else:
                ln_lam = th.ln_thresholds[0]
                lam = math.exp(ln_lam) if ln_lam is not None else 0.0
                # U_G = e^(2j - n) >= lambda  <=>  j >= present_counts[0] (eq 16's root)
                decision = verdict(present >= th.present_counts[0])
            # eqs 10-11 are fitted on the {-1,+1} tuple (fig 2a): ln U_G = 2j - n
            p = curves.p_multiplicative(2 * present - n, n, f.xi) if enc == "pm1" else None
            return {"U_G": u_g, "ln_U_G": ln_u_g, "threshold": lam, "ln_threshold": ln_lam,
                    "decision": decision, "p_h1": p}
        if name == "k-of-n":
            k = f.k
            if not 1 <= k <= n:
                return {"U_G": present, "threshold": None, "decision": "undecided", "p_h1": None}
            lam = 2 * k - n if enc == "pm1" else k  # sec 2.2.1: sum u_i >= 2k - n
            return {"U_G": total, "threshold": lam, "decision": verdict(present >= k), "p_h1": None}
        raise ParameterError("rule", name, "not a count rule")

    def _rule(self, name: str, n: int, present: int, received: np.ndarray, present_sub: np.ndarray,
              u: np.ndarray) -> dict:
        """One rule's result for the cycle; ``present_sub`` (bool) and ``u`` (the decisions in
        the scene's tuple) are over the received taxels, already checked (:meth:`cycle_decisions`)."""
        if name in COUNT_RULES:
            return dict(self._count_result(name, n, present))
        f = self.scene.fusion
        enc = self.encoding
        if name == "preferential":
            value = rules.preferential(u, f.p, f.q, enc)
            th = preferential_threshold_cached(n, f.xi, f.alpha, f.p, f.q, enc)
            # H1 at or above the band, H0 below it, undecided inside (the fuzzy zone, eq 20) or
            # without a band; certified: the exact U_G where rounding cannot decide an edge
            decision = band_decision(th, value, u)
            p = curves.p_preferential(value, th.g_max, f.xi)
            return {"U_G": value, "threshold": th.threshold_mean, "band": [th.threshold_initial, th.threshold_final],
                    "g_max": th.g_max, "decision": decision, "p_h1": p}
        if name == "llr":
            if self.pf is None:
                raise ParameterError("pf", None, "the llr rule needs pf and pm for every taxel")
            present_terms, absent_terms = self._llr_terms(received)
            # eq 31 = ln(P1/P0) + sum_S+ ln(pd/pf) + sum_S- ln((1-pd)/(1-pf))
            value = self._llr_prior + float(np.sum(np.where(present_sub, present_terms, absent_terms)))
            if value == self.llr_threshold:
                decision = "undecided"
            else:
                decision = verdict((value > self.llr_threshold) != self.llr_flip)
            # eq 31 is the log posterior ratio: P(H1|U) = 1 / (1 + e^-llr)
            p = 1.0 / (1.0 + math.exp(-value)) if value > -700 else 0.0
            return {"U_G": value, "threshold": self.llr_threshold, "decision": decision, "p_h1": p}
        if name == "np":
            if self.pf is None:
                raise ParameterError("pf", None, "the np rule needs pf and pm for every taxel")
            rule, present_terms, absent_terms = self._np_entry(received)
            if rule.statistic == "llr":  # eq 32's ln Lambda
                value = float(np.sum(np.where(present_sub, present_terms, absent_terms)))
            else:
                value = float(present)
            lam = rule.log_threshold if rule.statistic == "llr" else rule.count_threshold
            return {"U_G": value, "threshold": lam, "statistic": rule.statistic,
                    "decision": rule.decide_value(value), "p_h1": None}
        raise ParameterError("rule", name, "unknown fusion rule")
