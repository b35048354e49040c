"""The common frame of a receive turn on a scene of one-taxel nodes, fed in one loop: a
well-formed TPDO1 (the decision u_i, object 0x2000 or the cycle tag 0x2003) or TPDO2 (the
reading X_i, REAL32) that the open cycle takes without completing it, or that is late (issue 23,
SYNC -> command).

On the grasp scenes (52 one-taxel nodes) the cycle's answers come as a burst of 52 such frames
and the cycle closes at the last one. Fed one by one, each went through
``EventStream._feed_locked`` -> ``quantise_timestamp`` -> ``CycleAssembler.feed_all`` ->
``_entry`` -> ``_route`` -> ``_feed`` -> ``_delivered`` (7-11 µs a frame on the development
machine, ~0.45 ms of a cycle's SYNC -> command, bench/grip_latency.py ``assemble``).
:meth:`NodeFrames.feed` does the same work for a run of them in one loop, as
:class:`~.common_frames.CommonFrames` does for packed patch TPDOs: the assembler's state bound
to locals once per run, one dict lookup a frame, the per-node and per-taxel arrays written
through memoryviews, the counters added once at the end.

It stops at the first frame that is anything else - a flag, a COB-ID that is no one-taxel TPDO,
a wrong length or value, a frame not received (the centre's own), a repeat that is duplicate
node-ID evidence, a frame that ends the synchronous window or completes the cycle, an exception
(``None`` data, an odd time stamp) - having changed nothing for it, and the stream feeds that
frame through the general path, which decides, counts and raises exactly as before. So a turn
gives the same closed cycles, counters and records as feeding its frames one by one
(tests/test_node_frames.py, on random streams).
"""

from __future__ import annotations

import math
import struct
import sys
from typing import Sequence

from .cycle_records import C_LATE, C_TPDO1, C_TPDO2, TAG_MASK
from .decoder import K_TPDO1, K_TPDO2, STATE_OPERATIONAL, decision_of

__all__ = ["NodeFrames"]

NO_WINDOW_END = sys.maxsize  # the open cycle's window end when there is no window (0x1007 = 0)
_REAL32 = struct.Struct("<f")


class NodeFrames:
    """The common-frame path of a :class:`~.cycles.CycleAssembler` of one-taxel nodes (module
    docstring); :meth:`for_assembler` gives None for any other (patch nodes: ``CommonFrames``)."""

    def __init__(self, assembler):
        self.assembler = assembler
        # per channel: COB-ID of a one-taxel TPDO1 / TPDO2 -> (kind, taxel = device index)
        self.tables: list[dict[int, tuple[int, int]]] = [
            {cob_id: (kind, idx) for cob_id, (kind, idx) in table.items() if kind in (K_TPDO1, K_TPDO2)}
            for table in assembler.layout.tables]
        self.fd = assembler.fd
        self._views: tuple | None = None
        self._arrays: tuple = ()

    def _bound(self) -> tuple:
        """Memoryviews of the assembler's per-taxel arrays (filled in place at every SYNC; made
        again should one be replaced)."""
        a = self.assembler
        arrays = (a.got1, a.got2, a.decisions, a.held_decisions, a.readings, a.held_readings, a.last_heard,
                  a.state)
        if self._views is None or any(x is not y for x, y in zip(arrays, self._arrays)):
            self._arrays = arrays
            self._views = tuple(memoryview(x) for x in arrays)
        return self._views

    @classmethod
    def for_assembler(cls, assembler) -> NodeFrames | None:
        if assembler.patch or assembler.n_devices != assembler.n:
            return None
        return cls(assembler)

    def feed(self, msgs: Sequence, start: int, channel: int, first_us: int | None) -> tuple[int, int]:
        """Feed the common frames of ``msgs`` from ``start`` on, up to the first other one; returns
        how many it fed and the stream time stamp (µs) of the last of them (``CommonFrames.feed``)."""
        a = self.assembler
        if first_us is None or type(a.t0_us) is not int or type(a.last_us) is not int:
            return 0, 0  # nothing fed yet (or not the stream's integer µs)
        try:
            table = self.tables[channel]
            if msgs[start].arbitration_id not in table:
                return 0, 0  # not a TPDO (a heartbeat, an SDO answer...): the general path, no set-up
        except (IndexError, TypeError, AttributeError):
            return 0, 0
        t0 = a.t0_us
        last = a.last_us
        is_open = a.is_open
        sync_raw = a.sync_raw
        sync_counter = a.sync_counter
        tag_now = None if sync_counter is None else sync_counter & TAG_MASK
        tagged = a.tagged
        window_end = sync_raw + a.window_us if is_open and a.window_us else NO_WINDOW_END
        every_sync = a.synchronous_every_sync
        primary = a.primary
        pending = a.pending
        fd = self.fd
        got1, got2, decisions, held_decisions, readings, held_readings, last_heard, state = self._bound()
        expected = a.expected  # replaced at every SYNC: read per frame
        unpack = _REAL32.unpack
        isfinite = math.isfinite
        us = 0
        late = tpdo1 = tpdo2 = 0
        got2_any = False
        index = start  # the first frame not fed here
        for index in range(start, len(msgs)):
            msg = msgs[index]
            try:
                # (not is_fd) is fd: an FD frame on a classic scene, or a classic one on an FD scene
                if (msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id or (not msg.is_fd) is fd
                        or not msg.is_rx):
                    break
                entry = table.get(msg.arbitration_id)
                if entry is None:
                    break
                kind, idx = entry
                data = msg.data
                if kind == K_TPDO1:
                    if len(data) != 1:
                        break
                    value = data[0]
                    u = decision_of(value, tagged)
                    if u is None:
                        break  # bad_value
                else:
                    if len(data) != 4:
                        break
                    reading = unpack(data)[0]
                    if not isfinite(reading):
                        break  # bad_value
                stamp = round(msg.timestamp * 1e6)  # quantise_timestamp; None, inf, NaN raise
                raw = stamp - t0
                if stamp.__class__ is not int or stamp < first_us or raw > window_end:
                    break  # stamped before the stream's start (raised to it there) or after the open window
                if kind == K_TPDO1:
                    stale = raw < sync_raw or (tagged and (tag_now is None or (value >> 2) != tag_now))
                    if tagged and is_open and not stale and got1[idx] and every_sync:
                        break  # a second decision tagged with this cycle: duplicate node-ID evidence
                    accepted = is_open and not stale and not got1[idx]
                    delivers = accepted and primary == K_TPDO1 and every_sync and expected[idx]
                else:
                    accepted = is_open and raw >= sync_raw and not got2[idx]
                    delivers = accepted and primary == K_TPDO2 and every_sync and expected[idx]
                if delivers and pending == 1:
                    break  # the cycle's last awaited answer: it closes the cycle
            except Exception:  # noqa: BLE001 - the general path counts it (internal_error) as before
                break
            us = stamp
            if raw > last:
                last = raw
            last_heard[idx] = last
            state[idx] = STATE_OPERATIONAL
            if kind == K_TPDO1:
                held_decisions[idx] = u
                if not accepted:
                    late += 1
                    continue
                got1[idx] = True
                decisions[idx] = u
                tpdo1 += 1
            else:
                held_readings[idx] = reading
                if not accepted:
                    late += 1
                    continue
                got2[idx] = True
                got2_any = True
                readings[idx] = reading
                tpdo2 += 1
            if delivers:
                pending -= 1
        else:  # no break: every frame from start on was common
            index = len(msgs)
        fed = index - start
        if fed:
            a.last_us = last
            a.pending = pending
            if got2_any:
                a.got2_any = True
            counts = a.counts
            counts[C_TPDO1] += tpdo1
            counts[C_TPDO2] += tpdo2
            counts[C_LATE] += late
            a.late_since += late
        return fed, us
