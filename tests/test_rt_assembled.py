"""--rt-priority with --assemblers: the fuser's SYNC producer, receive thread and merge thread (it
evaluates the merged cycles and sends the command) are raised as in the plain centre
(AssembledFusionService.run ignored rt_priority without a word). The raise is
recorded, not made (taxel_net.realtime.fifo_threads replaced): the test needs no CAP_SYS_NICE."""

from __future__ import annotations

import sys
import threading
import uuid
from pathlib import Path

from fusion_center.service.assemblers import AssembledFusionService
from taxel_net import realtime
from taxel_net.scene import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_node_shards import _scene_file  # noqa: E402 - the two-channel patch scene (2 x 40 taxels)


def test_an_assembled_run_raises_its_sync_producer_receive_and_merge_threads(tmp_path, monkeypatch):
    asked = []

    def record(threads, priority):
        threads = list(threads)
        asked.append(([t.name for t in threads], priority))
        return [t.name for t in threads]

    monkeypatch.setattr(realtime, "fifo_threads", record)
    scene = load_scene(_scene_file(tmp_path))
    tag = uuid.uuid4().hex[:8]
    service = AssembledFusionService(scene, listen=("127.0.0.1", 47998), interface="virtual",
                                     channels=[f"ra-{tag}", f"rb-{tag}"], rt_priority=20, part_deadline_s=0.05)
    with service:
        service.run(2, timeout_s=10.0)
    assert len(asked) == 1
    names, priority = asked[0]
    assert priority == 20 and {"sync-producer", "centre-receive", "merge-deadline"} <= set(names), names
    assert service.rt_threads == names


def test_the_threads_are_raised_before_the_first_sync(tmp_path, monkeypatch):
    """FusionService.run raised them from the calling thread after the SYNC producer had started:
    its first SYNC (and so the first cycle) went out at the normal priority, and later ones too
    when the caller was late. Now the SYNC producer raises them before its first SYNC."""
    import test_realtime

    asked = []

    def record(threads, priority):
        threads = list(threads)
        master = holder[0].master
        asked.append((threading.current_thread() is master._sync_thread, master.sync_sent, priority))
        return [t.name for t in threads]

    holder: list = []
    real_init = test_realtime.FusionService.__init__

    def init(self, *args, **kwargs):
        real_init(self, *args, **kwargs)
        holder.append(self)

    monkeypatch.setattr(test_realtime.FusionService, "__init__", init)
    monkeypatch.setattr(realtime, "fifo_threads", record)
    service, seen = test_realtime._run(tmp_path, 20)
    assert asked == [(True, 0, 20)]                  # once, in the SYNC producer, before any SYNC
    assert service.rt_threads == ["centre-receive", "sync-producer", "master-heartbeat"]


def test_a_node_reconfigured_mid_run_is_configured_at_the_raised_priority(tmp_path, monkeypatch):
    """A node that boots again during a --rt-priority run is reconfigured by a recover thread,
    whose every SDO request is sent under the stream lock the receive thread needs: at the normal
    priority a holder preempted by the host's other jobs kept the SCHED_FIFO receive thread
    waiting. It is raised too (recorded here, not made: no CAP_SYS_NICE needed)."""
    import can

    import test_realtime
    from node_sim.rig import Rig

    asked = []

    def record(threads, priority):
        names = [t.name for t in threads]
        asked.append((names, priority))
        return names

    monkeypatch.setattr(realtime, "fifo_threads", record)
    path = tmp_path / "rt1.toml"
    path.write_text(test_realtime.SCENE.replace("cycles = 10", "cycles = 40"))
    scene = load_scene(path)
    channel = f"rr-{uuid.uuid4().hex[:8]}"
    rig = Rig(scene, channel=[channel])
    other = can.Bus(interface="virtual", channel=channel)

    def reset_node_1(k):
        if k == 5:  # NMT reset node (another master's): node 1 boots again, the centre reconfigures it
            other.send(can.Message(arbitration_id=0x000, data=bytes((0x81, 1)), is_extended_id=False))

    try:
        with test_realtime.FusionService(scene, channels=[channel], rt_priority=30) as service:
            rig.start()
            service.boot(3.0)
            at_boot = service.master.sdo_writes
            service.run(30, before_sync=reset_node_1)
            reconfigured = service.master.sdo_writes - at_boot
    finally:
        rig.stop()
        other.shutdown()
    assert reconfigured > 0                          # node 1's SDO configuration again, mid-run
    assert (["recover-0"], 30) in asked, asked
