"""The centre's trace writers (``--log``) and their flush at a cycle's close.

The stream writes the trace in stream order and, when a cycle closes, calls
:func:`flush_to_os`: every frame the writer has taken is then handed to the operating system
(not synced to the disk), so a process killed by SIGKILL loses at most the cycle in flight -
whatever the format:

* ``.log``, ``.asc``, ``.trc``, ``.csv`` (python-can's text writers): the file's buffer is
  flushed;
* ``.blf`` (:class:`can.BLFWriter`): python-can keeps the frames in an uncompressed buffer and
  writes a LOG_CONTAINER object only when it reaches ``max_container_size`` (128 KiB: tens of
  cycles) or at ``stop``; here the buffer is written as a container of its own at every cycle's
  close (its ``_flush``), then the file's buffer is flushed. The file header (file size,
  object count, end time) is still written by ``stop`` only: the trace of a killed run keeps the
  header written at its opening, which is how replay tells it (read up to its last complete
  container, :mod:`.traces`); Wireshark reads the containers one after the other and does not
  need the header's sizes;
* ``.db``: :class:`SqliteTraceWriter` (python-can's :class:`can.SqliteWriter` inserts from a
  thread of its own, 500 frames or 0.25 s of quiet at a time - a SIGKILL lost 3-6 cycles of
  matrix57 - and appends to a database of an earlier run);
* ``.mf4`` (:class:`can.MF4Writer`, with asammdf): nothing to flush - asammdf writes the
  whole file at ``stop`` (``MDF.save``): a killed run leaves an empty ``.mf4``.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

import can
from can.io.generic import MessageWriter

# python-can's SQLite schema (can.SqliteWriter), which can.SqliteReader reads back
SQLITE_TABLE = "messages"
_SQLITE_COLUMNS = ("ts REAL, arbitration_id INTEGER, extended INTEGER, remote INTEGER, error INTEGER, "
                   "dlc INTEGER, data BLOB")
SQLITE_PENDING_MAX = 4096  # rows kept before they are inserted (into the open transaction)


class SqliteTraceWriter(MessageWriter):
    """The ``.db`` trace: python-can's SQLite schema (table ``messages``, the columns of
    :class:`can.SqliteWriter`, read back by :class:`can.SqliteReader` in insertion order),
    written by the thread that writes the trace, one transaction a cycle, committed by
    :meth:`flush` (:func:`flush_to_os`, at the cycle's close).

    The file is the trace of this run: a table ``messages`` of an earlier one is replaced (as
    the other formats truncate their file; :class:`can.SqliteWriter` appends to it). Journal
    ``DELETE`` (one file, as the other formats), ``synchronous=OFF``: a commit hands the pages
    to the operating system without syncing them to the disk, as the other formats' flush (a
    process killed mid-commit leaves a ``-journal`` beside the file, which the next reader rolls
    back: that cycle is lost; a power cut may leave the database corrupt).

    Calls are serialised by the caller (the stream's trace lock); any thread may make them.
    """

    def __init__(self, file, table_name: str = SQLITE_TABLE, **kwargs) -> None:
        super().__init__(file, **kwargs)
        self.table_name = table_name
        self._conn = sqlite3.connect(str(Path(file)), check_same_thread=False, isolation_level=None)
        try:
            self._conn.execute("PRAGMA synchronous=OFF")
            self._conn.execute("BEGIN")
            self._conn.execute(f"DROP TABLE IF EXISTS {table_name}")
            self._conn.execute(f"CREATE TABLE {table_name} ({_SQLITE_COLUMNS})")
            self._conn.execute("COMMIT")
        except BaseException:
            self._conn.close()
            raise
        self._insert = f"INSERT INTO {table_name} VALUES (?, ?, ?, ?, ?, ?, ?)"
        self._pending: list[tuple] = []
        self._in_transaction = False
        self._uncommitted = 0
        self.num_frames = 0  # committed (as can.SqliteWriter's)

    def on_message_received(self, msg: can.Message) -> None:
        self._pending.append((msg.timestamp, msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
                              msg.is_error_frame, msg.dlc, bytes(msg.data)))
        if len(self._pending) >= SQLITE_PENDING_MAX:
            self._insert_pending()

    def _insert_pending(self) -> None:
        if not self._pending:
            return
        if not self._in_transaction:
            self._conn.execute("BEGIN")
            self._in_transaction = True
        rows, self._pending = self._pending, []
        self._conn.executemany(self._insert, rows)
        self._uncommitted += len(rows)

    def flush(self) -> None:
        """Insert the frames taken since the last flush and commit them (one transaction)."""
        self._insert_pending()
        if self._in_transaction:
            self._conn.execute("COMMIT")
            self._in_transaction = False
            self.num_frames += self._uncommitted
            self._uncommitted = 0

    def stop(self) -> None:
        try:
            self.flush()
        finally:
            self._conn.close()


def flush_to_os(writer) -> None:
    """Hand every frame ``writer`` has taken to the operating system (the trace at a cycle's
    close; see the module docstring for each format). Raises what the writer raises (OSError,
    sqlite3.Error...)."""
    if isinstance(writer, can.BLFWriter):
        # python-can's BLFWriter._flush writes at most max_container_size of its buffer as one
        # LOG_CONTAINER object (the rest stays for the next): the whole buffer, container by container
        while writer._buffer_size > 0 and not writer.file.closed:
            writer._flush()
    elif isinstance(writer, SqliteTraceWriter):
        writer.flush()
        return
    file = getattr(writer, "file", None)
    if file is not None and not file.closed:
        file.flush()


def open_writer(path) -> MessageWriter:
    """python-can's writer for ``path``'s extension (``can.Logger``), but ``.db``:
    :class:`SqliteTraceWriter`."""
    p = Path(path)
    if p.suffix.lower() == ".db":
        return SqliteTraceWriter(p)
    return can.Logger(str(p))
