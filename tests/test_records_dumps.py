"""records.dumpb / dumps (the decision log's line, the Zenoh record's payload, the Foxglove JSON
messages): orjson for plain values, json otherwise (issue 24's cost pass) - checked against the
standard library's json, the encoder the decision log had: the same JSON values (floats bit for
bit), NaN and infinity refused as json refuses them, what json refuses refused alike, ASCII."""

from __future__ import annotations

import dataclasses
import datetime
import enum
import json
import math
import uuid

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from fusion_center.service import records
from fusion_center.service.records import RecordWriter, dumpb, dumps


def reference(value) -> str:
    """The decision log's encoding before orjson (json.dumps, compact, allow_nan=False)."""
    return json.dumps(value, separators=(",", ":"), allow_nan=False)


def same(a, b) -> bool:
    """Equal JSON values with the same types, floats bit for bit (0.0 and -0.0 differ)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return a.hex() == b.hex()
    if isinstance(a, dict):
        return list(a) == list(b) and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return a == b


def as_json(value):
    """What a JSON reader makes of ``value`` (tuples are arrays, keys strings), computed here
    without any encoder."""
    if isinstance(value, dict):
        return {(k if isinstance(k, str) else json.dumps(k)): as_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [as_json(v) for v in value]
    if isinstance(value, float):
        return float(value)  # a numpy float64: its value
    return value


ODD = [
    {"cycle": 1, "t": 1e16, "small": 1e-05, "tiny": 1.5e-07, "neg": -0.0, "f": 1.7587922024243116e-25,
     "sub": 5e-324, "min": 2.2250738585072014e-308, "max": 1.7976931348623157e308, "i64": -2 ** 63, "u64": 2 ** 64 - 1},
    {"ctl": "a\x00b\tc\"d\\e/\x7f\x1f", "empty": {}, "nested": [[], [{}], [1, (2.5, None)]], "t": (1, "x")},
    {"bool": True, "none": None, "ints": [0, -1, 10 ** 30], "floats": [0.1, 2.0, 1 / 3, -1e-300]},
    {"b": 1, "a": 2, "order": {"z": 1, "y": 2}},
    {"scene": "caf\u00e9 \u2013 \U0001f600", "k\u00e9y": 1},  # non-ASCII: json's \u escapes
    {"lone": "\ud800"},                                       # a lone surrogate: json's escape
    {1: "int key", "2": [3], True: None},                     # keys json turns into strings
    {"np": np.float64(0.1), "deep": [[[[[[[[[[[[[[[[[[[[1]]]]]]]]]]]]]]]]]]]]},
]


@pytest.mark.parametrize("record", ODD)
def test_the_same_json_values_as_json_dumps(record):
    text = dumps(record)
    assert text.isascii() and "\n" not in text
    assert dumpb(record) == text.encode()
    assert same(json.loads(text), json.loads(reference(record)))
    assert same(json.loads(text), as_json(record))


@pytest.mark.parametrize("record", ODD[4:])
def test_what_orjson_does_not_write_as_json_would_is_json_s_bytes(record):
    """Non-ASCII text, non-str keys, numpy scalars, nesting: json writes them, as it did."""
    assert dumps(record) == reference(record)


_FLOATS = st.floats(allow_nan=False, allow_infinity=False) | st.sampled_from(
    [-0.0, 0.0, 1e16, 1e-5, 1e-4, 1.5e-7, 5e-324, 2.2250738585072014e-308, 2.225073858507201e-308, 1e22, 0.1,
     123456789012345678.0, 1e15, 9007199254740993.0])
_LEAVES = st.none() | st.booleans() | st.integers(min_value=-2 ** 70, max_value=2 ** 70) | _FLOATS | st.text(max_size=8)
_VALUES = st.recursive(_LEAVES, lambda children: st.lists(children, max_size=5)
                       | st.lists(children, max_size=3).map(tuple)
                       | st.dictionaries(st.text(max_size=6), children, max_size=5), max_leaves=40)


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.text(max_size=8), _VALUES, max_size=12))
def test_generated_records_read_back_equal_floats_bit_for_bit(record):
    text = dumps(record)
    assert text.isascii()
    assert same(json.loads(text), as_json(record))
    assert same(json.loads(text), json.loads(reference(record)))


@settings(max_examples=300, deadline=None)
@given(_FLOATS)
def test_every_float_reads_back_bit_for_bit(x):
    assert json.loads(dumps({"x": x}))["x"].hex() == x.hex()
    assert json.loads(dumps([x]))[0].hex() == x.hex()
    assert float(dumps(x)).hex() == x.hex()


def _nested(bad):
    return [
        bad,
        {"x": bad},
        {"a": None, "b": [1, 2, bad]},
        {"a": "s", "b": (0.5, bad)},
        {"rules": {"additive": {"U_G": 1.0, "p_h1": None}, "llr": {"U_G": bad}}},
        [{"k": [{"deep": [None, bad]}]}],
        {"np": np.float64(bad)},
    ]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nan_and_infinity_are_refused_wherever_they_are(bad):
    """orjson alone writes them as null: a record with one must still raise ValueError, with
    json's message, never become a line with null in it."""
    for value in _nested(bad):
        with pytest.raises(ValueError) as ours:
            dumpb(value)
        with pytest.raises(ValueError) as theirs:
            reference(value)
        assert str(ours.value) == str(theirs.value)


class Colour(enum.Enum):
    RED = 1


@dataclasses.dataclass
class Point:
    x: float


@pytest.mark.parametrize("odd", [np.int64(3), np.float32(0.5), np.bool_(True), Colour.RED, Point(1.0),
                                 datetime.datetime(2026, 1, 1), uuid.UUID(int=1), {1, 2}, b"bytes",
                                 np.zeros(2)])
def test_what_json_refuses_is_refused_alike(odd):
    """orjson serialises enums, dataclasses, datetimes, UUIDs (and numpy with an option) itself:
    the decision log must not start writing what it refused (json's TypeError, its message)."""
    with pytest.raises(TypeError) as ours:
        dumpb({"x": [odd]})
    with pytest.raises(TypeError) as theirs:
        reference({"x": [odd]})
    assert str(ours.value) == str(theirs.value)


def test_a_circular_record_is_refused_as_json_refuses_it():
    record: dict = {"a": []}
    record["a"].append(record)
    with pytest.raises(ValueError, match="Circular reference"):
        dumpb(record)


def test_plain_records_are_written_by_orjson(monkeypatch):
    """The cheap encoder is the one used for what records hold (json, the fallback, made to
    fail here); on main there is only json."""
    def no_json(value):
        raise AssertionError("json's encoder used for a plain record")

    monkeypatch.setattr(records, "_encode", no_json)
    for record in [ODD[0], ODD[1], dict(ODD[2], ints=[0, -1, 2 ** 63]), ODD[3]]:
        assert same(json.loads(dumpb(record)), as_json(record))


@pytest.fixture(scope="module")
def run_records():
    """Records of short demo runs: matrix57 (decision mode), matrix57 raw (forces, centralised
    tests), a grasp scene (grip, slip, grasp truth)."""
    from fusion_center.commands.demo import run_demo
    from taxel_net.scene import load_scene

    out = []
    for name, cycles in (("matrix57", 30), ("matrix57_raw", 20), ("grasp_lift", 50)):
        service, _ = run_demo(load_scene(name), cycles, keep_records=True)
        out += list(service.records)
    return out


def test_a_runs_records_take_orjson_and_read_back_as_jsons(run_records, monkeypatch, tmp_path):
    """Every record of the runs is plain (orjson writes it: json made to fail) and reads back
    as json's line of it reads back, floats bit for bit; the decision log holds those lines."""
    assert len(run_records) == 100 and any("grip" in r for r in run_records) and any("forces" in r for r in run_records)
    expected = [json.loads(reference(r)) for r in run_records]
    with RecordWriter(tmp_path / "log.jsonl") as writer:
        for r in run_records:
            writer.write(r)
    monkeypatch.setattr(records, "_encode", lambda value: (_ for _ in ()).throw(AssertionError("json used")))
    lines = (tmp_path / "log.jsonl").read_bytes().splitlines()
    assert lines == [dumpb(r) for r in run_records]
    for line, want in zip(lines, expected):
        assert same(json.loads(line), want)


def test_the_writer_writes_those_lines(tmp_path):
    with RecordWriter(tmp_path / "log.jsonl") as writer:
        for record in ODD:
            writer.write(record)
    raw = (tmp_path / "log.jsonl").read_bytes()
    assert raw.isascii()
    lines = raw.decode().splitlines()
    assert lines == [dumps(r) for r in ODD]
    assert all(same(json.loads(line), json.loads(reference(r))) for line, r in zip(lines, ODD))


def test_a_record_with_nan_is_not_written(tmp_path):
    """The writer leaves it out (False; counted, ``failure`` says so: the service logs it) and
    writes nothing of that record."""
    with RecordWriter(tmp_path / "log.jsonl") as writer:
        assert writer.write({"cycle": 0})
        assert not writer.write({"cycle": 1, "U_G": math.nan})
        assert writer.write({"cycle": 2})
    assert (tmp_path / "log.jsonl").read_bytes() == b'{"cycle":0}\n{"cycle":2}\n'
    assert writer.not_encoded == 1 and "at cycle 1" in writer.failure
