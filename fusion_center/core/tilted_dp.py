"""The lattice DP over the chain (eq 7) with exponential tilting: exact band rates (eq 20) of
the preferential rule down to any depth, as natural logarithms.

Where U_G = unit * x + start label + end label with x an integer (:mod:`.chain_dp`), the law
of x follows from a DP along the chain whose state is (u_(i-1), u_i) and the start label: an
array over x per state. A rate far in a tail (1e-5000 is ordinary at n = 10^4 under H0) has
no representable probability, and the columns that lead to it are far from the bulk. The DP
is therefore run on the tilted law

    P_theta(x) = P(x) e^(theta x) / Z(theta),      Z(theta) = E[e^(theta x)],

(every transition that moves x by s weighted by e^(theta s), a product weight, so the DP is
the same), with theta chosen so that E_theta[x] lies at the region's edge nearest the bulk
(Lambda'(theta) = t, Lambda = ln Z, the saddle point of the Chernoff bound). There the region
holds a fair share of the tilted mass, the window of x that matters is the tilted bulk (a
few dozen standard deviations, O(sqrt n) columns), and the rate comes back exactly as

    ln P(R) = logsumexp over x in R of (ln P_theta(x) - theta x) + ln Z(theta).

Lambda(theta) is ln (v M_2 ... M_(n-1) w) with 4 x 4 transfer matrices, multiplied pairwise
in numpy (log2 n levels, normalised per level). theta = 0 for a region that holds the bulk.
Probabilities are carried scaled by powers of two (the largest column at ~2^SCALE_BITS) and
each step's largest transition weight goes into an exact-sum logarithm, so nothing underflows.

Trimming and the error bound. Every TRIM_EVERY taxels the columns on either side of the window
below ``trim`` times the largest column are dropped; ``eps`` sums the dropped fraction of the
tilted mass. A state's future tilted weight differs from another's by at most e^G, G = |theta|
(2 dS + 2 dE) (dS, dE: spread of an inner / end step; a state's bits enter two terms), so
the dropped mass changes P_theta(R) by at most eps e^G of the total, and the relative error of
P(R) is at most

    eps e^G max_{x in R} e^(-theta x) / sum_{x in R} P_theta(x) e^(-theta x)

(R's reachable x, in the tilted total's units) -- computed for every rate and returned
(``error_bound``); trim = 1e-40 e^(-G) keeps it below ~1e-25 in every case tested. The region
that holds the bulk is 1 minus the other two (log1p, exact) when those sum to <= 1/2.
"""

from __future__ import annotations

import math

import numpy as np

from .chain_dp import SCALE_BITS, TRIM_EVERY, _first_at_least, _label_base, _Lattice, _x_range

__all__ = ["lattice_band_logs", "lattice_law_rows", "log_partition", "tilt_for_mean"]

_LN2 = math.log(2.0)
TRIM_REL = 1e-40
"""Columns below TRIM_REL e^(-G) of the largest are trimmed (module doc)."""
BOUND_OK = -15.0
"""log10 of the relative error bound accepted from a shared tilted run."""
G_MAX = 400.0
"""|theta| is capped so that G <= G_MAX (the trim threshold stays a normal double)."""


# ------------------------------------------------------------------ Lambda(theta)
def _spreads(lat: _Lattice) -> tuple[int, int]:
    starts = [lat.start[a][b][0] for a in (0, 1) for b in (0, 1)]
    ends = [lat.end[a][b][0] for a in (0, 1) for b in (0, 1)]
    ds = int(lat.shift.max() - lat.shift.min())
    return max(ds, 1), max(ends) - min(ends) + max(starts) - min(starts)


def theta_max(lat: _Lattice) -> float:
    ds, de = _spreads(lat)
    return G_MAX / (2.0 * ds + 2.0 * de + 1.0)


def log_partition(pi: np.ndarray, lat: _Lattice, thetas) -> np.ndarray:
    """Lambda(theta) = ln E[e^(theta x)] for each theta (x: the lattice coordinate including the
    first and last taxels' steps), from the product of the chain's transfer matrices
    (state (u_(i-1), u_i)), multiplied pairwise and normalised per level."""
    thetas = np.atleast_1d(np.asarray(thetas, float))
    n = pi.size
    k = thetas.size
    prob = np.stack([1.0 - pi, pi], axis=-1)
    v = np.zeros((k, 4))
    w = np.zeros((k, 4))
    for a in (0, 1):
        for b in (0, 1):
            v[:, 2 * a + b] = prob[0, a] * prob[1, b] * np.exp(thetas * lat.start[a][b][0])
            w[:, 2 * a + b] = np.exp(thetas * lat.end[a][b][0])
    log_acc = np.zeros(k)
    if n > 2:
        m = np.zeros((k, n - 2, 4, 4))
        for a in (0, 1):
            for b in (0, 1):
                for c in (0, 1):
                    m[:, :, 2 * a + b, 2 * b + c] = prob[None, 2:, c] * np.exp(thetas[:, None] * float(lat.shift[a, b, c]))
        while m.shape[1] > 1:
            if m.shape[1] % 2:
                m = np.concatenate([m, np.broadcast_to(np.eye(4), (k, 1, 4, 4))], axis=1)
            m = m[:, 0::2] @ m[:, 1::2]
            top = m.max(axis=(2, 3))
            m /= top[:, :, None, None]
            log_acc += np.log(top).sum(axis=1)
        vw = np.einsum("ki,kij,kj->k", v, m[:, 0], w)
    else:
        vw = np.einsum("ki,ki->k", v, w)
    with np.errstate(divide="ignore"):
        return np.log(vw) + log_acc


def tilt_for_mean(pi: np.ndarray, lat: _Lattice, target: float, mean: float) -> float:
    """theta with Lambda'(theta) = target (within two tilted standard deviations), by Newton's
    method safeguarded by bisection on [0, theta_max] (or its mirror); Lambda' and Lambda''
    by central differences. theta_max where the target is out of reach."""
    sign = 1.0 if target > mean else -1.0
    lo, hi = 0.0, theta_max(lat)
    theta = min(hi, 1.0)
    at_max = False
    for _ in range(60):
        h = 1e-3
        lam = log_partition(pi, lat, sign * np.array([theta - h, theta, theta + h]))
        d1 = sign * (lam[2] - lam[0]) / (2 * h)  # Lambda'(sign theta)
        d2 = max((lam[2] - 2 * lam[1] + lam[0]) / (h * h), 1e-12)
        if abs(d1 - target) <= max(1.0, 2.0 * math.sqrt(d2)):
            return sign * theta
        if sign * (d1 - target) < 0:
            lo = theta
        else:
            hi = theta
        step = theta - sign * (d1 - target) / d2
        if step >= hi and not at_max:
            theta, at_max = hi, True  # out of reach? try the cap once
            continue
        if at_max and theta == hi and sign * (d1 - target) < 0:
            return sign * theta
        theta = step if lo < step < hi else 0.5 * (lo + hi)
        if hi - lo < 1e-9 * max(1.0, hi):
            break
    return sign * theta


# ------------------------------------------------------------------ the DP
def lattice_law_rows(pi: np.ndarray, lat: _Lattice, theta: float = 0.0, trim: float | None = None,
                     trim_abs: float | None = None):
    """The tilted law of (u_(n-1), u_n, start label, x) for n = pi.size >= 2 taxels:
    (rows, log_scale, eps) with rows = [(a, b, ls, x_first, stored array over x)], x the lattice
    coordinate before the last taxel's term, and P_theta-mass * Z(theta) = stored e^(log_scale)
    e^(-theta x) ... precisely: P(x, state) = stored e^(log_scale - theta x). ``trim``: relative
    (module doc; default TRIM_REL e^(-G)), eps = the dropped fraction (summed); ``trim_abs``
    (theta = 0 only): drop columns of probability below it instead, eps = dropped probability.

    One step per taxel: Y[b, c] = P(c) (e^(theta s0) X[0, b] moved by s0 + e^(theta s1) X[1, b]
    moved by s1), s_a = shift[a, b, c], one vector addition per group of (b, c) with the same
    shifts and one multiplication per decision branch; the weights of a step are divided by
    their largest (its log goes into log_scale)."""
    n = pi.size
    shift = lat.shift
    smin, smax = int(shift.min()), int(shift.max())
    ds, de = _spreads(lat)
    g = abs(theta) * (2.0 * ds + 2.0 * de)
    if trim is None and trim_abs is None:
        trim = TRIM_REL * math.exp(-g)
    st = [lat.start[a][b][0] for a in (0, 1) for b in (0, 1)]
    xmin = min(st) + (n - 2) * smin
    pad = smax - smin + 2
    n_labels = len(lat.start_labels)
    # the window can only move by smin / smax per step: the buffer spans the reachable range
    size = max(st) - min(st) + (n - 2) * (smax - smin) + 1 + 2 * pad
    buffers = (np.zeros((2, 2, n_labels, size)), np.zeros((2, 2, n_labels, size)))
    x0 = buffers[0]
    lo, hi = size, 0
    first = []
    for a in (0, 1):
        for b in (0, 1):
            steps, label = lat.start[a][b]
            first.append((a, b, label, steps - xmin + pad,
                          math.log(pi[0] if a else 1.0 - pi[0]) if (pi[0] if a else 1.0 - pi[0]) > 0 else -math.inf,
                          math.log(pi[1] if b else 1.0 - pi[1]) if (pi[1] if b else 1.0 - pi[1]) > 0 else -math.inf,
                          steps))
    top = max(la + lb + theta * s for *_, la, lb, s in first)
    for a, b, label, j, la, lb, s in first:
        if la + lb > -math.inf:
            x0[a, b, label, j] += math.ldexp(math.exp(la + lb + theta * s - top), SCALE_BITS)
            lo, hi = min(lo, j), max(hi, j + 1)
    log_parts = [top]  # log_scale = sum(log_parts) - exponent ln 2
    exponent = SCALE_BITS
    eps = 0.0
    # per step i: weight of branch c from state (a, b) = P_i(c) e^(theta shift[a, b, c]) / wmax_i
    groups = []
    for c in (0, 1):
        if shift[0, 0, c] == shift[0, 1, c] and shift[1, 0, c] == shift[1, 1, c]:
            groups.append((slice(None), c, int(shift[0, 0, c]), int(shift[1, 0, c])))
        else:
            groups.extend((b, c, int(shift[0, b, c]), int(shift[1, b, c])) for b in (0, 1))
    # the factor applied to dest[b, c] after the group sum: P(c) e^(theta s0) / wmax; the
    # group sum carries X[1, b] times e^(theta (s1 - s0)) (a constant)
    with np.errstate(divide="ignore"):
        logp = (np.log1p(-pi), np.log(pi))
    smax_c = [max(int(shift[a, b, c]) for a in (0, 1) for b in (0, 1)) for c in (0, 1)]
    smin_c = [min(int(shift[a, b, c]) for a in (0, 1) for b in (0, 1)) for c in (0, 1)]
    best_c = [logp[c] + theta * (smax_c[c] if theta >= 0 else smin_c[c]) for c in (0, 1)]
    log_wmax = np.maximum(best_c[0], best_c[1])
    log_parts.append(math.fsum(log_wmax[2:].tolist()))
    cum_wmax = np.cumsum(log_wmax)  # for the absolute trimming threshold only
    s0_of = {(b, c): int(shift[0, b, c]) for b in (0, 1) for c in (0, 1)}
    factors = {}
    for c in (0, 1):
        s0s = {s0_of[(0, c)], s0_of[(1, c)]}
        keys = [(None, s) for s in s0s] if len(s0s) == 1 else [(b, s0_of[(b, c)]) for b in (0, 1)]
        for b, s0 in keys:
            f = np.exp(logp[c] + theta * s0 - log_wmax)
            factors[(b, c)] = f.tolist()
    ratios = [math.exp(theta * (s1 - s0)) for _, _, s0, s1 in groups]
    parity = 0
    for start in range(2, n, TRIM_EVERY):
        steps = min(n, start + TRIM_EVERY) - start
        lo, hi = lo + smin * steps, hi + smax * steps
        views = []
        for par in (0, 1):
            source, dest = buffers[par], buffers[1 - par]
            adds = [(source[0, b, :, lo - s0:hi - s0], source[1, b, :, lo - s1:hi - s1], dest[b, c, :, lo:hi], r)
                    for (b, c, s0, s1), r in zip(groups, ratios)]
            mults = [(dest[b, c, :, lo:hi] if b is not None else dest[:, c, :, lo:hi], f)
                     for (b, c), f in factors.items()]
            views.append((adds, mults))
        for i in range(start, start + steps):
            adds, mults = views[parity]
            for in0, in1, out, r in adds:
                if r == 1.0:
                    np.add(in0, in1, out=out)
                else:
                    np.multiply(in1, r, out=out)
                    out += in0
            for out, f in mults:
                fi = f[i]
                if fi != 1.0:
                    out *= fi
            parity = 1 - parity
        live = buffers[parity][:, :, :, lo:hi]
        cols = live.sum(axis=(0, 1, 2))
        peak = float(cols.max())
        if peak == 0.0:
            break
        k = math.frexp(peak)[1] - SCALE_BITS - 1
        if k:
            live *= math.ldexp(1.0, -k)
            cols *= math.ldexp(1.0, -k)
            peak = math.ldexp(peak, -k)
            exponent -= k
        if hi - lo > 8:
            if trim_abs is not None:  # theta = 0: stored = probability 2^exponent / e^(sum log_wmax so far)
                scale = math.exp(exponent * _LN2 - float(cum_wmax[start + steps - 1] - cum_wmax[1]) - log_parts[0])
                threshold = trim_abs * scale
            else:
                threshold = trim * peak
            keep = np.flatnonzero(cols >= threshold)
            f0, l0 = (int(keep[0]), int(keep[-1]) + 1) if keep.size else (0, 0)
            if f0 or l0 < hi - lo:
                dropped = float(cols[:f0].sum() + cols[l0:].sum())
                eps += dropped / scale if trim_abs is not None else dropped / float(cols.sum())
                for arr in buffers:
                    arr[:, :, :, lo:lo + f0] = 0.0
                    arr[:, :, :, lo + l0:hi] = 0.0
                lo, hi = lo + f0, lo + l0
    x_law = buffers[parity]
    rows = []
    for a in (0, 1):
        for b in (0, 1):
            for ls in range(n_labels):
                row = x_law[a, b, ls, lo:hi]
                if row.any():
                    rows.append((a, b, ls, lo - pad + xmin, row.copy()))
    return rows, math.fsum(log_parts) - exponent * _LN2, eps


def _logsumexp(values) -> float:
    values = [v for v in values if v > -math.inf]
    if not values:
        return -math.inf
    top = max(values)
    return top + math.log(math.fsum(math.exp(v - top) for v in values))


def _region_logs(rows, lat: _Lattice, edges: dict, theta: float, log_scale: float, eps: float,
                 x_reach: tuple[int, int]):
    """Per region (U >= high, low <= U < high, U < low): (ln P, log10 of the relative error
    bound) from the rows of a tilted run (module doc)."""
    parts = [[], [], []]
    total = []
    x_ref = rows[0][3] if rows else 0  # e^(-theta x) = e^(-theta x_ref) e^(-theta (x - x_ref))
    worst_untilt = [-math.inf] * 3
    for a, b, ls, x_first, arr in rows:
        e_steps, le = lat.end[a][b]
        t_low, t_high = edges[(ls, le)]
        x = (x_first - x_ref) + np.arange(arr.size)
        with np.errstate(divide="ignore"):
            lv = np.log(arr) - theta * x
        total.append(math.log(float(arr.sum())))
        # region index ranges on x (x + e_steps is the final coordinate)
        i_low = min(max(t_low - e_steps - x_first, 0), arr.size)
        i_high = min(max(t_high - e_steps - x_first, 0), arr.size)
        for r, (s, e) in enumerate(((i_high, arr.size), (i_low, max(i_low, i_high)), (0, i_low))):
            if e > s:
                seg = lv[s:e]
                top = float(seg.max())
                if top > -math.inf:
                    parts[r].append(top + math.log(float(np.exp(seg - top).sum())))
    # the largest untilt factor e^(-theta x) over each region's reachable x (every row's end label)
    xa, xb = x_reach
    for a in (0, 1):
        for b in (0, 1):
            e_steps, le = lat.end[a][b]
            for ls in range(len(lat.start_labels)):
                t_low, t_high = edges[(ls, le)]
                for r, (s, e) in enumerate(((t_high, xb + 1), (t_low, t_high), (xa, t_low))):
                    s, e = max(s, xa), min(e, xb + 1)
                    if e > s:
                        worst_untilt[r] = max(worst_untilt[r], -theta * (s - e_steps - x_ref),
                                              -theta * (e - 1 - e_steps - x_ref))
    log_total = _logsumexp(total)
    ds, de = _spreads(lat)
    g = abs(theta) * (2.0 * ds + 2.0 * de)
    out = []
    for r in range(3):
        log_sum = _logsumexp(parts[r])
        if eps == 0.0:
            bound = -math.inf
        elif log_sum == -math.inf:
            bound = math.inf
        else:
            bound = (math.log(eps) + g + log_total + worst_untilt[r] - log_sum) / math.log(10.0)
        out.append(((log_scale - theta * x_ref) + log_sum, bound))
    return out


def lattice_band_logs(pi: np.ndarray, lat: _Lattice, low: float, high: float, only=(0, 1, 2)):
    """Per region (U_G >= high, low <= U_G < high, U_G < low): (ln P, or -inf for an
    impossible event; log10 of the relative error bound), for one hypothesis (taxels present
    with probabilities ``pi``), n = pi.size >= 2, eq 7 and the eq 20 band. ``only``: the
    regions wanted (the others come back None)."""
    p, q = lat.p, lat.q
    if lat.reverse:
        pi = pi[::-1]
    n = pi.size
    pairs = [(ls, le) for ls in range(len(lat.start_labels)) for le in range(len(lat.end_labels))]
    edges = {key: (_first_at_least(lat, _label_base(lat, *key), low, p, q),
                   _first_at_least(lat, _label_base(lat, *key), high, p, q)) for key in pairs}
    xa, xb = _x_range(lat, n)
    # per region and label pair the reachable integer interval [s, e) of the final x
    intervals = [[(max(t_high, xa), xb + 1) for t_low, t_high in edges.values()],
                 [(max(t_low, xa), min(t_high, xb + 1)) for t_low, t_high in edges.values()],
                 [(xa, min(t_low, xb + 1)) for t_low, t_high in edges.values()]]
    empty = [all(e <= s for s, e in iv) for iv in intervals]
    h = 1e-3
    lam = log_partition(pi, lat, [-h, h])
    mean = float((lam[1] - lam[0]) / (2 * h))
    targets = []
    for r, iv in enumerate(intervals):
        live = [(s, e) for s, e in iv if e > s]
        if empty[r] or any(s <= mean <= e - 1 for s, e in live):
            targets.append(None)  # the bulk: theta = 0
        else:
            ends = [s for s, e in live] + [e - 1 for s, e in live]
            targets.append(min(ends, key=lambda x: abs(x - mean)))
    runs: dict = {}

    def run(theta: float):
        if theta not in runs:
            rows, log_scale, eps = lattice_law_rows(pi, lat, theta)
            runs[theta] = _region_logs(rows, lat, edges, theta, log_scale, eps, (xa, xb))
        return runs[theta]

    out: list = [None, None, None]
    for r in range(3):
        if empty[r]:
            out[r] = (-math.inf, -math.inf)
    far = [r for r in range(3) if out[r] is None and targets[r] is not None and r in only]
    if len(far) == 2:
        # both tails on one side of the bulk (the band beyond it): one run tilted to the middle of
        # their near edges usually holds both (each checked by its bound), else one run each
        theta = tilt_for_mean(pi, lat, 0.5 * (targets[far[0]] + targets[far[1]]), mean)
        for r in far:
            if run(theta)[r][1] <= BOUND_OK:
                out[r] = run(theta)[r]
    for r in far:
        if out[r] is None:
            out[r] = run(tilt_for_mean(pi, lat, targets[r], mean))[r]
    bulk = [r for r in range(3) if out[r] is None]
    if len(bulk) == 1 and bulk[0] in only:
        others = [out[r][0] for r in range(3) if r != bulk[0]]
        rest = _logsumexp(others)
        if rest <= math.log(0.5):
            # 1 - (the other two): exact in relative terms where they are at most 1/2
            bound = max(out[r][1] for r in range(3) if r != bulk[0])
            out[bulk[0]] = (math.log1p(-math.exp(rest)), bound)
    for r in range(3):
        if out[r] is None and r in only:
            out[r] = run(0.0)[r]
    return [out[r] if r in only else None for r in range(3)]
