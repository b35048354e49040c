"""Bridge trimming of the tilted DP (:mod:`.tilted_dp`) and what it rests on: products of the
chain's 4 x 4 transfer matrices over blocks of BLOCK taxels and, from them, Chernoff bounds on
the rest of the chain (the future's exponential moments at the block ends).

Bridge trimming (:func:`.tilted_dp.lattice_law_rows`, from tilted_dp.BRIDGE_MIN_TAXELS = 1000
taxels on). The trimming by the tilted law (:mod:`.tilted_dp`) keeps the tilted law of the
first i taxels to ~12 standard deviations, a window growing like sqrt(i); but a column x after i taxels matters only through the mass it can still carry into the
region R. For any tilt t with R inside [edge, oo) (t >= 0), inside (-oo, edge] (t <= 0), or
t = 0, 1[x_final in R] <= e^(t (x_final - edge)), so the column's share of P(R) is at most

    P_i(x) e^(t (x - edge)) Hmax_i(t),    Hmax_i(t) = max over states s of E[e^(t S) | s],

S the steps still to come (the last taxel's end steps included) -- a Chernoff bound on the
rest of the chain, rigorous for every t. The least over a grid of tilts (the run's theta plus
0, +-0.5, +-1, ..., +-256 tilted standard deviations, and t = 0; any subset of them bounds as
well) shrinks like the Brownian bridge from the start to the region's edge: the window is
~2 z sigma sqrt(i (n - i) / n) instead of ~2 z sigma sqrt(i) (z ~ 10), narrowest at both ends.
Hmax_i(t) comes from one backward pass over the chain for every t at once at the block ends
(:func:`_suffix_logs`: products of the block's 4 x 4 transfer matrices, upper bounds);
every BRIDGE_EVERY-th block end, columns are dropped from either side while each region's sum
of these bounds stays within BRIDGE_REL times its Chernoff bound, and the sums dropped are the
region's absolute error bound, divided by its computed P(R) for the relative bound returned
(~1e-15 to 1e-18 at n = 10^4). One bridge run serves both regions on one side of the bulk when
their edges are closer than BRIDGE_SHARED tilted standard deviations (the window spans both
bridges); farther apart, a run trimmed by the tilted law serves both if its bound holds,
else each region gets its own bridge run. A bridge run's theta only keeps the arithmetic in
range.

The constants that decide when and how hard a bridge run trims (BRIDGE_REL, BRIDGE_SHARED,
BRIDGE_EVERY, BRIDGE_MIN_TAXELS) stay with the DP that reads them, :mod:`.tilted_dp`.
"""

from __future__ import annotations

import math

import numpy as np

from .chain_dp import _Lattice

BLOCK = 32
"""Taxels per block: the window is trimmed and rescaled once per block (per-block work ~ 15
numpy calls, so blocks are long; the window grows by at most BLOCK steps meanwhile)."""
BRIDGE_GRID = (0.0,) + tuple(s * 0.5 * 2.0**j for j in range(10) for s in (1.0, -1.0))
"""Offsets of the bridge run's tilts from its own theta, in units of 1 / sigma (and theta = 0)."""


# ------------------------------------------------------------------ block products, suffix bounds
def _block_products(pi: np.ndarray, lat: _Lattice, thetas: np.ndarray, block: int, slack: float):
    """Per theta and block of ``block`` inner taxels (aligned on the last one; the first block
    padded with identities in front): the product of the block's transfer matrices M_j[(a, b),
    (b, c)] = P_j(c) e^(theta shift[a, b, c]) as (k, nb, 4, 4) with its largest entry 1, the
    logs of the scales (k, nb), and the padding. Formed backwards for every block and theta at
    once (the 4 x 4 product as 4 x 4 arrays over (theta, block)), normalised per step; with
    ``slack`` > 0 that fraction of the largest entry is added to every entry per step, so that
    nothing lost to underflow makes an entry smaller than its true value (upper bounds)."""
    k = thetas.size
    m = pi.size - 2
    nb = max(1, -(-m // block))
    pad = nb * block - m
    pp = np.concatenate([np.zeros(pad), pi[2:]]).reshape(nb, block)
    real = np.concatenate([np.zeros(pad, bool), np.ones(m, bool)]).reshape(nb, block)
    E = np.exp(thetas[:, None] * lat.shift.reshape(1, 8).astype(float)).reshape(k, 2, 2, 2)
    # V[row, col, k, block]; a step backwards: new row (a, b) = e^(theta s[a,b,0]) (1 - p) V[(b, 0)]
    # + e^(theta s[a,b,1]) p V[(b, 1)]
    V = np.zeros((4, 4, k, nb))
    for r in range(4):
        V[r, r] = 1.0
    logv = np.zeros((k, nb))
    ex = {(a, b, c): E[:, a, b, c][:, None] for a in (0, 1) for b in (0, 1) for c in (0, 1)}
    ones = {key: bool(np.all(e == 1.0)) for key, e in ex.items()}
    new = np.empty_like(V)
    for t in range(block - 1, -1, -1):
        pc = pp[:, t]
        x0 = [V[2 * b] * (1.0 - pc) for b in (0, 1)]
        x1 = [V[2 * b + 1] * pc for b in (0, 1)]
        for a in (0, 1):
            for b in (0, 1):
                out = new[2 * a + b]
                if ones[(a, b, 0)]:
                    out[...] = x0[b]
                else:
                    np.multiply(x0[b], ex[(a, b, 0)], out=out)
                out += x1[b] if ones[(a, b, 1)] else x1[b] * ex[(a, b, 1)]
        if not real[:, t].all():
            new[:, :, :, ~real[:, t]] = V[:, :, :, ~real[:, t]]
        V, new = new, V
        top = np.maximum.reduce(V.reshape(16, k, nb), axis=0)
        V /= top
        if slack:
            V += slack
        logv += np.log(top)
    return V.transpose(2, 3, 0, 1), logv, pad


def _end_vectors(pi: np.ndarray, lat: _Lattice, thetas: np.ndarray):
    """(ln v, ln w) per theta: v = P(u_1, u_2) e^(theta start steps), w = e^(theta end steps)."""
    k = thetas.size
    w = np.empty((k, 4))
    v = np.empty((k, 4))
    for a in (0, 1):
        for b in (0, 1):
            w[:, 2 * a + b] = thetas * lat.end[a][b][0]
            v[:, 2 * a + b] = thetas * lat.start[a][b][0]
    p0 = np.array([(1.0 - pi[0]) * (1.0 - pi[1]), (1.0 - pi[0]) * pi[1], pi[0] * (1.0 - pi[1]), pi[0] * pi[1]])
    with np.errstate(divide="ignore"):
        return np.log(p0)[None, :] + v, w


def _suffix_logs(pi: np.ndarray, lat: _Lattice, thetas, block: int = BLOCK):
    """The future's exponential moments at the block ends of a bridge run (module doc): (bounds, log_hmax, lam) with bounds[b] the number of taxels placed at
    the end of block b (blocks of ``block`` inner taxels aligned on the last one, bounds[0] = 2),

        log_hmax[k, b] >= ln max over states s of E[e^(theta_k S) | s after taxel bounds[b]],

    S the remaining inner steps plus the last taxel's end steps (an upper bound: the block
    products of :func:`_block_products` with slack 1e-300, chained from the end, normalised,
    1e-290 of the largest entry added per block), and lam[k] = Lambda(theta_k)
    (:func:`.tilted_dp.log_partition`). O(n K) work in ~block * 16 numpy calls and one short loop over
    the blocks."""
    thetas = np.asarray(thetas, float)
    V, logv, pad = _block_products(pi, lat, thetas, block, 1e-300)
    nb = V.shape[1]
    lv, w = _end_vectors(pi, lat, thetas)
    top = w.max(axis=1)
    h = np.exp(w - top[:, None])
    acc = top.copy()
    log_hmax = np.empty((thetas.size, nb + 1))
    log_hmax[:, nb] = acc
    for b in range(nb - 1, -1, -1):  # block b spans taxels bounds[b] .. bounds[b + 1] - 1
        h = np.einsum("kij,kj->ki", V[:, b], h) + 1e-290
        top = h.max(axis=1)
        h /= top[:, None]
        acc = acc + np.log(top) + logv[:, b]
        log_hmax[:, b] = acc
    top = lv.max(axis=1)
    lam = top + np.log((np.exp(lv - top[:, None]) * h).sum(axis=1)) + acc
    bounds = [2] + [2 + b * block - pad for b in range(1, nb + 1)]
    return bounds, log_hmax, lam


# ------------------------------------------------------------------ bridge trimming
def _bridge_setup(pi: np.ndarray, lat: _Lattice, theta: float, sigma: float, regions, rel: float) -> dict:
    """The tilts, the future's bounds (:func:`_suffix_logs`) and, per region, its lines and its
    budget for :func:`_bridge_trim`: ``rel`` times its Chernoff bound (tilted_dp.BRIDGE_REL,
    scaled like the run's trim)."""
    steps = [abs(int(v)) for v in lat.shift.ravel()]
    steps += [abs(lat.start[a][b][0]) for a in (0, 1) for b in (0, 1)]
    steps += [abs(lat.end[a][b][0]) for a in (0, 1) for b in (0, 1)]
    cap = 150.0 / max(1, *steps)  # e^(theta s) stays far inside the doubles
    grid = {0.0}
    for c in BRIDGE_GRID:
        grid.add(min(cap, max(-cap, theta + c / max(sigma, 1e-3))))
    thetas = np.array(sorted(grid))
    bounds, log_hmax, lam = _suffix_logs(pi, lat, thetas)
    k = thetas.size
    # per region and tilt: the line t (x - edge) (+ ln Hmax_b(t), added per block); a tilt of
    # the wrong sign for the region (no edge on that side) gets +inf
    offset = np.full((len(regions), k), math.inf)
    budgets = np.empty(len(regions))
    for r, (x_low, x_high) in enumerate(regions):
        for j, th in enumerate(thetas):
            if th == 0.0:
                offset[r, j] = 0.0
            elif th > 0.0 and x_low is not None:
                offset[r, j] = -th * float(x_low)
            elif th < 0.0 and x_high is not None:
                offset[r, j] = -th * float(x_high)
        chernoff = float(np.min(lam + offset[r]))  # >= the least Chernoff bound of the region
        budgets[r] = chernoff + math.log(rel)
    smin, smax = int(lat.shift.min()), int(lat.shift.max())
    return {"bounds": bounds, "log_hmax": log_hmax, "thetas": thetas, "offset": offset, "budgets": budgets,
            "segment": 2 * BLOCK * (smax - smin) + 32}


def _bridge_trim(state: dict, b: int, log_cols: np.ndarray, log_abs: float, x_first: int, theta_out: float,
                 errs: list) -> tuple[int, int]:
    """Columns to drop at the end of block b of a bridge run: (f0, l0), keep log_cols[f0:l0].
    A column x (P(x) = e^(log_cols + log_abs - theta_out x), every state and label) adds to a
    region R at most P(x) min over tilts t of e^(t (x - edge_t)) Hmax_b(t) (module doc); from
    either side, columns are dropped while every region's sum of these stays within its budget
    (both sides and every region at once, a segment of columns at a time), and the sums go into
    ``errs`` (ln, per region)."""
    size = log_cols.size
    if size < 2:
        return 0, size
    thetas = state["thetas"]
    lines = state["offset"] + state["log_hmax"][:, b][None, :]  # (regions, tilts)
    budgets = state["budgets"]
    seg = state["segment"]
    done = [0, 0]  # columns dropped from the left, from the right
    sums = np.zeros((len(budgets), 2))
    open_ = [True, True]
    while any(open_) and done[0] + done[1] < size - 1:
        room = size - 1 - done[0] - done[1]
        m = min(seg, room)
        idx = np.stack([done[0] + np.arange(m), size - 1 - done[1] - np.arange(m)])  # (side, m)
        x = (x_first + idx).astype(float)
        lf = log_cols[idx] + (log_abs - theta_out * x)
        # any subset of the lines bounds as well: those least at the segments' ends and middles
        probe = x[:, [0, m // 2, m - 1]].ravel()
        best = np.unique(np.argmin(lines[:, :, None] + thetas[None, :, None] * probe[None, None], axis=1))
        g = np.min(lines[:, best, None, None] + thetas[None, best, None, None] * x[None, None], axis=1)  # (r, side, m)
        with np.errstate(over="ignore"):
            c = np.cumsum(np.exp(np.minimum(lf[None] + g - budgets[:, None, None], 700.0)), axis=2) + sums[:, :, None]
        take = (c <= 1.0).sum(axis=2).min(axis=0)  # per side: columns every region can lose
        for side in (0, 1):
            t = int(take[side]) if open_[side] else 0
            if side == 1:
                t = min(t, size - 1 - done[0] - done[1])
            if t:
                sums[:, side] = c[:, side, t - 1]
                done[side] += t
            if t < m:
                open_[side] = False
    total = sums.sum(axis=1)
    for r in range(len(budgets)):
        if total[r] > 0.0:
            errs[r] = float(np.logaddexp(errs[r], math.log(total[r]) + budgets[r]))
    return done[0], size - done[1]
