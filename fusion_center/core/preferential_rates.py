"""Exact system error rates of the preferential rule (eq 7 with the band of eq 20): P(H1
decided), P(H0 decided), P(undecided) under H1 and H0 for independent taxels with any per-taxel
Pd_i / Pf_i, and U_G's law.

Which DP (:mod:`.chain_dp`, :mod:`.tilted_dp`, :mod:`.counts_dp`, :mod:`.extended_dp`):

* U_G on a lattice (``_lattice``: {-1,+1} with p, q > 0 -- "chain"; one zero weight --
  "lattice"; integer p, q on either tuple -- "integer"): the lattice DP over the chain tilted
  towards each region (:mod:`.tilted_dp`), every rate with a proven relative error bound,
  accepted at or below 10^BOUND_OK = 1e-13, the rates below FLOOR = 1e-300 included;
* {0,1} with a non-integer weight ("exact-counts"): U_G = a + b (2^p + 2^q) + d 2^(p+q) over
  three integer counts, a DP over them (polynomial; within budget up to SPARSE_MAX_TAXELS for
  any probabilities); where U_G needs two integer coordinates only (a zero weight, p or q an
  integer, p + q an integer) a DP over those two instead, up to TWO_COUNTS_MAX_TAXELS; every
  rate >= FLOOR exact; a Monte Carlo estimate with 95 % Wilson intervals beyond
  ("monte-carlo", said so);
* what those leave uncertified (``deep``, the default) -- a rate below FLOOR without a log (the
  tilt capped short of a region reachable only through decisions of tiny probability; a counts
  sum below FLOOR, or 0.0 that may be an underflow), or a bound above 1e-13 -- is recomputed
  by the extended-exponent DP of :mod:`.extended_dp` (no trimming, no underflow: its exact log,
  or -inf exactly when the event has probability 0), within its budget EXACT_WORK_MAX; beyond
  it the rate stays in ``below_floor`` with log None (or, for a bound, the tilted value).

Each comparison of U_G with a band edge is exact (mpmath where rounding cannot decide); the
three probabilities per hypothesis are sums of positive terms (the tilted DP's bulk region:
1 minus two rates that sum to at most 1/2, through log1p).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from taxel_net.errors import ParameterError

from .chain_dp import _float_value, _label_base, _lattice, _lattice_law
from .counts_dp import _rates_counts, _rates_two_counts, _two_count_form
from .dp_scaling import _LOG_FLOOR, FLOOR, _log_probability
from .extended_dp import counts_exact_logs, lattice_exact_logs
from .rate_sampling import monte_carlo_band_rates, wilson
from .tilted_dp import BOUND_OK, lattice_band_logs

SPARSE_MAX_TAXELS = 200
"""{0,1} with a non-integer weight: up to this many taxels the counts DP (counts_dp._rates_counts)
stays within its budget for any per-taxel probabilities (200 taxels at pi = 0.5: ~3.5 s), so the
rates are exact; beyond, exact while the budget holds (the law's box stays small), otherwise a
Monte Carlo estimate (method "monte-carlo"). The name is kept from the sparse DP it replaced."""
COUNTS_MAX_TAXELS = SPARSE_MAX_TAXELS
TWO_COUNTS_MAX_TAXELS = 1000
"""{0,1} where U_G needs two integer coordinates only (a zero weight, p or q an integer, p + q an
integer: counts_dp._two_count_form): the two-count DP (counts_dp._rates_two_counts) up to this
many taxels while its budget (counts_dp.TWO_COUNTS_WORK_MAX, ~1 s) holds -- for any
probabilities to ~300 taxels with p or q an integer, ~500 with p + q an integer or a zero
weight; beyond, Monte Carlo (the three-count DP would take minutes there)."""


def exact_counts_max_taxels(p: float, q: float) -> int:
    """Taxels up to which {0,1} with a non-integer weight has exact rates for any per-taxel
    probabilities: TWO_COUNTS_MAX_TAXELS where the two-count form applies, else
    SPARSE_MAX_TAXELS (the three-count DP)."""
    return TWO_COUNTS_MAX_TAXELS if _two_count_form(float(p), float(q)) is not None else SPARSE_MAX_TAXELS


def _log(x: float) -> float | None:
    return math.log(x) if x > 0.0 else None


_NAMES = ("p_detect", "p_undecided_h1", "p_miss", "p_false_alarm", "p_undecided_h0", "p_reject")


@dataclass(frozen=True)
class PreferentialRates:
    """System rates of the preferential band decision (eq 7, eq 20 band). Under H1: p_detect =
    P(H1 decided), p_undecided_h1, p_miss = P(H0 decided); under H0: p_false_alarm = P(H1
    decided), p_undecided_h0, p_reject = P(H0 decided). log_*: natural logarithms, exact
    whatever their size; None for an impossible event (probability 0: no decision vector
    reaches the region, or only through a taxel of probability exactly 0 or 1) -- except for a
    rate named in ``below_floor`` with log None, one below FLOOR whose log was not computed
    (``deep=False``, or beyond extended_dp.EXACT_WORK_MAX). ``below_floor`` names the rates
    below FLOOR = 1e-300 (their plain value underflows: exp of the log, 0.0 below ~5e-324,
    subnormal below ~2.2e-308). ``error_bounds`` (lattice cases): log10 of each rate's
    proven relative error bound (trimming; -inf where nothing was trimmed, e.g. the
    extended-exponent DP; rounding adds ~1e-13). method: "chain", "lattice",
    "integer", "exact-counts" (exact) or "monte-carlo" (estimate, with ``ci95`` per rate and
    ``samples``)."""

    log_p_detect: float | None
    log_p_undecided_h1: float | None
    log_p_miss: float | None
    log_p_false_alarm: float | None
    log_p_undecided_h0: float | None
    log_p_reject: float | None
    method: str
    samples: int | None = None
    ci95: dict | None = None
    below_floor: tuple = ()
    error_bounds: dict | None = None

    def __getattr__(self, name):
        if name in _NAMES:
            log = object.__getattribute__(self, "log_" + name)
            return 0.0 if log is None else math.exp(log)
        raise AttributeError(name)

    def logs(self) -> dict:
        return {f"log_{k}": getattr(self, "log_" + k) for k in _NAMES}

    def as_dict(self) -> dict:
        out = {k: getattr(self, k) for k in _NAMES}
        out.update(self.logs())
        return out


def _check_probs(name: str, values, n: int) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,) or not np.all(np.isfinite(arr)) or np.any(arr < 0.0) or np.any(arr > 1.0):
        raise ParameterError(name, values if arr.ndim == 0 else "a list", f"must be one or n={n} probabilities in [0, 1]")
    return arr



def preferential_law(pi, p, q, encoding: str, *, deep: bool = True, max_runs: int = 16):
    """The law of U_G (eq 7) for independent taxels present with probabilities ``pi``: (values,
    ln probabilities), values ascending (floats; equal values merged). Lattice cases only
    (module doc); None for {0,1} with a non-integer weight.

    Which atoms: every atom of probability >= FLOOR = 1e-300 (the lattice DP of
    :mod:`.chain_dp`, exact to ~1e-13 relative). With ``deep`` (default) also the atoms below
    FLOOR beyond the outermost atom >= FLOOR on either side, outward from it, by runs of the
    tilted DP (:func:`.tilted_dp.lattice_law_tail_atoms`: the tilted mean at the frontier,
    every atom kept with a proven relative error bound below 1e-13), up to ``max_runs`` runs per
    side (each O(n sqrt n): at n = 57 a few ms, the whole range in 2-6 runs; at n = 10^4 about
    0.5 s and a few hundred values of U_G per run) -- atoms beyond the last run are left out.
    Not computed in any mode: atoms below FLOOR lying between atoms >= FLOOR (e.g. a start
    label whose two first taxels are all but impossible). Without ``deep`` every atom below
    FLOOR is left out (< 1e-300 each and < 1e-290 together)."""
    from .encoding import check_encoding
    from .rules import check_weight

    p = check_weight("p", p)
    q = check_weight("q", q)
    encoding = check_encoding(encoding)
    pi = _check_probs("pi", pi, np.asarray(pi).size)
    n = pi.size
    if n == 1:
        u0 = 0.0 if encoding == "01" else -1.0
        atoms = {u0: 1.0 - pi[0], 1.0: pi[0]}
        vals = np.array(sorted(v for v, w in atoms.items() if (w > 0.0 if deep else w >= FLOOR)))
        return vals, np.log([atoms[v] for v in vals])
    lat = _lattice(p, q, encoding)
    if lat is None:
        return None
    p, q = lat.p, lat.q
    pi_l = pi[::-1] if lat.reverse else pi
    laws, scale, _ = _lattice_law(pi_l, lat)
    unit = _float_value(lat.unit, p, q)[0]
    keyed = {}  # (ls, le, x) -> ln P, the atoms >= FLOOR
    for (ls, le), (x_first, arr) in laws.items():
        for j in np.flatnonzero(arr):
            log = _log_probability(arr[j], scale)
            if log >= _LOG_FLOOR:
                keyed[(ls, le, int(x_first + j))] = log
    if deep and keyed:
        from .tilted_dp import lattice_law_tail_atoms

        xs = [k[2] for k in keyed]
        for frontier, upward in ((max(xs) + 1, True), (min(xs) - 1, False)):
            more, _ = lattice_law_tail_atoms(pi_l, lat, frontier, upward, max_runs)
            for key, log in more.items():
                keyed.setdefault(key, log)
    bases = {}
    vals = np.empty(len(keyed))
    logs = np.empty(len(keyed))
    for j, ((ls, le, x), log) in enumerate(keyed.items()):
        if (ls, le) not in bases:
            bases[(ls, le)] = _float_value(_label_base(lat, ls, le), p, q)[0]
        vals[j] = bases[(ls, le)] + unit * x
        logs[j] = log
    order = np.argsort(vals, kind="stable")
    vals, logs = vals[order], logs[order]
    uniq, start = np.unique(vals, return_index=True)
    merged = np.array([_logsumexp_arr(logs[s:e]) for s, e in zip(start, np.r_[start[1:], vals.size])])
    return uniq, merged


def _logsumexp_arr(x: np.ndarray) -> float:
    top = float(x.max())
    return top + math.log(float(np.exp(x - top).sum()))


def preferential_error_rates(pd, pf, p, q, encoding: str, low: float, high: float, n: int | None = None,
                             *, samples: int = 100_000, rng: np.random.Generator | None = None,
                             deep: bool = True) -> PreferentialRates:
    """Exact system rates of "H1 iff U_G >= high, H0 iff U_G < low" (eq 7, eq 20 band) for
    independent taxels with P(present) = pd_i under H1 and pf_i under H0 (module doc).

    ``pd``, ``pf``: one value or n values in [0, 1]; ``n`` required when both are scalars.
    ``deep``: compute the logs of the rates below FLOOR too (the tilted DP of :mod:`.tilted_dp`,
    and :mod:`.extended_dp` for what the fast DPs leave uncertified; extra time only when such
    rates exist); False leaves the logs below FLOOR None (those rates named in ``below_floor``;
    so is an impossible event where a fast DP cannot tell it from an underflow).
    """
    from .encoding import check_encoding
    from .rules import check_weight

    p = check_weight("p", p)
    q = check_weight("q", q)
    encoding = check_encoding(encoding)
    if n is None:
        n = np.asarray(pd).size if np.asarray(pd).ndim else np.asarray(pf).size
    pd_arr = _check_probs("pd", pd, n)
    pf_arr = _check_probs("pf", pf, n)
    lat = _lattice(p, q, encoding) if n >= 2 else None
    if n == 1:  # U_G = u_1 (boundary on both sides): an integer
        method = "integer"
        results = [_rates_single(pi[0], encoding, low, high) for pi in (pd_arr, pf_arr)]
    elif lat is not None:  # the lattice DP, trimmed by the tilted law (tilted_dp)
        method = lat.method
        bounds = {}
        results = []
        for h, pi in enumerate((pd_arr, pf_arr)):
            regions = lattice_band_logs(pi, lat, low, high, deep=deep)
            if deep:  # what the tilted DP leaves uncertified: exact in extended exponents
                regions = _exact_where_needed(regions,
                                              lambda need, pi=pi: lattice_exact_logs(pi, lat, low, high, need))
            results.append([(log, under) for log, under, _ in regions])
            bounds.update({_NAMES[3 * h + r]: b for r, (_, _, b) in enumerate(regions) if b is not None})
    else:  # {0,1} with a non-integer weight: the counts DP (polynomial), Monte Carlo beyond its budget
        method = "exact-counts"
        results = [None, None]
        if _two_count_form(p, q) is not None and n <= TWO_COUNTS_MAX_TAXELS:
            results = [_rates_two_counts(pd_arr, p, q, low, high)]
            results.append(_rates_two_counts(pf_arr, p, q, low, high) if results[0] is not None else None)
        if results[1] is None and (_two_count_form(p, q) is None or n <= SPARSE_MAX_TAXELS):
            results = [_rates_counts(pd_arr, p, q, low, high)]
            results.append(_rates_counts(pf_arr, p, q, low, high) if results[0] is not None else None)
        if results[1] is None:
            rng = rng if rng is not None else np.random.default_rng(0)
            r1 = monte_carlo_band_rates(pd_arr, p, q, encoding, low, high, samples, rng)
            r0 = monte_carlo_band_rates(pf_arr, p, q, encoding, low, high, samples, rng)
            ci = {name: wilson(x * samples, samples) for name, x in zip(_NAMES, (*r1, *r0))}
            logs = [(math.log(x) if x > 0 else None) for x in (*r1, *r0)]
            return PreferentialRates(*logs, method="monte-carlo", samples=samples, ci95=ci)
        if deep:  # the rates below FLOOR (or 0.0, perhaps underflowed): exact in extended exponents
            results = [[(log, under) for log, under, _ in _exact_where_needed(
                [(log, under, None) for log, under in res],
                lambda need, pi=pi: counts_exact_logs(pi, p, q, low, high, need))]
                for res, pi in zip(results, (pd_arr, pf_arr))]
    flat = [*results[0], *results[1]]
    below = tuple(name for name, (_, low_) in zip(_NAMES, flat) if low_)
    return PreferentialRates(*[log for log, _ in flat], method=method, below_floor=below,
                             error_bounds=bounds if lat is not None else None)


def _exact_where_needed(regions, exact):
    """``regions`` (per region: ln P or None, below FLOOR, log10 error bound or None) with every
    rate a fast DP left uncertified -- below FLOOR without a log (not reached, or 0.0 that may
    be an underflow), or with an error bound above 10^BOUND_OK -- replaced by its exact log from
    ``exact(needed regions)`` (:mod:`.extended_dp`: -inf only for probability 0, an impossible
    event; error bound -inf, nothing trimmed). Left as they are where ``exact`` returns None
    (beyond its budget)."""
    need = tuple(r for r, (log, under, bound) in enumerate(regions)
                 if (log is None and under) or (bound is not None and not bound <= BOUND_OK))  # NaN too
    if not need:
        return regions
    got = exact(need)
    if got is None:
        return regions
    out = list(regions)
    for r in need:
        log = got[r]
        out[r] = (None, False, None) if log == -math.inf else (log, log < _LOG_FLOOR, -math.inf)
    return out


def _rates_single(pi: float, encoding: str, low: float, high: float):
    """One taxel: U_G = u_1 in {-1, 1} or {0, 1} (eq 7 with u_0 = u_2 = 0): per region (ln P or
    None for an impossible event, below FLOOR), exact whatever the size."""
    logs: list = [[], [], []]
    for value, log in ((1.0, math.log(pi) if pi > 0.0 else None),
                       (-1.0 if encoding == "pm1" else 0.0, math.log1p(-pi) if pi < 1.0 else None)):
        if log is not None:
            logs[0 if value >= high else (2 if value < low else 1)].append(log)
    out = []
    for parts in logs:
        if not parts:
            out.append((None, False))
        else:
            top = max(parts)
            log = top + math.log(math.fsum(math.exp(x - top) for x in parts))
            out.append((log, log < _LOG_FLOOR))
    return out

