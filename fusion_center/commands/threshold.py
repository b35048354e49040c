"""``fusion-center threshold``: HEBTEM dynamic threshold of one fusion rule (eqs 16-20)."""

from __future__ import annotations

import argparse
import json
import math

from ..cli import UsageError
from ..errors import ParameterError
from ..thresholds import additive_threshold, multiplicative_threshold, preferential_threshold

HELP = "HEBTEM dynamic threshold of a fusion rule (eqs 16-20): additive, multiplicative, preferential"

RULES = ("additive", "multiplicative", "preferential")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rule", required=True, choices=RULES, help="fusion rule (eq 6, eq 5 or eq 7)")
    parser.add_argument("--n", required=True, metavar="N", help="number of taxels, integer >= 1")
    parser.add_argument("--xi", required=True, metavar="X", help="P(H1) with every taxel absent, in (0, 1)")
    level = parser.add_mutually_exclusive_group()
    level.add_argument("--alpha", metavar="A", help="Type I error level in (0, 1): additive, preferential")
    level.add_argument("--beta", metavar="B", help="Type II error level in (0, 1): multiplicative")
    parser.add_argument("--p", metavar="P", help="preferential: weight of the succeeding taxel in [0, 2] (default 1)")
    parser.add_argument("--q", metavar="Q", help="preferential: weight of the preceding taxel in [0, 2] (default 1)")
    parser.add_argument("--tuple", dest="encoding", choices=("pm1", "01"), default="pm1",
                        help="decision tuple: pm1 = {-1,+1} (default), 01 = {0,1}")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def _number(name: str, text: str, allowed: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ParameterError(name, text, allowed) from None
    if not math.isfinite(value):
        raise ParameterError(name, text, allowed)
    return value


def _integer(name: str, text: str) -> int:
    allowed = "must be an integer >= 1"
    value = _number(name, text, allowed)
    if value != math.floor(value) or value < 1:
        raise ParameterError(name, text, allowed)
    return int(value)


def _check_combination(args) -> None:
    rule = args.rule
    if rule == "multiplicative":
        if args.alpha is not None:
            raise UsageError("--rule multiplicative takes --beta (Type II error), not --alpha")
        if args.beta is None:
            raise UsageError("--rule multiplicative needs --beta B (Type II error level in (0, 1))")
        if args.encoding != "pm1":
            raise UsageError("--rule multiplicative is defined on the {-1,+1} tuple (eqs 10-11): use --tuple pm1")
    else:
        if args.beta is not None:
            raise UsageError(f"--rule {rule} takes --alpha (Type I error), not --beta")
        if args.alpha is None:
            raise UsageError(f"--rule {rule} needs --alpha A (Type I error level in (0, 1))")
    if rule != "preferential" and (args.p is not None or args.q is not None):
        raise UsageError("--p/--q only apply to --rule preferential")


def _result(args) -> dict:
    _check_combination(args)
    n = _integer("n", args.n)
    xi = _number("xi", args.xi, "must be a real number in the open interval (0, 1)")
    if args.rule == "multiplicative":
        beta = _number("beta", args.beta, "must be a real number in the open interval (0, 1)")
        res = multiplicative_threshold(n, xi, beta)
        return {"rule": "multiplicative", "n": n, "xi": xi, "beta": beta, "tuple": "pm1",
                "scaled_thresholds": list(res.scaled_thresholds),
                "ln_thresholds": list(res.ln_thresholds),
                "present_counts": list(res.present_counts)}
    alpha = _number("alpha", args.alpha, "must be a real number in the open interval (0, 1)")
    if args.rule == "additive":
        res = additive_threshold(n, xi, alpha, args.encoding)
        return {"rule": "additive", "n": n, "xi": xi, "alpha": alpha, "tuple": args.encoding,
                "thresholds": list(res.thresholds), "present_counts": list(res.present_counts)}
    p = _number("p", args.p, "must be a real number in [0, 2]") if args.p is not None else 1.0
    q = _number("q", args.q, "must be a real number in [0, 2]") if args.q is not None else 1.0
    res = preferential_threshold(n, xi, alpha, p, q, args.encoding)
    return {"rule": "preferential", "n": n, "xi": xi, "alpha": alpha, "p": p, "q": q, "tuple": args.encoding,
            "g_max": res.g_max, "threshold_mean": res.threshold_mean,
            "threshold_initial": res.threshold_initial, "threshold_final": res.threshold_final,
            "band_width": res.band_width, "present_count": res.present_count}


def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.10g}"
    return str(value)


def _title(result: dict) -> str:
    rule = result["rule"]
    level = f"alpha={result['alpha']:g}" if "alpha" in result else f"beta={result['beta']:g}"
    extra = f", p={result['p']:g}, q={result['q']:g}" if rule == "preferential" else ""
    return f"HEBTEM threshold, {rule} rule: n={result['n']}, xi={result['xi']:g}, {level}{extra}, tuple {result['tuple']}"


def _table(result: dict):
    from rich.table import Table

    rule = result["rule"]
    table = Table()
    if rule == "multiplicative":
        table.add_column("t = lambda/e^n", justify="right")
        table.add_column("ln lambda", justify="right")
        table.add_column("lambda", justify="right")
        table.add_column("present taxels needed", justify="right")
        for t, ln_lam, count in zip(result["scaled_thresholds"], result["ln_thresholds"], result["present_counts"]):
            if ln_lam is None:
                lam = _fmt(t * math.exp(result["n"])) if result["n"] < 700 else f"{t:.6g}*e^{result['n']}"
            else:
                lam = _fmt(math.exp(ln_lam)) if ln_lam < 700 else f"e^{ln_lam:.10g}"
            table.add_row(_fmt(t), _fmt(ln_lam), lam, _fmt(count))
        if not result["scaled_thresholds"]:
            table.add_row("no root in [-e^n, e^n]", "-", "-", "-")
    elif rule == "additive":
        table.add_column("lambda", justify="right")
        table.add_column("present taxels needed", justify="right")
        for lam, count in zip(result["thresholds"], result["present_counts"]):
            table.add_row(_fmt(lam), _fmt(count))
        if not result["thresholds"]:
            table.add_row("no root in the domain", "-")
    else:
        table.add_column("quantity")
        table.add_column("value", justify="right")
        for key in ("g_max", "threshold_mean", "threshold_initial", "threshold_final", "band_width", "present_count"):
            table.add_row(key, _fmt(result[key]))
    return table


def run(args) -> int:
    result = _result(args)
    if args.json:
        print(json.dumps(result))
    else:
        from rich.console import Console

        console = Console()
        console.print(_title(result), highlight=False, soft_wrap=True)
        console.print(_table(result))
    return 0
