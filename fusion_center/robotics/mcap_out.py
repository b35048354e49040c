"""Foxglove messages of a run and the MCAP file (``--mcap FILE``), with the Foxglove SDK
(``foxglove-sdk``, imported as ``foxglove``).

:func:`encode` turns one record (and, in raw mode, its readings) into the cycle's messages -
``foxglove.RawImage`` taxel maps (protobuf) and JSON messages with a JSON schema
(:mod:`.topics`) - once; :class:`FoxgloveSink` logs them on the channels of one SDK context
(the MCAP file's, or the live server's: :mod:`.foxglove_live`), creating a channel the first
time its topic has a message. The MCAP writer is deterministic (zstd chunks compressed on one
thread; the header names the SDK), so the same records make the same file: a replay's MCAP is
the live run's, byte for byte (``tests/test_robotics_mcap.py``).

The file is written as ``FILE.partial`` and renamed onto ``FILE`` when the run ends (a run that
fails leaves no file that looks complete; an earlier ``FILE`` is removed); a FIFO or device is
written in place (:class:`taxel_net.outputs.OutputPath`).
"""

from __future__ import annotations

import os
from pathlib import Path

from taxel_net.errors import UsageError, one_line
from taxel_net.outputs import OutputPath
from .topics import JSON_TOPICS, SCHEMAS, TopicMap, log_time_ns

PROFILE = ""            # MCAP header profile: none of the registry's (the messages are protobuf + JSON)
CHUNK_BYTES = 256 * 1024  # uncompressed chunk size: bounds the work of one chunk's compression

IMAGE, JSON_MSG = 0, 1


def encode(topics: TopicMap, record: dict, readings=None) -> tuple[int, list[tuple[str, int, bytes]]]:
    """(log time ns, [(topic, kind, payload), ...]) of one record, in a fixed order: the taxel
    maps, the readings (raw mode, with ``readings``), then the JSON topics."""
    RawImage, Timestamp = _messages()
    t = log_time_ns(record)
    stamp = Timestamp(sec=t // 1_000_000_000, nsec=t % 1_000_000_000)
    out: list[tuple[str, int, bytes]] = []
    for pad, data in zip(topics.pads, topics.map_images(record)):
        out.append((pad.map_topic, IMAGE, RawImage(timestamp=stamp, frame_id=pad.name, width=pad.width,
                                                   height=pad.height, encoding="mono8", step=pad.width,
                                                   data=data).encode()))
    if readings is not None:
        for pad, data in zip(topics.pads, topics.readings_images(readings)):
            out.append((pad.readings_topic, IMAGE, RawImage(timestamp=stamp, frame_id=pad.name, width=pad.width,
                                                            height=pad.height, encoding="32FC1",
                                                            step=4 * pad.width, data=data).encode()))
    for topic, payload in topics.json_messages(record):
        out.append((topic, JSON_MSG, payload))
    return t, out


_MESSAGE_TYPES: tuple | None = None


def _messages() -> tuple:
    """(RawImage, Timestamp) of the SDK, imported on first use."""
    global _MESSAGE_TYPES  # noqa: PLW0603
    if _MESSAGE_TYPES is None:
        from foxglove.messages import RawImage, Timestamp

        _MESSAGE_TYPES = (RawImage, Timestamp)
    return _MESSAGE_TYPES


class FoxgloveSink:
    """The channels of one SDK context; :meth:`log` writes one cycle's encoded messages."""

    def __init__(self, context, known=()):
        self.context = context
        self.channels: dict[str, object] = {}
        self.messages = 0
        for topic, is_image in known:  # TopicMap.known_topics: open before the first cycle
            self.channel(topic, IMAGE if is_image else JSON_MSG)

    def channel(self, topic: str, kind: int):
        ch = self.channels.get(topic)
        if ch is None:
            import foxglove
            from foxglove.messages import RawImage

            if kind == IMAGE:
                ch = foxglove.Channel(topic, schema=RawImage.get_schema(), message_encoding="protobuf",
                                      context=self.context)
            else:
                ch = foxglove.Channel(topic, schema=SCHEMAS[topic] if topic in JSON_TOPICS else {},
                                      context=self.context)
            self.channels[topic] = ch
        return ch

    def log(self, t: int, messages) -> None:
        for topic, kind, payload in messages:
            self.channel(topic, kind).log(payload, log_time=t)
        self.messages += len(messages)


class _InPlace:
    """A FIFO / device opened for writing, as the SDK's writer wants it (``write``, ``flush``,
    ``seek`` to where it is): written with seeking disabled."""

    def __init__(self, path: Path):
        self._f = open(path, "wb", buffering=0)
        self._pos = 0

    def write(self, data) -> int:
        n = self._f.write(data)
        self._pos += n
        return n

    def flush(self) -> None:
        pass

    def seek(self, offset: int, whence: int = 0) -> int:
        if (whence == os.SEEK_CUR and offset == 0) or (whence == os.SEEK_SET and offset == self._pos):
            return self._pos
        raise OSError("not seekable")

    def close(self) -> None:
        self._f.close()


class McapOutput:
    """``--mcap FILE``: every cycle's messages in one MCAP file (see the module docstring)."""

    def __init__(self, path, *, known=(), option: str = "--mcap"):
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        self.out = OutputPath(path, option=option)  # a directory: UsageError
        self.path = Path(path)
        self.context = foxglove.Context()
        in_place = self.out.in_place
        options = MCAPWriteOptions(compression=MCAPCompression.Zstd, compression_threads=0, profile=PROFILE,
                                   chunk_size=CHUNK_BYTES, disable_seeking=in_place)
        self._stream = None
        try:
            if in_place:
                self._stream = _InPlace(self.out.write_path)
                target = self._stream
            else:
                target = str(self.out.write_path)
            self.writer = foxglove.open_mcap(target, allow_overwrite=True, context=self.context,
                                             writer_options=options)
        except (OSError, RuntimeError, ValueError) as exc:
            self.out.discard_stale()
            raise UsageError(f"{option} {str(path)!r}: cannot be written: {exc}") from None
        self.sink = FoxgloveSink(self.context, known)
        self.closed = False

    def write_metadata(self, name: str, values: dict) -> None:
        try:
            self.writer.write_metadata(name, {str(k): str(v) for k, v in values.items()})
        except (OSError, RuntimeError) as exc:  # the SDK's I/O errors are RuntimeErrors
            raise UsageError(f"--mcap {str(self.path)!r}: cannot be written: {one_line(exc)}") from None

    def log(self, t: int, messages) -> None:
        self.sink.log(t, messages)

    def close(self, ok: bool = True) -> None:
        """Finish the file; ``ok``: rename it onto FILE, else leave ``FILE.partial`` and remove an
        earlier FILE (a failed run's file must not pass for a complete one)."""
        if self.closed:
            return
        self.closed = True
        try:
            self.writer.close()
        finally:
            if self._stream is not None:
                self._stream.close()
        if ok:
            self.out.commit()
        else:
            self.out.discard_stale()
