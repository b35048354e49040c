"""Raw-data mode (issue 6) in the live fusion centre: the nodes send X_i (TPDO2, REAL32 mV),
the centre decides per taxel (eqs 1-4), fuses, runs the centralised raw-data tests and
computes forces; every record says which stages / rules did not run and why."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import norm

from fusion_center.commands.demo import run_demo
from cli_inprocess import run_cli
from fusion_center.commands.run import apply_mode
from taxel_net.scene import load_scene
from fusion_center.service import ClosedCycle, CyclePipeline, replay_trace
from node_sim import physics

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"


@pytest.fixture(scope="module")
def matrix_raw():
    # 20 ms SYNC: fewer TPDOs delayed past the next SYNC on a loaded machine (the node twins
    # send TPDO1 and TPDO2 in raw mode: twice the frames of decision mode)
    scene = load_scene(SCENES / "matrix57_raw.toml")
    return dataclasses.replace(scene, bus=dataclasses.replace(scene.bus, sync_period_ms=20.0))


def wire(x):
    """The value a node puts in TPDO2: REAL32."""
    return np.asarray(x, dtype=np.float32).astype(float)


def clean_records(records):
    """Cycles whose every TPDO2 answers this cycle's SYNC (see test_service_e2e)."""
    return [r for prev, r in zip([None] + records, records)
            if r["closed_by"] == "complete" and (prev is None or prev["closed_by"] == "complete")]


# ----------------------------------------------------------------------------- on the bus
@pytest.fixture(scope="module")
def raw_demo(matrix_raw, tmp_path_factory):
    out = tmp_path_factory.mktemp("raw")
    live, trace = out / "live.jsonl", out / "trace.log"
    # node 27 (a contacted C-cell) dropped at cycle 30: degraded cycles use the centralised
    # test on the 56 received taxels
    service, summary = run_demo(matrix_raw, 50, drops={30: [27]}, json_lines=live, trace=trace)
    records = [json.loads(line) for line in live.read_text().splitlines()]
    return records, live, trace, summary


def test_raw_demo_records_match_the_physics(matrix_raw, raw_demo):
    records, _, _, summary = raw_demo
    assert [r["cycle"] for r in records] == list(range(50))
    assert summary["counters"]["tpdo2"] > 0
    # raw mode: the nodes send the reading *instead of* the decision (TPDO1 left invalid)
    assert summary["counters"].get("tpdo1", 0) == 0
    taxels = matrix_raw.taxels
    noise = np.array([t.noise_mv for t in taxels])
    zeta = np.array([t.zeta_mv for t in taxels])
    sigma = np.array([t.noise_sigma_mv for t in taxels])
    slope = np.array([t.slope or 0.0 for t in taxels])
    intercept = np.array([t.intercept or 0.0 for t in taxels])
    mu = matrix_raw.forces.mu
    clean = [r for r in clean_records(records) if r["cycle"] < 30]
    assert len(clean) >= 15, [r["closed_by"] for r in records]
    checked_present = 0
    for r in clean:
        assert r["mode"] == "raw" and not r["degraded"]
        x = wire(physics.sample_readings(matrix_raw, r["cycle"]))
        y = x - noise                                   # eq 4
        u = np.where(y >= zeta, 1, -1)                  # eqs 2-3, written out here
        ids = [t.node_id for t, ui in zip(taxels, u) if ui == 1]
        assert r["present_nodes"] == ids and r["present_count"] == len(ids)
        assert r["rules"]["additive"]["U_G"] == int(u.sum())  # eq 6 over the central decisions
        # centralised GLRT: sum_i max(0, LLR_i), LLR_i = (S_i y_i - S_i^2/2)/sigma_i^2, S_i the
        # nominal contact signal (m F + c for a calibrated taxel under F, else signal_mv)
        force = matrix_raw.object.tangential_force
        s = np.where(slope != 0, slope * force + intercept, [t.signal_mv for t in taxels])
        glrt = np.maximum(0.0, (s * y - s * s / 2) / sigma**2).sum()
        assert r["rules"]["centralised_glrt"]["U_G"] == pytest.approx(glrt, rel=1e-9)
        # centralised known: one footprint S(c) -> threshold -d^2/2 + d Q^-1(alpha) (closed form)
        pattern = physics.signal_mv(matrix_raw, 25)
        d = math.sqrt(float(np.sum(pattern**2 / sigma**2)))
        known = r["rules"]["centralised_known"]
        assert known["threshold"] == pytest.approx(-d * d / 2 + d * norm.isf(matrix_raw.fusion.np_false_alarm),
                                                   rel=1e-9)
        assert known["U_G"] == pytest.approx(float(np.sum((pattern * y - pattern**2 / 2) / sigma**2)), rel=1e-9)
        for name in ("centralised_glrt", "centralised_known"):
            res = r["rules"][name]
            assert res["decision"] == ("H1" if res["U_G"] > res["threshold"] else "H0")
            assert res["n"] == 57 and res["false_alarm"] == matrix_raw.fusion.np_false_alarm
        # forces: eq 30 on the present calibrated cells, eqs 24-25 (alpha = 0: sum), 26a, 26b
        cells = (u == 1) & (slope != 0)
        f = (y[cells] - intercept[cells]) / slope[cells]
        per = {str(t.node_id): v for t, v in zip([t for t, c in zip(taxels, cells) if c], f)}
        assert r["forces"]["per_taxel"].keys() == per.keys()
        for key, value in per.items():
            assert r["forces"]["per_taxel"][key] == pytest.approx(value, rel=1e-12)
        total = float(np.abs(f).sum())
        assert r["forces"]["total_tangential"] == pytest.approx(total, rel=1e-12)
        assert r["forces"]["grip_force_limit"] == pytest.approx(total / mu, rel=1e-12)
        assert r["forces"]["max_load"] == pytest.approx(2 * mu * total / mu, rel=1e-12)
        assert "forces" in r["stages_run"] and "fusion" in r["stages_run"]
        assert r["stages_skipped"] == {"slip": "not requested in [outputs] stages",
                                       "grip": "grip: the scene has no [gripper] (no drive to command)"}
        assert r["rules_skipped"] == {"preferential": "not requested in [fusion] rules"}
        checked_present += len(ids) > 0
    assert checked_present >= 3  # contact from cycle 20: some checked cycles have forces
    # inside the contact window the centralised tests detect, outside they do not (P_F 1e-3)
    assert all(r["rules"]["centralised_known"]["decision"] == r["truth"] for r in clean)


def test_raw_demo_degraded_cycles_use_the_received_taxels(raw_demo):
    records = raw_demo[0]
    late = [r for r in records if r["cycle"] >= 30]
    assert all(r["degraded"] and 27 not in r["present_nodes"] for r in late)
    # a cycle can lose answers delayed past its window on a loaded machine: every cycle that got
    # readings is fused over exactly those (how many arrive is the host's)
    full = [r for r in late if r["n_received"] > 0]
    assert len(full) >= 1, [r["n_received"] for r in late]
    for r in full:
        res = r["rules"]["centralised_glrt"]
        assert res["n"] == r["n_received"] <= 56
        assert res["decision"] == ("H1" if res["U_G"] > res["threshold"] else "H0")
        assert "27" not in r["forces"]["per_taxel"]


def test_replay_of_a_raw_trace_equals_live(matrix_raw, raw_demo, tmp_path, capsys):
    _, live, trace, _ = raw_demo
    replayed = tmp_path / "replay.jsonl"
    records, counters = replay_trace(matrix_raw, trace, json_lines=replayed)
    assert replayed.read_bytes() == live.read_bytes()
    assert counters["tpdo2"] > 0
    # the CLI with --mode raw on the decision-mode scene file reproduces it too
    out = tmp_path / "cli.jsonl"
    result = run_cli(capsys, "replay", "--scene", SCENES / "matrix57.toml", "--mode", "raw", trace, "--json-lines", out)
    assert result.returncode == 0, result.stderr
    cli = [json.loads(line) for line in out.read_text().splitlines()]
    # same records: the scene file differs only in name and (here) the SYNC period, which the
    # records do not depend on (the assembler uses the stream order, not the period)
    assert cli == [json.loads(line) for line in replayed.read_text().splitlines()]
    assert all(r["mode"] == "raw" for r in cli)


def test_demo_mode_option_overrides_the_scene(tmp_path, capsys):
    out = tmp_path / "d.jsonl"
    # main() in this process (tests/cli_inprocess.py): the test is about the records and the summary
    result = run_cli(capsys, "demo", "--mode", "raw", "--cycles", "12", "--no-live", "--json-lines", out)
    assert result.returncode == 0, result.stderr
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 12
    assert all(r["mode"] == "raw" for r in records)
    # a cycle whose answers were all delayed past the next SYNC (loaded machine) fuses nothing
    assert all("centralised_glrt" in r["rules"] for r in records if r["n_received"] > 0)
    assert sum(r["n_received"] > 0 for r in records) >= 6
    assert "tpdo2" in result.stdout


# ----------------------------------------------------------------------------- per scene
def closed_cycle(scene, cycle, readings=None, decisions=None):
    """A synthetic closed cycle: every node delivered (readings in raw mode, u_i otherwise)."""
    n = scene.n
    if readings is None:
        readings = np.full(n, np.nan)
    if decisions is None:
        decisions = np.zeros(n, dtype=np.int8)
    true = np.ones(n, dtype=bool)
    return ClosedCycle(cycle=cycle, sync_us=10_000 * cycle, close_us=10_000 * cycle + 5000, sync_counter=None,
                       closed_by="complete", decisions=np.asarray(decisions, dtype=np.int8),
                       readings=np.asarray(readings, dtype=float), received=true, expected=true,
                       missing=~true, held_decisions=np.zeros(n, dtype=np.int8),
                       held_readings=np.full(n, np.nan), late_frames=0, bad_frames=0, emcy=())


DECISION_ONLY = "decision mode carries only u_i"


@pytest.mark.parametrize("name,mode,skipped,rules_skipped", [
    ("matrix57", None, {"forces": DECISION_ONLY, "slip": "not requested"},
     {"preferential": "not requested", "centralised_glrt": DECISION_ONLY, "centralised_known": DECISION_ONLY}),
    ("gripper18", None, {"forces": DECISION_ONLY, "area": "not requested", "contact_type": "not requested",
                         "slip": "not requested"},
     {"additive": "not requested", "multiplicative": "not requested", "llr": "not requested",
      "np": "not requested", "centralised_glrt": DECISION_ONLY, "centralised_known": DECISION_ONLY}),
    ("point_force", None, {"forces": DECISION_ONLY, "slip": "not requested"},
     {"centralised_glrt": DECISION_ONLY, "centralised_known": DECISION_ONLY}),
    ("two_buses_200", None, {"forces": "not requested", "slip": "not requested"},
     {"centralised_glrt": DECISION_ONLY, "centralised_known": DECISION_ONLY}),
    ("matrix57_raw", None, {"slip": "not requested"}, {"preferential": "not requested"}),
    ("gripper18_raw", None, {"area": "not requested", "contact_type": "not requested", "slip": "not requested"},
     {"additive": "not requested", "multiplicative": "not requested", "llr": "not requested",
      "np": "not requested"}),
    ("matrix57_chapter", "raw", {"slip": "not requested"},
     {"preferential": "not requested", "llr": "not requested", "np": "not requested",
      "centralised_glrt": "noise_sigma_mv = 0", "centralised_known": "noise_sigma_mv = 0"}),
])
def test_every_record_says_what_did_not_run(name, mode, skipped, rules_skipped):
    scene = apply_mode(load_scene(SCENES / f"{name}.toml"), mode)
    pipeline = CyclePipeline(scene)
    cycle = scene.object.present[0][0] if scene.object.present else 0
    x = physics.sample_readings(scene, cycle)
    u = np.where(x - np.array([t.noise_mv for t in scene.taxels]) >= np.array([t.zeta_mv for t in scene.taxels]), 1, -1)
    raw = scene.bus.mode == "raw"
    record = pipeline.evaluate(closed_cycle(scene, cycle, readings=wire(x) if raw else None,
                                            decisions=None if raw else u))
    skipped = {**skipped, "grip": "no [gripper]"}  # the grip stage runs only with a drive (issue 23)
    assert set(record["stages_skipped"]) == set(skipped)
    for stage, why in skipped.items():
        assert why in record["stages_skipped"][stage], (stage, record["stages_skipped"][stage])
        assert stage not in record["stages_run"]
    assert set(record["rules_skipped"]) == set(rules_skipped)
    for rule, why in rules_skipped.items():
        assert why in record["rules_skipped"][rule], (rule, record["rules_skipped"][rule])
        assert rule not in record["rules"]
    # every stage is either run or skipped with a reason
    assert set(record["stages_run"]) | set(record["stages_skipped"]) == {"fusion", "forces", "area",
                                                                         "contact_type", "slip", "grip"}
    assert ("forces" in record) == ("forces" in record["stages_run"])
    assert record["present_count"] == int((u == 1).sum())


# ----------------------------------------------------------------------------- gripper forces
@pytest.fixture(scope="module")
def gripper_raw():
    scene = load_scene(SCENES / "gripper18_raw.toml")
    return dataclasses.replace(scene, stages=("fusion", "forces", "slip"))


def gripper_readings(scene, y_by_node):
    """X_i = N_i + Y_i for the given offsets Y (node-ID -> mV)."""
    return np.array([t.noise_mv + y_by_node[t.node_id] for t in scene.taxels])


def test_gripper_forces_eqs_27b_28_29_26(gripper_raw):
    pipeline = CyclePipeline(gripper_raw)
    # hand-worked cycle: slope 1, intercept 0 (F = Y, eq 30), M = 1 (F_g = Y, eq 27b)
    y = {1: 3.9, 2: 3.7,                                   # LC left / right
         3: 0.02, 4: 0.03, 5: 0.025, 6: 0.025, 7: 0.05,    # left jaw: 4 on y, node 7 on x
         8: 0.02, 9: 0.02, 10: 0.02, 11: 0.02, 12: 0.015,  # right jaw
         13: 400, 14: 400, 15: 400, 16: 400, 17: 400, 18: 400}
    record = pipeline.evaluate(closed_cycle(gripper_raw, 20, readings=gripper_readings(gripper_raw, y)))
    forces = record["forces"]
    left = math.sqrt(0.1**2 + 0.05**2)       # eq 28a (alpha = 0: sum of the y cells), eq 29
    right = math.sqrt(0.08**2 + 0.015**2)
    assert forces["tangential_per_jaw"]["left"] == pytest.approx(left, rel=1e-12)
    assert forces["tangential_per_jaw"]["right"] == pytest.approx(right, rel=1e-12)
    total = (left + right) / 2                # sec 7.2: mean over the jaws
    assert forces["total_tangential"] == pytest.approx(total, rel=1e-12)
    assert forces["grip_force"] == pytest.approx(3.8, rel=1e-12)             # (3.9 + 3.7) / 2, eq 27b
    assert forces["grip_force_per_cell"] == pytest.approx({"1": 3.9, "2": 3.7}, rel=1e-12)
    assert forces["grip_force_limit"] == pytest.approx(total / 0.3, rel=1e-12)   # eq 26a
    assert forces["max_load"] == pytest.approx(2 * 0.3 * total / 0.3, rel=1e-12)  # eq 26b
    assert forces["unit"] == "kgf"
    # the slip tracker got both forces: ratio TotF_t / (mu F_g)
    assert record["slip"]["force_ratio"] == pytest.approx(total / (0.3 * 3.8), rel=1e-12)
    assert not record["slip"]["slipping"]


def test_gripper_absent_cells_carry_no_force_and_slip_by_force(gripper_raw):
    pipeline = CyclePipeline(gripper_raw)
    base = {i: 400 for i in range(13, 19)}
    # right load cell below zeta (2 mV): absent, no grip on that jaw; y cell 4 below 0.012 mV: absent
    y = {**base, 1: 3.0, 2: 0.5, 3: 0.5, 4: 0.005, 5: 0.5, 6: 0.5, 7: 0.2,
         8: 0.5, 9: 0.5, 10: 0.5, 11: 0.5, 12: 0.2}
    record = pipeline.evaluate(closed_cycle(gripper_raw, 0, readings=gripper_readings(gripper_raw, y)))
    forces = record["forces"]
    assert "4" not in forces["per_taxel"] and forces["grip_force_per_cell"]["2"] == 0.0
    assert forces["grip_force"] == pytest.approx(1.5, rel=1e-12)
    left = math.sqrt(1.5**2 + 0.2**2)
    right = math.sqrt(2.0**2 + 0.2**2)
    total = (left + right) / 2
    assert forces["total_tangential"] == pytest.approx(total, rel=1e-12)
    # Coulomb: TotF_t > mu F_g (force_consecutive = 1): slip flagged by the force criterion
    assert total > 0.3 * 1.5
    assert record["slip"]["slipping"] and record["slip"]["criterion"] == "force"
    assert record["slip"]["onset_cycle"] == 0


def test_centralised_on_a_cycle_with_a_missing_reading(gripper_raw):
    pipeline = CyclePipeline(gripper_raw)
    x = wire(physics.sample_readings(gripper_raw, 30))
    x[4] = np.nan  # node 5's TPDO2 lost
    record = pipeline.evaluate(closed_cycle(gripper_raw, 30, readings=x))
    assert record["n_received"] == 17 and record["degraded"]
    sigma = np.array([t.noise_sigma_mv for t in gripper_raw.taxels])
    noise = np.array([t.noise_mv for t in gripper_raw.taxels])
    keep = ~np.isnan(x)
    pattern = physics.signal_mv(gripper_raw, 30)[keep]
    y = (x - noise)[keep]
    d = math.sqrt(float(np.sum(pattern**2 / sigma[keep] ** 2)))
    known = record["rules"]["centralised_known"]
    assert known["n"] == 17
    assert known["U_G"] == pytest.approx(float(np.sum((pattern * y - pattern**2 / 2) / sigma[keep] ** 2)), rel=1e-9)
    assert known["threshold"] == pytest.approx(-d * d / 2 + d * norm.isf(gripper_raw.fusion.np_false_alarm), rel=1e-9)


def test_degraded_thresholds_keep_the_false_alarm_bound():
    # slipping object: several footprints -> the known test's subset threshold is the union
    # bound sum_c Q((tau + d_c^2/2)/d_c) = alpha; the GLRT keeps its full-set threshold
    scene = apply_mode(load_scene(SCENES / "slipping.toml"), "raw")
    pipeline = CyclePipeline(scene)
    cycle = 100
    x = wire(physics.sample_readings(scene, cycle))
    x[0] = np.nan
    record = pipeline.evaluate(closed_cycle(scene, cycle, readings=x))
    known, glrt = record["rules"]["centralised_known"], record["rules"]["centralised_glrt"]
    assert known["n"] == glrt["n"] == scene.n - 1
    assert glrt["threshold"] == pipeline.central["centralised_glrt"].threshold
    sigma = np.array([t.noise_sigma_mv for t in scene.taxels])[1:]
    patterns = np.unique(np.array([physics.signal_mv(scene, c) for c in range(scene.cycles)
                                   if physics.object_present(scene, c)])[:, 1:], axis=0)
    d = np.sqrt((patterns**2 / sigma**2).sum(axis=1))
    d = d[d > 0]
    assert d.size > 1
    bound = norm.sf((known["threshold"] + d * d / 2) / d).sum()
    assert bound == pytest.approx(scene.fusion.np_false_alarm, rel=1e-8)
