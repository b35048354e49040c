"""Force models: eqs 23/27a/30 (per cell), 24-25, 28-29, 26a/26b, 27b, units."""

import math

import mpmath
import numpy as np
import pytest

from taxel_net.errors import ParameterError
from fusion_center.core.forces import (
    ForceReport, compose_pair, grip_force_limit, gripper_tangential, jaw_tangential,
    load_cell_grip_force, matrix_force_report, max_load, r_cell_tangential_force,
    tangential_force, total_tangential,
)
from fusion_center.core.units import KGF_IN_NEWTON, convert_force


def test_eq30_inverts_calibration_line():
    # y = m F + c with F known -> eq 30 must give F back (hand-picked numbers)
    slope = np.array([2.0, 0.5, 4.0])
    intercept = np.array([1.0, -0.25, 0.0])
    force = np.array([3.0, 8.0, 0.25])
    readings = slope * force + intercept           # 7.0, 3.75, 1.0
    assert readings.tolist() == [7.0, 3.75, 1.0]
    np.testing.assert_allclose(tangential_force(readings, slope, intercept), force, rtol=0, atol=1e-15)


def test_eq30_vectorised_over_cycles_and_scalar_calibration():
    y = np.array([[1.0, 2.0], [3.0, 5.0]])
    np.testing.assert_array_equal(tangential_force(y, 2.0, 1.0), [[0.0, 0.5], [1.0, 2.0]])


@pytest.mark.parametrize("bad_slope", [0.0, -0.0, np.nan, np.inf, -np.inf])
def test_eq30_rejects_unusable_slope_naming_cell(bad_slope):
    with pytest.raises(ParameterError, match=r"^slope\[1\]"):
        tangential_force([1.0, 2.0, 3.0], [1.0, bad_slope, 1.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"^slope\[0\]"):           # ParameterError is a ValueError
        tangential_force([1.0, 2.0], bad_slope, 0.0)


def test_eq30_rejects_nan_reading_and_length_mismatch():
    with pytest.raises(ParameterError, match=r"readings\[2\]"):
        tangential_force([1.0, 2.0, np.nan], 1.0, 0.0)
    with pytest.raises(ParameterError, match=r"^readings\[1\]=nan"):   # cycles x cells: the cell
        tangential_force([[1.0, 2.0], [3.0, np.nan]], 1.0, 0.0)
    with pytest.raises(ParameterError, match=r"intercept\[0\]"):
        tangential_force([1.0, 2.0], 1.0, [np.inf, 0.0])
    # cell 2 has a reading but no slope
    with pytest.raises(ParameterError, match=r"^slope\[2\]='missing'.*cell 2 has no slope"):
        tangential_force([1.0, 2.0, 3.0], [1.0, 2.0], 0.0)
    # intercept[2] has no reading
    with pytest.raises(ParameterError, match=r"^intercept\[2\]=7\.0.*intercept\[2\] has no cell"):
        tangential_force([1.0, 2.0], [1.0, 2.0], [0.0, 0.0, 7.0])
    with pytest.raises(ValueError):
        tangential_force(["a"], 1.0, 0.0)


@mpmath.workdps(50)
def test_eq25_law_of_cosines_against_mpmath():
    for a, b, alpha in [(1.5, 2.25, 0.3), (3.0, 4.0, math.pi / 2), (2.0, 2.0, math.pi), (0.7, 0.1, 2.0)]:
        ref = mpmath.sqrt(mpmath.mpf(a) ** 2 + mpmath.mpf(b) ** 2
                          + 2 * mpmath.mpf(a) * mpmath.mpf(b) * mpmath.cos(mpmath.mpf(alpha)))
        assert compose_pair(a, b, alpha) == pytest.approx(float(ref), rel=1e-14, abs=1e-15)
    assert compose_pair(3.0, 4.0, math.pi / 2) == pytest.approx(5.0, rel=1e-15)
    assert compose_pair(2.0, -3.0, 0.0) == 5.0  # eq 25: |F1| + |F2|


def test_eq24_total_parallel_is_sum_of_magnitudes():
    assert total_tangential([1.95, 3.00, 4.325]) == pytest.approx(9.275, rel=1e-15)
    assert total_tangential([]) == 0.0
    np.testing.assert_allclose(total_tangential([[1.0, 2.0], [3.0, 4.0]]), [3.0, 7.0])
    with pytest.raises(ParameterError, match=r"forces\[1\]"):
        total_tangential([1.0, np.nan, 2.0])


def test_eq24_fold_with_angle_matches_explicit_vectors():
    # each new force at alpha to the running resultant: with alpha = 90 deg and forces
    # 3, 4, 12 the resultants are 5 then 13 (Pythagorean triples)
    assert total_tangential([3.0, 4.0, 12.0], math.pi / 2) == pytest.approx(13.0, rel=1e-14)
    assert total_tangential([3.0, 4.0, 12.0], [math.pi / 2, 0.0]) == pytest.approx(17.0, rel=1e-14)
    with pytest.raises(ParameterError, match="inclusion_angle"):
        total_tangential([1.0, 2.0], -0.1)
    with pytest.raises(ParameterError, match="inclusion_angle"):
        total_tangential([1.0, 2.0, 3.0], [0.1, 0.2, 0.3])


def test_eq28_29_jaw_total():
    # parallel y-cells sum to 10, x-cell 24 orthogonal -> sqrt(100 + 576) = 26
    assert jaw_tangential([1.0, 2.0, 3.0, 4.0], 24.0) == pytest.approx(26.0, rel=1e-15)
    # eq 28a pairs (1,2) and (3,4): at alpha = 90 deg, (3,4) -> 5, (6,8) -> 10, then 5 (+) 10
    # at 90 deg -> sqrt(125); eq 29 with fx = 0
    assert jaw_tangential([3.0, 4.0, 6.0, 8.0], 0.0, math.pi / 2) == pytest.approx(math.sqrt(125.0))
    assert gripper_tangential([1, 2, 3, 4], 24, [3, 0, 0, 0], 4) == pytest.approx((26 + 5) / 2)
    with pytest.raises(ParameterError, match="fy_cells"):
        jaw_tangential([], 1.0)


def test_eq26a_26b_and_mu_validation():
    assert grip_force_limit(6.0, 0.3) == pytest.approx(20.0, rel=1e-15)
    assert max_load(20.0, 0.3) == pytest.approx(12.0, rel=1e-15)
    for bad in (0.0, -0.3, float("nan"), float("inf")):
        with pytest.raises(ParameterError, match="mu"):
            grip_force_limit(1.0, bad)
        with pytest.raises(ParameterError, match="mu"):
            max_load(1.0, bad)
    with pytest.raises(ParameterError, match="total_tangential"):
        grip_force_limit(-1.0, 0.3)


def test_eq27b_load_cells():
    g = load_cell_grip_force([4.0, 6.0], [2.0, 3.0])
    np.testing.assert_array_equal(g.per_jaw, [2.0, 2.0])
    assert g.mean == 2.0
    with pytest.raises(ParameterError, match=r"grip_factor\[0\]"):
        load_cell_grip_force([4.0, 6.0], [0.0, 3.0])
    with pytest.raises(ParameterError, match=r"grip_factor\[1\].*load cell 1 has no grip_factor"):
        load_cell_grip_force([4.0, 6.0], [2.0])
    with pytest.raises(ParameterError, match=r"readings\[1\]"):
        load_cell_grip_force([4.0, np.nan], 2.0)


def test_r_cell_sums_its_two_taxels():
    np.testing.assert_allclose(r_cell_tangential_force([[1.0, 2.0], [0.5, 0.5]], [3.0, 0.5], [0.0, -1.0]),
                               [1.0, 4.0])
    with pytest.raises(ParameterError, match="taxel_readings"):
        r_cell_tangential_force([1.0, 2.0, 3.0], 1.0, 0.0)
    with pytest.raises(ParameterError, match=r"taxel_readings\[1\]"):   # index = strut
        r_cell_tangential_force([[1.0, 2.0], [np.nan, 0.5]], 1.0, 0.0)


def test_units_explicit_and_convertible():
    rep = matrix_force_report([7.0, 3.0], [2.0, 1.0], [1.0, 0.0], 0.5, unit="kgf")
    assert isinstance(rep, ForceReport) and rep.unit == "kgf"
    assert rep.total_tangential == 6.0 and rep.grip_force_limit == 12.0 and rep.max_load == 12.0
    rep_n = rep.to("N")
    assert rep_n.unit == "N"
    assert rep_n.total_tangential == pytest.approx(6.0 * 9.80665, rel=1e-15)
    assert convert_force(9.80665, "N", "kgf") == pytest.approx(1.0, rel=1e-15)
    assert KGF_IN_NEWTON == 9.80665
    with pytest.raises(ParameterError, match="unit"):
        matrix_force_report([1.0], 1.0, 0.0, 0.3, unit="lbf")
    assert convert_force(2.0, "kgf", "N") == 2 * 9.80665
    np.testing.assert_allclose(convert_force([9.80665, 19.6133], "N", "kgf"), [1.0, 2.0], rtol=1e-15)
    with pytest.raises(ParameterError, match="^value"):
        convert_force("heavy", "kgf", "N")
    with pytest.raises(ParameterError, match="^to_unit"):
        convert_force(1.0, "kgf", "lb")
