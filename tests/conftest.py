"""Suite-wide checks that no single test can make for itself."""

from __future__ import annotations

import sys

import pytest

MPMATH_DEFAULT_PREC = 53   # mpmath's working precision, bits, as imported (mp.dps 15)

_HOW = "take it with mp.workdps(n), not mp.dps = n"


def _mpmath_prec() -> int | None:
    mpmath = sys.modules.get("mpmath")
    return None if mpmath is None else mpmath.mp.prec


@pytest.hookimpl(wrapper=True)
def pytest_make_collect_report(collector):
    """Importing a test module must leave mpmath's precision at its default: every test module is
    imported at collection, before any test runs, so a module that sets it at import (``mp.dps =
    50`` at its top) changes the references of every test after it, and the per-test guard below,
    which compares with the precision found at a test's setup, cannot see it. Such a module is a
    collection error naming it (and the precision is put back, so the next modules are judged on
    their own)."""
    report = yield
    if isinstance(collector, pytest.Module):
        prec = _mpmath_prec()
        if prec is not None and prec != MPMATH_DEFAULT_PREC:
            sys.modules["mpmath"].mp.prec = MPMATH_DEFAULT_PREC
            if report.outcome == "passed":
                report.outcome = "failed"
                report.longrepr = (f"{collector.nodeid}: importing it left mpmath at {prec} bits of precision "
                                   f"(default {MPMATH_DEFAULT_PREC}): {_HOW}")
    return report


@pytest.fixture(autouse=True, scope="module")
def _mpmath_precision_default_between_modules(request):
    """A module (its module-scoped fixtures included: autouse fixtures are set up first and torn
    down last in their scope) leaves mpmath at its default precision."""
    yield
    prec = _mpmath_prec()
    if prec is not None and prec != MPMATH_DEFAULT_PREC:
        sys.modules["mpmath"].mp.prec = MPMATH_DEFAULT_PREC
        pytest.fail(f"{request.node.nodeid} left mpmath at {prec} bits of precision after its tests "
                    f"(default {MPMATH_DEFAULT_PREC}): {_HOW}", pytrace=False)


@pytest.fixture(autouse=True)
def _mpmath_precision_left_as_found(request):
    """mpmath's working precision is global: a test (or a module's fixture) that sets it and does
    not restore it changes the precision of the references of whatever runs after it in the same
    worker. Tests take theirs with ``mp.workdps(n)`` (a ``with`` block, a decorator or a
    module-scoped fixture); this fails, at teardown, any test that leaves another precision."""
    before = _mpmath_prec()
    yield
    after = _mpmath_prec()
    if after is not None:
        expected = MPMATH_DEFAULT_PREC if before is None else before
        assert after == expected, (f"{request.node.nodeid} left mpmath at {after} bits of precision "
                                   f"(found {expected}): {_HOW}")
