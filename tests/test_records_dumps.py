"""records.dumps (the decision log's line, the Zenoh record's payload) is json.dumps with the
log's settings, byte for byte, made with one encoder for the run (issue 24's cost pass)."""

from __future__ import annotations

import json
import math

import pytest

from fusion_center.service.records import RecordWriter, dumps


ODD = [
    {"cycle": 1, "t": 1e16, "small": 1e-05, "neg": -0.0, "big": 2 ** 70, "f": 1.7587922024243116e-25},
    {"scene": "caf\u00e9 \u2013 \U0001f600", "ctl": "a\x00b\tc\"d\\e/", "empty": {}, "nested": [[], [{}], [1, [2.5]]]},
    {"bool": True, "none": None, "ints": [0, -1, 10 ** 30], "floats": [0.1, 2.0, 1 / 3, -1e-300]},
    {"b": 1, "a": 2, "order": {"z": 1, "y": 2}},
]


@pytest.mark.parametrize("record", ODD)
def test_the_same_text_as_json_dumps(record):
    assert dumps(record) == json.dumps(record, separators=(",", ":"), allow_nan=False)
    assert json.loads(dumps(record)) == record


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nan_and_infinity_are_refused(bad):
    with pytest.raises(ValueError):
        dumps({"x": [bad]})


def test_the_writer_writes_those_lines(tmp_path):
    with RecordWriter(tmp_path / "log.jsonl") as writer:
        for record in ODD:
            writer.write(record)
    lines = (tmp_path / "log.jsonl").read_text(encoding="utf-8").splitlines()
    assert lines == [json.dumps(r, separators=(",", ":"), allow_nan=False) for r in ODD]
