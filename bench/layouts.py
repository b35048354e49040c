"""Skin scale: exact bus cost of decisions vs raw readings for one-taxel and patch nodes, classic CAN and FD.

For each skin size: one-taxel nodes (the chapter's layout) and patch nodes of --patch taxels
(decisions packed one bit per taxel, readings as INTEGER8), each on classic CAN and on CAN FD
with bit-rate switch; printed side by side: channels (<= 127 nodes each), PDO frames per SYNC
cycle, bits per cycle over all channels (mean over payloads with P(bit = 1) = --p-one, and
worst case), bus load of the busiest channel at the SYNC period (heartbeats included), the
highest SYNC rate its worst-case cycle fits, the channels needed to fit the SYNC period, the
mean bits of event-driven decisions, then the raw / decision ratio of bus time per cycle.
Figures are exact (fusion_center.core.layouts; frame_bits / fd_frame_bits), not measured: they
do not depend on the machine.

    .venv/bin/python bench/layouts.py [--taxels 57,200,1024,4096] [--patch 192] [--bitrate 1000000]
                                      [--data-bitrate 5000000] [--sync-ms 10] [--heartbeat-ms 100]
                                      [--p-one 0.5] [--p-change 0.01]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fusion_center.core.layouts import channels_needed, layout_bus_use, skin_layout  # noqa: E402


def _rate(text: str) -> str:
    value = float(text)
    return f"{value / 1e6:g}M" if value >= 1e6 else f"{value / 1e3:g}k"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--taxels", default="57,200,1024,4096")
    ap.add_argument("--patch", type=int, default=192, help="taxels per patch node")
    ap.add_argument("--raw", default="raw8", choices=("raw8", "raw16", "real32"))
    ap.add_argument("--bitrate", type=float, default=1_000_000, help="nominal bit rate, bit/s")
    ap.add_argument("--data-bitrate", type=float, default=5_000_000, help="CAN FD data-phase bit rate, bit/s")
    ap.add_argument("--sync-ms", type=float, default=10.0)
    ap.add_argument("--heartbeat-ms", type=float, default=100.0)
    ap.add_argument("--p-one", type=float, default=0.5, help="P(taxel bit = 1) for the mean payload")
    ap.add_argument("--p-change", type=float, default=0.01, help="P(a decision changes) per taxel and cycle")
    args = ap.parse_args(argv)
    period = args.sync_ms / 1000.0
    hb = args.heartbeat_ms / 1000.0
    buses = {False: f"classic {_rate(args.bitrate)}", True: f"FD {_rate(args.bitrate)}/{_rate(args.data_bitrate)}"}
    layouts = {"per-taxel": 1, f"patch{args.patch}": args.patch}
    print(f"SYNC {args.sync_ms:g} ms, heartbeat {args.heartbeat_ms:g} ms, mean payload P(bit=1) = {args.p_one:g}, "
          f"event-driven: P(change) = {args.p_change:g} per taxel and cycle")
    head = (f"{'taxels':>6} {'layout':<9} {'payload':<8} {'bus':<13} {'ch':>3} {'frames':>6} {'bits/cycle':>10} "
            f"{'worst':>7} {'load':>8} {'max SYNC':>9} {'ch@SYNC':>7} {'event':>8}")
    print(head)
    ratios = []
    for n in (int(x) for x in args.taxels.split(",")):
        seconds = {}
        for label, per_node in layouts.items():
            for payload in ("decision", args.raw):
                for fd in (False, True):
                    kw = dict(taxels_per_node=per_node, payload=payload, fd=fd)
                    rates = dict(nominal_bitrate=args.bitrate, data_bitrate=args.data_bitrate if fd else None)
                    lay = skin_layout(n, **kw)
                    use = layout_bus_use(lay, sync_period_s=period, heartbeat_period_s=hb, p_one=args.p_one,
                                         **rates)
                    need = channels_needed(n, sync_period_s=period, heartbeat_period_s=hb, **rates, **kw)
                    event = "-"
                    if payload == "decision":
                        ev = layout_bus_use(lay, sync_period_s=period, heartbeat_period_s=hb, p_one=args.p_one,
                                            p_change=args.p_change, **rates)
                        event = f"{ev.mean_bits:.1f}"
                    seconds[label, payload, fd] = (use.mean_cycle_s, sum(c.worst_cycle_s for c in use.channels),
                                                   use.mean_bits)
                    print(f"{n:>6} {label:<9} {payload:<8} {buses[fd]:<13} {len(lay.channels):>3} {lay.n_frames:>6} "
                          f"{use.mean_bits:>10.1f} {use.worst_bits:>7} {100 * use.busiest.load:>6.1f} % "
                          f"{use.max_sync_hz:>6.0f} Hz {need if need is not None else '-':>7} {event:>8}")
        ratios.append((n, seconds))
    print()
    print(f"{args.raw} / decision, bus time per SYNC cycle over all channels, mean (worst case):")
    cols = [(label, fd) for label in layouts for fd in (False, True)]
    print(f"{'taxels':>6} " + " ".join(f"{label + ' ' + ('FD' if fd else 'classic'):>18}" for label, fd in cols))
    for n, seconds in ratios:
        cells = []
        for label, fd in cols:
            raw, dec = seconds[label, args.raw, fd], seconds[label, "decision", fd]
            cells.append(f"{raw[0] / dec[0]:.2f}x ({raw[1] / dec[1]:.2f}x)")
        print(f"{n:>6} " + " ".join(f"{c:>18}" for c in cells))
    chapter = {p: layout_bus_use(skin_layout(57, payload=p), nominal_bitrate=args.bitrate, sync_period_s=period,
                                 p_one=args.p_one).mean_bits for p in ("decision", "real32")}
    print(f"the chapter's layout (57 one-taxel nodes, classic): REAL32 / decision bits per cycle "
          f"{chapter['real32']:.1f} / {chapter['decision']:.1f} = {chapter['real32'] / chapter['decision']:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
