"""fusion-center bandwidth: hand-computed figures for a two-taxel scene.

Frame lengths come from an independent bit-level CAN 2.0A encoder written here (CRC-15 by
polynomial long division, not the shift register of fusion_center.core.bus_timing), and the
per-cycle sums, loads, rates and latencies are worked by hand in each test.
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from fusion_center import cli
from fusion_center.report import bandwidth
from taxel_net.scene import load_scene

TINY = """
[scene]
name = "tiny"
cycles = 10

[bus]
bitrate = 125000
sync_period_ms = 10.0
heartbeat_producer_ms = 100
inhibit_time_100us = {inhibit}
channels = ["taxel0"]

[kinds.R]
zeta_mv = 1.0
noise_mv = 0.5
noise_sigma_mv = 0.0
signal_mv = 3.0

[[taxels]]
node_id = 1
kind = "R"
x = 0.0
y = 0.0

[[taxels]]
node_id = 2
kind = "R"
x = 10.0
y = 0.0

[object]
model = "large"
x = 5.0
y = 0.0
radius = 20.0
present = [[2, 4]]

[fusion]
rules = ["additive", "k-of-n"]
tuple = "pm1"
k = 1
"""


def _bits(value, width):
    return [(value >> (width - 1 - i)) & 1 for i in range(width)]


def _crc15_long_division(bits):
    # remainder of M(x) * x^15 divided by G(x) = x^15+x^14+x^10+x^8+x^7+x^4+x^3+1
    gen = [1, 1, 0, 0, 0, 1, 0, 1, 1, 0, 0, 1, 1, 0, 0, 1]
    work = list(bits) + [0] * 15
    for i in range(len(bits)):
        if work[i]:
            for j, g in enumerate(gen):
                work[i + j] ^= g
    return work[-15:]


def reference_frame_bits(can_id: int, data: bytes) -> int:
    fields = [0] + _bits(can_id, 11) + [0, 0, 0] + _bits(len(data), 4)
    for b in data:
        fields += _bits(b, 8)
    seq = fields + _crc15_long_division(fields)
    stuffed, run, last = 0, 0, None
    for b in seq:
        run = run + 1 if b == last else 1
        last = b
        if run == 5:
            stuffed += 1
            last, run = 1 - b, 1
    return len(seq) + stuffed + 10 + 3  # + CRC delim, ACK slot, ACK delim, EOF(7) + intermission(3)


@pytest.fixture
def tiny(tmp_path):
    def make(inhibit=0):
        p = tmp_path / f"tiny{inhibit}.toml"
        p.write_text(TINY.format(inhibit=inhibit))
        return load_scene(p)
    return make


def test_reference_encoder_bounds():
    # no frame can be shorter than the unstuffed length 8n + 47 nor longer than the worst case
    for can_id in (0x080, 0x181, 0x282, 0x701):
        for data in (b"", b"\x01", b"\xff", b"\x00\x00\x00\x00"):
            n = len(data)
            assert 8 * n + 47 <= reference_frame_bits(can_id, data) <= 8 * n + 47 + (34 + 8 * n - 1) // 4


def test_decision_sync_hand_computed(tiny):
    scene = tiny()
    fig = bandwidth.bandwidth_figures(scene)
    sync = reference_frame_bits(0x080, b"")
    hb = reference_frame_bits(0x701, b"\x05") + reference_frame_bits(0x702, b"\x05")
    hb_per_cycle = hb * 10.0 / 100.0  # one heartbeat per node every 100 ms, SYNC every 10 ms
    absent = reference_frame_bits(0x181, b"\xff") + reference_frame_bits(0x182, b"\xff")  # u = -1 (INTEGER8)
    present = reference_frame_bits(0x181, b"\x01") + reference_frame_bits(0x182, b"\x01")
    # cycles 2, 3 present (object [2, 4)), the other 8 absent
    cycle_bits = [sync + (present if c in (2, 3) else absent) for c in range(10)]
    m = fig["modes"]["decision_sync"]
    assert m["sync_bits"] == sync
    assert m["bits_per_cycle"] == pytest.approx(np.mean(cycle_bits) + hb_per_cycle)
    assert m["bits_per_cycle_worst"] == pytest.approx(max(cycle_bits) + hb_per_cycle)
    assert m["bus_load"] == pytest.approx((np.mean(cycle_bits) + hb_per_cycle) / (0.010 * 125000))
    assert m["latency_ms"] == pytest.approx(1000 * max(cycle_bits) / 125000)
    hb_bits_per_s = hb / 0.1
    assert m["max_cycle_rate_hz"] == pytest.approx((125000 - hb_bits_per_s) / max(cycle_bits))
    assert m["pdo_frames_per_cycle"] == 2


def test_raw_hand_computed(tiny):
    scene = tiny()
    fig = bandwidth.bandwidth_figures(scene)
    # sigma = 0: X = N = 0.5 mV absent, X = S + N = 3.5 mV present, as REAL32 little endian
    def pdo(x):
        data = struct.pack("<f", x)
        return reference_frame_bits(0x281, data) + reference_frame_bits(0x282, data)
    sync = reference_frame_bits(0x080, b"")
    cycle_bits = [sync + (pdo(3.5) if c in (2, 3) else pdo(0.5)) for c in range(10)]
    hb = (reference_frame_bits(0x701, b"\x05") + reference_frame_bits(0x702, b"\x05")) * 0.1
    assert fig["modes"]["raw"]["bits_per_cycle"] == pytest.approx(np.mean(cycle_bits) + hb)
    assert fig["modes"]["raw"]["latency_ms"] == pytest.approx(1000 * max(cycle_bits) / 125000)


def test_decision_event_counts_changes(tiny):
    scene = tiny()
    fig = bandwidth.bandwidth_figures(scene)
    # each node sends at cycle 0 (first value), 2 (-1 -> +1) and 4 (+1 -> -1): 6 frames in 10 cycles
    m = fig["modes"]["decision_event"]
    assert m["pdo_frames_per_cycle"] == pytest.approx(6 / 10)
    sync = reference_frame_bits(0x080, b"")
    f_abs = reference_frame_bits(0x181, b"\xff") + reference_frame_bits(0x182, b"\xff")
    f_pre = reference_frame_bits(0x181, b"\x01") + reference_frame_bits(0x182, b"\x01")
    hb = (reference_frame_bits(0x701, b"\x05") + reference_frame_bits(0x702, b"\x05")) * 0.1
    assert m["bits_per_cycle"] == pytest.approx((10 * sync + 2 * f_abs + f_pre) / 10 + hb)


def test_inhibit_time_delays_events():
    # decisions of one node: -1 -1 +1 +1 -1 -1 -1 ; SYNC 10 ms, inhibit 25 ms (250 x 100 us)
    u = np.array([[-1], [-1], [1], [1], [-1], [-1], [-1]])
    sends = bandwidth.event_transmissions(u, 10.0, 250, 0)[:, 0]
    # cycle 0 sends; change at 2 (20 ms) inhibited until 25 ms -> sent at cycle 3 (30 ms);
    # change at 4 (40 ms) inhibited until 55 ms -> sent at cycle 6 (60 ms)
    assert sends.tolist() == [True, False, False, True, False, False, True]
    # event timer 30 ms without inhibit: a frame at least every 3 cycles even without change
    sends = bandwidth.event_transmissions(np.full((7, 1), -1), 10.0, 0, 30)[:, 0]
    assert sends.tolist() == [True, False, False, True, False, False, True]


def test_two_channels_reported_separately():
    scene = load_scene("scenes/two_buses_200.toml")
    fig = bandwidth.bandwidth_figures(scene, 500000, cycles=3)
    chans = fig["modes"]["decision_sync"]["channels"]
    assert [c["channel"] for c in chans] == ["taxel0", "taxel1"]
    assert [c["taxels"] for c in chans] == [100, 100]
    # 100 one-byte TPDOs and one SYNC per cycle on each bus
    assert all(c["pdo_frames_per_cycle"] == 100 for c in chans)


def test_cli_json_and_bad_bitrate(tiny, capsys):
    scene = tiny()
    assert cli.main(["bandwidth", "--scene", scene.path, "--bitrate", "500000", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["modes"]) == {"raw", "decision_sync", "decision_event"}
    assert out["bitrate"] == 500000
    assert cli.main(["bandwidth", "--scene", scene.path, "--bitrate", "500k", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == out  # 500k as python-can's tools write it
    with pytest.raises(SystemExit) as exit_:
        cli.main(["bandwidth", "--scene", scene.path, "--bitrate", "2000000"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "'2000000'" in err and "1..1000000" in err and len(err.strip().splitlines()) == 1


def test_report_into_a_directory_that_cannot_be_made_exits_2(tiny, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert cli.main(["report", "--scene", tiny().path, "--out", str(blocker / "x"), "--trials", "10"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out" in err[0] and "Not a directory" in err[0]


def test_patch_scene_priced_on_its_packed_tagged_tpdos(tmp_path):
    # the two taxels as ONE patch node (node 1) with a SYNC counter 4: its decisions in one TPDO
    # 0x181 = [tag = SYNC counter, bit 0 = taxel 0, bit 1 = taxel 1]; the SYNC carries 1..4
    text = TINY.format(inhibit=0).replace("node_id = 2", "node_id = 1").replace(
        'channels = ["taxel0"]', 'channels = ["taxel0"]\npatch_nodes = true\nsync_counter = 4\nraw_format = "int8"\n'
                                 'raw_lsb_mv = 0.1')
    p = tmp_path / "patch.toml"
    p.write_text(text)
    fig = bandwidth.bandwidth_figures(load_scene(p))
    counter = [c % 4 + 1 for c in range(10)]
    present = [c in (2, 3) for c in range(10)]
    sync = [reference_frame_bits(0x080, bytes([k])) for k in counter]
    dec = [reference_frame_bits(0x181, bytes([k, 0b11 if on else 0])) for k, on in zip(counter, present)]
    hb = reference_frame_bits(0x701, b"\x05") * 0.1  # ONE node: one heartbeat per 100 ms
    m = fig["modes"]["decision_sync"]
    assert m["pdo_frames_per_cycle"] == 1 and fig["nodes"] == 1
    assert m["bits_per_cycle"] == pytest.approx(np.mean([s + d for s, d in zip(sync, dec)]) + hb)
    assert m["bits_per_cycle_worst"] == pytest.approx(max(s + d for s, d in zip(sync, dec)) + hb)
    # raw: INTEGER8 counts of 0.1 mV, X = N = 0.5 mV absent (5), X = S + N = 3.5 mV present (35)
    raw = [reference_frame_bits(0x181, bytes([k, 35, 35] if on else [k, 5, 5])) for k, on in zip(counter, present)]
    assert fig["modes"]["raw"]["bits_per_cycle"] == pytest.approx(np.mean([s + r for s, r in zip(sync, raw)]) + hb)
    # event-driven: the TPDO goes out at cycle 0 and when its decisions change (cycles 2 and 4)
    ev = fig["modes"]["decision_event"]
    assert ev["pdo_frames_per_cycle"] == pytest.approx(3 / 10)
    assert ev["bits_per_cycle"] == pytest.approx((sum(sync) + dec[0] + dec[2] + dec[4]) / 10 + hb)


def test_fd_scene_frames_priced_in_bit_times_at_both_rates(tmp_path):
    from fusion_center.core.bus_timing import fd_frame_bits

    text = TINY.format(inhibit=0).replace("node_id = 2", "node_id = 1").replace(
        'channels = ["taxel0"]', 'channels = ["taxel0"]\npatch_nodes = true\nfd = true\ndata_bitrate = 2000000')
    p = tmp_path / "fd.toml"
    p.write_text(text)
    fig = bandwidth.bandwidth_figures(load_scene(p))
    present = [c in (2, 3) for c in range(10)]
    def fd_time(data):
        nominal, data_phase = fd_frame_bits(0x181, data, brs=True)
        return nominal + data_phase * 125000 / 2000000
    dec = [fd_time(bytes([0b11 if on else 0])) for on in present]  # untagged, one byte
    sync = reference_frame_bits(0x080, b"")
    hb = reference_frame_bits(0x701, b"\x05") * 0.1
    assert fig["modes"]["decision_sync"]["bits_per_cycle"] == pytest.approx(sync + np.mean(dec) + hb)
