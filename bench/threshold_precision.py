"""Precision vs run time of the HEBTEM threshold solvers (eqs 16-18), side by side with a naive
linear-domain scipy.optimize.brentq on the raw equations.

For each rule and a few cases the script sweeps the solver tolerance (our Newton rtol, brentq's
xtol/rtol), measures the relative error against an mpmath reference at 80 digits (the original
integral equation, mean form, refined by mp.findroot), the number of function evaluations and
the time per solve, prints a table and writes a log-log PNG (error vs time per solve).

    .venv/bin/python bench/threshold_precision.py [--out out/threshold_precision.png]
    .venv/bin/python bench/threshold_precision.py --against /tmp/before [--rounds 3]

Runtime: well under a minute on one core. ``--against OTHER_CHECKOUT`` (``git worktree add
/tmp/before <commit>``) instead times only our solvers at full accuracy (default arguments),
case by case, in both trees -- each in its own interpreter, alternately, best of ``--rounds`` --
and prints the times side by side with the ratio this/before.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
import warnings
from pathlib import Path

from scipy.optimize import brentq

from fusion_center.report.reference import ref_additive, ref_multiplicative, ref_preferential
from fusion_center.core.thresholds import additive_threshold, multiplicative_threshold, preferential_threshold

TARGET_US = 20.0
FLOOR = 1e-17  # errors of exactly 0 are drawn here on the log axis
RTOLS = [1e-2, 1e-4, 1e-6, 1e-8, 1e-11, 1e-14, 4 * 2.0**-52]
XTOLS = [1e-2, 1e-4, 1e-6, 1e-8, 1e-11, 1e-14, 2e-12 * 0 + 1e-300]


# ----------------------------------------------------------------------- naive brentq baselines


def naive_multiplicative(n, xi, beta, xtol, rtol):
    """brentq on eq 16 as printed: m, a from eqs 11a-11b, antiderivative (a/m) e^(m x)."""
    e2n = math.exp(2 * n)  # OverflowError for n >= 355
    en = math.exp(n)
    L = math.log(1 / xi)
    m = en * L / (e2n - 1)
    a = math.exp(-(e2n * L / (e2n - 1)))
    calls = [0]

    def G(lam):
        calls[0] += 1
        return a / m * (math.exp(m * en) - math.exp(m * lam)) - (1 - beta) * (en - lam)

    lam = brentq(G, -en, en * (1 - 1e-13), xtol=xtol, rtol=rtol, maxiter=500)
    return [lam / en], calls[0]


def naive_additive(n, xi, alpha, xtol, rtol, encoding="pm1"):
    """brentq on eq 17 as printed, closed-form antiderivative of eq 13 (or 12) in floats."""
    calls = [0]
    if encoding == "pm1":
        r = (xi + 1) + math.sqrt(xi * (xi + 2))
        F = lambda U: 0.5 * n * r ** (U / n) / math.log(r) + (1 - 0.5 * r) * U * U / (2 * n)
        lo = -n
    else:
        L = math.log(1 / xi)
        F = lambda U: xi * n / L * math.exp(L * U / n)
        lo = 0.0

    def G(lam):
        calls[0] += 1
        return F(n) - F(lam) - (1 - alpha) * (n - lam)

    lam = brentq(G, lo, n * (1 - 1e-12), xtol=xtol, rtol=rtol, maxiter=500)
    return [lam], calls[0]


def naive_preferential(n, xi, alpha, g, xtol, rtol):
    calls = [0]

    def G(lam):
        calls[0] += 1
        return (1 - xi) * (g**3 - lam**3) / (3 * g * g) + xi * (g - lam) - (1 - alpha) * (g - lam)

    lam = brentq(G, -g, g * (1 - 1e-12), xtol=xtol, rtol=rtol, maxiter=500)
    return [lam], calls[0]


# ------------------------------------------------------------------------------------- harness


def _time(fn, budget=0.004, rounds=5):
    """Best of `rounds` mean times per call (the machine is shared: the minimum is the signal)."""
    fn()
    best = math.inf
    for _ in range(rounds):
        reps, start = 0, time.perf_counter()
        while True:
            fn()
            reps += 1
            elapsed = time.perf_counter() - start
            if elapsed > budget or reps >= 20000:
                break
        best = min(best, elapsed / reps)
    return best


def _err(values, ref):
    if len(values) != len(ref):
        return math.inf
    return max((abs(v - r) / abs(r) if r else abs(v)) for v, r in zip(values, ref)) if ref else 0.0


CASES = [
    ("multiplicative", dict(n=57, xi=0.003, level=0.83)),
    ("multiplicative", dict(n=354, xi=0.003, level=0.3)),
    ("multiplicative", dict(n=355, xi=0.003, level=0.3)),
    ("multiplicative", dict(n=1_000_000, xi=1e-12, level=0.03)),
    ("additive", dict(n=57, xi=0.003, level=0.03)),
    ("additive", dict(n=57, xi=0.003, level=0.473)),
    ("additive", dict(n=57, xi=1e-12, level=0.03)),
    ("additive", dict(n=1_000_000, xi=1e-300, level=0.03)),
    ("additive", dict(n=57, xi=0.999999, level=0.38)),
    ("additive", dict(n=57, xi=0.999999, level=0.36)),  # ran to the 100-iteration limit before
    ("additive", dict(n=57, xi=0.9554284882838996, level=0.4039508811908412)),  # near-tangent
    ("additive-01", dict(n=57, xi=0.003, level=0.03)),
    ("preferential", dict(n=18, xi=0.003, level=0.48)),
    ("preferential", dict(n=1_000_000, xi=0.5, level=0.03)),
    ("preferential", dict(n=1_000_000, xi=0.5, level=0.03, p=0.5, q=2.0, tuple="01")),
    ("preferential", dict(n=57, xi=0.003, level=0.3, p=0.0, q=1.5)),
]

PROBE = r'''
import json, math, sys, time
root, cases = sys.argv[1], json.loads(sys.argv[2])
sys.path.insert(0, root)
import fusion_center.core.thresholds as th
def best(fn, budget=0.004, rounds=5):
    fn()
    out = math.inf
    for _ in range(rounds):
        reps, start = 0, time.perf_counter()
        while True:
            fn()
            reps += 1
            elapsed = time.perf_counter() - start
            if elapsed > budget or reps >= 20000:
                break
        out = min(out, elapsed / reps)
    return out
us = []
for rule, c in cases:
    n, xi, level = c["n"], c["xi"], c["level"]
    if rule == "multiplicative":
        fn = lambda: th.multiplicative_threshold(n, xi, level)
    elif rule.startswith("additive"):
        fn = lambda: th.additive_threshold(n, xi, level, "01" if rule.endswith("01") else "pm1")
    else:
        fn = lambda: th.preferential_threshold(n, xi, level, c.get("p", 1.0), c.get("q", 1.0), c.get("tuple", "pm1"))
    us.append(1e6 * best(fn))
print(json.dumps({"module": th.__file__, "us": us}))
'''


def against(other: Path, rounds: int) -> int:
    """Our solvers at full accuracy in two trees, side by side (module doc)."""
    root = Path(__file__).resolve().parent.parent
    trees = {"before": other.resolve(), "this": root}
    best: dict[str, list[float]] = {}
    for _ in range(rounds):
        for name, tree in trees.items():
            res = subprocess.run([sys.executable, "-c", PROBE, str(tree), json.dumps(CASES)], capture_output=True,
                                 text=True, cwd=tree, timeout=600)
            if res.returncode != 0:
                raise SystemExit(f"{tree}: {res.stderr.strip().splitlines()[-1]}")
            out = json.loads(res.stdout)
            if not out["module"].startswith(str(tree)):
                raise SystemExit(f"{tree}: imported {out['module']} instead")
            best[name] = [min(a, b) for a, b in zip(best.get(name, out["us"]), out["us"])]
    print(f"{'rule':<15} {'case':<48} {'before us':>10} {'this us':>8} {'ratio':>6}")
    for (rule, c), b, t in zip(CASES, best["before"], best["this"]):
        label = f"n={c['n']:g} xi={c['xi']:.7g} level={c['level']:.4g}"
        if "p" in c:
            label += f" p={c['p']:g} q={c['q']:g} {c.get('tuple', 'pm1')}"
        print(f"{rule:<15} {label:<48} {b:>10.2f} {t:>8.2f} {t / b:>6.2f}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/threshold_precision.png", help="PNG path (log-log error vs time)")
    parser.add_argument("--against", type=Path, help="another checkout: time our solvers side by side (module doc)")
    parser.add_argument("--rounds", type=int, default=3, help="with --against: alternating runs per tree")
    args = parser.parse_args(argv)
    if args.against is not None:
        return against(args.against, args.rounds)

    cases = CASES
    rows = []  # (rule, case, method, tol, err, evals, seconds, note)
    for rule, c in cases:
        n, xi, level = c["n"], c["xi"], c["level"]
        p, q, enc_pref = c.get("p", 1.0), c.get("q", 1.0), c.get("tuple", "pm1")
        label = f"n={n:g} xi={xi:.7g} {'beta' if rule == 'multiplicative' else 'alpha'}={level:.4g}"
        if (p, q, enc_pref) != (1.0, 1.0, "pm1"):
            label += f" p={p:g} q={q:g} {enc_pref}"
        if rule == "multiplicative":
            best = multiplicative_threshold(n, xi, level).scaled_thresholds
            ref = ref_multiplicative(n, xi, level, best[0])
            ours = lambda rt: multiplicative_threshold(n, xi, level, rtol=rt, info=info).scaled_thresholds
            naive = lambda xt, rt: naive_multiplicative(n, xi, level, xt, rt)
        elif rule.startswith("additive"):
            enc = "01" if rule.endswith("01") else "pm1"
            best = additive_threshold(n, xi, level, enc).thresholds
            ref = ref_additive(n, xi, level, best, enc)
            ours = lambda rt, enc=enc: additive_threshold(n, xi, level, enc, rtol=rt, info=info).thresholds
            naive = lambda xt, rt, enc=enc: naive_additive(n, xi, level, xt, rt, enc)
        else:
            res = preferential_threshold(n, xi, level, p, q, enc_pref)
            ref = ref_preferential(n, xi, level, res.g_max, res.threshold_mean)
            ours = None
            g = res.g_max
            naive = lambda xt, rt: naive_preferential(n, xi, level, g, xt, rt)
        if ours is None:
            f = lambda: (preferential_threshold(n, xi, level, p, q, enc_pref).threshold_mean,)
            rows.append((rule, label, "ours (closed form)", "-", _err(f(), ref), 0, _time(f), ""))
        else:
            for rt in RTOLS:
                info = {}
                vals = ours(rt)
                rows.append((rule, label, "ours (Newton)", f"{rt:.0e}", _err(vals, ref), info.get("evaluations", 0),
                             _time(lambda: ours(rt)), ""))
        for xt, rt in zip(XTOLS, RTOLS):
            rt_b = max(rt, 4 * 2.0**-52)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    vals, calls = naive(xt, rt_b)
                    secs = _time(lambda: naive(xt, rt_b))
                note = "finds 1 of 2 roots" if len(vals) != len(ref) else ""
                rows.append((rule, label, "naive brentq", f"{xt:.0e}", _err(vals, ref), calls, secs, note))
            except (OverflowError, ValueError, ZeroDivisionError) as exc:
                rows.append((rule, label, "naive brentq", f"{xt:.0e}", math.nan, 0, math.nan,
                             f"fails: {type(exc).__name__}: {str(exc)[:40]}"))
                break

    print(f"{'rule':<15} {'case':<48} {'method':<19} {'tol':>7} {'rel.err':>9} {'evals':>5} {'us/solve':>9}  note")
    for rule, label, method, tol, err, evals, secs, note in rows:
        e = "nan" if math.isnan(err) else ("inf" if math.isinf(err) else f"{err:.1e}")
        s = "-" if math.isnan(secs) else f"{secs * 1e6:.2f}"
        print(f"{rule:<15} {label:<48} {method:<19} {tol:>7} {e:>9} {evals:>5} {s:>9}  {note}")

    # target of the issue: <= 20 us per solve after warm-up at full accuracy (our default rtol)
    full = f"{RTOLS[-1]:.0e}"
    print(f"\nfull accuracy (rtol {full} / closed form), target <= {TARGET_US:g} us per solve:")
    for rule in dict.fromkeys(r[0] for r in rows):
        ours_rows = [r for r in rows if r[0] == rule and r[2].startswith("ours") and r[3] in (full, "-")]
        worst = max(ours_rows, key=lambda r: r[6])
        print(f"  {rule:<15} worst {worst[6] * 1e6:6.2f} us ({worst[1]}), max rel.err "
              f"{max(r[4] for r in ours_rows):.1e}, {'meets' if worst[6] * 1e6 <= TARGET_US else 'MISSES'} target")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rules = ["multiplicative", "additive", "additive-01", "preferential"]
    fig, axes = plt.subplots(1, len(rules), figsize=(5 * len(rules), 4.2), sharey=True)
    for ax, rule in zip(axes, rules):
        for label in dict.fromkeys(r[1] for r in rows if r[0] == rule):
            for method, marker in (("ours", "o-"), ("naive", "x--")):
                pts = [(r[6], max(r[4], FLOOR)) for r in rows
                       if r[0] == rule and r[1] == label and r[2].startswith(method) and math.isfinite(r[4])
                       and math.isfinite(r[6])]
                if pts:
                    ax.loglog([p[0] * 1e6 for p in pts], [p[1] for p in pts], marker, label=f"{method}: {label}", ms=4)
        ax.set_title(rule)
        ax.set_xlabel("time per solve [us]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6)
    axes[0].set_ylabel(f"relative error vs mpmath (0 drawn at {FLOOR:g})")
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
