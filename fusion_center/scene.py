"""Scene files (TOML): the taxels, the object/contact model, the bus, the rules and outputs.

The format is specified in ``docs/scene-format.md``. This module holds the typed,
validated form (frozen dataclasses) and ``load_scene``; every field error raises
:class:`fusion_center.errors.SceneError` naming the file, the field and the value.
This is I/O (it reads files), so it is *not* part of the numerical core.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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
    readings_mv: tuple[float, ...] | None = None  # "script": X_i per taxel (scene order) while present


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

    @property
    def n(self) -> int:
        return len(self.taxels)


def load_scene(path) -> Scene:  # implemented with the node rig (issue 4)
    raise NotImplementedError("load_scene: see docs/scene-format.md")
