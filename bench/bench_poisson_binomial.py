"""Poisson-binomial law of the present count: run time vs n, side by side with scipy.

Prints seconds per call and the ratio to n^2 (the recursion is O(n^2)); no assertions.
Run: .venv/bin/python bench/bench_poisson_binomial.py
"""

from __future__ import annotations

import time

import numpy as np
from scipy import stats

from fusion_center.core import poisson_binomial as pb


def best_of(fn, repeat=3):
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main():
    rng = np.random.default_rng(0)
    print(f"{'n':>7} {'pmf s':>9} {'log_pmf s':>10} {'scipy pmf s':>12} {'log_pmf/n^2 ns':>16} {'log/lin':>8}")
    for n in (100, 1000, 3000, 10000):
        probs = rng.uniform(1e-4, 0.2, n)
        t_lin = best_of(lambda: pb.pmf(probs))
        t_log = best_of(lambda: pb.log_pmf(probs))
        if hasattr(stats, "poisson_binom"):
            t_scipy = best_of(lambda: stats.poisson_binom.pmf(np.arange(n + 1), probs))
        else:
            t_scipy = float("nan")
        print(f"{n:>7} {t_lin:>9.4f} {t_log:>10.4f} {t_scipy:>12.4f} {1e9 * t_log / n**2:>16.2f} {t_log / t_lin:>8.1f}")


if __name__ == "__main__":
    main()
