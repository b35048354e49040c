"""``--foxglove``: the live Foxglove WebSocket server, through a WebSocket client of the test's own
(python ``websockets``) speaking the SDK's subprotocol ``foxglove.sdk.v1``: advertise, subscribe,
messages equal to the records; a stalled viewer loses messages, never cycles; loopback only."""

from __future__ import annotations

import asyncio
import json
import struct
import sys
import threading
import time
from pathlib import Path

import pytest

from fusion_center.cli import main
from fusion_center.robotics import foxglove_live
from fusion_center.robotics.outputs import RoboticsOutputs
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from robotics_helpers import decode_raw_image, image_array, read_mcap  # noqa: E402

SUBPROTOCOL = "foxglove.sdk.v1"
TIMEOUT = 30.0  # seconds any single wait may take (a bound, not a speed assertion)


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    from fusion_center.commands.demo import run_demo

    scene = load_scene("matrix57")
    service, _ = run_demo(scene, 40, keep_records=True)
    return scene, list(service.records)


async def _connect(port: int):
    from websockets.asyncio.client import connect

    return await connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None,
                         open_timeout=TIMEOUT)


async def _advertised(ws) -> dict:
    """topic -> channel of the server's advertise (after its serverInfo)."""
    channels: dict = {}
    info = json.loads(await asyncio.wait_for(ws.recv(), TIMEOUT))
    assert info["op"] == "serverInfo"
    while True:
        msg = json.loads(await asyncio.wait_for(ws.recv(), TIMEOUT))
        if msg["op"] == "advertise":
            channels.update({c["topic"]: c for c in msg["channels"]})
            return channels


async def _subscribe(ws, channels: dict) -> dict:
    subs = {k + 1: c for k, c in enumerate(channels.values())}
    await ws.send(json.dumps({"op": "subscribe",
                              "subscriptions": [{"id": sid, "channelId": c["id"]} for sid, c in subs.items()]}))
    return subs


def _wait(predicate) -> None:
    end = time.monotonic() + TIMEOUT
    while not predicate():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.01)


def _message_data(frame: bytes) -> tuple[int, int, bytes]:
    assert frame[0] == 0x01  # MessageData
    sid, log_time = struct.unpack_from("<IQ", frame, 1)
    return sid, log_time, frame[13:]


async def _publish_and_receive(ws, channels: dict, outputs, recs) -> dict[str, list]:
    """Subscribe to every channel, wait until the server has the subscriptions, publish ``recs``
    and read back every message: topic -> [(log time, payload)] in the order received."""
    subs = await _subscribe(ws, channels)
    await asyncio.to_thread(_wait, lambda: len(outputs.live.listener.active) == len(subs))
    for record in recs:
        outputs.on_cycle(record)
    got: dict[str, list] = {}
    while sum(map(len, got.values())) < len(recs) * len(subs):
        frame = await asyncio.wait_for(ws.recv(), TIMEOUT)
        if isinstance(frame, bytes):
            sid, log_time, payload = _message_data(frame)
            got.setdefault(subs[sid]["topic"], []).append((log_time, payload))
    return got


def test_advertise_subscribe_and_the_messages_are_the_records(records):
    scene, recs = records
    outputs = RoboticsOutputs(scene, foxglove=("127.0.0.1", 0), threaded=True)
    live = outputs.live
    assert live.host == "127.0.0.1"

    async def viewer():
        ws = await _connect(live.port)
        try:
            assert ws.subprotocol == SUBPROTOCOL
            channels = await _advertised(ws)
            assert set(channels) == {"/taxel/sensor/map", "/fusion/decision", "/bus", "/fusion/contact"}
            assert channels["/taxel/sensor/map"]["schemaName"] == "foxglove.RawImage"
            assert channels["/taxel/sensor/map"]["encoding"] == "protobuf"
            assert channels["/fusion/decision"]["encoding"] == "json"
            assert channels["/fusion/decision"]["schemaEncoding"] == "jsonschema"
            assert json.loads(channels["/fusion/decision"]["schema"])["title"] == "taxel_can.Decision"
            return await _publish_and_receive(ws, channels, outputs, recs)
        finally:
            await ws.close()

    try:
        got = asyncio.run(viewer())
    finally:
        stats = outputs.close()
    times = [round(r["t"] * 1e6) * 1000 for r in recs]
    for topic, messages in got.items():
        assert [t for t, _ in messages] == times, topic
    for record, (_, d), (_, b), (_, img) in zip(recs, got["/fusion/decision"], got["/bus"], got["/taxel/sensor/map"]):
        d, b = json.loads(d), json.loads(b)
        for key in ("cycle", "decision", "U_G", "threshold", "p_h1", "truth", "present_count"):
            assert d[key] == record[key]
        assert d["rules"] == {k.replace("-", "_"): v for k, v in record["rules"].items()}
        assert (b["closed_by"], b["closed_after_ms"], b["late_frames"]) == (
            record["closed_by"], record["closed_after_ms"], record["late_frames"])
        grid = image_array(decode_raw_image(img))
        assert int((grid == 255).sum()) == len({(scene.taxels[i].x, scene.taxels[i].y) for i, t in
                                                enumerate(scene.taxels) if t.node_id in record["present_nodes"]})
    assert stats["foxglove"]["cycles"] == len(recs) and stats["foxglove"]["dropped_cycles"] == 0
    assert stats["foxglove"]["clients"] == 1


def test_the_viewer_gets_the_mcap_files_messages_byte_for_byte(records, tmp_path):
    """With --mcap and --foxglove both on, each cycle is encoded once and the same bytes go to
    both sinks: every message a subscribed viewer receives equals the file's, topic by topic, in
    order, with the same log time."""
    scene, recs = records
    outputs = RoboticsOutputs(scene, foxglove=("127.0.0.1", 0), mcap=tmp_path / "both.mcap", threaded=True)
    live = outputs.live

    async def viewer():
        ws = await _connect(live.port)
        try:
            return await _publish_and_receive(ws, await _advertised(ws), outputs, recs)
        finally:
            await ws.close()

    try:
        got = asyncio.run(viewer())
    finally:
        outputs.close()
    _, in_file = read_mcap(tmp_path / "both.mcap")
    assert set(got) == set(in_file)
    for topic, messages in got.items():
        assert len(messages) == len(recs), topic
        assert messages == [(log_time, payload) for log_time, _, payload in in_file[topic]], topic


def test_a_stalled_viewer_loses_messages_not_cycles(records, tmp_path, monkeypatch):
    """The viewer subscribes and stops reading: every cycle still reaches the MCAP file and the
    SDK (none skipped in front of it); the viewer, reading again, has lost messages."""
    monkeypatch.setattr(foxglove_live, "CLIENT_BACKLOG", 8)
    scene, recs = records
    cycles = 4000
    outputs = RoboticsOutputs(scene, foxglove=("127.0.0.1", 0), mcap=tmp_path / "stall.mcap", threaded=True)
    live = outputs.live

    async def viewer():
        ws = await _connect(live.port)
        try:
            subs = await _subscribe(ws, await _advertised(ws))
            await asyncio.to_thread(_wait, lambda: len(live.listener.active) == len(subs))
            for k in range(cycles):  # the viewer reads nothing meanwhile
                outputs.on_cycle({**recs[k % len(recs)], "cycle": k, "t": 0.01 * k})
                if k % 50 == 49:  # a run's pace: the publisher never more than 50 cycles behind
                    await asyncio.to_thread(_wait, lambda: not outputs._queue)
            await asyncio.to_thread(_wait, lambda: not outputs._queue and live.cycles == cycles)
            received = 0
            try:
                while True:
                    frame = await asyncio.wait_for(ws.recv(), 2.0)
                    received += isinstance(frame, bytes)
            except asyncio.TimeoutError:
                pass
            return received, len(subs)
        finally:
            await ws.close()

    try:
        received, n_subs = asyncio.run(viewer())
    finally:
        stats = outputs.close()
    assert stats["foxglove"]["cycles"] == cycles and stats["foxglove"]["dropped_cycles"] == 0
    assert stats["mcap"]["cycles"] == cycles
    assert received < cycles * n_subs  # the stalled viewer lost messages in the SDK's outbox

    _, by_topic = read_mcap(tmp_path / "stall.mcap")
    assert len(by_topic["/fusion/decision"]) == cycles


def test_a_publisher_behind_skips_the_oldest_cycles_for_the_server_only(records, tmp_path, monkeypatch):
    """More than LIVE_BACKLOG cycles waiting: the oldest are skipped for the live server and
    counted; the MCAP file gets them all."""
    monkeypatch.setattr(foxglove_live, "LIVE_BACKLOG", 5)
    scene, recs = records
    outputs = RoboticsOutputs(scene, foxglove=("127.0.0.1", 0), mcap=tmp_path / "behind.mcap")
    outputs._queue.extend((r, None) for r in recs[:20])  # as the threaded callback queues them
    outputs._drain()
    stats = outputs.close()
    assert stats["foxglove"]["dropped_cycles"] == 15
    assert stats["mcap"]["cycles"] == 20


def test_listen_address_defaults_to_loopback_and_bad_ones_are_one_line(tmp_path, capsys):
    assert foxglove_live.parse_listen("8765") == ("127.0.0.1", 8765)
    assert foxglove_live.parse_listen("0.0.0.0:8765") == ("0.0.0.0", 8765)
    assert foxglove_live.parse_listen("[::1]:9") == ("::1", 9)
    assert main(["demo", "--foxglove", "http", "--cycles", "2", "--no-live"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--foxglove 'http'" in err


def test_a_port_in_use_is_one_line(capsys):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["demo", "--foxglove", str(port), "--cycles", "2", "--no-live"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "cannot listen" in err


def test_demo_with_foxglove_names_the_server_in_its_summary(capsys):
    assert main(["demo", "--cycles", "5", "--foxglove", "0", "--no-live"]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("foxglove:")]
    assert len(line) == 1 and "ws://127.0.0.1:" in line[0] and "0 client(s)" in line[0]
    assert "5 with none subscribed" in line[0]


def test_close_wakes_the_publisher_at_once(monkeypatch):
    """close() ends the publisher's wait between bursts, however long its period: with a period
    of an hour, close() returns (bounded here at 60 s, a hang guard) - a plain sleep held it
    up to one period."""
    from fusion_center.robotics import outputs as outputs_mod

    monkeypatch.setattr(outputs_mod, "POLL_S", 3600.0)
    scene = load_scene("matrix57")
    outputs = RoboticsOutputs(scene, mcap=None, foxglove=None, ros2_bag=None, threaded=True)
    time.sleep(0.05)  # the publisher is in its wait
    done = threading.Event()
    closer = threading.Thread(target=lambda: (outputs.close(), done.set()), daemon=True)
    closer.start()
    assert done.wait(60.0), "close() did not wake the publisher"
