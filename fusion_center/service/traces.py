"""CAN traces: the writer of a live run (``can.Logger``, format by extension), the channel of
a frame read back, and the offline replay that re-fuses a trace through the live classes
(:class:`~fusion_center.service.stream.EventStream` -> :class:`CyclePipeline`), so it
reproduces the live records exactly.
"""

from __future__ import annotations

import io
import locale
import logging
from pathlib import Path
from typing import Callable

import can
from can.io.logger import MESSAGE_WRITERS as _WRITERS  # what python-can writes, by extension
from can.io.player import MESSAGE_READERS as _READERS  # ... and reads back

from taxel_net.errors import UsageError, one_line
from taxel_net.outputs import OutputPath
from taxel_net.scene import Scene
from .cycle_records import ClosedCycle
from .cycles import CycleAssembler
from .pipeline import CyclePipeline
from .records import RecordWriter
from .stream import EventStream

TRACE_SUFFIXES = tuple(sorted(_WRITERS))
# formats whose frames come back without their channel (python-can's CSV and SQLite):
# single-channel scenes only
CHANNELLESS_SUFFIXES = (".csv", ".db")
# formats whose reader numbers channels from 1 (PCAN-View's TRC: the writer adds 1)
ONE_BASED_SUFFIXES = (".trc",)
# formats --log refuses (issue 21), and why: python-can writes them with frames lost or changed,
# so a replay of the run could not reproduce it, or writes nothing before the run ends, so a
# killed run loses the whole trace. Replay still reads such traces made by other tools (their
# limits in docs/service.md); the centre writes .log, .asc and .blf, each handed to the OS at
# every cycle's close (trace_writers.flush_to_os)
REFUSED_TRACE_SUFFIXES = {
    ".csv": "records no frame's CAN FD flag, bit-rate switch, direction or channel, so a replay could "
            "not reproduce the run",
    ".db": "records no frame's CAN FD flag, bit-rate switch, direction or channel, so a replay could "
           "not reproduce the run",
    ".trc": "writer drops CAN FD, remote and error frames, so a replay could not reproduce the run",
    ".mf4": "writer (asammdf) writes the file only when the run ends, so a killed run loses all of it",
}
logger = logging.getLogger("fusion_center.service")
# replay refuses a trace whose frames of node-IDs or COB-IDs the scene does not have exceed
# this fraction of its frames (a trace of another scene), unless --force
FOREIGN_FRACTION_MAX = 0.02


def check_trace_target(path) -> None:
    """Refuse, before a run starts, a ``--log`` path replay could not use: an extension python-
    can does not write or cannot read back (``.txt``), a writer whose optional package is not
    installed, a format that cannot carry every frame a bus delivers or keeps nothing of a
    killed run (:data:`REFUSED_TRACE_SUFFIXES`: ``.csv``, ``.db``, ``.trc``, ``.mf4``), so that
    the replay of every trace the centre writes reproduces the run's records byte for byte and
    a killed run loses at most the cycle in flight. Raises :class:`UsageError` (one line)."""
    if path is None:
        return
    p = Path(path)
    suffix = p.suffix.lower()
    readable = [s for s in TRACE_SUFFIXES if s in _READERS and s not in REFUSED_TRACE_SUFFIXES]
    if suffix not in _WRITERS:
        raise UsageError(f"--log {str(path)!r}: unknown trace format {p.suffix!r} "
                         f"(python-can writes and reads back {', '.join(readable)})")
    if suffix not in _READERS:
        raise UsageError(f"--log {str(path)!r}: python-can writes {suffix} but cannot read it back, so it "
                         f"cannot be replayed (use {', '.join(readable)})")
    if suffix in REFUSED_TRACE_SUFFIXES:
        raise UsageError(f"--log {str(path)!r}: python-can's {suffix} {REFUSED_TRACE_SUFFIXES[suffix]}; "
                         "record .log, .asc or .blf (python -m can.logconvert "
                         f"run.log run{suffix} converts a copy)")


def open_trace_writer(path) -> can.Listener:
    """The trace writer of ``path``'s format, by extension: python-can's (``can.Logger``: .log
    candump, .asc, .blf); :func:`check_trace_target` refuses the others. The stream hands its
    frames to the operating system at every cycle's close (:func:`~.trace_writers.flush_to_os`)."""
    check_trace_target(path)
    try:
        return can.Logger(str(Path(path)))
    except (OSError, ValueError, NotImplementedError, ImportError) as exc:
        raise UsageError(f"--log {str(path)!r}: cannot be written: {exc}") from None


def trace_channel(msg: can.Message, suffix: str = "") -> int:
    """Scene channel index of a frame read back from a trace of format ``suffix`` (see
    ``EventStream``): python-can's readers give the channel as written (``can0`` -> 0, ASC and
    BLF 0-based), TRC's from 1; CSV and SQLite none (channel 0)."""
    from can.util import channel2int

    channel = channel2int(msg.channel)
    if channel is None:
        return 0
    return channel - 1 if suffix.lower() in ONE_BASED_SUFFIXES else channel


def replay_trace(scene: Scene, trace_path, *, json_lines=None, truth: bool = True,
                 on_record: Callable[[dict], None] | None = None,
                 grasp_truth=None,
                 on_cycle: Callable[[dict, ClosedCycle], None] | None = None) -> tuple[list[dict], dict[str, int]]:
    """Re-fuse a recorded trace offline: the same stream -> the same records as live.

    Returns (records, counters). The open cycle at the end of the trace is not reported
    (live runs end theirs with an NMT broadcast, which is in the trace).

    A trace of any content - binary, wrong format, truncated, a BLF file cut after its writer
    closed it - raises :class:`UsageError` (one line naming the file and the position); one its
    writer never closed (a killed run: a BLF with its opening header, an ASC without its ``End
    TriggerBlock``, a candump ``.log`` whose last line has no newline) is read up to its last
    complete container or line, with a warning.
    ``json_lines`` is written to ``OUT.partial`` and renamed to ``OUT`` only when the whole
    trace was read: a failed replay leaves no complete-
    looking log (the partial one stays as ``OUT.partial``, and an ``OUT`` of an earlier run is
    removed). An ``OUT`` that is not a regular file (``/dev/null``, a FIFO, ``/dev/stdout``) is
    written in place and never renamed over nor removed (:class:`taxel_net.outputs.OutputPath`).
    ``grasp_truth``: the grasp world's truth (a :class:`~.grasp_truth.TruthTable`, ``--truth-log``)
    for the records' ``grasp_truth`` on a scene with a gripper.
    """
    p = Path(trace_path)
    name = str(trace_path)
    suffix = p.suffix.lower()
    out = OutputPath(json_lines, option="--json-lines") if json_lines is not None else None
    try:
        reader = _open_reader(p)
    except UsageError:
        if out is not None:
            out.discard_stale()  # a log of an earlier replay must not pass for this one's
        raise
    assembler = CycleAssembler(scene)
    pipeline = CyclePipeline(scene, truth=truth)
    pipeline.grasp_truth = grasp_truth
    closed_cycles: list[ClosedCycle] = []
    stream = EventStream(assembler, on_closed=closed_cycles.append)
    records: list[dict] = []
    partial = out.write_path if out is not None else None
    writer = RecordWriter(partial) if partial is not None else None
    frames = 0
    ok = False
    try:
        try:
            for msg in reader:
                frames += 1
                stream.receive(msg, trace_channel(msg, suffix))
                while closed_cycles:
                    closed = closed_cycles.pop(0)
                    record = pipeline.evaluate(closed)
                    records.append(record)
                    if writer is not None and not writer.write(record) and writer.io_failed:
                        raise UsageError(writer.failure + "; the replay stopped there")  # the log's fault, not the trace's
                    if on_record is not None:
                        on_record(record)
                    if on_cycle is not None:  # with the closed cycle, as FusionService.on_cycle
                        on_cycle(record, closed)
            ok = True
        except BrokenPipeError:
            raise  # stdout's reader went away: not the trace's fault (the CLI exits quietly)
        except UsageError:
            raise
        except Exception as exc:  # noqa: BLE001 - truncated, corrupted: any reader error
            raise UsageError(f"trace {name!r}: unreadable after frame {frames}: {one_line(exc)}"
                             + (f" (the {len(records)} records so far are in {str(partial)!r})"
                                if partial is not None else "")) from None
    finally:
        failure = None
        if writer is not None:
            writer.close()
            if ok:
                out.commit()
                failure = writer.failure  # records left out, not encodable (as live): kept, said
            else:
                out.discard_stale()  # a log of an earlier replay must not pass for this one's
        _stop(reader)
    if failure:
        raise UsageError(failure)
    return records, stream.counters()


def _open_reader(p: Path, *, notify: bool = True):
    """``can.LogReader`` of a trace, or :class:`UsageError` (one line naming it).

    A trace its writer never closed - a run killed (SIGKILL, a crash, a power cut): a BLF whose
    header is still the one written at its opening, an ASC without its ``End TriggerBlock`` - is
    read up to its last complete container (BLF) or line (ASC), which holds every cycle but the
    one in flight (the centre hands the trace to the OS at each cycle's close); with ``notify``,
    a warning line says so. A trace cut or altered after its writer closed it is refused
    (:func:`_check_complete`)."""
    name = str(p)
    if not p.is_file():
        raise UsageError(f"trace {name!r} not found")
    try:
        reader = can.LogReader(str(p))
    except Exception as exc:  # noqa: BLE001 - any content: one line naming the file
        raise UsageError(f"trace {name!r} cannot be read: {one_line(exc)}") from None
    try:
        unclosed = _check_complete(p, reader)
    except UsageError:
        _stop(reader)
        raise
    if unclosed is None:
        return reader
    end, what = unclosed
    size = p.stat().st_size
    if notify:
        why = ("never closed by its writer (the run was killed?)" if what == "container" else
               "no newline at its end: its writer was killed mid-line (or it was cut)" if p.suffix.lower() == ".log"
               else "no 'End TriggerBlock': never closed by its writer (the run was killed?) or cut")
        logger.warning("trace %r: %s: read up to its last complete %s (%d of its %d bytes)", name, why, what, end, size)
    if end == size:
        return reader
    _stop(reader)
    try:
        return _READERS[p.suffix.lower()](_prefix_file(p, end, text=what == "line"))
    except Exception as exc:  # noqa: BLE001 - any content: one line naming the file
        raise UsageError(f"trace {name!r} cannot be read: {one_line(exc)}") from None


def _patch_tpdo_tables(scene: Scene) -> tuple[list[dict[int, int]], list[dict[int, int]]]:
    """Per channel, COB-ID -> data length of the patches' TPDOs in the scene's mode and in the
    other mode."""
    import dataclasses

    from taxel_net.patches import devices

    other = dataclasses.replace(scene, bus=dataclasses.replace(
        scene.bus, mode="raw" if scene.bus.mode == "decision" else "decision"))
    tables = []
    for sc in (scene, other):
        table: list[dict[int, int]] = [{} for _ in scene.bus.channels]
        for device in devices(sc):
            for tpdo in device.tpdos:
                table[device.channel][tpdo.cob_id] = tpdo.length
        tables.append(table)
    return tables[0], tables[1]


def check_trace(scene: Scene, trace_path) -> dict:
    """Is this trace a recording of ``scene`` in ``scene.bus.mode``? One pass over the frames
    before replay writes anything; :class:`UsageError` (one line: what does not match, the
    counts, ``--force`` to replay anyway) when:

    * a frame is on a channel the scene does not have (channel index as :func:`trace_channel`
      maps it; e.g. a two-channel trace replayed with a one-channel scene);
    * the trace format stores no channel (``.csv``, ``.db``) and the scene has several;
    * more than :data:`FOREIGN_FRACTION_MAX` of the frames carry a node-ID that is not a node of
      the scene on that channel, or a COB-ID of no CANopen object the scene uses (a trace of
      another scene);
    * the nodes' PDOs are those of the other mode (TPDO2 X_i in a decision-mode replay, TPDO1
      u_i in a raw-mode one; with patch nodes, frames that fit only the other mode's TPDOs -
      COB-ID and length, :func:`taxel_net.patches.devices` - outnumber those that fit only
      this mode's).

    Returns the counts (``frames``, ``channels``, ``foreign``, ``tpdo1``, ``tpdo2``).
    """
    from .decoder import (BASE_EMCY, BASE_HEARTBEAT, BASE_SDO_REQUEST, BASE_SDO_RESPONSE, BASE_TPDO1,
                          BASE_TPDO2, COB_NMT, COB_SYNC, COB_TIME)

    p = Path(trace_path)
    name = str(trace_path)
    suffix = p.suffix.lower()
    n_channels = len(scene.bus.channels)
    if suffix in CHANNELLESS_SUFFIXES and n_channels > 1:
        raise UsageError(f"trace {name!r}: {suffix} stores no channel, and scene {scene.name!r} has {n_channels} "
                         "channels: replay a .log, .asc, .blf or .trc trace of the run (or --force: all on channel 0)")
    nodes = [set() for _ in range(n_channels)]
    for t in scene.taxels:
        nodes[t.channel].add(t.node_id)
    drive_cobs: set = set()  # the gripper drive's own COB-IDs (its RPDO1 too: the centre commands it)
    if scene.gripper is not None:  # the gripper drive is a node of the scene too
        from taxel_net.gripper import drive_cob_ids

        drive_cobs = {(scene.gripper.channel, cob) for cob in drive_cob_ids(scene.gripper.node_id)}
    bases = (BASE_EMCY, BASE_TPDO1, BASE_TPDO2, BASE_SDO_RESPONSE, BASE_SDO_REQUEST, BASE_HEARTBEAT)
    # the master's own heartbeat (CiA 302), when the scene's master produces one
    master_heartbeat = BASE_HEARTBEAT + scene.master.node_id if scene.master_heartbeat_ms > 0 else COB_NMT
    # patch nodes: TPDO COB-IDs are allotted per channel (taxel_net.patches), not 0x180/0x280 +
    # node-ID; a frame is one of this mode's / the other mode's TPDOs by COB-ID and length
    patch_tables = _patch_tpdo_tables(scene) if scene.bus.patch_nodes else None
    if patch_tables is not None:
        bases = (BASE_EMCY, BASE_SDO_RESPONSE, BASE_SDO_REQUEST, BASE_HEARTBEAT)
    frames = 0
    off_channel: dict[int, int] = {}
    foreign_nodes: dict[int, int] = {}
    foreign_cobs: dict[int, int] = {}
    tpdo = {BASE_TPDO1: 0, BASE_TPDO2: 0}
    reader = _open_reader(p, notify=False)  # replay_trace says it, after this check
    try:
        for msg in reader:
            frames += 1
            channel = trace_channel(msg, suffix)
            if not 0 <= channel < n_channels:
                off_channel[channel] = off_channel.get(channel, 0) + 1
                continue
            if msg.is_error_frame or msg.is_extended_id:
                continue  # counted as malformed by the replay itself, as live
            cob = msg.arbitration_id
            if cob in (COB_NMT, COB_SYNC, COB_TIME, master_heartbeat) or (channel, cob) in drive_cobs:
                continue
            if patch_tables is not None:
                this_mode, other_mode = patch_tables[0][channel].get(cob), patch_tables[1][channel].get(cob)
                if this_mode is not None or other_mode is not None:
                    fits_this, fits_other = this_mode == len(msg.data), other_mode == len(msg.data)
                    if fits_this and not fits_other:
                        tpdo[BASE_TPDO1 if scene.bus.mode == "decision" else BASE_TPDO2] += 1
                    elif fits_other and not fits_this:
                        tpdo[BASE_TPDO2 if scene.bus.mode == "decision" else BASE_TPDO1] += 1
                    continue  # a TPDO of the scene's patches (a bad length is counted by the replay)
            base, node = cob & 0x780, cob & 0x7F
            if base not in bases or node == 0:
                foreign_cobs[cob] = foreign_cobs.get(cob, 0) + 1
            elif node not in nodes[channel]:
                foreign_nodes[node] = foreign_nodes.get(node, 0) + 1
            elif base in tpdo:
                tpdo[base] += 1
    except Exception as exc:  # noqa: BLE001 - truncated, corrupted: any reader error
        raise UsageError(f"trace {name!r}: unreadable after frame {frames}: {one_line(exc)}") from None
    finally:
        _stop(reader)
    force = "; --force replays it anyway"
    if off_channel:
        listed = ", ".join(f"{ch} ({count} frames)" for ch, count in sorted(off_channel.items()))
        raise UsageError(f"trace {name!r}: frames on channel {listed}, but scene {scene.name!r} has channel(s) "
                         f"0..{n_channels - 1} ({', '.join(scene.bus.channels)}){force}")
    foreign = sum(foreign_nodes.values()) + sum(foreign_cobs.values())
    if frames and foreign > FOREIGN_FRACTION_MAX * frames:
        what = []
        if foreign_nodes:
            ids = sorted(foreign_nodes)
            what.append(f"node-ID(s) {', '.join(map(str, ids[:8]))}{', ...' if len(ids) > 8 else ''} "
                        f"({sum(foreign_nodes.values())} frames)")
        if foreign_cobs:
            cobs = sorted(foreign_cobs)
            what.append(f"COB-ID(s) {', '.join(f'0x{c:03X}' for c in cobs[:8])}{', ...' if len(cobs) > 8 else ''} "
                        f"({sum(foreign_cobs.values())} frames)")
        raise UsageError(f"trace {name!r}: {foreign} of {frames} frames belong to no node of scene {scene.name!r}: "
                         f"{' and '.join(what)}; recorded with another scene?{force}")
    mode = scene.bus.mode
    wanted, other = (BASE_TPDO1, BASE_TPDO2) if mode == "decision" else (BASE_TPDO2, BASE_TPDO1)
    if tpdo[other] > tpdo[wanted]:
        other_mode = "raw" if mode == "decision" else "decision"
        raise UsageError(f"trace {name!r}: recorded in {other_mode} mode (TPDO1 u_i frames: {tpdo[BASE_TPDO1]}, "
                         f"TPDO2 X_i frames: {tpdo[BASE_TPDO2]}), replayed in {mode} mode: give --mode {other_mode}"
                         f"{force}")
    return {"frames": frames, "channels": n_channels, "foreign": foreign,
            "tpdo1": tpdo[BASE_TPDO1], "tpdo2": tpdo[BASE_TPDO2]}


def _stop(reader) -> None:
    stop = getattr(reader, "stop", None)
    if stop is not None:
        try:
            stop()
        except Exception:  # noqa: BLE001
            pass


def _check_complete(path: Path, reader) -> tuple[int, str] | None:
    """Formats that say where they end: a BLF header carries the file size (python-can's writer
    writes it when it closes the file; at the opening it writes the header's own size), an ASC
    file that begins a trigger block (``Begin Triggerblock``, as python-can and Vector tools write
    it) ends with ``End TriggerBlock`` (can-utils' ``log2asc`` writes no trigger block: nothing to
    check).

    Returns None for a complete trace (or a format that cannot tell), ``(end, unit)`` for one
    its writer never closed - ``end`` is the end of its last complete ``unit`` ("container" of
    a BLF, "line" of an ASC or of a candump ``.log`` whose last line has no newline: a frame cut
    short would be read as another frame, ``639#230`` of ``639#2300...``) - and raises :class:`UsageError` for a BLF whose header's size is
    neither the file's nor the one written at the opening (cut or altered after it was closed)."""
    from can.io.blf import FILE_HEADER_STRUCT

    suffix = path.suffix.lower()
    size = path.stat().st_size
    if suffix == ".blf":
        declared = getattr(reader, "file_size", None)
        if declared is None or declared == size:
            return None
        with open(path, "rb") as f:
            header_length = FILE_HEADER_STRUCT.unpack(f.read(FILE_HEADER_STRUCT.size))[1]  # read by BLFReader
        if declared == header_length < size:
            return _blf_complete_end(path, header_length, size), "container"
        raise UsageError(f"trace {str(path)!r}: truncated or altered after its writer closed it "
                         f"(BLF header: {declared} bytes, file: {size} bytes)")
    if suffix == ".asc":
        with open(path, "rb") as f:
            begins = b"begin triggerblock" in f.read(4096).lower()
            f.seek(max(0, size - 256))
            tail = f.read().split(b"\n")
        if not begins:
            return None
        last = next((line.strip() for line in reversed(tail) if line.strip()), b"")
        if last != b"End TriggerBlock":
            return _last_line_end(path, size), "line"
    if suffix == ".log" and size:
        with open(path, "rb") as f:  # every line of a candump log ends with a newline
            f.seek(size - 1)
            if f.read(1) != b"\n":
                return _last_line_end(path, size), "line"
    return None


def _blf_complete_end(path: Path, start: int, size: int) -> int:
    """The end of a BLF's last complete object (its LOG_CONTAINERs, one a cycle from the centre),
    walking the object headers from ``start`` as python-can's BLFReader reads them (size, then
    ``size % 4`` padding bytes). At an object that does not begin with ``LOBJ`` the walk stops
    and the file's size is returned: the reader then fails there, as on any corrupted trace."""
    from can.io.blf import OBJ_HEADER_BASE_STRUCT

    base = OBJ_HEADER_BASE_STRUCT.size
    pos = start
    with open(path, "rb") as f:
        while pos + base <= size:
            f.seek(pos)
            signature, _, _, obj_size, _ = OBJ_HEADER_BASE_STRUCT.unpack(f.read(base))
            if signature != b"LOBJ" or obj_size < base:
                return size
            end = pos + obj_size + obj_size % 4
            if end > size:
                break  # the container being written when the writer stopped
            pos = end
    return pos


def _last_line_end(path: Path, size: int) -> int:
    """The end of a text file's last complete line (after its last newline; 0 without one)."""
    chunk = 4096
    with open(path, "rb") as f:
        pos = size
        while pos > 0:
            start = max(0, pos - chunk)
            f.seek(start)
            found = f.read(pos - start).rfind(b"\n")
            if found >= 0:
                return start + found + 1
            pos = start
    return 0


class _Prefix(io.RawIOBase):
    """The first ``limit`` bytes of a file, read-only (a trace read up to its last complete
    container or line)."""

    def __init__(self, path: Path, limit: int):
        self._file = open(path, "rb")
        self._left = limit

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        n = min(len(buffer), self._left)
        if n <= 0:
            return 0
        got = self._file.readinto(memoryview(buffer)[:n]) or 0
        self._left -= got
        return got

    def close(self) -> None:
        self._file.close()
        super().close()


def _prefix_file(path: Path, limit: int, *, text: bool):
    """A file object of ``path``'s first ``limit`` bytes, as python-can's readers open theirs
    (binary, or text in the locale's encoding)."""
    raw = io.BufferedReader(_Prefix(path, limit))
    if not text:
        return raw
    return io.TextIOWrapper(raw, encoding=locale.getpreferredencoding(False))
