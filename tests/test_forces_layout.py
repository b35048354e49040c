"""``core.forces.LayoutForces``: one layout's eqs 30, 24-25 / 28a-29, 27b per cycle in float
arithmetic - the same floats, bit for bit, as the pure functions on the cycle's arrays (what the
raw-mode forces stage computed with them), and the chapter's closed forms."""

import math

import mpmath
import numpy as np
import pytest

from taxel_net.errors import ParameterError
from fusion_center.core.forces import (
    LayoutForces, jaw_tangential, load_cell_grip_force, tangential_force, total_tangential,
)


def reference(y, used, slope, intercept, grip_factor, jaws, angle):
    """The cycle through the pure functions, as PhysicalEvaluation.forces did before LayoutForces."""
    y, used = np.asarray(y, dtype=float), np.asarray(used, dtype=bool)
    slope, intercept, grip_factor = (np.asarray(a, dtype=float) for a in (slope, intercept, grip_factor))
    tangential = slope != 0.0
    per_cell = np.zeros(len(y))
    cells = used & tangential
    if cells.any():
        per_cell[cells] = tangential_force(y[cells], slope[cells], intercept[cells])
    total = per_jaw = None
    if tangential.any():
        if jaws is not None:
            per_jaw = {}
            for jaw, (ys, xs) in jaws.items():
                ys, xs = np.array(ys, dtype=np.intp), np.array(xs, dtype=np.intp)
                fy = per_cell[ys] if ys.size else np.zeros(1)
                fx = total_tangential(per_cell[xs], 0.0) if xs.size else 0.0
                per_jaw[jaw] = jaw_tangential(fy, fx, angle)
            total = float(np.mean(list(per_jaw.values())))
        else:
            total = total_tangential(per_cell[cells], angle) if cells.any() else 0.0
    grip_per_cell = grip = None
    if (grip_factor != 0.0).any():
        lc = np.flatnonzero(grip_factor != 0.0)
        per_lc = np.zeros(lc.size)
        live = used[lc]
        if live.any():
            per_lc[live] = load_cell_grip_force(y[lc][live], grip_factor[lc][live]).per_jaw
        grip_per_cell, grip = [float(v) for v in per_lc], float(per_lc.mean())
    return ([(int(i), float(per_cell[i])) for i in np.flatnonzero(cells)], per_jaw, total, grip_per_cell, grip)


def same(a, b) -> bool:
    """Equal floats, the sign of a zero included (None / containers compared inside)."""
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, float) and isinstance(b, float) and a == b and math.copysign(1, a) == math.copysign(1, b)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return isinstance(b, dict) and list(a) == list(b) and all(same(a[k], b[k]) for k in a)
    return a == b


def random_layout(rng, n, with_jaws):
    kinds = rng.choice(["tbs", "lc", "p"], size=n, p=[0.5, 0.2, 0.3])
    slope = np.where(kinds == "tbs", rng.choice([-1, 1], size=n) * 10.0 ** rng.uniform(-3, 3, size=n), 0.0)
    intercept = np.where(kinds == "tbs", rng.normal(0, 1, size=n), 0.0)
    grip_factor = np.where(kinds == "lc", 10.0 ** rng.uniform(-2, 2, size=n), 0.0)
    jaws = None
    if with_jaws and (slope != 0).any():
        jaws = {}
        for i in np.flatnonzero(slope != 0):
            ys, xs = jaws.setdefault(str(rng.choice(["left", "right", "third"])), ([], []))
            (ys if rng.random() < 0.75 else xs).append(int(i))
    return slope, intercept, grip_factor, jaws


@pytest.mark.parametrize("with_jaws", [False, True])
def test_bit_for_bit_the_pure_functions_on_random_layouts_and_cycles(with_jaws):
    rng = np.random.default_rng(2323 + with_jaws)
    checked = 0
    for _ in range(300):
        n = int(rng.integers(1, 24))  # both sides of numpy's 8-value pairwise summation
        slope, intercept, grip_factor, jaws = random_layout(rng, n, with_jaws)
        angle = float(rng.choice([0.0, rng.uniform(0, math.pi), math.pi / 2, math.pi]))
        layout = LayoutForces(slope, intercept, grip_factor, jaws=jaws, inclusion_angle=angle)
        assert layout.checked
        for _ in range(10):
            # magnitudes 1e-6 .. 1e6 mixed: any change of the order of the additions shows
            y = rng.choice([-1, 1], size=n) * 10.0 ** rng.uniform(-6, 6, size=n)
            used = rng.random(n) < rng.uniform(0.2, 1.0)
            got = layout.cycle(y.tolist(), used.tolist())
            want = reference(y, used, slope, intercept, grip_factor, jaws, angle)
            assert same(tuple(got), want), (n, angle, jaws, y.tolist(), used.tolist())
            checked += 1
    assert checked == 3000


def test_a_gripper_pad_against_the_closed_forms():
    # two jaws of 4 y-axis TBS (2 mV/N, c = 0.2 mV: the grasp scenes) and one x-axis TBS, a load cell each
    slope = [2.0] * 5 + [0.0] + [2.0] * 5 + [0.0]
    intercept = [0.2] * 5 + [0.0] + [0.2] * 5 + [0.0]
    grip_factor = [0.0] * 5 + [0.5] + [0.0] * 5 + [0.5]
    jaws = {"left": ([0, 1, 2, 3], [4]), "right": ([6, 7, 8, 9], [10])}
    forces_n = [1.5, 0.25, 3.0, 0.75, 0.5, None, 2.0, 1.0, 0.5, 0.25, 0.0, None]  # F per TBS, N
    grip_n = {5: 10.0, 11: 12.0}
    y = [2.0 * f + 0.2 if f is not None else 0.5 * grip_n[i] for i, f in enumerate(forces_n)]
    used = [True] * 12
    for angle in (0.0, math.pi / 3):
        out = LayoutForces(slope, intercept, grip_factor, jaws=jaws, inclusion_angle=angle).cycle(y, used)
        mp = mpmath.mpf
        c = mpmath.cos(mp(angle))

        def pair(a, b):  # eq 28b
            return mpmath.sqrt(mp(a) ** 2 + mp(b) ** 2 + 2 * mp(a) * mp(b) * c)

        for jaw, (ys, (x,)) in jaws.items():
            f = [forces_n[i] for i in ys]
            tot_y = pair(pair(f[0], f[1]), pair(f[2], f[3]))  # eq 28a
            want = mpmath.sqrt(tot_y ** 2 + mp(forces_n[x]) ** 2)  # eq 29
            assert out.per_jaw[jaw] == pytest.approx(float(want), rel=1e-14)
        assert out.total == pytest.approx(sum(out.per_jaw.values()) / 2, rel=1e-15)  # sec 7.2: the jaws' mean
        assert out.grip_per_cell == [10.0, 12.0] and out.grip == 11.0  # eq 27b, Y / M
        assert [i for i, _ in out.per_cell] == [0, 1, 2, 3, 4, 6, 7, 8, 9, 10]
    at_zero = LayoutForces(slope, intercept, grip_factor, jaws=jaws).cycle(y, used)
    assert at_zero.per_jaw["left"] == pytest.approx(math.hypot(1.5 + 0.25 + 3.0 + 0.75, 0.5), rel=1e-15)  # eqs 25, 29


def test_unused_cells_carry_no_force_and_no_tangential_cell_gives_none():
    layout = LayoutForces([2.0, 2.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.5])
    out = layout.cycle([4.0, 6.0, 3.0], [True, False, False])
    assert out.per_cell == [(0, 2.0)] and out.total == 2.0 and out.grip_per_cell == [0.0] and out.grip == 0.0
    none = LayoutForces([0.0, 0.0], [0.0, 0.0], [0.0, 0.0]).cycle([1.0, 2.0], [True, True])
    assert none.total is None and none.per_jaw is None and none.grip is None and none.per_cell == []


def test_a_layout_the_checks_refuse_gets_the_pure_functions_errors():
    layout = LayoutForces([1.0, np.nan], [0.0, 0.0], [0.0, 0.0])
    assert not layout.checked
    assert layout.cycle([1.0, 2.0], [True, False]).total == 1.0  # the bad cell unused: no error
    with pytest.raises(ParameterError, match=r"^slope\[1\]"):
        layout.cycle([1.0, 2.0], [True, True])
    # a non-finite reading in a used cell: the reference's error, word for word
    good = LayoutForces([1.0, 2.0], [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(ParameterError) as got:
        good.cycle([1.0, float("inf")], [True, True])
    with pytest.raises(ParameterError) as want:
        tangential_force([1.0, float("inf")], [1.0, 2.0], [0.0, 0.0])
    assert str(got.value) == str(want.value)
    assert not LayoutForces([1.0], [0.0], [0.0], inclusion_angle=4.0).checked  # alpha outside [0, pi]
