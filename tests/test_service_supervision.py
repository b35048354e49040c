"""Network supervision (issue 10): NMT state per node in the record, restart policy, reset of
every node at start, duplicate node-IDs flagged."""

import dataclasses
import uuid
from pathlib import Path

import can
import pytest

from fusion_center.service import FusionService
from taxel_net.errors import SceneError
from taxel_net.scene import MasterSpec, load_scene

ROOT = Path(__file__).resolve().parent.parent
MATRIX = ROOT / "scenes" / "matrix57.toml"


def _run(scene, cycles, hooks, extra_nodes=()):
    """Twins + centre on a private virtual channel; ``hooks[cycle](bus)`` runs before that SYNC
    with a third-party bus on the same channel (a diagnostic tool, another master)."""
    from node_sim.rig import Rig

    channel = f"sup-{uuid.uuid4().hex[:8]}"
    service = FusionService(scene, interface="virtual", channels=[channel])
    rig = Rig(scene, interface="virtual", channel=[channel])
    others = [Rig(s, interface="virtual", channel=[channel]) for s in extra_nodes]
    tool = can.Bus(interface="virtual", channel=channel)
    try:
        with service:
            rig.start()
            for other in others:
                other.start()
            service.boot(3.0)
            summary = service.run(cycles, before_sync=lambda k: hooks[k](tool) if k in hooks else None)
    finally:
        tool.shutdown()
        for other in others:
            other.stop()
        rig.stop()
    return service, summary


def _stop_all(bus):
    bus.send(can.Message(arbitration_id=0x000, data=bytes((0x02, 0)), is_extended_id=False))


def test_forged_stop_all_restarted_within_two_heartbeat_periods():
    scene = load_scene(MATRIX)
    service, summary = _run(scene, 80, {20: _stop_all})
    from fusion_center.commands.run import format_summary, summarise

    lines = format_summary(summarise(service, summary))
    assert any(line.startswith("nmt_restarts:") for line in lines), lines
    records = service.records
    hb_cycles = int(2 * scene.bus.heartbeat_producer_ms / scene.bus.sync_period_ms)
    stopped = [r for r in records if "stopped" in r["nodes_by_state"]]
    assert stopped, "the stop-all was never seen in a record"
    first = stopped[0]["cycle"]
    assert 20 <= first <= 20 + hb_cycles // 2  # seen at the next SYNCs (later on a loaded host)
    # every node is named stopped (a node whose last PDO came after the forged frame looks
    # operational - silent - until its next heartbeat says stopped)
    named = {nid for r in stopped if r["cycle"] <= first + hb_cycles for nid in r["nodes_by_state"]["stopped"]}
    assert named == {t.node_id for t in scene.taxels}
    # started again (per node NMT start) and deciding within two heartbeat periods (a node
    # whose last PDO came after the forged frame looks operational until its next heartbeat)
    limit = first + hb_cycles
    # the NMT starts go out after 1.2 heartbeat periods; a heartbeat a node produced just before
    # it took the start (still "stopped") can arrive after it and stand until the node's next
    # heartbeat: no node is named stopped after half a period more
    settled = limit + hb_cycles // 4
    assert not [r["cycle"] for r in records if r["cycle"] > settled and "stopped" in r["nodes_by_state"]]
    assert any(r["n_received"] > 0 for r in records if first < r["cycle"] <= limit)
    # and as well as before the forged frame (PDOs late for their window on a loaded host
    # count against both sides alike)
    before = [r["n_received"] for r in records if r["cycle"] < 20]
    after = [r["n_received"] for r in records if r["cycle"] > limit]
    assert sum(after) / len(after) >= 0.5 * sum(before) / len(before)
    assert service.master.restarts >= scene.n


def test_restart_never_names_the_stopped_nodes_and_sends_nothing():
    scene = load_scene(MATRIX)
    scene = dataclasses.replace(scene, master=MasterSpec(restart="never"))
    service, _ = _run(scene, 60, {20: _stop_all})
    # from two heartbeat periods on, every node's heartbeat has said "stopped"
    hb_cycles = int(2 * scene.bus.heartbeat_producer_ms / scene.bus.sync_period_ms)
    after = [r for r in service.records if 20 + hb_cycles <= r["cycle"] and r["closed_by"] != "nmt"]
    assert after
    everyone = sorted(t.node_id for t in scene.taxels)
    for r in after:
        assert r["n_received"] == 0 and r["decision"] == "undecided"
        # named stopped (heartbeat byte or the NMT frame seen), or missing where a loaded host
        # delayed a node's heartbeat past the consumer time - never taken for operational
        states = r["nodes_by_state"]
        assert sorted(states.get("stopped", []) + states.get("missing", [])) == everyone, states
    assert any(sorted(r["nodes_by_state"].get("stopped", [])) == everyone for r in after)
    assert service.master.restarts == 0


def test_duplicate_node_id_is_flagged():
    """A second device answering for node 18 (a one-taxel rig on the same channel): its SDO
    answers and its PDOs are seen twice; node 18 is named in ``duplicate_nodes``."""
    scene = load_scene(MATRIX)
    index = [t.node_id for t in scene.taxels].index(18)
    twin = dataclasses.replace(scene, taxels=(scene.taxels[index],))
    service, _ = _run(scene, 30, {}, extra_nodes=[twin])
    from fusion_center.commands.run import format_summary, summarise

    lines = format_summary(summarise(service, _))
    assert [line.split(":", 1)[1].strip() for line in lines if line.startswith("duplicate_nodes:")] == [
        "18 (two devices answer for one node-ID)"]
    flagged = [r for r in service.records if r["duplicate_nodes"]]
    assert flagged and all(r["duplicate_nodes"] == [18] for r in flagged)
    assert service.assembler.duplicates == {index}


def test_no_duplicate_and_no_state_entries_on_a_healthy_run():
    # a 40 ms SYNC (32 ms window): complete cycles to check even on a host whose other test
    # worker holds a core (at 10 ms a loaded 2-core run got none complete)
    scene = load_scene(MATRIX)
    scene = dataclasses.replace(scene, bus=dataclasses.replace(scene.bus, sync_period_ms=40.0, sync_window_us=32000))
    service, _ = _run(scene, 30, {})
    assert not service.assembler.duplicates
    assert service.master.restarts == 0
    # node states come from heartbeats (every 100 ms here): a node heard pre-operational before the
    # NMT start that follows the reset at start-up is listed until its next heartbeat, so the
    # steady state begins two heartbeat periods (5 SYNC cycles of 40 ms) after the start
    periods = 2 * scene.bus.heartbeat_producer_ms / scene.bus.sync_period_ms
    steady = [r for r in service.records if r["closed_by"] == "complete" and r["cycle"] >= periods]
    assert steady and all(r["nodes_by_state"] == {} for r in steady), [r["nodes_by_state"] for r in steady]


def test_master_table_in_the_scene(tmp_path):
    text = MATRIX.read_text().replace('taxels_file = "data/matrix57_taxels.csv"',
                                      f'taxels_file = "{ROOT / "scenes" / "data" / "matrix57_taxels.csv"}"')
    ok = tmp_path / "ok.toml"
    ok.write_text(text + '\n[master]\nrestart = "never"\n')
    assert load_scene(ok).master.restart == "never"
    assert load_scene(MATRIX).master.restart == "always"
    bad = tmp_path / "bad.toml"
    bad.write_text(text + '\n[master]\nrestart = "sometimes"\n')
    with pytest.raises(SceneError, match="master.restart"):
        load_scene(bad)
    bad.write_text(text + '\n[master]\nrestart_delay = 1\n')
    with pytest.raises(SceneError):
        load_scene(bad)


@pytest.mark.multiprocess
def test_second_run_against_running_node_sim_decides_as_well_as_the_first(tmp_path, capsys):
    """node-sim keeps running between two `fusion-center run` processes (udp_multicast, hop
    limit 0): the master resets every node's communication at start, so the second run starts
    from the same node state and the same simulated cycle 0 (before: the twins went on from the
    first run's last cycle and the second run agreed with the truth in 47/145 cycles)."""
    import json

    from cli_inprocess import run_cli
    from process_helpers import node_sim, udp_loopback
    from test_service_multiprocess import GROUP, multicast_port

    port = multicast_port()
    bus = udp_loopback(GROUP, port)
    # matrix57 at a 40 ms SYNC (window 80 %: 32 ms): two processes on a host whose other test
    # worker holds a core still get PDOs in time (at 10 ms a loaded run saw the contact in 0 cycles)
    scene_file = tmp_path / "matrix57_40ms.toml"
    scene_file.write_text(MATRIX.read_text().replace('taxels_file = "data/', f'taxels_file = "{MATRIX.parent}/data/')
                          .replace("sync_period_ms = 10.0", "sync_period_ms = 40.0"))
    assert load_scene(scene_file).bus.sync_window == 32000
    with node_sim("--scene", str(scene_file), *bus):
        runs = []
        for k in range(2):
            out = tmp_path / f"run{k}.jsonl"
            # each `fusion-center run` through main() in this process (tests/cli_inprocess.py): a new
            # service, master and bus each time; what is about processes here is node-sim's, which
            # runs on between the two
            done = run_cli(capsys, "run", "--scene", scene_file, "--cycles", "100", "--no-live",
                           "--json-lines", out, *bus)
            assert done.returncode == 0, done.stderr
            runs.append([json.loads(line) for line in out.read_text().splitlines()])
    agreement, seen = [], []
    for records in runs:
        decided = [r for r in records if r["decision"] != "undecided"]
        agreement.append(sum(r["decision"] == r["truth"] for r in decided) / max(1, len(decided)))
        seen.append(sum(r["decision"] == "H1" for r in records))  # the contact of cycles 20..99
    print(f"agreement with the truth: first run {agreement[0]:.2f}, second run {agreement[1]:.2f}; "
          f"contact seen in {seen} cycles")
    # how many cycles get their PDOs in time depends on the host's load (two processes at 10 ms);
    # what a second run must not lose is the agreement of the cycles it decides (47/145 before)
    assert seen[0] >= 5 and seen[1] >= 5, seen
    assert min(agreement) >= 0.75, agreement
