"""``fusion-center fuse``: fuse one vector of local decisions with one rule and decide.

Rules: the chapter's additive (eq 6), multiplicative (eq 5) and preferential (eq 7) rules
with their P(H1) curves (eqs 10-14) and HEBTEM thresholds (eqs 16-18, 20); the k-out-of-n
rule (sec. 2.2.1); and the two baselines of sec. 4.3.3, the Chair-Varshney LLR (eq 31) and
the Neyman-Pearson statistic (eq 32).

Decision convention (sec. 2.2.2): U_G >= lambda -> H1. Additive rule on {-1,+1}: eq 17
has two roots +-lambda; with ``--root auto`` (default) the root on the side of U_G's sign is
used (sec. 6.3.1, footnote 3: "we consider the left hand side of the curve since the sign of
U_G is negative"; U_G = 0 counts as the right-hand side); ``--root positive|negative`` forces
one. Multiplicative rule: compared in the log domain, ln U_G >= ln lambda; a threshold
lambda <= 0 accepts every U_G > 0. Preferential rule: H1 at or above the upper band edge
lambda_Th-final, H0 below the lower edge lambda_Th-initial, "undecided" inside the band
(eq 20).

Decisions are given as ``--u=1,-1,1`` (the ``=`` is optional: values starting with "-" are
accepted as the argument). Bad input exits 2 with one line naming the parameter, its value
and the allowed range.
"""

from __future__ import annotations

import argparse
import json
import math
import re
from fractions import Fraction
import sys

import numpy as np

from ..core import baselines
from taxel_net.errors import UsageError
from ..core.curves import check_open_unit
from ..core.encoding import check_encoding, check_integer, present_count, validate_decisions
from taxel_net.errors import ParameterError
from ..core.rules import check_weight
from .threshold import parse_number, parse_option

HELP = "fuse one vector of local decisions u_i with a fusion rule (HEBTEM or a baseline) and decide H0/H1"

RULES = ("additive", "multiplicative", "preferential", "k-of-n", "llr", "np")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # let "--u -1,1,..." through: argparse would take "-1,1" for an option otherwise
    # (this parser has no option that looks like a negative number)
    parser._negative_number_matcher = re.compile(r"^-[\d.,\s+-]*$")
    parser.add_argument("--rule", required=True, choices=RULES, help="fusion rule")
    parser.add_argument("--u", required=True, help="local decisions, comma separated (e.g. 1,-1,1)")
    parser.add_argument("--tuple", default="pm1", dest="tuple", help="decision tuple: pm1 ({-1,+1}, default) or 01")
    parser.add_argument("--p", help="preferential: weight of the succeeding taxel, [0, 2] (default 1)")
    parser.add_argument("--q", help="preferential: weight of the preceding taxel, [0, 2] (default 1)")
    parser.add_argument("--k", help="k-of-n: H1 iff at least k taxels report present (1..n)")
    parser.add_argument("--xi", help="P(H1) with every taxel absent, (0, 1): enables P(H1) and the HEBTEM threshold")
    parser.add_argument("--alpha", help="Type I error level, (0, 1): additive and preferential thresholds")
    parser.add_argument("--beta", help="Type II error level, (0, 1): multiplicative threshold")
    parser.add_argument(
        "--root", choices=("auto", "positive", "negative"),
        help="additive {-1,+1}: which root of eq 17 (auto: the side of U_G's sign, sec. 6.3.1)",
    )
    parser.add_argument("--band", choices=("centred", "eq19"),
                        help="preferential: band centred on lambda_mean (default) or the band of eqs 19-20")
    parser.add_argument("--pd", help="llr/np/k-of-n (and additive/multiplicative with a threshold: exact system"
                        " P_D, P_F of the rule in count form): detection probability 1 - P_M per taxel (list) or one value")
    parser.add_argument("--pf", help="llr/np/k-of-n/additive/multiplicative: false-alarm probability P_F per taxel"
                        " (list) or one value")
    parser.add_argument("--prior-h1", help="llr: prior P(H1) in (0, 1) (default 0.5)")
    parser.add_argument("--false-alarm", help="np: system false-alarm rate in (0, 1) of the randomised N-P rule")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


# ------------------------------------------------------------------ parsing helpers
def _open_unit(name: str, text) -> float:
    return parse_option(name, text, lambda v: check_open_unit(name, v))


# options that only some rules use (argparse dest -> rules); anything else is a usage error
_RULE_OPTIONS = {
    "p": ("preferential",), "q": ("preferential",), "k": ("k-of-n",),
    "xi": ("additive", "multiplicative", "preferential"), "alpha": ("additive", "preferential"),
    "beta": ("multiplicative",), "pd": ("k-of-n", "llr", "np", "additive", "multiplicative", "preferential"),
    "pf": ("k-of-n", "llr", "np", "additive", "multiplicative", "preferential"), "prior_h1": ("llr",),
    "false_alarm": ("np",), "root": ("additive",), "band": ("preferential",),
}


def _check_options(args) -> None:
    for dest, users in _RULE_OPTIONS.items():
        if getattr(args, dest) is not None and args.rule not in users:
            flag = "--" + dest.replace("_", "-")
            raise UsageError(f"{flag} does not apply to --rule {args.rule} (only to: {', '.join(users)})")


def _number_list(name: str, text: str, allowed: str, integers: bool = False) -> np.ndarray:
    tokens = [t.strip() for t in str(text).split(",")]
    if tokens == [""]:
        raise ParameterError(name, text, allowed + "; got an empty list (n >= 1 needed)")
    values = []
    for i, token in enumerate(tokens):
        try:
            parsed = parse_number(f"{name}[{i}]", token)  # no silent underflow (1e-400 -> 0)
        except ParameterError as exc:
            raise ParameterError(f"{name}[{i}]", token, allowed if token else exc.allowed) from None
        if integers and not isinstance(parsed, int):  # 1.0000000000000001 would round to 1
            raise ParameterError(f"{name}[{i}]", token, allowed)
        value = float(parsed)
        if not math.isfinite(value):
            raise ParameterError(f"{name}[{i}]", token, allowed)
        values.append(value)
    return np.array(values)


def parse_decisions(text: str, encoding: str) -> np.ndarray:
    allowed = "-1 or 1 for tuple 'pm1'" if encoding == "pm1" else "0 or 1 for tuple '01'"
    values = _number_list("u", text, f"must be a comma-separated list of decisions ({allowed})", integers=True)
    return validate_decisions(values, encoding)


def _probabilities(name: str, text, n: int) -> np.ndarray:
    if text is None:
        raise ParameterError(name, None, "required for this rule: one probability in (0, 1) or n comma-separated ones")
    values = _number_list(name, text, "must be probabilities in the open interval (0, 1)")
    if values.size not in (1, n):
        raise ParameterError(name, f"{values.size} values", f"must give 1 or n={n} probabilities")
    return baselines._open_probabilities(values if values.size == n else values[0], name, n)


# ------------------------------------------------------------------ threshold adapters
def _side_root(roots, u_g: float, side: str) -> tuple[float, str, str]:
    """Pick the additive {-1,+1} threshold: (lambda, side, source).

    ``side`` "auto" takes the side of U_G's sign (sec. 6.3.1, footnote 3; U_G = 0 counts as
    positive). On that side we use a root of eq 17 if there is one ("root"); otherwise the
    mirror image -lambda of the root on the other side ("mirror"): sec. 2.2.3.2, "we can use
    either of the two thresholds, namely lambda_Th or -lambda_Th" (symmetric thresholding --
    eq 17 itself has a single root for xi <= 1/4).
    """
    finite = sorted(float(r) for r in roots if r is not None and math.isfinite(float(r)))
    if side == "auto":
        side = "negative" if u_g < 0 else "positive"
    on_side = [r for r in finite if (r < 0 if side == "negative" else r >= 0)]
    if on_side:
        return (on_side[0] if side == "negative" else on_side[-1]), side, "root"
    other = [r for r in finite if r != 0.0]
    if not other:
        raise ParameterError("root", side, f"no {side} threshold: eq 17 roots are {finite}")
    mirror = -(other[-1] if side == "negative" else other[0])
    return mirror, side, "mirror"


def _count_form_rates(args, record: dict, min_present: int) -> None:
    """With --pd/--pf: exact system P_D, P_F of "H1 iff K >= min_present" (Poisson-binomial)."""
    if args.pd is None and args.pf is None:
        return
    n = record["n"]
    min_present = min(max(0, min_present), n + 1)
    rates = baselines.count_rule_error_rates(min_present, _probabilities("pd", args.pd, n),
                                             _probabilities("pf", args.pf, n))
    record["min_present_count"] = min_present
    record["p_detect"] = rates.p_detect
    record["p_false_alarm"] = rates.p_false_alarm
    record["log_p_false_alarm"] = rates.log_p_false_alarm


def _hebtem(args, rule: str, u: np.ndarray, encoding: str, record: dict) -> None:
    """P(H1) on the rule's curve and, with --alpha/--beta, the HEBTEM threshold and decision."""
    from ..core import curves, rules  # the numerical core of sec. 2.2.3

    n = u.size
    xi = _open_unit("xi", args.xi) if args.xi is not None else None
    alpha = _open_unit("alpha", args.alpha) if args.alpha is not None else None
    beta = _open_unit("beta", args.beta) if args.beta is not None else None
    if (args.pd is not None or args.pf is not None) and alpha is None and beta is None:
        raise UsageError(f"--pd/--pf with --rule {rule} give the error rates of its HEBTEM threshold: "
                         f"add --xi and --{'beta' if rule == 'multiplicative' else 'alpha'}")
    if xi is None:
        if alpha is not None or beta is not None:
            raise ParameterError("xi", None, "required with --alpha/--beta: a number in the open interval (0, 1)")
        return

    if rule == "additive":
        u_g = record["U_G"]
        record["p_h1"] = float(
            curves.p_additive_pm1(u_g, n, xi) if encoding == "pm1" else curves.p_additive_01(u_g, n, xi)
        )
        if alpha is None:
            return
        from ..core import thresholds

        result = thresholds.additive_threshold(n, xi, alpha, encoding=encoding)
        if not result.thresholds:  # a result, not an error: no threshold, no decision
            domain = "[-n, n]" if encoding == "pm1" else "[0, n]"
            record["no_root"] = f"eq 17 has no root in {domain} for n={n}, xi={xi}, alpha={alpha}"
            return
        if encoding == "pm1":
            lam, side, source = _side_root(result.thresholds, u_g, args.root or "auto")
            record["threshold_side"] = side
            record["threshold_source"] = source
        else:
            lam = float(result.thresholds[-1])
        record["threshold"] = lam
        record["decision"] = "H1" if u_g >= lam else "H0"
        # U_G = 2K - n (pm1) or K (01) >= lambda  <=>  K >= min_present_count
        _count_form_rates(args, record, math.ceil((n + Fraction(lam)) / 2) if encoding == "pm1" else math.ceil(lam))
    elif rule == "multiplicative":
        # the curve (eqs 10-11) and eq 16 are written for the {-1,+1} tuple (fig. 2a):
        # with {0,1} decisions we evaluate them at the equivalent ln U_G = 2K - n
        ln_u_g_pm1 = float(2 * record["present_count"] - n)
        if encoding == "01":
            record["ln_U_G_pm1"] = ln_u_g_pm1  # what p_h1 and the threshold are evaluated at
        record["p_h1"] = float(curves.p_multiplicative(ln_u_g_pm1, n, xi))
        if beta is None:
            return
        from ..core import thresholds

        result = thresholds.multiplicative_threshold(n, xi, beta)
        if not result.scaled_thresholds:  # a result, not an error: no threshold, no decision
            record["no_root"] = f"eq 16 has no root in [-e^n, e^n] for n={n}, xi={xi}, beta={beta}"
            return
        scaled = float(result.scaled_thresholds[-1])
        ln_lam = result.ln_thresholds[-1]
        record["scaled_threshold"] = scaled  # lambda / e^n
        if ln_lam is not None:
            ln_lam = float(ln_lam)
            record["ln_threshold"] = ln_lam
            record["threshold"] = math.exp(ln_lam) if ln_lam < 709.0 else None
            record["decision"] = "H1" if ln_u_g_pm1 >= ln_lam else "H0"
            # e^(2K - n) >= lambda  <=>  K >= (n + ln lambda)/2
            _count_form_rates(args, record, math.ceil((n + Fraction(ln_lam)) / 2))
        else:  # lambda <= 0: every U_G > 0 accepts H1
            record["ln_threshold"] = None
            record["threshold"] = scaled * math.exp(n) if n < 709 else None
            record["decision"] = "H1"
            _count_form_rates(args, record, 0)
    elif rule == "preferential":
        p, q = record["p"], record["q"]
        g = float(rules.g_of_n(n, p, q))
        record["g"] = g
        record["p_h1"] = float(curves.p_preferential(record["U_G"], g, xi))
        if alpha is None:
            return
        from ..core import thresholds

        band = thresholds.preferential_threshold(n, xi, alpha, p, q, encoding=encoding, band=args.band or "centred")
        if band.near_double_root:
            record["near_double_root"] = True
        if band.threshold_mean is None:  # a result, not an error: no threshold, no decision
            record["no_root"] = f"eq 18 has no root in [-g, g] for xi={xi}, alpha={alpha}: 3 alpha/(1 - xi) > 9/4"
            return
        if band.band == "eq19":
            record["band"] = "eq19"
            if band.threshold_initial is None:
                record["threshold"] = float(band.threshold_mean)
                record["no_root"] = f"eqs 19-20 have no band in [-g, g] for xi={xi}, alpha={alpha}"
                return
        low, high = float(band.threshold_initial), float(band.threshold_final)
        record["threshold"] = float(band.threshold_mean)
        record["threshold_initial"] = low
        record["threshold_final"] = high
        record["band_width"] = float(band.band_width)
        if args.pd is not None or args.pf is not None:
            _preferential_rates(args, record, p, q, encoding, low, high)
        # exact U_G against the band edges (mpmath where rounding cannot decide)
        from ..core.preferential_band import band_decision

        record["decision"] = band_decision(band, record["U_G"], u)


def _preferential_rates(args, record: dict, p, q, encoding, low: float, high: float) -> None:
    """With --pd/--pf: exact system rates of the band decision (DP over the chain, exact_rates)."""
    from ..core.exact_rates import preferential_error_rates

    n = record["n"]
    rates = preferential_error_rates(_probabilities("pd", args.pd, n), _probabilities("pf", args.pf, n),
                                     p, q, encoding, low, high)
    for key in ("p_detect", "p_false_alarm", "p_undecided_h1", "p_undecided_h0"):
        record[key] = getattr(rates, key)
    for key in ("p_detect", "p_false_alarm", "p_undecided_h1", "p_undecided_h0"):
        record["log_" + key] = getattr(rates, "log_" + key)
    record["rates_method"] = rates.method
    keys = ("p_detect", "p_false_alarm", "p_undecided_h1", "p_undecided_h0")
    below = [key for key in keys if key in rates.below_floor]
    if below:  # plain values below 1e-300 (subnormal or 0.0, not impossible): the log_ fields hold
        # their exact logarithms, null only where none was computed (beyond the exact DP's budget)
        record["rates_below_1e-300"] = below
    # a rate whose proven relative error bound exceeds 1e-13 (the tilted DP's, where the exact DP
    # was beyond its budget): named with log10 of its bound, never silently inexact
    loose = {key: bound for key, bound in (rates.error_bounds or {}).items() if key in keys and not bound <= -13.0}
    if loose:
        record["rates_error_bound_log10"] = loose
    if rates.ci95:
        record["rates_ci95"] = {k: list(v) for k, v in rates.ci95.items()}


def _baseline_rates(record: dict, pd, pf, prior: float) -> None:
    """Exact P_D, P_F of "ln Lambda > threshold" (eq 31/32), or a Monte Carlo estimate, said so."""
    from ..core.exact_rates import llr_error_rates

    rates = llr_error_rates(pd, pf, prior)
    record["p_detect"] = rates.p_detect
    record["p_false_alarm"] = rates.p_false_alarm
    record["log_p_false_alarm"] = math.log(rates.p_false_alarm) if rates.p_false_alarm > 0 else None
    record["rates_method"] = rates.method
    if rates.ci95:
        record["rates_ci95"] = {k: list(v) for k, v in rates.ci95.items()}


# eqs 31-32: Lambda = lambda_threshold is the chapter's undefined case (sec. 6.2)
_DECISION = {1: "H1", 0: "undecided", -1: "H0"}


# ------------------------------------------------------------------ the command
def fuse(args) -> dict:
    """Evaluate the requested rule; returns the record printed by the command."""
    _check_options(args)
    encoding = check_encoding(args.tuple)
    u = parse_decisions(args.u, encoding)
    n = int(u.size)
    record: dict = {
        "rule": args.rule,
        "tuple": encoding,
        "n": n,
        "present_count": present_count(u, encoding),
        "U_G": None,
        "ln_U_G": None,
        "p_h1": None,
        "threshold": None,
        "decision": None,
    }
    rule = args.rule
    if rule in ("additive", "multiplicative", "preferential", "k-of-n"):
        from ..core import rules

        if rule == "additive":
            record["U_G"] = int(rules.additive(u, encoding))
        elif rule == "multiplicative":
            value = rules.multiplicative(u, encoding)
            record["ln_U_G"] = float(value.ln_U_G)
            record["U_G"] = float(value.U_G)
        elif rule == "preferential":
            record["p"] = parse_option("p", "1" if args.p is None else args.p, lambda v: check_weight("p", v))
            record["q"] = parse_option("q", "1" if args.q is None else args.q, lambda v: check_weight("q", v))
            record["U_G"] = float(rules.preferential(u, record["p"], record["q"], encoding))
        else:
            if args.k is None:
                raise ParameterError("k", None, f"required for --rule k-of-n: an integer in 1..n (n = {n})")
            allowed = f"must be an integer in 1..n (n = {n})"
            k = parse_option("k", args.k, lambda v: check_integer("k", v, 1, n, allowed=allowed))
            record["k"] = k
            record["U_G"] = int(rules.k_of_n(u, k, encoding))
            record["decision"] = "H1" if record["U_G"] == 1 else "H0"
            if args.pd is not None or args.pf is not None:
                pd = _probabilities("pd", args.pd, n)
                pf = _probabilities("pf", args.pf, n)
                rates = baselines.count_rule_error_rates(k, pd, pf)
                record["p_detect"] = rates.p_detect
                record["p_false_alarm"] = rates.p_false_alarm
                record["log_p_false_alarm"] = rates.log_p_false_alarm
        if rule != "k-of-n":
            _hebtem(args, rule, u, encoding, record)
        return record

    pd = _probabilities("pd", args.pd, n)
    pf = _probabilities("pf", args.pf, n)
    if rule == "llr":
        prior = _open_unit("prior_h1", "0.5" if args.prior_h1 is None else args.prior_h1)
        llr = baselines.chair_varshney_llr(u, pd, pf, encoding, prior_h1=prior)
        record.update(U_G=llr, statistic="ln P(H1|U)/P(H0|U) (eq 31)", prior_h1=prior, threshold=0.0)
        record["decision"] = _DECISION[baselines.compare_log_ratio(llr, 0.0)]
        _baseline_rates(record, pd, pf, prior)
        return record
    # np
    ln_lr = baselines.np_log_statistic(u, pd, pf, encoding)
    record.update(U_G=ln_lr, statistic="ln P(U|H1)/P(U|H0) (eq 32)")
    if args.false_alarm is None:
        # the chapter's comparison: Lambda(U) against lambda_threshold = 1 (ln 1 = 0)
        record["threshold"] = 0.0
        record["decision"] = _DECISION[baselines.compare_log_ratio(ln_lr, 0.0)]
        _baseline_rates(record, pd, pf, 0.5)  # Lambda > 1 is eq 31's test with P1 = P0
        return record
    alpha = _open_unit("false_alarm", args.false_alarm)
    np_rule = baselines.neyman_pearson_fusion(pd, pf, alpha)
    record.update(
        np_method=np_rule.method,
        np_statistic=np_rule.statistic,
        threshold=np_rule.log_threshold,
        count_threshold=np_rule.count_threshold,
        gamma=np_rule.gamma,
        achieved_false_alarm=np_rule.achieved_false_alarm,
        detection_probability=np_rule.detection_probability,
        optimal=np_rule.optimal,
        decision=np_rule.decide(u, encoding),
        p_detect=np_rule.detection_probability,
        p_false_alarm=np_rule.achieved_false_alarm,
    )
    return record


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None  # e.g. U_G = e^n beyond the float range: ln_U_G carries the value
    if isinstance(value, (np.floating, np.integer)):
        return _json_safe(value.item())
    return value


def run(args) -> int:
    record = fuse(args)
    if args.json:
        print(json.dumps({key: _json_safe(value) for key, value in record.items()}))
        return 0
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"fusion-center fuse: {record['rule']} rule, tuple {record['tuple']}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for key, value in record.items():
        if value is None or key in ("rule", "tuple"):
            continue
        table.add_row(key, f"{value:.6g}" if isinstance(value, float) else str(value))
    Console(file=sys.stdout, width=100).print(table)
    return 0
