"""The assembler link's messages (issue 21, item 3: "Any local user can run code in the fusion
centre"; issue 24: the link on Zenoh): nothing that arrives is unpickled, on either side. A
part, a hello and the answers travel as the msgpack maps of
``fusion_center.service.assembler_wire`` (protocol 3, docs/service.md), checked against the
scene's group layout, each signed with the run's key (``assembler_link``); a Zenoh peer on the
assemblers' keys (loopback, scouting off) that sends anything else - a pickle (the issue's
os.system payload among them), random bytes, an oversize message, a map of wrong types or
another version, a hello of another scene, a message not signed with the run's key - is
refused: counted, logged at most once a kind; the run goes on. Without FUSION_CENTER_AUTHKEY a
loopback fuser's key is its own (a 0600 file of its user's), not a constant of the source."""

from __future__ import annotations

import dataclasses
import logging
import os
import pickle
import random
import stat
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from taxel_net.errors import UsageError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from test_assemblers import StandInFuser, _assemble, _finish, _parts, _udp_rig, zenoh_peer  # noqa: E402
from test_node_shards import _scene_file  # noqa: E402 - the two-channel patch scene (2 x 40 taxels)

OLD_LOOPBACK_KEY = b"taxel-can loopback"  # the constant of the source before issue 21


class Payload:
    """The issue's payload: unpickling it runs a shell command (here: creates ``marker``)."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


def _wait(condition, what: str, limit_s: float = 30.0) -> None:
    """Waits until ``condition()`` (a safety limit, not a timing claim)."""
    end = time.monotonic() + limit_s
    while not condition():
        assert time.monotonic() < end, f"still waiting for {what}"
        time.sleep(0.01)


def _hello(peer, scene, key: bytes, payload: bytes, *, sign: bool = True, link_id: str | None = None):
    """A hello as an assembler sends it (a query on the hello key, signed with ``key`` unless
    not ``sign``): (link id, the decoded answer or None when none came within 5 s)."""
    from fusion_center.service import assembler_link as link
    from fusion_center.service.assembler_wire import decode_answer

    link_id = link_id or link.new_id()
    k = link.hello_key(link.prefix(scene.name))
    tag = link.mac(link.mac_key(key), k, payload, link_id.encode()) if sign else bytes(32)
    for reply in peer.get(k, payload=payload, attachment=link_id.encode() + tag, timeout=5):
        if reply.ok is not None:
            return link_id, decode_answer(reply.ok.payload.to_bytes())
    return link_id, None


def _put_part(peer, scene, key: bytes | None, link_id: str, payload: bytes) -> None:
    """A part on the part key of ``link_id`` (signed with ``key``; None: not signed)."""
    from fusion_center.service import assembler_link as link

    k = link.part_key(link.prefix(scene.name), link_id)
    peer.put(k, payload, attachment=link.mac(link.mac_key(key), k, payload) if key is not None else bytes(32))


def _rich_parts(scene):
    """Both groups' parts of one cycle with every field used: readings, held readings, EMCY of
    the group's nodes, duplicate evidence, a SYNC counter, a send time."""
    from fusion_center.service.assembler_parts import group_layout
    from fusion_center.service.cycle_records import EmcyEvent
    from taxel_net.patches import devices, node_label

    rng = np.random.default_rng(5)
    out = {}
    full = devices(scene)
    for name, part in _parts(scene, 7, 8).items():
        lay = group_layout(scene, part.channels)
        n = len(lay.taxels)
        readings = rng.normal(size=n)
        readings[::7] = np.nan
        emcy = tuple(EmcyEvent(node_label(full[d].channel, full[d].node_id), int(lay.taxels[k]), 0x5000 + k, 0x81,
                               "0a0b0c0d0e", 1000 * k - 3)
                     for k, d in enumerate(lay.devices))
        out[name] = dataclasses.replace(
            part, readings=readings, held_readings=rng.normal(size=n), emcy=emcy,
            duplicates=(int(lay.devices[-1]),), late_frames=3, bad_frames=1, emcy_dropped=2,
            bootups=((int(lay.devices[0]), 123_456 + int(lay.devices[0])),),
            states=np.where(np.arange(n) % 3 == 0, 127, 5).astype(np.int16), sent_at=1.7e9 + 0.25,
            decisions=rng.integers(-1, 2, size=n).astype(np.int8))
    return out


def _same_part(a, b) -> None:
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name == "devices":
            assert (x is None) == (y is None)
            if x is not None:
                for u, v in zip(x, y):
                    np.testing.assert_array_equal(np.asarray(u), np.asarray(v))
        elif isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=f.name)
            assert np.asarray(x).dtype.kind == np.asarray(y).dtype.kind, f.name
        else:
            assert x == y, f.name


# ---------------------------------------------------------------------------- the encoding

def test_a_part_round_trips_and_merges_as_the_part_itself(tmp_path):
    from fusion_center.service.assembler_parts import group_layout
    from fusion_center.service.assembler_wire import PartCodec, encode_part
    from fusion_center.service.cycle_merger import CycleMerger

    scene = load_scene(_scene_file(tmp_path))
    parts = _rich_parts(scene)
    decoded = {}
    for name, part in parts.items():
        layout = group_layout(scene, part.channels)
        data = encode_part(part)
        codec = PartCodec(scene, layout)
        assert len(data) <= codec.max_bytes
        decoded[name] = codec.decode(data)
        _same_part(part, decoded[name])
        # the spec's layout, read with msgpack alone: raw little-endian arrays, nil for no readings
        m = msgpack.unpackb(data)
        assert m["v"] == 3 and m["kind"] == "part"
        assert m["states"] == part.states.astype("<i2").tobytes()
        assert m["readings"] == np.asarray(part.readings, dtype="<f8").tobytes()
        assert m["received"] == bytes(part.received.astype(np.uint8))
        assert msgpack.unpackb(encode_part(dataclasses.replace(part, readings=None)))["readings"] is None
    merged = []
    for source in (parts, decoded):
        merger = CycleMerger(scene, part_deadline_s=1.0)
        for g in (0, 1):
            merger.add_group(group_layout(scene, [g]))
        merger.opened(8, 0, 0.0)
        for name, part in source.items():
            merger.add_part(name, part)
        (closed,) = merger.emit(0.0)
        merged.append(closed)
    a, b = merged
    assert a.emcy == b.emcy and len(a.emcy) == 4 and a.duplicates == b.duplicates
    assert a.bootups == b.bootups == tuple(sorted(p.bootups[0] for p in parts.values())) and len(a.bootups) == 2
    for f in ("decisions", "readings", "received", "expected", "missing", "states", "held_decisions", "held_readings"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)


def _largest_part(scene, lay):
    """A part of group ``lay`` with every field at its largest."""
    from fusion_center.service.assembler_parts import CyclePart
    from fusion_center.service.cycle_records import EMCY_PER_CYCLE, EmcyEvent
    from taxel_net.patches import devices, node_label

    n, d = len(lay.taxels), len(lay.devices)
    full = devices(scene)
    longest = max(lay.devices, key=lambda i: len(str(node_label(full[i].channel, full[i].node_id))))
    big = 2 ** 53
    return CyclePart(
        channels=lay.channels, number=2 ** 62, sync_counter=255, closed_by="x" * 32, closed_after_us=-big,
        decisions=np.full(n, -1, np.int8), readings=np.full(n, -1e300), received=np.ones(n, bool),
        expected=np.ones(n, bool), missing=np.ones(n, bool), states=np.full(n, 127, np.int16),
        held_decisions=np.ones(n, np.int8), held_readings=np.full(n, 1e300), late_frames=big, bad_frames=big,
        emcy=(EmcyEvent(node_label(full[longest].channel, full[longest].node_id), int(lay.taxels[-1]), 0xFFFF, 0xFF,
                        "f" * 10, -big),) * EMCY_PER_CYCLE,
        emcy_dropped=big, duplicates=tuple(int(i) for i in lay.devices),
        devices=(np.ones(d, bool), np.ones(d, bool), np.full(d, 127, np.int16), np.ones(d, bool)), sent_at=-1e300,
        bootups=tuple((int(i), -big) for i in lay.devices))


def test_the_largest_part_fits_its_frame_limit():
    """skin4096 in one group (4,096 taxels, 512 patch nodes): every field at its largest."""
    from fusion_center.service.assembler_parts import group_layout
    from fusion_center.service.assembler_wire import PartCodec, encode_part

    scene = load_scene("skin4096")
    lay = group_layout(scene, range(len(scene.bus.channels)))
    part = _largest_part(scene, lay)
    codec = PartCodec(scene, lay)
    data = encode_part(part)
    assert len(data) <= codec.max_bytes, (len(data), codec.max_bytes)
    _same_part(part, codec.decode(data))


def test_the_largest_part_crosses_the_link(monkeypatch):
    """... and goes from an assembler to the fuser over Zenoh (over 64 kB: Zenoh fragments it),
    signed and checked, into the merge."""
    from fusion_center.service.assembler_parts import group_layout
    from fusion_center.service.assembler_process import AssemblerProcess
    from fusion_center.service.assemblers import AssembledFusionService
    from fusion_center.service.assembler_wire import encode_part

    monkeypatch.setenv("FUSION_CENTER_AUTHKEY", "wire-test-key")
    scene = load_scene("skin4096")
    chans = range(len(scene.bus.channels))
    lay = group_layout(scene, chans)
    part = _largest_part(scene, lay)
    assert len(encode_part(part)) > 65536
    port = random.randint(40000, 60000)
    service = AssembledFusionService(scene, listen=("127.0.0.1", port), interface="virtual",
                                     channels=[f"big-{port}-{k}" for k in chans])
    service.open()
    process = AssemblerProcess(scene, list(chans), fuser=("127.0.0.1", port), interface="virtual",
                               channel_names=[f"big-{port}-{k}" for k in chans])
    try:
        process.open()
        process.connect(30)
        service.merger.opened(255, 0, time.monotonic())
        process._outbox.append(part)
        process._send()
        _wait(lambda: service.merger.stats.parts == 1 or service.merger.stats.refused, "the part merged")
        assert service.merger.stats.parts == 1 and service.merger.stats.refused == {}
    finally:
        process.close()
        service.close()


def _mutations(scene):
    """(what, change of a valid part's map) pairs: each breaks the spec."""
    from taxel_net.patches import devices, node_label

    other = [node_label(x.channel, x.node_id) for x in devices(scene) if x.channel == 0]

    def put(key, value):
        return lambda m: m.__setitem__(key, value)

    return [
        ("v 1", put("v", 1)), ("v missing", lambda m: m.pop("v")), ("v str", put("v", "2")),
        ("kind hello", put("kind", "hello")), ("unknown key", put("extra", 1)),
        ("key missing", lambda m: m.pop("emcy")),
        ("decisions short", lambda m: m.__setitem__("decisions", m["decisions"][:-1])),
        ("decisions as ints", lambda m: m.__setitem__("decisions", list(m["decisions"]))),
        ("decisions 2", lambda m: m.__setitem__("decisions", b"\x02" + m["decisions"][1:])),
        ("received 2", lambda m: m.__setitem__("received", b"\x02" + m["received"][1:])),
        ("states 3", lambda m: m.__setitem__("states", b"\x03\x00" + m["states"][2:])),
        ("readings odd", lambda m: m.__setitem__("readings", m["readings"][:-3])),
        ("readings str", put("readings", "1.0")),
        ("number -1", put("number", -1)), ("number str", put("number", "5")), ("number bool", put("number", True)),
        ("number float", put("number", 5.0)), ("number 2**64", put("number", 2 ** 64 - 1)),
        ("sync_counter 256", put("sync_counter", 256)), ("closed_by odd", put("closed_by", "Complete!")),
        ("closed_by long", put("closed_by", "a" * 33)), ("sent_at nan", put("sent_at", float("nan"))),
        ("sent_at int", put("sent_at", 1)), ("channels other group", put("channels", [0])),
        ("late_frames -1", put("late_frames", -1)),
        ("emcy node of group 0", lambda m: m["emcy"][0].__setitem__(0, other[0])),
        ("emcy taxel of group 0", lambda m: m["emcy"][0].__setitem__(1, 0)),
        ("emcy code 0x10000", lambda m: m["emcy"][0].__setitem__(2, 0x10000)),
        ("emcy manufacturer", lambda m: m["emcy"][0].__setitem__(4, "zz")),
        ("emcy entry short", lambda m: m["emcy"][0].pop()),
        ("emcy 17", lambda m: m.__setitem__("emcy", [m["emcy"][0]] * 17)),
        ("duplicates of group 0", put("duplicates", [0])),
        ("duplicates repeated", lambda m: m.__setitem__("duplicates", m["duplicates"] * 2)),
        ("bootups of group 0", put("bootups", [[0, 5]])),
        ("bootups repeated", lambda m: m.__setitem__("bootups", m["bootups"] * 2)),
        ("bootups t float", lambda m: m["bootups"][0].__setitem__(1, 5.0)),
        ("bootups t 2**63", lambda m: m["bootups"][0].__setitem__(1, 2 ** 63 - 1)),
        ("bootups entry short", lambda m: m["bootups"][0].pop()),
        ("bootups not a list", put("bootups", {})),
        ("devices 3", lambda m: m["devices"].pop()),
        ("devices short", lambda m: m["devices"].__setitem__(2, b"\x05\x00")),
    ]


def test_decode_refuses_every_part_that_breaks_the_spec(tmp_path):
    from fusion_center.service.assembler_parts import group_layout
    from fusion_center.service.assembler_wire import BadMessage, OtherVersion, PartCodec, encode_part

    scene = load_scene(_scene_file(tmp_path))
    part = _rich_parts(scene)["1"]
    codec = PartCodec(scene, group_layout(scene, [1]))
    good = encode_part(part)
    codec.decode(good)  # the unchanged map passes
    for what, change in _mutations(scene):
        m = msgpack.unpackb(good)
        change(m)
        with pytest.raises(BadMessage) as info:
            codec.decode(msgpack.packb(m, use_bin_type=True))
        assert isinstance(info.value, OtherVersion) == (what == "v 1"), what
    rng = random.Random(3)
    junk = [pickle.dumps(part), pickle.dumps({"kind": "part"}), pickle.dumps(Payload(tmp_path / "never")), b"",
            bytes(rng.randrange(256) for _ in range(200)), msgpack.packb([1, 2]), msgpack.packb({1: 2}),
            msgpack.packb(msgpack.ExtType(5, b"x")), b"\x91" * 5000, good + b"\x00", good[:-1]]
    for data in junk:
        with pytest.raises(BadMessage):
            codec.decode(data)
    assert not (tmp_path / "never").exists()


def test_hello_and_answers_are_checked(tmp_path):
    from fusion_center.service.assembler_parts import scene_fingerprint
    from fusion_center.service.assembler_wire import (BadMessage, OtherVersion, decode_answer, decode_hello,
                                                      encode_bye, encode_hello, encode_refused, encode_welcome)

    scene = load_scene(_scene_file(tmp_path))
    data = encode_hello(scene_fingerprint(scene), [1, 0], "host-a", 42, True)
    assert decode_hello(data) == {"scene": scene_fingerprint(scene), "channels": [1, 0], "host": "host-a",
                                  "pid": 42, "numbered_from_reset": True}
    good = msgpack.unpackb(data)
    for key, value in (("channels", "0"), ("channels", []), ("channels", [0, 0]), ("channels", [True]),
                       ("pid", -1), ("host", 5), ("numbered_from_reset", 1), ("scene", {"scene": "x"}),
                       ("scene", {**good["scene"], "n": "80"}), ("v", 1)):
        with pytest.raises(BadMessage):
            decode_hello(msgpack.packb({**good, key: value}))
    assert decode_answer(encode_welcome("0-1")) == {"kind": "welcome", "group": "0-1"}
    assert decode_answer(encode_refused("x" * 5000))["why"].endswith("...")
    assert decode_answer(encode_bye(), ("bye",)) == {"kind": "bye"}
    with pytest.raises(BadMessage):
        decode_answer(encode_welcome("0"), ("bye",))  # after the welcome only a bye
    # a refused of another version is read (its layout is every version's); other maps are not
    assert decode_answer(msgpack.packb({"v": 4, "kind": "refused", "why": "too old"})) == \
        {"kind": "refused", "why": "too old"}
    with pytest.raises(OtherVersion):
        decode_answer(msgpack.packb({"v": 4, "kind": "welcome", "group": "0"}))


def test_an_answer_of_another_version_is_unpacked_once(monkeypatch):
    """decode_answer reads a ``refused`` of another version from the map the check read, not by
    unpacking the bytes a second time."""
    from fusion_center.service import assembler_wire

    calls = []
    real = assembler_wire.msgpack.unpackb

    def counting(*args, **kwargs):
        calls.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(assembler_wire.msgpack, "unpackb", counting)
    data = msgpack.packb({"v": 4, "kind": "refused", "why": "too old"})
    assert assembler_wire.decode_answer(data) == {"kind": "refused", "why": "too old"}
    assert calls == [data]
    calls.clear()
    other = msgpack.packb({"v": 4, "kind": "welcome", "group": "0"})
    with pytest.raises(assembler_wire.OtherVersion):
        assembler_wire.decode_answer(other)
    assert calls == [other]


# ---------------------------------------------------------------------------- the fuser

def _service(scene, port, **kwargs):
    from fusion_center.service.assemblers import AssembledFusionService

    return AssembledFusionService(scene, listen=("127.0.0.1", port), interface="virtual",
                                  channels=[f"wire-{port}-a", f"wire-{port}-b"], **kwargs)


def test_a_pickle_from_a_peer_with_the_key_runs_nothing_in_the_fuser(tmp_path, monkeypatch):
    """The issue's reproduction, with the key known to the peer (the worst case): a pickle as
    the hello, signed; the fuser never unpickles it, does not answer, counts it; no file appears."""
    monkeypatch.setenv("FUSION_CENTER_AUTHKEY", "wire-test-key")
    scene = load_scene(_scene_file(tmp_path))
    port = random.randint(40000, 60000)
    service = _service(scene, port)
    marker = tmp_path / "pwned"
    service.open()
    peer = zenoh_peer(connect=port)
    try:
        _wait(lambda: _hello(peer, scene, b"x", b"probe", sign=False)[1] is None
              and service.merger.stats.refused.get("key"), "the peer connected")  # an unsigned probe: key
        _, answer = _hello(peer, scene, b"wire-test-key", pickle.dumps(Payload(marker)))
        assert answer is None
        _wait(lambda: service.merger.stats.refused.get("message"), "the refusal counted")
        assert not marker.exists()
        assert service.merger.stats.refused == {"message": 1, "key": 1} and service.merger.stats.parts == 0
    finally:
        peer.close()
        service.close()


def test_junk_peers_are_refused_counted_logged_once_and_the_link_goes_on(tmp_path, monkeypatch, caplog):
    from fusion_center.service import assembler_link as link
    from fusion_center.service.assembler_parts import scene_fingerprint
    from fusion_center.service.assembler_process import AssemblerProcess
    from fusion_center.service.assembler_wire import HELLO_MAX, encode_hello, encode_part

    monkeypatch.setenv("FUSION_CENTER_AUTHKEY", "wire-test-key")
    key = b"wire-test-key"
    scene = load_scene(_scene_file(tmp_path))
    port = random.randint(40000, 60000)
    service = _service(scene, port)
    service._log.interval_s = 3600.0  # one line a kind for the whole test, however slow the host
    marker = tmp_path / "pwned"
    good = msgpack.unpackb(encode_hello(scene_fingerprint(scene), [1], "h", 1, False))
    caplog.set_level(logging.WARNING, logger="fusion_center.service.assemblers")
    service.open()
    peer = zenoh_peer(connect=port)
    p = link.prefix(scene.name)
    try:
        _wait(lambda: _hello(peer, scene, key, b"\x00")[1] is None and service.merger.stats.refused,
              "the peer connected")  # not msgpack: message
        unanswered = []
        for payload, signed_with in (
                (pickle.dumps({"kind": "hello", "protocol": 1, "scene": scene_fingerprint(scene), "channels": [1]}),
                 None),  # version 1's hello, a benign pickle, not signed: key
                (pickle.dumps(Payload(marker)), OLD_LOOPBACK_KEY),  # signed with the old constant: key
                (bytes(random.Random(1).randrange(256) for _ in range(300)), key),
                (b"\x00" * (HELLO_MAX + 1), key),  # oversize: refused unread
                (msgpack.packb({**good, "channels": "1"}), key),
                (msgpack.packb({**good, "pid": 1.5}), key)):
            unanswered.append(_hello(peer, scene, signed_with or b"", payload, sign=signed_with is not None)[1])
        assert unanswered == [None] * 6
        # another version: told why (signed), counted
        _, answer = _hello(peer, scene, key, msgpack.packb({**good, "v": 4}))
        assert answer["kind"] == "refused" and "protocol version 4" in answer["why"], answer
        # a hello of another scene: refused with the reason
        _, answer = _hello(peer, scene, key, msgpack.packb({**good, "scene": {**good["scene"], "n": 81}}))
        assert answer["kind"] == "refused" and "scene differs" in answer["why"], answer
        # a well-formed hello; then parts: not signed, a signed pickle (its link dropped and told, the
        # pickle never loaded), a part of a link that is not there, an oversize one
        told = []
        link_id = link.new_id()
        told_q = peer.declare_queryable(link.to_link_key(p, link_id),
                                        lambda q: (told.append(q.payload.to_bytes()), q.reply(q.key_expr, b"")))
        _, answer = _hello(peer, scene, key, msgpack.packb(good), link_id=link_id)
        assert answer == {"kind": "welcome", "group": "1"}
        _wait(lambda: service.merger.covered() == {1}, "group 1 welcomed")
        _put_part(peer, scene, None, link_id, pickle.dumps(Payload(marker)))
        _wait(lambda: service.merger.stats.refused.get("key") == 3, "the unsigned part refused")
        assert service.merger.covered() == {1}  # an unsigned message changes nothing
        _put_part(peer, scene, key, link_id, pickle.dumps(Payload(marker)))
        _wait(lambda: service.merger.covered() == set(), "group 1 dropped")
        _wait(lambda: told, "the dropped link told")
        from fusion_center.service.assembler_wire import decode_answer

        assert decode_answer(told[0])["kind"] == "refused"
        _put_part(peer, scene, key, link.new_id(), encode_part(_parts(scene, 7, 8)["1"]))  # no such link
        _put_part(peer, scene, key, link.new_id(), b"\x00" * (HELLO_MAX + 1))
        told_q.undeclare()
        # ... and an assembler is welcomed: the link goes on, its parts merge
        process = AssemblerProcess(scene, [0], fuser=("127.0.0.1", port), interface="virtual", reconnect_timeout_s=5)
        try:
            process.open()
            process.connect(30)
            _wait(lambda: service.merger.covered() == {0}, "group 0 welcomed")
            assert service.merger.stats.parts == 0 and service.records == []
            service.merger.opened(8, 0, time.monotonic())
            process._outbox.append(_parts(scene, 7, 8)["0"])
            process._send()
            _wait(lambda: service.merger.stats.parts == 1, "the part merged")
            assert process.parts_sent == 1 and service.merger.stats.by_group == {"1": 0, "0": 1}
            assert service.merger.stats.unmatched_parts == 0
        finally:
            process.close()
        want = {"message": 8, "key": 3, "hello": 1, "link": 1}
        _wait(lambda: service.merger.stats.refused == want, f"{want} (got {service.merger.stats.refused})")
        assert not marker.exists()
        stats = service.merger.stats
        assert stats.reconnects == {} and len(service.refused) == 1  # the other scene's hello
        # logged at most once a kind (in the test's hour)
        lines = [r.getMessage() for r in caplog.records if "assembler message refused" in r.getMessage()]
        assert sorted(line.split("(")[1].split(")")[0] for line in lines) == sorted(want), lines
        assert len(encode_part(_parts(scene, 7, 8)["0"])) < 2000
    finally:
        peer.close()
        service.close()


# ---------------------------------------------------------------------------- the assembler

def test_an_assembler_runs_nothing_its_fuser_sends(tmp_path, monkeypatch):
    """A stand-in fuser (it has the key) answers the hello with the payload; then, welcomed, sends
    it (unsigned, signed) before its bye: the assembler refuses both, counts them, ends on the
    bye; a welcome not signed with the key is no answer."""
    from fusion_center.service.assembler_process import AssemblerProcess
    from fusion_center.service.assembler_wire import encode_bye, encode_welcome

    monkeypatch.setenv("FUSION_CENTER_AUTHKEY", "wire-test-key")
    scene = load_scene(_scene_file(tmp_path))
    marker = tmp_path / "pwned"
    port = random.randint(40000, 60000)
    fuser = StandInFuser(scene, b"wire-test-key", port)
    try:
        fuser.answers.put(pickle.dumps(Payload(marker)))
        process = AssemblerProcess(scene, [1], fuser=("127.0.0.1", port), interface="virtual", reconnect_timeout_s=10)
        try:
            process.open()
            with pytest.raises(UsageError) as info:
                process.connect(10)
        finally:
            process.close()
        assert not marker.exists()
        assert "not a fuser of protocol 3" in str(info.value)
        fuser.answers.put(encode_welcome("1"))
        process = AssemblerProcess(scene, [1], fuser=("127.0.0.1", port), interface="virtual", reconnect_timeout_s=10)
        try:
            process.open()
            process.connect(10)
            link_id = fuser.hellos[-1][0]
            assert fuser.tell(link_id, pickle.dumps(Payload(marker)), signed=False) == 0
            assert fuser.tell(link_id, pickle.dumps(Payload(marker))) == 0
            assert fuser.tell(link_id, encode_welcome("1")) == 0  # signed, of the protocol, not a bye
            assert process.bad_messages == 3 and not process.closed.is_set()
            assert fuser.tell(link_id, encode_bye()) == 1
            assert process.closed.wait(30)
            assert process.bye and process.bad_messages == 3 and process.reconnects == 0
        finally:
            process.close()
        assert not marker.exists()
    finally:
        fuser.close()
    unsigned = StandInFuser(scene, b"wire-test-key", port + 1, sign=False)
    try:
        unsigned.answers.put(encode_welcome("1"))
        process = AssemblerProcess(scene, [1], fuser=("127.0.0.1", port + 1), interface="virtual")
        process.handshake_timeout_s = 0.5
        try:
            process.open()
            with pytest.raises(UsageError, match=r"answers not signed with it: [1-9]"):
                process.connect(1.0)
        finally:
            process.close()
    finally:
        unsigned.close()


# ---------------------------------------------------------------------------- the loopback key

def test_without_the_variable_a_loopback_fuser_has_a_key_of_its_own(tmp_path, monkeypatch):
    from fusion_center.service.assembler_parts import key_dir, key_file, read_key_file, write_key_file
    from fusion_center.service.assembler_process import AssemblerProcess

    monkeypatch.delenv("FUSION_CENTER_AUTHKEY", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "run"))
    (tmp_path / "run").mkdir(mode=0o700)
    scene = load_scene(_scene_file(tmp_path))
    ports = random.sample(range(40000, 60000), 2)
    services = [_service(scene, port) for port in ports]
    try:
        for service in services:
            service.open()
        keys = [Path(key_file(port)).read_bytes() for port in ports]
        assert keys[0] != keys[1] and all(len(k) == 64 for k in keys)
        assert [s.authkey for s in services] == keys
        assert stat.S_IMODE(os.stat(key_file(ports[0])).st_mode) == 0o600
        assert stat.S_IMODE(os.stat(key_dir()).st_mode) == 0o700
        address = ("127.0.0.1", ports[0])
        for authkey in (OLD_LOOPBACK_KEY, keys[1]):  # the old constant, another run's key: no answer
            process = AssemblerProcess(scene, [0, 1], fuser=address, interface="virtual", authkey=authkey)
            process.handshake_timeout_s = 0.5
            try:
                process.open()
                with pytest.raises(UsageError, match="no answer to the hello"):
                    process.connect(0.2)
            finally:
                process.close()
        refused = dict(services[0].merger.stats.refused)
        assert set(refused) == {"key"} and refused["key"] >= 2, refused
        process = AssemblerProcess(scene, [0, 1], fuser=address, interface="virtual")
        try:
            process.open()
            process.connect(30)  # finds this user's fuser's key by itself
            _wait(lambda: services[0].merger.covered() == {0, 1}, "the assembler welcomed")
        finally:
            process.close()
    finally:
        for service in services:
            service.close()
    assert not os.path.exists(key_file(ports[0]))  # removed at the end of its run
    # a key directory or file open to others is refused, naming it
    write_key_file(ports[0])
    os.chmod(key_file(ports[0]), 0o644)
    with pytest.raises(UsageError, match="fuser key file .* mode 0644"):
        read_key_file(ports[0])
    os.chmod(key_dir(), 0o755)
    with pytest.raises(UsageError, match="fuser key directory .* mode 0755"):
        write_key_file(ports[1])
    service = _service(scene, ports[1])
    with pytest.raises(UsageError, match="fuser key directory"):
        service.open()
    peer = zenoh_peer(listen=ports[1])  # and nothing is left listening on its port
    peer.close()


# ---------------------------------------------------------------------------- a run

def test_junk_peers_during_a_run_change_no_record(tmp_path):
    """Two `fusion-center assemble` processes feed a run on udp_multicast (the key: this run's
    file); meanwhile a Zenoh peer on the assemblers' keys sends the payload signed with that key,
    junk, a hello signed with the old constant key, an unsigned part: nothing runs, each is
    refused and counted, and the run's records are those of a run without them."""
    from fusion_center.service import assembler_link as link
    from fusion_center.service.assembler_parts import read_key_file
    from test_assemblers import _fuser

    scene, path, rig, bus, port, fuser_port = _udp_rig(tmp_path)
    from skin_scale import check_records  # bench/ (importable after _udp_rig)
    service = _fuser(scene, bus, fuser_port)
    marker = tmp_path / "pwned"
    done = threading.Event()
    errors = []

    def attack():
        peer = None
        try:
            key = read_key_file(fuser_port)
            peer = zenoh_peer(connect=fuser_port)
            assert _hello(peer, scene, key, pickle.dumps(Payload(marker)))[1] is None
            assert _hello(peer, scene, key, os.urandom(64))[1] is None
            assert _hello(peer, scene, OLD_LOOPBACK_KEY, pickle.dumps(Payload(marker)))[1] is None
            _put_part(peer, scene, None, link.new_id(), pickle.dumps(Payload(marker)))
        except Exception as exc:  # noqa: BLE001 - reported by the test
            errors.append(exc)
        finally:
            if peer is not None:
                peer.close()
            done.set()

    def hook(k):
        if k == 10:
            threading.Thread(target=attack, daemon=True).start()

    procs = []
    try:
        rig.start()
        service.open()
        procs = [_assemble(path, serve, fuser_port, port) for serve in ("0", "1")]
        for proc in procs:
            line = proc.stdout.readline()
            assert "ready" in line, (line, proc.stderr.read() if proc.poll() is not None else "")
        service.boot(5.0)
        service.run(40, before_sync=hook, timeout_s=600)
        assert done.wait(60) and not errors, errors
    finally:
        service.close()
        rig.stop()
    outs = [_finish(proc) for proc in procs]
    records = service.records
    stats = service.merger.stats
    figures = check_records(scene, records)
    print(figures, stats.as_dict())
    assert not marker.exists()
    assert stats.refused == {"message": 2, "key": 2}
    assert [rc for rc, _, _ in outs] == [0, 0], outs
    assert all("40 cycles sent" in out and "0 reconnects" in out for _, out, _ in outs), outs
    assert [r["cycle"] for r in records] == list(range(40)) and figures["misattributed"] == 0
    assert stats.by_group == {"0": 40, "1": 40} and stats.unmatched_parts == 0 and stats.reconnects == {}
    assert any(r["closed_by"] == "complete" for r in records)
    assert all(r["parts_missing"] == [] for r in records if r["closed_by"] == "complete")
    from fusion_center.commands.run import format_summary  # the summary line names them

    summary_line = [line for line in format_summary({**_summary_stub(), "assemblers": stats.as_dict()})
                    if line.startswith("assemblers:")][0]
    assert "refused 4 (message 2, key 2)" in summary_line, summary_line


def _summary_stub() -> dict:
    return {"scene": "s", "mode": "m", "cycles": 0, "records": 0, "decisions": {"H1": 0, "H0": 0, "undecided": 0},
            "decide_with": "-", "agree_with_truth": None, "rules_agree_with_truth": {}, "degraded_cycles": 0,
            "missing_at_boot": [], "stages_run": [], "stages_skipped": {}, "rules_skipped": {}, "counters": {},
            "sdo": {"writes": 0, "aborts": 0, "timeouts": 0}, "sync_overruns": 0, "latency_ms_p50": None,
            "latency_ms_p99": None}
