"""ROS 2 bags (``export --ros2``, ``--ros2-bag``), read back by two readers: ``rosbags``' own
Reader and the ``mcap`` reader with ``mcap-ros2-support``'s CDR decoder; checked against the
decision log's records (issue 24, docs/robotics.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from fusion_center.cli import main
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from robotics_helpers import by_topic, message_counts, publish, site_grid  # noqa: E402

KGF_N = 9.80665  # standard gravity (CGPM 1901): 1 kgf in N


@pytest.fixture(scope="module")
def matrix57_log(tmp_path_factory):
    out = tmp_path_factory.mktemp("m57bag")
    assert main(["demo", "--cycles", "200", "--json-lines", str(out / "run.jsonl"), "--log", str(out / "run.log"),
                 "--no-live"]) == 0
    records = [json.loads(line) for line in open(out / "run.jsonl")]
    assert main(["export", "--ros2", str(out / "run.jsonl"), str(out / "bag"), "--scene", "matrix57"]) == 0
    return out, records


def _rosbags_messages(bag: Path) -> tuple[dict, dict]:
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        counts = {c.topic: c.msgcount for c in reader.connections}
        out = by_topic((connection.topic, (timestamp, store.deserialize_cdr(raw, connection.msgtype)))
                       for connection, timestamp, raw in reader.messages())
    assert message_counts(out) == {topic: n for topic, n in counts.items() if n}  # the index and the messages
    return out, {"types": types, "counts": counts}


def test_the_bag_of_a_200_cycle_run_reads_back_complete_with_rosbags(matrix57_log):
    out, records = matrix57_log
    from ruamel.yaml import YAML  # rosbags' own YAML library

    meta = YAML(typ="safe").load((out / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert (meta["version"], meta["storage_identifier"], meta["message_count"]) == (9, "mcap", 400)
    assert meta["relative_file_paths"] == ["bag.mcap"]
    for topic in meta["topics_with_message_count"]:
        qos = topic["topic_metadata"]["offered_qos_profiles"]
        assert qos and qos[0]["reliability"] == "reliable" and qos[0]["history"] == "keep_last"
        assert topic["topic_metadata"]["serialization_format"] == "cdr" and topic["message_count"] == 200
    assert (out / "bag" / "bag.mcap").is_file() and not (out / "bag.partial").exists()
    messages, info = _rosbags_messages(out / "bag")
    assert info["types"] == {"/taxel/sensor/map": "sensor_msgs/msg/Image",
                             "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray"}
    assert info["counts"] == {"/taxel/sensor/map": 200, "/diagnostics": 200}
    scene = load_scene("matrix57")
    where, width, height = site_grid(scene, range(scene.n))
    index = {t.node_id: i for i, t in enumerate(scene.taxels)}
    for record, (t_img, img), (t_diag, diag) in zip(records, messages["/taxel/sensor/map"], messages["/diagnostics"]):
        t = round(record["t"] * 1e6) * 1000
        assert t_img == t_diag == t
        assert img.header.stamp.sec * 1_000_000_000 + img.header.stamp.nanosec == t
        assert (img.encoding, img.width, img.height, img.step, img.header.frame_id) == ("mono8", width, height,
                                                                                       width, "sensor")
        grid = np.asarray(img.data).reshape(height, width)
        present_sites = {where[index[n]] for n in record["present_nodes"]}
        assert {tuple(rc) for rc in np.argwhere(grid == 255)} == present_sites
        status = {s.name: s for s in diag.status}
        fusion = status["taxel_can/fusion"]
        values = {kv.key: kv.value for kv in fusion.values}
        assert fusion.message.startswith(record["decision"]) and fusion.hardware_id == "matrix57"
        assert json.loads(values["U_G"]) == record["U_G"] and json.loads(values["threshold"]) == record["threshold"]
        for rule, result in record["rules"].items():
            assert json.loads(values[f"rules.{rule.replace('-', '_')}.U_G"]) == result["U_G"]
        expected_level = 2 if record["decision"] == "undecided" else 1 if record["degraded"] else 0
        assert fusion.level == expected_level
        bus = {kv.key: kv.value for kv in status["taxel_can/bus"].values}
        assert json.loads(bus["closed_after_ms"]) == record["closed_after_ms"]
        assert values["truth"] == record["truth"] and "taxel_can/world_truth" not in status


def test_the_bag_decodes_with_the_mcap_ros2_decoder(matrix57_log):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out, records = matrix57_log
    with open(out / "bag" / "bag.mcap", "rb") as f:
        messages = list(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert {(schema.encoding, channel.message_encoding) for schema, channel, _, _ in messages} == {("ros2msg", "cdr")}
    decoded = by_topic((channel.topic, (message.log_time, ros_msg)) for _, channel, message, ros_msg in messages)
    assert message_counts(decoded) == {"/taxel/sensor/map": 200, "/diagnostics": 200}
    for record, (t, img), (_, diag) in zip(records, decoded["/taxel/sensor/map"], decoded["/diagnostics"]):
        assert t == round(record["t"] * 1e6) * 1000
        assert int(np.count_nonzero(np.frombuffer(bytes(img.data), dtype=np.uint8) == 255)) == len(
            {(t_.x, t_.y) for t_ in load_scene("matrix57").taxels if t_.node_id in record["present_nodes"]})
        names = [s.name for s in diag.status]
        assert names[:2] == ["taxel_can/fusion", "taxel_can/bus"]


def test_export_equals_the_mcap_of_the_replay(matrix57_log, tmp_path):
    """Decision mode: the records are all there is, so the MCAP of `export --mcap` is the replay's."""
    out, _ = matrix57_log
    assert main(["export", str(out / "run.jsonl"), "--mcap", str(tmp_path / "e.mcap"), "--scene", "matrix57"]) == 0
    assert main(["replay", "--scene", "matrix57", str(out / "run.log"), "--json-lines", str(tmp_path / "r.jsonl"),
                 "--mcap", str(tmp_path / "r.mcap")]) == 0
    assert (tmp_path / "e.mcap").read_bytes() == (tmp_path / "r.mcap").read_bytes()


def test_raw_mode_bag_has_readings_and_the_wrench(tmp_path):
    scene = load_scene("gripper18_raw")
    trace = tmp_path / "g.log"
    assert main(["demo", "--scene", "gripper18_raw", "--cycles", "30", "--log", str(trace), "--no-live",
                 "--json-lines", str(tmp_path / "g.jsonl")]) == 0
    assert main(["replay", "--scene", "gripper18_raw", str(trace), "--json-lines", str(tmp_path / "r.jsonl"),
                 "--ros2-bag", str(tmp_path / "bag")]) == 0
    records = [json.loads(line) for line in open(tmp_path / "r.jsonl")]
    messages, info = _rosbags_messages(tmp_path / "bag")
    assert info["types"]["/taxel/left/readings"] == "sensor_msgs/msg/Image"
    assert info["types"]["/fusion/wrench"] == "geometry_msgs/msg/WrenchStamped"
    assert info["counts"]["/taxel/left/readings"] == len(records)
    for _, img in messages["/taxel/left/readings"]:
        assert img.encoding == "32FC1" and img.step == 4 * img.width and img.header.frame_id == "left"
    with_forces = [r for r in records if "forces" in r]
    assert len(messages["/fusion/wrench"]) == len(with_forces) > 0
    for record, (t, w) in zip(with_forces, messages["/fusion/wrench"]):
        assert t == round(record["t"] * 1e6) * 1000
        assert w.wrench.force.x == pytest.approx(record["forces"]["total_tangential"] * KGF_N)
        assert w.wrench.force.z == pytest.approx(record["forces"]["grip_force"] * KGF_N)


def test_grip_records_become_joint_states(tmp_path):
    from test_robotics_mcap import _grasp_record

    scene = load_scene("grasp_drive")
    records = [_grasp_record(k) for k in range(4)]
    publish(scene, records, ros2_bag=tmp_path / "bag")
    messages, info = _rosbags_messages(tmp_path / "bag")
    assert info["types"]["/grip/joint_states"] == "sensor_msgs/msg/JointState"
    for record, (_, actual), (_, command), (_, diag) in zip(records, messages["/grip/joint_states"],
                                                            messages["/grip/command"], messages["/diagnostics"]):
        assert list(actual.name) == ["jaw"] and len(actual.position) == 0
        assert list(actual.effort) == [record["grip"]["actual_n"]]
        assert list(command.effort) == [record["grip"]["command_n"]]
        status = {s.name: s for s in diag.status}
        grip = {kv.key: kv.value for kv in status["taxel_can/grip"].values}
        assert grip["drive_state"] == "operation_enabled" and json.loads(grip["slip"]) == record["grip"]["slip"]
        world = {kv.key: kv.value for kv in status["taxel_can/world_truth"].values}
        assert json.loads(world["normal_n"]) == record["grasp_truth"]["normal_n"]


@pytest.mark.parametrize("content, says", [
    ('{"cycle": 0, "t": 0.0}\n{"cycle": 1, "t": 0.01\n', "line 2: not JSON"),
    ('{"cycle": 0, "t": 0.0}\n[1, 2]\n', "line 2: not a record"),
    ('{"cycle": "x", "t": 0.0}\n', "line 1: not a record"),
    ("", "no records"),
    ("[" * 200_000 + "\n", "line 1: not JSON (nested too deeply)"),  # was a RecursionError, exit 1
    (b'{"cycle": 0, "t": 0.0}\n{"cycle": 1, "t": 0.01, "x": "\xe9"}\n', "byte 0xE9 in line 2, column 31"),
])
def test_a_bad_log_is_one_line_naming_file_and_line(tmp_path, capsys, content, says):
    log = tmp_path / "bad.jsonl"
    log.write_bytes(content) if isinstance(content, bytes) else log.write_text(content)
    assert main(["export", "--ros2", str(log), str(tmp_path / "bag"), "--scene", "matrix57"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(log) in err and says in err
    assert not (tmp_path / "bag").exists() and not (tmp_path / "bag.partial").exists()


def test_export_refuses_an_existing_directory_and_missing_arguments(tmp_path, capsys):
    log = tmp_path / "one.jsonl"
    log.write_text('{"cycle": 0, "t": 0.0}\n')
    (tmp_path / "bag").mkdir()
    assert main(["export", "--ros2", str(log), str(tmp_path / "bag"), "--scene", "matrix57"]) == 2
    assert "exists" in capsys.readouterr().err
    assert main(["export", "--ros2", str(log), "--scene", "matrix57"]) == 2
    assert "OUT_DIR" in capsys.readouterr().err
    assert main(["export", str(log), "--scene", "matrix57"]) == 2
    assert "nothing to export" in capsys.readouterr().err


def test_demo_writes_a_bag_and_bad_targets_are_one_line(tmp_path, capsys):
    assert main(["demo", "--cycles", "5", "--ros2-bag", str(tmp_path / "bag"), "--no-live"]) == 0
    assert "ros2_bag:" in capsys.readouterr().out
    _, info = _rosbags_messages(tmp_path / "bag")
    assert info["counts"] == {"/taxel/sensor/map": 5, "/diagnostics": 5}
    for args, says in ((["--ros2-bag", str(tmp_path / "no" / "bag")], "no directory"),
                       (["--mcap", str(tmp_path / "no" / "x.mcap")], "cannot be written")):
        assert main(["demo", "--cycles", "3", "--no-live", *args]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and says in err
