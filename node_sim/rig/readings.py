"""The rig's readings: X_i of every taxel per SYNC cycle, for every channel of the rig.

``reading_source(cycle) -> array`` (X_i in mV per taxel, scene order). Default:
``node_sim.physics.sample_readings(scene, cycle)`` with its canonical per-cycle random numbers
(reproducible in any process; ``seed`` replaces ``scene.seed``), which also applies the scene's
stuck / open-circuit faults. Those are a pure function of (scene, cycle), so the rig computes them
ahead, off the SYNC path: half a SYNC period after a SYNC, a thread of its own fills a cache with
the next :data:`PREFETCH_CYCLES` cycles in one ``sample_readings_batch`` call, holding no lock
while it computes (identical values, tested). An injected ``reading_source`` (or the grasp world's,
:mod:`.drive`) is called only when its cycle's SYNC arrives (it may depend on state set just
before).

:class:`ReadingFeed` is that part of :class:`~node_sim.rig.Rig` (a mixin: the channels call
``rig._readings`` / ``rig._schedule_prefetch``, :mod:`.channel`).
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING, Callable

import numpy as np

from taxel_net.errors import ParameterError

if TYPE_CHECKING:
    from .channel import Channel

logger = logging.getLogger("node_sim.rig")

ReadingSource = Callable[[int], np.ndarray]

PREFETCH_CYCLES = 4  # physics readings computed ahead per batch (4,096 taxels: ~2 ms, done before the next SYNC)


class ReadingFeed:
    """The readings of :class:`~node_sim.rig.Rig` (module docstring): the cache, the read-ahead thread."""

    def _init_readings(self) -> None:
        self._reading_cache: dict[int, np.ndarray] = {}   # cycle -> X (scene order)
        self._reading_lock = threading.Lock()
        self._prefetch_pending = False
        self._prefetch_thread: threading.Thread | None = None  # while started, default readings only
        self._prefetch_wake = threading.Event()
        self._prefetch_first = 0
        self._prefetch_stop = False

    def _start_prefetch(self) -> None:
        """The first SYNC's readings now, then the read-ahead thread (default reading source)."""
        self._readings(0)  # the first SYNC's readings (and the scene's arrays) off its path
        self._prefetch_thread = threading.Thread(target=self._prefetch_loop, name="node-sim-prefetch",
                                                 daemon=True)
        self._prefetch_thread.start()

    def _stop_prefetch(self) -> None:
        if self._prefetch_thread is not None:
            self._prefetch_stop = True
            self._prefetch_wake.set()
            self._prefetch_thread.join(timeout=5)
            self._prefetch_thread = None
            self._prefetch_stop = False
            self._prefetch_pending = False

    def _readings(self, cycle: int) -> np.ndarray:
        with self._reading_lock:
            cache = self._reading_cache
            x = cache.get(cycle)
            if x is not None:
                return x
            if self._reading_source is not None:
                x = np.asarray(self._reading_source(cycle), dtype=float)
            else:
                from .. import physics

                x = physics.sample_readings(self.scene, cycle)
            if x.shape != (self.scene.n,):
                raise ParameterError("reading_source", x.shape, f"must return {self.scene.n} readings (scene order)")
            if self._reading_source is not None:
                cache.clear()  # only the current cycle: an injected source is never read ahead
            cache[cycle] = x
            return x

    def _schedule_prefetch(self, channel: Channel, cycle: int) -> None:
        """After SYNC ``cycle``: at half a SYNC period, have the physics readings of the next
        cycles computed unless the cache already holds them (default reading source only)."""
        if self._reading_source is not None or self._prefetch_pending:
            return
        with self._reading_lock:  # two channels' SYNCs may get here at once: one schedules
            if self._prefetch_pending or cycle + 1 in self._reading_cache:
                return
            self._prefetch_pending = True
        delay = 0.5 * self.scene.bus.sync_period_ms / 1000.0
        channel.scheduler.call_later(delay, lambda: self._prefetch_request(cycle + 1))

    def _prefetch_request(self, first: int) -> None:
        """Timer callback (the channel lock is held): hand the work to the prefetch thread."""
        self._prefetch_first = first
        self._prefetch_wake.set()

    def _prefetch_loop(self) -> None:
        while True:
            self._prefetch_wake.wait()
            self._prefetch_wake.clear()
            if self._prefetch_stop:
                return
            try:
                self._prefetch(self._prefetch_first)
            except Exception:  # noqa: BLE001 - the SYNC path computes what is missing
                logger.exception("node-sim: reading ahead failed")

    def _prefetch(self, first: int) -> None:
        """The readings of :data:`PREFETCH_CYCLES` cycles from ``first`` on, computed with no lock
        held (the cache's lock only to look and to store): a channel's SYNC never waits for the
        physics. Computed by a channel's timer under its lock and the cache's, a batch of 16
        cycles of 4,096 taxels held every channel of the process for ~7 ms (one 800-cycle run
        of bench/skin_scale.py --shards 2: the cycles just after a batch complete 94-96 % of
        the time, the others 100 %; after the change no cycle phase stood out; the p50/p99 of
        the bench moved within its run-to-run spread)."""
        from .. import physics

        try:
            with self._reading_lock:
                # SYNCs may have come meanwhile: start at the next cycle no channel has seen yet
                # (sync_count is read without the channel locks: a stale value only costs one
                # cycle computed on the SYNC path instead of here)
                counts = [ch.sync_count for ch in self._channels] or [first]
                first = max(first, max(counts))
                cache = self._reading_cache
                for old in [c for c in cache if c < min(counts) - 1]:
                    del cache[old]
                wanted = [c for c in range(first, first + PREFETCH_CYCLES) if c not in cache]
            if wanted:
                batch = physics.sample_readings_batch(self.scene, np.array(wanted))
                with self._reading_lock:
                    for c, x in zip(wanted, batch):
                        cache.setdefault(c, x)  # the SYNC path may have computed it meanwhile: the same values
        finally:
            self._prefetch_pending = False
