"""EMCY producer of the taxel node twin (CiA 301 emergency object): codes, frame, 0x1001/0x1003.

Frame (COB-ID from 0x1014, default 0x80 + node-ID), 8 bytes little-endian:
``error code (UNSIGNED16) | error register 0x1001 (UNSIGNED8) | manufacturer field (5 bytes)``.
The taxel node's manufacturer field is ``fault id (UNSIGNED8) | offending reading (REAL32 mV)``.

Codes (CiA 301 error-code classes):

* ``0x0000`` error reset / no error — sent when the last active fault clears;
* ``0x5000`` device hardware — open circuit: the reading is not finite or |X| ≥ full scale
  (0x2002:1); an open bridge/input stage reads at the rail or produces no conversion;
* ``0x8130`` communication — heartbeat error: a heartbeat the node consumes (0x1016) was
  lost (:class:`node_sim.heartbeat.HeartbeatConsumer`); error register bits 0 and 4;
* ``0x7300`` sensor — stuck reading: M (0x2002:2) consecutive identical raw samples
  (the code CiA 402/404-style devices use for a sensor fault);
* ``0x3000`` voltage — input over range (patch nodes in raw mode,
  :data:`taxel_net.patches.EMCY_INPUT_OVER_RANGE`): a mapped INTEGER8/16 reading saturates at
  its limit code (CiA 404 AI status "positive / negative overload"); error register bits 0 and
  2 (voltage, as analog input modules report an input out of range); sent on the rising edge
  (:meth:`EmcyProducer.over_range`), its error reset when every mapped reading is back in range.
  Manufacturer field: over-range id 3, taxel k, its TPDO (1 = 0x1800), its AI status bits,
  taxels over range; the error reset names the over-range id alone.

A device-profile error (the gripper drive's CiA 402 faults, :mod:`node_sim.gripper.drive`) is
reported with :meth:`EmcyProducer.device_error`: its own code, error register bit 0 plus the bits the
device gives, the same pairing with its error reset. An RPDO error (:mod:`node_sim.rpdo`: 0x8210 a
PDO too short, 0xFF10 a value the SDO rules refuse) is an episode (:meth:`EmcyProducer.rpdo_error`):
one EMCY when it begins, whatever the PDO rate, its error reset at the first RPDO processed again;
0x1001 holds the bits the EMCY names (0 and 4) for the whole episode.

Error register bits set on a fault: bit 0 (generic error, mandatory whenever any error is
active) and bit 5 (device-profile specific).

:class:`EmcyProducer` (one per node) keeps the error register 0x1001 and the pre-defined
error field 0x1003 (newest first at sub 1, sub 0 = count, at most 8 entries; an entry is the
EMCY code with the fault id in bits 16-31) up to date when the application reports a fault
change, and sends the EMCY — in PRE-OPERATIONAL and OPERATIONAL only, and only while 0x1014
is valid (bit 31 clear); the error register is kept up to date in every state. EMCYs come in
pairs: a fault that begins while the node cannot report (STOPPED) is reported when it can
again (:meth:`EmcyProducer.resume`, on entering PRE-OPERATIONAL / OPERATIONAL), and an error
reset is sent only after a reported error (a fault that begins and ends unreported sends
neither; one reported and cleared while stopped gets its error reset on resuming). An
open-circuit reading of ±inf, or finite beyond REAL32, is sent as ±3.4e38 (the REAL32 field), NaN as NaN. Its SDO
rules: 0x1003:0 accepts only 0 (clear the history: subs 1-8 dropped), 0x1014 refuses a
29-bit CAN-ID (0x06090030).

Inhibit time 0x1015 (CiA 301, UNSIGNED16 in 100 µs; where the node's EDS has it - the patch
node's): an EMCY is not sent sooner than that after the previous one; one that would be is
queued and sent when the time is up, in order (as CANopenNode's EMCY FIFO), each the inhibit
time after the one before. A queued EMCY counts as reported: it is kept while the node may not
send (STOPPED, 0x1014 not valid) and sent when it may again (on entering PRE-OPERATIONAL /
OPERATIONAL, :meth:`EmcyProducer.resume`, before what resuming owes; or 0x1014 written valid);
only an NMT reset drops it (the error state starts afresh). 0 (the default): no inhibit time.
"""

from __future__ import annotations

import math
import struct
import time
from collections import deque
from typing import Callable

from canopen.sdo import SdoAbortedError

from taxel_net.patches import EMCY_INPUT_OVER_RANGE, EMCY_OVER_RANGE_ID, ERR_REG_VOLTAGE  # noqa: F401 - re-exported

from .nmt import OPERATIONAL, PRE_OPERATIONAL, NmtSlave
from .od import COB_29BIT, COB_ID_EMCY, COB_INVALID, ERROR_FIELD, ERROR_REGISTER, NodeObjects
from .sdo import ABORT_VALUE_RANGE

EMCY_NO_ERROR = 0x0000
EMCY_OPEN_CIRCUIT = 0x5000
EMCY_STUCK = 0x7300
EMCY_HEARTBEAT = 0x8130       # life guard / heartbeat error (a consumed heartbeat lost)
INHIBIT_TIME_EMCY = 0x1015    # UNSIGNED16, 100 µs units (CiA 301)

REAL32_MAX = 3.4028234663852886e38  # the largest finite IEEE 754 single

FAULT_NONE = 0
FAULT_STUCK = 1
FAULT_OPEN_CIRCUIT = 2
FAULT_OVER_RANGE = EMCY_OVER_RANGE_ID   # 3: the over-range EMCY's id (byte 3 of its field)
FAULT_NAMES = {FAULT_NONE: "none", FAULT_STUCK: "stuck", FAULT_OPEN_CIRCUIT: "open_circuit",
               FAULT_OVER_RANGE: "over_range"}
FAULT_EMCY_CODE = {FAULT_STUCK: EMCY_STUCK, FAULT_OPEN_CIRCUIT: EMCY_OPEN_CIRCUIT}

ERR_REG_GENERIC = 0x01
ERR_REG_COMMUNICATION = 0x10
ERR_REG_PROFILE = 0x20
ERR_REG_SENSOR_FAULT = ERR_REG_GENERIC | ERR_REG_PROFILE

EMCY_STRUCT = struct.Struct("<HBBf")  # code, error register, fault id, reading (REAL32)

ERROR_HISTORY_LENGTH = 8  # 0x1003 sub 1..8 (EDS SubNumber 9)

OVER_RANGE_RESET_FIELD = bytes((FAULT_OVER_RANGE, 0, 0, 0, 0))   # the error reset of an over range


def over_range_field(taxel: int, tpdo: int, status: int, count: int) -> bytes:
    """The manufacturer field of the over-range EMCY: id 3, taxel ``taxel`` (0-based), the TPDO
    carrying it (1 = 0x1800), its AI status bits, how many taxels are over range (<= 254)."""
    return bytes((FAULT_OVER_RANGE, taxel & 0xFF, tpdo & 0xFF, status & 0xFF, min(count, 255)))


def emcy_payload(code: int, error_register: int, fault_id: int = 0, reading: float = 0.0) -> bytes:
    """The 8 data bytes of an EMCY frame."""
    return EMCY_STRUCT.pack(code, error_register, fault_id, reading)


def parse_emcy(data: bytes) -> tuple[int, int, int, float]:
    """``(code, error_register, fault_id, reading)`` of an EMCY frame's 8 data bytes."""
    return EMCY_STRUCT.unpack(bytes(data[:8]))


class EmcyProducer:
    """One node's EMCY producer (see module docstring)."""

    def __init__(self, nmt: NmtSlave, objects: NodeObjects, send: Callable[[int, bytes], None], scheduler=None):
        self._nmt = nmt
        self._objects = objects
        self._send = send
        self._scheduler = scheduler   # node_sim.link.Scheduler: the inhibit time's timer (None: no inhibit time)
        self._has_inhibit = scheduler is not None and INHIBIT_TIME_EMCY in objects.od
        self._last_tx = -math.inf     # time.monotonic() of the last EMCY sent
        self._queue: deque[bytes] = deque()   # EMCYs waiting for the inhibit time, in order
        self._timer = None
        self._over: bytes | None = None   # an input over range: its manufacturer field
        self._over_reported = False
        self._active: tuple[int, int, int, float] | None = None   # the sensor fault now
        self._reported = False     # its EMCY was sent (an error reset is owed when it clears)
        self._comm_error = False   # a heartbeat consumed by this node is lost (0x1016)
        self._comm_reported = False
        self._device: tuple[int, int] | None = None   # a device-profile error (code, register bits)
        self._device_reported = False
        self._rpdo: tuple[int, int, bytes] | None = None   # an RPDO error episode (code, bits, field)
        self._rpdo_reported = False

    def reset(self) -> None:
        """NMT reset: the fault state is forgotten (the detector starts afresh)."""
        self._active = None
        self._reported = False
        self._comm_error = False
        self._comm_reported = False
        self._device = None
        self._device_reported = False
        self._rpdo = None
        self._rpdo_reported = False
        self._over = None
        self._over_reported = False
        self._drop_queue()

    def _register(self) -> int:
        register = ERR_REG_SENSOR_FAULT if self._active is not None else 0
        if self._over is not None:
            register |= ERR_REG_GENERIC | ERR_REG_VOLTAGE
        if self._device is not None:
            register |= ERR_REG_GENERIC | self._device[1]
        if self._comm_error:
            register |= ERR_REG_GENERIC | ERR_REG_COMMUNICATION
        if self._rpdo is not None:
            register |= ERR_REG_GENERIC | self._rpdo[1]
        return register

    def _store_register(self) -> int:
        """0x1001 set to the error register of the present errors (:meth:`_register`); returned."""
        register = self._register()
        self._objects.store(ERROR_REGISTER, 0, register)
        return register

    def _push_history(self, entry: int) -> None:
        objects = self._objects
        count = objects.read(ERROR_FIELD, 0)
        history = [entry] + [objects.read(ERROR_FIELD, s) for s in range(1, count + 1)]
        history = history[:ERROR_HISTORY_LENGTH]
        for sub, value in enumerate(history, start=1):
            objects.store(ERROR_FIELD, sub, value)
        objects.store(ERROR_FIELD, 0, len(history))

    def communication_error(self, active: bool) -> None:
        """A consumed heartbeat was lost (``active``) or every one is back: EMCY 0x8130 with
        error register bit 4, then its error reset (only after a reported 0x8130)."""
        if active == self._comm_error:
            return
        self._comm_error = active
        register = self._store_register()
        if active:
            self._push_history(EMCY_HEARTBEAT)
            self._comm_reported = self.send(EMCY_HEARTBEAT, register)
        elif self._comm_reported:
            self._comm_reported = not self.send(EMCY_NO_ERROR, register)

    def device_error(self, code: int | None, bits: int = 0) -> None:
        """A device-profile error began (``code``, e.g. a CiA 402 drive fault; ``bits``: its error
        register bits besides bit 0) or ended (None): 0x1001 and 0x1003 updated, the EMCY sent (its
        error reset only after a reported error)."""
        if code is None:
            if self._device is None:
                return
            self._device = None
            register = self._store_register()
            if self._device_reported:
                self._device_reported = not self.send(EMCY_NO_ERROR, register)
            return
        self._device = (code, bits)
        register = self._store_register()
        self._push_history(code)
        self._device_reported = self.send(code, register)

    def rpdo_error(self, code: int | None, bits: int = ERR_REG_COMMUNICATION, field: bytes = b"") -> None:
        """An RPDO error episode began (``code``, e.g. 0x8210 a PDO not processed for its length;
        ``bits`` its error register bits besides bit 0; ``field`` the manufacturer field) or ended
        (None: an RPDO was processed again): 0x1001 and 0x1003 updated, one EMCY at the start of
        the episode (a call while one is active does nothing: no flood at the PDO rate) and its
        error reset at the end (only after a reported one)."""
        if code is None:
            if self._rpdo is None:
                return
            self._rpdo = None
            register = self._store_register()
            if self._rpdo_reported:
                self._rpdo_reported = not self.send(EMCY_NO_ERROR, register)
            return
        if self._rpdo is not None:
            return
        self._rpdo = (code, bits, bytes(field))
        register = self._store_register()
        self._push_history(code)
        self._rpdo_reported = self.send_field(code, register, self._rpdo[2])

    @property
    def rpdo_error_active(self) -> int | None:
        """The EMCY code of the RPDO error episode now (None: none)."""
        return None if self._rpdo is None else self._rpdo[0]

    @property
    def over_range_active(self) -> bool:
        return self._over is not None

    def over_range(self, field: bytes | None) -> None:
        """Mapped readings began to saturate (``field``: the 5-byte manufacturer field naming the
        first, :func:`over_range_field`) or are all back in range (None): 0x1001 (bits 0 and 2)
        and 0x1003 updated, EMCY 0x3000 sent; its error reset (naming the over-range id) only
        after a reported one. A call while the state does not change does nothing (the rising
        edge only: readings that hover at the limit do not flood the bus)."""
        if field is None:
            if self._over is None:
                return
            self._over = None
            register = self._store_register()
            if self._over_reported:
                self._over_reported = not self.send_field(EMCY_NO_ERROR, register, OVER_RANGE_RESET_FIELD)
            return
        if self._over is not None:
            return
        self._over = bytes(field)
        register = self._store_register()
        self._push_history(EMCY_INPUT_OVER_RANGE | (FAULT_OVER_RANGE << 16))
        self._over_reported = self.send_field(EMCY_INPUT_OVER_RANGE, register, self._over)

    def resume(self) -> None:
        """The node can report again (PRE-OPERATIONAL / OPERATIONAL entered): send what the
        master has not been told — the EMCY of a fault that began while it could not
        report, or the error reset of a reported fault that cleared meanwhile; the EMCYs queued
        behind the inhibit time before it stopped go first (module docstring)."""
        self._restart_queue()
        if self._active is not None and not self._reported:
            self._reported = self.send(*self._active)
        elif self._active is None and self._reported:
            self._reported = not self.send(EMCY_NO_ERROR, self._register())
        if self._device is not None and not self._device_reported:
            self._device_reported = self.send(self._device[0], self._register())
        elif self._device is None and self._device_reported:
            self._device_reported = not self.send(EMCY_NO_ERROR, self._register())
        if self._comm_error and not self._comm_reported:
            self._comm_reported = self.send(EMCY_HEARTBEAT, self._register())
        elif not self._comm_error and self._comm_reported:
            self._comm_reported = not self.send(EMCY_NO_ERROR, self._register())
        if self._rpdo is not None and not self._rpdo_reported:
            self._rpdo_reported = self.send_field(self._rpdo[0], self._register(), self._rpdo[2])
        elif self._rpdo is None and self._rpdo_reported:
            self._rpdo_reported = not self.send(EMCY_NO_ERROR, self._register())
        if self._over is not None and not self._over_reported:
            self._over_reported = self.send_field(EMCY_INPUT_OVER_RANGE, self._register(), self._over)
        elif self._over is None and self._over_reported:
            self._over_reported = not self.send_field(EMCY_NO_ERROR, self._register(), OVER_RANGE_RESET_FIELD)

    def fault_changed(self, fault: int, reading: float) -> None:
        """The application's fault state became ``fault`` (``FAULT_NONE``: cleared) on
        ``reading``: update 0x1001/0x1003, send the EMCY (or the error reset)."""
        if fault == FAULT_NONE:
            self._active = None
            register = self._store_register()
            if self._reported:  # an error reset only follows a reported error
                self._reported = not self.send(EMCY_NO_ERROR, register)
            return
        code = FAULT_EMCY_CODE[fault]
        self._active = (code, ERR_REG_SENSOR_FAULT, fault, reading)
        register = self._store_register()
        self._push_history(code | (fault << 16))  # bits 16-31: manufacturer info (fault id)
        self._active = (code, register, fault, reading)
        self._reported = self.send(code, register, fault, reading)

    def send(self, code: int, register: int, fault_id: int = 0, reading: float = 0.0) -> bool:
        """Send an EMCY if the node may (see module docstring: now, or queued behind the inhibit
        time); True if it was sent or queued."""
        cob = self._may_send()
        if cob is None:
            return False
        # the REAL32 field: ±inf and anything beyond REAL32 as ±3.4e38, NaN as NaN
        r = reading if math.isnan(reading) or abs(reading) <= REAL32_MAX else math.copysign(3.4e38, reading)
        self._emit(cob, emcy_payload(code, register, fault_id, r))
        return True

    def send_field(self, code: int, register: int, field: bytes) -> bool:
        """:meth:`send` with a manufacturer field of its own (5 bytes)."""
        cob = self._may_send()
        if cob is None:
            return False
        self._emit(cob, struct.pack("<HB", code, register) + bytes(field[:5]).ljust(5, b"\0"))
        return True

    def _may_send(self) -> int | None:
        """The EMCY's CAN-ID when the node may send one (PRE-OPERATIONAL / OPERATIONAL, 0x1014
        valid), else None."""
        if self._nmt.state not in (PRE_OPERATIONAL, OPERATIONAL):
            return None
        cob = self._objects.read(COB_ID_EMCY)
        return None if cob & COB_INVALID else cob & 0x7FF

    def _inhibit_s(self) -> float:
        return self._objects.read(INHIBIT_TIME_EMCY) * 100e-6 if self._has_inhibit else 0.0

    def _emit(self, can_id: int, payload: bytes) -> None:
        """Send now, or queue behind the inhibit time 0x1015 (module docstring)."""
        inhibit = self._inhibit_s()
        now = time.monotonic()
        if self._queue or (inhibit > 0 and now < self._last_tx + inhibit):
            self._queue.append(payload)
            if self._timer is None:
                self._timer = self._scheduler.call_at(self._last_tx + inhibit, self._drain)
            return
        self._send(can_id, payload)
        self._last_tx = now

    def _drain(self) -> None:
        """The inhibit time is up: the oldest queued EMCY, the next one an inhibit time later."""
        self._timer = None
        if not self._queue:
            return
        cob = self._may_send()
        if cob is None:   # kept, counted as reported: sent on resume()
            return
        self._send(cob, self._queue.popleft())
        self._last_tx = now = time.monotonic()
        if self._queue:
            self._timer = self._scheduler.call_at(now + self._inhibit_s(), self._drain)

    def _restart_queue(self) -> None:
        """The EMCYs kept while the node could not send: sent from the inhibit time on."""
        if self._queue and self._timer is None and self._may_send() is not None:
            self._timer = self._scheduler.call_at(self._last_tx + self._inhibit_s(), self._drain)

    def _drop_queue(self) -> None:
        self._queue.clear()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    # -- SDO rules of 0x1003 and 0x1014
    def check_write(self, index: int, subindex: int, value, startup: bool) -> None:
        if index == ERROR_FIELD and subindex == 0 and value != 0:
            raise SdoAbortedError(ABORT_VALUE_RANGE)  # only 0 (clear history) may be written
        if index == COB_ID_EMCY and value & COB_29BIT:
            raise SdoAbortedError(ABORT_VALUE_RANGE)

    def written(self, index: int, subindex: int) -> None:
        if index == ERROR_FIELD and subindex == 0:  # 0 written: the history is cleared
            for sub in range(1, ERROR_HISTORY_LENGTH + 1):
                self._objects.discard(ERROR_FIELD, sub)
        elif index == COB_ID_EMCY and self._queue:
            # the hook runs before the value is stored: the queue restarts, if now valid, just after
            self._scheduler.call_later(0.0, self._restart_queue)
