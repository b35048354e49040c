"""The common frame of a receive turn, fed in one loop: a patch TPDO of packed decisions that
the open cycle takes and that does not close it (issue 14, skin scale).

At 4,096 taxels (``scenes/skin4096.toml``) 88 of the ~100 frames of a cycle are such TPDOs.
Fed one by one, each went through ``EventStream._feed_locked`` -> ``quantise_timestamp`` ->
``CycleAssembler.feed_all`` -> ``_entry`` -> ``_patch`` -> ``SlotDecoder.check`` ->
``_delivered``: seven Python calls and eight numpy scalar reads and writes a frame.
:meth:`CommonFrames.feed` does the same work for a run of such frames in one loop: the scene's
constants and the assembler's state bound to locals once per run, one dict lookup a frame
giving everything about its TPDO, the per-device and per-slot arrays written through
memoryviews, counters added once at the end of the run.

It stops at the first frame that is anything else - a flag, a COB-ID that is no packed patch
TPDO, a wrong length or padding, a tag or time stamp of another cycle, a repeat, no cycle open,
a frame that ends the synchronous window or completes the cycle, held events, an exception
(``None`` data, an odd time stamp) - having changed nothing for it, and the stream feeds that
frame through the general path (:meth:`~.stream.EventStream._feed_locked`), which decides,
counts and raises exactly as before; the next run starts after it. So a turn gives the same
closed cycles, counters and records as feeding its frames one by one
(tests/test_common_frames.py, on random streams).
"""

from __future__ import annotations

import sys
from typing import Sequence

from .cycle_records import C_TPDO1
from .decoder import K_PATCH, STATE_OPERATIONAL

__all__ = ["CommonFrames"]

NO_WINDOW_END = sys.maxsize  # the open cycle's window end when there is no window (0x1007 = 0)


class CommonFrames:
    """The common-frame path of a :class:`~.cycles.CycleAssembler` with packed decisions
    (module docstring); :meth:`for_assembler` gives None for an assembler without them."""

    def __init__(self, assembler):
        self.assembler = assembler
        self.packed = packed = assembler.packed
        layout = assembler.layout
        # per channel, as layout.tables: COB-ID of a packed patch TPDO -> everything its frame needs
        self.tables: list[dict[int, tuple]] = []
        for table in layout.tables:
            slots = {}
            for cob_id, (kind, slot) in table.items():
                place = packed.places[slot] if kind == K_PATCH else None
                if place is None:
                    continue
                decoder = layout.slot_decoders[slot]
                first, stop, start, end = place
                slots[cob_id] = (slot, int(layout.slot_device[slot]), decoder.length, decoder.tail,
                                 decoder.pad_mask, decoder.tagged, first, stop, start, end)
            self.tables.append(slots)
        self.fd = assembler.fd  # the scene's PDOs are CAN FD frames: a common frame has is_fd set

    @classmethod
    def for_assembler(cls, assembler) -> CommonFrames | None:
        """None when no TPDO of the assembler's scene carries packed decisions."""
        packed = assembler.packed
        if packed is None or all(place is None for place in packed.places):
            return None
        return cls(assembler)

    def feed(self, msgs: Sequence, start: int, channel: int, first_us: int | None) -> tuple[int, int]:
        """Feed the common frames of ``msgs`` from ``start`` on, up to the first other one.

        Returns how many it fed and the stream time stamp (µs) of the last of them: the
        stream's own bookkeeping of these frames (``fed``, ``last_us``). ``first_us``: the
        stream's first time stamp (None: nothing was fed yet); a frame stamped before it is
        left to the general path, which raises its stamp to it."""
        assembler = self.assembler
        if (assembler.packed is not self.packed or first_us is None or type(assembler.t0_us) is not int
                or type(assembler.last_us) is not int or not assembler.is_open or assembler.held):
            return 0, 0  # nothing fed yet (or not the stream's integer µs), no cycle open, held events
        try:
            table = self.tables[channel]
        except (IndexError, TypeError):
            return 0, 0
        t0 = assembler.t0_us
        last = assembler.last_us
        sync_raw = assembler.sync_raw
        sync_counter = assembler.sync_counter
        window_end = sync_raw + assembler.window_us if assembler.window_us else NO_WINDOW_END
        every_sync = assembler.synchronous_every_sync
        pending = assembler.pending
        fd = self.fd
        packed = self.packed
        cycle_bytes, held_bytes = packed.cycle_bytes, packed.held_bytes
        heard = memoryview(packed.heard)
        got = memoryview(assembler.slot_got)
        expected = memoryview(assembler.expected)
        last_heard = memoryview(assembler.last_heard)
        state = memoryview(assembler.state)
        us = 0
        index = start  # the first frame not fed here
        for index in range(start, len(msgs)):
            msg = msgs[index]
            try:
                # (not is_fd) is fd: an FD frame on a classic scene, or a classic one on an FD scene
                if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id or (not msg.is_fd) is fd:
                    break
                tpdo = table.get(msg.arbitration_id)
                if tpdo is None:
                    break
                slot, device, length, tail, pad_mask, tagged, first, stop, payload_start, end = tpdo
                data = msg.data
                if (len(data) != length or (tail and data[end:] != tail) or (pad_mask and data[end - 1] & pad_mask)
                        or (tagged and data[0] != sync_counter) or got[slot]):
                    break  # malformed, another cycle's tag (the open cycle's counter is in range), a repeat
                stamp = round(msg.timestamp * 1e6)  # quantise_timestamp; None, inf, NaN raise
                raw = stamp - t0
                if stamp.__class__ is not int or stamp < first_us or raw < sync_raw or raw > window_end:
                    break  # before the stream's start (to be raised to it), the open cycle's SYNC or after its window
                closes = every_sync and expected[device]
                if closes and pending == 1:
                    break  # the cycle's last awaited TPDO: it closes the cycle
            except Exception:  # noqa: BLE001 - the general path counts it (internal_error) as before
                break
            us = stamp
            if raw > last:
                last = raw
            last_heard[device] = last
            state[device] = STATE_OPERATIONAL
            payload = data[payload_start:end]
            held_bytes[first:stop] = payload
            heard[slot] = True
            got[slot] = True
            cycle_bytes[first:stop] = payload
            if closes:
                pending -= 1
        else:  # no break: every frame from start on was common
            index = len(msgs)
        fed = index - start
        if fed:
            assembler.last_us = last
            assembler.pending = pending
            assembler.counts[C_TPDO1] += fed
        return fed, us
