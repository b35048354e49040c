"""The live pipeline's fast path gives the library's values: every rule of a record is
recomputed here with the public functions (rules.*, thresholds.*, curves.*, baselines.*) on
the cycle's decisions, for random cycles (random received sets and decisions, both tuples),
and compared exactly; the scalar contact classifier equals contact.classify."""

import dataclasses
import math

import numpy as np
import pytest

from fusion_center.core import baselines, contact, curves, rules, thresholds
from taxel_net.errors import ParameterError
from taxel_net.scene import BusSpec, FusionSpec, Scene, TaxelSpec, load_scene
from fusion_center.service import decision_fusion
from fusion_center.service.cycle_records import ClosedCycle
from fusion_center.service.pipeline import CyclePipeline

ALL_RULES = ("additive", "multiplicative", "preferential", "k-of-n", "llr", "np")


def small_scene(n: int, encoding: str, *, identical: bool = False, k: int = 3) -> Scene:
    """n taxels with heterogeneous (or identical) pf/pm: N-P by enumeration (n <= 20) or by count."""
    rng = np.random.default_rng(n)
    taxels = []
    for i in range(n):
        pf = 0.01 if identical else float(rng.uniform(0.001, 0.05))
        pm = 0.02 if identical else float(rng.uniform(0.001, 0.05))
        taxels.append(TaxelSpec(node_id=1 + i, kind="R", x=float(i % 5), y=float(i // 5), pf=pf, pm=pm))
    fusion = FusionSpec(rules=ALL_RULES, decide_with="additive", tuple=encoding, alpha=0.3, beta=0.83,
                        k=k, np_false_alarm=0.01, prior_h1=0.3, costs=(0.0, 1.0, 1.0, 0.0))
    return Scene(path="<test>", name="fast", bus=BusSpec(), taxels=tuple(taxels), fusion=fusion,
                 stages=("fusion", "area", "contact_type"), cycles=50)


def closed_cycle(wire: np.ndarray, cycle: int = 0) -> ClosedCycle:
    n = wire.size
    received = wire != 0
    return ClosedCycle(cycle=cycle, sync_us=1000 * cycle, close_us=1000 * cycle + 500, sync_counter=None,
                       closed_by="complete", decisions=wire.astype(np.int8), readings=np.full(n, np.nan),
                       received=received, expected=np.ones(n, dtype=bool), missing=np.zeros(n, dtype=bool),
                       held_decisions=wire.astype(np.int8), held_readings=np.full(n, np.nan),
                       late_frames=0, bad_frames=0, emcy=())


def random_wire(rng, n: int) -> np.ndarray:
    """{-1, 0, +1} per taxel: mostly received, a few missing; present with a random rate."""
    rate = rng.choice([0.0, 0.05, 0.3, 0.7, 1.0])
    wire = np.where(rng.random(n) < rate, 1, -1).astype(np.int8)
    wire[rng.random(n) < rng.choice([0.0, 0.1, 0.5])] = 0
    if not wire.any():
        wire[int(rng.integers(n))] = 1
    return wire


def reference_rules(scene: Scene, wire: np.ndarray) -> dict:
    """Each rule recomputed from scratch with the library's public functions."""
    f = scene.fusion
    enc = f.tuple
    received = wire != 0
    n = int(received.sum())
    u_pm1 = wire[received]
    u = u_pm1 if enc == "pm1" else ((u_pm1 + 1) // 2).astype(np.int8)
    present = int(np.count_nonzero(u_pm1 == 1))
    pd = np.array([1 - t.pm for t in scene.taxels])[received]
    pf = np.array([t.pf for t in scene.taxels])[received]
    out = {}

    value = rules.additive(u, enc)
    th = thresholds.additive_threshold(n, f.xi, f.alpha, enc)
    lam = (th.thresholds[0] if f.additive_root == "lower" else th.thresholds[-1]) if th.thresholds else None
    p = curves.p_additive_pm1(value, n, f.xi) if enc == "pm1" else curves.p_additive_01(value, n, f.xi)
    out["additive"] = {"U_G": value, "threshold": lam,
                       "decision": "undecided" if lam is None else ("H1" if value >= lam else "H0"), "p_h1": p}

    mv = rules.multiplicative(u, enc)
    mth = thresholds.multiplicative_threshold(n, f.xi, f.beta)
    if not mth.present_counts or mth.present_counts[0] is None:
        m_decision, m_lam, m_ln = "undecided", None, None
    else:
        m_ln = mth.ln_thresholds[0]
        m_lam = math.exp(m_ln) if m_ln is not None else 0.0
        m_decision = "H1" if present >= mth.present_counts[0] else "H0"
    out["multiplicative"] = {"U_G": mv.U_G, "ln_U_G": mv.ln_U_G, "threshold": m_lam, "ln_threshold": m_ln,
                             "decision": m_decision,
                             "p_h1": curves.p_multiplicative(mv.ln_U_G, n, f.xi) if enc == "pm1" else None}

    if 1 <= f.k <= n:
        verdict = rules.k_of_n(u, f.k, enc)
        out["k-of-n"] = {"U_G": int(np.sum(u)), "threshold": 2 * f.k - n if enc == "pm1" else f.k,
                         "decision": "H1" if verdict == 1 else "H0", "p_h1": None}
    else:
        out["k-of-n"] = {"U_G": present, "threshold": None, "decision": "undecided", "p_h1": None}

    llr = baselines.chair_varshney_llr(u, pd, pf, enc, f.prior_h1)
    out["llr"] = llr

    rule = baselines.neyman_pearson_fusion(pd, pf, f.np_false_alarm)
    out["np"] = {"U_G": rule.statistic_value(u, enc), "statistic": rule.statistic,
                 "threshold": rule.log_threshold if rule.statistic == "llr" else rule.count_threshold,
                 "decision": rule.decide(u, enc), "p_h1": None}

    out["preferential"] = rules.preferential(u, f.p, f.q, enc)
    return out


def check_record(scene: Scene, record: dict, wire: np.ndarray) -> None:
    ref = reference_rules(scene, wire)
    got = record["rules"]
    for name in ("additive", "multiplicative", "k-of-n", "np"):
        assert got[name] == ref[name], name
    assert got["llr"]["U_G"] == ref["llr"]  # bit for bit: the same sums
    if "preferential" in scene.fusion.rules:
        assert got["preferential"]["U_G"] == ref["preferential"]
    received = wire != 0
    assert record["n_received"] == int(received.sum())
    assert record["present_count"] == int(np.count_nonzero(wire == 1))
    t_c = record["present_count"] / record["n_received"]
    assert record["contact_type"] == contact.classify(t_c).value


@pytest.mark.parametrize("n,encoding,identical", [
    (12, "pm1", False),   # N-P by enumeration: ln Lambda statistic
    (12, "01", False),
    (9, "pm1", True),     # identical taxels: count statistic, ties at the boundary count
    (25, "pm1", False),   # N-P by count
    (25, "01", False),
])
def test_random_cycles_equal_the_library(n, encoding, identical):
    scene = small_scene(n, encoding, identical=identical)
    pipe = CyclePipeline(scene, truth=False)
    rng = np.random.default_rng(1000 + n)
    for cycle in range(120):
        wire = random_wire(rng, n)
        record = pipe.evaluate(closed_cycle(wire, cycle))
        check_record(scene, record, wire)


def test_matrix57_cycles_equal_the_library():
    scene = load_scene("scenes/matrix57.toml")
    pipe = CyclePipeline(scene)
    rng = np.random.default_rng(57)
    for cycle in range(60):
        wire = random_wire(rng, scene.n)
        record = pipe.evaluate(closed_cycle(wire, cycle))
        check_record(scene, record, wire)
        assert record["truth"] == ("H1" if 20 <= cycle < 120 else "H0")  # scene: present = [[20, 120]]


def test_k_outside_1_to_n_is_undecided_as_before():
    scene = small_scene(6, "pm1", k=5)
    pipe = CyclePipeline(scene, truth=False)
    wire = np.array([1, -1, 1, 0, 0, 0], dtype=np.int8)  # n = 3 received < k = 5
    result = pipe.evaluate(closed_cycle(wire))["rules"]["k-of-n"]
    assert result == {"U_G": 2, "threshold": None, "decision": "undecided", "p_h1": None}


def test_np_decide_value_at_ties_matches_decide():
    # identical taxels: ln Lambda monotone in the count; the boundary count is a tie (randomised)
    pd, pf = np.full(9, 0.98), np.full(9, 0.01)
    rule = baselines.neyman_pearson_fusion(pd, pf, 0.01)
    assert 0.0 < rule.gamma < 1.0
    decisions = set()
    for present in range(10):
        u = np.array([1] * present + [-1] * (9 - present))
        decisions.add(rule.decide_value(rule.statistic_value(u, "pm1")))
        assert rule.decide_value(rule.statistic_value(u, "pm1")) == rule.decide(u, "pm1")
    assert decisions == {"H0", "undecided", "H1"}
    # heterogeneous, n > 20: the count statistic, boundary count randomised
    rng = np.random.default_rng(25)
    pd, pf = rng.uniform(0.9, 0.99, 25), rng.uniform(0.001, 0.05, 25)
    rule = baselines.neyman_pearson_fusion(pd, pf, 0.02)
    assert rule.statistic == "present_count" and 0.0 < rule.gamma < 1.0
    for present in range(26):
        u = np.array([1] * present + [-1] * (25 - present))
        assert rule.decide_value(float(present)) == rule.decide(u, "pm1")
    assert rule.decide_value(float(rule.count_threshold)) == "undecided"
    # heterogeneous, n <= 20: ln Lambda by enumeration, every decision vector of 8 taxels
    pd, pf = rng.uniform(0.9, 0.99, 8), rng.uniform(0.001, 0.05, 8)
    rule = baselines.neyman_pearson_fusion(pd, pf, 0.02)
    assert rule.statistic == "llr"
    for bits in range(256):
        u = np.array([1 if bits >> i & 1 else -1 for i in range(8)])
        assert rule.decide_value(rule.statistic_value(u, "pm1")) == rule.decide(u, "pm1")


def test_a_wire_value_other_than_plus_minus_one_is_refused():
    scene = small_scene(5, "pm1")
    pipe = CyclePipeline(scene, truth=False)
    wire = np.array([1, -1, 5, 0, -1], dtype=np.int8)
    with pytest.raises(ParameterError, match=r"u\[2\]"):
        pipe.evaluate(closed_cycle(wire))


def test_first_cycle_solves_no_threshold(monkeypatch):
    scene = load_scene("scenes/matrix57.toml")
    pipe = CyclePipeline(scene)

    def no_solve(*args):
        raise AssertionError("threshold solved on the live path")

    for name in ("additive_threshold_cached", "multiplicative_threshold_cached", "preferential_threshold_cached"):
        monkeypatch.setattr(decision_fusion, name, no_solve)
    monkeypatch.setattr(baselines, "neyman_pearson_fusion", no_solve)
    for present in (0, 6, 57):
        wire = np.array([1] * present + [-1] * (scene.n - present), dtype=np.int8)
        record = pipe.evaluate(closed_cycle(wire))
        assert all("error" not in r for r in record["rules"].values())
        assert record["rules"]["additive"]["U_G"] == 2 * present - scene.n


# ------------------------------------------------------------------ contact type, scalar
LIMITS = [dict(), dict(point_force_min=0.0, point_force_max=0.0, larger_object_min=1.0),
          dict(point_force_min=0.05, point_force_max=0.05, larger_object_min=0.06)]


@pytest.mark.parametrize("limits", LIMITS)
def test_classify_ratio_equals_classify(limits):
    edges = [0.0, 1.0, contact.POINT_FORCE_MIN, contact.POINT_FORCE_MAX, contact.LARGER_OBJECT_MIN,
             *limits.values()]
    ratios = [r for e in edges for r in (e, np.nextafter(e, -1.0), np.nextafter(e, 2.0)) if 0.0 <= r <= 1.0]
    ratios += list(np.random.default_rng(3).random(500)) + [k / 57 for k in range(58)]
    for r in ratios:
        assert contact.classify_ratio(r, **limits) is contact.classify(r, **limits), r
    array = contact.classify(np.array(ratios), **limits)
    assert [contact.classify_ratio(r, **limits) for r in ratios] == list(array)


def test_classify_ratio_hand_worked_rows():
    assert contact.classify_ratio(0.0) is contact.ContactType.NO_CONTACT
    assert contact.classify_ratio(0.01) is contact.ContactType.POINT_FORCE   # row 1 wins the overlap
    assert contact.classify_ratio(0.02) is contact.ContactType.POINT_FORCE
    assert contact.classify_ratio(0.05) is contact.ContactType.SMALL_OBJECT
    assert contact.classify_ratio(0.1) is contact.ContactType.LARGER_OBJECT  # shared limit: larger object
    assert contact.classify_ratio(6 / 57) is contact.ContactType.LARGER_OBJECT


@pytest.mark.parametrize("bad", [float("nan"), -0.01, 1.01, float("inf"), "x", None])
def test_classify_ratio_refuses_what_classify_refuses(bad):
    with pytest.raises(ParameterError, match="ratio"):
        contact.classify_ratio(bad)
    with pytest.raises(ParameterError, match="ratio"):
        contact.classify(bad)


def test_classify_ratio_checks_the_limits():
    with pytest.raises(ParameterError, match="limits"):
        contact.classify_ratio(0.5, point_force_max=0.2, larger_object_min=0.1)


def test_scene_tuple_01_is_the_same_record_as_pm1_but_for_the_tuple_values():
    pm1 = small_scene(10, "pm1")
    zero_one = dataclasses.replace(pm1, fusion=dataclasses.replace(pm1.fusion, tuple="01"))
    wire = np.array([1, 1, -1, -1, 0, 1, -1, -1, -1, 1], dtype=np.int8)
    a = CyclePipeline(pm1, truth=False).evaluate(closed_cycle(wire))
    b = CyclePipeline(zero_one, truth=False).evaluate(closed_cycle(wire))
    # eq 6: n - 2k on {-1,+1}, n - k on {0,1} (n = 9 received, k = 5 absent)
    assert a["rules"]["additive"]["U_G"] == 9 - 2 * 5 and b["rules"]["additive"]["U_G"] == 9 - 5
    # eq 5: ln U_G = n - 2k and n - k
    assert a["rules"]["multiplicative"]["ln_U_G"] == -1.0 and b["rules"]["multiplicative"]["ln_U_G"] == 4.0
    assert a["rules"]["llr"] == b["rules"]["llr"]  # "present" is u_i = +1 in both tuples


def test_area_of_fewer_than_three_present_taxels_is_zero_as_in_geometry():
    from fusion_center.core import geometry

    scene = load_scene("scenes/matrix57.toml")
    pipe = CyclePipeline(scene, truth=False)
    xy = np.array([[t.x, t.y] for t in scene.taxels])
    rng = np.random.default_rng(35)
    for present in (0, 1, 2, 3, 6):
        for _ in range(5):
            wire = -np.ones(scene.n, dtype=np.int8)
            wire[rng.choice(scene.n, present, replace=False)] = 1
            record = pipe.evaluate(closed_cycle(wire))
            expected = geometry.contact_area(xy[wire == 1]) if present else 0.0
            assert record["area"] == expected
