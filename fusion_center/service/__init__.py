"""The fusion centre as a CANopen master on a python-can bus (run / demo / replay).

Modules: :mod:`.decoder` (COB-ID tables, payload decoding - the hot path),
:mod:`.cycles` (the deterministic SYNC-cycle assembler and its contract),
:mod:`.pipeline` (closed cycle -> record), :mod:`.master` (NMT, SDO, SYNC, heartbeat),
:mod:`.records` (JSON-lines decision log), :mod:`.core` (buses, event stream, worker,
replay), :mod:`.live` (rich live view).
"""

from .core import EventStream, FusionService, RunSummary, open_trace_writer, replay_trace
from .cycles import COUNTER_NAMES, ClosedCycle, CycleAssembler, quantise_timestamp
from .pipeline import CyclePipeline
from .records import RecordWriter, read_records

__all__ = [
    "COUNTER_NAMES",
    "ClosedCycle",
    "CycleAssembler",
    "CyclePipeline",
    "EventStream",
    "FusionService",
    "RecordWriter",
    "RunSummary",
    "open_trace_writer",
    "quantise_timestamp",
    "read_records",
    "replay_trace",
]
