"""The gripper drive's frames in the event stream (issue 23): decoded, the latest values kept.

The cycle assembler (:mod:`.cycles`) hands every frame of the scene's gripper drive (``[gripper]``,
``taxel_net.gripper.drive_cob_ids``: ``K_DRIVE`` in :mod:`.decoder`'s tables) to one
:class:`DriveTracker`, which decodes it with the drive's PDO mapping (``eds/gripper_drive.eds``,
``docs/gripper-drive.md``) and keeps the latest values. When a cycle closes, :meth:`DriveTracker.snapshot`
is what was known of the drive at that instant (:class:`DriveCycle`, ``ClosedCycle.drive``): a
function of the stream alone, so ``replay`` of a trace gives the grip stage the same drive state as
the live run.

=========  ==========  ===================================================================
frame      COB-ID      payload (little endian)
=========  ==========  ===================================================================
TPDO1      0x180+id    0x6041 statusword U16, 0x6077 torque actual I16 (‰), 0x6064 position I32 (µm)
TPDO2      0x280+id    0x6061 mode display I8, 0x2100 grip state U8, 0x2101 force I16 (0.1 N),
                       0x2102 width U16 (0.1 mm), 0x603F error code U16
RPDO1      0x200+id    0x6040 controlword U16, 0x6071 target torque I16 (‰), 0x607A target
                       position I32 (µm): the centre's own command, seen in its stream
heartbeat  0x700+id    NMT state (0 boot-up, 4 stopped, 5 operational, 127 pre-operational)
EMCY       0x80+id     error code U16, error register U8, 5 bytes
SDO        0x580+id /  8 bytes; an answer to an outstanding request of the centre goes to canopen's
           0x600+id    SDO client (the assembler's ``solicited``)
=========  ==========  ===================================================================

A drive whose NMT state is not OPERATIONAL (a boot-up - its TPDO values are then dropped -, or a
heartbeat saying pre-operational or stopped) sends no PDO: :attr:`DriveCycle.state` is None until
a PDO or an operational heartbeat says it runs again (:attr:`DriveCycle.operational`; 2026-11-30
(stop 32): before, the last statusword stayed the drive's state for ever).

A frame of the wrong length or an unknown NMT state is counted in :attr:`DriveTracker.bad` and
changes nothing. Liveness: the drive is ``lost`` at a cycle's close when nothing valid was heard
from it for more than ``[bus] heartbeat_consumer_ms`` (0: only a drive never heard), the same
consumer rule as the taxels'. The CiA 402 state's name is canopen's (``State402.SW_MASK``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from canopen.profiles.p402 import State402

from .cycle_records import frozen_instance

# frame codes: the index of a K_DRIVE entry in the assembler's tables
F_EMCY, F_TPDO1, F_RPDO1, F_TPDO2, F_SDO_RESPONSE, F_SDO_REQUEST, F_HEARTBEAT = range(7)
FRAME_CODES = {"EMCY": F_EMCY, "TPDO1": F_TPDO1, "RPDO1": F_RPDO1, "TPDO2": F_TPDO2,
               "SDO response": F_SDO_RESPONSE, "SDO request": F_SDO_REQUEST, "heartbeat": F_HEARTBEAT}

GRIP_STATES = ("IDLE", "GRASPING", "NO_PART", "PART_LOST", "HOLDING", "RELEASED")  # 0x2100 (gripper-drive.md)
NMT_NAMES = {0: "boot-up", 4: "stopped", 5: "operational", 127: "pre-operational"}
EMCY_KEPT = 8  # EMCY frames of the drive kept per cycle (more: counted in emcy_dropped)

_TPDO1 = struct.Struct("<Hhi")
_TPDO2 = struct.Struct("<bBhHH")
_RPDO1 = struct.Struct("<Hhi")
_EMCY = struct.Struct("<HB5s")


def state_name(statusword: int | None) -> str | None:
    """The CiA 402 state of a statusword as canopen names it (``State402.SW_MASK``), None if none
    (remembered per statusword: a drive shows a handful, and the grip stage asks every cycle on
    the command's path)."""
    try:
        return _STATE_NAMES[statusword]
    except KeyError:
        pass
    name = None
    if statusword is not None:
        for candidate, (mask, value) in State402.SW_MASK.items():
            if statusword & mask == value:
                name = candidate
                break
        if 0 <= statusword <= 0xFFFF:  # an UNSIGNED16 (anything else is not kept)
            _STATE_NAMES[statusword] = name
    return name


_STATE_NAMES: dict[int | None, str | None] = {None: None}


def grip_state_name(code: int | None) -> str | None:
    if code is None:
        return None
    return GRIP_STATES[code] if 0 <= code < len(GRIP_STATES) else f"0x{code:02X}"


@dataclass(frozen=True)
class DriveCycle:
    """What the stream said of the drive when a cycle closed (None: never received)."""

    heard: bool                  # any valid frame of the drive so far
    lost: bool                   # heartbeat consumer time expired (or never heard)
    nmt_state: int | None        # from its heartbeat
    statusword: int | None       # TPDO1
    torque_permille: int | None
    position_um: int | None
    mode: int | None             # TPDO2
    grip_state: int | None
    force_01n: int | None        # per jaw, 0.1 N
    width_01mm: int | None
    error_code: int | None
    tpdo1_us: int | None         # stream time of the TPDO1 the values come from
    command: tuple | None        # the last RPDO1 in the stream: (controlword, target torque ‰, position µm)
    emcy: tuple = ()             # (code, register, t_us) of the drive's EMCY frames since the previous cycle
    emcy_dropped: int = 0
    bootups: int = 0             # boot-ups of the drive since the previous cycle

    @classmethod
    def make(cls, heard, lost, nmt_state, statusword, torque_permille, position_um, mode, grip_state, force_01n,
             width_01mm, error_code, tpdo1_us, command, emcy=(), emcy_dropped=0, bootups=0) -> "DriveCycle":
        """``DriveCycle(...)``, made faster (``cycle_records.frozen_instance``): every cycle's close."""
        return frozen_instance(cls, {
            "heard": heard, "lost": lost, "nmt_state": nmt_state, "statusword": statusword,
            "torque_permille": torque_permille, "position_um": position_um, "mode": mode, "grip_state": grip_state,
            "force_01n": force_01n, "width_01mm": width_01mm, "error_code": error_code, "tpdo1_us": tpdo1_us,
            "command": command, "emcy": emcy, "emcy_dropped": emcy_dropped, "bootups": bootups})

    @property
    def operational(self) -> bool:
        """The drive's NMT state is OPERATIONAL (or not known yet: nothing heard): a drive
        PRE-OPERATIONAL (after its boot-up) or STOPPED sends no PDO (CiA 301), so its last
        TPDO1 / TPDO2 are not its present state."""
        return self.nmt_state is None or self.nmt_state == 5

    @property
    def state(self) -> str | None:
        """CiA 402 state name (canopen's spelling), None before a statusword and while the drive
        is not NMT OPERATIONAL (its last statusword is stale: :attr:`operational`)."""
        return state_name(self.statusword) if self.operational else None

    @property
    def grip_state_name(self) -> str | None:
        return grip_state_name(self.grip_state)

    @property
    def force_n(self) -> float | None:
        return None if self.force_01n is None else self.force_01n / 10.0


class DriveTracker:
    """Decodes the drive's frames (module docstring); pure: no clock, only the stream's times."""

    def __init__(self, consumer_ms: int, node_id: int | None = None, channel: int = 0):
        self.consumer_us = int(consumer_ms) * 1000
        self.node_id, self.channel = node_id, channel
        self.last_heard = -1
        self.nmt_state: int | None = None
        self.tpdo1: tuple | None = None
        self.tpdo1_us: int | None = None
        self.tpdo2: tuple | None = None
        self.command: tuple | None = None
        self.sdo_outstanding = False
        self.emcy_since: list[tuple] = []
        self.emcy_dropped = 0
        self.bootups_since = 0
        self.bad = 0                 # malformed drive frames (wrong length, unknown NMT state)
        self.frames = [0] * len(FRAME_CODES)

    @classmethod
    def for_scene(cls, scene) -> "DriveTracker | None":
        g = scene.gripper
        return None if g is None else cls(scene.bus.heartbeat_consumer_ms, g.node_id, g.channel)

    def nmt_command(self, channel: int, command: int, node_id: int) -> None:
        """An NMT command in the stream (the master's or another's) to the drive (its node-ID or
        all on its channel): its NMT state until the drive's own frames say otherwise - a start
        (0x01) makes it operational before its first PDO, a stop (0x02) stopped, enter
        pre-operational (0x80) and the resets (0x81, 0x82; a boot-up follows) pre-operational."""
        if channel != self.channel or node_id not in (0, self.node_id) or self.nmt_state is None:
            return
        state = {0x01: 5, 0x02: 4, 0x80: 127, 0x81: 127, 0x82: 127}.get(command)
        if state is not None:
            self.nmt_state = state
            if state != 5:
                self._forget_pdos()

    def _forget_pdos(self) -> None:
        """The drive left OPERATIONAL (a boot-up, an NMT command to it, its heartbeat): its last
        TPDO values describe a drive that is gone - until its next TPDO1 it has no present CiA 402
        state (``DriveCycle.state`` None: the command held, nothing sent), so an NMT start that
        did not take effect never brings the old statusword back as the drive's state."""
        self.tpdo1 = self.tpdo1_us = self.tpdo2 = None

    def feed(self, code: int, t_us: int, data: bytes) -> bool:
        """One frame of the drive (``code``: ``F_*``) at stream time ``t_us``; True when it is the
        answer an SDO request of the centre awaits (to be passed on to canopen)."""
        size = len(data)
        if code == F_TPDO1:
            if size != _TPDO1.size:
                return self._bad()
            self.tpdo1 = _TPDO1.unpack(data)
            self.tpdo1_us = t_us
            self.nmt_state = 5  # a node that sends a PDO is operational
        elif code == F_TPDO2:
            if size != _TPDO2.size:
                return self._bad()
            self.tpdo2 = _TPDO2.unpack(data)
            self.nmt_state = 5
        elif code == F_HEARTBEAT:
            if size != 1 or data[0] not in NMT_NAMES:
                return self._bad()
            if data[0] == 0:
                # a reset drive: its PDO values are gone with it (and it sends none until started)
                self.bootups_since += 1
                self.nmt_state = 127
                self._forget_pdos()
            else:
                self.nmt_state = data[0]
                if data[0] != 5:
                    self._forget_pdos()
        elif code == F_EMCY:
            if size != 8:
                return self._bad()
            err, register, _ = _EMCY.unpack(data)
            if len(self.emcy_since) < EMCY_KEPT:
                self.emcy_since.append((err, register, t_us))
            else:
                self.emcy_dropped += 1
        elif code == F_RPDO1:  # the centre's own command (master frame): not the drive's liveness
            self.frames[code] += 1
            if size == _RPDO1.size:
                self.command = _RPDO1.unpack(data)
            return False
        elif code == F_SDO_REQUEST:
            self.frames[code] += 1
            if size == 8 and data[0] != 0x80:
                self.sdo_outstanding = True
            return False
        elif code == F_SDO_RESPONSE:
            if size != 8:
                return self._bad()
            self.frames[code] += 1
            self.last_heard = t_us
            answer, self.sdo_outstanding = self.sdo_outstanding, False
            return answer
        else:
            return self._bad()
        self.frames[code] += 1
        self.last_heard = t_us
        return False

    def _bad(self) -> bool:
        self.bad += 1
        return False

    def snapshot(self, t_us: int) -> DriveCycle:
        """The drive as known at stream time ``t_us`` (a cycle's close); clears the per-cycle lists."""
        heard = self.last_heard >= 0
        lost = not heard or (self.consumer_us > 0 and t_us - self.last_heard > self.consumer_us)
        sw, torque, position = self.tpdo1 if self.tpdo1 is not None else (None, None, None)
        mode, grip, force, width, error = self.tpdo2 if self.tpdo2 is not None else (None,) * 5
        out = DriveCycle.make(heard, lost, self.nmt_state, sw, torque, position, mode, grip, force, width, error,
                         self.tpdo1_us, self.command, tuple(self.emcy_since), self.emcy_dropped, self.bootups_since)
        if self.emcy_since:
            self.emcy_since = []
        self.emcy_dropped = 0
        self.bootups_since = 0
        return out
