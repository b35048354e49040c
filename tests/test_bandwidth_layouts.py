"""``fusion-center bandwidth --layouts`` / ``--taxels N``: layouts compared, worked by hand.

Classic frames are priced with the independent bit-level encoder of test_bandwidth.py (CRC-15
by long division), FD frames with ``fd_frame_bits`` (checked bit by bit in
test_fd_frame_bits.py); means over payloads and tag values, worst cases, loads, SYNC rates and
latencies are summed by hand for three taxels.
"""

from __future__ import annotations

import json

import pytest

from fusion_center import cli
from fusion_center.core.bus_timing import fd_frame_bits
from test_bandwidth import TINY, reference_frame_bits

RATE, DATA, PERIOD, HB = 500_000, 2_000_000, 0.010, 0.100


def run_json(capsys, *args):
    assert cli.main(["bandwidth", *args, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def row(out, layout, payload, bus, mode="sync"):
    (r,) = [r for r in out["layouts"]["rows"]
            if (r["layout"], r["payload"], r["bus"], r["mode"]) == (layout, payload, bus, mode)]
    return r


def stats(frames):
    """frames: [(COB-ID, [payload alternatives, equally likely])] -> (mean, worst) classic bits."""
    mean = sum(sum(reference_frame_bits(c, d) for d in alts) / len(alts) for c, alts in frames)
    worst = sum(max(reference_frame_bits(c, d) for d in alts) for c, alts in frames)
    return mean, worst


def hb_bits(nodes):
    return sum(reference_frame_bits(0x700 + k, b"\x05") for k in nodes)


def check(r, mean, worst, hb, *, data_mean=0.0, data_worst=0, frames=None):
    seconds = (mean - data_mean) / RATE + data_mean / DATA
    worst_s = (worst - data_worst) / RATE + data_worst / DATA
    assert r["bits_per_cycle"] == pytest.approx(mean)
    assert r["bits_per_cycle_worst"] == worst
    assert r["bus_load"] == pytest.approx(seconds / PERIOD + hb / RATE / HB)
    assert r["max_sync_hz"] == pytest.approx((1 - hb / RATE / HB) / worst_s)
    assert r["latency_ms"] == pytest.approx(1000 * worst_s)
    if frames is not None:
        assert r["pdo_frames_per_cycle"] == pytest.approx(frames)


def test_three_taxels_every_layout_by_hand(capsys):
    out = run_json(capsys, "--taxels", "3", "--patch", "2", "--bitrate", "500k", "--data-bitrate", "2M",
                   "--p-change", "0.1")
    sync = reference_frame_bits(0x080, b"")
    assert sync == 51
    # one-taxel nodes 1-3 on 0x181-0x183; a decision is bit 0 of one byte, a reading the whole byte
    dec = [(0x180 + k, [b"\x00", b"\x01"]) for k in (1, 2, 3)]
    raw = [(0x180 + k, [bytes([x]) for x in range(256)]) for k in (1, 2, 3)]
    hb3 = hb_bits((1, 2, 3))
    m, w = stats(dec)
    check(row(out, "per-taxel", "decision", "classic"), m + sync, w + sync, hb3, frames=3)
    m, w = stats(raw)
    check(row(out, "per-taxel", "raw8", "classic"), m + sync, w + sync, hb3)
    # event-driven: each one-taxel frame goes out with probability 0.1; worst case: all of them
    ev = row(out, "per-taxel", "decision", "classic", "event")
    m, w = stats(dec)
    check(ev, 0.1 * m + sync, w + sync, hb3, frames=0.3)
    # patches of 2: node 1 sends taxels 0-1 in bits 0-1 of 0x181, node 2 taxel 2 in bit 0 of 0x182
    dec2 = [(0x181, [bytes([x]) for x in range(4)]), (0x182, [b"\x00", b"\x01"])]
    hb2 = hb_bits((1, 2))
    m, w = stats(dec2)
    check(row(out, "patch2", "decision", "classic"), m + sync, w + sync, hb2, frames=2)
    ev = row(out, "patch2", "decision", "classic", "event")
    check(ev, (1 - 0.9 ** 2) * stats(dec2[:1])[0] + 0.1 * stats(dec2[1:])[0] + sync, w + sync, hb2,
          frames=(1 - 0.9 ** 2) + 0.1)
    # readings: node 1 two bytes (every one of the 65,536 payloads), node 2 one byte
    raw2 = [(0x181, [bytes([a, b]) for a in range(256) for b in range(256)]), (0x182, [bytes([x]) for x in range(256)])]
    m, w = stats(raw2)
    r = row(out, "patch2", "raw8", "classic")
    check(r, m + sync, w + sync, hb2, frames=2)
    assert r["channels"] == 1 and r["nodes"] == 2
    # CAN FD with BRS: (nominal, data) phases per frame, 500k / 2M
    phases = {k: [fd_frame_bits(0x180 + k, bytes([u])) for u in (0, 1)] for k in (1, 2, 3)}
    nominal = sum(p[0][0] for p in phases.values())        # the nominal part does not depend on the payload
    data_mean = sum((p[0][1] + p[1][1]) / 2 for p in phases.values())
    data_worst = sum(max(p[0][1], p[1][1]) for p in phases.values())
    check(row(out, "per-taxel", "decision", "FD"), nominal + data_mean + sync, nominal + data_worst + sync, hb3,
          data_mean=data_mean, data_worst=data_worst)
    # raw8 / decision ratio of bus time per cycle, one-taxel nodes on classic CAN
    ratio = out["layouts"]["raw_over_decision"]["per-taxel classic"]["mean"]
    assert ratio == pytest.approx((stats(raw)[0] + sync) / (stats(dec)[0] + sync))


def test_sync_counter_tags_patch_frames_by_hand(capsys):
    out = run_json(capsys, "--taxels", "3", "--patch", "2", "--bitrate", "500k", "--data-bitrate", "2M",
                   "--sync-counter", "4")
    syncs = [reference_frame_bits(0x080, bytes([c])) for c in (1, 2, 3, 4)]
    sync_mean, sync_worst = sum(syncs) / 4, max(syncs)
    # patch frames lead with the tag byte 1..4: [tag, decisions]
    dec2 = [(0x181, [bytes([t, x]) for t in (1, 2, 3, 4) for x in range(4)]),
            (0x182, [bytes([t, x]) for t in (1, 2, 3, 4) for x in (0, 1)])]
    m, w = stats(dec2)
    check(row(out, "patch2", "decision", "classic"), m + sync_mean, w + sync_worst, hb_bits((1, 2)))
    # one-taxel nodes keep their one byte; only the SYNC grows
    m, w = stats([(0x180 + k, [b"\x00", b"\x01"]) for k in (1, 2, 3)])
    check(row(out, "per-taxel", "decision", "classic"), m + sync_mean, w + sync_worst, hb_bits((1, 2, 3)))
    assert row(out, "patch2", "decision", "classic")["tag_bytes"] == 1
    assert row(out, "per-taxel", "decision", "classic")["tag_bytes"] == 0


def test_channels_and_per_channel_latency(capsys):
    # 300 one-taxel nodes need 3 channels (<= 127 nodes each); asking for 4 spreads them 75 each,
    # and each channel's latency is its own SYNC + 75 frames at their longest
    out = run_json(capsys, "--taxels", "300", "--channels", "4", "--bitrate", "1M")
    r = row(out, "per-taxel", "decision", "classic")
    assert r["channels"] == 4 and [c["nodes"] for c in r["per_channel"]] == [75] * 4
    worst = 51 + sum(max(reference_frame_bits(0x180 + k, bytes([u])) for u in (0, 1)) for k in range(1, 76))
    assert [c["latency_ms"] for c in r["per_channel"]] == pytest.approx([worst / 1000.0] * 4)
    # the 2 patches of 192 cannot use 4 channels: one node per channel at most
    assert row(out, "patch192", "decision", "classic")["channels"] == 2


def test_scene_layouts_use_the_scene_bus(tmp_path, capsys):
    path = tmp_path / "tiny.toml"
    path.write_text(TINY.format(inhibit=0))
    out = run_json(capsys, "--scene", str(path), "--layouts")
    assert set(out["modes"]) == {"raw", "decision_sync", "decision_event"}   # the scene's own table stays
    lay = out["layouts"]
    assert (lay["taxels"], lay["nominal_bitrate"], lay["sync_period_ms"], lay["sync_counter"]) == (2, 125000, 10.0, 0)
    m, w = stats([(0x181, [b"\x00", b"\x01"]), (0x182, [b"\x00", b"\x01"])])
    r = row(out, "per-taxel", "decision", "classic")
    assert r["bits_per_cycle"] == pytest.approx(m + 51) and r["latency_ms"] == pytest.approx((w + 51) / 125.0)


@pytest.mark.parametrize("args, flag, allowed", [
    (["--taxels", "0"], "--taxels", "1..1000000"),
    (["--taxels", "x"], "--taxels", "1..1000000"),
    (["--taxels", "8", "--patch", "1"], "--patch", "2..100000"),
    (["--taxels", "8", "--raw", "raw12"], "--raw", "raw8"),
    (["--taxels", "8", "--data-bitrate", "9M"], "--data-bitrate", "1..8000000"),
    (["--taxels", "8", "--data-bitrate", "500k"], "--data-bitrate", "1000000..8000000"),
    (["--taxels", "8", "--p-change", "1.5"], "--p-change", "[0, 1]"),
    (["--taxels", "8", "--sync-counter", "1"], "--sync-counter", "2..240"),
    (["--taxels", "8", "--channels", "0"], "--channels", "1..10000"),
    (["--taxels", "8", "--bitrate", "2M"], "--bitrate", "1..1000000"),
    ([], "--taxels", "--scene"),
])
def test_bad_values_exit_2_with_one_line(args, flag, allowed, capsys):
    with pytest.raises(SystemExit) as exc:
        code = cli.main(["bandwidth", *args])
        raise SystemExit(code)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and flag in err[0] and allowed in err[0]
