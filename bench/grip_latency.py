"""SYNC -> grip command on the bus, as a bus observer sees it, and where the time goes.

    .venv/bin/python bench/grip_latency.py [--runs 3] [--cycles 600]
        [--scenes grasp_lift grasp_lift_raw grasp_fragile grasp_lift_patch grasp_lift_raw_patch
                  grasp_lift_raw_patch_fd grasp_fragile_patch] [--transports embedded udp player] [--echo 2000]
        [--rt-priority N] [--nodes-rt N] [--pin NODE_CPUS CENTRE_CPUS] [--switch-interval-ms MS]

Issue 23's goal: SYNC -> command p99 at most 2 ms on the grasp scenes at a 100 Hz SYNC. The
chapter's one-taxel grasp scenes (52 CANopen nodes a gripper) need 3.2 / 4.5 ms of wire a cycle
at 1 Mbit/s before the command can leave, so the goal is out of reach there on any host; their
patch-node variants (``*_patch``: one node a pad, packed TPDOs) need 0.34 ms (decisions), 1.71 ms
(INTEGER16 readings, classic CAN) and 0.47 ms (the same on CAN FD 1/5 Mbit/s); grasp_fragile_patch
is the fragile task on grasp_lift_patch's nodes (0.34 ms). By default every
one of them runs, side by side. For each scene and transport, ``--runs`` times:

* ``embedded``: the node twins, the drive and the grasp world (``node_sim.rig.Rig``) and the
  centre in this process on one python-can virtual bus - ``fusion-center demo``'s set-up. The
  observer is one more virtual bus on that channel: python-can stamps every frame when it is
  sent (``VirtualBus.send``, ``time.time()``), so the observer's SYNC and RPDO1 stamps are the
  sender's send times.
* ``udp``: ``node-sim --scene S`` in another process, the centre in this one, over
  udp_multicast on loopback (``fusion-center run``'s set-up); the observer is a third process
  on the group, which reads the kernel's receive stamps (``SO_TIMESTAMP``) in batches every
  0.2 s (so it adds no wake-up per frame).
* ``player``: ``udp`` with the taxel nodes at hardware speed: bench/grip_player.py answers each
  SYNC at once with that cycle's taxel TPDOs as an embedded run of the same scene recorded them
  (the run of this invocation, else one more demo run first, uninstrumented), boot-ups,
  heartbeats and SDO confirmations as the twins'; the gripper drive stays the twin
  (``node_sim.gripper.host.DriveHost``, in a process of its own, without the grasp world). The
  centre boots both and commands the drive as in ``udp``: what SYNC -> command would be against
  CAN nodes that answer within their TPDO's transmission time (docs/grip-control.md).

Scheduling (udp, player; docs/grip-control.md "2026-11-30 (stop 31)"): ``--rt-priority N`` the
centre's ``FusionService(rt_priority=N)`` (``fusion-center run --rt-priority``); ``--nodes-rt N``
the node, drive and observer processes under SCHED_FIFO N from their start - CAN nodes are
hardware, their answers do not wait for the host's other jobs; ``--pin`` their and this
process's CPUs; ``--switch-interval-ms`` the interpreter's switch interval here, restored after.

Latency of cycle k: the observer's stamp of the drive's RPDO1 (0x200 + node-ID) that carries
cycle k's command minus its stamp of SYNC k (the k-th SYNC on the bus; the RPDO1s are matched
to the records with a command, in order, and checked against their controlword and torque).

Breakdown (centre side, same clock, ``time.time()``): where SYNC -> command goes, per cycle, as
marks taken by wrappers put around the centre's methods (they add ~1 µs a mark):

* ``answers``: SYNC -> the frame that closed the cycle (its stamp: the record's
  ``closed_after_ms``) - the nodes' answers, not the centre's work; ``closed_by`` other than
  ``complete`` (a late answer: the window or the next SYNC closes the cycle) is counted apart;
* ``wake``: that frame's stamp -> the stream got the receive turn that brought it
  (``EventStream.receive_all``): the receive thread's wake-up, then the turn's datagrams read
  and unpacked (one ``recvmsg`` each; the centre's own echoes among them before 2026-11-30,
  since then dropped in the kernel: ``taxel_net.udp_filter.drop_own_frames``) and any echoes
  left dropped; 0 when that began before the frame was sent (a burst drained as it comes);
* ``assemble``: -> the cycle's evaluation starts (the turn's frames fed to the assembler under
  the stream lock, the cycle closed, its evaluation begun in the same thread);
* ``rules``, ``forces``, ``slip``, ``grip``: the pipeline's stages (decision-vector part with the
  fusion rules; eqs 24-30 / 26a in raw mode; the slip tracker; the grip law and CiA 402);
* ``record``: the rest of the evaluation before the command (record fields);
* ``send``: end of the grip stage -> the RPDO1's stamp on the bus;
* ``centre``: the closing frame's stamp -> the RPDO1's stamp: the centre's whole part.

The wire floor printed per scene: what the same cycle takes on a real CAN bus at the scene's
bit rate whatever the hosts (``fusion_center.core.bus_timing.frame_bits``, exact stuff bits):
the SYNC, every taxel node's answer (TPDO1 of 1 byte in decision mode, TPDO2 of 4 in raw mode;
patch nodes: their packed TPDOs, :func:`wire_floor_ms`; the SYNC wins arbitration, the answers
follow back to back) and the command's RPDO1.

``--echo N``: the floor of any such path on this host - a python-can virtual bus, one thread
sends a frame, a receive thread blocked on it (as the centre's and the twins' are) wakes: the
send -> wake-up time, N times, p50/p99/max; and the same between two processes over
udp_multicast (kernel stamp -> the receiving process's read).

Prints one table per scene x transport over all runs (p50/p90/p99/max and cycles per run, and
their spread), the breakdown's p50/p99 per stage, then a summary: per scene x transport the wire
floor, p50/p99 over all runs' cycles pooled, whether p99 meets the goal ("(wire)": the bus alone
exceeds it) and the load average before and after its runs; then ``uptime``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import can  # noqa: E402

from grip_latency_floors import COB_SYNC, echo_udp, echo_virtual, scene_for, wire_floor, wire_floor_ms  # noqa: E402
from grip_latency_report import (HEADER, STAGES, _loadavg, _pct, compare, print_breakdown, print_row,  # noqa: E402
                                 print_summary, uptime)
from taxel_net.resources import resolve_scene  # noqa: E402

SCENES = ("grasp_lift", "grasp_lift_raw", "grasp_fragile",
          "grasp_lift_patch", "grasp_lift_raw_patch", "grasp_lift_raw_patch_fd", "grasp_fragile_patch")
TRANSPORTS = ("embedded", "udp", "player")


# --------------------------------------------------------------------------- centre-side marks
class Marks:
    """Per cycle: time.time() marks taken by wrappers around the centre's methods."""

    def __init__(self):
        self.by_cycle: dict[int, dict[str, float]] = {}
        self.current: dict[str, float] | None = None

    def mark(self, name: str) -> None:
        if self.current is not None:
            self.current[name] = time.time()


def _wrap(obj, name: str, before=None, after=None) -> bool:
    fn = getattr(obj, name, None)
    if fn is None:
        return False

    def wrapped(*args, **kwargs):
        if before is not None:
            before(*args, **kwargs)
        out = fn(*args, **kwargs)
        if after is not None:
            after(*args, **kwargs)
        return out

    setattr(obj, name, wrapped)
    return True


def instrument(service, marks: Marks) -> None:
    """Wrap the centre's evaluation path (works on the code before and after the reorder: the
    wrapped names exist in both)."""
    pipeline = service.pipeline
    assembler = service.assembler

    turn = [0.0, 0]  # the last receive turn's start and size (the stream's receive_all)

    def turn_start(msgs, *a, **k):
        turn[0], turn[1] = time.time(), len(msgs) if hasattr(msgs, "__len__") else -1

    _wrap(service.stream, "receive_all", before=turn_start)

    def eval_start(closed, *a, **k):
        t = time.time()
        cur = marks.by_cycle.setdefault(closed.cycle, {})
        if "eval" not in cur:
            cur["eval"] = t
            cur["close_frame"] = (assembler.t0_us + closed.close_us) * 1e-6
            cur["closed_by"] = closed.closed_by
            cur["turn"], cur["turn_frames"] = turn
        marks.current = cur

    for name in ("evaluate_command", "evaluate"):
        if getattr(pipeline, name, None) is not None:
            _wrap(pipeline, name, before=eval_start)
    _wrap(pipeline, "_pattern", after=lambda *a, **k: marks.mark("rules"))
    physical = pipeline.physical
    # what the command waits for of the forces: all of them before the reorder, the totals after
    forces_name = "force_totals" if getattr(physical, "force_totals", None) is not None else "forces"
    _wrap(physical, forces_name, before=lambda *a, **k: marks.mark("forces0"),
          after=lambda *a, **k: marks.mark("forces"))
    _wrap(physical, "slip_record", before=lambda *a, **k: marks.mark("slip0"),
          after=lambda *a, **k: marks.mark("slip"))
    if pipeline.grip is not None:
        _wrap(pipeline.grip, "evaluate", before=lambda *a, **k: marks.mark("grip0"),
              after=lambda *a, **k: marks.mark("grip"))


def breakdown(marks: Marks, sync_at: dict[int, float], cmd_at: dict[int, float]) -> dict[str, list[float]]:
    """Per stage, the ms of every complete cycle with a command (module docstring)."""
    out: dict[str, list[float]] = {s: [] for s in STAGES}
    for cycle, cmd in cmd_at.items():
        m = marks.by_cycle.get(cycle)
        sync = sync_at.get(cycle)
        if m is None or sync is None or m.get("closed_by") != "complete" or "grip" not in m:
            continue
        ms = lambda a, b: (b - a) * 1e3  # noqa: E731
        forces = ms(m["forces0"], m["forces"]) if "forces" in m else 0.0
        slip = ms(m["slip0"], m["slip"]) if "slip" in m else 0.0
        rules = ms(m["eval"], m["rules"]) if "rules" in m else 0.0
        grip = ms(m["grip0"], m["grip"])
        evaluation = ms(m["eval"], m["grip"])
        out["answers"].append(ms(sync, m["close_frame"]))
        # the turn that closed the cycle may have begun before its last frame was stamped (a
        # burst drained as it comes): the wake-up is then 0, the turn's feeding all "assemble"
        turn = max(m["turn"], m["close_frame"])
        out["wake"].append(ms(m["close_frame"], turn))
        out["assemble"].append(ms(turn, m["eval"]))
        out["centre"].append(ms(m["close_frame"], cmd))
        out["rules"].append(rules)
        out["forces"].append(forces)
        out["slip"].append(slip)
        out["grip"].append(grip)
        out["record"].append(evaluation - rules - forces - slip - grip)
        out["send"].append(ms(m["grip"], cmd))
    return out


# --------------------------------------------------------------------------- matching
def match(records, syncs: list[float], cmds: list[tuple[float, bytes]], node_id: int):
    """cycle -> SYNC stamp, cycle -> RPDO1 stamp (module docstring); raises on a mismatch."""
    with_cmd = [r for r in records if (r.get("grip_detail") or {}).get("controlword") is not None]
    if len(with_cmd) != len(cmds):
        raise SystemExit(f"{len(cmds)} RPDO1 frames seen for {len(with_cmd)} records with a command")
    sync_at = {k: t for k, t in enumerate(syncs)}
    cmd_at = {}
    for r, (t, data) in zip(with_cmd, cmds):
        cw, permille, _ = struct.unpack("<Hhi", bytes(data))
        d = r["grip_detail"]
        if (cw, permille) != (d["controlword"], d["target_permille"]):
            raise SystemExit(f"cycle {r['cycle']}: RPDO1 {cw:#x}/{permille} against the record's "
                             f"{d['controlword']:#x}/{d['target_permille']}")
        cmd_at[r["cycle"]] = t
    return sync_at, cmd_at


def latencies(sync_at, cmd_at) -> list[float]:
    return [(cmd_at[c] - sync_at[c]) * 1e3 for c in sorted(cmd_at) if c in sync_at]


# --------------------------------------------------------------------------- one run
# --rt-priority: the centre's FusionService options in udp / player runs
CENTRE_OPTIONS: dict = {}
RECORDED: dict[tuple[str, int], list] = {}  # (scene, cycles) -> an embedded run's taxel answers per cycle


def run_embedded(name: str, cycles: int, instrumented: bool = True) -> dict:
    from fusion_center.commands.demo import run_demo
    from fusion_center.service import fusion_service

    scene = scene_for(name)
    tag = uuid.uuid4().hex[:8]
    observer = can.Bus(interface="virtual", channel=f"demo-{tag}-{scene.bus.channels[0]}")
    marks = Marks()
    original = fusion_service.FusionService.open

    def open_and_instrument(self):
        out = original(self)
        if instrumented:
            instrument(self, marks)
        return out

    fusion_service.FusionService.open = open_and_instrument
    try:
        service, summary = run_demo(scene, cycles, channel_tag=tag, keep_records=True)
    finally:
        fusion_service.FusionService.open = original
    frames = []
    while (msg := observer.recv(0)) is not None:
        frames.append(msg)
    observer.shutdown()
    from grip_player import record_answers

    RECORDED[name, cycles] = record_answers(scene, frames)
    return finish(scene, service, summary, frames, marks) if instrumented else {}


def finish(scene, service, summary, frames, marks) -> dict:
    node = scene.gripper.node_id
    syncs = [m.timestamp for m in frames if m.arbitration_id == COB_SYNC]
    cmds = [(m.timestamp, bytes(m.data)) for m in frames if m.arbitration_id == 0x200 + node]
    records = list(service.records)
    sync_at, cmd_at = match(records, syncs, cmds, node)
    closed_by: dict[str, int] = {}
    for r in records:
        closed_by[r["closed_by"]] = closed_by.get(r["closed_by"], 0) + 1
    centre = service.drive.latency_ms if service.drive is not None else []
    return {"lat": latencies(sync_at, cmd_at), "stages": breakdown(marks, sync_at, cmd_at),
            "closed_by": closed_by, "centre_p99": _pct(list(centre), 99),
            "late": summary["counters"].get("late", 0)}


def observer_main(group: str, port: int, out: str) -> int:
    """``--observe``: a bus observer process (module docstring), until SIGTERM; writes JSON."""
    import signal

    from taxel_net.udp_wire import udp_multicast_drain

    bus = can.Bus(interface="udp_multicast", channel=group, port=port, hop_limit=0, receive_own_messages=False)
    sock = getattr(bus, "_multicast", None)
    raw = getattr(sock, "_socket", None)
    if raw is not None:
        raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 << 20)
    drain = udp_multicast_drain(bus)
    if drain is None:
        raise SystemExit("observer: not a python-can 4.x udp_multicast bus")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    seen: list[tuple[float, int, str]] = []
    print("observing", flush=True)
    while True:
        last = stop.is_set()
        for msg in drain():
            if msg.arbitration_id == COB_SYNC or 0x200 < msg.arbitration_id < 0x280:
                seen.append((msg.timestamp, msg.arbitration_id, bytes(msg.data).hex()))
        if last:
            break
        time.sleep(0.2)
    bus.shutdown()
    Path(out).write_text(json.dumps(seen))
    return 0


NODE_CPUS: list[set[int]] = []  # --pin: the node / drive / observer processes' CPUs
NODES_RT: list[int] = []        # --nodes-rt: their SCHED_FIFO priority


def _node_process_setup() -> None:
    """In the node / drive / observer processes before exec (--pin, --nodes-rt): every thread
    they start inherits it."""
    if NODE_CPUS:
        os.sched_setaffinity(0, NODE_CPUS[0])
    if NODES_RT:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(NODES_RT[0]))


def _cpus(text: str) -> set[int]:
    """--pin's CPU list ("0" or "0,1"), ValueError when not one."""
    cpus = {int(c) for c in text.split(",")}
    if not cpus or min(cpus) < 0:
        raise ValueError
    return cpus


def _fifo_permitted(priority: int) -> bool:
    """Whether SCHED_FIFO at ``priority`` is permitted here (tried on a short-lived thread)."""
    result = []

    def probe():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0), os.sched_param(priority))
            result.append(True)
        except (OSError, AttributeError):
            result.append(False)

    t = threading.Thread(target=probe)
    t.start()
    t.join(5)
    return bool(result and result[0])


def scheduling_error(args) -> str | None:
    """One line naming the option, the value and what is allowed, for a bad --rt-priority,
    --nodes-rt, --pin or --switch-interval-ms (they ended in a traceback, --nodes-rt's inside the
    node process's preexec_fn); None when all are usable."""
    from taxel_net import realtime

    for option, value in (("--rt-priority", args.rt_priority), ("--nodes-rt", args.nodes_rt)):
        if value is None:
            continue
        try:
            realtime.check_priority(value, option)
        except ValueError as exc:
            return str(exc)
    if args.nodes_rt is not None and not _fifo_permitted(args.nodes_rt):
        return (f"--nodes-rt {args.nodes_rt}: SCHED_FIFO not permitted or not available here "
                "(needs Linux and CAP_SYS_NICE or `ulimit -r` >= N)")
    if args.pin:
        for name, text in zip(("NODE_CPUS", "CENTRE_CPUS"), args.pin):
            try:
                cpus = _cpus(text)
            except ValueError:
                return f"--pin {name} {text!r}: not a CPU list (allowed: e.g. 0 or 0,1)"
            allowed = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else cpus
            if not cpus <= allowed:
                return f"--pin {name} {text!r}: CPU(s) {sorted(cpus - allowed)} not available (allowed: {sorted(allowed)})"
    if args.switch_interval_ms is not None and not (args.switch_interval_ms > 0 and args.switch_interval_ms < 1e6):
        return f"--switch-interval-ms {args.switch_interval_ms:g}: must be > 0 (ms)"
    return None


def _start(cmd: list[str], word: str) -> subprocess.Popen:
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_node_process_setup if NODE_CPUS or NODES_RT else None)
    got: list[str] = []
    reader = threading.Thread(target=lambda: got.append(proc.stdout.readline()), daemon=True)
    reader.start()
    reader.join(60)
    if not got or word not in got[0]:
        proc.kill()
        raise SystemExit(f"{cmd[2:4]} did not start: {got} {proc.stderr.read()}")
    return proc


def run_player(name: str, cycles: int, world: bool = False) -> dict:
    """``player``: ``run_udp`` with bench/grip_player.py in node-sim's place (the taxel nodes'
    answers recorded from an embedded run of the same scene, played at once on each SYNC; the
    drive a twin)."""
    if (name, cycles) not in RECORDED:
        run_embedded(name, cycles, instrumented=False)
    return run_udp(name, cycles, player=RECORDED[name, cycles], world=world)


def run_udp(name: str, cycles: int, player: list | None = None, world: bool = False) -> dict:
    from fusion_center.commands.run import execute
    from fusion_center.service import FusionService

    scene = scene_for(name)
    group = f"239.74.{random.randint(164, 250)}.{random.randint(1, 250)}"
    port = random.randint(40000, 60000)
    with tempfile.TemporaryDirectory() as tmp:
        seen_file = Path(tmp) / "observed.json"
        observer = _start([sys.executable, str(Path(__file__).resolve()), "--observe", group, str(port),
                           str(seen_file)], "observing")
        sim = drive = None
        try:
            if player is None:
                sim = _start([sys.executable, "-m", "node_sim.cli", "--scene", str(resolve_scene(name)),
                              "--interface", "udp_multicast", "--channel", group, "--bus-option", f"port={port}",
                              "--bus-option", "hop_limit=0"], "ready")
            else:
                frames_file = Path(tmp) / "answers.json"
                frames_file.write_text(json.dumps(player))
                base = [sys.executable, str(ROOT / "bench" / "grip_player.py"), "--scene", str(resolve_scene(name)),
                        "--group", group, "--port", str(port)]
                # the drive twin in a process of its own (a device of its own on a CAN bus): its
                # SYNC handling never holds the interpreter lock the nodes' answers need
                drive = _start(base + ["--part", "drive"] + (["--world"] if world else []), "ready")
                sim = _start(base + ["--part", "nodes", "--frames", str(frames_file)], "ready")
            marks = Marks()
            service = FusionService(scene, interface="udp_multicast", channels=[group],
                                    bus_kwargs={"port": port, "hop_limit": 0}, keep_records=True,
                                    **CENTRE_OPTIONS)
            with service:
                instrument(service, marks)
                receive = getattr(getattr(service.notifiers[0], "owner", None), "_thread", None)
                clock = time.pthread_getcpuclockid(receive.ident) if receive is not None else None
                cpu0 = time.clock_gettime(clock) if clock is not None else None
                summary = execute(service, cycles, live=False, boot_timeout=5.0)
                # the receive thread's CPU time over the run (boot included), per SYNC cycle
                receive_cpu_ms = ((time.clock_gettime(clock) - cpu0) * 1e3 / max(1, service.master.sync_sent)
                                  if clock is not None else None)
        finally:
            for proc in (sim, drive):
                if proc is not None:
                    proc.terminate()
                    proc.wait(10)
            time.sleep(0.3)
            observer.terminate()
            observer.wait(20)
        seen = json.loads(seen_file.read_text())
    frames = [can.Message(timestamp=t, arbitration_id=i, data=bytes.fromhex(d)) for t, i, d in seen]
    out = finish(scene, service, summary, frames, marks)
    out["rt_threads"] = getattr(service, "rt_threads", [])
    out["receive_cpu_ms"] = receive_cpu_ms
    return out


RUNS = {"embedded": run_embedded, "udp": run_udp, "player": run_player}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--cycles", type=int, default=600)
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--transports", nargs="+", default=list(TRANSPORTS), choices=TRANSPORTS)
    ap.add_argument("--echo", type=int, default=2000, help="echo samples (0: skip)")
    ap.add_argument("--rt-priority", type=int, default=None, metavar="N",
                    help="the centre's receive thread, SYNC producer and heartbeat under SCHED_FIFO N (udp, player; "
                         "fusion-center run --rt-priority)")
    ap.add_argument("--pin", nargs=2, metavar=("NODE_CPUS", "CENTRE_CPUS"), default=None,
                    help="CPU lists (e.g. 0 1): the node/drive/observer processes on NODE_CPUS, this process "
                         "(the centre) on CENTRE_CPUS - the nodes as hardware of their own (udp, player)")
    ap.add_argument("--nodes-rt", type=int, default=None, metavar="N",
                    help="the node / drive / observer processes under SCHED_FIFO N: the stand-ins for CAN hardware "
                         "answer whatever else the host runs (udp, player)")
    ap.add_argument("--switch-interval-ms", type=float, default=None, metavar="MS",
                    help="sys.setswitchinterval in this process (the centre's) for the runs, restored after "
                         "(default: Python's 5 ms)")
    ap.add_argument("--json", metavar="OUT", help="append each scene x transport's runs to OUT (JSON lines)")
    ap.add_argument("--compare", nargs="+", metavar="JSONL", help="print --json files side by side, run nothing")
    ap.add_argument("--observe", nargs=3, metavar=("GROUP", "PORT", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.observe:
        return observer_main(args.observe[0], int(args.observe[1]), args.observe[2])
    if args.compare:
        return compare(args.compare)
    import logging

    logging.basicConfig(level=logging.ERROR)
    bad = scheduling_error(args)
    if bad:
        print(f"grip_latency: error: {bad}", file=sys.stderr)
        return 2
    if args.rt_priority is not None:
        CENTRE_OPTIONS["rt_priority"] = args.rt_priority
    if args.nodes_rt is not None:
        NODES_RT.append(args.nodes_rt)
    if args.pin:
        NODE_CPUS.append(_cpus(args.pin[0]))
        os.sched_setaffinity(0, _cpus(args.pin[1]))  # this thread: the ones it starts inherit
    switch_before = sys.getswitchinterval()
    if args.switch_interval_ms is not None:
        sys.setswitchinterval(args.switch_interval_ms / 1e3)
    try:
        return _measure(args)
    finally:
        sys.setswitchinterval(switch_before)


def _measure(args) -> int:
    print(f"code: {ROOT}   start: {uptime()}   centre options: {CENTRE_OPTIONS or 'none'}   pin: {args.pin or 'no'}   nodes-rt: {args.nodes_rt or 'no'}   "
          f"switch interval: {sys.getswitchinterval() * 1e3:g} ms")
    print(f"SYNC -> command on the bus (observer's stamps), ms; {args.runs} run(s) x {args.cycles} cycles; "
          "figures: median over runs (min-max)")
    print(HEADER)
    results = []
    for name in args.scenes:
        print(f"{name}: {wire_floor(name)}")
        floor = wire_floor_ms(name)[1]
        for transport in args.transports:
            runs = []
            load_before = _loadavg()
            for _ in range(args.runs):
                runs.append(RUNS[transport](name, args.cycles))
            load = (load_before, _loadavg())
            print_row(name, transport, runs)
            print_breakdown(runs)
            results.append((name, transport, floor, runs, load))
            if args.json:
                with open(args.json, "a", encoding="utf-8") as out:
                    out.write(json.dumps({"scene": name, "transport": transport, "code": str(ROOT),
                                          "uptime": uptime(), "loadavg": load, "wire_floor_ms": floor,
                                          "rt_priority": args.rt_priority,
                                          "pin": args.pin, "nodes_rt": args.nodes_rt,
                                          "switch_interval_ms": sys.getswitchinterval() * 1e3,
                                          "runs": runs}) + "\n")
    print_summary(results)
    if args.echo:
        for label, fn in (("virtual bus, one process", echo_virtual), ("udp_multicast, two processes", echo_udp)):
            values = fn(args.echo)
            print(f"echo floor ({label}): send -> receive thread has it, {len(values)} frames: p50 "
                  f"{_pct(values, 50):.3f} ms, p90 {_pct(values, 90):.3f}, p99 {_pct(values, 99):.3f}, "
                  f"max {max(values):.3f}")
    print(f"end: {uptime()}   cpus: {os.cpu_count()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
