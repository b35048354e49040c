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

from taxel_net import gcfreeze
from taxel_net.errors import UsageError
from taxel_net.scene import Scene
from . import assembler_link as link_keys
from .assembler_parts import (AUTHKEY_ENV, LOG_INTERVAL_S, CyclePart, RateLimitedLog, authkey_for, key_file,
                              read_key_file, scene_fingerprint)
from .assembler_wire import (ANSWER_MAX, HANDSHAKE_TIMEOUT_S, PROTOCOL, BadMessage, decode_answer, encode_hello,
                             encode_part)
from .zenoh_config import endpoint, endpoint_host
from .common_frames import CommonFrames
from .cycle_records import EMCY_PER_CYCLE, EmcyEvent, quantise_timestamp

from .group_assembler import GroupAssembler  # noqa: F401 - the group's parts (a public name of .assemblers)

logger = logging.getLogger("fusion_center.service.assemblers")

RECONNECT_FIRST_S = 0.1  # wait before the first try after a break; doubled after every failed try
RECONNECT_MAX_S = 2.0    # ... up to this
CALLBACKS_WAIT_S = 2.0   # close(): at most this long for Zenoh callbacks still running


class Refused(Exception):
    """The fuser answered the hello with a refusal (the reason is the message)."""


class NoKey(Exception):
    """No ``$FUSION_CENTER_AUTHKEY`` and no key file of a fuser on that loopback port (yet)."""


class Unanswered(Exception):
    """No answer to the hello signed with this key in time (no fuser there yet, or one of
    another key)."""


# ---------------------------------------------------------------------------- the assembler process

class AssemblerProcess:
    """``fusion-center assemble``: a :class:`GroupAssembler` on its channels' buses, each
    closed cycle sent to the fuser as a :class:`CyclePart` over Zenoh (:mod:`.assembler_link`).

    When the link breaks without the fuser's ``bye`` (the fuser's liveliness token gone, or
    the fuser dropped the link) it keeps assembling (the parts closed meanwhile count as not
    sent; their boot-ups and EMCYs go with the next part sent) and says hello again, waiting 0.1 s
    doubling to 2 s between tries, for up to ``reconnect_timeout_s``; then :attr:`closed` is
    set with :attr:`gave_up` saying why.

    ``fuser``: the Zenoh endpoint of the fuser's link session (``tcp/127.0.0.1:47400``; a
    (host, port) pair or ``HOST:PORT`` mean tcp); ``zenoh_config``: a Zenoh configuration file
    (:mod:`.zenoh_config`: TLS, authentication)."""

    handshake_timeout_s = HANDSHAKE_TIMEOUT_S  # hello -> the fuser's answer, else the try failed

    def __init__(self, scene: Scene, channels: Sequence[int], *, fuser, interface: str,
                 channel_names: Sequence[str] | None = None, bitrate: int | None = None,
                 bus_kwargs: dict | None = None, authkey: bytes | None = None, reconnect_timeout_s: float = 60.0,
                 zenoh_config: str | None = None):
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
        if isinstance(fuser, tuple):
            host, port = fuser
            fuser = f"tcp/[{host}]:{port}" if ":" in host else f"tcp/{host}:{port}"
        self.fuser = endpoint(fuser, "--fuser")
        self.zenoh_config = zenoh_config
        self.port = int(self.fuser.split("?")[0].rpartition(":")[2])
        # None: the key of this user's fuser on that loopback port, read at every try (assembler_parts)
        self.authkey = authkey if authkey is not None else authkey_for(endpoint_host(self.fuser), "--fuser")
        self.prefix = link_keys.prefix(scene.name)
        self.buses = []
        self.notifiers = []
        self.session = None
        self.link: _Link | None = None     # the welcomed link (None: not connected)
        self.lock = threading.Lock()       # the event stream: one order over the group's channels
        self._send_lock = threading.Lock()
        self._outbox: deque[CyclePart] = deque()
        self.parts_sent = 0
        self.parts_unsent = 0
        # scene device -> t_us of a boot-up whose part was not sent: an event the fuser still needs (its
        # over-range tracker forgets the node's flag on it) - carried by the next part sent (_send)
        self._unsent_bootups: dict[int, int] = {}
        # likewise its EMCYs (bus order, at most EMCY_PER_CYCLE: an over-range EMCY is sent on the rising
        # edge only) and the EMCYs not kept (the part's own emcy_dropped, those beyond the bound)
        self._unsent_emcy: list[EmcyEvent] = []
        self._unsent_emcy_dropped = 0
        self.events = 0
        self.closed = threading.Event()    # the fuser said bye, or went away and did not come back
        self.bye = False
        self.reconnect_timeout_s = float(reconnect_timeout_s)
        self.reconnects = 0
        self.bad_messages = 0              # messages to this assembler that were no signed message of the protocol
        self.unsigned_answers = 0          # answers to a hello not signed with this key (a fuser of another key)
        self.gave_up: str | None = None    # why the fuser is given up (closed without bye)
        self._stop = threading.Event()     # close(): no more reconnecting
        self._broken = threading.Event()   # the link broke: the watcher says hello again
        self._dead: list[_Link] = []       # broken links, undeclared by the watcher
        self._log = RateLimitedLog(logger)
        # Zenoh callbacks running now (its threads, not Python's): close() waits for them, for a
        # Zenoh thread still in one when the interpreter finalizes is ended by pthread_exit, whose
        # unwinding through Rust frames aborts the process ("FATAL: exception not rethrown", rc -6)
        self._callbacks = 0
        self._callbacks_done = threading.Condition()

    def open(self) -> "AssemblerProcess":
        import can

        from taxel_net.canmsg import tune_udp_multicast
        from .zenoh_config import open_session

        if self.interface not in can.interfaces.VALID_INTERFACES:
            raise UsageError(f"--interface {self.interface!r}: not a python-can interface")
        config, what = link_keys.assembler_config(self.fuser, self.zenoh_config)
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
            self.session = open_session(config, f"--fuser {self.fuser}")
            for index, bus in enumerate(self.buses):
                self.notifiers.append(can.Notifier(bus, [_PartListener(self, index)], timeout=0.05))
        except BaseException:
            self.close()
            raise
        return self

    def _key(self) -> bytes:
        if self.authkey is not None:
            return self.authkey
        key = read_key_file(self.port)
        if key is None:
            raise NoKey(f"no key file {key_file(self.port)!r} of a fuser of this user (`fusion-center run "
                        f"--assemblers` writes it; another user's fuser: set {AUTHKEY_ENV} on both sides)")
        return key

    def _dial(self) -> "_Link":
        """One try: a new link id, its subscriber and liveliness token, the hello as a query,
        the fuser's signed answer -> the welcomed :class:`_Link`. Raises :class:`Refused`,
        :class:`NoKey`, :class:`Unanswered` (no signed answer within HANDSHAKE_TIMEOUT_S: no
        fuser there yet, or one of another key) or :class:`~.assembler_wire.BadMessage` (a
        signed answer that is no message of protocol 3). Nothing received is unpickled."""
        import zenoh

        mac_key = link_keys.mac_key(self._key())
        link = _Link(self, link_keys.new_id(), mac_key)
        try:
            link.declare()
            hello = encode_hello(scene_fingerprint(self.scene), self.layout.channels, socket.gethostname(),
                                 os.getpid(), self.group.heard_reset)
            key = link_keys.hello_key(self.prefix)
            hello_mac = link_keys.mac(mac_key, key, hello, link.id.encode())
            answer, unsigned = None, 0
            replies = self.session.get(key, payload=hello, attachment=link.id.encode() + hello_mac,
                                       timeout=self.handshake_timeout_s, congestion_control=zenoh.CongestionControl.BLOCK)
            for reply in replies:
                sample = reply.ok
                if sample is None:
                    continue
                payload = sample.payload.to_bytes()
                ident = link_keys.split_id(link_keys.as_bytes(sample.attachment))
                if len(payload) > ANSWER_MAX or ident is None or not link_keys.verify(
                        mac_key, key, payload, ident[1], hello_mac + ident[0].encode()):
                    unsigned += 1
                    continue
                answer = decode_answer(payload, ("welcome", "refused"))
                link.run = ident[0]
                break
            self.unsigned_answers += unsigned
            if answer is None:
                raise Unanswered(f"no answer to the hello signed with this key (answers not signed with it: "
                                 f"{self.unsigned_answers})")
            if answer["kind"] != "welcome":
                raise Refused(answer["why"])
            link.welcomed()
        except BaseException:
            link.undeclare()
            raise
        return link

    def connect(self, timeout_s: float = 30.0) -> None:
        """Say hello to the fuser (retrying while it is not there yet, and while its key file
        is missing or stale)."""
        where = self.fuser
        deadline = time.monotonic() + timeout_s
        last = None
        while True:
            try:
                link = self._dial()
                break
            except Refused as exc:
                raise UsageError(f"--fuser {where}: refused: {exc}") from None
            except BadMessage as exc:
                raise UsageError(f"--fuser {where}: not a fuser of protocol {PROTOCOL}: {exc}") from None
            except (NoKey, Unanswered) as exc:
                # no fuser yet, a key file not written yet, or one of the fuser before (replaced as it starts)
                last = exc
                if time.monotonic() < deadline:
                    self._stop.wait(0.1)
                    continue
                if isinstance(exc, NoKey):
                    raise UsageError(f"--fuser {where}: {exc}") from None
                hint = (f"the same {AUTHKEY_ENV} on both sides?" if self.authkey is not None else
                        f"the key in {key_file(self.port)!r} is not this fuser's: a fuser of another user? "
                        f"Then set {AUTHKEY_ENV} on both sides")
                raise UsageError(f"--fuser {where}: {last} within {timeout_s:g} s: is `fusion-center run "
                                 f"--assemblers {where}` running ({hint})?") from None
            except UsageError:
                raise
            except Exception as exc:  # noqa: BLE001 - anything else: one line
                raise UsageError(f"--fuser {where}: {type(exc).__name__}: {exc}") from None
        with self._send_lock:
            self.link = link
        threading.Thread(target=self._watch, name="fuser-watch", daemon=True).start()
        if not self._gc_held:  # the set-up is not traversed by the cyclic collector (as the centre's run)
            self._gc_held = True
            gcfreeze.hold()

    def _in_callback(self, delta: int) -> None:
        with self._callbacks_done:
            self._callbacks += delta
            if not self._callbacks:
                self._callbacks_done.notify_all()

    def _on_message(self, link: "_Link", query) -> None:
        """A message on this link's key from the fuser (a query, answered once taken): its bye
        ends the process, a refused (it dropped the link) a new hello; anything not signed and
        of the protocol is counted and ignored. The query is answered before :attr:`closed` is
        set: the bye's callback must not still be in Zenoh's ``reply`` when the process ends."""
        self._in_callback(+1)
        try:
            self._message(link, query)
        finally:
            self._in_callback(-1)

    def _message(self, link: "_Link", query) -> None:
        try:
            payload = link_keys.as_bytes(query.payload) or b""
            if len(payload) > ANSWER_MAX or not link_keys.verify(link.mac_key, link.to_key, payload,
                                                                 link_keys.as_bytes(query.attachment)):
                raise BadMessage("not signed with this run's key")
            answer = decode_answer(payload, ("bye", "refused"))
        except BadMessage as exc:
            self.bad_messages += 1
            self._log.warning("bad message", f"a message to this assembler on {link.to_key} is no signed bye or "
                                             f"refused of protocol {PROTOCOL} ({exc}): ignored")
            return
        except Exception:  # noqa: BLE001 - never raise into Zenoh
            logger.exception("fuser message failed")
            return
        try:
            query.reply(link.to_key, b"")
        except Exception:  # noqa: BLE001 - the fuser gone meanwhile
            pass
        if self.link is link:
            if answer["kind"] == "bye":
                self.bye = True
                self.closed.set()  # last: the process may end from here on
            else:
                self._log.warning("dropped", f"the fuser dropped the link ({answer['why']})")
                self._break(link)

    def _on_fuser_alive(self, link: "_Link", sample) -> None:
        self._in_callback(+1)
        try:
            import zenoh

            if sample.kind == zenoh.SampleKind.DELETE and self.link is link:
                self._break(link)
        except Exception:  # noqa: BLE001
            logger.exception("fuser liveliness failed")
        finally:
            self._in_callback(-1)

    def _break(self, link: "_Link") -> None:
        with self._send_lock:
            if self.link is link:
                self.link = None
                self._dead.append(link)
                self._broken.set()

    def _watch(self) -> None:
        """Says hello again whenever the link breaks without the fuser's bye."""
        while True:
            while not self._broken.wait(0.2):
                if self._stop.is_set() or self.closed.is_set():
                    return
            self._broken.clear()
            with self._send_lock:
                dead, self._dead = self._dead, []
            for link in dead:  # (not from a Zenoh callback: one may be running it)
                link.undeclare()
            if self._stop.is_set() or self.closed.is_set():
                return
            if not self._reconnect():
                self.closed.set()
                return

    def _reconnect(self) -> bool:
        """Try again and again (bounded back-off) until the fuser takes this group back (True),
        :meth:`close` or ``reconnect_timeout_s`` (False, :attr:`gave_up` set)."""
        where = self.fuser
        since = time.monotonic()
        deadline = since + self.reconnect_timeout_s
        unsent = self.parts_unsent
        self._log.warning("lost", f"the link to the fuser {where} broke: reconnecting for up to "
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
                link = self._dial()
            except Refused as exc:  # e.g. the fuser has not seen the break yet: try again
                last = f"refused: {exc}"
            except Exception as exc:  # noqa: BLE001 - unanswered, a wrong key: all retried
                last = f"{type(exc).__name__}: {exc}"
            else:
                with self._send_lock:
                    if self._stop.is_set():  # closed meanwhile
                        link.undeclare()
                        return False
                    self.link = link
                self.reconnects += 1
                self._log.warning("back", f"reconnected to the fuser {where} after "
                                          f"{time.monotonic() - since:.1f} s ({self.parts_unsent - unsent} "
                                          "cycle(s) not sent meanwhile)")
                return True
            if time.monotonic() - since >= LOG_INTERVAL_S:
                self._log.warning("retry", f"the fuser {where} is not back after "
                                           f"{time.monotonic() - since:.0f} s ({last})")
        self.gave_up = (f"the fuser {where} went away and was not back within {self.reconnect_timeout_s:g} s"
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
            link, self.link = self.link, None
            dead, self._dead = self._dead, []
        self._broken.set()  # wakes the watcher (it sees _stop)
        for old in dead + ([link] if link is not None else []):
            old.undeclare()
        if self.session is not None:
            try:
                self.session.close()
            except Exception:  # noqa: BLE001
                pass
            self.session = None
        with self._callbacks_done:  # none left in a Zenoh thread when the caller goes on (bounded)
            self._callbacks_done.wait_for(lambda: not self._callbacks, timeout=CALLBACKS_WAIT_S)

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

    def _unsent(self, part: CyclePart) -> None:
        """A part not sent (send lock held): counted; its boot-ups and EMCYs kept for the next part sent."""
        self.parts_unsent += 1
        kept = self._unsent_bootups
        for device, t_us in part.bootups:
            kept[device] = max(t_us, kept.get(device, t_us))
        emcy = part.emcy[:max(EMCY_PER_CYCLE - len(self._unsent_emcy), 0)]
        self._unsent_emcy.extend(emcy)
        self._unsent_emcy_dropped += part.emcy_dropped + len(part.emcy) - len(emcy)

    def _carry_unsent(self, part: CyclePart) -> None:
        """The boot-ups and EMCYs of parts not sent go with ``part`` (send lock held; if it is not
        sent either, _unsent keeps them again): a device's latest boot-up the one that counts, the
        kept EMCYs ahead of the part's own (bus order), at most EMCY_PER_CYCLE (the wire's bound; the
        earliest kept, the rest counted in emcy_dropped)."""
        if self._unsent_bootups:
            latest = self._unsent_bootups
            for device, t_us in part.bootups:
                latest[device] = max(t_us, latest.get(device, t_us))
            part.bootups = tuple(sorted(latest.items()))
            self._unsent_bootups = {}
        if self._unsent_emcy or self._unsent_emcy_dropped:
            emcy = self._unsent_emcy + list(part.emcy)
            part.emcy = tuple(emcy[:EMCY_PER_CYCLE])
            part.emcy_dropped += self._unsent_emcy_dropped + len(emcy) - len(part.emcy)
            self._unsent_emcy, self._unsent_emcy_dropped = [], 0

    def _send(self) -> None:
        with self._send_lock:  # parts leave in the order they closed
            while self._outbox:
                part = self._outbox.popleft()
                link = self.link
                if link is None or self.closed.is_set():  # disconnected: not sent, never queued
                    self._unsent(part)
                    continue
                self._carry_unsent(part)  # events of parts not sent go with this one
                part.sent_at = time.time()
                try:
                    data = encode_part(part)
                except Exception as exc:  # noqa: BLE001 - a part that cannot be encoded: not sent, the rest go on
                    self._unsent(part)
                    self._log.warning("encode", f"a part not sent: {type(exc).__name__}: {exc}")
                    continue
                try:
                    link.publisher.put(data, attachment=link_keys.mac(link.mac_key, link.part_key, data))
                    self.parts_sent += 1
                except Exception as exc:  # noqa: BLE001 - a closed session: the watcher says hello again
                    self._unsent(part)
                    self._log.warning("send", f"a part not sent: {type(exc).__name__}: {exc}")
                    self.link = None
                    self._dead.append(link)
                    self._broken.set()


class _Link:
    """One hello's link to the fuser: its id, keys, and the Zenoh entities declared for it."""

    def __init__(self, process: AssemblerProcess, link_id: str, mac_key: bytes):
        self.process = process
        self.id = link_id
        self.mac_key = mac_key
        p = process.prefix
        self.part_key = link_keys.part_key(p, link_id)
        self.to_key = link_keys.to_link_key(p, link_id)
        self.run: str | None = None  # the fuser's run id (from its answer)
        self.publisher = None
        self._entities: list = []

    def declare(self) -> None:
        session = self.process.session
        self._entities.append(session.declare_queryable(
            self.to_key, lambda query: self.process._on_message(self, query)))
        self._entities.append(session.liveliness().declare_token(link_keys.alive_key(self.process.prefix, self.id)))

    def welcomed(self) -> None:
        import zenoh

        session = self.process.session
        self.publisher = session.declare_publisher(
            self.part_key, congestion_control=zenoh.CongestionControl.BLOCK, express=True,
            priority=zenoh.Priority.REAL_TIME, reliability=zenoh.Reliability.RELIABLE)
        self._entities.append(self.publisher)
        key = link_keys.fuser_key(self.process.prefix, self.run)
        self._entities.append(session.liveliness().declare_subscriber(
            key, lambda sample: self.process._on_fuser_alive(self, sample), history=True))
        # gone between its answer and the subscriber (no DELETE would come): this try failed
        if not any(reply.ok is not None for reply in session.liveliness().get(
                key, timeout=self.process.handshake_timeout_s)):
            raise Unanswered("the fuser's liveliness token went away after its welcome")

    def undeclare(self) -> None:
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except Exception:  # noqa: BLE001 - a closed session
                pass
        self._entities = []


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

