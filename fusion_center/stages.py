"""Stage planning: which pipeline stages and fusion rules a scene needs *and* supports.

A scene requests output stages (``[outputs] stages``, see ``docs/scene-format.md``) and fusion
rules (``[fusion] rules``). The pipeline builds only what is requested and what the scene's
data supports; everything else is listed with the reason it did not run, so records and
reports can say so. Pure: reads the ``Scene`` dataclasses, no I/O.

Support conditions (chapter sections in brackets):

* ``fusion`` (sec. 2.2): always runs - it is the global decision every record carries.
* ``forces`` (sec. 4, eqs 23-27, 30): needs calibrated taxels - a tangential calibration
  ``y = m F + c`` with a non-zero slope (eq 30 divides by m) or a load-cell ``grip_factor`` M
  (eq 27b). Also built (as a dependency) when ``slip`` runs.
* ``area`` (sec. 6.2.3.3, eq 35): needs planar coordinates of every taxel (the convex hull of
  the active taxels).
* ``contact_type`` (sec. 5.2, eqs 34a/34b, Table 1): t_c needs only the count of active
  taxels; fp_c additionally needs ``area`` (noted when it is unavailable).
* ``slip`` (sec. 4, eqs 24-26, 28-29): needs tangential-calibrated cells (slope present and
  non-zero); a scene with load cells only has no slip model.
* ``grip`` (issue 23, :mod:`fusion_center.service.grip_stage`): not requested but implied by a
  ``[gripper]`` table - the centre commands the drive every cycle; skipped on every scene without
  one. Without ``[grasp]`` there is no task schedule (noted: the stage closes on presence from
  the drive's first OPERATION ENABLED on and never releases by itself); without the slip stage the
  law sees no slip (noted).

Bus mode (``[bus] mode``, or the ``mode`` argument): in ``decision`` mode a node sends only
u_i (TPDO1, one byte), so nothing that needs the readings X_i can run - ``forces`` is skipped
with that reason and ``slip`` runs on its motion criterion alone (centroid of the present
taxels). In ``raw`` mode (TPDO2, X_i as REAL32 mV) forces run when calibrated, slip gets its
force criterion when both a tangential and a grip force exist, and the centralised raw-data
tests (:mod:`fusion_center.core.centralised`, ``CENTRAL_TESTS``) run when every taxel has a noise
std > 0.

Rules:

* ``additive`` (eq 6, threshold eq 17), ``multiplicative`` (eq 5, threshold eq 16) and
  ``k-of-n`` (sec. 2.2.1) need only n >= 1 (k-of-n also 1 <= k <= n).
* ``preferential`` (eq 7, thresholds eqs 14, 15, 18-20) needs n >= 2: g(n) of eq 15 is the
  U_G of a row of at least two taxels.
* ``llr`` (Chair-Varshney, eq 31) and ``np`` (Neyman-Pearson, eq 32) need P_F and P_M of every
  taxel strictly inside (0, 1) (their logarithms enter the statistic).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from taxel_net.errors import ParameterError
from taxel_net.scene import BUS_MODES, RULES, STAGES, Scene

# centralised raw-data tests of the live service (fusion_center.core.centralised methods)
CENTRAL_TESTS = ("centralised_glrt", "centralised_known")
DECISION_MODE_FORCES = ("decision mode carries only u_i (TPDO1); needs raw mode (TPDO2 X_i) "
                        "and a force calibration")
DECISION_MODE_CENTRAL = ("decision mode carries only u_i (TPDO1); the centralised test needs "
                         "raw mode (TPDO2 X_i)")

_LIST_MAX = 12


def _node_list(taxels) -> str:
    """'taxels 3, 7' (node-IDs, with channel when the scene has several) - truncated politely."""
    multi = len({t.channel for t in taxels}) > 1
    names = [f"{t.node_id}@ch{t.channel}" if multi else str(t.node_id) for t in taxels]
    word = "taxel" if len(names) == 1 else "taxels"
    if len(names) > _LIST_MAX:
        return f"{word} {', '.join(names[:_LIST_MAX])} and {len(names) - _LIST_MAX} more"
    return f"{word} {', '.join(names)}"


@dataclass(frozen=True)
class StagePlan:
    """What the pipeline builds for a scene.

    ``run``: stages built, in ``scene.STAGES`` order (then ``grip``); ``skipped``: stage -> reason for every
    other stage (not requested, or requested but unsupported); ``rules_run`` /
    ``rules_skipped`` the same for fusion rules; ``central_run`` / ``central_skipped`` the
    same for the centralised raw-data tests (``CENTRAL_TESTS``); ``notes``: stage -> remark on
    a stage that runs in a reduced or implied form; ``mode`` the bus mode planned for.
    """

    run: tuple[str, ...]
    skipped: dict[str, str] = field(default_factory=dict)
    rules_run: tuple[str, ...] = ()
    rules_skipped: dict[str, str] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)
    mode: str = "decision"
    central_run: tuple[str, ...] = ()
    central_skipped: dict[str, str] = field(default_factory=dict)

    @property
    def all_rules_skipped(self) -> dict[str, str]:
        """Fusion rules and centralised tests that do not run, with the reason."""
        return {**self.rules_skipped, **self.central_skipped}

    def to_dict(self) -> dict:
        return {
            "mode": self.mode,
            "run": list(self.run),
            "skipped": dict(self.skipped),
            "rules_run": list(self.rules_run),
            "rules_skipped": dict(self.rules_skipped),
            "central_run": list(self.central_run),
            "central_skipped": dict(self.central_skipped),
            "notes": dict(self.notes),
        }


def _tangential(t) -> bool:
    return t.slope is not None and t.slope != 0.0


def _calibrated(t) -> bool:
    return _tangential(t) or (t.grip_factor is not None and t.grip_factor != 0.0)


def _missing_coordinates(scene: Scene):
    return [t for t in scene.taxels if t.x is None or t.y is None]


def _pf_pm_problem(scene: Scene) -> str | None:
    missing = [t for t in scene.taxels if t.pf is None or t.pm is None]
    if missing:
        return f"{_node_list(missing)} have no pf/pm" if len(missing) > 1 else f"{_node_list(missing)} has no pf/pm"
    degenerate = [t for t in scene.taxels if not (0.0 < t.pf < 1.0 and 0.0 < t.pm < 1.0)]
    if degenerate:
        return f"{_node_list(degenerate)}: pf and pm must lie strictly inside (0, 1)"
    return None


def rule_support(scene: Scene, rule: str) -> str | None:
    """None when ``rule`` can run on ``scene``, else the reason it cannot."""
    n = scene.n
    if n < 1:
        return "the scene has no taxels"
    if rule in ("additive", "multiplicative"):
        return None
    if rule == "k-of-n":
        k = scene.fusion.k
        return None if 1 <= k <= n else f"k={k} outside 1..n={n}"
    if rule == "preferential":
        return None if n >= 2 else f"needs a row of at least 2 taxels for g(n) (eq 15), n={n}"
    if rule in ("llr", "np"):
        return _pf_pm_problem(scene)
    return f"unknown rule {rule!r}"


def stage_support(scene: Scene, stage: str, mode: str | None = None) -> str | None:
    """None when ``stage`` can run on ``scene`` in bus ``mode`` (default: the scene's), else
    the reason it cannot."""
    mode = _mode(scene, mode)
    if stage in ("fusion", "contact_type"):
        return None if scene.n >= 1 else "the scene has no taxels"
    if stage == "forces":
        if not any(_calibrated(t) for t in scene.taxels):
            return "no taxel has a force calibration (non-zero slope, eq 23/30, or grip_factor, eq 27b)"
        return DECISION_MODE_FORCES if mode == "decision" else None
    if stage == "area":
        missing = _missing_coordinates(scene)
        if not missing:
            return None
        verb = "have" if len(missing) > 1 else "has"
        return f"{_node_list(missing)} {verb} no coordinates (convex hull, eq 35)"
    if stage == "slip":
        if any(_tangential(t) for t in scene.taxels):
            return None
        return "no tangential-calibrated taxel (slope present and non-zero, eq 23/27a)"
    return f"unknown stage {stage!r}"


def _mode(scene: Scene, mode: str | None) -> str:
    mode = scene.bus.mode if mode is None else mode
    if mode not in BUS_MODES:
        raise ParameterError("mode", mode, f"must be one of {BUS_MODES}")
    return mode


def centralised_support(scene: Scene) -> str | None:
    """None when the centralised raw-data statistic can be formed on ``scene`` (every sigma_i > 0), else the reason."""
    bad = [t for t in scene.taxels if not (t.noise_sigma_mv and t.noise_sigma_mv > 0)]
    if bad:
        ids = ", ".join(str(t.node_id) for t in bad[:12]) + (" ..." if len(bad) > 12 else "")
        return f"centralised: taxels {ids} have noise_sigma_mv = 0 (the raw-data LLR needs sigma > 0)"
    return None


def central_support(scene: Scene, test: str, mode: str | None = None) -> str | None:
    """None when the centralised raw-data test ``test`` can run, else the reason."""
    if test not in CENTRAL_TESTS:
        return f"unknown centralised test {test!r}"
    if _mode(scene, mode) == "decision":
        return DECISION_MODE_CENTRAL
    if scene.n < 1:
        return "the scene has no taxels"
    why = centralised_support(scene)
    return None if why is None else why.removeprefix("centralised: ")


def plan_stages(scene: Scene, mode: str | None = None) -> StagePlan:
    """Plan the stages and rules for ``scene`` in bus ``mode`` ("decision" | "raw"; default
    the scene's ``[bus] mode``) - see the module docstring for the conditions."""
    mode = _mode(scene, mode)
    requested = set(scene.stages)
    requested.add("fusion")  # the global decision always runs
    run: list[str] = []
    skipped: dict[str, str] = {}
    notes: dict[str, str] = {}
    if "fusion" not in scene.stages:
        notes["fusion"] = "always runs (the record's decision)"

    supported = {s: stage_support(scene, s, mode) for s in STAGES}
    if "slip" in requested and supported["slip"] is None:
        if mode == "decision":
            notes["slip"] = "motion criterion only (centroid of the present taxels): the force criterion needs raw mode"
        elif "forces" not in requested:
            requested.add("forces")
            notes["forces"] = "built because slip needs the tangential forces"

    for stage in STAGES:
        if stage not in requested:
            skipped[stage] = "not requested in [outputs] stages"
        elif supported[stage] is not None:
            skipped[stage] = f"{stage}: {supported[stage]}"
        else:
            run.append(stage)
    if scene.gripper is None:
        skipped["grip"] = "grip: the scene has no [gripper] (no drive to command)"
    else:
        run.append("grip")
        if getattr(scene, "grasp", None) is None:
            notes["grip"] = ("no [grasp] task: closes on presence from the drive's first OPERATION ENABLED on, "
                             "never releases by itself")
        if "slip" not in run:
            notes["grip"] = (notes.get("grip", "") + "; " if "grip" in notes else "") + (
                "the slip stage does not run: the law sees no slip")
    if "contact_type" in run and "area" not in run:
        notes["contact_type"] = "taxel count t_c only (eq 34a); fp_c (eq 34b) needs area"

    rules_run: list[str] = []
    rules_skipped: dict[str, str] = {}
    for rule in RULES:
        if rule not in scene.fusion.rules:
            rules_skipped[rule] = "not requested in [fusion] rules"
            continue
        why = rule_support(scene, rule)
        if why is None:
            rules_run.append(rule)
        else:
            rules_skipped[rule] = f"{rule}: {why}"
    central_run: list[str] = []
    central_skipped: dict[str, str] = {}
    for test in CENTRAL_TESTS:
        why = central_support(scene, test, mode)
        if why is None:
            central_run.append(test)
        else:
            central_skipped[test] = f"{test}: {why}"
    return StagePlan(tuple(run), skipped, tuple(rules_run), rules_skipped, notes, mode,
                     tuple(central_run), central_skipped)
