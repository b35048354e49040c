"""The grip stage end to end on the virtual bus (issue 23): the fusion centre commands the twins' CiA
402 drive of scenes/grasp_scripted.toml (no [grip] table: the law's defaults, the drive's range)
and the grasp world reacts. Checked against the world's own truth (the rig's truth records), never
against the centre's numbers alone; every wait bounded, no wall-clock limit."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import can
import pytest

from fusion_center.commands.run import execute
from fusion_center.service import FusionService, replay_trace
from fusion_center.service.drive_frames import DriveCycle
from fusion_center.service.drive_link import rpdo1_payload
from fusion_center.service.grasp_truth import FIELDS, TruthTable
from fusion_center.service.grip_stage import GripStage, RECOVER_EVERY_S
from node_sim.rig import Rig
from taxel_net.scene import load_scene

GRIP_KEYS = {"command_n", "actual_n", "drive_state", "grip_state", "slip"}
DRIVE = 32
SIMULATED_FAULT = 0x2110


def run_grasp(scene, cycles, *, hook=None, trace=None, json_lines=None, channels=None, rig=None):
    """The centre (and, unless given, a new rig) on private virtual channels; ``hook(k, rig, service)``
    before SYNC k. Returns (service, summary, truth table, the world's steps, rig, channels)."""
    tag = uuid.uuid4().hex[:8]
    channels = channels or [f"grip-{tag}-{name}" for name in scene.bus.channels]
    service = FusionService(scene, interface="virtual", channels=channels, trace=trace, json_lines=json_lines)
    table, steps = TruthTable(), []
    own_rig = rig is None
    if own_rig:
        rig = Rig(scene, interface="virtual", channel=channels, on_truth=[table.add, steps.append])
        service.pipeline.grasp_truth = table
    before = (lambda k: hook(k, rig, service)) if hook else None
    with service:
        try:
            summary = execute(service, cycles, live=False, boot_timeout=3.0, before_sync=before,
                              on_start=rig.start if own_rig else None)
        finally:
            if own_rig:
                rig.stop()
    return service, summary, table, steps, rig, channels


@pytest.fixture(scope="module")
def grasp(tmp_path_factory):
    scene = load_scene("grasp_scripted")
    d = tmp_path_factory.mktemp("grip_stage")
    trace, live = d / "run.log", d / "live.jsonl"
    service, summary, table, steps, _, _ = run_grasp(scene, 500, trace=trace, json_lines=live)
    return scene, service, summary, table, steps, trace, live


def test_gripped_on_presence_slips_in_the_lift_held_after(grasp):
    scene, service, summary, _, steps, _, _ = grasp
    records = list(service.records)
    assert len(records) == 500
    assert all(set(r["grip"]) == GRIP_KEYS for r in records)
    first = next(r for r in records if (r["grip"]["command_n"] or 0) > 0)
    assert first["decision"] == "H1" and first["grip_detail"]["task"] == "close"
    assert all(r["grip"]["command_n"] in (None, 0.0) for r in records[:first["cycle"]])
    # the world (its own steps, not the centre's records): gripped, slipped while being lifted, stuck again
    gripped = [s for s in steps if s["in_grip"] and s["normal_n"] > 0]
    assert gripped, "the jaws never pressed on the object"
    slipping = [s for s in steps if s["slipping"] and s["phase"] == "lift"]
    assert slipping, "the default law's light hold never slipped in the lift (nothing was tested)"
    last_slip = max(s["t_s"] for s in steps if s["slipping"])
    after = [s for s in steps if s["t_s"] > last_slip]
    assert len(after) >= 50 and not any(s["dropped"] for s in steps)
    assert after[-1]["phase"] == "hold" and after[-1]["in_grip"] and after[-1]["normal_n"] >= after[-1]["min_hold_n"]
    # the centre saw the slip and raised the force; the records carry the world's truth
    assert any(r["grip"]["slip"] for r in records)
    assert any("slip_raise" in r["grip_flags"] for r in records)
    with_truth = [r for r in records if "grasp_truth" in r]
    assert len(with_truth) >= 400 and all(set(r["grasp_truth"]) == set(FIELDS) for r in with_truth)
    assert any(r["grasp_truth"]["slipping"] for r in with_truth)
    grip = summary["grip"]
    assert grip["grasp"]["verdict"].startswith("slipped") and "caught" in grip["grasp"]["verdict"]
    assert grip["sync_to_command_ms_p50"] is not None and grip["sync_to_command_ms_p99"] >= grip["sync_to_command_ms_p50"]


def test_the_command_on_the_bus_is_the_records(grasp):
    scene, service, _, _, _, trace, _ = grasp
    sent = [bytes(m.data) for m in can.LogReader(str(trace)) if m.arbitration_id == 0x200 + DRIVE]
    wanted = [rpdo1_payload(r["grip_detail"]["controlword"], r["grip_detail"]["target_permille"])
              for r in service.records if r["grip_detail"]["controlword"] is not None]
    assert sent == wanted and len(sent) == service.drive.commands_sent
    # permille of the rated force per jaw (140 N): the command's force
    r = next(r for r in service.records if (r["grip"]["command_n"] or 0) > 1)
    assert r["grip_detail"]["target_permille"] == round(r["grip"]["command_n"] * 1000 / 140.0)


def test_a_normal_start_is_not_a_drive_not_operational(grasp):
    """The drive's boot-up before the run and the NMT start of all nodes are its start: no record
    flagged drive_booted / drive_not_operational, nothing counted, no NMT start of the drive."""
    _, service, summary, *_ = grasp
    assert not any({"drive_booted", "drive_not_operational"} & set(r["grip_flags"]) for r in service.records)
    assert not {"drive_bootups", "drive_not_operational", "nmt_starts"} & set(summary["grip"])


def test_replay_gives_the_live_records(grasp, tmp_path):
    scene, service, _, table, _, trace, live = grasp
    out = tmp_path / "replay.jsonl"
    records, _ = replay_trace(scene, trace, json_lines=out, grasp_truth=table)
    assert len(records) == 500 and out.read_bytes() == live.read_bytes()


def test_truth_log_file_round_trip(grasp, tmp_path):
    _, _, _, table, steps, _, _ = grasp
    path = tmp_path / "truth.jsonl"
    path.write_text("".join(json.dumps(s) + "\n" for s in steps))
    again = TruthTable.from_file(path)
    assert all(again.for_cycle(k) == table.for_cycle(k) for k in range(0, 520))


def _drive(state_sw, torque=0, force=0, grip=0, lost=False):
    return DriveCycle(True, lost, 5, state_sw, torque, 40000, 4, grip, force, 400, 0, 0, None)


@pytest.mark.parametrize("bad", [{"degraded": True}, {"late_frames": 2}, {"missing_nodes": [3]},
                                 {"over_range_nodes": [1]}])  # readings clipped at a packed limit code
def test_a_degraded_cycle_never_lowers_the_command(bad):
    from fusion_center.core.grip_law import GripState

    stage = GripStage(load_scene("grasp_scripted"))
    record = {"cycle": 0, "t": 0.0, "decision": "H1", "degraded": False, "slip": {"contact": True, "displacement": 0.0}}
    stage.evaluate(dict(record), _drive(0x8027 | 0x0400, torque=100, force=140, grip=4))
    assert stage.takeover and stage.law.phase == "hold" and stage.law.command_n == 14.0  # took over at 14 N
    assert stage.law.learned_n == 14.0  # and does not relax below what held the part
    stage.law = GripState(phase="hold", command_n=14.0, quiet_s=100.0)  # a hold of this centre's own, long quiet: it may relax
    for k in range(1, 50):  # degraded cycles: the law may not relax
        r = dict(record, cycle=k, t=k * 0.01, **bad)
        stage.evaluate(r, _drive(0x8027 | 0x0400, torque=100, force=140, grip=4))
        assert r["grip"]["command_n"] == 14.0 and "held_degraded" in r["grip_flags"]
    r = dict(record, cycle=50, t=0.5)
    stage.evaluate(r, _drive(0x8027 | 0x0400, torque=100, force=140, grip=4))
    assert r["grip"]["command_n"] < 14.0  # a good cycle relaxes toward the least safe force


def test_a_drive_fault_is_flagged_counted_and_reset_at_most_once_a_second():
    scene = load_scene("grasp_scripted")

    def fault_from_150(k, rig, service):  # a fault that comes back after every reset
        if k >= 150:
            with rig.gripper.lock:
                rig.gripper.drive.objects.store(SIMULATED_FAULT, 0, 0x5000)

    service, summary, *_ = run_grasp(scene, 400, hook=fault_from_150)
    records = list(service.records)
    faulted = [r for r in records if "drive_fault" in r["grip_flags"]]
    assert faulted and faulted[0]["cycle"] >= 150 and faulted[0]["grip"]["drive_state"] in ("FAULT", "FAULT REACTION ACTIVE")
    resets = [r["cycle"] for r in records if "fault_reset" in r["grip_flags"]]
    every = RECOVER_EVERY_S / (scene.bus.sync_period_ms / 1000)
    assert resets and all(b - a >= every for a, b in zip(resets, resets[1:]))
    assert len(resets) <= 1 + (400 - 150) / every
    assert summary["grip"]["fault_resets"] == len(resets)
    # episodes seen: a reset whose SWITCH ON DISABLED no record saw before the next fault merges two
    assert 1 <= summary["grip"]["drive_faults"] <= len(resets) + 1


def test_a_lost_drive_heartbeat_is_flagged_once_counted_and_not_a_burst():
    scene = load_scene("grasp_scripted")

    def silence_at_100(k, rig, service):
        if k == 100:
            with rig.gripper.lock:
                rig.gripper.drive.silent = True

    service, summary, *_ = run_grasp(scene, 200, hook=silence_at_100)
    records = list(service.records)
    lost = [r["cycle"] for r in records if "drive_lost" in r["grip_flags"]]
    consumer = scene.bus.heartbeat_consumer_ms / scene.bus.sync_period_ms
    # the drive's last heartbeat came at most one producer period before it fell silent at cycle
    # 100, the consumer times out heartbeat_consumer_ms after that heartbeat (CiA 301 7.2.8.3.2.2)
    producer = scene.bus.heartbeat_producer_ms / scene.bus.sync_period_ms
    assert lost and 100 - producer + consumer - 1 <= lost[0] <= 100 + consumer + 10
    assert lost == list(range(lost[0], 200))  # stays flagged: the drive never came back
    assert summary["grip"]["drive_lost"] == 1
    assert service.drive.commands_sent == sum(r["grip_detail"]["controlword"] is not None for r in records) <= 200


def test_a_new_centre_takes_a_held_part_over_without_opening_the_jaws():
    # the 0.2 kg object of tests/data/grasp_light.toml: lifted without a slip whatever the host's timing
    scene = load_scene(Path(__file__).parent / "data" / "grasp_light.toml")
    tag = uuid.uuid4().hex[:8]
    channels = [f"grip-{tag}-{name}" for name in scene.bus.channels]
    steps = []
    rig = Rig(scene, interface="virtual", channel=channels, on_truth=steps.append)
    rig.start()
    try:
        def die_at_420(k, rig_, service):  # the centre's process dies: nothing of it reaches the bus any more
            if k == 420:
                service.stream.transmit_all = lambda frames, remote=False: None
                service.master.stop_heartbeat()
        first, *_ = run_grasp(scene, 450, hook=die_at_420, channels=channels, rig=rig)
        held = [s for s in steps if s["in_grip"] and s["normal_n"] > 0]
        assert held and held[-1]["phase"] == "hold" and not held[-1]["dropped"]
        force_before = rig.gripper.drive.grip_force_n
        assert force_before > 0
        with rig.gripper.lock:
            torque_before = rig.gripper.drive.objects.read(0x6071)
        n_before = len(steps)
        second, summary, *_ = run_grasp(scene, 100, channels=channels, rig=rig)
        records = list(second.records)
        seen = [r for r in records if r["grip"]["drive_state"] is not None]
        assert "takeover" in seen[0]["grip_flags"] and summary["grip"]["takeovers"] == 1
        assert summary["grip"].get("found_holding") is True
        assert abs(seen[0]["grip"]["command_n"] - force_before) <= 0.1  # the drive's own force, not 0
        # its 0x2101 agrees with its torque; the drive was never found not operational (never reset)
        assert not any({"drive_force_implausible", "drive_not_operational", "drive_booted"} & set(r["grip_flags"])
                       for r in records)
        # the world in between and after: never opened, never dropped, held all along
        later = steps[n_before:]
        assert later and all(s["in_grip"] and not s["dropped"] and s["normal_n"] > 0 for s in later)
        # the new centre commands the drive: its RPDO's target torque is the drive's set-point now
        with rig.gripper.lock:
            torque_now = rig.gripper.drive.objects.read(0x6071)
        assert torque_now == records[-1]["grip_detail"]["target_permille"] and torque_before > 0
    finally:
        rig.stop()


def test_the_live_view_shows_the_grasp_in_80_columns(grasp):
    from types import SimpleNamespace

    from rich.console import Console

    from fusion_center.service.live import LiveView

    scene, service, *_ = grasp
    fake = SimpleNamespace(scene=scene, bitrate=None, labels=service.labels,
                           stream=SimpleNamespace(counters_snapshot=lambda: {"sync": 500, "drive": 1500}))
    view = LiveView(fake, cycles=500)
    slips = [r for r in service.records if r["grip"]["slip"]]
    for r in service.records[: slips[0]["cycle"] + 1]:
        view.update(r)
    console = Console(width=80, record=True, color_system=None, force_terminal=False)
    console.print(view)
    lines = console.export_text().splitlines()
    assert all(len(line) <= 80 for line in lines), [line for line in lines if len(line) > 80]
    text = "\n".join(lines)
    r = slips[0]
    assert f"command {r['grip']['command_n']:.2f} N" in text and "OPERATION ENABLED" in text
    assert "slip_raise" in text and "centre " in text and "!" in text.split("centre ")[-1].splitlines()[0]


def test_plot_of_a_grasp_run(grasp, tmp_path):
    from fusion_center.commands.plot import read_log
    from fusion_center.cli import main

    *_, live = grasp
    series = read_log(live)
    g = series["grasp"]
    assert len(g["t"]) == 500 and any(g["slip"]) and any(s for s in g["true_slip"] if s)
    out = tmp_path / "grasp.png"
    assert main(["plot", str(live), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 20_000


def test_quick_stop_and_disable_are_flagged_and_re_enabled_at_most_once_a_second():
    scene = load_scene("grasp_scripted")
    stage = GripStage(scene)
    every = round(RECOVER_EVERY_S / (scene.bus.sync_period_ms / 1000))
    sw = {"SWITCH ON DISABLED": 0x0040, "READY TO SWITCH ON": 0x0021, "OE": 0x0027, "QUICK STOP ACTIVE": 0x0007}
    log = []

    def cycle(k, state):
        r = {"cycle": k, "t": k * 0.01, "decision": "H0", "degraded": False}
        stage.evaluate(r, _drive(sw[state]))
        log.append((k, state, r["grip_detail"]["controlword"], r["grip_flags"]))
        return r["grip_detail"]["controlword"], r["grip_flags"]

    assert cycle(0, "SWITCH ON DISABLED")[0] == 0x06        # the first walk: shutdown
    assert cycle(1, "READY TO SWITCH ON")[0] == 0x0F        # switch on + enable operation
    assert cycle(2, "OE")[0] == 0x0F
    cw, flags = cycle(150, "QUICK STOP ACTIVE")               # someone else's quick stop
    assert cw == 0x02 and "quick_stop" in flags               # kept: never "disable voltage" mid-ramp
    cw, flags = cycle(151, "SWITCH ON DISABLED")              # its end (0x605A = 2)
    assert cw == 0x06 and "drive_not_enabled" in flags        # a walk: the last was 150 cycles ago
    for k in range(152, 152 + 20):                            # the drive does not follow: no new walk
        cw, _ = cycle(k, "SWITCH ON DISABLED")
        assert cw == (0x06 if k <= 151 + 10 else 0x00), (k, cw)
    assert cycle(151 + every, "SWITCH ON DISABLED")[0] == 0x06  # the next attempt, 1 s after the last
    assert cycle(152 + every, "READY TO SWITCH ON")[0] == 0x0F
    assert cycle(153 + every, "OE")[0] == 0x0F
    cw, flags = cycle(154 + every, "SWITCH ON DISABLED")      # disabled by someone else, no quick stop
    assert cw == 0x00 and "drive_not_enabled" in flags        # inside the second since the last walk: wait
    assert stage.counts["quick_stops"] == 1 and stage.counts["drive_disabled"] == 1
    assert stage.counts["enable_walks"] == 3


def test_raw_mode_grips_with_eq_26a_and_replays(tmp_path):
    from fusion_center.commands.run import apply_mode

    scene = apply_mode(load_scene("grasp_scripted"), "raw")
    trace, live = tmp_path / "raw.log", tmp_path / "raw.jsonl"
    service, summary, table, steps, _, _ = run_grasp(scene, 400, trace=trace, json_lines=live)
    records = list(service.records)
    assert not any(s["dropped"] for s in steps) and steps[-1]["in_grip"] and steps[-1]["normal_n"] > 0
    # the law's raw-mode input: eq 26a per jaw from the forces stage, T / mu (the scene's [forces] mu)
    lifted = [r for r in records if r.get("forces", {}).get("total_tangential") and r["grip_detail"]["law"] == "hold"]
    assert lifted
    for r in lifted:
        least = r["forces"]["total_tangential"] / scene.forces.mu
        # safety factor 1.2; the record rounds command_n to 0.1 mN
        assert r["grip"]["command_n"] >= min(1.2 * least, service.pipeline.grip.params.max_n) - 1e-4
    records_again, _ = replay_trace(scene, trace, grasp_truth=table)
    # the same records, the world's truth included: the step a SYNC samples is the last one tagged
    # with the cycle before, its record out before the sample (node_sim.world_runner's tag_lock)
    assert json.dumps(records_again) == json.dumps([json.loads(line) for line in live.read_text().splitlines()])


def test_the_task_follows_sync_time_not_the_cycle_count():
    """A SYNC producer that falls behind skips SYNCs (Master._sync_loop re-phases); the world's task
    clock does not stop: 1.2 s after the first OPERATION ENABLED the task is grasp_scripted's close
    phase (approach 1.0 s) even if only 60 cycles of 10 ms were seen."""
    stage = GripStage(load_scene("grasp_scripted"))
    for k in range(61):
        r = {"cycle": k, "t": 0.02 * k, "decision": "H0", "degraded": False}
        stage.evaluate(r, _drive(0x0027))
    assert r["grip_detail"]["task"] == "close"
    assert stage.task(0.99) == "open" and stage.task(1.0) == "close" and stage.task(1.8 + 1.0 + 4.0) == "close"
    assert stage.task(1.0 + 0.8 + 1.0 + 4.0 + 1.0) == "release"  # approach, close, lift, hold, place: release


def _slip_flags(stage, displacements):
    return [stage.slip_now({"cycle": k, "slip": {"contact": True, "displacement": d}})
            for k, d in enumerate(displacements)]


def test_slip_now_edge_cue_flags_the_contacts_first_edge_before_a_full_pitch():
    """The sub-pitch edge cue (docs/grip-control.md, "Why these rules"): before the first slip flag
    of a contact, a displacement beyond [grip] edge_fraction x the noise band for edge_cycles cycles
    in a row is slip - the first location at the footprint's edge switching moves the centroid of
    the 2 mm pads by 0.625 mm, less than the band (1 mm, half a pitch), which a full pitch of slide
    (1.875 mm) crosses only 2 mm later. A one-cycle flicker is no slip; the full pitch flags again.
    (The defaults, 0.4 and 2; the cue under other values: the next test.)"""
    from fusion_center.core.grip_law import GripParams

    assert GripParams().edge_cycles == 2 and 0.4 * 1.0 <= GripParams().edge_fraction * 1.0 < 0.625
    scene = load_scene("grasp_scripted")
    stage = GripStage(scene, noise_band=1.0, slip_hold=3)
    # at rest, then the first edge location leaves the footprint (0.625 mm) and stays: flagged the 2nd cycle
    flags = _slip_flags(stage, [0.0, 0.0, 0.0, 0.625, 0.625, 0.625, 0.625, 0.625, 0.625])
    assert flags == [False, False, False, False, True, True, True, False, False]
    # a full pitch later (1.875 mm > the band): a new farthest displacement flags again, for slip_hold cycles
    more = [stage.slip_now({"cycle": 9 + k, "slip": {"contact": True, "displacement": d}})
            for k, d in enumerate([0.625, 1.875, 1.875, 1.875, 1.875])]
    assert more == [False, True, True, True, False]
    # a flicker of one cycle at a time (the edge location on, off, on ...) is no slip
    flicker = GripStage(scene, noise_band=1.0)
    assert not any(_slip_flags(flicker, [0.0, 0.625, 0.0, 0.625, 0.0, 0.625, 0.0]))
    # a displacement below edge_fraction x the band, however long, is no slip
    small = GripStage(scene, noise_band=1.0)
    assert not any(_slip_flags(small, [0.0] + [0.39] * 20))
    # losing the contact forgets the run: the edge cue needs edge_cycles cycles of the new contact
    lost = GripStage(scene, noise_band=1.0)
    _slip_flags(lost, [0.0, 0.625])
    assert lost.slip_now({"cycle": 2, "slip": {"contact": False}}) is False
    assert [lost.slip_now({"cycle": 3 + k, "slip": {"contact": True, "displacement": d}})
            for k, d in enumerate([0.625, 0.625])] == [False, True]


def test_slip_now_says_which_flags_are_new_evidence_and_which_are_held():
    """GripFindings.slip_new (the law raises after an episode's first raise only on new evidence):
    True in the cycle of a new farthest displacement (the edge cue's confirming cycle included),
    False while the flag is only held for slip_hold cycles after it, and False for a flag held
    through a cycle that saw nothing of the contact (frames lost or late)."""
    stage = GripStage(load_scene("grasp_scripted"), noise_band=1.0, slip_hold=3)
    news = []
    for k, d in enumerate([0.0, 0.0, 0.0, 0.625, 0.625, 0.625, 0.625, 1.875, 1.875, 2.5, 2.5, 2.5, 2.5]):
        flag = stage.slip_now({"cycle": k, "slip": {"contact": True, "displacement": d}})
        news.append((flag, stage.slip_new))
    assert news == [(False, False)] * 4 + [(True, True), (True, False), (True, False), (True, True), (True, False),
                                           (True, True), (True, False), (True, False), (False, False)]
    held = stage.slip_now({"cycle": 13, "slip": {"contact": True, "displacement": 3.5}})
    assert (held, stage.slip_new) == (True, True)
    assert (stage.slip_now({"cycle": 14, "slip": {"contact": True, "observed": False}}), stage.slip_new) == (True, False)


def _edge_stage(**fields):
    """grasp_scripted's stage (no [grip]: the defaults) with the scene's [grip] edge fields set."""
    from dataclasses import replace

    from fusion_center.service.grip_stage import default_params

    scene = load_scene("grasp_scripted")
    scene = replace(scene, grip=replace(default_params(scene), **fields))
    return GripStage(scene, noise_band=1.0, slip_hold=3)


@pytest.mark.parametrize("fraction, cycles, step, first", [
    (0.4, 1, 0.625, 3),     # one cycle beyond 0.4 mm: flagged at once
    (0.4, 3, 0.625, 5),     # three cycles in a row
    (0.4, 5, 0.625, 7),
    (0.6, 2, 0.625, 4),     # 0.625 > 0.6 mm
    (0.65, 2, 0.625, None),  # 0.625 < 0.65 mm: no cue; only a full band crossing flags
    (1.0, 1, 0.625, None),   # 1: no cue below the band
    (0.2, 2, 0.25, 4),      # a finer first event (0.25 mm) caught by a lower fraction
    (0.4, 2, 0.25, None),   # ... not by the default
])
def test_slip_now_edge_cue_follows_the_grip_fields(fraction, cycles, step, first):
    """The edge cue's threshold and confirming run are the scene's [grip] edge_fraction and
    edge_cycles (GripStage reads them from Scene.grip, as bench/grasp.py's grasps do): a displacement
    of ``step`` mm from cycle 3 on (the band 1 mm) is flagged first at cycle 3 + edge_cycles - 1 if
    ``step > edge_fraction x band``, never below the band otherwise."""
    stage = _edge_stage(edge_fraction=fraction, edge_cycles=cycles)
    flags = _slip_flags(stage, [0.0, 0.0, 0.0] + [step] * 10)
    expect = None if step <= fraction * 1.0 else 3 + cycles - 1
    assert expect == first  # the table above is the rule's
    assert (flags.index(True) if any(flags) else None) == first, flags
    # a whole band of slide flags whatever the edge fields
    more = [stage.slip_now({"cycle": 13 + k, "slip": {"contact": True, "displacement": d}})
            for k, d in enumerate([1.5, 1.5])]
    assert more[0] is True


def _pressed_flags(stage, steps, t0=0):
    """``steps``: (displacement or None, pressing) per 10 ms cycle of one contact."""
    return [stage.slip_now({"cycle": t0 + k, "t": 0.01 * (t0 + k), "slip": {"contact": True, "displacement": d}},
                           pressing=p) for k, (d, p) in enumerate(steps)]


def test_the_footprint_forming_as_the_jaws_press_is_no_slip_and_the_reference_is_taken_again():
    """The presence cells see the object before the jaws touch it, so the slip tracker's reference is
    their centroid; as the jaws press, the pressure cells of a footprint that is not symmetric about
    it switch on and move the centroid by up to the band (a contact off the pad's middle): no slip.
    From the drive's first force on the part (0x2101 > 0) the cue waits settle_s (60 ms), then the
    stage has the tracker take its reference again (``rebase``) - once per contact; a slide after
    that flags as before. Once the jaws let go (a force of 0) the footprint dissolves: no cue."""
    resets = []
    scene = load_scene("grasp_scripted")
    stage = GripStage(scene, noise_band=1.0, slip_hold=3, rebase=lambda: resets.append(1))
    assert stage.params.settle_s == pytest.approx(0.06)
    before = [(0.0, False)] * 3                     # presence cells only: the reference, nothing moves
    press = [(0.0, True)] + [(0.83, True)] * 6      # the jaws press (cycle 3); the footprint forms (cycle 4 on)
    flags = _pressed_flags(stage, before + press)
    assert not any(flags) and len(resets) == 1      # reset 60 ms after the first press: cycle 9
    tracker_ref = [(None, True)] * 3                # the tracker's new reference cycles (no displacement)
    rest = [(0.0, True)] * 3
    slide = [(0.625, True)] * 3                     # the first edge event of a slide: flagged the 2nd cycle
    flags = _pressed_flags(stage, tracker_ref + rest + slide, t0=10)
    assert flags == [False] * 6 + [False, True, True] and len(resets) == 1
    # the jaws open (force 0): the footprint shrinks back to the presence cells - no cue
    flags = _pressed_flags(stage, [(0.625, True)] * 3 + [(1.9, False)] * 5, t0=19)
    assert not any(flags[3:])
    # contact lost, a new contact: a new press, a new reset
    assert stage.slip_now({"cycle": 27, "t": 0.27, "slip": {"contact": False}}, pressing=False) is False
    _pressed_flags(stage, [(0.0, False)] * 3 + [(0.9, True)] * 7, t0=28)
    assert len(resets) == 2
    # the drive's force not known (None): the cue as without the rule (never held back)
    unknown = GripStage(scene, noise_band=1.0, slip_hold=3, rebase=lambda: resets.append(1))
    assert _pressed_flags(unknown, [(0.0, None)] * 3 + [(0.625, None)] * 2) == [False] * 4 + [True]
    assert len(resets) == 2


def _off_drive(nmt, bootups=0, **kw):
    """A drive whose last TPDO1 / TPDO2 said OPERATION ENABLED, HOLDING, 30 N, now NMT ``nmt``."""
    return DriveCycle(True, False, nmt, 0x8027 | 0x0400, 214, 40000, 4, 4, 300, 400, 0, 0, None, bootups=bootups, **kw)


@pytest.mark.parametrize("nmt, bootups", [(127, 1), (127, 0), (4, 0)])
def test_a_drive_not_nmt_operational_is_flagged_counted_and_the_command_held(nmt, bootups):
    """Stop 32: a drive reset (boot-up, pre-operational) or NMT-stopped mid-hold sends no PDO; before,
    its stale OPERATION ENABLED / HOLDING went on in the records, nothing flagged nor counted."""
    from fusion_center.core.grip_law import GripState

    stage = GripStage(load_scene("grasp_scripted"))
    record = {"decision": "H1", "degraded": False, "slip": {"contact": True, "displacement": 0.0}}
    stage.evaluate(dict(record, cycle=0, t=0.0), _off_drive(5))
    stage.law = GripState(phase="hold", command_n=30.0, quiet_s=100.0)  # a hold that may relax
    flagged = []
    for k in range(1, 200):
        r = dict(record, cycle=k, t=k * 0.01)
        stage.evaluate(r, _off_drive(nmt, bootups=bootups if k == 1 else 0))
        flagged.append(r["grip_flags"])
        assert r["grip"]["drive_state"] is None and r["grip"]["actual_n"] is None
        assert r["grip"]["command_n"] == 30.0 and stage.command is None  # held, nothing sent
    assert all("drive_not_operational" in f for f in flagged)
    assert ("drive_booted" in flagged[0]) == bool(bootups) and not any("drive_booted" in f for f in flagged[1:])
    assert stage.counts["drive_not_operational"] == 1 and stage.counts["drive_bootups"] == bootups
    r = dict(record, cycle=200, t=2.0)
    stage.evaluate(r, _off_drive(5))  # started again (still OPERATION ENABLED after a stop)
    assert "drive_not_operational" not in r["grip_flags"] and r["grip"]["drive_state"] == "OPERATION ENABLED"
    stage.evaluate(dict(record, cycle=201, t=2.01), _off_drive(4))
    assert stage.counts["drive_not_operational"] == 2  # a second episode


def test_a_lost_drive_is_degraded_the_law_does_not_relax():
    """Stop 32 (hunt-b f_lost_relax.py): the law relaxed 14 -> 5.2 N in 2 s with the drive lost."""
    from fusion_center.core.grip_law import GripState

    stage = GripStage(load_scene("grasp_scripted"))
    record = {"decision": "H1", "degraded": False, "slip": {"contact": True, "displacement": 0.0}}
    stage.evaluate(dict(record, cycle=0, t=0.0), _drive(0x8027 | 0x0400, torque=100, force=140, grip=4))
    stage.law = GripState(phase="hold", command_n=14.0, quiet_s=100.0)
    for k in range(1, 200):
        r = dict(record, cycle=k, t=k * 0.01)
        stage.evaluate(r, _drive(0x8027 | 0x0400, torque=100, force=140, grip=4, lost=True))
        assert r["grip"]["command_n"] == 14.0 and "held_degraded" in r["grip_flags"]
    assert stage.counts["degraded_holds"] == 199 and stage.counts["drive_lost"] == 1


@pytest.mark.parametrize("force_01n, expected_n, implausible", [
    (300, 30.0, False),        # 0x2101 agrees with 214 permille x 140 N / 1000 = 29.96 N
    (310, 31.0, False),        # within 10 % / 1 N
    (32767, 29.96, True),      # 3276.7 N: beyond max_n (crush risk)
    (-300, 29.96, True),       # negative: the part let go
    (0, 29.96, True),          # 0 with a positive torque
    (200, 29.96, True),        # 20 N: a third off the torque's
])
def test_a_takeover_cross_checks_the_drives_force_with_its_torque(force_01n, expected_n, implausible):
    """Stop 32 (hunt-b f_takeover_force.py): 0x2101 was trusted blindly - 32767 made the command
    max_n, a negative one a negative learned floor."""
    stage = GripStage(load_scene("grasp_scripted"))
    r = {"cycle": 0, "t": 0.0, "decision": "H1", "degraded": False, "slip": {"contact": True, "displacement": 0.0}}
    stage.evaluate(r, _drive(0x8027 | 0x0400, torque=214, force=force_01n, grip=4))
    assert stage.takeover and stage.law.phase == "hold"
    assert stage.law.command_n == pytest.approx(expected_n) and stage.law.learned_n == pytest.approx(expected_n)
    assert ("drive_force_implausible" in r["grip_flags"]) == implausible
    assert stage.counts["drive_force_implausible"] == int(implausible)


@pytest.mark.parametrize("grip", [1, 2, 3])   # GRASPING, NO_PART, PART_LOST: jaws not pressing on a part
def test_a_takeover_of_a_drive_not_holding_takes_the_torques_force_without_a_flag(grip):
    """A drive whose grip state is not HOLDING reports 0x2101 = 0 whatever its torque (the twin's
    rule): no drive_force_implausible for it (a reviewer found a healthy drive flagged and logged)."""
    stage = GripStage(load_scene("grasp_scripted"))
    r = {"cycle": 0, "t": 0.0, "decision": "H1", "degraded": False, "slip": {"contact": True, "displacement": 0.0}}
    stage.evaluate(r, _drive(0x8027 | 0x0400, torque=214, force=0, grip=grip))
    assert stage.takeover and "drive_force_implausible" not in r["grip_flags"]
    assert stage.counts["drive_force_implausible"] == 0
    assert stage.law.command_n == pytest.approx(214 * stage.rated_n / 1000.0)


def test_a_drive_in_the_wrong_mode_is_counted_per_episode_and_logged(caplog):
    """Stop 32 (hunt-b f_mode.py): drive_mode was flagged every record, never counted nor logged."""
    import logging

    from fusion_center.service.drive_link import DriveLink
    from fusion_center.service.grasp_outcome import GraspOutcome
    from fusion_center.service.stream import RateLimitedLog

    stage = GripStage(load_scene("grasp_scripted"))
    link = object.__new__(DriveLink)
    link._log = RateLimitedLog(logging.getLogger("fusion_center.grip"), 2.0)
    link.outcome = GraspOutcome()
    link.service = None
    modes = [1] * 100 + [4] * 10 + [1] * 100
    with caplog.at_level(logging.WARNING, logger="fusion_center.grip"):
        for k, mode in enumerate(modes):
            r = {"cycle": k, "t": k * 0.01, "decision": "H1", "degraded": False}
            stage.evaluate(r, DriveCycle(True, False, 5, 0x0027, 0, 40000, mode, 0, 0, 400, 0, 0, None))
            link.after_record(k, r)
            assert ("drive_mode" in r["grip_flags"]) == (mode != 4)
    assert stage.counts["drive_mode"] == 2
    lines = [m for m in caplog.messages if "profile torque" in m]
    assert 1 <= len(lines) <= 2  # rate-limited (2 s): not one a record


def test_a_drive_started_again_before_its_first_tpdo1_keeps_the_held_command_in_the_record():
    """After its boot-up the drive's TPDO values are gone; started again (heartbeat operational) it
    has no state until its first TPDO1: nothing sent, the record's command the law's (held), not null."""
    stage = GripStage(load_scene("grasp_scripted"))
    record = {"decision": "H1", "degraded": False, "slip": {"contact": True, "displacement": 0.0}}
    stage.evaluate(dict(record, cycle=0, t=0.0), _off_drive(5))
    held = stage.law.command_n
    no_state = DriveCycle(True, False, 5, None, None, None, None, None, None, None, None, None, None)
    r = dict(record, cycle=1, t=0.01)
    stage.evaluate(r, no_state)
    assert "no_drive_state" in r["grip_flags"] and stage.command is None
    assert held > 0 and r["grip"]["command_n"] == held and r["grip_detail"]["task"] == "close"


@pytest.mark.parametrize("restart", [True, False])
def test_a_drive_not_operational_gets_an_nmt_start_at_most_once_a_second(restart, monkeypatch):
    """Stop 32: nobody started a reset / stopped drive again (Master._supervise / on_bootup are the
    taxel nodes'). An NMT start (0x01, never a reset) to its node-ID, at most once a second,
    under ``[master] restart = "always"`` only."""
    import logging
    import types

    from fusion_center.service import drive_link
    from fusion_center.service.drive_link import DriveLink
    from fusion_center.service.grasp_outcome import GraspOutcome
    from fusion_center.service.stream import RateLimitedLog

    sent, clock = [], [100.0]
    monkeypatch.setattr(drive_link.time, "monotonic", lambda: clock[0])
    link = object.__new__(DriveLink)
    link._log = RateLimitedLog(logging.getLogger("fusion_center.grip"), 2.0)
    link.outcome = GraspOutcome()
    link.service = types.SimpleNamespace(master=types.SimpleNamespace(restart=restart))
    link.stream = types.SimpleNamespace(transmit=lambda ch, cob, data: sent.append((ch, cob, bytes(data))))
    link.channel, link.spec = 0, types.SimpleNamespace(node_id=DRIVE)
    link.starts, link._last_start = 0, None
    stage = GripStage(load_scene("grasp_scripted"))
    for k in range(300):  # 3 s of 10 ms records, the drive pre-operational throughout
        clock[0] = 100.0 + k * 0.01
        r = {"cycle": k, "t": k * 0.01, "decision": "H1", "degraded": False}
        stage.evaluate(r, _off_drive(127, bootups=int(k == 0)))
        link.after_record(k, r)
    if restart:
        assert sent == [(0, 0x000, bytes((0x01, DRIVE)))] * 3 and link.starts == 3
    else:
        assert sent == [] and link.starts == 0


@pytest.mark.parametrize("nmt_command", [0x81, 0x02])  # reset node (a power glitch), stop (another master)
def test_a_drive_reset_or_stopped_mid_hold_is_flagged_started_again_and_re_enabled(nmt_command):
    """Stop 32 (hunt-b f_bootup_e2e.py, f_nmtstop_e2e.py): the drive reset or NMT-stopped mid-hold at
    cycle 300 (the command given to the twin directly, not seen in the centre's stream). Before,
    nobody started it again (PRE-OPERATIONAL / STOPPED, RPDO1 dropped; reset: the world dropped the
    part) and the records said OPERATION ENABLED / HOLDING without a flag."""
    scene = load_scene("grasp_scripted")

    def upset_at_300(k, rig, service):
        if k == 300:
            with rig.gripper.lock:
                rig.gripper._dispatch(0x000, bytes((nmt_command, rig.gripper.node_id)))
        if k == 410:
            with rig.gripper.lock:
                seen.update(nmt=rig.gripper.drive.state_name, cia402=rig.gripper.drive.cia402_state)

    seen = {}
    service, summary, *_ = run_grasp(scene, 420, hook=upset_at_300)
    records = list(service.records)
    off = [r["cycle"] for r in records if "drive_not_operational" in r["grip_flags"]]
    booted = [r["cycle"] for r in records if "drive_booted" in r["grip_flags"]]
    # a boot-up at once; a stop by the drive's next heartbeat (one producer period)
    producer = scene.bus.heartbeat_producer_ms / scene.bus.sync_period_ms
    assert off and 300 <= off[0] <= 300 + producer + 10
    if nmt_command == 0x81:
        assert booted == off[:1] and summary["grip"]["drive_bootups"] == 1
    else:
        assert booted == [] and "drive_bootups" not in summary["grip"]
    assert all(records[k]["grip"]["drive_state"] is None for k in off)
    assert summary["grip"]["drive_not_operational"] == 1 and summary["grip"]["nmt_starts"] >= 1
    # started and walked back: OPERATION ENABLED within a second (the twin's own state), commanded
    # the held force (whether the world kept the part depends on how far it slid in the meantime)
    back = next(r["cycle"] for r in records[off[-1]:] if r["grip"]["drive_state"] == "OPERATION ENABLED")
    assert back - off[0] <= 1.0 / (scene.bus.sync_period_ms / 1000.0)
    assert seen == {"nmt": "OPERATIONAL", "cia402": "OPERATION ENABLED"}
    held = records[off[0] - 1]["grip"]["command_n"]
    assert held > 0 and records[back]["grip"]["command_n"] >= held


def test_the_printed_summary_names_the_drives_upsets():
    """The printed grip line lists the stage's counts of a drive's upsets (a reviewer found a run
    whose drive was reset and started again printing only `enable_walks 2`)."""
    from fusion_center.commands.run import grip_lines

    g = {"commands_sent": 10, "drive_bootups": 1, "drive_not_operational": 2, "nmt_starts": 2, "drive_mode": 1,
         "drive_force_implausible": 1, "enable_walks": 2, "sync_to_command_ms_p50": 1.0,
         "sync_to_command_ms_p99": 2.0, "sync_to_command_ms_max": 3.0,
         "grasp": {"verdict": "held", "max_command_n": 5.0, "final": {}, "slip_cycles": 0}}
    text = " ".join(v for _, v in grip_lines(g))
    for key in ("drive_bootups 1", "drive_not_operational 2", "nmt_starts 2", "drive_mode 1",
                "drive_force_implausible 1", "enable_walks 2"):
        assert key in text, (key, text)
