"""``fusion-center threshold``: HEBTEM dynamic threshold of one fusion rule (eqs 16-20)."""

from __future__ import annotations

import argparse
import json
import math
from decimal import Decimal, InvalidOperation

from taxel_net.errors import UsageError
from ..core.curves import check_n, check_open_unit, check_xi
from taxel_net.errors import ParameterError
from ..core.rules import check_weight
from ..core.thresholds import additive_threshold, multiplicative_threshold, preferential_threshold

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
    parser.add_argument("--band", choices=("centred", "eq19"),
                        help="preferential: threshold band centred on lambda_mean (default) or the band of eqs 19-20")
    parser.add_argument("--tuple", dest="encoding", choices=("pm1", "01"), default="pm1",
                        help="decision tuple: pm1 = {-1,+1} (default), 01 = {0,1}")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


_MIN_NORMAL = 2.2250738585072014e-308


def parse_number(name: str, text):
    """The number typed for option ``name``, never silently changed: an integer as an exact
    int (so 9007199254740993 is not rounded to 2^53), anything else as the nearest double.
    Empty text, text that is no number, a value that overflows (1e400) or underflows a double
    (1e-400, or a subnormal that keeps fewer digits) raise ParameterError quoting the text."""
    raw = "" if text is None else str(text).strip()
    if raw == "":
        raise ParameterError(name, text, "is empty: give a number")
    try:
        exact = Decimal(raw)
    except InvalidOperation:
        raise ParameterError(name, text, "is not a number") from None
    if not exact.is_finite():
        return float(exact)  # nan / inf: each option's own check names its allowed range
    value = float(exact)  # correctly rounded
    if math.isinf(value):
        raise ParameterError(name, text, "overflows a double (magnitude above 1.8e308)")
    if exact == exact.to_integral_value():
        return int(exact)
    if math.isinf(value):
        raise ParameterError(name, text, "overflows a double (magnitude above 1.8e308)")
    if abs(value) < _MIN_NORMAL:
        raise ParameterError(name, text, "underflows a double (nonzero magnitude below 2.2e-308)")
    return value


def parse_option(name: str, text, check):
    """``check(value)`` with the library's own validator on the value of :func:`parse_number`;
    a ParameterError quotes the option as typed (``alpha='1e-400'``)."""
    try:
        value = parse_number(name, text)
    except ParameterError as exc:
        try:
            check(None)  # the option's own allowed range, for the message
        except ParameterError as allowed:
            raise ParameterError(exc.name, text, f"{exc.allowed}; {allowed.allowed}") from None
        raise
    try:
        return check(value)
    except ParameterError as exc:
        raise ParameterError(exc.name, text, exc.allowed) from None


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
    if rule != "preferential" and args.band is not None:
        raise UsageError("--band only applies to --rule preferential")


def _result(args) -> dict:
    _check_combination(args)
    n = parse_option("n", args.n, check_n)
    xi = parse_option("xi", args.xi, check_xi)
    if args.rule == "multiplicative":
        beta = parse_option("beta", args.beta, lambda v: check_open_unit("beta", v))
        res = multiplicative_threshold(n, xi, beta)
        return {"rule": "multiplicative", "n": n, "xi": xi, "beta": beta, "tuple": "pm1",
                "scaled_thresholds": list(res.scaled_thresholds),
                "ln_thresholds": list(res.ln_thresholds),
                "present_counts": list(res.present_counts)}
    alpha = parse_option("alpha", args.alpha, lambda v: check_open_unit("alpha", v))
    if args.rule == "additive":
        res = additive_threshold(n, xi, alpha, args.encoding)
        out = {"rule": "additive", "n": n, "xi": xi, "alpha": alpha, "tuple": args.encoding,
               "thresholds": list(res.thresholds), "present_counts": list(res.present_counts)}
        if res.near_double_root:
            out["near_double_root"] = True
        return out
    p = parse_option("p", args.p, lambda v: check_weight("p", v)) if args.p is not None else 1.0
    q = parse_option("q", args.q, lambda v: check_weight("q", v)) if args.q is not None else 1.0
    res = preferential_threshold(n, xi, alpha, p, q, args.encoding, band=args.band or "centred")
    out = {"rule": "preferential", "n": n, "xi": xi, "alpha": alpha, "p": p, "q": q, "tuple": args.encoding,
           "g_max": res.g_max, "threshold_mean": res.threshold_mean, "threshold_means": list(res.mean_roots),
           "threshold_initial": res.threshold_initial, "threshold_final": res.threshold_final,
           "band_width": res.band_width, "present_count": res.present_count}
    if res.near_double_root:
        out["near_double_root"] = True
    if res.band == "eq19":
        out["band"] = "eq19"
        out["eq19_bands"] = [list(b) for b in res.eq19_bands]
    return out


def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, list):
        return ", ".join(_fmt(v) for v in value) if value else "-"
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
                lam = _fmt(math.exp(ln_lam)) if abs(ln_lam) < 700 else f"e^{ln_lam:.10g}"
            table.add_row(_fmt(t), _fmt(ln_lam), lam, _fmt(count))
        if not result["scaled_thresholds"]:
            table.add_row("no root in [-e^n, e^n]", "-", "-", "-")
    elif rule == "additive":
        table.add_column("lambda", justify="right")
        table.add_column("present taxels needed", justify="right")
        for lam, count in zip(result["thresholds"], result["present_counts"]):
            table.add_row(_fmt(lam) + (" (near-double root)" if result.get("near_double_root") else ""), _fmt(count))
        if not result["thresholds"]:
            table.add_row("no root in the domain", "-")
    else:
        table.add_column("quantity")
        table.add_column("value", justify="right")
        keys = ("g_max", "threshold_mean", "threshold_initial", "threshold_final", "band_width", "present_count")
        if len(result["threshold_means"]) > 1:
            keys += ("threshold_means",)  # eq 18's second root (sec. 2.2.3.4)
        keys += tuple(k for k in ("near_double_root", "band", "eq19_bands") if k in result)
        for key in keys:
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
