"""The grip stage of a fuser fed by assemblers (issues 23 and 24): the assemblers' parts carry the
taxels only; the gripper drive's frames are heard by the fuser, the one CANopen master on the
bus, and its own assembler's snapshot of the drive at each cycle's close goes with the merged
cycle (``AssembledFusionService.evaluate_command``). Before, a merged cycle had no drive: the
grip stage never saw it, and ``run --assemblers`` on a grasp scene sent no command at all.

``node-sim --scene grasp_light --truth-log F`` in one process, ``fusion-center assemble`` in a
second, ``fusion-center run --assemblers`` in a third (udp_multicast on loopback: hop limit 0;
the Zenoh link on 127.0.0.1; every wait bounded)."""

from __future__ import annotations

import json
import random
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from process_helpers import multicast_group_port, node_sim, udp_loopback, wait_ready  # noqa: E402
from test_assemblers import _assemble, _finish  # noqa: E402 - an assemble process, and its bounded end

pytestmark = pytest.mark.multiprocess

CYCLES = 300  # 3 s: approach 1 s, close 0.8 s, lift 1 s, then the hold
SCENE = str(ROOT / "tests" / "data" / "grasp_light.toml")
CLI = [sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())"]  # as _assemble


def test_a_fuser_fed_by_an_assembler_drives_the_gripper(tmp_path):
    group, port = multicast_group_port()
    bus = udp_loopback(group, port)
    fuser_port = random.randint(40000, 60000)
    truth, live = tmp_path / "truth.jsonl", tmp_path / "run.jsonl"
    with node_sim("--scene", SCENE, *bus, "--truth-log", str(truth)):
        assembler = _assemble(SCENE, "0", fuser_port, port, channels=[group])
        try:
            centre = subprocess.run(
                [*CLI, "run", "--scene", SCENE, *bus, "--cycles", str(CYCLES), "--assemblers",
                 f"127.0.0.1:{fuser_port}", "--json-lines", str(live), "--no-live", "--boot-timeout", "5"],
                cwd=ROOT, capture_output=True, text=True, timeout=300)
            wait_ready(assembler, name="fusion-center assemble")
        finally:
            _finish(assembler)  # the fuser's bye ends it (else killed after 30 s)
    assert centre.returncode == 0, centre.stderr
    print(centre.stdout)
    records = [json.loads(line) for line in live.read_text().splitlines()]
    assert len(records) == CYCLES
    assert "assemblers:" in centre.stdout
    # the drive was seen and driven: its state in the records, commands sent
    states = {r["grip"]["drive_state"] for r in records}
    assert "OPERATION ENABLED" in states, states
    commanded = [r["grip"]["command_n"] for r in records if r["grip"]["command_n"]]
    assert commanded and max(commanded) > 0
    # and the world's own log: the object gripped, lifted, never dropped
    steps = [json.loads(line) for line in truth.read_text().splitlines()]
    gripped = [s for s in steps if s["in_grip"] and s["normal_n"] > 0]
    story = [(s["cycle"], s["phase"], round(s["height_mm"], 1), round(s["normal_n"], 2), s["dropped"])
             for s in steps[::20] if s["cycle"] is not None]
    assert gripped and max(s["height_mm"] for s in gripped) > 20, story
    assert not any(s["dropped"] for s in steps), story
