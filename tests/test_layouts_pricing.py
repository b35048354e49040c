"""layout_cycle_bits prices each distinct channel once (issue 14's scale figures call it for
skins of up to 8192 one-taxel nodes: 65 channels, 63 of them alike) and every channel's bits
still equal those of the channel priced on its own (``_channel_bits``: the frame-by-frame sum of
``pdo_frame_stats``, checked against enumeration in test_layouts.py) and its heartbeats'
``frame_bits`` (bit by bit in test_bus_timing.py)."""

from __future__ import annotations

import pytest

from fusion_center.core import layouts
from fusion_center.core.bus_timing import frame_bits
from fusion_center.core.layouts import layout_cycle_bits, skin_layout


@pytest.mark.parametrize("kwargs, p_change, sync_counter", [
    ({}, None, 0),                                              # 8 channels: 7 of 127 nodes, one of 127 - 1
    ({"fd": True}, 0.05, 0),
    ({"tag_bytes": 1}, 0.2, 17),
    ({"channels": 11}, None, 0),                               # 92 / 91 nodes: two kinds of channel
])
def test_every_channel_equals_its_frame_by_frame_sum(kwargs, p_change, sync_counter):
    layout = skin_layout(1015, **kwargs)
    assert len(layout.channels) > 1
    bits = layout_cycle_bits(layout, p_one=0.3, p_change=p_change, sync_counter=sync_counter)
    sync = [frame_bits(0x080, bytes([c]) if sync_counter else b"") for c in (range(1, sync_counter + 1) or [0])]
    for ch, got in zip(layout.channels, bits, strict=True):
        # the channel priced on its own (no sharing), its heartbeats frame by frame
        tags = tuple(range(1, sync_counter + 1)) if layout.tag_bytes else ()
        exp, mean_n, mean_d, worst_n, worst_d, _ = layouts._channel_bits(ch, layout, 0.3, p_change, tags)
        hb = sum(frame_bits(0x700 + node, b"\x05") for node in ch.node_ids)
        assert got.channel == ch.index and got.nodes == len(ch.node_ids) and got.taxels == ch.taxels
        assert got.frames == len(ch.frames) and got.expected_frames == exp
        assert got.mean_nominal == mean_n + sum(sync) / len(sync) and got.mean_data == mean_d
        assert got.worst_nominal == worst_n + max(sync) and got.worst_data == worst_d
        assert got.heartbeat_bits == hb


def test_alike_channels_are_priced_once(monkeypatch):
    """8192 one-taxel nodes: 65 channels of 126 or 127 nodes (COB-IDs from 0x181 on each): the
    frames of two channels are priced, not of 65 (main priced every frame of every channel)."""
    layout = skin_layout(8192)
    kinds = {(ch.node_ids, ch.frames) for ch in layout.channels}
    assert len(layout.channels) == 65 and len(kinds) == 2
    calls = []
    real = layouts.pdo_frame_stats
    monkeypatch.setattr(layouts, "pdo_frame_stats", lambda *a, **k: calls.append(a) or real(*a, **k))
    bits = layout_cycle_bits(layout)
    assert len(calls) == sum(len(frames) for _, frames in kinds)
    by_kind = {}
    for ch, b in zip(layout.channels, bits):
        fields = (b.nodes, b.taxels, b.frames, b.mean_nominal, b.worst_nominal, b.heartbeat_bits)
        assert by_kind.setdefault((ch.node_ids, ch.frames), fields) == fields
