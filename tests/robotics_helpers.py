"""Readers the robotics tests check the outputs with, independent of the code that writes them:
a protobuf wire-format decoder for ``foxglove.RawImage`` (field numbers of Foxglove's
RawImage.proto), the scene geometry of a taxel map recomputed from the scene file, an MCAP file
read back with the ``mcap`` package's reader, any reader's messages grouped by topic; and
:func:`publish`, hand-made records through the outputs."""

from __future__ import annotations

import struct
from collections.abc import Iterable

import numpy as np

# foxglove.RawImage (foxglove/schemas RawImage.proto): timestamp 1, width 2, height 3, encoding 4,
# step 5, data 6, frame_id 7; google.protobuf.Timestamp: seconds 1, nanos 2
_RAW_IMAGE = {1: "timestamp", 2: "width", 3: "height", 4: "encoding", 5: "step", 6: "data", 7: "frame_id"}


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        b = buf[i]
        i += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return value, i


def _fields(buf: bytes) -> dict[int, object]:
    out: dict[int, object] = {}
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            out[number], i = _varint(buf, i)
        elif wire == 2:
            n, i = _varint(buf, i)
            out[number] = bytes(buf[i:i + n])
            i += n
        elif wire == 5:
            out[number] = struct.unpack_from("<I", buf, i)[0]
            i += 4
        elif wire == 1:
            out[number] = struct.unpack_from("<Q", buf, i)[0]
            i += 8
        else:
            raise ValueError(f"wire type {wire}")
    return out


def decode_raw_image(payload: bytes) -> dict:
    f = _fields(payload)
    out = {name: f.get(number) for number, name in _RAW_IMAGE.items()}
    stamp = _fields(out["timestamp"] or b"")
    out["stamp_ns"] = stamp.get(1, 0) * 1_000_000_000 + stamp.get(2, 0)
    out["encoding"] = (out["encoding"] or b"").decode()
    out["frame_id"] = (out["frame_id"] or b"").decode()
    out["data"] = out["data"] or b""
    return out


def site_grid(scene, taxel_indexes) -> tuple[dict, int, int]:
    """(taxel index -> (row, column), width, height) of the taxels' distinct x / y values."""
    xs = sorted({scene.taxels[i].x for i in taxel_indexes})
    ys = sorted({scene.taxels[i].y for i in taxel_indexes})
    where = {i: (ys.index(scene.taxels[i].y), xs.index(scene.taxels[i].x)) for i in taxel_indexes}
    return where, len(xs), len(ys)


def image_array(img: dict) -> np.ndarray:
    if img["encoding"] == "mono8":
        return np.frombuffer(img["data"], dtype=np.uint8).reshape(img["height"], img["width"])
    assert img["encoding"] == "32FC1"
    return np.frombuffer(img["data"], dtype="<f4").reshape(img["height"], img["width"])


def by_topic(messages: Iterable[tuple[str, object]]) -> dict[str, list]:
    """A reader's ``(topic, message)`` pairs as topic -> its messages, in the order read."""
    out: dict[str, list] = {}
    for topic, message in messages:
        out.setdefault(topic, []).append(message)
    return out


def message_counts(grouped: dict[str, list]) -> dict[str, int]:
    """topic -> how many messages :func:`by_topic` found on it."""
    return {topic: len(messages) for topic, messages in grouped.items()}


def read_mcap(path) -> tuple[object, dict[str, list]]:
    """(summary, topic -> [(log_time, publish_time, payload), ...] in file order)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        grouped = by_topic((channel.topic, (message.log_time, message.publish_time, message.data))
                           for _schema, channel, message in reader.iter_messages(log_time_order=False))
    return summary, grouped


def publish(scene, records, **where) -> dict:
    """Every record through ``RoboticsOutputs(scene, **where)`` (``mcap=``, ``ros2_bag=``), closed:
    its statistics."""
    from fusion_center.robotics.outputs import RoboticsOutputs

    outputs = RoboticsOutputs(scene, **where)
    for record in records:
        outputs.on_cycle(record)
    return outputs.close()
