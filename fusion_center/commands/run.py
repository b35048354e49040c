"""``fusion-center run``: the fusion centre as CANopen master on any python-can bus."""

from __future__ import annotations

import argparse
import logging
import sys

HELP = "run the fusion centre (CANopen master, SYNC, fusion, decision log) on a python-can bus"



def _rt_priority(text: str) -> int:
    """``--rt-priority``: ASCII digits, 1-99 (argparse's int took ' 5', '1_0' and other scripts' digits)."""
    from taxel_net.realtime import PRIORITY_MAX, PRIORITY_MIN, check_priority

    if not (text.isascii() and text.isdigit()):
        raise argparse.ArgumentTypeError(f"{text!r}: an integer {PRIORITY_MIN}-{PRIORITY_MAX} (SCHED_FIFO's priorities)")
    try:
        return check_priority(int(text))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--rt-priority ")) from None

def add_common_outputs(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cycles", type=int, default=None, metavar="N",
                        help="SYNC cycles to run (default: the scene's [scene] cycles)")
    parser.add_argument("--json-lines", metavar="OUT", default=None,
                        help="decision log: one JSON object per cycle, flushed every cycle")
    parser.add_argument("--log", metavar="TRACE", default=None,
                        help="raw CAN trace via python-can's writers; format by extension "
                             "(.log candump, .asc Vector, .blf); replay it with `fusion-center replay`. "
                             "Handed to the OS at every cycle's close (.blf: a container a cycle): a crash "
                             "loses at most the cycle in flight. .trc, .csv, .db and .mf4 are refused (they "
                             "drop frames or keep nothing of a killed run): convert a copy with can.logconvert")
    parser.add_argument("--no-live", action="store_true", help="no live terminal view (off anyway without a TTY)")
    parser.add_argument("--boot-timeout", type=float, default=3.0, metavar="S",
                        help="seconds to wait for the nodes' boot-ups; later ones are missing (default 3)")
    add_mode_argument(parser)
    from ..service.zenoh_config import add_arguments as add_zenoh_arguments

    add_zenoh_arguments(parser, publication=True)


def zenoh_settings(args) -> dict | None:
    """The ``--zenoh`` publication's session settings for the robotics bridge (None without
    ``--zenoh``); the session flags without ``--zenoh`` are a :class:`UsageError`."""
    from taxel_net.errors import UsageError

    if not getattr(args, "zenoh", False):
        for flag in ("zenoh_listen", "zenoh_connect", "zenoh_mode"):
            if getattr(args, flag, None):
                raise UsageError(f"--{flag.replace('_', '-')}: only with --zenoh (the publication's session)")
        return None
    return {"config_file": args.zenoh_config, "listen": args.zenoh_listen, "connect": args.zenoh_connect,
            "mode": args.zenoh_mode}


def add_mode_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mode", choices=("decision", "raw"), default=None,
                        help="override the scene's [bus] mode: decision (TPDO1 u_i) or raw "
                             "(TPDO2 X_i, central per-taxel decisions + centralised raw-data tests)")


def apply_mode(scene, mode: str | None):
    """The scene with ``[bus] mode`` replaced by ``mode`` (None: unchanged)."""
    import dataclasses

    if mode is None or mode == scene.bus.mode:
        return scene
    return dataclasses.replace(scene, bus=dataclasses.replace(scene.bus, mode=mode))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from . import add_bus_arguments

    parser.add_argument("--scene", required=True, metavar="FILE",
                        help="scene file or bundled scene name (docs/scene-format.md)")
    add_bus_arguments(parser)
    add_common_outputs(parser)
    parser.add_argument("--assemblers", metavar="ENDPOINT", default=None,
                        help="listen on this Zenoh endpoint (HOST:PORT for tcp, or PROTO/HOST:PORT such as "
                             "tls/0.0.0.0:7447) for `fusion-center assemble` processes (other processes or hosts) "
                             "and fuse their cycles instead of assembling them here (beyond loopback: the same "
                             "FUSION_CENTER_AUTHKEY on every host; on loopback without it a key of this run's, "
                             "in a file only this user can read; docs/service.md)")
    parser.add_argument("--rt-priority", type=_rt_priority, default=None, metavar="N",
                        help="run the centre's receive thread, SYNC producer and heartbeat under SCHED_FIFO at priority N "
                             "(1-99; Linux, CAP_SYS_NICE (root) or `ulimit -r` >= N; not permitted: one warning, "
                             "normal priority). Default: the normal priority (docs/service.md)")
    from ..robotics.cli import add_arguments as add_robotics_arguments

    add_robotics_arguments(parser, live=True, bag=True)


def setup_logging() -> None:
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    # canopen logs an ERROR for every SDO transfer it gives up on; the master reports each
    # failure itself (node, object, cause; rate-limited) and counts it in the summary
    logging.getLogger("canopen.sdo.client").setLevel(logging.CRITICAL)


def execute(service, cycles: int, *, live: bool, boot_timeout: float, before_sync=None, on_start=None,
            bus: str | None = None) -> dict:
    """Boot, run and summarise one service (shared by ``run`` and ``demo``).

    Ctrl-C (SIGINT, in the main thread): during the run it stops the SYNC producer, which ends
    the open cycle with its NMT broadcast as at a normal end; every closed cycle is evaluated
    and written whole (flushed), and the partial summary comes back with ``interrupted`` set
    (the commands then exit 130). During boot it ends the boot (a summary of 0 cycles). A second
    Ctrl-C ends the command at once, without a summary (exit 130).

    The first Ctrl-C of the run is taken by a signal handler, not as a KeyboardInterrupt: one
    raised inside ``Thread.join`` (the main thread waits there for the SYNC producer) leaves
    CPython 3.11 believing the thread has ended (bpo-45274), so the summary would be taken
    before the producer's last cycle."""
    import contextlib
    import signal
    import threading

    from ..service.fusion_service import stdout_is_tty

    view = None
    if live and stdout_is_tty():
        from ..service.live import LiveView

        view = LiveView(service, cycles=cycles, bus=bus)
        service.on_record.append(view.update)
    if on_start is not None:
        on_start()
    interrupted = False
    phase = "boot"

    def on_sigint(signum, frame):
        nonlocal interrupted
        first, interrupted = not interrupted, True
        if first and phase == "run" and service.master is not None:
            service.master.stop()  # the SYNC producer ends; service.run returns the summary
            return
        raise KeyboardInterrupt

    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        with view if view is not None else contextlib.nullcontext():
            service.boot(boot_timeout)
            phase = "run"
            summary = service.run(cycles, before_sync=before_sync)
    except KeyboardInterrupt:
        if phase == "run":
            raise  # the second Ctrl-C: no summary
        interrupted = True
        summary = service.summary()
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
    result = summarise(service, summary, bus=bus)
    if interrupted:
        result["interrupted"] = {"cycles_asked": cycles}
    return result


def summarise(service, summary, *, bus: str | None = None) -> dict:
    """The summary of a run from the service's running aggregates (no record is needed);
    ``bus``: which bus the run used and where that came from (``run``; None for ``demo``)."""
    stats = service.stats
    out = {
        "scene": service.scene.name,
        "mode": service.scene.bus.mode,
        "cycles": summary.cycles,
        "records": stats.records,
        "decide_with": service.scene.fusion.decide_with,
        "decisions": {d: stats.decisions[d] for d in ("H1", "H0", "undecided")},
        "agree_with_truth": stats.agree_with_truth(),
        "rules_agree_with_truth": stats.rules_agree_with_truth(),
        "degraded_cycles": stats.degraded,
        "missing_at_boot": summary.missing_at_boot,
        "stages_run": stats.stages_run,
        "stages_skipped": service.pipeline.stages_skipped,
        "rules_skipped": service.pipeline.rules_skipped,
        "counters": {k: v for k, v in summary.counters.items() if v},
        "sdo": {"writes": summary.sdo_writes, "aborts": summary.sdo_aborts, "timeouts": summary.sdo_timeouts},
        "sync_overruns": summary.sync_overruns,
        "latency_ms_p50": _round(summary.latency_percentile(50)),
        "latency_ms_p99": _round(summary.latency_percentile(99)),
    }
    if summary.own_echoes:
        out["own_echoes_dropped"] = summary.own_echoes
    master = service.master
    if master is not None and master.restarts:
        out["nmt_restarts"] = master.restarts
    if bus is not None:
        out["bus"] = bus
    if getattr(service, "drive", None) is not None:  # the grip stage (issue 23)
        out["grip"] = service.drive.summary()
    over_range = getattr(service.pipeline, "over_range", None)
    if over_range is not None and (over_range.emcy or stats.over_range):  # raw patch scenes (docs/service.md)
        out["over_range"] = {"cycles": stats.over_range, "emcy": {str(k): v for k, v in over_range.emcy.items()}}
    if service.assembler.duplicates:
        out["duplicate_nodes"] = sorted((service.labels[i] for i in service.assembler.duplicates), key=str)
    return out


def _round(x):
    return None if x is None else round(x, 3)


def format_summary(summary: dict) -> list[str]:
    """The run summary as aligned ``label: value`` lines (one fact per line, grep-able)."""
    d = summary["decisions"]
    lines = [
        ("scene", f"{summary['scene']} ({summary['mode']} mode)"),
        *([("bus", summary["bus"])] if "bus" in summary else []),
        ("cycles", f"{summary['cycles']} SYNC, {summary['records']} records"),
        ("decisions", f"H1 {d['H1']}, H0 {d['H0']}, undecided {d['undecided']} ({summary['decide_with']})"),
        ("agree_with_truth", summary["agree_with_truth"] or "-"),
        ("rules_agree_with_truth", ", ".join(f"{k} {v}" for k, v in summary["rules_agree_with_truth"].items()) or "-"),
        ("degraded_cycles", str(summary["degraded_cycles"])),
        ("missing_at_boot", ", ".join(map(str, summary["missing_at_boot"])) or "none"),
        ("stages_run", ", ".join(summary["stages_run"]) or "-"),
    ]
    for skipped in (summary["stages_skipped"], summary["rules_skipped"]):
        lines += [(f"skipped {name}", why.removeprefix(f"{name}: ")) for name, why in skipped.items()
                  if not why.startswith("not requested") and not (name == "grip" and "grip" not in summary)]
    lines += [
        ("counters", ", ".join(f"{k} {v}" for k, v in summary["counters"].items())),
        ("sdo", f"{summary['sdo']['writes']} writes, {summary['sdo']['aborts']} aborts, "
                f"{summary['sdo']['timeouts']} timeouts"),
        ("sync_overruns", str(summary["sync_overruns"])),
        ("latency_ms", f"SYNC -> record p50 {_fmt_ms(summary['latency_ms_p50'])}, "
                       f"p99 {_fmt_ms(summary['latency_ms_p99'])}"),
    ]
    if "grip" in summary:
        lines += grip_lines(summary["grip"])
    if "own_echoes_dropped" in summary:
        lines.append(("own_echoes_dropped", str(summary["own_echoes_dropped"])))
    if "nmt_restarts" in summary:
        lines.append(("nmt_restarts", f"{summary['nmt_restarts']} (nodes found stopped or pre-operational, "
                                      "started again: [master] restart)"))
    if "over_range" in summary:
        o = summary["over_range"]
        lines.append(("over_range", f"{o['cycles']} cycles flagged, EMCY 0x3000 "
                                    f"{', '.join(f'node {k} {v}' for k, v in o['emcy'].items()) or 'none'} "
                                    "(raw readings clipped at the INTEGER8/16 limit)"))
    if "duplicate_nodes" in summary:
        lines.append(("duplicate_nodes", ", ".join(map(str, summary["duplicate_nodes"]))
                      + " (two devices answer for one node-ID)"))
    if "assemblers" in summary:
        a = summary["assemblers"]
        lines.append(("assemblers", f"{a['parts']} parts ({', '.join(f'{k} {v}' for k, v in a['by_group'].items())}); "
                                    f"cycles complete {a['complete']}, degraded {a['degraded']} "
                                    f"({a['parts_missing']} parts missing), late parts {a['late_parts']}"
                                    + _carried_on(a)
                                    + f", unmatched {a['unmatched_parts']}; reconnects {_reconnects(a)}; "
                                    f"refused {_by_kind(a.get('refused'))}; SYNC -> part sent p50 "
                                    f"{_fmt_ms(a['to_send_ms']['p50'])}, p99 {_fmt_ms(a['to_send_ms']['p99'])}; "
                                    f"part transport p50 {_fmt_ms(a['transport_ms']['p50'])}, "
                                    f"p99 {_fmt_ms(a['transport_ms']['p99'])}"))
    if "zenoh" in summary:
        z = summary["zenoh"]
        lines.append(("zenoh", f"{z['records']} records on {z['keys']['record']}, {z['grip']} on .../grip, "
                               f"{z['contact']} contact events on .../contact, {z['failed']} failed, "
                               f"{z['unmatched']} with no subscriber ({z['session']})"))
    if "robotics" in summary:
        from ..robotics.outputs import summary_lines

        lines += summary_lines(summary["robotics"])
    if "slow_down" in summary:
        lines.append(("slow_down", summary["slow_down"]))
    if "warning" in summary:
        lines.append(("warning", summary["warning"]))
    for label, text in summary.get("incomplete", ()):
        lines.append((label, "INCOMPLETE: " + text))
    if "interrupted" in summary:
        lines.append(("interrupted", f"Ctrl-C after {summary['cycles']} of {summary['interrupted']['cycles_asked']} "
                                     "SYNC cycles: a partial summary; every record written is complete"))
    width = max(len(k) for k, _ in lines)
    return [f"{k + ':':<{width + 1}} {v}" for k, v in lines]


def grip_lines(g: dict) -> list[tuple[str, str]]:
    """The grip stage's lines of the summary: the grasp's verdict, the commands and their latency."""
    grasp = g["grasp"]
    events = ", ".join(f"{k} {g[k]}" for k in ("drive_faults", "quick_stops", "drive_disabled", "drive_lost",
                                              "fault_resets", "enable_walks", "takeovers", "degraded_holds",
                                              "drive_bootups", "drive_not_operational", "nmt_starts", "drive_mode",
                                              "drive_force_implausible")
                       if g.get(k))
    final = grasp.get("final") or {}
    lines = [
        ("grasp", grasp["verdict"]),
        ("grip", f"{g['commands_sent']} commands, most {_fmt_n(grasp['max_command_n'])}, at the end "
                 f"{_fmt_n(final.get('command_n'))} commanded / {_fmt_n(final.get('actual_n'))} actual, drive "
                 f"{final.get('drive_state') or '-'}, {final.get('grip_state') or '-'}; centre's slip cycles "
                 f"{grasp['slip_cycles']}" + (f"; {events}" if events else "")),
        ("latency_command_ms", f"SYNC -> command p50 {_fmt_ms(g['sync_to_command_ms_p50'])}, "
                               f"p99 {_fmt_ms(g['sync_to_command_ms_p99'])}, max {_fmt_ms(g['sync_to_command_ms_max'])}"),
    ]
    if "truth" in grasp:
        t = grasp["truth"]
        lines.append(("grasp_truth", f"slip episodes {t['slip_episodes']} ({t['slip_cycles']} cycles), slid at most "
                                     f"{t['slid_mm_max']:.2f} mm, dropped {t['dropped']}, crushed {t['crushed']}, "
                                     f"most normal force {t['max_normal_n']:.2f} N"))
    return lines


def _fmt_n(x):
    return "-" if x is None else f"{x:.2f} N"


def _carried_on(a: dict) -> str:
    """The events of late parts carried on to the next cycle (CycleMerger._late), "" when none."""
    carried = [f"{a[key]} {what}" for key, what in (("late_bootups", "boot-ups"), ("late_emcy", "EMCYs")) if a.get(key)]
    return f" ({', '.join(carried)} carried on)" if carried else ""


def _reconnects(a: dict) -> str:
    """``0`` or ``3 (1 2, 0 1)``: groups that came back during the run, how often."""
    return _by_kind(a.get("reconnects"))


def _by_kind(by: dict | None) -> str:
    """``0`` or ``3 (key 2, message 1)``: a total and its parts."""
    by = by or {}
    total = sum(by.values())
    return f"{total} ({', '.join(f'{k} {v}' for k, v in by.items())})" if total else "0"


def _fmt_ms(x):
    return "-" if x is None else f"{x:.2f} ms"


def load_run_scene(args):
    """The scene of ``--scene`` with ``--mode`` applied, and the cycle count (``--cycles`` or the
    scene's). The node twins and the fusion centre get this same (overridden) scene."""
    from taxel_net.errors import UsageError
    from taxel_net.scene import CYCLES_MAX, load_scene

    if args.cycles is not None and not 1 <= args.cycles <= CYCLES_MAX:
        raise UsageError(f"--cycles {args.cycles}: must lie in 1..{CYCLES_MAX}")
    check_boot_timeout(args.boot_timeout)
    from ..service.fusion_service import check_rt_priority

    check_rt_priority(getattr(args, "rt_priority", None))
    from . import check_bitrate_flags

    check_bitrate_flags(args)
    scene = apply_mode(load_scene(args.scene), args.mode)
    cycles = args.cycles if args.cycles is not None else scene.cycles
    return scene, cycles


BOOT_TIMEOUT_MAX_S = 3600.0


def check_boot_timeout(value: float) -> None:
    import math

    from taxel_net.errors import UsageError

    if not (math.isfinite(value) and 0.0 < value <= BOOT_TIMEOUT_MAX_S):
        raise UsageError(f"--boot-timeout {value}: must be a number of seconds in (0, {BOOT_TIMEOUT_MAX_S:g}]")


def run_with_outputs(service, outputs, body) -> dict:
    """Open ``service``, publish its records to the robotics ``outputs`` (or None) while ``body()``
    runs it, close both: the outputs' files are committed when ``body`` returns a summary (also
    an interrupted run's), left partial when it raises; their figures join the summary."""
    try:
        with service:
            if outputs is not None:
                outputs.attach(service)
            summary = body()
    except BaseException:
        if outputs is not None:
            outputs.close(ok=False)
        raise
    if outputs is not None:
        summary["robotics"] = outputs.close(ok=True)
        if "zenoh" in summary["robotics"]:  # the bridge's publication (its own summary line)
            summary["zenoh"] = summary["robotics"].pop("zenoh")
    # a full disk under --json-lines / --log: the run went on, the file is incomplete
    failed = [(label, text) for label, text in (("decision_log", service.writer_failure),
                                                 ("trace", service.trace_failure)) if text]
    # cycles an output could not publish (a record its encoder refused): a file output lacks them
    from ..robotics.outputs import incomplete_files

    failed += incomplete_files(summary.get("robotics") or {})
    if failed:
        summary["incomplete"] = failed
    return summary


def finish_summary(summary: dict, command: str) -> int:
    """Print ``summary``; the exit status: 2 with each output's failure (decision log, trace) as
    one line on stderr after it (the run's figures are still worth having), 130 for an
    interrupted run."""
    import sys

    print_summary(summary)
    failed = summary.get("incomplete")
    for _, text in failed or ():
        print(f"fusion-center {command}: error: {text}", file=sys.stderr)
    if failed:
        return 2
    return 130 if "interrupted" in summary else 0


def print_summary(summary: dict) -> None:
    for line in format_summary(summary):
        print(line)


def run(args) -> int:
    from ..service import FusionService
    from . import resolve_bus
    from ..service.traces import check_trace_target

    from ..robotics import cli as robotics
    from . import check_output_paths

    setup_logging()
    check_output_paths(args)  # an output naming an input or another output: one line, nothing written
    scene, cycles = load_run_scene(args)
    check_trace_target(args.log)
    robotics.check(args)
    bus = resolve_bus(args, scene)
    options = dict(interface=bus.interface, channels=bus.channels, bitrate=bus.bitrate, bus_kwargs=bus.kwargs,
                   json_lines=args.json_lines, trace=args.log, keep_records=False,
                   rt_priority=getattr(args, "rt_priority", None))
    if getattr(args, "assemblers", None):  # the cycles come from `fusion-center assemble` processes
        from ..service.assemblers import AssembledFusionService
        from ..service.zenoh_config import endpoint

        service = AssembledFusionService(scene, listen=endpoint(args.assemblers, "--assemblers"),
                                         zenoh_config=getattr(args, "zenoh_config", None), **options)
    else:
        service = FusionService(scene, **options)
    # --zenoh and --foxglove: the robotics bridge process (docs/robotics.md, *The bridge process*)
    outputs = robotics.open_outputs(args, scene, threaded=True, zenoh=zenoh_settings(args),
                                    source={"scene": args.scene, "mode": args.mode, "slow_down": 1.0})
    summary = run_with_outputs(service, outputs,
                               lambda: execute(service, cycles, live=not args.no_live,
                                               boot_timeout=args.boot_timeout,
                                               bus=bus.describe(service.channel_names)))
    merger = getattr(service, "merger", None)
    if merger is not None:
        summary["assemblers"] = merger.stats.as_dict()
    return finish_summary(summary, "run")
