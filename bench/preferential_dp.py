"""Exact preferential-rule error rates (eq 7, eq 20 band): DP time against n.

Prints, for each method of fusion_center.core.exact_rates.preferential_error_rates, the time of
one call (both hypotheses, best of 3 on a shared machine: +-50 % noise) for n = 10^2 .. 10^4,
heterogeneous per-taxel pd_i / pf_i, the chapter's band (xi = 0.003, alpha = 0.48), and the
exact rates as log10 (the false-alarm rates here are far below the double range):

    .venv/bin/python bench/preferential_dp.py
"""

from __future__ import annotations

import math
import time

import numpy as np

from fusion_center.core.exact_rates import preferential_error_rates
from fusion_center.core.thresholds import preferential_threshold


def main() -> None:
    rng = np.random.default_rng(0)
    print(f"{'method':<8} {'tuple':<5} {'p':>4} {'q':>4} {'n':>6} {'seconds':>9}  {'log10 P_miss':>13} "
          f"{'log10 P_FA':>11} {'log10 P_und|H0':>15}")
    for encoding, p, q in (("pm1", 1.0, 1.0), ("pm1", 1.3, 0.2), ("01", 1.0, 1.0)):
        for n in (100, 300, 1000, 3000, 10000):
            if encoding == "01" and n > 3000:
                continue  # the integer-value DP is O(n g): minutes at 10^4
            pd = rng.uniform(0.8, 0.99, n)
            pf = rng.uniform(0.001, 0.01, n)
            band = preferential_threshold(n, 0.003, 0.48, p, q, encoding)
            best = float("inf")
            for _ in range(3):
                t0 = time.perf_counter()
                r = preferential_error_rates(pd, pf, p, q, encoding, band.threshold_initial, band.threshold_final)
                best = min(best, time.perf_counter() - t0)
            lg = lambda x: "-inf" if x is None else f"{x / math.log(10):.4f}"
            print(f"{r.method:<8} {encoding:<5} {p:>4g} {q:>4g} {n:>6} {best:>9.3f}  {lg(r.log_p_miss):>13} "
                  f"{lg(r.log_p_false_alarm):>11} {lg(r.log_p_undecided_h0):>15}")


if __name__ == "__main__":
    main()
