"""A gripper drive on its own python-can bus object: :class:`DriveHost`.

What :class:`node_sim.rig.channel.Channel` is for the taxel nodes of a rig channel, for one
:class:`node_sim.gripper.drive.GripperDrive`: one bus object, one lock, one timer thread
(:class:`node_sim.link.Scheduler`: heartbeat, SDO server timeout), a receive thread (python-can's
``Notifier``) that hands each frame to the drive with the lock held - NMT module control (to the
drive or broadcast), SDO requests (0x600 + node-ID), SYNC (the drive's 0x1005; a SYNC whose length
does not match 0x1019 is a length error: EMCY 0x8240 once, ignored), heartbeats of the other
participants (the drive's heartbeat consumer), the drive's RPDOs. The frames one SYNC triggers
(TPDOs, EMCYs) leave as one burst. Its bus filters let through only those (:meth:`DriveHost.refresh_filters`:
refreshed when an SDO download or a reset moves the SYNC or an RPDO COB-ID): the taxels' TPDOs on
the same channel never wake its receive thread nor take its lock.

Several hosts (or a host and a rig) share a CAN network by opening the same channel: on
``virtual`` and ``udp_multicast`` every bus object sees the others' frames.

The world (the grasp physics, later) acts on the drive inside ``with host.lock:``.
"""

from __future__ import annotations

import logging
import threading
from typing import Mapping

import can

from taxel_net.canmsg import TxMessage, tune_udp_multicast
from taxel_net.errors import ParameterError
from taxel_net.udp_filter import set_filters

from ..link import NodeLink, Scheduler
from .drive import GRIPPER_EDS_PATH, GripperDrive

logger = logging.getLogger(__name__)

EMCY_SYNC_LENGTH = 0x8240


class _Receiver(can.Listener):
    """The notifier's listener: hands every frame to its host (``Listener.stop`` is the notifier's)."""

    def __init__(self, host: "DriveHost"):
        self._host = host

    def on_message_received(self, msg: can.Message) -> None:
        self._host.on_message_received(msg)

    def on_error(self, exc: Exception) -> None:
        logger.error("gripper drive %d: bus error %s", self._host.node_id, exc)


class DriveHost:
    """One gripper drive on its own bus object (see module docstring).

    ``startup``: start-up values ``{(index, subindex): value}`` (checked as SDO downloads; a refused
    one raises ParameterError naming the object). :meth:`start` opens the bus, configures the drive
    and sends its boot-up; :meth:`stop` (idempotent) closes everything.
    """

    def __init__(self, node_id: int, interface: str = "virtual", channel: str = "taxel-can",
                 bus_kwargs: Mapping | None = None, startup: Mapping | None = None, eds_path=GRIPPER_EDS_PATH):
        if not isinstance(node_id, int) or isinstance(node_id, bool) or not 1 <= node_id <= 127:
            raise ParameterError("gripper.node_id", node_id, "CANopen node-ID must be an integer 1..127")
        self.node_id = node_id
        self.interface = interface
        self.channel = channel
        self.bus_kwargs = dict(bus_kwargs or {})
        self.startup = dict(startup or {})
        self.eds_path = eds_path
        self.lock = threading.RLock()
        self._send_lock = threading.Lock()
        self.bus: can.BusABC | None = None
        self.scheduler: Scheduler | None = None
        self.notifier: can.Notifier | None = None
        self.drive: GripperDrive | None = None
        self.cycle = -1                     # SYNCs processed - 1
        self._sync_length_error = False
        self._filtered: tuple[int, ...] | None = None  # the COB-IDs the bus filters let through

    @classmethod
    def for_scene(cls, scene, interface: str, channel: str, bus_kwargs: Mapping | None = None,
                  eds_path=GRIPPER_EDS_PATH) -> "DriveHost":
        """The drive of ``scene``'s ``[gripper]`` table (not started) on bus channel ``channel``
        (the scene channel ``scene.gripper.channel`` is opened as), with the scene's start-up
        values (:func:`taxel_net.gripper.startup_values`)."""
        from taxel_net.gripper import startup_values

        return cls(scene.gripper.node_id, interface, channel, bus_kwargs, startup_values(scene), eds_path)

    def __enter__(self) -> "DriveHost":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> "DriveHost":
        if self.bus is not None:
            return self
        try:
            try:
                self.bus = can.Bus(interface=self.interface, channel=self.channel, **self.bus_kwargs)
            except Exception as exc:  # noqa: BLE001 - any backend failure is "cannot open"
                raise ParameterError("channel", self.channel, f"cannot be opened with python-can interface "
                                     f"{self.interface!r}: {type(exc).__name__}: {exc}") from None
            tune_udp_multicast(self.bus)
            self.scheduler = Scheduler(self.lock, name=f"gripper-{self.node_id}-timers")
            link = NodeLink(self._send, self.scheduler)
            with self.lock:
                self.drive = GripperDrive(self.node_id, link, eds_path=self.eds_path)
                self.drive.configure(self.startup)
            with self.lock:
                self.refresh_filters()
            self.notifier = can.Notifier(self.bus, [_Receiver(self)], timeout=0.05)
            with self.lock:
                self.drive.power_on()
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        if self.scheduler is not None:
            self.scheduler.stop()
        if self.drive is not None:
            with self.lock:
                self.drive.shutdown()
        if self.notifier is not None:
            self.notifier.stop(timeout=2)
        if self.bus is not None:
            try:
                self.bus.shutdown()
            except Exception:  # noqa: BLE001
                logger.exception("gripper drive: bus shutdown failed")
        self.bus = self.scheduler = self.notifier = None
        self._filtered = None

    def refresh_filters(self) -> None:
        """Let through what the drive consumes (lock held): NMT, its SDO requests, heartbeats
        (0x700-0x77F: its heartbeat consumer), its SYNC COB-ID and its valid RPDOs' COB-IDs -
        python-can filters (udp_multicast: :func:`taxel_net.udp_filter.set_filters`)."""
        drive, bus = self.drive, self.bus
        if drive is None or bus is None:
            return
        ids = tuple(sorted({0x000, 0x600 + drive.node_id, drive.sync.cob_id, *drive.rpdo.cob_ids}))
        if ids == self._filtered:
            return
        self._filtered = ids
        set_filters(bus, [{"can_id": 0x700, "can_mask": 0x780, "extended": False}]
                    + [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids])

    # -- frames in
    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        try:
            with self.lock:
                self._dispatch(msg.arbitration_id, bytes(msg.data))
        except Exception:  # never kill the notifier thread
            logger.exception("gripper drive: handling frame 0x%03X failed", msg.arbitration_id)

    def _dispatch(self, can_id: int, data: bytes) -> None:
        drive = self.drive
        if drive is None:
            return
        link = drive.link
        if can_id == 0x000:
            if len(data) == 2 and data[1] in (0, drive.node_id):
                with link.burst():
                    drive.on_nmt(data[0])
                    if data[0] in (0x81, 0x82):  # resets restore 0x1005 and the RPDOs' COB-IDs
                        self.refresh_filters()
            return
        if can_id == 0x600 + drive.node_id:
            if len(data) == 8:
                with link.burst():  # the answer leaves once the filters take what the download moved
                    drive.on_sdo_request(data)
                    self.refresh_filters()
            return
        if can_id == drive.sync.cob_id:
            if len(data) != (1 if drive.sync.overflow else 0):
                if not self._sync_length_error:           # CiA 301: SYNC length error, once
                    self._sync_length_error = True
                    drive.emcy.send(EMCY_SYNC_LENGTH, 0x11)
                return
            self._sync_length_error = False
            self.cycle += 1
            with link.burst():
                drive.on_sync(self.cycle, None, data[0] if data else None)
            return
        if 0x701 <= can_id <= 0x77F and len(data) == 1:
            drive.on_heartbeat(can_id - 0x700, data[0])
            return
        drive.on_rpdo(can_id, data)

    # -- frames out
    def _send(self, can_id: int, data: bytes, fd: bool = False) -> None:
        bus = self.bus
        if bus is None:
            return
        msg = TxMessage(arbitration_id=can_id, data=data, is_extended_id=False)
        with self._send_lock:
            try:
                bus.send(msg)
            except can.CanError as exc:
                logger.warning("gripper drive %d: send 0x%03X failed: %s", self.node_id, can_id, exc)
