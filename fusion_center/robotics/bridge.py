"""The robotics bridge process: :func:`main` (``--fd N --flag-fd M --settings JSON``; the centre
runs it with ``python -c``, importing this package from where it did - :meth:`.bridge_link.RoboticsBridge.command`),
started by the centre (:class:`.bridge_link.RoboticsBridge`; docs/robotics.md, *The bridge
process*) - not a command of its own.

It loads the centre's scene (the settings name it; its fingerprint must match), opens what the
settings ask - the ``--zenoh`` publication (:class:`~fusion_center.service.zenoh_publisher.ZenohPublisher`)
and the live Foxglove server (:class:`.outputs.RoboticsOutputs` with its publisher thread) - and
prints ``{"ready": {...}}`` (or ``{"error": "one line"}`` and exits 2) on its stdout. Then it
reads the link's frames (:func:`.bridge_link.parse_frame`: JSON, nothing unpickled or executed),
publishes each exactly as the in-process outputs do (the record's payload the centre's line, the
same grip and contact messages, the same Foxglove channels and messages), and when the link
closes (the centre ended, or was killed) publishes what it holds, closes its outputs, prints
``{"stats": {...}, "received": N, "bad": M}`` and exits 0. SIGINT is ignored (a Ctrl-C on the
terminal is the centre's; this process is in a session of its own anyway).

**It dies with the centre** (:func:`die_with_parent`, its first act; Linux): with ``--parent-pid``
it asks the kernel for SIGTERM when the thread that started it ends (``prctl(PR_SET_PDEATHSIG)``)
and, the centre possibly gone already, exits at once if its parent is no longer that pid
(:func:`parent_pid_of`: ASCII digits, 1 .. pid_max - 1; else one line and exit 2). So a
centre killed while the bridge is still starting (a Zenoh session being opened, the scene being
loaded) leaves no bridge behind; later the link's end (above) ends it too. SIGTERM before the
ready line has its default action (nothing is written yet, and a handler would wait for a C call
- the Zenoh session's opening - to return); from the ready line on it shuts the link down, so the
bridge ends at a frame's boundary exactly as when the link closes (its outputs closed, its
counters printed) - from a watcher thread woken by the signal's wakeup fd, so also while the
main thread is blocked in a C call; an end not over within :data:`TERM_GRACE_S` (5 s) exits 143,
and so does a second SIGTERM at once while the main thread is still in that C call - once it got
to run the Python handler, SIGTERM has its default action back and a second one kills the bridge
by signal (status -15, no report) (:class:`_TermWatch`). The centre passes ``--parent-pid``
only when it starts the bridge from its main thread (the parent-death signal follows the
*thread* that forked: from another thread the bridge would die when that thread ends); where
``prctl`` is missing (not Linux) this is a no-op, logged at debug level, and the link's end is
what ends the bridge.
"""

from __future__ import annotations

import argparse
import json
import logging
import mmap
import os
import signal
import socket
import sys
import threading
import time

from taxel_net.errors import UsageError, one_line

logger = logging.getLogger("fusion_center.robotics.bridge")
RECV_BYTES = 16 << 20  # the largest frame read (the link's send buffer is far smaller)
WATCH_S = 0.05         # how often the bridge checks whether anything wants the cycles


_REPORT = None  # the centre's reading end: this process's stdout as it started (fd 1 then goes to stderr)


def _say(message: dict) -> None:
    _REPORT.write(json.dumps(message) + "\n")
    _REPORT.flush()


PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(parent_pid: int) -> bool:
    """Ask for SIGTERM when the thread that started this process ends (module docstring); False
    where that cannot be asked (not Linux: logged at debug level). Exits this process (status
    143, as the signal's) when its parent is no longer ``parent_pid`` (it ended before this call)."""
    asked = False
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            libc = ctypes.CDLL(None, use_errno=True)
            asked = libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) == 0
            if not asked:
                logger.debug("robotics bridge: prctl(PR_SET_PDEATHSIG): %s", os.strerror(ctypes.get_errno()))
        except (OSError, AttributeError) as exc:
            logger.debug("robotics bridge: no prctl: %s", exc)
    else:
        logger.debug("robotics bridge: no parent-death signal on %s: the link's end ends this process", sys.platform)
    if os.getppid() != parent_pid:  # the centre gone before the signal was asked for (reparented)
        logger.debug("robotics bridge: the centre (pid %d) ended before the bridge started: exiting", parent_pid)
        sys.exit(128 + signal.SIGTERM)
    return asked


PID_MAX_FALLBACK = 4194304  # the kernel's largest pid_max (PID_MAX_LIMIT on 64-bit), where /proc cannot say


def pid_max() -> int:
    """The kernel's ``pid_max`` (pids are 1 .. pid_max - 1); :data:`PID_MAX_FALLBACK` where it cannot be read."""
    try:
        with open("/proc/sys/kernel/pid_max", "rb") as f:
            value = int(f.read(32))
        return value if value > 1 else PID_MAX_FALLBACK
    except (OSError, ValueError):
        return PID_MAX_FALLBACK


def parent_pid_of(text: str) -> int | None:
    """``--parent-pid``'s value as a pid, or None when it is none: ASCII digits only (no sign,
    blank, ``_`` or other script's digits, which ``int`` takes), 1 .. pid_max - 1."""
    if not (0 < len(text) <= 10 and text.isascii() and text.isdigit()):
        return None
    value = int(text)
    return value if 1 <= value < pid_max() else None


TERM_GRACE_S = 5.0  # after SIGTERM: the clean end's bound, then the bridge exits 143 all the same


class _TermWatch:
    """SIGTERM from the ready line on (module docstring). Python runs a signal handler only on the
    main thread between bytecodes - never while it is blocked in a C call (a Zenoh close, a put
    held up) - so the handler acts through a watcher thread instead: the interpreter's C-level
    handler writes the signal's number to a wakeup socket (``signal.set_wakeup_fd``) at once, and
    the watcher shuts the link down (the clean end) and starts the grace: not over within
    :data:`TERM_GRACE_S`, ``os._exit(143)``; a second SIGTERM the watcher sees exits 143 at once. The
    Python handler, when it gets to run (the main thread between bytecodes), only gives SIGTERM its
    default action back: a further one then kills by signal (status -15, no report), even with the
    interpreter lock held - so 143 at a second SIGTERM holds while the main thread is still blocked."""

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self._read, self._write = socket.socketpair()
        self._write.setblocking(False)
        self.terms = 0
        # the wakeup fd and the watcher first, the handler last: a SIGTERM before the handler is in
        # place has its default action; one after it always wakes the watcher (handler first, one in
        # between ran the Python handler - SIG_DFL back - and woke nobody: the link never shut)
        signal.set_wakeup_fd(self._write.fileno(), warn_on_full_buffer=False)
        threading.Thread(target=self._watch, name="bridge-sigterm", daemon=True).start()
        signal.signal(signal.SIGTERM, self._handler)

    @staticmethod
    def _handler(signum, frame) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)

    def _watch(self) -> None:
        while True:
            try:
                data = self._read.recv(64)
            except InterruptedError:
                continue
            except OSError:
                return
            if not data:
                return
            for number in data:
                if number != signal.SIGTERM:
                    continue
                self.terms += 1
                if self.terms > 1:
                    os._exit(128 + signal.SIGTERM)
                _shut(self.sock)
                threading.Thread(target=self._grace, name="bridge-sigterm-grace", daemon=True).start()

    @staticmethod
    def _grace() -> None:
        time.sleep(TERM_GRACE_S)
        os.write(2, f"robotics bridge: its end took more than {TERM_GRACE_S:g} s after SIGTERM: exiting\n".encode())
        os._exit(128 + signal.SIGTERM)


def load_scene_of(settings: dict):
    from taxel_net.scene import load_scene

    from ..commands.run import apply_mode
    from .bridge_link import scene_digest

    source = settings["source"]
    scene = apply_mode(load_scene(source["scene"]), source.get("mode"))
    slow = source.get("slow_down", 1.0)
    if slow != 1.0:
        from ..commands.demo import slowed_down

        scene = slowed_down(scene, slow)
    if scene_digest(scene) != settings["digest"]:
        raise UsageError(f"robotics bridge: the scene {source['scene']!r} loaded here differs from the centre's "
                         "(the file changed since the run loaded it?)")
    return scene


class Bridge:
    def __init__(self, settings: dict):
        self.scene = load_scene_of(settings)
        self.publisher = self.outputs = None
        try:
            zenoh = settings.get("zenoh")
            if zenoh is not None:
                from ..service.zenoh_publisher import ZenohPublisher

                self.publisher = ZenohPublisher(self.scene.name, config_file=zenoh.get("config_file"),
                                                listen=zenoh.get("listen"), connect=zenoh.get("connect"),
                                                mode=zenoh.get("mode")).open()
            foxglove = settings.get("foxglove")
            if foxglove is not None:
                from .outputs import RoboticsOutputs

                self.outputs = RoboticsOutputs(self.scene, foxglove=(foxglove[0], int(foxglove[1])), threaded=True)
        except BaseException:
            self.close()
            raise
        self.received = 0
        self.bad = 0

    def ready(self) -> dict:
        out: dict = {"pid": os.getpid()}
        if self.publisher is not None:
            out["zenoh"] = {"keys": self.publisher.keys, "session": self.publisher.description}
        if self.outputs is not None:
            out["foxglove"] = {"host": self.outputs.live.host, "port": self.outputs.live.port}
        return out

    def wanted(self) -> bool:
        """Whether anything wants the cycles: a Zenoh subscriber matching any key, a viewer
        subscribed to any channel."""
        if self.publisher is not None and any(self.publisher._matching.values()):
            return True
        return self.outputs is not None and self.outputs.live.watched

    def tell(self, flag: mmap.mmap, stop: threading.Event) -> None:
        """Keeps the shared flag's first byte :meth:`wanted` (1 / 0; checked every
        :data:`WATCH_S`, the first time at once) for the centre to read."""
        while True:
            now = 1 if self.wanted() else 0
            if flag[0] != now:
                flag[0] = now
            if stop.wait(WATCH_S):
                return

    def serve(self, sock: socket.socket) -> None:
        from ..service.zenoh_publisher import FIRST_RECORD
        from .bridge_link import BASELINE_OF, FIRST, frame_gap, parse_frame

        buf = bytearray(RECV_BYTES)
        view = memoryview(buf)
        while True:
            try:
                n = sock.recv_into(buf)
            except InterruptedError:
                continue
            except OSError as exc:  # the centre gone: ECONNRESET
                logger.debug("link: %s", exc)
                return
            if n == 0:
                return  # the centre closed the link
            try:
                record, line, readings = parse_frame(view[:n])
            except ValueError as exc:
                self.bad += 1
                if self.bad <= 3:
                    logger.error("robotics bridge: a frame refused: %s%s", one_line(exc),
                                 " (further ones only counted)" if self.bad == 3 else "")
                continue
            self.received += 1
            if self.publisher is not None:
                gap, baseline = frame_gap(view)
                if gap:  # cycles this process did not see: the centre says what to compare with
                    self.publisher.rebase(FIRST_RECORD if baseline == FIRST
                                          else BASELINE_OF.get(baseline, record.get("decision")))
                self.publisher(record, line=line)
            if self.outputs is not None:
                self.outputs.publish(record, readings)

    def stats(self) -> dict:
        out: dict = {}
        if self.publisher is not None:
            out["zenoh"] = self.publisher.summary()
        if self.outputs is not None:
            out.update(self.outputs.close())
            self.outputs = None
        return out

    def close(self) -> None:
        if self.outputs is not None:
            self.outputs.close()
            self.outputs = None
        if self.publisher is not None:
            self.publisher.close()
            self.publisher = None


def _shut(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:  # closed already
        pass


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fusion_center.robotics.bridge", allow_abbrev=False,
                                     description="the centre's robotics bridge (started by run / demo)")
    parser.add_argument("--fd", type=int, required=True, help="the link's descriptor (inherited)")
    parser.add_argument("--flag-fd", type=int, required=True, help="the shared flag's memfd (inherited)")
    parser.add_argument("--settings", required=True, help="JSON: source, digest, zenoh, foxglove")
    parser.add_argument("--parent-pid", help="the centre's pid: die with it (SIGTERM; Linux)")
    args = parser.parse_args(argv)
    if args.parent_pid is not None:
        parent_pid = parent_pid_of(args.parent_pid)
        if parent_pid is None:
            sys.stderr.write(f"robotics bridge: --parent-pid {args.parent_pid!r}: expected a process id, "
                             f"ASCII digits 1..{pid_max() - 1} (/proc/sys/kernel/pid_max)\n")
            return 2
        die_with_parent(parent_pid)
    global _REPORT
    # the report channel is ours alone: anything a library prints goes to stderr, not into it
    _REPORT = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    sock = socket.socket(fileno=args.fd)
    flag = mmap.mmap(args.flag_fd, mmap.PAGESIZE)
    os.close(args.flag_fd)
    try:
        settings = json.loads(args.settings)
        bridge = Bridge(settings)
    except UsageError as exc:
        _say({"error": str(exc)})
        return 2
    except Exception as exc:  # noqa: BLE001 - one line to the centre
        _say({"error": f"robotics bridge: cannot start: {type(exc).__name__}: {one_line(exc)}"})
        return 2
    # SIGTERM (the centre's death, a user's kill) from here on: the link shut down, the bridge ends at
    # a frame's boundary as when the centre closes the link - outputs closed, counters printed - within
    # TERM_GRACE_S, even while blocked in a C call; a second SIGTERM ends it at once (_TermWatch)
    _TermWatch(sock)
    try:
        _say({"ready": bridge.ready()})
        stop = threading.Event()
        teller = threading.Thread(target=bridge.tell, args=(flag, stop), name="bridge-wanted", daemon=True)
        teller.start()
        bridge.serve(sock)
        stop.set()
        teller.join()
        sock.close()
        stats = bridge.stats()
        _say({"stats": stats, "received": bridge.received, "bad": bridge.bad})
    except BrokenPipeError:  # the centre gone before reading the report
        pass
    finally:
        bridge.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
