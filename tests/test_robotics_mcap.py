"""``--mcap``: every cycle as Foxglove messages in an MCAP file, read back with the ``mcap``
package's reader (not the SDK that wrote it) and checked against the decision log's records;
a replay's MCAP equals the live run's byte for byte; output paths (issue 24, docs/robotics.md)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from fusion_center.cli import main
from fusion_center.robotics.outputs import RoboticsOutputs
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from robotics_helpers import decode_raw_image, image_array, publish, read_mcap, site_grid  # noqa: E402

DECISION_CODE = {"H1": 1, "H0": 0, "undecided": -1}


@pytest.fixture(scope="module")
def matrix57_run(tmp_path_factory):
    """A 200-cycle matrix57 demo with --mcap (threaded publisher, as `demo --mcap`) and --log."""
    from fusion_center.commands.demo import run_demo

    out = tmp_path_factory.mktemp("m57")
    scene = load_scene("matrix57")
    outputs = RoboticsOutputs(scene, mcap=out / "run.mcap", threaded=True)
    service, summary = run_demo(scene, 200, trace=out / "run.log", json_lines=out / "run.jsonl",
                                keep_records=True, outputs=outputs)
    return out, scene, list(service.records), summary


def test_a_200_cycle_matrix57_run_reads_back_complete(matrix57_run):
    out, scene, records, summary = matrix57_run
    assert len(records) == 200 and summary["robotics"]["mcap"]["cycles"] == 200
    mcap_summary, by_topic = read_mcap(out / "run.mcap")
    topics = {ch.topic: ch for ch in mcap_summary.channels.values()}
    expected = {"/taxel/sensor/map": ("foxglove.RawImage", "protobuf", "protobuf"),
                "/fusion/decision": ("taxel_can.Decision", "jsonschema", "json"),
                "/fusion/contact": ("taxel_can.Contact", "jsonschema", "json"),
                "/bus": ("taxel_can.Bus", "jsonschema", "json")}
    assert set(topics) == set(expected)
    for topic, (schema_name, schema_encoding, encoding) in expected.items():
        channel = topics[topic]
        schema = mcap_summary.schemas[channel.schema_id]
        assert (schema.name, schema.encoding, channel.message_encoding) == (schema_name, schema_encoding, encoding)
        if schema_encoding == "jsonschema":
            assert json.loads(schema.data)["type"] == "object"
        # every cycle, every channel, in cycle order, log time = the cycle's SYNC time
        assert mcap_summary.statistics.channel_message_counts[channel.id] == 200
        times = [log for log, _, _ in by_topic[topic]]
        assert times == [round(r["t"] * 1e6) * 1000 for r in records]
        assert all(pub == log for log, pub, _ in by_topic[topic])
    assert mcap_summary.statistics.message_count == 200 * len(expected)


def test_decoded_values_equal_the_decision_log(matrix57_run):
    out, scene, records, _ = matrix57_run
    logged = [json.loads(line) for line in open(out / "run.jsonl")]
    assert logged == records
    _, by_topic = read_mcap(out / "run.mcap")
    assert "/world/truth" not in by_topic  # matrix57 has no grasp world: the truth is in /fusion/decision
    for record, (_, _, d), (_, _, b), (_, _, c) in zip(
            records, by_topic["/fusion/decision"], by_topic["/bus"], by_topic["/fusion/contact"]):
        d, b, c = (json.loads(x) for x in (d, b, c))
        assert d["cycle"] == record["cycle"]
        for key in ("decide_with", "decision", "U_G", "threshold", "p_h1", "present_count", "n_received",
                    "n_expected", "degraded", "truth"):
            assert d[key] == record[key], key
        assert d["decision_code"] == DECISION_CODE[record["decision"]]
        if record["U_G"] is None:  # undecided: no rule ran
            assert d["margin"] is None and record["decision"] == "undecided"
        else:
            assert d["margin"] == pytest.approx(record["U_G"] - record["threshold"])
        assert set(d["rules"]) == {name.replace("-", "_") for name in record["rules"]}
        for name, result in record["rules"].items():
            assert d["rules"][name.replace("-", "_")] == result
            assert d["rule_decisions"][name.replace("-", "_")] == DECISION_CODE[result["decision"]]
        for key in ("closed_by", "closed_after_ms", "n_live", "late_frames", "bad_frames", "sync_counter"):
            assert b[key] == record[key], key
        assert b["nodes_by_state"] == record["nodes_by_state"]
        for key in ("area", "t_c", "contact_type", "fp_c", "contact_type_fp"):
            assert c.get(key) == record.get(key)
        assert "area" in c
        assert d["truth_code"] == {"H1": 1, "H0": 0}[record["truth"]]


def test_the_taxel_map_shows_the_present_taxels_at_their_sites(matrix57_run):
    out, scene, records, _ = matrix57_run
    _, by_topic = read_mcap(out / "run.mcap")
    label_of = {t.node_id: i for i, t in enumerate(scene.taxels)}
    where, width, height = site_grid(scene, range(scene.n))
    assert (width, height) == (10, 11)  # matrix57's distinct x / y values
    seen_present = 0
    for record, (log_time, _, payload) in zip(records, by_topic["/taxel/sensor/map"]):
        img = decode_raw_image(payload)
        assert (img["encoding"], img["frame_id"], img["stamp_ns"]) == ("mono8", "sensor", log_time)
        assert img["step"] == img["width"] == width and img["height"] == height
        grid = image_array(img)
        present = {label_of[label] for label in record["present_nodes"]}
        not_heard = {label_of[label] for labels in record["nodes_by_state"].values() for label in labels}
        expected = np.zeros((height, width), dtype=np.uint8)
        for i in range(scene.n):
            code = 255 if i in present else 85 if i in not_heard else 170
            r, c = where[i]
            expected[r, c] = max(expected[r, c], code)
        assert np.array_equal(grid, expected), (record["cycle"], grid, expected)
        seen_present += bool(present)
    # the object sits on the sensor in cycles 20-119 (on a loaded host some cycles go undecided)
    assert seen_present >= 20, seen_present


def test_a_replay_makes_the_live_runs_mcap_byte_for_byte(matrix57_run, tmp_path, capsys):
    out, *_ = matrix57_run
    assert main(["replay", "--scene", "matrix57", str(out / "run.log"), "--json-lines", str(tmp_path / "r.jsonl"),
                 "--mcap", str(tmp_path / "r.mcap")]) == 0
    assert (tmp_path / "r.jsonl").read_bytes() == (out / "run.jsonl").read_bytes()
    assert (tmp_path / "r.mcap").read_bytes() == (out / "run.mcap").read_bytes()
    assert not (tmp_path / "r.mcap.partial").exists()


def test_raw_mode_readings_are_the_cycles_readings(tmp_path):
    """gripper18_raw: two pads (jaws) with maps and readings; every pixel of a readings image is
    the mean of the readings of the taxels at that site (taken from the closed cycles here, by a
    hook of the test's own)."""
    from fusion_center.commands.demo import run_demo
    from fusion_center.service import replay_trace

    scene = load_scene("gripper18_raw")
    trace = tmp_path / "g.log"
    run_demo(scene, 30, trace=trace, keep_records=False,
             outputs=RoboticsOutputs(scene, mcap=tmp_path / "g3.mcap", threaded=True))
    # the same cycles offline, with the readings each record was made from (held where the scene holds)
    captured = []
    out2 = RoboticsOutputs(scene, mcap=tmp_path / "g2.mcap")

    def hook(record, closed):
        readings = closed.readings
        if scene.bus.transmission_type != 1:
            readings = np.where(np.isnan(readings) & ~closed.missing, closed.held_readings, readings)
        captured.append((record, readings))
        out2.on_cycle(record, closed)

    replay_trace(scene, trace, on_cycle=hook)
    out2.close()
    assert (tmp_path / "g2.mcap").read_bytes() == (tmp_path / "g3.mcap").read_bytes()
    _, by_topic = read_mcap(tmp_path / "g3.mcap")
    assert {"/taxel/left/map", "/taxel/right/map", "/taxel/left/readings", "/taxel/right/readings",
            "/fusion/forces"} <= set(by_topic)
    for jaw in ("left", "right"):
        pad = [i for i, t in enumerate(scene.taxels) if t.jaw == jaw]
        where, width, height = site_grid(scene, pad)
        for (record, readings), (_, _, payload) in zip(captured, by_topic[f"/taxel/{jaw}/readings"]):
            img = decode_raw_image(payload)
            assert (img["encoding"], img["step"], img["frame_id"]) == ("32FC1", 4 * width, jaw)
            grid = image_array(img)
            for r in range(height):
                for c in range(width):
                    at = [readings[i] for i in pad if where[i] == (r, c) and not np.isnan(readings[i])]
                    if at:
                        assert grid[r, c] == pytest.approx(np.float32(np.mean(at)), rel=1e-6)
                    else:
                        assert np.isnan(grid[r, c])
    forces = [json.loads(p) for _, _, p in by_topic["/fusion/forces"]]
    assert forces == [r["forces"] for r, _ in captured if "forces" in r]


def test_grip_and_grasp_truth_are_published_when_records_carry_them(tmp_path):
    """Issue 23's record fields, on hand-made records of a grasp scene: /grip and /world/truth
    carry them as they are."""
    scene = load_scene("grasp_drive")
    records = [_grasp_record(k) for k in range(5)]
    publish(scene, records, mcap=tmp_path / "grip.mcap")
    _, by_topic = read_mcap(tmp_path / "grip.mcap")
    assert [json.loads(p) for _, _, p in by_topic["/grip"]] == [r["grip"] for r in records]
    truth = [json.loads(p) for _, _, p in by_topic["/world/truth"]]
    assert truth == [{"truth": r["truth"], "truth_code": 1, **r["grasp_truth"]} for r in records]
    assert [t for t, _, _ in by_topic["/grip"]] == [round(r["t"] * 1e6) * 1000 for r in records]


def _grasp_record(k: int) -> dict:
    return {"cycle": k, "t": 0.01 * k + 0.5, "closed_by": "complete", "closed_after_ms": 0.5, "n_expected": 6,
            "n_live": 6, "n_received": 6, "present_count": 2, "present_nodes": [3, 4], "mode": "decision",
            "U_G": 2, "threshold": 1, "decision": "H1", "p_h1": None, "decide_with": "k-of-n", "degraded": False,
            "missing_nodes": [], "silent_nodes": [], "nodes_by_state": {}, "duplicate_nodes": [], "late_frames": 0,
            "bad_frames": 0, "emcy": [], "rules": {"k-of-n": {"U_G": 2, "threshold": 1, "decision": "H1",
                                                              "p_h1": None}},
            "stages_run": ["fusion", "grip"], "stages_skipped": {}, "rules_skipped": {}, "truth": "H1",
            "grip": {"command_n": 10.0 + k, "actual_n": 9.5 + k, "drive_state": "operation_enabled",
                     "grip_state": "holding", "slip": k == 3},
            "grasp_truth": {"phase": "hold", "normal_n": 9.4 + k, "min_hold_n": 6.0, "slipping": k == 3,
                            "slid_mm": 0.1 * k, "dropped": False, "crushed": False}}


# ---------------------------------------------------------------------- output paths
def test_mcap_to_a_directory_is_refused_in_one_line(tmp_path, capsys):
    assert main(["replay", "--scene", "matrix57", "nosuch.log", "--mcap", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--mcap" in err and "is a directory" in err


def test_a_failed_replay_leaves_no_mcap_that_looks_complete(tmp_path, capsys):
    """A trace cut in the middle of a line: the replay fails after some records; an MCAP of an
    earlier replay at the same path is removed, the partial one keeps its .partial name."""
    demo_log = tmp_path / "d.log"
    assert main(["demo", "--cycles", "20", "--log", str(demo_log), "--no-live"]) == 0
    target = tmp_path / "out.mcap"
    target.write_bytes(b"an earlier replay's file")
    data = demo_log.read_bytes()
    broken = tmp_path / "broken.log"
    broken.write_bytes(data[: len(data) // 2] + b"(garbage) not a candump line\n" + data[len(data) // 2:])
    capsys.readouterr()
    assert main(["replay", "--scene", "matrix57", str(broken), "--mcap", str(target), "--force"]) == 2
    assert "unreadable" in capsys.readouterr().err
    assert not target.exists()


def test_mcap_to_a_device_is_written_in_place(tmp_path, capsys):
    demo_log = tmp_path / "d.log"
    assert main(["demo", "--cycles", "5", "--log", str(demo_log), "--no-live"]) == 0
    assert main(["replay", "--scene", "matrix57", str(demo_log), "--mcap", os.devnull, "--json-lines", os.devnull]) == 0
    assert Path(os.devnull).is_char_device()


def test_mcap_to_a_fifo_is_a_readable_mcap(tmp_path, capsys):
    """A FIFO is written in place with seeking off: what a reader gets is a whole MCAP file."""
    import threading

    demo_log = tmp_path / "d.log"
    assert main(["demo", "--cycles", "10", "--log", str(demo_log), "--no-live"]) == 0
    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)
    got = {}

    def read():
        with open(fifo, "rb") as f:
            got["data"] = f.read()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    assert main(["replay", "--scene", "matrix57", str(demo_log), "--mcap", str(fifo),
                 "--json-lines", str(tmp_path / "r.jsonl")]) == 0
    reader.join(timeout=30)
    assert fifo.is_fifo()
    (tmp_path / "copy.mcap").write_bytes(got["data"])
    _, by_topic = read_mcap(tmp_path / "copy.mcap")
    assert len(by_topic["/fusion/decision"]) == 10


def test_the_cached_json_is_the_plain_encoding_of_every_message(matrix57_run):
    """json_messages (rules and flat messages cached by content) decodes to values() for every
    record - a run's, hand-made grasp records, a record with EMCY and nodes by state, an
    evaluation error's record - and twice over (the second time from the caches)."""
    from fusion_center.robotics.topics import TopicMap

    _, scene, records, _ = matrix57_run
    odd = dict(records[60], emcy=[{"node": 5, "code": "0x8130", "register": "0x11", "manufacturer": "", "t": 1.0}],
               nodes_by_state={"silent": [5], "missing": [9]}, degraded=True)
    error = {"cycle": 7, "t": 0.5, "error": "boom"}
    grasp = [_grasp_record(k) for k in range(3)]
    for scene_name, recs in (("matrix57", records + [odd, error]), ("grasp_drive", grasp)):
        topics = TopicMap(load_scene(scene_name))
        for _ in range(2):
            for record in recs:
                plain = topics.values(record)
                fast = topics.json_messages(record)
                assert [t for t, _ in fast] == [t for t, _ in plain]
                for (_, text), (_, value) in zip(fast, plain):
                    assert json.loads(text) == value


def test_cached_bus_and_map_follow_the_nodes_by_state(matrix57_run):
    """The /bus text and the taxel map are cached per nodes-by-state pattern (one key for both):
    records alike in every cached field but which nodes are named (or in which state) each get
    their own message - equal to the plain encoding and to the map recomputed from the record."""
    from fusion_center.robotics.mcap_out import encode
    from fusion_center.robotics.topics import TopicMap

    _, scene, records, _ = matrix57_run
    label_of = {t.node_id: i for i, t in enumerate(scene.taxels)}
    where, width, height = site_grid(scene, range(scene.n))
    base = dict(records[10], present_nodes=[], emcy=[], duplicate_nodes=[], error=None)
    patterns = [{}, {"silent": [5]}, {"silent": [9]}, {"missing": [5]}, {"silent": [5, 9]}, {"silent": [9, 5]},
                {"silent": [5], "missing": [9]}, {"missing": [9], "silent": [5]}, {}]
    topics = TopicMap(scene)
    for _ in range(2):  # the second pass from the caches
        for states in patterns:
            record = dict(base, nodes_by_state=states)
            _, messages = encode(topics, record)
            by_topic = {topic: payload for topic, _, payload in messages}
            assert json.loads(by_topic["/bus"]) == dict(topics.values(record))["/bus"]
            assert list(json.loads(by_topic["/bus"])["nodes_by_state"].items()) == list(states.items())
            not_heard = {label_of[label] for labels in states.values() for label in labels}
            expected = np.zeros((height, width), dtype=np.uint8)
            for i in range(scene.n):
                r, c = where[i]
                expected[r, c] = max(expected[r, c], 85 if i in not_heard else 170)
            assert np.array_equal(image_array(decode_raw_image(by_topic["/taxel/sensor/map"])), expected), states


def test_the_publisher_thread_writes_what_the_cycle_thread_would(matrix57_run, tmp_path):
    """The publisher thread encodes a whole backlog before handing it to the outputs (in batches
    of DRAIN_BATCH cycles): the file is byte for byte the one written cycle by cycle, and a cycle
    that cannot be encoded (NaN in its slip, which JSON cannot hold) is counted and leaves out
    only itself - the cycles before and after it in the same batch are written."""
    from fusion_center.robotics import outputs as outputs_module

    _, scene, records, _ = matrix57_run
    bad = dict(records[70], slip={"speed": float("nan")})
    recs = records[:70] + [bad] + records[71:150]
    assert len(recs) > 2 * outputs_module.DRAIN_BATCH
    stats = {}
    for name, threaded in (("cycle.mcap", False), ("thread.mcap", True)):
        outputs = RoboticsOutputs(scene, mcap=tmp_path / name, threaded=threaded)
        for record in recs:  # far faster than the publisher's period: one backlog
            outputs.on_cycle(record)
        stats[name] = outputs.close()
    assert (tmp_path / "thread.mcap").read_bytes() == (tmp_path / "cycle.mcap").read_bytes()
    assert stats["thread.mcap"]["errors"] == 1 and stats["thread.mcap"]["mcap"]["cycles"] == 149
    _, by_topic = read_mcap(tmp_path / "thread.mcap")
    cycles = [json.loads(payload)["cycle"] for _, _, payload in by_topic["/fusion/decision"]]
    assert cycles == [r["cycle"] for r in recs if r is not bad]


def test_a_patch_scene_map_is_its_64_by_64_grid(tmp_path):
    """skin4096: patch nodes' taxel labels ("ID/k", "C:ID/k") land on their own pixels; a patch
    node named in nodes_by_state greys all its taxels."""
    from fusion_center.service.pipeline import node_labels, taxel_labels
    from taxel_net.patches import devices

    scene = load_scene("skin4096")
    labels = taxel_labels(scene)
    present = [5, 64, 65, 4095, 2000]
    silent_device = devices(scene)[3]
    record = {"cycle": 0, "t": 0.25, "present_nodes": [labels[i] for i in present],
              "nodes_by_state": {"silent": [node_labels(scene)[3]]}, "decision": "H1"}
    publish(scene, [record], mcap=tmp_path / "skin.mcap")
    _, by_topic = read_mcap(tmp_path / "skin.mcap")
    img = decode_raw_image(by_topic["/taxel/sensor/map"][0][2])
    grid = image_array(img)
    where, width, height = site_grid(scene, range(scene.n))
    assert (width, height) == (64, 64)
    expected = np.full((64, 64), 170, dtype=np.uint8)
    for i in silent_device.taxels:
        expected[where[i]] = 85
    for i in present:
        expected[where[i]] = 255
    assert np.array_equal(grid, expected)


def test_a_failed_live_run_leaves_only_the_partial_file(tmp_path):
    """run_with_outputs (run, demo): the run raises -> FILE.partial stays, an earlier FILE goes."""
    from fusion_center.commands.run import run_with_outputs

    class Service:
        on_cycle: list = []

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    scene = load_scene("matrix57")
    target = tmp_path / "live.mcap"
    target.write_bytes(b"an earlier run's file")
    outputs = RoboticsOutputs(scene, mcap=target, threaded=True)

    def body():
        outputs.on_cycle({"cycle": 0, "t": 0.1, "present_nodes": [], "nodes_by_state": {}})
        raise RuntimeError("the bus went away")

    with pytest.raises(RuntimeError):
        run_with_outputs(Service(), outputs, body)
    assert not target.exists() and (tmp_path / "live.mcap.partial").exists()


def test_run_on_a_bus_writes_the_mcap(tmp_path, capsys):
    """`run` (not only demo): a virtual bus with no nodes - 3 undecided cycles, all in the file."""
    import uuid

    out = tmp_path / "run.mcap"
    assert main(["run", "--scene", "matrix57", "-i", "virtual", "-c", f"viz-{uuid.uuid4().hex[:8]}", "--cycles", "3",
                 "--boot-timeout", "0.2", "--mcap", str(out), "--no-live"]) == 0
    assert f"mcap:" in capsys.readouterr().out
    _, by_topic = read_mcap(out)
    decisions = [json.loads(p)["decision"] for _, _, p in by_topic["/fusion/decision"]]
    assert decisions == ["undecided"] * 3


def test_a_fifo_whose_reader_goes_away_is_one_line_not_a_traceback(tmp_path, capsys):
    import threading

    demo_log = tmp_path / "d.log"
    assert main(["demo", "--cycles", "400", "--log", str(demo_log), "--no-live"]) == 0
    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)

    def read_a_little():
        with open(fifo, "rb") as f:
            f.read(16)

    reader = threading.Thread(target=read_a_little, daemon=True)
    reader.start()
    capsys.readouterr()
    assert main(["replay", "--scene", "matrix57", str(demo_log), "--mcap", str(fifo),
                 "--json-lines", str(tmp_path / "r.jsonl")]) == 2
    reader.join(timeout=30)
    err = capsys.readouterr().err
    assert "Traceback" not in err and "--mcap" in err.splitlines()[-1]
    assert fifo.is_fifo()


@pytest.mark.parametrize("t", [0, 5, 999_999_999, 1_000_000_000, 12_345_678_901_234,
                               (2 ** 32 - 1) * 10 ** 9 + 999_999_999])
def test_the_raw_images_are_the_sdks_bytes(t):
    """mcap_out.raw_image builds foxglove.RawImage's protobuf bytes itself: the same as the SDK's."""
    from foxglove.messages import RawImage, Timestamp

    from fusion_center.robotics.mcap_out import _stamp, raw_image

    rng = np.random.default_rng(t % 1000)
    for frame_id, width, height, encoding, step, size in (("sensor", 10, 11, "mono8", 10, 110),
                                                           ("left", 3, 5, "32FC1", 12, 60),
                                                           ("sensor", 64, 64, "mono8", 64, 4096),
                                                           ("x" * 200, 300, 1, "mono8", 300, 300)):
        data = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        sdk = RawImage(timestamp=Timestamp(sec=t // 10 ** 9, nsec=t % 10 ** 9), frame_id=frame_id, width=width,
                       height=height, encoding=encoding, step=step, data=data).encode()
        assert raw_image(_stamp(t), frame_id, width, height, encoding, step, data) == sdk


def test_a_run_whose_bus_cannot_be_opened_leaves_no_output(tmp_path, capsys):
    out = tmp_path / "run.mcap"
    assert main(["run", "--scene", "matrix57", "-i", "udp_multicast", "-c", "not-an-address", "--cycles", "3",
                 "--mcap", str(out), "--ros2-bag", str(tmp_path / "bag"), "--no-live"]) == 2
    assert "--channel" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_run_whose_mcap_lacks_cycles_exits_2_naming_it(tmp_path, capsys, monkeypatch):
    """A record the MCAP encoder refuses (a scene value that overflows to inf did so): the cycle is
    counted and logged and the run goes on, but the file lacks it - the run says INCOMPLETE and
    exits 2 as for the decision log (2026-11-30, stop 32; it exited 0 with the file complete-looking)."""
    from fusion_center.robotics import mcap_out

    real = mcap_out.encode

    def encode(topics, record, readings):
        if record.get("cycle") == 5:
            raise ValueError("a number the encoder refuses")
        return real(topics, record, readings)

    monkeypatch.setattr(mcap_out, "encode", encode)
    target = tmp_path / "out.mcap"
    assert main(["demo", "--cycles", "12", "--no-live", "--mcap", str(target)]) == 2
    out = capsys.readouterr()
    assert "mcap:                      INCOMPLETE: --mcap" in out.out and "1 cycle(s) not published" in out.err
    assert len(read_mcap(target)) > 0            # the other cycles are kept (the run's figures are worth having)
