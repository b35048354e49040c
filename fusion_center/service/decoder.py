"""Hot-path frame classification for the fusion centre (CiA 301 predefined connection set).

Every frame on a taxel channel is mapped, through one precomputed dict lookup per frame,
from its COB-ID to ``(kind, taxel_index)``: no canopen PDO objects on the hot path (those cost
~6 µs per frame against ~0.4 µs for a dict lookup plus ``int.from_bytes``/``struct``).

COB-IDs of the predefined connection set (CiA 301 §7.3.5), node-ID ``id`` in 1..127:

====================  ==========  ==================================================
object                COB-ID      payload
====================  ==========  ==================================================
NMT module control    0x000       2 bytes: command specifier, node-ID (0 = all)
SYNC                  0x080       0 bytes, or 1 byte counter 1..overflow (0x1019)
EMCY                  0x080+id    8 bytes: error code (U16 LE), error register (U8), 5 mfr
TIME                  0x100       6 bytes TIME_OF_DAY
TPDO1                 0x180+id    INTEGER8 local decision u_i in {-1,+1} (eqs 1-4)
TPDO2                 0x280+id    REAL32 little endian: process value X_i in mV (raw mode)
SDO server → client   0x580+id    8 bytes (byte 0 = 0x80: abort, bytes 4..7 abort code)
SDO client → server   0x600+id    8 bytes
NMT error control     0x700+id    1 byte NMT state (0 boot-up, 4 stopped, 5 operational,
                                  127 pre-operational)
master heartbeat      0x700+m     the same, of the master itself (``[master] node_id`` m,
                                  CiA 302; only while its heartbeat is on)
====================  ==========  ==================================================

A patch node's TPDO (``taxel_net.patches``) is decoded by its precomputed
:class:`SlotDecoder` (one per TPDO, built by the cycle assembler).
"""

from __future__ import annotations

import struct

import numpy as np

from taxel_net.patches import ENC_BITS, RAW_BYTES
from taxel_net.scene import Scene

from .cycle_records import C_BAD_DLC, C_BAD_VALUE, STATE_RESETTING

# frame kinds (small ints: compared on the hot path)
K_TPDO1 = 1
K_TPDO2 = 2
K_HEARTBEAT = 3
K_EMCY = 4
K_SDO_RESPONSE = 5
K_SDO_REQUEST = 6
K_SYNC = 7
K_NMT = 8
K_TIME = 9
K_LSS = 10  # CiA 305 LSS: 0x7E5 master -> slaves, 0x7E4 slave -> master
K_MASTER_HEARTBEAT = 11  # the master's own heartbeat, 0x700 + [master] node_id (CiA 302)
K_PATCH = 12  # a TPDO of a patch node (taxel_net.patches): the table's index is its slot, not a node
K_DRIVE = 13  # a frame of the scene's gripper drive ([gripper], taxel_net.gripper): counted, not a taxel's

COB_NMT = 0x000
COB_SYNC = 0x080
COB_TIME = 0x100
COB_LSS_SLAVE = 0x7E4
COB_LSS_MASTER = 0x7E5
BASE_EMCY = 0x080
BASE_TPDO1 = 0x180
BASE_TPDO2 = 0x280
BASE_SDO_RESPONSE = 0x580
BASE_SDO_REQUEST = 0x600
BASE_HEARTBEAT = 0x700

# NMT command specifiers (CiA 301 §7.2.8.3.1)
NMT_START = 0x01
NMT_STOP = 0x02
NMT_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82
NMT_COMMANDS = (NMT_START, NMT_STOP, NMT_PRE_OPERATIONAL, NMT_RESET_NODE, NMT_RESET_COMMUNICATION)

# NMT states carried by heartbeat frames
STATE_BOOTUP = 0x00
STATE_STOPPED = 0x04
STATE_OPERATIONAL = 0x05
STATE_PRE_OPERATIONAL = 0x7F
HEARTBEAT_STATES = (STATE_BOOTUP, STATE_STOPPED, STATE_OPERATIONAL, STATE_PRE_OPERATIONAL)
# the NMT state a node takes on an NMT command (the assembler's view; resets: "resetting" until its boot-up)
NMT_NEW_STATE = {NMT_START: STATE_OPERATIONAL, NMT_STOP: STATE_STOPPED, NMT_PRE_OPERATIONAL: STATE_PRE_OPERATIONAL,
                 NMT_RESET_NODE: STATE_RESETTING, NMT_RESET_COMMUNICATION: STATE_RESETTING}
STATE_NAMES = {
    -1: "unknown",
    STATE_BOOTUP: "boot-up",
    STATE_STOPPED: "stopped",
    STATE_OPERATIONAL: "operational",
    STATE_PRE_OPERATIONAL: "pre-operational",
}

_REAL32 = struct.Struct("<f")
_EMCY = struct.Struct("<HB5s")


def build_cob_tables(scene: Scene, devices=None) -> list[dict[int, tuple[int, int]]]:
    """One dict per scene channel: COB-ID -> (frame kind, taxel index in fusion order).

    Patch scenes (``[bus] patch_nodes``, ``devices`` = ``taxel_net.patches.devices(scene)``):
    the node's own COB-IDs (heartbeat, EMCY, SDO) map to the *device* index, and every TPDO of
    the devices to ``(K_PATCH, slot)``, slots numbered over the devices' TPDOs in order (no
    predefined TPDO1/TPDO2 per node-ID: the patches' TPDOs use those identifiers). In the
    chapter's one-taxel layout the device index is the taxel index.

    Channel-wide objects (NMT, SYNC, TIME, LSS, the master's heartbeat 0x700 + ``[master]
    node_id`` while it is on) map to taxel index -1; the gripper drive's COB-IDs (``[gripper]``) to
    ``(K_DRIVE, frame code)`` (:mod:`.drive_frames`). COB-IDs of node-IDs the scene does not name are absent: the assembler counts them as ``unknown_cob_id``. A taxel's own COB-IDs win over
    the master's heartbeat (the scene loader refuses that collision; a scene built in code may
    still have it).
    """
    tables: list[dict[int, tuple[int, int]]] = [
        {COB_NMT: (K_NMT, -1), COB_SYNC: (K_SYNC, -1), COB_TIME: (K_TIME, -1),
         COB_LSS_SLAVE: (K_LSS, -1), COB_LSS_MASTER: (K_LSS, -1)}
        for _ in scene.bus.channels
    ]
    if scene.master_heartbeat_ms > 0:
        for table in tables:
            table[BASE_HEARTBEAT + scene.master.node_id] = (K_MASTER_HEARTBEAT, -1)
    if scene.gripper is not None:  # the drive's own COB-IDs (CiA 301 pre-defined set) on its channel
        from taxel_net.gripper import drive_cob_ids

        from .drive_frames import FRAME_CODES

        for cob_id, what in drive_cob_ids(scene.gripper.node_id).items():
            tables[scene.gripper.channel][cob_id] = (K_DRIVE, FRAME_CODES[what])  # index: the frame's code
    if scene.bus.patch_nodes:
        if devices is None:
            from taxel_net.patches import devices as scene_devices

            devices = scene_devices(scene)
        slot = 0
        for index, dev in enumerate(devices):
            table = tables[dev.channel]
            _node_objects(table, dev.node_id, index)
            for tpdo in dev.tpdos:
                table[tpdo.cob_id] = (K_PATCH, slot)
                slot += 1
        return tables
    for index, taxel in enumerate(scene.taxels):
        table = tables[taxel.channel]
        table[BASE_TPDO1 + taxel.node_id] = (K_TPDO1, index)
        table[BASE_TPDO2 + taxel.node_id] = (K_TPDO2, index)
        _node_objects(table, taxel.node_id, index)
    return tables


def _node_objects(table: dict[int, tuple[int, int]], node_id: int, index: int) -> None:
    """The COB-IDs of node ``node_id``'s heartbeat, EMCY and SDO in a channel's table."""
    table[BASE_HEARTBEAT + node_id] = (K_HEARTBEAT, index)
    table[BASE_EMCY + node_id] = (K_EMCY, index)
    table[BASE_SDO_RESPONSE + node_id] = (K_SDO_RESPONSE, index)
    table[BASE_SDO_REQUEST + node_id] = (K_SDO_REQUEST, index)


def decode_decision(data: bytes) -> int:
    """TPDO1 payload (INTEGER8, two's complement) -> u_i as a Python int (range check by caller)."""
    value = data[0]
    return value - 256 if value > 127 else value


def decision_of(value: int, tagged: bool) -> int | None:
    """A TPDO1 byte -> u_i (+1 / -1), None where the byte is no decision: object 0x2000's
    INTEGER8 +1 / -1 (0x01 / 0xFF), or with ``tagged`` object 0x2003's u_i in bits 0-1 (0b01 / 0b11;
    the SYNC counter mod 64 in bits 2-7, for the caller)."""
    if tagged:
        code = value & 0b11
        return 1 if code == 0b01 else -1 if code == 0b11 else None
    return 1 if value == 1 else -1 if value == 0xFF else None


def decode_real32(data: bytes) -> float:
    """TPDO2 payload (REAL32 little endian, CiA 301 data type 0x0008) -> float mV."""
    return _REAL32.unpack_from(data)[0]


def encode_real32(value: float) -> bytes:
    return _REAL32.pack(value)


def decode_emcy(data: bytes) -> tuple[int, int, bytes]:
    """EMCY payload -> (error code, error register, manufacturer-specific 5 bytes)."""
    code, register, manufacturer = _EMCY.unpack_from(data)
    return code, register, manufacturer


def sync_payload(counter: int | None) -> bytes:
    """SYNC data field: empty, or the 1-byte counter when 0x1019 (sync_counter) is > 0."""
    return b"" if counter is None else bytes((counter,))


# bit k of a byte as a decision (u_i = +1 present, -1 absent): one table lookup per frame
_BITS_PM1 = np.where(np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1, bitorder="little") == 1,
                     np.int8(1), np.int8(-1)).astype(np.int8)
_BITS_PM1_BYTES = [row.tobytes() for row in _BITS_PM1]  # the same, a bytes object per byte value


class SlotDecoder:
    """The decoding of one patch TPDO, precomputed: exactly :func:`taxel_net.patches.unpack`
    (same values, same refusals), at a few µs a frame (a table of 8-byte patterns per byte value
    and one ``frombuffer`` for packed decisions; tests/test_cycles_patch.py checks the two agree on random frames).

    ``decode(data)`` -> ``(counter, tag, values)``: ``counter`` None when the frame fits, else
    the disposition (``C_BAD_DLC``, ``C_BAD_VALUE``)."""

    __slots__ = ("length", "tagged", "start", "end", "count", "tail", "pad_mask", "bits", "dtype", "lo", "lsb")

    def __init__(self, tpdo, lsb_mv: float):
        self.length = tpdo.length
        self.tagged = tpdo.tagged
        self.start = int(tpdo.tagged)
        self.end = self.start + tpdo.payload_bytes
        self.count = tpdo.count
        self.tail = bytes(tpdo.length - self.end)  # padding bytes: all 0
        self.bits = tpdo.encoding == ENC_BITS
        used = tpdo.count % 8
        self.pad_mask = (0xFF << used) & 0xFF if self.bits and used else 0  # unused bits of the last byte
        self.dtype = np.dtype("<i1") if RAW_BYTES.get(tpdo.encoding) == 1 else np.dtype("<i2")
        self.lo = int(np.iinfo(self.dtype).min)  # "not valid"
        self.lsb = float(lsb_mv)

    def check(self, data: bytes):
        """``(counter, tag)``: the refusals of :meth:`decode` (``counter`` None when the frame
        fits) and the cycle tag, without the values."""
        if len(data) != self.length:
            return C_BAD_DLC, None
        end = self.end
        if data[end:] != self.tail or (self.pad_mask and data[end - 1] & self.pad_mask):
            return C_BAD_VALUE, None
        return None, (data[0] if self.tagged else None)

    def decode(self, data: bytes):
        bad, tag = self.check(data)
        if bad is not None:
            return bad, None, None
        start, end = self.start, self.end
        if self.bits:  # eight decisions a byte, looked up as bytes: half the time of a numpy gather
            return None, tag, np.frombuffer(b"".join([_BITS_PM1_BYTES[b] for b in data[start:end]]),
                                            dtype=np.int8, count=self.count)
        counts = np.frombuffer(data, dtype=self.dtype, count=self.count, offset=start)
        mv = counts * self.lsb
        mv[counts == self.lo] = np.nan
        return None, tag, mv
