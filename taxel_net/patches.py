"""Devices and their TPDOs: which taxels a CANopen node hosts and how its PDOs carry them.

The one place the node twins and the fusion centre agree on a scene's PDO layout (issue 14).
Pure: no CAN, no clock, no files.

A **device** is one CANopen node: ``(channel, node_id)``. In the chapter's layout (the
default, ``[bus] patch_nodes = false``) every taxel is its own device, and its decision or
reading travels in the predefined TPDO1 / TPDO2 of CiA 301 (0x180 / 0x280 + node-ID) as before:
the INTEGER8 decision 0x2000, the tagged decision byte 0x2003 (scenes with a SYNC counter) or
the REAL32 process value. With ``patch_nodes = true`` the taxels that share a node-ID on a
channel form a **patch node** (up to :data:`PATCH_TAXELS_MAX`, in scene order) whose values
are packed:

* **decision mode**: one bit per taxel, bit ``k % 8`` of byte ``k // 8`` of the device's
  decision bytes (the UNSIGNED8 array :data:`PATCH_DECISIONS`, sub ``j`` = taxels ``8(j-1)``
  .. ``8j - 1``); 1 = present (u_i = +1, eqs 1-4), 0 = absent; unused bits 0.
* **raw mode**: the process value X_i of each taxel as INTEGER8 or INTEGER16
  (``[bus] raw_format``), little-endian, in counts of ``[bus] raw_lsb_mv`` mV
  (:data:`PATCH_RAW_LSB`); the most negative code means "not valid" (an open input, NaN),
  readings beyond the range saturate at the next codes. A limit code on the bus cannot be told
  from a genuine reading, so the node keeps the status apart, as CiA 404 does (its AI status
  0x6150: bit 0 not valid, bit 1 positive overload, bit 2 negative overload): the per-taxel
  :data:`PATCH_AI_STATUS` (:func:`counts_and_status`) and the over-range EMCY
  (:data:`EMCY_INPUT_OVER_RANGE`, sent on the rising edge, its error reset 0x0000 when every
  mapped reading is back in range; docs/node-twins.md).
* **cycle tag**: with a SYNC counter (``[bus] sync_counter`` > 0) every frame of a patch starts
  with one UNSIGNED8 byte, :data:`PATCH_CYCLE_TAG`: the counter of the SYNC its values were
  sampled at (CiA 301 SYNC counter, 1..overflow), so the centre counts every frame in its own
  cycle however late it arrives.

A patch's values fill frames of the largest size (8 bytes, 64 with ``[bus] fd = true``) in
taxel order; a reading never straddles two frames; the last frame holds the rest in whole
bytes, rounded up to a valid CAN FD data length (12, 16, 20, 24, 32, 48, 64) on FD; padding is
0. The frames are the device's TPDO 1, 2, ... (0x1800 + k, 0x1A00 + k), on consecutive 11-bit
COB-IDs per channel from ``[bus] tpdo_cob_id_base`` (default 0x181) in device order, within
0x181..0x57F (the TPDO/RPDO range of the predefined connection set; SDO, heartbeat, EMCY and
SYNC stay where CiA 301 puts them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PATCH_TAXELS_MAX = 254           # an ARRAY has sub-indices 1..254 (CiA 301): one array entry per taxel
CLASSIC_DATA_MAX = 8
FD_DATA_MAX = 64
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
COB_ID_FIRST = 0x181             # TPDO/RPDO identifiers of the predefined connection set
COB_ID_LAST = 0x57F
RAW_FORMATS = ("real32", "int16", "int8")
RAW_BYTES = {"int8": 1, "int16": 2}

# manufacturer objects of the patch node (eds/taxel_patch.eds)
PATCH_ZETA = 0x2010              # ARRAY REAL32: sub i = ζ of taxel i-1 (mV, eq 3)
PATCH_NOISE = 0x2011             # ARRAY REAL32: N_i (mV, eq 4)
PATCH_KIND = 0x2012              # ARRAY UNSIGNED8: kind code (taxel_net.scene.TAXEL_KINDS)
PATCH_X = 0x2013                 # ARRAY REAL32: x
PATCH_Y = 0x2014                 # ARRAY REAL32: y
PATCH_DECISIONS = 0x2020         # ARRAY UNSIGNED8: packed decisions, 8 taxels per sub
PATCH_CYCLE_TAG = 0x2021         # UNSIGNED8: counter of the sampling SYNC
PATCH_READINGS_I8 = 0x2030       # ARRAY INTEGER8: X_i in counts
PATCH_READINGS_I16 = 0x2031      # ARRAY INTEGER16: X_i in counts
PATCH_RAW_LSB = 0x2032           # REAL32: mV per count
PATCH_AI_STATUS = 0x2033         # ARRAY UNSIGNED8: AI status of taxel i-1 (CiA 404 0x6150's bits)

# AI status bits (CiA 404 AI status 0x6150, as the one-taxel node's 0x6150:1)
AI_NOT_VALID = 0x01              # no reading (NaN: the most negative code on the bus)
AI_POSITIVE_OVERLOAD = 0x02      # above the representable range: sent as the largest code
AI_NEGATIVE_OVERLOAD = 0x04      # below it: sent as the most negative code + 1
AI_OVERLOAD = AI_POSITIVE_OVERLOAD | AI_NEGATIVE_OVERLOAD

# The EMCY of a patch node whose mapped INTEGER8/16 readings saturate (CiA 301 EMCY, error code
# class 0x30xx "voltage": X_i is a bridge voltage in mV; error register bits 0 and 2), and its
# manufacturer-specific field (5 bytes): over-range id, taxel k (0-based, the node's own order),
# its TPDO (1 = 0x1800/0x1A00), its AI status bits, taxels over range (at most 254)
EMCY_INPUT_OVER_RANGE = 0x3000
EMCY_OVER_RANGE_ID = 3           # byte 3 of the field (the sensor faults use 1 stuck, 2 open circuit)
ERR_REG_VOLTAGE = 0x04           # error register 0x1001 bit 2

# how a TPDO's data encode its taxels
ENC_INTEGER8 = "integer8"        # per-taxel TPDO1: u_i as INTEGER8 +1 / -1 (0x2000)
ENC_TAGGED = "tagged"            # per-taxel TPDO1: 0x2003 (u_i bits 0-1, SYNC counter mod 64 bits 2-7)
ENC_REAL32 = "real32"            # per-taxel TPDO2: X_i as REAL32 mV
ENC_BITS = "bits"                # patch: packed decisions
ENC_INT8 = "int8"                # patch: packed INTEGER8 readings
ENC_INT16 = "int16"              # patch: packed INTEGER16 readings


class PatchFrameError(ValueError):
    """A frame that does not fit its TPDO: ``reason`` is the centre's counter name
    (``bad_dlc``: wrong length; ``bad_value``: a padding bit set)."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class Tpdo:
    """One TPDO of a device."""

    number: int                  # 0-based: communication 0x1800 + number, mapping 0x1A00 + number
    cob_id: int                  # 11-bit CAN identifier
    first: int                   # first taxel (position within the device) it carries
    count: int                   # taxels it carries
    encoding: str                # ENC_*
    tagged: bool                 # a leading UNSIGNED8 cycle tag (patch encodings only)
    length: int                  # data bytes on the bus (a valid FD length on FD)
    fd: bool                     # sent as a CAN FD frame (bit-rate switch on)

    @property
    def payload_bytes(self) -> int:
        """Bytes of values (after the tag), before padding."""
        if self.encoding == ENC_BITS:
            return (self.count + 7) // 8
        if self.encoding in RAW_BYTES:
            return self.count * RAW_BYTES[self.encoding]
        return 4 if self.encoding == ENC_REAL32 else 1


@dataclass(frozen=True)
class Device:
    """One CANopen node: the taxels it hosts (scene indices, in its own order) and its TPDOs."""

    channel: int
    node_id: int
    taxels: tuple[int, ...]
    tpdos: tuple[Tpdo, ...]

    @property
    def label(self) -> str:
        """As the centre's records name nodes: ``"12"`` on channel 0, ``"1:12"`` elsewhere."""
        return str(node_label(self.channel, self.node_id))


def node_label(channel: int, node_id: int) -> int | str:
    """How records name a node: its node-ID (an int) on channel 0, ``"C:ID"`` on channel C."""
    return node_id if channel == 0 else f"{channel}:{node_id}"


def fd_length(n: int) -> int:
    """The smallest valid CAN FD data length >= ``n`` (ISO 11898-1: 0-8, 12, 16, 20, 24, 32, 48, 64)."""
    for length in FD_LENGTHS:
        if length >= n:
            return length
    raise ValueError(f"{n} bytes: a CAN FD frame carries at most {FD_DATA_MAX}")


def values_per_frame(encoding: str, frame_bytes: int, tagged: bool) -> int:
    """How many taxels one full frame carries."""
    room = frame_bytes - int(tagged)
    if encoding == ENC_BITS:
        return 8 * room
    return room // RAW_BYTES[encoding]


def patch_encoding(mode: str, raw_format: str) -> str:
    return ENC_BITS if mode == "decision" else {"int8": ENC_INT8, "int16": ENC_INT16}[raw_format]


def devices(scene) -> tuple[Device, ...]:
    """The scene's devices, in order of their first taxel, with their TPDOs (module docstring).

    Raises ``ValueError`` when a patch has more than :data:`PATCH_TAXELS_MAX` taxels or a
    channel's TPDOs do not fit 0x181..0x57F (``load_scene`` checks both with a scene error)."""
    bus = scene.bus
    groups: dict[tuple[int, int], list[int]] = {}
    for i, t in enumerate(scene.taxels):
        groups.setdefault((t.channel, t.node_id), []).append(i)
    out = []
    if not bus.patch_nodes:
        for (channel, node_id), members in groups.items():
            if bus.mode == "raw":
                tpdo = Tpdo(1, 0x280 + node_id, 0, 1, ENC_REAL32, False, 4, bus.fd)
            elif bus.cycle_tag:
                tpdo = Tpdo(0, 0x180 + node_id, 0, 1, ENC_TAGGED, False, 1, bus.fd)
            else:
                tpdo = Tpdo(0, 0x180 + node_id, 0, 1, ENC_INTEGER8, False, 1, bus.fd)
            out.append(Device(channel, node_id, tuple(members), (tpdo,)))
        return tuple(out)
    encoding = patch_encoding(bus.mode, bus.raw_format)
    tagged = bus.sync_counter > 0
    frame_max = FD_DATA_MAX if bus.fd else CLASSIC_DATA_MAX
    per_frame = values_per_frame(encoding, frame_max, tagged)
    next_cob = [bus.tpdo_cob_id_base] * len(bus.channels)
    for (channel, node_id), members in groups.items():
        if len(members) > PATCH_TAXELS_MAX:
            raise ValueError(f"node-ID {node_id} on channel {channel} hosts {len(members)} taxels "
                             f"(a patch node holds at most {PATCH_TAXELS_MAX})")
        tpdos = []
        for number, first in enumerate(range(0, len(members), per_frame)):
            count = min(per_frame, len(members) - first)
            cob = next_cob[channel]
            if cob > COB_ID_LAST:
                raise ValueError(f"channel {channel}: the patches' TPDOs need more COB-IDs than "
                                 f"0x{bus.tpdo_cob_id_base:03X}..0x{COB_ID_LAST:03X} hold")
            next_cob[channel] += 1
            tpdo = Tpdo(number, cob, first, count, encoding, tagged, 0, bus.fd)
            length = int(tagged) + tpdo.payload_bytes
            tpdos.append(Tpdo(number, cob, first, count, encoding, tagged,
                              fd_length(length) if bus.fd else length, bus.fd))
        out.append(Device(channel, node_id, tuple(members), tuple(tpdos)))
    return tuple(out)


# ---------------------------------------------------------------------------- packing

def _raw_limits(encoding: str) -> tuple[int, int, np.dtype]:
    dtype = np.dtype("<i1") if encoding == ENC_INT8 else np.dtype("<i2")
    info = np.iinfo(dtype)
    return info.min, info.max, dtype


def pack(tpdo: Tpdo, values, tag: int | None = None) -> bytes:
    """The data of ``tpdo``: ``values`` are its ``count`` taxels' decisions (bool / 0-1 / ±1:
    present when > 0) for :data:`ENC_BITS`, or readings in mV scaled by ``lsb_mv`` beforehand
    (see :func:`pack_readings`) - here counts - for the raw encodings. ``tag``: the cycle tag
    (required when ``tpdo.tagged``)."""
    head = b""
    if tpdo.tagged:
        if tag is None or not 0 <= tag <= 255:
            raise ValueError(f"TPDO 0x{tpdo.cob_id:03X} is tagged: needs a tag 0..255, got {tag!r}")
        head = bytes((tag,))
    v = np.asarray(values)
    if v.shape != (tpdo.count,):
        raise ValueError(f"TPDO 0x{tpdo.cob_id:03X} carries {tpdo.count} taxels, got shape {v.shape}")
    if tpdo.encoding == ENC_BITS:
        body = np.packbits(v > 0, bitorder="little").tobytes()
    elif tpdo.encoding in RAW_BYTES:
        body = np.asarray(v, dtype=_raw_limits(tpdo.encoding)[2]).tobytes()
    else:
        raise ValueError(f"pack: {tpdo.encoding} is a per-taxel encoding")
    data = head + body
    return data + bytes(tpdo.length - len(data))


def counts_and_status(encoding: str, readings_mv, lsb_mv: float) -> tuple[np.ndarray, np.ndarray]:
    """Readings (mV, NaN = not valid) to the INTEGER8/16 counts of a raw patch encoding
    (:data:`ENC_INT8` / :data:`ENC_INT16`) and each reading's AI status (uint8, CiA 404 0x6150's
    bits): rounded to the nearest count; a reading whose nearest count lies above the largest
    code (more than half a count beyond it) is sent as that code and flagged
    :data:`AI_POSITIVE_OVERLOAD`, one below the most negative code + 1 as that code and flagged
    :data:`AI_NEGATIVE_OVERLOAD`; NaN is sent as the most negative code ("not valid",
    :data:`AI_NOT_VALID`); infinities overload."""
    lo, hi, dtype = _raw_limits(encoding)
    r = np.asarray(readings_mv, dtype=np.float64)
    bad = np.isnan(r)
    nearest = np.rint(np.where(bad, 0.0, r) / lsb_mv)
    above, below = nearest > hi, nearest < lo + 1
    counts = np.clip(nearest, lo + 1, hi)
    counts[bad] = lo
    status = (above * np.uint8(AI_POSITIVE_OVERLOAD)) | (below * np.uint8(AI_NEGATIVE_OVERLOAD)) \
        | (bad * np.uint8(AI_NOT_VALID))
    return counts.astype(dtype), status.astype(np.uint8)


def readings_to_counts(tpdo: Tpdo, readings_mv, lsb_mv: float) -> tuple[np.ndarray, int]:
    """Readings (mV, NaN = not valid) to the INTEGER8/16 counts of a raw patch TPDO: rounded to
    the nearest count, saturated at min + 1 .. max; NaN to the minimum ("not valid"). Returns
    the counts and how many readings saturated, i.e. their nearest count lies beyond the range
    (:func:`counts_and_status` has which, and how)."""
    counts, status = counts_and_status(tpdo.encoding, readings_mv, lsb_mv)
    return counts, int(np.count_nonzero(status & AI_OVERLOAD))


def unpack(tpdo: Tpdo, data: bytes, lsb_mv: float = 1.0) -> tuple[int | None, np.ndarray]:
    """Decode a patch TPDO: ``(tag or None, values)``; values are ±1 (int8) for
    :data:`ENC_BITS`, readings in mV (float64, NaN = not valid) for the raw encodings.
    Raises :class:`PatchFrameError` on a wrong length or a set padding bit."""
    if len(data) != tpdo.length:
        raise PatchFrameError("bad_dlc", f"TPDO 0x{tpdo.cob_id:03X}: {len(data)} data bytes, expected {tpdo.length}")
    start = int(tpdo.tagged)
    tag = data[0] if tpdo.tagged else None
    end = start + tpdo.payload_bytes
    if any(data[end:]):
        raise PatchFrameError("bad_value", f"TPDO 0x{tpdo.cob_id:03X}: padding bytes not 0")
    body = np.frombuffer(data, dtype=np.uint8, count=end - start, offset=start)
    if tpdo.encoding == ENC_BITS:
        bits = np.unpackbits(body, bitorder="little")
        if bits[tpdo.count:].any():
            raise PatchFrameError("bad_value", f"TPDO 0x{tpdo.cob_id:03X}: padding bits not 0")
        return tag, (2 * bits[: tpdo.count].astype(np.int8) - 1)
    if tpdo.encoding in RAW_BYTES:
        lo, _, dtype = _raw_limits(tpdo.encoding)
        counts = np.frombuffer(data, dtype=dtype, count=tpdo.count, offset=start)
        mv = counts.astype(np.float64) * lsb_mv
        mv[counts == lo] = np.nan
        return tag, mv
    raise ValueError(f"unpack: {tpdo.encoding} is a per-taxel encoding")
