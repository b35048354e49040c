"""The SYNC-cycle assembler on patch nodes (issue 14): hand-built streams of packed TPDOs
(``taxel_net.patches.pack``), hand-worked expectations (no bus, no clock)."""

import math

import numpy as np
import pytest

from taxel_net.patches import devices, pack
from taxel_net.scene import BusSpec, FusionSpec, Scene, TaxelSpec
from fusion_center.service.cycle_records import FLAG_FD
from fusion_center.service.cycles import CycleAssembler
from fusion_center.service.pipeline import CyclePipeline

MS = 1000  # µs


def patch_scene(sizes=(10, 70), mode="decision", sync_counter=64, fd=False, raw_format="int16", channels=("c0",),
                node_channels=None, window_us=0, lsb=0.01):
    """Patch node k+1 (channel node_channels[k], default 0) hosts sizes[k] taxels."""
    taxels = []
    for k, size in enumerate(sizes):
        ch = node_channels[k] if node_channels else 0
        taxels += [TaxelSpec(node_id=k + 1, kind="C", channel=ch, zeta_mv=1.0, noise_sigma_mv=0.5, signal_mv=2.0,
                             x=float(len(taxels) + j), y=0.0) for j in range(size)]
    bus = BusSpec(mode=mode, sync_counter=sync_counter, fd=fd, patch_nodes=True, raw_format=raw_format,
                  channels=channels, sync_window_us=window_us, raw_lsb_mv=lsb, heartbeat_consumer_ms=300)
    return Scene(path="<t>", name="t", bus=bus, taxels=tuple(taxels), fusion=FusionSpec())


def boot(a, sc, t=0):
    for d in devices(sc):
        assert a.feed(t, d.channel, 0x700 + d.node_id, b"\x00") is None
    for ch in range(len(sc.bus.channels)):
        assert a.feed(t, ch, 0x000, bytes([0x01, 0])) is None  # NMT start all


def sync(a, t, counter, channel=0):
    return a.feed_all(t, channel, 0x80, bytes([counter]))


def frames(sc, u, tag):
    """Every TPDO of every device for the taxel values ``u`` (scene order): (channel, cob, data)."""
    out = []
    for d in devices(sc):
        vals = np.asarray(u)[list(d.taxels)]
        for t in d.tpdos:
            out.append((d.channel, t.cob_id, pack(t, vals[t.first:t.first + t.count], tag=tag)))
    return out


def test_layout_of_the_test_scene():
    # 10 taxels: one tagged frame of 3 bytes; 70 taxels: 56 + 14 (7 decision bytes per tagged frame)
    a, b = devices(patch_scene())
    assert [(t.cob_id, t.count, t.length) for t in a.tpdos] == [(0x181, 10, 3)]
    assert [(t.cob_id, t.count, t.length) for t in b.tpdos] == [(0x182, 56, 8), (0x183, 14, 3)]


def test_a_cycle_completes_when_every_tpdo_of_every_device_arrived():
    sc = patch_scene()
    a = CycleAssembler(sc)
    assert a.n_devices == 2 and a.labels == [1, 2]
    boot(a, sc)
    u = np.where(np.arange(80) % 3 == 0, 1, -1)
    fs = frames(sc, u, tag=1)
    assert sync(a, 10 * MS, 1) == []
    for k, (ch, cob, data) in enumerate(fs[:-1]):
        assert a.feed(10 * MS + 100 + k, ch, cob, data) is None
    closed = a.feed(10 * MS + 200, *fs[-1])
    assert closed is not None and closed.closed_by == "complete" and closed.close_us == 10 * MS + 200
    assert closed.decisions.tolist() == u.tolist() and closed.received.all()
    assert closed.expected.shape == (80,) and closed.expected.all() and not closed.missing.any()
    assert closed.devices.complete.tolist() == [True, True] and closed.devices.expected.tolist() == [True, True]
    assert a.counters()["tpdo1"] == 3 and a.malformed() == 0
    rec = CyclePipeline(sc, truth=False).evaluate(closed)
    assert rec["n_received"] == 80 and rec["n_expected"] == 80 and rec["n_live"] == 80
    assert rec["present_count"] == 27 and rec["present_nodes"][:3] == ["1/0", "1/3", "1/6"]
    assert rec["nodes_by_state"] == {} and rec["degraded"] is False


def test_a_missing_tpdo_leaves_the_cycle_to_the_next_sync_degraded_and_names_the_node_silent():
    sc = patch_scene()
    a = CycleAssembler(sc)
    boot(a, sc)
    u = np.ones(80, dtype=int)
    fs = frames(sc, u, tag=1)
    sync(a, 10 * MS, 1)
    for ch, cob, data in (fs[0], fs[2]):  # TPDO 0x182 (taxels 10..65) never comes
        assert a.feed(10 * MS + 100, ch, cob, data) is None
    (closed,) = sync(a, 20 * MS, 2)
    assert closed.closed_by == "sync"
    assert closed.received.tolist() == [True] * 10 + [False] * 56 + [True] * 14
    assert closed.decisions[10:66].tolist() == [0] * 56
    assert closed.devices.complete.tolist() == [True, False]
    rec = CyclePipeline(sc, truth=False).evaluate(closed)
    assert rec["degraded"] is True and rec["n_received"] == 24 and rec["present_count"] == 24
    assert rec["silent_nodes"] == [2] and rec["nodes_by_state"] == {"silent": [2]} and rec["missing_nodes"] == []


def test_a_frame_tagged_with_an_earlier_sync_is_late_never_misattributed():
    sc = patch_scene(sizes=(8,))
    a = CycleAssembler(sc)
    boot(a, sc)
    (t,) = devices(sc)[0].tpdos
    sync(a, 10 * MS, 1)
    # the answer to SYNC 1 is handled after SYNC 2: late in cycle 1's successor, cycle 1 closed by SYNC 2
    (c0,) = sync(a, 20 * MS, 2)
    assert c0.closed_by == "sync" and not c0.received.any()
    assert a.feed(20 * MS + 50, 0, t.cob_id, pack(t, np.ones(8), tag=1)) is None
    assert a.counters()["late"] == 1 and a.is_open
    closed = a.feed(20 * MS + 60, 0, t.cob_id, pack(t, -np.ones(8), tag=2))
    assert closed.cycle == 1 and closed.decisions.tolist() == [-1] * 8 and closed.late_frames == 1
    # held_decisions keeps the last frame heard, whatever cycle it was for
    assert closed.held_decisions.tolist() == [-1] * 8


def test_two_frames_of_one_tpdo_for_one_sync_flag_a_duplicate_node_id():
    sc = patch_scene(sizes=(8, 8))
    a = CycleAssembler(sc)
    boot(a, sc)
    t = devices(sc)[1].tpdos[0]
    sync(a, 10 * MS, 1)
    a.feed(10 * MS + 1, 0, t.cob_id, pack(t, np.ones(8), tag=1))
    a.feed(10 * MS + 2, 0, t.cob_id, pack(t, -np.ones(8), tag=1))  # a second device answers as node 2
    (closed,) = sync(a, 20 * MS, 2)
    assert closed.duplicates == (1,) and closed.decisions[8:].tolist() == [1] * 8
    rec = CyclePipeline(sc, truth=False).evaluate(closed)
    assert rec["duplicate_nodes"] == [2] and rec["silent_nodes"] == [1]
    assert a.counters()["late"] == 1


@pytest.mark.parametrize("data, counter", [
    (bytes([1, 0xFF]), "bad_dlc"),            # 2 bytes for a 3-byte TPDO
    (bytes([1, 0xFF, 0b11, 0]), "bad_dlc"),
    (bytes([1, 0xFF, 0b111]), "bad_value"),   # bit of taxel 10 (there are 10)
    (bytes([0, 0xFF, 0b11]), "bad_value"),    # tag 0: no SYNC carries it
    (bytes([65, 0xFF, 0b11]), "bad_value"),   # beyond the overflow 64
])
def test_wrong_length_set_padding_bits_and_impossible_tags_are_malformed(data, counter):
    sc = patch_scene(sizes=(10,))
    a = CycleAssembler(sc)
    boot(a, sc)
    sync(a, 10 * MS, 1)
    assert a.feed(10 * MS + 1, 0, 0x181, data) is None
    assert a.counters()[counter] == 1 and a.malformed() == 1 and a.is_open
    assert sum(a.counters().values()) == a.events


def test_raw_patch_readings_in_mv_with_not_valid_as_nan():
    sc = patch_scene(sizes=(3,), mode="raw", raw_format="int8", lsb=0.1)
    a = CycleAssembler(sc)
    boot(a, sc)
    (t,) = devices(sc)[0].tpdos
    sync(a, 10 * MS, 5)
    closed = a.feed(10 * MS + 1, 0, t.cob_id, bytes([5, 13, 0x81, 0x80]))
    assert closed.closed_by == "complete" and closed.received.all()
    assert closed.readings[0] == pytest.approx(1.3) and closed.readings[1] == pytest.approx(-12.7)
    assert math.isnan(closed.readings[2])
    assert a.counters()["tpdo2"] == 1
    rec = CyclePipeline(sc, truth=False).evaluate(closed)
    # the centre decides per taxel (zeta 1 mV): 1.3 present, -12.7 absent, not valid: not received
    assert rec["n_received"] == 2 and rec["present_count"] == 1 and rec["present_nodes"] == ["1/0"]


def test_node_states_are_per_device_and_named_by_device():
    sc = patch_scene(sizes=(4, 4, 4))
    a = CycleAssembler(sc)
    boot(a, sc)
    a.feed(1 * MS, 0, 0x000, bytes([0x02, 2]))  # NMT stop node 2
    a.feed(2 * MS, 0, 0x703, b"\x7f")           # node 3: pre-operational by its heartbeat
    sync(a, 10 * MS, 1)
    t = devices(sc)[0].tpdos[0]
    closed = a.feed(10 * MS + 1, 0, t.cob_id, pack(t, np.ones(4), tag=1))
    assert closed.closed_by == "complete"  # node 1 was the only one expected
    assert closed.expected.tolist() == [True] * 4 + [False] * 8
    rec = CyclePipeline(sc, truth=False).evaluate(closed)
    assert rec["nodes_by_state"] == {"stopped": [2], "pre-operational": [3]}
    assert rec["n_received"] == 4 and rec["degraded"] is True


def test_missing_device_after_its_consumer_time():
    sc = patch_scene(sizes=(4, 4), channels=("a", "b"), node_channels=(0, 1))
    a = CycleAssembler(sc)
    assert a.labels == [1, "1:2"]
    boot(a, sc)
    t0 = devices(sc)[0].tpdos[0]
    sync(a, 400 * MS, 1)
    # nothing heard from either for 400 ms > 300 ms: both missing, the cycle waits for the next SYNC
    assert a.feed(400 * MS + 1, 0, t0.cob_id, pack(t0, np.ones(4), tag=1)) is None
    (closed,) = sync(a, 410 * MS, 2)
    assert closed.devices.missing.tolist() == [True, True] and closed.closed_by == "sync"
    # node 1 heard again: expected and the only one, so its TPDO completes the cycle
    closed = a.feed(410 * MS + 1, 0, t0.cob_id, pack(t0, np.ones(4), tag=2))
    assert closed.closed_by == "complete"
    assert closed.devices.missing.tolist() == [False, True] and closed.missing.tolist() == [False] * 4 + [True] * 4
    rec = CyclePipeline(sc, truth=False).evaluate(closed)
    assert rec["missing_nodes"] == ["1:2"] and rec["nodes_by_state"]["missing"] == ["1:2"]
    assert rec["n_live"] == 4


def test_fd_frames_are_the_pdos_of_an_fd_scene_only_on_their_cob_ids():
    sc = patch_scene(sizes=(100,), fd=True)
    (d,) = devices(sc)
    (t,) = d.tpdos
    assert (t.cob_id, t.count, t.length, t.fd) == (0x181, 100, 16, True)  # 1 + 13 bytes -> 16
    a = CycleAssembler(sc)
    boot(a, sc)
    sync(a, 10 * MS, 1)
    data = pack(t, np.ones(100), tag=1)
    assert a.feed(10 * MS + 1, 0, t.cob_id, data) is None          # classic frame on the FD PDO
    assert a.feed(10 * MS + 2, 0, 0x701, b"\x05", FLAG_FD) is None  # FD heartbeat: not a PDO
    assert a.counters()["fd_frame"] == 2 and a.is_open
    closed = a.feed(10 * MS + 3, 0, t.cob_id, data, FLAG_FD)
    assert closed.closed_by == "complete" and closed.decisions.tolist() == [1] * 100
    # a classic scene: every FD frame is malformed
    sc2 = patch_scene(sizes=(8,))
    b = CycleAssembler(sc2)
    boot(b, sc2)
    sync(b, 10 * MS, 1)
    (t2,) = devices(sc2)[0].tpdos
    assert b.feed(10 * MS + 1, 0, t2.cob_id, pack(t2, np.ones(8), tag=1), FLAG_FD) is None
    assert b.counters()["fd_frame"] == 1 and b.counters()["tpdo1"] == 0


def test_per_taxel_fd_scene_takes_its_tpdo1_as_fd_frames():
    taxels = tuple(TaxelSpec(node_id=10 + i, kind="R") for i in range(2))
    sc = Scene(path="<t>", name="t", bus=BusSpec(sync_counter=64, fd=True), taxels=taxels, fusion=FusionSpec())
    a = CycleAssembler(sc)
    for tx in sc.taxels:
        a.feed(0, 0, 0x700 + tx.node_id, b"\x00")
    a.feed(0, 0, 0, bytes([1, 0]))
    sync(a, 10 * MS, 1)
    tag = (1 << 2) | 0b01
    assert a.feed(10 * MS + 1, 0, 0x18A, bytes([tag])) is None  # classic: fd_frame
    assert a.feed(10 * MS + 2, 0, 0x18A, bytes([tag]), FLAG_FD) is None
    closed = a.feed(10 * MS + 3, 0, 0x18B, bytes([tag]), FLAG_FD)
    assert closed.closed_by == "complete" and closed.decisions.tolist() == [1, 1]
    assert a.counters()["fd_frame"] == 1 and closed.devices is None


def test_windowed_patch_answers_handled_after_the_next_sync_still_count():
    sc = patch_scene(sizes=(8, 8), window_us=4000)
    a = CycleAssembler(sc)
    boot(a, sc)
    t1, t2 = devices(sc)[0].tpdos[0], devices(sc)[1].tpdos[0]
    sync(a, 10 * MS, 1)
    a.feed(10 * MS + 100, 0, t1.cob_id, pack(t1, np.ones(8), tag=1))
    assert sync(a, 20 * MS, 2) == []  # SYNC 2 held while cycle 1's window is open
    closed = a.feed(10 * MS + 200, 0, t2.cob_id, pack(t2, np.ones(8), tag=1))  # stamped inside the window
    assert closed.cycle == 0 and closed.closed_by == "complete" and closed.received.all()
    assert a.cycle == 1 and a.is_open  # the held SYNC was fed


def test_non_contiguous_patch_taxels():
    # node 1 hosts taxels 0, 2, 4; node 2 taxels 1, 3 (scene order interleaved)
    taxels = tuple(TaxelSpec(node_id=1 + (i % 2), kind="C", zeta_mv=1.0) for i in range(5))
    sc = Scene(path="<t>", name="t", bus=BusSpec(sync_counter=8, patch_nodes=True), taxels=taxels,
               fusion=FusionSpec())
    a = CycleAssembler(sc)
    boot(a, sc)
    sync(a, 10 * MS, 3)
    u = np.array([1, -1, -1, 1, 1])
    for ch, cob, data in frames(sc, u, tag=3):
        closed = a.feed(10 * MS + 1, ch, cob, data)
    assert closed.decisions.tolist() == u.tolist()
    assert a.layout.taxel_device.tolist() == [0, 1, 0, 1, 0]


@pytest.mark.parametrize("mode, raw_format, fd, sync_counter", [
    ("decision", "int16", False, 64), ("decision", "int16", True, 64), ("decision", "int16", False, 0),
    ("raw", "int8", False, 64), ("raw", "int16", True, 64), ("raw", "int16", False, 0),
])
def test_the_assemblers_slot_decoder_is_patches_unpack(mode, raw_format, fd, sync_counter):
    """The assembler's precomputed decoder gives what taxel_net.patches.unpack gives, refusals included."""
    from taxel_net.patches import PatchFrameError, unpack
    from fusion_center.service.cycle_records import C_BAD_DLC, C_BAD_VALUE
    from fusion_center.service.decoder import SlotDecoder

    rng = np.random.default_rng(14)
    sc = patch_scene(sizes=(3, 70, 13), mode=mode, raw_format=raw_format, fd=fd, sync_counter=sync_counter, lsb=0.25)
    for dev in devices(sc):
        for t in dev.tpdos:
            dec = SlotDecoder(t, 0.25)
            for k in range(60):
                if k % 3 == 0:  # a valid frame, then maybe a flipped bit anywhere
                    vals = rng.integers(-200, 200, t.count) if mode == "raw" else rng.choice([-1, 1], t.count)
                    data = bytearray(pack(t, vals, tag=7 if t.tagged else None))
                    if k % 2:
                        bit = rng.integers(0, 8 * len(data))
                        data[bit // 8] ^= 1 << (bit % 8)
                else:
                    data = bytearray(rng.integers(0, 256, t.length + rng.integers(-1, 2), dtype=np.uint8).tobytes())
                    data[t.length - 1 if len(data) >= t.length else 0:] = bytes(len(data) - (t.length - 1)
                                                                                if len(data) >= t.length else len(data))
                data = bytes(data)
                bad, tag, values = dec.decode(data)
                try:
                    ref_tag, ref = unpack(t, data, 0.25)
                except PatchFrameError as exc:
                    assert bad == {"bad_dlc": C_BAD_DLC, "bad_value": C_BAD_VALUE}[exc.reason]
                    continue
                assert bad is None and tag == ref_tag
                np.testing.assert_array_equal(values, ref)


def test_a_patch_frame_stamped_before_its_sync_is_an_old_one_and_late():
    """The cycle tag (the full counter) repeats every overflow SYNCs: a frame held up behind a
    backlog that long carries the open cycle's tag but is stamped before its SYNC - late."""
    sc = patch_scene(sizes=(10,), sync_counter=4)
    a = CycleAssembler(sc)
    boot(a, sc)
    (tpdo,) = devices(sc)[0].tpdos
    old = pack(tpdo, np.ones(10), tag=2)
    sync(a, 50 * MS, 2)                                   # the SYNC with counter 2, four SYNCs later
    a.feed_all(40 * MS, 0, tpdo.cob_id, old)              # stamped before it: the answer of 40 ms ago
    assert a.counters()["late"] == 1
    closed = a.feed_all(50 * MS + 100, 0, tpdo.cob_id, pack(tpdo, -np.ones(10), tag=2))
    assert len(closed) == 1 and closed[0].closed_by == "complete" and (closed[0].decisions == -1).all()
