"""The centre on a bus with a gripper drive ([gripper], issue 22): the drive's frames are the
scene's (counted ``drive``), not malformed (``unknown_cob_id``), and a trace of such a run is the
scene's (replay accepts it and gives the live records). Before, every drive frame was counted
malformed with a warning, and ``replay`` refused the trace as one of another scene (11 % of its
frames from node 32)."""

import dataclasses

import can
import numpy as np
import pytest

from fusion_center.commands.demo import run_demo
from fusion_center.service import CycleAssembler, replay_trace
from fusion_center.service.assembler_parts import group_layout
from fusion_center.service.cycle_records import MALFORMED
from fusion_center.service.decoder import K_DRIVE, build_cob_tables
from fusion_center.service.drive_frames import F_TPDO1, FRAME_CODES
from fusion_center.service.traces import check_trace
from taxel_net.gripper import drive_cob_ids
from taxel_net.scene import load_scene


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    scene = load_scene("grasp_drive")
    d = tmp_path_factory.mktemp("gripper_centre")
    trace, live = d / "run.log", d / "live.jsonl"
    service, summary = run_demo(scene, 30, json_lines=live, trace=trace)
    return scene, trace, live, service.stream.counters()


def test_the_drives_frames_are_counted_as_the_drives(run):
    scene, trace, _, counters = run
    drive_frames = [m for m in can.LogReader(str(trace))
                    if m.arbitration_id in drive_cob_ids(scene.gripper.node_id)]
    assert len(drive_frames) >= 2 * 30  # TPDO1 and TPDO2 each SYNC, heartbeats, its SDO configuration
    assert counters["drive"] == len(drive_frames)
    assert sum(counters.get(name, 0) for name in MALFORMED) == 0


def test_a_trace_of_a_run_with_a_drive_replays_to_its_records(run, tmp_path):
    scene, trace, live, _ = run
    assert check_trace(scene, trace)["foreign"] == 0
    out = tmp_path / "replay.jsonl"
    records, counters = replay_trace(scene, trace, json_lines=out)
    assert len(records) == 30 and out.read_bytes() == live.read_bytes()
    assert sum(counters.values()) == len(list(can.LogReader(str(trace))))


def test_the_drive_is_its_channels_in_a_group_and_nobodys_elsewhere():
    base = load_scene("grasp_drive")
    two = dataclasses.replace(base, bus=dataclasses.replace(base.bus, channels=("a", "b")),
                              gripper=dataclasses.replace(base.gripper, channel=1))
    tables = build_cob_tables(two)
    cob_ids = drive_cob_ids(two.gripper.node_id)
    assert all(tables[1][c] == (K_DRIVE, FRAME_CODES[what]) for c, what in cob_ids.items())
    assert not any(c in tables[0] for c in cob_ids)
    served = group_layout(two, [1]).sub  # the drive's channel alone: renumbered 0
    assert served.gripper.channel == 0 and build_cob_tables(served)[0][0x180 + two.gripper.node_id] == (K_DRIVE, F_TPDO1)
    assert group_layout(two, [0]).sub.gripper is None
    a = CycleAssembler(served)
    a.feed(0, 0, 0x700 + two.gripper.node_id, b"\x05")
    assert a.counters()["drive"] == 1 and a.malformed() == 0
    assert np.all(a.node_states() == -1)  # no taxel's state moved
