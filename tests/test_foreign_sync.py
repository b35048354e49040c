"""A second SYNC producer on the bus (another master, a tool) does not open cycles in the centre:
its well-formed SYNCs, received after the centre's first frame, are counted ``foreign_sync`` and
traced; the centre's own SYNCs alone number the cycles, live and in replay. Before, each foreign
SYNC opened a cycle of its own (65 records were seen for 60 SYNCs)."""

from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path

import can
import pytest

from fusion_center.service import FusionService, replay_trace
from fusion_center.service.cycles import CycleAssembler
from fusion_center.service.stream import EventStream
from node_sim.rig import Rig
from node_sim.taxel.detector import tagged_decision
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
MATRIX = ROOT / "scenes" / "matrix57.toml"


@pytest.fixture(scope="module")
def matrix():
    return load_scene(MATRIX)


def frame(t: float, can_id: int, data: bytes, rx: bool) -> can.Message:
    return can.Message(timestamp=t, arbitration_id=can_id, data=data, is_extended_id=False, is_rx=rx)


def closed_cycles(matrix, frames):
    closed = []
    stream = EventStream(CycleAssembler(matrix), on_closed=closed.append)
    for msg in frames:
        stream.receive(msg, 0)
    return closed, stream.counters()


def answers(t: float, counter: int, rx: bool = True) -> list[can.Message]:
    """Every node's TPDO1: u_i = +1 tagged with the SYNC's counter (node_sim's tagged_decision)."""
    return [frame(t + 1e-4 * nid, 0x180 + nid, bytes([tagged_decision(+1, counter)]), rx) for nid in range(1, 58)]


def test_received_syncs_after_the_centres_first_frame_are_foreign(matrix):
    """The centre's stream: its NMT (Tx) first, then its SYNCs (Tx) and the nodes' answers (Rx);
    a foreign SYNC (Rx) between them is counted, not a cycle; the same frames of a bus monitor
    (every frame Rx, no Tx) keep every SYNC a SYNC."""
    frames = [frame(1.0, 0x000, bytes([0x01, 0x00]), rx=False)]
    for k in range(4):
        t = 1.01 + 0.01 * k
        frames.append(frame(t, 0x080, bytes([k + 1]), rx=False))
        frames += answers(t + 1e-3, k + 1)
        frames.append(frame(t + 0.007, 0x080, bytes([9]), rx=True))  # the other producer
    frames.append(frame(1.06, 0x080, bytes([5]), rx=False))
    closed, counters = closed_cycles(matrix, frames)
    assert [(c.cycle, c.sync_counter) for c in closed] == [(0, 1), (1, 2), (2, 3), (3, 4)]
    assert all(c.received.all() for c in closed)
    assert counters["foreign_sync"] == 4 and counters["sync"] == 5
    # a bus monitor's trace: nothing sent, every SYNC received - all of them open cycles
    monitor = [frame(m.timestamp, m.arbitration_id, bytes(m.data), rx=True) for m in frames[1:]]
    closed, counters = closed_cycles(matrix, monitor)
    assert "foreign_sync" not in counters
    assert [c.sync_counter for c in closed] == [1, 9, 2, 9, 3, 9, 4]  # (the last SYNC opens the one still open)


@pytest.mark.parametrize("ext", ["log", "blf"])
def test_a_second_sync_producer_opens_no_cycle_live_or_in_replay(matrix, tmp_path, ext):
    live, trace = tmp_path / "live.jsonl", tmp_path / f"trace.{ext}"
    channel = f"foreign-sync-{uuid.uuid4().hex[:8]}"
    service = FusionService(matrix, interface="virtual", channels=[channel], json_lines=live, trace=trace)
    rig = Rig(matrix, interface="virtual", channel=[channel])
    stop = threading.Event()
    sent = []

    def other_master():
        bus = can.Bus(interface="virtual", channel=channel)
        try:
            while not stop.wait(0.007):
                bus.send(can.Message(arbitration_id=0x080, data=bytes([1 + len(sent) % 16]), is_extended_id=False))
                sent.append(1)
        finally:
            bus.shutdown()

    producer = threading.Thread(target=other_master, daemon=True)
    with service:
        rig.start()
        try:
            service.boot(3.0)
            producer.start()
            service.run(40)
        finally:
            stop.set()
            producer.join(5)
            # The run ends once its 40 records are written: the SYNC thread and the cycle windows
            # close cycles whatever the receive thread's lag, and close() stops that thread with
            # the frames still in its queue unread. On a loaded host its lag reached most of the
            # producer's sending (105 sent, the first 10 received), so wait (bounded) until the
            # receive thread has taken every SYNC the producer sent, while the centre still reads.
            if not producer.is_alive():
                deadline = time.monotonic() + 10.0
                while service.stream.foreign_syncs < len(sent) and time.monotonic() < deadline:
                    time.sleep(0.01)
            rig.stop()
    assert not producer.is_alive()
    counters = service.stream.counters()
    records = list(service.records)
    received = [m for m in can.LogReader(str(trace)) if m.arbitration_id == 0x080 and m.is_rx]
    # every foreign SYNC sent was received, counted and traced, none opened a cycle
    assert len(sent) > 10 and counters["foreign_sync"] == len(received) == len(sent)
    assert [r["cycle"] for r in records] == list(range(40))
    # (the twins answer the other producer's SYNCs too, as real nodes would: late TPDOs, some
    # cycles closed by their window - but 40 SYNCs of the centre, 40 cycles)
    replayed = tmp_path / "replay.jsonl"
    again, replay_counters = replay_trace(matrix, trace, json_lines=replayed)
    assert replayed.read_bytes() == live.read_bytes()
    assert replay_counters["foreign_sync"] == len(received)
