"""The numerical core applied to a scene: what its pure functions need, derived from a scene.

``fusion_center.core`` takes numbers (thresholds, per-taxel rates, signal patterns); a scene
(``taxel_net.scene.Scene``) says what they are for one network, object and fusion set-up. This
module turns one into the other:

* :func:`scene_patterns` - the H1 signal vectors S(c) of the scene's present cycles and their
  weights, from the ground truth the node twins also use (``node_sim.physics``);
* :func:`count_threshold_for`, :func:`preferential_threshold_mean`, :func:`declared_pd_pf`,
  :func:`setup_rules` - every rule's decision parameters (thresholds of eqs 16-18, eq 22,
  eq 32) for the scene's fusion set-up, honouring the stage plan (``fusion_center.stages``);
* :func:`params_from_scene` - the centralised raw-data test's parameters;
* :func:`simulate` - Monte Carlo of every rule on the scene (``core.montecarlo.simulate_model``).

No CAN and no files: a scene object in, numbers out.
"""

from __future__ import annotations

import numpy as np

from node_sim import physics  # the ground truth shared with the node twins
from taxel_net.errors import ParameterError

from .core import baselines, centralised, montecarlo, thresholds
from .stages import centralised_support, plan_stages

def scene_patterns(scene) -> tuple[np.ndarray, np.ndarray, float]:
    """Distinct H1 signal vectors S(c) over the scene's present cycles (ground truth,
    ``node_sim.physics``), their weights, and pi1 = the share of present cycles."""
    rows = []
    present_cycles = 0
    for cycle in range(scene.cycles):
        if physics.object_present(scene, cycle):
            present_cycles += 1
            rows.append(np.asarray(physics.signal_mv(scene, cycle), dtype=float))
    if not rows:
        return np.zeros((0, scene.n)), np.zeros(0), 0.0
    patterns, counts = np.unique(np.vstack(rows), axis=0, return_counts=True)
    return patterns, counts / counts.sum(), present_cycles / scene.cycles



def nominal_signal_mv(taxel, obj) -> float:
    """S_i of a contacted taxel per docs/scene-format.md: m F + c for a tangential-calibrated
    taxel when the object applies a tangential force (eq 23), else the taxel's signal_mv."""
    if taxel.slope is not None and taxel.slope != 0.0 and obj.tangential_force:
        return float(taxel.slope * obj.tangential_force + (taxel.intercept or 0.0))
    return float(taxel.signal_mv)


def params_from_scene(scene, method: str = "glrt", false_alarm: float | None = None,
                      rng: np.random.Generator | None = None, n_samples: int = 200_000) -> centralised.CentralisedParams:
    """:class:`CentralisedParams` of a scene, threshold at ``false_alarm`` (default: the
    scene's ``np_false_alarm``, the same system P_F the N-P fusion rule is given)."""
    patterns = scene_patterns(scene)[0]
    nominal = np.array([nominal_signal_mv(t, scene.object) for t in scene.taxels])
    if patterns.shape[0] == 0:
        patterns = nominal[None, :]
    params = centralised.make_params([t.noise_mv for t in scene.taxels], [t.noise_sigma_mv for t in scene.taxels],
                         patterns, nominal, method)
    alpha = scene.fusion.np_false_alarm if false_alarm is None else false_alarm
    tau = centralised.centralised_threshold(params, alpha, method, rng=rng, n_samples=n_samples)
    return centralised.CentralisedParams(params.noise_mv, params.sigma_mv, params.signal_patterns_mv, params.taxel_signal_mv,
                             method, tau, {"false_alarm": float(alpha)})


def count_threshold_for(rule: str, scene, **overrides) -> tuple[int, float]:
    """(min present count m, threshold in the rule's own units) of a count rule: H1 iff K >= m.

    additive: eq 17 root chosen by ``additive_root`` (U_G units); multiplicative: eq 16 (ln of
    its threshold, U_G = e^(sum u)); k-of-n: m = k (sec. 2.2.1). ``overrides`` replace fusion
    fields (alpha, beta, xi, k, additive_root). m = n + 1 ("never H1") when no count reaches
    the threshold; ParameterError when the threshold equation has no root.
    """
    f = scene.fusion
    n = scene.n
    xi = overrides.get("xi", f.xi)
    if rule == "k-of-n":
        k = int(overrides.get("k", f.k))
        return k, float(k)
    if rule == "additive":
        alpha = overrides.get("alpha", f.alpha)
        res = thresholds.additive_threshold(n, xi, alpha, f.tuple)
        values, counts = res.thresholds, res.present_counts
        what = f"eq 17 has no root for n={n}, xi={xi}, alpha={alpha}"
    elif rule == "multiplicative":
        beta = overrides.get("beta", f.beta)
        res = thresholds.multiplicative_threshold(n, xi, beta)
        values, counts = res.scaled_thresholds, res.present_counts
        what = f"eq 16 has no root for n={n}, xi={xi}, beta={beta}"
    else:
        raise ParameterError("rule", rule, f"must be one of {montecarlo.COUNT_RULES}")
    if len(values) == 0:
        raise ParameterError(rule, "threshold", what)
    idx = _root_index(values, overrides.get("additive_root", f.additive_root))
    m = counts[idx]
    if rule == "multiplicative":
        ln_thr = res.ln_thresholds[idx]
        value = float(ln_thr) if ln_thr is not None else float("-inf")
    else:
        value = float(values[idx])
    return (n + 1 if m is None else int(m)), value


def _root_index(values, which: str) -> int:
    arr = np.atleast_1d(np.asarray(values, dtype=float))
    if arr.size == 1:
        return 0
    order = np.argsort(arr)
    return int(order[0] if which == "lower" else order[-1])


def preferential_threshold_mean(scene, alpha: float | None = None) -> float:
    """lambda_Th-mean of eq 18 (curve eq 14, g(n) of eq 15) for the scene's xi, p, q, tuple."""
    f = scene.fusion
    a = f.alpha if alpha is None else alpha
    res = thresholds.preferential_threshold(scene.n, f.xi, a, f.p, f.q, f.tuple)
    if res.threshold_mean is None:
        raise ParameterError("preferential", "threshold", f"eq 18 has no root in [-g, g] for alpha={a}")
    return float(res.threshold_mean)


def declared_pd_pf(scene) -> tuple[np.ndarray, np.ndarray]:
    """The scene's declared per-taxel pd_i = 1 - pm_i and pf_i (LLR / N-P inputs)."""
    pd = np.array([1.0 - t.pm for t in scene.taxels], dtype=float)
    pf = np.array([t.pf for t in scene.taxels], dtype=float)
    return pd, pf


def setup_rules(scene, rules=None, central=True, central_samples: int = 200_000,
                rng: np.random.Generator | None = None) -> montecarlo.RuleSetup:
    """Decision parameters of the requested and supported rules (``plan_stages``)."""
    plan = plan_stages(scene)
    wanted = tuple(plan.rules_run) if rules is None else tuple(rules)
    setup = montecarlo.RuleSetup(encoding=scene.fusion.tuple, n=scene.n)
    f = scene.fusion
    for rule in wanted:
        if rule in montecarlo.CENTRAL_TESTS:
            continue
        if rule not in montecarlo.DECISION_RULES:
            raise ParameterError("rules", rule, f"must be among {montecarlo.DECISION_RULES + montecarlo.CENTRAL_TESTS}")
        why = plan.rules_skipped.get(rule) if rule not in plan.rules_run else None
        if why and not why.startswith("not requested"):
            setup.skipped[rule] = why
            continue
        if rule in montecarlo.COUNT_RULES:
            try:
                m, thr = count_threshold_for(rule, scene)
            except ParameterError as exc:
                setup.skipped[rule] = f"{rule}: {exc}"
                continue
            setup.min_present_count[rule] = m
            setup.thresholds[rule] = thr
        elif rule == "preferential":
            try:
                tm = preferential_threshold_mean(scene)
            except ParameterError as exc:
                setup.skipped[rule] = f"{rule}: {exc}"
                continue
            setup.preferential = (f.p, f.q, tm)
            setup.thresholds[rule] = tm
        elif rule == "llr":
            pd, pf = declared_pd_pf(scene)
            c00, c01, c10, c11 = f.costs
            ln_l0 = baselines.bayes_log_threshold(f.prior_h1, c00, c01, c10, c11)
            setup.llr = (pd, pf, f.prior_h1, ln_l0)
            setup.thresholds[rule] = ln_l0
        elif rule == "np":
            pd, pf = declared_pd_pf(scene)
            setup.np_rule = baselines.neyman_pearson_fusion(pd, pf, f.np_false_alarm)
            setup.thresholds[rule] = (setup.np_rule.log_threshold if setup.np_rule.log_threshold is not None
                                      else float(setup.np_rule.count_threshold))
    if central:
        why = centralised_support(scene)
        for name in montecarlo.CENTRAL_TESTS:
            if why:
                setup.skipped[name] = why
                continue
            method = name.split("_", 1)[1]
            if method == "bayes":
                known = setup.central.get("centralised_known") or params_from_scene(
                    scene, "known", rng=rng, n_samples=central_samples)
                c00, c01, c10, c11 = f.costs
                tau = baselines.bayes_log_threshold(f.prior_h1, c00, c01, c10, c11)
                params = centralised.CentralisedParams(known.noise_mv, known.sigma_mv, known.signal_patterns_mv,
                                                       known.taxel_signal_mv, "known", tau, {"bayes": True})
            else:
                params = params_from_scene(scene, method, rng=rng, n_samples=central_samples)
            setup.central[name] = params
            setup.thresholds[name] = params.threshold
    return setup


def simulate(scene, n_trials: int, rng: np.random.Generator, rules=None, *, central: bool = True,
             setup: montecarlo.RuleSetup | None = None, **kwargs) -> montecarlo.MonteCarloResult:
    """Monte Carlo of every rule's decision and the centralised raw test on ``scene``.

    ``n_trials`` trials under H0 and as many under H1 (if the scene has present cycles).
    ``rules``: subset of DECISION_RULES (+ CENTRAL_TESTS), default: those the scene runs
    (``plan_stages``). Other keyword arguments (``chunk``, ``keep``, ``progress``, ``dtype``)
    go to :func:`fusion_center.core.montecarlo.simulate_model`.
    """
    if not isinstance(n_trials, (int, np.integer)) or n_trials < 1:
        raise ParameterError("n_trials", n_trials, "must be an integer >= 1")
    if setup is None:
        want_central = central and (rules is None or any(r in montecarlo.CENTRAL_TESTS for r in rules))
        setup = setup_rules(scene, rules, central=want_central)
    zeta = np.array([t.zeta_mv for t in scene.taxels], dtype=float)
    sigma = np.array([t.noise_sigma_mv for t in scene.taxels], dtype=float)
    patterns, weights, pi1 = scene_patterns(scene)
    return montecarlo.simulate_model(setup, zeta, sigma, patterns, weights, pi1, n_trials, rng, **kwargs)
