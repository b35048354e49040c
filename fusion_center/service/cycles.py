"""Deterministic SYNC-cycle assembler: a pure state machine over the serialised event stream.

This module keeps the cycles (SYNC, NMT, the synchronous window and bus order, the close);
what each frame says - COB-ID lookup, length and value checks, decoding, counting, late or
not - is :mod:`.cycle_frames` (the base class :class:`~.cycle_frames.CycleFrames`); what
the assembler reports (counters, :class:`~.cycle_records.ClosedCycle`) is :mod:`.cycle_records`.

Contract (what makes ``replay`` reproduce ``run`` exactly)
----------------------------------------------------------
The assembler sees ONE ordered stream of events ``(timestamp_us, channel, can_id, data,
flags)``: every frame received from the bus *and* every frame the master sends itself (SYNC,
NMT, SDO requests), serialised under one lock by the service, which writes the very same
events, in the same order, to the CAN trace (``--log``). The assembler never reads a clock:
everything it decides is a function of that stream, so feeding the trace back
(``fusion-center replay``) reproduces every closed cycle, hence every record.

* Cycle ``n`` opens at the ``n``-th valid SYNC event on channel 0 (``n`` counts from 0;
  with several channels the master sends the SYNCs of all channels back to back, and those
  of the other channels are only counted).
* At that SYNC, liveness is evaluated from the stream (CiA 301 heartbeat consumer, 0x1016
  semantics): a node is *missing* when it has never been heard or when nothing valid
  (heartbeat, boot-up, TPDO, EMCY, SDO response) was heard from it for more than
  ``heartbeat_consumer_ms`` before the SYNC timestamp. A consumer time of 0 disables the
  timeout (only never-heard nodes are missing). Hearing a node again brings it back.
* A node is *expected* in a cycle when it is live and operational (its NMT state follows the
  heartbeat byte, the master's own NMT commands seen in the stream, and "a node that sends a
  PDO is operational").
* The cycle closes (``closed_by``) at the end of the synchronous window (0x1007,
  ``[bus] sync_window_us``; ``"window"``: at the first node frame stamped later than SYNC +
  window, or when held frames are released - see *Bus order* - with ``close_us`` = SYNC +
  window), when every expected node has delivered its primary PDO
  (``"complete"``: TPDO1 in decision mode, TPDO2 in raw mode; only for synchronous
  transmission type 1 and at least one expected node), at the next valid SYNC
  (``"sync"``), or at an NMT broadcast stop / pre-operational / reset (``"nmt"``, the master
  sends one at the end of a run). A cycle still open when the stream ends is never reported.
* A PDO that cannot belong to the open cycle - a second PDO of a node that already reported,
  or any PDO while no cycle is open (after an early close, before the first SYNC) - is
  counted as ``late`` and dropped, never mixed into a finished cycle.

* With a SYNC counter (``sync_counter`` > 0) in decision mode, TPDO1 carries a *cycle tag*
  (object 0x2003: u_i in bits 0-1 as a 2-bit two's complement number, 0b01 = +1, 0b11 = -1;
  bits 2-7 the counter of the SYNC the node sampled, modulo 64). A decision is counted only
  in the cycle opened by the SYNC with that counter; any other tag is ``late``. A PDO delayed
  by a loaded host, a queue or a flood is never counted in a later cycle. The tag repeats
  every 64 SYNCs (patch nodes: every overflow value of the counter), so a PDO held up behind a
  backlog of that many periods carries the open cycle's tag: it is told apart by its time
  stamp, which precedes the SYNC it would answer (no answer is sent before its SYNC) - such a
  PDO is ``late`` too. Raw mode (TPDO2, a full REAL32) and scenes without a SYNC counter carry
  no tag and rely on the time stamps below.

* Untagged PDOs: a PDO whose own time stamp precedes the time stamp of the SYNC that opened the cycle was
  sent (virtual bus: stamped by the sender) or received (SocketCAN, udp_multicast: stamped by
  the kernel on reception) before that SYNC, so it answers an earlier one: ``late``, never
  counted in the open cycle. The master stamps its own SYNC *before* handing it to the bus,
  so every answer to it is later. The stream keeps each frame's own time stamp (the trace
  stores it, so replay decides the same); the assembler's clock ``t`` is that stamp made
  monotonic. This needs frame time stamps on the host's clock (python-can's virtual,
  socketcan and udp_multicast buses; an interface with its own hardware clock that python-can
  does not map to ``time.time()`` would need the SYNC's echo time instead).

Bus order (with a window): the stream is the order in which this process handled the frames,
not the order they had on the bus - the master's own SYNC k+1 is fed when it is sent, while
answers to SYNC k that were on the bus before it may still wait in a receive queue of a busy
host. So while cycle k is open, a master frame (SYNC, NMT, SDO request), or any frame that is
not a node's, arriving after SYNC k+1 is *held*, and node frames stamped inside k's window are
fed ahead of it: they were on the bus before SYNC k+1 (the master sends no two SYNCs closer
than the window). The first node frame stamped after the window closes k and feeds what was
held, in order; so do a second SYNC, an NMT broadcast stop / pre-operational / reset (the end
of a run) and :data:`HOLD_MAX` held frames. This is a function of the stream alone (replay
holds and releases the same frames), and the trace keeps the order the frames were handled in.

Every event fed is counted under exactly one disposition in :data:`COUNTER_NAMES`, so the
counters always sum to the number of events fed (the fuzz test checks this).

Timestamps are integers in microseconds (:func:`~.cycle_records.quantise_timestamp`): candump
``.log`` and Vector ``.asc`` keep 6 decimals of a second, so microsecond integers survive the
round trip through every trace format exactly (see ``FusionService`` for the monotonic clamp
applied before writing the trace).
"""

from __future__ import annotations

import numpy as np

from taxel_net.scene import Scene
from .cycle_frames import CycleFrames
from .cycle_layout import CycleLayout
from .cycle_records import (
    COUNTER_NAMES,
    C_BAD_DLC,
    C_BAD_VALUE,
    C_INTERNAL,
    C_NMT,
    C_SYNC,
    ClosedCycle,
    DeviceCycle,
    EmcyEvent,
    STATE_UNKNOWN,
    _MALFORMED_IDX,
)
from .decoder import (
    K_EMCY,
    K_HEARTBEAT,
    K_NMT,
    K_PATCH,
    K_SDO_RESPONSE,
    K_SYNC,
    K_TPDO1,
    K_TPDO2,
    NMT_COMMANDS,
    NMT_NEW_STATE,
    NMT_RESET_COMMUNICATION,
    NMT_RESET_NODE,
    NMT_START,
    STATE_OPERATIONAL,
)
from .drive_frames import DriveTracker
from .packed_decisions import PackedDecisions

NODE_KINDS = frozenset({K_TPDO1, K_TPDO2, K_PATCH, K_HEARTBEAT, K_EMCY, K_SDO_RESPONSE})  # frames a node sends

HOLD_MAX = 4096  # master / other frames held at most while a window is open (then released)



def counters_of(counts, held: int) -> dict[str, int]:
    """:meth:`CycleAssembler.counters` of its ``counts`` (in :data:`COUNTER_NAMES` order) and the
    number of events it holds (``held``, only while nonzero)."""
    counters = dict(zip(COUNTER_NAMES, counts))
    if held:
        counters["held"] = held
    return counters

class CycleAssembler(CycleFrames):
    """Pure state machine: ``feed`` events in stream order, get closed cycles back (what each
    frame says: :class:`~.cycle_frames.CycleFrames`; the SYNC cycles: here)."""

    def __init__(self, scene: Scene):
        self.scene = scene
        n = scene.n
        self.n = n
        bus = scene.bus
        self.layout = layout = CycleLayout(scene)  # where every taxel is (.cycle_layout)
        nd = layout.n_devices
        self.patch = bool(bus.patch_nodes)
        self.fd = bool(bus.fd)
        self.slot_got = np.zeros(len(layout.slot_tpdo), dtype=bool)
        # packed decisions unpacked at the close (.packed_decisions); None: per frame
        packed = PackedDecisions(layout, scene.n) if bus.patch_nodes else None
        self.packed = packed if packed is not None and packed.usable else None
        self.packed_places = self.packed.places if self.packed is not None else [None] * len(layout.slot_tpdo)
        self.lsb_mv = float(bus.raw_lsb_mv)
        self.primary = K_TPDO2 if bus.mode == "raw" else K_TPDO1
        self.synchronous_every_sync = bus.transmission_type == 1
        self.consumer_us = int(bus.heartbeat_consumer_ms) * 1000
        self.sync_overflow = int(bus.sync_counter)
        self.window_us = int(bus.sync_window)  # 0x1007, 0 = no window
        self.held: list[tuple] = []  # events held until the open cycle's window is over (_route)
        self.tagged = bus.cycle_tag  # TPDO1 maps 0x2003 (u_i + SYNC counter mod 64)

        self.counts = [0] * len(COUNTER_NAMES)
        self.t0_us: int | None = None
        self.last_us = 0
        # per device:
        self.last_heard = np.full(nd, -1, dtype=np.int64)  # relative µs, -1 = never
        self.bootup_seq = np.full(nd, -1, dtype=np.int64)  # events fed before its last boot-up, -1 = none
        self.reset_seq = np.full(nd, -1, dtype=np.int64)   # events fed before the last NMT reset to it
        self.state = np.full(nd, STATE_UNKNOWN, dtype=np.int16)
        # per taxel:
        self.decisions = np.zeros(n, dtype=np.int8)
        self.readings = np.full(n, np.nan)
        self.got1 = np.zeros(n, dtype=bool)
        self.got2 = np.zeros(n, dtype=bool)
        self.got2_any = False  # a TPDO2 was accepted since the last SYNC
        self.held_decisions = np.zeros(n, dtype=np.int8)
        self.held_readings = np.full(n, np.nan)
        self.expected = np.zeros(nd, dtype=bool)  # per device
        self.sync_state = self.state.copy()
        self.missing = np.ones(nd, dtype=bool)    # per device
        self.pending = 0
        self.is_open = False
        self.cycle = -1
        self.sync_us = 0
        self.sync_raw = 0  # the opening SYNC's own time stamp (the master's: taken before its send)
        self.sync_counter: int | None = None
        self.late_since = 0
        self.bad_since = 0
        self.emcy_since: list[EmcyEvent] = []
        self.emcy_dropped = 0
        self.bootups: list[int] = []  # device indexes that sent boot-up (drained by the master)
        self.bootup_since: dict[int, int] = {}  # device index -> t_us of its last boot-up since the previous close
        # duplicate node-ID evidence (two devices answering for one node-ID):
        self.sdo_outstanding = np.zeros(nd, dtype=bool)  # an SDO request is waiting for its answer
        self.duplicate_since: set[int] = set()          # evidence since the previous closed cycle
        self.duplicates: set[int] = set()               # every node-ID ever flagged (device indexes)
        self.solicited = [False] * len(scene.bus.channels)  # last SDO answer fed per channel was awaited
        self.drive = DriveTracker.for_scene(scene)  # the gripper drive's frames ([gripper]), None without

    # ------------------------------------------------------------------ queries
    @property
    def devices(self):
        return self.layout.devices

    @property
    def n_devices(self) -> int:
        return self.layout.n_devices

    @property
    def labels(self) -> list[int | str]:
        return self.layout.labels

    @property
    def events(self) -> int:
        """Events fed: every one counted under one disposition, or held (see *Bus order*)."""
        return sum(self.counts) + len(self.held)

    def counters(self) -> dict[str, int]:
        """Events per disposition; ``held`` (only while nonzero): fed, not yet handled."""
        return counters_of(self.counts, len(self.held))

    def malformed(self) -> int:
        return sum(self.counts[i] for i in _MALFORMED_IDX)

    def node_states(self) -> np.ndarray:
        return self.state.copy()

    def count_internal_error(self) -> None:
        self.counts[C_INTERNAL] += 1

    # ------------------------------------------------------------------ the machine
    def feed(self, timestamp_us: int, channel: int, can_id: int, data: bytes, flags: int = 0):
        """Consume one event; return the first :class:`ClosedCycle` it closed, or None (see
        :meth:`feed_all`: an event can close two cycles)."""
        closed = self.feed_all(timestamp_us, channel, can_id, data, flags)
        return closed[0] if closed else None

    def feed_all(self, timestamp_us: int, channel: int, can_id: int, data: bytes,
                 flags: int = 0) -> list[ClosedCycle]:
        """Consume one event; return the cycles it closed, oldest first (usually none or one)."""
        if self.t0_us is None:
            self.t0_us = timestamp_us
        raw = t = timestamp_us - self.t0_us  # raw: the frame's own time stamp
        if t < self.last_us:  # the assembler's clock is monotonic (the stream order is the truth)
            t = self.last_us
        self.last_us = t
        entry = self._entry(channel, can_id, flags)  # the one COB-ID lookup of the event
        if (entry is not None and entry[0] == K_PATCH and not self.held
                and (not self.window_us or not self.is_open or raw <= self.sync_raw + self.window_us)):
            # what _route does with a patch TPDO when nothing is held and no window ends with
            # it: fed at once (most frames at skin scale; this path saves its calls)
            closed = self._patch(t, raw, entry[1], data)
            return [] if closed is None else [closed]
        out: list[ClosedCycle] = []
        self._route(out, (t, raw, channel, can_id, data, flags), entry)
        return out

    def _route(self, out: list, event: tuple, entry: tuple[int, int] | None) -> None:
        """The synchronous window of the open cycle, in bus order (module docstring, "Bus order").

        While cycle k is open with a window, node frames (TPDO, heartbeat, EMCY, SDO answer)
        stamped inside its window are fed at once; the first one stamped after it closes the
        cycle (``window``). A master frame (SYNC k+1, NMT, SDO request) or any other frame
        arriving while k is open after SYNC k+1 has come is *held*: fed once the window is
        over, so an answer to SYNC k that was on the bus before SYNC k+1 but reached this
        process after it still counts in k. Also released by a second SYNC, an NMT broadcast
        stop / pre-operational / reset, or :data:`HOLD_MAX` held events.
        """
        t, raw, channel, can_id, data, flags = event
        if self.is_open and self.window_us:
            kind = entry[0] if entry is not None else None
            if kind in NODE_KINDS:
                if raw > self.sync_raw + self.window_us:
                    self._release(out)
                    self._route(out, event, entry)
                    return
                self._push(out, self._feed(t, raw, channel, data, flags, entry))
                if self.held and not self.is_open:  # it completed the cycle: feed what was held
                    self._release(out)
                return
            # only a SYNC that would open a cycle is SYNC k+1: a malformed one (wrong length, a
            # counter no SYNC carries) is counted where it stands and changes no cycle
            next_sync = kind == K_SYNC and channel == 0 and self._opens_cycle(data)
            if self.held:
                release = (
                    len(self.held) >= HOLD_MAX
                    or next_sync
                    or (kind == K_NMT and len(data) == 2 and data[1] == 0 and data[0] != NMT_START))
                if release:
                    self._release(out)
                    self._route(out, event, entry)
                else:
                    self.held.append((t, raw, channel, data, flags, entry))
                return
            if next_sync:
                self.held.append((t, raw, channel, data, flags, entry))  # SYNC k+1 while k's window is open
                return
        self._push(out, self._feed(t, raw, channel, data, flags, entry))

    def _release(self, out: list) -> None:
        """Close the open cycle at its window's end, then feed the held events in order."""
        if self.is_open:
            out.append(self._close("window", self.sync_us + self.window_us))
        held, self.held = self.held, []
        for t, raw, channel, data, flags, entry in held:
            self._push(out, self._feed(t, raw, channel, data, flags, entry))

    @staticmethod
    def _push(out: list, closed) -> None:
        if closed is not None:
            out.append(closed)

    # ------------------------------------------------------------------ helpers
    def _delivered(self, idx: int, t: int):
        if self.expected[idx] and self.synchronous_every_sync:
            self.pending -= 1
            if self.pending == 0:
                return self._close("complete", t)
        return None

    def _opens_cycle(self, data: bytes) -> bool:
        """Whether a SYNC with this payload is well formed (CiA 301: DLC 1 with a counter
        1..0x1019 where the scene has a counter, DLC 0 where it has none) - the one check
        :meth:`_sync` counts and :meth:`_route` holds by."""
        if self.sync_overflow:
            return len(data) == 1 and 1 <= data[0] <= self.sync_overflow
        return len(data) == 0

    def _sync(self, t: int, channel: int, data: bytes, raw: int | None = None):
        counter = None
        if not self._opens_cycle(data):
            wrong_length = len(data) != (1 if self.sync_overflow else 0)
            return self._bad(C_BAD_DLC if wrong_length else C_BAD_VALUE)
        if self.sync_overflow:
            counter = data[0]
        self.counts[C_SYNC] += 1
        if channel != 0:
            return None  # one cycle per SYNC instant: channel 0's SYNC opens it (the master
            # sends the SYNCs of all channels back to back under the stream lock)
        closed = self._close("sync", t) if self.is_open else None
        # open the next cycle: liveness from the stream (heartbeat consumer semantics): heard
        # (last_heard >= 0) and t - last_heard <= consumer time, i.e. last_heard >= max(0, t - consumer)
        live = self.last_heard >= (max(0, t - self.consumer_us) if self.consumer_us > 0 else 0)
        self.missing = ~live  # new arrays at every SYNC (never changed in place: _close hands them over)
        self.expected = live & (self.state == STATE_OPERATIONAL)
        self.sync_state = self.state.copy()  # replaced, never changed in place (handed over at the close)
        if not self.synchronous_every_sync:
            self.pending = -1
        elif self.patch:  # every TPDO of every expected device
            self.pending = int(self.layout.device_slots[self.expected].sum())
        else:
            self.pending = int(np.count_nonzero(self.expected))
        if self.pending == 0:
            self.pending = -1  # nothing to wait for: close at the next SYNC only
        self.decisions.fill(0)
        self.got1.fill(False)
        if self.patch:
            self.slot_got.fill(False)
        if self.got2_any:  # only TPDO2s (raw mode, or stray frames) touch these
            self.readings.fill(np.nan)
            self.got2.fill(False)
            self.got2_any = False
        self.cycle += 1
        self.sync_us = t
        self.sync_raw = t if raw is None else raw
        self.sync_counter = counter
        self.is_open = True
        return closed

    def _nmt(self, t: int, channel: int, data: bytes):
        if len(data) != 2:
            return self._bad(C_BAD_DLC)
        command, node_id = data[0], data[1]
        if command not in NMT_COMMANDS or node_id > 127:
            return self._bad(C_BAD_VALUE)
        self.counts[C_NMT] += 1
        new_state = NMT_NEW_STATE[command]
        is_reset = command in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION)
        if node_id == 0:
            members = self.layout.channel_members[channel] if 0 <= channel < len(self.layout.channel_members) else ()
            self.state[members] = new_state
            if is_reset:  # a boot-up fed after this point answers it (the master waits for that)
                self.reset_seq[members] = sum(self.counts) - 1
            if command != NMT_START and self.is_open:
                closed = self._close("nmt", t)  # the drive's new state after the cycle it ends
                if self.drive is not None:
                    self.drive.nmt_command(channel, command, node_id)
                return closed
        else:
            idx = self.layout.index_by_node[channel].get(node_id) if 0 <= channel < len(self.layout.index_by_node) else None
            if idx is not None:
                self.state[idx] = new_state
                if is_reset:
                    self.reset_seq[idx] = sum(self.counts) - 1
        if self.drive is not None:
            self.drive.nmt_command(channel, command, node_id)
        return None

    def _close(self, closed_by: str, t: int) -> ClosedCycle:
        if self.packed is not None:
            self.packed.unpack(self.slot_got, self.decisions, self.got1, self.held_decisions)
        primary_got = self.got2 if self.primary == K_TPDO2 else self.got1
        expected, missing, states = self.expected, self.missing, self.sync_state
        if self.patch:  # per device -> per taxel; a device is complete with all its TPDOs
            device = DeviceCycle.make(expected=expected, missing=missing, states=states,
                                 complete=np.bincount(self.layout.slot_device, weights=self.slot_got,
                                                      minlength=self.n_devices) == self.layout.device_slots)
            td = self.layout.taxel_device
            expected, missing, states = expected[td], missing[td], states[td]
        else:
            device = None
        closed = ClosedCycle.make(
            cycle=self.cycle,
            sync_us=self.sync_us,
            close_us=t,
            sync_counter=self.sync_counter,
            closed_by=closed_by,
            decisions=self.decisions.copy(),
            readings=self.readings.copy(),
            received=primary_got.copy(),
            expected=expected,  # replaced, not modified, at the next SYNC: no copy needed
            missing=missing,
            held_decisions=self.held_decisions.copy(),
            held_readings=self.held_readings.copy(),
            late_frames=self.late_since,
            bad_frames=self.bad_since,
            emcy=tuple(self.emcy_since),
            states=states,
            duplicates=tuple(sorted(self.duplicate_since)),
            emcy_dropped=self.emcy_dropped,
            devices=device,
            drive=None if self.drive is None else self.drive.snapshot(t),
            bootups=tuple(sorted(self.bootup_since.items())) if self.bootup_since else (),
        )
        self.is_open = False
        self.late_since = 0
        self.bad_since = 0
        self.emcy_since = []
        self.emcy_dropped = 0
        if self.duplicate_since:
            self.duplicate_since = set()
        if self.bootup_since:
            self.bootup_since = {}
        return closed
