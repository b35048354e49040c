"""The master's own frames looped back by udp_multicast (EchoFilter): one copy absorbed per frame
sent, within the echo window, on the channel it was sent on - nothing else."""

import can

from fusion_center.service import echo_filter, stream
from fusion_center.service.echo_filter import ECHO_WINDOW_S, EchoFilter


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def frame(can_id=0x080, data=b"\x05", remote=False, **kw):
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=False, is_remote_frame=remote, **kw)


def test_each_sent_frame_absorbs_one_copy_only():
    echoes = EchoFilter(Clock())
    echoes.sent(0, 0x080, b"\x05", False)
    assert echoes.is_echo(frame(), 0)
    # an identical frame from another sender (another master's SYNC) is not ours
    assert not echoes.is_echo(frame(), 0)
    assert len(echoes) == 0


def test_copies_match_channel_id_data_and_rtr_exactly():
    echoes = EchoFilter(Clock())
    echoes.sent(2, 0x080, b"\x05", False)
    assert not echoes.is_echo(frame(), 1)                 # other channel
    assert not echoes.is_echo(frame(can_id=0x081), 2)     # other ID
    assert not echoes.is_echo(frame(data=b"\x06"), 2)     # other data
    assert not echoes.is_echo(frame(remote=True, data=b""), 2)
    assert not echoes.is_echo(frame(is_fd=True), 2)       # the master sends no FD frame
    assert len(echoes) == 1
    assert echoes.is_echo(frame(), 2)


def test_repeated_frames_absorb_as_many_copies_as_were_sent():
    clock = Clock()
    echoes = EchoFilter(clock)
    for _ in range(3):
        echoes.sent(0, 0x000, b"\x01\x00", False)
        clock.now += 0.001
    assert [echoes.is_echo(frame(0x000, b"\x01\x00"), 0) for _ in range(4)] == [True, True, True, False]


def test_an_echo_later_than_the_window_is_not_absorbed():
    clock = Clock()
    echoes = EchoFilter(clock)
    echoes.sent(0, 0x080, b"\x05", False)
    clock.now += ECHO_WINDOW_S / 2
    echoes.sent(0, 0x080, b"\x05", False)
    clock.now += ECHO_WINDOW_S * 0.6  # the first is past the window, the second is not
    assert echoes.is_echo(frame(), 0)
    assert not echoes.is_echo(frame(), 0)
    assert len(echoes) == 0


def test_absorbed_frames_do_not_expire_younger_ones():
    clock = Clock()
    echoes = EchoFilter(clock)
    echoes.sent(0, 0x080, b"\x05", False)
    assert echoes.is_echo(frame(), 0)
    clock.now += ECHO_WINDOW_S / 2
    echoes.sent(0, 0x080, b"\x05", False)
    clock.now += ECHO_WINDOW_S * 0.6  # the first (already absorbed) expires: the second stays
    assert echoes.is_echo(frame(), 0)


def test_a_frame_that_could_not_be_sent_is_forgotten():
    echoes = EchoFilter(Clock())
    echoes.sent(1, 0x77F, b"\x05", False)
    echoes.forget(1, 0x77F, b"\x05", False)
    assert not echoes.is_echo(frame(0x77F), 1)
    echoes.forget(1, 0x77F, b"\x05", False)  # nothing awaited: no error
    assert len(echoes) == 0


def test_awaited_frames_are_bounded(monkeypatch):
    monkeypatch.setattr(echo_filter, "ECHO_PENDING_MAX", 4)
    echoes = EchoFilter(Clock())
    for counter in range(6):
        echoes.sent(0, 0x080, bytes([counter]), False)
    assert len(echoes) == 4
    assert not echoes.is_echo(frame(data=b"\x00"), 0)  # the two oldest were forgotten
    assert not echoes.is_echo(frame(data=b"\x01"), 0)
    assert all(echoes.is_echo(frame(data=bytes([c])), 0) for c in range(2, 6))


def test_foreign_is_is_echo_frame_by_frame_on_random_traffic():
    """A turn's frames through ``foreign`` (looked up only when one carries an awaited COB-ID)
    leave what ``is_echo`` one frame at a time leaves, and the two filters await the same frames
    after: random sends, failed sends, turns of echoes, foreign copies and other frames, on
    three channels, the clock moving past the echo window now and then."""
    import random

    rng = random.Random(7)
    clock = Clock()
    batch, single = EchoFilter(clock), EchoFilter(clock)
    ids = (0x000, 0x080, 0x601, 0x181, 0x702)
    sent = []  # (channel, id, data, remote) of frames sent, echo not yet seen
    for step in range(3000):
        op = rng.random()
        if op < 0.3:
            key = (rng.randrange(3), rng.choice(ids[:3]), bytes([rng.randrange(3)]), rng.random() < 0.1)
            if key[3]:
                key = key[:2] + (b"", True)
            for f in (batch, single):
                f.sent(*key)
            sent.append(key)
            if rng.random() < 0.1:  # the send failed
                for f in (batch, single):
                    f.forget(*key)
                sent.pop()
        elif op < 0.9:
            channel = rng.randrange(3)
            turn = []
            for _ in range(rng.randrange(1, 8)):
                if sent and rng.random() < 0.4:
                    ch, can_id, data, remote = sent.pop(rng.randrange(len(sent)))
                    if ch != channel and rng.random() < 0.5:
                        continue
                    turn.append(frame(can_id, data, remote))
                else:
                    turn.append(frame(rng.choice(ids), bytes([rng.randrange(3)])))
            kept = batch.foreign(turn, channel)
            assert list(kept) == [m for m in turn if not single.is_echo(m, channel)], step
        else:
            clock.now += rng.choice((0.01, 0.3, ECHO_WINDOW_S + 0.01))
        assert len(batch) == len(single)
        # the COB-ID index counts exactly the frames awaited (else the turns it lets through
        # unlooked-at could hold an echo, or every turn would be looked up)
        counts = {}
        for (_, can_id, _, _), times in batch._awaited.items():
            counts[can_id] = counts.get(can_id, 0) + len(times)
        assert batch._awaited_ids == counts
    assert len(batch) > 0  # the traffic left frames awaited: the comparison was not all empty


def test_the_streams_frames_on_udp_multicast_reach_python_can_and_come_back_as_echoes():
    """The master's frames written straight on the udp_multicast socket (data frames; a remote
    frame through ``bus.send``): a python-can receiver on each group gets them - ID, data, RTR,
    in order - and the stream's own sockets' copies are all absorbed as echoes, nothing else."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_cycles_patch import patch_scene  # noqa: E402
    from test_service_multiprocess import multicast_port  # noqa: E402

    from fusion_center.service.cycles import CycleAssembler

    groups = [("239.74.163.51", multicast_port()), ("239.74.163.52", multicast_port())]  # a port each:
    # a socket bound to a port hears every group joined on it (Linux, IP_MULTICAST_ALL)
    own = [can.Bus(interface="udp_multicast", channel=g, port=p, hop_limit=0) for g, p in groups]
    other = [can.Bus(interface="udp_multicast", channel=g, port=p, hop_limit=0) for g, p in groups]
    try:
        events = stream.EventStream(CycleAssembler(patch_scene(sizes=(10, 70))), buses=own)
        events.echoes = EchoFilter()
        events.transmit_all([(0, 0x080, b"\x01"), (1, 0x080, b"\x01")])
        events.transmit_all([(1, 0x000, bytes((0x01, 0x00)))])
        events.transmit_all([(0, 0x701, b"")], remote=True)
        assert events._senders[0] is not None  # the direct path was taken
        want = [[(0x080, b"\x01", False), (0x701, b"", True)], [(0x080, b"\x01", False), (0x000, b"\x01\x00", False)]]
        for k, bus in enumerate(other):
            got = [bus.recv(2.0) for _ in want[k]]
            assert [(m.arbitration_id, bytes(m.data), m.is_remote_frame) for m in got] == want[k]
        for k, bus in enumerate(own):
            copies = [bus.recv(2.0) for _ in want[k]]
            assert list(events.echoes.foreign(copies, k)) == []
        assert len(events.echoes) == 0
    finally:
        for bus in own + other:
            bus.shutdown()
