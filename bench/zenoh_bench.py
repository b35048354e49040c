"""Zenoh's cost (issue 24): the assembler link at skin scale against other trees', and the
CPU of ``--zenoh`` per cycle, side by side in one run.

    .venv/bin/python bench/zenoh_bench.py [--other TREE ...] [--cycles 300] [--repeat 3]
                                          [--part assemblers,publication] [--log]

* **assemblers** - skin4096 (8 channels, 100 Hz) as two node-sim shards (channels 0-3, 4-7),
  two ``fusion-center assemble`` processes (the same groups) and the fuser in this process,
  udp_multicast on the loopback, ``--cycles`` SYNCs; the same set-up run on each tree
  ``--other`` (repeatable, default /work/main; its own interpreter, ``TREE/.venv/bin/python``,
  the link it has - the TCP link of ``multiprocessing.connection`` before commit 83387cb, e.g.
  ``git archive c6a1f5d`` unpacked with a venv of its own), alternating, ``--repeat`` times
  each. Per run: cycles with both parts (complete), degraded (a part missing), late parts,
  unmatched parts, the parts the assemblers sent / did not send (their end lines) and the
  fuser received; SYNC -> part sent p50 / p99 (the assembler's side), part transport p50 / p99
  (sent -> received by the fuser) and SYNC -> record p50 / p99. Then medians over the runs and
  their ratios (this tree / each other), and the CPU per cycle of the fuser's process and of
  the two assembler processes. Goal: the figures within 10 %.
* **publication** - the centre alone in this process (the twins in one node-sim process,
  udp_multicast), matrix57 and skin4096, ``--cycles`` SYNCs, with and without ``--zenoh``
  (``ZenohPublisher``, a subscriber in another process - docs/examples/zenoh_subscriber.py -
  so that every sample goes out), alternating, ``--repeat`` times each: the process's CPU per
  cycle (median of the runs), and the publisher's own CPU per cycle (thread time inside its
  calls) and that of the process's threads that are no Python thread (Zenoh's runtime: its
  transmit thread works for every put; on - off is Zenoh's); the ratio on / off and the
  publisher's share, alone and with Zenoh's threads. ``--log``: both settings write a
  decision log (to /dev/null), whose line the publisher puts instead of serialising the record
  again. Goal: at most +5 %.

bench/zenoh_floor.py measures Zenoh's per-message cost alone (two processes, no centre);
bench/zenoh_put_floor.py that of one ``--zenoh`` put under each of Zenoh's settings.
The host's load is printed with each run: on a shared 2-core machine the spread between runs
is the figure to compare the ratios with.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent


def _root(argv) -> Path:
    for k, a in enumerate(argv):
        if a == "--root" and k + 1 < len(argv):
            return Path(argv[k + 1]).resolve()
    return HERE


ROOT = _root(sys.argv)
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))


# ---------------------------------------------------------------------------- one assembler run (a child)

def assembler_run(cycles: int) -> dict:
    """skin4096: two shards, two assemblers, the fuser here (this interpreter's tree)."""
    import numpy as np

    from fusion_center.service.assemblers import AssembledFusionService
    from skin_scale import CpuMeter, check_records, start_shards
    from taxel_net.scene import load_scene

    scene = load_scene(ROOT / "scenes" / "skin4096.toml")
    port = random.randint(40000, 60000)
    fuser_port = random.randint(40000, 60000)
    groups = [f"239.74.165.{10 + k}" for k in range(len(scene.bus.channels))]
    procs = []
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    service = None
    try:
        start_shards(scene, 2, groups, port, procs)
        service = AssembledFusionService(scene, listen=("127.0.0.1", fuser_port), interface="udp_multicast",
                                         channels=groups, bus_kwargs={"port": port, "hop_limit": 0},
                                         keep_records=True)
        service.open()
        assemblers = [subprocess.Popen(
            [sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())", "assemble",
             "--scene", str(scene.path), "-i", "udp_multicast", "-c", ",".join(groups), "--bus-kwargs",
             f"port={port}", "hop_limit=0", "--serve", serve, "--fuser", f"127.0.0.1:{fuser_port}"],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) for serve in ("0-3", "4-7")]
        procs.extend(assemblers)
        for proc in assemblers:
            line = proc.stdout.readline()
            if "ready" not in line:
                raise SystemExit(f"assemble did not start: {line} {proc.stderr.read() if proc.poll() is not None else ''}")
        service.boot(30.0)
        with CpuMeter([proc.pid for proc in assemblers]) as cpu:
            service.run(cycles, timeout_s=cycles * 0.1 + 120)
    finally:
        if service is not None:
            service.close()
        for proc in procs:
            if proc.poll() is None:
                try:
                    proc.wait(10 if proc in procs[2:] else 0.01)
                except subprocess.TimeoutExpired:
                    pass
            if proc.poll() is None:
                proc.terminate()
                proc.wait(10)
    sent = unsent = 0
    for proc in assemblers:  # "fusion-center assemble: N cycles sent, M not sent, ..."
        for line in (proc.stdout.read() or "").splitlines():
            if " cycles sent, " in line:
                words = line.split(": ", 1)[1].split()
                sent, unsent = sent + int(words[0]), unsent + int(words[3])
    stats = service.merger.stats.as_dict()
    figures = check_records(scene, service.records)
    hist = service.latency
    return {"cycles": len(service.records), "complete": stats["complete"], "degraded": stats["degraded"],
            "parts_sent": sent, "parts_unsent": unsent, "parts": stats["parts"],
            "late_parts": stats["late_parts"], "unmatched": stats["unmatched_parts"],
            "misattributed": figures["misattributed"],
            "to_send_p50": stats["to_send_ms"]["p50"], "to_send_p99": stats["to_send_ms"]["p99"],
            "transport_p50": stats["transport_ms"]["p50"], "transport_p99": stats["transport_ms"]["p99"],
            "record_p50": hist.percentile(50), "record_p99": hist.percentile(99),
            "fuser_cpu_ms": cpu.centre_s / max(cycles, 1) * 1e3, "assemblers_cpu_ms": cpu.twins_s / max(cycles, 1) * 1e3,
            "load": os.getloadavg()[0], "numpy": np.__version__}


# ---------------------------------------------------------------------------- one publication run

def publication_run(scene_name: str, cycles: int, zenoh_on: bool, log: bool = False) -> dict:
    import time as _time

    from fusion_center.service import FusionService
    from skin_scale import CpuMeter, start_shards
    from taxel_net.scene import load_scene

    scene = load_scene(ROOT / "scenes" / f"{scene_name}.toml")
    port = random.randint(40000, 60000)
    groups = [f"239.74.166.{10 + k}" for k in range(len(scene.bus.channels))]
    procs = []
    publisher = None
    spent = [0.0]
    try:
        start_shards(scene, 1, groups, port, procs)
        service = FusionService(scene, interface="udp_multicast", channels=groups,
                                bus_kwargs={"port": port, "hop_limit": 0}, keep_records=False,
                                json_lines=os.devnull if log else None)
        if zenoh_on:
            from fusion_center.service.zenoh_publisher import ZenohPublisher

            zport = random.randint(40000, 60000)
            publisher = ZenohPublisher(scene.name, listen=[f"tcp/127.0.0.1:{zport}"]).open()
            sub = subprocess.Popen([sys.executable, str(ROOT / "docs" / "examples" / "zenoh_subscriber.py"),
                                    "--connect", f"tcp/127.0.0.1:{zport}", "--scene", scene.name, "--raw",
                                    "--timeout", "600"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
            procs.append(sub)
            sub.stderr.readline()
            end = _time.monotonic() + 30
            while not publisher._publishers["record"].matching_status.matching and _time.monotonic() < end:
                _time.sleep(0.01)

            def timed(record, _pub=publisher):
                t0 = _time.thread_time()
                _pub(record)
                spent[0] += _time.thread_time() - t0
            service.on_record.append(timed)
        with service:
            service.boot(30.0)
            before = _native_tasks()
            with CpuMeter() as cpu:
                summary = service.run(cycles)
            after = _native_tasks()
    finally:
        if publisher is not None:
            publisher.close()
        for proc in procs:
            proc.terminate()
            proc.wait(10)
    n = max(summary.cycles, 1)
    native = {}
    for tid, (comm, ns) in after.items():
        if tid in before:  # a thread there throughout (one ending as it is read, not yet gone: left out)
            native[comm] = native.get(comm, 0) + ns - before[tid][1]
    return {"cpu_ms": cpu.centre_s / n * 1e3, "publisher_ms": spent[0] / n * 1e3,
            "native_ms": sum(native.values()) / n / 1e6,
            "native_top": sorted(((round(v / n / 1e6, 4), k) for k, v in native.items()), reverse=True)[:4],
            "records": publisher.records if publisher else 0, "failed": publisher.failed if publisher else 0,
            "p99": summary.latency_percentile(99), "load": os.getloadavg()[0]}


def _native_tasks() -> dict[int, tuple[str, int]]:
    """CPU time (ns, /proc/self/task/*/schedstat) of this process's threads that are no Python
    thread - Zenoh's runtime (its transmit thread ``tx-0`` ...), numpy's - by thread id: name, ns."""
    import threading

    python = {t.native_id for t in threading.enumerate()}
    out = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            tid = int(task.name)
            if tid not in python:
                out[tid] = ((task / "comm").read_text().strip(), int((task / "schedstat").read_text().split()[0]))
        except (OSError, ValueError, IndexError):  # ended meanwhile
            pass
    return out


# ---------------------------------------------------------------------------- the driver

def _child(python: str, root: Path, *args) -> dict:
    env = {**os.environ, "PYTHONPATH": str(root)}
    done = subprocess.run([python, str(Path(__file__).resolve()), "--root", str(root), *args], cwd=root,
                          capture_output=True, text=True, env=env, timeout=3600)
    for line in reversed(done.stdout.splitlines()):
        if line.startswith("{"):
            return json.loads(line)
    raise SystemExit(f"child {python} {args} failed ({done.returncode}): {done.stderr[-2000:]}")


def _median(runs, key):
    values = [r[key] for r in runs if r.get(key) is not None]
    return statistics.median(values) if values else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--other", type=Path, action="append", default=None,
                    help="a tree to compare the link with (repeatable; default /work/main); the ratios are "
                         "this tree's medians over each other's")
    ap.add_argument("--cycles", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--part", default="assemblers,publication")
    ap.add_argument("--log", action="store_true",
                    help="publication: both settings write a decision log (to /dev/null; the publisher reuses "
                         "its line)")
    ap.add_argument("--root", type=Path, default=HERE, help=argparse.SUPPRESS)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child == "assemblers":
        print(json.dumps(assembler_run(args.cycles)))
        return 0
    if args.child and args.child.startswith("publication:"):
        _, scene, on, log = args.child.split(":")
        print(json.dumps(publication_run(scene, args.cycles, on == "1", log == "1")))
        return 0
    parts = set(args.part.split(","))
    me = (sys.executable, HERE)
    others = [(str(tree / ".venv" / "bin" / "python"), tree.resolve()) for tree in (args.other or [Path("/work/main")])]
    commit = lambda root: subprocess.run(["git", "-C", str(root), "log", "-1", "--format=%h"], capture_output=True,  # noqa: E731
                                         text=True).stdout.strip()
    if "assemblers" in parts:
        trees = [("zenoh", me)] + [(f"other{k + 1}" if len(others) > 1 else "other", tree)
                                   for k, tree in enumerate(others)]
        print(f"assemblers, skin4096, {args.cycles} cycles, 2 shards + 2 assemblers + fuser; this tree "
              f"{commit(HERE)} (Zenoh link) against " + ", ".join(f"{name} = {root} {commit(root)}"
                                                                    for name, (_, root) in trees[1:]), flush=True)
        runs = {name: [] for name, _ in trees}
        for k in range(args.repeat):
            for name, (python, root) in trees[1:] + trees[:1]:
                r = _child(python, root, "--child", "assemblers", "--cycles", str(args.cycles))
                runs[name].append(r)
                print(f"  {name:6s} run {k + 1}: complete {r['complete']}/{r['cycles']}, degraded {r['degraded']}, "
                      f"late parts {r['late_parts']}, unmatched {r['unmatched']}, misattributed "
                      f"{r['misattributed']}, parts sent {r['parts_sent']} / not sent {r['parts_unsent']} / "
                      f"received {r['parts']}; "
                      f"SYNC -> part sent p50 {r['to_send_p50']:.2f} / p99 {r['to_send_p99']:.2f} ms, transport p50 "
                      f"{r['transport_p50']:.2f} / p99 {r['transport_p99']:.2f} ms, SYNC -> record p50 "
                      f"{r['record_p50']:.2f} / p99 {r['record_p99']:.2f} ms; CPU a cycle: fuser "
                      f"{r['fuser_cpu_ms']:.2f} ms, assemblers {r['assemblers_cpu_ms']:.2f} ms (load {r['load']:.1f})",
                      flush=True)
        for name, _ in trees[1:]:
            print(f"  medians (zenoh / {name} = ratio):")
            for key in ("complete", "degraded", "to_send_p50", "to_send_p99", "transport_p50", "transport_p99",
                        "record_p50", "record_p99", "fuser_cpu_ms", "assemblers_cpu_ms"):
                z, o = _median(runs["zenoh"], key), _median(runs[name], key)
                ratio = f"{z / o:.2f}" if z is not None and o else "-"
                print(f"    {key:17s} {z:10.2f} / {o:10.2f} = {ratio}")
    if "publication" in parts:
        print(f"--zenoh publication, the centre alone (twins in a node-sim process), {args.cycles} cycles, "
              f"a subscriber in another process" + (", both with a decision log (--log)" if args.log else ""),
              flush=True)
        for scene in ("matrix57", "skin4096"):
            runs = {"off": [], "on": []}
            for k in range(args.repeat):
                for on in (False, True):
                    r = _child(me[0], me[1], "--child", f"publication:{scene}:{int(on)}:{int(args.log)}",
                               "--cycles", str(args.cycles))
                    runs["on" if on else "off"].append(r)
                    print(f"  {scene} {'on ' if on else 'off'} run {k + 1}: CPU {r['cpu_ms']:.3f} ms a cycle, "
                          f"publisher {r['publisher_ms']:.4f} ms, native threads {r['native_ms']:.4f} ms "
                          f"({', '.join(f'{name} {ms:.3f}' for ms, name in r['native_top'])}), "
                          f"records {r['records']}, failed {r['failed']}, "
                          f"SYNC -> record p99 {r['p99']:.2f} ms (load {r['load']:.1f})", flush=True)
            off, on = _median(runs["off"], "cpu_ms"), _median(runs["on"], "cpu_ms")
            pub = _median(runs["on"], "publisher_ms")
            native = _median(runs["on"], "native_ms") - _median(runs["off"], "native_ms")
            print(f"  {scene}: CPU per cycle median on {on:.3f} / off {off:.3f} ms = {on / off:.3f}; "
                  f"the publisher's own {pub:.4f} ms a cycle = {100 * pub / off:.2f} % of the centre's; with Zenoh's "
                  f"threads (native threads on - off, {native:.4f} ms) {pub + native:.4f} ms = "
                  f"{100 * (pub + native) / off:.2f} %", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
