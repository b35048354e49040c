"""The centre's trace writers (``--log``) and their flush at a cycle's close.

The stream writes the trace in stream order and, when a cycle closes, calls
:func:`flush_to_os`: every frame the writer has taken is then handed to the operating system
(not synced to the disk), so a process killed by SIGKILL loses at most the cycle in flight.
The centre writes the formats that carry every frame and keep a killed run's cycles
(``traces.check_trace_target`` refuses ``.csv``, ``.db``, ``.trc`` and ``.mf4``):

* ``.log``, ``.asc`` (python-can's text writers): the file's buffer is flushed;
* ``.blf`` (:class:`can.BLFWriter`): python-can keeps the frames in an uncompressed buffer and
  writes a LOG_CONTAINER object only when it reaches ``max_container_size`` (128 KiB: tens of
  cycles - a SIGKILL lost 17-33 cycles of matrix57) or at ``stop``; here the buffer is written
  as a container of its own at every cycle's close (its ``_flush``), then the file's buffer is
  flushed. The file header (file size, object count, end time) is still written by ``stop``
  only: the trace of a killed run keeps the header written at its opening, which is how replay
  tells it (read up to its last complete container, :mod:`.traces`); Wireshark reads the
  containers one after the other and does not need the header's sizes.

(python-can's ``.db`` writer inserts from a thread of its own, 500 frames or 0.25 s of quiet at
a time - a SIGKILL lost 3-6 cycles - and appends to a database of an earlier run; ``.mf4``'s
asammdf writes the whole file at ``stop``: two more reasons they are refused.)
"""

from __future__ import annotations

import can


def flush_to_os(writer) -> None:
    """Hand every frame ``writer`` has taken to the operating system (the trace at a cycle's
    close; see the module docstring for each format). Raises what the writer raises (OSError)."""
    if isinstance(writer, can.BLFWriter):
        # python-can's BLFWriter._flush writes at most max_container_size of its buffer as one
        # LOG_CONTAINER object (the rest stays for the next): the whole buffer, container by container
        while writer._buffer_size > 0 and not writer.file.closed:
            writer._flush()
    file = getattr(writer, "file", None)
    if file is not None and not file.closed:
        file.flush()

