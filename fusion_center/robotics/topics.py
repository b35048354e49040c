"""The record -> message mapping shared by the MCAP file, the live Foxglove server and the ROS 2
bag (docs/robotics.md): which topics a scene has, the taxel maps as images, and the per-cycle
messages as plain values.

Pure: a function of the scene and of one decision-log record (``fusion_center.service.records``)
plus, in raw mode, the cycle's readings; so a replay, which makes the same records, makes the
same messages. What does not change from cycle to cycle - the pads and their pixel of every
taxel, the label -> taxel tables, the topic list, the JSON schemas - is computed once per scene
(:class:`TopicMap`); a taxel map is cached per (present taxels, taxels not heard) pattern, as
the pipeline caches its rules per decision vector.

**Time.** Every message of a cycle has the cycle's SYNC time as its log time: the record's
``t`` (seconds since the first CAN event of the run, on the stream's clock, identical in
replay) in integer nanoseconds, :func:`log_time_ns`. The epoch is therefore the run's first
event, not 1970: a viewer shows a run as starting near 0 s (Foxglove: 1970-01-01 00:00:00).

**Taxel maps.** One image per *pad*: the taxels of a jaw (``jaw = "left"`` / ``"right"``) in a
gripper scene, else the whole sensor (``sensor``; taxels without a jaw in a gripper scene too).
With coordinates (every taxel of the pad has ``x``, ``y``) column c is the c-th distinct ``x``
and row r the r-th distinct ``y`` of the pad, ascending (a regular layout - skin4096's 64 x 64 at
5 mm - is its own grid; matrix57's sites are 10 x 11, its R cells in pairs on one site); without,
one row in scene order. A cell's value in the ``map`` image (``mono8``): :data:`MAP_NONE` no
taxel there, :data:`MAP_NOT_HEARD` its node did not take part (``nodes_by_state``: missing,
silent, stopped ...), :data:`MAP_ABSENT` heard, no object, :data:`MAP_PRESENT` present
(``present_nodes``); taxels sharing a site show the highest of their values. The ``readings``
image (raw mode, ``32FC1``): X_i in mV, the mean of a site's readings, NaN where none.
"""

from __future__ import annotations

import math
from marshal import dumps as _marshal
from operator import itemgetter
from dataclasses import dataclass

import numpy as np

from taxel_net.scene import Scene
from ..service.records import dumpb as _dumpb, dumps as _json  # the decision log's encoder (below)

MAP_NONE, MAP_NOT_HEARD, MAP_ABSENT, MAP_PRESENT = 0, 85, 170, 255
DECISION_CODE = {"H1": 1, "H0": 0, "undecided": -1}
TRUTH_CODE = {"H1": 1, "H0": 0}

# topic names (docs/robotics.md); pads: /taxel/<pad>/map, /taxel/<pad>/readings
T_DECISION = "/fusion/decision"
T_CONTACT = "/fusion/contact"
T_SLIP = "/fusion/slip"
T_FORCES = "/fusion/forces"
T_GRIP = "/grip"
T_TRUTH = "/world/truth"
T_BUS = "/bus"


def log_time_ns(record: dict) -> int:
    """The cycle's SYNC time in integer ns since the run's first CAN event (``t`` is kept to the
    µs); a hand-made record's negative ``t`` is 0 (MCAP and ROS times are unsigned)."""
    return max(0, int(round(float(record.get("t") or 0.0) * 1e6)) * 1000)


def rule_key(name: str) -> str:
    """A rule's name as a field name viewers' message paths take (``k-of-n`` -> ``k_of_n``)."""
    key = _RULE_KEYS.get(name)
    if key is None:
        key = _RULE_KEYS[name] = name.replace("-", "_")
    return key


@dataclass(frozen=True)
class Pad:
    """One taxel map: ``name``, the scene taxel indexes it shows, the pixel of each
    (``cells``, row-major index) and the image size."""

    name: str
    taxels: np.ndarray   # int: scene taxel indexes, scene order
    cells: np.ndarray    # int: pixel index (row * width + column) of each taxel
    width: int
    height: int
    cell_mm: tuple       # (x, y) median spacing of the distinct coordinates, mm (None without coordinates)
    shared_sites: bool = False  # some taxels share a pixel (matrix57's R pairs)

    @property
    def map_topic(self) -> str:
        return f"/taxel/{self.name}/map"

    @property
    def readings_topic(self) -> str:
        return f"/taxel/{self.name}/readings"


def _pads(scene: Scene) -> list[Pad]:
    groups: dict[str, list[int]] = {}
    for i, t in enumerate(scene.taxels):
        groups.setdefault(t.jaw or "sensor", []).append(i)
    order = [name for name in ("sensor", "left", "right") if name in groups]
    order += sorted(name for name in groups if name not in order)
    pads = []
    for name in order:
        idx = np.array(groups[name], dtype=np.int64)
        taxels = [scene.taxels[i] for i in idx]
        if all(t.x is not None and t.y is not None for t in taxels):
            xs = sorted({float(t.x) for t in taxels})
            ys = sorted({float(t.y) for t in taxels})
            col = {x: c for c, x in enumerate(xs)}
            row = {y: r for r, y in enumerate(ys)}
            cells = np.array([row[float(t.y)] * len(xs) + col[float(t.x)] for t in taxels], dtype=np.int64)
            spacing = tuple(float(np.median(np.diff(v))) if len(v) > 1 else 1.0 for v in (xs, ys))
            pads.append(Pad(name, idx, cells, len(xs), len(ys), spacing, len(np.unique(cells)) < len(cells)))
        else:
            pads.append(Pad(name, idx, np.arange(len(idx), dtype=np.int64), len(idx), 1, None))
    return pads


class TopicMap:
    """Per scene: the pads, the topics and what each record becomes (see the module docstring)."""

    def __init__(self, scene: Scene):
        from ..service.pipeline import node_labels, taxel_labels
        from taxel_net.patches import devices

        self.scene = scene
        self.name = scene.name
        self.raw_mode = scene.bus.mode == "raw"
        self.hold = scene.bus.transmission_type != 1
        self.pads = _pads(scene)
        labels = taxel_labels(scene)
        self.taxel_of = {label: i for i, label in enumerate(labels)}
        # a node's label -> the taxels it hosts (nodes_by_state names nodes; patch scenes: devices)
        if scene.bus.patch_nodes:
            self.node_taxels = {label: np.array(d.taxels, dtype=np.int64)
                                for label, d in zip(node_labels(scene), devices(scene))}
        else:
            self.node_taxels = {label: np.array([i]) for i, label in enumerate(labels)}
        self.n = scene.n
        self._maps: dict = {}
        self._decision_cache: dict = {}
        self._contact_cache: dict = {}
        self._bus_cache: dict = {}
        self._flat_cache: dict = {}
        self.cycle_parts: dict = {}  # mcap_out.encode's: a cycle's shared JSON parts per content
        self.map_parts: dict = {}    # mcap_out.encode's: the maps' images but their stamp, per pattern
        self.known_topics = self._known_topics()

    def _known_topics(self) -> list[tuple[str, bool]]:
        """``(topic, is_image)`` of the topics the scene's records will have, by its stage plan
        (opened at start, so a live viewer sees them before the first cycle; a topic a record
        carries beyond these - ``/grip`` - opens with its first message)."""
        from ..stages import plan_stages

        run = plan_stages(self.scene).run
        out = [(p.map_topic, True) for p in self.pads]
        if self.raw_mode:
            out += [(p.readings_topic, True) for p in self.pads]
        out += [(T_DECISION, False), (T_BUS, False)]
        if "area" in run or "contact_type" in run:
            out.append((T_CONTACT, False))
        if "slip" in run:
            out.append((T_SLIP, False))
        if "forces" in run and self.raw_mode:
            out.append((T_FORCES, False))
        if getattr(self.scene, "gripper", None) is not None:  # the grip stage (issue 23) reports it
            out.append((T_GRIP, False))
        if getattr(self.scene, "grasp", None) is not None:   # the grasp world's truth (issue 23)
            out.append((T_TRUTH, False))
        return out

    # ------------------------------------------------------------------ taxel maps
    def taxel_codes(self, record: dict) -> np.ndarray:
        """uint8 per scene taxel: MAP_PRESENT / MAP_ABSENT / MAP_NOT_HEARD from the record."""
        codes = np.full(self.n, MAP_ABSENT, dtype=np.uint8)
        for labels in (record.get("nodes_by_state") or {}).values():
            for label in labels:
                idx = self.node_taxels.get(label)
                if idx is not None:
                    codes[idx] = MAP_NOT_HEARD
        present = [self.taxel_of[label] for label in record.get("present_nodes") or () if label in self.taxel_of]
        codes[present] = MAP_PRESENT
        return codes

    def map_images(self, record: dict, states_key=None) -> list[bytes]:
        """The ``mono8`` map of every pad (row-major, ``width`` bytes a row), cached per pattern
        (``states_key``: :func:`_states_key` of the record's ``nodes_by_state``, when the caller has it)."""
        if states_key is None:
            states_key = _states_key(record.get("nodes_by_state"))
        present = record.get("present_nodes")
        key = (tuple(present) if present else (), states_key)
        images = self._maps.get(key)
        if images is None:
            images = _remember(self._maps, key, self.make_map_images(record))
        return images

    def make_map_images(self, record: dict) -> list[bytes]:
        """:meth:`map_images` made anew, kept nowhere (``mcap_out.encode`` keeps its own)."""
        codes = self.taxel_codes(record)
        images = []
        for pad in self.pads:
            img = np.zeros(pad.width * pad.height, dtype=np.uint8)
            if pad.shared_sites:  # taxels on one site: the highest value
                np.maximum.at(img, pad.cells, codes[pad.taxels])
            else:
                img[pad.cells] = codes[pad.taxels]
            images.append(img.tobytes())
        return images

    def readings_of(self, closed) -> np.ndarray | None:
        """The readings a raw-mode record was made from (held ones where the pipeline holds)."""
        if not self.raw_mode or closed is None or getattr(closed, "readings", None) is None:
            return None
        readings = closed.readings
        if self.hold:
            readings = np.where(np.isnan(readings) & ~closed.missing, closed.held_readings, readings)
        return readings

    def readings_images(self, readings: np.ndarray) -> list[bytes]:
        """The ``32FC1`` image of every pad: mean reading (mV) per site, NaN where none."""
        out = []
        for pad in self.pads:
            values = readings[pad.taxels]
            ok = ~np.isnan(values)
            size = pad.width * pad.height
            sums = np.bincount(pad.cells[ok], weights=values[ok], minlength=size)
            counts = np.bincount(pad.cells[ok], minlength=size)
            with np.errstate(invalid="ignore", divide="ignore"):
                img = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
            out.append(img.astype("<f4").tobytes())
        return out

    # ------------------------------------------------------------------ per-cycle values
    def json_messages(self, record: dict, states_key=None) -> list[tuple[str, bytes]]:
        """:meth:`values` as JSON (UTF-8 bytes): the same values, made cheaply. What repeats from
        cycle to cycle is encoded once per distinct content and kept (at most 1024 entries each):
        ``/fusion/decision`` but its ``cycle`` (a function of the decision vector, the truth and
        the rules' results, which the pipeline itself caches per vector), ``/fusion/contact``,
        ``/bus`` but its per-cycle numbers (per nodes-by-state pattern: ``states_key``, the
        record's :func:`_states_key`, when the caller has made it for the map too), and the
        ``slip`` / ``grip`` / ``forces`` objects whose values are scalars. Keys are the values'
        texts (:func:`_exact`): values equal in Python but written apart (1, 1.0 and True; 0.0 and
        -0.0) never share a text."""
        get = record.get
        cycle = _scalar(get("cycle"))
        out = [(T_DECISION, self._decision_json(record, cycle)), (T_BUS, self._bus_json(record, cycle, states_key))]
        if "area" in record or "contact_type" in record:
            try:
                values = _contact_key(record)
            except KeyError:
                values = tuple([get(k) for k in _CONTACT_KEYS])
            try:
                key = _exact(values)
            except ValueError:  # no plain value: not cached
                key = None
            text = self._contact_cache.get(key)
            if text is None:
                text = _dumpb(contact_message(record))
                if key is not None:
                    _remember(self._contact_cache, key, text)
            out.append((T_CONTACT, text))
        for topic, key in ((T_SLIP, "slip"), (T_FORCES, "forces"), (T_GRIP, "grip")):
            value = get(key)
            if isinstance(value, dict):
                out.append((topic, self._flat_json(value)))
        if isinstance(get("grasp_truth"), dict):
            out.append((T_TRUTH, _dumpb(truth_message(record))))
        return out

    def _flat_json(self, value: dict) -> bytes:
        """A record's ``slip`` / ``grip`` / ``forces`` as JSON, cached per content when its values
        are scalars (a slip stage's result repeats while nothing slides); nested ones encoded."""
        try:
            hash(tuple(value.items()))
            key = _exact(value)
        except (TypeError, ValueError):  # a list or dict inside (forces' per-taxel values), no plain value
            return _dumpb(value)
        text = self._flat_cache.get(key)
        if text is None:
            text = _remember(self._flat_cache, key, _dumpb(value))
        return text

    def _decision_json(self, record: dict, cycle: str) -> bytes:
        rules = record.get("rules") or {}
        try:
            flat = _decision_key(record)
        except KeyError:  # a hand-made record without some field
            flat = tuple([record.get(k) for k in _DECISION_KEYS])
        try:
            key = _exact((flat, rules))
        except ValueError:  # no plain value: not cached
            key = None
        body = self._decision_cache.get(key)
        if body is None:
            value = decision_message(record)
            del value["cycle"]
            body = _dumpb(value)[1:]  # b'"decide_with":...}'
            if key is not None:
                _remember(self._decision_cache, key, body)
        return b'{"cycle":' + cycle.encode() + b"," + body

    def _bus_json(self, record: dict, cycle: str, states_key=None) -> bytes:
        get = record.get
        if get("emcy") or get("duplicate_nodes") or get("error") is not None or get("emcy_dropped"):
            return _dumpb(bus_message(record))
        states = get("nodes_by_state")
        if states and states_key is None:
            states_key = _states_key(states)
        try:
            values = _bus_key(record)
        except KeyError:
            values = (get("closed_by"), get("n_expected"), get("n_live"), get("n_received"))
        try:
            key = (_exact(values), states_key if states else ())
            stable = self._bus_cache.get(key)
        except (TypeError, ValueError):  # a label that is no scalar (a hand-made record)
            return _dumpb(bus_message(record))
        if stable is None:
            stable = _remember(self._bus_cache, key, (
                f',"closed_by":{_json(values[0])},"n_expected":{_scalar(values[1])},"n_live":{_scalar(values[2])},'
                f'"n_received":{_scalar(values[3])},"emcy_count":0,"emcy":[],'
                f'"not_taking_part":{sum(len(v) for v in states.values()) if states else 0},'
                f'"nodes_by_state":{_json(states) if states else "{}"},"duplicate_nodes":[],"error":null}}'))
        return (f'{{"cycle":{cycle},"sync_counter":{_scalar(get("sync_counter"))},'
                f'"closed_after_ms":{_scalar(get("closed_after_ms"))},"late_frames":{_scalar(get("late_frames"))},'
                f'"bad_frames":{_scalar(get("bad_frames"))}' + stable).encode()

    def values(self, record: dict, *, rules: bool = True) -> list[tuple[str, dict]]:
        """The JSON messages of one record: ``[(topic, dict), ...]`` in a fixed order; a topic
        whose data the record does not carry (no slip stage, no grip) is left out."""
        out = [(T_DECISION, decision_message(record, rules=rules)), (T_BUS, bus_message(record))]
        if "area" in record or "contact_type" in record:
            out.append((T_CONTACT, contact_message(record)))
        for topic, key in ((T_SLIP, "slip"), (T_FORCES, "forces"), (T_GRIP, "grip")):
            if isinstance(record.get(key), dict):
                out.append((topic, record[key]))
        truth = truth_message(record)
        if truth is not None:
            out.append((T_TRUTH, truth))
        return out


def decision_message(record: dict, *, rules: bool = True) -> dict:
    """``/fusion/decision``: the deciding rule's U_G against its threshold, the decision (and
    as a number: H1 1, H0 0, undecided -1), P(H1), the truth, every rule's result as the record
    has it under ``rules`` (names with ``_`` for ``-``: ``k_of_n``) and each rule's decision as a
    number under ``rule_decisions``."""
    decision = record.get("decision", "undecided")
    u_g, threshold = record.get("U_G"), record.get("threshold")
    truth = record.get("truth")
    out = {
        "cycle": record.get("cycle"),
        "decide_with": record.get("decide_with"),
        "decision": decision,
        "decision_code": DECISION_CODE.get(decision, -1),
        "U_G": u_g,
        "threshold": threshold,
        "margin": _difference(u_g, threshold),
        "p_h1": record.get("p_h1"),
        "present_count": record.get("present_count"),
        "n_received": record.get("n_received"),
        "n_expected": record.get("n_expected"),
        "degraded": record.get("degraded"),
        "truth": truth,
        "truth_code": TRUTH_CODE.get(truth),
    }
    if rules:  # (json_messages adds them itself, cached)
        out["rule_decisions"], out["rules"] = _rules_parts(record.get("rules") or {})
    return out


def _rules_parts(rules: dict) -> tuple[dict, dict]:
    codes, renamed = {}, {}
    for name, result in rules.items():
        key = _RULE_KEYS.get(name) or rule_key(name)
        renamed[key] = result
        codes[key] = DECISION_CODE.get(result.get("decision"), -1)
    return codes, renamed


_RULE_KEYS: dict[str, str] = {}
# every message's JSON is the decision log's encoder (orjson for plain values, json otherwise:
# compact, ASCII, NaN refused): _dumpb for bytes, _json for text (imported above)


def bus_message(record: dict) -> dict:
    """``/bus``: how the cycle closed and when (SYNC -> closing event, ms), nodes taking part,
    late and malformed frames since the previous cycle, EMCY, nodes by state (counts and labels)."""
    states = record.get("nodes_by_state") or {}
    return {
        "cycle": record.get("cycle"),
        "sync_counter": record.get("sync_counter"),
        "closed_by": record.get("closed_by"),
        "closed_after_ms": record.get("closed_after_ms"),
        "n_expected": record.get("n_expected"),
        "n_live": record.get("n_live"),
        "n_received": record.get("n_received"),
        "late_frames": record.get("late_frames"),
        "bad_frames": record.get("bad_frames"),
        "emcy_count": len(record.get("emcy") or ()) + int(record.get("emcy_dropped") or 0),
        "emcy": record.get("emcy") or [],
        "not_taking_part": sum(len(v) for v in states.values()),
        "nodes_by_state": states,
        "duplicate_nodes": record.get("duplicate_nodes") or [],
        "error": record.get("error"),
    }


def contact_message(record: dict) -> dict:
    """``/fusion/contact``: area (eq 35), t_c / fp_c and the contact types (eqs 34a/b) the
    record has, and the number of present taxels."""
    out = {k: record[k] for k in _CONTACT_KEYS[:-1] if k in record}
    out["present_count"] = record.get("present_count")
    return out


def truth_message(record: dict) -> dict | None:
    """``/world/truth``, in grasp scenes (records with ``grasp_truth``): the simulated world's
    state - phase, normal force, minimum hold force, slipping, slid distance, dropped, crushed -
    with the object's presence (``truth``, as ``/fusion/decision`` has it in every scene)."""
    grasp = record.get("grasp_truth")
    if not isinstance(grasp, dict):
        return None
    truth = record.get("truth")
    return {"truth": truth, "truth_code": TRUTH_CODE.get(truth), **grasp}


_DECISION_KEYS = ("decide_with", "decision", "U_G", "threshold", "p_h1", "present_count", "n_received",
                  "n_expected", "degraded", "truth")
_CONTACT_KEYS = ("area", "t_c", "contact_type", "fp_c", "contact_type_fp", "present_count")
# the cache keys of a record with every field (one C call; a record without some field: KeyError,
# then the same tuple made with get)
_decision_key = itemgetter(*_DECISION_KEYS)
_contact_key = itemgetter(*_CONTACT_KEYS)
_bus_key = itemgetter("closed_by", "n_expected", "n_live", "n_received")


def _states_key(states) -> tuple:
    """A record's ``nodes_by_state`` as a hashable key (labels in order), () when empty."""
    return tuple([(k, tuple(v)) for k, v in states.items()]) if states else ()


def _scalar(value) -> str:
    """JSON of one int, float or None as json writes it (a float's repr); anything else via json."""
    cls = value.__class__
    if cls is int:
        return str(value)
    if cls is float and math.isfinite(value):
        return repr(value)
    if value is None:
        return "null"
    return _json(value)


def _exact(value) -> bytes:
    """A cache key of plain values (str, int, float, bool, None; tuples, lists and dicts of them)
    as exact as their JSON: their ``marshal`` bytes (format 2: no back-references, so the same
    values make the same bytes) - a float's 8 bytes with its sign (``-0.0``) and each number's
    type (``1`` / ``1.0`` / ``True``), which ``==`` and ``hash`` do not tell apart: two values
    whose JSON differs never share a cached text. One C call (``repr`` would be exact too, but
    writing the floats costs several times more). Only made, never loaded.
    ValueError: a value of another type (the caller does not cache it)."""
    return _marshal(value, 2)


def _remember(cache: dict, key, value):
    if len(cache) > 1024:
        cache.clear()
    cache[key] = value
    return value


def _difference(a, b):
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        d = float(a) - float(b)
        return d if math.isfinite(d) else None
    return None


# JSON schemas (jsonschema, the encoding Foxglove and the MCAP registry name for JSON channels):
# the fields a viewer plots; records may carry more (every rule's own fields), JSON Schema allows them
_NUM = {"type": ["number", "null"]}
_INT = {"type": ["integer", "null"]}
_STR = {"type": ["string", "null"]}
SCHEMAS = {
    T_DECISION: {"title": "taxel_can.Decision", "type": "object", "properties": {
        "cycle": _INT, "decide_with": _STR, "decision": _STR, "decision_code": _INT, "U_G": _NUM,
        "threshold": _NUM, "margin": _NUM, "p_h1": _NUM, "present_count": _INT, "n_received": _INT,
        "n_expected": _INT, "degraded": {"type": ["boolean", "null"]}, "truth": _STR, "truth_code": _INT,
        "rule_decisions": {"type": "object", "additionalProperties": _INT},
        "rules": {"type": "object", "additionalProperties": {"type": "object"}}}},
    T_BUS: {"title": "taxel_can.Bus", "type": "object", "properties": {
        "cycle": _INT, "sync_counter": _INT, "closed_by": _STR, "closed_after_ms": _NUM, "n_expected": _INT,
        "n_live": _INT, "n_received": _INT, "late_frames": _INT, "bad_frames": _INT, "emcy_count": _INT,
        "emcy": {"type": "array"}, "not_taking_part": _INT, "nodes_by_state": {"type": "object"},
        "duplicate_nodes": {"type": "array"}, "error": _STR}},
    T_CONTACT: {"title": "taxel_can.Contact", "type": "object", "properties": {
        "area": _NUM, "t_c": _NUM, "contact_type": _STR, "fp_c": _NUM, "contact_type_fp": _STR,
        "present_count": _INT}},
    T_SLIP: {"title": "taxel_can.Slip", "type": "object", "properties": {
        "contact": {"type": ["boolean", "null"]}, "observed": {"type": ["boolean", "null"]},
        "slipping": {"type": ["boolean", "null"]}, "criterion": _STR,
        "force_ratio": _NUM, "onset_cycle": _INT, "speed": _NUM, "distance": _NUM}},
    T_FORCES: {"title": "taxel_can.Forces", "type": "object", "properties": {
        "unit": _STR, "total_tangential": _NUM, "grip_force": _NUM, "grip_force_limit": _NUM, "max_load": _NUM,
        "per_taxel": {"type": "object"}, "tangential_per_jaw": {"type": "object"},
        "grip_force_per_cell": {"type": "object"}}},
    T_GRIP: {"title": "taxel_can.Grip", "type": "object", "properties": {
        "command_n": _NUM, "actual_n": _NUM, "drive_state": _STR, "grip_state": _STR,
        "slip": {"type": ["boolean", "null", "object"]}}},
    T_TRUTH: {"title": "taxel_can.Truth", "type": "object", "properties": {
        "truth": _STR, "truth_code": _INT, "phase": _STR, "normal_n": _NUM, "min_hold_n": _NUM,
        "slipping": {"type": ["boolean", "null"]}, "slid_mm": _NUM, "dropped": {"type": ["boolean", "null"]},
        "crushed": {"type": ["boolean", "null"]}}},
}
JSON_TOPICS = (T_DECISION, T_BUS, T_CONTACT, T_SLIP, T_FORCES, T_GRIP, T_TRUTH)
