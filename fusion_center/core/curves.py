"""P(H1) curves of the chapter (sec. 2.2.2-2.2.3, eqs 8-14), vectorised and overflow-free.

Every curve is written so that it neither overflows nor cancels for any n up to 10^6 and any
xi down to 1e-300 (xi: P(H1) when every taxel decides absent, sec. 2.2.3.1):

* eq 10-11 (multiplicative) is evaluated in the scaled variable t = U_G / e^n, t in [-1, 1]:
  with L = ln(1/xi) the two-point fit through (e^-n, xi) and (e^n, 1) gives
  m e^n = L / (1 - e^(-2n)) and ln a = -m e^n, hence
  p(t) = exp(-L (1 - t) / (1 - e^(-2n))) -- no e^n, no e^(2n) anywhere.
* eq 13 (additive, {-1,+1}) is rewritten around its left end point (-n, xi), with
  x = U/n, y = 1 + x, r = (xi + 1) + sqrt(xi (xi + 2)), ln r = log1p(xi + sqrt(xi (xi + 2))),
  c = 1 - r/2 = (1 - 4 xi) / (2 (1 - xi + sqrt(xi (xi + 2)))):
  p = xi + (1/(2r)) expm1(y ln r) + c y. For xi <= 1/4 all three terms are >= 0 (no
  cancellation even where p = xi = 1e-300); for xi > 1/4 the curve stays above ~0.25.

Scalars in, numpy float64 scalar out; arrays in, arrays out. Inputs outside the curve's domain
or non-finite raise ParameterError.
"""

from __future__ import annotations

import math

import numpy as np

from .encoding import as_float_array, check_real
from taxel_net.errors import ParameterError
from .rules import _check_n

__all__ = [
    "p_linear",
    "p_exponential",
    "p_multiplicative_scaled",
    "p_multiplicative",
    "p_additive_01",
    "p_additive_pm1",
    "p_preferential",
    "check_n",
    "check_xi",
    "check_open_unit",
    "additive_pm1_constants",
]

check_n = _check_n


def check_open_unit(name: str, value) -> float:
    """A probability strictly inside (0, 1): xi, alpha, beta."""
    return check_real(name, value, 0.0, 1.0, open_interval=True,
                      allowed="must be a real number in the open interval (0, 1)")


def check_xi(xi) -> float:
    return check_open_unit("xi", xi)


def _array(name: str, values, low: float, high: float, what: str) -> np.ndarray:
    arr = as_float_array(name, values)
    bad = ~np.isfinite(arr) | (arr < low) | (arr > high)
    if bad.any():
        raise ParameterError(name, arr[bad].flat[0].item(), f"must be finite and lie in {what}")
    return arr


def _out(arr: np.ndarray):
    return arr[()] if arr.ndim == 0 else arr


def p_linear(k, n, xi):
    """Eq 8, straight-line map: p = ((xi - 1)/n) k + 1, k = number of absent taxels in [0, n].

    Evaluated as xi (k/n) + (n - k)/n: both terms are >= 0, so there is no cancellation where
    p -> xi (k -> n); the printed form gives (xi - 1) + 1 = 0 for xi = 1e-300 at k = n.
    """
    n = check_n(n)
    xi = check_xi(xi)
    k = _array("k", k, 0.0, n, f"[0, n] = [0, {n}]")
    return _out(xi * (k / n) + (n - k) / n)


def p_exponential(k, n, xi):
    """Eq 9, exponential curve: p = exp((ln xi / n) k), k = number of absent taxels in [0, n]."""
    n = check_n(n)
    xi = check_xi(xi)
    k = _array("k", k, 0.0, n, f"[0, n] = [0, {n}]")
    return _out(np.exp(math.log(xi) * (k / n)))


def _multiplicative_core(one_minus_t: np.ndarray, n: int, xi: float) -> np.ndarray:
    big_l = -math.log(xi)
    l_prime = big_l / -math.expm1(-2.0 * n)  # m e^n of eq 11a
    return np.exp(-l_prime * one_minus_t)


def p_multiplicative_scaled(t, n, xi):
    """Eqs 10-11 in the scaled variable t = U_G / e^n in [-1, 1].

    p = a exp(m U_G) with m, a of eqs 11a-11b is p(t) = xi ** ((1 - t)/(1 - e^(-2n)))
    = exp(-L (1 - t) / (-expm1(-2n))), L = ln(1/xi). p(e^-n / e^n) = xi, p(1) = 1.
    """
    n = check_n(n)
    xi = check_xi(xi)
    t = _array("t", t, -1.0, 1.0, "[-1, 1] (U_G in [-e^n, e^n])")
    return _out(_multiplicative_core(1.0 - t, n, xi))


def p_multiplicative(ln_U_G, n, xi):
    """Eqs 10-11 as a function of ln U_G in [-n, n] (U_G = e^(n-2k) for the {-1,+1} tuple).

    t = exp(ln U_G - n); 1 - t is formed as -expm1(ln U_G - n) so that U_G close to e^n keeps
    its digits.
    """
    n = check_n(n)
    xi = check_xi(xi)
    ln_u = _array("ln_U_G", ln_U_G, -float(n), float(n), f"[-n, n] = [-{n}, {n}]")
    return _out(_multiplicative_core(-np.expm1(ln_u - n), n, xi))


def p_additive_01(U, n, xi):
    """Eq 12, additive rule on the {0,1} tuple: p = xi exp(ln(1/xi) U / n), U in [0, n].

    Written as exp(-L (n - U)/n): exact at both ends (p(0) = xi, p(n) = 1), no overflow.
    """
    n = check_n(n)
    xi = check_xi(xi)
    u = _array("U", U, 0.0, float(n), f"[0, n] = [0, {n}]")
    return _out(np.exp(math.log(xi) * ((n - u) / n)))


def additive_pm1_constants(xi: float) -> tuple[float, float, float]:
    """(r, ln r, c) of eq 13 computed without cancellation.

    r = (xi + 1) + sqrt(xi (xi + 2)); ln r = log1p(xi + sqrt(xi (xi + 2)));
    c = 1 - r/2 = (1 - 4 xi) / (2 (1 - xi + sqrt(xi (xi + 2)))) (exact 1 - 4 xi, no
    cancellation near xi = 1/4 where c changes sign).
    """
    s = math.sqrt(xi * (xi + 2.0))
    r = (xi + 1.0) + s
    ln_r = math.log1p(xi + s)
    c = (1.0 - 4.0 * xi) / (2.0 * (1.0 - xi + s))
    return r, ln_r, c


def p_additive_pm1(U, n, xi):
    """Eq 13, additive rule on the {-1,+1} tuple, U in [-n, n]:

    p = 0.5 r^(U/n) + ((1 - 0.5 r)/n) U, the three-point fit through (-n, xi), (0, 0.5), (n, 1).
    Evaluated as p = xi + (1/(2r)) expm1(ln r (1 + U/n)) + c (1 + U/n) (see module docstring).
    """
    n = check_n(n)
    xi = check_xi(xi)
    u = _array("U", U, -float(n), float(n), f"[-n, n] = [-{n}, {n}]")
    r, ln_r, c = additive_pm1_constants(xi)
    y = (n + u) / n
    return _out(xi + np.expm1(ln_r * y) / (2.0 * r) + c * y)


def p_preferential(U, g, xi):
    """Eq 14, preferential rule: p = ((1 - xi)/g^2) U^2 + xi, U in [-g, g], g = g(n) of eq 15."""
    g = check_real("g", g, 0.0, math.inf, open_interval=True, allowed="must be a finite real > 0 (g(n) of eq 15)")
    xi = check_xi(xi)
    u = _array("U", U, -g, g, f"[-g, g] = [-{g:g}, {g:g}]")
    ratio = u / g
    return _out((1.0 - xi) * ratio * ratio + xi)
