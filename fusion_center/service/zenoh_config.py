"""Zenoh sessions of the project (issue 24): the record publication (``--zenoh``,
:mod:`.zenoh_publisher`) and the assembler link (``run --assemblers`` / ``assemble --fuser``,
:mod:`.assembler_link`) - their configuration, resolved as python-can resolves a bus.

**Precedence** (docs/robotics.md, *Zenoh*), for each setting: the command line's flags
(``--zenoh-listen``, ``--zenoh-connect``, ``--zenoh-mode``; for the link ``--assemblers`` /
``--fuser``), then the environment (``FUSION_CENTER_ZENOH_LISTEN``, ``..._CONNECT``,
``..._MODE``), then the Zenoh configuration file - ``--zenoh-config FILE``, else
``$FUSION_CENTER_ZENOH_CONFIG``, else ``$XDG_CONFIG_HOME/taxel-can/zenoh.json5`` (default
``~/.config/taxel-can/zenoh.json5``) when it exists: any file ``zenoh.Config.from_file``
reads (JSON5 or YAML, Zenoh's own keys: TLS, access control, user/password authentication,
routers to connect to) - then the project's defaults.

**The project's defaults are loopback**, unlike Zenoh's (a peer scouts by UDP multicast and
listens on every interface): multicast scouting off, the publication's session listening on
``tcp/127.0.0.1:7447`` only, the link's only where ``--assemblers`` says. A setting the user's
file or environment gives (``scouting/multicast/enabled``, ``listen/endpoints``) is taken as
given - that is how a user opens the sessions to other hosts.

A file Zenoh cannot read, a bad endpoint or a session that cannot open (the port taken) is
one :class:`~taxel_net.errors.UsageError` line naming the file or flag (exit 2).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

from taxel_net.errors import UsageError

ENV_CONFIG = "FUSION_CENTER_ZENOH_CONFIG"
ENV_LISTEN = "FUSION_CENTER_ZENOH_LISTEN"
ENV_CONNECT = "FUSION_CENTER_ZENOH_CONNECT"
ENV_MODE = "FUSION_CENTER_ZENOH_MODE"
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"  # the publication's session: Zenoh's port, loopback only
MODES = ("peer", "client")
# a sample larger than this is not reassembled by a session of ours (Zenoh's default: 1 GiB)
MAX_MESSAGE = 16 * 1024 * 1024
# batches a link may hold for data priority before a DROP put is dropped (Zenoh's default: 2).
# An express put is a batch of its own, and a cycle puts up to three (record, grip, contact):
# with two slots the third was dropped whenever Zenoh's transmit thread had not run within
# ``wait_before_drop`` (1 ms) - on a busy host, one cycle's contact event in a few runs. 16
# slots hold five cycles' puts; a stalled subscriber still fills them and loses samples, not
# cycles. Batches are allocated as used (lazy), at most 64 KiB each.
TX_QUEUE_DATA = 16
# Zenoh 1.x carries a sample above 3 KiB to a peer on the same host through its shared-memory
# pool (``transport/shared_memory/transport_optimization``, on by default). Measured here
# (bench/zenoh_floor.py, 15 kB at 100 Hz, the link's settings): the first such put of a
# session spends 8-11 ms of the caller's CPU touching ~10 MiB of the pool (2,661 page faults
# in the put: the assemblers' early stall, docs/robotics.md), and every later one costs the
# sender more than the socket does (440 against 320-360 us a message). Off unless the user's
# configuration says otherwise.
SHM_OPTIMIZATION = "transport/shared_memory/transport_optimization/enabled"

_ENDPOINT = re.compile(r"[a-z0-9]+/[^\s#?]+:\d{1,5}([?#].*)?")
_SEGMENT_BAD = re.compile(r"[^A-Za-z0-9_.-]")


def default_config_file() -> Path:
    base = os.environ.get("XDG_CONFIG_HOME", "")
    root = Path(base) if base and os.path.isabs(base) else Path.home() / ".config"
    return root / "taxel-can" / "zenoh.json5"


def zerror_text(exc: BaseException) -> str:
    """One line of a ``zenoh.ZError`` (Zenoh's source locations left out)."""
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?", "", str(exc))
    return " ".join(text.split())[:400]


def key_segment(name: str) -> str:
    """A scene name as one chunk of a key expression (``*``, ``$``, ``#``, ``?``, ``/`` and
    other characters outside ``A-Za-z0-9_.-`` become ``_``; an empty name ``_``)."""
    return _SEGMENT_BAD.sub("_", str(name)) or "_"


def endpoint(text: str, flag: str) -> str:
    """``HOST:PORT`` -> ``tcp/HOST:PORT``; a Zenoh locator ``PROTO/HOST:PORT`` (``tls/...``,
    ``quic/...``, ``tcp/[::1]:7447``) as given; else :class:`UsageError` naming ``flag``."""
    text = str(text).strip()
    if "/" not in text:
        text = f"tcp/{text}"
    port = text.split("?")[0].split("#")[0].rpartition(":")[2]
    if not _ENDPOINT.fullmatch(text) or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise UsageError(f"{flag} {text!r}: expected a Zenoh endpoint PROTO/HOST:PORT with a port in 1..65535 "
                         "(e.g. tcp/127.0.0.1:7447, tls/robot.local:7447) or HOST:PORT")
    return text


def endpoint_host(text: str) -> str:
    """The host of an endpoint (``tcp/[::1]:7447`` -> ``::1``)."""
    host = text.split("/", 1)[1].split("?")[0].split("#")[0].rpartition(":")[0]
    return host[1:-1] if host.startswith("[") and host.endswith("]") else host


def _endpoints(values, flag: str) -> list[str]:
    out: list[str] = []
    for value in values:
        out.extend(endpoint(v, flag) for v in str(value).split(",") if v.strip())
    return out


def config_file(flag_value: str | None) -> tuple[Path | None, str]:
    """The Zenoh configuration file and where its name came from (flag, environment, the
    default place when a file is there; None: none)."""
    if flag_value:
        return Path(flag_value), "--zenoh-config"
    env = os.environ.get(ENV_CONFIG, "")
    if env:
        return Path(env), ENV_CONFIG
    default = default_config_file()
    if default.is_file():
        return default, str(default)
    return None, ""


def _load(path: Path | None, source: str):
    import zenoh

    if path is None:
        return zenoh.Config()
    try:
        return zenoh.Config.from_file(str(path))
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError: unreadable, not JSON5/YAML, a bad key
        raise UsageError(f"zenoh config file {str(path)!r} (from {source}): {zerror_text(exc)}") from None


def _set(config, key: str, value, what: str) -> None:
    try:
        config.insert_json5(key, json.dumps(value))
    except Exception as exc:  # noqa: BLE001
        raise UsageError(f"{what}: {key} = {json.dumps(value)}: {zerror_text(exc)}") from None


def _is_default(config, key: str) -> bool:
    import zenoh

    return config.get_json(key) == zenoh.Config().get_json(key)


def resolve(*, config_flag: str | None = None, listen=None, connect=None, mode: str | None = None,
            default_listen: list[str] | None = None, force_listen: list[str] | None = None,
            force_connect: list[str] | None = None, purpose: str = "--zenoh"):
    """A ``zenoh.Config`` by the module's precedence. ``listen`` / ``connect``: the flags'
    endpoints (lists, comma-separated items); ``default_listen``: where to listen when nothing
    says (None: :data:`DEFAULT_LISTEN`); ``force_listen`` / ``force_connect``: the link's own
    endpoints (``--assemblers`` / ``--fuser``), whatever else says. Returns (config, a short
    description for messages)."""
    path, source = config_file(config_flag)
    config = _load(path, source)
    what = f"zenoh config file {str(path)!r}" if path is not None else purpose
    if mode is None:
        mode = os.environ.get(ENV_MODE) or None
        mode_flag = ENV_MODE
    else:
        mode_flag = "--zenoh-mode"
    if mode is not None:
        if mode not in MODES:
            raise UsageError(f"{mode_flag} {mode!r}: expected one of {', '.join(MODES)}")
        _set(config, "mode", mode, mode_flag)
    elif config.get_json("mode") in ("null", ""):
        _set(config, "mode", "peer", what)
    # loopback unless the user says otherwise
    if config.get_json("scouting/multicast/enabled") in ("null", ""):
        _set(config, "scouting/multicast/enabled", False, what)
    listen_eps = _endpoints(listen or [], "--zenoh-listen") or _endpoints(
        [os.environ[ENV_LISTEN]] if os.environ.get(ENV_LISTEN) else [], ENV_LISTEN)
    connect_eps = _endpoints(connect or [], "--zenoh-connect") or _endpoints(
        [os.environ[ENV_CONNECT]] if os.environ.get(ENV_CONNECT) else [], ENV_CONNECT)
    if force_listen is not None:
        listen_eps = force_listen
    if force_connect is not None:  # the link's endpoint first, then the others (a router in the user's file)
        given = [] if _is_default(config, "connect/endpoints") else json.loads(config.get_json("connect/endpoints"))
        given = given if isinstance(given, list) else []
        connect_eps = force_connect + [e for e in connect_eps + given if e not in force_connect]
    if listen_eps or force_listen is not None:
        _set(config, "listen/endpoints", listen_eps, what)
    elif _is_default(config, "listen/endpoints"):
        _set(config, "listen/endpoints", default_listen if default_listen is not None else [DEFAULT_LISTEN], what)
    if connect_eps:
        _set(config, "connect/endpoints", connect_eps, what)
    if _is_default(config, "transport/link/rx/max_message_size"):
        _set(config, "transport/link/rx/max_message_size", MAX_MESSAGE, what)
    if _is_default(config, "transport/link/tx/queue/size/data"):
        _set(config, "transport/link/tx/queue/size/data", TX_QUEUE_DATA, what)
    if _is_default(config, SHM_OPTIMIZATION):
        _set(config, SHM_OPTIMIZATION, False, what)
    return config, what


def open_session(config, what: str):
    """``zenoh.open(config)``; :class:`UsageError` naming ``what`` and the endpoints when it
    cannot open (a port taken, a TLS file missing)."""
    import zenoh

    try:
        return zenoh.open(config)
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError
        listen = config.get_json("listen/endpoints")
        raise UsageError(f"{what}: cannot open a Zenoh session (listen {listen}, connect "
                         f"{config.get_json('connect/endpoints')}): {zerror_text(exc)}") from None


def add_arguments(parser, *, publication: bool = True) -> None:
    """``--zenoh`` (``publication``) and the Zenoh session flags shared by run / demo /
    assemble."""
    if publication:
        parser.add_argument("--zenoh", action="store_true",
                            help="publish every record (and the grip command, contact events) on Zenoh: keys "
                                 "taxel/<scene>/record, .../grip, .../contact (docs/robotics.md); loopback only "
                                 f"unless configured (default listen {DEFAULT_LISTEN}, no multicast scouting); "
                                 "published by the robotics bridge process beside the centre")
        parser.add_argument("--zenoh-listen", action="append", default=None, metavar="ENDPOINT",
                            help=f"the publication's Zenoh listen endpoint(s) (default {DEFAULT_LISTEN}; "
                                 f"or ${ENV_LISTEN}, or the config file)")
        parser.add_argument("--zenoh-connect", action="append", default=None, metavar="ENDPOINT",
                            help=f"Zenoh endpoint(s) to connect to, e.g. a zenohd router (or ${ENV_CONNECT})")
        parser.add_argument("--zenoh-mode", choices=MODES, default=None,
                            help=f"Zenoh mode of the publication's session (default peer; or ${ENV_MODE})")
    parser.add_argument("--zenoh-config", metavar="FILE", default=None,
                        help=f"a Zenoh configuration file (JSON5/YAML: TLS, authentication, routers); default "
                             f"${ENV_CONFIG}, else {default_config_file()} when it exists")
