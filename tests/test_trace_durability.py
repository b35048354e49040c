"""A trace loses at most the cycle in flight, in every format the centre writes, and replay reads
what a killed run left: the writer hands every frame to the OS at each cycle's close
(fusion_center/service/trace_writers.py); a trace its writer never closed (a BLF with its opening
header, an ASC without its End TriggerBlock) is read up to its last complete container or line,
with a warning; one cut after its writer closed it is refused."""

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest

from cli_inprocess import run_cli
from fusion_center.commands.demo import run_demo
from fusion_center.service import replay_trace
from fusion_center.service.cycles import CycleAssembler
from fusion_center.service.stream import EventStream
from fusion_center.service.traces import open_trace_writer
from taxel_net.errors import UsageError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
MATRIX = ROOT / "scenes" / "matrix57.toml"
CLI = [sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())"]
# every format the centre writes (--log refuses .trc, .csv, .db and .mf4: traces.REFUSED_TRACE_SUFFIXES)
FORMATS = (".log", ".asc", ".blf")
SYNC = 0x080


def is_sync(msg: can.Message) -> bool:
    return msg.arbitration_id == SYNC and not msg.is_extended_id and not msg.is_error_frame


def read_on_disk(path: Path) -> list[can.Message]:
    """The frames python-can reads from the file as it is on disk now (its writer still open)."""
    reader = can.LogReader(str(path))
    try:
        return list(reader)
    finally:
        reader.stop()


@pytest.fixture(scope="module")
def matrix():
    return load_scene(MATRIX)


@pytest.fixture(scope="module")
def frames(matrix, tmp_path_factory):
    """The frames of a 40-cycle demo (a node dropped: degraded cycles too), and their channels."""
    trace = tmp_path_factory.mktemp("src") / "src.log"
    run_demo(matrix, 40, drops={8: [30]}, trace=trace)
    return [(msg, 0) for msg in can.LogReader(str(trace))]


def write_through_stream(matrix, frames, path, on_cycle=None):
    """Feed ``frames`` through the live path (EventStream with the writer of open_trace_writer:
    queued, written and flushed at each cycle's close as in a run); after each frame that closed
    a cycle, ``on_cycle(frames_fed, cycles_closed)`` - before the writer is stopped."""
    writer = open_trace_writer(path)
    closed = []
    stream = EventStream(CycleAssembler(matrix), trace=writer, on_closed=closed.append)
    for fed, (msg, channel) in enumerate(frames, 1):
        before = len(closed)
        stream.receive(can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id, data=msg.data,
                                   is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                                   is_rx=msg.is_rx, dlc=msg.dlc), channel)
        if len(closed) > before and on_cycle is not None:
            on_cycle(fed, len(closed))
    return stream


@pytest.mark.parametrize("suffix", FORMATS)
def test_every_closed_cycle_is_on_disk_before_the_writer_stops(matrix, frames, tmp_path, suffix):
    """After each cycle's close the file on disk (read by a second reader, the writer still open:
    what a SIGKILL leaves) holds every frame fed so far - the cycle that closed included. Before,
    a .blf held none of them until its 128 KiB container filled (tens of cycles)."""
    path = tmp_path / f"t{suffix}"
    checked = []

    def on_cycle(fed, cycles):
        on_disk = read_on_disk(path)
        assert len(on_disk) == fed, (cycles, len(on_disk), fed)
        assert [m.arbitration_id for m in on_disk] == [m.arbitration_id for m, _ in frames[:fed]]
        assert [bytes(m.data) for m in on_disk] == [bytes(m.data) for m, _ in frames[:fed]]
        checked.append(cycles)

    stream = write_through_stream(matrix, frames, path, on_cycle)
    stream.close_trace()
    assert len(checked) >= 35 and stream.trace_errors == 0
    assert len(read_on_disk(path)) == len(frames)


def test_blf_containers_end_at_cycle_closes(matrix, frames, tmp_path):
    """The .blf trace is one LOG_CONTAINER a closed cycle (a cycle of matrix57 is far from
    python-can's max_container_size), each a zlib stream python-can and Wireshark read one after
    the other."""
    from can.io.blf import LOG_CONTAINER, OBJ_HEADER_BASE_STRUCT

    path = tmp_path / "t.blf"
    ends = []
    stream = write_through_stream(matrix, frames, path, lambda fed, cycles: ends.append(path.stat().st_size))
    data = path.read_bytes()
    pos, objects = 144, []
    while pos < len(data):
        signature, _, _, size, kind = OBJ_HEADER_BASE_STRUCT.unpack_from(data, pos)
        assert signature == b"LOBJ" and kind == LOG_CONTAINER
        pos += size + size % 4
        objects.append(pos)
    # from the first cycle's close on, a container ends where each cycle's flush ended, and
    # nowhere else (before it, the boot's 2,500 SDO frames filled python-can's 128 KiB container)
    assert len(ends) >= 35 and [end for end in objects if end >= ends[0]] == ends
    stream.close_trace()


@pytest.mark.parametrize("suffix", [".trc", ".csv", ".db", ".mf4"])
def test_formats_that_lose_frames_or_a_killed_run_are_refused(tmp_path, suffix):
    """python-can's .db writer inserted from a thread of its own (a SIGKILL lost 3-6 cycles) and
    appended to an earlier run's table; asammdf writes a .mf4 whole at the end; .trc/.csv/.db
    lose frames (test_replay_checks): --log refuses them all in one line, writing nothing."""
    path = tmp_path / f"t{suffix}"
    with pytest.raises(UsageError) as info:
        open_trace_writer(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value) and "can.logconvert" in str(info.value)
    assert not path.exists()


# --------------------------------------------------------------------------- a killed run's trace
def unclosed_copy(matrix, frames, tmp_path, suffix):
    """A trace as a SIGKILL leaves it (copied before the writer stops), and the file size and
    frames fed at each cycle's close."""
    path = tmp_path / f"live{suffix}"
    bounds = []
    stream = write_through_stream(matrix, frames, path, lambda fed, cycles: bounds.append((path.stat().st_size, fed)))
    killed = tmp_path / f"killed{suffix}"
    shutil.copyfile(path, killed)
    stream.close_trace()
    return path, killed, bounds


@pytest.mark.parametrize("suffix", [".blf", ".asc"])
def test_unclosed_trace_replays_to_its_last_complete_unit_with_a_warning(matrix, frames, tmp_path, suffix, caplog):
    """A trace its writer never closed replays like the closed one up to where it ends, and says
    so; cut inside a cycle's container (BLF) or line (ASC), it gives the frames of every complete
    one before the cut - never a frame of the torn one."""
    closed, killed, bounds = unclosed_copy(matrix, frames, tmp_path, suffix)
    full, _ = replay_trace(matrix, closed)
    with caplog.at_level(logging.WARNING, logger="fusion_center.service"):
        records, _ = replay_trace(matrix, killed)
    assert records == full[:len(records)] and len(records) >= len(full) - 1
    notes = [r.getMessage() for r in caplog.records if "never closed by its writer" in r.getMessage()]
    assert len(notes) == 1 and str(killed) in notes[0]
    data = killed.read_bytes()
    for (end, fed), (next_end, next_fed) in list(zip(bounds, bounds[1:]))[::5]:
        for cut in (end, end + 1, (end + next_end) // 2, next_end - 1):
            torn = tmp_path / f"torn{suffix}"
            torn.write_bytes(data[:cut])
            got = replay_reads(torn)
            assert [m.arbitration_id for m in got] == [m.arbitration_id for m, _ in frames[:len(got)]]
            assert [bytes(m.data) for m in got] == [bytes(m.data) for m, _ in frames[:len(got)]]
            if suffix == ".blf":  # whole containers only: a cycle's frames, all or none
                assert len(got) == fed, (cut, end, next_end, len(got), fed)
            else:  # whole lines only
                assert fed <= len(got) < next_fed, (cut, end, next_end, len(got), fed)


def replay_reads(path) -> list[can.Message]:
    """The frames replay's reader takes from ``path``."""
    from fusion_center.service.traces import _open_reader, _stop

    reader = _open_reader(path, notify=False)
    try:
        return list(reader)
    finally:
        _stop(reader)


def test_blf_cut_after_its_writer_closed_it_is_refused(matrix, frames, tmp_path):
    closed, _, _ = unclosed_copy(matrix, frames, tmp_path, ".blf")
    cut = tmp_path / "cut.blf"
    cut.write_bytes(closed.read_bytes()[:closed.stat().st_size * 2 // 3])
    with pytest.raises(UsageError) as info:
        replay_trace(matrix, cut)
    assert "truncated or altered" in str(info.value) and str(cut) in str(info.value)


@pytest.mark.parametrize("suffix", FORMATS)
def test_sigkill_leaves_every_recorded_cycle_in_the_trace(tmp_path, capsys, suffix):
    """`fusion-center demo --log` killed by SIGKILL after N records: the trace read back (python-
    can's reader, then `fusion-center replay`) holds every cycle up to at least N - 1, and replay
    gives the live records. Before: .blf lost 17-33 cycles."""
    log, trace = tmp_path / "live.jsonl", tmp_path / f"t{suffix}"
    proc = subprocess.Popen(CLI + ["demo", "--cycles", "5000", "--no-live", "--json-lines", str(log), "--log", str(trace)],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if log.exists() and log.read_bytes().count(b"\n") >= 60:
                break
            if proc.poll() is not None:
                pytest.fail(f"demo exited early: {proc.stderr.read().decode()[-2000:]}")
            time.sleep(0.02)
        else:
            pytest.fail("demo wrote no 60 records in 120 s")
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
        proc.stderr.close()
    live = log.read_text().splitlines()
    n = len(live)
    assert n >= 60
    syncs = sum(map(is_sync, read_on_disk(trace)))
    assert syncs >= n - 1, (syncs, n)
    out = tmp_path / "replayed.jsonl"
    # the replay of what the killed process left: in this process (tests/cli_inprocess.py), its
    # warnings on stderr as the command's; an exception escaping it fails the test
    done = run_cli(capsys, "replay", "--scene", MATRIX, trace, "--json-lines", out)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    replayed = out.read_text().splitlines()
    assert len(replayed) >= n - 1, (len(replayed), n)
    assert replayed == live[:len(replayed)]
    assert json.loads(replayed[-1])["cycle"] == len(replayed) - 1
    warned = [line for line in done.stderr.splitlines() if "never closed by its writer" in line]
    assert len(warned) == (1 if suffix in (".blf", ".asc") else 0), done.stderr


def test_log_cut_mid_line_replays_to_its_last_complete_line_with_a_warning(matrix, frames, tmp_path, caplog):
    """A candump .log has no end marker: a run killed while a line was half written leaves a last
    line without its newline. Before, replay refused the trace ('not enough values to unpack') or,
    cut inside the data, read a different frame (``639#230`` of ``639#2300...``: a bad DLC); now it
    reads every complete line, says so in one warning, and never a frame of the torn line."""
    closed, killed, bounds = unclosed_copy(matrix, frames, tmp_path, ".log")
    data = killed.read_bytes()
    assert data.endswith(b"\n")  # handed to the OS at each cycle's close: whole lines
    full, _ = replay_trace(matrix, closed)
    for (end, fed), (next_end, next_fed) in list(zip(bounds, bounds[1:]))[::5]:
        for cut in (end + 1, (end + next_end) // 2, next_end - 1):
            torn = tmp_path / "torn.log"
            torn.write_bytes(data[:cut])
            if data[cut - 1:cut] == b"\n":
                continue
            got = replay_reads(torn)
            assert [m.arbitration_id for m in got] == [m.arbitration_id for m, _ in frames[:len(got)]]
            assert [bytes(m.data) for m in got] == [bytes(m.data) for m, _ in frames[:len(got)]]
            assert fed <= len(got) < next_fed, (cut, end, next_end, len(got), fed)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="fusion_center.service"):
        records, _ = replay_trace(matrix, torn)
    assert records == full[:len(records)]
    notes = [r.getMessage() for r in caplog.records if "no newline at its end" in r.getMessage()]
    assert len(notes) == 1 and str(torn) in notes[0]
