"""The SDO rules of PDO communication and mapping parameters (CiA 301), one copy for TPDOs
(:mod:`.pdo`, 0x180x/0x1A0x) and RPDOs (:mod:`.rpdo`, 0x140x/0x160x):

* communication, sub 1 (COB-ID): 29-bit refused; the CAN-ID changed only while the PDO is not
  valid (bit 31); sub 2 (transmission type): 0-240, 254, 255 (241-251 reserved, 252/253 RTR only,
  unsupported); for TPDOs sub 3 (inhibit time) and sub 6 (SYNC start value) only while not valid;
* mapping: only while the PDO is not valid; entries only while sub 0 is 0; sub 0 at most the
  record's entries (0x06090031 value too high) and the entries at most the PDO's bits
  (0x06040042); each entry an existing, PDO-mappable object of exactly its size, readable for a
  TPDO, writable for an RPDO (0x06040041).

``read(index, subindex)`` reads the node's OD (:meth:`node_sim.od.NodeObjects.read`);
violations raise canopen's :class:`~canopen.sdo.SdoAbortedError` with the CiA 301 code."""

from __future__ import annotations

from typing import Callable

import canopen
from canopen.sdo import SdoAbortedError

from .od import COB_29BIT, COB_INVALID, NodeObjects
from .sdo import (ABORT_NOT_MAPPABLE, ABORT_PDO_LENGTH_EXCEEDED, ABORT_UNSUPPORTED_ACCESS, ABORT_VALUE_RANGE,
                  ABORT_VALUE_TOO_HIGH)

TPDO_LOCKED_WHILE_VALID = (3, 6)  # inhibit time, SYNC start value


def check_comm_write(read: Callable[[int, int], int], comm: int, subindex: int, value: int, startup: bool,
                     locked_while_valid: tuple[int, ...] = ()) -> None:
    """A write of ``value`` to communication parameter ``comm``:``subindex`` (module docstring)."""
    valid_now = not (read(comm, 1) & COB_INVALID)
    if subindex == 1:
        if value & COB_29BIT:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if not startup and valid_now and not (value & COB_INVALID) and (value & 0x7FF) != (read(comm, 1) & 0x7FF):
            raise SdoAbortedError(ABORT_VALUE_RANGE)  # CAN-ID changes only while not valid
    elif subindex == 2:
        if not (value <= 240 or value in (254, 255)):
            raise SdoAbortedError(ABORT_VALUE_RANGE)  # 241-251 reserved, 252/253 RTR-only unsupported
    elif subindex in locked_while_valid:
        if not startup and valid_now:
            raise SdoAbortedError(ABORT_VALUE_RANGE)  # CiA 301: not while the PDO is valid


def check_map_write(objects: NodeObjects, comm: int, mapping: int, subindex: int, value: int, startup: bool,
                    max_mapped: int, max_bits: int, check_entry: Callable[[int], int]) -> None:
    """A write of ``value`` to mapping parameter ``mapping``:``subindex`` of the PDO whose
    communication parameter is ``comm``; ``check_entry(entry) -> bits`` checks one entry."""
    read = objects.read
    if not startup and not (read(comm, 1) & COB_INVALID):
        raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)  # mapping only while the PDO is not valid
    if subindex == 0:
        if value > max_mapped:
            raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
        bits = sum(check_entry(read(mapping, sub)) for sub in range(1, value + 1))
        if bits > max_bits:
            raise SdoAbortedError(ABORT_PDO_LENGTH_EXCEEDED)
    else:
        if not startup and read(mapping, 0) != 0:
            raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)  # CiA 301: set sub 0 to 0 first
        if value != 0:
            check_entry(value)


def mappable_bits(objects: NodeObjects, entry: int, *, receive: bool) -> int:
    """The bits of mapping ``entry`` (index << 16 | subindex << 8 | bits), or
    :class:`SdoAbortedError` 0x06040041: no such object, not PDO-mappable, another size, not
    readable (a TPDO's) or not writable (an RPDO's, ``receive``)."""
    index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
    od = objects.od
    try:
        var = objects.variable(index, subindex)
        if isinstance(od[index], (canopen.objectdictionary.ODRecord, canopen.objectdictionary.ODArray)) \
                and subindex not in od[index]:
            raise KeyError(subindex)
    except KeyError:
        raise SdoAbortedError(ABORT_NOT_MAPPABLE) from None
    if not var.pdo_mappable or bits != len(var) or not (var.writable if receive else var.readable):
        raise SdoAbortedError(ABORT_NOT_MAPPABLE)
    return bits
