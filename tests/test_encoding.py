import numpy as np
import pytest

from fusion_center.core.encoding import local_decision, present_count, to_01, to_pm1, validate_decisions
from taxel_net.errors import ParameterError


def test_local_decision_eqs_1_to_4_threshold_is_inclusive():
    # Y = X - N >= zeta -> present (eq 3 uses >=)
    x = np.array([2.0, 1.9999, 5.0, np.nan])
    u = local_decision(x, noise=1.0, zeta=1.0, encoding="pm1")
    assert u.tolist() == [1, -1, 1, -1]
    assert local_decision(x, 1.0, 1.0, encoding="01").tolist() == [1, 0, 1, 0]


def test_local_decision_per_taxel_zeta():
    u = local_decision([3.0, 3.0], noise=[0.0, 0.0], zeta=[2.0, 4.0])
    assert u.tolist() == [1, -1]


@pytest.mark.parametrize("zeta", [-0.1, float("nan"), float("inf")])
def test_bad_zeta_names_field(zeta):
    with pytest.raises(ParameterError, match="zeta"):
        local_decision([1.0], 0.0, zeta)


def test_encodings_are_explicit_and_convertible():
    assert to_01([1, -1, 1], "pm1").tolist() == [1, 0, 1]
    assert to_pm1([1, 0, 1], "01").tolist() == [1, -1, 1]
    assert present_count([1, 0, 1, 1], "01") == 3
    with pytest.raises(ParameterError, match=r"u\[1\]"):
        validate_decisions([1, 0], "pm1")
    with pytest.raises(ParameterError, match="tuple"):
        validate_decisions([1], "binary")


# ------------------------------------------------ shared input checks (every numerical module)
from fusion_center.core import baselines, curves, poisson_binomial, rules
from fusion_center.core import thresholds  # noqa: E402


@pytest.mark.parametrize("call,field", [
    (lambda: validate_decisions(["a", 1], "pm1"), "u"),
    (lambda: validate_decisions([None, 1], "pm1"), "u[0]"),
    (lambda: validate_decisions([[1], [1, 1]], "pm1"), "u"),
    (lambda: validate_decisions([1 + 0j, 1], "pm1"), "u"),
    (lambda: local_decision(["x"], 0.0, 1.0), "observation"),
    (lambda: local_decision([1.0], 0.0, "x"), "zeta"),
    (lambda: rules.check_weight("p", True), "p"),
    (lambda: rules.g_of_n(True, 1, 1), "n"),
    (lambda: rules.g_of_n(np.array([3, 4]), 1, 1), "n"),
    (lambda: rules.g_of_n(2**53 + 2, 1, 1), "n"),
    (lambda: thresholds.additive_threshold(57, np.array([0.003]), 0.03), "xi"),
    (lambda: thresholds.max_preferential_value(5, "x", 1, 1), "present"),
    (lambda: curves.p_additive_pm1("x", 5, 0.1), "U"),
    (lambda: poisson_binomial.pmf(["a"]), "probs"),
    (lambda: poisson_binomial.log_sf([0.5], True), "k"),
    (lambda: baselines.np_log_statistic([1], ["x"], 0.1), "pd"),
    (lambda: baselines.chair_varshney_llr([1], 0.9, 0.1, prior_h1="x"), "prior_h1"),
    (lambda: baselines.bayes_threshold(0.5, "x", 1, 1, 0), "c00"),
    (lambda: baselines.bayes_threshold(0.5, 0, True, 1, 0), "c01"),
    (lambda: baselines.neyman_pearson_fusion(0.9, [0.1] * 3, "x"), "false_alarm"),
])
def test_bad_types_raise_parameter_error_naming_the_field(call, field):
    with pytest.raises(ParameterError) as err:
        call()
    assert err.value.name == field


def test_numpy_scalars_and_integral_floats_are_accepted():
    assert rules.k_of_n([1, 1, -1], np.int32(2), "pm1") == 1
    assert rules.k_of_n([1, 1, -1], 2.0, "pm1") == 1
    assert rules.g_of_n(np.int64(18), np.float32(1), 1) == 68
    assert validate_decisions(np.array([True, False]), "01").tolist() == [1, 0]
    assert poisson_binomial.log_sf([0.5, 0.5], np.float64(1.0)) == pytest.approx(np.log(0.75), rel=1e-15)
    base = thresholds.additive_threshold(57, 0.003, 0.03)
    assert thresholds.additive_threshold(np.int64(57), np.float64(0.003), np.float64(0.03)) == base


# --------------------------------------------------------------------------- LocalDetectors
from fractions import Fraction  # noqa: E402

from hypothesis import given, settings, strategies as st  # noqa: E402

from fusion_center.core.encoding import LocalDetectors  # noqa: E402


def _exact_decision(x: float, n: float, z: float) -> int:
    """Eqs 2-4 in exact arithmetic on the IEEE result of Y = X - N (the node computes Y in
    float64): present iff Y >= zeta; NaN readings are not on the wire (0)."""
    if x != x:
        return 0
    y = x - n
    if y != y:
        return -1
    if y in (float("inf"), float("-inf")):
        return 1 if y > 0 else -1
    return 1 if Fraction(y) >= Fraction(z) else -1


def test_local_detectors_at_the_cut_off_and_without_a_reading():
    det = LocalDetectors(noise=[1.0, 1.0, 0.5, 0.0, 0.25], zeta=[1.0, 1.0, 0.0, 3.0, 2.0])
    x = np.array([2.0, np.nextafter(2.0, 0.0), 0.5, np.nan, np.inf])
    u, available = det.wire(x)
    assert u.dtype == np.int8
    assert u.tolist() == [1, -1, 1, 0, 1]                 # Y = zeta is present (eq 3: >=)
    assert available.tolist() == [True, True, True, False, True]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.one_of(st.floats(-1e3, 1e3), st.just(float("nan")), st.just(float("inf"))),
                          st.floats(0, 50), st.floats(0, 50)), min_size=1, max_size=64))
def test_local_detectors_equal_local_decision_and_the_exact_test(rows):
    x = np.array([r[0] for r in rows])
    noise = np.array([r[1] for r in rows])
    zeta = np.array([r[2] for r in rows])
    u, available = LocalDetectors(noise, zeta).wire(x)
    ok = ~np.isnan(x)
    old = np.zeros(len(x), dtype=np.int8)              # the pipeline's former code
    if ok.any():
        old[ok] = local_decision(x[ok], noise[ok], zeta[ok], "pm1")
    assert u.tolist() == old.tolist()
    assert available.tolist() == ok.tolist()
    assert u.tolist() == [_exact_decision(*r) for r in rows]


def test_local_detectors_refuse_bad_cut_offs_and_shapes():
    with pytest.raises(ParameterError, match="zeta"):
        LocalDetectors([0.0, 0.0], [1.0, -0.5])
    with pytest.raises(ParameterError, match="zeta"):
        LocalDetectors([0.0, 0.0], [1.0])
    with pytest.raises(ParameterError, match="readings"):
        LocalDetectors([0.0], [1.0]).wire(np.zeros(2))
