"""Suite-wide checks that no single test can make for itself."""

from __future__ import annotations

import sys

import pytest


@pytest.fixture(autouse=True)
def _mpmath_precision_left_as_found(request):
    """mpmath's working precision is global: a test (or a module's fixture) that sets it and does
    not restore it changes the precision of the references of whatever runs after it in the same
    worker. Tests take theirs with ``mp.workdps(n)`` (a ``with`` block, a decorator or a
    module-scoped fixture); this fails, at teardown, any test that leaves another precision."""
    mpmath = sys.modules.get("mpmath")
    before = mpmath.mp.prec if mpmath else None
    yield
    mpmath = sys.modules.get("mpmath")
    if mpmath is not None:
        after = mpmath.mp.prec
        expected = 53 if before is None else before
        assert after == expected, (f"{request.node.nodeid} left mpmath at {after} bits of precision "
                                   f"(found {expected}): take it with mp.workdps(n), not mp.dps = n")
