"""Keep what a set-up allocated out of the cyclic garbage collector while a run goes on.

A full collection traverses every tracked object: at 4,096 taxels the EDS imports, object
dictionaries, canopen objects and scene arrays of a centre or of the node twins made it a
40-130 ms pause on the SYNC path whenever it ran (after ``gc.freeze()`` 1.6 ms). The centre's
run, the rig and an assembler process each :func:`hold` the freeze while they run and
:func:`release` it when they stop; the objects are given back to the collector when the last
holder of the process releases (``gc.unfreeze()``), so what became garbage meanwhile - a
stopped rig, a finished run - is collected then, never kept for the life of the process.
"""

from __future__ import annotations

import gc
import threading

_lock = threading.Lock()
_holders = 0


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
