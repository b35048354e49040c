"""Fusion rules, eqs 5-7 and 15, against hand-worked values and the chapter's examples."""

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from taxel_net.errors import ParameterError
from fusion_center.core.rules import (
    additive,
    g_of_n,
    k_of_n,
    multiplicative,
    preferential,
    preferential_sister,
)

# sec. 7.2: 18 gripper taxels, taxels 4, 6, 10, 17, 18 absent (the chapter's {u_i} matrix, row-wise)
GRIPPER_PM1 = [1, 1, 1, -1, 1, -1, 1, 1, 1, -1, 1, 1, 1, 1, 1, 1, -1, -1]
GRIPPER_01 = [(x + 1) // 2 for x in GRIPPER_PM1]


def test_additive_eq6_both_tuples():
    # sec. 6.3.1: 7 of 57 taxels present -> U_G = 7 - 50 = -43 (pm1); n - k = 7 (01)
    u = [-1] * 57
    for i in (5, 8, 18, 19, 20, 31, 33):
        u[i - 1] = 1
    assert additive(u, "pm1") == -43
    assert additive([(x + 1) // 2 for x in u], "01") == 7


def test_multiplicative_eq5_chapter_value_and_overflow():
    u = [-1] * 50 + [1] * 7
    v = multiplicative(u, "pm1")
    assert v.ln_U_G == -43
    assert v.U_G == pytest.approx(2.11513e-19, rel=1e-5)  # printed in sec. 6.3.1
    assert v.scaled == pytest.approx(math.exp(-100), rel=1e-14)
    big = multiplicative([1] * 1000, "pm1")
    assert big.U_G == math.inf and big.scaled == 1.0 and big.ln_U_G == 1000
    small = multiplicative([-1] * 1000, "pm1")
    assert small.U_G == 0.0 and small.ln_U_G == -1000
    assert multiplicative([1, 0, 1], "01").ln_U_G == 2  # e^(n-k)


def test_preferential_eq7_chapter_example_is_the_01_tuple():
    # Hand-worked: eq 7 with p = q = 1 on the {0,1} tuple gives the chapter's U_G = 37;
    # on the {-1,+1} tuple it gives 14 (term by term: 2+4+0-4+0-4+0+4+0-4+0+4+4+4+4+0+0+0)
    assert preferential(GRIPPER_01, 1, 1, "01") == 37
    assert preferential(GRIPPER_PM1, 1, 1, "pm1") == 14


def _eq7_loop(u, p, q, sign=1):
    n = len(u)
    ext = [0] + list(u) + [0]
    total = 0.0
    for i in range(1, n + 1):
        a = 1 + sign * ext[i + 1]
        b = 1 + sign * ext[i - 1]
        total += ext[i] * (1.0 if (a == 0 and p == 0) else a**p) * (1.0 if (b == 0 and q == 0) else b**q)
    return total


@settings(max_examples=80, deadline=None)
@given(
    st.lists(st.sampled_from([-1, 1]), min_size=1, max_size=30),
    st.sampled_from([0.0, 0.5, 1.0, 1.7, 2.0]),
    st.sampled_from([0.0, 0.3, 1.0, 2.0]),
)
def test_preferential_matches_plain_loop(u, p, q):
    assert preferential(u, p, q, "pm1") == pytest.approx(_eq7_loop(u, p, q), abs=1e-12)
    assert preferential_sister(u, p, q, "pm1") == pytest.approx(_eq7_loop(u, p, q, -1), abs=1e-12)
    u01 = [(x + 1) // 2 for x in u]
    assert preferential(u01, p, q, "01") == pytest.approx(_eq7_loop(u01, p, q), abs=1e-12)


def test_zero_power_zero_is_one():
    # p = q = 0: every factor is 1 (including 0**0), so eq 7 reduces to the additive rule
    u = [1, -1, -1, 1, 1]
    assert preferential(u, 0, 0, "pm1") == additive(u, "pm1")
    # sister model, all present, p = q = 0: (1 - 1)**0 = 1
    assert preferential_sister([1, 1, 1], 0, 0, "pm1") == 3


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7])
@pytest.mark.parametrize("p,q", [(0, 0), (1, 1), (2, 0), (0.5, 1.5), (2, 2)])
def test_g_of_n_is_the_maximum_of_eq7(n, p, q):
    best = max(preferential(list(u), p, q, "pm1") for u in itertools.product([-1, 1], repeat=n))
    assert g_of_n(n, p, q) == pytest.approx(best, abs=1e-12)
    assert preferential([1] * n, p, q, "pm1") == pytest.approx(g_of_n(n, p, q))


def test_g_of_n_chapter_list():
    # sec. 2.2.3.3 prints {2n-1, 4n-5, 4n-4, 8n-10, 16n-24}. Eq 15 gives 2n-1 (1,0), 4n-4 (1,1),
    # 8n-10 (2,1), 16n-24 (2,2); "4n-5" needs p+q = 2 and 2^p + 2^q = 3, which has no real
    # solution (2^p + 4/2^p >= 4), so (2,0) gives 4n-3 instead (docs/chapter-notes.md).
    n = 18
    assert [g_of_n(n, *pq) for pq in [(1, 0), (1, 1), (2, 1), (2, 2), (2, 0)]] == [
        2 * n - 1, 4 * n - 4, 8 * n - 10, 16 * n - 24, 4 * n - 3]


def test_k_of_n():
    u = [1, -1, 1, 1]
    assert k_of_n(u, 3, "pm1") == 1
    assert k_of_n(u, 4, "pm1") == -1
    assert k_of_n([1, 0, 0], 1, "01") == 1
    for bad in (0, 5, 2.5, True):
        with pytest.raises(ParameterError, match="k="):
            k_of_n(u, bad, "pm1")


@pytest.mark.parametrize("field,args", [
    ("p", (3.0, 1.0)), ("p", (-0.1, 1.0)), ("q", (1.0, float("nan"))), ("q", (1.0, float("inf")))])
def test_bad_weights(field, args):
    with pytest.raises(ParameterError, match=f"^{field}="):
        preferential([1, 1], *args, "pm1")
    with pytest.raises(ParameterError, match=f"^{field}="):
        g_of_n(3, *args)


def test_bad_n_and_decisions():
    for n in (0, -1, 2.5, float("nan")):
        with pytest.raises(ParameterError, match="^n="):
            g_of_n(n, 1, 1)
    with pytest.raises(ParameterError, match=r"u\[0\]"):
        additive([0, 1], "pm1")
    with pytest.raises(ParameterError, match="tuple"):
        multiplicative([1], "binary")
    with pytest.raises(ParameterError):
        additive([], "pm1")
    assert np.isfinite(preferential([1], 2, 2, "pm1"))
