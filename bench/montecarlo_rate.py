"""Monte Carlo throughput: taxel decisions per second of fusion_center.evaluation.simulate.

One "taxel decision" is one simulated local decision u_i (eqs 1-4) of one trial; every trial
also evaluates every configured rule (count rules, preferential, LLR, N-P) and the three
centralised raw-data tests. Prints the measured rate beside the target (2e7 /s) and their ratio.

    .venv/bin/python bench/montecarlo_rate.py [--scene scenes/matrix57.toml] [--trials 200000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from fusion_center import evaluation
from fusion_center.core import montecarlo
from taxel_net.scene import load_scene

TARGET = 2e7


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="scenes/matrix57.toml")
    ap.add_argument("--trials", type=int, default=200_000, help="trials per hypothesis")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    scene = load_scene(args.scene)
    rules_all = list(montecarlo.DECISION_RULES) + list(montecarlo.CENTRAL_TESTS)
    for label, rules in (("all rules + centralised tests", rules_all), ("count rules only", ["k-of-n"])):
        setup = evaluation.setup_rules(scene, [r for r in rules if r not in montecarlo.CENTRAL_TESTS],
                                       central=any(r in montecarlo.CENTRAL_TESTS for r in rules))
        best = float("inf")
        for rep in range(args.repeat):
            rng = np.random.default_rng(rep)
            t0 = time.perf_counter()
            res = evaluation.simulate(scene, args.trials, rng, setup=setup)
            best = min(best, time.perf_counter() - t0)
        rate = res.taxel_decisions / best
        print(f"{scene.name} ({scene.n} taxels), {label}: {res.taxel_decisions:.3g} taxel decisions in "
              f"{best:.3f} s -> {rate:.3g} /s; target {TARGET:.1g} /s; ratio {rate / TARGET:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
