"""The decision log: one JSON object per SYNC cycle, one line each (JSON Lines).

Every record is written and flushed as soon as its cycle is evaluated, so a killed process
loses at most the cycle in flight (no ``os.fsync``: the OS keeps what was flushed). Floats are
written with Python's shortest round-trip repr and NaN/inf are refused (``allow_nan=False``:
the pipeline turns them into ``null``), so two runs that computed the same values write the
same bytes. :func:`jsonable` is that conversion of one value, used by every part of the
pipeline that puts a number into a record.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from taxel_net.errors import UsageError
from taxel_net.json_lines import iter_log


def jsonable(value):
    """Plain Python scalars for json; non-finite floats become None (JSON has no NaN)."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    value = float(value)
    return value if math.isfinite(value) else None


# json.dumps(record, separators=(",", ":"), allow_nan=False) with the encoder made once: the same
# text (json.dumps makes this very encoder per call), 5-10 % less CPU a record (measured with
# the decision-log records of matrix57 and skin4096, hot and after a 10 ms sleep)
_encode = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode


def dumps(record: dict) -> str:
    """The decision-log text of ``record`` (one line; NaN and infinity refused: ValueError)."""
    return _encode(record)


# the record a RecordWriter wrote last (the dict itself, kept alive here) and its line: the Zenoh
# publication of that record reuses the line instead of serialising it again (logged_line)
_logged: tuple = (None, "")


def logged_line(record: dict) -> str:
    """The decision-log line of ``record`` (no newline) when a :class:`RecordWriter` has just
    written this very dict, else :func:`dumps` of it now - the same text either way, computed
    once per record where the run writes a decision log and publishes it (``--json-lines`` with
    ``--zenoh``; the record's JSON was ~30 us of a cycle's CPU, 100-170 us after the idle gap
    between cycles on a loaded host)."""
    last, text = _logged
    return text if last is record else dumps(record)


class RecordWriter:
    """Append records to a JSON-lines file (created or truncated at open), flush per record."""

    def __init__(self, path):
        self.path = Path(path)
        try:
            self._file = open(self.path, "w", encoding="utf-8")
        except OSError as exc:
            raise UsageError(f"cannot write the decision log {str(path)!r}: {exc.strerror or exc}") from None
        self.count = 0

    def write(self, record: dict) -> None:
        global _logged
        text = dumps(record)
        self._file.write(text + "\n")
        self._file.flush()
        self.count += 1
        _logged = (record, text)

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_records(path) -> list[dict]:
    """Parse a decision log: every non-blank line one JSON object (``taxel_net.json_lines.iter_log``,
    the one reader of such files). A line that is not one (not UTF-8, not JSON, cut short, not an
    object) raises ValueError, one line naming the file, the line and what is wrong; a file that
    cannot be opened or read raises the OSError that ``open`` or the read raised."""
    try:
        return [record for _, record in iter_log(path)]
    except UsageError as exc:  # iter_log's error (exit 2 in the CLIs): a ValueError in this API
        if isinstance(exc.__context__, OSError):  # raised while handling it (from None)
            raise exc.__context__ from None
        raise ValueError(str(exc)) from None
