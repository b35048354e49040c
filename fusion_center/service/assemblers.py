"""Cycle assemblers in other processes or hosts, one fuser (issue 14, "Beyond one host").

The per-channel work of the centre - decoding every PDO, liveness, NMT states, closing SYNC
cycles (:class:`~fusion_center.service.cycles.CycleAssembler`) - can run in separate
processes or hosts, each for a group of scene channels (``fusion-center assemble --serve
0-3``); one fuser (``fusion-center run --assemblers HOST:PORT``) merges their cycles and
evaluates them with the usual pipeline, writing the same records as
:class:`~fusion_center.service.fusion_service.FusionService`.

* **The buses** are existing transports only: every participant opens the same channels
  (python-can's ``udp_multicast`` on a LAN - any number of bus objects share a group;
  ``socketcand`` serves several clients in front of real interfaces; on one host several
  SocketCAN sockets see one bus). The fuser is the one CANopen master: it sends SYNC (with
  its counter), NMT, the SDO configuration and its heartbeat on every channel exactly as
  ``FusionService`` does. An assembler only listens: it hears the master's SYNCs like any
  node and runs a ``CycleAssembler`` over its channels (a sub-scene: the scene's taxels of
  those channels, the first of them as the channel whose SYNC opens a cycle).
* **Cycle numbers**: an assembler numbers its cycles by SYNC, as ``node_sim.rig`` does (the
  master's broadcast reset communication restarts the count; a jump of the SYNC counter is
  read as lost SYNCs). The fuser maps a part to the SYNC it sent by the part's SYNC counter
  (the latest SYNC it sent with that counter: unambiguous while a part arrives within
  ``sync_counter`` periods of its SYNC), without a counter by the assembler's number.
* **Assembler -> fuser**: :mod:`multiprocessing.connection` frames over TCP (``Listener`` /
  ``Client``, its HMAC challenge on a shared key, ``send_bytes`` / ``recv_bytes`` with a size
  limit) carrying the messages of :mod:`.assembler_wire` (protocol 2: msgpack maps, arrays as
  raw little-endian bytes, every field checked against the scene's group layout on decode;
  nothing received is unpickled, on either side). (CANopen on an "uplink" bus was the
  alternative: a 4,096-taxel part is ~29 kB per cycle, i.e. segmented transfers and a second
  master role for no gain.) The key is ``FUSION_CENTER_AUTHKEY``; without it only loopback
  addresses, with a per-run key the fuser writes to a file only its user can read
  (:func:`.assembler_parts.key_file`). A peer that does not pass the key handshake, sends
  anything but a message of the protocol, a frame over its size limit, or no hello within
  5 s is refused: counted (``refused`` in the summary, by kind), logged (rate-limited), its
  connection closed; the run goes on.
* **Merge** (:class:`CycleMerger`): per SYNC the fuser sent, one part per channel group. The
  cycle is ``complete``-able when every group's part arrived; a group whose part has not
  arrived when a later part of that group arrived (parts come in order), when the group
  disconnected, or ``part_deadline_s`` after the SYNC, is *missing*: its taxels count as
  silent (received nothing), the record is degraded and names the group in
  ``parts_missing`` (``closed_by: "part_missing"``). Cycles are evaluated in SYNC order;
  a part for a cycle already evaluated is counted (``late_parts``), never mixed in.
* **Reconnects**: an assembler whose connection breaks without the fuser's ``bye`` keeps
  assembling its buses (the parts closed meanwhile are counted as not sent, never queued) and
  connects again (0.1 s doubling to 2 s between tries, for ``--reconnect-timeout`` s; then it
  exits 1). The fuser accepts a group of its run again with the same hello checks (a group that
  is still connected is refused), counts it (``reconnects``) and merges its parts from then on;
  the cycles in between are degraded naming the group. A restarted assembler process is
  accepted the same way (its cycles are mapped by the SYNC counter; in a scene without one
  only an assembler that heard the master's reset, i.e. the same process, can come back).

By job: :mod:`.assembler_parts` (what both sides share: addresses and keys, channel groups,
:class:`CyclePart`), :mod:`.assembler_process` (the assembler: ``GroupAssembler``,
``AssemblerProcess``), :mod:`.cycle_merger` (the merge) and this module, the fuser
(:class:`AssembledFusionService`), with :mod:`.assembler_wire` (the messages on the
connection); their public names are importable from here.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from taxel_net.errors import UsageError
from taxel_net.scene import Scene
from .assembler_parts import (AUTHKEY_ENV, COB_SYNC, NMT_RESETS, CyclePart,  # noqa: F401
                              GroupLayout, RateLimitedLog, authkey_for, check_serve, group_layout, group_name,
                              is_loopback, parse_address, remove_key_file, scene_fingerprint, shutdown_connection,
                              tune_connection, write_key_file)
from .assembler_wire import (HANDSHAKE_TIMEOUT_S, HELLO_MAX, PROTOCOL, BadMessage, Deadline,  # noqa: F401
                             OtherVersion, PartCodec, decode_hello, encode_bye, encode_refused, encode_welcome,
                             handshake, recv_frame)
from .assembler_process import AssemblerProcess, GroupAssembler  # noqa: F401 - public names of this module
from .cycle_merger import CycleMerger, MergeStats  # noqa: F401
from .cycle_records import ClosedCycle, quantise_timestamp
from .fusion_service import FusionService
from .stream import EventStream

logger = logging.getLogger("fusion_center.service.assemblers")

MAX_HANDSHAKES = 16  # connections in their key handshake / hello at once; more are closed at once

# what the master needs to hear (accept filters, 11-bit): NMT, SYNC + EMCY, TIME, SDO both ways,
# heartbeats / boot-ups, LSS - every COB-ID but the PDOs (0x181..0x57F), which the assemblers take
MASTER_FILTERS = [
    {"can_id": 0x000, "can_mask": 0x7FF, "extended": False},
    {"can_id": 0x080, "can_mask": 0x780, "extended": False},
    {"can_id": 0x100, "can_mask": 0x7FF, "extended": False},
    {"can_id": 0x580, "can_mask": 0x780, "extended": False},
    {"can_id": 0x600, "can_mask": 0x780, "extended": False},
    {"can_id": 0x700, "can_mask": 0x780, "extended": False},
    {"can_id": 0x7E4, "can_mask": 0x7FE, "extended": False},
]


# ---------------------------------------------------------------------------- the fuser

class _FuserStream(EventStream):
    """The fuser's event stream: notes every SYNC the master sends (before it goes out)."""

    on_sync = None  # callable(payload: bytes) set by the service

    def transmit_all(self, frames, remote: bool = False) -> None:
        frames = list(frames)
        if self.on_sync is not None and not remote:
            for channel, can_id, data in frames:
                if channel == 0 and can_id == COB_SYNC:
                    self.on_sync(bytes(data))
        super().transmit_all(frames, remote)


class AssembledFusionService(FusionService):
    """The fuser: the CANopen master of :class:`FusionService` on every channel, its cycles
    assembled by ``fusion-center assemble`` processes (module docstring).

    ``listen``: (host, port) of the ``multiprocessing.connection`` listener the assemblers
    connect to (``authkey``: the shared key; None: ``$FUSION_CENTER_AUTHKEY``, else on loopback
    a per-run key written to :func:`.assembler_parts.key_file` at :meth:`open`); :meth:`boot`
    waits up to ``assembler_wait_s`` for assemblers covering every scene channel. The service's
    own ``CycleAssembler`` still runs (boot-ups, SDO answers, NMT states for the master), its
    closed cycles are not evaluated.

    ``pdo_filter`` (off by default): the fuser's buses accept only the master's traffic
    (:data:`MASTER_FILTERS`; kernel filters on SocketCAN). Only for scenes without a synchronous
    window: with one, the own assembler would hold SYNC k+1 until SYNC k+2 (no node frame after
    the window closes k), and with it an SDO request of a mid-run reconfiguration - whose answer
    would then arrive unsolicited (not handed to the SDO client). Measured on udp_multicast it
    saved nothing (python-can filters after parsing every datagram)."""

    handshake_timeout_s = HANDSHAKE_TIMEOUT_S  # connect -> a hello, else the connection is closed

    def __init__(self, scene: Scene, *, listen: tuple[str, int], authkey: bytes | None = None,
                 part_deadline_s: float | None = None, assembler_wait_s: float = 30.0,
                 pdo_filter: bool = False, **kwargs):
        super().__init__(scene, **kwargs)
        self.pdo_filter = bool(pdo_filter)
        self.listen_address = listen
        self.authkey = authkey if authkey is not None else authkey_for(listen[0], "--assemblers")
        self._key_file: str | None = None  # the per-run key's file (loopback without the variable)
        period = scene.bus.sync_period_ms / 1000.0
        # an assembler without a window closes a cycle with a silent node at the next SYNC
        self.part_deadline_s = part_deadline_s if part_deadline_s is not None else 2.5 * period + 0.1
        self.assembler_wait_s = assembler_wait_s
        self.merger = CycleMerger(scene, part_deadline_s=self.part_deadline_s)
        self.own_closed = 0
        echoes = self.stream.echoes
        self.stream = _FuserStream(self.assembler, on_closed=self._own_cycle, after_closed=self._process_pending)
        self.stream.echoes = echoes
        self.stream.on_sync = self._on_sync
        self._listener = None
        self._conns: dict = {}  # group name -> its connection
        self._conn_lock = threading.Lock()  # a group's connection and its place in the merger change together
        self._log = RateLimitedLog(logger)
        self._threads: list[threading.Thread] = []
        self._stop_merge = threading.Event()
        self._merge_lock = threading.Lock()  # emission order into _pending
        self.refused: deque[str] = deque(maxlen=8)  # the latest reasons hellos were refused
        self._handshakes = threading.BoundedSemaphore(MAX_HANDSHAKES)

    # -- life cycle
    def open(self) -> "AssembledFusionService":
        from multiprocessing.connection import Listener

        super().open()
        if self.pdo_filter:  # the PDOs are the assemblers' (kernel filters on SocketCAN, else python-can's)
            for bus in self.buses:
                bus.set_filters(MASTER_FILTERS)
        try:  # no authkey: the handshake is each connection's own thread's (_serve), under a deadline
            self._listener = Listener(self.listen_address, backlog=MAX_HANDSHAKES)
        except OSError as exc:
            self.close()
            host, port = self.listen_address
            raise UsageError(f"--assemblers {host}:{port}: cannot listen there ({exc.strerror or exc})") from None
        if self.authkey is None:  # loopback without FUSION_CENTER_AUTHKEY: this run's own key
            try:
                self.authkey, self._key_file = write_key_file(self._listener.address[1])
            except BaseException:
                self.close()
                raise
        for target, name in ((self._accept_loop, "assembler-accept"), (self._tick_loop, "merge-deadline")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def close(self) -> None:
        self._stop_merge.set()
        listener, self._listener = self._listener, None
        if listener is not None:
            _wake(listener)  # a close alone leaves the accept blocked - and the port listening
            try:
                listener.close()
            except OSError:
                pass
        with self._conn_lock:
            conns = list(self._conns.values())
        for conn in conns:
            try:
                conn.send_bytes(encode_bye())
            except (OSError, ValueError, EOFError):
                pass
            try:
                conn.close()
            except OSError:
                pass
        if self._key_file is not None:
            remove_key_file(self._key_file, self.authkey)
            self._key_file = None
        super().close()

    def boot(self, timeout_s: float = 3.0, configure: bool = True) -> list[int]:
        self.wait_for_assemblers(self.assembler_wait_s)
        return super().boot(timeout_s, configure)

    def wait_for_assemblers(self, timeout_s: float) -> None:
        want = set(range(len(self.scene.bus.channels)))
        deadline = time.monotonic() + timeout_s
        while self.merger.covered() != want:
            if time.monotonic() >= deadline:
                lacking = sorted(want - self.merger.covered())
                host, port = self.listen_address
                why = f" (refused: {'; '.join(self.refused)})" if self.refused else ""
                raise UsageError(f"--assemblers {host}:{port}: no assembler for scene channel(s) {lacking} after "
                                 f"{timeout_s:g} s: start `fusion-center assemble --scene ... --serve "
                                 f"{group_name(lacking)} --fuser {host}:{port}`{why}")
            time.sleep(0.02)

    def run(self, cycles: int, *, before_sync=None, timeout_s: float | None = None):
        if cycles < 1:
            raise UsageError(f"--cycles {cycles}: must be >= 1")
        period = self.scene.bus.sync_period_ms / 1000.0
        self.master.start_sync(cycles, before_sync)
        self.master.wait_sync_done(timeout_s if timeout_s is not None else cycles * period * 3 + 10.0)
        self.master.stop()
        deadline = time.monotonic() + self.part_deadline_s + 1.0
        while self.merger.pending() and time.monotonic() < deadline:
            time.sleep(0.005)
        self._emit(final=True)
        self.drain(timeout=5.0)
        return self.summary()

    # -- merge
    def _own_cycle(self, closed: ClosedCycle) -> None:
        self.own_closed += 1  # the master's own view of the cycle: not evaluated (the parts are)

    def _on_sync(self, payload: bytes) -> None:
        t0 = self.assembler.t0_us
        wall = time.time()
        sync_us = quantise_timestamp(wall) - (t0 if t0 is not None else 0)
        self.merger.opened(payload[0] if payload else None, max(0, sync_us), time.monotonic(), wall)

    def _emit(self, final: bool = False) -> None:
        with self._merge_lock:
            for closed in self.merger.emit(time.monotonic(), final=final):
                self._pending.append(closed)
        self._process_pending()

    def _tick_loop(self) -> None:
        tick = max(0.002, min(0.02, self.part_deadline_s / 4))
        while not self._stop_merge.wait(tick):
            try:
                self._emit()
            except Exception:  # noqa: BLE001 - the deadline thread never dies
                logger.exception("merge tick failed")

    def evaluate(self, closed: ClosedCycle) -> dict:
        record = self.pipeline.evaluate(closed)
        info = self.merger.info.pop(closed.cycle, None)
        record["parts_missing"] = info["parts_missing"] if info else []
        return record

    # -- connections
    def _accept_loop(self) -> None:
        while not self._stop_merge.is_set():
            listener = self._listener
            if listener is None:
                return
            try:
                conn = listener.accept()  # no handshake here (open): a silent peer holds nothing
            except Exception as exc:  # noqa: BLE001 - closed listener, out of file descriptors
                if self._stop_merge.is_set():
                    return
                self._log.warning("accept", f"assembler connection not accepted: {type(exc).__name__}: {exc}")
                self._stop_merge.wait(0.05)
                continue
            if self._stop_merge.is_set():  # close() woke it
                conn.close()
                return
            if not self._handshakes.acquire(blocking=False):
                self._refuse_peer(conn, "busy", f"more than {MAX_HANDSHAKES} connections in their handshake at once")
                continue
            thread = threading.Thread(target=self._serve, args=(conn,), name="assembler-conn", daemon=True)
            thread.start()

    def _refuse_peer(self, conn, kind: str, why: str, answer: bool = False) -> None:
        """A peer refused (``kind``: busy, key, timeout, message, hello): counted in the summary,
        logged (at most one line of a kind every 10 s), its connection closed; ``answer``: told
        why first (a ``refused`` message)."""
        self.merger.count_refused(kind)
        self._log.warning(f"refused {kind}", f"assembler connection refused ({kind}): {why}")
        if answer:
            try:
                conn.send_bytes(encode_refused(why))
            except (OSError, ValueError):
                pass
        try:
            conn.close()
        except OSError:
            pass

    def drop_assembler(self, name: str) -> bool:
        """Break the connection of group ``name`` as a network fault would (its assembler
        reconnects); False when that group is not connected."""
        with self._conn_lock:
            conn = self._conns.get(name)
        if conn is None:
            return False
        shutdown_connection(conn)
        return True

    def _serve(self, conn) -> None:
        """One connection: the key handshake and the hello within HANDSHAKE_TIMEOUT_S, then its
        group's parts until it closes. Whatever a peer sends, nothing is unpickled
        (:mod:`.assembler_wire`); a peer that breaks the protocol is refused (:meth:`_refuse_peer`)."""
        from multiprocessing.connection import AuthenticationError

        name = None
        back = False
        stage = "key"  # -> "hello" -> "parts" (welcomed or refused: the handshake slot given back)
        peer = conn_peer(conn)
        deadline = Deadline(conn, self.handshake_timeout_s)

        def handshake_done():
            nonlocal stage
            if stage != "parts":
                stage = "parts"
                deadline.cancel()
                self._handshakes.release()

        try:
            tune_connection(conn)  # a peer gone without closing is noticed (assembler_parts.KEEPALIVE)
            handshake(conn, self.authkey, server=True)
            stage = "hello"
            hello = decode_hello(recv_frame(conn, HELLO_MAX))
            why = self._check_hello(hello)
            if why is None:
                layout = group_layout(self.scene, hello["channels"])
                codec = PartCodec(self.scene, layout)
                with self._conn_lock:
                    before = self.merger.stats.reconnects.get(layout.name, 0)
                    why = self.merger.add_group(layout)
                    if why is None:
                        name = layout.name
                        self._conns[name] = conn
                        back = self.merger.stats.reconnects.get(name, 0) > before
            handshake_done()
            if why is not None:
                self.refused.append(why)
                self._refuse_peer(conn, "hello", why, answer=True)
                return
            if back:
                self._log.warning(f"back {name}", f"assembler of channel(s) {name} is back (host "
                                  f"{hello['host']}, pid {hello['pid']}; reconnect "
                                  f"{self.merger.stats.reconnects[name]}): its parts merge again")
            conn.send_bytes(encode_welcome(name))
            while not self._stop_merge.is_set():
                part = codec.decode(recv_frame(conn, codec.max_bytes))
                self.merger.add_part(name, part, time.time())
                self._emit()
        except OtherVersion as exc:  # a peer of another version is told why
            self._refuse_peer(conn, "message", f"peer {peer}: {exc}", answer=stage == "hello")
        except BadMessage as exc:
            self._refuse_peer(conn, "message", f"peer {peer}, {stage}: {exc}")
        except AuthenticationError as exc:
            self._refuse_peer(conn, "key", f"peer {peer}: {exc}")
        except (EOFError, OSError) as exc:
            if deadline.expired and stage != "parts":
                self._refuse_peer(conn, "timeout", f"peer {peer}: no hello within {self.handshake_timeout_s:g} s "
                                                   f"of connecting ({stage} stage)")
            elif stage == "key":  # a port scan, a client of no key
                self._refuse_peer(conn, "key", f"peer {peer}: closed in the key handshake ({type(exc).__name__})")
            elif stage == "hello":
                self._refuse_peer(conn, "message", f"peer {peer}: closed without a hello ({type(exc).__name__})")
        except Exception:  # noqa: BLE001 - one bad assembler never stops the fuser
            logger.exception("assembler connection failed")
        finally:
            handshake_done()
            if name is not None:
                with self._conn_lock:
                    if self._conns.get(name) is conn:
                        self.merger.remove_group(name)
                        del self._conns[name]
                if not self._stop_merge.is_set():
                    self._log.warning(f"gone {name}", f"assembler of channel(s) {name} disconnected: its parts "
                                      "are missing until it is back")
                    self._emit()
            try:
                conn.close()
            except OSError:
                pass

    def _check_hello(self, hello: dict) -> str | None:
        """Why a hello (:func:`.assembler_wire.decode_hello`, types checked) is refused; None: welcome."""
        mine = scene_fingerprint(self.scene)
        theirs = hello["scene"]
        if theirs != mine:
            return f"scene differs: assembler {theirs}, fuser {mine}"
        channels = hello["channels"]
        n = len(self.scene.bus.channels)
        if not channels or not all(isinstance(c, int) and 0 <= c < n for c in channels):
            return f"channels {channels!r}: the scene has channels 0..{n - 1}"
        if not self.scene.bus.sync_counter and self.merger.sent and not hello["numbered_from_reset"]:
            return ("the scene has no SYNC counter and this run's SYNCs have begun: an assembler started now "
                    "cannot number its cycles (only one that heard the master's reset can come back)")
        return None


def _wake(listener) -> None:
    """Wakes a thread blocked in ``listener.accept()`` (a connection to it). Never raises."""
    import socket

    host, port = listener.address[:2]
    if host in ("0.0.0.0", "::", ""):
        host = "::1" if ":" in host else "127.0.0.1"
    try:
        socket.create_connection((host, port), timeout=1.0).close()
    except OSError:
        pass


def conn_peer(conn) -> str:
    """``HOST:PORT`` of a connection's peer (``?`` when it is gone). Never raises."""
    import os
    import socket

    try:
        sock = socket.socket(fileno=os.dup(conn.fileno()))
    except (OSError, ValueError):
        return "?"
    try:
        host, port = sock.getpeername()[:2]
        return f"{host}:{port}"
    except OSError:
        return "?"
    finally:
        sock.close()
