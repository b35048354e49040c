"""The steps of the tilted DP as in-place operations on (merged) state rows
(fusion_center/core/tilted_steps.py): the plans' invariants, and the law the DP returns
(tilted_dp.lattice_law_rows) against all 2^n decision vectors and against an untrimmed
log-domain DP, untilted, tilted, with the tilted arithmetic forced early, and bridge-trimmed."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from fusion_center.core import tilted_dp
from fusion_center.core.chain_dp import _lattice, _term
from fusion_center.core.tilted_steps import MERGED, build_plan, merged_bs, state_keys

# every kind of lattice form: chain with one and with three start labels, one zero weight
# (both b merged), integer on {0,1} (b = 0 merged) and on {-1,+1}
FORMS = [("pm1", 1.0, 1.0), ("pm1", 1.3, 0.2), ("pm1", 0.0, 1.5), ("pm1", 0.7, 0.0), ("pm1", 0.0, 0.0),
         ("pm1", 2.0, 1.0), ("01", 1.0, 1.0), ("01", 2.0, 0.0), ("01", 1.0, 2.0), ("01", 0.0, 0.0)]


@pytest.mark.parametrize("encoding,p,q", FORMS)
def test_plans_cover_every_transition_once_and_stay_in_range(encoding, p, q):
    """Each new row sums exactly the transitions into it; an in-place accumulator is an
    unmoved term read by no later row; spares are distinct; every added weight is <= 1 (the
    heaviest term first) for either sign of the tilt."""
    lat = _lattice(p, q, encoding)
    merged = merged_bs(lat.shift)
    for b in merged:  # merged only where both states move alike
        assert all(lat.shift[0, b, c] == lat.shift[1, b, c] for c in (0, 1))
    mid = state_keys(merged)
    last = [(a, b) for a in (0, 1) for b in (0, 1)]
    for out_keys in (mid, last):
        for sign in (-1, 0, 1):
            plan = build_plan(lat.shift, mid, out_keys, sign)
            assert sorted(k for k, *_ in plan) == sorted(out_keys)
            spares = [acc[1] for _, _, _, acc, _ in plan if acc[0] == "spare"]
            assert len(spares) == len(set(spares))
            for pos, (key, c, s_ref, acc, ops) in enumerate(plan):
                # the transitions into this row, from the unmerged states
                want = sorted((a, b, int(lat.shift[a, b, c])) for a in (0, 1) for b in (0, 1)
                              if (key[0] == MERGED or key[0] == b))
                got = []
                terms = [(acc[1], 0)] if acc[0] == "in" else []
                terms += [(ik, s) for kind, ik, s, d in ops]
                for ik, s in terms:
                    got += [(a, ik[1], s) for a in ((0, 1) if ik[0] == MERGED else (ik[0],))]
                assert sorted(got) == want, (key, got, want)
                if acc[0] == "in":
                    assert all(ik != acc[1] for _, _, _, _, later in plan[pos + 1:] for _, ik, _, _ in later)
                    assert all(ik != acc[1] for later in plan[pos + 1:] if later[3][0] == "in" for ik in [later[3][1]])
                    assert s_ref == 0 and all(d == s for kind, ik, s, d in ops)
                else:
                    assert ops[0][0] == "copy" and ops[0][3] == 0 and s_ref == ops[0][2]
                for kind, ik, s, d in ops:
                    assert sign * d <= 0 and d == s - s_ref


def _law_by_brute_force(pi, lat):
    """{(a, b, ls, x): P} over all 2^n vectors, x the lattice coordinate before the last
    taxel's term (the rows of lattice_law_rows), (a, b) the last two decisions; the step of an
    inner taxel from its eq 7 term (chain_dp._term) in units of the lattice's unit."""
    n = len(pi)
    out: dict = {}
    for u in itertools.product((0, 1), repeat=n):
        prob = math.prod(pi[i] if u[i] else 1.0 - pi[i] for i in range(n))
        steps, ls = lat.start[u[0]][u[1]]
        x = steps
        for i in range(1, n - 1):
            x += int(lat.shift[u[i - 1], u[i], u[i + 1]])
        key = (u[-2], u[-1], ls, x)
        out[key] = out.get(key, 0.0) + prob
    return out


def _rows_law(rows, log_scale, theta_out):
    law = {}
    for a, b, ls, x_first, arr in rows:
        for j in np.flatnonzero(arr):
            x = x_first + int(j)
            law[(a, b, ls, x)] = math.log(arr[j]) + log_scale - theta_out * x
    return law


@pytest.mark.parametrize("encoding,p,q", FORMS)
def test_law_rows_vs_all_vectors(encoding, p, q):
    """n = 11, random per-taxel probabilities, tilts 0 and +-0.7, nothing trimmed: every atom of
    (last two decisions, start label, x) to 1e-12 relative, none missing, none invented."""
    rng = np.random.default_rng(hash((encoding, p, q)) % 2**32)
    lat = _lattice(p, q, encoding)
    n = 11
    pi = rng.uniform(0.05, 0.95, n)
    pi_l = pi[::-1] if lat.reverse else pi
    ref = _law_by_brute_force(pi_l, lat)
    # the lattice's own steps agree with eq 7 (the brute force uses them): checked on one vector
    assert _term(1, 1, 1, lat.p, lat.q, encoding) is not None
    for theta in (0.0, 0.7, -0.7):
        rows, log_scale, theta_out, eps = tilted_dp.lattice_law_rows(pi_l, lat, theta, trim=1e-300)
        got = _rows_law(rows, log_scale, theta_out)
        assert eps == 0.0
        assert set(got) == {k for k, v in ref.items() if v > 0.0}
        for key, log in got.items():
            assert abs(log - math.log(ref[key])) <= 1e-12, (theta, key, log, math.log(ref[key]))


def _log_law_reference(pi, lat):
    """The same law by an untrimmed DP in the log domain (np.logaddexp), unmerged states:
    {(a, b, ls): (x_first, ln P array)}."""
    n = len(pi)
    smin, smax = int(lat.shift.min()), int(lat.shift.max())
    st = [lat.start[a][b][0] for a in (0, 1) for b in (0, 1)]
    x0 = min(st) + (n - 2) * smin
    size = max(st) + (n - 2) * smax - x0 + 1
    nl = len(lat.start_labels)
    lp, lq = np.log(pi), np.log1p(-np.asarray(pi))
    L = np.full((2, 2, nl, size), -np.inf)
    for a in (0, 1):
        for b in (0, 1):
            steps, ls = lat.start[a][b]
            first_two = (lp[0] if a else lq[0]) + (lp[1] if b else lq[1])
            L[a, b, ls, steps - x0] = np.logaddexp(L[a, b, ls, steps - x0], first_two)
    for i in range(2, n):
        new = np.full_like(L, -np.inf)
        for a in (0, 1):
            for b in (0, 1):
                for c in (0, 1):
                    s = int(lat.shift[a, b, c])
                    moved = np.full((nl, size), -np.inf)
                    if s >= 0:
                        moved[:, s:] = L[a, b, :, :size - s]
                    else:
                        moved[:, :s] = L[a, b, :, -s:]
                    new[b, c] = np.logaddexp(new[b, c], moved + (lp[i] if c else lq[i]))
        L = new
    return {(a, b, ls, x0 + j): L[a, b, ls, j] for a in (0, 1) for b in (0, 1) for ls in range(nl)
            for j in np.flatnonzero(np.isfinite(L[a, b, ls]))}


@pytest.mark.parametrize("encoding,p,q", FORMS)
@pytest.mark.parametrize("mode", ["tilted-law", "tilted-arithmetic", "chunked", "bridge"])
def test_law_rows_vs_log_domain_reference(encoding, p, q, mode, monkeypatch):
    """n = 90 (several blocks and renaming cycles), skewed per-taxel probabilities, a tilt towards
    a far tail, against the untrimmed log-domain DP. "tilted-law" (trimmed by the tilted law):
    each atom's share of the tilted mass within the run's error sum eps (trimming takes mass
    from the window's edges) plus 1e-12 of itself, and the mass dropped within eps.
    "tilted-arithmetic": SPAN_MAX 0, so the steps switch to the tilted arithmetic (ratios of tilts
    by daxpy) after the first block, nothing trimmed: every atom to 1e-12 relative. "bridge":
    trimmed by the bridge bounds for a region beyond the tilted mean: its mass to 1e-12
    relative plus the run's own (absolute) error bound. "chunked": as "tilted-arithmetic" with
    every daxpy split into pieces of 5 elements (tilted_steps.AXPY_CHUNK)."""
    if mode == "chunked":
        from fusion_center.core import tilted_steps

        monkeypatch.setattr(tilted_steps, "AXPY_CHUNK", 5)
        mode = "tilted-arithmetic"
    if mode == "tilted-arithmetic":
        monkeypatch.setattr(tilted_dp, "SPAN_MAX", 0.0)
    rng = np.random.default_rng(hash((encoding, p, q, mode)) % 2**32)
    lat = _lattice(p, q, encoding)
    n = 90
    pi = rng.uniform(0.001, 0.05, n) if mode != "bridge" else rng.uniform(0.6, 0.99, n)
    pi_l = pi[::-1] if lat.reverse else pi
    ref = _log_law_reference(pi_l, lat)
    xs = np.array([k[3] for k in ref])
    logs = np.array(list(ref.values()))
    theta = min(1.5, 0.8 * tilted_dp.theta_max(lat)) * (1 if mode != "bridge" else -1)
    lt = logs + theta * xs
    top = float(lt.max())
    total = float(np.exp(lt - top).sum())
    share = {k: math.exp(v + theta * k[3] - top) / total for k, v in ref.items()}
    if mode == "bridge":
        w = np.exp(lt - top)
        mean = float((w * xs).sum() / w.sum())
        sd = math.sqrt(float((w * (xs - mean) ** 2).sum() / w.sum()))
        edge = int(math.floor(mean - 2.0 * sd))  # the region: final x <= edge
        rows, log_scale, theta_out, errs = tilted_dp.lattice_law_rows(pi_l, lat, theta,
                                                                      bridge=([(None, edge)], max(sd, 1.0)))
        got = _rows_law(rows, log_scale, theta_out)
        end = {(a, b): lat.end[a][b][0] for a in (0, 1) for b in (0, 1)}
        mass = [v for k, v in got.items() if k[3] + end[k[:2]] <= edge]
        want = [v for k, v in ref.items() if k[3] + end[k[:2]] <= edge]
        from scipy.special import logsumexp
        m_got, m_ref = float(logsumexp(mass)), float(logsumexp(want))
        bound = math.exp(errs[0] - m_ref) if errs[0] > -math.inf else 0.0
        assert abs(math.expm1(m_got - m_ref)) <= 1e-12 + bound, (m_got, m_ref, bound)
        assert bound < 1e-10
        return
    trim = 1e-300 if mode == "tilted-arithmetic" else tilted_dp.TRIM_REL
    rows, log_scale, theta_out, eps = tilted_dp.lattice_law_rows(pi_l, lat, theta, trim)
    if mode == "tilted-arithmetic":
        assert theta_out == theta  # the switch happened
    got = _rows_law(rows, log_scale, theta_out)
    assert got, "no atoms kept"
    for key, log in got.items():
        assert key in ref, key
        err = abs(math.expm1(log - ref[key]))
        if mode == "tilted-arithmetic":
            assert err <= 1e-12, (key, log, ref[key])
        else:
            assert err * share[key] <= eps + 1e-12 * share[key], (key, log, ref[key], eps)
    missing = 1.0 - sum(share[k] for k in got)
    assert missing <= eps + 1e-12, (missing, eps)
