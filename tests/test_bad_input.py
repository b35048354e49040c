"""Bad input never gets a traceback or a hang (issue 10): every CLI value checked against its
range, scene/EDS/trace files of any content exit 2 with one line naming the file, and a
truncated or corrupted trace leaves no complete-looking decision log."""

from pathlib import Path

import can
import pytest

from cli_inprocess import run_cli
from fusion_center.cli import main
from fusion_center.service import FusionService
from taxel_net.errors import UsageError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
MATRIX = ROOT / "scenes" / "matrix57.toml"


@pytest.fixture
def cli(capsys):
    """``fusion-center ARGS`` in this process (tests/cli_inprocess.py): these tests are about what
    the command makes of its input - its exit status, its one-line error, the files it leaves -
    and an exception escaping it (a traceback in a subprocess) fails the test."""
    return lambda *args: run_cli(capsys, *args)


def assert_one_line_exit_2(done, *needles):
    assert done.returncode == 2, (done.returncode, done.stderr[-2000:])
    assert "Traceback" not in done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, done.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


def scene_text():
    return MATRIX.read_text().replace('taxels_file = "data/matrix57_taxels.csv"',
                                      f'taxels_file = "{ROOT / "scenes" / "data" / "matrix57_taxels.csv"}"')


@pytest.mark.parametrize("content, needle", [
    (bytes(range(256)) * 4, "not a UTF-8 text file"),
    ('[scene]\nname = "caf\u00e9"\n'.encode("latin-1"), "byte 0xE9"),
])
def test_scene_of_any_content(cli, tmp_path, content, needle):
    p = tmp_path / "s.toml"
    p.write_bytes(content)
    assert_one_line_exit_2(cli("run", "--scene", p), str(p), needle)


@pytest.mark.parametrize("old, new, needle", [
    ("cycles = 200", "cycles = 1000000000000", "scene.cycles"),
    ("sync_period_ms = 10.0", "sync_period_ms = 1e-9", "bus.sync_period_ms"),
])
def test_scene_values_out_of_range(cli, tmp_path, old, new, needle):
    p = tmp_path / "s.toml"
    p.write_text(scene_text().replace(old, new))
    assert_one_line_exit_2(cli("demo", "--scene", p), needle)


@pytest.mark.parametrize("args, needle", [
    (["--cycles", "1000000000000"], "--cycles"),
    (["--cycles", "0"], "--cycles"),
    (["--boot-timeout", "nan"], "--boot-timeout nan"),
    (["--boot-timeout", "-1"], "--boot-timeout -1"),
    (["--boot-timeout", "inf"], "--boot-timeout inf"),
    (["--bitrate", "-1"], "--bitrate -1"),
    (["--rt-priority", "0"], "--rt-priority: 0: out of range (allowed: 1-99"),
    (["--rt-priority", "100"], "--rt-priority: 100: out of range (allowed: 1-99"),
])
def test_cli_values_out_of_range(cli, args, needle):
    assert_one_line_exit_2(cli("run", "--scene", MATRIX, *args), needle)


def test_broken_eds(tmp_path):
    scene = load_scene(MATRIX)
    eds = (ROOT / "eds" / "taxel_node.eds").read_text().splitlines(keepends=True)
    cut = tmp_path / "cut.eds"
    cut.write_text("".join(eds[:eds.index("[2001]\n")]))  # ends before the detector object
    torn = tmp_path / "torn.eds"
    torn.write_text("".join(eds)[:3000])  # mid-line
    binary = tmp_path / "bin.eds"
    binary.write_bytes(bytes(range(256)))
    for path, needle in ((cut, "0x2001:1 is missing"), (torn, "has no ParameterName"), (binary, "not a text file")):
        with pytest.raises(UsageError) as info:
            with FusionService(scene, channels=["eds-test"], eds_path=path):
                pass
        message = str(info.value)
        assert str(path) in message and needle in message and "\n" not in message


@pytest.fixture(scope="module")
def traces(tmp_path_factory):
    """One demo trace in .log, converted to .asc and .blf (python-can's writers)."""
    d = tmp_path_factory.mktemp("traces")
    log = d / "t.log"
    assert main(["demo", "--cycles", "20", "--no-live", "--log", str(log)]) == 0
    for suffix in (".asc", ".blf"):
        with can.Logger(str(d / f"t{suffix}")) as writer:
            for msg in can.LogReader(str(log)):
                writer.on_message_received(msg)
    return d


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_complete_trace_replays(cli, traces, tmp_path, suffix):
    out = tmp_path / "o.jsonl"
    done = cli("replay", "--scene", MATRIX, traces / f"t{suffix}", "--json-lines", out)
    assert done.returncode == 0, done.stderr
    assert out.read_text().count("\n") >= 15 and not (tmp_path / "o.jsonl.partial").exists()


# an .asc cut (no End TriggerBlock), a .log cut in a line or a .blf its writer never closed is read
# up to its last complete line or container, with a warning: tests/test_trace_durability.py
@pytest.mark.parametrize("suffix, cut, needle", [
    (".blf", 0.6, "truncated or altered after its writer closed it"),
    (".log", 0.6, "unreadable after frame"),
    (".blf", None, "cannot be read"),
])
def test_truncated_or_corrupted_trace_leaves_no_complete_looking_log(cli, traces, tmp_path, suffix, cut, needle):
    src = (traces / f"t{suffix}").read_bytes()
    bad = tmp_path / f"bad{suffix}"
    if cut is None:
        bad.write_bytes(bytes((7 * k + 3) % 256 for k in range(4096)))
    else:
        data = src[:int(len(src) * cut)]
        if suffix == ".log":  # a broken line inside the trace (cut short at its end: read up to it)
            data = data[:data.rfind(b"\n") + 1]
            data += b"(1.0) can0 18\n" + src[len(data):]
        bad.write_bytes(data)
    out = tmp_path / "o.jsonl"
    out.write_text('{"an earlier": "log"}\n')
    assert_one_line_exit_2(cli("replay", "--scene", MATRIX, bad, "--json-lines", out), str(bad), needle)
    assert not out.exists()
