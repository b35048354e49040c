"""SDO server of the taxel node twin (CiA 301 §7.2.4), on canopen's ``LocalNode`` data store.

The protocol is the node's own (canopen 2.4.1's ``SdoServer`` refuses an expedited download
without size indication, echoes the previous transfer's multiplexer in its aborts, checks
access only after the last segment of a download and has no server timeout); canopen's
``LocalNode`` stays the object dictionary and data store (``get_data`` / ``set_data``).
Served in PRE-OPERATIONAL and OPERATIONAL only; every answer goes through the node's send
(a silent node answers nothing). One transfer at a time, as on any CiA 301 server:

* **expedited upload** (object ≤ 4 bytes, size indicated) and **segmented upload** (size
  indicated in the initiate response, 7-byte segments, toggle bit);
* **expedited download** with size indication (``n`` unused bytes) and without it (command
  0x22: the object's own size for a numeric type, else the 4 bytes); **segmented download**
  with or without size indication;
* **checked at initiate**: object (0x06020000), sub-index (0x06090011, also a sub-index other
  than 0 of a VAR), access (upload of a write-only object 0x06010001, download to a read-only
  or const one 0x06010002), the indicated size of a numeric type (0x06070010); the value
  itself when the data are complete (below);
* **aborts echo the request's multiplexer** (index, sub-index of the initiate being answered,
  of the transfer in progress for a segment); a segment with no transfer in progress or an
  unknown / reserved command specifier → 0x05040001; toggle bit not alternated → 0x05030000;
  more segment data than indicated or than :data:`MAX_SEGMENTED_SIZE` → 0x06070010 /
  0x05040005; an abort from the client ends the transfer silently; a new initiate replaces
  the transfer in progress;
* **server timeout**: a segmented transfer idle for :attr:`SdoServer.timeout_s` (default 1 s,
  as CANopenNode's) is aborted with 0x05040000, on the node's scheduler;
* **block transfer** is not implemented: block download 0x05040001, block upload 0x05040001
  unless the client allows the CiA 301 protocol switch (size ≤ its threshold), then it gets a
  normal upload.

Writes (SDO download, and the node's start-up values): before a value is stored,
:meth:`SdoServer.check_write` applies the checks every object gets — size of a numeric type
(0x06070010), REAL32 finite (0x06090030) and within the EDS ``LowLimit``/``HighLimit``
(0x06090032 / 0x06090031, read by :func:`node_sim.od.real_limits`), integer ``LowLimit`` /
``HighLimit`` of the EDS — then the object's own rules, registered by the service that owns
the object (:meth:`SdoServer.add_check`: 0x1003/0x1014 EMCY, 0x1005/0x1019 SYNC, 0x180x/0x1A0x
TPDOs, 0x2001:3 the detector). A refused write raises ``SdoAbortedError`` with the CiA 301
abort code, which the server sends. Side effects of a stored value (restart the heartbeat,
reconfigure the TPDOs, re-read the detector parameters, clear the error history) are the
owners' ``written`` hooks (:meth:`SdoServer.add_written`), called right before the value is
stored. Nothing of this runs per SYNC.
"""

from __future__ import annotations

import logging
import math
import struct
from typing import Callable, Iterable

from canopen.objectdictionary import ODVariable, datatypes
from canopen.sdo import SdoAbortedError

from .nmt import OPERATIONAL, PRE_OPERATIONAL, NmtSlave
from .od import NodeObjects

logger = logging.getLogger(__name__)

# SDO client command specifiers (CiA 301, bits 5-7 of byte 0)
SDO_CCS_SEGMENT_DOWNLOAD = 0x00
SDO_CCS_DOWNLOAD = 0x20
SDO_CCS_UPLOAD = 0x40
SDO_CCS_SEGMENT_UPLOAD = 0x60
SDO_ABORT = 0x80
SDO_CCS_BLOCK_UPLOAD = 0xA0
SDO_CCS_BLOCK_DOWNLOAD = 0xC0
SDO_CCS_RESERVED = 0xE0       # answered like an initiate: 0x05040001 with bytes 1-3 echoed
# server command specifiers
SDO_SCS_SEGMENT_UPLOAD = 0x00
SDO_SCS_SEGMENT_DOWNLOAD = 0x20
SDO_SCS_UPLOAD = 0x40
SDO_SCS_DOWNLOAD = 0x60
SDO_EXPEDITED = 0x02
SDO_SIZE_INDICATED = 0x01
SDO_TOGGLE = 0x10
SDO_LAST_SEGMENT = 0x01

# SDO abort codes (CiA 301)
ABORT_TOGGLE = 0x05030000
ABORT_TIMEOUT = 0x05040000
ABORT_COMMAND_SPECIFIER = 0x05040001
ABORT_OUT_OF_MEMORY = 0x05040005
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NOT_IN_OD = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH_EXCEEDED = 0x06040042
ABORT_LENGTH_MISMATCH = 0x06070010
ABORT_SUBINDEX_NOT_IN_OD = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_VALUE_TOO_HIGH = 0x06090031
ABORT_VALUE_TOO_LOW = 0x06090032
ABORT_GENERAL = 0x08000000
ABORT_NO_DATA = 0x08000024

SDO_TX_BASE = 0x580  # server -> client: 0x580 + node-ID
SDO_RX_BASE = 0x600  # client -> server: 0x600 + node-ID

DEFAULT_TIMEOUT_S = 1.0       # server timeout of a segmented transfer (CANopenNode's default)
MAX_SEGMENTED_SIZE = 1024     # largest segmented download accepted without size indication

_MUX = struct.Struct("<HB")
_ABORT = struct.Struct("<BHBL")

# check(index, subindex, decoded value, startup) raises SdoAbortedError; written(index, subindex)
Check = Callable[[int, int, object, bool], None]
Written = Callable[[int, int], None]


class _Transfer:
    """A segmented transfer in progress."""

    __slots__ = ("upload", "index", "subindex", "data", "size", "toggle", "timer")

    def __init__(self, upload: bool, index: int, subindex: int, data: bytearray, size: int | None):
        self.upload = upload
        self.index = index
        self.subindex = subindex
        self.data = data          # upload: what is left to send; download: what was received
        self.size = size          # download: the indicated size (None: not indicated)
        self.toggle = 0
        self.timer = None


class SdoServer:
    """The SDO server of one node (see module docstring): owns the object rules.

    ``scheduler`` (the channel's :class:`node_sim.link.Scheduler`) runs the server timeout;
    without one there is none. ``timeout_s``: the server timeout (0 or None: none).
    """

    def __init__(self, node_id: int, nmt: NmtSlave, objects: NodeObjects, send: Callable[[int, bytes], None],
                 scheduler=None, timeout_s: float | None = DEFAULT_TIMEOUT_S):
        self.node_id = node_id
        self._nmt = nmt
        self._objects = objects
        self._od = objects.od
        self._send = send
        self._tx = SDO_TX_BASE + node_id
        self._scheduler = scheduler
        self.timeout_s = timeout_s
        self._transfer: _Transfer | None = None
        self._checks: dict[int, Check] = {}
        self._written: dict[int | None, list[Written]] = {}
        self._local.add_write_callback(self._on_download)

    @property
    def _local(self):
        return self._objects.local

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
    def reset(self) -> None:
        """Forget the transfer in progress (NMT boot, stop, shutdown): no answer, no timeout."""
        transfer, self._transfer = self._transfer, None
        if transfer is not None and transfer.timer is not None:
            transfer.timer.cancel()

    @property
    def busy(self) -> bool:
        """A segmented transfer is in progress."""
        return self._transfer is not None

    def on_request(self, data: bytes) -> None:
        """An SDO request frame (8 bytes) from the client."""
        if self._nmt.state not in (PRE_OPERATIONAL, OPERATIONAL):
            return
        if len(data) != 8:  # CiA 301: an SDO frame has 8 data bytes; anything else is ignored
            return
        command = data[0]
        ccs = command & 0xE0
        if ccs in (SDO_CCS_DOWNLOAD, SDO_CCS_UPLOAD, SDO_CCS_BLOCK_UPLOAD, SDO_CCS_BLOCK_DOWNLOAD, SDO_CCS_RESERVED):
            self.reset()  # an initiate replaces the transfer in progress
            index, subindex = _MUX.unpack_from(data, 1)
            try:
                if ccs == SDO_CCS_DOWNLOAD:
                    self._initiate_download(command, index, subindex, data)
                elif ccs == SDO_CCS_UPLOAD:
                    self._initiate_upload(index, subindex, SDO_SCS_UPLOAD)
                elif ccs == SDO_CCS_BLOCK_UPLOAD and command & 0x03 == 0:
                    self._initiate_block_upload(index, subindex, data[5])
                else:  # block download, reserved sub-commands of block upload, ccs 7
                    raise SdoAbortedError(ABORT_COMMAND_SPECIFIER)
            except SdoAbortedError as exc:
                self.reset()
                self._abort(index, subindex, exc.code)
            except Exception:  # a bug in a check must not kill the channel: general error
                logger.exception("node %d: SDO request %s failed", self.node_id, data.hex())
                self.reset()
                self._abort(index, subindex, ABORT_GENERAL)
            return
        if ccs == SDO_ABORT:
            self.reset()  # the client aborted: no answer (CiA 301)
            return
        transfer = self._transfer
        if transfer is None or ccs not in (SDO_CCS_SEGMENT_DOWNLOAD, SDO_CCS_SEGMENT_UPLOAD) or \
                transfer.upload != (ccs == SDO_CCS_SEGMENT_UPLOAD):
            index, subindex = (transfer.index, transfer.subindex) if transfer is not None else (0, 0)
            self.reset()
            self._abort(index, subindex, ABORT_COMMAND_SPECIFIER)
            return
        try:
            if command & SDO_TOGGLE != transfer.toggle:
                raise SdoAbortedError(ABORT_TOGGLE)
            if transfer.upload:
                self._upload_segment(transfer)
            else:
                self._download_segment(transfer, command, data)
        except SdoAbortedError as exc:
            self.reset()
            self._abort(transfer.index, transfer.subindex, exc.code)
        except Exception:
            logger.exception("node %d: SDO segment %s failed", self.node_id, data.hex())
            self.reset()
            self._abort(transfer.index, transfer.subindex, ABORT_GENERAL)

    def _abort(self, index: int, subindex: int, code: int) -> None:
        self._send(self._tx, _ABORT.pack(SDO_ABORT, index, subindex, code))

    def _variable(self, index: int, subindex: int) -> ODVariable:
        obj = self._od.get(index)
        if obj is None:
            raise SdoAbortedError(ABORT_NOT_IN_OD)
        if isinstance(obj, ODVariable):
            if subindex != 0:
                raise SdoAbortedError(ABORT_SUBINDEX_NOT_IN_OD)
            return obj
        if subindex not in obj:
            raise SdoAbortedError(ABORT_SUBINDEX_NOT_IN_OD)
        return obj[subindex]

    def _start(self, transfer: _Transfer) -> None:
        self._transfer = transfer
        self._arm(transfer)

    def _arm(self, transfer: _Transfer) -> None:
        """(Re)start the server timeout of ``transfer``."""
        if transfer.timer is not None:
            transfer.timer.cancel()
            transfer.timer = None
        if self._scheduler is not None and self.timeout_s:
            def expired():
                if self._transfer is transfer:
                    self._transfer = None
                    if self._nmt.state in (PRE_OPERATIONAL, OPERATIONAL):
                        self._abort(transfer.index, transfer.subindex, ABORT_TIMEOUT)
            transfer.timer = self._scheduler.call_later(self.timeout_s, expired)

    # -- upload
    def _initiate_upload(self, index: int, subindex: int, scs: int) -> None:
        var = self._variable(index, subindex)
        if not var.readable:
            raise SdoAbortedError(ABORT_WRITE_ONLY)
        data = bytes(self._local.get_data(index, subindex))
        size = len(data)
        if size == 0:
            raise SdoAbortedError(ABORT_NO_DATA)
        if size <= 4:
            command = scs | SDO_EXPEDITED | SDO_SIZE_INDICATED | ((4 - size) << 2)
            self._send(self._tx, struct.pack("<BHB", command, index, subindex) + data.ljust(4, b"\0"))
            return
        self._send(self._tx, struct.pack("<BHBL", scs | SDO_SIZE_INDICATED, index, subindex, size))
        self._start(_Transfer(True, index, subindex, bytearray(data), size))

    def _upload_segment(self, transfer: _Transfer) -> None:
        chunk = bytes(transfer.data[:7])
        del transfer.data[:7]
        command = SDO_SCS_SEGMENT_UPLOAD | transfer.toggle | ((7 - len(chunk)) << 1)
        transfer.toggle ^= SDO_TOGGLE
        if not transfer.data:
            command |= SDO_LAST_SEGMENT
            self.reset()
        else:
            self._arm(transfer)
        self._send(self._tx, bytes([command]) + chunk.ljust(7, b"\0"))

    def _initiate_block_upload(self, index: int, subindex: int, protocol_switch_threshold: int) -> None:
        var = self._variable(index, subindex)
        if not var.readable:
            raise SdoAbortedError(ABORT_WRITE_ONLY)
        size = len(self._local.get_data(index, subindex))
        if size > protocol_switch_threshold:
            raise SdoAbortedError(ABORT_COMMAND_SPECIFIER)  # no block transfer
        self._initiate_upload(index, subindex, SDO_SCS_UPLOAD)  # CiA 301 protocol switch

    # -- download
    def _initiate_download(self, command: int, index: int, subindex: int, data: bytes) -> None:
        var = self._variable(index, subindex)
        if not var.writable:
            raise SdoAbortedError(ABORT_READ_ONLY)
        numeric = var.data_type in datatypes.NUMBER_TYPES
        if command & SDO_EXPEDITED:
            if command & SDO_SIZE_INDICATED:
                value = data[4:8 - ((command >> 2) & 0x3)]
            elif numeric and len(var) // 8 <= 4:
                value = data[4:4 + len(var) // 8]   # no size indicated: the object's size
            else:
                value = data[4:8]
            self._local.set_data(index, subindex, value)
            self._send(self._tx, struct.pack("<BHBL", SDO_SCS_DOWNLOAD, index, subindex, 0))
            return
        size = struct.unpack_from("<L", data, 4)[0] if command & SDO_SIZE_INDICATED else None
        if size is not None and numeric and 8 * size != len(var):
            raise SdoAbortedError(ABORT_LENGTH_MISMATCH)
        if size is not None and size > MAX_SEGMENTED_SIZE:
            raise SdoAbortedError(ABORT_OUT_OF_MEMORY)
        self._send(self._tx, struct.pack("<BHBL", SDO_SCS_DOWNLOAD, index, subindex, 0))
        self._start(_Transfer(False, index, subindex, bytearray(), size))

    def _download_segment(self, transfer: _Transfer, command: int, data: bytes) -> None:
        transfer.data += data[1:8 - ((command >> 1) & 0x7)]
        limit = transfer.size if transfer.size is not None else MAX_SEGMENTED_SIZE
        if len(transfer.data) > limit:
            raise SdoAbortedError(ABORT_LENGTH_MISMATCH if transfer.size is not None else ABORT_OUT_OF_MEMORY)
        response = bytes([SDO_SCS_SEGMENT_DOWNLOAD | transfer.toggle]) + bytes(7)
        transfer.toggle ^= SDO_TOGGLE
        if command & SDO_LAST_SEGMENT:
            if transfer.size is not None and len(transfer.data) != transfer.size:
                raise SdoAbortedError(ABORT_LENGTH_MISMATCH)
            self.reset()
            self._local.set_data(transfer.index, transfer.subindex, bytes(transfer.data))
        else:
            self._arm(transfer)
        self._send(self._tx, response)

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
