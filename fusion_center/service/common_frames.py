"""The common frame of a receive turn, fed in one loop: a well-formed patch TPDO of packed
decisions that the open cycle takes without completing it, or that is late (issue 14, skin scale).

At 4,096 taxels (``scenes/skin4096.toml``) 88 of the ~100 frames of a cycle are such TPDOs.
Fed one by one, each went through ``EventStream._feed_locked`` -> ``quantise_timestamp`` ->
``CycleAssembler.feed_all`` -> ``_entry`` -> ``_patch`` -> ``SlotDecoder.check`` ->
``_delivered``: seven Python calls and eight numpy scalar reads and writes a frame.
:meth:`CommonFrames.feed` does the same work for a run of such frames in one loop: the scene's
constants and the assembler's state bound to locals once per run, one dict lookup a frame
giving everything about its TPDO, the per-device and per-slot arrays written through
memoryviews, counters added once at the end of the run. Late frames - answers to an earlier
SYNC (stamped before the open cycle's, or tagged with another counter) or with no cycle open -
are common too: a loaded host hands over many (a sixth of the TPDOs in a replay captured while
the host ran a test suite beside the centre).

It stops at the first frame that is anything else - a flag, a COB-ID that is no packed patch
TPDO, a wrong length, padding or tag, a repeat within the open cycle (a duplicate node-ID
when tagged), a frame that ends the synchronous window or completes the cycle, an exception
(``None`` data, an odd time stamp) - having changed nothing for it, and the stream feeds that
frame through the general path (:meth:`~.stream.EventStream._feed_locked`), which decides,
counts and raises exactly as before; the next run starts after it. So a turn gives the same
closed cycles, counters and records as feeding its frames one by one
(tests/test_common_frames.py, on random streams). An assembler process
(:class:`~.assembler_process.AssemblerProcess`, ``fusion-center assemble``) feeds its turns
the same way, its group's frames through ``GroupAssembler.feed`` for the rest.

Events held behind the open cycle's window (``cycles`` module docstring, "Bus order": SYNC k+1
handled before the last answers to SYNC k, as a loaded host hands them over) change nothing
here: the general path too feeds a node frame stamped inside the window at once, and releases
what is held only when a frame ends the window or completes the cycle - which are not common.
"""

from __future__ import annotations

import sys
from typing import Sequence

from .cycle_records import C_LATE, C_TPDO1
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
                or type(assembler.last_us) is not int):
            return 0, 0  # nothing fed yet (or not the stream's integer µs)
        try:
            table = self.tables[channel]
        except (IndexError, TypeError):
            return 0, 0
        t0 = assembler.t0_us
        last = assembler.last_us
        is_open = assembler.is_open
        sync_raw = assembler.sync_raw
        sync_counter = assembler.sync_counter
        overflow = assembler.sync_overflow
        window_end = sync_raw + assembler.window_us if is_open and assembler.window_us else NO_WINDOW_END
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
        late = 0  # of the frames fed here
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
                if len(data) != length or (tail and data[end:] != tail) or (pad_mask and data[end - 1] & pad_mask):
                    break  # malformed
                stamp = round(msg.timestamp * 1e6)  # quantise_timestamp; None, inf, NaN raise
                raw = stamp - t0
                if stamp.__class__ is not int or stamp < first_us or raw > window_end:
                    break  # stamped before the stream's start (raised to it there) or after the open window
                if not is_open or raw < sync_raw or (tagged and data[0] != sync_counter):
                    # no cycle open, or an answer to an earlier SYNC (stamped before the open
                    # cycle's, or tagged with another counter): late
                    if tagged and not 1 <= data[0] <= overflow:
                        break  # a tag no SYNC carries: malformed
                    accepted = closes = False
                else:
                    if got[slot]:
                        break  # a repeat: late, and a duplicate node-ID when tagged
                    accepted = True
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
            if not accepted:
                late += 1
                continue
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
            counts = assembler.counts
            counts[C_TPDO1] += fed - late
            counts[C_LATE] += late
            assembler.late_since += late
        return fed, us
