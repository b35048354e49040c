"""Exact preferential rates (eq 7, eq 20 band) at any size (issue 21, item 6): every rate the
DPs report carries its exact natural log however small, 0 only for an event the rule cannot
produce, a rate below 1e-300 named in ``below_floor`` / ``rates_below_1e-300``.

The reference is independent of fusion_center's DPs: eq 7 evaluated term by term as integer
coefficients of (1, 2^p, 2^q, 2^(p+q)), a DP over (u_(i-1), u_i) -> {coefficients: probability}
in mpmath (60 digits, exponent range unbounded: 1e-2700 is an ordinary mpf), each final value
compared with the band edges in mpmath; the DP itself is checked against all 2^n vectors.

Tolerance on the logs: |ln ours - ln ref| <= 1e-12 + 1e-13 |ln ref|. The absolute part covers
the rates' relative error in P: the tilted DP accepts a proven bound <= 1e-13 (tilted_dp.BOUND_OK)
plus ~1e-13 of rounding, the extended-exponent DP <= (4 n + 6) 2^-53 < 3e-14 at n <= 60
(extended_dp's module doc), the counts DP is exact to ~1e-13 at or above 1e-300; the relative
part covers the double that holds ln P itself: forming ln P ~ -6000 as ln(mantissa) + e ln 2 costs
a few ulps of |ln P| (ulp(6000) ~ 9e-13). The reference's own error (60 digits) is negligible. A
wrong region, a lost taxel factor or a dropped label changes ln P by far more.
"""

from __future__ import annotations

import itertools
import json
import math
from fractions import Fraction

import mpmath as mp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mpmath.libmp import fzero, mpf_add, mpf_mul

from fusion_center.cli import main
from fusion_center.core.exact_rates import preferential_error_rates
from fusion_center.core.thresholds import preferential_threshold

DPS = 60
LOG_FLOOR = math.log(1e-300)
NAMES = ("p_detect", "p_undecided_h1", "p_miss", "p_false_alarm", "p_undecided_h0", "p_reject")


# ------------------------------------------------------------------ the independent reference
def _factor(neighbour: int, weight: float, encoding: str):
    """(1 + u_neighbour)^weight as an index: 'x' for 2^weight, 1, or 0 (0^0 = 1; the boundary u = 0)."""
    if neighbour == 1:
        return "x"
    if neighbour == 0 or weight == 0.0:  # boundary or {0,1}-absent: (1 + 0)^w = 1; 0^0 = 1
        return 1
    return 0  # {-1,+1} absent neighbour: 0^w = 0 for w > 0


def _term(prev: int, own: int, nxt: int, p: float, q: float, encoding: str) -> tuple:
    """Coefficients of (1, 2^p, 2^q, 2^(p+q)) of u_i (1 + u_(i+1))^p (1 + u_(i-1))^q (eq 7);
    own/prev/nxt are decision values (-1/0/1), prev/nxt None at the boundary (u = 0)."""
    if own == 0:
        return (0, 0, 0, 0)
    fp = _factor(0 if nxt is None else nxt, p, encoding)
    fq = _factor(0 if prev is None else prev, q, encoding)
    if fp == 0 or fq == 0:
        return (0, 0, 0, 0)
    index = (1 if fp == "x" else 0) + (2 if fq == "x" else 0)
    out = [0, 0, 0, 0]
    out[index] = own
    return _canonical(out, p, q)


def _canonical(c, p: float, q: float) -> tuple:
    """The same value with equal basis elements merged (exact identities: 2^p = 2^k for an
    integer p = k, likewise q, 2^(p+q) = 2^K for an integer p + q = K), so that the reference's
    keys stay few where the weights are integers or 0 (a linear map: applied per term)."""
    a, b, cq, d = c
    if float(p).is_integer():
        k = 2 ** int(p)
        a, b, cq, d = a + b * k, 0, cq + d * k, 0
    if float(q).is_integer():
        k = 2 ** int(q)
        a, b, cq, d = a + cq * k, b + d * k, 0, 0
    elif (Fraction(p) + Fraction(q)).denominator == 1:
        a, d = a + d * 2 ** int(Fraction(p) + Fraction(q)), 0
    return (a, b, cq, d)


def _value(coeffs, p: float, q: float, powers=None):
    """U_G from its coefficients; ``powers``: (2^p, 2^q) in mpmath if already formed."""
    big_p, big_q = powers if powers is not None else (mp.mpf(2) ** mp.mpf(p), mp.mpf(2) ** mp.mpf(q))
    a, b, c, d = coeffs
    return a + b * big_p + c * big_q + d * big_p * big_q


def _regions(final: dict, p, q, low, high) -> list:
    """[P(U >= high), P(low <= U < high), P(U < low)] from {coefficients: probability}."""
    out = [mp.mpf(0)] * 3
    lo, hi = mp.mpf(low), mp.mpf(high)
    powers = mp.mpf(2) ** mp.mpf(p), mp.mpf(2) ** mp.mpf(q)  # (once, not per value: the same numbers)
    for coeffs, w in final.items():
        v = _value(coeffs, p, q, powers)
        out[0 if v >= hi else (2 if v < lo else 1)] += w
    return out


_B = 1 << 24  # a packed key's base: a + b B + c B^2 + d B^3, every coefficient |x| < B / 2


def _pack(c) -> int:
    return c[0] + _B * (c[1] + _B * (c[2] + _B * c[3]))


def _unpack(key: int) -> tuple:
    out = []
    for _ in range(3):
        x = (key + _B // 2) % _B - _B // 2  # the balanced digit: coefficients may be negative
        out.append(x)
        key = (key - x) // _B
    return (*out, key)


def mp_band_rates(pi, p: float, q: float, encoding: str, low: float, high: float) -> list:
    """The three region probabilities (mpf) for taxels present with probabilities ``pi``.

    (How, not what: the coefficient tuples are packed into one int, ``_pack``, a linear map, so
    adding two keys is one int addition and a sum's key is the key of the summed coefficients;
    the eight terms are formed once; the inner loop runs mpmath's own mpf_add / mpf_mul on the
    raw (sign, man, exp, bc) tuples at the context's precision and rounding, what ``v * w`` and
    ``x + y`` of mpf numbers compute, without an mpf object per step. The same keys in the same
    order and the same mp numbers as the plain loop over tuples of mpf, ~4x faster.)"""
    absent = -1 if encoding == "pm1" else 0
    dec = {0: absent, 1: 1}
    with mp.workdps(DPS):
        prec, rnd = mp.mp._prec_rounding
        probs = [(1 - mp.mpf(float(x)), mp.mpf(float(x))) for x in pi]
        n = len(pi)
        assert n < _B // 2
        if n == 1:
            final: dict = {}
            for b in (0, 1):
                key = _term(None, dec[b], None, p, q, encoding)
                final[key] = final.get(key, mp.mpf(0)) + probs[0][b]
            return _regions(final, p, q, low, high)
        raw = [(x._mpf_, y._mpf_) for x, y in probs]
        coeffs = {(a, b, c): _term(dec[a], dec[b], dec[c], p, q, encoding)
                  for a in (0, 1) for b in (0, 1) for c in (0, 1)}
        assert n * max(abs(x) for t in coeffs.values() for x in t) < _B // 2  # no digit of a sum overflows
        terms = {abc: _pack(t) for abc, t in coeffs.items()}
        # state (u_(i-1), u_i) as bits; the first taxel's term is closed when the second is known
        states = {}
        for a in (0, 1):
            for b in (0, 1):
                states[(a, b)] = {_pack(_term(None, dec[a], dec[b], p, q, encoding)):
                                  mpf_mul(raw[0][a], raw[1][b], prec, rnd)}
        for i in range(2, n):
            new: dict = {}
            for (a, b), dist in states.items():
                for c in (0, 1):
                    t = terms[a, b, c]
                    target = new.setdefault((b, c), {})
                    get = target.get
                    w = raw[i][c]
                    for k, v in dist.items():
                        key = k + t
                        target[key] = mpf_add(get(key, fzero), mpf_mul(v, w, prec, rnd), prec, rnd)
            states = new
        final = {}
        for (a, b), dist in states.items():
            t = _pack(_term(dec[a], dec[b], None, p, q, encoding))
            for k, v in dist.items():
                key = k + t
                final[key] = mpf_add(final.get(key, fzero), v, prec, rnd)
        final = {_unpack(k): mp.mp.make_mpf(v) for k, v in final.items()}
        return _regions(final, p, q, low, high)


def mp_enumerate(pi, p, q, encoding, low, high) -> list:
    """The same by all 2^n decision vectors (to check the reference DP)."""
    absent = -1 if encoding == "pm1" else 0
    out = [mp.mpf(0)] * 3
    with mp.workdps(DPS):
        for bits in itertools.product((0, 1), repeat=len(pi)):
            u = [1 if b else absent for b in bits]
            coeffs = (0, 0, 0, 0)
            for i in range(len(u)):
                t = _term(u[i - 1] if i else None, u[i], u[i + 1] if i + 1 < len(u) else None, p, q, encoding)
                coeffs = tuple(x + y for x, y in zip(coeffs, t))
            v = _value(coeffs, p, q)
            w = mp.mpf(1)
            for b, x in zip(bits, pi):
                w *= mp.mpf(float(x)) if b else 1 - mp.mpf(float(x))
            out[0 if v >= mp.mpf(high) else (2 if v < mp.mpf(low) else 1)] += w
    return out


def assert_matches(ours, ref: dict) -> None:
    """Every rate: 0 exactly when the reference is 0 (log None, not in below_floor); else its
    log within the tolerance of the module doc, named in below_floor iff below 1e-300."""
    assert ours.method in ("chain", "lattice", "integer", "exact-counts"), ours.method
    for name in NAMES:
        r = ref[name]
        got = getattr(ours, "log_" + name)
        if r == 0:
            assert got is None and name not in ours.below_floor, (name, got, ours.below_floor)
            continue
        with mp.workdps(DPS):
            lr = float(mp.log(r))
        assert got is not None, (name, lr, ours.below_floor)
        assert abs(got - lr) <= 1e-12 + 1e-13 * abs(lr), (name, got, lr)
        if abs(lr - LOG_FLOOR) > 1e-9:
            assert (name in ours.below_floor) == (lr < LOG_FLOOR), (name, lr, ours.below_floor)


def reference(pd, pf, p, q, encoding, low, high) -> dict:
    h1 = mp_band_rates(pd, p, q, encoding, low, high)
    h0 = mp_band_rates(pf, p, q, encoding, low, high)
    return dict(zip(NAMES, (*h1, *h0)))


# ------------------------------------------------------------------ the reference itself
@pytest.mark.parametrize("encoding, p, q", [("pm1", 0.3169778809467432, 1.4445044222254704), ("pm1", 0.0, 1.5),
                                            ("pm1", 1.0, 2.0), ("01", 0.7362069775690239, 1.1216956018196342),
                                            ("01", 1.0, 1.0), ("01", 0.0, 0.0)])
def test_reference_dp_equals_enumeration(encoding, p, q):
    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 7):
        pi = rng.uniform(0.05, 0.95, n)
        g = 1.0 if n == 1 else 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
        for low, high in ((0.2 * g, 0.6 * g), (-0.5 * g, 0.1 * g)):
            with mp.workdps(DPS):
                a = mp_band_rates(pi, p, q, encoding, low, high)
                b = mp_enumerate(pi, p, q, encoding, low, high)
                assert all(abs(x - y) <= mp.mpf(10) ** -50 for x, y in zip(a, b))
                assert abs(sum(a) - 1) <= mp.mpf(10) ** -50


# ------------------------------------------------------------------ issue 21 item 6: the two cases
def fuse_json(capsys, *argv):
    rc = main(["fuse", *argv, "--json"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    return json.loads(out)


ISSUE_CASES = [
    ("pm1", "1,-1,1,1,-1,1,-1,-1,1,1,1,1,-1,1", 0.3169778809467432, 1.4445044222254704, "chain"),
    ("01", "1,0,1,1,0,1,0,1,0,1,1,1,1,1", 0.7362069775690239, 1.1216956018196342, "exact-counts"),
]


@pytest.mark.parametrize("encoding, u, p, q, method", ISSUE_CASES)
def test_issue_cases_report_the_exact_log(capsys, encoding, u, p, q, method):
    """pf = 1e-45 on 14 taxels: a false alarm needs all 14 present (U_G = g above the band), so
    P_F = 1e-630 exactly (ln = 14 ln 1e-45 = -1450.6286...): its log is reported and it is named
    in rates_below_1e-300 (before: a null log on the chain; 0.0 read as impossible on {0,1}).
    No value of U_G lies in the band here (checked by the reference): the undecided rates are
    impossible events, 0 with null logs, not named (before: named on the chain)."""
    rec = fuse_json(capsys, "--rule", "preferential", f"--u={u}", "--tuple", encoding, "--p", repr(p), "--q", repr(q),
                    "--xi", "0.01", "--alpha", "0.05", "--pd", "0.93", "--pf", "1e-45")
    assert rec["rates_method"] == method
    n = 14
    low, high = rec["threshold_initial"], rec["threshold_final"]
    h1 = mp_band_rates([0.93] * n, p, q, encoding, low, high)
    h0 = mp_band_rates([1e-45] * n, p, q, encoding, low, high)
    with mp.workdps(DPS):
        assert abs(h0[0] / mp.mpf(1e-45) ** 14 - 1) < mp.mpf(10) ** -50  # only all present reaches the edge
        expected = {"p_detect": h1[0], "p_undecided_h1": h1[1], "p_false_alarm": h0[0], "p_undecided_h0": h0[1]}
        for key, r in expected.items():
            if r == 0:
                assert rec[key] == 0.0 and rec["log_" + key] is None, key
                continue
            lr = float(mp.log(r))
            assert rec["log_" + key] is not None, key
            assert abs(rec["log_" + key] - lr) <= 1e-12 + 1e-13 * abs(lr), (key, rec["log_" + key], lr)
            assert math.isclose(rec[key], float(r), rel_tol=1e-12, abs_tol=0.0), key
    assert h1[1] == 0 and h0[1] == 0
    assert rec["rates_below_1e-300"] == ["p_false_alarm"]
    assert math.isclose(rec["log_p_false_alarm"], 14 * math.log(1e-45), rel_tol=1e-15)


# ------------------------------------------------------------------ hypothesis: extreme cases
WEIGHTS = st.one_of(st.sampled_from([0.0, 1.0, 2.0, 1e-12, 2.0**-40, 3e-7, 1.999999]),
                    st.floats(0.01, 2.0, allow_nan=False))


@st.composite
def probabilities(draw, n):
    """Per-taxel probabilities from one regime per hypothesis: tiny (1e-60 .. 1e-15, rates to
    below 1e-2000 at 60 taxels), small, moderate, or close to 1 (1 - 1e-15 .. 1 - 1e-2)."""
    regime = draw(st.sampled_from(["tiny", "small", "moderate", "near_one", "mixed"]))

    def one(kind):
        if kind == "tiny":
            return 10.0 ** draw(st.floats(-60.0, -15.0))
        if kind == "small":
            return 10.0 ** draw(st.floats(-6.0, -1.0))
        if kind == "moderate":
            return draw(st.floats(0.05, 0.95))
        return 1.0 - 10.0 ** draw(st.floats(-15.0, -2.0))

    kinds = [draw(st.sampled_from(["tiny", "small", "moderate", "near_one"])) if regime == "mixed" else regime
             for _ in range(n)]
    return [one(k) for k in kinds]


@st.composite
def cases(draw):
    encoding = draw(st.sampled_from(["pm1", "01"]))
    p, q = draw(WEIGHTS), draw(WEIGHTS)
    integer = float(p).is_integer() and float(q).is_integer()
    # the reference's keys: O(n) on {-1,+1} and for integer weights, up to ~n^3 / 36 coefficient
    # triples on {0,1} with non-integer ones (~n^2 where one of p, q, p + q is an integer or 0)
    two = any(float(x).is_integer() for x in (p, q)) or (Fraction(p) + Fraction(q)).denominator == 1
    n = draw(st.integers(1, 60 if encoding == "pm1" or integer else (40 if two else 20)))
    pd = draw(probabilities(n))
    pf = draw(probabilities(n))
    g = 1.0 if n == 1 else 2.0**p + 2.0**q + (n - 2) * 2.0 ** (p + q)
    if n >= 2 and draw(st.booleans()):  # the fuse command's band (eqs 18-20)
        band = preferential_threshold(n, draw(st.sampled_from([0.003, 0.01, 0.3])),
                                      draw(st.sampled_from([0.01, 0.05, 0.48])), p, q, encoding)
        if band.threshold_initial is not None:
            return encoding, p, q, pd, pf, band.threshold_initial, band.threshold_final
    low = g * draw(st.floats(-1.0, 1.0))
    high = low + g * draw(st.sampled_from([0.0, 1e-9, 0.01, 0.3, 2.0]))
    return encoding, p, q, pd, pf, low, high


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cases())
def test_every_rate_has_its_exact_log(case):
    encoding, p, q, pd, pf, low, high = case
    ours = preferential_error_rates(np.array(pd), np.array(pf), p, q, encoding, low, high)
    assert_matches(ours, reference(pd, pf, p, q, encoding, low, high))


@pytest.mark.parametrize("encoding, p, q", [("pm1", 1.0, 1.0), ("pm1", 1.3, 0.2), ("pm1", 0.0, 1.5),
                                            ("pm1", 1e-12, 1e-12), ("01", 1.0, 2.0), ("01", 0.5, 1.7)])
def test_rates_down_to_1e_2000(encoding, p, q):
    """pf ~ 1e-45 .. 1e-35 on 60 taxels ({0,1} non-integer: 24): a false alarm needs nearly all
    present -- rates far below 1e-2000 -- every one against the reference."""
    n = 60 if encoding == "pm1" or (float(p).is_integer() and float(q).is_integer()) else 24
    rng = np.random.default_rng(int(100 * p) + int(10 * q) + n)
    pd = rng.uniform(0.6, 0.99, n)
    pf = 10.0 ** rng.uniform(-45.0, -35.0, n)
    band = preferential_threshold(n, 0.01, 0.05, p, q, encoding)
    low, high = band.threshold_initial, band.threshold_final
    ours = preferential_error_rates(pd, pf, p, q, encoding, low, high)
    ref = reference(pd, pf, p, q, encoding, low, high)
    assert_matches(ours, ref)
    with mp.workdps(DPS):
        assert mp.log10(ref["p_false_alarm"]) < (-2000 if n == 60 else -800)


def test_beyond_the_exact_budget_the_rate_stays_named_without_a_log(monkeypatch):
    """Where the extended-exponent DP would exceed its budget the rate keeps the fast DP's
    answer: named below 1e-300, log None (docs/numerical-core.md says so) -- never 0 read as
    impossible."""
    from fusion_center.core import extended_dp

    monkeypatch.setattr(extended_dp, "EXACT_WORK_MAX", 0)
    for encoding, p, q in (("pm1", 0.3169778809467432, 1.4445044222254704),
                           ("01", 0.7362069775690239, 1.1216956018196342)):
        band = preferential_threshold(14, 0.01, 0.05, p, q, encoding)
        ours = preferential_error_rates(0.93, 1e-45, p, q, encoding, band.threshold_initial, band.threshold_final, n=14)
        assert ours.log_p_false_alarm is None and "p_false_alarm" in ours.below_floor


# a rate the tilted DP cannot certify: p = q = 0, so U_G = 2 K - n (K present taxels), and the
# band [-0.725, -0.0051) of xi = 0.3, alpha = 0.48 at n = 6 makes a false alarm K >= 3
COUNT_CASE = ("--rule", "preferential", "--u=1,1,1,1,1,1", "--p", "0", "--q", "0", "--xi", "0.3", "--alpha", "0.48",
              "--pd", "0.93", "--pf", "1e-45")


def binomial_tail_log(n: int, k: int, pi: float) -> float:
    with mp.workdps(DPS):
        x = mp.mpf(pi)
        return float(mp.log(mp.fsum(mp.binomial(n, j) * x**j * (1 - x) ** (n - j) for j in range(k, n + 1))))


def test_a_rate_with_a_failed_error_bound_is_recomputed(capsys):
    """The tilted DP's P_F here carries a proven bound of ~1e26 (relative): it was reported anyway,
    ln P_F = -308.546 where the binomial tail sum_(K >= 3) C(6, K) pf^K (1 - pf)^(6 - K) gives
    -307.853 (a factor 2 off, above 1e-300, nothing named). Now recomputed exactly."""
    rec = fuse_json(capsys, *COUNT_CASE)
    assert rec["rates_method"] == "integer" and -2.0 < rec["threshold_initial"] < rec["threshold_final"] <= 0.0
    assert abs(rec["log_p_false_alarm"] - binomial_tail_log(6, 3, 1e-45)) <= 1e-12 + 1e-13 * 307.9
    assert abs(rec["log_p_detect"] - binomial_tail_log(6, 3, 0.93)) <= 1e-12
    assert "rates_below_1e-300" not in rec and "rates_error_bound_log10" not in rec


def test_fuse_names_a_rate_whose_bound_stays_loose(capsys, monkeypatch):
    """Beyond the exact DP's budget the tilted value stays, and fuse names it with log10 of its
    proven relative error bound instead of passing it off as exact."""
    from fusion_center.core import extended_dp

    monkeypatch.setattr(extended_dp, "EXACT_WORK_MAX", 0)
    rec = fuse_json(capsys, *COUNT_CASE)
    assert list(rec["rates_error_bound_log10"]) == ["p_false_alarm"]
    assert rec["rates_error_bound_log10"]["p_false_alarm"] > -13


@pytest.mark.parametrize("encoding, p, q", [("pm1", 1.0, 0.5), ("pm1", 0.3169778809467432, 1.4445044222254704),
                                            ("01", 0.7362069775690239, 1.1216956018196342)])
@pytest.mark.parametrize("edge", [1e17, 1e100, 1e300, 1.7e308])
def test_band_edges_far_beyond_reach(encoding, p, q, edge):
    """Band edges far beyond any U_G (+-1e17 .. +-1.7e308): the exact threshold search walked
    from a float estimate off by ~edge * 1e-16 units, one unit a step (1e100: ~1e84 steps, a
    hang); now clamped to x's reach. Every vector is then on one side: the rates are 0 or 1,
    against the reference."""
    rng = np.random.default_rng(int(math.log10(edge)))
    pd, pf = rng.uniform(0.05, 0.95, 7), rng.uniform(0.05, 0.95, 7)
    for low, high in ((-edge, edge), (edge, edge), (-edge, -edge), (-edge, 0.5)):
        ours = preferential_error_rates(pd, pf, p, q, encoding, low, high)
        assert_matches(ours, reference(pd, pf, p, q, encoding, low, high))
