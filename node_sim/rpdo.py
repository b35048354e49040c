"""RPDO engine (CiA 301): receive PDOs, applied on SYNC (synchronous) or at once (event-driven).

canopen 2.4.1's ``LocalNode`` has no RPDO behaviour (its PDO maps are the master's view), so this
is the node's own. Configuration per 0x1400.. (communication: sub 1 COB-ID, sub 2 transmission
type) and 0x1600.. (mapping), read from the OD when it changes, never per frame:

* received only in OPERATIONAL, only while valid (0x140x:1 bit 31 clear) and mapped;
* a frame shorter than the mapping is not processed: EMCY 0x8210 ("PDO not processed due to
  length error"); longer: the mapped bytes are used (CiA 301 allows either; no EMCY 0x8220);
* synchronous (transmission type 0..240): the data of the last frame received are latched and
  written to the OD at the next SYNC (:meth:`RpdoEngine.on_sync`, before the application steps);
  only a frame received since the previous SYNC is applied, so a master that falls silent
  leaves the OD as it last wrote it;
* event-driven (254/255): written to the OD at once;
* after writing, ``applied(indexes)`` tells the application which objects a PDO wrote.

SDO rules (checked for downloads and start-up values): COB-ID 29-bit refused and its CAN-ID
changed only while the RPDO is not valid; transmission types 241-253 refused; mapping only while
not valid, entries only while sub 0 is 0, each entry an existing, writable, PDO-mappable object of
exactly its size, at most ``max_mapped`` entries and 64 bits.
"""

from __future__ import annotations

from typing import Callable, Iterable

from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError

from .nmt import OPERATIONAL, NmtSlave
from .od import COB_29BIT, COB_INVALID, ERROR_REGISTER, NodeObjects
from .sdo import ABORT_NOT_MAPPABLE, ABORT_PDO_LENGTH_EXCEEDED, ABORT_UNSUPPORTED_ACCESS, ABORT_VALUE_RANGE

EMCY_PDO_LENGTH = 0x8210      # PDO not processed due to length error
ERR_REG_COMMUNICATION = 0x10


class RpdoEngine:
    """The RPDOs of one node (see module docstring)."""

    def __init__(self, nmt: NmtSlave, objects: NodeObjects, send_emcy: Callable[[int, int], bool],
                 applied: Callable[[frozenset[int]], None], *, comm: Iterable[int] = (0x1400,),
                 mapping: Iterable[int] = (0x1600,), max_mapped: int = 8):
        self._nmt = nmt
        self._objects = objects
        self._send_emcy = send_emcy
        self._applied = applied
        self.comm = tuple(comm)
        self.mapping = tuple(mapping)
        self.max_mapped = max_mapped
        self._cfg: list[tuple[bool, int, int, list[tuple[int, int, int]]]] | None = None
        self._by_cob: dict[int, int] = {}
        self._latched: dict[int, bytes] = {}
        self.received = 0
        self.length_errors = 0

    # -- configuration
    def _config(self) -> list[tuple[bool, int, int, list[tuple[int, int, int]]]]:
        if self._cfg is None:
            read = self._objects.read
            cfg = []
            for comm, mapping in zip(self.comm, self.mapping):
                cob = read(comm, 1)
                entries = []
                for sub in range(1, read(mapping, 0) + 1):
                    e = read(mapping, sub)
                    entries.append((e >> 16, (e >> 8) & 0xFF, e & 0xFF))
                cfg.append((not cob & COB_INVALID, cob & 0x7FF, read(comm, 2), entries))
            self._cfg = cfg
            self._by_cob = {can_id: k for k, (valid, can_id, _, entries) in enumerate(cfg) if valid and entries}
        return self._cfg

    @property
    def cob_ids(self) -> frozenset[int]:
        """The CAN-IDs of the valid, mapped RPDOs."""
        self._config()
        return frozenset(self._by_cob)

    def invalidate(self) -> None:
        self._cfg = None

    def reset(self) -> None:
        """Boot, leaving OPERATIONAL: latched data forgotten, configuration re-read."""
        self._latched.clear()
        self.invalidate()

    # -- frames
    def on_rpdo(self, can_id: int, data: bytes) -> bool:
        """A frame on ``can_id``; True if it is one of this node's RPDOs (processed or not)."""
        cfg = self._config()
        k = self._by_cob.get(can_id)
        if k is None:
            return False
        if self._nmt.state != OPERATIONAL:
            return True
        _, _, tt, entries = cfg[k]
        length = sum(bits for _, _, bits in entries) // 8
        if len(data) < length:
            self.length_errors += 1
            self._send_emcy(EMCY_PDO_LENGTH, self._objects.read(ERROR_REGISTER) | 0x01 | ERR_REG_COMMUNICATION)
            return True
        self.received += 1
        if tt <= 240:
            self._latched[k] = bytes(data[:length])
        else:
            self._write(entries, bytes(data[:length]))
        return True

    def on_sync(self) -> None:
        """SYNC: write the synchronous RPDOs received since the last SYNC to the OD."""
        if not self._latched:
            return
        cfg = self._config()
        latched, self._latched = self._latched, {}
        for k, data in sorted(latched.items()):
            self._write(cfg[k][3], data)

    def _write(self, entries: list[tuple[int, int, int]], data: bytes) -> None:
        offset = 0
        for index, sub, bits in entries:
            n = bits // 8
            self._objects.store_raw(index, sub, data[offset:offset + n])
            offset += n
        self._applied(frozenset(index for index, _, _ in entries))

    # -- SDO rules
    def written(self, index: int, subindex: int) -> None:
        self.invalidate()

    def check_write(self, index: int, subindex: int, value, startup: bool) -> None:
        read = self._objects.read
        if index in self.comm:
            comm = index
            valid_now = not read(comm, 1) & COB_INVALID
            if subindex == 1:
                if value & COB_29BIT:
                    raise SdoAbortedError(ABORT_VALUE_RANGE)
                if not startup and valid_now and not value & COB_INVALID and (value & 0x7FF) != (read(comm, 1) & 0x7FF):
                    raise SdoAbortedError(ABORT_VALUE_RANGE)
            elif subindex == 2 and 240 < value < 254:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            return
        k = self.mapping.index(index)
        if not startup and not read(self.comm[k], 1) & COB_INVALID:
            raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)      # CiA 301: map only while not valid
        if subindex == 0:
            if value > self.max_mapped:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            entries = [read(index, s) for s in range(1, value + 1)]
            if sum(e & 0xFF for e in entries) > 64:
                raise SdoAbortedError(ABORT_PDO_LENGTH_EXCEEDED)
            for e in entries:
                self._check_entry(e)
            return
        if not startup and read(index, 0) != 0:
            raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)      # entries only while sub 0 is 0
        if value:
            self._check_entry(value)

    def _check_entry(self, entry: int) -> None:
        index, sub, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        obj = self._objects.od.get(index)
        if obj is None:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        if isinstance(obj, ODVariable):
            var = obj if sub == 0 else None
        else:
            var = obj[sub] if sub in obj else None
        if var is None or not var.pdo_mappable or not var.writable or len(var) != bits:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
