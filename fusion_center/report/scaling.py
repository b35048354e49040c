"""How the bus and the rules scale with the number of taxels (``fusion-center report``, issue 14).

Two families of curves for the report's scale plots, both exact (no Monte Carlo):

* :func:`layout_bits_vs_taxels` - bits per SYNC cycle of every layout (one-taxel vs patch
  nodes x packed decisions vs raw readings x classic CAN vs CAN FD, ``core.layouts``) for
  16..8192 taxels, summed over the channels each layout needs (<= 127 nodes per channel), with
  the capacity of one bus per SYNC period at each bit rate. CAN FD's data phase runs faster than
  its nominal phase, so FD curves are drawn in **nominal bit times**: nominal bits + data-phase
  bits x f_nominal / f_data (= bus time per cycle x f_nominal; for classic CAN the exact bits),
  which makes one limit line per nominal bit rate valid for both.
* :func:`rule_error_vs_taxels` - the detection error of every decision rule against the
  number of taxels n for identical taxels (the scene's R taxel, or its first kind with
  declared pf/pm): H0 all n taxels at pf; H1 a contact covering ``contact`` taxels (taxels
  0..contact-1 of the fusion order, each present with pd = 1 - pm; the others at pf) - the
  same object on a growing skin - or, with ``fraction``, ceil(fraction x n) taxels. Every rule
  with its own threshold for that n (HEBTEM eqs 16-18 at the scene's xi, alpha, beta, p, q;
  k-of-n with the scene's k; Chair-Varshney eq 31 with the declared pd/pf, the scene's prior
  and costs; N-P eq 32 at the scene's P_F target), its exact P_F and P_M from
  ``fusion_center.core``: count rules (additive, multiplicative, k-of-n: "H1 iff K >= m") by
  the Poisson-binomial law of the present count K (``poisson_binomial.log_pmf``, once per n and
  hypothesis), the preferential rule by the DP over the chain
  (``exact_rates.preferential_error_rates``), LLR by ``exact_rates.linear_statistic_tail``, N-P
  by its randomised count boundary. Error = Bayes error at prior 0.5: (P_F + P_M) / 2 - 0.5 is
  a rule that answers the same whatever the truth (100 of 200 cycles right in a scene present
  half the time).
"""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

import numpy as np

from taxel_net.errors import ParameterError

LAYOUT_SIZES = (16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192)
RULES = ("additive", "multiplicative", "preferential", "k-of-n", "llr", "np")
DEFAULT_R_TAXEL = {"pf": 0.0013, "pm": 0.0047}     # the matrix57 R kind (scenes/matrix57.toml)


def rule_sizes(n_scene: int | None = None, low: int = 8, high: int = 4096, points: int = 13) -> list[int]:
    """n = low..high log-spaced (and the scene's own n)."""
    sizes = {int(round(x)) for x in np.geomspace(low, high, points)}
    if n_scene is not None and low <= n_scene <= high:
        sizes.add(int(n_scene))
    return sorted(sizes)


def layout_bits_vs_taxels(*, nominal_bitrate: float, data_bitrate: float, sync_period_ms: float, patch: int = 192,
                          raw: str = "raw8", sizes=LAYOUT_SIZES, p_one: float = 0.5) -> dict:
    """Mean and worst-case bits per SYNC cycle over all channels, in nominal bit times (module
    docstring), of every layout for every size; ``limits``: bits one bus carries per SYNC
    period at the nominal bit rate."""
    from ..core.layouts import layout_bus_use, skin_layout

    curves = {}
    for per_node, name in ((1, "per-taxel"), (patch, f"patch{patch}")):
        for payload in ("decision", raw):
            for fd in (False, True):
                key = f"{name} {payload} {'FD' if fd else 'classic'}"
                rows = []
                for n in sizes:
                    lay = skin_layout(int(n), taxels_per_node=per_node, payload=payload, fd=fd)
                    use = layout_bus_use(lay, nominal_bitrate=nominal_bitrate,
                                         data_bitrate=data_bitrate if fd else None,
                                         sync_period_s=sync_period_ms / 1000.0, p_one=p_one)
                    rows.append({"taxels": int(n), "channels": len(lay.channels), "frames": lay.n_frames,
                                 "bits": use.mean_bits, "bits_worst": use.worst_bits,
                                 "nominal_bit_times": use.mean_cycle_s * nominal_bitrate,
                                 "nominal_bit_times_worst": sum(c.worst_cycle_s for c in use.channels) * nominal_bitrate})
                curves[key] = {"taxels_per_node": per_node, "payload": payload, "fd": fd, "points": rows}
    return {"nominal_bitrate": nominal_bitrate, "data_bitrate": data_bitrate, "sync_period_ms": sync_period_ms,
            "bus_capacity_bits_per_period": nominal_bitrate * sync_period_ms / 1000.0, "curves": curves}


def scene_taxel_rates(scene) -> dict:
    """Declared pf, pm of the scene's R taxels (else its first taxel with both), or the default
    R taxel; the contact size of its H1 patterns (most frequent pattern: taxels with signal)."""
    from ..evaluation import scene_patterns

    rated = [t for t in scene.taxels if t.pf is not None and t.pm is not None]
    pick = next((t for t in rated if t.kind == "R"), rated[0] if rated else None)
    rates = dict(DEFAULT_R_TAXEL, kind="R (default)") if pick is None else {"pf": pick.pf, "pm": pick.pm,
                                                                           "kind": pick.kind}
    patterns, weights, _ = scene_patterns(scene)
    contact = int(np.count_nonzero(patterns[int(np.argmax(weights))] > 0)) if len(weights) else None
    return {**rates, "contact": contact}


def _bayes(pf: float | None, pm: float | None) -> float | None:
    if pf is None or pm is None:
        return None
    return 0.5 * (min(max(pf, 0.0), 1.0) + min(max(pm, 0.0), 1.0))


def rule_error_vs_taxels(fusion, *, pf: float, pm: float, contact: int | None = None, fraction: float | None = None,
                         sizes=None, rules=RULES, time_budget_s: float = 60.0, h0_cache: dict | None = None) -> dict:
    """Exact P_F, P_M and Bayes error (prior 0.5) of every rule for identical taxels, per n
    (module docstring). ``fusion``: a scene's ``FusionSpec`` (thresholds, k, prior, costs, P_F
    target). A rule whose rates for one n take longer than ``time_budget_s`` in total stops
    there (``stopped_at``); a rule without a threshold at some n (no root of its equation) gets
    ``None`` there, with the reason in ``notes``. ``h0_cache``: a dict shared by several calls
    (``scale_figures``: both H1 models) keeps what depends on H0 alone - the count law, the
    LLR's P_F, the N-P rule - keyed by n and every other input, so each is computed once."""
    from ..core import baselines, exact_rates, montecarlo, poisson_binomial
    from .. import evaluation

    def tail(logs) -> float:
        return float(np.exp(np.logaddexp.reduce(logs))) if len(logs) else 0.0

    if (contact is None) == (fraction is None):
        raise ParameterError("contact/fraction", (contact, fraction), "give exactly one of them")
    sizes = rule_sizes() if sizes is None else list(sizes)
    pd = 1.0 - pm
    h0_cache = {} if h0_cache is None else h0_cache

    def h0_only(key: tuple, compute):
        """compute(), once per key: every input of the H0-only value (``h0_cache``)."""
        if key not in h0_cache:
            h0_cache[key] = compute()
        return h0_cache[key]

    out = {r: {"taxels": [], "p_false_alarm": [], "p_miss": [], "error": [], "seconds": 0.0, "notes": {}}
           for r in rules}
    for n in sizes:
        c = min(n, contact) if contact is not None else min(n, max(1, math.ceil(fraction * n)))
        h0 = np.full(n, pf)
        h1 = np.concatenate([np.full(c, pd), np.full(n - c, pf)])
        view = SimpleNamespace(n=n, fusion=fusion)
        declared_pd = np.full(n, pd)
        laws = None
        for rule in rules:
            rec = out[rule]
            if rec.get("stopped_at") is not None:
                continue
            t0 = time.perf_counter()
            pf_n = pm_n = None
            try:
                if rule in ("additive", "multiplicative", "k-of-n"):
                    if rule == "k-of-n" and fusion.k > n:
                        raise ParameterError("k", fusion.k, f"exceeds n={n}")
                    m, _ = evaluation.count_threshold_for(rule, view)
                    if laws is None:
                        laws = (h0_only(("law", n, pf), lambda: poisson_binomial.log_pmf(h0)),
                                poisson_binomial.log_pmf(h1))
                    pf_n, pm_n = tail(laws[0][m:]), tail(laws[1][:m])
                elif rule == "preferential":
                    tm = evaluation.preferential_threshold_mean(view)
                    r = exact_rates.preferential_error_rates(h1, h0, fusion.p, fusion.q, fusion.tuple, tm, tm)
                    pf_n, pm_n = r.p_false_alarm, 1.0 - r.p_detect
                elif rule == "llr":
                    c00, c01, c10, c11 = fusion.costs
                    ln_l0 = baselines.bayes_log_threshold(fusion.prior_h1, c00, c01, c10, c11)
                    shift = math.log(fusion.prior_h1) - math.log1p(-fusion.prior_h1)
                    a = np.log(declared_pd) - np.log(h0)
                    b = np.log1p(-declared_pd) - np.log1p(-h0)
                    d1 = exact_rates.linear_statistic_tail(a, b, h1, ln_l0 - shift, tol=0.0)
                    f0 = h0_only(("llr f0", n, pf, pd, ln_l0 - shift),
                                 lambda: exact_rates.linear_statistic_tail(a, b, h0, ln_l0 - shift, tol=0.0))
                    if d1 is not None and f0 is not None:
                        pf_n, pm_n = f0, 1.0 - d1
                else:
                    np_rule = h0_only(("np rule", n, pf, pd, fusion.np_false_alarm),
                                      lambda: baselines.neyman_pearson_fusion(declared_pd, h0, fusion.np_false_alarm))
                    d1, f0 = montecarlo._exact_randomised_count(np_rule, h0, h1[None, :], np.array([1.0]))
                    pf_n, pm_n = f0, 1.0 - d1
            except ParameterError as exc:
                rec["notes"][str(n)] = str(exc)
            rec["seconds"] += time.perf_counter() - t0
            rec["taxels"].append(n)
            rec["p_false_alarm"].append(pf_n)
            rec["p_miss"].append(pm_n)
            rec["error"].append(_bayes(pf_n, pm_n))
            if rec["seconds"] > time_budget_s:
                rec["stopped_at"] = n
    return {"pf": pf, "pm": pm, "contact": contact, "fraction": fraction, "sizes": sizes, "rules": out,
            "error": "Bayes error at prior 0.5: (P_F + P_M) / 2"}


DEFAULT_CONTACT = 6                     # matrix57's 6-taxel object, for a scene without a present cycle


def scale_figures(scene, bitrates, data_bitrate: int = 5_000_000, patch: int = 192) -> dict:
    """The report's two scale figures for ``scene`` (JSON-ready): ``layouts`` at the first bit
    rate, and ``rules`` for a contact of the scene's size (``fixed_contact``) and for a contact
    covering the scene's share of its taxels (``growing_contact``)."""
    rates = scene_taxel_rates(scene)
    contact = rates["contact"] or DEFAULT_CONTACT
    share = min(1.0, contact / scene.n)
    sizes = rule_sizes(scene.n)
    h0_cache: dict = {}     # H0 is the same for both H1 models
    fixed = rule_error_vs_taxels(scene.fusion, pf=rates["pf"], pm=rates["pm"], contact=contact, sizes=sizes,
                                 h0_cache=h0_cache)
    growing = rule_error_vs_taxels(scene.fusion, pf=rates["pf"], pm=rates["pm"], fraction=share, sizes=sizes,
                                   h0_cache=h0_cache)
    f = scene.fusion
    stopped = [f"{r} (up to n = {v['stopped_at']})" for p in (fixed, growing) for r, v in p["rules"].items()
               if v.get("stopped_at") is not None]
    caption = (f"Identical taxels: pf = {rates['pf']:g}, pm = {rates['pm']:g} (kind {rates['kind']}); H0: no contact; H1: "
               f"the contacted taxels report present with 1 - pm, the others with pf. Thresholds per n: xi = {f.xi:g}, "
               f"alpha = {f.alpha:g} (eqs 17, 18, {f.additive_root} root), beta = {f.beta:g} (eq 16), p = {f.p:g}, "
               f"q = {f.q:g}, k = {f.k}, LLR prior {f.prior_h1:g}, N-P P_F {f.np_false_alarm:g}; tuple {f.tuple}.\n"
               f"Exact rates at every n = {sizes[0]}..{sizes[-1]} ({len(sizes)} values): Poisson-binomial (count rules, "
               "N-P's randomised count), chain DP (preferential), kinds of equal rates (LLR)"
               + (f"; stopped early: {', '.join(stopped)}" if stopped else "; no rule stopped early") + ".")
    return {
        "layouts": layout_bits_vs_taxels(nominal_bitrate=int(bitrates[0]), data_bitrate=data_bitrate,
                                         sync_period_ms=scene.bus.sync_period_ms, patch=patch),
        "taxel_rates": rates,
        "rules": [dict(fixed, title=f"a contact of {contact} taxels on a skin of n (the scene's object"
                                    f"{'' if rates['contact'] else ': none, default'})"),
                  dict(growing, title=f"a contact covering {100 * share:.0f} % of the skin (ceil({share:.3g} n) taxels, "
                                      "the scene's share)")],
        "caption": caption,
    }
