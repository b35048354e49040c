"""A trace loses at most the cycle in flight, in every format the centre writes: the writer hands
every frame to the OS at each cycle's close (fusion_center/service/trace_writers.py)."""

import sys
from pathlib import Path

import can
import pytest

from fusion_center.commands.demo import run_demo
from fusion_center.service.cycles import CycleAssembler
from fusion_center.service.stream import EventStream
from fusion_center.service.traces import open_trace_writer
from taxel_net.errors import UsageError
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
MATRIX = ROOT / "scenes" / "matrix57.toml"
CLI = [sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())"]
# every format the centre writes here (.mf4 needs asammdf: refused without it, and asammdf writes
# the whole file at the end - see trace_writers)
FORMATS = (".log", ".asc", ".blf", ".trc", ".csv", ".db")
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
    a .blf held none of them until its 128 KiB container filled (tens of cycles) and a .db only
    what python-can's writer thread had inserted (500 frames or 0.25 s of quiet at a time)."""
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


def test_a_second_db_trace_replaces_the_first(matrix, frames, tmp_path):
    """``--log x.db`` twice: the second trace is that run's alone (python-can's SqliteWriter
    appended to the table of the first: replay re-fused both runs as one)."""
    path = tmp_path / "t.db"
    write_through_stream(matrix, frames, path).close_trace()
    write_through_stream(matrix, frames[:500], path).close_trace()
    assert len(read_on_disk(path)) == 500


def test_db_trace_of_a_file_that_is_no_database_is_one_line(tmp_path):
    path = tmp_path / "t.db"
    path.write_bytes(b"no database " * 100)
    with pytest.raises(UsageError) as info:
        open_trace_writer(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)
