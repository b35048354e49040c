"""The decision log: one JSON object per SYNC cycle, one line each (JSON Lines).

Every record is written and flushed as soon as its cycle is evaluated, so a killed process
loses at most the cycle in flight (no ``os.fsync``: the OS keeps what was flushed). Compact JSON,
ASCII only (other characters as ``\\uXXXX``), floats written as their shortest round-trip
decimal (read back bit for bit) and NaN/inf refused (ValueError, as ``json``'s
``allow_nan=False``: the pipeline turns them into ``null``), so two runs that computed the same
values write the same bytes. :func:`jsonable` is that conversion of one value, used by every
part of the pipeline that puts a number into a record.

**The encoder** (:func:`dumpb`): ``orjson`` where the value is plain JSON - dicts with ``str``
keys, lists, tuples, ``str``, ``int``, ``bool``, ``None`` and finite ``float`` (exactly these
classes), which a walk over the value checks first (orjson itself writes NaN and infinity as
``null``: the walk keeps them refused) - else the standard library's ``json`` with the settings
above, which writes what it always wrote or raises what it always raised (NaN and infinity,
numpy scalars, ``int`` keys, non-ASCII text, circular references go there). The two write the
same JSON values: the same text but for DEL (U+007F: orjson writes the byte, json ``\\u007f``)
and floats below 1e-4 that json writes in exponent form
(``1e-05``, ``1.5e-07``; orjson: ``0.00001``, ``1.5e-7``) and, with orjson 3.10, from 1e16 up
(``1e16`` for ``1e+16``) - the same digits (``tests/test_records_dumps.py``: every value of a generated record read back
equal, floats bit for bit). A matrix57 record (1.7 kB) costs 10 us instead of 29 back to back,
~100 instead of ~230 us after the 10 ms idle gap between cycles (``bench/records_encode.py``;
docs/robotics.md, *The JSON encoder*).
"""

from __future__ import annotations

import json
import math

import numpy as np
import orjson

from taxel_net.errors import UsageError
from taxel_net.json_lines import JsonLinesWriter, iter_log


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


# json.dumps(record, separators=(",", ":"), allow_nan=False) with the encoder made once (json.dumps
# makes this very encoder per call): the fallback of dumpb, whose text or error is today's
_encode = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode
_orjson = orjson.dumps
_isfinite = math.isfinite
_SCALARS = frozenset((str, int, bool, type(None)))


def _plain(container) -> bool:
    """Whether a dict / list / tuple holds only what :func:`dumpb` gives orjson: dicts (their
    keys are orjson's to check: a key that is no ``str`` makes it raise), lists, tuples, ``str``,
    ``int``, ``bool``, ``None`` and finite ``float`` - exactly these classes (a subclass, a numpy
    scalar, NaN or infinity: False). A circular value raises RecursionError. (6-8 us a
    decision-log record back to back: orjson's own time is 2-3 us.)"""
    for x in (container.values() if type(container) is dict else container):
        cls = type(x)
        if cls in _SCALARS:
            continue
        if cls is float:
            if x - x:  # NaN for NaN and +-inf, 0.0 for every finite float
                return False
        elif cls is dict or cls is list or cls is tuple:
            if not _plain(x):
                return False
        else:
            return False
    return True


def dumpb(value) -> bytes:
    """The decision-log text of ``value`` (a record, or any part of one) as bytes: one line,
    compact, ASCII; NaN and infinity refused (ValueError). orjson when :func:`_plain` says it
    may and its text is ASCII, else ``json`` (module docstring)."""
    cls = type(value)
    try:
        fast = _plain(value) if cls is dict or cls is list or cls is tuple else \
            cls in _SCALARS or (cls is float and _isfinite(value))
    except RecursionError:  # a circular value: json says so (ValueError)
        fast = False
    if fast:
        try:
            text = _orjson(value)
        except TypeError:  # orjson.JSONEncodeError: a key that is no str, an int beyond 64 bits, a lone
            pass           # surrogate, nesting deeper than orjson's 254 levels - json's to write or refuse
        else:
            if text.isascii():
                return text
    return _encode(value).encode()


def dumps(value) -> str:
    """:func:`dumpb` as a str: the decision-log line of ``value`` (no newline; NaN and infinity
    refused: ValueError)."""
    return dumpb(value).decode("ascii")


# the record a RecordWriter wrote last (the dict itself, kept alive here) and its line: the Zenoh
# publication of that record reuses the line instead of serialising it again (logged_line)
_logged: tuple = (None, b"")


def made_line(record: dict) -> bytes | None:
    """The decision-log line of ``record`` when a :class:`RecordWriter` has just written this
    very dict (no work), else None."""
    last, text = _logged
    return text if last is record else None


def logged_line(record: dict) -> bytes:
    """The decision-log line of ``record`` (bytes, no newline) when a :class:`RecordWriter` has
    just written this very dict, else :func:`dumpb` of it now - the same bytes either way,
    computed once per record where the run writes a decision log and publishes it
    (``--json-lines`` with ``--zenoh``)."""
    line = made_line(record)
    return dumpb(record) if line is None else line


class RecordWriter(JsonLinesWriter):
    """Append records to a JSON-lines file (created or truncated at open) with :func:`dumpb`, one
    write a record: :class:`taxel_net.json_lines.JsonLinesWriter` (a failed write never raises,
    ends the file at its last whole line and is said in :attr:`failure`)."""

    def __init__(self, path, option: str = "--json-lines"):
        super().__init__(path, dumpb, option=option, what="decision log")

    def write(self, record: dict) -> bool:
        global _logged
        if not super().write(record):
            return False
        _logged = (record, self.last_line)
        return True


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
