"""The centre's side of the robotics bridge (``--zenoh`` / ``--foxglove`` on ``run`` and ``demo``;
docs/robotics.md, *The bridge process*): :class:`RoboticsBridge` starts
the bridge process (:mod:`.bridge`; nothing imported from the current directory) beside the centre and hands it each
cycle as one frame; Zenoh's and the Foxglove server's threads run in that process, not in the
centre's.

**The link**: an ``AF_UNIX`` ``SOCK_SEQPACKET`` socket pair made here; the bridge gets its end as
an inherited descriptor (``pass_fds``, no other descriptor of the centre), the centre keeps the
other. Its settings go as one JSON argument on the command line (nothing is pickled). The bridge
says ``{"ready": {...}}`` or ``{"error": "one line"}`` on its stdout before the run starts (a
bounded wait, :data:`READY_TIMEOUT_S`): an error is this process's :class:`UsageError` (exit 2).

**A frame** (one datagram: the kernel delivers it whole or not at all): a 20-byte header
``<4sIIIBB2x`` (``b"TXB3"``, the record's length, the number of readings, the cycles left out
before it, the contact events' baseline - :data:`BASELINE_CODES` - and the record's encoding),
the record, then in raw mode the readings the taxel map needs
(:meth:`.topics.TopicMap.readings_of`) as little-endian float64. The record is its decision-log
line where the run has just written it (``--json-lines``: :func:`~fusion_center.service.records.made_line`,
no work; encoding :data:`ENC_JSON`), else a msgpack map of it (:data:`ENC_MSGPACK`; ``strict_types``:
only dict, list, str, int, float, bool and None, each of its exact type - what the record's
JSON line is made of) - half the CPU of making the JSON line (4.8-9 against 9-16 us a record in
a loop, ~70 of the hand-over's ~110 us at matrix57 in place) - and the bridge makes the line
(:func:`~fusion_center.service.records.dumpb`, the same bytes: a msgpack round trip keeps every
such value, -0.0 and int / float apart included) only where a Zenoh subscriber wants records. A
record of other types (a tuple, a numpy scalar) goes as its JSON line. The bridge reads the JSON
with :mod:`json` and msgpack with ``msgpack.unpackb`` (ext types refused - msgpack's own timestamp,
ext -1, too: ``unpackb`` reads it as a ``msgpack.Timestamp`` without asking ``ext_hook``, so a record
holding one is refused after it, the frame counted ``bad`` as any other; map keys of any plain type,
as the packer takes them) - nothing from the link is unpickled or executed.

**The cycle never waits**: the centre's end is non-blocking and a datagram is sent whole or not
at all (no partial frame, no pending buffer): when the socket's buffer is full (a bridge behind -
a slow viewer, a stalled Zenoh subscriber, a starved process) the cycle's frame is dropped and
counted (:attr:`RoboticsBridge.dropped`, logged rate-limited). A frame larger than the socket
can hold is counted apart (``too_large``). A bridge that ends mid-run (killed) is logged once;
the frames after it are counted (``lost``), the run goes on.

**Nobody watching, nothing made**: the bridge keeps a one-byte flag in a shared page (a
``memfd`` the centre makes and passes with the link; 1 or 0, set at each change) saying whether
anything wants the cycles - a Zenoh subscriber matching any of the keys, a Foxglove viewer
subscribed to any channel. While nothing does, the centre makes no frame (the cycle costs a
read of that byte and a ``waitpid`` to see the bridge still runs) and counts the cycle
``unwanted`` (a non-blocking ``recv`` on the link for the same word cost 30-40 us a cycle); these count
as ``with no subscriber`` / ``with none subscribed`` in the summary, as in process. The next
frame's header says how many cycles were left out before it and the decision the bridge's
contact events compare the record with (its *baseline*): after cycles nobody wanted, the
decision of the cycle before (what the in-process publisher, which sees every record, compares
with: a subscriber that joins gets the changes from then on); after dropped frames (a subscriber
watching, the bridge behind) the last decision handed over - a change whose frame was dropped
reaches the subscriber with the next frame, one cycle or more late, never lost
(``tests/test_robotics_bridge.py``).

**Lifecycle**: the bridge runs in a session of its own (``start_new_session``: a Ctrl-C on the
terminal reaches the centre only, which finishes its last records and then closes the link) and
ignores SIGINT; it ends when the link closes - at :meth:`RoboticsBridge.close`, or when the
centre ends in any way (killed: the kernel closes its end) - and prints its counters as one JSON
line, which :meth:`close` returns with the link's own. On Linux it also dies with the centre while it
is still starting (before it reads the link): ``--parent-pid`` asks it for the parent-death signal
(:func:`.bridge.die_with_parent`) - only when :meth:`RoboticsBridge.open` runs on the main thread, as
the signal follows the thread that started the bridge.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import mmap
import os
import selectors
import socket
import struct
import subprocess
import sys
import threading
import time

import msgpack
import numpy as np

from taxel_net.errors import UsageError

logger = logging.getLogger("fusion_center.robotics.bridge")

MAGIC = b"TXB3"
HEADER = struct.Struct("<4sIIIBB2x")
ENC_JSON, ENC_MSGPACK = 0, 1  # the header's encoding byte: the record as its JSON line, or a msgpack map
# the header's baseline byte: the decision the bridge's contact events compare the frame's record
# with (``zenoh_publisher``'s ``previous``); FIRST: no record before it (the run's first: an
# event of its own); OTHER: a decision not listed (the record's own becomes the baseline)
BASELINE_CODES = {"H0": 0, "H1": 1, "undecided": 2, None: 3}
BASELINE_OF = {code: decision for decision, code in BASELINE_CODES.items()}
FIRST, OTHER = 0xFE, 0xFF
READY_TIMEOUT_S = 60.0   # the bridge's start (imports, Zenoh session, server): a bound, not a budget
CLOSE_TIMEOUT_S = 60.0   # the bridge's end (what it has queued published, outputs closed)
SNDBUF = 1 << 20         # the link's buffer asked of the kernel (it doubles it, capped at net.core.wmem_max x 2):
# ~1,300 matrix57 frames (~13 s of cycles) where wmem_max allows; at Linux's default 212992 (425984 doubled)
# 185 frames of 1.5 kB (matrix57, 1.8 s), 12 of skin4096 raw mode's 34.7 kB (0.12 s) - measured


# the directory this process imported fusion_center from, and the bridge's entry point (``-c``: no
# current directory on sys.path but the '' that -c adds, removed here before anything is imported)
_CODE_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
_BRIDGE_MAIN = ("import sys; root = sys.argv.pop(1); sys.path[:] = [root] + [p for p in sys.path if p != '']; "
                "from fusion_center.robotics.bridge import main; sys.exit(main())")


def scene_digest(scene) -> str:
    """A fingerprint of a scene (the bridge checks it loaded the centre's scene)."""
    return hashlib.sha256(repr(scene).encode()).hexdigest()[:16]


def baseline_code(decision) -> int:
    """The header's baseline byte of a decision (:data:`BASELINE_CODES`, else :data:`OTHER`)."""
    try:
        return BASELINE_CODES.get(decision, OTHER)
    except TypeError:  # unhashable: a hand-made record
        return OTHER


def make_frame(payload: bytes, readings, gap: int = 0, baseline: int = FIRST, encoding: int = ENC_JSON) -> bytes:
    """One frame: header, the record (its JSON line, or with ``encoding`` :data:`ENC_MSGPACK` a
    msgpack map), the readings (float64, or none); ``gap``: the cycles left out before it;
    ``baseline``: the contact events' baseline (:func:`baseline_code`, :data:`FIRST`)."""
    gap = min(gap, 0xFFFFFFFF)
    if readings is None:
        return HEADER.pack(MAGIC, len(payload), 0, gap, baseline, encoding) + payload
    data = np.ascontiguousarray(readings, dtype="<f8")
    return b"".join((HEADER.pack(MAGIC, len(payload), data.size, gap, baseline, encoding), payload, data.tobytes()))


def _no_ext(code, data):
    raise ValueError(f"msgpack ext type {code}")


# the bytes before a msgpack timestamp's type byte 0xff (ext -1, which ``unpackb`` reads as a
# ``msgpack.Timestamp`` without asking ext_hook, whatever its ``timestamp=`` option - 0 to 3 all
# accept it): fixext 4 (0xd6), fixext 8 (0xd7), or ext 8 / 16 / 32 whose length ends in 4, 8 or 12
# (its only valid lengths: any other, unpackb raises ValueError)
_TIMESTAMP_LEAD = frozenset((0xD6, 0xD7, 4, 8, 12))


def _may_hold_timestamp(payload: bytes) -> bool:
    """Whether a msgpack payload may hold a timestamp: a byte 0xff after one of
    :data:`_TIMESTAMP_LEAD` - never false for one that does; a record's floats make it true at
    times, which only costs :func:`_holds_timestamp`'s walk (0xff is rare in a record: memchr)."""
    i = payload.find(b"\xff", 1)
    while i > 0:
        if payload[i - 1] in _TIMESTAMP_LEAD:
            return True
        i = payload.find(b"\xff", i + 1)
    return False


def _holds_timestamp(value) -> bool:
    """Whether a decoded msgpack value holds a ``msgpack.Timestamp`` (a value or a map key, at any
    depth: a loop, not recursion - unpackb nests up to 1024 levels, deeper than Python's recursion)."""
    stack = [value]
    while stack:
        value = stack.pop()
        kind = type(value)
        if kind is msgpack.Timestamp:
            return True
        if kind is dict:
            stack.extend(value)
            stack.extend(value.values())
        elif kind is list:
            stack.extend(value)
    return False


def frame_gap(frame) -> tuple[int, int]:
    """The cycles left out before a (parsed) frame and its baseline byte."""
    return HEADER.unpack_from(frame)[3:5]


def parse_frame(frame) -> tuple[dict, bytes | None, np.ndarray | None]:
    """``(record, line, readings)`` of a frame (``line`` None for a msgpack record: the caller
    makes it where wanted); ValueError (one line) for anything else."""
    if len(frame) < HEADER.size:
        raise ValueError(f"a frame of {len(frame)} bytes (the header alone is {HEADER.size})")
    magic, n_json, n_readings, _, _, encoding = HEADER.unpack_from(frame)
    if magic != MAGIC:
        raise ValueError(f"a frame that does not start with {MAGIC!r}")
    if len(frame) != HEADER.size + n_json + 8 * n_readings:
        raise ValueError(f"a frame of {len(frame)} bytes, its header says {HEADER.size + n_json + 8 * n_readings}")
    payload = bytes(frame[HEADER.size:HEADER.size + n_json])
    if encoding == ENC_JSON:
        line = payload
        try:
            record = json.loads(line)
        except RecursionError:  # nested deeper than the interpreter's recursion limit: a bad frame, not the end
            raise ValueError("a frame whose JSON record is nested too deep to read") from None
    elif encoding == ENC_MSGPACK:
        line = None
        try:
            # strict_map_key off: the centre's packer takes a key of any plain type (int, bool, None,
            # float) as JSON does - refused here, the whole frame was lost; dumpb writes such a key as
            # the decision log does. An array key cannot be hashed: TypeError, refused below.
            record = msgpack.unpackb(payload, raw=False, ext_hook=_no_ext, strict_map_key=False)
        except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as exc:
            raise ValueError(f"a frame whose msgpack record cannot be read: {type(exc).__name__}") from None
        # msgpack's own timestamp (ext -1) bypasses ext_hook: refused here as any other ext type - no
        # record holds one (the centre's strict packer makes none), and dumpb and the encoders cannot
        if _may_hold_timestamp(payload) and _holds_timestamp(record):
            raise ValueError("a frame whose msgpack record holds a msgpack timestamp (ext type -1)")
    else:
        raise ValueError(f"a frame of encoding {encoding} (known: {ENC_JSON} JSON, {ENC_MSGPACK} msgpack)")
    if not isinstance(record, dict):
        raise ValueError("a frame whose record is no object")
    readings = None
    if n_readings:
        readings = np.frombuffer(frame, dtype="<f8", count=n_readings, offset=HEADER.size + n_json).astype(float)
    return record, line, readings


class RoboticsBridge:
    """Starts the bridge process and hands it every cycle (module docstring).

    ``scene``: the run's scene; ``source``: how the bridge loads the same scene -
    ``{"scene": FILE_OR_NAME, "mode": None | "decision" | "raw", "slow_down": 1.0}`` (checked
    against ``scene``'s fingerprint); ``zenoh``: None or the ``--zenoh-*`` settings
    ``{"config_file", "listen", "connect", "mode"}``; ``foxglove``: None or ``(host, port)``.
    :meth:`open` starts it (UsageError: one line), :meth:`attach` feeds it a ``FusionService``'s
    cycles, :meth:`close` ends it and returns the figures."""

    def __init__(self, scene, source: dict, *, zenoh: dict | None = None, foxglove=None):
        from .topics import TopicMap

        self.scene = scene
        self.settings = {"source": dict(source), "digest": scene_digest(scene), "zenoh": zenoh,
                         "foxglove": list(foxglove) if foxglove is not None else None}
        # the taxel map's readings: only the live server draws them (raw mode)
        self.topics = TopicMap(scene) if foxglove is not None else None
        self.raw = self.topics is not None and self.topics.raw_mode
        self.proc = None
        self.sock = None
        self.ready: dict = {}
        self.frames = 0       # frames handed over
        self.dropped = 0      # frames dropped: the link's buffer full (the bridge behind)
        self.too_large = 0    # frames larger than the link can hold
        self.lost = 0         # frames after the bridge ended
        self.failed = 0       # records that could not be made a frame
        self.unwanted = 0     # cycles nobody wanted (the bridge said so): no frame made
        self._flag = None     # the shared page whose first byte the bridge sets (1: wanted)
        self._gap = 0         # cycles left out since the last frame
        self._baseline = FIRST  # the contact events' baseline for the next frame (module docstring)
        self.died: str | None = None
        self._timed_out = False  # the last _read_line waited its whole bound
        from ..service.records import dumpb, made_line

        self._made_line, self._dumpb = made_line, dumpb
        # a Packer is not thread-safe: on_cycle runs one call at a time (FusionService: under its evaluation
        # lock, from the merge thread or the main thread with --assemblers; replay: one thread)
        self._packb = msgpack.Packer(use_bin_type=True, strict_types=True).pack

    @property
    def wanted(self) -> bool:
        """The bridge's word: whether anything wants the cycles now."""
        return self._flag is None or self._flag[0] != 0

    def command(self) -> list[str]:
        """The bridge's command line: this interpreter, importing ``fusion_center`` from where this
        process did - never from the current directory (``python -m`` would put it first on
        ``sys.path``: a ``json.py`` or ``zenoh.py`` there would run in the bridge)."""
        argv = [sys.executable, "-c", _BRIDGE_MAIN, _CODE_ROOT, "--fd", "{fd}", "--flag-fd", "{flag}",
                "--settings", json.dumps(self.settings)]
        # the bridge dies with the centre (its parent-death signal) - which follows the thread that starts it:
        # asked for from the main thread only (from another, the bridge would die when that thread ends)
        if threading.current_thread() is threading.main_thread():
            argv += ["--parent-pid", str(os.getpid())]
        else:
            logger.debug("robotics bridge started from thread %s: no parent-death signal (the link's end ends it)",
                         threading.current_thread().name)
        return argv

    def open(self) -> "RoboticsBridge":
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        flag_fd = os.memfd_create("taxel-bridge-wanted")
        try:
            os.ftruncate(flag_fd, mmap.PAGESIZE)
            self._flag = mmap.mmap(flag_fd, mmap.PAGESIZE)
            self._flag[0] = 1  # wanted until the bridge says otherwise
            ours.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SNDBUF)
            argv = [a.replace("{fd}", str(theirs.fileno())).replace("{flag}", str(flag_fd)) for a in self.command()]
            self.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                         pass_fds=(theirs.fileno(), flag_fd), start_new_session=True)
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()  # the bridge's end lives in the bridge only
            os.close(flag_fd)
        ours.setblocking(False)
        self.sock = ours
        try:
            message = self._read_line(READY_TIMEOUT_S)
        except BaseException:
            self._kill()
            raise
        if message is None or "ready" not in message:
            error = (message or {}).get("error") if isinstance(message, dict) else None
            hung = self._timed_out
            status = self._kill()
            if error:
                raise UsageError(str(error))
            if hung:  # no line within the bound: stopped here
                raise UsageError(f"the robotics bridge gave no ready answer (waited up to {READY_TIMEOUT_S:g} s; "
                                 "stopped it; its log above)")
            raise UsageError(f"the robotics bridge ended before it was ready (exit status {status}; its log above)")
        self.ready = message["ready"]
        return self

    def _read_line(self, timeout: float):
        """The bridge's next JSON line on its stdout (None: it ended or said nothing within ``timeout``)."""
        out = self.proc.stdout
        fd = out.fileno()
        data = b""
        end = time.monotonic() + timeout
        self._timed_out = False
        with selectors.DefaultSelector() as sel:
            sel.register(fd, selectors.EVENT_READ)
            while b"\n" not in data:
                left = end - time.monotonic()
                if left <= 0 or not sel.select(left):
                    self._timed_out = True
                    return None
                chunk = os.read(fd, 65536)
                if not chunk:
                    return None
                data += chunk
        try:
            message = json.loads(data.split(b"\n", 1)[0])
        except ValueError:
            return None
        return message if isinstance(message, dict) else None

    def attach(self, service) -> None:
        """Hand over every cycle of ``service`` (a ``FusionService``)."""
        service.on_cycle.append(self.on_cycle)

    def on_cycle(self, record: dict, closed=None) -> None:
        """The record callback: one non-blocking send; never raises, never waits."""
        sock = self.sock
        if sock is None:
            return
        if self.died is not None:
            self.lost += 1
            return
        if not self._flag[0]:  # nothing wants the cycles (the bridge's word)
            if self.proc.poll() is not None:
                self._gone(record, "it exited")
                return
            self.unwanted += 1
            self._gap += 1
            self._baseline = baseline_code(record.get("decision"))  # as the in-process publisher tracks it
            return
        try:
            payload, encoding = self._made_line(record), ENC_JSON  # the decision log's line: no work
            if payload is None:
                try:
                    payload, encoding = self._packb(record), ENC_MSGPACK
                except (TypeError, ValueError, OverflowError):  # a tuple, a numpy scalar: its JSON line
                    payload = self._dumpb(record)
            frame = make_frame(payload, self.topics.readings_of(closed) if self.raw else None, self._gap,
                               self._baseline, encoding)
        except Exception as exc:  # noqa: BLE001 - a record neither msgpack nor JSON holds (a set, a cycle);
            # NaN, infinity and bytes go as msgpack: the bridge's dumpb refuses them (its zenoh ``failed``)
            self.failed += 1
            self._gap += 1
            if self.failed == 1 or self.failed % 1000 == 0:
                logger.warning("robotics bridge: %d record(s) not handed over, the last: %s: %s", self.failed,
                               type(exc).__name__, exc)
            return
        try:
            sock.send(frame)
            self.frames += 1
            self._gap = 0
            self._baseline = baseline_code(record.get("decision"))
        except BlockingIOError:
            self.dropped += 1
            self._gap += 1  # the bridge learns of it with the next frame (contact events' baseline)
            if self.dropped == 1 or self.dropped % 1000 == 0:
                logger.warning("robotics bridge behind: %d cycle(s) dropped at the hand-over so far (cycle %s)",
                               self.dropped, record.get("cycle"))
        except OSError as exc:
            if exc.errno == errno.EMSGSIZE:
                self.too_large += 1
                self._gap += 1
                if self.too_large == 1:
                    logger.warning("robotics bridge: a cycle of %d bytes is larger than the link holds: not "
                                   "handed over (counted)", len(frame))
                return
            self._gone(record, f"{type(exc).__name__}: {exc}")

    def _gone(self, record: dict, why: str) -> None:
        """The bridge ended mid-run: logged once, this cycle and the next ones counted ``lost``."""
        self.died = why
        self.lost += 1
        status = self.proc.poll() if self.proc is not None else None
        logger.error("robotics bridge ended at cycle %s (exit status %s): no more Zenoh / Foxglove output "
                     "for this run (counted; the run goes on)", record.get("cycle"), status)

    def close(self) -> dict:
        """Close the link (the bridge publishes what it has, closes its outputs and ends); the
        figures: the bridge's own (``zenoh``, ``foxglove``) and the hand-over's (``bridge``)."""
        if self.proc is None:
            return {}
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        report = None
        if self.died is None:
            report = self._read_line(CLOSE_TIMEOUT_S)
        try:
            status = self.proc.wait(CLOSE_TIMEOUT_S if report is not None else 5.0)
        except subprocess.TimeoutExpired:
            status = self._kill()
        if report is None and self.died is None:
            self.died = f"no report at its end (exit status {status})"
        elif self.died is not None:
            self.died += f" (exit status {status})"
        self.proc.stdout.close()
        self.proc = None
        self._flag.close()
        self._flag = None
        out = dict(report.get("stats", {})) if isinstance(report, dict) else {}
        if self.unwanted:  # nobody wanted them: as the in-process outputs count such cycles
            if "zenoh" in out:
                out["zenoh"]["unmatched"] += self.unwanted
            if "foxglove" in out:
                out["foxglove"]["unwatched_cycles"] += self.unwanted
        out["bridge"] = {"frames": self.frames, "dropped": self.dropped, "too_large": self.too_large,
                         "lost": self.lost, "failed": self.failed, "died": self.died, "unwanted": self.unwanted,
                         "received": (report or {}).get("received"), "bad": (report or {}).get("bad", 0)}
        return out

    def _kill(self):
        if self._flag is not None:
            self._flag.close()
            self._flag = None
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.kill()
        status = self.proc.wait()
        return status


def bridge_lines(stats: dict) -> list[tuple[str, str]]:
    """The summary's ``bridge`` line."""
    b = stats.get("bridge")
    if not b:
        return []
    text = (f"{b['frames']} cycles handed over, {b['dropped']} dropped at the hand-over (bridge behind)"
            + (f", {b['too_large']} too large" if b["too_large"] else "")
            + (f", {b['unwanted']} not made (nobody watching)" if b.get("unwanted") else "")
            + (f", {b['failed']} not encodable" if b["failed"] else "")
            + (f", {b['bad']} refused by the bridge" if b.get("bad") else ""))
    if b["died"]:
        text += f"; the bridge ENDED mid-run ({b['died']}): {b['lost']} cycles after it not published"
    return [("bridge", text)]
