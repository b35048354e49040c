"""P(H1) curves, eqs 8-14, against the chapter's formulas evaluated literally in mpmath."""

import math

import mpmath as mp
import numpy as np
import pytest

from fusion_center.core.curves import (
    p_additive_01,
    p_additive_pm1,
    p_exponential,
    p_linear,
    p_multiplicative,
    p_multiplicative_scaled,
    p_preferential,
)
from taxel_net.errors import ParameterError

NS = [1, 2, 18, 57, 354, 355, 1000, 100_000, 1_000_000]
XIS = [1e-300, 1e-12, 0.003, 0.5, 0.999999]
REL = 1e-12


def _dps(xi):
    # eq 13 written literally cancels ~log10(1/sqrt(xi)) digits near U = -n: carry them
    return 50 + int(-math.log10(xi)) + 10


def _close(ours, ref, rel=REL):
    ref = float(ref)
    assert abs(ours - ref) <= rel * abs(ref), (ours, ref)


@pytest.mark.parametrize("n", NS)
@pytest.mark.parametrize("xi", XIS)
def test_multiplicative_eqs_10_11_literal(n, xi):
    # eq 10 p = a exp(m U_G), eq 11a m = e^n ln(1/xi)/(e^2n - 1), eq 11b ln(1/a) = e^2n ln(1/xi)/(e^2n - 1)
    with mp.workdps(_dps(xi)):
        N, X = mp.mpf(n), mp.mpf(xi)
        e2n = mp.e ** (2 * N)
        m = mp.e**N * mp.log(1 / X) / (e2n - 1)
        a = mp.e ** (-(e2n * mp.log(1 / X) / (e2n - 1)))
        for ln_u in (-n, -n + 1, 0, n - 0.5, n):
            ref = a * mp.e ** (m * mp.e ** mp.mpf(ln_u))
            _close(p_multiplicative(ln_u, n, xi), ref)
            _close(p_multiplicative_scaled(math.exp(ln_u - n), n, xi), ref)
        for t in (-1.0, -0.3, 0.25):
            _close(p_multiplicative_scaled(t, n, xi), a * mp.e ** (m * mp.e**N * t))
    # the two interpolation points of sec. 2.2.3.1: (e^-n, xi) and (e^n, 1)
    assert p_multiplicative(-n, n, xi) == pytest.approx(xi, rel=1e-12)
    assert p_multiplicative(n, n, xi) == 1.0


@pytest.mark.parametrize("n", NS)
@pytest.mark.parametrize("xi", XIS)
def test_additive_eqs_12_13_literal(n, xi):
    with mp.workdps(_dps(xi)):
        N, X = mp.mpf(n), mp.mpf(xi)
        r = (X + 1) + mp.sqrt(X * (X + 2))
        for frac in (-1, -0.999, -0.5, 0, 0.123, 1):
            U = frac * n
            ref13 = mp.mpf("0.5") * mp.e ** (mp.log(r) / N * U) + (1 - mp.mpf("0.5") * r) / N * U
            _close(p_additive_pm1(U, n, xi), ref13)
            if frac >= 0:
                ref12 = X * mp.e ** (mp.log(1 / X) / N * U)
                _close(p_additive_01(U, n, xi), ref12)
    # three points of sec. 2.2.3.2: (-n, xi), (0, 0.5), (n, 1)
    assert p_additive_pm1([-n, 0, n], n, xi) == pytest.approx([xi, 0.5, 1.0], rel=1e-13)


def test_additive_pm1_chapter_value():
    # sec. 6.3.1 prints P(H1) = 0.124835 at U_G = -43, n = 57, xi = 0.003; eq 13 gives
    # 0.1248046 (agrees to 3e-5: the printed value is reproduced to about 4 digits)
    with mp.workdps(50):
        X = mp.mpf(0.003)
        r = (X + 1) + mp.sqrt(X * (X + 2))
        ref = 0.5 * r ** (mp.mpf(-43) / 57) + (1 - 0.5 * r) / 57 * -43
    assert float(ref) == pytest.approx(0.124835, abs=5e-5)
    _close(p_additive_pm1(-43, 57, 0.003), ref)


@pytest.mark.parametrize("n", [1, 57, 1_000_000])
@pytest.mark.parametrize("xi", XIS)
def test_eqs_8_9_14(n, xi):
    k = np.array([0, n / 3, n - 1e-3 * n, n])
    # eq 8 as printed cancels to xi at k = n: carry log10(1/xi) more digits than 50
    with mp.workdps(_dps(xi)):
        X = mp.mpf(xi)
        for ki, lin, ex in zip(k, p_linear(k, n, xi), p_exponential(k, n, xi)):
            _close(lin, (X - 1) / n * mp.mpf(ki) + 1)
            _close(ex, mp.e ** (mp.log(X) / n * mp.mpf(ki)))
        assert p_linear(n, n, xi) == xi  # the end point (n, xi) of fig. 1 exactly
        g = 4.0 * (n - 1) + 3
        for U in (-g, -1.0, 0.0, g / 7, g):
            _close(p_preferential(U, g, xi), (1 - X) / mp.mpf(g) ** 2 * mp.mpf(U) ** 2 + X)


def test_vectorised_shapes_and_scalars():
    u = np.linspace(-57, 57, 11).reshape(11, 1)
    assert p_additive_pm1(u, 57, 0.003).shape == (11, 1)
    assert np.ndim(p_additive_pm1(3, 57, 0.003)) == 0
    assert np.all(np.diff(p_multiplicative(np.arange(-57, 58), 57, 0.003)) >= 0)


@pytest.mark.parametrize("call,field", [
    (lambda: p_linear(1, 0, 0.1), "n"),
    (lambda: p_linear(-1, 5, 0.1), "k"),
    (lambda: p_exponential(1, 5, 1.0), "xi"),
    (lambda: p_multiplicative_scaled(1.5, 5, 0.1), "t"),
    (lambda: p_multiplicative(float("nan"), 5, 0.1), "ln_U_G"),
    (lambda: p_additive_01(-1, 5, 0.1), "U"),
    (lambda: p_additive_pm1(6, 5, 0.1), "U"),
    (lambda: p_additive_pm1(0, 5, float("nan")), "xi"),
    (lambda: p_preferential(1, 0, 0.1), "g"),
    (lambda: p_preferential(9, 8, 0.1), "U"),
])
def test_bad_inputs(call, field):
    with pytest.raises(ParameterError, match=f"^{field}="):
        call()
