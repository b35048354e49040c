"""Heartbeat producer of the taxel node twin (CiA 301).

Period from 0x1017 (producer heartbeat time, ms; 0 = off); frame ``0x700+id [state]`` with
the NMT state byte (0x7F pre-operational, 0x05 operational, 0x04 stopped). The next beat is
one period after the planned time (no drift); after a beat that came more than 10 % of the
period late, one period after now (no burst). A write to 0x1017 restarts the producer with
the new period once the value is stored. canopen's ``LocalNode`` would start a python-can
periodic task per node instead (:class:`node_sim.od.NodeObjects` removes that handler).
"""

from __future__ import annotations

import time
from typing import Callable

from .link import Scheduler
from .nmt import BOOT_UP_BASE, INITIALISING, NmtSlave
from .od import HEARTBEAT_PRODUCER, NodeObjects


class HeartbeatProducer:
    """One node's heartbeat: owns its timer (see module docstring)."""

    def __init__(self, node_id: int, nmt: NmtSlave, objects: NodeObjects,
                 send: Callable[[int, bytes], None], scheduler: Scheduler):
        self._can_id = BOOT_UP_BASE + node_id
        self._nmt = nmt
        self._objects = objects
        self._send = send
        self._scheduler = scheduler
        self._timer = None

    def restart(self) -> None:
        """(Re)start with the period 0x1017 holds now; stopped if it is 0."""
        self.stop()
        period_ms = self._objects.read(HEARTBEAT_PRODUCER)
        if period_ms > 0:
            self._schedule(time.monotonic() + period_ms / 1000.0, period_ms / 1000.0)

    def stop(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def written(self, index: int, subindex: int) -> None:
        """0x1017 written over SDO: restart once the value is stored (just after this call)."""
        self._scheduler.call_at(0.0, self.restart)

    def _schedule(self, when: float, period_s: float) -> None:
        def beat():
            state = self._nmt.state
            if state != INITIALISING:
                self._send(self._can_id, bytes([state]))
            # next beat one period after the planned time (no drift); after a beat that
            # came late by more than 10 % of the period, one period after now (no burst)
            now = time.monotonic()
            nxt = when + period_s if now - when <= 0.1 * period_s else now + period_s
            self._schedule(nxt, period_s)

        self._timer = self._scheduler.call_at(when, beat)
