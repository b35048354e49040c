"""What a run of a gripper scene did with the object (issue 23): the summary's ``grasp`` verdict.

Accumulated record by record (no record is kept): from the centre's own view (``grip``: its slip
events, the drive's grip state) and, where the records carry the world's truth (``grasp_truth``:
demo, replay with ``--truth-log``), from the world's. The verdict says whether the object was
held, slipped, was caught (stuck again after slipping, not dropped) or dropped; the world's truth
wins where it is known.
"""

from __future__ import annotations


class GraspOutcome:
    def __init__(self):
        self.records = 0
        self.slip_cycles = 0
        self.slip_events = 0
        self._slip_before = False
        self.max_command_n = None
        self.holding_seen = False
        self.part_lost = False
        self.last: dict | None = None
        self.released = False
        # the world's truth
        self.truth_records = 0
        self.truth_slip_cycles = 0
        self.truth_slip_events = 0
        self._truth_slip_before = False
        self.slid_mm_max = 0.0
        self.dropped = False
        self.crushed = False
        self.last_truth: dict | None = None
        self.max_normal_n = 0.0

    def add(self, record: dict) -> None:
        grip = record.get("grip")
        if not grip:
            return
        self.records += 1
        slip = bool(grip.get("slip"))
        self.slip_cycles += slip
        self.slip_events += slip and not self._slip_before
        self._slip_before = slip
        command = grip.get("command_n")
        if command is not None and (self.max_command_n is None or command > self.max_command_n):
            self.max_command_n = command
        state = grip.get("grip_state")
        self.holding_seen |= state == "HOLDING"
        self.part_lost |= state == "PART_LOST"
        self.released |= state == "RELEASED"
        self.last = grip
        truth = record.get("grasp_truth")
        if truth:
            self.truth_records += 1
            slipping = bool(truth.get("slipping"))
            self.truth_slip_cycles += slipping
            self.truth_slip_events += slipping and not self._truth_slip_before
            self._truth_slip_before = slipping
            self.slid_mm_max = max(self.slid_mm_max, abs(truth.get("slid_mm") or 0.0))
            self.max_normal_n = max(self.max_normal_n, truth.get("normal_n") or 0.0)
            self.dropped |= bool(truth.get("dropped"))
            self.crushed |= bool(truth.get("crushed"))
            self.last_truth = truth

    def verdict(self) -> str:
        if self.truth_records:
            if self.dropped:
                what = "dropped (lost from the grip: it fell, or the pads slid off it)"
            elif not self.holding_seen:
                what = "never held"
            elif self.truth_slip_events:
                what = (f"slipped ({self.truth_slip_events} episode(s), {self.slid_mm_max:.1f} mm), caught: "
                        + ("held after the slip" if not (self.last_truth or {}).get("slipping") else "still slipping"))
            else:
                what = "held, never slipped"
            if self.crushed:
                what += "; CRUSHED (above the object's max force)"
            if self.released and not self.dropped:
                what += "; released at the end"
            return what + " (the world's truth)"
        if self.part_lost:
            return "dropped (the drive reported PART_LOST)"
        if not self.holding_seen:
            return "never held (the drive never reported HOLDING)"
        slipped = f"slipped ({self.slip_events} event(s) seen by the centre), caught" if self.slip_events else "held"
        end = (self.last or {}).get("grip_state")
        return f"{slipped}; the drive's grip state at the end: {end} (the centre's view, no world truth)"

    def as_dict(self) -> dict:
        out = {"verdict": self.verdict(), "records": self.records, "slip_cycles": self.slip_cycles,
               "slip_events": self.slip_events, "max_command_n": self.max_command_n,
               "held": self.holding_seen and not self.part_lost and not self.dropped,
               "final": self.last}
        if self.truth_records:
            out["truth"] = {"slip_cycles": self.truth_slip_cycles, "slip_episodes": self.truth_slip_events,
                            "slid_mm_max": round(self.slid_mm_max, 3), "dropped": self.dropped,
                            "crushed": self.crushed, "max_normal_n": round(self.max_normal_n, 3)}
        return out
