"""--busy-poll-ms (taxel_net.receiver.SelectNotifiers.busy_poll, FusionService(busy_poll_ms=...)):
after each SYNC the centre's receive thread reads its buses without blocking until the cycle
closes or the time is up, then blocks again (issue 23, docs/grip-control.md "2026-11-30 (stop 31)")."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import can
import pytest

from fusion_center.service import FusionService
from node_sim.rig import Rig
from taxel_net.errors import UsageError
from taxel_net.receiver import SelectNotifiers
from taxel_net.scene import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_realtime import SCENE  # noqa: E402
from test_service_multiprocess import multicast_port  # noqa: E402

GROUP = "239.74.163.57"


def _wait(predicate, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def test_the_thread_polls_while_kept_then_blocks_again_and_frames_still_arrive():
    port = multicast_port()
    rx = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    tx = can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)
    got: list[int] = []
    notifiers = SelectNotifiers([(rx, [lambda msg: got.append(msg.arbitration_id)])], timeout=5.0)
    try:
        keep = [True]
        time.sleep(0.05)
        assert notifiers.poll_turns == 0                     # blocked in select (a 5 s timeout)
        notifiers.busy_poll(time.monotonic() + 30.0, lambda: keep[0])
        assert _wait(lambda: notifiers.poll_turns > 50)       # woken through its pipe, polling
        tx.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))
        assert _wait(lambda: 0x181 in got)
        keep[0] = False                                       # the cycle closed: back to blocking
        assert _wait(lambda: notifiers._poll is None)
        turns = notifiers.poll_turns
        time.sleep(0.1)
        assert notifiers.poll_turns == turns
        notifiers.busy_poll(time.monotonic() - 1.0, lambda: True)   # a deadline passed: no polling
        time.sleep(0.1)
        assert notifiers.poll_turns == turns and notifiers._poll is None
        tx.send(can.Message(arbitration_id=0x182, data=b"\x02", is_extended_id=False))
        assert _wait(lambda: 0x182 in got)                    # blocking reads still deliver
    finally:
        notifiers.stop()
        rx.shutdown()
        tx.shutdown()
    assert notifiers._wake is None                            # its pipe closed with the thread


@pytest.mark.parametrize("value", [0, -1, float("nan"), 21.0])
def test_a_bad_busy_poll_time_is_a_usage_error(tmp_path, value):
    path = tmp_path / "rt1.toml"
    path.write_text(SCENE)
    with pytest.raises(UsageError, match=r"--busy-poll-ms .*must be a number of ms in \(0, 20\]"):
        FusionService(load_scene(path), busy_poll_ms=value)


def _udp_run(tmp_path, busy_poll_ms):
    path = tmp_path / "rt1.toml"
    path.write_text(SCENE)
    scene = load_scene(path)
    port = multicast_port()
    group = f"239.74.163.{58 + int(busy_poll_ms or 0)}"
    rig = Rig(scene, interface="udp_multicast", channel=[group], bus_kwargs={"port": port, "hop_limit": 0})
    try:
        with FusionService(scene, interface="udp_multicast", channels=[group],
                           bus_kwargs={"port": port, "hop_limit": 0}, busy_poll_ms=busy_poll_ms) as service:
            rig.start()
            service.boot(3.0)
            service.run(10)
            owner = service.notifiers[0].owner
    finally:
        rig.stop()
    return service, owner


def test_the_centre_polls_after_each_sync_only_with_the_option(tmp_path):
    service, owner = _udp_run(tmp_path, 5.0)
    assert service.master.sync_sent == 10 and len(service.records) == 10
    assert owner.poll_turns > 0 and owner._poll is None
    assert all(r["closed_by"] == "complete" for r in service.records[1:])
    service, owner = _udp_run(tmp_path, None)
    assert service.master.sync_sent == 10 and owner.poll_turns == 0 and owner._wake is None
