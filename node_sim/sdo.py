"""SDO server of the taxel node twin (CiA 301): canopen's server behind CiA 301 checks.

Transfers: expedited and segmented uploads/downloads are canopen's ``SdoServer`` (of the
node's ``LocalNode``), answering through the node's send (so a silent node answers nothing).
Served in PRE-OPERATIONAL and OPERATIONAL only. Refused up front, where canopen's server
answers unlike a CiA 301 server:

* a sub-index other than 0 of a VAR object: 0x06090011 (canopen serves the VAR);
* a block upload the client did not allow to fall back to a normal upload (protocol switch
  threshold 0 or below the object's size): 0x05040001 (this node has no block transfer;
  canopen answers with a normal upload anyway).

Writes (SDO download, and the node's start-up values): before a value is stored,
:meth:`SdoServer.check_write` applies the checks every object gets — size of a numeric type
(0x06070010), REAL32 finite (0x06090030) and within the EDS ``LowLimit``/``HighLimit``
(0x06090032 / 0x06090031, read by :func:`node_sim.od.real_limits`), integer ``LowLimit`` /
``HighLimit`` of the EDS — then the object's own rules, registered by the service that owns
the object (:meth:`SdoServer.add_check`: 0x1003/0x1014 EMCY, 0x1005 SYNC, 0x180x/0x1A0x
TPDOs, 0x2001:3 the detector). A refused write raises ``SdoAbortedError`` with the CiA 301
abort code, which canopen's server sends. Side effects of a stored value (restart the
heartbeat, reconfigure the TPDOs, re-read the detector parameters, clear the error history)
are the owners' ``written`` hooks (:meth:`SdoServer.add_written`), called right before
canopen stores the value.
"""

from __future__ import annotations

import math
import struct
from typing import Callable, Iterable

from canopen.objectdictionary import ODVariable, datatypes
from canopen.sdo import SdoAbortedError

from .nmt import OPERATIONAL, PRE_OPERATIONAL, NmtSlave
from .od import NodeObjects

# SDO client command specifiers (CiA 301, bits 5-7 of byte 0) and the server's abort
SDO_CCS_DOWNLOAD = 0x20
SDO_CCS_UPLOAD = 0x40
SDO_CCS_BLOCK_UPLOAD = 0xA0
SDO_ABORT = 0x80

# SDO abort codes (CiA 301) used by the range checks
ABORT_COMMAND_SPECIFIER = 0x05040001
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_READ_ONLY = 0x06010002
ABORT_NOT_IN_OD = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH_EXCEEDED = 0x06040042
ABORT_LENGTH_MISMATCH = 0x06070010
ABORT_SUBINDEX_NOT_IN_OD = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_VALUE_TOO_HIGH = 0x06090031
ABORT_VALUE_TOO_LOW = 0x06090032

SDO_TX_BASE = 0x580  # server -> client: 0x580 + node-ID
SDO_RX_BASE = 0x600  # client -> server: 0x600 + node-ID

# check(index, subindex, decoded value, startup) raises SdoAbortedError; written(index, subindex)
Check = Callable[[int, int, object, bool], None]
Written = Callable[[int, int], None]


class _SdoLink:
    """The ``network`` canopen's SdoServer answers through: the node's (gated) send."""

    def __init__(self, send: Callable[[int, bytes], None]):
        self._send = send

    def send_message(self, can_id: int, data, remote: bool = False) -> None:
        self._send(can_id, bytes(data))


class SdoServer:
    """The SDO server of one node (see module docstring): owns the object rules."""

    def __init__(self, node_id: int, nmt: NmtSlave, objects: NodeObjects, send: Callable[[int, bytes], None]):
        self.node_id = node_id
        self._nmt = nmt
        self._objects = objects
        self._od = objects.od
        self._local = objects.local
        self._send = send
        self._checks: dict[int, Check] = {}
        self._written: dict[int | None, list[Written]] = {}
        self._local.sdo.network = _SdoLink(send)
        self._local.add_write_callback(self._on_download)

    # ------------------------------------------------------------------ object rules
    def add_check(self, indexes: Iterable[int], check: Check) -> None:
        """``check`` is the rule of the objects ``indexes`` (one owner per object)."""
        for index in indexes:
            if index in self._checks:
                raise ValueError(f"0x{index:04X} already has a check")
            self._checks[index] = check

    def add_written(self, indexes: Iterable[int] | None, written: Written) -> None:
        """Call ``written(index, subindex)`` after an accepted SDO download to one of
        ``indexes`` (None: to any object)."""
        for index in (None,) if indexes is None else indexes:
            self._written.setdefault(index, []).append(written)

    # ------------------------------------------------------------------ requests
    def on_request(self, data: bytes) -> None:
        """An SDO request frame (8 bytes) from the client."""
        if self._nmt.state not in (PRE_OPERATIONAL, OPERATIONAL):
            return
        refusal = self.refusal(data)
        if refusal is not None:
            index, subindex = struct.unpack_from("<HB", data, 1)
            self._send(SDO_TX_BASE + self.node_id, struct.pack("<BHBL", SDO_ABORT, index, subindex, refusal))
            return
        self._local.sdo.on_request(SDO_RX_BASE + self.node_id, data, 0.0)

    def refusal(self, data: bytes) -> int | None:
        """Abort code for the initiate requests canopen's SdoServer answers unlike a CiA 301
        server: a sub-index other than 0 of a VAR object (it serves the VAR instead of
        0x06090011) and a block upload the client did not allow to fall back to a normal
        upload (protocol switch threshold 0 or below the object's size: it answers with a
        normal upload anyway instead of 0x05040001; this node has no block transfer)."""
        ccs = data[0] & 0xE0
        initiate = ccs in (SDO_CCS_DOWNLOAD, SDO_CCS_UPLOAD) or \
            (ccs == SDO_CCS_BLOCK_UPLOAD and data[0] & 0x03 == 0)
        if not initiate:
            return None
        index, subindex = struct.unpack_from("<HB", data, 1)
        obj = self._od.get(index)
        if isinstance(obj, ODVariable) and subindex != 0:
            return ABORT_SUBINDEX_NOT_IN_OD
        if ccs == SDO_CCS_BLOCK_UPLOAD and obj is not None:
            protocol_switch_threshold = data[5]
            try:
                size = len(self._local.get_data(index, subindex))
            except KeyError:
                return None  # canopen answers 0x06020000 / 0x06090011
            if size > protocol_switch_threshold:
                return ABORT_COMMAND_SPECIFIER
        return None

    # ------------------------------------------------------------------ writes
    def _on_download(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        """LocalNode write callback (runs before the value is stored): the checks raise
        SdoAbortedError with the CiA 301 abort code; then the owners' side effects."""
        self.check_write(index, subindex, od, bytes(data), startup=False)
        for written in self._written.get(None, ()):
            written(index, subindex)
        for written in self._written.get(index, ()):
            written(index, subindex)

    def check_write(self, index: int, subindex: int, var: ODVariable, data: bytes, startup: bool) -> None:
        """Raise SdoAbortedError unless ``data`` may be written to ``index:subindex``
        (``startup``: a start-up value written before boot, not an SDO download)."""
        if var.data_type in datatypes.NUMBER_TYPES and 8 * len(data) != len(var):
            raise SdoAbortedError(ABORT_LENGTH_MISMATCH)
        value = var.decode_raw(data)
        if var.data_type in datatypes.FLOAT_TYPES:
            if not math.isfinite(value):
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            low, high = self._objects.real_limits.get((index, subindex), (-math.inf, math.inf))
            if value < low:
                raise SdoAbortedError(ABORT_VALUE_TOO_LOW)
            if value > high:
                raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
        elif isinstance(value, int):
            if var.min is not None and value < var.min:
                raise SdoAbortedError(ABORT_VALUE_TOO_LOW)
            if var.max is not None and value > var.max:
                raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
        check = self._checks.get(index)
        if check is not None:
            check(index, subindex, value, startup)
