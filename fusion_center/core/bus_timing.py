"""Exact bit accounting of classic CAN frames (ISO 11898-1 / Bosch CAN 2.0 A and B).

Numerical core: no CAN hardware, no I/O. The chapter (sec. 3.1, 4.3) leaves the transport
open; this module prices the bus cost of the fusion centre's traffic (one TPDO per taxel per
SYNC, eqs 1-4 decisions or raw X_i) so the bandwidth report is exact, frame by frame.

A data frame on the wire, in transmission order (bit value 0 = dominant)::

    SOF(1)=0 | ID(11) | RTR(1)=0 | IDE(1)=0 | r0(1)=0 | DLC(4) | DATA(8n) | CRC(15)     <- stuffed
    | CRC delimiter(1)=1 | ACK slot(1) | ACK delimiter(1)=1 | EOF(7)=1111111 | intermission(3)

extended (2.0B): SOF | base ID(11) | SRR(1)=1 | IDE(1)=1 | ID extension(18) | RTR | r1 | r0 | DLC |
DATA | CRC. The CRC-15 (generator x^15+x^14+x^10+x^8+x^7+x^4+x^3+1, i.e. 0x4599, initial value
0) is computed over the *unstuffed* bits from SOF to the end of the data field. Bit stuffing
(after five consecutive equal bits the transmitter inserts one complementary bit, which itself
starts the next run) applies from SOF to the end of the CRC sequence, including a stuff bit
after the CRC's last bit when its last five bits are equal. The 10 bits from the CRC delimiter
to the EOF and the 3-bit intermission are fixed form.

Worst case (Davis, Burns, Bril & Lukkien, "Controller Area Network (CAN) schedulability
analysis: Refuted, revisited and revised", Real-Time Systems 35(3), 2007, eq. 2; it corrects
Tindell's floor((34+8n)/5)): with g = 34 (standard) or 54 (extended) stuffable overhead bits,

    C = g + 8n + 13 + floor((g + 8n - 1) / 4)      bits, incl. the 3-bit intermission,

i.e. 8n + 47 + floor((34 + 8n - 1)/4) for 2.0A (135 bits for 8 bytes; the "8n + 44" form found
elsewhere omits the intermission) and 8n + 67 + floor((54 + 8n - 1)/4) for 2.0B (160 bits).
The Linux kernel (include/linux/can/length.h, ``can_frame_bits``) counts the same numbers.
Best case: no stuff bit at all, 8n + 47 (2.0A) or 8n + 67 (2.0B).

CAN FD (ISO 11898-1:2015) frames are built bit by bit too (``fd_frame_bits``; ``fd_frame_wire``
gives the transmitted sequence). What differs from a classic frame: RRS/FDF/res/BRS/ESI bits
in the arbitration and control fields; DLC codes 9..15 mean 12..64 bytes; dynamic stuffing ends
with the data field, followed by a 3-bit Gray-coded stuff-bit count and its parity bit;
CRC-17 (<= 16 bytes) or CRC-21 (> 16 bytes), computed over the dynamically *stuffed* bits, with
*fixed* stuff bits (one before the stuff count, then one after every fourth bit) instead of
dynamic stuffing; and the data phase (ESI to the last CRC bit) at a second, higher bit rate when
BRS is set, so a frame's duration is the sum of two bit-time products, not bits / bitrate.
``fd_frame_bits_estimate`` is the data-independent worst case of the same frame (the Linux
kernel's bound).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from typing import NamedTuple

from taxel_net.errors import ParameterError

CRC15_POLY = 0x4599                 # x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1 (x^15 implicit)
STUFF_RUN = 5                       # a stuff bit after 5 equal consecutive bits
INTERMISSION_BITS = 3
TRAILER_BITS = 1 + 2 + 7            # CRC delimiter, ACK slot + delimiter, EOF
STUFFABLE_OVERHEAD = {False: 34, True: 54}   # g: SOF..CRC minus the data field, 2.0A / 2.0B
MAX_STD_ID = 0x7FF
MAX_EXT_ID = 0x1FFFFFFF


def _to_bits(value: int, width: int) -> list[int]:
    return [(value >> (width - 1 - k)) & 1 for k in range(width)]


def _check_bits(bits) -> list[int]:
    out = [int(b) for b in bits]
    if any(b not in (0, 1) for b in out):
        raise ParameterError("bits", bits, "must contain only 0 and 1")
    return out


def crc15(bits: Iterable[int]) -> int:
    """CRC-15 of CAN (polynomial 0x4599, init 0) over a bit sequence, MSB first (ISO 11898-1 10.4.2.6).

    Shift-register form of the spec: CRC_NXT = bit XOR CRC[14]; shift left; XOR 0x4599 if CRC_NXT.
    """
    return _crc15(_check_bits(bits))


def _crc15(bits: list[int]) -> int:
    """:func:`crc15` of a checked 0/1 list (the frame builders' own bits: no re-check)."""
    crc = 0
    for b in bits:
        nxt = b ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if nxt:
            crc ^= CRC15_POLY
    return crc


def _stuff_count(bits: list[int]) -> int:
    """:func:`stuff_bits` of a checked 0/1 list, counted without building the stuffed list."""
    count, run_value, run_len = 0, -1, 0
    for b in bits:
        if b == run_value:
            run_len += 1
            if run_len == STUFF_RUN:
                count += 1
                run_value, run_len = 1 - b, 1  # the stuff bit starts the next run
        else:
            run_value, run_len = b, 1
    return count


def stuff_bits(bits: Iterable[int]) -> int:
    """Number of stuff bits the transmitter inserts into ``bits`` (the SOF..CRC sequence).

    After 5 consecutive equal bits a complementary bit is inserted; the stuff bit counts as
    the first bit of the next run. A stuff bit after the last bit is counted (CRC end).
    """
    seq = _check_bits(bits)
    return len(stuff(seq)) - len(seq)


def stuff(bits: Iterable[int]) -> list[int]:
    """The bit sequence as transmitted, with stuff bits inserted (see ``stuff_bits``)."""
    out: list[int] = []
    run_value, run_len = None, 0
    for b in _check_bits(bits):
        out.append(b)
        if b == run_value:
            run_len += 1
        else:
            run_value, run_len = b, 1
        if run_len == STUFF_RUN:
            s = 1 - b
            out.append(s)
            run_value, run_len = s, 1
    return out


def _check_frame(can_id, data, extended: bool, remote: bool, dlc) -> tuple[int, bytes, int]:
    if isinstance(can_id, bool) or not isinstance(can_id, int):
        raise ParameterError("can_id", can_id, "must be an integer")
    limit = MAX_EXT_ID if extended else MAX_STD_ID
    if not 0 <= can_id <= limit:
        raise ParameterError("can_id", can_id, f"must lie in 0..0x{limit:X} for "
                                               f"{'extended (2.0B)' if extended else 'standard (2.0A)'} frames")
    try:
        payload = bytes(data)
    except (TypeError, ValueError):
        raise ParameterError("data", data, "must be bytes or a sequence of integers 0..255") from None
    if len(payload) > 8:
        raise ParameterError("data", len(payload), "classic CAN carries 0..8 data bytes")
    if remote:
        if payload:
            raise ParameterError("data", payload, "a remote frame has no data field")
        code = 0 if dlc is None else dlc
    else:
        code = len(payload) if dlc is None else dlc
        if dlc is not None and dlc != len(payload):
            raise ParameterError("dlc", dlc, f"must equal len(data)={len(payload)} for a data frame")
    if isinstance(code, bool) or not isinstance(code, int) or not 0 <= code <= 8:
        raise ParameterError("dlc", code, "must lie in 0..8")
    return can_id, payload, code


def frame_fields(can_id: int, data: bytes | Sequence[int] = b"", extended: bool = False,
                 remote: bool = False, dlc: int | None = None) -> list[int]:
    """Unstuffed bits from SOF to the end of the data field (what the CRC covers)."""
    can_id, payload, code = _check_frame(can_id, data, extended, remote, dlc)
    rtr = 1 if remote else 0
    bits = [0]                                            # SOF
    if extended:
        bits += _to_bits(can_id >> 18, 11)                # base identifier ID28..ID18
        bits += [1, 1]                                    # SRR, IDE
        bits += _to_bits(can_id & 0x3FFFF, 18)            # identifier extension ID17..ID0
        bits += [rtr, 0, 0]                               # RTR, r1, r0
    else:
        bits += _to_bits(can_id, 11)
        bits += [rtr, 0, 0]                               # RTR, IDE, r0
    bits += _to_bits(code, 4)                             # DLC
    for byte in payload:
        bits += _to_bits(byte, 8)
    return bits


def frame_stuffable_bits(can_id: int, data: bytes | Sequence[int] = b"", extended: bool = False,
                         remote: bool = False, dlc: int | None = None) -> list[int]:
    """Unstuffed SOF..CRC sequence: ``frame_fields`` followed by its 15-bit CRC."""
    fields = frame_fields(can_id, data, extended, remote, dlc)
    return fields + _to_bits(_crc15(fields), 15)


def frame_bits(can_id: int, data: bytes | Sequence[int] = b"", extended: bool = False,
               remote: bool = False, dlc: int | None = None, intermission: bool = True) -> int:
    """Exact length on the wire, in bits, of one classic CAN data (or remote) frame.

    SOF..CRC with its actual stuff bits + CRC delimiter, ACK slot, ACK delimiter, EOF
    (+ the 3-bit intermission unless ``intermission=False``). ``dlc`` only for a remote
    frame (the requested length); for a data frame DLC = len(data).

    The same bits as ``frame_stuffable_bits`` and ``stuff_bits`` (tests/test_bus_timing.py),
    counted on integers: the SOF..data field as one number, its CRC by a byte table
    (:func:`_crc15_of`), the stuff bits run by run (:func:`_stuff_count_of_runs`) - the report
    and ``fusion-center bandwidth`` price tens of thousands of frames (4x faster than bit lists).
    """
    can_id, payload, code = _check_frame(can_id, data, extended, remote, dlc)
    rtr = 1 if remote else 0
    if extended:   # SOF, base ID, SRR=1, IDE=1, ID extension, RTR, r1, r0
        head, head_bits = (((can_id >> 18) << 2 | 0b11) << 18 | (can_id & 0x3FFFF)) << 3 | rtr << 2, 35
    else:          # SOF, ID, RTR, IDE=0, r0
        head, head_bits = can_id << 3 | rtr << 2, 15
    fields = (head << 4 | code) << 8 * len(payload) | int.from_bytes(payload, "big")
    n_fields = head_bits + 4 + 8 * len(payload)
    n_seq = n_fields + 15
    seq = format(fields << 15 | _crc15_of(fields, n_fields), f"0{n_seq}b")
    return n_seq + _stuff_count_of_runs(seq) + TRAILER_BITS + (INTERMISSION_BITS if intermission else 0)


def _crc15_table() -> tuple[int, ...]:
    """Register after shifting in each byte value from a zero register (:func:`_crc15`)."""
    table = []
    for byte in range(256):
        table.append(_crc15(_to_bits(byte, 8)))
    return tuple(table)


_CRC15_TABLE = _crc15_table()


def _crc15_of(value: int, n_bits: int) -> int:
    """:func:`crc15` of the ``n_bits``-bit sequence ``value`` (MSB first). With initial value 0,
    leading 0 bits leave the register 0, so the sequence is padded in front to whole bytes and
    shifted in a byte at a time (the table form of the spec's shift register)."""
    crc = 0
    for byte in value.to_bytes((n_bits + 7) // 8, "big"):
        crc = ((crc << 8) & 0x7FFF) ^ _CRC15_TABLE[((crc >> 7) ^ byte) & 0xFF]
    return crc


_LONG_RUNS = re.compile("0{4,}|1{4,}")


def _stuff_count_of_runs(bits: str) -> int:
    """:func:`_stuff_count` of a '0'/'1' string, a run of equal bits at a time. A run of L bits
    gets its first stuff bit after 5 of them, or after 4 when the bit sent just before it is a
    stuff bit (the previous run's last: the complement of that run, so this run's value), then
    one after every 5 more (each stuff bit ends the run it breaks); runs shorter than 4 never
    get one and are skipped."""
    count, stuffed_end = 0, -1          # where the last run ended with a stuff bit
    for match in _LONG_RUNS.finditer(bits):
        start, end = match.span()
        k, rest = divmod(end - start - (STUFF_RUN - 1 if start == stuffed_end else STUFF_RUN), STUFF_RUN)
        if k >= 0:
            count += k + 1
            if rest == 0:
                stuffed_end = end
    return count


def _check_dlc(dlc) -> int:
    if isinstance(dlc, bool) or not isinstance(dlc, int) or not 0 <= dlc <= 8:
        raise ParameterError("dlc", dlc, "must lie in 0..8")
    return dlc


def worst_case_frame_bits(dlc: int, extended: bool = False, intermission: bool = True) -> int:
    """Upper bound g + 8n + 13 + floor((g + 8n - 1)/4) (Davis et al. 2007, eq. 2; g = 34 or 54).

    With ``intermission=False`` 3 bits less (8n + 44 + ... for 2.0A)."""
    n = _check_dlc(dlc)
    g = STUFFABLE_OVERHEAD[bool(extended)]
    total = g + 8 * n + TRAILER_BITS + INTERMISSION_BITS + (g + 8 * n - 1) // 4
    return total if intermission else total - INTERMISSION_BITS


def best_case_frame_bits(dlc: int, extended: bool = False, intermission: bool = True) -> int:
    """Lower bound: the frame without any stuff bit, g + 8n + 13 (8n + 47 for 2.0A)."""
    n = _check_dlc(dlc)
    g = STUFFABLE_OVERHEAD[bool(extended)]
    return g + 8 * n + TRAILER_BITS + (INTERMISSION_BITS if intermission else 0)


def _check_bitrate(bitrate) -> float:
    if isinstance(bitrate, bool) or not isinstance(bitrate, (int, float)) or not bitrate > 0 \
            or bitrate != bitrate or bitrate == float("inf"):
        raise ParameterError("bitrate", bitrate, "must be a finite number of bit/s > 0")
    return float(bitrate)


def frame_time_s(bits: int, bitrate: float) -> float:
    """Transmission time of ``bits`` at ``bitrate`` bit/s (classic CAN: one bit time each)."""
    if isinstance(bits, bool) or not isinstance(bits, int) or bits < 0:
        raise ParameterError("bits", bits, "must be an integer >= 0")
    return bits / _check_bitrate(bitrate)


def bus_load(frames_bits_per_cycle: Iterable[int], cycle_period_s: float, bitrate: float) -> float:
    """Fraction of the bus time the frames of one cycle occupy: sum(bits) / (period * bitrate).

    A value > 1 means the cycle's traffic does not fit in the period.
    """
    total = 0
    for k, b in enumerate(frames_bits_per_cycle):
        if isinstance(b, bool) or not isinstance(b, int) or b < 0:
            raise ParameterError(f"frames_bits_per_cycle[{k}]", b, "must be an integer >= 0")
        total += b
    if isinstance(cycle_period_s, bool) or not isinstance(cycle_period_s, (int, float)) \
            or not cycle_period_s > 0 or cycle_period_s == float("inf"):
        raise ParameterError("cycle_period_s", cycle_period_s, "must be a finite number of seconds > 0")
    return total / (float(cycle_period_s) * _check_bitrate(bitrate))


# ---------------------------------------------------------------- CAN FD (worst-case estimate)

FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


def fd_frame_bits_estimate(data_len: int, extended: bool = False) -> tuple[int, int]:
    """Worst-case CAN FD frame length split as (nominal-phase bits, data-phase bits).

    Header up to and including BRS (SOF, ID, RRS/SRR, IDE, [ID ext, RRS,] FDF, res, BRS:
    17 bits standard, 36 extended) and, after the CRC, CRC delimiter + ACK slot + ACK delimiter
    + EOF + 3-bit intermission run at the nominal rate; ESI, DLC, data, stuff-bit count (4),
    CRC-17 (<= 16 bytes) or CRC-21 and its fixed stuff bits (6 or 7) at the data rate. Dynamic
    stuffing of SOF..data is bounded by floor((L - 1)/4), as for classic frames; the stuff bits
    of the first A header bits are floor((A - 1)/4), the rest are charged to the data phase.
    The total equals the Linux kernel's ``can_frame_bits(is_fd=true, bitstuffing=true,
    intermission=true)`` (include/linux/can/length.h).
    """
    if isinstance(data_len, bool) or not isinstance(data_len, int) or data_len not in FD_LENGTHS:
        raise ParameterError("data_len", data_len, f"CAN FD carries one of {FD_LENGTHS} bytes")
    header = 41 if extended else 22           # SOF .. DLC
    before_brs = 36 if extended else 17       # SOF .. BRS
    dynamic = header + 8 * data_len
    stuff_total = (dynamic - 1) // 4
    stuff_nominal = (before_brs - 1) // 4
    crc_field = 4 + (17 + 6 if data_len <= 16 else 21 + 7)   # SBC + CRC + fixed stuff bits
    nominal = before_brs + stuff_nominal + TRAILER_BITS + INTERMISSION_BITS   # CRC delim..EOF, IFS
    data = (header - before_brs) + 8 * data_len + (stuff_total - stuff_nominal) + crc_field
    return nominal, data


def fd_frame_time_s(data_len: int, nominal_bitrate: float, data_bitrate: float | None = None,
                    extended: bool = False) -> float:
    """Worst-case duration of a CAN FD frame: nominal bits at the nominal rate plus data-phase
    bits at ``data_bitrate`` (bit-rate switch); ``data_bitrate=None`` = no switch (BRS = 0)."""
    nominal, data = fd_frame_bits_estimate(data_len, extended)
    nb = _check_bitrate(nominal_bitrate)
    db = nb if data_bitrate is None else _check_bitrate(data_bitrate)
    return nominal / nb + data / db


# ---------------------------------------------------------------- CAN FD, bit by bit

CRC17_POLY = 0x1685B      # x^17 + x^16 + x^14 + x^13 + x^11 + x^6 + x^4 + x^3 + x + 1 (x^17 implicit)
CRC21_POLY = 0x102899     # x^21 + x^20 + x^13 + x^11 + x^7 + x^4 + x^3 + 1 (x^21 implicit)
FD_DLC = {n: code for code, n in enumerate(FD_LENGTHS)}   # data bytes -> DLC code (9..15: 12..64)
FD_BRS_INDEX = {False: 16, True: 35}   # position of BRS in SOF..data (SOF = 0), base / extended format
FD_TRAILER_BITS = 1 + 1 + 1 + 7        # CRC delimiter, ACK slot, ACK delimiter, EOF (nominal rate)


class FdFrameWire(NamedTuple):
    """One CAN FD data frame as transmitted, SOF through the last CRC bit (``fd_frame_wire``).

    ``bits``: the transmitted bit values (0 = dominant), dynamic and fixed stuff bits included;
    ``head``: how many of them lie from SOF up to and including BRS (the arbitration phase);
    ``stuff_count``: dynamic stuff bits inserted (the stuff count field carries it mod 8);
    ``crc``: the CRC-17 or CRC-21 value, ``crc_width`` 17 or 21.
    """

    bits: tuple[int, ...]
    head: int
    stuff_count: int
    crc: int
    crc_width: int


def _fd_crc(bits: Iterable[int], width: int, poly: int) -> int:
    # ISO 11898-1:2015 10.4.2.6: the register starts with a 1 in its most significant bit
    top = width - 1
    mask = (1 << width) - 1
    crc = 1 << top
    for b in _check_bits(bits):
        nxt = b ^ ((crc >> top) & 1)
        crc = (crc << 1) & mask
        if nxt:
            crc ^= poly
    return crc


def crc17(bits: Iterable[int]) -> int:
    """CRC-17 of CAN FD (frames with up to 16 data bytes; ISO 11898-1:2015 10.4.2.6), MSB first.

    Generator x^17+x^16+x^14+x^13+x^11+x^6+x^4+x^3+x+1, register initialised to 1 followed by
    16 zeros (ISO; the non-ISO Bosch FD 1.0 started from 0). Same shift register as ``crc15``."""
    return _fd_crc(bits, 17, CRC17_POLY)


def crc21(bits: Iterable[int]) -> int:
    """CRC-21 of CAN FD (frames with 20 to 64 data bytes; ISO 11898-1:2015 10.4.2.6), MSB first.

    Generator x^21+x^20+x^13+x^11+x^7+x^4+x^3+1, register initialised to 1 followed by 20 zeros."""
    return _fd_crc(bits, 21, CRC21_POLY)


def _check_fd_frame(can_id, data, brs, extended) -> tuple[int, bytes]:
    if not isinstance(brs, bool):
        raise ParameterError("brs", brs, "must be True or False")
    if not isinstance(extended, bool):
        raise ParameterError("extended", extended, "must be True or False")
    if isinstance(can_id, bool) or not isinstance(can_id, int):
        raise ParameterError("can_id", can_id, "must be an integer")
    limit = MAX_EXT_ID if extended else MAX_STD_ID
    if not 0 <= can_id <= limit:
        raise ParameterError("can_id", can_id, f"must lie in 0..0x{limit:X} for "
                                               f"{'extended' if extended else 'base'} format frames")
    try:
        payload = bytes(data)
    except (TypeError, ValueError):
        raise ParameterError("data", data, "must be bytes or a sequence of integers 0..255") from None
    if len(payload) not in FD_DLC:
        raise ParameterError("len(data)", len(payload),
                             "a CAN FD data field holds 0-8, 12, 16, 20, 24, 32, 48 or 64 bytes")
    return can_id, payload


def fd_frame_fields(can_id: int, data: bytes | Sequence[int] = b"", *, brs: bool = True,
                    extended: bool = False) -> list[int]:
    """Unstuffed bits of a CAN FD data frame from SOF to the end of the data field.

    ISO 11898-1:2015 10.4.2 (FD base format, FBFF): SOF | ID(11) | RRS=0 | IDE=0 | FDF=1 | res=0 |
    BRS | ESI | DLC(4) | data; extended format (FEFF): SOF | base ID(11) | SRR=1 | IDE=1 |
    ID extension(18) | RRS=0 | FDF=1 | res=0 | BRS | ESI | DLC | data. ESI = 0 (error-active
    transmitter); BRS = 1 when ``brs`` (bit-rate switch). DLC 9..15 code 12..64 bytes.
    """
    can_id, payload = _check_fd_frame(can_id, data, brs, extended)
    bits = [0]                                            # SOF
    if extended:
        bits += _to_bits(can_id >> 18, 11)                # base identifier ID28..ID18
        bits += [1, 1]                                    # SRR, IDE
        bits += _to_bits(can_id & 0x3FFFF, 18)            # identifier extension ID17..ID0
        bits += [0]                                       # RRS
    else:
        bits += _to_bits(can_id, 11)
        bits += [0, 0]                                    # RRS, IDE
    bits += [1, 0, 1 if brs else 0, 0]                    # FDF, res, BRS, ESI
    bits += _to_bits(FD_DLC[len(payload)], 4)
    for byte in payload:
        bits += _to_bits(byte, 8)
    return bits


def fd_frame_wire(can_id: int, data: bytes | Sequence[int] = b"", *, brs: bool = True,
                  extended: bool = False) -> FdFrameWire:
    """A CAN FD data frame as transmitted from SOF to the last CRC bit (ISO 11898-1:2015 10.5).

    1. Dynamic stuffing from SOF to the end of the data field: after five equal bits a
       complementary bit, which starts the next run - except after the last bit of the data
       field (of the DLC for 0 bytes): there the fixed stuff bit below takes its place and no
       dynamic stuff bit is inserted or counted (never two stuff bits in a row).
    2. Stuff count: the number of dynamic stuff bits mod 8 as a 3-bit Gray code, then an even
       parity bit over those three bits.
    3. CRC-17 (<= 16 data bytes) or CRC-21 over the stuffed SOF..data sequence followed by the
       stuff count and parity (the fixed stuff bits are not covered).
    4. Fixed stuff bits, each the complement of the bit before it: one before the stuff count,
       then one after every fourth bit of stuff count + CRC (6 bits with CRC-17, 7 with CRC-21).
    """
    can_id, payload = _check_fd_frame(can_id, data, brs, extended)
    fields = fd_frame_fields(can_id, payload, brs=brs, extended=extended)
    brs_index = FD_BRS_INDEX[extended]
    last = len(fields) - 1
    out: list[int] = []
    head = 0
    n_stuff = 0
    run_value, run_len = -1, 0
    for k, b in enumerate(fields):
        out.append(b)
        if b == run_value:
            run_len += 1
        else:
            run_value, run_len = b, 1
        if k == brs_index:
            head = len(out)                               # a stuff bit right after BRS is data phase
        if run_len == STUFF_RUN and k != last:
            out.append(1 - b)
            n_stuff += 1
            run_value, run_len = 1 - b, 1
    count = n_stuff % 8
    gray = _to_bits(count ^ (count >> 1), 3)
    stuff_field = gray + [gray[0] ^ gray[1] ^ gray[2]]   # even parity
    width, poly = (17, CRC17_POLY) if len(payload) <= 16 else (21, CRC21_POLY)
    crc = _fd_crc(out + stuff_field, width, poly)
    fixed_part = stuff_field + _to_bits(crc, width)
    wire = list(out)
    wire.append(1 - wire[-1])                             # fixed stuff bit before the stuff count
    for i, b in enumerate(fixed_part, 1):
        wire.append(b)
        if i % 4 == 0:
            wire.append(1 - b)                            # after every fourth bit
    return FdFrameWire(tuple(wire), head, n_stuff, crc, width)


def fd_frame_bits(can_id: int, data: bytes | Sequence[int] = b"", *, brs: bool = True,
                  extended: bool = False) -> tuple[int, int]:
    """Exact length of one CAN FD data frame as (nominal_bits, data_bits) (ISO 11898-1:2015).

    ``data_bits``: ESI through the last CRC bit, with the dynamic stuff bits, the stuff count,
    its parity and the fixed stuff bits in that span (sent at the data bit rate when BRS is
    set); ``nominal_bits``: everything else - SOF through BRS with their stuff bits, CRC
    delimiter, ACK slot, ACK delimiter, EOF and the 3-bit intermission. With ``brs=False``
    the whole frame runs at the nominal rate: ``(all bits, 0)``. The frame is built by
    ``fd_frame_wire``; valid data lengths are 0-8, 12, 16, 20, 24, 32, 48 and 64 bytes
    (anything else raises ``ParameterError``, a ``ValueError``). A frame's duration is
    nominal_bits / nominal bit rate + data_bits / data bit rate.
    """
    wire = fd_frame_wire(can_id, data, brs=brs, extended=extended)
    tail = FD_TRAILER_BITS + INTERMISSION_BITS
    if not brs:
        return len(wire.bits) + tail, 0
    return wire.head + tail, len(wire.bits) - wire.head
