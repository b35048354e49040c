"""Foxglove messages of a run and the MCAP file (``--mcap FILE``), with the Foxglove SDK
(``foxglove-sdk``, imported as ``foxglove``).

:func:`encode` turns one record (and, in raw mode, its readings) into the cycle's messages -
``foxglove.RawImage`` taxel maps (protobuf) and JSON messages with a JSON schema
(:mod:`.topics`) - once; :class:`FoxgloveSink` logs them on the channels of one SDK context
(the MCAP file's, or the live server's: :mod:`.foxglove_live`), creating a channel the first
time its topic has a message. The MCAP writer is deterministic (zstd chunks compressed on one
thread; the header names the SDK), so the same records make the same file: a replay's MCAP is
the live run's, byte for byte (``tests/test_robotics_mcap.py``).

The file is written as ``FILE.partial`` and renamed onto ``FILE`` when the run ends (a run that
fails leaves no file that looks complete; an earlier ``FILE`` is removed); a FIFO or device is
written in place (:class:`taxel_net.outputs.OutputPath`).
"""

from __future__ import annotations

import os
import struct
from operator import itemgetter
from pathlib import Path

from taxel_net.errors import UsageError, one_line
from taxel_net.outputs import OutputPath

from .topics import _CONTACT_KEYS as _CONTACT_FIELDS
from .topics import (JSON_TOPICS, SCHEMAS, T_BUS, T_CONTACT, T_DECISION, T_FORCES, T_GRIP, T_SLIP, T_TRUTH, TopicMap,
                     _bus_key, _contact_key, _decision_key, _dumpb, _exact, _remember, _scalar, _states_key, log_time_ns,
                     truth_message)

PROFILE = ""            # MCAP header profile: none of the registry's (the messages are protobuf + JSON)
CHUNK_BYTES = 256 * 1024  # uncompressed chunk size: bounds the work of one chunk's compression

IMAGE, JSON_MSG = 0, 1


def encode(topics: TopicMap, record: dict, readings=None) -> tuple[int, list[tuple[str, int, bytes]]]:
    """(log time ns, [(topic, kind, payload), ...]) of one record, in a fixed order: the taxel
    maps, the readings (raw mode, with ``readings``), then the JSON topics.

    The bytes are :func:`encode_plain`'s. What a cycle's messages share with earlier cycles is
    kept per content (at most 1024 entries each) and put around the cycle's own numbers: the
    taxel maps' images but their time stamp, per (present taxels, nodes by state) pattern
    (``TopicMap.map_parts``, made on a miss by ``TopicMap.make_map_images``: kept here only);
    ``/fusion/decision`` but its ``cycle``, ``/bus`` but its per-cycle
    numbers and ``/fusion/contact``, per content (``TopicMap.cycle_parts``, one key a cycle,
    :func:`_cycle_key`), cut from :meth:`TopicMap.json_messages`'s texts the first time
    (docs/robotics.md, *Cost*: the publisher's Python work a cycle was most of the live
    server's cost). A record the keys do not cover - raw mode's readings, EMCY, duplicate nodes,
    an error, a field missing, not hashable or of no plain type - is :func:`encode_plain`'s."""
    if readings is None:
        try:
            key, heads, maps_key, states_key = _cycle_key(record)
            images = topics.map_parts.get(maps_key)
            parts = topics.cycle_parts.get(key)  # TypeError: a value that is no key (a list in a rule)
        except (KeyError, TypeError, AttributeError, ValueError):  # a hand-made record: the plain path
            return encode_plain(topics, record)
        t = log_time_ns(record)
        stamp = _stamp(t)
        if images is None:
            images = _remember(topics.map_parts, maps_key, tuple(
                (pad.map_topic, raw_image(b"", pad.name, pad.width, pad.height, "mono8", pad.width, data))
                for pad, data in zip(topics.pads, topics.make_map_images(record))))
        out = [(topic, IMAGE, stamp + rest) for topic, rest in images]
        if parts is None:
            texts = topics.json_messages(record, states_key)
            _remember_parts(topics, key, heads, record, texts)
            out += [(topic, JSON_MSG, payload) for topic, payload in texts]
            return t, out
        decision, bus, contact = parts
        cycle_head, bus_head = heads
        out.append((T_DECISION, JSON_MSG, cycle_head + decision))
        out.append((T_BUS, JSON_MSG, bus_head + bus))
        if contact is not None:
            out.append((T_CONTACT, JSON_MSG, contact))
        get = record.get
        for topic, name in ((T_SLIP, "slip"), (T_FORCES, "forces"), (T_GRIP, "grip")):
            value = get(name)
            if isinstance(value, dict):
                out.append((topic, JSON_MSG, topics._flat_json(value)))
        if isinstance(get("grasp_truth"), dict):
            out.append((T_TRUTH, JSON_MSG, _dumpb(truth_message(record))))
        return t, out
    return encode_plain(topics, record, readings)


# the fields a cycle's cached parts depend on, besides the decision's, the bus's and the contact's
# (topics._decision_key, _bus_key, _contact_key)
_CYCLE_FIELDS = itemgetter("present_nodes", "nodes_by_state", "rules")
_PER_CYCLE = itemgetter("cycle", "sync_counter", "closed_after_ms", "late_frames", "bad_frames", "emcy",
                        "duplicate_nodes")


def _cycle_key(record: dict):
    """(key, heads, maps key, states key) of a record whose cached parts may be used: the key
    holds every field the decision (but its cycle), the bus's stable part and the contact are
    made from, as their exact texts (``topics._exact``: 0.0 and -0.0, 1 and 1.0 apart), the maps
    key the present taxels and nodes by state (labels); the heads are the per-cycle texts that open
    ``/fusion/decision`` (``{"cycle":N,``) and ``/bus`` (its cycle, SYNC counter, close time,
    late and malformed frames), as :meth:`TopicMap.json_messages` writes them.
    KeyError / TypeError / AttributeError / ValueError: not this path's record."""
    cycle, sync, closed_ms, late, bad, emcy, duplicates = _PER_CYCLE(record)
    get = record.get
    if emcy or duplicates or get("error") is not None or get("emcy_dropped"):
        raise KeyError("emcy")  # /bus made whole (topics._bus_json)
    present, states, rules = _CYCLE_FIELDS(record)
    contact = None
    if "area" in record or "contact_type" in record:
        try:
            contact = _contact_key(record)
        except KeyError:  # a stage plan with the area but not the contact type: which fields there are, too
            contact = tuple([(k in record, get(k)) for k in _CONTACT_FIELDS])
    if rules.__class__ is not dict:
        raise TypeError("rules")
    states_key = _states_key(states)
    key = (states_key, _exact((_decision_key(record), rules, _bus_key(record), contact)))
    cycle_head = b'{"cycle":' + _scalar(cycle).encode() + b","
    bus_head = cycle_head + (f'"sync_counter":{_scalar(sync)},"closed_after_ms":{_scalar(closed_ms)},'
                             f'"late_frames":{_scalar(late)},"bad_frames":{_scalar(bad)}').encode()
    return key, (cycle_head, bus_head), (tuple(present), states_key), states_key


def _remember_parts(topics: TopicMap, key, heads, record: dict, texts) -> None:
    """Cut the cycle's shared parts from :meth:`TopicMap.json_messages`'s texts and keep them
    under ``key`` - only when every text is one the parts rebuild exactly."""
    cycle_head, bus_head = heads
    decision, bus, contact, extra = None, None, None, 0
    for topic, payload in texts:
        if topic == T_DECISION and decision is None and payload.startswith(cycle_head):
            decision = payload[len(cycle_head):]
        elif topic == T_BUS and bus is None and payload.startswith(bus_head):
            bus = payload[len(bus_head):]
        elif topic == T_CONTACT and contact is None:
            contact = payload
        elif topic in (T_SLIP, T_FORCES, T_GRIP, T_TRUTH):
            extra += 1  # made every cycle (topics._flat_json caches them itself)
        else:
            return
    if decision is None or bus is None or (contact is None) != (key[-1] is None) or \
            extra != sum(isinstance(record.get(k), dict) for k in ("slip", "forces", "grip", "grasp_truth")):
        return
    _remember(topics.cycle_parts, key, (decision, bus, contact))


def encode_plain(topics: TopicMap, record: dict, readings=None) -> tuple[int, list[tuple[str, int, bytes]]]:
    """:func:`encode` without the per-cycle cache: every message made from the record (through
    :class:`TopicMap`'s per-part caches)."""
    t = log_time_ns(record)
    stamp = _stamp(t)
    states_key = _states_key(record.get("nodes_by_state"))  # the map's and the bus's cache keys share it
    out: list[tuple[str, int, bytes]] = []
    for pad, data in zip(topics.pads, topics.map_images(record, states_key)):
        out.append((pad.map_topic, IMAGE, raw_image(stamp, pad.name, pad.width, pad.height, "mono8", pad.width, data)))
    if readings is not None:
        for pad, data in zip(topics.pads, topics.readings_images(readings)):
            out.append((pad.readings_topic, IMAGE,
                        raw_image(stamp, pad.name, pad.width, pad.height, "32FC1", 4 * pad.width, data)))
    for topic, payload in topics.json_messages(record, states_key):
        out.append((topic, JSON_MSG, payload))
    return t, out


# ``foxglove.RawImage`` in protobuf's wire format, made here: the SDK's message objects cost more
# per cycle than the rest of an image (tests/test_robotics_mcap.py checks these bytes against
# the SDK's RawImage(...).encode()). Fields (foxglove/schemas RawImage.proto): timestamp 1
# (google.protobuf.Timestamp: seconds 1, nanos 2), width 2, height 3 (fixed32), encoding 4,
# step 5 (fixed32), data 6, frame_id 7; proto3 leaves out zero numbers and empty strings.
def _varint(n: int) -> bytes:
    if n < 128:
        return _SMALL[n]
    out = bytearray()
    while True:
        low, n = n & 0x7F, n >> 7
        if n:
            out.append(low | 0x80)
        else:
            out.append(low)
            return bytes(out)


_SMALL = [bytes((n,)) for n in range(128)]


def _stamp(t: int) -> bytes:
    """Field 1 (the Timestamp) of a RawImage at ``t`` ns (t >= 0)."""
    sec, nsec = divmod(t, 1_000_000_000)
    inner = (b"\x08" + _varint(sec) if sec else b"") + (b"\x10" + _varint(nsec) if nsec else b"")
    return b"\x0a" + _varint(len(inner)) + inner


_IMAGE_FIELDS: dict = {}


def raw_image(stamp: bytes, frame_id: str, width: int, height: int, encoding: str, step: int, data: bytes) -> bytes:
    """One ``foxglove.RawImage`` (``stamp``: :func:`_stamp`)."""
    key = (frame_id, width, height, encoding, step)
    fields = _IMAGE_FIELDS.get(key)
    if fields is None:
        enc, frame = encoding.encode(), frame_id.encode()
        head = b"".join(tag + struct.pack("<I", v) for tag, v in ((b"\x15", width), (b"\x1d", height)) if v)
        head += b"\x22" + _varint(len(enc)) + enc if enc else b""
        head += b"\x2d" + struct.pack("<I", step) if step else b""
        tail = b"\x3a" + _varint(len(frame)) + frame if frame else b""
        fields = _IMAGE_FIELDS[key] = (head, tail)
    head, tail = fields
    return stamp + head + (b"\x32" + _varint(len(data)) + data if data else b"") + tail


class FoxgloveSink:
    """The channels of one SDK context; :meth:`log` writes one cycle's encoded messages."""

    def __init__(self, context, known=()):
        self.context = context
        self.channels: dict[str, object] = {}
        self._log: dict[str, object] = {}  # topic -> the channel's BaseChannel.log (no wrapper per message)
        self.messages = 0
        for topic, is_image in known:  # TopicMap.known_topics: open before the first cycle
            self.channel(topic, IMAGE if is_image else JSON_MSG)

    def channel(self, topic: str, kind: int):
        ch = self.channels.get(topic)
        if ch is None:
            import foxglove
            from foxglove.messages import RawImage

            if kind == IMAGE:
                ch = foxglove.Channel(topic, schema=RawImage.get_schema(), message_encoding="protobuf",
                                      context=self.context)
            else:
                ch = foxglove.Channel(topic, schema=SCHEMAS[topic] if topic in JSON_TOPICS else {},
                                      context=self.context)
            self.channels[topic] = ch
            self._log[topic] = ch.base.log
        return ch

    def log(self, t: int, messages) -> None:
        logs = self._log
        for topic, kind, payload in messages:
            log = logs.get(topic)
            if log is None:
                self.channel(topic, kind)
                log = logs[topic]
            log(payload, t)
        self.messages += len(messages)


class _InPlace:
    """A FIFO / device opened for writing, as the SDK's writer wants it (``write``, ``flush``,
    ``seek`` to where it is): written with seeking disabled."""

    def __init__(self, path: Path):
        self._f = open(path, "wb", buffering=0)
        self._pos = 0

    def write(self, data) -> int:
        n = self._f.write(data)
        self._pos += n
        return n

    def flush(self) -> None:
        pass

    def seek(self, offset: int, whence: int = 0) -> int:
        if (whence == os.SEEK_CUR and offset == 0) or (whence == os.SEEK_SET and offset == self._pos):
            return self._pos
        raise OSError("not seekable")

    def close(self) -> None:
        self._f.close()


class McapOutput:
    """``--mcap FILE``: every cycle's messages in one MCAP file (see the module docstring)."""

    def __init__(self, path, *, known=(), option: str = "--mcap"):
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        self.out = OutputPath(path, option=option)  # a directory: UsageError
        self.path = Path(path)
        self.context = foxglove.Context()
        in_place = self.out.in_place
        options = MCAPWriteOptions(compression=MCAPCompression.Zstd, compression_threads=0, profile=PROFILE,
                                   chunk_size=CHUNK_BYTES, disable_seeking=in_place)
        self._stream = None
        try:
            if in_place:
                self._stream = _InPlace(self.out.write_path)
                target = self._stream
            else:
                target = str(self.out.write_path)
            self.writer = foxglove.open_mcap(target, allow_overwrite=True, context=self.context,
                                             writer_options=options)
        except (OSError, RuntimeError, ValueError) as exc:
            self.out.discard_stale()
            raise UsageError(f"{option} {str(path)!r}: cannot be written: {exc}") from None
        self.sink = FoxgloveSink(self.context, known)
        self.closed = False

    def write_metadata(self, name: str, values: dict) -> None:
        try:
            self.writer.write_metadata(name, {str(k): str(v) for k, v in values.items()})
        except (OSError, RuntimeError) as exc:  # the SDK's I/O errors are RuntimeErrors
            raise UsageError(f"--mcap {str(self.path)!r}: cannot be written: {one_line(exc)}") from None

    def log(self, t: int, messages) -> None:
        self.sink.log(t, messages)

    def close(self, ok: bool = True) -> None:
        """Finish the file; ``ok``: rename it onto FILE, else leave ``FILE.partial`` (none when no
        cycle was written) and remove an earlier FILE (a failed run's file must not pass for a
        complete one)."""
        if self.closed:
            return
        self.closed = True
        try:
            self.writer.close()
        finally:
            if self._stream is not None:
                self._stream.close()
        if ok:
            self.out.commit()
        else:
            self.out.discard_stale()
            if not self.sink.messages:  # failed before the first cycle (a bus that cannot be opened)
                self.out.discard_partial()
