"""``fusion-center demo``: matrix57's node twins and the fusion centre on one embedded virtual bus."""

from __future__ import annotations

import argparse
import uuid

from .run import add_common_outputs, execute, load_run_scene, print_summary, setup_logging

HELP = ("demo: node twins of a scene (default the 57-taxel matrix) and the fusion centre on an embedded "
        "virtual bus (no bus flags: python-can's configuration is not used); --mode raw|decision to compare both")

DEFAULT_SCENE = "matrix57"  # the bundled scenes/matrix57.toml (taxel_net.resources)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default=str(DEFAULT_SCENE), metavar="FILE",
                        help="scene file or bundled scene name (default: matrix57; list: fusion-center scenes)")
    parser.add_argument("--drop-node", action="append", default=[], metavar="ID@CYCLE",
                        help="silence node ID from SYNC cycle CYCLE on (repeatable), e.g. 18@50")
    add_common_outputs(parser)


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


def run_demo(scene, cycles: int, *, drops: dict[int, list[int]] | None = None, json_lines=None, trace=None,
             live: bool = False, boot_timeout: float = 3.0, channel_tag: str | None = None,
             keep_records: bool | int = True):
    """Start the node twins (``node_sim.rig.Rig``) and the fusion centre on a private virtual
    channel, run ``cycles`` SYNC cycles, return (service, summary dict)."""
    from node_sim.rig import Rig

    from ..service import FusionService

    tag = channel_tag or uuid.uuid4().hex[:8]
    channels = [f"demo-{tag}-{name}" for name in scene.bus.channels]
    drops = drops or {}
    service = FusionService(scene, interface="virtual", channels=channels, json_lines=json_lines, trace=trace,
                            keep_records=keep_records)
    rig = Rig(scene, interface="virtual", channel=channels)

    def before_sync(cycle: int) -> None:
        for node_id in drops.get(cycle, ()):
            rig.drop_node(node_id)

    with service:
        try:
            summary = execute(service, cycles, live=live, boot_timeout=boot_timeout,
                              before_sync=before_sync, on_start=rig.start)
        finally:
            rig.stop()
    return service, summary


def run(args) -> int:
    from ..service.traces import check_trace_target

    setup_logging()
    scene, cycles = load_run_scene(args)
    drops = parse_drops(args.drop_node, scene)
    check_trace_target(args.log, scene)
    _, summary = run_demo(scene, cycles, drops=drops, json_lines=args.json_lines, trace=args.log,
                          live=not args.no_live, boot_timeout=args.boot_timeout, keep_records=False)
    print_summary(summary)
    return 130 if "interrupted" in summary else 0
