"""ROS 2 bags of a run (``--ros2-bag DIR`` on ``run`` / ``replay``, ``fusion-center export --ros2
RUN.jsonl DIR``), written with ``rosbags``: rosbag2 version 9 (Jazzy), MCAP storage, its
``metadata.yaml`` with every topic's offered QoS profile, CDR-serialised standard messages a ROS 2
user already has (the type definitions of ``rosbags``' Jazzy type store, stored in the bag):

* ``/taxel/<pad>/map`` ``sensor_msgs/msg/Image`` ``mono8``, ``/taxel/<pad>/readings`` ``32FC1``
  (raw mode, from a run or replay - a decision log carries no readings): the images of
  :mod:`.topics`, ``header.frame_id`` the pad;
* ``/fusion/wrench`` ``geometry_msgs/msg/WrenchStamped`` (records with ``forces``, raw mode):
  ``force.x`` = total tangential force, ``force.z`` = grip force, in N (the record's kgf x
  9.80665), torque 0, ``frame_id`` ``gripper``;
* ``/grip/joint_states`` ``sensor_msgs/msg/JointState`` (records with ``grip``): joint ``jaw``,
  effort = the drive's actual force (N), position and velocity empty (the record has none);
  ``/grip/command`` likewise with the commanded force;
* ``/diagnostics`` ``diagnostic_msgs/msg/DiagnosticArray``: one ``DiagnosticStatus`` per part of
  the record - ``taxel_can/fusion`` (OK decided, WARN degraded, ERROR undecided; the decision,
  U_G, threshold, P(H1), every rule), ``taxel_can/bus``, ``taxel_can/contact``, ``taxel_can/slip``,
  ``taxel_can/grip``, ``taxel_can/world_truth`` when the record has them; values as strings
  (``json`` of the record's value).

Stamps (``header.stamp`` and the bag's time) are the cycle's SYNC time, as in the MCAP file
(:func:`.topics.log_time_ns`). The bag is written in ``DIR.partial/DIR`` and moved onto ``DIR``
when complete (a failed run leaves only ``DIR.partial``); ``DIR`` must not exist (rosbag2's own
rule: a bag is never appended to).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from taxel_net.errors import UsageError
from .topics import TopicMap, decision_message, bus_message, log_time_ns, truth_message

KGF_N = 9.80665
STORE = "ros2_jazzy"
PARTIAL = ".partial"


def _qos(depth: int = 10):
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(sec=0, nsec=0)  # RMW_DURATION_UNSPECIFIED: the default (infinite)
    return Qos(history=QosHistory.KEEP_LAST, depth=depth, reliability=QosReliability.RELIABLE,
               durability=QosDurability.VOLATILE, deadline=zero, lifespan=zero,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=zero,
               avoid_ros_namespace_conventions=False)


def check_bag_target(path, option: str = "--ros2-bag") -> Path:
    """Refuse, before anything runs, a bag directory that exists (one line)."""
    p = Path(path)
    if p.exists() or p.is_symlink():
        raise UsageError(f"{option} {str(path)!r}: exists; a ROS 2 bag is written into a new directory "
                         "(rosbag2 never appends): give another name or remove it")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise UsageError(f"{option} {str(path)!r}: no directory {str(parent)!r} to create it in")
    return p


class Ros2Bag:
    """One bag being written (see the module docstring)."""

    def __init__(self, path, topics: TopicMap, *, option: str = "--ros2-bag"):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        self.target = self.path = check_bag_target(path, option)
        # written as DIR.partial/DIR (rosbags names the storage file after the bag's directory:
        # DIR/DIR.mcap once moved), moved onto DIR when complete
        self.staging = self.target.with_name(self.target.name + PARTIAL)
        if self.staging.is_dir() and not self.staging.is_symlink():
            shutil.rmtree(self.staging)
        elif self.staging.exists() or self.staging.is_symlink():
            self.staging.unlink()
        try:
            self.staging.mkdir()
        except OSError as exc:
            raise UsageError(f"{option} {str(path)!r}: cannot be written: {exc.strerror or exc}") from None
        self.partial = self.staging / self.target.name
        self.topics = topics
        self.store = get_typestore(Stores(STORE))
        self.types = self.store.types
        try:
            self.writer = Writer(self.partial, version=9, storage_plugin=StoragePlugin.MCAP)
            self.writer.open()
        except Exception as exc:  # noqa: BLE001 - rosbags' WriterError, OSError
            raise UsageError(f"{option} {str(path)!r}: cannot be written: {exc}") from None
        self.connections: dict[str, object] = {}
        self.messages = 0
        self.cycles = 0
        self.closed = False
        T = self.types
        self._Time = T["builtin_interfaces/msg/Time"]
        self._Header = T["std_msgs/msg/Header"]
        self._Image = T["sensor_msgs/msg/Image"]
        self._JointState = T["sensor_msgs/msg/JointState"]
        self._Wrench = T["geometry_msgs/msg/Wrench"]
        self._WrenchStamped = T["geometry_msgs/msg/WrenchStamped"]
        self._Vector3 = T["geometry_msgs/msg/Vector3"]
        self._Array = T["diagnostic_msgs/msg/DiagnosticArray"]
        self._Status = T["diagnostic_msgs/msg/DiagnosticStatus"]
        self._KeyValue = T["diagnostic_msgs/msg/KeyValue"]

    def _write(self, topic: str, msgtype: str, t: int, msg) -> None:
        conn = self.connections.get(topic)
        if conn is None:
            conn = self.connections[topic] = self.writer.add_connection(
                topic, msgtype, typestore=self.store, offered_qos_profiles=[_qos()])
        self.writer.write(conn, t, bytes(self.store.serialize_cdr(msg, msgtype)))
        self.messages += 1

    def _header(self, t: int, frame: str):
        return self._Header(stamp=self._Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000), frame_id=frame)

    def write(self, record: dict, readings=None) -> None:
        """One cycle's messages (fixed order: maps, readings, wrench, joint states, diagnostics)."""
        t = log_time_ns(record)
        topics = self.topics
        for pad, data in zip(topics.pads, topics.map_images(record)):
            self._write(pad.map_topic, "sensor_msgs/msg/Image", t, self._Image(
                header=self._header(t, pad.name), height=pad.height, width=pad.width, encoding="mono8",
                is_bigendian=0, step=pad.width, data=np.frombuffer(data, dtype=np.uint8)))
        if readings is not None:
            for pad, data in zip(topics.pads, topics.readings_images(readings)):
                self._write(pad.readings_topic, "sensor_msgs/msg/Image", t, self._Image(
                    header=self._header(t, pad.name), height=pad.height, width=pad.width, encoding="32FC1",
                    is_bigendian=0, step=4 * pad.width, data=np.frombuffer(data, dtype=np.uint8)))
        forces = record.get("forces")
        if isinstance(forces, dict):
            scale = KGF_N if forces.get("unit", "kgf") == "kgf" else 1.0
            fx = _number(forces.get("total_tangential")) * scale
            fz = _number(forces.get("grip_force")) * scale
            V = self._Vector3
            self._write("/fusion/wrench", "geometry_msgs/msg/WrenchStamped", t, self._WrenchStamped(
                header=self._header(t, "gripper"),
                wrench=self._Wrench(force=V(x=fx, y=0.0, z=fz), torque=V(x=0.0, y=0.0, z=0.0))))
        grip = record.get("grip")
        if isinstance(grip, dict):
            for topic, key in (("/grip/joint_states", "actual_n"), ("/grip/command", "command_n")):
                self._write(topic, "sensor_msgs/msg/JointState", t, self._JointState(
                    header=self._header(t, "gripper"), name=["jaw"], position=np.array([], dtype=np.float64),
                    velocity=np.array([], dtype=np.float64), effort=np.array([_number(grip.get(key))])))
        self._write("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", t,
                    self._Array(header=self._header(t, ""), status=self._statuses(record)))
        self.cycles += 1

    def _status(self, name: str, level: int, message: str, values: dict):
        KV = self._KeyValue
        return self._Status(level=level, name=f"taxel_can/{name}", message=message,
                            hardware_id=self.topics.name,
                            values=[KV(key=str(k), value=v if isinstance(v, str) else json.dumps(v))
                                    for k, v in values.items()])

    def _statuses(self, record: dict) -> list:
        S = self._Status
        d = decision_message(record)
        rules = d.pop("rules")
        values = {k: v for k, v in d.items()}
        for rule, result in rules.items():
            for key in ("U_G", "threshold", "decision", "p_h1"):
                if key in result:
                    values[f"rules.{rule}.{key}"] = result[key]
        level = S.ERROR if d["decision"] == "undecided" else (S.WARN if d["degraded"] else S.OK)
        out = [self._status("fusion", level, f"{d['decision']} ({d['decide_with']})", values)]
        bus = bus_message(record)
        level = S.WARN if bus["not_taking_part"] or bus["bad_frames"] or bus["late_frames"] else S.OK
        out.append(self._status("bus", level, f"closed by {bus['closed_by']}", bus))
        contact = {k: record[k] for k in ("area", "t_c", "contact_type", "fp_c", "contact_type_fp") if k in record}
        if contact:
            out.append(self._status("contact", S.OK, str(contact.get("contact_type", "")), contact))
        slip = record.get("slip")
        if isinstance(slip, dict):
            out.append(self._status("slip", S.WARN if slip.get("slipping") else S.OK,
                                    "slipping" if slip.get("slipping") else "not slipping", slip))
        grip = record.get("grip")
        if isinstance(grip, dict):
            out.append(self._status("grip", S.OK, str(grip.get("grip_state", "")), grip))
        truth = truth_message(record)
        if truth is not None:
            out.append(self._status("world_truth", S.OK, str(truth.get("truth") or truth.get("phase") or ""), truth))
        return out

    def close(self, ok: bool = True) -> None:
        """Finish the bag; ``ok``: rename ``DIR.partial`` onto ``DIR``, else leave the partial one."""
        if self.closed:
            return
        self.closed = True
        self.writer.close()
        if ok:
            os.replace(self.partial, self.target)
            self.staging.rmdir()
        elif not self.messages:  # failed before the first cycle: nothing worth keeping
            shutil.rmtree(self.staging, ignore_errors=True)


def _number(value) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else float("nan")
