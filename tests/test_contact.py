"""Table 1 classes, eqs 33, 34a, 34b and fig. 15 zones."""

import numpy as np
import pytest

from fusion_center.core.contact import (
    CONTACT_MECHANICS, ContactType, ContactZone, classify, contact_zone, friction_plane_ratio,
    relative_softness_index, taxel_count_ratio,
)
from taxel_net.errors import ParameterError


@pytest.mark.parametrize("ratio, expected", [
    (0.0, "no_contact"), (0.0099, "no_contact"),
    (0.01, "point_force"), (0.015, "point_force"), (0.02, "point_force"),   # overlap -> narrower row
    (0.0201, "small_object"), (0.05, "small_object"), (0.0999, "small_object"),
    (0.1, "larger_object"), (0.5, "larger_object"), (1.0, "larger_object"),
])
def test_table1_precedence(ratio, expected):
    assert classify(ratio) == ContactType(expected)
    assert classify(ratio).value == expected


def test_table1_vectorised_and_mechanics_column():
    out = classify(np.array([0.005, 0.015, 0.05, 0.5]))
    assert [c.value for c in out] == ["no_contact", "point_force", "small_object", "larger_object"]
    grid = classify([[0.01, 0.1], [0.02, 0.0201]])
    assert grid.shape == (2, 2) and grid.tolist() == [
        [ContactType.POINT_FORCE, ContactType.LARGER_OBJECT], [ContactType.POINT_FORCE, ContactType.SMALL_OBJECT]]
    assert isinstance(classify(0.5), ContactType)
    assert CONTACT_MECHANICS[ContactType.POINT_FORCE] == "point contact (without friction)"
    assert CONTACT_MECHANICS[ContactType.LARGER_OBJECT] == "soft finger contact"


@pytest.mark.parametrize("bad", [-0.01, 1.01, float("nan"), float("inf")])
def test_classify_rejects_out_of_range(bad):
    with pytest.raises(ParameterError, match="ratio"):
        classify(bad)


def test_classify_limits_are_parameters():
    assert classify(0.03, point_force_max=0.04) == ContactType.POINT_FORCE
    with pytest.raises(ParameterError):
        classify(0.5, point_force_max=0.2, larger_object_min=0.1)


def test_eq34a_taxel_count():
    assert taxel_count_ratio(7, 57) == 7 / 57
    assert classify(taxel_count_ratio(1, 57)) == ContactType.POINT_FORCE       # 0.0175
    assert classify(taxel_count_ratio(7, 57)) == ContactType.LARGER_OBJECT     # 0.1228
    for args in ((58, 57), (-1, 57), (1, 0), (1.5, 57), ("x", 57)):
        with pytest.raises(ParameterError):
            taxel_count_ratio(*args)


def test_eq34b_friction_plane():
    assert friction_plane_ratio(1000.0, 8000.0) == 0.125
    with pytest.raises(ParameterError, match="total_area"):
        friction_plane_ratio(1.0, 0.0)
    with pytest.raises(ParameterError, match="area"):
        friction_plane_ratio(9.0, 8.0)
    with pytest.raises(ParameterError, match="^area"):
        friction_plane_ratio("big", 8.0)


def test_eq33_rsi():
    assert relative_softness_index(60.0, 30.0) == 1.0      # object half as hard -> RSI = 1
    assert relative_softness_index(45.0, 45.0) == 0.0
    assert relative_softness_index(20.0, 80.0) == -0.75
    np.testing.assert_allclose(relative_softness_index([60.0, 90.0], 30.0), [1.0, 2.0])
    with pytest.raises(ParameterError, match="hardness_object"):
        relative_softness_index(60.0, 0.0)
    with pytest.raises(ParameterError, match="hardness_jaw"):
        relative_softness_index("HRC 60", 30.0)


def test_fig15_zones_with_parameters():
    assert contact_zone(0.0) == ContactZone.LOCKED
    assert contact_zone(0.1) == ContactZone.POINT_WITHOUT_FRICTION
    assert contact_zone(-0.5) == ContactZone.POINT_WITHOUT_FRICTION
    assert contact_zone(1.0) == ContactZone.POINT_WITH_FRICTION
    assert contact_zone(5.0) == ContactZone.SOFT_FINGER
    assert contact_zone(5.0, soft_finger_from=10.0) == ContactZone.POINT_WITH_FRICTION
    assert contact_zone(0.05, locked_tolerance=0.1, frictionless_below=0.2) == ContactZone.LOCKED
    for bad in (-1.0, float("nan")):
        with pytest.raises(ParameterError, match="rsi"):
            contact_zone(bad)
