"""Skin layouts (fusion_center.core.layouts) against enumeration and hand-computed cases.

A frame's mean and worst case over its payloads come from a dynamic programme over the stuffing
state; here they are checked against enumerating every payload through ``frame_bits`` /
``fd_frame_bits`` (themselves checked bit by bit in test_bus_timing.py / test_fd_frame_bits.py).
The layouts (nodes, frames, COB-IDs, channels), the cycle sums, event-driven expectations, bus
loads and SYNC rates are worked out by hand below.
"""

from __future__ import annotations

import itertools

import pytest

from fusion_center.core.bus_timing import (
    fd_frame_bits,
    fd_frame_bits_estimate,
    frame_bits,
    worst_case_frame_bits,
)
from fusion_center.core.layouts import (
    layout_bus_use,
    channels_needed,
    layout_cycle_bits,
    node_frames,
    pdo_frame_stats,
    skin_layout,
)
from taxel_net.errors import ParameterError

FULL8 = (1 << 64) - 1


def enumerate_frame(cob_id: int, n_bytes: int, free_mask: int, p_one: float, fd: bool, brs: bool = True):
    """(mean nominal, mean data, worst nominal, worst data) by trying every payload."""
    nbits = 8 * n_bytes
    free = [k for k in range(nbits) if free_mask >> (nbits - 1 - k) & 1]
    mean_n = mean_d = 0.0
    worst = (-1, -1)
    for values in itertools.product((0, 1), repeat=len(free)):
        word, weight = 0, 1.0
        for k, v in zip(free, values):
            word |= v << (nbits - 1 - k)
            weight *= p_one if v else 1.0 - p_one
        data = word.to_bytes(n_bytes, "big")
        nominal, data_bits = fd_frame_bits(cob_id, data, brs=brs) if fd else (frame_bits(cob_id, data), 0)
        mean_n += weight * nominal
        mean_d += weight * data_bits
        if nominal + data_bits > sum(worst):
            worst = (nominal, data_bits)
    return mean_n, mean_d, worst[0], worst[1]


FRAME_CASES = [
    # (cob_id, n_bytes, free_mask, p_one, fd, brs)
    (0x181, 1, 0x01, 0.5, False, True),          # one-taxel decision node
    (0x1FF, 1, 0xFF, 0.5, False, True),          # one-taxel raw8 node
    (0x185, 1, 0xFF, 0.0, False, True),          # p_one = 0: mean = the zero payload, worst over all
    (0x7FF, 2, 0xF0F0, 0.3, False, True),
    (0x000, 0, 0, 0.5, False, True),
    (0x3C0, 2, 0xFFFF, 0.5, False, True),        # every bit of two bytes (CRC stuffing included)
    (0x181, 8, 0xFF << 56, 0.5, False, True),    # 8 bytes, taxel bits in byte 0, 56 zero bits after
    (0x181, 8, 0x3FF, 0.9, False, True),         # 8 bytes, the last 10 bits free
    (0x181, 1, 0x01, 0.5, True, True),
    (0x555, 2, 0xFFF0, 0.5, True, True),
    (0x2AA, 2, 0x0FF0, 1.0, True, False),        # no bit-rate switch: all nominal
    (0x000, 0, 0, 0.5, True, True),
    (0x181, 12, 0xFFF << 84, 0.5, True, True),   # CRC-17, 12 bytes, 12 taxel bits
    (0x181, 24, 0x3FF, 0.25, True, True),        # CRC-21, 24 bytes, the last 10 bits free
    (0x1F0, 64, 0xFF << 504, 0.5, True, True),   # 64 bytes, byte 0 free, then 63 zero bytes
]


@pytest.mark.parametrize("case", FRAME_CASES, ids=lambda c: f"{'fd' if c[4] else 'cc'}-0x{c[0]:X}-{c[1]}B-{c[2]:X}")
def test_frame_stats_equal_enumeration_of_every_payload(case):
    cob_id, n_bytes, mask, p_one, fd, brs = case
    st = pdo_frame_stats(cob_id, n_bytes, mask, p_one, fd=fd, brs=brs)
    mean_n, mean_d, worst_n, worst_d = enumerate_frame(cob_id, n_bytes, mask, p_one, fd, brs)
    assert st.mean_nominal == pytest.approx(mean_n, rel=1e-12, abs=1e-9)
    assert st.mean_data == pytest.approx(mean_d, rel=1e-12, abs=1e-9)
    assert st.worst_bits == worst_n + worst_d
    if fd and brs:   # the nominal phase does not depend on the payload
        assert st.worst_nominal == worst_n == st.mean_nominal


def test_worst_case_of_full_frames_lies_within_the_published_bounds():
    # classic: Davis et al. 2007 (135 bits for 8 bytes), no stuff bit at all: 8n + 47
    for cob_id in (0x181, 0x1FF, 0x2AA, 0x57F):
        st = pdo_frame_stats(cob_id, 8, FULL8, 0.5)
        assert 64 + 47 < st.mean_bits < st.worst_bits <= worst_case_frame_bits(8)
    # FD 64 bytes: fd_frame_bits_estimate per phase (the Linux kernel's total)
    nominal, data = fd_frame_bits_estimate(64)
    st = pdo_frame_stats(0x181, 64, (1 << 512) - 1, 0.5, fd=True)
    assert st.worst_nominal <= nominal and st.worst_data <= data
    assert st.mean_data > 5 + 512 + 32 and st.mean_data < st.worst_data


# ---------------------------------------------------------------- packing, by hand

def _mask(byte_values: bytes) -> int:
    return int.from_bytes(byte_values, "big")


def test_node_frames_by_hand():
    # one-taxel nodes: one byte; the decision is bit 0 (the last bit on the wire)
    assert node_frames(1, "decision", False) == [(1, 1, 0x01)]
    assert node_frames(1, "raw8", False) == [(1, 1, 0xFF)]
    assert node_frames(1, "real32", False) == [(4, 1, 0xFFFFFFFF)]
    # a 192-taxel patch: 192 decision bits = 3 classic frames of 64, or one 24-byte FD frame
    assert node_frames(192, "decision", False) == [(8, 64, FULL8)] * 3
    assert node_frames(192, "decision", True) == [(24, 192, (1 << 192) - 1)]
    # 192 readings of 8 bits: 24 classic frames of 8, 3 FD frames of 64
    assert node_frames(192, "raw8", False) == [(8, 8, FULL8)] * 24
    assert node_frames(192, "raw8", True) == [(64, 64, (1 << 512) - 1)] * 3
    # 100 decisions in FD: 13 bytes, padded to 16; taxels 96-99 in bits 0-3 of byte 12
    assert node_frames(100, "decision", True) == [(16, 100, _mask(b"\xff" * 12 + b"\x0f" + bytes(3)))]
    # 57 readings in FD: 57 bytes padded to 64
    assert node_frames(57, "raw8", True) == [(64, 57, _mask(b"\xff" * 57 + bytes(7)))]
    # 5 INTEGER16 readings on classic CAN: 4 in the first frame, 1 in a 2-byte frame
    assert node_frames(5, "raw16", False) == [(8, 4, FULL8), (2, 1, 0xFFFF)]
    # 70 decisions on classic CAN: 64 + 6 (one byte, bits 0-5)
    assert node_frames(70, "decision", False) == [(8, 64, FULL8), (1, 6, 0x3F)]


def test_skin_layout_by_hand():
    lay = skin_layout(200, taxels_per_node=192)          # decisions, classic
    assert len(lay.channels) == 1 and lay.n_nodes == 2 and lay.n_frames == 4
    frames = [(f.node_id, f.cob_id, f.n_bytes, f.taxels) for f in lay.channels[0].frames]
    assert frames == [(1, 0x181, 8, 64), (1, 0x182, 8, 64), (1, 0x183, 8, 64), (2, 0x184, 1, 8)]
    assert lay.channels[0].taxels == 200
    # one-taxel nodes: node k sends on its predefined TPDO1 0x180 + k; <= 127 nodes per channel
    lay = skin_layout(300)
    assert [len(ch.node_ids) for ch in lay.channels] == [100, 100, 100]
    for ch in lay.channels:
        assert [f.cob_id for f in ch.frames] == [0x180 + k for k in range(1, 101)]
        assert ch.node_ids == tuple(range(1, 101))
    assert [len(ch.node_ids) for ch in skin_layout(254).channels] == [127, 127]
    assert [len(ch.node_ids) for ch in skin_layout(255).channels] == [85, 85, 85]
    assert [len(ch.node_ids) for ch in skin_layout(256, channels=3).channels] == [86, 85, 85]
    # COB-IDs 0x181..0x57F: 30 patches of 192 INTEGER16 readings = 30 * 48 frames > 1023
    lay = skin_layout(30 * 192, taxels_per_node=192, payload="raw16")
    assert [len(ch.node_ids) for ch in lay.channels] == [15, 15]
    assert [len(ch.frames) for ch in lay.channels] == [720, 720]
    assert lay.channels[1].frames[-1].cob_id == 0x180 + 720


@pytest.mark.parametrize("call, name", [
    (lambda: skin_layout(0), "n_taxels"),
    (lambda: skin_layout(10, taxels_per_node=0), "taxels_per_node"),
    (lambda: skin_layout(10, payload="raw12"), "payload"),
    (lambda: skin_layout(300, channels=2), "channels"),
    (lambda: skin_layout(10, channels=11), "channels"),
    (lambda: skin_layout(128 * 512, taxels_per_node=128 * 512, payload="raw16"), "taxels_per_node"),
    (lambda: pdo_frame_stats(0x181, 9, 0), "n_bytes"),
    (lambda: pdo_frame_stats(0x181, 10, 0, fd=True), "n_bytes"),
    (lambda: pdo_frame_stats(0x800, 1, 0), "cob_id"),
    (lambda: pdo_frame_stats(0x181, 1, 0x100), "free_mask"),
    (lambda: pdo_frame_stats(0x181, 1, 1, 1.5), "p_one"),
    (lambda: layout_cycle_bits(skin_layout(4), p_change=-0.1), "p_change"),
    (lambda: layout_bus_use(skin_layout(4), nominal_bitrate=0), "nominal_bitrate"),
    (lambda: layout_bus_use(skin_layout(4), nominal_bitrate=1e6, sync_period_s=float("inf")), "sync_period_s"),
])
def test_bad_input_names_the_parameter(call, name):
    with pytest.raises(ParameterError) as exc:
        call()
    assert exc.value.name == name


# ---------------------------------------------------------------- bits per cycle, by hand

SYNC_BITS = 51          # 0x080 without data (hand-worked in test_bus_timing.py)


def test_cycle_bits_synchronous_and_event_driven_by_hand():
    lay = skin_layout(200, taxels_per_node=192)
    (ch,) = layout_cycle_bits(lay, p_one=0.0)                    # all decisions 0: exact frames
    zero_frames = [frame_bits(0x181, bytes(8)), frame_bits(0x182, bytes(8)), frame_bits(0x183, bytes(8)),
                   frame_bits(0x184, bytes(1))]
    assert ch.sync_bits == SYNC_BITS
    assert ch.mean_nominal == pytest.approx(sum(zero_frames) + SYNC_BITS)
    assert ch.mean_data == 0 and ch.worst_data == 0
    assert (ch.frames, ch.expected_frames, ch.nodes, ch.taxels) == (4, 4, 2, 200)
    # worst: every frame at its longest; the 8-taxel frame by enumeration of its 256 payloads
    last = max(frame_bits(0x184, bytes([x])) for x in range(256))
    big = [pdo_frame_stats(cob, 8, FULL8).worst_bits for cob in (0x181, 0x182, 0x183)]
    assert ch.worst_nominal == sum(big) + last + SYNC_BITS
    assert ch.heartbeat_bits == frame_bits(0x701, b"\x05") + frame_bits(0x702, b"\x05") == 58 + 58
    # event-driven, each taxel changing with probability 0.1 per cycle: a 64-taxel frame goes
    # out with probability 1 - 0.9^64, the 8-taxel frame with 1 - 0.9^8
    (ev,) = layout_cycle_bits(lay, p_one=0.0, p_change=0.1)
    sent = [1 - 0.9 ** 64] * 3 + [1 - 0.9 ** 8]
    assert ev.expected_frames == pytest.approx(sum(sent))
    assert ev.mean_nominal == pytest.approx(sum(s * b for s, b in zip(sent, zero_frames)) + SYNC_BITS)
    assert ev.worst_nominal == ch.worst_nominal            # every taxel changing at once
    (none,) = layout_cycle_bits(lay, p_change=0.0)
    assert none.mean_bits == SYNC_BITS and none.expected_frames == 0


def test_bus_use_of_the_chapters_57_one_taxel_nodes_by_hand():
    lay = skin_layout(57)
    use = layout_bus_use(lay, nominal_bitrate=1_000_000, sync_period_s=0.010, heartbeat_period_s=0.100, p_one=0.0)
    (ch,) = use.channels
    pdo = sum(frame_bits(0x180 + k, b"\x00") for k in range(1, 58))
    hb = sum(frame_bits(0x700 + k, b"\x05") for k in range(1, 58))
    worst = sum(max(frame_bits(0x180 + k, bytes([u])) for u in (0, 1)) for k in range(1, 58)) + SYNC_BITS
    assert ch.mean_cycle_s == pytest.approx((pdo + SYNC_BITS) / 1e6)
    assert ch.heartbeat_s_per_s == pytest.approx(hb / 1e6 / 0.1)
    assert ch.load == pytest.approx((pdo + SYNC_BITS) / 10_000 + hb / 100_000)
    assert ch.worst_cycle_s == pytest.approx(worst / 1e6)
    assert ch.max_sync_hz == pytest.approx((1 - hb / 100_000) / (worst / 1e6))
    assert use.busiest is ch and use.max_sync_hz == ch.max_sync_hz
    assert use.mean_bits == pytest.approx(pdo + SYNC_BITS)


def test_bus_use_of_an_fd_patch_by_hand():
    # 192 INTEGER8 readings: three 64-byte FD frames 0x181-0x183, at 1 Mbit/s nominal, 5 Mbit/s data
    lay = skin_layout(192, taxels_per_node=192, payload="raw8", fd=True)
    use = layout_bus_use(lay, nominal_bitrate=1e6, data_bitrate=5e6, sync_period_s=0.01, p_one=0.0)
    phases = [fd_frame_bits(cob, bytes(64)) for cob in (0x181, 0x182, 0x183)]
    seconds = sum(n / 1e6 + d / 5e6 for n, d in phases) + SYNC_BITS / 1e6
    (ch,) = use.channels
    assert ch.mean_cycle_s == pytest.approx(seconds)
    assert ch.load == pytest.approx(seconds / 0.01)
    assert use.mean_bits == pytest.approx(sum(n + d for n, d in phases) + SYNC_BITS)
    # the same frames without bit-rate switch: every bit at 1 Mbit/s
    slow = layout_bus_use(skin_layout(192, taxels_per_node=192, payload="raw8", fd=True, brs=False),
                   nominal_bitrate=1e6, sync_period_s=0.01, p_one=0.0)
    bits = sum(fd_frame_bits(cob, bytes(64), brs=False)[0] for cob in (0x181, 0x182, 0x183)) + SYNC_BITS
    assert slow.channels[0].mean_cycle_s == pytest.approx(bits / 1e6)


def test_channels_needed_by_hand():
    # two patches of 192 INTEGER8 readings, classic: each 24 frames of at most 135 bits (< 3,300 bits
    # with SYNC); both together more than 6,000 bits. 10 ms holds 10,000 bits at 1 Mbit/s, 5,000
    # at 500 kbit/s, 2,500 at 250 kbit/s (where one patch alone does not fit).
    kwargs = dict(taxels_per_node=192, payload="raw8", sync_period_s=0.01)
    one_patch = layout_cycle_bits(skin_layout(192, taxels_per_node=192, payload="raw8"))[0].worst_bits
    assert 2_500 < one_patch < 3_300
    assert channels_needed(384, nominal_bitrate=1_000_000, **kwargs) == 1
    assert channels_needed(384, nominal_bitrate=500_000, **kwargs) == 2
    assert channels_needed(384, nominal_bitrate=250_000, **kwargs) is None


def test_one_frame_per_taxel_hides_the_saving_that_packing_shows():
    # docs/bandwidth-and-report.md: with one node and one frame per taxel raw REAL32 costs ~1.37x
    # the bits of synchronous decisions (frame overhead dominates); packed in patch nodes the
    # frames carry 1 bit instead of 8 per taxel and the overhead is shared
    def bits(**kw):
        return layout_bus_use(skin_layout(**kw), nominal_bitrate=1e6).mean_bits

    per_taxel = bits(n_taxels=57, payload="real32") / bits(n_taxels=57)
    assert 1.3 < per_taxel < 1.45
    packed = bits(n_taxels=192, taxels_per_node=192, payload="raw8") / bits(n_taxels=192, taxels_per_node=192)
    assert packed > 6    # 24 frames of readings against 3 of decisions
