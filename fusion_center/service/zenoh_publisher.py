"""Every record of a run on Zenoh (``--zenoh`` on ``run`` and ``demo``; issue 24):
:class:`ZenohPublisher`, an ``on_record`` callback of
:class:`~fusion_center.service.fusion_service.FusionService`.

**Keys** (``<scene>``: the scene's name as one key chunk, :func:`.zenoh_config.key_segment`;
JSON payloads, encoding ``application/json``; docs/robotics.md, *Zenoh*):

* ``taxel/<scene>/record`` - every record: the bytes of its decision-log line
  (:func:`.records.dumpb`, no newline), so a subscriber reads what ``--json-lines`` writes -
  the JSON stream a tactile user knows from XELA's uSkin server; with ``--json-lines`` on, the
  line the log just wrote (:func:`.records.logged_line`: one serialisation a record);
* ``taxel/<scene>/grip`` - where a record has the grip stage's ``grip`` object (grasp scenes):
  ``{"cycle", "t", "command_n", "actual_n", "drive_state", "grip_state", "slip"}``, the
  record's ``grip`` with its cycle and SYNC time - what a gripper controller subscribes to;
* ``taxel/<scene>/contact`` - a contact event (iCub skinManager's idea) when the decision
  changes (and for the first record): ``{"cycle", "t", "event", "decision", "previous",
  "p_h1", "present_count", "present_nodes", "area", "contact_type"}``, ``event`` ``onset``
  (to H1), ``release`` (H1 to H0) or ``change`` (to or from undecided, the first record).

**Where it runs**: ``run --zenoh`` and ``demo --zenoh`` call it in the robotics bridge process
(:mod:`fusion_center.robotics.bridge`, with the centre's line as ``line``): Zenoh's threads are
not the centre's. Called as an ``on_record`` callback (the API) it runs in the caller's process.

**Never holds the cycle**: the callback runs on the thread that evaluated the record (a
receive thread, :mod:`.fusion_service`); each put uses ``CongestionControl.DROP``: with the
transmission queue full (a slow or stalled subscriber) a put waits at most Zenoh's
``transport/link/tx/queue/congestion_control/drop/wait_before_drop`` (1 ms by default; the
Zenoh file may lower it) and the sample is dropped - the subscriber loses samples, the run
loses nothing. While no subscriber wants a key (Zenoh's matching status), nothing is serialised
or put for it (:attr:`unmatched` counts the records). Express (sent at once, not batched): measured on loopback with a subscriber in
another process, a batched put after the 10 ms idle gap between cycles took 0.3-0.9 ms of the
caller's wall time (0.1-0.14 ms of its CPU: it waits for the batch), an express one 0.1-0.15 ms
(all CPU). Express puts flat out (2,000 of 1.4 kB back to back, far above any SYNC rate) fill
the queue and are dropped (1,782 of 2,000); at 2 kHz none were; a ``wait_before_drop`` of 0
dropped 46 of 2,000 even then. Zenoh's Python API reports no dropped sample to the publisher;
what this side counts is puts that failed (:attr:`failed`, e.g. the session closed) and what it
put.
"""

from __future__ import annotations

import json
import logging

from taxel_net.errors import UsageError
from .records import dumpb, logged_line
from .zenoh_config import key_segment, open_session, resolve

logger = logging.getLogger("fusion_center.service.zenoh")

GRIP_FIELDS = ("command_n", "actual_n", "drive_state", "grip_state", "slip")
CONTACT_FIELDS = ("p_h1", "present_count", "present_nodes", "area", "contact_type")


FIRST_RECORD = object()  # ZenohPublisher.rebase: no record before the next one

def keys(scene_name: str) -> dict[str, str]:
    """The publication's key expressions for a scene."""
    p = f"taxel/{key_segment(scene_name)}"
    return {"record": f"{p}/record", "grip": f"{p}/grip", "contact": f"{p}/contact"}


def grip_message(record: dict) -> dict | None:
    """The ``grip`` key's message of a record (None: the record has no ``grip``)."""
    grip = record.get("grip")
    if not isinstance(grip, dict):
        return None
    return {"cycle": record.get("cycle"), "t": record.get("t"), **{k: grip.get(k) for k in GRIP_FIELDS}}


def contact_event(record: dict, previous: str | None) -> dict:
    """The ``contact`` key's event of a record whose decision differs from ``previous``."""
    decision = record.get("decision")
    event = "onset" if decision == "H1" else "release" if previous == "H1" and decision == "H0" else "change"
    return {"cycle": record.get("cycle"), "t": record.get("t"), "event": event, "decision": decision,
            "previous": previous, **{k: record.get(k) for k in CONTACT_FIELDS}}


class ZenohPublisher:
    """Publishes every record it is called with (module docstring).

    ``with ZenohPublisher(scene.name) as pub: FusionService(scene, on_record=pub, ...)``.
    The session's settings: ``config_file`` / ``listen`` / ``connect`` / ``mode`` as the
    ``--zenoh-*`` flags (:mod:`.zenoh_config`; loopback ``tcp/127.0.0.1:7447`` by default);
    ``session``: an open ``zenoh.Session`` to use instead (not closed here). :meth:`open`
    raises :class:`UsageError` (one line) when the session cannot be had."""

    def __init__(self, scene_name: str, *, config_file: str | None = None, listen=None, connect=None,
                 mode: str | None = None, session=None):
        self.scene_name = scene_name
        self.keys = keys(scene_name)
        self.config_file = config_file
        self.listen = listen
        self.connect = connect
        self.mode = mode
        self.session = session
        self._own_session = session is None
        self.description = ""
        self._publishers: dict = {}
        self._matching: dict[str, bool] = {}  # a subscriber somewhere, per key (Zenoh's matching listener)
        self._listeners: list = []
        self.unmatched = 0      # records no subscriber wanted: not serialised, not put
        self.records = 0        # records put
        self.grips = 0          # grip messages put
        self.contacts = 0       # contact events put
        self.failed = 0         # puts that raised (a closed session)
        self._previous = None   # the decision of the last record
        self._first = True

    def open(self) -> "ZenohPublisher":
        import zenoh

        if self.session is None:
            config, what = resolve(config_flag=self.config_file, listen=self.listen, connect=self.connect,
                                   mode=self.mode)
            self.session = open_session(config, what)
            self.description = (f"listen {', '.join(json.loads(config.get_json('listen/endpoints')) or ['-'])}")
            connect = json.loads(config.get_json("connect/endpoints"))
            if connect:
                self.description += f", connect {', '.join(connect)}"
        try:
            for name, key in self.keys.items():
                publisher = self.session.declare_publisher(
                    key, encoding=zenoh.Encoding.APPLICATION_JSON, congestion_control=zenoh.CongestionControl.DROP,
                    express=True, priority=zenoh.Priority.DATA)
                self._listeners.append(publisher.declare_matching_listener(
                    lambda status, name=name: self._matching.__setitem__(name, bool(status.matching))))
                self._matching[name] = bool(publisher.matching_status.matching)
                self._publishers[name] = publisher
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError
            self.close()
            raise UsageError(f"--zenoh: cannot declare the publishers ({exc})") from None
        return self

    def __enter__(self) -> "ZenohPublisher":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def _put(self, name: str, payload: bytes) -> bool:
        try:
            self._publishers[name].put(payload)
            return True
        except Exception as exc:  # noqa: BLE001 - never raise into the evaluation
            self.failed += 1
            if self.failed == 1 or self.failed % 1000 == 0:
                logger.warning("zenoh: %d put(s) failed, the last: %s", self.failed, exc)
            return False

    def __call__(self, record: dict, line: bytes | None = None) -> None:
        """Publish one record (an ``on_record`` callback: quick, never raises, never waits);
        ``line``: the record's decision-log line when the caller has it (the robotics bridge:
        the centre's bytes), else :func:`.records.logged_line`."""
        if not self._publishers:
            return
        try:
            self._publish(record, line)
        except Exception as exc:  # noqa: BLE001 - a record JSON cannot hold (NaN in a hand-made one)
            self.failed += 1
            logger.warning("zenoh: a record not published: %s: %s", type(exc).__name__, exc)

    def _publish(self, record: dict, line: bytes | None = None) -> None:
        matching = self._matching
        if matching["record"]:
            self.records += self._put("record", logged_line(record) if line is None else line)
        else:
            self.unmatched += 1
        grip = grip_message(record) if matching["grip"] else None
        if grip is not None:
            self.grips += self._put("grip", dumpb(grip))
        decision = record.get("decision")
        if self._first or decision != self._previous:
            if matching["contact"]:
                self.contacts += self._put("contact", dumpb(contact_event(record, None if self._first else
                                                                          self._previous)))
            self._first = False
            self._previous = decision

    def rebase(self, previous=FIRST_RECORD) -> None:
        """Compare the next record's decision with ``previous`` (the contact events' baseline),
        not with the last record this publisher saw - for a caller that knows of records it was
        not given (the robotics bridge after cycles left out); :data:`FIRST_RECORD`: the next
        record is the run's first (an event of its own)."""
        self._first = previous is FIRST_RECORD
        self._previous = None if self._first else previous

    def summary(self) -> dict:
        return {"keys": dict(self.keys), "records": self.records, "grip": self.grips, "contact": self.contacts,
                "failed": self.failed, "unmatched": self.unmatched, "session": self.description}

    def close(self) -> None:
        for listener in self._listeners:
            try:
                listener.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self._listeners = []
        for publisher in self._publishers.values():
            try:
                publisher.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self._publishers = {}
        if self._own_session and self.session is not None:
            try:
                self.session.close()
            except Exception:  # noqa: BLE001
                pass
            self.session = None
