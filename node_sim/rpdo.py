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

SDO rules (checked for downloads and start-up values): :mod:`.pdo_rules`, the TPDOs' rules with
writable entries.
"""

from __future__ import annotations

from typing import Callable, Iterable

from .nmt import OPERATIONAL, NmtSlave
from .emcy import ERR_REG_COMMUNICATION
from .od import COB_INVALID, ERROR_REGISTER, NodeObjects
from .pdo_rules import check_comm_write, check_map_write, mappable_bits

EMCY_PDO_LENGTH = 0x8210      # PDO not processed due to length error


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
        if index in self.comm:
            check_comm_write(self._objects.read, index, subindex, value, startup)
        elif index in self.mapping:
            k = self.mapping.index(index)
            check_map_write(self._objects, self.comm[k], index, subindex, value, startup, self.max_mapped, 64,
                            lambda entry: mappable_bits(self._objects, entry, receive=True))
