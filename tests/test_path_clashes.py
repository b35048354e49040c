"""An output that names an input or another output is refused in one line (exit 2) before
anything is written (stop 32, the reviewer's HUNT-A items 1 and 2): a failed ``replay`` deleted
its own trace or truth log given as ``--json-lines`` / ``--mcap`` (discarded as a stale output);
``demo --json-lines x.log --log x.log`` wrote both into one file with exit 0; an export, a DCF or a
node-sim truth log overwrote the decision log or the scene it read. A character device or FIFO
(``/dev/null``) may be named twice. :func:`taxel_net.outputs.check_distinct_paths`."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from fusion_center.commands.demo import run_demo
from taxel_net.errors import UsageError
from taxel_net.outputs import check_distinct_paths
from taxel_net.resources import bundled_scenes
from taxel_net.scene import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_inprocess import run_cli  # noqa: E402
from test_replay_checks import scene_text  # noqa: E402

ALLOWED = "only a character device or FIFO such as /dev/null may be named twice"


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A three-node scene, the trace and the decision log of a 12-cycle demo of it."""
    d = tmp_path_factory.mktemp("clashes")
    scene = d / "tiny3.toml"
    scene.write_text(scene_text("tiny3"))
    trace, log = d / "full.log", d / "full.jsonl"
    run_demo(load_scene(scene), 12, json_lines=log, trace=trace)
    return scene, trace, log


@pytest.fixture
def work(tmp_path, made):
    """Copies of the scene, trace and log in the test's own directory (they may get clobbered)."""
    scene, trace, log = made
    for source in (scene, trace, log):
        shutil.copy(source, tmp_path / source.name)
    return tmp_path


def refused(done, *words):
    """Exit 2, one line on stderr naming ``words`` (both options, the path) and what is allowed."""
    assert done.returncode == 2, (done.returncode, done.stdout, done.stderr)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    for word in (*words, ALLOWED):
        assert word in lines[0], (word, lines[0])
    return lines[0]


# -- item 1: a failed replay deleted its own input ------------------------------------------------

def test_failed_replay_keeps_its_trace_given_as_json_lines(capsys, work):
    """The trace is another scene's (check_trace fails): before, --json-lines TRACE was discarded
    as a stale output - the trace was gone."""
    c5 = work / "c5.log"
    shutil.copy(work / "full.log", c5)
    before = c5.read_bytes()
    done = run_cli(capsys, "replay", "--scene", "grasp_lift_patch", c5, "--json-lines", c5, cwd=work)
    assert c5.exists() and c5.read_bytes() == before
    refused(done, "--json-lines", "TRACE", repr(str(c5)))


def test_failed_replay_keeps_its_truth_log_given_as_mcap(capsys, work):
    """A grasp scene the trace is not of: before, the failed check discarded --mcap, the truth log."""
    t6 = work / "t6.jsonl"
    t6.write_bytes(b"")  # an empty truth log reads as no steps
    done = run_cli(capsys, "replay", "--scene", "grasp_lift_patch", "full.log", "--truth-log", t6, "--mcap", t6,
                   cwd=work)
    assert t6.exists() and t6.read_bytes() == b""
    refused(done, "--mcap", "--truth-log", repr(str(t6)))


# -- item 2: outputs over inputs or over each other -----------------------------------------------

def test_demo_json_lines_and_log_one_file(capsys, work):
    done = run_cli(capsys, "demo", "--scene", "tiny3.toml", "--cycles", "3", "--no-live", "--json-lines", "x.log",
                   "--log", "x.log", cwd=work)
    refused(done, "--json-lines", "--log", "'x.log'")
    assert not (work / "x.log").exists()


def test_demo_json_lines_and_mcap_one_file(capsys, work):
    done = run_cli(capsys, "demo", "--scene", "tiny3.toml", "--cycles", "3", "--no-live", "--json-lines", "y.mcap",
                   "--mcap", "./y.mcap", cwd=work)
    refused(done, "--json-lines", "--mcap", "y.mcap")
    assert not (work / "y.mcap").exists()


def test_demo_json_lines_over_its_scene(capsys, work):
    before = (work / "tiny3.toml").read_bytes()
    done = run_cli(capsys, "demo", "--scene", "tiny3.toml", "--cycles", "3", "--no-live", "--json-lines",
                   "tiny3.toml", cwd=work)
    refused(done, "--json-lines", "--scene", "tiny3.toml")
    assert (work / "tiny3.toml").read_bytes() == before


@pytest.mark.parametrize("option", ["--json-lines", "--mcap"])
def test_replay_output_over_its_trace(capsys, work, option):
    """A trace that matches the scene: before, the replay ran and replaced its trace (exit 0)."""
    before = (work / "full.log").read_bytes()
    done = run_cli(capsys, "replay", "--scene", "tiny3.toml", "full.log", option, "full.log", cwd=work)
    refused(done, option, "TRACE", "'full.log'")
    assert (work / "full.log").read_bytes() == before


def test_replay_output_over_its_trace_through_a_link(capsys, work):
    """Another spelling of the trace (a symbolic link) is the same file."""
    os.symlink("full.log", work / "alias.log")
    before = (work / "full.log").read_bytes()
    done = run_cli(capsys, "replay", "--scene", "tiny3.toml", "full.log", "--json-lines", "alias.log", cwd=work)
    refused(done, "--json-lines", "TRACE", "'alias.log'", "'full.log'")
    assert (work / "full.log").read_bytes() == before


def test_replay_json_lines_over_the_partial_of_mcap(capsys, work):
    """--mcap M is written as M.partial first: a trace at M.partial would be truncated."""
    shutil.copy(work / "full.log", work / "m.log.partial")
    before = (work / "m.log.partial").read_bytes()
    done = run_cli(capsys, "replay", "--scene", "tiny3.toml", "m.log.partial", "--mcap", "m.log", cwd=work)
    refused(done, "--mcap", "TRACE", "'m.log.partial'")
    assert (work / "m.log.partial").read_bytes() == before


def test_replay_json_lines_and_mcap_one_file(capsys, work):
    """Before: a FileNotFoundError in one line and a complete-looking output of one of them."""
    done = run_cli(capsys, "replay", "--scene", "tiny3.toml", "full.log", "--json-lines", "rs2.out",
                   "--mcap", "rs2.out", cwd=work)
    refused(done, "--json-lines", "--mcap", "'rs2.out'")
    assert not (work / "rs2.out").exists()


def test_export_mcap_over_its_decision_log(capsys, work):
    before = (work / "full.jsonl").read_bytes()
    done = run_cli(capsys, "export", "--scene", "tiny3.toml", "full.jsonl", "--mcap", "full.jsonl", cwd=work)
    refused(done, "--mcap", "RUN.jsonl", "'full.jsonl'")
    assert (work / "full.jsonl").read_bytes() == before


def test_dcf_over_its_scene(capsys, work):
    before = (work / "tiny3.toml").read_bytes()
    done = run_cli(capsys, "dcf", "--scene", "tiny3.toml", "--node", "4", "-o", "tiny3.toml", cwd=work)
    refused(done, "-o", "--scene", "tiny3.toml")
    assert (work / "tiny3.toml").read_bytes() == before


def test_plot_over_its_log_is_refused_by_the_shared_check(capsys, work):
    done = run_cli(capsys, "plot", "full.jsonl", "--out", str(work / "full.jsonl"), cwd=work)
    # the log is no .png: the format check may answer first; a .png log is the clash itself
    assert done.returncode == 2
    shutil.copy(work / "full.jsonl", work / "log.png")
    before = (work / "log.png").read_bytes()
    done = run_cli(capsys, "plot", "log.png", "--out", "log.png", cwd=work)
    refused(done, "--out", "RUN.jsonl", "'log.png'")
    assert (work / "log.png").read_bytes() == before


def test_node_sim_truth_log_over_its_scene(tmp_path):
    """Before: the truth log truncated the scene file and the twins ran (until SIGINT here)."""
    source = bundled_scenes()["grasp_lift"]
    scene = tmp_path / "self2.toml"
    shutil.copy(source, scene)
    shutil.copytree(source.parent / "data", tmp_path / "data")
    before = scene.read_bytes()
    cmd = [sys.executable, "-c", "import sys; from node_sim.cli import main; sys.exit(main())",
           "--scene", str(scene), "-i", "virtual", "--truth-log", str(scene)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = proc.stdout.readline()  # "node-sim: ready ..." (before the fix) or EOF at the error's exit
    if proc.poll() is None and first:
        proc.send_signal(signal.SIGINT)
    _, err = proc.communicate()
    assert proc.returncode == 2, (first, err)
    assert "--truth-log" in err and "--scene" in err and ALLOWED in err, err
    assert len(err.strip().splitlines()) == 1, err
    assert scene.read_bytes() == before


# -- what stays allowed ---------------------------------------------------------------------------

def test_dev_null_twice_is_accepted(capsys, work):
    done = run_cli(capsys, "replay", "--scene", "tiny3.toml", "full.log", "--json-lines", os.devnull,
                   "--mcap", os.devnull, cwd=work)
    assert done.returncode == 0, done.stderr
    check_distinct_paths([("--scene", "tiny3.toml")], [("--json-lines", os.devnull), ("--mcap", os.devnull)])


def test_fifo_twice_is_accepted_and_distinct_files_pass(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    check_distinct_paths([("TRACE", tmp_path / "a.log")], [("--json-lines", fifo), ("--mcap", fifo),
                                                          ("--log", tmp_path / "b.log"), ("-o", "-"),
                                                          ("--ros2-bag", None)])


def test_hard_link_is_the_same_file(tmp_path):
    (tmp_path / "a.log").write_text("x\n")
    os.link(tmp_path / "a.log", tmp_path / "b.log")
    with pytest.raises(UsageError, match="--json-lines .*b.log.*TRACE .*a.log"):
        check_distinct_paths([("TRACE", tmp_path / "a.log")], [("--json-lines", tmp_path / "b.log")])


def test_scene_taxels_file_is_an_input():
    """A bundled scene's name resolves to its file, and its taxels_file CSV is an input too."""
    from taxel_net.outputs import scene_inputs

    source = bundled_scenes()["grasp_lift"]
    with pytest.raises(UsageError, match="--json-lines .*: is an input, --scene's taxels_file"):
        check_distinct_paths(scene_inputs("grasp_lift"),
                             [("--json-lines", source.parent / "data" / "grasp_pads_2mm.csv")])


# -- a discarded stale output is never an input ---------------------------------------------------

def test_replay_discard_spares_its_inputs_without_the_clash_check(capsys, work, monkeypatch):
    """Item 1 with the clash check taken away: the failed check's discard of --json-lines must
    still not delete the trace (replay's own guard), nor the truth log given as --mcap."""
    import fusion_center.commands as commands

    monkeypatch.setattr(commands, "check_output_paths", lambda *a, **k: None, raising=False)
    c5 = work / "c5.log"
    shutil.copy(work / "full.log", c5)
    before = c5.read_bytes()
    done = run_cli(capsys, "replay", "--scene", "grasp_lift_patch", c5, "--json-lines", c5, cwd=work)
    assert done.returncode == 2 and "belong to no node" in done.stderr, done.stderr
    assert c5.exists() and c5.read_bytes() == before


def test_discard_stale_spares_the_commands_inputs(tmp_path):
    """Every caller of discard_stale (traces.replay_trace, the MCAP writer) spares what the
    command's check_distinct_paths named as an input."""
    from taxel_net.outputs import discard_stale

    trace, stale = tmp_path / "t.log", tmp_path / "old.jsonl"
    trace.write_text("x\n")
    stale.write_text("y\n")
    check_distinct_paths([("TRACE", trace)], [("--json-lines", stale)])
    assert discard_stale(trace) is False and trace.read_text() == "x\n"
    assert discard_stale(stale) is True and not stale.exists()


def test_an_input_named_twice_is_no_clash(tmp_path):
    """Reading one file under two options harms nothing (only outputs must be distinct)."""
    (tmp_path / "a.log").write_text("x\n")
    check_distinct_paths([("TRACE", tmp_path / "a.log"), ("--truth-log", tmp_path / "a.log")],
                         [("--json-lines", tmp_path / "None")])


def test_run_log_over_its_scene_before_the_bus(capsys, work):
    """``run`` checks its paths before it looks for a bus (no interface is given here)."""
    before = (work / "tiny3.toml").read_bytes()
    done = run_cli(capsys, "run", "--scene", "tiny3.toml", "--cycles", "2", "--no-live", "--log", "./tiny3.toml",
                   cwd=work)
    refused(done, "--log", "--scene", "tiny3.toml")
    assert (work / "tiny3.toml").read_bytes() == before
