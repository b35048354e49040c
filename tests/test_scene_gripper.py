"""The scene's ``[gripper]`` table (taxel_net.gripper): defaults are the EDS's, values in the scene's
units become the drive's OD units exactly, every bad value is refused in one line naming the field,
and the CLIs exit 2 with that line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import canopen
import pytest

from taxel_net.errors import SceneError
from cli_inprocess import run_cli
from taxel_net.gripper import GripperSpec, startup_values
from taxel_net.resources import gripper_eds_path
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent

BASE = """
[scene]
name = "g"

[bus]
heartbeat_producer_ms = 40
channels = ["a", "b"]

[[taxels]]
node_id = 1
kind = "R"

[[taxels]]
node_id = 2
kind = "R"
channel = 1

[fusion]
tuple = "pm1"

[gripper]
node_id = 20
"""


def load(tmp_path, text):
    p = tmp_path / "g.toml"
    p.write_text(text)
    return load_scene(p)


def test_defaults_are_the_eds_defaults(tmp_path):
    """``[gripper] node_id = N`` alone: the drive as shipped (the application objects' start-up
    values are the EDS's DefaultValue, read by canopen)."""
    scene = load(tmp_path, BASE)
    assert scene.gripper == GripperSpec(node_id=20)
    od = canopen.import_od(str(gripper_eds_path()), 20)
    values = startup_values(scene)
    for (index, sub), value in values.items():
        if index >= 0x2000:
            var = od[index] if isinstance(od[index], canopen.objectdictionary.ODVariable) else od[index][sub]
            assert var.default == value, (hex(index), sub)
    # the communication values come from the scene's bus and master
    assert values[(0x1017, 0)] == 40 and values[(0x1019, 0)] == 0 and values[(0x1006, 0)] == 10_000
    assert values[(0x1016, 1)] == 127 << 16 | 120                  # 3 x the master's 40 ms
    assert values[(0x1018, 4)] & 0xFFFF == 20                      # channel 0, node 20
    assert load_scene("matrix57").gripper is None


def test_scene_units_become_od_units(tmp_path):
    scene = load(tmp_path, BASE.replace("node_id = 20\n", """node_id = 21
channel = 1
mode = "torque"
rated_force_n = 65.3
rated_torque_nm = 0.85
max_torque_permille = 2500
torque_slope_permille_s = 123
velocity_mm_s = 12.345
stroke_min_mm = 100.5
stroke_max_mm = 6553.5
position_window_mm = 0
quick_stop_option = 6
fault_reaction_option = 0
abort_connection_option = 3
master_timeout_ms = 41
"""))
    v = startup_values(scene)
    assert v[(0x6060, 0)] == 4 and v[(0x2103, 0)] == 653 and v[(0x6076, 0)] == 850 and v[(0x6072, 0)] == 2500
    assert v[(0x6087, 0)] == 123 and v[(0x6081, 0)] == 12345 and v[(0x6067, 0)] == 0
    assert v[(0x607D, 1)] == 100_500 and v[(0x607D, 2)] == 6_553_500
    assert list(v).index((0x607D, 2)) < list(v).index((0x607D, 1))   # max first: min < max at each write
    assert v[(0x605A, 0)] == 6 and v[(0x605E, 0)] == 0 and v[(0x6007, 0)] == 3
    assert v[(0x1016, 1)] == 127 << 16 | 41
    assert v[(0x1018, 4)] & 0xFFFF == 1 << 8 | 21
    # a taxel's node-ID of ANOTHER channel is free here (each channel is its own CANopen network)
    assert load(tmp_path, BASE.replace("node_id = 20\n", "node_id = 2\n")).gripper.node_id == 2


def test_no_master_heartbeat_no_watch(tmp_path):
    scene = load(tmp_path, BASE + "\n[master]\nheartbeat_ms = 0\n")
    assert startup_values(scene)[(0x1016, 1)] == 0


# (replace in [gripper] "node_id = 20\n" by ..., field, value)
ERRORS = [
    ("", "gripper.node_id", None),                                   # missing
    ("node_id = 0\n", "gripper.node_id", 0),
    ("node_id = 1\n", "gripper.node_id", 1),                         # a taxel's on channel 0
    ("node_id = 2\nchannel = 1\n", "gripper.node_id", 2),            # a taxel's on channel 1
    ("node_id = 127\n", "gripper.node_id", 127),                     # the master's
    ("node_id = 20\nchannel = 2\n", "gripper.channel", 2),
    ("node_id = 20\nchannel = true\n", "gripper.channel", True),
    ("node_id = 20\nmode = \"velocity\"\n", "gripper.mode", "velocity"),
    ("node_id = 20\nrated_force_n = 0.05\n", "gripper.rated_force_n", 0.05),     # below 0.1 N steps
    ("node_id = 20\nrated_force_n = 0\n", "gripper.rated_force_n", 0.0),
    ("node_id = 20\nrated_force_n = 6553.6\n", "gripper.rated_force_n", 6553.6),
    ("node_id = 20\nrated_force_n = nan\n", "gripper.rated_force_n", "nan"),
    ("node_id = 20\nrated_torque_nm = 0.0005\n", "gripper.rated_torque_nm", 0.0005),
    ("node_id = 20\nmax_torque_permille = 0\n", "gripper.max_torque_permille", 0),
    ("node_id = 20\nmax_torque_permille = 3001\n", "gripper.max_torque_permille", 3001),
    ("node_id = 20\nmax_torque_permille = 100.5\n", "gripper.max_torque_permille", 100.5),
    ("node_id = 20\ntorque_slope_permille_s = 0\n", "gripper.torque_slope_permille_s", 0),
    ("node_id = 20\nvelocity_mm_s = 0\n", "gripper.velocity_mm_s", 0.0),
    ("node_id = 20\nvelocity_mm_s = -5\n", "gripper.velocity_mm_s", -5.0),
    ("node_id = 20\nstroke_min_mm = 10\nstroke_max_mm = 10\n", "gripper.stroke_max_mm", 10.0),
    ("node_id = 20\nstroke_max_mm = 6553.6\n", "gripper.stroke_max_mm", 6553.6),
    ("node_id = 20\nstroke_min_mm = -1\n", "gripper.stroke_min_mm", -1.0),
    ("node_id = 20\nstroke_max_mm = 80.0005\n", "gripper.stroke_max_mm", 80.0005),   # not whole µm
    ("node_id = 20\nposition_window_mm = -0.001\n", "gripper.position_window_mm", -0.001),
    ("node_id = 20\nquick_stop_option = 3\n", "gripper.quick_stop_option", 3),
    ("node_id = 20\nfault_reaction_option = 3\n", "gripper.fault_reaction_option", 3),
    ("node_id = 20\nabort_connection_option = -1\n", "gripper.abort_connection_option", -1),
    ("node_id = 20\nmaster_timeout_ms = 40\n", "gripper.master_timeout_ms", 40),    # = the period
    ("node_id = 20\nmaster_timeout_ms = 70000\n", "gripper.master_timeout_ms", 70000),
    ("node_id = 20\nforce = 3\n", "gripper.force", 3),                              # unknown key
    # beyond any float / beyond round(): one line, no OverflowError (2026-11-30, stop 32)
    ("node_id = 20\nrated_force_n = 1e308\n", "gripper.rated_force_n", 1e308),
    ("node_id = 20\nvelocity_mm_s = 1e308\n", "gripper.velocity_mm_s", 1e308),
    ("node_id = 20\nrated_force_n = " + "9" * 400 + "\n", "gripper.rated_force_n", "999999999999... (400 digits)"),
    ("node_id = 20\nmax_torque_permille = " + "9" * 400 + "\n", "gripper.max_torque_permille",
     "999999999999... (400 digits)"),
]


@pytest.mark.parametrize("body, field, value", ERRORS, ids=[f"{e[1]}-{i}" for i, e in enumerate(ERRORS)])
def test_each_bad_value_is_refused_naming_the_field(tmp_path, body, field, value):
    path = tmp_path / "g.toml"
    path.write_text(BASE.replace("node_id = 20\n", body))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    err = info.value
    assert err.path == str(path) and err.field == field and err.problem
    if value == "nan":
        assert err.value != err.value
    elif value is not None:
        assert err.value == value and type(err.value) is type(value)
    assert "\n" not in str(err)


def test_table_itself_and_master_without_heartbeat(tmp_path):
    with pytest.raises(SceneError) as info:
        load(tmp_path, "gripper = 3\n" + BASE.replace("[gripper]\nnode_id = 20\n", ""))
    assert info.value.field == "gripper"
    text = BASE.replace("node_id = 20\n", "node_id = 20\nmaster_timeout_ms = 500\n") + "\n[master]\nheartbeat_ms = 0\n"
    with pytest.raises(SceneError) as info:
        load(tmp_path, text)
    assert info.value.field == "gripper.master_timeout_ms" and "no heartbeat" in info.value.problem


def test_patch_tpdo_on_a_drive_cob_id_is_refused(tmp_path):
    """Patch nodes' TPDOs take COB-IDs 0x181, 0x182, ... (bus.tpdo_cob_id_base): a drive with
    node-ID 2 has TPDO1 0x182 - taken by the second patch TPDO."""
    patch = BASE.replace('channels = ["a", "b"]', 'channels = ["a", "b"]\npatch_nodes = true')
    taxels = "".join(f'\n[[taxels]]\nnode_id = 1\nkind = "R"\n' for _ in range(40))
    text = patch.replace("[fusion]", taxels + "\n[fusion]")
    scene = load(tmp_path, text.replace("node_id = 20\n", "node_id = 3\n"))  # 41 taxels, 1 bit each: 1 TPDO
    assert scene.gripper.node_id == 3
    wide = text.replace("patch_nodes = true", "patch_nodes = true\nmode = \"raw\"")   # int16: 4 a frame
    with pytest.raises(SceneError) as info:
        load(tmp_path, wide.replace("node_id = 20\n", "node_id = 2\n"))
    assert info.value.field == "gripper.node_id" and "0x182" in info.value.problem


@pytest.mark.parametrize("cli", ["node_sim.cli", "fusion_center.cli"])
def test_clis_exit_2_with_the_one_line(tmp_path, capsys, cli):
    path = tmp_path / "g.toml"
    path.write_text(BASE.replace("node_id = 20\n", "node_id = 20\nstroke_max_mm = 80.0005\n"))
    if cli == "node_sim.cli":  # node-sim, a real process (its main, given a good scene, serves until a signal)
        done = subprocess.run([sys.executable, "-m", cli, "--scene", str(path), "-i", "virtual"], cwd=ROOT,
                              capture_output=True, text=True, timeout=120)
    else:  # fusion-center's main() in this process (tests/cli_inprocess.py): exit status and stderr
        done = run_cli(capsys, "demo", "--scene", path)
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "gripper.stroke_max_mm" in lines[0] and str(path) in lines[0], lines
