"""The grasp world in the twins: :class:`WorldRunner` (issue 22).

Where a scene has both ``[gripper]`` and ``[grasp]`` and a rig serves the drive's channel, the
rig (:mod:`node_sim.rig`) runs one :class:`~node_sim.world.GraspWorld` coupled to its drive
(:class:`~node_sim.world.JawCoupling`) and its taxels read the world instead of the scene's
``[object]`` script:

* **Own clock**: a thread of its own steps the world once per scene SYNC period
  (``bus.sync_period_ms``) on monotonic deadlines (``t0 + k * period``), not on the master's SYNCs:
  gravity does not stop when the master does. A thread that falls behind (a loaded host) catches
  up, one step per missed deadline, so world time keeps to the wall clock. Each step holds the
  drive host's lock (the drive's receive thread waits meanwhile).
* **The task** starts when the drive is first seen in OPERATION ENABLED (``JawCoupling``).
* **Readings**: at each SYNC the taxel nodes sample ``X_i`` of the world's latest step
  (:func:`node_sim.world.taxels.truth_readings`: the footprint, pressure and tangential cells, the
  cycle's canonical noise and the scene's faults). The step's signal ``S_i`` (footprint, pressure,
  tangential and load cells) is computed in the world's thread when it steps, and so is the next
  SYNC's canonical noise ``eps`` (a function of the scene's seed and the cycle); the SYNC adds the
  noise and the faults only (the same floats: ``truth_readings`` of the step's truth). Before the
  first step: no object between the jaws (noise only).
* **Truth out**: every step gives one record, :meth:`Truth.as_dict` plus ``sync_counter`` (the
  counter byte of the last SYNC the drive's channel heard, None without one) and ``cycle`` (the
  twins' cycle number of that SYNC, None before the first): :attr:`latest` and the ``on_truth``
  callbacks (``node-sim --truth-log FILE`` writes them as JSON lines; a caller running the rig in
  its own process passes ``Rig(on_truth=...)`` or reads ``Rig.world_truth``).
* **Which step a SYNC samples**, exactly: the drive channel's SYNC handling sets its SYNC state
  (``cycle`` k) and samples the readings holding :attr:`WorldRunner.tag_lock`, which a step holds
  from reading that state until its truth callbacks have returned. So SYNC k samples the last step
  tagged ``k - 1``, whose record is out before the taxels answer - the step the centre's record of
  cycle k is matched with (``fusion_center.service.grasp_truth``), live and in a replay of the
  truth log alike. (Before: a step that read the state just before a SYNC and published just after
  it was tagged ``k - 1`` without being sampled, its record sometimes after the centre's record of
  cycle k: the live record and the replay's differed.)

Deterministic: the world's steps are a function of the scene and of the drive's state at each
world step (its command sequence), tested with :meth:`step` called by hand; which world step a SYNC
samples depends on the two clocks' phase.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

import numpy as np

from taxel_net.errors import ParameterError

from . import physics
from .world import GraspWorld, JawCoupling
from .world.taxels import truth_signal

logger = logging.getLogger(__name__)

TruthCallback = Callable[[dict], None]


def has_world(scene) -> bool:
    """The scene runs the grasp world in the twins: it has both ``[gripper]`` and ``[grasp]``."""
    return getattr(scene, "grasp", None) is not None and getattr(scene, "gripper", None) is not None


class WorldRunner:
    """The world of ``scene`` coupled to ``drive`` (module docstring).

    ``lock``: the drive host's lock; ``sync_state() -> (sync_counter, cycle)``: the last SYNC the
    twins heard on the drive's channel; ``on_truth``: callbacks called with each step's record (in
    the world's thread; an exception is logged, the world goes on)."""

    def __init__(self, scene, drive, lock=None, sync_state: Callable[[], tuple] | None = None,
                 on_truth: TruthCallback | list[TruthCallback] | None = None, clock=time.monotonic):
        if not has_world(scene):
            raise ParameterError("scene", getattr(scene, "name", scene),
                                 "the grasp world needs both a [gripper] and a [grasp] table")
        self.scene = scene
        self.world = GraspWorld(scene.grasp, scene.bus.sync_period_ms / 1000.0)
        self.coupling = JawCoupling(self.world, drive, lock)
        self._sync_state = sync_state or (lambda: (None, None))
        if on_truth is None:
            self.callbacks: list[TruthCallback] = []
        elif callable(on_truth):
            self.callbacks = [on_truth]
        else:
            self.callbacks = list(on_truth)
        self._clock = clock
        self._truth = None                     # the latest Truth
        self._latest: tuple | None = None      # (the latest Truth, its signal S_i), replaced as one
        self._eps: tuple | None = None         # (cycle, its canonical eps), computed ahead by step()
        self.latest: dict | None = None        # its record
        self._held: dict = {}                  # stuck faults' readings (physics.observe)
        self._read_lock = threading.Lock()
        # held by a step from reading the SYNC state to its truth callbacks' return, and by the drive
        # channel's SYNC handling while it sets that state and samples the readings (module docstring)
        self.tag_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.error: BaseException | None = None
        self.late_steps = 0                    # steps taken after their deadline had passed by a period

    # ------------------------------------------------------------------ one step
    def step(self) -> dict:
        """One world step (the drive read, the world advanced); returns its record."""
        truth = self.coupling.step()
        with self.tag_lock:  # tagged, visible and its record out as one, between two SYNCs' samples
            counter, cycle = self._sync_state()
            record = {"t_s": truth.t_s, "sync_counter": counter, "cycle": cycle}
            record.update(truth.as_dict())
            self._latest = (truth, None)           # readable at once (a SYNC now computes S_i itself)
            self._truth = truth
            self.latest = record
            for cb in list(self.callbacks):
                try:
                    cb(record)
                except Exception:  # noqa: BLE001 - a caller's callback must not stop the world
                    logger.exception("grasp world: a truth callback failed")
        # then, after the step is visible and its record out as before: S_i of this step and the
        # next SYNC's noise (physics.canonical_eps: a function of the seed and the cycle), off the
        # SYNC - a SYNC's readings were most of the rig's SYNC handling for
        # scenes/grasp_lift_patch.toml (0.75-1.0 ms p50 at load 5), on the SYNC -> command path of
        # bench/grip_latency.py. After the callbacks: the step's truth record leaves as promptly
        # as before (a live record takes the truth the table holds when it is made; a later
        # record of the step moves which step a cycle gets - tests/test_grip_stage.py's replay
        # compares them)
        signal = truth_signal(self.scene, truth)
        if self._latest[0] is truth:
            self._latest = (truth, signal)
        upcoming = 0 if cycle is None else cycle + 1
        ahead = self._eps
        if ahead is None or ahead[0] != upcoming:
            self._eps = (upcoming, physics.canonical_eps(self.scene, upcoming))
        return record

    def readings(self, cycle: int) -> np.ndarray:
        """``X_i`` of SYNC ``cycle`` (scene order) from the latest world step (module docstring)."""
        latest, ahead = self._latest, self._eps
        eps = ahead[1] if ahead is not None and ahead[0] == cycle else None   # else computed now
        with self._read_lock:
            if latest is None:
                return physics.observe(self.scene, cycle, np.zeros(self.scene.n), self._held, eps)
            truth, signal = latest
            if signal is None:                 # the step has just been made: its S_i now
                signal = truth_signal(self.scene, truth)
            return physics.observe(self.scene, cycle, signal, self._held, eps)  # truth_readings(truth)

    # ------------------------------------------------------------------ the clock
    def start(self) -> "WorldRunner":
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="node-sim-world", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=5)
            self._thread = None

    def _run(self) -> None:
        period = self.world.step_s
        clock = self._clock
        deadline = clock() + period
        try:
            while not self._stop.wait(max(0.0, deadline - clock())):
                now = clock()
                while deadline <= now and not self._stop.is_set():
                    if now - deadline >= period:
                        self.late_steps += 1
                    self.step()
                    deadline += period
        except Exception as exc:  # noqa: BLE001 - logged once, the twins go on without a world clock
            self.error = exc
            logger.exception("grasp world: stopped at world time %.3f s", self.world.t_s)


__all__ = ["WorldRunner", "has_world", "TruthCallback"]
