"""A bus that fails for good, read by python-can's Notifier (interfaces without a socket: pcan,
kvaser, vector, socketcand, ...): the centre's receive thread must not call ``recv`` in a tight
loop - a core at 100 %, and with ``--rt-priority`` (which raises exactly this thread to
SCHED_FIFO, taxel_net.realtime) a thread that starves the host's normal tasks
(fusion_center.service.stream._StreamListener.on_error). Run at the normal priority here."""

from __future__ import annotations

import threading
import time
import uuid

import can

import fusion_center.service.fusion_service as fusion_service
from fusion_center.service import FusionService
from fusion_center.service.stream import BUS_ERROR_BACKOFF_S
from taxel_net.scene import load_scene

SCENE = """
[scene]
name = "bo1"
cycles = 10
[bus]
channels = ["a"]
sync_period_ms = 10.0
[[taxels]]
node_id = 1
kind = "R"
[fusion]
tuple = "pm1"
"""

FAILED_READS = 6


def test_a_bus_failing_for_good_is_not_read_in_a_tight_loop(tmp_path, monkeypatch):
    monkeypatch.setattr(fusion_service, "notifiers_for",  # as for a bus without a socket
                        lambda pairs, timeout=0.05, name="": [can.Notifier(bus, list(listeners), timeout=timeout)
                                                              for bus, listeners in pairs])
    path = tmp_path / "bo1.toml"
    path.write_text(SCENE)
    calls: list[float] = []
    enough = threading.Event()

    def unplugged(timeout):
        if len(calls) >= FAILED_READS:  # enough seen: from now on an idle bus (never spin in the test)
            enough.set()
            time.sleep(timeout or 0)
            return None, False
        calls.append(time.monotonic())
        raise can.CanOperationError("adapter unplugged")

    with FusionService(load_scene(path), channels=[f"bo-{uuid.uuid4().hex[:8]}"]) as service:
        service.buses[0]._recv_internal = unplugged
        assert enough.wait(30)
        reader = service.notifiers[0]._readers[0]
        assert reader.is_alive()                         # a python-can Notifier keeps reading after an error
    gaps = [b - a for a, b in zip(calls, calls[1:])]
    # the first error is retried at once; every later one only after the back-off (a lower bound:
    # a loaded host only lengthens the gaps)
    assert len(gaps) == FAILED_READS - 1
    assert min(gaps[1:]) >= BUS_ERROR_BACKOFF_S * 0.9, gaps
