"""Live terminal view of a run (rich ``Live``): the last cycle's decision with its labelled
quantities, every rule, the nodes by NMT state, the recent decisions, the frame counters.

For humans only: nothing shown here goes into the decision log. Off with ``--no-live`` or
when stdout is not a terminal. The worker thread only stores the latest record
(:meth:`LiveView.update`); the view is built when rich refreshes it (a few times per second),
so a 100 Hz SYNC costs the fusion centre nothing but a reference assignment. The frame counters
are the stream's as of its last closed cycle (``EventStream.counters_snapshot``): the refresh
never takes the stream lock, which the receive thread may need under ``SCHED_FIFO``
(``--rt-priority``; docs/service.md).

Every line fits the terminal's width down to 80 columns: label-value pairs are wrapped whole
(never cut to ``cyc…``), tables have few, labelled columns (``tests/test_live_view.py``
renders it with ``Console(width=80)``).
"""

from __future__ import annotations

import threading
import time

from rich.console import Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from ..core.bus_timing import worst_case_frame_bits

# data bytes per counted event (classic CAN 2.0A); bus load uses the worst-case frame length
_DATA_BYTES = {"sync": 0, "tpdo1": 1, "tpdo2": 4, "late": 1, "heartbeat": 1, "bootup": 1, "master_heartbeat": 1, "emcy": 8,
               "nmt": 2, "sdo": 8, "sdo_abort": 8, "time": 6, "drive": 8}
_DECISION_STYLE = {"H1": "bold green", "H0": "cyan", "undecided": "yellow"}
_HISTORY = 70  # decisions shown: one line at 80 columns with its indent (the slip strips' too)
_FRAMES = ("sync", "tpdo1", "tpdo2", "late", "heartbeat", "bootup", "master_heartbeat", "nmt", "emcy", "sdo",
           "sdo_abort", "drive")
_MALFORMED = ("bad_dlc", "bad_value", "unknown_cob_id", "remote_frame", "error_frame", "extended_id", "fd_frame",
              "internal_error")
# nodes that did not take part, by the record's nodes_by_state (docs/service.md, Supervision)
_NOT_OPERATIONAL = ("pre-operational", "stopped", "resetting", "unknown")
_NODE_MARK = {"missing": ("x", "bold red"), "silent": ("s", "yellow"), "pre-operational": ("p", "magenta"),
              "stopped": ("-", "red"), "resetting": ("r", "magenta"), "unknown": ("?", "dim")}
_LEGEND = ("█ object present", "· absent", "s silent", "p pre-operational", "- stopped", "r resetting", "x missing")


def _fmt(value, spec: str = ".4g") -> str:
    if value is None:
        return "-"
    if isinstance(value, (int, float)):
        return format(value, spec)
    return str(value)


def _wrapped(label: str, items, width: int, indent: int = 2, sep: str = ", ") -> Text:
    """``label item, item, ...`` wrapped at ``width`` between items (an item is never cut)."""
    out = Text(label, style="bold")
    column = len(label)
    for k, item in enumerate(items):
        piece = item if isinstance(item, Text) else Text(item)
        if k and column + len(sep) + len(piece) > width:
            out.append(sep.rstrip() + "\n" + " " * indent)
            column = indent
        else:
            gap = sep if k else (" " if label and not label.endswith(" ") else "")
            out.append(gap)
            column += len(gap)
        out.append_text(piece)
        column += len(piece)
    return out


class LiveView:
    """``with LiveView(service) as view: service.on_record.append(view.update)``."""

    def __init__(self, service, refresh_per_second: float = 4.0, cycles: int | None = None,
                 bus: str | None = None):
        self.service = service
        self.scene = service.scene
        self.bitrate = service.bitrate or service.scene.bus.bitrate
        self.cycles = cycles
        self.bus = bus
        self._last: dict | None = None
        self._lock = threading.Lock()
        self._history: list[str] = []
        self._slips: list[tuple] = []  # (centre's slip, the world's slipping or None) per cycle
        self._decided = 0
        self._agree = 0
        self._start = time.monotonic()
        self._load_t = self._start
        self._load_bits = 0.0
        self._load = 0.0
        self._live = Live(self, refresh_per_second=refresh_per_second, transient=False,
                          redirect_stderr=True, redirect_stdout=False)

    def __enter__(self):
        self._live.__enter__()
        return self

    def __exit__(self, *exc):
        self._live.refresh()
        self._live.__exit__(*exc)

    def update(self, record: dict) -> None:
        """Called by the worker for every record: store it (rendering happens on refresh)."""
        with self._lock:
            self._last = record
            decision = record.get("decision", "?")
            self._history.append(decision)
            del self._history[:-_HISTORY]
            grip = record.get("grip")
            if grip is not None:  # the grip stage (issue 23): the centre's slip and the world's
                truth = record.get("grasp_truth")
                self._slips.append((grip.get("slip"), None if truth is None else truth.get("slipping")))
                del self._slips[:-_HISTORY]
            truth = record.get("truth")
            if truth is not None and decision in ("H1", "H0"):
                self._decided += 1
                self._agree += decision == truth

    # ------------------------------------------------------------------ rendering
    def __rich_console__(self, console, options):
        width = max(40, min(options.max_width, console.width))
        with self._lock:
            record = self._last
            history = list(self._history)
            decided, agree = self._decided, self._agree
            slips = list(self._slips)
        # as of the last closed cycle, without the stream lock: this refresh thread runs at the normal
        # priority, the receive thread that needs the lock maybe under SCHED_FIFO (--rt-priority)
        counters = self.service.stream.counters_snapshot()
        parts = [self._header(record, counters, width), self._cycle_table(record), self._rules_table(record)]
        if record is not None and "grip" in record:
            parts.append(self._grip(record, slips, width))
        parts += [self._nodes(record, width), self._strip(history, decided, agree), self._counters(counters, width)]
        yield Group(*parts)

    def _grip(self, record, slips, width: int) -> Group:
        """The grip stage: command and actual force, the drive's and the grip's state, the task,
        flags; the centre's slip and the world's (when known) over the last cycles."""
        grip, detail = record["grip"], record.get("grip_detail") or {}
        truth = record.get("grasp_truth")
        force = [f"command {_fmt(grip.get('command_n'), '.2f')} N", f"actual {_fmt(grip.get('actual_n'), '.2f')} N"]
        if truth is not None:
            force.append(f"least holding {_fmt(truth.get('min_hold_n'), '.2f')} N")
        state = [Text(str(grip.get("drive_state") or "-"),
                      style="green" if grip.get("drive_state") == "OPERATION ENABLED" else "bold red"),
                 f"grip {grip.get('grip_state') or '-'}", f"task {detail.get('task') or '-'}",
                 f"law {detail.get('law') or '-'}"]
        lines = [_wrapped("grip:", force, width), _wrapped("drive:", state, width)]
        flags = record.get("grip_flags") or []
        if flags:
            lines.append(_wrapped("flags:", [Text(f, style="yellow") for f in flags], width))
        if truth is not None:
            world = [f"phase {truth.get('phase')}", f"slid {_fmt(truth.get('slid_mm'), '.2f')} mm",
                     Text("DROPPED", style="bold red") if truth.get("dropped") else "not dropped"]
            if truth.get("crushed"):
                world.append(Text("CRUSHED", style="bold red"))
            lines.append(_wrapped("world:", world, width))
        centre = Text("  centre ")
        for slip, _ in slips:
            centre.append("!" if slip else "·", style="bold yellow" if slip else "dim")
        lines += [Text(f"slip, last {len(slips)} cycles (! slipping)", style="bold"), centre]
        if any(t is not None for _, t in slips):
            world_line = Text("  world  ")
            for _, t in slips:
                world_line.append("?" if t is None else "!" if t else "·", style="bold red" if t else "dim")
            lines.append(world_line)
        return Group(*lines)

    def _bus_load(self, counters: dict) -> float:
        bits = sum(worst_case_frame_bits(_DATA_BYTES.get(name, 8)) * counters.get(name, 0) for name in _DATA_BYTES)
        now = time.monotonic()
        if now - self._load_t >= 0.5:
            self._load = (bits - self._load_bits) / (now - self._load_t) / self.bitrate
            self._load_bits, self._load_t = bits, now
        return self._load

    def _header(self, record, counters, width: int) -> Group:
        scene = self.scene
        done = "-" if record is None else str(record.get("cycle", "-"))
        total = f" (of 0..{self.cycles - 1})" if self.cycles else ""
        first = Text(scene.name, style="bold")
        first.append(f": {scene.n} taxels, {scene.bus.mode} mode, SYNC every {scene.bus.sync_period_ms:g} ms")
        bus = [f"{self.bus}" if self.bus else "embedded virtual bus", f"{self.bitrate // 1000} kbit/s",
               f"load ≈ {100 * self._bus_load(counters):.1f} % (worst-case frame bits)"]
        run = [f"{done}{total}", f"{time.monotonic() - self._start:.1f} s elapsed"]
        return Group(first, _wrapped("bus:", bus, width), _wrapped("cycle:", run, width))

    def _cycle_table(self, record) -> Table:
        """The last cycle: label-value pairs, two per row."""
        grid = Table.grid(padding=(0, 1))
        for _ in range(2):
            grid.add_column(style="bold", no_wrap=True)
            grid.add_column(min_width=24)
        if record is None:
            grid.add_row("last cycle", "waiting for the first record", "", "")
            return grid
        if "decision" not in record:
            grid.add_row("last cycle", Text(f"{record.get('cycle', '-')}: evaluation failed", style="red"),
                         "error", str(record.get("error", ""))[:40])
            return grid
        decision = record["decision"]
        forces = record.get("forces") or {}
        total = forces.get("total_tangential")
        closed = str(record.get("closed_by", "-")) + (" (degraded)" if record.get("degraded") else "")
        grid.add_row("decision", Text.assemble((decision, _DECISION_STYLE.get(decision, "")),
                                               f" ({record.get('decide_with', '-')})"),
                     "truth", str(record.get("truth", "-")))
        grid.add_row("U_G", _fmt(record.get("U_G")), "threshold", _fmt(record.get("threshold")))
        grid.add_row("P(H1)", _fmt(record.get("p_h1"), ".3g"), "closed by", closed)
        grid.add_row("taxels present", str(record.get("present_count", "-")),
                     "received", f"{record.get('n_received', '-')} of {record.get('n_expected', '-')}")
        grid.add_row("contact type", str(record.get("contact_type", "-")), "area", _fmt(record.get("area"), ".4g")
                     + (" units²" if record.get("area") is not None else ""))
        if total is not None:
            grid.add_row("tangential force", f"{total:.3g} {forces.get('unit', '')}", "", "")
        return grid

    def _rules_table(self, record) -> Table:
        """One row per rule (and centralised test): its decision, statistic and threshold."""
        table = Table(box=None, pad_edge=False, padding=(0, 2), header_style="bold")
        table.add_column("rule")
        table.add_column("decision")
        table.add_column("statistic", justify="right")
        table.add_column("threshold", justify="right")
        table.add_column("P(H1)", justify="right")
        for name, res in ((record or {}).get("rules") or {}).items():
            decision = res.get("decision", "?")
            table.add_row(name, Text(decision, style=_DECISION_STYLE.get(decision, "")),
                          _fmt(res.get("U_G", res.get("statistic")), ".4g"), _fmt(res.get("threshold"), ".4g"),
                          _fmt(res.get("p_h1"), ".3g"))
        return table

    def _nodes(self, record, width: int) -> Group:
        """The nodes by NMT state (counts), then one character per node in fusion order."""
        if record is None or "present_nodes" not in record:
            return Group(Text("nodes: -", style="bold"))
        by_state = {state: set(map(str, nodes)) for state, nodes in (record.get("nodes_by_state") or {}).items()}
        by_state.setdefault("missing", set(map(str, record.get("missing_nodes", []))))
        by_state.setdefault("silent", set(map(str, record.get("silent_nodes", []))))
        n = len(self.service.labels)
        off = {state: len(by_state.get(state, ())) for state in _NOT_OPERATIONAL}
        missing = len(by_state["missing"])
        operational = n - missing - sum(off.values())
        silent = len(by_state["silent"])
        counts = [f"operational {operational}" + (f" ({silent} silent: no PDO)" if silent else ""),
                  f"pre-operational {off['pre-operational']}", f"stopped {off['stopped']}"]
        counts += [f"{state} {off[state]}" for state in ("resetting", "unknown") if off[state]]
        counts.append(Text(f"missing {missing}", style="bold red" if missing else ""))
        present = {str(p).split("/")[0] for p in record["present_nodes"]}  # a patch's taxel "ID/k": node ID
        strip = Text("  ")
        for label in self.service.labels:
            key = str(label)
            mark = next((_NODE_MARK[state] for state in ("missing", *_NOT_OPERATIONAL, "silent")
                         if key in by_state.get(state, ())), None)
            if mark is not None:
                strip.append(*mark)
            elif key in present:
                strip.append("█", style="green")
            else:
                strip.append("·", style="dim")
        legend = _wrapped("  ", _LEGEND, width, sep="  ")
        legend.stylize("dim")
        return Group(_wrapped(f"nodes ({n}):", counts, width), strip, legend)

    def _strip(self, history: list[str], decided: int, agree: int) -> Group:
        head = Text(f"decisions, last {len(history)} (█ H1 · H0 ? undecided)", style="bold")
        if decided:
            head.append(f": agree with truth {agree}/{decided}")
        line = Text("  ")
        for d in history:
            line.append({"H1": "█", "H0": "·"}.get(d, "?"), style=_DECISION_STYLE.get(d, "red"))
        return Group(head, line)

    def _counters(self, counters: dict, width: int) -> Group:
        frames = [f"{name} {counters.get(name, 0)}" for name in _FRAMES
                  if counters.get(name, 0) or name in ("sync", "late", "sdo_abort", "emcy")]
        bad = [(name, counters.get(name, 0)) for name in _MALFORMED]
        total = sum(v for _, v in bad)
        malformed = [Text(f"{total}", style="bold red" if total else "")]
        malformed += [Text(f"{name} {v}", style="red") for name, v in bad if v]
        return Group(_wrapped("frames:", frames, width), _wrapped("malformed:", malformed, width))
