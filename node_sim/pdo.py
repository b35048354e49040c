"""TPDO engine of the taxel node twin (CiA 301): TPDO1/TPDO2, synchronous and event-driven.

canopen 2.4.1's ``LocalNode`` has no TPDO behaviour (no transmission on SYNC, no inhibit time
or event timer, PDO data kept apart from the OD: canopen issues #145, #520, #558), so this
module is the node's PDO engine. Configuration per 0x1800/0x1801 (communication) and
0x1A00/0x1A01 (mapping), read from the OD when it changes, never per SYNC:

* transmission only in OPERATIONAL, only while valid (0x180x:1 bit 31 clear) and mapped;
* synchronous (transmission type 1..240): every n-th SYNC, honouring the SYNC start value
  0x180x:6 when the SYNC carries a counter; type 0: on SYNC when the data changed;
* event-driven (254/255): on change of the mapped data, spaced by the inhibit time 0x180x:3
  (100 µs units; a change inside the inhibit window is sent when it ends, with the data
  current then) and refreshed by the event timer 0x180x:5 (ms); also sent once on entering
  OPERATIONAL. The change check runs on every SYNC (the data change when the node samples);
* the payload is assembled from the OD data store at transmission time (no stale copy);
  a TPDO's transmission time, the start of its inhibit time, is when its frame really left
  (:meth:`node_sim.link.NodeLink.mark_sent`: the end of the SYNC burst).

SDO rules (CiA 301), checked for downloads and start-up values: COB-ID 29-bit refused and its
CAN-ID changed only while the PDO is not valid; transmission types 241-253 refused (reserved /
RTR only); bit 30 of the COB-ID (no RTR) is set in the EDS defaults and the rig's start-up
values and stored as written, but no remote frame is ever answered; inhibit time and SYNC start value only while not valid; mapping only while not
valid, entries only while sub 0 is 0, each entry an existing, readable, PDO-mappable object
of exactly its size, at most 8 entries and 64 bits. A write to 0x180x/0x1A0x restarts the
event machinery with the new values once they are stored.

Generalised for patch nodes (:mod:`node_sim.patch`): ``TpdoEngine(..., comm=, mapping=,
max_mapped=, max_bits=, fd=)`` serves any number of TPDO pairs (the one-taxel node: 0x1800/0x1801,
8 entries, 64 bits), mapping records of up to ``max_mapped`` entries (64 on CAN FD) and
``max_bits`` bits (512 on CAN FD); with ``fd`` every TPDO leaves as a CAN FD frame with bit-rate
switch (the patch node pads its data with 0 to the next valid FD length, 12..64). A subclass may replace
:meth:`TpdoEngine._compile` / :meth:`TpdoEngine._payload` (the patch node packs from its process
image) and :meth:`TpdoEngine._check_mappable`.

Hot path (one SYNC, every node): the valid, mapped TPDOs with their configuration and run-time
state are kept as one tuple, rebuilt only after a change; the payload is read from the data
store - no canopen PDO or ODVariable call per SYNC.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING


from .link import NodeLink
from .nmt import OPERATIONAL, NmtSlave
from .od import COB_INVALID, TPDO_COMM, TPDO_MAP, NodeObjects
from .pdo_rules import TPDO_LOCKED_WHILE_VALID, check_comm_write, check_map_write, mappable_bits

if TYPE_CHECKING:
    from .node import TaxelNode

MAX_MAPPED = 8
N_TPDOS = len(TPDO_COMM)


@dataclass
class _TpdoConfig:
    valid: bool
    can_id: int
    transmission_type: int
    inhibit_s: float
    event_timer_s: float
    sync_start: int
    mapping: list[tuple[int, int, int]]  # (index, subindex, bits)
    plan: object = None                  # what _compile made of the mapping (subclasses)


@dataclass
class _TpdoRuntime:
    sync_count: int = 0
    started: bool = False            # SYNC start value reached (or not used)
    last_sent: bytes | None = None
    last_tx_time: float = -math.inf  # monotonic
    pending: object | None = None    # scheduler handle of an inhibited event transmission
    event_timer: object | None = None



class TpdoEngine:
    """The TPDOs of one node (see module docstring): owns their configuration, run-time state
    and timers. ``node`` is asked only whether it is silent."""

    def __init__(self, node: "TaxelNode", nmt: NmtSlave, objects: NodeObjects, link: NodeLink, *,
                 comm: tuple[int, ...] = TPDO_COMM, mapping: tuple[int, ...] = TPDO_MAP,
                 max_mapped: int | tuple[int, ...] = MAX_MAPPED, max_bits: int = 64, fd: bool = False):
        self._node = node
        self._nmt = nmt
        self._objects = objects
        self._local = objects.local
        self._link = link
        self.comm = tuple(comm)
        self.mapping = tuple(mapping)
        self.n_tpdos = n = len(self.comm)
        self.max_mapped = (max_mapped,) * n if isinstance(max_mapped, int) else tuple(max_mapped)
        self.max_bits = max_bits
        self.fd = fd
        self._cfg: list[_TpdoConfig | None] = [None] * n
        self._rt = [_TpdoRuntime() for _ in range(n)]
        self._active: tuple[tuple[int, _TpdoConfig, _TpdoRuntime], ...] | None = None
        self._dirty: set[int] = set()    # TPDOs written by SDO since the last reconfigure
        self.frames_sent = 0

    # ------------------------------------------------------------------ configuration
    def config(self, pdo: int) -> _TpdoConfig:
        """TPDO ``pdo`` (0-based) as the OD configures it now (cached until it changes).

        A TPDO that is not valid (0x180x:1 bit 31) is read no further than its COB-ID: nothing
        sends it and nothing of it is used until it becomes valid, which is a write to 0x180x:1
        that invalidates this entry (:meth:`written`). A patch node has 85 TPDOs, most of them not
        valid: reading every object of each through canopen's data store took ~0.1-0.2 ms a TPDO,
        ~12-34 ms for the two patches of scenes/grasp_lift_patch.toml at their NMT start - the
        centre's first SYNC, sent right after it, was handled past its synchronous window and
        answered by no patch."""
        cfg = self._cfg[pdo]
        if cfg is None:
            read = self._objects.read
            comm, mapping = self.comm[pdo], self.mapping[pdo]
            cob = read(comm, 1)
            if cob & COB_INVALID:
                cfg = self._cfg[pdo] = _TpdoConfig(valid=False, can_id=cob & 0x7FF, transmission_type=0,
                                                   inhibit_s=0.0, event_timer_s=0.0, sync_start=0, mapping=[])
                return cfg
            entries = []
            for sub in range(1, read(mapping, 0) + 1):
                e = read(mapping, sub)
                entries.append((e >> 16, (e >> 8) & 0xFF, e & 0xFF))
            cfg = _TpdoConfig(
                valid=not (cob & COB_INVALID), can_id=cob & 0x7FF,
                transmission_type=read(comm, 2),
                inhibit_s=read(comm, 3) * 100e-6,
                event_timer_s=read(comm, 5) / 1000.0,
                sync_start=read(comm, 6), mapping=entries)
            cfg.plan = self._compile(cfg)
            self._cfg[pdo] = cfg
        return cfg

    def invalidate(self, pdo: int | None = None) -> None:
        """The OD may have changed (start-up values, SDO download): re-read the configuration
        (of TPDO ``pdo`` only when given)."""
        if pdo is None:
            self._cfg = [None] * self.n_tpdos
        else:
            self._cfg[pdo] = None
        self._active = None

    def read_configuration(self) -> None:
        """Read every TPDO's configuration now (after a boot: the NMT start then finds it)."""
        for pdo in range(self.n_tpdos):
            self.config(pdo)

    def _compile(self, cfg: _TpdoConfig) -> object:
        """What the payload of ``cfg`` is made from (None: the data store, :meth:`_payload`)."""
        return None

    def _activate(self) -> tuple[tuple[int, _TpdoConfig, _TpdoRuntime], ...]:
        active = []
        for pdo in range(self.n_tpdos):
            cfg = self.config(pdo)
            if cfg.valid and cfg.mapping:
                active.append((pdo, cfg, self._rt[pdo]))
        self._active = tuple(active)
        return self._active

    # ------------------------------------------------------------------ NMT
    def reset(self) -> None:
        """Boot (power-on, NMT resets): timers stopped, configuration and state forgotten."""
        self.leave_operational()
        self.invalidate()
        self._rt = [_TpdoRuntime() for _ in range(self.n_tpdos)]
        self._dirty: set[int] = set()

    def enter_operational(self) -> None:
        self._rt = [_TpdoRuntime() for _ in range(self.n_tpdos)]
        self._active = None
        for pdo in range(self.n_tpdos):
            cfg = self.config(pdo)
            if cfg.valid and cfg.mapping and cfg.transmission_type >= 254:
                self._event(pdo, cfg, force=True)

    def leave_operational(self) -> None:
        """Cancel the inhibited transmissions and event timers."""
        for rt in self._rt:
            for handle in (rt.pending, rt.event_timer):
                if handle is not None:
                    handle.cancel()
            rt.pending = rt.event_timer = None

    # ------------------------------------------------------------------ SYNC
    def on_sync(self, counter: int | None) -> None:
        """A SYNC in OPERATIONAL (``counter``: its counter byte, None without), for a live node."""
        active = self._active
        if active is None:
            active = self._activate()
        link = self._link
        fd = self.fd
        for pdo, cfg, rt in active:
            tt = cfg.transmission_type
            if tt >= 254:
                self._event(pdo, cfg)
                continue
            if tt == 0:
                payload = self._payload(cfg)
                if payload != rt.last_sent:
                    self._transmit(pdo, cfg, payload)
                continue
            if not rt.started:
                if cfg.sync_start and counter is not None and counter != cfg.sync_start:
                    continue
                rt.started = True
                rt.sync_count = tt - 1 if cfg.sync_start and counter is not None else 0
            rt.sync_count += 1
            if rt.sync_count >= tt:
                rt.sync_count = 0
                # _transmit for a synchronous TPDO of a live node, inlined (hot path)
                payload = self._payload(cfg)
                if fd:
                    link.send(cfg.can_id, payload, True)
                else:
                    link.send(cfg.can_id, payload)
                self.frames_sent += 1
                rt.last_sent = payload
                link.mark_sent(rt)  # last_tx_time: now, or when the SYNC burst is sent

    # ------------------------------------------------------------------ transmission
    def _payload(self, cfg: _TpdoConfig) -> bytes:
        """The mapped objects' current bytes (what ``LocalNode.get_data`` returns: this node
        registers no read callback, so the data store, else the EDS value/default)."""
        local = self._local
        if local._read_callbacks:  # someone added one: canopen's path
            return b"".join(local.get_data(i, s)[: bits // 8] for i, s, bits in cfg.mapping)
        store = local.data_store
        if len(cfg.mapping) == 1:
            i, s, bits = cfg.mapping[0]
            try:
                return store[i][s][: bits // 8]
            except KeyError:
                return local.get_data(i, s)[: bits // 8]
        parts = []
        for i, s, bits in cfg.mapping:
            try:
                parts.append(store[i][s][: bits // 8])
            except KeyError:
                parts.append(local.get_data(i, s)[: bits // 8])
        return b"".join(parts)

    def _transmit(self, pdo: int, cfg: _TpdoConfig, payload: bytes) -> None:
        rt = self._rt[pdo]
        link = self._link
        if not self._node.silent:
            link.send(cfg.can_id, payload, self.fd)
            self.frames_sent += 1
        rt.last_sent = payload
        link.mark_sent(rt)  # last_tx_time: now, or when the SYNC burst is sent
        if cfg.transmission_type >= 254:
            self._arm_event_timer(pdo, cfg)

    def _event(self, pdo: int, cfg: _TpdoConfig, force: bool = False) -> None:
        rt = self._rt[pdo]
        payload = self._payload(cfg)
        if not force and payload == rt.last_sent:
            return
        if rt.pending is not None:
            return  # already waiting for the inhibit time; it sends the data current then
        now = time.monotonic()
        earliest = rt.last_tx_time + cfg.inhibit_s
        if now >= earliest:
            self._transmit(pdo, cfg, payload)
        else:
            def deferred():
                rt.pending = None
                if self._nmt.state == OPERATIONAL:
                    c = self.config(pdo)
                    if c.valid and c.transmission_type >= 254:
                        self._transmit(pdo, c, self._payload(c))

            rt.pending = self._link.scheduler.call_at(earliest, deferred)

    def _arm_event_timer(self, pdo: int, cfg: _TpdoConfig) -> None:
        rt = self._rt[pdo]
        if rt.event_timer is not None:
            rt.event_timer.cancel()
            rt.event_timer = None
        if cfg.event_timer_s > 0:
            def refresh():
                rt.event_timer = None
                if self._nmt.state == OPERATIONAL:
                    c = self.config(pdo)
                    if c.valid and c.transmission_type >= 254:
                        self._event(pdo, c, force=True)

            rt.event_timer = self._link.scheduler.call_later(cfg.event_timer_s, refresh)

    # ------------------------------------------------------------------ SDO
    def written(self, index: int, subindex: int) -> None:
        """0x180x / 0x1A0x downloaded: configuration stale now, event machinery restarted with
        the new values once they are stored (just after this call). Only the written TPDO's
        configuration is read again (the others are unchanged)."""
        pdo = self.comm.index(index) if index in self.comm else self.mapping.index(index)
        self.invalidate(pdo)
        self._dirty.add(pdo)
        self._link.scheduler.call_at(0.0, self.reconfigure)

    def reconfigure(self) -> None:
        """After an SDO write to 0x180x/0x1A0x: restart the event machinery with the new values."""
        dirty, self._dirty = self._dirty, set()
        for pdo in dirty:
            self.invalidate(pdo)
        if self._nmt.state != OPERATIONAL:
            return
        for pdo in range(self.n_tpdos):
            rt = self._rt[pdo]
            cfg = self.config(pdo)
            if rt.event_timer is not None:
                rt.event_timer.cancel()
                rt.event_timer = None
            if cfg.valid and cfg.mapping and cfg.transmission_type >= 254:
                self._arm_event_timer(pdo, cfg)
            elif rt.pending is not None:
                rt.pending.cancel()
                rt.pending = None

    def check_write(self, index: int, subindex: int, value, startup: bool) -> None:
        """SDO / start-up write to 0x180x or 0x1A0x (see module docstring)."""
        if index in self.comm:
            self._check_comm_write(self.comm.index(index), subindex, value, startup)
        elif index in self.mapping:
            self._check_map_write(self.mapping.index(index), subindex, value, startup)

    def _check_comm_write(self, pdo: int, subindex: int, value: int, startup: bool) -> None:
        check_comm_write(self._objects.read, self.comm[pdo], subindex, value, startup, TPDO_LOCKED_WHILE_VALID)

    def _check_map_write(self, pdo: int, subindex: int, value: int, startup: bool) -> None:
        check_map_write(self._objects, self.comm[pdo], self.mapping[pdo], subindex, value, startup,
                        self.max_mapped[pdo], self.max_bits, self._check_mappable)

    def _check_mappable(self, entry: int) -> int:
        return mappable_bits(self._objects, entry, receive=False)
