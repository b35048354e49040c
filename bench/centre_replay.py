"""The centre's own CPU per cycle at skin scale, replayed from a captured bus: this tree side by
side with another checkout, whatever else the host runs (issue 14).

    .venv/bin/python bench/centre_replay.py [--scene scenes/skin4096.toml] [--cycles 400]
                                            [--against OTHER_CHECKOUT] [--rounds 3]

``bench/skin_scale.py --twins player`` measures SYNC -> record on the bus, which depends on the
load of the 2-core host as much as on the code. This bench takes the bus away: it runs the
centre once with bench/patch_player.py answering on udp_multicast (as skin_scale.py does) and
captures what the centre's listeners received (after its receive thread's reading) and what
it transmitted, with their time stamps; then it replays that stream through a fresh centre on
python-can virtual buses - the received frames handed to its listeners a receive turn at a time
(``on_messages_received`` where the tree has it, else frame by frame), the transmitted ones
through its stream (SYNCs fed at their captured times) - and measures the thread CPU time of the
replay: stream, assembler, evaluation of every stage the scene asks for. What it leaves out is
the reading of the sockets (bench/skin_scale.py prints the receive thread's CPU, which has it).
Each tree replays in its own interpreter, alternately, ``--rounds`` times; printed per tree: the
best and median CPU per cycle, the ratio, and whether both trees made the same records (every
field but the latencies).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pickle
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

REPLAY = r'''
import hashlib, json, pickle, sys, time, uuid
root, events_path, scene_path = sys.argv[1:4]
sys.path.insert(0, root)
import can
import fusion_center
from fusion_center.service import FusionService
from fusion_center.service import stream as stream_module
from taxel_net.scene import load_scene
assert fusion_center.__file__.startswith(root), fusion_center.__file__
events = pickle.loads(open(events_path, "rb").read())
scene = load_scene(scene_path)


class CapturedClock:
    """time as the stream sees it: time() the captured send time of each transmission."""
    now = 0.0

    def time(self):
        return self.now

    def __getattr__(self, name):
        return getattr(time, name)


steps = []   # ("rx", channel, [can.Message]) per receive turn, ("tx", frames, remote, time)
for event in events:
    if event[0] == "rx":
        _, channel, turn = event
        steps.append(("rx", channel, [can.Message(timestamp=ts, arbitration_id=i, data=d, is_extended_id=x,
                                                  is_remote_frame=r, is_error_frame=e, is_fd=f, bitrate_switch=b)
                                      for ts, i, d, x, r, e, f, b in turn]))
    else:
        steps.append(event)
cycles = sum(1 for s in steps if s[0] == "tx" and any(f[1] == 0x080 and f[0] == 0 for f in s[1]))
tag = uuid.uuid4().hex[:8]
service = FusionService(scene, interface="virtual", channels=[f"{c}-{tag}" for c in scene.bus.channels])
service.open()
clock = CapturedClock()
stream_module.time = clock
listeners = [handle.listeners[0] for handle in service.notifiers]
stream = service.stream
t0 = time.thread_time()
for step in steps:
    if step[0] == "rx":
        listener = listeners[step[1]]
        if hasattr(listener, "on_messages_received"):
            listener.on_messages_received(step[2])
        else:
            for msg in step[2]:
                listener.on_message_received(msg)
    else:
        clock.now = step[3]
        stream.transmit_all(step[1], step[2])
cpu_s = time.thread_time() - t0
stream_module.time = time
service.drain()
records = [{k: v for k, v in r.items() if "latency" not in k} for r in service.records]
service.close()
digest = hashlib.sha256(json.dumps(records, sort_keys=True, default=str).encode()).hexdigest()[:16]
print(json.dumps({"ms_per_cycle": cpu_s / cycles * 1e3, "cycles": cycles, "records": len(records),
                  "digest": digest}))
'''


def capture(scene_path: Path, cycles: int, out: Path) -> None:
    """One centre run with the player; the listeners' receive turns and the stream's
    transmissions (with the send time the stream stamps them with) pickled to ``out``."""
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "bench"))
    import time

    from fusion_center.service import stream as stream_module
    from taxel_net.scene import load_scene

    import skin_scale

    events: list[tuple] = []
    listener_cls, echo_cls = stream_module._StreamListener, stream_module.EchoFilter
    batch, single, transmit, is_echo = (listener_cls.on_messages_received, listener_cls.on_message_received,
                                        stream_module.EventStream.transmit_all, echo_cls.is_echo)
    echoes: set[int] = set()  # id() of the frames the centre took as its own looped back

    def noted_is_echo(self, msg, channel):
        echo = is_echo(self, msg, channel)
        if echo:
            echoes.add(id(msg))
        return echo

    def turn(self, msgs):
        msgs = list(msgs)
        result = batch(self, msgs)
        events.append(("rx", self.channel, [(m.timestamp, m.arbitration_id, bytes(m.data), m.is_extended_id,
                                             m.is_remote_frame, m.is_error_frame, m.is_fd, m.bitrate_switch)
                                            for m in msgs if id(m) not in echoes]))  # own echoes: not replayed
        echoes.clear()
        return result

    def transmit_all(self, frames, remote=False):
        frames = list(frames)
        events.append(("tx", frames, remote, time.time()))
        return transmit(self, frames, remote)

    listener_cls.on_messages_received = turn
    listener_cls.on_message_received = lambda self, msg: turn(self, (msg,))
    stream_module.EventStream.transmit_all = transmit_all
    echo_cls.is_echo = noted_is_echo
    try:
        scene = load_scene(scene_path)
        skin_scale.run_sharded(scene, cycles, 1, player=True)
    finally:
        listener_cls.on_messages_received, listener_cls.on_message_received = batch, single
        stream_module.EventStream.transmit_all = transmit
        echo_cls.is_echo = is_echo
    out.write_bytes(pickle.dumps(events))


def replay(tree: Path, events: Path, scene: Path) -> dict:
    done = subprocess.run([sys.executable, "-c", REPLAY, str(tree), str(events), str(scene)],
                          capture_output=True, text=True, cwd=tree)
    if done.returncode != 0:
        raise SystemExit(f"replay in {tree} failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=ROOT / "scenes" / "skin4096.toml")
    ap.add_argument("--cycles", type=int, default=400)
    ap.add_argument("--against", type=Path, help="another checkout of this repository")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    if args.cycles < 50 or args.rounds < 1:
        ap.error("--cycles must be >= 50 and --rounds >= 1")
    trees = [ROOT.resolve()] + ([args.against.resolve()] if args.against else [])
    with tempfile.TemporaryDirectory() as tmp:
        events = Path(tmp) / "events.pkl"
        capture(args.scene.resolve(), args.cycles, events)
        digest = hashlib.sha256(events.read_bytes()).hexdigest()[:12]
        results: dict[Path, list[dict]] = {tree: [] for tree in trees}
        for _ in range(args.rounds):
            for tree in trees:
                results[tree].append(replay(tree, events, args.scene.resolve()))
    first = results[trees[0]][0]
    print(f"{args.scene.stem}: {first['cycles']} cycles captured with bench/patch_player.py (stream {digest}), "
          f"replayed {args.rounds}x per tree, thread CPU per cycle (stream, assembler, evaluation):")
    best = {}
    for tree in trees:
        ms = [r["ms_per_cycle"] for r in results[tree]]
        best[tree] = min(ms)
        print(f"  {tree}: best {min(ms):.3f} ms, median {statistics.median(ms):.3f} ms, "
              f"{results[tree][0]['records']} records (digest {results[tree][0]['digest']})")
    if len(trees) == 2:
        same = results[trees[0]][0]["digest"] == results[trees[1]][0]["digest"]
        print(f"  this tree / other: {best[trees[0]] / best[trees[1]]:.2f}x (best against best); "
              f"records {'identical' if same else 'DIFFER'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
