"""The chapter's worked numbers (sec. 6.2.3.2, 6.2.3.3, 7.1, 7.2) against its equations.

Every expected value is either printed in the chapter (and follows from its equations) or
worked by hand below; printed numbers that do not follow are asserted at OUR value, with the
derivation in docs/chapter-notes.md.
"""

import csv
import math
import re
from pathlib import Path

import numpy as np
import pytest

from fusion_center.core.contact import ContactType, classify, taxel_count_ratio
from fusion_center.core.forces import (
    grip_force_limit, gripper_tangential, load_cell_grip_force, max_load,
    r_cell_tangential_force, tangential_force, total_tangential,
)
from fusion_center.core.geometry import contact_area, convex_hull, polygon_area

DATA = Path(__file__).resolve().parents[1] / "scenes" / "data"

# sec. 6.2 raw sensory output Y_i (mV), 57 values as printed
Y_MATRIX = [float(v) for v in """2.3 7.8 0.6 0.8 15.6 5.8 2.4 18.0 4.3 5.5 4.2 0.5 3.7 2.7 5.1 5.4
8.8 19.3 14.6 4.4 5.5 2.6 6.4 8.8 4.88 17.0 2.9 13.4 9.0 5.6 7.5 11.7 7.8 3.6 8.5 5.69 6.5 8.5
9.5 7.5 6.4 5.3 4.3 3.5 2.6 2.6 4.4 4.5 5.6 6.7 7.8 8.4 9.6 0.4 9.5 4.6 6.7""".split()]

# sec. 6.2.3.2 slope/intercept matrix, as printed (55 pairs)
PRINTED_PAIRS = [tuple(int(x) for x in m) for m in re.findall(r"\((\d),(\d)\)", """
(0,6) (0,6) (0,3) (8,0) (7,1) (9,2) (5,3) (6,1) (3,1) (9,8) (9,1) (9,4) (0,2) (6,3) (2,4) (3,7) (4,2) (3,4)
(2,4) (2,1) (3,6) (3,0) (4,7) (3,4) (8,2) (9,2) (7,3) (4,2) (3,3) (4,2) (0,5) (6,1) (5,1) (4,4) (3,2) (6,3)
(2,4) (3,7) (2,1) (4,2) (3,4) (0,4) (3,6) (2,0) (4,7) (5,4) (8,2) (9,2) (7,3) (4,2) (3,3) (0,5) (0,2) (0,1) (0,1)""")]


def _rows(name):
    with open(DATA / name, newline="") as fh:
        return list(csv.DictReader(fh))


# ----------------------------------------------------------------- layout data files
def test_matrix57_layout_matches_sec_6233_table():
    rows = _rows("matrix57_taxels.csv")
    assert list(rows[0].keys()) == ["node_id", "kind", "x", "y", "slope", "intercept"]
    assert [int(r["node_id"]) for r in rows] == list(range(1, 58))
    kinds = [r["kind"] for r in rows]
    assert (kinds.count("C"), kinds.count("R"), kinds.count("P")) == (21, 32, 4)   # sec. 6.1
    xy = [(float(r["x"]), float(r["y"])) for r in rows]
    # 41 distinct locations of the sec. 6.2.3.3 table: 5x5 C minus 4 corners, 4x4 R, 4 P
    c_expected = {(x, y) for x in (1, 21, 41, 61, 81) for y in (4, 29, 54, 79, 104)} - \
        {(1, 4), (81, 4), (1, 104), (81, 104)}
    r_expected = {(x, y) for x in (11, 31, 51, 71) for y in (16.5, 41.5, 66.5, 91.5)}
    p_expected = {(51, 1), (1, 66.5), (82, 66.5), (51, 107)}
    assert {p for p, k in zip(xy, kinds) if k == "C"} == c_expected
    assert {p for p, k in zip(xy, kinds) if k == "P"} == p_expected
    r_points = [p for p, k in zip(xy, kinds) if k == "R"]
    assert set(r_points) == r_expected and all(r_points.count(p) == 2 for p in r_expected)
    # sec. 4.3.2 storage order: increasing y, ties by increasing x
    assert xy == sorted(xy, key=lambda p: (p[1], p[0]))
    # sec. 6.2.3.3: taxels 5, 8, 18, 19, 20, 31, 33 sit at these locations
    expected = [(11, 16.5), (31, 16.5), (11, 41.5), (11, 41.5), (31, 41.5), (1, 66.5), (11, 66.5)]
    assert [xy[i - 1] for i in (5, 8, 18, 19, 20, 31, 33)] == expected


def test_matrix57_calibration_is_printed_matrix_with_documented_mapping():
    rows = _rows("matrix57_taxels.csv")
    assert len(PRINTED_PAIRS) == 55
    for i, row in enumerate(rows, start=1):
        if i in (1, 57):            # no printed pair (P-cells at both ends of the order)
            assert row["slope"] == row["intercept"] == ""
            continue
        m, c = PRINTED_PAIRS[i - 2]  # taxel i <- printed pair i-1
        if m == 0:                   # slope 0 = no tangential calibration (sec. 4.3.2)
            assert row["slope"] == row["intercept"] == ""
        else:
            assert (float(row["slope"]), float(row["intercept"])) == (m, c)


def test_gripper18_layout_matches_fig20_and_sec72():
    rows = _rows("gripper18_taxels.csv")
    assert list(rows[0].keys()) == ["node_id", "kind", "x", "y", "jaw", "axis", "slope",
                                    "intercept", "grip_factor"]
    assert [int(r["node_id"]) for r in rows] == list(range(1, 19))
    assert [r["kind"] for r in rows] == ["LC"] * 2 + ["TBS"] * 10 + ["IR"] * 6
    assert [r["jaw"] for r in rows[:2]] == ["left", "right"]
    assert [(r["jaw"], r["axis"]) for r in rows[2:12]] == \
        [("left", "y")] * 4 + [("left", "x")] + [("right", "y")] * 4 + [("right", "x")]
    assert [r["jaw"] for r in rows[12:]] == ["left"] * 3 + ["right"] * 3


# ----------------------------------------------------------------- sec. 6.2.3.2
@pytest.mark.parametrize("taxel, printed", [(5, 1.95), (8, 3.00), (18, 4.325), (19, 3.5333)])
def test_sec6232_forces_that_follow_from_eq30(taxel, printed):
    rows = _rows("matrix57_taxels.csv")
    row = rows[taxel - 1]
    f = tangential_force([Y_MATRIX[taxel - 1]], float(row["slope"]), float(row["intercept"]))[0]
    assert f == pytest.approx(printed, abs=5e-5)


def test_sec6232_printed_forces_sum_to_printed_total_by_eq24_25():
    printed = [1.95, 3.00, 4.325, 3.5333, 3.85, 3.75, 2.06667]
    assert total_tangential(printed) == pytest.approx(22.475, abs=1e-4)


def test_sec6232_total_from_eq30_for_the_seven_taxels():
    # ours (docs/chapter-notes.md): 15.6/8 + 15/5 + 17.3/4 + 10.6/3 + 0.4/2 + 5.5/4 + 6.8/6
    rows = _rows("matrix57_taxels.csv")
    cells = [5, 8, 18, 19, 20, 31, 33]
    forces = tangential_force([Y_MATRIX[i - 1] for i in cells], [float(rows[i - 1]["slope"]) for i in cells],
                              [float(rows[i - 1]["intercept"]) for i in cells])
    hand = 1.95 + 3.0 + 4.325 + 10.6 / 3 + 0.2 + 1.375 + 6.8 / 6     # 15.51667 (printed 22.475)
    assert total_tangential(forces) == pytest.approx(hand, rel=1e-12)


def test_sec6232_taxels_20_31_33_follow_eq30_not_the_print():
    # eq 30 with Y_20 = 4.4 and (2, 4): 0.2; Y_31 = 7.5 and (4, 2): 1.375; Y_33 = 7.8 and (6, 1): 1.1333
    rows = _rows("matrix57_taxels.csv")
    got = [tangential_force([Y_MATRIX[i - 1]], float(rows[i - 1]["slope"]),
                            float(rows[i - 1]["intercept"]))[0] for i in (20, 31, 33)]
    np.testing.assert_allclose(got, [0.2, 1.375, 6.8 / 6], rtol=1e-12)


# ----------------------------------------------------------------- sec. 6.2.3.3
CHAPTER_POINTS = [(11, 16.5), (31, 16.5), (11, 41.5), (11, 41.5), (31, 41.5), (1, 66.5), (11, 66.5)]


def test_sec6233_hull_and_area():
    hull = convex_hull(CHAPTER_POINTS)
    assert set(map(tuple, hull.tolist())) == {(11, 16.5), (31, 16.5), (31, 41.5), (11, 66.5), (1, 66.5)}
    # hand: trapezoid x in [11, 31] (20 x 25 = 500) + triangle (31,41.5)-(11,66.5)-(11,41.5)
    # (20 x 25 / 2 = 250) + triangle (1,66.5)-(11,16.5)-(11,66.5) (10 x 50 / 2 = 250) = 1000
    assert contact_area(CHAPTER_POINTS) == pytest.approx(1000.0, abs=1e-9)


def test_sec6233_printed_625_is_a_non_convex_pentagon_without_taxel_33():
    # documented in chapter-notes: 625 = 500 (rectangle) + 125 (triangle), taxel 33 left out
    assert polygon_area([(1, 66.5), (11, 16.5), (31, 16.5), (31, 41.5), (11, 41.5)]) == 625.0


def test_sec6233_contact_type_of_the_example():
    assert classify(taxel_count_ratio(7, 57)) == ContactType.LARGER_OBJECT


# ----------------------------------------------------------------- sec. 7.1
R_READINGS = [(0.256, 0.064), (0.514, 0.128), (0.488, 0.122)]
R_SLOPE = [0.1661, 0.307, 0.3185]
R_INTERCEPT = [-0.0155, -0.0163, -0.0133]      # eq 36: Y = m F - 0.0155  ->  c = -0.0155


def test_sec71_total_grip_limit_and_load():
    per_strut = r_cell_tangential_force(R_READINGS, R_SLOPE, R_INTERCEPT)
    hand = [(0.32 + 0.0155) / 0.1661, (0.642 + 0.0163) / 0.307, (0.61 + 0.0133) / 0.3185]
    np.testing.assert_allclose(per_strut, hand, rtol=1e-14)
    total = total_tangential(per_strut)
    hand_total = sum(hand)                                         # 6.12115309520756...
    assert total == pytest.approx(hand_total, rel=1e-14)
    assert round(total, 3) == 6.121                                # printed 6.121 kgf
    fg = grip_force_limit(total, 0.3)
    assert fg == pytest.approx(hand_total / 0.3, rel=1e-14)        # 20.40384...
    # printed 20.41 does not follow: 6.1212 / 0.3 (and the printed 6.121 / 0.3) round to 20.40
    assert round(fg, 2) == 20.40 and round(6.121 / 0.3, 2) == 20.40
    w = max_load(fg, 0.3)
    assert w == pytest.approx(2 * hand_total, rel=1e-14)           # 2 mu (F_t / mu) = 12.2423
    assert round(w) == 12                                          # "12 kgf (approx.)"


def test_sec71_per_taxel_eq30_values_and_sign_conventions():
    y = np.array(R_READINGS).ravel()
    m = np.repeat(R_SLOPE, 2)
    c = np.repeat(R_INTERCEPT, 2)
    per_taxel = tangential_force(y, m, c)
    np.testing.assert_allclose(per_taxel, (y + np.repeat([0.0155, 0.0163, 0.0133], 2)) / m, rtol=1e-14)
    # neither sign reproduces the printed per-taxel forces or the printed total per taxel
    printed = np.array([1.6152, 0.4038, 1.7168, 0.4292, 1.5648, 0.3912])
    assert printed.sum() == pytest.approx(6.121, abs=1e-9)
    # per taxel each reading carries the whole intercept, i.e. 2|c| per strut:
    hand_neg = 0.351 / 0.1661 + 0.6746 / 0.307 + 0.6366 / 0.3185      # c < 0: (0.320 + 0.031)/0.1661 + ... = 6.3093
    hand_pos = 0.289 / 0.1661 + 0.6094 / 0.307 + 0.5834 / 0.3185      # c > 0: (0.320 - 0.031)/0.1661 + ... = 5.5567
    assert total_tangential(per_taxel) == pytest.approx(hand_neg, rel=1e-12)
    assert total_tangential(tangential_force(y, m, -c)) == pytest.approx(hand_pos, rel=1e-12)
    assert round(hand_neg, 3) != 6.121 and round(hand_pos, 3) != 6.121
    # the printed per-taxel forces are 0.8 / 0.2 of strut totals 2.019, 2.146, 1.956
    np.testing.assert_allclose(printed, np.outer([2.019, 2.146, 1.956], [0.8, 0.2]).ravel(), rtol=0, atol=1e-12)


# ----------------------------------------------------------------- sec. 7.2
Y_GRIPPER = [3.93, 3.89, 0.0226, 0.0218, 0.0245, 0.0214, 0.0259, 0.0228, 0.0234, 0.0219,
             0.0245, 0.0227, 429, 424, 410, 407, 388, 387]


def test_sec72_mean_tangential_and_grip_in_calibration_coefficients():
    rows = _rows("gripper18_taxels.csv")
    tbs = [i for i, r in enumerate(rows) if r["kind"] == "TBS"]
    f = dict(zip(tbs, tangential_force([Y_GRIPPER[i] for i in tbs],
                                       [float(rows[i]["slope"]) for i in tbs],
                                       [float(rows[i]["intercept"]) for i in tbs])))

    def cells(jaw, axis):
        return [f[i] for i in tbs if rows[i]["jaw"] == jaw and rows[i]["axis"] == axis]

    result = gripper_tangential(cells("left", "y"), cells("left", "x")[0],
                                cells("right", "y"), cells("right", "x")[0])
    hand_left = math.hypot(0.0226 + 0.0218 + 0.0245 + 0.0214, 0.0259)
    hand_right = math.hypot(0.0228 + 0.0234 + 0.0219 + 0.0245, 0.0227)
    assert result == pytest.approx((hand_left + hand_right) / 2, rel=1e-12)
    assert result == pytest.approx(0.09464, abs=5e-6)             # printed eta (0.09464) kgf
    lc = load_cell_grip_force(Y_GRIPPER[:2], [float(r["grip_factor"]) for r in rows[:2]])
    assert lc.mean == pytest.approx(3.91, abs=1e-12)              # printed (3.91 / M) kgf
