"""Reproduce the README's figures for the 57-taxel scene: the report plots and ONE markdown
table (issue 6, "Done when").

    .venv/bin/python bench/readme_figures.py [--scene scenes/matrix57.toml] [--out docs/img/report-matrix57]
                                             [--trials 200000] [--bitrates 125000,500000,1000000]

Runs ``fusion-center report`` (``fusion_center.report.build.build_report``) with the three
bit rates - it writes report.json and the PNGs into ``--out`` - and prints, from that
report.json, one markdown table: per bus mode (raw, decision_sync, decision_event) the exact
bits per SYNC cycle (``bus_timing.frame_bits``, mean over the scene's cycles), the bus load at
the scene's SYNC period, the highest SYNC rate the worst-case cycle fits and the SYNC ->
last-frame latency (worst case) at each bit rate, beside the detection error of the rules that
mode can run (Monte Carlo P_D, P_F, total error with its 95 % Wilson interval vs the scene's
ground truth; the exact values of every decision rule: Poisson-binomial for the count rules and
N-P on the count, the DP over the chain for the preferential rule, kinds of equal declared rates
for LLR / N-P on eq 32's statistic). ``--from-json`` prints the table
from an existing report.json without re-running the report.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

MODES = ("decision_sync", "decision_event", "raw")


def _g(x, digits: int = 3) -> str:
    if x is None:
        return "-"
    if x == 0:
        return "0"
    if x == 1:
        return "1"
    return f"{x:.{digits}g}"


def _err(res: dict) -> tuple[str, str, str, str]:
    pd = res.get("pd") or {}
    pf = res["pf"]
    te = res["total_error"]
    lo, hi = te["ci95"]
    total = f"{_g(te['estimate'])} [{_g(lo)}, {_g(hi)}]"
    exact = "-"
    if te.get("exact") is not None:
        exact = f"{_g(te['exact'])} (P_D {_g(pd.get('exact'), 6)}, P_F {_g(pf.get('exact'))})"
    return _g(pd.get("estimate"), 6), _g(pf.get("estimate")), total, exact


def rule_label(name: str, data: dict) -> str:
    th = data["thresholds"].get(name)
    res = data["rules"][name]
    if name == "k-of-n" or name == "additive" and res.get("min_present_count") is not None:
        return f"{name} (≥ {res.get('min_present_count')} present)"
    if name == "np":
        return "np (eq 32, P_F 1e-3)"
    if name == "llr":
        return "llr (Chair-Varshney eq 31)"
    if name == "centralised_bayes":
        return "centralised Bayes (eq 22)"
    if name.startswith("centralised_"):
        return f"centralised {name.split('_', 1)[1]} (P_F 1e-3)"
    if name == "multiplicative":
        return "multiplicative (eq 16)"
    return name if th is None else f"{name}"


def table(data: dict) -> str:
    bitrates = list(data["bandwidth_by_bitrate"])
    kb = " / ".join(f"{int(b) // 1000}k" for b in bitrates)
    head = ["mode", "bits/cycle", f"bus load ({kb})", f"max SYNC rate ({kb})", f"SYNC → last frame ({kb})",
            "rule", "P_D", "P_F", "total error [95 % CI]", "exact total error (P_D, P_F)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    decision_rules = [r for r in data["rules"] if not r.startswith("centralised")]
    central = [r for r in data["rules"] if r.startswith("centralised")]
    for mode in MODES:
        figs = [data["bandwidth_by_bitrate"][b]["modes"][mode] for b in bitrates]
        bus = [mode, f"{figs[0]['bits_per_cycle']:.0f}",
               " / ".join(f"{100 * f['bus_load']:.1f} %" for f in figs),
               " / ".join(f"{f['max_cycle_rate_hz']:.0f} Hz" for f in figs),
               " / ".join(f"{f['latency_ms']:.2f} ms" for f in figs)]
        if mode == "decision_event":
            rows = [("same decisions as decision_sync (a TPDO1 on every change of u_i, no inhibit time): "
                     "same errors", "", "", "", "")]
        else:
            names = decision_rules if mode == "decision_sync" else central
            rows = [(rule_label(n, data), *_err(data["rules"][n])) for n in names]
            if mode == "raw":
                rows.append(("per-taxel central decisions (eqs 1-4) + any rule above: = decision_sync rows",
                             "", "", "", ""))
        for k, row in enumerate(rows):
            cells = bus if k == 0 else [""] * len(bus)
            lines.append("| " + " | ".join([*cells, *row]) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default=str(ROOT / "scenes" / "matrix57.toml"))
    parser.add_argument("--out", default=str(ROOT / "docs" / "img" / "report-matrix57"))
    parser.add_argument("--trials", type=int, default=200_000)
    parser.add_argument("--bitrates", default="125000,500000,1000000")
    parser.add_argument("--from-json", action="store_true", help="only print the table from OUT/report.json")
    args = parser.parse_args(argv)
    out = Path(args.out)
    if args.from_json:
        data = json.loads((out / "report.json").read_text())
    else:
        from fusion_center.commands.report import parse_bitrates
        from fusion_center.report.build import build_report
        from taxel_net.scene import load_scene

        scene = load_scene(args.scene)
        data = build_report(scene, out, args.trials, scene.seed, parse_bitrates(args.bitrates))
    print(f"{data['scene']}: {data['taxels']} taxels, SYNC {data['bandwidth']['sync_period_ms']:g} ms, "
          f"{data['trials_per_hypothesis']} Monte Carlo trials per hypothesis (seed {data['seed']}), "
          f"π1 = {data['prior_h1']:g}\n")
    print(table(data))
    return 0


if __name__ == "__main__":
    sys.exit(main())
