"""``--foxglove [HOST:]PORT``: a live Foxglove WebSocket server with the MCAP file's channels
(the SDK's ``foxglove.start_server``, subprotocol ``foxglove.sdk.v1``; its own Rust threads).

Loopback (127.0.0.1) unless the user names a host. The cycle never waits for a viewer: the
record callback only appends to a queue (:class:`fusion_center.robotics.outputs.RoboticsOutputs`),
a publisher thread encodes and logs, and ``log`` hands each message to the SDK, which queues it
per client (``message_backlog_size``) and never blocks. Two places lose messages for a viewer:

* in front of the server: when the publisher falls more than :data:`LIVE_BACKLOG` cycles behind
  (a starved process), the oldest cycles are skipped for the live server (never for the MCAP file
  or bag) - counted exactly (``dropped``);
* in the SDK: a client that does not read (a stalled viewer) fills its outbox of
  :data:`CLIENT_BACKLOG` messages, after which the SDK drops that client's oldest messages. The
  SDK (0.30) exposes no count of these; the summary says how many clients connected and that
  their losses are not counted by the SDK (docs/robotics.md).
"""

from __future__ import annotations

import threading

from taxel_net.errors import UsageError
from .mcap_out import FoxgloveSink

DEFAULT_HOST = "127.0.0.1"
LIVE_BACKLOG = 256      # cycles the publisher may be behind before the live server skips the oldest
CLIENT_BACKLOG = 1024   # the SDK's per-client outbox (messages)


def parse_listen(text: str, option: str = "--foxglove") -> tuple[str, int]:
    """``PORT`` or ``HOST:PORT`` (``[v6]:PORT``): loopback unless a host is named; port 0..65535
    (0: any free port)."""
    value = str(text).strip()
    host, sep, port = value.rpartition(":")
    if not sep:
        host, port = DEFAULT_HOST, value
    host = host.strip("[]") or DEFAULT_HOST
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not 0 <= number <= 65535:
        raise UsageError(f"{option} {text!r}: expected PORT or HOST:PORT with a port in 0..65535 "
                         "(e.g. 8765 or 127.0.0.1:8765)")
    return host, number


class _Listener:
    """Counts clients and subscriptions (the SDK calls it from its own threads)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.clients: set[int] = set()
        self.active: set[tuple[int, int]] = set()  # (client, channel) subscribed now
        self.subscribed = threading.Event()         # set while any subscription is active

    def on_subscribe(self, client, channel) -> None:
        with self.lock:
            self.clients.add(client.id)
            self.active.add((client.id, channel.id))
            self.subscribed.set()

    def on_unsubscribe(self, client, channel) -> None:  # also when a client disconnects
        with self.lock:
            self.active.discard((client.id, channel.id))
            if not self.active:
                self.subscribed.clear()


class LiveServer:
    """The WebSocket server and its channels (see the module docstring)."""

    def __init__(self, host: str, port: int, *, known=(), name: str = "taxel-can", option: str = "--foxglove"):
        import foxglove

        self.context = foxglove.Context()
        self.listener = _Listener()
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context,
                                                server_listener=self.listener,
                                                message_backlog_size=CLIENT_BACKLOG)
        except Exception as exc:  # noqa: BLE001 - address in use, bad host: the SDK's RuntimeError
            raise UsageError(f"{option} {host}:{port}: cannot listen: {' '.join(str(exc).split())}") from None
        self.host = host
        self.port = self.server.port
        self.sink = FoxgloveSink(self.context, known)
        self.cycles = 0        # cycles handed to the SDK
        self.dropped = 0       # cycles skipped in front of the server (publisher behind)
        self.unwatched = 0     # cycles nobody was subscribed to (not encoded for the server)

    @property
    def watched(self) -> bool:
        """Whether any client is subscribed to any channel now (nobody watching: nothing to encode)."""
        return bool(self.listener.active)

    def log(self, t: int, messages) -> None:
        self.sink.log(t, messages)
        self.cycles += 1

    def stats(self) -> dict:
        with self.listener.lock:
            clients = len(self.listener.clients)
        return {"address": f"{self.host}:{self.port}", "cycles": self.cycles, "messages": self.sink.messages,
                "dropped_cycles": self.dropped, "clients": clients, "unwatched_cycles": self.unwatched}

    def close(self) -> None:
        self.server.stop()
