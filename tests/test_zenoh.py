"""Every record on Zenoh (issue 24, part 3): ``--zenoh`` on ``run`` / ``demo`` and
``ZenohPublisher`` publish each record (the decision log's bytes), the grip command and contact
events on the documented keys; the sessions' settings come from flags, then the environment,
then a Zenoh file, loopback by default; a bad file is one line; a stalled subscriber never
holds the publishing thread. Loopback endpoints only, multicast scouting off."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from taxel_net.errors import UsageError

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from test_assemblers import zenoh_peer  # noqa: E402

GRIP = {"command_n": 12.5, "actual_n": 11.75, "drive_state": "operation enabled", "grip_state": "holding",
        "slip": False}


def _ports(k: int) -> list[int]:
    """``k`` loopback TCP ports the system has just handed out as free (not a random pick that
    may be another test's listener: a peer connected there never matches)."""
    import socket

    sockets = [socket.socket() for _ in range(k)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def _subscribe(session, key: str):
    got = []
    cond = threading.Condition()

    def on_sample(sample):
        with cond:
            got.append((str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding)))
            cond.notify_all()

    sub = session.declare_subscriber(key, on_sample)

    def wait(n: int, limit_s: float = 30.0) -> list:  # a safety limit, not a timing claim
        with cond:
            cond.wait_for(lambda: len(got) >= n, limit_s)
            return list(got)
    return sub, got, wait


def _connected(publisher, *names: str) -> None:
    """Waits until the publisher itself knows a subscriber wants each of ``names`` (its matching
    listener, which decides whether a record is put: polling Zenoh's matching status instead
    raced that listener's thread); a safety limit, not a timing claim."""
    import time

    end = time.monotonic() + 30
    while not all(publisher._matching.get(n) for n in names) and time.monotonic() < end:
        time.sleep(0.01)
    assert all(publisher._matching.get(n) for n in names), f"no subscriber matched {names} within 30 s"


def test_a_hand_made_record_with_grip_goes_out_on_its_keys():
    """The record's bytes are its decision-log line; the grip object on .../grip with cycle and t;
    a contact event for the first record and at each change of the decision."""
    from fusion_center.service.records import dumps
    from fusion_center.service.zenoh_publisher import ZenohPublisher

    port, = _ports(1)
    records = [{"cycle": 0, "t": 0.0, "decision": "H0", "p_h1": 0.01, "present_count": 0, "present_nodes": [],
                "area": 0.0, "contact_type": None},
               {"cycle": 1, "t": 0.01, "decision": "H1", "p_h1": 0.99, "present_count": 2, "present_nodes": [3, 4],
                "area": 1.5e-5, "contact_type": "edge", "grip": GRIP},
               {"cycle": 2, "t": 0.02, "decision": "H1", "p_h1": 0.98, "present_count": 2, "present_nodes": [3, 4],
                "area": 1.5e-5, "contact_type": "edge", "grip": {**GRIP, "slip": True}},
               {"cycle": 3, "t": 0.03, "decision": "H0", "p_h1": 0.02, "present_count": 0, "present_nodes": [],
                "area": 0.0, "contact_type": None}]
    with ZenohPublisher("grasp/scene*1", listen=[f"tcp/127.0.0.1:{port}"]) as pub:
        assert pub.keys == {"record": "taxel/grasp_scene_1/record", "grip": "taxel/grasp_scene_1/grip",
                            "contact": "taxel/grasp_scene_1/contact"}
        peer = zenoh_peer(connect=port)
        try:
            sub, got, wait = _subscribe(peer, "taxel/grasp_scene_1/*")
            _connected(pub, "record", "grip", "contact")
            # a record a turn, as cycles come: a cycle's puts (record, grip, contact) go out
            # back to back and all arrive - with Zenoh's default of two data batches a link, the
            # third was dropped when its transmit thread had not run within 1 ms (2 of 6 runs
            # with the CPU busy: zenoh_config.TX_QUEUE_DATA); flooding the queue is the stalled
            # subscriber's test below
            for r, messages_so_far in zip(records, (2, 5, 7, 9)):  # record (+ grip) (+ contact event)
                pub(r)
                wait(messages_so_far)
            pub({"cycle": 4, "t": math.nan, "decision": "H0"})  # JSON cannot hold it: counted, not raised
        finally:
            peer.close()
    assert (pub.records, pub.grips, pub.contacts, pub.failed) == (4, 2, 3, 1)
    by_key = {}
    for key, payload, encoding in got:
        by_key.setdefault(key.rsplit("/", 1)[1], []).append(payload)
        assert encoding == "application/json"
    assert by_key["record"] == [dumps(r).encode() for r in records]  # the decision log's bytes
    grips = [json.loads(p) for p in by_key["grip"]]
    assert grips == [{"cycle": 1, "t": 0.01, **GRIP}, {"cycle": 2, "t": 0.02, **GRIP, "slip": True}]
    events = [json.loads(p) for p in by_key["contact"]]
    assert [(e["cycle"], e["event"], e["previous"], e["decision"]) for e in events] == [
        (0, "change", None, "H0"), (1, "onset", "H0", "H1"), (3, "release", "H1", "H0")]
    assert events[1]["present_nodes"] == [3, 4] and events[1]["contact_type"] == "edge"


def test_a_stalled_subscriber_never_holds_the_publishing_thread():
    """A subscriber whose callback blocks: its transport backs up, and the publisher's puts are
    dropped (CongestionControl.DROP, wait_before_drop 0), not waited for - every put returns
    while the subscriber is still stalled."""
    import zenoh

    from fusion_center.service.zenoh_publisher import ZenohPublisher

    port, = _ports(1)
    release = threading.Event()
    received = []
    puts_done_while_stalled = []
    with ZenohPublisher("stall", listen=[f"tcp/127.0.0.1:{port}"]) as pub:
        assert pub._publishers["record"].congestion_control == zenoh.CongestionControl.DROP
        peer = zenoh_peer(connect=port)
        try:
            def on_sample(sample):
                received.append(1)
                release.wait(120)  # stalls Zenoh's receive path of this session (a safety limit)

            peer.declare_subscriber("taxel/stall/record", on_sample)
            _connected(pub, "record")
            big = {"cycle": 0, "decision": "H0", "present_nodes": list(range(6000))}
            for k in range(1500):  # ~50 MB: far beyond the queues and socket buffers
                pub({**big, "cycle": k})
            puts_done_while_stalled.append(not release.is_set())
        finally:
            release.set()
            peer.close()
    assert puts_done_while_stalled == [True]
    assert pub.records == 1500 and pub.failed == 0


def test_settings_come_from_flags_then_environment_then_the_file_loopback_by_default(tmp_path, monkeypatch):
    from fusion_center.service.zenoh_config import DEFAULT_LISTEN, resolve

    monkeypatch.delenv("FUSION_CENTER_ZENOH_CONFIG", raising=False)
    monkeypatch.delenv("FUSION_CENTER_ZENOH_LISTEN", raising=False)
    monkeypatch.delenv("FUSION_CENTER_ZENOH_CONNECT", raising=False)
    monkeypatch.delenv("FUSION_CENTER_ZENOH_MODE", raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))

    def get(config, key):
        return json.loads(config.get_json(key))

    config, _ = resolve()  # nothing given: loopback
    assert get(config, "listen/endpoints") == [DEFAULT_LISTEN] == ["tcp/127.0.0.1:7447"]
    assert get(config, "scouting/multicast/enabled") is False and get(config, "mode") == "peer"
    assert get(config, "connect/endpoints") == []
    # the default file, then FUSION_CENTER_ZENOH_CONFIG, then --zenoh-config
    default = tmp_path / "xdg" / "taxel-can" / "zenoh.json5"
    default.parent.mkdir(parents=True)
    default.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:7001"] }, scouting: { multicast: { enabled: true } } }')
    config, _ = resolve()
    assert get(config, "listen/endpoints") == ["tcp/127.0.0.1:7001"]
    assert get(config, "scouting/multicast/enabled") is True  # the user's file says so
    env_file = tmp_path / "env.json5"
    env_file.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7002"] } }')
    monkeypatch.setenv("FUSION_CENTER_ZENOH_CONFIG", str(env_file))
    config, _ = resolve()
    assert get(config, "mode") == "client" and get(config, "connect/endpoints") == ["tcp/127.0.0.1:7002"]
    assert get(config, "listen/endpoints") == [DEFAULT_LISTEN]  # that file leaves it: loopback
    assert get(config, "scouting/multicast/enabled") is False
    flag_file = tmp_path / "flag.json5"
    flag_file.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:7003"] } }')
    config, _ = resolve(config_flag=str(flag_file))
    assert get(config, "listen/endpoints") == ["tcp/127.0.0.1:7003"] and get(config, "mode") == "peer"
    # the environment's settings over the file's, the flags' over both
    monkeypatch.setenv("FUSION_CENTER_ZENOH_LISTEN", "127.0.0.1:7004,tcp/127.0.0.1:7005")
    monkeypatch.setenv("FUSION_CENTER_ZENOH_MODE", "peer")
    config, _ = resolve(config_flag=str(flag_file))
    assert get(config, "listen/endpoints") == ["tcp/127.0.0.1:7004", "tcp/127.0.0.1:7005"]
    assert get(config, "mode") == "peer"
    config, _ = resolve(config_flag=str(flag_file), listen=["tcp/127.0.0.1:7006"], connect=["127.0.0.1:7007"],
                        mode="client")
    assert get(config, "listen/endpoints") == ["tcp/127.0.0.1:7006"]
    assert get(config, "connect/endpoints") == ["tcp/127.0.0.1:7007"] and get(config, "mode") == "client"
    for kwargs, needle in (({"listen": ["udp/x"]}, "--zenoh-listen 'udp/x'"), ({"mode": "router"}, "--zenoh-mode"),
                           ({"connect": ["host:99999"]}, "--zenoh-connect")):
        with pytest.raises(UsageError, match=needle):
            resolve(**kwargs)
    monkeypatch.setenv("FUSION_CENTER_ZENOH_MODE", "router")
    with pytest.raises(UsageError, match="FUSION_CENTER_ZENOH_MODE 'router'"):
        resolve()



@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RUSAGE_THREAD (a thread's page faults) is Linux's")
def test_a_links_part_sized_put_never_fills_a_shared_memory_pool(monkeypatch, tmp_path):
    """Zenoh 1.x's shared-memory transport optimisation (on by default) made one early put of
    a session's first >3 KiB samples touch ~10 MiB of its pool in the caller's thread (2,660
    page faults, 8-11 ms of CPU: the assemblers' early stall, docs/robotics.md); the link's
    and the publication's sessions switch it off. Counted in page faults, not time."""
    import os
    import resource
    import time

    import zenoh
    from fusion_center.service.assembler_link import assembler_config, fuser_config
    from fusion_center.service.zenoh_config import SHM_OPTIMIZATION, open_session, resolve

    for name in ("FUSION_CENTER_ZENOH_CONFIG", "FUSION_CENTER_ZENOH_LISTEN", "FUSION_CENTER_ZENOH_CONNECT",
                 "FUSION_CENTER_ZENOH_MODE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    config, _ = resolve()
    assert json.loads(config.get_json(SHM_OPTIMIZATION)) is False
    port, = _ports(1)
    fuser_cfg, what = fuser_config(f"tcp/127.0.0.1:{port}", None)
    fuser = open_session(fuser_cfg, what)
    assembler_cfg, what = assembler_config(f"tcp/127.0.0.1:{port}", None)
    assembler = open_session(assembler_cfg, what)
    try:
        sub, got, wait = _subscribe(fuser, "t/part")
        pub = assembler.declare_publisher("t/part", express=True, congestion_control=zenoh.CongestionControl.BLOCK)
        end = time.monotonic() + 30
        while not pub.matching_status.matching and time.monotonic() < end:
            time.sleep(0.01)
        payload = os.urandom(15_000)  # a skin4096 part's size
        faults = []
        for _ in range(30):  # paced as parts are: the pool was filled by the 3rd to the 12th
            time.sleep(0.01)
            before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
            pub.put(payload)
            faults.append(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before)
        assert len(wait(30)) == 30
        assert max(faults) < 500, f"a put touched {max(faults)} new pages (4 KiB each): {faults}"
    finally:
        assembler.close()
        fuser.close()

def _cli(*argv, env=None):
    import os

    return subprocess.run([sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())",
                           *argv], cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, **(env or {})})


def test_a_bad_config_or_a_taken_port_is_one_line_exit_2(tmp_path, monkeypatch, capsys):
    from fusion_center.cli import main as cli_main

    bad = tmp_path / "bad.json5"
    bad.write_text("{ listen: { endpoints: 5 } }")
    port, = _ports(1)
    peer = zenoh_peer(listen=port)  # takes the port
    try:
        cases = [
            (["demo", "--cycles", "2", "--no-live", "--zenoh", "--zenoh-config", str(bad)], {},
             f"zenoh config file '{bad}' (from --zenoh-config)"),
            (["demo", "--cycles", "2", "--no-live", "--zenoh"], {"FUSION_CENTER_ZENOH_CONFIG": str(bad)},
             f"zenoh config file '{bad}' (from FUSION_CENTER_ZENOH_CONFIG)"),
            (["demo", "--cycles", "2", "--no-live", "--zenoh", "--zenoh-config", str(tmp_path / "none.json5")], {},
             "none.json5"),
            (["demo", "--cycles", "2", "--no-live", "--zenoh", "--zenoh-listen", f"tcp/127.0.0.1:{port}"], {},
             f"cannot open a Zenoh session (listen [\"tcp/127.0.0.1:{port}\"]"),
            (["demo", "--cycles", "2", "--no-live", "--zenoh-listen", "tcp/127.0.0.1:7447"], {}, "only with --zenoh"),
        ]
        for argv, env, needle in cases:
            monkeypatch.delenv("FUSION_CENTER_ZENOH_CONFIG", raising=False)
            for name, value in env.items():
                monkeypatch.setenv(name, value)
            assert cli_main(argv) == 2, argv
            err = capsys.readouterr().err.strip()
            assert len(err.splitlines()) == 1 and needle in err, (argv, err)
    finally:
        peer.close()


def test_the_subscriber_example_receives_a_short_demo(tmp_path):
    """docs/examples/zenoh_subscriber.py listening, `demo --zenoh` connecting to it: every record
    it prints raw is the decision log's line."""
    sub_port, own_port = _ports(2)
    jsonl = tmp_path / "demo.jsonl"
    sub = subprocess.Popen([sys.executable, str(ROOT / "docs" / "examples" / "zenoh_subscriber.py"), "--listen",
                            f"tcp/127.0.0.1:{sub_port}", "--scene", "matrix57", "--count", "20", "--raw",
                            "--timeout", "120"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert "subscribed to taxel/matrix57/*" in sub.stderr.readline()
        done = _cli("demo", "--cycles", "20", "--no-live", "--json-lines", str(jsonl), "--zenoh",
                    "--zenoh-connect", f"tcp/127.0.0.1:{sub_port}", "--zenoh-listen", f"tcp/127.0.0.1:{own_port}")
        assert done.returncode == 0, done.stderr
        zline = [line for line in done.stdout.splitlines() if line.startswith("zenoh:")]
        assert zline and "20 records on taxel/matrix57/record" in zline[0] and "0 failed" in zline[0], done.stdout
        out, err = sub.communicate(timeout=120)
    finally:
        if sub.poll() is None:
            sub.kill()
            sub.communicate()
    assert sub.returncode == 0, err
    assert out.splitlines() == jsonl.read_text().splitlines()


def test_with_no_subscriber_nothing_is_serialised_or_put():
    """Zenoh's matching status per key: no subscriber, no work (counted as unmatched); one that
    subscribes later gets the records from then on."""
    from fusion_center.service.zenoh_publisher import ZenohPublisher

    port, = _ports(1)
    with ZenohPublisher("lonely", listen=[f"tcp/127.0.0.1:{port}"]) as pub:
        for k in range(5):
            pub({"cycle": k, "t": k * 0.01, "decision": "H0", "grip": GRIP})
        assert (pub.records, pub.grips, pub.contacts, pub.unmatched, pub.failed) == (0, 0, 0, 5, 0)
        peer = zenoh_peer(connect=port)
        try:
            sub, got, wait = _subscribe(peer, "taxel/lonely/record")
            _connected(pub, "record")
            pub({"cycle": 5, "t": 0.05, "decision": "H1", "grip": GRIP})
            assert [json.loads(p)["cycle"] for _, p, _ in wait(1)] == [5]
        finally:
            peer.close()
    assert (pub.records, pub.grips, pub.unmatched) == (1, 0, 5)  # .../grip and .../contact: nobody


def test_a_logged_record_is_published_as_the_logs_line_serialised_once(tmp_path, monkeypatch):
    """With a decision log and the publication on, a record's JSON is made once: the publisher
    puts the line the log just wrote (the same bytes); a record the log did not write - another
    dict, even an equal one - is serialised by the publisher itself."""
    from fusion_center.service import records as records_mod
    from fusion_center.service.records import RecordWriter
    from fusion_center.service.zenoh_publisher import ZenohPublisher

    made = []
    dumpb = records_mod.dumpb

    def counting(record):
        made.append(record.get("cycle"))
        return dumpb(record)

    monkeypatch.setattr(records_mod, "dumpb", counting)
    port, = _ports(1)
    log = tmp_path / "run.jsonl"
    with ZenohPublisher("logged", listen=[f"tcp/127.0.0.1:{port}"]) as pub:
        peer = zenoh_peer(connect=port)
        try:
            sub, got, wait = _subscribe(peer, "taxel/logged/record")
            _connected(pub, "record")
            with RecordWriter(log) as writer:
                for k in range(3):
                    record = {"cycle": k, "t": k * 0.01, "decision": "H0", "u_g": -1.5 - k}
                    writer.write(record)
                    pub(record)
            pub({"cycle": 2, "t": 0.02, "decision": "H0", "u_g": -3.5})  # equal to the last, not it
            payloads = [p for _, p, _ in wait(4)]
        finally:
            peer.close()
    lines = log.read_bytes().splitlines()
    assert payloads == lines + [lines[-1]]
    assert made == [0, 1, 2, 2]  # three by the log, one by the publisher (the unlogged dict)


def test_the_program_ends_without_finalization_once_zenoh_ran_and_only_then():
    """Zenoh's Rust threads can call into a finalizing interpreter and abort the process
    (SIGABRT, 'FATAL: exception not rethrown', after a complete run of an assembler): run as the
    program after a command that used Zenoh, ``main`` ends the process itself - its output
    flushed, the exit status kept, no finalization (atexit handlers do not run); without Zenoh, or
    called with arguments (in a process that goes on), it returns as always."""
    code = ("import atexit, sys\n"
            "atexit.register(lambda: print('FINALIZED', flush=True))\n"
            "{imports}"
            "from fusion_center.cli import main\n"
            "sys.argv = ['fusion-center', 'scenes']\n"
            "print('status', main(), flush=True)\n"
            "print('after main', flush=True)\n")
    with_zenoh = subprocess.run([sys.executable, "-c", code.format(imports="import zenoh\n")], cwd=ROOT,
                                capture_output=True, text=True, timeout=120)
    assert with_zenoh.returncode == 0, with_zenoh.stderr
    assert "matrix57" in with_zenoh.stdout                   # the command's output, flushed
    assert "after main" not in with_zenoh.stdout and "FINALIZED" not in with_zenoh.stdout
    plain = subprocess.run([sys.executable, "-c", code.format(imports="")], cwd=ROOT, capture_output=True, text=True,
                           timeout=120)
    assert plain.returncode == 0 and "status 0" in plain.stdout and "FINALIZED" in plain.stdout
    import zenoh  # noqa: F401 - in this process too: main with arguments returns
    from fusion_center.cli import main

    assert main(["scenes"]) == 0
