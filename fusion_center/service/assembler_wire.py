"""The assembler link's messages, protocol version 3 (issue 21; :mod:`.assemblers`): what an
assembler and the fuser send each other, encoded and decoded here only. Nothing that arrives is
unpickled or executed: every message is one msgpack map, checked against this specification
(docs/service.md, *The assembler link, protocol 3*, is the same text for a peer in another
language). Version 1 was a pickle of Python objects and is gone; version 2 had no ``bootups``.

**Transport.** One message is the payload of one Zenoh sample (:mod:`.assembler_link`: the
keys, the sessions, and the HMAC-SHA256 in each sample's attachment on the run's key that a
receiver checks before it decodes anything). The assembler's ``hello`` is the payload of a
query on the fuser's hello key, answered by one reply (``welcome`` or ``refused``); its parts
are reliable puts, in order; the fuser's ``bye`` / ``refused`` after the welcome are puts to
that assembler's key. A receiver decodes a message only up to its size limit
(:data:`HELLO_MAX`, :data:`ANSWER_MAX`, :meth:`PartCodec.max_bytes`); a longer one is refused
undecoded.

**Payload.** A msgpack map with string keys, exactly the keys listed for its ``kind`` (none
missing, none more), every map carrying ``"v": 2`` (an int) and ``"kind"``. msgpack types:
*int*, *float* (64-bit), *str* (UTF-8), *bin*, *bool*, *nil*, *array*; no ext types.
Arrays of numbers travel as *bin*: the raw little-endian values, ``n`` of them, ``n`` from the
scene's group layout (below), so a bin of the wrong length is refused. ``u8`` flags hold 0 or 1
only.

* ``hello`` (assembler -> fuser, the first message): ``scene`` a map ``{"scene": str, "n": int,
  "channels": int, "mode": str, "patch_nodes": bool, "sync_counter": int, "fd": bool}`` (the
  fingerprint both sides must share; str <= 1000 chars), ``channels`` an array of 1..256 distinct ints (the scene
  channels served), ``host`` str (<= 255 chars), ``pid`` int >= 0, ``numbered_from_reset`` bool.
* ``welcome`` (fuser -> assembler): ``group`` str (the group's name, ``0-3`` / ``0,2,5``).
* ``refused`` (fuser -> assembler: the answer to a hello it refuses, or - after a welcome -
  the link is dropped and the assembler says hello again): ``why`` str (<= 1000 chars). This
  one message keeps its layout in every version: a peer of another version (``"v"`` not 2)
  is answered with it.
* ``bye`` (fuser -> assembler, the run ended): no other key.
* ``part`` (assembler -> fuser, one per closed cycle; ``n`` the group's taxels, ``d`` its
  devices, both in the order of the group's sub-scene: :func:`.assembler_parts.group_layout`):

  ==================  ==============================================================
  ``channels``        array of int: the group's channels, as in its hello
  ``number``          int 0..2**62: the assembler's cycle number
  ``sync_counter``    nil or int 0..255: the SYNC counter byte of the cycle
  ``closed_by``       str, 1..32 of ``a-z_``: how the cycle closed (``complete``, ...)
  ``closed_after_us`` int, \\|x\\| < 2**53: SYNC -> closing event
  ``decisions``       bin, i8 x n, each -1, 0 or +1
  ``readings``        nil or bin, f64 x n
  ``received``        bin, u8 x n
  ``expected``        bin, u8 x n
  ``missing``         bin, u8 x n
  ``states``          bin, i16 x n, NMT states (-2, -1, 0, 4, 5, 127)
  ``held_decisions``  bin, i8 x n, each -1, 0 or +1
  ``held_readings``   nil or bin, f64 x n
  ``late_frames``     int 0..2**53
  ``bad_frames``      int 0..2**53
  ``emcy``            array of at most 16 arrays ``[node, taxel, code, register,
                      manufacturer, t_us]``: node the label of one of the group's
                      devices (int node-ID on channel 0, str ``"C:ID"``), taxel an int
                      of the group's taxels (scene index), code int 0..0xFFFF, register
                      int 0..0xFF, manufacturer str of 0..10 hex digits, t_us int,
                      \\|x\\| < 2**53
  ``emcy_dropped``    int 0..2**53
  ``duplicates``      array of distinct ints, each one of the group's devices (scene
                      device index)
  ``devices``         nil or array of 4 bins: expected u8 x d, missing u8 x d,
                      states i16 x d, complete u8 x d
  ``sent_at``         float, finite: seconds since 1970 when sent (latency figures)
  ``bootups``         array of at most d arrays ``[device, t_us]`` (protocol 3): each of
                      the group's devices (scene device index) at most once, that sent a
                      boot-up since the previous cycle, t_us its last one's time (int,
                      \\|x\\| < 2**53)
  ==================  ==============================================================

A message that breaks any of this is refused (:class:`BadMessage`): the fuser counts it and
logs it (rate-limited), drops the link of a part that breaks it (as a disconnected group), and
the run goes on (:mod:`.assemblers`).
"""

from __future__ import annotations

import math
import re
from typing import Sequence

import msgpack
import numpy as np

from taxel_net.patches import devices as scene_devices, node_label
from .assembler_parts import CyclePart, GroupLayout
from .cycle_records import EMCY_PER_CYCLE, STATE_RESETTING, EmcyEvent
from .decoder import STATE_NAMES

PROTOCOL = 3  # 3: a part's ``bootups`` (the over-range flags of a node that restarted by itself)
HELLO_MAX = 16 * 1024    # bytes: the largest hello a fuser reads
ANSWER_MAX = 16 * 1024   # bytes: the largest welcome / refused / bye an assembler reads
HANDSHAKE_TIMEOUT_S = 5.0  # hello -> the fuser's answer, else the try failed
WHY_MAX = 1000
HOST_MAX = 255
CHANNELS_MAX = 256
BIG = 2 ** 53

I8, U8, I16, F64 = np.dtype("<i1"), np.dtype("<u1"), np.dtype("<i2"), np.dtype("<f8")
_STATE_OK = np.zeros(1 << 16, dtype=bool)
_STATE_OK[np.array(sorted({*STATE_NAMES, STATE_RESETTING}), dtype=np.int16).view(np.uint16)] = True
_CLOSED_BY = re.compile(r"[a-z_]{1,32}")
_HEX = re.compile(r"[0-9a-fA-F]{0,10}")

HELLO_KEYS = frozenset({"v", "kind", "scene", "channels", "host", "pid", "numbered_from_reset"})
SCENE_KEYS = {"scene": str, "n": int, "channels": int, "mode": str, "patch_nodes": bool, "sync_counter": int,
              "fd": bool}
ANSWER_KEYS = {"welcome": frozenset({"v", "kind", "group"}), "refused": frozenset({"v", "kind", "why"}),
               "bye": frozenset({"v", "kind"})}
PART_KEYS = frozenset({"v", "kind", "channels", "number", "sync_counter", "closed_by", "closed_after_us",
                       "decisions", "readings", "received", "expected", "missing", "states", "held_decisions",
                       "held_readings", "late_frames", "bad_frames", "emcy", "emcy_dropped", "duplicates",
                       "devices", "sent_at", "bootups"})


class BadMessage(Exception):
    """A frame that is not a message of this protocol (the message says what is wrong)."""


class OtherVersion(BadMessage):
    """A msgpack map of another protocol version (its peer is answered ``refused``); ``message``:
    the map as read (a ``refused`` of any version is read from it: :func:`decode_answer`)."""

    def __init__(self, version, message: dict | None = None):
        super().__init__(f"protocol version {version!r}: this side speaks {PROTOCOL}")
        self.version = version
        self.message = message


# ---------------------------------------------------------------------------- maps

def _pack(message: dict) -> bytes:
    return msgpack.packb(message, use_bin_type=True)


def _unpack(data: bytes, kinds: dict) -> dict:
    """The map of ``data`` whose kind is one of ``kinds`` (kind -> its exact key set)."""
    try:
        m = msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True, timestamp=0)
    except Exception as exc:  # noqa: BLE001 - whatever the bytes: not msgpack
        raise BadMessage(f"not msgpack ({type(exc).__name__})") from None
    if not isinstance(m, dict):
        raise BadMessage(f"not a msgpack map but {type(m).__name__}")
    version = m.get("v")
    if type(version) is not int:
        raise BadMessage(f"no int protocol version 'v' (got {type(version).__name__})")
    if version != PROTOCOL:
        raise OtherVersion(version, m)
    kind = m.get("kind")
    if kind not in kinds:
        raise BadMessage(f"kind {str(kind)[:40]!r}: expected {' / '.join(kinds)}")
    keys = set(m)
    if keys != kinds[kind]:
        raise BadMessage(f"{kind}: keys missing {sorted(kinds[kind] - keys)}, unknown "
                         f"{sorted(str(k)[:40] for k in keys - kinds[kind])}")
    return m


def _int(m: dict, key: str, low: int, high: int) -> int:
    x = m[key]
    if type(x) is not int or not low <= x <= high:
        raise BadMessage(f"{key} {_shown(x)}: expected an int in {low}..{high}")
    return x


def _str(m: dict, key: str, limit: int) -> str:
    x = m[key]
    if type(x) is not str or len(x) > limit:
        raise BadMessage(f"{key} {_shown(x)}: expected a str of at most {limit} chars")
    return x


def _bool(m: dict, key: str) -> bool:
    x = m[key]
    if type(x) is not bool:
        raise BadMessage(f"{key} {_shown(x)}: expected a bool")
    return x


def _shown(x) -> str:
    text = repr(x)
    return text if len(text) <= 40 else text[:37] + "..."


# ---------------------------------------------------------------------------- hello and answers

def encode_hello(fingerprint: dict, channels: Sequence[int], host: str, pid: int, numbered_from_reset: bool) -> bytes:
    return _pack({"v": PROTOCOL, "kind": "hello", "scene": dict(fingerprint), "channels": [int(c) for c in channels],
                  "host": str(host)[:HOST_MAX], "pid": int(pid), "numbered_from_reset": bool(numbered_from_reset)})


def decode_hello(data: bytes) -> dict:
    """The hello's fields (``v`` and ``kind`` left out), every type and size checked; whether
    the scene and channels suit the fuser is the fuser's check."""
    m = _unpack(data, {"hello": HELLO_KEYS})
    scene = m["scene"]
    if not isinstance(scene, dict) or set(scene) != set(SCENE_KEYS):
        raise BadMessage(f"hello: scene {_shown(scene)}: expected a map of {sorted(SCENE_KEYS)}")
    for key, kind in SCENE_KEYS.items():
        if type(scene[key]) is not kind or (kind is str and len(scene[key]) > WHY_MAX):
            raise BadMessage(f"hello: scene {key} {_shown(scene[key])}: expected {kind.__name__}")
    channels = m["channels"]
    if (not isinstance(channels, list) or not 1 <= len(channels) <= CHANNELS_MAX
            or any(type(c) is not int or not 0 <= c < CHANNELS_MAX for c in channels)
            or len(set(channels)) != len(channels)):
        raise BadMessage(f"hello: channels {_shown(channels)}: expected 1..{CHANNELS_MAX} distinct ints "
                         f"in 0..{CHANNELS_MAX - 1}")
    return {"scene": scene, "channels": channels, "host": _str(m, "host", HOST_MAX),
            "pid": _int(m, "pid", 0, 2 ** 63 - 1), "numbered_from_reset": _bool(m, "numbered_from_reset")}


def encode_welcome(group: str) -> bytes:
    return _pack({"v": PROTOCOL, "kind": "welcome", "group": str(group)})


def encode_refused(why: str) -> bytes:
    why = str(why)
    return _pack({"v": PROTOCOL, "kind": "refused", "why": why if len(why) <= WHY_MAX else why[:WHY_MAX - 3] + "..."})


def encode_bye() -> bytes:
    return _pack({"v": PROTOCOL, "kind": "bye"})


def decode_answer(data: bytes, kinds: Sequence[str] = ("welcome", "refused", "bye")) -> dict:
    """A fuser's message (``kind`` and its field), checked; a ``refused`` of any version is read."""
    try:
        m = _unpack(data, {k: ANSWER_KEYS[k] for k in kinds})
    except OtherVersion as exc:
        m = exc.message  # the map _unpack read: the bytes are unpacked once
        if "refused" in kinds and m.get("kind") == "refused" and type(m.get("why")) is str:
            return {"kind": "refused", "why": m["why"][:WHY_MAX]}
        raise
    out = {"kind": m["kind"]}
    if m["kind"] == "welcome":
        out["group"] = _str(m, "group", 4 * CHANNELS_MAX)
    elif m["kind"] == "refused":
        out["why"] = _str(m, "why", WHY_MAX)
    return out


# ---------------------------------------------------------------------------- the part

def _raw(values, dtype: np.dtype) -> bytes:
    return np.ascontiguousarray(values, dtype=dtype).tobytes()


def encode_part(part: CyclePart) -> bytes:
    """The ``part`` message of a :class:`CyclePart` (arrays as raw little-endian bytes)."""
    dev = part.devices
    return _pack({
        "v": PROTOCOL, "kind": "part", "channels": [int(c) for c in part.channels], "number": int(part.number),
        "sync_counter": None if part.sync_counter is None else int(part.sync_counter),
        "closed_by": str(part.closed_by), "closed_after_us": int(part.closed_after_us),
        "decisions": _raw(part.decisions, I8),
        "readings": None if part.readings is None else _raw(part.readings, F64),
        "received": _raw(part.received, U8), "expected": _raw(part.expected, U8),
        "missing": _raw(part.missing, U8), "states": _raw(part.states, I16),
        "held_decisions": _raw(part.held_decisions, I8),
        "held_readings": None if part.held_readings is None else _raw(part.held_readings, F64),
        "late_frames": int(part.late_frames), "bad_frames": int(part.bad_frames),
        "emcy": [[e.node if isinstance(e.node, str) else int(e.node), int(e.taxel), int(e.code), int(e.register),
                  str(e.manufacturer), int(e.t_us)] for e in part.emcy],
        "emcy_dropped": int(part.emcy_dropped), "duplicates": [int(d) for d in part.duplicates],
        "devices": None if dev is None else [_raw(dev[0], U8), _raw(dev[1], U8), _raw(dev[2], I16),
                                             _raw(dev[3], U8)],
        "sent_at": float(part.sent_at),
        "bootups": [[int(d), int(t_us)] for d, t_us in part.bootups]})


class PartCodec:
    """Decodes the ``part`` messages of one channel group of ``scene`` (sizes, node labels,
    taxels and devices checked against its :class:`GroupLayout`)."""

    def __init__(self, scene, layout: GroupLayout):
        self.layout = layout
        self.channels = [int(c) for c in layout.channels]
        self.n = len(layout.taxels)
        self.d = len(layout.devices)
        full = scene_devices(scene)
        self.labels = {node_label(full[i].channel, full[i].node_id) for i in layout.devices}
        self.taxels = {int(t) for t in layout.taxels}
        self.devices = {int(i) for i in layout.devices}
        # per taxel: 5 flag / decision bytes, 2 state bytes, 16 reading bytes; per device 5 bytes, a
        # duplicate (9) and a bootups entry (16: array header, device, int64 t_us); EMCY entries; bin /
        # array headers, keys and scalars (under 1 kB)
        self.max_bytes = 4096 + 23 * self.n + 30 * self.d + EMCY_PER_CYCLE * 128 + 9 * len(self.channels)

    def _array(self, key: str, data, dtype: np.dtype, count: int, *, nil: bool = False):
        if data is None and nil:
            return None
        if type(data) is not bytes or len(data) != count * dtype.itemsize:
            raise BadMessage(f"part: {key} {_shown(data)[:20]}: expected {'nil or ' if nil else ''}bin of "
                             f"{count} x {dtype.str}")
        if dtype is U8:  # (bytes.translate: the bytes other than these, at C speed)
            if data.translate(None, b"\x00\x01"):
                raise BadMessage(f"part: {key}: a flag other than 0 / 1")
            return np.frombuffer(data, dtype=np.bool_)
        if dtype is I8 and data.translate(None, b"\x00\x01\xff"):
            raise BadMessage(f"part: {key}: a decision other than -1 / 0 / +1")
        a = np.frombuffer(data, dtype=dtype)
        if dtype is I16 and not _STATE_OK.take(a.view(np.uint16)).all():
            raise BadMessage(f"part: {key}: a value that is no NMT state")
        return a

    def decode(self, data: bytes) -> CyclePart:
        m = _unpack(data, {"part": PART_KEYS})
        if m["channels"] != self.channels:
            raise BadMessage(f"part: channels {_shown(m['channels'])}: this link's group is {self.channels}")
        counter = m["sync_counter"]
        if counter is not None:
            counter = _int(m, "sync_counter", 0, 255)
        closed_by = m["closed_by"]
        if type(closed_by) is not str or not _CLOSED_BY.fullmatch(closed_by):
            raise BadMessage(f"part: closed_by {_shown(closed_by)}: expected 1..32 of a-z_")
        sent_at = m["sent_at"]
        if type(sent_at) is not float or not math.isfinite(sent_at):
            raise BadMessage(f"part: sent_at {_shown(sent_at)}: expected a finite float")

        def array(key, dtype, nil=False):
            return self._array(key, m[key], dtype, self.n, nil=nil)

        return CyclePart(
            channels=tuple(self.channels), number=_int(m, "number", 0, 2 ** 62), sync_counter=counter,
            closed_by=closed_by, closed_after_us=_int(m, "closed_after_us", -BIG, BIG),
            decisions=array("decisions", I8), readings=array("readings", F64, nil=True),
            received=array("received", U8), expected=array("expected", U8), missing=array("missing", U8),
            states=array("states", I16), held_decisions=array("held_decisions", I8),
            held_readings=array("held_readings", F64, nil=True),
            late_frames=_int(m, "late_frames", 0, BIG), bad_frames=_int(m, "bad_frames", 0, BIG),
            emcy=self._emcy(m["emcy"]), emcy_dropped=_int(m, "emcy_dropped", 0, BIG),
            duplicates=self._duplicates(m["duplicates"]), devices=self._devices(m), sent_at=sent_at,
            bootups=self._bootups(m["bootups"]))

    def _emcy(self, entries) -> tuple:
        if not isinstance(entries, list) or len(entries) > EMCY_PER_CYCLE:
            raise BadMessage(f"part: emcy {_shown(entries)}: expected an array of at most {EMCY_PER_CYCLE}")
        out = []
        for entry in entries:
            if not isinstance(entry, list) or len(entry) != 6:
                raise BadMessage(f"part: emcy entry {_shown(entry)}: expected [node, taxel, code, register, "
                                 "manufacturer, t_us]")
            node, taxel, code, register, manufacturer, t_us = entry
            if type(node) not in (int, str) or node not in self.labels:
                raise BadMessage(f"part: emcy node {_shown(node)}: not a node of the group")
            if type(taxel) is not int or taxel not in self.taxels:
                raise BadMessage(f"part: emcy taxel {_shown(taxel)}: not a taxel of the group")
            fields = {"code": code, "register": register, "t_us": t_us}
            _int(fields, "code", 0, 0xFFFF)
            _int(fields, "register", 0, 0xFF)
            _int(fields, "t_us", -BIG, BIG)
            if type(manufacturer) is not str or not _HEX.fullmatch(manufacturer):
                raise BadMessage(f"part: emcy manufacturer {_shown(manufacturer)}: expected 0..10 hex digits")
            out.append(EmcyEvent(node, taxel, code, register, manufacturer, t_us))
        return tuple(out)

    def _duplicates(self, entries) -> tuple:
        if (not isinstance(entries, list) or len(entries) > self.d or len(set(entries)) != len(entries)
                or any(type(d) is not int or d not in self.devices for d in entries)):
            raise BadMessage(f"part: duplicates {_shown(entries)}: expected distinct devices of the group")
        return tuple(entries)

    def _bootups(self, entries) -> tuple:
        if not isinstance(entries, list) or len(entries) > self.d:
            raise BadMessage(f"part: bootups {_shown(entries)}: expected an array of at most {self.d} "
                             "[device, t_us]")
        out = []
        for entry in entries:
            if (not isinstance(entry, list) or len(entry) != 2 or type(entry[0]) is not int
                    or entry[0] not in self.devices):
                raise BadMessage(f"part: bootups entry {_shown(entry)}: expected [a device of the group, t_us]")
            _int({"t_us": entry[1]}, "t_us", -BIG, BIG)
            out.append((entry[0], entry[1]))
        if len({d for d, _ in out}) != len(out):
            raise BadMessage(f"part: bootups {_shown(entries)}: a device twice")
        return tuple(out)

    def _devices(self, m: dict):
        dev = m["devices"]
        if dev is None:
            return None
        if not isinstance(dev, list) or len(dev) != 4:
            raise BadMessage(f"part: devices {_shown(dev)[:20]}: expected nil or [expected, missing, states, complete]")
        names = ("devices.expected", "devices.missing", "devices.states", "devices.complete")
        return tuple(self._array(name, value, dtype, self.d)
                     for name, dtype, value in zip(names, (U8, U8, I16, U8), dev))
