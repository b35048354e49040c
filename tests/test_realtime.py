"""--rt-priority (taxel_net.realtime, FusionService(rt_priority=...), fusion-center run): the
centre's receive thread and SYNC producer under SCHED_FIFO, opt-in; a refusal is one warning
line, never an error (issue 23, docs/grip-control.md "2026-11-30 (stop 31)")."""

from __future__ import annotations

import logging
import os
import threading
import uuid

import pytest

from fusion_center.service import FusionService
from node_sim.rig import Rig
from taxel_net import realtime
from taxel_net.errors import UsageError
from taxel_net.scene import load_scene

SCENE = """
[scene]
name = "rt1"
cycles = 10
[bus]
channels = ["a"]
sync_period_ms = 10.0
heartbeat_producer_ms = 30
[[taxels]]
node_id = 1
kind = "R"
[[taxels]]
node_id = 2
kind = "R"
[fusion]
tuple = "pm1"
"""

linux_rt = pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="no sched_setscheduler here")


def _fifo_permitted() -> bool:
    """Whether this process may use SCHED_FIFO (tried on a short-lived thread of its own)."""
    result = []

    def probe():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(1))
            result.append(True)
        except OSError:
            result.append(False)

    t = threading.Thread(target=probe)
    t.start()
    t.join(5)
    return bool(result and result[0])


@pytest.mark.parametrize("value", [0, 100, -1, "x", 1.5, None])
def test_a_priority_outside_1_to_99_is_refused_with_the_option_named(value):
    with pytest.raises(ValueError, match=r"^--rt-priority .*allowed: 1-99"):
        realtime.check_priority(value)


def test_priorities_1_and_99_are_accepted():
    assert realtime.check_priority(1) == 1 and realtime.check_priority("99") == 99


def test_the_service_refuses_a_bad_priority_as_a_usage_error(tmp_path):
    path = tmp_path / "rt1.toml"
    path.write_text(SCENE)
    with pytest.raises(UsageError, match="--rt-priority 0: out of range"):
        FusionService(load_scene(path), rt_priority=0)


@linux_rt
def test_not_permitted_is_one_warning_and_the_thread_keeps_its_policy(monkeypatch, caplog):
    calls = []

    def refuse(tid, policy, param):
        calls.append(tid)
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(realtime, "_warned", False)
    stop = threading.Event()
    threads = [threading.Thread(target=stop.wait, args=(10,), name=f"t{k}") for k in range(2)]
    for t in threads:
        t.start()
    try:
        before = realtime.policy_of(threads[0])
        with caplog.at_level(logging.WARNING, logger="taxel_net.realtime"):
            assert realtime.fifo_threads(threads, 50) == []
            assert realtime.fifo_threads(threads, 50) == []
        assert realtime.policy_of(threads[0]) == before and before[0] == os.SCHED_OTHER
    finally:
        stop.set()
        for t in threads:
            t.join(5)
    assert len(calls) == 2                               # one try per call, not per thread after a refusal
    lines = [r.getMessage() for r in caplog.records if r.name == "taxel_net.realtime"]
    assert len(lines) == 1 and "--rt-priority 50: SCHED_FIFO not permitted (EPERM" in lines[0]


@linux_rt
def test_fifo_threads_puts_a_running_thread_under_sched_fifo():
    if not _fifo_permitted():
        pytest.skip("SCHED_FIFO not permitted for this user")
    stop = threading.Event()
    t = threading.Thread(target=stop.wait, args=(10,), name="rt-probe")
    t.start()
    try:
        assert realtime.policy_of(t)[0] == os.SCHED_OTHER
        assert realtime.fifo_threads([t], 7) == ["rt-probe"]
        assert realtime.policy_of(t) == (os.SCHED_FIFO, 7)
    finally:
        stop.set()
        t.join(5)


_RLIMIT_CHILD = """
import importlib.util, logging, resource, sys, threading
spec = importlib.util.spec_from_file_location("realtime", sys.argv[1])   # stdlib only: any python3 runs it
realtime = importlib.util.module_from_spec(spec)
spec.loader.exec_module(realtime)
logging.basicConfig(level=logging.WARNING, format="%(message)s", stream=sys.stdout)
limit = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
stop = threading.Event()
threads = [threading.Thread(target=stop.wait, args=(10,), name=f"rt-{p}") for p in (1, 2)]
for t in threads:
    t.start()
print("limit", limit)
if limit >= 1:
    print("within", realtime.fifo_threads([threads[0]], limit), realtime.policy_of(threads[0]))
print("above", realtime.fifo_threads([threads[1]], limit + 1), realtime.policy_of(threads[1]))
stop.set()
"""


def _as_nobody() -> list[str]:
    """_RLIMIT_CHILD's lines, run as the user nobody with RLIMIT_RTPRIO raised to 40 where this host
    lets root raise the hard limit (CAP_SYS_RESOURCE), else the limit inherited; skips (with the
    reason) where that cannot be done here: not root, a user namespace that maps only root, no
    python3 and project file nobody may run / read."""
    import resource
    import subprocess
    import sys
    from pathlib import Path

    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        pytest.skip("needs root to start a child as an unprivileged user (nobody)")

    def demote():
        try:
            resource.setrlimit(resource.RLIMIT_RTPRIO, (40, 40))
        except (ValueError, OSError):   # no CAP_SYS_RESOURCE (a container): the inherited limit
            pass
        os.setgroups([])
        os.setgid(65534)
        os.setuid(65534)

    module = Path(realtime.__file__).resolve()
    for python in dict.fromkeys((sys.executable, "/usr/bin/python3")):  # the venv's may lie under /root
        try:
            out = subprocess.run([python, "-c", _RLIMIT_CHILD, str(module)], capture_output=True, text=True,
                                 timeout=60, preexec_fn=demote, cwd="/", env={"PATH": os.environ.get("PATH", "")})
        except (PermissionError, FileNotFoundError):
            continue
        except subprocess.TimeoutExpired:
            raise
        except subprocess.SubprocessError as exc:   # preexec_fn failed: setuid refused (a user namespace)
            pytest.skip(f"cannot become the user nobody here ({exc}): a user namespace that maps only root?")
        if "Permission denied" not in out.stderr:
            assert out.returncode == 0, out.stderr
            return out.stdout.splitlines()
    pytest.skip("no python3 and project file here that the user nobody may run / read")


@linux_rt
def test_an_unprivileged_user_is_refused_sched_fifo_above_its_rlimit_rtprio_with_one_warning():
    """The path without CAP_SYS_NICE, against the kernel (not a patched setter): a child run as
    nobody asks for one more than its ``RLIMIT_RTPRIO`` (``ulimit -r``; often 0) and is refused
    (EPERM) with the one warning line naming ``ulimit -r``: the thread keeps SCHED_OTHER, the
    process goes on."""
    lines = _as_nobody()
    limit = int(lines[0].split()[1])
    assert f"above [] ({os.SCHED_OTHER}, 0)" in lines
    warnings = [line for line in lines if "SCHED_FIFO not permitted" in line]
    assert len(warnings) == 1
    assert f"--rt-priority {limit + 1}" in warnings[0] and f"`ulimit -r` >= {limit + 1}" in warnings[0]


@linux_rt
def test_an_unprivileged_user_gets_sched_fifo_up_to_its_rlimit_rtprio():
    """... and is granted SCHED_FIFO up to the limit (where root here may raise the hard limit to
    40 for the child, and SCHED_FIFO is permitted at all)."""
    if not _fifo_permitted():
        pytest.skip("SCHED_FIFO not permitted on this host even as root")
    lines = _as_nobody()
    limit = int(lines[0].split()[1])
    if limit < 1:
        pytest.skip("RLIMIT_RTPRIO cannot be raised here (no CAP_SYS_RESOURCE): nobody's limit is 0")
    assert f"within ['rt-1'] ({os.SCHED_FIFO}, {limit})" in lines


def _run(tmp_path, rt_priority):
    """A short run on a virtual bus; the scheduling policy seen by the receive thread (where the
    records are made) and by the SYNC producer (before_sync) in each cycle."""
    path = tmp_path / "rt1.toml"
    path.write_text(SCENE)
    scene = load_scene(path)
    channel = f"rt-{uuid.uuid4().hex[:8]}"
    seen = {"record": [], "sync": [], "heartbeat": []}
    rig = Rig(scene, channel=[channel])
    holder = []

    def on_record(record):
        seen["record"].append(os.sched_getscheduler(0))
        seen["heartbeat"].append(realtime.policy_of(holder[0].master._heartbeat_thread))

    try:
        with FusionService(scene, channels=[channel], rt_priority=rt_priority, on_record=on_record) as service:
            holder.append(service)
            rig.start()
            service.boot(3.0)
            service.run(8, before_sync=lambda k: seen["sync"].append(os.sched_getscheduler(0)))
    finally:
        rig.stop()
    return service, seen


@linux_rt
def test_the_receive_thread_sync_producer_and_heartbeat_run_under_sched_fifo_with_rt_priority(tmp_path):
    if not _fifo_permitted():
        pytest.skip("SCHED_FIFO not permitted for this user")
    flags = getattr(os, "SCHED_RESET_ON_FORK", 0)
    service, seen = _run(tmp_path, 20)
    assert service.rt_threads == ["centre-receive", "sync-producer", "master-heartbeat"]
    # the records are made in the receive thread; the SYNC producer raises the threads before
    # its first SYNC: every cycle runs raised
    assert len(seen["record"]) == 8 and {p & ~flags for p in seen["record"]} == {os.SCHED_FIFO}
    assert {p & ~flags for p in seen["sync"]} == {os.SCHED_FIFO}
    assert set(seen["heartbeat"]) == {(os.SCHED_FIFO, 20)}
    service, seen = _run(tmp_path, None)                 # default: the normal policy
    assert service.rt_threads == [] and set(seen["record"]) == set(seen["sync"]) == {os.SCHED_OTHER}
    assert {p for p, _ in seen["heartbeat"]} == {os.SCHED_OTHER}
