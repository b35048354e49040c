"""Live terminal view of a run (rich ``Live``): per-cycle decision, rules, bus load, node
states, counters.

For humans only: nothing shown here goes into the decision log. Off with ``--no-live`` or
when stdout is not a terminal. The worker thread only stores the latest record
(:meth:`LiveView.update`); the view is built when rich refreshes it (a few times per second),
so a 100 Hz SYNC costs the fusion centre nothing but a reference assignment.
"""

from __future__ import annotations

import threading
import time

from rich.console import Group
from rich.live import Live
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from ..core.bus_timing import worst_case_frame_bits

# data bytes per counted event (classic CAN 2.0A); bus load uses the worst-case frame length
_DATA_BYTES = {"sync": 0, "tpdo1": 1, "tpdo2": 4, "late": 1, "heartbeat": 1, "bootup": 1, "emcy": 8,
               "nmt": 2, "sdo": 8, "sdo_abort": 8, "time": 6}
_DECISION_STYLE = {"H1": "bold green", "H0": "cyan", "undecided": "yellow"}
_HISTORY = 80


def _fmt(value, spec: str = ".4g") -> str:
    if value is None:
        return "-"
    if isinstance(value, (int, float)):
        return format(value, spec)
    return str(value)


class LiveView:
    """``with LiveView(service) as view: service.on_record.append(view.update)``."""

    def __init__(self, service, refresh_per_second: float = 4.0, cycles: int | None = None):
        self.service = service
        self.scene = service.scene
        self.bitrate = service.bitrate or service.scene.bus.bitrate
        self.cycles = cycles
        self._last: dict | None = None
        self._lock = threading.Lock()
        self._history: list[str] = []
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
            truth = record.get("truth")
            if truth is not None and decision in ("H1", "H0"):
                self._decided += 1
                self._agree += decision == truth

    # ------------------------------------------------------------------ rendering
    def __rich__(self):
        with self._lock:
            record = self._last
            history = list(self._history)
            decided, agree = self._decided, self._agree
        counters = self.service.stream.counters()
        return Group(self._header(record, counters), self._cycle_table(record), self._rules_table(record),
                     self._nodes(record), self._strip(history, decided, agree), self._counters(counters))

    def _bus_load(self, counters: dict) -> float:
        bits = sum(worst_case_frame_bits(_DATA_BYTES.get(name, 8)) * counters.get(name, 0) for name in _DATA_BYTES)
        now = time.monotonic()
        if now - self._load_t >= 0.5:
            self._load = (bits - self._load_bits) / (now - self._load_t) / self.bitrate
            self._load_bits, self._load_t = bits, now
        return self._load

    def _header(self, record, counters) -> Table:
        scene = self.scene
        done = "-" if record is None else str(record.get("cycle", "-"))
        total = f"/{self.cycles - 1}" if self.cycles else ""
        head = Table.grid(padding=(0, 3))
        head.add_row(
            Text(f"{scene.name}", style="bold"),
            f"{scene.n} taxels, {scene.bus.mode} mode",
            f"SYNC {scene.bus.sync_period_ms:g} ms @ {self.bitrate // 1000} kbit/s",
            f"bus load ≈ {100 * self._bus_load(counters):.1f} % (worst-case frame bits)",
            f"cycle {done}{total}",
            f"{time.monotonic() - self._start:.1f} s",
        )
        return head

    def _cycle_table(self, record) -> Table:
        body = Table(show_header=True, header_style="bold", pad_edge=False, box=None, padding=(0, 2))
        for col in ("cycle", "decision", "truth", "rule", "U_G", "threshold", "P(H1)", "present", "received",
                    "closed by", "contact", "area", "force"):
            body.add_column(col, justify="right" if col not in ("decision", "truth", "rule", "closed by", "contact")
                            else "left")
        if record is not None and "decision" in record:
            decision = record["decision"]
            forces = record.get("forces") or {}
            total = forces.get("total_tangential")
            body.add_row(
                str(record["cycle"]), Text(decision, style=_DECISION_STYLE.get(decision, "")),
                str(record.get("truth", "-")), str(record.get("decide_with", "-")),
                _fmt(record.get("U_G")), _fmt(record.get("threshold")), _fmt(record.get("p_h1"), ".3g"),
                str(record["present_count"]), f"{record['n_received']}/{record['n_expected']}",
                str(record.get("closed_by", "-")), str(record.get("contact_type", "-")),
                _fmt(record.get("area"), ".4g"),
                "-" if total is None else f"{total:.3g} {forces.get('unit', '')}",
            )
        elif record is not None:
            body.add_row(str(record.get("cycle", "-")), Text("error", style="red"), "-", "-", "-", "-", "-", "-",
                         "-", "-", "-", "-", str(record.get("error", ""))[:40])
        return body

    def _rules_table(self, record) -> Text:
        line = Text("rules: ", style="bold")
        if record is None:
            return line
        for name, res in (record.get("rules") or {}).items():
            decision = res.get("decision", "?")
            line.append(f"{name} ")
            line.append(decision, style=_DECISION_STYLE.get(decision, ""))
            line.append(f" ({_fmt(res.get('U_G'), '.3g')} vs {_fmt(res.get('threshold'), '.3g')})   ")
        return line

    def _nodes(self, record) -> Text:
        """One character per node, fusion order: █ present, · absent, s silent, x missing."""
        line = Text("nodes: ", style="bold")
        if record is None or "present_nodes" not in record:
            return line
        present = set(map(str, record["present_nodes"]))
        missing = set(map(str, record.get("missing_nodes", [])))
        silent = set(map(str, record.get("silent_nodes", [])))
        for label in self.service.labels:
            key = str(label)
            if key in missing:
                line.append("x", style="bold red")
            elif key in silent:
                line.append("s", style="yellow")
            elif key in present:
                line.append("█", style="green")
            else:
                line.append("·", style="dim")
        line.append(f"   present {len(present)}, silent {len(silent)}, missing {len(missing)}"
                    + (f" ({', '.join(sorted(missing, key=lambda s: (len(s), s))[:8])})" if missing else ""))
        line.append("   (█ present · absent s silent x missing)", style="dim")
        return line

    def _strip(self, history: list[str], decided: int, agree: int) -> Text:
        line = Text("decisions: ", style="bold")
        for d in history:
            line.append({"H1": "█", "H0": "·"}.get(d, "?"), style=_DECISION_STYLE.get(d, "red"))
        if decided:
            line.append(f"   agree with truth {agree}/{decided}")
        return line

    def _counters(self, counters: dict) -> Panel:
        shown = ("sync", "tpdo1", "tpdo2", "late", "heartbeat", "bootup", "emcy", "sdo", "sdo_abort",
                 "bad_dlc", "bad_value", "unknown_cob_id", "remote_frame", "error_frame", "extended_id",
                 "internal_error")
        grid = Table.grid(padding=(0, 2))
        cells = []
        for name in shown:
            value = counters.get(name, 0)
            bad = name in ("bad_dlc", "bad_value", "unknown_cob_id", "remote_frame", "error_frame", "extended_id",
                           "internal_error", "sdo_abort", "emcy", "late") and value
            cells.append(Text(f"{name} {value}", style="red" if bad else ""))
        for i in range(0, len(cells), 8):
            grid.add_row(*cells[i:i + 8])
        return Panel(grid, title="frames", title_align="left", expand=False)
