"""The grasp world's ground truth matched to the centre's cycles (issue 23): ``grasp_truth`` in records.

The world (``node_sim.world_runner``, docs/grasp-world.md) steps on its own clock and tags every
step's record with ``cycle``, the twins' number of the last SYNC they had handled when the step
was taken. The taxels answer SYNC ``k`` with the world's latest step at that SYNC, one tagged
``k - 1`` - exactly the last step tagged ``k - 1``, whose record is out before the SYNC's sample
(``node_sim.world_runner.WorldRunner.tag_lock``); so the record of the centre's cycle ``k`` gets
the truth of the steps tagged ``k - 1``:
the last such step's fields, ``slipping`` true when any of them slipped. A SYNC period without a
step (the two clocks drift) takes the latest earlier one, at most :data:`LOOK_BACK` cycles back.
Steps taken before the first SYNC (``cycle`` null) are not used.

The same table serves the demo (filled live by ``Rig(on_truth=...)``, in the world's thread) and
``replay --truth-log FILE`` (read from node-sim's JSON lines), so both give the same records as
long as the twins' and the centre's cycle numbers agree: a node-sim that served an earlier master
numbers its SYNCs on (a centre that takes a grasp over): the match is then off by the cycles it
saw before - the truth there is for plots, not for checks.
"""

from __future__ import annotations

import math
import threading

from taxel_net.json_lines import iter_log
from taxel_net.scene_grasp import PHASES as TASK_PHASES

FIELDS = ("phase", "normal_n", "min_hold_n", "slipping", "slid_mm", "dropped", "crushed")
PHASES = ("idle", *TASK_PHASES, "done")  # a step's phase: before the task, the task's phases, after it
LOOK_BACK = 3
KEEP = 4096  # cycles of truth kept while running (memory does not grow with the run)


class TruthTable:
    """cycle -> the grasp truth of that cycle's record (module docstring); thread-safe ``add``."""

    def __init__(self, bounded: bool = True):
        self.bounded = bounded  # keep only the last KEEP cycles (live); a file read keeps all
        self._by_cycle: dict[int, dict] = {}
        self._lock = threading.Lock()
        self.steps = 0

    def add(self, step: dict) -> None:
        """One world step's record (``Truth.as_dict()`` + ``sync_counter`` + ``cycle``)."""
        cycle = step.get("cycle")
        if cycle is None:
            return
        entry = {k: step.get(k) for k in FIELDS}
        # lost from the grip: it fell (the world's ``dropped``) or the pads slid off it while it stood
        # on the table (the world's mode ``left``) - bench/grasp.py counts both as dropped
        entry["dropped"] = bool(entry["dropped"]) or step.get("mode") == "left"
        in_grip = step.get("in_grip")
        entry["in_grip"] = in_grip if isinstance(in_grip, bool) else None  # the record's "truth" (H1 / H0)
        with self._lock:
            self.steps += 1
            before = self._by_cycle.get(cycle)
            if before is not None and before["slipping"]:
                entry["slipping"] = True
            self._by_cycle[cycle] = entry
            if self.bounded and len(self._by_cycle) > 2 * KEEP:  # live: the records ask for recent cycles only
                for old in [k for k in self._by_cycle if k < cycle - KEEP]:
                    del self._by_cycle[old]

    def for_cycle(self, cycle: int) -> dict | None:
        """The record's ``grasp_truth`` (exactly :data:`FIELDS`), None when not known."""
        entry = self._entry(cycle)
        return None if entry is None else {k: entry[k] for k in FIELDS}

    def presence(self, cycle: int) -> str | None:
        """The record's ``truth`` on a grasp scene: "H1" while the object is between the jaws and
        not lost (the world's ``in_grip``), else "H0"; None when not known (the scene's
        ``[object]`` says nothing there: the world gives the readings)."""
        entry = self._entry(cycle)
        if entry is None or entry["in_grip"] is None:
            return None
        return "H1" if entry["in_grip"] else "H0"

    def _entry(self, cycle: int) -> dict | None:
        with self._lock:
            for k in range(cycle - 1, cycle - 1 - LOOK_BACK, -1):
                entry = self._by_cycle.get(k)
                if entry is not None:
                    return entry
        return None

    @classmethod
    def from_file(cls, path) -> "TruthTable":
        """Read node-sim's ``--truth-log`` (JSON lines); a bad line is one UsageError naming it."""
        table = cls(bounded=False)
        for _, step in iter_log(path, "--truth-log", check=_not_a_step, not_json="not a JSON object ({why})",
                                allow_nan=False):
            table.add(step)
        return table


def _not_a_step(step) -> str | None:
    """What is wrong with one line of a truth log, None if nothing."""
    if not isinstance(step, dict):
        return "not a JSON object"
    cycle = step.get("cycle")
    if cycle is not None and (isinstance(cycle, bool) or not isinstance(cycle, int) or cycle < 0):
        return f"cycle {cycle!r} must be an integer >= 0 or null"
    missing = [k for k in FIELDS if k not in step]
    if missing:
        return f"missing {', '.join(missing)} (not a node-sim truth log?)"
    for k in ("normal_n", "min_hold_n", "slid_mm"):
        v = step[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return f"{k} {v!r} must be a finite number"
    for k in ("slipping", "dropped", "crushed"):
        if not isinstance(step[k], bool):
            return f"{k} {step[k]!r} must be true or false"
    if step.get("in_grip") is not None and not isinstance(step["in_grip"], bool):
        return f"in_grip {step['in_grip']!r} must be true, false or null"
    phase = step["phase"]
    if not isinstance(phase, str) or phase not in PHASES:
        return f"phase {phase!r} must be one of {', '.join(PHASES)}"
    if step.get("mode") is not None and not isinstance(step["mode"], str):
        return f"mode {step['mode']!r} must be a string"
    return None
