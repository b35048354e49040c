"""bench/grip_latency.py's scheduling options (--rt-priority, --nodes-rt, --pin,
--switch-interval-ms): a bad value is one line naming the option, exit 2, before anything runs
(it was a traceback - --nodes-rt's from inside the node process's preexec_fn)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))
import grip_latency  # noqa: E402

RUN = ["--runs", "1", "--cycles", "5", "--echo", "0", "--scenes", "grasp_lift_patch", "--transports", "udp"]


@pytest.mark.parametrize("args, needle", [
    (["--rt-priority", "0"], "--rt-priority 0: out of range (allowed: 1-99"),
    (["--rt-priority", "100"], "--rt-priority 100: out of range (allowed: 1-99"),
    (["--nodes-rt", "0"], "--nodes-rt 0: out of range (allowed: 1-99"),
    (["--nodes-rt", "-1"], "--nodes-rt -1: out of range (allowed: 1-99"),
    (["--pin", "0", "x"], "--pin CENTRE_CPUS 'x': not a CPU list"),
    (["--pin", "4096", "0"], "--pin NODE_CPUS '4096': CPU(s) [4096] not available"),
    (["--switch-interval-ms", "0"], "--switch-interval-ms 0: must be > 0"),
    (["--switch-interval-ms", "-2"], "--switch-interval-ms -2: must be > 0"),
])
def test_a_bad_scheduling_option_is_one_line_and_exit_2(args, needle, capsys, monkeypatch):
    ran = []
    monkeypatch.setattr(grip_latency, "_measure", lambda a: ran.append(a) or 0)
    switch = sys.getswitchinterval()
    assert grip_latency.main(RUN + args) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err == f"grip_latency: error: {err.split('error: ', 1)[1]}" and needle in err, err
    assert ran == [] and sys.getswitchinterval() == switch
    assert grip_latency.CENTRE_OPTIONS == {} and grip_latency.NODES_RT == [] and grip_latency.NODE_CPUS == []


def test_nodes_rt_not_permitted_is_one_line_and_exit_2(capsys, monkeypatch):
    monkeypatch.setattr(grip_latency, "_measure", lambda a: 0)
    monkeypatch.setattr(grip_latency, "_fifo_permitted", lambda priority: False)
    assert grip_latency.main(RUN + ["--nodes-rt", "60"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--nodes-rt 60: SCHED_FIFO not permitted" in err, err
