"""The master's own frames looped back by udp_multicast (:class:`EchoFilter`): where the kernel
does not drop them (:func:`taxel_net.udp_filter.drop_own_frames`: remote frames, non-Linux), each
frame the centre sent absorbs one byte-identical copy received within :data:`ECHO_WINDOW_S`;
everything else - the same frame from another process included - is the bus's (docs/service.md)."""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Callable, Sequence

import can

ECHO_WINDOW_S = 1.0  # an echo of a frame the master sent comes back within this (udp_multicast)
ECHO_PENDING_MAX = 4096  # frames sent whose echo is still awaited (oldest forgotten first)


class EchoFilter:
    """The frames the master sent whose own echo has not come back yet (udp_multicast loops
    every datagram back to its sender). A received frame is dropped as an echo only if it is
    a byte-identical copy (channel, ID, data, RTR) of one of those sent within
    :data:`ECHO_WINDOW_S`, and each sent frame absorbs one copy at most: an identical-looking
    frame from another sender (another master's NMT/SYNC, a tool's SDO request) is counted
    and traced like any other frame.

    Every received frame is looked up, so the lookup is one dict access whatever the number of
    frames awaiting their echo (a scan of them took half the centre's CPU time at 4,096 taxels:
    ~10k frames/s against a few hundred SYNCs awaiting their echo; bench/skin_scale.py)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic):
        self._clock = clock
        self._awaited: dict[tuple[int, int, bytes, bool], deque[float]] = {}  # key -> send times, oldest first
        self._sent_order: deque[tuple[float, tuple[int, int, bytes, bool]]] = deque()  # for expiry, oldest first
        self._awaited_ids: dict[int, int] = {}  # COB-ID -> frames awaited with it (any channel)
        self._lock = threading.Lock()

    def __len__(self) -> int:
        """Frames sent within the echo window whose echo is still awaited."""
        now = self._clock()
        with self._lock:
            self._expire_locked(now)
            return sum(len(times) for times in self._awaited.values())

    def _expire_locked(self, now: float) -> None:
        order = self._sent_order
        while order and now - order[0][0] > ECHO_WINDOW_S:
            self._drop_oldest_locked()

    def _drop_oldest_locked(self) -> None:
        sent_at, key = self._sent_order.popleft()
        times = self._awaited.get(key)
        if times and times[0] == sent_at:  # not absorbed nor forgotten yet
            times.popleft()
            self._one_less_locked(key)
            if not times:
                del self._awaited[key]

    def _one_less_locked(self, key: tuple[int, int, bytes, bool]) -> None:
        ids = self._awaited_ids
        left = ids[key[1]] - 1
        if left:
            ids[key[1]] = left
        else:
            del ids[key[1]]

    def sent(self, channel: int, can_id: int, data: bytes, remote: bool) -> None:
        key = (channel, can_id, bytes(data), bool(remote))
        now = self._clock()
        with self._lock:
            if len(self._sent_order) >= ECHO_PENDING_MAX:
                self._drop_oldest_locked()
            self._awaited.setdefault(key, deque()).append(now)
            self._sent_order.append((now, key))
            self._awaited_ids[can_id] = self._awaited_ids.get(can_id, 0) + 1

    def forget(self, channel: int, can_id: int, data: bytes, remote: bool) -> None:
        """A frame that could not be sent: no echo will come."""
        key = (channel, can_id, bytes(data), bool(remote))
        with self._lock:
            times = self._awaited.get(key)
            if times:
                times.pop()  # the newest: the one just sent
                self._one_less_locked(key)
                if not times:
                    del self._awaited[key]

    def is_echo(self, msg: can.Message, channel: int) -> bool:
        if not self._awaited or msg.is_extended_id or msg.is_error_frame or msg.is_fd:
            return False  # none awaited (``sent`` is recorded before its frame goes out)
        now = self._clock()
        key = (channel, msg.arbitration_id, bytes(msg.data), bool(msg.is_remote_frame))
        with self._lock:
            self._expire_locked(now)
            times = self._awaited.get(key)
            if not times:
                return False
            times.popleft()  # each sent frame absorbs one copy, the oldest first
            self._one_less_locked(key)
            if not times:
                del self._awaited[key]
            return True

    def foreign(self, msgs: Sequence[can.Message], channel: int) -> Sequence[can.Message]:
        """The frames of a receive turn that are not echoes (:meth:`is_echo` of each, in order),
        looked up only where a frame carries a COB-ID a frame awaiting its echo was sent with (at
        skin scale a channel's SYNC echo comes in the turn of the ten PDOs answering it);
        ``msgs`` itself when no frame does."""
        ids = self._awaited_ids
        if not ids or not any(msg.arbitration_id in ids for msg in msgs):
            return msgs
        return [msg for msg in msgs if msg.arbitration_id not in ids or not self.is_echo(msg, channel)]
