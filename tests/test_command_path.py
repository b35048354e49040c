"""The centre's frame -> grip command path made shorter without changing what it gives (issue 23,
docs/grip-control.md "SYNC -> command"): the closed cycle's objects made without the frozen
dataclasses' per-field ``__init__``, packed decisions' repeated patterns unpacked once, the grip
stage's record fields made after the command, the command's datagram sent before the stream's
Message of it is made. Each compared with the way it was done before."""

from __future__ import annotations

import dataclasses
import inspect
import sys
from pathlib import Path

import can
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_cycles_patch import boot, frames, patch_scene  # noqa: E402
from test_packed_decisions import assert_same_closed, per_frame  # noqa: E402

from fusion_center.service import stream as stream_module  # noqa: E402
from fusion_center.service.cycle_records import ClosedCycle, DeviceCycle  # noqa: E402
from fusion_center.service.cycles import CycleAssembler  # noqa: E402
from fusion_center.service.drive_frames import DriveCycle  # noqa: E402
from fusion_center.service import packed_decisions  # noqa: E402
from fusion_center.service.pipeline import CyclePipeline  # noqa: E402

MS = 1000  # µs


def _values(cls):
    """A distinct object per field of ``cls`` (so a field set from the wrong argument shows)."""
    return {f.name: np.array([k]) if "ndarray" in str(f.type) else (f"v{k}",) for k, f in
            enumerate(dataclasses.fields(cls))}


@pytest.mark.parametrize("cls", [ClosedCycle, DeviceCycle, DriveCycle])
def test_make_is_the_dataclass_constructor(cls):
    fields = dataclasses.fields(cls)
    params = list(inspect.signature(cls.make).parameters.values())
    # the same names in the same order, the same defaults: a field added to the class and not to
    # make fails here
    assert [p.name for p in params] == [f.name for f in fields]
    for p, f in zip(params, fields):
        want = inspect.Parameter.empty if f.default is dataclasses.MISSING else f.default
        assert p.default == want, f.name
    values = _values(cls)
    made, built = cls.make(**values), cls(**values)
    assert type(made) is cls and vars(made) == vars(built)
    assert all(getattr(made, name) is value for name, value in values.items())
    positional = cls.make(*values.values())
    assert all(getattr(positional, name) is value for name, value in values.items())
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(made, fields[0].name, 1)
    replaced = dataclasses.replace(made, **{fields[0].name: "other"})
    assert getattr(replaced, fields[0].name) == "other" and getattr(replaced, fields[1].name) is values[fields[1].name]
    required = [f.name for f in fields if f.default is dataclasses.MISSING]
    with pytest.raises(TypeError):
        cls.make(**{name: values[name] for name in required[1:]})   # a field missing: refused as by cls()


def test_drive_cycle_made_as_the_snapshot_makes_it():
    """DriveCycle.make with every argument given positionally, as the drive's snapshot makes it:
    the constructor's object, field for field (an EMCY in the cycle)."""
    emcy = ((0x8130, 0x11, 5),)
    d = DriveCycle.make(True, False, 5, 0x27, 100, 40000, 4, 2, 140, 400, 0, 12, (0x0F, 100, 0), emcy, 1, 2)
    assert vars(d) == vars(DriveCycle(True, False, 5, 0x27, 100, 40000, 4, 2, 140, 400, 0, 12, (0x0F, 100, 0),
                                      emcy, 1, 2))
    assert d.state == "OPERATION ENABLED" and d.force_n == 14.0


def _few_patterns_stream(scene, rng, cycles):
    """A SYNC per cycle, then the frames of one of three decision vectors, some frames lost:
    the patterns repeat, as a grasp's do."""
    vectors = [np.where(rng.random(scene.n) < 0.4, 1, -1) for _ in range(3)]
    events, t = [], 10 * MS
    for cycle in range(cycles):
        counter = cycle % 64 + 1
        events.append((t, 0, 0x80, bytes([counter]), 0))
        batch = frames(scene, vectors[rng.integers(3)], tag=counter)
        for k, (ch, cob, data) in enumerate(batch):
            if rng.random() < 0.1:
                continue
            events.append((t + 50 + 10 * k, ch, cob, data, 0))
        t += 10 * MS
    return events


@pytest.mark.parametrize("seed", [0, 1])
def test_repeated_patterns_unpack_from_the_memo_as_per_frame(seed):
    scene = patch_scene(sizes=(26, 26))
    packed, reference = CycleAssembler(scene), per_frame(scene)
    assert packed.packed.memo is not None
    boot(packed, scene)
    boot(reference, scene)
    got, want = [], []
    for t, ch, cob, data, flags in _few_patterns_stream(scene, np.random.default_rng(seed), 120):
        got += packed.feed_all(t, ch, cob, data, flags)
        want += reference.feed_all(t, ch, cob, data, flags)
    assert len(want) >= 100
    assert_same_closed(got, want)
    assert packed.counters() == reference.counters()
    assert len(packed.packed.memo) < len(got) / 2   # the patterns repeated: most closes from the memo


def test_a_large_layout_keeps_no_memo():
    scene = patch_scene(sizes=(200, 200, 200))   # 75 decision bytes
    assert len(CycleAssembler(scene).packed.cycle_bytes) > packed_decisions.MEMO_BYTES
    assert CycleAssembler(scene).packed.memo is None


def test_the_grip_record_fields_are_made_after_the_command():
    """evaluate_command sets the command and leaves the grip stage's record fields to finish;
    the records are those of the stage writing them at once (as before)."""
    import json

    from taxel_net.scene import load_scene

    scene = load_scene("grasp_scripted")
    pipeline = CyclePipeline(scene)
    assembler = CycleAssembler(scene)
    closed: list = []
    events = stream_module.EventStream(assembler, on_closed=closed.append)
    # a short live-like stream: the drive's boot-up and TPDO1 in OPERATION ENABLED, then SYNCs
    node = scene.gripper.node_id
    events.receive(can.Message(timestamp=0.001, arbitration_id=0x700 + node, data=b"\x05", is_extended_id=False), 0)
    pending = None
    for k in range(5):
        t = 0.01 * (k + 1)
        events.receive(can.Message(timestamp=t, arbitration_id=0x80, data=b"", is_extended_id=False), 0)
        events.receive(can.Message(timestamp=t + 0.0002, arbitration_id=0x180 + node,
                                   data=bytes((0x27, 0x04, 0, 0, 0x40, 0x9C, 0, 0)), is_extended_id=False), 0)
    events.receive(can.Message(timestamp=0.07, arbitration_id=0x80, data=b"", is_extended_id=False), 0)
    assert closed
    reference = CyclePipeline(scene)
    for c in closed:
        pending = pipeline.evaluate_command(c)
        assert pipeline.grip.command is not None                       # the command is there
        assert "grip" not in pending.grip_view and "grip_detail" not in pending.grip_view  # its record is not yet
        record = pipeline.finish(pending)
        # the reference: the stage writing its fields at once, as before
        ref_pending = reference.evaluate_command(c)
        reference.grip.write_record()
        assert "grip" in ref_pending.grip_view
        assert json.dumps(record, default=repr) == json.dumps(reference.finish(ref_pending), default=repr)
        assert record["grip"]["drive_state"] == "OPERATION ENABLED"


def test_the_command_leaves_before_its_message_is_made(monkeypatch):
    """transmit_all on a direct sender: the datagram first, then the stream's TxMessage (with the
    time stamp taken before the send, as before); the event fed is the same frame."""
    order: list[str] = []

    class SpyMessage(stream_module.TxMessage):
        __slots__ = ()

        def __init__(self, *args, **kwargs):
            order.append("message")
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(stream_module, "TxMessage", SpyMessage)
    scene = patch_scene(sizes=(10, 70))
    fed: list = []
    events = stream_module.EventStream(CycleAssembler(scene), buses=[object()])
    events._senders[0] = lambda burst: order.append(("sent", tuple((i, bytes(d)) for i, d in burst)))
    original = events._feed_locked
    monkeypatch.setattr(events, "_feed_locked", lambda msg, ch: fed.append(msg) or original(msg, ch))
    before = stream_module.time.time()
    events.transmit(0, 0x240, bytes((0x0F, 0, 0x64, 0, 0, 0, 0, 0)))
    assert order == [("sent", ((0x240, bytes((0x0F, 0, 0x64, 0, 0, 0, 0, 0))),)), "message"]
    (msg,) = fed
    assert (msg.arbitration_id, bytes(msg.data), msg.is_rx, msg.is_remote_frame, msg.channel) == \
        (0x240, bytes((0x0F, 0, 0x64, 0, 0, 0, 0, 0)), False, False, 0)
    assert isinstance(msg.data, bytearray) and msg.dlc == 8 and before <= msg.timestamp


def test_a_turn_of_own_echoes_only_never_takes_the_stream_lock():
    """udp_multicast hands the centre its SYNC back at once, while the SYNC producer still holds
    the stream lock (it feeds the SYNC after sending it): a receive turn of nothing but own
    echoes counts them and leaves the stream alone; a turn with a foreign frame is fed."""
    import types

    from fusion_center.service.echo_filter import EchoFilter
    from fusion_center.service.stream import _StreamListener

    scene = patch_scene(sizes=(10, 70))
    events = stream_module.EventStream(CycleAssembler(scene))
    events.echoes = EchoFilter()
    calls: list[list] = []
    original = events.receive_all
    events.receive_all = lambda msgs, channel: calls.append(list(msgs)) or original(msgs, channel)
    service = types.SimpleNamespace(stream=events, own_echoes=0, on_bootup=lambda index: None)
    listener = _StreamListener(service, 0)
    events.echoes.sent(0, 0x80, b"", False)
    listener.on_messages_received([can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)])
    assert calls == [] and service.own_echoes == 1   # receive_all (its lock) not called for nothing
    heartbeat = can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False)
    listener.on_messages_received([heartbeat])
    assert calls == [[heartbeat]]


@pytest.mark.parametrize("direct", [True, False])
def test_a_one_channel_sync_is_fed_before_it_is_sent_and_the_lock_is_free_during_the_send(direct, monkeypatch):
    """transmit_fed_first (the SYNC producer's on a one-channel network): the SYNC is an event of
    the stream before its frame leaves - so no answer can be fed before it - and the stream lock
    is not held across the send (the receive thread can feed the answers while it is sent); a
    failed send is counted and its echo forgotten, the SYNC stays fed."""
    from fusion_center.service.echo_filter import EchoFilter

    scene = patch_scene(sizes=(10, 70))
    seen: list = []

    class Bus:
        def send(self, msg):
            seen.append(("bus", events.fed, events.lock.acquire(blocking=False), bytes(msg.data)))
            events.lock.release()
            if fail:
                raise can.CanError("bus off")

    events = stream_module.EventStream(CycleAssembler(scene), buses=[Bus()])
    events.echoes = EchoFilter()
    if direct:
        def sender(burst):
            seen.append(("direct", events.fed, events.lock.acquire(blocking=False), bytes(burst[0][1])))
            events.lock.release()
            if fail:
                raise can.CanError("bus off")
        events._senders[0] = sender
    else:
        monkeypatch.setattr(events, "_direct_sender", lambda channel: None)
    fed_before = events.fed
    fail = False
    before = stream_module.time.time()
    events.transmit_fed_first(0, 0x80, bytes((1,)))
    ((how, fed_at_send, lock_free, data),) = seen
    assert how == ("direct" if direct else "bus") and data == b"\x01"
    assert fed_at_send == fed_before + 1 and lock_free      # fed first; the lock free while sent
    assert events.tx_errors == 0 and before <= events.last_us / 1e6 + 1e-6
    fail = True
    events.transmit_fed_first(0, 0x80, bytes((2,)))
    assert events.fed == fed_before + 2 and events.tx_errors == 1
    assert not events.echoes.is_echo(can.Message(arbitration_id=0x80, data=b"\x02", is_extended_id=False), 0)
    assert events.echoes.is_echo(can.Message(arbitration_id=0x80, data=b"\x01", is_extended_id=False), 0)


def test_the_centre_s_own_frames_never_come_back_to_its_receive_thread():
    """udp_multicast loops every datagram back to its sender, and the centre's receive thread read
    its own SYNC (and command, heartbeat, NMT) in a turn of its own - a wake-up, a system call, an
    unpacking and the echo filter, on the way to the cycle's answers (docs/grip-control.md). The
    centre's datagrams now carry its bus's tag (taxel_net.udp_filter.drop_own_frames), which its
    socket's kernel filter drops: no frame of its own reaches its listener, each is still counted
    as an own echo dropped, and another sender's identical SYNC is still a foreign SYNC."""
    import time

    from test_junk_isolation import MATRIX, _without_sync_counter
    from test_service_multiprocess import GROUP, multicast_port

    from fusion_center.service import FusionService
    from taxel_net.scene import load_scene

    port = multicast_port()
    scene = _without_sync_counter(load_scene(MATRIX))
    tool = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    try:
        with FusionService(scene, interface="udp_multicast", channels=[GROUP],
                           bus_kwargs={"port": port, "hop_limit": 0}) as service:
            (handle,) = service.notifiers
            (listener,) = handle.listeners
            heard: list[int] = []
            original = listener.on_messages_received
            listener.on_messages_received = lambda msgs: heard.extend(m.arbitration_id for m in msgs) or original(msgs)
            for _ in range(20):
                service.stream.transmit(0, 0x080, b"")
                time.sleep(0.002)
            time.sleep(0.2)
            assert heard == []
            assert service.summary().own_echoes == 20
            tool.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
            deadline = time.monotonic() + 2
            while not heard and time.monotonic() < deadline:
                time.sleep(0.01)
            time.sleep(0.05)
            assert heard == [0x080]
            assert service.stream.counters()["foreign_sync"] == 1
    finally:
        tool.shutdown()
