"""The split of the threshold module (mean_deficit / thresholds / preferential_band) keeps every
name where it was, and the preferential band decision (sec. 2.2.3.3, eq 20) is certified: a
vector whose float U_G (eq 7) lies on the other side of a band edge than its exact value is
decided by the exact value, in the core (band_decision), in ``fuse`` and in the live service."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import mpmath
import numpy as np
import pytest

from fusion_center.core import preferential_band, rules, thresholds
from fusion_center.core.preferential_band import band_decision

ROOT = Path(__file__).resolve().parent.parent

# found by search: float U_G (rules.preferential) above the exact value (DOWN), and the exact
# value above the next double after the float U_G (UP); both checked below against mpmath
DOWN = ("01", 1.4708278463687552, 1.0981732127038792, [1, 1, 0, 0, 1, 1, 1, 1])
UP = ("pm1", 0.21298188804064308, 0.8234639657906898, [1, 1, -1])


def exact_u_g(u, p, q, encoding):
    """U_G of eq 7 summed term by term in mpmath (90 digits), independently of rules.py."""
    absent = -1 if encoding == "pm1" else 0
    with mpmath.workdps(90):
        big_p, big_q = mpmath.mpf(2) ** mpmath.mpf(p), mpmath.mpf(2) ** mpmath.mpf(q)
        padded = [0, *u, 0]
        total = mpmath.mpf(0)
        for i in range(1, len(u) + 1):
            nxt, prv = padded[i + 1], padded[i - 1]
            fp = big_p if nxt == 1 else (mpmath.mpf(0) if (nxt == absent == -1 and p > 0) else mpmath.mpf(1))
            fq = big_q if prv == 1 else (mpmath.mpf(0) if (prv == absent == -1 and q > 0) else mpmath.mpf(1))
            total += padded[i] * fp * fq
        return total


def band(encoding, p, q, n, low, high):
    th = thresholds.preferential_threshold(n, 0.003, 0.48, p, q, encoding)
    return dataclasses.replace(th, threshold_initial=low, threshold_final=high)


def test_the_search_cases_straddle_their_float():
    for encoding, p, q, u in (DOWN, UP):
        v = rules.preferential(u, p, q, encoding)
        exact = exact_u_g(u, p, q, encoding)
        if (encoding, p, q, u) == DOWN:
            assert exact < v
        else:
            assert exact > mpmath.mpf(np.nextafter(v, np.inf))


def test_band_decision_follows_the_exact_value_at_both_edges():
    encoding, p, q, u = DOWN
    v = rules.preferential(u, p, q, encoding)
    # final edge = the float U_G: floats say H1, the exact U_G lies below it
    assert band_decision(band(encoding, p, q, len(u), v - 1.0, v), v, u) == "undecided"
    # initial edge = the float U_G: floats say "not below", the exact U_G is below: H0
    assert band_decision(band(encoding, p, q, len(u), v, v + 1.0), v, u) == "H0"
    encoding, p, q, u = UP
    v = rules.preferential(u, p, q, encoding)
    above = float(np.nextafter(v, np.inf))
    # final edge one ulp above the float U_G: floats say below, the exact U_G reaches it: H1
    assert band_decision(band(encoding, p, q, len(u), v - 1.0, above), v, u) == "H1"
    # far from the edges the float comparison decides (and agrees)
    assert band_decision(band(encoding, p, q, len(u), v - 2.0, v - 1.0), v, u) == "H1"
    assert band_decision(band(encoding, p, q, len(u), v + 1.0, v + 2.0), v, u) == "H0"
    assert band_decision(band(encoding, p, q, len(u), v - 1.0, v + 1.0), v, u) == "undecided"


def test_band_decision_without_a_band_is_undecided():
    th = thresholds.preferential_threshold(5, 0.5, 0.9, 1.0, 1.0)  # 3 alpha/(1 - xi) > 9/4: no root
    assert th.threshold_mean is None
    assert band_decision(th, 3.0, [1, 1, 1, -1, 1]) == "undecided"


@pytest.mark.parametrize("case", [DOWN, UP], ids=["float-above-exact", "exact-above-next-float"])
def test_live_service_decides_with_the_exact_u_g(case, monkeypatch):
    """DecisionFusion's preferential rule at an edge placed on the cycle's float U_G."""
    from taxel_net.scene import BusSpec, FusionSpec, Scene, TaxelSpec
    from fusion_center.service import decision_fusion

    encoding, p, q, u = case
    n = len(u)
    v = rules.preferential(u, p, q, encoding)
    high = v if case is DOWN else float(np.nextafter(v, np.inf))
    expected = "undecided" if case is DOWN else "H1"
    taxels = tuple(TaxelSpec(node_id=1 + i, kind="R", x=float(i), y=0.0, pf=0.01, pm=0.02) for i in range(n))
    fusion = FusionSpec(rules=("preferential",), decide_with="preferential", tuple=encoding, alpha=0.48, p=p, q=q)
    scene = Scene(path="<test>", name="band", bus=BusSpec(), taxels=taxels, fusion=fusion,
                  stages=("fusion",), cycles=5)
    real = decision_fusion.preferential_threshold_cached
    monkeypatch.setattr(decision_fusion, "preferential_threshold_cached",
                        lambda *a: dataclasses.replace(real(*a), threshold_initial=v - 1.0, threshold_final=high))
    fuse = decision_fusion.DecisionFusion(scene, ("preferential",))
    wire = np.array([1 if x == 1 else -1 for x in u], dtype=np.int8)
    received, present, n_received, count = fuse.cycle_decisions(wire, np.ones(n, dtype=bool))
    result = fuse.results(wire, received, n_received, count)["preferential"]
    assert result["U_G"] == v
    assert result["band"] == [v - 1.0, high]
    assert result["decision"] == expected
    # the float comparison alone would have decided otherwise
    assert ("H1" if v >= high else "undecided") != expected


def test_split_keeps_every_name_in_place():
    from fusion_center import core
    from fusion_center.core import mean_deficit

    for name in ("additive_threshold", "multiplicative_threshold", "preferential_threshold", "AdditiveThreshold",
                 "MultiplicativeThreshold", "PreferentialThreshold"):
        assert getattr(core, name) is getattr(thresholds, name)
    assert all(hasattr(thresholds, name) for name in thresholds.__all__)
    assert thresholds.preferential_threshold is preferential_band.preferential_threshold
    assert thresholds.PreferentialThreshold is preferential_band.PreferentialThreshold
    assert thresholds.max_preferential_value is preferential_band.max_preferential_value
    assert thresholds.solve_mean_deficit is mean_deficit.solve_mean_deficit
    assert thresholds.DEFAULT_RTOL == mean_deficit.DEFAULT_RTOL
    for private in ("_d", "_dprime", "_dsecond", "_d_and_dprime", "_dprime_and_dsecond"):
        assert getattr(thresholds, private) is getattr(mean_deficit, private)


def test_core_preferential_threshold_stays_the_function_after_importing_the_submodules():
    """A submodule named like a public function would replace it on the package once imported;
    the band module is therefore preferential_band (checked in a fresh interpreter)."""
    code = ("import fusion_center.core.thresholds, fusion_center.core.preferential_band, "
            "fusion_center.core.mean_deficit\n"
            "import fusion_center.core as c\n"
            "print(callable(c.preferential_threshold) and not isinstance(c.preferential_threshold, type(c)),"
            " c.preferential_threshold is fusion_center.core.thresholds.preferential_threshold)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["True", "True"]
