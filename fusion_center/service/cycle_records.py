"""What the cycle assembler (:mod:`fusion_center.service.cycles`) reports: event flags, the one
disposition every fed event is counted under (:data:`COUNTER_NAMES`), NMT state codes of its own,
and the closed cycle it hands over (:class:`ClosedCycle`, with its :class:`EmcyEvent` entries).
Kept apart from the state machine so that its users import the vocabulary without the machine."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


# event flags
FLAG_EXTENDED = 1
FLAG_REMOTE = 2
FLAG_ERROR = 4
FLAG_FD = 8

STATE_UNKNOWN = -1
STATE_RESETTING = -2  # NMT reset sent: silent until its boot-up

TAG_MASK = 0x3F  # the cycle tag of object 0x2003 (bits 2-7): the SYNC counter modulo 64

EMCY_PER_CYCLE = 16  # EMCY entries a record carries at most (the rest are counted: emcy_dropped)

# one disposition per event fed (their sum == number of events)
COUNTER_NAMES: tuple[str, ...] = (
    "sync",            # valid SYNC (opened a cycle)
    "tpdo1",           # TPDO1 accepted into the open cycle
    "tpdo2",           # TPDO2 accepted into the open cycle
    "late",            # PDO for a closed cycle / duplicate / no cycle open: dropped
    "heartbeat",       # heartbeat (state != boot-up)
    "bootup",          # boot-up message (heartbeat state 0)
    "master_heartbeat",  # the master's own heartbeat (0x700 + [master] node_id, CiA 302)
    "emcy",            # emergency message
    "nmt",             # NMT module control (the master's own, or another master's)
    "sdo",             # SDO request or response
    "sdo_abort",       # SDO abort transfer (server -> client, command byte 0x80)
    "time",            # TIME stamp object
    "lss",             # CiA 305 layer setting service frame (0x7E4 / 0x7E5, 8 bytes)
    "drive",           # a frame of the scene's gripper drive ([gripper]: its PDOs, heartbeat, EMCY, SDO)
    "bad_dlc",         # known COB-ID, wrong data length
    "bad_value",       # known COB-ID, value outside its domain (u_i not ±1, state, counter...)
    "unknown_cob_id",  # COB-ID of no node/object in the scene
    "remote_frame",    # RTR frame (CiA 301 discourages RTR; not used by the taxel nodes)
    "error_frame",     # CAN error frame reported by the interface
    "extended_id",     # 29-bit identifier (CANopen uses 11-bit COB-IDs)
    "fd_frame",        # CAN FD frame where the scene has classic CAN (any FD frame without [bus] fd; with
                       # it, an FD frame on a COB-ID that is no PDO) or a classic frame on an FD PDO's COB-ID
    "internal_error",  # an exception inside the receive path (counted, never raised)
)
_C = {name: i for i, name in enumerate(COUNTER_NAMES)}
C_SYNC, C_TPDO1, C_TPDO2, C_LATE = _C["sync"], _C["tpdo1"], _C["tpdo2"], _C["late"]
C_HEARTBEAT, C_BOOTUP, C_EMCY, C_NMT = _C["heartbeat"], _C["bootup"], _C["emcy"], _C["nmt"]
C_SDO, C_SDO_ABORT, C_TIME, C_LSS = _C["sdo"], _C["sdo_abort"], _C["time"], _C["lss"]
C_BAD_DLC, C_BAD_VALUE, C_UNKNOWN = _C["bad_dlc"], _C["bad_value"], _C["unknown_cob_id"]
C_REMOTE, C_ERROR, C_EXTENDED, C_INTERNAL = (
    _C["remote_frame"], _C["error_frame"], _C["extended_id"], _C["internal_error"])
C_FD = _C["fd_frame"]
C_MASTER_HEARTBEAT = _C["master_heartbeat"]
C_DRIVE = _C["drive"]
MALFORMED = ("bad_dlc", "bad_value", "unknown_cob_id", "remote_frame", "error_frame", "extended_id", "fd_frame")
_MALFORMED_IDX = frozenset(_C[name] for name in MALFORMED)


def quantise_timestamp(timestamp: float | None) -> int:
    """Seconds (python-can ``Message.timestamp``) -> integer microseconds."""
    if timestamp is None or not math.isfinite(timestamp):
        return 0
    return int(round(timestamp * 1e6))


@dataclass(frozen=True)
class EmcyEvent:
    node: int | str       # node label (node-ID, or "channel:node-ID" off channel 0)
    taxel: int            # index in fusion order (a patch node: its first taxel)
    code: int             # emergency error code (CiA 301 table 21), 0x0000 = error reset
    register: int         # error register 0x1001
    manufacturer: str     # 5 manufacturer-specific bytes, hex
    t_us: int             # microseconds since the first event of the stream

    def as_record(self) -> dict:
        return {
            "node": self.node,
            "code": f"0x{self.code:04X}",
            "register": f"0x{self.register:02X}",
            "manufacturer": self.manufacturer,
            "t": round(self.t_us * 1e-6, 6),
        }


def frozen_instance(cls, fields: dict):
    """An instance of the frozen dataclass ``cls`` whose fields are ``fields`` (every field of
    ``cls``, each once): equal to ``cls(**fields)``, its attributes put in its ``__dict__`` at
    once instead of by the generated ``__init__``'s ``object.__setattr__`` per field - what a
    frozen dataclass costs to make: 1.2 against 13.6 µs for 20 fields on the shared 2-core host.
    A closed cycle makes three (:class:`ClosedCycle`, :class:`DeviceCycle`,
    ``drive_frames.DriveCycle``) between the frame that closes it and the grip command. Callers
    go through each class's ``make``, whose signature is the class's (tests/test_cycle_records_make.py)."""
    obj = object.__new__(cls)
    obj.__dict__.update(fields)
    return obj


@dataclass(frozen=True)
class DeviceCycle:
    """Per device (CANopen node; ``taxel_net.patches.devices`` order) of a cycle of a patch scene."""

    expected: np.ndarray       # bool: live and operational at the SYNC
    missing: np.ndarray        # bool: heartbeat consumer time expired / never heard
    states: np.ndarray         # int16: NMT state at the SYNC
    complete: np.ndarray       # bool: every TPDO of the device arrived in the cycle

    @classmethod
    def make(cls, expected, missing, states, complete) -> "DeviceCycle":
        """``DeviceCycle(...)``, made faster (:func:`frozen_instance`)."""
        return frozen_instance(cls, {"expected": expected, "missing": missing, "states": states, "complete": complete})


@dataclass(frozen=True)
class ClosedCycle:
    """Everything the stream said about one SYNC cycle (input of the per-cycle pipeline)."""

    cycle: int                 # 0-based index of the opening SYNC in the stream
    sync_us: int               # SYNC time, µs since the first event of the stream
    close_us: int              # time of the closing event
    sync_counter: int | None   # SYNC counter byte (0x1019 > 0), else None
    closed_by: str             # "complete" | "sync" | "nmt"
    decisions: np.ndarray      # int8 per taxel: wire u_i in {-1,+1} if TPDO1 arrived, else 0
    readings: np.ndarray       # float64 per taxel: X_i (mV) if TPDO2 arrived, else NaN
    received: np.ndarray       # bool per taxel: primary PDO arrived in this cycle
    expected: np.ndarray       # bool per taxel: its node live and operational at the SYNC
    missing: np.ndarray        # bool per taxel: its node's heartbeat consumer time expired / never heard
    held_decisions: np.ndarray  # int8: last u_i ever received per taxel (0 = never)
    held_readings: np.ndarray   # float64: last X_i ever received (NaN = never)
    late_frames: int           # late PDOs counted since the previous closed cycle
    bad_frames: int            # malformed frames since the previous closed cycle
    # EMCY frames since the previous closed cycle (at most EMCY_PER_CYCLE); with --assemblers it may begin with
    # a late / unsent part's EMCYs carried from an earlier cycle (their own t_us, from their process's first frame)
    emcy: tuple[EmcyEvent, ...]
    states: np.ndarray = None  # int16 per taxel: NMT state at the SYNC (STATE_*, -1 unknown, -2 resetting)
    duplicates: tuple[int, ...] = ()  # node (device) indexes with duplicate node-ID evidence since the previous cycle
    emcy_dropped: int = 0      # EMCY frames since the previous cycle beyond EMCY_PER_CYCLE (counted only)
    devices: DeviceCycle | None = None  # patch scenes: the nodes' view (one-taxel scenes: node = taxel)
    drive: object = None       # [gripper] scenes: the drive as known at the close (.drive_frames.DriveCycle)
    bootups: tuple[tuple[int, int], ...] = ()  # (device index, t_us of its last boot-up) since the previous cycle

    @classmethod
    def make(cls, cycle, sync_us, close_us, sync_counter, closed_by, decisions, readings, received, expected, missing,
             held_decisions, held_readings, late_frames, bad_frames, emcy, states=None, duplicates=(), emcy_dropped=0,
             devices=None, drive=None, bootups=()) -> "ClosedCycle":
        """``ClosedCycle(...)``, made faster (:func:`frozen_instance`): the assembler's close."""
        return frozen_instance(cls, {
            "cycle": cycle, "sync_us": sync_us, "close_us": close_us, "sync_counter": sync_counter,
            "closed_by": closed_by, "decisions": decisions, "readings": readings, "received": received,
            "expected": expected, "missing": missing, "held_decisions": held_decisions,
            "held_readings": held_readings, "late_frames": late_frames, "bad_frames": bad_frames, "emcy": emcy,
            "states": states, "duplicates": duplicates, "emcy_dropped": emcy_dropped, "devices": devices,
            "drive": drive, "bootups": bootups})
