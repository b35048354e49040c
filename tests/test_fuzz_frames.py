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
    """``count`` random frames; each frame's fields drawn independently, with the laws below (the
    draws made for all frames at once: numpy's per-call overhead was ~3/4 of the test's CPU)."""
    node_ids = np.array([t.node_id for t in scene.taxels])
    bases = np.array([0x000, 0x080, 0x100, 0x180, 0x280, 0x580, 0x600, 0x700, 0x77F])  # 0x77F: the master's heartbeat
    # half anywhere in the 11-bit space, half aimed at the scene's COB-IDs (valid or not)
    anywhere = rng.random(count) < 0.5
    base = rng.choice(bases, count)
    with_node = ~np.isin(base, (0x000, 0x080, 0x100, 0x77F))
    can_ids = np.where(anywhere, rng.integers(0, 0x800, count), base + np.where(with_node, rng.choice(node_ids, count), 0))
    dlcs = np.where(rng.random(count) < 0.6, rng.integers(0, 9, count), rng.choice([0, 1, 2, 8], count))
    payloads = rng.integers(0, 256, (count, 8), dtype=np.uint8)
    one_byte = (rng.random(count) < 0.5) & (dlcs == 1)  # a DLC-1 frame: half of them a state-like byte
    payloads[one_byte, 0] = rng.choice(np.array([0x01, 0xFF, 0x00, 0x05, 0x7F], dtype=np.uint8), count)[one_byte]
    flags = rng.random(count)
    extended_ids = rng.integers(0, 1 << 29, count)
    # some go backwards
    steps = np.where(rng.random(count) < 0.98, rng.exponential(2e-4, count), -0.01)
    stamps = 1_700_000_000.0 + np.cumsum(steps)
    for i in range(count):
        f, dlc = flags[i], int(dlcs[i])
        yield can.Message(
            timestamp=float(stamps[i]), arbitration_id=int(can_ids[i]) if f > 0.01 else int(extended_ids[i]),
            is_extended_id=bool(f <= 0.01), is_remote_frame=bool(0.01 < f <= 0.02),
            is_error_frame=bool(0.02 < f <= 0.03), data=b"" if 0.01 < f <= 0.02 else payloads[i, :dlc].tobytes(),
            dlc=dlc)


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
