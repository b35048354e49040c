"""JSON-lines files read back: the decision log (``fusion-center plot`` and ``export``) and
node-sim's ``--truth-log`` (``replay --truth-log``) - one reader, one way to say what is wrong.

Standard library only (and :class:`UsageError`): ``plot`` starts without the service's imports.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator

from .errors import UsageError


def iter_log(path, label: str = "decision log", *, check: Callable[[object], str | None] | None = None,
             not_json: str = "not JSON ({why})", allow_nan: bool = True) -> Iterator[tuple[int, object]]:
    """``(line number, value)`` of every non-blank line of a JSON-lines file, read as it goes.

    A line that cannot be used ends the reading with one :class:`UsageError` (exit 2), one line
    naming the file, the line and what is wrong: ``{label} 'FILE', line N: ...`` - not JSON
    (``not_json`` with ``{why}``: the parser's message and column), or what ``check(value)``
    returns (None: the value is fine; without ``check`` every value must be a JSON object). A
    byte that is not UTF-8 names its line and column; a file that cannot be opened or read says
    why. ``allow_nan=False`` refuses ``NaN`` / ``Infinity`` (not JSON; Python's json reads them).
    A last line cut short (a run killed mid-write: no newline, not JSON) is refused like any other
    bad line, naming it. An empty file yields nothing: the caller says what it needs.
    """
    name = str(path)
    check = _a_json_object if check is None else check
    parse_constant = None if allow_nan else _no_constant
    try:
        f = open(path, "rb")
    except OSError as exc:
        raise UsageError(f"{label} {name!r}: cannot be read: {exc.strerror or exc}") from None
    with f:
        try:
            for number, raw in enumerate(f, 1):
                try:
                    line = raw.decode("utf-8")
                except UnicodeDecodeError as exc:
                    raise UsageError(f"{label} {name!r}: not a UTF-8 text file (byte 0x{raw[exc.start]:02X} in "
                                     f"line {number}, column {exc.start + 1})") from None
                if not line.strip():
                    continue
                try:
                    value = json.loads(line, parse_constant=parse_constant)
                except (ValueError, RecursionError) as exc:
                    raise UsageError(f"{label} {name!r}, line {number}: {not_json.format(why=_why(exc))}") from None
                problem = check(value)
                if problem is not None:
                    raise UsageError(f"{label} {name!r}, line {number}: {problem}")
                yield number, value
        except OSError as exc:
            raise UsageError(f"{label} {name!r}: cannot be read: {exc.strerror or exc}") from None


def _why(exc: Exception) -> str:
    """What the JSON parser found wrong with a line (the column: the line is named already)."""
    if isinstance(exc, json.JSONDecodeError):
        return f"{exc.msg} at column {exc.colno}"
    if isinstance(exc, RecursionError):
        return "nested too deeply"
    return str(exc)


def _a_json_object(value) -> str | None:
    return None if isinstance(value, dict) else "not a JSON object"


def _no_constant(name: str):
    raise ValueError(f"{name} is not JSON")
