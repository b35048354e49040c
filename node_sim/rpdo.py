"""RPDO engine (CiA 301): receive PDOs, applied on SYNC (synchronous) or at once (event-driven).

canopen 2.4.1's ``LocalNode`` has no RPDO behaviour (its PDO maps are the master's view), so this
is the node's own. Configuration per 0x1400.. (communication: sub 1 COB-ID, sub 2 transmission
type) and 0x1600.. (mapping), read from the OD when it changes, never per frame:

* received only in OPERATIONAL, only while valid (0x140x:1 bit 31 clear) and mapped;
* a frame shorter than the mapping is not processed: EMCY 0x8210 ("PDO not processed due to
  length error"); longer: the mapped bytes are used (CiA 301 allows either; no EMCY 0x8220);
* a mapped value the object's SDO rules refuse (``check(index, subindex, data)`` False: the EDS's
  LowLimit / HighLimit, the application's rules - a CiA 402 mode the drive does not support, a max
  torque beyond 0x6072's HighLimit) is not written: the object keeps its value, the PDO's other
  entries are written. A PDO cannot abort (CiA 301), so the node reports it: manufacturer-specific
  EMCY 0xFF10 ("RPDO value not applied"), its field the object's index (UNSIGNED16), subindex
  and the RPDO's number (1 = 0x1400);
* an error episode (:meth:`node_sim.emcy.EmcyProducer.rpdo_error`): the first short frame or
  refused value sends one EMCY with error register bits 0 and 4 (0x1001 holds them too while the
  episode lasts), the following ones none (``length_errors`` / ``value_errors`` count them: no
  EMCY flood at the PDO rate; the drive's EDS has no inhibit time 0x1015); the first RPDO of the
  right length whose every value is written ends it: the error-reset EMCY 0x0000;
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

import struct
from typing import Callable, Iterable

from .nmt import OPERATIONAL, NmtSlave
from .emcy import ERR_REG_COMMUNICATION
from .od import COB_INVALID, NodeObjects
from .pdo_rules import check_comm_write, check_map_write, mappable_bits

EMCY_PDO_LENGTH = 0x8210      # PDO not processed due to length error (CiA 301)
EMCY_PDO_VALUE = 0xFF10       # manufacturer-specific: an RPDO's value refused by its object's rules


class RpdoEngine:
    """The RPDOs of one node (see module docstring)."""

    def __init__(self, nmt: NmtSlave, objects: NodeObjects,
                 report: Callable[[int | None, int, bytes], None],
                 applied: Callable[[frozenset[int]], None], *, comm: Iterable[int] = (0x1400,),
                 mapping: Iterable[int] = (0x1600,), max_mapped: int = 8,
                 check: Callable[[int, int, bytes], bool] | None = None):
        """``report(code, register bits, field)``: an error episode begins (``code``) or ends
        (None) - :meth:`node_sim.emcy.EmcyProducer.rpdo_error`; ``check(index, subindex, data)``:
        False when the object's SDO rules refuse the value (None: every value written)."""
        self._nmt = nmt
        self._objects = objects
        self._report = report
        self._applied = applied
        self._check = check
        self.comm = tuple(comm)
        self.mapping = tuple(mapping)
        self.max_mapped = max_mapped
        self._cfg: list[tuple[bool, int, int, list[tuple[int, int, int]]]] | None = None
        self._by_cob: dict[int, int] = {}
        self._latched: dict[int, tuple[bytes, int]] = {}   # RPDO -> (data, the error count at its reception)
        self._errors = 0              # length and value errors so far (an episode ends only after the last)
        self.received = 0
        self.length_errors = 0
        self.value_errors = 0

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
            self._errors += 1
            self._report(EMCY_PDO_LENGTH, ERR_REG_COMMUNICATION, b"")
            return True
        self.received += 1
        if tt <= 240:
            self._latched[k] = (bytes(data[:length]), self._errors)
        else:
            self._write(k, entries, bytes(data[:length]), self._errors)
        return True

    def on_sync(self) -> None:
        """SYNC: write the synchronous RPDOs received since the last SYNC to the OD."""
        if not self._latched:
            return
        cfg = self._config()
        latched, self._latched = self._latched, {}
        for k, (data, errors) in sorted(latched.items()):
            self._write(k, cfg[k][3], data, errors)

    def _write(self, k: int, entries: list[tuple[int, int, int]], data: bytes, errors: int) -> None:
        """RPDO ``k``'s values to the OD, each one its object's rules accept (module docstring);
        ``errors``: the error count when it was received - a frame received before the last
        error (latched for the SYNC) does not end the error episode."""
        offset = 0
        written = set()
        refused = None
        for index, sub, bits in entries:
            n = bits // 8
            value = data[offset:offset + n]
            offset += n
            if self._check is not None and not self._check(index, sub, value):
                self.value_errors += 1
                if refused is None:
                    refused = struct.pack("<HBBB", index, sub, k + 1, 0)
                continue
            self._objects.store_raw(index, sub, value)
            written.add(index)
        if refused is not None:
            self._errors += 1
            self._report(EMCY_PDO_VALUE, ERR_REG_COMMUNICATION, refused)
        elif errors == self._errors:
            self._report(None, 0, b"")        # received after the last error, processed as sent: the episode ends
        if written:
            self._applied(frozenset(written))

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
