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
3. **The centre** closes cycle ``k`` (every node delivered: a :class:`ClosedCycle`, with the
   drive's TPDO values of SYNC ``k`` as the stream would have decoded them,
   :class:`fusion_center.service.drive_frames.DriveCycle`) and evaluates it with the live centre's
   :class:`fusion_center.service.pipeline.CyclePipeline` - fusion, forces in raw mode, slip and
   **the grip stage** (:class:`fusion_center.service.grip_stage.GripStage`: the drive's walk to
   OPERATION ENABLED, the task from ``[grasp]``'s phases, the findings, the law
   :func:`fusion_center.core.grip_law.grip_step`, the controlword) - and sends the stage's command
   in the drive's RPDO1 (controlword, target torque in ‰ of the rated force) - applied at SYNC
   ``k + 1``. The same code as a live run's, cycle for cycle.

The baselines (a fixed force) skip the centre: the same drive, world and task, a constant command
from the close phase to the release.
"""

from __future__ import annotations

import copy
import functools
import struct
import threading
import time
from dataclasses import replace

import numpy as np

from fusion_center.core.bus_timing import frame_bits
from fusion_center.service.cycle_records import ClosedCycle
from fusion_center.service.drive_frames import DriveCycle
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
        self.send_torque(controlword, torque_of(force_n, self.gripper))

    def send_torque(self, controlword: int, torque_permille: int) -> None:
        with self.lock:
            self.drive.on_rpdo(self.rpdo_id, rpdo1(controlword, torque_permille))

    def state(self, t_us: int) -> DriveCycle:
        """What the centre's stream decodes of the drive's TPDO1 / TPDO2 of this SYNC
        (:class:`fusion_center.service.drive_frames.DriveCycle`), read from its OD."""
        with self.lock:
            read = self.drive.objects.read
            values = [read(index) for index in (0x6041, 0x6077, 0x6064, 0x6061, 0x2100, 0x2101, 0x2102, 0x603F)]
        return DriveCycle(True, False, 0x05, *values, t_us, None)

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
    jaw from the close phase to the release, the drive enabled by the bench). ``pipeline``: a
    :class:`CyclePipeline` of this scene's layout and mode to reuse (its per-run state, the slip
    tracker and the grip stage, renewed here: :meth:`CyclePipeline.new_run`).

    The centre evaluates every cycle from the first: it walks the drive to OPERATION ENABLED as a
    live centre does, and the world's task starts there (``docs/grasp-world.md``). The grasp ends
    5 cycles into the release (the object is down) or when it is dropped.

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
        else:
            pipeline.new_run(scene)  # this grasp's mu, [grip], [grasp] and drive
        if pipeline.grip is None:
            raise ValueError(f"scene {scene.name!r}: the grip stage does not run ({pipeline.plan.skipped.get('grip')})")
    noise = np.array([t.noise_mv for t in scene.taxels])
    zeta = np.array([t.zeta_mv for t in scene.taxels])
    bits = BitCounter(scene) if count_bits else None
    held: dict = {}
    rows = []
    centre_us: list[float] = []            # the centre's work per cycle: the pipeline with its grip stage, µs
    release_cycles = 0
    try:
        if not centre:  # the baselines: the bench enables the drive itself
            drv.send(CW_SHUTDOWN, 0.0)
            drv.sync()
            drv.send(CW_ENABLE, 0.0)
        truth = coupling.step()
        k = 0
        while True:
            k += 1
            x = truth_readings(scene, truth, k, held) if centre else None   # SYNC k: the world's latest step
            drv.sync()                                          # the RPDO of cycle k - 1 applies
            truth = coupling.step()                             # the world during cycle k
            task = TASK_OF_PHASE.get(truth.phase, "close")
            slip_now = False
            flags: tuple = ()
            if centre:
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
                closed = replace(closed, drive=drv.state(period_us * k))
                t0 = time.perf_counter()
                record = pipeline.evaluate(closed)
                centre_us.append((time.perf_counter() - t0) * 1e6)
                grip = record["grip"]
                force = grip["command_n"] if grip["command_n"] is not None else 0.0
                slip_now = bool(grip["slip"])
                flags = tuple(record.get("grip_flags", ()))
                command = pipeline.grip.command
                if command is not None:
                    drv.send_torque(*command)
            else:
                force = fixed_n if task == "close" else (-params.open_n if task == "release" else 0.0)
                drv.send(CW_ENABLE, force)
            rows.append((k, truth.phase, truth.normal_n, truth.min_hold_n, truth.slipping, truth.slid_mm,
                         truth.dropped, truth.crushed, force, slip_now, truth.in_grip, flags, truth.mode))
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


__all__ = ["run_grasp", "OfflineDrive", "rpdo1", "torque_of", "TASK_OF_PHASE"]
