"""Lambda(theta) = ln E[e^(theta x)] of the lattice coordinate x of U_G (eq 7) and the tilt
searches of the tilted DP (:mod:`.tilted_dp`, its module doc: the saddle point
Lambda'(theta) = t of the Chernoff bound), moved from there; importable from there as before."""

from __future__ import annotations

import math

import numpy as np

from .chain_dp import _Lattice
from .tilted_bridge import BLOCK, _block_products, _end_vectors

BRIDGE_MIN_TAXELS = 1000
"""Bridge trimming from this many taxels on (below, the backward pass costs more than it saves)."""
G_MAX = 400.0
"""|theta| is capped at G_MAX / (2 dS + 2 dE + 1) (dS, dE: spread of an inner / end step), so a
state's future weight differs from another's by at most ~e^G_MAX and thresholds stay doubles."""

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
    (state (u_(i-1), u_i)), multiplied pairwise and normalised per level; from
    BRIDGE_MIN_TAXELS taxels on the products of blocks of BLOCK taxels first
    (:func:`.tilted_bridge._block_products`, ~4x faster at 10^4 taxels), then pairwise."""
    thetas = np.atleast_1d(np.asarray(thetas, float))
    n = pi.size
    if n >= BRIDGE_MIN_TAXELS:
        m, logv, _ = _block_products(pi, lat, thetas, BLOCK, 0.0)
        lv, lw = _end_vectors(pi, lat, thetas)
        log_acc = logv.sum(axis=1) + lv.max(axis=1) + lw.max(axis=1)
        v = np.exp(lv - lv.max(axis=1)[:, None])
        w = np.exp(lw - lw.max(axis=1)[:, None])
        while m.shape[1] > 1:
            if m.shape[1] % 2:
                m = np.concatenate([m, np.broadcast_to(np.eye(4), (thetas.size, 1, 4, 4))], axis=1)
            m = m[:, 0::2] @ m[:, 1::2]
            top = m.max(axis=(2, 3))
            m /= top[:, :, None, None]
            log_acc += np.log(top).sum(axis=1)
        with np.errstate(divide="ignore"):
            return np.log(np.einsum("ki,kij,kj->k", v, m[:, 0], w)) + log_acc
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


def tilt_for_mean(pi: np.ndarray, lat: _Lattice, target: float, mean: float, var: float | None = None,
                  start: float | None = None, stop_below: float = -math.inf,
                  stop_target: float | None = None) -> tuple[float, float]:
    """(theta, Lambda(theta)) of :func:`_tilt_search` (its doc)."""
    return _tilt_search(pi, lat, target, mean, var, start, stop_below, stop_target)[:2]


def _tilt_search(pi: np.ndarray, lat: _Lattice, target: float, mean: float, var: float | None = None,
                 start: float | None = None, stop_below: float = -math.inf,
                 stop_target: float | None = None, memo: dict | None = None) -> tuple[float, float, float, float]:
    """(theta, Lambda(theta)) with Lambda'(theta) = target (within two tilted standard
    deviations), by Newton's method safeguarded by bisection on [0, theta_max] (or its mirror);
    Lambda' and Lambda'' by central differences. theta_max where the target is out of reach.
    First guess: ``start`` (a nearby solution), else (target - mean) / var (one Newton step
    from 0, var = Lambda''(0)), else 1. Returns at once where the Chernoff bound
    Lambda(theta) - theta t of P(x beyond t), t = ``stop_target`` (default ``target``), falls
    below ``stop_below`` (enough to skip a rate). Third value: Lambda''(theta), the tilted
    variance (central difference); fourth: Lambda'(theta), the tilted mean. ``memo``: Lambda at
    (theta - h, theta, theta + h) by signed theta, shared by the searches of one hypothesis."""
    memo = {} if memo is None else memo
    stop_target = target if stop_target is None else stop_target
    sign = 1.0 if target > mean else -1.0
    lo, hi = 0.0, theta_max(lat)
    cap = hi
    if start is not None and start * sign > 0:
        theta = min(hi, abs(start))
    else:
        theta = min(hi, abs(target - mean) / var if var else 1.0, 1.0)
    grow = True  # doubling until the target is passed (Newton from 0 overshoots far targets)
    at_max = False
    for _ in range(60):
        h = 1e-3
        if sign * theta not in memo:
            memo[sign * theta] = log_partition(pi, lat, sign * np.array([theta - h, theta, theta + h]))
        lam = memo[sign * theta]
        d1 = sign * (lam[2] - lam[0]) / (2 * h)  # Lambda'(sign theta)
        d2 = max((lam[2] - 2 * lam[1] + lam[0]) / (h * h), 1e-12)
        if abs(d1 - target) <= max(1.0, 2.0 * math.sqrt(d2)) or lam[1] - sign * theta * stop_target < stop_below:
            return sign * theta, float(lam[1]), float(d2), float(d1)
        if sign * (d1 - target) < 0:
            lo = theta
            if grow and 2 * theta < hi:
                theta *= 2
                continue
        else:
            hi = theta
        grow = False
        step = theta - sign * (d1 - target) / d2
        if step >= hi and not at_max and hi == cap:
            theta, at_max = hi, True  # out of reach? try the cap once (not a point already evaluated)
            continue
        if at_max and theta == hi and sign * (d1 - target) < 0:
            return sign * theta, float(lam[1]), float(d2), float(d1)
        theta = step if lo < step < hi else 0.5 * (lo + hi)
        if hi - lo < 1e-9 * max(1.0, hi):
            break
    lam = log_partition(pi, lat, sign * np.array([theta - 1e-3, theta, theta + 1e-3]))
    return (sign * theta, float(lam[1]), max(float((lam[2] - 2 * lam[1] + lam[0]) / 1e-6), 1e-12),
            float(sign * (lam[2] - lam[0]) / 2e-3))
