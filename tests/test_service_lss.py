"""``[master] assign_ids = "lss"``: the fusion centre gives non-configured node twins their
node-IDs by LSS Fastscan (CiA 305), then boots, configures and runs them as usual."""

from __future__ import annotations

import dataclasses
import json
import uuid
from pathlib import Path

import can
import pytest

from fusion_center.service import FusionService
from fusion_center.service.lss import expected_serial
from fusion_center.service.traces import trace_channel
from node_sim.rig import Rig, identity_serial
from taxel_net.patches import devices
from taxel_net.scene import MasterSpec, load_scene

ROOT = Path(__file__).resolve().parent.parent


def lss_scene(name):
    scene = load_scene(ROOT / "scenes" / f"{name}.toml")
    tag = uuid.uuid4().hex[:8]
    bus = dataclasses.replace(scene.bus, channels=tuple(f"lss-{tag}-{c}" for c in scene.bus.channels))
    return dataclasses.replace(scene, bus=bus, master=MasterSpec(assign_ids="lss"))


@pytest.mark.parametrize("name", [p.stem for p in sorted((ROOT / "scenes").glob("*.toml"))])
def test_the_centre_computes_the_serials_the_twins_carry(name):
    scene = load_scene(ROOT / "scenes" / f"{name}.toml")
    serials = [expected_serial(scene, t) for t in scene.taxels]
    assert serials == [identity_serial(scene, t) for t in scene.taxels]
    assert len(set(serials)) == len(devices(scene))  # one LSS address per node (a patch node: its taxels)


def test_lss_scene_key():
    assert load_scene(ROOT / "scenes" / "matrix57.toml").master.assign_ids == "scene"


@pytest.mark.parametrize("name", ["matrix57", "two_buses_200"])
def test_centre_assigns_the_scene_node_ids_by_fastscan_then_runs(name, tmp_path):
    scene = lss_scene(name)
    trace = tmp_path / "t.log"
    out = tmp_path / "r.jsonl"
    service = FusionService(scene, interface="virtual", channels=list(scene.bus.channels), trace=trace,
                            json_lines=out)
    rig = Rig(scene, interface="virtual", channel=list(scene.bus.channels))
    cycles = 20
    with service:
        rig.start()
        try:
            assert rig.nodes == {}  # every twin non-configured: LSS only
            missing = service.boot(5.0)
            # every twin got the node-ID the scene gives its serial number
            assert {(t.channel, t.node_id) for t in scene.taxels} == set(rig.nodes)
            for i, t in enumerate(scene.taxels):
                node = rig.node(t.node_id, t.channel)
                assert node.lss is rig.lss_slaves[i]
                assert node.read(0x1018, 4) == identity_serial(scene, t)
                assert node.lss.stored_node_id == t.node_id  # stored: it survives a reset node
            report = service.master.lss_report
            assert sorted(report.assigned) == sorted(
                (t.channel, identity_serial(scene, t), t.node_id) for t in scene.taxels)
            assert report.unknown == [] and report.not_found == []
            # one Fastscan reset, vendor, product, revision and serial frame per node (each
            # expected serial tried whole, the lowest first), then inquire, configure, store,
            # switch: 9 frames a node, plus the unanswered reset (twice) per channel
            # (more where a loaded host let an answer miss its time-out and a request was repeated)
            assert report.frames >= 9 * scene.n + 2 * len(scene.bus.channels)
            assert missing == []
            summary = service.run(cycles)
        finally:
            rig.stop()
    assert summary.records == cycles
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["cycle"] for r in records] == list(range(cycles))
    # the LSS frames are in the trace, before the NMT reset communication of the boot
    frames = list(can.LogReader(str(trace)))
    ids = [m.arbitration_id for m in frames]
    last_lss = max(k for k, i in enumerate(ids) if i in (0x7E4, 0x7E5))
    first_reset = next(k for k, m in enumerate(frames) if m.arbitration_id == 0 and bytes(m.data) == b"\x82\x00")
    assert last_lss < first_reset
    assert ids.count(0x7E5) == report.frames
    # every node took part in the run under its node-ID: its TPDO1 is in the trace (how many
    # cycles each one made depends on the host's load: the synchronous window)
    tpdos = {(trace_channel(m, ".log"), m.arbitration_id) for m in frames[first_reset:]}
    assert all((t.channel, 0x180 + t.node_id) in tpdos for t in scene.taxels)


def test_a_node_the_scene_does_not_list_is_left_unconfigured(tmp_path, monkeypatch):
    # finding an unexpected device probes its 128 address bits, one unanswered request per
    # bit that does not match: on a virtual bus 0.3 s is ample (canopen's 0.5 s costs ~15 s)
    monkeypatch.setattr("fusion_center.service.lss.RESPONSE_TIMEOUT_S", 0.3)
    scene = lss_scene("matrix57")
    # the twins run a scene with one more taxel (node-ID 100): its serial is not expected
    extra = dataclasses.replace(scene.taxels[0], node_id=100)
    twins = dataclasses.replace(scene, taxels=scene.taxels + (extra,))
    service = FusionService(scene, interface="virtual", channels=list(scene.bus.channels))
    rig = Rig(twins, interface="virtual", channel=list(scene.bus.channels))
    with service:
        rig.start()
        try:
            assert service.boot(5.0) == []
            report = service.master.lss_report
            assert len(report.assigned) == scene.n and report.not_found == []
            assert report.unknown == [(0, rig.lss_slaves[scene.n].address)]
            assert rig.lss_slaves[scene.n].active_node_id == 0xFF
            assert len(rig.nodes) == scene.n
        finally:
            rig.stop()


def test_absent_and_already_configured_nodes(tmp_path, monkeypatch):
    monkeypatch.setattr("fusion_center.service.lss.RESPONSE_TIMEOUT_S", 0.3)  # see above
    scene = lss_scene("matrix57")
    service = FusionService(scene, interface="virtual", channels=list(scene.bus.channels))
    # the twins of taxels 0 and 1 are not there; the rest run twice: the second boot finds them
    # configured (stored) and assigns nothing
    twins = dataclasses.replace(scene, taxels=scene.taxels[2:])
    rig = Rig(twins, interface="virtual", channel=list(scene.bus.channels))
    with service:
        rig.start()
        try:
            missing = service.boot(2.0)
            report = service.master.lss_report
            assert sorted(report.not_found) == [0, 1] and len(report.assigned) == scene.n - 2
            assert missing == [0, 1]
            again = service.master.assign_node_ids()
            assert again.assigned == [] and again.frames == 2  # an unanswered Fastscan reset, twice
            assert sorted(again.not_found) == list(range(scene.n))
        finally:
            rig.stop()


# ---------------------------------------------------------------------------------------
# the LSS master against LssSlave objects, frame by frame (no bus, no time-out reached)
# ---------------------------------------------------------------------------------------

class Wire:
    """LSS slaves behind a master: answers are queued synchronously; ``lose`` numbers the
    requests (from 1) whose answer is lost."""

    def __init__(self, slaves, lose=()):
        from node_sim.lss import answer_all

        self.answer_all = answer_all
        self.slaves = slaves
        self.lose = set(lose)
        self.sent = 0
        self.master = None

    def transmit(self, data):
        self.sent += 1
        for answer in self.answer_all(self.slaves, data):
            if self.sent not in self.lose:
                self.master.listener.queue.put(answer)


def wired(slaves, lose=()):
    from fusion_center.service.lss import LssMaster

    wire = Wire(slaves, lose)
    wire.master = LssMaster(wire.transmit, timeout_s=0.001)
    return wire


def test_fastscan_finds_an_unexpected_device_bit_by_bit_and_survives_lost_answers():
    from fusion_center.service.lss import LssReport, ScanFailed, assign_channel
    from node_sim.lss import LssSlave
    from taxel_net.scene import TaxelSpec

    scene = dataclasses.replace(load_scene(ROOT / "scenes" / "gripper18.toml"), master=MasterSpec(assign_ids="lss"))
    identity = (0, 0x7A01, 0x00010000)
    stranger = (7, 0x1234, 2, 0xDEADBEEF)
    slaves = [LssSlave(identity + (identity_serial(scene, t),)) for t in scene.taxels] + [LssSlave(stranger)]
    wire = wired(slaves)
    # nothing expected: the plain Fastscan finds the lowest address, bit by bit
    assert wire.master.scan(identity, [], set()) == min(s.address for s in slaves)
    # the answer to a serial bit all slaves share lost: the other value is taken, no slave has
    # it, the confirmation fails (requests: 1 reset, 2-4 vendor/product/revision, 5 bit 31, ...)
    for s in slaves:
        s.on_request(bytes((0x04, 0)) + bytes(6))
    shared = identity_serial(scene, scene.taxels[0]) >> 16
    bit = next(b for b in range(31, 15, -1) if not shared >> (b - 16) & 1)
    wire = wired(slaves, lose={5 + 31 - bit})
    with pytest.raises(ScanFailed):
        wire.master.scan(identity, [], set())
    # the whole assignment, with lost answers here and there: every taxel gets its node-ID,
    # the stranger none
    for s in slaves:
        s.on_request(bytes((0x04, 0)) + bytes(6))
    wire = wired(slaves, lose={9, 31, 200})  # 200: the first reset after the last taxel (asked again)
    report = LssReport()
    wanted = {identity_serial(scene, t): i for i, t in enumerate(scene.taxels)}
    assign_channel(wire.master, 0, scene, identity, wanted, report)
    assert sorted(report.assigned) == sorted((0, identity_serial(scene, t), t.node_id) for t in scene.taxels)
    assert report.unknown == [(0, stranger)] and report.not_found == []
    assert [s.active_node_id for s in slaves] == [t.node_id for t in scene.taxels] + [0xFF]
