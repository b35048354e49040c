"""Detection error against run time for every rule, on one scene (``fusion-center report``).

Answers "is decentralised decision fusion over CAN worth it against streaming raw data, for
this sensor at this bit rate, and what error does it cost?". Writes to ``--out``:

* ``report.json`` - every figure below, plus the stage plan (which stages/rules ran and why
  others did not) and the bandwidth figures;
* ``error_vs_runtime.png`` - total error (Monte Carlo, 95 % Wilson CI; the exact value for every
  decision rule: Poisson-binomial for count rules, the chain DP for the preferential rule, the
  product-of-binomials law for LLR / N-P, fusion_center.core.exact_rates, drawn down to 1e-300,
  "MC: no event" where the Monte Carlo saw none) of every rule in decision mode and of the centralised raw-data tests,
  against bus time per cycle (decision_sync resp. raw mode, ``fusion-center bandwidth``) and
  against the measured CPU time per fused decision (the per-cycle functions of
  ``fusion_center.core.rules`` / ``baselines`` / ``centralised``);
* ``roc.png`` - ROC curves and the rules' operating points;
* ``achieved_alpha.png`` - achieved P_F vs requested alpha (HEBTEM additive eq 17, preferential
  eq 18, N-P, centralised) and achieved P_M vs requested beta (multiplicative eq 16);
* ``work_precision.png`` - threshold solvers (eqs 16-18) against an mpmath reference;
* ``probability_curves.png`` - the chapter's figs 2-7 (eqs 10-14) with their thresholds;
* ``taxel_map.png`` - taxels, the active ones of a present cycle and their convex hull (eq 35);
* ``bits_vs_taxels.png`` - bits per SYNC cycle against 16..8192 taxels for every layout (one-taxel
  vs patch nodes x decisions vs raw readings x classic vs FD) with the capacity of the buses;
* ``error_vs_taxels.png`` - exact detection error of every rule against 8..4096 identical taxels
  (:mod:`.scaling` defines both).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from .. import evaluation
from ..core import baselines, centralised, curves, montecarlo, rules, thresholds
from ..core.encoding import local_decision
from taxel_net.errors import ParameterError
from ..stages import plan_stages
from . import bandwidth

DEFAULT_TRIALS = 200_000
ALPHA_GRID = (0.001, 0.003, 0.01, 0.03, 0.1, 0.2, 0.3, 0.473, 0.6)
BETA_GRID = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.83, 0.9)
PNG_FILES = ("error_vs_runtime.png", "roc.png", "achieved_alpha.png", "work_precision.png",
             "probability_curves.png", "taxel_map.png", "bits_vs_taxels.png", "error_vs_taxels.png")


# --------------------------------------------------------------------------- CPU time
def _time_per_call(fn, args_list, min_calls: int = 200) -> float:
    """Mean seconds per call of fn(*args) over args_list cycled (best of 3 passes)."""
    best = math.inf
    calls = max(min_calls, len(args_list))
    for _ in range(3):
        t0 = time.perf_counter()
        for j in range(calls):
            fn(*args_list[j % len(args_list)])
        best = min(best, (time.perf_counter() - t0) / calls)
    return best


def cpu_time_per_decision(scene, setup: montecarlo.RuleSetup, rng) -> dict[str, float]:
    """Measured seconds per fused decision with the per-cycle functions the live service uses."""
    enc = setup.encoding
    n = scene.n
    zeta = np.array([t.zeta_mv for t in scene.taxels])
    noise = np.array([t.noise_mv for t in scene.taxels])
    sigma = np.array([t.noise_sigma_mv for t in scene.taxels])
    x = noise + sigma * rng.standard_normal((64, n))
    u_list = [(local_decision(row, noise, zeta, enc),) for row in x]
    out: dict[str, float] = {}
    for rule, m in setup.min_present_count.items():
        thr = setup.thresholds[rule]
        if rule == "additive":
            out[rule] = _time_per_call(lambda u: rules.additive(u, enc) >= thr, u_list)
        elif rule == "multiplicative":
            out[rule] = _time_per_call(lambda u: rules.multiplicative(u, enc).ln_U_G >= thr, u_list)
        else:
            k = scene.fusion.k
            out[rule] = _time_per_call(lambda u: rules.k_of_n(u, k, enc) == 1, u_list)
    if setup.preferential is not None:
        p, q, tm = setup.preferential
        out["preferential"] = _time_per_call(lambda u: rules.preferential(u, p, q, enc) >= tm, u_list)
    if setup.llr is not None:
        pd, pf, prior, ln_l0 = setup.llr
        out["llr"] = _time_per_call(lambda u: baselines.chair_varshney_llr(u, pd, pf, enc, prior) > ln_l0, u_list)
    if setup.np_rule is not None:
        rule_np = setup.np_rule
        out["np"] = _time_per_call(lambda u: rule_np.decide(u, enc, rng), u_list)
    x_list = [(row,) for row in x]
    for name, params in setup.central.items():
        out[name] = _time_per_call(lambda xr: centralised.centralised_llr(xr, params) > params.threshold, x_list)
    return out


# --------------------------------------------------------------------------- achieved levels
def achieved_levels(scene, mc: montecarlo.MonteCarloResult, rng) -> dict:
    """Achieved P_F per requested alpha (and P_M per beta) - exact for count rules."""
    setup = mc.setup
    out: dict[str, dict] = {}
    n0 = mc.statistics_h0["present_count"].size
    if "additive" in setup.min_present_count:
        req, ach = [], []
        for a in ALPHA_GRID:
            try:
                m, _ = evaluation.count_threshold_for("additive", scene, alpha=a)
            except ParameterError:
                continue
            req.append(a)
            ach.append(montecarlo.exact_count_rates(m, mc.taxel_pf, mc.taxel_pd_patterns, mc.pattern_weights)[1])
        out["additive"] = {"requested": req, "achieved": ach, "source": "exact Poisson-binomial"}
    if "multiplicative" in setup.min_present_count and mc.taxel_pd_patterns.shape[0]:
        req, ach = [], []
        for b in BETA_GRID:
            try:
                m, _ = evaluation.count_threshold_for("multiplicative", scene, beta=b)
            except ParameterError:
                continue
            pd, _ = montecarlo.exact_count_rates(m, mc.taxel_pf, mc.taxel_pd_patterns, mc.pattern_weights)
            req.append(b)
            ach.append(1.0 - pd)
        out["multiplicative"] = {"requested": req, "achieved": ach, "source": "exact Poisson-binomial (P_M)"}
    if setup.preferential is not None and "preferential" in mc.statistics_h0:
        from ..core import exact_rates

        p, q, _ = setup.preferential
        req, ach, log10 = [], [], []
        stat = mc.statistics_h0["preferential"]
        exact = (exact_rates._lattice(p, q, setup.encoding) is not None
                 or scene.n <= exact_rates.exact_counts_max_taxels(p, q))
        for a in ALPHA_GRID:
            try:
                tm = evaluation.preferential_threshold_mean(scene, alpha=a)
            except ParameterError:
                continue
            req.append(a)
            if exact:  # U_G >= lambda_mean under H0, by the DP over the chain
                r = exact_rates.preferential_error_rates(mc.taxel_pf, mc.taxel_pf, p, q, setup.encoding, tm, tm)
                ach.append(r.p_false_alarm)
                log10.append(None if r.log_p_false_alarm is None else r.log_p_false_alarm / math.log(10.0))
            else:
                ach.append(float(np.mean(stat >= tm)))
        out["preferential"] = {"requested": req, "achieved": ach,
                               "source": "exact (DP over the chain)" if exact else f"MC, {n0} H0 trials"}
        if exact:
            out["preferential"]["log10_achieved"] = log10
    if setup.np_rule is not None:
        pd_dec, pf_dec = evaluation.declared_pd_pf(scene)
        req, ach = [], []
        np_by_mc = False
        for a in ALPHA_GRID:
            r = baselines.neyman_pearson_fusion(pd_dec, pf_dec, a)
            if r.statistic == "present_count":
                ach.append(montecarlo._exact_randomised_count(r, mc.taxel_pf, mc.taxel_pd_patterns, mc.pattern_weights)[1])
            else:
                from ..core import exact_rates

                a_ = np.log(r.pd) - np.log(r.pf)
                b_ = np.log1p(-r.pd) - np.log1p(-r.pf)
                value = exact_rates.linear_statistic_tail(a_, b_, mc.taxel_pf, r.log_threshold, r.gamma,
                                                          tol=baselines.LLR_TIE_TOLERANCE)
                if value is None:
                    np_by_mc = True
                    s_ = mc.statistics_h0["np"]
                    value = float(np.mean(s_ > r.log_threshold) + r.gamma * np.mean(np.isclose(s_, r.log_threshold)))
                ach.append(value)
            req.append(a)
        src = ("exact Poisson-binomial" if setup.np_rule.statistic == "present_count"
               else f"MC, {n0} H0 trials" if np_by_mc else "exact (kinds of equal declared rates)")
        out["np"] = {"requested": req, "achieved": ach, "source": src}
    if "centralised_glrt" in setup.central and "centralised_glrt" in mc.statistics_h0:
        params = setup.central["centralised_glrt"]
        stat = mc.statistics_h0["centralised_glrt"]
        req, ach = [], []
        for a in ALPHA_GRID:
            if a * 50_000 < 20:
                continue
            tau = centralised.centralised_threshold(params, a, rng=rng, n_samples=50_000)
            req.append(a)
            ach.append(float(np.mean(stat > tau)))
        out["centralised_glrt"] = {"requested": req, "achieved": ach,
                                   "source": f"threshold from 5e4 H0 draws, checked on {n0} independent ones"}
    return out


# --------------------------------------------------------------------------- exact ROC curves
def exact_rocs(setup: montecarlo.RuleSetup, mc: montecarlo.MonteCarloResult) -> dict:
    """Exact ROC curves of the statistics beyond the present count: the preferential U_G (eq 7,
    its law by the lattice DP of exact_rates) and the eq 31/32 log-likelihood ratio with the
    declared pd/pf (kinds of equal declared rates, a Poisson-binomial count per kind), under H0
    and the H1 patterns of the scene (mixed by their weights). Keys ``<rule>_exact``; a rule
    whose law is out of exact reach is left out (its Monte Carlo curve stays)."""
    from ..core import exact_rates

    out = {}
    rows, weights = mc.taxel_pd_patterns, mc.pattern_weights
    if setup.preferential is not None:
        p, q, _ = setup.preferential
        law0 = exact_rates.preferential_law(mc.taxel_pf, p, q, setup.encoding)
        laws1 = [exact_rates.preferential_law(row, p, q, setup.encoding) for row in rows] if law0 is not None else []
        if law0 is not None and all(law is not None for law in laws1):
            out["preferential_exact"] = exact_rates.roc_from_laws(law0, laws1, weights)
    stats = []
    if setup.llr is not None:
        pd, pf = setup.llr[0], setup.llr[1]
        stats.append(("llr_exact", pd, pf))
    if setup.np_rule is not None and setup.np_rule.statistic == "llr":
        stats.append(("np_exact", setup.np_rule.pd, setup.np_rule.pf))
    for key, pd, pf in stats:
        a = np.log(pd) - np.log(pf)
        b = np.log1p(-np.asarray(pd)) - np.log1p(-np.asarray(pf))
        law0 = exact_rates.linear_statistic_law(a, b, mc.taxel_pf)
        laws1 = [exact_rates.linear_statistic_law(a, b, row) for row in rows] if law0 is not None else []
        if law0 is not None and all(law is not None for law in laws1):
            out[key] = exact_rates.roc_from_laws(law0, laws1, weights)
    return out


# --------------------------------------------------------------------------- work-precision
def work_precision_rows(sizes=(10, 57, 200)) -> list[dict]:
    """Time per solve and relative error of the threshold solvers (eqs 16, 17 pm1, 18 with
    p = q = 1) against the mpmath references of :mod:`fusion_center.report.reference`, started at our
    solution."""
    from . import reference

    rows_out = []
    xi = 0.003
    for n in sizes:
        for kind, solve, extract, ref_of in (
            ("additive_pm1", lambda n_: thresholds.additive_threshold(n_, xi, 0.03, "pm1"),
             lambda r: r.thresholds[0] if r.thresholds else None,
             lambda v: reference.ref_additive(n, xi, 0.03, [v], "pm1")[0]),
            ("multiplicative", lambda n_: thresholds.multiplicative_threshold(n_, xi, 0.83),
             lambda r: r.scaled_thresholds[0] if r.scaled_thresholds else None,
             lambda v: reference.ref_multiplicative(n, xi, 0.83, v)[0]),
            ("preferential", lambda n_: thresholds.preferential_threshold(n_, xi, 0.48, 1.0, 1.0),
             lambda r: r.threshold_mean,
             lambda v: reference.ref_preferential(n, xi, 0.48, rules.g_of_n(n, 1.0, 1.0), v)[0]),
        ):
            value = extract(solve(n))
            if value is None:
                continue
            t = _time_per_call(solve, [(n,)], min_calls=200)
            ref = ref_of(value)
            rel = abs((value - ref) / ref) if ref != 0 else abs(value)
            rows_out.append({"solver": kind, "n": n, "time_us": 1e6 * t, "relative_error": rel,
                             "value": value, "reference": ref})
    return rows_out


# --------------------------------------------------------------------------- P(H1) curves
def probability_curve_data(n: int, xi: float, alpha: float, beta: float, pref_alpha: float) -> dict:
    """Figs 2-7: the curves of eqs 10-14 with the HEBTEM thresholds of eqs 16-18, 20."""
    out = {}
    ln_u = np.linspace(-n, n, 401)
    mt = thresholds.multiplicative_threshold(n, xi, beta)
    ths = [{"x": v, "label": f"ln λ = {v:.2f} (β={beta})"} for v in mt.ln_thresholds if v is not None]
    out["fig 2a/7a: multiplicative, {-1,+1} (eqs 10-11, 16)"] = {
        "lines": [{"x": ln_u.tolist(), "y": np.asarray(curves.p_multiplicative(ln_u, n, xi)).tolist()}],
        "thresholds": ths, "xlabel": "ln U_G = sum u_i"}
    # {0,1}: U_G = e^(n-k) in [1, e^n]; two-point exponential fit through (e^0, xi) and (e^n, 1)
    # in t = U_G / e^n: p = exp(-L (1 - t) / (1 - e^-n)), the {0,1} analogue of eqs 10-11
    ln_u01 = np.linspace(0, n, 401)
    t = np.exp(ln_u01 - n)
    p01 = np.exp(math.log(xi) * (1 - t) / -math.expm1(-n))
    out["fig 2b: multiplicative, {0,1}"] = {"lines": [{"x": ln_u01.tolist(), "y": p01.tolist()}],
                                            "xlabel": "ln U_G = sum u_i (01)"}
    u01 = np.linspace(0, n, 401)
    at01 = thresholds.additive_threshold(n, xi, alpha, "01")
    out["fig 3: additive, {0,1} (eqs 12, 17)"] = {
        "lines": [{"x": u01.tolist(), "y": np.asarray(curves.p_additive_01(u01, n, xi)).tolist()}],
        "thresholds": [{"x": v, "label": f"λ = {v:.2f} (α={alpha})"} for v in at01.thresholds], "xlabel": "U_G"}
    upm = np.linspace(-n, n, 401)
    atpm = thresholds.additive_threshold(n, xi, alpha, "pm1")
    out["fig 4/7b: additive, {-1,+1} (eqs 13, 17)"] = {
        "lines": [{"x": upm.tolist(), "y": np.asarray(curves.p_additive_pm1(upm, n, xi)).tolist()}],
        "thresholds": [{"x": v, "label": f"λ = {v:.2f} (α={alpha})"} for v in atpm.thresholds], "xlabel": "U_G"}
    lines, ths, bands = [], [], []
    gmax = 0.0
    for p_w, q_w in ((0.0, 1.0), (1.0, 1.0), (1.0, 2.0), (2.0, 2.0)):
        g = rules.g_of_n(n, p_w, q_w)
        gmax = max(gmax, g)
        ug = np.linspace(-g, g, 301)
        lines.append({"x": ug.tolist(), "y": np.asarray(curves.p_preferential(ug, g, xi)).tolist(),
                      "label": f"(p,q)=({p_w:g},{q_w:g}), g(n)={g:g}"})
        pt = thresholds.preferential_threshold(n, xi, pref_alpha, p_w, q_w)
        if pt.threshold_mean is not None:
            ths.append({"x": pt.threshold_mean, "label": f"λ_mean={pt.threshold_mean:.1f}", "color": "C%d" % (len(ths))})
            bands.append([pt.threshold_initial, pt.threshold_final])
    out[f"figs 5-6: preferential (eqs 14-15, 18-20), α={pref_alpha}"] = {
        "lines": lines, "thresholds": ths, "bands": bands, "xlabel": "U_G (eq 7)"}
    return out


# --------------------------------------------------------------------------- main
def build_report(scene, out_dir: Path, trials: int, seed: int, bitrate=None,
                 progress=None) -> dict:
    """Compute everything, write report.json and the PNGs into ``out_dir``; return the JSON.

    ``bitrate``: None (the scene's), one bit rate or a list of them; the first one is the
    report's ``bandwidth``, all of them are in ``bandwidth_by_bitrate`` and on the
    error-vs-bus-time plot."""
    from . import plots

    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 100:
        raise ParameterError("trials", trials, "must be an integer >= 100")
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    step = progress or (lambda what, frac=None: None)

    plan = plan_stages(scene)
    step("stage plan, rule thresholds")
    setup = evaluation.setup_rules(scene, central=True, rng=np.random.default_rng([seed, 1]))
    step("bandwidth")
    if bitrate is None:
        bitrates = [scene.bus.bitrate]
    elif isinstance(bitrate, (list, tuple)):
        bitrates = list(dict.fromkeys(bitrate))
    else:
        bitrates = [bitrate]
    if not bitrates:
        raise ParameterError("bitrate", bitrate, "at least one bit rate")
    inputs = bandwidth.simulate_bus_inputs(scene, scene.cycles)
    bw_by = {b: bandwidth.bandwidth_figures(scene, b, inputs=inputs) for b in bitrates}
    bw = bw_by[bitrates[0]]
    step("Monte Carlo", 0.0)
    mc = evaluation.simulate(scene, trials, rng, setup=setup,
                             progress=lambda d, t: step("Monte Carlo", d / t))
    step("CPU time per decision")
    cpu = cpu_time_per_decision(scene, setup, np.random.default_rng([seed, 2]))

    points = []
    for name, res in mc.rules.items():
        mode = "raw" if name in montecarlo.CENTRAL_TESTS else "decision_sync"
        points.append({
            "rule": name, "mode": mode,
            "bus_time_per_cycle_ms": bw["modes"][mode]["bus_time_per_cycle_ms"],
            "bus_load": bw["modes"][mode]["bus_load"],
            "bus_time_per_cycle_ms_by_bitrate": {str(b): f["modes"][mode]["bus_time_per_cycle_ms"]
                                                 for b, f in bw_by.items()},
            "cpu_time_per_decision_us": 1e6 * cpu[name],
            "total_error": res.total_error,
            "pd": None if res.pd is None else res.pd.to_dict(),
            "pf": res.pf.to_dict(),
        })

    step("ROC and achieved error levels")
    roc = {}
    if mc.taxel_pd_patterns.shape[0]:
        roc["count_exact"] = montecarlo.exact_count_roc(mc.taxel_pf, mc.taxel_pd_patterns, mc.pattern_weights)
        roc.update(exact_rocs(setup, mc))
        for key in ("preferential", "llr", "np", "centralised_known", "centralised_glrt"):  # bayes: same ROC as known
            if key in mc.statistics_h0 and key in mc.statistics_h1:
                roc[key] = montecarlo.empirical_roc(mc.statistics_h0[key], mc.statistics_h1[key])
                roc[key]["method"] = f"Monte Carlo, {mc.statistics_h0[key].size} trials per hypothesis"
    for key, r in roc.items():
        if "auc" not in r:
            r["auc"] = montecarlo.area_under_roc(r["pf"], r["pd"])
    achieved = achieved_levels(scene, mc, np.random.default_rng([seed, 3]))

    step("solver work-precision (mpmath reference, 80 digits)")
    wp = work_precision_rows()
    step("P(H1) curves, taxel map")
    f = scene.fusion
    pcurves = probability_curve_data(scene.n, f.xi, f.alpha, f.beta, f.alpha)

    # taxel map: decisions of the first present cycle (canonical readings)
    from node_sim import physics

    xy = np.array([[np.nan if t.x is None else t.x, np.nan if t.y is None else t.y] for t in scene.taxels])
    present_cycles = [c for c in range(scene.cycles) if physics.object_present(scene, c)]
    cycle = present_cycles[len(present_cycles) // 2] if present_cycles else 0
    xr = physics.sample_readings(scene, cycle)
    active = local_decision(xr, [t.noise_mv for t in scene.taxels], [t.zeta_mv for t in scene.taxels], "pm1") == 1
    hull = None
    has_xy = bool(np.all(np.isfinite(xy)))
    if has_xy and active.any():
        from ..core.geometry import convex_hull

        hull = convex_hull(xy[active])
    floor = 0.5 / trials
    step("scale: layouts and rules against the number of taxels")
    from . import scaling

    scale = scaling.scale_figures(scene, bitrates)

    data = {
        "scene": scene.name,
        "scene_path": str(scene.path),
        "taxels": scene.n,
        "trials_per_hypothesis": trials,
        "seed": seed,
        "stage_plan": plan.to_dict(),
        # what did not run and why (the Monte Carlo runs the centralised tests in any bus mode)
        "stages_skipped": dict(plan.skipped),
        "rules_skipped": {**plan.rules_skipped, **mc.skipped},
        "prior_h1": mc.prior_h1,
        "rules": {k: v.to_dict() for k, v in mc.rules.items()},
        "thresholds": {k: (None if v is None or not math.isfinite(v) else v) for k, v in setup.thresholds.items()},
        "skipped": mc.skipped,
        "bandwidth": bw,
        "bandwidth_by_bitrate": {str(b): f for b, f in bw_by.items()},
        "cpu_time_per_decision_s": cpu,
        "error_vs_runtime": points,
        # rules whose Monte Carlo saw no error event (its 0 is a bound; the exact value is given)
        "mc_no_event": {name: [what for what, none in (("false alarm", v.pf.successes == 0),
                                                       ("miss", v.pd is not None and v.pd.successes == v.pd.trials))
                               if none]
                        for name, v in mc.rules.items()
                        if v.pf.successes == 0 or (v.pd is not None and v.pd.successes == v.pd.trials)},
        "roc": roc,
        "achieved_vs_requested": achieved,
        "work_precision": wp,
        "taxel_map": {"cycle": cycle, "active_taxels": [scene.taxels[i].node_id for i in np.flatnonzero(active)],
                      "hull": None if hull is None else np.asarray(hull).tolist(),
                      "has_coordinates": has_xy},
        "taxel_decisions_simulated": mc.taxel_decisions,
        "scale": scale,
        "files": ["report.json", *PNG_FILES],
    }
    step("plots")
    plots.error_vs_runtime(points, floor, out_dir / "error_vs_runtime.png", bitrates)
    plots.roc_curves(roc, {k: (v.pf.estimate, None if v.pd is None else v.pd.estimate,
                               (v.pf.exact, None if v.pd is None else v.pd.exact)) for k, v in mc.rules.items()},
                            out_dir / "roc.png", trials=trials)
    plots.achieved_vs_requested(achieved, out_dir / "achieved_alpha.png")
    plots.work_precision(wp, out_dir / "work_precision.png")
    plots.probability_curves(pcurves, out_dir / "probability_curves.png")
    title = f"{scene.name}: cycle {cycle}, {int(active.sum())} of {scene.n} taxels active"
    if not has_xy:
        xy_plot = np.column_stack([np.arange(scene.n, dtype=float), np.zeros(scene.n)])
        title += " (no coordinates: taxels in fusion order)"
    else:
        xy_plot = xy
    plots.taxel_map(xy_plot, active, hull, title, out_dir / "taxel_map.png",
                    node_ids=[t.node_id for t in scene.taxels],
                    unit="fusion index" if not has_xy else "layout units (scene CSV)")
    plots.bits_vs_taxels(scale["layouts"], out_dir / "bits_vs_taxels.png", bitrates)
    plots.error_vs_taxels(scale["rules"], out_dir / "error_vs_taxels.png", scene_n=scene.n, caption=scale["caption"])
    (out_dir / "report.json").write_text(json.dumps(data, indent=1, default=_json_default))
    return data


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)
