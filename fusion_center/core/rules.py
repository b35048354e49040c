"""Fusion rules of the chapter (sec. 2.2.1-2.2.2, eqs 5-7 and 15).

Every rule takes the local decisions ``u`` and their ``encoding`` explicitly:

* ``"pm1"``: u_i in {-1, +1};
* ``"01"``:  u_i in {0, 1}.

The rules are the chapter's formulas applied *literally* to the values of the given tuple
(the chapter: "in a similar manner, we can obtain the values of U_G using {u_i}=[0,1] tuple").
So the additive rule gives n - 2k (pm1) or n - k (01), the multiplicative rule e^(n-2k) or
e^(n-k), where k is the number of taxels deciding "absent". For the preferential rule this
literal reading is what reproduces the chapter's worked example of sec. 7.2 (U_G = 37 for the
18-taxel gripper with 13 present, p = q = 1): eq 7 on the {0,1} tuple gives 37, on the
{-1,+1} tuple it gives 14 (see docs/chapter-notes.md).

Pure functions, no I/O.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .encoding import PRESENT, Encoding, check_integer, check_real, validate_decisions

__all__ = [
    "MultiplicativeValue",
    "additive",
    "multiplicative",
    "preferential",
    "preferential_coefficients",
    "preferential_value",
    "preferential_exact",
    "preferential_sister",
    "k_of_n",
    "g_of_n",
    "check_weight",
]


class MultiplicativeValue(NamedTuple):
    """U_G of the multiplicative rule (eq 5) in three forms that never overflow silently.

    ``ln_U_G`` = sum u_i (exact), ``U_G`` = exp(ln_U_G) (``inf`` above ~e^709, ``0.0`` below
    ~e^-745; never raises), ``scaled`` = U_G / e^n = exp(ln_U_G - n), the variable of the
    threshold solver (``thresholds.multiplicative_threshold``).
    """

    ln_U_G: float
    U_G: float
    scaled: float


# largest taxel count: every count 0..n and every U_G of eqs 5-6 is an exact float64 integer
MAX_TAXELS = 2**53


def check_weight(name: str, value) -> float:
    """p or q of eq 7: a finite real in [0, 2] (the chapter: 0 <= p, q <= 2)."""
    return check_real(name, value, 0.0, 2.0, allowed="must be a real number in [0, 2]")


def _check_n(n) -> int:
    return check_integer("n", n, 1, MAX_TAXELS, allowed="must be an integer >= 1 (and <= 2^53)")


def additive(u, encoding: Encoding) -> int:
    """Additive rule, eq 6: U_G = sum u_i = n - 2k (pm1) or n - k (01), k = absent count."""
    arr = validate_decisions(u, encoding)
    return int(arr.sum(dtype=np.int64))


def multiplicative(u, encoding: Encoding) -> MultiplicativeValue:
    """Multiplicative rule, eq 5: U_G = prod e^(u_i) = e^(n-2k) (pm1) or e^(n-k) (01).

    Returns ln U_G, U_G and U_G/e^n (see :class:`MultiplicativeValue`).
    """
    arr = validate_decisions(u, encoding)
    ln_u_g = float(arr.sum(dtype=np.int64))
    n = arr.size
    # exp of a huge argument: inf, not OverflowError
    try:
        u_g = math.exp(ln_u_g)
    except OverflowError:
        u_g = math.inf
    return MultiplicativeValue(ln_U_G=ln_u_g, U_G=u_g, scaled=math.exp(ln_u_g - n))


def _pow(base: np.ndarray, exponent: float) -> np.ndarray:
    # numpy already follows 0.0 ** 0.0 == 1.0 (the chapter's eq 15 needs (1+u)^0 = 1 for u=-1)
    return np.power(base, exponent)


def _neighbour_sum(values: np.ndarray, p: float, q: float, sign: float) -> float:
    padded = np.concatenate(([0.0], values, [0.0]))  # u_0 = u_{n+1} = 0 (chapter, below eq 7)
    nxt = padded[2:]
    prv = padded[:-2]
    terms = values * _pow(1.0 + sign * nxt, p) * _pow(1.0 + sign * prv, q)
    return float(terms.sum())


def preferential_coefficients(u, encoding: Encoding) -> tuple[int, int, int, int, int, int, int, int, int]:
    """Integer counts behind eq 7: U_G = sum over taxels of u_i F_p(s_next) F_q(s_prev), where a
    neighbour's factor (1 + u)^p is 0^p (absent on {-1,+1}), 1 (boundary u_0 = u_{n+1} = 0, or
    absent on {0,1}) or 2^p (present). Returns w[s_next][s_prev] flattened (s = 0: factor 0^.,
    1: factor 1, 2: factor 2^.), each the signed sum of u_i over the taxels in that state, so

        U_G = sum_{s, t} w[s][t] F_p(s) F_q(t)   exactly.
    """
    arr = validate_decisions(u, encoding).astype(np.int64)
    padded = np.concatenate(([0], arr, [0]))
    base = 1 + padded  # 1 + u_j: 0 (absent pm1), 1 (boundary / absent 01), 2 (present)
    nxt, prv = base[2:], base[:-2]
    index = 3 * nxt + prv
    w = np.bincount(index, weights=arr, minlength=9)
    return tuple(int(round(x)) for x in w)


def preferential_value(coefficients, p: float, q: float) -> float:
    """U_G of eq 7 from :func:`preferential_coefficients`, in floats: a + b 2^p + c 2^q + d 2^(p+q)
    with integer a, b, c, d (0^p, 0^q folded in). For the all-present vector this is the same
    float expression as g(n) (:func:`g_of_n`): (2^p + 2^q) + (n - 2) 2^(p+q), so U_G never
    exceeds g by a rounding error."""
    w = coefficients
    zp = 1 if p == 0.0 else 0
    zq = 1 if q == 0.0 else 0
    fp = (zp, 1, None)
    fq = (zq, 1, None)
    a = b = c = d = 0  # constant, 2^p, 2^q, 2^(p+q)
    for s in range(3):
        for t in range(3):
            k = w[3 * s + t]
            if not k:
                continue
            if s < 2 and t < 2:
                a += k * fp[s] * fq[t]
            elif s == 2 and t < 2:
                b += k * fq[t]
            elif s < 2 and t == 2:
                c += k * fp[s]
            else:
                d += k
    return ((b * 2.0**p + c * 2.0**q) + d * 2.0 ** (p + q)) + a


def preferential_exact(coefficients, p: float, q: float):
    """U_G of eq 7 as an mpmath number in the current precision (exact inputs)."""
    import mpmath

    w = coefficients
    big_p, big_q = mpmath.mpf(2) ** mpmath.mpf(p), mpmath.mpf(2) ** mpmath.mpf(q)
    fp = (1 if p == 0.0 else 0, 1, big_p)
    fq = (1 if q == 0.0 else 0, 1, big_q)
    return mpmath.fsum(w[3 * s + t] * fp[s] * fq[t] for s in range(3) for t in range(3) if w[3 * s + t])


def preferential(u, p, q, encoding: Encoding) -> float:
    """Preferential selection rule, eq 7: U_G = sum_i u_i (1 + u_{i+1})^p (1 + u_{i-1})^q.

    u_0 = u_{n+1} = 0 (the chapter's boundary convention), 0**0 = 1, p and q real in [0, 2]
    (weights of the succeeding and the preceding taxel). Applied to the values of the given
    tuple. For all taxels present the value is g(n) of eq 15 (:func:`g_of_n`) in both tuples,
    as the same float. Evaluated from the integer counts of :func:`preferential_coefficients`
    (error a few ulps of g; exact for integer p, q while the values stay below 2^53).
    """
    p = check_weight("p", p)
    q = check_weight("q", q)
    return preferential_value(preferential_coefficients(u, encoding), p, q)


def preferential_sister(u, p, q, encoding: Encoding) -> float:
    """The chapter's "sister model" of eq 7 (sec. 2.2.2): sum_i u_i (1 - u_{i+1})^p (1 - u_{i-1})^q.

    Same boundary convention (u_0 = u_{n+1} = 0), 0**0 = 1, p, q in [0, 2].
    """
    p = check_weight("p", p)
    q = check_weight("q", q)
    arr = validate_decisions(u, encoding).astype(float)
    return _neighbour_sum(arr, p, q, -1.0)


def k_of_n(u, k, encoding: Encoding) -> int:
    """The "k-out-of-n" rule of sec. 2.2.1: +1 if at least ``k`` taxels decide present, else -1.

    (The chapter's k here counts *present* taxels, unlike its k in eqs 5-6 which counts absent
    ones.) ``k`` must be an integer in 1..n.
    """
    arr = validate_decisions(u, encoding)
    n = arr.size
    k = check_integer("k", k, 1, n, allowed=f"must be an integer in 1..n (n = {n})")
    present = int(np.count_nonzero(arr == PRESENT))
    return 1 if present >= k else -1


def g_of_n(n, p, q) -> float:
    """g(n) of eq 15: the maximum of U_G (eq 7) over all decision vectors, reached with all u_i = +1.

    For n >= 2: g(n) = (2^p + 2^q) + (n - 2) 2^(p+q) (end taxels see one neighbour, the n - 2
    inner ones two). For n = 1 the single taxel has u_0 = u_2 = 0, so eq 7 gives
    U_G = 1 * 1^p * 1^q = 1: g(1) = 1 (eq 15 itself would give 2^p + 2^q - 2^(p+q), which is not
    the value of eq 7; we use eq 7).
    """
    n = _check_n(n)
    p = check_weight("p", p)
    q = check_weight("q", q)
    if n == 1:
        return 1.0
    return (2.0**p + 2.0**q) + (n - 2) * 2.0 ** (p + q)
