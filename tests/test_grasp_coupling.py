"""The grasp world coupled to a gripper drive (node_sim.world.coupling): a fake drive, and the real
GripperDrive of node_sim.gripper stepped without a bus."""

from __future__ import annotations

import math
import struct
import threading

import pytest

from node_sim.gripper.actuator import GripState
from node_sim.gripper.drive import GripperDrive
from node_sim.link import NodeLink, Scheduler
from node_sim.world import GraspWorld, JawCoupling
from taxel_net.scene_grasp import GraspSpec, PhaseSpec

G = 9.81


def spec(**over):
    base = dict(mass_kg=0.5, mu_s=0.5, mu_k=0.4, size_mm=40.0, gravity_m_s2=G, force_lag_ms=20.0, phases=(
        PhaseSpec("approach", 1.0), PhaseSpec("close", 1.0),
        PhaseSpec("lift", 1.0, height_mm=50.0, accel_m_s2=2.0, speed_m_s=0.2),
        PhaseSpec("hold", 0.5), PhaseSpec("place", 1.0, accel_m_s2=2.0, speed_m_s=0.2),
        PhaseSpec("release", 1.0)))
    base.update(over)
    return GraspSpec(**base)


class FakeDrive:
    """The world's interface of a drive (node_sim.world.coupling.DriveLike), set by hand."""

    def __init__(self, width_mm: float = 80.0):
        self.grip_force_n = 0.0
        self.width_mm = width_mm
        self.cia402_state = "SWITCH ON DISABLED"
        self.calls = []

    def jaw_blocked_at(self, width_mm):
        self.calls.append(("jaw_blocked_at", width_mm))

    def part_lost(self):
        self.calls.append(("part_lost",))


def test_the_task_starts_at_operation_enabled():
    drive = FakeDrive()
    c = JawCoupling(GraspWorld(spec(), 0.01), drive)
    assert {c.step().phase for _ in range(50)} == {"idle"}
    drive.cia402_state = "OPERATION ENABLED"
    t = c.step()
    assert t.phase == "approach" and t.task_s == pytest.approx(0.01)
    drive.cia402_state = "FAULT"                 # the clock goes on whatever the drive does later
    assert c.step().task_s == pytest.approx(0.02)


def test_jaws_told_at_the_close_and_the_force_lags():
    drive = FakeDrive()
    drive.cia402_state = "OPERATION ENABLED"
    c = JawCoupling(GraspWorld(spec(), 0.01), drive)
    for _ in range(100):                         # the approach: 1 s
        c.step()
    assert drive.calls == []
    drive.width_mm, drive.grip_force_n = 40.0, 10.0
    got = [c.step().normal_n for _ in range(3)]
    assert drive.calls == [("jaw_blocked_at", 40.0)]
    # first-order lag, tau = 20 ms, dt = 10 ms, F = 10 N from N = 0: N_k = 10 (1 - exp(-k/2))
    # = 3.9347, 6.3212, 7.7687 N
    assert got == pytest.approx([10 * (1 - math.exp(-k / 2)) for k in (1, 2, 3)], abs=1e-12)
    drive.width_mm = 40.5                        # the jaws open: no force at once
    t = c.step()
    assert t.normal_n == 0.0 and not t.dropped and t.mode == "table"


def test_lost_part_told_once():
    drive = FakeDrive()
    drive.cia402_state = "OPERATION ENABLED"
    c = JawCoupling(GraspWorld(spec(force_lag_ms=0.0), 0.01), drive)
    for _ in range(100):
        c.step()
    drive.width_mm, drive.grip_force_n = 40.0, 10.0
    while c.world.phase != "hold":
        c.step()
    drive.width_mm = 60.0                        # opened in the air: dropped
    t = c.step()
    assert t.dropped and not t.in_grip
    for _ in range(10):
        c.step()
    assert drive.calls == [("jaw_blocked_at", 40.0), ("part_lost",)]


def test_jaws_closed_before_the_object_came_between_them():
    drive = FakeDrive()
    drive.cia402_state = "OPERATION ENABLED"
    drive.width_mm = 0.0                         # the master closed during the approach
    c = JawCoupling(GraspWorld(spec(), 0.01), drive)
    out = [c.step() for _ in range(300)]
    assert c.missed and drive.calls == [] and out[-1].mode == "left" and not out[-1].dropped
    assert all(t.normal_n == 0.0 for t in out)


# ------------------------------------------------------------------ the real drive, no bus

def sdo_write(drive, index, sub, value, size):
    cmd = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    data = struct.pack("<BHB", cmd, index, sub) + int(value).to_bytes(4, "little", signed=value < 0)
    drive.on_sdo_request(data)


class Rig:
    """One GripperDrive on a NodeLink that sends nowhere; SYNC and world step by hand (10 ms)."""

    def __init__(self, grasp):
        self.lock = threading.RLock()
        self.scheduler = Scheduler(self.lock, name="test-world-timers")
        link = NodeLink(lambda *frame: None, self.scheduler)
        with self.lock:
            self.drive = GripperDrive(5, link)
            self.drive.configure({(0x6060, 0): 4, (0x1006, 0): 10000, (0x607D, 2): 50000})
            self.drive.power_on()
            self.drive.on_nmt(0x01)
        self.coupling = JawCoupling(GraspWorld(grasp, 0.01), self.drive, lock=self.lock)
        self.cycle = 0

    def write(self, index, sub, value, size):
        with self.lock:
            sdo_write(self.drive, index, sub, value, size)

    def step(self):
        with self.lock:
            self.drive.on_sync(self.cycle, None, None)
            self.cycle += 1
        return self.coupling.step()

    def close(self):
        self.scheduler.stop()
        with self.lock:
            self.drive.shutdown()


@pytest.fixture
def rig():
    made = []

    def make(grasp):
        r = Rig(grasp)
        made.append(r)
        return r
    yield make
    for r in made:
        r.close()


def run_task_with_drive(r, torque_permille):
    """Enable (no torque), close at the close phase, open at the release phase; the truths and the
    drive's grip state after each step."""
    r.write(0x6040, 0, 0x06, 2)
    out, grip = [r.step()], [r.drive.grip_state]
    r.write(0x6040, 0, 0x0F, 2)
    state = "wait"
    while out[-1].phase != "done":
        phase = r.coupling.world.phase
        if state == "wait" and phase == "close":
            r.write(0x6071, 0, torque_permille, 2)
            state = "closing"
        if state == "closing" and phase == "release":
            r.write(0x6071, 0, -300, 2)
            state = "opening"
        out.append(r.step())
        with r.lock:
            grip.append(r.drive.grip_state)
    return out, grip


def test_real_drive_holds_places_and_releases(rig):
    # 300 ‰ of the rated 100 N per jaw: 30 N per jaw (0x2101 = 300), well above m (g + a)/(2 mu_s) = 5.905 N
    r = rig(spec())
    out, grip = run_task_with_drive(r, 300)
    # the timeline started at the drive's OPERATION ENABLED (the second step), not at the world's first
    assert out[0].phase == "idle" and out[1].task_s == pytest.approx(0.01)
    hold = [i for i, t in enumerate(out) if t.phase == "hold"]
    assert all(out[i].normal_n == pytest.approx(30.0, abs=1e-6) and grip[i] is GripState.HOLDING for i in hold)
    assert not any(t.slipping or t.dropped for t in out)
    assert max(t.height_mm for t in out) == pytest.approx(50.0, abs=1e-9)
    assert out[-1].mode == "table" and not out[-1].dropped and out[-1].normal_n == 0.0
    assert grip[-1] is GripState.RELEASED and not r.coupling.lost_told


def test_real_drive_too_weak_loses_the_part(rig):
    # 50 ‰: 5 N per jaw < 5.905 N, and 2 mu_k N = 4 N < m g = 4.905 N: the pads slide up over the object
    # on the table until they leave it (20 + 10 = 30 mm): left behind, the drive told PART_LOST
    r = rig(spec())
    out, grip = run_task_with_drive(r, 50)
    lift = [i for i, t in enumerate(out) if t.phase == "lift"]
    assert out[lift[0]].slipping and out[lift[0]].normal_n == pytest.approx(5.0, abs=1e-6)
    assert out[lift[-1]].mode == "left" and not out[-1].dropped
    assert grip[lift[-1]] is GripState.PART_LOST and r.coupling.lost_told
