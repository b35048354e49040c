"""Bus flags the python-can way (issue 12): ``-i/-c/-b/--bus-kwargs`` from ``can.cli``, python-
can's configuration (``CAN_*`` environment variables, ``~/.canrc``) when no flag is given, on
``fusion-center run`` and ``node-sim`` alike; no interface anywhere, an unknown one or a bit rate
out of 125k..1M exit 2 with one line naming where the value came from; Ctrl-C during ``run``
prints the partial summary, leaves only complete records and exits 130."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import uuid
from pathlib import Path

import can
import can.util
import pytest

from fusion_center import cli
from fusion_center.commands import resolve_bus
from taxel_net.errors import UsageError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())"]
NODE_SIM = [sys.executable, "-c", "import sys; from node_sim.cli import main; sys.exit(main())"]

SCENE = """
[scene]
name = "tiny{channels}"
seed = 3
cycles = 10

[bus]
heartbeat_producer_ms = 50
channels = {names}

[kinds.R]
zeta_mv = 1.5
noise_mv = 0.5
noise_sigma_mv = 0.0
signal_mv = 0.0

[[taxels]]
node_id = 4
kind = "R"

[[taxels]]
node_id = 9
kind = "R"
channel = {last}

[object]
model = "script"
present = [[3, 7]]
readings_mv = [3.0, 3.0]

[fusion]
tuple = "pm1"
"""


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    d = tmp_path_factory.mktemp("bus_scenes")
    one, two = d / "one.toml", d / "two.toml"
    one.write_text(SCENE.format(channels=1, names='["taxel0"]', last=0))
    two.write_text(SCENE.format(channels=2, names='["a", "b"]', last=1))
    return one, two


@pytest.fixture
def no_config(monkeypatch, tmp_path):
    """No CAN_* variables, no config file: python-can's configuration is empty."""
    for name in list(os.environ):
        if name.startswith("CAN_"):
            monkeypatch.delenv(name)
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setattr(can.util, "CONFIG_FILES", [str(tmp_path / ".canrc")])
    monkeypatch.setattr(can, "rc", {})
    return tmp_path


def clean_env(home: Path, **extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}
    env.update(HOME=str(home), **extra)
    return env


def run_sub(command, *args, env):
    if Path("/etc/can.conf").exists():
        pytest.skip("/etc/can.conf exists on this machine: python-can would read it in the subprocess")
    return subprocess.run(command + [str(a) for a in args], cwd=ROOT, capture_output=True, text=True,
                          timeout=60, env=env)


def assert_one_line_exit_2(done, *needles):
    assert done.returncode == 2, (done.returncode, done.stdout[-500:], done.stderr[-2000:])
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


def line(summary: str, key: str) -> str:
    """The value of one ``key: value`` line of a run summary."""
    found = re.findall(rf"^{re.escape(key)}:\s+(.*)$", summary, re.MULTILINE)
    assert len(found) == 1, summary
    return found[0]


def parse(*argv):
    return cli.build_parser().parse_args(["run", *map(str, argv)])


# ---------------------------------------------------------------------------- resolution


def test_flags_are_python_cans(scenes, no_config):
    one, two = scenes
    args = parse("--scene", one, "-i", "udp_multicast", "-c", "239.74.163.2", "-b", "500k",
                 "--bus-kwargs", "port=43113", "hop_limit=0", "--bus-option", "receive_own_messages=false")
    bus = resolve_bus(args, load_scene(one))
    assert (bus.interface, bus.channels, bus.bitrate) == ("udp_multicast", ["239.74.163.2"], 500_000)
    assert bus.kwargs == {"port": 43113, "hop_limit": 0, "receive_own_messages": False}
    assert bus.source == "command line"
    # the long spellings the older command lines and the tests use
    args = parse("--scene", one, "--interface", "virtual", "--channel", "x", "--bitrate", "1000000",
                 "--bus-option", "port=1")
    assert resolve_bus(args, load_scene(one)).kwargs == {"port": 1}


@pytest.mark.parametrize("argv", [["-c", "p,q"], ["-c", "p", "-c", "q"], ["--channel", "p", "--channel", "q"]])
def test_one_channel_per_scene_channel(scenes, no_config, argv):
    _, two = scenes
    bus = resolve_bus(parse("--scene", two, "-i", "virtual", *argv), load_scene(two))
    assert bus.channels == ["p", "q"]
    with pytest.raises(UsageError, match=r"--channel 'p': scene 'tiny2' has 2 channel\(s\)"):
        resolve_bus(parse("--scene", two, "-i", "virtual", "-c", "p"), load_scene(two))


def test_environment_applies_when_no_flag_is_given(scenes, no_config, monkeypatch):
    one, _ = scenes
    monkeypatch.setenv("CAN_INTERFACE", "udp_multicast")
    monkeypatch.setenv("CAN_CHANNEL", "239.74.163.9")
    monkeypatch.setenv("CAN_BITRATE", "250000")
    monkeypatch.setenv("CAN_CONFIG", json.dumps({"port": 43999, "hop_limit": 0}))
    bus = resolve_bus(parse("--scene", one), load_scene(one))
    assert (bus.interface, bus.channels, bus.bitrate) == ("udp_multicast", ["239.74.163.9"], 250_000)
    assert bus.kwargs == {"port": 43999, "hop_limit": 0} and bus.source == "CAN_INTERFACE"
    # a flag wins over the environment
    bus = resolve_bus(parse("--scene", one, "-i", "virtual", "-c", "mine", "-b", "1M"), load_scene(one))
    assert (bus.interface, bus.channels, bus.bitrate) == ("virtual", ["mine"], 1_000_000)


def test_config_file_applies_after_the_environment(scenes, no_config, monkeypatch):
    one, _ = scenes
    (no_config / ".canrc").write_text("[default]\ninterface = virtual\nchannel = from-file\nbitrate = 125000\n")
    bus = resolve_bus(parse("--scene", one), load_scene(one))
    assert (bus.interface, bus.channels, bus.bitrate) == ("virtual", ["from-file"], 125_000)
    assert bus.source == "python-can config file"
    monkeypatch.setenv("CAN_CHANNEL", "from-env")
    assert resolve_bus(parse("--scene", one), load_scene(one)).channels == ["from-env"]


def test_no_interface_anywhere_is_a_usage_error(scenes, no_config):
    one, _ = scenes
    with pytest.raises(UsageError, match=r"no CAN interface given: use -i/--interface .*CAN_INTERFACE.*~/\.canrc"):
        resolve_bus(parse("--scene", one), load_scene(one))


@pytest.mark.parametrize("env, needle", [
    ({"CAN_INTERFACE": "nosuchbus"}, "CAN_INTERFACE: interface 'nosuchbus': not a python-can interface"),
    ({"CAN_CONFIG": '{"interface": "nosuchbus"}'}, "CAN_CONFIG: interface 'nosuchbus'"),
    ({"CAN_CONFIG": "{not json"}, "CAN_CONFIG '{not json': not a JSON object"),
    ({"CAN_INTERFACE": "virtual", "CAN_BITRATE": "2000000"}, "CAN_BITRATE: bitrate 2000000: must be a classic CAN"),
    ({"CAN_INTERFACE": "virtual", "CAN_BITRATE": "50k"}, "CAN_BITRATE: bitrate 50000"),
])
def test_bad_configuration_names_its_source(scenes, no_config, monkeypatch, env, needle):
    one, _ = scenes
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    with pytest.raises(UsageError) as info:
        resolve_bus(parse("--scene", one), load_scene(one))
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_bad_config_file_names_it(scenes, no_config):
    one, _ = scenes
    (no_config / ".canrc").write_text("[default]\ninterface = bogus\n")
    with pytest.raises(UsageError, match=r"python-can config file .*interface 'bogus'"):
        resolve_bus(parse("--scene", one), load_scene(one))


# ---------------------------------------------------------------------------- exit codes


def test_run_without_an_interface_exits_2(scenes, tmp_path):
    done = run_sub(CLI, "run", "--scene", scenes[0], env=clean_env(tmp_path))
    assert_one_line_exit_2(done, "no CAN interface given", "-i/--interface", "CAN_INTERFACE", "~/.canrc",
                           "fusion-center demo")


@pytest.mark.parametrize("argv, needle", [
    (["-b", "2M"], "--bitrate 2000000: must be a classic CAN bit rate in 125000..1000000"),
    (["-b", "100k"], "--bitrate 100000"),
    (["-b", "fast"], "'fast' is not a bit rate"),
    (["-i", "nosuchbus"], "invalid choice: 'nosuchbus'"),
    (["--data-bitrate", "2M"], "--data-bitrate 2000000: only with --fd"),
])
def test_run_bad_bus_flags_exit_2(scenes, tmp_path, argv, needle):
    done = run_sub(CLI, "run", "--scene", scenes[0], "-i", "virtual", *argv, env=clean_env(tmp_path))
    assert_one_line_exit_2(done, needle)


def test_run_bad_environment_exits_2(scenes, tmp_path):
    done = run_sub(CLI, "run", "--scene", scenes[0], env=clean_env(tmp_path, CAN_INTERFACE="nosuchbus"))
    assert_one_line_exit_2(done, "CAN_INTERFACE: interface 'nosuchbus'")


def test_node_sim_without_an_interface_exits_2(scenes, tmp_path):
    done = run_sub(NODE_SIM, "--scene", scenes[0], env=clean_env(tmp_path))
    assert_one_line_exit_2(done, "no CAN interface given", "-i/--interface", "CAN_INTERFACE")


@pytest.mark.parametrize("argv, env, needle", [
    (["-i", "virtual", "-b", "2M"], {}, "--bitrate=2000000"),
    ([], {"CAN_INTERFACE": "virtual", "CAN_BITRATE": "10000"}, "bitrate (python-can configuration)=10000"),
    ([], {"CAN_INTERFACE": "nosuchbus"}, "CAN_INTERFACE: interface='nosuchbus'"),
])
def test_node_sim_bad_bus_exits_2(scenes, tmp_path, argv, env, needle):
    done = run_sub(NODE_SIM, "--scene", scenes[0], *argv, env=clean_env(tmp_path, **env))
    assert_one_line_exit_2(done, needle)


def test_node_sim_takes_the_bus_from_the_environment(scenes, no_config, monkeypatch):
    """node-sim's resolution (its own code: the twins import nothing from the centre) agrees."""
    from node_sim.cli import build_parser, resolve_bus as node_resolve

    one, two = scenes
    monkeypatch.setenv("CAN_INTERFACE", "udp_multicast")
    monkeypatch.setenv("CAN_CONFIG", json.dumps({"port": 43998}))
    args = build_parser().parse_args(["--scene", str(two), "-c", "239.1.1.1", "-c", "239.1.1.2", "-b", "800k"])
    assert node_resolve(args, load_scene(two)) == ("udp_multicast", ["239.1.1.1", "239.1.1.2"], 800_000,
                                                    {"port": 43998})


# ---------------------------------------------------------------------------- end to end


def _start_twins(scene_path, channel):
    from node_sim.rig import Rig

    rig = Rig(load_scene(scene_path), interface="virtual", channel=[channel])
    rig.start()
    return rig


def test_run_reaches_the_twins_through_the_environment(scenes, no_config, monkeypatch, capsys, tmp_path):
    """CAN_INTERFACE/CAN_CHANNEL alone point ``run`` at the bus the twins are on (in-process
    virtual bus: the same code path as any interface), and the summary says which bus it used."""
    one, _ = scenes
    channel = f"env-{uuid.uuid4().hex[:8]}"
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", channel)
    rig = _start_twins(one, channel)
    try:
        rc = cli.main(["run", "--scene", str(one), "--cycles", "10", "--no-live", "--boot-timeout", "2",
                       "--json-lines", str(tmp_path / "r.jsonl")])
    finally:
        rig.stop()
    out = capsys.readouterr().out
    assert rc == 0
    assert line(out, "bus") == f"virtual {channel} (CAN_INTERFACE)"
    assert line(out, "missing_at_boot") == "none"
    records = [json.loads(line) for line in (tmp_path / "r.jsonl").read_text().splitlines()]
    assert len(records) == 10 and sum(r["decision"] in ("H1", "H0") for r in records) >= 5


def _interrupt_when(predicate):
    """SIGINT to this process (the main thread runs the command) once ``predicate()`` holds."""
    done = threading.Event()

    def watch():
        while not done.wait(0.02):
            if predicate():
                os.kill(os.getpid(), signal.SIGINT)
                return
    threading.Thread(target=watch, daemon=True).start()
    return done


def _lines(path: Path) -> int:
    try:
        return path.read_text().count("\n")
    except FileNotFoundError:
        return 0


def test_ctrl_c_during_run_prints_the_partial_summary_and_exits_130(scenes, no_config, capsys, tmp_path):
    one, _ = scenes
    channel = f"int-{uuid.uuid4().hex[:8]}"
    log = tmp_path / "r.jsonl"
    rig = _start_twins(one, channel)
    stray = []
    previous = signal.signal(signal.SIGINT, lambda *a: stray.append(a))  # a late signal must not stop pytest
    stop = _interrupt_when(lambda: _lines(log) >= 5)
    try:
        rc = cli.main(["run", "--scene", str(one), "-i", "virtual", "-c", channel, "--cycles", "100000",
                       "--no-live", "--boot-timeout", "2", "--json-lines", str(log)])
    finally:
        stop.set()
        signal.signal(signal.SIGINT, previous)
        rig.stop()
    out = capsys.readouterr().out
    assert rc == 130 and not stray
    text = log.read_text()
    assert text.endswith("\n")
    records = [json.loads(line) for line in text.splitlines()]  # every line a whole record
    n = len(records)
    assert 5 <= n < 100000 and [r["cycle"] for r in records] == list(range(n))
    assert line(out, "cycles") == f"{n} SYNC, {n} records"  # the summary counts what was written
    assert line(out, "interrupted").startswith(f"Ctrl-C after {n} of 100000 SYNC cycles")
    assert "closed_by" in records[-1] and records[-1]["closed_by"] in ("complete", "window", "nmt", "sync")


def test_ctrl_c_during_boot_exits_130_with_an_empty_summary(scenes, no_config, capsys, monkeypatch, tmp_path):
    from fusion_center.service import FusionService

    one, _ = scenes
    booting = threading.Event()
    boot = FusionService.boot

    def flagged_boot(self, *a, **k):
        booting.set()
        return boot(self, *a, **k)
    monkeypatch.setattr(FusionService, "boot", flagged_boot)
    stray = []
    previous = signal.signal(signal.SIGINT, lambda *a: stray.append(a))
    stop = _interrupt_when(booting.is_set)
    try:  # nobody on this channel: the boot would wait 60 s for the nodes
        rc = cli.main(["run", "--scene", str(one), "-i", "virtual", "-c", f"boot-{uuid.uuid4().hex[:8]}",
                       "--no-live", "--boot-timeout", "60", "--json-lines", str(tmp_path / "r.jsonl")])
    finally:
        stop.set()
        signal.signal(signal.SIGINT, previous)
    out = capsys.readouterr().out
    assert rc == 130 and not stray
    assert line(out, "cycles") == "0 SYNC, 0 records"
    assert line(out, "interrupted").startswith("Ctrl-C after 0 of 10 SYNC cycles")
    assert (tmp_path / "r.jsonl").read_text() == ""


@pytest.mark.parametrize("value", ["-1", "1_0", "５", " 5", str(2**63), "x"])
def test_node_sim_seed_is_the_scenes_range_in_one_line(capsys, value):
    """node-sim --seed: an integer 0..2^63-1 as the scene's [scene] seed, else exit 2 in one line -
    a negative one was taken, the world thread died on it (numpy: "expected non-negative
    integer") and the twins served on without a world (2026-11-30, stop 32)."""
    from node_sim.cli import main as node_main

    with pytest.raises(SystemExit) as info:
        node_main(["--scene", "grasp_lift", "-i", "virtual", "-c", "seed-test", "--seed", value])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "argument --seed" in err[-1] and "0..2^63-1" in err[-1]


def test_a_rig_refuses_a_seed_outside_the_scenes_range():
    from node_sim.rig import Rig
    from taxel_net.errors import ParameterError
    from taxel_net.scene import load_scene

    for seed in (-1, 2**63, True, 1.5):
        with pytest.raises(ParameterError, match="seed"):
            Rig(load_scene("grasp_lift"), channel=["seed-test"], seed=seed)
