"""CAN traces: the writer of a live run (``can.Logger``, format by extension), the channel of
a frame read back, and the offline replay that re-fuses a trace through the live classes
(:class:`~fusion_center.service.stream.EventStream` -> :class:`CyclePipeline`), so it
reproduces the live records exactly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import can

from taxel_net.errors import UsageError
from taxel_net.scene import Scene
from .cycles import ClosedCycle, CycleAssembler
from .pipeline import CyclePipeline
from .records import RecordWriter
from .stream import EventStream

TRACE_SUFFIXES = (".log", ".asc", ".blf", ".csv", ".trc", ".mf4", ".txt", ".db")


def open_trace_writer(path) -> can.Listener:
    """``can.Logger(path)``: the format follows the extension (.log candump, .asc, .blf, .csv...)."""
    p = Path(path)
    if p.suffix.lower() not in TRACE_SUFFIXES:
        raise UsageError(f"--log {str(path)!r}: unknown trace format {p.suffix!r} "
                         f"(python-can writes {', '.join(TRACE_SUFFIXES)})")
    try:
        return can.Logger(str(p))
    except (OSError, ValueError) as exc:
        raise UsageError(f"--log {str(path)!r}: cannot be written: {exc}") from None


def trace_channel(msg: can.Message) -> int:
    """Scene channel index of a frame read back from a trace (see ``EventStream``)."""
    from can.util import channel2int

    channel = channel2int(msg.channel)
    return 0 if channel is None else channel


def replay_trace(scene: Scene, trace_path, *, json_lines=None, truth: bool = True,
                 on_record: Callable[[dict], None] | None = None) -> tuple[list[dict], dict[str, int]]:
    """Re-fuse a recorded trace offline: the same stream -> the same records as live.

    Returns (records, counters). The open cycle at the end of the trace is not reported
    (live runs end theirs with an NMT broadcast, which is in the trace).
    """
    p = Path(trace_path)
    if not p.is_file():
        raise UsageError(f"trace {str(trace_path)!r} not found")
    try:
        reader = can.LogReader(str(p))
    except Exception as exc:  # noqa: BLE001
        raise UsageError(f"trace {str(trace_path)!r} cannot be read: {exc}") from None
    assembler = CycleAssembler(scene)
    pipeline = CyclePipeline(scene, truth=truth)
    closed_cycles: list[ClosedCycle] = []
    stream = EventStream(assembler, on_closed=closed_cycles.append)
    records: list[dict] = []
    writer = RecordWriter(json_lines) if json_lines is not None else None
    try:
        try:
            for msg in reader:
                stream.receive(msg, trace_channel(msg))
                while closed_cycles:
                    record = pipeline.evaluate(closed_cycles.pop(0))
                    records.append(record)
                    if writer is not None:
                        writer.write(record)
                    if on_record is not None:
                        on_record(record)
        except BrokenPipeError:
            raise  # stdout's reader went away: not the trace's fault (the CLI exits quietly)
        except (ValueError, OSError, EOFError) as exc:
            raise UsageError(f"trace {str(trace_path)!r}: unreadable frame: {exc}") from None
    finally:
        if writer is not None:
            writer.close()
        stop = getattr(reader, "stop", None)
        if stop is not None:
            stop()
    return records, assembler.counters()

