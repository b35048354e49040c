"""EMCY codes and frame layout of the taxel node (CiA 301 emergency object).

Frame (COB-ID from 0x1014, default 0x80 + node-ID), 8 bytes little-endian:
``error code (UNSIGNED16) | error register 0x1001 (UNSIGNED8) | manufacturer field (5 bytes)``.
The taxel node's manufacturer field is ``fault id (UNSIGNED8) | offending reading (REAL32 mV)``.

Codes (CiA 301 error-code classes):

* ``0x0000`` error reset / no error — sent when the last active fault clears;
* ``0x5000`` device hardware — open circuit: the reading is not finite or |X| ≥ full scale
  (0x2002:1); an open bridge/input stage reads at the rail or produces no conversion;
* ``0x7300`` sensor — stuck reading: M (0x2002:2) consecutive identical raw samples
  (the code CiA 402/404-style devices use for a sensor fault).

Error register bits set on a fault: bit 0 (generic error, mandatory whenever any error is
active) and bit 5 (device-profile specific).
"""

from __future__ import annotations

import struct

EMCY_NO_ERROR = 0x0000
EMCY_OPEN_CIRCUIT = 0x5000
EMCY_STUCK = 0x7300

FAULT_NONE = 0
FAULT_STUCK = 1
FAULT_OPEN_CIRCUIT = 2
FAULT_NAMES = {FAULT_NONE: "none", FAULT_STUCK: "stuck", FAULT_OPEN_CIRCUIT: "open_circuit"}
FAULT_EMCY_CODE = {FAULT_STUCK: EMCY_STUCK, FAULT_OPEN_CIRCUIT: EMCY_OPEN_CIRCUIT}

ERR_REG_GENERIC = 0x01
ERR_REG_PROFILE = 0x20
ERR_REG_SENSOR_FAULT = ERR_REG_GENERIC | ERR_REG_PROFILE

EMCY_STRUCT = struct.Struct("<HBBf")  # code, error register, fault id, reading (REAL32)


def emcy_payload(code: int, error_register: int, fault_id: int = 0, reading: float = 0.0) -> bytes:
    """The 8 data bytes of an EMCY frame."""
    return EMCY_STRUCT.pack(code, error_register, fault_id, reading)


def parse_emcy(data: bytes) -> tuple[int, int, int, float]:
    """``(code, error_register, fault_id, reading)`` of an EMCY frame's 8 data bytes."""
    return EMCY_STRUCT.unpack(bytes(data[:8]))
