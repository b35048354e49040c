"""Per-cycle evaluation: one :class:`ClosedCycle` -> one JSON-able record (dict).

Pure with respect to the bus: the record is a function of the closed cycle, the scene and
the pipeline's own state carried from cycle to cycle (the slip tracker), so live runs and
replays produce identical records.

:class:`CyclePipeline` composes the jobs, each in its module (chapter sections in brackets):

* fusion (sec. 2.2), :mod:`.decision_fusion`: every rule of ``[fusion] rules`` the scene
  supports over the decisions *received* in the cycle, thresholds and rule results cached
  (see there). The record's ``decision`` is the verdict of ``[fusion] decide_with``.
* raw mode (issue 6): the nodes send X_i (TPDO2, REAL32 mV) instead of u_i; the centre
  decides per taxel with the nodes' own test (eqs 1-4, ``encoding.LocalDetectors``, here:
  ``local_decision`` bit for bit) and fuses those decisions with every rule as in decision
  mode; :mod:`.centralised_tests` runs the centralised raw-data tests on the readings.
* forces (sec. 4.1-4.2, 7; raw mode only), area (eq 35), contact type (eqs 34a/34b) and slip
  (sec. 4), :mod:`.physical`.
* ground truth (``truth``): :mod:`node_sim.physics`, precomputed for the scene's cycles.

Every record says what did not run and why: ``stages_skipped`` (stage -> reason) and
``rules_skipped`` (fusion rule or centralised test -> reason), computed once per scene by
:func:`fusion_center.stages.plan_stages` and copied into each record.

Live fast path: everything that depends only on the decision vector (received and present
sets, fusion rules, area, t_c/fp_c and contact types) is cached per vector (``_pattern``): a
sensor at rest or under a steady contact repeats its vector, so most cycles only copy it; a
new vector costs the computation of :mod:`.decision_fusion` and :mod:`.physical` (the tail of
the SYNC -> record latency: a new contact pattern needs a convex hull, eq 35, and a new
received set its thresholds).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..core.encoding import LocalDetectors
from taxel_net.patches import node_label
from taxel_net.scene import Scene
from ..stages import plan_stages
from .centralised_tests import CentralisedTests
from .cycle_records import STATE_RESETTING, ClosedCycle
from .decoder import STATE_NAMES as _DECODER_STATE_NAMES
from .decision_fusion import DecisionFusion
from .over_range import OverRangeTracker
from .physical import PhysicalEvaluation
from .records import jsonable


STATE_NAMES = {**_DECODER_STATE_NAMES, STATE_RESETTING: "resetting"}
TRUTH_PRECOMPUTED = 4096  # cycles whose ground truth is computed when the pipeline is built


def node_labels(scene: Scene) -> list:
    """Label of every CANopen node (``taxel_net.patches.devices`` order): its node-ID on channel
    0, ``"C:ID"`` on channel C; in a one-taxel scene the node of taxel i is node i."""
    if not scene.bus.patch_nodes:
        return [node_label(t.channel, t.node_id) for t in scene.taxels]
    from taxel_net.patches import devices

    return [node_label(d.channel, d.node_id) for d in devices(scene)]


def taxel_labels(scene: Scene) -> list:
    """Label of every taxel in records (``present_nodes``, forces per taxel): its node's label
    in a one-taxel scene; ``"ID/k"`` (``"C:ID/k"`` off channel 0) for taxel k (0-based, the
    patch's own order) of patch node ID."""
    if not scene.bus.patch_nodes:
        return node_labels(scene)
    from taxel_net.patches import devices

    labels: list = [None] * scene.n
    for d in devices(scene):
        for k, i in enumerate(d.taxels):
            labels[i] = f"{d.label}/{k}"
    return labels


class _Pattern(NamedTuple):
    """Everything of a record that depends only on the cycle's decision vector (cached per vector)."""

    received: np.ndarray        # bool per taxel
    present_mask: np.ndarray    # bool per taxel
    n_received: int
    present: int
    present_nodes: tuple
    rules: dict                 # fusion rule -> JSON-able result (copied into each record)
    area: float | None          # eq 35 (None: stage not run)
    contact: tuple              # (key, value) pairs: t_c, contact_type, fp_c, contact_type_fp
    centroid: np.ndarray | None  # the slip stage's centroid of the present taxels' locations (None: no slip stage)


class PendingRecord:
    """One cycle between :meth:`CyclePipeline.evaluate_command` and :meth:`CyclePipeline.finish`."""

    __slots__ = ("closed", "readings", "available", "pattern", "central", "t_seconds", "forces", "slip",
                 "grip_view", "over_range_nodes")

    def __init__(self, closed: ClosedCycle):
        self.closed = closed
        self.readings = self.available = self.pattern = None
        self.central: dict | None = None       # the centralised tests' results, when one decides
        self.t_seconds = 0.0
        self.forces = None                     # raw mode: .core.forces.CycleForces
        self.slip: dict | None = None          # the slip stage's record
        self.grip_view: dict | None = None     # what the grip stage read and wrote (grip, grip_flags, grip_detail)
        self.over_range_nodes: list | None = None  # raw patch scenes: nodes whose readings are clipped (.over_range)


class CyclePipeline:
    """Evaluate closed cycles of one scene (stateful only through the slip tracker)."""

    def __init__(self, scene: Scene, *, truth: bool = True):
        self.scene = scene
        self.with_truth = truth
        self.plan = plan_stages(scene)
        fusion = scene.fusion
        self.decide_with = fusion.decide_with
        taxels = scene.taxels
        self.labels = taxel_labels(scene)
        self.node_labels = node_labels(scene)  # per device (CANopen node): nodes_by_state & co
        self.n = scene.n
        self.zeta = np.array([t.zeta_mv for t in taxels], dtype=float)
        self.noise = np.array([t.noise_mv for t in taxels], dtype=float)
        self.raw_mode = scene.bus.mode == "raw"
        self.detectors = LocalDetectors(self.noise, self.zeta)  # raw mode: the nodes' decisions, centrally
        self.mode = scene.bus.mode
        self.stages_skipped = dict(self.plan.skipped)
        self.rules_skipped = self.plan.all_rules_skipped
        # centralised raw-data tests: parameters and thresholds once per scene (raw mode only)
        self.centralised = CentralisedTests(scene, self.plan.central_run)
        self.central = self.centralised.params  # test name -> parameters of the full set
        self.hold = scene.bus.transmission_type != 1
        self.grip = None  # the grip stage ([gripper] scenes, .grip_stage): a command for the drive per cycle
        # raw patch scenes: nodes whose packed readings are clipped (their over-range EMCYs, .over_range)
        self.over_range = OverRangeTracker(self.node_labels) if scene.bus.patch_nodes and self.raw_mode else None
        self.new_run()   # the slip tracker (self.physical), the grip stage, the over-range tracker
        self.xy = self.physical.xy
        self.want_forces = "forces" in self.plan.run and self.raw_mode
        self.want_area = "area" in self.plan.run and self.xy is not None
        self.want_contact = "contact_type" in self.plan.run
        self.want_slip = self.physical.slip is not None
        self.fusion = DecisionFusion(scene, tuple(r for r in fusion.rules if r in self.plan.rules_run))
        self.grasp_truth = None  # cycle -> the world's truth (a .grasp_truth.TruthTable), demo / replay --truth-log
        self._every_sync_answers = scene.bus.transmission_type == 1  # every taxel answers every SYNC (._sampled)
        self._patterns: dict[bytes, _Pattern] = {}
        self._truth: list[str] = []
        if truth:
            from node_sim.physics import truth_batch

            # precomputed for the first cycles only (bounded memory; later cycles: object_present)
            first = np.arange(min(scene.cycles, TRUTH_PRECOMPUTED))
            self._truth = ["H1" if present else "H0" for present in truth_batch(scene, first)]
        self.fusion.warm_up()

    def new_run(self, scene: Scene | None = None) -> None:
        """Forget what the pipeline carries from cycle to cycle - the slip tracker and the grip
        stage (its law's state, the drive's state machine): the next cycle begins a run as a new
        pipeline would (``bench/grasp.py`` reuses one pipeline, its caches, for many grasps).
        ``scene``: the run's own scene where it differs from the pipeline's only in what those two
        read - ``[forces] mu``, ``[grip]``, ``[grasp]``, ``[gripper]`` - not in its taxels or mode
        (the bench's randomised grasps: one pipeline per layout and mode)."""
        scene = self.scene if scene is None else scene
        if self.over_range is not None:
            self.over_range.reset()
        self.physical = PhysicalEvaluation(scene, self.labels, self.noise, slip="slip" in self.plan.run)
        if "grip" in self.plan.run:
            from .grip_stage import GripStage

            slip = self.physical.slip
            self.grip = GripStage(scene, noise_band=slip.noise_band if slip is not None else None,
                                  slip_hold=slip.motion_consecutive if slip is not None else 3,
                                  rebase=slip.reset if slip is not None else None)

    # ------------------------------------------------------------------ the record
    def evaluate(self, closed: ClosedCycle) -> dict:
        """The record of a closed cycle: :meth:`evaluate_command`, then :meth:`finish`."""
        return self.finish(self.evaluate_command(closed))

    def evaluate_command(self, closed: ClosedCycle) -> "PendingRecord":
        """What the grip command of the cycle needs, and nothing else (the stage order of
        docs/service.md): the decision-vector part (cached per vector: received and present
        sets, the fusion rules), the verdict of ``[fusion] decide_with`` (a centralised test only
        when it decides), raw mode's tangential load and grip force (eqs 24-30, 27b), the slip
        stage, then the grip stage, which sets ``self.grip.command`` (the service sends it at
        once). Everything else of the record - the other rules' copies and the centralised tests,
        node lists, the forces' record with eqs 26a/26b, area, contact type, the truth - is
        :meth:`finish`'s, after the command has left. Same stages, same state, same order of
        state changes as one pass: ``finish(evaluate_command(c))`` is the record ``evaluate``
        always gave."""
        pending = PendingRecord(closed)
        if self.raw_mode:
            readings = closed.readings
            if self.hold:
                readings = np.where(np.isnan(readings) & ~closed.missing, closed.held_readings, readings)
            wire, available = self.detectors.wire(readings)  # eqs 1-4 on the received X_i, 0 elsewhere
        else:
            wire = closed.decisions
            if self.hold:
                wire = np.where((wire == 0) & ~closed.missing, closed.held_decisions, wire).astype(np.int8)
            available = None  # wire != 0, computed on a pattern-cache miss
            readings = None
        pending.readings, pending.available = readings, available
        if self.over_range is not None:  # before the command: clipped readings never lower it (.grip_stage)
            pending.over_range_nodes = over_range = self.over_range.update(closed)
        else:
            over_range = None
        pending.pattern = pattern = self._pattern(wire, available)
        n_received = pattern.n_received
        if n_received > 0 and self.central and self.decide_with in self.central:
            pending.central = self.centralised.results(readings, available)  # it decides: before the command
        pending.t_seconds = t_seconds = closed.sync_us * 1e-6
        total_tangential = grip_force = None
        if self.want_forces and readings is not None:
            pending.forces = cycle_forces = self.physical.force_totals(readings, pattern.present_mask)
            total_tangential, grip_force = cycle_forces.total, cycle_forces.grip
        if self.want_slip:
            pending.slip = self.physical.slip_record(t_seconds, pattern.present_mask, total_tangential, grip_force,
                                                     closed.cycle, centroid=pattern.centroid,
                                                     received=pattern.received)
        if self.grip is not None:
            main = (pending.central or pattern.rules).get(self.decide_with)
            device = closed.devices
            missing = closed.missing if device is None else device.missing
            # the fields of the record the grip stage reads (.grip_stage), as the record has them
            view = pending.grip_view = {
                "cycle": closed.cycle, "t": round(t_seconds, 6),
                "decision": main["decision"] if main else "undecided",
                "degraded": n_received < self.n, "late_frames": closed.late_frames,
                "missing_nodes": bool(missing.any()),
            }
            if over_range:
                view["over_range_nodes"] = over_range
            if pending.forces is not None:
                view["forces"] = {"total_tangential": jsonable(total_tangential)}
            if pending.slip is not None:
                view["slip"] = pending.slip
            self.grip.evaluate(view, closed.drive, defer_record=True)  # its record fields in finish
        return pending

    def finish(self, pending: "PendingRecord") -> dict:
        """The record of :meth:`evaluate_command`'s cycle (its fields in their documented order)."""
        closed, pattern = pending.closed, pending.pattern
        labels = self.labels
        n_received = pattern.n_received
        missing = closed.missing
        silent = closed.expected & ~closed.received

        record: dict = {
            "cycle": closed.cycle,
            "t": round(closed.sync_us * 1e-6, 6),
            "sync_counter": closed.sync_counter,
            "closed_by": closed.closed_by,
            # SYNC -> the event that closed the cycle, on the stream's time stamps (replayable):
            # the decision latency on the bus, before evaluation
            "closed_after_ms": round((closed.close_us - closed.sync_us) * 1e-3, 3),
            "n_expected": self.n,
            "n_live": self.n - int(np.count_nonzero(missing)),
            "n_received": n_received,
            "present_count": pattern.present,
            "present_nodes": list(pattern.present_nodes),
            "mode": self.mode,
        }
        stages_run: list[str] = []
        rule_results: dict[str, dict] = {}
        for name, result in pattern.rules.items():
            rule_results[name] = copied = dict(result)
            if "band" in copied:
                copied["band"] = list(copied["band"])
        if n_received > 0:
            if self.central:
                central = pending.central
                if central is None:
                    central = self.centralised.results(pending.readings, pending.available)
                rule_results.update(central)
            stages_run.append("fusion")
        main = rule_results.get(self.decide_with)
        record["U_G"] = main["U_G"] if main else None
        record["threshold"] = main["threshold"] if main else None
        record["decision"] = main["decision"] if main else "undecided"
        record["p_h1"] = main["p_h1"] if main else None
        record["decide_with"] = self.decide_with
        record["degraded"] = n_received < self.n
        device = closed.devices
        if device is not None:  # patch scene: the nodes' own view (labels of devices)
            labels = self.node_labels
            missing, silent = device.missing, device.expected & ~device.complete
        record["missing_nodes"] = [labels[i] for i in np.flatnonzero(missing)] if missing.any() else []
        record["silent_nodes"] = [labels[i] for i in np.flatnonzero(silent)] if silent.any() else []
        record["nodes_by_state"] = self._nodes_by_state(closed, missing, silent)
        record["duplicate_nodes"] = [labels[i] for i in closed.duplicates]
        record["late_frames"] = closed.late_frames
        record["bad_frames"] = closed.bad_frames
        record["emcy"] = [e.as_record() for e in closed.emcy]
        if closed.emcy_dropped:
            record["emcy_dropped"] = closed.emcy_dropped
        if self.over_range is not None:  # raw patch scenes: results from clipped readings flagged
            record["over_range_nodes"] = pending.over_range_nodes
        record["rules"] = rule_results

        if pending.forces is not None:
            record["forces"] = self.physical.forces_record(pending.forces)
            stages_run.append("forces")
        if self.want_area:
            record["area"] = jsonable(pattern.area)
            stages_run.append("area")
        if self.want_contact and n_received > 0:
            record.update(pattern.contact)
            stages_run.append("contact_type")
        if pending.slip is not None:
            record["slip"] = pending.slip
            stages_run.append("slip")
        if pending.grip_view is not None:
            view = pending.grip_view
            self.grip.write_record()
            record["grip"], record["grip_flags"], record["grip_detail"] = \
                view["grip"], view["grip_flags"], view["grip_detail"]
            stages_run.append("grip")
            if self.grasp_truth is not None and self._sampled(closed):
                truth = self.grasp_truth.for_cycle(closed.cycle)
                if truth is not None:
                    record["grasp_truth"] = truth
        record["stages_run"] = stages_run
        record["stages_skipped"] = self.stages_skipped
        record["rules_skipped"] = self.rules_skipped
        if self.with_truth:
            if self.scene.grasp is None:
                record["truth"] = self.truth(closed.cycle)
            else:  # a grasp world's readings: the truth is the world's (None where it is not known)
                table = self.grasp_truth
                record["truth"] = None if table is None or not self._sampled(closed) else table.presence(closed.cycle)
        return record

    def _sampled(self, closed: ClosedCycle) -> bool:
        """Whether the world step this cycle's SYNC sampled - the last one tagged with the cycle
        before (.grasp_truth) - is known to be in the truth table when the record is made. Where
        every taxel answers every SYNC (transmission type 1), a cycle closed before any answer
        came (frames lost or late: a stalled host) gets no world truth: the live record took
        whatever step the table held then, the replay (the whole truth log) the last one - they
        differed (reproduced: 3 such records in 8 runs of grasp_scripted's raw grasp beside 4
        spinning processes, each with n_received 0, closed by the SYNC window; none in 9 with
        this). Where taxels answer every n-th SYNC or on events, a cycle without an answer is
        the rule and keeps its truth."""
        return not self._every_sync_answers or bool(closed.received.any())

    def _nodes_by_state(self, closed: ClosedCycle, missing: np.ndarray, silent: np.ndarray) -> dict:
        """Every node that did not take part as an operational node: ``missing`` (heartbeat
        consumer time expired / never heard), ``silent`` (operational at the SYNC, no PDO), and
        the live nodes that were not operational at the SYNC by their NMT state (``stopped``,
        ``pre-operational``, ``resetting``, ``unknown``). Empty when every node took part."""
        out: dict[str, list] = {}
        labels, expected, states = self.labels, closed.expected, closed.states
        if closed.devices is not None:
            labels, expected, states = self.node_labels, closed.devices.expected, closed.devices.states
        off = ~expected & ~missing
        if missing.any():
            out["missing"] = [labels[i] for i in np.flatnonzero(missing)]
        if silent.any():
            out["silent"] = [labels[i] for i in np.flatnonzero(silent)]
        if off.any() and states is not None:
            for i in np.flatnonzero(off):
                name = STATE_NAMES.get(int(states[i]), "unknown")
                out.setdefault(name, []).append(labels[i])
        return out

    def truth(self, cycle: int) -> str:
        if 0 <= cycle < len(self._truth):
            return self._truth[cycle]  # precomputed with node_sim.physics.truth_batch
        from node_sim.physics import object_present

        return "H1" if object_present(self.scene, cycle) else "H0"

    def _pattern(self, wire: np.ndarray, available: np.ndarray | None) -> _Pattern:
        """The decision-vector part of the record, cached per vector (``wire``: {-1,0,+1} per
        taxel, 0 = not received; rules, area and contact type are functions of it alone)."""
        key = wire.tobytes()
        pattern = self._patterns.get(key)
        if pattern is None:
            if len(self._patterns) > 1024:
                self._patterns.clear()
            pattern = self._patterns[key] = self._new_pattern(wire, wire != 0 if available is None else available)
        return pattern

    def _new_pattern(self, wire: np.ndarray, available: np.ndarray) -> _Pattern:
        received, present_mask, n_received, present = self.fusion.cycle_decisions(wire, available)
        rule_results = self.fusion.results(wire, received, n_received, present) if n_received > 0 else {}
        area = self.physical.area(present_mask, present) if self.want_area else None
        contact_fields = ()
        if self.want_contact and n_received > 0:
            contact_fields = self.physical.contact_fields(present, n_received, area)
        labels = self.labels
        # a function of the present set alone, like the area: once per vector, not per cycle
        centroid = self.physical.locations.centroid(present_mask) if self.want_slip else None
        return _Pattern(received, present_mask, n_received, present,
                        tuple(labels[i] for i in np.flatnonzero(present_mask)), rule_results, area,
                        contact_fields, centroid)
