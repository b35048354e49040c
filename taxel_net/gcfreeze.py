"""Keep what a set-up allocated out of the cyclic garbage collector while a run goes on.

A full collection traverses every tracked object: at 4,096 taxels the EDS imports, object
dictionaries, canopen objects and scene arrays of a centre or of the node twins made it a
40-130 ms pause on the SYNC path whenever it ran (after ``gc.freeze()`` 1.6 ms). The centre's
run, the rig and an assembler process each :func:`hold` the freeze while they run and
:func:`release` it when they stop; the objects are given back to the collector when the last
holder of the process releases (``gc.unfreeze()``), so what became garbage meanwhile - a
stopped rig, a finished run - is collected then, never kept for the life of the process.

**Collections at a quiet moment** (:func:`defer`, :func:`collect_due`): the collector runs
when the allocations outnumber the deallocations by a threshold (700), in whichever thread
allocates then - in the centre, mostly its receive thread, on the way from a cycle's answers
to its grip command: a generation-0 collection of 0.2 ms in about 1 % of the cycles and a
generation-1 one of 2.4 ms once in 600 (``bench/grip_latency.py --transports player``,
docs/grip-control.md), the tail the command's p99 is made of. While deferred, the first
generation's threshold is :data:`BACKSTOP` times its own (a backstop: an allocation storm still
collects), and the holder calls :func:`collect_due` where nothing waits - the centre's SYNC
producer half a period after each SYNC - which collects what CPython's own rule would have
collected by then (the oldest generation whose count passed its threshold); the same
generations, a few milliseconds later, in another thread.
"""

from __future__ import annotations

import gc
import threading

_lock = threading.Lock()
_holders = 0
_deferring = 0
_thresholds: tuple[int, int, int] | None = None  # the collector's own, while deferred
BACKSTOP = 100


def hold() -> None:
    """Freeze every object alive now (``gc.freeze()``) and count one more holder."""
    global _holders
    with _lock:
        gc.freeze()
        _holders += 1


def release() -> None:
    """One holder fewer; the last one gives the frozen objects back (``gc.unfreeze()``)."""
    global _holders
    with _lock:
        if _holders == 0:
            return
        _holders -= 1
        if _holders == 0:
            gc.unfreeze()


def holders() -> int:
    with _lock:
        return _holders


def defer() -> None:
    """Count one more holder of the deferral (module docstring): the first one raises the
    first generation's threshold to :data:`BACKSTOP` times its own."""
    global _deferring, _thresholds
    with _lock:
        if _deferring == 0:
            _thresholds = gc.get_threshold()
            t0, t1, t2 = _thresholds
            if t0 > 0:  # (0: the collector's automatic runs are off already)
                gc.set_threshold(t0 * BACKSTOP, t1, t2)
        _deferring += 1


def resume() -> None:
    """One holder of the deferral fewer; the last one gives the collector its thresholds back."""
    global _deferring, _thresholds
    with _lock:
        if _deferring == 0:
            return
        _deferring -= 1
        if _deferring == 0 and _thresholds is not None:
            gc.set_threshold(*_thresholds)
            _thresholds = None


def collect_due() -> int | None:
    """While deferred: the collection CPython's rule would have made by now, in the calling
    thread - the oldest generation whose count is over its threshold (generation 2: the
    generation-1 collections since its last; 1: the generation-0 collections since its last; 0:
    the allocations less the deallocations); returns that generation, or None (nothing due, not
    deferred, or the collector off). A full collection is made on its count alone: CPython adds
    a condition Python does not see (the objects promoted since the last full collection at
    least a quarter of the long-lived ones), so this one collects the oldest generation at
    least as often as CPython would - never less, or cyclic garbage that outlived a
    generation-1 collection would pile up for the whole run - at the cost of a full collection
    every ~11 generation-1 ones, made mid-period; the set-up's objects are frozen meanwhile
    (:func:`hold`) and not traversed."""
    with _lock:
        thresholds = _thresholds if _deferring else None
    if thresholds is None or not gc.isenabled() or thresholds[0] <= 0:
        return None
    counts = gc.get_count()
    for generation in (2, 1, 0):
        if counts[generation] > thresholds[generation]:
            gc.collect(generation)
            return generation
    return None
