"""Cycle assemblers in other processes or hosts, one fuser (issue 14, "Beyond one host").

The per-channel work of the centre - decoding every PDO, liveness, NMT states, closing SYNC
cycles (:class:`~fusion_center.service.cycles.CycleAssembler`) - can run in separate
processes or hosts, each for a group of scene channels (``fusion-center assemble --serve
0-3``); one fuser (``fusion-center run --assemblers HOST:PORT``) merges their cycles and
evaluates them with the usual pipeline, writing the same records as
:class:`~fusion_center.service.fusion_service.FusionService`.

* **The buses** are existing transports only: every participant opens the same channels
  (python-can's ``udp_multicast`` on a LAN - any number of bus objects share a group;
  ``socketcand`` serves several clients in front of real interfaces; on one host several
  SocketCAN sockets see one bus). The fuser is the one CANopen master: it sends SYNC (with
  its counter), NMT, the SDO configuration and its heartbeat on every channel exactly as
  ``FusionService`` does. An assembler only listens: it hears the master's SYNCs like any
  node and runs a ``CycleAssembler`` over its channels (a sub-scene: the scene's taxels of
  those channels, the first of them as the channel whose SYNC opens a cycle).
* **Cycle numbers**: an assembler numbers its cycles by SYNC, as ``node_sim.rig`` does (the
  master's broadcast reset communication restarts the count; a jump of the SYNC counter is
  read as lost SYNCs). The fuser maps a part to the SYNC it sent by the part's SYNC counter
  (the latest SYNC it sent with that counter: unambiguous while a part arrives within
  ``sync_counter`` periods of its SYNC), without a counter by the assembler's number.
* **Assembler -> fuser**: :mod:`multiprocessing.connection` (``Listener``/``Client`` over
  TCP, HMAC challenge on a shared key, one pickled :class:`CyclePart` per closed cycle) -
  the standard library's message transport: framing, authentication and in-order delivery
  come with it, it works across hosts, and nothing is invented on the wire. (CANopen on an
  "uplink" bus was the alternative: a 4,096-taxel part is ~1 kB per cycle, i.e. segmented
  transfers and a second master role for no gain.) The key comes from the environment
  variable ``FUSION_CENTER_AUTHKEY``; without it only loopback addresses are allowed (the
  peer that knows the key can send any pickle).
* **Merge** (:class:`CycleMerger`): per SYNC the fuser sent, one part per channel group. The
  cycle is ``complete``-able when every group's part arrived; a group whose part has not
  arrived when a later part of that group arrived (parts come in order), when the group
  disconnected, or ``part_deadline_s`` after the SYNC, is *missing*: its taxels count as
  silent (received nothing), the record is degraded and names the group in
  ``parts_missing`` (``closed_by: "part_missing"``). Cycles are evaluated in SYNC order;
  a part for a cycle already evaluated is counted (``late_parts``), never mixed in.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import logging
import os
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Sequence

import can
import numpy as np

from taxel_net.errors import UsageError
from taxel_net.patches import devices as scene_devices
from taxel_net.scene import Scene
from .aggregates import LatencyHistogram
from .cycle_records import (
    EMCY_PER_CYCLE,
    STATE_UNKNOWN,
    ClosedCycle,
    DeviceCycle,
    EmcyEvent,
    quantise_timestamp,
)
from .fusion_service import FusionService
from .stream import EventStream

logger = logging.getLogger("fusion_center.service.assemblers")

AUTHKEY_ENV = "FUSION_CENTER_AUTHKEY"
DEFAULT_AUTHKEY = b"taxel-can loopback"  # only for loopback addresses (module docstring)
PROTOCOL = 1  # version of the hello / part messages
COB_SYNC = 0x080
# what the master needs to hear (accept filters, 11-bit): NMT, SYNC + EMCY, TIME, SDO both ways,
# heartbeats / boot-ups, LSS - every COB-ID but the PDOs (0x181..0x57F), which the assemblers take
MASTER_FILTERS = [
    {"can_id": 0x000, "can_mask": 0x7FF, "extended": False},
    {"can_id": 0x080, "can_mask": 0x780, "extended": False},
    {"can_id": 0x100, "can_mask": 0x7FF, "extended": False},
    {"can_id": 0x580, "can_mask": 0x780, "extended": False},
    {"can_id": 0x600, "can_mask": 0x780, "extended": False},
    {"can_id": 0x700, "can_mask": 0x780, "extended": False},
    {"can_id": 0x7E4, "can_mask": 0x7FE, "extended": False},
]
NMT_RESETS = (0x81, 0x82)


# ---------------------------------------------------------------------------- addresses and keys

def parse_address(text: str, flag: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` for IPv6) -> (host, port); else :class:`UsageError`."""
    host, sep, port = str(text).rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not sep or not host or not 1 <= number <= 65535:
        raise UsageError(f"{flag} {text!r}: expected HOST:PORT with a port in 1..65535 (e.g. 127.0.0.1:47000)")
    return host, number


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def authkey_for(host: str, flag: str) -> bytes:
    """The shared key: ``$FUSION_CENTER_AUTHKEY``; without it only a loopback address."""
    key = os.environ.get(AUTHKEY_ENV, "")
    if key:
        return key.encode()
    if not is_loopback(host):
        raise UsageError(f"{flag} {host!r}: beyond this host the assemblers and the fuser need a shared key: "
                         f"set {AUTHKEY_ENV} (the same value on every host), or use 127.0.0.1")
    return DEFAULT_AUTHKEY


def check_serve(channels: Sequence[int], scene: Scene, text: str | None = None) -> list[int]:
    served = sorted(set(int(c) for c in channels))
    n = len(scene.bus.channels)
    if not served or served[0] < 0 or served[-1] >= n:
        shown = text if text is not None else ",".join(map(str, channels))
        raise UsageError(f"--serve {shown!r}: scene {scene.name!r} has channels 0..{n - 1} "
                         f"{list(scene.bus.channels)}: give indices such as 0-{n - 1} or 0,{n - 1}")
    return served


def group_name(channels: Sequence[int]) -> str:
    """``0-3`` / ``0,2,5``: a channel group as ``--serve`` spells it."""
    chans = sorted(channels)
    if chans == list(range(chans[0], chans[-1] + 1)) and len(chans) > 1:
        return f"{chans[0]}-{chans[-1]}"
    return ",".join(map(str, chans))


# ---------------------------------------------------------------------------- the sub-scene

@dataclass(frozen=True)
class GroupLayout:
    """A channel group inside the full scene: its taxels and devices (full-scene indices, in
    the sub-scene's order) and the sub-scene an assembler runs."""

    channels: tuple[int, ...]
    taxels: np.ndarray     # sub taxel j -> scene taxel index
    devices: np.ndarray    # sub device d -> scene device index
    sub: Scene

    @property
    def name(self) -> str:
        return group_name(self.channels)


def group_layout(scene: Scene, channels: Sequence[int]) -> GroupLayout:
    """The scene restricted to ``channels`` (renumbered 0..k-1 in their order): same taxels,
    node-IDs and TPDO COB-IDs (a channel's TPDOs are numbered over its own nodes)."""
    served = tuple(sorted(set(int(c) for c in channels)))
    new = {c: k for k, c in enumerate(served)}
    taxels = [i for i, t in enumerate(scene.taxels) if t.channel in new]
    sub_taxels = tuple(dataclasses.replace(scene.taxels[i], channel=new[scene.taxels[i].channel]) for i in taxels)
    bus = dataclasses.replace(scene.bus, channels=tuple(scene.bus.channels[c] for c in served))
    sub = dataclasses.replace(scene, taxels=sub_taxels, bus=bus, faults=())
    full_index = {(d.channel, d.node_id): k for k, d in enumerate(scene_devices(scene))}
    devs = [full_index[(served[d.channel], d.node_id)] for d in scene_devices(sub)]
    return GroupLayout(served, np.array(taxels, dtype=np.intp), np.array(devs, dtype=np.intp), sub)


def scene_fingerprint(scene: Scene) -> dict:
    """What an assembler and the fuser must agree on (checked at the hello)."""
    return {"scene": scene.name, "n": scene.n, "channels": len(scene.bus.channels), "mode": scene.bus.mode,
            "patch_nodes": bool(scene.bus.patch_nodes), "sync_counter": int(scene.bus.sync_counter),
            "fd": bool(scene.bus.fd)}


# ---------------------------------------------------------------------------- the part

@dataclass
class CyclePart:
    """One closed cycle of one channel group, as sent to the fuser (sub-scene order)."""

    channels: tuple[int, ...]
    number: int                 # the assembler's cycle number (SYNCs since the master's reset)
    sync_counter: int | None
    closed_by: str
    closed_after_us: int        # SYNC -> closing event (the assembler's stream time)
    decisions: np.ndarray       # int8 per taxel of the group
    readings: np.ndarray | None  # float64 (None: none received - decision mode)
    received: np.ndarray
    expected: np.ndarray
    missing: np.ndarray
    states: np.ndarray
    held_decisions: np.ndarray
    held_readings: np.ndarray | None
    late_frames: int = 0
    bad_frames: int = 0
    emcy: tuple = ()            # EmcyEvent with the scene's labels and taxel indices
    emcy_dropped: int = 0
    duplicates: tuple = ()      # scene device indexes
    devices: tuple | None = None  # patch scenes: (expected, missing, states, complete) per device of the group
    sent_at: float = 0.0        # time.time() when sent (assembler -> fuser delay, same-host clocks)


class GroupAssembler:
    """A ``CycleAssembler`` over one channel group, its cycles numbered by SYNC and turned
    into :class:`CyclePart` (pure: feed events, get parts)."""

    def __init__(self, scene: Scene, channels: Sequence[int]):
        from .cycles import CycleAssembler

        self.scene = scene
        self.layout = group_layout(scene, channels)
        self.assembler = CycleAssembler(self.layout.sub)
        full_labels = {k: (d.node_id if d.channel == 0 else f"{d.channel}:{d.node_id}")
                       for k, d in enumerate(scene_devices(scene))}
        self._label = {sub_label: full_labels[int(self.layout.devices[d])]
                       for d, sub_label in enumerate(self.assembler.labels)}
        self.overflow = int(scene.bus.sync_counter)
        self.reset_at: int | None = None  # first assembler cycle after the master's reset broadcast
        self.last: tuple[int, int, int | None] | None = None  # (assembler cycle, number, counter)

    def note_reset(self) -> None:
        """The master's broadcast reset communication / node was fed: numbers restart."""
        self.reset_at = self.assembler.cycle + 1

    def feed(self, timestamp_us: int, channel: int, can_id: int, data: bytes, flags: int = 0) -> list[CyclePart]:
        closed = self.assembler.feed_all(timestamp_us, channel, can_id, data, flags)
        if channel == 0 and can_id == 0 and len(data) == 2 and data[1] == 0 and data[0] in NMT_RESETS:
            self.note_reset()
        return [self.part(c) for c in closed]

    def number(self, closed: ClosedCycle) -> int:
        c, counter = closed.cycle, closed.sync_counter
        if self.reset_at is not None and c >= self.reset_at:
            number = (counter - 1) if counter else c - self.reset_at  # the master counts from 1
            self.reset_at = None
        elif self.last is None:
            number = (counter - 1) if counter else c
        else:
            last_c, last_number, last_counter = self.last
            step = c - last_c
            if counter and last_counter and self.overflow:
                step = (counter - last_counter - 1) % self.overflow + 1  # a jump: lost SYNCs
            number = last_number + step
        self.last = (c, number, counter)
        return number

    def part(self, closed: ClosedCycle) -> CyclePart:
        lay = self.layout
        readings = closed.readings if not np.isnan(closed.readings).all() else None
        held = closed.held_readings if not np.isnan(closed.held_readings).all() else None
        emcy = tuple(EmcyEvent(self._label.get(e.node, e.node), int(lay.taxels[e.taxel]), e.code, e.register,
                               e.manufacturer, e.t_us) for e in closed.emcy)
        dev = closed.devices
        return CyclePart(
            channels=lay.channels, number=self.number(closed), sync_counter=closed.sync_counter,
            closed_by=closed.closed_by, closed_after_us=int(closed.close_us - closed.sync_us),
            decisions=closed.decisions, readings=readings, received=closed.received,
            expected=np.asarray(closed.expected), missing=np.asarray(closed.missing),
            states=np.asarray(closed.states), held_decisions=closed.held_decisions, held_readings=held,
            late_frames=closed.late_frames, bad_frames=closed.bad_frames, emcy=emcy,
            emcy_dropped=closed.emcy_dropped, duplicates=tuple(int(lay.devices[d]) for d in closed.duplicates),
            devices=None if dev is None else (dev.expected, dev.missing, dev.states, dev.complete))


# ---------------------------------------------------------------------------- the merge

@dataclass
class MergeStats:
    parts: int = 0
    complete: int = 0         # cycles with every group's part
    degraded: int = 0         # cycles with a missing part
    parts_missing: int = 0    # (cycle, group) pairs without a part
    late_parts: int = 0       # parts for a cycle already evaluated
    unmatched_parts: int = 0  # parts for no SYNC this fuser sent
    duplicate_parts: int = 0
    by_group: dict = field(default_factory=dict)  # group -> parts received
    # where a part's time goes (same-host clocks; across hosts only as good as their sync):
    to_send: LatencyHistogram = field(default_factory=LatencyHistogram)    # SYNC sent -> part sent
    transport: LatencyHistogram = field(default_factory=LatencyHistogram)  # part sent -> received

    def as_dict(self) -> dict:
        out = {k: v for k, v in vars(self).items() if not isinstance(v, LatencyHistogram)}
        out["by_group"] = dict(self.by_group)
        for name in ("to_send", "transport"):
            h = getattr(self, name)
            out[f"{name}_ms"] = {f"p{q}": None if h.percentile(q) is None else round(h.percentile(q), 3)
                                 for q in (50, 99)}
        return out


class CycleMerger:
    """Merges the groups' parts per SYNC into one :class:`ClosedCycle` over every taxel (module
    docstring, *Merge*). Pure: the caller passes the time; thread-safe (one lock)."""

    def __init__(self, scene: Scene, *, part_deadline_s: float):
        self.scene = scene
        self.n = scene.n
        self.n_devices = len(scene_devices(scene))
        self.patch = bool(scene.bus.patch_nodes)
        self.overflow = int(scene.bus.sync_counter)
        self.deadline_s = float(part_deadline_s)
        self.lock = threading.Lock()
        self.groups: dict[str, GroupLayout] = {}   # connected groups
        self.gone: set[str] = set()                # disconnected groups (their parts are missing)
        self.last_k: dict[str, int] = {}           # latest cycle a group sent a part for
        self.syncs: dict[int, tuple] = {}  # k -> (counter, sync_us, monotonic sent, time.time() sent)
        self.last_sync: tuple[int, int | None] | None = None
        self.parts: dict[int, dict[str, CyclePart]] = {}
        self.next_k: int | None = None
        self.sent = 0
        self.held_decisions = np.zeros(self.n, dtype=np.int8)
        self.held_readings = np.full(self.n, np.nan)
        self.stats = MergeStats()
        self.info: dict[int, dict] = {}  # k -> record fields of the merge (parts_missing, ...)

    # -- groups
    def add_group(self, layout: GroupLayout) -> str | None:
        """Register a group; a reason string when refused (overlap with a connected group)."""
        with self.lock:
            taken = {c for name, g in self.groups.items() for c in g.channels}
            overlap = sorted(taken & set(layout.channels))
            if overlap:
                return f"scene channel(s) {overlap} are already served by another assembler"
            self.groups[layout.name] = layout
            self.gone.discard(layout.name)
            self.stats.by_group.setdefault(layout.name, 0)
            return None

    def remove_group(self, name: str) -> None:
        with self.lock:
            if self.groups.pop(name, None) is not None:
                self.gone.add(name)

    def covered(self) -> set[int]:
        with self.lock:
            return {c for g in self.groups.values() for c in g.channels}

    # -- SYNCs and parts
    def opened(self, counter: int | None, sync_us: int, now: float, wall: float | None = None) -> int:
        """The fuser sent a SYNC (called before it goes on the bus): its cycle number."""
        with self.lock:
            k = self.sent
            self.sent += 1
            self.syncs[k] = (counter, sync_us, now, wall)
            self.last_sync = (k, counter)
            if self.next_k is None:
                self.next_k = k
            return k

    def cycle_of(self, part: CyclePart) -> int | None:
        """The SYNC (cycle number) a part answers (lock held)."""
        if self.last_sync is None:
            return None
        last_k, last_counter = self.last_sync
        if self.overflow and part.sync_counter is not None and last_counter is not None:
            return last_k - (last_counter - part.sync_counter) % self.overflow
        return part.number

    def add_part(self, name: str, part: CyclePart, received_at: float | None = None) -> None:
        with self.lock:
            stats = self.stats
            stats.parts += 1
            stats.by_group[name] = stats.by_group.get(name, 0) + 1
            k = self.cycle_of(part)
            if received_at is not None and part.sent_at:
                stats.transport.add((received_at - part.sent_at) * 1e3)
                wall = self.syncs[k][3] if k in self.syncs else None
                if wall is not None:
                    stats.to_send.add((part.sent_at - wall) * 1e3)
            if k is None or k not in self.syncs:
                if k is not None and self.next_k is not None and k < self.next_k:
                    stats.late_parts += 1
                else:
                    stats.unmatched_parts += 1
                return
            if self.next_k is not None and k < self.next_k:
                stats.late_parts += 1
                return
            got = self.parts.setdefault(k, {})
            if name in got:
                stats.duplicate_parts += 1
                return
            got[name] = part
            self.last_k[name] = max(k, self.last_k.get(name, -1))

    def emit(self, now: float, *, final: bool = False) -> list[ClosedCycle]:
        """The cycles now decided, in SYNC order (``final``: every cycle sent, missing parts missing)."""
        out = []
        with self.lock:
            while self.next_k is not None and self.next_k in self.syncs:
                k = self.next_k
                counter, sync_us, sent, _ = self.syncs[k]
                got = self.parts.get(k, {})
                names = sorted(set(self.groups) | self.gone)
                missing = []
                wait = False
                for name in names:
                    if name in got:
                        continue
                    if final or name in self.gone or self.last_k.get(name, -1) > k or now - sent > self.deadline_s:
                        missing.append(name)
                    else:
                        wait = True
                        break
                if wait or not names:
                    break
                out.append(self._merge(k, counter, sync_us, got, missing))
                self.parts.pop(k, None)
                del self.syncs[k]
                self.next_k = k + 1
        return out

    def pending(self) -> int:
        with self.lock:
            return len(self.syncs)

    def _merge(self, k: int, counter, sync_us: int, got: dict[str, CyclePart], missing: list[str]) -> ClosedCycle:
        n = self.n
        decisions = np.zeros(n, dtype=np.int8)
        readings = np.full(n, np.nan)
        received = np.zeros(n, dtype=bool)
        expected = np.ones(n, dtype=bool)    # a missing group's taxels: silent (expected, not received)
        missing_t = np.zeros(n, dtype=bool)
        states = np.full(n, STATE_UNKNOWN, dtype=np.int16)
        device = None
        if self.patch:
            nd = self.n_devices
            d_exp, d_miss = np.ones(nd, dtype=bool), np.zeros(nd, dtype=bool)
            d_states, d_complete = np.full(nd, STATE_UNKNOWN, dtype=np.int16), np.zeros(nd, dtype=bool)
        late = bad = dropped = 0
        emcy: list[EmcyEvent] = []
        duplicates: set[int] = set()
        close_after = 0
        by = []
        for name, part in got.items():
            layout = self.groups.get(name)
            if layout is None:  # disconnected since: its layout is still valid (by channels)
                layout = group_layout(self.scene, part.channels)
            idx = layout.taxels
            decisions[idx] = part.decisions
            if part.readings is not None:
                readings[idx] = part.readings
            received[idx] = part.received
            expected[idx] = part.expected
            missing_t[idx] = part.missing
            states[idx] = part.states
            self.held_decisions[idx] = part.held_decisions
            if part.held_readings is not None:
                self.held_readings[idx] = part.held_readings
            if self.patch and part.devices is not None:
                dv = layout.devices
                d_exp[dv], d_miss[dv], d_states[dv], d_complete[dv] = part.devices
            late += part.late_frames
            bad += part.bad_frames
            dropped += part.emcy_dropped
            emcy.extend(part.emcy)
            duplicates.update(part.duplicates)
            close_after = max(close_after, part.closed_after_us)
            by.append(part.closed_by)
        if len(emcy) > EMCY_PER_CYCLE:
            dropped += len(emcy) - EMCY_PER_CYCLE
            emcy = sorted(emcy, key=lambda e: e.t_us)[:EMCY_PER_CYCLE]
        if self.patch:
            device = DeviceCycle(expected=d_exp, missing=d_miss, states=d_states, complete=d_complete)
        if missing:
            closed_by = "part_missing"
            self.stats.degraded += 1
            self.stats.parts_missing += len(missing)
        else:
            self.stats.complete += 1
            closed_by = next((b for b in by if b != "complete"), "complete")
        self.info[k] = {"parts_missing": missing}
        if len(self.info) > 4096:
            self.info.pop(next(iter(self.info)))
        return ClosedCycle(
            cycle=k, sync_us=sync_us, close_us=sync_us + close_after, sync_counter=counter, closed_by=closed_by,
            decisions=decisions, readings=readings, received=received, expected=expected, missing=missing_t,
            held_decisions=self.held_decisions.copy(), held_readings=self.held_readings.copy(),
            late_frames=late, bad_frames=bad, emcy=tuple(emcy), states=states,
            duplicates=tuple(sorted(duplicates)), emcy_dropped=dropped, devices=device)


# ---------------------------------------------------------------------------- the fuser

class _FuserStream(EventStream):
    """The fuser's event stream: notes every SYNC the master sends (before it goes out)."""

    on_sync = None  # callable(payload: bytes) set by the service

    def transmit_all(self, frames, remote: bool = False) -> None:
        frames = list(frames)
        if self.on_sync is not None and not remote:
            for channel, can_id, data in frames:
                if channel == 0 and can_id == COB_SYNC:
                    self.on_sync(bytes(data))
        super().transmit_all(frames, remote)


class AssembledFusionService(FusionService):
    """The fuser: the CANopen master of :class:`FusionService` on every channel, its cycles
    assembled by ``fusion-center assemble`` processes (module docstring).

    ``listen``: (host, port) of the ``multiprocessing.connection`` listener the assemblers
    connect to; :meth:`boot` waits up to ``assembler_wait_s`` for assemblers covering every
    scene channel. The service's own ``CycleAssembler`` still runs (boot-ups, SDO answers, NMT
    states for the master), its closed cycles are not evaluated.

    ``pdo_filter`` (off by default): the fuser's buses accept only the master's traffic
    (:data:`MASTER_FILTERS`; kernel filters on SocketCAN). Only for scenes without a synchronous
    window: with one, the own assembler would hold SYNC k+1 until SYNC k+2 (no node frame after
    the window closes k), and with it an SDO request of a mid-run reconfiguration - whose answer
    would then arrive unsolicited (not handed to the SDO client). Measured on udp_multicast it
    saved nothing (python-can filters after parsing every datagram)."""

    def __init__(self, scene: Scene, *, listen: tuple[str, int], authkey: bytes | None = None,
                 part_deadline_s: float | None = None, assembler_wait_s: float = 30.0,
                 pdo_filter: bool = False, **kwargs):
        super().__init__(scene, **kwargs)
        self.pdo_filter = bool(pdo_filter)
        self.listen_address = listen
        self.authkey = authkey if authkey is not None else authkey_for(listen[0], "--assemblers")
        period = scene.bus.sync_period_ms / 1000.0
        # an assembler without a window closes a cycle with a silent node at the next SYNC
        self.part_deadline_s = part_deadline_s if part_deadline_s is not None else 2.5 * period + 0.1
        self.assembler_wait_s = assembler_wait_s
        self.merger = CycleMerger(scene, part_deadline_s=self.part_deadline_s)
        self.own_closed = 0
        echoes = self.stream.echoes
        self.stream = _FuserStream(self.assembler, on_closed=self._own_cycle, after_closed=self._process_pending)
        self.stream.echoes = echoes
        self.stream.on_sync = self._on_sync
        self._listener = None
        self._conns: list = []
        self._threads: list[threading.Thread] = []
        self._stop_merge = threading.Event()
        self._merge_lock = threading.Lock()  # emission order into _pending
        self.refused: list[str] = []

    # -- life cycle
    def open(self) -> "AssembledFusionService":
        from multiprocessing.connection import Listener

        super().open()
        if self.pdo_filter:  # the PDOs are the assemblers' (kernel filters on SocketCAN, else python-can's)
            for bus in self.buses:
                bus.set_filters(MASTER_FILTERS)
        try:
            self._listener = Listener(self.listen_address, authkey=self.authkey)
        except OSError as exc:
            self.close()
            host, port = self.listen_address
            raise UsageError(f"--assemblers {host}:{port}: cannot listen there ({exc.strerror or exc})") from None
        for target, name in ((self._accept_loop, "assembler-accept"), (self._tick_loop, "merge-deadline")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def close(self) -> None:
        self._stop_merge.set()
        listener, self._listener = self._listener, None
        if listener is not None:
            try:
                listener.close()
            except OSError:
                pass
        for conn in list(self._conns):
            try:
                conn.send({"kind": "bye"})
            except (OSError, ValueError, EOFError):
                pass
            try:
                conn.close()
            except OSError:
                pass
        super().close()

    def boot(self, timeout_s: float = 3.0, configure: bool = True) -> list[int]:
        self.wait_for_assemblers(self.assembler_wait_s)
        return super().boot(timeout_s, configure)

    def wait_for_assemblers(self, timeout_s: float) -> None:
        want = set(range(len(self.scene.bus.channels)))
        deadline = time.monotonic() + timeout_s
        while self.merger.covered() != want:
            if time.monotonic() >= deadline:
                lacking = sorted(want - self.merger.covered())
                host, port = self.listen_address
                why = f" (refused: {'; '.join(self.refused)})" if self.refused else ""
                raise UsageError(f"--assemblers {host}:{port}: no assembler for scene channel(s) {lacking} after "
                                 f"{timeout_s:g} s: start `fusion-center assemble --scene ... --serve "
                                 f"{group_name(lacking)} --fuser {host}:{port}`{why}")
            time.sleep(0.02)

    def run(self, cycles: int, *, before_sync=None, timeout_s: float | None = None):
        if cycles < 1:
            raise UsageError(f"--cycles {cycles}: must be >= 1")
        period = self.scene.bus.sync_period_ms / 1000.0
        self.master.start_sync(cycles, before_sync)
        self.master.wait_sync_done(timeout_s if timeout_s is not None else cycles * period * 3 + 10.0)
        self.master.stop()
        deadline = time.monotonic() + self.part_deadline_s + 1.0
        while self.merger.pending() and time.monotonic() < deadline:
            time.sleep(0.005)
        self._emit(final=True)
        self.drain(timeout=5.0)
        return self.summary()

    # -- merge
    def _own_cycle(self, closed: ClosedCycle) -> None:
        self.own_closed += 1  # the master's own view of the cycle: not evaluated (the parts are)

    def _on_sync(self, payload: bytes) -> None:
        t0 = self.assembler.t0_us
        wall = time.time()
        sync_us = quantise_timestamp(wall) - (t0 if t0 is not None else 0)
        self.merger.opened(payload[0] if payload else None, max(0, sync_us), time.monotonic(), wall)

    def _emit(self, final: bool = False) -> None:
        with self._merge_lock:
            for closed in self.merger.emit(time.monotonic(), final=final):
                self._pending.append(closed)
        self._process_pending()

    def _tick_loop(self) -> None:
        tick = max(0.002, min(0.02, self.part_deadline_s / 4))
        while not self._stop_merge.wait(tick):
            try:
                self._emit()
            except Exception:  # noqa: BLE001 - the deadline thread never dies
                logger.exception("merge tick failed")

    def evaluate(self, closed: ClosedCycle) -> dict:
        record = self.pipeline.evaluate(closed)
        info = self.merger.info.pop(closed.cycle, None)
        record["parts_missing"] = info["parts_missing"] if info else []
        return record

    # -- connections
    def _accept_loop(self) -> None:
        while not self._stop_merge.is_set():
            listener = self._listener
            if listener is None:
                return
            try:
                conn = listener.accept()
            except Exception as exc:  # noqa: BLE001 - wrong key, closed listener, a port scan
                if self._stop_merge.is_set():
                    return
                logger.warning("assembler connection refused: %s: %s", type(exc).__name__, exc)
                continue
            thread = threading.Thread(target=self._serve, args=(conn,), name="assembler-conn", daemon=True)
            thread.start()

    def _serve(self, conn) -> None:
        name = None
        try:
            hello = conn.recv()
            why = self._check_hello(hello)
            if why is None:
                layout = group_layout(self.scene, hello["channels"])
                why = self.merger.add_group(layout)
            if why is not None:
                self.refused.append(why)
                logger.warning("assembler refused: %s", why)
                conn.send({"kind": "refused", "why": why})
                return
            name = layout.name
            self._conns.append(conn)
            conn.send({"kind": "welcome", "group": name})
            while not self._stop_merge.is_set():
                part = conn.recv()
                if isinstance(part, CyclePart):
                    self.merger.add_part(name, part, time.time())
                    self._emit()
        except (EOFError, OSError):
            pass
        except Exception:  # noqa: BLE001 - one bad assembler never stops the fuser
            logger.exception("assembler connection failed")
        finally:
            if name is not None:
                self.merger.remove_group(name)
                if conn in self._conns:
                    self._conns.remove(conn)
                if not self._stop_merge.is_set():
                    logger.warning("assembler of channel(s) %s disconnected: its parts are missing", name)
                    self._emit()
            try:
                conn.close()
            except OSError:
                pass

    def _check_hello(self, hello) -> str | None:
        if not isinstance(hello, dict) or hello.get("kind") != "hello" or hello.get("protocol") != PROTOCOL:
            return f"not an assembler hello of protocol {PROTOCOL}: {str(hello)[:80]}"
        mine = scene_fingerprint(self.scene)
        theirs = hello.get("scene")
        if theirs != mine:
            return f"scene differs: assembler {theirs}, fuser {mine}"
        channels = hello.get("channels")
        n = len(self.scene.bus.channels)
        if not channels or not all(isinstance(c, int) and 0 <= c < n for c in channels):
            return f"channels {channels!r}: the scene has channels 0..{n - 1}"
        return None


# ---------------------------------------------------------------------------- the assembler process

class AssemblerProcess:
    """``fusion-center assemble``: a :class:`GroupAssembler` on its channels' buses, each
    closed cycle sent to the fuser as a :class:`CyclePart`."""

    def __init__(self, scene: Scene, channels: Sequence[int], *, fuser: tuple[str, int], interface: str,
                 channel_names: Sequence[str] | None = None, bitrate: int | None = None,
                 bus_kwargs: dict | None = None, authkey: bytes | None = None):
        self.scene = scene
        self.group = GroupAssembler(scene, channels)
        self.layout = self.group.layout
        names = list(channel_names) if channel_names is not None else list(scene.bus.channels)
        if len(names) != len(scene.bus.channels):
            raise UsageError(f"--channel: the scene has {len(scene.bus.channels)} channel(s) "
                             f"{list(scene.bus.channels)}, got {len(names)}")
        self.channel_names = [names[c] for c in self.layout.channels]
        self.interface = interface
        self.bitrate = bitrate
        self.bus_kwargs = dict(bus_kwargs or {})
        self.fuser = fuser
        self.authkey = authkey if authkey is not None else authkey_for(fuser[0], "--fuser")
        self.buses = []
        self.notifiers = []
        self.conn = None
        self.lock = threading.Lock()       # the event stream: one order over the group's channels
        self._send_lock = threading.Lock()
        self._outbox: deque[CyclePart] = deque()
        self.parts_sent = 0
        self.parts_unsent = 0
        self.events = 0
        self.closed = threading.Event()    # the fuser said bye or went away
        self.bye = False

    def open(self) -> "AssemblerProcess":
        import can

        from taxel_net.canmsg import tune_udp_multicast

        if self.interface not in can.interfaces.VALID_INTERFACES:
            raise UsageError(f"--interface {self.interface!r}: not a python-can interface")
        try:
            for name in self.channel_names:
                kwargs = dict(self.bus_kwargs)
                if self.bitrate is not None:
                    kwargs["bitrate"] = self.bitrate
                try:
                    bus = can.Bus(interface=self.interface, channel=name, **kwargs)
                except Exception as exc:  # noqa: BLE001
                    raise UsageError(f"--channel {name!r} cannot be opened with interface {self.interface!r}: "
                                     f"{type(exc).__name__}: {exc}") from None
                tune_udp_multicast(bus)
                self.buses.append(bus)
            for index, bus in enumerate(self.buses):
                self.notifiers.append(can.Notifier(bus, [_PartListener(self, index)], timeout=0.05))
        except BaseException:
            self.close()
            raise
        return self

    def connect(self, timeout_s: float = 30.0) -> None:
        """Connect to the fuser (retrying while it is not listening yet), say hello."""
        from multiprocessing.connection import Client

        host, port = self.fuser
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                conn = Client((host, port), authkey=self.authkey)
                break
            except (ConnectionRefusedError, socket.timeout, OSError) as exc:
                if isinstance(exc, ConnectionRefusedError) or getattr(exc, "errno", None) in (111, 113, 110):
                    if time.monotonic() < deadline:
                        time.sleep(0.1)
                        continue
                raise UsageError(f"--fuser {host}:{port}: cannot connect ({exc.strerror or exc}) within "
                                 f"{timeout_s:g} s: is `fusion-center run --assemblers {host}:{port}` running?") from None
            except Exception as exc:  # noqa: BLE001 - multiprocessing.AuthenticationError
                raise UsageError(f"--fuser {host}:{port}: {type(exc).__name__}: {exc} (the same "
                                 f"{AUTHKEY_ENV} on both sides?)") from None
        conn.send({"kind": "hello", "protocol": PROTOCOL, "scene": scene_fingerprint(self.scene),
                   "channels": list(self.layout.channels), "host": socket.gethostname(), "pid": os.getpid()})
        answer = conn.recv()
        if not isinstance(answer, dict) or answer.get("kind") != "welcome":
            conn.close()
            why = answer.get("why") if isinstance(answer, dict) else answer
            raise UsageError(f"--fuser {host}:{port}: refused: {why}")
        self.conn = conn
        threading.Thread(target=self._watch, name="fuser-watch", daemon=True).start()

    def _watch(self) -> None:
        try:
            while True:
                message = self.conn.recv()
                if isinstance(message, dict) and message.get("kind") == "bye":
                    self.bye = True
                    break
        except (EOFError, OSError):
            pass
        self.closed.set()

    def close(self) -> None:
        for notifier in self.notifiers:
            try:
                notifier.stop(timeout=2)
            except Exception:  # noqa: BLE001
                pass
        self.notifiers = []
        for bus in self.buses:
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001
                pass
        self.buses = []
        if self.conn is not None:
            try:
                self.conn.close()
            except OSError:
                pass
            self.conn = None

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()

    def receive(self, msg, channel: int) -> None:
        from .stream import message_flags

        with self.lock:
            self.events += 1
            parts = self.group.feed(quantise_timestamp(msg.timestamp), channel, msg.arbitration_id,
                                    bytes(msg.data), message_flags(msg))
            self._outbox.extend(parts)
        if parts:
            self._send()

    def _send(self) -> None:
        with self._send_lock:  # parts leave in the order they closed
            while self._outbox:
                part = self._outbox.popleft()
                conn = self.conn
                if conn is None or self.closed.is_set():
                    self.parts_unsent += 1
                    continue
                part.sent_at = time.time()
                try:
                    conn.send(part)
                    self.parts_sent += 1
                except (OSError, ValueError):
                    self.parts_unsent += 1
                    self.closed.set()


class _PartListener(can.Listener):
    """python-can listener of one channel of an assembler process (never raises)."""

    def __init__(self, process: AssemblerProcess, channel: int):
        self.process = process
        self.channel = channel

    def on_message_received(self, msg) -> None:
        try:
            self.process.receive(msg, self.channel)
        except Exception:  # noqa: BLE001 - never let the Notifier thread die
            logger.exception("assembler receive path failed")

    def on_error(self, exc) -> None:
        logger.warning("bus error on channel %d: %s", self.channel, exc)

    def stop(self) -> None:
        pass
