"""Output paths that are not regular files are written in place, never renamed over nor
deleted (issue 21, item 2): ``replay --json-lines /dev/null`` as root turned the device into a
regular file, and a failed replay deleted it. Tested with a FIFO, a character device made with
``mknod`` (root only: skipped otherwise), a link to a FIFO (as ``/dev/stdout`` is to a pipe),
a link to a regular file, and a directory."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from fusion_center.commands.demo import run_demo
from fusion_center.service import replay_trace
from taxel_net.errors import UsageError
from taxel_net.outputs import OutputPath, discard_stale
from taxel_net.scene import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_replay_checks import scene_text  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())"]
TINY = scene_text("tiny3")  # three nodes: a short demo


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A short demo: (scene path, its trace, its live decision log, the trace with a broken line
    after ~10 cycles - replay fails there; a trace merely cut in a line is read up to its last
    complete line, tests/test_trace_durability.py)."""
    d = tmp_path_factory.mktemp("outputs")
    scene = d / "tiny3.toml"
    scene.write_text(TINY)
    trace, live = d / "run.log", d / "live.jsonl"
    run_demo(load_scene(scene), 20, json_lines=live, trace=trace)
    text = trace.read_bytes()
    cut = d / "cut.log"
    head = text[: int(len(text) * 0.6)]
    head = head[: head.rfind(b"\n") + 1]
    cut.write_bytes(head + b"(12\n" + text[len(head):])  # a broken line after ~10 cycles
    return scene, trace, live, cut


def cli(*args):
    return subprocess.run(CLI + [str(a) for a in args], cwd=ROOT, capture_output=True, text=True, timeout=120)


class FifoReader:
    """Reads a FIFO to its end in a thread (what a user's ``cat FIFO`` does)."""

    def __init__(self, path: Path):
        self.path, self.data = path, b""
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        with open(self.path, "rb") as f:
            self.data = f.read()

    def result(self) -> bytes:
        """What was read, once the writer (a finished command) is gone."""
        self.thread.join(5)
        if self.thread.is_alive():  # the writer never opened it: unblock the reader
            os.close(os.open(self.path, os.O_WRONLY | os.O_NONBLOCK))
            self.thread.join(5)
        return self.data


def null_device(path: Path) -> Path:
    try:
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))  # a throw-away /dev/null
    except PermissionError:
        pytest.skip("mknod needs root (CAP_MKNOD): the character-device case runs as root only")
    return path


def assert_still_null_device(path: Path):
    st = os.lstat(path)
    assert stat.S_ISCHR(st.st_mode) and st.st_rdev == os.makedev(1, 3), oct(st.st_mode)


def test_replay_into_a_character_device_leaves_the_device(run, tmp_path):
    scene, trace, _, cut = run
    dev = null_device(tmp_path / "null")
    done = cli("replay", "--scene", scene, trace, "--json-lines", dev)
    assert done.returncode == 0, done.stderr
    assert_still_null_device(dev)
    assert os.listdir(tmp_path) == ["null"]  # no .partial beside it
    for bad in (cut, tmp_path / "absent.log"):  # a failed replay: after some records, and before any
        done = cli("replay", "--scene", scene, bad, "--json-lines", dev)
        assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
        assert_still_null_device(dev)
    done = cli("replay", "--scene", scene, "--mode", "raw", trace, "--json-lines", dev)
    assert done.returncode == 2 and "--force" in done.stderr  # refused by the trace checks, before the replay
    assert_still_null_device(dev)


def test_replay_into_a_fifo_streams_the_records_and_leaves_the_fifo(run, tmp_path):
    scene, trace, live, cut = run
    fifo = tmp_path / "records"
    os.mkfifo(fifo)
    reader = FifoReader(fifo)
    done = cli("replay", "--scene", scene, trace, "--json-lines", fifo)
    assert done.returncode == 0, done.stderr
    assert reader.result() == live.read_bytes()
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and os.listdir(tmp_path) == ["records"]
    reader = FifoReader(fifo)  # a failed replay (the cut is found before any record): the FIFO stays
    done = cli("replay", "--scene", scene, cut, "--json-lines", fifo)
    assert done.returncode == 2 and str(cut) in done.stderr
    assert live.read_bytes().startswith(reader.result())
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and os.listdir(tmp_path) == ["records"]


def test_a_link_to_a_fifo_stays_a_link(run, tmp_path):
    """As ``--json-lines /dev/stdout`` (a link to the terminal or a pipe)."""
    scene, trace, live, _ = run
    fifo, link = tmp_path / "pipe", tmp_path / "stdout"
    os.mkfifo(fifo)
    link.symlink_to(fifo)
    reader = FifoReader(fifo)
    records, _ = replay_trace(load_scene(scene), trace, json_lines=link)
    assert reader.result() == live.read_bytes() and len(records) == 20
    assert link.is_symlink() and os.readlink(link) == str(fifo) and stat.S_ISFIFO(os.lstat(fifo).st_mode)


def test_a_link_to_a_regular_file_stays_a_link_and_its_target_is_the_output(run, tmp_path):
    scene, trace, live, cut = run
    target, link = tmp_path / "run42.jsonl", tmp_path / "latest.jsonl"
    target.write_text("old\n")
    link.symlink_to(target)
    replay_trace(load_scene(scene), trace, json_lines=link)
    assert link.is_symlink() and target.read_bytes() == live.read_bytes()
    assert sorted(os.listdir(tmp_path)) == ["latest.jsonl", "run42.jsonl"]
    with pytest.raises(UsageError, match="unreadable"):
        replay_trace(load_scene(scene), cut, json_lines=link)
    # a failed replay: the earlier log must not pass for this one's; the link is kept
    assert link.is_symlink() and not target.exists() and (tmp_path / "run42.jsonl.partial").exists()


def test_a_regular_file_is_still_replaced_whole_or_removed(run, tmp_path):
    scene, trace, live, cut = run
    out = tmp_path / "out.jsonl"
    out.write_text("earlier\n")
    replay_trace(load_scene(scene), trace, json_lines=out)
    assert out.read_bytes() == live.read_bytes() and not (tmp_path / "out.jsonl.partial").exists()
    with pytest.raises(UsageError):
        replay_trace(load_scene(scene), cut, json_lines=out)
    assert not out.exists() and (tmp_path / "out.jsonl.partial").exists()


def test_a_directory_is_refused_in_one_line(run, tmp_path):
    scene, trace, _, _ = run
    done = cli("replay", "--scene", scene, trace, "--json-lines", tmp_path)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "is a directory" in done.stderr, done.stderr
    assert tmp_path.is_dir() and os.listdir(tmp_path) == []


def test_plot_into_a_fifo_writes_the_png_in_place(run, tmp_path):
    _, _, live, _ = run
    fifo = tmp_path / "figure.png"
    os.mkfifo(fifo)
    reader = FifoReader(fifo)
    done = cli("plot", live, "--out", fifo)
    assert done.returncode == 0, done.stderr
    assert reader.result().startswith(b"\x89PNG\r\n\x1a\n")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and os.listdir(tmp_path) == ["figure.png"]


def test_output_path_and_discard_stale_by_file_type(tmp_path):
    fifo = tmp_path / "f"
    os.mkfifo(fifo)
    assert OutputPath(fifo).in_place and OutputPath(fifo).write_path == fifo
    assert not discard_stale(fifo) and fifo.exists()
    regular = tmp_path / "r"
    regular.write_text("x")
    out = OutputPath(regular)
    assert not out.in_place and out.write_path == tmp_path / "r.partial"
    assert discard_stale(regular) and not regular.exists()
    new = OutputPath(tmp_path / "new")
    assert not new.in_place and new.write_path == tmp_path / "new.partial"
    assert not discard_stale(tmp_path / "new")
    with pytest.raises(UsageError, match=r"--json-lines .*is a directory"):
        OutputPath(tmp_path, option="--json-lines")


def unremovable_file() -> Path:
    """A file ``stat`` calls regular that not even root can remove, open for writing or create a
    sibling of: ``/proc/version``."""
    path = Path("/proc/version")
    if not (path.exists() and stat.S_ISREG(os.stat(path).st_mode)):
        pytest.skip("no /proc/version on this system (Linux has it): the unremovable-file case needs it")
    return path


def test_a_file_that_cannot_be_removed_is_left_with_a_warning_never_a_traceback(tmp_path, caplog):
    version = unremovable_file()
    before = version.read_bytes()
    assert not discard_stale(version)
    assert version.read_bytes() == before
    assert "could not be removed" in caplog.text and "/proc/version" in caplog.text


def test_mcap_onto_a_file_that_cannot_be_removed_fails_in_one_line(tmp_path):
    version = unremovable_file()
    scene = tmp_path / "tiny3.toml"
    scene.write_text(TINY)
    done = cli("demo", "--scene", scene, "--cycles", 3, "--no-live", "--mcap", version)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    errors = [line for line in done.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and "--mcap '/proc/version': cannot be written" in errors[0], done.stderr


def full_device() -> Path:
    """``/dev/full``: every write fails with ENOSPC (a full disk without filling one)."""
    path = Path("/dev/full")
    if not path.exists():
        pytest.skip("no /dev/full on this system (Linux has it): the full-disk case needs it")
    return path


def test_a_full_disk_under_the_decision_log_neither_stops_the_run_nor_passes_for_complete(run, capsys):
    """Before: the run went on with a warning per write and ended in a traceback at close (exit 1,
    no summary, nothing said of what the log lacks); replay blamed the trace ("unreadable after
    frame 3253") and then crashed. Now the run goes on (the log's end said once), prints its
    summary with the failure in it, then one line naming the option, the file, the error and the
    records missing, exit 2; replay stops there with the same line, not the trace's."""
    from fusion_center.cli import main

    scene, trace, _, _ = run
    full = full_device()
    line = ("--json-lines '/dev/full': OSError: [Errno 28] No space left on device at cycle 0: the file ends "
            "there, {} records not written; 0 records written (the decision log is incomplete)")
    assert main(["demo", "--scene", str(scene), "--cycles", "12", "--json-lines", str(full)]) == 2
    out, err = capsys.readouterr()
    assert err.strip().splitlines()[-1] == "fusion-center demo: error: " + line.format(12), err
    assert "decision_log:" in out and "INCOMPLETE: " + line.format(12) in out and "latency_ms:" in out
    assert main(["replay", "--scene", str(scene), str(trace), "--json-lines", str(full)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["fusion-center replay: error: " + line.format(1) + "; the replay stopped there"], err


def test_a_write_cut_by_a_full_file_leaves_the_log_readable_up_to_its_last_whole_line(tmp_path):
    """A real full disk (here a file-size limit, SIGXFSZ ignored: write() then stores a part of the
    line and fails with EFBIG) left a cut last line, which the log's readers refuse (the whole
    log unreadable); the writer cuts it off again, the file ends with its last whole line."""
    import resource
    import signal

    from fusion_center.service.records import RecordWriter, read_records

    path = tmp_path / "log.jsonl"
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    try:
        with RecordWriter(path) as writer:
            resource.setrlimit(resource.RLIMIT_FSIZE, (100, hard))
            written = [writer.write({"cycle": k, "t": k * 0.01, "pad": "x" * 20}) for k in range(6)]
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old_handler)
    assert written == [True, True, False, False, False, False]
    assert [r["cycle"] for r in read_records(path)] == [0, 1] and path.read_bytes().endswith(b"}\n")
    assert writer.io_error[0] == 2 and "File too large" in writer.failure and "4 records not written" in writer.failure


def test_a_record_that_cannot_be_encoded_is_left_out_and_counted_and_a_later_end_said_too(tmp_path):
    from fusion_center.service.records import RecordWriter, read_records

    path = tmp_path / "log.jsonl"
    with RecordWriter(path) as writer:
        assert writer.write({"cycle": 0, "t": 0.0})
        assert not writer.write({"cycle": 1, "t": float("nan")})     # the pipeline writes null, never NaN
        assert writer.write({"cycle": 2, "t": 0.02})
    assert [r["cycle"] for r in read_records(path)] == [0, 2]
    assert (writer.count, writer.not_encoded, writer.io_failed) == (2, 1, False)
    assert writer.failure == (f"--json-lines {str(path)!r}: 1 records left out, not encodable (the first at cycle 1: "
                              "ValueError: Out of range float values are not JSON compliant); 2 records written "
                              "(the decision log is incomplete)")
    with RecordWriter(tmp_path / "fine.jsonl") as fine:
        fine.write({"cycle": 0})
    assert fine.failure is None
    with RecordWriter(full_device()) as both:
        assert not both.write({"cycle": 0, "t": float("inf")}) and not both.write({"cycle": 1})
    assert "at cycle 1: the file ends there" in both.failure and "the first at cycle 0" in both.failure


@pytest.mark.parametrize("suffix", [".log", ".blf"])
def test_a_full_disk_under_the_trace_ends_it_says_so_and_replay_reads_what_it_holds(run, tmp_path, suffix):
    """Before: a trace on a full disk (here a file-size limit of 8 KiB, SIGXFSZ ignored: writes
    fail with EFBIG, as ENOSPC on a full disk) gave a warning, a traceback from the trace's close,
    and exit 0 with a summary that did not mention it. Now: the trace ends at the failure (logged
    once; not stopped, so it stays an unclosed trace, not a complete-looking one), the summary
    says `trace: INCOMPLETE`, one error line names --log, exit 2; replay reads the trace up to its
    last whole frame."""
    import resource
    import signal

    scene = run[0]
    trace = tmp_path / f"cut{suffix}"

    def limited():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (8192, resource.RLIM_INFINITY))

    done = subprocess.run(CLI + ["demo", "--scene", str(scene), "--cycles", "120", "--no-live", "--log", str(trace)],
                          cwd=ROOT, capture_output=True, text=True, timeout=120, preexec_fn=limited)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    errors = [line for line in done.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and errors[0].startswith(f"fusion-center demo: error: --log {str(trace)!r}: OSError: "
                                                     "[Errno 27] File too large: the trace ends there, the file "
                                                     "holds at most the "), errors
    assert errors[0].endswith("frames not traced (the trace is incomplete)")
    import re

    import can

    at_most = int(re.search(r"at most the (\d+) frames", errors[0]).group(1))
    held = 0
    try:
        for _ in can.LogReader(str(trace)):
            held += 1
    except Exception:  # noqa: BLE001 - the cut last line / container: what came before it counts
        pass
    assert 0 < held <= at_most, (held, at_most)
    assert "trace:                     INCOMPLETE: --log" in done.stdout and "latency_ms:" in done.stdout
    assert trace.stat().st_size <= 8192
    again = cli("replay", "--scene", scene, trace)
    assert again.returncode == 0 and "read up to its last complete" in again.stderr, again.stderr
