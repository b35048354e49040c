import numpy as np
import pytest

from fusion_center.encoding import local_decision, present_count, to_01, to_pm1, validate_decisions
from fusion_center.errors import ParameterError


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
