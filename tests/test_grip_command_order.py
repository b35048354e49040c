"""The grip command leaves as early as the cycle allows (issue 23, SYNC -> command): the drive's RPDO1
of cycle k is on the bus before the parts of cycle k's record the command does not need are made -
the node lists (every scene), the forces' record with eqs 26a/26b and the centralised raw-data
tests (raw mode, where ``decide_with`` is a fusion rule). The order is observed on the centre's
own calls (the stream's transmit, the record's makers), on the virtual bus with the twins, the
drive and the grasp world; every wait bounded, no wall-clock limit."""

from __future__ import annotations

import uuid

import pytest

from fusion_center.commands.run import execute
from fusion_center.core import forces
from fusion_center.service import FusionService
from fusion_center.service.centralised_tests import CentralisedTests
from fusion_center.service.pipeline import CyclePipeline
from fusion_center.service.stream import EventStream
from node_sim.rig import Rig
from taxel_net.scene import load_scene

CYCLES = 150


@pytest.mark.parametrize("name", ["grasp_lift", "grasp_lift_raw"])
def test_the_command_of_a_cycle_leaves_before_the_rest_of_its_record(name, monkeypatch):
    scene = load_scene(name)
    events: list[tuple] = []  # in call order: ("rpdo",) or (what, cycle)
    drive_cob = 0x200 + scene.gripper.node_id
    transmit, nodes_by_state = EventStream.transmit, CyclePipeline._nodes_by_state
    results, limit = CentralisedTests.results, forces.grip_force_limit
    current: list[int] = [-1]  # the cycle of the last node lists made

    def spy_transmit(self, channel, can_id, data, remote=False):
        if can_id == drive_cob:
            events.append(("rpdo",))
        return transmit(self, channel, can_id, data, remote)

    def spy_nodes(self, closed, *args):
        current[0] = closed.cycle
        events.append(("nodes", closed.cycle))
        return nodes_by_state(self, closed, *args)

    def spy_results(self, *args):
        events.append(("central",))
        return results(self, *args)

    def spy_limit(*args):
        events.append(("eq26a", current[0]))
        return limit(*args)

    monkeypatch.setattr(EventStream, "transmit", spy_transmit)
    monkeypatch.setattr(CyclePipeline, "_nodes_by_state", spy_nodes)
    monkeypatch.setattr(CentralisedTests, "results", spy_results)
    monkeypatch.setattr(forces, "grip_force_limit", spy_limit)

    channels = [f"order-{uuid.uuid4().hex[:8]}-{c}" for c in scene.bus.channels]
    service = FusionService(scene, interface="virtual", channels=channels)
    rig = Rig(scene, interface="virtual", channel=channels)
    with service:
        try:
            execute(service, CYCLES, live=False, boot_timeout=3.0, on_start=rig.start)
        finally:
            rig.stop()
    records = list(service.records)
    assert len(records) == CYCLES
    commanded = [r["cycle"] for r in records if r["grip_detail"]["controlword"] is not None]
    assert len(commanded) > CYCLES // 2  # the drive was seen and commanded (nothing vacuous)
    # the k-th RPDO1 carries the k-th commanded cycle's command (tests/test_grip_stage.py checks the
    # payloads); count the RPDO1s sent before each maker of a record's part is called
    # (a record's centralised tests come before its node lists, its eq 26a after them)
    sent, before, waiting = 0, {}, []
    for event in events:
        if event[0] == "rpdo":
            sent += 1
        elif event[0] == "central":
            waiting.append(sent)
        else:
            cycle = event[1]
            before.setdefault(event, sent)
            if event[0] == "nodes":
                for count in waiting:
                    before.setdefault(("central", cycle), count)
                waiting = []
    kinds = {"nodes"} | ({"central", "eq26a"} if scene.bus.mode == "raw" else set())
    assert {what for what, _ in before} == kinds
    for (what, cycle), count in before.items():
        assert count == sum(1 for c in commanded if c <= cycle), (what, cycle)
