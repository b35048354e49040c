"""The scene's ``[grip]`` table (taxel_net.scene_grip): the grip-force law's gains and limits as
``Scene.grip`` (a :class:`fusion_center.core.grip_law.GripParams`); every field read, every bad
value refused in one line naming the file and ``grip.<field>``; the cross-checks with the drive
and ``[forces]``; the CLIs exit 2 with that line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from fusion_center.core import grip_law
from cli_inprocess import run_cli
from taxel_net.errors import SceneError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent

BASE = """
[scene]
name = "g"

[[taxels]]
node_id = 1
kind = "R"

[fusion]
tuple = "pm1"

[forces]
mu = 0.35

[gripper]
node_id = 20
rated_force_n = 140.0
max_torque_permille = 800
"""
# the drive's largest force per jaw: 140 N x 800 / 1000 = 112 N


def write(tmp_path, grip: str | None, base: str = BASE) -> Path:
    path = tmp_path / "g.toml"
    path.write_text(base + ("" if grip is None else "\n[grip]\n" + grip))
    return path


def test_no_table_no_law(tmp_path):
    assert load_scene(write(tmp_path, None)).grip is None
    assert load_scene("grasp_scripted").grip is None


def test_empty_table_defaults(tmp_path):
    """All fields optional: the law's defaults, max_n the drive's largest force per jaw, mu [forces]'."""
    g = load_scene(write(tmp_path, "")).grip
    assert isinstance(g, grip_law.GripParams)
    assert g.max_n == pytest.approx(112.0) and g.mu == 0.35
    d = grip_law.GripParams()
    for name in ("grasp_n", "min_n", "raise_fraction", "raise_n", "settle_s", "margin", "relax_delay_s",
                 "return_delay_s", "relax_per_s", "probe_headroom", "return_per_s", "safety_factor", "open_n",
                 "presence_cycles", "edge_fraction", "edge_cycles"):
        assert getattr(g, name) == getattr(d, name), name


# every field, with a value that is not its default, read as given
ALL = {"grasp_n": 7.5, "min_n": 1.25, "max_n": 60.0, "raise_fraction": 0.4, "raise_n": 0.75, "settle_s": 0.03,
       "margin": 0.3, "relax_delay_s": 0.8, "return_delay_s": 0.1, "relax_per_s": 0.25, "probe_headroom": 2.0, "return_per_s": 2.5,
       "safety_factor": 1.5, "mu": 0.6, "open_n": 20.0, "presence_cycles": 3, "edge_fraction": 0.55, "edge_cycles": 3}


def test_every_field_is_read(tmp_path):
    g = load_scene(write(tmp_path, "".join(f"{k} = {v}\n" for k, v in ALL.items()))).grip
    for k, v in ALL.items():
        assert getattr(g, k) == v and type(getattr(g, k)) is type(v), k
    assert set(ALL) == {f for f in grip_law.GripParams.__dataclass_fields__}, "a field this test does not cover"


def test_integers_are_numbers(tmp_path):
    g = load_scene(write(tmp_path, "grasp_n = 8\nmax_n = 112\n")).grip
    assert g.grasp_n == 8.0 and type(g.grasp_n) is float and g.max_n == 112.0


ERRORS = [  # (the [grip] body, field, value, words in the problem)
    ("grasp_n = \"5\"\n", "grip.grasp_n", "5", "number"),
    ("grasp_n = true\n", "grip.grasp_n", True, "number"),
    ("grasp_n = nan\n", "grip.grasp_n", "nan", "finite"),
    ("grasp_n = 0.2\nmin_n = 0.5\n", "grip.grasp_n", 0.2, "min_n"),
    ("grasp_n = 0\nmin_n = 0\n", "grip.grasp_n", 0.0, "> 0"),
    ("grasp_n = 70.0\nmax_n = 60.0\n", "grip.grasp_n", 70.0, "max_n"),
    ("min_n = -1.0\n", "grip.min_n", -1.0, ">= 0"),
    ("min_n = inf\n", "grip.min_n", "inf", "finite"),
    ("max_n = 0.0\n", "grip.max_n", 0.0, "> 0"),
    ("max_n = -3.0\n", "grip.max_n", -3.0, "> 0"),
    ("max_n = 112.5\n", "grip.max_n", 112.5, "largest force per jaw, 112 N"),
    ("max_n = [1.0]\n", "grip.max_n", [1.0], "number"),
    ("raise_fraction = -0.1\n", "grip.raise_fraction", -0.1, ">= 0"),
    ("raise_fraction = 0\nraise_n = 0\n", "grip.raise_n", 0.0, "slip must raise"),
    ("raise_n = -0.5\n", "grip.raise_n", -0.5, ">= 0"),
    ("settle_s = -0.1\n", "grip.settle_s", -0.1, ">= 0"),
    ("margin = -0.1\n", "grip.margin", -0.1, ">= 0"),
    ("relax_delay_s = -1\n", "grip.relax_delay_s", -1.0, ">= 0"),
    ("return_delay_s = -1\n", "grip.return_delay_s", -1.0, ">= 0"),
    ("relax_per_s = -0.5\n", "grip.relax_per_s", -0.5, ">= 0"),
    ("return_per_s = -3\n", "grip.return_per_s", -3.0, ">= 0"),
    ("probe_headroom = 0.5\n", "grip.probe_headroom", 0.5, ">= 1"),
    ("relax_per_s = 2.0\nreturn_per_s = 1.0\n", "grip.return_per_s", 1.0, "relax_per_s"),
    ("safety_factor = 0.9\n", "grip.safety_factor", 0.9, ">= 1"),
    ("safety_factor = \"high\"\n", "grip.safety_factor", "high", "number"),
    ("mu = 0.0\n", "grip.mu", 0.0, "> 0"),
    ("mu = -0.2\n", "grip.mu", -0.2, "> 0"),
    ("open_n = 0.0\n", "grip.open_n", 0.0, "> 0"),
    ("open_n = 200.0\n", "grip.open_n", 200.0, "largest force per jaw"),
    ("presence_cycles = 0\n", "grip.presence_cycles", 0, ">= 1"),
    ("presence_cycles = 2.5\n", "grip.presence_cycles", 2.5, "integer"),
    ("presence_cycles = false\n", "grip.presence_cycles", False, "integer"),
    ("edge_fraction = 0\n", "grip.edge_fraction", 0.0, "(0, 1]"),
    ("edge_fraction = -0.2\n", "grip.edge_fraction", -0.2, "(0, 1]"),
    ("edge_fraction = 1.5\n", "grip.edge_fraction", 1.5, "(0, 1]"),
    ("edge_fraction = nan\n", "grip.edge_fraction", "nan", "finite"),
    ("edge_fraction = \"0.4\"\n", "grip.edge_fraction", "0.4", "number"),
    ("edge_fraction = true\n", "grip.edge_fraction", True, "number"),
    ("edge_cycles = 0\n", "grip.edge_cycles", 0, ">= 1"),
    ("edge_cycles = -2\n", "grip.edge_cycles", -2, ">= 1"),
    ("edge_cycles = 1.5\n", "grip.edge_cycles", 1.5, "integer"),
    ("edge_cycles = true\n", "grip.edge_cycles", True, "integer"),
    ("edge_cycles = \"2\"\n", "grip.edge_cycles", "2", "integer"),
    ("gain = 3\n", "grip.gain", 3, "unknown key"),
]


@pytest.mark.parametrize("body, field, value, words", ERRORS, ids=[f"{e[1]}-{i}" for i, e in enumerate(ERRORS)])
def test_each_bad_value_is_refused_naming_the_field(tmp_path, body, field, value, words):
    path = write(tmp_path, body)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    err = info.value
    assert err.path == str(path) and err.field == field, str(err)
    if value in ("nan",):
        assert err.value != err.value
    elif value == "inf":
        assert err.value == float("inf")
    else:
        assert err.value == value and type(err.value) is type(value)
    assert words in err.problem, err.problem
    assert "\n" not in str(err)


def test_grip_without_gripper_is_refused(tmp_path):
    base = BASE[:BASE.index("[gripper]")]
    with pytest.raises(SceneError) as info:
        load_scene(write(tmp_path, "grasp_n = 5.0\n", base))
    assert info.value.field == "grip" and "[gripper]" in info.value.problem


def test_table_itself_must_be_a_table(tmp_path):
    path = tmp_path / "g.toml"
    path.write_text("grip = 3\n" + BASE)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert info.value.field == "grip" and "table" in info.value.problem


def test_defaults_that_do_not_fit_the_drive_name_their_origin(tmp_path):
    """A weak drive (max 4 N per jaw) under the default grasp_n (5 N): grasp_n is named; a [forces]
    mu cannot be bad (its own loader refuses it), so only max_n's origin is ever the drive."""
    weak = BASE.replace("rated_force_n = 140.0", "rated_force_n = 5.0")
    with pytest.raises(SceneError) as info:
        load_scene(write(tmp_path, "", weak))
    assert info.value.field == "grip.grasp_n" and "max_n" in info.value.problem and "4" in info.value.problem


@pytest.mark.parametrize("cli, body, field", [
    ("node_sim.cli", "max_n = 500.0\n", "grip.max_n"),
    ("fusion_center.cli", "max_n = 500.0\n", "grip.max_n"),
    ("fusion_center.cli", "edge_fraction = 1.5\n", "grip.edge_fraction"),
    ("fusion_center.cli", "edge_cycles = 0\n", "grip.edge_cycles"),
    ("node_sim.cli", "edge_cycles = 2.5\n", "grip.edge_cycles"),
])
def test_clis_exit_2_with_the_one_line(tmp_path, capsys, cli, body, field):
    path = write(tmp_path, body)
    if cli == "node_sim.cli":  # node-sim, a real process (its main, given a good scene, serves until a signal)
        done = subprocess.run([sys.executable, "-m", cli, "--scene", str(path), "-i", "virtual"], cwd=ROOT,
                              capture_output=True, text=True, timeout=120)
    else:  # fusion-center's main() in this process (tests/cli_inprocess.py): exit status and stderr
        done = run_cli(capsys, "demo", "--scene", path)
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and field in lines[0] and str(path) in lines[0], lines


def test_the_default_opening_force_follows_a_drive_that_cannot_give_it(tmp_path):
    """[grip] without open_n on a drive whose largest force per jaw is below the default 10 N: the
    opening force is the drive's largest (it was taken unchecked, 10 N the drive cannot give);
    given explicitly above it, it is still refused naming the field."""
    import re

    from taxel_net.errors import SceneError
    from taxel_net.scene import load_scene

    text = (Path(load_scene("grasp_lift").path).read_text())
    small = re.sub(r"(?m)^max_torque_permille = .*$", "max_torque_permille = 100", text)
    small = re.sub(r"(?m)^rated_force_n = .*$", "rated_force_n = 40.0", small)
    small = re.sub(r"(?m)^(max_n|open_n) = .*\n", "", small)
    small = re.sub(r"(?m)^grasp_n = .*$", "grasp_n = 2.0", small)
    path = tmp_path / "small.toml"
    path.write_text(small.replace("data/", str(Path(load_scene("grasp_lift").path).parent / "data") + "/"))
    scene = load_scene(path)
    top = scene.gripper.rated_force_n * scene.gripper.max_torque_permille / 1000
    assert top == pytest.approx(4.0) and scene.grip.open_n == pytest.approx(top)
    path.write_text(path.read_text().replace("[grip]\n", "[grip]\nopen_n = 10.0\n", 1))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert info.value.field == "grip.open_n"
