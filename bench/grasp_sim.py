"""One grasp, offline, through the live centre's control code (``bench/grasp.py``'s engine).

Per SYNC cycle ``k`` (10 ms; the bus skipped, not the stages):

1. **SYNC k.** The taxel nodes sample the world's latest step: the taxels' view
   (:func:`node_sim.world.taxels.truth_readings`: footprint, pressure, load and tangential cells,
   the cycle's canonical noise, :func:`node_sim.physics.observe`); each node decides with its own
   detector (:func:`node_sim.taxel.detector.local_decision_pm1`, eqs 1-4) - decision mode sends
   ``u_i``, raw mode ``X_i`` as REAL32 (rounded to float32 as on the wire). The drive twin
   (:class:`node_sim.gripper.drive.GripperDrive`, on a link that sends nowhere, stepped as
   :class:`node_sim.gripper.host.DriveHost` steps it: ``on_sync`` under its lock) applies the RPDO
   the centre sent in cycle ``k - 1`` and steps its actuator.
2. **The world** steps once (:class:`node_sim.world.JawCoupling`: the drive's force through the
   jaws' lag, stick / slip / drop).
3. **The centre** closes cycle ``k`` (every node delivered: a :class:`ClosedCycle`), evaluates it
   with :class:`fusion_center.service.pipeline.CyclePipeline` (fusion, forces in raw mode, slip),
   derives the law's findings (:func:`findings_of`), steps the law
   (:func:`fusion_center.core.grip_law.grip_step`) and sends the command in the drive's RPDO1
   (controlword, target torque in ‰ of the rated force, target position) - applied at SYNC
   ``k + 1``.

The baselines (a fixed force) skip the centre: the same drive, world and task, a constant command
from the close phase to the release.
"""

from __future__ import annotations

import copy
import functools
import math
import struct
import threading
import time
from dataclasses import dataclass, replace

import numpy as np

from fusion_center.core.bus_timing import frame_bits
from fusion_center.core.grip_law import GripFindings, GripParams, GripState, grip_step
from fusion_center.service.cycle_records import ClosedCycle
from fusion_center.service.physical import PhysicalEvaluation
from fusion_center.service.pipeline import CyclePipeline
from node_sim import od as odx
from node_sim.gripper.drive import GRIPPER_EDS_PATH, GripperDrive
from node_sim.link import NodeLink, Scheduler
from node_sim.world import GraspWorld, JawCoupling
from node_sim.world.taxels import truth_readings
from taxel_net.gripper import startup_values

CW_ENABLE = 0x0F                        # switch on + enable operation (CiA 402)
CW_SHUTDOWN = 0x06
NMT_START = 0x01
TASK_OF_PHASE = {"idle": "open", "approach": "open", "close": "close", "lift": "close", "hold": "close",
                 "place": "close", "release": "release", "done": "release"}


def rpdo1(controlword: int, torque_permille: int, position_um: int = 0) -> bytes:
    """The drive's RPDO1 payload (0x1600: 0x6040 U16, 0x6071 I16, 0x607A I32)."""
    return struct.pack("<HhI", controlword, torque_permille, position_um & 0xFFFFFFFF)


def torque_of(force_n: float, gripper) -> int:
    """Per-jaw force (N; < 0 opens) -> target torque ‰ of the rated force (0x2103), clamped to I16."""
    t = int(round(force_n / gripper.rated_force_n * 1000.0))
    return max(-32768, min(32767, t))


@dataclass
class SlipMemory:
    """What the bench's findings function carries from cycle to cycle (the grip stage's own
    ``slip_now`` state: the farthest displacement of this contact and the cycle it was reached)."""

    band: float = 0.0
    hold: int = 3
    peak: float | None = None
    peak_cycle: int | None = None


def slip_now(record: dict, mem: SlipMemory, raw: bool) -> bool:
    """Slip **this cycle** from the slip stage's record, as the centre's grip stage derives it (the
    slip stage latches ``slipping`` until contact is lost): the present taxels' centroid reached a
    new farthest displacement from the contact's reference, beyond the slip stage's noise band
    (half a taxel pitch), in this cycle or the ``hold - 1`` before it; or, in raw mode, the force
    criterion ``TotF_t > mu F_g`` (eq 26a) holds this cycle."""
    slip = record.get("slip")
    if not slip or not slip.get("contact"):
        mem.peak = mem.peak_cycle = None
        return False
    now = False
    displacement = slip.get("displacement")
    if displacement is not None:
        peak = mem.band if mem.peak is None else mem.peak
        if displacement > peak + 1e-9:
            mem.peak_cycle = record["cycle"]
            mem.peak = displacement
        elif mem.peak is None:
            mem.peak = mem.band
        now = mem.peak_cycle is not None and record["cycle"] - mem.peak_cycle < mem.hold
    ratio = slip.get("force_ratio")
    if raw and ratio is not None and ratio > 1.0:
        now = True
    return now


def findings_of(record: dict, mem: SlipMemory, task: str, params: GripParams, dt: float, raw: bool) -> GripFindings:
    """The law's findings of one record (the bench's copy of the centre's grip stage, until it lands
    on this branch): ``present`` the decision of ``[fusion] decide_with`` (H1 True, H0 False, else
    None); ``slip`` :func:`slip_now`; ``degraded`` a node missing, silent or late; ``least_hold_n``
    raw mode's eq 26a per jaw with the law's mu, ``total_tangential / mu``."""
    decision = record.get("decision")
    present = True if decision == "H1" else False if decision == "H0" else None
    least = None
    forces = record.get("forces")
    if raw and forces is not None and forces.get("total_tangential") is not None:
        total = float(forces["total_tangential"])
        least = abs(total) / params.mu if math.isfinite(total) else None
    degraded = bool(record.get("degraded") or record.get("late_frames") or record.get("missing_nodes"))
    return GripFindings(task=task, present=present, slip=slip_now(record, mem, raw), degraded=degraded,
                        least_hold_n=least, dt_s=dt)


@functools.lru_cache(maxsize=4)
def _drive_od(node_id: int):
    """The drive's EDS imported once per process (a copy per drive: 0.1 s saved per grasp)."""
    return odx.load_od(node_id, GRIPPER_EDS_PATH, "gripper drive")


class OfflineDrive:
    """One :class:`GripperDrive` without a bus, enabled in profile torque (module docstring)."""

    def __init__(self, scene):
        g = scene.gripper
        self.gripper = g
        self.lock = threading.RLock()
        self.scheduler = Scheduler(self.lock, name="bench-grasp-timers")
        link = NodeLink(lambda *frame: None, self.scheduler)
        values = dict(startup_values(scene))
        values[(0x1016, 1)] = 0           # no master heartbeat offline: the drive does not watch it
        values[(0x1017, 0)] = 0           # nor sends its own (timers on the wall clock)
        values[(0x1800, 1)] = 0x80000180 + g.node_id   # no TPDOs: the bus is skipped (the world reads
        values[(0x1801, 1)] = 0x80000280 + g.node_id   # the drive's force directly, as JawCoupling does)
        with self.lock:
            self.drive = GripperDrive(g.node_id, link, od=copy.deepcopy(_drive_od(g.node_id)))
            self.drive.configure(values)
            self.drive.power_on()
            self.drive.on_nmt(NMT_START)
        self.rpdo_id = 0x200 + g.node_id
        self.cycle = -1

    def send(self, controlword: int, force_n: float) -> None:
        with self.lock:
            self.drive.on_rpdo(self.rpdo_id, rpdo1(controlword, torque_of(force_n, self.gripper)))

    def sync(self) -> None:
        with self.lock:
            self.cycle += 1
            self.drive.on_sync(self.cycle, None, None)

    def close(self) -> None:
        self.scheduler.stop()
        with self.lock:
            self.drive.shutdown()


def closed_cycle(scene, k: int, period_us: int, decisions=None, readings=None) -> ClosedCycle:
    n = scene.n
    true = np.ones(n, dtype=bool)
    return ClosedCycle(cycle=k, sync_us=period_us * k, close_us=period_us * k + period_us // 2, sync_counter=None,
                       closed_by="complete",
                       decisions=decisions if decisions is not None else np.zeros(n, dtype=np.int8),
                       readings=readings if readings is not None else np.full(n, np.nan),
                       received=true, expected=true, missing=~true, held_decisions=np.zeros(n, dtype=np.int8),
                       held_readings=np.full(n, np.nan), late_frames=0, bad_frames=0, emcy=())


class BitCounter:
    """Exact bits on the wire per cycle (ISO 11898-1 classic frames with stuffing,
    :func:`fusion_center.core.bus_timing.frame_bits`) of the taxels' PDOs, plus the loop's own
    frames (SYNC, the drive's TPDO1/TPDO2, the centre's RPDO1) priced once."""

    def __init__(self, scene):
        self.ids = [t.node_id for t in scene.taxels]
        self.cache: dict[tuple[int, bytes], int] = {}
        self.total = 0
        self.cycles = 0

    def _bits(self, can_id: int, data: bytes) -> int:
        key = (can_id, data)
        b = self.cache.get(key)
        if b is None:
            b = frame_bits(can_id, data)
            if len(self.cache) < 200_000:
                self.cache[key] = b
        return b

    def add_decisions(self, u: np.ndarray) -> None:
        self.total += sum(self._bits(0x180 + i, b"\x01" if d > 0 else b"\xff") for i, d in zip(self.ids, u))
        self.cycles += 1

    def add_readings(self, x32: np.ndarray) -> None:
        self.total += sum(self._bits(0x280 + i, struct.pack("<f", v)) for i, v in zip(self.ids, x32.tolist()))
        self.cycles += 1

    @staticmethod
    def loop_bits(node_id: int) -> int:
        """SYNC + drive TPDO1 (statusword, torque, position: 8 bytes) + TPDO2 (mode, grip state,
        force, width, error code: 8 bytes) + RPDO1 (8 bytes), typical payloads while holding."""
        return (frame_bits(0x080, b"") + frame_bits(0x180 + node_id, struct.pack("<HhI", 0x1637, 100, 40000))
                + frame_bits(0x280 + node_id, struct.pack("<bBhHH", 4, 4, 100, 400, 0))
                + frame_bits(0x200 + node_id, rpdo1(CW_ENABLE, 100)))


def run_grasp(scene, mode: str, fixed_n: float | None = None, count_bits: bool = False,
              pipeline: CyclePipeline | None = None) -> dict:
    """One grasp of ``scene`` (its ``[grasp]`` task, ``[gripper]`` drive, ``[grip]`` law) in ``mode``:
    "decision" / "raw" (the centre; the scene's bus mode must match) or "fixed" (``fixed_n`` N per
    jaw from the close phase to the release). ``pipeline``: a :class:`CyclePipeline` of this
    scene's layout and mode to reuse (its stateful part, the slip stage, is made afresh here).

    The centre runs from 50 ms before the close phase: before, the task is "open" and the law's
    command is 0 whatever the taxels say (its state stays "open" with no presence run: nothing
    is between the jaws), so skipping those cycles changes nothing but the run time. The grasp
    ends 5 cycles into the release (the object is down) or when it is dropped.

    Returns ``{"rows": [(cycle, phase, normal_n, min_hold_n, slipping, slid_mm, dropped, crushed,
    command_n, centre_slip, in_grip, grip_flags, world_mode), ...], ...}``."""
    period_s = scene.bus.sync_period_ms / 1000.0
    period_us = int(round(scene.bus.sync_period_ms * 1000))
    world = GraspWorld(scene.grasp, period_s)
    drv = OfflineDrive(scene)
    coupling = JawCoupling(world, drv.drive, lock=drv.lock)
    params = scene.grip
    centre = mode in ("decision", "raw")
    if centre:
        if pipeline is None:
            pipeline = CyclePipeline(scene, truth=False)
        else:  # a fresh slip stage (the pipeline's only state) for this grasp
            pipeline.physical = PhysicalEvaluation(scene, pipeline.labels, pipeline.noise,
                                                   slip="slip" in pipeline.plan.run)
    noise = np.array([t.noise_mv for t in scene.taxels])
    zeta = np.array([t.zeta_mv for t in scene.taxels])
    close_at = world.timeline.phase_starts["close"] - 0.05
    state = GripState()
    mem = SlipMemory(band=pipeline.physical._noise_band() if centre else 0.0)
    bits = BitCounter(scene) if count_bits else None
    held: dict = {}
    rows = []
    centre_us: list[float] = []            # the centre's work per cycle: evaluate + findings + law, µs
    release_cycles = 0
    try:
        drv.send(CW_SHUTDOWN, 0.0)
        drv.sync()
        truth = coupling.step()
        drv.send(CW_ENABLE, 0.0)
        k = 0
        while True:
            k += 1
            awake = centre and truth.task_s is not None and truth.task_s >= close_at
            x = truth_readings(scene, truth, k, held) if awake else None   # SYNC k: the world's latest step
            drv.sync()                                          # the RPDO of cycle k - 1 applies
            truth = coupling.step()                             # the world during cycle k
            task = TASK_OF_PHASE.get(truth.phase, "close")
            slip_now = False
            flags: tuple = ()
            if awake:
                if mode == "decision":
                    # each node's detector, eqs 1-4 (local_decision_pm1's comparison, vectorised)
                    u = np.where(x - noise >= zeta, 1, -1).astype(np.int8)
                    closed = closed_cycle(scene, k, period_us, decisions=u)
                    if bits is not None and k % 5 == 0:
                        bits.add_decisions(u)
                else:
                    x32 = x.astype(np.float32)                  # REAL32 on the wire (TPDO2)
                    closed = closed_cycle(scene, k, period_us, readings=x32.astype(float))
                    if bits is not None and k % 5 == 0:
                        bits.add_readings(x32)
                t0 = time.perf_counter()
                record = pipeline.evaluate(closed)
                f = findings_of(record, mem, task, params, period_s, mode == "raw")
                cmd, state = grip_step(params, state, f)
                centre_us.append((time.perf_counter() - t0) * 1e6)
                force = cmd.force_n
                slip_now = f.slip
                flags = cmd.flags
            elif centre:
                force = 0.0
            else:
                force = fixed_n if task == "close" else (-params.open_n if task == "release" else 0.0)
            drv.send(CW_ENABLE, force)
            rows.append((k, truth.phase, truth.normal_n, truth.min_hold_n, truth.slipping, truth.slid_mm,
                         truth.dropped, truth.crushed, force, bool(slip_now), truth.in_grip, flags, truth.mode))
            if truth.phase in ("release", "done"):
                release_cycles += 1
            if truth.dropped or truth.mode == "left" or release_cycles >= 5:
                break
    finally:
        drv.close()
    out = {"rows": rows, "centre_us": centre_us}
    if bits is not None and bits.cycles:
        out["taxel_bits_per_cycle"] = bits.total / bits.cycles
        out["loop_bits_per_cycle"] = BitCounter.loop_bits(scene.gripper.node_id)
    return out


__all__ = ["run_grasp", "findings_of", "slip_now", "OfflineDrive", "rpdo1", "torque_of", "TASK_OF_PHASE"]
