"""Cycle tags and SYNC counters in skin layouts (fusion_center.core.layouts / pdo_frames).

A tagged PDO frame starts with one UNSIGNED8 byte, the SYNC counter 1..N the taxels were
sampled at. Its mean (over tag values, equally often, and payloads) and its worst case are
checked against enumerating every tag value and every payload through ``frame_bits`` /
``fd_frame_bits``; the packing, the SYNC frame with its counter and the latency are worked
out by hand.
"""

from __future__ import annotations

import itertools

import pytest

from fusion_center.core.bus_timing import fd_frame_bits, frame_bits
from fusion_center.core.layouts import (
    layout_bus_use,
    layout_cycle_bits,
    node_frames,
    pdo_frame_stats,
    skin_layout,
    sync_frame_bits,
)
from taxel_net.errors import ParameterError


def enumerate_tagged(cob_id, n_bytes, free_mask, p_one, fd, tags, brs=True):
    """(mean nominal, mean data, worst total) over every tag value and every payload."""
    nbits = 8 * n_bytes
    free = [k for k in range(nbits) if free_mask >> (nbits - 1 - k) & 1]
    mean_n = mean_d = 0.0
    worst = -1
    for tag in tags:
        for values in itertools.product((0, 1), repeat=len(free)):
            word, weight = tag << (nbits - 8), 1.0 / len(tags)
            for k, v in zip(free, values):
                word |= v << (nbits - 1 - k)
                weight *= p_one if v else 1.0 - p_one
            data = word.to_bytes(n_bytes, "big")
            nominal, data_bits = fd_frame_bits(cob_id, data, brs=brs) if fd else (frame_bits(cob_id, data), 0)
            mean_n += weight * nominal
            mean_d += weight * data_bits
            worst = max(worst, nominal + data_bits)
    return mean_n, mean_d, worst


TAG_CASES = [
    # (cob_id, n_bytes, free_mask, p_one, fd, tags)
    (0x181, 1, 0, 0.5, False, tuple(range(1, 65))),           # the tag alone, counter 1..64
    (0x181, 2, 0xFF, 0.5, False, tuple(range(1, 65))),        # tag + 8 decisions
    (0x1F0, 3, 0x00FFF0, 0.3, False, (1, 2, 3, 31, 32, 33)),
    (0x57F, 8, 0x0F, 0.9, False, tuple(range(1, 241))),       # full frame, counter 1..240
    (0x181, 1, 0, 0.5, True, tuple(range(1, 65))),            # FD: the tag ends the data field
    (0x181, 2, 0xF0, 0.5, True, tuple(range(1, 17))),
    (0x2AA, 12, 0xFF << 80, 0.25, True, (1, 7, 8, 15, 16, 64)),   # CRC-17
    (0x181, 24, 0x3F, 0.5, True, tuple(range(1, 17))),        # CRC-21, 6 free bits at the end
    (0x181, 2, 0xFF, 0.5, True, (1, 2, 3, 4, 5)),
]


@pytest.mark.parametrize("case", TAG_CASES, ids=lambda c: f"{'fd' if c[4] else 'cc'}-0x{c[0]:X}-{c[1]}B-{c[2]:X}")
def test_tagged_frame_equals_enumeration_of_every_tag_and_payload(case):
    cob_id, n_bytes, mask, p_one, fd, tags = case
    st = pdo_frame_stats(cob_id, n_bytes, mask, p_one, fd=fd, tag_values=tags)
    mean_n, mean_d, worst = enumerate_tagged(cob_id, n_bytes, mask, p_one, fd, tags)
    assert st.mean_nominal == pytest.approx(mean_n, rel=1e-12, abs=1e-9)
    assert st.mean_data == pytest.approx(mean_d, rel=1e-12, abs=1e-9)
    assert st.worst_bits == worst


def test_tagged_frame_without_bit_rate_switch():
    tags = tuple(range(1, 33))
    st = pdo_frame_stats(0x305, 2, 0x0F, 0.5, fd=True, brs=False, tag_values=tags)
    mean_n, mean_d, worst = enumerate_tagged(0x305, 2, 0x0F, 0.5, True, tags, brs=False)
    assert mean_d == 0 and st.mean_data == 0
    assert st.mean_nominal == pytest.approx(mean_n, rel=1e-12)
    assert st.worst_bits == worst


def test_tag_byte_is_not_a_taxel_byte():
    with pytest.raises(ParameterError) as exc:
        pdo_frame_stats(0x181, 2, 0x8000, tag_values=(1, 2))   # a free bit inside byte 0
    assert exc.value.name == "free_mask"
    with pytest.raises(ParameterError) as exc:
        pdo_frame_stats(0x181, 2, 0xFF, tag_values=(256,))
    assert exc.value.name == "tag_values"


def test_tagged_packing_by_hand():
    full7 = (1 << 56) - 1                       # bytes 1..7 of an 8-byte frame
    # 192 decisions: 56 per classic frame after the tag, 3 x 56 + 24 (3 bytes after the tag)
    assert node_frames(192, "decision", False, 1) == [(8, 56, full7)] * 3 + [(4, 24, 0xFFFFFF)]
    # FD: 24 bytes of decisions after the tag = 25 bytes, padded to 32; bytes 1..24 carry them
    assert node_frames(192, "decision", True, 1) == [(32, 192, ((1 << 192) - 1) << 56)]
    # 192 INTEGER8 readings: 7 per classic frame (28 frames, the last with 3), 63 per FD frame
    classic = node_frames(192, "raw8", False, 1)
    assert len(classic) == 28 and classic[-1] == (4, 3, 0xFFFFFF) and classic[0] == (8, 7, full7)
    assert node_frames(192, "raw8", True, 1) == [(64, 63, (1 << 504) - 1)] * 3 + [(4, 3, 0xFFFFFF)]
    # 10 decisions: taxel j in bit j mod 8 of byte 1 + j div 8; on the wire byte 1's MSB first
    assert node_frames(10, "decision", False, 1) == [(3, 10, 0xFF03)]
    # no tag: as before
    assert node_frames(10, "decision", False, 0) == [(2, 10, 0xFF03)]
    lay = skin_layout(400, taxels_per_node=192, tag_bytes=1)
    assert lay.tag_bytes == 1
    assert [(f.node_id, f.cob_id, f.n_bytes, f.taxels) for f in lay.channels[0].frames] == [
        (1, 0x181, 8, 56), (1, 0x182, 8, 56), (1, 0x183, 8, 56), (1, 0x184, 4, 24),
        (2, 0x185, 8, 56), (2, 0x186, 8, 56), (2, 0x187, 8, 56), (2, 0x188, 4, 24),
        (3, 0x189, 3, 16)]


def test_sync_counter_and_tag_in_the_cycle_by_hand():
    # SYNC with a counter 1..64: one data byte, mean over the 64 values, the longest as worst
    sync = [frame_bits(0x080, bytes([c])) for c in range(1, 65)]
    assert sync_frame_bits(64) == (pytest.approx(sum(sync) / 64), max(sync))
    assert sync_frame_bits(0) == (51, 51)
    lay = skin_layout(20, taxels_per_node=20, tag_bytes=1)       # one frame: tag + 3 bytes
    (ch,) = layout_cycle_bits(lay, sync_counter=64, p_one=0.0)
    frames = [frame_bits(0x181, bytes([c, 0, 0, 0])) for c in range(1, 65)]
    assert ch.mean_nominal == pytest.approx(sum(frames) / 64 + sum(sync) / 64)
    # worst: the frame at its longest (enumerated in the test above) after the longest SYNC
    assert ch.worst_nominal == pdo_frame_stats(0x181, 4, 0xFFFF0F, tag_values=tuple(range(1, 65))).worst_bits + max(sync)
    # a tag needs a counter; a counter without tags only lengthens the SYNC
    with pytest.raises(ParameterError) as exc:
        layout_cycle_bits(lay)
    assert exc.value.name == "sync_counter"
    for bad in (1, 241, -1, True, 2.5):
        with pytest.raises(ParameterError) as exc:
            layout_cycle_bits(skin_layout(4), sync_counter=bad)
        assert exc.value.name == "sync_counter"
    with pytest.raises(ParameterError) as exc:
        skin_layout(4, tag_bytes=2)
    assert exc.value.name == "tag_bytes"
    (plain,) = layout_cycle_bits(skin_layout(4), sync_counter=64, p_one=0.0)
    assert plain.mean_nominal == pytest.approx(sum(frame_bits(0x180 + k, b"\x00") for k in range(1, 5))
                                               + sum(sync) / 64)


def test_latency_is_the_worst_case_cycle_by_hand():
    # two patches of 192 decisions in tagged FD frames (32 bytes each) on one channel, 1M / 5M:
    # SYNC (longest of its counter values) then both frames at their longest
    tags = tuple(range(1, 65))
    lay = skin_layout(384, taxels_per_node=192, fd=True, tag_bytes=1)
    use = layout_bus_use(lay, nominal_bitrate=1e6, data_bitrate=5e6, sync_counter=64)
    mask = ((1 << 192) - 1) << 56
    worst = [pdo_frame_stats(cob, 32, mask, fd=True, tag_values=tags) for cob in (0x181, 0x182)]
    sync = max(frame_bits(0x080, bytes([c])) for c in tags)
    expected = sync / 1e6 + sum(w.worst_nominal / 1e6 + w.worst_data / 5e6 for w in worst)
    (ch,) = use.channels
    assert ch.latency_s == pytest.approx(expected) and use.latency_s == ch.latency_s
    # at least the fixed bits: 29 nominal + 6 + 256 + 4 + 21 + 6 data-phase bits per frame (no stuffing)
    assert all(w.worst_nominal >= 29 and w.worst_data >= 6 + 256 + 4 + 21 + 6 for w in worst)
