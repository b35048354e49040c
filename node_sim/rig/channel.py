"""One channel of the rig: one CANopen network of node twins on one python-can bus object.

:class:`Channel` receives the bus's frames (its receive handle: :mod:`taxel_net.receiver`),
filters what its twins consume (:data:`CONSUMED_FILTERS`: python-can filters, refreshed when
the nodes' SYNC COB-ID changes) and dispatches them under the channel lock: NMT module
control, SDO requests, SYNC (cycle numbering from the SYNC counter, CiA 301 length error and
synchronous window, then every node samples its readings - patch nodes as one batch,
:class:`node_sim.patch.batch.PatchSyncBatch` - and the frames of that SYNC leave as one burst),
heartbeats of other participants, LSS requests. The :class:`~node_sim.rig.Rig` owns the channels
and what they share (readings, silence faults, LSS devices).

On a ``virtual`` bus the burst bypasses python-can's per-receiver deep copy
(:func:`virtual_burst_sender`), on a ``udp_multicast`` bus python-can's ``Message`` and
``msgpack`` map per frame (:func:`taxel_net.udp_wire.udp_multicast_burst_sender`: the same
datagrams).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Callable, Sequence

import can

from taxel_net.canmsg import TxMessage
from taxel_net.udp_filter import set_filters
from taxel_net.udp_wire import udp_multicast_burst_sender

from .. import lss as lssx
from .. import od as odx
from ..link import NodeLink, Scheduler
from ..node import TaxelNode
from ..patch.batch import PatchSyncBatch

if TYPE_CHECKING:
    from .api import Rig

logger = logging.getLogger("node_sim.rig")


def virtual_burst_sender(bus: can.BusABC) -> Callable[[list[tuple]], None] | None:
    """For python-can's ``virtual`` interface: send a burst of 11-bit data frames (``(can_id,
    data)``, or ``(can_id, data, True)`` for CAN FD with bit-rate switch) doing what
    ``VirtualBus.send`` does for each (python-can 4.x: per frame one timestamp, ``time.time()``
    unless ``preserve_timestamps``; for each receiving queue of the channel - its own only with
    ``receive_own_messages`` - a new ``Message`` with ``channel`` = the channel id and
    ``is_rx`` = not its own queue, put in order), without the per-receiver ``copy.deepcopy``
    (~5 µs a frame: most of a node twin's cost per SYNC). None for any other bus, or a
    ``VirtualBus`` without the attributes this relies on: those use ``bus.send`` per frame.
    """
    try:
        from can.interfaces.virtual import VirtualBus
    except ImportError:  # pragma: no cover - python-can always ships it
        return None
    needed = ("channel", "queue", "channel_id", "receive_own_messages", "preserve_timestamps", "_check_if_open")
    if type(bus) is not VirtualBus or not all(hasattr(bus, name) for name in needed) \
            or not isinstance(bus.channel, list):
        return None
    message = can.Message
    now = time.time

    def send_many(frames: list[tuple[int, bytes]]) -> None:
        bus._check_if_open()
        own = bus.queue
        channel_id = bus.channel_id
        receivers = [(q.put, q is not own) for q in list(bus.channel)
                     if q is not own or bus.receive_own_messages]
        preserve = bus.preserve_timestamps
        for frame in frames:
            timestamp = 0.0 if preserve else now()  # 0.0: a new Message's own timestamp
            if len(frame) == 2:
                can_id, data = frame
                for put, is_rx in receivers:
                    put(message(timestamp=timestamp, arbitration_id=can_id, is_extended_id=False,
                                channel=channel_id, data=data, is_rx=is_rx))
            else:  # (can_id, data, True): CAN FD with bit-rate switch (node_sim.link.NodeLink)
                can_id, data, _ = frame
                for put, is_rx in receivers:
                    put(message(timestamp=timestamp, arbitration_id=can_id, is_extended_id=False,
                                channel=channel_id, data=data, is_rx=is_rx, is_fd=True, bitrate_switch=True))

    return send_many


# What the twins of a channel consume (:meth:`_Channel._dispatch`), as python-can filters: NMT
# module control, SDO requests (0x601-0x67F), heartbeats / boot-ups (0x701-0x77F), LSS master
# requests, plus the nodes' SYNC COB-IDs (0x1005) - not the PDOs, EMCY and SDO answers of the
# bus (udp_multicast loops every twin's own frames back to it: a third of what it received)
CONSUMED_FILTERS = [
    {"can_id": 0x000, "can_mask": 0x7FF, "extended": False},
    {"can_id": 0x600, "can_mask": 0x780, "extended": False},
    {"can_id": 0x700, "can_mask": 0x780, "extended": False},
    {"can_id": lssx.LSS_MASTER_COB, "can_mask": 0x7FF, "extended": False},
]


class Channel(can.Listener):
    """One CANopen network: a bus object, its notifier, the nodes, one lock, one timer thread."""

    # patch nodes consuming the same SYNC are sampled as one (node_sim.patch.batch.PatchSyncBatch);
    # False: node by node through each SyncConsumer (the same frames, more CPU)
    batch_patch_sync = True

    def __init__(self, rig: "Rig", index: int, name: str, bus: can.BusABC):
        self.rig = rig
        self.index = index
        self.name = name
        self.bus = bus
        self.lock = threading.RLock()
        self.send_lock = threading.Lock()
        self.scheduler = Scheduler(self.lock, name=f"node-sim-timers-{name}")
        self._burst = virtual_burst_sender(bus) or udp_multicast_burst_sender(bus)
        self.link = NodeLink(self.send, self.scheduler, self.send_many if self._burst is not None else None)
        self.nodes: dict[int, TaxelNode] = {}
        self.scene_index: dict[int, object] = {}  # node-ID -> taxel index in scene order (a patch
                                                  # node: a slice / index array of its taxels)
        self.patch = False                      # patch nodes: each SYNC hands a node its readings' array
        self.lss: dict[int, lssx.LssSlave] = {}  # taxel index -> its LSS slave (configured or not)
        self.sync_count = 0                     # SYNCs seen (cycle of the next one if no loss)
        self.cycle: int | None = None           # cycle number of the last SYNC fully processed
        # (counter byte, cycle) of that SYNC as one tuple, published at once (a reader in another
        # thread - the grasp world's truth - never pairs one SYNC's counter with another's cycle)
        self.sync_state: tuple[int | None, int | None] = (None, None)
        self.lost_syncs = 0
        self._last_counter: int | None = None
        self._overflow = 0                      # the nodes' 0x1019 (read with the SYNC map)
        self._window = 0                        # the nodes' 0x1007, µs (read with the SYNC map)
        self._sync_length_error = False
        self._rx_time = 0.0
        self.late_syncs = 0  # SYNCs handled after their synchronous window (0x1007): no TPDO sent
        self.frames_sent = 0
        self.notifier = None  # its receive handle (a can.Notifier or a taxel_net.receiver one)
        self._sync_map: dict[int, list[tuple[TaxelNode, Callable, int]]] | None = None
        # per SYNC COB-ID, its patch nodes sampled as one (PatchSyncBatch), rebuilt with _sync_map
        self._sync_batches: dict[int, PatchSyncBatch] = {}
        self._sync_ids: frozenset[int] | None = None  # the SYNC COB-IDs the bus filters let through

    @property
    def last_counter(self) -> int | None:
        """The counter byte of the last SYNC processed (None without one, or since a reset of
        every node)."""
        return self._last_counter

    def refresh_filters(self) -> None:
        """Let through what the nodes consume (:data:`CONSUMED_FILTERS` and their SYNC COB-IDs,
        0x080 while there is no node): python-can filters, in the kernel or the controller
        where the interface can (socketcan; udp_multicast: :func:`taxel_net.udp_filter.set_filters`
        - the group's looped-back PDOs of the channel's own nodes never reach this process),
        else before a frame becomes a ``can.Message`` (:func:`taxel_net.receiver.udp_multicast_drain`)
        or at least before this listener."""
        ids = frozenset(n.sync.cob_id for n in self.nodes.values()) or frozenset((0x080,))
        if ids == self._sync_ids:
            return
        self._sync_ids = ids
        set_filters(self.bus, CONSUMED_FILTERS + [{"can_id": i, "can_mask": 0x7FF, "extended": False}
                                                  for i in sorted(ids)])

    # -- python-can Listener
    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        try:
            with self.lock:
                self._rx_time = msg.timestamp
                self._dispatch(msg.arbitration_id, bytes(msg.data))
        except Exception:  # never kill the notifier thread
            logger.exception("node-sim: handling frame 0x%03X failed", msg.arbitration_id)

    def on_error(self, exc: Exception) -> None:
        logger.error("node-sim channel %s: bus error %s", self.name, exc)

    def _dispatch(self, can_id: int, data: bytes) -> None:
        if can_id == 0x000:
            if len(data) == 2:  # CiA 301: NMT module control has DLC 2; any other length is ignored
                target = data[1]
                nodes = list(self.nodes.values()) if target == 0 else (
                    [self.nodes[target]] if target in self.nodes else [])
                with self.link.burst():  # the boot-ups leave once the filters take what a master may answer
                    for node in nodes:
                        node.on_nmt(data[0])
                    self._sync_map = None  # resets restore 0x1005
                    if data[0] in (0x81, 0x82):
                        self.refresh_filters()
                if target == 0 and data[0] in (0x81, 0x82):
                    # every node reset by the master: the simulated world restarts with the
                    # master's cycle 0 (a second master run sees the same scene as the first)
                    self.sync_count = 0
                    self._last_counter = None
            return
        if 0x601 <= can_id <= 0x67F:
            node = self.nodes.get(can_id - 0x600)
            if node is not None and len(data) == 8:
                # the answer leaves once the filters take the SYNC COB-ID it may have moved: the
                # master's next SYNC on it must not meet the old kernel filter (taxel_net.udp_filter)
                with self.link.burst():
                    node.on_sdo_request(data)
                    self._sync_map = None  # 0x1005 may have changed
                    if self._sync_ids is None or node.sync.cob_id not in self._sync_ids:
                        self.refresh_filters()
            return
        if self._sync_map is None:
            self._sync_map = {}
            for n in self.nodes.values():  # each node's SYNC consumer, by its SYNC COB-ID (0x1005)
                self._sync_map.setdefault(n.sync.cob_id, []).append(
                    (n, n.sync.on_sync, self.scene_index[n.node_id]))
            self._sync_batches = {
                cob_id: PatchSyncBatch([(n, index) for n, _, index in group])
                for cob_id, group in self._sync_map.items()
                if self.patch and self.batch_patch_sync and all(PatchSyncBatch.batchable(n) for n, _, _ in group)}
            # the SYNC counter overflow value 0x1019 of the channel's nodes (the most common
            # one, should a master give them different values)
            overflows = [n.sync.overflow for n in self.nodes.values()]
            self._overflow = max(set(overflows), key=overflows.count) if overflows else 0
            # and their synchronous window length 0x1007 (µs, 0 = none), likewise
            windows = [n.objects.read(odx.SYNC_WINDOW) for n in self.nodes.values()]
            self._window = max(set(windows), key=windows.count) if windows else 0
        sync_nodes = self._sync_map.get(can_id)
        if sync_nodes:
            if len(data) != (1 if self._overflow else 0):
                # CiA 301: SYNC length error - ignored, EMCY 0x8240 (once until a valid SYNC)
                if not self._sync_length_error:
                    self._sync_length_error = True
                    for node, _, _ in sync_nodes:
                        node.emcy.send(0x8240, 0x11)  # error register: generic + communication
                return
            self._sync_length_error = False
            window = self._window
            if window and self._rx_time and (time.time() - self._rx_time) * 1e6 > window:
                # CiA 301 0x1007: a synchronous PDO is not sent after the window; a SYNC handled
                # that late (a loaded host) only advances the cycle count
                self.late_syncs += 1
                self.sync_count += 1
                self._last_counter = data[0] if data else None
                self.cycle = self.sync_count - 1
                self.sync_state = (self._last_counter, self.cycle)
                return
            self._on_sync(data, sync_nodes, self._sync_batches.get(can_id))
        elif 0x701 <= can_id <= 0x77F and len(data) == 1:
            # a heartbeat / boot-up of another participant (the master): heartbeat consumers
            for node in self.nodes.values():
                node.on_heartbeat(can_id - 0x700, data[0])
        elif can_id == lssx.LSS_MASTER_COB and len(data) == 8:
            self._on_lss(data)

    def _on_lss(self, data: bytes) -> None:
        """A request of the LSS master (CiA 305) to every LSS slave of the channel (a dead
        node's answers nothing); identical answers leave as one frame (:func:`lssx.answer_all`)."""
        nodes = self.nodes
        slaves = [s for s in self.lss.values()
                  if not (s.active_node_id in nodes and nodes[s.active_node_id].silent)]
        for answer in lssx.answer_all(slaves, data):
            self.send(lssx.LSS_SLAVE_COB, answer)

    def _on_sync(self, data: bytes, nodes: Sequence[tuple[TaxelNode, Callable, int]],
                 batch: PatchSyncBatch | None = None) -> None:
        counter = data[0] if len(data) >= 1 else None
        if counter is not None and self._last_counter is not None:
            step = (counter - self._last_counter - 1) % self._overflow + 1
        else:
            step = 1
        self._last_counter = counter
        cycle = self.sync_count + step - 1
        self.lost_syncs += step - 1
        self.sync_count = cycle + 1
        world = self.rig.world if self.rig.runs_world else None
        if world is None:
            x = self.rig._readings(cycle)
        else:  # the cycle's tag and the sample as one against the world's steps (node_sim.world_runner)
            with world.tag_lock:
                self.sync_state = (counter, cycle)
                x = self.rig._readings(cycle)
        readings = x if self.patch else x.tolist()  # an array (patch nodes take a view) / Python floats
        rig = self.rig
        apply_silence = rig._apply_silence if rig._dropped or rig._silent_faults else None
        # the frames of this SYNC (EMCYs, TPDOs) go out back to back once every node has
        # sampled, in the order the nodes produced them (one burst, as on a real bus after
        # a SYNC): fewer thread switches between this notifier and the receivers' ones
        with self.link.burst():
            for node, on_sync, index in nodes:
                if apply_silence is not None:
                    apply_silence(self.index, node, cycle)
                elif node.silent:  # what _apply_silence does with no drop and no silent fault
                    node.silent = False
                if batch is None:
                    on_sync(cycle, readings[index], counter)  # node.sync.on_sync
            if batch is not None:  # the patch nodes, their detectors in one pass (silence set above)
                batch.on_sync(cycle, readings, counter)
        self.rig._schedule_prefetch(self, cycle)
        # published last: once a waiter sees this cycle, every node has sampled it and sent its
        # TPDOs (and the read-ahead of the next readings is scheduled)
        self.cycle = cycle
        self.sync_state = (counter, cycle)

    def send_many(self, frames: list[tuple]) -> None:
        """A SYNC burst, in order (:func:`virtual_burst_sender`, or udp_multicast's)."""
        with self.send_lock:
            try:
                self._burst(frames)
                self.frames_sent += len(frames)
            except can.CanError as exc:
                logger.warning("node-sim channel %s: sending %d frames failed: %s", self.name, len(frames), exc)

    def send(self, can_id: int, data: bytes, fd: bool = False) -> None:
        msg = TxMessage(arbitration_id=can_id, data=data, is_extended_id=False, is_fd=fd, bitrate_switch=fd)
        with self.send_lock:
            try:
                self.bus.send(msg)
                self.frames_sent += 1
            except can.CanError as exc:  # a full TX queue on a real bus: drop, like a node would
                logger.warning("node-sim channel %s: send 0x%03X failed: %s", self.name, can_id, exc)
