"""LSS master of the fusion centre (CiA 305): node-IDs for non-configured nodes.

With ``[master] assign_ids = "lss"`` the scene's nodes start without a node-ID (0xFF) and take
part in LSS only. Before the usual boot (NMT reset communication, SDO configuration, start),
the centre finds them on each channel by LSS Fastscan and gives each the node-ID the scene
lists for its LSS address: vendor-ID, product code and revision number of the EDS (0x1018:1-3)
and the serial number :func:`expected_serial` (0x1018:4; the twins compute the same,
``node_sim.rig.identity_serial``).

One round per node (CiA 305 §6.5, frames on 0x7E5, answers on 0x7E4):

1. Fastscan reset (BitChecked 0x80): every non-configured node answers; none within the
   response time-out, twice, ends the channel.
2. Vendor-ID, product code and revision number are tried whole (BitChecked 0: one frame each),
   then every expected serial number not yet assigned, the lowest first, until one answers.
   Without an answer (a device of another kind, or a serial the scene does not list) that LSS
   number is found bit by bit from bit 31 down, testing at each bit the value of the lowest
   expected number that agrees with the bits found so far (an answer confirms it, none means
   the other value; plain Fastscan when nothing is expected), then confirmed whole. An
   expected node thus costs 5 frames and no time-out; only absent expected serials (one
   time-out each, once) and the final reset (sent twice) wait for the time-out.
3. The node found is in the configuration state: inquire serial number (the device really
   found), configure node-ID, store configuration, switch state global to waiting: the
   non-configured node takes its node-ID and boots (boot-up 0x700 + node-ID).

A node whose LSS address the scene does not list is left non-configured (warning) and the
channel's scan ends when it is found again. Every frame goes through the event stream (trace,
cycle assembler) like the master's other frames; the answers are taken from the channel's
python-can notifier by a listener added for the duration of the scan.
"""

from __future__ import annotations

import logging
import queue
import struct
import time
from dataclasses import dataclass, field

import can

from taxel_net.identity import identity_serial
from taxel_net.scene import Scene

logger = logging.getLogger("fusion_center.lss")

LSS_MASTER_COB = 0x7E5
LSS_SLAVE_COB = 0x7E4
CS_SWITCH_STATE_GLOBAL = 0x04
CS_CONFIGURE_NODE_ID = 0x11
CS_STORE_CONFIGURATION = 0x17
CS_IDENTIFY_SLAVE = 0x4F
CS_FAST_SCAN = 0x51
CS_INQUIRE_SERIAL = 0x5D
WAITING, CONFIGURATION = 0, 1
FASTSCAN_CONFIRM = 0x80
RESPONSE_TIMEOUT_S = 0.5   # as canopen's LssMaster.RESPONSE_TIMEOUT
STORE_NOT_SUPPORTED = 1

_U32 = struct.Struct("<I")


expected_serial = identity_serial  # 0x1018:4 the scene gives taxel ``t`` (the twins' own rule)


@dataclass
class LssReport:
    """What the LSS phase did: ``assigned`` (channel, serial, node-ID) in order, ``unknown``
    (channel, LSS address) found but not in the scene, ``not_found`` taxel indexes whose
    serial no scan found (already configured, or absent), ``frames`` sent, ``seconds``."""
    assigned: list[tuple[int, int, int]] = field(default_factory=list)
    unknown: list[tuple[int, tuple[int, int, int, int]]] = field(default_factory=list)
    not_found: list[int] = field(default_factory=list)
    frames: int = 0
    seconds: float = 0.0


class ScanFailed(Exception):
    """A Fastscan whose bits did not hold together (an answer lost or late)."""


class _Answers(can.Listener):
    """The LSS answers (0x7E4) of one channel, queued for the master thread."""

    def __init__(self):
        self.queue: queue.Queue[bytes] = queue.Queue()

    def on_message_received(self, msg: can.Message) -> None:
        if (msg.arbitration_id == LSS_SLAVE_COB and not msg.is_extended_id and not msg.is_remote_frame
                and not msg.is_error_frame and len(msg.data) == 8 and getattr(msg, "is_rx", True)):
            self.queue.put(bytes(msg.data))


class LssMaster:
    """The LSS master of one channel (see module docstring). ``transmit(data)`` sends one
    frame on 0x7E5; answers are fed to :attr:`listener`."""

    def __init__(self, transmit, timeout_s: float = RESPONSE_TIMEOUT_S):
        self._transmit = transmit
        self.timeout_s = timeout_s
        self.listener = _Answers()
        self.frames = 0

    def request(self, data: bytes, answer: bool = True) -> bytes | None:
        """Send ``data`` (8 bytes); with ``answer``, the first answer within the time-out."""
        q = self.listener.queue
        while True:  # answers that came too late for an earlier request
            try:
                q.get_nowait()
            except queue.Empty:
                break
        self._transmit(data)
        self.frames += 1
        if not answer:
            return None
        try:
            return q.get(timeout=self.timeout_s)
        except queue.Empty:
            return None

    def fastscan(self, id_number: int, bit_checked: int, lss_sub: int, lss_next: int) -> bool:
        reply = self.request(struct.pack("<BIBBB", CS_FAST_SCAN, id_number, bit_checked, lss_sub, lss_next))
        return reply is not None and reply[0] == CS_IDENTIFY_SLAVE

    def scan(self, identity: tuple[int, int, int], serials: list[int], missed: set[int]
             ) -> tuple[int, int, int, int] | None:
        """One Fastscan: the LSS address of the node it put in the configuration state, None
        when no non-configured node answers. ``identity``: the expected vendor-ID, product
        code and revision; ``serials``: the expected serial numbers, each tried whole unless in
        ``missed`` (to which one without an answer is added). Raises :class:`ScanFailed`
        when the bits found do not hold together (an answer lost or late)."""
        # no answer twice: no non-configured node (one lost answer does not end the scan)
        if not (self.fastscan(0, FASTSCAN_CONFIRM, 0, 0) or self.fastscan(0, FASTSCAN_CONFIRM, 0, 0)):
            return None
        found: list[int] = []
        for sub in range(3):
            if self.fastscan(identity[sub], 0, sub, sub + 1):
                found.append(identity[sub])
            else:  # a device of another kind: the plain Fastscan
                found.append(self._bits(sub, sub + 1, []))
        candidates: list[int] = []
        if tuple(found) == tuple(identity):
            for serial in serials:
                if serial in missed:
                    continue
                if self.fastscan(serial, 0, 3, 0):
                    return (*found, serial)
                missed.add(serial)
            candidates = serials
        return (*found, self._bits(3, 0, candidates))

    def _bits(self, sub: int, nxt: int, candidates: list[int]) -> int:
        """LSS number ``sub`` bit by bit from bit 31, testing at each bit the value of the lowest
        candidate that agrees with the bits found so far (0 without one), then confirmed whole
        (moving the node to ``nxt``)."""
        value = 0
        for bit in range(31, -1, -1):
            high = (0xFFFFFFFF << (bit + 1)) & 0xFFFFFFFF
            guide = [v for v in candidates if (v & high) == value]
            probe = value | (((guide[0] >> bit) & 1) << bit if guide else 0)
            value = probe if self.fastscan(probe, bit, sub, sub) else probe ^ (1 << bit)
        if not self.fastscan(value, 0, sub, nxt):
            raise ScanFailed(f"LSS number {sub}: 0x{value:08X} not confirmed")
        return value

    def inquire_serial(self) -> int | None:
        reply = self.request(bytes((CS_INQUIRE_SERIAL,)) + bytes(7))
        if reply is None or reply[0] != CS_INQUIRE_SERIAL:
            return None
        return _U32.unpack_from(reply, 1)[0]

    def configure(self, cs: int, value: int = 0) -> int | None:
        """Configure node-ID / store configuration: the error code answered (None: no answer)."""
        reply = self.request(bytes((cs, value)) + bytes(6))
        if reply is None or reply[0] != cs:
            return None
        return reply[1]

    def switch_global(self, state: int) -> None:
        self.request(bytes((CS_SWITCH_STATE_GLOBAL, state)) + bytes(6), answer=False)


def assign_node_ids(service, scene: Scene, identity: tuple[int, int, int],
                    timeout_s: float | None = None) -> LssReport:
    """Find the non-configured nodes of every channel by Fastscan and give each the node-ID
    the scene lists for its LSS address (``identity``: the EDS's 0x1018:1-3). ``service``: the
    :class:`~fusion_center.service.fusion_service.FusionService` (its event stream sends, its
    notifiers receive)."""
    if timeout_s is None:
        timeout_s = RESPONSE_TIMEOUT_S  # read at call time (tests on a virtual bus shorten it)
    report = LssReport()
    start = time.monotonic()
    for channel in range(len(scene.bus.channels)):
        wanted = {expected_serial(scene, t): i for i, t in enumerate(scene.taxels) if t.channel == channel}
        if not wanted:
            continue
        master = LssMaster(lambda data, ch=channel: service.stream.transmit(ch, LSS_MASTER_COB, data), timeout_s)
        notifier = service.notifiers[channel]
        notifier.add_listener(master.listener)
        try:
            assign_channel(master, channel, scene, identity, wanted, report)
        finally:
            notifier.remove_listener(master.listener)
            report.frames += master.frames
    report.seconds = time.monotonic() - start
    return report


def assign_channel(master: LssMaster, channel: int, scene: Scene, identity, wanted: dict[int, int],
                    report: LssReport) -> None:
    remaining = dict(wanted)
    unknown: set[tuple[int, int, int, int]] = set()
    missed: set[int] = set()
    failures = 0
    while failures <= 3:
        try:
            address = master.scan(identity, sorted(remaining), missed)
        except ScanFailed as exc:
            logger.warning("LSS channel %d: %s: scanning again", channel, exc)
            failures += 1
            continue
        if address is None:
            break  # no non-configured node left
        serial = master.inquire_serial()
        if serial != address[3]:
            logger.warning("LSS channel %d: Fastscan found serial 0x%08X, the node in configuration state "
                           "says %s: scanning again", channel, address[3],
                           "nothing" if serial is None else f"0x{serial:08X}")
            master.switch_global(WAITING)
            failures += 1
            continue
        index = remaining.pop(serial, None) if address[:3] == tuple(identity) else None
        if index is None:
            master.switch_global(WAITING)
            if address in unknown:
                break  # found again: every expected serial was tried before it
            unknown.add(address)
            report.unknown.append((channel, address))
            logger.warning("LSS channel %d: a non-configured node with LSS address %s is not in the scene: "
                           "left without node-ID", channel, " ".join(f"0x{v:08X}" for v in address))
            continue
        node_id = scene.taxels[index].node_id
        error = master.configure(CS_CONFIGURE_NODE_ID, node_id)
        if error != 0:
            logger.warning("LSS channel %d: serial 0x%08X refused node-ID %d (%s)", channel, serial, node_id,
                           "no answer" if error is None else f"error {error}")
            remaining[serial] = index
            master.switch_global(WAITING)
            failures += 1
            continue
        stored = master.configure(CS_STORE_CONFIGURATION)
        if stored not in (0, STORE_NOT_SUPPORTED):
            logger.warning("LSS channel %d: node-ID %d not stored (%s)", channel, node_id,
                           "no answer" if stored is None else f"error {stored}")
        master.switch_global(WAITING)  # the node takes its node-ID and boots
        report.assigned.append((channel, serial, node_id))
    report.not_found.extend(sorted(remaining.values()))
