"""--rt-priority with --assemblers: the fuser's SYNC producer and receive thread are raised as in
the plain centre (AssembledFusionService.run ignored rt_priority without a word). The raise is
recorded, not made (taxel_net.realtime.fifo_threads replaced): the test needs no CAP_SYS_NICE."""

from __future__ import annotations

import sys
import uuid
from pathlib import Path

from fusion_center.service.assemblers import AssembledFusionService
from taxel_net import realtime
from taxel_net.scene import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_node_shards import _scene_file  # noqa: E402 - the two-channel patch scene (2 x 40 taxels)


def test_an_assembled_run_raises_its_sync_producer_and_receive_thread(tmp_path, monkeypatch):
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
    assert priority == 20 and "sync-producer" in names and "centre-receive" in names, names
    assert service.rt_threads == names
