"""Exact system error rates of every fusion rule: the preferential rule (eq 7 with the band of
eq 20) by a dynamic programme over the chain, Chair-Varshney / Neyman-Pearson (eqs 31-32) on
taxels that come in kinds, and their Monte Carlo / importance-sampling fallbacks.

This module gathers the public names of the modules that do the work (one job each):

* :mod:`.chain_dp` - the DP over the chain: U_G's law (eq 7) for independent taxels (its
  tilted form :mod:`.tilted_dp` with :mod:`.tilted_bridge`, the {0,1} counts DPs
  :mod:`.counts_dp`, the scaling they share :mod:`.dp_scaling`);
* :mod:`.preferential_rates` - the band decision's rates P(H1 decided), P(H0 decided),
  P(undecided) under H0 and H1 (:func:`preferential_error_rates`) and U_G's law
  (:func:`preferential_law`);
* :mod:`.kind_laws` - the laws of eq 31/32's statistic on kinds, LLR / N-P rates, exact ROC;
* :mod:`.rate_sampling` - Monte Carlo and importance-sampling fallbacks.
"""

from __future__ import annotations

from .chain_dp import FLOOR, _lattice
from .kind_laws import (KIND_ATOMS_MAX, KindRates, _kind_atoms, kinds_of, linear_statistic_law,
                        linear_statistic_tail, llr_error_rates, np_kinds_fusion, roc_from_laws)
from .preferential_rates import (SPARSE_MAX_TAXELS, PreferentialRates, exact_counts_max_taxels, preferential_error_rates,
                                 preferential_law)
from .rate_sampling import importance_sampling_tail

# private names other modules reach through this one (report/build.py, montecarlo.py, baselines.py)
_REEXPORTED = (_lattice, _kind_atoms, exact_counts_max_taxels)

__all__ = [
    "PreferentialRates",
    "preferential_error_rates",
    "preferential_law",
    "FLOOR",
    "SPARSE_MAX_TAXELS",
    "KindRates",
    "kinds_of",
    "llr_error_rates",
    "np_kinds_fusion",
    "KIND_ATOMS_MAX",
    "linear_statistic_law",
    "linear_statistic_tail",
    "roc_from_laws",
    "importance_sampling_tail",
]
