"""Wireshark reads the centre's BLF trace and dissects it as CANopen (issue 12).

Wireshark 4.0 (Debian 12) cannot open python-can's candump ``.log`` (the trailing direction
flag) nor its ``.asc``; it opens ``.blf``, and ``-d can.subdissector,canopen`` makes it decode
every frame as CANopen. Skipped where ``tshark`` is not installed (``apt-get install tshark``).
"""

from __future__ import annotations

import shutil
import subprocess
from collections import Counter
from pathlib import Path

import can
import pytest

from fusion_center.commands.demo import run_demo
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
TSHARK = shutil.which("tshark")
pytestmark = pytest.mark.skipif(TSHARK is None, reason="tshark (Wireshark) is not installed")


def test_tshark_dissects_the_blf_trace_as_canopen(tmp_path):
    scene = load_scene(ROOT / "docs" / "examples" / "four_taxels.toml")
    trace = tmp_path / "run.blf"
    cycles = 5
    run_demo(scene, cycles, json_lines=tmp_path / "run.jsonl", trace=trace)
    frames = list(can.BLFReader(str(trace)))
    done = subprocess.run([TSHARK, "-r", str(trace), "-d", "can.subdissector,canopen",
                           "-T", "fields", "-e", "can.id", "-e", "_ws.col.Info"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    rows = [line.split("\t") for line in done.stdout.splitlines() if line.strip()]
    # every frame of the trace, in order, with its identifier
    assert [int(r[0], 0) for r in rows] == [m.arbitration_id for m in frames]
    kinds = Counter()
    for can_id, info in rows:
        cid = int(can_id, 0)
        if cid == 0x080:
            assert info.startswith("SYNC"), info
            kinds["sync"] += 1
        elif 0x181 <= cid <= 0x1FF:
            assert info.startswith("PDO1"), info
            kinds["tpdo1"] += 1
        elif 0x601 <= cid <= 0x67F:
            assert "SDO" in info and "request" in info, info
            kinds["sdo_request"] += 1
        elif 0x581 <= cid <= 0x5FF:
            assert "SDO" in info and "response" in info, info
            kinds["sdo_response"] += 1
        elif cid == 0x000:
            assert info.startswith("NMT"), info
    assert kinds["sync"] == cycles
    assert kinds["tpdo1"] == sum(1 for m in frames if 0x181 <= m.arbitration_id <= 0x1FF) > 0
    assert kinds["sdo_request"] == kinds["sdo_response"] > 0
