"""The master's own frames looped back by udp_multicast (EchoFilter): one copy absorbed per frame
sent, within the echo window, on the channel it was sent on - nothing else."""

import can

from fusion_center.service import stream
from fusion_center.service.stream import ECHO_WINDOW_S, EchoFilter


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
    monkeypatch.setattr(stream, "ECHO_PENDING_MAX", 4)
    echoes = EchoFilter(Clock())
    for counter in range(6):
        echoes.sent(0, 0x080, bytes([counter]), False)
    assert len(echoes) == 4
    assert not echoes.is_echo(frame(data=b"\x00"), 0)  # the two oldest were forgotten
    assert not echoes.is_echo(frame(data=b"\x01"), 0)
    assert all(echoes.is_echo(frame(data=bytes([c])), 0) for c in range(2, 6))
