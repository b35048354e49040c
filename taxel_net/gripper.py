"""The scene's gripper drive (issue 22): the ``[gripper]`` table and the drive's start-up values.

A scene may put one CiA 402 gripper drive (``eds/gripper_drive.eds``, the twin
:mod:`node_sim.gripper`, ``docs/gripper-drive.md``) on one of its channels. ``[gripper]``
(``docs/scene-format.md``) gives its node-ID, channel and the parameters a real drive keeps in
its non-volatile memory, in the scene's units (mm, N, N·m); :func:`startup_values` turns them
into the drive's object-dictionary values (µm, 0.1 N, mN·m, ‰), which the rig writes at start-up
(``node_sim.rig``) and ``fusion-center dcf`` writes as ``ParameterValue`` of the drive's DCF. The
defaults are the EDS's defaults, so ``[gripper] node_id = N`` alone is the drive as shipped.

Every value is checked here (one line naming the file, the field, the value and what is allowed):
a value the drive's unit cannot hold exactly (e.g. 80.0005 mm in 1 µm steps) is refused, never
rounded; the drive's node-ID is no taxel's (patch node's) on its channel nor the master's, and
its COB-IDs (EMCY 0x80, TPDO1/2 0x180 / 0x280, RPDO1 0x200, SDO 0x580 / 0x600, heartbeat 0x700,
each + node-ID) are none of the patch nodes' TPDOs.

Shared by the twins and the centre (neither imports the other): no CAN library here.
"""

from __future__ import annotations

import math

from dataclasses import dataclass
from types import SimpleNamespace

from taxel_net.identity import identity_serial as _identity_serial
from taxel_net.scene_fields import Where, integer, number, string, table

# the drive's objects the start-up values write (CiA 301 / CiA 402 / vendor area, eds/gripper_drive.eds)
COMM_CYCLE_PERIOD = 0x1006        # µs per SYNC: the actuator's time step
CONSUMER_HEARTBEAT = 0x1016       # sub 1: master node-ID << 16 | consumer time ms (the lost-master watch)
HEARTBEAT_PRODUCER = 0x1017
IDENTITY = 0x1018                 # sub 4: serial number
SYNC_OVERFLOW = 0x1019
RATED_GRIP_FORCE = 0x2103         # 0.1 N per jaw at 1000 ‰
ABORT_CONNECTION = 0x6007
QUICK_STOP_OPTION = 0x605A
FAULT_REACTION_OPTION = 0x605E
MODES_OF_OPERATION = 0x6060
POSITION_WINDOW = 0x6067          # µm
MAX_TORQUE = 0x6072               # ‰
RATED_TORQUE = 0x6076             # mN·m
POSITION_LIMIT = 0x607D           # sub 1 min, sub 2 max, µm
PROFILE_VELOCITY = 0x6081         # µm/s
TORQUE_SLOPE = 0x6087             # ‰/s

MODES = {"position": 1, "torque": 4}           # 0x6060: profile position, profile torque
QUICK_STOP_OPTIONS = (0, 1, 2, 5, 6)           # 0x605A the drive supports (3, 4, 7, 8: no current limit)
FAULT_REACTION_OPTIONS = (0, 1, 2)             # 0x605E
ABORT_CONNECTION_OPTIONS = (0, 1, 2, 3)        # 0x6007
STROKE_MAX_MM = 6553.5                         # 0x2102 (jaw width, 0.1 mm, UNSIGNED16) must hold it
MAX_TORQUE_PERMILLE = 3000                     # 0x6072's HighLimit in the EDS
U16, U32 = 0xFFFF, 0xFFFFFFFF
CONSUMER_TIME_FACTOR = 3                       # default watch: 3 x the master's heartbeat period

GRIPPER_KEYS = ("node_id", "channel", "mode", "rated_force_n", "rated_torque_nm", "max_torque_permille",
                "torque_slope_permille_s", "velocity_mm_s", "stroke_min_mm", "stroke_max_mm",
                "position_window_mm", "quick_stop_option", "fault_reaction_option",
                "abort_connection_option", "master_timeout_ms")


@dataclass(frozen=True)
class GripperSpec:
    """``[gripper]``: one CiA 402 gripper drive (units of the scene; the OD's in brackets)."""

    node_id: int                          # CANopen node-ID 1..127, no taxel's on its channel
    channel: int = 0                      # index into bus.channels
    mode: str = "position"                # 0x6060 at start-up: "position" (1) | "torque" (4)
    rated_force_n: float = 100.0          # 0x2103: grip force per jaw at rated torque [0.1 N]
    rated_torque_nm: float = 1.2          # 0x6076: motor rated torque [mN·m]
    max_torque_permille: int = 1000       # 0x6072 [‰ of rated torque]
    torque_slope_permille_s: int = 5000   # 0x6087 [‰/s], also the stop ramp
    velocity_mm_s: float = 50.0           # 0x6081: jaw speed [µm/s]
    stroke_min_mm: float = 0.0            # 0x607D:1: closed stroke limit (opening width) [µm]
    stroke_max_mm: float = 80.0           # 0x607D:2: open stroke limit; the jaws start there [µm]
    position_window_mm: float = 0.01      # 0x6067 [µm]
    quick_stop_option: int = 2            # 0x605A
    fault_reaction_option: int = 2        # 0x605E
    abort_connection_option: int = 0      # 0x6007: 0 = a lost master leaves a held part held
    master_timeout_ms: int | None = None  # 0x1016:1 consumer time for the master's heartbeat, 0 = off;
                                          # None: 3 x the master's heartbeat period (0 without one)


def _exact(w: Where, key: str, value: float, unit: float, what: str, lo: int, hi: int) -> int:
    """``value`` (scene unit) in steps of ``unit``: an integer lo..hi, or a one-line error."""
    ratio = value / unit
    if not math.isfinite(ratio) or not lo - 1 <= ratio <= hi + 1:   # 1e308 / 0.001 is inf: no round()
        w.fail(key, value, f"must lie in {lo * unit:g}..{hi * unit:g} ({what})")
    steps = round(ratio)
    if abs(ratio - steps) > 1e-6:
        w.fail(key, value, f"must be a multiple of {unit:g} ({what})")
    if not lo <= steps <= hi:
        w.fail(key, value, f"must lie in {lo * unit:g}..{hi * unit:g} ({what})")
    return steps


def load_gripper(sp: str, raw, bus, taxels, master) -> GripperSpec:
    """The ``[gripper]`` table of scene file ``sp`` (the loader of :mod:`taxel_net.scene` calls
    it with the scene's bus, taxels and master); SceneError naming the field on any bad value."""
    top = Where(sp)
    g = table(top, "gripper", raw, GRIPPER_KEYS)
    w = Where(sp, "gripper")
    d = GripperSpec(node_id=1)
    if "node_id" not in g:
        w.fail("node_id", None, "missing required field (the drive's CANopen node-ID)")
    node_id = integer(w, "node_id", g["node_id"], 1, 127, "CANopen node-ID must lie in 1..127")
    n_ch = len(bus.channels)
    channel = integer(w, "channel", g.get("channel", d.channel), 0, n_ch - 1, f"must index bus.channels (0..{n_ch - 1})")
    used = sorted({t.node_id for t in taxels if t.channel == channel})
    if node_id in used:
        free = next((i for i in range(1, 128) if i not in used and i != master.node_id), None)
        w.fail("node_id", node_id, f"is a taxel's node-ID on channel {channel}: the drive needs a node-ID of its "
                                   "own on its channel" + (f" (free: e.g. {free})" if free else ""))
    if node_id == master.node_id:
        w.fail("node_id", node_id, "is the master's node-ID (master.node_id): the drive needs another")
    mode = string(w, "mode", g.get("mode", d.mode), tuple(MODES))
    force = number(w, "rated_force_n", g.get("rated_force_n", d.rated_force_n))
    _exact(w, "rated_force_n", force, 0.1, "N per jaw at rated torque: 0x2103 counts 0.1 N, UNSIGNED16", 1, U16)
    torque = number(w, "rated_torque_nm", g.get("rated_torque_nm", d.rated_torque_nm))
    _exact(w, "rated_torque_nm", torque, 0.001, "N·m: 0x6076 counts mN·m, UNSIGNED32", 1, U32)
    max_torque = integer(w, "max_torque_permille", g.get("max_torque_permille", d.max_torque_permille),
                         1, MAX_TORQUE_PERMILLE, f"0x6072 must lie in 1..{MAX_TORQUE_PERMILLE} ‰ of the rated torque")
    slope = integer(w, "torque_slope_permille_s", g.get("torque_slope_permille_s", d.torque_slope_permille_s),
                    1, U32, f"0x6087 must lie in 1..{U32} ‰/s (0 would never move the torque)")
    velocity = number(w, "velocity_mm_s", g.get("velocity_mm_s", d.velocity_mm_s))
    _exact(w, "velocity_mm_s", velocity, 0.001, "mm/s: 0x6081 counts µm/s, UNSIGNED32, > 0", 1, U32)
    lo_mm = number(w, "stroke_min_mm", g.get("stroke_min_mm", d.stroke_min_mm))
    hi_mm = number(w, "stroke_max_mm", g.get("stroke_max_mm", d.stroke_max_mm))
    stroke = "mm of opening width: 0x607D counts µm, 0x2102 must hold it in 0.1 mm"
    lo_um = _exact(w, "stroke_min_mm", lo_mm, 0.001, stroke, 0, round(STROKE_MAX_MM * 1000))
    hi_um = _exact(w, "stroke_max_mm", hi_mm, 0.001, stroke, 0, round(STROKE_MAX_MM * 1000))
    if hi_um <= lo_um:
        w.fail("stroke_max_mm", hi_mm, f"must be greater than stroke_min_mm ({lo_mm:g})")
    window = number(w, "position_window_mm", g.get("position_window_mm", d.position_window_mm))
    _exact(w, "position_window_mm", window, 0.001, "mm: 0x6067 counts µm, UNSIGNED32", 0, U32)
    options = {}
    for key, allowed, obj in (("quick_stop_option", QUICK_STOP_OPTIONS, "0x605A"),
                              ("fault_reaction_option", FAULT_REACTION_OPTIONS, "0x605E"),
                              ("abort_connection_option", ABORT_CONNECTION_OPTIONS, "0x6007")):
        value = integer(w, key, g.get(key, getattr(d, key)))
        if value not in allowed:
            w.fail(key, value, f"{obj}: one of {', '.join(map(str, allowed))} (docs/gripper-drive.md)")
        options[key] = value
    timeout = g.get("master_timeout_ms")
    if timeout is not None:
        timeout = integer(w, "master_timeout_ms", timeout, 0, U16, "0x1016 consumer time must lie in 0..65535 ms "
                                                                  "(0 = the drive does not watch the master)")
        period = master.heartbeat_ms if master.heartbeat_ms is not None else bus.heartbeat_producer_ms
        if timeout and not period:
            w.fail("master_timeout_ms", timeout, "the master sends no heartbeat (master.heartbeat_ms = 0): only 0")
        if timeout and timeout <= period:
            w.fail("master_timeout_ms", timeout, f"must be longer than the master's heartbeat period ({period} ms), "
                                                 "or 0 (off)")
    if bus.patch_nodes:
        _check_cob_ids(w, node_id, channel, bus, taxels)
    return GripperSpec(node_id=node_id, channel=channel, mode=mode, rated_force_n=force, rated_torque_nm=torque,
                       max_torque_permille=max_torque, torque_slope_permille_s=slope, velocity_mm_s=velocity,
                       stroke_min_mm=lo_mm, stroke_max_mm=hi_mm, position_window_mm=window,
                       master_timeout_ms=timeout, **options)


def drive_cob_ids(node_id: int) -> dict[int, str]:
    """The COB-IDs the drive uses (CiA 301 pre-defined connection set): id -> what."""
    return {0x80 + node_id: "EMCY", 0x180 + node_id: "TPDO1", 0x200 + node_id: "RPDO1",
            0x280 + node_id: "TPDO2", 0x580 + node_id: "SDO response", 0x600 + node_id: "SDO request",
            0x700 + node_id: "heartbeat"}


def _check_cob_ids(w: Where, node_id: int, channel: int, bus, taxels) -> None:
    """Patch nodes' TPDOs take COB-IDs from bus.tpdo_cob_id_base on: none may be the drive's."""
    from taxel_net.patches import devices

    try:
        devs = devices(SimpleNamespace(bus=bus, taxels=taxels))
    except ValueError:
        return  # the scene loader reports that one itself
    mine = drive_cob_ids(node_id)
    for dev in devs:
        if dev.channel != channel:
            continue
        for tpdo in dev.tpdos:
            if tpdo.cob_id in mine:
                w.fail("node_id", node_id, f"its {mine[tpdo.cob_id]} COB-ID 0x{tpdo.cob_id:03X} is a TPDO of patch "
                                           f"node {dev.label} (bus.tpdo_cob_id_base = 0x{bus.tpdo_cob_id_base:03X}): "
                                           "choose another node-ID or TPDO base")


def master_consumer_entry(scene) -> int:
    """0x1016:1 of the drive: ``master node-ID << 16 | consumer time ms`` (0: not watched)."""
    spec = scene.gripper
    timeout = spec.master_timeout_ms
    if timeout is None:
        timeout = min(U16, CONSUMER_TIME_FACTOR * scene.master_heartbeat_ms)
    return scene.master.node_id << 16 | timeout if timeout else 0


def identity_serial(scene) -> int:
    """0x1018:4 of the drive: the scene's rule for every device (:mod:`taxel_net.identity`)."""
    return _identity_serial(scene, scene.gripper)


def startup_values(scene) -> dict[tuple[int, int], int]:
    """``{(index, subindex): value}`` the drive of ``scene`` starts with (its stored parameters;
    what NMT reset-node restores), in OD units. Written in this order (0x607D:2 before :1: each
    must keep min < max with the other's current value)."""
    g, bus = scene.gripper, scene.bus
    return {
        (HEARTBEAT_PRODUCER, 0): int(bus.heartbeat_producer_ms),
        (SYNC_OVERFLOW, 0): int(bus.sync_counter),
        (COMM_CYCLE_PERIOD, 0): int(round(bus.sync_period_ms * 1000)),
        (CONSUMER_HEARTBEAT, 1): master_consumer_entry(scene),
        (IDENTITY, 4): identity_serial(scene),
        (MODES_OF_OPERATION, 0): MODES[g.mode],
        (RATED_GRIP_FORCE, 0): round(g.rated_force_n * 10),
        (RATED_TORQUE, 0): round(g.rated_torque_nm * 1000),
        (MAX_TORQUE, 0): g.max_torque_permille,
        (TORQUE_SLOPE, 0): g.torque_slope_permille_s,
        (PROFILE_VELOCITY, 0): round(g.velocity_mm_s * 1000),
        (POSITION_LIMIT, 2): round(g.stroke_max_mm * 1000),
        (POSITION_LIMIT, 1): round(g.stroke_min_mm * 1000),
        (POSITION_WINDOW, 0): round(g.position_window_mm * 1000),
        (QUICK_STOP_OPTION, 0): g.quick_stop_option,
        (FAULT_REACTION_OPTION, 0): g.fault_reaction_option,
        (ABORT_CONNECTION, 0): g.abort_connection_option,
    }
