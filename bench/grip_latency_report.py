"""bench/grip_latency.py's tables: per scene x transport rows, the breakdown, the summary and
``--compare`` of ``--json`` files. See that module's docstring."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np

GOAL_MS = 2.0  # issue 23: SYNC -> command p99 at most 2 ms
STAGES = ("answers", "wake", "assemble", "rules", "forces", "slip", "record", "grip", "send", "centre")


def _pct(values, q):
    return float(np.percentile(values, q)) if len(values) else float("nan")


def _spread(values) -> str:
    values = [v for v in values if v == v]
    if not values:
        return "-"
    if len(values) == 1:
        return f"{values[0]:.2f}"
    return f"{np.median(values):.2f} ({min(values):.2f}-{max(values):.2f})"


def uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "uptime: n/a"


def print_row(name: str, transport: str, runs: list[dict], label: str = "") -> None:
    stats = {q: [_pct(r["lat"], q) for r in runs] for q in (50, 90, 99, 100)}
    other = [sum(v for k, v in r["closed_by"].items() if k != "complete") for r in runs]
    print(f"{label}{name:16s} {transport:9s} {'/'.join(str(len(r['lat'])) for r in runs):>11s} "
          f"{_spread(stats[50]):>17s} {_spread(stats[90]):>17s} {_spread(stats[99]):>18s} "
          f"{_spread(stats[100]):>20s} {'/'.join(map(str, other)):>12s} "
          f"{_spread([r['centre_p99'] for r in runs]):>18s}")


def print_breakdown(runs: list[dict]) -> None:
    parts = []
    for stage in STAGES:
        values = [v for r in runs for v in r["stages"].get(stage, [])]
        if not values:
            continue
        parts.append(f"{stage} {_pct(values, 50):.3f}/{_pct(values, 99):.3f}")
    n = sum(len(r["stages"]["send"]) for r in runs)
    cpu = [r["receive_cpu_ms"] for r in runs if r.get("receive_cpu_ms") is not None]
    if cpu:  # udp / player: the centre's receive thread's CPU time (boot included) per SYNC
        parts.append("receive thread CPU " + "/".join(f"{v:.2f}" for v in cpu) + " ms/cycle")
    print(f"{'':10s}breakdown p50/p99 ms over {n} complete cycles: " + ", ".join(parts))


def _loadavg() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def print_summary(results) -> None:
    """Per scene x transport: the wire floor and the end-to-end p50/p99 over all runs' cycles
    pooled, against the goal; ``answers`` and ``centre`` p50/p99, ``wake`` and ``assemble`` p50
    (the breakdown's, pooled); the host's load average (1, 5, 15 min) before -> after."""
    print(f"\nsummary: SYNC -> command on the bus, all runs' cycles pooled; goal p99 <= {GOAL_MS:g} ms "
          f"(issue 23); {os.cpu_count()} cpus; answers, centre: p50/p99 ms; wake, assemble: p50 ms")
    print(f"{'scene':24s} {'transport':9s} {'wire floor':>10s} {'cycles':>7s} {'p50':>7s} {'p99':>7s} "
          f"{'p99 <= 2 ms':>11s} {'answers':>11s} {'centre':>11s} {'wake':>6s} {'assemble':>8s}"
          "  load average before -> after")
    for name, transport, floor, runs, (before, after) in results:
        lat = [v for r in runs for v in r["lat"]]
        p99 = _pct(lat, 99)
        verdict = "yes" if p99 <= GOAL_MS else "no"
        if floor > GOAL_MS:
            verdict += " (wire)"   # the bus alone takes longer than the goal
        stage = {s: [v for r in runs for v in r["stages"].get(s, [])] for s in ("answers", "centre", "wake", "assemble")}
        both = {s: f"{_pct(stage[s], 50):.2f}/{_pct(stage[s], 99):.2f}" for s in ("answers", "centre")}
        print(f"{name:24s} {transport:9s} {floor:8.2f} ms {len(lat):7d} {_pct(lat, 50):7.2f} {p99:7.2f} "
              f"{verdict:>11s} {both['answers']:>11s} {both['centre']:>11s} {_pct(stage['wake'], 50):6.2f} "
              f"{_pct(stage['assemble'], 50):8.2f}  "
              f"{' '.join(f'{v:.2f}' for v in before)} -> {' '.join(f'{v:.2f}' for v in after)}")


HEADER = (f"{'scene':16s} {'transport':9s} {'cycles/run':>11s} {'p50':>17s} {'p90':>17s} {'p99':>18s} "
          f"{'max':>20s} {'not complete':>12s} {'centre p99':>18s}")


def compare(files: list[str]) -> int:
    """``--compare A.jsonl B.jsonl ...``: the results of several ``--json`` files side by side."""
    data = []
    for f in files:
        rows = [json.loads(line) for line in Path(f).read_text().splitlines() if line.strip()]
        data.append((Path(f).stem, rows))
    keys = []
    for _, rows in data:
        for row in rows:
            if (row["scene"], row["transport"]) not in keys:
                keys.append((row["scene"], row["transport"]))
    print("label      " + HEADER)
    for scene, transport in keys:
        for label, rows in data:
            runs = [run for row in rows if (row["scene"], row["transport"]) == (scene, transport) for run in row["runs"]]
            if runs:
                print_row(scene, transport, runs, f"{label[:10]:10s} ")
        for label, rows in data:
            runs = [run for row in rows if (row["scene"], row["transport"]) == (scene, transport) for run in row["runs"]]
            if runs:
                print(f"{label[:10]:10s}", end="")
                print_breakdown(runs)
    return 0

