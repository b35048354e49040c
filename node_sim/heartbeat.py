"""Heartbeat producer and consumer of the taxel node twin (CiA 301 0x1017, 0x1016, 0x1029).

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

from canopen.sdo import SdoAbortedError

from .link import Scheduler
from .nmt import BOOT_UP_BASE, INITIALISING, NmtSlave
from .od import CONSUMER_HEARTBEAT, HEARTBEAT_PRODUCER, NodeObjects
from .sdo import ABORT_VALUE_RANGE


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


# ---------------------------------------------------------------------------- consumer

ABORT_PARAMETER_INCOMPATIBLE = 0x06040043
EMCY_HEARTBEAT = 0x8130        # CiA 301: life guard error or heartbeat error


class HeartbeatConsumer:
    """Heartbeat consumer of one node (CiA 301 0x1016) and its error behaviour (0x1029).

    0x1016:1..2 = ``node-ID << 16 | time ms`` (0 in either part: entry off; bits 24-31 must
    be 0: 0x06090030; two active entries for one node-ID: 0x06040043). An entry's monitoring
    starts at the first heartbeat of that node after it was configured (or after a boot);
    each heartbeat restarts its timer on the channel's scheduler. No heartbeat within the time:
    a heartbeat event — EMCY 0x8130 (error register bits 0 and 4), then the NMT state that
    0x1029:1 gives (0: pre-operational if operational, 1: no change, 2: stopped); the next
    heartbeat of that node ends the error (error reset EMCY) and monitoring goes on.
    Heartbeats reach it from the channel (``on_heartbeat``): from other bus participants,
    such as the master; twins of the same rig channel do not hear each other.
    """

    def __init__(self, nmt: NmtSlave, objects: NodeObjects, scheduler: Scheduler,
                 heartbeat_event: Callable[[int, bool], None]):
        self._nmt = nmt
        self._objects = objects
        self._scheduler = scheduler
        self._event = heartbeat_event       # (producer node-ID, lost) -> EMCY and behaviour
        self._timers: dict[int, object] = {}  # producer node-ID -> its timer (monitoring)
        self._lost: set[int] = set()
        self._times: dict[int, float] | None = None  # producer node-ID -> time s (from 0x1016)

    def _configured(self) -> dict[int, float]:
        times = self._times
        if times is None:
            times = {}
            obj = self._objects.od[CONSUMER_HEARTBEAT]
            for sub in range(1, self._objects.read(CONSUMER_HEARTBEAT, 0) + 1):
                if sub not in obj:
                    continue
                value = self._objects.read(CONSUMER_HEARTBEAT, sub)
                node_id, ms = (value >> 16) & 0xFF, value & 0xFFFF
                if node_id and ms:
                    times[node_id] = ms / 1000.0
            self._times = times
        return times

    @property
    def lost(self) -> frozenset[int]:
        """Producers whose heartbeat is lost now."""
        return frozenset(self._lost)

    @property
    def monitored(self) -> frozenset[int]:
        """Producers whose heartbeat is being timed now (seen since 0x1016 was configured, not lost)."""
        return frozenset(self._timers)

    def reset(self) -> None:
        """Boot / 0x1016 written: stop monitoring, forget lost heartbeats, re-read 0x1016."""
        for timer in self._timers.values():
            timer.cancel()
        self._timers.clear()
        self._lost.clear()
        self._times = None

    def written(self, index: int, subindex: int) -> None:
        self._scheduler.call_at(0.0, self.reset)  # once the value is stored

    def check_write(self, index: int, subindex: int, value, startup: bool) -> None:
        if index != CONSUMER_HEARTBEAT or subindex == 0:
            return
        if value & 0xFF000000:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        node_id, ms = (value >> 16) & 0xFF, value & 0xFFFF
        if node_id == 0 or ms == 0:
            return
        for sub in range(1, self._objects.read(CONSUMER_HEARTBEAT, 0) + 1):
            if sub == subindex:
                continue
            other = self._objects.read(CONSUMER_HEARTBEAT, sub)
            if (other >> 16) & 0xFF == node_id and other & 0xFFFF:
                raise SdoAbortedError(ABORT_PARAMETER_INCOMPATIBLE)

    def on_heartbeat(self, node_id: int, state: int) -> None:
        """A heartbeat (or boot-up) of ``node_id`` seen on the bus."""
        if self._nmt.state == INITIALISING:
            return
        period = self._configured().get(node_id)
        if period is None:
            return
        timer = self._timers.get(node_id)
        if timer is not None:
            timer.cancel()
        if node_id in self._lost:
            self._lost.discard(node_id)
            self._event(node_id, False)

        def expired():
            if self._timers.get(node_id) is entry:
                del self._timers[node_id]
                self._lost.add(node_id)
                self._event(node_id, True)

        entry = self._scheduler.call_later(period, expired)
        self._timers[node_id] = entry
