"""The gripper-drive twin: one jaw axis of an electric parallel gripper as a CANopen CiA 402 drive.

:class:`GripperDrive` is a device composed of the shared CANopen service modules of ``node_sim``
(as :class:`node_sim.node.TaxelNode`, whose composition it reuses): NMT slave, heartbeat producer
(0x1017) and consumer (0x1016, 0x1029), SDO server, SYNC consumer, TPDO engine (0x1800/0x1801),
EMCY (0x1001, 0x1003), plus the RPDO engine (:mod:`node_sim.rpdo`, 0x1400/0x1600). Its application
is :class:`DriveApplication`: the CiA 402 state machine (:mod:`.cia402`) and the actuator model
(:mod:`.actuator`) on the object dictionary of ``eds/gripper_drive.eds``.

Per SYNC (:meth:`DriveApplication.sample`, before the TPDOs): the RPDO received since the last
SYNC is written to the OD (controlword 0x6040, target torque 0x6071, target position 0x607A; a
parameter it writes, e.g. 0x6072, is re-read before this SYNC's step); a
controlword written since the last SYNC (by RPDO or SDO) is evaluated (CiA 402 commands, profile
position's new set-point on bit 4's rising edge, bit 6 relative, bit 8 halt); the actuator steps
by the communication cycle period 0x1006 (µs; the rig sets the scene's SYNC period); the
statusword and the actual values are written to the OD; then TPDO1 (statusword, torque actual,
position actual) and TPDO2 (mode display, grip state, grip force, jaw width, error code) leave.

Statusword 0x6041: the state bits (0-3, 5, 6), bit 4 voltage enabled, bit 7 warning (the master's
heartbeat is lost), bit 9 remote, bit 10 target reached (profile torque: torque actual = the
clamped target torque; profile position: within 0x6067 of the target and still; quick stop: the
ramp is done), bit 11 internal limit active (target torque beyond 0x6072, target position beyond
0x607D, or pushing against a stroke limit / an object in profile position), bit 12 set-point
acknowledge (profile position), bits 8, 14, 15 the grip state (0x2100) bits 0, 1, 2.

Faults: a simulated fault (0x2110 written with an error code 0x2000-0x7FFF) -> 0x603F = the code,
EMCY with that code (error register bit 0 and the class bit: 1 current, 2 voltage, 3 temperature,
else 5 device profile), transition 13 and the fault reaction 0x605E. Fault reset (controlword
bit 7 rising edge) clears 0x603F and 0x2110 and sends the error-reset EMCY (when no other error -
an RPDO error episode, a lost heartbeat - is left: :mod:`node_sim.emcy`).

Lost master (a heartbeat in 0x1016 not seen in time, or NMT stop): EMCY 0x8130 (error register
bits 0 and 4), 0x603F = 0x8130, statusword bit 7, the NMT state 0x1029:1 asks for (default 1: no
change, the drive keeps reporting), and the reaction of abort connection 0x6007: default 0 = no
action - the drive keeps the last set-points, so a held part stays held (1 fault, 2 disable
voltage, 3 quick stop all bring the grip force to 0 in profile torque: docs/gripper-drive.md).
The master's next heartbeat ends the communication error (error-reset EMCY if no error is left,
bit 7 cleared). An
NMT stop is an abort-connection event too: no EMCY in STOPPED (CiA 301), so with 0x6007 = 1 the
fault's own EMCY 0x8130 (0x1001 bits 0 and 4 at once) leaves when the drive leaves STOPPED; leaving
STOPPED ends the stop's communication error unless a consumed heartbeat is lost.

RPDO values go by the SDO rules (a refused one is not written, EMCY 0xFF10: :mod:`node_sim.rpdo`);
a parameter an RPDO writes is re-read as after an SDO download. 0x6081 and 0x6087 are at least 1.

Threading: every entry point runs with the owning channel's lock held; the world's calls
(:meth:`GripperDrive.jaw_blocked_at`, :meth:`GripperDrive.part_lost`) take that lock through the
host (:class:`node_sim.gripper.host.DriveHost`).
"""

from __future__ import annotations

from canopen.sdo import SdoAbortedError

from taxel_net.resources import gripper_eds_path

from .. import od as odx
from ..emcy import ERR_REG_COMMUNICATION
from ..heartbeat import EMCY_HEARTBEAT
from ..node import TaxelNode
from ..nmt import NMT_STOP, STOPPED
from ..rpdo import RpdoEngine
from ..sdo import ABORT_VALUE_RANGE, ABORT_VALUE_TOO_LOW
from . import cia402
from .actuator import GripState, JawAxis, grip_state_statusword

GRIPPER_EDS_PATH = gripper_eds_path()

__all__ = ["GripperDrive", "DriveApplication", "GRIPPER_EDS_PATH"]

# CiA 402 objects
ABORT_CONNECTION = 0x6007
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
FAULT_REACTION_OPTION = 0x605E
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
POSITION_WINDOW = 0x6067
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
TORQUE_DEMAND = 0x6074
RATED_TORQUE = 0x6076
TORQUE_ACTUAL = 0x6077
TARGET_POSITION = 0x607A
POSITION_LIMIT = 0x607D
PROFILE_VELOCITY = 0x6081
TORQUE_SLOPE = 0x6087
SUPPORTED_MODES = 0x6502
COMM_CYCLE_PERIOD = 0x1006
# vendor objects
GRIP_STATE = 0x2100
GRIP_FORCE = 0x2101           # INTEGER16, 0.1 N, per jaw
JAW_WIDTH = 0x2102            # UNSIGNED16, 0.1 mm
RATED_GRIP_FORCE = 0x2103     # UNSIGNED16, 0.1 N per jaw at 1000 ‰
SIMULATED_FAULT = 0x2110

PROFILE_POSITION = 1
PROFILE_TORQUE = 4
MODES = (PROFILE_POSITION, PROFILE_TORQUE)
# read at every use, never cached: an RPDO writing only these leaves the parameters as they are
SET_POINT_OBJECTS = frozenset((CONTROLWORD, TARGET_TORQUE, TARGET_POSITION, MODES_OF_OPERATION,
                               SIMULATED_FAULT))

CW_NEW_SET_POINT = 0x0010
CW_RELATIVE = 0x0040
SW_SET_POINT_ACK = 0x1000
SIMULATED_FAULT_CODES = range(0x2000, 0x8000)
ABORT_MAX_LESS_THAN_MIN = 0x06090036   # CiA 301: maximum value is less than minimum value
DEFAULT_CYCLE_S = 0.01
POSITION_LIMIT_MAX = 6553500  # µm: 0x2102 (0.1 mm, UNSIGNED16) must hold the width


def _error_register_bits(code: int) -> int:
    """CiA 301 error-register bit of an EMCY error code's class (besides bit 0, generic)."""
    return {0x2: 0x02, 0x3: 0x04, 0x4: 0x08}.get(code >> 12, 0x20)


class DriveApplication:
    """The drive's application: CiA 402 state machine + actuator on the OD (see module docstring)."""

    def __init__(self, drive: "GripperDrive"):
        self._drive = drive
        self._objects = drive.objects
        self.sm = cia402.StateMachine()
        self.axis = JawAxis()
        self.fault = 0                      # the active fault's error code (0: none)
        self.master_lost = False
        self._cw_pending = False
        self._last_cw = 0
        self._target_um = None              # profile position: the latched set-point
        self._ack = False
        self._mode = PROFILE_POSITION
        self._params = None
        self._width_initialised = False

    # -- parameters (re-read after any SDO write / start-up value)
    def invalidate(self, index: int | None = None, subindex: int | None = None) -> None:
        self._params = None

    def _read_params(self) -> dict:
        p = self._params
        if p is None:
            read = self._objects.read
            lim = self.axis.limits
            lim.min_um = float(read(POSITION_LIMIT, 1))
            lim.max_um = float(read(POSITION_LIMIT, 2))
            lim.velocity_um_s = float(read(PROFILE_VELOCITY))
            lim.slope_permille_s = float(read(TORQUE_SLOPE))
            lim.max_torque = float(read(MAX_TORQUE))
            lim.rated_force = float(read(RATED_GRIP_FORCE))
            self.sm.quick_stop_option = read(QUICK_STOP_OPTION)
            self.sm.fault_reaction_option = read(FAULT_REACTION_OPTION)
            cycle_us = read(COMM_CYCLE_PERIOD)
            p = self._params = {"dt": cycle_us / 1e6 if cycle_us else DEFAULT_CYCLE_S,
                                "window": float(read(POSITION_WINDOW)),
                                "abort": read(ABORT_CONNECTION)}
            if not self._width_initialised:
                self.axis.width_um = lim.max_um
                self._width_initialised = True
            self.axis.width_um = min(max(self.axis.width_um, lim.min_um), lim.max_um)
        return p

    # -- SDO rules of the application objects
    def check_write(self, index: int, subindex: int, value, startup: bool) -> None:
        ok = True
        if index == MODES_OF_OPERATION:
            ok = value in MODES
        elif index == QUICK_STOP_OPTION:
            ok = value in cia402.QUICK_STOP_OPTIONS
        elif index == FAULT_REACTION_OPTION:
            ok = value in cia402.FAULT_REACTION_OPTIONS
        elif index == ABORT_CONNECTION:
            ok = value in cia402.ABORT_CONNECTION_OPTIONS
        elif index == SIMULATED_FAULT:
            ok = value == 0 or value in SIMULATED_FAULT_CODES
        elif index == POSITION_LIMIT and subindex in (1, 2):
            other = self._objects.read(POSITION_LIMIT, 3 - subindex)
            low, high = (value, other) if subindex == 1 else (other, value)
            ok = 0 <= value <= POSITION_LIMIT_MAX
            if ok and low >= high:
                raise SdoAbortedError(ABORT_MAX_LESS_THAN_MIN)   # CiA 301: min >= max
        elif index in (PROFILE_VELOCITY, TORQUE_SLOPE) and value < 1:
            # 0: jaws that never move / a stop ramp that never ends (the EDS's LowLimit 1 too)
            raise SdoAbortedError(ABORT_VALUE_TOO_LOW)
        if not ok:
            raise SdoAbortedError(ABORT_VALUE_RANGE)

    def written(self, index: int, subindex: int) -> None:
        """An SDO download to 0x6040 / 0x6060 / 0x2110: acted on once the value is stored."""
        self._drive.link.scheduler.call_at(0.0, self._after_sdo)
        if index == CONTROLWORD:
            self._cw_pending = True

    def _after_sdo(self) -> None:
        self._read_params()
        self._evaluate()
        self._publish()

    def rpdo_applied(self, indexes: frozenset[int]) -> None:
        """An RPDO wrote ``indexes``: the controlword is evaluated at once; a parameter (0x6072,
        0x6081, 0x6087, ...: anything but the set-points) is re-read as after an SDO download."""
        if CONTROLWORD in indexes:
            self._cw_pending = True
        if indexes - SET_POINT_OBJECTS:
            self.invalidate()

    # -- life cycle
    def reset(self) -> None:
        """Power-on / NMT reset node: the state machine starts again (drive function off)."""
        self.sm = cia402.StateMachine()
        self._params = None
        self._read_params()
        self.sm.power_on()
        self.axis.disabled()
        self.fault = 0
        self.master_lost = False
        self._cw_pending = False
        self._last_cw = 0
        self._target_um = None
        self._ack = False
        self._publish()

    # -- events
    def raise_fault(self, code: int, emcy: bool = True, register_bits: int | None = None) -> None:
        """Transition 13 with ``code`` in 0x603F; ``emcy``: its EMCY (the device error, error
        register bit 0 and ``register_bits``, by default the code's class bit) - sent now, or,
        in STOPPED, once the node leaves it (:meth:`node_sim.emcy.EmcyProducer.resume`)."""
        if self.sm.state in (cia402.State.FAULT, cia402.State.FAULT_REACTION_ACTIVE):
            return
        self.fault = code
        self._objects.store(ERROR_CODE, 0, code)
        if emcy:
            bits = _error_register_bits(code) if register_bits is None else register_bits
            self._drive.emcy.device_error(code, bits)
        self.sm.fault()
        if not self.sm.drive_enabled:
            self.axis.disabled()

    def connection_lost(self, nmt_stop: bool = False) -> None:
        """The master is gone (a consumed heartbeat lost, or ``nmt_stop``: the NMT stop command):
        0x603F, statusword bit 7, the 0x6007 reaction. With 0x6007 = 1 the fault's EMCY 0x8130 is
        the heartbeat consumer's on a lost heartbeat; on an NMT stop the fault's own (error
        register bits 0 and 4 in 0x1001 at once, the EMCY when the node leaves STOPPED - CiA 301
        sends none in STOPPED - and its error reset on the fault reset)."""
        self.master_lost = True
        option = self._read_params()["abort"]
        if self.sm.state not in (cia402.State.FAULT, cia402.State.FAULT_REACTION_ACTIVE):
            self._objects.store(ERROR_CODE, 0, EMCY_HEARTBEAT)
        if option == 1:
            self.raise_fault(EMCY_HEARTBEAT, emcy=nmt_stop, register_bits=ERR_REG_COMMUNICATION)
        else:
            self.sm.abort_connection(option)
        if not self.sm.drive_enabled:
            self.axis.disabled()
        self._publish()

    def connection_back(self) -> None:
        self.master_lost = False
        if self.fault == 0 and self._objects.read(ERROR_CODE) == EMCY_HEARTBEAT:
            self._objects.store(ERROR_CODE, 0, 0)
        self._publish()

    # -- the SYNC step
    def sample(self, reading=None, counter: int | None = None) -> None:
        self._drive.rpdo.on_sync()    # first: a parameter a synchronous RPDO writes holds from this SYNC
        p = self._read_params()
        self._evaluate()
        self._step(p)
        self._publish()

    def _evaluate(self) -> None:
        read = self._objects.read
        if self._drive.objects.read(SIMULATED_FAULT) and self.fault == 0:
            self.raise_fault(read(SIMULATED_FAULT))
        mode = read(MODES_OF_OPERATION)
        if mode != self._mode and mode in MODES:   # an unsupported mode (only bypassing the rules): kept
            self._mode = mode
            self._target_um = None            # a new mode starts from where the jaws are
            self._ack = False
        if not self._cw_pending:
            return
        self._cw_pending = False
        cw = read(CONTROLWORD)
        was_fault = self.sm.state is cia402.State.FAULT
        self.sm.command(cw, fault_present=False)
        if was_fault and self.sm.state is cia402.State.SWITCH_ON_DISABLED:     # transition 15
            self.fault = 0
            self._objects.store(ERROR_CODE, 0, EMCY_HEARTBEAT if self.master_lost else 0)
            self._objects.store(SIMULATED_FAULT, 0, 0)
            self._drive.emcy.device_error(None)
        if not self.sm.drive_enabled:
            self.axis.disabled()
        if self.sm.follows_set_points and self._mode == PROFILE_POSITION:
            rising = cw & CW_NEW_SET_POINT and not self._last_cw & CW_NEW_SET_POINT
            if rising:
                target = float(read(TARGET_POSITION))
                if cw & CW_RELATIVE:
                    target += self._target_um if self._target_um is not None else self.axis.width_um
                self._target_um = target
                self._ack = True
        if not cw & CW_NEW_SET_POINT:
            self._ack = False
        self._last_cw = cw

    def _step(self, p: dict) -> None:
        sm, axis = self.sm, self.axis
        dt = p["dt"]
        if not sm.drive_enabled:
            axis.disabled()
            return
        halt = sm.follows_set_points and self._last_cw & cia402.CW_HALT
        if sm.ramp is not None or halt:
            if axis.stop_ramp(dt) and sm.ramp is not None:
                sm.stop_complete()
            return
        if not sm.follows_set_points:
            return                             # QUICK STOP ACTIVE after its ramp (codes 5, 6): stay still
        if self._mode == PROFILE_TORQUE:
            axis.torque_step(dt, float(self._objects.read(TARGET_TORQUE)))
        else:
            target = self._target_um if self._target_um is not None else axis.width_um
            lim = axis.limits
            clamped = min(max(target, lim.min_um), lim.max_um)
            axis.position_step(dt, clamped)
            axis.internal_limit = axis.internal_limit or clamped != target

    def _publish(self) -> None:
        """The statusword and the actual values into the OD (what TPDOs and SDO uploads read)."""
        store, sm, axis = self._objects.store, self.sm, self.axis
        sw = sm.statusword()
        if self.master_lost:
            sw |= cia402.SW_WARNING
        if axis.internal_limit and sm.drive_enabled:
            sw |= cia402.SW_INTERNAL_LIMIT
        if self._target_reached():
            sw |= cia402.SW_TARGET_REACHED
        if self._ack and self._mode == PROFILE_POSITION:
            sw |= SW_SET_POINT_ACK
        sw |= grip_state_statusword(int(axis.grip_state))
        store(STATUSWORD, 0, sw)
        store(MODES_DISPLAY, 0, self._mode)
        torque = int(round(axis.torque))
        store(TORQUE_ACTUAL, 0, torque)
        store(TORQUE_DEMAND, 0, torque)
        store(POSITION_ACTUAL, 0, int(round(axis.width_um)))
        store(GRIP_STATE, 0, int(axis.grip_state))
        store(GRIP_FORCE, 0, max(-32768, min(32767, int(round(axis.force_per_jaw)))))
        store(JAW_WIDTH, 0, max(0, min(65535, int(round(axis.width_um / 100.0)))))

    def _target_reached(self) -> bool:
        sm, axis = self.sm, self.axis
        if sm.state is cia402.State.QUICK_STOP_ACTIVE:
            return sm.ramp is None
        if not sm.follows_set_points:
            return False
        if self._last_cw & cia402.CW_HALT:
            return axis.torque == 0 or not axis.moving
        if self._mode == PROFILE_TORQUE:
            lim = axis.limits.max_torque
            target = max(-lim, min(lim, float(self._objects.read(TARGET_TORQUE))))
            return abs(axis.torque - target) < 0.5
        if self._target_um is None:
            return True
        window = self._params["window"] if self._params else 0.0
        return not axis.moving and abs(axis.width_um - self._target_um) <= window


class GripperDrive(TaxelNode):
    """One gripper drive (see module docstring): ``node_id`` 1..127 on ``link``'s channel.

    Services as :class:`node_sim.node.TaxelNode` (``nmt``, ``heartbeat``, ``heartbeat_consumer``,
    ``sdo``, ``sync``, ``pdo``, ``emcy``) plus ``rpdo``; ``drive`` is the application
    (:class:`DriveApplication`: ``drive.sm`` the CiA 402 state machine, ``drive.axis`` the jaws).
    """

    SCALAR_READING = False                 # a SYNC brings no reading: the drive samples itself
    APPLICATION_OBJECTS = (MODES_OF_OPERATION, QUICK_STOP_OPTION, FAULT_REACTION_OPTION, ABORT_CONNECTION,
                           SIMULATED_FAULT, POSITION_LIMIT, PROFILE_VELOCITY, TORQUE_SLOPE)

    def __init__(self, node_id: int, link, od=None, eds_path=GRIPPER_EDS_PATH):
        if od is None:  # checked against the shipped drive EDS, not the taxel node's
            od = odx.load_od(node_id, eds_path, "gripper drive")
        super().__init__(node_id, link, od, eds_path)
        self.drive: DriveApplication = self.detector
        self.rpdo = RpdoEngine(self.nmt, self.objects, self.emcy.rpdo_error, self.drive.rpdo_applied,
                               check=self._rpdo_value_allowed)
        rpdo_objects = self.rpdo.comm + self.rpdo.mapping
        self.sdo.add_check(rpdo_objects, self.rpdo.check_write)
        self.sdo.add_written(rpdo_objects, self.rpdo.written)
        self.sdo.add_written((CONTROLWORD, MODES_OF_OPERATION, SIMULATED_FAULT), self.drive.written)

    def _new_detector(self):
        return DriveApplication(self)

    def _rpdo_value_allowed(self, index: int, subindex: int, data: bytes) -> bool:
        """An RPDO's value for ``index:subindex``: the SDO rules (EDS limits, the drive's own) hold
        for it too - a PDO cannot abort, so a refused value is not written (:mod:`node_sim.rpdo`)."""
        try:
            self.sdo.check_write(index, subindex, self.objects.variable(index, subindex), data, startup=False)
        except SdoAbortedError:
            return False
        return True

    def configure(self, values) -> None:
        super().configure(values)
        self.rpdo.invalidate()

    # -- frames
    def on_rpdo(self, can_id: int, data: bytes) -> bool:
        """A frame that may be one of the drive's RPDOs (True if it was)."""
        if self.silent:
            return False
        return self.rpdo.on_rpdo(can_id, data)

    def on_nmt(self, command: int) -> None:
        before = self.nmt.state
        super().on_nmt(command)            # leaving STOPPED: the EMCYs owed are sent there
        if command == NMT_STOP and before != STOPPED and self.nmt.state == STOPPED:
            self.drive.connection_lost(nmt_stop=True)   # CiA 402: NMT stopped is an abort-connection event
        elif before == STOPPED and self.nmt.state != STOPPED and not self.heartbeat_consumer.lost:
            self.drive.connection_back()   # the stop's communication error ends (bit 7, 0x603F)

    # -- the world's side (call with the channel lock held)
    def jaw_blocked_at(self, width_mm: float | None) -> None:
        """An object ``width_mm`` wide is between the jaws (None: none): closing jaws stop there."""
        self.drive.axis.jaw_blocked_at(None if width_mm is None else width_mm * 1000.0)

    def part_lost(self) -> None:
        """The part slipped out of the jaws (grip state PART_LOST, the jaws close on)."""
        self.drive.axis.part_lost()

    @property
    def grip_force_n(self) -> float:
        """Normal force of one jaw on the part, N (0x2101 / 10 before rounding)."""
        return self.drive.axis.force_per_jaw / 10.0

    @property
    def width_mm(self) -> float:
        return self.drive.axis.width_um / 1000.0

    @property
    def grip_state(self) -> GripState:
        return self.drive.axis.grip_state

    @property
    def cia402_state(self) -> str:
        return self.drive.sm.state.label if self.drive.sm.state is not None else "START"

    # -- NMT hooks
    def _heartbeat_event(self, node_id: int, lost: bool) -> None:
        super()._heartbeat_event(node_id, lost)
        if lost:
            self.drive.connection_lost()
        elif not self.heartbeat_consumer.lost:
            self.drive.connection_back()

    def _before_boot(self) -> None:
        super()._before_boot()
        self.rpdo.reset()

    def _after_boot(self) -> None:
        super()._after_boot()
        if self.drive.sm.state is None:
            self.drive.reset()             # power on: transitions 0 and 1

    def _leave_operational(self) -> None:
        super()._leave_operational()
        self.rpdo.reset()

    def _reset_communication(self) -> None:
        """Reset communication: 0x1000-0x1FFF back; the drive keeps its state (a held part stays)."""
        self.objects.restore_communication()
        self.detector.invalidate()
        self.emcy.reset()
        self.rpdo.invalidate()


