"""A scene's [grasp] table (taxel_net.scene_grasp): loads, and every bad value is one line naming the
field (SceneError; the CLIs exit 2)."""

from __future__ import annotations

from pathlib import Path

import pytest

from node_sim.world import GraspWorld
from cli_inprocess import run_cli
from taxel_net.errors import SceneError
from taxel_net.scene import load_scene


HEAD = """[scene]
name = "grasp"

[[taxels]]
node_id = 1
kind = "LC"

[fusion]
tuple = "pm1"

[grasp]
"""

GRASP = {"mass_kg": "0.5", "mu_s": "0.5", "mu_k": "0.4", "size_mm": "40.0", "max_force_n": "25.0",
         "pad_length_mm": "40.0", "contact_mm": "20.0", "force_lag_ms": "20.0"}

PHASES = [
    {"name": '"approach"', "duration_s": "1.0"},
    {"name": '"close"', "duration_s": "0.5"},
    {"name": '"lift"', "duration_s": "1.0", "height_mm": "100.0", "accel_m_s2": "2.0", "speed_m_s": "0.2"},
    {"name": '"hold"', "duration_s": "2.0", "load_kg": "0.2", "load_at_s": "0.5", "shake_m_s2": "3.0",
     "shake_hz": "5.0", "shake_cycles": "2", "shake_at_s": "1.0"},
    {"name": '"place"', "duration_s": "1.0", "accel_m_s2": "2.0", "speed_m_s": "0.2"},
    {"name": '"release"', "duration_s": "0.5"},
]


def write(tmp_path, grasp=None, phases=None) -> Path:
    g = dict(GRASP) if grasp is None else grasp
    ph = PHASES if phases is None else phases
    text = HEAD + "".join(f"{k} = {v}\n" for k, v in g.items())
    for p in ph:
        text += "\n[[grasp.phase]]\n" + "".join(f"{k} = {v}\n" for k, v in p.items())
    path = tmp_path / "grasp.toml"
    path.write_text(text)
    return path


def test_a_grasp_scene_loads(tmp_path):
    scene = load_scene(write(tmp_path))
    g = scene.grasp
    assert (g.mass_kg, g.mu_s, g.mu_k, g.size_mm, g.max_force_n) == (0.5, 0.5, 0.4, 40.0, 25.0)
    assert [p.name for p in g.phases] == ["approach", "close", "lift", "hold", "place", "release"]
    assert g.phases[3].shake_cycles == 2 and g.phases[3].load_kg == 0.2
    assert g.phases[4].height_mm == 100.0          # place: the lift's height by default
    world = GraspWorld(g, scene.bus.sync_period_ms / 1000.0)
    world.start()
    assert world.step(0.0, jaws_open=True).phase == "approach"


def test_no_grasp_table_no_grasp_world(tmp_path):
    p = tmp_path / "plain.toml"
    p.write_text(HEAD.replace("[grasp]\n", ""))
    assert load_scene(p).grasp is None


def with_(key, value):
    g = dict(GRASP)
    if value is None:
        g.pop(key)
    else:
        g[key] = value
    return g


def phases_with(i, key, value):
    ph = [dict(p) for p in PHASES]
    if value is None:
        ph[i].pop(key)
    else:
        ph[i][key] = value
    return ph


BAD = [
    # (grasp, phases, field, words of the problem)
    (with_("mass_kg", "-0.5"), None, "grasp.mass_kg", "> 0 kg"),
    (with_("mass_kg", "0"), None, "grasp.mass_kg", "> 0 kg"),
    (with_("mass_kg", '"heavy"'), None, "grasp.mass_kg", "must be a number"),
    (with_("mass_kg", None), None, "grasp.mass_kg", "missing required field"),
    (with_("mu_k", "0.6"), None, "grasp.mu_k", "must not exceed static friction"),
    (with_("mu_s", "-0.1"), None, "grasp.mu_s", "> 0"),
    (with_("size_mm", "0"), None, "grasp.size_mm", "> 0"),
    (with_("max_force_n", "0"), None, "grasp.max_force_n", "> 0"),
    (with_("grip_at_mm", "50.0"), None, "grasp.grip_at_mm", "must lie on the pad"),
    (with_("force_lag_ms", "-1"), None, "grasp.force_lag_ms", ">= 0"),
    (with_("weight", "1"), None, "grasp.weight", "unknown key"),
    (None, [], "grasp.phase", "missing"),
    (None, [PHASES[0], PHASES[1], PHASES[3], PHASES[2]], "grasp.phase[3].name", "out of order"),
    (None, [PHASES[0], PHASES[1], PHASES[2], PHASES[3], PHASES[3]], "grasp.phase[4].name", "out of order"),
    (None, [PHASES[1], PHASES[0]], "grasp.phase[0].name", "starts with 'approach'"),
    (None, [PHASES[0], PHASES[2]], "grasp.phase[1].name", "'close' follows 'approach'"),
    (None, [PHASES[0], PHASES[1], PHASES[4]], "grasp.phase[2].name", "needs a 'lift'"),
    (None, phases_with(2, "name", '"shake"'), "grasp.phase[2].name", "must be one of"),
    (None, phases_with(0, "duration_s", "0.5"), "grasp.phase[0].duration_s", "at least 1 s"),
    (None, phases_with(1, "duration_s", "0"), "grasp.phase[1].duration_s", "> 0"),
    (None, phases_with(3, "height_mm", "5.0"), "grasp.phase[3].height_mm", "unknown key for a 'hold' phase"),
    (None, phases_with(2, "duration_s", "0.5"), "grasp.phase[2].duration_s", "shorter than its move"),
    (None, phases_with(4, "height_mm", "150.0"), "grasp.phase[4].height_mm", "below the table"),
    (None, phases_with(3, "shake_cycles", "10"), "grasp.phase[3].shake_cycles", "after the phase"),
    (None, phases_with(3, "shake_cycles", "2.5"), "grasp.phase[3].shake_cycles", "must be an integer"),
    (None, phases_with(3, "load_at_s", "3.0"), "grasp.phase[3].load_at_s", "must lie in the phase"),
    (None, phases_with(2, "accel_m_s2", "0"), "grasp.phase[2].accel_m_s2", "> 0"),
    (None, phases_with(1, "name", "5"), "grasp.phase[1].name", "must be one of approach, close"),
    (None, phases_with(1, "name", None), "grasp.phase[1].name", "missing required field"),
    (None, phases_with(1, "duration_s", None), "grasp.phase[1].duration_s", "missing required field"),
    (None, phases_with(3, "shake_cycles", "true"), "grasp.phase[3].shake_cycles", "must be an integer"),
    (with_("mass_kg", "inf"), None, "grasp.mass_kg", "finite"),
    (None, phases_with(2, "height_mm", "nan"), "grasp.phase[2].height_mm", "finite"),
]


@pytest.mark.parametrize("grasp,phases,field,words", BAD, ids=[f"{b[2]}-{b[3]}" for b in BAD])
def test_bad_values_name_the_field(tmp_path, grasp, phases, field, words):
    path = write(tmp_path, grasp, phases)
    with pytest.raises(SceneError) as exc:
        load_scene(path)
    assert exc.value.field == field and words in exc.value.problem
    assert "\n" not in str(exc.value) and str(path) in str(exc.value)


@pytest.mark.parametrize("key", ["shake_hz", "shake_at_s"])
@pytest.mark.parametrize("value", ["nan", "inf"])
def test_a_number_a_hold_without_shaking_ignores_must_still_be_finite(tmp_path, key, value):
    """shake_hz / shake_at_s count only with shake_m_s2 > 0; a nan or inf there was loaded without a
    word (every other number of a scene must be finite)."""
    ph = phases_with(3, "shake_m_s2", "0.0")
    ph[3][key] = value
    path = write(tmp_path, None, ph)
    with pytest.raises(SceneError) as exc:
        load_scene(path)
    assert exc.value.field == f"grasp.phase[3].{key}" and exc.value.problem == "must be finite"
    assert "\n" not in str(exc.value) and str(path) in str(exc.value)


def test_cli_exits_2_with_one_line(tmp_path, capsys):
    path = write(tmp_path, with_("mu_k", "0.6"))
    done = run_cli(capsys, "bandwidth", "--scene", path)  # main() in this process (tests/cli_inprocess.py)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "grasp.mu_k=0.6" in lines[0] and str(path) in lines[0]
