"""Stage planning per scene, and every scene file loads (fusion_center.stages)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from taxel_net.scene import load_scene
from fusion_center.stages import plan_stages

SCENES = sorted(Path("scenes").glob("*.toml"))


@pytest.mark.parametrize("path", SCENES, ids=lambda p: p.stem)
def test_every_scene_loads_and_plans(path):
    scene = load_scene(path)
    plan = plan_stages(scene)
    assert "fusion" in plan.run
    assert set(plan.run) | set(plan.skipped) == {"fusion", "forces", "area", "contact_type", "slip", "grip"}
    assert set(plan.rules_run) | set(plan.rules_skipped) == {"additive", "multiplicative", "preferential",
                                                             "k-of-n", "llr", "np"}


def test_matrix57_plan():
    scene = load_scene("scenes/matrix57.toml")
    plan = plan_stages(scene)
    assert scene.bus.mode == "decision" and plan.mode == "decision"
    # decision mode: u_i only on the bus, no forces and no centralised raw-data test
    assert plan.run == ("fusion", "area", "contact_type")
    assert plan.skipped["forces"].startswith("forces: decision mode carries only u_i")
    assert "raw mode (TPDO2" in plan.skipped["forces"]
    assert plan.skipped["slip"] == "not requested in [outputs] stages"
    assert plan.rules_run == ("additive", "multiplicative", "k-of-n", "llr", "np")
    assert plan.central_run == ()
    assert set(plan.central_skipped) == {"centralised_glrt", "centralised_known"}
    assert all("raw mode" in why for why in plan.central_skipped.values())
    raw = plan_stages(scene, "raw")
    assert raw.run == ("fusion", "forces", "area", "contact_type")
    assert raw.central_run == ("centralised_glrt", "centralised_known") and raw.central_skipped == {}
    assert raw.all_rules_skipped == {"preferential": "not requested in [fusion] rules"}
    assert plan_stages(load_scene("scenes/matrix57_raw.toml")) == raw


def test_bad_mode_is_a_parameter_error():
    from taxel_net.errors import ParameterError

    with pytest.raises(ParameterError, match="mode"):
        plan_stages(load_scene("scenes/matrix57.toml"), "streaming")


def test_centralised_needs_noise():
    # the chapter scenes replay printed readings with sigma = 0: no raw-data LLR exists
    plan = plan_stages(load_scene("scenes/matrix57_chapter.toml"), "raw")
    assert plan.central_run == ()
    assert "noise_sigma_mv = 0" in plan.central_skipped["centralised_glrt"]


def test_gripper18_without_pf_pm_skips_llr_and_np():
    scene = load_scene("scenes/gripper18.toml")
    taxels = tuple(dataclasses.replace(t, pf=None) if t.node_id in (3, 7) else t for t in scene.taxels)
    fusion = dataclasses.replace(scene.fusion, rules=("preferential", "llr", "np"))
    plan = plan_stages(dataclasses.replace(scene, taxels=taxels, fusion=fusion))
    assert plan.rules_run == ("preferential",)
    assert plan.rules_skipped["llr"] == "llr: taxels 3, 7 have no pf/pm"
    assert plan.rules_skipped["np"] == "np: taxels 3, 7 have no pf/pm"


def test_area_needs_coordinates():
    scene = load_scene("scenes/gripper18.toml")
    taxels = tuple(dataclasses.replace(t, x=None, y=None) if t.node_id in (3, 7) else t for t in scene.taxels)
    scene = dataclasses.replace(scene, taxels=taxels, stages=("fusion", "area", "contact_type"))
    plan = plan_stages(scene)
    assert "area" not in plan.run
    assert plan.skipped["area"].startswith("area: taxels 3, 7 have no coordinates")
    assert "contact_type" in plan.run and "t_c only" in plan.notes["contact_type"]


def test_slip_needs_tangential_calibration_and_pulls_in_forces():
    scene = load_scene("scenes/slipping.toml")
    plan = plan_stages(dataclasses.replace(scene, stages=("fusion", "slip")), "raw")
    assert plan.run == ("fusion", "forces", "slip")
    assert "slip" in plan.notes["forces"]
    # decision mode: slip on its motion criterion alone, forces impossible
    plan = plan_stages(dataclasses.replace(scene, stages=("fusion", "slip")), "decision")
    assert plan.run == ("fusion", "slip")
    assert "motion criterion only" in plan.notes["slip"]
    assert plan.skipped["forces"] == "not requested in [outputs] stages"
    flat = tuple(dataclasses.replace(t, slope=0.0 if t.slope is not None else None) for t in scene.taxels)
    plan = plan_stages(dataclasses.replace(scene, taxels=flat), "raw")
    assert plan.skipped["slip"].startswith("slip: no tangential-calibrated taxel")
    assert plan.skipped["forces"].startswith("forces: no taxel has a force calibration")


def test_preferential_needs_two_taxels_and_k_in_range():
    scene = load_scene("scenes/matrix57.toml")
    one = dataclasses.replace(scene, taxels=scene.taxels[:1],
                              fusion=dataclasses.replace(scene.fusion, rules=("preferential", "k-of-n"), k=4))
    plan = plan_stages(one)
    assert "n=1" in plan.rules_skipped["preferential"]
    assert plan.rules_skipped["k-of-n"] == "k-of-n: k=4 outside 1..n=1"


@pytest.mark.parametrize("name,low,high", [("point_force", 0.01, 0.02), ("small_object", 0.01, 0.1),
                                           ("large_object", 0.1, 1.0), ("slipping", 0.1, 1.0)])
def test_contact_scenes_match_table_1(name, low, high):
    from node_sim import physics

    scene = load_scene(f"scenes/{name}.toml")
    mid = (scene.object.present[0][0] + scene.object.present[0][1]) // 2
    t_c = physics.contact_mask(scene, scene.object.present[0][0]).sum() / scene.n  # eq 34a
    assert low <= t_c <= high
    assert physics.contact_mask(scene, mid).any()


def test_slipping_footprint_moves():
    from node_sim import physics

    scene = load_scene("scenes/slipping.toml")
    before = physics.contact_mask(scene, 50)
    after = physics.contact_mask(scene, 110)
    assert not np.array_equal(before, after)


def test_two_buses_200():
    scene = load_scene("scenes/two_buses_200.toml")
    assert scene.n == 200 > 127
    assert len(scene.bus.channels) == 2
    for ch in (0, 1):
        ids = [t.node_id for t in scene.taxels if t.channel == ch]
        assert len(ids) == 100 and len(set(ids)) == 100 and max(ids) <= 127
