"""Two processes on udp_multicast: how many decisions reach the centre within their window?

    .venv/bin/python bench/udp_two_process.py [--cycles 300] [--period-ms 10 20]

Starts ``node-sim`` (the 57 twins of scenes/matrix57.toml) in its own process and the fusion
centre in this one, both on python-can's udp_multicast interface (loopback), once per SYNC
period given. Prints per run: decisions received in their synchronous window (0x1007, 80 % of
the period) out of cycles x taxels, PDOs counted late, records complete / degraded /
undecided, and records carrying a decision of another cycle (``misattributed``, checked
against the physics of each cycle; the cycle tag of TPDO1 makes it 0 by construction).

The in-window fraction measures the host, not the code: how soon two Python processes are
scheduled after a SYNC datagram. Run it on an idle machine for the figure the docs quote
(docs/service.md, "Cycle integrity").
"""

from __future__ import annotations

import argparse
import dataclasses
import random
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from fusion_center.service import FusionService  # noqa: E402
from junk_flood import check_records  # noqa: E402
from taxel_net.scene import load_scene  # noqa: E402

GROUP = "239.74.163.2"
SCENE = ROOT / "scenes" / "matrix57.toml"


def run_once(period_ms: float, cycles: int) -> dict:
    port = random.randint(40000, 60000)
    scene = load_scene(SCENE)
    bus = dataclasses.replace(scene.bus, sync_period_ms=period_ms, sync_window_us=int(period_ms * 800))
    scene = dataclasses.replace(scene, bus=bus)
    text = SCENE.read_text().replace('taxels_file = "data/', f'taxels_file = "{SCENE.parent}/data/')
    text = text.replace("sync_period_ms = 10.0", f"sync_period_ms = {period_ms}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scene.toml"
        path.write_text(text)
        sim = subprocess.Popen([sys.executable, "-m", "node_sim.cli", "--scene", str(path), "--interface",
                                "udp_multicast", "--channel", GROUP, "--bus-option", f"port={port}",
                                "--bus-option", "hop_limit=0"],
                               cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            ready = sim.stdout.readline()
            if "ready" not in ready:
                raise SystemExit(f"node-sim did not start: {sim.stderr.read() if sim.poll() is not None else ready}")
            with FusionService(scene, interface="udp_multicast", channels=[GROUP],
                               bus_kwargs={"port": port, "hop_limit": 0}) as service:
                service.boot(5.0)
                summary = service.run(cycles)
        finally:
            sim.terminate()
            sim.wait(10)
    records = service.records
    received = sum(r["n_received"] for r in records)
    return {"period_ms": period_ms, "received": received, "expected": cycles * scene.n,
            "late": summary.counters.get("late", 0), **check_records(scene, records)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=300)
    ap.add_argument("--period-ms", type=float, nargs="+", default=[10.0, 20.0])
    args = ap.parse_args(argv)
    for period in args.period_ms:
        f = run_once(period, args.cycles)
        print(f"SYNC {f['period_ms']:g} ms: {f['received']}/{f['expected']} decisions in their window "
              f"({100 * f['received'] / f['expected']:.1f} %), {f['late']} late; records: {f['complete']} complete, "
              f"{f['degraded']} degraded, {f['undecided']} undecided, misattributed {f['misattributed']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
