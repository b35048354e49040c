"""Exact CAN bit accounting checked against hand-worked frames and independent references."""

import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fusion_center.core.bus_timing import (
    best_case_frame_bits,
    bus_load,
    crc15,
    frame_bits,
    frame_fields,
    frame_stuffable_bits,
    frame_time_s,
    stuff,
    stuff_bits,
    worst_case_frame_bits,
)
from taxel_net.errors import ParameterError

GENERATOR = 0xC599  # x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1, with the x^15 term


def crc_by_division(bitstring: str) -> int:
    """Independent CRC-15: remainder of M(x) * x^15 divided by G(x), long division on an int."""
    m = int(bitstring, 2) << 15 if bitstring else 0
    width = m.bit_length()
    while width > 15:
        m ^= GENERATOR << (width - 16)
        width = m.bit_length()
    return m


def destuff(stuffed: str) -> str:
    """Receiver side: drop the bit that follows five equal bits (independent of the encoder)."""
    out, run_char, run, skip = [], "", 0, False
    for ch in stuffed:
        if skip:
            assert ch != run_char, "a stuff bit must be the complement"
            run_char, run, skip = ch, 1, False
            continue
        out.append(ch)
        run = run + 1 if ch == run_char else 1
        run_char = ch
        if run == 5:
            skip = True
    return "".join(out)


def bits_str(bits) -> str:
    return "".join(str(b) for b in bits)


# Hand-worked frames. unstuffed = SOF | ID(11) | RTR IDE r0 | DLC(4) | data | CRC(15), written out
# field by field; stuffed = the same with the stuff bits (marked S in the comments) inserted.
HAND_FRAMES = [
    dict(  # id 0x000, no data: 19 zero bits, CRC of zeros = 0 -> 34 zeros, a stuff '1' after every 5
        can_id=0x000, data=b"",
        unstuffed="0" + "00000000000" + "000" + "0000" + "" + "000000000000000",
        crc=0x0000,
        stuffed="000001" * 6 + "0000",
        n_stuff=6, total=34 + 6 + 13,
    ),
    dict(  # NMT "start all nodes" 0x000 [0x01, 0x00]
        can_id=0x000, data=bytes([0x01, 0x00]),
        unstuffed="0" + "00000000000" + "000" + "0010" + "00000001" + "00000000" + "110000110010111",
        crc=0b110000110010111,
        # 17 zeros (S after 5, 10, 15) | 1 | 0 + 7 zeros (S after 5) | 1 | 8 zeros (S after 5) | CRC
        stuffed="00000" "1" "00000" "1" "00000" "1" "00" "1" "00000" "1" "000" "1" "00000" "1" "000"
                "110000110010111",
        n_stuff=5, total=50 + 5 + 13,
    ),
    dict(  # TPDO1 of node 5 (0x180 + 5) carrying one byte 0x01
        can_id=0x185, data=bytes([0x01]),
        unstuffed="0" + "00110000101" + "000" + "0001" + "00000001" + "001010011000110",
        crc=0b001010011000110,
        # ...0101 | 6 zeros (S after 5) | 1 | 7 zeros (S after 5) | 1 | CRC
        stuffed="000110000101" "00000" "1" "0" "1" "00000" "1" "00" "1" "001010011000110",
        n_stuff=2, total=42 + 2 + 13,
    ),
    dict(  # heartbeat of node 1 (0x700 + 1), state operational [0x05]
        can_id=0x701, data=bytes([0x05]),
        unstuffed="0" + "11100000001" + "000" + "0001" + "00000101" + "100110100001110",
        crc=0b100110100001110,
        # 0111 | 7 zeros (S after 5) | 1 | 6 zeros (S after 5) | 1 | 5 zeros (S) | 101 | CRC
        stuffed="0111" "00000" "1" "00" "1" "00000" "1" "0" "1" "00000" "1" "101" "100110100001110",
        n_stuff=3, total=42 + 3 + 13,
    ),
    dict(  # SYNC 0x080 without counter
        can_id=0x080, data=b"",
        unstuffed="0" + "00010000000" + "000" + "0000" + "" + "001110000000101",
        crc=0b001110000000101,
        # 0000 1 | 16 zeros (S after 5, 10, 15) | 111 | 7 zeros (S after 5) | 101
        stuffed="0000" "1" "00000" "1" "00000" "1" "00000" "1" "0" "111" "00000" "1" "00" "101",
        n_stuff=4, total=34 + 4 + 13,
    ),
]


@pytest.mark.parametrize("frame", HAND_FRAMES, ids=lambda f: f"0x{f['can_id']:03X}-{f['data'].hex()}")
def test_hand_worked_frames(frame):
    unstuffed, stuffed = frame["unstuffed"], frame["stuffed"]
    # the hand-written strings are self-consistent
    assert crc_by_division(unstuffed[:-15]) == frame["crc"] == int(unstuffed[-15:], 2)
    assert destuff(stuffed) == unstuffed
    assert len(stuffed) - len(unstuffed) == frame["n_stuff"]
    assert not re.search("000000|111111", stuffed)
    # the module agrees with them
    fields = frame_fields(frame["can_id"], frame["data"])
    assert bits_str(fields) == unstuffed[:-15]
    assert crc15(fields) == frame["crc"]
    seq = frame_stuffable_bits(frame["can_id"], frame["data"])
    assert bits_str(seq) == unstuffed
    assert bits_str(stuff(seq)) == stuffed
    assert stuff_bits(seq) == frame["n_stuff"]
    assert frame_bits(frame["can_id"], frame["data"]) == frame["total"]
    assert frame_bits(frame["can_id"], frame["data"], intermission=False) == frame["total"] - 3


def test_stuff_bit_after_last_crc_bit_is_counted():
    # five equal bits at the very end of the SOF..CRC sequence still get their stuff bit
    assert stuff_bits([1, 0, 0, 0, 0, 0]) == 1
    assert stuff_bits([1, 0, 0, 0, 0]) == 0
    # the stuff bit starts the next run: 0*5 S(1) 1111 -> the 4 ones plus S make five -> S(0)
    assert bits_str(stuff([0] * 5 + [1] * 4)) == "00000" "1" "1111" "0"


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 0x7FF), st.binary(max_size=8))
def test_crc_matches_polynomial_division_std(can_id, data):
    fields = bits_str(frame_fields(can_id, data))
    assert crc15(frame_fields(can_id, data)) == crc_by_division(fields)


@settings(max_examples=300, deadline=None)
@given(st.booleans(), st.integers(0, 0x1FFFFFFF), st.binary(max_size=8))
def test_bounds_hold_for_random_frames(extended, can_id, data):
    if not extended:
        can_id &= 0x7FF
    n = len(data)
    bits = frame_bits(can_id, data, extended=extended)
    assert best_case_frame_bits(n, extended) <= bits <= worst_case_frame_bits(n, extended)
    seq = frame_stuffable_bits(can_id, data, extended=extended)
    assert destuff(bits_str(stuff(seq))) == bits_str(seq)


def test_extended_field_layout():
    # 2.0B: SOF, base ID (ID28..18), SRR=1, IDE=1, ID17..0, RTR, r1, r0, DLC
    f = bits_str(frame_fields(0x1ABCDEF0, b"", extended=True))
    can_id = 0x1ABCDEF0
    assert f == ("0" + format(can_id >> 18, "011b") + "11" + format(can_id & 0x3FFFF, "018b")
                 + "000" + "0000")
    assert len(f) + 15 == 54  # g = 54 stuffable overhead bits


def test_worst_case_formula_closed_form_and_published_values():
    # Davis et al. 2007: 2.0A 8 bytes = 135 bits, 2.0B 8 bytes = 160 bits (incl. 3-bit intermission)
    assert worst_case_frame_bits(8) == 135
    assert worst_case_frame_bits(8, extended=True) == 160
    assert worst_case_frame_bits(8, intermission=False) == 132
    for n in range(9):
        assert worst_case_frame_bits(n) == 8 * n + 47 + (34 + 8 * n - 1) // 4
        assert best_case_frame_bits(n) == 8 * n + 47
        assert best_case_frame_bits(n, extended=True) == 8 * n + 67


def test_worst_case_agrees_with_linux_can_length_h():
    # include/linux/can/length.h: header 19 (SFF) / 39 (EFF), CRC field 16 (CRC + delimiter),
    # stuffed length L + (L - 1) // 4, footer 9, intermission 3.
    for extended, header in ((False, 19), (True, 39)):
        for n in range(9):
            destuffed = header + 8 * n + 16
            linux = destuffed + (destuffed - 1) // 4 + 9 + 3
            assert worst_case_frame_bits(n, extended=extended) == linux


def test_worst_case_stuffing_term_is_reached_by_the_worst_pattern():
    # 5 equal bits, then runs of 4 of alternating value: every run after the first
    # merges with the preceding stuff bit, so L bits carry floor((L - 1) / 4) stuff bits
    for length in range(1, 120):
        pattern = ("00000" + "".join(("1111", "0000")[k % 2] for k in range(40)))[:length]
        assert stuff_bits([int(c) for c in pattern]) == (length - 1) // 4
    # real frames stay below: SOF/RTR/IDE/r0 and the CRC are not free
    assert max(frame_bits(i, b"") for i in range(0x800)) <= worst_case_frame_bits(0)


def test_remote_frame():
    # RTR = 1, DLC = requested length, no data field
    f = bits_str(frame_fields(0x701, b"", remote=True, dlc=1))
    assert f == "0" + format(0x701, "011b") + "100" + "0001"
    assert frame_bits(0x701, remote=True, dlc=1) <= worst_case_frame_bits(0)


def test_time_and_load():
    # 57 TPDOs of 57 bits + SYNC (51 bits) every 10 ms at 1 Mbit/s
    frames = [57] * 57 + [51]
    assert bus_load(frames, 0.010, 1_000_000) == pytest.approx((57 * 57 + 51) / 10_000)
    assert frame_time_s(135, 1_000_000) == pytest.approx(135e-6)
    assert frame_time_s(135, 125_000) == pytest.approx(1.08e-3)


@pytest.mark.parametrize("call, name", [
    (lambda: frame_bits(0x800, b""), "can_id"),
    (lambda: frame_bits(-1, b""), "can_id"),
    (lambda: frame_bits(0x20000000, b"", extended=True), "can_id"),
    (lambda: frame_bits(1, bytes(9)), "data"),
    (lambda: frame_bits(1, [256]), "data"),
    (lambda: frame_bits(1, b"\x01", remote=True), "data"),
    (lambda: worst_case_frame_bits(9), "dlc"),
    (lambda: frame_time_s(10, 0), "bitrate"),
    (lambda: bus_load([10, -1], 0.01, 1e6), "frames_bits_per_cycle[1]"),
    (lambda: bus_load([10], 0.0, 1e6), "cycle_period_s"),
    (lambda: crc15([0, 2]), "bits"),
])
def test_bad_input_names_parameter(call, name):
    with pytest.raises(ParameterError) as exc:
        call()
    assert exc.value.name == name


def test_fd_estimate_total_agrees_with_linux_can_length_h():
    from fusion_center.core.bus_timing import FD_LENGTHS, fd_frame_bits_estimate, fd_frame_time_s

    # include/linux/can/length.h: FD header 22 (SFF) / 41 (EFF) bits stuffed as L + (L-1)//4,
    # CRC field 28 (CRC-17) / 33 (CRC-21) incl. stuff count, delimiter and fixed stuff bits,
    # footer 9, intermission 3
    for extended, header in ((False, 22), (True, 41)):
        for n in FD_LENGTHS:
            destuffed = header + 8 * n
            linux = destuffed + (destuffed - 1) // 4 + (28 if n <= 16 else 33) + 9 + 3
            nominal, data = fd_frame_bits_estimate(n, extended)
            assert nominal + data == linux
    nominal, data = fd_frame_bits_estimate(64)
    assert fd_frame_time_s(64, 500_000, 2_000_000) == pytest.approx(nominal / 5e5 + data / 2e6)
    assert fd_frame_time_s(64, 500_000) == pytest.approx((nominal + data) / 5e5)
    with pytest.raises(ParameterError):
        fd_frame_bits_estimate(9)


@settings(max_examples=150, deadline=None)
@given(st.booleans(), st.booleans(), st.integers(0, 0x1FFFFFFF), st.integers(0, 8),
       st.lists(st.sampled_from([0x00, 0xFF, 0x0F, 0xF0, 0x01, 0x80, 0x7C, 0x3E]) | st.integers(0, 255), max_size=8),
       st.booleans())
def test_frame_bits_equal_the_bit_level_frame(extended, remote, can_id, dlc, data, intermission):
    """frame_bits counts on integers (a CRC byte table, stuff bits run by run); the same frame
    bit by bit: the fields, their CRC by polynomial division, the encoder's stuffing checked by
    the independent receiver (destuff), the fixed 10 (+3) bits - run-heavy payloads included."""
    if not extended:
        can_id &= 0x7FF
    data = b"" if remote else bytes(data)
    kwargs = dict(extended=extended, remote=remote, dlc=dlc if remote else None)
    fields = bits_str(frame_fields(can_id, data, **kwargs))
    unstuffed = fields + format(crc_by_division(fields), "015b")
    stuffed = bits_str(stuff([int(b) for b in unstuffed]))
    assert destuff(stuffed) == unstuffed and not re.search("000000|111111", stuffed)
    assert frame_bits(can_id, data, intermission=intermission, **kwargs) == len(stuffed) + 10 + 3 * intermission


def test_stuff_count_by_runs_equals_the_encoder_on_every_short_sequence():
    from itertools import product

    from fusion_center.core.bus_timing import _stuff_count_of_runs

    for n in range(15):
        for bits in product("01", repeat=n):
            text = "".join(bits)
            assert _stuff_count_of_runs(text) == len(stuff([int(b) for b in text])) - n, text
