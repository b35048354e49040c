"""``fusion-center assemble``: a ``CycleAssembler`` over one channel group, listening on its
buses, each closed cycle sent to the fuser (issue 14; :mod:`.assemblers`).
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections import deque
from typing import Sequence

import can
import numpy as np

from taxel_net import gcfreeze
from taxel_net.errors import UsageError
from taxel_net.patches import devices as scene_devices, node_label
from taxel_net.scene import Scene
from .assembler_parts import (AUTHKEY_ENV, LOG_INTERVAL_S, NMT_RESETS, CyclePart, RateLimitedLog, authkey_for,
                              group_layout, key_file, read_key_file, scene_fingerprint, shutdown_connection,
                              tune_connection)
from .assembler_wire import (ANSWER_MAX, HANDSHAKE_TIMEOUT_S, PROTOCOL, BadMessage, Deadline, decode_answer,
                             encode_hello, encode_part, handshake, recv_frame)
from .common_frames import CommonFrames
from .cycle_records import ClosedCycle, EmcyEvent, quantise_timestamp

logger = logging.getLogger("fusion_center.service.assemblers")

RECONNECT_FIRST_S = 0.1  # wait before the first try after a break; doubled after every failed try
RECONNECT_MAX_S = 2.0    # ... up to this


class Refused(Exception):
    """The fuser answered the hello with a refusal (the reason is the message)."""


class NoKey(Exception):
    """No ``$FUSION_CENTER_AUTHKEY`` and no key file of a fuser on that loopback port (yet)."""


class Unanswered(Exception):
    """The fuser did not finish the key handshake and answer the hello in time."""


class GroupAssembler:
    """A ``CycleAssembler`` over one channel group, its cycles numbered by SYNC and turned
    into :class:`CyclePart` (pure: feed events, get parts)."""

    def __init__(self, scene: Scene, channels: Sequence[int]):
        from .cycles import CycleAssembler

        self.scene = scene
        self.layout = group_layout(scene, channels)
        self.assembler = CycleAssembler(self.layout.sub)
        full_labels = {k: node_label(d.channel, d.node_id) for k, d in enumerate(scene_devices(scene))}
        self._label = {sub_label: full_labels[int(self.layout.devices[d])]
                       for d, sub_label in enumerate(self.assembler.labels)}
        self.overflow = int(scene.bus.sync_counter)
        self.reset_at: int | None = None  # first assembler cycle after the master's reset broadcast
        self.heard_reset = False  # numbers count from the master's reset (told the fuser at a reconnect)
        self.last: tuple[int, int, int | None] | None = None  # (assembler cycle, number, counter)

    def note_reset(self) -> None:
        """The master's broadcast reset communication / node was fed: numbers restart."""
        self.reset_at = self.assembler.cycle + 1
        self.heard_reset = True

    def feed(self, timestamp_us: int, channel: int, can_id: int, data: bytes, flags: int = 0) -> list[CyclePart]:
        closed = self.assembler.feed_all(timestamp_us, channel, can_id, data, flags)
        if channel == 0 and can_id == 0 and len(data) == 2 and data[1] == 0 and data[0] in NMT_RESETS:
            self.note_reset()
        return [self.part(c) for c in closed]

    def number(self, closed: ClosedCycle) -> int:
        c, counter = closed.cycle, closed.sync_counter
        if self.reset_at is not None and c >= self.reset_at:
            number = (counter - 1) if counter else c - self.reset_at  # the master counts from 1
            self.reset_at = None
        elif self.last is None:
            number = (counter - 1) if counter else c
        else:
            last_c, last_number, last_counter = self.last
            step = c - last_c
            if counter and last_counter and self.overflow:
                step = (counter - last_counter - 1) % self.overflow + 1  # a jump: lost SYNCs
            number = last_number + step
        self.last = (c, number, counter)
        return number

    def part(self, closed: ClosedCycle) -> CyclePart:
        lay = self.layout
        readings = closed.readings if not np.isnan(closed.readings).all() else None
        held = closed.held_readings if not np.isnan(closed.held_readings).all() else None
        emcy = tuple(EmcyEvent(self._label.get(e.node, e.node), int(lay.taxels[e.taxel]), e.code, e.register,
                               e.manufacturer, e.t_us) for e in closed.emcy)
        dev = closed.devices
        return CyclePart(
            channels=lay.channels, number=self.number(closed), sync_counter=closed.sync_counter,
            closed_by=closed.closed_by, closed_after_us=int(closed.close_us - closed.sync_us),
            decisions=closed.decisions, readings=readings, received=closed.received,
            expected=np.asarray(closed.expected), missing=np.asarray(closed.missing),
            states=np.asarray(closed.states), held_decisions=closed.held_decisions, held_readings=held,
            late_frames=closed.late_frames, bad_frames=closed.bad_frames, emcy=emcy,
            emcy_dropped=closed.emcy_dropped, duplicates=tuple(int(lay.devices[d]) for d in closed.duplicates),
            devices=None if dev is None else (dev.expected, dev.missing, dev.states, dev.complete))


# ---------------------------------------------------------------------------- the assembler process

class AssemblerProcess:
    """``fusion-center assemble``: a :class:`GroupAssembler` on its channels' buses, each
    closed cycle sent to the fuser as a :class:`CyclePart`.

    When the connection breaks without the fuser's ``bye`` it keeps assembling (the parts
    closed meanwhile count as not sent) and connects again, waiting 0.1 s doubling to 2 s
    between tries, for up to ``reconnect_timeout_s``; then :attr:`closed` is set with
    :attr:`gave_up` saying why."""

    handshake_timeout_s = HANDSHAKE_TIMEOUT_S  # connect -> the fuser's answer to the hello, else closed

    def __init__(self, scene: Scene, channels: Sequence[int], *, fuser: tuple[str, int], interface: str,
                 channel_names: Sequence[str] | None = None, bitrate: int | None = None,
                 bus_kwargs: dict | None = None, authkey: bytes | None = None, reconnect_timeout_s: float = 60.0):
        self.scene = scene
        self.group = GroupAssembler(scene, channels)
        self.layout = self.group.layout
        # the group's patch TPDOs of packed decisions fed a run at a time (None: the scene has none)
        self.common = CommonFrames.for_assembler(self.group.assembler)
        self._gc_held = False  # holds taxel_net.gcfreeze once connected, until closed
        names = list(channel_names) if channel_names is not None else list(scene.bus.channels)
        if len(names) != len(scene.bus.channels):
            raise UsageError(f"--channel: the scene has {len(scene.bus.channels)} channel(s) "
                             f"{list(scene.bus.channels)}, got {len(names)}")
        self.channel_names = [names[c] for c in self.layout.channels]
        self.interface = interface
        self.bitrate = bitrate
        self.bus_kwargs = dict(bus_kwargs or {})
        self.fuser = fuser
        # None: the key of this user's fuser on that loopback port, read at every try (assembler_parts)
        self.authkey = authkey if authkey is not None else authkey_for(fuser[0], "--fuser")
        self.buses = []
        self.notifiers = []
        self.conn = None
        self.lock = threading.Lock()       # the event stream: one order over the group's channels
        self._send_lock = threading.Lock()
        self._outbox: deque[CyclePart] = deque()
        self.parts_sent = 0
        self.parts_unsent = 0
        self.events = 0
        self.closed = threading.Event()    # the fuser said bye, or went away and did not come back
        self.bye = False
        self.reconnect_timeout_s = float(reconnect_timeout_s)
        self.reconnects = 0
        self.bad_messages = 0              # frames from the fuser that were no message of the protocol
        self.gave_up: str | None = None    # why the fuser is given up (closed without bye)
        self._stop = threading.Event()     # close(): no more reconnecting
        self._log = RateLimitedLog(logger)

    def open(self) -> "AssemblerProcess":
        import can

        from taxel_net.canmsg import tune_udp_multicast

        if self.interface not in can.interfaces.VALID_INTERFACES:
            raise UsageError(f"--interface {self.interface!r}: not a python-can interface")
        try:
            for name in self.channel_names:
                kwargs = dict(self.bus_kwargs)
                if self.bitrate is not None:
                    kwargs["bitrate"] = self.bitrate
                try:
                    bus = can.Bus(interface=self.interface, channel=name, **kwargs)
                except Exception as exc:  # noqa: BLE001
                    raise UsageError(f"--channel {name!r} cannot be opened with interface {self.interface!r}: "
                                     f"{type(exc).__name__}: {exc}") from None
                tune_udp_multicast(bus)
                self.buses.append(bus)
            for index, bus in enumerate(self.buses):
                self.notifiers.append(can.Notifier(bus, [_PartListener(self, index)], timeout=0.05))
        except BaseException:
            self.close()
            raise
        return self

    def _key(self) -> bytes:
        if self.authkey is not None:
            return self.authkey
        key = read_key_file(self.fuser[1])
        if key is None:
            raise NoKey(f"no key file {key_file(self.fuser[1])!r} of a fuser of this user (`fusion-center run "
                        f"--assemblers` writes it; another user's fuser: set {AUTHKEY_ENV} on both sides)")
        return key

    def _dial(self):
        """One try: connect, key handshake, hello, welcome -> the connection. Raises :class:`Refused`,
        :class:`NoKey`, :class:`Unanswered` (the fuser took longer than HANDSHAKE_TIMEOUT_S),
        :class:`~.assembler_wire.BadMessage`, OSError, EOFError (closed during the hello) or
        multiprocessing's AuthenticationError. Nothing received is unpickled (:mod:`.assembler_wire`)."""
        from multiprocessing.connection import Client

        key = self._key()
        conn = Client(self.fuser)  # no authkey: the handshake below, under a deadline
        deadline = Deadline(conn, self.handshake_timeout_s)
        try:
            tune_connection(conn)
            handshake(conn, key, server=False)
            conn.send_bytes(encode_hello(scene_fingerprint(self.scene), self.layout.channels, socket.gethostname(),
                                         os.getpid(), self.group.heard_reset))
            answer = decode_answer(recv_frame(conn, ANSWER_MAX), ("welcome", "refused"))
        except BaseException as exc:
            deadline.cancel()
            conn.close()
            if deadline.expired and isinstance(exc, (EOFError, OSError)):
                raise Unanswered(f"no answer to the hello within {self.handshake_timeout_s:g} s") from None
            raise
        deadline.cancel()
        if answer["kind"] != "welcome":
            conn.close()
            raise Refused(answer["why"])
        return conn

    def connect(self, timeout_s: float = 30.0) -> None:
        """Connect to the fuser (retrying while it is not listening yet, and while its key file
        is missing or stale), say hello."""
        from multiprocessing.connection import AuthenticationError

        host, port = self.fuser
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                conn = self._dial()
                break
            except Refused as exc:
                raise UsageError(f"--fuser {host}:{port}: refused: {exc}") from None
            except EOFError:
                raise UsageError(f"--fuser {host}:{port}: the connection closed during the hello") from None
            except UsageError:
                raise
            except BadMessage as exc:
                raise UsageError(f"--fuser {host}:{port}: not a fuser of protocol {PROTOCOL}: {exc}") from None
            except (NoKey, AuthenticationError) as exc:
                # a key file not written yet, or one of the fuser before (replaced as the new one starts)
                if (isinstance(exc, NoKey) or self.authkey is None) and time.monotonic() < deadline:
                    time.sleep(0.1)
                    continue
                if isinstance(exc, NoKey):
                    raise UsageError(f"--fuser {host}:{port}: {exc}") from None
                hint = (f"the same {AUTHKEY_ENV} on both sides?" if self.authkey is not None else
                        f"the key in {key_file(port)!r} is not this fuser's: a fuser of another user? Then set "
                        f"{AUTHKEY_ENV} on both sides")
                raise UsageError(f"--fuser {host}:{port}: {type(exc).__name__}: {exc} ({hint})") from None
            except Unanswered as exc:
                raise UsageError(f"--fuser {host}:{port}: {exc} (is it a fuser?)") from None
            except (ConnectionRefusedError, socket.timeout, OSError) as exc:
                if isinstance(exc, ConnectionRefusedError) or getattr(exc, "errno", None) in (111, 113, 110):
                    if time.monotonic() < deadline:
                        time.sleep(0.1)
                        continue
                raise UsageError(f"--fuser {host}:{port}: cannot connect ({exc.strerror or exc}) within "
                                 f"{timeout_s:g} s: is `fusion-center run --assemblers {host}:{port}` running?") from None
            except Exception as exc:  # noqa: BLE001 - anything else: one line
                raise UsageError(f"--fuser {host}:{port}: {type(exc).__name__}: {exc}") from None
        self.conn = conn
        threading.Thread(target=self._watch, name="fuser-watch", daemon=True).start()
        if not self._gc_held:  # the set-up is not traversed by the cyclic collector (as the centre's run)
            self._gc_held = True
            gcfreeze.hold()

    def _watch(self) -> None:
        """Hears the fuser: its bye ends the process; a break without bye, a reconnect."""
        while True:
            conn = self.conn
            try:
                while conn is not None:  # the fuser sends nothing but its bye after the welcome
                    decode_answer(recv_frame(conn, ANSWER_MAX), ("bye",))
                    self.bye = True
                    self.closed.set()
                    return
            except BadMessage as exc:
                self.bad_messages += 1
                host, port = self.fuser
                self._log.warning("bad message", f"the fuser {host}:{port} sent what is not a bye of protocol "
                                                 f"{PROTOCOL} ({exc}): connection closed, reconnecting")
            except (EOFError, OSError):
                pass
            with self._send_lock:
                if self.conn is conn:
                    self.conn = None
            if conn is not None:
                try:
                    conn.close()
                except OSError:
                    pass
            if self._stop.is_set() or not self._reconnect():
                self.closed.set()
                return

    def _reconnect(self) -> bool:
        """Try again and again (bounded back-off) until the fuser takes this group back (True),
        :meth:`close` or ``reconnect_timeout_s`` (False, :attr:`gave_up` set)."""
        host, port = self.fuser
        since = time.monotonic()
        deadline = since + self.reconnect_timeout_s
        unsent = self.parts_unsent
        self._log.warning("lost", f"the connection to the fuser {host}:{port} broke: reconnecting for up to "
                                  f"{self.reconnect_timeout_s:g} s (cycles closed meanwhile are not sent)")
        delay, last = RECONNECT_FIRST_S, None
        while True:
            wait = min(delay, deadline - time.monotonic())
            if wait <= 0:
                break
            if self._stop.wait(wait):
                return False
            delay = min(2 * delay, RECONNECT_MAX_S)
            try:
                conn = self._dial()
            except Refused as exc:  # e.g. the fuser has not seen the break yet: try again
                last = f"refused: {exc}"
            except EOFError:
                last = "the connection closed during the hello"
            except Exception as exc:  # noqa: BLE001 - refused, unreachable, a wrong key: all retried
                last = f"{type(exc).__name__}: {getattr(exc, 'strerror', None) or exc}"
            else:
                with self._send_lock:
                    if self._stop.is_set():  # closed meanwhile
                        conn.close()
                        return False
                    self.conn = conn
                self.reconnects += 1
                self._log.warning("back", f"reconnected to the fuser {host}:{port} after "
                                          f"{time.monotonic() - since:.1f} s ({self.parts_unsent - unsent} "
                                          "cycle(s) not sent meanwhile)")
                return True
            if time.monotonic() - since >= LOG_INTERVAL_S:
                self._log.warning("retry", f"the fuser {host}:{port} is not back after "
                                           f"{time.monotonic() - since:.0f} s ({last})")
        self.gave_up = (f"the fuser {host}:{port} went away and was not back within {self.reconnect_timeout_s:g} s"
                        + (f" (last try: {last})" if last else ""))
        return False

    def close(self) -> None:
        self._stop.set()
        if self._gc_held:
            self._gc_held = False
            gcfreeze.release()
        for notifier in self.notifiers:
            try:
                notifier.stop(timeout=2)
            except Exception:  # noqa: BLE001
                pass
        self.notifiers = []
        for bus in self.buses:
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001
                pass
        self.buses = []
        with self._send_lock:
            conn, self.conn = self.conn, None
        if conn is not None:
            shutdown_connection(conn)  # wakes the watcher
            try:
                conn.close()
            except OSError:
                pass

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()

    def receive(self, msg, channel: int) -> None:
        self.receive_all((msg,), channel)

    def receive_all(self, msgs, channel: int) -> None:
        """Frames of one channel in bus order (a receive turn), under one take of the lock; the
        parts they close are sent after the last."""
        from .stream import message_flags

        if not isinstance(msgs, (list, tuple)):
            msgs = list(msgs)
        closed_any = False
        assembler = self.group.assembler
        with self.lock:
            common = self.common
            index, count = 0, len(msgs)
            while index < count:
                if common is not None:  # a run of common frames in one loop (.common_frames); they
                    # close nothing, and their time stamps are not before the first event's
                    fed, _ = common.feed(msgs, index, channel, assembler.t0_us)
                    if fed:
                        self.events += fed
                        index += fed
                        if index == count:
                            break
                msg = msgs[index]
                index += 1
                self.events += 1
                try:
                    parts = self.group.feed(quantise_timestamp(msg.timestamp), channel, msg.arbitration_id,
                                            bytes(msg.data), message_flags(msg))
                except Exception as exc:  # noqa: BLE001 - as the centre's stream: counted, logged, the turn goes on
                    # (raised out of here it would end the reading of the bus for good)
                    if assembler.events < self.events:
                        assembler.count_internal_error()
                    self._log.warning("internal_error", f"receive path: {type(exc).__name__}: {exc}")
                    continue
                if parts:
                    self._outbox.extend(parts)
                    closed_any = True
        if closed_any:
            self._send()

    def _send(self) -> None:
        with self._send_lock:  # parts leave in the order they closed
            while self._outbox:
                part = self._outbox.popleft()
                conn = self.conn
                if conn is None or self.closed.is_set():  # disconnected: not sent, never queued
                    self.parts_unsent += 1
                    continue
                part.sent_at = time.time()
                try:
                    data = encode_part(part)
                except Exception as exc:  # noqa: BLE001 - a part that cannot be encoded: not sent, the rest go on
                    self.parts_unsent += 1
                    self._log.warning("encode", f"a part not sent: {type(exc).__name__}: {exc}")
                    continue
                try:
                    conn.send_bytes(data)
                    self.parts_sent += 1
                except (OSError, ValueError):
                    self.parts_unsent += 1
                    self.conn = None
                    shutdown_connection(conn)  # the watcher wakes and reconnects


class _PartListener(can.Listener):
    """python-can listener of one channel of an assembler process (never raises)."""

    def __init__(self, process: AssemblerProcess, channel: int):
        self.process = process
        self.channel = channel

    def on_message_received(self, msg) -> None:
        self.on_messages_received((msg,))

    def on_messages_received(self, msgs) -> None:
        """A receive turn's frames (taxel_net.receiver), in order."""
        try:
            self.process.receive_all(msgs, self.channel)
        except Exception:  # noqa: BLE001 - never let the Notifier thread die
            logger.exception("assembler receive path failed")

    def on_error(self, exc) -> None:
        logger.warning("bus error on channel %d: %s", self.channel, exc)

    def stop(self) -> None:
        pass

