"""``mcap_out.encode``'s per-cycle cache (docs/robotics.md, *Cost*): a cycle whose content an
earlier cycle had is built from that cycle's message parts - the bytes every output (MCAP file,
live server) gets are exactly those of the plain encoding, cycle for cycle, for a run's records
and for hand-made ones the cache must not cover or must tell apart."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

from fusion_center.robotics import mcap_out
from fusion_center.robotics.topics import TopicMap
from taxel_net.scene import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from robotics_helpers import decode_raw_image  # noqa: E402


@pytest.fixture(scope="module")
def demo_records():
    """Records of short demos: matrix57 (decision mode, contact stages), slipping (the slip
    stage's /fusion/slip every cycle)."""
    from fusion_center.commands.demo import run_demo

    out = {}
    for name, cycles in (("matrix57", 150), ("slipping", 80)):
        scene = load_scene(name)
        service, _ = run_demo(scene, cycles, keep_records=True)
        out[name] = (scene, list(service.records))
    return out


def _plain(scene, records):
    """Every record through encode_plain (its own TopicMap: caches apart from encode's)."""
    topics = TopicMap(scene)
    out = []
    for record in records:
        try:
            out.append(mcap_out.encode_plain(topics, record))
        except Exception as exc:  # noqa: BLE001 - compared with encode's failure
            out.append(type(exc))
    return out


def _cached(scene, records, passes=2):
    topics = TopicMap(scene)
    out = []
    for _ in range(passes):  # the second pass: every cycle from the cache
        got = []
        for record in records:
            try:
                got.append(mcap_out.encode(topics, record))
            except Exception as exc:  # noqa: BLE001
                got.append(type(exc))
        out.append(got)
    return topics, out


def test_a_runs_cycles_are_the_plain_encodings_byte_for_byte(demo_records, monkeypatch):
    """Every cycle of the demos, twice over: the same (log time, [(topic, kind, bytes)]) as
    encode_plain's; and the caches are what make them - the JSON texts and the maps are made
    once per distinct content, not once per cycle (none in the second pass)."""
    for name, (scene, records) in demo_records.items():
        expected = _plain(scene, records)
        made = {"json": 0, "maps": 0}
        json_messages, map_images = TopicMap.json_messages, TopicMap.make_map_images

        def counted_json(self, *a, _f=json_messages):
            made["json"] += 1
            return _f(self, *a)

        def counted_maps(self, *a, _f=map_images):
            made["maps"] += 1
            return _f(self, *a)

        monkeypatch.setattr(TopicMap, "json_messages", counted_json)
        monkeypatch.setattr(TopicMap, "make_map_images", counted_maps)
        topics, (first, second) = _cached(scene, records)
        monkeypatch.undo()
        assert first == expected, name
        assert second == expected, name
        assert 0 < len(topics.cycle_parts) < len(records) // 2, (name, len(topics.cycle_parts))
        assert 0 < len(topics.map_parts) < len(records) // 2, (name, len(topics.map_parts))
        assert made == {"json": len(topics.cycle_parts), "maps": len(topics.map_parts)}, name


def _variants(record: dict) -> list[dict]:
    """Records like ``record`` in what the cache keys on, apart in what it does not - each must
    get its own bytes."""
    rules = record["rules"]
    name = next(iter(rules))
    other = dict(rules, **{name: dict(rules[name], U_G=12345.5)})
    states = {"silent": [record["present_nodes"][0] if record["present_nodes"] else 5]}
    return [
        dict(record, cycle=9), dict(record, cycle=10), dict(record, cycle=100000),     # the cycle's width
        dict(record, t=0.999999), dict(record, t=1.0), dict(record, t=12.000001),     # the stamp's seconds
        dict(record, t=0.0),
        dict(record, sync_counter=None), dict(record, closed_after_ms=1e-05),         # json's own texts
        dict(record, late_frames=True), dict(record, bad_frames=3),
        dict(record, rules=other), dict(record, U_G=-1.5), dict(record, truth=None),
        dict(record, present_nodes=[]), dict(record, nodes_by_state=states),
        dict(record, nodes_by_state=states, present_nodes=[]),
        dict(record, n_live=record["n_live"] - 1), dict(record, closed_by="window"),
        dict(record, area=0.123), dict(record, contact_type="point"),
        dict(record, emcy=[{"node": 5, "code": "0x8130", "register": "0x11", "manufacturer": "", "t": 1.0}]),
        dict(record, emcy_dropped=2), dict(record, duplicate_nodes=[7]), dict(record, error="boom"),
        dict(record, slip={"speed": 0.5}), dict(record, slip={"speed": math.nan}),   # NaN: refused both ways
        dict(record, grip={"command_n": 1.0}), dict(record, grasp_truth={"phase": "hold"}),
        dict(record, rules=dict(rules, band={"U_G": [1, 2]})),                       # a list: no key
        {k: v for k, v in record.items() if k != "bad_frames"},                      # a field missing
        {k: v for k, v in record.items() if k != "t_c"},                             # the contact's, too
        dict({k: v for k, v in record.items() if k != "t_c"}, area=0.5),
        dict(record, present_nodes=None), dict(record, rules=None),
        dict(record, U_G=math.nan),
        dict(record, p_h1=_Float(0.25)), dict(record, area=_Float(-0.0)),             # no plain type: no key
        dict(record, slip={"speed": _Float(0.5)}),
    ]


class _Float(float):
    """A float subclass (as numpy's float64 is): no cache key is made of it (topics._exact)."""


def test_hand_made_records_get_their_own_bytes(demo_records):
    """Variants of a run's records in every field the cached parts are keyed on or put around
    them (cycle and time stamp widths, per-cycle numbers, rules, nodes, contact, EMCY, errors,
    the per-cycle topics, fields missing, values no key can hold, NaN): encode gives
    encode_plain's bytes - or its failure - for each, before and after the originals are cached."""
    scene, records = demo_records["matrix57"]
    base = [records[30], records[60], records[100]]
    recs = base + [v for r in base for v in _variants(r)] + base
    expected = _plain(scene, recs)
    _, (first, second) = _cached(scene, recs)
    assert first == expected
    assert second == expected
    assert expected.count(ValueError) >= 2  # the NaN cases failed in both paths (not written as null)


def test_cached_cycles_decode_to_the_records_values(demo_records):
    """Independently of encode_plain: the cached path's JSON reads back as TopicMap.values of
    the record (the plain dicts), and its images carry the cycle's own time stamp."""
    scene, records = demo_records["slipping"]
    topics = TopicMap(scene)
    for _ in range(2):
        for record in records:
            t, messages = mcap_out.encode(topics, record)
            assert t == round(record["t"] * 1e6) * 1000
            images = [p for _, kind, p in messages if kind == mcap_out.IMAGE]
            assert [decode_raw_image(p)["stamp_ns"] for p in images] == [t] * len(topics.pads)
            text = [(topic, _exact_json(p)) for topic, kind, p in messages if kind == mcap_out.JSON_MSG]
            assert text == [(topic, _exact_json(json.dumps(value, separators=(",", ":"))))
                            for topic, value in topics.values(record)]  # number texts too: -0.0, 1.0


def _exact_json(payload: bytes):
    """A JSON text with its numbers kept apart by kind and sign: 1 and 1.0, -0.0 and 0.0 (and
    True) differ; two texts of one float - ``6.1e-06`` (json) and ``6.1e-6`` (orjson, the
    decision log's encoder) - read as one (a test that compared the texts failed on a record
    whose multiplicative U_G was that small)."""
    return json.loads(payload, parse_float=lambda s: ("float", float(s), math.copysign(1.0, float(s))),
                      parse_int=lambda s: ("int", int(s)))


def test_numbers_equal_but_written_apart_keep_their_own_texts(demo_records):
    """A field's value that equals an earlier cycle's in Python but is written apart in JSON
    (p_h1 0.0 / -0.0, n_expected 57 / 57.0, degraded False / 0, a rule's U_G 1 / 1.0, slip
    speed 0.0 / -0.0) gets its own text in encode and in encode_plain, cached or not - as
    json.dumps writes the record's values (compared number text by number text)."""
    scene, records = demo_records["matrix57"]
    base = records[60]
    name = next(iter(base["rules"]))
    pairs = [("p_h1", 0.0, -0.0), ("n_expected", base["n_expected"], float(base["n_expected"])),
             ("degraded", False, 0), ("area", 0.0, -0.0), ("n_live", 3, 3.0)]
    recs = []
    for field, a, b in pairs:
        recs += [dict(base, **{field: a}), dict(base, **{field: b})]
    rule = base["rules"][name]
    recs += [dict(base, rules=dict(base["rules"], **{name: dict(rule, U_G=1)})),
             dict(base, rules=dict(base["rules"], **{name: dict(rule, U_G=1.0)})),
             dict(base, slip={"speed": 0.0}), dict(base, slip={"speed": -0.0})]
    plain = TopicMap(scene)
    cached = TopicMap(scene)
    for _ in range(2):  # the second pass: every text from the caches
        for record in recs:
            want = [(topic, _exact_json(json.dumps(value, separators=(",", ":"))))
                    for topic, value in plain.values(record)]
            for got in (mcap_out.encode_plain(plain, record)[1], mcap_out.encode(cached, record)[1]):
                assert [(topic, _exact_json(p)) for topic, kind, p in got if kind == mcap_out.JSON_MSG] == want


def test_a_miss_keeps_the_map_once(demo_records):
    """The cached path makes a new pattern's map without putting it in TopicMap's own map cache
    (which it never reads): each pattern is kept once."""
    scene, records = demo_records["matrix57"]
    topics = TopicMap(scene)
    for record in records:
        mcap_out.encode(topics, record)
    assert topics.map_parts and not topics._maps
