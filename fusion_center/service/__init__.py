"""The fusion centre as a CANopen master on a python-can bus (run / demo / replay).

One module per job:

* :mod:`.decoder` - COB-ID tables, payload decoding (the hot path);
* :mod:`.cycles` - the deterministic SYNC-cycle assembler and its contract, :mod:`.cycle_frames`
  its frame decoding, :mod:`.cycle_records` what it reports;
* :mod:`.stream` - the serialised event stream (time stamps, trace queue, assembler) and its
  python-can listener;
* :mod:`.pipeline` - closed cycle -> record, composing:

  * :mod:`.decision_fusion` - the fusion rules over the received decisions, thresholds and
    rule results cached;
  * :mod:`.centralised_tests` - raw mode: the centralised raw-data tests of the readings;
  * :mod:`.physical` - forces, contact area, contact type, slip;

* :mod:`.records` - the JSON-lines decision log (and values made JSON-able);
* :mod:`.master` - NMT, SDO configuration, SYNC producer, heartbeat;
* :mod:`.fusion_service` - :class:`FusionService` (buses, evaluation of closed cycles, the
  decision log) and :class:`RunSummary`;
* :mod:`.traces` - trace writer, channel of a traced frame, offline replay;
* :mod:`.trace_writers` - the trace's flush at each cycle's close, for every format (BLF's
  container, the SQLite writer);
* :mod:`.live` - the rich live view;
* :mod:`.zenoh_publisher` - every record on Zenoh (``--zenoh``), :mod:`.zenoh_config` its
  session's settings; :mod:`.assemblers` and its modules - assemblers in other processes or
  hosts, linked to the fuser over Zenoh (:mod:`.assembler_link`).
"""

import pkgutil

import lazy_loader

# the names are imported on first use (PEP 562), as in fusion_center/__init__.py: a command that
# needs one module of the service (``fusion-center dcf``: master, lss; ``run``'s parser:
# zenoh_config) does not import all of them (the pipeline's scipy.special / scipy.spatial alone
# took ~0.5 s of CPU at every start-up); a module is also imported when read as an attribute
# (``fusion_center.service.traces``), as it was there after the eager imports
_SUBMODULES = sorted(m.name for m in pkgutil.iter_modules(__path__))
__getattr__, _dir, _names = lazy_loader.attach(__name__, submodules=_SUBMODULES, submod_attrs={
    "fusion_service": ["FusionService", "RunSummary"],
    "cycle_records": ["COUNTER_NAMES", "ClosedCycle", "quantise_timestamp"],
    "cycles": ["CycleAssembler"],
    "pipeline": ["CyclePipeline"],
    "records": ["RecordWriter", "read_records"],
    "stream": ["EventStream"],
    "traces": ["open_trace_writer", "replay_trace"],
    "zenoh_publisher": ["ZenohPublisher"],
})
__all__ = sorted(set(_names) - set(_SUBMODULES))


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_names))
