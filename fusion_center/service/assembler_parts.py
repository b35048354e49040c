"""What assemblers and fuser share (issue 14, "Beyond one host"; :mod:`.assemblers`): the
link's keys (its transport is Zenoh: :mod:`.assembler_link`), channel groups and their sub-scenes,
the scene fingerprint both sides compare, and :class:`CyclePart`, the one message an assembler
sends per closed cycle (on the wire: :mod:`.assembler_wire`).

**Keys.** ``$FUSION_CENTER_AUTHKEY`` when set (the same value on every host and for every user
of the link). Without it only loopback addresses, and the key is the fuser's own: a random key
per run that ``run --assemblers`` writes to :func:`key_file` (mode 0600 in a directory of mode
0700 of the user's, removed at its end) and ``assemble`` reads at every try to connect - so an
assembler of the same user on the same host needs nothing, and another local user's process
cannot join (issue 21; it would take that user's files).
"""

from __future__ import annotations

import dataclasses
import ipaddress
import logging
import os
import secrets
import stat
import tempfile
import threading
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from taxel_net.errors import UsageError
from taxel_net.patches import devices as scene_devices
from taxel_net.scene import Scene

logger = logging.getLogger("fusion_center.service.assemblers")

AUTHKEY_ENV = "FUSION_CENTER_AUTHKEY"
LOG_INTERVAL_S = 10.0  # disconnect / reconnect warnings: at most one of a kind in this time
COB_SYNC = 0x080
NMT_RESETS = (0x81, 0x82)


# ---------------------------------------------------------------------------- keys

def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def authkey_for(host: str, flag: str) -> bytes | None:
    """The shared key ``$FUSION_CENTER_AUTHKEY``; without it None on a loopback address (the
    fuser's per-run key in :func:`key_file`), else :class:`UsageError`."""
    key = os.environ.get(AUTHKEY_ENV, "")
    if key:
        return key.encode()
    if not is_loopback(host):
        raise UsageError(f"{flag} {host!r}: beyond this host the assemblers and the fuser need a shared key: "
                         f"set {AUTHKEY_ENV} (the same value on every host), or use 127.0.0.1")
    return None


def key_dir() -> str:
    """The user's directory of fuser keys: ``$XDG_RUNTIME_DIR/taxel-can`` (else in the temporary
    directory, ``taxel-can-UID``)."""
    runtime = os.environ.get("XDG_RUNTIME_DIR", "")
    if runtime and os.path.isabs(runtime):
        return os.path.join(runtime, "taxel-can")
    return os.path.join(tempfile.gettempdir(), f"taxel-can-{os.geteuid()}")


def key_file(port: int) -> str:
    """Where the fuser listening on loopback port ``port`` keeps its key."""
    return os.path.join(key_dir(), f"fuser-{int(port)}.key")


def _private(st: os.stat_result, path: str, what: str) -> None:
    if st.st_uid != os.geteuid() or st.st_mode & 0o077:
        raise UsageError(f"{what} {path!r} is owned by uid {st.st_uid} with mode {stat.S_IMODE(st.st_mode):04o}: "
                         f"it must be this user's (uid {os.geteuid()}) and closed to others (0700 / 0600); "
                         f"remove it, or set {AUTHKEY_ENV} on both sides")


def _check_key_dir(create: bool) -> str | None:
    path = key_dir()
    if create:
        try:
            os.mkdir(path, 0o700)
        except FileExistsError:
            pass
        except OSError as exc:
            raise UsageError(f"fuser key directory {path!r}: cannot create it ({exc.strerror or exc}); "
                             f"set {AUTHKEY_ENV} on both sides") from None
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    if not stat.S_ISDIR(st.st_mode):
        raise UsageError(f"fuser key directory {path!r} is not a directory; remove it, or set {AUTHKEY_ENV}")
    _private(st, path, "fuser key directory")
    return path


def write_key_file(port: int) -> tuple[bytes, str]:
    """A new random key for the fuser on loopback port ``port``, written (0600) to
    :func:`key_file`: (key, path)."""
    _check_key_dir(create=True)
    key = secrets.token_hex(32).encode()
    path = key_file(port)
    tmp = f"{path}.{os.getpid()}.{secrets.token_hex(4)}"
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        try:
            os.write(fd, key)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise UsageError(f"fuser key file {path!r}: cannot write it ({exc.strerror or exc}); "
                         f"set {AUTHKEY_ENV} on both sides") from None
    return key, path


def read_key_file(port: int) -> bytes | None:
    """The key of this user's fuser on loopback port ``port`` (None: there is none);
    :class:`UsageError` when the file or its directory is not this user's alone."""
    if _check_key_dir(create=False) is None:
        return None
    path = key_file(port)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise UsageError(f"fuser key file {path!r}: cannot read it ({exc.strerror or exc})") from None
    try:
        _private(os.fstat(fd), path, "fuser key file")
        key = os.read(fd, 256).strip()
    finally:
        os.close(fd)
    return key or None


def remove_key_file(path: str, key: bytes) -> None:
    """Remove the fuser's key file if it still holds ``key`` (not a newer fuser's). Never raises."""
    try:
        with open(path, "rb") as f:
            if f.read(256).strip() == key:
                os.unlink(path)
    except OSError:
        pass


def check_serve(channels: Sequence[int], scene: Scene, text: str | None = None) -> list[int]:
    served = sorted(set(int(c) for c in channels))
    n = len(scene.bus.channels)
    if not served or served[0] < 0 or served[-1] >= n:
        shown = text if text is not None else ",".join(map(str, channels))
        raise UsageError(f"--serve {shown!r}: scene {scene.name!r} has channels 0..{n - 1} "
                         f"{list(scene.bus.channels)}: give indices such as 0-{n - 1} or 0,{n - 1}")
    return served


def group_name(channels: Sequence[int]) -> str:
    """``0-3`` / ``0,2,5``: a channel group as ``--serve`` spells it."""
    chans = sorted(channels)
    if chans == list(range(chans[0], chans[-1] + 1)) and len(chans) > 1:
        return f"{chans[0]}-{chans[-1]}"
    return ",".join(map(str, chans))


# ---------------------------------------------------------------------------- the sub-scene

@dataclass(frozen=True)
class GroupLayout:
    """A channel group inside the full scene: its taxels and devices (full-scene indices, in
    the sub-scene's order) and the sub-scene an assembler runs."""

    channels: tuple[int, ...]
    taxels: np.ndarray     # sub taxel j -> scene taxel index
    devices: np.ndarray    # sub device d -> scene device index
    sub: Scene

    @property
    def name(self) -> str:
        return group_name(self.channels)


def group_layout(scene: Scene, channels: Sequence[int]) -> GroupLayout:
    """The scene restricted to ``channels`` (renumbered 0..k-1 in their order): same taxels,
    node-IDs and TPDO COB-IDs (a channel's TPDOs are numbered over its own nodes), and the
    gripper drive where its channel is served."""
    served = tuple(sorted(set(int(c) for c in channels)))
    new = {c: k for k, c in enumerate(served)}
    taxels = [i for i, t in enumerate(scene.taxels) if t.channel in new]
    sub_taxels = tuple(dataclasses.replace(scene.taxels[i], channel=new[scene.taxels[i].channel]) for i in taxels)
    bus = dataclasses.replace(scene.bus, channels=tuple(scene.bus.channels[c] for c in served))
    drive = scene.gripper  # the gripper drive goes with its channel (renumbered), else it is not this group's
    if drive is not None:
        drive = dataclasses.replace(drive, channel=new[drive.channel]) if drive.channel in new else None
    sub = dataclasses.replace(scene, taxels=sub_taxels, bus=bus, faults=(), gripper=drive)
    full_index = {(d.channel, d.node_id): k for k, d in enumerate(scene_devices(scene))}
    devs = [full_index[(served[d.channel], d.node_id)] for d in scene_devices(sub)]
    return GroupLayout(served, np.array(taxels, dtype=np.intp), np.array(devs, dtype=np.intp), sub)


def scene_fingerprint(scene: Scene) -> dict:
    """What an assembler and the fuser must agree on (checked at the hello)."""
    return {"scene": scene.name, "n": scene.n, "channels": len(scene.bus.channels), "mode": scene.bus.mode,
            "patch_nodes": bool(scene.bus.patch_nodes), "sync_counter": int(scene.bus.sync_counter),
            "fd": bool(scene.bus.fd)}


# ---------------------------------------------------------------------------- the part

@dataclass
class CyclePart:
    """One closed cycle of one channel group, as sent to the fuser (sub-scene order)."""

    channels: tuple[int, ...]
    number: int                 # the assembler's cycle number (SYNCs since the master's reset)
    sync_counter: int | None
    closed_by: str
    closed_after_us: int        # SYNC -> closing event (the assembler's stream time)
    decisions: np.ndarray       # int8 per taxel of the group
    readings: np.ndarray | None  # float64 (None: none received - decision mode)
    received: np.ndarray
    expected: np.ndarray
    missing: np.ndarray
    states: np.ndarray
    held_decisions: np.ndarray
    held_readings: np.ndarray | None
    late_frames: int = 0
    bad_frames: int = 0
    emcy: tuple = ()            # EmcyEvent with the scene's labels and taxel indices
    emcy_dropped: int = 0
    duplicates: tuple = ()      # scene device indexes
    devices: tuple | None = None  # patch scenes: (expected, missing, states, complete) per device of the group
    sent_at: float = 0.0        # time.time() when sent (assembler -> fuser delay, same-host clocks)
    bootups: tuple = ()         # (scene device index, t_us of its last boot-up) since the previous cycle



# ---------------------------------------------------------------------------- logs

class RateLimitedLog:
    """Warnings of one kind at most every ``interval_s`` (a flapping link never floods the log);
    the ones left out are counted in the next one logged."""

    def __init__(self, log: logging.Logger, interval_s: float = LOG_INTERVAL_S):
        self.log = log
        self.interval_s = float(interval_s)
        self._last: dict[str, float] = {}
        self._left_out: dict[str, int] = {}
        self._lock = threading.Lock()

    def warning(self, kind: str, message: str) -> bool:
        """Log ``message`` (no %-formatting) unless one of ``kind`` went out less than
        ``interval_s`` ago; True when logged."""
        now = time.monotonic()
        with self._lock:
            last = self._last.get(kind)
            if last is not None and now - last < self.interval_s:
                self._left_out[kind] = self._left_out.get(kind, 0) + 1
                return False
            self._last[kind] = now
            left_out = self._left_out.pop(kind, 0)
        if left_out:
            message += f" (+{left_out} like this not logged since the last)"
        self.log.warning("%s", message)
        return True
