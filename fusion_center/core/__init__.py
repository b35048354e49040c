"""The numerical core of the method: pure functions, no CAN, no files, no clock, no plotting.

The equations are those of the chapter "Grip Force and Slip Analysis in Robotic Grasp: New
Stochastic Paradigm Through Sensor Data Fusion"; every docstring names its equation numbers.

Modules (one job each):

* :mod:`.encoding` - the decision tuples {-1, +1} / {0, 1}, the local detector (eqs 1-4)
* :mod:`.rules` - the fusion rules: multiplicative (eq 5), additive (eq 6), preferential
  (eq 7, g(n) eq 15), k-of-n (sec. 2.2.1)
* :mod:`.curves` - the probability curves P(H1 | U_G) (eqs 8-14)
* :mod:`.thresholds` - HEBTEM thresholds (eqs 16-20)
* :mod:`.baselines` - Chair-Varshney (eq 31), Neyman-Pearson (eq 32), Bayes threshold (eq 22)
* :mod:`.poisson_binomial` - the law of the present count, in the log domain
* :mod:`.centralised` - the raw-data (centralised) tests
* :mod:`.montecarlo` - vectorised Monte Carlo of every rule, exact count-rule rates
* :mod:`.forces`, :mod:`.units` - forces (eqs 23-30, 36)
* :mod:`.geometry` - convex hull and contact area (eq 35)
* :mod:`.contact` - contact type (eqs 33-34, Table 1)
* :mod:`.slip` - slip detection (sec. 4)
* :mod:`.bus_timing` - exact CAN frame lengths and bus load

The names below are the public API (``docs/api.md``) and are imported on first use, so that
``import fusion_center.core.rules`` loads only what ``rules`` needs.
"""

from __future__ import annotations

import importlib

# public name -> core module that defines it
_EXPORTS = {
    "local_decision": "encoding",
    "present_count": "encoding",
    "to_pm1": "encoding",
    "to_01": "encoding",
    "additive": "rules",
    "multiplicative": "rules",
    "preferential": "rules",
    "preferential_sister": "rules",
    "k_of_n": "rules",
    "g_of_n": "rules",
    "p_additive_01": "curves",
    "p_additive_pm1": "curves",
    "p_multiplicative": "curves",
    "p_preferential": "curves",
    "p_linear": "curves",
    "p_exponential": "curves",
    "additive_threshold": "thresholds",
    "multiplicative_threshold": "thresholds",
    "preferential_threshold": "thresholds",
    "AdditiveThreshold": "thresholds",
    "MultiplicativeThreshold": "thresholds",
    "PreferentialThreshold": "thresholds",
    "chair_varshney_llr": "baselines",
    "np_log_statistic": "baselines",
    "neyman_pearson_fusion": "baselines",
    "NPFusionRule": "baselines",
    "bayes_log_threshold": "baselines",
    "bayes_threshold": "baselines",
    "k_of_n_error_rates": "baselines",
    "count_rule_error_rates": "baselines",
    "per_taxel_decisions": "centralised",
    "centralised_llr": "centralised",
    "centralised_decision": "centralised",
    "centralised_threshold": "centralised",
    "make_params": "centralised",
    "CentralisedParams": "centralised",
    "simulate_model": "montecarlo",
    "wilson_interval": "montecarlo",
    "taxel_rates": "montecarlo",
    "Rate": "montecarlo",
    "RuleSetup": "montecarlo",
    "MonteCarloResult": "montecarlo",
    "tangential_force": "forces",
    "gripper_tangential": "forces",
    "grip_force_limit": "forces",
    "load_cell_grip_force": "forces",
    "max_load": "forces",
    "matrix_force_report": "forces",
    "ForceReport": "forces",
    "convex_hull": "geometry",
    "contact_area": "geometry",
    "polygon_area": "geometry",
    "active_centroid": "geometry",
    "classify": "contact",
    "ContactType": "contact",
    "contact_zone": "contact",
    "ContactZone": "contact",
    "detect_slip": "slip",
    "SlipTracker": "slip",
    "SlipResult": "slip",
    "frame_bits": "bus_timing",
    "worst_case_frame_bits": "bus_timing",
    "best_case_frame_bits": "bus_timing",
    "frame_time_s": "bus_timing",
    "bus_load": "bus_timing",
    "convert_force": "units",
}
_MODULES = ("encoding", "rules", "curves", "thresholds", "baselines", "poisson_binomial", "centralised",
            "montecarlo", "forces", "units", "geometry", "contact", "slip", "bus_timing")

__all__ = sorted(_EXPORTS) + list(_MODULES)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    elif name in _MODULES:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
