"""What a node twin needs from its channel: :class:`NodeLink` and :class:`Scheduler`.

One channel (CANopen network) of the rig has one lock, one :class:`Scheduler` (the timer
thread of all its nodes: heartbeats, inhibit times, event timers) and one :class:`NodeLink`
(send a frame; hold the frames of one SYNC and send them as one burst). Every node entry
point and every timer callback runs with the channel lock held; nodes never block.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from .pdo import _TpdoRuntime

logger = logging.getLogger(__name__)


class Scheduler:
    """One timer thread for many nodes: ``call_at(monotonic_time, fn)`` runs ``fn`` with
    ``lock`` held. Returns a handle with ``cancel()``."""

    @dataclass(order=True)
    class _Entry:
        when: float
        seq: int
        fn: Callable[[], None] = field(compare=False)
        cancelled: bool = field(default=False, compare=False)

        def cancel(self) -> None:
            self.cancelled = True

    def __init__(self, lock: threading.RLock, name: str = "node-sim-timers"):
        self._lock = lock
        self._heap: list[Scheduler._Entry] = []
        self._cv = threading.Condition(threading.Lock())
        self._seq = itertools.count()
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def call_at(self, when: float, fn: Callable[[], None]) -> "Scheduler._Entry":
        entry = Scheduler._Entry(when, next(self._seq), fn)
        with self._cv:
            heapq.heappush(self._heap, entry)
            self._cv.notify()
        return entry

    def call_later(self, delay_s: float, fn: Callable[[], None]) -> "Scheduler._Entry":
        return self.call_at(time.monotonic() + delay_s, fn)

    def stop(self) -> None:
        with self._cv:
            self._stopped = True
            self._cv.notify()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=5)

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._stopped:
                    now = time.monotonic()
                    while self._heap and self._heap[0].cancelled:
                        heapq.heappop(self._heap)
                    if self._heap and self._heap[0].when <= now:
                        entry = heapq.heappop(self._heap)
                        break
                    self._cv.wait(None if not self._heap else self._heap[0].when - now)
                else:
                    return
            if entry.cancelled:
                continue
            with self._lock:
                if entry.cancelled:
                    continue
                try:
                    entry.fn()
                except Exception:  # a timer must never kill the thread
                    logger.exception("node-sim timer callback failed")


class NodeLink:
    """What a node needs from its channel: ``send(can_id, data, fd=False)``, a :class:`Scheduler`.

    ``fd``: a CAN FD frame with bit-rate switch (the PDOs of a scene with ``[bus] fd = true``;
    SDO, NMT, heartbeat and EMCY stay classic). An FD frame is handed on as ``(can_id, data,
    True)``: the channel's ``send(can_id, data, True)`` / in a burst a 3-tuple; a classic one as
    before (``send(can_id, data)``, a 2-tuple), so a channel that never sends FD needs no change.

    Bursts: between :meth:`hold` and :meth:`release` (the channel processing one SYNC for all
    its nodes, lock held) frames are queued and then sent back to back in the order they were
    produced. A TPDO's transmission time (the start of its inhibit time) is the time it really
    left: :meth:`mark_sent` records it at once outside a burst, at the end of the burst inside.
    """

    def __init__(self, send: Callable[[int, bytes], None], scheduler: Scheduler,
                 send_many: Callable[[list[tuple]], None] | None = None):
        self._send_now = send
        self._send_many = send_many   # optional: a whole burst in one call, same order
        self.scheduler = scheduler
        self._held: list[tuple] | None = None
        self._held_tx: list[_TpdoRuntime] = []

    def send(self, can_id: int, data: bytes, fd: bool = False) -> None:
        held = self._held
        if held is not None:
            held.append((can_id, data, True) if fd else (can_id, data))
        elif fd:
            self._send_now(can_id, data, True)
        else:
            self._send_now(can_id, data)

    def send_all(self, frames: list[tuple], sent: "tuple[_TpdoRuntime, ...]") -> None:
        """:meth:`send` each of ``frames`` (``(can_id, data)`` or ``(can_id, data, True)``), then
        :meth:`mark_sent` each of ``sent``: a node's TPDOs of one SYNC in one call."""
        held = self._held
        if held is not None:
            held.extend(frames)
            self._held_tx.extend(sent)
            return
        send = self._send_now
        for frame in frames:
            send(*frame)
        now = time.monotonic()
        for rt in sent:
            rt.last_tx_time = now

    def mark_sent(self, rt: "_TpdoRuntime") -> None:
        if self._held is None:
            rt.last_tx_time = time.monotonic()
        else:
            self._held_tx.append(rt)

    def hold(self) -> None:
        self._held = []
        self._held_tx = []

    @contextlib.contextmanager
    def burst(self):
        """:meth:`hold` for the ``with`` block, then :meth:`release` (also when it raises)."""
        self.hold()
        try:
            yield self
        finally:
            self.release()

    def release(self) -> None:
        held, self._held = self._held, None
        if not held:
            return
        if self._send_many is not None:
            self._send_many(held)
        else:
            send = self._send_now
            for frame in held:
                send(*frame)
        if self._held_tx:
            now = time.monotonic()
            for rt in self._held_tx:
                rt.last_tx_time = now
            self._held_tx = []
