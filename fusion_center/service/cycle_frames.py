"""The cycle assembler's frame decoding: what one event of the stream is and what it says.

:class:`CycleFrames` is the base of :class:`~.cycles.CycleAssembler` (as canopen's ``SdoBase``
is of ``SdoClient``): it looks an event's COB-ID up in the scene's tables (:mod:`.cycle_layout`;
flags, CAN FD format), checks a node's frame for length and value, decodes it (TPDO1 decision
and cycle tag, TPDO2 reading, a patch node's TPDO, heartbeat and boot-up, EMCY, SDO, LSS, the
master's heartbeat, the gripper drive's frames, TIME), and counts it under one disposition of
:data:`~.cycle_records.COUNTER_NAMES`. It keeps the node-side state (``last_heard``, ``state``,
the held values, the duplicate node-ID evidence) and decides whether a PDO is ``late`` (the
contract in :mod:`.cycles`' docstring: cycle tags and time stamps).

The SYNC cycles are the assembler's: a SYNC and an NMT command are handed to its ``_sync`` and
``_nmt``, a primary PDO accepted into the open cycle to its ``_delivered``; every attribute read
here is set by ``CycleAssembler.__init__`` and the cycle it opens (``is_open``, ``sync_raw``,
``sync_counter``, ``got1`` / ``got2`` / ``slot_got``).
"""

from __future__ import annotations

import math

from .cycle_records import (
    C_BAD_DLC,
    C_BAD_VALUE,
    C_BOOTUP,
    C_DRIVE,
    C_EMCY,
    C_ERROR,
    C_EXTENDED,
    C_FD,
    C_HEARTBEAT,
    C_LATE,
    C_LSS,
    C_MASTER_HEARTBEAT,
    C_REMOTE,
    C_SDO,
    C_SDO_ABORT,
    C_TIME,
    C_TPDO1,
    C_TPDO2,
    C_UNKNOWN,
    EMCY_PER_CYCLE,
    EmcyEvent,
    FLAG_ERROR,
    FLAG_EXTENDED,
    FLAG_FD,
    FLAG_REMOTE,
    TAG_MASK,
)
from .decoder import (
    HEARTBEAT_STATES,
    K_DRIVE,
    K_EMCY,
    K_HEARTBEAT,
    K_LSS,
    K_MASTER_HEARTBEAT,
    K_NMT,
    K_PATCH,
    K_SDO_REQUEST,
    K_SDO_RESPONSE,
    K_SYNC,
    K_TPDO1,
    K_TPDO2,
    STATE_BOOTUP,
    STATE_OPERATIONAL,
    STATE_PRE_OPERATIONAL,
    decision_of,
    decode_emcy,
    decode_real32,
)

__all__ = ["CycleFrames"]

PDO_KINDS = frozenset({K_TPDO1, K_TPDO2, K_PATCH})  # CAN FD frames on a scene with [bus] fd
K_FORMAT = -1  # a classic frame on a COB-ID whose PDO is a CAN FD frame: counted as fd_frame


class CycleFrames:
    """The frame decoding of :class:`~.cycles.CycleAssembler` (module docstring): one COB-ID
    lookup an event (:meth:`_entry`), then :meth:`_feed` (or :meth:`_patch` for a patch node's
    TPDO) decides, counts and keeps what the frame says."""

    def _entry(self, channel: int, can_id: int, flags: int) -> tuple[int, int] | None:
        """(frame kind, device index or patch slot) of a COB-ID on a channel; None: flagged,
        unknown or no such channel. With ``[bus] fd`` a CAN FD frame (no other flag) on a
        PDO's COB-ID is that PDO, and a classic frame there is ``(K_FORMAT, -1)``."""
        if flags and not (flags == FLAG_FD and self.fd):
            return None
        try:
            entry = self.layout.tables[channel].get(can_id)
        except (IndexError, TypeError, AttributeError):
            return None
        if self.fd and entry is not None and (entry[0] in PDO_KINDS) != bool(flags):
            return (K_FORMAT, -1) if not flags else None  # classic PDO / FD frame on another object
        return entry

    def _feed(self, t: int, raw: int, channel: int, data: bytes, flags: int, entry: tuple[int, int] | None):
        counts = self.counts
        if flags and entry is None:
            if flags & FLAG_ERROR:
                counts[C_ERROR] += 1
            elif flags & FLAG_REMOTE:
                counts[C_REMOTE] += 1
            elif flags & FLAG_EXTENDED:
                counts[C_EXTENDED] += 1
            else:
                counts[C_FD] += 1
            self.bad_since += 1
            return None
        if entry is None:
            counts[C_UNKNOWN] += 1
            self.bad_since += 1
            return None
        kind, idx = entry
        size = len(data)
        if kind == K_PATCH:
            return self._patch(t, raw, idx, data)
        if kind == K_FORMAT:
            counts[C_FD] += 1
            self.bad_since += 1
            return None
        if kind == K_TPDO1:
            if size != 1:
                return self._bad(C_BAD_DLC)
            value = data[0]
            u = decision_of(value, self.tagged)
            if u is None:
                return self._bad(C_BAD_VALUE)
            if self.tagged:
                # the tag names the SYNC it answers: the open cycle's, or it is late; and an
                # answer is never stamped before its SYNC - one that is carries the same tag as
                # a SYNC 64 (or overflow) cycles older, still queued behind a backlog
                stale = (self.sync_counter is None or (value >> 2) != (self.sync_counter & TAG_MASK)
                         or raw < self.sync_raw)
            else:
                stale = raw < self.sync_raw
            self.last_heard[idx] = t
            self.state[idx] = STATE_OPERATIONAL
            self.held_decisions[idx] = u
            if self.tagged and self.is_open and not stale and self.got1[idx] and self.synchronous_every_sync:
                # a second decision tagged with this cycle's SYNC: one node sends one synchronous
                # TPDO1 per SYNC, so two devices answer for this node-ID
                self._duplicate(idx)
            if not self.is_open or self.got1[idx] or stale:
                counts[C_LATE] += 1
                self.late_since += 1
                return None
            self.got1[idx] = True
            self.decisions[idx] = u
            counts[C_TPDO1] += 1
            if self.primary == K_TPDO1:
                return self._delivered(idx, t)
            return None
        if kind == K_HEARTBEAT:
            if size != 1:
                return self._bad(C_BAD_DLC)
            state = data[0]
            if state not in HEARTBEAT_STATES:
                return self._bad(C_BAD_VALUE)
            self.last_heard[idx] = t
            if state == STATE_BOOTUP:
                self.state[idx] = STATE_PRE_OPERATIONAL  # a node boots into pre-operational
                self.bootup_seq[idx] = sum(counts)
                self.bootups.append(idx)
                self.bootup_since[idx] = t
                counts[C_BOOTUP] += 1
            else:
                self.state[idx] = state
                counts[C_HEARTBEAT] += 1
            return None
        if kind == K_SYNC:
            return self._sync(t, channel, data, raw)
        if kind == K_TPDO2:
            if size != 4:
                return self._bad(C_BAD_DLC)
            reading = decode_real32(data)
            if not math.isfinite(reading):
                return self._bad(C_BAD_VALUE)
            self.last_heard[idx] = t
            self.state[idx] = STATE_OPERATIONAL
            self.held_readings[idx] = reading
            if not self.is_open or self.got2[idx] or raw < self.sync_raw:
                counts[C_LATE] += 1
                self.late_since += 1
                return None
            self.got2[idx] = True
            self.got2_any = True
            self.readings[idx] = reading
            counts[C_TPDO2] += 1
            if self.primary == K_TPDO2:
                return self._delivered(idx, t)
            return None
        if kind == K_EMCY:
            if size != 8:
                return self._bad(C_BAD_DLC)
            code, register, manufacturer = decode_emcy(data)
            self.last_heard[idx] = t
            if len(self.emcy_since) < EMCY_PER_CYCLE:
                self.emcy_since.append(EmcyEvent(self.labels[idx], self.devices[idx].taxels[0], code, register,
                                                 manufacturer.hex(), t))
            else:
                self.emcy_dropped += 1
            counts[C_EMCY] += 1
            return None
        if kind == K_SDO_RESPONSE or kind == K_SDO_REQUEST:
            if size != 8:
                return self._bad(C_BAD_DLC)
            if kind == K_SDO_RESPONSE:
                self.last_heard[idx] = t
                if self.sdo_outstanding[idx]:
                    self.sdo_outstanding[idx] = False
                    self.solicited[channel] = True  # the listener hands it to canopen's SDO client
                else:  # an answer nobody asked for: a second server with this node-ID
                    self._duplicate(idx)
                if data[0] == 0x80:
                    counts[C_SDO_ABORT] += 1
                    return None
            else:
                if data[0] != 0x80:  # an abort from the client expects no answer
                    self.sdo_outstanding[idx] = True
            counts[C_SDO] += 1
            return None
        if kind == K_NMT:
            return self._nmt(t, channel, data)
        if kind == K_LSS:
            if size != 8:
                return self._bad(C_BAD_DLC)
            counts[C_LSS] += 1
            return None
        if kind == K_MASTER_HEARTBEAT:  # the master's own (or one claiming its node-ID)
            if size != 1:
                return self._bad(C_BAD_DLC)
            if data[0] not in HEARTBEAT_STATES:
                return self._bad(C_BAD_VALUE)
            counts[C_MASTER_HEARTBEAT] += 1
            return None
        if kind == K_DRIVE:  # the gripper drive's frames: decoded for the grip stage (.drive_frames)
            counts[C_DRIVE] += 1
            if self.drive.feed(idx, t, data):
                self.solicited[channel] = True  # an awaited SDO answer of the drive: to canopen
            return None
        # K_TIME
        if size != 6:
            return self._bad(C_BAD_DLC)
        counts[C_TIME] += 1
        return None

    def _patch(self, t: int, raw: int, slot: int, data: bytes):
        """A TPDO of a patch node (``taxel_net.patches``): packed decisions or readings behind
        the cycle tag (the full counter of the sampling SYNC), counted only in that SYNC's cycle.
        Packed decisions are kept as they came and unpacked at the close (:mod:`.packed_decisions`)."""
        counts = self.counts
        place = self.packed_places[slot]
        if place is not None:
            bad, tag = self.layout.slot_decoders[slot].check(data)
            values = None
        else:
            bad, tag, values = self.layout.slot_decoders[slot].decode(data)
        if bad is not None:
            return self._bad(bad)
        if tag is not None:
            if not 1 <= tag <= self.sync_overflow:
                return self._bad(C_BAD_VALUE)  # no SYNC carries this counter
            # an answer is never stamped before its SYNC: one that is answers the SYNC that
            # carried the same counter a whole counter period earlier (a backlog), never this one
            stale = self.sync_counter is None or tag != self.sync_counter or raw < self.sync_raw
        else:
            stale = raw < self.sync_raw
        d = int(self.layout.slot_device[slot])
        self.last_heard[d] = t
        self.state[d] = STATE_OPERATIONAL
        if place is not None:
            first, stop, start, end = place
            payload = data[start:end]
            self.packed.held_bytes[first:stop] = payload
            self.packed.heard[slot] = True
        else:
            taxels = self.layout.slot_taxels[slot]
            bits = self.layout.slot_is_bits[slot]
            if bits:
                self.held_decisions[taxels] = values
            else:
                self.held_readings[taxels] = values
        got = self.slot_got
        if tag is not None and self.is_open and not stale and got[slot] and self.synchronous_every_sync:
            self._duplicate(d)  # a second frame of this TPDO tagged with this cycle's SYNC
        if not self.is_open or got[slot] or stale:
            counts[C_LATE] += 1
            self.late_since += 1
            return None
        got[slot] = True
        if place is not None:
            self.packed.cycle_bytes[first:stop] = payload
            counts[C_TPDO1] += 1
        elif bits:
            self.decisions[taxels] = values
            self.got1[taxels] = True
            counts[C_TPDO1] += 1
        else:
            self.readings[taxels] = values
            self.got2[taxels] = True
            self.got2_any = True
            counts[C_TPDO2] += 1
        return self._delivered(d, t)

    def _duplicate(self, idx: int) -> None:
        self.duplicate_since.add(idx)
        self.duplicates.add(idx)

    def _bad(self, counter: int):
        self.counts[counter] += 1
        self.bad_since += 1
        return None

