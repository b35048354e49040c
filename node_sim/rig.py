"""The rig: every node twin of a scene on its CAN bus(es), configured and booted.

``Rig(scene, ...)`` opens ONE python-can bus object per scene channel (``scene.bus.channels``;
more than 127 taxels need several, each its own CANopen network) and puts all that channel's
node twins on it: python-can's ``virtual`` interface deep-copies every frame once per
*receiving bus object*, so one bus per node would multiply the work by the node count.

Start-up (what a real node has in its non-volatile memory; a master that configures
nothing still gets working nodes): each node's OD is written from the scene — ζ, N_i, kind,
x, y (0x2001), slope/intercept (0x6126/0x6127), serial number (0x1018:4,
:func:`identity_serial`), heartbeat time (0x1017 =
``bus.heartbeat_producer_ms``), SYNC counter overflow (0x1019 = ``bus.sync_counter``), TPDO
transmission type / inhibit time / event timer (0x1800/0x1801 from ``bus``), TPDO2 enabled iff ``bus.mode == "raw"``, and the stuck-reading
detector switched off (0x2002:2 = 0) for a taxel simulated without noise
(``noise_sigma_mv == 0``: its readings are legitimately identical). These values are what
NMT reset-node / reset-communication restore. Then every node sends its boot-up.

LSS (CiA 305, :mod:`node_sim.lss`): every taxel is a device with an LSS slave whose address is
its 0x1018 (the EDS's vendor-ID, product code and revision, :func:`identity_serial`). With
``[master] assign_ids = "lss"`` the devices start non-configured (node-ID 0xFF): no node
twin, no boot-up, only LSS, until a master gives each a node-ID (Fastscan, configure node-ID,
switch state global); the device then boots as a node twin under that node-ID, with the
start-up values of its taxel for that node-ID. An NMT reset that activates another node-ID
(configured over LSS) starts the device again in the same way. One LSS request reaches every
slave of the channel; identical answers leave as one frame, as on a CAN bus.

SYNC cycle number: the nodes of a channel sample X_i for cycle ``c`` = the number of SYNCs
the rig has seen on that channel since :meth:`Rig.start` (the first SYNC is cycle 0). When
the SYNC carries a counter byte (the nodes' 0x1019 = overflow value 2..240, start-up value
``bus.sync_counter``; a SYNC whose length does not match 0x1019 is a length error), a jump of
the counter is read as lost SYNCs: the cycle number advances by the counter difference and
``lost_syncs`` counts the gap, so the nodes stay aligned with the master's cycles.

Readings: ``reading_source(cycle) -> array`` (X_i in mV per taxel, scene order). Default:
``node_sim.physics.sample_readings(scene, cycle)`` with its canonical per-cycle random
numbers (reproducible in any process; ``seed`` replaces ``scene.seed``), which also applies
the scene's stuck / open-circuit faults. Those are a pure function of (scene, cycle), so the
rig computes them ahead, off the SYNC path: half a SYNC period after a SYNC, a thread of
its own fills a cache with the next :data:`PREFETCH_CYCLES` cycles in one
``sample_readings_batch`` call, holding no lock while it computes (identical values, tested). An injected ``reading_source`` is
called only when its cycle's SYNC arrives (it may depend on state set just before).
"silent" faults (scene) and :meth:`Rig.drop_node` make a node dead (no frame out, none
processed) until the fault ends / :meth:`Rig.restore_node`.

Gripper drive (issue 22): a scene with a ``[gripper]`` table gets its CiA 402 drive
(:class:`node_sim.gripper.host.DriveHost`, ``docs/gripper-drive.md``) on that scene channel, if
served: a bus object of its own on the channel (the interface, bit rate and keywords of the
channel's), configured with ``taxel_net.gripper.startup_values`` (the ``[gripper]`` parameters,
0x1017 / 0x1019 / 0x1006 / 0x1016 from ``bus`` and ``master``), booted after the taxel nodes.
:attr:`Rig.gripper` is that host (None without one); the world acts on ``rig.gripper.drive``
inside ``with rig.gripper.lock:``.

Grasp world (issue 22): a scene with ``[gripper]`` and ``[grasp]`` whose drive's channel this rig
serves (:attr:`Rig.runs_world`) runs :class:`node_sim.world_runner.WorldRunner` beside the drive
(its own clock at the SYNC period); unless a ``reading_source`` is injected the taxels read the
world (``docs/grasp-world.md``), not ``[object]``. :attr:`Rig.world_truth` is its latest step's
record, ``on_truth`` / :meth:`Rig.add_truth_callback` get every step's.

SYNC hot path: the frames of one SYNC leave as one burst after every node has sampled
(``NodeLink.hold``/``release``; inhibit times start when the burst is sent), on a ``virtual``
bus without python-can's per-receiver deep copy (:func:`node_sim.channel.virtual_burst_sender`).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
import zlib
from typing import Callable, Mapping, Sequence

import can
import numpy as np

from taxel_net import gcfreeze, patches
from taxel_net.canmsg import tune_udp_multicast
from taxel_net.errors import ParameterError
from taxel_net.receiver import notifiers_for
from taxel_net.scene import TAXEL_KINDS, Scene

from . import lss as lssx
from . import od as odx
from .channel import Channel
from .gripper.host import GRIPPER_EDS_PATH, DriveHost
from .node import TaxelNode
from .od import COB_INVALID
from .patch import PATCH_EDS_PATH, PatchNode, patch_startup_values
from .world_runner import WorldRunner, has_world

logger = logging.getLogger(__name__)

ReadingSource = Callable[[int], np.ndarray]

PREFETCH_CYCLES = 4  # physics readings computed ahead per batch (4,096 taxels: ~2 ms, done before the next SYNC)


def identity_serial(scene: Scene, t) -> int:
    """0x1018:4 of taxel ``t``: ``crc32(scene name) & 0xFFFF`` in bits 16-31, its channel in
    bits 8-15, its node-ID in bits 0-7 — distinct for every node of a scene (node-IDs are
    unique per channel) and the same in every run and process of that scene."""
    return (zlib.crc32(scene.name.encode("utf-8")) & 0xFFFF) << 16 | (t.channel & 0xFF) << 8 | t.node_id


class Rig:
    """All node twins of ``scene`` (see module docstring).

    ``interface``: any python-can interface name ("virtual", "udp_multicast", "socketcan", …).
    ``channel``: None = the scene's channel names; a string (one scene channel) or a sequence
    (one per scene channel). ``bitrate`` is passed to ``can.Bus`` when given.
    ``bus_kwargs``: extra keyword arguments for every ``can.Bus`` (e.g. ``port`` of udp_multicast).
    ``serve_channels``: scene channel indices this rig runs (default all): a scene sharded over
    several rigs (``node-sim --serve``) opens only these buses and creates only their nodes.
    """

    def __init__(self, scene: Scene, interface: str = "virtual", channel: str | Sequence[str] | None = None,
                 bitrate: int | None = None, reading_source: ReadingSource | None = None,
                 seed: int | None = None, eds_path=odx.EDS_PATH, bus_kwargs: Mapping | None = None,
                 patch_eds_path=PATCH_EDS_PATH, serve_channels: Sequence[int] | None = None,
                 gripper_eds_path=GRIPPER_EDS_PATH, on_truth=None):
        if not isinstance(scene, Scene):
            raise ParameterError("scene", type(scene).__name__, "must be a taxel_net.scene.Scene")
        if scene.n == 0:
            raise ParameterError("scene.taxels", (), "a rig needs at least one taxel")
        self.scene = scene if seed is None else dataclasses.replace(scene, seed=int(seed))
        self.interface = interface
        names = list(scene.bus.channels)
        if channel is None:
            self.channel_names = names
        elif isinstance(channel, str):
            if len(names) != 1:
                raise ParameterError("channel", channel,
                                     f"the scene has {len(names)} channels: give one bus channel per scene channel")
            self.channel_names = [channel]
        else:
            if len(channel) != len(names):
                raise ParameterError("channel", list(channel), f"need exactly {len(names)} (one per scene channel)")
            self.channel_names = [str(c) for c in channel]
        if serve_channels is None:
            self.served = tuple(range(len(names)))
        else:
            served = sorted(set(int(c) for c in serve_channels))
            if not served or any(not 0 <= c < len(names) for c in served):
                raise ParameterError("serve_channels", list(serve_channels),
                                     f"scene channel indices 0..{len(names) - 1}, at least one")
            self.served = tuple(served)
        self.bitrate = bitrate
        self.bus_kwargs = dict(bus_kwargs or {})
        self.eds_path = odx.check_eds(eds_path)
        # patch nodes (issue 14): one twin per device of taxel_net.patches.devices
        self.devices = patches.devices(self.scene) if scene.bus.patch_nodes else None
        self.patch_eds_path = (odx.check_eds(patch_eds_path, "patch node")
                               if self.devices is not None else None)
        self._reading_source = reading_source
        # the gripper drive of [gripper] (issue 22): its own bus object on its scene channel
        self.gripper_eds_path = gripper_eds_path
        self.gripper: DriveHost | None = None
        # the grasp world of [gripper] + [grasp] (node_sim.world_runner), where this rig serves the
        # drive's channel: the taxels read it (an injected reading_source still wins)
        self.world: WorldRunner | None = None
        self._truth_callbacks = [on_truth] if callable(on_truth) else list(on_truth or ())
        self.runs_world = has_world(self.scene) and self.scene.gripper.channel in self.served
        if self.runs_world and reading_source is None:
            self._reading_source = self._world_readings
        self._channels: list[Channel] = []             # the served channels, in index order
        self._channel_at: dict[int, Channel] = {}       # scene channel index -> its channel
        self._dropped: set[tuple[int, int]] = set()
        self._silent_faults = [f for f in getattr(self.scene, "faults", ()) if f.fault == "silent"]
        self._reading_cache: dict[int, np.ndarray] = {}   # cycle -> X (scene order)
        self._reading_lock = threading.Lock()
        self._prefetch_pending = False
        self._prefetch_thread: threading.Thread | None = None  # while started, default readings only
        self._prefetch_wake = threading.Event()
        self._prefetch_first = 0
        self._prefetch_stop = False
        self._gc_held = False  # holds taxel_net.gcfreeze while started
        self.started = False
        for i, t in enumerate(scene.taxels):
            if not 0 <= t.channel < len(names):
                raise ParameterError(f"taxels[{i}].channel", t.channel, f"must index bus.channels (0..{len(names) - 1})")
        g = scene.gripper
        if g is not None and (not 0 <= g.channel < len(names)
                              or any(t.node_id == g.node_id and t.channel == g.channel for t in scene.taxels)):
            raise ParameterError("gripper", (g.channel, g.node_id), "the drive needs a channel of bus.channels and a "
                                 "node-ID no taxel has on that channel (the scene loader checks this)")

    # ------------------------------------------------------------------ life cycle
    def __enter__(self) -> "Rig":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> "Rig":
        """Open the buses, create and configure every node, send the boot-ups."""
        if self.started:
            return self
        try:
            for index, name in enumerate(self.channel_names):
                if index not in self.served:
                    continue
                kwargs = dict(self.bus_kwargs)
                if self.bitrate is not None:
                    kwargs["bitrate"] = self.bitrate
                if self.scene.bus.fd:
                    kwargs.setdefault("fd", True)   # udp_multicast / socketcan refuse FD frames without it
                try:
                    bus = can.Bus(interface=self.interface, channel=name, **kwargs)
                except Exception as exc:  # noqa: BLE001 - any backend failure is "cannot open"
                    raise ParameterError("channel", name,
                                         f"cannot be opened with python-can interface {self.interface!r}: "
                                         f"{type(exc).__name__}: {exc}") from None
                tune_udp_multicast(bus)  # udp_multicast: its own group only, room for bursts (57 SDO clients)
                self._channels.append(Channel(self, index, name, bus))
                self._channel_at[index] = self._channels[-1]
            unconfigured = self.scene.master.assign_ids == "lss"
            identity, bit_rates = self._lss_device()
            for device in self.devices or ():   # patch nodes (the scene loader refuses LSS for them)
                if device.channel in self._channel_at:
                    self._new_patch_node(self._channel_at[device.channel], device)
            for i, t in enumerate(self.scene.taxels if self.devices is None else ()):
                if t.channel not in self._channel_at:
                    continue
                ch = self._channel_at[t.channel]
                ch.lss[i] = lssx.LssSlave(
                    identity + (identity_serial(self.scene, t),),
                    lssx.UNCONFIGURED if unconfigured else t.node_id, self.bitrate or self.scene.bus.bitrate,
                    bit_rates=bit_rates, activate=lambda node_id, ch=ch, i=i: self._renumber(ch, i, None, node_id),
                    call_later=ch.scheduler.call_later)
                if not unconfigured:
                    self._new_node(ch, i, t.node_id)
            if self._reading_source is None:
                self._readings(0)  # the first SYNC's readings (and the scene's arrays) off its path
                self._prefetch_thread = threading.Thread(target=self._prefetch_loop, name="node-sim-prefetch",
                                                         daemon=True)
                self._prefetch_thread.start()
            # one receive thread for all the channels' buses (udp_multicast, socketcan, virtual:
            # taxel_net/receiver.py), else a python-can Notifier each
            for ch in self._channels:
                ch.refresh_filters()
            handles = notifiers_for([(ch.bus, [ch]) for ch in self._channels], timeout=0.05, name="node-sim-receive")
            for ch, handle in zip(self._channels, handles):
                ch.notifier = handle
            for ch in self._channels:
                with ch.lock:
                    for node in ch.nodes.values():
                        self._apply_silence(ch.index, node, 0)
                        node.power_on()
            self._start_gripper()
        except BaseException:
            self.stop()
            raise
        self.started = True
        # the set-up (EDS imports, ODs, scene arrays) is not traversed by the cyclic collector
        # while the rig runs: a full collection of it is a pause of tens of ms on a SYNC path
        gcfreeze.hold()
        self._gc_held = True
        return self

    def stop(self) -> None:
        """Stop timers, notifiers and buses (idempotent)."""
        if self.world is not None:
            self.world.stop()
        if self.gripper is not None:
            self.gripper.stop()
            self.gripper = None
        for ch in self._channels:
            ch.scheduler.stop()
        if self._prefetch_thread is not None:
            self._prefetch_stop = True
            self._prefetch_wake.set()
            self._prefetch_thread.join(timeout=5)
            self._prefetch_thread = None
            self._prefetch_stop = False
            self._prefetch_pending = False
        for ch in self._channels:
            with ch.lock:
                for node in ch.nodes.values():
                    node.shutdown()
            if ch.notifier is not None:
                ch.notifier.stop(timeout=2)
            try:
                ch.bus.shutdown()
            except Exception:  # noqa: BLE001
                logger.exception("node-sim: bus shutdown failed")
        self._channels = []
        self._channel_at = {}
        self.started = False
        if self._gc_held:
            self._gc_held = False
            gcfreeze.release()

    # ------------------------------------------------------------------ configuration
    def _start_gripper(self) -> None:
        """The scene's gripper drive, when it has one on a served channel: a
        :class:`~node_sim.gripper.host.DriveHost` on a bus object of its own on that channel
        (the same interface, bit rate and keywords as the channel's), configured with the
        scene's start-up values, booted after the taxel nodes."""
        g = self.scene.gripper
        if g is None or g.channel not in self._channel_at:
            return
        kwargs = dict(self.bus_kwargs)
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        if self.scene.bus.fd:
            kwargs.setdefault("fd", True)
        self.gripper = DriveHost.for_scene(self.scene, self.interface, self.channel_names[g.channel], kwargs,
                                           self.gripper_eds_path)
        self.gripper.start()
        if self.runs_world:
            ch = self._channel_at[g.channel]
            self.world = WorldRunner(self.scene, self.gripper.drive, self.gripper.lock,
                                     sync_state=lambda: (ch.last_counter, ch.cycle),
                                     on_truth=self._truth_callbacks).start()

    def _world_readings(self, cycle: int) -> np.ndarray:
        """The taxels' readings from the grasp world (before it runs: noise only)."""
        world = self.world
        if world is None:
            from . import physics

            return physics.observe(self.scene, cycle, np.zeros(self.scene.n))
        return world.readings(cycle)

    @property
    def world_truth(self) -> dict | None:
        """The grasp world's latest step (``Truth.as_dict()`` with ``sync_counter`` and ``cycle``,
        ``docs/grasp-world.md``), None before its first step or without a world."""
        return None if self.world is None else self.world.latest

    def add_truth_callback(self, callback) -> None:
        """Call ``callback(record)`` with every later world step's record (in the world's thread)."""
        self._truth_callbacks.append(callback)
        if self.world is not None and callback not in self.world.callbacks:
            self.world.callbacks.append(callback)

    def _lss_device(self) -> tuple[tuple[int, int, int], frozenset[int]]:
        """What the EDS says of every device: 0x1018:1-3 (vendor-ID, product code, revision
        number) and the bit rates it supports ([DeviceInfo] BaudRate_*), bit/s."""
        od = odx.load_od(1, self.eds_path)
        identity = tuple(int(odx.variable(od, odx.IDENTITY, sub).default) for sub in (1, 2, 3))
        return identity, frozenset(od.device_information.allowed_baudrates)

    def _new_node(self, ch: Channel, index: int, node_id: int) -> TaxelNode:
        """The node twin of taxel ``index`` under ``node_id``, configured with its start-up values."""
        node = TaxelNode(node_id, ch.link, eds_path=self.eds_path, lss=ch.lss[index],
                         renumber=lambda old, new, command: self._renumber(ch, index, old, new, command),
                         fd=self.scene.bus.fd)
        node.configure(self._startup_values(self.scene.taxels[index], node_id))
        if node_id in ch.nodes:
            logger.warning("node-sim channel %s: two nodes with node-ID %d: frames to it reach one only",
                           ch.name, node_id)
        ch.nodes[node_id] = node
        ch.scene_index[node_id] = index
        ch._sync_map = None
        return node

    def _new_patch_node(self, ch: Channel, device: patches.Device) -> PatchNode:
        """The patch node twin of ``device``, configured with its start-up values."""
        node = PatchNode(device.node_id, ch.link, len(device.taxels), eds_path=self.patch_eds_path,
                         fd=self.scene.bus.fd)
        serial = identity_serial(self.scene, self.scene.taxels[device.taxels[0]])
        node.configure(patch_startup_values(self.scene, device, serial))
        if device.node_id in ch.nodes:
            logger.warning("node-sim channel %s: two nodes with node-ID %d", ch.name, device.node_id)
        taxels = device.taxels
        contiguous = list(taxels) == list(range(taxels[0], taxels[0] + len(taxels)))
        ch.nodes[device.node_id] = node
        ch.scene_index[device.node_id] = (slice(taxels[0], taxels[0] + len(taxels)) if contiguous
                                          else np.asarray(taxels, dtype=np.intp))
        ch.patch = True
        ch._sync_map = None
        return node

    def _renumber(self, ch: Channel, index: int, old: TaxelNode | None, node_id: int, command: int = 0) -> None:
        """CiA 305: taxel ``index`` starts again under ``node_id`` (LSS switch state global of a
        non-configured node, or an NMT reset with another pending / stored node-ID): its old node
        leaves the bus; unless ``node_id`` is 0xFF (non-configured: LSS only) a new node boots
        with the start-up values of that node-ID (after a reset communication the application
        area 0x2000-0xFFFF keeps its values)."""
        if old is not None:
            old.shutdown()
            if ch.nodes.get(old.node_id) is old:
                del ch.nodes[old.node_id]
                ch.scene_index.pop(old.node_id, None)
            ch._sync_map = None
        if node_id == lssx.UNCONFIGURED:
            return
        node = self._new_node(ch, index, node_id)
        if old is not None and command != 0x81:  # reset communication: the application area stays
            store = node.local.data_store
            store.update({i: dict(subs) for i, subs in old.local.data_store.items() if i not in odx.COMM_AREA})
            node.detector.invalidate()
        self._apply_silence(ch.index, node, ch.cycle if ch.cycle is not None else 0)
        ch.refresh_filters()
        node.power_on()

    def _startup_values(self, t, node_id: int | None = None) -> dict[tuple[int, int], object]:
        """Start-up values of taxel ``t`` running under ``node_id`` (default: the scene's)."""
        node_id = t.node_id if node_id is None else node_id
        bus = self.scene.bus
        values: dict[tuple[int, int], object] = {
            odx.ZETA: float(t.zeta_mv),
            odx.NOISE_ESTIMATE: float(t.noise_mv),
            odx.TAXEL_KIND: TAXEL_KINDS[t.kind],
            (odx.HEARTBEAT_PRODUCER, 0): int(bus.heartbeat_producer_ms),
            (odx.SYNC_OVERFLOW, 0): int(bus.sync_counter),
            (odx.IDENTITY, 4): identity_serial(self.scene, t),
        }
        if t.x is not None:
            values[odx.POS_X] = float(t.x)
        if t.y is not None:
            values[odx.POS_Y] = float(t.y)
        if t.slope is not None:
            values[(odx.AI_SCALING_FACTOR, 1)] = float(t.slope)
        if t.intercept is not None:
            values[(odx.AI_SCALING_OFFSET, 1)] = float(t.intercept)
        if t.noise_sigma_mv == 0:
            values[odx.STUCK_SAMPLES] = 0
        for pdo, comm in enumerate(odx.TPDO_COMM):
            values[(comm, 2)] = int(bus.transmission_type)
            values[(comm, 3)] = int(bus.inhibit_time_100us)
            values[(comm, 5)] = int(bus.event_timer_ms)
        # raw mode: the node sends its reading (TPDO2) *instead of* its decision (TPDO1)
        raw = bus.mode == "raw"
        # bit 30 set: no RTR (the twins never answer a remote frame), as in the EDS defaults
        tpdo1_cob, tpdo2_cob = odx.COB_NO_RTR | 0x180 + node_id, odx.COB_NO_RTR | 0x280 + node_id
        values[(odx.TPDO_COMM[0], 1)] = tpdo1_cob | COB_INVALID if raw else tpdo1_cob
        # the cycle tag (decision mode with a SYNC counter): TPDO1 maps 0x2003 instead of 0x2000
        values[(odx.TPDO_MAP[0], 1)] = (odx.TAGGED_DECISION if bus.cycle_tag else odx.LOCAL_DECISION) << 16 | 8
        values[(odx.SYNC_WINDOW, 0)] = int(bus.sync_window)
        values[(odx.TPDO_COMM[1], 1)] = tpdo2_cob if raw else tpdo2_cob | COB_INVALID
        return values

    # ------------------------------------------------------------------ readings and faults
    def _readings(self, cycle: int) -> np.ndarray:
        with self._reading_lock:
            cache = self._reading_cache
            x = cache.get(cycle)
            if x is not None:
                return x
            if self._reading_source is not None:
                x = np.asarray(self._reading_source(cycle), dtype=float)
            else:
                from . import physics

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
        from . import physics

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

    def _apply_silence(self, channel: int, node: TaxelNode, cycle: int) -> None:
        if not self._dropped and not self._silent_faults:
            node.silent = False
            return
        key = (channel, node.node_id)
        silent = key in self._dropped or any(
            f.channel == channel and f.node_id == node.node_id and f.active(cycle) for f in self._silent_faults)
        node.silent = silent

    def drop_node(self, node_id: int, channel: int = 0) -> None:
        """Make a node dead (silent) until :meth:`restore_node`."""
        node = self._node(node_id, channel)
        with self._channel_at[channel].lock:
            self._dropped.add((channel, node_id))
            node.silent = True

    def restore_node(self, node_id: int, channel: int = 0) -> None:
        """End a :meth:`drop_node`; the node resumes in the NMT state it had (no new boot-up)."""
        node = self._node(node_id, channel)
        ch = self._channel_at[channel]
        with ch.lock:
            self._dropped.discard((channel, node_id))
            self._apply_silence(channel, node, ch.cycle if ch.cycle is not None else 0)

    # ------------------------------------------------------------------ introspection
    def _node(self, node_id: int, channel: int) -> TaxelNode:
        if not self._channels:
            raise ParameterError("rig", "stopped", "start() the rig first")
        if channel not in self._channel_at:
            raise ParameterError("channel", channel, f"not served by this rig (serves {list(self.served)})")
        node = self._channel_at[channel].nodes.get(node_id)
        if node is None:
            raise ParameterError("node_id", node_id, f"no such node on channel {channel}")
        return node

    def node(self, node_id: int, channel: int = 0) -> TaxelNode:
        return self._node(node_id, channel)

    @property
    def nodes(self) -> dict[tuple[int, int], TaxelNode]:
        """``{(channel, node_id): TaxelNode}`` of every node (scene order)."""
        return {(ch.index, nid): n for ch in self._channels for nid, n in ch.nodes.items()}

    @property
    def lss_slaves(self) -> dict[int, lssx.LssSlave]:
        """``{taxel index (scene order): LssSlave}``: every device's LSS slave (CiA 305), with
        or without a node-ID (a non-configured one has no entry in :attr:`nodes`)."""
        return {i: s for ch in self._channels for i, s in sorted(ch.lss.items())}

    @property
    def buses(self) -> list[can.BusABC]:
        return [ch.bus for ch in self._channels]

    def cycle(self, channel: int = 0) -> int | None:
        """Cycle number of the last SYNC processed on ``channel`` (None before the first)."""
        return self._channel_at[channel].cycle

    def lost_syncs(self, channel: int = 0) -> int:
        return self._channel_at[channel].lost_syncs

    def frames_sent(self) -> int:
        return sum(ch.frames_sent for ch in self._channels)

    def wait_cycle(self, cycle: int, channel: int = 0, timeout: float = 10.0) -> bool:
        """Block until ``channel`` has processed the SYNC of ``cycle``: every node has sampled it
        and sent the TPDOs it triggers (test/demo helper). False on timeout."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            c = self._channel_at[channel].cycle
            if c is not None and c >= cycle:
                return True
            time.sleep(0.001)
        return False
