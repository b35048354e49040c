"""The numerical core of the method: pure functions, no CAN, no files, no clock, no plotting.

The equations are those of the chapter "Grip Force and Slip Analysis in Robotic Grasp: New
Stochastic Paradigm Through Sensor Data Fusion"; every docstring names its equation numbers.

Modules (one job each):

* :mod:`.encoding` - the decision tuples {-1, +1} / {0, 1}, the local detector (eqs 1-4)
* :mod:`.rules` - the fusion rules: multiplicative (eq 5), additive (eq 6), preferential
  (eq 7, g(n) eq 15), k-of-n (sec. 2.2.1)
* :mod:`.curves` - the probability curves P(H1 | U_G) (eqs 8-14)
* :mod:`.thresholds` - HEBTEM thresholds (eqs 16-17 here, the names of eqs 18-20 re-exported);
  :mod:`.mean_deficit` - D(z) of Appendix I and its inverse; :mod:`.preferential_band` - the
  preferential band (eqs 18-20) and its certified decision; :mod:`.certify` - certified roots,
  counts and decisions (mpmath where rounding cannot decide)
* :mod:`.baselines` - Chair-Varshney (eq 31), Neyman-Pearson (eq 32), Bayes threshold (eq 22)
* :mod:`.poisson_binomial` - the law of the present count, in the log domain
* :mod:`.exact_rates` - exact system error rates of every rule (preferential DP, LLR/N-P by kinds),
  gathered from :mod:`.preferential_rates` (the band decision's rates, eq 7 / eq 20),
  :mod:`.chain_dp` (the DP over the chain), :mod:`.tilted_dp` (its exponentially tilted form:
  rates down to any depth; its bridge trimming :mod:`.tilted_bridge`), :mod:`.counts_dp` (the
  {0,1} counts DPs), :mod:`.dp_scaling` (the scaled probabilities the DPs share),
  :mod:`.kind_laws` (eqs 31-32 on kinds, exact ROC) and :mod:`.rate_sampling` (Monte Carlo /
  importance-sampling fallbacks)
* :mod:`.centralised` - the raw-data (centralised) tests
* :mod:`.montecarlo` - vectorised Monte Carlo of every rule, exact count-rule rates
* :mod:`.forces`, :mod:`.units` - forces (eqs 23-30, 36)
* :mod:`.geometry` - convex hull and contact area (eq 35)
* :mod:`.contact` - contact type (eqs 33-34, Table 1)
* :mod:`.slip` - slip detection (sec. 4)
* :mod:`.bus_timing` - exact CAN frame lengths and bus load
* :mod:`.layouts` - skin layouts (one-taxel or patch nodes, packed payloads, classic CAN or FD):
  exact bits per SYNC cycle, bus load, highest SYNC rate

The names below are the public API (``docs/api.md``) and are imported on first use, so that
``import fusion_center.core.rules`` loads only what ``rules`` needs.
"""

from __future__ import annotations

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__,
    submodules=["encoding", "rules", "curves", "thresholds", "certify", "baselines", "poisson_binomial",
                "exact_rates", "centralised", "montecarlo", "forces", "units", "geometry", "contact", "slip",
                "bus_timing", "layouts", "mean_deficit", "preferential_band", "preferential_rates", "chain_dp",
                "tilted_dp", "tilted_bridge", "counts_dp", "dp_scaling", "kind_laws", "rate_sampling"],
    submod_attrs={
        "encoding": ["local_decision", "LocalDetectors", "present_count", "to_pm1", "to_01"],
        "rules": ["additive", "multiplicative", "preferential", "preferential_sister", "k_of_n", "g_of_n"],
        "curves": [
            "p_additive_01", "p_additive_pm1", "p_multiplicative", "p_preferential", "p_linear",
            "p_exponential",
        ],
        "thresholds": [
            "additive_threshold", "multiplicative_threshold", "preferential_threshold", "AdditiveThreshold",
            "MultiplicativeThreshold", "PreferentialThreshold",
        ],
        "baselines": [
            "chair_varshney_llr", "np_log_statistic", "neyman_pearson_fusion", "NPFusionRule",
            "bayes_log_threshold", "bayes_threshold", "k_of_n_error_rates", "count_rule_error_rates",
        ],
        "centralised": [
            "per_taxel_decisions", "centralised_llr", "centralised_decision", "centralised_threshold",
            "make_params", "CentralisedParams",
        ],
        "montecarlo": [
            "simulate_model", "wilson_interval", "taxel_rates", "Rate", "RuleSetup", "MonteCarloResult",
        ],
        "forces": [
            "tangential_force", "gripper_tangential", "grip_force_limit", "load_cell_grip_force", "max_load",
            "matrix_force_report", "ForceReport",
        ],
        "geometry": ["convex_hull", "contact_area", "polygon_area", "active_centroid"],
        "contact": ["classify", "ContactType", "contact_zone", "ContactZone"],
        "slip": ["detect_slip", "SlipTracker", "SlipResult"],
        "bus_timing": [
            "frame_bits", "worst_case_frame_bits", "best_case_frame_bits", "frame_time_s", "bus_load",
            "fd_frame_bits",
        ],
        "layouts": [
            "skin_layout", "SkinLayout", "layout_cycle_bits", "layout_bus_use", "channels_needed",
            "pdo_frame_stats", "FrameStats", "LayoutUse",
        ],
        "units": ["convert_force"],
        "exact_rates": [
            "preferential_error_rates", "llr_error_rates", "np_kinds_fusion", "PreferentialRates", "KindRates",
            "preferential_law", "linear_statistic_law", "linear_statistic_tail", "roc_from_laws", "kinds_of",
            "importance_sampling_tail",
        ],
        "preferential_band": ["band_decision", "max_preferential_value"],
    },
)
