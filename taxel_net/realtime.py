"""Real-time scheduling of a process's time-critical threads, opt-in (``--rt-priority N``).

ros2_control's controller manager and the usual CANopen master stacks run their cyclic thread
under ``SCHED_FIFO`` when the host allows it and at the normal priority otherwise, with one line
saying so. The same here: :func:`fifo_threads` puts the given threads (the centre's receive
thread, its SYNC producer and its heartbeat) under ``SCHED_FIFO`` at priority N (1-99, Linux's range) with
``SCHED_RESET_ON_FORK`` (a process or thread they start gets the normal policy back). Such a
thread, once woken, runs before every ``SCHED_OTHER`` task of the host - the node twins, other
jobs - instead of taking its turn with them: what matters on a loaded host, where a wake-up
otherwise waits for a core (docs/grip-control.md, "2026-11-30 (stop 31)"). The kernel's RT
throttling (``/proc/sys/kernel/sched_rt_runtime_us``, 0.95 s a second by default) still
bounds what such threads can take.

Not permitted (``EPERM``: neither ``CAP_SYS_NICE`` - root usually has it - nor an
``RLIMIT_RTPRIO`` of at least N - ``ulimit -r``) or not available (no ``sched_setscheduler`` on the platform): one
warning line, once per process, and the threads keep their normal priority - never an error.
Only the threads named are changed; the interpreter lock is still shared with the process's
other threads.
"""

from __future__ import annotations

import logging
import os
import threading
from typing import Iterable

logger = logging.getLogger("taxel_net.realtime")

PRIORITY_MIN, PRIORITY_MAX = 1, 99  # SCHED_FIFO's range on Linux (sched_get_priority_min/max)

_warned = False


def check_priority(value, option: str = "--rt-priority") -> int:
    """``value`` as an int in 1..99, else ValueError with one line naming ``option``."""
    try:
        if isinstance(value, bool):  # int(True) == 1: not a priority
            raise ValueError
        priority = int(value)
        if priority != float(value):
            raise ValueError
    except (TypeError, ValueError, OverflowError):  # OverflowError: int(inf)
        raise ValueError(f"{option} {value!r}: not an integer (allowed: {PRIORITY_MIN}-{PRIORITY_MAX}, "
                         "SCHED_FIFO's priorities)") from None
    if not PRIORITY_MIN <= priority <= PRIORITY_MAX:
        raise ValueError(f"{option} {priority}: out of range (allowed: {PRIORITY_MIN}-{PRIORITY_MAX}, "
                         "SCHED_FIFO's priorities)")
    return priority


def _warn_once(message: str, *args) -> None:
    global _warned
    if not _warned:
        _warned = True
        logger.warning(message, *args)


def fifo_threads(threads: Iterable[threading.Thread], priority: int | None) -> list[str]:
    """Each running thread of ``threads`` under SCHED_FIFO at ``priority`` (nothing when None);
    returns the names of those changed. A refusal or a missing ``sched_setscheduler``: one
    warning line per process (module docstring), the rest left as they are."""
    if priority is None:
        return []
    priority = check_priority(priority)
    setter = getattr(os, "sched_setscheduler", None)
    if setter is None or not hasattr(os, "SCHED_FIFO"):
        _warn_once("--rt-priority %d: SCHED_FIFO is not available on this platform; normal priority", priority)
        return []
    policy = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
    done = []
    for thread in threads:
        tid = getattr(thread, "native_id", None)
        if tid is None or not thread.is_alive():
            continue
        try:
            setter(tid, policy, os.sched_param(priority))
        except PermissionError:
            _warn_once("--rt-priority %d: SCHED_FIFO not permitted (EPERM: needs CAP_SYS_NICE, which root "
                       "usually has, or `ulimit -r` >= %d); thread %r and the others keep the normal priority",
                       priority, priority, thread.name)
            return done
        except OSError as exc:  # ESRCH: the thread ended meanwhile; EINVAL: a kernel without RT
            _warn_once("--rt-priority %d: SCHED_FIFO for thread %r refused (%s); normal priority",
                       priority, thread.name, exc.strerror or exc)
            continue
        done.append(thread.name)
    return done


def policy_of(thread: threading.Thread) -> tuple[int, int] | None:
    """(policy without flags, priority) of a running thread, None where it cannot be read."""
    tid = getattr(thread, "native_id", None)
    if tid is None or not hasattr(os, "sched_getscheduler"):
        return None
    try:
        policy = os.sched_getscheduler(tid) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)
        return policy, os.sched_getparam(tid).sched_priority
    except OSError:
        return None
