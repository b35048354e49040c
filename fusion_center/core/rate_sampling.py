"""Monte Carlo fallbacks of the exact rates (:mod:`.exact_rates`): the preferential band
decision (eq 7, eq 20 band) sampled where no exact DP applies, the Wilson interval of a
sampled rate, and importance sampling (exponential tilting) of the Chair-Varshney / N-P
statistic (eqs 31-32) on fully heterogeneous taxels beyond exact enumeration."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["monte_carlo_band_rates", "wilson", "importance_sampling_tail"]


def monte_carlo_band_rates(pi: np.ndarray, p: float, q: float, encoding: str, low: float, high: float,
                           samples: int, rng: np.random.Generator):
    """Fractions of ``samples`` independent decision vectors (taxel i present with probability
    pi_i) with U_G >= high, low <= U_G < high, U_G < low (eq 7, eq 20 band). U_G of each sample
    from its integer coefficients (rules.preferential_coefficients, vectorised over a batch)
    and the float expression of rules.preferential_value, so each value is the one the rule
    computes."""
    counts = np.zeros(3)
    absent = -1 if encoding == "pm1" else 0
    n = pi.size
    zp, zq = (1 if p == 0.0 else 0), (1 if q == 0.0 else 0)
    fp, fq = (zp, 1), (zq, 1)
    batch = max(1, min(samples, 4_000_000 // max(n, 1)))
    done = 0
    while done < samples:
        m = min(batch, samples - done)
        u = np.where(rng.random((m, n)) < pi, 1, absent).astype(np.int64)
        padded = np.pad(u, ((0, 0), (1, 1)))
        index = 3 * (1 + padded[:, 2:]) + (1 + padded[:, :-2])
        rows = np.arange(m)[:, None] * 9
        w = np.bincount((rows + index).ravel(), weights=u.ravel(), minlength=9 * m).reshape(m, 9)
        w = [np.rint(w[:, k]).astype(np.int64) for k in range(9)]
        a = b = c = d = 0
        for s_ in range(3):
            for t in range(3):
                k = w[3 * s_ + t]
                if s_ < 2 and t < 2:
                    a = a + k * (fp[s_] * fq[t])
                elif s_ == 2 and t < 2:
                    b = b + k * fq[t]
                elif s_ < 2 and t == 2:
                    c = c + k * fp[s_]
                else:
                    d = d + k
        v = ((b * 2.0**p + c * 2.0**q) + d * 2.0 ** (p + q)) + a
        counts += [np.count_nonzero(v >= high), np.count_nonzero((v < high) & (v >= low)), np.count_nonzero(v < low)]
        done += m
    return counts / samples


def wilson(k: float, n: int) -> tuple[float, float]:
    z = 1.959963984540054
    phat = k / n
    denom = 1 + z * z / n
    centre = (phat + z * z / (2 * n)) / denom
    half = z * math.sqrt(phat * (1 - phat) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)



def importance_sampling_tail(a, b, probs, threshold: float, samples: int, rng: np.random.Generator):
    """P(S > threshold), S = sum_i (a_i if present else b_i), taxel i present with probability
    probs_i, by importance sampling with exponential tilting: taxel i is drawn present with
    q_i = p_i e^(theta a_i) / (p_i e^(theta a_i) + (1 - p_i) e^(theta b_i)), theta chosen so that
    the tilted mean of S is the threshold (theta = 0 when the event is not rare), each sample
    weighted by exp(-theta S + sum_i ln M_i(theta)). Returns (estimate, 95 % normal interval)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    p = np.asarray(probs, float)

    def tilted(theta):
        la = np.log(p) + theta * a
        lb = np.log1p(-p) + theta * b
        lm = np.logaddexp(la, lb)  # ln M_i(theta)
        q = np.exp(la - lm)
        return q, lm

    def mean(theta):
        q, _ = tilted(theta)
        return float(np.sum(q * a + (1 - q) * b))

    # the rarer side is estimated: the upper tail if the mean lies below the threshold (tilt up,
    # theta > 0), else the lower tail P(S <= threshold) (tilt down) and its complement returned
    upper = mean(0.0) < threshold
    sign = 1.0 if upper else -1.0
    lo, hi = 0.0, 1.0
    while (mean(sign * hi) < threshold) == upper and hi < 1e6:
        hi *= 2.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if (mean(sign * mid) < threshold) == upper:
            lo = mid
        else:
            hi = mid
    theta = sign * hi
    q, lm = tilted(theta)
    total_lm = float(np.sum(lm))
    values = []
    for start in range(0, samples, 10_000):
        m = min(10_000, samples - start)
        present = rng.random((m, p.size)) < q
        stat = np.where(present, a, b).sum(axis=1)
        hit = stat - threshold > 1e-9 * np.maximum(1.0, np.abs(stat))
        if not upper:
            hit = ~hit
        values.append(np.where(hit, np.exp(-theta * stat + total_lm), 0.0))
    w = np.concatenate(values)
    est = float(w.mean())
    half = 1.959963984540054 * float(w.std(ddof=1)) / math.sqrt(w.size)
    if upper:
        return est, (max(0.0, est - half), est + half)
    return 1.0 - est, (max(0.0, 1.0 - est - half), min(1.0, 1.0 - est + half))

