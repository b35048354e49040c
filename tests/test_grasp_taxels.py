"""The taxels' view of the grasp world (node_sim.world.taxels, issue 22): footprint, pressure, the
tangential cells' calibration lines, and the readings through the noise and faults of eqs 1-4.

Hand-worked values on scenes/grasp_scripted.toml (per jaw: LC at y = 20 with M = 0.5 mV/N; TBS
(axis y) at y = 12, 12, 28, 28 with y = 2.0 F + 0.2 mV; IR at y = 13, 27 with 400 mV; footprint
20 mm centred 20 mm up the pad, i.e. 10..30 mm while not slid)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fusion_center.core import forces
from node_sim import physics
from node_sim.world import GraspWorld
from node_sim.world.taxels import footprint_mask, taxel_signal, truth_readings
from taxel_net.errors import ParameterError
from taxel_net.scene import FaultSpec, load_scene
from taxel_net.scene_grasp import GraspSpec, PhaseSpec

SCENE = load_scene("scenes/grasp_scripted.toml")
ORDER = [t.node_id for t in SCENE.taxels]      # node-IDs 1..14 in scene order
LEFT = {"LC": 1, "TBS12": (2, 3), "TBS28": (4, 5), "IR13": 6, "IR27": 7}


def by_node(values) -> dict[int, float]:
    return {nid: float(v) for nid, v in zip(ORDER, values)}


def test_footprint_moves_down_the_pad_by_the_slid_distance():
    # not slid: 10..30 mm holds every taxel (y = 12, 13, 20, 27, 28)
    assert footprint_mask(SCENE, True, 0.0).all()
    # slid 3 mm: 7..27 mm - the TBS at 28 leave, the IR at 27 is on the edge (in)
    m = by_node(footprint_mask(SCENE, True, 3.0))
    assert [nid for nid, v in m.items() if not v] == [4, 5, 11, 12]
    # slid 3.5 mm: 6.5..26.5 - the IR at 27 leaves too
    m = by_node(footprint_mask(SCENE, True, 3.5))
    assert [nid for nid, v in m.items() if not v] == [4, 5, 7, 11, 12, 14]
    # slid up 5 mm (negative): 15..35 - the cells at 12 and 13 leave
    m = by_node(footprint_mask(SCENE, True, -5.0))
    assert [nid for nid, v in m.items() if not v] == [2, 3, 6, 9, 10, 13]
    # not between the jaws: nothing
    assert not footprint_mask(SCENE, False, 0.0).any()


def test_signal_hand_worked_sticking():
    # N = 8 N, T = 2.5 N per pad, not slid: LC 0.5 * 8 = 4.0 mV; each of the 4 TBS of a pad
    # carries 2.5 / 4 = 0.625 N: 2.0 * 0.625 + 0.2 = 1.45 mV; IR 400 mV
    s = by_node(taxel_signal(SCENE, True, 8.0, 2.5, 0.0))
    for jaw in (0, 7):
        assert s[1 + jaw] == pytest.approx(4.0, abs=1e-12)
        for nid in (2, 3, 4, 5):
            assert s[nid + jaw] == pytest.approx(1.45, abs=1e-12)
        assert s[6 + jaw] == s[7 + jaw] == 400.0


def test_signal_hand_worked_slid_the_remaining_cells_carry_the_load():
    # slid 3.5 mm: per pad the two TBS at 12 remain and carry 2.5 / 2 = 1.25 N: 2.0 * 1.25 + 0.2 = 2.7 mV
    s = by_node(taxel_signal(SCENE, True, 8.0, 2.5, 3.5))
    assert s[2] == s[3] == s[9] == s[10] == pytest.approx(2.7, abs=1e-12)
    assert s[4] == s[5] == s[7] == 0.0
    assert s[6] == 400.0 and s[1] == pytest.approx(4.0)


def test_signal_without_normal_force_only_presence():
    # jaws not pressing (N = 0): no load cell, no tangential cell - the IR still see the object
    s = by_node(taxel_signal(SCENE, True, 0.0, 0.0, 0.0))
    assert [nid for nid, v in s.items() if v != 0] == [6, 7, 13, 14]
    # pressed without load: a TBS reads its intercept 0.2 mV (below its cut-off 0.6)
    s = by_node(taxel_signal(SCENE, True, 3.0, 0.0, 0.0))
    assert s[2] == s[12] == pytest.approx(0.2) and s[1] == pytest.approx(1.5)


def test_eq30_on_the_signals_gives_back_the_load_per_pad():
    """Raw mode's estimate: eq 30 per cell and the sum of magnitudes (eqs 28a/28b, alpha = 0) per
    pad recover the world's load, here 3.7 N with 4 and with 2 cells in the footprint."""
    a = physics.taxel_arrays(SCENE)
    for slid, cells in ((0.0, [2, 3, 4, 5]), (3.5, [2, 3])):
        s = taxel_signal(SCENE, True, 9.0, 3.7, slid)
        idx = [ORDER.index(n) for n in cells]
        f = forces.tangential_force(s[idx], a["slope"][idx], a["intercept"][idx])
        assert forces.total_tangential(f) == pytest.approx(3.7, abs=1e-12)


def scene_with(**taxel_changes):
    """grasp_scripted with taxel 2 changed."""
    taxels = list(SCENE.taxels)
    taxels[1] = dataclasses.replace(taxels[1], **taxel_changes)
    return dataclasses.replace(SCENE, taxels=tuple(taxels))


def test_an_x_axis_cell_carries_none_of_the_vertical_load():
    # taxel 2 on the x axis: reads its intercept; the other 3 y cells of the pad share T: 3/3 = 1 N
    sc = scene_with(axis="x")
    s = by_node(taxel_signal(sc, True, 8.0, 3.0, 0.0))
    assert s[2] == pytest.approx(0.2)
    assert s[3] == s[4] == s[5] == pytest.approx(2.0 * 1.0 + 0.2)
    assert s[9] == pytest.approx(2.0 * 0.75 + 0.2)          # the right pad: 4 cells, 0.75 N each


def test_a_pressure_cell_grows_with_the_normal_force():
    # a C cell (no calibration) with signal 6 mV: 6 * N / pressure_ref_n (10 N): 12 N -> 7.2 mV
    sc = scene_with(kind="C", slope=None, intercept=None, axis=None, signal_mv=6.0)
    assert by_node(taxel_signal(sc, True, 12.0, 2.0, 0.0))[2] == pytest.approx(7.2, abs=1e-12)
    assert by_node(taxel_signal(sc, True, 0.0, 0.0, 0.0))[2] == 0.0
    # and the TBS cells of that pad: 3 share the load now
    assert by_node(taxel_signal(sc, True, 12.0, 3.0, 0.0))[3] == pytest.approx(2.2)


def test_readings_add_the_canonical_noise_and_the_faults():
    s = taxel_signal(SCENE, True, 8.0, 2.5, 0.0)
    a = physics.taxel_arrays(SCENE)
    x = physics.observe(SCENE, 17, s)
    eps = np.random.default_rng(np.random.SeedSequence([SCENE.seed, 17])).standard_normal(SCENE.n)
    np.testing.assert_array_equal(x, s + a["noise_mv"] + a["noise_sigma_mv"] * eps)
    faulted = dataclasses.replace(SCENE, faults=(FaultSpec(node_id=3, fault="open_circuit", from_cycle=10),
                                                 FaultSpec(node_id=4, fault="stuck", from_cycle=10, until_cycle=20)))
    held: dict = {}
    x12 = physics.observe(faulted, 12, s, held)
    assert np.isnan(x12[ORDER.index(3)])
    x13 = physics.observe(faulted, 13, s * 2, held)
    assert x13[ORDER.index(4)] == x12[ORDER.index(4)]           # stuck at the first faulted reading seen
    x20 = physics.observe(faulted, 20, s * 2, held)
    assert x20[ORDER.index(4)] != x12[ORDER.index(4)]           # the fault is over
    with pytest.raises(ParameterError):
        physics.observe(SCENE, 1, s[:3])


def test_a_scene_without_grasp_is_refused():
    with pytest.raises(ParameterError) as info:
        taxel_signal(load_scene("gripper18"), True, 1.0, 0.0, 0.0)
    assert "grasp" in str(info.value)


# ------------------------------------------------------------------ the world's tangential load

G = 9.81


def spec(**over):
    base = dict(mass_kg=0.5, mu_s=0.5, mu_k=0.4, size_mm=40.0, gravity_m_s2=G, force_lag_ms=0.0, phases=(
        PhaseSpec("approach", 1.0), PhaseSpec("close", 0.5),
        PhaseSpec("lift", 1.0, height_mm=100.0, accel_m_s2=2.0, speed_m_s=0.2), PhaseSpec("hold", 1.0)))
    base.update(over)
    return GraspSpec(**base)


def test_tangential_load_sticking_slipping_and_on_the_table():
    world = GraspWorld(spec(), 0.01)
    world.start()
    truths = [world.step(10.0) for _ in range(155)]        # approach, close, 5 steps of the lift
    # close (still, N = 10 N, on the table): no load on the pads
    assert truths[120].phase == "close" and truths[120].tangential_n == 0.0
    # lifting at a = 2 m/s², sticking (10 >= 5.905 N): m (g + a) / 2 = 0.5 * 11.81 / 2 = 2.9525 N per pad
    assert truths[152].mode == "stick" and truths[152].tangential_n == pytest.approx(2.9525, abs=1e-12)
    # the lift at 5 N (< 5.905) slips: mu_k N = 0.4 * 5 = 2.0 N per pad, down
    t = world.step(5.0)
    assert t.mode == "slip" and t.slipping and t.tangential_n == pytest.approx(2.0, abs=1e-12)
    # gone: nothing
    t = world.step(0.0, jaws_open=True)
    assert t.dropped and t.tangential_n == 0.0
    # the pads sliding over the resting object (a master squeezing at 2 N while the gripper lifts:
    # 2 mu_k N = 1.6 < m g = 4.905, so it is not lifted): mu_k N = 0.8 N, down (the pads go up)
    w2 = GraspWorld(spec(), 0.01)
    w2.start()
    for _ in range(151):
        t = w2.step(2.0)
    assert t.phase == "lift" and t.mode == "table" and t.tangential_n == pytest.approx(0.8, abs=1e-12)


def test_truth_readings_of_a_world_step():
    sc = dataclasses.replace(SCENE, grasp=dataclasses.replace(SCENE.grasp, force_lag_ms=0.0))
    world = GraspWorld(sc.grasp, 0.01)
    world.start()
    for _ in range(200):
        t = world.step(8.0)
    assert t.mode == "stick"
    s = taxel_signal(sc, t.in_grip, t.normal_n, t.tangential_n, t.slid_mm)
    np.testing.assert_array_equal(truth_readings(sc, t, 5), physics.observe(sc, 5, s))
    # held still in the lift's cruise (a = 0): m g / 2 / 4 per TBS = 0.5 * 9.80665 / 8 N
    assert t.tangential_n == pytest.approx(0.5 * 9.80665 / 2)
    assert by_node(s)[2] == pytest.approx(2.0 * 0.5 * 9.80665 / 8 + 0.2)


@pytest.mark.parametrize("value", ["0.0", "-1.0", '"ten"'])
def test_a_bad_pressure_reference_is_named(tmp_path, value):
    from taxel_net.errors import SceneError

    text = open("scenes/grasp_scripted.toml", encoding="utf-8").read()
    path = tmp_path / "s.toml"
    path.write_text(text.replace("pressure_ref_n = 10.0", f"pressure_ref_n = {value}"), encoding="utf-8")
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert "grasp.pressure_ref_n" in str(info.value) and "\n" not in str(info.value)
