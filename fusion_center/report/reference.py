"""High-precision (mpmath) references for the HEBTEM threshold equations 16-18.

Each function solves the chapter's area equation in its mean form - the mean of P(H1) over
[lambda, upper limit] equals 1 - alpha (or 1 - beta) - with the closed-form integral of the
printed curve (eq 10-11, 12/13, 14) at 80 significant digits (more for tiny xi), refined by
``mpmath.findroot`` from a starting guess (usually our double-precision solution). They serve
the work-precision figures of ``bench/threshold_precision.py`` and ``fusion-center report``;
they are slow (milliseconds) and never on the live path. The unit tests keep references of
their own, written independently of this module.
"""

from __future__ import annotations

import math

import mpmath as mp


def _digits(xi: float) -> int:
    return 80 + max(0, int(-math.log10(xi)))


def ref_multiplicative(n, xi, beta, guess_t) -> list[float]:
    """Eq 16 with f from eqs 10-11, as t = lambda/e^n (one non-trivial root)."""
    with mp.workdps(_digits(xi)):
        N, X, B = mp.mpf(n), mp.mpf(xi), mp.mpf(beta)
        E, e2n = mp.e**N, mp.e ** (2 * N)
        m = E * mp.log(1 / X) / (e2n - 1)                     # eq 11a
        a = mp.e ** (-(e2n * mp.log(1 / X) / (e2n - 1)))      # eq 11b
        F = lambda x: a / m * mp.e ** (m * x)                 # antiderivative of eq 10
        H = lambda w: (F(E) - F(E - E * w)) / (E * w) - (1 - B)
        w = mp.findroot(H, mp.mpf(1) - mp.mpf(guess_t))
        return [float(1 - w)]


def ref_additive(n, xi, alpha, guesses, encoding="pm1") -> list[float]:
    """Eq 17 with f from eq 13 (pm1) or eq 12 (01): one root per starting guess, ascending."""
    with mp.workdps(_digits(xi)):
        N, X, A = mp.mpf(n), mp.mpf(xi), mp.mpf(alpha)
        if encoding == "pm1":
            r = (X + 1) + mp.sqrt(X * (X + 2))
            F = lambda U: n * r ** (U / N) / (2 * mp.log(r)) + (1 - r / 2) * U**2 / (2 * N)
        else:
            L = mp.log(1 / X)
            F = lambda U: X * N / L * mp.e ** (L * U / N)
        H = lambda d: (F(N) - F(N - d)) / d - (1 - A)
        return sorted(float(N - mp.findroot(H, N - mp.mpf(g))) for g in guesses)


def ref_preferential(n, xi, alpha, g, guess) -> list[float]:
    """Eq 18 with f from eq 14 and g = g(n) (eq 15): the mean threshold near ``guess``."""
    with mp.workdps(80):
        X, A, G = mp.mpf(xi), mp.mpf(alpha), mp.mpf(g)
        F = lambda x: (1 - X) * x**3 / (3 * G**2) + X * x
        H = lambda d: (F(G) - F(G - d)) / d - (1 - A)
        return [float(G - mp.findroot(H, G - mp.mpf(guess)))]
