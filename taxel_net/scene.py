"""Scene files (TOML): the taxels, the object/contact model, the bus, the rules and outputs.

The format is specified in ``docs/scene-format.md``. This module holds the typed,
validated form (frozen dataclasses) and ``load_scene``; every field error raises
:class:`taxel_net.errors.SceneError` naming the file, the field and the value.
This is I/O (it reads files), so it is *not* part of the numerical core.
"""

from __future__ import annotations

import csv
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path

from taxel_net.errors import SceneError
from taxel_net.gripper import GripperSpec, load_gripper
from taxel_net.patches import COB_ID_FIRST, COB_ID_LAST, PATCH_TAXELS_MAX, RAW_FORMATS
from taxel_net.patches import devices as patch_devices
from taxel_net.scene_grasp import GraspSpec, load_grasp
from taxel_net.scene_grip import GripParams, load_grip
from taxel_net.scene_fields import Where as _Where
from taxel_net.scene_fields import array as _list
from taxel_net.scene_fields import boolean as _bool
from taxel_net.scene_fields import distinct_strings as _distinct_strings
from taxel_net.scene_fields import integer as _int
from taxel_net.scene_fields import number as _num
from taxel_net.scene_fields import string as _str
from taxel_net.scene_fields import table as _table

# 0x2001:3 taxel kind codes (UNSIGNED8); 0 is "unset" and refused by the node.
TAXEL_KINDS: dict[str, int] = {"R": 1, "C": 2, "P": 3, "LC": 4, "TBS": 5, "IR": 6}
KIND_NAMES: dict[int, str] = {v: k for k, v in TAXEL_KINDS.items()}

OBJECT_MODELS = ("none", "point", "small", "large", "slipping", "script")
RULES = ("additive", "multiplicative", "preferential", "k-of-n", "llr", "np")
STAGES = ("fusion", "forces", "area", "contact_type", "slip")


@dataclass(frozen=True)
class TaxelSpec:
    node_id: int                      # CANopen node-ID 1..127, unique per channel
    kind: str                         # one of TAXEL_KINDS
    channel: int = 0                  # index into BusSpec.channels
    x: float | None = None            # planar coordinates (0x2001:4/5); None = no geometry
    y: float | None = None
    zeta_mv: float = 1.0              # cut-off ζ, eq 3 (0x2001:1)
    noise_mv: float = 0.0             # N_i, the node's noise estimate, eq 4 (0x2001:2)
    noise_sigma_mv: float = 0.0       # std of simulated white noise on X_i
    signal_mv: float = 0.0            # S, signal under contact, eq 1
    pf: float | None = None           # per-taxel P_F (LLR / N-P baselines)
    pm: float | None = None           # per-taxel P_M
    slope: float | None = None        # y = m F + c (eq 23/27a), mV per force unit (0x6126)
    intercept: float | None = None    # mV (0x6127)
    grip_factor: float | None = None  # LC: Y = M F_g (eq 27b), mV per force unit
    jaw: str | None = None            # gripper: "left" | "right"
    axis: str | None = None           # gripper TBS: "x" | "y"


@dataclass(frozen=True)
class BusSpec:
    bitrate: int = 1_000_000
    sync_period_ms: float = 10.0
    sync_counter: int = 0             # 0x1019 overflow value: 0 = no counter byte, 2..240 = counter
    heartbeat_producer_ms: int = 100  # 0x1017 written to every node
    heartbeat_consumer_ms: int = 300  # master's 0x1016 consumer time per node
    mode: str = "decision"            # "decision" (TPDO1: u_i) | "raw" (TPDO2: process value mV)
    transmission_type: int = 1        # TPDO 0x1800:2 — 1..240 synchronous, 254/255 event-driven
    inhibit_time_100us: int = 0       # 0x1800:3
    event_timer_ms: int = 0           # 0x1800:5 (0 = off)
    channels: tuple[str, ...] = ("taxel0",)
    sync_window_us: int = 0           # 0x1007 synchronous window length (µs), 0: off (CiA 301 default);
                                      # -1: 80 % of the SYNC period (what a scene file gets by default)
    patch_nodes: bool = False         # taxels sharing a node-ID on a channel form one patch node with
                                      # packed PDOs (taxel_net.patches); False: one node per taxel
    fd: bool = False                  # PDOs as CAN FD frames (up to 64 bytes, bit-rate switch); SDO, NMT,
                                      # heartbeat, SYNC and EMCY stay classic
    data_bitrate: int = 5_000_000     # CAN FD data-phase bit rate (with fd only)
    raw_format: str = "real32"        # raw mode: "real32" (one-taxel nodes, TPDO2) | "int16" | "int8"
                                      # (patch nodes: packed counts of raw_lsb_mv)
    raw_lsb_mv: float = 0.01          # mV per count of the packed raw readings
    tpdo_cob_id_base: int = 0x181     # patch nodes: first COB-ID of a channel's TPDOs

    @property
    def sync_window(self) -> int:
        """The synchronous window length in µs (0x1007; 0 = no window)."""
        if self.sync_window_us >= 0:
            return self.sync_window_us
        return int(round(self.sync_period_ms * 1000)) * 4 // 5

    @property
    def cycle_tag(self) -> bool:
        """TPDO1 carries a cycle tag (object 0x2003: u_i in bits 0-1, the SYNC counter of the
        sampling SYNC modulo 64 in bits 2-7): decision mode with a SYNC counter (0x1019 > 0)."""
        return self.mode == "decision" and self.sync_counter > 0


MASTER_NODE_ID_DEFAULT = 127
MASTER_HEARTBEAT_MAX_MS = 0xFFFF // 3  # the nodes watch it for 3 x its period in 0x1016 (16 bits of ms)


@dataclass(frozen=True)
class MasterSpec:
    restart: str = "always"           # "always": NMT-start a live node found not operational | "never"
    assign_ids: str = "scene"         # "scene": nodes have the scene's node-IDs | "lss": they start
                                      # non-configured (0xFF) and the centre assigns each the scene's
                                      # node-ID for its serial number (0x1018:4) by LSS Fastscan (CiA 305)
    node_id: int = MASTER_NODE_ID_DEFAULT  # the master's node-ID (CiA 302): its heartbeat is 0x700+node_id
    heartbeat_ms: int | None = None   # the master's heartbeat period (its 0x1017), 0 = off;
                                      # None = the bus's heartbeat_producer_ms (Scene.master_heartbeat_ms)


@dataclass(frozen=True)
class ObjectSpec:
    model: str = "none"               # one of OBJECT_MODELS
    x: float = 0.0                    # contact centre (taxel coordinate units)
    y: float = 0.0
    radius: float = 0.0               # footprint radius; "point" contacts the nearest taxel only
    present: tuple[tuple[int, int], ...] = ()   # [start, end) cycle intervals with contact (ground truth)
    velocity: tuple[float, float] = (0.0, 0.0)  # "slipping": centre motion per cycle from slip_onset_cycle
    slip_onset_cycle: int | None = None
    tangential_force: float = 0.0     # force on each contacted calibrated taxel: signal = m F + c
    readings_mv: tuple[float, ...] | None = None  # "script": per taxel (scene order) while present
    readings_are: str = "Y"           # "script": "Y" = readings are Y_i = X_i - N_i (eq 4) | "X" = raw X_i


@dataclass(frozen=True)
class FusionSpec:
    rules: tuple[str, ...] = ("additive",)
    decide_with: str = "additive"     # the rule whose verdict is the record's `decision`
    tuple: str = "pm1"                # decision encoding, "pm1" | "01"
    xi: float = 0.003
    alpha: float = 0.03               # additive (eq 17), preferential (eqs 18-20)
    beta: float = 0.83                # multiplicative (eq 16)
    additive_root: str = "lower"      # which non-trivial root of eq 17 to use: "lower" | "upper"
    p: float = 1.0
    q: float = 1.0
    k: int = 1                        # k-of-n
    np_false_alarm: float = 1e-3      # N-P fusion target P_F
    prior_h1: float = 0.5             # LLR prior
    costs: tuple[float, float, float, float] = (0.0, 1.0, 1.0, 0.0)  # C00, C01, C10, C11 (eq 22)


@dataclass(frozen=True)
class ForcesSpec:
    mu: float = 0.3                   # coefficient of kinetic friction (eq 26)
    unit: str = "N"                   # force unit the calibration maps to ("N" | "kgf")
    inclusion_angle_deg: float = 0.0  # α of eqs 25/28b


FAULTS = ("stuck", "open_circuit", "silent")


@dataclass(frozen=True)
class FaultSpec:
    """A simulated node fault: active for from_cycle <= cycle < until_cycle (None = for ever).

    ``stuck``: the node keeps sending the reading it had at ``from_cycle``;
    ``open_circuit``: the input reads NaN (the node decides absent and should raise EMCY);
    ``silent``: the node stops transmitting PDOs and heartbeats (handled by the node twin).
    """

    node_id: int
    fault: str                        # one of FAULTS
    from_cycle: int
    channel: int = 0
    until_cycle: int | None = None

    def active(self, cycle: int) -> bool:
        return self.from_cycle <= cycle and (self.until_cycle is None or cycle < self.until_cycle)


@dataclass(frozen=True)
class Scene:
    path: str
    name: str
    description: str = ""
    seed: int = 0
    cycles: int = 100
    bus: BusSpec = field(default_factory=BusSpec)
    taxels: tuple[TaxelSpec, ...] = ()
    object: ObjectSpec = field(default_factory=ObjectSpec)
    fusion: FusionSpec = field(default_factory=FusionSpec)
    forces: ForcesSpec = field(default_factory=ForcesSpec)
    stages: tuple[str, ...] = ("fusion",)  # requested; the pipeline builds only what the scene supports
    faults: tuple[FaultSpec, ...] = ()
    master: MasterSpec = field(default_factory=MasterSpec)
    grasp: GraspSpec | None = None         # [grasp]: the grasp world's object and task (scene_grasp.py)
    gripper: GripperSpec | None = None     # [gripper]: a CiA 402 gripper drive on the bus (taxel_net.gripper)
    grip: GripParams | None = None         # [grip]: the centre's grip-force law (taxel_net.scene_grip)

    @property
    def n(self) -> int:
        return len(self.taxels)

    @property
    def master_heartbeat_ms(self) -> int:
        """The master's heartbeat period in ms (0 = off): ``[master] heartbeat_ms``, by default
        the bus's ``heartbeat_producer_ms``."""
        hb = self.master.heartbeat_ms
        return int(self.bus.heartbeat_producer_ms if hb is None else hb)


# ----------------------------------------------------------------------------------------
# Loader
# ----------------------------------------------------------------------------------------

# CAN classic bit-rate range accepted in a scene (CiA 301 bit-timing table: 10 kbit/s .. 1 Mbit/s)
BITRATE_MIN = 10_000
BITRATE_MAX = 1_000_000
DATA_BITRATE_MAX = 15_000_000   # CAN FD data phase (transceivers: 2, 5, 8 Mbit/s are common)
FOOTPRINT_MODELS = ("point", "small", "large", "slipping")
JAWS = ("left", "right")
AXES = ("x", "y")
BUS_MODES = ("decision", "raw")
FORCE_UNITS = ("N", "kgf")
ADDITIVE_ROOTS = ("lower", "upper")
READINGS_ARE = ("Y", "X")

# per-kind fields (allowed in [kinds.X], [[taxels]], CSV columns and [per_taxel])
KIND_FIELDS = ("zeta_mv", "noise_mv", "noise_sigma_mv", "signal_mv", "pf", "pm",
               "slope", "intercept", "grip_factor")
TAXEL_FIELDS = ("node_id", "kind", "channel", "x", "y", "jaw", "axis") + KIND_FIELDS
_INT_TAXEL_FIELDS = ("node_id", "channel")
_STR_TAXEL_FIELDS = ("kind", "jaw", "axis")

_TOP_KEYS = ("scene", "bus", "kinds", "taxels", "taxels_file", "per_taxel", "object", "fusion",
             "forces", "outputs", "faults", "master", "grasp", "gripper", "grip")
_SCENE_KEYS = ("name", "description", "seed", "cycles")
_BUS_KEYS = ("bitrate", "sync_period_ms", "sync_counter", "heartbeat_producer_ms",
             "heartbeat_consumer_ms", "mode", "transmission_type", "inhibit_time_100us",
             "event_timer_ms", "channels", "sync_window_us", "patch_nodes", "fd", "data_bitrate",
             "raw_format", "raw_lsb_mv", "tpdo_cob_id_base")
_OBJECT_KEYS = ("model", "x", "y", "radius", "present", "velocity", "slip_onset_cycle",
                "tangential_force", "readings_mv", "readings_are")
_FUSION_KEYS = ("rules", "decide_with", "tuple", "xi", "alpha", "beta", "additive_root", "p", "q",
                "k", "np_false_alarm", "prior_h1", "costs")
_MASTER_KEYS = ("restart", "assign_ids", "node_id", "heartbeat_ms")
RESTART_POLICIES = ("always", "never")
ASSIGN_IDS = ("scene", "lss")
SYNC_PERIOD_MIN_MS = 1.0          # the SYNC producer's resolution (a 57-node cycle needs ~3.5 ms at 1 Mbit/s)
SYNC_PERIOD_MAX_MS = 4_294_967.295  # 0x1006 communication cycle period: UNSIGNED32 µs
CYCLES_MAX = 10**10               # > 3 years of 10 ms cycles
_FORCES_KEYS = ("mu", "unit", "inclusion_angle_deg")
_OUTPUTS_KEYS = ("stages",)
_FAULT_KEYS = ("node_id", "channel", "fault", "from_cycle", "until_cycle")


def _kind_field(w: _Where, key: str, v) -> float:
    """Range of every per-kind field (eqs 1-4, 23, 27)."""
    if key in ("zeta_mv", "noise_mv", "noise_sigma_mv"):
        return _num(w, key, v, lo=0.0)
    if key in ("pf", "pm"):
        return _num(w, key, v, lo=0.0, hi=1.0, lo_open=True, hi_open=True)
    return _num(w, key, v)


def _read_toml(path: Path) -> dict:
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(str(path), "<toml>", None, f"TOML syntax error: {exc}") from None
    except UnicodeDecodeError as exc:
        raise SceneError(str(path), "<file>", None,
                         f"not a UTF-8 text file (TOML is UTF-8): byte 0x{exc.object[exc.start]:02X} "
                         f"at offset {exc.start}") from None
    except OSError as exc:
        raise SceneError(str(path), "<file>", None, f"cannot read: {exc.strerror or exc}") from None


def _read_csv_taxels(csv_path: Path, scene_w: _Where) -> list[tuple[_Where, dict]]:
    """Rows of a taxels_file: header = taxel field names; an empty cell means "not given"."""
    p = str(csv_path)
    try:
        with open(csv_path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        scene_w.fail("taxels_file", p, f"cannot read: {exc.strerror or exc}")
    except (UnicodeDecodeError, csv.Error) as exc:
        raise SceneError(p, "line ?", None, f"not a UTF-8 CSV file: {exc}") from None
    if not rows:
        raise SceneError(p, "line 1", None, "empty file: needs a header line")
    header = [h.strip() for h in rows[0]]
    for col in header:
        if col not in TAXEL_FIELDS:
            raise SceneError(p, f"line 1, column {col}", col,
                             f"unknown column (allowed: {', '.join(TAXEL_FIELDS)})")
    if len(set(header)) != len(header):
        dup = next(h for h in header if header.count(h) > 1)
        raise SceneError(p, f"line 1, column {dup}", dup, "duplicate column")
    out = []
    for ln, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue  # blank line
        w = _Where(p, csv_line=ln)
        if len(row) != len(header):
            raise SceneError(p, f"line {ln}", row, f"has {len(row)} cells, header has {len(header)}")
        rec = {}
        for col, cell in zip(header, row):
            cell = cell.strip()
            if cell == "":
                continue
            if col in _STR_TAXEL_FIELDS:
                rec[col] = cell
            elif col in _INT_TAXEL_FIELDS:
                try:
                    rec[col] = int(cell)
                except ValueError:
                    w.fail(col, cell, "must be an integer")
            else:
                try:
                    rec[col] = float(cell)
                except ValueError:
                    w.fail(col, cell, "must be a number")
        out.append((w, rec))
    return out


def load_scene(path) -> Scene:
    """Read and validate a scene file (format: ``docs/scene-format.md``).

    Raises :class:`SceneError` (file, dotted field, value, problem) on any unknown key, wrong
    type, out-of-range value, missing required field, duplicate node-ID per channel, a
    syntax error or an unreadable file. Precedence of per-taxel values:
    ``[kinds.X]`` < the taxel's own row/table < ``[per_taxel]`` arrays. ``path`` may also
    name a bundled scene (``"matrix57"``, :func:`taxel_net.resources.resolve_scene`).
    """
    from .resources import resolve_scene

    path = resolve_scene(path)
    sp = str(path)
    doc = _read_toml(path)
    top = _Where(sp)
    _table(top, "", doc, _TOP_KEYS)

    # [scene]
    if "scene" not in doc:
        top.fail("scene", None, "missing required table [scene]")
    sc = _table(top, "scene", doc["scene"], _SCENE_KEYS)
    sw = _Where(sp, "scene")
    if "name" not in sc:
        sw.fail("name", None, "missing required field")
    name = _str(sw, "name", sc["name"])
    if not name:
        sw.fail("name", name, "must not be empty")
    description = _str(sw, "description", sc.get("description", ""))
    seed = _int(sw, "seed", sc.get("seed", 0), 0, 2**63 - 1, "must be an integer >= 0")
    cycles = _int(sw, "cycles", sc.get("cycles", 100), 1, CYCLES_MAX, f"must be an integer in 1..{CYCLES_MAX}")

    bus = _load_bus(sp, top, doc.get("bus", {}))
    taxels = _load_taxels(path, top, doc, bus)
    obj = _load_object(sp, top, doc.get("object", {"model": "none"}), taxels)
    if "fusion" not in doc:
        top.fail("fusion", None, "missing required table [fusion] (its `tuple` is always explicit)")
    fusion = _load_fusion(sp, top, doc["fusion"], taxels)
    forces = _load_forces(sp, top, doc.get("forces", {}))
    ow = _Where(sp, "outputs")
    outs = _table(top, "outputs", doc.get("outputs", {}), _OUTPUTS_KEYS)
    stages = _distinct_strings(ow, "stages", outs.get("stages", ["fusion"]), STAGES)
    faults = _load_faults(sp, top, doc.get("faults", []), taxels)
    master = _load_master(sp, top, doc.get("master", {}), bus, taxels)
    if bus.patch_nodes:
        if master.assign_ids == "lss":
            _Where(sp, "master").fail("assign_ids", "lss", "patch nodes are not assigned by LSS yet: \"scene\"")
        try:
            patch_devices(Scene(path=sp, name=name, bus=bus, taxels=taxels))
        except ValueError as exc:
            _Where(sp, "bus").fail("tpdo_cob_id_base", f"0x{bus.tpdo_cob_id_base:03X}", str(exc))
    gripper = load_gripper(sp, doc["gripper"], bus, taxels, master) if "gripper" in doc else None
    grip = load_grip(sp, doc["grip"], gripper, forces.mu) if "grip" in doc else None
    return Scene(path=sp, name=name, description=description, seed=seed, cycles=cycles, bus=bus,
                 taxels=taxels, object=obj, fusion=fusion, forces=forces, stages=tuple(stages),
                 faults=faults, master=master, gripper=gripper, grip=grip,
                 grasp=load_grasp(sp, doc["grasp"]) if "grasp" in doc else None)


def _load_master(sp: str, top: _Where, raw, bus: BusSpec, taxels: tuple[TaxelSpec, ...]) -> MasterSpec:
    mt = _table(top, "master", raw, _MASTER_KEYS)
    w = _Where(sp, "master")
    restart = _str(w, "restart", mt.get("restart", MasterSpec.restart), RESTART_POLICIES)
    assign_ids = _str(w, "assign_ids", mt.get("assign_ids", MasterSpec.assign_ids), ASSIGN_IDS)
    node_id = _int(w, "node_id", mt.get("node_id", MASTER_NODE_ID_DEFAULT), 1, 127,
                   "CANopen node-ID must lie in 1..127")
    given = "heartbeat_ms" in mt
    heartbeat = mt["heartbeat_ms"] if given else bus.heartbeat_producer_ms
    _int(w, "heartbeat_ms", heartbeat, 0, MASTER_HEARTBEAT_MAX_MS,
         f"must lie in 0..{MASTER_HEARTBEAT_MAX_MS} ms (0 = off; the nodes' consumer time 0x1016, 3 x the "
         "period, has 16 bits)" + ("" if given else "; default: bus.heartbeat_producer_ms"))
    if heartbeat:  # the master's heartbeat 0x700+node_id must not be a taxel's
        used = {t.node_id for t in taxels}
        if node_id in used:
            channels = sorted({t.channel for t in taxels if t.node_id == node_id})
            free = next((i for i in range(127, 0, -1) if i not in used), None)
            w.fail("node_id", node_id,
                   f"is a taxel's node-ID (channel {', '.join(map(str, channels))}): the master's heartbeat "
                   "0x700+node_id needs a node-ID no taxel uses on any channel"
                   + (f" (free: e.g. {free})" if free else "") + ", or master.heartbeat_ms = 0")
    return MasterSpec(restart=restart, assign_ids=assign_ids, node_id=node_id,
                      heartbeat_ms=heartbeat if given else None)


def _load_bus(sp: str, top: _Where, raw) -> BusSpec:
    b = _table(top, "bus", raw, _BUS_KEYS)
    w = _Where(sp, "bus")
    d = BusSpec()
    bitrate = _int(w, "bitrate", b.get("bitrate", d.bitrate), BITRATE_MIN, BITRATE_MAX,
                   f"CAN bit rate must lie in {BITRATE_MIN}..{BITRATE_MAX} bit/s")
    sync = _num(w, "sync_period_ms", b.get("sync_period_ms", d.sync_period_ms), lo=SYNC_PERIOD_MIN_MS,
                hi=SYNC_PERIOD_MAX_MS)
    counter = _int(w, "sync_counter", b.get("sync_counter", d.sync_counter))
    if not (counter == 0 or 2 <= counter <= 240):
        w.fail("sync_counter", counter, "0x1019: 0 (no counter) or 2..240")
    hb_p = _int(w, "heartbeat_producer_ms", b.get("heartbeat_producer_ms", d.heartbeat_producer_ms),
                0, 0xFFFF)
    hb_c = _int(w, "heartbeat_consumer_ms", b.get("heartbeat_consumer_ms", d.heartbeat_consumer_ms),
                0, 0xFFFF)
    mode = _str(w, "mode", b.get("mode", d.mode), BUS_MODES)
    tt = _int(w, "transmission_type", b.get("transmission_type", d.transmission_type))
    if not (1 <= tt <= 240 or tt in (254, 255)):
        w.fail("transmission_type", tt, "must be 1..240 (synchronous) or 254/255 (event-driven)")
    inhibit = _int(w, "inhibit_time_100us", b.get("inhibit_time_100us", d.inhibit_time_100us), 0, 0xFFFF)
    ev = _int(w, "event_timer_ms", b.get("event_timer_ms", d.event_timer_ms), 0, 0xFFFF)
    channels = _distinct_strings(w, "channels", b.get("channels", list(d.channels)))
    if not channels:
        w.fail("channels", channels, "needs at least one channel")
    period_us = int(round(sync * 1000))
    window = _int(w, "sync_window_us", b.get("sync_window_us", period_us * 4 // 5), 0, 0xFFFFFFFF)
    if window >= period_us:
        w.fail("sync_window_us", window, f"0x1007 must be shorter than the SYNC period ({period_us} µs), "
                                         "or 0 (no window)")
    patch = _bool(w, "patch_nodes", b.get("patch_nodes", d.patch_nodes))
    fd = _bool(w, "fd", b.get("fd", d.fd))
    if "data_bitrate" in b and not fd:
        w.fail("data_bitrate", b["data_bitrate"], "only with fd = true (classic CAN has one bit rate)")
    data_bitrate = _int(w, "data_bitrate", b.get("data_bitrate", d.data_bitrate), bitrate, DATA_BITRATE_MAX,
                        f"CAN FD data bit rate must lie in bus.bitrate..{DATA_BITRATE_MAX} bit/s")
    raw_format = _str(w, "raw_format", b.get("raw_format", "int16" if patch else "real32"), RAW_FORMATS)
    if patch and raw_format == "real32":
        w.fail("raw_format", raw_format, "patch nodes pack their readings: int16 or int8")
    if not patch and raw_format != "real32":
        w.fail("raw_format", raw_format, "one-taxel nodes send REAL32 (TPDO2); int16 / int8 need patch_nodes = true")
    lsb = _num(w, "raw_lsb_mv", b.get("raw_lsb_mv", d.raw_lsb_mv), lo=0.0, lo_open=True)
    if "raw_lsb_mv" in b and not patch:
        w.fail("raw_lsb_mv", lsb, "only with patch_nodes = true (one-taxel nodes send REAL32 mV)")
    if "tpdo_cob_id_base" in b and not patch:
        w.fail("tpdo_cob_id_base", b["tpdo_cob_id_base"], "only with patch_nodes = true (one-taxel nodes use "
                                                          "the predefined 0x180 / 0x280 + node-ID)")
    cob_base = _int(w, "tpdo_cob_id_base", b.get("tpdo_cob_id_base", d.tpdo_cob_id_base), COB_ID_FIRST,
                    COB_ID_LAST, f"must lie in 0x{COB_ID_FIRST:03X}..0x{COB_ID_LAST:03X} (TPDO/RPDO range)")
    return BusSpec(bitrate=bitrate, sync_period_ms=sync, sync_counter=counter,
                   heartbeat_producer_ms=hb_p, heartbeat_consumer_ms=hb_c, mode=mode,
                   transmission_type=tt, inhibit_time_100us=inhibit, event_timer_ms=ev,
                   channels=tuple(channels), sync_window_us=window, patch_nodes=patch, fd=fd,
                   data_bitrate=data_bitrate, raw_format=raw_format, raw_lsb_mv=lsb, tpdo_cob_id_base=cob_base)


def _load_taxels(path: Path, top: _Where, doc: dict, bus: BusSpec) -> tuple[TaxelSpec, ...]:
    sp = str(path)
    # [kinds.X]
    kinds_raw = _table(top, "kinds", doc.get("kinds", {}), tuple(TAXEL_KINDS))
    kind_defaults: dict[str, dict] = {}
    for kname, kt in kinds_raw.items():
        _table(_Where(sp, "kinds"), kname, kt, KIND_FIELDS)
        kw = _Where(sp, f"kinds.{kname}")
        kind_defaults[kname] = {k: _kind_field(kw, k, v) for k, v in kt.items()}

    # rows: [[taxels]] or taxels_file
    if ("taxels" in doc) == ("taxels_file" in doc):
        top.fail("taxels", None, "give exactly one of [[taxels]] or taxels_file")
    rows: list[tuple[_Where, dict]] = []
    if "taxels" in doc:
        lst = _list(top, "taxels", doc["taxels"])
        for i, t in enumerate(lst):
            _table(top, f"taxels[{i}]", t, TAXEL_FIELDS)
            rows.append((_Where(sp, f"taxels[{i}]"), t))
    else:
        rel = _str(top, "taxels_file", doc["taxels_file"])
        csv_path = (path.parent / rel)
        rows = _read_csv_taxels(csv_path, top)
    if not rows:
        top.fail("taxels", [], "needs at least one taxel")

    # [per_taxel]: arrays in fusion order, highest precedence
    per_raw = _table(top, "per_taxel", doc.get("per_taxel", {}), KIND_FIELDS)
    pw = _Where(sp, "per_taxel")
    per: dict[str, list[float]] = {}
    for key, arr in per_raw.items():
        _list(pw, key, arr, len(rows))
        per[key] = [_kind_field(pw, f"{key}[{i}]", v) for i, v in enumerate(arr)]

    taxels = []
    seen: dict[tuple[int, int], str] = {}
    hosted: dict[tuple[int, int], int] = {}
    for i, (w, t) in enumerate(rows):
        for req in ("node_id", "kind"):
            if req not in t:
                w.fail(req, None, "missing required field")
        node_id = _int(w, "node_id", t["node_id"], 1, 127, "CANopen node-ID must lie in 1..127")
        kind = _str(w, "kind", t["kind"], tuple(TAXEL_KINDS))
        channel = _int(w, "channel", t.get("channel", 0), 0, len(bus.channels) - 1,
                       f"must index bus.channels (0..{len(bus.channels) - 1})")
        key = (channel, node_id)
        if key in seen and not bus.patch_nodes:
            w.fail("node_id", node_id, f"duplicate node-ID on channel {channel} (also at {seen[key]}; "
                                       "taxels share a node only with bus.patch_nodes = true)")
        hosted[key] = hosted.get(key, 0) + 1
        if hosted[key] > PATCH_TAXELS_MAX:
            w.fail("node_id", node_id, f"a patch node hosts at most {PATCH_TAXELS_MAX} taxels (CiA 301 arrays "
                                       f"have sub-indices 1..254); this is taxel {hosted[key]} of node "
                                       f"{node_id} on channel {channel}")
        seen.setdefault(key, w.name("node_id"))
        vals: dict = {}
        for k in ("x", "y"):
            if k in t:
                vals[k] = _num(w, k, t[k])
        if ("x" in vals) != ("y" in vals):
            missing = "y" if "x" in vals else "x"
            w.fail(missing, None, "x and y come together (both or neither)")
        if "jaw" in t:
            vals["jaw"] = _str(w, "jaw", t["jaw"], JAWS)
        if "axis" in t:
            vals["axis"] = _str(w, "axis", t["axis"], AXES)
        merged = dict(kind_defaults.get(kind, {}))
        for k in KIND_FIELDS:
            if k in t:
                merged[k] = _kind_field(w, k, t[k])
            if k in per:
                merged[k] = per[k][i]
        taxels.append(TaxelSpec(node_id=node_id, kind=kind, channel=channel, **vals, **merged))
    return tuple(taxels)


def _load_object(sp: str, top: _Where, raw, taxels: tuple[TaxelSpec, ...]) -> ObjectSpec:
    o = _table(top, "object", raw, _OBJECT_KEYS)
    w = _Where(sp, "object")
    if "model" not in o:
        w.fail("model", None, "missing required field")
    model = _str(w, "model", o["model"], OBJECT_MODELS)
    x = _num(w, "x", o.get("x", 0.0))
    y = _num(w, "y", o.get("y", 0.0))
    radius = _num(w, "radius", o.get("radius", 0.0), lo=0.0)
    present = []
    for i, iv in enumerate(_list(w, "present", o.get("present", []))):
        f = f"present[{i}]"
        _list(w, f, iv, 2)
        start = _int(w, f"{f}[0]", iv[0], 0, None, "start cycle must be >= 0")
        end = _int(w, f"{f}[1]", iv[1])
        if end <= start:
            w.fail(f, iv, "[start, end) needs end > start")
        present.append((start, end))
    vel = _list(w, "velocity", o.get("velocity", [0.0, 0.0]), 2)
    velocity = (_num(w, "velocity[0]", vel[0]), _num(w, "velocity[1]", vel[1]))
    onset = o.get("slip_onset_cycle")
    if onset is not None:
        onset = _int(w, "slip_onset_cycle", onset, 0, None, "must be an integer >= 0")
    force = _num(w, "tangential_force", o.get("tangential_force", 0.0), lo=0.0)
    readings = None
    if "readings_mv" in o:
        if model != "script":
            w.fail("readings_mv", o["readings_mv"], f"only used by model 'script' (model is {model!r})")
        arr = _list(w, "readings_mv", o["readings_mv"], len(taxels))
        readings = tuple(_num(w, f"readings_mv[{i}]", v) for i, v in enumerate(arr))
    readings_are = _str(w, "readings_are", o.get("readings_are", "Y"), READINGS_ARE)
    if model == "script" and readings is None:
        w.fail("readings_mv", None, f"model 'script' needs readings_mv ({len(taxels)} values)")
    if model == "slipping" and onset is None:
        w.fail("slip_onset_cycle", None, "model 'slipping' needs slip_onset_cycle")
    if model in ("small", "large", "slipping") and radius <= 0:
        w.fail("radius", radius, f"model {model!r} needs a footprint radius > 0")
    if model in FOOTPRINT_MODELS:
        for i, t in enumerate(taxels):
            if t.x is None:
                raise SceneError(sp, f"taxels[{i}].x", None,
                                 f"object.model={model} needs x,y for every taxel")
    return ObjectSpec(model=model, x=x, y=y, radius=radius, present=tuple(present), velocity=velocity,
                      slip_onset_cycle=onset, tangential_force=force, readings_mv=readings,
                      readings_are=readings_are)


def _load_fusion(sp: str, top: _Where, raw, taxels: tuple[TaxelSpec, ...]) -> FusionSpec:
    f = _table(top, "fusion", raw, _FUSION_KEYS)
    w = _Where(sp, "fusion")
    d = FusionSpec()
    if "tuple" not in f:
        w.fail("tuple", None, "missing required field: 'pm1' or '01' (always explicit)")
    enc = _str(w, "tuple", f["tuple"], ("pm1", "01"))
    rules = _distinct_strings(w, "rules", f.get("rules", list(d.rules)), RULES)
    if not rules:
        w.fail("rules", rules, "needs at least one rule")
    decide = _str(w, "decide_with", f.get("decide_with", rules[0]))
    if decide not in rules:
        w.fail("decide_with", decide, f"must be one of fusion.rules ({', '.join(rules)})")
    prob = dict(lo=0.0, hi=1.0, lo_open=True, hi_open=True)
    xi = _num(w, "xi", f.get("xi", d.xi), **prob)
    alpha = _num(w, "alpha", f.get("alpha", d.alpha), **prob)
    beta = _num(w, "beta", f.get("beta", d.beta), **prob)
    root = _str(w, "additive_root", f.get("additive_root", d.additive_root), ADDITIVE_ROOTS)
    p = _num(w, "p", f.get("p", d.p), lo=0.0, hi=2.0)
    q = _num(w, "q", f.get("q", d.q), lo=0.0, hi=2.0)
    k = _int(w, "k", f.get("k", d.k), 1, len(taxels), f"k-of-n needs 1 <= k <= n = {len(taxels)}")
    npfa = _num(w, "np_false_alarm", f.get("np_false_alarm", d.np_false_alarm), **prob)
    prior = _num(w, "prior_h1", f.get("prior_h1", d.prior_h1), **prob)
    costs_raw = _list(w, "costs", f.get("costs", list(d.costs)), 4)
    costs = tuple(_num(w, f"costs[{i}]", c) for i, c in enumerate(costs_raw))
    for rule in ("llr", "np"):
        if rule in rules:
            for i, t in enumerate(taxels):
                if t.pf is None or t.pm is None:
                    w.fail("rules", rules, f"rule {rule!r} needs pf and pm for every taxel "
                                           f"(taxel {i}, node-ID {t.node_id}, kind {t.kind} has none)")
    return FusionSpec(rules=tuple(rules), decide_with=decide, tuple=enc, xi=xi, alpha=alpha, beta=beta,
                      additive_root=root, p=p, q=q, k=k, np_false_alarm=npfa, prior_h1=prior,
                      costs=costs)


def _load_forces(sp: str, top: _Where, raw) -> ForcesSpec:
    f = _table(top, "forces", raw, _FORCES_KEYS)
    w = _Where(sp, "forces")
    d = ForcesSpec()
    mu = _num(w, "mu", f.get("mu", d.mu), lo=0.0, lo_open=True)
    unit = _str(w, "unit", f.get("unit", d.unit), FORCE_UNITS)
    angle = _num(w, "inclusion_angle_deg", f.get("inclusion_angle_deg", d.inclusion_angle_deg),
                 lo=0.0, hi=90.0, hi_open=True)
    return ForcesSpec(mu=mu, unit=unit, inclusion_angle_deg=angle)


def _load_faults(sp: str, top: _Where, raw, taxels: tuple[TaxelSpec, ...]) -> tuple[FaultSpec, ...]:
    lst = _list(top, "faults", raw)
    known = {(t.channel, t.node_id) for t in taxels}
    out = []
    for i, fr in enumerate(lst):
        _table(top, f"faults[{i}]", fr, _FAULT_KEYS)
        w = _Where(sp, f"faults[{i}]")
        for req in ("node_id", "fault", "from_cycle"):
            if req not in fr:
                w.fail(req, None, "missing required field")
        node_id = _int(w, "node_id", fr["node_id"], 1, 127, "CANopen node-ID must lie in 1..127")
        channel = _int(w, "channel", fr.get("channel", 0), 0, None, "must be >= 0")
        if (channel, node_id) not in known:
            w.fail("node_id", node_id, f"no taxel with this node-ID on channel {channel}")
        kind = _str(w, "fault", fr["fault"], FAULTS)
        start = _int(w, "from_cycle", fr["from_cycle"], 0, None, "must be an integer >= 0")
        until = fr.get("until_cycle")
        if until is not None:
            until = _int(w, "until_cycle", until, start + 1, None, f"must be > from_cycle ({start})")
        out.append(FaultSpec(node_id=node_id, fault=kind, from_cycle=start, channel=channel,
                             until_cycle=until))
    return tuple(out)


def taxel_index(scene: Scene, node_id: int, channel: int = 0) -> int:
    """Fusion-order index of the taxel with ``node_id`` on ``channel`` (KeyError if none)."""
    for i, t in enumerate(scene.taxels):
        if t.node_id == node_id and t.channel == channel:
            return i
    raise KeyError((channel, node_id))


def scene_to_dict(scene: Scene) -> dict:
    """JSON-safe summary (lists, numbers, strings, None) for records and reports."""

    def jsonable(v):
        if isinstance(v, dict):
            return {k: jsonable(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [jsonable(x) for x in v]
        return v

    d = jsonable(asdict(scene))
    d["n"] = scene.n
    d["kind_counts"] = {k: sum(1 for t in scene.taxels if t.kind == k)
                        for k in TAXEL_KINDS if any(t.kind == k for t in scene.taxels)}
    return d
