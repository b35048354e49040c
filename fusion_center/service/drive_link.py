"""The centre's end of the gripper drive (issue 23): boot, the command in RPDO1, its latency, its log.

:class:`DriveLink` is the part of :class:`~.fusion_service.FusionService` that talks to the scene's
CiA 402 drive (``[gripper]``, ``docs/gripper-drive.md``); what to command is the pipeline's grip
stage (:mod:`.grip_stage`, pure and replayable), how it is sent is here.

**Boot** (:meth:`DriveLink.boot`, between the taxels' SDO configuration and the NMT start of all
nodes): wait for the drive to be heard (boot-up or heartbeat; it boots with the taxel nodes), read
its statusword 0x6041 and torque 0x6077 over SDO, write what the master owns of its start-up values
(``taxel_net.gripper.startup_values``: heartbeat producer 0x1017, the master's heartbeat in its
consumer 0x1016:1, SYNC counter overflow 0x1019, the SYNC period 0x1006) and the mode the task needs,
0x6060 = 4 (profile torque). The drive's stored parameters (rated force, limits, slopes, 0x6007) are
the rig's / the DCF's. A drive found in OPERATION ENABLED with a positive torque holds a part (a
centre started again): its mode is left alone. The drive is never reset by this centre: the master
resets the taxel nodes one by one on a scene with a drive (``Master.wait_for_boot``), not with the
broadcast, and the NMT start that follows is harmless to a running drive. Its CiA 402 walk to
OPERATION ENABLED is done per cycle by the grip stage in RPDO1 (a synchronous RPDO, applied at the
next SYNC).

**Each cycle** (:meth:`DriveLink.send_command`, called by the service as soon as the pipeline has
what the command needs - ``CyclePipeline.evaluate_command`` - before the rest of the record is
made, in the thread that evaluated it; :meth:`DriveLink.after_record` once the record is made): the grip stage's ``(controlword, target torque ‰)``
goes out in RPDO1 (0x200 + node-ID: 0x6040 U16, 0x6071 I16, 0x607A I32 = 0), through the event
stream (so it is in the trace); SYNC -> command on the bus is measured (perf_counter at the SYNC's
send to perf_counter after this send) into :attr:`latency` (a histogram like SYNC -> record's).
Drive faults, quick stops, a lost drive heartbeat, a drive not NMT operational, a mode other than
profile torque and a takeover's implausible force are logged rate-limited (the service's
``RateLimitedLog``; counted by the grip stage).

**A drive not NMT operational** (2026-11-30 (stop 32): reset - a boot-up -, or stopped by someone
mid-run; it sends no PDO and drops its RPDO1): :meth:`DriveLink.start_again` sends it an NMT start
(0x01 to its node-ID; never a reset) at most once every :data:`START_EVERY_S` s, under the scene's
``[master] restart = "always"`` (the rule the master applies to the taxel nodes; ``"never"``: only
flagged and logged); counted ``nmt_starts``. The grip stage's re-enable walk then takes it back to
OPERATION ENABLED. A drive that was reset runs with its stored start-up values afterwards (the
master's part, above, is not written again).
"""

from __future__ import annotations

import logging
import struct
import time
from collections import deque

from taxel_net import gripper as tg
from .aggregates import LatencyHistogram
from .stream import RateLimitedLog

logger = logging.getLogger("fusion_center.grip")

COB_RPDO1 = 0x200
STATUSWORD, TORQUE_ACTUAL, MODE = 0x6041, 0x6077, 0x6060
PROFILE_TORQUE = 4
_RPDO1 = struct.Struct("<Hhi")
LATENCY_SAMPLES = 4096
COB_NMT, NMT_START = 0x000, 0x01
START_EVERY_S = 1.0   # at most one NMT start of the drive per this many seconds
# what the master writes of the drive's start-up values (the rest are the drive's stored parameters)
MASTER_OWNS = ((tg.HEARTBEAT_PRODUCER, 0), (tg.CONSUMER_HEARTBEAT, 1), (tg.SYNC_OVERFLOW, 0),
               (tg.COMM_CYCLE_PERIOD, 0))


def rpdo1_payload(controlword: int, permille: int) -> bytes:
    """RPDO1 of the drive: controlword, target torque (‰), target position 0 (unused in profile torque)."""
    return _RPDO1.pack(controlword & 0xFFFF, permille, 0)


class DriveLink:
    """The drive of ``service.scene`` (module docstring); ``node``: canopen's RemoteNode for SDO."""

    def __init__(self, service, networks):
        import canopen

        from taxel_net.resources import gripper_eds_path
        from taxel_net.eds_file import import_eds

        self.service = service
        self.stream = service.stream
        self.spec = service.scene.gripper
        self.channel = self.spec.channel
        self.cob_rpdo1 = COB_RPDO1 + self.spec.node_id
        self.node = canopen.RemoteNode(self.spec.node_id, import_eds(gripper_eds_path()))
        self.node.sdo.RESPONSE_TIMEOUT = 0.5
        networks[self.channel].add_node(self.node)
        self.latency = LatencyHistogram()          # SYNC sent -> RPDO1 sent, ms
        self.latency_ms: deque[float] = deque(maxlen=LATENCY_SAMPLES)
        self.commands_sent = 0
        self.found: dict | None = None             # what the boot found: statusword, torque, takeover
        self.sdo_failures = 0
        self.starts = 0                            # NMT starts sent to the drive found not operational
        self._last_start: float | None = None      # monotonic time of the last one
        self._log = RateLimitedLog(logger, 2.0)
        from .grasp_outcome import GraspOutcome

        self.outcome = GraspOutcome()              # the summary's verdict, record by record

    # ------------------------------------------------------------------ boot
    def heard(self) -> bool:
        with self.stream.lock:
            return self.stream.assembler.drive.last_heard >= 0

    def boot(self, timeout_s: float) -> bool:
        """Wait for the drive, read its state, write the master's part of its configuration
        (module docstring). False (logged) when it was not heard within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while not self.heard():
            if time.monotonic() >= deadline:
                logger.warning("gripper drive (node %d) not heard within %.1f s: not configured; the grip "
                               "stage commands it once its state is seen", self.spec.node_id, timeout_s)
                return False
            time.sleep(0.005)
        statusword = self._upload(STATUSWORD, "H")
        torque = self._upload(TORQUE_ACTUAL, "h")
        holding = statusword is not None and statusword & 0x6F == 0x27 and (torque or 0) > 0
        self.found = {"statusword": statusword, "torque_permille": torque, "holding": holding}
        values = tg.startup_values(self.service.scene)
        writes = [(index, sub, values[(index, sub)]) for index, sub in MASTER_OWNS]
        if not holding:
            writes.append((MODE, 0, PROFILE_TORQUE))
        for index, sub, value in writes:
            self._download(index, sub, value)
        if holding:
            logger.info("gripper drive holds a part (torque %d permille): taken over without a reset", torque)
        return True

    def _upload(self, index: int, fmt: str):
        try:
            return struct.unpack("<" + fmt, self.node.sdo.upload(index, 0)[:struct.calcsize(fmt)])[0]
        except Exception as exc:  # noqa: BLE001 - an SDO failure is logged, never fatal
            self.sdo_failures += 1
            self._log.warning("drive_sdo", "gripper drive: SDO upload 0x%04X failed: %s", index, exc)
            return None

    def _download(self, index: int, sub: int, value: int) -> None:
        try:
            var = self.node.sdo[index][sub] if sub else self.node.sdo[index]
            var.raw = value
        except Exception as exc:  # noqa: BLE001
            self.sdo_failures += 1
            self._log.warning("drive_sdo", "gripper drive: SDO download 0x%04X:%d = %r failed: %s", index, sub,
                              value, exc)

    # ------------------------------------------------------------------ every cycle
    def send_command(self, sync_sent: float | None) -> None:
        """Send the grip stage's command of this cycle (if any) and measure SYNC -> command: right
        after ``CyclePipeline.evaluate_command``, before the rest of the record is made."""
        grip = self.service.pipeline.grip
        command = grip.command if grip is not None else None
        if command is not None:
            self.stream.transmit(self.channel, self.cob_rpdo1, rpdo1_payload(*command))
            self.commands_sent += 1
            if sync_sent is not None:
                ms = (time.perf_counter() - sync_sent) * 1e3
                self.latency.add(ms)
                self.latency_ms.append(ms)

    def after_record(self, cycle: int, record: dict) -> None:
        """The cycle's record, once made: the grasp's verdict, rate-limited log lines."""
        self.outcome.add(record)
        flags = record.get("grip_flags") or ()
        if flags:
            detail = record.get("grip_detail") or {}
            state = (record.get("grip") or {}).get("drive_state")
            if "drive_fault" in flags:
                self._log.warning("drive_fault", "cycle %d: gripper drive in %s (error code %s)", cycle, state,
                                  detail.get("error_code", "-"))
            if "quick_stop" in flags:
                self._log.warning("drive_quick_stop", "cycle %d: gripper drive in QUICK STOP ACTIVE", cycle)
            if "drive_lost" in flags:
                self._log.warning("drive_lost", "cycle %d: gripper drive's heartbeat lost", cycle)
            if "drive_mode" in flags:
                self._log.warning("drive_mode", "cycle %d: gripper drive not in profile torque (0x6061 is not %d): "
                                  "its target torque is ignored", cycle, PROFILE_TORQUE)
            if "drive_force_implausible" in flags:
                self._log.warning("drive_force", "cycle %d: gripper drive's force 0x2101 (%s N) disagrees with its "
                                  "torque: the takeover starts from the torque's force", cycle,
                                  (record.get("grip") or {}).get("actual_n"))
            if "drive_not_operational" in flags:
                self._log.warning("drive_not_operational", "cycle %d: gripper drive %s: not NMT operational, "
                                  "command held", cycle, "booted again" if "drive_booted" in flags else "stopped "
                                  "or pre-operational")
                self.start_again()

    def start_again(self) -> None:
        """The drive is not NMT operational (a reset, an NMT stop): an NMT start to its node-ID
        (never a reset: the centre never resets the drive) under ``[master] restart = "always"``,
        at most once every :data:`START_EVERY_S` s; the grip stage's re-enable walk then takes
        it back to OPERATION ENABLED. ``"never"``: flagged and logged only."""
        master = getattr(self.service, "master", None)
        if master is None or not master.restart:
            return
        now = time.monotonic()
        if self._last_start is not None and now - self._last_start < START_EVERY_S:
            return
        self._last_start = now
        self.starts += 1
        self.stream.transmit(self.channel, COB_NMT, bytes((NMT_START, self.spec.node_id)))

    def summary(self) -> dict:
        grip = self.service.pipeline.grip
        out = {"commands_sent": self.commands_sent,
               "sync_to_command_ms_p50": _round(self.latency.percentile(50)),
               "sync_to_command_ms_p99": _round(self.latency.percentile(99)),
               "sync_to_command_ms_max": _round(self.latency.max)}
        if grip is not None:
            out.update({k: v for k, v in grip.counts.items() if v})
        if self.found is not None and self.found["holding"]:
            out["found_holding"] = True
        if self.starts:
            out["nmt_starts"] = self.starts
        if self.sdo_failures:
            out["sdo_failures"] = self.sdo_failures
        out["grasp"] = self.outcome.as_dict()
        return out


def _round(x):
    return None if x is None else round(x, 3)
