"""The assembler link on Zenoh (issue 24): key expressions, the per-run key's message
authentication, and the sessions of the fuser (``run --assemblers ENDPOINT``) and of an
assembler (``assemble --fuser ENDPOINT``). The messages are protocol 3's
(:mod:`.assembler_wire`: msgpack maps, checked, never unpickled); this module says where they
travel and how a receiver knows they come from its run.

**Keys** (``P`` = ``taxel/<scene>/link``, ``<scene>`` the scene's name as one key chunk,
:func:`.zenoh_config.key_segment`; ``<link>`` 32 hex digits an assembler draws at each hello):

==========================  ===========================================================
``P/hello``                 the fuser's queryable: an assembler's ``get`` carries its
                            ``hello``; the reply is ``welcome`` or ``refused``
``P/<link>/part``           the assembler's ``part`` messages (put, reliable, in order)
``P/<link>/fuser``          the fuser's ``bye`` (its end) or ``refused`` (it dropped the
                            link: say hello again) to that assembler
``P/<link>/alive``          the assembler's liveliness token: gone = disconnected
``P/fuser/<run>``           the fuser's liveliness token (``<run>``: 32 hex digits, in
                            its reply to the hello): gone without a bye = reconnect
==========================  ===========================================================

**Authentication** (attachments; the payload is the protocol-3 message unchanged). Every
message carries ``HMAC-SHA256(K, key expression + "\\n" + bound + payload)`` (32 bytes),
``K`` = SHA-256 of the shared key - ``$FUSION_CENTER_AUTHKEY``, else on loopback the fuser's
per-run key file (:mod:`.assembler_parts`). A hello's attachment is ``<link>`` (32 ASCII hex
digits) + its MAC, ``bound`` = ``<link>``; a reply's is ``<run>`` + its MAC, ``bound`` = the
hello's MAC + ``<run>`` (a reply answers that hello only); a part's and a fuser message's is
the MAC alone, ``bound`` empty. A message whose MAC does not verify is never decoded: the
fuser counts it (``refused``: ``key``), an assembler counts it as a bad message. So a stray
peer on the same keys (another run, another user's process on this host, a test tool) runs
nothing, changes no record, and is counted; the key is never sent. Across hosts Zenoh's own
TLS / mutual TLS / user-password authentication and access control (the user's Zenoh
configuration) keep others off the network and the link's traffic unread.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets

from .zenoh_config import key_segment

MAC_BYTES = 32
ID_BYTES = 32   # <link> and <run>: 32 hex digits (ASCII)
_ID = re.compile(rb"[0-9a-f]{32}")


def prefix(scene_name: str) -> str:
    return f"taxel/{key_segment(scene_name)}/link"


def hello_key(p: str) -> str:
    return f"{p}/hello"


def part_key(p: str, link: str) -> str:
    return f"{p}/{link}/part"


def to_link_key(p: str, link: str) -> str:
    return f"{p}/{link}/fuser"


def alive_key(p: str, link: str) -> str:
    return f"{p}/{link}/alive"


def fuser_key(p: str, run: str) -> str:
    return f"{p}/fuser/{run}"


def new_id() -> str:
    return secrets.token_hex(ID_BYTES // 2)


def link_of(key: str) -> str | None:
    """``<link>`` of ``P/<link>/part`` (None: not one)."""
    parts = str(key).rsplit("/", 2)
    if len(parts) != 3 or not _ID.fullmatch(parts[1].encode()):
        return None
    return parts[1]


def mac_key(secret: bytes) -> bytes:
    return hashlib.sha256(secret).digest()


def mac(key: bytes, key_expr: str, payload: bytes, bound: bytes = b"") -> bytes:
    h = hmac.new(key, key_expr.encode() + b"\n", hashlib.sha256)
    h.update(bound)
    h.update(payload)
    return h.digest()


def verify(key: bytes, key_expr: str, payload: bytes, tag: bytes | None, bound: bytes = b"") -> bool:
    return tag is not None and len(tag) == MAC_BYTES and hmac.compare_digest(mac(key, key_expr, payload, bound), tag)


def split_id(attachment: bytes | None) -> tuple[str, bytes] | None:
    """(id, MAC) of a hello's or reply's attachment; None when it is not one."""
    if attachment is None or len(attachment) != ID_BYTES + MAC_BYTES or not _ID.fullmatch(attachment[:ID_BYTES]):
        return None
    return attachment[:ID_BYTES].decode(), attachment[ID_BYTES:]


def as_bytes(zbytes) -> bytes | None:
    """A ``zenoh.ZBytes`` (or None) as bytes."""
    return None if zbytes is None else zbytes.to_bytes()


def fuser_config(listen: str, config_file: str | None):
    """The fuser's link session: listens on ``listen`` only (the user's file may add TLS,
    authentication, routers to connect to)."""
    from .zenoh_config import resolve

    return resolve(config_flag=config_file, force_listen=[listen], purpose="--assemblers")


def assembler_config(fuser: str, config_file: str | None):
    """An assembler's link session: listens nowhere, connects to ``fuser`` (retried from
    0.1 s up to 1 s apart while it is not there)."""
    import json

    from .zenoh_config import resolve

    config, what = resolve(config_flag=config_file, force_listen=[], force_connect=[fuser], purpose="--fuser")
    import zenoh

    if config.get_json("connect/retry") == zenoh.Config().get_json("connect/retry"):
        config.insert_json5("connect/retry", json.dumps({"period_init_ms": 100, "period_max_ms": 1000,
                                                         "period_increase_factor": 2}))
    return config, what
