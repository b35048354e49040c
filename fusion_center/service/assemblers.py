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
* **Assembler -> fuser: Zenoh** (:mod:`.assembler_link`: keys, sessions, authentication)
  carrying the messages of :mod:`.assembler_wire` (protocol 3: msgpack maps, arrays as raw
  little-endian bytes, every field checked against the scene's group layout on decode;
  nothing received is unpickled, on either side). The fuser's session listens on
  ``--assemblers`` (``HOST:PORT`` = ``tcp/HOST:PORT``, or any Zenoh endpoint such as
  ``tls/...``), an assembler's connects to it; multicast scouting is off and nothing else
  listens unless the user's Zenoh configuration says so. The hello is a query the fuser
  answers (welcome / refused), the parts are reliable puts in order, liveliness tokens tell
  each side the other is gone. Every message is authenticated with the run's key
  (``FUSION_CENTER_AUTHKEY``; without it only loopback endpoints, with a per-run key the fuser
  writes to a file only its user can read, :func:`.assembler_parts.key_file`): a message that
  fails it, is no message of the protocol or is over its size limit is refused - counted
  (``refused`` in the summary, by kind), logged (rate-limited), never decoded or merged; the
  run goes on. (CANopen on an "uplink" bus was the alternative: a 4,096-taxel part is ~29 kB
  per cycle, i.e. segmented transfers and a second master role for no gain.)
* **Merge** (:class:`CycleMerger`): per SYNC the fuser sent, one part per channel group. The
  cycle is ``complete``-able when every group's part arrived; a group whose part has not
  arrived when a later part of that group arrived (parts come in order), when the group
  disconnected, or ``part_deadline_s`` after the SYNC, is *missing*: its taxels count as
  silent (received nothing), the record is degraded and names the group in
  ``parts_missing`` (``closed_by: "part_missing"``). Cycles are evaluated in SYNC order,
  by the fuser's merge thread (woken by each merged part, and every tick for the deadlines) -
  not by Zenoh's callback thread, which takes every link's parts one after the other and only
  checks, decodes and merges them; a part for a cycle already evaluated is counted
  (``late_parts``), never mixed in - but its boot-ups and EMCYs (events, not cycle data) go into
  the next cycle closed, with their t_us (``late_bootups``, ``late_emcy``; at most
  ``EMCY_PER_CYCLE`` EMCYs, the rest in ``emcy_dropped``) when the part is newer than the group's
  last one (a duplicate or replayed part carries nothing); an assembler likewise sends the
  boot-ups and EMCYs of a part it could not send with its next part.
* **Reconnects**: an assembler whose link breaks without the fuser's ``bye`` (the fuser's
  liveliness token gone, or the fuser dropped the link) keeps
  assembling its buses (the parts closed meanwhile are counted as not sent, never queued) and
  connects again (0.1 s doubling to 2 s between tries, for ``--reconnect-timeout`` s; then it
  exits 1). The fuser accepts a group of its run again with the same hello checks (a group that
  is still connected is refused), counts it (``reconnects``) and merges its parts from then on;
  the cycles in between are degraded naming the group (its assembler's liveliness token gone:
  disconnected). A restarted assembler process is
  accepted the same way (its cycles are mapped by the SYNC counter; in a scene without one
  only an assembler that heard the master's reset, i.e. the same process, can come back).

By job: :mod:`.assembler_parts` (what both sides share: keys, channel groups,
:class:`CyclePart`), :mod:`.assembler_process` (the assembler: ``GroupAssembler``,
``AssemblerProcess``), :mod:`.cycle_merger` (the merge) and this module, the fuser
(:class:`AssembledFusionService`), with :mod:`.assembler_wire` (the messages) and
:mod:`.assembler_link` (their keys on Zenoh, their signatures, the sessions); their public
names are importable from here.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict, deque
from dataclasses import replace

from taxel_net.errors import UsageError
from taxel_net.scene import Scene
from . import assembler_link as link_keys
from .assembler_parts import (AUTHKEY_ENV, COB_SYNC, NMT_RESETS, CyclePart,  # noqa: F401
                              GroupLayout, RateLimitedLog, authkey_for, check_serve, group_layout, group_name,
                              is_loopback, remove_key_file, scene_fingerprint, write_key_file)
from .assembler_wire import (HELLO_MAX, PROTOCOL, BadMessage, OtherVersion, PartCodec,  # noqa: F401
                             decode_hello, encode_bye, encode_refused, encode_welcome)
from .assembler_process import AssemblerProcess, GroupAssembler  # noqa: F401 - public names of this module
from .cycle_merger import CycleMerger, MergeStats  # noqa: F401
from .cycle_records import ClosedCycle, quantise_timestamp
from .fusion_service import FusionService
from .stream import EventStream
from .zenoh_config import endpoint, endpoint_host

logger = logging.getLogger("fusion_center.service.assemblers")

LINKS_REMEMBERED = 256  # links the fuser dropped or saw gone (their late messages are answered once)

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

    def transmit_fed_first(self, channel: int, can_id: int, data: bytes) -> None:
        """A one-channel network's SYNC (the SYNC producer's way, :class:`EventStream`): noted too."""
        if self.on_sync is not None and channel == 0 and can_id == COB_SYNC:
            self.on_sync(bytes(data))
        super().transmit_fed_first(channel, can_id, data)


class _Link:
    """One welcomed assembler: its group, codec and keys."""

    __slots__ = ("id", "name", "codec", "part_key", "to_key", "host", "pid")

    def __init__(self, link_id, name, codec, prefix, host, pid):
        self.id = link_id
        self.name = name
        self.codec = codec
        self.part_key = link_keys.part_key(prefix, link_id)
        self.to_key = link_keys.to_link_key(prefix, link_id)
        self.host = host
        self.pid = pid


OWN_DRIVE_KEPT = 64  # the fuser's own drive snapshots kept for merged cycles (cycles)


class AssembledFusionService(FusionService):
    """The fuser: the CANopen master of :class:`FusionService` on every channel, its cycles
    assembled by ``fusion-center assemble`` processes (module docstring).

    ``listen``: the Zenoh endpoint the link's session listens on (``tcp/127.0.0.1:47400``,
    ``tls/...``; ``HOST:PORT`` or a (host, port) pair mean tcp); ``zenoh_config``: a Zenoh
    configuration file for that session (:mod:`.zenoh_config`; TLS, authentication);
    ``authkey``: the shared key (None: ``$FUSION_CENTER_AUTHKEY``, else on a loopback endpoint
    a per-run key written to :func:`.assembler_parts.key_file` at :meth:`open`). :meth:`boot`
    waits up to ``assembler_wait_s`` for assemblers covering every scene channel. The
    service's own ``CycleAssembler`` still runs (boot-ups, SDO answers, NMT states for the
    master), its closed cycles are not evaluated.

    ``pdo_filter`` (off by default): the fuser's buses accept only the master's traffic
    (:data:`MASTER_FILTERS`; kernel filters on SocketCAN). Only for scenes without a synchronous
    window: with one, the own assembler would hold SYNC k+1 until SYNC k+2 (no node frame after
    the window closes k), and with it an SDO request of a mid-run reconfiguration - whose answer
    would then arrive unsolicited (not handed to the SDO client). Measured on udp_multicast it
    saved nothing (python-can filters after parsing every datagram)."""

    def __init__(self, scene: Scene, *, listen, authkey: bytes | None = None, zenoh_config: str | None = None,
                 part_deadline_s: float | None = None, assembler_wait_s: float = 30.0,
                 pdo_filter: bool = False, **kwargs):
        super().__init__(scene, **kwargs)
        self.pdo_filter = bool(pdo_filter)
        if isinstance(listen, tuple):
            host, port = listen
            listen = f"tcp/[{host}]:{port}" if ":" in host else f"tcp/{host}:{port}"
        self.listen_address = endpoint(listen, "--assemblers")
        self.zenoh_config = zenoh_config
        self.authkey = authkey if authkey is not None else authkey_for(endpoint_host(self.listen_address),
                                                                       "--assemblers")
        self._key_file: str | None = None  # the per-run key's file (loopback without the variable)
        self._mac_key: bytes | None = None
        period = scene.bus.sync_period_ms / 1000.0
        # an assembler without a window closes a cycle with a silent node at the next SYNC
        self.part_deadline_s = part_deadline_s if part_deadline_s is not None else 2.5 * period + 0.1
        self.assembler_wait_s = assembler_wait_s
        self.merger = CycleMerger(scene, part_deadline_s=self.part_deadline_s)
        self.own_closed = 0
        # the gripper drive as the fuser's own assembler knew it at each cycle's close (its
        # frames are heard by the master on its bus; the assemblers' parts carry taxels only):
        # cycle -> (SYNC counter, DriveCycle), the latest few
        self._own_drive: OrderedDict[int, tuple] = OrderedDict()
        self._own_drive_lock = threading.Lock()
        echoes = self.stream.echoes
        self.stream = _FuserStream(self.assembler, on_closed=self._own_cycle, after_closed=self._process_pending)
        self.stream.echoes = echoes
        self.stream.on_sync = self._on_sync
        self.prefix = link_keys.prefix(scene.name)
        self.run_id = link_keys.new_id()
        self._session = None
        self._declared: list = []
        self._links: dict[str, _Link] = {}        # link id -> welcomed link
        self._gone: OrderedDict[str, bool] = OrderedDict()  # link ids dropped / gone (told once)
        self._conn_lock = threading.Lock()  # a group's link and its place in the merger change together
        self._part_lock = threading.Lock()  # one part decoded and merged at a time
        self._log = RateLimitedLog(logger)
        self._threads: list[threading.Thread] = []
        self._stop_merge = threading.Event()
        self._merge_wake = threading.Event()  # a part merged: the merge thread emits (_tick_loop)
        self._merge_lock = threading.Lock()  # emission order into _pending
        self.refused: deque[str] = deque(maxlen=8)  # the latest reasons hellos were refused

    # -- life cycle
    def open(self) -> "AssembledFusionService":
        import zenoh

        from .zenoh_config import open_session

        config, what = link_keys.fuser_config(self.listen_address, self.zenoh_config)
        super().open()
        try:
            if self.pdo_filter:  # the PDOs are the assemblers' (kernel filters on SocketCAN, else python-can's)
                for bus in self.buses:
                    bus.set_filters(MASTER_FILTERS)
            if self.authkey is None:  # loopback without FUSION_CENTER_AUTHKEY: this run's own key
                port = int(self.listen_address.split("?")[0].rpartition(":")[2])
                self.authkey, self._key_file = write_key_file(port)
            self._mac_key = link_keys.mac_key(self.authkey)
            self._session = open_session(config, f"--assemblers {self.listen_address}")
            p = self.prefix
            s = self._session
            self._declared = [
                s.liveliness().declare_token(link_keys.fuser_key(p, self.run_id)),
                s.declare_queryable(link_keys.hello_key(p), self._on_hello),
                s.declare_subscriber(f"{p}/*/part", self._on_part),
                s.liveliness().declare_subscriber(f"{p}/*/alive", self._on_alive),
            ]
            self._reply_options = {}
            self._tell_options = dict(congestion_control=zenoh.CongestionControl.BLOCK, express=True,
                                      priority=zenoh.Priority.REAL_TIME)
        except BaseException:
            self.close()
            raise
        thread = threading.Thread(target=self._tick_loop, name="merge-deadline", daemon=True)
        thread.start()
        self._threads.append(thread)
        return self

    def close(self) -> None:
        self._stop_merge.set()
        self._merge_wake.set()
        with self._conn_lock:
            links = list(self._links.values())
            self._links.clear()
        if self._session is not None:
            for link in links:  # (each assembler answers at once: 1 s for one that does not)
                self._tell(link.id, encode_bye(), wait_s=1.0)
            for entity in reversed(self._declared):
                try:
                    entity.undeclare()
                except Exception:  # noqa: BLE001 - closing anyway
                    pass
            self._declared = []
            try:
                self._session.close()
            except Exception:  # noqa: BLE001
                pass
            self._session = None
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
                where = self.listen_address
                why = f" (refused: {'; '.join(self.refused)})" if self.refused else ""
                raise UsageError(f"--assemblers {where}: no assembler for scene channel(s) {lacking} after "
                                 f"{timeout_s:g} s: start `fusion-center assemble --scene ... --serve "
                                 f"{group_name(lacking)} --fuser {where}`{why}")
            time.sleep(0.02)

    def _critical_threads(self) -> list[threading.Thread]:
        """The plain centre's (receive, SYNC producer, heartbeat) and the merge thread, which
        evaluates the merged cycles and sends the grip command here (Zenoh's callback threads,
        which take the parts, are the SDK's and keep the normal priority)."""
        threads = super()._critical_threads()
        threads.extend(t for t in self._threads if t.name == "merge-deadline")
        return threads

    def run(self, cycles: int, *, before_sync=None, timeout_s: float | None = None):
        if cycles < 1:
            raise UsageError(f"--cycles {cycles}: must be >= 1")
        period = self.scene.bus.sync_period_ms / 1000.0
        self._start_sync(cycles, before_sync)  # --rt-priority too (it was ignored here without a word)
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
        if closed.drive is not None:
            with self._own_drive_lock:
                self._own_drive[closed.cycle] = (closed.sync_counter, closed.drive)
                while len(self._own_drive) > OWN_DRIVE_KEPT:
                    self._own_drive.popitem(last=False)

    def _drive_of(self, closed: ClosedCycle):
        """The drive of a merged cycle: the fuser's own snapshot at the close of the same SYNC
        (the same counter where both have one), else the latest before it - a cycle whose parts
        came before the master's own close of it sees the drive as of the cycle before (never a
        later one's, and never a snapshot taken here, which would take that cycle's EMCYs)."""
        with self._own_drive_lock:
            own = self._own_drive.get(closed.cycle)
            if own is not None and (own[0] is None or closed.sync_counter is None or own[0] == closed.sync_counter):
                del self._own_drive[closed.cycle]
                return own[1]
            # (kept in the order the cycles closed: the first from the end before this one)
            return next((drive for cycle, (_, drive) in reversed(self._own_drive.items()) if cycle < closed.cycle),
                        None)

    def evaluate_command(self, closed: ClosedCycle):
        if self.drive is not None and closed.drive is None:
            closed = replace(closed, drive=self._drive_of(closed))
        return super().evaluate_command(closed)

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

    def _wake_merge(self) -> None:
        """A part merged or a group gone (a Zenoh callback): the merge thread emits and evaluates."""
        self._merge_wake.set()

    def _tick_loop(self) -> None:
        """The merge thread: emits the cycles a part completed (woken by :meth:`_wake_merge`) or
        whose deadline passed (every tick), and evaluates them. Not in Zenoh's callback thread,
        which takes every link's parts one after the other: a cycle evaluated there held the
        other group's part behind it (at skin4096 on a loaded host, 10 ms at p90 and 29 ms at
        p99 a part - parts came late and their cycles were degraded)."""
        tick = max(0.002, min(0.02, self.part_deadline_s / 4))
        wake = self._merge_wake
        while not self._stop_merge.is_set():
            wake.wait(tick)
            wake.clear()  # before the emit: a part merged after this wakes the next turn
            if self._stop_merge.is_set():
                return
            try:
                self._emit()
            except Exception:  # noqa: BLE001 - the merge thread never dies
                logger.exception("merge tick failed")

    def finish_record(self, pending) -> dict:
        record = super().finish_record(pending)
        info = self.merger.info.pop(pending.closed.cycle, None)
        record["parts_missing"] = info["parts_missing"] if info else []
        return record

    # -- the link (Zenoh callbacks: they never raise)
    def _refuse(self, kind: str, why: str) -> None:
        """A message refused (``kind``: key, message, hello, link): counted in the summary,
        logged (at most one line of a kind every 10 s)."""
        self.merger.count_refused(kind)
        self._log.warning(f"refused {kind}", f"assembler message refused ({kind}): {why}")

    def _tell(self, link_id: str, message: bytes, wait_s: float = 0.0) -> None:
        """A signed message to one assembler (``bye``, ``refused``): a query on its key, which
        it answers once it has the message; ``wait_s`` > 0: wait that long at most for the
        answer (the bye at the end: a session closed right after a put may not send it). Never
        raises."""
        key = link_keys.to_link_key(self.prefix, link_id)
        try:
            replies = self._session.get(key, payload=message, attachment=link_keys.mac(self._mac_key, key, message),
                                        timeout=max(wait_s, 1.0), **self._tell_options)
            if wait_s > 0:
                for _ in replies:
                    break
        except Exception as exc:  # noqa: BLE001 - a closed session
            logger.debug("message to link %s not sent: %s", link_id, exc)

    def _forget(self, link_id: str) -> None:
        self._gone[link_id] = False
        while len(self._gone) > LINKS_REMEMBERED:
            self._gone.popitem(last=False)

    def drop_assembler(self, name: str) -> bool:
        """Drop the link of group ``name`` as a network fault would (its assembler is told, and
        says hello again); False when that group is not connected."""
        with self._conn_lock:
            link = next((lk for lk in self._links.values() if lk.name == name), None)
            if link is None:
                return False
            del self._links[link.id]
            self._forget(link.id)
            self.merger.remove_group(name)
        self._tell(link.id, encode_refused("the fuser dropped this link: say hello again"))
        self._log.warning(f"gone {name}", f"assembler of channel(s) {name} dropped: its parts are missing until "
                                          "it is back")
        self._emit()
        return True

    def _on_hello(self, query) -> None:
        try:
            self._hello(query)
        except Exception:  # noqa: BLE001 - one bad peer never stops the fuser
            logger.exception("assembler hello failed")

    def _hello(self, query) -> None:
        """A hello (the query's payload): authenticated, decoded, checked, answered."""
        payload = link_keys.as_bytes(query.payload)
        key = link_keys.hello_key(self.prefix)
        if payload is None or len(payload) > HELLO_MAX:
            self._refuse("message", f"hello: {'no payload' if payload is None else f'{len(payload)} bytes'} "
                                    f"(at most {HELLO_MAX})")
            return
        ident = link_keys.split_id(link_keys.as_bytes(query.attachment))
        if ident is None or not link_keys.verify(self._mac_key, key, payload, ident[1], ident[0].encode()):
            self._refuse("key", "hello: not signed with this run's key (another run's assembler, or a stray peer)")
            return
        link_id, hello_mac = ident

        def answer(message: bytes) -> None:
            bound = hello_mac + self.run_id.encode()
            query.reply(key, message, attachment=self.run_id.encode() + link_keys.mac(self._mac_key, key, message,
                                                                                        bound),
                        **self._reply_options)

        try:
            hello = decode_hello(payload)
        except OtherVersion as exc:  # a peer of another version is told why
            self._refuse("message", f"link {link_id[:8]}: {exc}")
            answer(encode_refused(str(exc)))
            return
        except BadMessage as exc:
            self._refuse("message", f"link {link_id[:8]}, hello: {exc}")
            return
        why = self._check_hello(hello)
        name = None
        back = False
        if why is None:
            layout = group_layout(self.scene, hello["channels"])
            codec = PartCodec(self.scene, layout)
            with self._conn_lock:
                if link_id in self._gone or link_id in self._links:
                    why = "this link was used before: say hello with a new one"
                else:
                    before = self.merger.stats.reconnects.get(layout.name, 0)
                    why = self.merger.add_group(layout)
                    if why is None:
                        name = layout.name
                        self._links[link_id] = _Link(link_id, name, codec, self.prefix, hello["host"], hello["pid"])
                        back = self.merger.stats.reconnects.get(name, 0) > before
        if why is not None:
            self.refused.append(why)
            self._refuse("hello", why)
            answer(encode_refused(why))
            return
        if back:
            self._log.warning(f"back {name}", f"assembler of channel(s) {name} is back (host {hello['host']}, pid "
                                              f"{hello['pid']}; reconnect {self.merger.stats.reconnects[name]}): its "
                                              "parts merge again")
        answer(encode_welcome(name))

    def _on_part(self, sample) -> None:
        try:
            self._part(sample)
        except Exception:  # noqa: BLE001 - one bad assembler never stops the fuser
            logger.exception("assembler part failed")

    def _part(self, sample) -> None:
        received_at = time.time()
        key = str(sample.key_expr)
        link_id = link_keys.link_of(key)
        payload = sample.payload.to_bytes()
        link = self._links.get(link_id) if link_id is not None else None
        limit = link.codec.max_bytes if link is not None else HELLO_MAX
        if len(payload) > limit:
            self._refuse("message", f"part on {key}: {len(payload)} bytes, over its limit of {limit}")
            if link is not None:
                self._drop_link(link, f"a part over its size limit ({len(payload)} bytes)")
            return
        if not link_keys.verify(self._mac_key, key, payload, link_keys.as_bytes(sample.attachment)):
            self._refuse("key", f"part on {key}: not signed with this run's key")
            return
        if link is None:
            if link_id is not None and not self._gone.get(link_id):
                self._refuse("link", f"part of link {link_id[:8]}, which is not welcomed here (dropped, or an "
                                     "earlier fuser's): told to say hello again")
                self._gone[link_id] = True
                self._tell(link_id, encode_refused("no such link at this fuser: say hello again"))
            return
        with self._part_lock:
            try:
                part = link.codec.decode(payload)
            except BadMessage as exc:
                self._refuse("message", f"link {link.id[:8]} (channels {link.name}), part: {exc}")
                self._drop_link(link, str(exc))
                return
            if self._links.get(link.id) is not link:  # dropped meanwhile
                return
            self.merger.add_part(link.name, part, received_at)
        self._wake_merge()

    def _drop_link(self, link: _Link, why: str) -> None:
        """A link whose part broke the protocol: dropped as a disconnected group, told."""
        with self._conn_lock:
            if self._links.pop(link.id, None) is None:
                return
            self._forget(link.id)
            self.merger.remove_group(link.name)
        self._tell(link.id, encode_refused(f"the fuser dropped this link: {why}"[:900]))
        self._wake_merge()

    def _on_alive(self, sample) -> None:
        """An assembler's liveliness token: gone = that group disconnected."""
        try:
            import zenoh

            if sample.kind != zenoh.SampleKind.DELETE:
                return
            link_id = link_keys.link_of(str(sample.key_expr))
            with self._conn_lock:
                if link_id is None:
                    return
                link = self._links.pop(link_id, None)
                self._forget(link_id)
                if link is None:
                    return
                self.merger.remove_group(link.name)
            if not self._stop_merge.is_set():
                self._log.warning(f"gone {link.name}", f"assembler of channel(s) {link.name} disconnected (host "
                                                       f"{link.host}, pid {link.pid}): its parts are missing "
                                                       "until it is back")
                self._wake_merge()
        except Exception:  # noqa: BLE001
            logger.exception("assembler liveliness failed")

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
