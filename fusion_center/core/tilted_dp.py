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

Trimming and the error bound. Every BLOCK taxels the columns on either side of the window
below TRIM_REL / S_i times the largest column are dropped, S_i the spread of the states' future
tilted weights after taxel i (max over states / min over states of h_i(state), the weight of
all continuations, from one backward pass: ``_future_spread``); eps sums each drop's fraction of
the tilted mass times S_i. The tilted mass so lost is at most eps of the final total, so the
relative error of P(R) is at most

    eps max_{x in R} e^(-theta x) / sum_{x in R} P_theta(x) e^(-theta x)

(R's reachable x, in units of the tilted total) -- computed for every rate and returned
(``error_bounds`` of :class:`.preferential_rates.PreferentialRates`, log10; ~1e-27 in
the cases tested). A run tilted between the two regions on one side of the bulk serves both
when both bounds are below 10^BOUND_OK, else each gets its own. The region that holds the
bulk is 1 minus the other two (log1p, exact) when those sum to at most 1/2.

Bridge trimming (from BRIDGE_MIN_TAXELS = 1000 taxels on; :mod:`.tilted_bridge`, its module
doc): a column x after i taxels matters only through the mass it can still carry into the
region R, bounded by Chernoff bounds on the rest of the chain; the window then shrinks like the
Brownian bridge from the start to the region's edge (~2 z sigma sqrt(i (n - i) / n) instead of
~2 z sigma sqrt(i)), and the sums dropped are the region's absolute error bound. One bridge run
serves both regions on one side of the bulk when their edges are closer than BRIDGE_SHARED
tilted standard deviations; farther apart, a run trimmed by the tilted law serves both if its
bound holds, else each region gets its own bridge run.

Cost: a run is O(n W) with W the window, O(sqrt n) columns (n = 10^4, the chapter's band,
trimmed by the tilted law: ~4800 columns at the end under H1, ~11000 under H0 for both far
regions in one run, means over the run 2/3 of that; bridge-trimmed, the mean window is ~0.65 of
the tilted-law one for both H0 regions in one run, ~0.5 for a run serving one region), plus
fixed costs of ~0.05-0.1 s per hypothesis at 10^4 (the tilt searches, the backward pass, the
trims). At 10^4 the DP's vector operations run at ~0.5-1.5 ns per element (the window sits in
the L2 cache): the time is the number of element passes. The steps (:mod:`.tilted_steps`)
carry merged states where two move alike (4 rows on the chain, 3 on {0,1}, 2 with one zero
weight), labels innermost (one contiguous run per state row), and accumulate each new row in
place (two copies, four in-place additions and about two multiplications per taxel on the
chain, tilted or not).
"""

from __future__ import annotations

import math

import numpy as np

from .chain_dp import _first_at_least, _label_base, _Lattice, _x_range
from .dp_scaling import _LOG_FLOOR, SCALE_BITS
from .tilted_bridge import BLOCK, _bridge_setup, _bridge_trim
from .tilted_steps import StepRunner
from .tilted_partition import BRIDGE_MIN_TAXELS, G_MAX, _spreads, _tilt_search, log_partition, theta_max, tilt_for_mean  # noqa: F401

# the bridge trimming and the block products / Chernoff suffix bounds moved to tilted_bridge;
# kept importable from here
from .tilted_bridge import BRIDGE_GRID, _suffix_logs  # noqa: F401

_REEXPORTED = (BRIDGE_GRID, _suffix_logs)

__all__ = ["lattice_band_logs", "lattice_law_rows", "lattice_law_tail_atoms", "log_partition", "tilt_for_mean"]

_LN2 = math.log(2.0)
TRIM_REL = 1e-32
SHRINK_MAX = 400.0
"""A block of tilted steps ends before the mass can shrink by more than e^SHRINK_MAX."""
SPAN_MAX = 1200.0
"""Natural-log span of the untilted values a window may hold before the arithmetic is tilted
(the doubles hold ~e^1330 below the largest column at 2^SCALE_BITS)."""
"""Columns below TRIM_REL / spread of the largest are trimmed (module doc)."""
BOUND_OK = -13.0
"""log10 of the relative error bound accepted from a shared tilted run."""
BRIDGE_REL = 1e-22
"""Bridge trimming: each trim drops, per region, columns whose bounds sum to at most BRIDGE_REL
times the region's Chernoff bound (the least over the grid of tilts)."""
BRIDGE_SHARED = 10.0
"""A bridge run serves both regions on one side of the bulk when their near edges are closer
than this many tilted standard deviations D (:mod:`.tilted_bridge`: mean window ~(7.9 +
D / 2) sigma against ~16 sigma trimmed by the tilted law and 2 x 7.9 sigma for two bridge
runs; measured at 10^4 taxels: D ~ 9 ({0,1} under H0) gains ~20 %, D ~ 12-13 ({-1,+1} under
H1) loses a little to the bridge's fixed costs, backward pass and trims, ~0.05-0.1 s)."""
BRIDGE_EVERY = 2
"""A bridge run trims at every BRIDGE_EVERY-th block end (a trim costs ~0.2 ms)."""


# ------------------------------------------------------------------ the DP
def _future_spread(pi: np.ndarray, lat: _Lattice, theta: float) -> list:
    """spread[i] = max over states / min over states of h_i(state), the tilted weight of all
    continuations after taxel i (x before the last taxel's term; h_(n-1) = 1): the factor by
    which mass dropped in one state can outweigh the same mass elsewhere (module doc)."""
    n = pi.size
    w = [math.exp(theta * float(lat.shift[a, b, c])) for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    w000, w001, w010, w011, w100, w101, w110, w111 = w
    h0 = h1 = h2 = h3 = 1.0  # h(a, b) at index 2 a + b
    spread = [1.0] * n
    pl = pi.tolist()
    for i in range(n - 1, 1, -1):  # h_(i-1) from h_i: taxel i is added from state (u_(i-2), u_(i-1))
        pc = pl[i]
        qc = 1.0 - pc
        n0 = qc * w000 * h0 + pc * w001 * h1
        n1 = qc * w010 * h2 + pc * w011 * h3
        n2 = qc * w100 * h0 + pc * w101 * h1
        n3 = qc * w110 * h2 + pc * w111 * h3
        top = max(n0, n1, n2, n3)
        low = min(n0, n1, n2, n3)
        h0, h1, h2, h3 = n0 / top, n1 / top, n2 / top, n3 / top
        spread[i - 1] = top / low if low > 0.0 else math.inf
    return spread


def lattice_law_rows(pi: np.ndarray, lat: _Lattice, theta: float = 0.0, trim: float = TRIM_REL,
                     bridge: tuple | None = None):
    """The law of (u_(n-1), u_n, start label, x) for n = pi.size >= 2 taxels, trimmed by its
    tilted law (module doc): (rows, log_scale, theta_out, eps) with rows = [(a, b, ls, x_first,
    stored array over x)], x the lattice coordinate before the last taxel's term, and

        P(x, state) = stored e^(log_scale - theta_out x),

    theta_out 0 while the arithmetic is untilted, theta once it is tilted. eps: the dropped
    fraction of the tilted mass times the future spread, summed (the error bound's numerator).

    One step per taxel: Y[b, c] = P(c) (X[0, b] moved by s0 + X[1, b] moved by s1), s_a =
    shift[a, b, c], as in-place vector operations on (merged) state rows (:mod:`.tilted_steps`)
    -- the untilted arithmetic, the cheapest. The window is trimmed by the tilted columns
    (untilted ones times e^(theta x), formed per block); once the window's untilted values would
    span more than the double range (far tails, large |theta| W), the columns are multiplied by
    e^(theta (x - x_c)) and the steps carry the tilt: each term times e^(theta s) relative to its
    row's heaviest (BLAS daxpy), P(c) e^(theta s_ref) in the branch factor, every step's
    weights divided by (about) their largest (its log goes into log_scale).

    ``bridge`` = (regions, sigma): trimmed by the bridge bounds instead (:mod:`.tilted_bridge`),
    regions a list of (x_low, x_high) on the final x (None: unbounded), sigma the scale of the
    grid of tilts (the tilted law's standard deviation); eps is then the list of the regions' ln
    absolute error bounds (-inf: nothing dropped)."""
    n = pi.size
    shift = lat.shift
    smin, smax = int(shift.min()), int(shift.max())
    if bridge is not None:
        regions, sigma = bridge
        bridge_state = _bridge_setup(pi, lat, theta, sigma, regions, BRIDGE_REL * trim / TRIM_REL)
        spread = None
    else:
        spread = _future_spread(pi, lat, theta)
    st = [lat.start[a][b][0] for a in (0, 1) for b in (0, 1)]
    xmin = min(st) + (n - 2) * smin
    pad = smax - smin + 2
    n_labels = len(lat.start_labels)
    # the window can only move by smin / smax per step: the buffer spans the reachable range
    size = max(st) - min(st) + (n - 2) * (smax - smin) + 1 + 2 * pad
    # the state rows, labels innermost (a state's window is one contiguous run of memory), and
    # the steps as in-place operations on them (tilted_steps)
    runner = StepRunner(lat, pi, size, n_labels)
    lo, hi = size, 0
    for a in (0, 1):
        for b in (0, 1):
            steps, label = lat.start[a][b]
            j = steps - xmin + pad
            runner.put(a, b, j, label, math.ldexp((pi[0] if a else 1.0 - pi[0]) * (pi[1] if b else 1.0 - pi[1]),
                                                  SCALE_BITS))
            lo, hi = min(lo, j), max(hi, j + 1)
    exponent = SCALE_BITS
    log_parts = []  # log_scale = fsum(log_parts) - exponent ln 2
    eps = 0.0
    tilted = False
    log_wmax, least = runner.arithmetic(0.0)
    wmax_from = 2  # log_wmax[wmax_from:] not yet in log_parts
    if bridge is not None:
        cum_wmax = np.concatenate([[0.0], np.cumsum(log_wmax)])  # for the trims' absolute logs
        errs = [-math.inf] * len(regions)
        bounds = bridge_state["bounds"]
        next_b = 1
    x_of = lambda j: j - pad + xmin  # noqa: E731  the x of buffer column j
    end = 2
    while end < n:
        start = end
        if bridge is not None:  # blocks end where the future's bounds are known
            while bounds[next_b] <= start:
                next_b += 1
            end = bounds[next_b]
        else:
            end = min(n, start + BLOCK)
        if tilted:
            shrink = 0.0
            for i in range(start, end):
                shrink += least[i]
                if shrink < -SHRINK_MAX:
                    end = max(i, start + 1)
                    break
        steps = end - start
        lo, hi = lo + smin * steps, hi + smax * steps
        runner.run(start, end, lo, hi)
        cols = runner.column_sums(lo, hi)
        peak = float(cols.max())
        if peak == 0.0:
            break
        k = math.frexp(peak)[1] - SCALE_BITS - 1
        if k:
            runner.scale(lo, hi, math.ldexp(1.0, -k))
            cols *= math.ldexp(1.0, -k)
            exponent -= k
        with np.errstate(divide="ignore"):
            log_cols = np.log(cols)
        if bridge is not None:
            if start + steps == bounds[next_b] and start + steps < n and next_b % BRIDGE_EVERY == 0:
                log_abs = (math.fsum(log_parts) + float(cum_wmax[start + steps] - cum_wmax[wmax_from])
                           - exponent * _LN2)
                f0, l0 = _bridge_trim(bridge_state, next_b, log_cols, log_abs, x_of(lo),
                                      theta if tilted else 0.0, errs)
                if f0 or l0 < hi - lo:
                    runner.zero(lo, lo + f0)
                    runner.zero(lo + l0, hi)
                    lo, hi = lo + f0, lo + l0
                    log_cols = log_cols[f0:l0]
        else:
            s_i = spread[start + steps - 1]
            if not tilted and theta != 0.0:
                log_t = log_cols + theta * np.arange(cols.size)  # tilted, up to a constant
            else:
                log_t = log_cols
            top = float(log_t.max())
            keep = np.flatnonzero(log_t >= top + math.log(trim / s_i))
            f0, l0 = int(keep[0]), int(keep[-1]) + 1
            if f0 or l0 < hi - lo:
                w = np.exp(log_t - top)
                eps += float(w[:f0].sum() + w[l0:].sum()) / float(w.sum()) * s_i
                runner.zero(lo, lo + f0)
                runner.zero(lo + l0, hi)
                lo, hi = lo + f0, lo + l0
                log_cols = log_cols[f0:l0]
        if not tilted and theta != 0.0 and start + steps < n:
            span = float(log_cols.max() - log_cols[np.isfinite(log_cols)].min()) if log_cols.size else 0.0
            if span + abs(theta) * (smax - smin) * 2 * BLOCK > SPAN_MAX:
                # to tilted arithmetic: stored_t = stored_u e^(theta (x - x_c)), x_c the window's
                # tilted peak, so P = stored_t e^(scale + theta x_c - theta x)
                j = np.arange(lo, hi)
                x_c = x_of(lo + int(np.argmax(log_cols + theta * np.arange(hi - lo))))
                with np.errstate(divide="ignore"):  # in logs: e^(theta dx) alone may overflow
                    logs = np.log(runner.window(lo, hi)) + theta * (x_of(j) - x_c)[None, :, None]
                m = float(logs.max()) - SCALE_BITS * _LN2
                runner.set_window(lo, hi, np.exp(logs - m))
                log_parts.append(math.fsum(log_wmax[wmax_from:start + steps].tolist()))
                log_parts.append(theta * x_c + m)
                log_wmax, least = runner.arithmetic(theta)
                wmax_from = start + steps
                tilted = True
                if bridge is not None:
                    cum_wmax = np.concatenate([[0.0], np.cumsum(log_wmax)])
    log_parts.append(math.fsum(log_wmax[wmax_from:].tolist()))
    rows = []
    for a in (0, 1):
        for b in (0, 1):
            for ls in range(n_labels):
                if (a, b) not in runner.keys:  # stopped early (no mass left): nothing to return
                    continue
                row = runner.row(a, b, ls, lo, hi)
                if row.any():
                    rows.append((a, b, ls, x_of(lo), row.copy()))
    return rows, math.fsum(log_parts) - exponent * _LN2, (theta if tilted else 0.0), (eps if bridge is None else errs)


def _logsumexp(values) -> float:
    values = [v for v in values if v > -math.inf]
    if not values:
        return -math.inf
    top = max(values)
    return top + math.log(math.fsum(math.exp(v - top) for v in values))


def _region_logs(rows, lat: _Lattice, edges: dict, theta: float, theta_out: float, log_scale: float,
                 eps: float, x_reach: tuple[int, int]):
    """Per region (U >= high, low <= U < high, U < low): (ln P, log10 of the relative error
    bound) from the rows of a run trimmed by the law tilted by ``theta`` (stored values carry
    e^(theta_out x): lattice_law_rows). With T = sum_x P(x) e^(theta x) the bound is
    eps T max_{x in R} e^(-theta x) / P(R) (module doc)."""
    parts = [[], [], []]
    total = []
    x_ref = rows[0][3] if rows else 0  # e^(-theta x) = e^(-theta x_ref) e^(-theta (x - x_ref))
    worst_untilt = [-math.inf] * 3
    for a, b, ls, x_first, arr in rows:
        e_steps, le = lat.end[a][b]
        t_low, t_high = edges[(ls, le)]
        x = (x_first - x_ref) + np.arange(arr.size)
        with np.errstate(divide="ignore"):
            lv = np.log(arr) - theta_out * x  # ln P(x) - log_scale + theta_out x_ref
        lt = lv + theta * x  # tilted, same offset
        top_t = float(lt.max())
        total.append(top_t + math.log(float(np.exp(lt - top_t).sum())))
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
    out = []
    for r in range(3):
        log_sum = _logsumexp(parts[r])
        if isinstance(eps, dict):  # a bridge run: ln absolute error bounds of its regions
            value = (log_scale - theta_out * x_ref) + log_sum
            err = eps.get(r, math.inf)
            bound = (-math.inf if err == -math.inf else math.inf if log_sum == -math.inf
                     else (err - value) / math.log(10.0))
            out.append((value, bound))
            continue
        if eps == 0.0:
            bound = -math.inf
        elif log_sum == -math.inf:
            bound = math.inf
        else:
            bound = (math.log(eps) + log_total + worst_untilt[r] - log_sum) / math.log(10.0)
        out.append(((log_scale - theta_out * x_ref) + log_sum, bound))
    return out


def _shared_run_may_hold(pi: np.ndarray, lat: _Lattice, theta: float, edges, moments=None) -> bool:
    """Whether a run tilted by ``theta`` can give every region whose near edge is in ``edges``
    an error bound below 10^BOUND_OK: False where the Gaussian approximation of the tilted law
    (mean and variance Lambda'(theta), Lambda''(theta)) puts an edge so far out that the predicted
    bound, eps ~ n / BLOCK * TRIM_REL over the tilted mass near the edge, misses 10^BOUND_OK by
    more than a factor 10^3. A prediction only (it saves a run that would fail its check);
    the result does not depend on it: every rate is checked against its proven bound."""
    if moments is None:
        h = 1e-3
        lam = log_partition(pi, lat, [theta - h, theta, theta + h])
        moments = float((lam[2] - lam[0]) / (2 * h)), max(float((lam[2] - 2 * lam[1] + lam[0]) / (h * h)), 1e-12)
    mean, var = moments
    log_eps = math.log(max(pi.size / BLOCK, 1.0) * TRIM_REL)
    for edge in edges:
        z = (edge - mean) / math.sqrt(var)
        # ln of the tilted mass near the edge, weighted by e^(-theta (x - edge)) inside the region
        log_near = -0.5 * z * z - 0.5 * math.log(2 * math.pi * var) - math.log(-math.expm1(-abs(theta)))
        if (log_eps - log_near) / math.log(10.0) > BOUND_OK + 3.0:
            return False
    return True


def lattice_band_logs(pi: np.ndarray, lat: _Lattice, low: float, high: float, deep: bool = True):
    """Per region (U_G >= high, low <= U_G < high, U_G < low), for one hypothesis (taxels present
    with probabilities ``pi``), n = pi.size >= 2, eq 7 and the eq 20 band: (ln P or None, below
    FLOOR, log10 of the relative error bound or None). None with below False: an impossible
    event. ``deep`` False: a region whose Chernoff bound e^(Lambda(theta) - theta t) is below
    FLOOR is not computed (None, True, None); every rate >= FLOOR is."""
    p, q = lat.p, lat.q
    if lat.reverse:
        pi = pi[::-1]
    n = pi.size
    pairs = [(ls, le) for ls in range(len(lat.start_labels)) for le in range(len(lat.end_labels))]
    xa, xb = _x_range(lat, n)
    edges = {key: (_first_at_least(lat, _label_base(lat, *key), low, p, q, (xa, xb)),
                   _first_at_least(lat, _label_base(lat, *key), high, p, q, (xa, xb))) for key in pairs}
    # per region and label pair the reachable integer interval [s, e) of the final x
    intervals = [[(max(t_high, xa), xb + 1) for t_low, t_high in edges.values()],
                 [(max(t_low, xa), min(t_high, xb + 1)) for t_low, t_high in edges.values()],
                 [(xa, min(t_low, xb + 1)) for t_low, t_high in edges.values()]]
    empty = [all(e <= s for s, e in iv) for iv in intervals]
    h = 1e-3
    lam = log_partition(pi, lat, [-h, 0.0, h])
    mean = float((lam[2] - lam[0]) / (2 * h))
    var = max(float((lam[2] - 2 * lam[1] + lam[0]) / (h * h)), 1e-12)
    targets = []
    for r, iv in enumerate(intervals):
        live = [(s, e) for s, e in iv if e > s]
        if empty[r] or any(s <= mean <= e - 1 for s, e in live):
            targets.append(None)  # the bulk: theta = 0
        else:
            ends = [s for s, e in live] + [e - 1 for s, e in live]
            targets.append(min(ends, key=lambda x: abs(x - mean)))
    runs: dict = {}
    # each region's x on the final lattice coordinate lies in [x_low, x_high] (every label pair)
    spans = [(min(s for s, e in iv if e > s), max(e - 1 for s, e in iv if e > s)) if not empty[r] else None
             for r, iv in enumerate(intervals)]
    bridged = n >= BRIDGE_MIN_TAXELS

    def run(theta: float, trim: float = TRIM_REL, regions: tuple = (), sigma: float = 1.0):
        """The regions' rates from a run tilted by theta; with ``regions`` (bridged) a bridge
        run for those regions (their bounds from its own error sums)."""
        key = (theta, trim, regions)
        if key not in runs:
            if regions:
                bridge = ([(spans[r][0] if spans[r][0] > xa else None, spans[r][1] if spans[r][1] < xb else None)
                           for r in regions], sigma)
                rows, log_scale, theta_out, errs = lattice_law_rows(pi, lat, theta, trim, bridge)
                eps = dict(zip(regions, errs))
            else:
                rows, log_scale, theta_out, eps = lattice_law_rows(pi, lat, theta, trim)
            runs[key] = _region_logs(rows, lat, edges, theta, theta_out, log_scale, eps, (xa, xb))
        return runs[key]

    out: list = [None, None, None]
    skipped = []  # ln of the Chernoff bounds of regions not computed (each < ln FLOOR)
    for r in range(3):
        if empty[r]:
            out[r] = (-math.inf, -math.inf)
    far = [r for r in range(3) if out[r] is None and targets[r] is not None]
    # both tails on one side of the bulk (the band beyond it): one run tilted to the middle of
    # their near edges usually holds both (each checked by its bound), else one run each
    shared = len(far) == 2 and (targets[far[0]] > mean) == (targets[far[1]] > mean)
    # without deep, a search may stop once the Chernoff bound of the nearer edge is below FLOOR
    stop = -math.inf if deep else _LOG_FLOOR
    memo: dict = {}  # Lambda around each tilt tried (the searches start from each other's results)
    if shared:
        near = min(targets[far[0]], targets[far[1]], key=lambda t: abs(t - mean))
        middle = _tilt_search(pi, lat, 0.5 * (targets[far[0]] + targets[far[1]]), mean, var,
                              stop_below=stop, stop_target=near, memo=memo)  # near below FLOOR: the far one too
    tilts = {}
    for r in far:
        found = middle if shared else _tilt_search(pi, lat, targets[r], mean, var, stop_below=stop, memo=memo)
        theta, lam_t, var_t = found[:3]
        chernoff = lam_t - theta * targets[r]  # P(R) <= P(x beyond its near edge) <= e^chernoff
        if not deep and chernoff < _LOG_FLOOR:
            out[r] = "skipped"
            skipped.append(chernoff)
        tilts[r] = None if shared else (theta, var_t)
    far = [r for r in far if out[r] is None]
    if shared and far:
        # one bridge run holds both where their edges are closer than BRIDGE_SHARED tilted
        # standard deviations (its window spans both bridges); farther apart, the run trimmed
        # by the tilted law (as cheap there, without the bridge's fixed costs), or a run each
        sigma = math.sqrt(middle[2])
        if bridged and (len(far) == 1 or abs(targets[far[0]] - targets[far[1]]) < BRIDGE_SHARED * sigma):
            for r in far:
                got = run(middle[0], regions=tuple(far), sigma=sigma)[r]
                if got[1] <= BOUND_OK:
                    out[r] = got
        elif _shared_run_may_hold(pi, lat, middle[0], [targets[r] for r in far], middle[3:1:-1]):
            for r in far:
                if run(middle[0])[r][1] <= BOUND_OK:
                    out[r] = run(middle[0])[r]
    for r in far:
        if out[r] is None:
            theta, var_t = tilts[r] if tilts[r] is not None else \
                _tilt_search(pi, lat, targets[r], mean, var, middle[0], memo=memo)[::2]
            regions, sigma = ((r,), math.sqrt(var_t)) if bridged else ((), 1.0)
            out[r] = run(theta, regions=regions, sigma=sigma)[r]
            if out[r][1] > BOUND_OK:  # once more, trimmed 1e15 times less
                out[r] = run(theta, TRIM_REL * 1e-15, regions, sigma)[r]
    computed = [r for r in range(3) if isinstance(out[r], tuple)]
    bulk = [r for r in range(3) if out[r] is None]
    if len(bulk) == 1:
        rest = _logsumexp([out[r][0] for r in computed])
        rest_upper = _logsumexp([rest, *skipped])
        if rest_upper <= math.log(0.5):
            # 1 - (the other two): exact in relative terms where they sum to at most 1/2; its
            # error: theirs, and the skipped regions' mass (< their Chernoff bounds)
            err = [out[r][0] + out[r][1] * math.log(10.0) for r in computed] + skipped
            out[bulk[0]] = (math.log1p(-math.exp(rest)), (math.log(2.0) + _logsumexp(err)) / math.log(10.0))
    for r in range(3):
        if out[r] is None:
            out[r] = run(0.0)[r]
    result = []
    for r in range(3):
        if out[r] == "skipped":
            result.append((None, True, None))
        elif out[r][0] == -math.inf:
            result.append((None, not empty[r], None))  # 0 without being empty: below any double
        else:
            result.append((out[r][0], out[r][0] < _LOG_FLOOR, out[r][1]))
    return result


# ------------------------------------------------------------------ U_G's law beyond FLOOR
def lattice_law_tail_atoms(pi: np.ndarray, lat: _Lattice, frontier: int, upward: bool, max_runs: int = 64):
    """Atoms of U_G's law (eq 7) beyond the final lattice coordinate ``frontier`` on one side
    (``upward``: x >= frontier, else x <= frontier), for n = pi.size >= 2 taxels already in the
    lattice's orientation: {(ls, le, x): ln P}. Each run is tilted so that the tilted mean sits
    at the frontier (Lambda'(theta) = frontier, :func:`tilt_for_mean`); an atom is kept when its
    proven relative error bound eps T e^(-theta x) / P(x) (module doc, R = {x}) is below
    10^BOUND_OK, and the frontier moves past the contiguous run of kept x values (an x with
    every atom exactly 0 inside the live window is impossible: nothing is trimmed inside it).
    Stops at the end of the reachable range, after ``max_runs`` runs, or where a run keeps
    nothing (returns what it has and the frontier reached)."""
    n = pi.size
    xa, xb = _x_range(lat, n)
    h = 1e-3
    lam = log_partition(pi, lat, [-h, 0.0, h])
    mean = float((lam[2] - lam[0]) / (2 * h))
    var = max(float((lam[2] - 2 * lam[1] + lam[0]) / (h * h)), 1e-12)
    atoms: dict = {}
    step = 1 if upward else -1
    theta_prev = None
    for _ in range(max_runs):
        if (upward and frontier > xb) or (not upward and frontier < xa):
            break
        target = min(max(frontier, xa), xb)
        theta, _lam = tilt_for_mean(pi, lat, float(target), mean, var, start=theta_prev)
        theta_prev = theta
        rows, log_scale, theta_out, eps = lattice_law_rows(pi, lat, theta)
        if not rows:
            break
        x_ref = rows[0][3]
        per_x: dict = {}
        total = []
        for a, b, ls, x_first, arr in rows:
            e_steps, le = lat.end[a][b]
            x = (x_first - x_ref) + np.arange(arr.size)
            with np.errstate(divide="ignore"):
                lv = np.log(arr) - theta_out * x
            lt = lv + theta * x
            top = float(lt.max())
            total.append(top + math.log(float(np.exp(lt - top).sum())))
            for j in range(arr.size):
                xf = int(x_first + j + e_steps)
                per_x.setdefault(xf, []).append((ls, le, float(lv[j]), int(x[j])))
        log_total = _logsumexp(total)
        lo_x, hi_x = min(per_x), max(per_x)
        kept = 0
        x = frontier
        while lo_x <= x <= hi_x:
            entries = per_x.get(x, [])
            ok = True
            found = {}
            for ls, le, lv, xr in entries:
                if lv == -math.inf:
                    continue
                key = (ls, le, x)
                # ln P of this (state, start label) part; parts of one atom are summed below
                found.setdefault(key, []).append((lv, xr))
            for key, parts in found.items():
                log_p = _logsumexp([lv for lv, _ in parts])
                worst = max(-theta * xr for _, xr in parts)
                if eps > 0.0:
                    bound = (math.log(eps) + log_total + worst - log_p) / math.log(10.0)
                    if bound > BOUND_OK:
                        ok = False
                        break
            if not ok:
                break
            for key, parts in found.items():
                atoms[key] = _logsumexp([lv for lv, _ in parts]) + log_scale - theta_out * x_ref
            kept += 1
            x += step
        if kept == 0:
            break
        frontier = x
    return atoms, frontier
