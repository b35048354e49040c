"""The robotics bridge process (``--zenoh`` / ``--foxglove`` on run and demo; docs/robotics.md,
*The bridge process*): what goes through it equals the records (a Zenoh subscriber and a
Foxglove WebSocket client of the test's own), a bridge that does not read loses whole frames,
counted, and never holds the centre, and the bridge's life follows the centre's. Loopback only,
Zenoh's multicast scouting off (the project's defaults)."""

from __future__ import annotations

import asyncio
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import pytest

from fusion_center.robotics.bridge_link import (ENC_JSON, ENC_MSGPACK, RoboticsBridge, bridge_lines, make_frame,
                                                parse_frame)
from fusion_center.service.records import dumpb
from taxel_net.errors import UsageError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from test_assemblers import zenoh_peer  # noqa: E402
from test_robotics_live import SUBPROTOCOL, TIMEOUT, _advertised, _connect, _message_data, _subscribe  # noqa: E402
from test_zenoh import _ports  # noqa: E402


class _Collect:
    """An outputs stand-in for run_demo: keeps every (record, closed cycle)."""

    def __init__(self):
        self.cycles = []

    def attach(self, service):
        service.on_cycle.append(lambda record, closed: self.cycles.append((record, closed)))

    def close(self, ok=True):
        return {}


def _demo_cycles(scene_name: str, n: int):
    from fusion_center.commands.demo import run_demo

    scene = load_scene(scene_name)
    collect = _Collect()
    run_demo(scene, n, keep_records=False, outputs=collect)
    return scene, collect.cycles


def _wait(predicate, what: str) -> None:
    end = time.monotonic() + TIMEOUT  # a safety bound, not a timing claim
    while not predicate():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.01)



def _zenoh_subscriber(peer, key: str):
    """A Zenoh subscriber on ``key``: (subscriber, [(key, payload bytes), ...] as they come, the
    condition notified at each)."""
    got: list = []
    cond = threading.Condition()

    def on_sample(sample):
        with cond:
            got.append((str(sample.key_expr), sample.payload.to_bytes()))
            cond.notify_all()

    return peer.declare_subscriber(key, on_sample), got, cond

def test_a_frame_carries_the_line_and_the_readings_exactly():
    import numpy as np

    readings = np.array([1.5, np.nan, -0.0, 1e-300, 3.25])
    record, line, back = parse_frame(make_frame(b'{"cycle": 3, "t": 0.03}', readings))
    assert record == {"cycle": 3, "t": 0.03} and line == b'{"cycle": 3, "t": 0.03}'
    assert back.tobytes() == readings.tobytes()  # bit for bit, NaN and -0.0 included
    assert parse_frame(make_frame(b"{}", None))[2] is None
    # a msgpack record: read back as the same values (the line is the reader's to make)
    value = {"cycle": 3, "p_h1": -0.0, "n": 57, "x": 57.0, "ok": True, "none": None, "rules": {"k": [1, 2.5]}}
    packed = msgpack.packb(value, use_bin_type=True)
    record, line, back = parse_frame(make_frame(packed, readings, encoding=ENC_MSGPACK))
    assert line is None and back.tobytes() == readings.tobytes()
    assert dumpb(record) == dumpb(value) and math.copysign(1.0, record["p_h1"]) == -1.0
    assert type(record["n"]) is int and type(record["x"]) is float
    for bad in (b"", b"XXXX" + bytes(12), make_frame(b"{}", None)[:-1], make_frame(b"[1]", None),
                make_frame(b"{}", None, encoding=7), make_frame(packed[:-1], None, encoding=ENC_MSGPACK),
                make_frame(msgpack.packb([1, 2]), None, encoding=ENC_MSGPACK),
                make_frame(msgpack.packb({"a": msgpack.ExtType(5, b"x")}), None, encoding=ENC_MSGPACK),
                make_frame(packed + b"\x00", None, encoding=ENC_MSGPACK)):
        with pytest.raises(ValueError):
            parse_frame(bad)


def test_a_msgpack_record_with_keys_other_than_str_reads_back_as_its_line():
    """The centre's packer (strict types) takes a dict key of any plain type - int, bool, None,
    float, as JSON does, which writes them as strings; the bridge reads such a record back
    (msgpack's strict_map_key would refuse it: a whole frame lost for Zenoh and Foxglove, and
    the contact events' baseline left behind) and its line is the decision log's."""
    value = {"cycle": 5, "per_node": {1: 0.5, 2: -0.0}, "flags": {True: 1, None: 2, 1.5: 3}, "big": {2 ** 63: 1}}
    packed = msgpack.Packer(use_bin_type=True, strict_types=True).pack(value)
    record, line, _ = parse_frame(make_frame(packed, None, encoding=ENC_MSGPACK))
    assert line is None and dumpb(record) == dumpb(value)
    assert json.loads(dumpb(record))["per_node"] == {"1": 0.5, "2": -0.0}
    with pytest.raises(ValueError):  # a key msgpack cannot hash (an array): refused, one line
        parse_frame(make_frame(msgpack.packb({"a": {(1, 2): 3}}), None, encoding=ENC_MSGPACK))


def _timestamp_frames():
    """msgpack records holding msgpack's timestamp (ext -1) every way it is read: 32, 64 and 96-bit
    (fixext 4, fixext 8, ext 8), a non-minimal ext 16 / ext 32 of 8 bytes, in a list, as a map key."""
    import struct

    ts64 = msgpack.packb(msgpack.Timestamp(1, 5))[2:]
    raw = [msgpack.packb({"t": msgpack.Timestamp(1, 0)}), msgpack.packb({"t": msgpack.Timestamp(1, 5)}),
           msgpack.packb({"t": msgpack.Timestamp(2 ** 40, 5)}),
           b"\x81\xa1t\xc8\x00\x08\xff" + ts64, b"\x81\xa1t\xc9" + struct.pack(">I", 8) + b"\xff" + ts64,
           msgpack.packb({"cycle": 1, "rules": {"k": [1, msgpack.Timestamp(3, 0)]}}),
           msgpack.packb({"cycle": 1, "per_node": {msgpack.Timestamp(3, 0): 1}})]
    return [make_frame(packed, None, encoding=ENC_MSGPACK) for packed in raw]


def test_a_msgpack_timestamp_is_refused_at_decode():
    """msgpack's timestamp bypasses ext_hook (read as a msgpack.Timestamp whatever ``timestamp=``
    says): parse_frame refuses it as any other ext type - before, the record went on to dumpb and
    the encoders, which refused it later. Values whose bytes look like a timestamp's lead
    (0x04 0xff in a float, 0xd7 0xff in a string) still read back."""
    for frame in _timestamp_frames():
        with pytest.raises(ValueError, match="msgpack timestamp"):
            parse_frame(frame)
    import struct

    lookalike = {"x": struct.unpack(">d", b"\x3f\x04\xff\xd6\xff\x0c\xff\x01")[0], "s": "\u05ff", "b": -1,
                 "l": [-1, 4, -1, 8, -1, 12, -1], 4: -1}
    packed = msgpack.packb(lookalike, use_bin_type=True)
    assert b"\x04\xff" in packed and b"\x0c\xff" in packed  # the walk runs and finds nothing
    record, _, _ = parse_frame(make_frame(packed, None, encoding=ENC_MSGPACK))
    assert record == lookalike
    # as deep as unpackb reads (deeper than Python's recursion): walked all the same, no RecursionError
    deep = b"\x81\xa1d" + b"\x91" * 1000 + b"\x92\x04\xff"
    assert parse_frame(make_frame(deep, None, encoding=ENC_MSGPACK))[0]["d"] is not None
    with pytest.raises(ValueError, match="msgpack timestamp"):
        parse_frame(make_frame(b"\x81\xa1d" + b"\x91" * 1000 + msgpack.packb(msgpack.Timestamp(1, 0)), None,
                               encoding=ENC_MSGPACK))


def test_a_json_frame_nested_deeper_than_the_recursion_limit_is_a_bad_frame():
    """json.loads raises RecursionError on a record nested deep enough: refused as ValueError (the
    serve loop counts it bad and goes on) - before, it escaped the loop and ended the bridge."""
    deep = b"[" * 100_000 + b"]" * 100_000
    with pytest.raises(ValueError, match="nested too deep"):
        parse_frame(make_frame(deep, None, encoding=ENC_JSON))
    deep_object = b'{"a":' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    with pytest.raises(ValueError, match="nested too deep"):
        parse_frame(make_frame(deep_object, None, encoding=ENC_JSON))
    assert parse_frame(make_frame(b'{"a": ' + b"[" * 100 + b"]" * 100 + b"}", None, encoding=ENC_JSON))[0]["a"]


def test_a_bridge_counts_a_deeply_nested_json_frame_bad_and_takes_the_next():
    bridge = RoboticsBridge(load_scene("matrix57"), {"scene": "matrix57"}, foxglove=("127.0.0.1", 0)).open()
    try:
        bridge.sock.send(make_frame(b'{"a":' + b"[" * 100_000 + b"]" * 100_000 + b"}", None, encoding=ENC_JSON))
        bridge.sock.send(make_frame(json.dumps({"cycle": 2, "decision": "H0"}).encode(), None, encoding=ENC_JSON))
    finally:
        stats = bridge.close()
    b = stats["bridge"]
    assert (b["bad"], b["received"], b["died"]) == (1, 1, None)


def test_a_bridge_counts_a_timestamp_frame_bad_and_takes_the_next(tmp_path):
    """Through the bridge process: a frame holding a msgpack timestamp is counted ``bad`` (not
    received), the good frame after it goes through."""
    bridge = RoboticsBridge(load_scene("matrix57"), {"scene": "matrix57"}, foxglove=("127.0.0.1", 0)).open()
    try:
        bad = _timestamp_frames()[1]
        good = make_frame(msgpack.packb({"cycle": 2, "decision": "H0"}), None, encoding=ENC_MSGPACK)
        bridge.sock.send(bad)
        bridge.sock.send(good)
    finally:
        stats = bridge.close()
    b = stats["bridge"]
    assert (b["bad"], b["received"], b["died"]) == (1, 1, None)


def test_the_centre_hands_over_the_logs_line_else_a_msgpack_record_else_its_json(tmp_path):
    """What ``on_cycle`` puts in a frame: the decision log's line where the run has just written
    the record (no work), else the record as msgpack (plain types), else (a tuple, a numpy
    scalar: what msgpack's strict types refuse) its JSON line."""
    import socket

    import numpy as np

    from fusion_center.robotics.bridge_link import HEADER
    from fusion_center.service.records import RecordWriter

    scene = load_scene("matrix57")
    bridge = RoboticsBridge(scene, {"scene": "matrix57"})
    bridge.sock, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    bridge._flag = bytearray([1])  # the bridge's word: wanted
    plain = {"cycle": 1, "decision": "H1", "U_G": 6.14421235332821e-06, "p_h1": -0.0}
    logged = dict(plain, cycle=2)
    other = [dict(plain, cycle=3, rules=(1, 2)), dict(plain, cycle=4, U_G=np.float64(0.5))]
    writer = RecordWriter(tmp_path / "log.jsonl")
    try:
        bridge.on_cycle(plain)
        writer.write(logged)
        bridge.on_cycle(logged)
        for record in other:
            bridge.on_cycle(record)
        frames = [peer.recv(1 << 16) for _ in range(4)]
    finally:
        writer.close()
        bridge.sock.close()
        peer.close()
    encodings = [HEADER.unpack_from(f)[5] for f in frames]
    assert encodings == [ENC_MSGPACK, ENC_JSON, ENC_JSON, ENC_JSON]
    assert frames[1][HEADER.size:] == (tmp_path / "log.jsonl").read_bytes().rstrip(b"\n")
    assert msgpack.unpackb(frames[0][HEADER.size:]) == plain
    assert [parse_frame(f)[1] for f in frames[2:]] == [dumpb(r) for r in other]
    assert bridge.frames == 4 and bridge.failed == 0


def test_records_through_the_bridge_on_zenoh_are_the_decision_logs_lines():
    """Every record's payload on taxel/<scene>/record is the centre's decision-log line, byte for
    byte, in order; contact events as the in-process publisher makes them."""
    from fusion_center.service.zenoh_publisher import contact_event

    scene, cycles = _demo_cycles("matrix57", 30)
    port, = _ports(1)
    bridge = RoboticsBridge(scene, {"scene": "matrix57"}, zenoh={"listen": [f"tcp/127.0.0.1:{port}"]}).open()
    assert bridge.ready["zenoh"]["keys"]["record"] == "taxel/matrix57/record"
    peer = zenoh_peer(connect=port)
    sub, got, cond = _zenoh_subscriber(peer, "taxel/matrix57/*")
    try:
        first, closed0 = cycles[0]
        # the first record again and again until the subscriber has one (Zenoh's matching is the
        # bridge's to know), then the others once each
        end = time.monotonic() + TIMEOUT
        while not any(k.endswith("/record") for k, _ in got):
            assert time.monotonic() < end, "no record reached the subscriber"
            bridge.on_cycle(first, closed0)
            time.sleep(0.05)
        for record, closed in cycles[1:]:
            bridge.on_cycle(record, closed)
        with cond:
            cond.wait_for(lambda: sum(k.endswith("/record") for k, _ in got) >= len(cycles)
                          and [json.loads(p)["cycle"] for k, p in got if k.endswith("/record")][-1]
                          == cycles[-1][0]["cycle"], TIMEOUT)
    finally:
        stats = bridge.close()
        sub.undeclare()
        peer.close()
    records = [p for k, p in got if k.endswith("/record")]
    first_line = dumpb(first)
    rest = [p for p in records if p != first_line]
    assert set(records[:len(records) - len(rest)]) == {first_line}
    assert rest == [dumpb(r) for r, _ in cycles[1:]]
    contacts = [json.loads(p) for k, p in got if k.endswith("/contact")]
    expected, previous = [], None
    for k, (record, _) in enumerate(cycles):
        if k == 0 or record["decision"] != previous:
            expected.append(json.loads(dumpb(contact_event(record, None if k == 0 else previous))))
            previous = record["decision"]
    # the first record's event went out with the first probe, before the subscriber matched (or not)
    assert contacts in (expected, expected[1:]) and len(expected) >= 2
    b = stats["bridge"]
    assert b["frames"] == b["received"] and b["dropped"] == 0 and b["died"] is None and b["bad"] == 0
    assert stats["zenoh"]["records"] == len(records) and stats["zenoh"]["failed"] == 0


def test_the_foxglove_viewer_gets_the_in_process_messages_through_the_bridge():
    """Raw mode: the bridge's live server sends each cycle's messages - the taxel map, the
    readings image made from the readings the centre handed over, the JSON topics - byte for
    byte what the in-process encode path makes of the record."""
    from fusion_center.robotics.mcap_out import encode_plain
    from fusion_center.robotics.topics import TopicMap

    scene, cycles = _demo_cycles("matrix57_raw", 20)
    topics = TopicMap(scene)
    expected = {}
    for record, closed in cycles:
        t, messages = encode_plain(topics, record, topics.readings_of(closed))
        for topic, _, payload in messages:
            expected.setdefault(topic, []).append((t, payload))
    assert any("readings" in topic for topic in expected)
    bridge = RoboticsBridge(scene, {"scene": "matrix57_raw"}, foxglove=("127.0.0.1", 0)).open()
    port = bridge.ready["foxglove"]["port"]
    t0 = round(cycles[0][0]["t"] * 1e6) * 1000

    async def viewer():
        ws = await _connect(port)
        try:
            channels = await _advertised(ws)
            assert set(channels) == set(expected)
            subs = await _subscribe(ws, channels)
            got: dict = {}
            probing = True
            while True:
                if probing:  # the first cycle until the server sends it (the subscription arrived)
                    bridge.on_cycle(*cycles[0])
                try:
                    frame = await asyncio.wait_for(ws.recv(), 0.05 if probing else TIMEOUT)
                except asyncio.TimeoutError:
                    continue
                if not isinstance(frame, bytes):
                    continue
                sid, log_time, payload = _message_data(frame)
                if probing:
                    probing = False
                    for record, closed in cycles[1:]:
                        bridge.on_cycle(record, closed)
                if log_time != t0:
                    got.setdefault(subs[sid]["topic"], []).append((log_time, payload))
                if sum(map(len, got.values())) == (len(cycles) - 1) * len(subs):
                    return got
        finally:
            await ws.close()

    try:
        got = asyncio.run(asyncio.wait_for(viewer(), 4 * TIMEOUT))
    finally:
        stats = bridge.close()
    for topic, messages in expected.items():
        assert got[topic] == messages[1:], topic
    assert stats["foxglove"]["clients"] == 1 and stats["bridge"]["dropped"] == 0


class _SilentBridge(RoboticsBridge):
    """A bridge process that says ready and reads nothing until ``go`` exists; then it reads
    every frame left, parses each and reports how many it got."""

    def __init__(self, scene, go: Path):
        super().__init__(scene, {"scene": scene.name})
        self.go = go

    def command(self):
        code = ("import json, os, socket, sys, time\n"
                "from fusion_center.robotics.bridge_link import parse_frame\n"
                "s = socket.socket(fileno=int(sys.argv[1]))\n"
                "print(json.dumps({'ready': {}}), flush=True)\n"
                "parent = os.getppid()\n"
                "while not os.path.exists(sys.argv[2]) and os.getppid() == parent: time.sleep(0.01)\n"
                "n = bad = 0\n"
                "while True:\n"
                "    f = s.recv(1 << 24)\n"
                "    if not f: break\n"
                "    try: parse_frame(f); n += 1\n"
                "    except ValueError: bad += 1\n"
                "print(json.dumps({'stats': {}, 'received': n, 'bad': bad}), flush=True)\n")
        return [sys.executable, "-c", code, "{fd}", str(self.go), "{flag}"]


def test_a_bridge_that_does_not_read_loses_whole_frames_counted_and_never_holds_the_cycle(tmp_path):
    scene, cycles = _demo_cycles("matrix57", 5)
    bridge = _SilentBridge(scene, tmp_path / "go").open()
    n = 0
    try:
        while bridge.dropped < 100 and n < 200_000:  # ~1.5 kB a frame: 200,000 far more than the link holds
            record, closed = cycles[n % len(cycles)]
            bridge.on_cycle(record, closed)  # returns at once: the bridge reads nothing yet
            n += 1
        assert bridge.dropped > 0 and bridge.frames > 0 and bridge.frames + bridge.dropped == n
    finally:
        (tmp_path / "go").touch()
        stats = bridge.close()
    b = stats["bridge"]
    assert (b["received"], b["bad"], b["dropped"]) == (bridge.frames, 0, bridge.dropped)
    line, = bridge_lines(stats)
    assert f"{b['dropped']} dropped at the hand-over" in line[1]


def test_a_bridge_killed_mid_run_is_counted_once_and_the_cycles_go_on(caplog):
    scene, cycles = _demo_cycles("matrix57", 10)
    port, = _ports(1)
    bridge = RoboticsBridge(scene, {"scene": "matrix57"}, zenoh={"listen": [f"tcp/127.0.0.1:{port}"]}).open()
    for record, closed in cycles[:5]:
        bridge.on_cycle(record, closed)
    bridge.proc.kill()
    bridge.proc.wait(TIMEOUT)
    for record, closed in cycles[5:]:
        bridge.on_cycle(record, closed)  # never raises
    stats = bridge.close()
    b = stats["bridge"]
    # before it was killed each cycle was handed over or (nobody subscribed: the bridge said so) not made
    assert b["died"] and b["frames"] + b["unwanted"] == 5 and b["lost"] == 5 and "zenoh" not in stats
    assert len([r for r in caplog.records if "robotics bridge ended" in r.getMessage()]) == 1
    assert "ENDED mid-run" in bridge_lines(stats)[0][1]


def test_with_nobody_watching_the_centre_makes_no_frame_and_counts_the_cycles():
    """The bridge says nothing wants the cycles (no viewer): the centre makes no frame - the
    cycles are counted as the in-process server counts them (``with none subscribed``)."""
    scene, cycles = _demo_cycles("matrix57", 10)
    bridge = RoboticsBridge(scene, {"scene": "matrix57"}, foxglove=("127.0.0.1", 0)).open()
    n = 0
    try:
        end = time.monotonic() + TIMEOUT
        while bridge.wanted:  # until the bridge's first word arrives (a bound, not a timing claim)
            assert time.monotonic() < end, "the bridge never said whether anything is wanted"
            bridge.on_cycle(*cycles[n % len(cycles)])
            n += 1
            time.sleep(0.01)
        frames = bridge.frames
        for k in range(50):
            bridge.on_cycle(*cycles[k % len(cycles)])
        n += 50
        assert bridge.frames == frames and bridge.unwanted == n - frames
    finally:
        stats = bridge.close()
    assert stats["foxglove"]["unwatched_cycles"] == n and stats["foxglove"]["cycles"] == 0
    assert stats["bridge"]["unwanted"] == n - frames


def test_a_bridge_that_cannot_start_is_one_usage_error():
    scene = load_scene("matrix57")

    class Dies(RoboticsBridge):
        def command(self):
            return [sys.executable, "-c", "import sys; sys.exit(3)"]

    with pytest.raises(UsageError, match=r"ended before it was ready \(exit status 3"):
        Dies(scene, {"scene": "matrix57"}, zenoh={}).open()
    # a scene the bridge loads differently from the centre's: refused with one line
    with pytest.raises(UsageError, match="differs from the centre's") as err:
        RoboticsBridge(scene, {"scene": "matrix57", "mode": "raw"}, zenoh={}).open()
    assert "\n" not in str(err.value)


def test_a_bridge_that_hangs_at_its_start_is_stopped_and_named_so(monkeypatch):
    """No ready answer within the bound: the bridge is stopped (no process left) and the error
    says it hung - not that it ended by itself."""
    import fusion_center.robotics.bridge_link as link

    monkeypatch.setattr(link, "READY_TIMEOUT_S", 0.5)
    started = []

    class Hangs(RoboticsBridge):
        def command(self):
            return [sys.executable, "-c", f"import time; time.sleep({4 * TIMEOUT})"]

        def _read_line(self, timeout):
            started.append(self.proc)
            return super()._read_line(timeout)

    with pytest.raises(UsageError, match=r"gave no ready answer \(waited up to 0.5 s; stopped it") as err:
        Hangs(load_scene("matrix57"), {"scene": "matrix57"}, zenoh={}).open()
    assert "ended before" not in str(err.value)
    proc, = started
    assert proc.returncode is not None  # stopped and reaped: no process, no zombie


def test_the_bridge_imports_nothing_from_the_current_directory(tmp_path, monkeypatch):
    """A ``json.py`` in the directory the centre runs in (the user's data directory, a shared
    one) is not run by the bridge: it imports the project's code from where the centre did."""
    marker = tmp_path / "RAN"
    (tmp_path / "json.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    monkeypatch.chdir(tmp_path)
    bridge = RoboticsBridge(load_scene("matrix57"), {"scene": "matrix57"}, foxglove=("127.0.0.1", 0)).open()
    stats = bridge.close()
    assert not marker.exists(), "the bridge ran json.py from the current directory"
    assert stats["bridge"]["died"] is None and bridge.ready["foxglove"]["port"] > 0


def test_a_bridge_that_ends_at_its_start_is_named_so_with_its_status():
    """A bridge that exits before its ready line: 'ended before it was ready' with its status,
    never 'gave no ready answer' (the line's end of file is not the bound running out)."""
    for _ in range(5):  # the end of file may come before the process is reaped: each time the same
        class Dies(RoboticsBridge):
            def command(self):
                return [sys.executable, "-c", "import os, sys; sys.stdout.close(); os._exit(3)"]

        with pytest.raises(UsageError, match=r"ended before it was ready \(exit status 3"):
            Dies(load_scene("matrix57"), {"scene": "matrix57"}, zenoh={}).open()


def _cli(*argv, **kwargs):
    return subprocess.Popen([sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())",
                             *argv], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, **kwargs)


def _bridge_of(pid: int) -> int:
    """The pid of the bridge process the centre ``pid`` started."""
    found = []

    def look():
        try:
            children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
        except OSError:
            return False
        for child in children:
            try:
                if "fusion_center.robotics.bridge" in Path(f"/proc/{child}/cmdline").read_text():
                    found.append(int(child))
                    return True
            except OSError:
                continue
        return False

    _wait(look, "the bridge process")
    return found[0]


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def test_killing_the_centre_ends_the_bridge():
    port, = _ports(1)
    centre = _cli("demo", "--cycles", "100000", "--no-live", "--zenoh", "--zenoh-listen", f"tcp/127.0.0.1:{port}")
    try:
        bridge = _bridge_of(centre.pid)
        assert _alive(bridge)
        centre.kill()
        centre.wait(TIMEOUT)
        _wait(lambda: not _alive(bridge), "the bridge to end after the centre was killed")
    finally:
        if centre.poll() is None:
            centre.kill()
        centre.communicate()


def test_ctrl_c_on_the_terminal_leaves_the_bridge_to_the_centres_last_record(tmp_path):
    """SIGINT to the centre's whole process group (what a terminal's Ctrl-C does): the bridge is
    in a session of its own and ignores SIGINT; the centre ends its run, then the bridge reports
    every cycle it was handed."""
    port, = _ports(1)
    log = tmp_path / "run.jsonl"
    centre = _cli("demo", "--cycles", "100000", "--no-live", "--zenoh", "--zenoh-listen", f"tcp/127.0.0.1:{port}",
                  "--json-lines", str(log))
    try:
        bridge = _bridge_of(centre.pid)
        _wait(lambda: log.exists() and log.read_text().count("\n") >= 5, "some cycles")
        os.killpg(centre.pid, signal.SIGINT)
        out, err = centre.communicate(timeout=4 * TIMEOUT)
    finally:
        if centre.poll() is None:
            centre.kill()
            centre.communicate()
    assert centre.returncode == 130, err
    lines = {line.split(":", 1)[0]: line for line in out.splitlines()}
    records = int(lines["cycles"].split(",")[1].split()[0])
    import re

    handed, dropped = map(int, re.search(r"(\d+) cycles handed over, (\d+) dropped", lines["bridge"]).groups())
    unwanted = re.search(r"(\d+) not made", lines["bridge"])
    assert records > 0 and handed + dropped + int(unwanted.group(1) if unwanted else 0) == records
    assert dropped == 0 and "ENDED" not in lines["bridge"]
    assert f"{records} with no subscriber" in lines["zenoh"]
    assert not _alive(bridge)


class _DropNext:
    """The centre's end of the link with one send made to fail as a full buffer does
    (``BlockingIOError``: the bridge behind) when ``drop`` is set."""

    def __init__(self, sock):
        self.sock = sock
        self.drop = False

    def send(self, frame):
        if self.drop:
            self.drop = False
            raise BlockingIOError(11, "Resource temporarily unavailable")
        return self.sock.send(frame)

    def close(self):
        self.sock.close()


def _in_process_events(records):
    """The contact events the in-process publisher makes of ``records`` (zenoh_publisher's rule:
    the first record, then each change of the decision against the record before)."""
    from fusion_center.service.zenoh_publisher import contact_event

    out, previous = [], None
    for k, record in enumerate(records):
        if k == 0 or record["decision"] != previous:
            out.append(json.loads(dumpb(contact_event(record, None if k == 0 else previous))))
            previous = record["decision"]
    return out


def test_a_change_whose_frame_was_dropped_still_reaches_the_contact_subscriber():
    """The frame of a decision change is dropped at the hand-over (the bridge behind) while a
    subscriber watches: the change is not lost - the next frame, whose decision is the same,
    carries it (event against the last decision the subscriber was told), as if the dropped
    cycle had not been there; the subscriber's view of the contact never stays stale."""
    scene, cycles = _demo_cycles("matrix57", 30)
    decisions = [r["decision"] for r, _ in cycles]
    k = next((i for i in range(1, len(cycles) - 1)
              if decisions[i] != decisions[i - 1] and decisions[i + 1] == decisions[i]), None)
    assert k is not None, f"no change held for two cycles in {decisions}"
    port, = _ports(1)
    bridge = RoboticsBridge(scene, {"scene": "matrix57"}, zenoh={"listen": [f"tcp/127.0.0.1:{port}"]}).open()
    peer = zenoh_peer(connect=port)
    sub, got, cond = _zenoh_subscriber(peer, "taxel/matrix57/*")
    try:
        end = time.monotonic() + TIMEOUT
        while not any(key.endswith("/record") for key, _ in got):
            assert time.monotonic() < end, "no record reached the subscriber"
            bridge.on_cycle(*cycles[0])
            time.sleep(0.05)
        link = bridge.sock = _DropNext(bridge.sock)
        for i, (record, closed) in enumerate(cycles[1:], start=1):
            link.drop = i == k
            bridge.on_cycle(record, closed)
        with cond:
            cond.wait_for(lambda: [json.loads(p)["cycle"] for key, p in got if key.endswith("/record")][-1]
                          == cycles[-1][0]["cycle"], TIMEOUT)
    finally:
        stats = bridge.close()
        sub.undeclare()
        peer.close()
    assert stats["bridge"]["dropped"] == 1 and stats["bridge"]["died"] is None
    contacts = [json.loads(p) for key, p in got if key.endswith("/contact")]
    # what the in-process publisher makes of the cycles the bridge got (all but the dropped one)
    expected = _in_process_events([r for i, (r, _) in enumerate(cycles) if i != k])
    assert contacts in (expected, expected[1:])
    late = [e for e in contacts if e["cycle"] == cycles[k + 1][0]["cycle"]]
    assert [(e["decision"], e["previous"]) for e in late] == [(decisions[k], decisions[k - 1])]


# a centre of the test's own (a process the test can SIGKILL) whose bridge is slow to start: the real
# bridge's main(), with the scene's loading made to wait (a marker file says the bridge got there)
_SLOW_CENTRE = """
import sys
sys.path.insert(0, {root!r})
from fusion_center.robotics.bridge_link import RoboticsBridge
from taxel_net.scene import load_scene

SLOW = ("import time, fusion_center.robotics.bridge as b; load = b.load_scene_of; "
        "b.load_scene_of = lambda s: (open({marker!r}, 'w').close(), time.sleep({sleep!r}), load(s))[2]; main = b.main")


class SlowStart(RoboticsBridge):
    def command(self):
        argv = super().command()
        argv[2] = argv[2].replace("from fusion_center.robotics.bridge import main", SLOW)
        return argv


SlowStart(load_scene("matrix57"), {{"scene": "matrix57"}}, foxglove=("127.0.0.1", 0)).open()
"""


def _slow_centre(tmp_path):
    marker = tmp_path / "bridge-starting"
    script = tmp_path / "centre.py"
    script.write_text(_SLOW_CENTRE.format(root=str(ROOT), marker=str(marker), sleep=4 * TIMEOUT))
    centre = subprocess.Popen([sys.executable, str(script)], cwd=tmp_path, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True, start_new_session=True)
    return centre, marker


def test_killing_the_centre_while_its_bridge_starts_ends_the_bridge(tmp_path):
    """SIGKILL to the centre while the bridge is still starting (its link is not read yet): the
    bridge ends with it (the parent-death signal, SIGTERM) - not when its start is over."""
    centre, marker = _slow_centre(tmp_path)
    bridge = None
    try:
        bridge = _bridge_of(centre.pid)
        _wait(marker.exists, "the bridge to be starting")
        assert _alive(bridge)
        centre.kill()
        centre.wait(TIMEOUT)
        _wait(lambda: not _alive(bridge), "the bridge to end after the centre was killed in its start")
    finally:
        if centre.poll() is None:
            centre.kill()
        if bridge is not None and _alive(bridge):  # it holds the centre's stderr
            os.kill(bridge, signal.SIGKILL)
        centre.communicate()


def test_a_bridge_whose_centre_is_gone_before_it_asks_for_the_signal_exits_at_once():
    """The race: the centre ends before the bridge's first act - its parent is no longer the pid
    it was given, so it exits (143, as SIGTERM's) instead of starting."""

    ended = subprocess.Popen([sys.executable, "-c", ""])  # a pid that is not the test's (pid 1 may be: docker)
    ended.wait()

    class Orphan(RoboticsBridge):
        def command(self):
            argv = super().command()
            argv[argv.index("--parent-pid") + 1] = str(ended.pid)  # not its parent: as if the centre had ended
            return argv

    with pytest.raises(UsageError, match=r"ended before it was ready \(exit status 143"):
        Orphan(load_scene("matrix57"), {"scene": "matrix57"}, foxglove=("127.0.0.1", 0)).open()


def test_sigterm_ends_a_ready_bridge_cleanly_at_a_frames_boundary():
    """SIGTERM (the parent-death signal, a user's kill) after the ready line: the bridge publishes
    the frames it was handed, closes its outputs and prints its counters - as when the link closes."""
    scene, cycles = _demo_cycles("matrix57", 3)
    bridge = RoboticsBridge(scene, {"scene": "matrix57"}, foxglove=("127.0.0.1", 0)).open()
    try:
        for record, closed in cycles:
            bridge._flag[0] = 1  # as if a viewer were subscribed (the bridge may say otherwise any time)
            bridge.on_cycle(record, closed)
        bridge.proc.send_signal(signal.SIGTERM)
        bridge.proc.wait(TIMEOUT)
    finally:
        stats = bridge.close()
    b = stats["bridge"]
    assert b["died"] is None and b["frames"] + b["unwanted"] == 3 and b["frames"] > 0
    assert b["received"] == b["frames"] and b["bad"] == 0 and "foxglove" in stats


def test_a_bridge_started_from_a_thread_that_ends_lives_on():
    """The parent-death signal follows the thread that started the bridge: from a thread other
    than the main one the centre does not ask for it (no ``--parent-pid``), so the bridge outlives
    that thread and takes the cycles handed after it ended."""
    scene, cycles = _demo_cycles("matrix57", 2)
    opened = []
    starter = threading.Thread(target=lambda: opened.append(
        RoboticsBridge(scene, {"scene": "matrix57"}, foxglove=("127.0.0.1", 0)).open()))
    starter.start()
    starter.join()
    _wait(lambda: not Path(f"/proc/self/task/{starter.native_id}").exists(), "the starting thread's end")
    bridge, = opened
    try:
        args = bridge.proc.args
        for record, closed in cycles:
            bridge._flag[0] = 1
            bridge.on_cycle(record, closed)
    finally:
        stats = bridge.close()
    b = stats["bridge"]
    assert b["died"] is None and b["frames"] > 0 and b["received"] == b["frames"] and b["lost"] == 0
    assert "--parent-pid" not in args
    assert "--parent-pid" in RoboticsBridge(scene, {"scene": "matrix57"}, foxglove=("127.0.0.1", 0)).command()


@pytest.mark.parametrize("value", ["0", "-1", " 123 ", "1_0", "\u0661\u0662", "+12", "99999999999999999999",
                                   "4194305", "abc", ""])
def test_a_parent_pid_that_is_no_pid_is_refused_in_one_line(value, capsys):
    """``--parent-pid``: ASCII digits, 1 .. pid_max - 1 - not what int() also takes (blanks, ``_``,
    other scripts' digits, a sign); one line naming the option, the value and what is allowed, exit 2."""
    from fusion_center.robotics.bridge import main, pid_max

    assert main(["--fd", "99", "--flag-fd", "98", "--settings", "{}", "--parent-pid", value]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"robotics bridge: --parent-pid {value!r}: expected a process id, "
                                                   f"ASCII digits 1..{pid_max() - 1}"), err


def test_the_bridges_options_are_not_abbreviated(capsys):
    from fusion_center.robotics.bridge import main, parent_pid_of, pid_max

    with pytest.raises(SystemExit) as exited:
        main(["--fd", "99", "--flag-fd", "98", "--settings", "{}", f"--parent={os.getpid()}"])
    assert exited.value.code == 2 and "unrecognized arguments: --parent=" in capsys.readouterr().err
    assert parent_pid_of(str(os.getpid())) == os.getpid() and parent_pid_of(str(pid_max() - 1)) == pid_max() - 1
    assert parent_pid_of(str(pid_max())) is None


def test_pid_max_falls_back_where_proc_cannot_say(monkeypatch):
    import builtins

    from fusion_center.robotics import bridge

    real_open = builtins.open

    def no_proc(path, *args, **kwargs):
        if str(path).startswith("/proc/sys/kernel/pid_max"):
            raise FileNotFoundError(path)
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", no_proc)
    assert bridge.pid_max() == bridge.PID_MAX_FALLBACK == 4194304


# the real bridge's main(), a blocking C call patched in (a default pthread mutex locked twice: ctypes lets
# the interpreter lock go, and Python's signal handlers cannot run on the main thread meanwhile); the marker
# file (written whole, by a rename) names the mutex's address: the futex word the main thread then waits on.
# With grace_on_marker the grace (TERM_GRACE_S, its sleep) waits for the marker instead of a time: the
# grace's end (its line, os._exit(143)) comes only once the main thread reached the blocking call
_BLOCKED = """
import ctypes, os, time
import fusion_center.robotics.bridge as b
libc = ctypes.CDLL(None)
mutex = ctypes.create_string_buffer(64)
marker = {marker!r}

def blocked(*args):
    with open(marker + ".tmp", "w") as f:
        f.write(str(ctypes.addressof(mutex)))
    os.replace(marker + ".tmp", marker)
    libc.pthread_mutex_lock(mutex)
    libc.pthread_mutex_lock(mutex)

b.Bridge.{method} = blocked
b.TERM_GRACE_S = {grace!r}
if {grace_on_marker!r}:
    real_grace = b._TermWatch._grace

    def grace_on_marker():
        while not os.path.exists(marker):
            time.sleep(0.01)
        b.TERM_GRACE_S = 0.0
        real_grace()

    b._TermWatch._grace = staticmethod(grace_on_marker)
main = b.main
"""


def _blocked_bridge(tmp_path, method: str, grace: float, grace_on_marker: bool = False):
    marker = tmp_path / "blocked"
    code = "exec(" + repr(_BLOCKED.format(grace=grace, marker=str(marker), method=method,
                                          grace_on_marker=grace_on_marker)) + ")"

    class Blocked(RoboticsBridge):
        def command(self):
            argv = super().command()
            argv[2] = argv[2].replace("from fusion_center.robotics.bridge import main", code)
            return argv

    return Blocked(load_scene("matrix57"), {"scene": "matrix57"}, foxglove=("127.0.0.1", 0)).open(), marker


def _blocked_in_the_c_call(pid: int, marker) -> bool:
    """The main thread of ``pid`` waits in a system call on the mutex named by ``marker`` (its futex
    word: the syscall's first argument; /proc/PID/task/PID/syscall, 'running' when not in one)."""
    if not marker.exists():
        return False
    fields = Path(f"/proc/{pid}/task/{pid}/syscall").read_text().split()
    return len(fields) > 1 and fields[0] != "running" and int(fields[1], 16) == int(marker.read_text())


def test_a_second_sigterm_ends_a_bridge_blocked_in_a_c_call(tmp_path):
    """After the ready line, the main thread blocked in a C call (serving: a Zenoh put held up):
    Python's handler cannot run - before, SIGTERM then did nothing, a second one neither. Now the
    watcher thread woken by the signal's wakeup fd shuts the link down at the first, and a second
    SIGTERM exits the bridge (143) at once. The first SIGTERM goes only once the main thread waits
    on the mutex (a SIGTERM before, between the marker and the call, lets the Python handler run:
    SIGTERM's default action back, a second one kills by signal, status -15 - see the docs)."""
    bridge, marker = _blocked_bridge(tmp_path, "serve", grace=1e6)
    try:
        _wait(lambda: _blocked_in_the_c_call(bridge.proc.pid, marker), "the bridge to block in its serve loop")
        bridge.proc.send_signal(signal.SIGTERM)
        _wait(lambda: bridge.sock.recv(1) == b"" if _readable(bridge.sock) else False,
              "the bridge to shut its end of the link down")
        assert bridge.proc.poll() is None  # the grace (here a long one) goes on
        bridge.proc.send_signal(signal.SIGTERM)
        assert bridge.proc.wait(TIMEOUT) == 128 + signal.SIGTERM
    finally:
        stats = bridge.close()
    assert "no report at its end (exit status 143)" in stats["bridge"]["died"]


def test_a_bridge_whose_clean_end_blocks_after_sigterm_exits_after_the_grace(tmp_path):
    """SIGTERM, the link shut down, the clean end blocked in a C call (an output's close): the
    bridge exits 143 once TERM_GRACE_S is over, without a second signal. The grace's sleep is
    patched to wait for the marker (the clean end got to ``Bridge.stats``) - no time bound decides
    the outcome (before, a 0.2 s grace: a main thread slower than that to reach stats failed it)."""
    bridge, marker = _blocked_bridge(tmp_path, "stats", grace=1e6, grace_on_marker=True)
    try:
        bridge.proc.send_signal(signal.SIGTERM)
        assert bridge.proc.wait(TIMEOUT) == 128 + signal.SIGTERM
        assert marker.exists()  # it got to its clean end
    finally:
        stats = bridge.close()
    assert "no report at its end (exit status 143)" in stats["bridge"]["died"]


# the watcher of the real bridge, a SIGTERM sent to the process the moment the Python handler is installed
# (the latest it may come once signal.signal returned); the link's far end says whether it was shut down
_TERM_AT_HANDLER = """
import os, signal, socket
import fusion_center.robotics.bridge as b
real = signal.signal
def installed_then_term(signum, handler):
    old = real(signum, handler)
    if signum == signal.SIGTERM and callable(handler):
        os.kill(os.getpid(), signal.SIGTERM)
    return old
signal.signal = installed_then_term
ours, theirs = socket.socketpair()
watch = b._TermWatch(theirs)
print("shut" if ours.recv(1) == b"" else "data", watch.terms, flush=True)
"""


def test_a_sigterm_as_soon_as_the_handler_is_installed_wakes_the_watcher():
    """_TermWatch sets the wakeup fd and starts its watcher before it installs the Python handler:
    a SIGTERM once the handler is in place (the C handler writes its number to the wakeup fd,
    the Python handler gives SIGTERM its default action back) shuts the link down. Before, the
    handler came first: a SIGTERM between it and set_wakeup_fd woke nobody, the link was never
    shut, the bridge went on as if no SIGTERM had come (the subprocess blocked in its recv: the
    timeout only guards against that hang)."""
    try:
        out = subprocess.run([sys.executable, "-c", _TERM_AT_HANDLER], capture_output=True, text=True,
                             timeout=TIMEOUT, cwd=Path(__file__).resolve().parents[1])
    except subprocess.TimeoutExpired:
        pytest.fail("the SIGTERM woke no watcher: the link was never shut down")
    assert (out.returncode, out.stdout.split()) == (0, ["shut", "1"]), out.stderr


def _readable(sock) -> bool:
    import select

    return bool(select.select([sock], [], [], 0)[0])
