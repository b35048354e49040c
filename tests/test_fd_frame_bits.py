"""CAN FD frame lengths (ISO 11898-1:2015) against hand-worked frames and an independent derivation.

The hand-worked frames below are written out field by field. The independent derivation
(``reference_fd_frame``) is written differently from ``fusion_center.core.bus_timing``: strings
instead of bit lists, a look-back stuffing rule ("before sending the next bit, if the last five
bits on the wire are equal, send their complement"), which also yields the ISO end-of-data rule
(no dynamic stuff bit after the last data bit) without a special case, and CRC-17/21 by
polynomial long division on Python integers. The ISO start value of the CRC register (a 1 in
its top bit) is folded into the division: a register of width W starting at x^(W-1) yields
(x^(W-1) * x^n + M(x) * x^W) mod G = ((M(x) + x^(n-1)) * x^W) mod G for an n-bit message M,
i.e. the zero-start CRC of the message with its first bit inverted.

The four hand-worked frames were also checked (while writing this test, not at run time)
against the frame builder of the ISO 16845 compliance-test library of the CTU CAN FD project
(src/can_lib/BitFrame.cpp), which agreed with ``fd_frame_wire`` bit for bit on 6,000 random
frames of every length, both formats, with and without BRS.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fusion_center.core.bus_timing import (
    FD_LENGTHS,
    crc17,
    crc21,
    fd_frame_bits,
    fd_frame_bits_estimate,
    fd_frame_fields,
    fd_frame_wire,
    stuff,
)
from taxel_net.errors import ParameterError

G17 = (1 << 17) | 0x1685B    # x^17+x^16+x^14+x^13+x^11+x^6+x^4+x^3+x+1
G21 = (1 << 21) | 0x102899   # x^21+x^20+x^13+x^11+x^7+x^4+x^3+1


def crc_by_division(message: str, generator: int, iso_start: bool = True) -> int:
    """Remainder of M(x) * x^W divided by G(x) (W = degree of G); with ``iso_start`` the first
    message bit is inverted (the ISO start value x^(W-1), see the module docstring)."""
    width = generator.bit_length() - 1
    if iso_start and message:
        message = ("1" if message[0] == "0" else "0") + message[1:]
    rem = int(message, 2) << width if message else 0
    while rem.bit_length() > width:
        rem ^= generator << (rem.bit_length() - generator.bit_length())
    return rem


def test_reference_division_matches_the_published_check_values():
    # CRC catalogue (reveng): CRC-17/CAN-FD check 0x04F03, CRC-21/CAN-FD check 0x0ED841 for
    # the ASCII bytes "123456789", MSB first, start value 0 (the non-ISO Bosch FD 1.0 form)
    msg = "".join(format(c, "08b") for c in b"123456789")
    assert crc_by_division(msg, G17, iso_start=False) == 0x04F03
    assert crc_by_division(msg, G21, iso_start=False) == 0x0ED841


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(0, 1), min_size=1, max_size=700))
def test_crc17_crc21_match_the_division_with_the_iso_start_value(bits):
    s = "".join(map(str, bits))
    assert crc17(bits) == crc_by_division(s, G17)
    assert crc21(bits) == crc_by_division(s, G21)


def reference_fd_frame(can_id: int, data: bytes, brs: bool, extended: bool) -> tuple[str, int]:
    """Independent FD frame: (wire string SOF..last CRC bit, wire bits up to and incl. BRS)."""
    def b(value: int, width: int) -> str:
        return format(value, f"0{width}b")

    dlc = {n: code for code, n in enumerate([0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64])}
    if extended:
        arbitration = "0" + b(can_id >> 18, 11) + "11" + b(can_id & 0x3FFFF, 18) + "0"  # SOF ID SRR IDE IDext RRS
    else:
        arbitration = "0" + b(can_id, 11) + "00"                                        # SOF ID RRS IDE
    before_brs = arbitration + "10"                                                      # FDF, res
    rest = ("1" if brs else "0") + "0" + b(dlc[len(data)], 4) + "".join(b(x, 8) for x in data)  # BRS ESI DLC data
    unstuffed = before_brs + rest
    wire, head, n_stuff = "", 0, 0
    for k, bit in enumerate(unstuffed):
        last5 = wire[-5:]
        if len(last5) == 5 and last5 in ("00000", "11111"):
            wire += "1" if last5[0] == "0" else "0"
            n_stuff += 1
        wire += bit
        if k == len(before_brs):           # the BRS bit was just sent
            head = len(wire)
    gray = b((n_stuff % 8) ^ ((n_stuff % 8) >> 1), 3)
    counted = gray + str(gray.count("1") % 2)
    generator = G17 if len(data) <= 16 else G21
    width = generator.bit_length() - 1
    crc = b(crc_by_division(wire + counted, generator), width)
    protected = counted + crc
    groups = [protected[i:i + 4] for i in range(0, len(protected), 4)]
    fixed = ""
    for g in groups:
        fixed += ("1" if (wire + fixed)[-1] == "0" else "0") + g   # fixed stuff bit, then 4 bits
    return wire + fixed, head


def _ref_counts(can_id, data, brs, extended):
    wire, head = reference_fd_frame(can_id, data, brs, extended)
    after_crc = 1 + 1 + 1 + 7 + 3   # CRC delimiter, ACK slot, ACK delimiter, EOF, intermission
    return (head + after_crc, len(wire) - head) if brs else (len(wire) + after_crc, 0)


# Hand-worked frames, written field by field. Stuff bits are marked in the comments (S = dynamic,
# F = fixed); the stuff count is the Gray code of (dynamic stuff bits mod 8) plus even parity.
HAND_FRAMES = [
    dict(  # base format, ID 0x000, no data, BRS: the stuff condition falls on the last DLC bit
        can_id=0x000, data=b"", brs=True, extended=False,
        # SOF + ID + RRS + IDE = 14 zeros: S after the 5th and 10th | FDF res BRS
        head="00000" "1" "00000" "1" "0000" "101",
        # ESI + DLC 0000 = five zeros ending the field: no dynamic stuff bit there
        dynamic="00000",
        n_stuff=2, count="011" "0",
        crc=0b1_0011_1001_0001_0111, width=17,
        # F | count | F | CRC in fours, F after each fourth bit
        fixed="1" "0110" "1" "1001" "0" "1100" "1" "1000" "1" "1011" "0" "1",
        nominal=19 + 13, data_bits=5 + 27,
    ),
    dict(  # CANopen TPDO1 of node 5 (0x185) with one byte 0x01, no bit-rate switch
        can_id=0x185, data=bytes([0x01]), brs=False, extended=False,
        # SOF | ID 00110000101 | RRS IDE | FDF res BRS=0: no run of five
        head="0" "00110000101" "00" "10" "0",
        # ESI | DLC 0001 | 00000001: res BRS ESI + DLC 00 = five zeros -> S(1); data zeros 1-5 -> S(1)
        dynamic="0" "00" "1" "01" "00000" "1" "001",
        n_stuff=2, count="011" "0",
        crc=0b0_1011_1110_0111_0010, width=17,
        fixed="0" "0110" "1" "0101" "0" "1111" "0" "0011" "0" "1001" "0" "0",
        nominal=17 + 15 + 27 + 13, data_bits=0,      # all nominal without BRS
    ),
    dict(  # TPDO 0x181 of a 192-taxel patch: 24 bytes of packed decisions (taxel 0 present): CRC-21
        can_id=0x181, data=bytes([0x01]) + bytes(23), brs=True, extended=False,
        # SOF + 00 | 11 | 000000 (S after 5) ... 1 | RRS IDE | FDF res BRS
        head="000" "11" "00000" "1" "0" "1" "00" "1" "0" "1",
        # ESI | DLC 1100 | 00000001: DLC 00 + data 000 -> S(1) | 0000 1 | 23 zero bytes = 184 zeros:
        # 36 runs of five, each followed by S(1), then 4 zeros
        dynamic="0" "11" "00" "000" "1" "00001" + ("00000" "1") * 36 + "0000",
        n_stuff=1 + 1 + 36, count="101" "0",       # 38 mod 8 = 6 -> Gray 101, parity 0
        crc=0b1_0111_1101_0111_1100_0100, width=21,
        fixed="1" "1010" "1" "1011" "0" "1110" "1" "1011" "0" "1110" "1" "0010" "1" "0",
        nominal=18 + 13, data_bits=(5 + 192 + 37) + 32,
    ),
    dict(  # extended format 0x1ABCDEF0, 12 bytes 0xFF (DLC 9), BRS
        can_id=0x1ABCDEF0, data=bytes([0xFF] * 12), brs=True, extended=True,
        # SOF | base ID 11010101111 | SRR (5th one -> S(0)) | IDE | ID ext 001101111011110000 |
        # RRS (5th zero -> S(1)) | FDF res BRS
        head="0" "11010101111" "1" "0" "1" "001101111011110000" "0" "1" "1" "0" "1",
        # ESI | DLC 1001 | 96 ones: DLC's last 1 + 4 ones -> S(0), then 18 runs of five + S(0), 2 ones
        dynamic="0" "1001" "1111" "0" + ("11111" "0") * 18 + "11",
        n_stuff=2 + 1 + 18, count="111" "1",       # 21 mod 8 = 5 -> Gray 111, parity 1
        crc=0b0_0100_1000_1001_0011, width=17,
        fixed="0" "1111" "0" "0010" "1" "0100" "1" "0100" "1" "1001" "0" "1",
        nominal=38 + 13, data_bits=(5 + 96 + 19) + 27,
    ),
]


@pytest.mark.parametrize("frame", HAND_FRAMES, ids=lambda f: f"0x{f['can_id']:X}-{len(f['data'])}B")
def test_hand_worked_frames(frame):
    can_id, data, brs, ext = frame["can_id"], frame["data"], frame["brs"], frame["extended"]
    head, dynamic, fixed = frame["head"], frame["dynamic"], frame["fixed"]
    # the hand-written strings are self-consistent
    assert "000000" not in head + dynamic and "111111" not in head + dynamic
    assert frame["count"][:3] == format((frame["n_stuff"] % 8) ^ ((frame["n_stuff"] % 8) >> 1), "03b")
    assert crc_by_division(head + dynamic + frame["count"], G17 if frame["width"] == 17 else G21) == frame["crc"]
    protected = frame["count"] + format(frame["crc"], f"0{frame['width']}b")
    assert "".join(fixed[k] for k in range(len(fixed)) if k % 5) == protected
    assert all(fixed[k] != (head + dynamic + fixed)[len(head + dynamic) + k - 1] for k in range(0, len(fixed), 5))
    # the module agrees with them
    wire = fd_frame_wire(can_id, data, brs=brs, extended=ext)
    assert "".join(map(str, wire.bits)) == head + dynamic + fixed
    assert wire.head == len(head)
    assert wire.stuff_count == frame["n_stuff"]
    assert (wire.crc, wire.crc_width) == (frame["crc"], frame["width"])
    assert fd_frame_bits(can_id, data, brs=brs, extended=ext) == (frame["nominal"], frame["data_bits"])
    # and so does the independent derivation
    assert reference_fd_frame(can_id, data, brs, ext) == (head + dynamic + fixed, len(head))


def test_field_layout_before_stuffing():
    # FBFF: SOF ID RRS IDE FDF res BRS ESI DLC; FEFF: SOF baseID SRR IDE IDext RRS FDF res BRS ESI DLC
    fbff = "".join(map(str, fd_frame_fields(0x7FF, b"", brs=False)))
    assert fbff == "0" + "1" * 11 + "00" + "10" + "0" + "0" + "0000"
    f = "".join(map(str, fd_frame_fields(0x1ABCDEF0, bytes(64), extended=True)))
    assert f[:41] == "0" + "11010101111" + "11" + "001101111011110000" + "0" + "10" + "1" + "0" + "1111"
    assert len(f) == 41 + 512
    # DLC codes 9..15 stand for 12, 16, 20, 24, 32, 48, 64 bytes
    for code, n in zip(range(9, 16), (12, 16, 20, 24, 32, 48, 64)):
        assert "".join(map(str, fd_frame_fields(0x100, bytes(n))[18:22])) == format(code, "04b")


@settings(max_examples=400, deadline=None)
@given(st.booleans(), st.booleans(), st.integers(0, 0x1FFFFFFF), st.sampled_from(FD_LENGTHS), st.data())
def test_random_frames_match_the_independent_derivation(extended, brs, can_id, n, draw):
    if not extended:
        can_id &= 0x7FF
    data = draw.draw(st.one_of(st.binary(min_size=n, max_size=n),
                               st.lists(st.sampled_from([0x00, 0xFF, 0x0F, 0xF0, 0x1E, 0xE1]),
                                        min_size=n, max_size=n).map(bytes)))
    wire, head = reference_fd_frame(can_id, data, brs, extended)
    got = fd_frame_wire(can_id, data, brs=brs, extended=extended)
    assert "".join(map(str, got.bits)) == wire
    assert got.head == head
    assert fd_frame_bits(can_id, data, brs=brs, extended=extended) == _ref_counts(can_id, data, brs, extended)


@settings(max_examples=300, deadline=None)
@given(st.booleans(), st.integers(0, 0x1FFFFFFF), st.sampled_from(FD_LENGTHS), st.data())
def test_exact_lengths_lie_within_the_worst_case_bound(extended, can_id, n, draw):
    if not extended:
        can_id &= 0x7FF
    data = draw.draw(st.binary(min_size=n, max_size=n))
    nominal, data_bits = fd_frame_bits(can_id, data, extended=extended)
    est_nominal, est_data = fd_frame_bits_estimate(n, extended)
    assert nominal <= est_nominal and data_bits <= est_data
    # without stuff bits: 17/36 arbitration bits + 13, and ESI..data + 4-bit count + CRC + fixed stuff bits
    assert nominal >= (36 if extended else 17) + 13
    assert data_bits >= 5 + 8 * n + 4 + (17 + 6 if n <= 16 else 21 + 7)
    # BRS = 0 is another bit pattern (other stuffing), all of it nominal, within the same total bound
    total, zero = fd_frame_bits(can_id, data, brs=False, extended=extended)
    assert zero == 0 and total <= est_nominal + est_data


def test_the_end_of_data_rule_changes_the_count():
    # 0x000 with no data (first hand frame): five zeros end the DLC; a classic-style stuffer
    # would insert a sixth bit there and count 3. ISO: none, count 2, the fixed bit follows.
    wire = fd_frame_wire(0x000, b"")
    assert wire.stuff_count == 2
    assert "".join(map(str, wire.bits))[19:25] == "00000" "1"
    fields = fd_frame_fields(0x000, b"")
    assert len(stuff(fields)) - len(fields) == 3


@pytest.mark.parametrize("n", [9, 10, 11, 13, 15, 17, 25, 40, 63, 65, 128])
def test_invalid_fd_data_lengths_raise_value_error(n):
    with pytest.raises(ValueError) as exc:
        fd_frame_bits(0x181, bytes(n))
    assert isinstance(exc.value, ParameterError) and exc.value.name == "len(data)"
    message = str(exc.value)
    assert "\n" not in message and f"={n}:" in message and "12, 16, 20, 24, 32, 48 or 64" in message


@pytest.mark.parametrize("kwargs, name", [
    (dict(can_id=0x800, data=b""), "can_id"),
    (dict(can_id=-1, data=b""), "can_id"),
    (dict(can_id=0x20000000, data=b"", extended=True), "can_id"),
    (dict(can_id=True, data=b""), "can_id"),
    (dict(can_id=1, data=[256]), "data"),
    (dict(can_id=1, data=b"", brs=1), "brs"),
    (dict(can_id=1, data=b"", extended="yes"), "extended"),
])
def test_bad_input_names_the_parameter(kwargs, name):
    with pytest.raises(ParameterError) as exc:
        fd_frame_bits(**kwargs)
    assert exc.value.name == name
