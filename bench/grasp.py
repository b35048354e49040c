"""Randomised grasps through the centre's control code: decision mode, raw mode and two fixed forces.

The benchmark of issue 23: at least 1,000 randomised grasps (mass, mu_s / mu_k, lift acceleration,
a hold-phase disturbance - an added load or a shake -, pad pitch, the contact's position along the
slip axis within one pitch; a quarter of them fragile) each run four ways on the same world, drive
and task:

* ``decision`` - the centre in decision mode (one bit per taxel: presence and the footprint's
  motion), the grip law of ``fusion_center.core.grip_law`` with the scene's ``[grip]``;
* ``raw`` - the same centre and law in raw mode (X_i on the bus: eq 26a's least holding force
  from the tangential cells, with ``safety_factor``);
* ``fixed 2x`` - the vendors' sizing: a fixed force of twice the least holding force for the
  known mass and friction, ``2 m g / (2 mu_s)`` per jaw, from the close phase to the release;
* ``fixed 26b`` - a fixed force at eq 26b's bound without margin, ``m g / (2 mu_s)``.

Each grasp goes through ``bench/grasp_sim.py``: the grasp world and the drive twin per SYNC, the
taxels' readings and the nodes' detector, a closed cycle, ``CyclePipeline.evaluate`` (the same
stages as the live centre; the bus is skipped), the law's findings, ``grip_step`` and the drive's
RPDO. Seeded and deterministic (the same ``--seed`` and ``--grasps`` give the same table, whatever
``--jobs``). Prints per mode: objects dropped (of those the drive's range could hold), slip onset
-> detection (cycles, ms), onset -> stuck again (ms), slid distance (mm, taxel pitches), the steady
holding force over the least holding force, crushing events on the fragile objects, bus bits per
cycle. ``--json FILE`` writes every grasp's numbers; ``docs/grip-control.md`` shows a run.

Usage: python bench/grasp.py [--grasps 1000] [--seed 23] [--jobs N] [--json out.json] [--plot out.png]
       [--set FIELD=VALUE ...] (a [grip] parameter for every grasp) [--contact random|centred]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import multiprocessing
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import grasp_plot  # noqa: E402 - its figure
from grasp_layout import pad_rows  # noqa: E402
from grasp_sim import run_grasp  # noqa: E402

from taxel_net.errors import ParameterError  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402
from taxel_net.grip_params import FLOAT_FIELDS, INT_FIELDS  # noqa: E402
from taxel_net.scene_grasp import PhaseSpec  # noqa: E402

GRIP_FIELDS = FLOAT_FIELDS + INT_FIELDS

MODES = ("decision", "raw", "fixed 2x", "fixed 26b")
PITCHES = (1.5, 2.0, 2.5, 3.0, 4.0)
DISTURBANCES = ("none", "load", "shake")
BASE_SCENE = "grasp_lift"
HOLD_S = 2.2                   # the hold phase: the law's probe and a disturbance
DISTURB_AT_S = (0.2, 1.2)      # the disturbance starts this far into the hold (uniform)
DRIVE_MAX_TORQUE = 1000        # the bench's drive: the base scene's, up to 1000 ‰ (100 N per jaw)
G = 9.80665


@dataclasses.dataclass(frozen=True)
class Case:
    """One randomised grasp (SI; forces per jaw)."""

    index: int
    mass_kg: float
    mu_s: float
    mu_k: float
    accel_m_s2: float
    disturbance: str
    disturb_at_s: float
    load_kg: float
    shake_m_s2: float
    shake_hz: float
    pitch_mm: float
    fragile: bool
    max_force_n: float | None
    grasp_n: float
    contact_offset_mm: float = 0.0   # the contact's centre above the pad's middle (the pressure row's middle cell)

    @property
    def static_least_n(self) -> float:
        """m g / (2 mu_s): the least holding force at rest (eq 26b), per jaw."""
        return self.mass_kg * G / (2 * self.mu_s)

    @property
    def hardest_least_n(self) -> float:
        """The least holding force at the task's hardest moment, per jaw: the lift's
        ``m (g + a)`` or the hold's ``(m + load) (g + shake)``, over ``2 mu_s`` (eq 26b)."""
        lift = self.mass_kg * (G + self.accel_m_s2)
        hold = (self.mass_kg + self.load_kg) * (G + self.shake_m_s2)
        return max(lift, hold) / (2 * self.mu_s)


def make_case(rng: np.random.Generator, index: int) -> Case:
    """Draw one grasp (module docstring): log-uniform mass 0.1-1.5 kg, mu_s 0.3-0.9, mu_k / mu_s
    0.6-0.95, lift acceleration 1-6 m/s², a disturbance in the hold (none, an added load of 10-50 %
    of the mass, or two periods of a 3-6 Hz shake at 1-4 m/s², 0.2-1.2 s into the hold), pad pitch 1.5-4 mm; one in four
    fragile (crushed above 1.4-1.8 x the lift's least holding force, no disturbance). The law's
    first squeeze ``grasp_n`` is the vendors' sizing, twice the static least holding force (at most
    0.9 x the crushing force): the law's job is to come down from it and to react when the load
    changes."""
    mass = float(math.exp(rng.uniform(math.log(0.1), math.log(1.5))))
    mu_s = float(rng.uniform(0.3, 0.9))
    mu_k = float(mu_s * rng.uniform(0.6, 0.95))
    accel = float(rng.uniform(1.0, 6.0))
    fragile = bool(rng.random() < 0.25)
    disturbance = "none" if fragile else str(rng.choice(DISTURBANCES))
    load = float(mass * rng.uniform(0.1, 0.5)) if disturbance == "load" else 0.0
    shake = float(rng.uniform(1.0, 4.0)) if disturbance == "shake" else 0.0
    hz = float(rng.uniform(3.0, 6.0)) if disturbance == "shake" else 0.0
    at = float(rng.uniform(*DISTURB_AT_S)) if disturbance != "none" else 0.0
    pitch = float(rng.choice(PITCHES))
    static = mass * G / (2 * mu_s)
    lift = mass * (G + accel) / (2 * mu_s)
    max_force = float(lift * rng.uniform(1.4, 1.8)) if fragile else None
    grasp = min(2.0 * static, drive_max_n())
    if max_force is not None:
        grasp = min(grasp, 0.9 * max_force)
    return Case(index, mass, mu_s, mu_k, accel, disturbance, at, load, shake, hz, pitch, fragile, max_force, grasp)


def place_contacts(cases: list[Case], seed: int, how: str) -> list[Case]:
    """The contact's position along the slip axis: ``centred`` on the pad's middle (a pressure cell
    there: on the 2 and 2.5 mm pads the 20 mm footprint's edges then lie on cells), or ``random``:
    its centre uniform over one pitch about the middle, ``[-p/2, p/2)``, so the footprint's edges fall
    anywhere between the cells. Drawn from a generator of its own (``(seed, 1)``): the cases' other
    draws are the same either way, so ``--contact centred`` and ``random`` compare the same grasps."""
    if how == "centred":
        return [dataclasses.replace(c, contact_offset_mm=0.0) for c in cases]
    rng = np.random.default_rng((seed, 1))
    u = rng.uniform(-0.5, 0.5, size=len(cases))
    return [dataclasses.replace(c, contact_offset_mm=float(x * c.pitch_mm)) for c, x in zip(cases, u)]


def drive_max_n() -> float:
    g = _base().gripper
    return g.rated_force_n * DRIVE_MAX_TORQUE / 1000.0


def case_scene(base, case: Case, mode: str, drive: tuple[float, ...] | None = None):
    """The base scene with the case's object, contact position, task, pad layout and law (raw: the bus
    in raw mode); ``drive`` ``(torque slope N/s per jaw, jaws' force lag ms[, SYNC period ms])``
    replaces the base scene's (0x6087, ``[grasp] force_lag_ms`` and ``[bus] sync_period_ms``: the
    world, the drive and the centre all step by the SYNC period; ``bench/grasp_drive.py``)."""
    kinds = {t.kind: t for t in base.taxels}
    taxels = []
    for r in pad_rows(case.pitch_mm):
        proto = kinds[r["kind"]]
        taxels.append(dataclasses.replace(proto, node_id=r["node_id"], x=r["x"], y=r["y"], jaw=r["jaw"],
                                          axis=r["axis"]))
    lift_h = 60.0
    phases = [PhaseSpec("approach", 1.0), PhaseSpec("close", 0.35),
              PhaseSpec("lift", 0.6, height_mm=lift_h, accel_m_s2=case.accel_m_s2, speed_m_s=0.3)]
    if case.disturbance == "load":
        phases.append(PhaseSpec("hold", HOLD_S, load_kg=case.load_kg, load_at_s=case.disturb_at_s))
    elif case.disturbance == "shake":
        phases.append(PhaseSpec("hold", HOLD_S, shake_m_s2=case.shake_m_s2, shake_hz=case.shake_hz, shake_cycles=2,
                                shake_at_s=case.disturb_at_s))
    else:
        phases.append(PhaseSpec("hold", HOLD_S))
    phases += [PhaseSpec("place", 0.6, height_mm=lift_h, accel_m_s2=2.0, speed_m_s=0.3), PhaseSpec("release", 0.3)]
    grasp = dataclasses.replace(base.grasp, mass_kg=case.mass_kg, mu_s=case.mu_s, mu_k=case.mu_k,
                                max_force_n=case.max_force_n, phases=tuple(phases),
                                grip_at_mm=base.grasp.grip_at + case.contact_offset_mm)
    gripper = dataclasses.replace(base.gripper, max_torque_permille=DRIVE_MAX_TORQUE)
    if drive is not None:
        slope_n_s, lag_ms = drive[:2]
        gripper = dataclasses.replace(gripper, torque_slope_permille_s=int(round(slope_n_s * 1000.0
                                                                                  / gripper.rated_force_n)))
        grasp = dataclasses.replace(grasp, force_lag_ms=float(lag_ms))
    bus = dataclasses.replace(base.bus, mode="raw" if mode == "raw" else "decision")
    if drive is not None and len(drive) > 2:
        bus = dataclasses.replace(bus, sync_period_ms=float(drive[2]))
    top = drive_max_n()
    max_n = min(top, 0.9 * case.max_force_n) if case.fragile else top
    grip = dataclasses.replace(base.grip, grasp_n=case.grasp_n, max_n=max_n, min_n=min(base.grip.min_n, case.grasp_n),
                               mu=case.mu_s)
    forces = dataclasses.replace(base.forces, mu=case.mu_s)
    return dataclasses.replace(base, taxels=tuple(taxels), grasp=grasp, grip=grip, bus=bus, forces=forces,
                               gripper=gripper)


# ---------------------------------------------------------------------------------------- metrics
def grasp_metrics(rows, case: Case, dt_s: float) -> dict:
    """The numbers of one grasp from its per-cycle rows (see ``grasp_sim.run_grasp``).

    * ``dropped``: the object is lost - it fell, or the pads slid off it on the table (left behind);
      ``crushed``: the world's truth at the end;
    * slip episodes (the world's truth, from the close phase to the place): onset = the first
      slipping cycle, stuck again = the first cycle after it that does not slip; detection = the
      first cycle from the onset on in which the centre's slip flag is set (within the episode or
      up to 10 cycles after it), also counted from the cycle the contact had slid one taxel pitch
      since the onset; onset -> stuck again in its parts (:func:`stuck_parts`);
    * ``false_flags``: the centre's slip flags that rose with no slip in the world's truth in the
      10 cycles up to them (a cue that fires on nothing);
    * ``slid_mm``: the largest slide (mm, down) before the place;
    * ``ratio``: the steady holding force over the least holding force, ``normal_n / min_hold_n``
      averaged over the hold's last 0.2 s (the object at rest; None if it is gone).
    """
    phase = [r[1] for r in rows]
    slipping = [bool(r[4]) for r in rows]
    slid = [r[5] for r in rows]
    det = [bool(r[9]) for r in rows]
    active = [p in ("close", "lift", "hold") for p in phase]
    episodes = []
    i = 0
    n = len(rows)
    while i < n:
        if active[i] and slipping[i] and rows[i][10]:
            j = i
            while j < n and slipping[j] and rows[j][10]:
                j += 1
            ep = {"onset": i, "end": j, "stuck_ms": (j - i) * dt_s * 1e3 if j < n and not rows[j][6] else None}
            d = next((c for c in range(i, min(n, j + 10)) if det[c]), None)
            ep["detect_cycles"] = None if d is None else d - i
            pitch_at = next((c for c in range(i, j) if abs(slid[c] - (slid[i - 1] if i else 0.0)) >= case.pitch_mm),
                            None)
            ep["detect_after_pitch"] = None if d is None or pitch_at is None else d - pitch_at
            ep["slid_mm"] = max(slid[i:j]) - (slid[i - 1] if i else 0.0)
            ep.update(stuck_parts(rows, i, j, d, case, dt_s))
            episodes.append(ep)
            i = j
        else:
            i += 1
    # the centre's slip flags that rose with no slip in the world's truth in the 10 cycles up to them
    false_flags = sum(1 for k in range(n) if det[k] and (k == 0 or not det[k - 1])
                      and not any(slipping[max(0, k - 10):k + 1]))
    before_place = [s for s, p in zip(slid, phase) if p in ("close", "lift", "hold")]
    hold_idx = [c for c, p in enumerate(phase) if p == "hold"]
    ratio = None
    if hold_idx and not rows[hold_idx[-1]][6]:
        tail = hold_idx[-int(round(0.2 / dt_s)):]
        vals = [rows[c][2] / rows[c][3] for c in tail if rows[c][3] > 0]
        ratio = float(np.mean(vals)) if vals else None
    return {"dropped": bool(rows[-1][6]) or rows[-1][12] == "left", "crushed": bool(rows[-1][7]),
            "slid_mm": max([0.0] + before_place), "ratio": ratio, "episodes": episodes, "false_flags": false_flags}


PARTS = ("detect", "raise", "force", "stop")   # onset -> stuck again, in cycles (stuck_parts)


def stuck_parts(rows, i: int, j: int, d: int | None, case: Case, dt_s: float) -> dict:
    """Onset -> stuck again of the slip episode of rows ``i`` .. ``j - 1`` split into its parts,
    in cycles (``parts``), where they happen in this order:

    * ``detect``: the onset -> the centre's first slip flag (row ``d``);
    * ``raise``: -> the first cycle from ``d`` on whose command carries the law's ``slip_raise``
      (0: the law raised in the cycle it was told; more: ``settle_s`` held it back);
    * ``force``: -> the first world step from the raise on whose jaw force ``N`` stops the slide,
      ``N >= m (g + a) / (2 mu_k) = min_hold_n mu_s / mu_k`` (the slide decelerates from then on):
      the RPDO's next SYNC, the drive's torque slope and the jaws' force lag;
    * ``stop``: -> the first step without slip (the object decelerated to the pads' speed, back
      to static friction).

    Episodes whose slide ended before the centre raised (the load fell by itself, or an earlier
    raise's force was still on its way) have no parts (``parts`` None); ``self_stopped`` says
    which. ``raises``: the law's raises from the onset to 10 cycles after the stop. ``slid_at_detect_mm``: the slide of the world step the detecting cycle sampled (the
    step before its row) since the onset; ``onset_accel_m_s2``: the slide's acceleration in its
    first step, ``2 s / dt²`` (from rest)."""
    slid = [r[5] for r in rows]
    base = slid[i - 1] if i else 0.0
    out: dict = {"parts": None, "self_stopped": False,
                 "slid_at_detect_mm": None if d is None or d == 0 else slid[d - 1] - base}
    out["onset_accel_m_s2"] = 2.0 * (slid[i] - base) * 1e-3 / dt_s ** 2
    out["raises"] = sum(1 for k in range(i, min(len(rows), j + 10)) if "slip_raise" in rows[k][11])
    if d is None or d >= j:
        out["self_stopped"] = True
        return out
    c = next((k for k in range(d, j) if "slip_raise" in rows[k][11]), None)
    if c is None:
        out["self_stopped"] = True
        return out
    ratio = case.mu_s / case.mu_k
    h = next((k for k in range(c, j) if rows[k][2] >= rows[k][3] * ratio), None)
    if h is None:
        out["self_stopped"] = True
        return out
    out["parts"] = [d - i, c - d, h - c, j - h]
    return out


def run_case(args) -> dict:
    """All four modes of one case (a worker's job); an exception comes back as text (a worker's
    exception that does not unpickle would hang the pool)."""
    try:
        return _run_case(args)
    except Exception as exc:  # noqa: BLE001 - reported by main, never lost
        import traceback

        return {"case": dataclasses.asdict(args[0]), "error": f"{type(exc).__name__}: {exc}",
                "traceback": traceback.format_exc()}


def run_jobs(jobs: list, processes: int, *, every: int, unit: str) -> tuple[list[dict], float, list[dict]]:
    """:func:`run_case` of every job, in ``processes`` spawned processes (1: here), progress on
    stderr every ``every`` jobs; returns the results in job order, the seconds taken and the
    results that failed (each printed with its traceback)."""
    t0 = time.perf_counter()
    results = []
    pool = multiprocessing.get_context("spawn").Pool(processes) if processes > 1 else None
    try:
        it = pool.imap(run_case, jobs, chunksize=2) if pool else map(run_case, jobs)
        for n, res in enumerate(it, 1):
            results.append(res)
            if n % every == 0 or n == len(jobs):
                print(f"  {n}/{len(jobs)} {unit}, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    finally:
        if pool:
            pool.terminate()
    elapsed = time.perf_counter() - t0
    errors = [r for r in results if "error" in r]
    for r in errors:
        print(f"grasp {r['case']['index']}: {r['error']}\n{r['traceback']}", file=sys.stderr)
    return results, elapsed, errors


def _run_case(args) -> dict:
    """``(case, want_bits, overrides[, modes[, drive]])``: the case in each of ``modes`` (default
    all four), with the law's ``overrides`` and the drive ``(slope N/s, lag ms[, SYNC ms])`` (default
    the base scene's)."""
    case, want_bits, overrides = args[:3]
    modes = args[3] if len(args) > 3 and args[3] else MODES
    drive = args[4] if len(args) > 4 else None
    base = _base()
    if overrides:
        base = dataclasses.replace(base, grip=dataclasses.replace(base.grip, **overrides))
    out = {"case": dataclasses.asdict(case)}
    dt = (drive[2] if drive is not None and len(drive) > 2 else base.bus.sync_period_ms) / 1000.0
    for mode in modes:
        if mode in ("decision", "raw"):
            scene = case_scene(base, case, mode, drive)
            res = run_grasp(scene, mode, count_bits=want_bits, pipeline=_pipeline(scene, case.pitch_mm, mode))
        else:
            scene = case_scene(base, case, "decision", drive)
            force = (2.0 if mode == "fixed 2x" else 1.0) * case.static_least_n
            res = run_grasp(scene, "fixed", fixed_n=force)
        m = grasp_metrics(res["rows"], case, dt)
        if res.get("centre_us"):
            m["centre_us"] = [round(x, 1) for x in np.percentile(res["centre_us"], (50, 99))] + [len(res["centre_us"])]
        for key in ("taxel_bits_per_cycle", "loop_bits_per_cycle"):
            if key in res:
                m[key] = res[key]
        out[mode] = m
    return out


_BASE = None
_PIPELINES: dict = {}


def _base():
    global _BASE
    if _BASE is None:
        _BASE = load_scene(BASE_SCENE)
    return _BASE


def _pipeline(scene, pitch: float, mode: str):
    """One CyclePipeline per (pad pitch, mode) and process: its thresholds and centralised tests
    depend on the layout and the SYNC period only (the grasp's own state, the slip stage, is renewed
    per grasp)."""
    from fusion_center.service.pipeline import CyclePipeline

    key = (pitch, mode, scene.bus.sync_period_ms)
    if key not in _PIPELINES:
        _PIPELINES[key] = CyclePipeline(scene, truth=False)
    return _PIPELINES[key]


# ---------------------------------------------------------------------------------------- table
def _pct(values, q):
    return float(np.percentile(values, q)) if values else float("nan")


def summarise(results: list[dict]) -> dict:
    """Per mode: the table's numbers (see the module docstring)."""
    table = {}
    for mode in MODES:
        rows = [r[mode] for r in results]
        cases = [Case(**r["case"]) for r in results]
        top = {}
        holdable = [m for m, c in zip(rows, cases)
                    if c.hardest_least_n <= (min(drive_max_n(), 0.9 * c.max_force_n) if c.fragile else drive_max_n())]
        eps = [e for m in rows for e in m["episodes"]]
        det = [e["detect_cycles"] for e in eps if e["detect_cycles"] is not None]
        det_p = [e["detect_after_pitch"] for e in eps if e["detect_after_pitch"] is not None]
        stuck = [e["stuck_ms"] for e in eps if e["stuck_ms"] is not None]
        slid = [m["slid_mm"] for m in rows]
        pitches = [m["slid_mm"] / c.pitch_mm for m, c in zip(rows, cases)]
        ratios = [m["ratio"] for m in rows if m["ratio"] is not None]
        fragile = [m for m, c in zip(rows, cases) if c.fragile]
        top["grasps"] = len(rows)
        top["dropped"] = sum(m["dropped"] for m in rows)
        top["dropped_holdable"] = sum(m["dropped"] for m in holdable)
        top["grasps_with_slip"] = sum(1 for m in rows if m["episodes"])
        top["false_flags"] = sum(m.get("false_flags", 0) for m in rows)
        top["grasps_false_flags"] = sum(1 for m in rows if m.get("false_flags", 0))
        top["slip_episodes"] = len(eps)
        top["episodes_detected"] = len(det)
        top["detect_cycles_median"] = _pct(det, 50)
        top["detect_cycles_p95"] = _pct(det, 95)
        top["detect_after_pitch_median"] = _pct(det_p, 50)
        top["detect_after_pitch_p95"] = _pct(det_p, 95)
        top["stuck_ms_median"] = _pct(stuck, 50)
        top["stuck_ms_p95"] = _pct(stuck, 95)
        chained = [e["parts"] for e in eps if e.get("parts")]
        top["parts_episodes"] = len(chained)
        top["episodes_raised_twice"] = sum(1 for e in eps if e.get("raises", 0) >= 2)
        top["self_stopped"] = sum(1 for e in eps if e.get("self_stopped"))
        for n_part, part in enumerate(PARTS):
            vals = [c[n_part] for c in chained]
            top[f"part_{part}_median"] = _pct(vals, 50)
            top[f"part_{part}_p95"] = _pct(vals, 95)
        sums = [sum(c) for c in chained]
        top["parts_stuck_median"] = _pct(sums, 50)
        top["parts_stuck_p95"] = _pct(sums, 95)
        at_det = [e["slid_at_detect_mm"] for e in eps if e.get("slid_at_detect_mm") is not None]
        top["slid_at_detect_mm_median"] = _pct(at_det, 50)
        top["slid_at_detect_mm_p95"] = _pct(at_det, 95)
        acc = [e["onset_accel_m_s2"] for e in eps if e.get("onset_accel_m_s2") is not None]
        top["onset_accel_median"] = _pct(acc, 50)
        top["onset_accel_p5"] = _pct(acc, 5)
        top["slid_mm_median"] = _pct(slid, 50)
        top["slid_mm_p95"] = _pct(slid, 95)
        top["slid_pitches_median"] = _pct(pitches, 50)
        top["slid_pitches_p95"] = _pct(pitches, 95)
        top["ratio_median"] = _pct(ratios, 50)
        top["ratio_p95"] = _pct(ratios, 95)
        top["ratio_le_1_3"] = (sum(1 for r in ratios if r <= 1.3) / len(ratios)) if ratios else float("nan")
        top["fragile"] = len(fragile)
        top["crushed_fragile"] = sum(m["crushed"] for m in fragile)
        bits = [m["taxel_bits_per_cycle"] for m in rows if "taxel_bits_per_cycle" in m]
        loop = [m["loop_bits_per_cycle"] for m in rows if "loop_bits_per_cycle" in m]
        cu = [m["centre_us"] for m in rows if "centre_us" in m]
        top["centre_ms_p50"] = float(np.median([c[0] for c in cu])) / 1000 if cu else None
        top["centre_ms_p99"] = float(np.median([c[1] for c in cu])) / 1000 if cu else None
        top["taxel_bits_per_cycle"] = float(np.mean(bits)) if bits else None
        top["loop_bits_per_cycle"] = float(np.mean(loop)) if loop else None
        table[mode] = top
    return table


def _fmt(v, digits=1):
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def render(table: dict, dt_ms: float) -> str:
    lines = []
    head = f"{'':40s}" + "".join(f"{m:>14s}" for m in MODES)
    lines.append(head)

    def row(label, fn):
        lines.append(f"{label:40s}" + "".join(f"{fn(table[m]):>14s}" for m in MODES))

    row("grasps", lambda t: str(t["grasps"]))
    row("dropped (holdable)", lambda t: f"{t['dropped']} ({t['dropped_holdable']})")
    row("grasps with slip / episodes", lambda t: f"{t['grasps_with_slip']}/{t['slip_episodes']}")
    row("slip flags without slip (grasps)", lambda t: f"{t.get('false_flags', 0)} ({t.get('grasps_false_flags', 0)})")
    row("onset->detect cycles med/p95", lambda t: f"{_fmt(t['detect_cycles_median'], 0)}/{_fmt(t['detect_cycles_p95'], 0)}")
    row("onset->detect ms med/p95", lambda t: f"{_fmt(t['detect_cycles_median'] * dt_ms, 0)}/"
                                             f"{_fmt(t['detect_cycles_p95'] * dt_ms, 0)}")
    row("one pitch->detect cycles med/p95", lambda t: f"{_fmt(t['detect_after_pitch_median'], 0)}/"
                                                     f"{_fmt(t['detect_after_pitch_p95'], 0)}")
    row("onset->stuck ms med/p95", lambda t: f"{_fmt(t['stuck_ms_median'], 0)}/{_fmt(t['stuck_ms_p95'], 0)}")
    row("stuck in parts: episodes (self-stopped)", lambda t: f"{t.get('parts_episodes', 0)} ({t.get('self_stopped', 0)})")
    for part, label in zip(PARTS, ("onset->detect", "detect->raise", "raise->force holds", "force->stuck")):
        row(f"  {label} ms med/p95", lambda t, part=part: f"{_fmt(t.get(f'part_{part}_median', float('nan')) * dt_ms, 0)}/"
                                                          f"{_fmt(t.get(f'part_{part}_p95', float('nan')) * dt_ms, 0)}")
    row("  their sum (onset->stuck) ms med/p95", lambda t: f"{_fmt(t.get('parts_stuck_median', float('nan')) * dt_ms, 0)}/"
                                                          f"{_fmt(t.get('parts_stuck_p95', float('nan')) * dt_ms, 0)}")
    row("episodes raised twice or more", lambda t: str(t.get("episodes_raised_twice", "-")))
    row("slid at detection mm med/p95", lambda t: f"{_fmt(t.get('slid_at_detect_mm_median'))}/"
                                                  f"{_fmt(t.get('slid_at_detect_mm_p95'))}")
    row("slide accel at onset m/s2 med/p5", lambda t: f"{_fmt(t.get('onset_accel_median'))}/"
                                                      f"{_fmt(t.get('onset_accel_p5'))}")
    row("slid mm med/p95", lambda t: f"{_fmt(t['slid_mm_median'])}/{_fmt(t['slid_mm_p95'])}")
    row("slid pitches med/p95", lambda t: f"{_fmt(t['slid_pitches_median'])}/{_fmt(t['slid_pitches_p95'])}")
    row("hold force/least med/p95", lambda t: f"{_fmt(t['ratio_median'], 2)}/{_fmt(t['ratio_p95'], 2)}")
    row("hold force/least <= 1.3", lambda t: f"{_fmt(100 * t['ratio_le_1_3'], 0)} %")
    row("crushed (fragile)", lambda t: f"{t['crushed_fragile']}/{t['fragile']}")
    row("centre ms/cycle p50/p99 (*)", lambda t: f"{_fmt(t.get('centre_ms_p50'), 2)}/{_fmt(t.get('centre_ms_p99'), 2)}")
    row("taxel bits/cycle", lambda t: _fmt(t["taxel_bits_per_cycle"], 0))
    row("+ SYNC, drive PDOs, RPDO bits", lambda t: _fmt(t["loop_bits_per_cycle"], 0))
    lines.append("(*) evaluate + findings + grip_step per cycle, the median over grasps of each grasp's p50 / p99; "
                 "this machine, under the bench's own load")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grasps", type=int, default=1000, help="randomised grasps (default 1000)")
    ap.add_argument("--seed", type=int, default=23)
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="worker processes (default: the CPUs)")
    ap.add_argument("--bits-every", type=int, default=10, help="count the bus bits on every N-th grasp")
    ap.add_argument("--json", type=Path, help="write every grasp's numbers and the table here")
    ap.add_argument("--plot", type=Path, help="draw the table's figure into this PNG (matplotlib)")
    ap.add_argument("--from-json", type=Path, help="no run: the table (and --plot) of a --json file written before")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a [grip] parameter of the law for every grasp (repeatable)")
    ap.add_argument("--contact", choices=("random", "centred"), default="random",
                    help="the contact's position along the slip axis: uniform over one pitch about the pad's middle "
                         "(default), or centred on it (the bench before: footprint edges on cells at 2 and 2.5 mm)")
    args = ap.parse_args(argv)
    if args.grasps < 1 or args.jobs < 1 or args.bits_every < 1:
        ap.error("--grasps, --jobs and --bits-every must be >= 1")
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        if key not in GRIP_FIELDS or not value:
            ap.error(f"--set {item!r}: FIELD=VALUE with FIELD one of {', '.join(GRIP_FIELDS)}")
        try:
            overrides[key] = int(value) if key in INT_FIELDS else float(value)
            dataclasses.replace(_base().grip, **overrides)   # GripParams' own checks, before any grasp
        except (ValueError, ParameterError) as exc:
            ap.error(f"--set {item!r}: {exc}")
    if args.from_json:
        saved = json.loads(args.from_json.read_text())
        results, table = saved["grasps"], summarise(saved["grasps"])
        dt_ms = _base().bus.sync_period_ms
        print(render(table, dt_ms))
        if args.plot:
            a = saved["args"]
            grasp_plot.plot(results, table, args.plot, f"bench/grasp.py --grasps {a['grasps']} --seed {a['seed']} "
                                                       f"({a.get('date', '')})", MODES, _base())
        return 0
    rng = np.random.default_rng(args.seed)
    cases = place_contacts([make_case(rng, i) for i in range(args.grasps)], args.seed, args.contact)
    jobs = [(c, c.index % args.bits_every == 0, overrides) for c in cases]
    results, elapsed, errors = run_jobs(jobs, args.jobs, every=50, unit="grasps")
    if errors:
        print(f"{len(errors)} grasp(s) failed (above); the table is of the others", file=sys.stderr)
    results = [r for r in results if "error" not in r]
    table = summarise(results)
    dt_ms = _base().bus.sync_period_ms
    print(f"bench/grasp.py --grasps {args.grasps} --seed {args.seed} --contact {args.contact}: {args.grasps} grasps "
          f"x {len(MODES)} modes in {elapsed:.0f} s ({args.jobs} job(s)); SYNC {dt_ms:g} ms")
    print(render(table, dt_ms))
    if args.plot:
        grasp_plot.plot(results, table, args.plot, f"bench/grasp.py --grasps {args.grasps} --seed {args.seed} "
                                                   f"({time.strftime('%Y-%m-%d', time.gmtime())})", MODES, _base())
    if args.json:
        args.json.write_text(json.dumps({"args": {"grasps": args.grasps, "seed": args.seed, "overrides": overrides,
                                                  "contact": args.contact,
                                                  "date": time.strftime("%Y-%m-%d", time.gmtime()),
                                                  "elapsed_s": round(elapsed, 1), "jobs": args.jobs},
                                         "table": table,
                                         "grasps": results}, indent=None, default=float))
    return 1 if errors else 0   # a table with grasps left out is not a complete run


if __name__ == "__main__":
    raise SystemExit(main())
