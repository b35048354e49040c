"""10^5 random frames fed straight into the listener path: the centre keeps running and every
frame is accounted for (the disposition counters sum to the frames fed)."""

import numpy as np
import can

from taxel_net.scene import load_scene
from fusion_center.service.stream import EventStream
from fusion_center.service.cycles import CycleAssembler
from fusion_center.service.pipeline import CyclePipeline

FRAMES = 100_000


def random_frames(rng, scene, count):
    node_ids = np.array([t.node_id for t in scene.taxels])
    bases = np.array([0x000, 0x080, 0x100, 0x180, 0x280, 0x580, 0x600, 0x700, 0x77F])  # 0x77F: the master's heartbeat
    t = 1_700_000_000.0
    for i in range(count):
        r = rng.random()
        if r < 0.5:   # anywhere in the 11-bit space
            can_id = int(rng.integers(0, 0x800))
        else:         # aimed at the scene's COB-IDs (valid or not)
            base = int(rng.choice(bases))
            can_id = base + (int(rng.choice(node_ids)) if base not in (0x000, 0x080, 0x100, 0x77F) else 0)
        dlc = int(rng.integers(0, 9)) if rng.random() < 0.6 else int(rng.choice([0, 1, 2, 8]))
        data = rng.integers(0, 256, dlc, dtype=np.uint8).tobytes()
        if rng.random() < 0.5 and dlc == 1:
            data = bytes([int(rng.choice([0x01, 0xFF, 0x00, 0x05, 0x7F]))])
        flags = rng.random()
        t += float(rng.exponential(2e-4)) if rng.random() < 0.98 else -0.01  # some go backwards
        yield can.Message(
            timestamp=t, arbitration_id=can_id if flags > 0.01 else int(rng.integers(0, 1 << 29)),
            is_extended_id=flags <= 0.01, is_remote_frame=0.01 < flags <= 0.02,
            is_error_frame=0.02 < flags <= 0.03, data=b"" if 0.01 < flags <= 0.02 else data, dlc=dlc)


def test_fuzzed_frames_are_all_accounted_for_and_cycles_evaluate():
    scene = load_scene("scenes/matrix57.toml")
    assembler = CycleAssembler(scene)
    pipeline = CyclePipeline(scene)
    records = []
    stream = EventStream(assembler, on_closed=lambda c: records.append(pipeline.evaluate(c)))
    rng = np.random.default_rng(20240601)
    for msg in random_frames(rng, scene, FRAMES):
        stream.receive(msg, 0)
    counters = assembler.counters()
    assert stream.fed == FRAMES
    assert sum(counters.values()) == FRAMES
    assert counters["internal_error"] == 0
    # the fuzz reached the interesting paths
    for name in ("sync", "tpdo1", "late", "heartbeat", "bootup", "master_heartbeat", "emcy", "nmt", "bad_dlc", "bad_value",
                 "unknown_cob_id", "remote_frame", "error_frame", "extended_id"):
        assert counters[name] > 0, name
    assert len(records) > 10
    for r in records:
        assert r["decision"] in ("H1", "H0", "undecided")
        assert r["n_received"] <= r["n_expected"] == scene.n
        assert r["present_count"] <= r["n_received"]
    # cycles are numbered without gaps and in order
    assert [r["cycle"] for r in records] == list(range(records[0]["cycle"], records[0]["cycle"] + len(records)))


def test_a_raising_consumer_is_counted_as_internal_error_not_raised():
    scene = load_scene("scenes/matrix57.toml")
    assembler = CycleAssembler(scene)

    def broken(_closed):
        raise RuntimeError("boom")

    stream = EventStream(assembler, on_closed=broken)
    # matrix57 has a SYNC counter (1 byte)
    stream.receive(can.Message(timestamp=1.0, arbitration_id=0x080, data=b"\x01", is_extended_id=False), 0)
    # a heartbeat stamped after the 8 ms window closes cycle 0, and the consumer raises
    stream.receive(can.Message(timestamp=1.009, arbitration_id=0x701, data=b"\x05", is_extended_id=False), 0)
    counters = assembler.counters()
    # the heartbeat was counted before the consumer raised: no double count
    assert counters["sync"] == 1 and counters["heartbeat"] == 1 and counters["internal_error"] == 0
    assert sum(counters.values()) == stream.fed == 2
    # a frame that breaks the assembler itself (data of the wrong type) is an internal error
    bad = can.Message(timestamp=1.02, arbitration_id=0x181, data=b"\x01", is_extended_id=False)
    bad.data = None
    stream.receive(bad, 0)
    assert assembler.counters()["internal_error"] == 1
    assert sum(assembler.counters().values()) == stream.fed == 3
