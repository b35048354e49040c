"""The robotics outputs of one run: the MCAP file, the live Foxglove server, the ROS 2 bag
(docs/robotics.md), fed from the centre's record callback.

:meth:`RoboticsOutputs.on_cycle` is the callback (``FusionService.on_cycle``,
``replay_trace(on_cycle=...)``): with ``threaded=True`` (``run``, ``demo``) it only appends the
record (and its readings in raw mode) to a queue - no encoding, no I/O, no lock the cycle could
wait on - and a publisher thread, woken every :data:`POLL_S` (10 times a second: a wake-up per
cycle would cost more than the publishing on a loaded host), encodes each cycle once and logs it
to every output in cycle order - the cycles that wait (up to :data:`DRAIN_BATCH`) all encoded
first, then their messages handed to the outputs back to back, so that the SDK's threads take
them in one wake-up and each output's code runs hot (docs/robotics.md, *Cost*); the MCAP file and the bag get every cycle, the live server
skips the oldest when more than ``LIVE_BACKLOG`` cycles wait (counted). With only the live server
and no viewer subscribed, the callback queues nothing (the cycle is counted ``unwatched``) and
the publisher waits for a subscription. ``threaded=False`` (``replay``, ``export``) does the same
work in the caller. Either way the messages and their order are the same, so the MCAP of a
replay is the live run's.
"""

from __future__ import annotations

import logging
import threading
from collections import deque

from taxel_net.errors import UsageError, one_line
from .topics import TopicMap

logger = logging.getLogger("fusion_center.robotics")
POLL_S = 0.1
DRAIN_BATCH = 64  # cycles encoded before their messages go to the outputs (bounds the memory of a backlog)


class RoboticsOutputs:
    def __init__(self, scene, *, mcap=None, foxglove=None, ros2_bag=None, threaded: bool = False,
                 topics: TopicMap | None = None):
        self.topics = topics or TopicMap(scene)
        self.mcap = self.live = self.bag = None
        self.threaded = threaded
        self._queue: deque = deque()
        self._stop = threading.Event()
        self._thread = None
        self.cycles = 0
        self.errors = 0
        try:
            if ros2_bag is not None:
                from .ros2_bag import Ros2Bag

                self.bag = Ros2Bag(ros2_bag, self.topics)
            if mcap is not None:
                from .mcap_out import McapOutput

                self.mcap = McapOutput(mcap, known=self.topics.known_topics)
                self.mcap.write_metadata("taxel_can", {"scene": scene.name, "mode": scene.bus.mode,
                                                       "taxels": scene.n, "time": "log time = SYNC time, ns "
                                                       "since the run's first CAN event"})
            if foxglove is not None:
                from .foxglove_live import LiveServer

                host, port = foxglove
                self.live = LiveServer(host, port, known=self.topics.known_topics)
        except BaseException:
            self.close(ok=False)
            raise
        self._live_only = self.live is not None and self.mcap is None and self.bag is None
        if threaded:
            self._thread = threading.Thread(target=self._worker, name="robotics-publisher", daemon=True)
            self._thread.start()

    def attach(self, service) -> None:
        """Publish every record of ``service`` (a ``FusionService``)."""
        service.on_cycle.append(self.on_cycle)

    def on_cycle(self, record: dict, closed=None) -> None:
        if self._live_only and not self.live.watched:
            self.live.unwatched += 1  # nobody to send it to, nothing else to write
            return
        self.publish(record, self.topics.readings_of(closed))

    def publish(self, record: dict, readings=None) -> None:
        """:meth:`on_cycle` with the readings given (``TopicMap.readings_of``; the robotics
        bridge gets them from the centre)."""
        if self._live_only and not self.live.watched:
            self.live.unwatched += 1
            return
        if self.threaded:
            self._queue.append((record, readings))
        else:
            self._publish(record, readings, live=True)

    def _publish(self, record: dict, readings, *, live: bool) -> None:
        self._publish_all([(record, readings, live)])

    def _publish_all(self, items) -> None:
        """Publish ``[(record, readings, live), ...]`` in order: every cycle's messages are made
        first, then handed to the outputs back to back - the SDK's threads (the server's sender,
        woken by a message) then take a burst's messages in one wake-up instead of one a cycle,
        and each output's code runs hot. The files get the same messages in the same order."""
        from .mcap_out import encode

        made = []
        for record, readings, live in items:
            if live and self.live is not None and not self.live.watched:
                live = False  # no viewer subscribed: nothing to send (the SDK would drop it)
                self.live.unwatched += 1
            try:
                t, messages = encode(self.topics, record, readings) \
                    if self.mcap is not None or (live and self.live is not None) else (None, None)
            except Exception as exc:  # noqa: BLE001 - an output never stops the run
                self._failed(record, exc)
                continue
            made.append((record, readings, live, t, messages))
        for record, readings, live, t, messages in made:
            try:
                if self.mcap is not None:
                    self.mcap.log(t, messages)
                if live and self.live is not None:
                    self.live.log(t, messages)
                if self.bag is not None:
                    self.bag.write(record, readings)
                self.cycles += 1
            except Exception as exc:  # noqa: BLE001 - an output never stops the run
                self._failed(record, exc)

    def _failed(self, record: dict, exc: Exception) -> None:
        """Counted, logged (3 lines at most)."""
        self.errors += 1
        if self.errors <= 3:
            logger.error("cycle %s: publishing failed: %s%s", record.get("cycle"), one_line(exc),
                         " (further failures only counted)" if self.errors == 3 else "")

    def _drain(self) -> None:
        from .foxglove_live import LIVE_BACKLOG

        queue = self._queue
        lossless = self.mcap is not None or self.bag is not None
        batch = []
        while queue:
            record, readings = queue.popleft()
            live = True
            if self.live is not None and len(queue) >= LIVE_BACKLOG:
                live = False
                self.live.dropped += 1
            if live or lossless:
                batch.append((record, readings, live))
            if len(batch) >= DRAIN_BATCH:
                self._publish_all(batch)
                batch = []
        if batch:
            self._publish_all(batch)

    def _worker(self) -> None:
        while True:
            if self._live_only and not self.live.watched and not self._queue:
                # nobody subscribed: wait for a subscription (or the end), not on a clock
                self.live.listener.subscribed.wait()
                if self._stop.is_set():
                    break
            # a timed wait close() ends at once (a plain sleep costs half the wake-up's CPU but
            # held close() up to POLL_S more: docs/robotics.md, *Cost*)
            if self._stop.wait(POLL_S):
                break
            self._drain()
        self._drain()

    def close(self, ok: bool = True) -> dict:
        """Publish what is queued, finish every output (``ok``: files committed, else left
        partial), return the summary figures."""
        if self._thread is not None:
            self._stop.set()
            if self.live is not None:
                self.live.listener.subscribed.set()  # a publisher waiting for a viewer: wake it
            self._thread.join()
            self._thread = None
        elif self._queue:
            self._drain()
        stats = self.stats()
        failed = []
        for option, output in (("--mcap", self.mcap), ("--ros2-bag", self.bag)):
            if output is not None:
                try:
                    output.close(ok=ok)
                except Exception as exc:  # noqa: BLE001 - a full disk, a FIFO's reader gone: one line
                    failed.append(f"{option} {str(getattr(output, 'path', ''))!r}: {one_line(exc)}")
        if self.live is not None:
            self.live.close()
        if failed and ok:
            raise UsageError("; ".join(failed) + " (not finished: not renamed onto its name)")
        return stats

    def stats(self) -> dict:
        out: dict = {}
        if self.mcap is not None:
            out["mcap"] = {"path": str(self.mcap.path), "cycles": self.cycles, "messages": self.mcap.sink.messages}
        if self.bag is not None:
            out["ros2_bag"] = {"path": str(self.bag.target), "cycles": self.bag.cycles, "messages": self.bag.messages}
        if self.live is not None:
            out["foxglove"] = self.live.stats()
        if self.errors:
            out["errors"] = self.errors
        return out


def summary_lines(stats: dict) -> list[tuple[str, str]]:
    """``(label, text)`` lines for the run summary."""
    lines = []
    if "mcap" in stats:
        m = stats["mcap"]
        lines.append(("mcap", f"{m['path']}: {m['cycles']} cycles, {m['messages']} messages"))
    if "ros2_bag" in stats:
        b = stats["ros2_bag"]
        lines.append(("ros2_bag", f"{b['path']}: {b['cycles']} cycles, {b['messages']} messages"))
    if "foxglove" in stats:
        f = stats["foxglove"]
        lines.append(("foxglove", f"ws://{f['address']}: {f['cycles']} cycles published to {f['clients']} "
                                  f"client(s), {f['unwatched_cycles']} with none subscribed, {f['dropped_cycles']} "
                                  "dropped before the server (a stalled client's losses in the SDK's outbox are "
                                  "not counted by the SDK)"))
    if "bridge" in stats:
        from .bridge_link import bridge_lines

        lines += bridge_lines(stats)
    if "errors" in stats:
        lines.append(("robotics_errors", f"{stats['errors']} cycles not published (see the log)"))
    return lines


def incomplete_files(stats: dict) -> list[tuple[str, str]]:
    """``(label, one line)`` for each file output (MCAP, ROS 2 bag) of ``stats`` (:meth:`RoboticsOutputs.close`)
    that lacks cycles an encoder refused (counted in ``errors``): the run's exit status says it."""
    if not stats.get("errors"):
        return []
    return [(label, f"{option} {stats[label]['path']!r}: {stats['errors']} cycle(s) not published (see the log): "
                    "the file lacks them")
            for label, option in (("mcap", "--mcap"), ("ros2_bag", "--ros2-bag")) if label in stats]
