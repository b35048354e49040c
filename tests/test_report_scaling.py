"""The report's scale curves (fusion_center.report.scaling) against brute force and hand sums.

Rule errors: for a few small n every one of the 2^n decision vectors is enumerated, each rule
applied with the per-cycle functions of fusion_center.core (rules, baselines) and its own
threshold for that n, and P_F, P_M summed exactly - independent of the Poisson-binomial, chain
DP and kinds laws the curves use. Layout bits: summed frame by frame with the independent
encoder of test_bandwidth.py and fd_frame_bits.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from fusion_center.core import baselines, rules, thresholds
from fusion_center.core.bus_timing import fd_frame_bits
from fusion_center.report import scaling
from taxel_net.scene import FusionSpec
from test_bandwidth import reference_frame_bits

PF, PM = 0.05, 0.1          # large enough that every rule's errors are far from 0 at small n


def brute_force(fusion, n: int, contact: int):
    """{rule: (P_F, P_M)} over every decision vector (pm1 tuple)."""
    pd = 1 - PM
    h1 = [pd] * contact + [PF] * (n - contact)
    add = thresholds.additive_threshold(n, fusion.xi, fusion.alpha, "pm1")
    lam_add = min(add.thresholds) if add.thresholds else math.inf        # the lower root
    mult = thresholds.multiplicative_threshold(n, fusion.xi, fusion.beta)
    ln_mult = min(v for v in mult.ln_thresholds if v is not None) if mult.ln_thresholds else -math.inf
    pref = thresholds.preferential_threshold(n, fusion.xi, fusion.alpha, fusion.p, fusion.q, "pm1").threshold_mean
    ln_l0 = baselines.bayes_log_threshold(0.5, 0, 1, 1, 0)
    np_rule = baselines.neyman_pearson_fusion(np.full(n, pd), np.full(n, PF), fusion.np_false_alarm)
    out = {r: [0.0, 0.0] for r in scaling.RULES}
    for bits in itertools.product((0, 1), repeat=n):
        u = np.array([1 if b else -1 for b in bits])
        p0 = math.prod(PF if b else 1 - PF for b in bits)
        p1 = math.prod(q if b else 1 - q for b, q in zip(bits, h1))
        says = {
            "additive": float(rules.additive(u, "pm1") >= lam_add),
            "multiplicative": float(rules.multiplicative(u, "pm1").ln_U_G >= ln_mult),
            "preferential": float(rules.preferential(u, fusion.p, fusion.q, "pm1") >= pref),
            "k-of-n": float(rules.k_of_n(u, fusion.k, "pm1") == 1),
            "llr": float(baselines.chair_varshney_llr(u, np.full(n, pd), np.full(n, PF), "pm1", 0.5) > ln_l0),
        }
        d = np_rule.decide(u, "pm1")
        says["np"] = {"H1": 1.0, "H0": 0.0}.get(d, np_rule.gamma)
        for r, h in says.items():
            out[r][0] += p0 * h
            out[r][1] += p1 * (1 - h)
    return out


@pytest.mark.parametrize("n, contact", [(6, 6), (9, 3), (11, 2)])
def test_rule_errors_equal_brute_force(n, contact):
    fusion = FusionSpec(rules=scaling.RULES, alpha=0.3, beta=0.5, k=2, np_false_alarm=0.01, xi=0.003)
    got = scaling.rule_error_vs_taxels(fusion, pf=PF, pm=PM, contact=contact, sizes=[n])
    want = brute_force(fusion, n, contact)
    for rule in scaling.RULES:
        rec = got["rules"][rule]
        assert rec["taxels"] == [n]
        assert rec["p_false_alarm"][0] == pytest.approx(want[rule][0], rel=1e-9, abs=1e-15), rule
        assert rec["p_miss"][0] == pytest.approx(want[rule][1], rel=1e-9, abs=1e-15), rule
        assert rec["error"][0] == pytest.approx(0.5 * sum(want[rule]), rel=1e-9, abs=1e-15), rule


def test_growing_contact_and_the_scene_claim():
    # the issue: 200 one-taxel nodes, a 32-taxel contact (two_buses_200): HEBTEM's additive rule
    # at alpha = 0.03 never says "present" (error 0.5: right in 100 of 200 cycles), k-of-n
    # (k = 4) and N-P (P_F 1e-3) are nearly always right; k-of-n loses as n grows (P_F -> 1)
    fusion = FusionSpec(rules=scaling.RULES, k=4)
    res = scaling.rule_error_vs_taxels(fusion, pf=0.0013, pm=0.0047, contact=32, sizes=[200, 4096])
    err = {r: v["error"] for r, v in res["rules"].items()}
    assert err["additive"][0] == pytest.approx(0.5, abs=1e-12)
    assert err["k-of-n"][0] < 1e-3 and err["np"][0] < 1e-3
    assert err["k-of-n"][1] > 0.3                 # 4096 x 0.0013 = 5.3 false "present" on average
    # a contact covering a share of the skin: ceil(0.25 n) taxels
    res = scaling.rule_error_vs_taxels(fusion, pf=0.0013, pm=0.0047, fraction=0.25, sizes=[8, 16])
    assert res["contact"] is None and res["fraction"] == 0.25
    with pytest.raises(Exception):
        scaling.rule_error_vs_taxels(fusion, pf=0.1, pm=0.1, sizes=[8])


def test_layout_curves_by_hand():
    data = scaling.layout_bits_vs_taxels(nominal_bitrate=1_000_000, data_bitrate=4_000_000, sync_period_ms=10,
                                         sizes=(16,), patch=8)
    assert data["bus_capacity_bits_per_period"] == 10_000
    (p,) = data["curves"]["per-taxel decision classic"]["points"]
    mean = sum((reference_frame_bits(0x180 + k, b"\x00") + reference_frame_bits(0x180 + k, b"\x01")) / 2
               for k in range(1, 17)) + 51
    assert p["bits"] == pytest.approx(mean) and p["nominal_bit_times"] == pytest.approx(mean)
    # two patches of 8 decisions: one byte each on 0x181, 0x182 (all 256 values); CAN FD in nominal bit times
    (p,) = data["curves"]["patch8 decision FD"]["points"]
    phases = [[fd_frame_bits(cob, bytes([x])) for x in range(256)] for cob in (0x181, 0x182)]
    bits = sum(sum(a + b for a, b in ph) / 256 for ph in phases) + 51
    times = sum(sum(a + b / 4 for a, b in ph) / 256 for ph in phases) + 51
    worst = sum(max(a + b / 4 for a, b in ph) for ph in phases) + 51
    assert p["bits"] == pytest.approx(bits)
    assert p["nominal_bit_times"] == pytest.approx(times)
    assert p["nominal_bit_times_worst"] == pytest.approx(worst)
    assert (p["channels"], p["frames"]) == (1, 2)


def test_both_h1_models_share_what_depends_on_h0_alone(monkeypatch):
    """scale_figures' two H1 models have the same H0: with one ``h0_cache`` the second call
    computes no H0 count law, LLR P_F or N-P rule again, and every value (brute-force checked
    above) is the same as without the cache (main computed each twice)."""
    fusion = FusionSpec(rules=scaling.RULES, alpha=0.3, beta=0.5, k=2, np_false_alarm=0.01, xi=0.003)
    args = dict(pf=PF, pm=PM, sizes=[9, 11])
    alone = [scaling.rule_error_vs_taxels(fusion, contact=3, **args),
             scaling.rule_error_vs_taxels(fusion, fraction=0.5, **args)]
    calls = []
    real = baselines.neyman_pearson_fusion
    monkeypatch.setattr(baselines, "neyman_pearson_fusion", lambda *a, **k: calls.append(a) or real(*a, **k))
    cache: dict = {}
    shared = [scaling.rule_error_vs_taxels(fusion, contact=3, h0_cache=cache, **args)]
    assert len(calls) == 2 and {key[0] for key in cache} == {"law", "llr f0", "np rule"}
    shared.append(scaling.rule_error_vs_taxels(fusion, fraction=0.5, h0_cache=cache, **args))
    assert len(calls) == 2
    for a, b in zip(alone, shared):
        for rule in scaling.RULES:
            for key in ("taxels", "p_false_alarm", "p_miss", "error", "notes"):
                assert a["rules"][rule][key] == b["rules"][rule][key], (rule, key)
    # another P_F target is another N-P rule: not taken from the cache
    other = FusionSpec(rules=scaling.RULES, alpha=0.3, beta=0.5, k=2, np_false_alarm=0.2, xi=0.003)
    scaling.rule_error_vs_taxels(other, contact=3, h0_cache=cache, **args)
    assert len(calls) == 4
