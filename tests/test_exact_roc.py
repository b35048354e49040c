"""Exact ROC curves of the report (issue 13, part B): the law of the preferential U_G (eq 7)
and of the eq 31/32 statistic against brute force over all decision vectors, the ROC built from
laws against the brute-force ROC, the count ROC's log tails, the Mann-Whitney AUC of the Monte
Carlo curves against counting pairs, and the report's figures: exact curves beside the Monte
Carlo ones, floors at the exact values, both taxels of a strut on the taxel map."""

from __future__ import annotations

import itertools
import math
import sys
from pathlib import Path

import mpmath as mp
import numpy as np
import pytest

from fusion_center.core import exact_rates, montecarlo

sys.path.insert(0, str(Path(__file__).resolve().parent))
from exact_rate_references import log_chain_states  # noqa: E402 - the shared log-domain reference DP


def brute_law(pi, p, q, encoding):
    """{U_G (mpmath, 60 digits): probability} over all 2^n vectors, eq 7 term by term."""
    n = len(pi)
    absent = -1 if encoding == "pm1" else 0
    out = {}
    with mp.workdps(60):
        P, Q = mp.mpf(2) ** mp.mpf(p), mp.mpf(2) ** mp.mpf(q)
        for bits in itertools.product((0, 1), repeat=n):
            u = [1 if b else absent for b in bits]
            padded = [0, *u, 0]
            val = mp.mpf(0)
            for i in range(1, n + 1):
                nxt, prv = padded[i + 1], padded[i - 1]
                fp = P if nxt == 1 else (0 if (nxt == -1 and p > 0) else 1)
                fq = Q if prv == 1 else (0 if (prv == -1 and q > 0) else 1)
                val += padded[i] * fp * fq
            w = math.prod(x if b else 1 - x for b, x in zip(bits, pi))
            key = mp.nstr(val, 30)
            out[key] = out.get(key, 0.0) + w
    return {float(mp.mpf(k)): v for k, v in out.items()}


@pytest.mark.parametrize("encoding, p, q", [("pm1", 1.3, 0.18), ("pm1", 1.0, 1.0), ("pm1", 0.0, 1.5),
                                            ("01", 1.0, 2.0), ("pm1", 2.0, 0.0)])
@pytest.mark.parametrize("n", [1, 2, 5, 10])
def test_preferential_law_vs_all_vectors(encoding, p, q, n):
    rng = np.random.default_rng(7 * n + int(10 * p))
    pi = rng.uniform(0.05, 0.95, n)
    values, logp = exact_rates.preferential_law(pi, p, q, encoding)
    ref = brute_law(pi, p, q, encoding)
    assert np.all(np.diff(values) > 0)
    assert len(values) == len(ref)
    for v, lp in zip(values, logp):
        key = min(ref, key=lambda k: abs(k - v))
        assert abs(key - v) <= 1e-12 * max(1.0, abs(v))
        assert math.isclose(math.exp(lp), ref[key], rel_tol=1e-12)


def test_preferential_law_is_none_for_01_with_a_non_integer_weight():
    assert exact_rates.preferential_law([0.3] * 5, 0.5, 2.0, "01") is None


def brute_roc(law0: dict, laws1: list[dict], weights):
    values = sorted(set(law0) | {v for law in laws1 for v in law}, reverse=True)
    pf = [sum(w for v, w in law0.items() if v >= t) for t in values]
    pd = [sum(wt * sum(w for v, w in law.items() if v >= t) for law, wt in zip(laws1, weights)) for t in values]
    pm = [sum(wt * sum(w for v, w in law.items() if v < t) for law, wt in zip(laws1, weights)) for t in values]
    return values, pf, pd, pm


def test_roc_from_laws_vs_brute_force():
    """Preferential U_G, 9 taxels, two H1 patterns: every kept threshold's P_F, P_D and log10 P_M,
    and the AUC (trapezoid over every threshold) against sums over all 2^9 vectors."""
    rng = np.random.default_rng(3)
    n, p, q = 9, 1.3, 0.4
    pf = rng.uniform(0.01, 0.2, n)
    patterns = [rng.uniform(0.5, 0.95, n), rng.uniform(0.2, 0.9, n)]
    weights = [0.3, 0.7]
    roc = exact_rates.roc_from_laws(exact_rates.preferential_law(pf, p, q, "pm1"),
                                    [exact_rates.preferential_law(r, p, q, "pm1") for r in patterns], weights)
    values, bpf, bpd, bpm = brute_roc(brute_law(pf, p, q, "pm1"), [brute_law(r, p, q, "pm1") for r in patterns],
                                      weights)
    for t, f, d, lm in zip(roc["thresholds"], roc["pf"], roc["pd"], roc["log10_pm"]):
        j = min(range(len(values)), key=lambda k: abs(values[k] - t))
        assert math.isclose(f, bpf[j], rel_tol=1e-12) and math.isclose(d, bpd[j], rel_tol=1e-12, abs_tol=1e-15)
        if bpm[j] > 0:
            assert math.isclose(10.0**lm, bpm[j], rel_tol=1e-11)
        else:
            assert lm is None
    auc = float(np.trapezoid([0.0, *bpd, 1.0], [0.0, *bpf, 1.0]))
    assert math.isclose(roc["auc"], auc, rel_tol=1e-12)


def test_linear_statistic_law_vs_all_vectors_unequal_probabilities_within_a_kind():
    """eq 31's statistic with two declared kinds and true probabilities that differ taxel by
    taxel: the kinds law (Poisson-binomial count per kind) against all 2^10 vectors."""
    rng = np.random.default_rng(9)
    a = np.r_[np.full(6, 2.2), np.full(4, 0.9)]
    b = np.r_[np.full(6, -1.7), np.full(4, -0.3)]
    probs = rng.uniform(0.02, 0.98, 10)
    values, logp = exact_rates.linear_statistic_law(a, b, probs)
    ref = {}
    for bits in itertools.product((0, 1), repeat=10):
        s = round(sum(a[i] if x else b[i] for i, x in enumerate(bits)), 9)
        ref[s] = ref.get(s, 0.0) + math.prod(probs[i] if x else 1 - probs[i] for i, x in enumerate(bits))
    assert len(values) == len(ref)
    for v, lp in zip(values, logp):
        assert math.isclose(math.exp(lp), ref[round(v, 9)], rel_tol=1e-11)
    tail = exact_rates.linear_statistic_tail(a, b, probs, 1.0)
    assert math.isclose(tail, sum(w for s, w in ref.items() if s > 1.0), rel_tol=1e-11)


def test_count_roc_log_tails_far_below_the_double_range():
    """log10 P_F and log10 P_M of "K >= m" against mpmath sums, down to 1e-400."""
    pf = np.full(150, 2e-3)
    pd = np.full(150, 0.999)
    roc = montecarlo.exact_count_roc(pf, pd[None, :], np.array([1.0]))
    with mp.workdps(50):
        for m in (0, 1, 75, 140, 150, 151):
            ref_f = mp.fsum(mp.binomial(150, k) * mp.mpf(2e-3) ** k * (1 - mp.mpf(2e-3)) ** (150 - k)
                            for k in range(m, 151))
            ref_m = mp.fsum(mp.binomial(150, k) * mp.mpf(0.999) ** k * (1 - mp.mpf(0.999)) ** (150 - k)
                            for k in range(0, min(m, 151)))
            for got, ref in ((roc["log10_pf"][m], ref_f), (roc["log10_pm"][m], ref_m)):
                if ref == 0:
                    assert got is None
                else:
                    assert abs(got - float(mp.log10(ref))) <= 1e-11 * max(1.0, abs(float(mp.log10(ref))))
    assert roc["log10_pf"][150] < -400


def test_mann_whitney_auc_counts_pairs():
    rng = np.random.default_rng(2)
    s0 = rng.integers(0, 6, 300).astype(float)
    s1 = rng.integers(2, 9, 200).astype(float)
    pairs = (s1[:, None] > s0[None, :]).sum() + 0.5 * (s1[:, None] == s0[None, :]).sum()
    assert math.isclose(montecarlo.mann_whitney_auc(s0, s1), pairs / (300 * 200), rel_tol=1e-14)
    assert math.isclose(montecarlo.empirical_roc(s0, s1)["auc"], pairs / (300 * 200), rel_tol=1e-14)


def test_mean_ranks_by_counting_without_importing_scipy_stats(monkeypatch):
    """The AUC's ranks (scipy.stats.rankdata's mean ranks): each value's rank counted pairwise,
    #{x_j < x_i} + (#{x_j == x_i} + 1) / 2 - ties, infinities, -0.0, one value, none; NaN ->
    all NaN - computed without scipy.stats (its import took ~0.7 s of the report's CPU time;
    main imported it here)."""
    rng = np.random.default_rng(4)
    cases = [rng.integers(0, 7, 500).astype(float), rng.normal(size=301), np.array([2.0]), np.array([]),
             np.array([np.inf, -np.inf, 0.0, -0.0, np.inf, 1e-300, 0.0])]
    monkeypatch.setitem(sys.modules, "scipy.stats", None)   # importing it now raises ImportError
    for x in cases:
        counted = (x[None, :] < x[:, None]).sum(axis=1) + ((x[None, :] == x[:, None]).sum(axis=1) + 1) / 2
        got = montecarlo.mean_ranks(x)
        assert got.dtype == np.float64 and np.array_equal(got, counted), x
    assert np.isnan(montecarlo.mean_ranks([1.0, np.nan, 1.0])).all()
    s0, s1 = cases[0][:300], cases[0][300:]
    pairs = (s1[:, None] > s0[None, :]).sum() + 0.5 * (s1[:, None] == s0[None, :]).sum()
    assert math.isclose(montecarlo.mann_whitney_auc(s0, s1), pairs / (300 * 200), rel_tol=1e-14)


# ------------------------------------------------------------------ the report
@pytest.fixture(scope="module")
def point_force_report(tmp_path_factory):
    """point_force's report.json (4000 trials). What is read here - the ROC curves, the achieved
    levels - is computed before and apart from the figures, so the PNGs are built but not
    rendered and the scale figures (JSON ``scale``, another computation) are not computed: ~85 %
    of the report's CPU. The whole report, PNGs included: tests/test_report.py."""
    import json

    from fusion_center import cli
    from fusion_center.report import plots, scaling

    out = tmp_path_factory.mktemp("report_pf")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(plots, "_save", lambda fig, path: plots.plt.close(fig))
        patch.setattr(scaling, "scale_figures", lambda scene, bitrates: {"layouts": None, "rules": None, "caption": None})
        patch.setattr(plots, "bits_vs_taxels", lambda *args, **kwargs: None)
        patch.setattr(plots, "error_vs_taxels", lambda *args, **kwargs: None)
        assert cli.main(["report", "--scene", "scenes/point_force.toml", "--out", str(out), "--trials", "4000",
                         "--seed", "5"]) == 0
    data = json.loads((out / "report.json").read_text())
    assert data["scale"] == {"layouts": None, "rules": None, "caption": None}  # (the stand-ins were used)
    return data


def test_report_has_exact_roc_curves_beside_monte_carlo(point_force_report):
    """point_force runs all six decision rules: exact curves for the count rules, the
    preferential U_G and the eq 31/32 statistic; each Monte Carlo AUC lies within 4 standard
    errors of the exact one (the cross-check)."""
    roc = point_force_report["roc"]
    for key in ("count_exact", "preferential_exact", "llr_exact", "np_exact"):
        assert key in roc and roc[key]["method"] == "exact", key
    trials = point_force_report["trials_per_hypothesis"]
    for rule in ("preferential", "llr", "np"):
        exact, mc = roc[f"{rule}_exact"]["auc"], roc[rule]["auc"]
        se = math.sqrt(max(exact * (1 - exact), 1e-6) / trials) * 2
        assert abs(exact - mc) <= 4 * se, (rule, exact, mc)
    # the exact curve reaches far below the Monte Carlo's floor
    assert min(v for v in roc["preferential_exact"]["log10_pf"] if v is not None) < -100


def test_report_achieved_levels_exact_for_preferential(point_force_report):
    from fusion_center import evaluation
    from fusion_center.core.montecarlo import taxel_rates
    from taxel_net.scene import load_scene

    data = point_force_report["achieved_vs_requested"]["preferential"]
    assert data["source"].startswith("exact")
    scene = load_scene("scenes/point_force.toml")
    f = scene.fusion
    taxel_pf = taxel_rates(0.0, [t.zeta_mv for t in scene.taxels], [t.noise_sigma_mv for t in scene.taxels])
    for alpha, achieved, log10 in zip(data["requested"], data["achieved"], data["log10_achieved"]):
        tm = evaluation.preferential_threshold_mean(scene, alpha=alpha)
        r = exact_rates.preferential_error_rates(taxel_pf, taxel_pf, f.p, f.q, f.tuple, tm, tm)
        assert achieved == r.p_false_alarm
        assert log10 == (None if r.log_p_false_alarm is None else r.log_p_false_alarm / math.log(10.0))


def _capture(monkeypatch):
    import fusion_center.report.plots as plots

    figures = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: figures.append(fig))
    return plots, figures


def test_taxel_map_shows_both_taxels_of_a_strut_with_node_ids(monkeypatch):
    plots, figures = _capture(monkeypatch)
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 0.0], [20.0, 5.0]])
    active = np.array([False, True, True, False])
    plots.taxel_map(xy, active, None, "t", "unused.png", node_ids=[7, 8, 9, 10], unit="mm")
    ax = figures[0].axes[0]
    points = np.vstack([c.get_offsets() for c in ax.collections])
    assert len({tuple(pt) for pt in points}) == 4  # the two taxels at (10, 0) drawn apart
    assert sorted(t.get_text() for t in ax.texts) == ["10", "7", "8", "9"]
    assert ax.get_xlabel() == "x [mm]"


def test_error_plot_floor_reaches_the_exact_values(monkeypatch):
    """An exact total error of 3e-200 is drawn where it is (the axis reaches below it), one below
    1e-300 as a down triangle at 1e-300; a Monte Carlo 0 sits on the labelled floor line."""
    plots, figures = _capture(monkeypatch)

    def point(rule, est, exact):
        return {"rule": rule, "mode": "decision_sync", "bus_time_per_cycle_ms": 3.0, "cpu_time_per_decision_us": 9.0,
                "total_error": {"estimate": est, "ci95": [0.0, 1e-4] if est == 0 else [est / 2, est * 2],
                                "exact": exact}}

    plots.error_vs_runtime([point("additive", 0.0, 3e-200), point("preferential", 1e-3, 0.0)], 2.5e-6, "unused.png")
    ax = figures[0].axes[0]
    assert ax.get_ylim()[0] < 3e-200
    markers = {line.get_marker(): line.get_ydata()[0] for line in ax.lines if len(line.get_ydata()) == 1}
    assert markers["D"] == 3e-200 and markers["v"] == 1e-300
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any(text.startswith("MC floor") for text in labels) and "exact < 1e-300" in labels


def log_law_reference(pi, p, q):
    """U_G's law for {-1,+1}, p, q > 0 from the independent log-domain DP of test_exact_rates
    (np.logaddexp, no scaling or trimming; U_G in mpmath, 40 digits). Returns {U_G: ln P}."""
    L, mid = log_chain_states(pi)
    ninf = -np.inf
    out = {}
    with mp.workdps(40):
        P, Q = mp.mpf(2) ** mp.mpf(p), mp.mpf(2) ** mp.mpf(q)
        for a in (0, 1):
            for b in (0, 1):
                en = (1 if b else -1) if a else 0
                for e1 in (-1, 0, 1):
                    for j in np.flatnonzero(np.isfinite(L[a, b, e1 + 1])):
                        key = mp.nstr(P * Q * (j - mid) + P * e1 + Q * en, 25)
                        out[key] = float(np.logaddexp(out.get(key, ninf), L[a, b, e1 + 1, j]))
    return {float(mp.mpf(k)): v for k, v in out.items()}


@pytest.mark.parametrize("p, q", [(1.0, 1.0), (1.3, 0.2)])
def test_preferential_law_deep_atoms_vs_log_domain_reference(p, q):
    """n = 150 taxels present with probability 0.002-0.008 (every taxel present: ~1e-350): with
    deep (default) the atoms below 1e-300 beyond the outermost atom >= 1e-300
    come from tilted runs; every returned ln P against an untrimmed log-domain DP to 1e-11
    (relative on the log); without deep none below 1e-300, and the same atoms above it."""
    rng = np.random.default_rng(5)
    pi = rng.uniform(0.002, 0.008, 150)
    ref = log_law_reference(pi, p, q)
    keys = np.array(sorted(ref))
    values, logp = exact_rates.preferential_law(pi, p, q, "pm1")
    assert logp.min() < math.log(1e-300) - 50  # deep atoms are there
    for v, lp in zip(values, logp):
        key = keys[np.argmin(np.abs(keys - v))]
        assert abs(key - v) <= 1e-12 * max(1.0, abs(v))
        assert abs(lp - ref[key]) <= 1e-11 * max(1.0, abs(ref[key])), (v, lp, ref[key])
    shallow_v, shallow_lp = exact_rates.preferential_law(pi, p, q, "pm1", deep=False)
    assert shallow_lp.min() >= math.log(1e-300)
    kept = np.isin(values, shallow_v)
    assert np.array_equal(values[kept], shallow_v) and np.allclose(logp[kept], shallow_lp, rtol=1e-14)
    # the upper tail is covered from the bulk to the all-present vector (its atom: every taxel present)
    top = float(np.sum(np.log(pi)))
    assert math.isclose(logp[-1], top, rel_tol=1e-12)
