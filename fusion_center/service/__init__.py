"""The fusion centre as a CANopen master on a python-can bus (run / demo / replay).

Modules: :mod:`.decoder` (COB-ID tables, payload decoding - the hot path),
:mod:`.cycles` (the deterministic SYNC-cycle assembler and its contract),
:mod:`.pipeline` (closed cycle -> record), :mod:`.master` (NMT, SDO, SYNC, heartbeat),
:mod:`.records` (JSON-lines decision log), :mod:`.stream` (the serialised event stream,
its python-can listener), :mod:`.fusion_service` (:class:`FusionService`: buses, evaluation
of closed cycles, :class:`RunSummary`), :mod:`.traces` (trace writer, offline replay),
:mod:`.live` (rich live view).
"""

from .fusion_service import FusionService, RunSummary
from .cycles import COUNTER_NAMES, ClosedCycle, CycleAssembler, quantise_timestamp
from .pipeline import CyclePipeline
from .records import RecordWriter, read_records
from .stream import EventStream
from .traces import open_trace_writer, replay_trace

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
