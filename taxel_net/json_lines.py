"""JSON-lines files written and read back: the decision log (``--json-lines``; ``fusion-center
plot`` and ``export`` read it) and node-sim's ``--truth-log`` (``replay --truth-log``) - one
writer (:class:`JsonLinesWriter`), one reader (:func:`iter_log`), one way to say what is wrong.

Standard library only (and :class:`UsageError`): ``plot`` starts without the service's imports.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator
from pathlib import Path

from .errors import UsageError, one_line


LINE_MAX = 64 * 2**20   # bytes: a decision record of the largest scenes is ~0.2 MiB (skin4096 raw)


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
    bad line, naming it. A line longer than :data:`LINE_MAX` is refused when that much is read
    (``/dev/zero``: never a whole line). An empty file yields nothing: the caller says what it needs.
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
            number = 0
            while True:
                # a line read at most LINE_MAX bytes at a time: /dev/zero or a file without newlines
                # is one endless line, which a plain read would hold in memory without bound
                raw = f.readline(LINE_MAX + 1)
                if not raw:
                    break
                number += 1
                if len(raw) > LINE_MAX and not raw.endswith(b"\n"):
                    raise UsageError(f"{label} {name!r}, line {number}: longer than {LINE_MAX // 2**20} MiB "
                                     "(not a JSON-lines file of this project?)")
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


class JsonLinesWriter:
    """Write values as JSON lines to ``path`` (created or truncated at open), one ``write`` system
    call a line: each line reaches the OS as soon as it is made (a killed process loses at most
    the line in flight). ``encode(value) -> bytes``: one line without its newline.

    A write that fails never raises (a full disk must not stop a centre holding a part, nor the
    twins): :meth:`write` returns False. A value that cannot be encoded is left out and counted
    (``not_encoded``); a failed write (no space left, a file-size limit, an I/O error, a pipe's
    reader gone) ends the file: what the failed write left of its line is cut off again (a
    regular file ends with its last whole line, which :func:`iter_log` needs), the file is
    closed, every later value is counted, not written (``not_written``). :attr:`failure` is one
    line naming the option, the file, the failures and what is missing, or None."""

    def __init__(self, path, encode: Callable[[object], bytes], *, option: str, what: str = "file"):
        self.path = Path(path)
        self.option = option
        self.what = what                      # what the file is, in :attr:`failure`
        self._encode = encode
        try:
            self._file = _open_fifo(self.path) if is_fifo(self.path) else open(self.path, "wb", buffering=0)
        except OSError as exc:
            raise UsageError(f"{option} {str(path)!r}: cannot be opened for writing: {exc.strerror or exc}") from None
        self.count = 0
        self.last_line = b""                  # the last line written (without its newline)
        self.not_encoded = 0
        self.encode_error: tuple | None = None   # (cycle, one line) of the first value left out
        self.not_written = 0
        self.io_error: tuple | None = None       # (cycle, one line): the failure that ended the file
        self.new_failure: tuple | None = None    # after write: ("io" | "encode", one line) when it was the first of its kind
        self._end_offset = 0                     # the file's size after its last whole line

    @property
    def io_failed(self) -> bool:
        return self.io_error is not None

    def write(self, value) -> bool:
        """Write ``value`` as one line; False when it was not written (class docstring)."""
        self.new_failure = None
        if self.io_error is not None:
            self.not_written += 1
            return False
        try:
            text = self._encode(value)
        except (ValueError, TypeError, RecursionError) as exc:
            self.not_encoded += 1
            if self.encode_error is None:
                self.encode_error = (_cycle_of(value), one_line(exc))
                self.new_failure = ("encode", self.encode_error[1])
            return False
        line = memoryview(text + b"\n")
        try:
            while line:  # a raw write may take a part of it
                line = line[self._file.write(line):]
        except (OSError, ValueError) as exc:  # ValueError: the file closed under us
            self.not_written += 1
            self.io_error = (_cycle_of(value), one_line(exc))
            self.new_failure = ("io", self.io_error[1])
            self._end()
            return False
        self._end_offset += len(text) + 1
        self.count += 1
        self.last_line = text
        return True

    def _end(self) -> None:
        try:
            os.ftruncate(self._file.fileno(), self._end_offset)  # a regular file: its last whole line
        except (OSError, ValueError):
            pass  # a device, a FIFO, a closed file: nothing to cut
        try:
            self._file.close()
        except OSError:
            pass

    @property
    def failure(self) -> str | None:
        parts = []
        if self.io_error is not None:
            cycle, error = self.io_error
            where = "its close" if cycle == "close" else f"cycle {cycle}" if cycle is not None else "a record of no cycle"
            parts.append(f"{error} at {where}: the file ends there, {self.not_written} records not written")
        if self.encode_error is not None:
            cycle, error = self.encode_error
            parts.append(f"{self.not_encoded} records left out, not encodable (the first at cycle {cycle}: {error})")
        if not parts:
            return None
        return (f"{self.option} {str(self.path)!r}: " + "; ".join(parts)
                + f"; {self.count} records written (the {self.what} is incomplete)")

    def close(self) -> None:
        if not self._file.closed:
            try:
                self._file.close()
            except OSError as exc:
                if self.io_error is None:
                    self.io_error = ("close", one_line(exc))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _cycle_of(value):
    return value.get("cycle") if isinstance(value, dict) else None


def is_fifo(path) -> bool:
    """``path`` names a FIFO (False where it cannot be looked at)."""
    import stat

    try:
        return stat.S_ISFIFO(os.stat(path).st_mode)
    except OSError:
        return False


def _open_fifo(path: Path):
    """A FIFO opened for writing once a reader has it open - polled (``O_NONBLOCK``: ENXIO while
    there is none) rather than blocked in ``open()``: a signal the kernel gives another thread of
    the process (Ctrl-C) never interrupts a blocked ``open()`` of the main thread, so the process
    could not be stopped while it waited; polling runs the interpreter's handlers between tries."""
    import errno
    import time

    while True:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
            break
        except OSError as exc:
            if exc.errno != errno.ENXIO:
                raise
            time.sleep(0.05)
    os.set_blocking(fd, True)
    return os.fdopen(fd, "wb", buffering=0)
