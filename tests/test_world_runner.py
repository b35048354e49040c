"""The grasp world in the twins (node_sim.world_runner, issue 22): stepped by hand it is a function
of the scene and of the drive's states; its records; the readings the taxels sample from it; its own
clock; node-sim --truth-log."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from node_sim import physics
from node_sim.rig import Rig
from node_sim.world.taxels import truth_readings
from node_sim.world_runner import WorldRunner, has_world
from taxel_net.errors import ParameterError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
SCENE = load_scene("scenes/grasp_scripted.toml")
WAIT_S = 10.0

sys.path.insert(0, str(Path(__file__).resolve().parent))
from process_helpers import start_node_sim, stop  # noqa: E402
from test_grasp_coupling import FakeDrive as _FakeDrive  # noqa: E402


def FakeDrive():  # noqa: N802 - the world's interface of a drive, jaws at 60 mm
    return _FakeDrive(width_mm=60.0)


def script(drive: FakeDrive, k: int) -> None:
    """A drive's states per world step: enabled at step 10, closes on the object at step 130
    (10 ms steps: the approach ends at step 110), grips with 8 N, opens at step 400."""
    if k == 10:
        drive.cia402_state = "OPERATION ENABLED"
    if k == 130:
        drive.width_mm, drive.grip_force_n = 40.0, 8.0
    if k == 400:
        drive.width_mm, drive.grip_force_n = 60.0, 0.0


def run(n: int) -> tuple[list[dict], FakeDrive, WorldRunner]:
    drive = FakeDrive()
    counter = iter(range(10**6))
    runner = WorldRunner(SCENE, drive, sync_state=lambda: (7, next(counter)))
    out = []
    for k in range(n):
        script(drive, k)
        out.append(runner.step())
    return out, drive, runner


def test_stepped_by_hand_the_world_is_a_function_of_the_drive_states():
    a, drive, runner = run(420)
    b, _, _ = run(420)
    assert a == b
    # the record: world time, the SYNC state, the truth fields
    assert a[0]["t_s"] == pytest.approx(0.01) and a[0]["sync_counter"] == 7 and a[0]["cycle"] == 0
    for key in ("phase", "normal_n", "min_hold_n", "slipping", "slid_mm", "dropped", "crushed", "tangential_n"):
        assert key in a[0]
    json.dumps(a)                                                  # JSON-safe
    phases = [r["phase"] for r in a]
    assert phases[9] == "idle" and phases[10] == "approach"       # started at OPERATION ENABLED
    assert phases[110] == "close" and ("jaw_blocked_at", 40.0) in drive.calls
    assert a[200]["mode"] == "stick" and a[200]["phase"] == "lift" and a[300]["phase"] == "hold"
    assert a[-1]["dropped"] and ("part_lost",) in drive.calls     # opened in the air


def test_readings_come_from_the_latest_step():
    recs, _, runner = run(300)
    truth = runner._truth
    np.testing.assert_array_equal(runner.readings(42), truth_readings(SCENE, truth, 42))
    # the LC of both jaws read M N: the force lagging behind 8 N
    lc = [i for i, t in enumerate(SCENE.taxels) if t.kind == "LC"]
    s = runner.readings(42) - physics.taxel_arrays(SCENE)["noise_mv"]
    eps = physics.canonical_eps(SCENE, 42)
    np.testing.assert_allclose(s[lc] - 0.1 * eps[lc], 0.5 * recs[-1]["normal_n"], atol=1e-12)
    # before any step: noise only
    fresh = WorldRunner(SCENE, FakeDrive())
    np.testing.assert_array_equal(fresh.readings(3), physics.observe(SCENE, 3, np.zeros(SCENE.n)))


def test_a_sync_adds_only_the_noise_to_the_steps_signal(monkeypatch):
    """The world's signal S_i is computed when it steps (its thread), not at every SYNC's
    readings: at a SYNC the rig's readings were ~60 % of its SYNC handling for
    scenes/grasp_lift_patch.toml, on the SYNC -> command path. The readings stay the step's
    truth_readings (the same floats)."""
    import node_sim.world.taxels as taxels_module

    recs, _, runner = run(300)
    truth = runner._truth
    calls = []
    original = taxels_module.taxel_signal              # what truth_signal / truth_readings compute S_i with
    monkeypatch.setattr(taxels_module, "taxel_signal", lambda *a, **k: calls.append(a) or original(*a, **k))
    got = [runner.readings(c) for c in (42, 43, 44)]
    assert calls == []                                  # three SYNCs, no signal computed again
    runner.step()
    assert len(calls) == 1                              # once a step
    for c, x in zip((42, 43, 44), got):
        np.testing.assert_array_equal(x, truth_readings(SCENE, truth, c))
    # and the noise of the SYNC after the step's (its sync_state's cycle + 1) is drawn by the step
    eps_calls = []
    original_eps = physics.canonical_eps
    monkeypatch.setattr(physics, "canonical_eps", lambda *a: eps_calls.append(a[1]) or original_eps(*a))
    cycle = runner.latest["cycle"]
    runner.step()                                       # its record's cycle: cycle + 1
    assert eps_calls == [cycle + 2]
    x = runner.readings(cycle + 2)
    assert eps_calls == [cycle + 2]                     # not drawn again at the SYNC
    np.testing.assert_array_equal(x, truth_readings(SCENE, runner._truth, cycle + 2))


def test_a_callback_that_fails_does_not_stop_the_world():
    seen = []

    def bad(record):
        raise RuntimeError("caller's bug")

    runner = WorldRunner(SCENE, FakeDrive(), on_truth=[bad, seen.append])
    for _ in range(3):
        runner.step()
    assert len(seen) == 3


def test_a_scene_without_both_tables_has_no_world():
    assert has_world(SCENE) and not has_world(load_scene("grasp_drive")) and not has_world(load_scene("gripper18"))
    with pytest.raises(ParameterError):
        WorldRunner(load_scene("grasp_drive"), FakeDrive())


def test_its_own_clock_steps_without_any_sync():
    """No master, no SYNC: the world steps on (idle), the records say no SYNC was heard."""
    channel = f"g22w-{uuid.uuid4().hex[:8]}"
    scene = dataclasses.replace(SCENE, bus=dataclasses.replace(SCENE.bus, channels=(channel,)))
    got = []
    done = threading.Event()

    def on_truth(record):
        got.append(record)
        if len(got) >= 20:
            done.set()

    with Rig(scene, interface="virtual", on_truth=on_truth) as rig:
        assert rig.world is not None and rig.runs_world
        assert done.wait(WAIT_S)
        assert rig.world_truth is not None and rig.world_truth["phase"] == "idle"
    steps = [round(r["t_s"] / 0.01) for r in got[:20]]
    assert steps == list(range(1, 21))
    assert all(r["cycle"] is None and r["sync_counter"] is None for r in got)


def test_an_injected_reading_source_wins_and_a_shard_without_the_drive_has_no_world():
    channel = f"g22w-{uuid.uuid4().hex[:8]}"
    scene = dataclasses.replace(SCENE, bus=dataclasses.replace(SCENE.bus, channels=(channel, channel + "b")),
                                gripper=dataclasses.replace(SCENE.gripper, channel=1))
    rig = Rig(scene, interface="virtual", serve_channels=[0])
    assert not rig.runs_world and rig.world_truth is None
    rig2 = Rig(SCENE, interface="virtual", reading_source=lambda c: np.zeros(SCENE.n))
    assert rig2.runs_world and rig2._reading_source is not rig2._world_readings


def node_sim(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "node_sim.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


def test_truth_log_refused_without_a_world(tmp_path):
    out = tmp_path / "t.jsonl"
    r = node_sim("--scene", "grasp_drive", "-i", "virtual", "-c", f"g22w-{uuid.uuid4().hex[:8]}",
                 "--truth-log", str(out))
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "--truth-log" in r.stderr and "no grasp world" in r.stderr
    assert not out.exists()
    r = node_sim("--scene", "grasp_scripted", "-i", "virtual", "-c", f"g22w-{uuid.uuid4().hex[:8]}",
                 "--truth-log", str(tmp_path))
    assert r.returncode == 2 and "is a directory" in r.stderr and r.stderr.strip().count("\n") == 0


def _run_until_lines(args, path: Path, lines: int):
    proc = start_node_sim(*args)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if path.exists() and path.is_file() and path.read_text().count("\n") >= lines:
                break
            if proc.poll() is not None:
                break
            time.sleep(0.05)
    finally:
        stop(proc, 30)
    return proc


def test_truth_log_writes_one_json_line_per_step(tmp_path):
    out = tmp_path / "t.jsonl"
    proc = _run_until_lines(["--scene", "grasp_scripted", "-i", "virtual", "-c", f"g22w-{uuid.uuid4().hex[:8]}",
                             "--truth-log", str(out)], out, 10)
    assert proc.returncode == 0, proc.stderr.read()
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(recs) >= 10 and not out.with_name("t.jsonl.partial").exists()
    assert [round(r["t_s"] / 0.01) for r in recs[:10]] == list(range(1, 11))
    assert recs[0]["phase"] == "idle" and recs[0]["cycle"] is None


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_truth_log_to_a_fifo_stays_a_fifo(tmp_path):
    import stat

    fifo = tmp_path / "truth.fifo"
    os.mkfifo(fifo)
    lines: list[str] = []

    def reader():
        with open(fifo, encoding="utf-8") as f:
            for line in f:
                lines.append(line)
                if len(lines) >= 5:
                    return

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    proc = start_node_sim("--scene", "grasp_scripted", "-i", "virtual", "-c", f"g22w-{uuid.uuid4().hex[:8]}",
                          "--truth-log", str(fifo))
    try:
        t.join(60)
    finally:
        rc = stop(proc, 30)
    assert len(lines) >= 5 and json.loads(lines[0])["phase"] == "idle"
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert rc == 0


def test_a_sync_samples_the_last_step_tagged_before_it():
    """The step a SYNC samples is the last one tagged with an earlier cycle, and that step's record
    is out before the SYNC's sample (fusion_center.service.grasp_truth matches record k with the
    last step tagged k - 1, live and in a replay alike). A step that has read the SYNC state is
    held here for 2 ms before it publishes - the moment a SYNC arriving then used to sample the
    step before, while this one, tagged with the earlier cycle too, came out after it."""
    import can

    channel = f"g22t-{uuid.uuid4().hex[:8]}"
    scene = dataclasses.replace(SCENE, bus=dataclasses.replace(SCENE.bus, channels=(channel,)))
    records: list[dict] = []      # every step's record, in the order the callbacks got them
    sampled: list[tuple] = []     # (cycle, t_s of the step sampled, records out by then)
    with Rig(scene, interface="virtual", on_truth=records.append) as rig:
        world = rig.world
        read_state, read = world._sync_state, world.readings

        def slow_state():
            state = read_state()
            time.sleep(0.002)
            return state

        def reading(cycle):
            latest = world._latest
            sampled.append((cycle, None if latest is None else latest[0].t_s, len(records)))
            return read(cycle)

        world._sync_state, world.readings = slow_state, reading
        with can.Bus(interface="virtual", channel=channel) as master:
            master.send(can.Message(arbitration_id=0x000, data=[0x01, 0], is_extended_id=False))
            time.sleep(0.2)
            for k in range(120):   # SYNCs at 3-7 ms: every phase against the world's 10 ms steps
                master.send(can.Message(arbitration_id=0x080, data=[], is_extended_id=False))
                time.sleep(0.003 + 0.004 * ((k * 7) % 5) / 4)
            time.sleep(0.05)
    checked = 0
    for cycle, t_s, out in sampled:
        before = [r for r in records[:out] if r["cycle"] is not None and r["cycle"] < cycle]
        tagged = [r for r in records if r["cycle"] is not None and r["cycle"] < cycle]
        if t_s is None or not tagged:
            continue
        assert tagged[-1]["t_s"] == t_s, (cycle, t_s, tagged[-1])   # the last step tagged before it
        assert before and before[-1]["t_s"] == t_s, (cycle, t_s)     # ... and its record already out
        checked += 1
    assert checked >= 60, (checked, len(sampled))


def test_node_sim_says_it_waits_for_a_fifos_reader_and_ctrl_c_ends_it_without_a_traceback(tmp_path):
    """node-sim --truth-log FIFO with no reader: opening it waits until a reader opens it (as
    `tee` does) - node-sim says so, and Ctrl-C there ends it with exit 130 and one line, also when
    it was started with SIGINT ignored (it hung without a word; Ctrl-C printed a traceback, or did
    nothing at all under an ignoring parent; 2026-11-30, stop 32)."""
    import os
    import signal
    import sys
    from pathlib import Path

    here = Path(__file__).resolve().parent
    sys.path.insert(0, str(here))
    import subprocess

    from process_helpers import NODE_SIM, ROOT, wait_line

    fifo = tmp_path / "truth.fifo"
    os.mkfifo(fifo)
    # started with SIGINT ignored, as a script's background job or a test runner's worker has it
    # (inherited: Ctrl-C did nothing until node-sim set its own handler, after the FIFO opened)
    proc = subprocess.Popen([*NODE_SIM, "--scene", "grasp_lift", "-i", "virtual", "-c", "fifo-test",
                             "--truth-log", str(fifo)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        wait_line(proc, proc.stdout, "waiting for its reader", 60, "node-sim did not say it waits for the FIFO")
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, (out, err)
    assert "Traceback" not in err and err.strip().splitlines()[-1] == "node-sim: interrupted before it was ready"
