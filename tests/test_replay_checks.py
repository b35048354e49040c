"""Replay checks the trace against the scene (issue 12): a channel the scene does not have, a
format without channels for a scene with several, a trace of another scene, the other mode -
each exits 2 with one line and writes nothing, ``--force`` replays anyway; every format python-
can writes and reads back replays to the live records (``.trc`` numbers its channels from 1; the
lossy formats, refused by ``--log``, replayed from converted copies);
can-utils' ``log2asc``/``asc2log`` read and write traces replay accepts (skipped without them).

Small scenes (three and four nodes) keep every test short."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path
from unittest import mock

import can.logconvert
import pytest

from cli_inprocess import run_cli
from fusion_center.commands.demo import run_demo
from fusion_center.service import replay_trace
from fusion_center.service.traces import FOREIGN_FRACTION_MAX, check_trace
from taxel_net.errors import UsageError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent

TAXELS = """
[[taxels]]
node_id = {a}
kind = "R"{ca}

[[taxels]]
node_id = {b}
kind = "R"{cb}

[[taxels]]
node_id = {c}
kind = "R"{cc}
"""


def scene_text(name, ids=(4, 9, 17), channels=("taxel0",), taxel_channels=(0, 0, 0), mode="decision"):
    taxels = TAXELS.format(a=ids[0], b=ids[1], c=ids[2],
                           **{k: f"\nchannel = {ch}" if ch else "" for k, ch in zip(("ca", "cb", "cc"), taxel_channels)})
    return f"""
[scene]
name = "{name}"
seed = 3
cycles = 10

[bus]
heartbeat_producer_ms = 50
mode = "{mode}"
channels = {list(channels)!r}

[kinds.R]
zeta_mv = 1.5
noise_mv = 0.5
noise_sigma_mv = 0.0
signal_mv = 0.0
{taxels}
[object]
model = "script"
present = [[3, 7]]
readings_mv = [3.0, 3.0, 0.5]

[fusion]
tuple = "pm1"
""".replace("'", '"')


@pytest.fixture(scope="module")
def traces(tmp_path_factory):
    """One short demo per case: (scene path, trace, live decision log)."""
    d = tmp_path_factory.mktemp("replay_checks")
    scenes = {
        "one": scene_text("tiny3"),
        "other": scene_text("other3", ids=(30, 31, 32)),
        "two": scene_text("tiny2ch", channels=("a", "b"), taxel_channels=(0, 1, 1)),
        "raw": scene_text("tiny3", mode="raw"),
    }
    paths = {}
    for key, text in scenes.items():
        paths[key] = d / f"{key}.toml"
        paths[key].write_text(text)
    out = {}
    for key, scene_key, ext in (("log", "one", "log"), ("trc", "one", "trc"), ("two_log", "two", "log"),
                                ("two_csv", "two", "csv"), ("raw_log", "raw", "log")):
        trace, live = d / f"{key}.{ext}", d / f"{key}.jsonl"
        if ext == "log":
            run_demo(load_scene(paths[scene_key]), 10, json_lines=live, trace=trace)
        else:  # --log refuses the lossy formats: a copy converted as users make one
            recorded = d / f"{key}.recorded.log"
            run_demo(load_scene(paths[scene_key]), 10, json_lines=live, trace=recorded)
            with mock.patch.object(sys, "argv", ["can.logconvert", str(recorded), str(trace)]):
                can.logconvert.main()  # python -m can.logconvert's code, in this process
        out[key] = (paths[scene_key], trace, live)
    out["scenes"] = paths
    return out


@pytest.fixture
def cli(capsys):
    """``fusion-center ARGS`` in this process (tests/cli_inprocess.py): these tests are about what
    the command makes of the trace and scene - its exit status, its one-line error, what it prints
    and writes - and an exception escaping it (a traceback in a subprocess) fails the test."""
    return lambda *args: run_cli(capsys, *args)


def assert_one_line_exit_2(done, *needles):
    assert done.returncode == 2, (done.returncode, done.stderr[-2000:])
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert done.stdout == ""  # no record printed before the refusal


def test_trc_replays_to_the_live_records(traces, tmp_path):
    """TRC numbers channels from 1 (python-can's writer adds 1): before, its frames all landed
    on channel 1 of a one-channel scene - 0 records, every frame unknown_cob_id."""
    scene, trace, live = traces["trc"]
    assert " 1 " in next(line for line in trace.read_text().splitlines() if " DT " in line)  # bus 1 in the file
    replayed = tmp_path / "r.jsonl"
    records, counters = replay_trace(load_scene(scene), trace, json_lines=replayed)
    assert len(records) == 10 and counters["unknown_cob_id"] == 0
    assert replayed.read_bytes() == live.read_bytes()
    assert check_trace(load_scene(scene), trace)["frames"] > 0


def test_two_channel_trace_against_a_one_channel_scene_exits_2(cli, traces, tmp_path):
    _, trace, _ = traces["two_log"]
    out = tmp_path / "out.jsonl"
    out.write_text('{"cycle": 0}\n')  # a log of an earlier replay must not pass for this one's
    done = cli("replay", "--scene", traces["scenes"]["one"], trace, "--json-lines", out)
    assert_one_line_exit_2(done, str(trace), "channel 1", "tiny3", "--force")
    assert not out.exists() and not Path(str(out) + ".partial").exists()


def test_two_channel_csv_exits_2_at_replay(cli, traces):
    scene, trace, _ = traces["two_csv"]
    with pytest.raises(UsageError, match=r"\.csv stores no channel.*2 channels"):
        check_trace(load_scene(scene), trace)
    # its records would be wrong: both channels' frames come back on channel 0
    assert_one_line_exit_2(cli("replay", "--scene", scene, trace), ".csv stores no channel", "--force")


@pytest.mark.parametrize("ext,needle", [("csv", "CAN FD flag"), ("db", "CAN FD flag"), ("trc", "drops CAN FD")])
def test_formats_that_lose_frames_are_refused_at_log_time(cli, traces, tmp_path, ext, needle):
    """python-can's CSV and SQLite record no FD flag (an FD frame on a node's PDO COB-ID came
    back as that node's classic PDO), its TRC writer drops FD, remote and error frames: the
    replay of a run with such frames on its bus differed from the live records (issue 21)."""
    for scene in (traces["scenes"]["one"], traces["scenes"]["two"]):
        assert_one_line_exit_2(cli("demo", "--scene", scene, "--log", tmp_path / f"x.{ext}", "--no-live"),
                               "--log", needle, ".log, .asc or .blf", "can.logconvert")
        assert not (tmp_path / f"x.{ext}").exists()


def test_two_channel_log_replays_with_its_scene(traces, tmp_path):
    scene, trace, live = traces["two_log"]
    replayed = tmp_path / "r.jsonl"
    check_trace(load_scene(scene), trace)
    replay_trace(load_scene(scene), trace, json_lines=replayed)
    assert replayed.read_bytes() == live.read_bytes()


def test_trace_of_another_scene_exits_2(cli, traces):
    _, trace, _ = traces["log"]
    other = traces["scenes"]["other"]
    assert_one_line_exit_2(cli("replay", "--scene", other, trace), "node-ID(s) 4, 9, 17", "other3", "--force")


def test_force_replays_the_trace_of_another_scene(cli, traces, tmp_path):
    _, trace, _ = traces["log"]
    other = traces["scenes"]["other"]
    out = tmp_path / "forced.jsonl"
    done = cli("replay", "--scene", other, trace, "--json-lines", out, "--force")
    assert done.returncode == 0, done.stderr
    assert "records: 10" in done.stdout and "unknown_cob_id" in done.stdout  # replayed, and says what it saw


def test_a_few_foreign_frames_are_tolerated(traces, tmp_path):
    """Another device's frames on the bus (below FOREIGN_FRACTION_MAX) are no reason to refuse."""
    scene, trace, _ = traces["log"]
    lines = trace.read_text().splitlines()
    stamp = lines[-1].split()[0]
    allowed = int(FOREIGN_FRACTION_MAX * len(lines))
    few, many = tmp_path / "few.log", tmp_path / "many.log"
    few.write_text("\n".join(lines + [f"{stamp} can0 1B5#01"] * allowed) + "\n")
    many.write_text("\n".join(lines + [f"{stamp} can0 1B5#01"] * (allowed + 5)) + "\n")
    assert check_trace(load_scene(scene), few)["foreign"] == allowed
    with pytest.raises(UsageError, match="node-ID\\(s\\) 53"):
        check_trace(load_scene(scene), many)


@pytest.mark.parametrize("trace_key, scene_key, mode, needle", [
    ("log", "one", "raw", "recorded in decision mode"),    # --mode raw on a decision trace
    ("raw_log", "one", None, "recorded in raw mode"),      # a raw trace replayed with the decision scene
])
def test_mode_mismatch_exits_2(cli, traces, trace_key, scene_key, mode, needle):
    _, trace, _ = traces[trace_key]
    args = ["replay", "--scene", traces["scenes"][scene_key], trace] + (["--mode", mode] if mode else [])
    other = "decision" if "decision" in needle else "raw"
    assert_one_line_exit_2(cli(*args), needle, f"--mode {other}", "--force")


def test_mode_given_right_replays_the_raw_trace(cli, traces, tmp_path):
    scene, trace, live = traces["raw_log"]
    replayed = tmp_path / "r.jsonl"
    done = cli("replay", "--scene", traces["scenes"]["one"], trace, "--mode", "raw", "--json-lines", replayed)
    assert done.returncode == 0, done.stderr
    assert replayed.read_bytes() == live.read_bytes()


def test_log_formats_python_can_cannot_read_back_are_refused_before_the_run(cli, tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(scene_text("tiny3"))
    assert_one_line_exit_2(cli("demo", "--scene", scene, "--log", tmp_path / "x.txt", "--no-live"),
                           "cannot read it back")
    assert not (tmp_path / "x.txt").exists()


def _can_utils(*tools):
    missing = [t for t in tools if shutil.which(t) is None]
    if missing:
        pytest.skip(f"can-utils' {', '.join(missing)} not installed (apt-get install can-utils)")


def test_can_utils_log2asc_reads_the_candump_log(traces, tmp_path):
    """can-utils' log2asc converts the service's candump .log; the ASC it writes replays to the
    live records (it has no trigger block, so no 'End TriggerBlock' is asked for)."""
    _can_utils("log2asc")
    scene, trace, live = traces["log"]
    converted = tmp_path / "conv.asc"
    done = subprocess.run(["log2asc", "-I", str(trace), "-O", str(converted), "can0"], capture_output=True,
                          text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    frames = [line for line in converted.read_text().splitlines() if " Rx " in line or " Tx " in line]
    assert len(frames) == len(trace.read_text().splitlines())
    replayed = tmp_path / "r.jsonl"
    replay_trace(load_scene(scene), converted, json_lines=replayed)
    assert replayed.read_bytes() == live.read_bytes()


def test_can_utils_asc2log_output_replays(traces, tmp_path):
    _can_utils("asc2log")
    scene, trace, live = traces["log"]
    asc = tmp_path / "t.asc"
    import can

    with can.Logger(str(asc)) as writer:  # the same frames in python-can's ASC
        for msg in can.LogReader(str(trace)):
            writer.on_message_received(msg)
    back = tmp_path / "back.log"
    done = subprocess.run(["asc2log", "-I", str(asc), "-O", str(back)], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    replayed = tmp_path / "r.jsonl"
    replay_trace(load_scene(scene), back, json_lines=replayed)
    assert replayed.read_bytes() == live.read_bytes()
