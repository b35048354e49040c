"""The taxel node firmware twin: one CANopen slave composed of its services.

canopen 2.4.1's ``LocalNode`` supplies the object dictionary (loaded from the EDS) and the
data store. It has no slave behaviour beyond that (no TPDO on SYNC, no
inhibit time / event timer, PDO data kept apart from the OD, no way out of INITIALISING
after an NMT reset: canopen issues #145, #520, #558, #47), so the node twin adds one module
per CANopen service, each owning that service's state (the layout follows canopen's own:
``nmt``, ``sdo``, ``pdo``, ``sync``, ``emcy``):

* :class:`node_sim.od.NodeObjects` - the OD glue: ``LocalNode``, typed reads/writes of the
  data store, start-up values restored by the NMT resets;
* :class:`node_sim.nmt.NmtSlave` - NMT state machine and boot-up;
* :class:`node_sim.heartbeat.HeartbeatProducer` - heartbeat per 0x1017;
  :class:`node_sim.heartbeat.HeartbeatConsumer` - the master's heartbeat per 0x1016, error
  behaviour 0x1029 on its loss;
* :class:`node_sim.sdo.SdoServer` - canopen's SDO server behind the CiA 301 checks; every
  object's write rules are registered by the service that owns the object;
* :class:`node_sim.sync.SyncConsumer` - 0x1005 and what a SYNC triggers;
* :class:`node_sim.taxel.detector.Detector` - the application: X_i sampled per SYNC, sensor-fault
  checks, the local decision of the chapter (eqs 1-4), OD update;
* :class:`node_sim.pdo.TpdoEngine` - TPDO1/TPDO2, synchronous and event-driven;
* :class:`node_sim.emcy.EmcyProducer` - EMCY, 0x1001 and 0x1003.

:class:`TaxelNode` creates them, wires the NMT transitions to the services (boot: timers
stopped and TPDO state forgotten, then the heartbeat started; start / stop: TPDOs; resets:
the OD restored and the fault state forgotten) and routes the frames of its channel:
NMT → :meth:`TaxelNode.on_nmt`, SDO requests → :meth:`TaxelNode.on_sdo_request`, SYNC →
:meth:`TaxelNode.on_sync` (the rig calls the SYNC consumer's bound ``on_sync`` directly).
``silent`` (a dead node): no frame is sent and none is processed while it is set.

Threading: every entry point runs with the owning channel's lock held (the rig's notifier
thread or its scheduler thread); nodes never block.
"""

from __future__ import annotations

from canopen.sdo import SdoAbortedError

from . import od as odx
from .taxel.detector import Detector
from .emcy import EmcyProducer
from .heartbeat import HeartbeatConsumer, HeartbeatProducer
from .link import NodeLink, Scheduler
from .nmt import (NMT_ENTER_PRE_OPERATIONAL, NMT_RESET_COMMUNICATION, NMT_RESET_NODE, NMT_STOP,
                  OPERATIONAL, STATE_NAMES, STOPPED, NmtSlave)
from .od import COB_INVALID
from .pdo import TpdoEngine
from .sdo import SdoServer
from .sync import SyncConsumer

# the node, and what its channel side needs (NodeLink, Scheduler, COB_INVALID re-exported)
__all__ = ["TaxelNode", "NodeLink", "Scheduler", "COB_INVALID"]


class TaxelNode:
    """One taxel's CANopen node twin (see module docstring).

    ``node_id`` 1..127; ``link`` gives the channel's ``send`` and scheduler; ``od`` defaults
    to the EDS imported for ``node_id``. Call :meth:`configure` with start-up values, then
    :meth:`power_on`. Entry points (:meth:`on_nmt`, :meth:`on_sdo_request`, :meth:`on_sync`)
    must be called with the channel lock held.

    Services (attributes): ``objects``, ``nmt``, ``heartbeat``, ``emcy``, ``detector``,
    ``pdo``, ``sync``, ``sdo``; ``od`` and ``local`` are ``objects.od`` / ``objects.local``.

    LSS (CiA 305): ``lss`` is the device's :class:`node_sim.lss.LssSlave` (None: no LSS), which
    outlives the node; an NMT reset that makes another node-ID active (configured over LSS)
    is handed to ``renumber(node, node_id, command)``: the owner starts the device again
    under that node-ID (0xFF: non-configured, LSS only), as a CANopen stack re-initialises its
    communication objects.
    """

    def __init__(self, node_id: int, link: NodeLink, od=None, eds_path=odx.EDS_PATH, *,
                 lss=None, renumber=None, fd: bool = False):
        self.node_id = node_id
        self.link = link
        self.silent = False
        self.lss = lss
        self._renumber = renumber
        self._frames_sent = 0
        self.objects = objects = odx.NodeObjects(node_id, od, eds_path)
        self.od = objects.od
        self.local = objects.local
        self.nmt = NmtSlave(node_id, self._send,
                            before_boot=self._before_boot, after_boot=self._after_boot,
                            enter_operational=self._enter_operational,
                            leave_operational=self._leave_operational,
                            reset_node=self._reset_node, reset_communication=self._reset_communication)
        self.heartbeat = HeartbeatProducer(node_id, self.nmt, objects, self._send, link.scheduler)
        self.emcy = EmcyProducer(self.nmt, objects, self._send, link.scheduler)
        self.heartbeat_consumer = HeartbeatConsumer(self.nmt, objects, link.scheduler, self._heartbeat_event)
        self.detector = self._new_detector()
        self.pdo = self._new_pdo(fd)
        self.sync = SyncConsumer(self, self.nmt, objects, self.detector.sample, self.pdo.on_sync,
                                 scalar=self.SCALAR_READING)
        self.sdo = SdoServer(node_id, self.nmt, objects, self._send, link.scheduler)
        # each object's write rules and side effects, from the service that owns it
        sdo = self.sdo
        pdo_objects = self.pdo.comm + self.pdo.mapping
        sdo.add_check((odx.ERROR_FIELD, odx.COB_ID_EMCY), self.emcy.check_write)
        sdo.add_check((odx.COB_ID_SYNC, odx.SYNC_OVERFLOW), self.sync.check_write)
        sdo.add_check(pdo_objects, self.pdo.check_write)
        sdo.add_check(self.APPLICATION_OBJECTS, self.detector.check_write)
        sdo.add_written(None, self.detector.invalidate)  # any write: parameters re-read at the next SYNC
        sdo.add_written((odx.ERROR_FIELD, odx.COB_ID_EMCY), self.emcy.written)
        sdo.add_written(pdo_objects, self.pdo.written)
        sdo.add_written((odx.HEARTBEAT_PRODUCER,), self.heartbeat.written)
        sdo.add_check((odx.CONSUMER_HEARTBEAT,), self.heartbeat_consumer.check_write)
        sdo.add_written((odx.CONSUMER_HEARTBEAT,), self.heartbeat_consumer.written)

    # the application (a subclass, node_sim.patch.PatchNode, hosts many taxels)
    SCALAR_READING = True                     # on_sync gets one reading (False: an array)
    APPLICATION_OBJECTS = (odx.DETECTOR, odx.FAULT_DETECTION)   # the detector's write rules

    def _new_detector(self):
        return Detector(self.objects, self.emcy.fault_changed)

    def _new_pdo(self, fd: bool) -> TpdoEngine:
        return TpdoEngine(self, self.nmt, self.objects, self.link, fd=fd)

    # ------------------------------------------------------------------ OD access
    def read(self, index: int, subindex: int = 0):
        """Current value of ``index:subindex`` decoded with its EDS data type."""
        return self.objects.read(index, subindex)

    def configure(self, values: dict[tuple[int, int], object]) -> None:
        """Write start-up values (the node's stored parameters) into the OD, each checked by
        the same rules as an SDO download; a refused value raises ParameterError. Then they
        become the values NMT reset-node / reset-communication restore."""
        from taxel_net.errors import ParameterError

        objects = self.objects
        for (index, subindex), value in values.items():
            var = objects.variable(index, subindex)
            data = var.encode_raw(value)
            try:
                self.sdo.check_write(index, subindex, var, data, startup=True)
            except SdoAbortedError as exc:
                raise ParameterError(f"node {self.node_id} 0x{index:04X}:{subindex}", value,
                                     f"refused by the node (SDO abort 0x{exc.code:08X})") from None
            objects.store_raw(index, subindex, data)
        objects.save_startup()
        self.pdo.invalidate()
        self.detector.invalidate()

    # ------------------------------------------------------------------ frames in
    def power_on(self) -> None:
        """INITIALISING → boot-up frame → PRE-OPERATIONAL, heartbeat started."""
        self.nmt.boot()

    def on_nmt(self, command: int) -> None:
        if self.silent:
            return
        if self.lss is not None and command in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            node_id = self.lss.on_reset(application=command == NMT_RESET_NODE)
            if node_id != self.node_id and self._renumber is not None:
                self._renumber(self, node_id, command)  # CiA 305: the new node-ID becomes active
                return
        self.nmt.on_command(command)
        if self.nmt.state == STOPPED:
            self.sdo.reset()  # no SDO in STOPPED: a transfer in progress is dropped
        else:
            self.emcy.resume()  # EMCYs owed while the node could not report

    def on_heartbeat(self, node_id: int, state: int) -> None:
        """A heartbeat / boot-up frame of ``node_id`` (the heartbeat consumer, 0x1016)."""
        if self.silent:
            return
        self.heartbeat_consumer.on_heartbeat(node_id, state)

    def on_sdo_request(self, data: bytes) -> None:
        if self.silent:
            return
        self.sdo.on_request(data)

    def on_sync(self, cycle: int, reading: float, counter: int | None = None) -> None:
        """SYNC: sample X_i of ``cycle``, decide (eqs 1-4), update the OD, run the TPDOs
        (:meth:`node_sim.sync.SyncConsumer.on_sync`)."""
        self.sync.on_sync(cycle, reading, counter)

    def shutdown(self) -> None:
        self.heartbeat.stop()
        self.heartbeat_consumer.reset()
        self.sdo.reset()
        self.pdo.leave_operational()

    # ------------------------------------------------------------------ frames out
    def _send(self, can_id: int, data: bytes) -> None:
        if self.silent:
            return
        self.link.send(can_id, data)
        self._frames_sent += 1

    # ------------------------------------------------------------------ NMT hooks
    def _heartbeat_event(self, node_id: int, lost: bool) -> None:
        """A consumed heartbeat lost / back: EMCY 0x8130 (or its reset), then on a loss the
        NMT state 0x1029:1 asks for (0: pre-operational if operational, 1: none, 2: stopped)."""
        self.emcy.communication_error(bool(self.heartbeat_consumer.lost))
        if not lost:
            return
        behaviour = self.objects.read(odx.ERROR_BEHAVIOUR, 1)
        if behaviour == 0 and self.nmt.state == OPERATIONAL:
            self.on_nmt(NMT_ENTER_PRE_OPERATIONAL)
        elif behaviour == 2:
            self.on_nmt(NMT_STOP)

    def _before_boot(self) -> None:
        self.heartbeat.stop()
        self.heartbeat_consumer.reset()
        self.sdo.reset()
        self.pdo.reset()

    def _after_boot(self) -> None:
        self.heartbeat.restart()
        # the TPDOs' configuration read now, in PRE-OPERATIONAL after the boot-up frame: an NMT
        # start then reads only what SDO downloads changed, and the SYNC right after it finds
        # the node OPERATIONAL with its TPDOs ready (TpdoEngine.config)
        self.pdo.read_configuration()

    def _enter_operational(self) -> None:
        self.pdo.enter_operational()

    def _leave_operational(self) -> None:
        self.pdo.leave_operational()

    def _reset_node(self) -> None:
        self.objects.restore_startup()
        self.detector.invalidate()
        self.detector.reset()
        self.emcy.reset()

    def _reset_communication(self) -> None:
        self.objects.restore_communication()
        self.detector.invalidate()
        self.detector.reset()
        self.emcy.reset()

    # ------------------------------------------------------------------ introspection
    @property
    def state(self) -> int:
        """NMT state (the heartbeat state byte)."""
        return self.nmt.state

    @property
    def state_name(self) -> str:
        return STATE_NAMES[self.nmt.state]

    @property
    def decision(self) -> int:
        return self.read(odx.LOCAL_DECISION)

    @property
    def fault(self) -> int:
        """Active sensor fault (``node_sim.emcy.FAULT_*``)."""
        return self.detector.fault

    @property
    def last_cycle(self) -> int | None:
        """Cycle number of the last SYNC consumed (None before the first)."""
        return self.sync.last_cycle

    @property
    def frames_sent(self) -> int:
        return self._frames_sent + self.pdo.frames_sent
