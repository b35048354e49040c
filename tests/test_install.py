"""A plain (non-editable) install carries what it needs: the wheel holds the EDS and the bundled
scenes, and ``fusion-center demo`` runs from a fresh virtual environment outside the checkout.

The fresh venv gets the project's wheel only; its dependencies (numpy, scipy, python-can,
canopen, ...) come from this test run's environment through a ``.pth`` line, so the test needs
no network and installs nothing else, yet imports the project from the wheel alone: the
checkout is neither on ``sys.path`` nor the working directory.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import tomllib
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_every_package_of_the_tree_is_listed_in_pyproject():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    in_tree = {".".join(p.parent.relative_to(ROOT).parts) for top in ("fusion_center", "node_sim", "taxel_net")
               for p in (ROOT / top).rglob("__init__.py")}
    assert in_tree <= listed, f"packages missing from pyproject.toml: {sorted(in_tree - listed)}"
    assert {"taxel_net.eds", "taxel_net.scenes"} <= listed


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(ROOT)],
                           capture_output=True, text=True, timeout=600)
    if build.returncode != 0 and ("Could not find a version" in build.stderr or "connection" in build.stderr.lower()):
        pytest.skip(f"pip could not fetch the build backend (no package index here): {build.stderr.strip()[-200:]}")
    assert build.returncode == 0, build.stderr
    (whl,) = out.glob("taxel_can-*.whl")
    return whl


def test_wheel_carries_the_eds_and_every_bundled_scene(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    assert "taxel_net/eds/taxel_node.eds" in names
    assert "taxel_net/eds/gripper_drive.eds" in names   # the gripper-drive twin (issue 22)
    for scene in (ROOT / "scenes").rglob("*"):
        if scene.is_file():
            assert f"taxel_net/scenes/{scene.relative_to(ROOT / 'scenes').as_posix()}" in names, scene
    # the packaged EDS is the repository's one copy, byte for byte
    assert zipfile.ZipFile(wheel).read("taxel_net/eds/taxel_node.eds") == (ROOT / "eds" / "taxel_node.eds").read_bytes()
    assert zipfile.ZipFile(wheel).read("taxel_net/eds/gripper_drive.eds") == \
        (ROOT / "eds" / "gripper_drive.eds").read_bytes()


@pytest.fixture(scope="module")
def fresh_env(wheel, tmp_path_factory) -> Path:
    env_dir = tmp_path_factory.mktemp("venv") / "fresh"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    # the dependencies of this test run, not the project: the editable finder of this checkout
    # is a .pth *file* of our site-packages, which a path line does not execute
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    install = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q",
                              str(wheel)], capture_output=True, text=True, timeout=600)
    assert install.returncode == 0, install.stderr
    return env_dir


def _run(env_dir: Path, cwd: Path, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["COLUMNS"] = "120"
    return subprocess.run([str(env_dir / "bin" / args[0]), *args[1:]], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=300)


def test_installed_packages_come_from_the_wheel(fresh_env, tmp_path):
    out = _run(fresh_env, tmp_path, "python", "-c",
               "import fusion_center, node_sim, taxel_net, json; from taxel_net import resources;"
               "print(json.dumps([fusion_center.__file__, node_sim.__file__, str(resources.eds_path())]))")
    assert out.returncode == 0, out.stderr
    for path in json.loads(out.stdout):
        assert not Path(path).resolve().is_relative_to(ROOT), f"{path} is in the checkout, not the wheel"
        assert Path(path).exists()


def test_demo_runs_after_a_plain_install_outside_the_checkout(fresh_env, tmp_path):
    out = _run(fresh_env, tmp_path, "fusion-center", "demo", "--cycles", "30", "--no-live")
    assert out.returncode == 0, out.stderr
    assert "matrix57" in out.stdout
    assert "30 SYNC, 30 records" in out.stdout


def test_scenes_are_listed_and_named_after_a_plain_install(fresh_env, tmp_path):
    listed = _run(fresh_env, tmp_path, "fusion-center", "scenes", "--json")
    assert listed.returncode == 0, listed.stderr
    names = {row["name"] for row in json.loads(listed.stdout)}
    assert names == {p.stem for p in (ROOT / "scenes").glob("*.toml")}
    bw = _run(fresh_env, tmp_path, "fusion-center", "bandwidth", "--scene", "two_buses_200", "--json")
    assert bw.returncode == 0, bw.stderr
    assert json.loads(bw.stdout)["taxels"] == 200  # its CSV taxel table came along
    bad = _run(fresh_env, tmp_path, "fusion-center", "bandwidth", "--scene", "no_such_scene")
    assert bad.returncode == 2
    assert "bundled: " in bad.stderr and "matrix57" in bad.stderr and "Traceback" not in bad.stderr


def test_both_commands_report_the_installed_version(fresh_env, tmp_path):
    want = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    for command in ("fusion-center", "node-sim"):
        out = _run(fresh_env, tmp_path, command, "--version")
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == f"{command} {want}"
