"""Per-cycle evaluation: one :class:`ClosedCycle` -> one JSON-able record (dict).

Pure with respect to the bus: the record is a function of the closed cycle, the scene and
the pipeline's own state carried from cycle to cycle (the slip tracker), so live runs and
replays produce identical records.

What is computed (chapter sections in brackets):

* fusion (sec. 2.2): every rule of ``[fusion] rules`` the scene supports
  (:func:`fusion_center.stages.plan_stages`) over the decisions *received* in the cycle, in
  fusion order, with n adjusted to the number received (a missing or silent node is left
  out; for the preferential rule eq 7 the remaining taxels become neighbours). HEBTEM
  thresholds depend only on (n, xi, alpha/beta, p, q) and are cached per n, so a degraded
  cycle costs one solve once. The record's ``decision`` is the verdict of
  ``[fusion] decide_with``.
* raw mode (issue 6): the nodes send X_i (TPDO2, REAL32 mV) instead of u_i; the centre
  decides per taxel with the nodes' own test (eqs 1-4, ``encoding.local_decision``) and fuses
  those decisions with every rule as in decision mode, and it also runs the centralised
  raw-data tests of :mod:`fusion_center.core.centralised` (``rules.centralised_glrt``,
  ``rules.centralised_known``: statistic, threshold at the scene's ``np_false_alarm``,
  decision) - the "what you lose by deciding locally" reference. Their parameters are built
  once (``params_from_scene``); a cycle with readings missing uses the same test on the
  received taxels (threshold recomputed once per missing-set, cached).
* forces (sec. 4.1-4.2, 7): need the readings X_i, which travel on the bus only in raw mode.
  In decision mode a node sends only u_i (1 byte), so no force, grip limit or load is
  computable and the stage is skipped (``stages_skipped`` says so). In raw mode, with
  Y = X - N_i (eq 4), over the taxels deciding "present" (a cell deciding "absent" carries
  no force): tangential cells (non-zero slope) F = (Y - c)/m (eq 30); the total tangential
  force is eqs 24-25 over the cells, or - when every tangential cell has a gripper ``jaw`` and
  ``axis`` - eqs 28a/28b/29 per jaw and their mean (``forces.gripper_tangential``);
  load cells (``grip_factor`` M) give the grip force F_g = Y/M (eq 27b, mean over the jaws);
  the grip-force limit F_g^cal = TotF_t / mu (eq 26a) and the maximum load W = 2 mu F_g^cal
  (eq 26b).
* area (sec. 4.3.2, 6.2.3.3, eq 35): convex hull of the scene coordinates of the taxels
  deciding "present" - computable from u_i alone.
* contact type (sec. 5.2, eqs 34a/34b, Table 1): t_c = present / n_received and
  fp_c = area / area of the hull of all taxels.
* slip (sec. 4): :class:`fusion_center.core.slip.SlipTracker`, motion criterion over the centroid
  of the present taxels, plus the force criterion TotF_t > mu F_g when raw-mode forces give
  both a total tangential force and a load-cell grip force.

Every record says what did not run and why: ``stages_skipped`` (stage -> reason) and
``rules_skipped`` (fusion rule or centralised test -> reason), computed once per scene by
:func:`fusion_center.stages.plan_stages` and copied into each record.

Live fast path (same values as the library functions, tested equal in
``tests/test_pipeline_fastpath.py``): the decisions of a cycle come from the assembler, which
accepts only u_i = +-1 on the wire, so they are checked once per cycle (``_cycle_decisions``)
and the rules are evaluated without re-validating them in every rule:

* additive (eq 6), multiplicative (eq 5) and k-of-n (sec. 2.2.1) depend on the decisions only
  through the received count n and the present count j: sum u_i = 2j - n ({-1,+1} tuple) or
  j ({0,1} tuple). Their whole result (U_G, threshold, decision, p_h1 of eqs 10-13) is computed
  from (n, j) by ``_count_rule`` and cached per (rule, n, j); the full-set entries
  (n = scene n, every j) are computed when the pipeline starts, so cycle 0 costs no solve;
* Chair-Varshney (eq 31) and Neyman-Pearson (eq 32): the per-taxel log-likelihood terms
  ln(pd/pf) and ln((1-pd)/(1-pf)) are computed once per received set (the same numpy
  expressions as :mod:`fusion_center.core.baselines`, so the sums are bit-identical) and summed over
  the cycle's present/absent taxels;
* the preferential rule (eq 7) calls :func:`fusion_center.core.rules.preferential` (it needs the
  order of the decisions);
* contact type: :func:`fusion_center.core.contact.classify_ratio` (scalar, same class boundaries as
  :func:`~fusion_center.core.contact.classify`); ground truth precomputed for the scene's cycles;
* everything that depends only on the decision vector (received and present sets, fusion
  rules, area, t_c/fp_c and contact types) is cached per vector (``_pattern``): a sensor at
  rest or under a steady contact repeats its vector, so most cycles only copy it; a new vector
  costs the computation above (the tail of the SYNC -> record latency: a new contact pattern
  needs a convex hull, eq 35, and a new received set its thresholds).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from .. import evaluation
from ..core import baselines, centralised, contact, curves, forces, geometry, poisson_binomial, rules, thresholds
from ..core.encoding import local_decision
from taxel_net.errors import ParameterError
from taxel_net.scene import Scene
from ..stages import plan_stages
from .cycles import ClosedCycle

DECISIONS = ("H1", "H0", "undecided")


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


def _jsonable(value):
    """Plain Python scalars for json; non-finite floats become None (JSON has no NaN)."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    value = float(value)
    return value if math.isfinite(value) else None


def _verdict(condition: bool) -> str:
    return "H1" if condition else "H0"


def _json_result(result: dict) -> dict:
    """A rule's result with JSON-able values (lists element-wise)."""
    return {k: (_jsonable(v) if not isinstance(v, list) else [_jsonable(x) for x in v]) for k, v in result.items()}


def _rule_error(exc: ParameterError) -> dict:
    return {"U_G": None, "threshold": None, "decision": "undecided", "p_h1": None, "error": str(exc)}


def log_ratio_terms(pd: np.ndarray, pf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-taxel log-likelihood terms of eqs 31-32: (present: ln(pd/pf), absent:
    ln((1-pd)/(1-pf))), the same numpy expressions as :mod:`fusion_center.core.baselines`, so sums
    over them equal ``baselines.np_log_statistic`` bit for bit."""
    return np.log(pd) - np.log(pf), np.log1p(-pd) - np.log1p(-pf)


def _memo(cache: dict, key, limit: int, compute):
    """Bounded memo of the pipeline's per-cycle caches: ``compute()`` once per key (the cache is
    emptied past ``limit`` entries); a ParameterError is cached as the result and raised again."""
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


_COUNT_RULES = frozenset(("additive", "multiplicative", "k-of-n"))


class _Pattern(NamedTuple):
    """Everything of a record that depends only on the cycle's decision vector (cached per vector)."""

    received: np.ndarray        # bool per taxel
    present_mask: np.ndarray    # bool per taxel
    n_received: int
    present: int
    present_nodes: tuple
    rules: dict                 # fusion rule -> JSON-able result (copied into each record)
    area: float | None          # eq 35 (None: stage not run)
    contact: tuple              # (key, value) pairs: t_c, contact_type, fp_c, contact_type_fp


class CyclePipeline:
    """Evaluate closed cycles of one scene (stateful only through the slip tracker)."""

    def __init__(self, scene: Scene, *, truth: bool = True):
        self.scene = scene
        self.with_truth = truth
        self.plan = plan_stages(scene)
        fusion = scene.fusion
        self.encoding = fusion.tuple
        self.rules = tuple(r for r in fusion.rules if r in self.plan.rules_run)
        self.decide_with = fusion.decide_with
        taxels = scene.taxels
        self.labels = [t.node_id if t.channel == 0 else f"{t.channel}:{t.node_id}" for t in taxels]
        self.n = scene.n
        self.zeta = np.array([t.zeta_mv for t in taxels], dtype=float)
        self.noise = np.array([t.noise_mv for t in taxels], dtype=float)
        has_pf = all(t.pf is not None and t.pm is not None for t in taxels)
        self.pf = np.array([t.pf for t in taxels], dtype=float) if has_pf else None
        self.pd = np.array([1.0 - t.pm for t in taxels], dtype=float) if has_pf else None
        self.slope = np.array([t.slope if t.slope is not None else 0.0 for t in taxels], dtype=float)
        self.intercept = np.array([t.intercept if t.intercept is not None else 0.0 for t in taxels],
                                  dtype=float)
        self.tangential = self.slope != 0.0
        self.grip_factor = np.array([t.grip_factor if t.grip_factor else 0.0 for t in taxels], dtype=float)
        self.load_cells = self.grip_factor != 0.0
        self.jaws = self._jaw_layout(taxels)
        self.raw_mode = scene.bus.mode == "raw"
        self.mode = scene.bus.mode
        self.stages_skipped = dict(self.plan.skipped)
        self.rules_skipped = self.plan.all_rules_skipped
        # centralised raw-data tests: parameters and thresholds once per scene (raw mode only)
        self.central: dict[str, centralised.CentralisedParams] = {}
        for name in self.plan.central_run:
            self.central[name] = evaluation.params_from_scene(scene, name.removeprefix("centralised_"))
        self._central_subsets: dict[tuple[str, bytes], object] = {}
        self.hold = scene.bus.transmission_type != 1
        has_xy = all(t.x is not None and t.y is not None for t in taxels)
        self.xy = np.array([[t.x, t.y] for t in taxels], dtype=float) if has_xy else None
        self.total_area = geometry.contact_area(self.xy) if has_xy and self.n >= 3 else 0.0
        self.want_forces = "forces" in self.plan.run and self.raw_mode
        self.want_area = "area" in self.plan.run and self.xy is not None
        self.want_contact = "contact_type" in self.plan.run
        self.slip = None
        if "slip" in self.plan.run and self.xy is not None:
            from ..core.slip import SlipTracker

            self.slip = SlipTracker(scene.forces.mu, noise_band=self._noise_band(),
                                    period=scene.bus.sync_period_ms * 1e-3)
        self._last_slip_t: float | None = None
        if "llr" in self.rules and self.pf is not None:
            c00, c01, c10, c11 = fusion.costs
            p1 = fusion.prior_h1
            # eq 31 carries ln(P1/P0); the Bayes rule (eq 22) then compares it with
            # ln((C10 - C00)/(C01 - C11)); the comparison flips when both differences are < 0
            self.llr_threshold = baselines.bayes_log_threshold(p1, c00, c01, c10, c11) + math.log(p1 / (1 - p1))
            self.llr_flip = (c10 - c00) < 0
        self._np_rules: dict[bytes, object] = {}
        self._areas: dict[bytes, float] = {}
        self._count_results: dict[tuple[str, int, int], dict] = {}
        self._patterns: dict[bytes, _Pattern] = {}
        self._llr_subsets: dict[bytes, object] = {}
        if "llr" in self.rules and self.pf is not None:
            p1 = fusion.prior_h1  # checked in (0, 1) by bayes_log_threshold above
            self._llr_prior = float(np.log(p1) - np.log1p(-p1))  # eq 31's ln(P1/P0), as baselines
        self._truth: list[str] = []
        if truth:
            from node_sim.physics import truth_batch

            self._truth = ["H1" if present else "H0" for present in truth_batch(scene, np.arange(scene.cycles))]
        self._warm_up()

    def _warm_up(self) -> None:
        """Compute what the first cycles would otherwise compute on the live path: the count
        rules' results for the full set (n = scene n, every present count, thresholds solved
        once), the N-P rule and the log-likelihood terms of the full set."""
        everyone = np.ones(self.n, dtype=bool)
        for name in self.rules:
            if name in _COUNT_RULES:
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

    @staticmethod
    def _jaw_layout(taxels):
        """Gripper layout (sec. 3.2, 7.2) when every tangential cell has a jaw and an axis:
        {jaw: (indexes of its y-axis cells, indexes of its x-axis cells)}, else None."""
        cells = [(i, t) for i, t in enumerate(taxels) if t.slope is not None and t.slope != 0.0]
        if not cells or any(t.jaw is None or t.axis is None for _, t in cells):
            return None
        layout: dict[str, tuple[list[int], list[int]]] = {}
        for i, t in cells:
            ys, xs = layout.setdefault(t.jaw, ([], []))
            (ys if t.axis == "y" else xs).append(i)
        return {jaw: (np.array(ys, dtype=np.intp), np.array(xs, dtype=np.intp)) for jaw, (ys, xs) in layout.items()}

    def _noise_band(self) -> float:
        """Half the smallest distance between distinct taxel locations: one taxel pitch of
        centroid motion is slip, less is the staircase of the taxel grid."""
        pts = np.unique(self.xy, axis=0)
        if len(pts) < 2:
            return 1.0
        d = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
        d[d == 0] = np.inf
        return float(d.min()) / 2.0

    def _area(self, present_mask: np.ndarray) -> float:
        """Eq 35 on the convex hull of the present taxels (cached per pattern: contacts repeat)."""
        key = present_mask.tobytes()
        area = self._areas.get(key)
        if area is None:
            if len(self._areas) > 1024:
                self._areas.clear()
            area = self._areas[key] = geometry.contact_area(self.xy[present_mask])
        return area

    # ------------------------------------------------------------------ rules
    def _np_entry(self, received: np.ndarray):
        """(N-P rule of the received taxels, its log-likelihood terms), cached per received set
        (a ParameterError is cached and raised again)."""
        def compute():
            rule = baselines.neyman_pearson_fusion(self.pd[received], self.pf[received],
                                                   self.scene.fusion.np_false_alarm)
            return (rule, *log_ratio_terms(rule.pd, rule.pf))

        return _memo(self._np_rules, received.tobytes(), 256, compute)

    def _llr_terms(self, received: np.ndarray):
        """Log-likelihood terms of eq 31 over the received taxels, cached per received set
        (pd, pf checked once in (0, 1) as :func:`baselines.chair_varshney_llr` does)."""
        def compute():
            pd = poisson_binomial.validate_probabilities(self.pd[received], "pd", open_interval=True)
            pf = poisson_binomial.validate_probabilities(self.pf[received], "pf", open_interval=True)
            return log_ratio_terms(pd, pf)

        return _memo(self._llr_subsets, received.tobytes(), 256, compute)

    def _count_result(self, name: str, n: int, present: int) -> dict:
        """JSON-able result of a count rule for (n received, present), cached (module docstring)."""
        def compute():
            try:
                return _json_result(self._count_rule(name, n, present))
            except ParameterError as exc:
                return _json_result(_rule_error(exc))

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
                decision = _verdict(value >= lam)
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
                decision = _verdict(present >= th.present_counts[0])
            # eqs 10-11 are fitted on the {-1,+1} tuple (fig 2a): ln U_G = 2j - n
            p = curves.p_multiplicative(2 * present - n, n, f.xi) if enc == "pm1" else None
            return {"U_G": u_g, "ln_U_G": ln_u_g, "threshold": lam, "ln_threshold": ln_lam,
                    "decision": decision, "p_h1": p}
        if name == "k-of-n":
            k = f.k
            if not 1 <= k <= n:
                return {"U_G": present, "threshold": None, "decision": "undecided", "p_h1": None}
            lam = 2 * k - n if enc == "pm1" else k  # sec 2.2.1: sum u_i >= 2k - n
            return {"U_G": total, "threshold": lam, "decision": _verdict(present >= k), "p_h1": None}
        raise ParameterError("rule", name, "not a count rule")

    def _rule(self, name: str, n: int, present: int, received: np.ndarray, present_sub: np.ndarray,
              u: np.ndarray) -> dict:
        """One rule's result for the cycle; ``present_sub`` (bool) and ``u`` (the decisions in
        the scene's tuple) are over the received taxels, already checked (``_cycle_decisions``)."""
        if name in _COUNT_RULES:
            return dict(self._count_result(name, n, present))
        f = self.scene.fusion
        enc = self.encoding
        if name == "preferential":
            value = rules.preferential(u, f.p, f.q, enc)
            th = preferential_threshold_cached(n, f.xi, f.alpha, f.p, f.q, enc)
            if th.threshold_mean is None:
                decision = "undecided"
            elif value >= th.threshold_final:
                decision = "H1"
            elif value < th.threshold_initial:
                decision = "H0"
            else:
                decision = "undecided"  # inside the threshold band: the fuzzy zone (eqs 19-20)
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
                decision = _verdict((value > self.llr_threshold) != self.llr_flip)
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

    # ------------------------------------------------------------------ raw mode
    def _central_params(self, name: str, available: np.ndarray):
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
        params = self.central[name]
        if available.all():
            return params
        key = (name, available.tobytes())
        sub = self._central_subsets.get(key)
        if sub is None:
            if len(self._central_subsets) > 256:
                self._central_subsets.clear()
            try:
                sub = self._subset_params(params, available)
            except ParameterError as exc:
                sub = exc
            self._central_subsets[key] = sub
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

    def _central(self, name: str, readings: np.ndarray, available: np.ndarray) -> dict:
        """Centralised raw-data test of one cycle (decide H1 iff statistic > threshold)."""
        params = self._central_params(name, available)
        value = centralised.centralised_llr(readings[available], params)
        result = {"U_G": value, "threshold": params.threshold, "decision": _verdict(value > params.threshold),
                  "false_alarm": params.info["false_alarm"], "n": int(params.n)}
        if params.method == "known":
            # exact log-likelihood ratio of the scene's own H1: posterior with the prior (eq 22)
            p1 = self.scene.fusion.prior_h1
            z = value + math.log(p1 / (1.0 - p1))
            result["p_h1"] = 1.0 / (1.0 + math.exp(-z)) if z > -700 else 0.0
        else:
            result["p_h1"] = None
        return result

    def _forces(self, readings: np.ndarray, present_mask: np.ndarray) -> tuple[dict, float | None, float | None]:
        """Raw-mode forces of one cycle (module docstring: eqs 30, 24-25 or 28-29, 27b, 26a/b)."""
        scene = self.scene
        labels = self.labels
        mu = scene.forces.mu
        angle = math.radians(scene.forces.inclusion_angle_deg)
        valid = present_mask & ~np.isnan(readings)
        y = readings - self.noise  # Y = X - N (eq 4)
        out: dict = {"unit": scene.forces.unit}
        tangential_cells = self.tangential
        per_cell = np.zeros(self.n)
        cells = valid & tangential_cells
        if cells.any():
            per_cell[cells] = forces.tangential_force(y[cells], self.slope[cells], self.intercept[cells])  # eq 30
        out["per_taxel"] = {str(labels[i]): _jsonable(per_cell[i]) for i in np.flatnonzero(cells)}
        total = None
        if tangential_cells.any():
            if self.jaws is not None:
                per_jaw = {}
                for jaw, (ys, xs) in self.jaws.items():
                    fy = per_cell[ys] if ys.size else np.zeros(1)
                    fx = forces.total_tangential(per_cell[xs], 0.0) if xs.size else 0.0
                    per_jaw[jaw] = forces.jaw_tangential(fy, fx, angle)  # eqs 28a, 28b, 29
                total = float(np.mean(list(per_jaw.values())))  # sec 7.2: mean over the jaws
                out["tangential_per_jaw"] = {jaw: _jsonable(v) for jaw, v in per_jaw.items()}
            else:
                total = forces.total_tangential(per_cell[cells], angle) if cells.any() else 0.0  # eqs 24-25
            out["total_tangential"] = _jsonable(total)
        grip = None
        if self.load_cells.any():
            lc = np.flatnonzero(self.load_cells)
            per_lc = np.zeros(lc.size)
            live = valid[lc]
            if live.any():  # eq 27b: F_g = Y / M; a load cell deciding "absent" carries no grip
                per_lc[live] = forces.load_cell_grip_force(y[lc][live], self.grip_factor[lc][live]).per_jaw
            grip = float(per_lc.mean())
            out["grip_force"] = _jsonable(grip)
            out["grip_force_per_cell"] = {str(labels[i]): _jsonable(f) for i, f in zip(lc, per_lc)}
        if total is not None:
            limit = forces.grip_force_limit(total, mu)  # eq 26a
            out["grip_force_limit"] = _jsonable(limit)
            out["max_load"] = _jsonable(forces.max_load(limit, mu))  # eq 26b
        return out, total, grip

    # ------------------------------------------------------------------ the record
    def evaluate(self, closed: ClosedCycle) -> dict:
        scene = self.scene
        labels = self.labels
        if self.raw_mode:
            readings = closed.readings
            if self.hold:
                readings = np.where(np.isnan(readings) & ~closed.missing, closed.held_readings, readings)
            available = ~np.isnan(readings)
            wire = np.zeros(self.n, dtype=np.int8)
            if available.any():
                wire[available] = local_decision(readings[available], self.noise[available],
                                                 self.zeta[available], "pm1")
        else:
            wire = closed.decisions
            if self.hold:
                wire = np.where((wire == 0) & ~closed.missing, closed.held_decisions, wire).astype(np.int8)
            available = None  # wire != 0, computed on a pattern-cache miss
            readings = None
        pattern = self._pattern(wire, available)
        present_mask, n_received = pattern.present_mask, pattern.n_received
        missing = closed.missing
        silent = closed.expected & ~closed.received

        record: dict = {
            "cycle": closed.cycle,
            "t": round(closed.sync_us * 1e-6, 6),
            "sync_counter": closed.sync_counter,
            "closed_by": closed.closed_by,
            "n_expected": self.n,
            "n_live": self.n - int(np.count_nonzero(missing)),
            "n_received": n_received,
            "present_count": pattern.present,
            "present_nodes": list(pattern.present_nodes),
            "mode": self.mode,
        }
        stages_run: list[str] = []
        rule_results: dict[str, dict] = {}
        for name, result in pattern.rules.items():
            rule_results[name] = copied = dict(result)
            if "band" in copied:
                copied["band"] = list(copied["band"])
        if n_received > 0:
            for name in self.central:
                try:
                    result = self._central(name, readings, available)
                except ParameterError as exc:
                    result = {"U_G": None, "threshold": None, "decision": "undecided", "p_h1": None,
                              "error": str(exc)}
                rule_results[name] = {k: _jsonable(v) for k, v in result.items()}
            stages_run.append("fusion")
        main = rule_results.get(self.decide_with)
        record["U_G"] = main["U_G"] if main else None
        record["threshold"] = main["threshold"] if main else None
        record["decision"] = main["decision"] if main else "undecided"
        record["p_h1"] = main["p_h1"] if main else None
        record["decide_with"] = self.decide_with
        record["degraded"] = n_received < self.n
        record["missing_nodes"] = [labels[i] for i in np.flatnonzero(missing)] if missing.any() else []
        record["silent_nodes"] = [labels[i] for i in np.flatnonzero(silent)] if silent.any() else []
        record["late_frames"] = closed.late_frames
        record["bad_frames"] = closed.bad_frames
        record["emcy"] = [e.as_record() for e in closed.emcy]
        record["rules"] = rule_results

        t_seconds = closed.sync_us * 1e-6
        total_tangential = grip_force = None
        if self.want_forces and readings is not None:
            record["forces"], total_tangential, grip_force = self._forces(readings, present_mask)
            stages_run.append("forces")
        if self.want_area:
            record["area"] = _jsonable(pattern.area)
            stages_run.append("area")
        if self.want_contact and n_received > 0:
            record.update(pattern.contact)
            stages_run.append("contact_type")
        if self.slip is not None and (self._last_slip_t is None or t_seconds > self._last_slip_t):
            self._last_slip_t = t_seconds
            if total_tangential is not None and grip_force is not None:
                state = self.slip.update(t_seconds, self.xy[present_mask], total_tangential, grip_force)
            else:
                state = self.slip.update(t_seconds, self.xy[present_mask])
            record["slip"] = {
                "contact": state.contact,
                "slipping": state.slipping,
                "criterion": state.criterion,
                "force_ratio": _jsonable(state.force_ratio),
                "onset_cycle": None if state.onset_index is None else closed.cycle - (state.cycle - state.onset_index),
                "displacement": _jsonable(state.displacement),
                "speed": _jsonable(state.speed),
                "distance": _jsonable(state.distance),
            }
            stages_run.append("slip")
        record["stages_run"] = stages_run
        record["stages_skipped"] = self.stages_skipped
        record["rules_skipped"] = self.rules_skipped
        if self.with_truth:
            record["truth"] = self.truth(closed.cycle)
        return record

    def truth(self, cycle: int) -> str:
        if 0 <= cycle < len(self._truth):
            return self._truth[cycle]  # precomputed with node_sim.physics.truth_batch
        from node_sim.physics import object_present

        return "H1" if object_present(self.scene, cycle) else "H0"

    def _pattern(self, wire: np.ndarray, available: np.ndarray | None) -> _Pattern:
        """The decision-vector part of the record, cached per vector (``wire``: {-1,0,+1} per
        taxel, 0 = not received; rules, area and contact type are functions of it alone)."""
        key = wire.tobytes()
        pattern = self._patterns.get(key)
        if pattern is None:
            if len(self._patterns) > 1024:
                self._patterns.clear()
            pattern = self._patterns[key] = self._new_pattern(wire, wire != 0 if available is None else available)
        return pattern

    def _new_pattern(self, wire: np.ndarray, available: np.ndarray) -> _Pattern:
        received, present_mask, n_received, present = self._cycle_decisions(wire, available)
        rule_results: dict[str, dict] = {}
        if n_received > 0:
            u_pm1 = wire[received]
            present_sub = u_pm1 == 1
            u = u_pm1 if self.encoding == "pm1" else present_sub.astype(np.int8)
            for name in self.rules:
                try:
                    result = self._rule(name, n_received, present, received, present_sub, u)
                except ParameterError as exc:
                    result = _rule_error(exc)
                rule_results[name] = result if name in _COUNT_RULES else _json_result(result)
        area = None
        if self.want_area:
            # eq 35 of fewer than 3 points is 0 (geometry.contact_area: no polygon), no hull needed
            area = self._area(present_mask) if present >= 3 else 0.0
        contact_fields: list[tuple[str, object]] = []
        if self.want_contact and n_received > 0:
            t_c = contact.taxel_count_ratio(present, n_received)
            contact_fields += [("t_c", _jsonable(t_c)), ("contact_type", contact.classify_ratio(t_c).value)]
            if area is not None and self.total_area > 0:
                fp_c = contact.friction_plane_ratio(min(area, self.total_area), self.total_area)
                contact_fields += [("fp_c", _jsonable(fp_c)), ("contact_type_fp", contact.classify_ratio(fp_c).value)]
        labels = self.labels
        return _Pattern(received, present_mask, n_received, present,
                        tuple(labels[i] for i in np.flatnonzero(present_mask)), rule_results, area,
                        tuple(contact_fields))

    def _cycle_decisions(self, wire: np.ndarray, available: np.ndarray):
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
