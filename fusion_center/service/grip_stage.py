"""The grip stage (issue 23): from a closed cycle's record and the drive's state to a grip command.

Pure with respect to the bus and the clock, like the rest of the pipeline: its inputs are the
record the other stages made of the cycle and :class:`~.drive_frames.DriveCycle` (the drive as the
event stream knew it when the cycle closed), its state is carried from cycle to cycle, so a replay
of the trace gives the same ``grip`` fields and the same commands as the live run. The service
(:mod:`.drive_link`) sends :attr:`GripStage.command` in the drive's RPDO1 right after the record.

Per cycle (``docs/service.md``, "The grip stage"; the law: ``docs/grip-control.md``):

* **findings** for :func:`fusion_center.core.grip_law.grip_step`: ``present`` the HEBTEM decision
  of ``[fusion] decide_with`` (H1 True, H0 False, undecided None); ``slip`` the centre's slip
  *this cycle* (:meth:`GripStage.slip_now`: the slip stage latches ``slipping`` until contact is
  lost, so the law gets the per-cycle events: the centroid of the present taxels reached a new
  farthest displacement from the contact's reference - beyond the slip stage's noise band, half a
  taxel pitch - in this cycle or the ``slip_hold`` - 1 before it (default 3, the slip stage's
  ``motion_consecutive``: one-bit decisions see the position only in taxel pitches, so a sliding
  contact moves the centroid once per pitch, not every cycle); before the contact's first such
  event also the **edge cue**: a displacement beyond ``[grip] edge_fraction`` of the band for
  ``edge_cycles`` cycles in a row (0.4, 2) - the first location at the footprint's edge switching
  moves the centroid by less than the band, below a pitch of slide (``docs/grip-control.md``); or,
  in raw mode, ``TotF_t > mu F_g`` this cycle, eq 26a). The **footprint forming** is no slip: the
  presence cells see the object before the jaws touch it, so the slip tracker's reference is their
  centroid, which the pressure cells switching on as the jaws press move by up to the band (a
  contact off the pads' middle); from the drive's first force on the part (0x2101 > 0) the motion
  cue waits ``settle_s``, then the stage has the tracker take its reference again (``rebase``, the
  pipeline's ``SlipTracker.reset``), once per contact; once the jaws let go (a force of 0) there is
  no motion cue. ``actual_n`` the drive's force (0x2101:
  when the law's last raise has arrived); ``degraded`` a cycle with a
  taxel missing, silent or late, or (raw patch scenes) a node's readings clipped at a packed
  limit code (``over_range_nodes``: the load they carry is at least what they say, so the law
  may raise on them, never relax); ``least_hold_n`` in raw mode eq 26a per jaw, ``T / mu`` with T the
  forces stage's tangential load per jaw (sec 7.2: the mean over the jaws) and mu the law's.
* **task** from the scene's ``[grasp]`` phases and the SYNC time (the record's ``t``) since the
  cycle the drive was first seen OPERATION ENABLED (the world starts its task clock there,
  docs/grasp-world.md; time, not cycles x period: a SYNC producer that falls behind skips SYNCs,
  the world's clock goes on): ``open`` in the
  approach, ``close`` from the close phase through the place phase, ``release`` from the release
  phase on. Without ``[grasp]``: ``close`` from the first OPERATION ENABLED on (grip what is
  present, never release by itself).
* **CiA 402**: the controlword that keeps the drive where it is, or the next step toward
  OPERATION ENABLED (canopen's ``State402`` tables): at the first sight of the drive, then after a
  fault, a quick stop or a disable at most once every :data:`RECOVER_EVERY_S` s (a fault reset -
  bit 7's edge - or a re-enable walk of at most :data:`WALK_CYCLES` cycles); never in a tight loop.
  canopen's ``BaseNode402`` is not used for this: its ``state`` setter blocks (polling the
  statusword, ``TIMEOUT_CHECK_TPDO`` 0.2 s per step) where this runs on the receive thread every
  cycle, and it sends a synchronous RPDO only on ``transmit()``; the drive applies RPDO1 at the
  next SYNC, so one step per cycle is what it can take.
* **takeover**: a drive first seen in OPERATION ENABLED with a positive torque (a centre started
  again while it holds a part) is not walked nor opened: the law starts in ``hold`` with the
  drive's present force (0x2101), also as its learned force (this centre does not know what the
  part needs, so it does not relax below what held it; a slip still raises it), the task is
  ``close`` (the task clock is unknown) - the part stays held and this centre commands it. The
  force is cross-checked (:meth:`GripStage.takeover_force`, 2026-11-30 (stop 32)): 0x2101 outside
  ``[0, max_n]`` or off the torque-derived force ``0x6077 x rated / 1000`` by more than
  :data:`TAKEOVER_TOLERANCE` of it (or :data:`TAKEOVER_TOLERANCE_N`) is not trusted - the
  torque's force is used, flagged ``drive_force_implausible`` and counted.
* **safety**: the law never lowers the command on a degraded cycle - a lost drive heartbeat is a
  degraded cycle too (its state and force may be stale); while the drive is not OPERATION ENABLED
  the law is not stepped (its command kept). A drive not NMT operational (a boot-up: flagged
  ``drive_booted`` too, pre-operational or stopped: it sends no PDO and drops its RPDO) has no
  present state (``drive_state`` None): the law is not stepped, nothing is sent, the record is
  flagged ``drive_not_operational``, and the service sends the drive an NMT start
  (:meth:`.drive_link.DriveLink.start_again`); its re-enable walk follows once its TPDO1 is seen
  again. A drive fault, a quick stop, a disable, a lost drive heartbeat, a drive not NMT
  operational, a mode other than profile torque are flagged (``grip_flags``) and counted per
  episode (:attr:`counts`); boot-ups counted each.
"""

from __future__ import annotations

import math

from ..core.grip_law import GripFindings, GripParams, GripState, grip_step
from .drive_frames import DriveCycle, grip_state_name
from .records import jsonable

RECOVER_EVERY_S = 1.0   # at most one fault reset / re-enable attempt per this many seconds
WALK_CYCLES = 10        # cycles a re-enable walk may take (SWITCH ON DISABLED -> OPERATION ENABLED: 2-4)
PROFILE_TORQUE = 4      # 0x6060 / 0x6061
# a takeover's 0x2101 must agree with the torque-derived force within this fraction of it, or this many N
TAKEOVER_TOLERANCE = 0.1
TAKEOVER_TOLERANCE_N = 1.0

OE = "OPERATION ENABLED"
# the controlword that keeps the drive in its state (no transition), and the next step toward OE
_HOLD_CW = {"NOT READY TO SWITCH ON": 0x00, "SWITCH ON DISABLED": 0x00, "READY TO SWITCH ON": 0x06,
            "SWITCHED ON": 0x07, OE: 0x0F, "QUICK STOP ACTIVE": 0x02, "FAULT REACTION ACTIVE": 0x00,
            "FAULT": 0x00}
# State402.TRANSITIONTABLE's commands toward OE; READY TO SWITCH ON -> OE at once (3 then 4: 0x0F)
_STEP_CW = {"SWITCH ON DISABLED": 0x06, "READY TO SWITCH ON": 0x0F, "SWITCHED ON": 0x0F, OE: 0x0F}
CW_FAULT_RESET = 0x80


def default_params(scene) -> GripParams:
    """``Scene.grip`` where the scene has a ``[grip]`` table, else the law's defaults with the
    scene's ``[forces] mu`` and the drive's most force per jaw (rated force x max torque)."""
    grip = getattr(scene, "grip", None)
    if grip is not None:
        return grip
    g = scene.gripper
    most = g.rated_force_n * g.max_torque_permille / 1000.0
    base = GripParams()
    return GripParams(mu=scene.forces.mu, max_n=most, grasp_n=min(base.grasp_n, most),
                      min_n=min(base.min_n, most))


def task_schedule(scene, period_s: float) -> list[tuple[float, str]] | None:
    """``[(start_s, task)]`` of ``[grasp]``'s phases (None without ``[grasp]``)."""
    grasp = getattr(scene, "grasp", None)
    if grasp is None:
        return None
    out, t = [], 0.0
    for phase in grasp.phases:
        task = "open" if phase.name == "approach" else "release" if phase.name == "release" else "close"
        out.append((t, task))
        t += phase.duration_s
    return out


class GripStage:
    """One scene's grip stage (module docstring). ``evaluate(record, closed)`` adds ``grip``,
    ``grip_flags`` and ``grip_detail`` to the record and sets :attr:`command`
    ``(controlword, target torque ‰)`` for this cycle, or None (nothing to send: the drive's state
    is not known yet)."""

    def __init__(self, scene, *, noise_band: float | None = None, slip_hold: int = 3, rebase=None):
        g = scene.gripper
        self.params = default_params(scene)
        self.rated_n = g.rated_force_n
        self.max_permille = g.max_torque_permille
        self.period_s = scene.bus.sync_period_ms / 1000.0
        self.schedule = task_schedule(scene, self.period_s)
        self.raw = scene.bus.mode == "raw"
        self.band = noise_band if noise_band is not None else 0.0
        self.recover_cycles = max(1, math.ceil(RECOVER_EVERY_S / self.period_s))
        self.law = GripState()
        self.command: tuple[int, int] | None = None
        self._defer = False              # evaluate's defer_record
        self._deferred: tuple | None = None  # the record fields' arguments, until write_record
        self.enabled_at: int | None = None   # cycle the drive was first seen OPERATION ENABLED
        self.enabled_t = 0.0                 # its SYNC time (the record's t), s
        self.takeover = False
        self.seen = False                    # the drive's state known (a TPDO1 seen)
        self.last_attempt: int | None = None  # cycle of the last walk / fault reset start
        self.walk_until = -1
        self.reset_sent = False
        self.last_cw = 0
        self.last_state: str | None = None
        self.lost = False
        self.not_operational = False         # the drive's NMT state was not OPERATIONAL last cycle
        self.wrong_mode = False              # 0x6061 was not profile torque last cycle
        self.peak: float | None = None       # slip_now: farthest displacement reached in this contact
        self.peak_cycle: int | None = None   # the cycle it was reached
        self.slip_hold = slip_hold
        self.edge_band = self.band * self.params.edge_fraction  # slip_now's edge cue (sub-pitch), before the first slip flag
        self.edge_cycles = self.params.edge_cycles              # ... that many cycles in a row (a flicker is no slip)
        self.edge_run = 0                           # cycles in a row beyond edge_band
        self.slip_new = False                       # slip_now's flag is a new farthest displacement this cycle
        self.rebase = rebase                        # the slip tracker's reset: its reference taken again
        self.pressed_t: float | None = None         # SYNC time the jaws first pressed on this contact
        self.rebased = False                        # ... and its reference was taken again settle_s later
        self.counts = {"drive_faults": 0, "quick_stops": 0, "drive_disabled": 0, "drive_lost": 0,
                       "fault_resets": 0, "enable_walks": 0, "takeovers": 0, "degraded_holds": 0,
                       "drive_bootups": 0, "drive_not_operational": 0, "drive_mode": 0, "drive_force_implausible": 0}

    # ------------------------------------------------------------------ findings
    def slip_now(self, record: dict, pressing: bool | None = None) -> bool:
        """The centre's slip this cycle (module docstring) from the slip stage's record; ``pressing``:
        the drive reports a force on the part (0x2101 > 0: its jaws press on it), False a force of
        0, None not known."""
        self.slip_new = False
        slip = record.get("slip")
        if not slip or not slip.get("contact"):
            self.peak = self.peak_cycle = None
            self.edge_run = 0
            self.pressed_t, self.rebased = None, False
            return False
        now = False
        displacement = slip.get("displacement")
        unobserved = slip.get("observed") is False   # the cycle saw nothing of the contact (lost, late)
        if self.rebased and pressing is False:
            displacement = None     # the jaws let go (release, a lost part): the footprint dissolves
            unobserved = False
        elif self.rebase is not None and not self.rebased:
            # the footprint forms as the jaws press (the contact was seen before, by presence cells
            # alone): no motion cue from the first press until settle_s later, then the slip
            # tracker's reference is taken again (docs/grip-control.md, "the footprint forms")
            if pressing and self.pressed_t is None:
                self.pressed_t = record["t"]
            if self.pressed_t is not None:
                if record["t"] - self.pressed_t >= self.params.settle_s - 1e-9:
                    self.rebase()
                    self.rebased = True
                self.peak = self.peak_cycle = None
                self.edge_run = 0
                displacement = None
        if displacement is not None:
            peak = self.band if self.peak is None else self.peak
            if displacement > peak + 1e-9:
                self.peak_cycle = record["cycle"]
                self.peak = displacement
            elif self.peak is None:
                self.peak = self.band
            if self.peak_cycle is None:
                # the edge cue: the contact's first edge location switching (sub-pitch) moves the
                # centroid by less than the band; beyond edge_band for edge_cycles cycles in a row
                self.edge_run = self.edge_run + 1 if displacement > self.edge_band + 1e-9 else 0
                if self.edge_run >= self.edge_cycles:
                    self.peak_cycle = record["cycle"]   # the peak stays at the band: the full pitch flags again
        if displacement is not None or unobserved:
            # (unobserved: nothing measured - the flag of the last new farthest displacement held as
            # long as it would have been: the motion it stood for is not known to have stopped)
            now = self.peak_cycle is not None and record["cycle"] - self.peak_cycle < self.slip_hold
            self.slip_new = now and displacement is not None and self.peak_cycle == record["cycle"]
        ratio = slip.get("force_ratio")
        if self.raw and ratio is not None and ratio > 1.0:
            now = self.slip_new = True
        return now

    def least_hold_n(self, record: dict) -> float | None:
        """Raw mode: eq 26a per jaw, ``T / mu`` (the forces stage's tangential load per jaw)."""
        forces = record.get("forces")
        if not forces:
            return None
        total = forces.get("total_tangential")
        if total is None or not math.isfinite(total):
            return None
        return abs(total) / self.params.mu

    def task(self, t_s: float) -> str:
        """The task at SYNC time ``t_s`` (the record's ``t``, the stream's clock): the time since the
        SYNC of the cycle the drive was first seen OPERATION ENABLED, not cycles x period - a SYNC
        producer that falls behind skips SYNCs, the world's clock does not."""
        if self.takeover:
            return "close"
        if self.enabled_at is None:
            return "open"
        if self.schedule is None:
            return "close"
        elapsed = t_s - self.enabled_t
        task = "open"
        for start, name in self.schedule:
            if elapsed + 1e-9 >= start:
                task = name
        return task

    # ------------------------------------------------------------------ the cycle
    def evaluate(self, record: dict, drive: DriveCycle | None, defer_record: bool = False) -> None:
        """The cycle's command (:attr:`command`) and the record's ``grip``, ``grip_flags`` and
        ``grip_detail``; with ``defer_record`` those three only at :meth:`write_record` (the
        pipeline's ``finish``, after the command has left: the same fields, nothing between
        changes what they read)."""
        self._defer = defer_record
        cycle = record["cycle"]
        flags: list[str] = []
        force = drive.force_n if drive is not None and drive.operational else None
        slip = self.slip_now(record, pressing=None if force is None else force > 0)
        state = drive.state if drive is not None else None
        if drive is not None and drive.lost:
            flags.append("drive_lost")
            if not self.lost:
                self.counts["drive_lost"] += 1
        self.lost = bool(drive is not None and drive.lost)
        actual = drive.force_n if drive is not None else None
        if drive is not None and drive.bootups and self.seen:  # (before its state was seen: its start)
            flags.append("drive_booted")
            self.counts["drive_bootups"] += drive.bootups
        off = drive is not None and drive.heard and not drive.operational
        if off != self.not_operational and off:
            self.counts["drive_not_operational"] += 1
        self.not_operational = off
        if off:
            # PRE-OPERATIONAL (booted) or STOPPED: no PDO in either direction (CiA 301), its last
            # statusword / force are stale. The law is not stepped (its command held); nothing is
            # sent (an RPDO would be dropped); the service starts the drive again (DriveLink)
            self.command = None
            flags.append("drive_not_operational")
            held = self.law.command_n if self.seen else None
            self._record(record, held, None, None, drive, slip, flags, self.task(record["t"]) if self.seen else None,
                         None)
            return
        if state is None:
            self.command = None
            flags.append("no_drive_state")
            # (once seen: the drive started again, its first TPDO1 still to come - the law's command held)
            self._record(record, self.law.command_n if self.seen else None, actual, None, drive, slip, flags,
                         self.task(record["t"]) if self.seen else None, None)
            return
        if not self.seen:
            self.seen = True
            if state == OE and (drive.torque_permille or 0) > 0:
                # a centre started again while the drive holds: take the grasp over as it is
                self.takeover = True
                self.enabled_at, self.enabled_t = cycle, record["t"]
                force = self.takeover_force(actual, drive.torque_permille, flags,
                                            holding=grip_state_name(drive.grip_state) == "HOLDING")
                self.law = GripState(phase="hold", command_n=force, learned_n=force)
                self.counts["takeovers"] += 1
                flags.append("takeover")
        if state == OE and self.enabled_at is None:
            self.enabled_at, self.enabled_t = cycle, record["t"]
        self._count_transition(state, flags)
        wrong_mode = drive.mode is not None and drive.mode != PROFILE_TORQUE
        if wrong_mode:
            flags.append("drive_mode")
            if not self.wrong_mode:
                self.counts["drive_mode"] += 1
        self.wrong_mode = wrong_mode
        task = self.task(record["t"])
        if state == OE:
            present = {"H1": True, "H0": False}.get(record.get("decision"))
            # readings clipped at a packed limit code (over_range_nodes) under-state the load: degraded too
            # and a lost drive (its heartbeat expired: the state and force are its last, maybe stale)
            degraded = bool(record.get("degraded") or record.get("late_frames") or record.get("missing_nodes")
                            or record.get("over_range_nodes") or drive.lost)
            findings = GripFindings(task=task, present=present, slip=slip, degraded=degraded,
                                    least_hold_n=self.least_hold_n(record) if self.raw else None,
                                    dt_s=self.period_s, actual_n=actual, slip_new=self.slip_new)
            out, self.law = grip_step(self.params, self.law, findings)
            command_n = out.force_n
            flags.extend(out.flags)
            if "held_degraded" in out.flags:
                self.counts["degraded_holds"] += 1
        else:
            command_n = self.law.command_n
        cw = self._controlword(state, cycle, flags)
        permille = max(-self.max_permille, min(self.max_permille, round(command_n * 1000.0 / self.rated_n)))
        self.command = (cw, permille)
        self.last_cw = cw
        self._record(record, command_n, actual, state, drive, slip, flags, task, (cw, permille))

    def takeover_force(self, actual: float | None, torque_permille: int, flags: list[str],
                       holding: bool = True) -> float:
        """The force a takeover starts the law with: the drive's 0x2101 when it is within
        ``[0, max_n]`` and agrees with the torque-derived force ``0x6077 x rated / 1000`` (the
        drive's own rule, docs/gripper-drive.md) within :data:`TAKEOVER_TOLERANCE` of it or
        :data:`TAKEOVER_TOLERANCE_N`, whichever is larger; else the torque-derived force (clamped
        to ``[0, max_n]``), flagged ``drive_force_implausible`` and counted. A drive whose grip state
        is not HOLDING (0x2100: its jaws not pressing on a part) reports 0x2101 = 0 whatever its
        torque: the torque-derived force, not flagged."""
        from_torque = min(max(torque_permille * self.rated_n / 1000.0, 0.0), self.params.max_n)
        if not holding:
            return from_torque
        tolerance = max(TAKEOVER_TOLERANCE * from_torque, TAKEOVER_TOLERANCE_N)
        if (actual is not None and math.isfinite(actual) and 0.0 <= actual <= self.params.max_n
                and abs(actual - from_torque) <= tolerance):
            return actual
        flags.append("drive_force_implausible")
        self.counts["drive_force_implausible"] += 1
        return from_torque

    def _count_transition(self, state: str, flags: list[str]) -> None:
        before = self.last_state
        self.last_state = state
        if state in ("FAULT", "FAULT REACTION ACTIVE"):
            flags.append("drive_fault")
            if before not in ("FAULT", "FAULT REACTION ACTIVE"):
                self.counts["drive_faults"] += 1
        elif state == "QUICK STOP ACTIVE":
            flags.append("quick_stop")
            if before != state:
                self.counts["quick_stops"] += 1
        elif state != OE and before == OE:
            self.counts["drive_disabled"] += 1
        if state != OE and self.enabled_at is not None:
            flags.append("drive_not_enabled")

    def _controlword(self, state: str, cycle: int, flags: list[str]) -> int:
        """Keep the drive in its state, or take one step toward OPERATION ENABLED while a walk is
        allowed (module docstring: at the first sight, then at most every RECOVER_EVERY_S)."""
        if state == OE:
            self.walk_until = -1  # a walk ends where it was going: a new disable waits for the next attempt
            return _HOLD_CW[OE]
        if cycle > self.walk_until and (self.last_attempt is None or cycle - self.last_attempt >= self.recover_cycles):
            if state in _STEP_CW or state == "FAULT":
                self.last_attempt = cycle
                self.walk_until = cycle + WALK_CYCLES
                self.reset_sent = False
                self.counts["enable_walks"] += 1
        if cycle <= self.walk_until:
            if state == "FAULT":  # bit 7's rising edge (after a cycle without it), once per walk
                if self.last_cw & CW_FAULT_RESET == 0 and not self.reset_sent:
                    self.reset_sent = True
                    self.counts["fault_resets"] += 1
                    flags.append("fault_reset")
                    return CW_FAULT_RESET
                return 0x00
            if state in _STEP_CW:
                return _STEP_CW[state]
        return _HOLD_CW.get(state, 0x00)

    def _record(self, *args) -> None:
        if self._defer:
            self._deferred = args
        else:
            self._write(*args)

    def write_record(self) -> None:
        """The record fields :meth:`evaluate` deferred (``defer_record``), if any."""
        args, self._deferred = self._deferred, None
        if args is not None:
            self._write(*args)

    def _write(self, record, command_n, actual, state, drive, slip, flags, task, command) -> None:
        record["grip"] = {
            "command_n": None if command_n is None else jsonable(round(command_n, 4)),
            "actual_n": actual,
            "drive_state": state,
            "grip_state": grip_state_name(drive.grip_state) if drive is not None and drive.operational else None,
            "slip": bool(slip),
        }
        record["grip_flags"] = flags
        detail = {"task": task, "law": self.law.phase,
                  "controlword": None if command is None else command[0],
                  "target_permille": None if command is None else command[1]}
        if drive is not None and drive.error_code:
            detail["error_code"] = f"0x{drive.error_code:04X}"
        if drive is not None and drive.emcy:
            detail["emcy"] = [f"0x{code:04X}" for code, _, _ in drive.emcy]
        record["grip_detail"] = detail
