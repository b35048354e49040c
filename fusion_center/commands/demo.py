"""``fusion-center demo``: matrix57's node twins and the fusion centre on one embedded virtual bus."""

from __future__ import annotations

import argparse
import uuid

from .run import add_common_outputs, execute, finish_summary, load_run_scene, setup_logging

HELP = ("demo: node twins of a scene (default the 57-taxel matrix) and the fusion centre on an embedded "
        "virtual bus (no bus flags: python-can's configuration is not used); --mode raw|decision to compare both")

DEFAULT_SCENE = "matrix57"  # the bundled scenes/matrix57.toml (taxel_net.resources)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default=str(DEFAULT_SCENE), metavar="FILE",
                        help="scene file or bundled scene name (default: matrix57; list: fusion-center scenes)")
    parser.add_argument("--drop-node", action="append", default=[], metavar="ID@CYCLE",
                        help="silence node ID from SYNC cycle CYCLE on (repeatable), e.g. 18@50")
    parser.add_argument("--slow-down", type=float, default=1.0, metavar="K",
                        help="run every bus time K times longer (SYNC period, synchronous window, heartbeats, "
                             "inhibit and event timers), 1..1000 (default 1: the scene's own times): for a "
                             "scene whose twins and centre do not keep its SYNC period in one process")
    add_common_outputs(parser)
    from ..robotics.cli import add_arguments as add_robotics_arguments

    add_robotics_arguments(parser, live=True, bag=True)


def parse_drops(items: list[str], scene) -> dict[int, list[int]]:
    from taxel_net.errors import UsageError

    node_ids = {t.node_id for t in scene.taxels if t.channel == 0}
    drops: dict[int, list[int]] = {}
    for item in items:
        node, sep, cycle = item.partition("@")
        try:
            node_id, at = int(node), int(cycle)
        except ValueError:
            raise UsageError(f"--drop-node {item!r}: expected ID@CYCLE, e.g. 18@50") from None
        if not sep or node_id not in node_ids:
            raise UsageError(f"--drop-node {item!r}: node {node} is not a node of the scene's channel 0")
        if at < 0:
            raise UsageError(f"--drop-node {item!r}: cycle must be >= 0")
        drops.setdefault(at, []).append(node_id)
    return drops


SLOW_DOWN_MAX = 1000.0


def slowed_down(scene, factor: float):
    """``scene`` with every bus time ``factor`` times longer: SYNC period (0x1006), synchronous
    window (0x1007), heartbeat producer and consumer times (0x1017, 0x1016) and the master's
    heartbeat, TPDO inhibit time and event timer (0x1800:3, :5). Per-cycle physics and fusion are
    unchanged; times (a record's ``t``) and per-second rates (slip velocity) are in the slowed
    clock. A time the objects cannot hold (16-bit ms / 100 µs) is a one-line error."""
    import dataclasses

    from taxel_net.errors import UsageError
    from taxel_net.scene import MASTER_HEARTBEAT_MAX_MS

    if not (1.0 <= factor <= SLOW_DOWN_MAX):  # also refuses NaN
        raise UsageError(f"--slow-down {factor}: must lie in 1..{SLOW_DOWN_MAX:g}")
    if factor == 1.0:
        return scene
    bus = scene.bus

    def scaled(name: str, value: int, limit: int) -> int:
        out = int(round(value * factor))
        if out > limit:
            raise UsageError(f"--slow-down {factor:g}: the scene's {name} {value} becomes {out}, "
                             f"more than its object holds ({limit})")
        return out

    master_hb = scene.master.heartbeat_ms
    master = scene.master if master_hb is None else dataclasses.replace(
        scene.master, heartbeat_ms=scaled("[master] heartbeat_ms", master_hb, MASTER_HEARTBEAT_MAX_MS))
    bus = dataclasses.replace(
        bus, sync_period_ms=bus.sync_period_ms * factor,
        sync_window_us=scaled("sync window (us)", bus.sync_window, 0xFFFFFFFF),
        heartbeat_producer_ms=scaled("heartbeat_producer_ms", bus.heartbeat_producer_ms,
                                     MASTER_HEARTBEAT_MAX_MS if master_hb is None else 0xFFFF),
        heartbeat_consumer_ms=scaled("heartbeat_consumer_ms", bus.heartbeat_consumer_ms, 0xFFFF),
        inhibit_time_100us=scaled("inhibit_time_100us", bus.inhibit_time_100us, 0xFFFF),
        event_timer_ms=scaled("event_timer_ms", bus.event_timer_ms, 0xFFFF))
    return dataclasses.replace(scene, bus=bus, master=master)


def fell_behind(summary: dict, period_ms: float) -> str | None:
    """A warning when most cycles were degraded with PDOs late: the twins and the centre did
    not keep the SYNC period in one process (``--slow-down`` suggested from the p99 latency)."""
    late = summary["counters"].get("late", 0)
    if not late or summary["degraded_cycles"] * 2 <= max(summary["records"], 1):
        return None
    p99 = summary.get("latency_ms_p99") or 0.0
    k = 2
    while k * period_ms < 2 * p99 and k < SLOW_DOWN_MAX:
        k *= 2
    return (f"{summary['degraded_cycles']} of {summary['records']} cycles degraded, {late} PDOs late: the node twins "
            f"and the centre did not keep the {period_ms:g} ms SYNC in one process on this host; decisions of "
            f"degraded cycles rest on the taxels heard; try --slow-down {k}")


def run_demo(scene, cycles: int, *, drops: dict[int, list[int]] | None = None, json_lines=None, trace=None,
             live: bool = False, boot_timeout: float = 3.0, channel_tag: str | None = None,
             keep_records: bool | int = True, on_record=(), outputs=None):
    """Start the node twins (``node_sim.rig.Rig``) and the fusion centre on a private virtual
    channel, run ``cycles`` SYNC cycles, return (service, summary dict)."""
    from node_sim.rig import Rig

    from ..service import FusionService

    tag = channel_tag or uuid.uuid4().hex[:8]
    channels = [f"demo-{tag}-{name}" for name in scene.bus.channels]
    drops = drops or {}
    service = FusionService(scene, interface="virtual", channels=channels, json_lines=json_lines, trace=trace,
                            keep_records=keep_records)
    service.on_record.extend(on_record)
    truth = None
    if service.pipeline.grip is not None and getattr(scene, "grasp", None) is not None:
        from ..service.grasp_truth import TruthTable

        truth = service.pipeline.grasp_truth = TruthTable()  # the world's truth in the records (grasp_truth)
    rig = Rig(scene, interface="virtual", channel=channels, on_truth=truth.add if truth is not None else None)
    service.rig = rig

    def before_sync(cycle: int) -> None:
        for node_id in drops.get(cycle, ()):
            rig.drop_node(node_id)

    from .run import run_with_outputs

    def body():
        try:
            return execute(service, cycles, live=live, boot_timeout=boot_timeout,
                           before_sync=before_sync, on_start=rig.start)
        finally:
            rig.stop()

    summary = run_with_outputs(service, outputs, body)
    return service, summary


def run(args) -> int:
    from ..service.traces import check_trace_target

    from ..robotics import cli as robotics

    from . import check_output_paths

    setup_logging()
    check_output_paths(args)  # an output naming an input or another output: one line, nothing written
    scene, cycles = load_run_scene(args)
    nominal_ms = scene.bus.sync_period_ms
    scene = slowed_down(scene, args.slow_down)
    drops = parse_drops(args.drop_node, scene)
    check_trace_target(args.log)
    robotics.check(args)
    from .run import zenoh_settings

    # --zenoh and --foxglove: the robotics bridge process (docs/robotics.md, *The bridge process*)
    outputs = robotics.open_outputs(args, scene, threaded=True, zenoh=zenoh_settings(args),
                                    source={"scene": args.scene, "mode": args.mode, "slow_down": args.slow_down})
    _, summary = run_demo(scene, cycles, drops=drops, json_lines=args.json_lines, trace=args.log,
                          live=not args.no_live, boot_timeout=args.boot_timeout, keep_records=False,
                          outputs=outputs)
    if args.slow_down != 1.0:
        summary["slow_down"] = (f"{args.slow_down:g}x: SYNC every {scene.bus.sync_period_ms:g} ms instead of "
                                f"{nominal_ms:g} ms, every bus time likewise (per-cycle results unchanged)")
    warning = fell_behind(summary, scene.bus.sync_period_ms)
    if warning:
        summary["warning"] = warning
    return finish_summary(summary, "demo")
