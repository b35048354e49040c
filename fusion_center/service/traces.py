"""CAN traces: the writer of a live run (``can.Logger``, format by extension), the channel of
a frame read back, and the offline replay that re-fuses a trace through the live classes
(:class:`~fusion_center.service.stream.EventStream` -> :class:`CyclePipeline`), so it
reproduces the live records exactly.
"""

from __future__ import annotations

import os
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

    A trace of any content - binary, wrong format, truncated, a BLF file its writer never
    closed, an ASC file without its ``End TriggerBlock`` - raises :class:`UsageError` (one
    line naming the file and the position). ``json_lines`` is written to ``OUT.partial`` and
    renamed to ``OUT`` only when the whole trace was read: a failed replay leaves no complete-
    looking log (the partial one stays as ``OUT.partial``, and an ``OUT`` of an earlier run is
    removed).
    """
    p = Path(trace_path)
    name = str(trace_path)
    out = Path(json_lines) if json_lines is not None else None
    try:
        if not p.is_file():
            raise UsageError(f"trace {name!r} not found")
        try:
            reader = can.LogReader(str(p))
        except Exception as exc:  # noqa: BLE001 - any content: one line naming the file
            raise UsageError(f"trace {name!r} cannot be read: {_one_line(exc)}") from None
        try:
            _check_complete(p, reader)
        except UsageError:
            _stop(reader)
            raise
    except UsageError:
        if out is not None and out.exists():
            out.unlink()  # a log of an earlier replay must not pass for this one's
        raise
    assembler = CycleAssembler(scene)
    pipeline = CyclePipeline(scene, truth=truth)
    closed_cycles: list[ClosedCycle] = []
    stream = EventStream(assembler, on_closed=closed_cycles.append)
    records: list[dict] = []
    partial = out.with_name(out.name + ".partial") if out is not None else None
    writer = RecordWriter(partial) if partial is not None else None
    frames = 0
    ok = False
    try:
        try:
            for msg in reader:
                frames += 1
                stream.receive(msg, trace_channel(msg))
                while closed_cycles:
                    record = pipeline.evaluate(closed_cycles.pop(0))
                    records.append(record)
                    if writer is not None:
                        writer.write(record)
                    if on_record is not None:
                        on_record(record)
            ok = True
        except BrokenPipeError:
            raise  # stdout's reader went away: not the trace's fault (the CLI exits quietly)
        except UsageError:
            raise
        except Exception as exc:  # noqa: BLE001 - truncated, corrupted: any reader error
            raise UsageError(f"trace {name!r}: unreadable after frame {frames}: {_one_line(exc)}"
                             + (f" (the {len(records)} records so far are in {str(partial)!r})"
                                if partial is not None else "")) from None
    finally:
        if writer is not None:
            writer.close()
            if ok:
                os.replace(partial, out)
            elif out.exists():
                out.unlink()  # a log of an earlier replay must not pass for this one's
        _stop(reader)
    return records, assembler.counters()


def _one_line(exc: BaseException) -> str:
    return " ".join(f"{type(exc).__name__}: {exc}".split())


def _stop(reader) -> None:
    stop = getattr(reader, "stop", None)
    if stop is not None:
        try:
            stop()
        except Exception:  # noqa: BLE001
            pass


def _check_complete(path: Path, reader) -> None:
    """Formats that say where they end: a BLF header carries the file size (written when the
    writer closes the file), an ASC file ends with ``End TriggerBlock``."""
    suffix = path.suffix.lower()
    size = path.stat().st_size
    if suffix == ".blf":
        declared = getattr(reader, "file_size", None)
        if declared is not None and declared != size:
            raise UsageError(f"trace {str(path)!r}: truncated or never closed by its writer "
                             f"(BLF header: {declared} bytes, file: {size} bytes)")
    elif suffix == ".asc":
        with open(path, "rb") as f:
            f.seek(max(0, size - 256))
            tail = f.read().split(b"\n")
        last = next((line.strip() for line in reversed(tail) if line.strip()), b"")
        if last != b"End TriggerBlock":
            raise UsageError(f"trace {str(path)!r}: truncated (an ASC trace ends with 'End TriggerBlock'; "
                             f"the last line is {last[:60].decode('latin-1')!r})")

