"""Live terminal view of a run (rich ``Live``): per-cycle decision, bus load, nodes, counters.

For humans only: nothing shown here goes into the decision log. Off with ``--no-live`` or
when stdout is not a terminal.
"""

from __future__ import annotations

import threading
import time

from rich.console import Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

# nominal CAN 2.0A frame length without bit stuffing: 47 bits + 8 per data byte
_FRAME_BITS = {"sync": 47, "tpdo1": 55, "tpdo2": 79, "late": 55, "heartbeat": 55, "bootup": 55,
               "emcy": 111, "nmt": 63, "sdo": 111, "sdo_abort": 111, "time": 95}


class LiveView:
    """``with LiveView(service) as view: service.on_record.append(view.update)``."""

    def __init__(self, service, refresh_per_second: float = 8.0):
        self.service = service
        self.scene = service.scene
        self.bitrate = service.bitrate or service.scene.bus.bitrate
        self._last: dict | None = None
        self._lock = threading.Lock()
        self._history: list[str] = []
        self._load_t = time.monotonic()
        self._load_bits = 0
        self._load = 0.0
        self._live = Live(self._render(), refresh_per_second=refresh_per_second, transient=False)

    def __enter__(self):
        self._live.__enter__()
        return self

    def __exit__(self, *exc):
        self._live.update(self._render())
        self._live.__exit__(*exc)

    def update(self, record: dict) -> None:
        with self._lock:
            self._last = record
            self._history.append(record.get("decision", "?"))
            del self._history[:-60]
        self._live.update(self._render())

    def _bus_load(self, counters: dict) -> float:
        bits = sum(_FRAME_BITS.get(name, 55) * count for name, count in counters.items())
        now = time.monotonic()
        if now - self._load_t >= 0.5:
            self._load = (bits - self._load_bits) / (now - self._load_t) / self.bitrate
            self._load_bits, self._load_t = bits, now
        return self._load

    def _render(self):
        record = self._last
        counters = self.service.stream.counters()
        head = Table.grid(padding=(0, 2))
        head.add_row(Text(f"scene {self.scene.name}", style="bold"), f"n = {self.scene.n}",
                     f"SYNC {self.scene.bus.sync_period_ms:g} ms", f"bus load ≈ {100 * self._bus_load(counters):.1f} %")
        body = Table(title="last cycle", show_header=True)
        for col in ("cycle", "decision", "truth", "present", "U_G", "threshold", "P(H1)", "received", "missing"):
            body.add_column(col)
        if record is not None and "decision" in record:
            decision = record["decision"]
            style = {"H1": "green", "H0": "cyan"}.get(decision, "yellow")
            u_g = record.get("U_G")
            th = record.get("threshold")
            p = record.get("p_h1")
            body.add_row(str(record["cycle"]), Text(decision, style=style), str(record.get("truth", "-")),
                         str(record["present_count"]),
                         "-" if u_g is None else f"{u_g:.4g}", "-" if th is None else f"{th:.4g}",
                         "-" if p is None else f"{p:.3g}",
                         f"{record['n_received']}/{record['n_expected']}",
                         ", ".join(map(str, record["missing_nodes"][:8])) or "-")
        strip = Text("".join({"H1": "█", "H0": "·"}.get(d, "?") for d in self._history))
        shown = ("tpdo1", "tpdo2", "late", "heartbeat", "emcy", "sdo_abort", "bad_dlc", "bad_value",
                 "unknown_cob_id", "internal_error")
        counts = Table.grid(padding=(0, 2))
        counts.add_row(*[f"{name} {counters.get(name, 0)}" for name in shown[:5]])
        counts.add_row(*[f"{name} {counters.get(name, 0)}" for name in shown[5:]])
        return Group(head, body, Text("decisions (█ H1, · H0, ? undecided): ") + strip, counts)
